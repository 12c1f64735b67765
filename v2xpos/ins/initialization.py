"""Starting and restarting ``InsFilter``: initialisation from a known state, alignment from the
data, and the resets of position and heading.

``Initialization`` is a base class of ``InsFilter`` holding these methods; they read and write the
filter's state (``nav``, ``C_nb``, ``P``, ``corr``, ``fx``, ``heading_known``, ...), documented in
``filter.py``. Alignment (``_try_align``): once the coarse aligner (``alignment.CoarseAligner``)
has levelled the IMU, the filter starts either at a stop with the heading left open
(ZUPT/ZARU estimate the biases meanwhile, ``_heading_reset`` turns the attitude
about down to the GNSS course when the vehicle moves) or, moving faster than
``align_min_speed_mps``, with the heading of the GNSS course. The initial covariance is diagonal:
the given position/velocity/attitude sd, the bias priors (or a stop calibration's estimate) and
the effect priors.
"""
from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from v2xpos import geo
from v2xpos.rotation import dcm_from_euler, euler_from_dcm, rot_z, skew

from .ekf import ATT, BA, BG, EFFECT_SIZES, POS, VEL, kalman_update
from .mechanization import COR_BA, COR_BG, MEM_F, MEM_VALID, MEM_W
from . import updates
from .driveoff_timing import TimeAlignment
from .updates import TIMING_STATES_POSITION, UpdateResult

if TYPE_CHECKING:
    from .config import InsConfig

STOP_GYRO_BIAS_INIT_SD_FLOOR_RPS = 1e-3
"""Least initial gyro-bias sd when the filter starts from a stop calibration's estimate."""
MIN_START_POSITION_SD_M = 0.05
"""Least initial and reset position sd [m], whatever the receiver reports."""
GNSS_RESET_DISTANCE_M = 30.0
"""A forced GNSS fix (after ``gnss.gnss_max_consecutive_rejections``) further than this from the
filter resets its position instead of updating it (beyond the linearisation's reach)."""
ALIGNMENT_LATEST_S = 1.0
"""The drive-off alignment (``driveoff_timing``) runs at the first GNSS epoch after its wait if that
epoch comes within this many seconds of it [s]; after an outage it is given up."""


def antenna_fix_inverse_jacobian(layout, C_nb: np.ndarray, lever_arm_m: np.ndarray, v_ned_mps: np.ndarray,
                                 heading_known: bool = True, timing: bool = True) -> np.ndarray:
    """G (3 x n): how the error of an IMU position taken from an antenna fix depends on the other
    error states. The fix gives ``p = p_ant - C_nb l - v gap`` (``Initialization._imu_point_at_label``);
    with errors as estimate minus truth the GNSS position model ``d = H dx + n`` (``updates.
    gnss_position``: ``H = [I, [C l x], C, -v]`` over position, attitude, lever arm and timing)
    solved for the position error gives ``dp = n + G dx_rest``, ``G = [-[C l x], -C, +v]`` (Groves
    2013 eq. 14.121 inverted). The velocity's share (``-gap dv``, a few mm) is left out. With the
    heading open (``heading_known`` False) the yaw column is 0: that error is decoupled while it
    is unknown (``InsFilter._decouple_yaw``).

    G must be minus the rest of the H that the *following* fixes are processed with, or the reset
    covariance and the updates describe two different models. The timing columns are therefore
    there only when ``timing`` is True, i.e. when the filter's GNSS models carry them at this state
    (``InsFilter._timing_in_models``: moving faster than ``timing_min_speed_mps``, not at a stop).
    Below that speed H has no timing column (the time offset is treated as not observable); a
    timing column in G then tells the filter that the IMU point holds ``v dt`` of time-offset error
    which the next fixes' model says is not in their prediction, so every innovation after the
    reset is partly read as a time offset: after a heading reset below the speed threshold (a
    walker's) the time offset left its prior while still unobservable, and later fixes were gated
    out; without the columns they were not (docs/ins.md, Initialisation, item 5)."""
    G = np.zeros((3, layout.n))
    G[:, ATT:ATT + 3] = -skew(C_nb @ lever_arm_m)
    if not heading_known:
        G[:, ATT + 2] = 0.0
    i = layout.at("lever_arm")
    if i >= 0:
        G[:, i:i + 3] = -C_nb
    for name in TIMING_STATES_POSITION if timing else ():
        i = layout.at(name)
        if i >= 0:
            G[:, i] = v_ned_mps
    return G


def position_from_antenna_covariance(P: np.ndarray, G: np.ndarray, pos_sd_m: np.ndarray) -> np.ndarray:
    """Covariance after the position rows were taken from an antenna fix with 1-sigma
    ``pos_sd_m`` (NED): the old position rows and columns are discarded, and with ``dp = n + G
    dx_rest`` (``antenna_fix_inverse_jacobian``; G has no position columns)
    ``P_pp = R + G P Gᵀ``, ``P_px = G P`` (the covariance of a linear function of independent
    Gaussians, Bierman 1977 ch. II). Then the covariance of the predicted antenna position
    ``H dx`` equals the fix's R, as it must right after the fix. Setting ``P_pp = R`` with no
    cross terms instead claims the *IMU point* known to the fix's centimetres whatever the lever
    arm and attitude; the next fixes, which measure only ``p + C l``, then "determine" the lever
    arm at once, even at a stop, far from the true offset, and the online lever-arm state never
    moves again (docs/ins.md, Initialisation, item 5). Returns a new array."""
    P = P.copy()
    P[POS:POS + 3, :] = 0.0
    P[:, POS:POS + 3] = 0.0
    GP = G @ P
    P[POS:POS + 3, :] = GP
    P[:, POS:POS + 3] = GP.T
    P[POS:POS + 3, POS:POS + 3] = np.diag(np.broadcast_to(np.asarray(pos_sd_m, float), (3,)) ** 2) + GP @ G.T
    return P


class Initialization:
    """Initialisation, alignment and resets of ``InsFilter`` (module docstring)."""

    cfg: InsConfig

    def initialize(self, t_s: float, lla: np.ndarray, v_ned_mps: np.ndarray, rpy_rad: np.ndarray,
                   pos_sd_m: float = 0.05, vel_sd_mps: float | None = None,
                   att_sd_rad: np.ndarray | None = None) -> None:
        """Start the filter from a known state of the IMU point at GPS time t_s (rpy of C_nb)."""
        i = self.cfg.initial
        self._start(t_s, np.asarray(lla, float), np.asarray(v_ned_mps, float),
                    dcm_from_euler(*np.asarray(rpy_rad, float)), pos_sd_m,
                    i.init_vel_sd_mps if vel_sd_mps is None else vel_sd_mps,
                    np.array([i.init_level_sd_rad, i.init_level_sd_rad, i.init_yaw_sd_rad])
                    if att_sd_rad is None else np.asarray(att_sd_rad, float))

    def _start(self, t_s, lla, v, C_nb, pos_sd, vel_sd, att_sd, from_antenna: bool = False,
               heading_known: bool = True) -> None:
        """Diagonal covariance (the given sds, bias and effect priors) at the given state; with
        ``from_antenna`` the position was taken from an antenna fix with sd ``pos_sd`` and its rows
        follow that fix (``position_from_antenna_covariance``)."""
        self._smoothing_boundary()
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
        d[BG:BG + 3] = c.imu.gyro_bias_init_sd_rps ** 2
        d[BA:BA + 3] = c.imu.accel_bias_init_sd_mps2 ** 2
        est = self.calibrator.latest if c.stops.apply_static_calibration else None
        if est is not None:
            self.corr[COR_BG:COR_BG + 3] = est.gyro_bias_rps
            self.corr[COR_BA:COR_BA + 3] = est.accel_bias_mps2
            d[BG:BG + 3] = np.maximum(est.gyro_sd_rps, STOP_GYRO_BIAS_INIT_SD_FLOOR_RPS) ** 2
        for name in self.layout.effects:
            i, k = self.layout.index[name], EFFECT_SIZES[name]
            d[i:i + k] = c.effects.effect_initial_sd.get(name, 0.01) ** 2
        self.P[np.diag_indices(n)] = d
        if est is not None:
            self.P[BA:BA + 3, BA:BA + 3] = est.accel_cov
        if from_antenna:
            self.P = position_from_antenna_covariance(self.P, self._antenna_fix_jacobian(heading_known), pos_sd)
        self._level_start()
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
        self.heading_known = heading_known
        self.consistency.restart(float(t_s))
        self._restart_separation()
        self._v_prev_chunk = None
        self.acc_ned_mps2 = np.zeros(3)
        self.acc_strapdown_ned_mps2 = np.zeros(3)
        self._dv_corrections_mps = np.zeros(3)
        self._free_v_prev = None
        self._free_corr_mps = np.zeros(3)

    def _level_start(self) -> None:
        """Part of a start's prior: the vehicle stands or drives level about its forward axis within
        ``initial.start_roll_sd_rad`` (``updates.vehicle_level``), applied once to the fresh
        covariance, with the misalignment state only. The roll of a mounting is observed by no
        motion, so without it the vehicle roll the filter reports keeps the misalignment prior
        (10 deg) for the whole drive, and every relative position with it through the height
        difference of the two vehicles' points. Once per start, not per epoch: the roads' cross
        slopes along a drive are correlated, not independent draws."""
        sd = self.cfg.initial.start_roll_sd_rad
        if not sd or self.layout.at("misalignment") < 0:
            return
        H, d, R = updates.vehicle_level(self.layout, self.C_nb, self.misalignment_dcm(), float(sd))
        dx, P, _, _, ok = kalman_update(self.P, H, d, R, None, consider=self.consider)
        if ok:
            self.P = P
            self._apply(dx)

    def _velocity_from_positions(self, t_s, lla, sd) -> np.ndarray | None:
        """Horizontal velocity from the constant-velocity tracker when the receiver gives none;
        None until its speed sd is below max(a third of the alignment speed, a fifth of the speed),
        i.e. the course is known to ~11 deg or better; that course sd widens the initial yaw sd."""
        out = self._course_tracker.update(float(t_s), lla, float(max(sd[0], sd[1])))
        if out is None:
            return None
        v, v_sd = out
        speed = float(np.hypot(v[0], v[1]))
        if v_sd > max(self.cfg.initial.align_min_speed_mps / 3.0, 0.2 * speed):
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
        pos_sd = np.maximum(sd * c.gnss.fix_sd_scale.get(fix, 2.0), MIN_START_POSITION_SD_M)
        if (speed < c.stops.static_max_gnss_speed_mps and self.static
                and self.aligner.levelled_static):
            # stopped and levelled: start now with the yaw left open, so that ZUPT/ZARU estimate the
            # biases during the stop; the heading is set when the platform moves (_heading_reset)
            C = self.aligner.C_nb
            self._start(self.t_s, self._imu_point_at_label(t_s, lla, np.zeros(3), C), np.zeros(3), C, pos_sd,
                        c.initial.init_vel_sd_mps,
                        np.array([c.initial.init_level_sd_rad, c.initial.init_level_sd_rad, math.pi]),
                        from_antenna=True, heading_known=False)
            if self.separation is not None:
                self.separation.stop()
            self._clear_drive_off()
            self.last_fix = fix
            self.last_gnss_t_s = t_s
            return UpdateResult("gnss_pos", t_s, False, np.nan, reason="initialised at a stop, heading pending")
        if speed < c.initial.align_min_speed_mps:
            return UpdateResult("gnss_pos", t_s, False, np.nan, reason="aligning: too slow for heading")
        C = self.aligner.attitude_with_heading(float(np.arctan2(vel[1], vel[0])))
        if C is None:
            return UpdateResult("gnss_pos", t_s, False, np.nan, reason="aligning: not levelled yet")
        self._start(self.t_s, self._imu_point_at_label(t_s, lla, vel, C), vel, C, pos_sd, c.initial.init_vel_sd_mps,
                    np.array([c.initial.init_level_sd_rad, c.initial.init_level_sd_rad,
                              max(c.initial.init_yaw_sd_rad, self._course_sd_rad)]),
                    from_antenna=True)
        self.last_fix = fix
        self.last_gnss_t_s = t_s
        return UpdateResult("gnss_pos", t_s, False, np.nan, reason="initialised from this epoch")

    def _position_reset(self, t_s, lla, sd, fix, vel, err_m: float) -> UpdateResult:
        """The filter has drifted beyond linear reach (consecutive rejections and an innovation over
        ``GNSS_RESET_DISTANCE_M``): take position (and velocity when given) from GNSS and reset
        their covariance; attitude, biases and effects are kept."""
        self._smoothing_boundary()
        c = self.cfg
        v = self.nav[3:6].copy() if vel is None else np.asarray(vel, float)
        self.nav[:3] = self._imu_point_at_label(t_s, lla, v, self.C_nb)
        self.nav[3:6] = v
        self._v_prev_chunk = None
        idx = np.r_[POS:POS + 3, VEL:VEL + 3]
        self.P[idx, :] = 0.0
        self.P[:, idx] = 0.0
        pos_sd = np.maximum(sd * c.gnss.fix_sd_scale.get(fix, 2.0), MIN_START_POSITION_SD_M)
        vel_sd = c.initial.init_vel_sd_mps if vel is not None else max(c.initial.init_vel_sd_mps, 0.1 * err_m)
        self.P[idx, idx] = np.r_[pos_sd ** 2, np.full(3, vel_sd ** 2)]
        G = self._antenna_fix_jacobian(self.heading_known)
        self.P = position_from_antenna_covariance(self.P, G, pos_sd)
        if self.separation is not None:
            self.separation.reset_states(idx, self.P)
            if self.separation.P is not None:
                self.separation.P = position_from_antenna_covariance(self.separation.P, G, pos_sd)
        self._gnss_rejections = 0
        self.counts["position_resets"] += 1
        self.last_fix = fix
        self.last_gnss_t_s = t_s
        return UpdateResult("gnss_pos", t_s, False, np.nan,
                            reason=f"position reset: the filter was {err_m:.1f} m off after rejections")

    def _antenna_fix_jacobian(self, heading_known: bool) -> np.ndarray:
        """``antenna_fix_inverse_jacobian`` at the current attitude, lever arm and velocity, its
        timing columns as the GNSS models carry them now (``InsFilter._timing_in_models``)."""
        v = self.nav[3:6]
        return antenna_fix_inverse_jacobian(self.layout, self.C_nb, self.fx.lever_arm_m, v, heading_known,
                                            self._timing_in_models(v))

    def _turn_about_down(self, turn: np.ndarray) -> None:
        """Turn the attitude about down by the rotation ``turn`` (NED, ``C_nb <- turn C_nb``) when
        the pending heading is set, and the attitude error's rows and columns of P with it.

        With errors as ``C_est = (I - [phi x]) C_true`` (``InsFilter._apply``), an estimate whose
        heading is off by the open yaw ``-a`` and whose tilt is off by ``phi`` is
        ``C_est = (I - [phi x]) R_z(-a) C_true``; the turn ``R_z(a)`` gives
        ``R_z(a) C_est = (I - [(R_z(a) phi) x]) C_true``: the tilt error is the same tilt of the
        body, expressed in NED axes turned with it (Groves 2013 sec. 2.3.3 for the small-angle
        form). So the tilt error and every covariance the stop taught it -- above all the
        accelerometer bias, which the levelling ties to it through ``g x phi = -C b`` with the
        estimated C -- are transformed as ``phi' = R_z(a) phi`` (P <- T P T^T, T the identity with
        ``turn`` in the attitude block); the yaw row is set afterwards. Without it the tilt's
        correlations stayed in the axes of the arbitrary pre-turn yaw (up to 180 deg away), and
        the fault-tolerant solution missed an undeclared antenna lever arm: the rows the filter
        reported VALID after its exclusion were often outside 3 sd (tests/test_integrity_recordings.py
        ``[lever]``; docs/ins.md, Initialisation, item 4). The models' two kinematic accelerations
        (``imu_path._smooth_acceleration``) are NED vectors of the pre-turn heading as well and
        turn with it: left as they were, the first GNSS velocities after a drive-off's heading
        reset were regressed on an acceleration pointing up to 180 deg away from the true one."""
        self.C_nb = turn @ self.C_nb
        T = np.eye(self.layout.n)
        T[ATT:ATT + 3, ATT:ATT + 3] = turn
        self.P = T @ self.P @ T.T
        self.acc_ned_mps2 = turn @ self.acc_ned_mps2
        self.acc_strapdown_ned_mps2 = turn @ self.acc_strapdown_ned_mps2
        if self._free_v_prev is not None:
            self._free_v_prev = turn @ self._free_v_prev
        self._free_corr_mps = turn @ self._free_corr_mps
        if self.driveoff is not None:
            self.driveoff.turn(turn)

    def _heading_from_baseline(self, t_s: float, heading_rad: float, sd_rad: float,
                               baseline_vehicle_m: np.ndarray) -> UpdateResult:
        """Pending heading set from a dual-antenna baseline azimuth: turn the attitude about down
        by the azimuth difference (a turn about down changes every NED azimuth by the same angle),
        move the IMU point so the antenna stays where it was (``p_ant = p + C l``), then apply the
        azimuth as an ungated measurement at the turned state (residual 0, so only the covariance
        changes): the yaw error, open while pending (``InsFilter._decouple_yaw``), takes the
        measurement's variance together with its correlation to the misalignment states, since the
        baseline fixes the vehicle's heading, not the IMU's. Level, biases and velocity keep what
        the stop taught."""
        self._smoothing_boundary()
        R_vb = self.misalignment_dcm()
        u = self.C_nb @ R_vb.T @ baseline_vehicle_m
        turn_rad = math.remainder(heading_rad - math.atan2(u[1], u[0]), 2.0 * math.pi)
        C_before = self.C_nb
        self._turn_about_down(rot_z(turn_rad))
        self.nav[:3] = geo.ned_to_lla((C_before - self.C_nb) @ self.fx.lever_arm_m, self.nav[:3])
        self.heading_known = True
        m = updates.dual_antenna_heading(self.layout, self.C_nb, R_vb, baseline_vehicle_m, heading_rad, sd_rad)
        res = self._update("heading", t_s, *m, gate=False)
        self.consistency.restart(float(t_s))
        self._restart_separation()
        res.reason = f"heading set from the dual-antenna baseline (turned {math.degrees(turn_rad):.1f} deg)"
        return res

    def _note_drive_off(self, t_s: float, lla: np.ndarray, sd_ned_m: np.ndarray, vel) -> None:
        """Feed a GNSS epoch of the open-heading phase to the drive-off time alignment
        (``driveoff_timing``)."""
        d = self.driveoff
        if d is None or vel is None:
            return
        if self._driveoff_origin is None:
            self._driveoff_origin = np.asarray(lla, float).copy()
        d.note_gnss(t_s, self._driveoff_ne(lla), float(np.hypot(sd_ned_m[0], sd_ned_m[1]) / math.sqrt(2.0)),
                    float(np.hypot(vel[0], vel[1])))

    def _driveoff_ne(self, lla: np.ndarray) -> np.ndarray:
        """North/east metres of ``lla`` from the alignment's origin (curvilinear, Groves 2013 eq. 2.119)."""
        o = self._driveoff_origin
        r_m, r_n = geo.radii_m(o[0])
        return np.array([(lla[0] - o[0]) * (r_m + o[2]), (lla[1] - o[1]) * (r_n + o[2]) * math.cos(o[0])])

    def _note_drive_off_ins(self) -> None:
        """The free strapdown's velocity change over the chunk (``driveoff_timing``)."""
        if self.driveoff is not None and self.t_stamp_s is not None and self._free_dv_mps is not None:
            self.driveoff.note_ins(self.t_stamp_s, self._free_dv_mps[:2], (self.C_nb @ self.fx.lever_arm_m)[:2])

    def _clear_drive_off(self) -> None:
        if self.driveoff is not None:
            self.driveoff.clear()
        self._driveoff_origin = None
        self._align_pending_until_s = None

    def _timing_as_noise(self, m: updates.Measurement, rate_ned: np.ndarray) -> updates.Measurement:
        """While the drive-off alignment is pending the GNSS models carry no timing columns
        (``InsFilter._timing_in_models``); the time offset's effect, ``-rate dt`` with ``rate`` the
        velocity (position rows) or the acceleration (velocity rows), enters R as its variance
        ``rate rate^T sd_dt^2`` instead (the time offset as an unestimated error, Schmidt 1966 in its
        simplest form: the cross-covariances left out), so that the first second of a drive-off
        neither teaches the offset through a linearisation that does not hold there nor is read as
        errors of the other states."""
        if self._align_pending_until_s is None:
            return m
        i = self.layout.at("imu_time_offset")
        r = np.asarray(rate_ned, float)
        return m._replace(R=m.R + float(self.P[i, i]) * np.outer(r, r))

    def _finish_drive_off_alignment(self, t_s, lla, sd, fix, vel) -> UpdateResult | None:
        """The first GNSS epoch after the alignment's wait: align the drive-off (``driveoff_timing``),
        set the IMU time offset and its sd (no correlations: the models carried no timing columns
        since the heading reset), and take the heading, position and velocity again from this epoch
        at the filter's new label (``_heading_reset``). Without an epoch soon after the wait (an
        outage) or without an answer, the timing columns come back and the filter goes on."""
        d = self.driveoff
        due = self._align_pending_until_s
        i = self.layout.at("imu_time_offset")
        res = None
        if t_s - due <= ALIGNMENT_LATEST_S and vel is not None:
            bias_sd = float(np.sqrt(np.mean(np.diag(self.P)[BA:BA + 2])))
            res = d.align(self.fx.imu_time_offset_s, math.sqrt(float(self.P[i, i])), bias_sd)
        self._clear_drive_off()
        if res is None:
            return None
        return self._heading_reset(t_s, lla, sd, fix, vel, alignment=res)

    def _heading_reset(self, t_s, lla, sd, fix, vel, alignment: TimeAlignment | None = None) -> UpdateResult:
        """First epoch fast enough for a course: turn the attitude about down so that the body x axis
        points along the course, take position and velocity from GNSS, and reset their covariance
        (biases and level keep what the stop taught them). With a drive-off ``alignment``
        (``_finish_drive_off_alignment``) the IMU time offset and its sd are set first, without
        correlations, and the filter's label moves with them."""
        self._smoothing_boundary()
        c = self.cfg
        if alignment is not None:
            i = self.layout.at("imu_time_offset")
            self.time_alignment = alignment
            self.fx.imu_time_offset_s = alignment.offset_s
            self.P[i, :] = 0.0
            self.P[:, i] = 0.0
            self.P[i, i] = alignment.sd_s ** 2
        d = self.driveoff
        if (d is not None and not self.heading_known and d.starts_at_rest()
                and self._align_pending_until_s is None):
            i = self.layout.at("imu_time_offset")
            self._align_pending_until_s = float(t_s) + d.needed_wait_s(math.sqrt(float(self.P[i, i])))
        yaw_now = float(euler_from_dcm(self.C_nb)[2])
        turn = rot_z(float(np.arctan2(vel[1], vel[0])) - yaw_now)
        self._turn_about_down(turn)
        self._free_corr_mps = self._free_corr_mps + (vel - turn @ self.nav[3:6])
        self.nav[:3] = self._imu_point_at_label(t_s, lla, vel, self.C_nb)
        self.nav[3:6] = vel
        self._v_prev_chunk = None
        idx = np.r_[POS:POS + 3, VEL:VEL + 3, ATT + 2]
        self.P[idx, :] = 0.0
        self.P[:, idx] = 0.0
        pos_sd = np.maximum(sd * c.gnss.fix_sd_scale.get(fix, 2.0), MIN_START_POSITION_SD_M)
        self.P[idx, idx] = np.r_[pos_sd ** 2, np.full(3, c.initial.init_vel_sd_mps ** 2),
                                 max(c.initial.init_yaw_sd_rad, self._course_sd_rad) ** 2]
        self.P = position_from_antenna_covariance(self.P, self._antenna_fix_jacobian(True), pos_sd)
        self.heading_known = True
        self.consistency.restart(float(t_s))
        self._restart_separation()
        self.last_fix = fix
        self.last_gnss_t_s = t_s
        return UpdateResult("gnss_pos", t_s, False, np.nan, reason="heading set from the GNSS course")
