"""What the master's MCAP session recording holds (written by ``v2xpos.output.recorder``): the
channels, their JSON schemas and the documents written on them.

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
"""
from __future__ import annotations

import math
from typing import Any

import numpy as np

from v2xpos.types import FixStatus, NavState
from v2xpos.wire import RelativeResult, TargetStatus

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
                 "clock_unsynced", "inconsistent", "unverified"]

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


_STATUS_NAME = {int(s): s.name.lower() for s in TargetStatus}
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
