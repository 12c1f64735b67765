"""``InsDriver``: the one event loop that feeds ``InsFilter``.

Every path that runs the filter -- ``v2xpos replay`` and ``calibrate``'s replays
(``replay_engine.run_replay``), the ``recording``, ``device`` and ``sim`` sources, the grading's
fused path -- turns its input into the events below and hands them to this driver; nothing else
calls the filter's ``process_imu`` / ``update_*`` in a loop.

Events and their time of validity (GPS seconds), on the filter's *current* estimates:

==============  ======================================  =====================================
event           tag                                     valid at
==============  ======================================  =====================================
IMU sample      stamp ``s`` (the IMU clock on GPS time)  ``s + dt`` (``fx.imu_time_offset_s``:
                                                        the filter's own label of its state)
GNSS epoch      receiver tag ``t`` (position,           ``t - lat`` (``fx.gnss_latency_s``)
                velocity, fix)
heading         receiver tag ``t`` (dual antenna)       ``t - lat`` (the same receiver epoch)
wheel speed     ``t``                                   ``t``
marks           ``t`` (replay's outage ends and         ``t``; an outage end ``t - lat`` (it
                outputs, scheduled constraints)         marks the return of the GNSS)
==============  ======================================  =====================================

Ordering rule. Events are processed in the order of (time of validity, rank), ranks
IMU < wheel < outage end < GNSS < heading < output < constraint. A measurement is applied after
every IMU sample valid at or before it and before the first later one: the strapdown predicts to
the last sample at or before its time of validity, then the measurement corrects, the shape of
robot_localization's ``processMeasurement`` (predict to the measurement's stamp, then correct;
Moore & Stouch 2014, "A generalized extended Kalman filter implementation for the Robot Operating
System"). What is left of the gap (less than one IMU interval) is carried by the measurement
models (``updates``: ``gap``). **Equal times**: the IMU sample first, then the measurement -- the
sample brings the state exactly to that time, so a GNSS epoch valid at an IMU sample's time is
applied with gap 0 after that sample, and one valid a microsecond earlier before it. The delays
are read from the filter right after the previous measurement was applied (they are estimated
online), and the IMU samples before the next measurement are fixed with them (``_plan``): how the
IMU is cut into batches, how far a source advances per call, or whether a late event made the
driver process its history again, never changes what the filter does.

Output states (``emit_states``): one ``NavState`` per IMU sample once the filter is initialised,
stamped with the filter's time label ``s + dt`` -- the time it is valid for -- after every
measurement valid at that same time that has arrived; a label that would not be later than the
previous one (the time-offset estimate moved back) gives no state and is counted.

Offline and live are one loop. A whole recording pushed at once (``complete=True``: replay,
calibrate, the ``recording`` source) and events pushed as they arrive (``device``, ``sim``) are
processed alike: an IMU sample as soon as no earlier measurement waits; a measurement as soon as
the IMU beyond its time of validity is there (or the input has ended; live, or after
``max_wait_s`` without any IMU sample, at the state it has, counted ``applied_without_imu``).
Live (``reorder_window_s`` given: the ``device`` source) a measurement that arrives after the IMU
beyond its time was processed -- a GNSS solution reaches the host 20-80 ms after its epoch -- is
put in its place: the driver keeps snapshots of the filter over the last ``reorder_window_s`` and
the events processed since, restores the last snapshot before the late event's place and
processes the events again in order (robot_localization's ``smooth_lagged_data``). States already returned
stay as they were (the best estimate when returned); the following ones include the late event.
So a live state leaves as soon as its IMU sample arrives, and only what actually arrives out of
order is reordered. An event older than the window (without a window, any late event), or not
newer than the previous event of its own sensor, is counted and rejected, never applied out of
order; so is an IMU sample with a non-finite stamp or one not after the previous sample.
``counts`` says what happened to each input.

Start: the filter aligns itself from the data (``InsFilter``: coarse levelling, then a static
start or the GNSS course), or starts from a declared state through :meth:`InsDriver.initialize`
(a simulator's truth, the grading's in-motion alignment) -- one path either way. The numba kernels
are compiled (or their cache loaded) by :func:`warm_up` before real time starts.

Hooks (``DriverHook``) see the epochs, marks, updates and states; in live mode they see the
events processed again after a reorder a second time (``on_reorder`` first).
"""
from __future__ import annotations

import copy
import math
from collections import deque
from typing import Any, Callable, Sequence

import numpy as np

from v2xpos.types import Dataset, FixStatus, NavState

from .filter import InsFilter
from .updates import UpdateResult

# event kinds (measurement queues); their number is their rank at equal times of validity (IMU: 0)
IMU = 0
WHEEL, OUTAGE_END, GNSS, HEADING, OUTPUT, CONSTRAINT = range(1, 7)
KIND_NAMES = {IMU: "imu", WHEEL: "wheel", OUTAGE_END: "outage_end", GNSS: "gnss", HEADING: "heading",
              OUTPUT: "output", CONSTRAINT: "constraint"}
DELAYED_LIKE_GNSS = frozenset((OUTAGE_END, GNSS, HEADING))
"""Kinds whose time of validity is the tag minus the GNSS latency estimate."""
SENSOR_KINDS = frozenset((WHEEL, GNSS, HEADING))
"""Kinds that must arrive strictly newer than the previous event of the same kind."""

REORDER_WINDOW_S = 0.5
"""Default of how far back (IMU stamps) a live event may still be put in its place: a receiver's
20-80 ms, plus what an IMU time-offset estimate still far from converged (prior sd 0.3 s) moves
the place of a GNSS epoch among the IMU samples."""
SNAPSHOT_EVERY_S = 0.05
"""Live: a filter snapshot at least this often (IMU time), the places a late event rewinds to."""
MAX_WAIT_S = 1.0
"""Live: a measurement still waiting for the IMU this long after its time of validity is applied
at the state the filter has (an IMU stream that stopped must not hold the GNSS back forever)."""


class DriverHook:
    """What the driver shows its observers; every callback does nothing unless overridden. ``f`` is
    the filter, ``t_s`` the event's tag (GPS time [s]), ``k`` the GNSS epoch's index given with
    it, ``used`` whether the epoch's GNSS is used (outside the replay's outages)."""

    def on_gnss_epoch(self, f: InsFilter, t_s: float, k: int, used: bool) -> None:
        """At a GNSS epoch, before its update."""

    def after_gnss_epoch(self, f: InsFilter, t_s: float, k: int, used: bool) -> None:
        """At a GNSS epoch, after its update (if used)."""

    def on_outage_end(self, f: InsFilter, t_s: float, i: int) -> None:
        """At the end of outage i (a ``OUTAGE_END`` mark)."""

    def on_output(self, f: InsFilter, t_s: float, used: bool) -> None:
        """At an output time (an ``OUTPUT`` mark)."""

    def on_update(self, result: UpdateResult, f: InsFilter) -> None:
        """After every measurement update (GNSS, vehicle constraints, odometer, static calibration)."""

    def on_state(self, f: InsFilter, nav: NavState) -> None:
        """A state output (``emit_states``): the filter after an IMU sample (see the module docstring)."""

    def on_reorder(self, f: InsFilter, t_s: float) -> None:
        """Live: the filter was restored to its snapshot at GPS time ``t_s`` to put a late event in its
        place; the events after it are processed again."""


def overrides(hook: DriverHook, name: str) -> bool:
    """Whether ``hook`` overrides callback ``name`` of ``DriverHook``."""
    return getattr(type(hook), name, None) is not getattr(DriverHook, name)


class _ImuQueue:
    """IMU samples waiting, as arrays (a recording pushed at once is one block, no copy)."""

    def __init__(self) -> None:
        self.t = np.zeros(0)
        self.acc = np.zeros((0, 3))
        self.gyr = np.zeros((0, 3))
        self.i = 0
        self._new: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []

    def extend(self, t: np.ndarray, acc: np.ndarray, gyr: np.ndarray, front: bool = False) -> None:
        if front:
            self._settle()
            self.t = np.concatenate([t, self.t[self.i:]])
            self.acc = np.concatenate([acc, self.acc[self.i:]])
            self.gyr = np.concatenate([gyr, self.gyr[self.i:]])
            self.i = 0
        elif self.i >= len(self.t) and not self._new:
            self.t, self.acc, self.gyr, self.i = t, acc, gyr, 0
        else:
            self._new.append((t, acc, gyr))

    def _settle(self) -> None:
        if self._new:
            self.t = np.concatenate([self.t[self.i:]] + [b[0] for b in self._new])
            self.acc = np.concatenate([self.acc[self.i:]] + [b[1] for b in self._new])
            self.gyr = np.concatenate([self.gyr[self.i:]] + [b[2] for b in self._new])
            self.i = 0
            self._new.clear()

    def __len__(self) -> int:
        return len(self.t) - self.i + sum(len(b[0]) for b in self._new)

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
        """(t, acc, gyr, head index) with every pushed sample in them."""
        self._settle()
        return self.t, self.acc, self.gyr, self.i


class InsDriver:
    """The event loop of the module docstring around one ``InsFilter``.

    Push events with ``push_imu`` / ``push_imu_block``, ``push_gnss``, ``push_heading``,
    ``push_wheel``, ``push_mark``; run with ``run(until_s)`` (returns the states emitted);
    ``end_of_input()`` once nothing more will come (offline: ``complete=True`` from the start).

    f: the filter; reorder_window_s: live, how far back (IMU stamps) a late event is still put
    in its place (snapshots and history are kept for it); None: no reordering, a late event is
    rejected (offline, and sources whose events arrive in order); complete: every event is pushed before the first ``run`` (no measurement waits for IMU samples
    that may still come); emit_states: return a state per IMU sample; hooks: ``DriverHook``s (their
    ``on_update`` becomes the filter's); snapshot_every_s / max_wait_s: module constants; wheel_min_interval_s: odometer updates at most this often (its errors are
    correlated at higher rates; None: the filter's constraint period); imu_progress: called with
    the number of IMU samples each time some were processed.
    """

    def __init__(self, f: InsFilter, *, reorder_window_s: float | None = None, complete: bool = False,
                 emit_states: bool = False, hooks: Sequence[DriverHook] = (),
                 snapshot_every_s: float = SNAPSHOT_EVERY_S, max_wait_s: float = MAX_WAIT_S,
                 wheel_min_interval_s: float | None = None, imu_progress: Callable[[int], None] | None = None):
        self.f = f
        self.live = reorder_window_s is not None
        self.complete = complete
        self.hooks = list(hooks)
        self.state_hooks = [h for h in self.hooks if overrides(h, "on_state")]
        self.emit_states = emit_states or bool(self.state_hooks)
        self.reorder_window_s = float(reorder_window_s) if self.live else 0.0
        self.snapshot_every_s = float(snapshot_every_s)
        self.max_wait_s = float(max_wait_s)
        self.wheel_min_interval_s = (1.0 / f.cfg.constraints.constraint_rate_hz if wheel_min_interval_s is None
                                     else float(wheel_min_interval_s))
        self.imu_progress = imu_progress
        update_hooks = [h for h in self.hooks if overrides(h, "on_update")]
        if update_hooks:
            def on_update(res: UpdateResult, filt: InsFilter) -> None:
                for h in update_hooks:
                    h.on_update(res, filt)
            f.on_update = on_update
        self._imu = _ImuQueue()
        self._queues: dict[int, deque] = {k: deque() for k in KIND_NAMES if k != IMU}
        self._last_tag = {k: -math.inf for k in SENSOR_KINDS}
        self._last_imu_pushed = -math.inf
        # what processing changes, restored with the filter by a reorder
        self._proc = {"last_stamp": -math.inf, "wheel_next_t": -math.inf, "last_key": (-math.inf, 0),
                      "plan_tau": f.fx.imu_time_offset_s, "applied": {name: 0 for name in KIND_NAMES.values()}}
        self._plan: tuple | None = None        # (kind, tag, time of validity, IMU stamp threshold)
        self._pending_emit = False
        self._last_out_t = -math.inf
        self._emitted_stamp = -math.inf        # live: states for samples up to here were returned
        self._log: list[tuple] = []            # live: events processed since the oldest snapshot
        self._snaps: list[tuple] = []          # live: (log index, IMU stamp, filter state, proc state)
        self._out: list[NavState] = []
        self.counts = {"imu_pushed": 0, "gnss_pushed": 0, "heading_pushed": 0, "wheel_pushed": 0,
                       "rejected_out_of_order": 0, "imu_out_of_order": 0, "rejected_late": 0, "rejected_malformed": 0,
                       "reordered": 0, "applied_without_imu": 0, "states": 0, "states_non_monotonic": 0}

    # ------------------------------------------------------------------ input
    def push_imu(self, t_s: float, acc_mps2: np.ndarray, gyro_rps: np.ndarray) -> None:
        """One IMU sample (IMU axes) stamped t_s (GPS time of the IMU clock)."""
        self.push_imu_block(np.array([float(t_s)]), np.asarray(acc_mps2, float).reshape(1, 3),
                            np.asarray(gyro_rps, float).reshape(1, 3))

    def push_imu_block(self, t_s: np.ndarray, acc_mps2: np.ndarray, gyro_rps: np.ndarray) -> None:
        """IMU samples in stamp order (a whole recording, or what arrived). A sample whose stamp is
        not finite (``rejected_malformed``) or not after every earlier one (``imu_out_of_order``) is
        counted and dropped; non-finite values go to the filter, which counts and skips them
        (``InsFilter.counts["malformed_inputs"]``)."""
        t = np.ascontiguousarray(t_s, dtype=float).reshape(-1)
        if not len(t):
            return
        acc = np.ascontiguousarray(acc_mps2, dtype=float).reshape(-1, 3)
        gyr = np.ascontiguousarray(gyro_rps, dtype=float).reshape(-1, 3)
        self.counts["imu_pushed"] += len(t)
        finite = np.isfinite(t)
        prev = np.maximum.accumulate(np.concatenate([[self._last_imu_pushed], np.where(finite, t, -np.inf)]))[:-1]
        keep = finite & (t > prev)
        if not keep.all():
            self.counts["rejected_malformed"] += int((~finite).sum())
            self.counts["imu_out_of_order"] += int((finite & ~keep).sum())
            t, acc, gyr = t[keep], acc[keep], gyr[keep]
            if not len(t):
                return
        self._last_imu_pushed = float(t[-1])
        self._imu.extend(t, acc, gyr)

    def push_gnss(self, t_s: float, lla: np.ndarray, sd_ned_m: np.ndarray, fix: FixStatus | int,
                  vel_ned_mps: np.ndarray | None = None, vel_sd_ned_mps: np.ndarray | None = None,
                  index: int = -1, used: bool = True) -> bool:
        """A GNSS epoch tagged t_s (``InsFilter.update_gnss``'s arguments); ``index`` and ``used`` go
        to the hooks (``used`` False: the hooks see the epoch, the filter does not). False when
        rejected (counted)."""
        self.counts["gnss_pushed"] += 1
        return self._push(GNSS, t_s, (lla, sd_ned_m, fix, vel_ned_mps, vel_sd_ned_mps, index, used))

    def push_heading(self, t_s: float, heading_rad: float, sd_rad: float, baseline_vehicle_m: np.ndarray) -> bool:
        """A dual-antenna heading tagged t_s (``InsFilter.update_heading``'s arguments)."""
        self.counts["heading_pushed"] += 1
        return self._push(HEADING, t_s, (heading_rad, sd_rad, baseline_vehicle_m))

    def push_wheel(self, t_s: float, speed_mps: float) -> bool:
        """A wheel (forward) speed [m/s] at GPS time t_s."""
        self.counts["wheel_pushed"] += 1
        return self._push(WHEEL, t_s, speed_mps)

    def push_mark(self, kind: int, t_s: float, action: Callable[[InsFilter], None]) -> bool:
        """``action(filter)`` at GPS time t_s in the event order: kind ``OUTAGE_END`` or ``OUTPUT``
        (readouts for hooks) or ``CONSTRAINT`` (e.g. ``InsFilter.apply_vehicle_constraints``)."""
        if kind not in (OUTAGE_END, OUTPUT, CONSTRAINT):
            raise ValueError(f"push_mark: kind {kind} is not a mark")
        return self._push(kind, t_s, action)

    def _push(self, kind: int, t_s: float, payload: Any) -> bool:
        try:
            t = float(t_s)
        except (TypeError, ValueError):
            t = math.nan
        if not math.isfinite(t):
            self.counts["rejected_malformed"] += 1
            return False
        if kind in SENSOR_KINDS:
            if t <= self._last_tag[kind]:
                self.counts["rejected_out_of_order"] += 1
                return False
            self._last_tag[kind] = t
        if self._is_late(kind, t):
            if not (self.live and self._reorder(kind, t, payload)):
                self.counts["rejected_late"] += 1
                if kind in SENSOR_KINDS:
                    self._last_tag[kind] = t
                return False
            return True
        self._queues[kind].append((t, payload))
        if self._plan is not None and self._key(kind, t) < self._key(self._plan[0], self._plan[1]):
            self._plan = None      # an earlier measurement than the one planned: plan again
        return True

    def end_of_input(self) -> None:
        """Nothing more will be pushed: waiting measurements are applied once the IMU queue is done."""
        self.complete = True

    # ------------------------------------------------------------------ order
    def _delay(self, kind: int) -> float:
        return self.f.fx.gnss_latency_s if kind in DELAYED_LIKE_GNSS else 0.0

    def _key(self, kind: int, t: float) -> tuple[float, int]:
        return (t - self._delay(kind), kind)

    def _head(self) -> tuple[int, float] | None:
        """(kind, tag) of the waiting measurement first in (time of validity, rank) order."""
        best, best_key = None, None
        for kind, q in self._queues.items():
            if q:
                key = self._key(kind, q[0][0])
                if best_key is None or key < best_key:
                    best, best_key = (kind, q[0][0]), key
        return best

    def _is_late(self, kind: int, t: float) -> bool:
        """Whether an event of ``kind`` tagged t belongs before something already processed."""
        key = self._key(kind, t)
        return key[0] - self._proc["plan_tau"] < self._proc["last_stamp"] or key < self._proc["last_key"]

    # ------------------------------------------------------------------ the loop
    def run(self, until_s: float = math.inf, now_s: float | None = None) -> list[NavState]:
        """Process every event whose time of validity is <= ``until_s`` and whose place is known;
        ``now_s`` (live, GPS time) lets a measurement that waited ``max_wait_s`` for the IMU go.
        Returns the states emitted (``emit_states``), oldest first."""
        self._out = []
        f = self.f
        while True:
            if self._plan is None:
                head = self._head()
                if head is not None:
                    kind, tag = head
                    tv = tag - self._delay(kind)
                    self._plan = (kind, tag, tv, tv - self._proc["plan_tau"])
            thr = self._plan[3] if self._plan is not None else math.inf
            t_imu, acc, gyr, i = self._imu.arrays()
            n = len(t_imu)
            if i < n and t_imu[i] <= thr:
                limit = until_s - f.fx.imu_time_offset_s
                if not t_imu[i] <= limit:
                    break
                j = int(np.searchsorted(t_imu, min(thr, limit), side="right"))
                self._process_imu(t_imu, acc, gyr, i, j)
                continue
            if self._plan is None:
                break
            kind, tag, tv, thr = self._plan
            if tv > until_s:
                break
            if i >= n and not self.complete and thr > self._last_imu_pushed:
                # an IMU sample at or before the measurement may still come (samples arrive in order)
                if now_s is None or now_s - tv < self.max_wait_s:
                    break
                self.counts["applied_without_imu"] += 1
            self._apply_planned()
        self._flush_emit()
        out, self._out = self._out, []
        return out

    def _process_imu(self, t: np.ndarray, acc: np.ndarray, gyr: np.ndarray, i: int, j: int) -> None:
        f = self.f
        if not (self.emit_states or self.live):
            f.process_imu_batch(t[i:j], acc[i:j], gyr[i:j])
        else:
            for k in range(i, j):
                self._flush_emit()
                if self.live:
                    self._maybe_snapshot(float(t[k]))
                    self._log.append((IMU, float(t[k]), acc[k], gyr[k]))
                f.process_imu_batch(t[k:k + 1], acc[k:k + 1], gyr[k:k + 1])
                self._proc["last_stamp"] = max(self._proc["last_stamp"], float(t[k]))
                self._pending_emit = self.emit_states and float(t[k]) > self._emitted_stamp
        if not (self.emit_states or self.live):
            self._proc["last_stamp"] = max(self._proc["last_stamp"], float(t[j - 1]))
        self._proc["last_key"] = (-math.inf, 0)
        self._imu.i = j
        if self.imu_progress is not None:
            self.imu_progress(j - i)

    def _flush_emit(self) -> None:
        if not self._pending_emit:
            return
        self._pending_emit = False
        f = self.f
        self._emitted_stamp = max(self._emitted_stamp, self._proc["last_stamp"])
        if not f.initialized:
            return
        nav = f.nav_state()
        if nav.t_s <= self._last_out_t:
            self.counts["states_non_monotonic"] += 1
            return
        self._last_out_t = nav.t_s
        self.counts["states"] += 1
        self._out.append(nav)
        for h in self.state_hooks:
            h.on_state(f, nav)

    def _apply_planned(self) -> None:
        kind, tag, tv, thr = self._plan
        self._plan = None
        if thr > self._proc["last_stamp"]:
            self._flush_emit()      # a later measurement: the state of the last sample goes out without it
        _, payload = self._queues[kind].popleft()
        if self._snaps:
            self._log.append((kind, tag, payload))
        self._proc["last_key"] = (tv, kind)
        self._proc["applied"][KIND_NAMES[kind]] += 1
        self._apply(kind, tag, payload)
        self._proc["plan_tau"] = self.f.fx.imu_time_offset_s

    def _apply(self, kind: int, tag: float, payload: Any) -> None:
        f = self.f
        if kind == GNSS:
            lla, sd, fix, vel, vel_sd, k, used = payload
            for h in self.hooks:
                h.on_gnss_epoch(f, tag, k, used)
            if used:
                f.update_gnss(tag, lla, sd, fix, vel, vel_sd)
            for h in self.hooks:
                h.after_gnss_epoch(f, tag, k, used)
        elif kind == WHEEL:
            if tag >= self._proc["wheel_next_t"]:
                f.update_wheel_speed(tag, payload)
                self._proc["wheel_next_t"] = tag + self.wheel_min_interval_s
        elif kind == HEADING:
            f.update_heading(tag, *payload)
        else:
            payload(f)

    # ------------------------------------------------------------------ live: put late events in place
    def _maybe_snapshot(self, stamp: float) -> None:
        snaps = self._snaps
        if snaps and stamp - snaps[-1][1] < self.snapshot_every_s:
            return
        snaps.append((len(self._log), stamp, _filter_state(self.f), copy.deepcopy(self._proc)))
        # keep the newest snapshot at least a window old, and everything after it
        k = 0
        while k + 1 < len(snaps) and snaps[k + 1][1] <= stamp - self.reorder_window_s:
            k += 1
        if k:
            cut = snaps[k][0]
            del snaps[:k]
            del self._log[:cut]
            self._snaps = [(idx - cut, s, fs, p) for idx, s, fs, p in snaps]

    def _reorder(self, kind: int, t: float, payload: Any) -> bool:
        """Restore the last snapshot before the place of the late event (kind, t) and queue it with
        everything processed since; False (nothing changed) when no snapshot is that old (the place
        is more than ``reorder_window_s`` of IMU stamps back)."""
        key = self._key(kind, t)
        thr = key[0] - self._proc["plan_tau"]
        place = len(self._log)
        while place > 0:
            e = self._log[place - 1]
            if e[0] == IMU:
                if e[1] <= thr:
                    break
            elif self._key(e[0], e[1]) <= key:
                break
            place -= 1
        snap = None
        for s in reversed(self._snaps):
            # the snapshot's state must be from before the event's place (the log may be cut there)
            if s[0] <= place and s[3]["last_stamp"] <= thr and s[3]["last_key"] <= key:
                snap = s
                break
        if snap is None:
            return False
        idx, stamp, fstate, proc = snap
        redo = self._log[idx:]
        del self._log[idx:]
        self._snaps = [s for s in self._snaps if s[0] < idx] + [snap]
        _restore_filter(self.f, fstate)
        self._proc = copy.deepcopy(proc)
        self._plan = None
        self._pending_emit = False
        imu = [e for e in redo if e[0] == IMU]
        if imu:
            self._imu.extend(np.array([e[1] for e in imu]), np.array([e[2] for e in imu]),
                             np.array([e[3] for e in imu]), front=True)
        for q_kind in self._queues:
            back = [(e[1], e[2]) for e in redo if e[0] == q_kind]
            if back:
                self._queues[q_kind].extendleft(reversed(back))
        self._queues[kind].append((t, payload))
        for h in self.hooks:
            h.on_reorder(self.f, stamp + self.f.fx.imu_time_offset_s)
        self.counts["reordered"] += 1
        return True

    # ------------------------------------------------------------------ start and status
    def initialize(self, t_s: float, lla: np.ndarray, v_ned_mps: np.ndarray, rpy_rad: np.ndarray,
                   **sd: Any) -> None:
        """Start the filter from a declared state of the IMU point at GPS time t_s
        (``InsFilter.initialize``; ``sd``: its pos_sd_m, vel_sd_mps, att_sd_rad) instead of aligning
        it from the data. IMU samples not after t_s are dropped."""
        self.f.initialize(t_s, lla, v_ned_mps, rpy_rad, **sd)
        t, acc, gyr, i = self._imu.arrays()
        self._imu.i = max(i, int(np.searchsorted(t, t_s - self.f.fx.imu_time_offset_s, side="right")))
        self._proc["last_stamp"] = t_s - self.f.fx.imu_time_offset_s
        self._proc["plan_tau"] = self.f.fx.imu_time_offset_s
        self._plan = None

    def pending(self) -> dict:
        """Events waiting, per kind."""
        out = {"imu": len(self._imu)}
        out.update({KIND_NAMES[k]: len(q) for k, q in self._queues.items() if q})
        return out

    def done(self) -> bool:
        """Nothing waits (with ``complete``: the input is exhausted)."""
        return not len(self._imu) and not any(self._queues.values())

    def status(self) -> dict:
        """Counters (``counts``), what was applied per kind, what waits, the live history kept."""
        return {"counts": dict(self.counts), "applied": dict(self._proc["applied"]), "pending": self.pending(),
                "live": self.live, "reorder_window_s": self.reorder_window_s if self.live else None,
                "snapshots": len(self._snaps)}


_SHARED = ("cfg", "on_update", "stage_s", "residuals")
"""Filter attributes a snapshot shares instead of copying: the configuration and the hook (never
changed by a run), the stage timings (wall time spent, kept), and the residual log (append-only:
a restore cuts it back to its length at the snapshot). An object a caller attaches to the filter
that must not be copied either (e.g. a recorder of its steps, told by ``DriverHook.on_reorder``)
is named in the filter's ``snapshot_shared`` attribute."""


def _shared(f: InsFilter, d: dict) -> dict:
    names = _SHARED + tuple(getattr(f, "snapshot_shared", ()))
    memo = {id(d[k]): d[k] for k in names if k in d}
    memo[id(f)] = f
    return memo


def _filter_state(f: InsFilter) -> tuple[dict, int]:
    return copy.deepcopy(f.__dict__, _shared(f, f.__dict__)), len(f.residuals)


def _restore_filter(f: InsFilter, state: tuple[dict, int]) -> None:
    d, n_res = state
    memo = _shared(f, d)
    residuals, on_update = f.residuals, f.on_update
    f.__dict__.clear()
    f.__dict__.update(copy.deepcopy(d, memo))
    del residuals[n_res:]
    f.residuals, f.on_update = residuals, on_update


def push_dataset(drv: InsDriver, dataset: Dataset, *, imu: tuple | None = None, wheel: bool = True,
                 gnss_used: Callable[[float], bool] | None = None) -> None:
    """A whole recording into the driver: its IMU samples (``imu`` = (t, acc, gyro) instead, e.g.
    with interpolated samples added), its GNSS epochs in time order (``gnss_used(t)`` False: the
    hooks see the epoch, the filter does not -- a simulated outage) and, for a car with ``wheel``,
    its wheel speeds."""
    if imu is None:
        imu = (dataset.imu.t_s, dataset.imu.acc_mps2, dataset.imu.gyro_rps)
    drv.push_imu_block(*imu)
    gn, t_gnss = dataset.gnss, np.asarray(dataset.gnss.t_s, float)
    vel, vel_sd, fix = gn.vel_ned_mps, gn.vel_sd_ned_mps, np.asarray(gn.fix)
    for k in np.argsort(t_gnss, kind="stable"):
        t = float(t_gnss[k])
        drv.push_gnss(t, gn.lla[k], gn.sd_ned_m[k], FixStatus(int(fix[k])), None if vel is None else vel[k],
                      None if vel_sd is None else vel_sd[k], index=int(k),
                      used=True if gnss_used is None else gnss_used(t))
    if wheel and dataset.wheel is not None and drv.f.cfg.setup.platform == "car":
        for t, v in zip(np.asarray(dataset.wheel.t_s, float), np.asarray(dataset.wheel.speed_mps, float)):
            drv.push_wheel(float(t), float(v))


def warm_up(cfg: Any) -> None:
    """Compile the filter's jitted kernels (or load their cache) before real time starts: a
    throw-away filter of configuration ``cfg`` through a throw-away driver, started at a stop,
    0.3 s of samples at rest and one GNSS epoch. One function for every source."""
    f = InsFilter(cfg)
    d = InsDriver(f, emit_states=True, complete=True)
    lla = np.array([math.radians(45.0), math.radians(7.0), 300.0])
    d.initialize(0.0, lla, np.zeros(3), np.zeros(3))
    g_imu = np.asarray(cfg.setup.imu_to_body, float).T @ np.array([0.0, 0.0, -9.80665])
    t = 0.01 * np.arange(1, 31)
    d.push_imu_block(t, np.tile(g_imu, (len(t), 1)), np.zeros((len(t), 3)))
    d.push_gnss(0.3, lla, np.full(3, 0.02), FixStatus.FIXED, np.zeros(3), np.full(3, 0.05))
    d.run()
