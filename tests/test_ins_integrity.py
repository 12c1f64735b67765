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
    mon = ConsistencyMonitor(window_s=5.0)
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


def test_consistent_innovations_pass_and_verification_follows_the_protection_level():
    straight = _run_monitor(np.zeros(3), 0.0)
    assert straight.failures == 0
    assert straight.state == VERIFIED                  # no protection level given: nothing to wait for
    straight.set_protection(0.4, 0.25)
    assert straight.state == UNVERIFIED                # the fault-tolerant solution cannot vouch yet
    straight.set_protection(0.2, 0.25)
    assert straight.state == VERIFIED
    assert straight.variance_ratio() == 1.0                # a pessimistic filter is never shrunk


def test_turn_counting_still_gates_verification_when_configured():
    def run(rate_dps: float) -> ConsistencyMonitor:
        mon = ConsistencyMonitor(window_s=5.0, verify_turn_deg=45.0)
        mon.restart(0.0)
        rng = np.random.default_rng(1)
        for k in range(600):
            yaw = math.radians(rate_dps) * 0.1 * k
            c, s = math.cos(yaw), math.sin(yaw)
            C_nb = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
            _feed_velocity(mon, rng, 0.1 * k, C_nb)
            mon.feed_motion(0.1 * k, 0.1, math.radians(rate_dps), 10.0)
        return mon
    assert run(10.0).state == VERIFIED
    # a gentle curve (2 deg/s): the mean test would miss a lever arm of about 1 m, it does not count
    assert run(2.0).state == UNVERIFIED


@pytest.mark.slow
def test_false_alarm_rate_is_per_hour_not_per_window():
    """An hour of exactly consistent 10 Hz position and velocity updates (innovation covariance as
    predicted, not pessimistic): with the per-hour level split over the disjoint blocks (Bonferroni,
    1e-3 per hour) no alarm is expected; a per-window level of 3 sd (0.27 %) over the 4,320 tests of
    an hour would give about 12."""
    rng = np.random.default_rng(7)
    mon = ConsistencyMonitor(window_s=5.0, false_alarm_per_hour=1e-3)
    mon.restart(0.0)
    assert mon.mean_z_limit == pytest.approx(5.17, abs=0.01)
    C_nb = np.eye(3)
    S = np.eye(3)
    z_blocks = []
    for k in range(36000):
        t = 0.1 * k
        for kind in ("gnss_pos", "gnss_vel"):
            d = rng.normal(0.0, 1.0, 3)
            mon.feed_update(kind, t, float(d @ d), 3, d, S, C_nb)
        if k % 50 == 49:
            z_blocks.append(mon.last_statistic.get("gnss_pos_mean", (math.nan,))[0])
    assert mon.failures == 0
    z = np.asarray([x for x in z_blocks if x == x])
    assert len(z) > 600 and 0.85 < float(np.std(z)) < 1.15      # the block means are N(0, 1)


@pytest.mark.parametrize("reverify,final", [(False, INCONSISTENT), (True, VERIFIED)])
def test_a_failure_is_released_once_the_evidence_is_gone(reverify, final):
    """A body-frame bias for 20 s, then consistent innovations: the failure is lifted only after
    ``release_windows`` consecutive blocks pass at the 1 % level (the hysteresis), or never
    (``reverify`` off)."""
    rng = np.random.default_rng(4)
    mon = ConsistencyMonitor(window_s=5.0, reverify=reverify, release_windows=6)
    mon.restart(0.0)
    S = np.eye(3) * 0.02 ** 2
    released_at = None
    for k in range(900):
        t = 0.1 * k
        bias = np.array([0.03, 0.0, 0.0]) if t < 20.0 else np.zeros(3)
        d = rng.normal(0.0, 0.01, 3) + bias
        mon.feed_update("gnss_pos", t, float(d @ np.linalg.solve(S, d)), 3, d, S, np.eye(3))
        _feed_velocity(mon, rng, t, np.eye(3))
        if mon.failures and not mon.failed and released_at is None:
            released_at = t
    assert mon.failures > 0
    assert mon.state == final
    if reverify:
        assert released_at >= 20.0 + 6 * 5.0 - 0.2     # six quiet blocks after the bias ended
        assert mon.releases == 1


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
    flt = InsFilter(InsConfig(setup={"platform": "car"}))
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


def test_a_consistency_failure_changes_no_state_and_reopens_a_verified_setup():
    """A failed innovation test says the covariance does not describe the innovations: the filter
    changes no state (a jump would move every vehicle's reported point), and a set-up verified on
    an earlier drive goes back to the prior of an unverified one."""
    from v2xpos.ins import InsConfig, InsFilter
    flt = InsFilter(InsConfig(setup={"platform": "car", "lever_arm_sd_m": 0.02},
                              integrity={"fault_tolerant_solution": True, "setup_verified": True}))
    flt.initialize(100.0, np.array([0.7, 0.2, 300.0]), np.array([10.0, 0.0, 0.0]), np.zeros(3))
    assert flt.separation.prior == flt.cfg.integrity.setup_change_prior
    P, nav = flt.P.copy(), flt.nav.copy()
    flt._on_inconsistency()
    np.testing.assert_array_equal(flt.P, P)
    np.testing.assert_array_equal(flt.nav, nav)
    assert flt.separation.prior == flt.cfg.integrity.setup_fault_prior
    assert flt.counts["verification_reopened"] == 1


def test_protection_levels_known_answers():
    """The bound L of (1 - w1) P(|e0| > L) + w1 P(|s + ew| > L) = risk: the fault-free quantile
    when w1 = 0; the separation plus the twin's quantile at risk / w1 when the fault is certain."""
    from scipy.stats import norm
    from v2xpos.ins.integrity import protection_levels
    pl = protection_levels(1e-5, 0.0, np.array([0.02]), np.array([0.0]), np.array([0.5]))
    assert pl[0] == pytest.approx(0.02 * norm.isf(0.5e-5), rel=1e-6)
    pl = protection_levels(1e-5, 1.0, np.array([0.02]), np.array([0.4]), np.array([0.05]))
    assert pl[0] == pytest.approx(0.4 + 0.05 * norm.isf(1e-5), rel=1e-3)
    # a prior too small to matter leaves the fault-free bound; one that matters widens it
    small = protection_levels(1e-5, 1e-7, np.array([0.02]), np.array([0.0]), np.array([0.5]))
    large = protection_levels(1e-5, 1e-3, np.array([0.02]), np.array([0.0]), np.array([0.5]))
    assert small[0] == pytest.approx(0.02 * norm.isf(0.5e-5), rel=0.05)
    assert large[0] > 1.0
    assert np.isinf(protection_levels(1e-5, 1.0, np.array([0.02]), np.array([0.0]), np.array([1e5])))[0]


def test_horizontal_tail_is_the_2d_normal_outside_a_circle():
    """``horizontal_tail`` against the non-central chi-square with 2 degrees of freedom (isotropic
    errors, down to 1e-6) and against 4e6 samples (elongated, correlated, off-centre errors); the
    horizontal protection level against its closed form and the per-axis bound it improves on."""
    from scipy.stats import ncx2
    from v2xpos.ins.integrity import horizontal_protection_level, horizontal_tail, protection_levels
    for sd, mean, L in [(0.02, (0.0, 0.0), 0.1), (0.02, (0.05, 0.03), 0.15), (0.5, (0.1, -0.2), 1.9),
                        (0.07, (0.0, 0.0), 0.3), (0.3, (0.2, 0.1), 0.3)]:
        exact = ncx2.sf(L ** 2 / sd ** 2, 2, (mean[0] ** 2 + mean[1] ** 2) / sd ** 2) if any(mean) \
            else math.exp(-L ** 2 / (2 * sd ** 2))
        assert horizontal_tail(L, np.array(mean), np.eye(2) * sd ** 2) == pytest.approx(exact, rel=1e-9)
    rng = np.random.default_rng(1)
    for cov, mean, L in [(np.diag([0.01 ** 2, 0.07 ** 2]), (0.02, 0.05), 0.2),
                         (np.array([[0.05 ** 2, 0.03 ** 2], [0.03 ** 2, 0.02 ** 2]]), (0.1, -0.05), 0.2),
                         (np.diag([0.5 ** 2, 0.003 ** 2]), (0.0, 0.0), 1.0)]:
        e = rng.multivariate_normal(mean, cov, 4_000_000)
        p_mc = float(np.mean(np.hypot(e[:, 0], e[:, 1]) > L))
        p = horizontal_tail(L, np.array(mean), cov)
        assert abs(p - p_mc) < 5 * math.sqrt(p * (1 - p) / len(e))
    for sd in (0.01, 0.05):                               # fault-free, circular: sd sqrt(2 ln(1/risk))
        pl = horizontal_protection_level(1e-5, 0.0, np.eye(2) * sd ** 2, np.zeros(2), np.eye(2))
        assert pl == pytest.approx(sd * math.sqrt(2 * math.log(1e5)), rel=1e-4)
        axes = protection_levels(0.5e-5, 0.0, np.array([sd, sd]), np.zeros(2), np.ones(2))
        assert pl < math.hypot(axes[0], axes[1])
    # the fault dominates: the separation plus the twin's own radial quantile
    pl = horizontal_protection_level(1e-5, 1.0, np.eye(2) * 0.01 ** 2, np.array([0.4, 0.0]), np.eye(2) * 0.02 ** 2)
    assert horizontal_tail(pl, np.array([0.4, 0.0]), np.eye(2) * 0.02 ** 2) == pytest.approx(1e-5, rel=1e-3)
    assert 0.4 < pl < 0.4 + 0.02 * 4.8
    assert math.isinf(horizontal_protection_level(1e-5, 1.0, np.eye(2), np.zeros(2), np.eye(2) * 1e10))


def _toy_truth(T: int, rate_rps: float, lever_error_m: np.ndarray, seed: int):
    """A 2-D car at constant speed on a circle of yaw rate ``rate_rps`` with its GNSS antenna at
    l_true = declared + lever_error in the body frame: returns per-epoch (C_nb, true state)."""
    rng = np.random.default_rng(seed)
    out = []
    for k in range(T):
        yaw = rate_rps * 0.1 * k
        c, s = math.cos(yaw), math.sin(yaw)
        C = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        out.append((C, rng.normal(0.0, 0.01, 3)))
    return out


def _toy_run(lever_error_m, rate_rps: float = 0.15, T: int = 1200, seed: int = 0, prior: float = 1e-3):
    """Linear error-state model of ``FaultTolerantSolution``'s use in the filter: states position
    (random walk), velocity, lever arm; GNSS antenna position h = r + C l at 10 Hz (1 cm). The main
    filter holds the declared lever arm (sd 2 cm); the truth has ``lever_error_m`` more.
    Returns, per epoch, the main filter's position error, the protection level and the alarm, the
    fault-tolerant solution's position next to an independent wide-prior Kalman filter's, and the
    probability of the set-up fault."""
    from v2xpos.ins.integrity import FaultTolerantSolution
    from v2xpos.ins.ekf import propagate_covariance, transition_matrix
    n, L = 9, 6
    A = np.zeros((n, n))
    A[0:3, 3:6] = np.eye(3) * 0.1
    q = np.zeros(n)
    q[3:6] = 0.002 ** 2                      # velocity random walk [m/s/sqrt(s)]^2: an IMU-aided car
    x_true = np.zeros(n)
    x_true[L:L + 3] = lever_error_m            # errors relative to the declared lever arm
    P = np.diag([0.01 ** 2] * 3 + [0.01 ** 2] * 3 + [0.02 ** 2] * 3)
    est = np.zeros(n)
    sep = FaultTolerantSolution(L, fault_sd_m=0.5, false_alarm_per_hour=1e-3, prior=prior, integrity_risk=1e-5,
                                test_every_s=1.0)
    sep.start(P, np.eye(3), np.zeros(3))
    P_ref, est_ref = sep.P.copy(), np.zeros(n)   # the independent wide-prior filter
    Phi = np.eye(n) + A
    rows = []
    rng = np.random.default_rng(seed + 100)
    for k, (C, noise) in enumerate(_toy_truth(T, rate_rps, lever_error_m, seed)):
        x_true = Phi @ x_true
        x_true[3:6] += rng.normal(0.0, math.sqrt(q[3] * 0.1), 3)
        sep.propagate(transition_matrix(A), q, 0.1)
        P = propagate_covariance(P, A.copy(), q, 0.1)
        P_ref = propagate_covariance(P_ref, A.copy(), q, 0.1)
        est, est_ref = Phi @ est, Phi @ est_ref
        H = np.zeros((3, n))
        H[:, 0:3] = np.eye(3)
        H[:, L:L + 3] = C
        z = H @ x_true + noise
        R = np.eye(3) * 0.01 ** 2
        d = H @ est - z                      # prediction minus measurement (filter convention)
        S = H @ P @ H.T + R
        K = P @ H.T @ np.linalg.inv(S)
        dx = K @ d
        sep.update(H, d, R, dx, float(d @ np.linalg.solve(S, d)), S)
        est = est - dx
        P = P - K @ H @ P
        K_ref = P_ref @ H.T @ np.linalg.inv(H @ P_ref @ H.T + R)
        est_ref = est_ref + K_ref @ (z - H @ est_ref)
        P_ref = P_ref - K_ref @ H @ P_ref
        alarm = sep.test(0.1 * k, np.eye(n)[0:3], P, 0.0) if sep.due(0.1 * k) else False
        rows.append((float(np.hypot(*(est - x_true)[0:2])), sep.protection_m, alarm,
                     (est - sep.w)[0:3].copy(), est_ref[0:3].copy(), sep.fault_probability))
    return rows


def test_fault_tolerant_solution_is_the_wide_prior_filter():
    """The separation filter, kept in the main filter's error coordinates, reproduces a Kalman
    filter run independently with the wide lever-arm prior."""
    rows = _toy_run(np.array([0.3, -0.2, 0.0]), T=300)
    for _, _, _, ft, ref, _ in rows:
        np.testing.assert_allclose(ft, ref, atol=1e-9)


@pytest.mark.slow
def test_no_fault_no_alarm_and_the_protection_level_falls_with_turning():
    rows = _toy_run(np.zeros(3), rate_rps=0.15)
    assert not any(r[2] for r in rows)
    assert rows[5][1] > 0.3                         # before turning: the lever arm is open
    assert rows[-1][1] < 0.3                        # after 120 s at 8.6 deg/s: pinned down
    assert max(r[5] for r in rows) == pytest.approx(1e-3)   # no evidence for a fault: the prior
    straight = _toy_run(np.zeros(3), rate_rps=0.0, T=600)
    assert straight[-1][1] > 0.3                    # a straight road never verifies a lever arm...
    verified = _toy_run(np.zeros(3), rate_rps=0.0, T=600, prior=1e-6)
    assert all(r[1] < 0.3 for r in verified[20:])   # ...but a set-up verified before needs no turn


@pytest.mark.slow
@pytest.mark.parametrize("error", [(0.3, 0.0), (0.0, -0.5), (0.4, 0.4), (0.15, -0.1)])
def test_an_undeclared_lever_arm_is_found_before_the_protection_level_vouches(error):
    """Integrity: at every epoch before the first alarm, a protection level within the alert limit
    bounds the main filter's real error (the undetected lever arm never makes a verified, wrong
    result); the data make the fault probable as the car turns."""
    rows = _toy_run(np.array([error[0], error[1], 0.0]), rate_rps=0.15)
    first_alarm = next((k for k, r in enumerate(rows) if r[2]), len(rows))
    assert first_alarm < len(rows) or math.hypot(*error) < 0.2
    for err, pl, *_ in rows[:first_alarm]:
        if pl <= 0.3:
            assert err <= pl
    if first_alarm < len(rows):
        assert rows[first_alarm][5] > 0.5


def _twin_lever_sd_after(corrected_heading_rad: float, turned_rad: float, first_estimates: bool,
                          heading_sd_rad: float = 0.0) -> float:
    """Horizontal lever-arm sd of the twin after 30 s of 10 Hz antenna fixes (1 cm) on a car whose
    body turns by ``turned_rad`` while the main filter's heading estimate is corrected by
    ``corrected_heading_rad`` (the convergence after a drive-off), applied in equal steps as the
    position rows' attitude corrections. The position rows are the filter's
    (``updates.gnss_position``: ``[I, [C l x], C]`` on position, attitude, lever arm, at the
    attitude before the correction); ``first_estimates``: the twin is told the attitude after each
    correction (as ``InsFilter`` tells it), so it takes the lever-arm columns at the gyro-propagated
    attitude (``FaultTolerantSolution.update``); ``heading_sd_rad``: the main filter's heading sd
    it is told with each correction."""
    from v2xpos.ins.ekf import ATT, POS
    from v2xpos.ins.integrity import FaultTolerantSolution
    from v2xpos.rotation import exp_so3, skew
    n, L, steps = 12, 9, 300
    P = np.diag([0.01 ** 2] * 3 + [0.01 ** 2] * 3 + [0.005 ** 2, 0.005 ** 2, 0.05 ** 2] + [0.02 ** 2] * 3)
    lever = np.array([0.0, 0.0, -1.5])
    C_est = exp_so3(np.array([0.0, 0.0, corrected_heading_rad]))
    sep = FaultTolerantSolution(L, fault_sd_m=0.5)
    sep.start(P, C_est, np.zeros(3))
    rng = np.random.default_rng(0)
    for _ in range(steps):
        body_turn = exp_so3(np.array([0.0, 0.0, turned_rad / steps]))
        C_est = C_est @ body_turn                                 # the strapdown: body side
        H = np.zeros((3, n))
        H[:, POS:POS + 3] = np.eye(3)
        H[:, ATT:ATT + 3] = skew(C_est @ lever)
        H[:, L:L + 3] = C_est
        R = np.eye(3) * 0.01 ** 2
        dx = np.zeros(n)
        dx[ATT + 2] = -corrected_heading_rad / steps              # the heading converges to the truth
        C_after = exp_so3(dx[ATT:ATT + 3]) @ C_est                # the correction: NED side
        sep.propagate(np.eye(n), np.zeros(n), 0.1)
        sep.update(H, rng.normal(0.0, 0.01, 3), R, dx, C_nb_after=C_after if first_estimates else None,
                   heading_sd_rad=heading_sd_rad)
        C_est = C_after
    return float(math.sqrt(0.5 * (sep.P[L, L] + sep.P[L + 1, L + 1])))


def test_the_twin_sees_the_lever_arm_only_through_a_turn_the_gyros_measured():
    """First-estimates lever-arm columns (docs/integrity.md, "The lever arm is seen only through
    rotation the IMU measured"): a heading estimate corrected by 3 deg while the car drives straight
    gives a linear twin lever-arm information the data do not hold (the columns turn as if the car
    had); taken at the gyro-propagated attitude they give none, and a real 90 deg turn still pins
    the lever arm down."""
    straight_corrected = math.radians(3.0)
    assert _twin_lever_sd_after(straight_corrected, 0.0, first_estimates=False) < 0.2   # the mechanism
    assert _twin_lever_sd_after(straight_corrected, 0.0, first_estimates=True) > 0.49
    assert _twin_lever_sd_after(0.0, 0.0, first_estimates=True) > 0.49
    turned = _twin_lever_sd_after(straight_corrected, math.pi / 2, first_estimates=True)
    assert turned < 0.05
    assert turned == pytest.approx(_twin_lever_sd_after(0.0, math.pi / 2, first_estimates=True), rel=0.05)


def test_the_first_estimates_anchor_follows_corrections_outside_the_small_angle_regime():
    """Corrections made while the main filter's heading sd is above ``FEJ_MAX_HEADING_SD_RAD`` are
    a convergence the linearisation does not describe: the anchor follows them (the twin behaves as
    without first estimates); at or below it the anchor ignores them."""
    from v2xpos.ins.integrity import FEJ_MAX_HEADING_SD_RAD
    corrected = math.radians(3.0)
    wide = _twin_lever_sd_after(corrected, 0.0, first_estimates=True, heading_sd_rad=2 * FEJ_MAX_HEADING_SD_RAD)
    assert wide == pytest.approx(_twin_lever_sd_after(corrected, 0.0, first_estimates=False), rel=1e-6)
    assert _twin_lever_sd_after(corrected, 0.0, first_estimates=True, heading_sd_rad=FEJ_MAX_HEADING_SD_RAD) > 0.49


def test_the_anchor_is_not_told_an_attitude_without_the_heading_sd():
    """The first-estimates anchor needs the regime of each correction: an attitude without the
    main filter's heading sd is rejected, not taken as the small-angle regime."""
    from v2xpos.ins.integrity import FaultTolerantSolution
    n, L = 12, 9
    sep = FaultTolerantSolution(L, fault_sd_m=0.5)
    sep.start(np.eye(n) * 1e-4, np.eye(3), np.zeros(3))
    H = np.zeros((3, n))
    H[:, :3] = np.eye(3)
    with pytest.raises(ValueError, match="heading_sd_rad"):
        sep.update(H, np.zeros(3), np.eye(3) * 1e-4, np.zeros(n), C_nb_after=np.eye(3))
    sep.update(H, np.zeros(3), np.eye(3) * 1e-4, np.zeros(n), C_nb_after=np.eye(3), heading_sd_rad=0.01)
    sep.update(H, np.zeros(3), np.eye(3) * 1e-4, np.zeros(n))           # no anchor: plain columns


def test_an_exclusion_takes_the_fault_tolerant_solution():
    """RAIM exclusion: the separation test's alarm makes the filter take the twin's state and
    covariance (the estimate that never relied on the declared lever arm)."""
    from v2xpos.ins.filter import InsConfig, InsFilter
    flt = InsFilter(InsConfig(setup={"platform": "car", "lever_arm_sd_m": 0.02},
                              integrity={"undeclared_lever_arm_sd_m": 0.5, "fault_tolerant_solution": True}))
    flt.initialize(100.0, np.array([0.7, 0.2, 300.0]), np.array([10.0, 0.0, 0.0]), np.zeros(3))
    sep = flt.separation
    assert sep.active
    i = flt.layout.at("lever_arm")
    assert flt.P[i, i] == pytest.approx(0.02 ** 2) and sep.P[i, i] == pytest.approx(0.25)
    sep.w[0:3] = [0.3, -0.2, 0.0]                    # it thinks the main position is 0.3 m north, 0.2 m west off
    P_ft = sep.P.copy()
    north_before = flt.nav[0]
    flt._exclude_declaration()
    assert flt.counts["lever_arm_excluded"] == 1 and sep.excluded and sep.fault_probability == 0.0
    np.testing.assert_allclose(flt.P, P_ft)
    r_m = 6.36e6                                       # ~ meridian radius at 40 deg (only the sign and size matter)
    assert (north_before - flt.nav[0]) * r_m == pytest.approx(0.3, rel=0.01)
    assert not np.any(sep.w)                          # one estimate now: nothing left to separate


def _yaw_var_after(scale_model: str, yaw_rate_rps: float, seconds: float = 20.0, rate_hz: float = 100.0):
    """Yaw-error variance of a filter started level at 10 m/s heading north with a known heading,
    after ``seconds`` of IMU samples at a constant yaw rate (no GNSS, no vehicle constraints, so the
    covariance is the time update alone); and the filter. scale_model: the gyro scale error is
    "estimated" (a state), "consider" (Schmidt consider state) or "none" (white noise only)."""
    from v2xpos.ins import InsConfig, InsFilter
    from v2xpos.ins.ekf import ATT
    cfg = InsConfig(setup={"platform": "car"},
                    effects={"states": ("gyro_scale",) if scale_model == "estimated" else (),
                             "effect_initial_sd": {"gyro_scale": 0.01}},
                    imu={"consider_gyro_scale": scale_model == "consider", "gyro_noise_rps_rthz": 1e-4},
                    constraints={"constraints_on_request": True}, stops={"apply_static_calibration": False})
    flt = InsFilter(cfg)
    flt.initialize(100.0, np.array([0.7, 0.2, 300.0]), np.array([10.0, 0.0, 0.0]), np.zeros(3),
                   att_sd_rad=np.radians([0.1, 0.1, 0.1]))
    n = int(seconds * rate_hz)
    t = 100.0 + np.arange(1, n + 1) / rate_hz
    acc = np.tile([0.0, 10.0 * yaw_rate_rps, -9.80665], (n, 1))    # centripetal, body y; gravity up on z
    gyro = np.tile([0.0, 0.0, yaw_rate_rps], (n, 1))
    flt.process_imu_batch(t, acc, gyro)
    flt._flush_covariance()
    return flt.P[ATT + 2, ATT + 2], flt


@pytest.mark.parametrize("scale_model", ["estimated", "consider"])
def test_an_unknown_gyro_scale_grows_the_yaw_sigma_in_turns_only(scale_model):
    """A gyro scale error s makes the heading error s * (heading turned): with its uncertainty in the
    covariance (estimated state or Schmidt consider state) the yaw variance grows by
    (sd_s * yaw turned)^2 in a turn, and not at all on a straight, where the heading sd stays that of
    the white gyro noise."""
    straight_s, _ = _yaw_var_after(scale_model, 0.0)
    straight_w, _ = _yaw_var_after("none", 0.0)
    assert straight_s == pytest.approx(straight_w, rel=1e-6)
    rate = 0.2                                                       # 20 s at 11.5 deg/s: 229 deg
    turn_s, flt = _yaw_var_after(scale_model, rate)
    turn_w, _ = _yaw_var_after("none", rate)
    turned_rad = rate * 20.0
    assert turn_s - turn_w == pytest.approx((0.01 * turned_rad) ** 2, rel=0.05)
    i = flt.layout.at("gyro_scale")
    np.testing.assert_allclose(np.sqrt(np.diag(flt.P)[i:i + 3]), 0.01)


def test_the_service_filter_estimates_the_gyro_scale_and_keeps_heading_noise_at_the_measured_one():
    """``ins_config(service=True)``: gyro scale estimated (the datasheet-class prior, or the
    calibration's value and sd), heading white noise the measured one while roll/pitch keep the
    margin (docs/integrity.md); the meter applies the factor per body axis."""
    from v2xpos.datasets.calibration import CalibrationEntry, CalibrationTable
    from v2xpos.ins.calibrated import ins_config
    from v2xpos.ins.effects import DEFAULT_INITIAL_SD
    cfg = ins_config("car", np.eye(3), np.zeros(3), 0.02, service=True)
    assert "gyro_scale" in cfg.effects.states
    assert cfg.effects.effect_initial_sd["gyro_scale"] == DEFAULT_INITIAL_SD["gyro_scale"]
    cal = CalibrationTable({"gyro_scale": CalibrationEntry((0.0, 0.0, -0.007), (0.0, 0.0, 0.0005))}, source="x.toml")
    cfg_cal = ins_config("car", np.eye(3), np.zeros(3), 0.02, calibration=cal, service=True)
    assert list(cfg_cal.effects.states).count("gyro_scale") == 1
    np.testing.assert_allclose(cfg_cal.effects.effect_initial_sd["gyro_scale"], [0.0, 0.0, 0.0005])
    assert "gyro_scale" not in ins_config("car", np.eye(3), np.zeros(3), 0.02).effects.states
    rng = np.random.default_rng(5)
    dt = 0.01
    meter = ImuNoiseMeter(window_s=10.0, gyro_scale=(7.0, 7.0, 1.0))
    n_true = 1e-4
    t = np.arange(3000) * dt
    meter.feed(t, rng.normal(0.0, n_true / math.sqrt(dt), (3000, 3)), np.zeros((3000, 3)))
    q = np.zeros(15)
    meter.apply(q, np.eye(3))
    np.testing.assert_allclose(np.sqrt(q[6:9]), [7 * n_true, 7 * n_true, n_true], rtol=0.1)


def test_consider_states_are_never_estimated_and_their_covariance_is_exact():
    """``kalman_update`` with consider states: no correction and no variance reduction for them,
    and the covariance is the Joseph form of the gain with their rows zeroed (valid for any gain)."""
    from v2xpos.ins.ekf import kalman_update
    rng = np.random.default_rng(3)
    n = 7
    A = rng.normal(size=(n, n))
    P = A @ A.T + np.eye(n)
    H = rng.normal(size=(2, n))
    R = np.eye(2) * 0.2
    d = rng.normal(size=2)
    c = slice(4, 7)
    dx, P_new, _, S, ok = kalman_update(P, H, d, R, None, consider=c)
    assert ok and np.all(dx[c] == 0.0)
    np.testing.assert_allclose(P_new[c, c], P[c, c])
    K = P @ H.T @ np.linalg.inv(S)
    K[c] = 0.0
    I_KH = np.eye(n) - K @ H
    np.testing.assert_allclose(P_new, I_KH @ P @ I_KH.T + K @ R @ K.T, atol=1e-12)
    _, P_opt, _, _, _ = kalman_update(P, H, d, R, None)
    assert np.all(np.diag(P_new) >= np.diag(P_opt) - 1e-12)          # not estimating costs information


def test_the_protection_level_keeps_the_evidence_once_it_was_there():
    """``FaultTolerantSolution.peak_fault_probability``: after the data made the set-up fault
    likely, a later collapse of the likelihood ratio (a model that does not describe the vehicle,
    docs: dev_like seed 9) does not bring the protection level back to the prior's; a right
    declaration, whose posterior never rose, is unaffected; an exclusion resolves it."""
    from v2xpos.ins.integrity import FaultTolerantSolution
    n, L = 9, 6
    P = np.diag([0.01 ** 2] * 6 + [0.02 ** 2] * 3)

    def pl_after(log_lrs):
        sep = FaultTolerantSolution(L, prior=1e-3)
        sep.start(P, np.eye(3), np.zeros(3))
        sep.w = np.zeros(n)
        sep.w[0] = 0.05                                    # a small separation on body x
        for k, llr in enumerate(log_lrs):
            sep.log_lr = llr
            sep.test(float(k), np.eye(n)[0:3], P, 0.0)
        return sep

    quiet = pl_after([-3.0, -3.0])
    assert quiet.peak_fault_probability == pytest.approx(1e-3) and quiet.last["fault_probability"] == pytest.approx(1e-3)
    forgot = pl_after([9.0, -3.0])                          # P(H1) 0.89, then back at the prior
    assert forgot.fault_probability == pytest.approx(1e-3)
    assert forgot.last["fault_probability"] == pytest.approx(forgot.peak_fault_probability)
    assert forgot.peak_fault_probability > 0.8
    assert forgot.protection_m > quiet.protection_m + 0.5  # the bound still holds H1 likely
    forgot.exclude(P)
    forgot.test(3.0, np.eye(n)[0:3], P, 0.0)
    assert forgot.last["fault_probability"] == 0.0        # excluded: the twin is the main filter
