"""Shared pieces of the close-the-loop tests (tests/test_diagnose_calibrate*.py): the known-truth
effects of the simulated drives and the fit of an injected copy started from a baseline."""
from __future__ import annotations

import numpy as np

from v2xpos.diagnose import calibrate as C
from v2xpos.diagnose.inject import EffectSet

SIM_TRUTH = EffectSet(imu_time_offset_s=0.005, imu_clock_drift_ppm=50.0,
                      imu_misalignment_rad=np.radians([0.3, -0.3, 0.3]),
                      gnss_lever_arm_m=np.array([0.1, -0.1, 0.0]), gyro_scale=np.array([0.0, 0.0, 0.003]))
"""Effects injected into the simulated drives, none of them declared."""


def fit_from_baseline(est: C.Estimator, ds, theta_start: np.ndarray):
    """The refined fit of ``ds`` (an injected copy of ``est.ds``) from ``theta_start``, reusing the
    estimator's baseline Jacobian (three refinement passes)."""
    f, _, _ = est.refine(ds, theta_start, iterations=3)
    return f


def fit_simulated(ds):
    """(estimator, joint fit, problem) of a simulated drive: coarse start, two Gauss-Newton passes,
    one exact replay."""
    est = C.Estimator(ds)
    theta = est.gauss_newton(est.coarse(), iterations=2)
    f, prob, _ = est.refine(ds, theta, iterations=0)
    return est, f, prob
