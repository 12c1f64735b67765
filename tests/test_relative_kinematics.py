"""Relative kinematics in the master body frame against closed-form and finite-difference truths."""
import math

import numpy as np
import pytest

from v2xpos.geo import dcm_ecef_to_ned, ned_to_lla
from v2xpos.relative import relative_kinematics
from v2xpos.rotation import dcm_from_euler, euler_from_dcm, operator_T
from v2xpos.types import FixStatus
from v2xpos.wire import Geometry, StateMessage

BASE_LLA = np.array([math.radians(39.75), math.radians(-105.2), 1650.0])


def state(ned_m=(0.0, 0.0, 0.0), v_ned=(0.0, 0.0, 0.0), acc_b=(0.0, 0.0, 0.0), rate_b=(0.0, 0.0, 0.0),
          rpy=(0.0, 0.0, 0.0), pos_sd=(0.01, 0.01, 0.02), att_sd=(0.0, 0.0, 0.0), geometry=None,
          vid="s", kind="vehicle", t=1000.0) -> StateMessage:
    """A state given in the NED frame at BASE_LLA, re-expressed in the vehicle's own local NED."""
    lla = ned_to_lla(np.asarray(ned_m, float), BASE_LLA)
    C_own_base = dcm_ecef_to_ned(lla[0], lla[1]) @ dcm_ecef_to_ned(BASE_LLA[0], BASE_LLA[1]).T
    rpy_own = euler_from_dcm(C_own_base @ dcm_from_euler(*rpy))
    return StateMessage(fleet="t", vehicle_id=vid, seq=1, t_gps_s=t, fix=FixStatus.FIXED, lat_rad=lla[0],
                        lon_rad=lla[1], height_m=lla[2], v_ned_mps=C_own_base @ np.array(v_ned, float),
                        acc_body_mps2=np.array(acc_b, float), rate_body_rps=np.array(rate_b, float),
                        rpy_rad=rpy_own, pos_sd_m=np.array(pos_sd, float),
                        vel_sd_mps=np.full(3, 0.02), att_sd_rad=np.array(att_sd, float),
                        geometry=geometry if geometry is not None else Geometry(), kind=kind)


def test_operator_T_90deg_yaw_closed_form():
    m = state(rpy=(0, 0, 0))
    s = state(ned_m=(10, 0, 0), rpy=(0, 0, math.pi / 2))
    res = relative_kinematics(m, s)
    np.testing.assert_allclose(res.rel_rpy_rad, [0, 0, math.pi / 2], atol=1e-6)
    T = operator_T(res.rel_rpy_rad[2], res.rel_rpy_rad[1], res.rel_rpy_rad[0])
    # the slave's forward axis points along the master's right axis
    np.testing.assert_allclose(T @ [1, 0, 0], [0, 1, 0], atol=1e-6)


def test_position_in_master_frame_facing_east():
    m = state(rpy=(0, 0, math.pi / 2))            # master faces east
    s = state(ned_m=(10, 0, 0))                    # target 10 m north = to the master's left
    res = relative_kinematics(m, s)
    np.testing.assert_allclose(res.rel_pos_body_m, [0, -10, 0], atol=1e-6)
    assert res.range_m == pytest.approx(10, abs=1e-6)
    assert res.bearing_rad == pytest.approx(-math.pi / 2, abs=1e-6)
    assert res.bearing_deg == pytest.approx(-90, abs=1e-4)


def test_pitched_master_elevation():
    m = state(rpy=(0, math.radians(10), 0))        # nose up 10 deg
    s = state(ned_m=(20, 0, 0))
    res = relative_kinematics(m, s)
    # level target appears 10 deg below the master's x axis
    assert res.elevation_rad == pytest.approx(-math.radians(10), abs=1e-5)
    assert res.range_m == pytest.approx(20, abs=1e-6)
    assert res.rel_rpy_rad[1] == pytest.approx(-math.radians(10), abs=1e-6)


def test_relative_velocity_straight_and_rotating_master():
    m = state(v_ned=(10, 0, 0))
    s = state(ned_m=(20, 0, 0), v_ned=(15, 0, 0))
    res = relative_kinematics(m, s)
    np.testing.assert_allclose(res.rel_vel_body_mps, [5, 0, 0], atol=1e-6)
    assert res.closing_speed_mps == pytest.approx(-5, abs=1e-6) and res.ttc_s is None
    # stationary master yawing right at 0.5 rad/s: a fixed object 10 m ahead moves left at 5 m/s
    m = state(rate_b=(0, 0, 0.5))
    s = state(ned_m=(10, 0, 0))
    res = relative_kinematics(m, s)
    np.testing.assert_allclose(res.rel_vel_body_mps, [0, -5, 0], atol=1e-6)
    np.testing.assert_allclose(res.rel_acc_body_mps2, [-2.5, 0, 0], atol=1e-6)  # centripetal w^2 r


def test_rigidly_attached_target_has_zero_relative_motion():
    w = np.array([0.02, -0.03, 0.4])
    yaw = 0.7
    C_nb = dcm_from_euler(0.01, -0.02, yaw)
    v_m = np.array([12.0, 5.0, 0.1])
    lever_b = np.array([6.0, 1.5, -0.3])
    v_s = v_m + C_nb @ np.cross(w, lever_b)
    a_m_b = np.cross(w, C_nb.T @ v_m)  # steady turn
    a_s_b = a_m_b + np.cross(w, np.cross(w, lever_b))
    m = state(v_ned=v_m, acc_b=a_m_b, rate_b=w, rpy=(0.01, -0.02, yaw))
    s = state(ned_m=C_nb @ lever_b, v_ned=v_s, acc_b=a_s_b, rate_b=w, rpy=(0.01, -0.02, yaw))
    res = relative_kinematics(m, s)
    np.testing.assert_allclose(res.rel_pos_body_m, lever_b, atol=1e-6)
    np.testing.assert_allclose(res.rel_vel_body_mps, 0, atol=1e-6)
    np.testing.assert_allclose(res.rel_acc_body_mps2, 0, atol=1e-6)
    np.testing.assert_allclose(res.rel_rpy_rad, 0, atol=1e-9)


def _truth(t):
    """Master on a 20 m/s, 0.3 rad/s circle; target braking on a straight line at 25 deg."""
    V, w = 20.0, 0.3
    psi = 0.2 + w * t
    R = V / w
    m_ned = (R * (math.sin(psi) - math.sin(0.2)), R * (math.cos(0.2) - math.cos(psi)), 0.0)
    m = state(ned_m=m_ned, v_ned=(V * math.cos(psi), V * math.sin(psi), 0), acc_b=(0, w * V, 0),
              rate_b=(0, 0, w), rpy=(0, 0, psi), vid="m")
    b, v0, hd = 3.0, 17.0, math.radians(25)
    d = 30 + v0 * t - 0.5 * b * t * t
    s = state(ned_m=(d * math.cos(hd), 8 + d * math.sin(hd), 0), v_ned=((v0 - b * t) * math.cos(hd),
              (v0 - b * t) * math.sin(hd), 0), acc_b=(-b, 0, 0), rpy=(0, 0, hd))
    return m, s


def test_relative_velocity_and_acceleration_match_finite_differences():
    h = 1e-3
    r = [relative_kinematics(*_truth(t)) for t in (-h, 0.0, h)]
    v_fd = (r[2].rel_pos_body_m - r[0].rel_pos_body_m) / (2 * h)
    a_fd = (r[2].rel_pos_body_m - 2 * r[1].rel_pos_body_m + r[0].rel_pos_body_m) / h ** 2
    np.testing.assert_allclose(r[1].rel_vel_body_mps, v_fd, atol=2e-3)
    np.testing.assert_allclose(r[1].rel_acc_body_mps2, a_fd, atol=0.05)
    rng_fd = (r[2].range_m - r[0].range_m) / (2 * h)
    g_fd = (r[2].gap_m - r[0].gap_m) / (2 * h)
    assert r[1].closing_speed_mps == pytest.approx(-g_fd, abs=2e-3)
    assert r[1].gap_m == pytest.approx(r[1].range_m)
    assert rng_fd == pytest.approx(-r[1].closing_speed_mps, abs=2e-3)


def test_measurement_points_contact_points_and_ttc():
    front_bumper = np.array([3.5, 0.0, 0.0])
    box = Geometry.box(front_m=3.8, rear_m=1.0, half_width_m=0.9, kind="points")
    m = state(v_ned=(20, 0, 0))
    s = state(ned_m=(25, 0.5, 0), v_ned=(15, 0, 0), geometry=box)
    res = relative_kinematics(m, s, master_points=front_bumper)
    # nearest contact point: target's rear-left corner (-1.0, -0.9) -> (24.0, -0.4) in master frame
    assert res.longitudinal_m == pytest.approx(24.0 - 3.5, abs=1e-6)
    assert res.lateral_m == pytest.approx(-0.4, abs=1e-6)
    gap = math.hypot(20.5, 0.4)
    assert res.gap_m == pytest.approx(gap, abs=1e-6)
    assert res.closing_speed_mps == pytest.approx(5 * 20.5 / gap, abs=1e-6)
    assert res.ttc_s == pytest.approx(gap / (5 * 20.5 / gap), rel=1e-6)


def test_polygon_nearest_edge_and_inside():
    poly = Geometry.box(front_m=2.0, rear_m=2.0, half_width_m=1.0, kind="polygon")
    m = state()
    s = state(ned_m=(10, 0.3, 0), geometry=poly)
    res = relative_kinematics(m, s)
    # nearest point is on the rear edge (x = 8), not a corner
    assert res.longitudinal_m == pytest.approx(8.0, abs=1e-6)
    assert res.lateral_m == pytest.approx(0.0, abs=1e-6)
    assert res.gap_m == pytest.approx(8.0, abs=1e-6)
    inside = relative_kinematics(m, state(ned_m=(1.0, 0.5, 0), geometry=poly))
    assert inside.gap_m == 0.0 and inside.ttc_s is None     # both at rest: not closing


def test_pedestrian_radius_and_covariance():
    ped = Geometry(kind="circle", radius_m=0.4)
    m = state(pos_sd=(0.01, 0.01, 0.02))
    s = state(ned_m=(6, 8, 0), pos_sd=(0.02, 0.02, 0.03), geometry=ped, kind="pedestrian", vid="p1")
    res = relative_kinematics(m, s)
    assert res.target_kind == "pedestrian" and res.target_id == "p1"
    assert res.gap_m == pytest.approx(10 - 0.4, abs=1e-6)
    np.testing.assert_allclose(res.rel_pos_sd_m, np.sqrt([0.01 ** 2 + 0.02 ** 2] * 2 + [0.02 ** 2 + 0.03 ** 2]),
                               rtol=1e-6)
    # master yaw uncertainty adds range x sd across the line of sight
    res_att = relative_kinematics(state(att_sd=(0, 0, 0.01)), s)
    assert res_att.rel_pos_sd_m[0] == pytest.approx(math.hypot(res.rel_pos_sd_m[0], 8 * 0.01), rel=1e-3)
    assert res_att.range_sd_m == pytest.approx(res.range_sd_m, rel=0.05)


def test_long_range_target_uses_master_ned():
    # 2 km north: the target's own NED differs from the master's by 3e-4 rad; velocity must be rotated
    s_ned = np.array([2000.0, 0.0, 0.0])
    m = state(v_ned=(20, 0, 0))
    lla_s = ned_to_lla(s_ned, m.lla)
    s = state(ned_m=s_ned, v_ned=(20, 0, 0))
    np.testing.assert_allclose([s.lat_rad, s.lon_rad, s.height_m], lla_s, atol=1e-12)
    # the same physical velocity in the target's own NED: its north axis is tilted by the arc
    arc = 2000.0 / 6.37e6
    np.testing.assert_allclose(s.v_ned_mps, [20 * math.cos(arc), 0, -20 * math.sin(arc)], atol=2e-5)
    res = relative_kinematics(m, s)
    np.testing.assert_allclose(res.rel_pos_body_m, s_ned, atol=1e-6)
    np.testing.assert_allclose(res.rel_vel_body_mps, 0, atol=1e-3)


from hypothesis import given, settings, strategies as st  # noqa: E402

angle = st.floats(-math.pi, math.pi)
small = st.floats(-0.5, 0.5)


@settings(max_examples=60, deadline=None)
@given(ned=st.tuples(st.floats(-500, 500), st.floats(-500, 500), st.floats(-20, 20)),
       rpy_m=st.tuples(small, small, angle), rpy_s=st.tuples(small, small, angle),
       v_m=st.tuples(st.floats(-40, 40), st.floats(-40, 40), st.floats(-1, 1)),
       v_s=st.tuples(st.floats(-40, 40), st.floats(-40, 40), st.floats(-1, 1)),
       w_m=st.tuples(small, small, small), w_s=st.tuples(small, small, small))
def test_swapping_master_and_target_is_consistent(ned, rpy_m, rpy_s, v_m, v_s, w_m, w_s):
    """Seen from the target, the master sits at -C_sm r_b with the inverse relative attitude and
    (by the rotating-frame formula) velocity -C_sm (v_rel + w_m x r_b) - w_s x r_sm."""
    m = state(rpy=rpy_m, v_ned=v_m, rate_b=w_m, vid="m")
    s = state(ned_m=ned, rpy=rpy_s, v_ned=v_s, rate_b=w_s, vid="s")
    ab, ba = relative_kinematics(m, s), relative_kinematics(s, m)
    C_ms = operator_T(ab.rel_rpy_rad[2], ab.rel_rpy_rad[1], ab.rel_rpy_rad[0])
    C_sm = operator_T(ba.rel_rpy_rad[2], ba.rel_rpy_rad[1], ba.rel_rpy_rad[0])
    np.testing.assert_allclose(C_ms @ C_sm, np.eye(3), atol=1e-9)
    np.testing.assert_allclose(ba.rel_pos_body_m, -C_ms.T @ ab.rel_pos_body_m, atol=1e-6)
    assert ba.range_m == pytest.approx(ab.range_m, abs=1e-6)
    v_inertial_b = ab.rel_vel_body_mps + np.cross(w_m, ab.rel_pos_body_m)   # C_bn (v_s - v_m)
    expect = -C_ms.T @ v_inertial_b - np.cross(w_s, ba.rel_pos_body_m)
    np.testing.assert_allclose(ba.rel_vel_body_mps, expect, atol=1e-6)
