"""CAN output of the master's results: shipped DBC (``v2xpos.dbc``), python-can bus, cantools encoding.

Public API (stable)
-------------------
* ``DBC_PATH`` -- the shipped DBC; ``load_dbc(path=None)`` -> cantools database.
* ``generate_dbc(n_slots=64) -> str`` -- the DBC text (the shipped file is its output; a test
  checks they agree).
* ``SlotTable(n_slots)`` -- stable target id -> slot assignment (``slot_of(id)``, ``release(id)``).
* ``CanOutput(channel, interface, dbc_path=None, n_slots=64, bus=None)``:
  ``frames_for_result(res, slot)``, ``send_result(res, slot=None)`` (slot from its SlotTable),
  ``send_lanes(ids, lateral_m, lateral_speed_mps)``, ``send_objects(ids, distance_m, bearing_rad,
  ttc_s)``, ``send_scene(scene_result)``, ``send_master_status(n_targets, master_fix, t_gps_s)``,
  ``frames_sent``, ``close()``. OBJECT frames are indexed by position in ``Scene.objects``
  (points, then polygons); LANE frames by the lane's feature index in the GeoJSON file.
* ``decode_frames(frames, db=None) -> dict`` -- {"targets": {slot: {...}}, "lanes": {index: {...}},
  "objects": {index: {...}}, "master": {...}}, signal names without the slot prefix and
  physical values; a TTC of "none" decodes as None.

Layout (11-bit ids, little-endian signals, 8-byte frames; full table in docs/protocol.md):
0x1F0 MASTER_STATUS; per target slot k (0..63): 0x200+k TGTkk_STATUS, 0x240+k TGTkk_POS,
0x280+k TGTkk_RANGE, 0x2C0+k TGTkk_VEL, 0x300+k TGTkk_EXT; 0x380 LANE (one frame per lane line),
0x381 OBJECT (one frame per static object). Values outside a signal's range are saturated;
NaN is sent as 0.
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Iterable, Sequence

import cantools
import can

from v2xpos.wire import RelativeResult, TargetStatus

DBC_PATH = Path(__file__).with_name("v2xpos.dbc")
N_SLOTS = 64
NODE = "V2XPOS_MASTER"

ID_MASTER = 0x1F0
ID_STATUS, ID_POS, ID_RANGE, ID_VEL, ID_EXT = 0x200, 0x240, 0x280, 0x2C0, 0x300
ID_LANE, ID_OBJECT = 0x380, 0x381
TTC_NONE_RAW = 0xFFFF
OBJECT_KIND = {"point": 0, "polygon": 1}

# name, start bit, length, signed, scale, offset, unit, comment
_TARGET_MESSAGES: dict[str, tuple[int, list]] = {
    "STATUS": (ID_STATUS, [
        ("Status", 0, 4, False, 1, 0, "", "0 valid 1 fix_invalid 2 timeout 3 no_data 4 future"),
        ("FixSide", 4, 2, False, 1, 0, "", "bit0 master not RTK, bit1 target not RTK"),
        ("Degraded", 6, 1, False, 1, 0, "", "IMU quality degraded"),
        ("Kind", 7, 1, False, 1, 0, "", "0 vehicle 1 pedestrian"),
        ("Counter", 8, 8, False, 1, 0, "", "per-slot update counter"),
        ("Latency", 16, 16, True, 0.1, 0, "ms", "master time - target time of validity"),
        ("TTC", 32, 16, False, 0.01, 0, "s", "time to collision, raw 65535 = none"),
        ("RelYaw", 48, 16, True, 0.01, 0, "deg", "target yaw relative to master")]),
    "POS": (ID_POS, [
        ("PosX", 0, 24, True, 0.001, 0, "m", "relative position, master body x (forward)"),
        ("PosY", 24, 24, True, 0.001, 0, "m", "relative position, master body y (right)"),
        ("PosZ", 48, 16, True, 0.001, 0, "m", "relative position, master body z (down)")]),
    "RANGE": (ID_RANGE, [
        ("Range", 0, 24, False, 0.001, 0, "m", "reference point range"),
        ("Bearing", 24, 16, True, 0.01, 0, "deg", "azimuth in master body frame, + right"),
        ("ClosingSpeed", 40, 16, True, 0.01, 0, "m/s", "> 0 when the gap shrinks"),
        ("Counter", 56, 8, False, 1, 0, "", "per-slot update counter")]),
    "VEL": (ID_VEL, [
        ("VelX", 0, 16, True, 0.01, 0, "m/s", "relative velocity, master body x"),
        ("VelY", 16, 16, True, 0.01, 0, "m/s", "relative velocity, master body y"),
        ("Longitudinal", 32, 16, True, 0.01, 0, "m", "measurement point to nearest target point, x"),
        ("Lateral", 48, 16, True, 0.01, 0, "m", "measurement point to nearest target point, y")]),
    "EXT": (ID_EXT, [
        ("AccX", 0, 16, True, 0.01, 0, "m/s2", "relative acceleration, master body x"),
        ("AccY", 16, 16, True, 0.01, 0, "m/s2", "relative acceleration, master body y"),
        ("RelRoll", 32, 16, True, 0.01, 0, "deg", "target roll relative to master"),
        ("RelPitch", 48, 16, True, 0.01, 0, "deg", "target pitch relative to master")]),
}
_SCENE_MESSAGES: dict[str, tuple[int, list]] = {
    "MASTER_STATUS": (ID_MASTER, [
        ("Counter", 0, 8, False, 1, 0, "", "master update counter"),
        ("NTargets", 8, 8, False, 1, 0, "", "targets with a slot"),
        ("MasterFix", 16, 4, False, 1, 0, "", "0 none 1 DR 2 single 3 DGPS 4 float 5 fixed"),
        ("TimeOfWeek", 24, 32, False, 0.001, 0, "s", "master GPS time of week")]),
    "LANE": (ID_LANE, [
        ("LaneIndex", 0, 8, False, 1, 0, "", "lane line index in the scene file"),
        ("Counter", 8, 8, False, 1, 0, "", "update counter"),
        ("LateralDist", 16, 24, True, 0.001, 0, "m", "signed distance to the line, + line to the right"),
        ("LateralSpeed", 40, 16, True, 0.01, 0, "m/s", "rate of change of LateralDist")]),
    "OBJECT": (ID_OBJECT, [
        ("ObjectIndex", 0, 8, False, 1, 0, "", "static object index in the scene file"),
        ("Distance", 8, 24, False, 0.001, 0, "m", "measurement point to object (nearest edge)"),
        ("Bearing", 32, 16, True, 0.01, 0, "deg", "azimuth in master body frame, + right"),
        ("TTC", 48, 16, False, 0.01, 0, "s", "time to collision, raw 65535 = none")]),
}


def _signal_range(length: int, signed: bool, scale: float, offset: float) -> tuple:
    lo_raw, hi_raw = (-(1 << (length - 1)), (1 << (length - 1)) - 1) if signed else (0, (1 << length) - 1)
    return lo_raw * scale + offset, hi_raw * scale + offset


def _fmt(x: float) -> str:
    return f"{x:.10g}"


def _message_dbc(frame_id: int, name: str, signals: list, prefix: str) -> tuple:
    lines = [f"BO_ {frame_id} {name}: 8 {NODE}"]
    comments = []
    for sname, start, length, signed, scale, offset, unit, comment in signals:
        lo, hi = _signal_range(length, signed, scale, offset)
        full = f"{prefix}{sname}"
        lines.append(f" SG_ {full} : {start}|{length}@1{'-' if signed else '+'} ({_fmt(scale)},{_fmt(offset)}) "
                     f"[{_fmt(lo)}|{_fmt(hi)}] \"{unit}\" Vector__XXX")
        comments.append(f'CM_ SG_ {frame_id} {full} "{comment}";')
    return lines, comments


def generate_dbc(n_slots: int = N_SLOTS) -> str:
    """The DBC text: master status, n_slots x 5 target messages, lane and object messages."""
    body, comments, values = [], [], []
    for name, (fid, sigs) in _SCENE_MESSAGES.items():
        prefix = {"MASTER_STATUS": "M_", "LANE": "L_", "OBJECT": "O_"}[name]
        lines, cm = _message_dbc(fid, name, sigs, prefix)
        body += lines + [""]
        comments += cm
    values.append(f'VAL_ {ID_OBJECT} O_TTC {TTC_NONE_RAW} "none" ;')
    for slot in range(n_slots):
        for kind, (base, sigs) in _TARGET_MESSAGES.items():
            lines, cm = _message_dbc(base + slot, f"TGT{slot:02d}_{kind}", sigs, f"T{slot:02d}_")
            body += lines + [""]
            comments += cm
        values.append(f'VAL_ {ID_STATUS + slot} T{slot:02d}_Status 0 "valid" 1 "fix_invalid" 2 "timeout" '
                      f'3 "no_data" 4 "future" ;')
        values.append(f'VAL_ {ID_STATUS + slot} T{slot:02d}_TTC {TTC_NONE_RAW} "none" ;')
    header = ['VERSION "v2xpos 1"', "", "NS_ :", "", "BS_:", "", f"BU_: {NODE}", ""]
    footer = [f'CM_ "v2xpos master outputs, {n_slots} target slots; see docs/protocol.md";']
    return "\n".join(header + body + footer + comments + values) + "\n"


def load_dbc(path: str | Path | None = None) -> "cantools.database.can.Database":
    """Load the DBC (default the shipped one)."""
    return cantools.database.load_file(str(path or DBC_PATH))


class SlotTable:
    """Stable assignment of target ids to CAN slots 0..n_slots-1 (first come, first served)."""

    def __init__(self, n_slots: int = N_SLOTS):
        self.n_slots = n_slots
        self._slot: dict[str, int] = {}
        self._free = list(range(n_slots - 1, -1, -1))

    def slot_of(self, target_id: str) -> int | None:
        """Slot of target_id, assigning the lowest free one on first sight; None when full."""
        s = self._slot.get(target_id)
        if s is None and self._free:
            s = self._free.pop()
            self._slot[target_id] = s
        return s

    def release(self, target_id: str) -> None:
        """Free the slot of a target that left."""
        s = self._slot.pop(target_id, None)
        if s is not None:
            self._free.append(s)
            self._free.sort(reverse=True)

    def __len__(self) -> int:
        return len(self._slot)

    def items(self) -> Iterable:
        return self._slot.items()


def _ttc_raw_value(ttc_s: float | None, scale: float) -> float:
    """TTC physical value to send: None/NaN/inf -> the "none" code; else saturated below it."""
    if ttc_s is None or not math.isfinite(ttc_s):
        return TTC_NONE_RAW * scale
    return min(max(ttc_s, 0.0), (TTC_NONE_RAW - 1) * scale)


def _finite(x: float) -> float:
    return x if math.isfinite(x) else 0.0


TTC_SCALE = 0.01


class FramePacker:
    """Precompiled encoder of one DBC message (little-endian integer signals, as in the shipped DBC).

    Built from the cantools message's signals (start bit, length, signedness, scale, offset,
    minimum, maximum); ``pack(values)`` takes physical values in ``names`` order and returns the
    data bytes that ``message.encode(..., strict=False)`` gives for the same values after the
    saturation of ``CanOutput._encode``: NaN -> 0, then clipped to [minimum, maximum], raw =
    round((value - offset) / scale) (cantools' conversion), two's complement in ``length`` bits
    at ``start`` of the little-endian payload (Intel byte order, DBC ``@1``). About 10x cheaper
    than cantools' generic path; ``tests/test_output_can_packer.py`` checks it bit-exact against
    cantools.
    """

    def __init__(self, message: Any, order: Sequence[str] | None = None):
        by_name = {sig.name: sig for sig in message.signals}
        names = tuple(order) if order is not None else tuple(by_name)
        if set(names) != set(by_name):
            raise ValueError(f"{message.name}: packer signals {sorted(names)} != DBC signals {sorted(by_name)}")
        fields = []
        for name in names:
            sig = by_name[name]
            if sig.byte_order != "little_endian" or sig.is_float:
                raise ValueError(f"{message.name}.{name}: only little-endian integer signals are precompiled")
            lo = -math.inf if sig.minimum is None else sig.minimum
            hi = math.inf if sig.maximum is None else sig.maximum
            fields.append((sig.start, (1 << sig.length) - 1, sig.conversion.scale, sig.conversion.offset, lo, hi))
        self.frame_id = message.frame_id
        self.length = message.length
        self.names = names
        self._fields = tuple(fields)

    def pack(self, values: Sequence[float]) -> bytes:
        """Data bytes of physical ``values`` given in ``names`` order."""
        word = 0
        for v, (start, mask, scale, offset, lo, hi) in zip(values, self._fields):
            v = 0.0 if v != v else lo if v < lo else hi if v > hi else v
            word |= (int(round((v - offset) / scale)) & mask) << start
        return word.to_bytes(self.length, "little")

    def pack_mapping(self, values: dict) -> bytes:
        """Data bytes of a {signal name: physical value} mapping (every signal of the message)."""
        if len(values) != len(self.names):
            missing = sorted(set(self.names) - set(values))
            raise KeyError(f"signals missing or unknown for frame 0x{self.frame_id:03X}: {missing or sorted(values)}")
        return self.pack([values[n] for n in self.names])


class CanOutput:
    """Sends master results as CAN frames on a python-can bus using the DBC.

    ``interface`` "socketcan" with channel "can0" on a vehicle, "virtual" in tests (channel name
    shared by the buses of one process). Pass ``bus`` to reuse an existing python-can bus.
    """

    def __init__(self, channel: str = "vcan0", interface: str = "virtual", dbc_path: str | Path | None = None,
                 n_slots: int = N_SLOTS, bus: can.BusABC | None = None, **bus_kwargs: Any):
        if not 1 <= n_slots <= N_SLOTS:
            raise ValueError(f"n_slots must be 1..{N_SLOTS} (the DBC defines {N_SLOTS} target slots), got {n_slots}")
        self.db = load_dbc(dbc_path)
        self.n_slots = n_slots
        self.slots = SlotTable(n_slots)
        self.bus = bus if bus is not None else can.Bus(channel=channel, interface=interface, **bus_kwargs)
        self._own_bus = bus is None
        self.frames_sent = 0
        self._counter = [0] * n_slots
        self._scene_counter = 0
        self._master_counter = 0
        self._msg = {}
        self._packers: dict[int, FramePacker] = {}
        for slot in range(n_slots):
            for kind, (base, _) in _TARGET_MESSAGES.items():
                self._msg[(slot, kind)] = self.db.get_message_by_frame_id(base + slot)
        self._lane = self.db.get_message_by_frame_id(ID_LANE)
        self._object = self.db.get_message_by_frame_id(ID_OBJECT)
        self._master = self.db.get_message_by_frame_id(ID_MASTER)
        # per slot: (STATUS, POS, RANGE, VEL, EXT) packers, signal order as in _TARGET_MESSAGES
        self._slot_packers = [tuple(self._packer(self._msg[(slot, kind)], [f"T{slot:02d}_{sig[0]}" for sig in sigs])
                                    for kind, (_, sigs) in _TARGET_MESSAGES.items())
                              for slot in range(n_slots)]

    # -- encoding (pure) --------------------------------------------------------------
    def _packer(self, message: Any, order: Sequence[str] | None = None) -> "FramePacker":
        packer = self._packers.get(message.frame_id)
        if packer is None or (order is not None and packer.names != tuple(order)):
            packer = self._packers[message.frame_id] = FramePacker(message, order)
        return packer

    def _encode(self, message: Any, values: dict) -> can.Message:
        """Frame of physical values: saturated to each signal's range, NaN sent as 0 (cantools
        cannot encode NaN; a non-finite value must not stop the other frames)."""
        packer = self._packer(message)
        return can.Message(arbitration_id=message.frame_id, data=packer.pack_mapping(values), is_extended_id=False)

    def frames_for_result(self, res: RelativeResult, slot: int, counter: int = 0) -> list:
        """CAN frames of one target result in ``slot``; kinematic frames only when status is VALID."""
        if not 0 <= slot < self.n_slots:
            raise ValueError(f"slot {slot} outside 0..{self.n_slots - 1}")
        st, pos, rng, vel, ext = self._slot_packers[slot]
        valid = res.status == TargetStatus.VALID
        counter &= 0xFF
        status = st.pack((int(res.status), int(res.fix_side), int(bool(res.degraded)),
                          int(res.target_kind == "pedestrian"), counter, _finite(res.latency_s * 1e3),
                          _ttc_raw_value(res.ttc_s if valid else None, TTC_SCALE),
                          math.degrees(res.rel_rpy_rad[2]) if valid else 0.0))
        frames = [can.Message(arbitration_id=st.frame_id, data=status, is_extended_id=False)]
        if not valid:
            return frames
        r, v, a, att = (res.rel_pos_body_m.tolist(), res.rel_vel_body_mps.tolist(), res.rel_acc_body_mps2.tolist(),
                        res.rel_rpy_rad.tolist())
        for packer, values in (
                (pos, r),
                (rng, (res.range_m, math.degrees(res.bearing_rad), _finite(res.closing_speed_mps), counter)),
                (vel, (v[0], v[1], _finite(res.longitudinal_m), _finite(res.lateral_m))),
                (ext, (a[0], a[1], math.degrees(att[0]), math.degrees(att[1])))):
            frames.append(can.Message(arbitration_id=packer.frame_id, data=packer.pack(values), is_extended_id=False))
        return frames

    def lane_frames(self, ids: Sequence[int], lateral_m: Sequence[float],
                    lateral_speed_mps: Sequence[float]) -> list:
        """One LANE frame per lane line (index, signed lateral distance, lateral speed)."""
        c = self._scene_counter & 0xFF
        return [self._encode(self._lane, {"L_LaneIndex": int(i) & 0xFF, "L_Counter": c,
                                          "L_LateralDist": _finite(d), "L_LateralSpeed": _finite(s)})
                for i, d, s in zip(ids, lateral_m, lateral_speed_mps)]

    def object_frames(self, ids: Sequence[int], distance_m: Sequence[float], bearing_rad: Sequence[float],
                      ttc_s: Sequence[float | None]) -> list:
        """One OBJECT frame per static object (index, distance to nearest edge, bearing, TTC)."""
        return [self._encode(self._object, {"O_ObjectIndex": int(i) & 0xFF, "O_Distance": _finite(d),
                                            "O_Bearing": math.degrees(_finite(b)),
                                            "O_TTC": _ttc_raw_value(t, 0.01)})
                for i, d, b, t in zip(ids, distance_m, bearing_rad, ttc_s)]

    def master_frame(self, n_targets: int, master_fix: int, t_gps_s: float) -> can.Message:
        """MASTER_STATUS frame (time of week from GPS seconds since the GPS epoch)."""
        return self._encode(self._master, {"M_Counter": self._master_counter & 0xFF, "M_NTargets": min(n_targets, 255),
                                           "M_MasterFix": int(master_fix), "M_TimeOfWeek": t_gps_s % 604800.0})

    # -- sending -----------------------------------------------------------------------
    def _send(self, frames: list) -> int:
        for f in frames:
            self.bus.send(f)
        self.frames_sent += len(frames)
        return len(frames)

    def send_result(self, res: RelativeResult, slot: int | None = None) -> int:
        """Send one target result; slot from the SlotTable by target_id when not given.

        Returns the number of frames sent (0 when no slot is free).
        """
        if slot is None:
            slot = self.slots.slot_of(res.target_id)
            if slot is None:
                return 0
        frames = self.frames_for_result(res, slot, self._counter[slot])
        self._counter[slot] = (self._counter[slot] + 1) & 0xFF
        return self._send(frames)

    def send_lanes(self, ids: Sequence[int], lateral_m: Sequence[float], lateral_speed_mps: Sequence[float]) -> int:
        """Send one LANE frame per lane line (``lane_frames``); returns the frames sent."""
        n = self._send(self.lane_frames(ids, lateral_m, lateral_speed_mps))
        self._scene_counter += 1
        return n

    def send_objects(self, ids: Sequence[int], distance_m: Sequence[float], bearing_rad: Sequence[float],
                     ttc_s: Sequence[float | None]) -> int:
        """Send one OBJECT frame per static object (``object_frames``); returns the frames sent."""
        return self._send(self.object_frames(ids, distance_m, bearing_rad, ttc_s))

    def send_scene(self, scene_result: Any) -> int:
        """Send a ``scene.SceneResult``: one LANE frame per lane line, one OBJECT frame per object."""
        n = self.send_lanes(scene_result.lane_index, scene_result.lane_lateral_m,
                            scene_result.lane_lateral_speed_mps)
        return n + self.send_objects(range(len(scene_result.object_ids)), scene_result.object_distance_m,
                                     scene_result.object_bearing_rad, scene_result.object_ttc_s)

    def send_master_status(self, n_targets: int, master_fix: int, t_gps_s: float) -> int:
        """Send the MASTER_STATUS frame (``master_frame``); returns 1."""
        n = self._send([self.master_frame(n_targets, master_fix, t_gps_s)])
        self._master_counter += 1
        return n

    def close(self) -> None:
        """Shut the bus down if this object opened it."""
        if self._own_bus:
            self.bus.shutdown()

    def __enter__(self) -> "CanOutput":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


def decode_frames(frames: Iterable[can.Message], db: Any = None) -> dict:
    """Decode frames with the DBC into {"targets", "lanes", "objects", "master", "unknown", "malformed"}.

    targets: {slot: {signal: value}} merged over a slot's frames (later frames win);
    lanes/objects: {index: {signal: value}}; TTC "none" -> None; unknown ids are counted;
    frames of the wrong length are skipped and described in "malformed".
    """
    db = db if db is not None else load_dbc()
    out: dict = {"targets": {}, "lanes": {}, "objects": {}, "master": {}, "unknown": 0, "malformed": []}
    for f in frames:
        try:
            msg = db.get_message_by_frame_id(f.arbitration_id)
        except KeyError:
            out["unknown"] += 1
            continue
        if len(f.data) != msg.length:
            out["malformed"].append(f"id 0x{f.arbitration_id:03X}: {len(f.data)} data bytes, expected {msg.length}")
            continue
        raw = msg.decode(bytes(f.data), decode_choices=False, scaling=False)
        vals = msg.decode(bytes(f.data), decode_choices=False)
        fid = f.arbitration_id
        if ID_STATUS <= fid < ID_LANE:
            slot = (fid - ID_STATUS) % N_SLOTS
            prefix = f"T{slot:02d}_"
            d = out["targets"].setdefault(slot, {})
            for k, v in vals.items():
                name = k[len(prefix):]
                d[name] = None if name == "TTC" and raw[k] == TTC_NONE_RAW else v
        elif fid == ID_LANE:
            d = {k[2:]: v for k, v in vals.items()}
            out["lanes"][int(d["LaneIndex"])] = d
        elif fid == ID_OBJECT:
            d = {k[2:]: v for k, v in vals.items()}
            if raw["O_TTC"] == TTC_NONE_RAW:
                d["TTC"] = None
            out["objects"][int(d["ObjectIndex"])] = d
        elif fid == ID_MASTER:
            out["master"] = {k[2:]: v for k, v in vals.items()}
    return out
