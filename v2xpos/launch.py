"""Starting the services as OS processes on one machine: config files, free loopback ports, process
handles, the collector setting of a service's real-time loop. Used by ``v2xpos convoy``
(recordings), the simulator's demo launcher, the benches and the services.

Nothing here knows what a service's source is: a launcher writes each service's TOML (with
:func:`to_toml`) and starts ``python -m v2xpos.cli master|slave --config FILE``.
"""
from __future__ import annotations

import math
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import IO

PROJECT_ROOT = Path(__file__).resolve().parents[1]


def freeze_setup_heap(young_collections: bool = True) -> None:
    """Call once a service is set up, before its real-time loop: what exists now (modules, numba's
    compiled kernels, the filter's configuration) leaves the cyclic collector's scans. A full
    collection over the whole heap of a service with numba and zenoh loaded takes tens of
    milliseconds of CPU at a random moment -- states held that long miss their time at the master;
    after the freeze it scans only what the loop itself made.

    ``young_collections``: also make the young collections rarer (thresholds 50,000 / 50 / 100,
    the master's message path, whose objects die young). Not for a loop whose objects survive a
    young collection: the middle generation then holds up to 50 x 50,000 objects before it is
    scanned, one long pause. The demo's simulated slaves fell behind with those thresholds (their
    states reached the master later than the demo's latency budget); with the freeze alone they
    keep up, so the slaves use the freeze alone."""
    import gc
    gc.collect()
    gc.freeze()
    if young_collections:
        gc.set_threshold(50_000, 50, 100)


def apply_realtime_priority(priority: int, who: str = "service") -> bool:
    """Put the calling thread under SCHED_RR at ``priority`` (1-99) before the service creates its
    threads and worker processes, which inherit it (Linux sched(7)): other processes on the same
    computer -- the simulated vehicles of the demo, the test jobs of a shared bench -- can then not
    hold the service's loop off the CPU for hundreds of milliseconds (states that miss the master's
    timeout). Needs CAP_SYS_NICE or an rtprio limit; if not granted the service runs at normal
    priority and says so (``who`` names it). The kernel keeps 5 % of each period for normal tasks
    (sched_rt_runtime_us). 0: the scheduling is left alone."""
    if priority <= 0:
        return False
    try:
        os.sched_setscheduler(0, os.SCHED_RR, os.sched_param(priority))
        return True
    except (AttributeError, OSError) as exc:
        print(f"{who}: realtime_priority {priority} not granted ({exc}); running at normal priority",
              file=sys.stderr)
        return False


def free_tcp_port() -> int:
    """A TCP port on 127.0.0.1 that is free now (asked from the OS)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def free_udp_port() -> int:
    """A UDP port on 127.0.0.1 that is free now (asked from the OS)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _toml_key(k: str) -> str:
    return k if k.replace("_", "").replace("-", "").isalnum() else '"' + k.replace('"', '\\"') + '"'


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
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{_toml_key(k)} = {_toml_value(x)}" for k, x in v.items() if x is not None) + " }"
    raise TypeError(f"cannot write {type(v).__name__} to TOML")


def to_toml(d: dict, prefix: str = "") -> str:
    """Minimal TOML writer for nested dicts of scalars/lists (what the service configs use);
    a dict nested at the top of a table becomes a sub-table, inside a list an inline table."""
    scalars = [(k, v) for k, v in d.items() if not isinstance(v, dict) and v is not None]
    tables = [(k, v) for k, v in d.items() if isinstance(v, dict)]
    out = []
    if prefix and (scalars or not tables):
        out.append(f"[{prefix}]")
    out += [f"{_toml_key(k)} = {_toml_value(v)}" for k, v in scalars]
    for k, v in tables:
        sub = to_toml(v, f"{prefix}.{_toml_key(k)}" if prefix else _toml_key(k))
        if sub:
            out.append(sub)
    return "\n".join(out) + ("\n" if out else "")


def service_env() -> dict:
    """Environment for a child service: unbuffered output, this checkout first on the path."""
    env = dict(os.environ)
    env.setdefault("PYTHONUNBUFFERED", "1")
    root = str(PROJECT_ROOT)
    env["PYTHONPATH"] = root + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    return env


class ServiceProcesses:
    """Service processes of one run, started in the given order, logs in ``log_dir``; stops only
    the processes it started."""

    def __init__(self, log_dir: Path):
        self.log_dir = Path(log_dir)
        self.procs: dict[str, subprocess.Popen] = {}
        self._logs: list[IO] = []

    def start(self, name: str, command: str, config: Path, extra_args: list[str] | None = None,
              nice: int = 0) -> subprocess.Popen:
        """``python -m v2xpos.cli COMMAND --config CONFIG [extra_args]`` with output to ``log_dir/NAME.log``."""
        self.log_dir.mkdir(parents=True, exist_ok=True)
        log = open(self.log_dir / f"{name}.log", "w")
        self._logs.append(log)
        proc = subprocess.Popen(
            [sys.executable, "-m", "v2xpos.cli", command, "--config", str(config), *(extra_args or [])],
            stdout=log, stderr=subprocess.STDOUT, env=service_env(), cwd=str(PROJECT_ROOT),
            preexec_fn=(lambda n=nice: os.nice(n)) if nice else None)
        self.procs[name] = proc
        return proc

    def running(self) -> list[str]:
        return [k for k, p in self.procs.items() if p.poll() is None]

    def wait(self, deadline_unix_s: float, poll_s: float = 0.1) -> dict[str, int | None]:
        """Wait until every process ended or the deadline passed, then stop what is left."""
        while self.running() and time.time() < deadline_unix_s:
            time.sleep(poll_s)
        return self.stop()

    def stop(self, grace_s: float = 5.0, order: list[str] | None = None) -> dict[str, int | None]:
        """SIGTERM every process still running (in ``order`` when given), SIGKILL after ``grace_s``;
        returns the exit codes."""
        names = order or list(self.procs)
        for name in names:
            p = self.procs[name]
            if p.poll() is None:
                p.send_signal(signal.SIGTERM)
        t_end = time.time() + grace_s
        for name in names:
            p = self.procs[name]
            try:
                p.wait(timeout=max(0.1, t_end - time.time()))
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
        for log in self._logs:
            if not log.closed:
                log.close()
        return {k: p.returncode for k, p in self.procs.items()}

    def log_tail(self, name: str, lines: int = 20) -> str:
        """The last lines of a process's log (for error messages)."""
        try:
            text = (self.log_dir / f"{name}.log").read_text(errors="replace")
        except OSError:
            return ""
        return "\n".join(text.splitlines()[-lines:])
