"""The IMU path of ``InsFilter``: sample input, strapdown batches, and the steps at the end of each
chunk of ``cov_every`` samples.

``ImuPath`` is a base class of ``InsFilter`` holding these methods; they read and write the
filter's state (documented on ``InsFilter``) and call its covariance flush
(``_flush_covariance``), vehicle constraints (``_vehicle_constraints``) and stop-calibration
update (``_update_static_calibration``). Input checks: a sample with a non-finite value or a
stamp not after the previous one is counted in ``counts["malformed_inputs"]`` and skipped.
"""
from __future__ import annotations

import math
from time import perf_counter
from typing import TYPE_CHECKING

import numpy as np

from v2xpos import geo
from v2xpos.rotation import orthonormalize

from .ekf import ATT, BA, BG
from .mechanization import COR_BA, COR_BG, MEM_W, NAV_H, NAV_LAT, strapdown_batch
from .static_calibration import PRIOR_BA, PRIOR_BG, PRIOR_MIS, StaticBiasEstimate, StopPrior

if TYPE_CHECKING:
    from .config import InsConfig

DIVERGED_LATITUDE_RAD = 1.5
"""|latitude| beyond this (86 deg) means the strapdown has run away (no vehicle goes there): the
filter drops its solution and aligns again."""
ORTHONORMALIZE_EVERY_CHUNKS = 100
"""C_nb is re-orthonormalised every this many IMU chunks (rounding drift of the products)."""
TIME_TOLERANCE_S = 1e-6
"""Stamps this close count as the same time when deciding whether a constraint is due."""
ACC_SMOOTHING_TAU_S = 0.2
"""Time constant of the low-pass of the acceleration used in the measurement models' H (not in
``nav_state``): long enough to drop engine vibration, short against a vehicle's manoeuvres."""
CALIBRATION_MOVING_SPEED_MPS = 0.5
"""Above this filter speed the stop calibrator is told "moving" whatever the stop detector says."""


class ImuPath:
    """IMU input and chunk steps of ``InsFilter`` (module docstring)."""

    cfg: InsConfig

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
        M = self.cfg.setup.imu_to_body
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
        f_b = np.ascontiguousarray(acc @ self.cfg.setup.imu_to_body.T)
        w_b = np.ascontiguousarray(gyr @ self.cfg.setup.imu_to_body.T)
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
        ce = self.cfg.numerics.cov_every
        while i < n:
            j = min(n, i + ce - self._since_chunk)
            if self.initialized:
                t_prev = self.t_stamp_s if self.t_stamp_s is not None else t_s[i]
                t0 = perf_counter()
                strapdown_batch(t_s, f_b, w_b, i, j, t_prev, self.nav, self.C_nb, self.corr, self.mem,
                                self.A, self.kidx, 1.0 / self.cfg.imu.gyro_bias_tau_s,
                                1.0 / self.cfg.imu.accel_bias_tau_s)
                self.stage_s["strapdown"] += perf_counter() - t0
            self.t_stamp_s = float(t_s[j - 1])
            self._chunk_t.append(t_s[i:j])
            self._chunk_f.append(f_b[i:j])
            self._chunk_w.append(w_b[i:j])
            self._since_chunk += j - i
            i = j
            if self._since_chunk >= ce:
                self._end_chunk()

    def _end_chunk(self) -> None:
        """End of an IMU chunk (``cov_every`` samples): the steps below, in this order. Before the
        filter is aligned only the first three run, and the chunk feeds the coarse alignment."""
        t, f, w = self._take_chunk()
        if len(t) == 0:
            return
        self._last_w_b = (self.mem[MEM_W:MEM_W + 3].copy() if self.initialized
                          else w[-1] - self.corr[COR_BG:COR_BG + 3])
        self._detect_stop(f, w)
        if self.noise_meter is not None:
            self.noise_meter.feed(t, w, f, static=self.static)
        if self.initialized:
            self._smooth_acceleration(float(t[-1]))
            if not self.heading_known or self._align_pending_until_s is not None:
                self._note_drive_off_ins()
        speed = math.sqrt(float(self.nav[3:6] @ self.nav[3:6])) if self.initialized else 0.0
        ests, made = self._feed_stop_calibration(t, f, w, speed)
        self.counts["static_calibrations"] += len(ests)
        if not self.initialized:
            self._feed_alignment(t, f, w, made)
            return
        if np.abs(self.nav[NAV_LAT]) > DIVERGED_LATITUDE_RAD or not np.all(np.isfinite(self.nav)):
            self.initialized = False
            return
        self._flush_covariance()
        self._feed_consistency_motion(speed)
        for est in ests:
            if self.cfg.stops.apply_static_calibration and not (est.late or est.applied):
                self._update_static_calibration(est)
        if (not self.cfg.constraints.constraints_on_request
                and self.t_stamp_s - self._last_constraint_t
                >= 1.0 / self.cfg.constraints.constraint_rate_hz - TIME_TOLERANCE_S):
            self._last_constraint_t = self.t_stamp_s
            self._vehicle_constraints(speed)
        self._chunks_since_ortho += 1
        if self._chunks_since_ortho >= ORTHONORMALIZE_EVERY_CHUNKS:
            self._chunks_since_ortho = 0
            self.C_nb = orthonormalize(self.C_nb)

    def _take_chunk(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(t, f_b, w_b) of the samples since the last chunk end; the buffers start empty."""
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
        return t, f, w

    def _detect_stop(self, f: np.ndarray, w: np.ndarray) -> None:
        """Feed the chunk to the stop detector (``motion``) and set ``static``."""
        if self.initialized:
            self.stops.feed(f, w, self.C_nb, self.corr[COR_BA:COR_BA + 3])
        else:
            self.stops.feed(f, w)
        self.static = self.stops.is_static(self.t_s, self.corr[COR_BG:COR_BG + 3],
                                           self.nav[3:6] if self.initialized else None)

    def _smooth_acceleration(self, t_end_s: float) -> None:
        """Two kinematic accelerations for the measurement models (not for ``nav_state``), each the
        velocity change over the chunk through a first-order low-pass of time constant
        ``ACC_SMOOTHING_TAU_S`` (gain dt / tau, at most 1):

        * ``acc_ned_mps2``: the change of the filter's velocity, updates' corrections included
          (it follows the GNSS velocity): the models' predictions over an epoch gap and the GNSS
          velocity latency's column, which shifts the receiver's velocity, a GNSS quantity;
        * ``acc_strapdown_ned_mps2``: the strapdown's own change, every update's velocity
          correction since the last chunk end taken out (``InsFilter._apply``): the columns of the
          IMU time offset (and of the GNSS latency, which must keep the same H), which shifts the
          IMU's propagated trajectory, whose derivative is exactly that (Li & Mourikis 2014). With
          the corrections in this regressor it carried the noise of the previous epochs'
          innovations, with which the next innovation is negatively correlated (its prediction
          contains the previous correction): an errors-in-variables bias (Fuller 1987 ch. 1) of the
          time offset, always positive. The GNSS velocity latency's column keeps the filter's
          velocity change: the strapdown's there made the replay outages worse (docs/calibration.md,
          Online agreement, item 4).
        """
        v_now = self.nav[3:6].copy()
        self._free_dv_mps = None if self._free_v_prev is None else v_now - self._free_v_prev - self._free_corr_mps
        self._free_v_prev, self._free_corr_mps = v_now, np.zeros(3)
        if self._v_prev_chunk is not None and t_end_s > self._t_prev_chunk:
            dt_c = float(t_end_s - self._t_prev_chunk)
            k = min(1.0, dt_c / ACC_SMOOTHING_TAU_S)
            a_c = (v_now - self._v_prev_chunk) / dt_c
            self.acc_ned_mps2 = self.acc_ned_mps2 + k * (a_c - self.acc_ned_mps2)
            a_s = (v_now - self._v_prev_chunk - self._dv_corrections_mps) / dt_c
            self.acc_strapdown_ned_mps2 = self.acc_strapdown_ned_mps2 + k * (a_s - self.acc_strapdown_ned_mps2)
        self._v_prev_chunk, self._t_prev_chunk = v_now, t_end_s
        self._dv_corrections_mps = np.zeros(3)

    def _feed_stop_calibration(self, t: np.ndarray, f: np.ndarray, w: np.ndarray,
                               speed_mps: float) -> tuple[list[StaticBiasEstimate], StaticBiasEstimate | None]:
        """The stop calibrator (``static_calibration``) with the chunk: the vehicle is moving unless
        the stop detector says static and the speed is below ``CALIBRATION_MOVING_SPEED_MPS``. The
        detector's rate test (mean rate less the gyro bias state) is left out while that state's sd
        exceeds the test's limit: it cannot then tell a bias from a turn, and a large bias must not
        keep the calibration that finds it from running. At a stop the calibrator is given the
        normal gravity at the position and, when a window needs it, the filter's attitude,
        mounting and bias states (``_stop_prior``). Returns the estimates published in this chunk
        and the one made in it."""
        bias_known = (self.initialized
                      and float(np.max(np.diag(self.P)[BG:BG + 3])) < self.cfg.stops.static_gyro_mean_max_rps ** 2)
        still = self.static if bias_known else self.stops.is_static(
            self.t_s, self.corr[COR_BG:COR_BG + 3], self.nav[3:6] if self.initialized else None, rate_test=False)
        moving = not still or (self.initialized and speed_mps > CALIBRATION_MOVING_SPEED_MPS)
        g = geo.normal_gravity_mps2(self.nav[NAV_LAT], self.nav[NAV_H]) if self.initialized and not moving else None
        made = self.calibrator.made
        ests = self.calibrator.feed(t, f, w, moving=moving, gravity_mps2=g, prior=self._stop_prior)
        self.counts["stops_not_level"] = self.calibrator.stops_not_level
        return ests, (self.calibrator.latest if self.calibrator.made != made else None)

    def _stop_prior(self) -> StopPrior:
        """What the filter knows for the stop calibrator: attitude, estimated mounting
        (``misalignment``; its prior before alignment), bias states and the covariance of their
        errors in the ``static_calibration.PRIOR_*`` blocks (zero where a state is absent)."""
        c = self.cfg
        cov = np.zeros((12, 12))
        i_m = self.layout.at("misalignment")
        if not self.initialized:
            if i_m >= 0:
                cov[PRIOR_MIS, PRIOR_MIS] = np.diag(np.broadcast_to(c.effects.effect_initial_sd["misalignment"], 3)
                                            ** 2)
            cov[PRIOR_BG, PRIOR_BG] = np.eye(3) * c.imu.gyro_bias_init_sd_rps ** 2
            cov[PRIOR_BA, PRIOR_BA] = np.eye(3) * c.imu.accel_bias_init_sd_mps2 ** 2
            return StopPrior(self.fx.misalignment_rad.copy(), self.corr[COR_BG:COR_BG + 3].copy(),
                             self.corr[COR_BA:COR_BA + 3].copy(), cov)
        idx = np.r_[ATT:ATT + 3, (np.arange(i_m, i_m + 3) if i_m >= 0 else np.full(3, -1)), BG:BG + 3, BA:BA + 3]
        have = idx >= 0
        cov[np.ix_(have, have)] = self.P[np.ix_(idx[have], idx[have])]
        return StopPrior(self.fx.misalignment_rad.copy(), self.corr[COR_BG:COR_BG + 3].copy(),
                         self.corr[COR_BA:COR_BA + 3].copy(), cov, self.C_nb.copy(),
                         geo.earth_rate_ned_rps(self.nav[NAV_LAT]), self.heading_known)

    def _feed_alignment(self, t: np.ndarray, f: np.ndarray, w: np.ndarray, est: StaticBiasEstimate | None) -> None:
        """Before alignment: the coarse aligner gets the bias-compensated chunk, and a stop's
        estimate goes straight into the compensation, whatever its level verdict: nothing else
        knows the biases yet, and the stop detector's rate test, hence the filter's static start,
        needs the gyro bias. The filter's start takes its covariance as the bias prior
        (``Initialization._start``); its publication waits for the verdict like any other."""
        self.aligner.feed(t, f - self.corr[COR_BA:COR_BA + 3], w - self.corr[COR_BG:COR_BG + 3], self.static)
        if est is not None and self.cfg.stops.apply_static_calibration:
            self.corr[COR_BG:COR_BG + 3] = est.gyro_bias_rps
            self.corr[COR_BA:COR_BA + 3] = est.accel_bias_mps2
            est.applied = True

    def _feed_consistency_motion(self, speed_mps: float) -> None:
        """Tell the consistency test (``consistency``) how far the vehicle turned since the last chunk."""
        t_end = float(self.t_s)
        if self._t_motion_s is not None and self.heading_known:
            yaw_rate = float(self.C_nb[2] @ self._last_w_b)
            self.consistency.feed_motion(t_end, t_end - self._t_motion_s, yaw_rate, speed_mps)
        self._t_motion_s = t_end
