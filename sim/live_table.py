"""Live terminal table of a running master, fed by its status JSON on
``v2xpos/<fleet>/master/<id>/status`` (zenoh). On a terminal the table is redrawn in place
(ANSI cursor-home + clear); when stdout is not a tty one plain-text block is printed every
``plain_every_s`` seconds, so logs stay readable.

Columns: target, kind, status, range [m], bearing [deg], gap [m] to the nearest target point from
the master measurement point, TTC [s], latency [ms] (master time - target time of validity),
accepted / rejected message counts, |range error| [m] against the simulator truth when a
scenario is given (the demo knows the truth; a field monitor would not), and the IMU grades of the
target's units (DEGRADED when its results are flagged).
"""
from __future__ import annotations

import json
import math
import sys
import threading
import time
from typing import TextIO

import numpy as np

from v2xpos.link import Link, LinkConfig
from v2xpos.wire import status_key
from v2xpos.monitor.table import fit_number


class LiveTable:
    def __init__(self, link_cfg: LinkConfig, fleet: str, master_id: str, scenario=None,
                 out: TextIO | None = None, plain_every_s: float = 5.0):
        out = sys.stdout if out is None else out      # resolved per call: a stream bound at import may be closed
        self.link = Link(link_cfg)
        self.scenario = scenario
        self.out = out
        self.tty = out.isatty()
        self.plain_every_s = plain_every_s
        self._last_plain = 0.0
        self._lock = threading.Lock()
        self.latest: dict | None = None
        self.updates = 0
        self.link.subscribe(status_key(fleet, master_id), self._on_status)

    def _on_status(self, payload: bytes, key: str, att, t_arr: float) -> None:
        try:
            st = json.loads(payload)
        except ValueError:
            return
        with self._lock:
            self.latest = st
            self.updates += 1

    def render(self, st: dict) -> str:
        def f(x, fmt):
            # fitted to the column (v2xpos.monitor.table.fit_number): a TTC of 12436 s never
            # widens it; one space keeps it apart from the column before
            width = int(fmt.split(".")[0]) if fmt[0].isdigit() else 0
            decimals = int(fmt.split(".")[1].rstrip("f")) if "." in fmt else 0
            if width == 0:
                return "-" if x is None or (isinstance(x, float) and not math.isfinite(x)) else format(x, fmt)
            return " " + fit_number(x, width - 1, decimals)
        lines = [f"master {st.get('master_id')}  t={st.get('t_rel_s', 0):6.1f} s  fix={st.get('master_fix')}  "
                 f"processed={st.get('processed')}  pipeline p50/p99={f(st.get('pipeline_ms_p50'), '.2f')}/"
                 f"{f(st.get('pipeline_ms_p99'), '.2f')} ms  e2e p99={f(st.get('e2e_ms_p99'), '.2f')} ms  "
                 f"CAN={st.get('can_frames')} UDP={st.get('udp_datagrams')}  rejected={st.get('rejected')}",
                 f"{'target':<7}{'kind':<11}{'status':<12}{'range':>8}{'brg':>7}{'gap':>8}{'ttc':>7}"
                 f"{'lat_ms':>8}{'acc':>7}{'rej':>5}{'|dR|':>8}  imu"]
        grades = st.get("imu_grades") or {}
        for vid, t in sorted(st.get("targets", {}).items()):
            last = t.get("last") or {}
            d_range = None
            if self.scenario is not None and last.get("range_m") is not None and vid in self.scenario.actors:
                from sim.evaluate import truth_relative
                tr = truth_relative(self.scenario, vid, np.array([last["t_gps_s"]]))
                d_range = abs(last["range_m"] - float(tr["range_m"][0]))
            lines.append(f"{vid:<7}{t.get('kind', ''):<11}{t.get('status', ''):<12}{f(last.get('range_m'), '8.2f')}"
                         f"{f(last.get('bearing_deg'), '7.1f')}{f(last.get('gap_m'), '8.2f')}"
                         f"{f(last.get('ttc_s'), '7.1f')}{f(last.get('latency_ms'), '8.1f')}"
                         f"{t.get('accepted', 0):>7}{sum(t.get('rejected', {}).values()):>5}{f(d_range, '8.3f')}"
                         f"  {_grade_text(grades.get(vid), t.get('degraded', False))}")
        return "\n".join(lines)

    def refresh(self) -> None:
        with self._lock:
            st = self.latest
        if st is None:
            return
        text = self.render(st)
        if self.tty:
            self.out.write("\x1b[H\x1b[J" + text + "\n")
            self.out.flush()
        elif time.time() - self._last_plain >= self.plain_every_s:
            self._last_plain = time.time()
            self.out.write(text + "\n\n")
            self.out.flush()

    def close(self) -> None:
        self.link.close()


def _grade_text(g: dict | None, degraded: bool) -> str:
    """``imu1:pass imu2:warn ...`` (or the grader status), ``DEGRADED`` when results are flagged."""
    if not g:
        return "-"
    units = g.get("units") or {}
    text = " ".join(f"{u}:{v or '?'}" for u, v in sorted(units.items())) if g.get("status") == "graded" \
        else str(g.get("status"))
    return text + ("  DEGRADED" if degraded else "")
