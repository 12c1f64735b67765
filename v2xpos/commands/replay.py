"""``v2xpos replay``: options, input checks and the printed summary; the input-check helpers
(``load_for_command``, ``check_only``, ...) are shared with ``v2xpos calibrate``.

Inputs are checked before the run (``load_for_command``: descriptor, files, and the plausibility
checks of ``v2xpos.datasets.checks``): an error stops the command with exit code 2 and a message
naming the file and the key; warnings are printed and carried in the summary (``input_checks``).
The replay is ``v2xpos.ins.replay.replay``, its metrics those of ``v2xpos.ins.replay_metrics``.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from v2xpos.ins.replay import replay
from v2xpos.ins.replay_engine import OutageSchedule
from v2xpos.types import Dataset


def add_schedule_arguments(parser: argparse.ArgumentParser) -> None:
    """The outage-schedule options shared by ``v2xpos replay`` and ``v2xpos calibrate``."""
    parser.add_argument("--outage-length", type=float, default=15.0, help="outage length [s] (default 15)")
    parser.add_argument("--outage-every", type=float, default=45.0, help="outage period [s] (default 45)")
    parser.add_argument("--outage-first", type=float, default=40.0,
                        help="start of the first outage after the first GNSS epoch [s] (default 40)")


def schedule_from_args(args: argparse.Namespace) -> OutageSchedule:
    """OutageSchedule from the options of ``add_schedule_arguments``."""
    return OutageSchedule(args.outage_length, args.outage_every, args.outage_first)


def add_input_arguments(parser: argparse.ArgumentParser) -> None:
    """Input-check options shared by ``v2xpos replay`` and ``v2xpos calibrate``."""
    from v2xpos.datasets.checks import MIN_OVERLAP_SHARE
    parser.add_argument("--check", action="store_true",
                        help="only check the inputs (descriptor, files, time overlap, mounting against "
                             "gravity, rates and gaps): exit 2 on an error, 0 otherwise")
    parser.add_argument("--min-overlap", type=float, default=MIN_OVERLAP_SHARE,
                        help="least share of the recording that IMU and GNSS must have in common "
                             f"(default {MIN_OVERLAP_SHARE})")


def load_for_command(path: str, command: str, min_overlap_share: float | None = None) -> Dataset | None:
    """Load a dataset for a command and check it (``v2xpos.datasets.checks``). On an error print
    one line per problem (naming the file and the key) and return None; print the warnings, keep
    the check in ``notes["input_check"]`` for the report, and drop GNSS epochs the IMU does not
    cover (``restrict_to_imu_coverage``)."""
    from v2xpos.datasets import load_dataset
    from v2xpos.datasets.checks import MIN_OVERLAP_SHARE, check_dataset, restrict_to_imu_coverage
    import logging
    loader_log = logging.getLogger("v2xpos.datasets.loader")
    level = loader_log.level
    loader_log.setLevel(logging.ERROR)   # the checks below restate its warnings, in the report too
    try:
        ds = load_dataset(path)
    except (OSError, ValueError) as e:
        msg = " ".join(str(e).split())
        print(f"v2xpos {command}: cannot load {msg if str(path) in msg else f'{path}: {msg}'}",
              file=sys.stderr)
        return None
    finally:
        loader_log.setLevel(level)
    chk = check_dataset(ds, MIN_OVERLAP_SHARE if min_overlap_share is None else min_overlap_share)
    for f in chk.errors:
        print(f"v2xpos {command}: {f.message}", file=sys.stderr)
    if chk.errors:
        return None
    ds, dropped = restrict_to_imu_coverage(ds)
    if dropped:
        chk.add("warning", "overlap", f"{chk.source}: {dropped} GNSS epoch(s) outside the IMU's span not used")
    for f in chk.warnings:
        print(f"v2xpos {command}: warning: {f.message}", file=sys.stderr)
    ds.notes["input_check"] = chk.as_dict()
    return ds


def note_warning(summary: dict, command: str, message: str) -> None:
    """Print a warning found while running and add it to the summary's ``input_checks``."""
    print(f"v2xpos {command}: warning: {message}", file=sys.stderr)
    summary.setdefault("input_checks", {}).setdefault("warnings", []).append(message)
    summary["warnings"] = len(summary["input_checks"]["warnings"])


def check_only(ds: Dataset, command: str, json_path: str | None) -> int:
    """``--check``: the inputs passed (errors were already reported); print the summary."""
    chk = ds.notes.get("input_check", {})
    rates = chk.get("rates", {})
    ov = chk.get("overlap") or {}
    print(f"v2xpos {command}: inputs OK: {ds.name}, {len(ds.imu)} IMU samples "
          f"({rates.get('imu_rate_hz') or float('nan'):.1f} Hz), {len(ds.gnss)} GNSS epochs "
          f"({rates.get('gnss_rate_hz') or float('nan'):.1f} Hz), IMU/GNSS overlap "
          f"{100 * ov.get('share', float('nan')):.0f} %, {len(chk.get('warnings', []))} warning(s)")
    if json_path:
        Path(json_path).parent.mkdir(parents=True, exist_ok=True)
        Path(json_path).write_text(json.dumps({"dataset": ds.name, "input_checks": chk}, indent=2))
    return 0


def command_provenance(command: str, args: argparse.Namespace) -> dict:
    """``v2xpos.provenance`` object of a dataset command: the dataset descriptor's hash (its
    ``dataset.toml``; a directory without one: path only) and the command's options."""
    from v2xpos.provenance import provenance
    ds = Path(args.dataset)
    descriptor = ds / "dataset.toml" if ds.is_dir() and (ds / "dataset.toml").is_file() else ds
    options = {k: v for k, v in sorted(vars(args).items()) if k not in ("dataset", "func") and not callable(v)}
    return provenance(command, {"dataset": descriptor, "options": options})


SMOOTHED_KEYS = ("inside_outage_epochs", "inside_outage_h_rms_m", "inside_outage_h_max_m", "inside_outage_within_3sd",
                 "smoothed_outage_h_rms_m", "smoothed_outage_h_max_m", "smoothed_inside_outage_h_rms_m",
                 "smoothed_inside_outage_h_max_m", "smoothed_inside_outage_v_rms_m", "smoothed_inside_outage_within_3sd")
"""The summary lines ``--smooth`` adds (``v2xpos.ins.replay_smoothing``)."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``v2xpos replay``."""
    parser.add_argument("dataset", help="dataset.toml (or a dataset directory, e.g. a comma2k19 segment)")
    add_schedule_arguments(parser)
    add_input_arguments(parser)
    parser.add_argument("--json", help="write the summary JSON here")
    parser.add_argument("--plots", help="write PNG plots into this directory")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.add_argument("--solution", metavar="FILE",
                        help="write the per-epoch solution (time, position, velocity, attitude, sigmas, fix, "
                             "effect states) to FILE: .csv or .mcap")
    parser.add_argument("--solution-hz", type=float, default=None,
                        help="solution output rate [Hz] (default: every GNSS epoch, the filter's own epochs)")
    parser.add_argument("--smooth", action="store_true",
                        help="also smooth the whole recording (Rauch-Tung-Striebel backward pass, docs/smoothing.md): "
                             "the outages scored forward and smoothed, at their ends and at every RTK-fixed epoch "
                             "inside them; --solution writes the smoothed solution (column smoothed)")
    add_profile_argument(parser)


def add_profile_argument(parser: argparse.ArgumentParser) -> None:
    """``--profile``, shared by ``v2xpos replay`` and ``v2xpos calibrate`` (``v2xpos.ins.profiles``)."""
    from v2xpos.ins.profiles import DEFAULT_PROFILE
    parser.add_argument("--profile", choices=("service", "plain"), default=DEFAULT_PROFILE,
                        help="filter profile: service (default, the filter the services run) or plain "
                             "(without its integrity machinery: configured IMU noise, no reopening, no "
                             "fault-tolerant solution, no gyro-scale state)")


def run(args: argparse.Namespace) -> int:
    """``v2xpos replay``: print the summary, optionally write the JSON and plots; 2 if the inputs
    cannot be used (the message names the file and the key)."""
    ds = load_for_command(args.dataset, "replay", args.min_overlap)
    if ds is None:
        return 2
    if args.check:
        return check_only(ds, "replay", args.json)
    sched = schedule_from_args(args)
    writer = None
    if args.solution:
        from v2xpos.ins.solution import SolutionWriter
        if args.solution_hz is not None and not args.solution_hz > 0:
            print("v2xpos replay: --solution-hz must be > 0", file=sys.stderr)
            return 2
        try:
            writer = SolutionWriter(args.solution, ("smoothed",) if args.smooth else ())
        except (OSError, ValueError) as exc:
            print(f"v2xpos replay: {exc}", file=sys.stderr)
            return 2
    try:
        res = replay(ds, sched, progress=not args.no_progress, solution=writer, solution_hz=args.solution_hz,
                     profile=args.profile, smooth=args.smooth)
    finally:
        if writer is not None:
            writer.close()
    if writer is not None:
        print(f"{'solution':>20}: {writer.rows} epochs -> {args.solution}")
    if res.summary["outage_count"] == 0:
        note_warning(res.summary, "replay",
                     f"{ds.source or ds.name}: no outage was scored ({res.summary['outages_skipped_no_imu']} "
                     "scheduled outage(s) not covered by the IMU); the recording may be shorter than "
                     "--outage-first + --outage-length")
    keys = ("dataset", "profile", "imu_samples", "gnss_epochs", "malformed_lines", "warnings", "outage_count",
            "outages_skipped_no_imu", "outage_h_rms_m",
            "outage_h_max_m", "outage_v_rms_m", "aided_h_rms_m", "aided_h_rms_steady_m", "wall_s",
            "imu_samples_per_s",
            "reference_h_rms_m") + (SMOOTHED_KEYS if args.smooth else ())
    for k in keys:
        if k in res.summary:
            v = res.summary[k]
            print(f"{k:>20}: {v:.4g}" if isinstance(v, float) else
                  f"{k:>20}: {'n/a' if v is None else v}")
    if args.smooth:
        sm = res.summary["smoothing"]
        print(f"{'smoothing':>20}: {sm['nodes']} nodes in {sm['segments']} segment(s), {sm['stored_mib']:.1f} MiB "
              f"stored, backward pass {sm['backward_s']:.2f} s after the forward {sm['forward_s']:.2f} s")
    eff = res.summary["effects"]
    print(f"{'effects':>20}: time offset {eff['imu_time_offset_s'] * 1e3:.1f} ms, lever arm "
          f"{np.round(eff['lever_arm_m'], 3).tolist()} m, misalignment "
          f"{np.round(np.degrees(eff['misalignment_rad']), 2).tolist()} deg")
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps({**res.summary, "provenance": command_provenance("replay", args)},
                                              indent=2))
    if args.plots:
        from v2xpos.ins.replay_plots import write_plots
        for p in write_plots(res, args.plots):
            print(f"{'plot':>20}: {p}")
    return 0

