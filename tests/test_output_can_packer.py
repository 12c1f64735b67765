"""The precompiled CAN frame packer is bit-exact against cantools' encoder on the shipped DBC."""
from __future__ import annotations

import math

import numpy as np
import pytest

from v2xpos.output.can import (ID_EXT, ID_LANE, ID_MASTER, ID_OBJECT, ID_POS, ID_RANGE, ID_STATUS, ID_VEL,
                               CanOutput, FramePacker, load_dbc)
from v2xpos.wire import FixSide, RelativeResult, TargetStatus


@pytest.fixture(scope="module")
def db():
    return load_dbc()


def _cantools_reference(message, values: dict) -> bytes:
    """What CanOutput sent through cantools: NaN -> 0, clip to the DBC range, encode(strict=False)."""
    clamped = {}
    for s in message.signals:
        v = values[s.name]
        clamped[s.name] = 0.0 if v != v else s.minimum if v < s.minimum else s.maximum if v > s.maximum else v
    return bytes(message.encode(clamped, strict=False))


def _random_value(rng: np.random.Generator, sig) -> float | int:
    lo, hi = sig.minimum, sig.maximum
    pick = rng.integers(0, 10)
    if pick == 0:
        return math.nan
    if pick == 1:
        return lo - abs(rng.normal()) * (hi - lo + 1.0)
    if pick == 2:
        return hi + abs(rng.normal()) * (hi - lo + 1.0)
    if pick == 3:
        return float(rng.choice([lo, hi, 0.0, math.inf, -math.inf]))
    if pick == 4:   # exact raw grid points and half-way points (banker's rounding in both encoders)
        k = int(rng.integers(round((lo - sig.offset) / sig.scale), round((hi - sig.offset) / sig.scale) + 1))
        return sig.offset + (k + 0.5 * int(rng.integers(0, 2))) * sig.scale
    if pick == 5 and sig.scale == 1:
        return int(rng.integers(int(lo), int(hi) + 1))
    return float(rng.uniform(lo, hi))


@pytest.mark.parametrize("frame_id", [ID_MASTER, ID_LANE, ID_OBJECT] +
                         [base + slot for base in (ID_STATUS, ID_POS, ID_RANGE, ID_VEL, ID_EXT) for slot in (0, 17, 63)])
def test_packer_bit_exact_against_cantools(db, frame_id):
    message = db.get_message_by_frame_id(frame_id)
    packer = FramePacker(message)
    rng = np.random.default_rng(frame_id)
    for _ in range(400):
        values = {s.name: _random_value(rng, s) for s in message.signals}
        assert packer.pack_mapping(values) == _cantools_reference(message, values), values


def test_packer_rejects_missing_signal(db):
    message = db.get_message_by_frame_id(ID_POS)
    packer = FramePacker(message)
    with pytest.raises(KeyError):
        packer.pack_mapping({"T00_PosX": 1.0})


def _result(rng: np.random.Generator, status: TargetStatus) -> RelativeResult:
    res = RelativeResult(target_id="t1", target_kind=str(rng.choice(["vehicle", "pedestrian"])), status=status,
                         fix_side=FixSide(int(rng.integers(0, 4))), degraded=bool(rng.integers(0, 2)),
                         latency_s=float(rng.uniform(-0.05, 4.0)))
    if status == TargetStatus.VALID:
        res.rel_pos_body_m = rng.normal(0, 3000, 3)
        res.rel_vel_body_mps = rng.normal(0, 200, 3)
        res.rel_acc_body_mps2 = rng.normal(0, 200, 3)
        res.rel_rpy_rad = rng.uniform(-math.pi, math.pi, 3)
        res.range_m = float(np.linalg.norm(res.rel_pos_body_m))
        res.bearing_rad = float(rng.uniform(-math.pi, math.pi))
        res.closing_speed_mps = float(rng.choice([rng.normal(0, 400), math.nan]))
        res.longitudinal_m = float(rng.choice([rng.normal(0, 400), math.nan]))
        res.lateral_m = float(rng.normal(0, 400))
        res.ttc_s = None if rng.integers(0, 3) == 0 else float(rng.choice([rng.uniform(-5, 900), math.inf]))
    return res


def _reference_frames(out: CanOutput, res: RelativeResult, slot: int, counter: int) -> dict:
    """The signal dictionaries CanOutput built for cantools before the packer (same formulas)."""
    p = f"T{slot:02d}_"
    valid = res.status == TargetStatus.VALID
    ttc = res.ttc_s if valid else None
    ttc_v = 65535 * 0.01 if ttc is None or not math.isfinite(ttc) else min(max(ttc, 0.0), 65534 * 0.01)
    fin = (lambda x: x if math.isfinite(x) else 0.0)
    frames = {ID_STATUS + slot: {p + "Status": int(res.status), p + "FixSide": int(res.fix_side),
                                 p + "Degraded": int(res.degraded), p + "Kind": int(res.target_kind == "pedestrian"),
                                 p + "Counter": counter & 0xFF, p + "Latency": fin(res.latency_s * 1e3),
                                 p + "TTC": ttc_v, p + "RelYaw": math.degrees(res.rel_rpy_rad[2]) if valid else 0.0}}
    if valid:
        r, v, a, att = res.rel_pos_body_m, res.rel_vel_body_mps, res.rel_acc_body_mps2, res.rel_rpy_rad
        frames[ID_POS + slot] = {p + "PosX": r[0], p + "PosY": r[1], p + "PosZ": r[2]}
        frames[ID_RANGE + slot] = {p + "Range": res.range_m, p + "Bearing": math.degrees(res.bearing_rad),
                                   p + "ClosingSpeed": fin(res.closing_speed_mps), p + "Counter": counter & 0xFF}
        frames[ID_VEL + slot] = {p + "VelX": v[0], p + "VelY": v[1], p + "Longitudinal": fin(res.longitudinal_m),
                                 p + "Lateral": fin(res.lateral_m)}
        frames[ID_EXT + slot] = {p + "AccX": a[0], p + "AccY": a[1], p + "RelRoll": math.degrees(att[0]),
                                 p + "RelPitch": math.degrees(att[1])}
    return frames


def test_result_frames_bit_exact_against_cantools(db):
    out = CanOutput(channel="packer-test", interface="virtual")
    try:
        rng = np.random.default_rng(7)
        for i in range(300):
            status = TargetStatus.VALID if i % 3 else TargetStatus(int(rng.integers(1, 5)))
            res = _result(rng, status)
            slot, counter = int(rng.integers(0, 64)), int(rng.integers(0, 600))
            got = out.frames_for_result(res, slot, counter)
            ref = _reference_frames(out, res, slot, counter)
            assert [f.arbitration_id for f in got] == list(ref)
            for f in got:
                message = db.get_message_by_frame_id(f.arbitration_id)
                assert bytes(f.data) == _cantools_reference(message, ref[f.arbitration_id])
                assert not f.is_extended_id and len(f.data) == 8
    finally:
        out.close()
