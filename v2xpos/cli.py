"""The ``v2xpos`` command: a table of subcommands, each implemented in the module that owns it.

Every command module exposes ``add_arguments(parser)`` and ``run(args) -> int``. Only the chosen
command's module is imported, so ``v2xpos --help`` stays fast and a broken optional dependency
of one command never breaks the others.

Exit codes: 0 done; 1 done, and the result says something failed (a graded unit, a process);
2 bad input, usage or environment (the message names the file and key, or the endpoint);
3 an unexpected error, i.e. a bug (one line; ``V2XPOS_DEBUG=1`` prints the traceback);
130 interrupted (Ctrl-C).
"""
from __future__ import annotations

import argparse
import difflib
import importlib
import os
import sys
import traceback

from v2xpos import stop_signals

EXIT_INPUT = 2
EXIT_INTERNAL = 3
EXIT_INTERRUPTED = 130

COMMANDS: dict[str, tuple[str, str]] = {
    "replay": ("v2xpos.commands.replay", "replay a recorded drive through the GNSS/INS EKF with simulated outages"),
    "calibrate": ("v2xpos.commands.calibrate", "find missing model effects from residuals, estimate them, report before/after"),
    "grade": ("v2xpos.commands.grade", "grade the IMU units of a multi-IMU recording"),
    "demo": ("sim.demo", "run master, slaves and a pedestrian as processes on loopback; write a report"),
    "master": ("master.service", "run the master (hunter) service"),
    "slave": ("slave.service", "run a slave (target) service"),
    "keys": ("v2xpos.commands.keys", "generate vehicle signing keys and manage the master's trust list"),
    "replay-session": ("master.replay_session", "re-run the master pipeline from an MCAP recording"),
    "convoy": ("master.convoy", "run master and slaves on recorded drives as processes; write results.csv"),
    "monitor": ("v2xpos.commands.monitor", "live table and web bird's-eye view of a running master"),
    "emulate": ("v2xpos.commands.emulate", "serve a recording's byte streams as live devices (pseudo-terminals or TCP)"),
    "simulate": ("sim.recordings", "write simulated recordings in the shared formats (convoy: leader + followers, truth; "
                                   "sensor: an object list)"),
    "evaluate": ("v2xpos.commands.evaluate", "judge a sensor's object list against the reference: latency, "
                                             "mounting yaw, range bias, errors, detection"),
}

STOPS_CLEANLY = {"master.service", "slave.service"}
"""Services that stop cleanly on a signal, also while their modules load (``v2xpos.stop_signals``)."""

BENCHES: dict[str, tuple[str, str]] = {
    "replay": ("bench.replay", "EKF replay throughput [IMU samples/s]"),
    "fanin": ("bench.fanin", "slaves at 100 Hz one master core sustains with e2e p99 <= 10 ms"),
    "soak": ("bench.soak", "long run: sent / received / recorded / lost, memory growth"),
    "trust": ("bench.trust", "forged / replayed messages, fuzzing, fault scenarios"),
    "grading": ("bench.grading", "IMU grading on simulated vehicles: fault sweep, lidar rate check"),
    "fuzz": ("bench.fuzz", "fuzz the message decoder and dataset readers"),
    "monitor": ("bench.monitor", "monitor CPU and status-change delay at N targets x rate"),
    "corpus": ("bench.corpus", "broken inputs through replay/calibrate/grade/config loading: tracebacks, silent exits"),
    "calibration": ("bench.calibration", "Monte-Carlo coverage of calibrate's estimates and sds (simulated drives)"),
    "evaluate": ("bench.evaluate", "evaluate: Monte-Carlo recovery of simulated sensor effects; 30 min 20 Hz 32-object speed"),
    "real-pair": ("bench.real_pair", "a real recording and itself delayed as two vehicles, scored against the RTK"),
    "smoothing-memory": ("bench.smoothing_memory", "peak memory of replay --smooth on a generated hour (limit 1 GiB)"),
    "figures": ("bench.figures", "run the benchmarks behind the docs' figures and write docs/figures.md (--quick: CI subset)"),
}


BENCH_LINE = ("bench", "benchmarks that print figures: replay, fanin, soak, trust, ... (v2xpos bench --help)")


class Parser(argparse.ArgumentParser):
    """argparse with a "did you mean" for a misspelt option (``--outage-lenght``)."""

    def error(self, message: str) -> None:  # type: ignore[override]
        hint = ""
        for word in message.replace(",", " ").split():
            if word.startswith("--") and "unrecognized" in message:
                options = [o for a in self._actions for o in a.option_strings if o.startswith("--")]
                near = difflib.get_close_matches(word.split("=", 1)[0], options, n=1)
                if near:
                    hint = f" (did you mean {near[0]}?)"
                    break
        super().error(message + hint)


def _usage(table: dict, prog: str) -> str:
    entries = list(table.items()) + ([(BENCH_LINE[0], ("", BENCH_LINE[1]))] if table is COMMANDS else [])
    width = max(len(k) for k, _ in entries)
    rows = "\n".join(f"  {k:<{width}}  {d}" for k, (_, d) in entries)
    version = "\n  --version  print the version and exit\n" if prog == "v2xpos" else ""
    return f"usage: {prog} COMMAND [options]\n\ncommands:\n{rows}\n{version}"


def _dispatch(table: dict, argv: list[str], prog: str, entry: str) -> int:
    if not argv or argv[0] in ("-h", "--help"):
        print(_usage(table, prog))
        return 0 if argv else 2
    name = argv[0]
    if name not in table:
        names = list(table) + ([BENCH_LINE[0]] if table is COMMANDS else [])
        near = difflib.get_close_matches(name, names, n=1)
        hint = f" (did you mean {near[0]!r}?)" if near else ""
        print(f"{prog}: unknown command {name!r}{hint}\n\n{_usage(table, prog)}", file=sys.stderr)
        return 2
    if table[name][0] in STOPS_CLEANLY:
        stop_signals.exit_until_handled(name)
    module = importlib.import_module(table[name][0])
    parser = Parser(prog=f"{prog} {name}", description=table[name][1])
    getattr(module, f"add_{entry}arguments")(parser)
    args = parser.parse_args(argv[1:])
    return int(getattr(module, f"run_{entry[:-1]}" if entry else "run")(args) or 0)


def version() -> str:
    """The installed distribution's version (the package's own when not installed)."""
    from importlib import metadata
    try:
        return metadata.version("v2xpos")
    except metadata.PackageNotFoundError:
        from v2xpos import __version__
        return __version__


def _prog(argv: list[str]) -> str:
    words = [a for a in argv[:2] if not a.startswith("-")]
    if words and words[0] == "bench":
        return " ".join(["v2xpos", *words[:2]])
    return " ".join(["v2xpos", *words[:1]])


def run_command(argv: list[str]) -> int:
    """Run one command without the guard of ``main`` (an exception propagates): what the
    bad-input corpus calls, so that an error a command did not handle counts as a traceback."""
    if argv and argv[0] == "bench":
        # bench modules expose add_bench_arguments(parser) and run_bench(args)
        return _dispatch(BENCHES, argv[1:], "v2xpos bench", "bench_")
    return _dispatch(COMMANDS, argv, "v2xpos", "")


def main(argv: list[str] | None = None) -> int:
    """Run one command; never lets an exception out as a traceback (see the module doc for the
    exit codes). ``V2XPOS_DEBUG=1`` adds the traceback of an unexpected error."""
    as_program = argv is None
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv and argv[0] == "--version":
        print(f"v2xpos {version()}")
        return 0
    rc = _guarded(argv)
    if as_program and argv and COMMANDS.get(argv[0], ("",))[0] in STOPS_CLEANLY:
        # A service has closed its link, outputs and recorder and printed its counters. The
        # interpreter's own shutdown with zenoh's native threads still running took 1-3 s on a
        # loaded machine (past the 1 s a stop may take) and could abort: leave at once instead.
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(rc)
    return rc


def _guarded(argv: list[str]) -> int:
    prog = _prog(argv)
    try:
        return run_command(argv)
    except KeyboardInterrupt:
        print(f"{prog}: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except BrokenPipeError:  # output piped into a command that stopped reading (e.g. head)
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # no second error at exit
        return 1
    except Exception as exc:  # the last line of defence: a message, not a traceback
        return report_unexpected(prog, exc)


def report_unexpected(prog: str, exc: BaseException) -> int:
    """One line for an exception no command handled. OSError (a file, a device, a port) and
    ValueError (a value read from input) are input or environment errors (exit 2); anything else
    is a bug (exit 3)."""
    debug = os.environ.get("V2XPOS_DEBUG", "") not in ("", "0")
    if debug:
        traceback.print_exception(type(exc), exc, exc.__traceback__)
    text = " ".join(str(exc).split()) or type(exc).__name__
    hint = "" if debug else " (V2XPOS_DEBUG=1 shows the traceback)"
    if isinstance(exc, (OSError, ValueError)):
        print(f"{prog}: error: {text}", file=sys.stderr)
        return EXIT_INPUT
    print(f"{prog}: internal error: {type(exc).__name__}: {text}{hint}", file=sys.stderr)
    return EXIT_INTERNAL


if __name__ == "__main__":
    sys.exit(main())
