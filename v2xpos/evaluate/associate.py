"""Predicting the sensor's measurement of every target, gating, and gated global nearest neighbour.

Measurement model (sensor frame, x boresight, y right; ``docs/evaluate.md``): the sensor stamps at
t what it measured at t - tau; it measures range r and azimuth az of the reported point with a
range bias b_r, and its boresight is turned by delta (mounting yaw, + to the right) from the
declared one, so that

    r_meas(t)  = r_ref(t - tau) + b_r + n_r,       az_meas(t) = az_ref(t - tau) - delta + n_az,

theta = (tau [s], b_r [m], delta [rad]). A constant azimuth bias of the sensor is the same rotation
about the sensor origin as a mounting yaw: one sensor's data cannot separate them, and delta is
their sum (azimuth bias counted with the opposite sign).

Association per cycle (Blackman & Popoli 1999, "Design and Analysis of Modern Tracking Systems",
sec. 6.4, gated GNN): candidate pairs (object row, target) inside the gate; the assignment that
minimises the summed squared normalised distance, one object per target and one target per
object (``scipy.optimize.linear_sum_assignment``, Crouse 2016, IEEE TAES 52(4)); cycles where no
object or target has two candidates are assigned directly.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment

from .config import SensorConfig
from .objects import ObjectList
from .reference import Reference, reported_point

GATE_CHI2 = 18.42
"""chi^2 with 2 degrees of freedom at 1 - 1e-4: a Gaussian measurement falls outside the
statistical gate once in 10,000 cycles."""

SIGMA_FLOOR_M = 0.02
SIGMA_FLOOR_RAD = np.radians(0.02)
"""Floors of the gate's sigmas: the reference itself is good to about 2 cm (RTK), so a gate tighter
than that would cut real detections of a very precise sensor."""


def wrap(a: np.ndarray) -> np.ndarray:
    return (a + np.pi) % (2.0 * np.pi) - np.pi


@dataclass
class Geometry:
    """The reported point of every target at the object rows' times minus tau: per target index
    k, arrays over all rows (NaN / ok False where the reference is absent)."""
    r: np.ndarray          # (K, N) range [m] (horizontal, sensor frame)
    az: np.ndarray         # (K, N) azimuth [rad]
    r_dot: np.ndarray      # (K, N) range rate [m/s]
    az_dot: np.ndarray     # (K, N) [rad/s]
    x: np.ndarray
    y: np.ndarray
    vx: np.ndarray
    vy: np.ndarray
    sd_r: np.ndarray       # (K, N) the reference's 1-sigma along the line of sight [m] (0 when not given)
    sd_perp: np.ndarray    # (K, N) across it [m]
    ok: np.ndarray         # (K, N)


def geometry_at(ref: Reference, targets: list[str], cfg: SensorConfig, t_s: np.ndarray) -> Geometry:
    """Reported points of ``targets`` at times t_s (already shifted by the latency)."""
    K, N = len(targets), len(t_s)
    out = {k: np.full((K, N), np.nan) for k in ("r", "az", "r_dot", "az_dot", "x", "y", "vx", "vy", "sd_r", "sd_perp")}
    ok = np.zeros((K, N), bool)
    for k, tid in enumerate(targets):
        tr = ref.tracks[tid]
        if len(tr.t_s) < 2:
            continue
        inside = np.flatnonzero((t_s >= tr.t_s[0]) & (t_s <= tr.t_s[-1]))
        if not len(inside):
            continue
        rp = reported_point(tr, cfg.target(tid), cfg, t_s[inside])
        q, qd = rp["q"], rp["q_dot"]
        r = np.hypot(q[:, 0], q[:, 1])
        rs = np.where(r > 0, r, np.nan)
        out["x"][k, inside], out["y"][k, inside] = q[:, 0], q[:, 1]
        out["vx"][k, inside], out["vy"][k, inside] = qd[:, 0], qd[:, 1]
        out["r"][k, inside] = r
        out["az"][k, inside] = np.arctan2(q[:, 1], q[:, 0])
        out["r_dot"][k, inside] = (q[:, 0] * qd[:, 0] + q[:, 1] * qd[:, 1]) / rs
        out["az_dot"][k, inside] = (q[:, 0] * qd[:, 1] - q[:, 1] * qd[:, 0]) / rs ** 2
        ok[k, inside] = rp["ok"] & (r > 0)
        # the reference's sd (master body axes) along and across the line of sight
        los = np.arctan2(q[:, 1], q[:, 0]) + cfg.mount_yaw_rad
        sd = np.where(np.isfinite(rp["sd_m"]), rp["sd_m"], 0.0)
        c, s = np.cos(los), np.sin(los)
        out["sd_r"][k, inside] = np.hypot(c * sd[:, 0], s * sd[:, 1])
        out["sd_perp"][k, inside] = np.hypot(s * sd[:, 0], c * sd[:, 1])
    return Geometry(ok=ok, **out)


def predict_xy(g: Geometry, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Predicted measured x, y (K, N) of each target with the effects theta (the latency is already
    in ``g``'s times): range + b_r, azimuth - delta."""
    r = g.r + theta[1]
    az = g.az - theta[2]
    return r * np.cos(az), r * np.sin(az)


@dataclass
class Pairs:
    """Associated (row, target index) pairs and their normalised squared distances."""
    row: np.ndarray
    target: np.ndarray
    d2: np.ndarray


def candidates(objs: ObjectList, g: Geometry, theta: np.ndarray, gate_m: np.ndarray | float | None,
               sigma: tuple[float, float] | None) -> Pairs:
    """Every (row, target) pair inside the gate: Euclidean ``gate_m`` (scalar or per (K, N)) when
    ``sigma`` is None, else the chi^2 gate on (range, azimuth) residuals with sigmas (m, rad)."""
    rows, tgts, d2s = [], [], []
    r_m = np.hypot(objs.x_m, objs.y_m)
    az_m = np.arctan2(objs.y_m, objs.x_m)
    px, py = predict_xy(g, theta)
    for k in range(g.r.shape[0]):
        ok = g.ok[k]
        if sigma is None:
            gate = gate_m[k] if np.ndim(gate_m) == 2 else gate_m
            d2 = ((objs.x_m - px[k]) ** 2 + (objs.y_m - py[k]) ** 2) / np.square(gate)
            inside = ok & (d2 <= 1.0)
        else:
            s_r = max(sigma[0], SIGMA_FLOOR_M)
            s_a = max(sigma[1], SIGMA_FLOOR_RAD)
            d2 = ((r_m - g.r[k] - theta[1]) / s_r) ** 2 + (wrap(az_m - g.az[k] + theta[2]) / s_a) ** 2
            inside = ok & (d2 <= GATE_CHI2)
        idx = np.flatnonzero(inside)
        rows.append(idx)
        tgts.append(np.full(len(idx), k))
        d2s.append(d2[idx])
    return Pairs(np.concatenate(rows), np.concatenate(tgts), np.concatenate(d2s))


def assign(objs: ObjectList, cand: Pairs) -> Pairs:
    """Gated GNN per cycle (module docstring) over the candidate pairs."""
    if not len(cand.row):
        return cand
    cyc = objs.cycle[cand.row]
    order = np.lexsort((cand.target, cyc))
    row, tgt, d2, cyc = cand.row[order], cand.target[order], cand.d2[order], cyc[order]
    # a cycle needs the assignment when a target or an object there has more than one candidate
    key_t = cyc * (int(tgt.max()) + 1) + tgt
    dup_t = np.zeros(len(row), bool)
    same = key_t[1:] == key_t[:-1]
    dup_t[1:] |= same
    dup_t[:-1] |= same
    _, inv, cnt = np.unique(row, return_inverse=True, return_counts=True)
    dup_o = cnt[inv] > 1
    conflict_cycles = np.unique(cyc[dup_t | dup_o])
    simple = ~np.isin(cyc, conflict_cycles)
    keep_row, keep_tgt, keep_d2 = [row[simple]], [tgt[simple]], [d2[simple]]
    if len(conflict_cycles):
        sel = np.flatnonzero(~simple)
        bounds = np.flatnonzero(np.diff(cyc[sel])) + 1
        for part in np.split(sel, bounds):
            rows_u, ri = np.unique(row[part], return_inverse=True)
            tg_u, ti = np.unique(tgt[part], return_inverse=True)
            cost = np.full((len(rows_u), len(tg_u)), 1e9)
            cost[ri, ti] = d2[part]
            a, b = linear_sum_assignment(cost)
            ok = cost[a, b] < 1e9
            keep_row.append(rows_u[a[ok]])
            keep_tgt.append(tg_u[b[ok]])
            keep_d2.append(cost[a[ok], b[ok]])
    out = Pairs(np.concatenate(keep_row), np.concatenate(keep_tgt), np.concatenate(keep_d2))
    order = np.argsort(out.row, kind="stable")
    return Pairs(out.row[order], out.target[order], out.d2[order])


def id_switches(objs: ObjectList, pairs: Pairs, k: int) -> tuple[int, np.ndarray]:
    """Number of times target k's associated object id differs from its previous associated one
    (CLEAR MOT's identity switches, Bernardin & Stiefelhagen 2008, EURASIP JIVP), and the flag
    per pair of k (in row order)."""
    rows = pairs.row[pairs.target == k]
    ids = objs.id_code[rows]
    flag = np.zeros(len(rows), bool)
    if len(rows) > 1:
        flag[1:] = ids[1:] != ids[:-1]
    return int(flag.sum()), flag
