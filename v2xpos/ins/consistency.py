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

So the monitor keeps two facts per vehicle (``ConsistencyMonitor``):

* **failed**: over the last ``window_s``, (a) the sum of the GNSS position (and, separately,
  velocity) NIS exceeds the chi-square quantile ``1 - false_alarm`` of its degrees of freedom
  (each update's NIS capped at the quantile ``1 - 1e-9`` of its own dof, so that one gross outlier
  counts as a strong, not an infinite, piece of evidence), or (b) the normalised innovations'
  window mean along body x or y, times sqrt(n), exceeds ``mean_z_limit`` (N(0, 1) for a consistent
  filter; the innovations of a filter whose noise is pessimistic have a smaller spread, so the
  test is conservative there);
* **latched**: a failure stays (``INCONSISTENT``) for the rest of the session unless ``reverify``:
  it is evidence of an effect the filter's model lacks, and the same test passing in later turns
  says nothing of the straight road in between, where that effect is a bias no test sees (on
  generated convoys, re-verifying after 45 deg of passing turns left 1,500-1,800 VALID rows per
  run beyond max(0.3 m, 4 sigma) on 3 of 10 followers). The remedy is a calibration
  (``v2xpos calibrate`` writes the ``[calibration]`` table the filter then starts from);
* **excitation**: only turning fast enough counts, i.e. while the lever-arm error the mean test
  would find with 90 % power (``detectable_lever_arm_m``, the minimal detectable bias of the
  test) is at most ``detectable_m`` = 0.3 m (the error a reference must not hide). At a velocity
  innovation sd of 0.05 m/s and 50 updates per window this is a yaw rate of about 0.1 rad/s
  (6 deg/s); a 45 deg curve at 2 deg/s, which let a 0.6 m lever-arm error through, does not count;
* **verified**: since the last failure (or the start), the vehicle has turned by at least
  ``verify_turn_deg`` (the integral of |yaw rate| while it moves faster than ``min_speed_mps``,
  with GNSS updates arriving) without a failure -- the test has then had the excitation that
  reveals a wrong lever arm, mounting or gyro scale.

``state`` is then ``VERIFIED``, ``UNVERIFIED`` (no failure yet, not enough turning) or
``INCONSISTENT`` (a failure since the last verification). Updates within ``settle_s`` of the
heading being set are not tested (the filter is still converging from its initial covariance).
"""
from __future__ import annotations

import math
from collections import deque

import numpy as np
from scipy.stats import chi2

VERIFIED, UNVERIFIED, INCONSISTENT = "verified", "unverified", "inconsistent"
_CAP_PROBABILITY = 1e-9


class ConsistencyMonitor:
    """Windowed NIS test and turn-excitation bookkeeping of one filter (see module docstring)."""

    def __init__(self, window_s: float = 5.0, false_alarm: float = 1e-4, verify_turn_deg: float = 45.0,
                 min_speed_mps: float = 1.0, settle_s: float = 5.0, kinds: tuple = ("gnss_pos", "gnss_vel"),
                 mean_z_limit: float = 3.0, mean_window_s: float | None = None, reverify: bool = False,
                 detectable_m: float = 0.3):
        self.window_s = float(window_s)
        self.false_alarm = float(false_alarm)
        self.verify_turn_rad = math.radians(verify_turn_deg)
        self.min_speed_mps = float(min_speed_mps)
        self.settle_s = float(settle_s)
        self.kinds = tuple(kinds)
        self._win: dict[str, deque] = {k: deque() for k in self.kinds}
        self._sum: dict[str, list] = {k: [0.0, 0] for k in self.kinds}
        self.mean_z_limit = float(mean_z_limit)
        self.reverify = bool(reverify)
        self.detectable_m = float(detectable_m)
        self.vel_innovation_sd_mps = math.inf
        self.mean_window_s = float(window_s if mean_window_s is None else mean_window_s)
        self._mwin: dict[str, deque] = {k: deque() for k in self.kinds}
        self._msum: dict[str, list] = {k: [0.0, 0.0, 0] for k in self.kinds}
        self._threshold: dict[int, float] = {}
        self._cap: dict[int, float] = {}
        self.failed = False
        self.turn_since_fail_rad = 0.0
        self.t_settled_s = -math.inf
        self.t_last_gnss_s = -math.inf
        self.failures = 0
        self.last_failure_t_s = math.nan
        self.last_statistic: dict[str, tuple] = {}

    def restart(self, t_s: float) -> None:
        """The filter (re)set its heading at t_s: test its updates from t_s + settle_s."""
        self.t_settled_s = float(t_s) + self.settle_s
        for k in self.kinds:
            self._win[k].clear()
            self._sum[k] = [0.0, 0]
            self._mwin[k].clear()
            self._msum[k] = [0.0, 0.0, 0]

    def _quantile(self, dof: int) -> float:
        q = self._threshold.get(dof)
        if q is None:
            q = self._threshold[dof] = float(chi2.ppf(1.0 - self.false_alarm, dof))
        return q

    def _capped(self, nis: float, dof: int) -> float:
        c = self._cap.get(dof)
        if c is None:
            c = self._cap[dof] = float(chi2.ppf(1.0 - _CAP_PROBABILITY, dof))
        return c if not math.isfinite(nis) else min(nis, c)

    def feed_update(self, kind: str, t_s: float, nis: float, dof: int, innovation=None, S=None,
                    C_nb=None) -> bool:
        """One GNSS update (accepted or rejected by the gate): its NIS and, for the mean test, its
        innovation (NED), innovation covariance S and the attitude C_nb. True when the test failed
        at this update (the filter reacts: ``InsFilter._on_inconsistency``)."""
        if kind not in self._win:
            return False
        self.t_last_gnss_s = float(t_s)
        if t_s < self.t_settled_s:
            return False
        win, acc = self._win[kind], self._sum[kind]
        x = self._capped(float(nis), int(dof))
        win.append((float(t_s), x, int(dof)))
        acc[0] += x
        acc[1] += int(dof)
        while win and win[0][0] <= t_s - self.window_s:
            _, x0, d0 = win.popleft()
            acc[0] -= x0
            acc[1] -= d0
        total, dof_sum = acc
        limit = self._quantile(dof_sum) if dof_sum > 0 else math.inf
        self.last_statistic[kind] = (total, dof_sum, limit)
        fail = total > limit
        if innovation is not None and S is not None and C_nb is not None and len(innovation) == 3:
            fail |= self._mean_test(kind, float(t_s), innovation, S, C_nb)
        if fail:
            self.failed = True
            self.turn_since_fail_rad = 0.0
            self.failures += 1
            self.last_failure_t_s = float(t_s)
        return bool(fail)

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

    def clear_windows(self) -> None:
        """Forget the windowed sums (after the filter changed its model, e.g. widened an effect's
        covariance: the innovations before it no longer describe the filter that follows)."""
        for k in self.kinds:
            self._win[k].clear()
            self._sum[k] = [0.0, 0]
            self._mwin[k].clear()
            self._msum[k] = [0.0, 0.0, 0]

    def _mean_test(self, kind: str, t_s: float, innovation, S, C_nb) -> bool:
        """Window mean of the body-x / body-y normalised innovations (see module docstring)."""
        nu_b = C_nb.T @ np.asarray(innovation, float)
        S_b = C_nb.T @ np.asarray(S, float) @ C_nb
        sx, sy = math.sqrt(max(S_b[0, 0], 1e-30)), math.sqrt(max(S_b[1, 1], 1e-30))
        if kind == "gnss_vel":
            self.vel_innovation_sd_mps = max(sx, sy)
        zx, zy = float(nu_b[0]) / sx, float(nu_b[1]) / sy
        cap = 6.0
        zx, zy = max(-cap, min(cap, zx)), max(-cap, min(cap, zy))
        win, acc = self._mwin[kind], self._msum[kind]
        win.append((t_s, zx, zy))
        acc[0] += zx
        acc[1] += zy
        acc[2] += 1
        while win and win[0][0] <= t_s - self.mean_window_s:
            _, x0, y0 = win.popleft()
            acc[0] -= x0
            acc[1] -= y0
            acc[2] -= 1
        n = acc[2]
        if n < 10:
            return False
        r = 1.0 / math.sqrt(n)
        self.last_statistic[kind + "_mean"] = (acc[0] * r, acc[1] * r, self.mean_z_limit)
        return abs(acc[0]) * r > self.mean_z_limit or abs(acc[1]) * r > self.mean_z_limit

    def detectable_lever_arm_m(self, yaw_rate_rps: float) -> float:
        """The smallest horizontal lever-arm error the mean test finds at this yaw rate (minimal
        detectable bias, Baarda 1968; Teunissen 2000 *Testing theory* ch. 4): an error dl gives the
        GNSS velocity innovations a body-frame mean |w| dl, so over a window of n updates of sd
        sigma_v the statistic is |w| dl sqrt(n) / sigma_v, found with 90 % power (1.28 sd above the
        limit) when dl >= (limit + 1.28) sigma_v / (|w| sqrt(n))."""
        n = self._msum["gnss_vel"][2] if "gnss_vel" in self._msum else 0
        w = abs(yaw_rate_rps)
        if n < 10 or w <= 0 or not math.isfinite(self.vel_innovation_sd_mps):
            return math.inf
        return (self.mean_z_limit + 1.28) * self.vel_innovation_sd_mps / (w * math.sqrt(n))

    def feed_motion(self, t_s: float, dt_s: float, yaw_rate_rps: float, speed_mps: float) -> None:
        """Vehicle motion over the last dt_s: the turn counts toward verification when moving with
        GNSS updates (within the last second) and turning fast enough that the test would find a
        lever-arm error of ``detectable_lever_arm_m`` (a gentle curve turns the car without
        testing it)."""
        if speed_mps < self.min_speed_mps or t_s - self.t_last_gnss_s > 1.0 or t_s < self.t_settled_s:
            return
        if self.detectable_lever_arm_m(yaw_rate_rps) > self.detectable_m:
            return
        self.turn_since_fail_rad += abs(yaw_rate_rps) * max(dt_s, 0.0)
        if self.failed and self.reverify and self.turn_since_fail_rad >= self.verify_turn_rad:
            self.failed = False

    @property
    def verified(self) -> bool:
        return not self.failed and self.turn_since_fail_rad >= self.verify_turn_rad

    @property
    def state(self) -> str:
        if self.failed:
            return INCONSISTENT
        return VERIFIED if self.verified else UNVERIFIED

    def summary(self) -> dict:
        return {"state": self.state, "failures": self.failures, "last_failure_t_s": self.last_failure_t_s,
                "turn_since_failure_deg": math.degrees(self.turn_since_fail_rad),
                "window": {k: list(v) for k, v in self.last_statistic.items()}}
