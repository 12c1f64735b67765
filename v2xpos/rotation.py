"""Rotations: DCM, quaternion, Euler yaw-pitch-roll (Z-Y-X), rotation vector (Rodrigues), operator T.

Conventions
-----------
* ``C_ab`` is the direction-cosine matrix that takes a vector from frame b to frame a:
  ``v_a = C_ab @ v_b``. ``C_nb`` = body -> navigation (NED).
* Euler angles are (roll, pitch, yaw) [rad] of the Z-Y-X (yaw, then pitch, then roll) sequence:
  ``C_nb = Rz(yaw) @ Ry(pitch) @ Rx(roll)`` (Groves 2013 eq. 2.22, transposed).
* Quaternions are Hamilton, scalar first ``q = [w, x, y, z]``; ``q_nb`` rotates body -> nav,
  ``v_n = q_nb * v_b * q_nb^-1``.
* Rotation vector ``phi`` (axis * angle, rad); ``exp_so3(phi)`` is the DCM of the rotation,
  ``log_so3(C)`` its inverse (Rodrigues' formula).
* Body frame: x forward, y right, z down.
"""
from __future__ import annotations

import numpy as np

_EPS = 1e-12


def skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrix [v x] with skew(a) @ b == cross(a, b)."""
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def rot_x(a_rad: float) -> np.ndarray:
    """Active rotation about x by a_rad (DCM from the rotated frame to the original)."""
    c, s = np.cos(a_rad), np.sin(a_rad)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rot_y(a_rad: float) -> np.ndarray:
    """Active rotation about y by a_rad."""
    c, s = np.cos(a_rad), np.sin(a_rad)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rot_z(a_rad: float) -> np.ndarray:
    """Active rotation about z by a_rad."""
    c, s = np.cos(a_rad), np.sin(a_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def dcm_from_euler(roll_rad: float, pitch_rad: float, yaw_rad: float) -> np.ndarray:
    """C_nb (body -> nav) from Z-Y-X Euler angles: Rz(yaw) Ry(pitch) Rx(roll)."""
    cr, sr = np.cos(roll_rad), np.sin(roll_rad)
    cp, sp = np.cos(pitch_rad), np.sin(pitch_rad)
    cy, sy = np.cos(yaw_rad), np.sin(yaw_rad)
    return np.array([
        [cp * cy, -cr * sy + sr * sp * cy, sr * sy + cr * sp * cy],
        [cp * sy, cr * cy + sr * sp * sy, -sr * cy + cr * sp * sy],
        [-sp, sr * cp, cr * cp]])


def euler_from_dcm(C_nb: np.ndarray) -> np.ndarray:
    """(roll, pitch, yaw) [rad] of C_nb = Rz(yaw) Ry(pitch) Rx(roll); yaw in (-pi, pi]."""
    roll = np.arctan2(C_nb[2, 1], C_nb[2, 2])
    pitch = -np.arcsin(np.clip(C_nb[2, 0], -1.0, 1.0))
    yaw = np.arctan2(C_nb[1, 0], C_nb[0, 0])
    return np.array([roll, pitch, yaw])


def dcm_from_euler_xyz(angles_rad: np.ndarray) -> np.ndarray:
    """DCM of the intrinsic X-Y-Z sequence, C = Rx(a) Ry(b) Rz(c), angles (a, b, c) [rad].

    Used for mounting angles given "in X-Y-Z order" (rotate about x, then the new y, then the
    new z): the DCM taking vectors from the mounted unit's frame to the reference frame.
    """
    a, b, c = angles_rad
    return rot_x(a) @ rot_y(b) @ rot_z(c)


def quat_from_dcm(C: np.ndarray) -> np.ndarray:
    """Unit quaternion [w, x, y, z] of the DCM C (Shepperd's method, numerically robust)."""
    tr = C[0, 0] + C[1, 1] + C[2, 2]
    k = int(np.argmax([tr, C[0, 0], C[1, 1], C[2, 2]]))
    if k == 0:
        w = 0.5 * np.sqrt(1.0 + tr)
        q = [w, (C[2, 1] - C[1, 2]) / (4 * w), (C[0, 2] - C[2, 0]) / (4 * w), (C[1, 0] - C[0, 1]) / (4 * w)]
    elif k == 1:
        x = 0.5 * np.sqrt(1.0 + 2 * C[0, 0] - tr)
        q = [(C[2, 1] - C[1, 2]) / (4 * x), x, (C[0, 1] + C[1, 0]) / (4 * x), (C[0, 2] + C[2, 0]) / (4 * x)]
    elif k == 2:
        y = 0.5 * np.sqrt(1.0 + 2 * C[1, 1] - tr)
        q = [(C[0, 2] - C[2, 0]) / (4 * y), (C[0, 1] + C[1, 0]) / (4 * y), y, (C[1, 2] + C[2, 1]) / (4 * y)]
    else:
        z = 0.5 * np.sqrt(1.0 + 2 * C[2, 2] - tr)
        q = [(C[1, 0] - C[0, 1]) / (4 * z), (C[0, 2] + C[2, 0]) / (4 * z), (C[1, 2] + C[2, 1]) / (4 * z), z]
    q = np.array(q)
    return q / np.linalg.norm(q) * (1.0 if q[0] >= 0 else -1.0)


def dcm_from_quat(q: np.ndarray) -> np.ndarray:
    """DCM of the unit quaternion q = [w, x, y, z]."""
    w, x, y, z = q
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def quat_mult(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Hamilton product p * q."""
    pw, px, py, pz = p
    qw, qx, qy, qz = q
    return np.array([pw * qw - px * qx - py * qy - pz * qz,
                     pw * qx + px * qw + py * qz - pz * qy,
                     pw * qy - px * qz + py * qw + pz * qx,
                     pw * qz + px * qy - py * qx + pz * qw])


def quat_from_rotvec(phi: np.ndarray) -> np.ndarray:
    """Quaternion of the rotation vector phi [rad]: [cos(|phi|/2), sin(|phi|/2) phi/|phi|]."""
    a = float(np.linalg.norm(phi))
    if a < 1e-8:
        return np.array([1.0 - a * a / 8.0, *(0.5 - a * a / 48.0) * np.asarray(phi)])
    return np.array([np.cos(a / 2), *(np.sin(a / 2) / a) * np.asarray(phi)])


def rotvec_from_quat(q: np.ndarray) -> np.ndarray:
    """Rotation vector [rad] of the unit quaternion q (angle in [0, pi])."""
    q = q if q[0] >= 0 else -q
    s = float(np.linalg.norm(q[1:]))
    if s < 1e-8:
        return 2.0 * q[1:] / q[0]
    return 2.0 * np.arctan2(s, q[0]) / s * q[1:]


def exp_so3(phi: np.ndarray) -> np.ndarray:
    """DCM of the rotation vector phi (Rodrigues: I + sin a/a [phi x] + (1-cos a)/a^2 [phi x]^2)."""
    a = float(np.linalg.norm(phi))
    K = skew(phi)
    if a < 1e-8:
        return np.eye(3) + K + 0.5 * K @ K
    return np.eye(3) + np.sin(a) / a * K + (1.0 - np.cos(a)) / a ** 2 * K @ K


def so3_integrals(phi: np.ndarray) -> tuple:
    """exp([phi x]) and its first and second integrals over the rotation, with K = [phi x], a = |phi|:

        Gamma1 = int_0^1 exp(s K) ds = I + (1 - cos a)/a^2 K + (a - sin a)/a^3 K^2,
        Gamma2 = int_0^1 int_0^s exp(u K) du ds = I/2 + (a - sin a)/a^3 K + (a^2/2 + cos a - 1)/a^4 K^2.

    Gamma1 is the left Jacobian of SO(3) (Barfoot, *State Estimation for Robotics*, 2017, ch. 7);
    Gamma2 = int_0^1 (1 - s) exp(s K) ds follows from the same Rodrigues series (the integrals of
    IMU preintegration, Forster et al., IEEE T-RO 2017). Below a = 0.1 the coefficients are their
    Taylor series to a^6 (the closed forms cancel there: ~1e-16 / a^4 in the last one). With constant body rate w and body acceleration
    f over t: C(t) = C exp([w t x]), v(t) = v + C Gamma1(w t) f t, r(t) = r + v t + C Gamma2(w t) f t^2.
    """
    phi = np.asarray(phi, dtype=float)
    a2 = float(phi @ phi)
    if a2 < 1e-2:
        series = np.array([[1 / 2, -1 / 24, 1 / 720, -1 / 40320],
                           [1 / 6, -1 / 120, 1 / 5040, -1 / 362880],
                           [1 / 24, -1 / 720, 1 / 40320, -1 / 3628800]])
        k1, k2, k3 = series @ a2 ** np.arange(4)
    else:
        a = np.sqrt(a2)
        k1, k2, k3 = (1.0 - np.cos(a)) / a2, (a - np.sin(a)) / (a2 * a), (0.5 * a2 + np.cos(a) - 1.0) / a2 ** 2
    K = skew(phi)
    K2 = K @ K
    return exp_so3(phi), np.eye(3) + k1 * K + k2 * K2, 0.5 * np.eye(3) + k2 * K + k3 * K2


def log_so3(C: np.ndarray) -> np.ndarray:
    """Rotation vector [rad] of the DCM C (inverse Rodrigues), robust near 0 and pi."""
    return rotvec_from_quat(quat_from_dcm(C))


def orthonormalize(C: np.ndarray) -> np.ndarray:
    """Nearest rotation matrix to C (SVD projection)."""
    u, _, vt = np.linalg.svd(C)
    R = u @ vt
    if np.linalg.det(R) < 0:
        u[:, -1] *= -1
        R = u @ vt
    return R


def wrap_pi(a: np.ndarray | float) -> np.ndarray | float:
    """Wrap angle(s) to (-pi, pi]."""
    return -((-np.asarray(a) + np.pi) % (2.0 * np.pi) - np.pi)


def operator_T(d_yaw_rad: float, d_pitch_rad: float, d_roll_rad: float) -> np.ndarray:
    """Yaw-pitch-roll operator T taking a vector from the slave body frame to the master body frame.

    With the slave's attitude relative to the master expressed as Z-Y-X Euler angles
    (d_yaw, d_pitch, d_roll), ``v_master_body = T @ v_slave_body`` where
    ``T = Rz(d_yaw) Ry(d_pitch) Rx(d_roll) = C_ms``. Equivalently ``C_ms = C_nm^T C_ns`` from the
    two vehicles' body->NED attitudes (see ``relative_attitude``).
    """
    return dcm_from_euler(d_roll_rad, d_pitch_rad, d_yaw_rad)


def relative_attitude(C_n_master: np.ndarray, C_n_slave: np.ndarray) -> tuple:
    """Relative attitude of the slave in the master body frame.

    Returns ``(C_ms, euler)`` with ``C_ms = C_n_master^T C_n_slave`` (slave body -> master body) and
    ``euler = (d_roll, d_pitch, d_yaw)`` [rad] such that ``operator_T(d_yaw, d_pitch, d_roll) == C_ms``.
    """
    C_ms = C_n_master.T @ C_n_slave
    return C_ms, euler_from_dcm(C_ms)


def dcm_from_euler_batch(rpy_rad: np.ndarray) -> np.ndarray:
    """Vectorised ``dcm_from_euler`` for an (N, 3) array of (roll, pitch, yaw) -> (N, 3, 3)."""
    r, p, y = rpy_rad[:, 0], rpy_rad[:, 1], rpy_rad[:, 2]
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    C = np.empty((len(r), 3, 3))
    C[:, 0, 0] = cp * cy
    C[:, 0, 1] = -cr * sy + sr * sp * cy
    C[:, 0, 2] = sr * sy + cr * sp * cy
    C[:, 1, 0] = cp * sy
    C[:, 1, 1] = cr * cy + sr * sp * sy
    C[:, 1, 2] = -sr * cy + cr * sp * sy
    C[:, 2, 0] = -sp
    C[:, 2, 1] = sr * cp
    C[:, 2, 2] = cr * cp
    return C


def euler_from_dcm_batch(C: np.ndarray) -> np.ndarray:
    """Vectorised ``euler_from_dcm`` for (N, 3, 3) -> (N, 3) (roll, pitch, yaw)."""
    roll = np.arctan2(C[:, 2, 1], C[:, 2, 2])
    pitch = -np.arcsin(np.clip(C[:, 2, 0], -1.0, 1.0))
    yaw = np.arctan2(C[:, 1, 0], C[:, 0, 0])
    return np.stack([roll, pitch, yaw], axis=1)
