"""Master-side IMU grading: the IMU stream payload is validated (malformed counted, never raised),
a vehicle's faulty unit is graded fail from streamed chunks, and a unit is published "fail" (the
vehicle DEGRADED) only when its raw fail persists over consecutive regrades (hysteresis)."""
from __future__ import annotations

import msgpack
import numpy as np
import pytest

from master.grading import FAIL_CLEAR_REGRADES, FAIL_CONFIRM_REGRADES, FleetGrader, GradeHysteresis
from sim.imu_faults import simulate_vehicle
from v2xpos.wire import ImuPayloadError, decode_imu_payload, encode_imu_payload


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
        decode_imu_payload(payload)
    fg = FleetGrader()
    fg.add_payload(payload)
    assert fg.malformed == 1 and fg.graders == {}


def test_imu_payload_encoder_writes_the_documented_map_and_decodes_back():
    """The slave's encoder against the layout written out by hand (``chunks`` above, docs/protocol.md)."""
    v = simulate_vehicle(2, "gyro_scale", seed=1, duration_s=2.0, grade="tactical")
    mounting = {k: [float(x) for x in m] for k, m in v.mounting_xyz_deg.items()}
    units = {u: (imu.t_s[:25], imu.acc_mps2[:25], imu.gyro_rps[:25]) for u, imu in v.units.items()}
    data = encode_imu_payload("f", "car1", units, mounting)
    assert msgpack.unpackb(data) == msgpack.unpackb(next(chunks(v, "car1")))
    p = decode_imu_payload(data)
    assert (p.vehicle_id, p.fleet, p.rate_hz, p.mounting_xyz_deg) == ("car1", "f", 100.0, mounting)
    for u, (t, acc, gyro) in units.items():
        np.testing.assert_array_equal(p.units[u][0], t)
        np.testing.assert_array_equal(p.units[u][1], acc)
        np.testing.assert_array_equal(p.units[u][2], gyro)


def test_streamed_chunks_grade_the_faulty_unit():
    """Streamed as a slave does, asked every second as the worker does: from the first regrade on (10 s
    of a drive with little turning) the faulty unit is the only raw "fail" -- the gyro correlation
    counts only the windows with motion, so the healthy units do not fail for want of it and no
    regrade is inconclusive -- and it is published "fail" from the second regrade on."""
    v = simulate_vehicle(3, "gyro_scale", seed=4, duration_s=35.0, grade="tactical")
    fg = FleetGrader(min_history_s=10.0, regrade_every_s=5.0)
    for k, p in enumerate(chunks(v, "car1")):
        fg.add_payload(p)
        if k % 4 == 3:                                  # the worker asks every second (4 chunks of 0.25 s)
            fg.grades()
    fg.add_payload(b"junk")
    g = fg.grades()["car1"]
    assert g["status"] == "graded" and fg.malformed == 1
    assert g["regrades"] == 5                           # at 10, 15, ... 30 s of data
    assert all(h["raw"][v.faulty] == "fail" for h in g["history"])
    assert g["units"][v.faulty] == "fail" and g["inconclusive_regrades"] == 0
    assert all(grade != "fail" for h in g["history"] for u, grade in h["raw"].items() if u != v.faulty)
    assert [h["published"][v.faulty] for h in g["history"]] == ["warn"] + ["fail"] * 4
    assert all(grade != "fail" for u, grade in g["units"].items() if u != v.faulty)


def test_a_lost_payload_is_counted_as_a_gap():
    """A payload lost on the way leaves the grader interpolating across its 0.25 s: counted, with the
    time lost, so that a grade over lost data says so; a complete stream counts none."""
    v = simulate_vehicle(3, "gyro_scale", seed=4, duration_s=12.0, grade="tactical")
    for drop in (None, 17):
        fg = FleetGrader(min_history_s=10.0, regrade_every_s=5.0)
        for k, p in enumerate(chunks(v, "car1")):
            if k != drop:
                fg.add_payload(p)
        gaps = fg.grades()["car1"]["gaps"]
        if drop is None:
            assert gaps == {"count": 0, "lost_s": 0.0}
        else:
            assert gaps["count"] == 1 and gaps["lost_s"] == pytest.approx(0.25, abs=0.011)


def test_hysteresis_transient_is_a_warning_persistent_is_a_failure():
    h = GradeHysteresis(confirm=3, clear=3)
    seq = ["fail", "pass", None, "fail", "fail", "warn", "fail", "fail", "fail", "pass", "pass", None, "fail",
           "pass", "pass", "pass", "pass"]
    out = [h.update({"u": g})["u"] for g in seq]
    assert out == ["warn", "pass", None, "warn", "warn", "warn", "warn", "warn", "fail", "fail", "fail", "fail", "fail",
                   "fail", "fail", "pass", "pass"]
    assert h.transient == {"u": 5}
    h2 = GradeHysteresis(confirm=3, clear=3)
    h2.update({"a": "fail", "b": "pass"})
    assert h2.warnings() == {"a": "transient fail (1 of 3 consecutive regrades)"}


def test_every_unit_failing_together_is_inconclusive():
    h = GradeHysteresis(confirm=2, clear=3)
    allfail = {"a": "fail", "b": "fail", "c": "fail"}
    for _ in range(4):                                   # any number of them: nobody degraded
        assert set(h.update(allfail).values()) == {"warn"}
    assert h.inconclusive_regrades == 4 and "inconclusive" in h.warnings()["a"]
    assert h.update({"a": "pass", "b": "pass", "c": "fail"})["c"] == "warn"
    assert h.update({"a": "pass", "b": "pass", "c": "fail"})["c"] == "fail"      # 2 conclusive in a row
    assert h.update(allfail) == {"a": "warn", "b": "warn", "c": "fail"}          # keeps, neither clears
    two = GradeHysteresis(confirm=2, clear=3)                                    # two units: no such rule
    two.update({"a": "fail", "b": "fail"})
    assert two.update({"a": "fail", "b": "fail"}) == {"a": "fail", "b": "fail"}
    with pytest.raises(ValueError):
        GradeHysteresis(confirm=0)
    assert (FAIL_CONFIRM_REGRADES, FAIL_CLEAR_REGRADES) == (2, 3)


class _ScriptedGrader:
    """Stands in for a VehicleGrader: one scripted regrade per call of ``next_regrade``."""

    def __init__(self, script):
        self.script, self.k = script, 0

    def next_regrade(self):
        self.k += 1

    def grades(self):
        if self.k == 0:
            return {"t_s": 0.0, "status": "collecting", "units": {u: None for u in self.script[0]},
                    "rejected_samples": 0}
        return {"t_s": 100.0 + 5 * self.k, "status": "graded", "units": self.script[self.k - 1],
                "rejected_samples": 0}


def test_one_filter_step_per_regrade_not_per_publication():
    """The worker publishes every second; a regrade comes every 5 s of data: repeated publications of
    one regrade must not count as consecutive regrades. A healthy vehicle whose three units all
    fail at one regrade (the demo's false degradation) is never degraded."""
    fg = FleetGrader()
    healthy = _ScriptedGrader([{"imu1": "fail", "imu2": "fail", "imu3": "fail"}] + [{"imu1": "pass", "imu2": "pass",
                                                                                     "imu3": "pass"}] * 4)
    faulty = _ScriptedGrader([{"imu1": "warn", "imu2": "warn", "imu3": "fail"}] * 5)
    for vid, g in (("t1", healthy), ("t2", faulty)):
        fg.graders[vid] = g
        fg.filters[vid] = GradeHysteresis()
    degraded_seen = {"t1": False, "t2": False}
    assert fg.grades()["t1"]["units"] == {"imu1": None, "imu2": None, "imu3": None}
    for _ in range(5):
        healthy.next_regrade()
        faulty.next_regrade()
        for _ in range(5):                              # five publications per regrade
            out = fg.grades()
            for vid in degraded_seen:
                degraded_seen[vid] |= any(v == "fail" for v in out[vid]["units"].values())
        if healthy.k == 1:
            assert out["t1"]["warnings"] and out["t1"]["units"]["imu1"] == "warn"
        if faulty.k < FAIL_CONFIRM_REGRADES:
            assert out["t2"]["units"]["imu3"] == "warn"
    assert degraded_seen == {"t1": False, "t2": True}
    assert out["t1"]["regrades"] == 5 and out["t1"]["degraded_regrades"] == 0
    assert out["t1"]["transient_fails"] == {"imu1": 1, "imu2": 1, "imu3": 1}
    assert out["t2"]["degraded_regrades"] == 4 and out["t2"]["first_degraded_t_s"] == 110.0
    assert [h["published"]["imu3"] for h in out["t2"]["history"]] == ["warn", "fail", "fail", "fail", "fail"]


def test_regrades_follow_the_data_not_the_publication_clock():
    """A starved worker (niced, under load) may not publish for many seconds; every regrade due in
    the data still happens, at the same data times as when it is asked every second. Before the
    payloads stepped the graders, a worker asked once at the end regraded once (the demo's faulty
    unit published "warn" instead of "fail" on a loaded machine)."""
    v = simulate_vehicle(3, "gyro_scale", seed=4, duration_s=35.0, grade="tactical")
    polled, starved = FleetGrader(min_history_s=10.0, regrade_every_s=5.0), FleetGrader(min_history_s=10.0,
                                                                                         regrade_every_s=5.0)
    for k, p in enumerate(chunks(v, "car1")):
        polled.add_payload(p)
        starved.add_payload(p)
        if k % 4 == 3:
            polled.grades()
    a, b = polled.grades()["car1"], starved.grades()["car1"]
    assert b["regrades"] == a["regrades"] == 5
    assert [h["t_s"] for h in b["history"]] == [h["t_s"] for h in a["history"]]
    assert b["units"] == a["units"] and b["units"][v.faulty] == "fail"


def test_a_regrade_that_raises_is_counted_and_grading_goes_on(monkeypatch):
    """The worker's consumer: a payload whose grading raises is counted, the next ones are graded."""
    import queue

    from master.grading import _consume
    v = simulate_vehicle(3, "gyro_scale", seed=4, duration_s=12.0, grade="tactical")
    fg = FleetGrader(min_history_s=10.0, regrade_every_s=5.0)
    real = fg.add_payload
    calls = {"n": 0}

    def flaky(data: bytes) -> None:
        calls["n"] += 1
        if calls["n"] == 3:
            raise ValueError("the units do not overlap in time")
        real(data)
    monkeypatch.setattr(fg, "add_payload", flaky)
    inbox: queue.SimpleQueue = queue.SimpleQueue()
    for p in chunks(v, "car1"):
        inbox.put(p)
    inbox.put(None)
    _consume(inbox, fg)
    assert fg.grading_errors == 1
    g = fg.grades()["car1"]
    assert g["status"] == "graded" and g["units"][v.faulty] in ("warn", "fail")
