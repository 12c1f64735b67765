"""Integrity of one vehicle's solution: the declared set-up as a hypothesis, the filter that does
not rely on it, the posterior probability that it is wrong, and the protection level
(docs/integrity.md).

**Hypotheses.** H0: the set-up is as declared -- the antenna lever arm within its declared sd and
every effect a ``[calibration]`` table narrowed within the table's sd. The filter (the *main*
solution, the one reported) is the right estimator under H0. H1: the set-up is not as declared (a
survey blunder, a mounting that moved): the right estimator is the *fault-tolerant twin*, the same
error-state filter run on the same measurements with the declared set-up states widened to what
is known without the declaration (``start``). An undeclared error is thus a fault with a prior
probability, not a certainty (advanced RAIM: Blanch et al. 2015, "Baseline advanced RAIM user
algorithm and possible improvements", IEEE TAES 51(1)): ``prior`` = P(H1) before any data, the
rate of set-up blunders for an unverified set-up, the rate of a set-up changing since it was
verified for a verified one (``InsConfig.integrity.setup_fault_prior`` / ``setup_change_prior``).

**Evidence.** Both filters predict every measurement; the likelihood ratio of their innovation
sequences updates the hypothesis probability (the static multiple-model estimator, Magill 1965,
IEEE TAC 10(4); Bar-Shalom, Li & Kirubarajan 2001 sec. 11.6.2):

    log L_k = log L_{k-1} + log N(d_k - H w; 0, S_w) - log N(d_k; 0, S_m)
    P(H1 | y) = 1 / (1 + (1 - p) / p exp(-log L))

with d_k the main filter's innovation and S_m its covariance, ``w`` the twin's estimate of the main
filter's error (so d - H w is the twin's innovation) and S_w = H P_w H^T + R. Each update's term is
taken with its NIS capped at the chi-square quantile 1 - 1e-9 of its degrees of freedom (one gross
outlier is strong, not infinite, evidence). P(H1 | y) is floored at the prior: evidence *for* H0
is not trusted beyond it. Both models approximate the real vehicle; the twin, with its wider
covariance, loses a little likelihood on every epoch where the data cannot tell the hypotheses
apart (the Occam factor), which over a long drive would drive P(H1) to zero whatever the set-up,
also before the first turn, where a wrong lever arm has not yet shown.

**Evidence is not forgotten.** The protection level weighs H1 with the *largest* posterior seen
since the twin started (``peak_fault_probability``), not the current one. The twin models the
set-up fault as a lever-arm (and widened calibrated-effect) error; other undeclared effects
(mounting, a late IMU stamp, a gyro scale) move its lever-arm estimate too. On a generated
follower with all of them (dev_like seed 9) the data made H1 likely (P = 0.85 over 15 s of turns),
then a manoeuvre pulled the twin's lever arm back to the declared one, the likelihood ratio fell by
e^10 within 3 s, and with P(H1) back at its prior the protection level vouched for a solution
0.53 m off. A posterior that collapses like that says the hypotheses do not describe the vehicle;
the likelihood ratio still decides the reason shown and the exclusion test is unchanged, but the
bound keeps the evidence once it was there. A right declaration never raises P(H1) above its prior
(no cost); a wrong one stays unverified until it is excluded, after which the twin is the main
filter and the bound is that of its own error.

**Protection level** (multiple-hypothesis integrity, Pervan, Pullen & Christie 1998, "A multiple
hypothesis approach to satellite navigation integrity", Navigation 45(1)). For the horizontal
error of the reported position (body x forward, y right), the integrity risk of the main solution
at a radius L:

    IR(L) = P(H0|y) P(|e_0| > L) + P(H1|y) P(|s + e_w| > L)

e_0 ~ N(0, P_0) the main filter's 2-D error under H0; under H1 the main solution is off by its
separation s from the twin plus the twin's own error e_w ~ N(0, P_w) -- the separation is
observed, so the bound uses it, not a worst case below a detection threshold. The protection level
solves IR(PL) = IR budget with the circle as the event (``horizontal_tail``: the 2-D normal
outside a circle, exact to quadrature precision). Splitting the budget over the two axes and
taking hypot(PL_x, PL_y) also bounds the error, but the rectangle's corners waste budget: for a
circular error that level is 6.45 sd against the circle's 4.80 at 1e-5 (34 % larger). Before the
vehicle turns a wrong lever arm is invisible (a constant body-frame offset, Groves 2013 sec.
14.2.7): the twin's sd stays at the widened prior, and whether the solution is vouched for then
depends only on the prior -- P(H1) x P(|e_w| > AL) against the budget. Turning pins the lever arm
down in the twin; a right declaration keeps the separation small and the PL falls, a wrong one
makes the separation grow and the PL with it, before the error it describes is reported as bounded.

**Exclusion.** The separation is also tested as in solution-separation RAIM (Brenner 1996,
"Integrated GPS/inertial fault detection availability", Navigation 43(2)): under H0 its covariance
is P_w - P_m, and |s_i| > K_fa sd_ss,i on an axis is an alarm. The filter then takes the twin's
state and covariance (it excludes the declaration, ``InsFilter._exclude_declaration``) and the
hypothesis is resolved: from then on the reported solution is the one that never relied on the
declared set-up, and its PL is that of its own error. The test's level is set per hour by the
Bonferroni bound over the tests of an hour (``false_alarm_per_hour``), so that the exclusion, which
moves the reported position by the separation, happens on evidence and not on noise.

**The lever arm is seen only through rotation the IMU measured** (first-estimates Jacobians: Huang,
Mourikis & Roumeliotis 2010, "Observability-based rules for designing consistent EKF SLAM
estimators", IJRR 29(5)). The GNSS rows' lever-arm columns are ``C_nb`` (position) and ``C_nb [w x]``
(velocity), evaluated at the main filter's attitude. Each correction turns that attitude -- by
degrees while the heading converges after the drive-off -- and a linear filter reads the turned
columns as the antenna seen from another side: a body that never turned appears to, and a
direction that is unobservable on a straight road (the lever arm against the IMU position) gains
information it does not have. The main filter, with its lever arm held to the declared
centimetres, hardly notices; the twin, with 0.5 m, does: on a generated follower accelerating
straight from rest its lateral lever arm went from 0.5 m sd to 0.09 m within 10 s, estimated
0.4 m off a declaration that was right, and its likelihood ratio rose by e^7 -- evidence for a
fault that was the linearisation's. The twin therefore evaluates the lever-arm columns at an anchor
attitude that the gyros turn with the body and the corrections do not, ``C_fej = R_c^T C_nb`` with
``R_c`` the product of the main filter's attitude corrections since the twin's start (they act on
the NED side of ``C_nb``, the strapdown on the body side), i.e. ``H_l <- H_l B`` with ``B = C_nb^T
R_c^T C_nb`` (exact for the position rows; for the velocity rows to first order in the correction
times the rate). A real turn rotates ``C_fej`` as much as ``C_nb``, so the information from turning
is kept. The anchor ignores only corrections made in the small-angle regime of the error state (the
main filter's heading sd at most ``FEJ_MAX_HEADING_SD_RAD``, 5°, where the neglected second-order
term of a rotation error, theta^2/2, is 4 % of the first-order one; it is also a car's start sd from
the course, so a car's twin anchors where its heading is set). A correction made above it is the
convergence of a linearisation that does not yet hold, and an anchor that ignored it would be as far
off the body as the correction is; the anchor follows it, ``R_c <- exp(phi) R_c exp(-phi)``, keeping
its offset from the corrected attitude. (On the real walk_0827 the heading set from the walking
course was about 60° off; an anchor ignoring those corrections made the twin exclude the right
set-up.)

Kept in the main filter's error coordinates: prediction ``w <- Phi w``, ``P_w <- Phi P_w Phi^T +
Q``; at an update ``w <- w + K_w (d - H w)``, ``P_w <- (I - K_w H) P_w``, then ``w <- w - dx_main``
(the main filter feeds its correction back into its nominal state, moving the origin).
"""
from __future__ import annotations

import math

import numpy as np
from scipy.optimize import brentq
from scipy.special import log_ndtr
from scipy.stats import chi2, norm

from .consistency import widen_lever_arm
from ..rotation import exp_so3
from .ekf import ATT, POS, VEL, kalman_update, propagate_with_transition
from .observers import FilterObserver

NIS_CAP_PROBABILITY = 1e-9
"""An update's NIS enters the likelihood ratio capped at this upper quantile of its chi-square."""
FEJ_MAX_HEADING_SD_RAD = math.radians(5.0)
"""The first-estimates anchor ignores the main filter's attitude corrections made at a heading sd
up to this (the small-angle regime of the error state) and follows those made above it."""
PL_SEARCH_MAX_M = 1e4
"""The protection level is searched below this (a PL above it is reported as infinite)."""
HORIZONTAL_TAIL_NODES = 400
"""Gauss-Legendre nodes of ``horizontal_tail``: >= 12 per sd of the density wherever the circle's
radius is within 10 sds (beyond, that hypothesis adds nothing to the risk)."""


def _tail(L: np.ndarray, mean: np.ndarray, sd: np.ndarray) -> np.ndarray:
    """P(|mean + e| > L) for e ~ N(0, sd^2), elementwise."""
    sd = np.maximum(sd, 1e-12)
    return np.exp(log_ndtr((-L - mean) / sd)) + np.exp(log_ndtr((mean - L) / sd))


def protection_levels(risk: float, w1: float, sd0: np.ndarray, sep: np.ndarray, sd_w: np.ndarray,
                      iterations: int = 60) -> np.ndarray:
    """Per axis, the bound L with (1 - w1) P(|e_0| > L) + w1 P(|s + e_w| > L) = risk (module
    docstring), by bisection on [0, ``PL_SEARCH_MAX_M``] (the risk falls monotonically with L);
    infinite where even that bound leaves more risk."""
    sd0, sep, sd_w = (np.asarray(x, float) for x in (sd0, sep, sd_w))
    lo, hi = np.zeros_like(sd0), np.full_like(sd0, PL_SEARCH_MAX_M)

    def excess(L: np.ndarray) -> np.ndarray:
        return (1.0 - w1) * _tail(L, np.zeros_like(L), sd0) + w1 * _tail(L, sep, sd_w) - risk

    out_of_reach = excess(hi) > 0
    for _ in range(iterations):
        mid = 0.5 * (lo + hi)
        above = excess(mid) > 0
        lo = np.where(above, mid, lo)
        hi = np.where(above, hi, mid)
    return np.where(out_of_reach, np.inf, hi)


_GL_THETA, _GL_WEIGHT = np.polynomial.legendre.leggauss(HORIZONTAL_TAIL_NODES)
_GL_THETA = 0.5 * math.pi * _GL_THETA
_GL_WEIGHT = 0.5 * math.pi * _GL_WEIGHT


def horizontal_tail(L: float, mean: np.ndarray, cov: np.ndarray) -> float:
    """P(|m + e| > L) for a 2-D e ~ N(0, cov): the probability that a horizontal error of mean ``m``
    lies outside the circle of radius L.

    In the principal axes of ``cov`` (sds a >= b, mean (m1, m2) there) the error leaves the circle
    either through the strip |x| >= L (``x = m1 + a u``, a normal tail) or, at |x| < L, through
    |y| > sqrt(L^2 - x^2) (two normal tails in y). The second part is integrated over x = L sin t,
    t in (-pi/2, pi/2) -- the substitution takes the square root's endpoint singularity away --
    by Gauss-Legendre quadrature, with x along the *larger* sd so that the density is the wider
    factor of the integrand. Every term is a tail probability (``log_ndtr``), so risks of 1e-6 are
    not lost to cancellation against 1."""
    lam, V = np.linalg.eigh(0.5 * (cov + cov.T))
    a = math.sqrt(max(float(lam[1]), 1e-24))
    b = math.sqrt(max(float(lam[0]), 1e-24))
    m = V.T @ np.asarray(mean, float)
    m1, m2 = float(m[1]), float(m[0])
    strip = math.exp(log_ndtr((-L - m1) / a)) + math.exp(log_ndtr((m1 - L) / a))
    x = L * np.sin(_GL_THETA)
    r = L * np.cos(_GL_THETA)
    density = np.exp(-0.5 * ((x - m1) / a) ** 2) / (a * math.sqrt(2.0 * math.pi))
    across = np.exp(log_ndtr((-r - m2) / b)) + np.exp(log_ndtr((m2 - r) / b))
    return strip + float(np.sum(_GL_WEIGHT * density * across * r))


def horizontal_protection_level(risk: float, w1: float, cov0: np.ndarray, sep: np.ndarray, cov_w: np.ndarray,
                                tol_m: float = 1e-6) -> float:
    """The radius L with (1 - w1) P(|e_0| > L) + w1 P(|s + e_w| > L) = risk for the horizontal
    (2-D) errors -- the module docstring's integrity risk with the circle as the event, not each
    axis. The per-axis levels at risk / 2 each (``protection_levels``) bound it from above (the
    circle of their hypot holds their rectangle), so Brent's method searches below that; infinite
    where even ``PL_SEARCH_MAX_M`` leaves more risk."""
    zero = np.zeros(2)
    sep = np.asarray(sep, float)

    def excess(L: float) -> float:
        out = (1.0 - w1) * horizontal_tail(L, zero, cov0) if w1 < 1.0 else 0.0
        if w1 > 0.0:
            out += w1 * horizontal_tail(L, sep, cov_w)
        return out - risk

    axes = protection_levels(0.5 * risk, w1, np.sqrt(np.maximum(np.diag(cov0), 0.0)), sep,
                             np.sqrt(np.maximum(np.diag(cov_w), 0.0)))
    hi = min(float(math.hypot(axes[0], axes[1])), PL_SEARCH_MAX_M)
    if excess(hi) > 0:
        if excess(PL_SEARCH_MAX_M) > 0:
            return math.inf
        hi = PL_SEARCH_MAX_M
    return float(brentq(excess, 0.0, hi, xtol=tol_m)) if excess(0.0) > 0 else 0.0


class FaultTolerantSolution(FilterObserver):
    """The set-up fault hypothesis of one filter: the twin, P(H1 | y) and the protection level (see
    the module docstring).

    lever_index: first index of the lever-arm block in the error state; fault_sd_m: horizontal
    lever-arm sd without the declaration; widen: other (index, sd) pairs the twin starts wider
    (effects a calibration narrowed); prior: P(H1) at the start; integrity_risk: the budget of the
    protection level; false_alarm_per_hour: of the exclusion test; consider: the Schmidt consider
    states of the main filter, carried the same way.
    """

    def __init__(self, lever_index: int, fault_sd_m: float = 0.5, false_alarm_per_hour: float = 1e-3,
                 prior: float = 1e-3, integrity_risk: float = 1e-5, test_every_s: float = 1.0,
                 min_sd_m: float = 1e-3, consider: slice | None = None, widen: tuple = ()):
        self.lever_index = int(lever_index)
        self.consider = consider
        self.fault_sd_m = float(fault_sd_m)
        self.widen = tuple((int(i), float(sd)) for i, sd in widen)
        self.test_every_s = float(test_every_s)
        n_tests = 2.0 * 3600.0 / self.test_every_s
        self.p_test = float(false_alarm_per_hour) / n_tests
        self.k_fa = float(norm.isf(0.5 * self.p_test))
        self.prior = float(prior)
        self.integrity_risk = float(integrity_risk)
        self.min_sd_m = float(min_sd_m)
        self.P: np.ndarray | None = None
        self.w: np.ndarray | None = None
        self.log_lr = 0.0
        self.t_last_test_s = -math.inf
        self.protection_m = math.inf
        self.setup_share = 0.0
        self.separation_sd: tuple = (math.nan, math.nan)
        self.last: dict = {}
        self.alarms = 0
        self.excluded = False
        self.peak_fault_probability = self.prior
        self._cap: dict[int, float] = {}
        self._R_corr = np.eye(3)

    @property
    def active(self) -> bool:
        return self.P is not None

    @property
    def fault_probability(self) -> float:
        """P(H1 | y): 0 once the declaration is excluded, never below the prior before."""
        if self.excluded:
            return 0.0
        p = self.prior
        if not 0.0 < p < 1.0:
            return p
        x = math.log(p / (1.0 - p)) + self.log_lr
        post = 1.0 / (1.0 + math.exp(-x)) if x > -700 else 0.0
        return max(p, post)

    def set_prior(self, prior: float) -> None:
        """A new P(H1) before the evidence (a consistency alarm re-opens a verified set-up)."""
        self.prior = float(prior)
        self.peak_fault_probability = max(self.peak_fault_probability, self.prior)

    def start(self, P_main: np.ndarray, C_nb: np.ndarray, rate_body_rps: np.ndarray) -> None:
        """Start from the main filter's covariance with the declared set-up widened
        (``consistency.widen_lever_arm`` for the horizontal lever arm, which moves the IMU point a
        filter tracking its antenna reports; the ``widen`` states decoupled at their wider sd), no
        separation, and the evidence gathered so far kept (a restart of the heading does not undo
        what the earlier data said about the set-up). After an exclusion the main filter no
        longer holds the declaration: the twin is the main filter."""
        if self.excluded:
            self.P = P_main.copy()
        else:
            P = widen_lever_arm(P_main, self.lever_index, POS, VEL, C_nb, rate_body_rps, self.fault_sd_m)
            for i, sd in self.widen:
                if P[i, i] < sd * sd:
                    P[i, :] = 0.0
                    P[:, i] = 0.0
                    P[i, i] = sd * sd
            self.P = P
        self.w = np.zeros(self.P.shape[0])
        self._R_corr = np.eye(3)
        self.protection_m = math.inf
        self.t_last_test_s = -math.inf

    def _anchor_turn(self, C_nb: np.ndarray) -> np.ndarray:
        """``B = C_nb^T R_c^T C_nb``: the anchor attitude ``C_fej = R_c^T C_nb = C_nb B`` as a turn
        on the body side of the attitude ``C_nb`` (body -> NED)."""
        return C_nb.T @ self._R_corr.T @ C_nb

    def in_main_coordinates(self, C_nb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(w, P) with the lever-arm block turned from the twin's first-estimates body axes into
        the main filter's current ones (``update``): the twin's lever-arm error ``w_l`` moves the
        antenna by ``C_fej w_l = C_nb B w_l``, so in the main filter's axes it is ``B w_l``."""
        B = self._anchor_turn(C_nb)
        T = np.eye(self.P.shape[0])
        li = self.lever_index
        T[li:li + 3, li:li + 3] = B
        return T @ self.w, T @ self.P @ T.T

    def exclude(self, P_main: np.ndarray) -> None:
        """The main filter took over this solution (the declaration was rejected): both are the
        same estimate from now on, and the hypothesis is resolved."""
        self.excluded = True
        self.P = P_main.copy()
        self.w = np.zeros(P_main.shape[0])

    def stop(self) -> None:
        self.P = None
        self.w = None
        self.protection_m = math.inf

    def propagate(self, Phi: np.ndarray, q_c: np.ndarray, dt_s: float) -> None:
        """Time update with the main filter's transition and process noise."""
        if self.P is None:
            return
        self.P = propagate_with_transition(self.P, Phi, q_c, max(dt_s, 0.0))
        self.w = Phi @ self.w

    # the filter's steps, observed (``observers.FilterObserver``)
    def propagating(self, f, Phi: np.ndarray, q_c: np.ndarray, dt_s: float) -> None:
        self.propagate(Phi, q_c, dt_s)

    def corrected(self, f, H: np.ndarray, d: np.ndarray, R: np.ndarray, dx: np.ndarray, nis: float,
                  S: np.ndarray) -> None:
        self.update(H, d, R, dx, nis, S, C_nb_after=f.C_nb,
                    heading_sd_rad=math.sqrt(max(f.P[ATT + 2, ATT + 2], 0.0)))

    def states_reset(self, f, P_before: np.ndarray, index: np.ndarray) -> None:
        self.reset_states(index, f.P)

    def _capped(self, nis: float, dof: int) -> float:
        c = self._cap.get(dof)
        if c is None:
            c = self._cap[dof] = float(chi2.isf(NIS_CAP_PROBABILITY, dof))
        return c if not math.isfinite(nis) else min(nis, c)

    def update(self, H: np.ndarray, d: np.ndarray, R: np.ndarray, dx_main: np.ndarray,
               nis_main: float = math.nan, S_main: np.ndarray | None = None,
               C_nb_after: np.ndarray | None = None, heading_sd_rad: float | None = None) -> None:
        """Measurement update with the data the main filter accepted: the twin's own
        ``ekf.kalman_update`` (ungated: the main filter gated it) on its innovation d - H w, then
        the log likelihood ratio of the two filters' innovations (module docstring) when the main
        filter's NIS and S are given. ``C_nb_after``: the main filter's attitude (body -> NED)
        after this correction; given, the lever-arm columns are taken at the first-estimates
        anchor (module docstring), which ignores ``dx_main``'s attitude part when
        ``heading_sd_rad`` (the main filter's, after the correction) is within
        ``FEJ_MAX_HEADING_SD_RAD`` and turns with it otherwise (so the two go together: an anchor
        without the heading sd would not know which regime it is in)."""
        if C_nb_after is not None and heading_sd_rad is None:
            raise ValueError("FaultTolerantSolution.update: C_nb_after needs heading_sd_rad, the main filter's "
                             "heading sd after the correction")
        if self.P is None:
            return
        d = np.asarray(d, float)
        if C_nb_after is not None:
            phi = np.asarray(dx_main[ATT:ATT + 3], float)
            C_meas = exp_so3(-phi) @ C_nb_after
            B = self._anchor_turn(C_meas)
            H = H.copy()
            li = self.lever_index
            H[:, li:li + 3] = H[:, li:li + 3] @ B
            if heading_sd_rad <= FEJ_MAX_HEADING_SD_RAD:
                self._R_corr = exp_so3(phi) @ self._R_corr
            else:
                self._R_corr = exp_so3(phi) @ self._R_corr @ exp_so3(-phi)
        d_w = d - H @ self.w
        dw, P, nis_w, S_w, ok = kalman_update(self.P, H, d_w, R, None, consider=self.consider)
        if not ok:
            return
        if S_main is not None and math.isfinite(nis_main) and not self.excluded:
            m = len(d)
            sign_w, logdet_w = np.linalg.slogdet(S_w)
            sign_m, logdet_m = np.linalg.slogdet(S_main)
            if sign_w > 0 and sign_m > 0:
                self.log_lr += 0.5 * (self._capped(nis_main, m) + logdet_m - self._capped(nis_w, m) - logdet_w)
        self.w = self.w + dw - dx_main
        self.P = P

    def reset_states(self, index, P_main: np.ndarray) -> None:
        """The main filter took these states from a measurement and reset their covariance
        (position reset): the twin takes the same values."""
        if self.P is None:
            return
        idx = np.asarray(index)
        self.P[idx, :] = 0.0
        self.P[:, idx] = 0.0
        self.P[np.ix_(idx, idx)] = P_main[np.ix_(idx, idx)]
        self.w[idx] = 0.0

    def due(self, t_s: float) -> bool:
        return self.P is not None and t_s - self.t_last_test_s >= self.test_every_s - 1e-9

    def test(self, t_s: float, J_pos: np.ndarray, P_main: np.ndarray, yaw_rad: float) -> bool:
        """Separation test and protection level of the reported position (rows ``J_pos`` of the
        reported Jacobian, ``reported.reported_jacobian``) along the body x / y axes (heading
        ``yaw_rad``). True when the separation exceeds its threshold on an axis (exclusion)."""
        if self.P is None:
            return False
        self.t_last_test_s = float(t_s)
        c, s = math.cos(yaw_rad), math.sin(yaw_rad)
        T = np.array([[c, s, 0.0], [-s, c, 0.0]]) @ J_pos          # body x / y <- error state
        sep = T @ self.w
        Pm = T @ P_main @ T.T
        Pw = T @ self.P @ T.T
        sd0 = np.sqrt(np.maximum(np.diag(Pm), 0.0))
        sd_ss = np.sqrt(np.maximum(np.diag(Pw - Pm), self.min_sd_m ** 2))
        sd_w = np.sqrt(np.maximum(np.diag(Pw), 0.0))
        w1 = self.fault_probability
        if not self.excluded:
            self.peak_fault_probability = w1 = max(self.peak_fault_probability, w1)
        self.protection_m = horizontal_protection_level(self.integrity_risk, w1, Pm, sep, Pw)
        free_m = horizontal_protection_level(self.integrity_risk, 0.0, Pm, sep, Pw)
        # how much of the PL the set-up hypothesis adds (0: the fault-free error alone sets it)
        self.setup_share = (0.0 if not math.isfinite(self.protection_m) or self.protection_m <= 0
                            else max(0.0, 1.0 - free_m / self.protection_m))
        self.separation_sd = (float(sd_ss[0]), float(sd_ss[1]))
        z = np.abs(sep) / sd_ss
        self.last = {"t_s": float(t_s), "separation_m": sep.tolist(), "sd_separation_m": sd_ss.tolist(),
                     "sd_fault_tolerant_m": sd_w.tolist(), "sd_main_m": sd0.tolist(),
                     "protection_m": self.protection_m, "fault_free_protection_m": free_m,
                     "fault_probability": w1, "z": z.tolist(), "k_fa": self.k_fa}
        alarm = bool(np.any(z > self.k_fa)) and not self.excluded
        self.alarms += int(alarm)
        return alarm
