"""RTKLIB solution files (``.pos``, "lat/lon/height" format).

Layout (RTKLIB 2.4.x manual, appendix B "Output file formats"): ``%`` comment lines, the last of
which names the columns; then one line per epoch:
``time  lat(deg)  lon(deg)  height(m)  Q  ns  sdn sde sdu sdne sdeu sdun [m]  age(s)  ratio``
optionally followed by ``vn ve vu [m/s]`` and ``sdvn sdve sdvu sdvne sdveu sdvun``.
Time is either ``yyyy/mm/dd hh:mm:ss.sss`` or ``week tow``, in GPST (or UTC when the header
says ``UTC``). Q: 1 fixed, 2 float, 3 SBAS, 4 DGPS, 5 single, 6 PPP.

Conventions of the result: t_s in GPS seconds; lat/lon in radians; the height is kept as the
file gives it and its datum is recorded in ``GnssData.height_datum`` (RTKLIB writes ellipsoidal
heights unless configured for geodetic/MSL heights; the shared drive_0708 and walk_0827 files are
above mean sea level, hence the default ``"msl"``). Velocity ``(vn, ve, vu)`` becomes NED
``(vn, ve, -vu)``; its sigmas keep their magnitudes.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from v2xpos import timebase
from v2xpos.datasets.issues import ParseIssues
from v2xpos.types import FixStatus, GnssData

_DEFAULT_COLUMNS = ["GPST", "latitude(deg)", "longitude(deg)", "height(m)", "Q", "ns", "sdn(m)",
                    "sde(m)", "sdu(m)", "sdne(m)", "sdeu(m)", "sdun(m)", "age(s)", "ratio"]
_REQUIRED = ("latitude(deg)", "longitude(deg)", "height(m)", "Q", "sdn(m)", "sde(m)", "sdu(m)")
_VELOCITY = ("vn(m/s)", "ve(m/s)", "vu(m/s)")
_VELOCITY_SD = ("sdvn", "sdve", "sdvu")


def _columns_from_header(line: str) -> list[str] | None:
    tokens = line.lstrip("%").split()
    if not tokens or tokens[0] not in ("GPST", "UTC", "JST") or "latitude(deg)" not in tokens:
        return None
    return tokens


def _parse_time_s(date_tok: str, time_tok: str, time_system: str) -> float:
    if "/" in date_tok:
        y, mo, d = (int(v) for v in date_tok.split("/"))
        hh, mm, ss = time_tok.split(":")
        t = timebase.gpst_calendar_to_gps_seconds(y, mo, d, int(hh), int(mm), float(ss))
        if time_system == "UTC":
            return float(timebase.unix_to_gps_seconds(t + timebase.GPS_UNIX_OFFSET_S))
        return t
    return float(timebase.gps_seconds_from_week_tow(int(date_tok), float(time_tok)))


def read_rtklib_pos(path: str | Path, height_datum: str = "msl") -> tuple[GnssData, ParseIssues]:
    """Read an RTKLIB ``.pos`` file -> (GnssData, ParseIssues).

    Lines that cannot be parsed (wrong field count, non-numbers, non-finite values, time not
    increasing) and a last line without end-of-line (truncated by the logger) are skipped and
    counted with their line numbers. Raises ValueError for a file in another solution format
    (e.g. ECEF x/y/z) and OSError when it cannot be read.
    """
    path = Path(path)
    issues = ParseIssues(str(path))
    raw = path.read_bytes()
    text = raw.decode("ascii", errors="replace")
    lines = text.split("\n")
    last_complete = text.endswith("\n")
    if last_complete:
        lines = lines[:-1]
    columns = list(_DEFAULT_COLUMNS)
    times, llh, q, sd, vel, vel_sd = [], [], [], [], [], []
    col_index: dict[str, int] = {}
    n_tokens = 0

    def set_columns(cols: list[str]) -> None:
        nonlocal col_index, n_tokens
        if cols[0] not in ("GPST", "UTC"):
            raise ValueError(f"{path}: time system {cols[0]!r} is not supported (need GPST or UTC)")
        missing = [c for c in _REQUIRED if c not in cols]
        if missing:
            raise ValueError(f"{path}: solution format not supported, missing column(s) {missing}")
        # The time column spans two whitespace-separated tokens in both time formats.
        col_index = {name: i + 1 for i, name in enumerate(cols)}
        n_tokens = len(cols) + 1

    set_columns(columns)
    time_system = "GPST"
    last_t = -math.inf
    for line_no, line in enumerate(lines, start=1):
        stripped = line.strip()
        if not stripped:
            continue
        if stripped.startswith("%"):
            cols = _columns_from_header(stripped)
            if cols is not None:
                set_columns(cols)
                time_system = cols[0]
            continue
        if line_no == len(lines) and not last_complete:
            issues.add(line_no, "truncated last line (no end of line)")
            continue
        tokens = stripped.split()
        if len(tokens) != n_tokens:
            issues.add(line_no, f"expected {n_tokens} fields, found {len(tokens)}")
            continue
        try:
            t = _parse_time_s(tokens[0], tokens[1], time_system)
            values = {name: float(tokens[i]) for name, i in col_index.items() if name not in
                      ("GPST", "UTC")}
        except (ValueError, IndexError, OverflowError) as exc:
            issues.add(line_no, f"unparsable field: {exc}")
            continue
        core = [values[c] for c in _REQUIRED]
        if not all(math.isfinite(v) for v in core) or not -90.0 <= values["latitude(deg)"] <= 90.0:
            issues.add(line_no, "non-finite or out-of-range position")
            continue
        if t <= last_t:
            issues.add(line_no, f"time {t:.3f} s not after the previous epoch {last_t:.3f} s")
            continue
        last_t = t
        times.append(t)
        llh.append((math.radians(values["latitude(deg)"]), math.radians(values["longitude(deg)"]),
                    values["height(m)"]))
        q.append(int(FixStatus.from_rtklib_q(int(round(values["Q"])))))
        sd.append((values["sdn(m)"], values["sde(m)"], values["sdu(m)"]))
        if all(c in values for c in _VELOCITY):
            vel.append((values["vn(m/s)"], values["ve(m/s)"], -values["vu(m/s)"]))
        if all(c in values for c in _VELOCITY_SD):
            vel_sd.append((abs(values["sdvn"]), abs(values["sdve"]), abs(values["sdvu"])))
    n = len(times)
    gnss = GnssData(
        t_s=np.asarray(times, dtype=float),
        lla=np.asarray(llh, dtype=float).reshape(n, 3),
        fix=np.asarray(q, dtype=np.int8),
        sd_ned_m=np.abs(np.asarray(sd, dtype=float).reshape(n, 3)),
        vel_ned_mps=np.asarray(vel, dtype=float).reshape(n, 3) if len(vel) == n and n else None,
        vel_sd_ned_mps=np.asarray(vel_sd, dtype=float).reshape(n, 3) if len(vel_sd) == n and n
        else None,
        height_datum=height_datum,
    )
    return gnss, issues
