"""Live IMU grading for the master (issue 5 in the service): a worker process started by the master.

Slaves publish their IMU units' raw samples on ``v2xpos/<fleet>/vehicle/<id>/imu`` (payload below);
the worker keeps one ``v2xpos.quality.VehicleGrader`` per vehicle (units in their own axes, declared
mountings), regrades every ``regrade_every_s`` of new data, and publishes the grades as JSON on
``v2xpos/<fleet>/master/<id>/grades``. The master subscribes to that key, marks the results of a
vehicle with a failing unit ``degraded`` and shows ``imu_grades`` in its status and report.

It runs in its own process so grading (tens to hundreds of ms of numpy per regrade) never holds
the GIL of the master's message path.

IMU payload (msgpack map): ``{"T": "imu", "ver": 1, "fleet": str, "id": str, "rate_hz": float,
"mounting_xyz_deg": {unit: [x, y, z]}, "units": {unit: [[t_gps_s, ax, ay, az, gx, gy, gz], ...]}}``
(m/s^2, rad/s, unit axes; mounting: X-Y-Z Euler angles unit -> vehicle body, ``docs/quality.md``).
Malformed payloads are counted and skipped.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import signal
import sys
import threading
import time

import msgpack
import numpy as np

MAX_ROWS = 10_000
GRADER_NICE = 10
MAX_UNITS = 16


class ImuPayloadError(ValueError):
    pass


def parse_imu_payload(data: bytes) -> dict:
    """Validated IMU payload -> {"id", "fleet", "mounting", "units": {uid: (t, acc, gyro)}}."""
    try:
        m = msgpack.unpackb(data, raw=False, strict_map_key=True, max_array_len=MAX_ROWS)
    except Exception as exc:  # msgpack raises many types, all mean "not a valid payload"
        raise ImuPayloadError(f"not msgpack ({type(exc).__name__})") from None
    if type(m) is not dict or m.get("T") != "imu" or m.get("ver") != 1:
        raise ImuPayloadError("not an imu message of version 1")
    vid, units = m.get("id"), m.get("units")
    if type(vid) is not str or not vid or type(units) is not dict or not 0 < len(units) <= MAX_UNITS:
        raise ImuPayloadError("missing id or units")
    out = {}
    for uid, rows in units.items():
        try:
            a = np.asarray(rows, dtype=float)
        except (TypeError, ValueError):
            raise ImuPayloadError(f"unit {uid!r}: rows are not numbers") from None
        if a.ndim != 2 or a.shape[1] != 7 or not np.isfinite(a).all():
            raise ImuPayloadError(f"unit {uid!r}: rows must be finite [t, ax, ay, az, gx, gy, gz]")
        out[str(uid)] = (a[:, 0], a[:, 1:4], a[:, 4:7])
    mounting = m.get("mounting_xyz_deg") or {}
    if type(mounting) is not dict:
        raise ImuPayloadError("mounting_xyz_deg is not a map")
    angles = {}
    for uid, v in mounting.items():
        try:
            a = np.asarray(v, dtype=float)
        except (TypeError, ValueError):
            raise ImuPayloadError(f"mounting_xyz_deg[{uid!r}]: not numbers") from None
        if a.shape != (3,) or not np.isfinite(a).all() or np.abs(a).max() > 360.0:
            raise ImuPayloadError(f"mounting_xyz_deg[{uid!r}]: need 3 finite angles in [-360, 360] deg")
        angles[str(uid)] = a.tolist()
    return {"id": vid, "fleet": m.get("fleet"), "units": out, "mounting": angles}


class FleetGrader:
    """One VehicleGrader per vehicle, created on the vehicle's first IMU payload."""

    def __init__(self, history_s: float = 60.0, min_history_s: float = 10.0, regrade_every_s: float = 5.0):
        self.history_s, self.min_history_s, self.regrade_every_s = history_s, min_history_s, regrade_every_s
        self.graders: dict = {}
        self.malformed = 0
        self.lock = threading.Lock()

    def add_payload(self, data: bytes) -> None:
        from v2xpos.quality import VehicleGrader
        try:
            p = parse_imu_payload(data)
        except ImuPayloadError:
            self.malformed += 1
            return
        with self.lock:
            g = self.graders.get(p["id"])
            if g is None:
                if len(p["units"]) < 2:
                    self.malformed += 1
                    return
                g = self.graders[p["id"]] = VehicleGrader(
                    sorted(p["units"]), history_s=self.history_s, min_history_s=self.min_history_s,
                    regrade_every_s=self.regrade_every_s, mounting_xyz_deg=p["mounting"] or None)
        for uid, (t, acc, gyro) in p["units"].items():
            g.add(uid, t, gyro, acc)

    def grades(self) -> dict:
        with self.lock:
            graders = dict(self.graders)
        out = {}
        for vid, g in graders.items():
            r = g.grades()
            out[vid] = {"status": r["status"], "units": r["units"], "rejected_samples": r["rejected_samples"],
                        "t_s": r.get("t_s")}
        return out


def run_worker(endpoint: str, fleet: str, master_id: str, period_s: float = 1.0,
               stop: threading.Event | None = None) -> int:
    from v2xpos.link import Link, LinkConfig, grades_key
    from v2xpos.wire import imu_key
    stop = stop or threading.Event()
    parent = os.getppid()
    fg = FleetGrader()
    link = Link(LinkConfig(mode="client", connect=[endpoint], connect_timeout_ms=30000))
    try:
        link.subscribe(imu_key(fleet, "*"), lambda p, k, a, t: fg.add_payload(p))
        pub = link.publisher(grades_key(fleet, master_id), express=False)
        while not stop.wait(period_s):
            if os.getppid() != parent:          # the master is gone: do not linger as an orphan
                break
            grades = fg.grades()
            pub.put(json.dumps({"t_wall_s": time.time(), "malformed": fg.malformed, "vehicles": grades},
                               default=_json_default).encode())
    finally:
        link.close()
    return 0


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
    os.nice(GRADER_NICE)                 # background work: never ahead of the master's message path
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    return run_worker(a.endpoint, a.fleet, a.master_id, a.period_s, stop)


if __name__ == "__main__":
    sys.exit(main())
