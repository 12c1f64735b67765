"""The IMU position taken from an antenna fix (start at a stop, heading reset) keeps the fix's
information about the *antenna*, not about the IMU point: right after the reset the covariance of
the predicted antenna position is the fix's R, and a second, identical fix does not "determine"
the lever arm (``initialization.position_from_antenna_covariance``).

Drive: 4 s parked, then 2 m/s^2 straight ahead (the heading reset comes at 1 m/s GNSS speed);
error-free IMU at 100 Hz, 10 Hz GNSS of the true antenna 0.5 m ahead of and 1.5 m above the IMU
with no noise; the filter is told the antenna is straight above (0, 0, -1.5) with a 0.5 m prior.
"""
import numpy as np
import pytest

from sim.sensors import GnssErrorModel, ImuErrorModel, simulate_gnss, simulate_imu
from sim.trajectory import Segment, generate
from v2xpos.ins import InsConfig, InsFilter
from v2xpos.ins import updates
from v2xpos.ins.ekf import ATT
from v2xpos.types import FixStatus

TRUE_LEVER_ARM_M = np.array([0.5, 0.0, -1.5])
DECLARED_LEVER_ARM_M = np.array([0.0, 0.0, -1.5])
LEVER_PRIOR_SD_M = 0.5
FIX_SD_M = 0.05


def _predicted_antenna(f: InsFilter, t_s: float, lla: np.ndarray) -> updates.Measurement:
    """The filter's own GNSS position model at its current state (the open yaw column kept out,
    as ``InsFilter._update`` does while the heading is unknown)."""
    v = f.nav[3:6]
    timing = f._timing_in_models(v)   # without timing columns while a drive-off alignment is pending
    m = updates.gnss_position(f.layout, f.nav, f.C_nb, f.fx.lever_arm_m, v, f._gap_s(t_s), lla,
                              np.full(3, FIX_SD_M), f.cfg.gnss.gnss_pos_sd_floor_m, timing)
    if not f.heading_known:
        m.H[:, ATT + 2] = 0.0
    return m


@pytest.fixture(scope="module")
def resets() -> dict:
    """Run the drive; at the start and at the heading reset record the fix's R, H P H^T of the
    predicted antenna position, and the lever-arm sd before and after the same fix once more."""
    tr = generate([Segment(4.0), Segment(4.0, accel_mps2=2.0)], speed0_mps=0.0)
    imu = simulate_imu(tr, ImuErrorModel(), rng=np.random.default_rng(1))
    gn = simulate_gnss(tr, GnssErrorModel(rate_hz=10.0, lever_arm_m=TRUE_LEVER_ARM_M), rng=np.random.default_rng(2))
    s = tr.sample(gn.t_s)
    vel = s["v_ned_mps"] + np.einsum("nij,nj->ni", s["C_nb"], np.cross(s["w_nb_b_rps"], TRUE_LEVER_ARM_M))
    f = InsFilter(InsConfig(setup={"platform": "car", "lever_arm_m": DECLARED_LEVER_ARM_M,
                                   "lever_arm_sd_m": LEVER_PRIOR_SD_M}))
    i_l = f.layout.at("lever_arm")
    out = {}
    gi = 0
    for k in range(len(imu.t_s)):
        f.process_imu(imu.t_s[k], imu.acc_mps2[k], imu.gyro_rps[k])
        while gi < len(gn.t_s) and gn.t_s[gi] <= imu.t_s[k] + 1e-6:
            fix = (gn.t_s[gi], gn.lla[gi], np.full(3, FIX_SD_M), FixStatus.FIXED, vel[gi], np.full(3, 0.02))
            r = f.update_gnss(*fix)
            for key, reason in (("start", "initialised at a stop"), ("heading", "heading set from the GNSS course")):
                if key not in out and r.reason.startswith(reason):
                    m = _predicted_antenna(f, gn.t_s[gi], gn.lla[gi])
                    cov_antenna = m.H @ f.P @ m.H.T
                    sd_before = np.sqrt(np.diag(f.P)[i_l:i_l + 3])
                    f.update_gnss(*fix)
                    out[key] = (m.R, cov_antenna, sd_before, np.sqrt(np.diag(f.P)[i_l:i_l + 3]))
            gi += 1
    return out


@pytest.mark.parametrize("key", ["start", "heading"])
def test_antenna_position_covariance_after_a_reset_is_the_fix(resets, key):
    R, cov_antenna, _, _ = resets[key]
    assert np.allclose(cov_antenna, R, rtol=1e-6, atol=1e-9), (cov_antenna, R)


@pytest.mark.parametrize("key", ["start", "heading"])
def test_a_repeated_fix_does_not_determine_the_lever_arm(resets, key):
    """The repeated fix says nothing the first did not: the horizontal lever-arm sd stays at what
    the reset left (without the cross terms it fell from 0.5 to ~0.07 m)."""
    _, _, sd_before, sd_after = resets[key]
    assert sd_before[0] > 0.8 * LEVER_PRIOR_SD_M
    assert np.all(sd_after[:2] > 0.95 * sd_before[:2]), (sd_before, sd_after)
