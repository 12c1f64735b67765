"""The simulator's truth must be self-consistent: the ideal IMU outputs integrate back to the path."""
import numpy as np

from sim.sensors import GnssErrorModel, ImuErrorModel, simulate_gnss, simulate_imu
from sim.trajectory import Segment, figure_eight_drive, generate, static, urban_drive
from v2xpos import geo
from v2xpos.rotation import exp_so3


def _integrate_ned(traj):
    """Plain second-order NED mechanization of the ideal IMU outputs (independent of v2xpos.ins)."""
    C = traj.C_nb[0].copy()
    v = traj.v_ned_mps[0].copy()
    lla = traj.lla[0].copy()
    for k in range(1, len(traj)):
        dt = traj.t_s[k] - traj.t_s[k - 1]
        w_ie = geo.earth_rate_ned_rps(lla[0])
        w_en = geo.transport_rate_ned_rps(lla[0], lla[2], v)
        w = 0.5 * (traj.w_ib_b_rps[k - 1] + traj.w_ib_b_rps[k])
        f = 0.5 * (traj.f_b_mps2[k - 1] + traj.f_b_mps2[k])
        C_mid = C @ exp_so3(0.5 * w * dt)
        a = C_mid @ f + geo.gravity_ned_mps2(lla[0], lla[2]) - np.cross(2 * w_ie + w_en, v)
        C = exp_so3(-(w_ie + w_en) * dt) @ C @ exp_so3(w * dt)
        v_new = v + a * dt
        r_m, r_n = geo.radii_m(lla[0])
        vm = 0.5 * (v + v_new)
        lla = lla + np.array([vm[0] / (r_m + lla[2]), vm[1] / ((r_n + lla[2]) * np.cos(lla[0])), -vm[2]]) * dt
        v = v_new
    return lla, v


def test_static_specific_force_is_gravity_and_rate_is_earth_rate():
    tr = static(2.0)
    g = geo.normal_gravity_mps2(tr.lla0[0], tr.lla0[2])
    assert np.allclose(tr.f_b_mps2, [0, 0, -g], atol=1e-9)
    assert np.allclose(np.linalg.norm(tr.w_ib_b_rps, axis=1), geo.OMEGA_IE_RPS, rtol=1e-9)


def test_turning_drive_integrates_back_to_truth():
    tr = generate([Segment(3, accel_mps2=2.0), Segment(10, yaw_rate_rps=0.3), Segment(5, accel_mps2=-1.0,
                   yaw_rate_rps=-0.2, pitch_rad=0.03)], dt_s=0.005, speed0_mps=5.0, yaw0_rad=0.5)
    lla, v = _integrate_ned(tr)
    err_m = np.linalg.norm(geo.lla_to_ned(lla, tr.lla[-1]))
    assert err_m < 0.05, err_m
    assert np.linalg.norm(v - tr.v_ned_mps[-1]) < 0.01


def test_urban_drive_stops_and_turns():
    tr = urban_drive(90.0, seed=3)
    assert tr.speed_mps[0] == 0 and tr.speed_mps[-1] < 0.05
    assert np.abs(tr.w_nb_b_rps[:, 2]).max() > 0.08
    assert tr.speed_mps.min() >= 0


def test_sensor_models_apply_declared_errors():
    tr = static(20.0)
    m = ImuErrorModel(gyro_bias_rps=np.array([1e-3, 0, 0]), accel_scale=np.array([0, 0, 0.01]))
    imu = simulate_imu(tr, m, time_offset_s=0.005)
    assert np.isclose(imu.gyro_rps[:, 0].mean() - tr.w_ib_b_rps[:, 0].mean(), 1e-3)
    assert np.isclose(imu.acc_mps2[:, 2].mean(), 1.01 * tr.f_b_mps2[:, 2].mean())
    assert abs(imu.t_s[0] - (tr.t_s[0] - 0.005)) < 1e-6     # np.isclose's rtol would allow hours at 1.4e9 s
    gn = simulate_gnss(tr, GnssErrorModel(rate_hz=5.0), fix_schedule=[(5, 10, 4)])
    ned = geo.lla_to_ned(gn.lla, tr.lla0)
    assert np.std(ned[gn.fix == 5, 0]) < 0.03 and np.std(ned[gn.fix == 4, 0]) > 0.03


def test_gnss_velocity_is_the_antenna_velocity():
    tr = generate([Segment(10.0, yaw_rate_rps=0.3)], speed0_mps=10.0, roll_per_lat_acc_rad=0.0)
    lever = np.array([0.0, 0.0, -1.5])            # antenna 1.5 m above the IMU: no effect in an unbanked turn
    gn = simulate_gnss(tr, GnssErrorModel(vel_sd_mps=0.0, lever_arm_m=np.array([2.0, 0.0, 0.0])))
    s = tr.sample(gn.t_s)
    # antenna 2 m ahead of the IMU, yaw rate 0.3 rad/s: extra 0.6 m/s towards the body's right
    right_ned = np.einsum("nij,j->ni", s["C_nb"], [0.0, 1.0, 0.0])
    extra = np.einsum("ni,ni->n", gn.vel_ned_mps - s["v_ned_mps"], right_ned)
    assert np.allclose(extra[5:-5], 0.6, atol=0.01)
    gn0 = simulate_gnss(tr, GnssErrorModel(vel_sd_mps=0.0, lever_arm_m=lever))
    assert np.allclose(gn0.vel_ned_mps, tr.sample(gn0.t_s)["v_ned_mps"], atol=1e-3)


def test_gnss_latency_tags_epochs_late():
    tr = generate([Segment(10.0)], speed0_mps=10.0, yaw0_rad=0.0)
    gn = simulate_gnss(tr, GnssErrorModel(latency_s=0.05, sd_h_m={5: 0.0}, vertical_factor=0.0, vel_sd_mps=0.0))
    north_m = geo.lla_to_ned(gn.lla, tr.lla0)[:, 0]
    # the position is the truth 50 ms before the tag: 0.5 m behind where the vehicle is at the tag time
    assert np.allclose(north_m - tr.sample(gn.t_s)["r_ned_m"][:, 0], -0.5, atol=1e-3)


def test_figure_eight_drive_turns_both_ways_at_several_speeds_within_the_lateral_limit():
    tr = figure_eight_drive(300.0, max_lat_acc_mps2=4.0)
    yaw_rate = tr.w_nb_b_rps[:, 2]
    lat_acc = np.abs(tr.speed_mps * yaw_rate)
    assert lat_acc.max() < 4.0 * 1.05
    turning = np.abs(yaw_rate) > 0.1
    speeds = np.round(tr.speed_mps[turning])
    assert len(np.unique(speeds)) >= 5                      # turns at several speeds
    assert (yaw_rate > 0.1).sum() > 1000 and (yaw_rate < -0.1).sum() > 1000
    assert tr.speed_mps[0] == 0.0 and tr.speed_mps[-1] < 0.1   # static start (alignment), ends stopped
