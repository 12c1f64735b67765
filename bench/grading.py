"""``v2xpos bench grading faults|lidar``: the IMU grading on simulated vehicles (the simulator
makes the faults and the lidar scans, so this is a bench, not part of the library).

* ``faults [--seeds N]``: one faulty unit per fault kind and seed among healthy units
  (``sim.imu_faults``); every faulty unit must grade fail and no healthy one.
* ``lidar [--plots DIR]``: pose-aided rate check end to end (ray-cast scans, KISS-ICP poses).
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from v2xpos.commands.grade import write_report_json
from v2xpos.quality.grader import grade_units


def run_fault_sweep(seeds: int = 20, n_units: int = 3, duration_s: float = 60.0, progress: bool = True) -> dict:
    """Grade simulated vehicles with one faulty unit per fault and seed (sim.imu_faults); returns
    {'faults': {kind: {'detected', 'runs', 'healthy_fail', 'healthy_warn', 'healthy_units'}}, 'clean': {...}}."""
    from tqdm import tqdm

    from sim.imu_faults import FAULTS, simulate_vehicle

    res = {}
    kinds = [None, *FAULTS]
    bar = tqdm(total=len(kinds) * seeds, disable=not progress, file=sys.stderr, desc="fault sweep")
    for kind in kinds:
        r = {"runs": seeds, "detected": 0, "healthy_units": 0, "healthy_fail": 0, "healthy_warn": 0,
             "missed_seeds": []}
        for seed in range(seeds):
            v = simulate_vehicle(n_units, kind, seed, duration_s)
            rep = grade_units(v.units, mounting_xyz_deg=v.mounting_xyz_deg)
            for u in rep["units"]:
                if u["id"] == v.faulty:
                    if u["grade"] == "fail":
                        r["detected"] += 1
                    else:
                        r["missed_seeds"].append(seed)
                else:
                    r["healthy_units"] += 1
                    r["healthy_fail"] += u["grade"] == "fail"
                    r["healthy_warn"] += u["grade"] == "warn"
            bar.update()
        res[kind or "none"] = r
    bar.close()
    return res


def run_lidar_check(seed: int = 0, duration_s: float = 4.0, scale_error: float = 0.03) -> dict:
    """Pose-aided rate check end to end: truth turn -> ray-cast scans -> KISS-ICP poses -> angular
    rate; one healthy and one scale-faulty gyro. Returns yaw-rate recovery and both checks."""
    from sim.imu_faults import FaultSpec, inject_fault
    from sim.lidar import LidarModel, courtyard, kiss_icp_poses, simulate_scans
    from sim.sensors import ImuErrorModel, simulate_imu
    from sim.trajectory import Segment, generate

    from v2xpos.quality.rate_check import angular_rates_from_poses, rate_check

    speed, yaw_rate = 5.0, 0.3
    radius = speed / yaw_rate
    traj = generate([Segment(duration_s + 2.0, yaw_rate_rps=yaw_rate)], dt_s=0.01, speed0_mps=speed,
                    smooth_tau_s=0.0, r0_ned_m=np.array([0.0, -radius, 0.0]))
    scene = courtyard(n_cylinders=20, n_boxes=10, ground=False, seed=seed)
    model = LidarModel(azimuth_step_deg=0.25, elevations_deg=np.linspace(-10.0, 20.0, 16))
    rng = np.random.default_rng(seed)
    seq = simulate_scans(traj, scene, model, rng, t_start_s=traj.t_s[0] + 1.0, duration_s=duration_s)
    poses = kiss_icp_poses(seq)
    t_mid, w_pose = angular_rates_from_poses(seq.t_s, poses)
    yaw_icp = float(np.mean(w_pose[:, 2]))
    yaw_true = float(np.mean(np.interp(t_mid, traj.t_s, traj.w_nb_b_rps[:, 2])))
    imu = simulate_imu(traj, ImuErrorModel.preset("automotive", rng), rng=rng)
    bad = inject_fault(imu, FaultSpec("gyro_scale", scale_error))
    healthy = rate_check(seq.t_s, poses, imu.t_s, imu.gyro_rps, window_s=2.0)
    faulty = rate_check(seq.t_s, poses, bad.t_s, bad.gyro_rps, window_s=2.0)
    return {"n_scans": len(seq.scans), "points_per_scan": int(np.mean([len(s) for s in seq.scans])),
            "yaw_rate_true_dps": float(np.degrees(yaw_true)), "yaw_rate_icp_dps": float(np.degrees(yaw_icp)),
            "yaw_rate_rel_error": float(yaw_icp / yaw_true - 1.0),
            "healthy": healthy.as_dict(), "scale_fault": faulty.as_dict(),
            "_results": {"healthy": healthy, f"scale {scale_error:.0%}": faulty}}


def add_bench_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("what", choices=("faults", "lidar"), help="faults: fault sweep; lidar: KISS-ICP rate check")
    parser.add_argument("--seeds", type=int, default=20, help="seeds per fault (faults)")
    parser.add_argument("--json", type=Path, help="write the result as JSON to this file")
    parser.add_argument("--plots", type=Path, help="write PNG figures to this folder (lidar)")


def run_bench(args: argparse.Namespace) -> int:
    args.path = None
    if args.what == "faults":
        t0 = time.perf_counter()
        res = run_fault_sweep(args.seeds)
        print(f"{'fault':<16} {'faulty unit graded fail':<24} {'healthy fail':<13} healthy warn")
        for k, r in res.items():
            det = f"{r['detected']}/{r['runs']}" if k != "none" else "-"
            print(f"{k:<16} {det:<24} {r['healthy_fail']}/{r['healthy_units']:<11} {r['healthy_warn']}")
        print(f"({time.perf_counter() - t0:.1f} s)")
        if args.json:
            write_report_json(args.json, {"seeds": args.seeds, "faults": res}, args)
        ok = all(r["healthy_fail"] == 0 for r in res.values()) and \
            all(r["detected"] == r["runs"] for k, r in res.items() if k != "none")
        return 0 if ok else 1
    if args.what == "lidar":
        res = run_lidar_check()
        print(f"scans {res['n_scans']} ({res['points_per_scan']} points each); yaw rate true "
              f"{res['yaw_rate_true_dps']:.3f} dps, KISS-ICP {res['yaw_rate_icp_dps']:.3f} dps "
              f"({100 * res['yaw_rate_rel_error']:+.2f} %)")
        for name in ("healthy", "scale_fault"):
            r = res[name]
            print(f"{name:<12} mean |w_imu|-|w_pose| {r['mean_diff_dps']:+.3f} dps, threshold "
                  f"{r['threshold_dps']:.3f} dps -> {'ANOMALY' if r['anomaly'] else 'ok'}")
        if args.plots:
            from v2xpos.quality.plots import plot_rate_check
            print(f"wrote {plot_rate_check(res['_results'], Path(args.plots) / 'rate_check.png')}")
        if args.json:
            write_report_json(args.json, {k: v for k, v in res.items() if not k.startswith("_")}, args)
        return 0
    return 2
