"""A ``device`` slave end to end: ``v2xpos emulate`` writes walk_0827's raw u-blox stream and IMU csv
into pseudo-terminals at their recorded arrival times; ``v2xpos slave`` with ``[source] type =
"device"`` reads them as serial ports, runs its filter on GPS time from the host clock (mapped
onto the recording: emulation only) and publishes its states over zenoh; the states received by a
router in this test give the same solution as ``v2xpos replay`` of the recording (horizontal
RMS difference <= 0.05 m)."""
from __future__ import annotations

import json
import signal
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

from tests.test_device_source import RMS_BOUND_M, WALK_IMU_TO_BODY, antenna_difference, needs_walk, walk_reference  # noqa: F401
from v2xpos.launch import free_tcp_port, service_env, to_toml
from v2xpos.link import Link, LinkConfig
from v2xpos.wire import decode_state, state_key


@needs_walk
@pytest.mark.slow
def test_device_slave_on_emulated_streams_matches_replay(walk_reference, tmp_path):
    toml, ds, series = walk_reference
    speed = 4.0
    port = free_tcp_port()
    router = Link(LinkConfig(mode="router", listen=[f"tcp/127.0.0.1:{port}"]))
    states, lock = [], threading.Lock()

    def on_state(payload, key, att, t_arr):
        msg = decode_state(payload)
        with lock:
            states.append(msg)

    router.subscribe(state_key("field", "walker"), on_state)
    emu = subprocess.Popen([sys.executable, "-m", "v2xpos.cli", "emulate", str(toml), "--json", "--start-in", "8",
                            "--speed", str(speed)], stdout=subprocess.PIPE, text=True, env=service_env())
    slave = None
    try:
        info = json.loads(emu.stdout.readline())
        dev = info["devices"]
        cfg = {"service": {"fleet": "field", "vehicle_id": "walker", "rate_hz": 100.0},
               "link": {"mode": "client", "connect": [f"tcp/127.0.0.1:{port}"], "connect_timeout_ms": 10000},
               "source": {"type": "device", "platform": "pedestrian", "imu_to_body": WALK_IMU_TO_BODY,
                          "lever_arm_m": [0.0, 0.0, 0.0], "lever_arm_sd_m": 0.05, "gnss": {"format": "ubx", "port": dev["gnss"]["port"]},
                          "imu": {"format": "csv_g_dps_ms", "port": dev["imu"]["port"]},
                          "reorder_window_s": 0.1 * speed * 0.75,
                          "clock": {"host_time_offset_s": info["host_time_offset_s"],
                                    "emulation_speed": info["emulation_speed"],
                                    "latency_floor_s": info["latency_floor_s"]}}}
        path = tmp_path / "slave_device.toml"
        path.write_text(to_toml(cfg))
        slave = subprocess.Popen([sys.executable, "-m", "v2xpos.cli", "slave", "--config", str(path)],
                                 stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=service_env())
        t_end = time.time() + 60 + (info["recording_end_gps_s"] - info["recording_start_gps_s"]) / speed
        while time.time() < t_end and slave.poll() is None:
            with lock:
                last = states[-1].t_gps_s if states else None
            if last is not None and last >= info["recording_end_gps_s"] - 0.5:
                break
            time.sleep(0.1)
        slave.send_signal(signal.SIGINT)
        out, err = slave.communicate(timeout=20)
        assert slave.returncode == 130 and "Traceback" not in err, err[-3000:]     # stopped by SIGINT
        counters = json.loads(out.strip().splitlines()[-1])
    finally:
        if slave is not None and slave.poll() is None:
            slave.kill()
        emu.terminate()
        emu.wait(10)
        router.close()
    assert counters["source"] == "device" and counters["sent"] > 0.9 * len(states) > 1000
    assert all(m.time_ok for m in states[len(states) // 5:])       # receiver time within 20 ms of the host
    navs = [m.to_nav_state() for m in states]
    d = antenna_difference(navs, series)
    rms = float(np.sqrt(np.mean(d ** 2)))
    print(f"device slave (emulated ptys, x{speed:g}) vs replay: {len(d)} epochs, horizontal RMS {rms * 1e3:.1f} mm")
    assert len(d) >= len(ds.gnss) - 30
    assert rms <= RMS_BOUND_M
