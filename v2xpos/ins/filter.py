"""``InsFilter``: loosely coupled GNSS/INS error-state EKF with vehicle constraints and effect states.

Flow per IMU chunk of ``cov_every`` samples: jitted strapdown (``mechanization``) that also sums
the error dynamics -> covariance propagation (``ekf``) -> stop detection -> ZUPT/ZARU when static,
NHC for cars when moving (``updates``) -> seed 001 static calibration (``static_calibration``).
GNSS and wheel-speed updates come from the caller. Corrections are fed back into the nominal state
after every update (closed loop), so the error state is zero between updates.
The equations are in docs/ins.md.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from time import perf_counter

import numpy as np
from scipy.stats import chi2

from v2xpos import geo
from v2xpos.rotation import dcm_from_euler, euler_from_dcm, orthonormalize, rot_z, skew
from v2xpos.types import FixStatus, NavState

from . import ekf
from .alignment import CoarseAligner, CourseTracker
from .ekf import ATT, BA, BG, EFFECT_SIZES, POS, VEL, StateLayout
from .effects import DEFAULT_INITIAL_SD, DEFAULT_RANDOM_WALK, PLATFORM_EFFECTS, EffectValues
from .consistency import INCONSISTENT, VERIFIED, ConsistencyMonitor
from .noise import ImuNoiseMeter
from .reported import correlations, reported_covariance, reported_jacobian
from .mechanization import (COR_BA, COR_BG, COR_SA, COR_SG, MEM_F, MEM_SIZE, MEM_VALID, MEM_W, NAV_H, NAV_LAT,
                            NAV_LON, NAV_VEL, strapdown_batch)
from .static_calibration import StaticBiasEstimate, StaticCalibrationConfig, StaticCalibrator
from .updates import UpdateResult, kalman_update

DEFAULT_FIX_SD_SCALE = {FixStatus.FIXED: 1.0, FixStatus.FLOAT: 2.0, FixStatus.DGPS: 2.0,
                        FixStatus.SINGLE: 2.0, FixStatus.DEAD_RECKONING: 10.0, FixStatus.NONE: 10.0}


@dataclass
class InsConfig:
    """Filter configuration. Units in the names; defaults are for an automotive MEMS IMU
    (e.g. ARW ~0.2 deg/sqrt(s) including vehicle vibration, bias instability ~10 deg/h) and an RTK
    receiver; docs/ins.md gives the reasoning.

    platform: "car" (NHC on), "pedestrian" or "generic" (no vehicle constraints).
    imu_to_body: v_body = imu_to_body @ v_imu (declared nominal mounting).
    lever_arm_m: antenna relative to the IMU in body axes [m]; lever_arm_sd_m its prior 1-sigma.
    effects: extra error states (``ekf.EFFECT_SIZES``); None = the platform default.
    """
    platform: str = "car"
    imu_to_body: np.ndarray = field(default_factory=lambda: np.eye(3))
    lever_arm_m: np.ndarray = field(default_factory=lambda: np.zeros(3))
    lever_arm_sd_m: float = 0.1
    effects: tuple | None = None
    # IMU stochastic model
    gyro_noise_rps_rthz: float = 3e-3
    accel_noise_mps2_rthz: float = 3e-2
    gyro_bias_sd_rps: float = 1e-4
    gyro_bias_tau_s: float = 600.0
    accel_bias_sd_mps2: float = 5e-3
    accel_bias_tau_s: float = 600.0
    gyro_bias_init_sd_rps: float = 0.01
    accel_bias_init_sd_mps2: float = 0.2
    imu_noise_from_data: bool = False             # white-noise densities measured from the samples (ImuNoiseMeter),
    imu_noise_window_s: float = 10.0              # averaged over this time constant, scaled, capped by the two above
    imu_gyro_noise_scale: float = 7.0             # attitude noise = this x the measured gyro white noise (docs/integrity.md)
    imu_accel_noise_scale: float = 1.0            # velocity noise = this x the measured accelerometer white noise
    # own consistency test (consistency.ConsistencyMonitor)
    consistency_window_s: float = 5.0
    consistency_false_alarm: float = 1e-4         # of the windowed NIS test (chi-square quantile 1 - this)
    consistency_mean_z: float = 3.0               # limit of the windowed body-frame innovation mean (N(0, 1) units)
    consistency_reverify: bool = False            # a failure is lifted by verify_turn_deg of passing turns (else latched)
    verify_detectable_lever_arm_m: float = 0.3    # turning counts while the test would find a lever-arm error this size
    verify_turn_deg: float = 45.0                 # turning that must pass the test before the solution is verified
    reopen_on_inconsistency: bool = False         # a failed test reopens the effect states (_on_inconsistency)
    undeclared_lever_arm_sd_m: float = 0.5        # horizontal lever-arm sd the filter reopens to when its test fails
    reopen_all_effects: bool = True               # ... and every other effect state to its prior sd
    effect_initial_sd: dict = field(default_factory=dict)
    initial_time_offset_s: float = 0.0             # starting value of imu_time_offset (e.g. from calibrate)
    initial_misalignment_rad: np.ndarray = field(default_factory=lambda: np.zeros(3))
    initial_effects: dict = field(default_factory=dict)   # other starting values: imu_clock_drift [s/s],
    # gnss_latency_s, gnss_vel_latency_s, odometer_scale, gyro_scale (3), accel_scale (3)
    effect_random_walk: dict = field(default_factory=dict)
    # initial state uncertainty
    init_vel_sd_mps: float = 0.3
    init_level_sd_rad: float = math.radians(2.0)
    init_yaw_sd_rad: float | None = None          # None: 5 deg car, 20 deg otherwise
    align_min_speed_mps: float | None = None      # None: 1 m/s car, 0.5 m/s otherwise
    # GNSS measurement model
    fix_sd_scale: dict = field(default_factory=lambda: dict(DEFAULT_FIX_SD_SCALE))
    gnss_pos_sd_floor_m: float = 0.01
    gnss_vel_sd_floor_mps: float = 0.03
    gnss_vel_sd_scale: float = 1.0
    use_gnss_velocity: bool = True
    gate_probability: float = 0.9999
    gnss_max_consecutive_rejections: int = 8
    gnss_reset_distance_m: float = 30.0           # a forced fix further than this resets position instead
    # vehicle constraints and stops
    constraint_rate_hz: float = 10.0
    constraints_on_request: bool = False          # NHC/ZUPT only via apply_vehicle_constraints() (calibration replays)
    nhc_sd_mps: tuple = (0.1, 0.5)                # lateral, vertical (body pitch varies with load/braking)
    nhc_sd_per_yaw_rate_m: float = 1.0            # adds |yaw rate| x 1 m to the lateral sd (IMU off the rear axle)
    nhc_min_speed_mps: float = 0.5
    odometer_sd_mps: float = 0.05
    zupt_sd_mps: float = 0.02
    zaru_sd_rps: float = 2e-3
    static_window_s: float = 0.5
    static_acc_std_max_mps2: float = 0.18
    static_gyro_mean_max_rps: float = 0.005
    static_max_speed_mps: float = 1.0
    static_acc_h_max_mps2: float = 0.2           # horizontal specific force in NED (a stop has none)
    static_max_gnss_speed_mps: float = 0.2
    static_calibration: StaticCalibrationConfig = field(default_factory=StaticCalibrationConfig)
    apply_static_calibration: bool = True
    timing_min_speed_mps: float = 1.0             # below it the timing states get no H (noise would pass for signal)
    acc_smoothing_tau_s: float = 0.2              # low-pass of the acceleration used in H (not in nav_state)
    static_start: bool = True                     # start at a stop with the yaw open (see _try_align)
    # numerics
    cov_every: int = 10
    coast_after_s: float = 1.0
    log_residuals: bool = True

    def __post_init__(self) -> None:
        if self.platform not in PLATFORM_EFFECTS:
            raise ValueError(f"platform {self.platform!r} not one of {sorted(PLATFORM_EFFECTS)}")
        self.imu_to_body = np.asarray(self.imu_to_body, float).reshape(3, 3)
        self.lever_arm_m = np.asarray(self.lever_arm_m, float).reshape(3)
        if self.effects is None:
            self.effects = PLATFORM_EFFECTS[self.platform]
        self.effect_initial_sd = {**DEFAULT_INITIAL_SD, "lever_arm": self.lever_arm_sd_m, **self.effect_initial_sd}
        self.effect_random_walk = {**DEFAULT_RANDOM_WALK, **self.effect_random_walk}
        if self.init_yaw_sd_rad is None:
            self.init_yaw_sd_rad = math.radians(5.0 if self.platform == "car" else 20.0)
        if self.align_min_speed_mps is None:
            self.align_min_speed_mps = 1.0 if self.platform == "car" else 0.5


def _small_rotation(phi: np.ndarray) -> np.ndarray:
    """exp([phi x]) (Rodrigues), inlined for the per-update feedback."""
    a2 = float(phi @ phi)
    if a2 < 1e-12:
        s, c = 1.0 - a2 / 6.0, 0.5 - a2 / 24.0
    else:
        a = math.sqrt(a2)
        s, c = math.sin(a) / a, (1.0 - math.cos(a)) / a2
    K = skew(phi)
    return np.eye(3) + s * K + c * (K @ K)


class InsFilter:
    """Loosely coupled GNSS/INS error-state EKF (see module docstring and docs/ins.md).

    Times passed to ``process_imu`` are the IMU stamps; the filter's own time label is
    ``stamp + imu_time_offset`` (``effects.py``). GNSS and wheel times are GPS times.
    """

    def __init__(self, cfg: InsConfig | None = None):
        self.cfg = cfg or InsConfig()
        c = self.cfg
        self.layout = StateLayout.build(c.effects)
        n = self.layout.n
        self.P = np.zeros((n, n))
        self.nav = np.zeros(6)
        self.C_nb = np.eye(3)
        self.corr = np.zeros(12)
        self.mem = np.zeros(MEM_SIZE)
        self.A = np.zeros((n, n))
        self.q_c = ekf.process_noise_density(self.layout, c)
        self.noise_meter = (ImuNoiseMeter(c.imu_noise_window_s, c.imu_gyro_noise_scale, c.imu_accel_noise_scale,
                                          c.gyro_noise_rps_rthz, c.accel_noise_mps2_rthz) if c.imu_noise_from_data else None)
        self.consistency = ConsistencyMonitor(c.consistency_window_s, c.consistency_false_alarm, c.verify_turn_deg,
                                              mean_z_limit=c.consistency_mean_z, reverify=c.consistency_reverify,
                                              detectable_m=c.verify_detectable_lever_arm_m)
        self._t_motion_s: float | None = None
        self.kidx = self.layout.kernel_index()
        self.fx = EffectValues(c.lever_arm_m)
        self.fx.imu_time_offset_s = float(c.initial_time_offset_s)
        self.fx.misalignment_rad = np.asarray(c.initial_misalignment_rad, float).reshape(3).copy()
        for name, value in c.initial_effects.items():
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
        # stop-detector window: per chunk [samples, sum|f|, sum|f|^2, sum w (3), samples * f_h^n (2)]
        self._win = np.zeros((max(1, int(round(c.static_window_s * c.constraint_rate_hz))), 8))
        self._win_filled = 0
        self._win_pos = 0
        self.static = False
        self._last_constraint_t: float = -np.inf
        self.aligner = CoarseAligner()
        self._course_tracker = CourseTracker()
        self._course_sd_rad = 0.0
        self._mis_cache: tuple | None = None
        self.calibrator = StaticCalibrator(c.static_calibration)
        self.gate = {k: float(chi2.ppf(c.gate_probability, k)) for k in (1, 2, 3, 6)}
        self.last_fix = FixStatus.NONE
        self.last_gnss_t_s = -np.inf
        self._gnss_rejections = 0
        self._gnss_speed_mps: float | None = None
        self._gnss_speed_t_s = -np.inf
        self.counts = {"gnss_pos_accepted": 0, "gnss_pos_rejected": 0, "gnss_vel_accepted": 0,
                       "gnss_vel_rejected": 0, "nhc": 0, "nhc_rejected": 0, "zupt": 0, "zaru": 0,
                       "odometer": 0, "odometer_rejected": 0, "gnss_forced": 0, "position_resets": 0, "static_calibrations": 0,
                       "malformed_inputs": 0}
        self.residuals: list[UpdateResult] = []
        self.stage_s = {"strapdown": 0.0, "covariance": 0.0, "kalman_updates": 0.0}
        self.on_update = None
        self._last_w_b = np.zeros(3)
        self._last_sample_t: float | None = None
        self.acc_ned_mps2 = np.zeros(3)
        self._v_prev_chunk: np.ndarray | None = None
        self._t_prev_chunk = -np.inf
        self._last_raw_f_b: np.ndarray | None = None
        self._last_raw_w_b: np.ndarray | None = None

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

    # ------------------------------------------------------------------ initialisation
    def initialize(self, t_s: float, lla: np.ndarray, v_ned_mps: np.ndarray, rpy_rad: np.ndarray,
                   pos_sd_m: float = 0.05, vel_sd_mps: float | None = None,
                   att_sd_rad: np.ndarray | None = None) -> None:
        """Start the filter from a known state of the IMU point at GPS time t_s (rpy of C_nb)."""
        self._start(t_s, np.asarray(lla, float), np.asarray(v_ned_mps, float),
                    dcm_from_euler(*np.asarray(rpy_rad, float)), pos_sd_m,
                    self.cfg.init_vel_sd_mps if vel_sd_mps is None else vel_sd_mps,
                    np.array([self.cfg.init_level_sd_rad, self.cfg.init_level_sd_rad, self.cfg.init_yaw_sd_rad])
                    if att_sd_rad is None else np.asarray(att_sd_rad, float))

    def _start(self, t_s, lla, v, C_nb, pos_sd, vel_sd, att_sd) -> None:
        c = self.cfg
        n = self.layout.n
        self.nav[:3] = lla
        self.nav[3:6] = v
        self.C_nb = C_nb.copy()
        self.P = np.zeros((n, n))
        d = np.zeros(n)
        d[POS:POS + 3] = np.broadcast_to(np.asarray(pos_sd, float), 3) ** 2
        d[VEL:VEL + 3] = np.broadcast_to(np.asarray(vel_sd, float), 3) ** 2
        d[ATT:ATT + 3] = att_sd ** 2
        d[BG:BG + 3] = c.gyro_bias_init_sd_rps ** 2
        d[BA:BA + 3] = c.accel_bias_init_sd_mps2 ** 2
        if self.calibrator.estimates and c.apply_static_calibration:
            est = self.calibrator.estimates[-1]
            self.corr[COR_BG:COR_BG + 3] = est.gyro_bias_rps
            self.corr[COR_BA:COR_BA + 3] = est.accel_bias_mps2
            d[BG:BG + 3] = np.maximum(est.gyro_sem_rps, 1e-3) ** 2
            d[BA:BA + 3] = c.static_calibration.level_fx_max_mps2 ** 2
        for name in self.layout.effects:
            i, k = self.layout.index[name], ekf.EFFECT_SIZES[name]
            d[i:i + k] = c.effect_initial_sd.get(name, 0.01) ** 2
        self.P[np.diag_indices(n)] = d
        self.A[:] = 0.0
        self.mem[:] = 0.0
        if self._last_raw_f_b is not None:
            self.mem[MEM_W:MEM_W + 3] = self._last_raw_w_b - self.corr[COR_BG:COR_BG + 3]
            self.mem[MEM_F:MEM_F + 3] = self._last_raw_f_b - self.corr[COR_BA:COR_BA + 3]
            self.mem[MEM_VALID] = 1.0
        if self.t_stamp_s is None:
            self.t_stamp_s = t_s - self.fx.imu_time_offset_s
        self._t_cov_s = self.t_stamp_s
        self.initialized = True
        self.heading_known = True
        self.consistency.restart(float(t_s))
        self._v_prev_chunk = None
        self.acc_ned_mps2 = np.zeros(3)

    # ------------------------------------------------------------------ IMU
    def process_imu(self, t_s: float, acc_mps2: np.ndarray, gyro_rps: np.ndarray) -> None:
        """One IMU sample in IMU axes (specific force [m/s^2], rate [rad/s]) stamped t_s."""
        try:
            t = float(t_s)
            a = np.asarray(acc_mps2, float).reshape(3)
            g = np.asarray(gyro_rps, float).reshape(3)
        except (TypeError, ValueError):
            self.counts["malformed_inputs"] += 1
            return
        if (not math.isfinite(t) or not math.isfinite(float(a @ a + g @ g))
                or (self._last_sample_t is not None and t <= self._last_sample_t)):
            self.counts["malformed_inputs"] += 1
            return
        M = self.cfg.imu_to_body
        f_b = M @ a
        w_b = M @ g
        self._last_sample_t = t
        self._last_raw_f_b = f_b
        self._last_raw_w_b = w_b
        self._run_body(np.array([t]), f_b.reshape(1, 3), w_b.reshape(1, 3))

    def process_imu_batch(self, t_s: np.ndarray, acc_mps2: np.ndarray, gyro_rps: np.ndarray) -> None:
        """Several IMU samples (IMU axes); equivalent to calling ``process_imu`` on each in order."""
        acc = np.asarray(acc_mps2, float).reshape(-1, 3)
        gyr = np.asarray(gyro_rps, float).reshape(-1, 3)
        t_s = np.ascontiguousarray(np.atleast_1d(t_s), dtype=float)
        good = np.isfinite(t_s) & np.isfinite(acc).all(axis=1) & np.isfinite(gyr).all(axis=1)
        if not good.all():
            acc, gyr = np.where(good[:, None], acc, 0.0), np.where(good[:, None], gyr, 0.0)
        f_b = np.ascontiguousarray(acc @ self.cfg.imu_to_body.T)
        w_b = np.ascontiguousarray(gyr @ self.cfg.imu_to_body.T)
        if self._last_sample_t is not None:
            good &= t_s > self._last_sample_t
        if not good.all():
            self.counts["malformed_inputs"] += int((~good).sum())
            t_s, f_b, w_b = t_s[good], f_b[good], w_b[good]
        if len(t_s) > 1:
            keep = np.concatenate([[True], t_s[1:] > np.maximum.accumulate(t_s)[:-1]])
            if not keep.all():
                self.counts["malformed_inputs"] += int((~keep).sum())
                t_s, f_b, w_b = t_s[keep], f_b[keep], w_b[keep]
        if len(t_s):
            self._last_sample_t = float(t_s[-1])
            self._last_raw_f_b = f_b[-1].copy()
            self._last_raw_w_b = w_b[-1].copy()
            self._run_body(t_s, f_b, w_b)

    def _run_body(self, t_s: np.ndarray, f_b: np.ndarray, w_b: np.ndarray) -> None:
        n = len(t_s)
        i = 0
        ce = self.cfg.cov_every
        while i < n:
            j = min(n, i + ce - self._since_chunk)
            if self.initialized:
                t_prev = self.t_stamp_s if self.t_stamp_s is not None else t_s[i]
                t0 = perf_counter()
                strapdown_batch(t_s, f_b, w_b, i, j, t_prev, self.nav, self.C_nb, self.corr, self.mem,
                                self.A, self.kidx, 1.0 / self.cfg.gyro_bias_tau_s, 1.0 / self.cfg.accel_bias_tau_s)
                self.stage_s["strapdown"] += perf_counter() - t0
            self.t_stamp_s = float(t_s[j - 1])
            self._chunk_t.append(t_s[i:j])
            self._chunk_f.append(f_b[i:j])
            self._chunk_w.append(w_b[i:j])
            self._since_chunk += j - i
            i = j
            if self._since_chunk >= ce:
                self._end_chunk()

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
            self.P = ekf.propagate_covariance(self.P, self.A, self.q_c, max(dt, 0.0))
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

    def _end_chunk(self) -> None:
        if len(self._chunk_t) == 1:
            t, f, w = self._chunk_t[0], self._chunk_f[0], self._chunk_w[0]
        else:
            t = np.concatenate(self._chunk_t)
            f = np.concatenate(self._chunk_f)
            w = np.concatenate(self._chunk_w)
        self._chunk_t.clear()
        self._chunk_f.clear()
        self._chunk_w.clear()
        self._since_chunk = 0
        if len(t) == 0:
            return
        self._last_w_b = (self.mem[MEM_W:MEM_W + 3].copy() if self.initialized
                          else w[-1] - self.corr[COR_BG:COR_BG + 3])
        if self.noise_meter is not None:
            self.noise_meter.feed(t, w, f)
        f2 = np.einsum("ij,ij->i", f, f)
        row = self._win[self._win_pos]
        row[0] = len(t)
        row[1] = np.sqrt(f2).sum()
        row[2] = f2.sum()
        row[3:6] = w.sum(axis=0)
        if self.initialized:
            row[6:8] = (self.C_nb[:2] @ (f.sum(axis=0) - len(t) * self.corr[COR_BA:COR_BA + 3]))
        else:
            row[6:8] = 0.0
        self._win_pos = (self._win_pos + 1) % len(self._win)
        self._win_filled = min(self._win_filled + 1, len(self._win))
        self.static = self._detect_static()
        if self.initialized:
            v_now = self.nav[3:6].copy()
            if self._v_prev_chunk is not None and t[-1] > self._t_prev_chunk:
                dt_c = float(t[-1] - self._t_prev_chunk)
                a_c = (v_now - self._v_prev_chunk) / dt_c
                k = min(1.0, dt_c / max(self.cfg.acc_smoothing_tau_s, 1e-6))
                self.acc_ned_mps2 = self.acc_ned_mps2 + k * (a_c - self.acc_ned_mps2)
            self._v_prev_chunk, self._t_prev_chunk = v_now, float(t[-1])
        speed = math.sqrt(float(self.nav[3:6] @ self.nav[3:6])) if self.initialized else 0.0
        moving = self.initialized and speed > 0.5
        g = geo.normal_gravity_mps2(self.nav[NAV_LAT], self.nav[NAV_H]) if self.initialized and not moving else None
        est = self.calibrator.feed(t, f, w, moving=moving, gravity_mps2=g)
        if not self.initialized:
            self.aligner.feed(t, f - self.corr[COR_BA:COR_BA + 3], w - self.corr[COR_BG:COR_BG + 3], self.static)
            if est is not None:
                self.counts["static_calibrations"] += 1
                if self.cfg.apply_static_calibration:
                    self.corr[COR_BG:COR_BG + 3] = est.gyro_bias_rps
                    self.corr[COR_BA:COR_BA + 3] = est.accel_bias_mps2
            return
        if np.abs(self.nav[NAV_LAT]) > 1.5 or not np.all(np.isfinite(self.nav)):
            self.initialized = False
            return
        self._flush_covariance()
        t_end = float(self.t_s)
        if self._t_motion_s is not None and self.heading_known:
            yaw_rate = float(self.C_nb[2] @ self._last_w_b)
            self.consistency.feed_motion(t_end, t_end - self._t_motion_s, yaw_rate, speed)
        self._t_motion_s = t_end
        if est is not None:
            self.counts["static_calibrations"] += 1
            if self.cfg.apply_static_calibration:
                self._update_static_calibration(est)
        if (not self.cfg.constraints_on_request
                and self.t_stamp_s - self._last_constraint_t >= 1.0 / self.cfg.constraint_rate_hz - 1e-6):
            self._last_constraint_t = self.t_stamp_s
            self._vehicle_constraints(speed)
        self._chunks_since_ortho += 1
        if self._chunks_since_ortho >= 100:
            self._chunks_since_ortho = 0
            self.C_nb = orthonormalize(self.C_nb)

    def _detect_static(self) -> bool:
        c = self.cfg
        if self._win_filled < len(self._win):
            return False
        tot = self._win.sum(axis=0)
        n, s1, s2, sw = tot[0], tot[1], tot[2], tot[3:6]
        acc_sd = math.sqrt(max(s2 / n - (s1 / n) ** 2, 0.0))
        dw = sw / n - self.corr[COR_BG:COR_BG + 3]
        w_mean = math.sqrt(float(dw @ dw))
        ok = acc_sd < c.static_acc_std_max_mps2 and w_mean < c.static_gyro_mean_max_rps
        if ok and self.initialized:
            fh = tot[6:8] / n
            v = self.nav[3:6]
            ok = float(v @ v) < c.static_max_speed_mps ** 2 and float(fh @ fh) < c.static_acc_h_max_mps2 ** 2
        if ok and self._gnss_speed_mps is not None and self.t_s - self._gnss_speed_t_s < 1.0:
            ok = self._gnss_speed_mps < c.static_max_gnss_speed_mps
        return bool(ok)

    # ------------------------------------------------------------------ update machinery
    def _apply(self, dx: np.ndarray) -> None:
        lat, h = self.nav[NAV_LAT], self.nav[NAV_H]
        r_m, r_n = geo.radii_m(lat)
        self.nav[NAV_LAT] -= dx[POS] / (r_m + h)
        self.nav[NAV_LON] -= dx[POS + 1] / ((r_n + h) * math.cos(lat))
        self.nav[NAV_H] += dx[POS + 2]
        self.nav[NAV_VEL:NAV_VEL + 3] -= dx[VEL:VEL + 3]
        self.C_nb = _small_rotation(dx[ATT:ATT + 3]) @ self.C_nb
        self.corr[COR_BG:COR_BG + 3] -= dx[BG:BG + 3]
        self.corr[COR_BA:COR_BA + 3] -= dx[BA:BA + 3]
        self.fx.apply_correction(self.layout, dx, self.corr)

    def _update(self, kind: str, t_s: float, H: np.ndarray, d: np.ndarray, R: np.ndarray,
                gate: bool = True, force: bool = False) -> UpdateResult:
        t0 = perf_counter()
        dx, P, nis, S, ok = kalman_update(self.P, H, d, R, self.gate.get(len(d), None) if gate else None, force)
        if ok:
            self.P = P
            self._apply(dx)
        self.stage_s["kalman_updates"] += perf_counter() - t0
        res = UpdateResult(kind=kind, t_s=t_s, accepted=ok, nis=nis, innovation=-d,
                           innovation_sd=np.sqrt(np.abs(np.diag(S))), innovation_cov=S)
        if kind.startswith("gnss") and self.consistency.feed_update(kind, t_s, nis, len(d), -d, S, self.C_nb):
            self._on_inconsistency()
        if self.cfg.log_residuals and kind.startswith("gnss"):
            self.residuals.append(res)
        # every update (GNSS, NHC, ZUPT, ZARU, odometer) is offered to the hook with the filter,
        # whose motion_signals() give the signals at the same instant
        if self.on_update is not None:
            self.on_update(res, self)
        return res

    def _on_inconsistency(self) -> None:
        """The consistency test failed: the declared model does not explain the innovations. The
        effect whose declared prior is the tightest and whose error only turning reveals -- the
        horizontal antenna lever arm, declared to a few cm (an undeclared 0.5 m offset is a
        constant body-frame bias the filter cannot see on a straight road, Groves 2013 sec. 14.2.7)
        -- gets its variance reopened to ``undeclared_lever_arm_sd_m``^2 with its correlations
        dropped (a covariance reset; conservative: the other states keep theirs). The position
        covariance then grows through the lever arm's in the next GNSS updates and the turns that
        follow estimate it; the reported sigma includes what is still unknown. The windows of the
        test restart (their innovations came from the filter before the reset)."""
        i = self.layout.at("lever_arm")
        sd = self.cfg.undeclared_lever_arm_sd_m
        if not self.cfg.reopen_on_inconsistency or i < 0 or not sd > 0:
            return
        reopen = [(i, sd), (i + 1, sd)]
        if self.cfg.reopen_all_effects:
            # the other effect states were estimated with the lever arm held at its declared value:
            # what they absorbed of its signature (a velocity latency dt gives a x dt = v w dt
            # sideways in a steady turn, as w x l does) is re-estimated jointly from their priors
            for name in self.layout.effects:
                if name == "lever_arm":
                    continue
                j, sd0 = self.layout.at(name), np.broadcast_to(self.cfg.effect_initial_sd.get(name, 0.0), (EFFECT_SIZES[name],))
                reopen += [(j + m, float(sd0[m])) for m in range(EFFECT_SIZES[name])]
        widened = False
        for k, s_k in reopen:
            if s_k > 0 and self.P[k, k] < 0.25 * s_k * s_k:
                self.P[k, :] = 0.0
                self.P[:, k] = 0.0
                self.P[k, k] = s_k * s_k
                widened = True
        if widened:
            self.counts["lever_arm_reopened"] = self.counts.get("lever_arm_reopened", 0) + 1
            self.consistency.clear_windows()

    def _gap_s(self, t_meas_s: float) -> float:
        return t_meas_s - self.fx.gnss_latency_s - self.t_s

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
            self.counts["malformed_inputs"] += 1
            return UpdateResult("gnss_pos", t_s if isinstance(t_s, float) else np.nan, False, np.nan,
                                reason=f"malformed GNSS input: {e}")
        if fix in (FixStatus.NONE, FixStatus.DEAD_RECKONING):
            return UpdateResult("gnss_pos", t_s, False, np.nan, reason="no fix")
        if vel_ned_mps is not None and np.all(np.isfinite(vel_ned_mps)):
            self._gnss_speed_mps = float(np.linalg.norm(vel_ned_mps))
            self._gnss_speed_t_s = float(t_s)
        if not self.initialized:
            return self._try_align(t_s, lla, sd, fix, vel_ned_mps)
        if not self.heading_known:
            vel = vel_ned_mps if vel_ned_mps is not None else self._velocity_from_positions(t_s, lla, sd)
            if vel is not None and float(np.hypot(vel[0], vel[1])) >= c.align_min_speed_mps:
                return self._heading_reset(t_s, lla, sd, fix, vel)
            if vel is None or float(np.hypot(vel[0], vel[1])) > c.static_max_gnss_speed_mps:
                return UpdateResult("gnss_pos", t_s, False, np.nan, reason="moving, heading pending")
        self._flush_covariance()
        gap = self._gap_s(t_s)
        n = self.layout.n
        C = self.C_nb
        l_b = self.fx.lever_arm_m
        Cl = C @ l_b
        v = self.nav[3:6]
        a = self.acc_ned_mps2
        lat, h = self.nav[NAV_LAT], self.nav[NAV_H]
        r_m, r_n = geo.radii_m(lat)
        pred_ned = Cl + v * gap
        meas_ned = np.array([(lla[0] - lat) * (r_m + h), (lla[1] - self.nav[NAV_LON]) * (r_n + h) * math.cos(lat),
                             -(lla[2] - h)])
        d = pred_ned - meas_ned
        H = np.zeros((3, n))
        H[:, POS:POS + 3] = np.eye(3)
        H[:, ATT:ATT + 3] = skew(Cl)
        timing = not self.static and float(v @ v) > self.cfg.timing_min_speed_mps ** 2
        self._effect_rows(H, C, -v if timing else np.zeros(3))
        scale = c.fix_sd_scale.get(fix, 2.0)
        R = np.diag(np.maximum(sd * scale, c.gnss_pos_sd_floor_m) ** 2)
        force = self._gnss_rejections >= c.gnss_max_consecutive_rejections
        if force and float(d @ d) > c.gnss_reset_distance_m ** 2:
            return self._position_reset(t_s, lla, sd, fix, vel_ned_mps, float(np.sqrt(d @ d)))
        res = self._update("gnss_pos", t_s, H, d, R, force=force)
        if res.accepted:
            self.counts["gnss_pos_accepted"] += 1
            self.counts["gnss_forced"] += int(force)
            self._gnss_rejections = 0
            self.last_fix = fix
            self.last_gnss_t_s = t_s
        else:
            self.counts["gnss_pos_rejected"] += 1
            self._gnss_rejections += 1
        if c.use_gnss_velocity and vel_ned_mps is not None and np.all(np.isfinite(vel_ned_mps)):
            w = self.mem[MEM_W:MEM_W + 3].copy()
            wl = np.cross(w, l_b)
            Cwl = C @ wl
            d = v + Cwl + a * (gap - self.fx.gnss_vel_latency_s) - vel_ned_mps
            H = np.zeros((3, n))
            H[:, VEL:VEL + 3] = np.eye(3)
            H[:, ATT:ATT + 3] = skew(Cwl)
            H[:, BG:BG + 3] = C @ skew(l_b)
            i = self.layout.at("lever_arm")
            if i >= 0:
                H[:, i:i + 3] = C @ skew(w)
            for name in ("imu_time_offset", "gnss_latency", "gnss_vel_latency"):
                i = self.layout.at(name)
                if i >= 0 and timing:
                    H[:, i] = -a
            R = np.diag(np.maximum(vel_sd_ned_mps * c.gnss_vel_sd_scale * scale, c.gnss_vel_sd_floor_mps) ** 2)
            rv = self._update("gnss_vel", t_s, H, d, R)
            self.counts["gnss_vel_accepted" if rv.accepted else "gnss_vel_rejected"] += 1
        return res

    def _effect_rows(self, H: np.ndarray, C: np.ndarray, timing_col: np.ndarray) -> None:
        i = self.layout.at("lever_arm")
        if i >= 0:
            H[:, i:i + 3] = C
        for name in ("imu_time_offset", "gnss_latency"):
            i = self.layout.at(name)
            if i >= 0:
                H[:, i] = timing_col

    def _velocity_from_positions(self, t_s, lla, sd) -> np.ndarray | None:
        """Horizontal velocity from the constant-velocity tracker when the receiver gives none;
        None until its speed sd is below max(a third of the alignment speed, a fifth of the speed),
        i.e. the course is known to ~11 deg or better; that course sd widens the initial yaw sd."""
        out = self._course_tracker.update(float(t_s), lla, float(max(sd[0], sd[1])))
        if out is None:
            return None
        v, v_sd = out
        speed = float(np.hypot(v[0], v[1]))
        if v_sd > max(self.cfg.align_min_speed_mps / 3.0, 0.2 * speed):
            return None
        self._course_sd_rad = v_sd / max(speed, 1e-3)
        return v

    def _imu_point_at_label(self, t_s, lla, vel, C) -> np.ndarray:
        """IMU position from an antenna fix at t_s, moved to the state label with the GNSS velocity."""
        r_m, r_n = geo.radii_m(lla[0])
        Cl = C @ self.fx.lever_arm_m
        lla_imu = lla - np.array([Cl[0] / (r_m + lla[2]), Cl[1] / ((r_n + lla[2]) * math.cos(lla[0])), -Cl[2]])
        gap = self.t_s - t_s
        return lla_imu + np.array([vel[0] / (r_m + lla[2]), vel[1] / ((r_n + lla[2]) * math.cos(lla[0])),
                                   -vel[2]]) * gap

    def _try_align(self, t_s, lla, sd, fix, vel) -> UpdateResult:
        c = self.cfg
        if vel is None:
            vel = self._velocity_from_positions(t_s, lla, sd)
        if vel is None or self.t_stamp_s is None:
            return UpdateResult("gnss_pos", t_s, False, np.nan, reason="aligning: no velocity yet")
        speed = float(np.hypot(vel[0], vel[1]))
        pos_sd = np.maximum(sd * c.fix_sd_scale.get(fix, 2.0), 0.05)
        if (c.static_start and speed < c.static_max_gnss_speed_mps and self.static
                and self.aligner.levelled_static):
            # stopped and levelled: start now with the yaw left open, so that ZUPT/ZARU estimate the
            # biases during the stop; the heading is set when the platform moves (_heading_reset)
            C = self.aligner.C_nb
            self._start(self.t_s, self._imu_point_at_label(t_s, lla, np.zeros(3), C), np.zeros(3), C, pos_sd,
                        c.init_vel_sd_mps, np.array([c.init_level_sd_rad, c.init_level_sd_rad, math.pi]))
            self.heading_known = False
            self.last_fix = fix
            self.last_gnss_t_s = t_s
            return UpdateResult("gnss_pos", t_s, False, np.nan, reason="initialised at a stop, heading pending")
        if speed < c.align_min_speed_mps:
            return UpdateResult("gnss_pos", t_s, False, np.nan, reason="aligning: too slow for heading")
        C = self.aligner.attitude_with_heading(float(np.arctan2(vel[1], vel[0])))
        if C is None:
            return UpdateResult("gnss_pos", t_s, False, np.nan, reason="aligning: not levelled yet")
        self._start(self.t_s, self._imu_point_at_label(t_s, lla, vel, C), vel, C, pos_sd, c.init_vel_sd_mps,
                    np.array([c.init_level_sd_rad, c.init_level_sd_rad, max(c.init_yaw_sd_rad, self._course_sd_rad)]))
        self.last_fix = fix
        self.last_gnss_t_s = t_s
        return UpdateResult("gnss_pos", t_s, False, np.nan, reason="initialised from this epoch")

    def _position_reset(self, t_s, lla, sd, fix, vel, err_m: float) -> UpdateResult:
        """The filter has drifted beyond linear reach (consecutive rejections and an innovation over
        ``gnss_reset_distance_m``): take position (and velocity when given) from GNSS and reset
        their covariance; attitude, biases and effects are kept."""
        c = self.cfg
        v = self.nav[3:6].copy() if vel is None else np.asarray(vel, float)
        self.nav[:3] = self._imu_point_at_label(t_s, lla, v, self.C_nb)
        self.nav[3:6] = v
        self._v_prev_chunk = None
        idx = np.r_[POS:POS + 3, VEL:VEL + 3]
        self.P[idx, :] = 0.0
        self.P[:, idx] = 0.0
        pos_sd = np.maximum(sd * c.fix_sd_scale.get(fix, 2.0), 0.05)
        vel_sd = c.init_vel_sd_mps if vel is not None else max(c.init_vel_sd_mps, 0.1 * err_m)
        self.P[idx, idx] = np.r_[pos_sd ** 2, np.full(3, vel_sd ** 2)]
        self._gnss_rejections = 0
        self.counts["position_resets"] += 1
        self.last_fix = fix
        self.last_gnss_t_s = t_s
        return UpdateResult("gnss_pos", t_s, False, np.nan,
                            reason=f"position reset: the filter was {err_m:.1f} m off after rejections")

    def _heading_reset(self, t_s, lla, sd, fix, vel) -> UpdateResult:
        """First epoch fast enough for a course: turn the attitude about down so that the body x axis
        points along the course, take position and velocity from GNSS, and reset their covariance
        (biases and level keep what the stop taught them)."""
        c = self.cfg
        yaw_now = float(euler_from_dcm(self.C_nb)[2])
        self.C_nb = rot_z(float(np.arctan2(vel[1], vel[0])) - yaw_now) @ self.C_nb
        self.nav[:3] = self._imu_point_at_label(t_s, lla, vel, self.C_nb)
        self.nav[3:6] = vel
        self._v_prev_chunk = None
        idx = np.r_[POS:POS + 3, VEL:VEL + 3, ATT + 2]
        self.P[idx, :] = 0.0
        self.P[:, idx] = 0.0
        pos_sd = np.maximum(sd * c.fix_sd_scale.get(fix, 2.0), 0.05)
        self.P[idx, idx] = np.r_[pos_sd ** 2, np.full(3, c.init_vel_sd_mps ** 2),
                                 max(c.init_yaw_sd_rad, self._course_sd_rad) ** 2]
        self.heading_known = True
        self.consistency.restart(float(t_s))
        self.last_fix = fix
        self.last_gnss_t_s = t_s
        return UpdateResult("gnss_pos", t_s, False, np.nan, reason="heading set from the GNSS course")

    # ------------------------------------------------------------------ vehicle constraints
    def _vehicle_rows(self):
        Rm = self.misalignment_dcm()
        RCt = Rm @ self.C_nb.T
        v = self.nav[3:6]
        v_b = self.C_nb.T @ v
        Hv = RCt
        Hphi = -RCt @ skew(v)
        Hmis = -skew(v_b)
        return RCt @ v, Hv, Hphi, Hmis

    def _vehicle_constraints(self, speed_mps: float) -> None:
        if self.static:
            self._update_zupt()
        elif self.cfg.platform == "car" and speed_mps > self.cfg.nhc_min_speed_mps and self.heading_known:
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
        c = self.cfg
        v_v, Hv, Hphi, Hmis = self._vehicle_rows()
        H = np.zeros((2, self.layout.n))
        H[:, VEL:VEL + 3] = Hv[1:]
        H[:, ATT:ATT + 3] = Hphi[1:]
        i = self.layout.at("misalignment")
        if i >= 0:
            H[:, i:i + 3] = Hmis[1:]
        yaw_rate = abs(self._last_w_b[2])
        R = np.diag([(c.nhc_sd_mps[0] + c.nhc_sd_per_yaw_rate_m * yaw_rate) ** 2, c.nhc_sd_mps[1] ** 2])
        r = self._update("nhc", self.t_s, H, v_v[1:], R)
        self.counts["nhc" if r.accepted else "nhc_rejected"] += 1

    def _update_zupt(self) -> None:
        c = self.cfg
        n = self.layout.n
        H = np.zeros((3, n))
        H[:, VEL:VEL + 3] = np.eye(3)
        self._update("zupt", self.t_s, H, self.nav[3:6].copy(), np.eye(3) * c.zupt_sd_mps ** 2, gate=False)
        self.counts["zupt"] += 1
        tot = self._win.sum(axis=0)
        w_mean = tot[3:6] / tot[0]
        w_ie_b = self.C_nb.T @ geo.earth_rate_ned_rps(self.nav[NAV_LAT])
        d = w_mean - self.corr[COR_BG:COR_BG + 3] - w_ie_b
        H = np.zeros((3, n))
        H[:, BG:BG + 3] = -np.eye(3)
        self._update("zaru", self.t_s, H, d, np.eye(3) * c.zaru_sd_rps ** 2, gate=False)
        self.counts["zaru"] += 1

    def _update_static_calibration(self, est: StaticBiasEstimate) -> None:
        """Seed 001 estimate applied online as a direct measurement of the bias states (the Earth
        rate, known once the attitude is, is taken out of the gyro mean)."""
        c = self.cfg
        n = self.layout.n
        H = np.zeros((6, n))
        H[0:3, BG:BG + 3] = np.eye(3)
        H[3:6, BA:BA + 3] = np.eye(3)
        w_ie_b = self.C_nb.T @ geo.earth_rate_ned_rps(self.nav[NAV_LAT])
        d = np.concatenate([self.corr[COR_BG:COR_BG + 3] - (est.gyro_bias_rps - w_ie_b),
                            self.corr[COR_BA:COR_BA + 3] - est.accel_bias_mps2])
        sd = np.concatenate([np.maximum(est.gyro_sem_rps, 5e-4),
                             np.full(3, max(c.static_calibration.level_fx_max_mps2, 0.05))])
        self._update("static_calibration", self.t_s, H, d, np.diag(sd ** 2))

    def update_wheel_speed(self, t_s: float, speed_mps: float) -> UpdateResult:
        """Odometer: forward speed of the vehicle [m/s] at GPS time t_s (Shin 2001 sec. 4.3)."""
        try:
            t_s, speed_mps = float(t_s), float(speed_mps)
            if not (math.isfinite(t_s) and math.isfinite(speed_mps)):
                raise ValueError("non-finite")
        except (TypeError, ValueError):
            self.counts["malformed_inputs"] += 1
            return UpdateResult("odometer", np.nan, False, np.nan, reason="malformed wheel-speed input")
        if not self.initialized:
            return UpdateResult("odometer", t_s, False, np.nan, reason="not initialised")
        self._flush_covariance()
        v_v, Hv, Hphi, Hmis = self._vehicle_rows()
        s = self.fx.odometer_scale
        H = np.zeros((1, self.layout.n))
        H[0, VEL:VEL + 3] = (1 + s) * Hv[0]
        H[0, ATT:ATT + 3] = (1 + s) * Hphi[0]
        i = self.layout.at("misalignment")
        if i >= 0:
            H[0, i:i + 3] = (1 + s) * Hmis[0]
        i = self.layout.at("odometer_scale")
        if i >= 0:
            H[0, i] = v_v[0]
        gap = t_s - self.t_s
        a_fwd = (self.misalignment_dcm() @ self.C_nb.T @ self.acc_ned_mps2)[0]
        d = np.array([(1 + s) * (v_v[0] + a_fwd * gap) - speed_mps])
        r = self._update("odometer", t_s, H, d, np.array([[self.cfg.odometer_sd_mps ** 2]]))
        self.counts["odometer" if r.accepted else "odometer_rejected"] += 1
        return r

    # ------------------------------------------------------------------ output
    def motion_signals(self) -> dict:
        """Signals an effect imprints on residuals (for ``on_update`` hooks / diagnosis):
        speed [m/s], kinematic acceleration NED [m/s^2], body rate and specific force (bias
        compensated, filter body axes), attitude rpy of C_nb [rad], C_nb (body -> NED)."""
        v = self.nav[3:6]
        return {"t_s": float(self.t_s), "speed_mps": math.sqrt(float(v @ v)), "v_ned_mps": v.copy(),
                "acc_ned_mps2": self.acc_ned_mps2.copy(), "rate_body_rps": self.mem[MEM_W:MEM_W + 3].copy(),
                "f_body_mps2": self.mem[MEM_F:MEM_F + 3].copy(), "rpy_rad": euler_from_dcm(self.C_nb),
                "C_nb": self.C_nb.copy(), "static": self.static}

    def kinematics_now(self) -> tuple[np.ndarray, np.ndarray]:
        """Body rate w_nb^b [rad/s] (filter body axes, relative to the local-level frame) and
        kinematic acceleration a^n = dv^n/dt [m/s^2, NED] at the last processed IMU sample.

        From that sample compensated with the current bias and scale estimates,
        w_ib = (w~ - b_g)/(1 + s_g), f = (f~ - b_a)/(1 + s_a):
        w_nb^b = w_ib^b - C_bn (w_ie^n + w_en^n) and
        a^n = C_nb f^b + g^n - (2 w_ie^n + w_en^n) x v^n (the velocity equation, Groves eq. 5.54).
        Instantaneous (no smoothing, no lag); its noise is the sensor's per-sample noise.
        """
        if self._last_raw_f_b is None or not self.initialized:
            w = self._last_w_b.copy() if self._last_raw_w_b is None else \
                self._last_raw_w_b - self.corr[COR_BG:COR_BG + 3]
            return w, self.acc_ned_mps2.copy()
        c = self.corr
        w_ib = (self._last_raw_w_b - c[COR_BG:COR_BG + 3]) / (1.0 + c[COR_SG:COR_SG + 3])
        f_b = (self._last_raw_f_b - c[COR_BA:COR_BA + 3]) / (1.0 + c[COR_SA:COR_SA + 3])
        lat, h = float(self.nav[NAV_LAT]), float(self.nav[NAV_H])
        v = self.nav[3:6]
        w_ie = geo.earth_rate_ned_rps(lat)
        w_en = geo.transport_rate_ned_rps(lat, h, v)
        a_n = self.C_nb @ f_b - np.cross(2.0 * w_ie + w_en, v)
        a_n[2] += geo.normal_gravity_mps2(lat, h)
        return w_ib - self.C_nb.T @ (w_ie + w_en), a_n

    def nav_state(self) -> NavState:
        """Solution at the IMU point at the last processed IMU sample (vehicle axes when
        misalignment is estimated); rate and acceleration from ``kinematics_now`` (independent of
        the covariance cadence ``cov_every``). Standard deviations (and the position's correlation
        coefficients) are those of the reported quantities -- position and velocity at the time
        label, vehicle attitude -- from the last covariance step (``reported``: J P J^T), scaled by
        the windowed NIS ratio of the GNSS position updates when it exceeds 1
        (``ConsistencyMonitor.variance_ratio``: the filter's covariance understates its errors)."""
        Rm = self.misalignment_dcm()
        C_nv = self.C_nb @ Rm.T
        w_nb_b, a_n = self.kinematics_now()
        J = reported_jacobian(self.layout, self.C_nb, self.fx.misalignment_rad, self.nav[3:6], a_n, w_nb_b)
        cov = reported_covariance(self.P, J) * self.consistency.variance_ratio()
        sd = np.sqrt(np.abs(np.diag(cov)))
        coasting = (self.t_s - self.last_gnss_t_s) > self.cfg.coast_after_s
        fix = FixStatus.DEAD_RECKONING if (coasting and self.initialized) else self.last_fix
        return NavState(t_s=float(self.t_s), lla=self.nav[:3].copy(), v_ned_mps=self.nav[3:6].copy(),
                        acc_body_mps2=C_nv.T @ a_n, rate_body_rps=Rm @ w_nb_b,
                        rpy_rad=euler_from_dcm(C_nv), pos_sd_m=sd[0:3].copy(),
                        vel_sd_mps=sd[3:6].copy(), att_sd_rad=sd[6:9].copy(), fix=fix,
                        attitude_ok=bool(self.heading_known), pos_corr=correlations(cov[0:3, 0:3]),
                        consistent=self.consistency.state != INCONSISTENT,
                        verified=self.consistency.state == VERIFIED)

    def antenna_lla(self) -> np.ndarray:
        """Current antenna position (lat, lon rad; h m) from the IMU point and the lever arm."""
        Cl = self.C_nb @ self.fx.lever_arm_m
        lat, h = self.nav[NAV_LAT], self.nav[NAV_H]
        r_m, r_n = geo.radii_m(lat)
        return self.nav[:3] + np.array([Cl[0] / (r_m + h), Cl[1] / ((r_n + h) * math.cos(lat)), -Cl[2]])

    def effects_report(self) -> dict:
        out = self.fx.as_dict(self.corr)
        out["sd"] = {name: self.sd(name).tolist() for name in self.layout.effects}
        return out
