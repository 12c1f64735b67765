"""UDP (Ethernet) output of the master's results: a fixed little-endian binary layout.

Public API (stable)
-------------------
* ``UdpOutput(host="127.0.0.1", port=...)``: ``send(results, seq, t_gps_s, lanes=None,
  objects=None) -> bytes sent``, ``datagrams_sent``, ``close()``. Any unicast destination
  (loopback or not, IPv4 or IPv6, or a host name resolving to one); multicast, broadcast and
  unspecified addresses are refused (``check_destination(host)`` raises ValueError saying why).
* ``build_datagram(results, seq, t_gps_s, lanes=None, objects=None) -> bytes`` and
  ``parse_datagram(data) -> UdpDatagram`` (raises ``UdpFormatError(reason, offset)``); the parser
  also reads version-1 datagrams (one header time for every record, no fix states) and version-2
  ones (no reasons, no protection level).
* ``LaneRecord``, ``ObjectRecord`` -- scene records; ``records_from_scene(scene_result)
  -> (lanes, objects)``.

Layout version 3 (all little-endian; docs/protocol.md §6):
header ``<4sBBHHHId`` (24 bytes): magic b"V2XR", version 3, flags, n_targets, n_lanes,
n_objects, seq (u32), t_gps_s (f64, the master time of the datagram's last result, or of the
heartbeat); then n_targets target records (``TARGET_FMT``, 184 bytes: each with its own time of
validity ``t_gps_s``, master output sequence number, master and target fix status and sigmas,
which vehicle made a non-VALID status and both filters' reasons, the relative protection level),
n_lanes lane records, n_objects object records (``LANE_FMT``, ``OBJECT_FMT``). Version 3 uses the
bytes version 2 left as padding: a record has the same size and offsets.
Header flag ``HEADER_FLAG_HEARTBEAT``: the master's heartbeat (no records), sent at its status rate
whatever it has to say, with its GPS time now: a consumer that gets no datagram for three periods
knows the master is gone, not that there is nothing to report (``heartbeat``).
Target kinematics are NaN unless the status carries kinematics (``wire.KINEMATIC_STATUSES``;
only VALID may be used as a reference); TTC NaN = none.
"""
from __future__ import annotations

import ipaddress
import math
import socket
import struct
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np

from v2xpos.types import FixStatus
from v2xpos.wire import KINEMATIC_STATUSES, FixSide, RelativeResult, TargetStatus

MAGIC = b"V2XR"
VERSION = 3
VERSIONS = (1, 2, 3)
HEADER_FMT = "<4sBBHHHId"
TARGET_FMT = "<32sBBBBBBBBdQIf3d3f3f3f3fd9ff"
"""id, status, fix_side, flags, master_fix, target_fix, reason_side, master_reason, target_reason,
t_gps_s, source_seq, seq, latency_s, position (f64), position sd, velocity, acceleration,
d_roll/d_pitch/d_yaw, range (f64), range sd, bearing, elevation, longitudinal, lateral, gap,
closing speed, TTC, relative yaw sd, protection level (NaN: none)."""
TARGET_V2_FMT = "<32sBBBBB3xdQIf3d3f3f3f3fd9f4x"
TARGET_V1_FMT = "<32sBBBBQf3d3f3f3f3fdffffffff"
LANE_FMT = "<H2xff"
OBJECT_FMT = "<HBxffff"
HEADER = struct.Struct(HEADER_FMT)
TARGET = struct.Struct(TARGET_FMT)
TARGET_V2 = struct.Struct(TARGET_V2_FMT)
TARGET_V1 = struct.Struct(TARGET_V1_FMT)
assert TARGET.size == TARGET_V2.size
LANE = struct.Struct(LANE_FMT)
OBJECT = struct.Struct(OBJECT_FMT)
MAX_DATAGRAM_BYTES = 65507
FLAG_DEGRADED, FLAG_PEDESTRIAN = 1, 2
HEADER_FLAG_HEARTBEAT = 1
_FIX_BY_CODE = {int(f): f for f in FixStatus}


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
    """A parsed datagram (header sequence number and time; ``version`` of its layout)."""
    seq: int
    t_gps_s: float
    version: int = VERSION
    heartbeat: bool = False
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
    if r.status in KINEMATIC_STATUSES:
        p, ps, v = _vec(r.rel_pos_body_m), _vec(r.rel_pos_sd_m), _vec(r.rel_vel_body_mps)
        a, att = _vec(r.rel_acc_body_mps2), _vec(r.rel_rpy_rad)
        scal = (r.range_m, r.range_sd_m, r.bearing_rad, r.elevation_rad, r.longitudinal_m, r.lateral_m,
                r.gap_m, r.closing_speed_mps, _nan(r.ttc_s))
        yaw_sd = r.rel_yaw_sd_rad
    else:
        p = ps = v = a = att = _NAN3
        scal = _NAN9
        yaw_sd = math.nan
    return TARGET.pack(r.target_id.encode()[:32], int(r.status), int(r.fix_side), flags, int(r.master_fix),
                       int(r.target_fix), int(r.reason_side), min(int(r.master_reason), 255),
                       min(int(r.target_reason), 255), float(r.t_gps_s), int(r.source_seq) & 0xFFFFFFFFFFFFFFFF,
                       int(r.seq) & 0xFFFFFFFF, _nan(r.latency_s), *p, *ps, *v, *a, *att, *scal, yaw_sd,
                       r.protection_m)


def heartbeat(seq: int, t_gps_s: float) -> bytes:
    """The master's heartbeat datagram: a header with ``HEADER_FLAG_HEARTBEAT`` and no records."""
    return HEADER.pack(MAGIC, VERSION, HEADER_FLAG_HEARTBEAT, 0, 0, 0, seq & 0xFFFFFFFF, t_gps_s)


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


def _fix(code: int, offset: int, what: str) -> FixStatus:
    fix = _FIX_BY_CODE.get(code)
    if fix is None:
        raise UdpFormatError(f"unknown {what} fix status {code}", offset)
    return fix


def _target_from_record(f: tuple, off: int, version: int, seq: int, t_header: float) -> RelativeResult:
    try:
        status = TargetStatus(f[1])
    except ValueError:
        raise UdpFormatError(f"unknown target status {f[1]}", off + 32) from None
    try:
        tid = f[0].rstrip(b"\0").decode()
    except UnicodeDecodeError:
        raise UdpFormatError("target id not utf-8", off) from None
    if version == 1:
        if status > TargetStatus.FUTURE:
            raise UdpFormatError(f"status {f[1]} does not exist in version 1", off + 32)
        master_fix = target_fix = FixStatus.NONE
        t_rec, src_seq, rec_seq, latency, k, yaw_sd = t_header, f[5], seq, f[6], 7, math.nan
    elif version == 2:
        if status > TargetStatus.INCONSISTENT:
            raise UdpFormatError(f"status {f[1]} does not exist in version 2", off + 32)
        master_fix, target_fix = _fix(f[4], off + 35, "master"), _fix(f[5], off + 36, "target")
        t_rec, src_seq, rec_seq, latency, k, yaw_sd = f[6], f[7], f[8], f[9], 10, f[34]
    else:
        master_fix, target_fix = _fix(f[4], off + 35, "master"), _fix(f[5], off + 36, "target")
        if f[6] > 3:
            raise UdpFormatError(f"reason side {f[6]} outside 0..3", off + 37)
        t_rec, src_seq, rec_seq, latency, k, yaw_sd = f[9], f[10], f[11], f[12], 13, f[37]
    vec = [np.array(f[k + 3 * i:k + 3 * i + 3], dtype=float) for i in range(5)]
    (rng, rng_sd, brg, elv, lon, lat, gap, cls, ttc) = f[k + 15:k + 24]
    res = RelativeResult(
        target_id=tid, target_kind="pedestrian" if f[3] & FLAG_PEDESTRIAN else "vehicle", status=status,
        fix_side=FixSide(f[2] & 3), degraded=bool(f[3] & FLAG_DEGRADED), seq=rec_seq, source_seq=src_seq,
        t_gps_s=t_rec, latency_s=latency, rel_pos_body_m=vec[0], rel_pos_sd_m=vec[1],
        rel_vel_body_mps=vec[2], rel_acc_body_mps2=vec[3], rel_rpy_rad=vec[4], range_m=rng,
        range_sd_m=rng_sd, bearing_rad=brg, elevation_rad=elv, longitudinal_m=lon, lateral_m=lat,
        gap_m=gap, closing_speed_mps=cls, ttc_s=None if math.isnan(ttc) else ttc, schema=version,
        master_fix=master_fix, target_fix=target_fix, rel_yaw_sd_rad=yaw_sd)
    if version >= 3:
        res.reason_side, res.master_reason, res.target_reason, res.protection_m = FixSide(f[6]), f[7], f[8], f[38]
    return res


def parse_datagram(data: bytes) -> UdpDatagram:
    """Parse a datagram (a version of VERSIONS) into RelativeResult / LaneRecord / ObjectRecord lists;
    UdpFormatError if bad. Each target's ``t_gps_s`` is its record's time of validity (version 1:
    the header time), ``seq`` its master output sequence number (version 1: the header's)."""
    if len(data) < HEADER.size:
        raise UdpFormatError(f"shorter than the {HEADER.size}-byte header", 0)
    magic, version, flags, nt, nl, no, seq, t = HEADER.unpack_from(data, 0)
    if magic != MAGIC:
        raise UdpFormatError(f"bad magic {magic!r}", 0)
    if version not in VERSIONS:
        raise UdpFormatError(f"unknown version {version}", 4)
    record = {1: TARGET_V1, 2: TARGET_V2, 3: TARGET}[version]
    expect = HEADER.size + nt * record.size + nl * LANE.size + no * OBJECT.size
    if len(data) != expect:
        raise UdpFormatError(f"length {len(data)} != {expect} for {nt} targets, {nl} lanes, {no} objects "
                             f"(version {version})", 6)
    out = UdpDatagram(seq=seq, t_gps_s=t, version=version, heartbeat=bool(flags & HEADER_FLAG_HEARTBEAT))
    off = HEADER.size
    for _ in range(nt):
        out.targets.append(_target_from_record(record.unpack_from(data, off), off, version, seq, t))
        off += record.size
    for _ in range(nl):
        out.lanes.append(LaneRecord(*LANE.unpack_from(data, off)))
        off += LANE.size
    for _ in range(no):
        out.objects.append(ObjectRecord(*OBJECT.unpack_from(data, off)))
        off += OBJECT.size
    return out


def check_destination(host: str) -> None:
    """Raise ValueError unless ``host`` is a unicast address (or a name, resolved when opening):
    multicast, broadcast (255.255.255.255) and unspecified (0.0.0.0, ::) destinations are refused."""
    if not isinstance(host, str) or not host.strip():
        raise ValueError(f"UDP destination {host!r} is empty")
    try:
        addr = ipaddress.ip_address(host)
    except ValueError:
        return                                  # a host name: checked again once resolved
    if addr.is_multicast:
        raise ValueError(f"UDP destination {host!r} is multicast; only unicast destinations are allowed")
    if addr.is_unspecified:
        raise ValueError(f"UDP destination {host!r} is the unspecified address; give the receiver's address")
    if isinstance(addr, ipaddress.IPv4Address) and addr == ipaddress.IPv4Address("255.255.255.255"):
        raise ValueError(f"UDP destination {host!r} is the broadcast address; only unicast destinations are allowed")


class UdpOutput:
    """Sends one datagram per master update to a unicast (host, port) (see ``check_destination``)."""

    def __init__(self, host: str = "127.0.0.1", port: int = 47001):
        check_destination(host)
        if not 0 < int(port) < 65536:
            raise ValueError(f"UDP port {port} outside 1..65535")
        try:
            infos = socket.getaddrinfo(host, int(port), type=socket.SOCK_DGRAM)
        except socket.gaierror as exc:
            raise ValueError(f"UDP destination {host!r}: cannot resolve ({exc.strerror})") from None
        family, _, _, _, sockaddr = infos[0]
        check_destination(sockaddr[0])
        self.address = sockaddr
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

    def send_heartbeat(self, seq: int, t_gps_s: float) -> int:
        """Send the master's heartbeat (``heartbeat``); returns the number of bytes sent."""
        n = self.sock.sendto(heartbeat(seq, t_gps_s), self.address)
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
