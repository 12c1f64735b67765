"""``v2xpos calibrate``: options, input checks, the printed summary, the JSON, ``--write-dataset``
and ``--plots`` around ``v2xpos.diagnose.calibrate.calibrate_dataset``."""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from v2xpos.commands.replay import (add_input_arguments, add_profile_argument, add_schedule_arguments, check_only,
                                    command_provenance, load_for_command)
from v2xpos.diagnose.calibrate import calibrate_dataset, to_json
from v2xpos.ins.replay_engine import OutageSchedule


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("dataset", help="dataset.toml of the recording")
    parser.add_argument("--json", help="write the result JSON here ('-': to stdout, the summary then goes to stderr)")
    parser.add_argument("--plots", help="directory for the report (PNG figures + report.md)")
    parser.add_argument("--write-dataset", metavar="OUT.toml",
                        help="write a dataset descriptor: the input's declared tables (paths relative to OUT) "
                             "and a [calibration] table with the effects found")
    add_schedule_arguments(parser)
    add_input_arguments(parser)
    parser.add_argument("--iterations", type=int, default=2, help="Gauss-Newton iterations (default 2)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bars")
    add_profile_argument(parser)


def run(args: argparse.Namespace) -> int:
    """``v2xpos calibrate``: 2 (with the file and key named) when the inputs cannot be used; the
    input warnings go into the JSON (``input_checks``)."""
    ds = load_for_command(args.dataset, "calibrate", args.min_overlap)
    if ds is None:
        return 2
    if args.check:
        return check_only(ds, "calibrate", args.json)
    schedule = OutageSchedule(args.outage_length, args.outage_every, args.outage_first)
    cal = calibrate_dataset(ds, schedule, progress=not args.no_progress, gn_iterations=args.iterations,
                            profile=args.profile)
    out = to_json(cal)
    out["input_checks"] = ds.notes.get("input_check", {})
    out["warnings"] = len(out["input_checks"].get("warnings", []))
    out["provenance"] = command_provenance("calibrate", args)
    text = json.dumps(out, indent=2)
    if args.json == "-":
        print(text)
    elif args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(text + "\n")
    from v2xpos.diagnose.summary import summary_text
    print(summary_text(cal), file=sys.stderr if args.json == "-" else sys.stdout)
    if args.write_dataset:
        from v2xpos.diagnose.writeback import write_dataset
        if ds.source is None:
            print("v2xpos calibrate: --write-dataset needs a dataset loaded from a descriptor (.toml)", file=sys.stderr)
            return 2
        path = write_dataset(ds.source, args.write_dataset, cal.table)
        print(f"calibrated dataset: {path}", file=sys.stderr if args.json == "-" else sys.stdout)
    if args.plots:
        from v2xpos.diagnose.report import write_report
        path = write_report(cal, Path(args.plots))
        print(f"report: {path}", file=sys.stderr)
    return 0
