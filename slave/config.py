"""Slave configuration (TOML) and the pieces shared with the master: state source, link, impairment.
One group per table (``SlaveConfig.service``, ``.link``, ``.source``, ``.impairment``, ``.security``,
``.corrections``, ``.validity``), each read against its schema (``v2xpos.schema.read_table``).

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

from v2xpos.config import (ConfigError, FilterValidity, LinkImpairment, SourceConfig, check_keys,  # noqa: F401
                           config_dir, corrections_from_table, field_key, impairment_from_table, link_from_table,
                           load_toml, read_group, take, validity_from_table)
from v2xpos.link import LinkConfig


@dataclass
class SlaveService:
    """``[service]``: identity, publish rate, session length, IMU publishing, real-time priority."""
    fleet: str = "demo"
    vehicle_id: str = "t1"
    rate_hz: float = 100.0               # StateMessage publish rate
    duration_s: float | None = None
    publish_imu: bool = False
    realtime_priority: int = 0


SERVICE_KEYS = (field_key(SlaveService, "fleet", str), field_key(SlaveService, "vehicle_id", str),
                field_key(SlaveService, "rate_hz", float, low=0.1, high=1000.0),
                field_key(SlaveService, "duration_s", float), field_key(SlaveService, "publish_imu", bool),
                field_key(SlaveService, "realtime_priority", int, low=0, high=99))


@dataclass
class SlaveSecurity:
    """``[security]``: the optional Ed25519 signing key (relative to the config file)."""
    key_file: str | None = None


@dataclass
class SlaveConfig:
    """A slave's configuration: one group per TOML table (module docstring), ``path`` the file."""
    service: SlaveService = field(default_factory=SlaveService)
    link: LinkConfig = field(default_factory=lambda: LinkConfig(mode="client", connect=["tcp/127.0.0.1:7447"],
                                                                        connect_timeout_ms=60000))
    source: SourceConfig = field(default_factory=SourceConfig)
    impairment: LinkImpairment = field(default_factory=LinkImpairment)
    security: SlaveSecurity = field(default_factory=SlaveSecurity)
    corrections: object | None = None
    validity: FilterValidity = field(default_factory=FilterValidity)
    path: str = "<defaults>"

    @classmethod
    def load(cls, path: str | Path) -> "SlaveConfig":
        d = load_toml(path)
        return cls.from_dict(d, str(path))

    @classmethod
    def from_dict(cls, d: dict, path: str = "<dict>") -> "SlaveConfig":
        check_keys(d, {"service", "link", "source", "impairment", "security", "corrections", "validity"}, path)
        validity = validity_from_table(take(d, "validity", dict, {}, path), f"{path}: [validity]", config_dir(path))
        service = read_group(SlaveService, take(d, "service", dict, {}, path), SERVICE_KEYS, f"{path}: [service]")
        security = read_group(SlaveSecurity, take(d, "security", dict, {}, path),
                              (field_key(SlaveSecurity, "key_file", str),), f"{path}: [security]")
        if security.key_file:                 # relative to the config file, as every path in it
            security.key_file = str(config_dir(path) / Path(security.key_file).expanduser())
        return cls(service=service,
                   link=link_from_table(take(d, "link", dict, {"mode": "client", "connect": ["tcp/127.0.0.1:7447"],
                                                             "connect_timeout_ms": 60000}, path), f"{path}: [link]"),
                   source=SourceConfig.from_table(take(d, "source", dict, {}, path), f"{path}: [source]"),
                   impairment=impairment_from_table(take(d, "impairment", dict, {}, path), f"{path}: [impairment]"),
                   security=security, corrections=corrections_from_table(d, path),
                   validity=FilterValidity(validity.filter_integrity, validity.verification_out), path=path)
