"""A slave written from docs/protocol.md alone (plain msgpack) is accepted by decode_state."""
import math
import re
import time
from pathlib import Path

import msgpack
import numpy as np

from v2xpos.types import FixStatus
from v2xpos.wire import decode_state, state_key

DOC = Path(__file__).resolve().parents[1] / "docs" / "protocol.md"


def test_documented_example_decodes():
    text = DOC.read_text()
    code = re.search(r"### Minimal compatible slave.*?```python\n(.*?)```", text, re.S).group(1)
    scope: dict = {}
    exec(compile(code, str(DOC), "exec"), scope)   # the snippet as documented
    msg = decode_state(scope["payload"])
    assert msg.vehicle_id == "car-7" and msg.fix == FixStatus.FIXED and msg.seq == 42
    assert msg.geometry.kind == "polygon" and msg.geometry.points_body_m.shape == (4, 3)
    assert abs(msg.t_sent_wall_s - time.time()) < 60
    assert state_key(msg.fleet, msg.vehicle_id) == "v2xpos/demo/vehicle/car-7/state"


def test_integers_for_floats_and_unknown_keys_are_accepted():
    body = {"T": "state", "ver": 1, "fleet": "f", "id": "x", "kind": "pedestrian", "seq": 0, "t": 1400000000,
            "fix": 4, "lat": 0, "lon": 1, "h": 100, "v": [1, 0, 0], "a": [0, 0, 0], "w": [0, 0, 0],
            "rpy": [0, 0, 3], "sp": [0, 0, 0], "sv": [0, 0, 0], "sa": [0, 0, 0], "g": {"k": "circle", "r": 0.3},
            "future_field": {"anything": [1, 2, 3]}}
    msg = decode_state(msgpack.packb([1, msgpack.packb(body, use_bin_type=True), None, None], use_bin_type=True))
    assert msg.kind == "pedestrian" and msg.geometry.radius_m == 0.3 and msg.t_gps_s == 1.4e9
    assert msg.v_ned_mps.dtype == np.float64 and math.isclose(msg.rpy_rad[2], 3.0)
