"""CAN frames checked by an independent decoder: the shipped DBC loaded with cantools, the E2E CRC checked
with cantools' AUTOSAR profile-2 implementation (``cantools.autosar.end_to_end``, crccheck's CRC-8/AUTOSAR),
counters read from the decoded signals; the fixed target -> slot mapping from a master config."""
from __future__ import annotations

import math
import uuid

import can
import cantools
import numpy as np
import pytest
from cantools.autosar.end_to_end import check_profile2_crc

from master.config import MasterConfig
from master.outputs import CanSink, master_status
from v2xpos.config import ConfigError
from v2xpos.output.can import CanOutput
from v2xpos.output.can_dbc import DBC_PATH, ID_ID, ID_STATUS
from v2xpos.types import FixStatus, NavState
from v2xpos.wire import KINEMATIC_STATUSES, FixSide, RelativeResult, TargetStatus


@pytest.fixture(scope="module")
def db():
    """The reference decoder: cantools on the shipped file (not the implementation's loader)."""
    return cantools.database.load_file(str(DBC_PATH))


def result(target_id: str, k: int, status: TargetStatus = TargetStatus.VALID, **kw) -> RelativeResult:
    base = dict(target_id=target_id, status=status, seq=k, t_gps_s=1.4e9 + 0.01 * k, latency_s=0.05 + 0.001 * k,
                master_fix=FixStatus.FIXED, target_fix=FixStatus.FIXED)
    if status in KINEMATIC_STATUSES:
        base.update(rel_pos_body_m=np.array([20.0 + k, -1.5 - 0.1 * k, 0.3]), rel_pos_sd_m=np.array([0.02, 0.03, 0.05]),
                    rel_vel_body_mps=np.array([-1.0, 0.2, 0.0]), rel_acc_body_mps2=np.array([0.3, -0.1, 0.05]),
                    rel_rpy_rad=np.array([0.01, -0.02, 0.5]), range_m=float(np.hypot(20.0 + k, 1.5 + 0.1 * k)),
                    range_sd_m=0.025, bearing_rad=-0.07, elevation_rad=0.0, longitudinal_m=16.0 + k,
                    lateral_m=-1.2, gap_m=16.1 + k, closing_speed_mps=1.0, ttc_s=16.1 + k, rel_yaw_sd_rad=0.004)
    else:
        base.update(fix_side=FixSide.SLAVE, target_fix=FixStatus.SINGLE)
    base.update(kw)
    return RelativeResult(**base)


def receive(rx: can.BusABC) -> list[can.Message]:
    frames = []
    while (f := rx.recv(timeout=0.05)) is not None:
        frames.append(f)
    return frames


def updates_of_slot(frames: list[can.Message], slot: int) -> list[list[can.Message]]:
    """Frames of one slot grouped into updates: each update starts with the STATUS frame."""
    out: list[list[can.Message]] = []
    for f in frames:
        if f.arbitration_id == ID_STATUS + slot:
            out.append([f])
        elif (f.arbitration_id - ID_STATUS) % 64 == slot and ID_STATUS <= f.arbitration_id <= ID_ID + 63:
            out[-1].append(f)
    return out


def test_counter_and_crc_of_every_frame_checked_by_cantools(db):
    channel = f"e2e-{uuid.uuid4().hex}"
    rx = can.Bus(channel=channel, interface="virtual")
    statuses = [TargetStatus.VALID] * 8 + [TargetStatus.FIX_INVALID] * 3 + [TargetStatus.SIGMA_EXCEEDED] * 2 + \
        [TargetStatus.VALID] * 9                                  # 22 updates: the 4-bit counter wraps
    with CanOutput(channel=channel, interface="virtual") as out:
        for k, st in enumerate(statuses):
            out.send_result(result("car-7", k, st))
        for _ in range(3):
            out.send_master_status({"t_gps_s": 1.4e9, "master_fix": 5})
    frames = receive(rx)
    rx.shutdown()
    protected = 0
    for f in frames:
        msg = db.get_message_by_frame_id(f.arbitration_id)
        if any(s.name.endswith("_CRC") for s in msg.signals):
            assert check_profile2_crc(bytes(f.data), f.arbitration_id & 0xFF), hex(f.arbitration_id)
            protected += 1
    assert protected == len(frames)                               # no OBJECT frame here: all protected
    ups = updates_of_slot(frames, 0)
    assert len(ups) == len(statuses)
    counters = []
    for up, st in zip(ups, statuses):
        decoded = [db.decode_message(f.arbitration_id, f.data, decode_choices=False) for f in up]
        values = {v for d in decoded for k, v in d.items() if k.endswith("_Counter")}
        assert len(values) == 1, "every frame of one update carries the same counter"
        counters.append(values.pop())
        assert len(up) == (9 if st in KINEMATIC_STATUSES else 2)
    assert counters == [k % 16 for k in range(len(statuses))]
    master = [db.decode_message(f.arbitration_id, f.data) for f in frames if f.arbitration_id in (0x1F0, 0x1F1)]
    assert [m.get("M_Counter", m.get("MS_Counter")) for m in master] == [0, 0, 1, 1, 2, 2]


def test_corrupted_or_misrouted_frames_fail_the_check(db):
    channel = f"e2e-{uuid.uuid4().hex}"
    rx = can.Bus(channel=channel, interface="virtual")
    with CanOutput(channel=channel, interface="virtual") as out:
        out.send_result(result("car-7", 3), slot=12)
    frames = receive(rx)
    rx.shutdown()
    pos = next(f for f in frames if f.arbitration_id == 0x240 + 12)
    data = bytearray(pos.data)
    assert check_profile2_crc(bytes(data), pos.arbitration_id & 0xFF)
    assert not check_profile2_crc(bytes(data), (pos.arbitration_id + 1) & 0xFF)   # same bytes, other frame id
    for bit in range(8, 64):
        flipped = bytearray(data)
        flipped[bit // 8] ^= 1 << (bit % 8)
        assert not check_profile2_crc(bytes(flipped), pos.arbitration_id & 0xFF), bit


def test_signals_decode_to_the_result_and_the_target_id(db):
    channel = f"e2e-{uuid.uuid4().hex}"
    rx = can.Bus(channel=channel, interface="virtual")
    res = result("a-rather-long-target-id.31", 4, target_fix=FixStatus.FLOAT)
    with CanOutput(channel=channel, interface="virtual") as out:
        for _ in range(5):                        # 26 bytes: five ID parts, one per update
            out.send_result(res, slot=9)
    frames = receive(rx)
    rx.shutdown()
    sig: dict = {}
    parts: dict = {}
    for f in frames:
        d = db.decode_message(f.arbitration_id, f.data, decode_choices=False)
        sig.update(d)
        if f.arbitration_id == ID_ID + 9:
            p = d["T09_IdPart"]
            parts[p] = int(d[f"T09_IdText{p}"]).to_bytes(6, "little")
            assert d["T09_IdLast"] == (p == 4)
    assert b"".join(parts[p] for p in range(5)).rstrip(b"\0").decode() == res.target_id
    checks = {"T09_PosX": res.rel_pos_body_m[0], "T09_PosY": res.rel_pos_body_m[1], "T09_PosZ": res.rel_pos_body_m[2],
              "T09_Range": res.range_m, "T09_RangeSd": res.range_sd_m, "T09_SdX": 0.02, "T09_SdY": 0.03,
              "T09_SdZ": 0.05, "T09_RelYawSd": math.degrees(0.004), "T09_RelYaw": math.degrees(0.5),
              "T09_Bearing": math.degrees(-0.07), "T09_AccZ": 0.05, "T09_Latency": res.latency_s * 1e3,
              "T09_TTC": res.ttc_s, "T09_MasterFix": 5, "T09_TargetFix": 4, "T09_Status": 0}
    for name, value in checks.items():
        s = db.get_message_by_frame_id(next(f.arbitration_id for f in frames
                                            if name in db.decode_message(f.arbitration_id, f.data))).get_signal_by_name(name)
        assert sig[name] == pytest.approx(value, abs=s.scale / 2 + 1e-9), name


SIM_SOURCE = {"type": "sim", "model": "truth_noise"}
"""A valid ``[source]`` table (required in every service config; not what these tests are about)."""


def _master_config(slots: dict, channel: str) -> MasterConfig:
    return MasterConfig.from_dict({"source": SIM_SOURCE,
                                   "output": {"can": {"enabled": True, "interface": "virtual", "channel": channel,
                                                      "rate_hz": 0, "slots": slots}}}, "master.toml")


def test_slot_mapping_from_config(db):
    channel = f"slots-{uuid.uuid4().hex}"
    cfg = _master_config({"leader": 3, "ped-1": 0}, channel)
    assert cfg.output.can.slots == {"leader": 3, "ped-1": 0}
    rx = can.Bus(channel=channel, interface="virtual")
    sink = CanSink.from_config(cfg)
    try:
        for k, vid in enumerate(["cut-in", "ped-1", "other", "leader"]):   # arrival order != slot order
            sink.write(result(vid, k))
        sink.write_master_status(master_status(None, t_gps_s=1.4e9))
    finally:
        sink.close()
    frames = receive(rx)
    rx.shutdown()
    ids = {}
    for f in frames:
        if ID_ID <= f.arbitration_id < ID_ID + 64:
            slot = f.arbitration_id - ID_ID
            d = db.decode_message(f.arbitration_id, f.data, decode_choices=False)
            p = d[f"T{slot:02d}_IdPart"]
            ids[slot] = int(d[f"T{slot:02d}_IdText{p}"]).to_bytes(6, "little").rstrip(b"\0").decode()
    # configured ids on their slots; the others first come, first served on the slots left (1, 2);
    # ids of at most 6 bytes fit one ID frame
    assert ids == {3: "leader", 0: "ped-1", 1: "cut-in", 2: "other"}
    m = db.decode_message(0x1F0, next(f.data for f in frames if f.arbitration_id == 0x1F0))
    assert m["M_NTargets"] == 4


@pytest.mark.parametrize("slots, match", [({"a": 64}, "slot number"), ({"a": 1, "b": 1}, "both on slot 1"),
                                          ({"a": True}, "slot number"), ({"a/b": 2}, "vehicle id")])
def test_bad_slot_tables_are_config_errors(slots, match):
    with pytest.raises(ConfigError, match=match):
        _master_config(slots, "x")


def test_bus_options_from_config_and_unavailable_socketcan_is_one_line():
    can_table = {"enabled": True, "interface": "socketcan", "channel": "v2xpos-absent0", "bitrate": 500000,
                 "fd": True, "data_bitrate": 2000000, "receive_own_messages": True}
    cfg = MasterConfig.from_dict({"source": SIM_SOURCE, "output": {"can": can_table}}, "m.toml")
    assert cfg.output.can.bus_kwargs() == {"bitrate": 500000, "fd": True, "data_bitrate": 2000000,
                                    "receive_own_messages": True}
    with pytest.raises(ConfigError) as info:
        CanSink.from_config(cfg)
    text = str(info.value)
    assert text.startswith("m.toml: [output.can]: CAN interface 'socketcan' channel 'v2xpos-absent0': cannot open")
    assert "\n" not in text
    with pytest.raises(ConfigError, match="did you mean 'socketcan'"):
        MasterConfig.from_dict({"source": SIM_SOURCE, "output": {"can": {"interface": "socketcann"}}}, "m.toml")
    with pytest.raises(ConfigError, match="data_bitrate: only with fd"):
        MasterConfig.from_dict({"source": SIM_SOURCE, "output": {"can": {"data_bitrate": 2000000}}}, "m.toml")


def test_master_status_from_a_filter_state(db):
    nav = NavState(t_s=1.4e9 + 12.5, lla=np.zeros(3), v_ned_mps=np.zeros(3), acc_body_mps2=np.zeros(3),
                   rate_body_rps=np.zeros(3), rpy_rad=np.zeros(3), pos_sd_m=np.array([0.012, 0.013, 0.03]),
                   vel_sd_mps=np.zeros(3), att_sd_rad=np.array([0.001, 0.001, math.radians(0.8)]),
                   fix=FixStatus.FLOAT)
    channel = f"ms-{uuid.uuid4().hex}"
    rx = can.Bus(channel=channel, interface="virtual")
    sink = CanSink(channel=channel, interface="virtual")
    sink.write_master_status(master_status(nav, heading_valid=False, clock_synced=False, clock_offset_s=0.031))
    sink.close()
    frames = receive(rx)
    rx.shutdown()
    d = {}
    for f in frames:
        d.update(db.decode_message(f.arbitration_id, f.data))
    assert str(d["M_MasterFix"]) == "rtk_float" and str(d["M_HeadingValid"]) == "pending"
    assert str(d["M_ClockState"]) == "unsynced" and d["M_ClockOffset"] == pytest.approx(25.5)   # saturated
    assert d["M_TimeOfWeek"] == pytest.approx((1.4e9 + 12.5) % 604800, abs=1e-3)
    assert d["MS_PosSdE"] == pytest.approx(0.013) and d["MS_YawSd"] == pytest.approx(0.8)
