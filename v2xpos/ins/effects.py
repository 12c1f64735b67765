"""Augmentable error-state effects (issue 3): what each one means, its default prior and how the
filter applies its correction. The state layout itself is ``ekf.StateLayout``.

Conventions (shared with ``v2xpos calibrate``):

* ``imu_time_offset`` dt [s]: ``t_gps = t_stamp + dt``; the filter labels its state with
  ``t_stamp + dt_est``. A label error moves the predicted antenna by ``-v dt_err`` (position) and
  ``-a dt_err`` (velocity) (Li & Mourikis 2014, "Online temporal calibration for camera-aided
  inertial navigation", IJRR 33(7), adapted to GNSS).
* ``imu_clock_drift`` [s/s]: the time offset changes as ``d(dt)/dt = drift`` (a residual scale
  error of the stamps' clock model); needs ``imu_time_offset``.
* ``gnss_latency`` [s]: the GNSS solution stamped t describes t - latency (opposite sign of the
  above; the two are not separable from GNSS alone: enable one of them).
* ``gnss_vel_latency`` [s]: the GNSS *velocity* stamped t describes t - latency, on top of the
  position timing (receivers/RTKLIB often report the mean velocity over the last epoch interval,
  i.e. half an interval late). H = -a.
* ``lever_arm`` [m]: antenna relative to the IMU in the vehicle/body frame [forward, right, down].
* ``misalignment`` (roll, pitch, yaw) [rad]: ``v_vehicle = R v_body``, ``R = Rz(y) Ry(p) Rx(r)``;
  only the vehicle constraints (NHC, odometer) and the reported vehicle attitude see it.
* ``gyro_scale`` / ``accel_scale``: per body axis, measured = (1 + s) true.
* ``odometer_scale``: wheel speed measured = (1 + s) true forward speed.
* ``rear_axle_distance`` d [m]: how far the IMU is ahead of the rear axle along the vehicle's x axis.
  A car's rear axle does not slip sideways (kinematic steering; Gillespie 1992, *Fundamentals of
  Vehicle Dynamics*, ch. 6), so a point d ahead of it moves sideways at ``v_y = omega_z d`` in a
  turn; the NHC measures that, not zero (``updates.nhc``).
* ``rear_slip_compliance`` k [rad per m/s^2]: the rear tyres slip at an angle ``k a_y`` to carry the
  lateral acceleration (a tyre's cornering force is ~0.2 of its load per degree of slip, Gillespie
  1992 ch. 10: ~5 deg at 1 g), so the rear axle itself moves sideways at ``-k a_y v``; needs
  ``rear_axle_distance``.

Each effect is a random constant with an optional random walk (``InsConfig.effects.effect_random_walk``).
"""
from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from .mechanization import COR_SA, COR_SG

if TYPE_CHECKING:
    from .ekf import StateLayout

DEFAULT_INITIAL_SD = {
    "imu_time_offset": 0.3,            # s: serial IMU logging delays reach hundreds of ms
    "gnss_latency": 0.05,              # s
    "imu_clock_drift": 2e-4,           # s/s (200 ppm)
    "gnss_vel_latency": 0.2,           # s
    "misalignment": np.radians(10.0),  # rad per axis: "nominal" mountings are off by degrees
    "gyro_scale": 0.01,
    "accel_scale": 0.01,
    "odometer_scale": 0.05,
    "rear_axle_distance": 2.0,         # m: an IMU anywhere between behind the rear axle and past the front one
    "rear_slip_compliance": 0.01,      # rad per m/s^2: 5.6 deg at 1 g
}
"""Priors for the effect states (1 sigma); the lever-arm prior is the dataset's lever_arm_sd_m."""

DEFAULT_RANDOM_WALK = {
    "imu_time_offset": 2e-5,           # s/sqrt(s): absorbs a residual clock drift of ~ tens of ppm
    "gnss_latency": 0.0,
    "imu_clock_drift": 0.0,
    "gnss_vel_latency": 0.0,
    "lever_arm": 0.0,
    "misalignment": 2e-6,              # rad/sqrt(s)
    "gyro_scale": 0.0,
    "accel_scale": 0.0,
    "odometer_scale": 1e-5,
    "rear_axle_distance": 0.0,
    "rear_slip_compliance": 0.0,
}

PLATFORM_EFFECTS = {
    "car": ("lever_arm", "imu_time_offset", "imu_clock_drift", "misalignment", "gnss_vel_latency"),
    "pedestrian": ("lever_arm", "imu_time_offset", "imu_clock_drift", "gnss_vel_latency"),
    "generic": ("lever_arm", "gnss_vel_latency"),
}
"""Effects estimated by default per platform (misalignment only matters with vehicle constraints)."""


class EffectValues:
    """Current estimates of the effect parameters (the nominal values the error states correct)."""

    def __init__(self, lever_arm_m: np.ndarray):
        self.lever_arm_m = np.asarray(lever_arm_m, float).copy()
        self.imu_time_offset_s = 0.0
        self.gnss_latency_s = 0.0
        self.gnss_vel_latency_s = 0.0
        self.imu_clock_drift = 0.0
        self.misalignment_rad = np.zeros(3)
        self.odometer_scale = 0.0
        self.rear_axle_distance_m = 0.0
        self.rear_slip_compliance = 0.0

    def apply_correction(self, layout: StateLayout, dx: np.ndarray, corr: np.ndarray) -> None:
        """value <- value - dx for every enabled effect (errors are estimate minus truth).
        corr is the mechanization's correction vector (scales live there)."""
        for name, i in layout.index.items():
            if name == "lever_arm":
                self.lever_arm_m -= dx[i:i + 3]
            elif name == "imu_time_offset":
                self.imu_time_offset_s -= dx[i]
            elif name == "gnss_latency":
                self.gnss_latency_s -= dx[i]
            elif name == "imu_clock_drift":
                self.imu_clock_drift -= dx[i]
            elif name == "gnss_vel_latency":
                self.gnss_vel_latency_s -= dx[i]
            elif name == "misalignment":
                self.misalignment_rad -= dx[i:i + 3]
            elif name == "gyro_scale":
                corr[COR_SG:COR_SG + 3] -= dx[i:i + 3]
            elif name == "accel_scale":
                corr[COR_SA:COR_SA + 3] -= dx[i:i + 3]
            elif name == "odometer_scale":
                self.odometer_scale -= dx[i]
            elif name == "rear_axle_distance":
                self.rear_axle_distance_m -= dx[i]
            elif name == "rear_slip_compliance":
                self.rear_slip_compliance -= dx[i]

    def as_dict(self, corr: np.ndarray) -> dict:
        return {"lever_arm_m": self.lever_arm_m.tolist(), "imu_time_offset_s": self.imu_time_offset_s,
                "gnss_latency_s": self.gnss_latency_s, "gnss_vel_latency_s": self.gnss_vel_latency_s,
                "imu_clock_drift_ppm": self.imu_clock_drift * 1e6,
                "misalignment_rad": self.misalignment_rad.tolist(),
                "gyro_scale": corr[COR_SG:COR_SG + 3].tolist(), "accel_scale": corr[COR_SA:COR_SA + 3].tolist(),
                "odometer_scale": self.odometer_scale, "rear_axle_distance_m": self.rear_axle_distance_m,
                "rear_slip_compliance": self.rear_slip_compliance}
