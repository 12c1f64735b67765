"""IMU csv logs (format ``csv_g_dps_ms``) with an RTKLIB TIMETAG file for their bytes' arrival.

Format: one sample per line, no header, CRLF or LF: ``ax, ay, az`` [g], ``gx, gy, gz`` [deg/s],
``counter`` [ms since IMU power-up], in the IMU's own axes. Converted to SI: specific force
``acc_mps2 = g0 * a`` with standard gravity g0 = 9.80665 m/s^2 (CGPM 1901, ISO 80000-3) and
``gyro_rps = radians(g)``.

Time mapping (see ``v2xpos.timebase``): the counter is the only sampling clock; the TIMETAG file
gives the GPS time by which each line's last byte (its end of line) had reached the logger. The
counter -> arrival relation is fitted as a lower envelope ``arrival = offset + (1 + drift) *
counter`` and each sample is stamped ``t_s = offset + (1 + drift) * counter_s``: the earliest
arrival consistent with all lines. The true time of validity is earlier by an unknown constant
(sensor filtering + serial transfer of the shortest-delay lines); that residual constant delay is
left to the filter/calibration as ``imu_time_offset_s``.

Malformed lines (wrong field count, non-numbers, a number printed with a different number of
decimals than the rest of the file, which is how a line cut at its start shows; a last line
without end of line; a counter out of sequence) are skipped and counted. Limitation: a line cut
exactly after a minus sign still parses (with the wrong sign).
"""
from __future__ import annotations

import re
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.ndimage import median_filter

from v2xpos import timebase
from v2xpos.geo import G0_MPS2
from v2xpos.datasets.issues import ParseIssues
from v2xpos.datasets.timetag import TimeTag, read_timetag
from v2xpos.types import ImuData

STANDARD_GRAVITY_MPS2 = G0_MPS2
COUNTER_MODULUS_MS = 1 << 32
"""The counter is taken as a uint32 millisecond count: a backwards step of more than half of
this is a wrap, not a malformed line."""
_OUTLIER_WINDOW = 101
_OUTLIER_PERIODS = 10.0

_NUMBER = r"[-+]?[0-9]+\.([0-9]+)"
_SEP = r"[ \t]*,[ \t]*"
_LOOSE = re.compile(r"^[ \t]*" + _SEP.join([_NUMBER] * 6) + _SEP + r"([0-9]+)[ \t]*\r?\Z")


@dataclass
class ImuCsvResult:
    """What :func:`read_imu_csv` found.

    imu: samples (t_s in GPS seconds when a timetag was given, else counter seconds);
    issues: malformed lines; clock: counter -> GPS model (None without timetag);
    rate_hz: sample rate from the counter (1 / mean spacing, logging gaps excluded);
    mean_rate_hz: samples / counter span (gaps included);
    counter_wraps: wraps unwrapped; arrival_delay_s: per-sample arrival - t_s (NaN where the
    timetag does not cover the line), i.e. the delay above the envelope.
    """
    imu: ImuData
    issues: ParseIssues
    clock: timebase.ClockModel | None
    rate_hz: float
    mean_rate_hz: float
    counter_wraps: int = 0
    arrival_delay_s: np.ndarray = field(default_factory=lambda: np.zeros(0))
    timetag_issues: ParseIssues | None = None

    def summary(self) -> dict:
        out = {"samples": len(self.imu), "malformed_lines": self.issues.count,
               "rate_hz": self.rate_hz, "mean_rate_hz": self.mean_rate_hz,
               "counter_wraps": self.counter_wraps, "malformed": self.issues.as_dict()}
        if self.clock is not None:
            out["clock"] = self.clock.as_dict()
        return out


def sample_rate_hz(counter_ms: np.ndarray) -> tuple[float, float]:
    """(1 / mean spacing over spacings < 5 x the median, i.e. without logging gaps;
    samples per counter span) [Hz] from an increasing millisecond counter."""
    dt_ms = np.diff(np.asarray(counter_ms, dtype=float))
    if not dt_ms.size or dt_ms.sum() <= 0:
        return float("nan"), float("nan")
    regular = dt_ms[dt_ms < 5.0 * np.median(dt_ms)]
    return float(1000.0 / regular.mean()), float(1000.0 * dt_ms.size / dt_ms.sum())


def _decimals_in_use(lines: list[str], probe: int = 2000) -> tuple[int, ...] | None:
    """Most common number of decimals of the six value fields among the first well-formed lines."""
    counts: Counter = Counter()
    for line in lines:
        m = _LOOSE.match(line)
        if m is not None:
            counts[tuple(len(m.group(k)) for k in range(1, 7))] += 1
            if sum(counts.values()) >= probe:
                break
    return counts.most_common(1)[0][0] if counts else None


def _strict_pattern(decimals: tuple[int, ...]) -> re.Pattern:
    fields = [rf"[-+]?[0-9]+\.[0-9]{{{d}}}" for d in decimals]
    return re.compile(r"^[ \t]*" + _SEP.join(fields) + _SEP + r"[0-9]+[ \t]*\r?\Z")


def _line_spans(raw: bytes) -> tuple[np.ndarray, np.ndarray, bool]:
    """Start offsets and end offsets (exclusive, after the LF) of every line; whether the last
    line is complete (ends with LF)."""
    if not raw:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64), True
    nl = np.flatnonzero(np.frombuffer(raw, dtype=np.uint8) == 10)
    ends = nl + 1
    complete = True
    if len(raw) and (not len(nl) or ends[-1] != len(raw)):
        ends = np.append(ends, len(raw))
        complete = False
    starts = np.concatenate(([0], ends[:-1]))
    return starts, ends, complete


def read_imu_csv(path: str | Path, timetag: str | Path | TimeTag | None = None) -> ImuCsvResult:
    """Read a ``csv_g_dps_ms`` IMU log and stamp its samples in GPS time (see module doc)."""
    path = Path(path)
    issues = ParseIssues(str(path))
    raw = path.read_bytes()
    starts, ends, last_complete = _line_spans(raw)
    text = raw.decode("ascii", errors="replace")
    lines = text.split("\n")[:len(starts)]
    n_lines = len(lines)
    if n_lines and not last_complete:
        if lines[-1].strip():
            issues.add(n_lines, "truncated last line (no end of line)")
        lines[-1] = ""
    ref_decimals = _decimals_in_use(lines)
    strict = _strict_pattern(ref_decimals) if ref_decimals else _LOOSE
    good = [i for i, line in enumerate(lines) if strict.match(line)]
    for i in sorted(set(range(n_lines)) - set(good)):
        line = lines[i]
        if not line.strip():
            continue
        m = _LOOSE.match(line)
        if m is None:
            issues.add(i + 1, f"expected 7 numeric fields, found {line.count(',') + 1} field(s): "
                              f"{line.strip()[:60]!r}")
        else:
            dec = tuple(len(m.group(k)) for k in range(1, 7))
            issues.add(i + 1, f"fields printed with {dec} decimals, the file uses {ref_decimals}: "
                              "line cut short")
    line_idx = np.asarray(good, dtype=np.int64)
    table = np.loadtxt([lines[i] for i in good], delimiter=",", dtype=float, ndmin=2) \
        if good else np.zeros((0, 7))
    counter = table[:, 6]
    in_range = np.isfinite(table).all(axis=1) & (counter >= 0) & (counter < COUNTER_MODULUS_MS)
    for k in np.flatnonzero(~in_range):
        issues.add(int(line_idx[k]) + 1, f"counter {counter[k]:.6g} ms or a value out of range "
                                         f"(finite numbers, counter 0 .. {COUNTER_MODULUS_MS - 1})")
    table, line_idx = table[in_range], line_idx[in_range]
    values = table[:, :6]
    counter_ms = table[:, 6].astype(np.int64)

    # Counter wraps (uint32 ms), then lone counters out of sequence, then strict increase.
    steps = np.diff(counter_ms)
    wraps = steps < -COUNTER_MODULUS_MS // 2
    counter_wraps = int(wraps.sum())
    if counter_wraps:
        counter_ms = counter_ms + COUNTER_MODULUS_MS * np.concatenate(([0], np.cumsum(wraps)))
    keep = np.ones(counter_ms.size, dtype=bool)
    if counter_ms.size >= 3:
        period_ms = float(np.median(np.diff(counter_ms))) if counter_ms.size > 1 else 1.0
        window = min(_OUTLIER_WINDOW, counter_ms.size | 1)
        local = median_filter(counter_ms.astype(float), size=window, mode="nearest")
        off = np.abs(counter_ms - local) > max(_OUTLIER_PERIODS * abs(period_ms), 1.0)
        for k in np.flatnonzero(off):
            issues.add(int(line_idx[k]) + 1,
                       f"counter {counter_ms[k]} ms out of sequence with its neighbours")
        keep &= ~off
    kept = np.flatnonzero(keep)
    if kept.size > 1:
        previous_max = np.maximum.accumulate(counter_ms[kept])[:-1]
        for j in np.flatnonzero(counter_ms[kept[1:]] <= previous_max):
            k = kept[j + 1]
            issues.add(int(line_idx[k]) + 1, f"counter {counter_ms[k]} ms not after the previous "
                                             f"sample ({int(previous_max[j])} ms)")
            keep[k] = False
    line_idx, values, counter_ms = line_idx[keep], values[keep], counter_ms[keep]
    issues.examples.sort()

    counter_s = counter_ms * 1e-3
    rate_hz, mean_rate_hz = sample_rate_hz(counter_ms)

    clock = None
    tag_issues = None
    t_s = counter_s.copy()
    delay = np.full(counter_s.size, np.nan)
    if timetag is not None and len(line_idx) >= 2:   # fewer samples: the caller reports the file
        tag_name = "the timetag"
        if not isinstance(timetag, TimeTag):
            tag_name = f"the timetag {timetag}"
            timetag, tag_issues = read_timetag(timetag)
        arrival = timetag.arrival_gps_s(ends[line_idx])
        ok = np.isfinite(arrival)
        if ok.sum() < 2:
            raise ValueError(f"{path}: {tag_name} covers fewer than 2 valid lines "
                             f"({len(timetag)} record(s) for {len(line_idx)} line(s))")
        clock = timebase.fit_clock_lower_envelope(counter_s[ok], arrival[ok])
        t_s = clock.to_gps(counter_s)
        delay = arrival - t_s

    imu = ImuData(t_s=t_s, acc_mps2=values[:, 0:3] * STANDARD_GRAVITY_MPS2,
                  gyro_rps=np.radians(values[:, 3:6]), counter_ms=counter_ms)
    return ImuCsvResult(imu=imu, issues=issues, clock=clock, rate_hz=rate_hz,
                        mean_rate_hz=mean_rate_hz, counter_wraps=counter_wraps,
                        arrival_delay_s=delay, timetag_issues=tag_issues)
