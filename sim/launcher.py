"""Start the simulated V2V demo as separate OS processes on loopback.

``write_configs`` turns a scenario into one master TOML and one TOML per slave, each with a
``[source] type = "sim"`` table (the simulator's plugin, ``sim.source``; every process rebuilds
the same truth from the shared scenario parameters) and the start handshake file; ``Fleet``
starts them with ``python -m v2xpos.cli master|slave --config FILE`` (each process prepares --
sensor simulation, filter JIT warm-up, zenoh session --, signals ready, then waits for the common
start stamp, the wall time of the scenario epoch, in the handshake file: ``sim.source.ScenarioClock``),
and stops them (SIGTERM, then SIGKILL after a grace period) -- only the processes it started.
The generic parts (ports, TOML writer, process handles) are ``v2xpos.launch``.
"""
from __future__ import annotations

import os
import time
from dataclasses import dataclass, field
from pathlib import Path

from sim.scenarios import Scenario
from v2xpos.launch import ServiceProcesses, to_toml

SIM_FACTORY = "sim.source:from_config"


SLAVE_NICE = 10
"""Slaves run at a lower CPU priority than the master: on one shared machine this stands in for
the separate computers they would have, so the master (the system under test) is not preempted
by simulated vehicles."""


MASTER_REALTIME_PRIORITY = 10
"""The demo asks for the master under SCHED_RR (``[service] realtime_priority``), as a test rig's
master computer would run it; where that is not permitted it runs at normal priority."""


@dataclass
class FleetPlan:
    """Where everything goes for one run."""
    out_dir: Path
    router_port: int
    udp_port: int
    source_type: str = "ins"
    fleet: str = "demo"
    configs: dict[str, Path] = field(default_factory=dict)
    start_file: Path | None = None
    results_npz: Path | None = None
    summary_json: Path | None = None
    geojson: Path | None = None


def write_configs(sc: Scenario, plan: FleetPlan, duration_s: float, can: bool = True, udp: bool = True,
                  publish_imu: bool = True) -> FleetPlan:
    """Master and slave TOML files for every actor of the scenario (in plan.out_dir/configs). The plan's
    directory and start file are made absolute first: the services resolve their config's paths
    against the config's directory."""
    import json
    plan.out_dir = Path(plan.out_dir).resolve()
    if plan.start_file is not None:
        plan.start_file = Path(plan.start_file).resolve()
    from sim.scenarios import scene_geojson
    cdir = plan.out_dir / "configs"
    cdir.mkdir(parents=True, exist_ok=True)
    endpoint = f"tcp/127.0.0.1:{plan.router_port}"
    src = {"type": "sim", "factory": SIM_FACTORY, "model": plan.source_type, "scenario": sc.name,
           "start_file": str(plan.start_file) if plan.start_file else None, "params": dict(sc.params)}
    plan.geojson = cdir / "scene.geojson"
    plan.geojson.write_text(json.dumps(scene_geojson(sc)))
    plan.results_npz = plan.out_dir / "master_results.npz"
    plan.summary_json = plan.out_dir / "master_summary.json"
    master = sc.master
    mp = [float(master.geometry.points_body_m[:, 0].max()), 0.0, 0.0]
    mcfg = {"service": {"fleet": plan.fleet, "master_id": sc.master_id, "timeout_ms": 200.0,
                        "measurement_point_m": mp, "known_vehicles": [a.actor_id for a in sc.slaves],
                        "duration_s": float(duration_s), "status_hz": 2.0, "tick_hz": 10.0,
                        "realtime_priority": MASTER_REALTIME_PRIORITY},
            "link": {"mode": "router", "listen": [endpoint]},
            "source": {**src, "actor": sc.master_id},
            "output": {"can": {"enabled": can, "interface": "virtual", "channel": f"v2xpos-{plan.router_port}"},
                       "udp": {"enabled": udp, "host": "127.0.0.1", "port": plan.udp_port},
                       "zenoh": {"enabled": True}},
            "scene": {"geojson": str(plan.geojson)},
            "grading": {"enabled": publish_imu},
            "record": {"results_npz": str(plan.results_npz), "summary_json": str(plan.summary_json),
                       "evaluate_uncompensated": True, "mcap": str(plan.out_dir / "session.mcap")}}
    path = cdir / "master.toml"
    path.write_text(to_toml(mcfg))
    plan.configs[sc.master_id] = path
    for a in sc.slaves:
        scfg = {"service": {"fleet": plan.fleet, "vehicle_id": a.actor_id, "rate_hz": 100.0,
                            "duration_s": float(duration_s), "publish_imu": publish_imu},
                "link": {"mode": "client", "connect": [endpoint], "connect_timeout_ms": 60000},
                "source": {**src, "actor": a.actor_id},
                "impairment": {"latency_ms": float(a.link.latency_ms), "jitter_ms": float(a.link.jitter_ms),
                               "spikes": [[sc.epoch_gps_s + t0, sc.epoch_gps_s + t1, float(extra)]
                                          for t0, t1, extra in a.link.spikes],
                               "seed": int(a.seed + 12345)}}
        path = cdir / f"slave_{a.actor_id}.toml"
        path.write_text(to_toml(scfg))
        plan.configs[a.actor_id] = path
    return plan


class Fleet(ServiceProcesses):
    """Processes of one run (master first, then slaves, slaves at a lower priority); logs in
    out_dir/logs."""

    def __init__(self, plan: FleetPlan, master_id: str, start_file: Path | None = None):
        super().__init__(plan.out_dir / "logs")
        self.plan = plan
        self.master_id = master_id
        self.start_file = Path(start_file) if start_file is not None else plan.start_file

    def start(self) -> None:
        order = [self.master_id] + [k for k in self.plan.configs if k != self.master_id]
        for vid in order:
            cmd = "master" if vid == self.master_id else "slave"
            super().start(vid, cmd, self.plan.configs[vid], nice=0 if vid == self.master_id else SLAVE_NICE)


def signal_ready_and_wait(start_file: str | Path, ready_id: str, timeout_s: float = 120.0,
                          stop=None) -> float | None:
    """Start handshake of a service process: create ``<start_file>.ready.<ready_id>``, then wait for
    ``start_file`` to hold the start stamp (Unix s) and return it (None on timeout or when the
    callable ``stop()`` returns True)."""
    start_file = Path(start_file)
    Path(f"{start_file}.ready.{ready_id}").write_text(str(os.getpid()))
    t_end = time.time() + timeout_s
    while time.time() < t_end and not (stop is not None and stop()):
        try:
            text = start_file.read_text().strip()
            if text:
                return float(text)
        except (FileNotFoundError, ValueError):
            pass
        time.sleep(0.02)
    return None


def release_when_ready(start_file: str | Path, ids: list[str], lead_s: float = 1.0,
                       timeout_s: float = 120.0, fleet: "Fleet | None" = None) -> float:
    """Wait until every id signalled ready (or timeout / a process died), then write the start
    stamp now + lead_s into start_file (atomically) and return it."""
    start_file = Path(start_file)
    t_end = time.time() + timeout_s
    while time.time() < t_end:
        if all(Path(f"{start_file}.ready.{i}").exists() for i in ids):
            break
        if fleet is not None and len(fleet.running()) < len(fleet.procs):
            break
        time.sleep(0.05)
    start = time.time() + lead_s
    tmp = start_file.with_suffix(".tmp")
    tmp.write_text(repr(start))
    tmp.replace(start_file)
    return start
