"""Compiled (numba) navigation math on scalars: the Earth model, rotations and SO(3) series that the
jitted strapdown (``ins.mechanization``) and the compiled relative-kinematics kernel
(``relative_jit``) share.

This is the compiled twin of ``geo`` and ``rotation`` (the readable numpy reference, which the
interpreted code and ``relative`` use); ``tests/test_kernels.py`` checks each function here against
its counterpart there. Conventions are theirs: ``C_ab`` takes vectors from b to a; Euler angles
(roll, pitch, yaw) of ``C_nb = Rz(yaw) Ry(pitch) Rx(roll)``; NED local level; WGS84.

Representation: 3x3 matrices are row-major flat arrays of 9 (``M[3 i + j]``), 3-vectors are three
scalars or tuples, so that the kernels allocate little and inline well. All functions are
``njit(cache=True)``: compiled on first use, then loaded from numba's on-disk cache. Numba checks a
cached function against its own source file only: after editing this module, delete the caches of
its callers too (``__pycache__/*.nbi``, ``*.nbc`` beside ``ins/mechanization.py`` and
``relative_jit.py``), or they keep the old code compiled in.

Sources: NIMA TR8350.2 (WGS84, Somigliana gravity eq. 4-1, free-air correction eq. 4-3); Groves,
*Principles of GNSS, Inertial, and Multisensor Integrated Navigation Systems*, 2nd ed. (2013),
eqs. 2.105-2.106 (radii), 2.112 (geodetic -> ECEF), 2.150 (C_en); Barfoot, *State Estimation for
Robotics* (2017) ch. 7 (SO(3) exponential and its left Jacobian).
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from v2xpos import geo

A_M = geo.A_M
E2 = geo.E2
OMEGA_IE_RPS = geo.OMEGA_IE_RPS
_GRAVITY_M = geo.OMEGA_IE_RPS ** 2 * geo.A_M ** 2 * geo.B_M / geo.GM_M3PS2
"""m = omega^2 a^2 b / GM of the free-air correction (TR8350.2 eq. 4-3)."""

SMALL_ANGLE_EXP_RAD2 = 1e-16
"""Below this squared rotation angle exp() uses its series (sin a / a and (1 - cos a) / a^2 lose
no digits above it)."""
SMALL_ANGLE_INTEGRALS_RAD2 = 1e-2
"""Below this squared rotation angle the coefficients of the integrals of exp() are their Taylor
series to a^6 (truncation < 3e-15); above it the closed forms, whose cancellation error
(~1e-16 / a^4 in the K^2 coefficient of Gamma2) times |K^2| = a^2 stays below 1e-14."""


# ----------------------------------------------------------------------------- Earth (geo)
@njit(cache=True)
def radii(lat_rad):
    """(R_M, R_N): meridian and prime-vertical radii of curvature [m] (geo.radii_m)."""
    s2 = math.sin(lat_rad) ** 2
    w = 1.0 - E2 * s2
    return A_M * (1.0 - E2) / w ** 1.5, A_M / math.sqrt(w)


@njit(cache=True)
def normal_gravity(lat_rad, h_m):
    """Magnitude of normal gravity [m/s^2] at latitude and ellipsoidal height
    (geo.normal_gravity_mps2)."""
    s2 = math.sin(lat_rad) ** 2
    g0 = geo.GAMMA_E_MPS2 * (1.0 + geo.GAMMA_K * s2) / math.sqrt(1.0 - E2 * s2)
    return g0 * (1.0 - 2.0 / A_M * (1.0 + geo.F + _GRAVITY_M - 2.0 * geo.F * s2) * h_m + 3.0 * h_m * h_m / (A_M * A_M))


@njit(cache=True)
def c_en(lat_rad, lon_rad):
    """C_en, ECEF -> NED at (lat, lon), flat (geo.dcm_ecef_to_ned)."""
    sl, cl, so, co = math.sin(lat_rad), math.cos(lat_rad), math.sin(lon_rad), math.cos(lon_rad)
    C = np.empty(9)
    C[0], C[1], C[2] = -sl * co, -sl * so, cl
    C[3], C[4], C[5] = -so, co, 0.0
    C[6], C[7], C[8] = -cl * co, -cl * so, -sl
    return C


@njit(cache=True)
def lla_to_ecef(lat_rad, lon_rad, h_m):
    """Geodetic -> ECEF (x, y, z) [m] (geo.lla_to_ecef)."""
    _, r_n = radii(lat_rad)
    cl = math.cos(lat_rad)
    return (r_n + h_m) * cl * math.cos(lon_rad), (r_n + h_m) * cl * math.sin(lon_rad), \
        (r_n * (1.0 - E2) + h_m) * math.sin(lat_rad)


# ----------------------------------------------------------------------------- rotations
@njit(cache=True)
def dcm_from_euler(roll_rad, pitch_rad, yaw_rad):
    """C_nb = Rz(yaw) Ry(pitch) Rx(roll), flat (rotation.dcm_from_euler)."""
    cr, sr = math.cos(roll_rad), math.sin(roll_rad)
    cp, sp = math.cos(pitch_rad), math.sin(pitch_rad)
    cy, sy = math.cos(yaw_rad), math.sin(yaw_rad)
    C = np.empty(9)
    C[0], C[1], C[2] = cp * cy, -cr * sy + sr * sp * cy, sr * sy + cr * sp * cy
    C[3], C[4], C[5] = cp * sy, cr * cy + sr * sp * sy, -sr * cy + cr * sp * sy
    C[6], C[7], C[8] = -sp, sr * cp, cr * cp
    return C


@njit(cache=True)
def euler_from_dcm(C):
    """(roll, pitch, yaw) [rad] of a flat C_nb (rotation.euler_from_dcm)."""
    return math.atan2(C[7], C[8]), -math.asin(max(-1.0, min(1.0, C[6]))), math.atan2(C[3], C[0])


@njit(cache=True)
def matmul(A, B, transpose_a=False, transpose_b=False):
    """op(A) op(B) of flat 3x3 matrices, op = transpose where asked (op(A)[i, k] = A[i sr + k sc])."""
    ar, ac = (1, 3) if transpose_a else (3, 1)
    br, bc = (1, 3) if transpose_b else (3, 1)
    C = np.empty(9)
    for i in range(3):
        for j in range(3):
            C[3 * i + j] = (A[i * ar] * B[j * bc] + A[i * ar + ac] * B[br + j * bc]
                            + A[i * ar + 2 * ac] * B[2 * br + j * bc])
    return C


@njit(cache=True)
def mv(M, x, y, z):
    """M v of a flat 3x3 M and v = (x, y, z)."""
    return M[0] * x + M[1] * y + M[2] * z, M[3] * x + M[4] * y + M[5] * z, M[6] * x + M[7] * y + M[8] * z


@njit(cache=True)
def mtv(M, x, y, z):
    """M^T v of a flat 3x3 M and v = (x, y, z)."""
    return M[0] * x + M[3] * y + M[6] * z, M[1] * x + M[4] * y + M[7] * z, M[2] * x + M[5] * y + M[8] * z


@njit(cache=True)
def quadratic_form(Q, x, y, z):
    """c^T Q c of a flat 3x3 Q and c = (x, y, z)."""
    q0, q1, q2 = mv(Q, x, y, z)
    return x * q0 + y * q1 + z * q2


@njit(cache=True)
def cross(a0, a1, a2, b0, b1, b2):
    """a x b."""
    return a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0


@njit(cache=True)
def cross_into(a, b, out):
    """out = a x b for 3-arrays."""
    out[0], out[1], out[2] = cross(a[0], a[1], a[2], b[0], b[1], b[2])


# ----------------------------------------------------------------------------- SO(3)
@njit(cache=True)
def so3_poly_into(x, y, z, c0, c1, c2, M):
    """M (flat, 9) = c0 I + c1 K + c2 K^2 with K = [phi x], phi = (x, y, z), and
    K^2 = phi phi^T - |phi|^2 I."""
    M[0], M[1], M[2] = c0 - c2 * (y * y + z * z), -c1 * z + c2 * x * y, c1 * y + c2 * x * z
    M[3], M[4], M[5] = c1 * z + c2 * x * y, c0 - c2 * (x * x + z * z), -c1 * x + c2 * y * z
    M[6], M[7], M[8] = -c1 * y + c2 * x * z, c1 * x + c2 * y * z, c0 - c2 * (x * x + y * y)


@njit(cache=True)
def so3_poly(x, y, z, c0, c1, c2):
    """c0 I + c1 K + c2 K^2 as a new flat array (``so3_poly_into``)."""
    M = np.empty(9)
    so3_poly_into(x, y, z, c0, c1, c2, M)
    return M


@njit(cache=True)
def exp_coefficients(a2):
    """(sin a / a, (1 - cos a) / a^2) of a = sqrt(a2): exp([phi x]) = I + s K + c K^2 (Rodrigues)."""
    if a2 < SMALL_ANGLE_EXP_RAD2:
        return 1.0 - a2 / 6.0, 0.5 - a2 / 24.0
    a = math.sqrt(a2)
    return math.sin(a) / a, (1.0 - math.cos(a)) / a2


@njit(cache=True)
def exp_so3_into(x, y, z, M):
    """M (flat, 9) = exp([phi x]), phi = (x, y, z) [rad] (rotation.exp_so3); no allocation, for
    per-sample loops."""
    s, c = exp_coefficients(x * x + y * y + z * z)
    so3_poly_into(x, y, z, 1.0, s, c, M)


@njit(cache=True)
def exp_so3(x, y, z):
    """exp([phi x]) as a new flat array (``exp_so3_into``)."""
    M = np.empty(9)
    exp_so3_into(x, y, z, M)
    return M


@njit(cache=True)
def so3_integrals(x, y, z):
    """exp([phi x]) and its first and second integrals, flat, phi = (x, y, z) [rad]:
    Gamma1 = int_0^1 exp(s K) ds = I + (1 - cos a)/a^2 K + (a - sin a)/a^3 K^2 (the left Jacobian),
    Gamma2 = int_0^1 int_0^s exp(u K) du ds = I/2 + (a - sin a)/a^3 K + (a^2/2 + cos a - 1)/a^4 K^2
    (rotation.so3_integrals)."""
    a2 = x * x + y * y + z * z
    if a2 < SMALL_ANGLE_INTEGRALS_RAD2:
        c1 = 1.0 / 2.0 - a2 * (1.0 / 24.0 - a2 * (1.0 / 720.0 - a2 / 40320.0))
        c2 = 1.0 / 6.0 - a2 * (1.0 / 120.0 - a2 * (1.0 / 5040.0 - a2 / 362880.0))
        d2 = 1.0 / 24.0 - a2 * (1.0 / 720.0 - a2 * (1.0 / 40320.0 - a2 / 3628800.0))
    else:
        a = math.sqrt(a2)
        s, c = math.sin(a), math.cos(a)
        c1, c2 = (1.0 - c) / a2, (a - s) / (a2 * a)
        d2 = (0.5 * a2 + c - 1.0) / (a2 * a2)
    return exp_so3(x, y, z), so3_poly(x, y, z, 1.0, c1, c2), so3_poly(x, y, z, 0.5, c2, d2)
