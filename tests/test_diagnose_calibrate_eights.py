"""Close-the-loop tests on a simulated calibration drive (figure-eights at six speeds).

Cost control: one Estimator per recording (module fixtures): the Jacobian of the baseline is
reused for the injected copies (two replays each)."""
from __future__ import annotations


import numpy as np
import pytest

from sim.calibration_drive import simulated_recording
from v2xpos.diagnose.inject import (N_PARAMS, PARAM_NAMES, P_ACCEL_SCALE, P_CLOCK_DRIFT, P_GNSS_LATENCY, P_GYRO_SCALE,
                                    P_LEVER_ARM, P_MISALIGN, P_TIME_OFFSET, EffectSet, inject)
from tests.calibrate_cases import SIM_TRUTH, fit_from_baseline, fit_simulated

pytestmark = pytest.mark.slow   # every test fits a 300 s drive: 10-100 CPU-s each


@pytest.fixture(scope="module")
def eight_fit():
    """The known-truth effects on a calibration drive: figure-eights at six speeds (6-15 m/s)."""
    ds, truth = simulated_recording(300.0, seed=3, effects=SIM_TRUTH, imu_grade="tactical", gnss_rate_hz=10.0,
                                    drive="figure_eights")
    est, f, prob = fit_simulated(ds)
    return est, f, prob, truth


def test_sim_calibration_drive_separates_offset_and_forward_lever_arm(eight_fit):
    """Turning at several speeds separates a time offset (lateral velocity residual v w tau) from a
    forward lever arm (w l_x), which the urban drive at one speed confounds: the forward lever arm
    is found, the 5 ms offset is estimated within its sd (300 s of figure-eights do not reach 3 sd
    for 5 ms), and the effects present are reported while the absent ones are not."""
    import copy
    est, f_joint, prob, truth = eight_fit
    t = truth.to_vector()
    f = est.confirm(est.ds, copy.deepcopy(f_joint), prob)
    info = [(r["name"], round(r["value"], 5), round(r["sd"], 5), r["significant"]) for r in f.table()]
    lx = P_LEVER_ARM.start
    assert abs(f_joint.theta[P_TIME_OFFSET] - t[P_TIME_OFFSET]) < min(0.003, 3 * f_joint.sd[P_TIME_OFFSET]), info
    assert abs(f.theta[lx] - t[lx]) < 0.04 and f.significant[lx], info
    present = [P_CLOCK_DRIFT, P_MISALIGN.start + 1, P_MISALIGN.start + 2, lx, lx + 1, P_GYRO_SCALE.stop - 1]
    assert f.significant[present].all(), info
    for i in present:
        assert abs(f.theta[i] - t[i]) < 3 * f.sd[i], (PARAM_NAMES[i], info)
    absent = [P_GNSS_LATENCY, lx + 2, P_GYRO_SCALE.start, P_GYRO_SCALE.start + 1,
              *range(P_ACCEL_SCALE.start, P_ACCEL_SCALE.stop)]
    assert not f.significant[absent].any(), info


@pytest.mark.parametrize("param, value, tol", [(P_TIME_OFFSET, +0.005, 0.001), (P_TIME_OFFSET, -0.005, 0.001),
                                               (P_LEVER_ARM.start, +0.1, 0.015), (P_LEVER_ARM.start, -0.1, 0.015)],
                         ids=["stamps+5ms", "stamps-5ms", "antenna_x+0.1", "antenna_x-0.1"])
def test_sim_calibration_drive_paired_offset_and_antenna(eight_fit, param, value, tol):
    """IMU stamps shifted or the antenna moved forward on top of the known-truth effects, fitted
    against the un-shifted fit of the same drive (as for drive_0708): the shifted parameter moves by
    the injected amount within its tolerance, every other one by less than its sd."""
    est, f0, prob, truth = eight_fit
    inj = np.zeros(N_PARAMS)
    inj[param] = value
    f = fit_from_baseline(est, inject(est.ds, EffectSet.from_vector(inj)), f0.theta)
    diff = f.theta - f0.theta
    assert abs(diff[param] - value) < tol, (param, value, diff[param])
    others = [i for i in np.flatnonzero(est.active) if i != param]
    assert np.all(np.abs(diff[others]) < f.sd_stat[others]), {int(i): float(diff[i] / f.sd_stat[i]) for i in others}
