"""Dual-antenna heading in the filter: at a standstill start the heading is pending (never a guess)
until a moving-base receiver's baseline azimuth sets it; afterwards headings are measurements."""
from __future__ import annotations

import math

import numpy as np
import pytest

from v2xpos.ins import InsFilter
from v2xpos.ins.calibrated import ins_config
from v2xpos.types import FixStatus

LLA = np.array([math.radians(48.1), math.radians(11.6), 520.0])
LEVER_M = np.array([0.4, -0.2, -1.3])
G_MPS2 = 9.80665


def _parked_filter(seconds: float = 12.0) -> InsFilter:
    """A car standing level, IMU 100 Hz, RTK fixes 10 Hz: started at the stop, heading pending."""
    f = InsFilter(ins_config("car", np.eye(3), LEVER_M, 0.02, service=True))
    rng = np.random.default_rng(3)
    for k in range(1, int(seconds * 100) + 1):
        t = k * 0.01
        f.process_imu(t, np.array([0.0, 0.0, -G_MPS2]) + rng.normal(0, 0.02, 3), rng.normal(0, 2e-4, 3))
        if k % 10 == 0:
            f.update_gnss(t, LLA, np.full(3, 0.02), FixStatus.FIXED, vel_ned_mps=np.zeros(3),
                          vel_sd_ned_mps=np.full(3, 0.03))
    return f


def _antenna_ned_m(f: InsFilter) -> np.ndarray:
    """The antenna point (IMU point + C l, l the filter's lever-arm estimate) in NED metres from LLA."""
    from v2xpos import geo
    return geo.lla_to_ned(f.nav[:3], LLA) + f.C_nb @ f.fx.lever_arm_m


@pytest.mark.parametrize("baseline_body_m, heading_deg, yaw_deg", [
    ([1.0, 0.0, 0.0], 120.0, 120.0),        # baseline along the car
    ([0.0, 1.2, 0.0], 30.0, -60.0),         # across the car, to the right: the car heads 90 deg left of it
])
def test_a_baseline_azimuth_sets_the_pending_heading_at_a_stop(baseline_body_m, heading_deg, yaw_deg):
    f = _parked_filter()
    assert f.initialized and not f.heading_known and not f.nav_state().attitude_ok
    antenna_before = _antenna_ned_m(f)
    r = f.update_heading(f.t_s, math.radians(heading_deg), math.radians(0.2), np.asarray(baseline_body_m))
    assert r.accepted and f.heading_known and f.nav_state().attitude_ok
    yaw = math.degrees(float(f.nav_state().rpy_rad[2]))
    assert abs((yaw - yaw_deg + 180) % 360 - 180) < 0.05
    # the antenna stays where the fixes put it: the IMU point moved with the turned lever arm
    np.testing.assert_allclose(_antenna_ned_m(f), antenna_before, atol=1e-6)
    assert math.degrees(f.nav_state().att_sd_rad[2]) == pytest.approx(0.2, rel=0.05)


def test_later_headings_are_measurements_that_pull_the_yaw_and_shrink_its_sd():
    f = _parked_filter()
    f.update_heading(f.t_s, math.radians(10.0), math.radians(1.0), np.array([1.0, 0.0, 0.0]))
    sd_before = f.nav_state().att_sd_rad[2]
    for _ in range(20):
        r = f.update_heading(f.t_s, math.radians(10.5), math.radians(1.0), np.array([1.0, 0.0, 0.0]))
        assert r.accepted
    # the vehicle's yaw (the baseline is fixed to the vehicle; at a stop nothing tells the IMU's
    # yaw from its mounting, so the correction is shared between them)
    yaw = math.degrees(float(f.nav_state().rpy_rad[2]))
    assert 10.3 < yaw < 10.55          # 21 equal-weight looks, 20 at 10.5 deg: mean 10.48
    assert f.nav_state().att_sd_rad[2] < sd_before / 3
    assert f.counts["heading"] == 20 and f.counts["heading_sets"] == 1


def test_a_malformed_heading_is_counted_and_changes_nothing():
    f = _parked_filter(seconds=11.0)
    C = f.C_nb.copy()
    for args in [(f.t_s, float("nan"), 0.01, [1, 0, 0]), (f.t_s, 1.0, 0.0, [1, 0, 0]),
                 (f.t_s, 1.0, 0.01, [0, 0, 1]), (f.t_s, 1.0, 0.01, "x")]:
        r = f.update_heading(*args)
        assert not r.accepted
    assert f.counts["malformed_inputs"] == 4 and not f.heading_known
    np.testing.assert_array_equal(f.C_nb, C)


def test_a_heading_turn_turns_the_models_accelerations_with_it():
    """The models' kinematic accelerations are NED vectors of the heading they were integrated
    with: a turn of the attitude about down (the heading reset at a drive-off, the dual-antenna
    heading at a stop) turns them by the same rotation, as it turns the tilt error."""
    from v2xpos.rotation import rot_z
    f = InsFilter()
    f.acc_ned_mps2 = np.array([1.5, 0.0, 0.1])
    f.acc_strapdown_ned_mps2 = np.array([1.4, 0.2, 0.0])
    f._turn_about_down(rot_z(math.pi / 2))
    np.testing.assert_allclose(f.acc_ned_mps2, [0.0, 1.5, 0.1], atol=1e-12)
    np.testing.assert_allclose(f.acc_strapdown_ned_mps2, [-0.2, 1.4, 0.0], atol=1e-12)
