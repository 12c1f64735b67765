"""``v2xpos bench smoothing-memory [--duration 3600] [--recording DATASET_TOML] [--keep DIR]``: peak
memory of ``v2xpos replay --smooth --solution`` on a long recording (issue 32: a one-hour recording
at 100 Hz within 1 GiB).

Without ``--recording`` it generates one (``sim.recordings.generate_convoy``: preset ``clean``,
``--duration`` seconds, IMU at 100 Hz, GNSS at 10 Hz, vehicle A). It then runs, each in its own
child process so that nothing else shares the figure, the plain forward replay and the smoothed
replay with the smoothed solution written to a CSV (every GNSS epoch), and prints each process's
peak resident set size (``VmHWM`` of /proc/self/status, which the child writes at its end: the
high-water mark of its own address space -- ``ru_maxrss`` would include the memory the child had
before ``exec``, a copy of this process's), the smoother's stored bytes, the times and the
inside-outage figures.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

LIMIT_MIB = 1024.0


def add_bench_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``v2xpos bench smoothing-memory``."""
    parser.add_argument("--duration", type=float, default=3600.0, help="generated recording length [s] (default 3600)")
    parser.add_argument("--seed", type=int, default=5, help="seed of the generated recording (default 5)")
    parser.add_argument("--recording", help="use this dataset.toml instead of generating one")
    parser.add_argument("--keep", help="keep the generated recording and the outputs in this directory")
    parser.add_argument("--json", help="write the figures to this JSON file")


CHILD = """
import os, runpy, sys
sys.argv = ["v2xpos"] + sys.argv[1:]
try:
    runpy.run_module("v2xpos", run_name="__main__")
finally:
    with open("/proc/self/status") as fh, open(os.environ["V2XPOS_PEAK_FILE"], "w") as out:
        out.write(next(line for line in fh if line.startswith("VmHWM:")).split()[1])
"""
"""The child: ``python -m v2xpos ARGS`` that writes its peak resident set size [KiB] to a file."""


def _measure(argv: list[str], log: Path) -> dict:
    """Run ``v2xpos`` with ``argv`` as a child process; its exit code and peak RSS [MiB]."""
    peak = log.with_suffix(".peak_kib")
    with open(log, "w") as fh:
        proc = subprocess.run([sys.executable, "-c", CHILD, *argv], stdout=fh, stderr=subprocess.STDOUT,
                              cwd=Path(__file__).resolve().parents[1], env={**os.environ, "V2XPOS_PEAK_FILE": str(peak)})
    if proc.returncode not in (0, 1) or not peak.is_file():
        raise RuntimeError(f"v2xpos {' '.join(argv)} failed (exit {proc.returncode}):\n{log.read_text()[-2000:]}")
    return {"rc": proc.returncode, "mib": float(peak.read_text()) / 1024.0}


def run_bench(args: argparse.Namespace) -> int:
    work = Path(args.keep).resolve() if args.keep else Path(tempfile.mkdtemp(prefix="v2xpos-smoothing-memory-"))
    work.mkdir(parents=True, exist_ok=True)
    try:
        if args.recording:
            dataset = Path(args.recording)
        else:
            from sim.recordings import generate_convoy
            print(f"generating a {args.duration:.0f} s recording (seed {args.seed}, clean) in {work / 'rec'}", flush=True)
            generate_convoy(work / "rec", seed=args.seed, preset="clean", duration_s=args.duration)
            dataset = work / "rec" / "A" / "dataset.toml"
        common = ["replay", str(dataset), "--no-progress"]
        fwd = _measure(common + ["--json", str(work / "forward.json")], work / "forward.log")
        smo = _measure(common + ["--smooth", "--solution", str(work / "smoothed_solution.csv"),
                                 "--json", str(work / "smoothed.json")], work / "smoothed.log")
        f_sum = json.loads((work / "forward.json").read_text())
        s_sum = json.loads((work / "smoothed.json").read_text())
        sm = s_sum["smoothing"]
        report = {"dataset": str(dataset), "imu_samples": s_sum["imu_samples"], "gnss_epochs": s_sum["gnss_epochs"],
                  "forward_peak_mib": fwd["mib"], "smoothed_peak_mib": smo["mib"], "limit_mib": LIMIT_MIB,
                  "stored_mib": sm["stored_mib"], "nodes": sm["nodes"], "forward_s": f_sum["wall_s"],
                  "smoothed_forward_s": sm["forward_s"], "backward_s": sm["backward_s"],
                  "inside_outage_h_rms_m": s_sum["inside_outage_h_rms_m"],
                  "smoothed_inside_outage_h_rms_m": s_sum["smoothed_inside_outage_h_rms_m"],
                  "smoothed_inside_outage_within_3sd": s_sum["smoothed_inside_outage_within_3sd"]}
        print(f"{report['imu_samples']} IMU samples, {report['gnss_epochs']} GNSS epochs ({dataset})")
        print(f"  forward replay:  peak RSS {fwd['mib']:.0f} MiB, {f_sum['wall_s']:.1f} s")
        print(f"  smoothed replay (+ smoothed solution csv): peak RSS {smo['mib']:.0f} MiB "
              f"[limit {LIMIT_MIB:.0f}], {sm['nodes']} nodes, {sm['stored_mib']:.0f} MiB stored, forward "
              f"{sm['forward_s']:.1f} s + backward {sm['backward_s']:.1f} s")
        print(f"  inside the outages: forward h RMS {report['inside_outage_h_rms_m']:.3f} m, smoothed "
              f"{report['smoothed_inside_outage_h_rms_m']:.3f} m, within 3 sd "
              f"{report['smoothed_inside_outage_within_3sd']:.3f}")
        if args.json:
            Path(args.json).write_text(json.dumps(report, indent=1))
        return 0 if smo["mib"] <= LIMIT_MIB else 1
    except (OSError, ValueError, RuntimeError) as exc:
        print(f"v2xpos bench smoothing-memory: {exc}", file=sys.stderr)
        return 2
    finally:
        if not args.keep:
            shutil.rmtree(work, ignore_errors=True)


