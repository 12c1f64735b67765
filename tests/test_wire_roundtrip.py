"""Roundtrip of the wire messages (StateMessage, RelativeResult, envelope with signature slot)."""
import math

import msgpack
import numpy as np
import pytest

from v2xpos.types import FixStatus
from v2xpos.wire import (KINEMATIC_STATUSES, RELATIVE_SCHEMA_VERSION, FixSide, Geometry, RelativeResult,
                         StateMessage, TargetStatus, WireError, decode_relative, decode_state, encode_relative,
                         encode_state, pack_envelope, unpack_envelope)


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


def _kinematic(**kw) -> RelativeResult:
    base = dict(target_id="car-2", fleet="test", master_id="m1", seq=4, source_seq=18, t_gps_s=1.4e9 + 0.05,
                latency_s=0.08, rel_pos_body_m=np.array([12.0, -1.5, 0.2]), rel_pos_sd_m=np.array([0.03, 0.02, 0.05]),
                rel_vel_body_mps=np.array([-2.0, 0.1, 0.0]), rel_acc_body_mps2=np.array([0.5, 0.0, 0.0]),
                rel_rpy_rad=np.array([0.0, 0.01, -0.2]), range_m=12.1, range_sd_m=0.03, bearing_rad=-0.124,
                elevation_rad=-0.016, longitudinal_m=7.3, lateral_m=-1.2, gap_m=7.4, closing_speed_mps=2.0,
                ttc_s=3.7, master_fix=FixStatus.FIXED, target_fix=FixStatus.FLOAT, rel_yaw_sd_rad=0.0123)
    base.update(kw)
    return RelativeResult(**base)


@pytest.mark.parametrize("status", sorted(KINEMATIC_STATUSES))
def test_kinematic_statuses_carry_fix_states_kinematics_and_yaw_sigma(status):
    res = _kinematic(status=status)
    out = decode_relative(encode_relative(res))
    assert out == res and out.schema == RELATIVE_SCHEMA_VERSION
    assert out.master_fix == FixStatus.FIXED and out.target_fix == FixStatus.FLOAT
    assert out.rel_yaw_sd_rad == 0.0123 and out.has_kinematics
    assert (out.status == TargetStatus.VALID) == (status == TargetStatus.VALID)


def test_non_kinematic_status_keeps_fix_states_and_no_kinematics():
    res = RelativeResult(target_id="car-2", fleet="test", master_id="m1", status=TargetStatus.FIX_INVALID,
                         fix_side=FixSide.SLAVE, master_fix=FixStatus.FIXED, target_fix=FixStatus.SINGLE)
    out = decode_relative(encode_relative(res))
    assert out.master_fix == FixStatus.FIXED and out.target_fix == FixStatus.SINGLE
    assert math.isnan(out.range_m) and math.isnan(out.rel_yaw_sd_rad)
    assert "kin" not in msgpack.unpackb(unpack_envelope(encode_relative(res)).body, raw=False)


def test_schema_1_messages_still_decode():
    """A body written by a version-1 master (no fix states, no yaw sigma, kinematics on VALID only)."""
    body = msgpack.unpackb(unpack_envelope(encode_relative(_kinematic())).body, raw=False)
    body["ver"] = 1
    del body["mfix"], body["tfix"], body["kin"]["ys"]
    out = decode_relative(pack_envelope(msgpack.packb(body, use_bin_type=True)))
    assert out.schema == 1 and out.status == TargetStatus.VALID
    assert out.master_fix == FixStatus.NONE and out.target_fix == FixStatus.NONE and math.isnan(out.rel_yaw_sd_rad)
    np.testing.assert_array_equal(out.rel_pos_body_m, [12.0, -1.5, 0.2])
    body["status"] = int(TargetStatus.ATTITUDE_UNCERTAIN)     # did not exist in schema 1
    with pytest.raises(WireError, match="schema 1") as info:
        decode_relative(pack_envelope(msgpack.packb(body, use_bin_type=True)))
    assert info.value.field == "status"


@pytest.mark.parametrize("edit, field", [
    (lambda b: b.pop("mfix"), "mfix"),
    (lambda b: b.update(tfix=9), "tfix"),
    (lambda b: b.update(ver=99), "ver"),
    (lambda b: b["kin"].update(ys=-0.1), "kin.ys"),
    (lambda b: b.pop("kin"), "kin"),
])
def test_schema_2_fields_are_validated(edit, field):
    body = msgpack.unpackb(unpack_envelope(encode_relative(_kinematic(status=TargetStatus.SIGMA_EXCEEDED))).body,
                           raw=False)
    edit(body)
    with pytest.raises(WireError) as info:
        decode_relative(pack_envelope(msgpack.packb(body, use_bin_type=True)))
    assert info.value.field == field
