"""``v2xpos bench monitor``: what watching a master with ``v2xpos monitor`` costs -- the monitor
process's CPU and the delay from a target's status change to the snapshot and the table showing it,
at N targets x rate, against a fake master (``bench.fake_master``) in a child process."""
from __future__ import annotations

import argparse
import io
import json
import os
import subprocess
import sys
import threading
import time
import urllib.request
from pathlib import Path

from v2xpos.launch import free_tcp_port, service_env
from v2xpos.link import LinkConfig
from v2xpos.monitor.attach import MasterMonitor
from v2xpos.monitor.table import render
from v2xpos.monitor.web import WebServer


def add_bench_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--targets", type=int, default=64, help="targets (default 64)")
    parser.add_argument("--rate-hz", type=float, default=100.0, help="results per target per second (default 100)")
    parser.add_argument("--duration", type=float, default=20.0, help="measured seconds (default 20)")
    parser.add_argument("--flip-every", type=float, default=1.3,
                        help="seconds between status changes of one target (latency samples)")
    parser.add_argument("--json", help="write the figures here")


def run_bench(args: argparse.Namespace) -> int:
    """A fake master (child process: results of N targets at the rate, status JSON at 2 Hz, one
    target's status flipped VALID <-> FIX_INVALID every ``--flip-every`` s, each flip time printed)
    and this process as the monitor, with the web page polled at 5 Hz and the table rendered at
    every snapshot, as a user would run it. Reports the monitor process's CPU [% of one core] and
    the delay from a flip's first result to the first snapshot / table showing it."""
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    warm_s = 3.0
    pub = subprocess.Popen([sys.executable, "-m", "bench.fake_master", "--endpoint", endpoint,
                            "--targets", str(args.targets), "--rate-hz", str(args.rate_hz),
                            "--duration", str(args.duration + warm_s + 2.0), "--flip-every", str(args.flip_every)],
                           stdout=subprocess.PIPE, text=True,
                           env=service_env())
    flips: list[tuple[float, str]] = []
    flip_target = None

    def read_pub() -> None:
        nonlocal flip_target
        for line in pub.stdout:
            d = json.loads(line)
            if "flip" in d:
                flips.append((d["t_wall_s"], d["status"]))
                flip_target = d["flip"]
    threading.Thread(target=read_pub, daemon=True).start()
    seen: list[tuple[float, str]] = []
    shown: list[tuple[float, str]] = []
    sink = io.StringIO()

    def on_snapshot(snap: dict) -> None:
        t = time.time()
        text = render(snap, 64)
        sink.seek(0)
        sink.write(text)
        t_shown = time.time()
        for r in snap["rows"]:
            if r["id"] == flip_target:
                if not seen or seen[-1][1] != r["status"]:
                    seen.append((t, r["status"]))
                    shown.append((t_shown, r["status"]))
    deadline = time.time() + 30
    while time.time() < deadline:   # the fake master's router
        try:
            mon = MasterMonitor(LinkConfig(mode="client", connect=[endpoint], connect_timeout_ms=1000),
                                "demo", "ego", on_snapshot=on_snapshot).start()
            break
        except Exception:
            time.sleep(0.2)
    else:
        pub.kill()
        print("bench monitor: fake master did not come up", file=sys.stderr)
        return 1
    web = WebServer(mon.snapshot).start()
    stop = threading.Event()

    def page() -> None:
        while not stop.wait(0.2):
            with urllib.request.urlopen(web.url + "api/state") as r:
                r.read()
    threading.Thread(target=page, daemon=True).start()
    time.sleep(warm_s)
    c0, t0, n0 = os.times(), time.time(), mon.state.received
    time.sleep(args.duration)
    c1, t1, n1 = os.times(), time.time(), mon.state.received
    stop.set()
    web.close()
    mon.close()
    pub.wait(timeout=10)
    cpu = (c1.user + c1.system - c0.user - c0.system) / (t1 - t0)
    delays = []
    delays_table = []
    for t_flip, status in flips:
        if not t0 <= t_flip <= t1 - 1.0:
            continue
        after = [t for t, s in seen if s == status and t >= t_flip]
        after_tab = [t for t, s in shown if s == status and t >= t_flip]
        if after:
            delays.append(after[0] - t_flip)
            delays_table.append(after_tab[0] - t_flip)
    import numpy as np
    out = {"targets": args.targets, "rate_hz": args.rate_hz, "results_per_s": (n1 - n0) / (t1 - t0),
           "monitor_cpu_percent_of_one_core": 100 * cpu, "status_changes": len(delays),
           "change_to_snapshot_s_max": max(delays) if delays else None,
           "change_to_snapshot_s_p50": float(np.median(delays)) if delays else None,
           "change_to_table_s_max": max(delays_table) if delays_table else None,
           "missed_changes": sum(1 for t, _ in flips if t0 <= t <= t1 - 1.0) - len(delays)}
    print(json.dumps(out, indent=1))
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=1))
    return 0
