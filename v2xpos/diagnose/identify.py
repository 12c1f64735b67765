"""Effect estimation from whitened EKF innovations, and the significance decisions.

Method (prediction-error / output-error identification, Ljung 1999 "System Identification",
ch. 7; Maybeck 1982 "Stochastic Models, Estimation and Control" vol. 2, ch. 10): the EKF's
innovations nu_k with covariances S_k are the prediction errors of the model; whitening them,
r_k = L_k^-1 nu_k with S_k = L_k L_k^T, makes sum |r_k|^2 the negative log-likelihood up to terms
in S. With the effect vector theta applied to the inputs (``inject.correct``), the replay gives
r(theta); its Jacobian J = dr/dtheta is taken by finite differences through the replay. The
Gauss-Newton / MAP step with a Gaussian prior N(0, diag(prior_sd^2)) is

    theta+ = theta - H^-1 (J^T r(theta) + P0^-1 theta),   H = J^T J + P0^-1.

Uncertainty: residuals of a GNSS/INS filter are not white (RTK multipath, unmodelled dynamics),
so the reported covariance is the larger, per parameter, of (a) H^-1 scaled by the reduced
chi-square and (b) the cluster-robust sandwich H^-1 (sum_b g_b g_b^T) H^-1 with g_b = J_b^T r_b
summed over time blocks (Liang & Zeger 1986, Biometrika 73(1)); blocks longer than the residual
correlation time make (b) valid under serial correlation.

Significance: |theta_i| > 3 sd_i AND a real error reduction: the effect, estimated on one half of
the recording, lowers the residual cost of the other half (both ways, linearised model).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .inject import N_PARAMS, PARAM_NAMES


@dataclass
class LinearProblem:
    """Whitened residuals r (M,) at theta0 (P,), Jacobian J (M, P), row times t_s (M,), priors."""
    r: np.ndarray
    J: np.ndarray
    theta0: np.ndarray
    t_s: np.ndarray
    prior_sd: np.ndarray
    active: np.ndarray = field(default_factory=lambda: np.ones(N_PARAMS, bool))

    def subset(self, rows: np.ndarray) -> "LinearProblem":
        return LinearProblem(self.r[rows], self.J[rows], self.theta0, self.t_s[rows], self.prior_sd, self.active)


@dataclass
class Fit:
    """MAP estimate and its uncertainty. sd_stat is the sd from the data alone (for comparing two
    estimates on the same recording); sd adds the systematic terms in ``systematic_sd``; sd_white
    is the sd the residuals would give if they were white (``(J^T J + P0^-1)^-1`` x chi2_red)."""
    theta: np.ndarray
    cov: np.ndarray
    sd: np.ndarray
    sd_stat: np.ndarray
    cost_before: float
    cost_after: float
    n_rows: int
    reduced_chi2: float
    significant: np.ndarray = field(default_factory=lambda: np.zeros(N_PARAMS, bool))
    cv_gain: np.ndarray = field(default_factory=lambda: np.zeros(N_PARAMS))
    sd_white: np.ndarray = field(default_factory=lambda: np.zeros(N_PARAMS))
    determined: np.ndarray = field(default_factory=lambda: np.ones(N_PARAMS, bool))

    def table(self) -> list[dict]:
        return [{"name": PARAM_NAMES[i], "value": float(self.theta[i]), "sd": float(self.sd[i]),
                 "sd_stat": float(self.sd_stat[i]), "significant": bool(self.significant[i]),
                 "determined": bool(self.determined[i]), "cv_gain": float(self.cv_gain[i])}
                for i in range(len(self.theta))]


DETERMINED_RATIO = 0.5
"""An effect is *determined* by the recording when its sd is below half its prior sd, i.e. the data
carry at least three times the prior's information (1/sd^2 >= 4/prior^2): its value then reflects
the recording and not the prior. Otherwise (e.g. a vertical lever arm on a flat road, which moves
the antenna only through roll and pitch; the split of IMU offset and GNSS latency) it is reported
as not determined and is never significant."""


def _solve(prob: LinearProblem, active: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """theta (P,) and H^-1 (P,P): active parameters estimated, the others held at zero (effect
    absent). Minimises |r + J (theta - theta0)|^2 + |theta / prior_sd|^2 over the active set."""
    idx = np.flatnonzero(active)
    theta = np.zeros(N_PARAMS)
    Hinv = np.zeros((N_PARAMS, N_PARAMS))
    r_at_zero = prob.r - prob.J @ prob.theta0
    if len(idx) == 0:
        return theta, Hinv
    J = prob.J[:, idx]
    p_inv = 1.0 / prob.prior_sd[idx] ** 2
    H = J.T @ J + np.diag(p_inv)
    Hi = np.linalg.inv(H)
    theta[idx] = -Hi @ (J.T @ r_at_zero)
    Hinv[np.ix_(idx, idx)] = Hi
    return theta, Hinv


def refit(prob: LinearProblem, active: np.ndarray) -> np.ndarray:
    """MAP estimate of the linearised problem with only ``active`` parameters free (the others at
    zero): e.g. an effect removed and the parameters correlated with it re-estimated."""
    return _solve(prob, active & prob.active)[0]


def applied(prob: LinearProblem, f: Fit) -> Fit:
    """The fit as it goes back into the vehicle: the significant effects re-estimated with every
    other effect held at 0, the value the calibration writes for it (``writeback``), so that the
    applied set is a consistent model and not a slice of the joint one.

    In the joint (final) model the not-significant parameters stay free; a significant effect's
    value there is conditional on their joint estimates, and writing those as 0 while keeping that
    value moves it by ``-H_ss^-1 H_sn theta_n``. Measured on a convoy recording (follower B): the
    clock drift at -64 +- 43 ppm (not significant, truth 0) held the IMU offset at -23.6 ms and the
    lateral lever arm at 0.392 m (correlations -0.67 with the drift, 0.7 with the unobservable roll);
    with the not-applied effects at 0: -28.7 ms (truth about -30) and 0.270 m (0.3).
    The sd stays that of the final model: with the others free it is the marginal sd, i.e. the
    consider covariance of the applied estimate with the not-applied effects' uncertainty from the
    same fit (``H_ss^-1 + K C_nn K^T``, ``K = H_ss^-1 H_sn``; Bierman 1977, "Factorization Methods
    for Discrete Sequential Estimation", ch. VIII), not the smaller conditional one."""
    import copy
    out = copy.deepcopy(f)
    sig = np.asarray(f.significant, bool) & prob.active
    if sig.any():
        out.theta = np.where(sig, refit(prob, sig), f.theta)
    return out


def predicted_residual(prob: LinearProblem, theta: np.ndarray) -> np.ndarray:
    return prob.r + prob.J @ (theta - prob.theta0)


def cost(prob: LinearProblem, theta: np.ndarray) -> float:
    rr = predicted_residual(prob, theta)
    return float(rr @ rr)


def jackknife_var(prob: LinearProblem, active: np.ndarray, n_blocks: int = 8) -> np.ndarray:
    """Delete-one-block jackknife variance over contiguous time blocks (Kunsch 1989, Ann. Stat.
    17(3)): covers slow changes of the effects and of the residual statistics along the drive."""
    if n_blocks < 3 or len(prob.r) < 10 * n_blocks:
        return np.zeros(N_PARAMS)
    edges = np.quantile(prob.t_s, np.linspace(0, 1, n_blocks + 1))
    blk = np.clip(np.searchsorted(edges, prob.t_s, side="right") - 1, 0, n_blocks - 1)
    th = np.array([_solve(prob.subset(blk != b), active)[0] for b in range(n_blocks)])
    return (n_blocks - 1) / n_blocks * np.sum((th - th.mean(axis=0)) ** 2, axis=0)


def fit(prob: LinearProblem, block_s: float = 10.0, systematic_sd: np.ndarray | None = None,
        active: np.ndarray | None = None, jackknife_blocks: int = 8) -> Fit:
    """One MAP step on the linearised problem, with the robust covariance described above."""
    active = prob.active if active is None else active
    theta, Hinv = _solve(prob, active)
    res = predicted_residual(prob, theta)
    m = len(res)
    k = int(active.sum())
    chi2 = float(res @ res) / max(m - k, 1)
    cov_naive = Hinv * max(chi2, 1.0)
    blocks = np.floor((prob.t_s - prob.t_s.min()) / block_s).astype(int) if m else np.zeros(0, int)
    G = np.zeros((N_PARAMS, N_PARAMS))
    for b in np.unique(blocks):
        sel = blocks == b
        g = prob.J[sel].T @ res[sel]
        g[~active] = 0.0
        G += np.outer(g, g)
    cov_sand = Hinv @ G @ Hinv
    var_stat = np.maximum(np.diag(cov_naive), np.diag(cov_sand))
    var_stat = np.maximum(var_stat, jackknife_var(prob, active, n_blocks=jackknife_blocks))
    sys = np.zeros(N_PARAMS) if systematic_sd is None else np.asarray(systematic_sd, float)
    var_stat = np.where(active, var_stat, prob.prior_sd ** 2)
    sd_stat = np.sqrt(var_stat)
    sd = np.sqrt(var_stat + sys ** 2)
    sd_white = np.sqrt(np.diag(cov_naive))
    scale = np.where(sd_white > 0, sd_stat / np.maximum(sd_white, 1e-300), 1.0)
    cov = cov_naive * np.outer(scale, scale)
    determined = active & (sd < DETERMINED_RATIO * prob.prior_sd)
    return Fit(theta=theta, cov=cov, sd=sd, sd_stat=sd_stat, cost_before=cost(prob, np.zeros(N_PARAMS)),
               cost_after=float(res @ res), n_rows=m, reduced_chi2=chi2, sd_white=sd_white,
               determined=determined)


def halves(prob: LinearProblem, t_split_s: float | None = None) -> tuple[LinearProblem, LinearProblem]:
    """The problem restricted to rows before / after t_split_s (default: the middle)."""
    t_split_s = float(np.median(prob.t_s)) if t_split_s is None else t_split_s
    first = prob.t_s < t_split_s
    return prob.subset(first), prob.subset(~first)


def cross_validated_gain(prob: LinearProblem, active: np.ndarray) -> np.ndarray:
    """For every active parameter: cost reduction on one half when the effect estimated on the
    other half is included, minus when it is left out (summed over both directions)."""
    a, b = halves(prob)
    gain = np.zeros(N_PARAMS)
    for train, test in ((a, b), (b, a)):
        th_all, _ = _solve(train, active)
        c_all = cost(test, th_all)
        for i in np.flatnonzero(active):
            without = active.copy()
            without[i] = False
            th_wo, _ = _solve(train, without)
            gain[i] += cost(test, th_wo) - c_all
    return gain


def decide(prob: LinearProblem, f: Fit, n_sigma: float = 3.0, active: np.ndarray | None = None) -> Fit:
    """Mark parameters significant: beyond n_sigma sd and a positive cross-validated gain."""
    active = prob.active if active is None else active
    f.cv_gain = cross_validated_gain(prob, active)
    f.significant = active & f.determined & (np.abs(f.theta) > n_sigma * f.sd) & (f.cv_gain > 0)
    return f


def compare(f1: Fit, f2: Fit, use_stat: bool = False) -> np.ndarray:
    """Difference of two estimates in units of their combined sd (per parameter)."""
    s1, s2 = (f1.sd_stat, f2.sd_stat) if use_stat else (f1.sd, f2.sd)
    comb = np.sqrt(s1 ** 2 + s2 ** 2)
    return np.abs(f1.theta - f2.theta) / np.where(comb > 0, comb, np.inf)
