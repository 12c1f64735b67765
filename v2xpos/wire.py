"""V2V wire format: versioned, validated msgpack messages (schema in docs/protocol.md).

Public API (stable)
-------------------
* ``SCHEMA_VERSION``, ``ENVELOPE_VERSION``, ``MAX_MESSAGE_BYTES``, ``MAX_GEOMETRY_POINTS``
* key expressions, every one the project uses: ``state_key(fleet, vehicle_id)``,
  ``STATE_KEY_ALL(fleet)`` (``v2xpos/<fleet>/vehicle/*/state``), ``relative_key(fleet, master_id)``,
  ``imu_key(fleet, vehicle_id)``, ``status_key`` and ``grades_key``
  (fleet, master_id), ``clock_key(fleet)`` and ``ready_key(fleet, vehicle_id)`` (session clock),
  ``corrections_key(fleet)``
* the IMU stream of the grading: ``encode_imu_payload``, ``decode_imu_payload`` -> ``ImuPayload``
* ``WireError(reason, field)`` -- every malformed input raises this, never anything else.
* ``Geometry`` -- target outline in its own body frame (points, polygon or circle).
* ``StateMessage`` -- one vehicle/pedestrian state; ``encode_state(msg, sign=None) -> bytes``,
  ``decode_state(data) -> StateMessage``.
* ``TargetStatus`` (VALID, FIX_INVALID, TIMEOUT, NO_DATA, FUTURE and the kinematic-but-not-valid
  statuses of ``KINEMATIC_STATUSES``), ``FixSide`` (which side's fix failed the gate) and
  ``RelativeResult`` -- what the master republishes; ``encode_relative(res, sign=None) -> bytes``
  (always ``RELATIVE_SCHEMA_VERSION``), ``decode_relative(data) -> RelativeResult`` (versions in
  ``RELATIVE_SCHEMA_VERSIONS``: 1 = before the vehicles' fix states and the yaw sigma, decoded with
  ``master_fix``/``target_fix`` NONE and ``rel_yaw_sd_rad`` NaN).
* Envelope helpers for signing: ``pack_envelope(body, sig, key_id)``, ``unpack_envelope(data)
  -> Envelope``.

Envelope and signing
--------------------
Every datagram is a msgpack array ``[ENVELOPE_VERSION, body, sig, key_id]``: ``body`` is the
msgpack-encoded message map as a *bin* value -- exactly the byte string that is signed
(Ed25519 over ``body``); ``sig`` is bin or nil, ``key_id`` str or nil. ``decode_state`` keeps
``body`` in ``StateMessage.signed_payload`` so a verifier checks ``sig`` over it without
re-encoding. ``sign`` arguments are callables ``body -> (sig_bytes, key_id)``.

Frames and units: positions geodetic (lat/lon rad, ellipsoidal height m); velocity NED [m/s];
acceleration (kinematic, gravity removed) and angular rate in the vehicle body frame
(x forward, y right, z down) [m/s^2, rad/s]; attitude Z-Y-X Euler (roll, pitch, yaw) of C_nb
[rad]; standard deviations are 1-sigma per axis.
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from enum import IntEnum, IntFlag
from typing import Any, Callable

import msgpack
import numpy as np

from v2xpos.types import FixStatus, NavState

SCHEMA_VERSION = 1
"""Version of the StateMessage body (``ver``)."""
RELATIVE_SCHEMA_VERSION = 2
"""Version of the RelativeResult body the encoder writes: 2 adds ``mfix``/``tfix`` (both vehicles'
fix status), ``kin.ys`` (relative yaw sigma) and kinematics on every status of KINEMATIC_STATUSES."""
RELATIVE_SCHEMA_VERSIONS = (1, 2)
"""RelativeResult body versions the decoder accepts (docs/protocol.md §3)."""
ENVELOPE_VERSION = 1
MAX_MESSAGE_BYTES = 8192
MAX_GEOMETRY_POINTS = 64
MAX_ID_CHARS = 32

MAX_SPEED_MPS = 150.0
MAX_ACC_MPS2 = 100.0
MAX_RATE_RPS = 50.0
MAX_HEIGHT_M = 20000.0
MIN_HEIGHT_M = -1000.0
MAX_SD = 1.0e6
MAX_GEOMETRY_M = 100.0
MAX_T_GPS_S = 1.0e11
MAX_UINT64 = 2 ** 64 - 1

STATE_FLAG_ATTITUDE_UNDETERMINED = 1
"""State flag bit: the sender's attitude (heading) is not determined yet (e.g. pending at a stop)."""
STATE_FLAG_TIME_UNSYNCED = 2
"""State flag bit: the sender's clock is off GNSS time beyond its bound."""
STATE_FLAG_INCONSISTENT = 4
"""State flag bit: the sender's filter fails its own consistency test (windowed NIS of its GNSS
updates, ``v2xpos.ins.consistency``): its covariance does not describe its errors."""
STATE_FLAG_UNVERIFIED = 8
"""State flag bit: the sender's consistency test has not yet passed through enough turning to reveal
an undeclared lever arm, mounting or gyro scale (``v2xpos.ins.consistency``)."""
KINDS = ("vehicle", "pedestrian")
GEOMETRY_KINDS = ("points", "polygon", "circle")
_ID_RE = re.compile(r"[A-Za-z0-9_.\-]+")

Signer = Callable[[bytes], tuple[bytes, str]]


def state_key(fleet: str, vehicle_id: str) -> str:
    """Zenoh key expression a slave publishes its StateMessage on."""
    return f"v2xpos/{fleet}/vehicle/{vehicle_id}/state"


def STATE_KEY_ALL(fleet: str) -> str:  # noqa: N802 (reads as a constant pattern)
    """Key expression matching every vehicle's state in a fleet."""
    return f"v2xpos/{fleet}/vehicle/*/state"


def relative_key(fleet: str, master_id: str) -> str:
    """Zenoh key expression a master republishes its RelativeResult messages on."""
    return f"v2xpos/{fleet}/master/{master_id}/relative"


def imu_key(fleet: str, vehicle_id: str) -> str:
    """Zenoh key expression for IMU samples used by IMU grading."""
    return f"v2xpos/{fleet}/vehicle/{vehicle_id}/imu"


def status_key(fleet: str, master_id: str) -> str:
    """Key on which a master publishes its periodic status (JSON, for monitors and the demo table)."""
    return f"v2xpos/{fleet}/master/{master_id}/status"


def grades_key(fleet: str, master_id: str) -> str:
    """Key on which a master publishes IMU grades (JSON)."""
    return f"v2xpos/{fleet}/master/{master_id}/grades"


def clock_key(fleet: str) -> str:
    """Key of the session clock published by a recording master."""
    return f"v2xpos/{fleet}/session/clock"


def ready_key(fleet: str, vehicle_id: str) -> str:
    """Key on which a recording slave says it is ready for the session clock."""
    return f"v2xpos/{fleet}/session/ready/{vehicle_id}"


def corrections_key(fleet: str) -> str:
    """Zenoh key of a fleet's GNSS correction stream."""
    return f"v2xpos/{fleet}/corrections"


class WireError(ValueError):
    """A message that cannot be accepted: ``reason`` (short, stable text) and ``field`` (or None)."""

    def __init__(self, reason: str, field: str | None = None):
        self.reason = reason
        self.field = field
        super().__init__(f"{reason} (field {field!r})" if field else reason)


class TargetStatus(IntEnum):
    """Per-target status sent with every result (CAN/UDP/zenoh code = value)."""
    VALID = 0
    FIX_INVALID = 1   # master or slave not RTK fixed/float; FixSide says which
    TIMEOUT = 2       # latency above the timeout: no relative output from that message
    NO_DATA = 3       # no message from the target yet / target silent
    FUTURE = 4        # slave time of validity ahead of the master beyond tolerance
    # statuses below carry the computed kinematics (has_kinematics) but say why they are not VALID
    ATTITUDE_UNCERTAIN = 5   # a vehicle's heading/attitude is not determined (e.g. pending at a standstill start)
    SIGMA_EXCEEDED = 6       # predicted relative sigma beyond the configured limit
    CLOCK_UNSYNCED = 7       # a service's clock is off GNSS time beyond the configured bound
    INCONSISTENT = 8         # a filter's own consistency checks (NIS, whiteness) show an undeclared effect


KINEMATIC_STATUSES = frozenset({TargetStatus.VALID, TargetStatus.ATTITUDE_UNCERTAIN, TargetStatus.SIGMA_EXCEEDED,
                                TargetStatus.CLOCK_UNSYNCED, TargetStatus.INCONSISTENT})
"""Statuses whose results carry computed kinematics (only VALID may be used as a reference)."""


class FixSide(IntFlag):
    """Which side failed the fix gate (MASTER | SLAVE when both)."""
    NONE = 0
    MASTER = 1
    SLAVE = 2


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
                   "attitude_ok", "time_ok", "consistent", "verified")
        arrays = ("v_ned_mps", "acc_body_mps2", "rate_body_rps", "rpy_rad", "pos_sd_m",
                  "vel_sd_mps", "att_sd_rad", "pos_corr")
        return (all(getattr(self, k) == getattr(other, k) for k in scalars)
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
                   consistent=bool(getattr(nav, "consistent", True)), verified=bool(getattr(nav, "verified", True)))

    def to_nav_state(self) -> NavState:
        """The kinematic content as a NavState."""
        return NavState(t_s=self.t_gps_s, lla=self.lla, v_ned_mps=self.v_ned_mps.copy(),
                        acc_body_mps2=self.acc_body_mps2.copy(), rate_body_rps=self.rate_body_rps.copy(),
                        rpy_rad=self.rpy_rad.copy(), pos_sd_m=self.pos_sd_m.copy(),
                        vel_sd_mps=self.vel_sd_mps.copy(), att_sd_rad=self.att_sd_rad.copy(),
                        fix=FixStatus(self.fix), attitude_ok=self.attitude_ok, pos_corr=self.pos_corr.copy(),
                        consistent=self.consistent, verified=self.verified)


_NAN3 = (math.nan, math.nan, math.nan)


@dataclass
class RelativeResult:
    """Relative kinematics of one target in the master body frame (x fwd, y right, z down).

    ``rel_pos_body_m``: target reference point minus master reference point;
    ``rel_vel_body_mps`` / ``rel_acc_body_mps2``: first/second time derivative of it as seen in
    the rotating master body frame; ``rel_rpy_rad``: (d_roll, d_pitch, d_yaw) of the target body
    relative to the master body (``operator_T(d_yaw, d_pitch, d_roll)`` = C_master_target);
    ``range_m``/``bearing_rad``/``elevation_rad``: of rel_pos_body_m; ``longitudinal_m``,
    ``lateral_m``, ``gap_m``: from the master measurement point to the target's nearest
    contact point / polygon edge / circle edge (horizontal); ``closing_speed_mps`` > 0 when the
    gap shrinks; ``ttc_s`` = gap / closing speed when closing, else None. Kinematic fields are NaN
    unless ``status`` is in KINEMATIC_STATUSES (only VALID may be used as a reference).
    ``latency_s`` = master time - target time of validity. ``master_fix`` / ``target_fix``: fix
    status of the master state and of the target message the result was computed from (on every
    status; NONE when that side has no state yet). ``rel_yaw_sd_rad``: 1-sigma of the relative yaw
    (``rel_rpy_rad[2]``), NaN without kinematics.
    """
    target_id: str = ""
    target_kind: str = "vehicle"
    status: TargetStatus = TargetStatus.VALID
    fix_side: FixSide = FixSide.NONE
    degraded: bool = False
    fleet: str = ""
    master_id: str = ""
    seq: int = 0
    source_seq: int = 0
    t_gps_s: float = 0.0
    latency_s: float = math.nan
    rel_pos_body_m: np.ndarray = field(default_factory=lambda: np.array(_NAN3))
    rel_pos_sd_m: np.ndarray = field(default_factory=lambda: np.array(_NAN3))
    rel_vel_body_mps: np.ndarray = field(default_factory=lambda: np.array(_NAN3))
    rel_acc_body_mps2: np.ndarray = field(default_factory=lambda: np.array(_NAN3))
    rel_rpy_rad: np.ndarray = field(default_factory=lambda: np.array(_NAN3))
    range_m: float = math.nan
    range_sd_m: float = math.nan
    bearing_rad: float = math.nan
    elevation_rad: float = math.nan
    longitudinal_m: float = math.nan
    lateral_m: float = math.nan
    gap_m: float = math.nan
    closing_speed_mps: float = math.nan
    ttc_s: float | None = None
    t_sent_wall_s: float | None = None
    schema: int = RELATIVE_SCHEMA_VERSION
    master_fix: FixStatus = FixStatus.NONE
    target_fix: FixStatus = FixStatus.NONE
    rel_yaw_sd_rad: float = math.nan

    @property
    def bearing_deg(self) -> float:
        """Bearing (azimuth in the master body frame, clockwise from x forward) [deg]."""
        return math.degrees(self.bearing_rad)

    @property
    def has_kinematics(self) -> bool:
        """True when the kinematic fields are computed (VALID, or a status in KINEMATIC_STATUSES that
        says why they are not to be trusted)."""
        return self.status in KINEMATIC_STATUSES

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, RelativeResult):
            return NotImplemented
        for k, v in self.__dict__.items():
            w = other.__dict__[k]
            if isinstance(v, np.ndarray):
                if not np.array_equal(v, w, equal_nan=True):
                    return False
            elif isinstance(v, float) and isinstance(w, float):
                if not (v == w or (math.isnan(v) and math.isnan(w))):
                    return False
            elif v != w:
                return False
        return True


@dataclass
class Envelope:
    """Outer frame: ``body`` (the signed bytes), optional ``sig`` and ``key_id``."""
    body: bytes
    sig: bytes | None = None
    key_id: str | None = None


# ----------------------------------------------------------------------------- encoding

def _f3(a: np.ndarray) -> list:
    if type(a) is np.ndarray and a.dtype == np.float64 and a.shape == (3,):
        return a.tolist()
    return [float(a[0]), float(a[1]), float(a[2])]


def pack_envelope(body: bytes, sig: bytes | None = None, key_id: str | None = None) -> bytes:
    """``[ENVELOPE_VERSION, body, sig, key_id]`` as msgpack."""
    return msgpack.packb([ENVELOPE_VERSION, body, sig, key_id], use_bin_type=True)


def _seal(body: bytes, sign: Signer | None) -> bytes:
    if sign is None:
        return pack_envelope(body)
    sig, key_id = sign(body)
    return pack_envelope(body, sig, key_id)


def _geometry_map(g: Geometry) -> dict:
    pts = np.asarray(g.points_body_m, dtype=float).reshape(-1)
    return {"k": g.kind, "p": [float(x) for x in pts], "r": float(g.radius_m)}


def encode_state_body(msg: StateMessage) -> bytes:
    """The msgpack body of a StateMessage (the byte string that gets signed)."""
    body = {"T": "state", "ver": int(msg.schema), "fleet": msg.fleet, "id": msg.vehicle_id,
            "kind": msg.kind, "seq": int(msg.seq), "t": float(msg.t_gps_s), "fix": int(msg.fix),
            "lat": float(msg.lat_rad), "lon": float(msg.lon_rad), "h": float(msg.height_m),
            "v": _f3(msg.v_ned_mps), "a": _f3(msg.acc_body_mps2), "w": _f3(msg.rate_body_rps),
            "rpy": _f3(msg.rpy_rad), "sp": _f3(msg.pos_sd_m), "sv": _f3(msg.vel_sd_mps),
            "sa": _f3(msg.att_sd_rad), "g": _geometry_map(msg.geometry)}
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
        body["pc"] = _f3(pc)
    return msgpack.packb(body, use_bin_type=True)


def encode_state(msg: StateMessage, sign: Signer | None = None) -> bytes:
    """StateMessage -> envelope bytes; ``sign(body) -> (sig, key_id)`` adds a signature."""
    return _seal(encode_state_body(msg), sign)


def encode_relative_body(res: RelativeResult) -> bytes:
    """The msgpack body of a RelativeResult (schema ``RELATIVE_SCHEMA_VERSION``)."""
    body = {"T": "relative", "ver": RELATIVE_SCHEMA_VERSION, "fleet": res.fleet, "master": res.master_id,
            "target": res.target_id, "kind": res.target_kind, "seq": int(res.seq),
            "src_seq": int(res.source_seq), "t": float(res.t_gps_s), "status": int(res.status),
            "fix_side": int(res.fix_side), "degraded": bool(res.degraded),
            "mfix": int(res.master_fix), "tfix": int(res.target_fix)}
    if math.isfinite(res.latency_s):
        body["lat_s"] = float(res.latency_s)
    if res.t_sent_wall_s is not None:
        body["tw"] = float(res.t_sent_wall_s)
    if res.status in KINEMATIC_STATUSES:
        body["kin"] = {
            "p": _f3(res.rel_pos_body_m), "ps": _f3(res.rel_pos_sd_m), "v": _f3(res.rel_vel_body_mps),
            "a": _f3(res.rel_acc_body_mps2), "att": _f3(res.rel_rpy_rad), "rng": float(res.range_m),
            "rng_sd": float(res.range_sd_m), "brg": float(res.bearing_rad),
            "elv": float(res.elevation_rad), "lon_d": float(res.longitudinal_m),
            "lat_d": float(res.lateral_m), "gap": float(res.gap_m),
            "cls": float(res.closing_speed_mps),
            "ttc": None if res.ttc_s is None else float(res.ttc_s),
            "ys": float(res.rel_yaw_sd_rad) if math.isfinite(res.rel_yaw_sd_rad) else None}
    return msgpack.packb(body, use_bin_type=True)


def encode_relative(res: RelativeResult, sign: Signer | None = None) -> bytes:
    """RelativeResult -> envelope bytes."""
    return _seal(encode_relative_body(res), sign)


# ----------------------------------------------------------------------------- decoding

def unpack_envelope(data: bytes) -> Envelope:
    """Envelope bytes -> Envelope; WireError if malformed or oversize."""
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise WireError("not bytes", None)
    if len(data) > MAX_MESSAGE_BYTES:
        raise WireError(f"oversize ({len(data)} > {MAX_MESSAGE_BYTES} bytes)", None)
    try:
        env = msgpack.unpackb(data, raw=False, strict_map_key=True, max_bin_len=MAX_MESSAGE_BYTES,
                              max_str_len=MAX_MESSAGE_BYTES, max_array_len=1024, max_map_len=256)
    except Exception as exc:  # msgpack raises many types; all mean "not a valid frame"
        raise WireError(f"not msgpack ({type(exc).__name__})", "envelope") from None
    if type(env) is not list or len(env) != 4:
        raise WireError("envelope is not a 4-element array", "envelope")
    ver, body, sig, key_id = env
    if type(ver) is not int:
        raise WireError("envelope version not an integer", "envelope.version")
    if ver != ENVELOPE_VERSION:
        raise WireError(f"unknown envelope version {ver}", "envelope.version")
    if type(body) is not bytes:
        raise WireError("body is not bin", "envelope.body")
    if sig is not None and type(sig) is not bytes:
        raise WireError("signature is not bin", "envelope.sig")
    if key_id is not None and (type(key_id) is not str or not key_id or len(key_id) > MAX_ID_CHARS):
        raise WireError("key id is not a short string", "envelope.key_id")
    return Envelope(body, sig, key_id)


def _unpack_body(body: bytes, expect_type: str, versions: tuple = (SCHEMA_VERSION,)) -> dict:
    try:
        m = msgpack.unpackb(body, raw=False, strict_map_key=True, max_array_len=1024, max_map_len=256)
    except Exception as exc:
        raise WireError(f"body not msgpack ({type(exc).__name__})", "body") from None
    if type(m) is not dict:
        raise WireError("body is not a map", "body")
    t = m.get("T")
    if t != expect_type:
        raise WireError(f"message type {t!r} is not {expect_type!r}", "T")
    ver = m.get("ver")
    if type(ver) is not int:
        raise WireError("missing or non-integer schema version", "ver")
    if ver not in versions:
        raise WireError(f"unknown schema version {ver}", "ver")
    return m


def _get(m: dict, key: str) -> Any:
    try:
        return m[key]
    except KeyError:
        raise WireError("missing field", key) from None


def _num(m: dict, key: str, lo: float, hi: float) -> float:
    x = _get(m, key)
    tx = type(x)
    if tx is not float and tx is not int:
        raise WireError(f"not a number ({tx.__name__})", key)
    x = float(x)
    if not math.isfinite(x):
        raise WireError("non-finite number", key)
    if x < lo or x > hi:
        raise WireError(f"out of range [{lo:g}, {hi:g}]: {x:g}", key)
    return x


def _opt_num(m: dict, key: str, lo: float, hi: float) -> float | None:
    return None if m.get(key) is None else _num(m, key, lo, hi)


def _uint(m: dict, key: str, hi: int = MAX_UINT64) -> int:
    x = _get(m, key)
    if type(x) is not int:
        raise WireError(f"not an integer ({type(x).__name__})", key)
    if x < 0 or x > hi:
        raise WireError(f"out of range [0, {hi}]: {x}", key)
    return x


_VALID_IDENTS: set = set()
_IDENT_CACHE_MAX = 4096


def _ident(m: dict, key: str) -> str:
    s = _get(m, key)
    if type(s) is str and s in _VALID_IDENTS:
        return s
    s = _check_ident(s, key)
    if len(_VALID_IDENTS) >= _IDENT_CACHE_MAX:
        _VALID_IDENTS.clear()
    _VALID_IDENTS.add(s)
    return s


def _check_ident(s: Any, key: str) -> str:
    if type(s) is not str:
        raise WireError(f"not a string ({type(s).__name__})", key)
    if not s or len(s) > MAX_ID_CHARS or not _ID_RE.fullmatch(s):
        raise WireError(f"identifier must be 1-{MAX_ID_CHARS} chars of [A-Za-z0-9_.-]", key)
    return s


def _vec3(m: dict, key: str, bound: float, nonneg: bool = False) -> np.ndarray:
    return np.array(_vec3_list(m, key, bound, nonneg), dtype=float)


def _vec3_list(m: dict, key: str, bound: float, nonneg: bool = False) -> list:
    """The validated 3-number list of ``key``."""
    try:
        v = m[key]
    except KeyError:
        raise WireError("missing field", key) from None
    if type(v) is not list or len(v) != 3:
        raise WireError("not an array of 3 numbers", key)
    a, b, c = v
    ta, tb, tc = type(a), type(b), type(c)
    if not ((ta is float or ta is int) and (tb is float or tb is int) and (tc is float or tc is int)):
        raise WireError("not a number", key)
    lo = 0.0 if nonneg else -bound
    # chained comparisons are False for NaN, so this also rejects non-finite values
    if lo <= a <= bound and lo <= b <= bound and lo <= c <= bound:
        return v
    if not (math.isfinite(a) and math.isfinite(b) and math.isfinite(c)):
        raise WireError("non-finite number", key)
    if nonneg and (a < 0 or b < 0 or c < 0):
        raise WireError("negative standard deviation", key)
    raise WireError(f"out of range (|x| <= {bound:g})", key)


_NUMBER_TYPES = frozenset((float, int))
_VALID_GEOMETRY_CACHE: dict = {}
_GEOMETRY_CACHE_MAX = 4096
"""Geometry maps already validated (kind, flat points, radius): a vehicle sends the same outline in
every message, so its per-value checks run once. Bounded; cleared when full."""


def _geometry(m: dict) -> Geometry:
    g = _get(m, "g")
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
        radius = _num(g, "r", 0.0, MAX_GEOMETRY_M) if "r" in g else 0.0
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


_FIX_BY_CODE = {int(f): f for f in FixStatus}


def decode_state_body(body: bytes) -> StateMessage:
    """Validated StateMessage from its msgpack body (no envelope)."""
    m = _unpack_body(body, "state")
    fix_code = _uint(m, "fix", 255)
    fix = _FIX_BY_CODE.get(fix_code)
    if fix is None:
        raise WireError(f"unknown fix status {fix_code}", "fix")
    kind = _get(m, "kind")
    if kind not in KINDS:
        raise WireError(f"kind must be one of {KINDS}", "kind")
    v = _vec3_list(m, "v", MAX_SPEED_MPS)
    if v[0] * v[0] + v[1] * v[1] + v[2] * v[2] > MAX_SPEED_MPS * MAX_SPEED_MPS:
        raise WireError(f"speed above {MAX_SPEED_MPS:g} m/s", "v")
    rpy = _vec3_list(m, "rpy", 2.0 * math.pi)
    if abs(rpy[0]) > math.pi or abs(rpy[1]) > 0.5 * math.pi:
        raise WireError("roll must be within +-pi and pitch within +-pi/2", "rpy")
    iq = m.get("iq")
    if iq is not None and type(iq) is not dict:
        raise WireError("imu_quality is not a map", "iq")
    # validated in the same order as the fields below; the seven 3-vectors become rows of one
    # array (one numpy allocation per message instead of seven)
    fleet, vehicle_id, seq = _ident(m, "fleet"), _ident(m, "id"), _uint(m, "seq")
    t_gps_s = _num(m, "t", 0.0, MAX_T_GPS_S)
    lat = _num(m, "lat", -0.5 * math.pi, 0.5 * math.pi)
    lon = _num(m, "lon", -math.pi, math.pi)
    h = _num(m, "h", MIN_HEIGHT_M, MAX_HEIGHT_M)
    vecs = np.array((v, _vec3_list(m, "a", MAX_ACC_MPS2), _vec3_list(m, "w", MAX_RATE_RPS), rpy,
                     _vec3_list(m, "sp", MAX_SD, True), _vec3_list(m, "sv", MAX_SD, True),
                     _vec3_list(m, "sa", MAX_SD, True)), dtype=float)
    geometry = _geometry(m)
    t_sent = _opt_num(m, "tw", 0.0, MAX_T_GPS_S)
    flags = _uint(m, "fl", 255) if "fl" in m else 0
    pos_corr = np.array(_vec3_list(m, "pc", 1.0), dtype=float) if "pc" in m else np.zeros(3)
    msg = StateMessage.__new__(StateMessage)
    msg.__dict__.update(
        fleet=fleet, vehicle_id=vehicle_id, seq=seq, t_gps_s=t_gps_s, fix=fix, lat_rad=lat, lon_rad=lon,
        height_m=h, v_ned_mps=vecs[0], acc_body_mps2=vecs[1], rate_body_rps=vecs[2], rpy_rad=vecs[3],
        pos_sd_m=vecs[4], vel_sd_mps=vecs[5], att_sd_rad=vecs[6], geometry=geometry, kind=kind,
        schema=m["ver"], t_sent_wall_s=t_sent, imu_quality=iq, sig=None, key_id=None, signed_payload=None,
        attitude_ok=not flags & STATE_FLAG_ATTITUDE_UNDETERMINED, time_ok=not flags & STATE_FLAG_TIME_UNSYNCED,
        pos_corr=pos_corr, consistent=not flags & STATE_FLAG_INCONSISTENT, verified=not flags & STATE_FLAG_UNVERIFIED)
    return msg


def decode_state(data: bytes) -> StateMessage:
    """Envelope bytes -> validated StateMessage (with sig, key_id, signed_payload); WireError if bad."""
    env = unpack_envelope(data)
    msg = decode_state_body(env.body)
    msg.sig, msg.key_id, msg.signed_payload = env.sig, env.key_id, env.body
    return msg


def _fix_field(m: dict, key: str) -> FixStatus:
    code = _uint(m, key, 255)
    fix = _FIX_BY_CODE.get(code)
    if fix is None:
        raise WireError(f"unknown fix status {code}", key)
    return fix


def decode_relative_body(body: bytes) -> RelativeResult:
    """Validated RelativeResult from its msgpack body (schema 1 or 2, see RELATIVE_SCHEMA_VERSIONS)."""
    m = _unpack_body(body, "relative", RELATIVE_SCHEMA_VERSIONS)
    ver = m["ver"]
    try:
        status = TargetStatus(_uint(m, "status", 255))
    except ValueError:
        raise WireError("unknown target status", "status") from None
    if ver == 1 and status > TargetStatus.FUTURE:
        raise WireError(f"status {int(status)} does not exist in schema 1", "status")
    side = _uint(m, "fix_side", 3)
    degraded = m.get("degraded", False)
    if type(degraded) is not bool:
        raise WireError("not a boolean", "degraded")
    kind = _get(m, "kind")
    if kind not in KINDS:
        raise WireError(f"kind must be one of {KINDS}", "kind")
    res = RelativeResult(
        target_id=_ident(m, "target"), target_kind=kind, status=status, fix_side=FixSide(side),
        degraded=degraded, fleet=_ident(m, "fleet"), master_id=_ident(m, "master"),
        seq=_uint(m, "seq"), source_seq=_uint(m, "src_seq"), t_gps_s=_num(m, "t", 0.0, MAX_T_GPS_S),
        latency_s=math.nan if m.get("lat_s") is None else _num(m, "lat_s", -1e6, 1e6),
        t_sent_wall_s=_opt_num(m, "tw", 0.0, MAX_T_GPS_S), schema=ver)
    if ver >= 2:
        res.master_fix = _fix_field(m, "mfix")
        res.target_fix = _fix_field(m, "tfix")
    kin = m.get("kin")
    if status in KINEMATIC_STATUSES:
        if type(kin) is not dict:
            raise WireError(f"{status.name} result without kinematics map", "kin")
        try:
            _decode_kinematics(kin, res)
            if ver >= 2 and kin.get("ys") is not None:
                res.rel_yaw_sd_rad = _num(kin, "ys", 0.0, MAX_SD)
        except WireError as err:
            raise WireError(err.reason, f"kin.{err.field}") from None
    elif kin is not None:
        raise WireError(f"kinematics present on a {status.name} result", "kin")
    return res


def _decode_kinematics(kin: dict, res: RelativeResult) -> None:
    """Fill the kinematic fields of ``res`` from the ``kin`` map (field names relative to it)."""
    big = 1.0e7
    res.rel_pos_body_m = _vec3(kin, "p", big)
    res.rel_pos_sd_m = _vec3(kin, "ps", MAX_SD, True)
    res.rel_vel_body_mps = _vec3(kin, "v", 10 * MAX_SPEED_MPS)
    res.rel_acc_body_mps2 = _vec3(kin, "a", 1e4)
    res.rel_rpy_rad = _vec3(kin, "att", 2 * math.pi)
    res.range_m = _num(kin, "rng", 0.0, big)
    res.range_sd_m = _num(kin, "rng_sd", 0.0, MAX_SD)
    res.bearing_rad = _num(kin, "brg", -math.pi, math.pi)
    res.elevation_rad = _num(kin, "elv", -0.5 * math.pi, 0.5 * math.pi)
    res.longitudinal_m = _num(kin, "lon_d", -big, big)
    res.lateral_m = _num(kin, "lat_d", -big, big)
    res.gap_m = _num(kin, "gap", 0.0, big)
    res.closing_speed_mps = _num(kin, "cls", -10 * MAX_SPEED_MPS, 10 * MAX_SPEED_MPS)
    res.ttc_s = _opt_num(kin, "ttc", 0.0, 1e9)


def decode_relative(data: bytes) -> RelativeResult:
    """Envelope bytes -> validated RelativeResult; WireError if malformed."""
    return decode_relative_body(unpack_envelope(data).body)


# ----------------------------------------------------------------------------- IMU stream (grading)

IMU_PAYLOAD_VERSION = 1
MAX_IMU_ROWS = 10_000
"""Most rows of one unit in one payload (a slave sends 0.25 s of samples per payload)."""
MAX_IMU_UNITS = 16


class ImuPayloadError(ValueError):
    """A received IMU-stream payload that is not valid (the message says why)."""


@dataclass
class ImuPayload:
    """One IMU-stream message: every unit's samples since the previous message of the vehicle.

    ``units``: unit id -> (t_gps_s (n,), acc_mps2 (n, 3), gyro_rps (n, 3)) in the unit's own axes;
    ``mounting_xyz_deg``: unit id -> X-Y-Z Euler angles unit -> vehicle body [deg] (docs/quality.md),
    for the units whose mounting is declared."""
    vehicle_id: str
    fleet: str | None
    units: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]]
    mounting_xyz_deg: dict[str, list[float]]
    rate_hz: float | None = None


def encode_imu_payload(fleet: str, vehicle_id: str, units: dict, mounting_xyz_deg: dict,
                       rate_hz: float = 100.0) -> bytes:
    """The msgpack map a slave publishes on ``imu_key`` (docs/protocol.md): ``{"T": "imu", "ver": 1,
    "fleet", "id", "rate_hz", "mounting_xyz_deg": {unit: [x, y, z]}, "units": {unit: rows}}`` with
    rows ``[t_gps_s, ax, ay, az, gx, gy, gz]`` (m/s^2, rad/s, unit axes). ``units``: unit id ->
    (t_gps_s, acc_mps2, gyro_rps) as in ``ImuPayload``."""
    rows = {uid: np.column_stack([t, acc, gyro]).tolist() for uid, (t, acc, gyro) in units.items()}
    return msgpack.packb({"T": "imu", "ver": IMU_PAYLOAD_VERSION, "fleet": fleet, "id": vehicle_id,
                          "rate_hz": rate_hz, "mounting_xyz_deg": mounting_xyz_deg, "units": rows},
                         use_bin_type=True)


def _imu_numbers(value: Any, error: str) -> np.ndarray:
    try:
        return np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise ImuPayloadError(error) from None


def decode_imu_payload(data: bytes) -> ImuPayload:
    """Validated IMU-stream payload; ``ImuPayloadError`` for anything else (never another exception):
    not msgpack, another type or version, no vehicle id, 0 or more than ``MAX_IMU_UNITS`` units, rows
    that are not finite 7-vectors, mountings that are not 3 finite angles within +-360 deg."""
    try:
        m = msgpack.unpackb(data, raw=False, strict_map_key=True, max_array_len=MAX_IMU_ROWS)
    except Exception as exc:  # msgpack raises many types, all mean "not a valid payload"
        raise ImuPayloadError(f"not msgpack ({type(exc).__name__})") from None
    if type(m) is not dict or m.get("T") != "imu" or m.get("ver") != IMU_PAYLOAD_VERSION:
        raise ImuPayloadError(f"not an imu message of version {IMU_PAYLOAD_VERSION}")
    vid, units = m.get("id"), m.get("units")
    if type(vid) is not str or not vid or type(units) is not dict or not 0 < len(units) <= MAX_IMU_UNITS:
        raise ImuPayloadError("missing id or units")
    samples = {}
    for uid, rows in units.items():
        a = _imu_numbers(rows, f"unit {uid!r}: rows are not numbers")
        if a.ndim != 2 or a.shape[1] != 7 or not np.isfinite(a).all():
            raise ImuPayloadError(f"unit {uid!r}: rows must be finite [t, ax, ay, az, gx, gy, gz]")
        samples[str(uid)] = (a[:, 0], a[:, 1:4], a[:, 4:7])
    mounting = m.get("mounting_xyz_deg") or {}
    if type(mounting) is not dict:
        raise ImuPayloadError("mounting_xyz_deg is not a map")
    angles = {}
    for uid, v in mounting.items():
        a = _imu_numbers(v, f"mounting_xyz_deg[{uid!r}]: not numbers")
        if a.shape != (3,) or not np.isfinite(a).all() or np.abs(a).max() > 360.0:
            raise ImuPayloadError(f"mounting_xyz_deg[{uid!r}]: need 3 finite angles in [-360, 360] deg")
        angles[str(uid)] = a.tolist()
    rate = m.get("rate_hz")
    return ImuPayload(vid, m.get("fleet"), samples, angles,
                      float(rate) if type(rate) in (int, float) and math.isfinite(rate) else None)
