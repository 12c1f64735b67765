"""Start the V2V services as separate OS processes on loopback: config files, ports, process handles.

``write_configs`` turns a scenario into one master TOML and one TOML per slave (all sharing the
scenario parameters, so every process rebuilds the same truth); ``Fleet`` starts them with
``python -m v2xpos.cli ...`` and a start handshake (each process prepares -- sensor simulation,
filter JIT warm-up, zenoh session -- signals ready, then waits for the common start stamp, the
wall time of the scenario epoch, in ``--start-file``), and stops them (SIGTERM, then SIGKILL after a grace period) -- only the processes it started.
"""
from __future__ import annotations

import math
import os
import signal
import socket
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

from sim.scenarios import Scenario


SLAVE_NICE = 10
"""Slaves run at a lower CPU priority than the master: on one shared machine this stands in for
the separate computers they would have, so the master (the system under test) is not preempted
by simulated vehicles."""


MASTER_REALTIME_PRIORITY = 10
"""The demo asks for the master under SCHED_RR (``[service] realtime_priority``), as a test rig's
master computer would run it; where that is not permitted it runs at normal priority."""


def free_tcp_port() -> int:
    """A TCP port on 127.0.0.1 that is free now (asked from the OS)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float)):
        if isinstance(v, float) and not math.isfinite(v):
            raise ValueError(f"cannot write non-finite number {v} to TOML")
        return repr(v)
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    raise TypeError(f"cannot write {type(v).__name__} to TOML")


def to_toml(d: dict, prefix: str = "") -> str:
    """Minimal TOML writer for nested dicts of scalars/lists (what the service configs use)."""
    scalars = [(k, v) for k, v in d.items() if not isinstance(v, dict) and v is not None]
    tables = [(k, v) for k, v in d.items() if isinstance(v, dict)]
    out = []
    if prefix and scalars:
        out.append(f"[{prefix}]")
    out += [f"{k} = {_toml_value(v)}" for k, v in scalars]
    for k, v in tables:
        sub = to_toml(v, f"{prefix}.{k}" if prefix else k)
        if sub:
            out.append(sub)
    return "\n".join(out) + ("\n" if out else "")


@dataclass
class FleetPlan:
    """Where everything goes for one run."""
    out_dir: Path
    router_port: int
    udp_port: int
    source_type: str = "ins"
    fleet: str = "demo"
    configs: dict[str, Path] = field(default_factory=dict)
    results_npz: Path | None = None
    summary_json: Path | None = None
    geojson: Path | None = None


def write_configs(sc: Scenario, plan: FleetPlan, duration_s: float, can: bool = True, udp: bool = True,
                  publish_imu: bool = True) -> FleetPlan:
    """Master and slave TOML files for every actor of the scenario (in plan.out_dir/configs)."""
    import json
    from sim.scenarios import scene_geojson
    cdir = plan.out_dir / "configs"
    cdir.mkdir(parents=True, exist_ok=True)
    endpoint = f"tcp/127.0.0.1:{plan.router_port}"
    src = {"type": plan.source_type, "scenario": sc.name, "params": dict(sc.params)}
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
                "source": {**src, "actor": a.actor_id}}
        path = cdir / f"slave_{a.actor_id}.toml"
        path.write_text(to_toml(scfg))
        plan.configs[a.actor_id] = path
    return plan


class Fleet:
    """Processes of one run (master first, then slaves); logs in out_dir/logs."""

    def __init__(self, plan: FleetPlan, master_id: str, start_file: Path):
        self.plan = plan
        self.master_id = master_id
        self.start_file = Path(start_file)
        self.procs: dict[str, subprocess.Popen] = {}
        self._logs: list = []

    def start(self) -> None:
        logdir = self.plan.out_dir / "logs"
        logdir.mkdir(parents=True, exist_ok=True)
        env = dict(os.environ)
        env.setdefault("PYTHONUNBUFFERED", "1")
        root = str(Path(__file__).resolve().parents[1])
        env["PYTHONPATH"] = root + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
        order = [self.master_id] + [k for k in self.plan.configs if k != self.master_id]
        for vid in order:
            cmd = "master" if vid == self.master_id else "slave"
            log = open(logdir / f"{vid}.log", "w")
            self._logs.append(log)
            nice = 0 if vid == self.master_id else SLAVE_NICE
            self.procs[vid] = subprocess.Popen(
                [sys.executable, "-m", "v2xpos.cli", cmd, "--config", str(self.plan.configs[vid]),
                 "--start-file", str(self.start_file)], stdout=log, stderr=subprocess.STDOUT, env=env, cwd=root,
                preexec_fn=(lambda n=nice: os.nice(n)) if nice else None)

    def running(self) -> list[str]:
        return [k for k, p in self.procs.items() if p.poll() is None]

    def wait(self, deadline_unix_s: float) -> dict[str, int | None]:
        while self.running() and time.time() < deadline_unix_s:
            time.sleep(0.1)
        return self.stop()

    def stop(self, grace_s: float = 5.0) -> dict[str, int | None]:
        """SIGTERM every process still running, SIGKILL after grace_s; returns exit codes."""
        for p in self.procs.values():
            if p.poll() is None:
                p.send_signal(signal.SIGTERM)
        t_end = time.time() + grace_s
        for p in self.procs.values():
            try:
                p.wait(timeout=max(0.1, t_end - time.time()))
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
        for log in self._logs:
            log.close()
        return {k: p.returncode for k, p in self.procs.items()}


def signal_ready_and_wait(start_file: str | Path, ready_id: str, timeout_s: float = 120.0,
                          stop=None) -> float | None:
    """Start handshake of a service process: create ``<start_file>.ready.<ready_id>``, then wait for
    ``start_file`` to hold the start stamp (Unix s) and return it (None on timeout or stop)."""
    start_file = Path(start_file)
    Path(f"{start_file}.ready.{ready_id}").write_text(str(os.getpid()))
    t_end = time.time() + timeout_s
    while time.time() < t_end and not (stop is not None and stop.flag):
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
