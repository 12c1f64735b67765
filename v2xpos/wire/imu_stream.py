"""The IMU stream of the grading: every unit's samples, published by a slave on ``imu_key`` and read
by the master's grader (docs/protocol.md, docs/quality.md).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import msgpack
import numpy as np


IMU_PAYLOAD_VERSION = 1
MAX_IMU_ROWS = 10_000
"""Most rows of one unit in one payload (a slave sends 0.25 s of samples per payload)."""
MAX_IMU_UNITS = 16


class ImuPayloadError(ValueError):
    """A received IMU-stream payload that is not valid (the message says why)."""


@dataclass
class ImuPayload:
    """One IMU-stream message: every unit's samples since the previous message of the vehicle.

    ``units``: unit id -> (t_gps_s (n,), acc_mps2 (n, 3), gyro_rps (n, 3)) in the unit's own axes;
    ``mounting_xyz_deg``: unit id -> X-Y-Z Euler angles unit -> vehicle body [deg] (docs/quality.md),
    for the units whose mounting is declared."""
    vehicle_id: str
    fleet: str | None
    units: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]]
    mounting_xyz_deg: dict[str, list[float]]
    rate_hz: float | None = None


def encode_imu_payload(fleet: str, vehicle_id: str, units: dict, mounting_xyz_deg: dict,
                       rate_hz: float = 100.0) -> bytes:
    """The msgpack map a slave publishes on ``imu_key`` (docs/protocol.md): ``{"T": "imu", "ver": 1,
    "fleet", "id", "rate_hz", "mounting_xyz_deg": {unit: [x, y, z]}, "units": {unit: rows}}`` with
    rows ``[t_gps_s, ax, ay, az, gx, gy, gz]`` (m/s^2, rad/s, unit axes). ``units``: unit id ->
    (t_gps_s, acc_mps2, gyro_rps) as in ``ImuPayload``."""
    rows = {uid: np.column_stack([t, acc, gyro]).tolist() for uid, (t, acc, gyro) in units.items()}
    return msgpack.packb({"T": "imu", "ver": IMU_PAYLOAD_VERSION, "fleet": fleet, "id": vehicle_id,
                          "rate_hz": rate_hz, "mounting_xyz_deg": mounting_xyz_deg, "units": rows},
                         use_bin_type=True)


def _imu_numbers(value: Any, error: str) -> np.ndarray:
    try:
        return np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise ImuPayloadError(error) from None


def decode_imu_payload(data: bytes) -> ImuPayload:
    """Validated IMU-stream payload; ``ImuPayloadError`` for anything else (never another exception):
    not msgpack, another type or version, no vehicle id, 0 or more than ``MAX_IMU_UNITS`` units, rows
    that are not finite 7-vectors, mountings that are not 3 finite angles within +-360 deg."""
    try:
        m = msgpack.unpackb(data, raw=False, strict_map_key=True, max_array_len=MAX_IMU_ROWS)
    except Exception as exc:  # msgpack raises many types, all mean "not a valid payload"
        raise ImuPayloadError(f"not msgpack ({type(exc).__name__})") from None
    if type(m) is not dict or m.get("T") != "imu" or m.get("ver") != IMU_PAYLOAD_VERSION:
        raise ImuPayloadError(f"not an imu message of version {IMU_PAYLOAD_VERSION}")
    vid, units = m.get("id"), m.get("units")
    if type(vid) is not str or not vid or type(units) is not dict or not 0 < len(units) <= MAX_IMU_UNITS:
        raise ImuPayloadError("missing id or units")
    samples = {}
    for uid, rows in units.items():
        a = _imu_numbers(rows, f"unit {uid!r}: rows are not numbers")
        if a.ndim != 2 or a.shape[1] != 7 or not np.isfinite(a).all():
            raise ImuPayloadError(f"unit {uid!r}: rows must be finite [t, ax, ay, az, gx, gy, gz]")
        samples[str(uid)] = (a[:, 0], a[:, 1:4], a[:, 4:7])
    mounting = m.get("mounting_xyz_deg") or {}
    if type(mounting) is not dict:
        raise ImuPayloadError("mounting_xyz_deg is not a map")
    angles = {}
    for uid, v in mounting.items():
        a = _imu_numbers(v, f"mounting_xyz_deg[{uid!r}]: not numbers")
        if a.shape != (3,) or not np.isfinite(a).all() or np.abs(a).max() > 360.0:
            raise ImuPayloadError(f"mounting_xyz_deg[{uid!r}]: need 3 finite angles in [-360, 360] deg")
        angles[str(uid)] = a.tolist()
    rate = m.get("rate_hz")
    return ImuPayload(vid, m.get("fleet"), samples, angles,
                      float(rate) if type(rate) in (int, float) and math.isfinite(rate) else None)
