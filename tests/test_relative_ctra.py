"""CTRA latency compensation against exact circular-arc truth, and the gating/staleness rules."""
import math

import numpy as np
import pytest

from v2xpos.geo import lla_to_ned
from v2xpos.relative import (FixSide, TargetStatus, check_latency, evaluate_target, fix_failed_side,
                             gate_fix_status, predict_state, relative_kinematics)
from v2xpos.types import FixStatus
from v2xpos.wire import Geometry, StateMessage

LLA0 = np.array([math.radians(39.75), math.radians(-105.2), 1650.0])
V0, W = 20.0, 0.3


def arc_truth(t: float, brake_mps2: float, psi0: float = 0.4) -> tuple:
    """Exact state on a constant-yaw-rate arc with constant deceleration (integrated on a fine grid).

    Returns (north_m, east_m, yaw_rad, speed_mps) after t seconds from the origin.
    """
    ts = np.linspace(0.0, t, 200001)
    psi = psi0 + W * ts
    sp = V0 - brake_mps2 * ts
    dt = ts[1] - ts[0]
    vn, ve = sp * np.cos(psi), sp * np.sin(psi)
    n = dt * (vn.sum() - 0.5 * (vn[0] + vn[-1]))
    e = dt * (ve.sum() - 0.5 * (ve[0] + ve[-1]))
    return n, e, psi[-1], sp[-1]


def target_at_origin(brake_mps2: float, psi0: float = 0.4, fix=FixStatus.FIXED, t=5000.0) -> StateMessage:
    return StateMessage(fleet="t", vehicle_id="tgt", seq=9, t_gps_s=t, fix=fix, lat_rad=LLA0[0], lon_rad=LLA0[1],
                        height_m=LLA0[2], v_ned_mps=np.array([V0 * math.cos(psi0), V0 * math.sin(psi0), 0.0]),
                        acc_body_mps2=np.array([-brake_mps2, W * V0, 0.0]), rate_body_rps=np.array([0, 0, W]),
                        rpy_rad=np.array([0.0, 0.0, psi0]), pos_sd_m=np.full(3, 0.01),
                        vel_sd_mps=np.full(3, 0.02), att_sd_rad=np.full(3, 0.002),
                        geometry=Geometry.box(3.8, 1.0, 0.9))


@pytest.mark.parametrize("brake", [0.0, 4.0])
@pytest.mark.parametrize("dt", [0.1, 0.2])
def test_ctra_prediction_on_turning_braking_target(brake, dt):
    msg = target_at_origin(brake)
    pred = predict_state(msg, dt)
    n, e, psi, sp = arc_truth(dt, brake)
    err_m = np.linalg.norm(lla_to_ned(pred.lla, LLA0) - [n, e, 0.0])
    limit = 0.01 if dt <= 0.1 else 0.02
    assert err_m < limit, f"prediction error {err_m:.4f} m after {dt} s"
    assert abs(pred.rpy_rad[2] - psi) < 1e-9
    np.testing.assert_allclose(pred.v_ned_mps[:2], [sp * math.cos(psi), sp * math.sin(psi)], atol=0.05)
    assert pred.t_gps_s == pytest.approx(msg.t_gps_s + dt)
    # the uncompensated position is wrong by about speed x latency
    assert np.linalg.norm(lla_to_ned(msg.lla, LLA0) - [n, e, 0.0]) > 0.9 * V0 * dt


def test_constant_turn_is_exact():
    pred = predict_state(target_at_origin(0.0), 0.1)
    n, e, _, _ = arc_truth(0.1, 0.0)
    assert np.linalg.norm(lla_to_ned(pred.lla, LLA0)[:2] - [n, e]) < 1e-5


def test_prediction_covariance_grows_with_velocity_and_acceleration_sd():
    msg = target_at_origin(0.0)
    p1, p2 = predict_state(msg, 0.1), predict_state(msg, 0.2)
    assert np.all(p2.pos_sd_m > p1.pos_sd_m) and np.all(p1.pos_sd_m > msg.pos_sd_m)
    # velocity sd 0.02 over 0.2 s adds at least 4 mm in quadrature
    assert p2.pos_sd_m[0] >= math.hypot(0.01, 0.02 * 0.2) - 1e-9
    noisy = predict_state(msg, 0.2, acc_sd_mps2=2.0)
    assert noisy.pos_sd_m[0] > p2.pos_sd_m[0]
    back = predict_state(p2, 0.0)
    np.testing.assert_allclose(back.pos_sd_m, p2.pos_sd_m)


def test_evaluate_target_compensates_latency():
    """Master parked 30 m from the arc; the 100 ms old target message is compensated to < 1 cm."""
    latency = 0.1
    tgt = target_at_origin(4.0, t=5000.0)
    n, e, psi, sp = arc_truth(latency, 4.0)
    master = StateMessage(fleet="t", vehicle_id="m", seq=1, t_gps_s=5000.0 + latency, fix=FixStatus.FLOAT,
                          lat_rad=LLA0[0] - 30.0 / 6.37e6, lon_rad=LLA0[1], height_m=LLA0[2],
                          v_ned_mps=np.zeros(3), acc_body_mps2=np.zeros(3), rate_body_rps=np.zeros(3),
                          rpy_rad=np.zeros(3), pos_sd_m=np.full(3, 0.01), vel_sd_mps=np.full(3, 0.01),
                          att_sd_rad=np.full(3, 0.001))
    truth_now = predict_state(tgt, 0.0)
    from v2xpos.geo import ned_to_lla
    truth_now.lat_rad, truth_now.lon_rad, truth_now.height_m = ned_to_lla(np.array([n, e, 0.0]), LLA0)
    truth_rel = relative_kinematics(master, truth_now).rel_pos_body_m
    res = evaluate_target(master, tgt)
    assert res.status == TargetStatus.VALID and res.latency_s == pytest.approx(latency)
    assert np.linalg.norm(res.rel_pos_body_m - truth_rel) < 0.01
    raw = evaluate_target(master, tgt, compensate=False)
    assert np.linalg.norm(raw.rel_pos_body_m - truth_rel) > 1.5
    assert res.source_seq == 9 and res.target_id == "tgt"


def test_gate_truth_table():
    for m in FixStatus:
        for s in FixStatus:
            status = gate_fix_status(m, s)
            side = fix_failed_side(m, s)
            both_rtk = m in (FixStatus.FIXED, FixStatus.FLOAT) and s in (FixStatus.FIXED, FixStatus.FLOAT)
            assert (status == TargetStatus.VALID) == both_rtk
            assert (status == TargetStatus.FIX_INVALID) == (not both_rtk)
            assert bool(side & FixSide.MASTER) == (m not in (FixStatus.FIXED, FixStatus.FLOAT))
            assert bool(side & FixSide.SLAVE) == (s not in (FixStatus.FIXED, FixStatus.FLOAT))


def test_latency_timeout_and_future():
    assert check_latency(100.15, 100.0) == (TargetStatus.VALID, pytest.approx(0.15))
    assert check_latency(100.25, 100.0)[0] == TargetStatus.TIMEOUT
    assert check_latency(100.25, 100.0, timeout_s=0.3)[0] == TargetStatus.VALID
    assert check_latency(100.0, 100.01)[0] == TargetStatus.VALID
    status, lat = check_latency(100.0, 100.5)
    assert status == TargetStatus.FUTURE and lat == pytest.approx(-0.5)


@pytest.mark.parametrize("m_fix,s_fix,t_master,expect,side", [
    (FixStatus.FIXED, FixStatus.SINGLE, 5000.05, TargetStatus.FIX_INVALID, FixSide.SLAVE),
    (FixStatus.DGPS, FixStatus.FIXED, 5000.05, TargetStatus.FIX_INVALID, FixSide.MASTER),
    (FixStatus.NONE, FixStatus.DEAD_RECKONING, 5000.05, TargetStatus.FIX_INVALID, FixSide.MASTER | FixSide.SLAVE),
    (FixStatus.FIXED, FixStatus.FLOAT, 5000.35, TargetStatus.TIMEOUT, FixSide.NONE),
    (FixStatus.FIXED, FixStatus.FIXED, 4999.0, TargetStatus.FUTURE, FixSide.NONE),
])
def test_evaluate_target_statuses_carry_no_kinematics(m_fix, s_fix, t_master, expect, side):
    tgt = target_at_origin(0.0, fix=s_fix)
    master = target_at_origin(0.0, fix=m_fix, t=t_master)
    res = evaluate_target(master, tgt)
    assert res.status == expect and res.fix_side == side
    assert not res.has_kinematics and math.isnan(res.range_m) and res.ttc_s is None
    assert math.isfinite(res.latency_s)


def test_closed_form_covariance_equals_full_9x9_propagation():
    """sqrt(diag(F P F^T + G Q G^T)) of the full error-state model equals predict_state's sds."""
    from v2xpos.rotation import dcm_from_euler, exp_so3, skew
    msg = target_at_origin(3.0)
    msg.rpy_rad = np.array([0.05, -0.03, 0.4])
    msg.rate_body_rps = np.array([0.02, -0.05, 0.3])
    msg.att_sd_rad = np.array([0.003, 0.004, 0.01])
    dt, sa, sw = 0.15, 0.7, 0.03
    C = dcm_from_euler(*msg.rpy_rad)
    # Gamma integrals by numerical quadrature (independent of the closed form)
    s = np.linspace(0.0, 1.0, 4001)
    E = np.array([exp_so3(msg.rate_body_rps * dt * x) for x in s])
    G1 = np.trapezoid(E, s, axis=0)
    G2 = np.trapezoid(E * (1.0 - s)[:, None, None], s, axis=0)
    a = msg.acc_body_mps2
    F = np.eye(9)
    F[0:3, 3:6] = np.eye(3) * dt
    F[0:3, 6:9] = -skew(C @ G2 @ a * dt * dt)
    F[3:6, 6:9] = -skew(C @ G1 @ a * dt)
    P = np.diag(np.concatenate([msg.pos_sd_m, msg.vel_sd_mps, msg.att_sd_rad]) ** 2)
    Ga = np.vstack([C @ G2 * dt * dt, C @ G1 * dt, np.zeros((3, 3))])
    Gw = np.vstack([np.zeros((6, 3)), C @ exp_so3(msg.rate_body_rps * dt) * dt])
    P = F @ P @ F.T + sa ** 2 * Ga @ Ga.T + sw ** 2 * Gw @ Gw.T
    pred = predict_state(msg, dt, acc_sd_mps2=sa, rate_sd_rps=sw)
    np.testing.assert_allclose(np.concatenate([pred.pos_sd_m, pred.vel_sd_mps, pred.att_sd_rad]),
                               np.sqrt(np.diag(P)), rtol=1e-6)


def test_predict_nav_state_same_as_message():
    msg = target_at_origin(2.0)
    nav = msg.to_nav_state()
    p_msg, p_nav = predict_state(msg, 0.1), predict_state(nav, 0.1)
    assert type(p_nav) is type(nav) and p_nav.t_s == pytest.approx(msg.t_gps_s + 0.1)
    np.testing.assert_allclose(p_nav.lla, p_msg.lla, rtol=0, atol=1e-12)
    np.testing.assert_allclose(p_nav.pos_sd_m, p_msg.pos_sd_m)
    np.testing.assert_allclose(nav.lla, msg.lla)      # input untouched
