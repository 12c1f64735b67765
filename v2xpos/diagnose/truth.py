"""Scoring a master's ``results.csv`` against a recording's truth (recordings of the ``convoy_dev``
kind: ``truth_rel.csv`` beside the vehicles' folders, ``truth.csv`` in each).

``truth_rel.csv``: GPS time of week [s], the target's IMU point in the master's body frame
(x forward, y right, z down) [m] and the target's yaw minus the master's [deg], every 0.1 s.
``truth.csv`` (per vehicle): time of week, lat/lon/height of the IMU point, NED velocity,
roll/pitch/yaw [deg]. The GPS week is taken from the results' own times (a recording does not
cross a week boundary; a wrap of the time of week is unwrapped).

The truth is interpolated to each result's time of validity with a cubic spline (relative
position in a turning master frame is curved: over 0.1 s linear interpolation would err by up to
``a dt^2 / 8`` ~ 6 mm at 5 m/s^2 of relative acceleration, the spline by well under 1 mm).

Figures per target (``score_target``), over VALID rows:

* ``moving``: rows where both vehicles move (truth speed > ``moving_speed_mps``): horizontal
  error RMS/max, per-axis mean (a bias) and RMS;
* ``standstill``: the other VALID rows;
* ``moving_computed``: the same over every row that carries kinematics with both attitudes
  determined and both clocks synchronised (VALID, INCONSISTENT, SIGMA_EXCEEDED): the accuracy of
  the computation whatever its consistency flags;
* consistency: the fraction of rows with |error| <= 3 sigma per horizontal axis, the normalised
  errors' RMS (1 for an honest sigma), the median horizontal sigma against the horizontal RMS error,
  and every VALID row whose horizontal error exceeds max(0.3 m, 4 sigma_h) (``violations``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from v2xpos.timebase import SECONDS_PER_WEEK

MOVING_SPEED_MPS = 0.5
VIOLATION_FLOOR_M = 0.3
VIOLATION_SIGMAS = 4.0
HEADING_CHANGE_DEG = 1.0
"""A vehicle has "turned" once its course differs from its drive-off course by this much. A
horizontal lever-arm error ``dl`` moves the antenna against the IMU point by ``C_nb dl``, which
changes only with the heading: by ``|dl| dpsi`` after a heading change ``dpsi`` (Groves 2013
§14.2.7). Before a vehicle's first heading change no measurement depends on ``dl``, so a set-up
never verified cannot be vouched for there. 1° is generous (a 0.3 m error moves by 5 mm, below
RTK noise), so the share of the moving time after it is an upper bound on what such a set-up can
be VALID without trusting an untested declaration."""


@dataclass
class TruthTrack:
    """A truth series on full GPS seconds: ``t_s`` and columns by name."""
    t_s: np.ndarray
    cols: dict

    def at(self, name: str, t_s: np.ndarray) -> np.ndarray:
        """Column ``name`` at times ``t_s`` (cubic spline; NaN outside the series)."""
        from scipy.interpolate import CubicSpline
        y = self.cols[name]
        out = np.full(len(t_s), np.nan)
        inside = (t_s >= self.t_s[0]) & (t_s <= self.t_s[-1])
        if inside.any():
            out[inside] = CubicSpline(self.t_s, y)(t_s[inside])
        return out


def _read_tow_csv(path: Path, names: tuple, week: int) -> TruthTrack:
    data = np.loadtxt(path, delimiter=",", comments="#", ndmin=2)
    if data.shape[1] < len(names) + 1:
        raise ValueError(f"{path}: expected {len(names) + 1} columns, found {data.shape[1]}")
    tow = np.unwrap(data[:, 0], period=SECONDS_PER_WEEK)
    t = week * SECONDS_PER_WEEK + tow
    return TruthTrack(t, {n: data[:, k + 1] for k, n in enumerate(names)})


def read_truth_rel(path: str | Path, week: int) -> TruthTrack:
    """``truth_rel.csv`` on GPS week ``week``: columns x_m, y_m, z_m, rel_yaw_deg."""
    tr = _read_tow_csv(Path(path), ("x_m", "y_m", "z_m", "rel_yaw_deg"), week)
    tr.cols["rel_yaw_deg"] = np.degrees(np.unwrap(np.radians(tr.cols["rel_yaw_deg"])))
    return tr


def read_vehicle_truth(path: str | Path, week: int) -> TruthTrack:
    """A vehicle's ``truth.csv`` on GPS week ``week`` (adds ``speed_mps``, horizontal)."""
    tr = _read_tow_csv(Path(path), ("lat_deg", "lon_deg", "h_m", "vn", "ve", "vd", "roll_deg", "pitch_deg",
                                    "yaw_deg"), week)
    tr.cols["speed_mps"] = np.hypot(tr.cols["vn"], tr.cols["ve"])
    return tr


def week_of(t_gps_s: np.ndarray) -> int:
    """GPS week of a set of times (the first finite one)."""
    t = np.asarray(t_gps_s, float)
    t = t[np.isfinite(t)]
    if len(t) == 0:
        raise ValueError("no finite times to take the GPS week from")
    return int(t[0] // SECONDS_PER_WEEK)


def first_heading_change_s(track: TruthTrack, moving_speed_mps: float = MOVING_SPEED_MPS,
                           heading_change_deg: float = HEADING_CHANGE_DEG) -> float | None:
    """GPS time at which the course over ground ``atan2(ve, vn)`` first differs from the course of
    the first moving sample by more than ``heading_change_deg`` (only samples faster than
    ``moving_speed_mps``: the course of a car at rest is undefined). The course, not the IMU's yaw,
    so that a mounting (an IMU z-up, x backward) does not matter. None: it never turns."""
    speed = track.cols["speed_mps"]
    moving = np.flatnonzero(speed > moving_speed_mps)
    if len(moving) == 0:
        return None
    course = np.arctan2(track.cols["ve"][moving], track.cols["vn"][moving])
    turned = np.abs(np.angle(np.exp(1j * (course - course[0])))) > math.radians(heading_change_deg)
    return float(track.t_s[moving][np.argmax(turned)]) if turned.any() else None


def _rms(x: np.ndarray) -> float | None:
    return float(np.sqrt(np.mean(x ** 2))) if len(x) else None


def score_target(rows: dict, target: str, truth_rel: TruthTrack, master_truth: TruthTrack | None = None,
                 target_truth: TruthTrack | None = None, moving_speed_mps: float = MOVING_SPEED_MPS) -> dict:
    """Figures of one target's rows of a results.csv (``v2xpos.output.results_csv.read_results_csv``)
    against the truth (see the module docstring). Without the vehicles' truth every VALID row
    counts as moving."""
    sel = rows["target"] == target
    status = rows["status"][sel]
    t = rows["t_gps_s"][sel]
    counts = {str(s): int(n) for s, n in zip(*np.unique(status, return_counts=True))}
    valid = status == "VALID"
    out: dict = {"target": target, "rows": int(sel.sum()), "status_counts": counts,
                 "valid_fraction": float(valid.mean()) if len(valid) else 0.0}
    tv = t[valid]
    x, y = rows["x_m"][sel][valid], rows["y_m"][sel][valid]
    sx, sy = rows["sd_x_m"][sel][valid], rows["sd_y_m"][sel][valid]
    ex = x - truth_rel.at("x_m", tv)
    ey = y - truth_rel.at("y_m", tv)
    known = np.isfinite(ex) & np.isfinite(ey)
    moving = np.ones(len(tv), bool)
    if master_truth is not None and target_truth is not None:
        moving = ((master_truth.at("speed_mps", tv) > moving_speed_mps)
                  & (target_truth.at("speed_mps", tv) > moving_speed_mps))
    eh = np.hypot(ex, ey)
    sh = np.hypot(sx, sy)

    def block(m: np.ndarray) -> dict:
        m = m & known
        return {"n": int(m.sum()), "h_rms_m": _rms(eh[m]), "h_max_m": float(eh[m].max()) if m.any() else None,
                "x_mean_m": float(ex[m].mean()) if m.any() else None, "y_mean_m": float(ey[m].mean()) if m.any() else None,
                "x_rms_m": _rms(ex[m]), "y_rms_m": _rms(ey[m])}

    out["moving"] = block(moving)
    # availability while both move: the VALID share of those rows and the time from the first
    # instant both move to the first VALID row (None: never VALID, or no vehicle truth)
    if master_truth is not None and target_truth is not None and len(t):
        both = ((master_truth.at("speed_mps", t) > moving_speed_mps)
                & (target_truth.at("speed_mps", t) > moving_speed_mps))
        out["moving_valid_fraction"] = float(valid[both].mean()) if both.any() else None
        first_valid = t[valid & both]
        out["time_to_first_valid_s"] = (float(first_valid[0] - t[both][0]) if both.any() and len(first_valid)
                                        else None)
        # the share of that time after both vehicles' first heading change (HEADING_CHANGE_DEG): the
        # most a set-up never verified can be VALID without vouching for a lever arm no data tested
        turns = [first_heading_change_s(master_truth, moving_speed_mps), first_heading_change_s(target_truth, moving_speed_mps)]
        t_turned = math.inf if None in turns else max(turns)
        out["moving_after_turn_fraction"] = float(np.mean(t[both] >= t_turned)) if both.any() else None
        out["time_to_turn_s"] = float(t_turned - t[both][0]) if both.any() and math.isfinite(t_turned) else None
    out["standstill"] = block(~moving)
    # the computed kinematics of every status that carries them (VALID or flagged), while both move:
    # the accuracy of the computation itself, e.g. to compare two runs whose flags differ
    computed = np.isfinite(rows["x_m"][sel]) & ~np.isin(status, ("ATTITUDE_UNCERTAIN", "CLOCK_UNSYNCED"))
    tc = t[computed]
    cx = rows["x_m"][sel][computed] - truth_rel.at("x_m", tc)
    cy = rows["y_m"][sel][computed] - truth_rel.at("y_m", tc)
    cm = np.isfinite(cx) & np.isfinite(cy)
    if master_truth is not None and target_truth is not None:
        cm &= (master_truth.at("speed_mps", tc) > moving_speed_mps) & (target_truth.at("speed_mps", tc) > moving_speed_mps)
    out["moving_computed"] = {"n": int(cm.sum()), "h_rms_m": _rms(np.hypot(cx[cm], cy[cm])),
                              "x_mean_m": float(cx[cm].mean()) if cm.any() else None,
                              "y_mean_m": float(cy[cm].mean()) if cm.any() else None}
    k = known
    if k.any():
        zx, zy = ex[k] / sx[k], ey[k] / sy[k]
        out["within_3sd_x"] = float(np.mean(np.abs(zx) <= 3.0))
        out["within_3sd_y"] = float(np.mean(np.abs(zy) <= 3.0))
        out["normalised_rms_x"] = _rms(zx)
        out["normalised_rms_y"] = _rms(zy)
        out["median_sigma_h_m"] = float(np.median(sh[k]))
        h_rms = out["moving"]["h_rms_m"] or _rms(eh[k])
        out["median_sigma_h_over_h_rms"] = float(out["median_sigma_h_m"] / h_rms) if h_rms else None
        bound = np.maximum(VIOLATION_FLOOR_M, VIOLATION_SIGMAS * sh[k])
        bad = eh[k] > bound
        out["violations"] = int(bad.sum())
        out["violation_examples"] = [{"t_gps_s": float(tv[k][i]), "h_err_m": float(eh[k][i]),
                                      "sigma_h_m": float(sh[k][i])} for i in np.flatnonzero(bad)[:5]]
    out["truth_missing"] = int((~known).sum())
    return out


def score_results_csv(results_csv: str | Path, truth_rel_csv: str | Path, vehicle_truth: dict | None = None,
                      master_id: str | None = None) -> dict:
    """Score every target of a results.csv. ``vehicle_truth``: vehicle id -> its truth.csv (the
    master's and the targets', for the moving/standstill split; optional)."""
    from v2xpos.output.results_csv import read_results_csv
    rows = read_results_csv(results_csv)
    if len(rows["t_gps_s"]) == 0:
        raise ValueError(f"{results_csv}: no result rows")
    week = week_of(rows["t_gps_s"])
    truth_rel = read_truth_rel(truth_rel_csv, week)
    vt = {k: read_vehicle_truth(p, week) for k, p in (vehicle_truth or {}).items() if p is not None and Path(p).is_file()}
    targets = sorted(set(rows["target"].tolist()))
    return {"results_csv": str(results_csv), "truth_rel_csv": str(truth_rel_csv),
            "targets": {tg: score_target(rows, tg, truth_rel, vt.get(master_id), vt.get(tg)) for tg in targets}}


def format_score(score: dict) -> str:
    """A few human-readable lines of ``score_results_csv``'s output."""
    lines = []
    for tg, s in score["targets"].items():
        mv = s["moving"]
        f = (lambda v, d=3: "-" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:.{d}f}")
        lines.append(f"  {tg}: rows {s['rows']}, VALID {100 * s['valid_fraction']:.1f} %; while both move: "
                     f"h RMS {f(mv['h_rms_m'])} m (max {f(mv['h_max_m'])}, bias x {f(mv['x_mean_m'])} "
                     f"y {f(mv['y_mean_m'])}) over {mv['n']} rows; within 3 sd x/y "
                     f"{f(s.get('within_3sd_x'), 3)}/{f(s.get('within_3sd_y'), 3)}; median sigma_h "
                     f"{f(s.get('median_sigma_h_m'))} m; violations {s.get('violations', '-')}")
    return "\n".join(lines)
