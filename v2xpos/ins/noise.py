"""The IMU's white-noise densities measured from its own samples, for the filter's process noise.

Why: the filter's covariance is the sigma every relative result carries (docs/integrity.md). With
the configured automotive figures (gyro 3e-3 rad/s/sqrt(Hz), "including vehicle vibration") on an
IMU whose noise is 35 times lower (the convoy recordings), the filter's yaw sd is 5-10 times its
real error and every relative sigma with it; on a real car the vibration while driving is larger
than that figure and changes with speed (drive_0708: 7e-4 stopped, 1e-2 driving). So the density
is measured, continuously, from the data.

Method (the estimator of ``v2xpos.diagnose.tuning.imu_noise_density``, run online): for white
noise of variance s^2 per sample, the second difference d_k = x_{k+1} - 2 x_k + x_{k-1} has
E[d^2] = 6 s^2, while the vehicle's own motion, smooth at the sample rate, contributes
(x'' dt^2)^2 (negligible); the density is n = s sqrt(dt). Mean squares are averaged with an
exponential window of time constant ``window_s`` per body axis, and the process noise of the
error state, whose attitude and velocity errors are in NED, is the diagonal of
C_nb diag(n_b^2) C_bn (per-axis densities rotated; Groves 2013 sec. 14.2.6 for the continuous
noise model, Q_phi = n_g^2 I for an isotropic gyro).

Limits: an IMU that low-pass filters internally below its output rate hides part of its white
noise from second differences (the estimate is then optimistic); vibration is not white (its
power sits at high frequencies), which makes the estimate conservative for the attitude random
walk. Both are visible in the filter's NIS (``v2xpos.ins.consistency``).
"""
from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from .ekf import ATT, BA, BG, EFFECT_SIZES, VEL, StateLayout

if TYPE_CHECKING:
    from .config import InsConfig

NOISE_WINDOW_S = 10.0
"""Time constant over which the running densities are averaged [s]."""
MIN_SAMPLES = 50
"""Second differences needed before the measured densities replace the configured ones."""
MIN_STATIC_SAMPLES = 300
"""Second differences at standstill needed before they set the heading axis's density (3 s at
100 Hz: the density's relative sd is then below 5 %)."""


def second_differences(x: np.ndarray) -> np.ndarray:
    """d_k = x_{k+1} - 2 x_k + x_{k-1} along axis 0: for white noise of variance s^2 per sample,
    E[d^2] = 6 s^2; the smooth motion of a vehicle adds (x'' dt^2)^2, negligible at IMU rates."""
    x = np.asarray(x, float)
    return x[2:] - 2.0 * x[1:-1] + x[:-2]


def density_from_mean_square(mean_d2: np.ndarray | float, dt_s: float) -> np.ndarray | float:
    """White-noise density s sqrt(dt) from the mean square of second differences (s^2 = E[d^2] / 6)."""
    return np.sqrt(np.asarray(mean_d2, float) / 6.0 * dt_s)


def allan_sums(x: np.ndarray, dt_s: float, m: int) -> tuple[np.ndarray, int]:
    """Sums of squared second differences of the integrated rate behind the overlapping Allan
    variance at cluster size ``m`` (tau = m dt), per column, and their count. With theta the
    integral of the rate x, IEEE Std 952-1997 (Annex C) / El-Sheimy et al. 2008 (eq. 4):
    ``AVAR(tau) = sum_k (theta_{k+2m} - 2 theta_{k+m} + theta_k)^2 / (2 tau^2 (N - 2m))``.
    The sums (not the variance) are returned so that several stops can be pooled."""
    x = np.asarray(x, float).reshape(len(x), -1)
    return allan_sums_theta(np.vstack((np.zeros((1, x.shape[1])), np.cumsum(x, axis=0) * dt_s)), m)


def allan_sums_theta(theta: np.ndarray, m: int) -> tuple[np.ndarray, int]:
    """``allan_sums`` from the integrated rate ``theta`` sampled every dt (rows)."""
    theta = np.asarray(theta, float).reshape(len(theta), -1)
    if 2 * m >= len(theta):
        return np.zeros(theta.shape[1]), 0
    d = theta[2 * m:] - 2.0 * theta[m:-m] + theta[:-2 * m]
    return np.einsum("ij,ij->j", d, d), len(d)


def allan_deviation(x: np.ndarray, dt_s: float, m: int) -> np.ndarray:
    """Overlapping Allan deviation of rate samples ``x`` (one column per axis) at tau = m dt (see
    ``allan_sums``); NaN when the record is shorter than 2 tau."""
    s, n = allan_sums(x, dt_s, m)
    return np.sqrt(s / (2.0 * (m * dt_s) ** 2 * n)) if n else np.full(s.shape, np.nan)


def process_noise_density(layout: StateLayout, cfg: InsConfig) -> np.ndarray:
    """Diagonal of the continuous process noise Q_c (per second) from the configured IMU figures
    (``ImuNoiseMeter.apply`` later replaces the white-noise parts with measured densities).

    Velocity: accelerometer white noise (VRW) density^2; attitude: gyro white noise (ARW)
    density^2; biases: 2 sigma^2 / tau (stationary Gauss-Markov); effects: their random walk^2.
    """
    q = np.zeros(layout.n)
    q[VEL:VEL + 3] = cfg.imu.accel_noise_mps2_rthz ** 2
    q[ATT:ATT + 3] = cfg.imu.gyro_noise_rps_rthz ** 2
    q[BG:BG + 3] = 2.0 * cfg.imu.gyro_bias_sd_rps ** 2 / cfg.imu.gyro_bias_tau_s
    q[BA:BA + 3] = 2.0 * cfg.imu.accel_bias_sd_mps2 ** 2 / cfg.imu.accel_bias_tau_s
    for name in layout.effects:
        i, k = layout.index[name], EFFECT_SIZES[name]
        q[i:i + k] = cfg.effects.effect_random_walk.get(name, 0.0) ** 2
    return q


class ImuNoiseMeter:
    """Running white-noise densities of gyro [rad/s/sqrt(Hz)] and accelerometer [m/s^2/sqrt(Hz)]
    per body axis (see the module docstring). ``gyro_scale``: the factor on the measured gyro
    density, one number or one per body axis (x, y, z)."""

    def __init__(self, window_s: float = NOISE_WINDOW_S, gyro_scale: float | tuple = 1.0, accel_scale: float = 1.0,
                 gyro_max_rps_rthz: float = math.inf, accel_max_mps2_rthz: float = math.inf):
        self.window_s = float(window_s)
        self.gyro_scale = np.broadcast_to(np.asarray(gyro_scale, float), (3,)).copy()
        self.accel_scale = float(accel_scale)
        self.gyro_max_rps_rthz = float(gyro_max_rps_rthz)
        self.accel_max_mps2_rthz = float(accel_max_mps2_rthz)
        self._tail_t: np.ndarray | None = None
        self._tail: np.ndarray | None = None
        self._sum = np.zeros(6)       # decayed sums of d^2 (gyro xyz, accel xyz)
        self._n = 0.0                 # decayed count
        self._sum_dt = 0.0
        self._t_last: float | None = None
        self.samples = 0
        self._static_sum = np.zeros(3)   # sums of d^2 of the gyro at standstill (not decayed)
        self._static_n = 0
        self._static_dt = 0.0

    def feed(self, t_s: np.ndarray, gyro_rps: np.ndarray, acc_mps2: np.ndarray, static: bool = False) -> None:
        """Samples of one chunk (body axes, in time order); ``static``: the vehicle stood still
        over the chunk (the stop detector's verdict), so the gyro's second differences are the
        sensor's own noise (``heading_density``)."""
        x = np.hstack((np.asarray(gyro_rps, float).reshape(-1, 3), np.asarray(acc_mps2, float).reshape(-1, 3)))
        t = np.asarray(t_s, float).reshape(-1)
        if self._tail is not None:
            x = np.vstack((self._tail, x))
            t = np.concatenate((self._tail_t, t))
        if len(t) >= 3:
            dt = np.diff(t)
            # equal spacing only: a gap or a jitter spike would read as noise
            h = np.median(dt)
            ok = (np.abs(dt[1:] - h) < 0.25 * h) & (np.abs(dt[:-1] - h) < 0.25 * h)
            d2 = second_differences(x)[ok]
            if len(d2):
                t_end = float(t[-1])
                decay = 1.0 if self._t_last is None else math.exp(-max(t_end - self._t_last, 0.0) / self.window_s)
                self._sum = self._sum * decay + np.einsum("ij,ij->j", d2, d2)
                self._n = self._n * decay + len(d2)
                self._sum_dt = self._sum_dt * decay + float(h) * len(d2)
                self._t_last = t_end
                self.samples += len(d2)
                if static:
                    self._static_sum += np.einsum("ij,ij->j", d2[:, :3], d2[:, :3])
                    self._static_n += len(d2)
                    self._static_dt += float(h) * len(d2)
        self._tail, self._tail_t = x[-2:].copy(), t[-2:].copy()

    @property
    def ready(self) -> bool:
        return self.samples >= MIN_SAMPLES and self._n > 0

    def densities(self) -> tuple[np.ndarray, np.ndarray]:
        """(gyro, accel) white-noise densities per body axis; NaN before ``ready``."""
        if not self.ready:
            return np.full(3, np.nan), np.full(3, np.nan)
        n = density_from_mean_square(self._sum / self._n, self._sum_dt / self._n)
        return n[:3], n[3:]

    def static_gyro_density(self) -> np.ndarray:
        """Gyro white-noise density per body axis over every standstill so far (NaN before
        ``MIN_STATIC_SAMPLES`` of them)."""
        if self._static_n < MIN_STATIC_SAMPLES:
            return np.full(3, np.nan)
        return density_from_mean_square(self._static_sum / self._static_n, self._static_dt / self._static_n)

    def apply(self, q_c: np.ndarray, C_nb: np.ndarray) -> None:
        """Write the scaled measured densities, each at most the configured one, into the
        filter's continuous process noise ``q_c`` (in place: attitude and velocity blocks, NED
        diagonal of the rotated per-axis noise); unchanged until ``ready``. The cap is the rule of
        ``v2xpos.diagnose.calibrate``: second differences weigh high-frequency vibration up to 16/6
        times, so an estimate above the configured figure may be out-of-band vibration and the
        configured figure stays."""
        if not self.ready:
            return
        g, a = self.densities()
        # the heading axis (body z): the density at standstill once there is one. While driving
        # the second differences of the z gyro carry the vibration of the other axes through the
        # mounting (and what the road shakes about z): real rotation at tens of Hz, whose integral
        # is bounded, not a random walk; the heading's random walk is driven by the sensor's
        # low-frequency noise, which a stop shows without the vehicle's motion (an Allan deviation
        # at tau >= 1 s at the stops agrees with it for a white sensor, IEEE Std 952-1997)
        g_static = self.static_gyro_density()
        if np.isfinite(g_static[2]):
            g = g.copy()
            g[2] = min(g[2], g_static[2])
        g = np.minimum(g * self.gyro_scale, self.gyro_max_rps_rthz)
        a = np.minimum(a * self.accel_scale, self.accel_max_mps2_rthz)
        C2 = C_nb * C_nb
        q_c[ATT:ATT + 3] = C2 @ (g * g)
        q_c[VEL:VEL + 3] = C2 @ (a * a)
