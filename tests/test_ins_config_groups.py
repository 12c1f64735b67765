"""``InsConfig`` in groups: at most ten at the top, a group given as a dict of some of its fields,
a misspelt field rejected with a "did you mean", and overrides applied field by field."""
from __future__ import annotations

from dataclasses import fields

import pytest

from v2xpos.ins.config import GROUPS, ImuModel, InsConfig, overridden


def test_the_top_level_is_a_few_groups():
    top = [f.name for f in fields(InsConfig)]
    assert top == list(GROUPS) and len(top) <= 10


def test_a_group_given_as_a_dict_keeps_the_defaults_of_the_rest():
    cfg = InsConfig(setup={"platform": "pedestrian"}, imu={"gyro_noise_rps_rthz": 1e-4})
    assert isinstance(cfg.imu, ImuModel) and cfg.imu.gyro_noise_rps_rthz == 1e-4
    assert cfg.imu.accel_noise_mps2_rthz == ImuModel.accel_noise_mps2_rthz
    assert cfg.initial.align_min_speed_mps == 0.5             # the platform's default, filled in


def test_a_misspelt_field_says_did_you_mean():
    with pytest.raises(TypeError, match=r"InsConfig.imu: unknown key 'gyro_noise_rps_rthzz' "
                                        r"\(did you mean 'gyro_noise_rps_rthz'\?\)"):
        InsConfig(imu={"gyro_noise_rps_rthzz": 1e-4})
    with pytest.raises(ValueError, match=r"setup.platform 'boat'"):
        InsConfig(setup={"platform": "boat"})


def test_overrides_apply_field_by_field_without_changing_the_base():
    base = {"integrity": {"alert_limit_m": 0.3, "integrity_risk": 1e-5}}
    out = overridden(base, {"integrity": {"alert_limit_m": 0.5}, "gnss": {"gate_probability": 1.0}})
    assert out == {"integrity": {"alert_limit_m": 0.5, "integrity_risk": 1e-5}, "gnss": {"gate_probability": 1.0}}
    assert base["integrity"]["alert_limit_m"] == 0.3
