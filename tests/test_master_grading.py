"""Master-side IMU grading: the IMU stream payload is validated (malformed counted, never raised)
and a vehicle's faulty unit is graded fail from streamed chunks."""
from __future__ import annotations

import msgpack
import numpy as np
import pytest

from master.grading import FleetGrader, ImuPayloadError, parse_imu_payload
from sim.imu_faults import simulate_vehicle


def chunks(v, vid: str, n: int = 25):
    t = v.units["imu1"].t_s
    for i0 in range(0, len(t), n):
        units = {u: np.column_stack([imu.t_s[i0:i0 + n], imu.acc_mps2[i0:i0 + n], imu.gyro_rps[i0:i0 + n]]).tolist()
                 for u, imu in v.units.items()}
        yield msgpack.packb({"T": "imu", "ver": 1, "fleet": "f", "id": vid, "rate_hz": 100.0,
                             "mounting_xyz_deg": {k: [float(x) for x in m] for k, m in v.mounting_xyz_deg.items()},
                             "units": units})


@pytest.mark.parametrize("payload", [
    b"\x00\x01", msgpack.packb([1, 2]), msgpack.packb({"T": "imu", "ver": 2, "id": "a", "units": {"u": []}}),
    msgpack.packb({"T": "imu", "ver": 1, "id": "a", "units": {"u": [[1, 2, 3]]}}),
    msgpack.packb({"T": "imu", "ver": 1, "id": "a", "units": {"u": [[float("nan")] * 7]}}),
    msgpack.packb({"T": "imu", "ver": 1, "id": "", "units": {"u": [[0.0] * 7]}}),
    msgpack.packb({"T": "imu", "ver": 1, "id": "a", "units": {"u": [[0.0] * 7]}, "mounting_xyz_deg": {"u": 5}}),
    msgpack.packb({"T": "imu", "ver": 1, "id": "a", "units": {"u": [[0.0] * 7]}, "mounting_xyz_deg": {"u": "x"}}),
    msgpack.packb({"T": "imu", "ver": 1, "id": "a", "units": {"u": [[0.0] * 7]}, "mounting_xyz_deg": {"u": [1, 2]}}),
])
def test_malformed_imu_payloads_are_rejected(payload):
    with pytest.raises(ImuPayloadError):
        parse_imu_payload(payload)
    fg = FleetGrader()
    fg.add_payload(payload)
    assert fg.malformed == 1 and fg.graders == {}


def test_streamed_chunks_grade_the_faulty_unit():
    v = simulate_vehicle(3, "gyro_scale", seed=4, duration_s=25.0, grade="tactical")
    fg = FleetGrader(min_history_s=10.0, regrade_every_s=5.0)
    for p in chunks(v, "car1"):
        fg.add_payload(p)
    fg.add_payload(b"junk")
    g = fg.grades()["car1"]
    assert g["status"] == "graded" and fg.malformed == 1
    assert g["units"][v.faulty] == "fail"
    assert all(grade != "fail" for u, grade in g["units"].items() if u != v.faulty)
