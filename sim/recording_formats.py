"""Writers for the file formats of a recording (the inverse of ``v2xpos.datasets``'s readers).

* IMU log ``csv_g_dps_ms``: ``ax,ay,az`` [g = 9.80665 m/s^2], ``gx,gy,gz`` [deg/s] in the IMU's own
  axes, ``counter`` [ms since IMU power-up], printed with 3 decimals, CRLF line ends, no header.
  The logger starts while the first line is on the wire: that line is kept without its head.
* RTKLIB ``TIMETAG`` (layout in ../shared/data/README.md and ``v2xpos.datasets.timetag``):
  60-byte NUL-padded ASCII header, ``uint32`` tick [ms] at open, ``uint32`` seconds + ``float64``
  fraction of the open time in GPST counted from 1970 without leap seconds, then records
  ``(uint32 ms since open, uint32 bytes of the csv received)``, little-endian.
* RTKLIB solution ``.pos`` (RTKLIB 2.4 manual, appendix B, lat/lon/height with velocity):
  ``yyyy/mm/dd hh:mm:ss.sss`` GPST, lat/lon [deg], height [m], Q, ns, sdn/sde/sdu, sdne/sdeu/sdun
  [m], age [s], ratio, vn/ve/vu [m/s], sdvn/sdve/sdvu/sdvne/sdveu/sdvun [m/s].
* Truth tables (csv with one ``#`` header line) and the ``dataset.toml`` descriptor
  (``v2xpos.datasets.loader``).
"""
from __future__ import annotations

import math
import struct
from pathlib import Path

import numpy as np

from v2xpos import timebase
from v2xpos.geo import G0_MPS2

TIMETAG_HEADER_BYTES = 60
POS_COLUMNS = ("%  GPST                  latitude(deg) longitude(deg)  height(m)   Q  ns   sdn(m)   sde(m)"
               "   sdu(m)  sdne(m)  sdeu(m)  sdun(m) age(s)  ratio    vn(m/s)    ve(m/s)    vu(m/s)      sdvn"
               "     sdve     sdvu    sdvne    sdveu    sdvun")
"""The column line of an RTKLIB lat/lon/height solution with velocities (``outvel`` on)."""
TRUTH_HEADER = "# gps_tow_s,lat_deg,lon_deg,h_m,vn,ve,vd,roll_deg,pitch_deg,yaw_deg (IMU point)"
RTKLIB_Q = {"fixed": 1, "float": 2}


def imu_csv_lines(acc_mps2: np.ndarray, gyro_rps: np.ndarray, counter_ms: np.ndarray) -> list[bytes]:
    """One CRLF-terminated line per sample: specific force in g, rate in deg/s, 3 decimals."""
    acc_g = np.asarray(acc_mps2, float) / G0_MPS2
    gyro_dps = np.degrees(np.asarray(gyro_rps, float))
    fmt = "%.3f,%.3f,%.3f,%.3f,%.3f,%.3f,%d\r\n"
    rows = np.column_stack([acc_g, gyro_dps]).tolist()
    return [(fmt % (*r, c)).encode("ascii") for r, c in zip(rows, np.asarray(counter_ms, np.int64).tolist())]


def cut_head(line: bytes, rng: np.random.Generator) -> bytes:
    """The line without a random head, as a logger that opened mid-line keeps it: the cut falls at
    or after the first decimal point, so what is left never parses as a sample (no sign-only cut,
    no line that still has 7 numbers) and is never blank."""
    body = line.rstrip(b"\r\n")
    first_dot = body.index(b".")
    k = int(rng.integers(first_dot, len(body) - 1))
    return line[k:]


def logger_records(available_gps_s: np.ndarray, line_end_bytes: np.ndarray, open_gps_s: float,
                   rng: np.random.Generator, poll_ms: int = 16, poll_jitter_mean_ms: float = 6.0,
                   poll_jitter_max_ms: int = 19) -> tuple[np.ndarray, np.ndarray]:
    """TIMETAG records of a logger that polls its serial port every ``poll_ms`` plus a random
    scheduling delay (gamma, shape 1.5, mean ``poll_jitter_mean_ms``; a draw above
    ``poll_jitter_max_ms`` is replaced by a uniform one below it) and writes one record whenever new complete lines arrived.

    available_gps_s: when each line's last byte was in the logger's buffer (non-decreasing: the
    serial stream keeps its order); line_end_bytes: byte offset after each line in the file.
    Returns (ms since open, byte offset) with integer ms rounded up, so that a record never
    claims a byte before it was there; the last record covers the whole file.
    """
    avail_ms = (np.asarray(available_gps_s, float) - open_gps_s) * 1e3
    if np.any(np.diff(avail_ms) < 0):
        raise ValueError("line availability must be non-decreasing")
    span_ms = float(avail_ms[-1])
    n_polls = int(span_ms / poll_ms) + 16
    jitter = rng.gamma(1.5, poll_jitter_mean_ms / 1.5, n_polls)
    over = jitter > poll_jitter_max_ms                 # the rare long waits: redrawn below the maximum
    jitter[over] = rng.uniform(0.0, poll_jitter_max_ms, int(over.sum()))
    poll = np.cumsum(poll_ms + np.floor(jitter)).astype(np.int64)
    while poll[-1] < span_ms:            # (never with the margin above; kept for safety)
        poll = np.append(poll, poll[-1] + poll_ms)
    poll = poll[: int(np.searchsorted(poll, math.ceil(span_ms))) + 1]
    n_lines = np.searchsorted(avail_ms, poll, side="right")        # lines complete by each poll
    keep = np.concatenate([[n_lines[0] > 0], np.diff(n_lines) > 0])
    poll, n_lines = poll[keep], n_lines[keep]
    offsets = np.asarray(line_end_bytes, np.int64)[n_lines - 1]
    return poll, offsets


def timetag_bytes(open_gps_s: float, tick_ms: int, rec_ms: np.ndarray, rec_offset: np.ndarray,
                  header_text: str = "TIMETAG RTKLIB v2xpos-sim") -> bytes:
    """A TIMETAG file: header, tick, open time (GPST seconds since 1970 + fraction), records."""
    unix_style = float(open_gps_s) + timebase.GPS_UNIX_OFFSET_S
    sec = int(math.floor(unix_style))
    frac = unix_style - sec
    head = header_text.encode("ascii")[:TIMETAG_HEADER_BYTES].ljust(TIMETAG_HEADER_BYTES, b"\0")
    rec = np.empty(len(rec_ms), dtype=[("ms", "<u4"), ("off", "<u4")])
    rec["ms"] = rec_ms
    rec["off"] = rec_offset
    return head + struct.pack("<IId", int(tick_ms) & 0xFFFFFFFF, sec, frac) + rec.tobytes()


NAV_PVT_FMT = struct.Struct("<IHBBBBBBIiBBBBiiiiIIiiiiiIIHH4xihH")
"""UBX-NAV-PVT payload (u-blox F9 interface description, UBX-01-07, 92 bytes)."""


def ubx_frame(msg_class: int, msg_id: int, payload: bytes) -> bytes:
    """A UBX frame: sync 0xB5 0x62, class, id, length, payload, 8-bit Fletcher checksum."""
    body = bytes((msg_class, msg_id)) + struct.pack("<H", len(payload)) + payload
    ck_a = ck_b = 0
    for b in body:
        ck_a = (ck_a + b) & 0xFF
        ck_b = (ck_b + ck_a) & 0xFF
    return b"\xb5\x62" + body + bytes((ck_a, ck_b))


def nav_pvt(t_gps_s: float, lla: np.ndarray, carr_soln: int, num_sv: int, sd_ned_m: np.ndarray,
            vel_ned_mps: np.ndarray, vel_sd_mps: float) -> bytes:
    """One NAV-PVT frame of an RTK receiver at GPS time ``t_gps_s`` (iTOW, and the UTC date and time
    through the leap-second table, fully resolved): position (lla rad, rad, ellipsoidal m; 1e-7 deg
    and mm, as the receiver rounds them), ``carr_soln`` 2 fixed / 1 float, hAcc = sqrt(2) * the
    horizontal sd per axis (the inverse of ``v2xpos.devices.ubx``), velocity NED and sAcc."""
    week, tow = timebase.week_tow_from_gps_seconds(t_gps_s)
    itow_ms = int(round(tow * 1e3))
    utc_s = t_gps_s - float(timebase.gps_minus_utc_at_gps(t_gps_s))
    ms = int(round(utc_s * 1e3))
    cal = timebase.gps_seconds_to_gpst_calendar(ms // 1000)
    nano = (ms % 1000) * 1_000_000
    h_acc = int(round(math.hypot(sd_ned_m[0], sd_ned_m[1]) * 1e3))
    v = [int(round(x * 1e3)) for x in vel_ned_mps]
    payload = NAV_PVT_FMT.pack(
        itow_ms, cal.year, cal.month, cal.day, cal.hour, cal.minute, cal.second, 0x07, 20, nano, 3,
        0x01 | 0x02 | (int(carr_soln) << 6), 0xE0, int(num_sv),
        int(round(math.degrees(lla[1]) * 1e7)), int(round(math.degrees(lla[0]) * 1e7)),
        int(round(lla[2] * 1e3)), int(round(lla[2] * 1e3)), h_acc, int(round(sd_ned_m[2] * 1e3)),
        v[0], v[1], v[2], int(round(math.hypot(v[0], v[1]))), 0, int(round(vel_sd_mps * 1e3)), 18000000, 120, 0,
        0, 0, 0)
    return ubx_frame(0x01, 0x07, payload)


def gpst_calendar(t_gps_s: float) -> str:
    """``yyyy/mm/dd hh:mm:ss.sss`` in GPST (RTKLIB's time column), rounded to the millisecond."""
    ms = int(round(t_gps_s * 1000.0))
    dt = timebase.gps_seconds_to_gpst_calendar(ms // 1000)
    return f"{dt:%Y/%m/%d %H:%M:%S}.{ms % 1000:03d}"


def pos_text(t_gps_s: np.ndarray, lla: np.ndarray, q: np.ndarray, ns: np.ndarray, sd_neu_m: np.ndarray,
             vel_neu_mps: np.ndarray, vel_sd_neu_mps: np.ndarray) -> str:
    """An RTKLIB ``.pos`` (lat/lon/height, GPST, with velocities): the column line, then one line per
    epoch. lla in (rad, rad, m); sd and velocity in north/east/up (covariances written as 0)."""
    lines = [POS_COLUMNS]
    lat, lon = np.degrees(lla[:, 0]), np.degrees(lla[:, 1])
    for k in range(len(t_gps_s)):
        sd, v, vs = sd_neu_m[k], vel_neu_mps[k], vel_sd_neu_mps[k]
        lines.append(
            f"{gpst_calendar(float(t_gps_s[k]))} {lat[k]:.9f} {lon[k]:.9f} {lla[k, 2]:.4f} {int(q[k])} {int(ns[k])} "
            f"{sd[0]:.4f} {sd[1]:.4f} {sd[2]:.4f} 0.0000 0.0000 0.0000 0.00 0.0 "
            f"{v[0]:.4f} {v[1]:.4f} {v[2]:.4f} {vs[0]:.4f} {vs[1]:.4f} {vs[2]:.4f} 0.0000 0.0000 0.0000")
    return "\n".join(lines) + "\n"


def truth_text(tow_s: np.ndarray, lla: np.ndarray, v_ned_mps: np.ndarray, rpy_rad: np.ndarray) -> str:
    """truth.csv: GPS time of week, lat/lon [deg], height [m] of the IMU point, NED velocity
    [m/s], roll/pitch/yaw [deg] (yaw in [0, 360))."""
    lat, lon = np.degrees(lla[:, 0]), np.degrees(lla[:, 1])
    r, p = np.degrees(rpy_rad[:, 0]), np.degrees(rpy_rad[:, 1])
    y = np.degrees(rpy_rad[:, 2]) % 360.0
    table = np.column_stack([tow_s, lat, lon, lla[:, 2], v_ned_mps, r, p, y])
    body = "\n".join(",".join(f"{x:.9f}" for x in row) for row in table.tolist())
    return TRUTH_HEADER + "\n" + body + "\n"


def truth_rel_text(tow_s: np.ndarray, rel_body_m: np.ndarray, rel_yaw_rad: np.ndarray, slave: str,
                   master: str) -> str:
    """truth_rel.csv: the slave's IMU point in the master's body frame [m] and yaw difference [deg]."""
    table = np.column_stack([tow_s, rel_body_m, np.degrees(rel_yaw_rad)])
    body = "\n".join(",".join(f"{x:.6f}" for x in row) for row in table.tolist())
    return (f"# gps_tow_s,x_fwd_m,y_right_m,z_down_m,rel_yaw_deg ({slave}'s IMU point in {master}'s body frame)\n"
            + body + "\n")


def _toml_matrix(m: np.ndarray) -> str:
    rows = []
    for row in np.asarray(m).tolist():
        rows.append("[" + ", ".join(str(int(round(x))) if abs(x - round(x)) < 1e-12 else repr(float(x))
                                    for x in row) + "]")
    return "[" + ", ".join(rows) + "]"


def dataset_toml(name: str, imu_to_body: np.ndarray, lever_arm_m: np.ndarray, lever_arm_sd_m: float,
                 platform: str = "car") -> str:
    """The descriptor: what is declared (nominal mounting, lever arm and its sd), nothing else."""
    lever = "[" + ", ".join(repr(round(float(x), 4)) for x in lever_arm_m) + "]"
    return (f'name = "{name}"\nplatform = "{platform}"\n\n[imu]\nfile = "imu.csv"\nformat = "csv_g_dps_ms"\n'
            f'timetag = "imu.csv.tag"\nimu_to_body = {_toml_matrix(imu_to_body)}\n\n[gnss]\nfile = "gnss.pos"\n'
            f'format = "rtklib_pos"\nraw = "gnss.ubx"\nraw_timetag = "gnss.ubx.tag"\nlever_arm_m = {lever}\n'
            f'lever_arm_sd_m = {float(lever_arm_sd_m)!r}\n')


def write_bytes(path: Path, data: bytes | str) -> None:
    """Write text (as ASCII with the newlines given) or bytes."""
    path.write_bytes(data.encode("ascii") if isinstance(data, str) else data)
