"""Roundtrip of the wire messages (StateMessage, RelativeResult, envelope with signature slot)."""
import math

import numpy as np

from v2xpos.types import FixStatus
from v2xpos.wire import (FixSide, Geometry, RelativeResult, StateMessage, TargetStatus, decode_relative,
                         decode_state, encode_relative, encode_state, unpack_envelope)


def make_state(**kw) -> StateMessage:
    base = dict(fleet="test", vehicle_id="car-2", seq=17, t_gps_s=1_400_000_000.25, fix=FixStatus.FIXED,
                lat_rad=0.6981, lon_rad=-1.8326, height_m=1612.5, v_ned_mps=np.array([19.5, -3.25, 0.1]),
                acc_body_mps2=np.array([-1.5, 2.0, 0.05]), rate_body_rps=np.array([0.01, -0.02, 0.3]),
                rpy_rad=np.array([0.02, -0.01, 2.5]), pos_sd_m=np.array([0.01, 0.012, 0.02]),
                vel_sd_mps=np.array([0.02, 0.02, 0.03]), att_sd_rad=np.array([0.001, 0.001, 0.004]),
                geometry=Geometry.box(3.8, 1.0, 0.9), t_sent_wall_s=1.7e9)
    base.update(kw)
    return StateMessage(**base)


def test_state_roundtrip_exact():
    msg = make_state(imu_quality={"grade": "A", "rmse": [0.1, 0.2]})
    out = decode_state(encode_state(msg))
    assert out == msg
    assert out.geometry.points_body_m.shape == (4, 3)
    assert out.signed_payload is not None


def test_pedestrian_circle_roundtrip():
    msg = make_state(vehicle_id="ped-1", kind="pedestrian", geometry=Geometry(kind="circle", radius_m=0.3),
                     t_sent_wall_s=None)
    out = decode_state(encode_state(msg))
    assert out == msg and out.kind == "pedestrian" and out.geometry.radius_m == 0.3


def test_signature_slot_covers_body():
    msg = make_state()
    data = encode_state(msg, sign=lambda body: (b"S" * 64, "car-2-key"))
    env = unpack_envelope(data)
    out = decode_state(data)
    assert out.sig == b"S" * 64 and out.key_id == "car-2-key"
    assert out.signed_payload == env.body
    # the signed bytes do not depend on the signature
    assert unpack_envelope(encode_state(msg)).body == env.body


def test_relative_roundtrip_valid_and_timeout():
    res = RelativeResult(target_id="car-2", fleet="test", master_id="m1", seq=3, source_seq=17,
                         t_gps_s=1.4e9, latency_s=0.1, rel_pos_body_m=np.array([12.0, -1.5, 0.2]),
                         rel_pos_sd_m=np.array([0.01, 0.01, 0.02]), rel_vel_body_mps=np.array([-2.0, 0.1, 0.0]),
                         rel_acc_body_mps2=np.array([0.5, 0.0, 0.0]), rel_rpy_rad=np.array([0.0, 0.01, -0.2]),
                         range_m=12.1, range_sd_m=0.01, bearing_rad=-0.124, elevation_rad=-0.016,
                         longitudinal_m=7.3, lateral_m=-1.2, gap_m=7.4, closing_speed_mps=2.0, ttc_s=3.7)
    assert decode_relative(encode_relative(res)) == res
    timeout = RelativeResult(target_id="car-2", fleet="test", master_id="m1", status=TargetStatus.TIMEOUT,
                             latency_s=0.35)
    out = decode_relative(encode_relative(timeout))
    assert out == timeout and math.isnan(out.range_m) and not out.has_kinematics
    fix = RelativeResult(target_id="car-2", fleet="test", master_id="m1", status=TargetStatus.FIX_INVALID,
                         fix_side=FixSide.MASTER | FixSide.SLAVE)
    assert decode_relative(encode_relative(fix)).fix_side == FixSide.MASTER | FixSide.SLAVE
