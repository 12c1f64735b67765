"""decode_state's cache of validated geometry maps never admits what the full check rejects."""
from __future__ import annotations

import msgpack
import numpy as np
import pytest

from v2xpos.types import FixStatus
from v2xpos.wire import Geometry, StateMessage, WireError, decode_state, encode_state, encode_state_body, pack_envelope


def _msg(geometry: Geometry) -> StateMessage:
    return StateMessage("f", "v1", 1, 1.4e9, FixStatus.FIXED, 0.8, 0.2, 100.0, np.zeros(3), np.zeros(3), np.zeros(3),
                        np.zeros(3), np.full(3, 0.01), np.full(3, 0.02), np.full(3, 0.001), geometry)


def _with_geometry(g: dict) -> bytes:
    body = msgpack.unpackb(encode_state_body(_msg(Geometry())), raw=False)
    body["g"] = g
    return pack_envelope(msgpack.packb(body, use_bin_type=True))


def test_repeated_geometry_decodes_equal_and_independent():
    box = Geometry.box(1.0, 1.0, 1.0)
    a, b = decode_state(encode_state(_msg(box))), decode_state(encode_state(_msg(box)))
    assert a.geometry == box and b.geometry == box
    a.geometry.points_body_m[0, 0] = 99.0          # each message owns its arrays
    assert b.geometry == box


@pytest.mark.parametrize("bad", [
    {"k": "polygon", "p": [1.0, 1.0, 0.0, True, -1.0, 0.0, -1.0, -1.0, 0.0], "r": 0.0},   # bool == 1.0
    {"k": "polygon", "p": [1.0, 1.0, 0.0, 1.0, -1.0, 0.0, -1.0, -1.0, 0.0], "r": True},
    {"k": ["polygon"], "p": [1.0, 1.0, 0.0, 1.0, -1.0, 0.0, -1.0, -1.0, 0.0], "r": 0.0},
    {"k": "polygon", "p": [1.0, 1.0, 0.0, 1.0, -1.0, 0.0, -1.0, -1.0, [0.0]], "r": 0.0},
])
def test_cached_valid_geometry_does_not_admit_equal_looking_invalid_one(bad):
    good = {"k": "polygon", "p": [1.0, 1.0, 0.0, 1.0, -1.0, 0.0, -1.0, -1.0, 0.0], "r": 0.0}
    for _ in range(2):
        assert decode_state(_with_geometry(good)).geometry.kind == "polygon"
    with pytest.raises(WireError):
        decode_state(_with_geometry(bad))
