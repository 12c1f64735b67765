"""Output sinks of the master pipeline: each has ``write(result)`` and counts what it sent.

* ``CanSink`` -- ``v2xpos.output.can.CanOutput`` (DBC frames; python-can ``virtual`` or socketcan);
  scene results as LANE / OBJECT frames (``write_scene``); the master status frames
  (``write_master_status``, to be called at ``[output.can] status_hz``);
* ``UdpSink`` -- ``v2xpos.output.udp.UdpOutput``, one datagram per flush: the results of one message
  or of one dispatch batch, each record with its own time of validity (layout in docs/protocol.md)
  and one datagram of lane / object records per scene update;
* ``ZenohSink`` -- ``encode_relative`` republished on ``v2xpos/<fleet>/master/<id>/relative``.

``CanSink.from_config(cfg)`` / ``UdpSink.from_config(cfg)`` build them from a ``MasterConfig``
(``[output.can]`` / ``[output.udp]``); a bus that cannot be opened is a ``ConfigError`` naming the
file, interface and channel. ``master_status(nav, ...)`` makes the dict ``write_master_status`` takes.

Every output is registered by name (``output_kinds``): the built-in ones (``BUILTIN_OUTPUTS``: ``can``,
``udp``, ``zenoh``, ``results_csv``), those registered at run time and every entry point of the group
``v2xpos.outputs`` (``v2xpos.plugins``). A factory is ``factory(table, where, ctx: OutputContext) ->
sink``; a plug-in output is configured by its own ``[output.NAME]`` table (``enabled = false`` turns it
off; ``factory = "module:function"`` names a factory that is not registered) and its module may have
``check_table(table, where)``, called when the config loads. A sink has ``write(result)`` and
``close()``; ``flush()``, ``write_scene(...)`` when it has them (``master.pipeline``).
docs/extending.md adds one.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping

from v2xpos import plugins
from v2xpos.config import ConfigError
from v2xpos.link import Publisher
from v2xpos.wire import RelativeResult, encode_relative, relative_key

OUTPUT_GROUP = "v2xpos.outputs"
BUILTIN_OUTPUTS: dict[str, str] = {
    "can": "master.outputs:can_output",
    "udp": "master.outputs:udp_output",
    "zenoh": "master.outputs:zenoh_output",
    "results_csv": "master.outputs:results_csv_output",
}
PLUGIN_TABLE_KEYS = ("enabled", "factory")
"""Keys of an ``[output.NAME]`` table that the master reads itself; the rest is the factory's."""


@dataclass
class OutputContext:
    """What an output factory may use besides its table: the master's config and its link."""
    cfg: Any
    link: Any = None


def output_kinds() -> dict[str, str]:
    """Every known output name -> ``module:factory``."""
    return plugins.registered(OUTPUT_GROUP, BUILTIN_OUTPUTS)


def _output_ref(name: str, table: Mapping, where: str) -> str:
    ref = table.get("factory")
    if ref is not None:
        if not isinstance(ref, str) or ":" not in ref:
            raise ConfigError(f"{where}.factory: expected 'module:function', got {ref!r}")
        return ref
    kinds = output_kinds()
    if name not in kinds:
        from v2xpos.schema import check_choice
        check_choice(name, sorted(kinds), where, ConfigError)
    return kinds[name]


def check_output_table(name: str, table: Mapping, where: str) -> None:
    """Validate a plug-in's ``[output.NAME]`` table when the config loads: the name is registered (or
    the table names a factory) and the factory module's ``check_table(table, where)``, if any, passes."""
    ref = _output_ref(name, table, where)
    check = plugins.load(f"{ref.partition(':')[0]}:check_table", where, ConfigError, missing=None)
    if check is not None:
        check({k: v for k, v in table.items() if k not in PLUGIN_TABLE_KEYS}, where)


def make_output(name: str, table: Mapping, where: str, ctx: OutputContext):
    """The sink the output ``name`` (registered, or ``table["factory"]``) builds from ``table``."""
    factory = plugins.load(_output_ref(name, table, where), where, ConfigError)
    return factory({k: v for k, v in table.items() if k not in PLUGIN_TABLE_KEYS}, where, ctx)


def can_output(table: Mapping, where: str, ctx: OutputContext) -> "CanSink":
    """The built-in ``can`` output (``[output.can]``, read into the MasterConfig)."""
    return CanSink.from_config(ctx.cfg)


def udp_output(table: Mapping, where: str, ctx: OutputContext) -> "UdpSink":
    """The built-in ``udp`` output (``[output.udp]``)."""
    return UdpSink.from_config(ctx.cfg)


def zenoh_output(table: Mapping, where: str, ctx: OutputContext) -> "ZenohSink":
    """The built-in ``zenoh`` output: results republished on the master's relative key."""
    return ZenohSink(ctx.link.publisher(relative_key(ctx.cfg.service.fleet, ctx.cfg.service.master_id), express=False))


def results_csv_output(table: Mapping, where: str, ctx: OutputContext):
    """The built-in ``results_csv`` output (``[record] results_csv``)."""
    from v2xpos.output.results_csv import ResultsCsvWriter
    return ResultsCsvWriter(ctx.cfg.record.results_csv)


def summary_provenance(cfg: Any, seeds: Mapping[str, Any] | None = None) -> dict:
    """The ``"provenance"`` object of the master summary JSON (``v2xpos.provenance``): software,
    the master config file's hash (and its source's dataset / params when set), seeds, process start."""
    from v2xpos.provenance import provenance
    configs: dict = {"master": cfg.path}
    table = getattr(getattr(cfg, "source", None), "table", None) or {}
    dataset = table.get("dataset")
    if dataset:
        configs["source_dataset"] = dataset
    params = table.get("params")
    if params:
        configs["source_params"] = dict(params)
    if seeds is None and isinstance(params, Mapping) and "seed" in params:
        seeds = {"source": params["seed"]}
    return provenance("master", configs, seeds=seeds)


def master_status(nav: Any, t_gps_s: float | None = None, heading_valid: bool | None = None,
                  clock_synced: bool | None = None, clock_offset_s: float | None = None) -> dict:
    """The ``write_master_status`` dict of the master's latest filter state ``nav`` (NavState or
    StateMessage; None before the first state): time (``t_gps_s`` or the state's), fix, position sd
    (N, E, D), yaw sd and the filter's reason code; the heading and clock flags when the caller
    knows them (None = unknown)."""
    st: dict = {"heading_valid": heading_valid, "clock_synced": clock_synced, "clock_offset_s": clock_offset_s}
    if nav is None:
        st.update(t_gps_s=t_gps_s if t_gps_s is not None else 0.0, master_fix=None)
        return st
    st.update(t_gps_s=float(nav.t_s if t_gps_s is None else t_gps_s), master_fix=int(nav.fix),
              pos_sd_m=[float(x) for x in nav.pos_sd_m], yaw_sd_rad=float(nav.att_sd_rad[2]),
              reason=int(getattr(nav, "reason", 0)))
    return st


class CanSink:
    """Target results as CAN frames (slots: ``slots`` {id: slot} fixed, others first come first served).

    ``rate_hz``: at most this many updates per target per second (None = every result); a change of
    status is always sent at once. A target update with kinematics is 9 frames (docs/protocol.md §5):
    a 1 Mbit/s bus carries about 8,000 8-byte frames per second, i.e. 64 targets at 13 Hz or 16 at
    50 Hz; UDP and zenoh carry every result regardless.
    """

    def __init__(self, channel: str = "v2xpos", interface: str = "virtual", dbc_path: str | None = None,
                 rate_hz: float | None = None, slots: Mapping[str, int] | None = None, **bus_kwargs):
        from v2xpos.output.can import CanOutput
        self.out = CanOutput(channel=channel, interface=interface, dbc_path=dbc_path, slots=slots, **bus_kwargs)
        self.min_period_s = 0.0 if not rate_hz else 1.0 / rate_hz
        self._last: dict[str, tuple[float, int]] = {}
        self.skipped = 0
        self.status_frames = 0

    @classmethod
    def from_config(cls, cfg: Any) -> "CanSink":
        """CanSink of ``cfg``'s ``[output.can]``; ConfigError (one line) when the bus cannot be opened."""
        from v2xpos.output.can import CanBusError
        try:
            can = cfg.output.can
            return cls(channel=can.channel, interface=can.interface, rate_hz=can.rate_hz or None, slots=can.slots,
                       **can.bus_kwargs())
        except CanBusError as exc:
            raise ConfigError(f"{cfg.path}: [output.can]: {exc}") from None

    @property
    def frames(self) -> int:
        return self.out.frames_sent

    def write(self, result: RelativeResult) -> None:
        if self.min_period_s > 0.0:
            last = self._last.get(result.target_id)
            if (last is not None and last[1] == int(result.status)
                    and result.t_gps_s - last[0] < self.min_period_s - 1e-4):
                self.skipped += 1
                return
            self._last[result.target_id] = (result.t_gps_s, int(result.status))
        self.out.send_result(result)

    def write_scene(self, scene_result, t_gps_s: float, seq: int) -> None:
        """LANE / OBJECT frames numbered as in docs/protocol.md §5 (``CanOutput.send_scene``)."""
        self.out.send_scene(scene_result)

    def write_master_status(self, status: Mapping[str, Any]) -> None:
        """MASTER_STATUS + MASTER_SIGMA frames (``CanOutput.send_master_status``; keys ``t_gps_s``,
        ``master_fix``, ``heading_valid``, ``pos_sd_m``, ``yaw_sd_rad``, ``clock_synced``,
        ``clock_offset_s``; ``master_status(nav, ...)`` makes it). Call at ``[output.can] status_hz``."""
        self.status_frames += self.out.send_master_status(status)

    def close(self) -> None:
        self.out.close()


class UdpSink:
    """UDP datagrams to a configured unicast host: ``write`` queues a result, ``flush`` sends the
    queued results as one datagram (the pipeline flushes after every message, or once per dispatch
    batch); every record carries its own time of validity and sequence number, the header the last
    result's. Scene updates go out at once."""

    def __init__(self, host: str = "127.0.0.1", port: int = 47001):
        from v2xpos.output.udp import MAX_DATAGRAM_BYTES, TARGET, UdpOutput
        self.out = UdpOutput(host=host, port=port)
        self.max_targets = (MAX_DATAGRAM_BYTES - 64) // TARGET.size
        self._queued: list[RelativeResult] = []

    @classmethod
    def from_config(cls, cfg: Any) -> "UdpSink":
        """UdpSink of ``cfg``'s ``[output.udp]``; ConfigError when the destination is refused."""
        try:
            return cls(cfg.output.udp.host, cfg.output.udp.port)
        except (ValueError, OSError) as exc:
            raise ConfigError(f"{cfg.path}: [output.udp]: {exc}") from None

    @property
    def datagrams(self) -> int:
        return self.out.datagrams_sent

    def write(self, result: RelativeResult) -> None:
        self._queued.append(result)
        if len(self._queued) >= self.max_targets:
            self.flush()

    def flush(self) -> None:
        """Send the queued results (if any) as one datagram."""
        q = self._queued
        if q:
            self.out.send(q, q[-1].seq, q[-1].t_gps_s)
            q.clear()

    def write_heartbeat(self, seq: int, t_gps_s: float) -> None:
        """The master's heartbeat datagram (``v2xpos.output.udp.heartbeat``), after the queued results."""
        self.flush()
        self.out.send_heartbeat(seq, t_gps_s)

    def write_scene(self, scene_result, t_gps_s: float, seq: int) -> None:
        """One datagram with no targets and the lane / object records."""
        from v2xpos.output.udp import records_from_scene
        lanes, objects = records_from_scene(scene_result)
        self.out.send([], seq, t_gps_s, lanes, objects)

    def close(self) -> None:
        self.flush()
        self.out.close()


class ZenohSink:
    """Republish results for monitors (msgpack envelope, ``v2xpos.wire.encode_relative``)."""

    def __init__(self, publisher: Publisher, sign=None):
        self.pub = publisher
        self.sign = sign

    @property
    def sent(self) -> int:
        return self.pub.sent

    def write(self, result: RelativeResult) -> None:
        self.pub.put(encode_relative(result, self.sign))

    def close(self) -> None:
        pass
