"""``v2xpos evaluate --reference RESULTS --sensor OBJECTS --sensor-config SENSOR.toml --out DIR``:
the sensor under test against the v2xpos reference (``v2xpos.evaluate``, ``docs/evaluate.md``).

Exit codes: 0 done; 2 bad input (a file that cannot be read, an unknown or misspelt SENSOR.toml key,
a DBC without the mapped signals, no time overlap) -- the message names the file and the key, and
nothing is written to DIR.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--reference", required=True, metavar="RESULTS",
                        help="results.csv (a master's, v2xpos convoy's, or smoothed) or a session MCAP")
    parser.add_argument("--sensor", required=True, metavar="OBJECTS",
                        help="the sensor's object list: .csv, or a CAN log .asc / .blf / .mf4 (with [can] in SENSOR.toml)")
    parser.add_argument("--sensor-config", required=True, metavar="SENSOR.toml", help="what is declared about the sensor")
    parser.add_argument("--out", required=True, metavar="DIR",
                        help="output directory: metrics.json, matches.csv, plots, report.html")
    parser.add_argument("--no-plots", action="store_true", help="metrics.json and matches.csv only (no figures, no HTML)")


def run(args: argparse.Namespace) -> int:
    from v2xpos.evaluate.config import SensorConfigError, load_sensor_config
    from v2xpos.evaluate.evaluation import evaluate
    from v2xpos.evaluate.objects import read_objects
    from v2xpos.evaluate.reference import read_reference
    from v2xpos.evaluate.report import summary_text, write_outputs
    t0 = time.time()
    try:
        cfg = load_sensor_config(args.sensor_config)
        objs = read_objects(args.sensor, cfg)
        ref = read_reference(args.reference)
        ev = evaluate(objs, ref, cfg)
    except (SensorConfigError, ValueError, OSError) as exc:
        print(f"v2xpos evaluate: {exc}", file=sys.stderr)
        return 2
    inputs = {"reference": args.reference, "sensor": args.sensor, "sensor_config": args.sensor_config}
    if cfg.can is not None and Path(args.sensor).suffix.lower() != ".csv":
        inputs["dbc"] = str(cfg.can.dbc)
    out = write_outputs(ev, Path(args.out), inputs, objs.fmt, plots=not args.no_plots)
    print(summary_text(ev.metrics))
    print(f"wrote {out} in {time.time() - t0:.1f} s")
    return 0
