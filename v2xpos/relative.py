"""Relative kinematics between a master (hunter) and a target: gating, staleness, latency
compensation (CTRA) and the transform into the master body frame with operator T.

Public API (stable; composed by the master service)
----------------------------------------------------
* ``TargetStatus``, ``FixSide``, ``RelativeResult`` (re-exported from ``v2xpos.wire``)
* ``gate_fix_status(master_fix, slave_fix) -> TargetStatus`` and
  ``fix_failed_side(master_fix, slave_fix) -> FixSide``
* ``check_latency(master_t_gps_s, slave_t_gps_s, timeout_s=0.2, future_tolerance_s=0.02)
  -> (TargetStatus, latency_s)``
* ``predict_state(state, dt_s, acc_sd_mps2=..., rate_sd_rps=...)`` -> same type (StateMessage or
  NavState), CTRA latency compensation with covariance
* ``relative_kinematics(master_state, slave_state, master_points=None, slave_points=None)
  -> RelativeResult``
* ``evaluate_target(master_state, slave_msg, master_point=None, timeout_s=0.2, ...)
  -> RelativeResult`` -- gate, staleness, compensation and transform in one call.
* ``relative_yaw_sd(master_att_sd_rad, slave_att_sd_rad, dt_s, rate_sd_rps) -> float``

``master_state`` / ``slave_state`` may be a ``StateMessage`` or a ``NavState`` (both expose
``lla``, ``t_s``, ``v_ned_mps``, ``acc_body_mps2``, ``rate_body_rps``, ``rpy_rad``, ``pos_sd_m``,
``vel_sd_mps``, ``att_sd_rad``, ``fix``).

Frames: NED is the local-level frame at the *master* position; body frames x forward, y right,
z down; ``C_ab`` takes vectors from b to a. ``w_m`` is the master body rate, ``r_b`` the target
reference point relative to the master reference point in the master body frame.

Relative motion (derivatives seen from the rotating master frame: Goldstein, Poole & Safko,
*Classical Mechanics*, 3rd ed., 2002, §4.9-4.10, Coriolis and centripetal terms):
    r_b = C_bn (r_s - r_m)_n
    v_rel_b = d/dt r_b |_master = C_bn (v_s - v_m) - w_m x r_b
    a_rel_b = C_bn (a_s - a_m)_n - 2 w_m x C_bn (v_s - v_m) + w_m x (w_m x r_b)   (w_m constant)
so a point rigidly attached to the master has zero relative velocity and acceleration
(what a driver in the master sees). Relative attitude: C_ms = C_nm^T C_ns =
operator_T(d_yaw, d_pitch, d_roll). The target's velocity and attitude are rotated from its own
NED to the master's NED (C_n_m n_s = C_en(m) C_en(s)^T) so the result stays exact at long range.
"""
from __future__ import annotations

import math
from typing import Any

import numpy as np

from v2xpos.geo import A_M, E2
from v2xpos.types import FixStatus
from v2xpos.wire import FixSide, Geometry, RelativeResult, StateMessage, TargetStatus

__all__ = ["TargetStatus", "FixSide", "RelativeResult", "DEFAULT_TIMEOUT_S",
           "DEFAULT_FUTURE_TOLERANCE_S", "gate_fix_status", "fix_failed_side", "check_latency",
           "ctra_increments", "predict_state", "relative_kinematics", "relative_yaw_sd", "evaluate_target"]

DEFAULT_TIMEOUT_S = 0.200
DEFAULT_FUTURE_TOLERANCE_S = 0.020
DEFAULT_ACC_SD_MPS2 = 0.5
"""1-sigma of the unmodelled change of body acceleration over a prediction (jerk allowance)."""
DEFAULT_RATE_SD_RPS = 0.02
"""1-sigma of the unmodelled change of body angular rate over a prediction."""
CLOSING_EPS_MPS = 1.0e-3



# ----------------------------------------------------------------------------- gating

_RTK_FIXES = frozenset((FixStatus.FIXED, FixStatus.FLOAT))


def fix_failed_side(master_fix: FixStatus | int, slave_fix: FixStatus | int) -> FixSide:
    """Which side is not RTK (fixed or float): FixSide.MASTER | FixSide.SLAVE, NONE if both are."""
    if master_fix in _RTK_FIXES and slave_fix in _RTK_FIXES:
        return FixSide.NONE
    side = FixSide.NONE
    if not FixStatus(master_fix).is_rtk:
        side |= FixSide.MASTER
    if not FixStatus(slave_fix).is_rtk:
        side |= FixSide.SLAVE
    return side


def gate_fix_status(master_fix: FixStatus | int, slave_fix: FixStatus | int) -> TargetStatus:
    """VALID only when both master and slave are RTK fixed or float, else FIX_INVALID.

    ``fix_failed_side`` says which side failed.
    """
    return TargetStatus.VALID if fix_failed_side(master_fix, slave_fix) == FixSide.NONE \
        else TargetStatus.FIX_INVALID


def check_latency(master_t_gps_s: float, slave_t_gps_s: float, timeout_s: float = DEFAULT_TIMEOUT_S,
                  future_tolerance_s: float = DEFAULT_FUTURE_TOLERANCE_S) -> tuple:
    """Staleness of a target message: ``(status, latency_s)``, latency = master time - slave time.

    latency > timeout_s -> TIMEOUT (no relative output from that message);
    latency < -future_tolerance_s -> FUTURE (slave clock ahead, reported); else VALID.
    """
    latency_s = float(master_t_gps_s) - float(slave_t_gps_s)
    if latency_s > timeout_s:
        return TargetStatus.TIMEOUT, latency_s
    if latency_s < -future_tolerance_s:
        return TargetStatus.FUTURE, latency_s
    return TargetStatus.VALID, latency_s


# ----------------------------------------------------------------------------- 3-D helpers
# Small fixed-size algebra in plain floats: 3-vectors are tuples, 3x3 matrices are row-major
# 9-tuples. On single vectors this is several times faster than numpy's per-call overhead.

def _mv(M: tuple, v: tuple) -> tuple:
    """M v."""
    x, y, z = v
    return (M[0] * x + M[1] * y + M[2] * z, M[3] * x + M[4] * y + M[5] * z, M[6] * x + M[7] * y + M[8] * z)


def _mtv(M: tuple, v: tuple) -> tuple:
    """M^T v."""
    x, y, z = v
    return (M[0] * x + M[3] * y + M[6] * z, M[1] * x + M[4] * y + M[7] * z, M[2] * x + M[5] * y + M[8] * z)


def _mm(A: tuple, B: tuple) -> tuple:
    """A B."""
    a0, a1, a2, a3, a4, a5, a6, a7, a8 = A
    b0, b1, b2, b3, b4, b5, b6, b7, b8 = B
    return (a0 * b0 + a1 * b3 + a2 * b6, a0 * b1 + a1 * b4 + a2 * b7, a0 * b2 + a1 * b5 + a2 * b8,
            a3 * b0 + a4 * b3 + a5 * b6, a3 * b1 + a4 * b4 + a5 * b7, a3 * b2 + a4 * b5 + a5 * b8,
            a6 * b0 + a7 * b3 + a8 * b6, a6 * b1 + a7 * b4 + a8 * b7, a6 * b2 + a7 * b5 + a8 * b8)


def _transpose(A: tuple) -> tuple:
    return (A[0], A[3], A[6], A[1], A[4], A[7], A[2], A[5], A[8])


def _mtm(A: tuple, B: tuple) -> tuple:
    """A^T B."""
    return _mm(_transpose(A), B)


def _mmt(A: tuple, B: tuple) -> tuple:
    """A B^T."""
    return _mm(A, _transpose(B))


def _cross(a: tuple, b: tuple) -> tuple:
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def _dcm(roll: float, pitch: float, yaw: float) -> tuple:
    """C_nb = Rz(yaw) Ry(pitch) Rx(roll) (same as rotation.dcm_from_euler)."""
    cr, sr, cp, sp, cy, sy = math.cos(roll), math.sin(roll), math.cos(pitch), math.sin(pitch), math.cos(yaw), math.sin(yaw)
    return (cp * cy, -cr * sy + sr * sp * cy, sr * sy + cr * sp * cy,
            cp * sy, cr * cy + sr * sp * sy, -sr * cy + cr * sp * sy,
            -sp, sr * cp, cr * cp)


def _euler(C: tuple) -> tuple:
    """(roll, pitch, yaw) of C_nb (same as rotation.euler_from_dcm)."""
    return (math.atan2(C[7], C[8]), -math.asin(max(-1.0, min(1.0, C[6]))), math.atan2(C[3], C[0]))


def _c_en(lat: float, lon: float) -> tuple:
    """C_en, ECEF -> NED at (lat, lon) (Groves 2013 eq. 2.150)."""
    sl, cl, so, co = math.sin(lat), math.cos(lat), math.sin(lon), math.cos(lon)
    return (-sl * co, -sl * so, cl, -so, co, 0.0, -cl * co, -cl * so, -sl)


def _ecef(lat: float, lon: float, h: float) -> tuple:
    """Geodetic -> ECEF [m] (Groves 2013 eq. 2.112)."""
    sl, cl = math.sin(lat), math.cos(lat)
    r_n = A_M / math.sqrt(1.0 - E2 * sl * sl)
    return ((r_n + h) * cl * math.cos(lon), (r_n + h) * cl * math.sin(lon), (r_n * (1.0 - E2) + h) * sl)


def _poly_so3(phi: tuple, c0: float, c1: float, c2: float) -> tuple:
    """c0 I + c1 K + c2 K^2 with K = [phi x] and K^2 = phi phi^T - |phi|^2 I."""
    x, y, z = phi
    a2 = x * x + y * y + z * z
    return (c0 + c2 * (x * x - a2), -c1 * z + c2 * x * y, c1 * y + c2 * x * z,
            c1 * z + c2 * x * y, c0 + c2 * (y * y - a2), -c1 * x + c2 * y * z,
            -c1 * y + c2 * x * z, c1 * x + c2 * y * z, c0 + c2 * (z * z - a2))


def _so3_integrals(phi: tuple) -> tuple:
    """exp([phi x]) and its first and second integrals Gamma1, Gamma2 (see ``ctra_increments``).

    exp = I + sin a/a K + (1-cos a)/a^2 K^2 (Rodrigues);
    Gamma1 = int_0^1 exp(s K) ds = I + (1-cos a)/a^2 K + (a - sin a)/a^3 K^2;
    Gamma2 = int_0^1 int_0^s exp(u K) du ds = I/2 + (a - sin a)/a^3 K + (a^2/2 + cos a - 1)/a^4 K^2;
    a = |phi|. Gamma1 is the left Jacobian of SO(3) (Barfoot, *State Estimation for Robotics*,
    2017, ch. 7); Gamma2 = int_0^1 (1 - s) exp(s K) ds follows from the same Rodrigues series
    (the same integrals appear in IMU preintegration, Forster et al., IEEE T-RO 2017).
    Taylor series below a = 1e-4.
    """
    a2 = phi[0] * phi[0] + phi[1] * phi[1] + phi[2] * phi[2]
    if a2 < 1e-8:
        e1, e2 = 1.0 - a2 / 6.0, 0.5 - a2 / 24.0
        c1, c2 = 0.5 - a2 / 24.0, 1.0 / 6.0 - a2 / 120.0
        d2 = 1.0 / 24.0 - a2 / 720.0
    else:
        a = math.sqrt(a2)
        s, c = math.sin(a), math.cos(a)
        e1, e2 = s / a, (1.0 - c) / a2
        c1, c2 = (1.0 - c) / a2, (a - s) / (a2 * a)
        d2 = (0.5 * a2 + c - 1.0) / (a2 * a2)
    return _poly_so3(phi, 1.0, e1, e2), _poly_so3(phi, 1.0, c1, c2), _poly_so3(phi, 0.5, c2, d2)


def _tup(a: Any) -> tuple | list:
    """Plain-float sequence of a vector (tuples pass through: the fast path's own values)."""
    t = type(a)
    if t is tuple:
        return a
    if t is np.ndarray:
        return a.tolist()
    return tuple(a.tolist()) if isinstance(a, np.ndarray) else tuple(float(x) for x in a)


def _lla_of(state: Any) -> tuple:
    if hasattr(state, "lat_rad"):
        return float(state.lat_rad), float(state.lon_rad), float(state.height_m)
    return _tup(state.lla)


# ----------------------------------------------------------------------------- CTRA prediction

def ctra_increments(v_ned_mps: np.ndarray, C_nb: np.ndarray, acc_body_mps2: np.ndarray,
                    rate_body_rps: np.ndarray, dt_s: float) -> tuple:
    """Exact motion over dt_s with constant body angular rate w and constant body acceleration a.

    C_nb(t) = C_nb exp([w t x]);  v(t) = v + C_nb Gamma1(w t) a t;  r(t) = r + v t + C_nb Gamma2(w t) a t^2
    (Gamma1/2: ``_so3_integrals``). Returns (dr_ned_m, v_ned_new_mps, C_nb_new) as numpy arrays.
    Uniform circular motion (a = w x v_b) is reproduced exactly; Earth rate and transport rate are
    neglected (< 1e-5 rad over 0.2 s).
    """
    C = _tup(np.asarray(C_nb, dtype=float).reshape(9))
    dr, v_new, C_new, _, _ = _ctra(_tup(v_ned_mps), C, _tup(acc_body_mps2), _tup(rate_body_rps), float(dt_s))
    return np.array(dr), np.array(v_new), np.array(C_new).reshape(3, 3)


def _ctra(v: tuple, C: tuple, a: tuple, w: tuple, dt: float) -> tuple:
    E, G1, G2 = _so3_integrals((w[0] * dt, w[1] * dt, w[2] * dt))
    dv = _mv(C, _mv(G1, a))
    dr_a = _mv(C, _mv(G2, a))
    dt2 = dt * dt
    s_r = (dr_a[0] * dt2, dr_a[1] * dt2, dr_a[2] * dt2)
    s_v = (dv[0] * dt, dv[1] * dt, dv[2] * dt)
    dr = (v[0] * dt + s_r[0], v[1] * dt + s_r[1], v[2] * dt + s_r[2])
    v_new = (v[0] + s_v[0], v[1] + s_v[1], v[2] + s_v[2])
    return dr, v_new, _mm(C, E), (s_r, s_v), (_mm(C, G1), _mm(C, G2))


def _skew_sandwich_diag(s: tuple, p: tuple) -> tuple:
    """diag([s x] diag(p) [s x]^T)."""
    return (s[2] * s[2] * p[1] + s[1] * s[1] * p[2], s[2] * s[2] * p[0] + s[0] * s[0] * p[2],
            s[1] * s[1] * p[0] + s[0] * s[0] * p[1])


def _row_sq(M: tuple) -> tuple:
    return (M[0] * M[0] + M[1] * M[1] + M[2] * M[2], M[3] * M[3] + M[4] * M[4] + M[5] * M[5],
            M[6] * M[6] + M[7] * M[7] + M[8] * M[8])


def _predict_core(msg: Any, dt: float, acc_sd_mps2: float, rate_sd_rps: float) -> tuple:
    """CTRA prediction and covariance of ``predict_state`` in plain floats:
    (lat, lon, h, v_ned, rpy, var_r, var_v, var_a)."""
    C = _dcm(*_tup(msg.rpy_rad))
    dr, v_new, C_new, (s_r, s_v), (CG1, CG2) = _ctra(_tup(msg.v_ned_mps), C, _tup(msg.acc_body_mps2),
                                                     _tup(msg.rate_body_rps), dt)
    lat, lon, h = _lla_of(msg)
    sl = math.sin(lat)
    w = 1.0 - E2 * sl * sl
    r_n = A_M / math.sqrt(w)
    r_m = r_n * (1.0 - E2) / w
    lat_new = lat + dr[0] / (r_m + h)
    lon_new = lon + dr[1] / ((r_n + h) * math.cos(lat))
    lon_new = (lon_new + math.pi) % (2.0 * math.pi) - math.pi

    p_r = tuple(x * x for x in _tup(msg.pos_sd_m))
    p_v = tuple(x * x for x in _tup(msg.vel_sd_mps))
    p_a = tuple(x * x for x in _tup(msg.att_sd_rad))
    qa, qw = acc_sd_mps2 * acc_sd_mps2, rate_sd_rps * rate_sd_rps * dt * dt
    sr, sv = _skew_sandwich_diag(s_r, p_a), _skew_sandwich_diag(s_v, p_a)
    gr, gv = _row_sq(CG2), _row_sq(CG1)
    dt2, dt4 = dt * dt, dt ** 4
    var_r = [p_r[i] + dt2 * p_v[i] + sr[i] + qa * dt4 * gr[i] for i in range(3)]
    var_v = [p_v[i] + sv[i] + qa * dt2 * gv[i] for i in range(3)]
    var_a = [p_a[i] + qw for i in range(3)]
    return lat_new, lon_new, h - dr[2], v_new, _euler(C_new), var_r, var_v, var_a


def predict_state(msg: Any, dt_s: float, acc_sd_mps2: float = DEFAULT_ACC_SD_MPS2,
                  rate_sd_rps: float = DEFAULT_RATE_SD_RPS) -> StateMessage:
    """Latency compensation: the target state predicted by dt_s [s] with CTRA (``ctra_increments``).

    Position is moved in the local-level frame at the target and converted back to geodetic with
    the curvilinear relation (Groves 2013 eq. 2.119; error < 1 um for displacements < 10 m).
    Covariance of the error state [dr_n, dv_n, psi_n] (block-diagonal from the message's sds) is
    propagated as P' = F P F^T + G Q G^T with
        F = [[I, I dt, -[C Gamma2 a dt^2 x]], [0, I, -[C Gamma1 a dt x]], [0, 0, I]],
        acceleration noise acc_sd_mps2 entering through (C Gamma2 dt^2, C Gamma1 dt, 0) and rate
        noise rate_sd_rps through (0, 0, C(t) dt); the returned sds are sqrt(diag P') (computed
        in closed form per block). Attitude sd (roll, pitch, yaw) is treated as the nav-frame
        attitude error (small tilt). The result keeps ids, fix, geometry; t_gps_s advances by dt_s;
        acceleration and rate are held constant. Works on a StateMessage or a NavState (e.g. to
        bring the master's own state to the current time) and returns the same type.
    """
    dt = float(dt_s)
    lat_new, lon_new, h_new, v_new, rpy_new, var_r, var_v, var_a = _predict_core(msg, dt, acc_sd_mps2, rate_sd_rps)
    out = type(msg).__new__(type(msg))
    out.__dict__.update(msg.__dict__)
    if isinstance(msg, StateMessage):
        out.t_gps_s = msg.t_gps_s + dt
        out.lat_rad, out.lon_rad, out.height_m = lat_new, lon_new, h_new
        out.signed_payload = None
    else:
        out.t_s = msg.t_s + dt
        out.lla = np.array((lat_new, lon_new, h_new))
    out.v_ned_mps = np.array(v_new)
    out.rpy_rad = np.array(rpy_new)
    out.pos_sd_m = np.sqrt(var_r)
    out.vel_sd_mps = np.sqrt(var_v)
    out.att_sd_rad = np.sqrt(var_a)
    return out


# ----------------------------------------------------------------------------- transform

def _target_outline(slave_state: Any, slave_points: Any) -> Geometry:
    if slave_points is None:
        g = getattr(slave_state, "geometry", None)
        return g if isinstance(g, Geometry) else Geometry()
    if isinstance(slave_points, Geometry):
        return slave_points
    pts = np.asarray(slave_points, dtype=float).reshape(-1, 3)
    return Geometry(kind="points", points_body_m=pts)


def _nearest_outline_point(Q: list, polygon: bool, px: float, py: float) -> tuple:
    """Nearest point to (px, py) on a point set or a closed polygon boundary (horizontal).

    Q: target outline points already in the master frame [(x, y), ...]. Returns
    (index_a, index_b, t, qx, qy, inside) with the nearest point = Q[a] + t (Q[b] - Q[a]);
    inside by the even-odd rule.
    """
    best = (math.inf, 0, 0, 0.0, Q[0][0], Q[0][1])
    n = len(Q)
    if not polygon:
        for i, (x, y) in enumerate(Q):
            d2 = (x - px) ** 2 + (y - py) ** 2
            if d2 < best[0]:
                best = (d2, i, i, 0.0, x, y)
        return best[1], best[2], best[3], best[4], best[5], False
    inside = False
    for i in range(n):
        ax, ay = Q[i]
        bx, by = Q[(i + 1) % n]
        ex, ey = bx - ax, by - ay
        L2 = ex * ex + ey * ey
        t = ((px - ax) * ex + (py - ay) * ey) / L2 if L2 > 0 else 0.0
        t = 0.0 if t < 0.0 else 1.0 if t > 1.0 else t
        qx, qy = ax + t * ex, ay + t * ey
        d2 = (qx - px) ** 2 + (qy - py) ** 2
        if d2 < best[0]:
            best = (d2, i, (i + 1) % n, t, qx, qy)
        if (ay > py) != (by > py) and ax + (py - ay) * ex / ey > px:
            inside = not inside
    return best[1], best[2], best[3], best[4], best[5], inside


def _t_of(state: Any) -> float:
    t = getattr(state, "t_gps_s", None)
    return float(state.t_s if t is None else t)


def relative_kinematics(master_state: Any, slave_state: Any, master_points: Any = None,
                        slave_points: Any = None) -> RelativeResult:
    """Target relative to the master, in the master body frame (see module docstring).

    master_points: the master measurement point (3,) in the master body frame [m] (default the
    reference point). slave_points: a Geometry or (N, 3) contact points in the target body frame
    (default ``slave_state.geometry``, else the reference point). The two states must be at the
    same time (compensate with ``predict_state`` first).

    Measurement-point outputs: d = nearest target point - master measurement point, projected on
    the master body x-y plane: longitudinal_m = d_x, lateral_m = d_y, gap_m = |d_xy| (0 inside a
    polygon or circle). The nearest point is a contact point, the nearest point on a polygon edge, or
    the circle edge (pedestrian radius). Its velocity relative to the master point in the master
    frame is u = v_rel_b + C_ms (w_s x p_s) - w_m x (C_ms p_s); closing_speed = -(d_xy . u_xy)/|d_xy|;
    ttc_s = gap / closing speed if closing speed > 1 mm/s else None.
    Position covariance: P_b = C_bn (P_s + P_m + [r_n x] Psi_m [r_n x]^T) C_nb (P_s, P_m position
    covariances, Psi_m master attitude-error covariance); range_sd_m = sqrt(u_n^T (...) u_n) with
    u_n the line-of-sight unit vector.
    """
    lat_m, lon_m, h_m = _lla_of(master_state)
    lat_s, lon_s, h_s = _lla_of(slave_state)
    C_en_m = _c_en(lat_m, lon_m)
    C_nm_ns = _mmt(C_en_m, _c_en(lat_s, lon_s))
    em, es = _ecef(lat_m, lon_m, h_m), _ecef(lat_s, lon_s, h_s)
    r_n = _mv(C_en_m, (es[0] - em[0], es[1] - em[1], es[2] - em[2]))

    C_nm = _dcm(*_tup(master_state.rpy_rad))
    C_ns = _mm(C_nm_ns, _dcm(*_tup(slave_state.rpy_rad)))
    C_ms = _mtm(C_nm, C_ns)
    w_m = _tup(master_state.rate_body_rps)
    w_s = _tup(slave_state.rate_body_rps)
    v_s = _mv(C_nm_ns, _tup(slave_state.v_ned_mps))
    v_m = _tup(master_state.v_ned_mps)

    r_b = _mtv(C_nm, r_n)
    dv_b = _mtv(C_nm, (v_s[0] - v_m[0], v_s[1] - v_m[1], v_s[2] - v_m[2]))
    wxr = _cross(w_m, r_b)
    v_rel = (dv_b[0] - wxr[0], dv_b[1] - wxr[1], dv_b[2] - wxr[2])
    a_s = _mv(C_ms, _tup(slave_state.acc_body_mps2))
    a_m = _tup(master_state.acc_body_mps2)
    cor = _cross(w_m, dv_b)
    cen = _cross(w_m, wxr)
    a_rel = tuple(a_s[i] - a_m[i] - 2.0 * cor[i] + cen[i] for i in range(3))

    rng = math.sqrt(r_b[0] ** 2 + r_b[1] ** 2 + r_b[2] ** 2)
    rho_ref = math.hypot(r_b[0], r_b[1])
    bearing = math.atan2(r_b[1], r_b[0])
    elevation = math.atan2(-r_b[2], rho_ref)

    # covariance in NED: D + [r x] Psi [r x]^T, then quadratic forms along the body axes
    ps, pm, pa = _tup(slave_state.pos_sd_m), _tup(master_state.pos_sd_m), _tup(master_state.att_sd_rad)
    x, y, z = r_n
    p0, p1, p2 = pa[0] ** 2, pa[1] ** 2, pa[2] ** 2
    Q = (ps[0] ** 2 + pm[0] ** 2 + z * z * p1 + y * y * p2, -x * y * p2, -x * z * p1,
         -x * y * p2, ps[1] ** 2 + pm[1] ** 2 + z * z * p0 + x * x * p2, -y * z * p0,
         -x * z * p1, -y * z * p0, ps[2] ** 2 + pm[2] ** 2 + y * y * p0 + x * x * p1)

    def quad(c: tuple) -> float:
        Qc = _mv(Q, c)
        return c[0] * Qc[0] + c[1] * Qc[1] + c[2] * Qc[2]

    pos_sd = tuple(math.sqrt(max(quad((C_nm[i], C_nm[3 + i], C_nm[6 + i])), 0.0)) for i in range(3))
    u_n = (x / rng, y / rng, z / rng) if rng > 0 else (C_nm[0], C_nm[3], C_nm[6])
    range_sd = math.sqrt(max(quad(u_n), 0.0))

    if master_points is None:
        p_m = (0.0, 0.0, 0.0)
    elif type(master_points) is tuple and len(master_points) == 3:
        p_m = master_points
    else:
        p_m = _tup(np.asarray(master_points, dtype=float).reshape(-1, 3)[0])
    outline = _target_outline(slave_state, slave_points)
    if outline.kind == "circle" or len(outline.points_body_m) == 0:
        dx, dy = r_b[0] - p_m[0], r_b[1] - p_m[1]
        rho = math.hypot(dx, dy)
        gap = max(rho - outline.radius_m, 0.0)
        scale = gap / rho if rho > 0 else 0.0
        d_xy = (dx * scale, dy * scale)
        u_pt = v_rel
    else:
        P_s = np.asarray(outline.points_body_m, dtype=float).tolist()
        Q_b = [_mv(C_ms, p) for p in P_s]
        ia, ib, t, qx, qy, inside = _nearest_outline_point(
            [(r_b[0] + q[0], r_b[1] + q[1]) for q in Q_b], outline.kind == "polygon", p_m[0], p_m[1])
        p_s = tuple(P_s[ia][k] + t * (P_s[ib][k] - P_s[ia][k]) for k in range(3))
        d_xy = (0.0, 0.0) if inside else (qx - p_m[0], qy - p_m[1])
        gap = math.hypot(d_xy[0], d_xy[1])
        spin = _mv(C_ms, _cross(w_s, p_s))
        drag = _cross(w_m, _mv(C_ms, p_s))
        u_pt = tuple(v_rel[k] + spin[k] - drag[k] for k in range(3))
    if gap > 0:
        closing = -(d_xy[0] * u_pt[0] + d_xy[1] * u_pt[1]) / gap
    else:
        closing = -(r_b[0] * u_pt[0] + r_b[1] * u_pt[1]) / max(rho_ref, 1e-9)
    ttc = gap / closing if closing > CLOSING_EPS_MPS else None

    return RelativeResult(
        target_id=str(getattr(slave_state, "vehicle_id", "")),
        target_kind=str(getattr(slave_state, "kind", "vehicle")),
        t_gps_s=_t_of(master_state),
        rel_pos_body_m=np.array(r_b), rel_pos_sd_m=np.array(pos_sd), rel_vel_body_mps=np.array(v_rel),
        rel_acc_body_mps2=np.array(a_rel), rel_rpy_rad=np.array(_euler(C_ms)), range_m=rng,
        range_sd_m=range_sd, bearing_rad=bearing, elevation_rad=elevation, longitudinal_m=float(d_xy[0]),
        lateral_m=float(d_xy[1]), gap_m=gap, closing_speed_mps=closing, ttc_s=ttc)


def _point3(point: Any) -> np.ndarray:
    if point is None:
        return np.zeros(3)
    if type(point) is np.ndarray and point.shape == (3,) and point.dtype == np.float64:
        return point
    return np.array(np.asarray(point, dtype=float).reshape(-1, 3)[0])


def _evaluate_compiled(*args: Any) -> RelativeResult:
    """``relative_jit.evaluate_compiled`` (imported on first use: numba compiles or loads its cache)."""
    global _evaluate_compiled
    from v2xpos.relative_jit import evaluate_compiled
    _evaluate_compiled = evaluate_compiled
    return evaluate_compiled(*args)


def relative_yaw_sd(master_att_sd_rad: Any, slave_att_sd_rad: Any, dt_s: float = 0.0,
                    rate_sd_rps: float = DEFAULT_RATE_SD_RPS) -> float:
    """1-sigma of the relative yaw d_yaw = yaw_target - yaw_master [rad] (first version).

    The two filters' yaw errors are taken as independent and the target's yaw is predicted over
    ``dt_s`` with the rate noise of ``predict_state`` (var grows by (rate_sd_rps dt)^2):
        sd = sqrt(sd_yaw_m^2 + sd_yaw_s^2 + (rate_sd_rps dt)^2).
    Exact for level vehicles (d_yaw of operator T is the yaw difference when roll = pitch = 0);
    the roll/pitch coupling at large tilt and any master-target error correlation are neglected.
    """
    m, s = float(master_att_sd_rad[2]), float(slave_att_sd_rad[2])
    q = rate_sd_rps * dt_s
    return math.sqrt(m * m + s * s + q * q)


def evaluate_target(master_state: Any, slave_msg: StateMessage, master_point: Any = None,
                    timeout_s: float = DEFAULT_TIMEOUT_S,
                    future_tolerance_s: float = DEFAULT_FUTURE_TOLERANCE_S,
                    compensate: bool = True, acc_sd_mps2: float = DEFAULT_ACC_SD_MPS2,
                    rate_sd_rps: float = DEFAULT_RATE_SD_RPS) -> RelativeResult:
    """One target update: fix gate -> staleness -> CTRA compensation to the master time -> transform.

    Returns a RelativeResult with target_id/kind/source_seq/latency_s/t_sent_wall_s filled, and on
    every status ``master_fix`` / ``target_fix`` (the two states' fix status); for FIX_INVALID (with
    fix_side), TIMEOUT and FUTURE the kinematic fields are NaN (no output from that message).
    With kinematics, ``rel_yaw_sd_rad`` comes from ``relative_yaw_sd`` over the compensated latency.
    ``compensate=False`` transforms the unpredicted message (for comparisons).
    The compensated path runs the compiled kernel ``v2xpos.relative_jit`` (same equations as
    ``predict_state`` + ``relative_kinematics``, agreement to ~1e-13 tested).
    The caller fills fleet, master_id, seq and degraded.
    """
    t_m = _t_of(master_state)
    master_fix, slave_fix = FixStatus(master_state.fix), FixStatus(slave_msg.fix)
    side = fix_failed_side(master_fix, slave_fix)
    status, latency_s = check_latency(t_m, slave_msg.t_gps_s, timeout_s, future_tolerance_s)
    if side != FixSide.NONE:
        status = TargetStatus.FIX_INVALID
    if status != TargetStatus.VALID:
        return RelativeResult(target_id=slave_msg.vehicle_id, target_kind=slave_msg.kind, status=status,
                              fix_side=side, source_seq=slave_msg.seq, t_gps_s=t_m, latency_s=latency_s,
                              t_sent_wall_s=slave_msg.t_sent_wall_s, master_fix=master_fix, target_fix=slave_fix)
    if compensate:
        res = _evaluate_compiled(master_state, slave_msg, latency_s, _point3(master_point), acc_sd_mps2,
                                 rate_sd_rps, t_m)
    else:
        res = relative_kinematics(master_state, slave_msg, master_point)
    res.source_seq = slave_msg.seq
    res.latency_s = latency_s
    res.t_sent_wall_s = slave_msg.t_sent_wall_s
    res.master_fix = master_fix
    res.target_fix = slave_fix
    res.rel_yaw_sd_rad = relative_yaw_sd(master_state.att_sd_rad, slave_msg.att_sd_rad,
                                         latency_s if compensate else 0.0, rate_sd_rps)
    return res
