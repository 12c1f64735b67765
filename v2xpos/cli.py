"""The ``v2xpos`` command: a table of subcommands, each implemented in the module that owns it.

Every command module exposes ``add_arguments(parser)`` and ``run(args) -> int``. Only the chosen
command's module is imported, so ``v2xpos --help`` stays fast and a broken optional dependency
of one command never breaks the others.
"""
from __future__ import annotations

import argparse
import importlib
import sys

COMMANDS: dict[str, tuple[str, str]] = {
    "replay": ("v2xpos.ins.replay", "replay a recorded drive through the GNSS/INS EKF with simulated outages"),
    "calibrate": ("v2xpos.diagnose.calibrate", "find missing model effects from residuals, estimate them, report before/after"),
    "grade": ("v2xpos.quality.grade", "grade the IMU units of a multi-IMU recording"),
    "demo": ("sim.demo", "run master, slaves and a pedestrian as processes on loopback; write a report"),
    "master": ("master.service", "run the master (hunter) service"),
    "slave": ("slave.service", "run a slave (target) service"),
    "keys": ("v2xpos.security", "generate vehicle signing keys and manage the master's trust list"),
    "replay-session": ("master.replay_session", "re-run the master pipeline from an MCAP recording"),
    "monitor": ("v2xpos.monitor.command", "live table and web bird's-eye view of a running master"),
    "emulate": ("v2xpos.devices.emulate", "serve a recording's byte streams as live devices (pseudo-terminals or TCP)"),
    "simulate": ("sim.recordings", "write simulated recordings in the shared formats (convoy: leader + followers, truth)"),
}

BENCHES: dict[str, tuple[str, str]] = {
    "replay": ("v2xpos.ins.replay", "EKF replay throughput [IMU samples/s]"),
    "fanin": ("master.bench_fanin", "slaves at 100 Hz one master core sustains with e2e p99 <= 10 ms"),
    "soak": ("master.bench_soak", "long run: sent / received / recorded / lost, memory growth"),
    "trust": ("v2xpos.security_bench", "forged / replayed messages, fuzzing, fault scenarios"),
    "fuzz": ("v2xpos.fuzz", "fuzz the message decoder and dataset readers"),
    "monitor": ("v2xpos.monitor.command", "monitor CPU and status-change delay at N targets x rate"),
    "calibration": ("sim.bench_calibration", "Monte-Carlo coverage of calibrate's estimates and sds (simulated drives)"),
}


def _usage(table: dict, prog: str) -> str:
    width = max(len(k) for k in table)
    rows = "\n".join(f"  {k:<{width}}  {d}" for k, (_, d) in table.items())
    return f"usage: {prog} COMMAND [options]\n\ncommands:\n{rows}\n"


def _dispatch(table: dict, argv: list[str], prog: str, entry: str) -> int:
    if not argv or argv[0] in ("-h", "--help"):
        print(_usage(table, prog))
        return 0 if argv else 2
    name = argv[0]
    if name not in table:
        print(f"{prog}: unknown command {name!r}\n\n{_usage(table, prog)}", file=sys.stderr)
        return 2
    module = importlib.import_module(table[name][0])
    parser = argparse.ArgumentParser(prog=f"{prog} {name}", description=table[name][1])
    getattr(module, f"add_{entry}arguments")(parser)
    args = parser.parse_args(argv[1:])
    return int(getattr(module, f"run_{entry[:-1]}" if entry else "run")(args) or 0)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv and argv[0] == "bench":
        # bench modules expose add_bench_arguments(parser) and run_bench(args)
        return _dispatch(BENCHES, argv[1:], "v2xpos bench", "bench_")
    return _dispatch(COMMANDS, argv, "v2xpos", "")


if __name__ == "__main__":
    sys.exit(main())
