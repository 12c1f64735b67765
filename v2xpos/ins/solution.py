"""Per-epoch navigation solution of a replay (``v2xpos replay DATASET --solution FILE``): one row per
output epoch with time, position, velocity, attitude, their 1-sigma, the fix and every state of
the filter that models an effect (IMU biases, and the augmented effects the configuration
estimates: lever arm, IMU time offset / clock drift, misalignment, scale factors, GNSS latencies,
odometer scale), with its 1-sigma.

Frames and units (also in each column name): position of the IMU point, geodetic latitude /
longitude [deg] and ellipsoidal height [m]; velocity north/east/down [m/s]; attitude Z-Y-X Euler
angles of the vehicle body (x forward, y right, z down) to NED [deg]; position sigmas north /
east / down [m]; attitude sigmas of the NED tilt errors [deg]; gyro bias [deg/h], accelerometer
bias [m/s^2] in the IMU body axes; lever arm in the body frame [m]; time offsets [ms]; drift and
scale factors [ppm]; ``fix``: the GNSS solution status last used, ``DR`` while coasting;
``gnss_used``: 0 inside a simulated outage.

Formats, by the file's extension: ``.csv`` (one header line, comma separated) or ``.mcap``
(JSON rows on ``/solution`` with their JSON schema, and ``foxglove.LocationFix`` on
``/location/solution`` so that Foxglove draws the track on a map; log times = the epoch in Unix
time).
"""
from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from v2xpos.timebase import gps_seconds_to_unix, week_tow_from_gps_seconds
from v2xpos.types import FixStatus

from .ekf import ATT, BA, BG, EFFECT_SIZES

DEG = 180.0 / math.pi

# effect -> (column stem, unit suffix, scale from filter units, component names)
EFFECT_COLUMNS: dict[str, tuple[str, str, float, tuple[str, ...]]] = {
    "lever_arm": ("lever_arm", "m", 1.0, ("x", "y", "z")),
    "imu_time_offset": ("imu_time_offset", "ms", 1e3, ("",)),
    "imu_clock_drift": ("imu_clock_drift", "ppm", 1e6, ("",)),
    "misalignment": ("misalignment", "deg", DEG, ("roll", "pitch", "yaw")),
    "gyro_scale": ("gyro_scale", "ppm", 1e6, ("x", "y", "z")),
    "accel_scale": ("accel_scale", "ppm", 1e6, ("x", "y", "z")),
    "gnss_latency": ("gnss_latency", "ms", 1e3, ("",)),
    "gnss_vel_latency": ("gnss_vel_latency", "ms", 1e3, ("",)),
    "odometer_scale": ("odometer_scale", "ppm", 1e6, ("",)),
    "rear_axle_distance": ("rear_axle_distance", "m", 1.0, ("",)),
    "rear_slip_compliance": ("rear_slip_compliance", "deg_per_g", DEG * 9.80665, ("",)),
}

BASE_COLUMNS = ("t_gps_s", "gps_week", "gps_tow_s", "lat_deg", "lon_deg", "height_m", "vn_mps", "ve_mps", "vd_mps",
                "roll_deg", "pitch_deg", "yaw_deg", "sd_north_m", "sd_east_m", "sd_down_m", "sd_vn_mps", "sd_ve_mps",
                "sd_vd_mps", "sd_roll_deg", "sd_pitch_deg", "sd_yaw_deg", "fix", "gnss_used",
                "gyro_bias_x_dph", "gyro_bias_y_dph", "gyro_bias_z_dph", "sd_gyro_bias_x_dph", "sd_gyro_bias_y_dph",
                "sd_gyro_bias_z_dph", "accel_bias_x_mps2", "accel_bias_y_mps2", "accel_bias_z_mps2",
                "sd_accel_bias_x_mps2", "sd_accel_bias_y_mps2", "sd_accel_bias_z_mps2")


def _effect_names(stem: str, unit: str, comps: tuple[str, ...]) -> list[str]:
    return [f"{stem}_{c}_{unit}" if c else f"{stem}_{unit}" for c in comps]


def columns(effects: tuple[str, ...]) -> list[str]:
    """Column names for a filter that estimates ``effects`` (value, then sd_ value per component)."""
    out = list(BASE_COLUMNS)
    for name in effects:
        stem, unit, _, comps = EFFECT_COLUMNS[name]
        names = _effect_names(stem, unit, comps)
        out += names + [f"sd_{n}" for n in names]
    return out


def _effect_values(f: Any, name: str) -> np.ndarray:
    """Current value of an effect in filter units (the same quantities as ``effects_report``)."""
    fx = f.fx
    if name == "lever_arm":
        return np.asarray(fx.lever_arm_m, float)
    if name == "imu_time_offset":
        return np.array([fx.imu_time_offset_s])
    if name == "imu_clock_drift":
        return np.array([fx.imu_clock_drift])
    if name == "misalignment":
        return np.asarray(fx.misalignment_rad, float)
    if name in ("gyro_scale", "accel_scale"):
        rep = fx.as_dict(f.corr)
        return np.asarray(rep[name], float)
    if name == "gnss_latency":
        return np.array([fx.gnss_latency_s])
    if name == "gnss_vel_latency":
        return np.array([fx.gnss_vel_latency_s])
    if name == "odometer_scale":
        return np.array([fx.odometer_scale])
    if name == "rear_axle_distance":
        return np.array([fx.rear_axle_distance_m])
    if name == "rear_slip_compliance":
        return np.array([fx.rear_slip_compliance])
    raise KeyError(name)


def row(f: Any, gnss_used: bool) -> dict:
    """One solution row from an initialised ``InsFilter`` at its current time label."""
    nav = f.nav_state()
    t = float(nav.t_s)
    week, tow = week_tow_from_gps_seconds(t)
    sd = np.sqrt(np.abs(np.diag(f.P)))
    fix = FixStatus(nav.fix)
    r: dict = {"t_gps_s": t, "gps_week": week, "gps_tow_s": tow,
               "lat_deg": nav.lla[0] * DEG, "lon_deg": nav.lla[1] * DEG, "height_m": float(nav.lla[2])}
    r.update(zip(("vn_mps", "ve_mps", "vd_mps"), map(float, nav.v_ned_mps)))
    r.update(zip(("roll_deg", "pitch_deg", "yaw_deg"), (float(x) * DEG for x in nav.rpy_rad)))
    r.update(zip(("sd_north_m", "sd_east_m", "sd_down_m"), map(float, nav.pos_sd_m)))
    r.update(zip(("sd_vn_mps", "sd_ve_mps", "sd_vd_mps"), map(float, nav.vel_sd_mps)))
    r.update(zip(("sd_roll_deg", "sd_pitch_deg", "sd_yaw_deg"), (float(x) * DEG for x in sd[ATT:ATT + 3])))
    r["fix"] = "DR" if fix == FixStatus.DEAD_RECKONING else fix.name
    r["gnss_used"] = int(bool(gnss_used))
    dph = DEG * 3600.0
    for a, k in zip("xyz", range(3)):
        r[f"gyro_bias_{a}_dph"] = float(f.gyro_bias_rps[k]) * dph
        r[f"sd_gyro_bias_{a}_dph"] = float(sd[BG + k]) * dph
        r[f"accel_bias_{a}_mps2"] = float(f.accel_bias_mps2[k])
        r[f"sd_accel_bias_{a}_mps2"] = float(sd[BA + k])
    for name in f.layout.effects:
        stem, unit, scale, comps = EFFECT_COLUMNS[name]
        names = _effect_names(stem, unit, comps)
        vals = _effect_values(f, name) * scale
        sds = f.sd(name) * scale
        assert len(vals) == len(sds) == EFFECT_SIZES[name]
        for n, v, s in zip(names, vals, sds):
            r[n] = float(v)
            r[f"sd_{n}"] = float(s)
    return r


class SolutionWriter:
    """Writes rows to ``path`` (.csv or .mcap); ``write(f, gnss_used)`` per epoch (or ``write_row``
    with a ``row`` already made), ``close()``. The columns follow the first filter written (its
    estimated effects), then ``extra_columns`` (integers, e.g. ``smoothed``)."""

    def __init__(self, path: str | Path, extra_columns: tuple[str, ...] = ()):
        self.path = Path(path)
        self.extra_columns = tuple(extra_columns)
        self.kind = self.path.suffix.lower()
        if self.kind not in (".csv", ".mcap"):
            raise ValueError(f"--solution {self.path}: the extension must be .csv or .mcap")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.columns: list[str] = []
        self.rows = 0
        self._fh = open(self.path, "w" if self.kind == ".csv" else "wb")
        self._writer = None
        if self.kind == ".mcap":
            from mcap.writer import CompressionType, Writer
            self._writer = Writer(self._fh, compression=CompressionType.ZSTD)
            self._writer.start(profile="", library="v2xpos")

    def _start(self, effects: tuple[str, ...]) -> None:
        self.columns = columns(tuple(effects)) + list(self.extra_columns)
        if self.kind == ".csv":
            self._fh.write(",".join(self.columns) + "\n")
        else:
            from v2xpos.output.foxglove import schema_data
            ints = ("gps_week", "gnss_used") + self.extra_columns
            props = {c: ({"type": "string"} if c == "fix" else {"type": "integer"} if c in ints
                         else {"type": "number"}) for c in self.columns}
            schema = {"type": "object", "description": __doc__.split("\n\n")[1], "properties": props,
                      "required": self.columns}
            sid = self._writer.register_schema("v2xpos.Solution", "jsonschema", json.dumps(schema).encode())
            self._ch = self._writer.register_channel("/solution", "json", sid)
            fid = self._writer.register_schema("foxglove.LocationFix", "protobuf", schema_data("foxglove.LocationFix"))
            self._loc = self._writer.register_channel("/location/solution", "protobuf", fid)

    def write(self, f: Any, gnss_used: bool) -> None:
        self.write_row(row(f, gnss_used), f.layout.effects)

    def write_row(self, r: dict, effects: tuple[str, ...]) -> None:
        """One row (``row``'s keys, plus ``extra_columns``) of a filter estimating ``effects``."""
        if not self.columns:
            self._start(effects)
        self.rows += 1
        if self.kind == ".csv":
            self._fh.write(",".join(r[c] if isinstance(r[c], str) else f"{r[c]:.12g}" for c in self.columns) + "\n")
            return
        from v2xpos.output.foxglove import location_fix
        t_ns = int(round(gps_seconds_to_unix(r["t_gps_s"]) * 1e9))
        self._writer.add_message(self._ch, log_time=t_ns, publish_time=t_ns, sequence=self.rows,
                                 data=json.dumps({c: r[c] for c in self.columns}).encode())
        lla = np.radians([r["lat_deg"], r["lon_deg"]]).tolist() + [r["height_m"]]
        self._writer.add_message(self._loc, log_time=t_ns, publish_time=t_ns, sequence=self.rows,
                                 data=location_fix(t_ns, "solution", lla, [r["sd_north_m"], r["sd_east_m"], r["sd_down_m"]],
                                                   [r["vn_mps"], r["ve_mps"], r["vd_mps"]], math.radians(r["yaw_deg"]),
                                                   "valid" if r["gnss_used"] else "fix_invalid"))

    def close(self) -> None:
        if self._writer is not None:
            self._writer.finish()
        self._fh.close()
