"""Seed 001 online bias calibration at level stops, judged and computed with what the filter knows.

Frames: b is the filter's body frame (IMU axes turned by the *declared* mounting, x forward, y right,
z down), v the vehicle frame, ``R_vb = R(m)`` (Z-Y-X Euler angles m = roll, pitch, yaw) the
estimated mounting (the filter's ``misalignment`` effect), NED the local level frame, ``C_nb``
b -> NED. Every estimate is in b axes, the axes of the filter's bias states and of the compensation
of the raw samples (``InsFilter.corr``): a bias b_imu in IMU axes is ``imu_to_body @ b_imu`` there.
Errors are estimate minus truth, as in the filter.

**Stop.** Every frame must be static, ``|w| < gyro_norm_max_rps`` and ``| |f| - g | <
accel_norm_dev_max_mps2``, and the caller must not say ``moving`` (the filter: its stop detector,
without the rate test while the gyro bias is unknown, and its speed; ``ImuPath._feed_stop_calibration``). Window 1 (``window1_s``) is judged for level; window 2
follows and lasts while the stop does (at least ``window2_s``, at most ``window2_max_s``; ended by
motion, it loses its last ``end_trim_s``, which may hold the first motion). One estimate per stop;
the calibrator re-arms after a non-static frame; ``finish`` closes an open window at the end of the
data.

**Level** is a property of the vehicle on the road, not of the IMU: a stop on a grade (a hill start:
the brakes hold the car against gravity, the body settles on its suspension) is no calibration
stop. The vehicle's down direction in its own axes is ``u_v = R_vb u_b``, with ``u_b`` the IMU's own
gravity direction over the stop, ``-(mean f - b_a) / |mean f - b_a|`` (b_a the filter's
accelerometer bias state); roll ``atan2(u_y, u_z)``, pitch ``-asin(u_x)`` (Groves 2013 eqs.
5.101-5.102). Their covariance: the bias error db turns ``u_b`` by ``rho = -[u_b x] db / g``, the
mounting error dm enters through ``R(m - dm)``; (db, dm) and their correlation are the filter's
covariance, and the Jacobian of (roll, pitch) in (rho, dm) is taken by central differences.

What needs level, with the filter's attitude: nothing in the estimates. The gyro bias needs only an
IMU that stands still (the Earth rate is removed with the attitude); the accelerometer bias is
taken with the filter's attitude, not with an assumed level, and is off by g times that attitude's
error at any grade (below). A grade changes them only in second order: g sin(theta) on a horizontal
axis meets the gyro's g-sensitivity and the accelerometer's scale and cross-axis errors (0.05 g at
a 5 % grade: 5e-3 deg/s at 0.1 deg/s/g, 5 mm/s^2 at 1 %), and on a grade a car whose brake is
let go creeps with an acceleration up to g sin(theta) that the per-frame static test does not see
(only the filter's speed does, once the creep has lasted).
That is why a hill stop is left out; nothing is lost by it, the ZARU and the ZUPT take its samples
as at any stop. The level verdict is therefore a test whose costly error is the false "not level":
a valid stop and its check are lost, and on real roads -- a crossfall of 1.5 to 2.5 % (0.9 to
1.4 deg), a roll mounting the motion does not show (the vehicle constraints see a velocity along
the vehicle's x axis, which a roll leaves unchanged) and so known only to about a degree -- a rule
that wants the stop *shown* level loses most stops. A false "level" (a grade a little beyond the
limit) keeps estimates that are right within their sds. So a stop is **not level only when its
tilt is beyond the limits with confidence**: P(|roll| < ``level_roll_max_rad``) times P(|pitch| <
``level_pitch_max_rad``), each tilt x ~ N(estimate, sd^2) (``Phi((lim - x)/s) - Phi((-lim - x)/s)``;
roll and pitch errors taken as independent), is at most ``1 - level_confidence``. A tilt known
to a tenth of a degree beyond the limit (a 5 % grade: 2.9 deg) is not level; an unknown one is
not shown to be tilted and is level (a tilt sd of 10 deg gives 0.16 per axis), except when the
prior itself makes a tilt beyond the limits likely on both axes (both mounting angles at their
10-degree prior: 0.16 x 0.16 = 0.025; a filter with the level start,
``Initialization._level_start``, knows the roll to 2 deg from its start and judges such a stop at
once). The mounting is constant and each stop's mean specific force is kept, so a stop not level
is judged again at every later stop for ``level_pending_max_s`` with the filter's mounting and bias
of then (the accelerometer bias drift over that time, <= 5e-3 m/s^2 in the
default model, turns u_b by 0.03 deg), and its estimate is published when the stop is then level
(``late``).

**Estimate** over window 2: the means of w and f, their standard errors by batch means over
``sem_blocks`` blocks (correlated engine vibration stays honest; Flegal & Jones 2010, Ann. Stat.
38(2)). At rest the true specific force is ``-g u_b`` and the true rate the Earth rate, so with the
filter's attitude at the start of window 2 (the vehicle stands still; that attitude has not seen
window 2's samples), ``u_b = C_bn e_D``:

    b_g = mean w - C_bn w_ie^n,          b_a = mean f + g u_b.

**The accelerometer bias is separable from tilt only to the accuracy of that attitude**: an
attitude error phi moves the estimate by ``-C_bn [g^n x] phi``, g per radian of tilt, i.e.
9.8 mm/s^2 per mrad (0.17 m/s^2 per degree) on the horizontal axes, and the estimate's covariance
adds ``A P_phi A^T`` (``A = -C_bn [g^n x]``) to the sampling part. A GNSS-aided filter that has
driven with turns knows its tilt to a few mrad (a few cm/s^2); one that has only stood still knows
it to its accelerometer bias prior over g, i.e. the estimate then says nothing new horizontally.
Without an attitude (before alignment) only the component along gravity is measured,
``u_b . b_a = u_b . b_a0 + g - |mean f - b_a0|`` to first order; the horizontal components keep
the caller's prior (mean b_a0 and covariance). The Earth rate (<= 7.3e-5 rad/s) is removed with the
attitude; with the heading open only its vertical part (the horizontal part, of known size and
unknown direction, is noise of variance |w_h|^2 / 2 per horizontal axis); without a position it
stays in, with variance |w_ie|^2 per axis. Floors on the sampling sds: a standing car still moves on
its suspension and under its occupants, its attitude over a window changing by about
``settling_angle_rad`` (drive_0708's parking stop: 1 mrad in 2 s), which a rate mean over T reads
as a bias of that / T and a specific-force mean as g times it; normal gravity is wrong by the
gravity anomaly and the deflection of the vertical (``gravity_anomaly_mps2``).

**Check against the filter** (with an attitude): the estimate minus the filter's bias states at the
start of window 2 and the covariance of that difference, gyro ``R_g + P_bg``, accelerometer
``R_a + J P J^T`` with ``J = [A, -I]`` over (phi, b_a), which keeps the correlation of tilt and
bias the filter's levelling built; ``*_nis`` are the normalised squared differences (chi-square,
3 degrees of freedom, when both are right). How the filter uses an estimate (one estimate of each
bias, no sample counted twice): ``InsFilter._update_static_calibration`` and docs/ins.md.

``estimates`` keeps every published estimate (the IMU-grading work reads the bias stability between
stops), ``not_level`` the verdicts of the stops not (yet) level, ``latest`` the last estimate
made, published or not (the filter's start uses it).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
from scipy.stats import norm

from v2xpos.geo import G0_MPS2, OMEGA_IE_RPS
from v2xpos.rotation import dcm_from_euler, exp_so3, skew

PRIOR_ATT, PRIOR_MIS, PRIOR_BG, PRIOR_BA = slice(0, 3), slice(3, 6), slice(6, 9), slice(9, 12)
"""Blocks of ``StopPrior.cov``: attitude error phi (NED), mounting error (roll, pitch, yaw), gyro
bias, accelerometer bias."""
TILT_JACOBIAN_STEP_RAD = 1e-6
"""Step of the central differences that give the tilt's Jacobian."""


@dataclass
class StaticCalibrationConfig:
    """Thresholds and windows (defaults for automotive MEMS IMUs on a parked car with the engine
    running; see docs/ins.md)."""
    enabled: bool = True
    gyro_norm_max_rps: float = 0.15          # per frame (engine vibration reaches ~0.07 rad/s)
    accel_norm_dev_max_mps2: float = 0.8     # per frame
    level_roll_max_rad: float = math.radians(2.0)    # the vehicle's roll and pitch at a level stop
    level_pitch_max_rad: float = math.radians(2.0)   # (a 5 % grade is 2.9 deg)
    level_confidence: float = 0.95           # not level when P(beyond the limits) is at least this
    level_pending_max_s: float = 600.0       # a stop not level is judged again at later stops this long
    window1_s: float = 1.0
    window2_s: float = 1.0                   # least length of window 2 ...
    window2_max_s: float = 10.0              # ... which lasts while the stop does, up to this
    end_trim_s: float = 0.5                  # dropped from a window 2 ended by motion (the stop detector's window)
    sem_blocks: int = 10                     # batch means for the standard errors
    settling_angle_rad: float = 1e-3         # attitude change of a standing car over a window (suspension, occupants)
    gravity_anomaly_mps2: float = 3e-3       # normal gravity's error (anomaly, deflection of the vertical)
    accel_bias_prior_sd_mps2: float = 0.2    # accelerometer bias prior of a calibrator without a filter
    gravity_mps2: float = G0_MPS2            # replaced by normal gravity at the position when known


@dataclass
class StopPrior:
    """What the caller (the navigation filter) knows now: the estimated mounting R_vb =
    R(``mounting_rpy_rad``), the bias states (the compensation of the raw samples, b axes) and the
    covariance of the errors of (phi, mounting, b_g, b_a) in the ``PRIOR_*`` blocks; ``C_nb``
    (b -> NED) None before the filter has an attitude, ``earth_rate_ned_rps`` None before it has a
    position, ``heading_known`` False while the yaw is open."""
    mounting_rpy_rad: np.ndarray
    gyro_bias_rps: np.ndarray
    accel_bias_mps2: np.ndarray
    cov: np.ndarray
    C_nb: np.ndarray | None = None
    earth_rate_ned_rps: np.ndarray | None = None
    heading_known: bool = True


def standalone_prior(cfg: StaticCalibrationConfig) -> StopPrior:
    """The prior of a calibrator fed without a filter: samples already in vehicle axes (the
    mounting exact), zero biases, the accelerometer bias known to ``accel_bias_prior_sd_mps2``."""
    cov = np.zeros((12, 12))
    cov[PRIOR_BA, PRIOR_BA] = np.eye(3) * cfg.accel_bias_prior_sd_mps2 ** 2
    return StopPrior(np.zeros(3), np.zeros(3), np.zeros(3), cov)


@dataclass
class StopTilt:
    """The level verdict of a stop whose window 1 spans [t_start_s, t_end_s]: the vehicle's (roll,
    pitch) [rad], their sds, the probability that both are within the limits and the verdict (not
    level when that probability is at most ``1 - level_confidence``), made with the filter's
    knowledge at ``t_judged_s``."""
    t_start_s: float
    t_end_s: float
    tilt_rad: np.ndarray
    tilt_sd_rad: np.ndarray
    level_probability: float
    level: bool
    t_judged_s: float

    def as_dict(self) -> dict:
        return {"t_start_s": self.t_start_s, "t_end_s": self.t_end_s, "tilt_rad": self.tilt_rad.tolist(),
                "tilt_sd_rad": self.tilt_sd_rad.tolist(), "level_probability": self.level_probability,
                "t_judged_s": self.t_judged_s}


@dataclass
class StaticBiasEstimate:
    """One stop: the time span [s] of window 2, gyro bias [rad/s] and accelerometer bias [m/s^2] in
    b axes, the standard errors of the window's means (``*_sem_*``), the estimates' covariances
    (sems floored, attitude and Earth-rate terms added; module docstring), the number of frames,
    whether the filter's attitude removed gravity (``attitude``) and the level verdict.
    ``accel_attitude_sd_mps2``: the part of the accelerometer estimate's sd that is the gravity
    removed with an uncertain attitude, g times the tilt's sd on the horizontal axes (without an
    attitude: the prior of the horizontal components, which the stop does not measure). With an
    attitude, ``filter_*`` are the filter's bias states at the start of window 2 and
    ``*_difference_sd_*`` the sds of estimate minus state. ``late``: published at a later stop that
    showed this one level; ``applied``: the filter used it (``InsFilter._update_static_calibration``,
    before alignment ``ImuPath._feed_alignment``)."""
    t_start_s: float
    t_end_s: float
    gyro_bias_rps: np.ndarray
    accel_bias_mps2: np.ndarray
    gyro_sem_rps: np.ndarray
    accel_sem_mps2: np.ndarray
    frames: int
    gyro_cov: np.ndarray
    accel_cov: np.ndarray
    attitude: bool
    tilt: StopTilt
    accel_attitude_sd_mps2: np.ndarray = field(default_factory=lambda: np.zeros(3))
    filter_gyro_bias_rps: np.ndarray | None = None
    filter_accel_bias_mps2: np.ndarray | None = None
    gyro_difference_sd_rps: np.ndarray | None = None
    accel_difference_sd_mps2: np.ndarray | None = None
    gyro_nis: float | None = None
    accel_nis: float | None = None
    late: bool = False
    applied: bool = False

    @property
    def gyro_sd_rps(self) -> np.ndarray:
        return np.sqrt(np.diag(self.gyro_cov))

    @property
    def accel_sd_mps2(self) -> np.ndarray:
        return np.sqrt(np.diag(self.accel_cov))

    def as_dict(self) -> dict:
        d = {"t_start_s": self.t_start_s, "t_end_s": self.t_end_s,
             "gyro_bias_rps": self.gyro_bias_rps.tolist(), "accel_bias_mps2": self.accel_bias_mps2.tolist(),
             "gyro_sem_rps": self.gyro_sem_rps.tolist(), "accel_sem_mps2": self.accel_sem_mps2.tolist(),
             "gyro_sd_rps": self.gyro_sd_rps.tolist(), "accel_sd_mps2": self.accel_sd_mps2.tolist(),
             "accel_attitude_sd_mps2": self.accel_attitude_sd_mps2.tolist(),
             "frames": self.frames, "attitude": self.attitude, "late": self.late, "applied": self.applied,
             "level": self.tilt.as_dict()}
        if self.filter_gyro_bias_rps is not None:
            d.update({"filter_gyro_bias_rps": self.filter_gyro_bias_rps.tolist(),
                      "filter_accel_bias_mps2": self.filter_accel_bias_mps2.tolist(),
                      "gyro_difference_rps": (self.gyro_bias_rps - self.filter_gyro_bias_rps).tolist(),
                      "gyro_difference_sd_rps": self.gyro_difference_sd_rps.tolist(),
                      "accel_difference_mps2": (self.accel_bias_mps2 - self.filter_accel_bias_mps2).tolist(),
                      "accel_difference_sd_mps2": self.accel_difference_sd_mps2.tolist(),
                      "gyro_nis": self.gyro_nis, "accel_nis": self.accel_nis})
        return d


def vehicle_tilt(down_b: np.ndarray, mounting_rpy_rad: np.ndarray) -> np.ndarray:
    """(roll, pitch) [rad] of the vehicle whose b axes see NED down along the unit ``down_b``,
    with the mounting R_vb = R(``mounting_rpy_rad``)."""
    u = dcm_from_euler(*mounting_rpy_rad) @ down_b
    return np.array([math.atan2(u[1], u[2]), math.atan2(-u[0], math.hypot(u[1], u[2]))])


def tilt_covariance(down_b: np.ndarray, mounting_rpy_rad: np.ndarray, cov_rho_mis: np.ndarray) -> np.ndarray:
    """2 x 2 covariance of ``vehicle_tilt`` from the 6 x 6 covariance of (rho, dm): rho the small
    rotation (b axes) from ``down_b`` to the true down, dm the mounting error."""
    J = np.zeros((2, 6))
    m = np.asarray(mounting_rpy_rad, float)
    e = TILT_JACOBIAN_STEP_RAD
    for k in range(6):
        step = np.zeros(6)
        step[k] = e
        up = vehicle_tilt(exp_so3(step[:3]) @ down_b, m - step[3:])
        dn = vehicle_tilt(exp_so3(-step[:3]) @ down_b, m + step[3:])
        J[:, k] = (up - dn) / (2 * e)
    return J @ cov_rho_mis @ J.T


def level_probability(tilt_rad: np.ndarray, tilt_sd_rad: np.ndarray, max_rad: np.ndarray) -> float:
    """P(|roll| < max and |pitch| < max), each tilt x ~ N(estimate, sd^2) (sd 0: certain), the two
    independent. Arrays are (roll, pitch)."""
    def inside(x: float, s: float, lim: float) -> float:
        return float(norm.cdf((lim - x) / s) - norm.cdf((-lim - x) / s)) if s > 0 else float(abs(x) < lim)
    return inside(float(tilt_rad[0]), float(tilt_sd_rad[0]), float(max_rad[0])) * \
        inside(float(tilt_rad[1]), float(tilt_sd_rad[1]), float(max_rad[1]))


def gravity_tilt_jacobian(C_nb: np.ndarray, gravity_mps2: float) -> np.ndarray:
    """A = -C_bn [g^n x]: how an attitude error phi (NED) moves ``mean f + g C_bn e_D``."""
    return -C_nb.T @ skew(np.array([0.0, 0.0, gravity_mps2]))


def batch_sem(x: np.ndarray, blocks: int) -> np.ndarray:
    """Standard error of the mean of each column by batch means over ``blocks`` contiguous blocks
    (from the samples' own variance when there are fewer than two samples a block)."""
    n = len(x)
    if n < 2 * blocks or blocks < 2:
        return np.sqrt(np.var(x, axis=0, ddof=1) / n) if n > 1 else np.zeros(x.shape[1])
    means = np.array([b.mean(axis=0) for b in np.array_split(x, blocks)])
    return np.sqrt(np.var(means, axis=0, ddof=1) / blocks)


def judge_level(cfg: StaticCalibrationConfig, mean_f_b: np.ndarray, gravity_mps2: float, p: StopPrior,
                t_start_s: float, t_end_s: float, t_judged_s: float) -> StopTilt:
    """The level verdict of a stop with mean specific force ``mean_f_b`` (b axes) given what the
    filter knows in ``p`` (module docstring)."""
    fc = mean_f_b - p.accel_bias_mps2
    u = -fc / np.linalg.norm(fc)
    S = skew(u) / gravity_mps2
    cov = np.zeros((6, 6))
    cov[:3, :3] = S @ p.cov[PRIOR_BA, PRIOR_BA] @ S.T
    cov[:3, 3:] = -S @ p.cov[PRIOR_BA, PRIOR_MIS]
    cov[3:, :3] = cov[:3, 3:].T
    cov[3:, 3:] = p.cov[PRIOR_MIS, PRIOR_MIS]
    tilt = vehicle_tilt(u, p.mounting_rpy_rad)
    sd = np.sqrt(np.maximum(np.diag(tilt_covariance(u, p.mounting_rpy_rad, cov)), 0.0))
    prob = level_probability(tilt, sd, np.array([cfg.level_roll_max_rad, cfg.level_pitch_max_rad]))
    return StopTilt(t_start_s, t_end_s, tilt, sd, prob, prob > 1.0 - cfg.level_confidence, t_judged_s)


def bias_estimate(cfg: StaticCalibrationConfig, f: np.ndarray, w: np.ndarray, gravity_mps2: float, p: StopPrior,
                  t_start_s: float, t_end_s: float, tilt: StopTilt) -> StaticBiasEstimate:
    """The estimate from window 2's raw samples ``f``, ``w`` (b axes) with what the filter knew at
    its start (module docstring), compared with the filter's bias states when it had an attitude."""
    g = gravity_mps2
    mf, mw = f.mean(axis=0), w.mean(axis=0)
    sf, sw = batch_sem(f, cfg.sem_blocks), batch_sem(w, cfg.sem_blocks)
    span_s = max(t_end_s - t_start_s, 1e-3)
    gyro_cov = np.diag(np.maximum(sw, cfg.settling_angle_rad / span_s) ** 2)
    r_a = np.diag(np.maximum(sf, math.hypot(cfg.gravity_anomaly_mps2, g * cfg.settling_angle_rad)) ** 2)
    if p.C_nb is not None:
        u = p.C_nb[2].copy()
    else:
        fc = mf - p.accel_bias_mps2
        u = -fc / np.linalg.norm(fc)
    horizontal = np.eye(3) - np.outer(u, u)
    if p.earth_rate_ned_rps is None:
        earth_b = np.zeros(3)
        gyro_cov += np.eye(3) * OMEGA_IE_RPS ** 2
    elif p.C_nb is None or not p.heading_known:
        w_n = p.earth_rate_ned_rps
        earth_b = w_n[2] * u
        gyro_cov += horizontal * 0.5 * float(w_n[0] ** 2 + w_n[1] ** 2)
    else:
        earth_b = p.C_nb.T @ p.earth_rate_ned_rps
    if p.C_nb is not None:
        ba = mf + g * u
        A = gravity_tilt_jacobian(p.C_nb, g)
        attitude_cov = A @ p.cov[PRIOR_ATT, PRIOR_ATT] @ A.T
        accel_cov = r_a + attitude_cov
    else:
        ba = p.accel_bias_mps2 + (g - float(np.linalg.norm(mf - p.accel_bias_mps2))) * u
        attitude_cov = horizontal @ p.cov[PRIOR_BA, PRIOR_BA] @ horizontal
        accel_cov = attitude_cov + float(u @ r_a @ u) * np.outer(u, u)
    est = StaticBiasEstimate(t_start_s, t_end_s, mw - earth_b, ba, sw, sf, len(f), gyro_cov, accel_cov,
                             p.C_nb is not None, tilt, np.sqrt(np.maximum(np.diag(attitude_cov), 0.0)))
    if p.C_nb is not None:
        compare_with_filter(est, p, r_a, g)
    return est


def compare_with_filter(est: StaticBiasEstimate, p: StopPrior, accel_noise_cov: np.ndarray, g: float) -> None:
    """Set ``est``'s ``filter_*``, ``*_difference_sd_*`` and ``*_nis``: the estimate minus the
    filter's bias states in ``p`` and the covariance of that difference (module docstring);
    ``accel_noise_cov`` is the sampling part of the accelerometer estimate's covariance."""
    d_g = est.gyro_bias_rps - p.gyro_bias_rps
    cov_g = est.gyro_cov + p.cov[PRIOR_BG, PRIOR_BG]
    J = np.zeros((3, 12))
    J[:, PRIOR_ATT] = gravity_tilt_jacobian(p.C_nb, g)
    J[:, PRIOR_BA] = -np.eye(3)
    d_a = est.accel_bias_mps2 - p.accel_bias_mps2
    cov_a = accel_noise_cov + J @ p.cov @ J.T
    est.filter_gyro_bias_rps = p.gyro_bias_rps.copy()
    est.filter_accel_bias_mps2 = p.accel_bias_mps2.copy()
    est.gyro_difference_sd_rps = np.sqrt(np.diag(cov_g))
    est.accel_difference_sd_mps2 = np.sqrt(np.diag(cov_a))
    est.gyro_nis = float(d_g @ np.linalg.solve(cov_g, d_g))
    est.accel_nis = float(d_a @ np.linalg.solve(cov_a, d_a))


@dataclass
class _PendingStop:
    """A stop not (yet) judged level: its verdict, the mean specific force and the gravity
    of its windows, and its estimate (None while window 2 runs or if it was too short)."""
    tilt: StopTilt
    mean_f_b: np.ndarray
    gravity_mps2: float
    est: StaticBiasEstimate | None = None


@dataclass
class StaticCalibrator:
    """State machine fed with chunks of raw body-frame samples (module docstring)."""
    cfg: StaticCalibrationConfig = field(default_factory=StaticCalibrationConfig)
    estimates: list = field(default_factory=list)
    not_level: list = field(default_factory=list)
    _pending: list = field(default_factory=list)
    _phase: int = 0          # 0 window 1, 1 window 2, 2 done for this stop (wait for motion)
    _t0: float = 0.0
    _n1: int = 0
    _sum_f1: np.ndarray = field(default_factory=lambda: np.zeros(3))
    _t: list = field(default_factory=list)
    _f: list = field(default_factory=list)
    _w: list = field(default_factory=list)
    _g: float = G0_MPS2
    _prior: StopPrior | None = None
    _tilt: StopTilt | None = None
    _t_level_end: float = -math.inf
    made: int = 0                                    # estimates made, published or not
    latest: StaticBiasEstimate | None = None         # the last one made

    @property
    def stops_not_level(self) -> int:
        return len(self.not_level)

    def averaging(self, t_s: float, after_s: float) -> bool:
        """Whether a rate mean over the ``after_s`` before ``t_s`` reaches into the window 2 of a
        stop judged level (now averaging, or ended less than ``after_s`` before ``t_s``): the
        samples whose rate information goes to the filter through this calibrator's estimate."""
        return (self._phase == 1 and self._tilt.level) or t_s - self._t_level_end < after_s

    def static_frames(self, acc_b: np.ndarray, gyro_b: np.ndarray, gravity_mps2: float) -> np.ndarray:
        c = self.cfg
        return ((np.linalg.norm(gyro_b, axis=1) < c.gyro_norm_max_rps)
                & (np.abs(np.linalg.norm(acc_b, axis=1) - gravity_mps2) < c.accel_norm_dev_max_mps2))

    def _reset(self, phase: int, t0: float) -> None:
        self._phase, self._t0 = phase, t0
        self._n1 = 0
        self._sum_f1[:] = 0.0
        self._t.clear()
        self._f.clear()
        self._w.clear()

    def feed(self, t_s: np.ndarray, acc_b: np.ndarray, gyro_b: np.ndarray, moving: bool = False,
             gravity_mps2: float | None = None,
             prior: StopPrior | Callable[[], StopPrior] | None = None) -> list[StaticBiasEstimate]:
        """Consume a chunk (arrays of equal length, raw samples in b axes). ``moving``: the
        caller's cue that the vehicle is not standing (ends the stop); ``prior``: what the caller
        knows, or a function giving it (called only at the end of a window 1); None:
        ``standalone_prior``. Returns the estimates published in this chunk (this stop's, and
        earlier stops' judged level now)."""
        if not self.cfg.enabled or len(t_s) == 0:
            return []
        if moving:
            out = self._end_stop()
            self._reset(0, float(t_s[-1]))
            return out
        g = self.cfg.gravity_mps2 if gravity_mps2 is None else gravity_mps2
        bad = np.flatnonzero(~self.static_frames(acc_b, gyro_b, g))
        if len(bad) == 0:
            return self._consume(t_s, acc_b, gyro_b, g, prior)
        out = self._consume(t_s[:bad[0]], acc_b[:bad[0]], gyro_b[:bad[0]], g, prior) if bad[0] > 0 else []
        out = out + self._end_stop()
        self._reset(0, float(t_s[bad[-1]]))
        k = bad[-1] + 1
        if k < len(t_s):
            out = out + self._consume(t_s[k:], acc_b[k:], gyro_b[k:], g, prior)
        return out

    def _consume(self, t, f, w, g, prior) -> list[StaticBiasEstimate]:
        c = self.cfg
        if self._phase == 2:
            return []
        if self._phase == 0:
            if self._n1 == 0:
                self._t0 = float(t[0])
            self._n1 += len(t)
            self._sum_f1 += f.sum(0)
        else:
            self._t.append(t)
            self._f.append(f)
            self._w.append(w)
        t_end = float(t[-1])
        if self._phase == 0 and t_end - self._t0 >= c.window1_s:
            p = prior() if callable(prior) else prior
            p = p if p is not None else standalone_prior(c)
            out = self._revisit(p, t_end)
            tilt = judge_level(c, self._sum_f1 / self._n1, g, p, self._t0, t_end, t_end)
            if not tilt.level:
                self.not_level.append(tilt)
                self._pending.append(_PendingStop(tilt, self._sum_f1 / self._n1, g))
            n1, sum_f1 = self._n1, self._sum_f1.copy()
            self._reset(1, t_end)
            self._prior, self._tilt, self._g, self._n1, self._sum_f1 = p, tilt, g, n1, sum_f1
            return out
        if self._phase == 1 and t_end - self._t0 >= c.window2_max_s:
            out = self._finish(t_end)
            self._reset(2, t_end)
            return out
        return []

    def finish(self) -> list[StaticBiasEstimate]:
        """The data ended: an open window 2 is closed as if the stop ended there (nothing to trim)."""
        if self._phase != 1 or not self._t:
            return []
        t_last = float(self._t[-1][-1])
        out = self._finish(t_last)
        self._reset(2, t_last)
        return out

    def _end_stop(self) -> list[StaticBiasEstimate]:
        """The stop ended (a non-static frame or the caller's cue): window 2 without its last
        ``end_trim_s``, which may hold the first motion."""
        if self._phase != 1 or not self._t:
            return []
        t = np.concatenate(self._t)
        keep = t <= t[-1] - self.cfg.end_trim_s
        self._t, self._f, self._w = [t[keep]], [np.concatenate(self._f)[keep]], [np.concatenate(self._w)[keep]]
        return self._finish(float(t[keep][-1]) if keep.any() else self._t0)

    def _finish(self, t_end_s: float) -> list[StaticBiasEstimate]:
        """The estimate of window 2 if it lasted ``window2_s``: published when the stop is level,
        else kept for later verdicts."""
        c = self.cfg
        if t_end_s - self._t0 < c.window2_s:
            return []
        f, w = np.concatenate(self._f), np.concatenate(self._w)
        est = bias_estimate(c, f, w, self._g, self._prior, self._t0, t_end_s, self._tilt)
        self.made += 1
        self.latest = est
        if est.tilt.level:
            self._t_level_end = t_end_s
            self.estimates.append(est)
            return [est]
        pending = next(x for x in self._pending if x.tilt is est.tilt)
        pending.est, pending.mean_f_b = est, (f.sum(0) + self._sum_f1) / (len(f) + self._n1)
        return []

    def _revisit(self, p: StopPrior, t_s: float) -> list[StaticBiasEstimate]:
        """Judge the pending stops again with what the filter knows now: those now level leave
        ``not_level`` and their estimates are published (``late``); those older than
        ``level_pending_max_s`` are judged no more (their verdict stays in ``not_level``)."""
        c = self.cfg
        out, keep = [], []
        for s in self._pending:
            if t_s - s.tilt.t_end_s > c.level_pending_max_s:
                continue
            tilt = judge_level(c, s.mean_f_b, s.gravity_mps2, p, s.tilt.t_start_s, s.tilt.t_end_s, t_s)
            i = next(k for k, x in enumerate(self.not_level) if x is s.tilt)
            if tilt.level:
                del self.not_level[i]
                if s.est is not None:
                    s.est.tilt, s.est.late = tilt, True
                    self.estimates.append(s.est)
                    out.append(s.est)
            else:
                self.not_level[i] = tilt
                if s.est is not None:
                    s.est.tilt = tilt
                s.tilt = tilt
                keep.append(s)
        self._pending = keep
        return out
