"""Model effects as one parameter set: inject them into a recording, or correct a recording for them.

Conventions (the JSON of ``v2xpos calibrate`` uses the same names and signs; docs/calibration.md):

* IMU time: ``t_gps = t_stamp + imu_time_offset_s + 1e-6 * imu_clock_drift_ppm * (t_stamp - t0_s)``
  with ``t0_s`` the first IMU stamp of the recording.
* GNSS latency: a solution tagged ``t_tag`` is valid at ``t_tag - gnss_latency_s`` (it is reported
  late by the latency).
* Mounting: ``v_vehicle = R imu_to_body v_imu`` with ``R = Rz(yaw) Ry(pitch) Rx(roll)`` from
  ``imu_misalignment_rad`` = (roll, pitch, yaw); ``imu_to_body`` is the declared nominal DCM.
* Lever arm: antenna relative to the IMU in the vehicle frame [forward, right, down] in metres,
  added to the declared one.
* Scale: in the nominal vehicle axes ``imu_to_body @ measured = (1 + s) * (R^T true_vehicle)``,
  per axis, for gyro and accelerometer.

``inject`` writes additional, undeclared effects into the data (what a test does to a real
recording; ``inject_imu_bias`` a constant sensor bias); ``correct`` removes estimated effects (stamps, samples and GNSS tags) and declares
the rest (``imu_to_body``, ``lever_arm_m``) so that the replay runs on a calibrated model.
Both return a new ``Dataset``; the input is never modified.
"""
from __future__ import annotations

import copy
from dataclasses import dataclass, field, fields

import numpy as np

from v2xpos import geo
from v2xpos.rotation import dcm_from_euler, dcm_from_euler_batch
from v2xpos.types import Dataset, GnssData

# parameter vector layout shared by identify.py, estimator.py and calibrate.py
P_TIME_OFFSET = 0
P_CLOCK_DRIFT = 1
P_GNSS_LATENCY = 2
P_MISALIGN = slice(3, 6)
P_LEVER_ARM = slice(6, 9)
P_GYRO_SCALE = slice(9, 12)
P_ACCEL_SCALE = slice(12, 15)
N_PARAMS = 15

PARAM_NAMES = ("imu_time_offset_s", "imu_clock_drift_ppm", "gnss_latency_s",
               "misalign_roll_rad", "misalign_pitch_rad", "misalign_yaw_rad",
               "lever_arm_x_m", "lever_arm_y_m", "lever_arm_z_m",
               "gyro_scale_x", "gyro_scale_y", "gyro_scale_z",
               "accel_scale_x", "accel_scale_y", "accel_scale_z")


@dataclass
class EffectSet:
    """Values of every effect (zero = absent). Units in the names; angles in radians."""
    imu_time_offset_s: float = 0.0
    imu_clock_drift_ppm: float = 0.0
    gnss_latency_s: float = 0.0
    imu_misalignment_rad: np.ndarray = field(default_factory=lambda: np.zeros(3))
    gnss_lever_arm_m: np.ndarray = field(default_factory=lambda: np.zeros(3))
    gyro_scale: np.ndarray = field(default_factory=lambda: np.zeros(3))
    accel_scale: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def to_vector(self) -> np.ndarray:
        """Parameter vector in the P_* layout."""
        v = np.zeros(N_PARAMS)
        v[P_TIME_OFFSET] = self.imu_time_offset_s
        v[P_CLOCK_DRIFT] = self.imu_clock_drift_ppm
        v[P_GNSS_LATENCY] = self.gnss_latency_s
        v[P_MISALIGN] = self.imu_misalignment_rad
        v[P_LEVER_ARM] = self.gnss_lever_arm_m
        v[P_GYRO_SCALE] = self.gyro_scale
        v[P_ACCEL_SCALE] = self.accel_scale
        return v

    @classmethod
    def from_vector(cls, v: np.ndarray) -> "EffectSet":
        v = np.asarray(v, float)
        return cls(float(v[P_TIME_OFFSET]), float(v[P_CLOCK_DRIFT]), float(v[P_GNSS_LATENCY]),
                   v[P_MISALIGN].copy(), v[P_LEVER_ARM].copy(), v[P_GYRO_SCALE].copy(),
                   v[P_ACCEL_SCALE].copy())

    def is_zero(self) -> bool:
        return not np.any(self.to_vector())

    def __repr__(self) -> str:
        parts = []
        for f in fields(self):
            val = np.atleast_1d(getattr(self, f.name))
            if np.any(val):
                parts.append(f"{f.name}={np.array2string(val, precision=5)}")
        return "EffectSet(" + ", ".join(parts) + ")"


def vehicle_attitude_from_gnss(gnss: GnssData, min_speed_mps: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Approximate vehicle attitude at the GNSS epochs from the GNSS velocity (no side-slip).

    Yaw = course over ground, pitch = path inclination atan2(-v_d, v_h), roll = 0; below
    ``min_speed_mps`` the last valid attitude is held (the first valid one is used before it).
    Returns (C_nv (N,3,3) vehicle->NED, w_nv_v_rps (N,3) yaw rate on the vehicle z axis).
    Accurate to a few degrees, enough to move an antenna by decimetres (error ~ l * angle).
    """
    n = len(gnss)
    if gnss.vel_ned_mps is not None:
        v = np.asarray(gnss.vel_ned_mps, float)
    else:
        r = geo.lla_to_ned(gnss.lla, gnss.lla[0])
        v = np.gradient(r, gnss.t_s, axis=0) if n > 1 else np.zeros((n, 3))
    vh = np.hypot(v[:, 0], v[:, 1])
    ok = vh >= min_speed_mps
    yaw = np.arctan2(v[:, 1], v[:, 0])
    pitch = np.arctan2(-v[:, 2], np.maximum(vh, 1e-9))
    if ok.any():
        idx = np.where(ok, np.arange(n), -1)
        idx = np.maximum.accumulate(idx)
        idx[idx < 0] = int(np.argmax(ok))
        yaw, pitch = yaw[idx], pitch[idx]
    else:
        yaw, pitch = np.zeros(n), np.zeros(n)
    yaw_u = np.unwrap(yaw)
    yaw_rate = np.gradient(yaw_u, gnss.t_s) if n > 1 else np.zeros(n)
    rpy = np.stack([np.zeros(n), pitch, yaw], axis=1)
    w = np.zeros((n, 3))
    w[:, 2] = yaw_rate
    return dcm_from_euler_batch(rpy), w


def _vehicle_axes_map(imu_to_body: np.ndarray, matrix_in_vehicle_axes: np.ndarray) -> np.ndarray:
    """The IMU-axes matrix B^T M B of a map M written in nominal vehicle axes."""
    return imu_to_body.T @ matrix_in_vehicle_axes @ imu_to_body


def _time_shift_s(t_stamp_s: np.ndarray, offset_s: float, drift_ppm: float, t0_s: float) -> np.ndarray:
    return offset_s + 1e-6 * drift_ppm * (t_stamp_s - t0_s)


def _copy(ds: Dataset) -> Dataset:
    out = copy.copy(ds)
    out.imu = copy.copy(ds.imu)
    out.gnss = copy.copy(ds.gnss)
    out.notes = dict(ds.notes)
    return out


def _move_antenna(gnss: GnssData, delta_lever_m: np.ndarray, attitude: tuple | None) -> GnssData:
    """GNSS solutions of an antenna displaced by delta_lever_m (vehicle frame):
    r' = r + C_nv dl, v' = v + C_nv (w_nv x dl)."""
    C_nv, w_v = attitude if attitude is not None else vehicle_attitude_from_gnss(gnss)
    d_ned = np.einsum("nij,j->ni", C_nv, delta_lever_m)
    ref = gnss.lla[0]
    r = geo.lla_to_ned(gnss.lla, ref) + d_ned
    out = copy.copy(gnss)
    out.lla = geo.ned_to_lla(r, ref)
    if gnss.vel_ned_mps is not None:
        out.vel_ned_mps = gnss.vel_ned_mps + np.einsum("nij,nj->ni", C_nv, np.cross(w_v, delta_lever_m))
    return out


def inject(ds: Dataset, effects: EffectSet, attitude: tuple | None = None) -> Dataset:
    """A copy of ``ds`` whose data carry ``effects`` in addition to what they already carry,
    with nothing declared about them (the dataset's imu_to_body and lever arm are unchanged).

    attitude: optional (C_nv, w_nv_v_rps) at the GNSS epochs for the antenna move; by default
    ``vehicle_attitude_from_gnss``.
    """
    out = _copy(ds)
    B = np.asarray(ds.imu_to_body, float)
    e = effects
    imu = out.imu
    if np.any(e.imu_misalignment_rad) or np.any(e.gyro_scale) or np.any(e.accel_scale):
        R_T = dcm_from_euler(*e.imu_misalignment_rad).T
        M_g = _vehicle_axes_map(B, np.diag(1.0 + e.gyro_scale) @ R_T)
        M_a = _vehicle_axes_map(B, np.diag(1.0 + e.accel_scale) @ R_T)
        imu.gyro_rps = imu.gyro_rps @ M_g.T
        imu.acc_mps2 = imu.acc_mps2 @ M_a.T
    if e.imu_time_offset_s or e.imu_clock_drift_ppm:
        t = imu.t_s
        imu.t_s = t - _time_shift_s(t, e.imu_time_offset_s, e.imu_clock_drift_ppm, float(t[0]))
    if np.any(e.gnss_lever_arm_m):
        out.gnss = _move_antenna(out.gnss, np.asarray(e.gnss_lever_arm_m, float), attitude)
    if e.gnss_latency_s:
        out.gnss = copy.copy(out.gnss)
        out.gnss.t_s = out.gnss.t_s + e.gnss_latency_s
    out.notes["injected_effects"] = repr(e)
    return out


def inject_imu_bias(ds: Dataset, gyro_bias_rps: np.ndarray, accel_bias_mps2: np.ndarray) -> Dataset:
    """A copy of ``ds`` whose IMU samples carry an additional constant bias, given in IMU axes
    (rad/s, m/s^2), with nothing declared about it; in the filter's body axes it is
    ``imu_to_body @ bias``."""
    out = _copy(ds)
    out.imu = copy.copy(ds.imu)
    out.imu.gyro_rps = np.asarray(ds.imu.gyro_rps, float) + np.asarray(gyro_bias_rps, float)
    out.imu.acc_mps2 = np.asarray(ds.imu.acc_mps2, float) + np.asarray(accel_bias_mps2, float)
    out.notes["injected_imu_bias"] = {"gyro_bias_rps": np.asarray(gyro_bias_rps, float).tolist(),
                                      "accel_bias_mps2": np.asarray(accel_bias_mps2, float).tolist()}
    return out


def correct(ds: Dataset, effects: EffectSet) -> Dataset:
    """A copy of ``ds`` corrected for ``effects``: IMU stamps mapped to GPS time, samples
    rescaled per vehicle axis, GNSS tags moved to their validity time, and the misalignment and
    lever arm declared (``imu_to_body = R imu_to_body``, ``lever_arm_m += lever``)."""
    out = _copy(ds)
    B = np.asarray(ds.imu_to_body, float)
    e = effects
    imu = out.imu
    if np.any(e.gyro_scale) or np.any(e.accel_scale):
        imu.gyro_rps = imu.gyro_rps @ _vehicle_axes_map(B, np.diag(1.0 / (1.0 + e.gyro_scale))).T
        imu.acc_mps2 = imu.acc_mps2 @ _vehicle_axes_map(B, np.diag(1.0 / (1.0 + e.accel_scale))).T
    if e.imu_time_offset_s or e.imu_clock_drift_ppm:
        t = imu.t_s
        imu.t_s = t + _time_shift_s(t, e.imu_time_offset_s, e.imu_clock_drift_ppm, float(t[0]))
    if e.gnss_latency_s:
        out.gnss.t_s = out.gnss.t_s - e.gnss_latency_s
    out.imu_to_body = dcm_from_euler(*e.imu_misalignment_rad) @ B
    out.lever_arm_m = np.asarray(ds.lever_arm_m, float) + np.asarray(e.gnss_lever_arm_m, float)
    out.notes["corrected_effects"] = repr(e)
    return out
