"""``v2xpos monitor``: a live view of any running master -- a terminal table and, with ``--web``, a
page with a bird's-eye view and the same table -- and ``v2xpos bench monitor``, what that costs.

The monitor is a zenoh client of the master's router (``--connect``, the master's listen
endpoint); it reads only what the master publishes anyway (see ``v2xpos.monitor.attach``), so
attaching one adds no work to the master.
"""
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

from v2xpos.link import LinkConfig
from v2xpos.monitor.attach import MasterMonitor
from v2xpos.monitor.table import render
from v2xpos.monitor.web import WebServer, parse_host_port

PLAIN_EVERY_S = 5.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--connect", default="tcp/127.0.0.1:7447",
                        help="the master's zenoh endpoint (its [link] listen), default tcp/127.0.0.1:7447")
    parser.add_argument("--master", default=None,
                        help="master id (default: the first master of the fleet that publishes its status)")
    parser.add_argument("--fleet", default="demo", help="fleet name (default demo)")
    parser.add_argument("--web", nargs="?", const="127.0.0.1:8080", default=None, metavar="HOST:PORT",
                        help="serve the live page on HOST:PORT (default 127.0.0.1:8080; port 0: any free port)")
    parser.add_argument("--no-table", action="store_true", help="no terminal table (with --web)")
    parser.add_argument("--rows", type=int, default=64, help="most target lines in the terminal table (default 64)")
    parser.add_argument("--refresh-hz", type=float, default=5.0, help="snapshots per second (default 5)")
    parser.add_argument("--duration", type=float, default=None, help="stop after this many seconds (default: Ctrl-C)")
    parser.add_argument("--connect-timeout-ms", type=int, default=10000,
                        help="how long to wait for the master's router at start (default 10000; -1 forever)")


class _TableOut:
    """Redraws in place on a terminal; on a pipe or file prints one block every PLAIN_EVERY_S."""

    def __init__(self, out=sys.stdout, rows: int = 64):
        self.out = out
        self.rows = rows
        self.tty = out.isatty()
        self._last = 0.0

    def __call__(self, snap: dict) -> None:
        if not snap["rows"] and snap["master"]["id"] is None:
            return   # nothing heard from the master yet
        text = render(snap, self.rows)
        if self.tty:
            self.out.write("\x1b[H\x1b[J" + text + "\n")
            self.out.flush()
        elif time.time() - self._last >= PLAIN_EVERY_S:
            self._last = time.time()
            self.out.write(text + "\n\n")
            self.out.flush()


def run(args: argparse.Namespace) -> int:
    try:
        link_cfg = LinkConfig(mode="client", connect=[args.connect], connect_timeout_ms=args.connect_timeout_ms)
        web_addr = parse_host_port(args.web) if args.web else None
    except ValueError as exc:
        print(f"v2xpos monitor: {exc}", file=sys.stderr)
        return 2
    if args.refresh_hz <= 0 or args.rows < 1:
        print("v2xpos monitor: --refresh-hz must be > 0 and --rows >= 1", file=sys.stderr)
        return 2
    table = None if args.no_table else _TableOut(rows=args.rows)
    mon = MasterMonitor(link_cfg, args.fleet, args.master, refresh_period_s=1.0 / args.refresh_hz, on_snapshot=table)
    try:
        mon.start()
    except Exception as exc:   # zenoh could not reach the router
        print(f"v2xpos monitor: cannot connect to {args.connect}: {exc}", file=sys.stderr)
        return 2
    web = None
    try:
        if web_addr is not None:
            try:
                web = WebServer(mon.snapshot, *web_addr).start()
            except OSError as exc:
                print(f"v2xpos monitor: --web {args.web}: {exc}", file=sys.stderr)
                return 2
            print(f"v2xpos monitor: page on {web.url}", file=sys.stderr, flush=True)
        t_end = time.time() + args.duration if args.duration else float("inf")
        while time.time() < t_end:
            time.sleep(min(0.2, max(0.0, t_end - time.time())))
    except KeyboardInterrupt:
        pass
    finally:
        if web is not None:
            web.close()
        mon.close()
    return 0


# ----------------------------------------------------------------------------- bench

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
    import socket
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    endpoint = f"tcp/127.0.0.1:{port}"
    warm_s = 3.0
    pub = subprocess.Popen([sys.executable, "-m", "v2xpos.monitor.fake_master", "--endpoint", endpoint,
                            "--targets", str(args.targets), "--rate-hz", str(args.rate_hz),
                            "--duration", str(args.duration + warm_s + 2.0), "--flip-every", str(args.flip_every)],
                           stdout=subprocess.PIPE, text=True,
                           env={**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[2])})
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
