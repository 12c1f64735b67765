"""``v2xpos bench replay``: EKF replay throughput [IMU samples/s], per stage and end to end, on a
recording given on the command line (e.g. ``../shared/data/drive_0708/dataset.toml``).

``--smooth`` also times the smoothed replay (``replay(smooth=True)``: the forward pass recording
for the smoother, then the backward pass) against the plain forward replay, best of ``--repeat``
each, interleaved so that both see the same machine load, in wall and CPU seconds; the issue's
budget is a smoothing cost of at most twice the forward replay's time (docs/smoothing.md)."""
from __future__ import annotations

import argparse
import time

import numpy as np

from v2xpos.ins.filter import InsFilter
from v2xpos.ins.replay import replay
from v2xpos.ins.replay_engine import OutageSchedule, config_for


def add_bench_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``v2xpos bench replay``."""
    parser.add_argument("dataset", help="dataset.toml of the recording to replay")
    parser.add_argument("--repeat", type=int, default=2, help="replays to time (best is reported)")
    parser.add_argument("--profile", choices=("service", "plain"), default="service",
                        help="filter profile (v2xpos.ins.profiles; default service, what v2xpos replay reports)")
    parser.add_argument("--smooth", action="store_true",
                        help="also time the smoothed replay (forward with recording + backward pass) against the forward one")


def run_bench(args: argparse.Namespace) -> int:
    """``v2xpos bench replay``: throughput per stage and end to end [IMU samples/s]."""
    from v2xpos.ins.ekf import propagate_covariance
    from v2xpos.ins.mechanization import MEM_SIZE, strapdown_batch
    from v2xpos.datasets import load_dataset
    t0 = time.perf_counter()
    ds = load_dataset(args.dataset)
    t_load = time.perf_counter() - t0
    n = len(ds.imu)
    print(f"dataset {ds.name}: {n} IMU samples, {len(ds.gnss)} GNSS epochs, load {t_load:.2f} s, "
          f"profile {args.profile}")
    cfg = config_for(ds, args.profile)
    f = InsFilter(cfg)
    f_b = np.ascontiguousarray(ds.imu.acc_mps2 @ cfg.setup.imu_to_body.T)
    w_b = np.ascontiguousarray(ds.imu.gyro_rps @ cfg.setup.imu_to_body.T)
    t = np.ascontiguousarray(ds.imu.t_s, dtype=float)
    nav = np.array([ds.gnss.lla[0][0], ds.gnss.lla[0][1], ds.gnss.lla[0][2], 0, 0, 0], float)
    A = np.zeros((f.layout.n, f.layout.n))
    for _ in range(2):   # first call compiles (or loads the cache)
        C = np.eye(3)
        mem = np.zeros(MEM_SIZE)
        t1 = time.perf_counter()
        strapdown_batch(t, f_b, w_b, 0, n, t[0], nav.copy(), C, np.zeros(12), mem, A, f.kidx, 1e-3, 1e-3)
        t_mech = time.perf_counter() - t1
    print(f"  strapdown + F accumulation (jitted): {n / t_mech:,.0f} samples/s")
    P = np.eye(f.layout.n)
    reps = 2000
    t1 = time.perf_counter()
    for _ in range(reps):
        P = propagate_covariance(P * 0 + np.eye(f.layout.n), A * 0, f.q_c, 0.1)
    t_cov = (time.perf_counter() - t1) / reps
    print(f"  covariance propagation ({f.layout.n} states): {t_cov * 1e6:.1f} us per call, "
          f"every {cfg.numerics.cov_every} samples -> {cfg.numerics.cov_every / t_cov:,.0f} samples/s")
    best = None
    for _ in range(max(1, args.repeat)):
        r = replay(ds, OutageSchedule(), progress=False, keep_series=False, profile=args.profile)
        if best is None or r.summary["wall_s"] < best.summary["wall_s"]:
            best = r
    s = best.summary
    print(f"  end to end replay (filter + updates, no loading): {s['imu_samples_per_s']:,.0f} IMU samples/s "
          f"wall ({s['wall_s']:.2f} s), {n / s['cpu_s']:,.0f} IMU samples per CPU second of one core "
          f"({s['cpu_s']:.2f} s); target >= 30,000")
    print(f"  end to end including loading: {n / (s['wall_s'] + t_load):,.0f} IMU samples/s")
    st = best.filter.stage_s
    other = s["wall_s"] - sum(st.values())
    for name, sec in list(st.items()) + [("python glue (events, stop detection, H/R building)", other)]:
        print(f"    stage {name:<52} {sec:6.3f} s  ({100 * sec / s['wall_s']:4.1f} %)  -> {n / max(sec, 1e-9):>12,.0f} samples/s")
    print(f"  outage_h_rms_m {s['outage_h_rms_m']:.3f}")
    if args.smooth:
        bench_smoothing(ds, max(1, args.repeat), args.profile)
    return 0


def bench_smoothing(ds, repeat: int, profile: str = "service") -> dict:
    """Forward replay against the smoothed replay, best of ``repeat`` each (interleaved); prints and
    returns the times [s] (wall and CPU) and the smoothed figures."""
    fwd, smo = [], []
    res = None
    for _ in range(repeat):
        r = replay(ds, OutageSchedule(), cfg=config_for(ds, profile), progress=False, keep_series=False)
        fwd.append((r.summary["wall_s"], r.summary["cpu_s"]))
        res = replay(ds, OutageSchedule(), cfg=config_for(ds, profile), progress=False, keep_series=False, smooth=True)
        sm = res.summary["smoothing"]
        smo.append((sm["forward_s"] + sm["backward_s"], sm["forward_cpu_s"] + sm["backward_cpu_s"],
                    sm["forward_s"], sm["backward_s"]))
    f_wall, f_cpu = min(w for w, _ in fwd), min(c for _, c in fwd)
    s_wall, s_cpu = min(x[0] for x in smo), min(x[1] for x in smo)
    best = min(smo)
    s = res.summary
    out = {"forward_wall_s": f_wall, "forward_cpu_s": f_cpu, "smoothed_wall_s": s_wall, "smoothed_cpu_s": s_cpu,
           "smoothing_cost_wall": (s_wall - f_wall) / f_wall, "smoothing_cost_cpu": (s_cpu - f_cpu) / f_cpu,
           "nodes": s["smoothing"]["nodes"], "stored_mib": s["smoothing"]["stored_mib"]}
    print(f"  forward replay:  {f_wall:.2f} s wall, {f_cpu:.2f} s CPU (best of {repeat})")
    print(f"  smoothed replay: {s_wall:.2f} s wall, {s_cpu:.2f} s CPU (forward with recording {best[2]:.2f} s + "
          f"backward pass {best[3]:.2f} s; {out['nodes']} nodes, {out['stored_mib']:.1f} MiB stored)")
    print(f"  smoothing cost = (smoothed - forward) / forward: {out['smoothing_cost_wall']:.2f} x wall, "
          f"{out['smoothing_cost_cpu']:.2f} x CPU; target <= 2")
    print(f"  inside the outages ({s['inside_outage_epochs']} RTK-fixed epochs): forward h RMS "
          f"{s['inside_outage_h_rms_m']:.3f} m, smoothed {s['smoothed_inside_outage_h_rms_m']:.3f} m "
          f"(max {s['smoothed_inside_outage_h_max_m']:.3f} m, within 3 sd {s['smoothed_inside_outage_within_3sd']:.3f})")
    return out
