"""The batch estimator of ``v2xpos calibrate``: fit replays at effect vectors theta, their residual
rows (``rows``), the finite-difference Jacobian, Gauss-Newton with backtracking, chord refinement
with a central-difference Jacobian at the final iterate, and significance by backward elimination
with replays (docs/calibration.md gives the reasoning).
"""
from __future__ import annotations

import numpy as np

from v2xpos.ins.config import overridden
from v2xpos.ins.profiles import DEFAULT_PROFILE
from v2xpos.types import Dataset

from . import identify
from .identify import Fit, LinearProblem
from .inject import (N_PARAMS, PARAM_NAMES, P_ACCEL_SCALE, P_CLOCK_DRIFT, P_GNSS_LATENCY, P_GYRO_SCALE, P_LEVER_ARM,
                     P_MISALIGN, P_TIME_OFFSET, EffectSet, correct)
from .rows import ROLL_SYSTEMATIC_SD_RAD, RowSet, align, ref_times, residual_rows, roll_block_sd
from .runner import OutageSchedule, ReplayOutcome, replay

FD_STEP = np.zeros(N_PARAMS)
FD_STEP[P_TIME_OFFSET] = 0.02
FD_STEP[P_MISALIGN] = 0.01
FD_STEP[P_LEVER_ARM] = 0.1
FD_STEP[P_GYRO_SCALE] = 0.01
FD_STEP[P_ACCEL_SCALE] = 0.01
"""Finite-difference steps (s, rad, m, fraction): large against replay round-off, small against
the curvature of the innovation sequence."""



def active_parameters(platform: str) -> np.ndarray:
    """Parameters estimated per platform. Left out (value 0, sd = prior, never significant):
    roll/pitch-axis gyro scale (a car or a walker barely rotates about them) and the vertical
    accelerometer scale (against ~1 g it is the vertical accelerometer bias the filter already
    estimates); for a pedestrian or a generic platform also the mounting misalignment, which
    only the vehicle constraints see."""
    a = np.ones(N_PARAMS, bool)
    a[P_GYRO_SCALE.start:P_GYRO_SCALE.start + 2] = False
    a[P_ACCEL_SCALE.stop - 1] = False
    if platform != "car":
        a[P_MISALIGN] = False
    return a


def default_prior_sd(ds: Dataset) -> np.ndarray:
    """Weakly informative priors; dataset notes may override the timing ones:
    ``imu_time_offset_prior_sd_s`` (default 0.1 s) and ``gnss_latency_prior_sd_s`` (default 1 ms:
    post-processed RTK solutions are tagged with their measurement epoch)."""
    p = np.zeros(N_PARAMS)
    p[P_TIME_OFFSET] = float(ds.notes.get("imu_time_offset_prior_sd_s", 0.1))
    p[P_CLOCK_DRIFT] = float(ds.notes.get("imu_clock_drift_prior_sd_ppm", 200.0))
    p[P_GNSS_LATENCY] = float(ds.notes.get("gnss_latency_prior_sd_s", 1e-3))
    p[P_MISALIGN] = np.radians(10.0)
    p[P_LEVER_ARM] = max(float(ds.lever_arm_sd_m), 0.5)
    p[P_GYRO_SCALE] = 0.02
    p[P_ACCEL_SCALE] = 0.02
    return p



CALIBRATION_REPLAY_CONFIG = {"gnss": {"gate_probability": 1.0}}
"""Replays that feed the fit run without the chi-square gate (a gate decision that flips between
two replays makes the innovation sequence jump and spoils the finite differences) and without the
receiver's velocities when they lag the positions: an RTK engine's velocity may be a smoothed,
lagged state (``kinematic.velocity_lag`` compares the course from velocities and from positions
against the gyro); a lag would bias the time offset, and positions are the outage reference."""
EXACT_EPOCHS = True
"""Fit replays bring the state exactly to each GNSS epoch and apply the vehicle constraints mid-way
between epochs (``runner.replay``): with the constraints at chunk ends and the GNSS update
extrapolated from the last sample, the replayed cost jumped whenever a stamp shift moved a GNSS
epoch past an IMU sample, by as much as a few milliseconds of offset cost (docs/calibration.md,
Exact epochs in the fit replays)."""

TUNE_PREDICTOR = True
"""Fit replays run a filter whose noise matches the recording (``Estimator.tune``, ``tuning.py``):
a prediction-error fit through a mistuned filter uses parameters that change the filter's gains
(e.g. a vertical lever arm on a flat road) to whiten the residuals."""

CALIBRATION_OUTAGES = OutageSchedule(length_s=5.0, every_s=15.0, first_s=20.0)
"""Short GNSS gaps in the fit replays: the first innovation after each gap is a 5 s dead-reckoning
prediction error, so the likelihood also weighs the multi-step prediction that outages need
(k-step-ahead prediction-error identification, Ljung 1999 sec. 7.3)."""


class Progress:
    """One progress bar for the whole calibration: a tick per replay, the current step shown beside
    it. The number of replays is known only roughly in advance (backtracking, elimination rounds),
    so the total grows when it is reached."""

    def __init__(self, enabled: bool, total: int = 40, desc: str = "calibrate"):
        self.bar = None
        if enabled:
            from tqdm import tqdm
            self.bar = tqdm(total=total, desc=desc, unit="replay", dynamic_ncols=True,
                            bar_format="{desc}: {n}/{total} replays |{bar}| {elapsed}<{remaining} {postfix}")

    def start(self, label: str) -> None:
        if self.bar is not None:
            self.bar.set_postfix_str(label, refresh=True)

    def done(self) -> None:
        if self.bar is not None:
            if self.bar.n + 1 > self.bar.total:
                self.bar.total = self.bar.n + 2
            self.bar.update(1)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.total = self.bar.n
            self.bar.set_postfix_str("done", refresh=True)
            self.bar.close()


NO_PROGRESS = Progress(False)


class Estimator:
    """Batch estimator bound to one recording; keeps the Jacobian so that recordings derived from
    the same drive (e.g. with injected effects) can be fitted with a couple of replays."""

    def __init__(self, ds: Dataset, progress: bool | Progress = False, prior_sd: np.ndarray | None = None,
                 profile: str = DEFAULT_PROFILE):
        self.ds = ds
        self.profile = profile          # the live filter's profile (``coarse``, ``online``)
        self.bar = progress if isinstance(progress, Progress) else NO_PROGRESS
        self.progress = bool(progress) and not isinstance(progress, Progress)   # per-replay bars
        self.prior_sd = default_prior_sd(ds) if prior_sd is None else prior_sd
        self.t0_s = float(ds.imu.t_s[0])
        self.replays = 0
        self.weights: dict | None = None
        self.roll_sd = np.radians(1.0)
        self.base_rows: RowSet | None = None
        self.theta_lin = np.zeros(N_PARAMS)
        self.J: np.ndarray | None = None
        self.coarse_report: dict = {}
        self.active = active_parameters(ds.platform)
        self.schedule: OutageSchedule | None = CALIBRATION_OUTAGES
        self.velocity_lag: tuple | None = None
        self.config = overridden({}, CALIBRATION_REPLAY_CONFIG)
        self.exact_epochs = EXACT_EPOCHS
        self.confirm_log: list = []      # (effect, half-cost rises, kappa, z in the model) per test
        self.tune_predictor = TUNE_PREDICTOR
        self.tuning: dict = {}

    def _replay(self, ds: Dataset, theta: np.ndarray, label: str) -> ReplayOutcome:
        self.replays += 1
        self.bar.start(label)
        out = replay(correct(ds, EffectSet.from_vector(theta)), self.schedule, config=self.config,
                     progress=self.progress, label=label, exact_epochs=self.exact_epochs)
        self.bar.done()
        return out

    def coarse(self) -> np.ndarray:
        """Starting point from the filter's own augmented effect states (lever arm, IMU time offset,
        misalignment), one ``v2xpos replay`` run without outages."""
        from v2xpos.ins.replay_engine import OutageSchedule as InsSchedule
        from v2xpos.ins.replay_engine import config_for
        from v2xpos.ins.replay import replay as ins_replay
        if self.ds.calibration is not None and self.ds.calibration.effects:
            # a vehicle that is already calibrated: its table is the starting point
            from .writeback import theta_from_table
            th = np.where(self.active, theta_from_table(self.ds.calibration)[0], 0.0)
            self.coarse_report = {"from": "[calibration] table of the dataset"}
            self.check_velocity_lag(th)
            return th
        cfg = config_for(self.ds, self.profile, effects={"states": ("lever_arm", "imu_time_offset", "misalignment")})
        self.bar.start("online effect states (starting point)")
        res = ins_replay(self.ds, InsSchedule(0.0, 0.0, 0.0), cfg=cfg, progress=self.progress, keep_series=False)
        self.bar.done()
        self.replays += 1
        rep = res.summary.get("effects", {})
        self.coarse_report = {k: v for k, v in rep.items() if k != "sd"}
        th = np.zeros(N_PARAMS)
        th[P_TIME_OFFSET] = float(rep.get("imu_time_offset_s", 0.0))
        if self.active[P_MISALIGN].all():
            th[P_MISALIGN] = np.asarray(rep.get("misalignment_rad", np.zeros(3)), float)
        th[P_LEVER_ARM] = np.asarray(rep.get("lever_arm_m", self.ds.lever_arm_m), float) - np.asarray(self.ds.lever_arm_m)
        self.check_velocity_lag(th)
        return th

    def online(self) -> dict:
        """The live filter's own effect states on this recording: ``v2xpos replay``'s filter (its
        default effect states and noise) with the effect priors of this fit, one run without outages.
        Returns {parameter index: (value at the end of the drive, sd)} in the ``inject.P_*`` units
        (IMU offset, mounting, lever arm relative to the declared one)."""
        from v2xpos.ins.replay_engine import OutageSchedule as InsSchedule
        from v2xpos.ins.replay_engine import config_for
        from v2xpos.ins.replay import replay as ins_replay
        p = self.prior_sd
        lever_sd = p[P_LEVER_ARM].copy()
        # a vertical antenna offset moves the antenna only through roll and pitch, which a car
        # hardly has: online it trades against the IMU height (antenna height = IMU height - l_z)
        # and a loose prior lets both wander (on a convoy follower l_z ran far beyond the 0.5 m
        # prior); it starts from the declaration, as the live filter does
        lever_sd[2] = float(self.ds.lever_arm_sd_m)
        cfg = config_for(self.ds, self.profile, effects={"effect_initial_sd": {
            "lever_arm": lever_sd, "imu_time_offset": float(p[P_TIME_OFFSET]), "misalignment": p[P_MISALIGN].copy()}})
        self.bar.start("online effect states (agreement)")
        res = ins_replay(self.ds, InsSchedule(0.0, 0.0, 0.0), cfg=cfg, progress=self.progress, keep_series=False)
        self.bar.done()
        self.replays += 1
        rep = res.summary.get("effects", {})
        sds = rep.get("sd", {})
        out = {}
        if "imu_time_offset" in sds:
            out[P_TIME_OFFSET] = (float(rep["imu_time_offset_s"]), float(sds["imu_time_offset"][0]))
        if "misalignment" in sds:
            for k in range(3):
                out[P_MISALIGN.start + k] = (float(rep["misalignment_rad"][k]), float(sds["misalignment"][k]))
        if "lever_arm" in sds:
            lever = np.asarray(rep["lever_arm_m"], float) - np.asarray(self.ds.lever_arm_m, float)
            for k in range(3):
                out[P_LEVER_ARM.start + k] = (float(lever[k]), float(sds["lever_arm"][k]))
        self.online_t_end_s = float(self.ds.imu.t_s[-1] - self.t0_s)
        return out

    def tune(self, theta: np.ndarray, iterations: int = 2) -> dict:
        """Make the fit replays' filter match the recording (``tuning``): IMU white noise from the
        samples, then the GNSS position and velocity noise rescaled until the filter's innovation
        covariances match its innovations (``iterations`` replays at theta); the vehicle
        constraints keep their declared noise (``tuning`` module docstring)."""
        from v2xpos.ins.config import InsConfig
        from .tuning import imu_noise_density, innovation_scale, rescaled_config
        d = InsConfig()
        gyro, accel = imu_noise_density(self.ds.imu)
        # the second-difference estimate bounds the in-band white noise from above (it weighs
        # high-frequency vibration up to 16/6 times): below the filter's default it shows the
        # default is too large and replaces it; above it, the excess may be out-of-band vibration
        # and the default stays (a driving vehicle's vibration can put it several times above the
        # in-band noise its stops show; docs/calibration.md, Allan deviation at the stops)
        if np.isfinite(gyro) and gyro > 0:
            self.config = overridden(self.config, {"imu": {
                "gyro_noise_rps_rthz": min(gyro, d.imu.gyro_noise_rps_rthz)}})
        if np.isfinite(accel) and accel > 0:
            self.config = overridden(self.config, {"imu": {
                "accel_noise_mps2_rthz": min(accel, d.imu.accel_noise_mps2_rthz)}})
        base = {k: getattr(d.gnss, k) for k in ("gnss_pos_sd_floor_m", "gnss_vel_sd_scale", "gnss_vel_sd_floor_mps")}
        history = []
        for k in range(iterations):
            out = self._replay(self.ds, theta, f"tuning {k + 1}")
            fac = innovation_scale(out.log)
            history.append(fac)
            self.config = rescaled_config(self.config, base, fac)
        self.tuning = {"gyro_noise_rps_rthz": gyro, "accel_noise_mps2_rthz": accel, "factors": history,
                       "config": overridden({}, self.config)}
        return self.tuning

    def check_velocity_lag(self, theta: np.ndarray) -> None:
        """Leave the receiver velocities out of the fit when they lag the positions by > 3 sd."""
        from v2xpos.rotation import dcm_from_euler
        from .kinematic import velocity_lag
        C = dcm_from_euler(*theta[P_MISALIGN]) @ np.asarray(self.ds.imu_to_body, float)
        self.velocity_lag = velocity_lag(self.ds.imu, self.ds.gnss, C)
        if self.velocity_lag is not None:
            lag, sd = self.velocity_lag
            self.config = overridden(self.config, {"gnss": {"use_gnss_velocity": not (abs(lag) > 3.0 * sd)}})

    def replayed_residuals(self, ds: Dataset, theta: np.ndarray, label: str) -> np.ndarray:
        """Residuals of a replay at theta on the rows of the linearisation point; rows missing in
        the replay keep their linearisation value."""
        rows, _ = self.rows(ds, theta, label)
        r = align(self.base_rows, rows)
        return np.where(np.isfinite(r), r, self.base_rows.r)

    def true_cost(self, ds: Dataset, theta: np.ndarray, label: str) -> float:
        """Residual cost of a replay at theta (``replayed_residuals``)."""
        r = self.replayed_residuals(ds, theta, label)
        return float(r @ r)

    def rows(self, ds: Dataset, theta: np.ndarray, label: str) -> tuple[RowSet, ReplayOutcome]:
        out = self._replay(ds, theta, label)
        rows, _ = residual_rows(out.log, EffectSet.from_vector(theta), self.weights, self.t0_s, self.roll_sd,
                                ref_times(ds, theta), self.exact_epochs)
        return rows, out

    def set_baseline(self, theta0: np.ndarray) -> RowSet:
        """Replay ``self.ds`` at theta0 and make its rows the reference of every later replay: the
        row keys, the per-kind weights (variance components) and the roll block sd."""
        out = self._replay(self.ds, theta0, "linearisation point")
        self.roll_sd = roll_block_sd(out.log, self.t0_s)
        self.base_rows, self.weights = residual_rows(out.log, EffectSet.from_vector(theta0), None,
                                                     self.t0_s, self.roll_sd, ref_times(self.ds, theta0),
                                                     self.exact_epochs)
        return self.base_rows

    def linearize(self, theta0: np.ndarray, keep_weights: bool = False) -> RowSet:
        """Rows at theta0 and the finite-difference Jacobian there (one replay per parameter)."""
        if not keep_weights or self.weights is None:
            rows0 = self.set_baseline(theta0)
        else:
            rows0, _ = self.rows(self.ds, theta0, "linearisation point")
        r0 = align(self.base_rows, rows0)
        self.theta_lin = theta0.copy()
        J = np.zeros((len(self.base_rows.r), N_PARAMS))
        it = [p for p in np.flatnonzero(FD_STEP > 0) if self.active[p]]
        if self.progress:
            from tqdm import tqdm
            it = tqdm(it, desc="jacobian", unit="replay", leave=False)
        for p in it:
            th = theta0.copy()
            th[p] += FD_STEP[p]
            rows, _ = self.rows(self.ds, th, f"Jacobian d/d {PARAM_NAMES[p]}")
            J[:, p] = (align(self.base_rows, rows) - r0) / FD_STEP[p]
        self.J = self._with_timing_columns(J)
        return rows0

    def _with_timing_columns(self, J: np.ndarray) -> np.ndarray:
        """J with the GNSS latency and clock drift columns taken from the IMU offset's (in place):
        identical relative timing, GNSS latency (tags moved back) = IMU offset (stamps moved on); a
        slow clock drift acts as the local offset 1e-6 d (t - t0) (filter memory << drive)."""
        J[:, P_GNSS_LATENCY] = J[:, P_TIME_OFFSET]
        J[:, P_CLOCK_DRIFT] = J[:, P_TIME_OFFSET] * 1e-6 * (self.base_rows.t_s - self.t0_s)
        return J

    def problem(self, rows: RowSet, theta: np.ndarray) -> LinearProblem:
        """Linear problem at theta from residual rows of a replay at theta and the stored J."""
        r = align(self.base_rows, rows)
        ok = np.isfinite(r) & np.all(np.isfinite(self.J), axis=1)
        return LinearProblem(r=r[ok], J=self.J[ok], theta0=theta.copy(), t_s=self.base_rows.t_s[ok],
                             prior_sd=self.prior_sd, active=self.active.copy())

    def systematic_sd(self) -> np.ndarray:
        s = np.zeros(N_PARAMS)
        s[P_MISALIGN.start] = ROLL_SYSTEMATIC_SD_RAD
        return s

    def gauss_newton(self, theta_start: np.ndarray, iterations: int = 2) -> np.ndarray:
        """Gauss-Newton with the Jacobian taken again at every iterate (on ``self.ds``); each step
        is accepted only if the replayed cost drops, else halved (backtracking, at most 3 times)."""
        theta = theta_start.copy()
        for k in range(iterations):
            if self.tune_predictor and k == 0:
                # the predictor is tuned once, at the starting point, and then held: every later
                # replay (Jacobian, refinement, elimination) runs the same filter, so that costs and
                # weights stay comparable. (Re-tuning at every iterate was tried: it inflated the
                # lever-arm and time-offset sds and the elimination dropped them; docs/calibration.md,
                # What the fit needs from its predictor.)
                self.tune(theta, iterations=2)
            rows0 = self.linearize(theta, keep_weights=k > 0)
            c0 = float(np.nansum(align(self.base_rows, rows0) ** 2))
            step = identify.fit(self.problem(rows0, theta), systematic_sd=self.systematic_sd()).theta - theta
            for _ in range(4):
                c1 = self.true_cost(self.ds, theta + step, f"GN {k + 1} trial")
                if c1 < c0:
                    theta = theta + step
                    break
                step = step / 2.0
            else:
                break
        return theta

    def central_jacobian(self, ds: Dataset, theta: np.ndarray, label: str = "Jacobian at the estimate") -> np.ndarray:
        """Central-difference Jacobian of the residual rows of ``ds`` at theta (two replays per active
        parameter with an ``FD_STEP``): ``J_p = (r(theta + h e_p) - r(theta - h e_p)) / 2h``, error
        O(h^2) against O(h) for the one-sided difference of ``linearize``, which is the slope at
        theta + h/2 (10 ms away for the IMU offset). The GNSS latency and clock drift columns follow
        from the IMU offset's (``_with_timing_columns``)."""
        J = np.zeros((len(self.base_rows.r), N_PARAMS))
        for p in [p for p in np.flatnonzero(FD_STEP > 0) if self.active[p]]:
            side = []
            for sign in (+1.0, -1.0):
                th = theta.copy()
                th[p] += sign * FD_STEP[p]
                rows, _ = self.rows(ds, th, f"{label} d/d {PARAM_NAMES[p]} ({'+' if sign > 0 else '-'})")
                side.append(align(self.base_rows, rows))
            J[:, p] = (side[0] - side[1]) / (2.0 * FD_STEP[p])
        return self._with_timing_columns(J)

    def refine(self, ds: Dataset, theta_start: np.ndarray, iterations: int = 1) -> tuple[Fit, LinearProblem, ReplayOutcome]:
        """Fit of ``ds`` from theta_start: ``iterations`` chord (simplified Gauss-Newton) steps with
        the stored finite-difference Jacobian held fixed, then the Jacobian taken again at the final
        iterate by central differences (``central_jacobian``) and the MAP step and sds computed
        with it (Dennis & Schnabel 1983, "Numerical Methods for Unconstrained Optimization and
        Nonlinear Equations", secs. 5.4 and 10.2).

        Why not a secant (Broyden 1965) update of J (docs/calibration.md, Method and why): (1) Broyden's
        update is the least change of J in the Frobenius norm of the raw parameter units, so it is not
        invariant to their scaling: with seconds, ppm, radians and metres a clock-drift step of a few
        ppm dominated |dtheta|^2 and the rank-one corrections landed in the drift column. (2) Scaled
        versions (least change in the metric of the prior covariance, or of the information J^T J +
        P0^-1, which is invariant to linear reparametrisation) do not help, because the secant
        difference r(theta + s) - r(theta) - J s over the refinement's steps (milliseconds, a few ppm,
        fractions of a mrad) is not a derivative of the replays but a large part of |J s| (the replays
        are not smooth at that scale; a difference quotient needs a step large against that noise, More
        & Wild 2012, ACM TOMS 38(3)). (3) The update depends on the path, so two fits of the same drive,
        one with an injected effect, end at different points of J^T r = 0: the estimate is then not
        equivariant under ``inject``/``correct``, which the replayed residuals are (r_injected(theta +
        e) = r(theta)); every metric tried for the update (raw units, the prior's, the information's)
        moved some paired single-effect test, no update none.
        Why the Jacobian at the final iterate: the chord iterations converge to the point where the
        stored (one-sided, linearisation-point) J satisfies J^T r + P0^-1 theta = 0, which is not a
        stationary point of the replayed cost when J changes between there and here; the step with
        the central-difference Jacobian at the chord point lowers the replayed cost further. Cost:
        two replays per active parameter. Both steps are equivariant under
        ``inject``/``correct``, so paired fits move only by the injected effect."""
        theta = theta_start.copy()
        rows, out = self.rows(ds, theta, "refine start")
        for k in range(iterations):
            new = identify.fit(self.problem(rows, theta), systematic_sd=self.systematic_sd()).theta
            rows, out = self.rows(ds, new, f"refine {k + 1}")
            theta = new
        J_saved = self.J
        try:
            self.J = self.central_jacobian(ds, theta)
            prob = self.problem(rows, theta)
            f = identify.decide(prob, identify.fit(prob, systematic_sd=self.systematic_sd()))
            return f, prob, out
        finally:
            self.J_refined = self.J
            self.J = J_saved

    def confirm(self, ds: Dataset, f: Fit, prob: LinearProblem, n_sigma: float = 3.0) -> Fit:
        """Real error reduction, by backward elimination with replays: the candidates are the
        effects beyond the t(dof) equivalent of 3 sd (``Fit.threshold_sd``); in the current model (all active parameters minus those dropped,
        estimated together by ``identify.refit``) each candidate is removed in turn, the others
        re-estimated without it, and the recording replayed. A candidate stays only if the replayed
        cost rises in BOTH halves of the recording and in total by more than ``n_sigma^2 kappa``,
        where ``kappa = (sd / sd_white)^2`` is the variance factor of the robust (Normal-
        equivalent) sd over the white-residual one and ``n_sigma`` is replaced by the parameter's
        ``threshold_sd`` in the current model: in the linear model the cost rise is
        ``(value / sd_white)^2``, so this is the same t(dof) test again, with the replay in place
        of the linearisation (a likelihood-ratio test with the same non-whiteness allowance), and
        if it is still beyond that threshold in the current model. Otherwise the candidate with the smallest ``rise / kappa`` is dropped and the rest
        are tested again in the model without it.
        The refit lets correlated parameters take over what they can: an IMU time offset and a
        forward lever arm that only trade along ``l_x - v tau`` (docs/calibration.md) each look
        necessary while the other is held at its joint estimate, but not when it may move.
        The significant effects' values and sd become those of the final model; the others keep
        the joint fit's."""
        cand = [int(i) for i in np.flatnonzero(prob.active & f.determined
                                               & (np.abs(f.theta) > f.threshold_sd(n_sigma) * f.sd))]
        t_mid = float(np.median(prob.t_s))
        first = self.base_rows.t_s < t_mid
        gain = np.zeros(N_PARAMS)
        model = prob.active.copy()
        sys_sd = self.systematic_sd()

        def half_costs(theta: np.ndarray, label: str) -> np.ndarray:
            r = self.replayed_residuals(ds, theta, label)
            return np.array([np.sum(r[h] ** 2) for h in (first, ~first)])

        self.confirm_log = []
        fm = identify.fit(prob, systematic_sd=sys_sd, active=model)
        c_with = half_costs(fm.theta, "model") if cand else None
        while cand:
            sd_w = fm.sd_white
            kappa = np.maximum(np.where(sd_w > 0, (fm.sd_stat / np.where(sd_w > 0, sd_w, 1.0)) ** 2, 1.0), 1.0)
            thr = fm.threshold_sd(n_sigma)
            worst, worst_z2, tried = None, np.inf, {}
            for i in cand:
                without = model.copy()
                without[i] = False
                th = identify.refit(prob, without)
                c = half_costs(th, f"without {PARAM_NAMES[i]}")
                tried[i] = c
                d = c - c_with
                gain[i] = float(d.sum())
                z2 = gain[i] / kappa[i]
                keep = np.all(d > 0) and z2 > thr[i] ** 2 and abs(fm.theta[i]) > thr[i] * fm.sd[i]
                self.confirm_log.append((PARAM_NAMES[i], d.tolist(), float(kappa[i]), float(fm.theta[i] / fm.sd[i])))
                if not keep and z2 < worst_z2:
                    worst, worst_z2 = i, z2
            if worst is None:
                break
            model[worst] = False
            cand.remove(worst)
            fm = identify.fit(prob, systematic_sd=sys_sd, active=model)
            c_with = tried[worst]                # the model without it was just replayed
        sig = np.zeros(N_PARAMS, bool)
        sig[cand] = True
        f.theta = np.where(sig, fm.theta, f.theta)
        f.sd = np.where(sig, fm.sd, f.sd)
        f.sd_stat = np.where(sig, fm.sd_stat, f.sd_stat)
        f.dof = np.where(sig, fm.dof, f.dof)
        f.bandwidth_s = np.where(sig, fm.bandwidth_s, f.bandwidth_s)
        f.cv_gain = gain
        f.significant = sig
        return f

