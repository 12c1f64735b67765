"""Whitened residual rows of a fit replay: the data vector of ``v2xpos calibrate``'s fit.

Each row is one component of a GNSS position/velocity or NHC innovation divided by its baseline
innovation sd, or a block-mean vehicle roll; its key names the measurement (kind, time relative
to the recording's first stamp in ms, component) so that the same row is found in every replay,
whatever stamps or tags the replay shifted.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from v2xpos.types import Dataset

from .inject import EffectSet
from .residuals import ResidualLog

ROLL_BLOCK_S = 30.0
ROLL_MIN_SPEED_MPS = 3.0
ROLL_SYSTEMATIC_SD_RAD = np.radians(0.5)
"""Road cross-slope left in the mean vehicle roll of a drive (crowned roads, driving on one side)."""


@dataclass
class RowSet:
    """Whitened residual rows of one replay: keys identify the same row across replays."""
    keys: np.ndarray
    r: np.ndarray
    t_s: np.ndarray


def roll_rows(log: ResidualLog, t0_s: float, roll_sd_rad: float) -> tuple[list, list, list]:
    g = log["gnss_pos"]
    moving = g.speed_mps > ROLL_MIN_SPEED_MPS
    roll = g.rpy_rad[:, 0]
    blocks = np.floor((g.t_s - t0_s) / ROLL_BLOCK_S).astype(int)
    keys, vals, ts = [], [], []
    for b in np.unique(blocks[moving]):
        sel = moving & (blocks == b)
        if sel.sum() >= 20:
            keys.append(("roll", int(b), 0))
            vals.append(float(np.mean(roll[sel])) / roll_sd_rad)
            ts.append(float(np.mean(g.t_s[sel])))
    return keys, vals, ts


def residual_rows(log: ResidualLog, applied: EffectSet, weights: dict | None, t0_s: float,
                  roll_sd_rad: float, ref_times: tuple[float, float],
                  constraints_in_gnss_time: bool = False) -> tuple[RowSet, dict]:
    """Rows from GNSS position/velocity and NHC innovations (each component divided by the
    baseline innovation sd in ``weights``, or by its own sd when weights is None) plus the block
    mean vehicle roll. Keys are times relative to the first GNSS tag / first IMU stamp of the
    replayed recording (``ref_times``), with the applied clock drift removed, so that the same
    epoch keeps its key when stamps or tags are shifted; constraint rows applied at GNSS-defined
    times (``runner.replay(exact_epochs=True)``) are keyed like GNSS rows."""
    keys, vals, ts = [], [], []
    new_w = {}
    drift = applied.imu_clock_drift_ppm
    gnss0, imu0 = ref_times
    for kind in ("gnss_pos", "gnss_vel", "nhc"):
        if kind not in log:
            continue
        s = log[kind]
        if kind.startswith("gnss") or constraints_in_gnss_time:
            t_rel = s.t_s - gnss0
        else:
            t_rel = (s.t_s - imu0) / (1.0 + 1e-6 * drift)
        kms = np.round(t_rel * 1000.0).astype(np.int64)
        for i in range(len(s)):
            for c in range(s.innovation.shape[1]):
                key = (kind, int(kms[i]), c)
                sd = s.sd[i, c]
                if weights is None:
                    if not s.accepted[i] or not np.isfinite(sd) or sd <= 0:
                        continue
                    new_w[key] = sd
                    w = sd
                else:
                    w = weights.get(key)
                    if w is None:
                        continue
                val = s.innovation[i, c] / w
                if np.isfinite(val):
                    keys.append(key)
                    vals.append(val)
                    ts.append(float(s.t_s[i]))
    k, v, t = roll_rows(log, t0_s, roll_sd_rad)
    keys += k
    vals += v
    ts += t
    if weights is None:
        for kk in k:
            new_w[kk] = roll_sd_rad
        # variance components: rescale each kind to unit mean square (Koch 1999, sec. 3.6), so that
        # an over- or under-confident filter tuning does not set the relative weights of the kinds
        kinds = np.array([kk[0] for kk in keys])
        vals_a = np.asarray(vals, float)
        for kind in set(kinds.tolist()):
            sel = kinds == kind
            if kind == "roll" or sel.sum() < 10:
                continue
            f = float(np.sqrt(np.mean(vals_a[sel] ** 2)))
            if f > 0:
                vals_a[sel] /= f
                for j in np.flatnonzero(sel):
                    new_w[keys[j]] *= f
        vals = vals_a.tolist()
    arr = np.empty(len(keys), dtype=object)
    arr[:] = keys
    return RowSet(arr, np.asarray(vals), np.asarray(ts)), new_w


def ref_times(ds: Dataset, theta: np.ndarray) -> tuple[float, float]:
    """First GNSS tag and first IMU stamp of ``correct(ds, theta)``."""
    e = EffectSet.from_vector(theta)
    return float(ds.gnss.t_s[0] - e.gnss_latency_s), float(ds.imu.t_s[0] + e.imu_time_offset_s)


def align(base: RowSet, other: RowSet) -> np.ndarray:
    """other's values on base's keys (NaN where other lacks the row)."""
    idx = {k: i for i, k in enumerate(other.keys)}
    out = np.full(len(base.keys), np.nan)
    for i, k in enumerate(base.keys):
        j = idx.get(k)
        if j is not None:
            out[i] = other.r[j]
    return out


def roll_block_sd(log: ResidualLog, t0_s: float) -> float:
    _, vals, _ = roll_rows(log, t0_s, 1.0)
    return float(max(np.std(vals), np.radians(0.2))) if len(vals) > 2 else np.radians(1.0)

