"""The live status of one vehicle service (master or slave), published at 1 Hz and printed as a line.

``VehicleStatus.snapshot(source, clock, nav)`` makes the JSON document a service publishes on
``v2xpos/<fleet>/vehicle/<id>/status`` (a slave) or inside its master status (``"vehicle"``), and
that the monitor's vehicle panel shows. It gathers what the pre-drive checklist (docs/field.md,
section 7) reads, in one place:

* ``clock``: the session clock's status (``SessionClock.status()``: for live devices the receiver
  time against the host clock, ``offset_s``, ``synchronised``) and ``gps_minus_wall_s``, the
  session GPS time minus the host's wall clock (on one bench, two services whose values differ
  run on different clocks);
* ``streams``: per device stream whether its transport is connected, the messages (frames, or lines
  of a text stream) per second since the last snapshot (``rate_hz``), the bytes per second and the
  malformed records;
* ``imu_clock``: the IMU counter's clock model (points, span, ``drift_ppm``);
* ``corrections``: the age of the last RTCM message received or relayed;
* ``filter``: the latest navigation state: time, its age against the session clock (``age_s``),
  fix, heading determined, consistent, verified, the filter's reason
  (``v2xpos.types.FilterReason``) and protection level, position and yaw sigmas.

``status_line(doc)`` is the one-line summary a service prints every few seconds (``--quiet`` turns
it off); ``reason_instruction`` turns a filter reason into what the operator should do.
"""
from __future__ import annotations

import math
import time
from typing import Any

from v2xpos.types import FilterReason, FixStatus

STATUS_PERIOD_S = 1.0
"""Live status period of every vehicle service [s]."""
STATUS_LINE_PERIOD_S = 5.0
"""A service prints its one-line status this often [s]."""

REASON_INSTRUCTIONS: dict[str, str] = {
    "OK": "",
    "ALIGNING": "filter aligning: wait for a GNSS fix",
    "HEADING_PENDING": "heading pending: drive off (or declare a dual-antenna baseline)",
    "COASTING": "coasting without GNSS: check the receiver and the sky view",
    "TIME_OFFSET_CONVERGING": "IMU time offset converging: keep driving",
    "SETUP_UNVERIFIED": "lever arm unverified: drive a turn",
    "PROTECTION_EXCEEDED": "protection level above its limit: drive on, check the set-up",
    "TEST_POSITION": "position test failed: check the lever arm and the receiver",
    "TEST_VELOCITY": "velocity test failed: check the IMU mounting and time offset",
    "TEST_SEPARATION": "solution-separation test failed: the declared set-up is wrong, survey it",
    "RECEIVER_FLOAT": "receiver float: check the corrections and the sky view",
}
"""What the operator does about each ``FilterReason`` (the monitor's instruction column)."""


def reason_instruction(reason: str | int | None) -> str:
    """The instruction for a filter reason (its name or code); empty for OK or None."""
    if reason is None:
        return ""
    if not isinstance(reason, str):
        try:
            reason = FilterReason(int(reason)).name
        except ValueError:
            return f"filter reason {reason}"
    return REASON_INSTRUCTIONS.get(reason, f"filter: {reason.lower()}")


def _finite(x: Any) -> float | None:
    try:
        x = float(x)
    except (TypeError, ValueError):
        return None
    return x if math.isfinite(x) else None


def filter_status(nav: Any, t_now_gps_s: float | None = None) -> dict | None:
    """The ``filter`` section of a vehicle status from its latest NavState (None before the first)."""
    if nav is None:
        return None
    reason = getattr(nav, "reason", FilterReason.OK)
    try:
        reason_name = FilterReason(int(reason)).name
    except ValueError:
        reason_name = str(int(reason))
    sd = [float(x) for x in nav.pos_sd_m]
    return {"t_gps_s": float(nav.t_s), "age_s": None if t_now_gps_s is None else t_now_gps_s - float(nav.t_s),
            "fix": FixStatus(int(nav.fix)).name, "heading_determined": bool(getattr(nav, "attitude_ok", True)),
            "consistent": bool(getattr(nav, "consistent", True)), "verified": bool(getattr(nav, "verified", True)),
            "reason": reason_name, "protection_m": _finite(getattr(nav, "protection_m", math.nan)),
            "sigma_h_m": math.hypot(sd[0], sd[1]), "yaw_sd_deg": math.degrees(float(nav.att_sd_rad[2]))}


class VehicleStatus:
    """Builds a vehicle's status documents; keeps the previous counters to give rates."""

    def __init__(self, role: str, vehicle_id: str, fleet: str):
        self.role, self.vehicle_id, self.fleet = role, vehicle_id, fleet
        self._prev: dict[str, tuple[float, int, int]] = {}    # stream -> (wall s, records, bytes)
        self.seq = 0

    def _streams(self, streams: dict, t_wall: float) -> dict:
        out = {}
        for name, st in streams.items():
            tr = st.get("transport") or {}
            framing = st.get("framing") or {}
            frames = framing.get("frames")
            records = int(sum(frames.values()) if isinstance(frames, dict) else framing.get("lines", st.get("records", 0)))
            nbytes = int(tr.get("bytes_in", 0))
            prev = self._prev.get(name)
            rate = bps = None
            if prev is not None and t_wall > prev[0]:
                rate = (records - prev[1]) / (t_wall - prev[0])
                bps = (nbytes - prev[2]) / (t_wall - prev[0])
            self._prev[name] = (t_wall, records, nbytes)
            out[name] = {"format": st.get("format"), "connected": tr.get("connected"), "rate_hz": rate,
                         "bytes_per_s": bps, "messages": records, "malformed": st.get("malformed", 0),
                         "disconnects": tr.get("disconnects", 0), "last_error": tr.get("last_error")}
        return out

    def snapshot(self, source: Any, clock: Any, nav: Any, extra: dict | None = None,
                 t_wall_s: float | None = None) -> dict:
        """The status document (see the module docstring); ``extra`` is merged at the top level."""
        t_wall = time.time() if t_wall_s is None else t_wall_s
        self.seq += 1
        src = source.status() if source is not None else {}
        now = None
        clock_doc: dict = {}
        if clock is not None:
            now = clock.now_gps_s()
            clock_doc = dict(clock.status())
            clock_doc["synchronised"] = bool(clock.synchronised())
            clock_doc["gps_minus_wall_s"] = now - t_wall
        doc = {"role": self.role, "id": self.vehicle_id, "fleet": self.fleet, "seq": self.seq, "t_wall_s": t_wall,
               "t_gps_s": now, "source": getattr(source, "name", None), "clock": clock_doc,
               "streams": self._streams(src.get("streams") or {}, t_wall), "imu_clock": src.get("imu_clock"),
               "gnss": src.get("gnss"), "filter": filter_status(nav, now)}
        counts = src.get("counts")
        if counts is not None:
            doc["counts"] = counts
        if extra:
            doc.update(extra)
        return doc


def _ms(x: Any) -> str:
    v = _finite(x)
    return "-" if v is None else f"{v * 1e3:.0f} ms"


def status_line(doc: dict) -> str:
    """One line of a vehicle status: clock, streams and rates, filter state and reason."""
    clock = doc.get("clock") or {}
    parts = [f"{doc.get('role', 'vehicle')} {doc.get('id', '?')}:"]
    sync = clock.get("synchronised")
    off = clock.get("offset_s")
    parts.append("clock " + ("?" if sync is None else "ok" if sync else "UNSYNCED")
                 + ("" if off is None else f" offset {_ms(off)}"))
    for name, st in (doc.get("streams") or {}).items():
        rate = _finite(st.get("rate_hz"))
        conn = st.get("connected")
        parts.append(f"{name} " + ("down" if conn is False else "-" if rate is None else f"{rate:.0f}/s"))
    drift = (doc.get("imu_clock") or {}).get("drift_ppm")
    if _finite(drift) is not None:
        parts.append(f"imu drift {drift:.0f} ppm")
    corr = doc.get("corrections") or {}
    if corr.get("age_s") is not None:
        parts.append(f"corrections {corr['age_s']:.1f} s old")
    f = doc.get("filter")
    if f is None:
        parts.append("filter not started")
    else:
        state = "verified" if f["verified"] and f["consistent"] else "INCONSISTENT" if not f["consistent"] else \
            "unverified"
        pl = f.get("protection_m")
        parts.append(f"filter {f['fix']} {'heading ok' if f['heading_determined'] else 'heading pending'} {state}"
                     + ("" if pl is None else f" PL {pl:.2f} m") + f" sigma {f['sigma_h_m']:.3f} m")
        hint = reason_instruction(f.get("reason"))
        if hint:
            parts.append(f"-> {hint}")
    for key in ("sent", "processed"):
        if doc.get(key) is not None:
            parts.append(f"{key} {doc[key]}")
    return "  ".join(parts)
