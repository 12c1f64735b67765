"""The heading reset after a standstill start keeps what the stop taught about level and biases.

At a stop the specific force fixes only ``g x tilt + b`` per horizontal body axis: roll and the
lateral accelerometer bias are known as a pair (correlation of magnitude 1 in body axes), not apart, until the
vehicle turns. The filter starts at the stop with the heading open and turns its attitude to the
GNSS course when it drives off (``Initialization._heading_reset``); the attitude error is a
nav-frame vector, so its covariance must turn with it, or the pair points along the old, arbitrary
heading and the first seconds of driving "resolve" roll against the bias (docs/calibration.md:
on a convoy recording the roll sd fell from 0.45 to 0.03 deg while the roll was 0.25 deg off)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from sim.sensors import GnssErrorModel, ImuErrorModel, simulate_gnss, simulate_imu
from sim.trajectory import Segment, generate
from v2xpos.ins import InsConfig, InsFilter
from v2xpos.ins.ekf import ATT, BA

LEVER_M = np.array([0.3, 0.2, -1.5])


def _body_level_bias_corr(f: InsFilter) -> np.ndarray:
    """Correlations of the (roll, pitch) errors about the body axes with the (x, y) accelerometer
    biases: a (2, 2) matrix [[roll-bx, roll-by], [pitch-bx, pitch-by]]."""
    f._flush_covariance()
    C = f.C_nb
    P_att = C.T @ f.P[ATT:ATT + 3, ATT:ATT + 3] @ C
    P_ab = C.T @ f.P[ATT:ATT + 3, BA:BA + 3]
    sd_a = np.sqrt(np.diag(P_att))[:2]
    sd_b = np.sqrt(np.diag(f.P[BA:BA + 3, BA:BA + 3]))[:2]
    return P_ab[:2, :2] / np.outer(sd_a, sd_b)


@pytest.mark.parametrize("yaw0_deg", [40.0, -120.0, 175.0])
def test_heading_reset_keeps_the_level_bias_pair_in_body_axes(yaw0_deg):
    """Across the reset (which turns the attitude by tens of degrees about down) the body-axis
    correlation of roll with the lateral accelerometer bias, and of pitch with the forward one,
    stays what the stop made it (magnitude ~1, unchanged within 0.05)."""
    tr = generate([Segment(15.0), Segment(6.0, accel_mps2=1.5)], yaw0_rad=math.radians(yaw0_deg))
    imu = simulate_imu(tr, ImuErrorModel(accel_bias_mps2=np.array([0.02, 0.04, 0.0]), gyro_noise_rps_rthz=1e-4,
                                         accel_noise_mps2_rthz=1e-3), rng=np.random.default_rng(1))
    gn = simulate_gnss(tr, GnssErrorModel(rate_hz=10.0, lever_arm_m=LEVER_M), rng=np.random.default_rng(2))
    f = InsFilter(InsConfig(platform="car", lever_arm_m=LEVER_M, lever_arm_sd_m=0.01, effects=()))
    before = after = None
    gi = 0
    for k in range(len(imu)):
        f.process_imu(imu.t_s[k], imu.acc_mps2[k], imu.gyro_rps[k])
        while gi < len(gn) and gn.t_s[gi] <= imu.t_s[k] + 1e-9:
            pending = f.initialized and not f.heading_known
            corr = _body_level_bias_corr(f) if pending else None
            f.update_gnss(gn.t_s[gi], gn.lla[gi], gn.sd_ned_m[gi], gn.fix[gi], gn.vel_ned_mps[gi],
                          gn.vel_sd_ned_mps[gi])
            if pending and f.heading_known:
                before, after = corr, _body_level_bias_corr(f)
            gi += 1
        if after is not None:
            break
    assert after is not None, "the heading was never set from the course"
    pair = np.array([before[0, 1], before[1, 0]])           # roll-by, pitch-bx
    assert np.all(np.abs(pair) > 0.95), before               # what the stop taught
    np.testing.assert_allclose([after[0, 1], after[1, 0]], pair, atol=0.05)
