"""evaluate_target's compiled kernel (v2xpos.relative_jit) agrees with the interpreted public
composition predict_state -> relative_kinematics, for every outline kind and measurement point form."""
from __future__ import annotations

import numpy as np
import pytest

from v2xpos.relative import evaluate_target, predict_state, relative_kinematics
from v2xpos.types import FixStatus
from v2xpos.wire import Geometry, StateMessage, TargetStatus


def _state(rng: np.random.Generator, vid: str, geometry: Geometry, kind: str = "vehicle") -> StateMessage:
    return StateMessage("f", vid, 1, 1.4e9 + rng.uniform(0, 0.1), FixStatus.FIXED,
                        0.8 + rng.normal(0, 1e-5), 0.2 + rng.normal(0, 1e-5), 100 + rng.normal(0, 2),
                        rng.normal(0, 10, 3), rng.normal(0, 2, 3), rng.normal(0, 0.3, 3),
                        np.array([rng.normal(0, .05), rng.normal(0, .05), rng.uniform(-3, 3)]),
                        np.abs(rng.normal(0, .02, 3)), np.abs(rng.normal(0, .02, 3)),
                        np.abs(rng.normal(0, .002, 3)), geometry, kind=kind)


def test_fast_path_equals_predict_then_transform():
    rng = np.random.default_rng(11)
    ranges_m = []
    for i in range(400):
        geometry = [Geometry.box(3.8, 1.0, 0.9), Geometry(kind="circle", radius_m=0.3),
                    Geometry(kind="points", points_body_m=rng.normal(0, 2, (3, 3))), Geometry()][i % 4]
        master, target = _state(rng, "m", Geometry()), _state(rng, "s", geometry, ("vehicle", "pedestrian")[i % 2])
        master.t_gps_s = target.t_gps_s + rng.uniform(0.0, 0.15)
        point = [None, np.array([3.8, 0.0, 0.0]), (3.8, 0.1, -0.2), [1.0, 0.0, 0.0]][i % 4]
        res = evaluate_target(master, target, point, timeout_s=1.0, future_tolerance_s=1.0)
        assert res.status == TargetStatus.VALID
        dt = master.t_gps_s - target.t_gps_s
        predicted = predict_state(target, dt)
        ref = relative_kinematics(master, predicted, point)
        ref.source_seq, ref.latency_s, ref.t_sent_wall_s = target.seq, dt, target.t_sent_wall_s
        ref.master_fix, ref.target_fix = master.fix, target.fix
        # both filters' yaw sd, the target's grown over the latency as predict_state grows it
        ref.rel_yaw_sd_rad = float(np.hypot(master.att_sd_rad[2], predicted.att_sd_rad[2]))
        for name, value in res.__dict__.items():
            other = ref.__dict__[name]
            if isinstance(value, np.ndarray):
                np.testing.assert_allclose(value, other, rtol=1e-12, atol=1e-11, err_msg=name)
            elif isinstance(value, float) and isinstance(other, float):
                assert value == pytest.approx(other, rel=1e-12, abs=1e-11, nan_ok=True), name
            else:
                assert value == other, name
        assert res.target_id == "s" and res.target_kind == target.kind
        # NaN == NaN passes the comparison above: the relative state itself must be numbers
        for name in ("rel_pos_body_m", "rel_pos_sd_m", "rel_vel_body_mps", "rel_acc_body_mps2", "rel_rpy_rad"):
            assert np.all(np.isfinite(getattr(res, name))), (i, name, getattr(res, name))
        ranges_m.append(res.range_m)
    # the cases differ: targets spread over tens of metres, no two at the same range
    assert np.ptp(ranges_m) > 10.0 and len(np.unique(np.round(ranges_m, 6))) == len(ranges_m)


@pytest.mark.parametrize("master_fix, target_fix, status", [
    (FixStatus.FIXED, FixStatus.FLOAT, TargetStatus.VALID),
    (FixStatus.FIXED, FixStatus.SINGLE, TargetStatus.FIX_INVALID),
    (FixStatus.DEAD_RECKONING, FixStatus.FIXED, TargetStatus.FIX_INVALID),
])
def test_both_fix_states_on_every_status(master_fix, target_fix, status):
    rng = np.random.default_rng(3)
    master, target = _state(rng, "m", Geometry()), _state(rng, "s", Geometry())
    master.fix, target.fix = master_fix, target_fix
    master.t_gps_s = target.t_gps_s + 0.05
    res = evaluate_target(master, target, timeout_s=1.0)
    assert res.status == status and res.master_fix == master_fix and res.target_fix == target_fix
    assert np.isfinite(res.rel_yaw_sd_rad) == (status == TargetStatus.VALID)
    master.t_gps_s = target.t_gps_s + 2.0                   # stale: TIMEOUT, still both fixes
    late = evaluate_target(master, target, timeout_s=1.0)
    assert late.status in (TargetStatus.TIMEOUT, TargetStatus.FIX_INVALID)
    assert late.master_fix == master_fix and late.target_fix == target_fix
