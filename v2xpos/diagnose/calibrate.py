"""``v2xpos calibrate``: residuals -> missing effects -> calibrated model, before and after.

Pipeline (docs/calibration.md gives the reasoning):

1. *before*: replay with the declared model only (no effect states), with the outage schedule.
2. *coarse*: one replay with the filter's own augmented effect states (lever arm, IMU time offset,
   misalignment, gyro and accelerometer scale) gives a starting point theta_c for large effects.
3. *batch fit*: at theta_c the inputs are corrected (``inject.correct``) and replayed without
   outages; the whitened innovations r(theta) and their finite-difference Jacobian through the
   replay give a Gauss-Newton/MAP estimate (``identify``), refined by chord iterations with the
   same Jacobian. Robust sd, 3-sd + cross-validated significance, first/second half estimates.
4. *after*: the significant effects are corrected and the outage replay is run again.
"""
from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from v2xpos.ins.replay import (add_input_arguments, add_schedule_arguments, check_only, command_provenance,
                                  load_for_command)
from v2xpos.types import Dataset

from . import identify, structure
from .identify import Fit, LinearProblem
from .inject import (N_PARAMS, PARAM_NAMES, P_ACCEL_SCALE, P_CLOCK_DRIFT, P_GNSS_LATENCY, P_GYRO_SCALE, P_LEVER_ARM,
                     P_MISALIGN, P_TIME_OFFSET, EffectSet, correct)
from .residuals import ResidualLog
from .runner import OutageSchedule, ReplayOutcome, replay

ROLL_BLOCK_S = 30.0
ROLL_MIN_SPEED_MPS = 3.0
ROLL_SYSTEMATIC_SD_RAD = np.radians(0.5)
"""Road cross-slope left in the mean vehicle roll of a drive (crowned roads, driving on one side)."""

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


# ---------------------------------------------------------------------------------- residual rows
@dataclass
class RowSet:
    """Whitened residual rows of one replay: keys identify the same row across replays."""
    keys: np.ndarray
    r: np.ndarray
    t_s: np.ndarray


def _roll_rows(log: ResidualLog, t0_s: float, roll_sd_rad: float) -> tuple[list, list, list]:
    g = log["gnss_pos"]
    moving = g.speed_mps > ROLL_MIN_SPEED_MPS
    roll = g.rpy_rad[:, 0]
    blocks = np.floor((g.t_s - t0_s) / ROLL_BLOCK_S).astype(int)
    keys, vals, ts = [], [], []
    for b in np.unique(blocks[moving]):
        sel = moving & (blocks == b)
        if sel.sum() >= 20:
            keys.append(("roll", int(b), 0))
            vals.append(float(np.mean(roll[sel])) / roll_sd_rad)
            ts.append(float(np.mean(g.t_s[sel])))
    return keys, vals, ts


def residual_rows(log: ResidualLog, applied: EffectSet, weights: dict | None, t0_s: float,
                  roll_sd_rad: float, ref_times: tuple[float, float],
                  constraints_in_gnss_time: bool = False) -> tuple[RowSet, dict]:
    """Rows from GNSS position/velocity and NHC innovations (each component divided by the
    baseline innovation sd in ``weights``, or by its own sd when weights is None) plus the block
    mean vehicle roll. Keys are times relative to the first GNSS tag / first IMU stamp of the
    replayed recording (``ref_times``), with the applied clock drift removed, so that the same
    epoch keeps its key when stamps or tags are shifted; constraint rows applied at GNSS-defined
    times (``runner.replay(exact_epochs=True)``) are keyed like GNSS rows."""
    keys, vals, ts = [], [], []
    new_w = {}
    drift = applied.imu_clock_drift_ppm
    gnss0, imu0 = ref_times
    for kind in ("gnss_pos", "gnss_vel", "nhc"):
        if kind not in log:
            continue
        s = log[kind]
        if kind.startswith("gnss") or constraints_in_gnss_time:
            t_rel = s.t_s - gnss0
        else:
            t_rel = (s.t_s - imu0) / (1.0 + 1e-6 * drift)
        kms = np.round(t_rel * 1000.0).astype(np.int64)
        for i in range(len(s)):
            for c in range(s.innovation.shape[1]):
                key = (kind, int(kms[i]), c)
                sd = s.sd[i, c]
                if weights is None:
                    if not s.accepted[i] or not np.isfinite(sd) or sd <= 0:
                        continue
                    new_w[key] = sd
                    w = sd
                else:
                    w = weights.get(key)
                    if w is None:
                        continue
                val = s.innovation[i, c] / w
                if np.isfinite(val):
                    keys.append(key)
                    vals.append(val)
                    ts.append(float(s.t_s[i]))
    k, v, t = _roll_rows(log, t0_s, roll_sd_rad)
    keys += k
    vals += v
    ts += t
    if weights is None:
        for kk in k:
            new_w[kk] = roll_sd_rad
        # variance components: rescale each kind to unit mean square (Koch 1999, sec. 3.6), so that
        # an over- or under-confident filter tuning does not set the relative weights of the kinds
        kinds = np.array([kk[0] for kk in keys])
        vals_a = np.asarray(vals, float)
        for kind in set(kinds.tolist()):
            sel = kinds == kind
            if kind == "roll" or sel.sum() < 10:
                continue
            f = float(np.sqrt(np.mean(vals_a[sel] ** 2)))
            if f > 0:
                vals_a[sel] /= f
                for j in np.flatnonzero(sel):
                    new_w[keys[j]] *= f
        vals = vals_a.tolist()
    arr = np.empty(len(keys), dtype=object)
    arr[:] = keys
    return RowSet(arr, np.asarray(vals), np.asarray(ts)), new_w


def _ref_times(ds: Dataset, theta: np.ndarray) -> tuple[float, float]:
    """First GNSS tag and first IMU stamp of ``correct(ds, theta)``."""
    e = EffectSet.from_vector(theta)
    return float(ds.gnss.t_s[0] - e.gnss_latency_s), float(ds.imu.t_s[0] + e.imu_time_offset_s)


def _align(base: RowSet, other: RowSet) -> np.ndarray:
    """other's values on base's keys (NaN where other lacks the row)."""
    idx = {k: i for i, k in enumerate(other.keys)}
    out = np.full(len(base.keys), np.nan)
    for i, k in enumerate(base.keys):
        j = idx.get(k)
        if j is not None:
            out[i] = other.r[j]
    return out


def _roll_block_sd(log: ResidualLog, t0_s: float) -> float:
    _, vals, _ = _roll_rows(log, t0_s, 1.0)
    return float(max(np.std(vals), np.radians(0.2))) if len(vals) > 2 else np.radians(1.0)


# ---------------------------------------------------------------------------------- calibration
@dataclass
class Calibration:
    """Everything the report needs."""
    dataset: str
    fit: Fit
    problem: LinearProblem
    theta_coarse: np.ndarray
    fit_first: Fit
    fit_second: Fit
    effects_significant: EffectSet
    before: dict = field(default_factory=dict)
    after: dict = field(default_factory=dict)
    log_before: ResidualLog | None = None
    log_after: ResidualLog | None = None
    coarse_report: dict = field(default_factory=dict)
    replays: int = 0
    table: object | None = None          # datasets.calibration.CalibrationTable written back
    tuning: dict = field(default_factory=dict)
    source: str = ""
    online: list = field(default_factory=list)    # ``agreement`` rows: offline vs the live filter's states


CALIBRATION_REPLAY_CONFIG = {"gate_probability": 1.0}
"""Replays that feed the fit run without the chi-square gate (a gate decision that flips between
two replays makes the innovation sequence jump and spoils the finite differences) and without the
receiver's velocities when they lag the positions: an RTK engine's velocity may be a smoothed,
lagged state (``kinematic.velocity_lag`` compares the course from velocities and from positions
against the gyro); a lag would bias the time offset, and positions are the outage reference."""
EXACT_EPOCHS = True
"""Fit replays bring the state exactly to each GNSS epoch and apply the vehicle constraints mid-way
between epochs (``runner.replay``): with the constraints at chunk ends and the GNSS update
extrapolated from the last sample, the replayed cost jumped by 50-140 whenever a stamp shift moved
a GNSS epoch past an IMU sample (a simulated drive, 2026-11-23), as much as a 2 ms offset costs."""

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


def metrics_replay(ds: Dataset, schedule: OutageSchedule, progress: bool | Progress = False,
                   label: str = "outage replay") -> dict:
    """Outage metrics exactly as ``v2xpos replay`` computes them (default filter configuration,
    the dataset's ``[calibration]`` applied by ``ins_config``), plus ``nis_mean`` of the accepted
    GNSS position and velocity updates."""
    from v2xpos.ins.replay import OutageSchedule as InsSchedule
    from v2xpos.ins.replay import replay as ins_replay
    sched = InsSchedule(schedule.length_s, schedule.every_s, schedule.first_s)
    bar = progress if isinstance(progress, Progress) else None
    if bar:
        bar.start(label)
    res = ins_replay(ds, sched, progress=bool(progress) and bar is None, keep_series=False)
    if bar:
        bar.done()
    out = dict(res.summary)
    nis = [r.nis for r in res.filter.residuals if r.accepted and r.kind in ("gnss_pos", "gnss_vel")]
    out["nis_mean"] = float(np.mean(nis)) if nis else float("nan")
    return out


class Estimator:
    """Batch estimator bound to one recording; keeps the Jacobian so that recordings derived from
    the same drive (e.g. with injected effects) can be fitted with a couple of replays."""

    def __init__(self, ds: Dataset, progress: bool | Progress = False, prior_sd: np.ndarray | None = None):
        self.ds = ds
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
        self.config = dict(CALIBRATION_REPLAY_CONFIG)
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
        from v2xpos.ins.replay import OutageSchedule as InsSchedule
        from v2xpos.ins.replay import config_for
        from v2xpos.ins.replay import replay as ins_replay
        if self.ds.calibration is not None and self.ds.calibration.effects:
            # a vehicle that is already calibrated: its table is the starting point
            from .writeback import theta_from_table
            th = np.where(self.active, theta_from_table(self.ds.calibration)[0], 0.0)
            self.coarse_report = {"from": "[calibration] table of the dataset"}
            self.check_velocity_lag(th)
            return th
        cfg = config_for(self.ds, effects=("lever_arm", "imu_time_offset", "misalignment"))
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
        from v2xpos.ins.replay import OutageSchedule as InsSchedule
        from v2xpos.ins.replay import config_for
        from v2xpos.ins.replay import replay as ins_replay
        p = self.prior_sd
        cfg = config_for(self.ds, effect_initial_sd={"lever_arm": p[P_LEVER_ARM].copy(),
                                                     "imu_time_offset": float(p[P_TIME_OFFSET]),
                                                     "misalignment": p[P_MISALIGN].copy()})
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
        from v2xpos.ins.filter import InsConfig
        from .tuning import imu_noise_density, innovation_scale, rescaled_config
        d = InsConfig()
        gyro, accel = imu_noise_density(self.ds.imu)
        # the second-difference estimate bounds the in-band white noise from above (it weighs
        # high-frequency vibration up to 16/6 times): below the filter's default it shows the
        # default is too large and replaces it; above it, the excess may be out-of-band vibration
        # and the default stays (drive_0708: 5.6e-3 measured, 6e-4..1.2e-3 in band at its stops)
        if np.isfinite(gyro) and gyro > 0:
            self.config["gyro_noise_rps_rthz"] = min(gyro, d.gyro_noise_rps_rthz)
        if np.isfinite(accel) and accel > 0:
            self.config["accel_noise_mps2_rthz"] = min(accel, d.accel_noise_mps2_rthz)
        base = {k: getattr(d, k) for k in ("gnss_pos_sd_floor_m", "gnss_vel_sd_scale", "gnss_vel_sd_floor_mps")}
        history = []
        for k in range(iterations):
            out = self._replay(self.ds, theta, f"tuning {k + 1}")
            fac = innovation_scale(out.log)
            history.append(fac)
            self.config = rescaled_config(self.config, base, fac)
        self.tuning = {"gyro_noise_rps_rthz": gyro, "accel_noise_mps2_rthz": accel, "factors": history,
                       "config": {k: v for k, v in self.config.items()}}
        return self.tuning

    def check_velocity_lag(self, theta: np.ndarray) -> None:
        """Leave the receiver velocities out of the fit when they lag the positions by > 3 sd."""
        from v2xpos.rotation import dcm_from_euler
        from .kinematic import velocity_lag
        C = dcm_from_euler(*theta[P_MISALIGN]) @ np.asarray(self.ds.imu_to_body, float)
        self.velocity_lag = velocity_lag(self.ds.imu, self.ds.gnss, C)
        if self.velocity_lag is not None:
            lag, sd = self.velocity_lag
            self.config["use_gnss_velocity"] = not (abs(lag) > 3.0 * sd)

    def replayed_residuals(self, ds: Dataset, theta: np.ndarray, label: str) -> np.ndarray:
        """Residuals of a replay at theta on the rows of the linearisation point; rows missing in
        the replay keep their linearisation value."""
        rows, _ = self.rows(ds, theta, label)
        r = _align(self.base_rows, rows)
        return np.where(np.isfinite(r), r, self.base_rows.r)

    def true_cost(self, ds: Dataset, theta: np.ndarray, label: str) -> float:
        """Residual cost of a replay at theta (``replayed_residuals``)."""
        r = self.replayed_residuals(ds, theta, label)
        return float(r @ r)

    def rows(self, ds: Dataset, theta: np.ndarray, label: str) -> tuple[RowSet, ReplayOutcome]:
        out = self._replay(ds, theta, label)
        rows, _ = residual_rows(out.log, EffectSet.from_vector(theta), self.weights, self.t0_s, self.roll_sd,
                                _ref_times(ds, theta), self.exact_epochs)
        return rows, out

    def set_baseline(self, theta0: np.ndarray) -> RowSet:
        """Replay ``self.ds`` at theta0 and make its rows the reference of every later replay: the
        row keys, the per-kind weights (variance components) and the roll block sd."""
        out = self._replay(self.ds, theta0, "linearisation point")
        self.roll_sd = _roll_block_sd(out.log, self.t0_s)
        self.base_rows, self.weights = residual_rows(out.log, EffectSet.from_vector(theta0), None,
                                                     self.t0_s, self.roll_sd, _ref_times(self.ds, theta0),
                                                     self.exact_epochs)
        return self.base_rows

    def linearize(self, theta0: np.ndarray, keep_weights: bool = False) -> RowSet:
        """Rows at theta0 and the finite-difference Jacobian there (one replay per parameter)."""
        if not keep_weights or self.weights is None:
            rows0 = self.set_baseline(theta0)
        else:
            rows0, _ = self.rows(self.ds, theta0, "linearisation point")
        r0 = _align(self.base_rows, rows0)
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
            J[:, p] = (_align(self.base_rows, rows) - r0) / FD_STEP[p]
        # identical relative timing: GNSS latency (tags moved back) = IMU offset (stamps moved on);
        # a slow clock drift acts as the local offset 1e-6 d (t - t0) (filter memory << drive)
        J[:, P_GNSS_LATENCY] = J[:, P_TIME_OFFSET]
        J[:, P_CLOCK_DRIFT] = J[:, P_TIME_OFFSET] * 1e-6 * (self.base_rows.t_s - self.t0_s)
        self.J = J
        return rows0

    def problem(self, rows: RowSet, theta: np.ndarray) -> LinearProblem:
        """Linear problem at theta from residual rows of a replay at theta and the stored J."""
        r = _align(self.base_rows, rows)
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
                # weights stay comparable. (Re-tuning at every iterate was tried: on convoy_dev B it
                # inflated the lever-arm and time-offset sds 2-3 times and the elimination dropped
                # them; 2026-11-24, docs/calibration.md.)
                self.tune(theta, iterations=2)
            rows0 = self.linearize(theta, keep_weights=k > 0)
            c0 = float(np.nansum(_align(self.base_rows, rows0) ** 2))
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

    def refine(self, ds: Dataset, theta_start: np.ndarray, iterations: int = 1) -> tuple[Fit, LinearProblem, ReplayOutcome]:
        """Quasi-Newton iterations on ``ds`` starting from the stored finite-difference Jacobian,
        improved after every step by Broyden's rank-one update J += (dr - J dth) dth^T / |dth|^2
        (Broyden 1965, Math. Comp. 19) so that a recording derived from the linearised one
        converges with a few replays; then the fit at the final point."""
        J_saved = self.J
        self.J = self.J.copy()
        try:
            theta = theta_start.copy()
            rows, out = self.rows(ds, theta, "refine start")
            r_prev = _align(self.base_rows, rows)
            for k in range(iterations):
                prob = self.problem(rows, theta)
                new = identify.fit(prob, systematic_sd=self.systematic_sd()).theta
                rows, out = self.rows(ds, new, f"refine {k + 1}")
                r_new = _align(self.base_rows, rows)
                dth = new - theta
                ok = np.isfinite(r_new) & np.isfinite(r_prev) & np.all(np.isfinite(self.J), axis=1)
                nrm = float(dth[self.active] @ dth[self.active])
                if nrm > 0:
                    upd = np.zeros_like(self.J)
                    upd[ok] = np.outer(r_new[ok] - r_prev[ok] - self.J[ok] @ dth, dth) / nrm
                    upd[:, ~self.active] = 0.0
                    self.J = self.J + upd
                theta, r_prev = new, r_new
            prob = self.problem(rows, theta)
            f = identify.fit(prob, systematic_sd=self.systematic_sd())
            if iterations > 0:
                # the secant-updated J serves the estimate; its columns need not be good derivatives
                # (the update lands mostly in the columns with large raw steps), so each sd is the
                # larger of the one it gives and the one from the finite-difference Jacobian
                J_secant, self.J = self.J, J_saved
                f_fd = identify.fit(self.problem(rows, theta), systematic_sd=self.systematic_sd())
                self.J = J_secant
                f.sd = np.maximum(f.sd, f_fd.sd)
                f.sd_stat = np.maximum(f.sd_stat, f_fd.sd_stat)
                f.determined = f.determined & f_fd.determined
            f = identify.decide(prob, f)
            return f, prob, out
        finally:
            self.J_refined = self.J
            self.J = J_saved

    def confirm(self, ds: Dataset, f: Fit, prob: LinearProblem, n_sigma: float = 3.0) -> Fit:
        """Real error reduction, by backward elimination with replays: the candidates are the
        effects beyond 3 sd; in the current model (all active parameters minus those dropped,
        estimated together by ``identify.refit``) each candidate is removed in turn, the others
        re-estimated without it, and the recording replayed. A candidate stays only if the replayed
        cost rises in BOTH halves of the recording and in total by more than ``n_sigma^2 kappa``,
        where ``kappa = (sd / sd_white)^2`` is the variance factor of the robust sd over the
        white-residual one: in the linear model the cost rise is ``(value / sd_white)^2``, so this
        is the 3-sd test again, with the replay in place of the linearisation (a likelihood-ratio
        test with the same non-whiteness allowance), and if it is still beyond 3 sd in the current
        model. Otherwise the candidate with the smallest ``rise / kappa`` is dropped and the rest
        are tested again in the model without it.
        The refit lets correlated parameters take over what they can: an IMU time offset and a
        forward lever arm that only trade along ``l_x - v tau`` (docs/calibration.md) each look
        necessary while the other is held at its joint estimate, but not when it may move.
        The significant effects' values and sd become those of the final model; the others keep
        the joint fit's."""
        cand = [int(i) for i in np.flatnonzero(prob.active & f.determined & (np.abs(f.theta) > n_sigma * f.sd))]
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
                keep = np.all(d > 0) and z2 > n_sigma ** 2 and abs(fm.theta[i]) > n_sigma * fm.sd[i]
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
        f.cv_gain = gain
        f.significant = sig
        return f


def with_calibration(ds: Dataset, table) -> Dataset:
    """A shallow copy of ``ds`` carrying ``table`` as its ``[calibration]`` (replaces any other)."""
    import copy
    out = copy.copy(ds)
    out.calibration = table
    return out


def calibrate_dataset(ds: Dataset, schedule: OutageSchedule, progress: bool = True,
                      gn_iterations: int = 2) -> Calibration:
    """The full pipeline of the module docstring. *before* is the vehicle as configured (declared
    values and the dataset's own ``[calibration]``, if any); *after* is the same replay with the
    table this calibration writes back (``ins_config``), i.e. exactly what ``v2xpos replay`` gives
    on the ``--write-dataset`` descriptor."""
    from .writeback import calibration_table
    n_active = int(active_parameters(ds.platform).sum())
    bar = Progress(progress, total=6 + gn_iterations * (n_active + 4) + 3 + 8)
    try:
        est = Estimator(ds, progress=bar)
        before = metrics_replay(ds, schedule, bar, "before: the vehicle as declared")
        theta_c = est.coarse()
        theta = est.gauss_newton(theta_c, iterations=gn_iterations)
        f, prob, out_fit = est.refine(ds, theta, iterations=2)
        f = est.confirm(ds, f, prob)
        a, b = identify.halves(prob)
        f1 = identify.fit(a, systematic_sd=est.systematic_sd())
        f2 = identify.fit(b, systematic_sd=est.systematic_sd())
        sig = EffectSet.from_vector(np.where(f.significant, f.theta, 0.0))
        source = str(getattr(ds, "source", "") or ds.name)
        noise = None
        if "gyro_noise_rps_rthz" in est.config:
            # the predictor's IMU noise (``Estimator.tune``) goes back into the vehicle with the fit
            noise = (est.config["gyro_noise_rps_rthz"], est.config["accel_noise_mps2_rthz"], len(ds.imu.t_s))
        table = calibration_table(f.theta, f.sd, f.significant, f.determined, est.prior_sd, ds.lever_arm_sd_m,
                                  source=source, imu_noise=noise)
        after = metrics_replay(with_calibration(ds, table), schedule, bar, "after: the calibrated vehicle")
        online = agreement(f, est.online(), est.online_t_end_s)
        base_fit = est._replay(ds, np.zeros(N_PARAMS), "declared model (report)")
    finally:
        bar.close()
    return Calibration(dataset=ds.name, fit=f, problem=prob, theta_coarse=theta_c, fit_first=f1,
                       fit_second=f2, effects_significant=sig, before=before, after=after,
                       log_before=base_fit.log, log_after=out_fit.log, coarse_report=est.coarse_report,
                       replays=est.replays + 2, table=table, tuning=est.tuning, source=source, online=online)


def agreement(f: Fit, online: dict, t_end_s: float) -> list[dict]:
    """Offline estimate against the live filter's state per effect: ``z = (online - offline) /
    sqrt(sd_on^2 + sd_off^2)``, agreeing when |z| <= 2. The offline IMU offset is moved to the end
    of the drive with its clock drift (the online state is the offset at that time)."""
    rows = []
    for i, (v_on, sd_on) in sorted(online.items()):
        v_off, var_off = float(f.theta[i]), float(f.sd[i]) ** 2
        if i == P_TIME_OFFSET:
            g = np.zeros(N_PARAMS)
            g[P_TIME_OFFSET], g[P_CLOCK_DRIFT] = 1.0, 1e-6 * t_end_s
            v_off = float(g @ f.theta)
            var_off = max(float(g @ f.cov @ g), var_off)
        comb = np.sqrt(var_off + sd_on ** 2)
        z = (v_on - v_off) / comb if comb > 0 else np.inf
        rows.append({"index": int(i), "name": PARAM_NAMES[i], "offline": v_off, "offline_sd": float(np.sqrt(var_off)),
                     "online": v_on, "online_sd": sd_on, "z": float(z), "agree": bool(abs(z) <= 2.0),
                     "determined": bool(f.determined[i])})
    return rows


# ---------------------------------------------------------------------------------- JSON
def _entry(f: Fit, sl, scale: float = 1.0) -> dict:
    if isinstance(sl, slice):
        return {"value": (f.theta[sl] * scale).tolist(), "sd": (f.sd[sl] * scale).tolist(),
                "significant": [bool(x) for x in f.significant[sl]],
                "determined": [bool(x) for x in f.determined[sl]]}
    return {"value": float(f.theta[sl] * scale), "sd": float(f.sd[sl] * scale), "significant": bool(f.significant[sl]),
            "determined": bool(f.determined[sl])}


def effects_json(f: Fit) -> dict:
    """The ``effects`` object of the calibrate JSON (angles in degrees). ``determined`` is false where
    the recording could not tell the effect (sd not below half the prior's: the value is then the
    prior's, not a measurement; ``identify.DETERMINED_RATIO``)."""
    from .writeback import EFFECT_SLICES
    return {name: _entry(f, sl, k) for name, (sl, k) in EFFECT_SLICES.items()}


METRIC_KEYS = ("outage_h_rms_m", "outage_h_max_m", "aided_h_rms_m", "nis_mean")


def to_json(cal: Calibration) -> dict:
    return {"dataset": cal.dataset,
            "effects": effects_json(cal.fit),
            "before": {k: cal.before[k] for k in METRIC_KEYS},
            "after": {k: cal.after[k] for k in METRIC_KEYS},
            "online_agreement": {r["name"]: {k: r[k] for k in ("offline", "offline_sd", "online", "online_sd", "z", "agree")}
                                 for r in cal.online}}


# ---------------------------------------------------------------------------------- command
def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("dataset", help="dataset.toml of the recording")
    parser.add_argument("--json", help="write the result JSON here ('-': to stdout, the summary then goes to stderr)")
    parser.add_argument("--plots", help="directory for the report (PNG figures + report.md)")
    parser.add_argument("--write-dataset", metavar="OUT.toml",
                        help="write a dataset descriptor: the input's declared tables (paths relative to OUT) "
                             "and a [calibration] table with the effects found")
    add_schedule_arguments(parser)
    add_input_arguments(parser)
    parser.add_argument("--iterations", type=int, default=2, help="Gauss-Newton iterations (default 2)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bars")


def run(args: argparse.Namespace) -> int:
    """``v2xpos calibrate``: 2 (with the file and key named) when the inputs cannot be used; the
    input warnings go into the JSON (``input_checks``)."""
    ds = load_for_command(args.dataset, "calibrate", args.min_overlap)
    if ds is None:
        return 2
    if args.check:
        return check_only(ds, "calibrate", args.json)
    schedule = OutageSchedule(args.outage_length, args.outage_every, args.outage_first)
    cal = calibrate_dataset(ds, schedule, progress=not args.no_progress, gn_iterations=args.iterations)
    out = to_json(cal)
    out["input_checks"] = ds.notes.get("input_check", {})
    out["warnings"] = len(out["input_checks"].get("warnings", []))
    out["provenance"] = command_provenance("calibrate", args)
    text = json.dumps(out, indent=2)
    if args.json == "-":
        print(text)
    elif args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(text + "\n")
    from .summary import summary_text
    print(summary_text(cal), file=sys.stderr if args.json == "-" else sys.stdout)
    if args.write_dataset:
        from .writeback import write_dataset
        if ds.source is None:
            print("v2xpos calibrate: --write-dataset needs a dataset loaded from a descriptor (.toml)", file=sys.stderr)
            return 2
        path = write_dataset(ds.source, args.write_dataset, cal.table)
        print(f"calibrated dataset: {path}", file=sys.stderr if args.json == "-" else sys.stdout)
    if args.plots:
        from .report import write_report
        path = write_report(cal, Path(args.plots))
        print(f"report: {path}", file=sys.stderr)
    return 0
