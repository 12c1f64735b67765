"""``v2xpos convoy MASTER_DATASET SLAVE_DATASET... --out DIR [--speed S]``: recorded vehicles end to end.

Starts ``v2xpos master`` on the first recording and ``v2xpos slave`` on each of the others, as
separate processes talking zenoh over loopback (the master embeds the router on a free
``tcp/127.0.0.1`` port); every process runs the navigation filter on its own recording on its own
GPS time (``v2xpos.sources.recording``): the master leads the session clock once every slave is
ready, the slaves follow it. Target ids are the datasets' ``name``. The master writes
``DIR/results.csv`` (``v2xpos.output.results_csv``); the configs and logs are in ``DIR/configs``
and ``DIR/logs``, the master's summary in ``DIR/master_summary.json``.

``--in-process`` runs the same recordings through the same master pipeline in one process
without a link (each slave state evaluated against the master's state at the same session time):
the reference that shows what processes, link and time handling cost. ``--in-process --smooth``
forms the results from every vehicle's smoothed states instead (``master.smoothed_convoy``,
docs/smoothing.md): ``results.csv`` with a trailing column ``smoothed``, the forward results in
``results_forward.csv``.

``--truth truth_rel.csv`` scores the results (``v2xpos.diagnose.truth``); the vehicles'
``truth.csv`` are taken from beside their datasets when present. The score goes into
``DIR/report.json`` with the run's facts.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from v2xpos.launch import ServiceProcesses, free_tcp_port, free_udp_port, to_toml
from v2xpos.stop_signals import interrupt_on_stop_signals

from master.in_process import STATUS_PERIOD_S, feed_pipeline


class ConvoyError(RuntimeError):
    """A convoy that cannot be started (message names the dataset)."""


def dataset_identity(path: str | Path) -> tuple[Path, str, str]:
    """(descriptor path, name, platform) of a dataset.toml or a folder holding one, without loading it."""
    from v2xpos.datasets.loader import read_descriptor
    p = Path(path)
    if p.is_dir():
        p = p / "dataset.toml"
    if not p.is_file():
        raise ConvoyError(f"{path}: no dataset.toml")
    try:
        desc = read_descriptor(p)
    except ValueError as exc:
        raise ConvoyError(str(exc)) from None
    name = desc.get("name")
    if not isinstance(name, str) or not name:
        raise ConvoyError(f"{p}: field name missing (the convoy uses it as the vehicle id)")
    return p.resolve(), name, str(desc.get("platform", "car"))


def write_configs(out: Path, master: tuple, slaves: list[tuple], speed: float, fleet: str = "convoy",
                  router_port: int | None = None, udp_port: int | None = None, can: bool = True,
                  mcap: bool = False) -> dict[str, Path]:
    """Master and slave TOML files for a recorded convoy in ``out/configs``; returns id -> path. ``out``
    is made absolute: the services resolve their config's paths against the config's directory."""
    out = Path(out).resolve()
    cdir = out / "configs"
    cdir.mkdir(parents=True, exist_ok=True)
    port = router_port or free_tcp_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    mpath, mname, _ = master
    ids = [s[1] for s in slaves]
    mcfg = {"service": {"fleet": fleet, "master_id": mname, "known_vehicles": ids, "status_hz": 2.0, "tick_hz": 10.0},
            "link": {"mode": "router", "listen": [endpoint]},
            "source": {"type": "recording", "dataset": str(mpath), "speed": float(speed), "wait_for": ids},
            "output": {"can": {"enabled": can, "interface": "virtual", "channel": f"v2xpos-convoy-{port}"},
                       "udp": {"enabled": True, "host": "127.0.0.1", "port": udp_port or free_udp_port()},
                       "zenoh": {"enabled": True}},
            "record": {"results_csv": str(out / "results.csv"), "summary_json": str(out / "master_summary.json")}}
    if mcap:
        mcfg["record"]["mcap"] = str(out / "session.mcap")
    paths = {mname: cdir / "master.toml"}
    paths[mname].write_text(to_toml(mcfg))
    for spath, sname, _ in slaves:
        scfg = {"service": {"fleet": fleet, "vehicle_id": sname, "rate_hz": 100.0},
                "link": {"mode": "client", "connect": [endpoint], "connect_timeout_ms": 60000},
                "source": {"type": "recording", "dataset": str(spath)}}
        paths[sname] = cdir / f"slave_{sname}.toml"
        paths[sname].write_text(to_toml(scfg))
    return paths


def _status_watch(fleet: str, master_id: str, port: int):
    """A zenoh client on the master's status key (for progress lines); None if it cannot connect."""
    from v2xpos.link import Link, LinkConfig, LinkUnavailable
    from v2xpos.wire import status_key
    latest: dict = {}
    try:
        link = Link(LinkConfig(mode="client", connect=[f"tcp/127.0.0.1:{port}"], connect_timeout_ms=2000))
    except LinkUnavailable:
        return None, latest

    def on_status(payload: bytes, key: str, att, t_arr: float) -> None:
        try:
            latest.update(json.loads(payload))
        except ValueError:
            pass

    link.subscribe(status_key(fleet, master_id), on_status)
    return link, latest


def run_processes(out: Path, master: tuple, slaves: list[tuple], speed: float, log=None,
                  timeout_s: float | None = None, mcap: bool = False) -> dict:
    """Run the convoy as processes; returns exit codes, durations and the master's summary.
    ``log``: progress lines (default the current ``sys.stderr``)."""
    log = sys.stderr if log is None else log      # resolved per call: a stream bound at import may be closed
    from v2xpos.datasets.loader import load_dataset
    configs = write_configs(out, master, slaves, speed, mcap=mcap)
    from v2xpos.compat import tomllib
    mcfg = tomllib.loads(configs[master[1]].read_text())
    port = int(mcfg["link"]["listen"][0].rsplit(":", 1)[1])
    span = None
    try:
        ds = load_dataset(master[0])
        span = float(ds.imu.t_s[-1] - ds.imu.t_s[0])
    except (OSError, ValueError) as exc:
        raise ConvoyError(str(exc)) from None
    results = out / "results.csv"
    if results.exists():
        results.unlink()
    procs = ServiceProcesses(out / "logs")
    t0 = time.time()
    procs.start(master[1], "master", configs[master[1]])
    for _, sname, _ in slaves:
        procs.start(sname, "slave", configs[sname], nice=5)
    deadline = t0 + (timeout_s if timeout_s is not None else 120.0 + 2.0 * span / speed)
    try:
        with interrupt_on_stop_signals():   # a stop signal stops the services too (see stop_signals)
            _watch_until_done(procs, master, mcfg, port, span, deadline, t0, log)
    finally:
        codes = procs.stop(grace_s=10.0, order=[master[1]] + [s[1] for s in slaves])
    summary = {}
    if (out / "master_summary.json").is_file():
        summary = json.loads((out / "master_summary.json").read_text())
    return {"exit_codes": codes, "wall_s": time.time() - t0, "master_summary": summary}


def _watch_until_done(procs: ServiceProcesses, master: tuple, mcfg: dict, port: int, span: float | None,
                      deadline: float, t0: float, log) -> None:
    """Until the master ends or the deadline: fail on a slave that exits with an error, print
    progress from the master's status every ``STATUS_PERIOD_S``."""
    watch, latest = None, {}
    try:
        next_line = time.time() + STATUS_PERIOD_S
        while time.time() < deadline:
            if procs.procs[master[1]].poll() is not None:
                break
            dead = [k for k in procs.running()]
            if len(dead) < len(procs.procs) and procs.procs[master[1]].poll() is None:
                failed = [k for k, p in procs.procs.items() if p.poll() not in (None, 0)]
                if failed:
                    raise ConvoyError(f"{failed[0]} exited with code {procs.procs[failed[0]].returncode}:\n"
                                      f"{procs.log_tail(failed[0])}")
            if watch is None and time.time() - t0 > 1.0:
                watch, latest = _status_watch(mcfg["service"]["fleet"], master[1], port)
            if time.time() >= next_line:
                next_line += STATUS_PERIOD_S
                if latest.get("t_rel_s") is not None and latest.get("phase") == "run":
                    done = max(0.0, min(1.0, latest["t_rel_s"] / span)) if span else 0.0
                    print(f"convoy: {100 * done:5.1f} % of {span:.0f} s, results {latest.get('processed', 0)}, "
                          f"targets {sorted(latest.get('targets', {}))}", file=log, flush=True)
                else:
                    print(f"convoy: starting ({latest.get('phase', 'loading')})", file=log, flush=True)
            time.sleep(0.2)
        else:
            print("convoy: time limit reached, stopping", file=log, flush=True)
    finally:
        if watch is not None:
            watch.close()


def run_in_process(out: Path, master: tuple, slaves: list[tuple], rate_hz: float = 100.0, log=None,
                   smooth: bool = False) -> dict:
    """The same recordings through the same pipeline in one process, no link: every slave state is
    evaluated against the master's state at the same session time (latency 0). Writes results.csv.
    ``smooth``: from every vehicle's smoothed states instead (``master.smoothed_convoy``). ``log``:
    progress lines (default the current ``sys.stderr``)."""
    log = sys.stderr if log is None else log      # resolved per call: a stream bound at import may be closed
    if smooth:
        from master.smoothed_convoy import run_in_process_smoothed
        return run_in_process_smoothed(out, master, slaves, rate_hz, log)
    from v2xpos.output.results_csv import ResultsCsvWriter
    from v2xpos.sources.recording import RecordingSource
    out.mkdir(parents=True, exist_ok=True)
    msrc = RecordingSource(master[0], sync="none")
    ssrc = {s[1]: RecordingSource(s[0], sync="none") for s in slaves}
    sink = ResultsCsvWriter(out / "results.csv")
    try:
        return feed_pipeline(sink, master[1], msrc, ssrc, rate_hz, log)
    finally:
        sink.close()


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("datasets", nargs="+", metavar="DATASET",
                        help="the master's dataset.toml, then one per slave")
    parser.add_argument("--out", required=True, help="output directory (results.csv, configs, logs, report.json)")
    parser.add_argument("--speed", type=float, default=1.0, help="replay speed (default 1.0: real time)")
    parser.add_argument("--truth", help="truth_rel.csv of the recordings: score the results against it")
    parser.add_argument("--in-process", action="store_true",
                        help="run the recordings through the pipeline in one process (reference, no link)")
    parser.add_argument("--smooth", action="store_true",
                        help="with --in-process: relative results from every vehicle's smoothed states "
                             "(results.csv with a trailing column smoothed; the forward ones in results_forward.csv)")
    parser.add_argument("--mcap", action="store_true", help="also record the session (DIR/session.mcap)")


def run(args: argparse.Namespace) -> int:
    if len(args.datasets) < 2:
        print("v2xpos convoy: need the master's dataset and at least one slave's", file=sys.stderr)
        return 2
    if not 0 < args.speed <= 100:
        print(f"v2xpos convoy: --speed {args.speed} outside (0, 100]", file=sys.stderr)
        return 2
    out = Path(args.out).resolve()   # the services resolve config paths against the config's directory
    try:
        idents = [dataset_identity(p) for p in args.datasets]
        names = [i[1] for i in idents]
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise ConvoyError(f"dataset name(s) {dup} used twice: the convoy uses each dataset's name as its id")
        out.mkdir(parents=True, exist_ok=True)
        master, slaves = idents[0], idents[1:]
        print(f"convoy: master {master[1]} ({master[0]}), slaves {[s[1] for s in slaves]}, speed {args.speed}",
              file=sys.stderr, flush=True)
        t0 = time.time()
        if args.smooth and not args.in_process:
            raise ConvoyError("--smooth needs --in-process (the smoother runs after each whole recording)")
        if args.in_process:
            facts = run_in_process(out, master, slaves, smooth=args.smooth)
        else:
            facts = run_processes(out, master, slaves, args.speed, mcap=args.mcap)
    except ConvoyError as exc:
        print(f"v2xpos convoy: {exc}", file=sys.stderr)
        return 2
    report = {"master": master[1], "slaves": [s[1] for s in slaves], "speed": args.speed,
              "in_process": bool(args.in_process), "smoothed": bool(args.smooth), "wall_s": time.time() - t0,
              "results_csv": str(out / "results.csv"), **facts}
    rc = 0
    codes = facts.get("exit_codes", {})
    if any(c not in (0, None) for c in codes.values()):
        print(f"v2xpos convoy: a service failed: {codes} (logs in {out / 'logs'})", file=sys.stderr)
        rc = 1
    if args.truth:
        from v2xpos.diagnose.truth import format_score, score_results_csv
        vehicle_truth = {i[1]: i[0].parent / "truth.csv" for i in idents}
        try:
            report["score"] = score_results_csv(out / "results.csv", args.truth, vehicle_truth, master[1])
            print(format_score(report["score"]), file=sys.stderr)
        except (OSError, ValueError) as exc:
            print(f"v2xpos convoy: cannot score against {args.truth}: {exc}", file=sys.stderr)
            rc = rc or 2
    (out / "report.json").write_text(json.dumps(report, indent=1, default=str))
    print(f"convoy: results {out / 'results.csv'}, report {out / 'report.json'}", file=sys.stderr)
    return rc
