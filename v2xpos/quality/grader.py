"""Grading of a vehicle's IMU units: batch (``grade_units``) and incremental (``VehicleGrader``).

``grade_units`` runs ``unit_comparison.compare_units`` (time sync, alignment, first parameter for every
pair), scores every unit by consensus, adds the optional second parameter (fused-solution
differences), the pose-aided rate check and the bias stability between stops, and returns a
plain dict (the ``v2xpos grade`` JSON). ``VehicleGrader`` keeps a bounded history of samples per
unit as they arrive and re-grades it on demand. Key names are documented in docs/quality.md.
"""
from __future__ import annotations

import threading

import numpy as np

from v2xpos.types import ImuData

from . import unit_rotation
from .bias import unit_bias_stability
from .consistency import box_stats, pcc_stats
from .unit_comparison import AXES, UnitComparison, GradeConfig, compare_units
from .verdict import Thresholds, accel_pcc_check, check, fused_checks, unit_checks, worst


def _per_axis(values: np.ndarray, scale: float = 1.0) -> list[float]:
    return [float(v) * scale for v in values]


def _finite_or_none(values: np.ndarray) -> list[float | None]:
    return [float(v) if np.isfinite(v) else None for v in values]


def _pair_block(fc: UnitComparison, ref: str, uid: str, cfg: GradeConfig,
                mounting: dict | None) -> dict:
    """Per-axis first-parameter values of uid against ref (ref's axes)."""
    p = fc.pair_direct(ref, uid, cfg, mounting)
    (pcc_g, n_g), (pcc_a, n_a) = p.gyro.median_pcc(), p.accel.median_pcc()
    r2d = np.degrees(1.0)
    g_rmse, a_rmse = p.gyro.rmse, p.accel.rmse
    block = {
        "compared_with": ref,
        "rmse": {"gyro": _per_axis(np.median(g_rmse, axis=0), r2d),
                 "accel": _per_axis(np.median(a_rmse, axis=0))},
        "pcc": {"gyro": _finite_or_none(pcc_g), "accel": _finite_or_none(pcc_a)},
        "pcc_signal_windows": {"gyro": n_g.tolist(), "accel": n_a.tolist()},
        "rmse_stats": {"gyro": {a: box_stats(g_rmse[:, k] * r2d) for k, a in enumerate(AXES)},
                       "accel": {a: box_stats(a_rmse[:, k]) for k, a in enumerate(AXES)}},
        "pcc_stats": {"gyro": pcc_stats(p.gyro.pcc), "accel": pcc_stats(p.accel.pcc)},
        "n_windows": int(len(g_rmse)),
        "time_offset_ms": 1e3 * p.offset_s,
        "time_offset_estimated": p.offset_estimated,
        "scale_gyro": [None if not np.isfinite(s) else float(s) for s in p.scale_gyro],
        "relative_rotation": {
            "frame": f"{uid} axes -> {ref} axes",
            "C_ref_unit": p.C_ref_ut.tolist(),
            "euler_xyz_deg": unit_rotation.euler_xyz_deg_from_dcm(p.C_ref_ut).tolist(),
            "angle_deg": unit_rotation.rotation_angle_deg(p.C_ref_ut),
            "source": p.rotation_source,
            "kabsch_condition": p.kabsch_condition,
        },
    }
    if p.C_declared is not None:
        block["relative_rotation"]["declared_euler_xyz_deg"] = unit_rotation.euler_xyz_deg_from_dcm(p.C_declared).tolist()
        block["relative_rotation"]["residual_vs_declared_deg"] = unit_rotation.rotation_angle_deg(p.C_declared.T @ p.C_ref_ut)
    return block


def choose_reference(scores: dict) -> str:
    """The unit agreeing best with the others (smallest gyro-noise score, then drift)."""
    return min(scores, key=lambda u: (scores[u]["noise_gyro_rps"]["score"], scores[u]["bias_drift_rps"]["score"]))


def grade_units(units: dict[str, ImuData], reference: str | None = None,
                mounting_xyz_deg: dict | None = None, thresholds: Thresholds | None = None,
                cfg: GradeConfig | None = None, fixes: dict | None = None,
                rate_check: dict | None = None, bias_stops: bool = True,
                extra_checks: dict[str, dict] | None = None) -> dict:
    """Grade every unit; returns the report dict (JSON-ready after ``public_report``).

    fixes: position fixes for the second parameter, {'t_s', 'r_ned_m' (N, 3 local NED), 'sd_m',
    'source'} on the units' time axis (GNSS converted to local NED, or a reference trajectory);
    rate_check: unit id -> ``RateCheckResult.as_dict()`` from a pose source. Both optional; units
    without them get no ``fused_diff`` / ``rate_check`` entry. extra_checks: unit id -> one more
    check dict (e.g. the recording's ``coverage``).
    """
    th = thresholds or Thresholds()
    cfg = cfg or GradeConfig()
    fc = compare_units(units, cfg, mounting_xyz_deg)
    scores = fc.scores()
    if reference is not None and reference not in fc.unit_ids:
        raise ValueError(f"reference unit {reference!r} is not among the units {fc.unit_ids}")
    ref = reference or choose_reference(scores)
    entries: dict[str, dict] = {}
    for uid in fc.unit_ids:
        partner = scores[uid]["noise_gyro_rps"]["partner"] if uid == ref else ref
        entries[uid] = {"id": uid, "reference": uid == ref,
                        **_pair_block(fc, partner, uid, cfg, mounting_xyz_deg)}
        if uid == ref:
            entries[uid]["time_offset_ms"] = 0.0
            entries[uid]["relative_rotation"] = {
                "frame": f"{uid} axes -> {ref} axes", "C_ref_unit": np.eye(3).tolist(),
                "euler_xyz_deg": [0.0, 0.0, 0.0], "angle_deg": 0.0, "source": "reference",
                "kabsch_condition": None}
    fused = None
    if fixes is not None and len(fixes.get("t_s", [])) >= 10:
        from .fused import fused_differences
        C_ref = {u: np.eye(3) if u == ref else np.asarray(entries[u]["relative_rotation"]["C_ref_unit"])
                 for u in fc.unit_ids}
        off = {u: 0.0 if u == ref else entries[u]["time_offset_ms"] / 1e3 for u in fc.unit_ids}
        try:
            fused = fused_differences(fc.units, ref, C_ref, fixes["t_s"], fixes["r_ned_m"],
                                      fix_sd_m=float(fixes.get("sd_m", 0.05)), time_offset_s=off)
            for v in fused.values():
                v["fix_source"] = fixes.get("source", v["fix_source"])
        except ValueError as exc:
            fused = None
            entries[ref]["fused_diff_error"] = str(exc)
    out_units = []
    for uid in fc.unit_ids:
        s = scores[uid]
        entry = entries[uid]
        stuck = float(max(fc.flatline[uid]["gyro"].max(), fc.flatline[uid]["accel"].max()))
        has_motion = any(fc.pair(uid, v).pcc_signal.any() for v in fc.unit_ids if v != uid)
        pcc_min = 1.0 - s["pcc_deficit"]["score"] if has_motion else None
        checks = unit_checks(uid, s, stuck, pcc_min, th)
        if has_motion and uid != ref:
            checks.append(accel_pcc_check(entry["pcc"]["accel"], th))
        if extra_checks and uid in extra_checks:
            checks.append(extra_checks[uid])
        if bias_stops:
            m = (mounting_xyz_deg or {}).get(uid)
            bs = unit_bias_stability(fc.units[uid], None if m is None else unit_rotation.mounting_dcm(m))
            entry["bias_stability"] = bs
            if bs["max_spread_dps"] is not None:
                checks.append(check("bias_stability", bs["max_spread_dps"], th.bias_spread_warn_dps,
                                    th.bias_spread_fail_dps, "deg/s"))
        if fused and uid in fused:
            entry["fused_diff"] = fused[uid]
            checks.extend(fused_checks(uid, fused, th))
        if rate_check and rate_check.get(uid) is not None:
            rc = rate_check[uid]
            entry["rate_check"] = rc
            checks.append({"name": "pose_rate", "value": rc.get("mean_diff_dps"), "unit": "deg/s",
                           "warn": None, "fail": rc.get("threshold_dps"),
                           "grade": "fail" if rc.get("anomaly") else "pass"})
        entry["consensus"] = s
        entry["checks"] = checks
        entry["grade"] = worst([c["grade"] for c in checks])
        out_units.append(entry)
    return {
        "reference": ref,
        "reference_chosen": "given" if reference else "auto",
        "n_units": len(fc.unit_ids),
        "duration_s": fc.duration_s,
        "rate_hz": fc.rate_hz,
        "dropped_samples": fc.dropped_samples,
        "window_s": cfg.window_s,
        "step_s": cfg.step_s,
        "consensus_k": fc.k_partner(),
        "units_order": fc.unit_ids,
        "thresholds": th.as_dict(),
        "units": out_units,
        "_comparison": fc,
    }


def public_report(report: dict) -> dict:
    """The report without internal objects (JSON-serialisable)."""
    return {k: v for k, v in report.items() if not k.startswith("_")}


class VehicleGrader:
    """Incremental grader of one vehicle's IMU units.

    Feed samples as they arrive (``add`` per unit, or ``add_aligned`` for all units at once),
    ask for ``grades()`` at any time. Memory is bounded by ``history_s`` per unit; the grading is
    recomputed on the retained history when at least ``regrade_every_s`` of new data arrived.
    Thread-safe (one lock). Units: t_s GPS seconds, gyro rad/s, accel m/s^2, unit axes.
    """

    def __init__(self, unit_ids: list[str], history_s: float = 120.0, min_history_s: float = 10.0,
                 regrade_every_s: float = 5.0, reference: str | None = None,
                 mounting_xyz_deg: dict | None = None, thresholds: Thresholds | None = None,
                 cfg: GradeConfig | None = None):
        if len(unit_ids) < 2:
            raise ValueError("VehicleGrader needs at least two unit ids")
        self.unit_ids = list(unit_ids)
        self.history_s = history_s
        self.min_history_s = min_history_s
        self.regrade_every_s = regrade_every_s
        self.reference = reference
        self.mounting_xyz_deg = mounting_xyz_deg
        self.thresholds = thresholds or Thresholds()
        self.cfg = cfg or GradeConfig()
        self._chunks: dict[str, list[np.ndarray]] = {u: [] for u in self.unit_ids}
        self._last_t: dict[str, float] = {u: -np.inf for u in self.unit_ids}
        self._graded_at: float | None = None
        self._report: dict | None = None
        self.rejected_samples = 0
        self._lock = threading.Lock()

    def add(self, unit_id: str, t_s: np.ndarray, gyro_rps: np.ndarray, acc_mps2: np.ndarray) -> int:
        """Append one or more samples of one unit (t [s], gyro (N, 3) [rad/s], accel (N, 3) [m/s^2]);
        returns how many were accepted. Samples of an unknown unit, non-numeric, non-finite, or not
        later than the unit's last sample are rejected (counted; non-numeric input counts as one)."""
        try:
            t = np.atleast_1d(np.asarray(t_s, float))
            g = np.atleast_2d(np.asarray(gyro_rps, float))
            a = np.atleast_2d(np.asarray(acc_mps2, float))
        except (TypeError, ValueError):
            self.rejected_samples += 1
            return 0
        if unit_id not in self._chunks or g.shape != (len(t), 3) or a.shape != (len(t), 3):
            self.rejected_samples += len(t)
            return 0
        with self._lock:
            ok = np.isfinite(t) & np.all(np.isfinite(g), axis=1) & np.all(np.isfinite(a), axis=1)
            tt = np.where(ok, t, -np.inf)
            prev_max = np.maximum.accumulate(np.concatenate([[self._last_t[unit_id]], tt]))[:-1]
            keep = ok & (t > prev_max)
            self.rejected_samples += int(len(t) - keep.sum())
            if keep.any():
                self._chunks[unit_id].append(np.column_stack([t[keep], g[keep], a[keep]]))
                self._last_t[unit_id] = float(t[keep][-1])
                self._trim(unit_id)
            return int(keep.sum())

    def add_aligned(self, t_s: float, samples: dict) -> None:
        """One time step for several units: samples = {unit_id: (gyro_rps (3,), acc_mps2 (3,))}."""
        for uid, (g, a) in samples.items():
            self.add(uid, [t_s], [g], [a])

    def _trim(self, uid: str) -> None:
        chunks = self._chunks[uid]
        if len(chunks) > 64:
            chunks[:] = [np.concatenate(chunks)]
        t_end = self._last_t[uid]
        while chunks and chunks[0][-1, 0] < t_end - self.history_s:
            chunks.pop(0)
        if chunks and chunks[0][0, 0] < t_end - self.history_s:
            c = chunks[0]
            chunks[0] = c[c[:, 0] >= t_end - self.history_s]

    def _units(self) -> dict[str, ImuData]:
        out = {}
        for uid, chunks in self._chunks.items():
            if not chunks:
                continue
            d = np.concatenate(chunks)
            out[uid] = ImuData(t_s=d[:, 0], gyro_rps=d[:, 1:4], acc_mps2=d[:, 4:7])
        return out

    def grades(self, force: bool = False) -> dict:
        """Current grades: {'t_s', 'status', 'units': {id: grade}, 'report': full report or None}.

        status is 'collecting' until every unit has min_history_s of overlapping data.
        """
        with self._lock:
            units = self._units()
            t_now = min((float(u.t_s[-1]) for u in units.values()), default=None)
            overlap = 0.0
            if len(units) == len(self.unit_ids):
                overlap = t_now - max(float(u.t_s[0]) for u in units.values())
            if overlap < self.min_history_s:
                return {"t_s": t_now, "status": "collecting", "units": {u: None for u in self.unit_ids},
                        "report": None, "rejected_samples": self.rejected_samples}
            due = (force or self._report is None or self._graded_at is None
                   or t_now - self._graded_at >= self.regrade_every_s)
            if due:
                rep = grade_units(units, self.reference, self.mounting_xyz_deg, self.thresholds, self.cfg)
                self._report = public_report(rep)
                self._graded_at = t_now
            rep = self._report
            return {"t_s": self._graded_at, "status": "graded",
                    "units": {u["id"]: u["grade"] for u in rep["units"]}, "report": rep,
                    "rejected_samples": self.rejected_samples}


UnitGrader = VehicleGrader
"""Alias: the incremental grader of a vehicle's units (one instance per vehicle)."""
