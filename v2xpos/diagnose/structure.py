"""Statistical tests for structure left in a residual sequence.

* whiteness: sample autocorrelation and the Ljung-Box portmanteau statistic
  Q = n (n + 2) sum_{k=1..h} rho_k^2 / (n - k), chi-square with h dof under whiteness
  (Ljung & Box 1978, Biometrika 65(2)).
* bias: mean against zero with a t statistic whose sample size is reduced for lag-1
  autocorrelation, n_eff = n (1 - rho1) / (1 + rho1) (AR(1) variance inflation; Wilks 2011,
  Statistical Methods in the Atmospheric Sciences, eq. 5.12).
* correlation with a motion signal: Pearson r, tested with t = r sqrt((n_eff - 2) / (1 - r^2)) and
  n_eff = n (1 - r1 s1) / (1 + r1 s1) from the lag-1 autocorrelations of both series
  (Bretherton et al. 1999, J. Climate 12, eq. 31), plus the least-squares slope and its sd.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
from scipy import stats


@dataclass
class TestResult:
    """A test statistic, its p-value and the decision at the chosen level."""
    name: str
    statistic: float
    p_value: float
    significant: bool
    n: int
    detail: dict

    def as_dict(self) -> dict:
        return asdict(self)


def _finite(*arrays: np.ndarray) -> tuple:
    ok = np.ones(len(arrays[0]), bool)
    for a in arrays:
        ok &= np.isfinite(a)
    return tuple(np.asarray(a, float)[ok] for a in arrays)


def autocorrelation(x: np.ndarray, max_lag: int) -> np.ndarray:
    """Sample autocorrelation rho_1..rho_max_lag of x (mean removed, biased estimator)."""
    (x,) = _finite(np.asarray(x, float))
    x = x - x.mean()
    n = len(x)
    den = float(x @ x)
    if n < 2 or den <= 0:
        return np.zeros(max_lag)
    return np.array([float(x[:-k] @ x[k:]) / den if k < n else 0.0 for k in range(1, max_lag + 1)])


def ljung_box(x: np.ndarray, lags: int | None = None, alpha: float = 0.01) -> TestResult:
    """Ljung-Box whiteness test; significant means the sequence is NOT white."""
    (x,) = _finite(np.asarray(x, float))
    n = len(x)
    h = int(lags or max(1, min(20, n // 5)))
    if n < h + 2:
        return TestResult("ljung_box", float("nan"), float("nan"), False, n, {"lags": h})
    rho = autocorrelation(x, h)
    q = n * (n + 2) * float(np.sum(rho ** 2 / (n - np.arange(1, h + 1))))
    p = float(stats.chi2.sf(q, h))
    return TestResult("ljung_box", q, p, p < alpha, n, {"lags": h, "rho1": float(rho[0])})


def effective_n(n: int, rho1_a: float, rho1_b: float | None = None) -> float:
    """Effective number of independent samples for a mean (one series) or a correlation (two)."""
    prod = rho1_a if rho1_b is None else rho1_a * rho1_b
    prod = float(np.clip(prod, -0.99, 0.99))
    return max(2.0, n * (1.0 - prod) / (1.0 + prod))


def mean_bias(x: np.ndarray, alpha: float = 0.01) -> TestResult:
    """t-test of mean(x) = 0 with the AR(1)-reduced sample size."""
    (x,) = _finite(np.asarray(x, float))
    n = len(x)
    if n < 3:
        return TestResult("mean_bias", float("nan"), float("nan"), False, n, {})
    rho1 = float(autocorrelation(x, 1)[0])
    ne = effective_n(n, max(rho1, 0.0))
    mean = float(x.mean())
    sd_mean = float(x.std(ddof=1)) / np.sqrt(ne)
    t = mean / sd_mean if sd_mean > 0 else 0.0
    p = float(2 * stats.t.sf(abs(t), ne - 1))
    return TestResult("mean_bias", t, p, p < alpha, n, {"mean": mean, "sd_mean": sd_mean, "n_eff": ne})


def correlation(residual: np.ndarray, signal: np.ndarray, alpha: float = 0.01) -> TestResult:
    """Correlation of a residual with a motion signal, significance with the effective sample size.

    detail: r, slope (residual per unit signal, least squares), slope_sd (with n_eff), n_eff.
    """
    y, x = _finite(np.asarray(residual, float), np.asarray(signal, float))
    n = len(y)
    if n < 4 or np.std(x) == 0 or np.std(y) == 0:
        return TestResult("correlation", 0.0, 1.0, False, n, {"r": 0.0, "slope": 0.0, "slope_sd": float("inf")})
    r = float(np.corrcoef(x, y)[0, 1])
    r = float(np.clip(r, -0.999999, 0.999999))
    ry = float(autocorrelation(y, 1)[0])
    rx = float(autocorrelation(x, 1)[0])
    ne = effective_n(n, max(ry, 0.0), max(rx, 0.0))
    t = r * np.sqrt(max(ne - 2, 1.0) / (1 - r * r))
    p = float(2 * stats.t.sf(abs(t), max(ne - 2, 1.0)))
    xc = x - x.mean()
    slope = float(xc @ (y - y.mean()) / (xc @ xc))
    resid = y - y.mean() - slope * xc
    slope_sd = float(np.sqrt((resid @ resid) / max(n - 2, 1) / (xc @ xc) * n / ne))
    return TestResult("correlation", t, p, p < alpha, n, {"r": r, "slope": slope, "slope_sd": slope_sd, "n_eff": ne})
