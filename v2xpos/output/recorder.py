"""MCAP session recorder of the master: every received payload, the master's own state, every
silence tick and every output, rotated by size, so that ``v2xpos replay-session`` re-runs the
pipeline and reproduces the outputs byte for byte -- and a recording that opens as a map and a 3D
scene in Foxglove, with every V2V message readable as JSON.

Format: MCAP (https://mcap.dev/spec) written with the ``mcap`` package; the channels, their
schemas and the message documents are ``v2xpos.output.recording_schema``.

Session metadata (MCAP metadata record ``v2xpos.session``): the pipeline configuration and the
admission settings (trust list document) as JSON strings.

Rotation: when the current file has grown beyond ``max_bytes`` it is finished (summary and
index written, so each file is a valid MCAP on its own) and ``<base>_<NNNN>.mcap`` is opened;
the session metadata, the latest master state and the site's lanes are repeated at the head of
every file. Log times are wall-clock nanoseconds of the master (arrival time for received
payloads).
"""
from __future__ import annotations
import base64
import dataclasses
import json
import math
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator

import numpy as np
import orjson
from mcap.records import Channel, Message, Metadata
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

from v2xpos.types import FixStatus
from v2xpos.wire import RelativeResult, WireError, decode_relative, decode_state, encode_relative

from .recording_schema import (FOXGLOVE_TOPICS, PROFILE, SCHEMAS, SESSION_METADATA, TOPIC_DEGRADED, TOPIC_LOCATION_PREFIX,
                               TOPIC_NAV, TOPIC_RAW_RELATIVE, TOPIC_RAW_RX, TOPIC_RELATIVE, TOPIC_RX, TOPIC_SCENE_LANES,
                               TOPIC_SCENE_TARGETS, TOPIC_TF, TOPIC_TICK, nav_to_dict, result_doc, scene_features,
                               state_doc)


class McapRecorder:
    """Thread-safe MCAP writer with size-based rotation.

    ``path``: ``<dir>/<base>.mcap``; rotated files are ``<base>_0001.mcap``, ... beside it.
    ``recorded`` counts messages written per topic; ``files`` lists the files written.
    ``viz_hz``: most Foxglove messages (map fix, transform, scene) per vehicle per second.
    """

    def __init__(self, path: str | Path, max_bytes: int = 256 * 2 ** 20,
                 chunk_size: int = 256 * 1024, compression: str = "zstd", viz_hz: float = 10.0):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.max_bytes = int(max_bytes)
        self.chunk_size = int(chunk_size)
        self.compression = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4,
                            "none": CompressionType.NONE}[compression]
        self.viz_period_ns = int(1e9 / viz_hz) if viz_hz > 0 else None
        self.files: list[Path] = []
        self.recorded: dict[str, int] = {t: 0 for t in [*SCHEMAS, *FOXGLOVE_TOPICS]}
        self.session: dict[str, str] = {}
        self.master_id = "master"
        self._lock = threading.Lock()
        self._fh = None
        self._writer: Writer | None = None
        self._channels: dict[str, int] = {}
        self._schema_ids: dict[str, int] = {}
        self._last_nav: dict | None = None
        self._seq = 0
        self._unchecked_bytes = 0
        self._closed = False
        # Foxglove views
        self._origin: np.ndarray | None = None
        self._features: list[dict] | None = None
        self._lanes_written = False
        self._viz_next: dict[str, int] = {}
        self._pending_state: dict[str, Any] = {}     # target -> last decoded state (until its output)
        self._outline: dict[str, tuple] = {}         # target -> (outline points (N, 3) or None, radius)
        self._targets: dict[str, dict] = {}          # target -> latest pose/status for the scene
        self._open_next()

    @property
    def total_recorded(self) -> int:
        return sum(self.recorded.values())

    # ------------------------------------------------------------------ files and channels
    def _open_next(self) -> None:
        n = len(self.files)
        path = self.path if n == 0 else self.path.with_name(f"{self.path.stem}_{n:04d}{self.path.suffix}")
        self._fh = open(path, "wb")
        self._writer = Writer(self._fh, chunk_size=self.chunk_size, compression=self.compression)
        self._writer.start(profile=PROFILE, library="v2xpos")
        self._channels = {}
        self._schema_ids = {}
        for topic, (name, schema) in SCHEMAS.items():
            sid = self._writer.register_schema(name=name, encoding="jsonschema", data=json.dumps(schema).encode())
            self._channels[topic] = self._writer.register_channel(topic=topic, message_encoding="json",
                                                                  schema_id=sid)
        for topic, name in FOXGLOVE_TOPICS.items():
            self._channels[topic] = self._writer.register_channel(topic=topic, message_encoding="protobuf",
                                                                  schema_id=self._protobuf_schema(name))
        self.files.append(path)
        if self.session:
            self._writer.add_metadata(SESSION_METADATA, dict(self.session))
        if self._last_nav is not None:
            self._add(TOPIC_NAV, self._last_nav, time.time_ns(), count=False)
        self._lanes_written = False
        self._write_lanes(time.time_ns(), count=n == 0)

    def _protobuf_schema(self, name: str) -> int:
        sid = self._schema_ids.get(name)
        if sid is None:
            from v2xpos.output.foxglove import schema_data
            sid = self._schema_ids[name] = self._writer.register_schema(name=name, encoding="protobuf",
                                                                        data=schema_data(name))
        return sid

    def _location_channel(self, vehicle_id: str) -> str:
        topic = TOPIC_LOCATION_PREFIX + vehicle_id
        if topic not in self._channels:
            self._channels[topic] = self._writer.register_channel(
                topic=topic, message_encoding="protobuf", schema_id=self._protobuf_schema("foxglove.LocationFix"))
            self.recorded.setdefault(topic, 0)
        return topic

    def _finish(self) -> None:
        self._writer.finish()
        self._fh.close()

    def _add(self, topic: str, doc: dict, log_time_ns: int, count: bool = True) -> None:
        # orjson: ~5x faster than json.dumps; NaN / inf become null (JSON has neither)
        self._add_raw(topic, orjson.dumps(doc, option=orjson.OPT_SERIALIZE_NUMPY), log_time_ns, count)

    def _add_raw(self, topic: str, data: bytes, log_time_ns: int, count: bool = True) -> None:
        """``count=False``: a copy repeated at the head of a rotated file, written with sequence 0
        (real messages count from 1) so that readers skip it."""
        if count:
            self._seq += 1
        self._writer.add_message(self._channels[topic], log_time=log_time_ns, data=data,
                                 publish_time=log_time_ns, sequence=self._seq if count else 0)
        if count:
            self.recorded[topic] += 1
        self._unchecked_bytes += len(data)
        if self._unchecked_bytes >= self.chunk_size:
            # the file grows only when a chunk is written, so its size is read (a syscall, which
            # also hands the GIL to any waiting thread) once per chunk of data, not per message
            self._unchecked_bytes = 0
            if self._fh.tell() >= self.max_bytes:
                self._finish()
                self._open_next()

    def _viz_due(self, key: str, t_ns: int) -> bool:
        """Rate limit of the Foxglove channels: True at most every ``viz_period_ns`` per key."""
        if self.viz_period_ns is None:
            return False
        if t_ns < self._viz_next.get(key, -1):
            return False
        self._viz_next[key] = t_ns + self.viz_period_ns
        return True

    # ------------------------------------------------------------------ inputs
    def write_session(self, session: dict[str, Any]) -> None:
        """Session metadata (values JSON-encoded) written now and at the head of rotated files."""
        with self._lock:
            self.session = {k: v if isinstance(v, str) else json.dumps(v) for k, v in session.items()}
            try:
                self.master_id = json.loads(self.session.get("pipeline_config", "{}")).get("master_id") or "master"
            except ValueError:
                pass
            self._writer.add_metadata(SESSION_METADATA, dict(self.session))

    def write_scene_features(self, features: list[dict]) -> None:
        """The site's lane lines and objects (``scene_features``), drawn on ``/scene/lanes``."""
        with self._lock:
            self._features = features
            self._lanes_written = False
            self._write_lanes(time.time_ns())

    def _write_lanes(self, t_ns: int, count: bool = True) -> None:
        if self._lanes_written or self._features is None or self._origin is None:
            return
        from v2xpos.output.foxglove import lanes_entity
        self._lanes_written = True
        self._add_raw(TOPIC_SCENE_LANES, lanes_entity(t_ns, self._features, self._origin), t_ns, count)

    def record_nav(self, nav: Any, index: int) -> None:
        self.record_nav_doc(nav_to_dict(nav, index))

    def record_nav_doc(self, doc: dict, log_time_ns: int | None = None) -> None:
        """The master state as ``nav_to_dict`` made it."""
        t_ns = time.time_ns() if log_time_ns is None else log_time_ns
        with self._lock:
            self._last_nav = doc
            self._add(TOPIC_NAV, doc, t_ns)
            if self._origin is None:
                self._origin = np.array(doc["lla"], float)
                self._write_lanes(t_ns)
            if self._viz_due("nav", t_ns):
                from v2xpos.output import foxglove as fg
                mid = self.master_id
                self._add_raw(self._location_channel(mid),
                              fg.location_fix(t_ns, mid, doc["lla"], doc["pos_sd_m"], doc["v_ned_mps"],
                                              doc["rpy_rad"][2], "valid" if doc["fix"] >= int(FixStatus.FLOAT)
                                              else "fix_invalid"), t_ns)
                tf = fg.master_transform(t_ns, mid, self._origin, doc["lla"], doc["rpy_rad"])
                self._add_raw(TOPIC_TF, fg.frame_transforms([tf]), t_ns)

    def record_received(self, payload: bytes, key: str | None, t_arrival_wall_s: float,
                        t_now_gps_s: float, nav_index: int) -> None:
        payload = bytes(payload)
        t_ns = int(t_arrival_wall_s * 1e9)
        # exact replay input: hand-formatted JSON; repr(float) round-trips exactly
        raw = (f'{{"key":{json.dumps(key)},"payload_b64":"{base64.b64encode(payload).decode()}",'
               f'"t_arrival_wall_s":{float(t_arrival_wall_s)!r},"t_now_gps_s":{float(t_now_gps_s)!r},'
               f'"nav_index":{int(nav_index)}}}')
        try:
            msg = decode_state(payload)
            doc, error = state_doc(msg), None
        except WireError as exc:
            msg, doc, error = None, None, str(exc)
        with self._lock:
            self._add_raw(TOPIC_RAW_RX, raw.encode(), t_ns)
            self._add(TOPIC_RX, {"key": key, "t_arrival_wall_s": float(t_arrival_wall_s),
                                 "t_now_gps_s": float(t_now_gps_s), "size_bytes": len(payload), "error": error,
                                 "message": doc}, t_ns)
            if msg is not None:
                self._pending_state[msg.vehicle_id] = msg

    def record_tick(self, t_now_gps_s: float, master_t_gps_s: float | None, log_time_ns: int | None = None,
                    master_fix: int | None = None) -> None:
        doc = {"t_now_gps_s": float(t_now_gps_s),
               "master_t_gps_s": None if master_t_gps_s is None else float(master_t_gps_s),
               "master_fix": None if master_fix is None else int(master_fix)}
        with self._lock:
            self._add(TOPIC_TICK, doc, time.time_ns() if log_time_ns is None else log_time_ns)

    def record_degraded(self, vehicle_ids: list[str], log_time_ns: int | None = None) -> None:
        """The set of vehicles flagged degraded changed (replayed before the next input)."""
        with self._lock:
            self._add(TOPIC_DEGRADED, {"vehicle_ids": sorted(vehicle_ids)},
                      time.time_ns() if log_time_ns is None else log_time_ns)

    def record_result(self, res: RelativeResult) -> None:
        self.record_result_bytes(encode_relative(res))

    def record_result_bytes(self, raw: bytes, log_time_ns: int | None = None) -> None:
        """One output: its wire bytes (replay reference), decoded (``/v2xpos/out/relative``) and drawn
        (``/tf``, ``/scene/targets``, the target's ``/location``)."""
        t_ns = time.time_ns() if log_time_ns is None else log_time_ns
        raw = bytes(raw)
        try:
            res = decode_relative(raw)
            doc = result_doc(res)
        except WireError as exc:
            res, doc = None, {"target_id": "", "status": "unknown", "seq": -1, "t_gps_s": 0.0, "error": str(exc)}
        with self._lock:
            self._add_raw(TOPIC_RAW_RELATIVE, f'{{"payload_b64":"{base64.b64encode(raw).decode()}"}}'.encode(), t_ns)
            self._add(TOPIC_RELATIVE, doc, t_ns)
            if res is not None and self.viz_period_ns is not None:
                self._draw_result(res, doc, t_ns)

    def _draw_result(self, res: RelativeResult, doc: dict, t_ns: int) -> None:
        from v2xpos.output import foxglove as fg
        tid = res.target_id
        msg = self._pending_state.get(tid)
        if msg is not None and msg.seq == res.source_seq:
            # the state this output was computed from was admitted: it goes on the map
            self._outline[tid] = (np.asarray(msg.geometry.points_body_m, float) if len(msg.geometry.points_body_m)
                                  else None, float(msg.geometry.radius_m))
            if self._viz_due(f"loc/{tid}", t_ns):
                self._add_raw(self._location_channel(tid),
                              fg.location_fix(t_ns, tid, msg.lla, msg.pos_sd_m, msg.v_ned_mps, msg.rpy_rad[2],
                                              doc["status"]), t_ns)
        if res.has_kinematics:
            self._targets[tid] = {"p": res.rel_pos_body_m.copy(), "att": res.rel_rpy_rad.copy()}
        if tid in self._targets:
            self._targets[tid]["status"] = doc["status"]
            self._targets[tid]["label"] = (f"{tid} {doc['status'].upper()}"
                                           + (f" {doc['range_m']:.1f} m" if math.isfinite(doc["range_m"]) else ""))
        if res.has_kinematics and self._viz_due(f"tf/{tid}", t_ns):
            tf = fg.target_transform(t_ns, self.master_id, tid, res.rel_pos_body_m, res.rel_rpy_rad)
            self._add_raw(TOPIC_TF, fg.frame_transforms([tf]), t_ns)
        if self._targets and self._viz_due("scene", t_ns):
            ents = []
            for t, d in self._targets.items():
                outline, radius = self._outline.get(t, (None, 0.0))
                ents.append(fg.target_entity(t_ns, self.master_id, t, d["status"], d["p"], d["att"], outline,
                                             radius, d["label"]))
            self._add_raw(TOPIC_SCENE_TARGETS, fg.scene_update(ents), t_ns)

    def close(self) -> None:
        with self._lock:
            if not self._closed:
                self._closed = True
                self._finish()

    def __enter__(self) -> "McapRecorder":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class RecorderSink:
    """Pipeline output sink that records every RelativeResult (``write(result)``)."""

    def __init__(self, recorder: McapRecorder):
        self.recorder = recorder

    def write(self, result: RelativeResult) -> None:
        self.recorder.record_result(result)

    def close(self) -> None:
        pass


def pipeline_session(pipeline: Any) -> dict[str, Any]:
    """What replay needs besides the messages: the PipelineConfig and the admission settings."""
    cfg = dataclasses.asdict(pipeline.config) if dataclasses.is_dataclass(pipeline.config) else {}
    auth = getattr(pipeline, "authenticator", None)
    session: dict[str, Any] = {"pipeline_config": cfg, "authenticator": None}
    if auth is not None and hasattr(auth, "trust"):
        session["authenticator"] = {
            "trust_list": auth.trust.to_json(), "require_signature": auth.require_signature,
            "max_age_s": auth.max_age_s, "future_tolerance_s": auth.future_tolerance_s,
            "replay_window": auth.replay_window}
    return session


class RecordingPipeline:
    """Wraps a ``master.pipeline.MasterPipeline``: records each input before it is processed and
    each output as it is written; everything else is delegated to the wrapped pipeline.

    Whatever changes outputs besides the inputs is recorded too, before the input it affects:
    the set of degraded vehicles (IMU grading, set by the service between messages)."""

    def __init__(self, pipeline: Any, recorder: McapRecorder):
        self._pipeline = pipeline
        self.recorder = recorder
        self._nav_obj: Any = None
        self._nav_index = -1
        self._degraded: frozenset = frozenset()
        self._scene_sent = False
        pipeline.sinks.append(RecorderSink(recorder))
        recorder.write_session(pipeline_session(pipeline))

    def __getattr__(self, name: str) -> Any:
        return getattr(self._pipeline, name)

    def _nav(self, master: Any) -> None:
        if master is not self._nav_obj:
            self._nav_obj = master
            self._nav_index += 1
            self.recorder.record_nav(master, self._nav_index)

    def _check_degraded(self) -> None:
        current = self._pipeline.degraded_vehicles
        if current != self._degraded:
            self._degraded = frozenset(current)
            self.recorder.record_degraded(sorted(self._degraded))

    def handle(self, payload: bytes, key: str | None, master: Any, t_now_gps_s: float,
               t_arrival_wall_s: float | None = None, signature_valid: bool | None = None):
        if t_arrival_wall_s is None:
            t_arrival_wall_s = self._pipeline.clock_wall()
        self._check_degraded()
        self._nav(master)
        self.recorder.record_received(payload, key, t_arrival_wall_s, t_now_gps_s, self._nav_index)
        return self._pipeline.handle(payload, key, master, t_now_gps_s, t_arrival_wall_s, signature_valid)

    def tick(self, t_now_gps_s: float, master_t_gps_s: float | None = None, master_fix: Any = None):
        self._check_degraded()
        self.recorder.record_tick(t_now_gps_s, master_t_gps_s, master_fix=master_fix)
        if master_fix is None:
            return self._pipeline.tick(t_now_gps_s, master_t_gps_s)
        return self._pipeline.tick(t_now_gps_s, master_t_gps_s, master_fix)

    def process_scene(self, scene: Any, master: Any):
        if not self._scene_sent:
            self._scene_sent = True
            self.recorder.write_scene_features(scene_features(scene))
        return self._pipeline.process_scene(scene, master)


# ----------------------------------------------------------------------------- reading

@dataclass
class RecordedMessage:
    """One message read back: topic, log time [ns], the JSON document (None for a channel that is
    not JSON, e.g. Foxglove's protobuf ones: ``data`` holds its bytes)."""
    topic: str
    log_time_ns: int
    doc: dict | None
    data: bytes = b""
    encoding: str = "json"


def recording_files(path: str | Path) -> list[Path]:
    """The files of one recording: ``path`` and its rotated siblings ``<stem>_NNNN.mcap``, in
    order; a directory gives every ``*.mcap`` in it sorted by name."""
    path = Path(path)
    if path.is_dir():
        return sorted(path.glob("*.mcap"))
    rotated = sorted(path.parent.glob(f"{path.stem}_[0-9][0-9][0-9][0-9]{path.suffix}"))
    return [path, *rotated]


def _stream_records(f: Path) -> tuple[list[tuple[int, str, int, bytes, str]], dict[str, str], str | None]:
    """Messages (sequence, topic, log time, data, message encoding) and session metadata of one
    file read as a stream -- works on a file cut short (a crash before the summary was written):
    reading stops at the damaged tail, whose error is returned."""
    channels: dict[int, tuple[str, str]] = {}
    rows: list[tuple[int, str, int, bytes, str]] = []
    session: dict[str, str] = {}
    error = None
    with open(f, "rb") as fh:
        try:
            for record in StreamReader(fh).records:
                if isinstance(record, Channel):
                    channels[record.id] = (record.topic, record.message_encoding)
                elif isinstance(record, Message):
                    topic, enc = channels.get(record.channel_id, ("?", ""))
                    rows.append((record.sequence, topic, record.log_time, record.data, enc))
                elif isinstance(record, Metadata) and record.name == SESSION_METADATA:
                    session = dict(record.metadata)
        except Exception as exc:  # truncated or corrupt tail: keep everything before it
            error = f"{f}: stopped at a damaged record ({type(exc).__name__}: {exc})"
    return rows, session, error


def read_session(path: str | Path) -> dict[str, Any]:
    """Session metadata of the first file, values JSON-decoded."""
    _, session, _ = _stream_records(recording_files(path)[0])
    return {k: json.loads(v) for k, v in session.items()}


def read_recording(path: str | Path, topics: tuple[str, ...] | None = None,
                   errors: list[str] | None = None) -> Iterator[RecordedMessage]:
    """Messages of all files in write order (by the recorder's sequence number within a file).

    Files are read as streams, so a recording whose last file was cut short (the master was
    killed) yields everything before the damage; the damage is described in ``errors`` when a
    list is given. The master state and lanes repeated at the head of a rotated file (sequence 0)
    are skipped: they duplicate what the previous file holds.
    """
    for i, f in enumerate(recording_files(path)):
        rows, _, error = _stream_records(f)
        if error is not None and errors is not None:
            errors.append(error)
        rows.sort(key=lambda r: r[0])
        for seq, topic, log_time, data, enc in rows:
            if i > 0 and seq == 0:
                continue
            if topics and topic not in topics:
                continue
            yield RecordedMessage(topic, log_time, json.loads(data) if enc == "json" else None, data, enc)
