"""CAN output: the shipped DBC loads in cantools, frames sent on a python-can virtual bus decode to the
inputs within the documented resolution."""
import math
import uuid

import can
import numpy as np
import pytest

from v2xpos.output.can import (DBC_PATH, N_SLOTS, CanOutput, SlotTable, decode_frames, generate_dbc, load_dbc)
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
    assert len(db.messages) == 3 + 5 * N_SLOTS >= 3 + 5 * 32
    assert all(m.length == 8 for m in db.messages) and max(ids) < 0x800
    assert db.get_message_by_name("TGT31_POS").frame_id == 0x240 + 31


def test_frames_decode_to_inputs_within_resolution(buses):
    out, rx = buses
    res = result()
    assert out.send_result(res) == 5
    assert out.send_result(result("ped-1", target_kind="pedestrian", ttc_s=None, degraded=True)) == 5
    dec = decode_frames(drain(rx))
    t = dec["targets"][0]
    assert t["Status"] == 0 and t["Kind"] == 0 and t["Counter"] == 0
    for key, value, resolution in [("PosX", 123.4567, 1e-3), ("PosY", -12.3456, 1e-3), ("PosZ", 0.789, 1e-3),
                                   ("Range", 124.0739, 1e-3), ("Bearing", math.degrees(-0.0997), 0.01),
                                   ("VelX", -4.567, 0.01), ("VelY", 0.321, 0.01), ("AccX", 1.234, 0.01),
                                   ("AccY", -0.567, 0.01), ("RelYaw", math.degrees(1.234), 0.01),
                                   ("RelRoll", math.degrees(0.012), 0.01), ("RelPitch", math.degrees(-0.034), 0.01),
                                   ("Longitudinal", 118.37, 0.01), ("Lateral", -11.46, 0.01),
                                   ("ClosingSpeed", 4.5, 0.01), ("TTC", 26.42, 0.01), ("Latency", 103.4, 0.1)]:
        assert t[key] == pytest.approx(value, abs=resolution / 2 + 1e-9), key
    ped = dec["targets"][1]
    assert ped["Kind"] == 1 and ped["Degraded"] == 1 and ped["TTC"] is None
    assert out.frames_sent == 10


def test_invalid_status_sends_only_status_frame_and_counter_increments(buses):
    out, rx = buses
    out.send_result(result(), slot=7)
    out.send_result(RelativeResult(target_id="car-2", status=TargetStatus.FIX_INVALID,
                                   fix_side=FixSide.SLAVE, latency_s=0.05), slot=7)
    frames = drain(rx)
    assert len(frames) == 6 and frames[-1].arbitration_id == 0x200 + 7
    t = decode_frames(frames[-1:])["targets"][7]
    assert t["Status"] == int(TargetStatus.FIX_INVALID) and t["FixSide"] == 2 and t["Counter"] == 1
    assert t["TTC"] is None


def test_saturation_instead_of_error(buses):
    out, rx = buses
    out.send_result(result(rel_pos_body_m=np.array([1e5, -1e5, 100.0]), rel_vel_body_mps=np.array([900.0, 0, 0]),
                           ttc_s=1e6), slot=0)
    t = decode_frames(drain(rx))["targets"][0]
    assert t["PosX"] == pytest.approx(8388.607) and t["PosY"] == pytest.approx(-8388.608)
    assert t["PosZ"] == pytest.approx(32.767) and t["VelX"] == pytest.approx(327.67)
    assert t["TTC"] == pytest.approx(655.34)   # saturated just below the "none" code


def test_nan_in_a_valid_result_is_sent_as_zero_not_fatal(buses):
    out, rx = buses
    assert out.send_result(result(rel_pos_body_m=np.array([np.nan, 2.0, 0.0]), bearing_rad=np.nan), slot=0) == 5
    t = decode_frames(drain(rx))["targets"][0]
    assert t["PosX"] == 0.0 and t["Bearing"] == 0.0 and t["PosY"] == pytest.approx(2.0)


def test_lane_object_and_master_frames(buses):
    out, rx = buses
    out.send_lanes([0, 3], [1.8345, -1.75], [-0.25, 0.0])
    out.send_objects([5, 6], [20.0005, 3.5], [0.1, -1.2], [2.0, float("nan")])
    out.send_master_status(n_targets=2, master_fix=5, t_gps_s=1_400_000_123.456)
    dec = decode_frames(drain(rx))
    assert dec["lanes"][0]["LateralDist"] == pytest.approx(1.8345, abs=5e-4)
    assert dec["lanes"][3]["LateralSpeed"] == pytest.approx(0.0)
    assert dec["objects"][5]["Distance"] == pytest.approx(20.0005, abs=5e-4)
    assert dec["objects"][5]["TTC"] == pytest.approx(2.0) and dec["objects"][6]["TTC"] is None
    assert dec["objects"][6]["Bearing"] == pytest.approx(math.degrees(-1.2), abs=0.005)
    assert dec["master"]["TimeOfWeek"] == pytest.approx(1_400_000_123.456 % 604800, abs=1e-3)
    assert dec["master"]["MasterFix"] == 5


def test_slot_table_is_stable_and_bounded():
    slots = SlotTable(3)
    assert [slots.slot_of(x) for x in ("a", "b", "a", "c")] == [0, 1, 0, 2]
    assert slots.slot_of("d") is None
    slots.release("b")
    assert slots.slot_of("d") == 1 and len(slots) == 3


def test_unknown_and_short_frames_counted_not_fatal():
    dec = decode_frames([can.Message(arbitration_id=0x7FF, data=bytes(8), is_extended_id=False),
                         can.Message(arbitration_id=0x240, data=bytes(3), is_extended_id=False),
                         can.Message(arbitration_id=0x380, data=bytes([2, 0, 1, 0, 0, 0, 0, 0]), is_extended_id=False)])
    assert dec["unknown"] == 1
    assert len(dec["malformed"]) == 1 and "0x240" in dec["malformed"][0] and "3 data bytes" in dec["malformed"][0]
    assert dec["lanes"][2]["LateralDist"] == pytest.approx(0.001)


def test_slot_count_bounded_by_dbc():
    with pytest.raises(ValueError, match="n_slots"):
        CanOutput(channel="x", interface="virtual", n_slots=65)
