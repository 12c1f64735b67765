"""Terminal table of a monitor snapshot (``MonitorState.refresh``): one header line for the master
(its state -- live, starting, gone -- the age of its status, its clock), a line per clock alarm,
one line of column names with their units, one line per target, worst first, each with what the
operator should do about it (``do``), then the vehicle panel (one line per vehicle service).
Before anything is heard it says what it waits for, where.

Every number is fitted to its column by ``fit_number``: fewer decimals first, then a k / M suffix
(a TTC of 12436 s prints as ``12k``), so no value ever widens its column or shifts the next one.
"""
from __future__ import annotations

import math

COLUMNS: tuple[tuple[str, int, str], ...] = (
    # (header with unit, width, alignment)
    ("target", 9, "<"), ("kind", 4, "<"), ("status", 18, "<"), ("reason", 26, "<"), ("fix M/T", 13, "<"),
    ("range[m]", 8, ">"), ("x[m]", 8, ">"), ("y[m]", 7, ">"), ("yaw[deg]", 8, ">"), ("sig[m]", 6, ">"),
    ("age[ms]", 7, ">"), ("TTC[s]", 6, ">"), ("IMU", 14, "<"), ("do", 44, "<"))


def fit_number(x: float | None, width: int, decimals: int) -> str:
    """``x`` right-aligned in ``width`` characters: ``-`` when unknown; the decimals are reduced
    until it fits, then a k (1e3) / M (1e6) suffix is used, finally ``>`` / ``<`` with the largest
    value that fits."""
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "-".rjust(width)
    for d in range(decimals, -1, -1):
        s = f"{x:.{d}f}"
        if len(s) <= width:
            return s.rjust(width)
    for scale, suffix in ((1e3, "k"), (1e6, "M")):
        for d in (1, 0):
            s = f"{x / scale:.{d}f}{suffix}"
            if len(s) <= width:
                return s.rjust(width)
    return (">" if x > 0 else "<").rjust(width)


def _cut(text: str | None, width: int) -> str:
    text = "-" if text in (None, "") else str(text)
    return text if len(text) <= width else text[: width - 1] + "~"


def _cell(text: str, width: int, align: str) -> str:
    return f"{text:{align}{width}}"


def header_line() -> str:
    return " ".join(_cell(name, w, a) for name, w, a in COLUMNS)


def row_line(r: dict) -> str:
    kind = {"vehicle": "veh", "pedestrian": "ped"}.get(r.get("kind"), _cut(r.get("kind"), 4))
    fixes = f"{r.get('master_fix') or '-'}/{r.get('target_fix') or '-'}"
    status = r["status"].upper() + (" DEG" if r.get("degraded") else "")
    cells = [_cut(r["id"], 9), kind, _cut(status, 18), _cut(r.get("reason"), 26), _cut(fixes, 13),
             fit_number(r.get("range_m"), 8, 2), fit_number(r.get("x_m"), 8, 2), fit_number(r.get("y_m"), 7, 2),
             fit_number(r.get("rel_yaw_deg"), 8, 1), fit_number(r.get("sigma_h_m"), 6, 3),
             fit_number(r.get("age_ms"), 7, 1), fit_number(r.get("ttc_s"), 6, 1), _cut(r.get("imu"), 14),
             _cut(r.get("instruction"), 44)]
    return " ".join(_cell(c, w, a) for c, (_, w, a) in zip(cells, COLUMNS))


def num(x: float | None, decimals: int) -> str:
    """A number in free text (no column to fit): ``-`` when unknown."""
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "-"
    return f"{x:.{decimals}f}"


def master_line(snap: dict) -> str:
    m = snap["master"]
    mon = snap["monitor"]
    rej = sum((m.get("rejected") or {}).values())
    state = m.get("state") or "live"
    age = m.get("status_age_s")
    if state == "gone":
        return (f"master {m.get('id') or '?'}  GONE: no status for {num(age, 1)} s -- every row below is STALE, "
                f"nothing shown is live")
    head = f"master {m.get('id') or '?'}  {state.upper()}"
    if state == "starting":
        waiting = m.get("waiting_for")
        head += f" (phase {m.get('phase')}" + (f", waiting for {', '.join(waiting)}" if waiting else "") + ")"
    synced = m.get("clock_synchronised")
    clock = "clock -" if synced is None else ("clock ok" if synced else "clock UNSYNCED")
    off = m.get("clock_offset_s")
    if off is not None:
        clock += f" {off * 1e3:.0f} ms"
    return (f"{head}  status {num(age, 1)} s old  fix {m.get('fix') or '-'}  {clock}  t {num(m.get('t_rel_s'), 1)} s  "
            f"processed {m.get('processed') or 0}  rejected {rej}  "
            f"pipeline p99 {num(m.get('pipeline_ms_p99'), 2)} ms  "
            f"e2e p99 {num(m.get('e2e_ms_p99'), 2)} ms  CAN {m.get('can_frames') or 0}  "
            f"UDP {m.get('udp_datagrams') or 0}  |  monitor: {len(snap['rows'])} targets, "
            f"{mon['received']} results received")


def alarm_lines(snap: dict) -> list[str]:
    """One line per clock alarm (a target whose clock differs from the master's)."""
    rows = {r["id"]: r for r in snap["rows"]}
    return [f"CLOCK ALARM {tid}: {rows[tid]['reason'].split('; ')[-1]} -- check both services' time"
            for tid in snap["master"].get("clock_alarms") or [] if tid in rows]


def vehicle_lines(snap: dict) -> list[str]:
    """The vehicle panel: one line per vehicle service (the master's own first)."""
    out = []
    for v in snap.get("vehicles") or []:
        state = v["state"].upper()
        age = "" if v["state"] == "live" else f" ({num(v['status_age_s'], 0)} s ago)"
        out.append(f"[{state}{age}] {v['line']}")
    return ["vehicles:", *("  " + line for line in out)] if out else []


def waiting_text(snap: dict, endpoint: str, fleet: str, master: str | None) -> str:
    """What the monitor shows before it has heard the master."""
    who = f"master {master!r}" if master else "any master"
    return (f"waiting for {who} of fleet {fleet!r} at {endpoint}: nothing heard for "
            f"{num(snap['monitor'].get('waited_s'), 0)} s (is it running? check --connect, --fleet"
            f"{', --master' if master else ''})")


def render(snap: dict, max_rows: int | None = None) -> str:
    """The whole table as text (``max_rows``: at most this many target lines, worst first)."""
    rows = snap["rows"] if max_rows is None else snap["rows"][:max_rows]
    lines = [master_line(snap), *alarm_lines(snap), header_line(), *(row_line(r) for r in rows)]
    if max_rows is not None and len(snap["rows"]) > max_rows:
        lines.append(f"... {len(snap['rows']) - max_rows} more")
    return "\n".join(lines + vehicle_lines(snap))
