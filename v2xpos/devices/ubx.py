"""Live u-blox UBX messages -> records, decoded with pyubx2 (``UBXReader.parse``).

* NAV-PVT (UBX-01-07) -> :class:`GnssEpoch` with the conventions of ``v2xpos.datasets.ubx``
  (the recorded-file reader, so a live stream and its recording give the same solutions): time
  of validity = GPS week (from the UTC date, through the leap-second table) + iTOW; ellipsoidal
  height; fix from ``fix_status_from_nav_pvt`` (carrSoln 2 FIXED, 1 FLOAT, fixType 1 DR,
  2/3/4 SINGLE or DGPS, not gnssFixOk NONE); sd_n = sd_e = hAcc / sqrt(2), sd_d = vAcc;
  velocity NED with sAcc per axis. Also a :class:`ReceiverTime` (the receiver's GPS time and,
  when date and time are valid and fully resolved, its GPS - UTC leap count).
* NAV-RELPOSNED (UBX-01-3C) -> :class:`HeadingObs` when the receiver is the rover of a moving-base
  pair and flags gnssFixOK, relPosValid and relPosHeadingValid: relPosHeading / accHeading [deg]
  (heading of the baseline from the base antenna to this one) and the baseline length.
* ESF-MEAS (UBX-10-02) and ESF-RAW (UBX-10-03) of a receiver with an IMU (F9R/F9K) ->
  :class:`ImuRecord` once the six axes of one time tag are in hand. Data types (u-blox F9 HPS
  interface description, "ESF data types"): 14/13/5 gyro x/y/z [deg/s * 2^-12], 16/17/18
  accelerometer x/y/z [m/s^2 * 2^-10], 24-bit two's complement; the time tag counts
  ``tick_s`` seconds (1 ms for ESF-MEAS timeTag; check the ESF-RAW sTtag unit of your receiver:
  a wrong tick shows as an absurd drift in the IMU clock model's status).

Anything pyubx2 cannot decode is counted in ``issues`` and skipped.
"""
from __future__ import annotations

import datetime
import math

import numpy as np
from pyubx2 import UBXReader

from v2xpos import timebase
from v2xpos.datasets.issues import ParseIssues
from v2xpos.datasets.ubx import fix_status_from_nav_pvt
from v2xpos.devices.records import GnssEpoch, HeadingObs, ImuRecord, ReceiverTime

NAV_PVT = (0x01, 0x07)
NAV_RELPOSNED = (0x01, 0x3C)
ESF_MEAS = (0x10, 0x02)
ESF_RAW = (0x10, 0x03)
ESF_GYRO = {14: 0, 13: 1, 5: 2}
ESF_ACC = {16: 0, 17: 1, 18: 2}
ESF_GYRO_SCALE_DPS = 2.0 ** -12
ESF_ACC_SCALE_MPS2 = 2.0 ** -10


def _int24(v: int) -> int:
    v &= 0xFFFFFF
    return v - (1 << 24) if v & 0x800000 else v


def nav_pvt_time(msg) -> float:
    """GPS seconds of a NAV-PVT epoch: week from the UTC date (leap table), time of week = iTOW."""
    itow_s = int(msg.iTOW) * 1e-3
    utc_guess = timebase.utc_to_gps_seconds(datetime.datetime(msg.year, msg.month, msg.day, msg.hour, msg.min,
                                                              min(int(msg.second), 59)))
    week = round((utc_guess - itow_s) / timebase.SECONDS_PER_WEEK)
    return float(timebase.gps_seconds_from_week_tow(week, itow_s))


class UbxDecoder:
    """Decode checked UBX frames (``framing.Frame``) into records (see module docstring)."""

    def __init__(self, name: str = "ubx", esf_tick_s: float = 1e-3):
        self.issues = ParseIssues(name)
        self.esf_tick_s = float(esf_tick_s)
        self.counts: dict[str, int] = {}
        self._week: int | None = None
        self._esf_slots: dict[tuple[str, int], list] = {}
        self._last_pvt_t = -math.inf

    def decode(self, raw: bytes, arrival_s: float, where: int = 0) -> list:
        """Records from one UBX frame (``where``: its stream offset, for the issue report)."""
        key = (raw[2], raw[3])
        if key not in (NAV_PVT, NAV_RELPOSNED, ESF_MEAS, ESF_RAW):
            name = f"UBX-{raw[2]:02X}-{raw[3]:02X}"
            self.counts[name] = self.counts.get(name, 0) + 1
            return []
        try:
            msg = UBXReader.parse(raw)
            if key == NAV_PVT:
                out = self._nav_pvt(msg, arrival_s, where)
            elif key == NAV_RELPOSNED:
                out = self._relposned(msg, arrival_s)
            else:
                out = self._esf(msg, raw, key, arrival_s)
        except Exception as exc:  # pyubx2 raises several types; any of them is one bad message
            self.issues.add(where, f"UBX 0x{key[0]:02x} 0x{key[1]:02x} not decodable: {exc}")
            return []
        name = {NAV_PVT: "NAV-PVT", NAV_RELPOSNED: "NAV-RELPOSNED", ESF_MEAS: "ESF-MEAS", ESF_RAW: "ESF-RAW"}[key]
        self.counts[name] = self.counts.get(name, 0) + 1
        return out

    def _nav_pvt(self, msg, arrival_s: float, where: int) -> list:
        if not (msg.validDate and msg.validTime):
            self.issues.add(where, "NAV-PVT without valid date/time")
            return []
        t = nav_pvt_time(msg)
        self._week = int(t // timebase.SECONDS_PER_WEEK)
        if t <= self._last_pvt_t:
            self.issues.add(where, f"NAV-PVT time {t:.3f} s not after the previous epoch")
            return []
        self._last_pvt_t = t
        leap = math.nan
        if getattr(msg, "fullyResolved", 0):
            utc = datetime.datetime(msg.year, msg.month, msg.day, msg.hour, msg.min, min(int(msg.second), 59),
                                    tzinfo=datetime.timezone.utc)
            unix = (utc - timebase.UNIX_EPOCH_UTC).total_seconds() + int(msg.nano) * 1e-9
            leap = float(round(t - (unix - timebase.GPS_UNIX_OFFSET_S)))
        fix = fix_status_from_nav_pvt(msg.fixType, msg.gnssFixOk, msg.diffSoln, msg.carrSoln)
        h_sd = msg.hAcc * 1e-3 / math.sqrt(2.0)
        s_acc = msg.sAcc * 1e-3
        epoch = GnssEpoch(t_s=t, lla=np.array([math.radians(msg.lat), math.radians(msg.lon), msg.height * 1e-3]),
                          sd_ned_m=np.array([h_sd, h_sd, msg.vAcc * 1e-3]), fix=fix, arrival_s=arrival_s,
                          vel_ned_mps=np.array([msg.velN, msg.velE, msg.velD]) * 1e-3,
                          vel_sd_ned_mps=np.full(3, s_acc), num_sv=int(msg.numSV), message="NAV-PVT")
        return [epoch, ReceiverTime(t_s=t, arrival_s=arrival_s, message="NAV-PVT", gps_minus_utc_s=leap)]

    def _relposned(self, msg, arrival_s: float) -> list:
        if not (msg.gnssFixOK and msg.relPosValid and msg.relPosHeadingValid) or self._week is None:
            return []
        t = float(timebase.gps_seconds_from_week_tow(self._week, int(msg.iTOW) * 1e-3))
        baseline_m = float(msg.relPosLength) * 1e-2    # pyubx2 adds the 0.1 mm part (_HPrelPosLength) [cm]
        return [HeadingObs(t_s=t, heading_rad=math.radians(msg.relPosHeading) % (2 * math.pi),
                           heading_sd_rad=math.radians(msg.accHeading), arrival_s=arrival_s,
                           baseline_m=baseline_m, message="NAV-RELPOSNED")]

    def _esf(self, msg, raw: bytes, key: tuple, arrival_s: float) -> list:
        if key == ESF_MEAS:
            n = int(msg.numMeas)
            tag = int(msg.timeTag)
            items = [(tag, int(getattr(msg, f"dataType_{i:02d}")), _int24(int(getattr(msg, f"dataField_{i:02d}"))))
                     for i in range(1, n + 1)]
            kind = "meas"
        else:
            payload = raw[6:-2]
            items = []
            for k in range(4, len(payload) - 7, 8):
                word = int.from_bytes(payload[k:k + 4], "little")
                tag = int.from_bytes(payload[k + 4:k + 8], "little")
                items.append((tag, word >> 24, _int24(word)))
            kind = "raw"
        out = []
        for tag, dtype, value in items:
            if dtype not in ESF_GYRO and dtype not in ESF_ACC:
                continue
            slot = self._esf_slots.setdefault((kind, tag), [np.full(3, np.nan), np.full(3, np.nan)])
            if dtype in ESF_GYRO:
                slot[1][ESF_GYRO[dtype]] = math.radians(value * ESF_GYRO_SCALE_DPS)
            else:
                slot[0][ESF_ACC[dtype]] = value * ESF_ACC_SCALE_MPS2
            if np.isfinite(slot[0]).all() and np.isfinite(slot[1]).all():
                out.append(ImuRecord(counter_s=tag * self.esf_tick_s, acc_mps2=slot[0], gyro_rps=slot[1],
                                     arrival_s=arrival_s))
                del self._esf_slots[(kind, tag)]
        if len(self._esf_slots) > 64:           # axes that never completed: forget the oldest
            for k in sorted(self._esf_slots, key=lambda kt: kt[1])[:len(self._esf_slots) - 64]:
                del self._esf_slots[k]
                self.issues.add(0, f"ESF time tag {k[1]} never got all six axes")
        return out
