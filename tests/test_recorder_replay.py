"""MCAP recorder (all inputs and outputs, rotation by size, readable back) and exact session replay."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest
from mcap.reader import make_reader

from master import replay_session as rs
from master.pipeline import MasterPipeline, PipelineConfig
from v2xpos import security as sec
from v2xpos.output import recorder as rec
from v2xpos.output import recording_schema as schema
from v2xpos.types import FixStatus, NavState
from v2xpos.wire import Geometry, StateMessage, decode_relative, encode_state, state_key

pytestmark = pytest.mark.slow   # whole sessions recorded, some through the recorder child process, and replayed

T0 = 1.4e9


def _nav(t: float, fix=FixStatus.FIXED) -> NavState:
    return NavState(t_s=t, lla=np.array([0.7, -1.8 + 1e-7 * (t - T0), 1600.0]),
                    v_ned_mps=np.array([0.0, 20.0, 0.0]), acc_body_mps2=np.array([0.1, 0.0, 0.0]),
                    rate_body_rps=np.array([0.0, 0.0, 0.02]), rpy_rad=np.array([0.0, 0.0, math.pi / 2]),
                    pos_sd_m=np.full(3, 0.01), vel_sd_mps=np.full(3, 0.02), att_sd_rad=np.full(3, 1e-3),
                    fix=fix)


def _slave(vid: str, seq: int, t: float, fix=FixStatus.FIXED) -> StateMessage:
    n = _nav(t, fix)
    n.lla = n.lla + np.array([0.0, 3e-6 * (1 + int(vid[-1])), 0.0])
    return StateMessage.from_nav_state(n, "demo", vid, seq, geometry=Geometry.box(3.8, 1.0, 0.9),
                                       t_sent_wall_s=1.7e9 + (t - T0))


def _drive(pipe, signers, n_steps=400):
    """Two signed slaves at 100 Hz with faults: malformed, replayed, forged, fix drop, a delay
    spike (timeout) and silence ticks."""
    outsider = sec.MessageSigner(sec.Ed25519PrivateKey.generate())
    captured = None
    for k in range(n_steps):
        t = T0 + 0.01 * k
        nav = _nav(t, FixStatus.FLOAT if 200 <= k < 220 else FixStatus.FIXED)
        for vid in ("car1", "car2"):
            if vid == "car2" and 300 <= k < 340:
                continue  # car2 silent for 0.4 s
            t_valid = t - (0.3 if (vid == "car1" and k == 150) else 0.005)
            fix = FixStatus.SINGLE if (vid == "car2" and 100 <= k < 110) else FixStatus.FIXED
            payload = encode_state(_slave(vid, k, t_valid, fix), sign=signers[vid])
            if k == 50 and vid == "car1":
                captured = payload
            pipe.handle(payload, state_key("demo", vid), nav, t + 0.002, 1.7e9 + 0.01 * k)
        if k % 37 == 0:
            pipe.handle(b"\x93\x01\xc4", state_key("demo", "car1"), nav, t + 0.002, 1.7e9 + 0.01 * k)
        if k == 120:
            pipe.handle(captured, state_key("demo", "car1"), nav, t + 0.002, 1.7e9 + 0.01 * k)
            forged = encode_state(_slave("car1", 10_000, t - 0.004), sign=outsider)
            pipe.handle(forged, state_key("demo", "car1"), nav, t + 0.002, 1.7e9 + 0.01 * k)
        if k % 10 == 0:
            pipe.tick(t + 0.003, t)


@pytest.fixture(params=["in_process", "child_process"])
def recorded_session(tmp_path, request):
    """The same session recorded by McapRecorder in the pipeline's process and by RecorderProcess
    (the master's default: the writing happens in a child process)."""
    trust = sec.TrustList()
    signers = {}
    for vid in ("car1", "car2"):
        signers[vid] = sec.MessageSigner(sec.Ed25519PrivateKey.generate())
        trust.add(vid, signers[vid].public_key)
    pipe = MasterPipeline(PipelineConfig(fleet="demo", master_id="ego", measurement_point_m=(3.8, 0, 0),
                                         known_vehicles=("car1", "car2")),
                          authenticator=sec.MessageAuthenticator(trust))
    path = tmp_path / "rec" / "session.mcap"
    if request.param == "in_process":
        recorder = rec.McapRecorder(path, max_bytes=60_000, chunk_size=8_000)
    else:
        from v2xpos.output.recorder_process import RecorderProcess
        recorder = RecorderProcess(path, max_bytes=60_000, chunk_size=8_000)
    wrapped = rec.RecordingPipeline(pipe, recorder)
    _drive(wrapped, signers)
    recorder.close()
    return path, pipe, recorder


def test_everything_recorded_rotated_and_readable(recorded_session):
    path, pipe, recorder = recorded_session
    files = rec.recording_files(path)
    assert len(files) >= 3 and files == recorder.files
    msgs = list(rec.read_recording(path))
    by_topic = {t: [m for m in msgs if m.topic == t] for t in schema.SCHEMAS}
    n_received = 400 * 2 - 40 + 11 + 2
    assert len(by_topic[schema.TOPIC_RX]) == n_received == recorder.recorded[schema.TOPIC_RX]
    assert len(by_topic[schema.TOPIC_RELATIVE]) == pipe.seq == recorder.recorded[schema.TOPIC_RELATIVE]
    assert len(by_topic[schema.TOPIC_TICK]) == 40
    assert pipe.rejected["malformed"] == 11
    assert pipe.rejected[sec.REJECT_UNKNOWN_KEY] == 1
    # the replayed capture is stopped by the pipeline's sequence check or by the authenticator
    assert pipe.rejected[sec.REJECT_REPLAY] + pipe.rejected["out_of_order"] + pipe.rejected["duplicate"] >= 1
    statuses = {m.doc["status"] for m in by_topic[schema.TOPIC_RELATIVE]}
    assert {"valid", "fix_invalid", "timeout"} <= statuses
    # the outputs are readable JSON, and their raw bytes (replay reference) decode to the same
    raw = [decode_relative(__import__("base64").b64decode(m.doc["payload_b64"]))
           for m in by_topic[schema.TOPIC_RAW_RELATIVE]]
    assert [r.seq for r in raw] == [m.doc["seq"] for m in by_topic[schema.TOPIC_RELATIVE]]
    first = by_topic[schema.TOPIC_RELATIVE][0].doc
    assert first["target_id"] in ("car1", "car2") and first["target_id"] == raw[0].target_id
    valid = next(m.doc for m in by_topic[schema.TOPIC_RELATIVE] if m.doc["status"] == "valid")
    assert len(valid["rel_vel_body_mps"]) == 3 and len(valid["rel_roll_pitch_yaw_deg"]) == 3
    # received states decoded (no base64 in the readable channel); malformed ones say why
    rx = by_topic[schema.TOPIC_RX]
    assert sum(m.doc["error"] is not None for m in rx) == 11
    good = next(m.doc["message"] for m in rx if m.doc["message"] is not None)
    assert good["vehicle_id"] in ("car1", "car2") and good["fix"] == "FIXED" and good["signed"]
    # every file is a complete MCAP: JSON channels with jsonschema schemas and Foxglove's protobuf ones
    for f in files:
        with open(f, "rb") as fh:
            summary = make_reader(fh).get_summary()
        assert {c.message_encoding for c in summary.channels.values()} == {"json", "protobuf"}
        assert {s.encoding for s in summary.schemas.values()} == {"jsonschema", "protobuf"}
    session = rec.read_session(files[-1])
    assert session["pipeline_config"]["timeout_s"] == pytest.approx(0.2)
    assert "car1" in json.dumps(session["authenticator"])


def test_replay_session_reproduces_outputs_exactly(recorded_session, monkeypatch):
    path, pipe, _ = recorded_session
    report = rs.replay_session(path)
    assert report.identical, report.as_dict()
    assert report.matched == pipe.seq > 700
    assert report.rejected == dict(pipe.rejected)
    assert rs.run(type("A", (), {"file": str(path), "json": None})()) == 0

    # a different pipeline configuration does not reproduce them: the comparison can fail
    original = rec.read_session

    def altered(p):
        s = original(p)
        s["pipeline_config"]["timeout_s"] = 0.35
        return s
    monkeypatch.setattr(rs, "read_session", altered)
    bad = rs.replay_session(path)
    assert not bad.identical and bad.mismatches


def test_replay_follows_the_recorded_degraded_set(tmp_path):
    """IMU grading flags a vehicle degraded between messages (the service sets the set): the
    recording carries the change, so the replay reproduces the flagged outputs."""
    pipe = MasterPipeline(PipelineConfig(fleet="demo", master_id="ego", known_vehicles=("car2", "car1")))
    recorder = rec.McapRecorder(tmp_path / "d.mcap")
    wrapped = rec.RecordingPipeline(pipe, recorder)
    for k in range(120):
        t = T0 + 0.01 * k
        if k == 40:
            pipe.degraded_vehicles.add("car1")
        if k == 80:
            pipe.degraded_vehicles.discard("car1")
        for vid in ("car1", "car2"):
            wrapped.handle(encode_state(_slave(vid, k, t - 0.005)), state_key("demo", vid), _nav(t), t + 0.002,
                           1.7e9 + 0.01 * k)
        if k % 10 == 0:
            wrapped.tick(t + 0.003, t)
    recorder.close()
    outs = [m.doc for m in rec.read_recording(tmp_path / "d.mcap", topics=(schema.TOPIC_RELATIVE,))]
    assert sum(d["degraded"] for d in outs) == 40
    report = rs.replay_session(tmp_path / "d.mcap")
    assert report.identical and report.matched == pipe.seq


def test_recording_cut_short_is_read_up_to_the_damage(recorded_session, tmp_path):
    """A master killed mid-run leaves a file without summary: everything before the cut is kept."""
    path, pipe, recorder = recorded_session
    last = recorder.files[-1]
    data = last.read_bytes()
    # cut inside the messages (before the summary section, which repeats the schemas): the footer
    # record (opcode, length, summary_start, summary_offset_start, crc) precedes the closing magic
    summary_start = int.from_bytes(data[-8 - 20:-8 - 12], "little")
    last.write_bytes(data[: int(summary_start * 0.6)])
    errors: list[str] = []
    msgs = list(rec.read_recording(path, errors=errors))
    assert errors and last.name in errors[0]
    n_rx = sum(1 for m in msgs if m.topic == schema.TOPIC_RX)
    assert 0 < n_rx <= recorder.recorded[schema.TOPIC_RX]
    assert len(msgs) < sum(recorder.recorded.values())      # the cut lost messages (of any topic)
    report = rs.replay_session(path)
    assert report.damaged and report.identical and report.matched == report.recorded_outputs > 0


def test_recorder_process_failure_does_not_stop_the_master(tmp_path, capsys):
    """The child dying is reported once; the calls keep returning and count what was dropped."""
    from v2xpos.output.recorder_process import RecorderProcess
    recorder = RecorderProcess(tmp_path / "s.mcap")
    recorder.record_tick(T0, T0)
    recorder.flush()
    recorder.proc.kill()
    recorder.proc.wait()
    for k in range(2000):   # enough to fill the buffer and hit the closed pipe
        recorder.record_received(b"x" * 100, "k", 1.7e9 + k, T0 + k, 0)
    recorder.close()
    assert recorder.failure
    assert recorder.dropped > 0
    assert "recorder" in capsys.readouterr().err
