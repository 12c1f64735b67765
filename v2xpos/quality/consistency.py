"""First parameter: sliding-window deviation and similarity of two aligned streams.

For a window W of n samples and one axis, with reference x and unit under test y:

    RMSE = sqrt( (1/n) sum_{k in W} (y_k - x_k)^2 )                         (deviation)
    PCC  = sum (x_k - mx)(y_k - my) / sqrt( sum (x_k - mx)^2 sum (y_k - my)^2 )  (similarity)

The window series are summarised by the boxplot statistics of Tukey (1977): quartiles Q1, Q3,
median, and whiskers at the most extreme data within 1.5 IQR of the quartiles; plus mean and
standard deviation. PCC series: mean, standard deviation and the 3x3 covariance between axes.

Extensions used by the verdict (documented in docs/quality.md): the per-window mean difference
(bias between units; its spread over the run is the bias stability) and the relative scale factor
as the total-least-squares slope of y on x (errors in both variables; Golub & Van Loan 1980).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.signal import butter, sosfiltfilt


PCC_SNR_MIN = 3.0
"""A window tells two units' similarity on an axis only when the signal there stands out of the
noise by this factor: two healthy units measuring a signal of s.d. s with noise s.d. sigma
correlate with PCC = s^2 / (s^2 + sigma^2); a window s.d. of 3 sigma (s = 2.8 sigma) gives 0.89,
above the warn level (0.75, reached at s = 1.7 sigma). Windows with less signal measure the noise,
not the units."""
PCC_MIN_SIGNAL_WINDOWS = 4
"""Fewest windows with signal on an axis for its median PCC to be a statistic (2.5 s of motion
at the default 1-s windows every 0.5 s)."""


@dataclass
class WindowSeries:
    """Per-window metrics, arrays (n_windows, 3): rmse, pcc, mean_diff (y - x); ref_sd / ut_sd: each
    stream's own s.d. in the window; ref_noise / ut_noise: each stream's white-noise s.d. in the
    window, RMS of the sample-to-sample difference / sqrt(2) (the motion, band-limited far below
    the sample rate, cancels in a one-sample difference; white noise of s.d. sigma gives
    sqrt(2) sigma); t_s: window centres."""
    t_s: np.ndarray
    rmse: np.ndarray
    pcc: np.ndarray
    mean_diff: np.ndarray
    ref_sd: np.ndarray | None = None
    ut_sd: np.ndarray | None = None
    ref_noise: np.ndarray | None = None
    ut_noise: np.ndarray | None = None

    def swapped(self) -> "WindowSeries":
        """The same windows seen from the other stream (difference negated, the streams exchanged)."""
        return WindowSeries(self.t_s, self.rmse, self.pcc, -self.mean_diff, self.ut_sd, self.ref_sd,
                            self.ut_noise, self.ref_noise)

    def difference_sd(self) -> np.ndarray:
        """(n_windows, 3): the s.d. of the difference in each window, sqrt(RMSE^2 - mean_diff^2)
        (RMSE without the window's mean difference, so a constant bias between the units does not
        count)."""
        return np.sqrt(np.maximum(self.rmse ** 2 - self.mean_diff ** 2, 0.0))

    def signal(self, snr_min: float = PCC_SNR_MIN) -> np.ndarray:
        """(n_windows, 3) bool: windows where the quieter stream (per axis, the smaller median
        white-noise s.d. over the run) varies by at least ``snr_min`` times the noise.

        The noise is the smaller of two estimates that each can only err high: the quieter
        stream's one-sample-difference noise (``ref_noise`` / ``ut_noise``; too high when fast
        vibration common to both units passes for noise, as on a quadrotor's frame) and the
        difference's s.d. over sqrt(2) (the median over the windows of ``difference_sd``; exact
        for two healthy units of equal noise, too high when one is faulty).
        So a unit whose output is noise or garbage cannot remove the windows that show it: it is
        judged on the motion its partner saw, and correlates badly there. A stream without any
        noise (a stuck axis) never decides while its partner has some; a window without any
        variation never counts (noiseless simulated units at rest)."""
        if self.ref_noise is None or self.ut_noise is None or not len(self.rmse):
            return np.zeros(self.pcc.shape, dtype=bool)
        noise_ref = np.median(self.ref_noise, axis=0)
        noise_ut = np.median(self.ut_noise, axis=0)
        quiet_is_ref = ((noise_ref <= noise_ut) & (noise_ref > 0.0)) | (noise_ut <= 0.0)
        sd = np.where(quiet_is_ref[None, :], self.ref_sd, self.ut_sd)
        noise = np.minimum(np.where(quiet_is_ref, noise_ref, noise_ut),
                           np.median(self.difference_sd(), axis=0) / np.sqrt(2.0))
        return (sd >= snr_min * noise[None, :]) & (sd > 0.0)

    def median_pcc(self, snr_min: float = PCC_SNR_MIN,
                   min_windows: int = PCC_MIN_SIGNAL_WINDOWS) -> tuple[np.ndarray, np.ndarray]:
        """Per axis: the median PCC over the windows with signal (``signal``), NaN where fewer
        than ``min_windows`` have it, and the number of those windows."""
        sig = self.signal(snr_min)
        n = sig.sum(axis=0)
        med = np.array([float(np.median(self.pcc[sig[:, k], k])) if n[k] >= min_windows else np.nan
                        for k in range(self.pcc.shape[1])])
        return med, n


def window_starts(n_samples: int, window_n: int, step_n: int) -> np.ndarray:
    """Start indices of full windows of window_n samples every step_n samples."""
    if window_n < 2 or step_n < 1 or n_samples < window_n:
        return np.zeros(0, dtype=int)
    return np.arange(0, n_samples - window_n + 1, step_n)


def sliding_window_metrics(t_s: np.ndarray, x: np.ndarray, y: np.ndarray, window_n: int,
                           step_n: int) -> WindowSeries:
    """RMSE, PCC and mean difference per window and axis for (N, 3) streams x (ref), y (ut).

    A window where either signal is constant on an axis has PCC 0 on that axis (no similarity can
    be shown), never NaN.
    """
    x = np.asarray(x, float)
    y = np.asarray(y, float)
    starts = window_starts(len(x), window_n, step_n)
    if len(starts) == 0:
        empty = np.zeros((0, 3))
        return WindowSeries(np.zeros(0), empty, empty, empty, empty, empty, empty, empty)
    idx = starts[:, None] + np.arange(window_n)[None, :]
    X = x[idx]
    Y = y[idx]
    D = Y - X
    rmse = np.sqrt(np.mean(D ** 2, axis=1))
    mean_diff = D.mean(axis=1)
    Xc = X - X.mean(axis=1, keepdims=True)
    Yc = Y - Y.mean(axis=1, keepdims=True)
    num = np.sum(Xc * Yc, axis=1)
    den = np.sqrt(np.sum(Xc ** 2, axis=1) * np.sum(Yc ** 2, axis=1))
    pcc = np.where(den > 1e-300, num / np.maximum(den, 1e-300), 0.0)
    t = np.asarray(t_s, float)[starts + window_n // 2]
    ref_sd = np.sqrt(np.mean(Xc ** 2, axis=1))
    ut_sd = np.sqrt(np.mean(Yc ** 2, axis=1))
    ref_noise = np.sqrt(np.mean(np.diff(X, axis=1) ** 2, axis=1) / 2.0)
    ut_noise = np.sqrt(np.mean(np.diff(Y, axis=1) ** 2, axis=1) / 2.0)
    return WindowSeries(t, rmse, np.clip(pcc, -1.0, 1.0), mean_diff, ref_sd, ut_sd, ref_noise, ut_noise)


def box_stats(values: np.ndarray) -> dict:
    """Tukey boxplot statistics of a 1-D series: upper/lower whisker, quartiles, median, mean, std."""
    v = np.asarray(values, float)
    v = v[np.isfinite(v)]
    if v.size == 0:
        return {k: None for k in ("upper_whisker", "upper_quartile", "median", "lower_quartile",
                                  "lower_whisker", "mean", "std")}
    q1, med, q3 = np.percentile(v, [25, 50, 75])
    iqr = q3 - q1
    hi = v[v <= q3 + 1.5 * iqr]
    lo = v[v >= q1 - 1.5 * iqr]
    return {"upper_whisker": float(hi.max()), "upper_quartile": float(q3), "median": float(med),
            "lower_quartile": float(q1), "lower_whisker": float(lo.min()), "mean": float(v.mean()),
            "std": float(v.std())}


def pcc_stats(pcc: np.ndarray) -> dict:
    """PCC window series (n, 3): per-axis mean and std, and the 3x3 covariance between axes."""
    p = np.asarray(pcc, float)
    if len(p) < 2:
        return {"mean": p.mean(axis=0).tolist() if len(p) else [None] * 3, "std": [None] * 3,
                "covariance": None}
    return {"mean": p.mean(axis=0).tolist(), "std": p.std(axis=0).tolist(),
            "covariance": np.cov(p, rowvar=False).tolist()}


def lowpass(x: np.ndarray, rate_hz: float, cutoff_hz: float, order: int = 4) -> np.ndarray:
    """Zero-phase Butterworth low-pass along axis 0 (cutoff clipped below Nyquist)."""
    fc = min(cutoff_hz, 0.45 * rate_hz)
    if len(x) < 3 * (2 * order + 1):
        return np.asarray(x, float).copy()
    sos = butter(order, fc, fs=rate_hz, output="sos")
    return sosfiltfilt(sos, np.asarray(x, float), axis=0)


def tls_slope(x: np.ndarray, y: np.ndarray) -> float:
    """Total-least-squares slope of y on x (both de-meaned): the direction of the largest
    principal axis of the (x, y) scatter. Unbiased by noise of equal variance in x and y."""
    X = np.stack([x - np.mean(x), y - np.mean(y)], axis=1)
    _, _, Vt = np.linalg.svd(X, full_matrices=False)
    v = Vt[0]
    return float(v[1] / v[0]) if abs(v[0]) > 1e-12 else float("inf")


def relative_scale(x: np.ndarray, y: np.ndarray, rate_hz: float, cutoff_hz: float,
                   min_signal_sd: float) -> np.ndarray:
    """Per-axis relative scale factor y/x (TLS slope of the low-passed signals); NaN on axes whose
    low-passed reference signal has a standard deviation below min_signal_sd (not observable)."""
    xl = lowpass(x, rate_hz, cutoff_hz)
    yl = lowpass(y, rate_hz, cutoff_hz)
    out = np.full(3, np.nan)
    for k in range(3):
        if np.std(xl[:, k]) >= min_signal_sd:
            out[k] = tls_slope(xl[:, k], yl[:, k])
    return out


def robust_range(values: np.ndarray, lo_pct: float = 5.0, hi_pct: float = 95.0) -> np.ndarray:
    """Spread P_hi - P_lo along axis 0 (per column), e.g. of window mean differences."""
    v = np.asarray(values, float)
    if len(v) == 0:
        return np.full(v.shape[1:] or (1,), np.nan)
    lo, hi = np.percentile(v, [lo_pct, hi_pct], axis=0)
    return hi - lo


def longest_constant_run_s(t_s: np.ndarray, x: np.ndarray, active: np.ndarray | None = None) -> np.ndarray:
    """Per axis, the longest time [s] over which the raw samples repeat exactly (a stuck channel;
    a live, noisy sensor changes its output within a few samples even when quantised).

    active: optional boolean mask per sample; only runs of consecutive active samples count (e.g.
    while the unit turns, so that a quiet, coarsely quantised axis at rest is not called stuck).
    """
    x = np.asarray(x, float)
    t = np.asarray(t_s, float)
    out = np.zeros(x.shape[1])
    if len(x) < 2:
        return out
    both = np.ones(len(x) - 1, bool) if active is None else (active[1:] & active[:-1])
    for k in range(x.shape[1]):
        same = (np.diff(x[:, k]) == 0.0) & both
        if not same.any():
            continue
        edges = np.diff(np.concatenate([[0], same.astype(np.int8), [0]]))
        starts = np.flatnonzero(edges == 1)
        ends = np.flatnonzero(edges == -1)
        out[k] = float(np.max(t[ends] - t[starts]))
    return out


def turning_mask(t_s: np.ndarray, gyro_rps: np.ndarray, min_rate_dps: float = 2.0,
                 smooth_s: float = 0.2) -> np.ndarray:
    """Samples where the moving-average angular-rate norm exceeds min_rate_dps."""
    g = np.asarray(gyro_rps, float)
    if len(g) < 3:
        return np.ones(len(g), bool)
    rate = 1.0 / float(np.median(np.diff(np.asarray(t_s, float))))
    n = max(1, int(round(smooth_s * rate)))
    kern = np.ones(n) / n
    sm = np.stack([np.convolve(g[:, i], kern, mode="same") for i in range(3)], axis=1)
    return np.linalg.norm(sm, axis=1) > np.radians(min_rate_dps)
