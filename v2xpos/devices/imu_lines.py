"""Live line-based IMU in the recorded ``csv_g_dps_ms`` format -> :class:`ImuRecord`.

Format (``v2xpos.datasets.imu_csv``): ``ax, ay, az`` [g], ``gx, gy, gz`` [deg/s], ``counter``
[ms since IMU power-up], one sample per line, LF or CR LF. Converted to SI with standard gravity
(``acc_mps2 = g0 * a``) and ``gyro_rps = radians(g)``. The counter is unwrapped as a uint32
millisecond count. The line's arrival time (its LF) goes with it; the consumer maps the counter to
GPS time with the online lower-envelope model (``v2xpos.devices.clock_model``), as the recorded
reader does with the TIMETAG arrivals.

Malformed lines are counted and skipped, as in the file reader: wrong field count or non-numbers;
fields printed with a different number of decimals than the stream uses (how a line cut at its
start shows: the stream was opened mid-line, or bytes were lost); a counter that is not after the
previous one.
"""
from __future__ import annotations

import re

import numpy as np

from v2xpos.datasets.imu_csv import COUNTER_MODULUS_MS, STANDARD_GRAVITY_MPS2
from v2xpos.datasets.issues import ParseIssues
from v2xpos.devices.records import ImuRecord

_NUMBER = r"([-+]?[0-9]+\.([0-9]+))"
_SEP = r"[ \t]*,[ \t]*"
_LINE = re.compile(r"^[ \t]*" + _SEP.join([_NUMBER] * 6) + _SEP + r"([0-9]+)[ \t]*\r?\n?\Z")
_PROBE_LINES = 20


class CsvImuDecoder:
    """Decode ``csv_g_dps_ms`` lines (see module docstring). ``decode(line, arrival_s)``."""

    def __init__(self, name: str = "imu"):
        self.issues = ParseIssues(name)
        self.samples = 0
        self.counter_wraps = 0
        self._decimals: tuple[int, ...] | None = None
        self._votes: dict[tuple[int, ...], int] = {}
        self._held: list[tuple[bytes, float, int]] = []
        self._last_ms: int | None = None
        self._wrap_ms = 0

    def decode(self, raw: bytes, arrival_s: float, where: int = 0) -> list[ImuRecord]:
        text = raw.decode("ascii", "replace")
        if not text.strip():
            return []
        m = _LINE.match(text)
        if m is None:
            self.issues.add(where, f"expected 7 numeric fields: {text.strip()[:60]!r}")
            return []
        decimals = tuple(len(m.group(2 * k + 2)) for k in range(6))
        if self._decimals is None:
            # learn the stream's decimals from its first lines; hold them until then
            self._votes[decimals] = self._votes.get(decimals, 0) + 1
            self._held.append((raw, arrival_s, where))
            if len(self._held) < _PROBE_LINES:
                return []
            self._decimals = max(self._votes, key=self._votes.get)
            held, self._held = self._held, []
            out: list[ImuRecord] = []
            for r, a, w in held:
                out += self.decode(r, a, w)
            return out
        if decimals != self._decimals:
            self.issues.add(where, f"fields printed with {decimals} decimals, the stream uses "
                                   f"{self._decimals}: line cut short")
            return []
        values = np.array([float(m.group(2 * k + 1)) for k in range(6)])
        ms = int(m.group(13))
        if ms >= COUNTER_MODULUS_MS:
            self.issues.add(where, f"counter {ms} ms out of range")
            return []
        if self._last_ms is not None:
            full = ms + self._wrap_ms
            if full < self._last_ms - COUNTER_MODULUS_MS // 2:
                self._wrap_ms += COUNTER_MODULUS_MS
                self.counter_wraps += 1
            full = ms + self._wrap_ms
            if full <= self._last_ms:
                self.issues.add(where, f"counter {ms} ms not after the previous sample")
                return []
        full = ms + self._wrap_ms
        self._last_ms = full
        self.samples += 1
        return [ImuRecord(counter_s=full * 1e-3, acc_mps2=values[0:3] * STANDARD_GRAVITY_MPS2,
                          gyro_rps=np.radians(values[3:6]), arrival_s=arrival_s)]

    def flush(self) -> list[ImuRecord]:
        """Decode the lines still held for learning the decimals (a stream shorter than the probe)."""
        if self._decimals is None and self._held:
            self._decimals = max(self._votes, key=self._votes.get)
            held, self._held = self._held, []
            out: list[ImuRecord] = []
            for r, a, w in held:
                out += self.decode(r, a, w)
            return out
        return []
