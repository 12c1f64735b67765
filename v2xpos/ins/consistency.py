"""The filter's own consistency test: does its covariance describe its GNSS innovations?

A filter whose model is right produces innovations d with covariance S = H P H^T + R, so the
normalised innovation squared NIS = d^T S^-1 d of an m-row update is chi-square with m degrees of
freedom, and the sum over a window of updates is chi-square with the summed degrees of freedom
(the time-average NIS test, Bar-Shalom, Li & Kirubarajan 2001, *Estimation with Applications to
Tracking and Navigation*, sec. 5.4.2). An undeclared effect breaks it where it acts: an antenna
lever arm that differs from the declared one by dl moves the antenna by C_nb dl, which the filter
cannot tell from a position error while the heading is constant, but which turns with the car --
in a turn the GNSS position and velocity innovations grow with the yaw rate (w x dl) and the
windowed NIS leaves its chi-square band. The same holds for a yaw misalignment or a gyro scale
error: all of them are observable only through rotation (Groves 2013, *Principles of GNSS, Inertial,
and Multisensor Integrated Navigation Systems*, 2nd ed., sec. 14.2.7 and 16.3.3 on lever-arm and
attitude observability).

The NIS is an omnibus test: it sums squares over all axes, so a small systematic innovation
(the filter absorbs most of a wrong lever arm by tracking the point IMU + C_nb dl, a rigid-body
point whose motion the IMU explains except for its centripetal acceleration) drowns in the white
part. On convoy_dev's follower the body-x GNSS velocity innovation follows -0.08 x yaw rate
(correlation -0.42) while the NIS in turns rises only from 1.8 to 3.5 per 3 dof. A directed test
sees it: the *mean* of the normalised innovations over a window, per body axis (the residual
whiteness / zero-mean test, Bar-Shalom et al. 2001 sec. 5.4.2; Mehra & Peschon 1971, Automatica
7(5)), in the body frame because the signature C_nb (w x dl) turns with the car.

So the monitor keeps these facts per vehicle (``ConsistencyMonitor``):

* **tests on disjoint blocks** of ``window_s`` (5 s): per kind (GNSS position, velocity) (a) the
  block's NIS sum against the chi-square quantile of its degrees of freedom (each update's NIS
  capped at the quantile ``1 - 1e-9`` of its own dof, so that one gross outlier counts as a
  strong, not an infinite, piece of evidence), (b) the block mean of the normalised innovations
  along body x and y, times sqrt(n), against N(0, 1). Each update is tested once (a running window
  tested at every epoch re-tests the same data 50 times and has no stated false-alarm rate);
* **a false-alarm rate per hour**: the level of each test is ``false_alarm_per_hour`` divided by
  the number of tests in an hour (6 statistics per block, 720 blocks): P(any false alarm in an
  hour) <= sum of the levels (Bonferroni's inequality, valid whatever the tests' correlation).
  For 1e-3 per hour the mean test's limit is 5.17 sd (a fixed 3 sd, 0.27 % per window, would
  give about a dozen false alarms an hour for an exactly consistent filter);
* **what an alarm means**: a block NIS beyond its limit says the covariance understates the
  spread of the innovations -- a real RTK receiver's sds are pessimistic on average and optimistic
  in bursts (docs/integrity.md) -- and is answered by
  covariance matching in what the filter reports (``variance_ratio``), so the reported sds stay
  honest; it is counted (``variance_alarms``), not a failure. A block *mean* beyond its limit is
  a systematic error the model lacks: that is a failure;
* **failed** (``INCONSISTENT``) from a failure until the evidence has gone: released after
  ``release_windows`` consecutive blocks per kind (6 x 5 s = 30 s of GNSS) in which every statistic
  passes at the 1 % level -- a hysteresis between the alarm level (~5 sd) and the release level
  (2.58 sd), so one marginal block neither sets nor clears it, and a false alarm costs tens of
  seconds, not the session (``reverify=False`` latches instead). An alarm changes no state of the
  filter: it says that the filter's covariance does not describe its innovations (the reported
  sds are scaled by ``variance_ratio`` meanwhile) and it re-opens a set-up verified on an earlier
  drive (``InsFilter._on_inconsistency``). What a wrong set-up does to the solution is the
  business of the set-up hypothesis (``integrity.FaultTolerantSolution``), which excludes the
  declaration on its own evidence;
* **verified**: not failed, and the horizontal protection level (``integrity``, set by the
  filter through ``set_protection``) within the alert limit. Turn counting (``verify_turn_deg``)
  remains available as an extra requirement (0 by default).

``state`` is then ``VERIFIED``, ``UNVERIFIED`` (not failed, protection level not yet within its
limit) or ``INCONSISTENT``. Updates within ``settle_s`` of the heading being set are not tested
(the filter is still converging from its initial covariance).
"""
from __future__ import annotations

import math
from collections import deque

import numpy as np
from scipy.stats import chi2, norm

from v2xpos.rotation import skew


VERIFIED, UNVERIFIED, INCONSISTENT = "verified", "unverified", "inconsistent"
_CAP_PROBABILITY = 1e-9
_MIN_MEAN_UPDATES = 10


class ConsistencyMonitor:
    """Block NIS and body-frame mean tests, their release, and the verification state of one
    filter (see module docstring)."""

    def __init__(self, window_s: float = 5.0, false_alarm_per_hour: float = 1e-3, verify_turn_deg: float = 0.0,
                 min_speed_mps: float = 1.0, settle_s: float = 5.0, kinds: tuple = ("gnss_pos", "gnss_vel"),
                 reverify: bool = True, release_windows: int = 6, release_level: float = 0.01,
                 detectable_m: float = 0.3, mean_z_limit: float | None = None):
        self.window_s = float(window_s)
        self.kinds = tuple(kinds)
        # Bonferroni: 3 statistics (NIS, mean along body x, along body y) per kind and block
        self.tests_per_hour = 3 * len(self.kinds) * 3600.0 / self.window_s
        self.false_alarm_per_hour = float(false_alarm_per_hour)
        self.p_test = self.false_alarm_per_hour / self.tests_per_hour
        self.mean_z_limit = float(norm.isf(0.5 * self.p_test)) if mean_z_limit is None else float(mean_z_limit)
        self.release_level = float(release_level)
        self.release_z = float(norm.isf(0.5 * self.release_level))
        self.release_windows = int(release_windows)
        self.verify_turn_rad = math.radians(verify_turn_deg)
        self.min_speed_mps = float(min_speed_mps)
        self.settle_s = float(settle_s)
        self.reverify = bool(reverify)
        self.detectable_m = float(detectable_m)
        self._win: dict[str, deque] = {k: deque() for k in self.kinds}
        self._sum: dict[str, list] = {k: [0.0, 0] for k in self.kinds}
        self._blk: dict[str, list | None] = {k: None for k in self.kinds}
        self._threshold: dict[tuple, float] = {}
        self._cap: dict[int, float] = {}
        self.vel_innovation_sd_mps = math.inf
        self.vel_updates_per_block = 0
        self.failed = False
        self.turn_since_fail_rad = 0.0
        self.t_settled_s = -math.inf
        self.t_last_gnss_s = -math.inf
        self.failures = 0
        self.releases = 0
        self.quiet_blocks = 0
        self.last_failure_t_s = math.nan
        self.last_failed_kind = ""
        self.variance_alarms = 0
        self.last_statistic: dict[str, tuple] = {}
        self.protection_m = 0.0
        self.protection_limit_m = math.inf

    def set_protection(self, protection_m: float, limit_m: float) -> None:
        """The horizontal protection level of the fault-tolerant solution (``FaultTolerantSolution``)
        and its limit: the solution is verified only while it is within the limit."""
        self.protection_m = float(protection_m)
        self.protection_limit_m = float(limit_m)

    def fail(self, t_s: float, kind: str = "") -> None:
        """A failure of these tests (``kind``: the kind of update whose block failed) or of another
        test of the same filter (e.g. ``"separation"``)."""
        self.failed = True
        self.last_failed_kind = str(kind)
        self.turn_since_fail_rad = 0.0
        self.failures += 1
        self.quiet_blocks = 0
        self.last_failure_t_s = float(t_s)

    def restart(self, t_s: float) -> None:
        """The filter (re)set its heading at t_s: test its updates from t_s + settle_s."""
        self.t_settled_s = float(t_s) + self.settle_s
        self.clear_windows()

    def clear_windows(self) -> None:
        """Forget the windowed sums and the open blocks (after the filter changed its model, e.g.
        widened an effect's covariance: the innovations before it no longer describe the filter
        that follows)."""
        for k in self.kinds:
            self._win[k].clear()
            self._sum[k] = [0.0, 0]
            self._blk[k] = None

    def _chi2(self, p: float, dof: int) -> float:
        q = self._threshold.get((p, dof))
        if q is None:
            q = self._threshold[(p, dof)] = float(chi2.isf(p, dof))
        return q

    def _capped(self, nis: float, dof: int) -> float:
        c = self._cap.get(dof)
        if c is None:
            c = self._cap[dof] = float(chi2.isf(_CAP_PROBABILITY, dof))
        return c if not math.isfinite(nis) else min(nis, c)

    def feed_update(self, kind: str, t_s: float, nis: float, dof: int, innovation=None, S=None,
                    C_nb=None) -> bool:
        """One GNSS update (accepted or rejected by the gate): its NIS and, for the mean test, its
        innovation (NED), innovation covariance S and the attitude C_nb. True when a test failed
        at this update (the filter reacts: ``InsFilter._on_inconsistency``)."""
        if kind not in self._win:
            return False
        t_s = float(t_s)
        self.t_last_gnss_s = t_s
        if t_s < self.t_settled_s:
            return False
        x = self._capped(float(nis), int(dof))
        win, acc = self._win[kind], self._sum[kind]
        win.append((t_s, x, int(dof)))
        acc[0] += x
        acc[1] += int(dof)
        while win and win[0][0] <= t_s - self.window_s:
            _, x0, d0 = win.popleft()
            acc[0] -= x0
            acc[1] -= d0
        zx = zy = math.nan
        if innovation is not None and S is not None and C_nb is not None and len(innovation) == 3:
            nu_b = C_nb.T @ np.asarray(innovation, float)
            S_b = C_nb.T @ np.asarray(S, float) @ C_nb
            sx, sy = math.sqrt(max(S_b[0, 0], 1e-30)), math.sqrt(max(S_b[1, 1], 1e-30))
            if kind == "gnss_vel":
                self.vel_innovation_sd_mps = max(sx, sy)
            cap = 6.0
            zx = max(-cap, min(cap, float(nu_b[0]) / sx))
            zy = max(-cap, min(cap, float(nu_b[1]) / sy))
        fail = False
        blk = self._blk[kind]
        if blk is not None and t_s >= blk[0] + self.window_s:
            fail = self._evaluate(kind, blk, t_s)
            blk = None
        if blk is None:
            blk = self._blk[kind] = [t_s, 0.0, 0, 0.0, 0.0, 0]
        blk[1] += x
        blk[2] += int(dof)
        if zx == zx:
            blk[3] += zx
            blk[4] += zy
            blk[5] += 1
        return fail

    def _evaluate(self, kind: str, blk: list, t_s: float) -> bool:
        """The tests of one completed block (disjoint blocks: each update is tested once)."""
        _, nis_sum, dof_sum, zx, zy, n = blk
        # a block NIS beyond its quantile says the covariance understates the innovations' spread:
        # answered by covariance matching in what is reported (``variance_ratio``), so the sds stay
        # honest; it is counted, and it holds off a release. A *mean* beyond its limit is a
        # systematic error the model lacks: that is the failure.
        if dof_sum > 0 and nis_sum > self._chi2(self.p_test, dof_sum):
            self.variance_alarms += 1
        alarm = False
        quiet = dof_sum == 0 or nis_sum <= self._chi2(self.release_level, dof_sum)
        mx = my = math.nan
        if n >= _MIN_MEAN_UPDATES:
            r = 1.0 / math.sqrt(n)
            mx, my = zx * r, zy * r
            alarm = max(abs(mx), abs(my)) > self.mean_z_limit
            quiet &= max(abs(mx), abs(my)) <= self.release_z
            if kind == "gnss_vel":
                self.vel_updates_per_block = n
        self.last_statistic[kind] = (nis_sum, dof_sum, self._chi2(self.p_test, dof_sum) if dof_sum else math.inf)
        self.last_statistic[kind + "_mean"] = (mx, my, self.mean_z_limit)
        if alarm:
            self.fail(t_s, kind)
        elif quiet:
            self.quiet_blocks += 1
            if self.failed and self.reverify and self.quiet_blocks >= self.release_windows * len(self.kinds):
                self.failed = False
                self.releases += 1
        else:
            self.quiet_blocks = 0
        return bool(alarm)

    def variance_ratio(self, kind: str = "gnss_pos", min_dof: int = 30) -> float:
        """max(1, windowed sum of NIS / its degrees of freedom) of ``kind``: the factor by which the
        filter's covariance understates its innovations over the window (1 when it does not, or
        with fewer than ``min_dof`` degrees of freedom). Its maximum-likelihood meaning: for
        innovations with covariance k S, the estimate of k is NIS_sum / dof (covariance matching,
        Mehra 1970, IEEE TAC 15(2)), floored at 1 so that a pessimistic filter is never shrunk."""
        acc = self._sum.get(kind)
        if acc is None or acc[1] < min_dof:
            return 1.0
        return max(1.0, acc[0] / acc[1])

    def detectable_lever_arm_m(self, yaw_rate_rps: float) -> float:
        """The smallest horizontal lever-arm error the mean test finds at this yaw rate with 90 %
        power if the innovations carried its whole signature (minimal detectable bias, Baarda 1968;
        Teunissen 2000 *Testing theory* ch. 4): an error dl gives the GNSS velocity innovations a
        body-frame mean |w| dl, so over a block of n updates of sd sigma_v the statistic is
        |w| dl sqrt(n) / sigma_v, found when dl >= (limit + 1.28) sigma_v / (|w| sqrt(n)). The
        filter absorbs part of that signature (``FaultTolerantSolution`` accounts for it); this
        figure only gates the turn counting of ``verify_turn_deg``."""
        n = self.vel_updates_per_block
        w = abs(yaw_rate_rps)
        if n < _MIN_MEAN_UPDATES or w <= 0 or not math.isfinite(self.vel_innovation_sd_mps):
            return math.inf
        return (self.mean_z_limit + 1.28) * self.vel_innovation_sd_mps / (w * math.sqrt(n))

    def feed_motion(self, t_s: float, dt_s: float, yaw_rate_rps: float, speed_mps: float) -> None:
        """Vehicle motion over the last dt_s: the turn counts toward ``verify_turn_deg`` when moving
        with GNSS updates (within the last second) and turning fast enough that the test would find
        a lever-arm error of ``detectable_m``."""
        if self.verify_turn_rad <= 0.0:
            return
        if speed_mps < self.min_speed_mps or t_s - self.t_last_gnss_s > 1.0 or t_s < self.t_settled_s:
            return
        if self.detectable_lever_arm_m(yaw_rate_rps) > self.detectable_m:
            return
        self.turn_since_fail_rad += abs(yaw_rate_rps) * max(dt_s, 0.0)

    @property
    def verified(self) -> bool:
        return (not self.failed and self.turn_since_fail_rad >= self.verify_turn_rad
                and self.protection_m <= self.protection_limit_m)

    @property
    def state(self) -> str:
        if self.failed:
            return INCONSISTENT
        return VERIFIED if self.verified else UNVERIFIED

    def summary(self) -> dict:
        return {"state": self.state, "failures": self.failures, "releases": self.releases,
                "variance_alarms": self.variance_alarms,
                "last_failure_t_s": self.last_failure_t_s, "protection_m": self.protection_m,
                "turn_since_failure_deg": math.degrees(self.turn_since_fail_rad),
                "window": {k: list(v) for k, v in self.last_statistic.items()}}


def widen_lever_arm(P: np.ndarray, lever_index: int, pos_index: int, vel_index: int, C_nb: np.ndarray,
                    rate_body_rps: np.ndarray, sd_m: float, axes: tuple = (0, 1)) -> np.ndarray:
    """P with the lever arm's variance on ``axes`` (body x, y) raised to ``sd_m``^2, as the filter's
    errors would be if the antenna were off by an extra dl ~ N(0, (sd_m^2 - P_ll) I) on those axes.

    A filter that tracks its GNSS antenna (10 Hz fixes of 1 cm) while holding a lever arm that is
    wrong by dl puts the IMU point where the antenna minus the wrong lever arm is: its position
    error is -C_nb dl and its velocity error -C_nb (w x dl) (the GNSS models of ``updates``).
    So the widened covariance is ``P + G D G^T`` with G = [-C_nb; -C_nb [w x]; I] on
    (position, velocity, lever arm) and D the added variance -- not a bare diagonal entry, which
    would claim the IMU point known to centimetres while its antenna offset is unknown to
    decimetres (a consider-parameter view, Bar-Shalom et al. 2001 sec. 9.3). Axes already that
    uncertain are left alone."""
    P = P.copy()
    n = P.shape[0]
    W = skew(rate_body_rps)
    for a in axes:
        add = sd_m ** 2 - P[lever_index + a, lever_index + a]
        if not add > 0:
            continue
        e = np.zeros(3)
        e[a] = 1.0
        g = np.zeros(n)
        g[pos_index:pos_index + 3] = -C_nb @ e
        g[vel_index:vel_index + 3] = -C_nb @ (W @ e)
        g[lever_index + a] = 1.0
        P += add * np.outer(g, g)
    return 0.5 * (P + P.T)
