"""``InsFilter.nav_state()`` against simulator truth: body rate and kinematic acceleration at the
last IMU sample whatever the covariance cadence, and the effect states (lever arm, timing) staying
at truth on data that has none of those errors.

The vehicle starts moving at 20 m/s (a slave that joins mid-drive), 100 Hz automotive IMU,
10 Hz RTK (1 cm), antenna 0.5 m ahead of and 1.4 m above the IMU, as in ``sim.scenarios.convoy``.
"""
import numpy as np
import pytest

from sim.sensors import GnssErrorModel, ImuErrorModel, simulate_gnss, simulate_imu
from sim.trajectory import Segment, generate
from v2xpos import geo
from v2xpos.ins import InsConfig, InsFilter
from v2xpos.types import FixStatus

pytestmark = pytest.mark.slow   # replays of whole recordings (make test-fast leaves them out)

LEVER_ARM_M = np.array([0.5, 0.0, -1.4])
SPEED_MPS = 20.0


@pytest.fixture(scope="module")
def run():
    """Truth, sensors and a sample-by-sample run of two filters (cov_every 10 and 1), recording
    nav_state() after every IMU sample."""
    segs = [Segment(3.0), Segment(6.0, yaw_rate_rps=-0.08), Segment(3.0), Segment(2.5, accel_mps2=-3.0),
            Segment(2.0), Segment(3.0, accel_mps2=2.5), Segment(6.0, yaw_rate_rps=0.10), Segment(3.0),
            Segment(3.0, yaw_rate_rps=-0.10), Segment(3.0, yaw_rate_rps=0.10), Segment(6.0)]
    tr = generate(segs, speed0_mps=SPEED_MPS)
    imu = simulate_imu(tr, ImuErrorModel.preset("automotive", np.random.default_rng(11)),
                       rng=np.random.default_rng(12))
    gm = GnssErrorModel(rate_hz=10.0, lever_arm_m=LEVER_ARM_M)
    gn = simulate_gnss(tr, gm, rng=np.random.default_rng(13))
    # the receiver reports the antenna's velocity: v + C_nb (w_nb x l) (computed here from truth so
    # that the test does not depend on whether the simulator adds the lever-arm term)
    s = tr.sample(gn.t_s)
    gn.vel_ned_mps = (s["v_ned_mps"] + np.einsum("nij,nj->ni", s["C_nb"], np.cross(s["w_nb_b_rps"], LEVER_ARM_M))
                      + np.random.default_rng(14).normal(0, gm.vel_sd_mps, (len(gn.t_s), 3)))
    filters = {ce: InsFilter(InsConfig(setup={"platform": "car", "lever_arm_m": LEVER_ARM_M}, numerics={"cov_every": ce},
                                       imu={"gyro_noise_rps_rthz": 3 * np.radians(0.3) / 60,
                                            "accel_noise_mps2_rthz": 3 * 150e-6 * 9.81}))
               for ce in (10, 1)}
    out = {ce: [] for ce in filters}
    for ce, f in filters.items():
        f.initialize(tr.t_s[0], tr.lla[0], tr.v_ned_mps[0], tr.rpy_rad[0])
        gi = 0
        for k in range(1, len(imu.t_s)):
            f.process_imu(imu.t_s[k], imu.acc_mps2[k], imu.gyro_rps[k])
            while gi < len(gn.t_s) and gn.t_s[gi] <= imu.t_s[k] + 1e-6:
                f.update_gnss(gn.t_s[gi], gn.lla[gi], gn.sd_ned_m[gi], FixStatus(int(gn.fix[gi])),
                              gn.vel_ned_mps[gi], gn.vel_sd_ned_mps[gi])
                gi += 1
            out[ce].append(f.nav_state())
    return tr, filters, out


def _truth_index(tr, t_s):
    return np.clip(np.round((np.asarray(t_s) - tr.t_s[0]) / tr.dt_s).astype(int), 0, len(tr.t_s) - 1)


def test_rate_and_acceleration_are_current_and_accurate(run):
    """Rate and acceleration are those of the last IMU sample (no 100-ms chunk staleness, no
    low-pass lag): sensor-noise-level error at zero shift, and identical for cov_every 10 and 1."""
    tr, _, out = run
    st = out[10]
    t = np.array([s.t_s for s in st])
    k = _truth_index(tr, t)
    # label = sample time + the estimated IMU time offset (prior 0.3 s, converged within a few seconds)
    assert np.max(np.abs(t - tr.t_s[k])[t > t[0] + 5.0]) < 3e-3
    truth = tr.sample(t)
    rate = np.array([s.rate_body_rps for s in st])
    acc = np.array([s.acc_body_mps2 for s in st])
    rate_err = np.sqrt(np.mean((rate - truth["w_nb_b_rps"]) ** 2, axis=0))
    acc_err = np.sqrt(np.mean((acc - truth["acc_body_mps2"]) ** 2, axis=0))
    # automotive per-sample noise at 100 Hz: gyro 8.7e-4 rad/s, accel 0.015 m/s^2
    assert np.all(rate_err < 2e-3), rate_err
    assert np.all(acc_err < 0.03), acc_err
    # no lag: the error grows when the truth is shifted by one sample either way
    for axis in (0, 1):
        errs = {sh: np.sqrt(np.mean((acc[5:-5, axis] - tr.acc_body_mps2[k[5:-5] - sh, axis]) ** 2))
                for sh in (-1, 0, 1)}
        assert errs[0] < errs[1] and errs[0] < errs[-1], errs
    # the covariance cadence does not change what is reported
    rate1 = np.array([s.rate_body_rps for s in out[1]])
    acc1 = np.array([s.acc_body_mps2 for s in out[1]])
    late = t > t[0] + 1.0
    assert np.sqrt(np.mean((rate1 - rate)[late] ** 2)) < 3e-4
    assert np.sqrt(np.mean((acc1 - acc)[late] ** 2)) < 5e-3


def test_default_car_effects_stay_at_truth_on_error_free_data(run):
    """Lever arm, IMU time offset, clock drift, misalignment and GNSS velocity latency are all
    estimated (car defaults) on data without any of those errors: the lever arm stays within a few
    cm, the timing within 2 ms (its sd is ~2 ms after 40 s), and the IMU point shows no along-track lag (it drifted to
    l_x = 0.55 m and ~4 ms of lag when the first IMU interval after start was dropped)."""
    tr, filters, out = run
    f = filters[10]
    assert set(f.layout.effects) >= {"lever_arm", "imu_time_offset", "imu_clock_drift", "misalignment"}
    fx = f.effects_report()
    lever_err = np.array(fx["lever_arm_m"]) - LEVER_ARM_M
    assert abs(lever_err[0]) < 0.03 and np.all(np.abs(lever_err) < 0.05), fx["lever_arm_m"]
    assert abs(fx["imu_time_offset_s"]) < 2e-3
    assert abs(fx["gnss_vel_latency_s"]) < 2e-3
    st = out[10]
    t = np.array([s.t_s for s in st])
    truth = tr.sample(t)                                # at the filter's time label
    err = np.array([geo.lla_to_ned(s.lla, tr.lla0) for s in st]) - truth["r_ned_m"]
    fwd = truth["v_ned_mps"] / np.linalg.norm(truth["v_ned_mps"], axis=1)[:, None]
    along = np.einsum("ij,ij->i", err, fwd)
    late = t > t[0] + 10.0
    assert abs(along[late].mean()) < 0.02, along[late].mean()       # < 1 ms at 20 m/s
    assert np.sqrt(np.mean(err[late] ** 2)) < 0.03


def test_first_interval_after_initialize_is_integrated():
    """initialize() at t0 and a first sample at t0 + 10 ms: the state moves to t0 + 10 ms."""
    f = InsFilter(InsConfig(setup={"platform": "generic"}, effects={"states": ()}))
    t0 = 1.4e9
    lla0 = np.array([np.radians(40.0), np.radians(-105.0), 1600.0])
    f.initialize(t0, lla0, np.array([SPEED_MPS, 0.0, 0.0]), np.zeros(3))
    g = geo.normal_gravity_mps2(lla0[0], lla0[2])
    f.process_imu(t0 + 0.01, np.array([0.0, 0.0, -g]), np.zeros(3))
    assert abs(f.t_s - (t0 + 0.01)) < 1e-9
    assert abs(geo.lla_to_ned(f.lla, lla0)[0] - SPEED_MPS * 0.01) < 1e-3
