"""``v2xpos slave --config FILE``: a target vehicle (or pedestrian) that runs its navigation filter
in real time and publishes its state on zenoh.

Loop (single thread, paced by the wall clock): the scenario GPS time is
``t_gps = epoch + (time.time() - start_unix_s)``; the source consumes every sensor sample up to
t_gps; every ``1/rate_hz`` of filter time a StateMessage is queued for sending at
``validity wall time + injected delay`` (FIFO, see ``sim.scenarios.LinkImpairment``); due messages
are stamped with ``t_sent_wall_s`` (the publish instant, so end-to-end latency excludes the injected
delay), optionally signed, and published on ``v2xpos/<fleet>/vehicle/<id>/state`` with
CongestionControl.BLOCK. With ``publish_imu`` the raw samples of every IMU unit on board go to
``v2xpos/<fleet>/vehicle/<id>/imu`` every 0.25 s for the master's IMU grading.

Stops at epoch + duration_s or on SIGTERM/SIGINT, closes the zenoh session, prints one JSON line
with its counters.
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

import msgpack
import numpy as np

from sim.scenarios import LinkImpairment, build
from slave.config import ConfigError, SlaveConfig
from slave.source import make_source
from v2xpos.link import Link
from v2xpos.wire import StateMessage, encode_state, imu_key, state_key

WARMUP_S = 1.0
"""The filter starts this long before the scenario epoch (the states are published from then on)."""
IMU_PERIOD_S = 0.25
"""IMU grading messages carry the samples of the last 0.25 s of every unit (full 100 Hz)."""


class _Stop:
    def __init__(self) -> None:
        self.flag = False

    def __call__(self, *_: object) -> None:
        self.flag = True


def run_slave(cfg: SlaveConfig, start_unix_s: float | None = None, stop: _Stop | None = None,
              start_file: str | None = None) -> dict:
    """Run until the configured duration ends or ``stop.flag``; returns the counters."""
    stop = stop or _Stop()
    start = float(cfg.source.start_unix_s if start_unix_s is None else start_unix_s)
    if start <= 0:
        start = time.time() + WARMUP_S
    try:
        sc = build(cfg.source.scenario, **cfg.source.params)
    except ValueError as exc:  # unknown scenario or parameter (did you mean)
        raise ConfigError(f"{cfg.path}: [source.params]: {exc}") from None
    actor_id = cfg.source.actor or cfg.vehicle_id
    if cfg.source.type == "dataset":
        from sim.scenarios import Actor
        from v2xpos.wire import Geometry
        try:
            source = make_source("dataset", sc, None, cfg.source.dataset, cfg.source.align_to_epoch)
        except (OSError, ValueError) as exc:
            raise ConfigError(f"{cfg.path}: [source].dataset: {exc}") from None
        actor = Actor(cfg.vehicle_id, source.kind, "slave", sc.master.truth,
                      Geometry.box(3.8, 1.0, 0.9) if source.kind == "vehicle" else Geometry(kind="circle", radius_m=0.3),
                      imu_units=1)
    else:
        if actor_id not in sc.actors:
            raise ConfigError(f"{cfg.path}: [source].actor {actor_id!r} not in scenario actors {sorted(sc.actors)}")
        actor = sc.actors[actor_id]
        source = make_source(cfg.source.type, sc, actor)
    imp = actor.link
    if cfg.latency_ms is not None or cfg.jitter_ms is not None:
        imp = LinkImpairment(cfg.latency_ms if cfg.latency_ms is not None else imp.latency_ms,
                             cfg.jitter_ms if cfg.jitter_ms is not None else imp.jitter_ms, list(imp.spikes))
    delay_rng = np.random.default_rng(actor.seed + 12345)
    signer = None
    if cfg.key_file:
        from v2xpos.security import MessageSigner
        try:
            signer = MessageSigner.from_file(cfg.key_file)
        except (OSError, ValueError) as exc:
            raise ConfigError(f"{cfg.path}: [security].key_file: {exc}") from None

    epoch = sc.epoch_gps_s
    end_gps = epoch + cfg.duration_s if cfg.duration_s is not None else math.inf
    gps_of = (lambda wall: epoch + (wall - start))
    wall_of = (lambda t: start + (t - epoch))
    source.warm_up()
    if cfg.source.type != "dataset":
        source.advance(sc.epoch_gps_s - WARMUP_S - 0.5)   # driving history before the run: filter converged
    link = Link(cfg.link)
    pub = link.publisher(state_key(cfg.fleet, cfg.vehicle_id))
    grading = cfg.publish_imu and actor.imu_units >= 2      # grading compares units: needs two or more
    imu_pub = link.publisher(imu_key(cfg.fleet, cfg.vehicle_id), express=False) if grading else None
    if start_file is not None:
        from sim.launcher import signal_ready_and_wait
        got = signal_ready_and_wait(start_file, cfg.vehicle_id, stop=stop)
        if got is None:
            link.close()
            raise ConfigError(f"no start stamp in {start_file} (timeout or stopped)")
        start = got
    queue: deque = deque()
    seq = 0
    last_send_wall = 0.0
    pub_period = 1.0 / cfg.rate_hz
    next_pub_t = -math.inf
    units, mounting, unit_idx = {}, {}, {}
    if imu_pub is not None:
        from slave.source import imu_units
        sen = getattr(source, "sensors", None)
        units, mounting = imu_units(sc, actor, sen.imu if sen is not None else None)
        unit_idx = {u: int(np.searchsorted(imu.t_s, epoch - WARMUP_S)) for u, imu in units.items()}
    next_imu_pub_t = -math.inf
    counters = {"vehicle_id": cfg.vehicle_id, "source": source.name, "states": 0, "queued": 0, "sent": 0,
                "imu_msgs": 0, "late_ms_max": 0.0}
    try:
        while not stop.flag:
            now = time.time()
            t_gps = gps_of(now)
            if t_gps < epoch - WARMUP_S:
                time.sleep(min(0.05, wall_of(epoch - WARMUP_S) - now))
                continue
            if t_gps > end_gps and not queue:
                break
            if t_gps <= end_gps:
                for nav in source.advance(t_gps):
                    counters["states"] += 1
                    if nav.t_s + 1e-6 < next_pub_t:
                        continue
                    behind = not math.isfinite(next_pub_t) or nav.t_s - next_pub_t > pub_period
                    next_pub_t = nav.t_s + pub_period if behind else next_pub_t + pub_period
                    seq += 1
                    msg = StateMessage.from_nav_state(nav, cfg.fleet, cfg.vehicle_id, seq,
                                                      geometry=actor.geometry, kind=actor.kind)
                    delay = float(imp.delays_s(np.array([nav.t_s - epoch]), delay_rng)[0])
                    send_at = max(last_send_wall, wall_of(nav.t_s) + delay)
                    last_send_wall = send_at
                    queue.append((send_at, msg))
                    counters["queued"] += 1
            now = time.time()
            while queue and queue[0][0] <= now:
                send_at, msg = queue.popleft()
                msg.t_sent_wall_s = time.time()
                pub.put(encode_state(msg, signer))
                counters["sent"] += 1
                counters["late_ms_max"] = max(counters["late_ms_max"], (msg.t_sent_wall_s - send_at) * 1e3)
            if imu_pub is not None and t_gps >= next_imu_pub_t and t_gps <= end_gps:
                next_imu_pub_t = t_gps + IMU_PERIOD_S
                imu_pub.put(_imu_payload(cfg, units, mounting, unit_idx, t_gps))
                counters["imu_msgs"] += 1
            now = time.time()
            t_next = wall_of((math.floor(gps_of(now) * 100.0) + 1) / 100.0)
            if queue:
                t_next = min(t_next, queue[0][0])
            dt = t_next - time.time()
            if dt > 0:
                time.sleep(dt)
    finally:
        link.close()
    return counters


def _imu_payload(cfg: SlaveConfig, units: dict, mounting: dict, idx: dict, t_gps_s: float) -> bytes:
    """Grading message with every unit's samples since the last one (layout in master/grading.py and
    docs/protocol.md): msgpack map {T, ver, fleet, id, rate_hz, mounting_xyz_deg, units: {unit: rows}},
    rows [t_gps_s, ax, ay, az, gx, gy, gz] (m/s^2, rad/s, unit axes)."""
    out = {}
    for uid, imu in units.items():
        i0 = idx[uid]
        i1 = int(np.searchsorted(imu.t_s, t_gps_s, side="right"))
        idx[uid] = i1
        out[uid] = np.column_stack([imu.t_s[i0:i1], imu.acc_mps2[i0:i1], imu.gyro_rps[i0:i1]]).tolist()
    return msgpack.packb({"T": "imu", "ver": 1, "fleet": cfg.fleet, "id": cfg.vehicle_id, "rate_hz": 100.0,
                          "mounting_xyz_deg": mounting, "units": out}, use_bin_type=True)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", required=True, help="slave TOML file (see configs/slave_*.toml)")
    parser.add_argument("--start", type=float, default=None,
                        help="wall time (Unix s) of the scenario epoch, shared by all processes")
    parser.add_argument("--start-file", default=None,
                        help="start handshake: signal <file>.ready.<id>, then read the start stamp from <file>")
    parser.add_argument("--summary", default=None, help="write the final counters to this JSON file")


def run(args: argparse.Namespace) -> int:
    try:
        cfg = SlaveConfig.load(args.config)
    except ConfigError as exc:
        print(f"v2xpos slave: {exc}", file=sys.stderr)
        return 2
    stop = _Stop()
    signal.signal(signal.SIGTERM, stop)
    signal.signal(signal.SIGINT, stop)
    try:
        counters = run_slave(cfg, args.start, stop, args.start_file)
    except ConfigError as exc:
        print(f"v2xpos slave: {exc}", file=sys.stderr)
        return 2
    line = json.dumps(counters)
    print(line, flush=True)
    if args.summary:
        Path(args.summary).write_text(line + "\n")
    return 0
