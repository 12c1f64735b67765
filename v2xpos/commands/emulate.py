"""``v2xpos emulate DATASET_TOML``: serve a recording's byte streams as live devices
(``v2xpos.devices.emulate``: pseudo-terminals, or TCP listeners with ``--tcp``), print where they are
and the ``[source]`` table of a ``device`` slave on them, play until the end or a signal."""
from __future__ import annotations

import argparse
import json
import signal
import sys
import time
from pathlib import Path

from v2xpos.devices.emulate import Emulator, min_nav_pvt_latency_s


def source_snippet(emu: Emulator, latency_floor_s: float | None) -> str:
    """A ``[source]`` table for a ``device`` slave on the emulated streams (TOML text)."""
    devs = emu.devices()
    lines = ["[source]", 'type = "device"']

    def stream(d: dict) -> str:
        where = f'port = "{d["port"]}"' if "port" in d else f'tcp = "{d["tcp"]}"'
        return f'{{ format = "{d["format"]}", {where} }}'
    if "gnss" in devs:
        lines.append(f"gnss = {stream(devs['gnss'])}")
    if "imu" in devs:
        lines.append(f"imu = {stream(devs['imu'])}")
    clock = [f"host_time_offset_s = {emu.host_time_offset_s!r}", f"emulation_speed = {emu.speed!r}"]
    if latency_floor_s is not None:
        clock.append(f"latency_floor_s = {latency_floor_s:.3f}")
    lines.append("clock = { " + ", ".join(clock) + " }   # emulation only")
    return "\n".join(lines)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("dataset", help="dataset.toml with TIMETAG'd byte streams (e.g. walk_0827, drive_0708)")
    parser.add_argument("--speed", type=float, default=1.0, help="play faster than recorded (default 1)")
    parser.add_argument("--tcp", action="store_true", help="serve TCP listeners on 127.0.0.1 instead of pseudo-terminals")
    parser.add_argument("--start-in", type=float, default=2.0,
                        help="seconds between printing the devices and the first byte (default 2)")
    parser.add_argument("--duration", type=float, default=None, help="recorded seconds to play (default all)")
    parser.add_argument("--skip", type=float, default=0.0, help="recorded seconds to skip at the start")
    parser.add_argument("--only", action="append", choices=["gnss", "imu"], help="serve only this stream (repeatable)")
    parser.add_argument("--json", action="store_true", help="print one JSON line (devices, timing) instead of text")


def run(args: argparse.Namespace) -> int:
    try:
        emu = Emulator(args.dataset, speed=args.speed, tcp=args.tcp, start_in_s=args.start_in,
                       duration_s=args.duration, only=args.only, skip_s=args.skip)
    except (OSError, ValueError) as exc:
        print(f"v2xpos emulate: {exc}", file=sys.stderr)
        return 2
    floor = None
    try:
        from v2xpos.datasets.loader import read_descriptor
        g = read_descriptor(args.dataset).get("gnss", {})
        tag = g.get("raw_timetag") or (g.get("timetag") if g.get("format") == "ubx" else None)
        gs = [s for s in emu.streams if s.name == "gnss"]
        if gs and tag:
            floor = min_nav_pvt_latency_s(gs[0], Path(args.dataset).parent / tag)
    except (OSError, ValueError):
        floor = None
    emu.set_start(args.start_in)
    info = {"devices": emu.devices(), **emu.timing(), "latency_floor_s": floor}
    if args.json:
        print(json.dumps(info), flush=True)
    else:
        for name, d in emu.devices().items():
            print(f"{name:>5}: {d.get('port') or d.get('tcp')}  ({d['format']}, {d['source']})")
        print(f"host_time_offset_s = {emu.host_time_offset_s!r}   emulation_speed = {emu.speed!r}   "
              f"(emulation only: gps = speed * host_gps + offset)")
        if floor is not None:
            print(f"latency_floor_s = {floor:.3f}   (smallest NAV-PVT latency of the recording)")
        print(f"playing {emu.t_end_rec_s - emu.t0_rec_s:.1f} recorded s from {time.strftime('%H:%M:%S', time.localtime(emu.h0_unix_s))}"
              f"\n\n# a device slave on these streams:\n{source_snippet(emu, floor)}\n", flush=True)

    def on_signal(signum, frame):
        emu.stop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, on_signal)
    try:
        counts = emu.run()
    finally:
        emu.close()
    summary = {"done": True, "counts": counts}
    print(json.dumps(summary) if args.json else f"done: {counts}", flush=True)
    return 0
