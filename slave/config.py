"""Slave configuration (TOML) and the pieces shared with the master: state source and link.

Example (``configs/slave_t1.toml``)::

    [service]
    fleet = "demo"
    vehicle_id = "t1"
    rate_hz = 100          # StateMessage publish rate [Hz]
    duration_s = 40        # stop at scenario epoch + duration (omit: run until SIGTERM/SIGINT)

    [link]                 # v2xpos.link.LinkConfig
    mode = "client"         # routed by the master's router (see docs/services.md)
    connect_timeout_ms = 60000  # wait this long for the router at start
    connect = ["tcp/127.0.0.1:7447"]

    [source]
    type = "ins"           # ins (simulated sensors through the INS filter) | dataset | truth_noise
    # dataset = "../shared/data/drive_0708"   # with type = "dataset": a recording paced at real time
    # align_to_epoch = true                   # its first IMU sample at the scenario epoch
    scenario = "convoy"    # sim.scenarios builder
    actor = "t1"           # default: vehicle_id
    start_unix_s = 0       # wall time of the scenario epoch (the CLI --start overrides)
    [source.params]        # scenario parameters, identical in every process
    vehicles = 4
    seed = 0

    [impairment]           # injected link delay; default: the scenario's setting for this actor
    latency_ms = 100
    jitter_ms = 5

    [security]
    key_file = "keys/t1.key"   # optional Ed25519 signing key (v2xpos keys)

Every error names the file and the key.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from v2xpos.compat import tomllib
from v2xpos.link import LinkConfig


class ConfigError(ValueError):
    """A configuration file that cannot be used; the message names the file and the key."""


def load_toml(path: str | Path) -> dict:
    p = Path(path)
    try:
        with p.open("rb") as f:
            return tomllib.load(f)
    except FileNotFoundError:
        raise ConfigError(f"{p}: file not found") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{p}: not valid TOML: {exc}") from None
    except UnicodeDecodeError as exc:  # added by trust/resilience (fuzz finding): name the file
        raise ConfigError(f"{p}: not UTF-8 text: {exc}") from None


def take(table: dict, key: str, kind: type | tuple, default: Any, where: str) -> Any:
    """``table[key]`` checked against ``kind`` (ints are accepted for floats); default if absent."""
    if key not in table:
        return default
    v = table[key]
    kinds = kind if isinstance(kind, tuple) else (kind,)
    if float in kinds and isinstance(v, int) and not isinstance(v, bool):
        v = float(v)
    if not isinstance(v, kinds) or (isinstance(v, bool) and bool not in kinds):
        names = "/".join(k.__name__ for k in kinds)
        raise ConfigError(f"{where}.{key}: expected {names}, got {type(v).__name__} {v!r}")
    return v


def check_keys(table: dict, allowed: set, where: str) -> None:
    """ConfigError naming ``where`` and the unknown keys, with a "did you mean" for a near miss."""
    unknown = sorted((str(k) for k in set(table) - set(allowed)))
    if unknown:
        from v2xpos.datasets.calibration import did_you_mean
        hint = "".join(did_you_mean(k, allowed).replace(" (did you mean", f" ({k!r}: did you mean")
                       for k in unknown[:3])
        raise ConfigError(f"{where}: unknown key(s) {unknown}{hint}; allowed {sorted(allowed)}")


@dataclass
class SourceConfig:
    """Where the vehicle's states come from (see slave.source)."""
    type: str = "ins"
    scenario: str = "convoy"
    actor: str | None = None
    start_unix_s: float = 0.0
    params: dict = field(default_factory=dict)
    dataset: str | None = None
    align_to_epoch: bool = True

    @classmethod
    def from_table(cls, t: dict, where: str) -> "SourceConfig":
        check_keys(t, {"type", "scenario", "actor", "start_unix_s", "params", "dataset", "align_to_epoch"}, where)
        typ = take(t, "type", str, "ins", where)
        if typ not in ("ins", "truth_noise", "dataset"):
            raise ConfigError(f"{where}.type: {typ!r} is not one of ['ins', 'truth_noise', 'dataset']")
        dataset = take(t, "dataset", str, None, where)
        if typ == "dataset" and not dataset:
            raise ConfigError(f"{where}.dataset: required with type = 'dataset' (a dataset folder or dataset.toml)")
        return cls(type=typ, scenario=take(t, "scenario", str, "convoy", where),
                   actor=take(t, "actor", str, None, where),
                   start_unix_s=take(t, "start_unix_s", float, 0.0, where),
                   params=dict(take(t, "params", dict, {}, where)), dataset=dataset,
                   align_to_epoch=take(t, "align_to_epoch", bool, True, where))


def link_from_table(t: dict, where: str) -> LinkConfig:
    try:
        return LinkConfig.from_dict(t, where)
    except ValueError as exc:
        raise ConfigError(str(exc)) from None


@dataclass
class SlaveConfig:
    fleet: str = "demo"
    vehicle_id: str = "t1"
    rate_hz: float = 100.0
    duration_s: float | None = None
    link: LinkConfig = field(default_factory=lambda: LinkConfig(mode="client", connect=["tcp/127.0.0.1:7447"],
                                                                        connect_timeout_ms=60000))
    source: SourceConfig = field(default_factory=SourceConfig)
    latency_ms: float | None = None
    jitter_ms: float | None = None
    key_file: str | None = None
    publish_imu: bool = False
    path: str = "<defaults>"

    @classmethod
    def load(cls, path: str | Path) -> "SlaveConfig":
        d = load_toml(path)
        return cls.from_dict(d, str(path))

    @classmethod
    def from_dict(cls, d: dict, path: str = "<dict>") -> "SlaveConfig":
        check_keys(d, {"service", "link", "source", "impairment", "security"}, path)
        s = take(d, "service", dict, {}, path)
        w = f"{path}: [service]"
        check_keys(s, {"fleet", "vehicle_id", "rate_hz", "duration_s", "publish_imu"}, w)
        rate = take(s, "rate_hz", float, 100.0, w)
        if not 0.1 <= rate <= 1000.0:
            raise ConfigError(f"{w}.rate_hz: {rate} outside 0.1..1000 Hz")
        imp = take(d, "impairment", dict, {}, path)
        wi = f"{path}: [impairment]"
        check_keys(imp, {"latency_ms", "jitter_ms"}, wi)
        sec = take(d, "security", dict, {}, path)
        check_keys(sec, {"key_file"}, f"{path}: [security]")
        cfg = cls(fleet=take(s, "fleet", str, "demo", w), vehicle_id=take(s, "vehicle_id", str, "t1", w),
                  rate_hz=rate, duration_s=take(s, "duration_s", float, None, w),
                  link=link_from_table(take(d, "link", dict, {"mode": "client", "connect": ["tcp/127.0.0.1:7447"],
                                                        "connect_timeout_ms": 60000}, path), f"{path}: [link]"),
                  source=SourceConfig.from_table(take(d, "source", dict, {}, path), f"{path}: [source]"),
                  latency_ms=take(imp, "latency_ms", float, None, wi),
                  jitter_ms=take(imp, "jitter_ms", float, None, wi),
                  key_file=take(sec, "key_file", str, None, f"{path}: [security]"),
                  publish_imu=take(s, "publish_imu", bool, False, w), path=path)
        return cfg
