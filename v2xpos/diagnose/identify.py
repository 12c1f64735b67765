"""Effect estimation from whitened EKF innovations, and the significance decisions.

Method (prediction-error / output-error identification, Ljung 1999 "System Identification",
ch. 7; Maybeck 1982 "Stochastic Models, Estimation and Control" vol. 2, ch. 10): the EKF's
innovations nu_k with covariances S_k are the prediction errors of the model; whitening them,
r_k = L_k^-1 nu_k with S_k = L_k L_k^T, makes sum |r_k|^2 the negative log-likelihood up to terms
in S. With the effect vector theta applied to the inputs (``inject.correct``), the replay gives
r(theta); its Jacobian J = dr/dtheta is taken by finite differences through the replay. The
Gauss-Newton / MAP step with a Gaussian prior N(0, diag(prior_sd^2)) is

    theta+ = theta - H^-1 (J^T r(theta) + P0^-1 theta),   H = J^T J + P0^-1.

Uncertainty: residuals of a GNSS/INS filter are not white (RTK errors are Gauss-Markov with
time constants of tens of seconds, multipath, unmodelled dynamics), so the reported variance of
theta_i is the largest of (a) H^-1 scaled by the reduced chi-square, (b) the heteroskedasticity-
and autocorrelation-consistent (HAC) long-run variance of theta_i's influence series
u_i(t) = (H^-1 J_t^T r_t)_i (``long_run_variance``: Bartlett kernel, Newey & West 1987, with the
bandwidth chosen from the series' own autocorrelation, Andrews 1991, and the fixed-b bias
correction of Kiefer & Vogelsang 2005) and (c) a delete-one-block jackknife over blocks no shorter than that bandwidth
(Kunsch 1989). A 200 s drive with errors correlated over tens of seconds holds only a few
independent blocks, so each estimate carries its degrees of freedom (nu = 1.5 T / S for the
Bartlett estimator, G - 1 for G jackknife blocks) and the reported sd is *Normal-equivalent*:
the standard error times q_t(nu, Phi(2)) / 2, so that value +- 2 sd is the 95.4 % t-interval
(Cameron & Miller 2015, "A Practitioner's Guide to Cluster-Robust Inference", J. Human
Resources 50(2), sec. VI: t(G-1) critical values with few clusters).

Significance: |theta_i| beyond the two-sided t(nu_i) quantile of a 3-sigma Normal test
(``Fit.threshold_sd``) AND a real error reduction: the effect, estimated on one half of the
recording, lowers the residual cost of the other half (both ways, linearised model).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import stats

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

    @property
    def n_params(self) -> int:
        """P: calibrate's effect vector (``inject.N_PARAMS``) or any other parameter vector
        (``v2xpos.evaluate.effects``: a sensor's latency, range bias and mounting yaw)."""
        return len(self.theta0)

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
    dof: np.ndarray = field(default_factory=lambda: np.full(N_PARAMS, np.inf))
    bandwidth_s: np.ndarray = field(default_factory=lambda: np.zeros(N_PARAMS))

    def threshold_sd(self, n_sigma: float = 3.0) -> np.ndarray:
        """Per parameter, the |value| / sd beyond which the effect is significant at the level of a
        two-sided n_sigma Normal test, for sds with ``dof`` degrees of freedom (``significance_sd``)."""
        return significance_sd(self.dof, n_sigma)

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


SCORE_BIN_S = 1.0
"""Width of the time bins [s] in which the per-row influence terms are summed before their
autocovariances are taken: far below the correlation times that matter (tens of seconds) and
above the row spacing (0.1 s), so that the series is regular in time; the window and bandwidth
below are found in seconds and do not depend on it while it stays that short."""

SOKAL_WINDOW_C = 5.0
"""Sokal's automatic window (reported integrated autocorrelation time): the smallest lag M with
M >= c tau_int(M). c = 5 keeps the truncation
bias of an exponentially decaying autocorrelation below exp(-c/2) ~ 8 % of tau_int while the
estimator's variance grows only as (2M + 1) / T (Sokal 1997, "Monte Carlo Methods in Statistical
Mechanics: Foundations and New Algorithms", sec. 3, recommends c ~ 4-6 for such decay)."""


@dataclass
class LongRunVariance:
    """Long-run variance of the sum of a series and how it was found (``long_run_variance``)."""
    variance_of_sum: float
    bandwidth_s: float
    tau_int_s: float
    window_s: float
    dof: float


def long_run_variance(u: np.ndarray, bin_s: float = SCORE_BIN_S, c: float = SOKAL_WINDOW_C) -> LongRunVariance:
    """Var(sum_t u_t) of a zero-mean, serially correlated series u (T,) sampled every bin_s.

    1. Autocovariances gamma_j = (1/T) sum_t u_t u_(t+j) (not centred: u are scores at the
       estimate, whose sum is ~0 by the normal equations).
    2. Bandwidth S (in bins) by Andrews' (1991, Econometrica 59(3), sec. 6) AR(1) plug-in for the
       Bartlett kernel: rho = gamma_1 / gamma_0, alpha(1) = 4 rho^2 / ((1 - rho)^2 (1 + rho)^2),
       S = 1.1447 (alpha(1) T)^(1/3), at most T - 1; rho <= 0 gives S = 1 (white). For an
       AR(1) the bandwidth in seconds, 1.1447 (4 tau_c^2 T bin_s)^(1/3) with tau_c the correlation
       time, does not depend on the bin width. The nonparametric plug-in of Newey & West (1994)
       was not used: its s1 = 2 sum j gamma_j over a pilot window is dominated by the long lags,
       which the normal equations drive negative (the autocovariances of u sum to (sum u)^2 / T
       = 0), so on a 200 s drive it often came out negative (S -> 1) exactly when the correlation
       is long.
    3. Bartlett (Newey & West 1987, Econometrica 55(3)) estimate
       Omega = gamma_0 + 2 sum_(1 <= j < S) (1 - j/S) gamma_j, divided by 1 - b + b^2/3 with
       b = S / T: the mean of the Bartlett estimator's fixed-b limit when u sums to zero
       (Kiefer & Vogelsang 2005, Econometric Theory 21(6), Theorem 1 with E W(r)^2 terms; the
       downward bias of a bandwidth that is not small against the record). Var(sum u) = T Omega.
    4. Degrees of freedom: a Bartlett long-run variance with bandwidth S is approximately
       chi^2_nu / nu distributed with nu = 1.5 T / S (its variance is (4/3)(S/T) Omega^2:
       Priestley 1981, "Spectral Analysis and Time Series", sec. 6.2.4; the equivalent t(nu) of
       Lazarus, Lewis, Stock & Watson 2018, J. Bus. Econ. Stat. 36(4)), i.e. the G - 1 of Cameron
       & Miller (2015) with G = nu + 1 effective blocks.
    5. For the report, the integrated autocorrelation time with Sokal's automatic window
       (Madras & Sokal 1988, J. Stat. Phys. 50; Sokal 1997 sec. 3): tau_int(M) = 1 + 2 sum_(j<=M)
       gamma_j / gamma_0, M the smallest lag with M >= c tau_int(M), at most T/2.
    """
    u = np.asarray(u, float)
    T = len(u)
    if T < 4 or not np.any(u):
        return LongRunVariance(float(np.sum(u ** 2)), bin_s, bin_s, 0.0, np.inf)
    nfft = 1 << int(np.ceil(np.log2(2 * T)))
    f = np.fft.rfft(u, nfft)
    gamma = np.fft.irfft(f * np.conj(f), nfft)[:T] / T
    rho = float(gamma[1] / gamma[0])
    if rho > 0:
        alpha = 4.0 * rho ** 2 / ((1.0 - rho) ** 2 * (1.0 + rho) ** 2)
        S = float(np.clip(1.1447 * (alpha * T) ** (1.0 / 3.0), 1.0, T - 1.0))
    else:
        S = 1.0
    jj = np.arange(1, int(np.ceil(S)))
    b = S / T
    omega = (gamma[0] + 2.0 * np.sum((1.0 - jj / S) * gamma[jj])) / (1.0 - b + b * b / 3.0)
    tau = 1.0 + 2.0 * np.cumsum(gamma[1:] / gamma[0])
    lags = np.arange(1, T)
    ok = np.flatnonzero((lags >= c * tau) & (lags <= max(T // 2, 1)))
    M = int(lags[ok[0]]) if len(ok) else max(T // 2, 1)
    return LongRunVariance(float(T * max(omega, 0.0)), S * bin_s, float(max(tau[M - 1], 0.0) * bin_s),
                           float(M * bin_s), 1.5 * T / S)


def influence_series(prob: LinearProblem, res: np.ndarray, Hinv: np.ndarray, active: np.ndarray,
                     bin_s: float = SCORE_BIN_S) -> np.ndarray:
    """u (T, P): per time bin, sum over its rows of H^-1 J_k^T r_k (the rows' contributions to the
    estimate's error, theta_hat - theta = -H^-1 sum_k J_k^T r_k to first order), inactive columns 0."""
    if len(res) == 0:
        return np.zeros((0, prob.n_params))
    b = np.floor((prob.t_s - prob.t_s.min()) / bin_s).astype(int)
    scores = prob.J * res[:, None]
    scores[:, ~active] = 0.0
    g = np.zeros((int(b.max()) + 1, prob.n_params))
    np.add.at(g, b, scores)
    return g @ Hinv.T


def t_equivalent(z: float, dof: np.ndarray | float) -> np.ndarray:
    """q_t(dof, Phi(z)): the t(dof) quantile at the probability of the Normal z-sigma level
    (z for dof = inf; dof below 1 taken as 1)."""
    dof = np.asarray(dof, float)
    fin = np.isfinite(dof)
    return np.where(fin, stats.t.ppf(stats.norm.cdf(z), np.where(fin, np.maximum(dof, 1.0), 1.0)), z)


def normal_equivalent_factor(dof: np.ndarray | float, z: float = 2.0) -> np.ndarray:
    """q_t(dof, Phi(z)) / z: the standard error times this is the sd whose +- z interval is the
    t(dof) interval of the Normal z-sigma level (1 for dof = inf)."""
    return t_equivalent(z, dof) / z


def significance_sd(dof: np.ndarray | float, n_sigma: float = 3.0) -> np.ndarray:
    """|value| / (Normal-equivalent sd) at which a two-sided test with the false-alarm rate of an
    n_sigma Normal test rejects 'effect absent' when the standard error has ``dof`` degrees of
    freedom: q_t(dof, Phi(n_sigma)) / normal_equivalent_factor(dof) (n_sigma for dof = inf)."""
    return t_equivalent(n_sigma, dof) / normal_equivalent_factor(dof)


def _solve(prob: LinearProblem, active: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """theta (P,) and H^-1 (P,P): active parameters estimated, the others held at zero (effect
    absent). Minimises |r + J (theta - theta0)|^2 + |theta / prior_sd|^2 over the active set."""
    idx = np.flatnonzero(active)
    theta = np.zeros(prob.n_params)
    Hinv = np.zeros((prob.n_params, prob.n_params))
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
    value moves it by ``-H_ss^-1 H_sn theta_n``: on a convoy follower a not-significant clock drift,
    correlated with the IMU offset, and the unobservable roll, correlated with the lateral lever
    arm, held both away from the truth; with the not-applied effects at 0 both came near it.
    The sd is the root mean square error of this restricted estimate, sqrt(sd^2 + shift^2), with
    sd that of the final model and shift = applied - joint value. Holding a not-applied effect at
    0 when it is really theta_n != 0 biases the applied value by K theta_n (K = H_ss^-1 H_sn), the
    MSE of a restricted least-squares estimate is its variance plus that bias squared (Toro-
    Vizcarrondo & Wallace 1968, JASA 63(322)), and the shift K theta_n_hat is the data's estimate
    of the bias. The marginal sd (the consider covariance H_ss^-1 + K C_nn K^T, Bierman 1977,
    "Factorization Methods for Discrete Sequential Estimation", ch. VIII) covers the bias only
    when theta_n is within its own sd of 0: in the coverage Monte-Carlo a mounting roll (never
    significant: the cross-slope sd hides it) held at 0 moved the lateral lever arm and the gyro z
    scale by several of their sds (docs/calibration.md, Applied values and their sd). When the
    not-applied effects are truly 0 the shift is noise of the same size as the difference of the
    marginal and conditional sds, so the sd is conservative by at most sqrt(2). Significance is
    decided before (``Estimator.confirm``), in the model in which the effect was tested."""
    import copy
    out = copy.deepcopy(f)
    sig = np.asarray(f.significant, bool) & prob.active
    if sig.any():
        conditional = refit(prob, sig)
        shift = np.where(sig, conditional - f.theta, 0.0)
        out.theta = np.where(sig, conditional, f.theta)
        out.sd = np.sqrt(f.sd ** 2 + shift ** 2)
        out.sd_stat = np.sqrt(f.sd_stat ** 2 + shift ** 2)
    return out


def predicted_residual(prob: LinearProblem, theta: np.ndarray) -> np.ndarray:
    return prob.r + prob.J @ (theta - prob.theta0)


def cost(prob: LinearProblem, theta: np.ndarray) -> float:
    rr = predicted_residual(prob, theta)
    return float(rr @ rr)


def jackknife_var(prob: LinearProblem, active: np.ndarray, n_blocks: int = 8) -> np.ndarray:
    """Delete-one-block jackknife variance over n_blocks contiguous time blocks (Kunsch 1989, Ann.
    Stat. 17(3)): covers slow changes of the effects and of the residual statistics along the
    drive. Its blocks are treated as independent, so ``fit`` makes them no shorter than the HAC
    bandwidth; the estimate then has n_blocks - 1 degrees of freedom."""
    if n_blocks < 3 or len(prob.r) < 10 * n_blocks:
        return np.zeros(prob.n_params)
    edges = np.quantile(prob.t_s, np.linspace(0, 1, n_blocks + 1))
    blk = np.clip(np.searchsorted(edges, prob.t_s, side="right") - 1, 0, n_blocks - 1)
    th = np.array([_solve(prob.subset(blk != b), active)[0] for b in range(n_blocks)])
    return (n_blocks - 1) / n_blocks * np.sum((th - th.mean(axis=0)) ** 2, axis=0)


JACKKNIFE_MAX_BLOCKS = 8
"""At most 8 jackknife blocks (25 s of a 200 s drive): fewer, longer blocks when the HAC
bandwidth says the residuals are correlated for longer; never fewer than 3."""


def fit(prob: LinearProblem, systematic_sd: np.ndarray | None = None, active: np.ndarray | None = None,
        bin_s: float = SCORE_BIN_S) -> Fit:
    """One MAP step on the linearised problem, with the robust variance of the module docstring.

    Per active parameter i three variance estimates, each with its degrees of freedom, are made
    Normal-equivalent (times ``normal_equivalent_factor(dof)^2``) and the largest is reported:
    white (H^-1 chi2_red, dof = inf), HAC of the influence series (``long_run_variance``, dof
    1.5 T / S) and the jackknife over G = clip(floor(span / S), 3, 8) blocks (dof G - 1).
    ``dof`` records the winner's, ``threshold_sd`` turns it into the significance threshold."""
    active = prob.active if active is None else active
    theta, Hinv = _solve(prob, active)
    n_params = prob.n_params
    res = predicted_residual(prob, theta)
    m = len(res)
    k = int(active.sum())
    chi2 = float(res @ res) / max(m - k, 1)
    cov_naive = Hinv * max(chi2, 1.0)
    var_white = np.diag(cov_naive).copy()
    var_hac = np.zeros(n_params)
    dof_hac = np.full(n_params, np.inf)
    bandwidth_s = np.zeros(n_params)
    u = influence_series(prob, res, Hinv, active, bin_s)
    span_s = len(u) * bin_s
    for i in np.flatnonzero(active):
        lrv = long_run_variance(u[:, i], bin_s)
        var_hac[i], dof_hac[i], bandwidth_s[i] = lrv.variance_of_sum, lrv.dof, lrv.bandwidth_s
    n_jack = np.clip(np.floor(span_s / np.maximum(bandwidth_s, bin_s)), 3, JACKKNIFE_MAX_BLOCKS).astype(int)
    var_jack = np.zeros(n_params)
    for n in np.unique(n_jack[active]):
        sel = active & (n_jack == n)
        var_jack[sel] = jackknife_var(prob, active, n_blocks=int(n))[sel]
    dof_jack = n_jack - 1.0
    cand_var = np.vstack([var_white, var_hac * normal_equivalent_factor(dof_hac) ** 2,
                          var_jack * normal_equivalent_factor(dof_jack) ** 2])
    cand_dof = np.vstack([np.full(n_params, np.inf), dof_hac, dof_jack])
    win = np.argmax(cand_var, axis=0)
    var_stat = cand_var[win, np.arange(n_params)]
    dof = np.where(active, cand_dof[win, np.arange(n_params)], np.inf)
    sys = np.zeros(n_params) if systematic_sd is None else np.asarray(systematic_sd, float)
    var_stat = np.where(active, var_stat, prob.prior_sd ** 2)
    sd_stat = np.sqrt(var_stat)
    sd = np.sqrt(var_stat + sys ** 2)
    sd_white = np.sqrt(var_white)
    scale = np.where(sd_white > 0, sd_stat / np.maximum(sd_white, 1e-300), 1.0)
    cov = cov_naive * np.outer(scale, scale)
    determined = active & (sd < DETERMINED_RATIO * prob.prior_sd)
    return Fit(theta=theta, cov=cov, sd=sd, sd_stat=sd_stat, cost_before=cost(prob, np.zeros(n_params)),
               cost_after=float(res @ res), n_rows=m, reduced_chi2=chi2, sd_white=sd_white,
               determined=determined, dof=dof, bandwidth_s=bandwidth_s)


def halves(prob: LinearProblem, t_split_s: float | None = None) -> tuple[LinearProblem, LinearProblem]:
    """The problem restricted to rows before / after t_split_s (default: the middle)."""
    t_split_s = float(np.median(prob.t_s)) if t_split_s is None else t_split_s
    first = prob.t_s < t_split_s
    return prob.subset(first), prob.subset(~first)


def cross_validated_gain(prob: LinearProblem, active: np.ndarray) -> np.ndarray:
    """For every active parameter: cost reduction on one half when the effect estimated on the
    other half is included, minus when it is left out (summed over both directions)."""
    a, b = halves(prob)
    gain = np.zeros(prob.n_params)
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
    """Mark parameters significant: beyond the t(dof) equivalent of an n_sigma Normal test
    (``Fit.threshold_sd``) and a positive cross-validated gain."""
    active = prob.active if active is None else active
    f.cv_gain = cross_validated_gain(prob, active)
    f.significant = active & f.determined & (np.abs(f.theta) > f.threshold_sd(n_sigma) * f.sd) & (f.cv_gain > 0)
    return f


def compare(f1: Fit, f2: Fit, use_stat: bool = False) -> np.ndarray:
    """Difference of two estimates in units of their combined sd (per parameter)."""
    s1, s2 = (f1.sd_stat, f2.sd_stat) if use_stat else (f1.sd, f2.sd)
    comb = np.sqrt(s1 ** 2 + s2 ** 2)
    return np.abs(f1.theta - f2.theta) / np.where(comb > 0, comb, np.inf)
