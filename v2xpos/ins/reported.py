"""Covariance of what the filter *reports*, not of its error state.

``InsFilter.nav_state`` reports the IMU point's position and velocity and the *vehicle* attitude
``C_nv = C_nb R(m)^T`` (R: the estimated misalignment, body -> vehicle), all labelled with the GPS
time ``t_L = stamp + dt_est`` (dt: the estimated IMU time offset). Their errors are linear in the
error state x (est minus truth, ``ekf`` conventions: ``C_nb_est = (I - [phi x]) C_nb``,
``dm = m_est - m_true``, ``d(dt) = dt_est - dt_true``):

    position at t_L:   dr_L  = dr  - v^n d(dt)
    velocity at t_L:   dv_L  = dv  - a^n d(dt)
    vehicle attitude:  phi_L = phi + C_nb Gamma(m) dm + C_nb w_nb^b d(dt)

(the state describes the true time t_L - d(dt); moving it to t_L adds the motion over d(dt).
``Gamma(m)`` is the body-frame Jacobian of the ZYX Euler angles, R(m + e) = R(m)(I + [Gamma e x]):
Gamma = [[1, 0, -sin p], [0, cos r, sin r cos p], [0, -sin r, cos r cos p]] (Groves 2013 eq. 2.56
for the Euler-rate relation)). Hence the reported covariance is ``J P J^T`` with J the 9 x n
matrix of these rows (Bar-Shalom, Li & Kirubarajan 2001 sec. 1.4.15, the covariance of a linear
function of a Gaussian vector). Taking only ``diag(P)`` of the attitude block, as before, ignored
that NHC fixes the *vehicle* heading (phi_D + dm_yaw strongly anti-correlated: the vehicle yaw
is known better than the IMU's), and that at 15 m/s a time-offset sd of 3 ms is 4.5 cm along track.
"""
from __future__ import annotations

import math

import numpy as np

from .ekf import ATT, POS, VEL


def euler_body_jacobian(rpy_rad: np.ndarray) -> np.ndarray:
    """Gamma(m): R(m + e) = R(m) (I + [Gamma e x]) for R = Rz(yaw) Ry(pitch) Rx(roll), e = (roll,
    pitch, yaw) increments."""
    r, p = float(rpy_rad[0]), float(rpy_rad[1])
    sr, cr, sp, cp = math.sin(r), math.cos(r), math.sin(p), math.cos(p)
    return np.array([[1.0, 0.0, -sp], [0.0, cr, sr * cp], [0.0, -sr, cr * cp]])


def reported_jacobian(layout, C_nb: np.ndarray, misalignment_rad: np.ndarray, v_ned_mps: np.ndarray,
                      acc_ned_mps2: np.ndarray, rate_body_rps: np.ndarray) -> np.ndarray:
    """J (9 x n): rows position NED, velocity NED, vehicle attitude error NED (see module docstring)."""
    J = np.zeros((9, layout.n))
    J[0:3, POS:POS + 3] = np.eye(3)
    J[3:6, VEL:VEL + 3] = np.eye(3)
    J[6:9, ATT:ATT + 3] = np.eye(3)
    i = layout.at("misalignment")
    if i >= 0:
        J[6:9, i:i + 3] = C_nb @ euler_body_jacobian(misalignment_rad)
    k = layout.at("imu_time_offset")
    if k >= 0:
        J[0:3, k] = -np.asarray(v_ned_mps, float)
        J[3:6, k] = -np.asarray(acc_ned_mps2, float)
        J[6:9, k] = C_nb @ np.asarray(rate_body_rps, float)
    return J


def reported_covariance(P: np.ndarray, J: np.ndarray) -> np.ndarray:
    """J P J^T, symmetrised (9 x 9: position, velocity, vehicle attitude)."""
    C = J @ P @ J.T
    return 0.5 * (C + C.T)


def correlations(C3: np.ndarray) -> np.ndarray:
    """Correlation coefficients (NE, ND, ED) of a 3 x 3 covariance (0 where a variance is 0)."""
    d = np.sqrt(np.maximum(np.diag(C3), 0.0))

    def rho(i: int, j: int) -> float:
        den = d[i] * d[j]
        return float(np.clip(C3[i, j] / den, -1.0, 1.0)) if den > 0 else 0.0
    return np.array([rho(0, 1), rho(0, 2), rho(1, 2)])
