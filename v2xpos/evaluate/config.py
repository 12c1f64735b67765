"""``SENSOR.toml``: what is declared about the sensor under test, read and checked.

Layout (every table and key; an unknown key is rejected with the file, the table and a "did you
mean")::

    [sensor]
    name = "front_radar"
    mount_m = [3.7, 0.0, -0.5]     # sensor origin in the master's body frame (x fwd, y right, z down)
    mount_yaw_deg = 0.0            # declared boresight yaw in the master's body frame (+ turns right)
    clock = "gps"                  # object time stamps: "gps" (GPS seconds) or "utc" (Unix seconds, UTC)
    field_of_view_deg = 120.0      # full horizontal opening angle, centred on the boresight
    max_range_m = 150.0

    [targets.B]                    # one table per reference target (optional: default reference point 0)
    reference_point_m = [-1.0, 0.0, 0.0]   # the point the sensor reports of B, in B's body frame
    # reference = "nearest"                # or: the point of B's outline nearest to the sensor
    # outline_m = [[2.0, -0.9, 0.0], ...]  # B's footprint polygon (body frame) for "nearest",
                                           # when the reference (a session MCAP) carries none

    [association]                  # optional
    gate_m = 5.0                   # first-pass gate around the predicted reference point [m]
    max_latency_s = 0.75           # latencies searched: -max/3 .. max [s]

    [can]                          # only for a CAN log (ASC, BLF, MF4)
    dbc = "radar.dbc"              # relative to SENSOR.toml
    [can.signals]                  # field = "MESSAGE.SIGNAL" or {signal = "MESSAGE.SIGNAL", scale = -1.0}
    object_id = "Obj.Obj_ID"
    x_m = "Obj.Obj_DistLong"
    y_m = "Obj.Obj_DistLat"
    vx_mps = "Obj.Obj_VrelLong"
    vy_mps = "Obj.Obj_VrelLat"
    # z_m, existence, class: optional, from the same message

Frames: the sensor frame has x along the boresight, y to its right, z down; it is the master's
body frame rotated by ``mount_yaw_deg`` about z and moved to ``mount_m``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from v2xpos.config import ConfigError, check_keys, load_toml, take

SENSOR_KEYS = {"name", "mount_m", "mount_yaw_deg", "clock", "field_of_view_deg", "max_range_m"}
TARGET_KEYS = {"reference_point_m", "reference", "outline_m"}
ASSOCIATION_KEYS = {"gate_m", "max_latency_s"}
CAN_KEYS = {"dbc", "signals"}
OBJECT_FIELDS = ("object_id", "x_m", "y_m", "vx_mps", "vy_mps")
OPTIONAL_FIELDS = ("z_m", "existence", "class")
SIGNAL_KEYS = {"signal", "scale", "offset"}
CLOCKS = ("gps", "utc")

DEFAULT_GATE_M = 5.0
"""First-pass gate [m]: the reported point is searched within this distance of the reference point
predicted with the effects estimated so far (later passes gate statistically)."""

DEFAULT_MAX_LATENCY_S = 0.75
"""Latency search window [s]: automotive radars and cameras report 30-300 ms after their
measurement (ISO 23150:2023 object interface timestamps; camera pipelines up to ~200 ms)."""


class SensorConfigError(ConfigError):
    """A SENSOR.toml that cannot be used (the message names the file, the table and the key)."""


@dataclass
class SignalRef:
    """One object field decoded from a CAN signal: value = scale * decoded + offset."""
    message: str
    signal: str
    scale: float = 1.0
    offset: float = 0.0


@dataclass
class CanMap:
    dbc: Path
    signals: dict[str, SignalRef]


@dataclass
class TargetDecl:
    """What the sensor reports of one target: a fixed point of its body or its nearest point."""
    reference_point_m: np.ndarray = field(default_factory=lambda: np.zeros(3))
    nearest: bool = False
    outline_m: np.ndarray | None = None


@dataclass
class SensorConfig:
    path: Path
    name: str
    mount_m: np.ndarray
    mount_yaw_rad: float
    clock: str = "gps"
    field_of_view_rad: float = math.radians(120.0)
    max_range_m: float = 150.0
    targets: dict[str, TargetDecl] = field(default_factory=dict)
    gate_m: float = DEFAULT_GATE_M
    max_latency_s: float = DEFAULT_MAX_LATENCY_S
    can: CanMap | None = None

    def target(self, target_id: str) -> TargetDecl:
        return self.targets.get(target_id, TargetDecl())

    def as_dict(self) -> dict:
        """The declaration as written into metrics.json (degrees, lists)."""
        return {"name": self.name, "mount_m": [float(x) for x in self.mount_m],
                "mount_yaw_deg": math.degrees(self.mount_yaw_rad), "clock": self.clock,
                "field_of_view_deg": math.degrees(self.field_of_view_rad), "max_range_m": self.max_range_m,
                "targets": {k: ({"reference": "nearest"} if t.nearest else
                                {"reference_point_m": [float(x) for x in t.reference_point_m]})
                            for k, t in sorted(self.targets.items())},
                "association": {"gate_m": self.gate_m, "max_latency_s": self.max_latency_s}}


def _vec(table: dict, key: str, n: int, default, where: str) -> np.ndarray:
    v = take(table, key, list, default, where)
    if v is None:
        return None
    if len(v) != n or not all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in v):
        raise SensorConfigError(f"{where}.{key}: expected {n} numbers, got {v!r}")
    out = np.asarray(v, float)
    if not np.all(np.isfinite(out)):
        raise SensorConfigError(f"{where}.{key}: not finite: {v!r}")
    return out


def _positive(table: dict, key: str, default: float, where: str, upper: float = math.inf) -> float:
    v = take(table, key, float, default, where)
    if not (0.0 < v <= upper):
        raise SensorConfigError(f"{where}.{key}: must be in (0, {upper:g}], got {v!r}")
    return v


def _signal(value, where: str) -> SignalRef:
    if isinstance(value, str):
        value = {"signal": value}
    if not isinstance(value, dict):
        raise SensorConfigError(f"{where}: expected \"MESSAGE.SIGNAL\" or a table, got {value!r}")
    check_keys(value, SIGNAL_KEYS, where)
    name = take(value, "signal", str, None, where)
    if not name or name.count(".") != 1 or not all(name.split(".")):
        raise SensorConfigError(f"{where}.signal: expected \"MESSAGE.SIGNAL\", got {name!r}")
    msg, sig = name.split(".")
    return SignalRef(msg, sig, take(value, "scale", float, 1.0, where), take(value, "offset", float, 0.0, where))


def _outline(table: dict, where: str) -> np.ndarray | None:
    v = take(table, "outline_m", list, None, where)
    if v is None:
        return None
    try:
        pts = np.asarray(v, float)
    except (TypeError, ValueError):
        raise SensorConfigError(f"{where}.outline_m: expected a list of [x, y, z] points") from None
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) < 3 or not np.all(np.isfinite(pts)):
        raise SensorConfigError(f"{where}.outline_m: expected at least 3 [x, y, z] points, got {v!r}")
    return pts


def load_sensor_config(path: str | Path) -> SensorConfig:
    """Read and check SENSOR.toml (module docstring); SensorConfigError names the file and key."""
    path = Path(path)
    try:
        d = load_toml(path)
    except ConfigError as exc:
        raise SensorConfigError(str(exc)) from None
    try:
        return _parse(path, d)
    except SensorConfigError:
        raise
    except ConfigError as exc:
        raise SensorConfigError(str(exc)) from None


def _parse(path: Path, d: dict) -> SensorConfig:
    check_keys(d, {"sensor", "targets", "association", "can"}, f"{path}")
    s = take(d, "sensor", dict, None, f"{path}")
    if s is None:
        raise SensorConfigError(f"{path}: missing table [sensor]")
    w = f"{path}: [sensor]"
    check_keys(s, SENSOR_KEYS, w)
    name = take(s, "name", str, None, w)
    if not name:
        raise SensorConfigError(f"{w}.name: missing")
    mount = _vec(s, "mount_m", 3, None, w)
    if mount is None:
        raise SensorConfigError(f"{w}.mount_m: missing (the sensor origin in the master's body frame)")
    clock = take(s, "clock", str, "gps", w)
    if clock not in CLOCKS:
        raise SensorConfigError(f"{w}.clock: one of {list(CLOCKS)}, got {clock!r}")
    cfg = SensorConfig(path=path, name=name, mount_m=mount,
                       mount_yaw_rad=math.radians(take(s, "mount_yaw_deg", float, 0.0, w)), clock=clock,
                       field_of_view_rad=math.radians(_positive(s, "field_of_view_deg", 120.0, w, 360.0)),
                       max_range_m=_positive(s, "max_range_m", 150.0, w))
    targets = take(d, "targets", dict, {}, f"{path}")
    for tid, t in targets.items():
        wt = f"{path}: [targets.{tid}]"
        if not isinstance(t, dict):
            raise SensorConfigError(f"{wt}: expected a table")
        check_keys(t, TARGET_KEYS, wt)
        ref = take(t, "reference", str, "point", wt)
        if ref not in ("point", "nearest"):
            raise SensorConfigError(f"{wt}.reference: \"point\" or \"nearest\", got {ref!r}")
        if ref == "nearest" and "reference_point_m" in t:
            raise SensorConfigError(f"{wt}: reference = \"nearest\" and reference_point_m exclude each other")
        cfg.targets[str(tid)] = TargetDecl(reference_point_m=_vec(t, "reference_point_m", 3, [0.0, 0.0, 0.0], wt),
                                           nearest=ref == "nearest", outline_m=_outline(t, wt))
    a = take(d, "association", dict, {}, f"{path}")
    wa = f"{path}: [association]"
    check_keys(a, ASSOCIATION_KEYS, wa)
    cfg.gate_m = _positive(a, "gate_m", DEFAULT_GATE_M, wa)
    cfg.max_latency_s = _positive(a, "max_latency_s", DEFAULT_MAX_LATENCY_S, wa, 10.0)
    c = take(d, "can", dict, None, f"{path}")
    if c is not None:
        wc = f"{path}: [can]"
        check_keys(c, CAN_KEYS, wc)
        dbc = take(c, "dbc", str, None, wc)
        if not dbc:
            raise SensorConfigError(f"{wc}.dbc: missing (the sensor's DBC file)")
        sig = take(c, "signals", dict, None, wc)
        if sig is None:
            raise SensorConfigError(f"{wc}: missing table [can.signals]")
        ws = f"{path}: [can.signals]"
        check_keys(sig, set(OBJECT_FIELDS) | set(OPTIONAL_FIELDS), ws)
        missing = [k for k in OBJECT_FIELDS if k not in sig]
        if missing:
            raise SensorConfigError(f"{ws}: missing {missing}")
        refs = {k: _signal(v, f"{ws}.{k}") for k, v in sig.items()}
        if len({r.message for r in refs.values()}) != 1:
            raise SensorConfigError(f"{ws}: every field must come from one message (one object per frame), got "
                                    f"{sorted({r.message for r in refs.values()})}")
        cfg.can = CanMap(dbc=(path.parent / dbc), signals=refs)
    return cfg
