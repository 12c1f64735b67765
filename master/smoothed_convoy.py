"""``v2xpos convoy --in-process --smooth``: relative results from every vehicle's smoothed states.

Each recording runs through its service's filter (``v2xpos.sources.recording.RecordingSource``,
the states the in-process convoy evaluates) to its end with a ``v2xpos.ins.smoother.StepRecorder``
attached and a tap at every state it produces (the rows of what ``nav_state`` reports). After the
backward pass every state has a smoothed twin (``smoother.smoothed_nav_state``: position,
velocity and attitude corrected, their sds the smoother's covariance, the time label moved with the
smoothed IMU time offset) with the smoothed fix below;
states outside a smoothed interval (before the heading is set at a parked start, after the last
covariance step of the recording) stay forward. Both sets of states then go through the same
in-process loop (``in_process.feed_pipeline``): ``results.csv`` from the smoothed states with a trailing
column ``smoothed`` (1 when both the master's and the target's state are smoothed), and
``results_forward.csv`` from the forward states (what ``convoy --in-process`` writes). The
pipeline forms each result's status from these states as from live ones: fix gate, attitude,
clock, the filter's own consistency and verification flags, and the smoothed sigma against the
validity limits.

Flags: a forward state's consistency and verification flags vouch for the data up to it; a
smoothed state also uses the data after it -- above all, in a GNSS gap, the fixes that close the
gap. So a smoothed state is consistent (verified) only while the forward filter was, from it
until one consistency-test window (``InsConfig.consistency.consistency_window_s``, the time the test takes to
judge an innovation) after the first GNSS position used after it; its reason is the first failing
state's (``smoothed_flags``). The smoother computes no protection level of its own: a smoothed
state carries none (NaN). Without
it, on drive_0708 re-stamped 1.5 s later with B's default outages, four smoothed rows at the end
of one outage were VALID 0.3 m off with sds of 5-7 cm: the first fix after that gap was accepted,
the next eight rejected (NIS 35-107), and the forward test failed only then.

Time labels: a forward state is labelled with the filter's running estimate of the IMU time offset,
which differs between two filters of the same drive by the tens of milliseconds it has still to
converge (drive_0708 re-stamped 1.5 s later with a 15 s outage in B: up to 20 ms, the pipeline's
FUTURE tolerance); the smoothed state carries the smoothed offset, estimated from the whole
recording. Like the source, a stream leaves out a state whose label is not after the last one.

Smoothed fix: the GNSS status behind a smoothed state. While GNSS is used it is the forward one
(the last fix used); in a gap (the forward state is dead reckoning) the smoothed state is tied to
the fixes on both sides, and its fix is the worse of the last one before and the first one after
the gap (dead reckoning when no fix follows).
"""
from __future__ import annotations

import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

from v2xpos.types import FilterReason, FixStatus, NavState


class StoredStates:
    """A vehicle's states as the in-process loop reads them (``advance(t)``: the states its source
    released up to stamp t since the last call), forward or smoothed; ``flag[id(state)]`` says
    whether a returned state is smoothed."""

    def __init__(self, vehicle: "SmoothedVehicle", smoothed: bool):
        self.v, self.smoothed = vehicle, smoothed
        self.i = 0
        self.last_t_s = -np.inf
        self.non_monotonic = 0
        self.flag: dict[int, bool] = {}
        self.geometry, self.kind = vehicle.geometry, vehicle.kind
        self.t_begin_gps_s, self.t_end_gps_s = vehicle.t_begin_gps_s, vehicle.t_end_gps_s

    def advance(self, t_gps_s: float) -> list[NavState]:
        v = self.v
        j = int(np.searchsorted(v.release_s, t_gps_s, side="right"))
        out = []
        for k in range(self.i, j):
            st = v.state(k) if self.smoothed else v.forward[k]
            if st.t_s <= self.last_t_s:
                self.non_monotonic += 1
                continue
            self.last_t_s = st.t_s
            self.flag[id(st)] = self.smoothed and bool(v.is_smoothed[k])
            out.append(st)
        self.i = max(self.i, j)
        return out


class SmoothedVehicle:
    """One recording through its filter with the smoother (module docstring): the forward states,
    the stamps at which the source released them, and what ``state(k)`` needs to build the smoothed
    twin of state k (``y``, ``cov``, the smoothed fix)."""

    def __init__(self, path: str | Path):
        from v2xpos.ins.smoother import StepRecorder, reported_rows
        from v2xpos.sources.recording import RecordingSource
        src = RecordingSource(path, sync="none")
        f = src.filter
        f.recorder = rec = StepRecorder.for_filter(f, tap_rows=9)
        self.geometry, self.kind = src.geometry, src.kind
        self.t_begin_gps_s, self.t_end_gps_s = src.t_begin_gps_s, src.t_end_gps_s
        self.forward: list[NavState] = []
        release, last_fix, last_gnss, timing = [], [], [], []
        window_s = f.cfg.consistency.consistency_window_s
        i_dt = f.layout.at("imu_time_offset")
        for t_k in np.asarray(src.ds.imu.t_s, float):
            for st in src.advance(float(t_k)):
                J = reported_rows(f)
                rec.tap(f.t_stamp_s, J)
                if i_dt >= 0:
                    timing.append(J[:, i_dt])
                self.forward.append(st)
                release.append(t_k)
                last_fix.append(int(f.last_fix))
                last_gnss.append(f.last_gnss_t_s)
        rec.finish(f)
        sm = rec.smooth()
        self.release_s = np.asarray(release, float)
        self.is_smoothed, self.y, self.cov = sm.smoothed, sm.y, sm.cov
        self.timing = np.asarray(timing, float) if i_dt >= 0 else None
        self.dt_error_s = sm.dx[:, i_dt].astype(float) if i_dt >= 0 else None
        self.fix = smoothed_fix(np.array([int(s.fix) for s in self.forward], int), np.asarray(last_fix, int),
                                np.asarray(last_gnss, float))
        self.flags = smoothed_flags(self.forward, np.asarray(last_gnss, float), window_s)
        self.nodes, self.segments, self.stored_mib = rec.nodes, len(rec.segments), rec.stored_bytes / 2 ** 20
        self.segment_times = rec.segment_times()

    def state(self, k: int) -> NavState:
        """State k, smoothed when it lies in a smoothed interval."""
        if not self.is_smoothed[k]:
            return self.forward[k]
        from v2xpos.ins.smoother import smoothed_nav_state
        consistent, verified, reason = (x[k] for x in self.flags)
        if self.timing is None:
            st = smoothed_nav_state(self.forward[k], self.y[k], self.cov[k], FixStatus(int(self.fix[k])))
        else:
            st = smoothed_nav_state(self.forward[k], self.y[k], self.cov[k], FixStatus(int(self.fix[k])),
                                    self.dt_error_s[k], self.timing[k])
        return replace(st, consistent=bool(consistent), verified=bool(verified), reason=FilterReason(int(reason)),
                       protection_m=float("nan"))


def smoothed_fix(forward_fix: np.ndarray, last_fix: np.ndarray, last_gnss_t_s: np.ndarray) -> np.ndarray:
    """The smoothed fix of each state (module docstring) from, per state in time order, its forward
    fix, the filter's last fix used and that fix's time: in a gap (forward dead reckoning) the worse
    of the last fix and the first one used after it."""
    n = len(forward_fix)
    change = np.flatnonzero(np.diff(last_gnss_t_s) != 0) + 1
    j = np.searchsorted(change, np.arange(n), side="right")
    has_next = j < len(change)
    next_fix = np.where(has_next, last_fix[change[np.minimum(j, len(change) - 1)]] if len(change) else 0,
                        int(FixStatus.DEAD_RECKONING))
    gap = forward_fix == int(FixStatus.DEAD_RECKONING)
    return np.where(gap, np.minimum(last_fix, next_fix), forward_fix)


def _next_change_time(last_gnss_t_s: np.ndarray) -> np.ndarray:
    """Per state (time order): the time of the first GNSS position used after it (inf if none)."""
    n = len(last_gnss_t_s)
    change = np.flatnonzero(np.diff(last_gnss_t_s) != 0) + 1
    j = np.searchsorted(change, np.arange(n), side="right")
    return np.where(j < len(change), last_gnss_t_s[change[np.minimum(j, max(len(change) - 1, 0))]]
                    if len(change) else np.inf, np.inf)


def _first_bad_from(bad: np.ndarray) -> np.ndarray:
    """For each index k the first index >= k where ``bad`` holds (len(bad) if none)."""
    n = len(bad)
    idx = np.where(bad, np.arange(n), n)
    return np.minimum.accumulate(idx[::-1])[::-1]


def smoothed_flags(states: list[NavState], last_gnss_t_s: np.ndarray, window_s: float) -> tuple:
    """(consistent, verified, reason) of each smoothed state (module docstring, "Flags"): the forward
    flags over [t, first GNSS position used after t + ``window_s``]."""
    n = len(states)
    if not n:
        return np.zeros(0, bool), np.zeros(0, bool), np.zeros(0, int)
    t = np.array([s.t_s for s in states], float)
    cons = np.array([s.consistent for s in states], bool)
    ver = np.array([s.verified for s in states], bool)
    reason = np.array([int(s.reason) for s in states], int)
    end = np.maximum(t, _next_change_time(np.asarray(last_gnss_t_s, float))) + window_s
    j = np.searchsorted(t, end, side="right")
    first_c, first_v, first_any = _first_bad_from(~cons), _first_bad_from(~ver), _first_bad_from(~(cons & ver))
    consistent, verified = first_c >= j, first_v >= j
    bad_at = np.minimum(first_any, n - 1)
    return consistent, verified, np.where(first_any < j, reason[bad_at], reason)


def run_in_process_smoothed(out: Path, master: tuple, slaves: list[tuple], rate_hz: float = 100.0,
                            log=None) -> dict:
    """The smoothed in-process convoy (module docstring); returns the pipeline's counts per run and
    the smoother's per vehicle. ``log``: progress lines (default the current ``sys.stderr``)."""
    log = sys.stderr if log is None else log      # resolved per call: a stream bound at import may be closed
    from master.in_process import feed_pipeline
    from v2xpos.output.results_csv import ResultsCsvWriter
    out.mkdir(parents=True, exist_ok=True)
    vehicles = {}
    for path, name, _ in [master] + list(slaves):
        print(f"convoy (smoothed): {name}: forward and backward pass", file=log, flush=True)
        vehicles[name] = SmoothedVehicle(path)
    facts: dict = {"smoothing": {name: {"states": len(v.forward), "smoothed": int(v.is_smoothed.sum()),
                                        "nodes": v.nodes, "segments": v.segments, "stored_mib": v.stored_mib,
                                        "segment_times": v.segment_times}
                                 for name, v in vehicles.items()}}
    slave_ids = [s[1] for s in slaves]
    sink = ResultsCsvWriter(out / "results_forward.csv")
    try:
        facts["forward"] = feed_pipeline(sink, master[1], StoredStates(vehicles[master[1]], False),
                                         {sid: StoredStates(vehicles[sid], False) for sid in slave_ids}, rate_hz, log)
    finally:
        sink.close()
    sink = ResultsCsvWriter(out / "results.csv", extra_columns=("smoothed",))
    mstream = StoredStates(vehicles[master[1]], True)
    sstreams = {sid: StoredStates(vehicles[sid], True) for sid in slave_ids}

    def flag(master_state: NavState, sid: str, slave_state: NavState) -> None:
        both = mstream.flag.get(id(master_state), False) and sstreams[sid].flag.get(id(slave_state), False)
        sink.extra["smoothed"] = int(both)
    try:
        facts.update(feed_pipeline(sink, master[1], mstream, sstreams, rate_hz, log, before_handle=flag))
    finally:
        sink.close()
    for name, stream in [(master[1], mstream)] + list(sstreams.items()):
        facts["smoothing"][name]["non_monotonic"] = stream.non_monotonic
    return facts
