"""MCAP session recorder of the master: every received payload, the master's own state, every
silence tick and every output, rotated by size, so ``v2xpos replay-session`` can re-run the
pipeline and reproduce the outputs byte for byte.

Format: MCAP (https://mcap.dev/spec) written with the ``mcap`` package; messages are JSON
(``message_encoding = "json"``, schema encoding ``jsonschema``) so Foxglove shows them directly.
Raw wire bytes are carried base64-encoded in ``raw_b64`` for exact replay. Channels:

* ``/v2xpos/rx`` -- every payload received on the state key expression, before validation:
  ``key``, ``raw_b64``, ``t_arrival_wall_s``, ``t_now_gps_s`` (master GPS time used for it),
  ``nav_index`` (the master state it was processed against);
* ``/v2xpos/master_nav`` -- the master's filter state whenever the pipeline is given a new one
  (``index``, NavState fields: t_s, lla [rad, rad, m], v_ned_mps, acc_body_mps2, rate_body_rps,
  rpy_rad, *_sd, fix);
* ``/v2xpos/tick`` -- silence checks (``t_now_gps_s``, ``master_t_gps_s``);
* ``/v2xpos/out/relative`` -- every RelativeResult the pipeline produced (``raw_b64`` =
  ``encode_relative`` bytes, plus readable fields).
Session metadata (MCAP metadata record ``v2xpos.session``): the pipeline configuration and the
admission settings (trust list document) as JSON strings.

Rotation: when the current file has grown beyond ``max_bytes`` it is finished (summary and
index written, so each file is a valid MCAP on its own) and ``<base>_<NNNN>.mcap`` is opened;
the session metadata and the latest master state are repeated at the head of every file.
Log times are wall-clock nanoseconds (arrival time for received payloads).
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
from mcap.records import Channel, Message, Metadata
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

from v2xpos.types import FixStatus, NavState
from v2xpos.wire import RelativeResult, encode_relative

TOPIC_RX = "/v2xpos/rx"
TOPIC_NAV = "/v2xpos/master_nav"
TOPIC_TICK = "/v2xpos/tick"
TOPIC_RELATIVE = "/v2xpos/out/relative"
SESSION_METADATA = "v2xpos.session"
PROFILE = "v2xpos"

_NUM = {"type": "number"}
_VEC3 = {"type": "array", "items": _NUM, "minItems": 3, "maxItems": 3}
_NAV_VECTORS = ("lla", "v_ned_mps", "acc_body_mps2", "rate_body_rps", "rpy_rad", "pos_sd_m",
                "vel_sd_mps", "att_sd_rad")
SCHEMAS: dict[str, tuple[str, dict]] = {
    TOPIC_RX: ("v2xpos.Received", {
        "type": "object", "properties": {
            "key": {"type": ["string", "null"]}, "raw_b64": {"type": "string"},
            "t_arrival_wall_s": _NUM, "t_now_gps_s": _NUM, "nav_index": {"type": "integer"}}}),
    TOPIC_NAV: ("v2xpos.MasterNav", {
        "type": "object", "properties": {"index": {"type": "integer"}, "t_s": _NUM,
                                         "fix": {"type": "integer"},
                                         **{k: _VEC3 for k in _NAV_VECTORS}}}),
    TOPIC_TICK: ("v2xpos.Tick", {
        "type": "object", "properties": {"t_now_gps_s": _NUM, "master_t_gps_s": {"type": ["number", "null"]}}}),
    TOPIC_RELATIVE: ("v2xpos.RelativeResult", {
        "type": "object", "properties": {
            "raw_b64": {"type": "string"}, "target_id": {"type": "string"},
            "status": {"type": "string"}, "seq": {"type": "integer"}, "source_seq": {"type": "integer"},
            "t_gps_s": _NUM, "latency_s": {"type": ["number", "null"]},
            "rel_pos_body_m": {"type": ["array", "null"], "items": _NUM},
            "range_m": {"type": ["number", "null"]}, "ttc_s": {"type": ["number", "null"]}}}),
}


def _num(x: float | None) -> str:
    """JSON text of a number; ``null`` for None / NaN / inf (repr round-trips a float exactly)."""
    return "null" if x is None or not math.isfinite(x) else repr(float(x))


def nav_to_dict(nav: Any, index: int) -> dict:
    """Master state (NavState-like) -> JSON-ready dict; floats round-trip exactly (repr)."""
    d = {"index": index, "t_s": float(nav.t_s), "fix": int(nav.fix)}
    for k in _NAV_VECTORS:
        d[k] = [float(x) for x in np.asarray(getattr(nav, k), dtype=float).reshape(3)]
    return d


def nav_from_dict(d: dict) -> NavState:
    """Inverse of :func:`nav_to_dict`."""
    kw = {k: np.array(d[k], dtype=float) for k in _NAV_VECTORS}
    return NavState(t_s=float(d["t_s"]), fix=FixStatus(int(d["fix"])), **kw)


def result_fields(res: RelativeResult) -> tuple:
    """Readable fields of an output for ``/v2xpos/out/relative`` (positions, range and TTC only
    when the result has kinematics): target_id, status name, seq, source_seq, t_gps_s, latency_s,
    rel_pos_body_m (3 floats or None), range_m, ttc_s."""
    valid = res.has_kinematics
    p = res.rel_pos_body_m
    return (res.target_id, res.status.name.lower(), int(res.seq), int(res.source_seq), float(res.t_gps_s),
            float(res.latency_s), (float(p[0]), float(p[1]), float(p[2])) if valid else None,
            float(res.range_m) if valid else None,
            float(res.ttc_s) if valid and res.ttc_s is not None else None)


class McapRecorder:
    """Thread-safe MCAP writer with size-based rotation.

    ``path``: ``<dir>/<base>.mcap``; rotated files are ``<base>_0001.mcap``, ... beside it.
    ``recorded`` counts messages written per topic; ``files`` lists the files written.
    """

    def __init__(self, path: str | Path, max_bytes: int = 256 * 2 ** 20,
                 chunk_size: int = 256 * 1024, compression: str = "zstd"):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.max_bytes = int(max_bytes)
        self.chunk_size = int(chunk_size)
        self.compression = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4,
                            "none": CompressionType.NONE}[compression]
        self.files: list[Path] = []
        self.recorded: dict[str, int] = {t: 0 for t in SCHEMAS}
        self.session: dict[str, str] = {}
        self._lock = threading.Lock()
        self._fh = None
        self._writer: Writer | None = None
        self._channels: dict[str, int] = {}
        self._last_nav: dict | None = None
        self._seq = 0
        self._unchecked_bytes = 0
        self._closed = False
        self._open_next()

    @property
    def total_recorded(self) -> int:
        return sum(self.recorded.values())

    def _open_next(self) -> None:
        n = len(self.files)
        path = self.path if n == 0 else self.path.with_name(f"{self.path.stem}_{n:04d}{self.path.suffix}")
        self._fh = open(path, "wb")
        self._writer = Writer(self._fh, chunk_size=self.chunk_size, compression=self.compression)
        self._writer.start(profile=PROFILE, library="v2xpos")
        self._channels = {}
        for topic, (name, schema) in SCHEMAS.items():
            sid = self._writer.register_schema(name=name, encoding="jsonschema",
                                               data=json.dumps(schema).encode())
            self._channels[topic] = self._writer.register_channel(topic=topic, message_encoding="json",
                                                                  schema_id=sid)
        self.files.append(path)
        if self.session:
            self._writer.add_metadata(SESSION_METADATA, dict(self.session))
        if self._last_nav is not None:
            self._add(TOPIC_NAV, self._last_nav, time.time_ns(), count=False)

    def _finish(self) -> None:
        self._writer.finish()
        self._fh.close()

    def _add(self, topic: str, doc: dict, log_time_ns: int, count: bool = True) -> None:
        self._add_raw(topic, json.dumps(doc, separators=(",", ":")).encode(), log_time_ns, count)

    def _add_raw(self, topic: str, data: bytes, log_time_ns: int, count: bool = True) -> None:
        self._seq += 1
        self._writer.add_message(self._channels[topic], log_time=log_time_ns, data=data,
                                 publish_time=log_time_ns, sequence=self._seq)
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

    def write_session(self, session: dict[str, Any]) -> None:
        """Session metadata (values JSON-encoded) written now and at the head of rotated files."""
        with self._lock:
            self.session = {k: v if isinstance(v, str) else json.dumps(v) for k, v in session.items()}
            self._writer.add_metadata(SESSION_METADATA, dict(self.session))

    def record_nav(self, nav: Any, index: int) -> None:
        self.record_nav_doc(nav_to_dict(nav, index))

    def record_nav_doc(self, doc: dict, log_time_ns: int | None = None) -> None:
        """The master state as ``nav_to_dict`` made it."""
        with self._lock:
            self._last_nav = doc
            self._add(TOPIC_NAV, doc, time.time_ns() if log_time_ns is None else log_time_ns)

    def record_received(self, payload: bytes, key: str | None, t_arrival_wall_s: float,
                        t_now_gps_s: float, nav_index: int) -> None:
        # hand-formatted JSON (hot path, ~1 per received message); repr(float) round-trips exactly
        text = (f'{{"key":{json.dumps(key)},"raw_b64":"{base64.b64encode(bytes(payload)).decode()}",'
                f'"t_arrival_wall_s":{float(t_arrival_wall_s)!r},"t_now_gps_s":{float(t_now_gps_s)!r},'
                f'"nav_index":{int(nav_index)}}}')
        with self._lock:
            self._add_raw(TOPIC_RX, text.encode(), int(t_arrival_wall_s * 1e9))

    def record_tick(self, t_now_gps_s: float, master_t_gps_s: float | None, log_time_ns: int | None = None) -> None:
        doc = {"t_now_gps_s": float(t_now_gps_s),
               "master_t_gps_s": None if master_t_gps_s is None else float(master_t_gps_s)}
        with self._lock:
            self._add(TOPIC_TICK, doc, time.time_ns() if log_time_ns is None else log_time_ns)

    def record_result(self, res: RelativeResult) -> None:
        self.record_result_fields(encode_relative(res), *result_fields(res))

    def record_result_fields(self, raw: bytes, target_id: str, status: str, seq: int, source_seq: int,
                             t_gps_s: float, latency_s: float, rel_pos_body_m: Any, range_m: float | None,
                             ttc_s: float | None, log_time_ns: int | None = None) -> None:
        """One output: its wire bytes and the readable fields of ``result_fields``."""
        # hand-formatted JSON (hot path, one per output); non-finite numbers become null
        pos = "null" if rel_pos_body_m is None else f"[{_num(rel_pos_body_m[0])},{_num(rel_pos_body_m[1])},{_num(rel_pos_body_m[2])}]"
        text = (f'{{"raw_b64":"{base64.b64encode(raw).decode()}",'
                f'"target_id":{json.dumps(target_id)},"status":"{status}",'
                f'"seq":{int(seq)},"source_seq":{int(source_seq)},"t_gps_s":{_num(t_gps_s)},'
                f'"latency_s":{_num(latency_s)},"rel_pos_body_m":{pos},'
                f'"range_m":{_num(range_m)},"ttc_s":{_num(ttc_s)}}}')
        with self._lock:
            self._add_raw(TOPIC_RELATIVE, text.encode(), time.time_ns() if log_time_ns is None else log_time_ns)

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
    each output as it is written; everything else is delegated to the wrapped pipeline."""

    def __init__(self, pipeline: Any, recorder: McapRecorder):
        self._pipeline = pipeline
        self.recorder = recorder
        self._nav_obj: Any = None
        self._nav_index = -1
        pipeline.sinks.append(RecorderSink(recorder))
        recorder.write_session(pipeline_session(pipeline))

    def __getattr__(self, name: str) -> Any:
        return getattr(self._pipeline, name)

    def _nav(self, master: Any) -> None:
        if master is not self._nav_obj:
            self._nav_obj = master
            self._nav_index += 1
            self.recorder.record_nav(master, self._nav_index)

    def handle(self, payload: bytes, key: str | None, master: Any, t_now_gps_s: float,
               t_arrival_wall_s: float | None = None, signature_valid: bool | None = None):
        if t_arrival_wall_s is None:
            t_arrival_wall_s = self._pipeline.clock_wall()
        self._nav(master)
        self.recorder.record_received(payload, key, t_arrival_wall_s, t_now_gps_s, self._nav_index)
        return self._pipeline.handle(payload, key, master, t_now_gps_s, t_arrival_wall_s, signature_valid)

    def tick(self, t_now_gps_s: float, master_t_gps_s: float | None = None):
        self.recorder.record_tick(t_now_gps_s, master_t_gps_s)
        return self._pipeline.tick(t_now_gps_s, master_t_gps_s)


# ----------------------------------------------------------------------------- reading

@dataclass
class RecordedMessage:
    """One message read back: topic, log time [ns], the JSON document."""
    topic: str
    log_time_ns: int
    doc: dict


def recording_files(path: str | Path) -> list[Path]:
    """The files of one recording: ``path`` and its rotated siblings ``<stem>_NNNN.mcap``, in
    order; a directory gives every ``*.mcap`` in it sorted by name."""
    path = Path(path)
    if path.is_dir():
        return sorted(path.glob("*.mcap"))
    rotated = sorted(path.parent.glob(f"{path.stem}_[0-9][0-9][0-9][0-9]{path.suffix}"))
    return [path, *rotated]


def _stream_records(f: Path) -> tuple[list[tuple[int, str, int, bytes]], dict[str, str], str | None]:
    """Messages (sequence, topic, log time, data) and session metadata of one file read as a
    stream -- works on a file cut short (a crash before the summary was written): reading stops
    at the damaged tail, whose error is returned."""
    channels: dict[int, str] = {}
    rows: list[tuple[int, str, int, bytes]] = []
    session: dict[str, str] = {}
    error = None
    with open(f, "rb") as fh:
        try:
            for record in StreamReader(fh).records:
                if isinstance(record, Channel):
                    channels[record.id] = record.topic
                elif isinstance(record, Message):
                    rows.append((record.sequence, channels.get(record.channel_id, "?"), record.log_time,
                                 record.data))
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
    list is given. The master state repeated at the head of a rotated file is skipped (it
    duplicates the last state of the previous file).
    """
    for i, f in enumerate(recording_files(path)):
        rows, _, error = _stream_records(f)
        if error is not None and errors is not None:
            errors.append(error)
        rows.sort(key=lambda r: r[0])
        for j, (_, topic, log_time, data) in enumerate(rows):
            if i > 0 and j == 0 and topic == TOPIC_NAV:
                continue
            if topics and topic not in topics:
                continue
            yield RecordedMessage(topic, log_time, json.loads(data))
