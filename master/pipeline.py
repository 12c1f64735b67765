"""The master's per-message pipeline as a plain class (no I/O of its own), so that the zenoh service,
recording replay and fuzzing all drive exactly the same code.

For every received slave payload ``handle(payload, key, master, t_now_gps_s, t_arrival_wall_s)``:

1. validate: ``v2xpos.wire.decode_state`` (schema, ranges, finite numbers), the key's vehicle id
   equals the body's, the fleet matches, the vehicle is known (``known_vehicles``; empty = any),
   optional admission control (``authenticator.check(msg, now)``: signatures, replay windows);
   per vehicle the sequence number must increase (equal = ``duplicate``, lower =
   ``out_of_order``, except a restarted sender: far lower with a later time) and so must the time of
   validity (``out_of_order``). These read-only checks come before the authenticator, and the track
   is only updated after it, so forged traffic cannot move the windows.
   Rejections are counted by reason, globally and per vehicle (the id is taken from the key when
   the body cannot be decoded), and never touch another target's state.
2. staleness: age = master GPS time now - slave time of validity; age > ``timeout_s`` gives
   TIMEOUT and no kinematics (``v2xpos.relative.check_latency``). The clocks are compared too
   (``ClockComparison``): a sender that stamps its session GPS time at publishing lets the master
   tell "late" from "on another clock".
3. gate + compensate + transform: ``v2xpos.relative.evaluate_target`` with the master's latest
   filter state (time t_m): fix gate (RTK fixed/float on both sides), CTRA prediction of the slave
   over t_m - t_slave, operator T into the master body frame, range/bearing/gap/TTC from the
   configured master measurement point to the target outline.
4. degrade flag from IMU grading (``degraded_vehicles``), sequence number, fleet/master ids.
5. outputs: every sink's ``write(result)`` (CAN, UDP, zenoh republish, recorder), then the
   ``flush()`` of the sinks that have one (UDP: one datagram with the pending target records).
   Inside ``with pipeline.batch():`` the flush happens once at the end of the block, so a dispatch
   batch of n messages costs one datagram (one system call) instead of n.

``process_scene(scene, master)`` evaluates the surveyed lanes / points / polygons (V2L / V2X) for
the master state and sends them to the sinks (CAN LANE/OBJECT frames, UDP lane/object records).

``tick(t_now_gps_s)`` reports targets that went silent: NO_DATA for a known vehicle never heard,
TIMEOUT once the last message is older than the timeout (status only; never kinematics).

Timing: ``pipeline_ms`` = wall time after the flush of the sinks (all outputs written) minus the
arrival stamp; ``e2e_ms`` = the same instant minus the slave's publish stamp ``t_sent_wall_s``
(same machine).
"""
from __future__ import annotations

import math
import re
import time
from array import array
from collections import Counter, defaultdict, deque
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any, Callable, Iterator, Protocol

import numpy as np

from v2xpos.relative import check_latency, evaluate_target
from v2xpos.stats import LatencyHistogram
from v2xpos.types import FixStatus
from v2xpos.wire import (FixSide, RelativeResult, StateMessage, TargetStatus, WireError, decode_state, reason_name,
                         reason_text)

REJECT_MALFORMED = "malformed"
REJECT_KEY_MISMATCH = "key_mismatch"
REJECT_WRONG_FLEET = "wrong_fleet"
REJECT_UNKNOWN_VEHICLE = "unknown_vehicle"
REJECT_DUPLICATE = "duplicate"
REJECT_OUT_OF_ORDER = "out_of_order"
REJECT_SELF = "own_id"
RESTART_SEQ_GAP = 1024
"""A sequence number this far below the last one, with a later time of validity, is a restarted
sender (its counter began again), not a replay or reordering."""
LATENCY_WINDOW = 4096
"""Latency samples kept exactly for windowed percentiles; whole-run percentiles come from a
constant-memory log histogram (``v2xpos.stats``), so memory stays bounded on any run length."""

_STATUS_NAME = {s: s.name.lower() for s in TargetStatus}
_KEY_RE = re.compile(r"^v2xpos/([^/]+)/vehicle/([^/]+)/state$")


class Sink(Protocol):
    """An output stage: ``write(result)`` sends one RelativeResult somewhere (or queues it: a sink
    may also have ``flush()``, called after the results of one batch were written)."""

    def write(self, result: RelativeResult) -> None: ...


@dataclass
class PipelineConfig:
    """Master pipeline settings.

    timeout_s: staleness limit (default 0.2 s). future_tolerance_s: allowed negative age.
    measurement_point_m: master measurement point in the master body frame (e.g. front bumper).
    known_vehicles: accepted target ids (empty = any id). evaluate_uncompensated: also transform
    the unpredicted target (for the demo's comparison; costs one more transform per message).
    record: keep one row per result for the report (``records``).
    Validity limits (docs/integrity.md): max_sigma_h_m / max_sigma_yaw_deg: a result whose predicted
    1-sigma horizontal position (sqrt(sd_x^2 + sd_y^2)) or relative yaw (vehicle targets) exceeds
    them is SIGMA_EXCEEDED; require_consistency: a result is INCONSISTENT while either vehicle's filter
    has a failed consistency test not yet released (flag 4), UNVERIFIED while either is not verified,
    i.e. its protection level is above its limit (flag 8; ``v2xpos.ins.consistency``); the result
    says which vehicle (``reason_side``) and carries both filters' reasons.
    max_clock_disagreement_s: a target whose clock differs from the master's by more than this
    (``ClockComparison``) is a clock alarm: its computed results are CLOCK_UNSYNCED (both sides, since
    one comparison cannot say which clock is wrong), its silent ones say so in the status.
    """
    fleet: str = "demo"
    master_id: str = "ego"
    timeout_s: float = 0.200
    future_tolerance_s: float = 0.020
    measurement_point_m: tuple = (0.0, 0.0, 0.0)
    known_vehicles: tuple = ()
    evaluate_uncompensated: bool = False
    record: bool = False
    max_sigma_h_m: float = 0.10
    max_sigma_yaw_deg: float = 1.0
    require_consistency: bool = True
    max_clock_disagreement_s: float = 0.05


CLOCK_WINDOW_S = 10.0
"""Window of the clock comparison's minimum [s of master time]."""


class ClockComparison:
    """The target's clock against the master's, from the messages' send stamps.

    A sender stamps its session GPS time ``t_sent_gps_s`` when it publishes. At arrival the master
    reads its own session GPS time; the difference ``d = t_master_at_arrival - t_sent_gps_s`` is
    (master clock - sender clock) + transit. The transit is positive and its minimum over many
    messages is close to the link's floor (loopback: < 1 ms; a V2V link: a few ms), so the
    running minimum of ``d`` over ``CLOCK_WINDOW_S`` estimates the clock difference, biased by that
    floor (the NTP lower-envelope argument, Mills, RFC 5905 section 10). One comparison cannot say
    which clock is wrong: each service checks its own clock against GNSS time (its status)."""

    def __init__(self, window_s: float = CLOCK_WINDOW_S):
        self.window_s = float(window_s)
        self._q: deque = deque()       # (t_master, d) with increasing d: the window's minimum first
        self.samples = 0

    def add(self, t_master_s: float, t_sent_gps_s: float) -> None:
        d = t_master_s - t_sent_gps_s
        q = self._q
        while q and q[-1][1] >= d:
            q.pop()
        q.append((t_master_s, d))
        while q[0][0] < t_master_s - self.window_s:
            q.popleft()
        self.samples += 1

    @property
    def offset_s(self) -> float:
        """Master clock minus the target's (+ the transit floor) [s]; NaN before any stamp."""
        return self._q[0][1] if self._q else math.nan


@dataclass
class TargetTrack:
    """What the master knows of one target."""
    target_id: str
    kind: str = "vehicle"
    last_seq: int = -1
    last_t_gps_s: float = -math.inf
    status: TargetStatus = TargetStatus.NO_DATA
    fix_side: FixSide = FixSide.NONE
    last_result: RelativeResult | None = None
    accepted: int = 0
    restarts: int = 0
    results: Counter = field(default_factory=Counter)
    rejected: Counter = field(default_factory=Counter)
    clock: ClockComparison = field(default_factory=ClockComparison)
    last_message: StateMessage | None = None


RECORD_FIELDS = ("t_gps_s", "t_slave_gps_s", "status", "latency_s", "pipeline_ms", "e2e_ms",
                 "rel_pos_x", "rel_pos_y", "rel_pos_z", "rel_vel_x", "rel_vel_y", "rel_vel_z",
                 "range_m", "unc_pos_x", "unc_pos_y", "unc_pos_z", "fix_side", "ttc_s", "gap_m", "slave_fix",
                 "t_out_wall_s")


class MasterPipeline:
    """validate -> stale -> gate -> compensate -> transform -> outputs (see module docstring)."""

    def __init__(self, config: PipelineConfig, sinks: list[Sink] | None = None,
                 authenticator: Any = None, clock_wall: Callable[[], float] = time.time):
        self.config = config
        self.sinks: list[Sink] = list(sinks or [])
        self.authenticator = authenticator
        self.clock_wall = clock_wall
        self.tracks: dict[str, TargetTrack] = {}
        self.rejected: Counter = Counter()
        self.degraded_vehicles: set[str] = set()
        self.master_fix = FixStatus.NONE
        """Fix of the master state of the last handled message (or given to ``tick``)."""
        self.seq = 0
        self.processed = 0
        self.pipeline_ms = LatencyHistogram(recent=LATENCY_WINDOW)
        self.e2e_ms = LatencyHistogram(recent=LATENCY_WINDOW)
        # one flat float array per target (RECORD_FIELDS per row): no object per row for the
        # garbage collector to scan (a list of tuples made each young-generation collection cost
        # ~20 ms at 6,400 results/s)
        self.records: dict[str, array] = defaultdict(lambda: array("d"))
        self.scene_updates = 0
        self.last_scene = None
        self.last_scene_t_gps_s = math.nan
        self.scene_records: list[tuple] = []
        self._mpoint = np.asarray(config.measurement_point_m, dtype=float)
        self._known = set(config.known_vehicles)
        self._batching = False
        self._unflushed: list[tuple] = []     # (result, message, arrival wall time, uncompensated)
        self.master_time_ok = True            # the master's clock within its bound of GNSS time
        for vid in dict.fromkeys(config.known_vehicles):   # configured order, not set order:
            self.tracks[vid] = TargetTrack(vid)             # tick() emits NO_DATA in this order

    def warm_up(self) -> None:
        """Compile (or load from numba's cache) the compensation kernel before the first message."""
        from v2xpos.relative_jit import warm_up
        warm_up()

    # ------------------------------------------------------------------ validation
    def _reject(self, reason: str, vehicle_id: str | None) -> None:
        self.rejected[reason] += 1
        if vehicle_id is not None and vehicle_id in self.tracks:
            self.tracks[vehicle_id].rejected[reason] += 1

    def _admit(self, payload: bytes, key: str | None, t_now_gps_s: float,
               t_arrival_wall_s: float, signature_valid: bool | None = None) -> StateMessage | None:
        key_id = None
        key_fleet = None
        if key is not None:
            m = _KEY_RE.match(key)
            if m:
                key_fleet, key_id = m.group(1), m.group(2)
        try:
            msg = decode_state(payload)
        except WireError:
            self._reject(REJECT_MALFORMED, key_id)
            return None
        vid = msg.vehicle_id
        if key_id is not None and key_id != vid:
            self._reject(REJECT_KEY_MISMATCH, key_id)
            return None
        if msg.fleet != self.config.fleet or (key_fleet is not None and key_fleet != self.config.fleet):
            self._reject(REJECT_WRONG_FLEET, None)
            return None
        if vid == self.config.master_id:
            self._reject(REJECT_SELF, None)
            return None
        if self._known and vid not in self._known:
            self._reject(REJECT_UNKNOWN_VEHICLE, None)
            return None
        track = self.tracks.get(vid)
        if track is None:
            track = self.tracks[vid] = TargetTrack(vid)
        restart = msg.seq < track.last_seq - RESTART_SEQ_GAP and msg.t_gps_s > track.last_t_gps_s
        if msg.seq == track.last_seq:
            self._reject(REJECT_DUPLICATE, vid)
            return None
        if (msg.seq < track.last_seq and not restart) or msg.t_gps_s <= track.last_t_gps_s:
            self._reject(REJECT_OUT_OF_ORDER, vid)
            return None
        if self.authenticator is not None:
            t_arr_gps = t_now_gps_s - (self.clock_wall() - t_arrival_wall_s)
            reason = self.authenticator.check(msg, t_now_gps_s, t_arr_gps, signature_valid)
            if reason is not None:
                self._reject(reason, vid)
                return None
        if restart:
            track.restarts += 1
        track.last_seq = msg.seq
        track.last_t_gps_s = msg.t_gps_s
        track.kind = msg.kind
        track.accepted += 1
        return msg

    # ------------------------------------------------------------------ main entry
    def handle(self, payload: bytes, key: str | None, master: Any, t_now_gps_s: float,
               t_arrival_wall_s: float | None = None, signature_valid: bool | None = None) -> RelativeResult | None:
        """Run one received payload through the pipeline; returns the result sent (None if rejected).

        master: the master's latest filter state (StateMessage or NavState, time t_m <= now).
        signature_valid: ``MessageAuthenticator.verify_envelope(payload)`` when a receive thread
        already ran it (None: verified here when the message gets that far).
        """
        t_arr = self.clock_wall() if t_arrival_wall_s is None else t_arrival_wall_s
        msg = self._admit(payload, key, t_now_gps_s, t_arr, signature_valid)
        if msg is None:
            return None
        return self.handle_message(msg, master, t_now_gps_s, t_arr)

    def handle_message(self, msg: StateMessage, master: Any, t_now_gps_s: float,
                       t_arrival_wall_s: float) -> RelativeResult:
        """Stages 2-5 for an admitted message."""
        cfg = self.config
        status, age_s = check_latency(t_now_gps_s, msg.t_gps_s, cfg.timeout_s, cfg.future_tolerance_s)
        self.master_fix = FixStatus(master.fix)
        track = self.tracks.get(msg.vehicle_id)
        clock_alarm = False
        if track is not None:
            track.last_message = msg
            if msg.t_sent_gps_s is not None:
                track.clock.add(t_now_gps_s, msg.t_sent_gps_s)
            clock_alarm = self.clock_alarm(track)
        if status != TargetStatus.VALID:
            res = RelativeResult(target_id=msg.vehicle_id, target_kind=msg.kind, status=status,
                                 source_seq=msg.seq, t_gps_s=float(master.t_s), latency_s=age_s,
                                 t_sent_wall_s=msg.t_sent_wall_s, master_fix=self.master_fix,
                                 target_fix=FixStatus(msg.fix))
            if clock_alarm:
                res.reason_side = FixSide.MASTER | FixSide.SLAVE
        else:
            res = evaluate_target(master, msg, self._mpoint, timeout_s=math.inf,
                                  future_tolerance_s=math.inf)
            res.latency_s = age_s
            if res.status == TargetStatus.VALID:
                res.status = self._validity(master, msg, res, clock_alarm)
        res.master_reason = int(getattr(master, "reason", 0))
        res.target_reason = int(msg.reason)
        res.protection_m = float(getattr(master, "protection_m", math.nan)) + float(msg.protection_m)
        res.master_fix = master.fix
        res.target_fix = msg.fix
        unc = None
        if cfg.evaluate_uncompensated and res.status == TargetStatus.VALID:
            # the unpredicted message through the compiled transform (prediction over 0 s: the
            # same position as relative_kinematics(master, msg) to ~1e-8 m, 5x cheaper)
            from v2xpos.relative_jit import evaluate_compiled
            unc = evaluate_compiled(master, msg, 0.0, self._mpoint, 0.0, 0.0, res.t_gps_s).rel_pos_body_m
        return self._emit(res, msg, t_arrival_wall_s, unc)

    def clock_alarm(self, track: TargetTrack) -> bool:
        """True while the target's clock differs from the master's beyond the configured bound."""
        return abs(track.clock.offset_s) > self.config.max_clock_disagreement_s

    def _validity(self, master: Any, msg: StateMessage, res: RelativeResult, clock_alarm: bool = False) -> TargetStatus:
        """A computed result is VALID only when both vehicles' attitude is determined (a heading
        pending at a standstill start turns every bearing into a guess), both clocks are on GNSS
        time and agree with each other, both filters pass their own consistency tests
        (INCONSISTENT otherwise) and are verified (UNVERIFIED otherwise: the protection level of
        their fault-tolerant solution bounds what an undeclared error could do, within the
        filter's limit: ``v2xpos.ins.consistency``), and the predicted sigma is within the
        configured limits; otherwise the status says which, in this order, and ``reason_side``
        which vehicle (the kinematics stay in the result). docs/integrity.md gives the reasoning."""
        cfg = self.config
        checks = [(TargetStatus.ATTITUDE_UNCERTAIN, getattr(master, "attitude_ok", True), msg.attitude_ok),
                  (TargetStatus.CLOCK_UNSYNCED, self.master_time_ok and not clock_alarm, msg.time_ok and not clock_alarm)]
        if cfg.require_consistency:
            checks += [(TargetStatus.INCONSISTENT, getattr(master, "consistent", True), msg.consistent),
                       (TargetStatus.UNVERIFIED, getattr(master, "verified", True), msg.verified)]
        for status, master_ok, target_ok in checks:
            if not (master_ok and target_ok):
                res.reason_side = (FixSide.NONE if master_ok else FixSide.MASTER) | (
                    FixSide.NONE if target_ok else FixSide.SLAVE)
                return status
        sd = res.rel_pos_sd_m
        sigma_h = math.hypot(float(sd[0]), float(sd[1]))
        if not sigma_h <= cfg.max_sigma_h_m:
            return TargetStatus.SIGMA_EXCEEDED
        # a pedestrian's yaw (its walking direction) is no reference quantity: only a vehicle's is limited
        if msg.kind == "vehicle" and not math.degrees(res.rel_yaw_sd_rad) <= cfg.max_sigma_yaw_deg:
            return TargetStatus.SIGMA_EXCEEDED
        return TargetStatus.VALID

    def _emit(self, res: RelativeResult, msg: StateMessage | None, t_arr: float,
              unc: np.ndarray | None = None) -> RelativeResult:
        cfg = self.config
        self.seq += 1
        res.seq = self.seq
        res.fleet = cfg.fleet
        res.master_id = cfg.master_id
        res.degraded = res.target_id in self.degraded_vehicles
        track = self.tracks.get(res.target_id)
        if track is not None:
            track.status = res.status
            track.fix_side = res.fix_side
            track.last_result = res
            track.results[_STATUS_NAME[res.status]] += 1
        for sink in self.sinks:
            sink.write(res)
        self._unflushed.append((res, msg, t_arr, unc))
        if not self._batching:
            self.flush()
        return res

    @contextmanager
    def batch(self) -> Iterator[None]:
        """Results produced inside the block are flushed together at its end (see module docstring,
        step 5); their pipeline and end-to-end times end at that flush."""
        self._batching = True
        try:
            yield
        finally:
            self._batching = False
            self.flush()

    def flush(self) -> None:
        """Flush the sinks that queue (``flush()``), then stamp the pending results as written."""
        pending = self._unflushed
        if not pending:
            return
        for sink in self.sinks:
            flush = getattr(sink, "flush", None)
            if flush is not None:
                flush()
        t_done = self.clock_wall()
        record = self.config.record
        for res, msg, t_arr, unc in pending:
            self.processed += 1
            pipe_ms = (t_done - t_arr) * 1e3
            e2e = math.nan if res.t_sent_wall_s is None else (t_done - res.t_sent_wall_s) * 1e3
            if msg is not None:
                self.pipeline_ms.append(pipe_ms)
                if not math.isnan(e2e):
                    self.e2e_ms.append(e2e)
            if record:
                self._record(res, msg, pipe_ms, e2e, unc, t_done)
        pending.clear()

    def _record(self, res: RelativeResult, msg: StateMessage | None, pipe_ms: float, e2e: float,
                unc: np.ndarray | None, t_done_wall_s: float) -> None:
        rows = self.records[res.target_id]
        p, v = res.rel_pos_body_m, res.rel_vel_body_mps
        p = p.tolist() if type(p) is np.ndarray else p
        v = v.tolist() if type(v) is np.ndarray else v
        u = (math.nan, math.nan, math.nan) if unc is None else unc.tolist() if type(unc) is np.ndarray else unc
        rows.extend((res.t_gps_s, math.nan if msg is None else msg.t_gps_s, int(res.status), res.latency_s,
                     pipe_ms, e2e, p[0], p[1], p[2], v[0], v[1], v[2], res.range_m, u[0], u[1], u[2],
                     int(res.fix_side), math.nan if res.ttc_s is None else res.ttc_s, res.gap_m,
                     math.nan if msg is None else int(msg.fix), t_done_wall_s))

    # ------------------------------------------------------------------ scene (V2L / V2X)
    def process_scene(self, scene: Any, master: Any) -> Any:
        """Evaluate the surveyed scene (``v2xpos.scene.Scene``) for the master state from the
        measurement point and send it to every sink that has ``write_scene``."""
        res = scene.evaluate(master, self._mpoint)
        self.scene_updates += 1
        self.last_scene = res
        self.last_scene_t_gps_s = float(master.t_s)
        if self.config.record:
            self.scene_records.append((float(master.t_s), *map(float, res.lane_lateral_m),
                                       *map(float, res.object_distance_m)))
        for sink in self.sinks:
            write = getattr(sink, "write_scene", None)
            if write is not None:
                write(res, float(master.t_s), self.scene_updates)
        return res

    def scene_summary(self) -> dict | None:
        r = self.last_scene
        if r is None:
            return None
        fin = (lambda x: None if not np.isfinite(x) else float(x))
        return {"updates": self.scene_updates, "t_gps_s": self.last_scene_t_gps_s,
                "lanes": {str(i): {"lateral_m": fin(d), "lateral_speed_mps": fin(v)}
                          for i, d, v in zip(r.lane_ids, r.lane_lateral_m, r.lane_lateral_speed_mps)},
                "objects": {str(i): {"distance_m": fin(d), "bearing_deg": fin(math.degrees(b)), "ttc_s": fin(t)}
                            for i, d, b, t in zip(r.object_ids, r.object_distance_m, r.object_bearing_rad,
                                                  r.object_ttc_s)}}

    # ------------------------------------------------------------------ silence
    def tick(self, t_now_gps_s: float, master_t_gps_s: float | None = None,
             master_fix: FixStatus | None = None) -> list[RelativeResult]:
        """Status-only results for targets without fresh data: NO_DATA (never heard) or TIMEOUT
        (last message older than the timeout). Call a few times per second. ``master_fix``: the
        master's current fix (default: the one of the last handled message); the target's fix is
        that of its last result (NONE when never heard)."""
        out = []
        t_m = t_now_gps_s if master_t_gps_s is None else master_t_gps_s
        if master_fix is not None:
            self.master_fix = FixStatus(master_fix)
        for track in self.tracks.values():
            if track.last_seq < 0:
                status, lat = TargetStatus.NO_DATA, math.nan
            else:
                lat = t_now_gps_s - track.last_t_gps_s
                if lat <= self.config.timeout_s:
                    continue
                status = TargetStatus.TIMEOUT
            res = RelativeResult(target_id=track.target_id, target_kind=track.kind, status=status,
                                 source_seq=max(track.last_seq, 0), t_gps_s=t_m, latency_s=lat,
                                 master_fix=self.master_fix,
                                 target_fix=FixStatus.NONE if track.last_result is None else track.last_result.target_fix)
            if track.last_message is not None:
                res.target_reason = int(track.last_message.reason)
            if self.clock_alarm(track):
                res.reason_side = FixSide.MASTER | FixSide.SLAVE
            out.append(self._emit(res, None, self.clock_wall()))
        return out

    # ------------------------------------------------------------------ summaries
    def summary(self, window: int | None = None) -> dict:
        """Counters and per-target status for monitors (JSON-serialisable); latency percentiles over
        the last ``window`` messages (exact), or over the whole run (None; log-histogram, 1.2 %)."""
        def pct(a: LatencyHistogram, q: float) -> float | None:
            return a.percentile(q, window)
        return {
            "processed": self.processed, "rejected": dict(self.rejected),
            "pipeline_ms_p50": pct(self.pipeline_ms, 50), "pipeline_ms_p99": pct(self.pipeline_ms, 99),
            "e2e_ms_p50": pct(self.e2e_ms, 50), "e2e_ms_p99": pct(self.e2e_ms, 99),
            "scene": self.scene_summary(),
            "targets": {vid: self._target_summary(vid, t) for vid, t in self.tracks.items()},
        }

    def _target_summary(self, vid: str, t: TargetTrack) -> dict:
        res = t.last_result
        clock_s = t.clock.offset_s
        return {"kind": t.kind, "status": t.status.name.lower(), "fix_side": int(t.fix_side),
                "accepted": t.accepted, "restarts": t.restarts, "results": dict(t.results),
                "rejected": dict(t.rejected), "degraded": vid in self.degraded_vehicles,
                "last": _result_brief(res),
                "reason_side": None if res is None else int(res.reason_side),
                "master_reason": None if res is None else reason_name(res.master_reason),
                "target_reason": None if res is None else reason_name(res.target_reason),
                "reason": None if res is None else reason_text(res),
                "protection_m": None if res is None or not math.isfinite(res.protection_m) else res.protection_m,
                "clock": {"offset_ms": None if math.isnan(clock_s) else clock_s * 1e3,
                          "alarm": bool(self.clock_alarm(t)), "samples": t.clock.samples}}

    def records_arrays(self) -> dict[str, np.ndarray]:
        """Recorded rows per target as (N, len(RECORD_FIELDS)) float arrays."""
        return {vid: np.frombuffer(rows, dtype=np.float64).reshape(-1, len(RECORD_FIELDS)).copy()
                for vid, rows in self.records.items()}


def _result_brief(res: RelativeResult | None) -> dict | None:
    if res is None:
        return None
    valid = res.status == TargetStatus.VALID
    f = (lambda x: float(x) if valid and x is not None and math.isfinite(x) else None)
    return {"t_gps_s": res.t_gps_s, "latency_ms": None if not math.isfinite(res.latency_s) else res.latency_s * 1e3,
            "range_m": f(res.range_m), "bearing_deg": f(math.degrees(res.bearing_rad)) if valid else None,
            "lon_m": f(res.longitudinal_m), "lat_m": f(res.lateral_m), "gap_m": f(res.gap_m),
            "ttc_s": f(res.ttc_s), "closing_mps": f(res.closing_speed_mps)}
