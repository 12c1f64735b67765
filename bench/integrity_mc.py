"""Monte-Carlo of the master's integrity figures over generated convoy recordings (issue 15).

For every (preset, seed[, mounting]) case: ``sim.recordings`` writes a recording of the convoy_dev
kind (cached under ``--work``), the pair goes through ``v2xpos convoy --in-process`` (the master
pipeline in one process, ``master.convoy.run_in_process``) and the results are scored
against the truth (``v2xpos.diagnose.truth``). One line per case and the pooled figures:

* VALID fraction; its share of the time both cars move, next to the share of that time after both
  have turned (``v2xpos.diagnose.truth.HEADING_CHANGE_DEG``: the most a set-up never verified can
  be VALID, since before a heading change no data depends on its lever arm);
* h RMS while both move, the largest |mean| per axis (a bias);
* within 3 sd x / y, normalised RMS x / y (1 for an honest sigma);
* median sigma_h over the h RMS (issue 15: <= 3 on a clean pair; the summary gives its largest);
* violations: VALID rows with h error > max(0.3 m, 4 sigma_h) (issue 15: none).

    python -m bench.integrity_mc --presets clean,dev_like --seeds 0-9 [--mounting B=x-backward/z-up]
        [--effect B.lever_arm_error_m=0.8,0,0] [--route drive_off_radius_m=12]
        [--real ../shared/data/convoy_dev] [--json out.json]

Run it with ``nice -n 10`` on a shared machine (about 15 s of CPU per case).
"""
from __future__ import annotations

import argparse
import io
import json
import math
import sys
import time
from pathlib import Path

import numpy as np


def _seeds(text: str) -> list[int]:
    out: list[int] = []
    for part in text.split(","):
        a, _, b = part.partition("-")
        out.extend(range(int(a), int(b) + 1) if b else [int(a)])
    return out


def make_recording(work: Path, preset: str, seed: int, mountings: list[str], effects: list[str],
                   floats: list[str], routes: list[str] = ()) -> Path:
    """The recording of one case (generated once, then reused)."""
    from sim.recordings import apply_overrides, draw_params, simulate, write
    tag = "_".join(x.replace("/", "-").replace("=", "-").replace(",", "_")
                   for x in [*mountings, *effects, *floats, *routes])
    d = work / f"{preset}_s{seed}{'_' + tag if tag else ''}"
    if not (d / "truth_rel.csv").is_file():
        p = draw_params(seed, preset)
        apply_overrides(p, mountings, effects, floats, routes)
        write(simulate(p), d)
    return d


def prepared(rec: Path, work: Path, verified: bool = False, calibrate: bool = False) -> tuple[Path, Path]:
    """The dataset.toml of A and B as the case runs them: as recorded; with ``verified`` each with
    the ``[verification]`` record its own drive gives (a set-up verified on an earlier drive of the
    same vehicle: ``diagnose.writeback.verification_of``); with ``calibrate`` the follower's
    ``calibrate --write-dataset`` descriptor (its ``[calibration]`` and ``[verification]``)."""
    a, b = rec / "A" / "dataset.toml", rec / "B" / "dataset.toml"
    if not (verified or calibrate):
        return a, b
    from v2xpos.diagnose.writeback import verification_of, write_dataset
    work.mkdir(parents=True, exist_ok=True)
    out = []
    for name, src in (("A", a), ("B", b)):
        dst = work / f"{name}.toml"
        if calibrate and name == "B":
            if not dst.is_file():
                from v2xpos.datasets.loader import load_dataset
                from v2xpos.diagnose.calibrate import calibrate_dataset
                from v2xpos.ins.replay_engine import OutageSchedule
                cal = calibrate_dataset(load_dataset(src), OutageSchedule(), progress=False)
                write_dataset(src, dst, cal.table, verify=True)
        elif not dst.is_file():
            import tomli_w
            from v2xpos.datasets.loader import read_descriptor
            from v2xpos.diagnose.writeback import PATH_KEYS, _rebased
            desc = read_descriptor(src)
            desc.pop("verification", None)
            for tab, key in PATH_KEYS:
                t = desc if not tab else desc.get(tab)
                if isinstance(t, dict) and isinstance(t.get(key), str):
                    t[key] = _rebased(t[key], src.parent, dst.parent)
            record = verification_of(src) if verified else None
            dst.write_text(tomli_w.dumps(desc) + ("\n" + record.to_toml() if record is not None else ""))
        out.append(dst)
    return out[0], out[1]


def run_case(rec: Path, out: Path, verified: bool = False, calibrate: bool = False) -> dict:
    """In-process convoy of ``rec`` (A master, B slave) scored against its truth."""
    from master.convoy import dataset_identity, run_in_process
    from v2xpos.diagnose.truth import score_results_csv
    a_toml, b_toml = prepared(rec, out / "datasets", verified, calibrate)
    a, b = dataset_identity(a_toml), dataset_identity(b_toml)
    out.mkdir(parents=True, exist_ok=True)
    run_in_process(out, a, [b], log=io.StringIO())
    score = score_results_csv(out / "results.csv", rec / "truth_rel.csv",
                              {a[1]: rec / "A" / "truth.csv", b[1]: rec / "B" / "truth.csv"}, a[1])
    return score["targets"][b[1]]


def brief(s: dict) -> dict:
    """The figures of one scored target that the table shows."""
    mv = s["moving"]
    bias = max(abs(mv["x_mean_m"] or 0.0), abs(mv["y_mean_m"] or 0.0)) if mv["n"] else None
    return {"valid": s["valid_fraction"], "valid_moving": s.get("moving_valid_fraction"),
            "first_valid_s": s.get("time_to_first_valid_s"), "after_turn": s.get("moving_after_turn_fraction"),
            "turn_s": s.get("time_to_turn_s"), "n_moving": mv["n"], "h_rms_m": mv["h_rms_m"], "bias_m": bias,
            "in3x": s.get("within_3sd_x"), "in3y": s.get("within_3sd_y"), "nrms_x": s.get("normalised_rms_x"),
            "nrms_y": s.get("normalised_rms_y"), "sig_ratio": s.get("median_sigma_h_over_h_rms"),
            "sigma_h_m": s.get("median_sigma_h_m"), "violations": s.get("violations", 0),
            "statuses": s["status_counts"]}


def _f(v, d: int = 3) -> str:
    return "-" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:.{d}f}"


def _pct(v: float | None) -> str:
    return _f(100 * v, 1) if v is not None else "-"


def line(name: str, b: dict) -> str:
    return (f"{name:34s} VALID {_pct(b['valid']):>5s} % (moving {_pct(b['valid_moving']):>5s} % of "
            f"{_pct(b.get('after_turn')):>5s} % after both turned at {_f(b.get('turn_s'), 1):>5s} s, "
            f"first after {_f(b['first_valid_s'], 1):>5s} s)  hRMS {_f(b['h_rms_m'])}  bias {_f(b['bias_m'])}  "
            f"in3sd {_f(b['in3x'])}/{_f(b['in3y'])}  nRMS {_f(b['nrms_x'], 2)}/{_f(b['nrms_y'], 2)}  "
            f"sig_h {_f(b['sigma_h_m'])} ({_f(b['sig_ratio'], 1)}x)  viol {b['violations']}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--presets", default="clean,dev_like")
    ap.add_argument("--seeds", default="0-9")
    ap.add_argument("--mounting", action="append", default=[])
    ap.add_argument("--effect", action="append", default=[])
    ap.add_argument("--float", action="append", default=[])
    ap.add_argument("--route", action="append", default=[], help="a route override, e.g. drive_off_radius_m=12")
    ap.add_argument("--real", action="append", default=[], help="a recording folder with A/, B/, truth_rel.csv")
    ap.add_argument("--work", default="/tmp/v2xpos-integrity-mc")
    ap.add_argument("--json", help="write every case's figures here")
    ap.add_argument("--verified", action="store_true",
                    help="every vehicle starts with the [verification] record of its own drive (verified before)")
    ap.add_argument("--calibrate", action="store_true",
                    help="the follower runs with its calibrate --write-dataset table (and verification record)")
    args = ap.parse_args(argv)
    work = Path(args.work)
    cases: list[tuple[str, Path]] = [(Path(r).name, Path(r)) for r in args.real]
    for preset in [p for p in args.presets.split(",") if p]:
        for seed in _seeds(args.seeds):
            cases.append((f"{preset} s{seed}", make_recording(work / "rec", preset, seed, args.mounting,
                                                              args.effect, args.float, args.route)))
    rows = {}
    for name, rec in cases:
        t0 = time.time()
        mode = "_verified" if args.verified else ""
        mode += "_calibrated" if args.calibrate else ""
        b = brief(run_case(rec, work / "out" / (rec.name + mode), args.verified, args.calibrate))
        rows[name] = b
        print(line(name, b) + f"  ({time.time() - t0:.0f} s)", flush=True)
    by_preset: dict = {}
    for name, b in rows.items():
        by_preset.setdefault(name.split(" ")[0], []).append(b)
    for preset, bs in by_preset.items():
        h = [b["h_rms_m"] for b in bs if b["h_rms_m"] is not None]
        ratios = [b["sig_ratio"] for b in bs if b["sig_ratio"]]
        mvs = [b["valid_moving"] for b in bs if b["valid_moving"] is not None]
        fv = [b["first_valid_s"] for b in bs if b["first_valid_s"] is not None]
        turned = [b["after_turn"] for b in bs if b.get("after_turn") is not None]
        print(f"{preset}: cases {len(bs)}, h RMS median {_f(float(np.median(h)) if h else None)} max "
              f"{_f(max(h) if h else None)}, min in3sd {_f(min(min(b['in3x'] or 0, b['in3y'] or 0) for b in bs))}, "
              f"sigma ratio median {_f(float(np.median(ratios)) if ratios else None, 1)} "
              f"max {_f(max(ratios) if ratios else None, 1)}, "
              f"violations {sum(b['violations'] for b in bs)}, VALID median "
              f"{_f(100 * float(np.median([b['valid'] for b in bs])), 1)} % min {_f(100 * min(b['valid'] for b in bs), 1)} %, "
              f"VALID while moving median {_f(100 * float(np.median(mvs)) if mvs else None, 1)} % "
              f"min {_f(100 * min(mvs) if mvs else None, 1)} % (after both turned: largest "
              f"{_f(100 * max(turned) if turned else None, 1)} %), first VALID after max "
              f"{_f(max(fv) if fv else None, 1)} s")
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
