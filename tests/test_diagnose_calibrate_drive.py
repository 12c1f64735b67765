"""Close-the-loop tests on the real drive_0708: effects injected in code (never declared) are found
by the batch fit relative to the un-injected drive.

Cost control: one Estimator per recording (module fixtures): the Jacobian of the baseline is
reused for the injected copies (two replays each)."""
from __future__ import annotations


import numpy as np
import pytest

from v2xpos.diagnose import calibrate as C
from v2xpos.diagnose import identify
from v2xpos.diagnose.inject import (N_PARAMS, P_GNSS_LATENCY, P_GYRO_SCALE, P_LEVER_ARM, P_MISALIGN, P_TIME_OFFSET,
                                    EffectSet, inject)
from tests.calibrate_cases import fit_from_baseline
from tests.shared_data import SHARED_DATA, require_shared

pytestmark = pytest.mark.slow   # every test fits a 300 s drive: 10-100 CPU-s each

DATA = SHARED_DATA
DRIVE = DATA / "drive_0708" / "dataset.toml"

DEG = np.pi / 180.0


# ------------------------------------------------------------------ drive_0708 (real data)
@pytest.fixture(scope="module")
def drive_baseline():
    require_shared(DRIVE)
    from v2xpos.datasets import load_dataset
    ds = load_dataset(DRIVE)
    est = C.Estimator(ds)
    theta = est.gauss_newton(est.coarse(), iterations=1)
    f = fit_from_baseline(est, ds, theta)
    return est, f, theta


INJECTED = {P_TIME_OFFSET: 0.005, P_MISALIGN.start: 0.3 * DEG, P_MISALIGN.start + 1: -0.3 * DEG,
            P_MISALIGN.start + 2: 0.3 * DEG, P_GYRO_SCALE.stop - 1: 0.005, P_LEVER_ARM.start + 1: 0.1}
FOUND = (P_MISALIGN.start + 1, P_GYRO_SCALE.stop - 1)
TOLERANCE = {P_TIME_OFFSET: 0.0025, P_MISALIGN.start: 0.1 * DEG, P_MISALIGN.start + 1: 0.1 * DEG,
             P_MISALIGN.start + 2: 0.15 * DEG, P_GYRO_SCALE.stop - 1: 0.0015, P_LEVER_ARM.start + 1: 0.05}


@pytest.mark.parametrize("sign", [+1.0, -1.0])
def test_drive_injected_effects_found_relative_to_baseline(drive_baseline, sign):
    est, f0, start = drive_baseline
    inj = np.zeros(N_PARAMS)
    for i, v in INJECTED.items():
        inj[i] = sign * v
    ds_inj = inject(est.ds, EffectSet.from_vector(inj))
    f = fit_from_baseline(est, ds_inj, start)
    diff = f.theta - f0.theta
    report = {int(i): (round(float(diff[i]), 5), round(float(f.sd_stat[i]), 5)) for i in np.flatnonzero(est.active)}
    # each injected effect: estimated within the tolerance or, where the drive barely reveals it
    # (time offset, roll), within 3 of its own sd; the well-observed ones must also be found (> 3 sd)
    # (with all effects at once the stamp shift trades off against the clock drift; alone it is
    # held to its tolerance: test_drive_single_effect_recovered_to_tolerance)
    for i, v in INJECTED.items():
        assert abs(diff[i] - sign * v) < max(TOLERANCE[i], 3 * f.sd_stat[i]), (i, sign * v, report)
    # found: beyond 3 standard errors, i.e. the sd without the small-sample t factor of its degrees
    # of freedom (``identify.normal_equivalent_factor``). The paired difference is close to the
    # injected value itself, so "found" holds only for an effect several standard errors large: the
    # drive's turns reveal the gyro z scale to ~0.1 %, so 0.3 % sat at 3 se (a coin toss) and the
    # injection is 0.5 %; the single-effect test below keeps 0.3 % to its tolerance
    se = f.sd_stat / identify.normal_equivalent_factor(f.dof)
    for i in FOUND:
        assert abs(diff[i]) > 3 * se[i], (i, report, float(diff[i] / se[i]))
    # no false positives: the parameters not injected stay where the baseline put them
    z = identify.compare(f, f0, use_stat=True)
    others = [i for i in np.flatnonzero(est.active) if i not in INJECTED and i != P_GNSS_LATENCY]
    assert np.all(z[others] < 3.0), report


@pytest.mark.parametrize("param, value", [
    (P_TIME_OFFSET, +0.005), (P_TIME_OFFSET, -0.005), (P_MISALIGN.start, 0.3 * DEG),
    (P_MISALIGN.start + 1, -0.3 * DEG), (P_MISALIGN.start + 2, 0.3 * DEG), (P_GYRO_SCALE.stop - 1, -0.003),
    (P_LEVER_ARM.start + 1, 0.1)], ids=["stamps+5ms", "stamps-5ms", "roll", "pitch", "yaw", "gyro_z", "antenna_y"])
def test_drive_single_effect_recovered_to_tolerance(drive_baseline, param, value):
    """One undeclared effect injected into the real drive: the fit moves that parameter by the
    injected amount within its tolerance, and no other parameter by 1.5 sd or more (the antenna
    y case moves the IMU offset and the clock drift by 1.2-1.3 sd since the fit replays are exact
    at the GNSS epochs, docs/calibration.md; every other case stays below 1 sd). The absolute
    values are known only to their sd (e.g. the IMU time offset to ~7 ms), but the change between
    two fits of the same drive is a paired comparison in which the drive's own noise cancels."""
    est, f0, start = drive_baseline
    inj = np.zeros(N_PARAMS)
    inj[param] = value
    f = fit_from_baseline(est, inject(est.ds, EffectSet.from_vector(inj)), start)
    diff = f.theta - f0.theta
    assert abs(diff[param] - value) < TOLERANCE[param], (param, value, diff[param])
    others = [i for i in np.flatnonzero(est.active) if i != param]
    assert np.all(np.abs(diff[others]) < 1.5 * f.sd_stat[others]), {int(i): float(diff[i] / f.sd_stat[i]) for i in others}
