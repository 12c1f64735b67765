"""Pose-aided angular-rate check end to end: ray-cast lidar scans along a simulated turn,
KISS-ICP odometry, rotation vectors of the relative poses -> angular rate. Recovers the true yaw
rate within 1 % and flags a 3 % gyro scale error while the healthy gyro passes."""
import numpy as np
import pytest

from sim.lidar import Box, Cylinder, LidarModel, Scene, cast
from v2xpos.quality import grade_units
from bench.grading import run_lidar_check

pytestmark = pytest.mark.slow   # kiss-icp over a lidar recording (make test-fast leaves it out)


def test_ray_casting_hits_known_surfaces():
    scene = Scene(ground_z_m=0.0, boxes=[Box(np.array([10.0, -5.0, -4.0]), np.array([11.0, 5.0, 0.0]))],
                  cylinders=[Cylinder(np.array([0.0, 10.0]), 1.0, -5.0, 0.0)])
    o = np.array([0.0, 0.0, -2.0])
    dirs = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0],
                     [np.cos(0.1), 0.0, -np.sin(0.1)]])
    r = cast(scene, o, dirs, 100.0)
    np.testing.assert_allclose(r[:3], [10.0, 9.0, 2.0])
    assert np.isinf(r[3])
    # upward ray over the 4 m box top (at z = -4 the ray is 2 m up: 2 / sin(0.1) m along it)
    assert np.isclose(r[4], 10.0 / np.cos(0.1))
    assert LidarModel().ray_directions_s().shape == (16 * 900, 3)


@pytest.fixture(scope="module")
def lidar_result():
    return run_lidar_check(seed=0, duration_s=4.0)


def test_kiss_icp_recovers_yaw_rate_within_1_percent(lidar_result):
    r = lidar_result
    assert r["n_scans"] >= 40
    assert abs(r["yaw_rate_rel_error"]) < 0.01, r["yaw_rate_rel_error"]
    assert abs(r["yaw_rate_true_dps"] - np.degrees(0.3)) < 0.1


def test_rate_check_flags_3_percent_scale_and_passes_healthy(lidar_result):
    h, f = lidar_result["healthy"], lidar_result["scale_fault"]
    assert not h["anomaly"] and abs(h["mean_diff_dps"]) < h["threshold_dps"]
    assert f["anomaly"]
    assert 0.02 < f["relative_diff"] < 0.04          # the 3 % scale shows as ~3 % of the rate


def test_rate_check_result_fails_the_unit_in_the_verdict(lidar_result):
    from sim.imu_faults import simulate_vehicle
    v = simulate_vehicle(3, None, seed=2)
    rc = {"imu2": lidar_result["scale_fault"], "imu3": lidar_result["healthy"]}
    rep = grade_units(v.units, mounting_xyz_deg=v.mounting_xyz_deg, rate_check=rc)
    grades = {u["id"]: u["grade"] for u in rep["units"]}
    assert grades == {"imu1": "pass", "imu2": "fail", "imu3": "pass"}
    assert next(u for u in rep["units"] if u["id"] == "imu2")["rate_check"]["anomaly"] is True
