"""CAN output: the shipped DBC loads in cantools, frames sent on a python-can virtual bus decode to the
inputs within the documented resolution."""
import math
import uuid

import can
import numpy as np
import pytest

from v2xpos.output.can import CanBusError, CanOutput, SlotTable, decode_frames
from v2xpos.output.can_dbc import (DBC_PATH, FRAMES_PER_KINEMATIC_UPDATE, FRAMES_PER_STATUS_UPDATE, N_SLOTS,
                                   generate_dbc, load_dbc)
from v2xpos.types import FixStatus
from v2xpos.wire import FixSide, RelativeResult, TargetStatus


def result(target_id="car-2", **kw) -> RelativeResult:
    base = dict(target_id=target_id, latency_s=0.1034, rel_pos_body_m=np.array([123.4567, -12.3456, 0.789]),
                rel_pos_sd_m=np.full(3, 0.01), rel_vel_body_mps=np.array([-4.567, 0.321, 0.0]),
                rel_acc_body_mps2=np.array([1.234, -0.567, 0.0]), rel_rpy_rad=np.array([0.012, -0.034, 1.234]),
                range_m=124.0739, range_sd_m=0.01, bearing_rad=-0.0997, elevation_rad=0.0,
                longitudinal_m=118.37, lateral_m=-11.46, gap_m=118.9, closing_speed_mps=4.5, ttc_s=26.42)
    base.update(kw)
    return RelativeResult(**base)


@pytest.fixture
def buses():
    channel = f"v2xpos-test-{uuid.uuid4().hex}"
    out = CanOutput(channel=channel, interface="virtual")
    rx = can.Bus(channel=channel, interface="virtual")
    yield out, rx
    out.close()
    rx.shutdown()


def drain(rx) -> list:
    frames = []
    while (f := rx.recv(timeout=0.05)) is not None:
        frames.append(f)
    return frames


def test_shipped_dbc_loads_and_matches_generator():
    db = load_dbc()
    assert DBC_PATH.read_text() == generate_dbc()
    ids = {m.frame_id for m in db.messages}
    assert len(db.messages) == 4 + 9 * N_SLOTS and len(ids) == len(db.messages)
    assert all(m.length == 8 for m in db.messages) and max(ids) < 0x800
    assert db.get_message_by_name("TGT31_POS").frame_id == 0x240 + 31
    assert db.get_message_by_name("TGT63_ID").frame_id == 0x400 + 63


def test_dbc_cycle_times_value_tables_ranges_and_comments():
    db = load_dbc()
    assert db.get_message_by_name("MASTER_STATUS").cycle_time == 100
    assert db.get_message_by_name("TGT05_STATUS").cycle_time == 40
    assert all(m.cycle_time for m in db.messages)
    st = db.get_message_by_name("TGT05_STATUS")
    assert {k: str(v) for k, v in st.get_signal_by_name("T05_Status").choices.items()} == \
        {int(s): s.name.lower() for s in TargetStatus}
    for name in ("T05_MasterFix", "T05_TargetFix"):
        sig = st.get_signal_by_name(name)
        assert str(sig.choices[5]) == "rtk_fixed" and str(sig.choices[4]) == "rtk_float"
        assert (sig.minimum, sig.maximum) == (0, 5)
    assert str(st.get_signal_by_name("T05_TTC").choices[65535]) == "none"
    att = db.get_message_by_name("TGT05_ATT")
    assert att.get_signal_by_name("T05_RelYaw").maximum == 180 and att.get_signal_by_name("T05_RelPitch").minimum == -90
    tow = db.get_message_by_name("MASTER_STATUS").get_signal_by_name("M_TimeOfWeek")
    assert tow.maximum == pytest.approx(604799.999)
    for m in db.messages:
        for sig in m.signals:
            assert sig.comment, f"{m.name}.{sig.name} has no comment"
            # physical range within what the raw bits can hold
            bits = sig.length - (1 if sig.is_signed else 0)
            lo_raw = -(1 << bits) if sig.is_signed else 0
            hi_raw = (1 << bits) - 1
            assert lo_raw * sig.scale - 1e-9 <= sig.minimum <= sig.maximum <= hi_raw * sig.scale + 1e-9, sig.name


def test_frames_decode_to_inputs_within_resolution(buses):
    out, rx = buses
    res = result()
    assert out.send_result(res) == FRAMES_PER_KINEMATIC_UPDATE == 9
    assert out.send_result(result("ped-1", target_kind="pedestrian", ttc_s=None, degraded=True)) == 9
    dec = decode_frames(drain(rx))
    assert dec["e2e_errors"] == []
    t = dec["targets"][0]
    assert t["Status"] == 0 and t["Kind"] == 0 and t["Counter"] == 0 and t["TargetId"] == "car-2"
    for key, value, resolution in [("PosX", 123.4567, 1e-3), ("PosY", -12.3456, 1e-3), ("PosZ", 0.789, 1e-3),
                                   ("Range", 124.0739, 1e-3), ("Bearing", math.degrees(-0.0997), 0.01),
                                   ("VelX", -4.567, 0.01), ("VelY", 0.321, 0.01), ("AccX", 1.234, 0.01),
                                   ("AccY", -0.567, 0.01), ("RelYaw", math.degrees(1.234), 0.01),
                                   ("RelRoll", math.degrees(0.012), 0.01), ("RelPitch", math.degrees(-0.034), 0.01),
                                   ("Longitudinal", 118.37, 0.01), ("Lateral", -11.46, 0.01),
                                   ("ClosingSpeed", 4.5, 0.01), ("TTC", 26.42, 0.01), ("Latency", 103.4, 0.1)]:
        assert t[key] == pytest.approx(value, abs=resolution / 2 + 1e-9), key
    ped = dec["targets"][1]
    assert ped["Kind"] == 1 and ped["Degraded"] == 1 and ped["TTC"] is None and ped["TargetId"] == "ped-1"
    assert out.frames_sent == 18


def test_invalid_status_sends_status_and_id_frames_and_counter_increments(buses):
    out, rx = buses
    out.send_result(result(), slot=7)
    out.send_result(RelativeResult(target_id="car-2", status=TargetStatus.FIX_INVALID, fix_side=FixSide.SLAVE,
                                   latency_s=0.05, master_fix=FixStatus.FIXED, target_fix=FixStatus.SINGLE), slot=7)
    frames = drain(rx)
    assert len(frames) == 9 + FRAMES_PER_STATUS_UPDATE
    assert [f.arbitration_id for f in frames[-2:]] == [0x200 + 7, 0x400 + 7]
    t = decode_frames(frames[-2:-1])["targets"][7]
    assert t["Status"] == int(TargetStatus.FIX_INVALID) and t["FixSide"] == 2 and t["Counter"] == 1
    assert t["TTC"] is None and t["MasterFix"] == 5 and t["TargetFix"] == 2


def test_kinematic_but_not_valid_status_sends_kinematics(buses):
    out, rx = buses
    assert out.send_result(result(status=TargetStatus.ATTITUDE_UNCERTAIN), slot=3) == 9
    t = decode_frames(drain(rx))["targets"][3]
    assert t["Status"] == int(TargetStatus.ATTITUDE_UNCERTAIN) and t["PosX"] == pytest.approx(123.457)


def test_saturation_instead_of_error(buses):
    out, rx = buses
    out.send_result(result(rel_pos_body_m=np.array([1e5, -1e5, 100.0]), rel_vel_body_mps=np.array([900.0, 0, 0]),
                           ttc_s=1e6), slot=0)
    t = decode_frames(drain(rx))["targets"][0]
    assert t["PosX"] == pytest.approx(8388.607) and t["PosY"] == pytest.approx(-8388.608)
    assert t["PosZ"] == pytest.approx(32.767) and t["VelX"] == pytest.approx(327.67)
    assert t["TTC"] == pytest.approx(655.34)   # saturated just below the "none" code
    out.send_result(result(rel_pos_sd_m=np.array([7.0, 0.5, np.nan]), rel_yaw_sd_rad=np.nan), slot=0)
    t = decode_frames(drain(rx))["targets"][0]
    assert t["SdX"] == pytest.approx(4.094) and t["SdY"] == pytest.approx(0.5)   # saturated below n/a
    assert t["SdZ"] is None and t["RelYawSd"] is None                           # NaN -> n/a


def test_nan_in_a_valid_result_is_sent_as_zero_not_fatal(buses):
    out, rx = buses
    assert out.send_result(result(rel_pos_body_m=np.array([np.nan, 2.0, 0.0]), bearing_rad=np.nan), slot=0) == 9
    t = decode_frames(drain(rx))["targets"][0]
    assert t["PosX"] == 0.0 and t["Bearing"] == 0.0 and t["PosY"] == pytest.approx(2.0)


def test_lane_object_and_master_frames(buses):
    out, rx = buses
    out.send_lanes([0, 3], [1.8345, -1.75], [-0.25, 0.0])
    out.send_objects([5, 6], [20.0005, 3.5], [0.1, -1.2], [2.0, float("nan")])
    out.send_master_status({"t_gps_s": 1_400_000_123.456, "master_fix": 5, "n_targets": 2, "heading_valid": True,
                            "pos_sd_m": [0.011, 0.012, 0.025], "yaw_sd_rad": math.radians(0.3),
                            "clock_synced": True, "clock_offset_s": -0.0031})
    dec = decode_frames(drain(rx))
    assert dec["e2e_errors"] == []
    m = dec["master"]
    assert m["HeadingValid"] == 1 and m["ClockState"] == 1 and m["ClockOffset"] == pytest.approx(-3.1)
    assert m["PosSdN"] == pytest.approx(0.011) and m["PosSdD"] == pytest.approx(0.025)
    assert m["YawSd"] == pytest.approx(0.3) and m["NTargets"] == 2
    assert dec["lanes"][0]["LateralDist"] == pytest.approx(1.8345, abs=5e-4)
    assert dec["lanes"][3]["LateralSpeed"] == pytest.approx(0.0)
    assert dec["objects"][5]["Distance"] == pytest.approx(20.0005, abs=5e-4)
    assert dec["objects"][5]["TTC"] == pytest.approx(2.0) and dec["objects"][6]["TTC"] is None
    assert dec["objects"][6]["Bearing"] == pytest.approx(math.degrees(-1.2), abs=0.005)
    assert dec["master"]["TimeOfWeek"] == pytest.approx(1_400_000_123.456 % 604800, abs=1e-3)
    assert dec["master"]["MasterFix"] == 5
    out.send_master_status({"t_gps_s": 1.0})        # nothing known yet: n/a codes, counter +1
    m = decode_frames(drain(rx))["master"]
    assert m["PosSdN"] is None and m["YawSd"] is None and m["ClockOffset"] is None
    assert m["ClockState"] == 0 and m["MasterFix"] == 0 and m["Counter"] == 1


def test_slot_table_is_stable_and_bounded():
    slots = SlotTable(3)
    assert [slots.slot_of(x) for x in ("a", "b", "a", "c")] == [0, 1, 0, 2]
    assert slots.slot_of("d") is None
    slots.release("b")
    assert slots.slot_of("d") == 1 and len(slots) == 3


def test_slot_table_fixed_slots_first_come_for_the_others():
    slots = SlotTable(4, {"lead": 0, "ped": 2})
    assert [slots.slot_of(x) for x in ("x", "ped", "y", "lead")] == [1, 2, 3, 0]
    assert slots.slot_of("z") is None                      # 0 and 2 stay reserved
    slots.release("ped")
    assert slots.slot_of("z") is None and slots.slot_of("ped") == 2
    with pytest.raises(ValueError, match="share"):
        SlotTable(4, {"a": 1, "b": 1})
    with pytest.raises(ValueError, match="outside"):
        SlotTable(4, {"a": 4})


def test_unknown_and_short_frames_counted_not_fatal():
    dec = decode_frames([can.Message(arbitration_id=0x7FF, data=bytes(8), is_extended_id=False),
                         can.Message(arbitration_id=0x240, data=bytes(3), is_extended_id=False),
                         can.Message(arbitration_id=0x480, data=bytes([0, 0, 0x20, 0, 0, 0, 0, 0]), is_extended_id=False),
                         can.Message(arbitration_id=0x481, data=bytes([0x21, 0, 0, 0, 0, 0, 0, 0]), is_extended_id=False)])
    assert dec["unknown"] == 1
    assert len(dec["malformed"]) == 1 and "0x240" in dec["malformed"][0] and "3 data bytes" in dec["malformed"][0]
    assert len(dec["e2e_errors"]) == 1 and "0x480" in dec["e2e_errors"][0]     # LANE with a wrong CRC
    assert dec["objects"][2]["Counter"] == 1                                  # OBJECT: no CRC


def test_slot_count_bounded_by_dbc():
    with pytest.raises(ValueError, match="n_slots"):
        CanOutput(channel="x", interface="virtual", n_slots=65)


def test_unavailable_bus_is_one_line_naming_interface_and_channel():
    """No such SocketCAN device (or no SocketCAN at all in this kernel): a CanBusError, not an OSError."""
    with pytest.raises(CanBusError) as info:
        CanOutput(channel="v2xpos-no-such-can9", interface="socketcan")
    text = str(info.value)
    assert "'socketcan'" in text and "'v2xpos-no-such-can9'" in text and "\n" not in text
