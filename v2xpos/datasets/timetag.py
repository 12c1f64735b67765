"""RTKLIB TIMETAG files: when each byte of a logged stream arrived at the logging computer.

Layout (RTKLIB demo5 ``stream.c``, little-endian; described in ../shared/data/README.md):
60-byte ASCII header (``TIMETAG RTKLIB ...``, NUL padded); ``uint32`` tick [ms] at file open;
``uint32`` seconds + ``float64`` fraction = file-open time in GPST counted as seconds since
1970-01-01 without leap seconds; then records ``(uint32 ms since open, uint32 byte offset
reached in the data file)``.

The arrival time of byte offset k is the time of the first record whose offset is >= k: the
logger had that byte in hand no later than then (resolution: one record period, ~16 ms).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from v2xpos import timebase
from v2xpos.datasets.issues import ParseIssues

HEADER_TEXT_BYTES = 60
HEADER_BYTES = HEADER_TEXT_BYTES + 4 + 4 + 8
RECORD_DTYPE = np.dtype([("ms_since_open", "<u4"), ("byte_offset", "<u4")])


@dataclass
class TimeTag:
    """Parsed TIMETAG file.

    open_gps_s: GPS seconds at file open; tick_ms: the logger's tick at open;
    t_s: GPS arrival time of each record [s]; byte_offset: bytes of the data file received by
    then (non-decreasing).
    """
    header: str
    tick_ms: int
    open_gps_s: float
    t_s: np.ndarray
    byte_offset: np.ndarray

    def __len__(self) -> int:
        return len(self.t_s)

    def arrival_gps_s(self, byte_end: np.ndarray) -> np.ndarray:
        """GPS time [s] by which byte offset ``byte_end`` (bytes received) had arrived; NaN for
        offsets beyond the last record."""
        byte_end = np.asarray(byte_end)
        idx = np.searchsorted(self.byte_offset, byte_end, side="left")
        out = np.full(byte_end.shape, np.nan)
        ok = idx < len(self.byte_offset)
        out[ok] = self.t_s[idx[ok]]
        return out


def read_timetag(path: str | Path) -> tuple[TimeTag, ParseIssues]:
    """Read a TIMETAG file -> (TimeTag, ParseIssues).

    A trailing partial record and records whose time or offset go backwards are dropped and
    counted (the record index is reported as the line number). Raises ValueError when the header
    is not a TIMETAG header.
    """
    path = Path(path)
    issues = ParseIssues(str(path))
    raw = path.read_bytes()
    if len(raw) < HEADER_BYTES or not raw.startswith(b"TIMETAG"):
        raise ValueError(f"{path}: not an RTKLIB TIMETAG file (header missing or too short)")
    header = raw[:HEADER_TEXT_BYTES].rstrip(b"\0").decode("ascii", errors="replace")
    tick_ms = int(np.frombuffer(raw, "<u4", 1, HEADER_TEXT_BYTES)[0])
    sec = int(np.frombuffer(raw, "<u4", 1, HEADER_TEXT_BYTES + 4)[0])
    frac = float(np.frombuffer(raw, "<f8", 1, HEADER_TEXT_BYTES + 8)[0])
    open_gps_s = timebase.gpst_unix_style_to_gps_seconds(sec) + frac
    body = raw[HEADER_BYTES:]
    n = len(body) // RECORD_DTYPE.itemsize
    if len(body) % RECORD_DTYPE.itemsize:
        issues.add(n + 1, f"partial record of {len(body) % RECORD_DTYPE.itemsize} bytes at the end")
    rec = np.frombuffer(body, RECORD_DTYPE, n)
    ms = rec["ms_since_open"].astype(np.int64)
    off = rec["byte_offset"].astype(np.int64)
    keep = np.ones(n, dtype=bool)
    if n:
        run_ms = np.maximum.accumulate(ms)
        run_off = np.maximum.accumulate(off)
        back = np.zeros(n, dtype=bool)
        back[1:] = (ms[1:] < run_ms[:-1]) | (off[1:] < run_off[:-1])
        for i in np.flatnonzero(back):
            issues.add(int(i) + 1, "record time or byte offset goes backwards")
        keep = ~back
    tag = TimeTag(header=header, tick_ms=tick_ms, open_gps_s=open_gps_s,
                  t_s=open_gps_s + ms[keep] * 1e-3, byte_offset=off[keep])
    return tag, issues
