"""Close-the-loop tests: effects injected in code (never declared) are found by the batch fit.

Cost control: one Estimator per recording (module fixtures): the Jacobian of the baseline is
reused for the injected copies (two replays each)."""
from __future__ import annotations


import numpy as np
import pytest

from sim.calibration_drive import simulated_recording
from v2xpos.diagnose import calibrate as C
from v2xpos.diagnose.inject import (P_ACCEL_SCALE, P_CLOCK_DRIFT, P_GNSS_LATENCY, P_GYRO_SCALE, P_LEVER_ARM, P_MISALIGN,
                                    P_TIME_OFFSET, EffectSet, inject)
from tests.calibrate_cases import SIM_TRUTH, fit_from_baseline, fit_simulated

pytestmark = pytest.mark.slow   # every test fits a 300 s drive: 10-100 CPU-s each

DEG = np.pi / 180.0


# ------------------------------------------------------------------ simulator (known truth)
SIM_TOL = {P_CLOCK_DRIFT: 20.0, P_MISALIGN.start + 1: 0.05 * DEG,
           P_MISALIGN.start + 2: 0.05 * DEG, P_LEVER_ARM.start + 1: 0.07,
           P_GYRO_SCALE.stop - 1: 0.0005}


@pytest.fixture(scope="module")
def sim_fit():
    ds, truth = simulated_recording(300.0, seed=3, effects=SIM_TRUTH, imu_grade="tactical", gnss_rate_hz=10.0)
    est, f, prob = fit_simulated(ds)
    return est, f, prob, truth


def test_sim_effects_found_with_known_truth(sim_fit):
    est, f, prob, truth = sim_fit
    t = truth.to_vector()
    for i, tol in SIM_TOL.items():
        assert abs(f.theta[i] - t[i]) < tol, (i, f.theta[i], t[i], f.sd[i])
        assert abs(f.theta[i]) > 3 * f.sd[i], (i, f.theta[i], f.sd[i])
    # roll is seen only through the level-road rows: estimated, with an honest sd
    assert abs(f.theta[P_MISALIGN.start] - t[P_MISALIGN.start]) < 3 * f.sd[P_MISALIGN.start]


def test_sim_along_track_offset_found(sim_fit):
    """At near-constant speed a time offset moves the predicted antenna along track by -v dt, as a
    forward lever arm does by +l_x; this drive separates them only weakly (docs/calibration.md),
    so the test checks what it determines: l_x - v dt at the mean moving speed."""
    est, f, prob, truth = sim_fit
    g = est.ds.gnss
    speed = np.hypot(g.vel_ned_mps[:, 0], g.vel_ned_mps[:, 1])
    v_mean = float(np.mean(speed[speed > 2.0]))
    est_off = f.theta[P_LEVER_ARM.start] - v_mean * f.theta[P_TIME_OFFSET]
    true_off = truth.gnss_lever_arm_m[0] - v_mean * truth.imu_time_offset_s
    assert abs(est_off - true_off) < 0.03, (est_off, true_off, f.theta[P_TIME_OFFSET], f.theta[P_LEVER_ARM.start])


def test_sim_absent_effects_not_significant(sim_fit):
    est, f, prob, truth = sim_fit
    f = est.confirm(est.ds, f, prob)
    absent = [P_GNSS_LATENCY, P_ACCEL_SCALE.start, P_ACCEL_SCALE.start + 1, P_GYRO_SCALE.start,
              P_GYRO_SCALE.start + 1, P_ACCEL_SCALE.stop - 1]
    assert not f.significant[absent].any(), f.table()
    assert f.significant[[P_MISALIGN.start + 1, P_MISALIGN.start + 2, P_GYRO_SCALE.stop - 1]].all(), f.table()


def test_sim_gnss_latency_found_when_imu_is_synchronised(sim_fit):
    """30 ms GNSS latency on a drive whose IMU timing is declared. Like the IMU offset, the latency
    moves the predicted antenna along track (-v L) as a forward lever arm does, and this drive
    does not separate the two: the test asserts the along-track combination, the timing split
    that the priors impose and that a latency is detected; its size is a documented shortfall
    (the forward lever arm takes part of it, the same bias along l_x - v tau as on the un-injected
    drive, docs/calibration.md; the speed-change drive separates them, next test)."""
    est, f_base, _, truth = sim_fit
    from v2xpos.diagnose.inject import correct
    # an IMU whose timing is declared (synchronised): the known offset and drift are corrected, and
    # the GNSS solutions are tagged 30 ms late; tight timing prior for the IMU, loose for latency
    known = EffectSet(imu_time_offset_s=truth.imu_time_offset_s, imu_clock_drift_ppm=truth.imu_clock_drift_ppm)
    ds_lat = inject(correct(est.ds, known), EffectSet(gnss_latency_s=0.03))
    saved = est.prior_sd.copy()
    est.prior_sd = est.prior_sd.copy()
    est.prior_sd[P_TIME_OFFSET] = 1e-4
    est.prior_sd[P_CLOCK_DRIFT] = 0.1
    est.prior_sd[P_GNSS_LATENCY] = 0.1
    try:
        start = f_base.theta.copy()
        start[[P_TIME_OFFSET, P_CLOCK_DRIFT, P_GNSS_LATENCY]] = 0.0
        f = fit_from_baseline(est, ds_lat, start)
    finally:
        est.prior_sd = saved
    g = est.ds.gnss
    speed = np.hypot(g.vel_ned_mps[:, 0], g.vel_ned_mps[:, 1])
    v_mean = float(np.mean(speed[speed > 2.0]))
    along = f.theta[P_LEVER_ARM.start] - v_mean * (f.theta[P_TIME_OFFSET] + f.theta[P_GNSS_LATENCY])
    along_true = truth.gnss_lever_arm_m[0] - v_mean * 0.03
    info = (f.theta[:3], f.sd[:3], f.theta[P_LEVER_ARM.start], along, along_true)
    assert abs(along - along_true) < 0.03, info
    assert abs(f.theta[P_TIME_OFFSET]) < 0.001, info
    assert f.theta[P_GNSS_LATENCY] > 3 * f.sd[P_GNSS_LATENCY], info


def test_sim_gnss_latency_separated_from_lever_arm_when_speed_changes():
    """30 ms GNSS latency, IMU timing declared (synchronised), on a drive whose cruise speed keeps
    changing (4-19 m/s): the latency moves the antenna along track by -v L, a forward lever arm by
    a constant, so the speed changes separate them -- the latency is found and significant, the
    forward lever arm is not reported. (The IMU offset and the GNSS latency give the same relative
    timing; with neither declared only their sum is identifiable, docs/calibration.md.)"""
    from v2xpos.ins.replay_engine import OutageSchedule
    ds, _ = simulated_recording(300.0, seed=3, effects=EffectSet(gnss_latency_s=0.03), imu_grade="tactical",
                                gnss_rate_hz=10.0, drive="speed_changes")
    ds.notes.update(imu_time_offset_prior_sd_s=1e-3, imu_clock_drift_prior_sd_ppm=1.0, gnss_latency_prior_sd_s=0.1)
    # before/after in the plain profile: in the services' profile the table's IMU noise replaces
    # the online noise meter, and this tactical-grade drive's outages come out 0.41 m after
    # calibration against 0.17 m with the true latency removed (a shortfall of that profile's
    # use of a calibrated noise, not of the fit)
    cal = C.calibrate_dataset(ds, OutageSchedule(15.0, 45.0, 40.0), progress=False, profile="plain")
    f = cal.fit
    info = {r["name"]: (round(r["value"], 4), round(r["sd"], 4), r["significant"]) for r in f.table()}
    assert abs(f.theta[P_GNSS_LATENCY] - 0.03) < 0.005 and f.significant[P_GNSS_LATENCY], info
    assert abs(f.theta[P_TIME_OFFSET]) < 0.001, info
    lx = P_LEVER_ARM.start
    assert not f.significant[lx] and abs(f.theta[lx]) < 3 * f.sd[lx], info
    # the correction does as well as the true one; on this drive `v2xpos replay`'s default filter,
    # with its own online timing state, happens to do better on the uncorrected data (0.74 m against
    # 0.80 m with the true 30 ms removed: the first outage comes before that state has settled)
    from v2xpos.diagnose.inject import correct
    truth = C.metrics_replay(correct(ds, EffectSet(gnss_latency_s=0.03)), OutageSchedule(15.0, 45.0, 40.0), False,
                             profile="plain")
    assert cal.after["outage_h_rms_m"] < truth["outage_h_rms_m"] + 0.02, (cal.before, cal.after, truth)
    # nothing but the latency is reported (until the fit replays were exact at the GNSS epochs a
    # false vertical lever arm of -0.7..-0.9 m at 3-4 sd was; now -0.42 +- 0.22 m, docs/calibration.md)
    others = np.ones(len(f.theta), bool)
    others[P_GNSS_LATENCY] = False
    assert not f.significant[others].any(), info


@pytest.mark.parametrize("seed", [3, 4])
def test_sim_clean_drive_reports_no_effect(seed):
    """A simulated drive with no effect in it: nothing is reported significant. The joint fit alone
    puts the IMU offset and the forward lever arm far out along their common ridge (l_x - v tau ~ 0,
    each ~7 sd: seed 3 -17 ms / -0.19 m, seed 4 +17 ms / +0.18 m); the backward elimination in
    ``Estimator.confirm`` lets each take over the other's part and drops both."""
    ds, _ = simulated_recording(300.0, seed=seed, effects=EffectSet(), imu_grade="tactical", gnss_rate_hz=10.0)
    est, f, prob = fit_simulated(ds)
    f = est.confirm(ds, f, prob)
    assert not f.significant.any(), [r for r in f.table() if r["significant"]]
