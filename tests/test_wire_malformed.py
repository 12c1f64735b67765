"""decode_state rejects every kind of malformed input with a WireError naming the reason and field."""
import math

import msgpack
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from v2xpos.types import FixStatus
from v2xpos.wire import (MAX_MESSAGE_BYTES, Geometry, StateMessage, WireError, decode_relative, decode_state,
                         encode_state, encode_state_body, pack_envelope)


def good() -> StateMessage:
    return StateMessage(fleet="test", vehicle_id="car-2", seq=17, t_gps_s=1.4e9, fix=FixStatus.FIXED,
                        lat_rad=0.6981, lon_rad=-1.8326, height_m=1612.5, v_ned_mps=np.array([19.5, -3.25, 0.1]),
                        acc_body_mps2=np.array([-1.5, 2.0, 0.05]), rate_body_rps=np.array([0.01, -0.02, 0.3]),
                        rpy_rad=np.array([0.02, -0.01, 2.5]), pos_sd_m=np.array([0.01, 0.012, 0.02]),
                        vel_sd_mps=np.array([0.02, 0.02, 0.03]), att_sd_rad=np.array([0.001, 0.001, 0.004]),
                        geometry=Geometry.box(3.8, 1.0, 0.9))


def body_map() -> dict:
    return msgpack.unpackb(encode_state_body(good()), raw=False)


def with_body(**changes) -> bytes:
    m = body_map()
    for k, v in changes.items():
        if v is KeyError:
            del m[k]
        else:
            m[k] = v
    return pack_envelope(msgpack.packb(m, use_bin_type=True))


def rejects(data: bytes, field, reason_part: str = "") -> WireError:
    with pytest.raises(WireError) as info:
        decode_state(data)
    assert info.value.field == field, (info.value.reason, info.value.field)
    assert reason_part in info.value.reason
    return info.value


def test_good_message_decodes():
    assert decode_state(encode_state(good())) == good()


@pytest.mark.parametrize("data,field,reason", [
    (b"", "envelope", "not msgpack"),
    (b"\xc1\x00\xff", "envelope", "not msgpack"),
    (msgpack.packb({"a": 1}), "envelope", "4-element"),
    (msgpack.packb([2, b"x", None, None]), "envelope.version", "unknown envelope version"),
    (msgpack.packb([1, "text", None, None]), "envelope.body", "bin"),
    (msgpack.packb([1, b"x", "sig", None], use_bin_type=True), "envelope.sig", "bin"),
    (pack_envelope(b"\x92\x01\x02"), "body", "not a map"),
    (pack_envelope(b"\xc1"), "body", "not msgpack"),
])
def test_envelope_errors(data, field, reason):
    rejects(data, field, reason)


def test_oversize_rejected_before_parsing():
    err = rejects(b"\x00" * (MAX_MESSAGE_BYTES + 1), None, "oversize")
    assert str(MAX_MESSAGE_BYTES) in err.reason


@pytest.mark.parametrize("changes,field,reason", [
    ({"T": "relative"}, "T", "not 'state'"),
    ({"ver": 99}, "ver", "unknown schema version"),
    ({"ver": "1"}, "ver", "non-integer"),
    ({"seq": KeyError}, "seq", "missing"),
    ({"lat": KeyError}, "lat", "missing"),
    ({"seq": -1}, "seq", "out of range"),
    ({"seq": 1.5}, "seq", "not an integer"),
    ({"seq": True}, "seq", "not an integer"),
    ({"lat": "0.5"}, "lat", "not a number"),
    ({"lat": True}, "lat", "not a number"),
    ({"lat": math.nan}, "lat", "non-finite"),
    ({"h": math.inf}, "h", "non-finite"),
    ({"lat": 1.6}, "lat", "out of range"),
    ({"lon": -3.2}, "lon", "out of range"),
    ({"t": -1.0}, "t", "out of range"),
    ({"v": [151.0, 0.0, 0.0]}, "v", "out of range"),
    ({"v": [110.0, 110.0, 0.0]}, "v", "speed above"),
    ({"v": [1.0, 2.0]}, "v", "3 numbers"),
    ({"v": [1.0, math.nan, 2.0]}, "v", "non-finite"),
    ({"a": [0, 0, 1000.0]}, "a", "out of range"),
    ({"w": [0, 0, "x"]}, "w", "not a number"),
    ({"rpy": [0.0, 1.7, 0.0]}, "rpy", "pitch"),
    ({"sp": [0.01, -0.01, 0.02]}, "sp", "negative"),
    ({"sv": [0.01, 0.01, math.inf]}, "sv", "non-finite"),
    ({"fix": 9}, "fix", "unknown fix status"),
    ({"fix": -1}, "fix", "out of range"),
    ({"kind": "bicycle"}, "kind", "kind must be"),
    ({"id": ""}, "id", "identifier"),
    ({"id": "car/2"}, "id", "identifier"),
    ({"id": "car\n"}, "id", "identifier"),
    ({"fleet": "a*"}, "fleet", "identifier"),
    ({"fleet": "x" * 33}, "fleet", "identifier"),
    ({"id": 7}, "id", "not a string"),
    ({"g": [1, 2]}, "g", "not a map"),
    ({"g": {"k": "blob", "p": []}}, "g.k", "geometry kind"),
    ({"g": {"k": "polygon", "p": [0.0, 0.0, 0.0, 1.0, 1.0]}}, "g.p", "3N"),
    ({"g": {"k": "polygon", "p": [0.0] * 6}}, "g.p", "three vertices"),
    ({"g": {"k": "points", "p": [0.0, 0.0, 1e4]}}, "g.p", "within 100 m"),
    ({"g": {"k": "points", "p": [0.0] * (3 * 65)}}, "g.p", "more than 64"),
    ({"g": {"k": "circle", "p": [], "r": -0.5}}, "g.r", "out of range"),
    ({"tw": "now"}, "tw", "not a number"),
    ({"iq": [1, 2]}, "iq", "imu_quality"),
])
def test_body_errors_name_the_field(changes, field, reason):
    rejects(with_body(**changes), field, reason)


def test_relative_decoder_rejects_state_messages():
    with pytest.raises(WireError) as info:
        decode_relative(encode_state(good()))
    assert info.value.field == "T"


@settings(max_examples=200, deadline=None)
@given(st.binary(max_size=600))
def test_random_bytes_never_crash(data):
    try:
        decode_state(data)
    except WireError as err:
        assert err.reason


@settings(max_examples=200, deadline=None)
@given(st.data())
def test_mutated_fields_are_decoded_or_rejected(data):
    m = body_map()
    key = data.draw(st.sampled_from(sorted(m)))
    m[key] = data.draw(st.one_of(st.none(), st.booleans(), st.integers(-2 ** 63, 2 ** 64 - 1), st.floats(), st.text(max_size=5),
                                 st.lists(st.floats(), max_size=4), st.binary(max_size=4)))
    try:
        msg = decode_state(pack_envelope(msgpack.packb(m, use_bin_type=True)))
    except WireError as err:
        assert err.field is not None
    else:
        assert abs(msg.lat_rad) <= math.pi / 2 and np.all(np.isfinite(msg.v_ned_mps))


def test_relative_kinematics_errors_are_prefixed():
    from v2xpos.wire import RelativeResult, encode_relative_body
    res = RelativeResult(target_id="a", fleet="f", master_id="m", rel_pos_body_m=np.ones(3), rel_pos_sd_m=np.ones(3),
                         rel_vel_body_mps=np.ones(3), rel_acc_body_mps2=np.ones(3), rel_rpy_rad=np.zeros(3),
                         range_m=1.7, range_sd_m=0.1, bearing_rad=0.7, elevation_rad=-0.6, longitudinal_m=1,
                         lateral_m=1, gap_m=1.4, closing_speed_mps=0.0, ttc_s=None)
    m = msgpack.unpackb(encode_relative_body(res), raw=False)
    m["kin"]["rng"] = -1.0
    with pytest.raises(WireError) as info:
        decode_relative(pack_envelope(msgpack.packb(m, use_bin_type=True)))
    assert info.value.field == "kin.rng"
