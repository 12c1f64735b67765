"""Master configuration (TOML). Example (``configs/master.toml``)::

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

from v2xpos.config import (ConfigError, SourceConfig, check_keys, config_dir, corrections_from_table,
                           link_from_table, load_toml, take, validity_from_table)
from v2xpos.link import LinkConfig
from v2xpos.schema import Key, check_choice

VALIDITY_KEYS = (Key("max_sigma_h_m", float, 0.10), Key("max_sigma_yaw_deg", float, 1.0),
                 Key("require_consistency", bool, True), Key("max_clock_disagreement_ms", float, 50.0))
"""The master's own ``[validity]`` keys (when a computed result is VALID), read with the own filter's
keys by ``v2xpos.config.validity_from_table``."""


@dataclass
class MasterConfig:
    fleet: str = "demo"
    master_id: str = "ego"
    timeout_ms: float = 200.0
    measurement_point_m: tuple = (0.0, 0.0, 0.0)
    known_vehicles: tuple = ()
    duration_s: float | None = None
    status_hz: float = 2.0
    tick_hz: float = 10.0
    realtime_priority: int = 0
    dispatch: str = "inline"
    link: LinkConfig = field(default_factory=lambda: LinkConfig(mode="router", listen=["tcp/127.0.0.1:7447"]))
    source: SourceConfig = field(default_factory=SourceConfig)
    can_enabled: bool = False
    can_interface: str = "virtual"
    can_channel: str = "v2xpos"
    can_rate_hz: float = 25.0
    can_status_hz: float = 10.0
    can_bitrate: int | None = None
    can_fd: bool = False
    can_data_bitrate: int | None = None
    can_receive_own_messages: bool = False
    can_slots: dict = field(default_factory=dict)
    udp_enabled: bool = False
    udp_host: str = "127.0.0.1"
    udp_port: int = 47001
    udp_status_hz: float = 10.0
    zenoh_enabled: bool = True
    output_plugins: dict = field(default_factory=dict)
    """Plug-in outputs: name -> its ``[output.NAME]`` table (``master.outputs``)."""
    geojson: str | None = None
    scene_hz: float = 10.0
    results_npz: str | None = None
    results_csv: str | None = None
    summary_json: str | None = None
    evaluate_uncompensated: bool = False
    trust_list: str | None = None
    require_signature: bool = True
    max_age_s: float = 5.0
    future_tolerance_s: float = 0.05
    replay_window: int = 1024
    mcap: str | None = None
    mcap_max_mb: float = 256.0
    grading: bool = False
    corrections: object | None = None
    max_sigma_h_m: float = 0.10
    max_sigma_yaw_deg: float = 1.0
    require_consistency: bool = True
    max_clock_disagreement_s: float = 0.05
    filter_integrity: dict = field(default_factory=dict)   # [validity] alert_limit_m / integrity_risk of the own filter
    verification_out: Path | None = None                    # [validity] write the own set-up's record here at the end
    path: str = "<defaults>"

    @classmethod
    def load(cls, path: str | Path) -> "MasterConfig":
        return cls.from_dict(load_toml(path), str(path))

    PATH_FIELDS = ("results_npz", "results_csv", "summary_json", "mcap", "geojson", "trust_list")
    """Fields that name files: relative ones resolve against the config file's directory."""

    @classmethod
    def from_dict(cls, d: dict, path: str = "<dict>") -> "MasterConfig":
        check_keys(d, {"service", "link", "source", "output", "scene", "record", "security", "grading", "corrections",
                       "validity"}, path)
        wv = f"{path}: [validity]"
        validity = validity_from_table(take(d, "validity", dict, {}, path), wv, config_dir(path), VALIDITY_KEYS)
        va = validity.service
        max_clock_ms = va["max_clock_disagreement_ms"]
        if not 0 < max_clock_ms <= 60000:
            raise ConfigError(f"{wv}.max_clock_disagreement_ms: {max_clock_ms} outside (0, 60000]")
        max_sigma_h = va["max_sigma_h_m"]
        max_sigma_yaw = va["max_sigma_yaw_deg"]
        if not max_sigma_h > 0 or not max_sigma_yaw > 0:
            raise ConfigError(f"{wv}: max_sigma_h_m and max_sigma_yaw_deg must be > 0")
        gr = take(d, "grading", dict, {}, path)
        check_keys(gr, {"enabled"}, f"{path}: [grading]")
        w = f"{path}: [service]"
        s = take(d, "service", dict, {}, path)
        check_keys(s, {"fleet", "master_id", "timeout_ms", "measurement_point_m", "known_vehicles",
                       "duration_s", "status_hz", "tick_hz", "dispatch", "realtime_priority"}, w)
        rt = take(s, "realtime_priority", int, 0, w)
        if not 0 <= rt <= 99:
            raise ConfigError(f"{w}.realtime_priority: {rt} outside 0..99")
        dispatch = take(s, "dispatch", str, "inline", w)
        check_choice(dispatch, ("inline", "asyncio"), f"{w}.dispatch", ConfigError)
        timeout = take(s, "timeout_ms", float, 200.0, w)
        if not 0 < timeout <= 60000:
            raise ConfigError(f"{w}.timeout_ms: {timeout} outside (0, 60000]")
        mp = take(s, "measurement_point_m", list, [0.0, 0.0, 0.0], w)
        if len(mp) != 3 or not all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in mp):
            raise ConfigError(f"{w}.measurement_point_m: expected 3 numbers, got {mp!r}")
        known = take(s, "known_vehicles", list, [], w)
        if not all(isinstance(x, str) for x in known):
            raise ConfigError(f"{w}.known_vehicles: expected a list of strings")
        outputs = output_from_table(take(d, "output", dict, {}, path), path)
        sc = take(d, "scene", dict, {}, path)
        check_keys(sc, {"geojson", "rate_hz"}, f"{path}: [scene]")
        scene_hz = take(sc, "rate_hz", float, 10.0, f"{path}: [scene]")
        if not 0 < scene_hz <= 100:
            raise ConfigError(f"{path}: [scene].rate_hz: {scene_hz} outside (0, 100]")
        rec = take(d, "record", dict, {}, path)
        wr = f"{path}: [record]"
        check_keys(rec, {"results_npz", "results_csv", "summary_json", "evaluate_uncompensated", "mcap", "mcap_max_mb"}, wr)
        sec = take(d, "security", dict, {}, path)
        ws = f"{path}: [security]"
        check_keys(sec, {"trust_list", "require_signature", "max_age_s", "future_tolerance_s", "replay_window"}, ws)
        mcap_mb = take(rec, "mcap_max_mb", float, 256.0, wr)
        if not mcap_mb > 0:
            raise ConfigError(f"{wr}.mcap_max_mb: must be > 0, got {mcap_mb}")
        window = take(sec, "replay_window", int, 1024, ws)
        if not 1 <= window <= 1 << 20:
            raise ConfigError(f"{ws}.replay_window: {window} outside 1..1048576")
        return cls(
            fleet=take(s, "fleet", str, "demo", w), master_id=take(s, "master_id", str, "ego", w),
            timeout_ms=timeout, measurement_point_m=tuple(float(x) for x in mp), known_vehicles=tuple(known),
            duration_s=take(s, "duration_s", float, None, w), status_hz=take(s, "status_hz", float, 2.0, w),
            tick_hz=take(s, "tick_hz", float, 10.0, w), dispatch=dispatch, realtime_priority=rt,
            link=link_from_table(take(d, "link", dict, {"mode": "router", "listen": ["tcp/127.0.0.1:7447"]}, path),
                                 f"{path}: [link]"),
            source=SourceConfig.from_table(take(d, "source", dict, {}, path), f"{path}: [source]"),
            **outputs,
            geojson=take(sc, "geojson", str, None, f"{path}: [scene]"), scene_hz=scene_hz,
            results_npz=take(rec, "results_npz", str, None, wr),
            results_csv=take(rec, "results_csv", str, None, wr), summary_json=take(rec, "summary_json", str, None, wr),
            evaluate_uncompensated=take(rec, "evaluate_uncompensated", bool, False, wr),
            mcap=take(rec, "mcap", str, None, wr), mcap_max_mb=mcap_mb,
            grading=take(gr, "enabled", bool, False, f"{path}: [grading]"),
            trust_list=take(sec, "trust_list", str, None, ws),
            require_signature=take(sec, "require_signature", bool, True, ws),
            max_age_s=take(sec, "max_age_s", float, 5.0, ws),
            future_tolerance_s=take(sec, "future_tolerance_s", float, 0.05, ws), replay_window=window,
            corrections=corrections_from_table(d, path), max_sigma_h_m=max_sigma_h, max_sigma_yaw_deg=max_sigma_yaw,
            require_consistency=va["require_consistency"], max_clock_disagreement_s=max_clock_ms / 1e3,
            filter_integrity=validity.filter_integrity, verification_out=validity.verification_out,
            path=path)._resolved()

    def _resolved(self) -> "MasterConfig":
        """Relative file paths made absolute against the config file's directory (``config_dir``), as
        the file's comments say; a config built in memory resolves against the working directory."""
        base = config_dir(self.path)
        for name in self.PATH_FIELDS:
            value = getattr(self, name)
            if value:
                setattr(self, name, str(base / Path(value).expanduser()))
        return self

    def enabled_outputs(self) -> list[tuple[str, dict]]:
        """(name, table) of every output to open, in this order: ``can``, ``udp``, ``zenoh``,
        ``results_csv`` when enabled (their settings are this config's fields), then the plug-ins."""
        builtin = (("can", self.can_enabled), ("udp", self.udp_enabled), ("zenoh", self.zenoh_enabled),
                   ("results_csv", bool(self.results_csv)))
        return [(name, {}) for name, on in builtin if on] + [
            (name, t) for name, t in self.output_plugins.items() if t.get("enabled", True)]

    def can_bus_kwargs(self) -> dict:
        """python-can ``Bus`` options of ``[output.can]`` (besides interface and channel)."""
        kw = {"receive_own_messages": self.can_receive_own_messages}
        if self.can_bitrate is not None:
            kw["bitrate"] = self.can_bitrate
        if self.can_fd:
            kw["fd"] = True
            if self.can_data_bitrate is not None:
                kw["data_bitrate"] = self.can_data_bitrate
        return kw


CAN_INTERFACES_HINT = ("socketcan", "virtual")
"""The interfaces this project runs and tests: SocketCAN on a vehicle, python-can's virtual bus in tests."""


def output_from_table(out: dict, path: str) -> dict:
    """The MasterConfig fields of the ``[output]`` table (``[output.can]``, ``[output.udp]``,
    ``[output.zenoh]``, and a table per plug-in output: ``master.outputs``), validated; ConfigError
    naming the file and key otherwise."""
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
    can_t = take(out, "can", dict, {}, f"{path}: [output]")
    udp_t = take(out, "udp", dict, {}, f"{path}: [output]")
    zen_t = take(out, "zenoh", dict, {}, f"{path}: [output]")
    check_keys(can_t, {"enabled", "interface", "channel", "rate_hz", "status_hz", "bitrate", "fd", "data_bitrate",
                       "receive_own_messages", "slots"}, wc)
    check_keys(udp_t, {"enabled", "host", "port", "status_hz"}, wu)
    check_keys(zen_t, {"enabled"}, wz)
    can_rate = take(can_t, "rate_hz", float, 25.0, wc)
    if not 0 <= can_rate <= 1000:
        raise ConfigError(f"{wc}.rate_hz: {can_rate} outside 0..1000 (0 = every result)")
    status_hz = take(can_t, "status_hz", float, 10.0, wc)
    if not 0 < status_hz <= 100:
        raise ConfigError(f"{wc}.status_hz: {status_hz} outside (0, 100]")
    interface = take(can_t, "interface", str, "virtual", wc)
    from can.interfaces import VALID_INTERFACES
    check_choice(interface, sorted(VALID_INTERFACES), f"{wc}.interface (python-can interfaces)", ConfigError)
    channel = take(can_t, "channel", str, "v2xpos", wc)
    if not channel:
        raise ConfigError(f"{wc}.channel: empty")
    bitrates = {}
    for key, lo, hi in (("bitrate", 10_000, 1_000_000), ("data_bitrate", 10_000, 16_000_000)):
        v = take(can_t, key, int, None, wc)
        if v is not None and not lo <= v <= hi:
            raise ConfigError(f"{wc}.{key}: {v} outside {lo}..{hi} bit/s")
        bitrates[key] = v
    fd = take(can_t, "fd", bool, False, wc)
    if bitrates["data_bitrate"] is not None and not fd:
        raise ConfigError(f"{wc}.data_bitrate: only with fd = true")
    from v2xpos.output.can_dbc import N_SLOTS
    slots = take(can_t, "slots", dict, {}, wc)
    seen: dict = {}
    for vid, slot in slots.items():
        if not re.fullmatch(r"[A-Za-z0-9_.\-]{1,32}", vid):
            raise ConfigError(f"{wc}.slots: {vid!r} is not a vehicle id (1-32 characters of [A-Za-z0-9_.-])")
        if not isinstance(slot, int) or isinstance(slot, bool) or not 0 <= slot < N_SLOTS:
            raise ConfigError(f"{wc}.slots.{vid}: {slot!r} is not a slot number 0..{N_SLOTS - 1}")
        if slot in seen:
            raise ConfigError(f"{wc}.slots: {seen[slot]!r} and {vid!r} both on slot {slot}")
        seen[slot] = vid
    host = take(udp_t, "host", str, "127.0.0.1", wu)
    from v2xpos.output.udp import check_destination
    try:
        check_destination(host)
    except ValueError as exc:
        raise ConfigError(f"{wu}.host: {exc}") from None
    port = take(udp_t, "port", int, 47001, wu)
    if not 0 < port < 65536:
        raise ConfigError(f"{wu}.port: {port} outside 1..65535")
    udp_status_hz = take(udp_t, "status_hz", float, 10.0, wu)
    if not 0 <= udp_status_hz <= 100:
        raise ConfigError(f"{wu}.status_hz: {udp_status_hz} outside 0..100 (0 = no heartbeat)")
    return dict(can_enabled=take(can_t, "enabled", bool, False, wc), can_interface=interface, can_channel=channel,
                can_rate_hz=can_rate, can_status_hz=status_hz, can_bitrate=bitrates["bitrate"], can_fd=fd,
                can_data_bitrate=bitrates["data_bitrate"],
                can_receive_own_messages=take(can_t, "receive_own_messages", bool, False, wc), can_slots=dict(slots),
                udp_enabled=take(udp_t, "enabled", bool, False, wu), udp_host=host, udp_port=port,
                udp_status_hz=udp_status_hz,
                zenoh_enabled=take(zen_t, "enabled", bool, True, wz), output_plugins=plugins)
