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


@pytest.mark.parametrize("states, needed", [(("lever_arm", "imu_clock_drift"), "imu_time_offset"),
                                            (("misalignment", "rear_slip_compliance"), "rear_axle_distance")])
def test_an_effect_without_the_effect_it_acts_through_is_refused(states, needed):
    """A clock drift acts only through the time offset, a slip compliance only through the rear-axle
    distance (``ekf.EFFECT_NEEDS``): alone, the state would have no column in any measurement and
    stay at its prior unseen, so the configuration is refused naming both."""
    with pytest.raises(ValueError, match=rf"effect '{states[1]}' needs '{needed}'"):
        InsConfig(effects={"states": states})
    InsConfig(effects={"states": states + (needed,)})
    with pytest.raises(ValueError, match=r"unknown effect 'lever_arms'"):
        InsConfig(effects={"states": ("lever_arms",)})
