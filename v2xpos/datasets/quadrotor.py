"""Quadrotor multi-IMU recordings (Hurwitz & Klein 2023, "Quadrotor dead reckoning with multiple
inertial sensors", dataset ansfl/Quadrotor-Dead-Reckoning-with-Multiple-Inertial-Sensors).

A path folder holds ``IMU_k.csv`` (four Xsens DOT units, 120 Hz) with the header
``time,Euler_X,Euler_Y,Euler_Z,Acc_X,Acc_Y,Acc_Z,Gyr_X,Gyr_Y,Gyr_Z`` (time [s], Euler [deg],
specific force [m/s^2], rate [deg/s], each unit in its own axes) and ``GT.csv`` (10 Hz RTK
reference of the DJI Phantom 4 RTK): ``time, distance [m], speed [m/s], compass_heading [deg],
pitch [deg], roll [deg], height_above_takeoff [m], North, East, Down [m]``.

Conventions of the result: times stay on the recording's own axis (seconds from its start, as
the source gives them; not GPS time); rates in rad/s; Euler angles in rad, *as the unit reports
them* (Xsens DOT: X, Y, Z = roll, pitch, yaw of the sensor against its own local earth frame),
not converted to any vehicle frame. The relative orientation of the units is not declared and is
left to the grading (``v2xpos.quality``). The reference becomes a
:class:`v2xpos.types.LocalReference` (NED about the take-off point, rpy = roll, pitch, heading).
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from v2xpos.datasets.issues import ParseIssues
from v2xpos.types import (Dataset, GnssData, ImuData, LocalReference, MultiImuRecording)

IMU_COLUMNS = ("time", "Euler_X", "Euler_Y", "Euler_Z", "Acc_X", "Acc_Y", "Acc_Z",
               "Gyr_X", "Gyr_Y", "Gyr_Z")
GT_COLUMNS = ("time", "distance", "speed", "compass_heading", "pitch", "roll",
              "height_above_takeoff", "North", "East", "Down")


def _column_key(name: str) -> str:
    return name.strip().split("(")[0].strip()


def read_numeric_csv(path: str | Path, columns: tuple[str, ...]) -> tuple[np.ndarray, ParseIssues]:
    """Read a csv with a header naming ``columns`` (units in parentheses ignored) -> (N, len(columns))
    array in that column order. Rows with a wrong field count, a non-number, a non-finite value or a
    time not after the previous row are skipped and counted. ValueError if a column is missing."""
    path = Path(path)
    issues = ParseIssues(str(path))
    lines = path.read_text(encoding="ascii", errors="replace").splitlines()
    if not lines:
        raise ValueError(f"{path}: empty file, expected a header with {columns}")
    header = [_column_key(h) for h in lines[0].split(",")]
    missing = [c for c in columns if c not in header]
    if missing:
        raise ValueError(f"{path}: header lacks column(s) {missing}")
    idx = [header.index(c) for c in columns]
    rows: list[list[float]] = []
    last_t = -math.inf
    for line_no, line in enumerate(lines[1:], start=2):
        if not line.strip():
            continue
        fields = line.split(",")
        if len(fields) != len(header):
            issues.add(line_no, f"expected {len(header)} fields, found {len(fields)}")
            continue
        try:
            vals = [float(fields[i]) for i in idx]
        except ValueError as exc:
            issues.add(line_no, f"unparsable number: {exc}")
            continue
        if not all(math.isfinite(v) for v in vals):
            issues.add(line_no, "non-finite value")
            continue
        if vals[0] <= last_t:
            issues.add(line_no, f"time {vals[0]} s not after the previous row")
            continue
        last_t = vals[0]
        rows.append(vals)
    if len(rows) < 2:
        why = f"{issues.count} malformed row(s) skipped" if issues.count else "header only"
        raise ValueError(f"{path}: {len(rows)} usable data row(s), need at least 2 ({why})")
    return np.asarray(rows, dtype=float).reshape(-1, len(columns)), issues


def read_quadrotor_path(folder: str | Path) -> MultiImuRecording:
    """Read one ``path_k`` folder -> MultiImuRecording with units ``IMU_1`` ... and the GT reference."""
    folder = Path(folder)
    unit_files = sorted(folder.glob("IMU_*.csv"), key=lambda p: (len(p.stem), p.stem))
    if not unit_files:
        raise ValueError(f"{folder}: no IMU_k.csv files")
    units: dict[str, ImuData] = {}
    euler: dict[str, np.ndarray] = {}
    malformed: dict[str, dict] = {}
    total_bad = 0
    for f in unit_files:
        data, issues = read_numeric_csv(f, IMU_COLUMNS)
        units[f.stem] = ImuData(t_s=data[:, 0], acc_mps2=data[:, 4:7],
                                gyro_rps=np.radians(data[:, 7:10]))
        euler[f.stem] = np.radians(data[:, 1:4])
        malformed[f.name] = issues.as_dict()
        total_bad += issues.count
    reference = None
    gt_file = folder / "GT.csv"
    if gt_file.is_file():
        gt, issues = read_numeric_csv(gt_file, GT_COLUMNS)
        reference = LocalReference(
            t_s=gt[:, 0], pos_ned_m=gt[:, 7:10],
            rpy_rad=np.radians(np.column_stack([gt[:, 5], gt[:, 4], gt[:, 3]])),
            speed_mps=gt[:, 2])
        malformed[gt_file.name] = issues.as_dict()
        total_bad += issues.count
    rates = {name: float(1.0 / np.median(np.diff(u.t_s))) for name, u in units.items() if len(u) > 1}
    name = f"{folder.parent.name}/{folder.name}"
    return MultiImuRecording(name=name, units=units, unit_euler_rad=euler, reference=reference,
                             time_scale="recording", malformed_lines=total_bad, source=folder,
                             notes={"malformed": malformed, "rate_hz": rates})


def dataset_from_multi_imu(rec: MultiImuRecording, unit: str | None = None) -> Dataset:
    """A :class:`Dataset` view of a multi-IMU recording: ``imu`` is one unit (default: the first),
    ``gnss`` is empty (the source has no absolute positions), the whole recording is in
    ``notes["multi_imu"]`` and its local reference in ``notes["local_reference"]``."""
    unit = unit or next(iter(rec.units))
    empty = GnssData(t_s=np.zeros(0), lla=np.zeros((0, 3)), fix=np.zeros(0, dtype=np.int8),
                     sd_ned_m=np.zeros((0, 3)))
    return Dataset(name=rec.name, platform="quadrotor", imu=rec.units[unit], gnss=empty,
                   malformed_lines=rec.malformed_lines, source=rec.source,
                   notes={"multi_imu": rec, "local_reference": rec.reference, "imu_unit": unit,
                          "time_scale": rec.time_scale, "malformed": rec.notes["malformed"]})
