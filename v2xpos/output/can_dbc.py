"""The CAN layout of the master's results: signal definitions, the shipped DBC (``v2xpos.dbc``, the
output of ``generate_dbc`` with the defaults; a test checks they agree), ``load_dbc`` and the E2E
checksum. The frames themselves are built and sent by ``v2xpos.output.can``.

Layout (classic CAN, 11-bit ids, 8-byte frames, little-endian signals; docs/protocol.md §5):
0x1F0 MASTER_STATUS, 0x1F1 MASTER_SIGMA; per target slot k (0..63): 0x200+k STATUS, 0x240+k POS,
0x280+k RANGE, 0x2C0+k VEL, 0x300+k GAP, 0x340+k ATT, 0x380+k ACC, 0x3C0+k SIGMA, 0x400+k ID;
0x480 LANE (one frame per lane line), 0x481 OBJECT (one frame per static object).

End-to-end protection (AUTOSAR E2E Profile 2 layout, AUTOSAR FO "E2E Protocol Specification"
(PRS E2E Protocol), E2E Profile 2): byte 0 = CRC-8-H2F (polynomial 0x2F, initial value 0xFF, final
XOR 0xFF, i.e. CRC-8/AUTOSAR) computed over data bytes 1..7 followed by the Data ID byte; the low
nibble of byte 1 = a 4-bit counter, +1 (mod 16) per update of that slot / of the master status / of
the scene, the same value in every frame of one update. Data ID: the 16 entries of the profile's
DataIDList are all ``frame id & 0xFF``. Every frame carries the counter; every frame but OBJECT
(whose 64 bits are all signals) carries the CRC. Values outside a signal's range are saturated;
NaN is sent as 0, or as the signal's "none"/"n/a" code where it has one.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cantools

from v2xpos.types import FilterReason
from v2xpos.wire import TargetStatus

DBC_PATH = Path(__file__).with_name("v2xpos.dbc")
DBC_VERSION = "v2xpos 3"
N_SLOTS = 64
NODE = "V2XPOS_MASTER"

ID_MASTER, ID_MASTER_SIGMA = 0x1F0, 0x1F1
ID_STATUS, ID_POS, ID_RANGE, ID_VEL, ID_GAP, ID_ATT, ID_ACC, ID_SIGMA, ID_ID = (
    0x200, 0x240, 0x280, 0x2C0, 0x300, 0x340, 0x380, 0x3C0, 0x400)
ID_LANE, ID_OBJECT = 0x480, 0x481
TTC_NONE_RAW = 0xFFFF
SD_NA_RAW = 0xFFF
ID_CHARS_PER_FRAME = 6
ID_PARTS = 6
"""A target id (at most 32 characters, wire.MAX_ID_CHARS) goes out 6 UTF-8 bytes per ID frame, one
part per update, cycling through its parts (a 5-character id: every ID frame is complete)."""
OBJECT_KIND = {"point": 0, "polygon": 1}

STATUS_CHOICES = {int(s): s.name.lower() for s in TargetStatus}
REASON_CHOICES = {int(r): r.name.lower() for r in FilterReason}
REASON_OTHER_RAW = 15
"""A filter reason code above 14 (a newer filter) goes out as 15, "other"."""
FIX_CHOICES = {0: "none", 1: "dead_reckoning", 2: "single", 3: "dgps", 4: "rtk_float", 5: "rtk_fixed"}


@dataclass(frozen=True)
class Sig:
    """One DBC signal (Intel byte order). ``minimum``/``maximum``: physical range (default: the raw
    range minus the special code); ``special``: a raw value with a meaning ("none", "n/a") outside it."""
    name: str
    start: int
    length: int
    signed: bool
    scale: float
    unit: str
    comment: str
    minimum: float | None = None
    maximum: float | None = None
    choices: tuple = ()
    special: int | None = None
    mux: int | None = None          # multiplexed signal: sent when the multiplexer equals this
    multiplexer: bool = False

    def raw_range(self) -> tuple[int, int]:
        lo, hi = (-(1 << (self.length - 1)), (1 << (self.length - 1)) - 1) if self.signed else (0, (1 << self.length) - 1)
        if self.special is not None:
            if self.special == hi:
                hi -= 1
            elif self.special == lo:
                lo += 1
        return lo, hi

    def physical_range(self) -> tuple[float, float]:
        lo, hi = self.raw_range()
        return (lo * self.scale if self.minimum is None else self.minimum,
                hi * self.scale if self.maximum is None else self.maximum)


E2E_CRC = Sig("CRC", 0, 8, False, 1, "", "E2E profile 2 CRC-8-H2F (0x2F, init 0xFF, xor 0xFF) over bytes 1-7 "
                                          "and the data ID (frame id & 0xFF)")


def _counter(comment: str) -> Sig:
    return Sig("Counter", 8, 4, False, 1, "", comment)


_SLOT_COUNTER = _counter("E2E counter: +1 mod 16 per update of the slot, the same in every frame of one update")
_FIX_COMMENT = "fix status of the {} state the result was computed from"
_SD_COMMENT = "1-sigma of the relative position along master body {}; 4095 = n/a (no kinematics)"

# kind -> (base id, signals); STATUS and ID always, the others with kinematics (KINEMATIC_STATUSES)
TARGET_MESSAGES: dict[str, tuple[int, list[Sig]]] = {
    "STATUS": (ID_STATUS, [
        E2E_CRC, _SLOT_COUNTER,
        Sig("Status", 12, 4, False, 1, "", "result status; only 0 (valid) may be used as a reference; 5-9 carry "
            "kinematics that are not valid", 0, max(STATUS_CHOICES), tuple(STATUS_CHOICES.items())),
        Sig("FixSide", 16, 2, False, 1, "", "side whose fix failed the RTK gate: bit0 master, bit1 target", 0, 3,
            ((0, "none"), (1, "master"), (2, "target"), (3, "both"))),
        Sig("Degraded", 18, 1, False, 1, "", "target IMU degraded: a unit failed on consecutive regrades "
            "(docs/quality.md)", 0, 1, ((0, "ok"), (1, "degraded"))),
        Sig("Kind", 19, 1, False, 1, "", "target kind", 0, 1, ((0, "vehicle"), (1, "pedestrian"))),
        Sig("MasterFix", 20, 3, False, 1, "", _FIX_COMMENT.format("master"), 0, 5, tuple(FIX_CHOICES.items())),
        Sig("TargetFix", 23, 3, False, 1, "", _FIX_COMMENT.format("target"), 0, 5, tuple(FIX_CHOICES.items())),
        Sig("Latency", 32, 16, True, 0.1, "ms", "master time - target time of validity"),
        Sig("TTC", 48, 16, False, 0.01, "s", "time to collision; 65535 = none (not closing / no kinematics)",
            choices=((TTC_NONE_RAW, "none"),), special=TTC_NONE_RAW),
        Sig("ReasonSide", 26, 2, False, 1, "", "vehicle whose own state made a non-valid status (attitude, clock, "
            "consistency, verification): bit0 master (its reason: MASTER_SIGMA MasterReason), bit1 target "
            "(TargetReason); a clock alarm sets both", 0, 3, ((0, "none"), (1, "master"), (2, "target"), (3, "both"))),
        Sig("TargetReason", 28, 4, False, 1, "", "the target filter's reason (v2xpos FilterReason); 15 = another "
            "code", 0, REASON_OTHER_RAW, (*REASON_CHOICES.items(), (REASON_OTHER_RAW, "other")))]),
    "POS": (ID_POS, [
        E2E_CRC, _SLOT_COUNTER,
        Sig("PosX", 16, 24, True, 0.001, "m", "target reference point - master reference point, master body x (forward)"),
        Sig("PosY", 40, 24, True, 0.001, "m", "target reference point - master reference point, master body y (right)")]),
    "RANGE": (ID_RANGE, [
        E2E_CRC, _SLOT_COUNTER,
        Sig("Range", 12, 24, False, 0.001, "m", "distance between the reference points"),
        Sig("PosZ", 36, 16, True, 0.001, "m", "target reference point - master reference point, master body z (down)"),
        Sig("RangeSd", 52, 12, False, 0.001, "m", "1-sigma of Range; 4095 = n/a", choices=((SD_NA_RAW, "n/a"),),
            special=SD_NA_RAW)]),
    "VEL": (ID_VEL, [
        E2E_CRC, _SLOT_COUNTER,
        Sig("VelX", 16, 16, True, 0.01, "m/s", "relative velocity seen in the master body frame, x"),
        Sig("VelY", 32, 16, True, 0.01, "m/s", "relative velocity seen in the master body frame, y"),
        Sig("ClosingSpeed", 48, 16, True, 0.01, "m/s", "closing speed of the gap, > 0 when it shrinks")]),
    "GAP": (ID_GAP, [
        E2E_CRC, _SLOT_COUNTER,
        Sig("Longitudinal", 16, 16, True, 0.01, "m", "master measurement point to nearest target point, master body x"),
        Sig("Lateral", 32, 16, True, 0.01, "m", "master measurement point to nearest target point, master body y"),
        Sig("Bearing", 48, 16, True, 0.01, "deg", "azimuth of the target reference point in the master body frame, "
            "+ to the right", -180.0, 180.0)]),
    "ATT": (ID_ATT, [
        E2E_CRC, _SLOT_COUNTER,
        Sig("RelRoll", 16, 16, True, 0.01, "deg", "target roll relative to the master (operator T)", -180.0, 180.0),
        Sig("RelPitch", 32, 16, True, 0.01, "deg", "target pitch relative to the master (operator T)", -90.0, 90.0),
        Sig("RelYaw", 48, 16, True, 0.01, "deg", "target yaw relative to the master (operator T)", -180.0, 180.0)]),
    "ACC": (ID_ACC, [
        E2E_CRC, _SLOT_COUNTER,
        Sig("AccX", 16, 16, True, 0.01, "m/s2", "relative acceleration seen in the master body frame, x"),
        Sig("AccY", 32, 16, True, 0.01, "m/s2", "relative acceleration seen in the master body frame, y"),
        Sig("AccZ", 48, 16, True, 0.01, "m/s2", "relative acceleration seen in the master body frame, z")]),
    "SIGMA": (ID_SIGMA, [
        E2E_CRC, _SLOT_COUNTER,
        Sig("SdX", 16, 12, False, 0.001, "m", _SD_COMMENT.format("x"), choices=((SD_NA_RAW, "n/a"),), special=SD_NA_RAW),
        Sig("SdY", 28, 12, False, 0.001, "m", _SD_COMMENT.format("y"), choices=((SD_NA_RAW, "n/a"),), special=SD_NA_RAW),
        Sig("SdZ", 40, 12, False, 0.001, "m", _SD_COMMENT.format("z"), choices=((SD_NA_RAW, "n/a"),), special=SD_NA_RAW),
        Sig("RelYawSd", 52, 12, False, 0.01, "deg", "1-sigma of RelYaw; 4095 = n/a", choices=((SD_NA_RAW, "n/a"),),
            special=SD_NA_RAW)]),
    "ID": (ID_ID, [
        E2E_CRC, _SLOT_COUNTER,
        Sig("IdPart", 12, 3, False, 1, "", "which 6 bytes of the target id this frame carries (bytes 6*IdPart..)",
            0, ID_PARTS - 1, multiplexer=True),
        Sig("IdLast", 15, 1, False, 1, "", "1: the last part of the target id", 0, 1, ((0, "more"), (1, "last"))),
        *[Sig(f"IdText{p}", 16, 48, False, 1, "", f"target id bytes {6 * p}-{6 * p + 5}, UTF-8, NUL padded, "
              "little-endian (first byte in the low byte)", mux=p) for p in range(ID_PARTS)]]),
}
KINEMATIC_KINDS = ("POS", "RANGE", "VEL", "GAP", "ATT", "ACC", "SIGMA")
FRAMES_PER_KINEMATIC_UPDATE = 2 + len(KINEMATIC_KINDS)
"""Frames of one target update with kinematics (STATUS, the kinematic frames, ID)."""
FRAMES_PER_STATUS_UPDATE = 2
"""Frames of one target update without kinematics (STATUS, ID)."""

SCENE_MESSAGES: dict[str, tuple[int, str, list[Sig]]] = {
    "MASTER_STATUS": (ID_MASTER, "M_", [
        E2E_CRC, _counter("E2E counter: +1 mod 16 per master status update (MASTER_STATUS and MASTER_SIGMA)"),
        Sig("MasterFix", 12, 3, False, 1, "", "fix status of the master's state", 0, 5, tuple(FIX_CHOICES.items())),
        Sig("HeadingValid", 15, 1, False, 1, "", "1: the master's heading is determined (not pending)", 0, 1,
            ((0, "pending"), (1, "valid"))),
        Sig("NTargets", 16, 7, False, 1, "", "targets holding a CAN slot", 0, N_SLOTS),
        Sig("ClockState", 23, 2, False, 1, "", "master clock against GNSS time", 0, 2,
            ((0, "unknown"), (1, "synced"), (2, "unsynced"))),
        Sig("TimeOfWeek", 25, 30, False, 0.001, "s", "GPS time of week of this status", 0.0, 604799.999),
        Sig("ClockOffset", 55, 9, True, 0.1, "ms", "receiver time - host clock; -256 = n/a, saturated at +-25.5 ms",
            choices=((-256, "n/a"),), special=-256)]),
    "MASTER_SIGMA": (ID_MASTER_SIGMA, "MS_", [
        E2E_CRC, _counter("E2E counter: the one of the MASTER_STATUS frame of the same update"),
        Sig("PosSdN", 12, 12, False, 0.001, "m", "master position 1-sigma north; 4095 = n/a",
            choices=((SD_NA_RAW, "n/a"),), special=SD_NA_RAW),
        Sig("PosSdE", 24, 12, False, 0.001, "m", "master position 1-sigma east; 4095 = n/a",
            choices=((SD_NA_RAW, "n/a"),), special=SD_NA_RAW),
        Sig("PosSdD", 36, 12, False, 0.001, "m", "master position 1-sigma down; 4095 = n/a",
            choices=((SD_NA_RAW, "n/a"),), special=SD_NA_RAW),
        Sig("YawSd", 48, 12, False, 0.01, "deg", "master yaw 1-sigma; 4095 = n/a",
            choices=((SD_NA_RAW, "n/a"),), special=SD_NA_RAW),
        Sig("MasterReason", 60, 4, False, 1, "", "the master filter's reason (v2xpos FilterReason); 15 = another "
            "code", 0, REASON_OTHER_RAW, (*REASON_CHOICES.items(), (REASON_OTHER_RAW, "other")))]),
    "LANE": (ID_LANE, "L_", [
        E2E_CRC, _counter("E2E counter: +1 mod 16 per scene update (all LANE frames of one update)"),
        Sig("LaneIndex", 12, 8, False, 1, "", "lane line index in the scene file"),
        Sig("LateralDist", 20, 24, True, 0.001, "m", "signed distance to the line, + line to the right"),
        Sig("LateralSpeed", 44, 16, True, 0.01, "m/s", "rate of change of LateralDist")]),
    "OBJECT": (ID_OBJECT, "O_", [
        Sig("Counter", 0, 4, False, 1, "", "counter: +1 mod 16 per scene update (no CRC: every bit is a signal)"),
        Sig("ObjectIndex", 4, 8, False, 1, "", "static object index in the scene file (points, then polygons)"),
        Sig("Distance", 12, 20, False, 0.001, "m", "measurement point to object (nearest edge, 0 inside)"),
        Sig("Bearing", 32, 16, True, 0.01, "deg", "azimuth in the master body frame, + right", -180.0, 180.0),
        Sig("TTC", 48, 16, False, 0.01, "s", "time to collision; 65535 = none", choices=((TTC_NONE_RAW, "none"),),
            special=TTC_NONE_RAW)]),
}
_E2E_IDS = frozenset(fid for fid, _, sigs in SCENE_MESSAGES.values() if sigs[0] is E2E_CRC)


# ----------------------------------------------------------------------------- E2E checksum
def _crc8h2f_table() -> tuple:
    table = []
    for byte in range(256):
        crc = byte
        for _ in range(8):
            crc = ((crc << 1) ^ 0x2F) & 0xFF if crc & 0x80 else (crc << 1) & 0xFF
        table.append(crc)
    return tuple(table)


_CRC_TABLE = _crc8h2f_table()


def data_id(frame_id: int) -> int:
    """Data ID of a frame (every DataIDList entry): the low byte of its CAN identifier."""
    return frame_id & 0xFF


def e2e_crc(data: bytes, frame_id: int) -> int:
    """CRC-8-H2F of data bytes 1..7 then the Data ID (AUTOSAR E2E Profile 2; see module docstring)."""
    t = _CRC_TABLE
    crc = 0xFF
    for b in data[1:]:
        crc = t[crc ^ b]
    return t[crc ^ (frame_id & 0xFF)] ^ 0xFF


def is_e2e_protected(frame_id: int) -> bool:
    """True for frames with a CRC in byte 0 (all but OBJECT)."""
    return ID_STATUS <= frame_id < ID_STATUS + len(TARGET_MESSAGES) * N_SLOTS or frame_id in _E2E_IDS


# ----------------------------------------------------------------------------- DBC text
def _fmt(x: float) -> str:
    if float(x).is_integer() and abs(x) < 1e16:
        return str(int(x))
    return f"{x:.10g}"


def _message_dbc(frame_id: int, name: str, signals: list[Sig], prefix: str, cycle_ms: int) -> tuple:
    lines = [f"BO_ {frame_id} {name}: 8 {NODE}"]
    comments, values = [], []
    for s in signals:
        lo, hi = s.physical_range()
        full = f"{prefix}{s.name}"
        mux = " M" if s.multiplexer else f" m{s.mux}" if s.mux is not None else ""
        lines.append(f" SG_ {full}{mux} : {s.start}|{s.length}@1{'-' if s.signed else '+'} ({_fmt(s.scale)},0) "
                     f"[{_fmt(lo)}|{_fmt(hi)}] \"{s.unit}\" Vector__XXX")
        comments.append(f'CM_ SG_ {frame_id} {full} "{s.comment}";')
        if s.choices:
            values.append(f"VAL_ {frame_id} {full} " + " ".join(f'{k} "{v}"' for k, v in s.choices) + " ;")
    attrs = [f'BA_ "GenMsgCycleTime" BO_ {frame_id} {cycle_ms};']
    return lines, comments, values, attrs


def generate_dbc(n_slots: int = N_SLOTS, target_cycle_ms: int = 40, master_cycle_ms: int = 100,
                 scene_cycle_ms: int = 100) -> str:
    """The DBC text: master status and sigma, n_slots x 9 target messages, lane and object messages.

    ``GenMsgCycleTime``: the nominal period of each message [ms] -- target frames at the CAN target
    rate (``[output.can] rate_hz``, default 25 Hz; a target's frames are sent with its updates, at
    most that often), master frames at ``[output.can] status_hz`` (10 Hz), scene frames at
    ``[scene] rate_hz`` (10 Hz). Regenerate with other periods if the configuration differs.
    """
    body, comments, values, attrs = [], [], [], []
    for name, (fid, prefix, sigs) in SCENE_MESSAGES.items():
        cyc = master_cycle_ms if name.startswith("MASTER") else scene_cycle_ms
        lines, cm, val, ba = _message_dbc(fid, name, sigs, prefix, cyc)
        body += lines + [""]
        comments += cm
        values += val
        attrs += ba
    for slot in range(n_slots):
        for kind, (base, sigs) in TARGET_MESSAGES.items():
            lines, cm, val, ba = _message_dbc(base + slot, f"TGT{slot:02d}_{kind}", sigs, f"T{slot:02d}_",
                                              target_cycle_ms)
            body += lines + [""]
            comments += cm
            values += val
            attrs += ba
    header = [f'VERSION "{DBC_VERSION}"', "", "NS_ :", "\tBA_DEF_", "\tBA_DEF_DEF_", "\tCM_", "\tVAL_", "",
              "BS_:", "", f"BU_: {NODE}", ""]
    footer = [f'CM_ "v2xpos master outputs, {n_slots} target slots, AUTOSAR E2E profile 2 (CRC-8-H2F in byte 0, '
              f'4-bit counter in byte 1, data ID = frame id & 0xFF); see docs/protocol.md";',
              'CM_ BU_ V2XPOS_MASTER "v2xpos master (hunter) service";']
    defs = ['BA_DEF_ BO_ "GenMsgCycleTime" INT 0 65535;', 'BA_DEF_DEF_ "GenMsgCycleTime" 0;']
    return "\n".join(header + body + footer + comments + defs + attrs + values) + "\n"


_DB_CACHE: dict = {}


def load_dbc(path: str | Path | None = None) -> "cantools.database.can.Database":
    """Load the DBC (default the shipped one; loaded once per process and path+mtime, ~0.4 s)."""
    p = Path(path or DBC_PATH)
    key = (str(p.resolve()), p.stat().st_mtime_ns)
    db = _DB_CACHE.get(key)
    if db is None:
        db = _DB_CACHE[key] = cantools.database.load_file(str(p))
    return db
