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

This module is the readable reference, written on ``geo`` and ``rotation``; the master's message
path runs the compiled kernel of the same equations (``relative_jit`` on ``kernels``), checked
against it by ``tests/test_relative_fastpath.py``.
"""
from __future__ import annotations

import math
from typing import Any

import numpy as np

from v2xpos import geo
from v2xpos.rotation import dcm_from_euler, euler_from_dcm, skew, so3_integrals
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


# ----------------------------------------------------------------------------- inputs

def _vec3(a: Any) -> np.ndarray:
    """A 3-vector as a float array."""
    return np.asarray(a, dtype=float).reshape(3)


def _lla_of(state: Any) -> np.ndarray:
    """(lat_rad, lon_rad, h_m) of a StateMessage (separate fields) or a NavState (``lla``)."""
    if hasattr(state, "lat_rad"):
        return np.array((float(state.lat_rad), float(state.lon_rad), float(state.height_m)))
    return _vec3(state.lla)


# ----------------------------------------------------------------------------- CTRA prediction

def ctra_increments(v_ned_mps: np.ndarray, C_nb: np.ndarray, acc_body_mps2: np.ndarray,
                    rate_body_rps: np.ndarray, dt_s: float) -> tuple:
    """Exact motion over dt_s with constant body angular rate w and constant body acceleration a.

    C_nb(t) = C_nb exp([w t x]);  v(t) = v + C_nb Gamma1(w t) a t;  r(t) = r + v t + C_nb Gamma2(w t) a t^2
    (Gamma1/2: ``rotation.so3_integrals``). Returns (dr_ned_m, v_ned_new_mps, C_nb_new).
    Uniform circular motion (a = w x v_b) is reproduced exactly; Earth rate and transport rate are
    neglected (< 1e-5 rad over 0.2 s).
    """
    dr, v_new, C_new, _, _ = _ctra(_vec3(v_ned_mps), np.asarray(C_nb, dtype=float).reshape(3, 3),
                                   _vec3(acc_body_mps2), _vec3(rate_body_rps), float(dt_s))
    return dr, v_new, C_new


def _ctra(v: np.ndarray, C: np.ndarray, a: np.ndarray, w: np.ndarray, dt: float) -> tuple:
    """``ctra_increments`` plus the acceleration terms (s_r, s_v) = (C Gamma2 a dt^2, C Gamma1 a dt)
    and the matrices (C Gamma1, C Gamma2) that the covariance propagation needs."""
    E, G1, G2 = so3_integrals(w * dt)
    s_r = C @ (G2 @ a) * (dt * dt)
    s_v = C @ (G1 @ a) * dt
    return v * dt + s_r, v + s_v, C @ E, (s_r, s_v), (C @ G1, C @ G2)


def _predict_core(msg: Any, dt: float, acc_sd_mps2: float, rate_sd_rps: float) -> tuple:
    """CTRA prediction and covariance of ``predict_state``:
    (lat, lon, h, v_ned, rpy, var_r, var_v, var_a)."""
    C = dcm_from_euler(*_vec3(msg.rpy_rad))
    dr, v_new, C_new, (s_r, s_v), (CG1, CG2) = _ctra(_vec3(msg.v_ned_mps), C, _vec3(msg.acc_body_mps2),
                                                     _vec3(msg.rate_body_rps), dt)
    lat, lon, h = _lla_of(msg)
    r_m, r_n = geo.radii_m(lat)
    lat_new = lat + dr[0] / (r_m + h)
    lon_new = lon + dr[1] / ((r_n + h) * math.cos(lat))
    lon_new = (lon_new + math.pi) % (2.0 * math.pi) - math.pi

    p_r, p_v, p_a = _vec3(msg.pos_sd_m) ** 2, _vec3(msg.vel_sd_mps) ** 2, _vec3(msg.att_sd_rad) ** 2
    # diagonals of F P F^T + G Q G^T, block by block (see predict_state)
    S_r, S_v = skew(s_r), skew(s_v)
    var_r = (p_r + dt * dt * p_v + np.diag(S_r @ np.diag(p_a) @ S_r.T)
             + acc_sd_mps2 ** 2 * dt ** 4 * np.sum(CG2 ** 2, axis=1))
    var_v = p_v + np.diag(S_v @ np.diag(p_a) @ S_v.T) + acc_sd_mps2 ** 2 * dt * dt * np.sum(CG1 ** 2, axis=1)
    var_a = p_a + (rate_sd_rps * dt) ** 2
    return lat_new, lon_new, h - dr[2], v_new, euler_from_dcm(C_new), var_r, var_v, var_a


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


def _nearest_outline_point(Q: np.ndarray, polygon: bool, p: np.ndarray) -> tuple:
    """Nearest point to p (2,) on a point set or a closed polygon boundary (horizontal).

    Q: (n, 2) target outline points already in the master frame. Returns (index_a, index_b, t,
    nearest (2,), inside) with nearest = Q[a] + t (Q[b] - Q[a]), the first of equally near ones;
    inside by the even-odd rule (a ray from p towards +x crosses the boundary an odd number of times).
    """
    if not polygon:
        d2 = np.sum((Q - p) ** 2, axis=1)
        i = int(np.argmin(d2))
        return i, i, 0.0, Q[i], False
    B = np.roll(Q, -1, axis=0)                    # edge k runs from Q[k] to Q[k + 1]
    E = B - Q
    L2 = np.sum(E ** 2, axis=1)
    t = np.clip(np.where(L2 > 0, np.sum((p - Q) * E, axis=1) / np.where(L2 > 0, L2, 1.0), 0.0), 0.0, 1.0)
    nearest = Q + t[:, None] * E
    i = int(np.argmin(np.sum((nearest - p) ** 2, axis=1)))
    straddles = (Q[:, 1] > p[1]) != (B[:, 1] > p[1])
    x_cross = Q[:, 0] + (p[1] - Q[:, 1]) * E[:, 0] / np.where(straddles, E[:, 1], 1.0)
    inside = bool(np.count_nonzero(straddles & (x_cross > p[0])) % 2)
    return i, (i + 1) % len(Q), float(t[i]), nearest[i], inside


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
    lla_m, lla_s = _lla_of(master_state), _lla_of(slave_state)
    C_en_m = geo.dcm_ecef_to_ned(lla_m[0], lla_m[1])
    C_nm_ns = C_en_m @ geo.dcm_ecef_to_ned(lla_s[0], lla_s[1]).T      # target NED -> master NED
    r_n = C_en_m @ (geo.lla_to_ecef(lla_s) - geo.lla_to_ecef(lla_m))

    C_nm = dcm_from_euler(*_vec3(master_state.rpy_rad))
    C_ns = C_nm_ns @ dcm_from_euler(*_vec3(slave_state.rpy_rad))
    C_ms = C_nm.T @ C_ns
    w_m, w_s = _vec3(master_state.rate_body_rps), _vec3(slave_state.rate_body_rps)
    dv_b = C_nm.T @ (C_nm_ns @ _vec3(slave_state.v_ned_mps) - _vec3(master_state.v_ned_mps))

    r_b = C_nm.T @ r_n
    wxr = np.cross(w_m, r_b)
    v_rel = dv_b - wxr
    a_rel = (C_ms @ _vec3(slave_state.acc_body_mps2) - _vec3(master_state.acc_body_mps2)
             - 2.0 * np.cross(w_m, dv_b) + np.cross(w_m, wxr))

    rng = float(np.linalg.norm(r_b))
    rho_ref = math.hypot(r_b[0], r_b[1])
    bearing = math.atan2(r_b[1], r_b[0])
    elevation = math.atan2(-r_b[2], rho_ref)

    # position covariance in NED: P_s + P_m + [r x] Psi_m [r x]^T, then along the body axes
    S = skew(r_n)
    Q = (np.diag(_vec3(slave_state.pos_sd_m) ** 2 + _vec3(master_state.pos_sd_m) ** 2)
         + S @ np.diag(_vec3(master_state.att_sd_rad) ** 2) @ S.T)
    pos_sd = np.sqrt(np.maximum(np.diag(C_nm.T @ Q @ C_nm), 0.0))
    u_n = r_n / rng if rng > 0 else C_nm[:, 0]
    range_sd = math.sqrt(max(float(u_n @ Q @ u_n), 0.0))

    p_m = _point3(master_points)
    outline = _target_outline(slave_state, slave_points)
    if outline.kind == "circle" or len(outline.points_body_m) == 0:
        dx, dy = r_b[0] - p_m[0], r_b[1] - p_m[1]
        rho = math.hypot(dx, dy)
        gap = max(rho - outline.radius_m, 0.0)
        scale = gap / rho if rho > 0 else 0.0
        d_xy = (dx * scale, dy * scale)
        u_pt = v_rel
    else:
        P_s = np.asarray(outline.points_body_m, dtype=float).reshape(-1, 3)
        Q_b = P_s @ C_ms.T + r_b                  # outline points relative to the master, master body
        ia, ib, t, q, inside = _nearest_outline_point(Q_b[:, :2], outline.kind == "polygon", p_m[:2])
        p_s = P_s[ia] + t * (P_s[ib] - P_s[ia])
        d_xy = (0.0, 0.0) if inside else (float(q[0] - p_m[0]), float(q[1] - p_m[1]))
        gap = math.hypot(d_xy[0], d_xy[1])
        u_pt = v_rel + C_ms @ np.cross(w_s, p_s) - np.cross(w_m, C_ms @ p_s)
    if gap > 0:
        closing = -(d_xy[0] * u_pt[0] + d_xy[1] * u_pt[1]) / gap
    else:
        closing = -(r_b[0] * u_pt[0] + r_b[1] * u_pt[1]) / max(rho_ref, 1e-9)
    closing = float(closing)
    ttc = gap / closing if closing > CLOSING_EPS_MPS else None

    return RelativeResult(
        target_id=str(getattr(slave_state, "vehicle_id", "")),
        target_kind=str(getattr(slave_state, "kind", "vehicle")),
        t_gps_s=_t_of(master_state),
        rel_pos_body_m=r_b, rel_pos_sd_m=pos_sd, rel_vel_body_mps=v_rel,
        rel_acc_body_mps2=a_rel, rel_rpy_rad=euler_from_dcm(C_ms), range_m=rng,
        range_sd_m=range_sd, bearing_rad=bearing, elevation_rad=elevation, longitudinal_m=float(d_xy[0]),
        lateral_m=float(d_xy[1]), gap_m=float(gap), closing_speed_mps=closing, ttc_s=ttc)


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
