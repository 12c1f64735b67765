"""``InsFilter``: loosely coupled GNSS/INS error-state EKF with vehicle constraints and effect states.

The class runs named steps; the ideas live in their own modules:

* the IMU path (``imu_path``): per sample batch (``_run_body``) the jitted strapdown
  (``mechanization``), which also sums the error dynamics A = sum F dt; per chunk of
  ``cov_every`` samples (``_end_chunk``) stop detection (``motion``), the smoothed
  acceleration for the models, the stop calibration (``static_calibration``), the divergence
  check, covariance propagation (``ekf``, Q_c from ``noise``), the consistency test's motion
  (``consistency``), and at ``constraint_rate_hz`` ZUPT/ZARU when static or the car's NHC;
* measurements: GNSS position/velocity, dual-antenna heading and wheel speed from the caller;
  every model is a pure builder of (H, d, R) in ``updates`` (or the caller's own: ``correct``)
  and goes through ``_update`` (gated ``ekf.kalman_update``, then ``_apply``); ``predict`` and
  ``correct`` are the two generic steps (robot_localization's ``FilterBase``);
* start, alignment and resets: ``initialization``; what is reported: ``outputs``; settings:
  ``config.InsConfig``.

Corrections are fed back into the nominal state after every update (closed loop), so the error
state is zero between updates. The equations are in docs/ins.md.
"""
from __future__ import annotations

import math
from time import perf_counter

import numpy as np
from scipy.stats import chi2

from v2xpos import geo
from v2xpos.rotation import dcm_from_euler, exp_so3
from v2xpos.types import FixStatus

from . import ekf, updates
from .alignment import CoarseAligner, CourseTracker
from .config import InsConfig
from .consistency import ConsistencyMonitor
from .effects import DEFAULT_INITIAL_SD
from .integrity import FaultTolerantSolution
from .driveoff_timing import DriveOffTimer, TimeAlignment
from .ekf import ATT, BA, BG, EFFECT_SIZES, POS, VEL, StateLayout, kalman_update
from .effects import EffectValues
from .imu_path import ImuPath
from .initialization import GNSS_RESET_DISTANCE_M, Initialization
from .mechanization import COR_BA, COR_BG, COR_SA, COR_SG, MEM_SIZE, MEM_W, NAV_H, NAV_LAT, NAV_LON, NAV_VEL
from .motion import StopDetector
from .noise import ImuNoiseMeter, process_noise_density
from .outputs import Outputs
from .reported import reported_jacobian
from .static_calibration import StaticBiasEstimate, StaticCalibrator
from .updates import UpdateResult


class InsFilter(ImuPath, Initialization, Outputs):
    """Loosely coupled GNSS/INS error-state EKF (see module docstring and docs/ins.md).

    Times passed to ``process_imu`` are the IMU stamps; the filter's own time label is
    ``stamp + imu_time_offset`` (``effects.py``). GNSS and wheel times are GPS times.

    State (read and written by the steps here and in ``initialization`` / ``outputs``):
    ``nav`` = (lat rad, lon rad, h m, v_N, v_E, v_D m/s) of the IMU point (``NAV_*`` indices);
    ``C_nb`` body -> NED; ``corr`` the compensation of the raw samples (gyro/accel bias and scale,
    ``COR_*``); ``fx`` the other effect values (``effects.EffectValues``); ``P`` the error-state
    covariance in ``layout`` (with ``cfg.imu.consider_gyro_scale`` the gyro scale block, ``consider``, is
    in it but never estimated: ``ekf.kalman_update``); ``A`` the error dynamics summed since the last propagation;
    ``mem`` the strapdown's memory of the previous sample; ``acc_ned_mps2`` the smoothed
    acceleration of the measurement models and ``acc_strapdown_ned_mps2`` the strapdown's own (the
    IMU time offset's column); ``static`` the stop detector's (``stops``) verdict;
    ``initialized`` / ``heading_known`` the alignment's progress; ``counts`` / ``residuals``
    what the updates did; ``on_update(result, filter)`` an optional hook after every update;
    ``separation`` (the integrity twin), ``recorder`` (the smoother's) and ``observers`` follow
    every covariance propagation, correction, boundary (a reset that rewrites P and moves the
    state) and decoupling reset (the gyro biases at a refuted stop) as ``observers.FilterObserver``s.
    """

    def __init__(self, cfg: InsConfig | None = None):
        self.cfg = cfg or InsConfig()
        c = self.cfg
        imu, ct, it = c.imu, c.consistency, c.integrity
        self.layout = StateLayout.build(tuple(c.effects.states) + (("gyro_scale",) if imu.consider_gyro_scale else ()))
        i_sg = self.layout.at("gyro_scale")
        self.consider = slice(i_sg, i_sg + 3) if imu.consider_gyro_scale else None
        n = self.layout.n
        self.P = np.zeros((n, n))
        self.nav = np.zeros(6)
        self.C_nb = np.eye(3)
        self.corr = np.zeros(12)
        self.mem = np.zeros(MEM_SIZE)
        self.A = np.zeros((n, n))
        self.q_c = process_noise_density(self.layout, c)
        gyro_scale = (imu.imu_gyro_noise_scale, imu.imu_gyro_noise_scale, imu.imu_yaw_gyro_noise_scale)
        self.noise_meter = (ImuNoiseMeter(gyro_scale=gyro_scale, accel_scale=imu.imu_accel_noise_scale,
                                          gyro_max_rps_rthz=imu.gyro_noise_rps_rthz,
                                          accel_max_mps2_rthz=imu.accel_noise_mps2_rthz)
                            if imu.imu_noise_from_data else None)
        self.consistency = ConsistencyMonitor(ct.consistency_window_s, ct.consistency_false_alarm_per_hour,
                                              ct.verify_turn_deg, reverify=ct.consistency_reverify,
                                              release_windows=ct.consistency_release_windows,
                                              detectable_m=ct.verify_detectable_lever_arm_m)
        i_l = self.layout.at("lever_arm")
        self.separation = (FaultTolerantSolution(i_l, it.undeclared_lever_arm_sd_m, it.integrity_false_alarm_per_hour,
                                                 self._setup_prior(), it.integrity_risk, consider=self.consider,
                                                 widen=self._declared_effects())
                           if it.fault_tolerant_solution and i_l >= 0 and it.undeclared_lever_arm_sd_m > 0 else None)
        self._t_motion_s: float | None = None
        self.kidx = self.layout.kernel_index()
        self.fx = EffectValues(c.setup.lever_arm_m)
        self.fx.imu_time_offset_s = float(c.effects.initial_time_offset_s)
        self.fx.misalignment_rad = np.asarray(c.effects.initial_misalignment_rad, float).reshape(3).copy()
        for name, value in c.effects.initial_effects.items():
            if name in ("gyro_scale", "accel_scale"):
                k = COR_SG if name == "gyro_scale" else COR_SA
                self.corr[k:k + 3] = np.asarray(value, float).reshape(3)
            elif name in ("imu_clock_drift", "gnss_latency_s", "gnss_vel_latency_s", "odometer_scale"):
                setattr(self.fx, name, float(value))
            else:
                raise ValueError(f"initial_effects: unknown effect {name!r}")
        self.initialized = False
        self.heading_known = True
        self.t_stamp_s: float | None = None
        self._t_cov_s: float | None = None
        self._since_chunk = 0
        self._chunks_since_ortho = 0
        self._chunk_t: list = []
        self._chunk_f: list = []
        self._chunk_w: list = []
        self.stops = StopDetector(c)
        self.static = False
        self._last_constraint_t: float = -np.inf
        self.aligner = CoarseAligner()
        self._course_tracker = CourseTracker()
        self._course_sd_rad = 0.0
        self._mis_cache: tuple | None = None
        self.calibrator = StaticCalibrator(c.stops.static_calibration)
        self.gate = {k: float(chi2.ppf(c.gnss.gate_probability, k)) for k in (1, 2, 3, 6)}
        self.last_fix = FixStatus.NONE
        self.last_gnss_t_s = -np.inf
        self._gnss_rejections = 0
        self.counts = {"gnss_pos_accepted": 0, "gnss_pos_rejected": 0, "gnss_vel_accepted": 0,
                       "gnss_vel_rejected": 0, "nhc": 0, "nhc_rejected": 0, "zupt": 0, "zaru": 0,
                       "odometer": 0, "odometer_rejected": 0, "gnss_forced": 0, "position_resets": 0, "static_calibrations": 0,
                       "stops_not_level": 0, "static_calibration_resets": 0,
                       "malformed_inputs": 0}
        self.residuals: list[UpdateResult] = []
        self.stage_s = {"strapdown": 0.0, "covariance": 0.0, "kalman_updates": 0.0}
        self.on_update = None
        self.recorder = None
        self.observers: list = []
        self._last_w_b = np.zeros(3)
        self._last_sample_t: float | None = None
        self.acc_ned_mps2 = np.zeros(3)
        self._v_prev_chunk: np.ndarray | None = None
        self._dv_corrections_mps = np.zeros(3)
        self._free_v_prev: np.ndarray | None = None
        self._free_corr_mps = np.zeros(3)
        self._free_dv_mps: np.ndarray | None = None
        self._align_pending_until_s: float | None = None
        self.acc_strapdown_ned_mps2 = np.zeros(3)
        self._t_prev_chunk = -np.inf
        self._last_raw_f_b: np.ndarray | None = None
        self._last_raw_w_b: np.ndarray | None = None
        self.driveoff = (DriveOffTimer(c.stops.static_max_gnss_speed_mps)
                         if self.layout.at("imu_time_offset") >= 0 and c.effects.align_time_at_drive_off else None)
        self._driveoff_origin: np.ndarray | None = None
        self.time_alignment: TimeAlignment | None = None

    # ------------------------------------------------------------------ time and state access
    @property
    def time_offset_s(self) -> float:
        return self.fx.imu_time_offset_s

    @property
    def t_s(self) -> float:
        """GPS time label of the current state."""
        return (self.t_stamp_s if self.t_stamp_s is not None else np.nan) + self.fx.imu_time_offset_s

    @property
    def lla(self) -> np.ndarray:
        return self.nav[:3].copy()

    @property
    def v_ned_mps(self) -> np.ndarray:
        return self.nav[3:6].copy()

    @property
    def gyro_bias_rps(self) -> np.ndarray:
        return self.corr[COR_BG:COR_BG + 3].copy()

    @property
    def accel_bias_mps2(self) -> np.ndarray:
        return self.corr[COR_BA:COR_BA + 3].copy()

    def misalignment_dcm(self) -> np.ndarray:
        """R: vehicle <- filter body (identity unless the misalignment effect is estimated)."""
        m = self.fx.misalignment_rad
        key = (float(m[0]), float(m[1]), float(m[2]))
        if self._mis_cache is None or self._mis_cache[0] != key:
            self._mis_cache = (key, dcm_from_euler(*key))
        return self._mis_cache[1]

    def sd(self, name: str) -> np.ndarray:
        """1-sigma of an effect block from P (empty when the effect is not estimated)."""
        i = self.layout.at(name)
        if i < 0:
            return np.zeros(0)
        k = ekf.EFFECT_SIZES[name]
        return np.sqrt(np.diag(self.P)[i:i + k])

    def _flush_covariance(self) -> None:
        if not self.initialized or self._t_cov_s is None:
            return
        dt = self.t_stamp_s - self._t_cov_s
        if dt > 0 or np.any(self.A):
            i_dt, i_dr = self.layout.at("imu_time_offset"), self.layout.at("imu_clock_drift")
            if i_dt >= 0 and i_dr >= 0 and dt > 0:
                self.A[i_dt, i_dr] += dt
                self.fx.imu_time_offset_s += self.fx.imu_clock_drift * dt
            if self.noise_meter is not None:
                self.noise_meter.apply(self.q_c, self.C_nb)
            t0 = perf_counter()
            Phi = ekf.transition_matrix(self.A)
            self.A[:] = 0.0
            for o in self._observers():
                o.propagating(self, Phi, self.q_c, max(dt, 0.0))
            self.P = ekf.propagate_with_transition(self.P, Phi, self.q_c, max(dt, 0.0))
            self.stage_s["covariance"] += perf_counter() - t0
            if not self.heading_known:
                self._decouple_yaw()
        self._t_cov_s = self.t_stamp_s

    def _decouple_yaw(self) -> None:
        """While the heading is unknown its error state is kept out of every other state."""
        k = ATT + 2
        d = self.P[k, k]
        self.P[k, :] = 0.0
        self.P[:, k] = 0.0
        self.P[k, k] = d

    # ------------------------------------------------------------------ update machinery
    def _apply(self, dx: np.ndarray) -> None:
        """Closed-loop feedback of the error estimate dx (est minus truth, ``ekf``): position in
        curvilinear increments (lat -= dr_N / (R_M + h), lon -= dr_E / ((R_N + h) cos lat),
        h += dr_D), v -= dv, C_nb <- exp([phi x]) C_nb (the inverse of C_est = (I - [phi x]) C to
        first order; Groves 2013 ch. 14, closed-loop correction), biases and effect values -= their
        errors."""
        lat, h = self.nav[NAV_LAT], self.nav[NAV_H]
        r_m, r_n = geo.radii_m(lat)
        self.nav[NAV_LAT] -= dx[POS] / (r_m + h)
        self.nav[NAV_LON] -= dx[POS + 1] / ((r_n + h) * math.cos(lat))
        self.nav[NAV_H] += dx[POS + 2]
        self.nav[NAV_VEL:NAV_VEL + 3] -= dx[VEL:VEL + 3]
        # kept out of the strapdown's own acceleration (``_smooth_acceleration``)
        self._dv_corrections_mps = self._dv_corrections_mps - dx[VEL:VEL + 3]
        self._free_corr_mps = self._free_corr_mps - dx[VEL:VEL + 3]
        self.C_nb = exp_so3(dx[ATT:ATT + 3]) @ self.C_nb
        self.corr[COR_BG:COR_BG + 3] -= dx[BG:BG + 3]
        self.corr[COR_BA:COR_BA + 3] -= dx[BA:BA + 3]
        self.fx.apply_correction(self.layout, dx, self.corr)

    def _malformed_input(self, kind: str, what: str, t_s: float = np.nan) -> UpdateResult:
        """A measurement input that cannot be used: counted in ``counts["malformed_inputs"]``,
        the filter unchanged, the result not accepted with ``malformed <what>`` as its reason."""
        self.counts["malformed_inputs"] += 1
        return UpdateResult(kind, t_s, False, np.nan, reason=f"malformed {what}")

    def _update(self, kind: str, t_s: float, H: np.ndarray, d: np.ndarray, R: np.ndarray,
                gate: bool = True, force: bool = False) -> UpdateResult:
        t0 = perf_counter()
        if not self.heading_known and np.any(H[:, ATT + 2]):
            # the open heading (sd ~180 deg, decoupled by ``_decouple_yaw``) stays out of the
            # measurements too: linearised about an arbitrary yaw, a tall antenna's few mm of
            # horizontal C l at a tilt turned it by tens of degrees at a stop, and C l with it.
            # What the yaw does to the prediction is noise instead: a horizontal vector u turned by
            # a uniformly distributed yaw is uniform on a circle, covariance |u|^2/2 per horizontal
            # axis, and |u| = |dh/dyaw| (NED rows: GNSS position and velocity)
            h_yaw = H[:, ATT + 2].copy()
            H = H.copy()
            H[:, ATT + 2] = 0.0
            if len(d) == 3:
                R = R + 0.5 * float(h_yaw @ h_yaw) * np.diag([1.0, 1.0, 0.0])
        dx, P, nis, S, ok = kalman_update(self.P, H, d, R, self.gate.get(len(d), None) if gate else None, force,
                                          self.consider)
        if ok:
            self.P = P
            self._apply(dx)
            for o in self._observers():
                o.corrected(self, H, d, R, dx, nis, S)
        self.stage_s["kalman_updates"] += perf_counter() - t0
        res = UpdateResult(kind=kind, t_s=t_s, accepted=ok, nis=nis, innovation=-d,
                           innovation_sd=np.sqrt(np.abs(np.diag(S))), innovation_cov=S)
        if kind.startswith("gnss") and self.consistency.feed_update(kind, t_s, nis, len(d), -d, S, self.C_nb):
            self._on_inconsistency()
        if kind.startswith("gnss"):
            self.residuals.append(res)
        # every update (GNSS, NHC, ZUPT, ZARU, odometer) is offered to the hook with the filter
        if self.on_update is not None:
            self.on_update(res, self)
        return res

    # ------------------------------------------------------------------ generic steps
    def predict(self) -> None:
        """Bring the error covariance to the filter's time: P <- Phi P Phi^T + Q_d over the IMU
        samples since the last propagation (Phi from the error dynamics summed by ``process_imu``,
        which already moved the nominal state with every sample), with the fault-tolerant twin and
        the smoother's recorder told (robot_localization's ``predict``; KF-GINS's
        ``insPropagation`` covariance half). Idempotent: a second call at the same time does
        nothing."""
        self._flush_covariance()

    def correct(self, kind: str, t_s: float, measurement: updates.Measurement | tuple) -> UpdateResult:
        """One measurement at the filter's time (robot_localization's ``correct``):
        ``measurement`` = (H, d, R) of a model, ``d = h(x_est) - z ~ H dx + v``, v ~ N(0, R), dx the
        error state (estimate minus truth) in ``layout``'s columns (``updates`` module docstring).
        ``predict``, then the gated Kalman update with closed-loop feedback, the consistency
        tests, the residual log and the hooks (``_update``). Counts ``<kind>`` or
        ``<kind>_rejected``. A malformed measurement (shapes that do not fit the layout, a
        non-finite entry, R not symmetric positive definite) is counted in ``malformed_inputs`` and
        not used; before initialisation nothing is used. A model built outside the library goes
        through here unchanged (docs/extending.md, section 3)."""
        try:
            H, d, R = (np.asarray(x, dtype=float) for x in measurement)
            m = d.reshape(-1).shape[0]
            d = d.reshape(m)
            if H.shape != (m, self.layout.n) or R.shape != (m, m) or m == 0:
                raise ValueError("shapes")
            if not (np.all(np.isfinite(H)) and np.all(np.isfinite(d)) and np.all(np.isfinite(R))
                    and np.allclose(R, R.T)):
                raise ValueError("values")
            np.linalg.cholesky(R)
        except (TypeError, ValueError, np.linalg.LinAlgError):
            return self._malformed_input(kind, f"{kind} measurement", t_s)
        if not self.initialized:
            return UpdateResult(kind, t_s, False, np.nan, reason="not initialised")
        self.predict()
        r = self._update(kind, t_s, H, d, R)
        key = kind if r.accepted else f"{kind}_rejected"
        self.counts[key] = self.counts.get(key, 0) + 1
        return r

    def _setup_prior(self) -> float:
        """P(the declared set-up is wrong) before this drive's data (``integrity``): the rate of a
        set-up changing since it was verified on an earlier drive, or of a blunder in one never
        verified."""
        it = self.cfg.integrity
        return it.setup_change_prior if it.setup_verified else it.setup_fault_prior

    def _declared_effects(self) -> tuple:
        """(index, sd) of the effect states a calibration declared tighter than the platform's
        default prior (``effects.DEFAULT_INITIAL_SD``): the set-up hypothesis widens them back
        (the lever arm is widened by ``undeclared_lever_arm_sd_m`` on its own)."""
        out = []
        for name in self.layout.effects:
            if name == "lever_arm" or name not in DEFAULT_INITIAL_SD:
                continue
            k = EFFECT_SIZES[name]
            declared = np.broadcast_to(np.asarray(self.cfg.effects.effect_initial_sd.get(name, 0.0), float), (k,))
            default = np.broadcast_to(np.asarray(DEFAULT_INITIAL_SD[name], float), (k,))
            i = self.layout.at(name)
            out += [(i + m, float(default[m])) for m in range(k) if declared[m] < default[m]]
        return tuple(out)

    def _on_inconsistency(self) -> None:
        """The innovation tests failed: the filter's covariance does not describe its innovations.
        No state is changed -- the reported sds are scaled by the windowed NIS ratio meanwhile
        (``ConsistencyMonitor.variance_ratio``) and the result is INCONSISTENT until the evidence
        has gone -- but a set-up verified on an earlier drive is verified no more: the set-up
        hypothesis goes back to the prior of an unverified one (issue 27: a consistency alarm
        re-opens the verification)."""
        sep = self.separation
        if sep is not None and sep.prior < self.cfg.integrity.setup_fault_prior:
            sep.set_prior(self.cfg.integrity.setup_fault_prior)
            self.counts["verification_reopened"] = self.counts.get("verification_reopened", 0) + 1

    def _exclude_declaration(self) -> None:
        """The separation test found the declared set-up wrong (``integrity``: RAIM fault
        exclusion): take the twin's state and covariance -- the estimate that never relied on the
        declaration and is consistent under the fault -- and restart the innovation tests, whose
        windows hold the innovations of the filter before the change."""
        self._smoothing_boundary()
        sep = self.separation
        w, P = sep.in_main_coordinates(self.C_nb)
        self._apply(w)
        self.P = P
        sep.exclude(self.P)
        self.counts["lever_arm_excluded"] = self.counts.get("lever_arm_excluded", 0) + 1
        self.consistency.clear_windows()

    def _smoothing_boundary(self) -> None:
        """Called before a reset rewrites P and moves the state (start, position and heading
        resets, lever-arm exclusion): the smoother's backward pass does not cross it."""
        for o in self._observers():
            o.boundary(self)

    def _observers(self) -> list:
        """Who follows the filter's steps without being part of them (``observers.FilterObserver``):
        the integrity twin, the smoother's recorder, then any the caller put in ``observers``."""
        return [o for o in (self.separation, self.recorder) if o is not None] + self.observers

    def _restart_separation(self) -> None:
        """(Re)start the twin from the current covariance (heading set, filter started): its
        evidence about the set-up is gathered from here on."""
        if self.separation is not None:
            self.separation.start(self.P, self.C_nb, self.mem[MEM_W:MEM_W + 3])
            self.consistency.set_protection(math.inf, self.cfg.integrity.alert_limit_m)

    def _test_separation(self, t_s: float) -> None:
        """Separation test and protection level (``integrity.FaultTolerantSolution``), at most every
        ``test_every_s``; a separation beyond its threshold excludes the declared set-up."""
        sep = self.separation
        if sep is None or not sep.due(t_s):
            return
        w_nb_b, a_n = self.kinematics_now()
        J = reported_jacobian(self.layout, self.C_nb, self.fx.misalignment_rad, self.nav[3:6], a_n, w_nb_b)
        C_nv = self.C_nb @ self.misalignment_dcm().T
        alarm = sep.test(t_s, J[0:3], self.P, math.atan2(C_nv[1, 0], C_nv[0, 0]))
        self.consistency.set_protection(sep.protection_m, self.cfg.integrity.alert_limit_m)
        if alarm and t_s >= self.consistency.t_settled_s:
            self._exclude_declaration()

    def _gap_s(self, t_meas_s: float) -> float:
        return t_meas_s - self.fx.gnss_latency_s - self.t_s

    def _timing_in_models(self, v_ned_mps: np.ndarray) -> bool:
        """Whether the GNSS models carry the timing columns at this state (``updates``: not at a
        stop and faster than ``timing_min_speed_mps``, below which the time offset is not
        observable against the noise); the antenna-fix covariance of a start or reset follows the
        same models (``initialization.antenna_fix_inverse_jacobian``)."""
        v = np.asarray(v_ned_mps, float)
        return (not self.static and float(v @ v) > self.cfg.gnss.timing_min_speed_mps ** 2
                and self._align_pending_until_s is None)

    # ------------------------------------------------------------------ GNSS
    def update_gnss(self, t_s: float, lla: np.ndarray, sd_ned_m: np.ndarray, fix: FixStatus | int,
                    vel_ned_mps: np.ndarray | None = None,
                    vel_sd_ned_mps: np.ndarray | None = None) -> UpdateResult:
        """GNSS antenna position (and velocity) valid at GPS time t_s; before the filter is aligned
        this drives the heading initialisation and returns accepted=False with reason."""
        c = self.cfg
        try:
            t_s = float(t_s)
            if not math.isfinite(t_s):
                raise ValueError("non-finite time")
            lla = np.asarray(lla, float).reshape(3)
            sd = np.broadcast_to(np.asarray(sd_ned_m, float), (3,)).copy()
            fix = FixStatus(int(fix))
            if vel_ned_mps is not None:
                vel_ned_mps = np.asarray(vel_ned_mps, float).reshape(3)
                vel_sd_ned_mps = (np.full(3, 0.1) if vel_sd_ned_mps is None
                                  else np.broadcast_to(np.asarray(vel_sd_ned_mps, float), (3,)).copy())
            if not (np.all(np.isfinite(lla)) and np.all(np.isfinite(sd)) and abs(lla[0]) <= math.pi / 2):
                raise ValueError("non-finite or out-of-range position")
        except (ValueError, TypeError) as e:
            return self._malformed_input("gnss_pos", f"GNSS input: {e}", t_s if isinstance(t_s, float) else np.nan)
        if fix in (FixStatus.NONE, FixStatus.DEAD_RECKONING):
            return UpdateResult("gnss_pos", t_s, False, np.nan, reason="no fix")
        if vel_ned_mps is not None and np.all(np.isfinite(vel_ned_mps)):
            self.stops.note_gnss_speed(float(t_s), float(np.linalg.norm(vel_ned_mps)))
        if not self.initialized:
            return self._try_align(t_s, lla, sd, fix, vel_ned_mps)
        if not self.heading_known:
            vel = vel_ned_mps if vel_ned_mps is not None else self._velocity_from_positions(t_s, lla, sd)
            self._note_drive_off(t_s, lla, sd * c.gnss.fix_sd_scale.get(fix, 2.0), vel)
            if vel is not None and float(np.hypot(vel[0], vel[1])) >= c.initial.align_min_speed_mps:
                return self._heading_reset(t_s, lla, sd, fix, vel)
            if vel is None or float(np.hypot(vel[0], vel[1])) > c.stops.static_max_gnss_speed_mps:
                return UpdateResult("gnss_pos", t_s, False, np.nan, reason="moving, heading pending")
        if self._align_pending_until_s is not None and t_s >= self._align_pending_until_s:
            aligned = self._finish_drive_off_alignment(t_s, lla, sd, fix, vel_ned_mps)
            if aligned is not None:
                return aligned
        self._flush_covariance()
        gap = self._gap_s(t_s)
        C_before = self.C_nb
        v = self.nav[3:6]
        timing = self._timing_in_models(v)
        scale = c.gnss.fix_sd_scale.get(fix, 2.0)
        m = updates.gnss_position(self.layout, self.nav, C_before, self.fx.lever_arm_m, v, gap, lla, sd * scale,
                                  c.gnss.gnss_pos_sd_floor_m, timing)
        m = self._timing_as_noise(m, v)
        force = self._gnss_rejections >= c.gnss.gnss_max_consecutive_rejections
        if force and float(m.d @ m.d) > GNSS_RESET_DISTANCE_M ** 2:
            return self._position_reset(t_s, lla, sd, fix, vel_ned_mps, float(np.sqrt(m.d @ m.d)))
        res = self._update("gnss_pos", t_s, *m, force=force)
        if res.accepted:
            self._test_separation(t_s)
            self.counts["gnss_pos_accepted"] += 1
            self.counts["gnss_forced"] += int(force)
            self._gnss_rejections = 0
            self.last_fix = fix
            self.last_gnss_t_s = t_s
        else:
            self.counts["gnss_pos_rejected"] += 1
            self._gnss_rejections += 1
        if c.gnss.use_gnss_velocity and vel_ned_mps is not None and np.all(np.isfinite(vel_ned_mps)):
            # the position update has corrected v and the lever arm in place; the attitude and
            # the epoch gap are still those the position update was built with
            # at a stop the body does not turn (the stop detector's rate test, ZARU): the sample's
            # rate is vibration and noise, and as the regressor of the lever arm (w x l) it made the
            # lever arm look known after a parked start (errors in variables, as for the timing rows)
            rate_b = np.zeros(3) if self.static else self.mem[MEM_W:MEM_W + 3].copy()
            m = updates.gnss_velocity(self.layout, C_before, self.fx.lever_arm_m, rate_b,
                                      v, self.acc_ned_mps2, gap, self.fx.gnss_vel_latency_s, vel_ned_mps,
                                      vel_sd_ned_mps * c.gnss.gnss_vel_sd_scale * scale,
                                      c.gnss.gnss_vel_sd_floor_mps, timing,
                                      acc_strapdown_ned_mps2=self.acc_strapdown_ned_mps2)
            m = self._timing_as_noise(m, self.acc_strapdown_ned_mps2)
            rv = self._update("gnss_vel", t_s, *m)
            self.counts["gnss_vel_accepted" if rv.accepted else "gnss_vel_rejected"] += 1
        return res

    # ------------------------------------------------------------------ vehicle constraints
    def _vehicle_constraints(self, speed_mps: float) -> None:
        if self.static:
            self._update_zupt()
        elif self.cfg.setup.platform == "car" and speed_mps > updates.NHC_MIN_SPEED_MPS and self.heading_known:
            self._update_nhc()

    def apply_vehicle_constraints(self) -> None:
        """ZUPT/ZARU when static, else the car's NHC, at the time of the last sample; with
        ``constraints_on_request`` the caller chooses these times (e.g. mid-way between GNSS epochs,
        so that a shift of the IMU stamps never reorders a constraint and a GNSS update)."""
        if not self.initialized:
            return
        self._flush_covariance()
        self._last_w_b = self.mem[MEM_W:MEM_W + 3].copy()
        self._vehicle_constraints(math.sqrt(float(self.nav[3:6] @ self.nav[3:6])))

    def _update_nhc(self) -> None:
        R_vb = self.misalignment_dcm()
        modelled = self.layout.at("rear_axle_distance") >= 0
        # the rear-axle model takes the vehicle frame's yaw rate; the loose zero only its size, of
        # the body's (as the figures were measured)
        yaw_rate_rps = float((R_vb @ self._last_w_b)[2] if modelled else self._last_w_b[2])
        gnss_recent = self.t_s - self.last_gnss_t_s <= updates.REAR_AXLE_LEARN_MAX_GNSS_AGE_S
        m = updates.nhc(self.layout, self.C_nb, R_vb, self.nav[3:6], yaw_rate_rps,
                        rear_axle_distance_m=self.fx.rear_axle_distance_m,
                        rear_slip_compliance=self.fx.rear_slip_compliance, learn_rear_axle=modelled and gnss_recent)
        r = self._update("nhc", self.t_s, *m)
        self.counts["nhc" if r.accepted else "nhc_rejected"] += 1

    def _update_zupt(self) -> None:
        """ZUPT, then ZARU with the stop window's mean rate (both ungated: a stop is certain); no
        ZARU while its window reaches into a stop calibration's (``_update_static_calibration``)."""
        c = self.cfg
        self._update("zupt", self.t_s, *updates.zupt(self.layout, self.nav[3:6]), gate=False)
        self.counts["zupt"] += 1
        if c.stops.apply_static_calibration and self.calibrator.averaging(self.t_stamp_s, c.stops.static_window_s):
            return
        m = updates.zaru(self.layout, self.C_nb, self.nav[NAV_LAT], self.stops.mean_rate_rps(),
                         self.corr[COR_BG:COR_BG + 3])
        self._update("zaru", self.t_s, *m, gate=False)
        self.counts["zaru"] += 1

    def _update_static_calibration(self, est: StaticBiasEstimate) -> None:
        """A stop's gyro-bias estimate as the measurement of the gyro bias states for its window's
        samples (R its covariance); ``est.applied`` says it was used. One estimate of each bias and
        each sample counted once: the ZARU, which measures the same rate means, is held while the
        window averages (``_update_zupt``), and an estimate published late (its stop judged level
        only at a later stop, ``est.late``) is not applied, the ZARU having had those samples. The
        accelerometer estimate is not applied: over the same samples the ZUPT measured the
        specific force (a velocity that stays zero), the same information about tilt and bias; it
        is the check that the two agree (``static_calibration``: ``accel_nis``). An update that
        fails the gate means the bias states are refuted by a direct measurement of them (a bias
        step the bias model does not allow, e.g. after a temperature change): they are reset to the
        estimate, their covariance to its covariance and uncorrelated with the rest, in the
        integrity twin too (counted in ``static_calibration_resets``). docs/ins.md, "Seed 001 stop calibration"."""
        m = updates.stop_gyro_bias(self.layout, self.corr[COR_BG:COR_BG + 3], est.gyro_bias_rps, est.gyro_cov)
        est.applied = True
        if self._update("static_calibration", self.t_s, *m).accepted:
            return
        observers = self._observers()
        P_before = self.P.copy() if observers else None
        self.corr[COR_BG:COR_BG + 3] = est.gyro_bias_rps
        self.P[BG:BG + 3, :] = 0.0
        self.P[:, BG:BG + 3] = 0.0
        self.P[BG:BG + 3, BG:BG + 3] = est.gyro_cov
        self.counts["static_calibration_resets"] += 1
        for o in observers:
            o.states_reset(self, P_before, np.arange(BG, BG + 3))

    def update_heading(self, t_s: float, heading_rad: float, sd_rad: float,
                       baseline_vehicle_m: np.ndarray) -> UpdateResult:
        """Dual-antenna heading: the azimuth of the antenna baseline ``baseline_vehicle_m`` (vehicle
        axes like the lever arm, primary -> secondary antenna) at GPS time t_s, clockwise from north, with its 1-sigma.
        While the heading is still pending (at a stop after alignment) it sets the heading
        (``Initialization._heading_from_baseline``); afterwards it is a gated Kalman update
        (``updates.dual_antenna_heading``). The label gap to the filter's state adds the body's
        turn over it, ``|w_z| |t_s - t_state|``, to the sd. Counts ``heading``,
        ``heading_rejected``, ``heading_sets`` (created on first use)."""
        try:
            t_s, heading_rad, sd_rad = float(t_s), float(heading_rad), float(sd_rad)
            baseline = np.asarray(baseline_vehicle_m, dtype=float).reshape(3)
            if not (math.isfinite(t_s) and math.isfinite(heading_rad) and math.isfinite(sd_rad) and sd_rad > 0
                    and np.all(np.isfinite(baseline)) and math.hypot(baseline[0], baseline[1]) > 0):
                raise ValueError("non-finite, sd <= 0 or a vertical baseline")
        except (TypeError, ValueError):
            return self._malformed_input("heading", "heading input")
        if not self.initialized:
            return UpdateResult("heading", t_s, False, np.nan, reason="not initialised")
        self._flush_covariance()
        sd_rad = math.hypot(sd_rad, float(self._last_w_b[2]) * (t_s - self.t_s))
        if not self.heading_known:
            self.counts["heading_sets"] = self.counts.get("heading_sets", 0) + 1
            return self._heading_from_baseline(t_s, heading_rad, sd_rad, baseline)
        m = updates.dual_antenna_heading(self.layout, self.C_nb, self.misalignment_dcm(), baseline, heading_rad, sd_rad)
        return self.correct("heading", t_s, m)

    def update_wheel_speed(self, t_s: float, speed_mps: float) -> UpdateResult:
        """Odometer: forward speed of the vehicle [m/s] at GPS time t_s (Shin 2001 sec. 4.3)."""
        try:
            t_s, speed_mps = float(t_s), float(speed_mps)
            if not (math.isfinite(t_s) and math.isfinite(speed_mps)):
                raise ValueError("non-finite")
        except (TypeError, ValueError):
            return self._malformed_input("odometer", "wheel-speed input")
        if not self.initialized:
            return UpdateResult("odometer", t_s, False, np.nan, reason="not initialised")
        self._flush_covariance()
        m = updates.odometer(self.layout, self.C_nb, self.misalignment_dcm(), self.nav[3:6], self.acc_ned_mps2,
                             self.fx.odometer_scale, t_s - self.t_s, speed_mps)
        return self.correct("odometer", t_s, m)
