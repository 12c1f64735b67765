"""UDP (Ethernet) output of the master's results: a fixed little-endian binary layout.

Public API (stable)
-------------------
* ``UdpOutput(host="127.0.0.1", port=..., allow_remote=False)``: ``send(results, seq, t_gps_s,
  lanes=None, objects=None) -> bytes sent``, ``datagrams_sent``, ``close()``. Destinations that are
  not loopback are refused unless ``allow_remote=True``.
* ``build_datagram(results, seq, t_gps_s, lanes=None, objects=None) -> bytes`` and
  ``parse_datagram(data) -> UdpDatagram`` (raises ``UdpFormatError(reason, offset)``).
* ``LaneRecord``, ``ObjectRecord`` -- scene records; ``records_from_scene(scene_result)
  -> (lanes, objects)``.

Layout (all little-endian; docs/protocol.md §6):
header ``<4sBBHHHId`` (24 bytes): magic b"V2XR", version 1, flags 0, n_targets, n_lanes,
n_objects, seq (u32), t_gps_s (f64); then n_targets target records, n_lanes lane records,
n_objects object records (formats ``TARGET_FMT``, ``LANE_FMT``, ``OBJECT_FMT``).
Target kinematics are NaN when status is not VALID; TTC NaN = none.
"""
from __future__ import annotations

import ipaddress
import math
import socket
import struct
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np

from v2xpos.wire import FixSide, RelativeResult, TargetStatus

MAGIC = b"V2XR"
VERSION = 1
HEADER_FMT = "<4sBBHHHId"
TARGET_FMT = "<32sBBBBQf3d3f3f3f3fdffffffff"
LANE_FMT = "<H2xff"
OBJECT_FMT = "<HBxffff"
HEADER = struct.Struct(HEADER_FMT)
TARGET = struct.Struct(TARGET_FMT)
LANE = struct.Struct(LANE_FMT)
OBJECT = struct.Struct(OBJECT_FMT)
MAX_DATAGRAM_BYTES = 65507
FLAG_DEGRADED, FLAG_PEDESTRIAN = 1, 2


class UdpFormatError(ValueError):
    """Malformed datagram: ``reason`` and byte ``offset``."""

    def __init__(self, reason: str, offset: int = 0):
        self.reason, self.offset = reason, offset
        super().__init__(f"{reason} (at byte {offset})")


@dataclass
class LaneRecord:
    """Signed lateral distance [m, + line to the right] and its rate [m/s] to lane line ``index``."""
    index: int
    lateral_m: float
    lateral_speed_mps: float


@dataclass
class ObjectRecord:
    """Static object ``index`` (kind 0 point, 1 polygon): distance [m], bearing [rad], TTC [s or NaN]."""
    index: int
    kind: int
    distance_m: float
    bearing_rad: float
    ttc_s: float
    closing_speed_mps: float


@dataclass
class UdpDatagram:
    """A parsed datagram."""
    seq: int
    t_gps_s: float
    targets: list = field(default_factory=list)
    lanes: list = field(default_factory=list)
    objects: list = field(default_factory=list)


def records_from_scene(scene_result: Any) -> tuple:
    """(lanes, objects) records of a ``scene.SceneResult`` (object index = position in Scene.objects)."""
    r = scene_result
    lanes = [LaneRecord(int(i), float(d), float(s))
             for i, d, s in zip(r.lane_index, r.lane_lateral_m, r.lane_lateral_speed_mps)]
    objects = [ObjectRecord(k, int(kind), float(d), float(b), float(t), float(c))
               for k, (kind, d, b, t, c) in enumerate(zip(r.object_kind, r.object_distance_m, r.object_bearing_rad,
                                                          r.object_ttc_s, r.object_closing_speed_mps))]
    return lanes, objects


def _nan(x: float | None) -> float:
    return math.nan if x is None else float(x)


def _vec(a: Any) -> list:
    return a.tolist() if type(a) is np.ndarray else [float(x) for x in a]


_NAN3 = [math.nan] * 3
_NAN9 = [math.nan] * 9


def _pack_target(r: RelativeResult) -> bytes:
    flags = (FLAG_DEGRADED if r.degraded else 0) | (FLAG_PEDESTRIAN if r.target_kind == "pedestrian" else 0)
    if r.status == TargetStatus.VALID:
        p, ps, v = _vec(r.rel_pos_body_m), _vec(r.rel_pos_sd_m), _vec(r.rel_vel_body_mps)
        a, att = _vec(r.rel_acc_body_mps2), _vec(r.rel_rpy_rad)
        scal = (r.range_m, r.range_sd_m, r.bearing_rad, r.elevation_rad, r.longitudinal_m, r.lateral_m,
                r.gap_m, r.closing_speed_mps, _nan(r.ttc_s))
    else:
        p = ps = v = a = att = _NAN3
        scal = _NAN9
    return TARGET.pack(r.target_id.encode()[:32], int(r.status), int(r.fix_side), flags, 0,
                       int(r.source_seq) & 0xFFFFFFFFFFFFFFFF, _nan(r.latency_s), *p, *ps, *v, *a, *att, *scal)


def build_datagram(results: Sequence[RelativeResult], seq: int, t_gps_s: float,
                   lanes: Sequence[LaneRecord] | None = None,
                   objects: Sequence[ObjectRecord] | None = None) -> bytes:
    """Serialise one master update (see module docstring for the layout)."""
    lanes = lanes or []
    objects = objects or []
    parts = [HEADER.pack(MAGIC, VERSION, 0, len(results), len(lanes), len(objects), seq & 0xFFFFFFFF, t_gps_s)]
    parts += [_pack_target(r) for r in results]
    parts += [LANE.pack(l.index, l.lateral_m, l.lateral_speed_mps) for l in lanes]
    parts += [OBJECT.pack(o.index, o.kind, o.distance_m, o.bearing_rad, _nan(o.ttc_s), o.closing_speed_mps)
              for o in objects]
    data = b"".join(parts)
    if len(data) > MAX_DATAGRAM_BYTES:
        raise ValueError(f"datagram of {len(data)} bytes exceeds {MAX_DATAGRAM_BYTES}")
    return data


def parse_datagram(data: bytes) -> UdpDatagram:
    """Parse a datagram into RelativeResult / LaneRecord / ObjectRecord lists; UdpFormatError if bad."""
    if len(data) < HEADER.size:
        raise UdpFormatError(f"shorter than the {HEADER.size}-byte header", 0)
    magic, version, _flags, nt, nl, no, seq, t = HEADER.unpack_from(data, 0)
    if magic != MAGIC:
        raise UdpFormatError(f"bad magic {magic!r}", 0)
    if version != VERSION:
        raise UdpFormatError(f"unknown version {version}", 4)
    expect = HEADER.size + nt * TARGET.size + nl * LANE.size + no * OBJECT.size
    if len(data) != expect:
        raise UdpFormatError(f"length {len(data)} != {expect} for {nt} targets, {nl} lanes, {no} objects", 6)
    out = UdpDatagram(seq=seq, t_gps_s=t)
    off = HEADER.size
    for _ in range(nt):
        f = TARGET.unpack_from(data, off)
        try:
            status = TargetStatus(f[1])
        except ValueError:
            raise UdpFormatError(f"unknown target status {f[1]}", off + 32) from None
        try:
            tid = f[0].rstrip(b"\0").decode()
        except UnicodeDecodeError:
            raise UdpFormatError("target id not utf-8", off) from None
        k = 7
        vec = [np.array(f[k + 3 * i:k + 3 * i + 3], dtype=float) for i in range(5)]
        (rng, rng_sd, brg, elv, lon, lat, gap, cls, ttc) = f[k + 15:k + 24]
        out.targets.append(RelativeResult(
            target_id=tid, target_kind="pedestrian" if f[3] & FLAG_PEDESTRIAN else "vehicle", status=status,
            fix_side=FixSide(f[2] & 3), degraded=bool(f[3] & FLAG_DEGRADED), seq=seq, source_seq=f[5],
            t_gps_s=t, latency_s=f[6], rel_pos_body_m=vec[0], rel_pos_sd_m=vec[1],
            rel_vel_body_mps=vec[2], rel_acc_body_mps2=vec[3], rel_rpy_rad=vec[4], range_m=rng,
            range_sd_m=rng_sd, bearing_rad=brg, elevation_rad=elv, longitudinal_m=lon, lateral_m=lat,
            gap_m=gap, closing_speed_mps=cls, ttc_s=None if math.isnan(ttc) else ttc))
        off += TARGET.size
    for _ in range(nl):
        out.lanes.append(LaneRecord(*LANE.unpack_from(data, off)))
        off += LANE.size
    for _ in range(no):
        out.objects.append(ObjectRecord(*OBJECT.unpack_from(data, off)))
        off += OBJECT.size
    return out


def _is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def _is_multicast(host: str) -> bool:
    try:
        return ipaddress.ip_address(host).is_multicast
    except ValueError:
        return False


class UdpOutput:
    """Sends one datagram per master update to (host, port); loopback only unless allow_remote."""

    def __init__(self, host: str = "127.0.0.1", port: int = 47001, allow_remote: bool = False):
        if not allow_remote and not _is_loopback(host):
            raise ValueError(f"UDP destination {host!r} is not loopback; pass allow_remote=True to send there")
        if _is_multicast(host):
            raise ValueError(f"UDP destination {host!r} is multicast; refused")
        family = socket.AF_INET6 if ":" in host else socket.AF_INET
        self.address = ("127.0.0.1" if host == "localhost" else host, int(port))
        self.sock = socket.socket(family, socket.SOCK_DGRAM)
        self.datagrams_sent = 0
        self.bytes_sent = 0

    def send(self, results: Sequence[RelativeResult], seq: int, t_gps_s: float,
             lanes: Sequence[LaneRecord] | None = None, objects: Sequence[ObjectRecord] | None = None) -> int:
        """Send one update; returns the number of bytes sent."""
        data = build_datagram(results, seq, t_gps_s, lanes, objects)
        n = self.sock.sendto(data, self.address)
        self.datagrams_sent += 1
        self.bytes_sent += n
        return n

    def close(self) -> None:
        """Close the socket."""
        self.sock.close()

    def __enter__(self) -> "UdpOutput":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
