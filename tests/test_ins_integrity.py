"""The filter's integrity pieces (issue 15, docs/integrity.md): the consistency test, the IMU noise
measured from the samples, the covariance of the reported quantities and the reaction to a failed
test. Each test builds its input from a known law and checks the statistic against it."""
from __future__ import annotations

import math

import numpy as np
import pytest

from v2xpos.ins.consistency import INCONSISTENT, UNVERIFIED, VERIFIED, ConsistencyMonitor
from v2xpos.ins.noise import ImuNoiseMeter, density_from_mean_square, second_differences


def _run_monitor(bias_body_m: np.ndarray, yaw_rate_rps: float, seconds: float = 60.0, seed: int = 0,
                 sd_m: float = 0.01, predicted_sd_m: float = 0.02) -> ConsistencyMonitor:
    """10 Hz 3-row GNSS updates of a filter whose innovations are N(0, sd^2 I) plus a body-frame
    bias, while the car turns at a constant rate at 10 m/s; the filter predicts ``predicted_sd_m``
    (twice the real spread by default: the measured normalised innovation RMS of the tuned filter on
    clean generated pairs is about 0.5, docs/integrity.md)."""
    rng = np.random.default_rng(seed)
    mon = ConsistencyMonitor(window_s=5.0, false_alarm=1e-4, verify_turn_deg=45.0)
    mon.restart(0.0)
    S = np.eye(3) * predicted_sd_m ** 2
    yaw = 0.0
    for k in range(int(seconds * 10)):
        t = 0.1 * k
        yaw += yaw_rate_rps * 0.1
        c, s = math.cos(yaw), math.sin(yaw)
        C_nb = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        d = rng.normal(0.0, sd_m, 3) + C_nb @ bias_body_m
        nis = float(d @ np.linalg.solve(S, d))
        mon.feed_update("gnss_pos", t, nis, 3, d, S, C_nb)
        _feed_velocity(mon, rng, t, C_nb)
        mon.feed_motion(t, 0.1, yaw_rate_rps, 10.0)
    return mon


def _feed_velocity(mon: ConsistencyMonitor, rng, t: float, C_nb: np.ndarray, sd_mps: float = 0.025) -> None:
    """A consistent (pessimistic x2) GNSS velocity update: it sets the test's velocity sd."""
    S = np.eye(3) * (2 * sd_mps) ** 2
    d = rng.normal(0.0, sd_mps, 3)
    mon.feed_update("gnss_vel", t, float(d @ np.linalg.solve(S, d)), 3, d, S, C_nb)


def test_consistent_innovations_pass_and_verify_only_after_turning():
    straight = _run_monitor(np.zeros(3), 0.0)
    assert straight.failures == 0
    assert straight.state == UNVERIFIED            # no turning: nothing tested that a lever arm would show
    turning = _run_monitor(np.zeros(3), math.radians(10.0))
    assert turning.failures == 0
    assert turning.state == VERIFIED
    assert turning.variance_ratio() == 1.0                 # a pessimistic filter is never shrunk
    # 10 deg/s: the test finds (4.28 x 0.05 m/s) / (0.17 rad/s x sqrt(50)) = 0.17 m of lever arm
    assert turning.detectable_lever_arm_m(math.radians(10.0)) == pytest.approx(0.17, abs=0.01)
    # a gentle curve (2 deg/s for 60 s, 120 deg in all) would hide 0.9 m: it does not verify
    gentle = _run_monitor(np.zeros(3), math.radians(2.0))
    assert gentle.failures == 0 and gentle.state == UNVERIFIED


def test_a_body_frame_bias_fails_the_mean_test_and_stays_inconsistent_while_it_lasts():
    # a bias of one predicted sd along body x: each update's NIS is about 1.25 per dof (a NIS test
    # alone passes it), the window mean is ~7 sd off
    mon = _run_monitor(np.array([0.02, 0.0, 0.0]), math.radians(10.0))
    assert mon.failures > 0
    assert mon.state == INCONSISTENT


def test_a_large_innovation_scale_fails_the_nis_test():
    rng = np.random.default_rng(3)
    mon = ConsistencyMonitor(window_s=5.0, false_alarm=1e-4)
    mon.restart(0.0)
    for k in range(200):
        d = rng.normal(0.0, 2.0, 3)               # innovations twice the sd the filter predicts
        mon.feed_update("gnss_pos", 0.1 * k, float(d @ d), 3)
    assert mon.failures > 0 and mon.state == INCONSISTENT
    assert mon.variance_ratio() == pytest.approx(4.0, rel=0.3)


@pytest.mark.parametrize("rate_hz", [100.0, 150.0])
def test_noise_meter_measures_a_known_white_noise_density(rate_hz):
    gyro_density, accel_density = 8.7e-5, 1.0e-3
    rng = np.random.default_rng(1)
    n = int(60 * rate_hz)
    dt = 1.0 / rate_hz
    t = np.arange(n) * dt
    # a smooth vehicle motion under the noise: it must not read as noise
    motion = np.c_[0.3 * np.sin(0.5 * t), 0.1 * np.cos(0.2 * t), 0.2 * np.sin(t)]
    w = motion + rng.normal(0.0, gyro_density / math.sqrt(dt), (n, 3))
    f = 2.0 * motion + rng.normal(0.0, accel_density / math.sqrt(dt), (n, 3))
    meter = ImuNoiseMeter(window_s=20.0)
    for a in range(0, n, 37):                     # chunks of odd size: the tail between chunks is used
        meter.feed(t[a:a + 37], w[a:a + 37], f[a:a + 37])
    g, acc = meter.densities()
    np.testing.assert_allclose(g, gyro_density, rtol=0.08)
    np.testing.assert_allclose(acc, accel_density, rtol=0.08)
    # the same estimator as a one-shot function (the calibration's)
    d2 = second_differences(w)
    assert float(density_from_mean_square(np.mean(d2 ** 2), dt)) == pytest.approx(gyro_density, rel=0.08)


def test_noise_meter_only_lowers_the_configured_density():
    meter = ImuNoiseMeter(window_s=10.0, gyro_scale=7.0, accel_scale=1.0, gyro_max_rps_rthz=3e-3,
                          accel_max_mps2_rthz=3e-2)
    rng = np.random.default_rng(2)
    dt = 0.01
    t = np.arange(2000) * dt
    meter.feed(t, rng.normal(0.0, 1e-3 / math.sqrt(dt), (2000, 3)), rng.normal(0.0, 1e-1 / math.sqrt(dt), (2000, 3)))
    q = np.zeros(15)
    meter.apply(q, np.eye(3))
    np.testing.assert_allclose(q[6:9], 3e-3 ** 2)          # 7 x 1e-3 above the configured 3e-3: capped
    np.testing.assert_allclose(q[3:6], 3e-2 ** 2)          # 1e-1 above 3e-2: capped


def test_reported_vehicle_yaw_sd_uses_the_misalignment_correlation():
    """NHC fixes the *vehicle* heading: IMU-body yaw error and yaw misalignment are strongly
    anti-correlated, and the vehicle yaw error phi_D + dm_yaw has a far smaller sd than either."""
    from v2xpos.ins.ekf import ATT
    from v2xpos.ins import InsConfig, InsFilter
    from v2xpos.ins.reported import reported_covariance, reported_jacobian
    flt = InsFilter(InsConfig(platform="car"))
    i = flt.layout.at("misalignment")
    assert i >= 0
    P = np.eye(flt.layout.n) * 1e-6
    sd_body, rho = math.radians(0.5), -0.99
    P[ATT + 2, ATT + 2] = P[i + 2, i + 2] = sd_body ** 2
    P[ATT + 2, i + 2] = P[i + 2, ATT + 2] = rho * sd_body ** 2
    J = reported_jacobian(flt.layout, np.eye(3), np.zeros(3), np.zeros(3), np.zeros(3), np.zeros(3))
    C = reported_covariance(P, J)
    expected = math.sqrt(2 * sd_body ** 2 * (1 + rho))
    assert math.sqrt(C[8, 8]) == pytest.approx(expected, rel=1e-6)
    assert math.sqrt(C[8, 8]) < 0.2 * sd_body


def test_a_failed_test_reopens_the_horizontal_lever_arm():
    from v2xpos.ins import InsConfig, InsFilter
    flt = InsFilter(InsConfig(platform="car", lever_arm_sd_m=0.02, undeclared_lever_arm_sd_m=0.5,
                              reopen_on_inconsistency=True))
    i = flt.layout.at("lever_arm")
    before = np.diag(flt.P)[i:i + 3].copy()
    flt._on_inconsistency()
    after = np.diag(flt.P)[i:i + 3]
    np.testing.assert_allclose(after[:2], 0.25)
    assert after[2] == before[2]
    assert flt.counts["lever_arm_reopened"] == 1
    k = flt.layout.at("gnss_vel_latency")               # the other effects back to their priors
    assert flt.P[k, k] == pytest.approx(flt.cfg.effect_initial_sd["gnss_vel_latency"] ** 2)
    flt._on_inconsistency()                                 # already open: not reset again
    assert flt.counts["lever_arm_reopened"] == 1


@pytest.mark.parametrize("reverify,final", [(False, INCONSISTENT), (True, VERIFIED)])
def test_a_failure_is_latched_unless_reverification_is_configured(reverify, final):
    """A bias for 20 s, then consistent innovations while the car keeps turning: the failure stays
    (latched, the default) or is lifted by 45 deg of passing turns (``reverify``)."""
    rng = np.random.default_rng(4)
    mon = ConsistencyMonitor(window_s=5.0, verify_turn_deg=45.0, reverify=reverify)
    mon.restart(0.0)
    S = np.eye(3) * 0.02 ** 2
    rate = math.radians(10.0)
    for k in range(600):
        t = 0.1 * k
        c, s = math.cos(rate * t), math.sin(rate * t)
        C_nb = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        bias = C_nb @ np.array([0.03, 0.0, 0.0]) if t < 20.0 else np.zeros(3)
        d = rng.normal(0.0, 0.01, 3) + bias
        mon.feed_update("gnss_pos", t, float(d @ np.linalg.solve(S, d)), 3, d, S, C_nb)
        _feed_velocity(mon, rng, t, C_nb)
        mon.feed_motion(t, 0.1, rate, 10.0)
    assert mon.failures > 0
    assert mon.state == final
