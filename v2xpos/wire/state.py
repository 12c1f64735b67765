"""The ``StateMessage`` a vehicle or pedestrian publishes: its content, its outline (``Geometry``),
and its codec (``encode_state`` / ``decode_state``).

Frames and units: positions geodetic (lat/lon rad, ellipsoidal height m); velocity NED [m/s];
acceleration (kinematic, gravity removed) and angular rate in the vehicle body frame
(x forward, y right, z down) [m/s^2, rad/s]; attitude Z-Y-X Euler (roll, pitch, yaw) of C_nb
[rad]; standard deviations are 1-sigma per axis. ``decode_state`` keeps the signed ``body`` in
``StateMessage.signed_payload`` so a verifier checks ``sig`` over it without re-encoding.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import msgpack
import numpy as np

from v2xpos.types import FilterReason, FixStatus, NavState

from .envelope import Signer, seal, unpack_envelope
from .fields import (FIX_BY_CODE, KINDS, MAX_ACC_MPS2, MAX_GEOMETRY_M, MAX_GEOMETRY_POINTS, MAX_HEIGHT_M,
                     MAX_RATE_RPS, MAX_SD, MAX_SPEED_MPS, MAX_T_GPS_S, MIN_HEIGHT_M, WireError, f3, get_field,
                     ident, num, opt_num, uint, unpack_body, vec3_list)

SCHEMA_VERSION = 2
"""Version of the StateMessage body the encoder writes (``ver``): 2 adds the sender's filter reason
(``rsn``, ``v2xpos.types.FilterReason``), its horizontal protection level (``pl``) and its session
GPS time at publishing (``ts``)."""
SCHEMA_VERSIONS = (1, 2)
"""StateMessage body versions the decoder accepts; a version-1 body decodes with reason 0 (none
given), protection level NaN and no send time (docs/protocol.md)."""
MAX_REASON_CODE = 63
"""Largest filter reason code on the wire (codes a newer sender adds decode as numbers)."""
STATE_FLAG_ATTITUDE_UNDETERMINED = 1
"""State flag bit: the sender's attitude (heading) is not determined yet (e.g. pending at a stop)."""
STATE_FLAG_TIME_UNSYNCED = 2
"""State flag bit: the sender's clock is off GNSS time beyond its bound."""
STATE_FLAG_INCONSISTENT = 4
"""State flag bit: the sender's filter fails its own consistency test (block NIS, body-frame
innovation mean or solution separation, ``v2xpos.ins.consistency``): its covariance does not
describe its errors. Released once the evidence is gone (docs/integrity.md)."""
STATE_FLAG_UNVERIFIED = 8
"""State flag bit: the sender's solution is not verified: the protection level of its
solution-separation test against an undeclared horizontal lever arm is above its limit
(``v2xpos.ins.consistency.FaultTolerantSolution``)."""
GEOMETRY_KINDS = ("points", "polygon", "circle")


@dataclass
class Geometry:
    """Target outline in its own body frame (x forward, y right, z down) [m].

    kind "points": contact points (N, 3), e.g. the four bumper corners; "polygon": footprint
    vertices (N, 3) in order (closed implicitly); "circle": a disc of ``radius_m`` about the
    reference point (pedestrians), ``points_body_m`` empty.
    """
    kind: str = "circle"
    points_body_m: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    radius_m: float = 0.0

    @classmethod
    def box(cls, front_m: float, rear_m: float, half_width_m: float, z_m: float = 0.0,
            kind: str = "polygon") -> "Geometry":
        """Rectangle footprint: x from -rear_m to front_m, y +-half_width_m (corners FL, FR, RR, RL)."""
        pts = np.array([[front_m, -half_width_m, z_m], [front_m, half_width_m, z_m],
                        [-rear_m, half_width_m, z_m], [-rear_m, -half_width_m, z_m]])
        return cls(kind=kind, points_body_m=pts, radius_m=0.0)

    def __eq__(self, other: object) -> bool:
        return (isinstance(other, Geometry) and self.kind == other.kind
                and self.radius_m == other.radius_m
                and np.array_equal(self.points_body_m, other.points_body_m))


def _vec(x: Any) -> np.ndarray:
    return np.asarray(x, dtype=float).reshape(3)


@dataclass
class StateMessage:
    """State of one vehicle or pedestrian at GPS time ``t_gps_s`` (time of validity).

    See the module docstring for frames/units. ``seq`` increments by one per message per
    vehicle. ``t_sent_wall_s``: sender's wall clock (time.time()) at publish, for end-to-end
    latency on one machine. ``imu_quality``: optional grading payload (dict). ``sig``/``key_id``:
    Ed25519 signature over ``signed_payload`` (the body bytes), filled by decode_state.
    """
    fleet: str
    vehicle_id: str
    seq: int
    t_gps_s: float
    fix: FixStatus
    lat_rad: float
    lon_rad: float
    height_m: float
    v_ned_mps: np.ndarray
    acc_body_mps2: np.ndarray
    rate_body_rps: np.ndarray
    rpy_rad: np.ndarray
    pos_sd_m: np.ndarray
    vel_sd_mps: np.ndarray
    att_sd_rad: np.ndarray
    geometry: Geometry = field(default_factory=Geometry)
    kind: str = "vehicle"
    schema: int = SCHEMA_VERSION
    t_sent_wall_s: float | None = None
    imu_quality: dict | None = None
    sig: bytes | None = None
    key_id: str | None = None
    signed_payload: bytes | None = field(default=None, compare=False, repr=False)
    attitude_ok: bool = True
    time_ok: bool = True
    pos_corr: np.ndarray = field(default_factory=lambda: np.zeros(3))
    consistent: bool = True
    verified: bool = True
    reason: int = 0
    """``v2xpos.types.FilterReason`` code of the sender's filter (0: OK or not given)."""
    protection_m: float = math.nan
    """Sender's horizontal protection level [m] (NaN: none computed or not given)."""
    t_sent_gps_s: float | None = None
    """Sender's session GPS time when it published the message [s] (the master compares it with
    its own clock: ``master.clock_check``)."""

    @property
    def lla(self) -> np.ndarray:
        """(lat_rad, lon_rad, h_m)."""
        return np.array([self.lat_rad, self.lon_rad, self.height_m])

    @property
    def t_s(self) -> float:
        """Alias of t_gps_s (same name as NavState)."""
        return self.t_gps_s

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, StateMessage):
            return NotImplemented
        scalars = ("fleet", "vehicle_id", "seq", "t_gps_s", "fix", "lat_rad", "lon_rad", "height_m",
                   "geometry", "kind", "schema", "t_sent_wall_s", "imu_quality", "sig", "key_id",
                   "attitude_ok", "time_ok", "consistent", "verified", "reason", "t_sent_gps_s")
        arrays = ("v_ned_mps", "acc_body_mps2", "rate_body_rps", "rpy_rad", "pos_sd_m",
                  "vel_sd_mps", "att_sd_rad", "pos_corr")
        pl_a, pl_b = self.protection_m, other.protection_m
        return (all(getattr(self, k) == getattr(other, k) for k in scalars)
                and (pl_a == pl_b or (math.isnan(pl_a) and math.isnan(pl_b)))
                and all(np.array_equal(getattr(self, k), getattr(other, k)) for k in arrays))

    @classmethod
    def from_nav_state(cls, nav: NavState, fleet: str, vehicle_id: str, seq: int,
                       geometry: Geometry | None = None, kind: str = "vehicle",
                       t_sent_wall_s: float | None = None, time_ok: bool = True) -> "StateMessage":
        """Wrap a NavState for publishing; ``time_ok``: the sender's clock is within its bound of GNSS
        time (``SessionClock.synchronised``)."""
        return cls(fleet=fleet, vehicle_id=vehicle_id, seq=int(seq), t_gps_s=float(nav.t_s),
                   fix=FixStatus(nav.fix), lat_rad=float(nav.lla[0]), lon_rad=float(nav.lla[1]),
                   height_m=float(nav.lla[2]), v_ned_mps=_vec(nav.v_ned_mps),
                   acc_body_mps2=_vec(nav.acc_body_mps2), rate_body_rps=_vec(nav.rate_body_rps),
                   rpy_rad=_vec(nav.rpy_rad), pos_sd_m=_vec(nav.pos_sd_m),
                   vel_sd_mps=_vec(nav.vel_sd_mps), att_sd_rad=_vec(nav.att_sd_rad),
                   geometry=geometry if geometry is not None else Geometry(), kind=kind,
                   t_sent_wall_s=t_sent_wall_s, attitude_ok=bool(getattr(nav, "attitude_ok", True)),
                   time_ok=bool(time_ok), pos_corr=_vec(getattr(nav, "pos_corr", (0.0, 0.0, 0.0))),
                   consistent=bool(getattr(nav, "consistent", True)), verified=bool(getattr(nav, "verified", True)),
                   reason=int(getattr(nav, "reason", 0)), protection_m=float(getattr(nav, "protection_m", math.nan)))

    def to_nav_state(self) -> NavState:
        """The kinematic content as a NavState."""
        return NavState(t_s=self.t_gps_s, lla=self.lla, v_ned_mps=self.v_ned_mps.copy(),
                        acc_body_mps2=self.acc_body_mps2.copy(), rate_body_rps=self.rate_body_rps.copy(),
                        rpy_rad=self.rpy_rad.copy(), pos_sd_m=self.pos_sd_m.copy(),
                        vel_sd_mps=self.vel_sd_mps.copy(), att_sd_rad=self.att_sd_rad.copy(),
                        fix=FixStatus(self.fix), attitude_ok=self.attitude_ok, pos_corr=self.pos_corr.copy(),
                        consistent=self.consistent, verified=self.verified, reason=_filter_reason(self.reason),
                        protection_m=self.protection_m)


def _filter_reason(code: int) -> "FilterReason | int":
    """The FilterReason of a wire code (a code this version does not know stays a number)."""
    try:
        return FilterReason(code)
    except ValueError:
        return code


def _geometry_map(g: Geometry) -> dict:
    pts = np.asarray(g.points_body_m, dtype=float).reshape(-1)
    return {"k": g.kind, "p": [float(x) for x in pts], "r": float(g.radius_m)}


def encode_state_body(msg: StateMessage) -> bytes:
    """The msgpack body of a StateMessage (the byte string that gets signed)."""
    body = {"T": "state", "ver": int(msg.schema), "fleet": msg.fleet, "id": msg.vehicle_id,
            "kind": msg.kind, "seq": int(msg.seq), "t": float(msg.t_gps_s), "fix": int(msg.fix),
            "lat": float(msg.lat_rad), "lon": float(msg.lon_rad), "h": float(msg.height_m),
            "v": f3(msg.v_ned_mps), "a": f3(msg.acc_body_mps2), "w": f3(msg.rate_body_rps),
            "rpy": f3(msg.rpy_rad), "sp": f3(msg.pos_sd_m), "sv": f3(msg.vel_sd_mps),
            "sa": f3(msg.att_sd_rad), "g": _geometry_map(msg.geometry)}
    if msg.t_sent_wall_s is not None:
        body["tw"] = float(msg.t_sent_wall_s)
    if msg.imu_quality is not None:
        body["iq"] = msg.imu_quality
    flags = ((0 if msg.attitude_ok else STATE_FLAG_ATTITUDE_UNDETERMINED) | (0 if msg.time_ok else STATE_FLAG_TIME_UNSYNCED)
             | (0 if msg.consistent else STATE_FLAG_INCONSISTENT) | (0 if msg.verified else STATE_FLAG_UNVERIFIED))
    if flags:
        body["fl"] = flags
    pc = msg.pos_corr
    if pc[0] != 0.0 or pc[1] != 0.0 or pc[2] != 0.0:
        body["pc"] = f3(pc)
    if msg.schema >= 2:
        if msg.reason:
            body["rsn"] = int(msg.reason)
        if math.isfinite(msg.protection_m):
            body["pl"] = float(msg.protection_m)
        if msg.t_sent_gps_s is not None:
            body["ts"] = float(msg.t_sent_gps_s)
    return msgpack.packb(body, use_bin_type=True)


def encode_state(msg: StateMessage, sign: Signer | None = None) -> bytes:
    """StateMessage -> envelope bytes; ``sign(body) -> (sig, key_id)`` adds a signature."""
    return seal(encode_state_body(msg), sign)


_NUMBER_TYPES = frozenset((float, int))
_VALID_GEOMETRY_CACHE: dict = {}
_GEOMETRY_CACHE_MAX = 4096
"""Geometry maps already validated (kind, flat points, radius): a vehicle sends the same outline in
every message, so its per-value checks run once. Bounded; cleared when full."""


def _geometry(m: dict) -> Geometry:
    g = get_field(m, "g")
    if type(g) is not dict:
        raise WireError("geometry is not a map", "g")
    p, r = g.get("p", []), g.get("r", 0.0)
    key = None
    # equal keys may differ in type (True == 1.0): a hit also needs plain numbers only
    if type(p) is list and (type(r) is float or type(r) is int) and _NUMBER_TYPES.issuperset(map(type, p)):
        try:
            key = (g.get("k"), tuple(p), r, "r" in g)
            cached = _VALID_GEOMETRY_CACHE.get(key)
        except TypeError:   # unhashable kind
            key = cached = None
        if cached is not None:
            return Geometry(kind=cached[0], points_body_m=np.array(p, dtype=float).reshape(cached[1], 3),
                            radius_m=cached[2])
    geometry = _validate_geometry(g)
    if key is not None:
        if len(_VALID_GEOMETRY_CACHE) >= _GEOMETRY_CACHE_MAX:
            _VALID_GEOMETRY_CACHE.clear()
        _VALID_GEOMETRY_CACHE[key] = (geometry.kind, len(geometry.points_body_m), geometry.radius_m)
    return geometry


def _validate_geometry(g: dict) -> Geometry:
    kind = g.get("k")
    if kind not in GEOMETRY_KINDS:
        raise WireError(f"geometry kind must be one of {GEOMETRY_KINDS}", "g.k")
    try:
        radius = num(g, "r", 0.0, MAX_GEOMETRY_M) if "r" in g else 0.0
    except WireError as err:
        raise WireError(err.reason, "g.r") from None
    p = g.get("p", [])
    if type(p) is not list or len(p) % 3:
        raise WireError("geometry points must be a flat array of 3N numbers", "g.p")
    n = len(p) // 3
    if n > MAX_GEOMETRY_POINTS:
        raise WireError(f"more than {MAX_GEOMETRY_POINTS} geometry points", "g.p")
    for x in p:
        if (type(x) is not float and type(x) is not int) or not math.isfinite(x) or abs(x) > MAX_GEOMETRY_M:
            raise WireError("geometry point not a finite number within 100 m", "g.p")
    if kind == "points" and n < 1:
        raise WireError("contact points geometry needs at least one point", "g.p")
    if kind == "polygon" and n < 3:
        raise WireError("polygon geometry needs at least three vertices", "g.p")
    return Geometry(kind=kind, points_body_m=np.array(p, dtype=float).reshape(n, 3), radius_m=radius)


def decode_state_body(body: bytes) -> StateMessage:
    """Validated StateMessage from its msgpack body (no envelope)."""
    m = unpack_body(body, "state", SCHEMA_VERSIONS)
    fix_code = uint(m, "fix", 255)
    fix = FIX_BY_CODE.get(fix_code)
    if fix is None:
        raise WireError(f"unknown fix status {fix_code}", "fix")
    kind = get_field(m, "kind")
    if kind not in KINDS:
        raise WireError(f"kind must be one of {KINDS}", "kind")
    v = vec3_list(m, "v", MAX_SPEED_MPS)
    if v[0] * v[0] + v[1] * v[1] + v[2] * v[2] > MAX_SPEED_MPS * MAX_SPEED_MPS:
        raise WireError(f"speed above {MAX_SPEED_MPS:g} m/s", "v")
    rpy = vec3_list(m, "rpy", 2.0 * math.pi)
    if abs(rpy[0]) > math.pi or abs(rpy[1]) > 0.5 * math.pi:
        raise WireError("roll must be within +-pi and pitch within +-pi/2", "rpy")
    iq = m.get("iq")
    if iq is not None and type(iq) is not dict:
        raise WireError("imu_quality is not a map", "iq")
    # validated in the same order as the fields below; the seven 3-vectors become rows of one
    # array (one numpy allocation per message instead of seven)
    fleet, vehicle_id, seq = ident(m, "fleet"), ident(m, "id"), uint(m, "seq")
    t_gps_s = num(m, "t", 0.0, MAX_T_GPS_S)
    lat = num(m, "lat", -0.5 * math.pi, 0.5 * math.pi)
    lon = num(m, "lon", -math.pi, math.pi)
    h = num(m, "h", MIN_HEIGHT_M, MAX_HEIGHT_M)
    vecs = np.array((v, vec3_list(m, "a", MAX_ACC_MPS2), vec3_list(m, "w", MAX_RATE_RPS), rpy,
                     vec3_list(m, "sp", MAX_SD, True), vec3_list(m, "sv", MAX_SD, True),
                     vec3_list(m, "sa", MAX_SD, True)), dtype=float)
    geometry = _geometry(m)
    t_sent = opt_num(m, "tw", 0.0, MAX_T_GPS_S)
    flags = uint(m, "fl", 255) if "fl" in m else 0
    pos_corr = np.array(vec3_list(m, "pc", 1.0), dtype=float) if "pc" in m else np.zeros(3)
    reason, protection, t_sent_gps = 0, math.nan, None
    if m["ver"] >= 2:
        reason = uint(m, "rsn", MAX_REASON_CODE) if "rsn" in m else 0
        protection = num(m, "pl", 0.0, MAX_SD) if "pl" in m else math.nan
        t_sent_gps = opt_num(m, "ts", 0.0, MAX_T_GPS_S)
    msg = StateMessage.__new__(StateMessage)
    msg.__dict__.update(
        fleet=fleet, vehicle_id=vehicle_id, seq=seq, t_gps_s=t_gps_s, fix=fix, lat_rad=lat, lon_rad=lon,
        height_m=h, v_ned_mps=vecs[0], acc_body_mps2=vecs[1], rate_body_rps=vecs[2], rpy_rad=vecs[3],
        pos_sd_m=vecs[4], vel_sd_mps=vecs[5], att_sd_rad=vecs[6], geometry=geometry, kind=kind,
        schema=m["ver"], t_sent_wall_s=t_sent, imu_quality=iq, sig=None, key_id=None, signed_payload=None,
        attitude_ok=not flags & STATE_FLAG_ATTITUDE_UNDETERMINED, time_ok=not flags & STATE_FLAG_TIME_UNSYNCED,
        pos_corr=pos_corr, consistent=not flags & STATE_FLAG_INCONSISTENT, verified=not flags & STATE_FLAG_UNVERIFIED,
        reason=reason, protection_m=protection, t_sent_gps_s=t_sent_gps)
    return msg


def decode_state(data: bytes) -> StateMessage:
    """Envelope bytes -> validated StateMessage (with sig, key_id, signed_payload); WireError if bad."""
    env = unpack_envelope(data)
    msg = decode_state_body(env.body)
    msg.sig, msg.key_id, msg.signed_payload = env.sig, env.key_id, env.body
    return msg
