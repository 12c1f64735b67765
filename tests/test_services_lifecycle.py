"""Both services stop cleanly on SIGINT and on SIGTERM within 1 s in every phase of their life:
building the source (loading a recording), waiting for the zenoh router, waiting for the session
clock, running. Exit code 0 (130 only before the service exists), no traceback; a slave waiting
for its router says so; a master whose port is taken fails with one line naming the endpoint."""
from __future__ import annotations

import json
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from v2xpos.launch import free_tcp_port, service_env, to_toml
from tests.shared_data import SHARED_DATA, require_shared

ROOT = Path(__file__).resolve().parents[1]
DATA = SHARED_DATA / "convoy_dev"
STOP_WITHIN_S = 1.0

pytestmark = pytest.mark.slow


def _dataset(name: str) -> str:
    p = DATA / name / "dataset.toml"
    return str(require_shared(p).resolve())


class Service:
    """A service process whose stderr lines are collected as they come."""

    def __init__(self, command: str, cfg: dict, tmp: Path):
        path = tmp / f"{command}.toml"
        path.write_text(to_toml(cfg))
        self.proc = subprocess.Popen([sys.executable, "-m", "v2xpos.cli", command, "--config", str(path)],
                                     stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=service_env(),
                                     cwd=str(ROOT))
        self.err: list[str] = []
        self._t = threading.Thread(target=lambda: self.err.extend(iter(self.proc.stderr.readline, "")), daemon=True)
        self._t.start()

    def wait_for_line(self, text: str, timeout_s: float = 60.0) -> None:
        t_end = time.time() + timeout_s
        while time.time() < t_end:
            if any(text in line for line in self.err):
                return
            if self.proc.poll() is not None:
                break
            time.sleep(0.02)
        raise AssertionError(f"no line with {text!r} on stderr: {''.join(self.err)[-2000:]}")

    def stop(self, sig: int) -> tuple[int, float, str, str]:
        t0 = time.time()
        self.proc.send_signal(sig)
        try:
            self.proc.wait(timeout=15)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
            self._t.join(2)
            return -9, time.time() - t0, self.proc.stdout.read(), "".join(self.err)
        dt = time.time() - t0
        self._t.join(2)                  # the reader thread owns stderr (communicate would race it)
        return self.proc.returncode, dt, self.proc.stdout.read(), "".join(self.err)

    def wait(self, timeout_s: float) -> str:
        """Wait for the process to end by itself; its stdout."""
        self.proc.wait(timeout=timeout_s)
        self._t.join(2)
        return self.proc.stdout.read()


def slave_cfg(port: int, dataset: str, sync: str = "auto") -> dict:
    return {"service": {"fleet": "life", "vehicle_id": "B"},
            "link": {"mode": "client", "connect": [f"tcp/127.0.0.1:{port}"], "connect_timeout_ms": 60000},
            "source": {"type": "recording", "dataset": dataset, "sync": sync}}


def master_cfg(port: int, dataset: str, wait_for: list) -> dict:
    return {"service": {"fleet": "life", "master_id": "A", "status_hz": 5.0},
            "link": {"mode": "router", "listen": [f"tcp/127.0.0.1:{port}"]},
            "source": {"type": "recording", "dataset": dataset, "wait_for": wait_for}}


def _check(rc: int, dt: float, err: str) -> None:
    """Stopped by a signal: no traceback, exit code 130 (README: "130 interrupted"), within the bound."""
    assert "Traceback" not in err, err[-3000:]
    assert rc == 130, (rc, err[-2000:])
    assert dt <= STOP_WITHIN_S, f"stopped after {dt:.2f} s"


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_slave_stops_in_every_phase(tmp_path, sig):
    b = _dataset("B")
    port = free_tcp_port()                         # nobody listens here (yet)
    # building the source: the recording is still loading
    s = Service("slave", slave_cfg(port, b), tmp_path)
    time.sleep(0.8)
    rc, dt, out, err = s.stop(sig)
    _check(rc, dt, err)
    assert json.loads(out.strip().splitlines()[-1])["stopped_early"] is True
    # waiting for its router: says so, retries
    s = Service("slave", slave_cfg(port, b), tmp_path)
    s.wait_for_line("waiting for the zenoh router")
    time.sleep(1.2)
    rc, dt, out, err = s.stop(sig)
    _check(rc, dt, err)
    # waiting for the session clock (a router, no master)
    from v2xpos.link import Link, LinkConfig
    router = Link(LinkConfig(mode="router", listen=[f"tcp/127.0.0.1:{port}"]))
    try:
        s = Service("slave", slave_cfg(port, b), tmp_path)
        s.wait_for_line("waiting for the session clock")
        rc, dt, out, err = s.stop(sig)
        _check(rc, dt, err)
        # running (alone on its recording): stopped once its states arrive
        got = threading.Event()
        router.subscribe("v2xpos/life/vehicle/B/state", lambda *a: got.set())
        s = Service("slave", slave_cfg(port, b, sync="none"), tmp_path)
        assert got.wait(60), "".join(s.err)
        rc, dt, out, err = s.stop(sig)
        _check(rc, dt, err)
        counters = json.loads(out.strip().splitlines()[-1])
        assert counters["phase"] == "done" and counters["sent"] > 0
    finally:
        router.close()


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_master_stops_in_every_phase(tmp_path, sig):
    a = _dataset("A")
    port = free_tcp_port()
    s = Service("master", master_cfg(port, a, ["B"]), tmp_path)     # loading its recording
    time.sleep(0.8)
    rc, dt, out, err = s.stop(sig)
    _check(rc, dt, err)
    s = Service("master", master_cfg(port, a, ["B"]), tmp_path)     # waiting for B to be ready
    s.wait_for_line("waiting for ['B']")
    rc, dt, out, err = s.stop(sig)
    _check(rc, dt, err)
    from v2xpos.link import Link, LinkConfig
    from v2xpos.wire import status_key
    s = Service("master", master_cfg(port, a, []), tmp_path)        # running
    client = None
    try:
        seen = threading.Event()
        t_end = time.time() + 60
        while client is None and time.time() < t_end:
            try:
                client = Link(LinkConfig(mode="client", connect=[f"tcp/127.0.0.1:{port}"], connect_timeout_ms=500))
            except Exception:
                time.sleep(0.2)
        client.subscribe(status_key("life", "A"), lambda *x: seen.set())
        assert seen.wait(60), "".join(s.err)
        rc, dt, out, err = s.stop(sig)
        _check(rc, dt, err)
        assert json.loads(out.strip().splitlines()[-1])["processed"] == 0
    finally:
        if client is not None:
            client.close()


def test_master_port_in_use_is_one_line(tmp_path):
    a = _dataset("A")
    from v2xpos.link import Link, LinkConfig
    port = free_tcp_port()
    holder = Link(LinkConfig(mode="router", listen=[f"tcp/127.0.0.1:{port}"]))
    try:
        s = Service("master", master_cfg(port, a, []), tmp_path)
        s.wait(60)
        err = "".join(s.err)
        assert s.proc.returncode == 2 and "Traceback" not in err
        assert f"tcp/127.0.0.1:{port}" in err and "[link]" in err
    finally:
        holder.close()
