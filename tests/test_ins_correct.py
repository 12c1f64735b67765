"""``InsFilter.predict`` / ``correct``: a measurement model written outside the library goes through
the filter's gated update as it is (docs/extending.md, section 3).

The model here is a barometer-like antenna height: z = h_antenna + v, v ~ N(0, sd^2). With the
error state dx = estimate - truth (position block NED, metres), the antenna height of the estimate
is h_imu - (C_nb l)_D, so d = h_est - z and the row of H is -1 in the down-position column (the
attitude's part, [C l x], is a few mm here and left out). Fed the withheld GNSS heights during a
GNSS outage, it must hold the vertical error where the free inertial solution drifts."""
from __future__ import annotations

import math

import numpy as np

from sim.calibration_drive import simulated_recording
from v2xpos.ins import InsFilter
from v2xpos.ins.driver import CONSTRAINT, DriverHook, InsDriver, push_dataset
from v2xpos.ins.ekf import POS
from v2xpos.ins.profiles import dataset_config
from v2xpos.ins.updates import Measurement

BARO_SD_M = 0.05


def height_measurement(f: InsFilter, z_antenna_h_m: float, sd_m: float) -> Measurement:
    """(H, d, R) of an antenna-height reading (module docstring)."""
    H = np.zeros((1, f.layout.n))
    H[0, POS + 2] = -1.0
    d = np.array([f.antenna_lla()[2] - z_antenna_h_m])
    return Measurement(H, d, np.array([[sd_m ** 2]]))


class OutageHeightError(DriverHook):
    """The antenna height error against the withheld GNSS height at each epoch of the outage."""

    def __init__(self):
        self.errors_m: list[float] = []

    def on_gnss_epoch(self, f, t_s, k, used):
        if not used and f.initialized:
            self.errors_m.append(float(f.antenna_lla()[2] - self.heights[k]))


def _outage_height_errors(with_barometer: bool) -> tuple[np.ndarray, InsFilter]:
    ds, _ = simulated_recording(150.0, seed=1, imu_grade="automotive", gnss_rate_hz=10.0)
    t_gnss = np.asarray(ds.gnss.t_s, float)
    t_out0, t_out1 = t_gnss[0] + 80.0, t_gnss[0] + 110.0
    f = InsFilter(dataset_config(ds))
    hook = OutageHeightError()
    hook.heights = np.asarray(ds.gnss.lla, float)[:, 2]
    drv = InsDriver(f, complete=True, hooks=[hook])
    inside = lambda t: t_out0 <= t < t_out1    # noqa: E731
    push_dataset(drv, ds, gnss_used=lambda t: not inside(t))
    if with_barometer:
        for t, h in zip(t_gnss, hook.heights):
            if inside(t):
                drv.push_mark(CONSTRAINT, float(t) + 1e-4,
                              lambda f, h=float(h): f.correct("barometer", f.t_s, height_measurement(f, h, BARO_SD_M)))
    drv.run()
    return np.asarray(hook.errors_m), f


def test_a_model_from_outside_holds_the_height_in_an_outage():
    free, _ = _outage_height_errors(False)
    aided, f = _outage_height_errors(True)
    assert len(free) == len(aided) > 250
    rms = lambda e: float(np.sqrt(np.mean(e ** 2)))    # noqa: E731
    assert f.counts["barometer"] > 250 and f.counts.get("barometer_rejected", 0) == 0
    assert rms(aided) < 3 * BARO_SD_M, (rms(aided), rms(free))
    assert rms(aided) < 0.5 * rms(free), (rms(aided), rms(free))


def test_a_malformed_measurement_is_counted_and_not_used():
    ds, _ = simulated_recording(30.0, seed=2, imu_grade="automotive", gnss_rate_hz=10.0)
    f = InsFilter(dataset_config(ds))
    drv = InsDriver(f, complete=True)
    push_dataset(drv, ds)
    drv.run()
    assert f.initialized
    before = (f.nav.copy(), f.P.copy())
    n = f.layout.n
    bad = [(np.zeros((1, n + 1)), np.zeros(1), np.eye(1)),                 # H does not fit the layout
           (np.zeros((1, n)), np.array([math.nan]), np.eye(1)),            # non-finite residual
           (np.zeros((1, n)), np.zeros(1), -np.eye(1)),                    # R not positive definite
           (np.zeros((2, n)), np.zeros(2), np.array([[1.0, 0.5], [0.0, 1.0]])),   # R not symmetric
           "not a measurement"]
    for m in bad:
        r = f.correct("probe", f.t_s, m)
        assert not r.accepted and r.reason == "malformed probe measurement"
    assert f.counts["malformed_inputs"] == len(bad) and "probe" not in f.counts
    np.testing.assert_array_equal(f.nav, before[0])
    np.testing.assert_array_equal(f.P, before[1])
