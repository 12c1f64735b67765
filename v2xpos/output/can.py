"""CAN output of the master's results: shipped DBC (``v2xpos.dbc``), python-can bus, E2E-protected frames.

Public API (stable)
-------------------
* ``DBC_PATH``, ``load_dbc(path=None)``, ``generate_dbc(...)``, ``e2e_crc(data, frame_id)``,
  ``data_id(frame_id)`` -- the shipped DBC and the E2E checksum (``v2xpos.output.can_dbc``, where the
  layout, the frame ids and the signal tables are defined).
* ``SlotTable(n_slots, fixed=None)`` -- target id -> slot: ``fixed`` {id: slot} from the config
  (``[output.can] slots``) always, first come first served among the other slots for ids not in
  it (``slot_of(id)``, ``release(id)``).
* ``CanOutput(channel, interface, dbc_path=None, n_slots=64, bus=None, slots=None, **bus_kwargs)``:
  ``frames_for_result(res, slot, counter)``, ``send_result(res, slot=None)``,
  ``send_lanes(...)``, ``send_objects(...)``, ``send_scene(scene_result)``,
  ``master_frames(status, counter)``, ``send_master_status(status)``, ``frames_sent``, ``close()``.
  A bus that cannot be opened raises ``CanBusError`` (one line naming interface and channel).
* ``decode_frames(frames, db=None) -> dict`` -- {"targets": {slot: {...}}, "lanes", "objects",
  "master", "unknown", "malformed", "e2e_errors"}: signal names without the slot prefix, physical
  values; TTC "none" and sigma "n/a" decode as None; a slot's ``TargetId`` once its ID parts
  arrived.

Layout and E2E protection: ``v2xpos.output.can_dbc`` and docs/protocol.md §5.
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Iterable, Mapping, Sequence

import can

from v2xpos.types import FixStatus
from v2xpos.wire import KINEMATIC_STATUSES, RelativeResult

from .can_dbc import (DBC_PATH, E2E_CRC, FRAMES_PER_KINEMATIC_UPDATE, FRAMES_PER_STATUS_UPDATE, ID_CHARS_PER_FRAME,
                      ID_ID, ID_LANE, ID_MASTER, ID_MASTER_SIGMA, ID_OBJECT, ID_PARTS, ID_STATUS, N_SLOTS,
                      REASON_OTHER_RAW, SCENE_MESSAGES, TARGET_MESSAGES, Sig, is_e2e_protected, load_dbc)
from .can_dbc import data_id, e2e_crc, generate_dbc  # noqa: F401  (public API of this module, see above)

# ----------------------------------------------------------------------------- slots
class SlotTable:
    """Target id -> CAN slot 0..n_slots-1.

    ``fixed`` {id: slot} (``[output.can] slots``): those ids always get their slot, and those slots
    are never given to anyone else. Other ids: the lowest slot neither fixed nor taken, on first
    sight (first come, first served); ``release`` returns it.
    """

    def __init__(self, n_slots: int = N_SLOTS, fixed: Mapping[str, int] | None = None):
        fixed = dict(fixed or {})
        bad = {k: v for k, v in fixed.items() if not (isinstance(v, int) and 0 <= v < n_slots)}
        if bad:
            raise ValueError(f"slots outside 0..{n_slots - 1}: {bad}")
        if len(set(fixed.values())) != len(fixed):
            raise ValueError(f"two target ids share a slot: {fixed}")
        self.n_slots = n_slots
        self.fixed = fixed
        self._slot: dict[str, int] = {}
        reserved = set(fixed.values())
        self._free = [s for s in range(n_slots - 1, -1, -1) if s not in reserved]

    def slot_of(self, target_id: str) -> int | None:
        """Slot of target_id (its configured one, else the lowest free one on first sight); None when full."""
        s = self._slot.get(target_id)
        if s is None:
            s = self.fixed.get(target_id)
            if s is None and self._free:
                s = self._free.pop()
            if s is not None:
                self._slot[target_id] = s
        return s

    def release(self, target_id: str) -> None:
        """Free the slot of a target that left (a configured slot stays reserved for its id)."""
        s = self._slot.pop(target_id, None)
        if s is not None and target_id not in self.fixed:
            self._free.append(s)
            self._free.sort(reverse=True)

    def __len__(self) -> int:
        return len(self._slot)

    def items(self) -> Iterable:
        return self._slot.items()


# ----------------------------------------------------------------------------- packing
class FramePacker:
    """Precompiled encoder of one DBC message (little-endian integer signals, as in the shipped DBC).

    Built from the cantools message's signals (start bit, length, scale, offset, minimum, maximum)
    and the special raw codes of ``specials`` {signal name: raw}; ``pack(values)`` takes physical
    values in ``names`` order (the E2E ``CRC`` signal, if the message has one, is not among them:
    it is computed over the packed bytes) and returns the data bytes. Per value: None -> the
    signal's special code (else 0); NaN -> the special code if any, else 0; then clipped to
    [minimum, maximum]; raw = round((value - offset) / scale) (cantools' conversion), two's
    complement in ``length`` bits at ``start`` (Intel byte order, DBC ``@1``). About 10x cheaper than
    cantools' generic path; ``tests/test_output_can_packer.py`` checks it bit-exact against cantools.
    """

    def __init__(self, message: Any, order: Sequence[str] | None = None, specials: Mapping[str, int] | None = None):
        by_name = {sig.name: sig for sig in message.signals}
        crc_names = [n for n in by_name if n.endswith("_CRC") and by_name[n].start == 0 and by_name[n].length == 8]
        self.e2e = bool(crc_names)
        payload = {n: s for n, s in by_name.items() if n not in crc_names}
        names = tuple(order) if order is not None else tuple(payload)
        if set(names) != set(payload):
            raise ValueError(f"{message.name}: packer signals {sorted(names)} != DBC signals {sorted(payload)}")
        specials = specials or {}
        fields = []
        for name in names:
            sig = by_name[name]
            if sig.byte_order != "little_endian" or sig.is_float:
                raise ValueError(f"{message.name}.{name}: only little-endian integer signals are precompiled")
            lo = -math.inf if sig.minimum is None else sig.minimum
            hi = math.inf if sig.maximum is None else sig.maximum
            special = specials.get(name)
            fields.append((sig.start, (1 << sig.length) - 1, sig.conversion.scale, sig.conversion.offset, lo, hi,
                           special))
        self.frame_id = message.frame_id
        self.length = message.length
        self.names = names
        self._fields = tuple(fields)
        self.pack = self._compile()

    def _compile(self):
        """``pack`` as a function generated for this layout (constants inlined: ~2x faster than a
        loop over the field table; same arithmetic)."""
        lines = ["def pack(values):", f"    ({', '.join(f'v{i}' for i in range(len(self._fields)))},) = values",
                 "    w = 0"]
        for i, (start, mask, scale, offset, lo, hi, special) in enumerate(self._fields):
            v = f"v{i}"
            nan_branch = (f"w |= {(special & mask) << start}" if special is not None else f"{v} = 0.0")
            lines.append(f"    if {v} is None or {v} != {v}:")
            lines.append(f"        {nan_branch}")
            lines.append("    else:" if special is not None else "    if True:")
            clip = []
            if lo != -math.inf:
                clip.append(f"        if {v} < {lo!r}: {v} = {lo!r}")
            if hi != math.inf:
                clip.append(f"        if {v} > {hi!r}: {v} = {hi!r}")
            lines += clip
            lines.append(f"        w |= (int(round(({v} - {offset!r}) / {scale!r})) & {mask}) << {start}")
        lines.append(f"    data = w.to_bytes({self.length}, 'little')")
        if self.e2e:
            lines.append(f"    return bytes((e2e_crc(data, {self.frame_id}),)) + data[1:]")
        else:
            lines.append("    return data")
        namespace = {"e2e_crc": e2e_crc}
        exec("\n".join(lines), namespace)   # noqa: S102 (generated from the DBC's numbers only)
        return namespace["pack"]

    def pack_loop(self, values: Sequence[float | None]) -> bytes:
        """Data bytes of physical ``values`` given in ``names`` order (CRC filled when E2E-protected);
        the readable reference of the generated ``pack``."""
        word = 0
        for v, (start, mask, scale, offset, lo, hi, special) in zip(values, self._fields):
            if v is None or v != v:
                if special is not None:
                    word |= (special & mask) << start
                    continue
                v = 0.0
            v = lo if v < lo else hi if v > hi else v
            word |= (int(round((v - offset) / scale)) & mask) << start
        data = word.to_bytes(self.length, "little")
        if self.e2e:
            data = bytes((e2e_crc(data, self.frame_id),)) + data[1:]
        return data

    def pack_mapping(self, values: dict) -> bytes:
        """Data bytes of a {signal name: physical value} mapping (every signal but the CRC)."""
        if len(values) != len(self.names):
            missing = sorted(set(self.names) - set(values))
            raise KeyError(f"signals missing or unknown for frame 0x{self.frame_id:03X}: {missing or sorted(values)}")
        return self.pack([values[n] for n in self.names])


def _specials(sigs: list[Sig], prefix: str) -> dict:
    return {f"{prefix}{s.name}": s.special for s in sigs if s.special is not None}


def _ttc_value(ttc_s: float | None) -> float | None:
    """TTC to send: None/NaN/inf -> None (the "none" code); else saturated below it by the packer."""
    return ttc_s if ttc_s is not None and math.isfinite(ttc_s) else None


def _reason_raw(code: int) -> int:
    """A FilterReason code as the 4-bit CAN signal (codes beyond it: REASON_OTHER_RAW)."""
    code = int(code)
    return code if 0 <= code < REASON_OTHER_RAW else REASON_OTHER_RAW


def _finite(x: float) -> float:
    return x if math.isfinite(x) else 0.0


def _deg(x: float) -> float:
    return math.degrees(x)


def _id_parts(target_id: str) -> list[tuple[int, int, int]]:
    """(part, last, 48-bit little-endian value) of each 6-byte part of the UTF-8 id."""
    raw = target_id.encode()[:ID_CHARS_PER_FRAME * ID_PARTS]
    n = max(1, -(-len(raw) // ID_CHARS_PER_FRAME))
    return [(p, int(p == n - 1), int.from_bytes(raw[ID_CHARS_PER_FRAME * p:ID_CHARS_PER_FRAME * (p + 1)]
                                                 .ljust(ID_CHARS_PER_FRAME, b"\0"), "little")) for p in range(n)]


_PACKER_CACHE: dict = {}
"""Compiled packers by (database, frame id, signal order): immutable, shared by every CanOutput."""


class CanBusError(RuntimeError):
    """The CAN bus could not be opened (message: interface, channel, reason; one line)."""


def open_bus(channel: str, interface: str, **bus_kwargs: Any) -> can.BusABC:
    """``can.Bus(channel, interface, **bus_kwargs)``; any failure -> CanBusError naming both."""
    try:
        return can.Bus(channel=channel, interface=interface, **bus_kwargs)
    except (OSError, can.CanError, ImportError, ValueError, TypeError, NotImplementedError) as exc:
        reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc) or type(exc).__name__
        if isinstance(exc, OSError) and exc.errno == 97 and interface == "socketcan":
            reason += " (no SocketCAN in this kernel / container)"
        elif isinstance(exc, OSError) and exc.errno == 19:
            reason += f" (no network interface {channel!r}: ip link add / set {channel} up)"
        raise CanBusError(f"CAN interface {interface!r} channel {channel!r}: cannot open: {reason}") from None


class CanOutput:
    """Sends master results as CAN frames on a python-can bus using the DBC.

    ``interface`` "socketcan" with channel "can0" on a vehicle, "virtual" in tests (channel name
    shared by the buses of one process). Pass ``bus`` to reuse an existing python-can bus;
    ``bus_kwargs`` go to ``can.Bus`` (bitrate, fd, data_bitrate, receive_own_messages, ...).
    ``slots``: the fixed {target id: slot} mapping (``SlotTable``).
    """

    def __init__(self, channel: str = "vcan0", interface: str = "virtual", dbc_path: str | Path | None = None,
                 n_slots: int = N_SLOTS, bus: can.BusABC | None = None, slots: Mapping[str, int] | None = None,
                 **bus_kwargs: Any):
        if not 1 <= n_slots <= N_SLOTS:
            raise ValueError(f"n_slots must be 1..{N_SLOTS} (the DBC defines {N_SLOTS} target slots), got {n_slots}")
        self.slots = SlotTable(n_slots, slots)
        self.db = load_dbc(dbc_path)
        self.n_slots = n_slots
        self.fd = bool(bus_kwargs.get("fd", False))
        self.bus = bus if bus is not None else open_bus(channel, interface, **bus_kwargs)
        self._own_bus = bus is None
        self.frames_sent = 0
        self._counter = [0] * n_slots
        self._id_part = [0] * n_slots
        self._id_cache: dict[str, list] = {}
        self._scene_counter = 0
        self._master_counter = 0
        self._packers: dict[int, FramePacker] = {}
        # per slot: {kind: packer}, payload signal order as in TARGET_MESSAGES (CRC excluded)
        self._slot_packers = []
        for slot in range(n_slots):
            p = f"T{slot:02d}_"
            self._slot_packers.append({
                kind: self._packer(self.db.get_message_by_frame_id(base + slot),
                                   [p + s.name for s in sigs if s is not E2E_CRC], _specials(sigs, p))
                for kind, (base, sigs) in TARGET_MESSAGES.items() if kind != "ID"})
        self._scene = {name: self._packer(self.db.get_message_by_frame_id(fid),
                                          [prefix + s.name for s in sigs if s is not E2E_CRC], _specials(sigs, prefix))
                       for name, (fid, prefix, sigs) in SCENE_MESSAGES.items()}

    # -- encoding (pure) --------------------------------------------------------------
    def _packer(self, message: Any, order: Sequence[str] | None = None,
                specials: Mapping[str, int] | None = None) -> FramePacker:
        key = (id(self.db), message.frame_id, None if order is None else tuple(order))
        packer = _PACKER_CACHE.get(key)
        if packer is None:
            packer = _PACKER_CACHE[key] = FramePacker(message, order, specials)
        self._packers[message.frame_id] = packer
        return packer

    def _frame(self, frame_id: int, data: bytes) -> can.Message:
        return can.Message(arbitration_id=frame_id, data=data, is_extended_id=False, is_fd=self.fd)

    def id_frame(self, target_id: str, slot: int, counter: int, part: int = 0) -> can.Message:
        """TGTnn_ID frame with part ``part`` (mod the id's number of parts) of ``target_id``."""
        parts = self._id_cache.get(target_id)
        if parts is None:
            if len(self._id_cache) > 4 * N_SLOTS:
                self._id_cache.clear()
            parts = self._id_cache[target_id] = _id_parts(target_id)
        p, last, text = parts[part % len(parts)]
        word = ((counter & 0xF) << 8) | (p << 12) | (last << 15) | (text << 16)
        data = word.to_bytes(8, "little")
        fid = ID_ID + slot
        return self._frame(fid, bytes((e2e_crc(data, fid),)) + data[1:])

    def frames_for_result(self, res: RelativeResult, slot: int, counter: int = 0, id_part: int = 0) -> list:
        """CAN frames of one target result in ``slot``: STATUS, the kinematic frames when the status
        carries kinematics (``wire.KINEMATIC_STATUSES``), and one ID frame (part ``id_part``)."""
        if not 0 <= slot < self.n_slots:
            raise ValueError(f"slot {slot} outside 0..{self.n_slots - 1}")
        pk = self._slot_packers[slot]
        kin = res.status in KINEMATIC_STATUSES
        c = counter & 0xF
        frame = self._frame
        st = pk["STATUS"]
        frames = [frame(st.frame_id, st.pack((c, int(res.status), int(res.fix_side), int(bool(res.degraded)),
                                               int(res.target_kind == "pedestrian"), int(res.master_fix),
                                               int(res.target_fix), _finite(res.latency_s * 1e3),
                                               _ttc_value(res.ttc_s) if kin else None, int(res.reason_side),
                                               _reason_raw(res.target_reason))))]
        if kin:
            r, v, a, att, sd = (res.rel_pos_body_m.tolist(), res.rel_vel_body_mps.tolist(),
                                res.rel_acc_body_mps2.tolist(), res.rel_rpy_rad.tolist(), res.rel_pos_sd_m.tolist())
            for kind, values in (
                    ("POS", (c, r[0], r[1])),
                    ("RANGE", (c, res.range_m, r[2], res.range_sd_m)),
                    ("VEL", (c, v[0], v[1], _finite(res.closing_speed_mps))),
                    ("GAP", (c, _finite(res.longitudinal_m), _finite(res.lateral_m), _deg(res.bearing_rad))),
                    ("ATT", (c, _deg(att[0]), _deg(att[1]), _deg(att[2]))),
                    ("ACC", (c, a[0], a[1], a[2])),
                    ("SIGMA", (c, sd[0], sd[1], sd[2], _deg(res.rel_yaw_sd_rad)))):
                packer = pk[kind]
                frames.append(frame(packer.frame_id, packer.pack(values)))
        frames.append(self.id_frame(res.target_id, slot, c, id_part))
        return frames

    def lane_frames(self, ids: Sequence[int], lateral_m: Sequence[float],
                    lateral_speed_mps: Sequence[float]) -> list:
        """One LANE frame per lane line (index, signed lateral distance, lateral speed)."""
        c = self._scene_counter & 0xF
        pk = self._scene["LANE"]
        return [self._frame(pk.frame_id, pk.pack((c, int(i) & 0xFF, _finite(d), _finite(s))))
                for i, d, s in zip(ids, lateral_m, lateral_speed_mps)]

    def object_frames(self, ids: Sequence[int], distance_m: Sequence[float], bearing_rad: Sequence[float],
                      ttc_s: Sequence[float | None]) -> list:
        """One OBJECT frame per static object (index, distance to nearest edge, bearing, TTC)."""
        c = self._scene_counter & 0xF
        pk = self._scene["OBJECT"]
        return [self._frame(pk.frame_id, pk.pack((c, int(i) & 0xFF, _finite(d), math.degrees(_finite(b)),
                                                  _ttc_value(t))))
                for i, d, b, t in zip(ids, distance_m, bearing_rad, ttc_s)]

    def master_frames(self, status: Mapping[str, Any], counter: int = 0) -> list:
        """MASTER_STATUS and MASTER_SIGMA frames of a master status (keys: see ``send_master_status``)."""
        c = counter & 0xF
        fix = status.get("master_fix")
        heading = status.get("heading_valid")
        synced = status.get("clock_synced")
        offset = status.get("clock_offset_s")
        n = status.get("n_targets")
        sd = status.get("pos_sd_m")
        yaw_sd = status.get("yaw_sd_rad")
        if yaw_sd is None and status.get("att_sd_rad") is not None:
            yaw_sd = status["att_sd_rad"][2]
        sd = [None, None, None] if sd is None else [float(x) for x in sd]
        ms, sg = self._scene["MASTER_STATUS"], self._scene["MASTER_SIGMA"]
        return [self._frame(ms.frame_id, ms.pack((
                    c, int(FixStatus.NONE if fix is None else fix), int(bool(heading)),
                    min(len(self.slots) if n is None else int(n), N_SLOTS),
                    0 if synced is None else 1 if synced else 2, float(status["t_gps_s"]) % 604800.0,
                    None if offset is None else offset * 1e3))),
                self._frame(sg.frame_id, sg.pack((c, *sd, None if yaw_sd is None else math.degrees(yaw_sd),
                                                  _reason_raw(status.get("reason") or 0))))]

    # -- sending -----------------------------------------------------------------------
    def _send(self, frames: list) -> int:
        send = self.bus.send
        for f in frames:
            send(f)
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
        frames = self.frames_for_result(res, slot, self._counter[slot], self._id_part[slot])
        self._counter[slot] = (self._counter[slot] + 1) & 0xF
        self._id_part[slot] = (self._id_part[slot] + 1) % ID_PARTS
        return self._send(frames)

    def send_lanes(self, ids: Sequence[int], lateral_m: Sequence[float], lateral_speed_mps: Sequence[float]) -> int:
        """Send one LANE frame per lane line (``lane_frames``) as one scene update; returns the frames sent."""
        n = self._send(self.lane_frames(ids, lateral_m, lateral_speed_mps))
        self._scene_counter += 1
        return n

    def send_objects(self, ids: Sequence[int], distance_m: Sequence[float], bearing_rad: Sequence[float],
                     ttc_s: Sequence[float | None]) -> int:
        """Send one OBJECT frame per static object (``object_frames``); returns the frames sent."""
        return self._send(self.object_frames(ids, distance_m, bearing_rad, ttc_s))

    def send_scene(self, scene_result: Any) -> int:
        """Send a ``scene.SceneResult``: one LANE frame per lane line, one OBJECT frame per object, all
        with the same counter."""
        n = self._send(self.lane_frames(scene_result.lane_index, scene_result.lane_lateral_m,
                                        scene_result.lane_lateral_speed_mps))
        n += self.send_objects(range(len(scene_result.object_ids)), scene_result.object_distance_m,
                               scene_result.object_bearing_rad, scene_result.object_ttc_s)
        self._scene_counter += 1
        return n

    def send_master_status(self, status: Mapping[str, Any]) -> int:
        """Send MASTER_STATUS + MASTER_SIGMA (same counter); returns 2.

        ``status`` keys (all optional but ``t_gps_s``): ``t_gps_s`` [GPS s], ``master_fix``
        (FixStatus code), ``heading_valid`` (bool), ``pos_sd_m`` (N, E, D), ``yaw_sd_rad`` (or
        ``att_sd_rad``), ``clock_synced`` (bool), ``clock_offset_s``, ``n_targets`` (default: the
        targets holding a slot), ``reason`` (the master filter's FilterReason code). A missing value goes out as its "n/a"/"unknown" code.
        """
        n = self._send(self.master_frames(status, self._master_counter))
        self._master_counter = (self._master_counter + 1) & 0xF
        return n

    def close(self) -> None:
        """Shut the bus down if this object opened it."""
        if self._own_bus:
            self.bus.shutdown()

    def __enter__(self) -> "CanOutput":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


# ----------------------------------------------------------------------------- decoding
def _special_codes(frame_id: int) -> dict:
    """{signal name: raw code} of the "none"/"n/a" codes of a frame of the v2xpos layout."""
    for _, (fid, prefix, sigs) in SCENE_MESSAGES.items():
        if fid == frame_id:
            return _specials(sigs, prefix)
    if ID_STATUS <= frame_id < ID_LANE:
        slot = (frame_id - ID_STATUS) % N_SLOTS
        for base, sigs in TARGET_MESSAGES.values():
            if base + slot == frame_id:
                return _specials(sigs, f"T{slot:02d}_")
    return {}


def decode_frames(frames: Iterable[can.Message], db: Any = None) -> dict:
    """Decode frames with the DBC into {"targets", "lanes", "objects", "master", "unknown", "malformed",
    "e2e_errors"}.

    targets: {slot: {signal: value}} merged over a slot's frames (later frames win), with
    ``TargetId`` once the id's parts up to the last one arrived; lanes/objects: {index: {...}};
    master: the MASTER_STATUS and MASTER_SIGMA signals; "none"/"n/a" codes -> None; unknown ids are
    counted; frames of the wrong length are skipped and described in "malformed"; frames whose E2E
    CRC does not match are described in "e2e_errors" and skipped.
    """
    db = db if db is not None else load_dbc()
    out: dict = {"targets": {}, "lanes": {}, "objects": {}, "master": {}, "unknown": 0, "malformed": [],
                 "e2e_errors": []}
    id_bytes: dict[int, dict[int, bytes]] = {}
    id_last: dict[int, int] = {}
    for f in frames:
        fid = f.arbitration_id
        try:
            msg = db.get_message_by_frame_id(fid)
        except KeyError:
            out["unknown"] += 1
            continue
        data = bytes(f.data)
        if len(data) != msg.length:
            out["malformed"].append(f"id 0x{fid:03X}: {len(data)} data bytes, expected {msg.length}")
            continue
        if is_e2e_protected(fid) and data[0] != e2e_crc(data, fid):
            out["e2e_errors"].append(f"id 0x{fid:03X}: CRC 0x{data[0]:02X}, expected 0x{e2e_crc(data, fid):02X}")
            continue
        raw = msg.decode(data, decode_choices=False, scaling=False)
        vals = msg.decode(data, decode_choices=False)
        specials = _special_codes(fid)
        vals = {k: (None if k in specials and raw[k] == specials[k] else v) for k, v in vals.items()}
        if ID_STATUS <= fid < ID_LANE:
            slot = (fid - ID_STATUS) % N_SLOTS
            prefix = f"T{slot:02d}_"
            d = out["targets"].setdefault(slot, {})
            d.update({k[len(prefix):]: v for k, v in vals.items()})
            if fid - slot == ID_ID:
                part = int(raw[prefix + "IdPart"])
                id_bytes.setdefault(slot, {})[part] = int(raw[f"{prefix}IdText{part}"]).to_bytes(6, "little")
                if raw[prefix + "IdLast"]:
                    id_last[slot] = part
                parts = id_bytes[slot]
                if slot in id_last and all(p in parts for p in range(id_last[slot] + 1)):
                    text = b"".join(parts[p] for p in range(id_last[slot] + 1)).rstrip(b"\0")
                    d["TargetId"] = text.decode(errors="replace")
        elif fid == ID_LANE:
            d = {k[2:]: v for k, v in vals.items()}
            out["lanes"][int(d["LaneIndex"])] = d
        elif fid == ID_OBJECT:
            d = {k[2:]: v for k, v in vals.items()}
            out["objects"][int(d["ObjectIndex"])] = d
        elif fid in (ID_MASTER, ID_MASTER_SIGMA):
            out["master"].update({k.split("_", 1)[1]: v for k, v in vals.items() if not k.endswith("_CRC")})
    return out


__all__ = ["DBC_PATH", "N_SLOTS", "CanBusError", "CanOutput", "FramePacker", "SlotTable", "decode_frames",
           "e2e_crc", "data_id", "generate_dbc", "load_dbc", "open_bus", "FRAMES_PER_KINEMATIC_UPDATE",
           "FRAMES_PER_STATUS_UPDATE"]
