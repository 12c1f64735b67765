"""Stop detection (``v2xpos.ins.motion.StopDetector``) on generated IMU chunks: a parked vehicle
with idle vibration is static once the window is full, and each of the documented tests on its
own makes it not static."""
from __future__ import annotations

import numpy as np

from v2xpos.ins import InsConfig
from v2xpos.ins.motion import StopDetector

CFG = InsConfig(setup={"platform": "car"})
G_MPS2 = 9.81
CHUNK = CFG.numerics.cov_every
WINDOW_CHUNKS = round(CFG.stops.static_window_s * CFG.constraints.constraint_rate_hz)


def _chunk(rng, acc_sd_mps2=0.02, rate_rps=np.zeros(3), f_extra=np.zeros(3)):
    f = np.array([0.0, 0.0, -G_MPS2]) + f_extra + rng.normal(0.0, acc_sd_mps2, (CHUNK, 3))
    w = rate_rps + rng.normal(0.0, 1e-4, (CHUNK, 3))
    return f, w


def _fill(det, rng, n=WINDOW_CHUNKS, **kw):
    for _ in range(n):
        det.feed(*_chunk(rng, **kw), C_nb=np.eye(3), accel_bias_mps2=np.zeros(3))


def test_parked_is_static_only_once_the_window_is_full():
    rng = np.random.default_rng(3)
    det = StopDetector(CFG)
    _fill(det, rng, WINDOW_CHUNKS - 1)
    assert not det.is_static(0.0, np.zeros(3), np.zeros(3))
    _fill(det, rng, 1)
    assert det.is_static(0.0, np.zeros(3), np.zeros(3))
    assert det.is_static(0.0, np.zeros(3))                  # before the filter has a solution


def test_each_test_alone_rejects_a_stop():
    rng = np.random.default_rng(4)
    cases = {
        "vibration": dict(acc_sd_mps2=3 * CFG.stops.static_acc_std_max_mps2),
        "turning": dict(rate_rps=np.array([0.0, 0.0, 3 * CFG.stops.static_gyro_mean_max_rps])),
        "braking": dict(f_extra=np.array([2 * CFG.stops.static_acc_h_max_mps2, 0.0, 0.0])),
    }
    for name, kw in cases.items():
        det = StopDetector(CFG)
        _fill(det, rng, **kw)
        assert not det.is_static(0.0, np.zeros(3), np.zeros(3)), name
    det = StopDetector(CFG)
    _fill(det, rng)
    assert not det.is_static(0.0, np.zeros(3), np.array([1.5 * CFG.stops.static_max_speed_mps, 0.0, 0.0]))
    # the gyro mean is taken against the bias estimate: a turning rate that is all bias is a stop
    det = StopDetector(CFG)
    bias = np.array([0.0, 0.0, 3 * CFG.stops.static_gyro_mean_max_rps])
    _fill(det, rng, rate_rps=bias)
    assert det.is_static(0.0, bias, np.zeros(3))
    np.testing.assert_allclose(det.mean_rate_rps(), bias, atol=1e-4)


def test_a_recent_gnss_speed_vetoes_and_a_stale_one_does_not():
    rng = np.random.default_rng(5)
    det = StopDetector(CFG)
    _fill(det, rng)
    det.note_gnss_speed(100.0, 2 * CFG.stops.static_max_gnss_speed_mps)
    assert not det.is_static(100.0 + 0.5 * CFG.stops.static_gnss_speed_max_age_s, np.zeros(3), np.zeros(3))
    assert det.is_static(100.0 + 2 * CFG.stops.static_gnss_speed_max_age_s, np.zeros(3), np.zeros(3))
