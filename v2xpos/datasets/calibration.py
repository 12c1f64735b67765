"""The ``[calibration]`` table of a dataset descriptor or a vehicle config: estimated effects that
go back into the vehicle.

Every value is the same quantity, with the same name, sign and unit, as the ``effects`` object of
``v2xpos calibrate --json`` (conventions in ``v2xpos.diagnose.inject``): corrections to what the
``[imu]``/``[gnss]`` tables declare, not totals. Angles are in degrees because people read and
write this table::

    [calibration]
    source = "convoy_dev/B/dataset.toml"     # the recording it was estimated from
    date = "2026-11-24"                       # when it was estimated (ISO 8601)
    software = "v2xpos 0.2.0 (git 1a2b3c4)"   # optional
    imu_time_offset_s = { value = -0.025, sd = 0.003 }
    imu_clock_drift_ppm = { value = 0.0, sd = 5.0 }
    gnss_latency_s = { value = 0.0, sd = 0.001 }
    imu_misalignment_deg = { value = [0.4, -0.6, -1.0], sd = [0.05, 0.05, 0.1] }   # roll, pitch, yaw
    gnss_lever_arm_m = { value = [0.5, 0.3, 0.0], sd = [0.02, 0.02, 0.1] }         # added to [gnss] lever_arm_m
    gyro_scale = { value = [0.0, 0.0, -0.007], sd = [0.0, 0.0, 0.0005] }            # fraction, vehicle axes
    accel_scale = { value = [0.0, 0.0, 0.0], sd = [0.01, 0.01, 0.01] }
    imu_gyro_noise_rps_rthz = { value = 8.7e-5, sd = 1e-6 }    # measured white noise of this IMU
    imu_accel_noise_mps2_rthz = { value = 1.0e-3, sd = 1e-5 }   # (replaces the filter's default)
    imu_gyro_allan_rps_rthz = { value = 1.2e-4, sd = 4e-5 }    # white density covering the Allan
    imu_accel_allan_mps2_rthz = { value = 1.1e-3, sd = 4e-4 }  # deviation at the stops (tau >= 1 s)

Effects left out are zero (not estimated); the noise entries, when present, replace the
filter's default IMU noise densities (they are totals, not corrections; the larger of the white
noise and the Allan-covering density of a sensor is used, ``v2xpos.ins.calibrated``). An entry's sd is its 1-sigma; a value whose sd is 0
is taken as exact. Unknown keys are rejected with the table and the key named.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

from v2xpos.schema import check_keys

EFFECT_SHAPES: dict[str, int] = {
    "imu_time_offset_s": 1, "imu_clock_drift_ppm": 1, "gnss_latency_s": 1,
    "imu_misalignment_deg": 3, "gnss_lever_arm_m": 3, "gyro_scale": 3, "accel_scale": 3,
    "imu_gyro_noise_rps_rthz": 1, "imu_accel_noise_mps2_rthz": 1,
    "imu_gyro_allan_rps_rthz": 1, "imu_accel_allan_mps2_rthz": 1,
}
"""Effect name -> number of components (1 = scalar)."""
INFO_KEYS = ("source", "date", "software")


class CalibrationError(ValueError):
    """A ``[calibration]`` table that cannot be used; the message names where and the key."""


@dataclass
class CalibrationEntry:
    """One effect: value and 1-sigma, scalars as floats, vectors as 3-tuples."""
    value: float | tuple
    sd: float | tuple


@dataclass
class CalibrationTable:
    """Parsed ``[calibration]`` table: effects by name plus where they came from."""
    effects: dict[str, CalibrationEntry] = field(default_factory=dict)
    source: str | None = None
    date: str | None = None
    software: str | None = None

    def value(self, name: str) -> Any:
        """The value of effect ``name`` (zero of its shape when absent)."""
        if name in self.effects:
            return self.effects[name].value
        return 0.0 if EFFECT_SHAPES[name] == 1 else (0.0, 0.0, 0.0)

    def to_toml(self) -> str:
        """The table as TOML text (``[calibration]`` header included), parseable by
        :func:`parse_calibration`."""
        lines = ["[calibration]"]
        for key in INFO_KEYS:
            v = getattr(self, key)
            if v is not None:
                lines.append(f"{key} = {_toml_str(v)}")
        for name in EFFECT_SHAPES:
            if name in self.effects:
                e = self.effects[name]
                lines.append(f"{name} = {{ value = {_toml_num(e.value)}, sd = {_toml_num(e.sd)} }}")
        return "\n".join(lines) + "\n"


def _toml_str(s: str) -> str:
    return '"' + s.replace("\\", "\\\\").replace('"', '\\"') + '"'


def _toml_num(v: Any) -> str:
    if isinstance(v, (tuple, list)):
        return "[" + ", ".join(_toml_num(x) for x in v) + "]"
    return repr(float(v))


def _number(v: Any, where: str) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(float(v)):
        raise CalibrationError(f"{where}: expected a finite number, got {v!r}")
    return float(v)


def _component(v: Any, n: int, where: str) -> float | tuple:
    if n == 1:
        return _number(v, where)
    if not isinstance(v, list) or len(v) != n:
        raise CalibrationError(f"{where}: expected a list of {n} numbers, got {v!r}")
    return tuple(_number(x, f"{where}[{i}]") for i, x in enumerate(v))


def parse_calibration(table: Any, where: str) -> CalibrationTable:
    """Validate a ``[calibration]`` table (a dict from TOML). ``where`` names the file (and table)
    in every error, e.g. ``"B/dataset.toml: [calibration]"``."""
    if not isinstance(table, dict):
        raise CalibrationError(f"{where}: expected a table, got {type(table).__name__}")
    out = CalibrationTable()
    check_keys(table, (*INFO_KEYS, *EFFECT_SHAPES), where, CalibrationError)
    for key, v in table.items():
        if key in INFO_KEYS:
            if not isinstance(v, str):
                raise CalibrationError(f"{where}.{key}: expected a string, got {v!r}")
            setattr(out, key, v)
            continue
        w = f"{where}.{key}"
        if not isinstance(v, dict):
            raise CalibrationError(f"{w}: expected {{ value = ..., sd = ... }}, got {v!r}")
        check_keys(v, ("value", "sd"), w, CalibrationError)
        if "value" not in v or "sd" not in v:
            raise CalibrationError(f"{w}: needs both 'value' and 'sd'")
        n = EFFECT_SHAPES[key]
        value = _component(v["value"], n, f"{w}.value")
        sd = _component(v["sd"], n, f"{w}.sd")
        if any(s < 0 for s in (sd if isinstance(sd, tuple) else (sd,))):
            raise CalibrationError(f"{w}.sd: must be >= 0, got {v['sd']!r}")
        out.effects[key] = CalibrationEntry(value, sd)
    return out
