"""MCAP session recorder of the master: every received payload, the master's own state, every
silence tick and every output, rotated by size, so that ``v2xpos replay-session`` re-runs the
pipeline and reproduces the outputs byte for byte -- and a recording that opens as a map and a 3D
scene in Foxglove, with every V2V message readable as JSON.

Format: MCAP (https://mcap.dev/spec) written with the ``mcap`` package. Channels:

Decoded, for people and viewers (JSON, schema encoding ``jsonschema``; schemas in ``SCHEMAS``):

* ``/v2xpos/rx`` -- every payload received on the state key expression, decoded
  (``v2xpos.wire.decode_state``) into a readable StateMessage (lat/lon in degrees, attitude in
  degrees, fix name, outline ...), or the decode error when it is malformed;
* ``/v2xpos/out/relative`` -- every RelativeResult the pipeline produced, every field (status and
  fixes by name, relative position / velocity / acceleration / attitude and their sigmas, range,
  bearing, gap, TTC);
* ``/v2xpos/master_nav`` -- the master's filter state whenever the pipeline is given a new one
  (``index``, NavState fields: t_s, lla [rad, rad, m], v_ned_mps, acc_body_mps2, rate_body_rps,
  rpy_rad, *_sd, fix); ``/v2xpos/tick`` -- silence checks; ``/v2xpos/degraded`` -- the vehicles
  whose results are flagged degraded (IMU grading), whenever that set changes.

Foxglove's well-known schemas (protobuf, ``v2xpos.output.foxglove``), at most ``viz_hz`` per
vehicle: ``/location/<vehicle_id>`` (``foxglove.LocationFix``: the master from its filter, each
target from its admitted state messages), ``/tf`` (``foxglove.FrameTransforms``: world -> master
body -> each target), ``/scene/targets`` (``foxglove.SceneUpdate``: outlines coloured by status,
labels) and ``/scene/lanes`` (lane lines and static objects of the site).

For replay only (JSON; ``payload_b64`` is the exact wire bytes, base64): ``/v2xpos/raw/rx``
(``key``, ``payload_b64``, ``t_arrival_wall_s``, ``t_now_gps_s``, ``nav_index``: the master state it
was processed against) and ``/v2xpos/raw/out/relative`` (the ``encode_relative`` bytes of each
output, compared by ``replay-session``).

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

from v2xpos.types import FixStatus, NavState
from v2xpos.wire import RelativeResult, WireError, decode_relative, decode_state, encode_relative

TOPIC_RX = "/v2xpos/rx"
TOPIC_RAW_RX = "/v2xpos/raw/rx"
TOPIC_NAV = "/v2xpos/master_nav"
TOPIC_TICK = "/v2xpos/tick"
TOPIC_DEGRADED = "/v2xpos/degraded"
TOPIC_RELATIVE = "/v2xpos/out/relative"
TOPIC_RAW_RELATIVE = "/v2xpos/raw/out/relative"
TOPIC_TF = "/tf"
TOPIC_SCENE_TARGETS = "/scene/targets"
TOPIC_SCENE_LANES = "/scene/lanes"
TOPIC_LOCATION_PREFIX = "/location/"
SESSION_METADATA = "v2xpos.session"
PROFILE = ""
"""No MCAP profile: the channels are neither ROS 1 nor ROS 2 messages (mcap.dev spec, profiles)."""

_NUM = {"type": "number"}
_NUM_OR_NULL = {"type": ["number", "null"]}
_INT = {"type": "integer"}
_STR = {"type": "string"}


def _vec3(desc: str, nullable: bool = False) -> dict:
    v = {"type": "array", "items": _NUM_OR_NULL if nullable else _NUM, "minItems": 3, "maxItems": 3,
         "description": desc}
    if nullable:
        v = {"type": ["array", "null"], "items": _NUM_OR_NULL, "minItems": 3, "maxItems": 3, "description": desc}
    return v


_NAV_VECTORS = ("lla", "v_ned_mps", "acc_body_mps2", "rate_body_rps", "rpy_rad", "pos_sd_m",
                "vel_sd_mps", "att_sd_rad")
_FIX_NAMES = [f.name for f in FixStatus]
_GEOMETRY = {"type": "object", "description": "target outline in its body frame (x fwd, y right, z down)",
             "properties": {"kind": {"enum": ["points", "polygon", "circle"]},
                            "points_body_m": {"type": "array", "items": _vec3("point [m]")},
                            "radius_m": _NUM},
             "required": ["kind", "points_body_m", "radius_m"]}
_STATE_MESSAGE = {
    "type": "object", "description": "v2xpos.wire.StateMessage, decoded (docs/protocol.md)",
    "properties": {
        "fleet": _STR, "vehicle_id": _STR, "kind": {"enum": ["vehicle", "pedestrian"]}, "seq": _INT,
        "t_gps_s": {"type": "number", "description": "time of validity, GPS seconds"},
        "fix": {"enum": _FIX_NAMES}, "lat_deg": _NUM, "lon_deg": _NUM,
        "height_m": {"type": "number", "description": "ellipsoidal height"},
        "v_ned_mps": _vec3("velocity north/east/down [m/s]"),
        "acc_body_mps2": _vec3("kinematic acceleration, body frame [m/s^2]"),
        "rate_body_rps": _vec3("angular rate, body frame [rad/s]"),
        "roll_pitch_yaw_deg": _vec3("Z-Y-X Euler angles of C_nb [deg]"),
        "pos_sd_ned_m": _vec3("1-sigma north/east/down [m]"), "vel_sd_ned_mps": _vec3("1-sigma [m/s]"),
        "att_sd_deg": _vec3("1-sigma roll/pitch/yaw [deg]"), "geometry": _GEOMETRY,
        "t_sent_wall_s": _NUM_OR_NULL, "signed": {"type": "boolean"}, "key_id": {"type": ["string", "null"]},
        "imu_quality": {"type": ["object", "null"]}},
    "required": ["fleet", "vehicle_id", "kind", "seq", "t_gps_s", "fix", "lat_deg", "lon_deg", "height_m",
                 "v_ned_mps", "roll_pitch_yaw_deg", "pos_sd_ned_m", "geometry"]}
_STATUS_NAMES = ["valid", "fix_invalid", "timeout", "no_data", "future", "attitude_uncertain", "sigma_exceeded",
                 "clock_unsynced", "inconsistent"]

SCHEMAS: dict[str, tuple[str, dict]] = {
    TOPIC_RX: ("v2xpos.ReceivedState", {
        "type": "object", "description": "a payload received on the state key, decoded",
        "properties": {"key": {"type": ["string", "null"]}, "t_arrival_wall_s": _NUM, "t_now_gps_s": _NUM,
                       "size_bytes": _INT, "error": {"type": ["string", "null"],
                                                     "description": "why it could not be decoded"},
                       "message": {"oneOf": [_STATE_MESSAGE, {"type": "null"}]}},
        "required": ["key", "t_arrival_wall_s", "t_now_gps_s", "size_bytes", "error", "message"]}),
    TOPIC_RELATIVE: ("v2xpos.RelativeResult", {
        "type": "object", "description": "v2xpos.wire.RelativeResult: a target in the master body frame "
                                         "(x fwd, y right, z down); kinematic fields null when not computed",
        "properties": {
            "target_id": _STR, "target_kind": _STR, "status": {"enum": _STATUS_NAMES + ["unknown"]},
            "status_code": _INT, "fix_side": {"type": "array", "items": {"enum": ["master", "slave"]}},
            "degraded": {"type": "boolean"}, "fleet": _STR, "master_id": _STR, "seq": _INT, "source_seq": _INT,
            "t_gps_s": _NUM, "latency_s": _NUM_OR_NULL, "master_fix": {"enum": _FIX_NAMES},
            "target_fix": {"enum": _FIX_NAMES},
            "rel_pos_body_m": _vec3("relative position [m]", True), "rel_pos_sd_m": _vec3("1-sigma [m]", True),
            "rel_vel_body_mps": _vec3("relative velocity [m/s]", True),
            "rel_acc_body_mps2": _vec3("relative acceleration [m/s^2]", True),
            "rel_roll_pitch_yaw_deg": _vec3("target attitude relative to the master [deg]", True),
            "rel_yaw_sd_deg": _NUM_OR_NULL, "range_m": _NUM_OR_NULL, "range_sd_m": _NUM_OR_NULL,
            "bearing_deg": _NUM_OR_NULL, "elevation_deg": _NUM_OR_NULL, "longitudinal_m": _NUM_OR_NULL,
            "lateral_m": _NUM_OR_NULL, "gap_m": _NUM_OR_NULL, "closing_speed_mps": _NUM_OR_NULL,
            "ttc_s": _NUM_OR_NULL, "t_sent_wall_s": _NUM_OR_NULL, "error": {"type": ["string", "null"]}},
        "required": ["target_id", "status", "seq", "t_gps_s"]}),
    TOPIC_NAV: ("v2xpos.MasterNav", {
        "type": "object", "properties": {"index": _INT, "t_s": _NUM, "fix": _INT,
                                         **{k: _vec3(k) for k in _NAV_VECTORS}},
        "required": ["index", "t_s", "fix", *_NAV_VECTORS]}),
    TOPIC_TICK: ("v2xpos.Tick", {
        "type": "object", "properties": {"t_now_gps_s": _NUM, "master_t_gps_s": _NUM_OR_NULL,
                                         "master_fix": {"type": ["integer", "null"]}},
        "required": ["t_now_gps_s", "master_t_gps_s"]}),
    TOPIC_DEGRADED: ("v2xpos.DegradedVehicles", {
        "type": "object", "properties": {"vehicle_ids": {"type": "array", "items": _STR}},
        "required": ["vehicle_ids"]}),
    TOPIC_RAW_RX: ("v2xpos.RawReceived", {
        "type": "object", "description": "replay input: the exact received bytes",
        "properties": {"key": {"type": ["string", "null"]}, "payload_b64": {"type": "string", "contentEncoding": "base64"},
                       "t_arrival_wall_s": _NUM, "t_now_gps_s": _NUM, "nav_index": _INT},
        "required": ["key", "payload_b64", "t_arrival_wall_s", "t_now_gps_s", "nav_index"]}),
    TOPIC_RAW_RELATIVE: ("v2xpos.RawRelative", {
        "type": "object", "description": "replay reference: the exact output bytes (encode_relative)",
        "properties": {"payload_b64": {"type": "string", "contentEncoding": "base64"}},
        "required": ["payload_b64"]}),
}
"""JSON channels: topic -> (schema name, JSON schema)."""

FOXGLOVE_TOPICS: dict[str, str] = {TOPIC_TF: "foxglove.FrameTransforms", TOPIC_SCENE_TARGETS: "foxglove.SceneUpdate",
                                   TOPIC_SCENE_LANES: "foxglove.SceneUpdate"}
"""Fixed protobuf channels (``/location/<id>`` channels are added per vehicle)."""


def _fin(x: Any) -> float | None:
    """float, or None for None / NaN / inf (JSON has no NaN)."""
    if x is None:
        return None
    x = float(x)
    return x if math.isfinite(x) else None


def _fin3(a: Any, scale: float = 1.0) -> list | None:
    vals = [_fin(v) for v in np.asarray(a, dtype=float).reshape(3)]
    if all(v is None for v in vals):
        return None
    return [None if v is None else v * scale for v in vals]


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


def state_doc(msg: Any) -> dict:
    """A decoded StateMessage as the ``/v2xpos/rx`` ``message`` document."""
    deg = 180.0 / math.pi
    g = msg.geometry
    return {"fleet": msg.fleet, "vehicle_id": msg.vehicle_id, "kind": msg.kind, "seq": int(msg.seq),
            "t_gps_s": float(msg.t_gps_s), "fix": FixStatus(msg.fix).name, "lat_deg": msg.lat_rad * deg,
            "lon_deg": msg.lon_rad * deg, "height_m": float(msg.height_m), "v_ned_mps": msg.v_ned_mps.tolist(),
            "acc_body_mps2": msg.acc_body_mps2.tolist(), "rate_body_rps": msg.rate_body_rps.tolist(),
            "roll_pitch_yaw_deg": (msg.rpy_rad * deg).tolist(), "pos_sd_ned_m": msg.pos_sd_m.tolist(),
            "vel_sd_ned_mps": msg.vel_sd_mps.tolist(), "att_sd_deg": (msg.att_sd_rad * deg).tolist(),
            "geometry": {"kind": g.kind, "points_body_m": np.asarray(g.points_body_m, float).tolist(),
                         "radius_m": float(g.radius_m)},
            "t_sent_wall_s": msg.t_sent_wall_s, "signed": msg.sig is not None, "key_id": msg.key_id,
            "imu_quality": msg.imu_quality}


_STATUS_NAME = {int(s): s.name.lower() for s in __import__("v2xpos.wire", fromlist=["TargetStatus"]).TargetStatus}
_FIX_NAME = {int(f): f.name for f in FixStatus}
_SIDES = {0: [], 1: ["master"], 2: ["slave"], 3: ["master", "slave"]}
_DEG = 180.0 / math.pi


def result_doc(res: RelativeResult) -> dict:
    """A RelativeResult as the ``/v2xpos/out/relative`` document (every field, names for codes,
    degrees for angles; NaN -- not computed -- becomes null when written with ``orjson``)."""
    kin = res.has_kinematics
    deg = _DEG
    a = res.rel_rpy_rad
    return {
        "target_id": res.target_id, "target_kind": res.target_kind,
        "status": _STATUS_NAME.get(int(res.status), "unknown"), "status_code": int(res.status),
        "fix_side": _SIDES.get(int(res.fix_side), []), "degraded": bool(res.degraded), "fleet": res.fleet,
        "master_id": res.master_id, "seq": int(res.seq), "source_seq": int(res.source_seq),
        "t_gps_s": float(res.t_gps_s), "latency_s": float(res.latency_s),
        "master_fix": _FIX_NAME.get(int(res.master_fix), "NONE"), "target_fix": _FIX_NAME.get(int(res.target_fix), "NONE"),
        "rel_pos_body_m": res.rel_pos_body_m.tolist() if kin else None,
        "rel_pos_sd_m": res.rel_pos_sd_m.tolist() if kin else None,
        "rel_vel_body_mps": res.rel_vel_body_mps.tolist() if kin else None,
        "rel_acc_body_mps2": res.rel_acc_body_mps2.tolist() if kin else None,
        "rel_roll_pitch_yaw_deg": [a[0] * deg, a[1] * deg, a[2] * deg] if kin else None,
        "rel_yaw_sd_deg": res.rel_yaw_sd_rad * deg, "range_m": res.range_m, "range_sd_m": res.range_sd_m,
        "bearing_deg": res.bearing_rad * deg, "elevation_deg": res.elevation_rad * deg,
        "longitudinal_m": res.longitudinal_m, "lateral_m": res.lateral_m, "gap_m": res.gap_m,
        "closing_speed_mps": res.closing_speed_mps, "ttc_s": res.ttc_s,
        "t_sent_wall_s": res.t_sent_wall_s, "error": None}


def scene_features(scene: Any) -> list[dict]:
    """Lane lines and static objects of a ``v2xpos.scene.Scene`` for ``/scene/lanes``:
    [{"id", "kind", "lla_rad": [[lat, lon, h or None], ...]}]."""
    out = []
    for kind, feats in (("lane", scene.lanes), ("object", scene.objects)):
        for f in feats:
            out.append({"id": str(f.id), "kind": kind,
                        "lla_rad": [[float(p[0]), float(p[1]), None if not math.isfinite(p[2]) else float(p[2])]
                                    for p in np.asarray(f.lla, float)]})
    return out


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
