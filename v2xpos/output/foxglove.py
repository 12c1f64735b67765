"""Foxglove's well-known schemas for the MCAP recorder: maps (``foxglove.LocationFix``), the frame
tree (``foxglove.FrameTransforms``) and 3D scenes (``foxglove.SceneUpdate``), built with the
protobuf classes of ``foxglove-schemas-protobuf`` and registered with their FileDescriptorSet
(``mcap_protobuf.schema``), so Foxglove shows a recording as a map and a 3D scene and any mcap
reader decodes them (``mcap_protobuf.decoder``).

Frames (FrameTransform: "the position and orientation of the child frame in the parent frame"):

* ``world``: east-north-up (ENU, z up) tangent frame at the first master position of the
  recording -- the fixed frame Foxglove's 3D panel should display (z up);
* ``<master_id>``: the master body frame (x forward, y right, z down), child of ``world``:
  translation = master position in ENU, rotation ``C_world_body = C_enu_ned C_nb`` (a proper
  rotation: NED -> ENU swaps x/y and negates z, determinant +1);
* ``<target_id>``: each target's body frame, child of the master body frame: translation = the
  relative position in the master body frame, rotation = ``operator_T(d_yaw, d_pitch, d_roll)``.

Targets are drawn in the master body frame (outline LINE_LOOP, reference point, label, coloured by
status); lanes and static objects in ``world``. Timestamps: the master's wall clock at logging
(the MCAP log time of the same message), so playback and transform look-ups agree; the GPS
times of validity are in the JSON channels.
"""
from __future__ import annotations

import math
from typing import Iterable

import numpy as np
from foxglove_schemas_protobuf.Color_pb2 import Color
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms
from foxglove_schemas_protobuf.LinePrimitive_pb2 import LinePrimitive
from foxglove_schemas_protobuf.LocationFix_pb2 import LocationFix
from foxglove_schemas_protobuf.Point3_pb2 import Point3
from foxglove_schemas_protobuf.Pose_pb2 import Pose
from foxglove_schemas_protobuf.Quaternion_pb2 import Quaternion
from foxglove_schemas_protobuf.SceneEntity_pb2 import SceneEntity
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from foxglove_schemas_protobuf.SpherePrimitive_pb2 import SpherePrimitive
from foxglove_schemas_protobuf.TextPrimitive_pb2 import TextPrimitive
from foxglove_schemas_protobuf.Vector3_pb2 import Vector3
from google.protobuf.timestamp_pb2 import Timestamp
from mcap_protobuf.schema import build_file_descriptor_set

from v2xpos import geo
from v2xpos.rotation import dcm_from_euler, operator_T, quat_from_dcm

WORLD_FRAME = "world"

STATUS_RGBA: dict[str, tuple[float, float, float, float]] = {
    "valid": (0.10, 0.61, 0.23, 1.0), "fix_invalid": (0.94, 0.55, 0.0, 1.0), "timeout": (0.84, 0.15, 0.16, 1.0),
    "no_data": (0.55, 0.55, 0.55, 1.0), "future": (0.56, 0.27, 0.68, 1.0),
    "attitude_uncertain": (0.79, 0.63, 0.0, 1.0), "sigma_exceeded": (0.89, 0.36, 0.61, 1.0),
    "clock_unsynced": (0.16, 0.48, 0.69, 1.0), "inconsistent": (0.50, 0.25, 0.0, 1.0),
    "unverified": (0.69, 0.50, 0.25, 1.0)}
"""Status colours (the same as the monitor page)."""

MESSAGE_CLASSES = {"foxglove.LocationFix": LocationFix, "foxglove.FrameTransforms": FrameTransforms,
                   "foxglove.SceneUpdate": SceneUpdate}


def schema_data(name: str) -> bytes:
    """Serialized FileDescriptorSet of a well-known schema (MCAP schema encoding ``protobuf``)."""
    return build_file_descriptor_set(MESSAGE_CLASSES[name]).SerializeToString()


def _stamp(t_ns: int) -> Timestamp:
    return Timestamp(seconds=int(t_ns // 1_000_000_000), nanos=int(t_ns % 1_000_000_000))


def _quat(C: np.ndarray) -> Quaternion:
    w, x, y, z = quat_from_dcm(C)
    return Quaternion(x=float(x), y=float(y), z=float(z), w=float(w))


def _color(status: str) -> Color:
    r, g, b, a = STATUS_RGBA.get(status, (0.0, 0.0, 0.0, 1.0))
    return Color(r=r, g=g, b=b, a=a)


def location_fix(t_ns: int, frame_id: str, lla_rad: Iterable[float], pos_sd_ned_m: Iterable[float],
                 v_ned_mps: Iterable[float] | None = None, yaw_rad: float | None = None,
                 status: str | None = None) -> bytes:
    """LocationFix of one vehicle: lat/lon [deg], ellipsoidal height [m], diagonal ENU covariance
    from the NED standard deviations, heading clockwise from north [rad], ENU velocity [m/s]."""
    lat, lon, h = (float(x) for x in lla_rad)
    sn, se, sd = (float(x) for x in pos_sd_ned_m)
    msg = LocationFix(timestamp=_stamp(t_ns), frame_id=frame_id, latitude=math.degrees(lat),
                      longitude=math.degrees(lon), altitude=h,
                      position_covariance=[se * se, 0, 0, 0, sn * sn, 0, 0, 0, sd * sd],
                      position_covariance_type=LocationFix.PositionCovarianceType.DIAGONAL_KNOWN)
    if yaw_rad is not None and math.isfinite(yaw_rad):
        msg.heading = float(yaw_rad) % (2 * math.pi)
    if v_ned_mps is not None:
        vn, ve, vd = (float(x) for x in v_ned_mps)
        msg.velocity.CopyFrom(Vector3(x=ve, y=vn, z=-vd))
    if status is not None:
        msg.color.CopyFrom(_color(status))
    return msg.SerializeToString()


def master_transform(t_ns: int, master_id: str, origin_lla_rad: np.ndarray, lla_rad: Iterable[float],
                     rpy_rad: Iterable[float]) -> FrameTransform:
    """world (ENU at the origin) -> master body (FRD)."""
    enu = geo.lla_to_enu(np.asarray(list(lla_rad), float), origin_lla_rad)
    C = geo.NED_TO_ENU @ dcm_from_euler(*[float(x) for x in rpy_rad])
    return FrameTransform(timestamp=_stamp(t_ns), parent_frame_id=WORLD_FRAME, child_frame_id=master_id,
                          translation=Vector3(x=float(enu[0]), y=float(enu[1]), z=float(enu[2])),
                          rotation=_quat(C))


def target_transform(t_ns: int, master_id: str, target_id: str, rel_pos_body_m: Iterable[float],
                     rel_rpy_rad: Iterable[float]) -> FrameTransform:
    """master body -> target body (relative position and attitude of a result)."""
    x, y, z = (float(v) for v in rel_pos_body_m)
    d_roll, d_pitch, d_yaw = (float(v) for v in rel_rpy_rad)
    return FrameTransform(timestamp=_stamp(t_ns), parent_frame_id=master_id, child_frame_id=target_id,
                          translation=Vector3(x=x, y=y, z=z), rotation=_quat(operator_T(d_yaw, d_pitch, d_roll)))


def frame_transforms(transforms: list[FrameTransform]) -> bytes:
    return FrameTransforms(transforms=transforms).SerializeToString()


def target_entity(t_ns: int, master_id: str, target_id: str, status: str, rel_pos_body_m: Iterable[float],
                  rel_rpy_rad: Iterable[float], outline_body_m: np.ndarray | None, radius_m: float,
                  label: str) -> SceneEntity:
    """A target in the master body frame: its outline (polygon/contact points as a LINE_LOOP, or a
    sphere of the circle radius), its reference point and a label, in its status colour."""
    p = np.array([float(v) for v in rel_pos_body_m])
    d_roll, d_pitch, d_yaw = (float(v) for v in rel_rpy_rad)
    col = _color(status)
    ent = SceneEntity(timestamp=_stamp(t_ns), frame_id=master_id, id=f"target/{target_id}")
    if outline_body_m is not None and len(outline_body_m) >= 2:
        pts = p + np.asarray(outline_body_m, float) @ operator_T(d_yaw, d_pitch, d_roll).T
        ent.lines.append(LinePrimitive(type=LinePrimitive.Type.LINE_LOOP, thickness=0.08, color=col,
                                       points=[Point3(x=float(a), y=float(b), z=float(c)) for a, b, c in pts],
                                       pose=Pose(orientation=Quaternion(w=1.0))))
    size = max(0.3, 2.0 * float(radius_m)) if radius_m else 0.3
    ent.spheres.append(SpherePrimitive(pose=Pose(position=Vector3(x=p[0], y=p[1], z=p[2]),
                                                 orientation=Quaternion(w=1.0)),
                                       size=Vector3(x=size, y=size, z=size), color=col))
    ent.texts.append(TextPrimitive(pose=Pose(position=Vector3(x=p[0], y=p[1], z=p[2] - 1.5),
                                             orientation=Quaternion(w=1.0)),
                                   billboard=True, font_size=14.0, scale_invariant=True, color=col, text=label))
    return ent


def scene_update(entities: list[SceneEntity]) -> bytes:
    return SceneUpdate(entities=entities).SerializeToString()


def lanes_entity(t_ns: int, features: list[dict], origin_lla_rad: np.ndarray) -> SceneUpdate:
    """Lane lines (LINE_STRIP) and static objects (LINE_LOOP / sphere) of the site in ``world``.
    ``features``: [{"id", "kind" ("lane" | "object"), "lla_rad": [[lat, lon, h or None], ...]}];
    a missing height is the origin's."""
    ents = []
    for f in features:
        lla = np.array([[p[0], p[1], origin_lla_rad[2] if p[2] is None else p[2]] for p in f["lla_rad"]], float)
        enu = np.atleast_2d(geo.lla_to_enu(lla, origin_lla_rad))
        pts = [Point3(x=float(a), y=float(b), z=float(c)) for a, b, c in enu]
        ent = SceneEntity(timestamp=_stamp(t_ns), frame_id=WORLD_FRAME, id=f"{f['kind']}/{f['id']}")
        if f["kind"] == "lane":
            ent.lines.append(LinePrimitive(type=LinePrimitive.Type.LINE_STRIP, thickness=0.15,
                                           color=Color(r=0.9, g=0.9, b=0.95, a=1.0), points=pts,
                                           pose=Pose(orientation=Quaternion(w=1.0))))
        elif len(pts) >= 2:
            ent.lines.append(LinePrimitive(type=LinePrimitive.Type.LINE_LOOP, thickness=0.1,
                                           color=Color(r=0.3, g=0.5, b=0.9, a=1.0), points=pts,
                                           pose=Pose(orientation=Quaternion(w=1.0))))
        else:
            ent.spheres.append(SpherePrimitive(pose=Pose(position=Vector3(x=pts[0].x, y=pts[0].y, z=pts[0].z),
                                                         orientation=Quaternion(w=1.0)),
                                               size=Vector3(x=0.5, y=0.5, z=0.5),
                                               color=Color(r=0.3, g=0.5, b=0.9, a=1.0)))
        ents.append(ent)
    return SceneUpdate(entities=ents).SerializeToString()
