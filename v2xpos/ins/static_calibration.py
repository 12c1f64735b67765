"""Seed 001 online bias calibration from stops.

Over a first window of ``window1_s`` every frame must be static: ``|w| < gyro_norm_max_rps`` (thr1)
and ``| |f| - g | < accel_norm_dev_max_mps2`` (thr2); the window is then *level* when
``mean |f_x| < level_fx_max_mps2`` (thr3) and ``mean |f_y| < level_fy_max_mps2`` (thr4), with f
in the nominal body frame (IMU axes turned by the declared mounting). The means over the next
``window2_s`` (all frames still static) give the six error parameters: gyro bias = mean w; for a
level static IMU with z down, accelerometer bias x, y = mean f_x, f_y and z = mean f_z + g.
The Earth rate (< 7.3e-5 rad/s) is left inside the gyro bias: it is below MEMS bias stability.

A stop yields at most one estimate; the calibrator re-arms after a non-static frame. All estimates
are kept in ``estimates`` (the IMU-grading work reads the bias stability between stops).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from v2xpos.geo import G0_MPS2


@dataclass
class StaticCalibrationConfig:
    """Thresholds and windows (defaults chosen for automotive MEMS IMUs on a parked car with the
    engine running; see docs/ins.md)."""
    enabled: bool = True
    gyro_norm_max_rps: float = 0.15          # thr1, per frame (engine vibration reaches ~0.07 rad/s)
    accel_norm_dev_max_mps2: float = 0.8     # thr2, per frame
    level_fx_max_mps2: float = 0.35          # thr3 (~2 deg of pitch)
    level_fy_max_mps2: float = 0.35          # thr4 (~2 deg of roll)
    window1_s: float = 1.0
    window2_s: float = 2.0
    gravity_mps2: float = G0_MPS2            # replaced by normal gravity at the position when known


@dataclass
class StaticBiasEstimate:
    """One stop: time span [s], gyro bias [rad/s] and accelerometer bias [m/s^2] (body axes),
    their standard errors of the mean and the number of frames."""
    t_start_s: float
    t_end_s: float
    gyro_bias_rps: np.ndarray
    accel_bias_mps2: np.ndarray
    gyro_sem_rps: np.ndarray
    accel_sem_mps2: np.ndarray
    frames: int

    def as_dict(self) -> dict:
        return {"t_start_s": self.t_start_s, "t_end_s": self.t_end_s,
                "gyro_bias_rps": self.gyro_bias_rps.tolist(), "accel_bias_mps2": self.accel_bias_mps2.tolist(),
                "gyro_sem_rps": self.gyro_sem_rps.tolist(), "accel_sem_mps2": self.accel_sem_mps2.tolist(),
                "frames": self.frames}


@dataclass
class StaticCalibrator:
    """State machine fed with chunks of body-frame samples (see module docstring)."""
    cfg: StaticCalibrationConfig = field(default_factory=StaticCalibrationConfig)
    estimates: list = field(default_factory=list)
    _phase: int = 0          # 0 window1, 1 window2, 2 done for this stop (wait for motion)
    _t0: float = 0.0
    _n: int = 0
    _sum_w: np.ndarray = field(default_factory=lambda: np.zeros(3))
    _sum_f: np.ndarray = field(default_factory=lambda: np.zeros(3))
    _sum_w2: np.ndarray = field(default_factory=lambda: np.zeros(3))
    _sum_f2: np.ndarray = field(default_factory=lambda: np.zeros(3))
    _sum_abs_fx: float = 0.0
    _sum_abs_fy: float = 0.0

    def static_frames(self, acc_b: np.ndarray, gyro_b: np.ndarray, gravity_mps2: float) -> np.ndarray:
        c = self.cfg
        return ((np.linalg.norm(gyro_b, axis=1) < c.gyro_norm_max_rps)
                & (np.abs(np.linalg.norm(acc_b, axis=1) - gravity_mps2) < c.accel_norm_dev_max_mps2))

    def _reset(self, phase: int, t0: float) -> None:
        self._phase, self._t0, self._n = phase, t0, 0
        self._sum_w[:] = 0.0
        self._sum_f[:] = 0.0
        self._sum_w2[:] = 0.0
        self._sum_f2[:] = 0.0
        self._sum_abs_fx = self._sum_abs_fy = 0.0

    def feed(self, t_s: np.ndarray, acc_b: np.ndarray, gyro_b: np.ndarray, moving: bool = False,
             gravity_mps2: float | None = None) -> StaticBiasEstimate | None:
        """Consume a chunk (arrays of equal length). ``moving``: an external cue (e.g. the filter's
        speed) that vetoes the chunk. Returns a new estimate when one is completed in this chunk."""
        if not self.cfg.enabled or len(t_s) == 0:
            return None
        if moving:
            if self._phase != 0 or self._n:
                self._reset(0, float(t_s[-1]))
            return None
        g = self.cfg.gravity_mps2 if gravity_mps2 is None else gravity_mps2
        ok = self.static_frames(acc_b, gyro_b, g)
        if moving:
            ok[:] = False
        bad = np.flatnonzero(~ok)
        if len(bad) == 0:
            return self._consume(t_s, acc_b, gyro_b, g)
        result = None
        if bad[0] > 0:
            result = self._consume(t_s[:bad[0]], acc_b[:bad[0]], gyro_b[:bad[0]], g)
        if self._phase != 0 or self._n:
            self._reset(0, float(t_s[bad[-1]]))
        k = bad[-1] + 1
        if k < len(t_s):
            result = self._consume(t_s[k:], acc_b[k:], gyro_b[k:], g) or result
        return result

    def _consume(self, t, f, w, g) -> StaticBiasEstimate | None:
        c = self.cfg
        if self._phase == 2:
            return None
        if self._n == 0:
            self._t0 = float(t[0])
        self._sum_w += w.sum(0)
        self._sum_f += f.sum(0)
        self._sum_w2 += (w * w).sum(0)
        self._sum_f2 += (f * f).sum(0)
        self._sum_abs_fx += np.abs(f[:, 0]).sum()
        self._sum_abs_fy += np.abs(f[:, 1]).sum()
        self._n += len(t)
        span = t[-1] - self._t0
        if self._phase == 0 and span >= c.window1_s:
            level = (self._sum_abs_fx / self._n < c.level_fx_max_mps2
                     and self._sum_abs_fy / self._n < c.level_fy_max_mps2)
            self._reset(1 if level else 2, t[-1])
            return None
        if self._phase == 1 and span >= c.window2_s:
            m = self._n
            mw, mf = self._sum_w / m, self._sum_f / m
            sw = np.sqrt(np.maximum(self._sum_w2 / m - mw ** 2, 0.0) / m)
            sf = np.sqrt(np.maximum(self._sum_f2 / m - mf ** 2, 0.0) / m)
            ba = np.array([mf[0], mf[1], mf[2] + g])
            est = StaticBiasEstimate(self._t0, float(t[-1]), mw, ba, sw, sf, m)
            self.estimates.append(est)
            self._reset(2, t[-1])
            return est
        return None
