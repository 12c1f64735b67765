"""Live NMEA 0183 sentences -> records, decoded with pynmeagps (``NMEAReader.parse``).

One navigation epoch is spread over several sentences with the same UTC time of day:

* GGA: position (latitude, longitude, altitude above MSL + geoid separation = ellipsoidal
  height), quality -> fix (0 NONE, 1 SINGLE, 2 DGPS, 4 FIXED, 5 FLOAT, 6 DEAD_RECKONING), SVs;
* RMC: date, speed over ground [knots] and course over ground [deg true] -> v_N, v_E (v_D is not
  in NMEA: it is given as 0 with ``vel_vertical_sd_mps``, i.e. almost no information);
* GST: 1-sigma of latitude, longitude and altitude errors [m] -> sd_ned_m;
* HDT: true heading [deg] (a dual-antenna receiver or a heading sensor) -> :class:`HeadingObs`
  at the current epoch's time (HDT carries no time; sd not given: NaN).

The epoch is emitted when every sentence type of the previous epoch has arrived for it, or when a
sentence of a later time arrives. Without GST the position sd is ``sd_by_fix_m[fix]`` (an
assumption the config states, not a measurement); without RMC there is no velocity. GPS time =
UTC (date from RMC, else from the host's arrival time) + GPS - UTC from ``v2xpos.timebase``.
Sentences pynmeagps cannot decode, or with a checksum error, are counted in ``issues``.
"""
from __future__ import annotations

import datetime
import math

import numpy as np
from pynmeagps import NMEAReader

from v2xpos import timebase
from v2xpos.datasets.issues import ParseIssues
from v2xpos.devices.records import GnssEpoch, HeadingObs, ReceiverTime
from v2xpos.types import FixStatus

KNOT_MPS = 1852.0 / 3600.0
GGA_QUALITY = {0: FixStatus.NONE, 1: FixStatus.SINGLE, 2: FixStatus.DGPS, 3: FixStatus.SINGLE, 4: FixStatus.FIXED,
               5: FixStatus.FLOAT, 6: FixStatus.DEAD_RECKONING}
DEFAULT_SD_BY_FIX_M = {FixStatus.FIXED: 0.02, FixStatus.FLOAT: 0.3, FixStatus.DGPS: 0.8, FixStatus.SINGLE: 2.5,
                       FixStatus.DEAD_RECKONING: 10.0, FixStatus.NONE: 100.0}
USED = ("GGA", "RMC", "GST", "HDT")


class NmeaDecoder:
    """Assemble NMEA sentences into epochs (see module docstring).

    sd_by_fix_m: horizontal 1-sigma per fix status when no GST arrives (vertical x 2);
    vel_sd_mps: horizontal velocity 1-sigma for RMC speed/course; vel_vertical_sd_mps: the sd that
    goes with the v_D = 0 placeholder.
    """

    def __init__(self, name: str = "nmea", sd_by_fix_m: dict | None = None, vel_sd_mps: float = 0.1,
                 vel_vertical_sd_mps: float = 1.0):
        self.issues = ParseIssues(name)
        self.sd_by_fix_m = {**DEFAULT_SD_BY_FIX_M, **(sd_by_fix_m or {})}
        self.vel_sd_mps = float(vel_sd_mps)
        self.vel_vertical_sd_mps = float(vel_vertical_sd_mps)
        self.counts: dict[str, int] = {}
        self._pending: dict | None = None
        self._expected: set[str] = set()
        self._date: datetime.date | None = None
        self._last_epoch_t = math.nan
        self._last_emitted_t = -math.inf

    def decode(self, raw: bytes, arrival_s: float, where: int = 0) -> list:
        """Records completed by one checked sentence."""
        kind = raw[3:6].decode("ascii", "replace") if len(raw) > 6 else "?"
        self.counts[kind] = self.counts.get(kind, 0) + 1
        if kind not in USED:
            return []
        try:
            msg = NMEAReader.parse(raw)
        except Exception as exc:  # pynmeagps raises several types; any of them is one bad sentence
            self.issues.add(where, f"NMEA {kind} not decodable: {exc}")
            return []
        if kind == "HDT":
            try:
                heading = float(msg.headingT)
            except (TypeError, ValueError):
                self.issues.add(where, "HDT without heading")
                return []
            return [HeadingObs(t_s=self._last_epoch_t, heading_rad=math.radians(heading) % (2 * math.pi),
                               heading_sd_rad=math.nan, arrival_s=arrival_s, message="HDT")]
        tod = getattr(msg, "time", None)
        if not isinstance(tod, datetime.time):
            self.issues.add(where, f"NMEA {kind} without time")
            return []
        out: list = []
        if self._pending is not None and self._pending["tod"] != tod:
            out += self._flush()
        if self._pending is None:
            self._pending = {"tod": tod, "arrival_s": arrival_s, "kinds": set()}
        p = self._pending
        p["kinds"].add(kind)
        p[kind] = msg
        if kind == "GGA":
            p["gga_arrival_s"] = arrival_s
        if kind == "RMC" and isinstance(getattr(msg, "date", None), datetime.date):
            self._date = msg.date
        if self._expected and self._expected <= p["kinds"]:
            out += self._flush()
        return out

    def _gps_time(self, tod: datetime.time, arrival_s: float) -> float:
        date = self._date
        host_utc = timebase.gps_seconds_to_utc(arrival_s)
        if date is None:                   # date from the host: the UTC day whose tod is nearest
            date = host_utc.date()
            cand = datetime.datetime.combine(date, tod, tzinfo=datetime.timezone.utc)
            delta = (cand - host_utc).total_seconds()
            if delta > 43200:
                date -= datetime.timedelta(days=1)
            elif delta < -43200:
                date += datetime.timedelta(days=1)
        return timebase.utc_to_gps_seconds(datetime.datetime.combine(date, tod, tzinfo=datetime.timezone.utc))

    def _flush(self) -> list:
        p, self._pending = self._pending, None
        if p is None:
            return []
        self._expected = set(p["kinds"])
        gga = p.get("GGA")
        if gga is None:
            return []
        t = self._gps_time(p["tod"], p["arrival_s"])
        self._last_epoch_t = t
        if t <= self._last_emitted_t:
            self.issues.add(0, f"NMEA epoch {p['tod']} not after the previous one")
            return []
        self._last_emitted_t = t
        try:
            quality = int(gga.quality)
            fix = GGA_QUALITY.get(quality, FixStatus.NONE)
            lat, lon = float(gga.lat), float(gga.lon)
            h = float(gga.alt) + float(gga.sep or 0.0)
        except (TypeError, ValueError):
            if str(getattr(gga, "quality", "")) in ("0", ""):
                return [ReceiverTime(t_s=t, arrival_s=p.get("gga_arrival_s", p["arrival_s"]), message="GGA")]
            self.issues.add(0, f"GGA at {p['tod']} without a usable position")
            return []
        gst = p.get("GST")
        sd = None
        if gst is not None:
            try:
                sd = np.array([float(gst.stdLat), float(gst.stdLong), float(gst.stdAlt)])
            except (TypeError, ValueError):
                sd = None
        if sd is None or not np.all(np.isfinite(sd)) or np.any(sd <= 0):
            s = self.sd_by_fix_m.get(fix, 100.0)
            sd = np.array([s, s, 2.0 * s])
        vel = vel_sd = None
        rmc = p.get("RMC")
        if rmc is not None and str(rmc.status) == "A":
            try:
                spd = float(rmc.spd) * KNOT_MPS
                cog = math.radians(float(rmc.cog)) if rmc.cog not in ("", None) else 0.0
                vel = np.array([spd * math.cos(cog), spd * math.sin(cog), 0.0])
                vel_sd = np.array([self.vel_sd_mps, self.vel_sd_mps, self.vel_vertical_sd_mps])
            except (TypeError, ValueError):
                vel = vel_sd = None
        arrival = p.get("gga_arrival_s", p["arrival_s"])
        epoch = GnssEpoch(t_s=t, lla=np.array([math.radians(lat), math.radians(lon), h]), sd_ned_m=sd, fix=fix,
                          arrival_s=arrival, vel_ned_mps=vel, vel_sd_ned_mps=vel_sd,
                          num_sv=int(gga.numSV or 0), message="+".join(k for k in ("GGA", "RMC", "GST") if k in p))
        return [epoch, ReceiverTime(t_s=t, arrival_s=arrival, message="GGA")]
