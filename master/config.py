"""Master configuration (TOML): one group per table (``MasterConfig.service``, ``.link``, ``.source``,
``.output`` with ``.can`` / ``.udp`` / ``.zenoh`` / ``.plugins``, ``.scene``, ``.record``,
``.security``, ``.validity``, ``.grading``, ``.corrections``), each read against its schema
(``v2xpos.schema.read_table``: an unknown or misspelt key is refused with a "did you mean").
Example (``configs/master.toml``)::

    [service]
    fleet = "demo"
    master_id = "ego"
    timeout_ms = 200                  # staleness limit
    measurement_point_m = [3.8, 0, 0] # master body frame (front bumper)
    known_vehicles = []               # accepted target ids; empty = any
    duration_s = 40                   # stop this long after the session clock starts (omit: until the
                                      # source ends, or SIGTERM/SIGINT)
    status_hz = 2                     # status JSON on v2xpos/<fleet>/master/<id>/status
    tick_hz = 10                      # NO_DATA / TIMEOUT reports for silent targets
    dispatch = "inline"               # inline (pipeline on the zenoh thread) | asyncio (queue to the loop)
    realtime_priority = 0             # 1-99: run the master SCHED_RR at this priority (0 = normal)

    [validity]                        # when a computed result is VALID (docs/integrity.md)
    max_sigma_h_m = 0.10              # predicted 1-sigma horizontal relative position above it: SIGMA_EXCEEDED
    max_sigma_yaw_deg = 1.0           # predicted 1-sigma relative yaw above it: SIGMA_EXCEEDED
    require_consistency = true        # both filters consistent (else INCONSISTENT) and verified (else UNVERIFIED)
    max_clock_disagreement_ms = 50    # a target's clock this far from the master's: clock alarm (CLOCK_UNSYNCED)
    alert_limit_m = 0.30              # the own filter is verified only while its protection level is within it
    integrity_risk = 1e-5             # the protection level's risk budget (docs/integrity.md)
    verification_file = "A.verification.toml"   # optional: the set-up's [verification] record, read at the start
    write_verification = false        # ... and written at the end of the session (what the filter vouches for then)

    [link]                            # the master embeds the router by default
    mode = "router"
    listen = ["tcp/127.0.0.1:7447"]

    [source]                          # the master's own vehicle, as for a slave (slave.config.SourceConfig)
    type = "recording"
    dataset = "../shared/data/convoy_dev/A/dataset.toml"
    wait_for = ["B"]                  # recording: start the session clock when these slaves are ready

    [output.can]                      # docs/protocol.md §5
    enabled = true
    interface = "virtual"             # python-can interface: "socketcan" (channel "can0") on a vehicle
    channel = "v2xpos"
    bitrate = 500000                  # optional; SocketCAN takes it from `ip link set can0 type can bitrate ...`
    fd = false                        # CAN FD bus (frames stay 8 bytes, layout unchanged)
    data_bitrate = 2000000            # optional, CAN FD data phase
    receive_own_messages = false
    rate_hz = 25                      # max updates per target per second (0 = every result)
    status_hz = 10                    # MASTER_STATUS / MASTER_SIGMA frames per second
    [output.can.slots]                # fixed target -> slot (0..63); other ids: first free slot
    car-2 = 0
    ped-1 = 7
    [output.udp]
    enabled = true
    host = "127.0.0.1"                # any unicast address or host name (not multicast/broadcast)
    port = 47001
    status_hz = 10                    # heartbeat datagrams per second (0 = none): the master is alive
    [output.zenoh]
    enabled = true                    # republish RelativeResult on .../master/<id>/relative

    [scene]
    geojson = "scene.geojson"         # optional V2L lane lines / points / polygons
    rate_hz = 10                      # scene evaluations per second

    [record]                          # paths relative to this file (as every path in it)
    results_csv = "out/results.csv"   # every result as a CSV row (master.results_csv.COLUMNS), streamed
    results_npz = "out/master_results.npz"   # per-result rows for the report (optional)
    summary_json = "out/master_summary.json"
    evaluate_uncompensated = false
    mcap = "out/session.mcap"         # optional: every input and output (v2xpos replay-session)
    mcap_max_mb = 256                 # rotation size

    [grading]
    enabled = false                   # live IMU grading worker (master/grading.py)

    [corrections]                     # optional RTK corrections relayed to every slave (docs/field.md)
    source = "ntrip"                  # ntrip | serial | tcp (v2xpos.sources.corrections)
    caster = "caster.example.net:2101"
    mountpoint = "MOUNT"

    [security]                        # admission control (v2xpos.security.MessageAuthenticator)
    trust_list = "keys/trust.json"    # optional; without it unsigned messages are admitted
    require_signature = true          # with a trust list
    max_age_s = 5.0                   # older: too_old (replay)
    future_tolerance_s = 0.05         # newer than now + this: future
    replay_window = 1024              # anti-replay sequence window
"""
from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from v2xpos.config import (ConfigError, FilterValidity, SourceConfig, check_keys, config_dir, corrections_from_table,
                           field_key, link_from_table, load_toml, read_group, take, validity_from_table)
from v2xpos.link import LinkConfig
from v2xpos.schema import Key, check_choice


@dataclass
class ServiceSettings:
    """``[service]``: identity, staleness limit, measurement point, session length, rates, dispatch."""
    fleet: str = "demo"
    master_id: str = "ego"
    timeout_ms: float = 200.0
    measurement_point_m: tuple = (0.0, 0.0, 0.0)    # master body frame
    known_vehicles: tuple = ()                     # accepted target ids; empty = any
    duration_s: float | None = None
    status_hz: float = 2.0
    tick_hz: float = 10.0
    realtime_priority: int = 0
    dispatch: str = "inline"


SERVICE_KEYS = (field_key(ServiceSettings, "fleet", str), field_key(ServiceSettings, "master_id", str),
                field_key(ServiceSettings, "timeout_ms", float, above=0, high=60000),
                Key("measurement_point_m", list, [0.0, 0.0, 0.0]), Key("known_vehicles", list, []),
                field_key(ServiceSettings, "duration_s", float), field_key(ServiceSettings, "status_hz", float),
                field_key(ServiceSettings, "tick_hz", float), field_key(ServiceSettings, "dispatch", str),
                field_key(ServiceSettings, "realtime_priority", int, low=0, high=99))


@dataclass
class CanOutput:
    """``[output.can]`` (docs/protocol.md §5): the python-can bus, the rates, fixed target slots."""
    enabled: bool = False
    interface: str = "virtual"
    channel: str = "v2xpos"
    rate_hz: float = 25.0                 # max updates per target per second (0 = every result)
    status_hz: float = 10.0
    bitrate: int | None = None
    fd: bool = False
    data_bitrate: int | None = None
    receive_own_messages: bool = False
    slots: dict = field(default_factory=dict)

    def bus_kwargs(self) -> dict:
        """python-can ``Bus`` options (besides interface and channel)."""
        kw = {"receive_own_messages": self.receive_own_messages}
        if self.bitrate is not None:
            kw["bitrate"] = self.bitrate
        if self.fd:
            kw["fd"] = True
            if self.data_bitrate is not None:
                kw["data_bitrate"] = self.data_bitrate
        return kw


CAN_KEYS = (field_key(CanOutput, "enabled", bool), field_key(CanOutput, "interface", str),
            field_key(CanOutput, "channel", str), field_key(CanOutput, "rate_hz", float, low=0, high=1000),
            field_key(CanOutput, "status_hz", float, above=0, high=100),
            field_key(CanOutput, "bitrate", int, low=10_000, high=1_000_000), field_key(CanOutput, "fd", bool),
            field_key(CanOutput, "data_bitrate", int, low=10_000, high=16_000_000),
            field_key(CanOutput, "receive_own_messages", bool), field_key(CanOutput, "slots", dict))


@dataclass
class UdpOutput:
    """``[output.udp]``: destination and heartbeat rate (0 = none)."""
    enabled: bool = False
    host: str = "127.0.0.1"
    port: int = 47001
    status_hz: float = 10.0


UDP_KEYS = (field_key(UdpOutput, "enabled", bool), field_key(UdpOutput, "host", str),
            field_key(UdpOutput, "port", int, low=1, high=65535),
            field_key(UdpOutput, "status_hz", float, low=0, high=100))


@dataclass
class ZenohOutput:
    """``[output.zenoh]``: republish RelativeResult on .../master/<id>/relative."""
    enabled: bool = True


@dataclass
class Outputs:
    """``[output]``: the built-in outputs and the plug-ins (name -> its ``[output.NAME]`` table,
    ``master.outputs``)."""
    can: CanOutput = field(default_factory=CanOutput)
    udp: UdpOutput = field(default_factory=UdpOutput)
    zenoh: ZenohOutput = field(default_factory=ZenohOutput)
    plugins: dict = field(default_factory=dict)


@dataclass
class SceneSettings:
    """``[scene]``: optional V2L GeoJSON and the evaluation rate."""
    geojson: str | None = None
    rate_hz: float = 10.0


@dataclass
class RecordSettings:
    """``[record]``: result files and the MCAP session recording (paths relative to the file)."""
    results_npz: str | None = None
    results_csv: str | None = None
    summary_json: str | None = None
    evaluate_uncompensated: bool = False
    mcap: str | None = None
    mcap_max_mb: float = 256.0


@dataclass
class SecuritySettings:
    """``[security]``: admission control (``v2xpos.security.MessageAuthenticator``)."""
    trust_list: str | None = None
    require_signature: bool = True
    max_age_s: float = 5.0
    future_tolerance_s: float = 0.05
    replay_window: int = 1024


@dataclass
class MasterValidity(FilterValidity):
    """``[validity]``: when a computed result is VALID, and what it sets for the own filter
    (``FilterValidity``)."""
    max_sigma_h_m: float = 0.10
    max_sigma_yaw_deg: float = 1.0
    require_consistency: bool = True
    max_clock_disagreement_s: float = 0.05


@dataclass
class GradingSettings:
    """``[grading]``: the live IMU grading worker (master/grading.py)."""
    enabled: bool = False


VALIDITY_KEYS = (field_key(MasterValidity, "max_sigma_h_m", float, above=0),
                 field_key(MasterValidity, "max_sigma_yaw_deg", float, above=0),
                 field_key(MasterValidity, "require_consistency", bool),
                 Key("max_clock_disagreement_ms", float, 50.0, above=0, high=60000))
"""The master's own ``[validity]`` keys (when a computed result is VALID), read with the own filter's
keys by ``v2xpos.config.validity_from_table``."""
SCENE_KEYS = (field_key(SceneSettings, "geojson", str), field_key(SceneSettings, "rate_hz", float, above=0, high=100))
RECORD_KEYS = tuple(field_key(RecordSettings, name, kind) for name, kind in (
    ("results_npz", str), ("results_csv", str), ("summary_json", str), ("evaluate_uncompensated", bool),
    ("mcap", str))) + (field_key(RecordSettings, "mcap_max_mb", float, above=0),)
SECURITY_KEYS = tuple(field_key(SecuritySettings, name, kind) for name, kind in (
    ("trust_list", str), ("require_signature", bool), ("max_age_s", float), ("future_tolerance_s", float))) + (
    field_key(SecuritySettings, "replay_window", int, low=1, high=1 << 20),)
GRADING_KEYS = (field_key(GradingSettings, "enabled", bool),)
TABLES = ("service", "link", "source", "output", "scene", "record", "security", "grading", "corrections", "validity")
"""The top-level tables of a master config."""


@dataclass
class MasterConfig:
    """A master's configuration: one group per TOML table (module docstring), ``path`` the file."""
    service: ServiceSettings = field(default_factory=ServiceSettings)
    link: LinkConfig = field(default_factory=lambda: LinkConfig(mode="router", listen=["tcp/127.0.0.1:7447"]))
    source: SourceConfig = field(default_factory=SourceConfig)
    output: Outputs = field(default_factory=Outputs)
    scene: SceneSettings = field(default_factory=SceneSettings)
    record: RecordSettings = field(default_factory=RecordSettings)
    security: SecuritySettings = field(default_factory=SecuritySettings)
    validity: MasterValidity = field(default_factory=MasterValidity)
    grading: GradingSettings = field(default_factory=GradingSettings)
    corrections: object | None = None
    path: str = "<defaults>"

    @classmethod
    def load(cls, path: str | Path) -> "MasterConfig":
        return cls.from_dict(load_toml(path), str(path))

    PATH_FIELDS = (("record", "results_npz"), ("record", "results_csv"), ("record", "summary_json"),
                   ("record", "mcap"), ("scene", "geojson"), ("security", "trust_list"))
    """(group, field) of the fields that name files: relative ones resolve against the config file's
    directory."""

    @classmethod
    def from_dict(cls, d: dict, path: str = "<dict>") -> "MasterConfig":
        check_keys(d, set(TABLES), path)

        def table(name: str, default: Any = None) -> Any:
            return take(d, name, dict, {} if default is None else default, path)

        # read in this order, so that a file with several faults names the same one first as before
        groups = dict(validity=master_validity(table("validity"), f"{path}: [validity]", config_dir(path)),
                      grading=read_group(GradingSettings, table("grading"), GRADING_KEYS, f"{path}: [grading]"),
                      service=service_from_table(table("service"), f"{path}: [service]"),
                      output=output_from_table(table("output"), path),
                      scene=read_group(SceneSettings, table("scene"), SCENE_KEYS, f"{path}: [scene]"),
                      record=read_group(RecordSettings, table("record"), RECORD_KEYS, f"{path}: [record]"),
                      security=read_group(SecuritySettings, table("security"), SECURITY_KEYS, f"{path}: [security]"))
        return cls(**groups, link=link_from_table(table("link", {"mode": "router", "listen": ["tcp/127.0.0.1:7447"]}),
                                                  f"{path}: [link]"),
                   source=SourceConfig.from_table(table("source"), f"{path}: [source]"),
                   corrections=corrections_from_table(d, path), path=path)._resolved()

    def _resolved(self) -> "MasterConfig":
        """Relative file paths made absolute against the config file's directory (``config_dir``), as
        the file's comments say; a config built in memory resolves against the working directory."""
        base = config_dir(self.path)
        for group, name in self.PATH_FIELDS:
            value = getattr(getattr(self, group), name)
            if value:
                setattr(getattr(self, group), name, str(base / Path(value).expanduser()))
        return self

    def enabled_outputs(self) -> list[tuple[str, dict]]:
        """(name, table) of every output to open, in this order: ``can``, ``udp``, ``zenoh``,
        ``results_csv`` when enabled (their settings are this config's groups), then the plug-ins."""
        out = self.output
        builtin = (("can", out.can.enabled), ("udp", out.udp.enabled), ("zenoh", out.zenoh.enabled),
                   ("results_csv", bool(self.record.results_csv)))
        return [(name, {}) for name, on in builtin if on] + [
            (name, t) for name, t in out.plugins.items() if t.get("enabled", True)]


def service_from_table(t: dict, where: str) -> ServiceSettings:
    """``[service]`` against ``SERVICE_KEYS``, with the checks a range cannot state."""
    v = read_group(dict, t, SERVICE_KEYS, where)
    check_choice(v["dispatch"], ("inline", "asyncio"), f"{where}.dispatch", ConfigError)
    mp = v["measurement_point_m"]
    if len(mp) != 3 or not all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in mp):
        raise ConfigError(f"{where}.measurement_point_m: expected 3 numbers, got {mp!r}")
    if not all(isinstance(x, str) for x in v["known_vehicles"]):
        raise ConfigError(f"{where}.known_vehicles: expected a list of strings")
    return ServiceSettings(**{**v, "measurement_point_m": tuple(float(x) for x in mp),
                              "known_vehicles": tuple(v["known_vehicles"])})


def master_validity(t: dict, where: str, base_dir: Path) -> MasterValidity:
    """``[validity]``: the master's own keys (``VALIDITY_KEYS``) and the own filter's
    (``v2xpos.config.validity_from_table``)."""
    validity = validity_from_table(t, where, base_dir, VALIDITY_KEYS)
    va = validity.service
    return MasterValidity(max_sigma_h_m=va["max_sigma_h_m"], max_sigma_yaw_deg=va["max_sigma_yaw_deg"],
                          require_consistency=va["require_consistency"],
                          max_clock_disagreement_s=va["max_clock_disagreement_ms"] / 1e3,
                          filter_integrity=validity.filter_integrity, verification_out=validity.verification_out)


CAN_INTERFACES_HINT = ("socketcan", "virtual")
"""The interfaces this project runs and tests: SocketCAN on a vehicle, python-can's virtual bus in tests."""


def output_from_table(out: dict, path: str) -> Outputs:
    """The ``[output]`` table (``[output.can]``, ``[output.udp]``, ``[output.zenoh]``, and a table per
    plug-in output: ``master.outputs``), validated; ConfigError naming the file and key otherwise."""
    from master.outputs import check_output_table, output_kinds
    builtin = {"can", "udp", "zenoh"}
    known = set(output_kinds()) - {"results_csv"}     # results_csv is a path of [record]
    plugins = {k: v for k, v in out.items() if k not in builtin and (k in known or isinstance(v, dict) and "factory" in v)}
    check_keys(out, known | set(plugins), f"{path}: [output]")
    for name, t in plugins.items():
        wp = f"{path}: [output.{name}]"
        if not isinstance(t, dict):
            raise ConfigError(f"{wp}: expected a table, got {type(t).__name__}")
        take(t, "enabled", bool, True, wp)
        check_output_table(name, t, wp)
    wc, wu, wz = f"{path}: [output.can]", f"{path}: [output.udp]", f"{path}: [output.zenoh]"
    can = read_group(CanOutput, take(out, "can", dict, {}, f"{path}: [output]"), CAN_KEYS, wc)
    udp = read_group(UdpOutput, take(out, "udp", dict, {}, f"{path}: [output]"), UDP_KEYS, wu)
    zenoh = read_group(ZenohOutput, take(out, "zenoh", dict, {}, f"{path}: [output]"),
                       (field_key(ZenohOutput, "enabled", bool),), wz)
    from can.interfaces import VALID_INTERFACES
    check_choice(can.interface, sorted(VALID_INTERFACES), f"{wc}.interface (python-can interfaces)", ConfigError)
    if not can.channel:
        raise ConfigError(f"{wc}.channel: empty")
    if can.data_bitrate is not None and not can.fd:
        raise ConfigError(f"{wc}.data_bitrate: only with fd = true")
    from v2xpos.output.can_dbc import N_SLOTS
    seen: dict = {}
    for vid, slot in can.slots.items():
        if not re.fullmatch(r"[A-Za-z0-9_.\-]{1,32}", vid):
            raise ConfigError(f"{wc}.slots: {vid!r} is not a vehicle id (1-32 characters of [A-Za-z0-9_.-])")
        if not isinstance(slot, int) or isinstance(slot, bool) or not 0 <= slot < N_SLOTS:
            raise ConfigError(f"{wc}.slots.{vid}: {slot!r} is not a slot number 0..{N_SLOTS - 1}")
        if slot in seen:
            raise ConfigError(f"{wc}.slots: {seen[slot]!r} and {vid!r} both on slot {slot}")
        seen[slot] = vid
    can.slots = dict(can.slots)
    from v2xpos.output.udp import check_destination
    try:
        check_destination(udp.host)
    except ValueError as exc:
        raise ConfigError(f"{wu}.host: {exc}") from None
    return Outputs(can=can, udp=udp, zenoh=zenoh, plugins=plugins)
