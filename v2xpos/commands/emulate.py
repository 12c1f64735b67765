"""``v2xpos emulate DATASET_TOML [DATASET_TOML ...]``: serve recordings' byte streams as live devices
(``v2xpos.devices.emulate``: pseudo-terminals, or TCP listeners with ``--tcp``) on one timeline,
print where they are and, per recording, a complete ``[source]`` table of a ``device`` vehicle on
them (platform, mounting, lever arm from the recording's descriptor, the streams, the emulation
clock); with ``--configs DIR`` also write a master config for the first recording and a slave
config for each other one, ready to run. Play until the end or a signal.

A recording that cannot be served fully (no GNSS byte stream, e.g. an RTKLIB ``.pos`` only, or no
IMU byte stream) is refused, saying what is missing; ``--only imu`` / ``--only gnss`` serves a
part of it on purpose, without a table (a device source needs both).
"""
from __future__ import annotations

import argparse
import json
import signal
import sys
import time
from pathlib import Path

import numpy as np

from v2xpos.devices.emulate import Emulator, min_nav_pvt_latency_s, missing_streams

ROUTER_DEFAULT = "tcp/127.0.0.1:7447"


def source_table(emu: Emulator, vehicle: str, latency_floor_s: float | None) -> dict:
    """The ``[source]`` table of a ``device`` vehicle on the emulated streams of ``vehicle``'s
    recording: what its descriptor declares (platform, ``imu_to_body``, lever arm and its sd,
    a ``[calibration]`` table) and the emulation clock (``host_time_offset_s``, ``emulation_speed``:
    for emulation only; ``latency_floor_s``: the recording's smallest NAV-PVT latency)."""
    from v2xpos.datasets.loader import read_descriptor
    path = emu.vehicle_ids[vehicle]
    desc = read_descriptor(path)
    imu_t, gnss_t = desc.get("imu") or {}, desc.get("gnss") or {}
    table: dict = {"type": "device", "platform": desc.get("platform", "car")}
    for name, d in emu.devices(vehicle).items():
        table[name] = {"format": d["format"], **({"port": d["port"]} if "port" in d else {"tcp": d["tcp"]})}
    mounting = imu_t.get("imu_to_body")
    table["imu_to_body"] = "identity" if mounting is None or np.allclose(mounting, np.eye(3)) else mounting
    table["lever_arm_m"] = [float(x) for x in gnss_t.get("lever_arm_m", [0.0, 0.0, 0.0])]
    if "lever_arm_sd_m" in gnss_t:
        table["lever_arm_sd_m"] = float(gnss_t["lever_arm_sd_m"])
    clock = {"host_time_offset_s": emu.host_time_offset_s, "emulation_speed": emu.speed}
    if latency_floor_s is not None:
        clock["latency_floor_s"] = round(latency_floor_s, 3)
    table["clock"] = clock
    if "calibration" in desc:
        table["calibration"] = desc["calibration"]
    return table


def _toml_value(v) -> str:
    """A value as inline TOML (strings, numbers, booleans, arrays, inline tables)."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float)):
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{k} = {_toml_value(x)}" for k, x in v.items()) + " }"
    raise TypeError(f"no TOML for {type(v).__name__}")


def toml_text(doc: dict) -> str:
    """``doc`` ({table: {key: value}}) as TOML with one line per key, sub-tables inline (readable
    and pasteable: ``gnss = { format = "ubx", tcp = "..." }``)."""
    out = []
    for table, keys in doc.items():
        out.append(f"[{table}]")
        out += [f"{k} = {_toml_value(v)}" for k, v in keys.items()]
        out.append("")
    return "\n".join(out)


BENCH_REALTIME_PRIORITY = 10
"""``[service] realtime_priority`` of the configs ``emulate`` writes: a bench is a shared computer,
and a service starved of the CPU for 200 ms by other jobs shows its states as TIMEOUT at the master
(``v2xpos.launch.apply_realtime_priority``; without the privilege the services say so and run at
normal priority)."""


def service_configs(emu: Emulator, out_dir: Path, router: str, fleet: str, floors: dict) -> dict[str, Path]:
    """Write ``master.toml`` (the first recording's vehicle, the router on ``router``) and one
    ``slave_<id>.toml`` per other recording into ``out_dir`` (made absolute: the services resolve
    the config's paths against its own directory). Returns {vehicle id: path}."""
    out_dir = Path(out_dir).resolve()
    out_dir.mkdir(parents=True, exist_ok=True)
    ids = list(emu.vehicle_ids)
    written = {}
    for k, vid in enumerate(ids):
        source = source_table(emu, vid, floors.get(vid))
        if k == 0:
            doc = {"service": {"fleet": fleet, "master_id": vid, "known_vehicles": ids[1:],
                               "realtime_priority": BENCH_REALTIME_PRIORITY},
                   "link": {"mode": "router", "listen": [router]}, "source": source,
                   "record": {"results_csv": "results.csv", "summary_json": "master_summary.json"}}
            path = out_dir / "master.toml"
        else:
            doc = {"service": {"fleet": fleet, "vehicle_id": vid, "realtime_priority": BENCH_REALTIME_PRIORITY},
                   "link": {"mode": "client", "connect": [router], "connect_timeout_ms": 60000}, "source": source}
            path = out_dir / f"slave_{vid}.toml"
        path.write_text("# written by v2xpos emulate: emulated devices (clock.host_time_offset_s and emulation_speed "
                        "are for emulation only)\n" + toml_text(doc))
        written[vid] = path
    return written


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("dataset", nargs="+",
                        help="dataset.toml with TIMETAG'd byte streams (a GNSS u-blox stream and an IMU csv); several "
                             "recordings of one drive share one timeline")
    parser.add_argument("--speed", type=float, default=1.0, help="play faster than recorded (default 1)")
    parser.add_argument("--tcp", action="store_true", help="serve TCP listeners on 127.0.0.1 instead of pseudo-terminals")
    parser.add_argument("--start-in", type=float, default=2.0,
                        help="seconds between printing the devices and the first byte (default 2)")
    parser.add_argument("--duration", type=float, default=None, help="recorded seconds to play (default all)")
    parser.add_argument("--skip", type=float, default=0.0, help="recorded seconds to skip at the start")
    parser.add_argument("--only", action="append", choices=["gnss", "imu"],
                        help="serve only this stream (repeatable; no [source] table then)")
    parser.add_argument("--configs", default=None, metavar="DIR",
                        help="write master.toml (first dataset) and slave_<id>.toml (the others) into DIR")
    parser.add_argument("--router", default=ROUTER_DEFAULT,
                        help=f"the master's zenoh endpoint in the written configs (default {ROUTER_DEFAULT})")
    parser.add_argument("--fleet", default="bench", help="fleet name in the written configs (default bench)")
    parser.add_argument("--json", action="store_true", help="print one JSON line (devices, timing) instead of text")


def _floors(emu: Emulator) -> dict:
    """Per vehicle, the smallest NAV-PVT latency of its recorded u-blox stream (None when unknown)."""
    from v2xpos.datasets.loader import read_descriptor
    out = {}
    for vid, path in emu.vehicle_ids.items():
        try:
            g = read_descriptor(path).get("gnss", {})
            tag = g.get("raw_timetag") or (g.get("timetag") if g.get("format") == "ubx" else None)
            gs = [s for s in emu.streams if s.name == "gnss" and s.vehicle == vid]
            out[vid] = min_nav_pvt_latency_s(gs[0], Path(path).parent / tag) if gs and tag else None
        except (OSError, ValueError):
            out[vid] = None
    return out


def run(args: argparse.Namespace) -> int:
    if not (args.speed > 0) or args.start_in < 0:
        print("v2xpos emulate: --speed must be > 0 and --start-in >= 0", file=sys.stderr)
        return 2
    if args.only is None:
        for path in args.dataset:
            try:
                missing = missing_streams(path)
            except (OSError, ValueError) as exc:
                print(f"v2xpos emulate: {exc}", file=sys.stderr)
                return 2
            if missing:
                print(f"v2xpos emulate: {path}: cannot be served as a device vehicle: " + "; ".join(missing)
                      + ". `--only imu` serves the IMU alone (no [source] table: a device source needs both); "
                        "`v2xpos simulate convoy` writes recordings with both streams.", file=sys.stderr)
                return 2
    try:
        emu = Emulator(args.dataset, speed=args.speed, tcp=args.tcp, start_in_s=args.start_in,
                       duration_s=args.duration, only=args.only, skip_s=args.skip)
    except (OSError, ValueError) as exc:
        print(f"v2xpos emulate: {exc}", file=sys.stderr)
        return 2
    floors = _floors(emu)
    complete = args.only is None
    configs = {}
    emu.set_start(args.start_in)
    if args.configs and complete:
        configs = service_configs(emu, Path(args.configs), args.router, args.fleet, floors)
    first = next(iter(emu.vehicle_ids))
    info = {"devices": emu.devices(), **emu.timing(), "latency_floor_s": floors.get(first),
            "vehicles": {vid: {**v, "latency_floor_s": floors.get(vid),
                               "source": source_table(emu, vid, floors.get(vid)) if complete else None}
                         for vid, v in emu.vehicles().items()},
            "configs": {vid: str(p) for vid, p in configs.items()}}
    if args.json:
        print(json.dumps(info), flush=True)
    else:
        _print_text(emu, floors, complete, configs)

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


def _print_text(emu: Emulator, floors: dict, complete: bool, configs: dict) -> None:
    for s in emu.streams:
        print(f"{s.vehicle:>6} {s.name:>5}: {s.path or s.address}  ({s.format}, {s.source})")
    print(f"host_time_offset_s = {emu.host_time_offset_s!r}   emulation_speed = {emu.speed!r}   "
          f"(emulation only: gps = speed * host_gps + offset; the same for every vehicle served here)")
    print(f"playing {emu.t_end_rec_s - emu.t0_rec_s:.1f} recorded s from "
          f"{time.strftime('%H:%M:%S', time.localtime(emu.h0_unix_s))}")
    if not complete:
        print("\n(partial streams: no [source] table, a device source needs a GNSS and an IMU stream)", flush=True)
        return
    for vid in emu.vehicle_ids:
        table = source_table(emu, vid, floors.get(vid))
        print(f"\n# a device vehicle on the streams of {vid} ({emu.vehicle_ids[vid]}):\n"
              + toml_text({"source": table}).rstrip())
    for vid, path in configs.items():
        role = "master" if path.name == "master.toml" else "slave"
        print(f"\n{role} {vid}: v2xpos {role} --config {path}")
    print("", flush=True)
