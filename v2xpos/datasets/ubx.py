"""u-blox UBX streams: NAV-PVT solutions as GnssData, with the messages' arrival latency.

Framing (u-blox "Interface Description", UBX protocol: frame structure and checksum):
``0xB5 0x62 | class | id | uint16 length (LE) | payload | CK_A CK_B``, 8-bit Fletcher checksum over
class..payload. Frames are located and checked here so that every frame's byte offset is known
(for the TIMETAG arrival time) and bad frames are counted without decoding the large raw
measurement messages; NAV-PVT frames are decoded with pyubx2 (``UBXReader.parse``).

NAV-PVT (UBX-01-07) -> GnssData:
- time of validity t_s = GPS week (from the UTC date in the message, through the leap-second table)
  + iTOW [ms] (the GPS time of week of the navigation epoch);
- lat/lon [deg] -> rad; height = ellipsoidal ``height`` [mm] -> m (``height_datum="ellipsoidal"``);
  ``hMSL`` is kept in ``UbxResult.height_msl_m``, so ``height - hMSL`` is the receiver's geoid
  separation;
- fix: not gnssFixOk -> NONE; carrSoln 2 -> FIXED, 1 -> FLOAT; else fixType 1 -> DEAD_RECKONING,
  2/3/4 -> DGPS if diffSoln else SINGLE; 0/5 -> NONE;
- sigmas: hAcc is taken as the horizontal RMS error, so sd_n = sd_e = hAcc / sqrt(2); sd_d = vAcc;
  velocity (velN, velE, velD) [mm/s] -> m/s with per-axis sigma sAcc.

Latency: arrival_s = GPS time by which the frame's last byte had reached the logger (TIMETAG);
latency = arrival_s - t_s, which includes the receiver's computation and the serial transfer.
"""
from __future__ import annotations

import datetime
import math
import re
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from pyubx2 import UBXReader

from v2xpos import timebase
from v2xpos.datasets.issues import ParseIssues
from v2xpos.datasets.timetag import TimeTag, read_timetag
from v2xpos.types import FixStatus, GnssData

SYNC = b"\xb5\x62"
HEADER_BYTES = 6
CHECKSUM_BYTES = 2
NAV_PVT = (0x01, 0x07)
MAX_PAYLOAD_BYTES = 8192
_NMEA_START = re.compile(rb"\$[A-Z]{5},")


@dataclass
class UbxFrame:
    """One checked UBX frame: class and id, payload-including frame bytes, [start, end) offsets."""
    msg_class: int
    msg_id: int
    start: int
    end: int


def _fletcher8(data: np.ndarray) -> tuple[int, int]:
    """8-bit Fletcher checksum (CK_A, CK_B) of a uint8 array, as u-blox defines it."""
    n = data.size
    weights = np.arange(n, 0, -1, dtype=np.int64)
    d = data.astype(np.int64)
    return int(d.sum() & 0xFF), int((d * weights).sum() & 0xFF)


def scan_frames(raw: bytes, issues: ParseIssues) -> tuple[list[UbxFrame], int]:
    """Locate UBX frames; count frames with a bad checksum or a cut end in ``issues`` (the
    byte offset is reported as the position). Returns (frames, bytes that were not UBX)."""
    buf = np.frombuffer(raw, dtype=np.uint8)
    frames: list[UbxFrame] = []
    pos = 0
    skipped = 0
    n = len(raw)
    while True:
        start = raw.find(SYNC, pos)
        if start < 0:
            skipped += n - pos
            break
        skipped += start - pos
        if start + HEADER_BYTES > n:
            issues.add(start, "UBX frame cut at the end of the stream (header)")
            break
        length = int(buf[start + 4]) | (int(buf[start + 5]) << 8)
        end = start + HEADER_BYTES + length + CHECKSUM_BYTES
        if length > MAX_PAYLOAD_BYTES:
            issues.add(start, f"implausible UBX length {length}")
            pos = start + 2
            continue
        if end > n:
            issues.add(start, "UBX frame cut at the end of the stream")
            break
        ck_a, ck_b = _fletcher8(buf[start + 2:end - 2])
        if ck_a != buf[end - 2] or ck_b != buf[end - 1]:
            issues.add(start, f"UBX checksum mismatch (class 0x{buf[start + 2]:02x} "
                              f"id 0x{buf[start + 3]:02x})")
            pos = start + 2
            continue
        frames.append(UbxFrame(int(buf[start + 2]), int(buf[start + 3]), start, end))
        pos = end
    return frames, skipped


def fix_status_from_nav_pvt(fix_type: int, gnss_fix_ok: int, diff_soln: int,
                            carr_soln: int) -> FixStatus:
    """NAV-PVT fixType / flags -> FixStatus (see module doc)."""
    if not gnss_fix_ok:
        return FixStatus.NONE
    if carr_soln == 2:
        return FixStatus.FIXED
    if carr_soln == 1:
        return FixStatus.FLOAT
    if fix_type == 1:
        return FixStatus.DEAD_RECKONING
    if fix_type in (2, 3, 4):
        return FixStatus.DGPS if diff_soln else FixStatus.SINGLE
    return FixStatus.NONE


@dataclass
class UbxResult:
    """What :func:`read_ubx` found: NAV-PVT solutions, their arrival times and latencies [s]
    (NaN without a timetag), ``height_msl_m`` per epoch, message counts by name, bad frames."""
    gnss: GnssData
    issues: ParseIssues
    arrival_s: np.ndarray
    latency_s: np.ndarray
    height_msl_m: np.ndarray
    message_counts: dict[str, int] = field(default_factory=dict)
    non_ubx_bytes: int = 0
    """Bytes between UBX frames (NMEA sentences, counted in message_counts, or noise)."""

    def summary(self) -> dict:
        lat = self.latency_s[np.isfinite(self.latency_s)]
        out = {"nav_pvt_epochs": len(self.gnss), "message_counts": self.message_counts,
               "unparsable": self.issues.count, "non_ubx_bytes": self.non_ubx_bytes,
               "malformed": self.issues.as_dict()}
        if lat.size:
            out["latency_s"] = {"min": float(lat.min()), "median": float(np.median(lat)),
                                "p95": float(np.percentile(lat, 95)), "max": float(lat.max())}
        if len(self.gnss):
            out["geoid_separation_m"] = float(np.median(self.gnss.lla[:, 2] - self.height_msl_m))
        return out


def _message_name(cls_id: tuple[int, int]) -> str:
    from pyubx2 import UBX_MSGIDS
    return UBX_MSGIDS.get(bytes(cls_id), f"UBX-{cls_id[0]:02X}-{cls_id[1]:02X}")


def read_ubx(path: str | Path, timetag: str | Path | TimeTag | None = None) -> UbxResult:
    """Read a UBX stream (+ optional TIMETAG of its bytes) -> UbxResult (see module doc)."""
    path = Path(path)
    issues = ParseIssues(str(path))
    raw = path.read_bytes()
    frames, skipped = scan_frames(raw, issues)
    counts = Counter(_message_name((f.msg_class, f.msg_id)) for f in frames)
    gaps = [raw[a.end:b.start] for a, b in zip([UbxFrame(0, 0, 0, 0)] + frames, frames + [
        UbxFrame(0, 0, len(raw), len(raw))])]
    nmea = sum(len(_NMEA_START.findall(g)) for g in gaps)
    if nmea:
        counts["NMEA sentences"] = nmea
    rows, ends = [], []
    last_t = -math.inf
    for f in frames:
        if (f.msg_class, f.msg_id) != NAV_PVT:
            continue
        try:
            msg = UBXReader.parse(raw[f.start:f.end])
            itow_ms = int(msg.iTOW)
            utc_guess = timebase.utc_to_gps_seconds(
                datetime.datetime(msg.year, msg.month, msg.day, msg.hour, msg.min,
                                  min(int(msg.second), 59)))
            week = round((utc_guess - itow_ms * 1e-3) / timebase.SECONDS_PER_WEEK)
            t = timebase.gps_seconds_from_week_tow(week, itow_ms * 1e-3)
            fix = fix_status_from_nav_pvt(msg.fixType, msg.gnssFixOk, msg.diffSoln, msg.carrSoln)
            row = (t, math.radians(msg.lat), math.radians(msg.lon), msg.height * 1e-3,
                   msg.hMSL * 1e-3, int(fix), msg.hAcc * 1e-3, msg.vAcc * 1e-3,
                   msg.velN * 1e-3, msg.velE * 1e-3, msg.velD * 1e-3, msg.sAcc * 1e-3)
        except Exception as exc:  # pyubx2 raises several types; any of them is one bad message
            issues.add(f.start, f"NAV-PVT not decodable: {exc}")
            continue
        if not (msg.validDate and msg.validTime):
            issues.add(f.start, "NAV-PVT without valid date/time")
            continue
        if t <= last_t:
            issues.add(f.start, f"NAV-PVT time {t:.3f} s not after the previous epoch")
            continue
        last_t = t
        rows.append(row)
        ends.append(f.end)
    arr = np.asarray(rows, dtype=float).reshape(-1, 12)
    h_sd = arr[:, 6] / math.sqrt(2.0)
    gnss = GnssData(t_s=arr[:, 0], lla=arr[:, 1:4], fix=arr[:, 5].astype(np.int8),
                    sd_ned_m=np.column_stack([h_sd, h_sd, arr[:, 7]]),
                    vel_ned_mps=arr[:, 8:11], vel_sd_ned_mps=np.repeat(arr[:, 11:12], 3, axis=1),
                    height_datum="ellipsoidal")
    arrival = np.full(len(rows), np.nan)
    if timetag is not None:
        if not isinstance(timetag, TimeTag):
            timetag, tag_issues = read_timetag(timetag)
            issues.merge(tag_issues, "timetag: ")
        arrival = timetag.arrival_gps_s(np.asarray(ends, dtype=np.int64))
    return UbxResult(gnss=gnss, issues=issues, arrival_s=arrival, latency_s=arrival - gnss.t_s,
                     height_msl_m=arr[:, 4], message_counts=dict(counts), non_ubx_bytes=skipped)
