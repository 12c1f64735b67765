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
    checked = 0
    for i in range(400):
        geometry = [Geometry.box(3.8, 1.0, 0.9), Geometry(kind="circle", radius_m=0.3),
                    Geometry(kind="points", points_body_m=rng.normal(0, 2, (3, 3))), Geometry()][i % 4]
        master, target = _state(rng, "m", Geometry()), _state(rng, "s", geometry, ("vehicle", "pedestrian")[i % 2])
        master.t_gps_s = target.t_gps_s + rng.uniform(0.0, 0.15)
        point = [None, np.array([3.8, 0.0, 0.0]), (3.8, 0.1, -0.2), [1.0, 0.0, 0.0]][i % 4]
        res = evaluate_target(master, target, point, timeout_s=1.0, future_tolerance_s=1.0)
        assert res.status == TargetStatus.VALID
        dt = master.t_gps_s - target.t_gps_s
        ref = relative_kinematics(master, predict_state(target, dt), point)
        ref.source_seq, ref.latency_s, ref.t_sent_wall_s = target.seq, dt, target.t_sent_wall_s
        for name, value in res.__dict__.items():
            other = ref.__dict__[name]
            if isinstance(value, np.ndarray):
                np.testing.assert_allclose(value, other, rtol=1e-12, atol=1e-11, err_msg=name)
            elif isinstance(value, float) and isinstance(other, float):
                assert value == pytest.approx(other, rel=1e-12, abs=1e-11), name
            else:
                assert value == other, name
        assert res.target_id == "s" and res.target_kind == target.kind
        checked += 1
    assert checked == 400
