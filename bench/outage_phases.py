"""Before/after a ``[calibration]`` table over every placement of the outage schedule.

``v2xpos calibrate``'s before/after figure is the RMS of the horizontal error at the end of the
3-4 outages one schedule places on a 200-s drive (15 s every 45 s from 40 s). One outage that
happens to span a turn, or the first seconds after the heading converged, sets that figure: on
the generated seed-10 leader (nothing undeclared) the written table gave 0.551 m against 0.415 m
before with the first outage at 40 s, 0.159 against 0.629 m with it at 30 s. This sweep moves the
first outage over one schedule period (``FIRSTS_S``) and pools every outage, so that a change of
the filter's noise is judged on the drive and not on where four outages fell.

    python -m bench.outage_phases CALIBRATED.toml [...]     # tables written by calibrate --write-dataset

"before" is the same descriptor with its ``[calibration]`` removed (the vehicle as declared).
CPU: 2 x 12 replays per descriptor (about 1 s each for a 200-s drive); run it niced.
"""
from __future__ import annotations

import argparse
import copy
import sys

import numpy as np

FIRSTS_S = tuple(float(x) for x in np.arange(24.0, 70.0, 4.0))
"""First-outage times swept [s after the first GNSS epoch]: one 45-s period in 4-s steps (40 s, the
default schedule's, included)."""


def sweep(ds, length_s: float = 15.0, every_s: float = 45.0, firsts_s: tuple = FIRSTS_S) -> dict:
    """{"before"|"after": {"pooled_rms_m", "median_m", "per_phase_rms_m", "errors_m"}} for a dataset
    carrying a ``[calibration]`` table (``after``) and the same dataset without it (``before``)."""
    from v2xpos.ins.replay import replay
    from v2xpos.ins.replay_engine import OutageSchedule
    out = {}
    for label, table in (("before", None), ("after", ds.calibration)):
        d = copy.copy(ds)
        d.calibration = table
        errs, per = [], []
        for f0 in firsts_s:
            s = replay(d, OutageSchedule(length_s, every_s, float(f0)), progress=False, keep_series=False).summary
            errs += list(s["outage_h_m"])
            per.append(float(s["outage_h_rms_m"]))
        e = np.asarray(errs, float)
        out[label] = {"pooled_rms_m": float(np.sqrt(np.mean(e ** 2))) if len(e) else float("nan"),
                      "median_m": float(np.median(e)) if len(e) else float("nan"),
                      "per_phase_rms_m": per, "errors_m": e.tolist()}
    b, a = np.asarray(out["before"]["per_phase_rms_m"]), np.asarray(out["after"]["per_phase_rms_m"])
    out["phases_after_worse"] = int(np.sum(a > b))
    out["firsts_s"] = list(firsts_s)
    return out


def main(argv: list[str] | None = None) -> int:
    from v2xpos.datasets import load_dataset
    p = argparse.ArgumentParser(prog="python -m bench.outage_phases", description=__doc__.split("\n\n")[0])
    p.add_argument("descriptors", nargs="+", help="dataset descriptors with a [calibration] table")
    args = p.parse_args(argv)
    print(f"{'descriptor':48s} {'before pooled':>13s} {'after pooled':>12s} {'before med':>10s} {'after med':>9s} "
          f"{'at 40 s':>15s} {'phases worse':>12s}")
    for path in args.descriptors:
        ds = load_dataset(path)
        r = sweep(ds)
        i = r["firsts_s"].index(40.0)
        b, a = r["before"], r["after"]
        print(f"{path[-48:]:48s} {b['pooled_rms_m']:13.3f} {a['pooled_rms_m']:12.3f} {b['median_m']:10.3f} "
              f"{a['median_m']:9.3f} {b['per_phase_rms_m'][i]:7.3f}->{a['per_phase_rms_m'][i]:.3f} "
              f"{r['phases_after_worse']:>6d}/{len(r['firsts_s'])}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
