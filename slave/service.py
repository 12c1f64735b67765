"""``v2xpos slave --config FILE``: a target vehicle (or pedestrian) that runs its navigation filter
in real time and publishes its state on zenoh.

Phases (each stops within about half a second on SIGINT/SIGTERM):

1. build the source named by ``[source]`` (``v2xpos.sources.make_source``: a recording, live
   devices, or the simulator's plugin) and warm it up (JIT, loading);
2. open the zenoh link (a client whose router is not up says so and retries);
3. start the session clock (``source.make_clock``): a recording follows the master's session
   clock, live devices run on GPS time from the host clock, the simulator on its scenario clock;
4. loop paced by that clock, and woken by the source's input (a device record: its state leaves
   at once, not at the next tick): the source consumes every sensor sample up to the session time;
   every ``1/rate_hz`` of filter time a StateMessage is queued for sending at
   ``clock.wall_of(time of validity) + injected delay`` (``[impairment]``, FIFO; none on a
   vehicle); due messages are stamped with ``t_sent_wall_s``, flagged when the clock is not
   synchronised to GNSS time, optionally signed, and published on
   ``v2xpos/<fleet>/vehicle/<id>/state`` (CongestionControl.BLOCK). With ``publish_imu`` and a
   source with several IMU units, their raw samples go to ``v2xpos/<fleet>/vehicle/<id>/imu`` every
   0.25 s for the master's IMU grading.

Every second it publishes its live status (``v2xpos.sources.status``: clock, device streams and
their rates, IMU clock drift, corrections, filter state and reason) on
``v2xpos/<fleet>/vehicle/<id>/status``, and every 5 s prints it as one line on stderr (``--quiet``:
not). Each published state carries the slave's session GPS time at publishing (``t_sent_gps_s``),
from which the master compares the two clocks.

Stops at clock start + ``duration_s``, when the source has nothing more (end of a recording), or on
SIGTERM/SIGINT; closes the link and prints one JSON line with its counters. Exit code 0 when it
ran to its end, 130 when a signal stopped it (README, exit codes).
"""
from __future__ import annotations

import argparse
import json
import math
import signal
import sys
import time
from collections import deque
from pathlib import Path

import numpy as np

from slave.config import ConfigError, SlaveConfig
from v2xpos.config import config_dir
from v2xpos.launch import apply_realtime_priority, freeze_setup_heap
from v2xpos.link import Link, LinkUnavailable
from v2xpos.sources import SourceContext, SourceError, Stopped, make_source, run_until_stopped
from v2xpos.wire import StateMessage, encode_imu_payload, encode_state, imu_key, state_key, vehicle_status_key, alive_key

EXIT_INTERRUPTED = 130
"""Exit code of a service stopped by a signal (README: exit codes)."""
IMU_PERIOD_S = 0.25
"""IMU grading messages carry the samples of the last 0.25 s of every unit (full rate)."""
TICK_S = 0.01
"""The loop wakes every 10 ms of session time, at every due message, and when the source has new
input (``VehicleSource.wait_for_input``: a device record)."""
AGE_HISTORY = 10_000
"""Messages whose age when sent (session time at sending - time of validity) the final counters
summarise (``state_age_at_send_ms``: median and 95th percentile)."""


class _Stop:
    def __init__(self) -> None:
        self.flag = False

    def __call__(self, *_: object) -> None:
        self.flag = True


def _say(vehicle_id: str):
    return lambda text: print(f"slave {vehicle_id}: {text}", file=sys.stderr, flush=True)


def run_slave(cfg: SlaveConfig, stop: _Stop | None = None, quiet: bool = False) -> dict:
    """Run until the configured duration ends, the source ends, or ``stop.flag``; returns the counters."""
    stop = stop or _Stop()
    stopped = lambda: stop.flag  # noqa: E731
    say = _say(cfg.service.vehicle_id)
    realtime = apply_realtime_priority(cfg.service.realtime_priority, f"slave {cfg.service.vehicle_id}")
    ctx = SourceContext(vehicle_id=cfg.service.vehicle_id, fleet=cfg.service.fleet, role="slave",
                        config_dir=config_dir(cfg.path), stop=stopped, filter_overrides={"integrity": dict(cfg.validity.filter_integrity)})
    try:
        source = run_until_stopped(make_source, stopped, cfg.source.table, f"{cfg.path}: [source]", ctx)
    except SourceError as exc:
        raise ConfigError(str(exc)) from None
    except Stopped:
        return {"vehicle_id": cfg.service.vehicle_id, "phase": "source", "stopped_early": True}
    signer = None
    if cfg.security.key_file:
        from v2xpos.security import MessageSigner
        try:
            signer = MessageSigner.from_file(cfg.security.key_file)
        except (OSError, ValueError) as exc:
            raise ConfigError(f"{cfg.path}: [security].key_file: {exc}") from None
    counters = {"vehicle_id": cfg.service.vehicle_id, "source": source.name, "states": 0, "queued": 0, "sent": 0,
                "imu_msgs": 0, "late_ms_max": 0.0, "phase": "warm_up",
                "realtime_priority": cfg.service.realtime_priority if realtime else 0}
    link = clock = sink = None
    try:
        run_until_stopped(source.warm_up, stopped)
        counters["phase"] = "link"
        try:
            link = Link.open_when_available(cfg.link, stop=stopped, say=say)
        except LinkUnavailable as exc:
            raise ConfigError(f"{cfg.path}: [link]: {exc}") from None
        if link is None:
            return counters
        ctx.link = link
        if cfg.corrections is not None and cfg.corrections.receive:
            from v2xpos.sources.corrections import CorrectionSink
            sink = CorrectionSink(link, cfg.service.fleet, source.write_corrections)
        clock = source.make_clock(ctx)
        counters["phase"] = "clock"
        try:
            if not run_until_stopped(clock.start, stopped, stopped):
                return counters
        except TimeoutError as exc:
            raise ConfigError(f"{cfg.path}: [source]: {exc}") from None
        counters["phase"] = "run"
        freeze_setup_heap(young_collections=False)
        _loop(cfg, source, clock, link, signer, stop, counters, quiet, sink)
        counters["phase"] = "done"
    except Stopped:
        counters["stopped_early"] = True
    finally:
        if sink is not None:
            counters["corrections"] = sink.stats()
            sink.close()
        counters["source_status"] = source.status()
        if cfg.validity.verification_out is not None and counters.get("phase") in ("run", "done"):
            from v2xpos.datasets.verification import write_session_record
            counters["verification"], said = write_session_record(source, cfg.validity.verification_out,
                                                                  f"session of {cfg.service.vehicle_id}")
            say(said)
        if clock is not None:
            counters["clock"] = clock.status()
            clock.close()
        source.close()
        if link is not None:
            link.close()
    return counters


def _loop(cfg: SlaveConfig, source, clock, link: Link, signer, stop: _Stop, counters: dict,
          quiet: bool = False, corrections=None) -> None:
    pub = link.publisher(state_key(cfg.service.fleet, cfg.service.vehicle_id))
    live = _LiveStatus(cfg, link, quiet, corrections)
    units = source.imu_units() if cfg.service.publish_imu else None
    imu_pub = link.publisher(imu_key(cfg.service.fleet, cfg.service.vehicle_id), express=False) if units else None
    imp = cfg.impairment
    delay_rng = np.random.default_rng(imp.seed)
    t_start = clock.now_gps_s()
    end_gps = clock.session_start_gps_s() + cfg.service.duration_s if cfg.service.duration_s is not None else math.inf
    source.prime(t_start)
    queue: deque = deque()
    seq = 0
    last_send_wall = 0.0
    pub_period = 1.0 / cfg.service.rate_hz
    next_pub_t = -math.inf
    unit_idx = {}
    if units:
        unit_imu, mounting = units
        unit_idx = {u: int(np.searchsorted(imu.t_s, t_start)) for u, imu in unit_imu.items()}
    next_imu_pub_t = -math.inf
    age_at_send_s: deque = deque(maxlen=AGE_HISTORY)
    while not stop.flag:
        t_gps = clock.now_gps_s()
        done = t_gps > end_gps or source.finished(t_gps)
        if done and not queue:
            break
        if not done:
            time_ok = clock.synchronised()
            nav_states = source.advance(min(t_gps, end_gps))
            for nav in nav_states:
                counters["states"] += 1
                if nav.t_s + 1e-6 < next_pub_t:
                    continue
                behind = not math.isfinite(next_pub_t) or nav.t_s - next_pub_t > pub_period
                next_pub_t = nav.t_s + pub_period if behind else next_pub_t + pub_period
                seq += 1
                msg = StateMessage.from_nav_state(nav, cfg.service.fleet, cfg.service.vehicle_id, seq,
                                                  geometry=source.geometry, kind=source.kind, time_ok=time_ok)
                delay = float(imp.delays_s(np.array([nav.t_s]), delay_rng)[0]) if imp.active else 0.0
                send_at = max(last_send_wall, clock.wall_of(nav.t_s) + delay)
                last_send_wall = send_at
                queue.append((send_at, msg))
                counters["queued"] += 1
            if nav_states:
                live.nav = nav_states[-1]
        now = time.time()
        while queue and queue[0][0] <= now:
            send_at, msg = queue.popleft()
            msg.t_sent_wall_s = time.time()
            msg.t_sent_gps_s = clock.now_gps_s()
            pub.put(encode_state(msg, signer))
            counters["sent"] += 1
            counters["late_ms_max"] = max(counters["late_ms_max"], (msg.t_sent_wall_s - send_at) * 1e3)
            age_at_send_s.append(msg.t_sent_gps_s - msg.t_gps_s)
        live.tick(now, source, clock, counters)
        if imu_pub is not None and not done and t_gps >= next_imu_pub_t:
            next_imu_pub_t = t_gps + IMU_PERIOD_S
            imu_pub.put(_imu_payload(cfg, unit_imu, mounting, unit_idx, t_gps))
            counters["imu_msgs"] += 1
        t_next = clock.wall_of((math.floor(clock.now_gps_s() / TICK_S) + 1) * TICK_S)
        if queue:
            t_next = min(t_next, queue[0][0])
        source.wait_for_input(min(t_next - time.time(), 0.25))
    ages_ms = np.asarray(age_at_send_s, float) * 1e3
    counters["state_age_at_send_ms"] = ({"p50": float(np.median(ages_ms)), "p95": float(np.percentile(ages_ms, 95)),
                                         "n": len(ages_ms)} if len(ages_ms) else None)


class _LiveStatus:
    """The slave's status at 1 Hz on zenoh and as a line every few seconds on stderr."""

    def __init__(self, cfg: SlaveConfig, link: Link, quiet: bool, corrections=None):
        from v2xpos.sources.status import STATUS_LINE_PERIOD_S, STATUS_PERIOD_S, VehicleStatus
        self.builder = VehicleStatus("slave", cfg.service.vehicle_id, cfg.service.fleet)
        self.pub = link.publisher(vehicle_status_key(cfg.service.fleet, cfg.service.vehicle_id), express=False)
        link.declare_alive(alive_key(cfg.service.fleet, "vehicle", cfg.service.vehicle_id))
        self.quiet = quiet
        self.period_s, self.line_period_s = STATUS_PERIOD_S, STATUS_LINE_PERIOD_S
        self.next_pub = self.next_line = 0.0
        self.nav = None
        self.corrections = corrections       # the CorrectionSink writing RTCM into the receiver, if any

    def tick(self, t_wall_s: float, source, clock, counters: dict) -> None:
        if t_wall_s < self.next_pub:
            return
        from v2xpos.sources.status import status_line
        self.next_pub = t_wall_s + self.period_s
        extra = {"sent": counters["sent"]}
        if self.corrections is not None:
            extra["corrections"] = self.corrections.stats()
        doc = self.builder.snapshot(source, clock, self.nav, extra, t_wall_s)
        self.pub.put(json.dumps(doc).encode())
        if not self.quiet and t_wall_s >= self.next_line:
            self.next_line = t_wall_s + self.line_period_s
            print(status_line(doc), file=sys.stderr, flush=True)


def _imu_payload(cfg: SlaveConfig, units: dict, mounting: dict, idx: dict, t_gps_s: float) -> bytes:
    """IMU-stream message (``v2xpos.wire.encode_imu_payload``) with every unit's samples since the
    last one (``idx``: each unit's first sample not yet sent, advanced here)."""
    since_last = {}
    for uid, imu in units.items():
        i0 = idx[uid]
        i1 = idx[uid] = int(np.searchsorted(imu.t_s, t_gps_s, side="right"))
        since_last[uid] = (imu.t_s[i0:i1], imu.acc_mps2[i0:i1], imu.gyro_rps[i0:i1])
    return encode_imu_payload(cfg.service.fleet, cfg.service.vehicle_id, since_last, mounting, rate_hz=100.0)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", required=True, help="slave TOML file (see configs/slave_*.toml)")
    parser.add_argument("--summary", default=None, help="write the final counters to this JSON file")
    parser.add_argument("--quiet", action="store_true", help="no one-line status every 5 s on stderr")


def run(args: argparse.Namespace) -> int:
    stop = _Stop()
    signal.signal(signal.SIGTERM, stop)
    signal.signal(signal.SIGINT, stop)
    try:
        cfg = SlaveConfig.load(args.config)
    except ConfigError as exc:
        print(f"v2xpos slave: {exc}", file=sys.stderr)
        return 2
    signal.signal(signal.SIGTERM, stop)
    signal.signal(signal.SIGINT, stop)
    try:
        counters = run_slave(cfg, stop, quiet=args.quiet)
    except ConfigError as exc:
        print(f"v2xpos slave: {exc}", file=sys.stderr)
        return 2
    finally:
        signal.signal(signal.SIGTERM, signal.SIG_IGN)   # asked again while finishing: finish anyway
        signal.signal(signal.SIGINT, signal.SIG_IGN)
    line = json.dumps(counters)
    print(line, flush=True)
    if args.summary:
        Path(args.summary).write_text(line + "\n")
    return EXIT_INTERRUPTED if stop.flag else 0
