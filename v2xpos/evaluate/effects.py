"""The sensor's undeclared effects -- latency tau, range bias b_r, mounting yaw delta -- with their
sds and significance, by the same estimator and decision as ``v2xpos calibrate``
(``v2xpos.diagnose.identify``: MAP step, the largest of white / HAC / jackknife variances with
their degrees of freedom, significance at the t(dof) equivalent of a 3-sigma test and a positive
cross-validated gain between the two halves of the run).

Residuals (measurement model in ``associate``): per associated pair two rows,
rho_r = (r_meas - r_ref(t - tau) - b_r) / sigma_r and
rho_az = wrap(az_meas - az_ref(t - tau) + delta) / sigma_az, whose Jacobian in theta is
[[ r_dot / sigma_r, -1 / sigma_r, 0], [az_dot / sigma_az, 0, 1 / sigma_az]] (the reference's
range and azimuth rates at t - tau). sigma_r, sigma_az: robust scales (1.4826 MAD, Rousseeuw &
Croux 1993) of the residuals, re-estimated at each step.

Latency is not linear over a wide range, so a coarse search comes first (``coarse_latency``): over
a grid of tau, the spread of the range residuals and of the azimuth residuals (MADs about their
medians, so that a bias does not move it) of the candidate pairs, minimised; Gauss-Newton then
refines it with the other effects.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from v2xpos.diagnose import identify

from .associate import Geometry, geometry_at, wrap
from .config import SensorConfig
from .objects import ObjectList
from .reference import Reference

NAMES = ("latency_s", "range_bias_m", "mount_yaw_rad")
PRIOR_SD = np.array([1.0, 10.0, 0.5])
"""Priors wide enough to be no information (1 s, 10 m, 29 deg): the estimates come from the data."""

MAD_TO_SD = 1.4826
COARSE_MAX_PAIRS = 6000
"""The coarse latency search uses at most this many candidate pairs (evenly spread in time)."""


def mad(x: np.ndarray) -> float:
    x = x[np.isfinite(x)]
    if not len(x):
        return float("nan")
    return float(MAD_TO_SD * np.median(np.abs(x - np.median(x))))


def coarse_latency(objs: ObjectList, rows: np.ndarray, tgt: np.ndarray, ref: Reference, targets: list[str],
                   cfg: SensorConfig) -> tuple[float, np.ndarray, np.ndarray]:
    """tau minimising the residual spread of the candidate pairs (module docstring): a 10 ms grid
    over [-max/3, max], then 1 ms around the best. Returns (tau, grid, cost)."""
    if len(rows) > COARSE_MAX_PAIRS:
        pick = np.linspace(0, len(rows) - 1, COARSE_MAX_PAIRS).astype(int)
        rows, tgt = rows[pick], tgt[pick]
    r_m = np.hypot(objs.x_m[rows], objs.y_m[rows])
    az_m = np.arctan2(objs.y_m[rows], objs.x_m[rows])
    t = objs.t_s[rows]

    def cost(tau: float) -> float:
        r_ref = np.full(len(rows), np.nan)
        az_ref = np.full(len(rows), np.nan)
        for k, tid in enumerate(targets):
            m = tgt == k
            if m.any():
                g = geometry_at(ref, [tid], cfg, t[m] - tau)
                r_ref[m] = np.where(g.ok[0], g.r[0], np.nan)
                az_ref[m] = np.where(g.ok[0], g.az[0], np.nan)
        e_r = r_m - r_ref
        e_az = wrap(az_m - az_ref)
        ok = np.isfinite(e_r) & np.isfinite(e_az)
        if ok.sum() < 10:
            return np.inf
        scale = float(np.median(r_m[ok]))
        return mad(e_r[ok]) ** 2 + (scale * mad(e_az[ok])) ** 2

    hi = cfg.max_latency_s
    grid = np.round(np.arange(-hi / 3.0, hi + 1e-9, 0.01), 6)
    costs = np.array([cost(tau) for tau in grid])
    best = float(grid[int(np.argmin(costs))]) if np.isfinite(costs).any() else 0.0
    fine = np.round(np.arange(best - 0.01, best + 0.0105, 0.001), 6)
    fine_costs = np.array([cost(tau) for tau in fine])
    if np.isfinite(fine_costs).any():
        best = float(fine[int(np.argmin(fine_costs))])
    return best, np.concatenate([grid, fine]), np.concatenate([costs, fine_costs])


@dataclass
class Residuals:
    """Per pair: range and azimuth residuals at theta and the reference rates."""
    e_r: np.ndarray
    e_az: np.ndarray
    r_dot: np.ndarray
    az_dot: np.ndarray
    t_s: np.ndarray
    sd_ref_r: np.ndarray
    sd_ref_az: np.ndarray


def residuals(objs: ObjectList, rows: np.ndarray, tgt: np.ndarray, g: Geometry, theta: np.ndarray) -> Residuals:
    """Residuals of the pairs (rows, tgt) with ``g`` evaluated at the rows' times minus theta[0]."""
    r_m = np.hypot(objs.x_m[rows], objs.y_m[rows])
    az_m = np.arctan2(objs.y_m[rows], objs.x_m[rows])
    r_ref = g.r[tgt, rows]
    return Residuals(e_r=r_m - r_ref - theta[1], e_az=wrap(az_m - g.az[tgt, rows] + theta[2]),
                     r_dot=g.r_dot[tgt, rows], az_dot=g.az_dot[tgt, rows], t_s=objs.t_s[rows],
                     sd_ref_r=g.sd_r[tgt, rows], sd_ref_az=g.sd_perp[tgt, rows] / r_ref)


def reference_sd(res: Residuals) -> np.ndarray:
    """Systematic sds of (tau, b_r, delta) from the reference's own uncertainty: the RMS of its
    1-sigma along (range bias) and across (mounting yaw, as an angle) the line of sight over the
    pairs. An RTK/INS relative position error is correlated over tens of seconds, so over a run it
    acts as a bias that does not average out: counted as fully correlated (conservative; the
    reference's timing error, well below a millisecond, is left out)."""
    rms = lambda x: float(np.sqrt(np.mean(np.square(x[np.isfinite(x)])))) if np.isfinite(x).any() else 0.0  # noqa: E731
    return np.array([0.0, rms(res.sd_ref_r), rms(res.sd_ref_az)])


def problem(res: Residuals, theta: np.ndarray, sigma: tuple[float, float]) -> identify.LinearProblem:
    """The whitened linear problem at theta (module docstring): range rows, then azimuth rows."""
    s_r, s_a = sigma
    n = len(res.e_r)
    J = np.zeros((2 * n, 3))
    J[:n, 0] = res.r_dot / s_r
    J[:n, 1] = -1.0 / s_r
    J[n:, 0] = res.az_dot / s_a
    J[n:, 2] = 1.0 / s_a
    r = np.concatenate([res.e_r / s_r, res.e_az / s_a])
    return identify.LinearProblem(r=r, J=J, theta0=np.asarray(theta, float).copy(),
                                  t_s=np.concatenate([res.t_s, res.t_s]), prior_sd=PRIOR_SD.copy(),
                                  active=np.ones(3, bool))


def robust_sigma(res: Residuals) -> tuple[float, float]:
    return (max(mad(res.e_r), 1e-4), max(mad(res.e_az), 1e-6))


@dataclass
class Effects:
    """Estimates, Normal-equivalent sds (``identify.fit``), significance (``identify.decide``)."""
    theta: np.ndarray
    sd: np.ndarray
    significant: np.ndarray
    dof: np.ndarray
    sigma: tuple[float, float]
    pairs: int

    def entry(self, i: int, scale: float = 1.0) -> dict:
        return {"value": float(self.theta[i] * scale), "sd": float(self.sd[i] * scale),
                "significant": bool(self.significant[i]),
                "dof": None if not np.isfinite(self.dof[i]) else float(self.dof[i])}


def estimate(res: Residuals, theta: np.ndarray, sigma: tuple[float, float], decide: bool) -> Effects:
    """One MAP step from theta (and, with ``decide``, the significance decision)."""
    prob = problem(res, theta, sigma)
    f = identify.fit(prob, systematic_sd=reference_sd(res))
    if decide:
        f = identify.decide(prob, f)
    return Effects(theta=f.theta, sd=f.sd, significant=np.asarray(f.significant, bool)[:3] & decide,
                   dof=np.asarray(f.dof, float), sigma=sigma, pairs=len(res.e_r))
