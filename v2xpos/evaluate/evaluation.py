"""The evaluation: time alignment, association, effects, metrics (``docs/evaluate.md``).

Steps (``evaluate``):

1. Coarse latency (``effects.coarse_latency``) on every pair within a wide gate at tau = 0:
   ``gate_m`` plus the reported point's speed in the sensor frame times the largest latency searched.
2. Three passes of: predict every target's measurement with the current effects, gate (first pass
   ``gate_m`` in metres, then the chi^2 gate on the range / azimuth residuals with their robust
   sigmas), gated GNN per cycle, one MAP step of the effects.
3. The final association and the effects' sds and significance (``identify.fit`` / ``decide``).
4. Errors (sensor minus reference, sensor frame with the declared mount) with the latency
   compensated when it is significant (else with none), and the metrics.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from . import effects as fx
from .associate import GATE_CHI2, Pairs, assign, candidates, geometry_at, id_switches, wrap
from .config import SensorConfig
from .objects import ObjectList, cycle_grid
from .reference import Reference

PASSES = 3
PERCENTILES = (50, 90, 99)


class NoOverlapError(ValueError):
    """The object list and the reference share no time (the message names both files)."""


@dataclass
class Evaluation:
    metrics: dict
    matches: dict                      # column -> array (matches.csv)
    series: dict = field(default_factory=dict)   # for the plots


def error_stats(e: np.ndarray) -> dict:
    """bias (mean), sd, rms, and the 50/90/99th percentiles of |e|; None when there is no error."""
    e = np.asarray(e, float)
    e = e[np.isfinite(e)]
    if not len(e):
        return {"bias": None, "sd": None, "rms": None, **{f"p{q}": None for q in PERCENTILES}, "n": 0}
    a = np.abs(e)
    return {"bias": float(np.mean(e)), "sd": float(np.std(e, ddof=1)) if len(e) > 1 else 0.0,
            "rms": float(np.sqrt(np.mean(e * e))), **{f"p{q}": float(np.percentile(a, q)) for q in PERCENTILES},
            "n": int(len(e))}


def _check_overlap(objs: ObjectList, ref: Reference, targets: list[str]) -> None:
    t0, t1 = float(objs.t_s[0]), float(objs.t_s[-1])
    spans = {tid: (ref.tracks[tid].t_s[0], ref.tracks[tid].t_s[-1]) for tid in targets if len(ref.tracks[tid].t_s) > 1}
    if not spans:
        raise NoOverlapError(f"{ref.path}: no VALID reference row for any target (targets {sorted(ref.tracks)})")
    lo = min(s[0] for s in spans.values()) - 1.0
    hi = max(s[1] for s in spans.values()) + 1.0
    if t1 < lo or t0 > hi:
        raise NoOverlapError(
            f"{objs.path}: no overlap with the reference {ref.path}: objects t_gps_s {t0:.3f}..{t1:.3f}, VALID "
            f"reference {lo + 1.0:.3f}..{hi - 1.0:.3f} (GPS seconds; is [sensor] clock right?)")


def evaluate(objs: ObjectList, ref: Reference, cfg: SensorConfig) -> Evaluation:
    """Everything of metrics.json, matches.csv and the plots (module docstring)."""
    targets = sorted(tid for tid, tr in ref.tracks.items() if len(tr.t_s) > 1)
    _check_overlap(objs, ref, targets)
    K = len(targets)

    # 1. coarse latency from the pairs within the wide gate at tau = 0
    g0 = geometry_at(ref, targets, cfg, objs.t_s)
    speed = np.hypot(g0.vx, g0.vy)
    wide = cfg.gate_m + np.where(np.isfinite(speed), speed, 0.0) * cfg.max_latency_s
    cand = candidates(objs, g0, np.zeros(3), wide, None)
    if not len(cand.row):
        raise NoOverlapError(f"{objs.path}: no object within {cfg.gate_m:g} m (+ latency) of any reference target "
                             f"{targets} of {ref.path} while both exist: check [sensor] mount_m / mount_yaw_deg, "
                             f"[targets] and the clock")
    tau0, grid, cost = fx.coarse_latency(objs, cand.row, cand.target, ref, targets, cfg)
    # only rows within the wide gate of some target can ever be associated: the passes work on them
    all_objs = objs
    near = np.unique(cand.row)
    objs = all_objs.subset(near)

    # 2. passes of association and effects
    g = geometry_at(ref, targets, cfg, objs.t_s - tau0)
    res0 = fx.residuals(objs, np.searchsorted(near, cand.row), cand.target, g, np.zeros(3))
    ok0 = np.isfinite(res0.e_r) & np.isfinite(res0.e_az)
    theta = np.array([tau0, float(np.median(res0.e_r[ok0])), -float(np.median(res0.e_az[ok0]))])
    sigma = None
    pairs = Pairs(np.zeros(0, int), np.zeros(0, int), np.zeros(0))
    est = None
    for p in range(PASSES + 1):
        g = geometry_at(ref, targets, cfg, objs.t_s - theta[0])
        pairs = assign(objs, candidates(objs, g, theta, cfg.gate_m, sigma))
        if len(pairs.row) < 10:
            raise NoOverlapError(f"{objs.path}: fewer than 10 objects associate with the reference targets {targets} "
                                 f"of {ref.path}; check [sensor] mount_m / mount_yaw_deg and [targets]")
        res = fx.residuals(objs, pairs.row, pairs.target, g, np.zeros(3))
        res_theta = fx.residuals(objs, pairs.row, pairs.target, g, theta)
        sigma = fx.robust_sigma(res_theta)
        final = p == PASSES
        est = fx.estimate(_shifted(res, theta), theta, sigma, decide=final)
        if not final:
            theta = est.theta.copy()
    tau_comp = float(est.theta[0]) if est.significant[0] else 0.0
    yaw_sig = float(est.theta[2]) if est.significant[2] else 0.0

    # 3. errors with the declared mount, latency compensated when significant
    ge = geometry_at(ref, targets, cfg, objs.t_s - tau_comp)
    rows, tk = pairs.row, pairs.target
    x_m, y_m = objs.x_m[rows], objs.y_m[rows]
    r_m = np.hypot(x_m, y_m)
    az_m = np.arctan2(y_m, x_m)
    rr_m = (x_m * objs.vx_mps[rows] + y_m * objs.vy_mps[rows]) / np.where(r_m > 0, r_m, np.nan)
    e = {"range_error_m": r_m - ge.r[tk, rows],
         "azimuth_error_deg": np.degrees(wrap(az_m - ge.az[tk, rows])),
         "longitudinal_error_m": x_m - ge.x[tk, rows],
         "lateral_error_m": y_m - ge.y[tk, rows],
         "range_rate_error_mps": rr_m - ge.r_dot[tk, rows]}

    # 4. cycles, view, detection, false objects (over every row again)
    assoc_rows = near[rows]
    objs, sub = all_objs, objs
    grid_t, period, observed = cycle_grid(objs.cycle_t_s)
    if not math.isfinite(period):
        period = 0.0
    gc = geometry_at(ref, targets, cfg, grid_t - tau_comp)
    az_true = gc.az + yaw_sig
    in_view = gc.ok & (np.abs(wrap(az_true)) <= cfg.field_of_view_rad / 2.0) & (gc.r <= cfg.max_range_m)
    detected = np.zeros((K, len(grid_t)), bool)
    detected[tk, observed[objs.cycle[assoc_rows]]] = True
    covered_cycle = gc.ok.all(axis=0)                        # every target's reference present
    row_covered = covered_cycle[observed[objs.cycle]]
    # an id is judged where it first appears: births in covered cycles over the covered time
    n_ids = int(objs.id_code.max()) + 1
    first = np.full(n_ids, len(objs))
    np.minimum.at(first, objs.id_code, np.arange(len(objs)))
    associated = np.zeros(n_ids, bool)
    associated[objs.id_code[assoc_rows]] = True
    false_codes = np.flatnonzero(row_covered[first] & ~associated)
    false_ids = objs.object_id[first[false_codes]].tolist()
    covered_min = float(covered_cycle.sum()) * period / 60.0

    switch_flag = np.zeros(len(rows), bool)
    per_target = {}
    for k, tid in enumerate(targets):
        tr = ref.tracks[tid]
        mk = tk == k
        n_sw, flag = id_switches(sub, pairs, k)
        switch_flag[np.flatnonzero(mk)] = flag
        avail = gc.ok[k]
        view = in_view[k]
        span = (float(grid_t[avail][-1] - grid_t[avail][0]) if avail.sum() > 1 else 0.0)
        per_target[tid] = {
            "span_s": span,
            "reference_rows": int(len(tr.t_s)),
            "reference_rows_total": tr.rows_total,
            "reference_gaps": _gaps(grid_t, avail, period, tr.status_counts),
            "cycles_in_view": int(view.sum()),
            "cycles_detected": int((detected[k] & view).sum()),
            "detection_rate": float((detected[k] & view).sum() / view.sum()) if view.any() else None,
            "associations": int(mk.sum()),
            "object_ids": int(len(np.unique(objs.id_code[assoc_rows[mk]]))),
            "id_switches": n_sw,
            **{name: error_stats(v[mk]) for name, v in e.items()},
        }
    names = {0: ("latency_ms", 1e3), 1: ("range_bias_m", 1.0), 2: ("mount_yaw_deg", math.degrees(1.0))}
    fx_json = {name: est.entry(i, scale) for i, (name, scale) in names.items()}
    fx_json["latency_ms"]["compensated_ms"] = tau_comp * 1e3
    metrics = {
        "sensor": cfg.name,
        **fx_json,
        "false_objects_per_min": (len(false_ids) / covered_min) if covered_min > 0 else None,
        "false_objects": len(false_ids),
        "targets": per_target,
        "reference_smoothed": bool(ref.smoothed),
        "reference": {"kind": ref.kind, "rows": ref.rows, "targets": sorted(ref.tracks),
                      "covered_min": covered_min},
        "objects": {"rows": int(len(objs)), "rows_skipped": int(objs.skipped), "object_ids": n_ids,
                    "cycles": int(len(objs.cycle_t_s)), "cycles_empty": int(len(grid_t) - len(objs.cycle_t_s)),
                    "cycle_period_s": period, "span_s": float(objs.t_s[-1] - objs.t_s[0])},
        "association": {"pairs": int(len(rows)), "gate_m": cfg.gate_m,
                        "sigma_range_m": float(est.sigma[0]), "sigma_azimuth_deg": math.degrees(est.sigma[1]),
                        "gate_chi2": GATE_CHI2},
        "declared": cfg.as_dict(),
    }
    matches = {"t_gps_s": sub.t_s[rows], "cycle": sub.cycle[rows], "target": np.array(targets, dtype=object)[tk]
               if K else np.zeros(0, object), "object_id": sub.object_id[rows], "x_m": x_m, "y_m": y_m,
               "ref_x_m": ge.x[tk, rows], "ref_y_m": ge.y[tk, rows], "range_m": r_m, "ref_range_m": ge.r[tk, rows],
               "azimuth_deg": np.degrees(az_m), **e, "id_switch": switch_flag.astype(int), "gate_d2": pairs.d2}
    is_false = np.zeros(n_ids, bool)
    is_false[false_codes] = True
    false_rows = np.flatnonzero(is_false[objs.id_code])
    series = {"targets": targets, "grid_t": grid_t, "in_view": in_view, "detected": detected,
              "ref_x": gc.x, "ref_y": gc.y, "latency_grid_s": grid, "latency_cost": cost,
              "false_rows_xy": (objs.x_m[false_rows], objs.y_m[false_rows]),
              "t0": float(objs.t_s[0]), "fov_rad": cfg.field_of_view_rad, "max_range_m": cfg.max_range_m}
    return Evaluation(metrics=metrics, matches=matches, series=series)


def _shifted(res: fx.Residuals, theta: np.ndarray) -> fx.Residuals:
    """Residuals at theta (bias and yaw applied) from those at (tau, 0, 0)."""
    return fx.Residuals(e_r=res.e_r - theta[1], e_az=wrap(res.e_az + theta[2]), r_dot=res.r_dot,
                        az_dot=res.az_dot, t_s=res.t_s, sd_ref_r=res.sd_ref_r, sd_ref_az=res.sd_ref_az)


def _gaps(grid_t: np.ndarray, avail: np.ndarray, period: float, status_counts: dict) -> dict:
    """Reference gaps over the object list's cycles: seconds without a VALID reference, the longest
    spans, and the non-VALID rows of the reference by status."""
    miss = ~avail
    spans = []
    if miss.any():
        edges = np.flatnonzero(np.diff(np.concatenate([[0], miss.astype(int), [0]])))
        for a, b in zip(edges[::2], edges[1::2]):
            spans.append([float(grid_t[a]), float(grid_t[b - 1]) + period])
    spans.sort(key=lambda s: s[0] - s[1])
    return {"seconds": float(miss.sum() * period), "spans": len(spans), "longest": spans[:5],
            "rows_by_status": dict(sorted(status_counts.items()))}
