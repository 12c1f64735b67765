"""Slave configuration (TOML) and the pieces shared with the master: state source, link, impairment.

Example (``configs/slave_t1.toml``)::

    [service]
    fleet = "demo"
    vehicle_id = "t1"
    rate_hz = 100          # StateMessage publish rate [Hz]
    duration_s = 40        # stop this long after the session clock starts (omit: until the source
                           # ends, or SIGTERM/SIGINT)

    [link]                 # v2xpos.link.LinkConfig
    mode = "client"         # routed by the master's router (see docs/services.md)
    connect_timeout_ms = 60000  # wait this long for the router at start
    connect = ["tcp/127.0.0.1:7447"]

    [source]               # where the states come from (v2xpos.sources): recording | device | sim
    type = "recording"
    dataset = "../shared/data/convoy_dev/B/dataset.toml"   # relative to this file
    speed = 1.0            # replay speed; the session clock follows the master's (sync = "auto")

    [impairment]           # optional injected link delay (tests and trials only)
    latency_ms = 100
    jitter_ms = 5
    spikes = [[1400000010.0, 1400000012.0, 300.0]]   # [t_start_gps_s, t_end_gps_s, extra_ms]

    [security]
    key_file = "keys/t1.key"   # optional Ed25519 signing key (v2xpos keys)

    [corrections]          # RTK corrections relayed by the master (v2xpos.sources.corrections)
    receive = true         # write them into this vehicle's receiver

Every error names the file and the key.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from v2xpos.config import (ConfigError, LinkImpairment, SourceConfig, check_keys, config_dir,  # noqa: F401
                           corrections_from_table, impairment_from_table, link_from_table, load_toml, take,
                           validity_from_table)
from v2xpos.link import LinkConfig


@dataclass
class SlaveConfig:
    fleet: str = "demo"
    vehicle_id: str = "t1"
    rate_hz: float = 100.0
    duration_s: float | None = None
    link: LinkConfig = field(default_factory=lambda: LinkConfig(mode="client", connect=["tcp/127.0.0.1:7447"],
                                                                        connect_timeout_ms=60000))
    source: SourceConfig = field(default_factory=SourceConfig)
    impairment: LinkImpairment = field(default_factory=LinkImpairment)
    key_file: str | None = None
    publish_imu: bool = False
    realtime_priority: int = 0
    corrections: object | None = None
    filter_integrity: dict = field(default_factory=dict)   # [validity]: the filter's alert limit / integrity risk
    verification_out: Path | None = None                    # [validity]: write the set-up's record here at the end
    path: str = "<defaults>"

    @classmethod
    def load(cls, path: str | Path) -> "SlaveConfig":
        d = load_toml(path)
        return cls.from_dict(d, str(path))

    @classmethod
    def from_dict(cls, d: dict, path: str = "<dict>") -> "SlaveConfig":
        check_keys(d, {"service", "link", "source", "impairment", "security", "corrections", "validity"}, path)
        validity = validity_from_table(take(d, "validity", dict, {}, path), f"{path}: [validity]", config_dir(path))
        s = take(d, "service", dict, {}, path)
        w = f"{path}: [service]"
        check_keys(s, {"fleet", "vehicle_id", "rate_hz", "duration_s", "publish_imu", "realtime_priority"}, w)
        rate = take(s, "rate_hz", float, 100.0, w)
        if not 0.1 <= rate <= 1000.0:
            raise ConfigError(f"{w}.rate_hz: {rate} outside 0.1..1000 Hz")
        rt = take(s, "realtime_priority", int, 0, w)
        if not 0 <= rt <= 99:
            raise ConfigError(f"{w}.realtime_priority: {rt} outside 0..99")
        sec = take(d, "security", dict, {}, path)
        check_keys(sec, {"key_file"}, f"{path}: [security]")
        cfg = cls(fleet=take(s, "fleet", str, "demo", w), vehicle_id=take(s, "vehicle_id", str, "t1", w),
                  rate_hz=rate, duration_s=take(s, "duration_s", float, None, w),
                  link=link_from_table(take(d, "link", dict, {"mode": "client", "connect": ["tcp/127.0.0.1:7447"],
                                                        "connect_timeout_ms": 60000}, path), f"{path}: [link]"),
                  source=SourceConfig.from_table(take(d, "source", dict, {}, path), f"{path}: [source]"),
                  impairment=impairment_from_table(take(d, "impairment", dict, {}, path), f"{path}: [impairment]"),
                  key_file=take(sec, "key_file", str, None, f"{path}: [security]"),
                  publish_imu=take(s, "publish_imu", bool, False, w), realtime_priority=rt,
                  corrections=corrections_from_table(d, path),
                  filter_integrity=validity.filter_integrity, verification_out=validity.verification_out,
                  path=path)
        if cfg.key_file:                      # relative to the config file, as every path in it
            cfg.key_file = str(config_dir(path) / Path(cfg.key_file).expanduser())
        return cfg
