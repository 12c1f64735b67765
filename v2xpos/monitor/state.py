"""What the monitor knows of one master: the latest result per target, the master's status, trails.

Pure bookkeeping (no I/O), fed by ``v2xpos.monitor.attach`` from zenoh and by tests directly:

* ``on_relative(body, target_id, t_wall_s)``: the msgpack body of a RelativeResult (the envelope
  already removed); only the latest body per target is kept -- a target's bodies between two
  refreshes are superseded, so the expensive validated decode (``v2xpos.wire.decode_relative_body``)
  runs once per target per refresh, not once per message (64 targets at 100 Hz: 6,400 messages/s,
  about 320 decodes/s at 5 refreshes/s);
* ``on_status(doc, t_wall_s)``: the master's status JSON (``master.service.MasterService.status``:
  master fix, counters, latency percentiles, per-target status and last brief, IMU grades, scene
  lanes); targets the monitor has no fresh result for are shown from it;
* ``on_geometry(target_id, geometry)``: a target's outline in its body frame (from one of its state
  messages);
* ``refresh(t_wall_s) -> dict``: the snapshot both views draw (rows sorted worst first, trails,
  lanes, master line).

Frames and units: positions in the master body frame (x forward, y right, z down) [m], the
relative yaw is the target's heading minus the master's [deg], sigma_h is the horizontal 1-sigma of
the relative position, sqrt(sd_x^2 + sd_y^2) [m]; age is the master time minus the target's time of
validity [ms] (what the master reports as latency).
"""
from __future__ import annotations

import math
from collections import deque
from typing import Any

from v2xpos.types import FixStatus
from v2xpos.wire import FixSide, Geometry, RelativeResult, TargetStatus, WireError, decode_relative_body

STATUS_RANK: dict[str, int] = {
    "timeout": 0, "no_data": 1, "future": 2, "fix_invalid": 3, "inconsistent": 4, "clock_unsynced": 5,
    "sigma_exceeded": 6, "attitude_uncertain": 7, "valid": 8}
"""Sort order of the table, worst first: a target that went silent, then one never heard, a time
ahead of the master, a failed fix gate, then the statuses that carry kinematics but are not VALID;
unknown statuses (a newer master) rank first."""

RESULT_FRESH_S = 2.0
"""A target's row comes from its latest result while that is younger than this (monitor wall
time); otherwise from the master's status JSON (e.g. a master without the zenoh republish)."""


def fix_name(code: Any) -> str | None:
    """FixStatus code -> short name (``FIXED``, ``FLOAT``, ``SINGLE``, ``DGPS``, ``DR``, ``NONE``)."""
    if code is None:
        return None
    try:
        f = FixStatus(int(code))
    except (ValueError, TypeError):
        return f"?{code}"
    return "DR" if f == FixStatus.DEAD_RECKONING else f.name


def _finite(x: Any) -> float | None:
    if x is None:
        return None
    try:
        x = float(x)
    except (TypeError, ValueError):
        return None
    return x if math.isfinite(x) else None


def status_reason(status: str, fix_side: int, master_fix: str | None, target_fix: str | None,
                  age_ms: float | None, sigma_h_m: float | None, degraded: bool) -> str:
    """Why a target has its status, in a few words (the table's ``reason`` column)."""
    if status == "fix_invalid":
        parts = []
        if fix_side & FixSide.MASTER:
            parts.append(f"master {master_fix or 'not RTK'}")
        if fix_side & FixSide.SLAVE:
            parts.append(f"target {target_fix or 'not RTK'}")
        text = "fix: " + ", ".join(parts) if parts else "fix gate"
    elif status == "timeout":
        text = "silent" if age_ms is None else f"silent {age_ms / 1e3:.1f} s"
    elif status == "no_data":
        text = "never heard"
    elif status == "future":
        text = "time ahead" if age_ms is None else f"time ahead {-age_ms:.0f} ms"
    elif status == "attitude_uncertain":
        text = "heading not determined"
    elif status == "sigma_exceeded":
        text = "sigma over limit" if sigma_h_m is None else f"sigma {sigma_h_m:.2f} m > limit"
    elif status == "clock_unsynced":
        text = "clock off GNSS time"
    elif status == "inconsistent":
        text = "filter NIS/whiteness check"
    elif status == "valid":
        text = ""
    else:
        text = f"status {status}"
    if degraded:
        text = (text + "; " if text else "") + "IMU degraded"
    return text


def grade_text(grade: dict | None) -> str:
    """IMU grade of a vehicle from the status JSON: ``pass``, ``warn imu2``, ``FAIL imu3``, or the
    grader's state (``pending`` ...); ``-`` when not graded."""
    if not grade:
        return "-"
    units = grade.get("units") or {}
    if grade.get("status") != "graded" or not units:
        return str(grade.get("status") or "-")
    fails = sorted(u for u, v in units.items() if v == "fail")
    warns = sorted(u for u, v in units.items() if v == "warn")
    if fails:
        return "FAIL " + ",".join(fails)
    if warns:
        return "warn " + ",".join(warns)
    return "pass"


def _geometry_doc(g: Geometry) -> dict:
    """Outline for drawing: polygon / points as [[x, y], ...] in the target body frame [m], or a
    circle radius [m]."""
    return {"kind": g.kind, "points_m": [[float(p[0]), float(p[1])] for p in g.points_body_m],
            "radius_m": float(g.radius_m)}


class MonitorState:
    """Latest state of one master's targets (see the module docstring)."""

    def __init__(self, trail_s: float = 20.0, trail_hz: float = 2.0):
        self.trail_s = float(trail_s)
        self.trail_period_s = 1.0 / float(trail_hz)
        self.status: dict | None = None
        self.status_wall_s = math.nan
        self.status_updates = 0
        self.received = 0
        self.malformed = 0
        self.decoded = 0
        self._bodies: dict[str, tuple[bytes, float]] = {}     # target -> (latest body, arrival wall)
        self._results: dict[str, tuple[RelativeResult, float]] = {}
        self._dirty: set[str] = set()
        self._geometry: dict[str, dict] = {}
        self._trails: dict[str, deque] = {}
        self._trail_last: dict[str, float] = {}
        self._changes: dict[str, tuple[str, float]] = {}      # target -> (status, wall time first seen)
        self._last_pose: dict[str, tuple[float, float, float | None]] = {}   # target -> last x, y, yaw
        self.version = 0

    # ------------------------------------------------------------------ inputs
    def on_relative(self, body: bytes, target_id: str, t_wall_s: float) -> None:
        """Latest RelativeResult body of ``target_id`` (cheap: no decode here)."""
        self.received += 1
        self._bodies[target_id] = (body, t_wall_s)
        self._dirty.add(target_id)

    def on_result(self, res: RelativeResult, t_wall_s: float) -> None:
        """An already decoded result (e.g. read from a recording)."""
        self.received += 1
        self._results[res.target_id] = (res, t_wall_s)

    def on_status(self, doc: dict, t_wall_s: float) -> None:
        self.status = doc
        self.status_wall_s = t_wall_s
        self.status_updates += 1

    def on_geometry(self, target_id: str, geometry: Geometry) -> None:
        self._geometry[target_id] = _geometry_doc(geometry)

    def has_geometry(self, target_id: str) -> bool:
        return target_id in self._geometry

    def targets(self) -> list[str]:
        """Every target id known from results or status, in first-seen order."""
        ids = dict.fromkeys(self._bodies)
        ids.update(dict.fromkeys(self._results))
        if self.status:
            ids.update(dict.fromkeys((self.status.get("targets") or {})))
        return list(ids)

    # ------------------------------------------------------------------ snapshot
    def _decode_dirty(self) -> None:
        for tid in self._dirty:
            body, t_wall = self._bodies[tid]
            try:
                res = decode_relative_body(body)
            except WireError:
                self.malformed += 1
                continue
            self.decoded += 1
            self._results[tid] = (res, t_wall)
        self._dirty.clear()

    def _row_from_result(self, res: RelativeResult, t_wall: float, grades: dict, degraded_ids: set) -> dict:
        status = res.status.name.lower() if isinstance(res.status, TargetStatus) else str(res.status)
        kin = res.has_kinematics
        p = res.rel_pos_body_m
        sd = res.rel_pos_sd_m
        x, y, z = (_finite(p[0]), _finite(p[1]), _finite(p[2])) if kin else (None, None, None)
        sx, sy = (_finite(sd[0]), _finite(sd[1])) if kin else (None, None)
        sigma_h = math.hypot(sx, sy) if sx is not None and sy is not None else None
        age_ms = None if not math.isfinite(res.latency_s) else res.latency_s * 1e3
        # a master that does not send the fixes leaves both at NONE (never true of a result with
        # kinematics, which needs RTK on both sides); then the master's fix comes from its status
        known = not (res.master_fix == FixStatus.NONE and res.target_fix == FixStatus.NONE)
        mfix = fix_name(res.master_fix) if known else None
        tfix = fix_name(res.target_fix) if known else None
        if mfix is None and self.status is not None:
            mfix = fix_name(self.status.get("master_fix"))
        degraded = bool(res.degraded) or res.target_id in degraded_ids
        yaw_sd = _finite(res.rel_yaw_sd_rad)
        return {
            "id": res.target_id, "kind": res.target_kind, "status": status, "status_code": int(res.status),
            "reason": status_reason(status, int(res.fix_side), mfix, tfix, age_ms, sigma_h, degraded),
            "master_fix": mfix, "target_fix": tfix,
            "range_m": _finite(res.range_m) if kin else None, "x_m": x, "y_m": y, "z_m": z,
            "rel_yaw_deg": math.degrees(res.rel_rpy_rad[2]) if kin and _finite(res.rel_rpy_rad[2]) is not None else None,
            "sigma_h_m": sigma_h, "sigma_yaw_deg": None if yaw_sd is None else math.degrees(yaw_sd),
            "age_ms": age_ms, "ttc_s": _finite(res.ttc_s) if kin else None,
            "gap_m": _finite(res.gap_m) if kin else None,
            "closing_mps": _finite(res.closing_speed_mps) if kin else None,
            "imu": grade_text(grades.get(res.target_id)), "degraded": degraded,
            "t_gps_s": res.t_gps_s, "seq": res.seq, "updated_wall_s": t_wall, "source": "results"}

    def _row_from_status(self, tid: str, t: dict, grades: dict) -> dict:
        last = t.get("last") or {}
        rng, brg = _finite(last.get("range_m")), _finite(last.get("bearing_deg"))
        x = y = None
        if rng is not None and brg is not None:
            x, y = rng * math.cos(math.radians(brg)), rng * math.sin(math.radians(brg))
        status = str(t.get("status", "no_data"))
        age_ms = _finite(last.get("latency_ms"))
        degraded = bool(t.get("degraded"))
        mfix = fix_name(self.status.get("master_fix")) if self.status else None
        return {
            "id": tid, "kind": t.get("kind", "vehicle"), "status": status,
            "status_code": int(TargetStatus[status.upper()]) if status.upper() in TargetStatus.__members__ else -1,
            "reason": status_reason(status, int(t.get("fix_side", 0) or 0), mfix, None, age_ms, None, degraded),
            "master_fix": mfix, "target_fix": None, "range_m": rng, "x_m": x, "y_m": y, "z_m": None,
            "rel_yaw_deg": None, "sigma_h_m": None, "sigma_yaw_deg": None, "age_ms": age_ms,
            "ttc_s": _finite(last.get("ttc_s")), "gap_m": _finite(last.get("gap_m")),
            "closing_mps": _finite(last.get("closing_mps")), "imu": grade_text(grades.get(tid)),
            "degraded": degraded, "t_gps_s": _finite(last.get("t_gps_s")), "seq": None,
            "updated_wall_s": self.status_wall_s, "source": "status"}

    def refresh(self, t_wall_s: float) -> dict:
        """The snapshot drawn by the table and the web page (JSON-serialisable)."""
        self._decode_dirty()
        st = self.status or {}
        grades = st.get("imu_grades") or {}
        degraded_ids = set(st.get("degraded_vehicles") or [])
        st_targets = st.get("targets") or {}
        rows = []
        for tid in self.targets():
            got = self._results.get(tid)
            if got is not None and (t_wall_s - got[1] <= RESULT_FRESH_S or tid not in st_targets):
                row = self._row_from_result(got[0], got[1], grades, degraded_ids)
            elif tid in st_targets:
                row = self._row_from_status(tid, st_targets[tid], grades)
            else:
                continue
            row["geometry"] = self._geometry.get(tid)
            prev = self._changes.get(tid)
            if prev is None or prev[0] != row["status"]:
                self._changes[tid] = (row["status"], t_wall_s)
            row["status_since_wall_s"] = self._changes[tid][1]
            if row["x_m"] is not None and row["y_m"] is not None:
                self._last_pose[tid] = (row["x_m"], row["y_m"], row["rel_yaw_deg"])
            # where it was last seen, for a target whose status carries no position (e.g. TIMEOUT)
            row["last_x_m"], row["last_y_m"], row["last_rel_yaw_deg"] = self._last_pose.get(tid, (None, None, None))
            self._trail(tid, row, t_wall_s)
            rows.append(row)
        rows.sort(key=sort_key)
        self.version += 1
        scene = st.get("scene") or {}
        lanes = [{"id": k, "lateral_m": _finite(v.get("lateral_m"))} for k, v in (scene.get("lanes") or {}).items()]
        return {
            "version": self.version, "t_wall_s": t_wall_s,
            "master": {"id": st.get("master_id"), "fix": fix_name(st.get("master_fix")),
                       "t_rel_s": _finite(st.get("t_rel_s")), "t_gps_s": _finite(st.get("t_gps_s")),
                       "processed": st.get("processed"), "rejected": st.get("rejected") or {},
                       "pipeline_ms_p99": _finite(st.get("pipeline_ms_p99")),
                       "e2e_ms_p99": _finite(st.get("e2e_ms_p99")), "can_frames": st.get("can_frames"),
                       "udp_datagrams": st.get("udp_datagrams"), "source": st.get("source"),
                       "status_age_s": None if math.isnan(self.status_wall_s) else t_wall_s - self.status_wall_s},
            "rows": rows, "lanes": lanes,
            "trails": {tid: [[x, y] for _, x, y in tr] for tid, tr in self._trails.items()},
            "monitor": {"received": self.received, "decoded": self.decoded, "malformed": self.malformed,
                        "status_updates": self.status_updates}}

    def _trail(self, tid: str, row: dict, t_wall_s: float) -> None:
        tr = self._trails.setdefault(tid, deque())
        while tr and t_wall_s - tr[0][0] > self.trail_s:
            tr.popleft()
        if row["x_m"] is None or row["y_m"] is None:
            return
        if t_wall_s - self._trail_last.get(tid, -math.inf) >= self.trail_period_s:
            self._trail_last[tid] = t_wall_s
            tr.append((t_wall_s, row["x_m"], row["y_m"]))


def sort_key(row: dict) -> tuple:
    """Worst first: status rank, degraded before healthy, then the shortest TTC, then the nearest."""
    ttc = row.get("ttc_s")
    rng = row.get("range_m")
    return (STATUS_RANK.get(row["status"], -1), not row.get("degraded", False),
            math.inf if ttc is None else ttc, math.inf if rng is None else rng, row["id"])
