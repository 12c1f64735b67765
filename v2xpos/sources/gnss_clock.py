"""``HostGnssClock``: the session clock of a live vehicle -- GPS time from the host clock, checked
continuously against the receiver's own time.

GPS time. ``now_gps_s() = unix_to_gps_seconds(time.time())``: the host's UTC (POSIX, kept by
chrony/ntpd; in the field disciplined by the receiver's PPS, so within microseconds of GPS time)
plus GPS - UTC from the leap-second table of ``v2xpos.timebase``.

The check against the receiver. Each solution message says when it was valid in the receiver's
GPS time (NAV-PVT iTOW; GGA/RMC UTC time + leap seconds) and the transport stamps when it arrived
on the host clock. Their difference

    d_i = arrival_i - t_i = latency_i + offset        (offset: host clock minus receiver GPS time)

mixes the message output latency (computation + serial transfer + USB/OS buffering: 24-74 ms on
a u-blox F9P recording at 4 Hz) with the clock offset, and one message cannot separate them. The
clock therefore uses the minimum over a sliding window (``window_s``) -- the message that went
through fastest -- and subtracts a configured ``latency_floor_s``, the receiver's minimum output
latency measured once on the bench with a known-good host clock (``status()["receiver"]
["min_delay_s"]`` is that figure when the host is disciplined)::

    offset_s = min_{window} d_i - latency_floor_s

Limits, stated: (1) a constant error in the floor is indistinguishable from a clock offset, so the
check resolves an offset only to the accuracy of the floor and to the spread of the window's
minimum (a few ms at 4-10 Hz); (2) a host that is *behind* shows at once (negative offset, as soon
as one message seems to arrive before it was valid), a host *ahead* only once it exceeds the
floor's uncertainty; (3) a time-pulse message (UBX-TIM-TP) does not improve this on its own: it
announces the next PPS edge in receiver time, but its arrival is as late as any message; the edge
itself must be captured on the host (PPS into chrony or a GPIO), which is what chrony does.
So in the field the host clock *is* the PPS-disciplined time and this check is the alarm that says
when it is not (chrony lost the PPS, wrong leap-second file, a receiver without fix feeding stale
time).

``synchronised()`` is False while |offset_s| > ``max_offset_s`` (default 0.02 s), while no receiver
time arrived within ``stale_after_s``, when the receiver's GPS - UTC (NAV-PVT with fully resolved
time) disagrees with the leap-second table, and, with ``require_kernel_sync``, while the kernel
reports its clock unsynchronised (``adjtimex``: TIME_ERROR / STA_UNSYNC, set by chrony/ntpd).

Emulation only (``v2xpos emulate``; never on a vehicle): a recording's receiver time lies in the
past, so a bench trial shifts (and with ``--speed`` scales) the host clock onto it:
``now_gps_s = emulation_speed * unix_to_gps_seconds(time.time()) + host_time_offset_s``, with the
two numbers the emulator prints. Both default to the identity (0 and 1). ``max_offset_s`` is a
tolerance on the host clock, in host seconds: at ``emulation_speed`` k a host (or emulator) timing
error of d seconds appears as k d on the emulated GPS time, so the offset is checked against
k ``max_offset_s``.
"""
from __future__ import annotations

import ctypes
import ctypes.util
import math
import threading
import time
from collections import deque
from typing import Callable

from v2xpos import timebase
from v2xpos.schema import Key, read_table
from v2xpos.sources.base import SessionClock

CLOCK_SCHEMA = (Key("max_offset_s", float, None, above=0.0), Key("latency_floor_s", float, None),
                Key("window_s", float, None, above=0.0), Key("stale_after_s", float, None, above=0.0),
                Key("host_time_offset_s", float, None), Key("emulation_speed", float, None, above=0.0),
                Key("require_kernel_sync", bool, None))
"""The ``clock = { ... }`` table; absent keys keep ``HostGnssClock``'s defaults."""


class _Timex(ctypes.Structure):
    """The leading fields of Linux ``struct timex`` (adjtimex(2)); the rest is padding."""
    _fields_ = [("modes", ctypes.c_uint), ("offset", ctypes.c_long), ("freq", ctypes.c_long),
                ("maxerror", ctypes.c_long), ("esterror", ctypes.c_long), ("status", ctypes.c_int),
                ("_rest", ctypes.c_byte * 200)]


STA_UNSYNC = 0x0040
TIME_ERROR = 5


def kernel_clock_status() -> dict | None:
    """The kernel's view of its clock discipline (``adjtimex`` read-only): synchronised, estimated
    and maximum error [us]; None where unavailable (not Linux)."""
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
        tx = _Timex()
        state = libc.adjtimex(ctypes.byref(tx))
    except (OSError, AttributeError):
        return None
    if state < 0:
        return None
    return {"synchronised": bool(state != TIME_ERROR and not (tx.status & STA_UNSYNC)),
            "esterror_us": int(tx.esterror), "maxerror_us": int(tx.maxerror), "state": int(state)}


class HostGnssClock(SessionClock):
    """GPS time from the host clock, checked against the receiver (see module docstring).

    ``observe(t_receiver_s, arrival_s, gps_minus_utc_s=nan, message="")`` feeds one receiver time
    statement (the device source calls it for every NAV-PVT / GGA); ``host_gps_s()`` is the stamp
    transports use for arrivals (the same time as ``now_gps_s``).
    """

    def __init__(self, max_offset_s: float = 0.02, latency_floor_s: float = 0.0, window_s: float = 10.0,
                 stale_after_s: float = 5.0, host_time_offset_s: float = 0.0, emulation_speed: float = 1.0,
                 require_kernel_sync: bool = False, time_fn: Callable[[], float] = time.time):
        self.max_offset_s = float(max_offset_s)
        self.latency_floor_s = float(latency_floor_s)
        self.window_s = float(window_s)
        self.stale_after_s = float(stale_after_s)
        self.host_time_offset_s = float(host_time_offset_s)
        self.speed = float(emulation_speed)
        self.require_kernel_sync = bool(require_kernel_sync)
        self.time_fn = time_fn
        self._lock = threading.Lock()
        self._window: deque[tuple[float, float]] = deque()      # (arrival_s, delay_s)
        self._min: deque[tuple[float, float]] = deque()         # monotone deque for the window minimum
        self.observations = 0
        self.last_arrival_s = -math.inf
        self.last_message = ""
        self.last_delay_s = math.nan
        self.receiver_leap_s = math.nan
        self.leap_mismatches = 0

    # ------------------------------------------------------------------ time
    def host_gps_s(self) -> float:
        """GPS seconds of the host clock now (shifted/scaled only in emulation)."""
        return self.speed * float(timebase.unix_to_gps_seconds(self.time_fn())) + self.host_time_offset_s

    def now_gps_s(self) -> float:
        return self.host_gps_s()

    def wall_of(self, t_gps_s: float) -> float:
        return self.time_fn() + (t_gps_s - self.now_gps_s()) / self.speed

    # ------------------------------------------------------------------ receiver comparison
    def observe(self, t_receiver_s: float, arrival_s: float, gps_minus_utc_s: float = math.nan,
                message: str = "") -> None:
        """One receiver time statement: valid at ``t_receiver_s`` (receiver GPS time), in hand on
        the host at ``arrival_s`` (host GPS time)."""
        if not (math.isfinite(t_receiver_s) and math.isfinite(arrival_s)):
            return
        delay = arrival_s - t_receiver_s
        with self._lock:
            self.observations += 1
            self.last_arrival_s = arrival_s
            self.last_message = message
            self.last_delay_s = delay
            self._window.append((arrival_s, delay))
            while self._min and self._min[-1][1] >= delay:
                self._min.pop()
            self._min.append((arrival_s, delay))
            self._expire(arrival_s)
            if math.isfinite(gps_minus_utc_s):
                self.receiver_leap_s = gps_minus_utc_s
                if gps_minus_utc_s != float(timebase.gps_minus_utc_at_gps(t_receiver_s)):
                    self.leap_mismatches += 1

    def _expire(self, now_s: float) -> None:
        cut = now_s - self.window_s
        while self._window and self._window[0][0] < cut:
            self._window.popleft()
        while self._min and self._min[0][0] < cut:
            self._min.popleft()

    def min_delay_s(self) -> float:
        """Minimum of arrival - validity over the window [s] (NaN without observations)."""
        with self._lock:
            return self._min[0][1] if self._min else math.nan

    def offset_s(self) -> float:
        """Estimated host clock minus receiver GPS time [s] (module docstring), NaN without data."""
        return self.min_delay_s() - self.latency_floor_s

    def _verdict(self) -> tuple[bool, str]:
        now = self.now_gps_s()
        with self._lock:
            self._expire(now)
            age = now - self.last_arrival_s
            mn = self._min[0][1] if self._min else math.nan
            leap_bad = (math.isfinite(self.receiver_leap_s)
                        and self.receiver_leap_s != float(timebase.gps_minus_utc_at_gps(now)))
        if not math.isfinite(mn) or age > self.stale_after_s:
            return False, f"no receiver time within {self.stale_after_s:g} s"
        off = mn - self.latency_floor_s
        limit_s = self.max_offset_s * self.speed
        if abs(off) > limit_s:
            return False, f"host - receiver offset {off * 1e3:.1f} ms beyond +-{limit_s * 1e3:.0f} ms"
        if leap_bad:
            return False, "receiver GPS-UTC differs from the leap-second table"
        if self.require_kernel_sync:
            k = kernel_clock_status()
            if k is None or not k["synchronised"]:
                return False, "kernel clock not synchronised (chrony/ntpd)"
        return True, "ok"

    def synchronised(self) -> bool:
        return self._verdict()[0]

    def status(self) -> dict:
        ok, why = self._verdict()
        now = self.now_gps_s()
        with self._lock:
            delays = [d for _, d in self._window]
            out = {"kind": "HostGnssClock", "gps_now_s": now, "synchronised": ok, "reason": why,
                   "max_offset_s": self.max_offset_s, "latency_floor_s": self.latency_floor_s,
                   "receiver": {"message": self.last_message, "observations": self.observations,
                                "age_s": now - self.last_arrival_s if self.observations else None,
                                "min_delay_s": self._min[0][1] if self._min else None,
                                "median_delay_s": float(sorted(delays)[len(delays) // 2]) if delays else None,
                                "last_delay_s": self.last_delay_s if self.observations else None,
                                "window_s": self.window_s, "gps_minus_utc_s": self.receiver_leap_s
                                if math.isfinite(self.receiver_leap_s) else None,
                                "leap_mismatches": self.leap_mismatches},
                   "leap_table_gps_minus_utc_s": float(timebase.gps_minus_utc_at_gps(now))}
        off = out["receiver"]["min_delay_s"]
        out["offset_s"] = None if off is None else off - self.latency_floor_s
        if self.host_time_offset_s or self.speed != 1.0:
            out["emulation"] = {"host_time_offset_s": self.host_time_offset_s, "emulation_speed": self.speed}
        out["kernel"] = kernel_clock_status()
        return out


def clock_from_config(table: dict | None, where: str) -> HostGnssClock:
    """HostGnssClock from a ``clock = { ... }`` table (``CLOCK_SCHEMA``); ValueError naming
    ``where`` and the key."""
    kw = read_table({} if table is None else table, CLOCK_SCHEMA, where)
    return HostGnssClock(**{k: v for k, v in kw.items() if v is not None})
