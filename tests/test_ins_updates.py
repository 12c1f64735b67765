"""The measurement models of ``v2xpos.ins.updates`` against measurements built independently.

For each model: a true state, the measurement it gives (positions through ECEF with
``geo.ned_to_lla``, not the models' curvilinear increments), and an estimate off the truth by a
small error dx (est minus truth, the filter's convention: C_est = exp(-[phi x]) C_true,
b_est = b_true + db, ...). The model's residual d = h(x_est) - z must then be H dx to first order:
a wrong sign or a missing block in H leaves a residual of the size of that block's H dx, ten to a
hundred times the tolerance (the second-order terms).
"""
from __future__ import annotations

import numpy as np
import pytest

from v2xpos import geo
from v2xpos.ins import ATT, BA, BG, POS, VEL, StateLayout
from v2xpos.ins import updates
from v2xpos.rotation import dcm_from_euler, exp_so3

LAYOUT = StateLayout.build(("lever_arm", "imu_time_offset", "gnss_latency", "gnss_vel_latency", "misalignment",
                            "odometer_scale"))
LLA = np.array([0.7, 0.2, 300.0])
C_NB = dcm_from_euler(0.02, -0.03, 1.1)
LEVER_M = np.array([0.5, -0.3, -1.2])
V_NED = np.array([8.0, 5.0, 0.2])
ACC_NED = np.array([0.5, -0.3, 0.1])
RATE_B = np.array([0.01, -0.02, 0.3])
GAP_S = 0.05


def _error(**blocks) -> np.ndarray:
    """Error-state vector with the named blocks (``pos``, ``att``, effect names, ...) set."""
    dx = np.zeros(LAYOUT.n)
    base = {"pos": POS, "vel": VEL, "att": ATT, "bg": BG, "ba": BA}
    for name, value in blocks.items():
        i = base[name] if name in base else LAYOUT.at(name)
        value = np.atleast_1d(value)
        dx[i:i + len(value)] = value
    return dx


def _estimate_lla(dr_ned_m: np.ndarray) -> np.ndarray:
    """The geodetic point whose position error against LLA is dr_ned_m (est minus truth)."""
    r_m, r_n = geo.radii_m(LLA[0])
    return LLA + np.array([dr_ned_m[0] / (r_m + LLA[2]), dr_ned_m[1] / ((r_n + LLA[2]) * np.cos(LLA[0])),
                           -dr_ned_m[2]])


def test_gnss_position_residual_is_h_times_the_error():
    z_lla = geo.ned_to_lla(C_NB @ LEVER_M + V_NED * GAP_S, LLA)
    dx = _error(pos=[0.3, -0.2, 0.1], att=[2e-3, -1e-3, 3e-3], lever_arm=[0.02, -0.01, 0.03],
                imu_time_offset=0.01, gnss_latency=0.004)
    C_est = exp_so3(-dx[ATT:ATT + 3]) @ C_NB
    gap_est = GAP_S - dx[LAYOUT.at("imu_time_offset")] - dx[LAYOUT.at("gnss_latency")]
    m = updates.gnss_position(LAYOUT, _estimate_lla(dx[POS:POS + 3]), C_est, LEVER_M + dx[LAYOUT.at("lever_arm"):][:3],
                              V_NED, gap_est, z_lla, np.full(3, 0.02), 0.01, timing=True)
    assert np.abs(m.H @ dx).max() > 0.1
    np.testing.assert_allclose(m.d, m.H @ dx, atol=2e-3)
    np.testing.assert_allclose(np.sqrt(np.diag(m.R)), [0.02, 0.02, 0.02])


def test_gnss_position_without_timing_leaves_the_timing_states_out():
    m = updates.gnss_position(LAYOUT, LLA, C_NB, LEVER_M, V_NED, GAP_S, LLA, np.full(3, 0.001), 0.01, timing=False)
    assert not m.H[:, LAYOUT.at("imu_time_offset")].any() and not m.H[:, LAYOUT.at("gnss_latency")].any()
    np.testing.assert_allclose(np.sqrt(np.diag(m.R)), [0.01, 0.01, 0.01])   # the floor


def test_gnss_velocity_residual_is_h_times_the_error():
    vel_latency_s = 0.02
    z = V_NED + C_NB @ np.cross(RATE_B, LEVER_M) + ACC_NED * (GAP_S - vel_latency_s)
    dx = _error(vel=[0.05, -0.03, 0.02], att=[2e-3, -1e-3, 3e-3], bg=[1e-3, -2e-3, 1.5e-3],
                lever_arm=[0.02, -0.01, 0.03], imu_time_offset=0.01, gnss_vel_latency=0.01)
    C_est = exp_so3(-dx[ATT:ATT + 3]) @ C_NB
    m = updates.gnss_velocity(LAYOUT, C_est, LEVER_M + dx[LAYOUT.at("lever_arm"):][:3], RATE_B - dx[BG:BG + 3],
                              V_NED + dx[VEL:VEL + 3], ACC_NED, GAP_S - dx[LAYOUT.at("imu_time_offset")],
                              vel_latency_s + dx[LAYOUT.at("gnss_vel_latency")], z, np.full(3, 0.05), 0.03,
                              timing=True)
    assert np.abs(m.H @ dx).max() > 0.02
    np.testing.assert_allclose(m.d, m.H @ dx, atol=5e-4)


@pytest.mark.parametrize("mis_rad", [np.zeros(3), np.array([0.01, -0.02, 0.015])])
def test_nhc_and_odometer_residuals_are_h_times_the_error(mis_rad):
    R_vb = dcm_from_euler(*mis_rad)
    v_true = C_NB @ R_vb.T @ np.array([10.0, 0.0, 0.0])   # a car: no lateral or vertical velocity
    scale = 0.02
    speed = (1 + scale) * (R_vb @ C_NB.T @ (v_true + ACC_NED * GAP_S))[0]
    dx = _error(vel=[0.05, -0.03, 0.02], att=[2e-3, -1e-3, 3e-3], misalignment=[1e-3, -2e-3, 1.5e-3],
                odometer_scale=0.01)
    C_est = exp_so3(-dx[ATT:ATT + 3]) @ C_NB
    R_est = dcm_from_euler(*(mis_rad + dx[LAYOUT.at("misalignment"):][:3]))
    v_est = v_true + dx[VEL:VEL + 3]
    nhc = updates.nhc(LAYOUT, C_est, R_est, v_est, 0.3, (0.1, 0.5), 1.0)
    assert np.abs(nhc.H @ dx).max() > 0.02
    np.testing.assert_allclose(nhc.d, nhc.H @ dx, atol=1e-3)
    np.testing.assert_allclose(np.sqrt(np.diag(nhc.R)), [0.1 + 1.0 * 0.3, 0.5])
    odo = updates.odometer(LAYOUT, C_est, R_est, v_est, ACC_NED, scale + dx[LAYOUT.at("odometer_scale")], GAP_S,
                           speed, 0.05)
    assert np.abs(odo.H @ dx).max() > 0.05
    np.testing.assert_allclose(odo.d, odo.H @ dx, atol=1e-3)


def test_stop_models_measure_the_bias_errors():
    w_ie_b = C_NB.T @ geo.earth_rate_ned_rps(LLA[0])
    b_g = np.array([2e-3, -1e-3, 4e-3])
    dx = _error(vel=[0.01, -0.02, 0.005], bg=[1e-4, -3e-4, 2e-4], ba=[0.01, 0.02, -0.01])
    zupt = updates.zupt(LAYOUT, dx[VEL:VEL + 3], 0.02)
    np.testing.assert_allclose(zupt.d, zupt.H @ dx)
    zaru = updates.zaru(LAYOUT, C_NB, LLA[0], b_g + w_ie_b, b_g + dx[BG:BG + 3], 2e-3)
    np.testing.assert_allclose(zaru.d, zaru.H @ dx, atol=1e-12)
    cov = np.diag([1e-8, 4e-8, 9e-8])
    stop = updates.stop_gyro_bias(LAYOUT, b_g + dx[BG:BG + 3], b_g, cov)
    np.testing.assert_allclose(stop.d, stop.H @ dx, atol=1e-12)
    np.testing.assert_allclose(stop.R, cov)


@pytest.mark.parametrize("baseline_vehicle_m", [[1.2, 0.0, 0.0], [0.1, -0.9, 0.05], [-0.7, 0.4, -0.3]])
def test_dual_antenna_heading_residual_is_h_times_the_error(baseline_vehicle_m):
    """The true azimuth of the baseline from its NED vector; the estimate's attitude off by phi and
    its misalignment (vehicle <- body) by dm, R_est = exp(dm) R_true."""
    b = np.asarray(baseline_vehicle_m)
    R_vb = dcm_from_euler(0.01, -0.02, 0.03)
    u_true = C_NB @ R_vb.T @ b
    z = float(np.arctan2(u_true[1], u_true[0])) % (2 * np.pi)
    dx = _error(att=[4e-3, -3e-3, 5e-3], misalignment=[-2e-3, 3e-3, -4e-3])
    R_est = exp_so3(dx[LAYOUT.at("misalignment"):][:3]) @ R_vb
    m = updates.dual_antenna_heading(LAYOUT, exp_so3(-dx[ATT:ATT + 3]) @ C_NB, R_est, b, z, 0.01)
    assert abs(float((m.H @ dx)[0])) > 5e-4
    np.testing.assert_allclose(m.d, m.H @ dx, atol=1e-4)
    # each block on its own (a misalignment error alone moves the vehicle's heading too)
    for blocks in ({"att": dx[ATT:ATT + 3]}, {"misalignment": dx[LAYOUT.at("misalignment"):][:3]}):
        e = _error(**blocks)
        R_e = exp_so3(e[LAYOUT.at("misalignment"):][:3]) @ R_vb
        m = updates.dual_antenna_heading(LAYOUT, exp_so3(-e[ATT:ATT + 3]) @ C_NB, R_e, b, z, 0.01)
        assert abs(float((m.H @ e)[0])) > 1e-3
        np.testing.assert_allclose(m.d, m.H @ e, atol=1e-4)
    assert m.R[0, 0] == pytest.approx(1e-4)


@pytest.mark.parametrize("pitch_rad", [0.0, -0.08])
def test_vehicle_level_residual_is_h_times_the_error(pitch_rad):
    """A vehicle level about its forward axis (roll 0, on a grade or not), the IMU mounted with a
    misalignment; the estimate's attitude off by phi and its misalignment by dm: the residual
    (the estimate's vehicle roll as cos(pitch) sin(roll)) is H dx, and neither block nor the
    heading error is left out or wrongly signed."""
    R_vb = dcm_from_euler(0.03, -0.02, 0.04)
    C_nb_true = dcm_from_euler(0.0, pitch_rad, 1.1) @ R_vb      # C_nv R_vb: the body of a level vehicle
    dx = _error(att=[4e-3, -3e-3, 5e-3], misalignment=[-3e-3, 2e-3, -4e-3])
    i = LAYOUT.at("misalignment")
    for e in (dx, _error(att=dx[ATT:ATT + 3]), _error(misalignment=dx[i:i + 3])):
        m = updates.vehicle_level(LAYOUT, exp_so3(-e[ATT:ATT + 3]) @ C_nb_true,
                                  exp_so3(e[i:i + 3]) @ R_vb, np.radians(2.0))
        assert abs(float((m.H @ e)[0])) > 5e-4
        np.testing.assert_allclose(m.d, m.H @ e, atol=3e-5)
    assert m.H[0, ATT + 2] == 0.0                              # the heading, open at a stop start, stays out
    assert m.R[0, 0] == pytest.approx(np.sin(np.radians(2.0)) ** 2)


@pytest.mark.parametrize("learn", [True, False])
def test_nhc_sees_the_lateral_velocity_of_a_point_ahead_of_a_slipping_rear_axle(learn):
    """A car turning left at 0.25 rad/s at 9 m/s whose IMU is 1.3 m ahead of the rear axle and whose
    rear tyres slip 0.004 rad per m/s^2 of lateral acceleration: its IMU moves sideways at
    omega (d - k v^2). With the true distance and compliance the lateral residual is zero; with
    the estimates off by (dd, dk) (and the velocity and attitude off too) it is H dx. Without
    learning (no recent GNSS) the constraint is the one without the states: a zero lateral
    velocity, no columns for them, the loose sd."""
    layout = StateLayout.build(("misalignment", "rear_axle_distance", "rear_slip_compliance"))
    yaw_rate, speed, d_true, k_true = -0.25, 9.0, 1.3, 0.004
    v_vehicle = np.array([speed, yaw_rate * (d_true - k_true * speed ** 2), 0.0])
    assert abs(v_vehicle[1]) > 0.2                                   # the case is not the old zero
    R_vb = dcm_from_euler(0.01, -0.02, 0.015)
    v_true = C_NB @ R_vb.T @ v_vehicle
    i_d, i_k = layout.at("rear_axle_distance"), layout.at("rear_slip_compliance")
    exact = updates.nhc(layout, C_NB, R_vb, v_true, yaw_rate, rear_axle_distance_m=d_true,
                        rear_slip_compliance=k_true, learn_rear_axle=learn)
    if not learn:
        np.testing.assert_allclose(exact.d, v_vehicle[1:], atol=1e-12)
        assert not exact.H[:, [i_d, i_k]].any()
        assert exact.R[0, 0] == pytest.approx((0.05 + updates.NHC_SD_PER_YAW_RATE_M * 0.25) ** 2)
        return
    np.testing.assert_allclose(exact.d, 0.0, atol=1e-12)
    dx = np.zeros(layout.n)
    dx[VEL:VEL + 3] = [0.02, -0.03, 0.01]
    dx[ATT:ATT + 3] = [1e-3, -1e-3, 2e-3]
    dx[i_d], dx[i_k] = 0.3, -0.002
    C_est = exp_so3(-dx[ATT:ATT + 3]) @ C_NB
    m = updates.nhc(layout, C_est, R_vb, v_true + dx[VEL:VEL + 3], yaw_rate, rear_axle_distance_m=d_true + dx[i_d],
                    rear_slip_compliance=k_true + dx[i_k])
    assert m.H[0, i_d] == -yaw_rate and m.H[0, i_k] == pytest.approx(yaw_rate * speed ** 2, rel=1e-2)
    np.testing.assert_allclose(m.d, m.H @ dx, atol=2e-3)
    assert abs(float(m.d[0])) > 0.1                              # the distance and compliance errors show
    assert m.R[0, 0] == pytest.approx((0.05 + updates.NHC_SD_UNMODELLED_PER_YAW_RATE_M * 0.25) ** 2)


def test_dual_antenna_heading_residual_wraps_at_north():
    """A baseline just east of north measured just west of it: the residual is the small angle."""
    C = dcm_from_euler(0.0, 0.0, 0.01)
    m = updates.dual_antenna_heading(LAYOUT, C, np.eye(3), np.array([1.0, 0.0, 0.0]), 2 * np.pi - 0.01, 0.01)
    assert float(m.d[0]) == pytest.approx(0.02, abs=1e-9)
