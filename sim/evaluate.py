"""Errors of the master's results against the simulator truth, and the demo report.

Truth relative kinematics at the master time t_m (vectorised, same definitions as
``v2xpos.relative.relative_kinematics``): with ECEF positions r_e and C_en the ECEF->NED DCM at the
master,
    r_b = C_bn_m C_en_m (r_e_s - r_e_m),
    v_rel_b = C_bn_m (C_nm_ns v_s - v_m) - w_nb_m x r_b,
reference point to reference point. Uncompensated error: the slave message transformed without
prediction (its own time of validity) compared with the same truth at t_m.
"""
from __future__ import annotations

import math

import numpy as np

from master.pipeline import RECORD_FIELDS
from sim.scenarios import Scenario
from v2xpos import geo
from v2xpos.types import FixStatus
from v2xpos.wire import TargetStatus

F = {name: i for i, name in enumerate(RECORD_FIELDS)}


def _C_en(lat: np.ndarray, lon: np.ndarray) -> np.ndarray:
    """(N, 3, 3) ECEF -> NED DCMs."""
    sl, cl, so, co = np.sin(lat), np.cos(lat), np.sin(lon), np.cos(lon)
    C = np.empty((len(lat), 3, 3))
    C[:, 0] = np.stack([-sl * co, -sl * so, cl], axis=1)
    C[:, 1] = np.stack([-so, co, np.zeros_like(lat)], axis=1)
    C[:, 2] = np.stack([-cl * co, -cl * so, -sl], axis=1)
    return C


def truth_relative(sc: Scenario, target_id: str, t_s: np.ndarray) -> dict:
    """True relative position/velocity (master body frame) and range of a target at times t_s."""
    m = sc.master.truth.sample(t_s)
    s = sc.actors[target_id].truth.sample(t_s)
    re_m = geo.lla_to_ecef(m["lla"])
    re_s = geo.lla_to_ecef(s["lla"])
    Cm = _C_en(m["lla"][:, 0], m["lla"][:, 1])
    Cs = _C_en(s["lla"][:, 0], s["lla"][:, 1])
    r_n = np.einsum("nij,nj->ni", Cm, re_s - re_m)
    C_bn = np.transpose(m["C_nb"], (0, 2, 1))
    r_b = np.einsum("nij,nj->ni", C_bn, r_n)
    v_s_mn = np.einsum("nij,njk,nk->ni", Cm, np.transpose(Cs, (0, 2, 1)), s["v_ned_mps"])
    v_rel = np.einsum("nij,nj->ni", C_bn, v_s_mn - m["v_ned_mps"]) - np.cross(m["w_nb_b_rps"], r_b)
    return {"rel_pos_b_m": r_b, "rel_vel_b_mps": v_rel, "range_m": np.linalg.norm(r_b, axis=1)}


def gnss_relative_error_rms(sc: Scenario, target_ids: list[str], t_from_s: float, t_to_s: float,
                            window_s: float = 1.0) -> dict[str, float | None]:
    """Per target, the RMS [m] of its GNSS position error minus the master's (each receiver's fix
    minus its true antenna position, RTK-fixed epochs of both in [t_from_s, t_to_s)), averaged over
    ``window_s``: the relative error the two filters start from. Averaging removes the white part
    of the receiver noise, which filtering removes too; the time-correlated part (Gauss-Markov,
    ``sim.sensors.GnssErrorModel``) stays, and no single-vehicle filter can take it out."""
    from sim.source import simulated_gnss

    def errors(actor_id: str) -> tuple[np.ndarray, np.ndarray]:
        a = sc.actors[actor_id]
        g = simulated_gnss(sc, a)
        sel = (g.t_s >= t_from_s) & (g.t_s < t_to_s) & (np.asarray(g.fix) == int(FixStatus.FIXED))
        tr = a.truth.sample(g.t_s[sel])
        r_ant = tr["r_ned_m"] + np.einsum("nij,j->ni", tr["C_nb"], np.asarray(a.lever_arm_m, float))
        return g.t_s[sel], geo.lla_to_ned(np.asarray(g.lla)[sel], a.truth.lla0) - r_ant

    t_m, e_m = errors(sc.master_id)
    out: dict[str, float | None] = {}
    for target_id in target_ids:
        t_s, e_s = errors(target_id)
        out[target_id] = None
        if len(t_m) < 2 or len(t_s) < 2:
            continue
        j = np.clip(np.searchsorted(t_s, t_m), 1, len(t_s) - 1)
        gap = np.minimum(np.abs(t_s[j] - t_m), np.abs(t_s[j - 1] - t_m))
        near = gap < 0.2   # the target has a fixed epoch next to the master's
        d = (np.stack([np.interp(t_m, t_s, e_s[:, i]) for i in range(3)], axis=1) - e_m)[near]
        k = max(1, int(round(window_s / float(np.median(np.diff(t_m))))))
        if len(d) < k:
            continue
        kernel = np.ones(k) / k
        smooth = np.stack([np.convolve(d[:, i], kernel, mode="valid") for i in range(3)], axis=1)
        out[target_id] = float(np.sqrt(np.mean(np.sum(smooth ** 2, axis=1))))
    return out


def _rms(x: np.ndarray) -> float | None:
    return float(np.sqrt(np.mean(x ** 2))) if len(x) else None


def _pct(x: np.ndarray, q: float) -> float | None:
    x = x[np.isfinite(x)]
    return float(np.percentile(x, q)) if len(x) else None


def evaluate_target(sc: Scenario, target_id: str, rows: np.ndarray, t_from_s: float) -> dict:
    """Report entry of one target from the master's recorded rows (``RECORD_FIELDS``)."""
    a = sc.actors[target_id]
    rows = rows[rows[:, F["t_gps_s"]] >= t_from_s]
    status = rows[:, F["status"]].astype(int)
    valid = rows[status == int(TargetStatus.VALID)]
    from_msg = rows[np.isfinite(rows[:, F["t_slave_gps_s"]])]
    out = {"id": target_id, "kind": a.kind, "samples": int(len(rows)),
           "valid_fraction": float(len(valid) / len(rows)) if len(rows) else 0.0,
           "status_counts": {TargetStatus(s).name.lower(): int(np.sum(status == s)) for s in np.unique(status)}}
    if len(valid):
        tr = truth_relative(sc, target_id, valid[:, F["t_gps_s"]])
        p = valid[:, [F["rel_pos_x"], F["rel_pos_y"], F["rel_pos_z"]]]
        v = valid[:, [F["rel_vel_x"], F["rel_vel_y"], F["rel_vel_z"]]]
        u = valid[:, [F["unc_pos_x"], F["unc_pos_y"], F["unc_pos_z"]]]
        e = np.linalg.norm(p - tr["rel_pos_b_m"], axis=1)
        eu = np.linalg.norm(u - tr["rel_pos_b_m"], axis=1)
        ev = np.linalg.norm(v - tr["rel_vel_b_mps"], axis=1)
        er = valid[:, F["range_m"]] - tr["range_m"]
        fixed = valid[:, F["slave_fix"]] == 5
        near = tr["range_m"] <= 50.0
        out.update({"rel_pos_err_rms_rtk_fixed_m": _rms(e[fixed]), "rel_pos_err_rms_within_50m_m": _rms(e[near])})
        out.update({"rel_pos_err_rms_m": _rms(e), "rel_pos_err_p99_m": _pct(e, 99),
                    "rel_vel_err_rms_mps": _rms(ev), "range_err_rms_m": _rms(er),
                    "uncompensated_rel_pos_err_rms_m": _rms(eu[np.isfinite(eu)])})
    else:
        out.update({k: None for k in ("rel_pos_err_rms_m", "rel_pos_err_p99_m", "rel_vel_err_rms_mps",
                                      "range_err_rms_m", "uncompensated_rel_pos_err_rms_m")})
    lat_ms = from_msg[:, F["latency_s"]] * 1e3
    out.update({"latency_ms_p50": _pct(lat_ms, 50), "latency_ms_p99": _pct(lat_ms, 99),
                "e2e_ms_p50": _pct(from_msg[:, F["e2e_ms"]], 50), "e2e_ms_p99": _pct(from_msg[:, F["e2e_ms"]], 99)})
    return out


def series(sc: Scenario, target_id: str, rows: np.ndarray) -> dict:
    """Time series for plots: t rel. epoch, status, range, position error, uncompensated error."""
    t = rows[:, F["t_gps_s"]]
    status = rows[:, F["status"]].astype(int)
    valid = status == int(TargetStatus.VALID)
    err = np.full(len(rows), math.nan)
    unc = np.full(len(rows), math.nan)
    rng_true = np.full(len(rows), math.nan)
    if valid.any():
        tr = truth_relative(sc, target_id, t[valid])
        p = rows[valid][:, [F["rel_pos_x"], F["rel_pos_y"], F["rel_pos_z"]]]
        u = rows[valid][:, [F["unc_pos_x"], F["unc_pos_y"], F["unc_pos_z"]]]
        err[valid] = np.linalg.norm(p - tr["rel_pos_b_m"], axis=1)
        unc[valid] = np.linalg.norm(u - tr["rel_pos_b_m"], axis=1)
    if len(rows):
        rng_true = truth_relative(sc, target_id, t)["range_m"]
    return {"t_rel_s": t - sc.epoch_gps_s, "status": status, "range_m": rows[:, F["range_m"]],
            "range_true_m": rng_true, "err_m": err, "unc_err_m": unc,
            "latency_ms": rows[:, F["latency_s"]] * 1e3}
