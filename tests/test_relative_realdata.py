"""Latency compensation on a real drive (drive_0708, RTK at 4 Hz): predict each epoch 250 ms ahead
with CTRA from causal (backward-difference) rate and acceleration, compare with the next RTK fix."""
import math

import numpy as np

from v2xpos.geo import lla_to_ned
from v2xpos.relative import predict_state
from v2xpos.types import FixStatus
from v2xpos.wire import StateMessage
from tests.shared_data import SHARED_DATA, require_shared

DATA = SHARED_DATA
POS = DATA / "drive_0708" / "gnss_1934.pos"


def test_ctra_beats_constant_velocity_on_real_drive():
    require_shared(POS)
    from v2xpos.datasets.rtklib_pos import read_rtklib_pos
    gnss, _ = read_rtklib_pos(POS)
    t, lla, v = gnss.t_s, gnss.lla, gnss.vel_ned_mps
    assert v is not None
    step = float(np.median(np.diff(t)))
    err = {"ctra": [], "cv": [], "none": []}
    for k in range(1, len(t) - 1):
        if abs(t[k] - t[k - 1] - step) > 1e-3 or abs(t[k + 1] - t[k] - step) > 1e-3:
            continue
        speed, speed_prev = np.hypot(*v[k, :2]), np.hypot(*v[k - 1, :2])
        if min(speed, speed_prev) < 3.0:          # course over ground is undefined when stopped
            continue
        yaw, yaw_prev = math.atan2(v[k, 1], v[k, 0]), math.atan2(v[k - 1, 1], v[k - 1, 0])
        rate = ((yaw - yaw_prev + math.pi) % (2 * math.pi) - math.pi) / step
        a_n = (v[k] - v[k - 1]) / step
        c, s = math.cos(yaw), math.sin(yaw)
        acc_b = np.array([c * a_n[0] + s * a_n[1], rate * speed, a_n[2]])
        msg = StateMessage(fleet="d", vehicle_id="car", seq=k, t_gps_s=t[k], fix=FixStatus(int(gnss.fix[k])),
                           lat_rad=lla[k, 0], lon_rad=lla[k, 1], height_m=lla[k, 2], v_ned_mps=v[k].copy(),
                           acc_body_mps2=acc_b, rate_body_rps=np.array([0.0, 0.0, rate]),
                           rpy_rad=np.array([0.0, 0.0, yaw]), pos_sd_m=np.full(3, 0.01),
                           vel_sd_mps=np.full(3, 0.02), att_sd_rad=np.full(3, 0.01))
        cv = StateMessage(**{**msg.__dict__, "acc_body_mps2": np.zeros(3), "rate_body_rps": np.zeros(3)})
        for name, m in (("ctra", predict_state(msg, step)), ("cv", predict_state(cv, step)), ("none", msg)):
            err[name].append(np.linalg.norm(lla_to_ned(m.lla, lla[k + 1])[:2]))
    rms = {k: float(np.sqrt(np.mean(np.square(e)))) for k, e in err.items()}
    assert len(err["ctra"]) > 1000
    assert rms["none"] > 1.0                       # uncompensated: speed x 250 ms
    assert rms["ctra"] < 0.8 * rms["cv"]           # turn rate and acceleration matter
    assert rms["ctra"] < 0.06, rms
