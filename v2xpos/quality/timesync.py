"""Time sync between IMU units: one time grid, clock offsets estimated from the data.

All streams carry GPS seconds (``v2xpos.timebase`` maps device clocks, UTC and GPS week/TOW onto
that axis). What remains between two units of one vehicle is an unknown offset of their clocks. It
is estimated from the data with ``v2xpos.timebase.estimate_offset_xcorr`` applied to the low-passed
norm of the angular rate, |w|, which does not depend on how each unit is mounted, so the offset
is found before the attitude alignment.
"""
from __future__ import annotations

import numpy as np

from v2xpos.timebase import estimate_offset_xcorr
from v2xpos.types import ImuData

from .consistency import lowpass


def median_rate_hz(t_s: np.ndarray) -> float:
    """Median sample rate [Hz] of a time series."""
    return float(1.0 / np.median(np.diff(np.asarray(t_s, float))))


def common_grid(units: dict[str, ImuData], rate_hz: float | None = None,
                margin_s: float = 0.0) -> np.ndarray:
    """Uniform time grid [s] over the overlap of all units, shrunk by margin_s at both ends,
    at rate_hz (default: the fastest unit's median rate)."""
    t0 = max(float(u.t_s[0]) for u in units.values()) + margin_s
    t1 = min(float(u.t_s[-1]) for u in units.values()) - margin_s
    if rate_hz is None:
        rate_hz = max(median_rate_hz(u.t_s) for u in units.values())
    if t1 <= t0:
        raise ValueError("the units do not overlap in time (after the margin for clock offsets)")
    return t0 + np.arange(int(np.floor((t1 - t0) * rate_hz)) + 1) / rate_hz


def resample(t_src_s: np.ndarray, x: np.ndarray, t_dst_s: np.ndarray) -> np.ndarray:
    """Linear interpolation of the (N, 3) series x from t_src_s onto t_dst_s."""
    return np.stack([np.interp(t_dst_s, t_src_s, x[:, k]) for k in range(x.shape[1])], axis=1)


def gyro_norm_offset_s(ref: ImuData, ut: ImuData, max_lag_s: float = 0.2,
                       cutoff_hz: float = 10.0) -> tuple[float, float]:
    """Clock offset of the unit under test against the reference [s] and the peak correlation.

    Returns ``offset_s`` with ``|w_ut|(t + offset_s) ~ |w_ref|(t)``: the unit-under-test sample
    stamped t + offset_s was taken at the reference's instant t (offset > 0: ut stamps late).
    """
    fr = median_rate_hz(ref.t_s)
    fu = median_rate_hz(ut.t_s)
    nr = lowpass(np.linalg.norm(ref.gyro_rps, axis=1)[:, None], fr, cutoff_hz)[:, 0]
    nu = lowpass(np.linalg.norm(ut.gyro_rps, axis=1)[:, None], fu, cutoff_hz)[:, 0]
    res = estimate_offset_xcorr(ref.t_s, nr, ut.t_s, nu, max_lag_s=max_lag_s,
                                rate_hz=max(fr, fu))
    return res.offset_s, res.peak_corr


def vector_offset_s(t_s: np.ndarray, x: np.ndarray, y: np.ndarray, max_lag_s: float = 0.05,
                    cutoff_hz: float = 10.0, differentiate: bool = True) -> float:
    """Refined clock offset [s] of two aligned (N, 3) series on one uniform grid t_s.

    The cross-correlations of the low-passed, de-meaned axes are summed (axes with more motion
    weigh more), the peak is refined by a parabola through its neighbours. With differentiate,
    the time derivatives are correlated instead (pre-whitening: slowly varying differences such
    as bias drift no longer pull the broad peak of smooth vehicle motion, and the peak narrows). Same sign convention as
    ``gyro_norm_offset_s``: y(t + offset) ~ x(t).
    """
    rate = median_rate_hz(t_s)
    xl = lowpass(x - x.mean(axis=0), rate, cutoff_hz)
    yl = lowpass(y - y.mean(axis=0), rate, cutoff_hz)
    if differentiate:
        xl = np.gradient(xl, axis=0)
        yl = np.gradient(yl, axis=0)
    n = len(xl)
    L = max(1, int(np.ceil(max_lag_s * rate)))
    if n < 4 * L:
        raise ValueError("vector_offset_s: series shorter than 4 x max lag")
    core = xl[L:n - L]
    c = np.array([np.sum(core * yl[L + k:n - L + k]) for k in range(-L, L + 1)])
    k = int(np.argmax(c))
    frac = 0.0
    if 0 < k < len(c) - 1:
        den = c[k - 1] - 2.0 * c[k] + c[k + 1]
        if den < 0.0:
            frac = 0.5 * (c[k - 1] - c[k + 1]) / den
    return float((k - L + frac) / rate)
