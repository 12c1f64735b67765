"""What the live decoders produce: one small record per decoded message, each stamped with the
host arrival time of the chunk that completed it (GPS seconds of the host clock, the way an RTKLIB
TIMETAG file stamps the bytes of a logged stream: the time by which the byte had arrived).

Times: ``t_s`` is a time of validity on the GPS time axis (seconds since 1980-01-06), as the
receiver states it; ``arrival_s`` is the host's GPS time when the message was in hand. IMU
records carry the device counter instead of a time of validity: the counter is mapped to GPS time
by the online clock model (``v2xpos.devices.clock_model``) in the consumer.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from v2xpos.types import FixStatus


@dataclass
class GnssEpoch:
    """A position (and velocity) solution of the receiver at the antenna.

    lla: (lat_rad, lon_rad, height_m ellipsoidal); sd_ned_m: 1-sigma per NED axis [m];
    vel_ned_mps / vel_sd_ned_mps: velocity and 1-sigma when the message has them (else None);
    message: which message(s) it came from (``NAV-PVT``, ``GGA+RMC+GST`` ...).
    """
    t_s: float
    lla: np.ndarray
    sd_ned_m: np.ndarray
    fix: FixStatus
    arrival_s: float
    vel_ned_mps: np.ndarray | None = None
    vel_sd_ned_mps: np.ndarray | None = None
    num_sv: int = 0
    message: str = ""


@dataclass
class HeadingObs:
    """Heading of the vehicle from a dual-antenna (moving-base) receiver or an NMEA HDT sentence.

    heading_rad: true heading of the baseline (clockwise from north, 0..2 pi) at time t_s (NaN when
    the sentence has no time: HDT); heading_sd_rad: 1-sigma (NaN when the message gives none);
    baseline_m: antenna separation when known (NaN otherwise).
    """
    t_s: float
    heading_rad: float
    heading_sd_rad: float
    arrival_s: float
    baseline_m: float = float("nan")
    message: str = ""


@dataclass
class ImuRecord:
    """One IMU sample as the device gave it: counter [s] of the device clock (a csv logger's
    millisecond counter, a receiver's ESF time tag), specific force [m/s^2] and rate [rad/s] in
    the IMU's own axes, and the host arrival time of its bytes."""
    counter_s: float
    acc_mps2: np.ndarray
    gyro_rps: np.ndarray
    arrival_s: float


@dataclass
class ReceiverTime:
    """The receiver's statement of GPS time: a message valid at ``t_s`` (receiver GPS time) that
    arrived at ``arrival_s`` (host GPS time). ``arrival_s - t_s`` is the output latency plus the
    host clock's offset from the receiver (see ``v2xpos.sources.gnss_clock``).
    ``gps_minus_utc_s`` is the receiver's leap-second count when the message tells it (NaN else)."""
    t_s: float
    arrival_s: float
    message: str
    gps_minus_utc_s: float = float("nan")
