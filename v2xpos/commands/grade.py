"""``v2xpos grade``: grade the IMU units of a multi-IMU recording (``v2xpos.quality.recording``).

    v2xpos grade CONFIG_OR_DIR [--reference UNIT] [--json FILE] [--plots DIR] [--check]
    (simulated vehicles: ``v2xpos bench grading faults|lidar``, bench/grading.py)

Prints one line per unit; ``--json`` writes the report as strict JSON with its provenance;
``--check`` only checks the inputs. Exit 0: every unit passes or warns; 1: a unit fails; 2: bad input.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import TextIO

import numpy as np

from v2xpos.quality.grader import public_report
from v2xpos.quality.recording import grade_recording, prepare_recording
from v2xpos.quality.unit_comparison import GradeConfig


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("path", nargs="?", help="quadrotor_mimu path folder or dataset toml")
    parser.add_argument("--reference", help="reference unit id (default: the unit agreeing best with the others)")
    parser.add_argument("--json", type=Path, help="write the report as JSON to this file")
    parser.add_argument("--plots", type=Path, help="write PNG figures to this folder")
    parser.add_argument("--window-s", type=float, default=None, help="sliding window length [s] (default 1)")
    parser.add_argument("--step-s", type=float, default=None, help="sliding window step [s] (default 0.5)")
    parser.add_argument("--no-fusion", action="store_true", help="skip the second parameter (fused differences)")
    parser.add_argument("--check", action="store_true",
                        help="only check the inputs (files, [grade] table, each unit's coverage): exit 2 "
                             "on an error, 0 otherwise (warnings printed and in --json)")


def _json_default(o):
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.floating, np.integer, np.bool_)):
        return o.item()
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def _finite(o):
    """Replace non-finite floats by None (strict JSON), recursively."""
    if isinstance(o, dict):
        return {k: _finite(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_finite(v) for v in o]
    if isinstance(o, np.ndarray):
        return _finite(o.tolist())
    if isinstance(o, (float, np.floating)):
        return float(o) if np.isfinite(o) else None
    return o


def write_report_json(path: Path, obj: dict, args: argparse.Namespace | None = None) -> None:
    """The report as strict JSON, with a ``provenance`` object (``v2xpos.provenance``: the graded
    recording's descriptor hash, the options, seeds of a simulation)."""
    if args is not None:
        from v2xpos.provenance import provenance
        configs: dict = {"options": {k: (str(v) if isinstance(v, Path) else v) for k, v in sorted(vars(args).items())
                                     if k not in ("path", "json", "plots")}}
        if args.path:
            p = Path(args.path)
            configs["recording"] = p if p.is_file() else str(p)
        seeds = {"seeds": list(range(args.seeds))} if getattr(args, "seeds", None) else None
        obj = {**obj, "provenance": provenance("grade", configs, seeds=seeds)}
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(_finite(obj), indent=1, default=_json_default, allow_nan=False))
    print(f"wrote {path}")



def print_table(report: dict, out: TextIO | None = None) -> None:
    """One line per unit: grade, gyro RMSE and PCC per axis, clock offset, rotation, failed checks."""
    out = out or sys.stdout
    print(f"reference: {report['reference']} ({report['reference_chosen']}), {report['n_units']} units, "
          f"{report['duration_s']:.1f} s", file=out)
    print(f"{'unit':<8} {'grade':<5} {'gyro RMSE x/y/z [dps]':<23} {'gyro PCC x/y/z':<21} "
          f"{'dt [ms]':>7}  {'rotation XYZ [deg]':<22} {'fused att/pos P90':<18} {'rate chk':<9} notes", file=out)
    for u in report["units"]:
        rm = "/".join(f"{v:.2f}" for v in u["rmse"]["gyro"])
        pc = "/".join("-" if v is None else f"{v:.3f}" for v in u["pcc"]["gyro"])
        rot = "/".join(f"{v:.2f}" for v in u["relative_rotation"]["euler_xyz_deg"])
        fd = u.get("fused_diff")
        fds = f"{fd['att_deg']['p90']:.2f} deg/{fd['pos_m']['p90']:.2f} m" if fd else "-"
        notes = ", ".join(f"{c['name']}={c['value']:.3g} {c['grade']}" for c in u["checks"]
                          if c["grade"] != "pass" and c["value"] is not None)
        tag = " (ref)" if u["reference"] else ""
        rc = u.get("rate_check")
        rcs = f"{100 * rc['relative_diff']:+.2f}%" if rc else "-"
        print(f"{u['id'] + tag:<8} {u['grade']:<5} {rm:<23} {pc:<21} {u['time_offset_ms']:7.2f}  "
              f"{rot:<22} {fds:<18} {rcs:<9} {notes}", file=out)



def run(args: argparse.Namespace) -> int:
    cfg = GradeConfig()
    if args.window_s:
        cfg.window_s = args.window_s
    if args.step_s:
        cfg.step_s = args.step_s
    if not args.path:
        print("v2xpos grade: give CONFIG_OR_DIR (simulated vehicles: v2xpos bench grading faults|lidar)",
              file=sys.stderr)
        return 2
    if args.check:
        try:
            prep = prepare_recording(args.path, args.reference, cfg)
        except (ValueError, OSError) as exc:
            print(f"v2xpos grade: {' '.join(str(exc).split())}", file=sys.stderr)
            return 2
        cov = prep["coverage"]
        for w in cov["warnings"]:
            print(f"v2xpos grade: warning: {w}", file=sys.stderr)
        print(f"v2xpos grade: inputs OK: {len(prep['rec'].units)} units, common span {cov['common_s']:.1f} s "
              f"of {cov['recording_s']:.1f} s, {len(cov['warnings'])} warning(s)")
        if args.json:
            write_report_json(args.json, {"recording": prep["rec"].name, "coverage": cov, "warnings": cov["warnings"]})
        return 0
    try:
        rep = grade_recording(args.path, args.reference, cfg, fusion=not args.no_fusion)
    except (ValueError, OSError) as exc:
        print(f"v2xpos grade: {' '.join(str(exc).split())}", file=sys.stderr)
        return 2
    for w in rep.get("warnings", []):
        print(f"v2xpos grade: warning: {w}", file=sys.stderr)
    print_table(rep)
    if args.plots:
        from v2xpos.quality.plots import plot_first_parameter
        for p in plot_first_parameter(rep["_comparison"], rep["reference"], args.plots, cfg):
            print(f"wrote {p}")
    if args.json:
        write_report_json(args.json, public_report(rep), args)
    return 0 if all(u["grade"] != "fail" for u in rep["units"]) else 1
