"""The ``RelativeResult`` a master republishes per target, its status codes (``TargetStatus``,
``FixSide``), and its codec (``encode_relative`` / ``decode_relative``).

The encoder writes ``RELATIVE_SCHEMA_VERSION``; the decoder accepts ``RELATIVE_SCHEMA_VERSIONS``
(1 = before the vehicles' fix states and the yaw sigma, decoded with ``master_fix``/``target_fix``
NONE and ``rel_yaw_sd_rad`` NaN; 2 = before the reasons and the protection level, decoded with
reasons 0, ``reason_side`` NONE and ``protection_m`` NaN). Frames: the master's body frame (x forward, y right, z down).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from enum import IntEnum, IntFlag

import msgpack
import numpy as np

from v2xpos.types import FilterReason, FixStatus

from .envelope import Signer, seal, unpack_envelope
from .fields import (KINDS, MAX_SD, MAX_SPEED_MPS, MAX_T_GPS_S, WireError, f3, fix_field, get_field, ident, num,
                     opt_num, uint, unpack_body, vec3)

RELATIVE_SCHEMA_VERSION = 3
"""Version of the RelativeResult body the encoder writes: 2 adds ``mfix``/``tfix`` (both vehicles'
fix status), ``kin.ys`` (relative yaw sigma) and kinematics on every status of KINEMATIC_STATUSES;
3 adds the status UNVERIFIED, the vehicles' filter reasons (``mrsn``/``trsn``), which vehicle made
the status (``rside``) and the relative protection level (``pl``)."""
RELATIVE_SCHEMA_VERSIONS = (1, 2, 3)
"""RelativeResult body versions the decoder accepts (docs/protocol.md §3)."""

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
    INCONSISTENT = 8         # a filter's consistency test failed (NIS, innovation mean, solution separation)
    UNVERIFIED = 9           # a filter passes its tests but is not verified yet (protection level above its limit)


KINEMATIC_STATUSES = frozenset({TargetStatus.VALID, TargetStatus.ATTITUDE_UNCERTAIN, TargetStatus.SIGMA_EXCEEDED,
                                TargetStatus.CLOCK_UNSYNCED, TargetStatus.INCONSISTENT, TargetStatus.UNVERIFIED})
LAST_STATUS_OF_SCHEMA = {1: TargetStatus.FUTURE, 2: TargetStatus.INCONSISTENT, 3: TargetStatus.UNVERIFIED}
"""The highest status code each RelativeResult schema version defines."""
MAX_REASON_CODE = 63
"""Largest filter reason code on the wire (``v2xpos.types.FilterReason``; newer codes stay numbers)."""
"""Statuses whose results carry computed kinematics (only VALID may be used as a reference)."""


class FixSide(IntFlag):
    """Which side failed the fix gate (MASTER | SLAVE when both)."""
    NONE = 0
    MASTER = 1
    SLAVE = 2


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
    (``rel_rpy_rad[2]``), NaN without kinematics. ``reason_side``: which vehicle made a non-VALID
    status (MASTER, SLAVE = the target, or both; NONE when the status is not a vehicle's own, e.g.
    TIMEOUT or SIGMA_EXCEEDED; FIX_INVALID keeps using ``fix_side``); ``master_reason`` /
    ``target_reason``: the ``v2xpos.types.FilterReason`` codes of the two filters (0: OK or not
    given); ``protection_m``: horizontal protection level of the relative position, the sum of the
    two vehicles' (NaN when either has none).
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
    reason_side: FixSide = FixSide.NONE
    master_reason: int = 0
    target_reason: int = 0
    protection_m: float = math.nan

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


def reason_name(code: int) -> str:
    """Name of a filter reason code (``FilterReason``), or the number for a code this version lacks."""
    try:
        return FilterReason(int(code)).name
    except ValueError:
        return str(int(code))


_SIDE_WORD = {FixSide.MASTER: "master", FixSide.SLAVE: "target", FixSide.MASTER | FixSide.SLAVE: "both"}


def reason_text(res: RelativeResult) -> str:
    """Which vehicle made a result's status and why, as ``results.csv`` writes it: empty for VALID;
    ``target:SETUP_UNVERIFIED``, ``master:TEST_POSITION``, ``master:COASTING;target:OK``, ``both:CLOCK``
    (a clock alarm or unsynchronised clocks), ``master:FIX``/``target:FIX`` (the RTK gate); for a
    status that is no vehicle's own (TIMEOUT, NO_DATA, FUTURE, SIGMA_EXCEEDED) the status alone."""
    status = res.status
    if status == TargetStatus.VALID:
        return ""
    if status == TargetStatus.FIX_INVALID:
        side = res.fix_side
        return ";".join(f"{w}:FIX" for bit, w in ((FixSide.MASTER, "master"), (FixSide.SLAVE, "target"))
                        if side & bit) or status.name
    side = res.reason_side
    if not side:
        return status.name
    if status == TargetStatus.CLOCK_UNSYNCED or status in (TargetStatus.TIMEOUT, TargetStatus.NO_DATA):
        return f"{_SIDE_WORD[side]}:CLOCK"
    parts = []
    if side & FixSide.MASTER:
        parts.append(f"master:{reason_name(res.master_reason) if res.master_reason else status.name}")
    if side & FixSide.SLAVE:
        parts.append(f"target:{reason_name(res.target_reason) if res.target_reason else status.name}")
    return ";".join(parts)



def encode_relative_body(res: RelativeResult) -> bytes:
    """The msgpack body of a RelativeResult (schema ``RELATIVE_SCHEMA_VERSION``)."""
    body = {"T": "relative", "ver": RELATIVE_SCHEMA_VERSION, "fleet": res.fleet, "master": res.master_id,
            "target": res.target_id, "kind": res.target_kind, "seq": int(res.seq),
            "src_seq": int(res.source_seq), "t": float(res.t_gps_s), "status": int(res.status),
            "fix_side": int(res.fix_side), "degraded": bool(res.degraded),
            "mfix": int(res.master_fix), "tfix": int(res.target_fix)}
    if res.reason_side:
        body["rside"] = int(res.reason_side)
    if res.master_reason:
        body["mrsn"] = int(res.master_reason)
    if res.target_reason:
        body["trsn"] = int(res.target_reason)
    if math.isfinite(res.protection_m):
        body["pl"] = float(res.protection_m)
    if math.isfinite(res.latency_s):
        body["lat_s"] = float(res.latency_s)
    if res.t_sent_wall_s is not None:
        body["tw"] = float(res.t_sent_wall_s)
    if res.status in KINEMATIC_STATUSES:
        body["kin"] = {
            "p": f3(res.rel_pos_body_m), "ps": f3(res.rel_pos_sd_m), "v": f3(res.rel_vel_body_mps),
            "a": f3(res.rel_acc_body_mps2), "att": f3(res.rel_rpy_rad), "rng": float(res.range_m),
            "rng_sd": float(res.range_sd_m), "brg": float(res.bearing_rad),
            "elv": float(res.elevation_rad), "lon_d": float(res.longitudinal_m),
            "lat_d": float(res.lateral_m), "gap": float(res.gap_m),
            "cls": float(res.closing_speed_mps),
            "ttc": None if res.ttc_s is None else float(res.ttc_s),
            "ys": float(res.rel_yaw_sd_rad) if math.isfinite(res.rel_yaw_sd_rad) else None}
    return msgpack.packb(body, use_bin_type=True)


def encode_relative(res: RelativeResult, sign: Signer | None = None) -> bytes:
    """RelativeResult -> envelope bytes."""
    return seal(encode_relative_body(res), sign)


def decode_relative_body(body: bytes) -> RelativeResult:
    """Validated RelativeResult from its msgpack body (a schema of RELATIVE_SCHEMA_VERSIONS)."""
    m = unpack_body(body, "relative", RELATIVE_SCHEMA_VERSIONS)
    ver = m["ver"]
    try:
        status = TargetStatus(uint(m, "status", 255))
    except ValueError:
        raise WireError("unknown target status", "status") from None
    if status > LAST_STATUS_OF_SCHEMA[ver]:
        raise WireError(f"status {int(status)} does not exist in schema {ver}", "status")
    side = uint(m, "fix_side", 3)
    degraded = m.get("degraded", False)
    if type(degraded) is not bool:
        raise WireError("not a boolean", "degraded")
    kind = get_field(m, "kind")
    if kind not in KINDS:
        raise WireError(f"kind must be one of {KINDS}", "kind")
    res = RelativeResult(
        target_id=ident(m, "target"), target_kind=kind, status=status, fix_side=FixSide(side),
        degraded=degraded, fleet=ident(m, "fleet"), master_id=ident(m, "master"),
        seq=uint(m, "seq"), source_seq=uint(m, "src_seq"), t_gps_s=num(m, "t", 0.0, MAX_T_GPS_S),
        latency_s=math.nan if m.get("lat_s") is None else num(m, "lat_s", -1e6, 1e6),
        t_sent_wall_s=opt_num(m, "tw", 0.0, MAX_T_GPS_S), schema=ver)
    if ver >= 2:
        res.master_fix = fix_field(m, "mfix")
        res.target_fix = fix_field(m, "tfix")
    if ver >= 3:
        res.reason_side = FixSide(uint(m, "rside", 3)) if "rside" in m else FixSide.NONE
        res.master_reason = uint(m, "mrsn", MAX_REASON_CODE) if "mrsn" in m else 0
        res.target_reason = uint(m, "trsn", MAX_REASON_CODE) if "trsn" in m else 0
        res.protection_m = num(m, "pl", 0.0, MAX_SD) if "pl" in m else math.nan
    kin = m.get("kin")
    if status in KINEMATIC_STATUSES:
        if type(kin) is not dict:
            raise WireError(f"{status.name} result without kinematics map", "kin")
        try:
            _decode_kinematics(kin, res)
            if ver >= 2 and kin.get("ys") is not None:
                res.rel_yaw_sd_rad = num(kin, "ys", 0.0, MAX_SD)
        except WireError as err:
            raise WireError(err.reason, f"kin.{err.field}") from None
    elif kin is not None:
        raise WireError(f"kinematics present on a {status.name} result", "kin")
    return res


def _decode_kinematics(kin: dict, res: RelativeResult) -> None:
    """Fill the kinematic fields of ``res`` from the ``kin`` map (field names relative to it)."""
    big = 1.0e7
    res.rel_pos_body_m = vec3(kin, "p", big)
    res.rel_pos_sd_m = vec3(kin, "ps", MAX_SD, True)
    res.rel_vel_body_mps = vec3(kin, "v", 10 * MAX_SPEED_MPS)
    res.rel_acc_body_mps2 = vec3(kin, "a", 1e4)
    res.rel_rpy_rad = vec3(kin, "att", 2 * math.pi)
    res.range_m = num(kin, "rng", 0.0, big)
    res.range_sd_m = num(kin, "rng_sd", 0.0, MAX_SD)
    res.bearing_rad = num(kin, "brg", -math.pi, math.pi)
    res.elevation_rad = num(kin, "elv", -0.5 * math.pi, 0.5 * math.pi)
    res.longitudinal_m = num(kin, "lon_d", -big, big)
    res.lateral_m = num(kin, "lat_d", -big, big)
    res.gap_m = num(kin, "gap", 0.0, big)
    res.closing_speed_mps = num(kin, "cls", -10 * MAX_SPEED_MPS, 10 * MAX_SPEED_MPS)
    res.ttc_s = opt_num(kin, "ttc", 0.0, 1e9)


def decode_relative(data: bytes) -> RelativeResult:
    """Envelope bytes -> validated RelativeResult; WireError if malformed."""
    return decode_relative_body(unpack_envelope(data).body)
