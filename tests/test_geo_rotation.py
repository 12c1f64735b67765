"""Geodesy and rotations against published reference values and closed-form cases."""
import numpy as np
import pytest

from v2xpos import geo
from v2xpos import rotation as R


def test_wgs84_ecef_special_points():
    assert np.allclose(geo.lla_to_ecef(np.array([0.0, 0.0, 0.0])), [6378137.0, 0, 0], atol=1e-6)
    # semi-minor axis b = 6356752.314245 m (NIMA TR8350.2 table 3.3)
    assert np.allclose(geo.lla_to_ecef(np.array([np.pi / 2, 0.0, 0.0])), [0, 0, 6356752.314245], atol=1e-5)
    assert np.allclose(geo.lla_to_ecef(np.array([0.0, np.pi / 2, 100.0])), [0, 6378237.0, 0], atol=1e-6)


@pytest.mark.parametrize("lat_deg, lon_deg, h_m", [(40.0, -105.0, 1600.0), (-33.9, 151.2, -30.0),
                                                   (89.99, 10.0, 5000.0), (0.0, 180.0, 0.0)])
def test_ecef_lla_roundtrip_sub_mm(lat_deg, lon_deg, h_m):
    lla = np.array([np.radians(lat_deg), np.radians(lon_deg), h_m])
    back = geo.ecef_to_lla(geo.lla_to_ecef(lla))
    assert abs(back[0] - lla[0]) * 6.4e6 < 1e-4 and abs(back[2] - h_m) < 1e-4
    assert abs(R.wrap_pi(back[1] - lla[1])) * 6.4e6 * np.cos(lla[0]) < 1e-4


def test_radii_and_gravity_reference_values():
    r_m, r_n = geo.radii_m(0.0)
    assert np.isclose(r_n, 6378137.0) and np.isclose(r_m, 6335439.327, atol=1e-3)
    r_m, r_n = geo.radii_m(np.pi / 2)
    assert np.isclose(r_m, 6399593.626, atol=1e-3) and np.isclose(r_n, 6399593.626, atol=1e-3)
    # TR8350.2: normal gravity 9.7803253359 at the equator, 9.8321849378 at the poles
    assert np.isclose(geo.normal_gravity_mps2(0.0, 0.0), 9.7803253359, atol=1e-9)
    assert np.isclose(geo.normal_gravity_mps2(np.pi / 2, 0.0), 9.8321849378, atol=1e-9)
    # free-air gradient about 3.086e-6 s^-2
    dg = geo.normal_gravity_mps2(np.radians(45), 0.0) - geo.normal_gravity_mps2(np.radians(45), 1000.0)
    assert np.isclose(dg, 3.086e-3, rtol=0.01)


def test_ned_enu_local_frames():
    ref = np.array([np.radians(40.0), np.radians(-105.0), 1600.0])
    pts = np.array([[100.0, -50.0, 3.0], [0.0, 0.0, 0.0], [-2000.0, 1500.0, -20.0]])
    assert np.allclose(geo.lla_to_ned(geo.ned_to_lla(pts, ref), ref), pts, atol=1e-6)
    enu = geo.lla_to_enu(geo.ned_to_lla(pts, ref), ref)
    assert np.allclose(enu, pts[:, [1, 0, 2]] * [1, 1, -1], atol=1e-6)
    # one arc-second of latitude north is R_M/206265 m north
    r_m, _ = geo.radii_m(ref[0])
    n = geo.lla_to_ned(ref + [np.radians(1 / 3600), 0, 0], ref)
    assert np.isclose(n[0], (r_m + ref[2]) * np.radians(1 / 3600), rtol=1e-6)


def test_earth_and_transport_rate():
    w = geo.earth_rate_ned_rps(np.radians(30))
    assert np.isclose(np.linalg.norm(w), 7.292115e-5) and w[2] < 0
    v = np.array([0.0, 20.0, 0.0])
    w_en = geo.transport_rate_ned_rps(0.0, 0.0, v)
    assert np.isclose(w_en[0], 20.0 / 6378137.0)


def test_euler_dcm_closed_form():
    C = R.dcm_from_euler(0.0, 0.0, np.pi / 2)          # heading east
    assert np.allclose(C @ [1, 0, 0], [0, 1, 0], atol=1e-12)
    C = R.dcm_from_euler(0.0, np.radians(10), 0.0)     # nose up: forward axis points up (negative down)
    assert (C @ [1, 0, 0])[2] < 0
    C = R.dcm_from_euler(np.radians(20), 0.0, 0.0)     # right wing down: body y points down
    assert (C @ [0, 1, 0])[2] > 0
    rpy = np.array([0.3, -1.2, -2.9])
    assert np.allclose(R.euler_from_dcm(R.dcm_from_euler(*rpy)), rpy)
    assert np.allclose(R.dcm_from_euler(*rpy), R.rot_z(rpy[2]) @ R.rot_y(rpy[1]) @ R.rot_x(rpy[0]))


def test_quaternion_rotvec_rodrigues():
    rng = np.random.default_rng(0)
    for _ in range(20):
        phi = rng.normal(0, 1.0, 3)
        C = R.exp_so3(phi)
        assert np.allclose(C.T @ C, np.eye(3), atol=1e-12) and np.isclose(np.linalg.det(C), 1)
        assert np.allclose(R.dcm_from_quat(R.quat_from_rotvec(phi)), C, atol=1e-12)
        assert np.allclose(R.exp_so3(R.log_so3(C)), C, atol=1e-10)
        q1, q2 = R.quat_from_rotvec(phi), R.quat_from_rotvec(rng.normal(0, 1, 3))
        assert np.allclose(R.dcm_from_quat(R.quat_mult(q1, q2)), R.dcm_from_quat(q1) @ R.dcm_from_quat(q2))
    assert np.allclose(R.exp_so3(np.array([0, 0, np.pi / 2])) @ [1, 0, 0], [0, 1, 0])
    assert np.allclose(R.log_so3(R.rot_x(np.pi - 1e-9)), [np.pi - 1e-9, 0, 0], atol=1e-6)


def test_operator_T_maps_slave_body_into_master_body():
    # master heading north, slave heading east: the slave's forward axis is the master's right axis
    C_m = R.dcm_from_euler(0.0, 0.0, 0.0)
    C_s = R.dcm_from_euler(0.0, 0.0, np.pi / 2)
    C_ms, eul = R.relative_attitude(C_m, C_s)
    assert np.allclose(eul, [0, 0, np.pi / 2])
    assert np.allclose(R.operator_T(eul[2], eul[1], eul[0]) @ [1, 0, 0], [0, 1, 0], atol=1e-12)
    # general case: T equals C_nm^T C_ns for any attitudes
    rng = np.random.default_rng(1)
    for _ in range(10):
        C_m = R.dcm_from_euler(*rng.uniform(-0.5, 0.5, 2), rng.uniform(-3, 3))
        C_s = R.dcm_from_euler(*rng.uniform(-0.5, 0.5, 2), rng.uniform(-3, 3))
        C_ms, (dr, dp, dy) = R.relative_attitude(C_m, C_s)
        assert np.allclose(R.operator_T(dy, dp, dr), C_m.T @ C_s, atol=1e-12)
