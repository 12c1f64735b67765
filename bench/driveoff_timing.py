"""How honest the IMU time offset is after a drive-off (docs/integrity.md, What is short).

For every (preset, seed[, overrides]) case ``sim.recordings`` writes a two-car recording of the
convoy_dev kind (cached under ``--work``, shared with ``bench.integrity_mc``'s cache layout) and the
follower's service filter replays it (``ins.replay_engine.run_replay``, the filter ``v2xpos
replay`` runs). From the heading reset (the first GNSS epoch fast enough for a course) the
estimate of ``imu_time_offset`` and its sd are taken 1, 3, 5 and 10 s later and compared with the
truth the generator wrote (``truth_effects.json``: the stamps are ``imu_time_late_s`` late, so the
offset to add is its negative). One line per case and, per instant, the pooled normalised error:

* ``z = (estimate - truth) / sd``: for an honest filter N(0, 1), so its RMS over the cases is ~1
  and |z| > 3 is rare (0.27 % per case and instant);
* at a constant acceleration the time offset is nearly collinear with the error of the velocity
  the heading reset takes from GNSS (``dp = dv t - (v0 + a t) dt``), so the seconds after the reset
  should leave its sd wide until the acceleration changes.

    python -m bench.driveoff_timing --presets clean,dev_like --seeds 10-18 [--mounting B=x-backward/z-up]
        [--effect B.imu_stamp_extra_delay_s=0.028] [--route drive_off_radius_m=12 --vehicle A]
        [--json out.json]

About 2 s of CPU per case once the recording exists (generating one takes ~1 s).
"""
from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

from bench.integrity_mc import _seeds, make_recording

SECONDS_AFTER_RESET = (1.0, 3.0, 5.0, 10.0)


def time_offset_after_reset(rec: Path, vehicle: str = "B",
                            after_s: tuple[float, ...] = SECONDS_AFTER_RESET) -> dict:
    """Truth and (estimate, sd) of ``vehicle``'s IMU time offset [s] ``after_s`` seconds after its
    heading reset, from a replay of its dataset with the service filter."""
    from v2xpos.datasets.loader import load_dataset
    from v2xpos.ins.filter import InsFilter
    from v2xpos.ins.replay_engine import ReplayHook, config_for, run_replay
    effects = json.loads((rec / "truth_effects.json").read_text())["vehicles"][vehicle]
    truth_s = -float(effects["imu_time_late_s"])
    ds = load_dataset(rec / vehicle / "dataset.toml")
    flt = InsFilter(config_for(ds, "service"))
    i = flt.layout.at("imu_time_offset")
    if i < 0:
        raise ValueError(f"{rec / vehicle}: the service filter has no imu_time_offset state")
    seen: dict = {}

    class AfterReset(ReplayHook):
        def on_update(self, r, f):
            if "reset_s" not in seen:
                if f.heading_known:
                    seen["reset_s"] = float(r.t_s)
                return
            for t in after_s:
                if t not in seen and r.t_s - seen["reset_s"] >= t:
                    seen[t] = (float(f.fx.imu_time_offset_s), math.sqrt(float(f.P[i, i])))

    run_replay(flt, ds, [], [AfterReset()])
    return {"truth_s": truth_s, "reset_s": seen.get("reset_s"),
            "after": {t: seen[t] for t in after_s if t in seen}}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--presets", default="clean,dev_like")
    ap.add_argument("--seeds", default="10-18")
    ap.add_argument("--mounting", action="append", default=[])
    ap.add_argument("--effect", action="append", default=[])
    ap.add_argument("--route", action="append", default=[],
                    help="a route override: drive_off_radius_m=12 makes the leader (--vehicle A) drive off turning")
    ap.add_argument("--vehicle", default="B")
    ap.add_argument("--work", type=Path, default=Path("build/driveoff_timing"))
    ap.add_argument("--json", type=Path)
    args = ap.parse_args(argv)
    rows = []
    for preset in args.presets.split(","):
        for seed in _seeds(args.seeds):
            rec = make_recording(args.work / "rec", preset, seed, args.mounting, args.effect, [], args.route)
            r = time_offset_after_reset(rec, args.vehicle)
            r["case"] = f"{preset} s{seed}"
            rows.append(r)
            cells = [f"{t:4.0f} s {e * 1e3:7.1f} ± {s * 1e3:5.1f} ms z {(e - r['truth_s']) / s:5.1f}"
                     for t, (e, s) in r["after"].items()]
            print(f"{r['case']:14s} truth {r['truth_s'] * 1e3:6.1f} ms | " + " | ".join(cells), flush=True)
    summary = {}
    for t in SECONDS_AFTER_RESET:
        zs = [(e - r["truth_s"]) / s for r in rows if t in r["after"] for e, s in [r["after"][t]]]
        if zs:
            summary[t] = {"cases": len(zs), "z_rms": math.sqrt(sum(z * z for z in zs) / len(zs)),
                          "z_abs_max": max(abs(z) for z in zs), "beyond_3": int(sum(abs(z) > 3 for z in zs))}
            s = summary[t]
            print(f"{t:4.0f} s after the reset: {s['cases']} cases, normalised error RMS {s['z_rms']:.2f} "
                  f"(honest ~1), largest |z| {s['z_abs_max']:.1f}, beyond 3 sd: {s['beyond_3']}")
    if args.json:
        args.json.write_text(json.dumps({"cases": [{**r, "after": {str(k): v for k, v in r["after"].items()}}
                                                    for r in rows],
                                         "summary": {str(k): v for k, v in summary.items()}}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
