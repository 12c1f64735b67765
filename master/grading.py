"""Live IMU grading for the master: a worker process started by the master grades every vehicle's
IMU units from the streamed samples (``FleetGrader``: one ``VehicleGrader`` per vehicle).

Slaves publish their IMU units' raw samples on ``v2xpos/<fleet>/vehicle/<id>/imu``
(``v2xpos.wire.encode_imu_payload``); the worker keeps one ``v2xpos.quality.VehicleGrader`` per vehicle (units in their own axes, declared
mountings), regrades every ``regrade_every_s`` of new data, and publishes the grades as JSON on
``v2xpos/<fleet>/master/<id>/grades``. The master subscribes to that key, marks the results of a
vehicle with a failing unit ``degraded`` and shows ``imu_grades`` in its status and report.

It runs in its own process so grading (tens to hundreds of ms of numpy per regrade) never holds
the GIL of the master's message path.

Regrades follow the data, not the worker's publication clock: every IMU payload steps its vehicle's
grader (a regrade when ``regrade_every_s`` of new data arrived), so a starved worker (it runs niced)
grades the same data times as an idle one. On stop the worker publishes its grades once more with
``"final": true``; the master waits for that message before it writes its report, so the last
regrade is not lost.

The IMU payload is ``v2xpos.wire``'s IMU stream (``encode_imu_payload`` / ``decode_imu_payload``,
docs/protocol.md). Malformed payloads are counted and skipped.

No false degradation (``GradeHysteresis``, docs/quality.md §"Persistence"): what is published as a
unit's grade is the grader's raw grade filtered over consecutive regrades. A unit is published
"fail" only once its raw grade was "fail" on ``FAIL_CONFIRM_REGRADES`` consecutive regrades, and stays
"fail" until it was not "fail" on ``FAIL_CLEAR_REGRADES`` consecutive regrades; a regrade in which
all of three or more units fail is inconclusive (no evidence either way); a raw "fail" that is not
(yet) persistent is published "warn" and listed in the vehicle's ``warnings`` (a status field: never
the CAN/UDP/zenoh ``degraded`` flag, which follows the published "fail"). The master's
``_on_grades`` marks a vehicle degraded when a published unit grade is "fail", so it needs no
knowledge of the rule.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import queue
import signal
import sys
import threading
import time

import numpy as np

from v2xpos.wire import ImuPayloadError, decode_imu_payload

GRADER_NICE = 10
FAIL_CONFIRM_REGRADES = 2
"""Consecutive regrades with a raw "fail" before a unit is published "fail" (the vehicle DEGRADED):
the demo's false degradation was one regrade of raw "fail" on a healthy vehicle (docs/quality.md)."""
FAIL_CLEAR_REGRADES = 3
"""Consecutive regrades without a raw "fail" before a published "fail" is lifted."""
FINAL_LINGER_S = 0.5
"""Seconds the worker stays connected after its final publication: closing the session at once may
drop a message still in its transmission queue."""
GAP_PERIODS = 2.5
"""A unit's next payload starting more than this many sample periods after its last sample is a gap
(counted per vehicle in ``gaps``: the grader interpolates across it, so a grade over lost data says so)."""
HISTORY_REGRADES = 16
"""Regrades kept per vehicle in the published ``history`` (raw and published grades)."""


class GradeHysteresis:
    """Per-unit persistence filter of one vehicle's raw grades (module docstring; docs/quality.md).

    ``update(raw)`` takes the raw grades of one regrade {unit: "pass"|"warn"|"fail"|None} and returns
    the published ones: "fail" once the unit's raw grade was "fail" on ``confirm`` consecutive
    regrades, kept until it was not "fail" on ``clear`` consecutive regrades; a raw "fail" before
    that is "warn" (a transient, listed by ``warnings``); otherwise the raw grade. None (no grade
    yet) neither confirms nor clears. A regrade in which every unit of a vehicle with three or more
    units is raw "fail" is *inconclusive*: the units disagree with each other and none stands out
    (seen with too little motion for the correlation checks, e.g. the first regrades of a drive);
    it counts as None for every unit.
    """

    def __init__(self, confirm: int = FAIL_CONFIRM_REGRADES, clear: int = FAIL_CLEAR_REGRADES):
        if confirm < 1 or clear < 1:
            raise ValueError("confirm and clear must be >= 1 regrade")
        self.confirm, self.clear = confirm, clear
        self.fail_streak: dict[str, int] = {}
        self.ok_streak: dict[str, int] = {}
        self.failed: dict[str, bool] = {}
        self.published: dict[str, str | None] = {}
        self.transient: dict[str, int] = {}
        self.inconclusive = False
        self.inconclusive_regrades = 0

    def update(self, raw: dict) -> dict:
        self.inconclusive = len(raw) >= 3 and all(g == "fail" for g in raw.values())
        self.inconclusive_regrades += self.inconclusive
        out = {}
        for unit, grade in raw.items():
            evidence = None if self.inconclusive else grade
            if evidence == "fail":
                self.fail_streak[unit] = self.fail_streak.get(unit, 0) + 1
                self.ok_streak[unit] = 0
            elif evidence is not None:
                self.ok_streak[unit] = self.ok_streak.get(unit, 0) + 1
                self.fail_streak[unit] = 0
            failed = self.failed.get(unit, False)
            if not failed and self.fail_streak.get(unit, 0) >= self.confirm:
                failed = True
            elif failed and self.ok_streak.get(unit, 0) >= self.clear:
                failed = False
            self.failed[unit] = failed
            out[unit] = "fail" if failed else "warn" if grade == "fail" else grade
            if grade == "fail" and not failed:
                self.transient[unit] = self.transient.get(unit, 0) + 1
        self.published = out
        return out

    def warnings(self) -> dict:
        """{unit: text} of the units whose last raw grade is a "fail" not published as such."""
        out = {}
        for u, g in self.published.items():
            if g != "warn":
                continue
            if self.inconclusive:
                out[u] = "inconclusive regrade: every unit failed, none stands out (too little motion?)"
            elif self.fail_streak.get(u, 0) > 0:
                out[u] = f"transient fail ({self.fail_streak[u]} of {self.confirm} consecutive regrades)"
        return out


class FleetGrader:
    """One VehicleGrader per vehicle, created on the vehicle's first IMU payload; its raw grades go
    through a ``GradeHysteresis`` once per regrade (a new grading time ``t_s``)."""

    def __init__(self, history_s: float = 60.0, min_history_s: float = 10.0, regrade_every_s: float = 5.0,
                 confirm_regrades: int = FAIL_CONFIRM_REGRADES, clear_regrades: int = FAIL_CLEAR_REGRADES):
        self.history_s, self.min_history_s, self.regrade_every_s = history_s, min_history_s, regrade_every_s
        self.confirm_regrades, self.clear_regrades = confirm_regrades, clear_regrades
        self.graders: dict = {}
        self.filters: dict[str, GradeHysteresis] = {}
        self.last_graded_t: dict[str, float] = {}
        self.history: dict[str, list] = {}
        self.regrades: dict[str, int] = {}
        self.degraded_regrades: dict[str, int] = {}
        self.first_degraded_t: dict[str, float | None] = {}
        self.malformed = 0
        self.grading_errors = 0                    # regrades that raised (``_consume``)
        self.gaps: dict[str, dict] = {}            # vehicle -> {"count", "lost_s"}: samples missing between payloads
        self._last_sample_t: dict[tuple[str, str], float] = {}
        self.lock = threading.Lock()
        self.latest: dict[str, dict] = {}

    def add_payload(self, data: bytes) -> None:
        from v2xpos.quality import VehicleGrader
        try:
            p = decode_imu_payload(data)
        except ImuPayloadError:
            self.malformed += 1
            return
        with self.lock:
            g = self.graders.get(p.vehicle_id)
            if g is None:
                if len(p.units) < 2:
                    self.malformed += 1
                    return
                g = self.graders[p.vehicle_id] = VehicleGrader(
                    sorted(p.units), history_s=self.history_s, min_history_s=self.min_history_s,
                    regrade_every_s=self.regrade_every_s, mounting_xyz_deg=p.mounting_xyz_deg or None)
                self.filters[p.vehicle_id] = GradeHysteresis(self.confirm_regrades, self.clear_regrades)
        with self.lock:
            self._count_gap(p)
        for uid, (t, acc, gyro) in p.units.items():
            g.add(uid, t, gyro, acc)
        with self.lock:                     # a regrade due at this data time happens now, whoever asks
            self.latest[p.vehicle_id] = self._filtered(p.vehicle_id, g.grades())

    def _count_gap(self, p) -> None:
        """Count samples lost before payload ``p`` (one dropped on the way, or a slave that skipped):
        a unit's first sample more than GAP_PERIODS sample periods after its last one; one gap per
        payload, the longest over its units."""
        if not p.rate_hz or p.rate_hz <= 0:
            return
        lost_s = 0.0
        for uid, (t, _, _) in p.units.items():
            if not len(t):
                continue
            key = (p.vehicle_id, uid)
            last = self._last_sample_t.get(key)
            if last is not None and float(t[0]) - last > GAP_PERIODS / p.rate_hz:
                lost_s = max(lost_s, float(t[0]) - last - 1.0 / p.rate_hz)
            self._last_sample_t[key] = float(t[-1]) if last is None else max(float(t[-1]), last)
        if lost_s > 0.0:
            g = self.gaps.setdefault(p.vehicle_id, {"count": 0, "lost_s": 0.0})
            g["count"] += 1
            g["lost_s"] += lost_s

    def _filtered(self, vid: str, r: dict) -> dict:
        """Published grades of vehicle ``vid`` from its grader's answer ``r`` (one filter step per new regrade)."""
        flt = self.filters[vid]
        if r["status"] == "graded" and r.get("t_s") is not None and r["t_s"] != self.last_graded_t.get(vid):
            self.last_graded_t[vid] = r["t_s"]
            units = flt.update(r["units"])
            self.regrades[vid] = self.regrades.get(vid, 0) + 1
            degraded = any(v == "fail" for v in units.values())
            if degraded:
                self.degraded_regrades[vid] = self.degraded_regrades.get(vid, 0) + 1
                if self.first_degraded_t.get(vid) is None:
                    self.first_degraded_t[vid] = r["t_s"]
            hist = self.history.setdefault(vid, [])
            hist.append({"t_s": r["t_s"], "raw": dict(r["units"]), "published": dict(units)})
            del hist[:-HISTORY_REGRADES]
        units = dict(flt.published) if flt.published else {u: None for u in r["units"]}
        return {"status": r["status"], "units": units, "raw_units": dict(r["units"]),
                "warnings": flt.warnings(), "regrades": self.regrades.get(vid, 0),
                "degraded_regrades": self.degraded_regrades.get(vid, 0),
                "first_degraded_t_s": self.first_degraded_t.get(vid),
                "transient_fails": dict(flt.transient), "inconclusive_regrades": flt.inconclusive_regrades,
                "rule": {"confirm_regrades": flt.confirm, "clear_regrades": flt.clear},
                "history": list(self.history.get(vid, [])),
                "rejected_samples": r["rejected_samples"],
                "gaps": dict(self.gaps.get(vid, {"count": 0, "lost_s": 0.0})), "t_s": r.get("t_s")}

    def grades(self) -> dict:
        """{vehicle id: {"status", "units" (published, hysteresis-filtered), "raw_units", "warnings",
        "regrades", "degraded_regrades", "first_degraded_t_s", "transient_fails", "rule", "history" (last
        HISTORY_REGRADES regrades: raw and published), "rejected_samples", "gaps" ({"count", "lost_s"}:
        samples missing between payloads), "t_s"}} -- call periodically
        (the worker: every second); each new regrade (new grading time) is one filter step. The
        counters are cumulative over the run: ``degraded_regrades`` > 0 means the vehicle was DEGRADED
        at some point."""
        with self.lock:
            for vid, g in self.graders.items():
                self.latest[vid] = self._filtered(vid, g.grades())
            return dict(self.latest)


def run_worker(endpoint: str, fleet: str, master_id: str, period_s: float = 1.0,
               stop: threading.Event | None = None) -> int:
    from v2xpos.link import Link, LinkConfig
    from v2xpos.wire import grades_key
    from v2xpos.wire import imu_key
    stop = stop or threading.Event()
    parent = os.getppid()
    fg = FleetGrader()
    # the zenoh callback only queues: a regrade takes tens to hundreds of ms, and a zenoh thread held
    # that long backs up the link, where the router drops what does not fit (counted as ``gaps``)
    inbox: queue.SimpleQueue = queue.SimpleQueue()
    consumer = threading.Thread(target=_consume, args=(inbox, fg), name="grading-consumer", daemon=True)
    consumer.start()
    link = Link(LinkConfig(mode="client", connect=[endpoint], connect_timeout_ms=30000))
    try:
        link.subscribe(imu_key(fleet, "*"), lambda p, k, a, t: inbox.put(p))
        pub = link.publisher(grades_key(fleet, master_id), express=False)

        def publish(final: bool) -> None:
            pub.put(json.dumps({"t_wall_s": time.time(), "malformed": fg.malformed,
                                "grading_errors": fg.grading_errors, "final": final,
                                "vehicles": fg.grades()}, default=_json_default).encode())

        orphan = False
        while not stop.wait(period_s):
            if os.getppid() != parent:          # the master is gone: do not linger as an orphan
                orphan = True
                break
            publish(final=False)
        if not orphan:
            inbox.put(None)                     # grade what arrived before the stop, then publish
            consumer.join()
            publish(final=True)
            time.sleep(FINAL_LINGER_S)
    finally:
        link.close()
    return 0


def _consume(inbox: "queue.SimpleQueue", fg: FleetGrader) -> None:
    """Feed queued IMU payloads to the grader until a None arrives. A payload whose grading raises
    is counted in ``fg.grading_errors`` (the first of each kind said on stderr) and the next one
    graded: one bad regrade never stops the grading of the session."""
    said: set = set()
    while True:
        data = inbox.get()
        if data is None:
            return
        try:
            fg.add_payload(data)
        except Exception as exc:  # any failure of one regrade: count it, keep grading the rest
            fg.grading_errors += 1
            kind = type(exc).__name__
            if kind not in said:
                said.add(kind)
                print(f"grading: a regrade failed ({kind}: {exc}); counted, grading goes on",
                      file=sys.stderr, flush=True)


def _json_default(x):
    if isinstance(x, (np.floating, np.integer)):
        v = float(x)
        return v if math.isfinite(v) else None
    if isinstance(x, np.ndarray):
        return x.tolist()
    return str(x)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m master.grading", description="master IMU grading worker")
    ap.add_argument("--endpoint", required=True)
    ap.add_argument("--fleet", required=True)
    ap.add_argument("--master-id", required=True)
    ap.add_argument("--period-s", type=float, default=1.0)
    a = ap.parse_args(argv)
    # background work, never ahead of the master's message path: GRADER_NICE in all, not on top of
    # the niceness the master already gave the worker (``master.service._background_priority``; both
    # at 10 made it 19, which on a busy machine got no CPU for the whole session)
    os.nice(max(0, GRADER_NICE - os.nice(0)))
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    return run_worker(a.endpoint, a.fleet, a.master_id, a.period_s, stop)


if __name__ == "__main__":
    sys.exit(main())
