"""``v2xpos monitor``: a live view of any running master -- a terminal table and, with ``--web``, a
page with a bird's-eye view and the same table (``v2xpos bench monitor``, what that costs, is
``bench.monitor``).

The monitor is a zenoh client of the master's router (``--connect``, the master's listen
endpoint); it reads only what the master publishes anyway (see ``v2xpos.monitor.attach``), so
attaching one adds no work to the master.
"""
from __future__ import annotations

import argparse
import sys
import time

from v2xpos.link import LinkConfig
from v2xpos.monitor.attach import MasterMonitor
from v2xpos.monitor.table import render, waiting_text
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

    def __init__(self, out=None, rows: int = 64, endpoint: str = "", fleet: str = "", master: str | None = None):
        out = sys.stdout if out is None else out      # resolved per call: a stream bound at import may be closed
        self.out = out
        self.rows = rows
        self.tty = out.isatty()
        self._last = 0.0
        self.endpoint, self.fleet, self.master = endpoint, fleet, master

    def __call__(self, snap: dict) -> None:
        if not snap["rows"] and snap["master"]["id"] is None and snap["master"]["state"] == "not_heard":
            text = waiting_text(snap, self.endpoint, self.fleet, self.master)
        else:
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
    table = None if args.no_table else _TableOut(rows=args.rows, endpoint=args.connect, fleet=args.fleet,
                                                 master=args.master)
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
