"""Measurement models of the error-state filter: pure builders of (H, d, R).

Conventions: errors are estimate minus truth (``ekf.py``); every builder returns a
``Measurement(H, d, R)`` with the prediction-minus-measurement ``d = h(x_est) - z``, so that
``d ~ H dx + noise`` with noise covariance R; ``ekf.kalman_update`` turns it into a correction.
Reported innovations are ``z - h(x_est)`` (measurement minus prediction). The builders read only
their arguments; which model runs when, and with which state, is ``InsFilter``'s business.

Symbols: C = C_nb estimate (body -> NED), l = lever arm in body, w = compensated body rate,
v = NED velocity, a = kinematic acceleration NED, R_m = misalignment DCM vehicle <- body,
v_b = C^T v.

* GNSS position at the antenna (Groves 2013 eq. 14.121 with our signs), with
  gap = t_meas - latency - (t_stamp + dt) from the state label to the epoch the fix describes:
  h = r + C l + v_IMU * gap;  H_r = I, H_phi = [(C l) x], H_l = C, H_dt = H_lat = -v
  (both shorten the gap).
* GNSS velocity at the antenna: h = v + C (w x l) + a (gap - vel_latency);  H_v = I,
  H_phi = [(C (w x l)) x], H_bg = C [l x], H_l = C [w x], H_dt = H_lat = -a_strapdown,
  H_vel_lat = -a (``InsFilter._smooth_acceleration``: which acceleration for which state).
* Non-holonomic constraint (Shin 2001 sec. 4.3; Dissanayake et al. 2001): the vehicle-frame lateral
  and vertical velocity are zero: h = (R_m C^T v)_{y,z};
  H_v = R_m C^T, H_phi = -R_m C^T [v x], H_mis = -[v_b x].
* Odometer (wheel speed = (1 + s_odo) x forward speed, Shin 2001 sec. 4.3): h = (1 + s_odo)
  ((R_m C^T v)_x + a_fwd gap); H as the NHC rows (x component) times (1 + s_odo),
  H_s = (R_m C^T v)_x.
* Dual-antenna heading (a moving-base receiver's baseline azimuth, u-blox NAV-RELPOSNED): with
  u = C R_vb^T b the baseline in NED (b in vehicle axes), h = atan2(u_E, u_N); the baseline turns
  with the attitude error as the lever arm does, du = [u x] phi, so H_phi = g^T [u x] with
  g = (-u_E, u_N, 0) / (u_N^2 + u_E^2) (level: H_phi = (0, 0, -1)); H_mis = g^T C R_vb^T [b x].
* Level start (``vehicle_level``): the vehicle's roll at the start is that of the road it stands
  or drives on, zero within the road's cross slope. With u = C R_vb^T e_y the vehicle's y axis in
  NED, h = u_D = cos(pitch) sin(roll), z = 0; as above du = [u x] phi and H_mis = e_D^T C R_vb^T [e_y x],
  so H_phi = (-u_E, u_N, 0): only the tilt, never the (possibly open) heading.
* ZUPT: h = v, H_v = I. ZARU: h = w - C^T w_ie, H_bg = -I (Groves 2013 sec. 15.3).
* Stop calibration (``static_calibration``): the gyro bias measured directly, h = b_g, H_bg = I.

The timing columns (H_dt, H_lat, H_vel_lat) are zero when the caller says the platform is too
slow for timing to be observable (``InsConfig.gnss.timing_min_speed_mps``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from v2xpos import geo
from v2xpos.rotation import skew

from .ekf import ATT, BA, BG, POS, VEL, StateLayout
from .mechanization import NAV_H, NAV_LAT, NAV_LON

TIMING_STATES_POSITION = ("imu_time_offset", "gnss_latency")
"""Effect states that shift the epoch a GNSS position describes (H = -v)."""
TIMING_STATES_VELOCITY = ("imu_time_offset", "gnss_latency", "gnss_vel_latency")
"""Effect states that shift the epoch a GNSS velocity describes (H = -a)."""


@dataclass
class UpdateResult:
    """Outcome of one measurement update.

    innovation: z - h(x) in the measurement's units and axes; innovation_sd: sqrt(diag(S));
    nis: normalised innovation squared; accepted: False when the chi-square gate rejected it.
    """
    kind: str
    t_s: float
    accepted: bool
    nis: float
    innovation: np.ndarray = field(default_factory=lambda: np.zeros(0))
    innovation_sd: np.ndarray = field(default_factory=lambda: np.zeros(0))
    reason: str = ""
    innovation_cov: np.ndarray | None = None   # S = H P H^T + R


class Measurement(NamedTuple):
    """A linearised measurement: d = h(x_est) - z ~ H dx + noise, noise covariance R."""
    H: np.ndarray
    d: np.ndarray
    R: np.ndarray


def gnss_position(layout: StateLayout, nav: np.ndarray, C_nb: np.ndarray, lever_arm_m: np.ndarray,
                  v_ned_mps: np.ndarray, gap_s: float, lla_meas: np.ndarray, sd_ned_m: np.ndarray,
                  sd_floor_m: float, timing: bool) -> Measurement:
    """Antenna position fix ``lla_meas`` (lat, lon rad; h m) with 1-sigma ``sd_ned_m`` (floored at
    ``sd_floor_m``) against the IMU point ``nav[:3]``; the difference is taken in NED metres at
    the state (curvilinear increments, Groves 2013 eq. 2.119)."""
    lat, h = nav[NAV_LAT], nav[NAV_H]
    r_m, r_n = geo.radii_m(lat)
    Cl = C_nb @ lever_arm_m
    pred_ned = Cl + v_ned_mps * gap_s
    meas_ned = np.array([(lla_meas[0] - lat) * (r_m + h), (lla_meas[1] - nav[NAV_LON]) * (r_n + h) * math.cos(lat),
                         -(lla_meas[2] - h)])
    d = pred_ned - meas_ned
    H = np.zeros((3, layout.n))
    H[:, POS:POS + 3] = np.eye(3)
    H[:, ATT:ATT + 3] = skew(Cl)
    i = layout.at("lever_arm")
    if i >= 0:
        H[:, i:i + 3] = C_nb
    timing_col = -v_ned_mps if timing else np.zeros(3)
    for name in TIMING_STATES_POSITION:
        i = layout.at(name)
        if i >= 0:
            H[:, i] = timing_col
    R = np.diag(np.maximum(sd_ned_m, sd_floor_m) ** 2)
    return Measurement(H, d, R)


def gnss_velocity(layout: StateLayout, C_nb: np.ndarray, lever_arm_m: np.ndarray, rate_body_rps: np.ndarray,
                  v_ned_mps: np.ndarray, acc_ned_mps2: np.ndarray, gap_s: float, vel_latency_s: float,
                  vel_meas_ned_mps: np.ndarray, sd_ned_mps: np.ndarray, sd_floor_mps: float,
                  timing: bool, acc_strapdown_ned_mps2: np.ndarray | None = None) -> Measurement:
    """Antenna velocity ``vel_meas_ned_mps`` with 1-sigma ``sd_ned_mps`` (floored): the IMU
    velocity plus the lever arm's rotation C (w x l), moved over the epoch gap and the velocity's
    own latency with the acceleration. ``acc_strapdown_ned_mps2`` (when given) is the regressor
    of the IMU time offset and GNSS latency columns (``InsFilter._smooth_acceleration``)."""
    Cwl = C_nb @ np.cross(rate_body_rps, lever_arm_m)
    d = v_ned_mps + Cwl + acc_ned_mps2 * (gap_s - vel_latency_s) - vel_meas_ned_mps
    H = np.zeros((3, layout.n))
    H[:, VEL:VEL + 3] = np.eye(3)
    H[:, ATT:ATT + 3] = skew(Cwl)
    H[:, BG:BG + 3] = C_nb @ skew(lever_arm_m)
    i = layout.at("lever_arm")
    if i >= 0:
        H[:, i:i + 3] = C_nb @ skew(rate_body_rps)
    for name in TIMING_STATES_VELOCITY:
        i = layout.at(name)
        if i >= 0 and timing:
            clock_state = name in TIMING_STATES_POSITION and acc_strapdown_ned_mps2 is not None
            H[:, i] = -(acc_strapdown_ned_mps2 if clock_state else acc_ned_mps2)
    R = np.diag(np.maximum(sd_ned_mps, sd_floor_mps) ** 2)
    return Measurement(H, d, R)


def vehicle_frame_rows(C_nb: np.ndarray, R_vb: np.ndarray, v_ned_mps: np.ndarray) -> tuple:
    """(v_v, H_v, H_phi, H_mis): the velocity in vehicle axes v_v = R_vb C^T v and its three
    Jacobian blocks (rows x, y, z), shared by the NHC and the odometer."""
    RCt = R_vb @ C_nb.T
    v_b = C_nb.T @ v_ned_mps
    return RCt @ v_ned_mps, RCt, -RCt @ skew(v_ned_mps), -skew(v_b)


NHC_SD_MPS = (0.05, 0.5)
"""1-sigma of the NHC's zero lateral and vertical velocity [m/s]: the vertical one loose because the
body pitches against the road under braking and load (docs/ins.md, Measurements)."""
NHC_SD_PER_YAW_RATE_M = 1.0
"""Added to the lateral sd per rad/s of yaw rate [m]: an IMU metres from the rear axle slips sideways
in turns."""
NHC_SD_UNMODELLED_PER_YAW_RATE_M = 0.2
"""Added to the lateral sd per rad/s of yaw rate [m] when the rear-axle distance is a state: what the
kinematic model leaves out (the tyres' nonlinearity, roll steer, the road's camber)."""
REAR_AXLE_LEARN_MAX_GNSS_AGE_S = 1.0
"""The rear-axle states enter the NHC only while a GNSS update is at most this old: in an outage the
NHC alone would move them to absorb the heading's drift (on drive_0708's replay the compliance
turned negative in the first 15-s outage and the twin then excluded a right declaration)."""
NHC_MIN_SPEED_MPS = 0.5
"""The NHC is applied above this speed (below it the vehicle frame's velocity direction is noise)."""
ODOMETER_SD_MPS = 0.05
"""1-sigma of a wheel-speed measurement [m/s] (quantisation and tyre slip of an ABS wheel speed)."""
ZUPT_SD_MPS = 0.02
"""1-sigma of the zero velocity at a stop [m/s] (engine vibration of a parked car)."""
ZARU_SD_RPS = 2e-3
"""1-sigma of the zero angular rate at a stop [rad/s] (engine vibration, occupants)."""


def nhc(layout: StateLayout, C_nb: np.ndarray, R_vb: np.ndarray, v_ned_mps: np.ndarray, yaw_rate_rps: float,
        sd_mps: tuple = NHC_SD_MPS, sd_per_yaw_rate_m: float = NHC_SD_PER_YAW_RATE_M,
        rear_axle_distance_m: float = 0.0, rear_slip_compliance: float = 0.0,
        learn_rear_axle: bool = True) -> Measurement:
    """The vehicle's lateral and vertical velocity at the IMU (vehicle frame: y right, z down).

    Without the ``rear_axle_distance`` state both are zero and the lateral sd grows by
    ``sd_per_yaw_rate_m`` x |yaw rate| (an IMU ahead of the rear axle moves sideways in turns).
    With it, the lateral velocity is the kinematic one of a point ``d`` ahead of a rear axle that
    slips at the angle ``k a_y`` (``k``: ``rear_slip_compliance`` [rad per m/s^2], when estimated;
    a_y = v omega the lateral acceleration):

        v_y = omega (d - k v^2),  H_d = -omega,  H_k = omega v^2

    (Gillespie 1992, *Fundamentals of Vehicle Dynamics*, ch. 6: the rear axle's velocity points
    along the car up to the rear tyres' slip angle, which is proportional to their lateral force),
    and what remains unmodelled is ``NHC_SD_UNMODELLED_PER_YAW_RATE_M`` x |yaw rate|. With
    ``learn_rear_axle`` False (no recent GNSS) the constraint is the one without the states: in an
    outage the NHC is the only lateral reference, and the model's estimates used there (as an
    offset, or with their covariance and the tight sd) made drive_0708's and convoy_dev B's
    outages worse than the loose zero (docs/ins.md, Measurements).

    yaw_rate_rps: the vehicle's yaw rate (vehicle z axis, down: positive turning right)."""
    v_v, Hv, Hphi, Hmis = vehicle_frame_rows(C_nb, R_vb, v_ned_mps)
    H = np.zeros((2, layout.n))
    H[:, VEL:VEL + 3] = Hv[1:]
    H[:, ATT:ATT + 3] = Hphi[1:]
    i = layout.at("misalignment")
    if i >= 0:
        H[:, i:i + 3] = Hmis[1:]
    d = v_v[1:].copy()
    i = layout.at("rear_axle_distance")
    if i >= 0 and learn_rear_axle:
        v2 = float(v_v[0] * v_v[0])
        d[0] -= yaw_rate_rps * (rear_axle_distance_m - rear_slip_compliance * v2)
        H[0, i] = -yaw_rate_rps
        k = layout.at("rear_slip_compliance")
        if k >= 0:
            H[0, k] = yaw_rate_rps * v2
        sd_per_yaw_rate_m = NHC_SD_UNMODELLED_PER_YAW_RATE_M
    R = np.diag([(sd_mps[0] + sd_per_yaw_rate_m * abs(yaw_rate_rps)) ** 2, sd_mps[1] ** 2])
    return Measurement(H, d, R)


def odometer(layout: StateLayout, C_nb: np.ndarray, R_vb: np.ndarray, v_ned_mps: np.ndarray,
             acc_ned_mps2: np.ndarray, odometer_scale: float, gap_s: float, speed_mps: float,
             sd_mps: float = ODOMETER_SD_MPS) -> Measurement:
    """Wheel speed ``speed_mps`` measured ``gap_s`` after the state label: the vehicle's forward
    velocity moved over the gap with the forward acceleration, times (1 + scale)."""
    v_v, Hv, Hphi, Hmis = vehicle_frame_rows(C_nb, R_vb, v_ned_mps)
    s = odometer_scale
    H = np.zeros((1, layout.n))
    H[0, VEL:VEL + 3] = (1 + s) * Hv[0]
    H[0, ATT:ATT + 3] = (1 + s) * Hphi[0]
    i = layout.at("misalignment")
    if i >= 0:
        H[0, i:i + 3] = (1 + s) * Hmis[0]
    i = layout.at("odometer_scale")
    if i >= 0:
        H[0, i] = v_v[0]
    a_fwd = (R_vb @ C_nb.T @ acc_ned_mps2)[0]
    d = np.array([(1 + s) * (v_v[0] + a_fwd * gap_s) - speed_mps])
    return Measurement(H, d, np.array([[sd_mps ** 2]]))


def zupt(layout: StateLayout, v_ned_mps: np.ndarray, sd_mps: float = ZUPT_SD_MPS) -> Measurement:
    """Zero velocity at a stop."""
    H = np.zeros((3, layout.n))
    H[:, VEL:VEL + 3] = np.eye(3)
    return Measurement(H, v_ned_mps.copy(), np.eye(3) * sd_mps ** 2)


def _vehicle_vector_row(layout: StateLayout, CRt: np.ndarray, b_vehicle: np.ndarray, u: np.ndarray,
                        g: np.ndarray) -> np.ndarray:
    """H (1 x n) of a scalar ``h(u)`` of a vector fixed to the vehicle, ``u = C R_vb^T b`` in NED
    (``CRt`` = C R_vb^T), whose gradient in u is ``g``: ``du = [u x] phi + C R_vb^T [b x] dm`` (the
    attitude error turns u as it turns the lever arm; with R_vb,est = (I + [dm x]) R_vb,true, the NHC
    rows' convention), so H_phi = g^T [u x] and H_mis = g^T C R_vb^T [b x]."""
    H = np.zeros((1, layout.n))
    H[0, ATT:ATT + 3] = g @ skew(u)
    i = layout.at("misalignment")
    if i >= 0:
        H[0, i:i + 3] = g @ CRt @ skew(b_vehicle)
    return H


def dual_antenna_heading(layout: StateLayout, C_nb: np.ndarray, R_vb: np.ndarray, baseline_vehicle_m: np.ndarray,
                         heading_rad: float, sd_rad: float) -> Measurement:
    """A moving-base receiver's baseline azimuth (clockwise from north) as a measurement of the
    vehicle's attitude: model in the module docstring; ``d`` is wrapped to (-pi, pi]. The baseline
    is fixed to the vehicle (declared in vehicle axes like the lever arm), so the body's
    misalignment R_vb enters too: u = C R_vb^T b, and with R_vb,est = (I + [dm x]) R_vb,true (the
    NHC rows' convention) H_mis = g^T C R_vb^T [b x]. The baseline's horizontal length must be
    nonzero (checked by the caller's configuration)."""
    b = np.asarray(baseline_vehicle_m, float)
    CRt = C_nb @ R_vb.T
    u = CRt @ b
    h2 = u[0] * u[0] + u[1] * u[1]
    H = _vehicle_vector_row(layout, CRt, b, u, np.array([-u[1], u[0], 0.0]) / h2)
    d = math.remainder(math.atan2(u[1], u[0]) - heading_rad, 2.0 * math.pi)
    return Measurement(H, np.array([d]), np.array([[sd_rad ** 2]]))


def vehicle_level(layout: StateLayout, C_nb: np.ndarray, R_vb: np.ndarray, sd_rad: float) -> Measurement:
    """The vehicle is level about its forward axis within ``sd_rad`` (its roll is the road's
    cross slope): a measurement of the roll of the vehicle frame, ``h = (C R_vb^T e_y)_D = cos(pitch)
    sin(roll)``, ``z = 0``, ``R = sin(sd)^2`` (model in the module docstring). The IMU's own tilt
    is measured by gravity; the mounting's roll about the forward axis is not observed by any
    motion (a rotation about the direction of travel changes neither the lateral nor the vertical
    velocity the constraints see), so this is where the filter learns it."""
    CRt = C_nb @ R_vb.T
    u = CRt[:, 1]
    H = _vehicle_vector_row(layout, CRt, np.array([0.0, 1.0, 0.0]), u, np.array([0.0, 0.0, 1.0]))
    return Measurement(H, np.array([u[2]]), np.array([[math.sin(sd_rad) ** 2]]))


def zaru(layout: StateLayout, C_nb: np.ndarray, lat_rad: float, mean_rate_body_rps: np.ndarray,
         gyro_bias_rps: np.ndarray, sd_rps: float = ZARU_SD_RPS) -> Measurement:
    """Zero angular rate at a stop: the mean raw rate over the stop window, less the bias estimate
    and the Earth rate in body axes, is the bias error."""
    w_ie_b = C_nb.T @ geo.earth_rate_ned_rps(lat_rad)
    d = mean_rate_body_rps - gyro_bias_rps - w_ie_b
    H = np.zeros((3, layout.n))
    H[:, BG:BG + 3] = -np.eye(3)
    return Measurement(H, d, np.eye(3) * sd_rps ** 2)


def stop_gyro_bias(layout: StateLayout, gyro_bias_rps: np.ndarray, est_gyro_bias_rps: np.ndarray,
                   est_gyro_cov: np.ndarray) -> Measurement:
    """A stop calibration's gyro-bias estimate (``static_calibration.StaticBiasEstimate``: the
    window's mean rate less the Earth rate, R its covariance) as a direct measurement of the gyro
    bias states."""
    H = np.zeros((3, layout.n))
    H[:, BG:BG + 3] = np.eye(3)
    return Measurement(H, np.asarray(gyro_bias_rps, float) - est_gyro_bias_rps, np.asarray(est_gyro_cov, float))
