"""Initial attitude before the filter starts.

1. Coarse levelling while static (Groves 2013 eq. 5.101-5.102; z down, f_b = -C_bn g^n):
   ``roll = atan2(-f_y, -f_z)``, ``pitch = atan2(f_x, sqrt(f_y^2 + f_z^2))`` from the mean specific
   force of a static window (yaw arbitrary, set to 0).
2. Between the last static window and the moment the platform moves fast enough, the attitude is
   carried forward by integrating the (bias-compensated) gyro: ``C <- C exp([w dt x])``; the
   Earth and transport rates are neglected over these seconds.
3. Heading from the GNSS course once ``|v_h| >= align_min_speed_mps``: the yaw of the carried
   attitude is replaced by the course (a car moves along its body x axis; for a pedestrian the
   course is only a start, with a wide sd: the device may point anywhere), i.e.
   ``C_nb = Rz(course - yaw(C)) C``.

Without a static window the level comes from the mean specific force of the first ``level_window_s``
(the error is the mean kinematic acceleration over that window divided by g).
"""
from __future__ import annotations

import numpy as np

from v2xpos.rotation import dcm_from_euler, euler_from_dcm, exp_so3, orthonormalize, rot_z


def level_from_specific_force(f_b_mps2: np.ndarray) -> tuple[float, float]:
    """(roll, pitch) [rad] of C_nb from a mean specific force in body axes (x fwd, y right, z down)."""
    fx, fy, fz = f_b_mps2
    return float(np.arctan2(-fy, -fz)), float(np.arctan2(fx, np.hypot(fy, fz)))


class CoarseAligner:
    """Keeps a levelled attitude (yaw arbitrary) up to date until heading is known."""

    def __init__(self, level_window_s: float = 0.5):
        self.level_window_s = level_window_s
        self.C_nb: np.ndarray | None = None
        self.levelled_static = False
        self._sum_f = np.zeros(3)
        self._n = 0
        self._t0: float | None = None

    def feed(self, t_s: np.ndarray, f_b: np.ndarray, w_b: np.ndarray, static: bool) -> None:
        """One chunk of bias-compensated body-frame samples; ``static`` from the stop detector."""
        if len(t_s) == 0:
            return
        if self._t0 is None:
            self._t0 = float(t_s[0])
        if static:
            yaw = 0.0 if self.C_nb is None else float(euler_from_dcm(self.C_nb)[2])
            roll, pitch = level_from_specific_force(f_b.mean(axis=0))
            self.C_nb = dcm_from_euler(roll, pitch, yaw)
            self.levelled_static = True
            return
        if self.C_nb is None:
            self._sum_f += f_b.sum(axis=0)
            self._n += len(t_s)
            if t_s[-1] - self._t0 >= self.level_window_s:
                roll, pitch = level_from_specific_force(self._sum_f / self._n)
                self.C_nb = dcm_from_euler(roll, pitch, 0.0)
            return
        dt = np.diff(t_s, prepend=t_s[0] - (t_s[1] - t_s[0] if len(t_s) > 1 else 0.01))
        self.C_nb = orthonormalize(self.C_nb @ exp_so3((w_b * dt[:, None]).sum(axis=0)))

    def attitude_with_heading(self, yaw_rad: float) -> np.ndarray | None:
        """C_nb (body -> NED) with its yaw set to yaw_rad, or None before levelling."""
        if self.C_nb is None:
            return None
        yaw_now = float(euler_from_dcm(self.C_nb)[2])
        return rot_z(yaw_rad - yaw_now) @ self.C_nb


class CourseTracker:
    """Velocity and course from GNSS positions alone (receivers that report no velocity), for the
    heading initialisation: a constant-velocity Kalman filter (filterpy ``KalmanFilter``; Labbe,
    *Kalman and Bayesian Filters in Python*, ch. 8) on local north/east positions, state
    [N, vN, E, vE], process noise = discrete white-noise acceleration of ``accel_sd_mps2``.
    """

    def __init__(self, accel_sd_mps2: float = 1.0):
        self.accel_sd_mps2 = accel_sd_mps2
        self.kf = None
        self.origin = None
        self.t_s: float | None = None
        self.updates = 0

    def update(self, t_s: float, lla: np.ndarray, sd_h_m: float) -> tuple[np.ndarray, float] | None:
        """Feed one fix; returns (velocity NED with zero down [m/s], speed sd [m/s]) once two fixes
        have been seen, else None. A gap over 2 s restarts the tracker."""
        from filterpy.common import Q_discrete_white_noise
        from filterpy.kalman import KalmanFilter

        from v2xpos import geo
        if self.kf is None or self.t_s is None or not 0.0 < t_s - self.t_s < 2.0:
            self.kf = KalmanFilter(dim_x=4, dim_z=2)
            self.kf.H = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]])
            self.kf.P = np.diag([sd_h_m ** 2, 25.0, sd_h_m ** 2, 25.0])
            self.origin = np.asarray(lla, float).copy()
            self.kf.x = np.zeros((4, 1))
            self.t_s, self.updates = t_s, 0
            return None
        dt = t_s - self.t_s
        self.t_s = t_s
        f1 = np.array([[1.0, dt], [0.0, 1.0]])
        self.kf.F = np.kron(np.eye(2), f1)
        self.kf.Q = Q_discrete_white_noise(dim=2, dt=dt, var=self.accel_sd_mps2 ** 2, block_size=2)
        self.kf.R = np.eye(2) * max(sd_h_m, 0.01) ** 2
        self.kf.predict()
        ne = geo.lla_to_ned(np.asarray(lla, float), self.origin)[:2]
        self.kf.update(ne.reshape(2, 1))
        self.updates += 1
        v = np.array([self.kf.x[1, 0], self.kf.x[3, 0], 0.0])
        return v, float(np.sqrt(0.5 * (self.kf.P[1, 1] + self.kf.P[3, 3])))
