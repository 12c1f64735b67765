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
* ``on_vehicle_status(doc, t_wall_s)``: a vehicle service's live status (``v2xpos.sources.status``;
  the master's own is inside its status), shown in the vehicle panel;
* ``on_alive(kind, id, alive, t_wall_s)``: a service's zenoh liveliness token appeared or went (a
  killed process's token goes within milliseconds: its session closed);
* ``refresh(t_wall_s) -> dict``: the snapshot both views draw (rows sorted worst first, trails,
  lanes, master line, vehicle panel).

Nothing stale looks live. Every row carries the age of its data as the monitor shows it
(``age_ms``: the master's age of the target state when it made the result, plus the time since the
monitor received that result). A row whose master has not said anything about it for longer than
the master's timeout (results arrive with every message and at the master's tick for silent
targets; rows read from the status every status period, so theirs is timeout + one period) is
``stale``: drawn and listed as STALE with the master's last status beside it, never as that
status. A master whose liveliness token went, or whose status is overdue by three periods, is
``gone`` and every row stale; a master still starting says which phase it is in and whom it waits
for.

Frames and units: positions in the master body frame (x forward, y right, z down) [m], the
relative yaw is the target's heading minus the master's [deg], sigma_h is the horizontal 1-sigma of
the relative position, sqrt(sd_x^2 + sd_y^2) [m]; age is the master time minus the target's time of
validity [ms] (what the master reports as latency).
"""
from __future__ import annotations

import math
from collections import deque
from typing import Any

from v2xpos.sources.status import reason_instruction, status_line
from v2xpos.types import FixStatus
from v2xpos.wire import FixSide, Geometry, RelativeResult, TargetStatus, WireError, decode_relative_body, reason_name

STATUS_RANK: dict[str, int] = {
    "stale": 0, "timeout": 1, "no_data": 2, "future": 3, "fix_invalid": 4, "inconsistent": 5, "clock_unsynced": 6,
    "unverified": 7, "sigma_exceeded": 8, "attitude_uncertain": 9, "valid": 10}
"""Sort order of the table, worst first: a row whose data is older than the timeout at the monitor
(the master silent or gone), a target that went silent, then one never heard, a time ahead of the
master, a failed fix gate, then the statuses that carry kinematics but are not VALID; unknown
statuses (a newer master) rank first."""
DEFAULT_TIMEOUT_S = 0.2
"""The master's staleness limit when its status does not say (``[service] timeout_ms``)."""
DEFAULT_STATUS_PERIOD_S = 0.5
"""The master's status period when its status does not say (``[service] status_hz`` = 2)."""
STATUS_OVERDUE_PERIODS = 3.0
"""A master whose status is this many periods overdue is gone (its liveliness token says it sooner)."""
VEHICLE_STATUS_OVERDUE_S = 3.0
"""A vehicle whose 1 Hz status is older than this is shown as silent."""

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


_SIDE_NAMES = ((int(FixSide.MASTER), "master"), (int(FixSide.SLAVE), "target"))


def _named_reasons(side: int, master_reason: Any, target_reason: Any) -> list[tuple[str, str | None]]:
    """(vehicle, reason name) of each vehicle ``side`` names."""
    reasons = {"master": master_reason, "target": target_reason}
    return [(word, None if reasons[word] in (None, 0, "OK") else
             reasons[word] if isinstance(reasons[word], str) else reason_name(reasons[word]))
            for bit, word in _SIDE_NAMES if side & bit]


def status_reason(status: str, fix_side: int, master_fix: str | None, target_fix: str | None,
                  age_ms: float | None, sigma_h_m: float | None, degraded: bool, reason_side: int = 0,
                  master_reason: Any = None, target_reason: Any = None, clock_ms: float | None = None) -> str:
    """Why a target has its status, in a few words (the table's ``reason`` column): the vehicle and
    its filter's reason for a status a vehicle made (``reason_side``), the clock difference when the
    master's clock comparison raised an alarm (``clock_ms``: master minus target)."""
    named = _named_reasons(reason_side, master_reason, target_reason)
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
        text = "heading not determined" + (" (" + ", ".join(w for w, _ in named) + ")" if named else "")
    elif status == "sigma_exceeded":
        text = "sigma over limit" if sigma_h_m is None else f"sigma {sigma_h_m:.2f} m > limit"
    elif status == "clock_unsynced":
        text = "clock off GNSS time" if clock_ms is None else _clock_words(clock_ms)
    elif status in ("inconsistent", "unverified"):
        what = "test failed" if status == "inconsistent" else "not verified"
        text = ", ".join(f"{w} {r or what}" for w, r in named) if named else f"filter {what}"
    elif status == "stale":
        text = "no data" if age_ms is None else f"no data for {age_ms / 1e3:.1f} s"
    elif status == "valid":
        text = ""
    else:
        text = f"status {status}"
    if clock_ms is not None and status in ("timeout", "no_data", "future"):
        text += "; " + _clock_words(clock_ms)
    if degraded:
        text = (text + "; " if text else "") + "IMU degraded"
    return text


def _clock_words(clock_ms: float) -> str:
    return f"clock: target {abs(clock_ms):.0f} ms {'behind' if clock_ms > 0 else 'ahead of'} master"


def instruction(row: dict, master_state: str | None = None) -> str:
    """What the operator should do about a row (the monitor's ``do`` column): from the filter's
    reason of the vehicle that made the status (``v2xpos.sources.status.REASON_INSTRUCTIONS``), the
    fix gate, the clocks, or a silent master."""
    status = row["status"]
    if status == "valid":
        return ""
    if status == "stale":
        return ("master gone: restart it or check the link" if master_state == "gone"
                else "no data from the master: check it and the link")
    if row.get("clock_alarm"):
        return "clocks disagree: check chrony on both (bench: the same host_time_offset_s)"
    if status == "fix_invalid":
        bad = [f"{w} receiver {row.get('target_fix' if w == 'target' else 'master_fix') or 'not RTK'}"
               for bit, w in _SIDE_NAMES if (row.get("fix_side") or 0) & bit]
        return (", ".join(bad) or "receiver not RTK") + ": check the corrections and the sky view"
    if status == "sigma_exceeded" and _far_target(row):
        return (f"target far ({row['range_m']:.0f} m): the master's heading error across that range; "
                "VALID when closer")
    if status in STATUS_INSTRUCTIONS:
        return STATUS_INSTRUCTIONS[status]
    named = _named_reasons(row.get("reason_side") or 0, row.get("master_reason"), row.get("target_reason"))
    hints = [f"{w}: {reason_instruction(r)}" for w, r in named if r and reason_instruction(r)]
    return "; ".join(hints) if hints else VEHICLE_STATUS_INSTRUCTIONS.get(status, "")


FAR_CROSS_RANGE_SHARE = 0.9
"""A sigma over its limit is the range's, not the receivers', when the s.d. across the line of sight
carries at least this share of the horizontal s.d.: heading error times range is cross-range only,
an RTK position error has no preferred direction (0.71 for a circular one)."""


def _far_target(row: dict) -> bool:
    cross, h = row.get("sigma_cross_m"), row.get("sigma_h_m")
    return (cross is not None and h is not None and row.get("range_m") is not None and h > 0.0
            and cross >= FAR_CROSS_RANGE_SHARE * h)


STATUS_INSTRUCTIONS = {
    "timeout": "target silent: check the slave and the link", "no_data": "target silent: check the slave and the link",
    "future": "target time ahead: check both clocks", "clock_unsynced": "clock off GNSS time: check chrony and the PPS",
    "sigma_exceeded": "sigma above its limit: wait for RTK fixed"}
"""What to do about a status that is no vehicle filter's own."""
VEHICLE_STATUS_INSTRUCTIONS = {
    "attitude_uncertain": "heading pending: drive off", "inconsistent": "a filter test failed: check the declared set-up",
    "unverified": "set-up not yet verified: drive a turn"}
"""What to do about a vehicle's status when its filter gave no reason."""


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
        self._vehicles: dict[str, tuple[dict, float]] = {}    # vehicle id -> (latest status, arrival wall)
        self._alive: dict[tuple[str, str], tuple[bool, float]] = {}   # (kind, id) -> (alive, since wall)
        self.first_wall_s = math.nan
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

    def on_vehicle_status(self, doc: dict, t_wall_s: float) -> None:
        """A vehicle service's live status (``v2xpos.sources.status``)."""
        vid = doc.get("id")
        if isinstance(vid, str):
            self._vehicles[vid] = (doc, t_wall_s)

    def on_alive(self, kind: str, ident: str, alive: bool, t_wall_s: float) -> None:
        """A liveliness token of ``kind`` ("master" or "vehicle") ``ident`` appeared or went."""
        self._alive[(kind, ident)] = (bool(alive), t_wall_s)

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
        range_sd = _finite(res.range_sd_m) if kin else None
        # s.d. across the line of sight, what the master's heading error makes (range times its
        # s.d.): the trace of the horizontal covariance is sd_x^2 + sd_y^2 in any axes, so also
        # the range's variance plus the cross-range one
        sigma_cross = (math.sqrt(max(sigma_h ** 2 - range_sd ** 2, 0.0))
                       if sigma_h is not None and range_sd is not None else None)
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
        clock_ms = self._clock_alarm_ms(res.target_id)
        return {
            "id": res.target_id, "kind": res.target_kind, "status": status, "status_code": int(res.status),
            "reason": status_reason(status, int(res.fix_side), mfix, tfix, age_ms, sigma_h, degraded,
                                    int(res.reason_side), res.master_reason, res.target_reason, clock_ms),
            "fix_side": int(res.fix_side), "reason_side": int(res.reason_side),
            "master_reason": reason_name(res.master_reason) if res.master_reason else None,
            "target_reason": reason_name(res.target_reason) if res.target_reason else None,
            "protection_m": _finite(res.protection_m), "clock_alarm": clock_ms is not None,
            "master_fix": mfix, "target_fix": tfix,
            "range_m": _finite(res.range_m) if kin else None, "x_m": x, "y_m": y, "z_m": z,
            "rel_yaw_deg": math.degrees(res.rel_rpy_rad[2]) if kin and _finite(res.rel_rpy_rad[2]) is not None else None,
            "sigma_h_m": sigma_h, "sigma_cross_m": sigma_cross,
            "sigma_yaw_deg": None if yaw_sd is None else math.degrees(yaw_sd),
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
        side = int(t.get("reason_side") or 0)
        clock_ms = self._clock_alarm_ms(tid)
        return {
            "id": tid, "kind": t.get("kind", "vehicle"), "status": status,
            "status_code": int(TargetStatus[status.upper()]) if status.upper() in TargetStatus.__members__ else -1,
            "reason": status_reason(status, int(t.get("fix_side", 0) or 0), mfix, None, age_ms, None, degraded,
                                    side, t.get("master_reason"), t.get("target_reason"), clock_ms),
            "fix_side": int(t.get("fix_side", 0) or 0), "reason_side": side,
            "master_reason": t.get("master_reason"), "target_reason": t.get("target_reason"),
            "protection_m": _finite(t.get("protection_m")), "clock_alarm": clock_ms is not None,
            "master_fix": mfix, "target_fix": None, "range_m": rng, "x_m": x, "y_m": y, "z_m": None,
            "rel_yaw_deg": None, "sigma_h_m": None, "sigma_cross_m": None, "sigma_yaw_deg": None, "age_ms": age_ms,
            "ttc_s": _finite(last.get("ttc_s")), "gap_m": _finite(last.get("gap_m")),
            "closing_mps": _finite(last.get("closing_mps")), "imu": grade_text(grades.get(tid)),
            "degraded": degraded, "t_gps_s": _finite(last.get("t_gps_s")), "seq": None,
            "updated_wall_s": self.status_wall_s, "source": "status"}

    def _clock_alarm_ms(self, tid: str) -> float | None:
        """Master minus target clock [ms] when the master's clock comparison raised an alarm."""
        t = ((self.status or {}).get("targets") or {}).get(tid) or {}
        clock = t.get("clock") or {}
        return _finite(clock.get("offset_ms")) if clock.get("alarm") else None

    def master_state(self, t_wall_s: float) -> str:
        """``not_heard`` (nothing yet), ``gone`` (its liveliness token went, or its status is overdue),
        ``starting`` (its session clock does not run yet), ``live``."""
        st = self.status
        alive = self._alive.get(("master", str((st or {}).get("master_id"))))
        if st is None:
            return "gone" if alive is not None and not alive[0] else "not_heard"
        period = _finite(st.get("status_period_s")) or DEFAULT_STATUS_PERIOD_S
        if (alive is not None and not alive[0] and alive[1] >= self.status_wall_s) \
                or t_wall_s - self.status_wall_s > STATUS_OVERDUE_PERIODS * period:
            return "gone"
        if st.get("phase") not in (None, "run"):
            return "starting"
        return "live"

    def _stale(self, row: dict, arrival_wall_s: float, t_wall_s: float, master_state: str) -> None:
        """Turn a row whose data is older than the master's timeout (at the monitor) into STALE."""
        st = self.status or {}
        timeout = _finite(st.get("timeout_s")) or DEFAULT_TIMEOUT_S
        period = 0.0 if row["source"] == "results" else (_finite(st.get("status_period_s")) or DEFAULT_STATUS_PERIOD_S)
        since = max(0.0, t_wall_s - arrival_wall_s)
        row["seen_s"] = since
        if row["age_ms"] is not None:
            row["age_ms"] = row["age_ms"] + since * 1e3
        if master_state == "gone" or since > timeout + period:
            row["last_status"] = row["status"]
            row["status"] = "stale"
            row["status_code"] = -1
            age = since * 1e3 if row["age_ms"] is None else row["age_ms"]
            row["reason"] = f"no data for {age / 1e3:.1f} s (last {row['last_status'].upper()})"
            for k in ("x_m", "y_m", "z_m", "range_m", "rel_yaw_deg", "sigma_h_m", "sigma_cross_m", "ttc_s", "gap_m",
                      "closing_mps"):
                row[k] = None

    def _vehicle_panel(self, t_wall_s: float) -> list[dict]:
        """One entry per vehicle service: the master's own (from its status) and every slave's."""
        docs = []
        st = self.status
        if st is not None and isinstance(st.get("vehicle"), dict):
            docs.append((st["vehicle"], self.status_wall_s))
        docs += [v for vid, v in sorted(self._vehicles.items())]
        out = []
        for doc, t_arr in docs:
            vid = str(doc.get("id"))
            alive = self._alive.get(("master" if doc.get("role") == "master" else "vehicle", vid))
            age = t_wall_s - t_arr
            state = ("gone" if alive is not None and not alive[0] and alive[1] >= t_arr
                     else "silent" if age > VEHICLE_STATUS_OVERDUE_S else "live")
            f = doc.get("filter") or {}
            hint = reason_instruction(f.get("reason")) if f else "filter not started"
            clock = doc.get("clock") or {}
            out.append({"id": vid, "role": doc.get("role"), "state": state, "status_age_s": age,
                        "line": status_line(doc), "instruction": hint,
                        "clock_synchronised": clock.get("synchronised"), "clock_offset_s": clock.get("offset_s"),
                        "gps_minus_wall_s": clock.get("gps_minus_wall_s"), "filter": f or None,
                        "streams": doc.get("streams") or {}, "imu_clock": doc.get("imu_clock"),
                        "corrections": doc.get("corrections")})
        return out

    def refresh(self, t_wall_s: float) -> dict:
        """The snapshot drawn by the table and the web page (JSON-serialisable)."""
        self._decode_dirty()
        if math.isnan(self.first_wall_s):
            self.first_wall_s = t_wall_s
        st = self.status or {}
        grades = st.get("imu_grades") or {}
        degraded_ids = set(st.get("degraded_vehicles") or [])
        st_targets = st.get("targets") or {}
        mstate = self.master_state(t_wall_s)
        rows = []
        for tid in self.targets():
            got = self._results.get(tid)
            if got is not None and (t_wall_s - got[1] <= RESULT_FRESH_S or tid not in st_targets):
                row = self._row_from_result(got[0], got[1], grades, degraded_ids)
                arrival = got[1]
            elif tid in st_targets:
                row = self._row_from_status(tid, st_targets[tid], grades)
                arrival = self.status_wall_s
            else:
                continue
            self._stale(row, arrival, t_wall_s, mstate)
            row["instruction"] = instruction(row, mstate)
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
        clock = st.get("clock") or {}
        return {
            "version": self.version, "t_wall_s": t_wall_s,
            "master": {"id": st.get("master_id"), "state": mstate, "phase": st.get("phase"),
                       "waiting_for": st.get("waiting_for"), "fix": fix_name(st.get("master_fix")),
                       "clock_synchronised": st.get("time_synchronised"), "clock_offset_s": clock.get("offset_s"),
                       "timeout_s": _finite(st.get("timeout_s")) or DEFAULT_TIMEOUT_S,
                       "clock_alarms": sorted(r["id"] for r in rows if r.get("clock_alarm")),
                       "t_rel_s": _finite(st.get("t_rel_s")), "t_gps_s": _finite(st.get("t_gps_s")),
                       "processed": st.get("processed"), "rejected": st.get("rejected") or {},
                       "pipeline_ms_p99": _finite(st.get("pipeline_ms_p99")),
                       "e2e_ms_p99": _finite(st.get("e2e_ms_p99")), "can_frames": st.get("can_frames"),
                       "udp_datagrams": st.get("udp_datagrams"), "source": st.get("source"),
                       "status_age_s": None if math.isnan(self.status_wall_s) else t_wall_s - self.status_wall_s},
            "rows": rows, "lanes": lanes, "vehicles": self._vehicle_panel(t_wall_s),
            "trails": {tid: [[x, y] for _, x, y in tr] for tid, tr in self._trails.items()},
            "monitor": {"received": self.received, "decoded": self.decoded, "malformed": self.malformed,
                        "status_updates": self.status_updates, "waited_s": t_wall_s - self.first_wall_s}}

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
