"""Compare the IMU units of one vehicle pairwise and score each unit against the others (the first
parameter: window consistency of the aligned angular rates, plus scale and bias stability).

Pipeline for every pair of units (u, v):

1. time sync: clock offset from the gyro-norm cross-correlation (``timesync``), v resampled
   onto u's grid at ``t + offset``; refined after alignment with the per-axis correlation;
2. attitude alignment: declared mounting (``C_u_v = C_body_u^T C_body_v``) or, when not declared,
   the Kabsch fit of v's angular rates onto u's (``unit_rotation``);
3. first parameter: sliding-window RMSE / PCC / mean difference per axis (``consistency``), plus
   the relative scale factor (TLS slope on low-passed rates) and the bias stability (spread of the
   window mean differences over the run).

Each pairwise feature is a "badness" d(u, v). A unit's score is the k-th smallest of its d(u, v)
over the other units, k = ceil((N - 1) / 2): a unit is as good as its agreement with at least half
of the others, so one faulty unit cannot make a healthy one look bad. For N >= 3 the consensus
baseline of u is the median of d over the pairs that do not involve u; relative checks compare
score / baseline. The verdict (``verdict``) turns scores into pass / warn / fail.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from itertools import combinations

import numpy as np

from v2xpos.types import ImuData

from . import unit_rotation
from .consistency import (PCC_MIN_SIGNAL_WINDOWS, WindowSeries, longest_constant_run_s, relative_scale,
                          turning_mask, robust_range,
                          sliding_window_metrics)
from .timesync import common_grid, gyro_norm_offset_s, median_rate_hz, resample, vector_offset_s

AXES = ("x", "y", "z")


@dataclass
class GradeConfig:
    """Processing settings (not thresholds; those are in ``verdict.Thresholds``).

    window_s / step_s: sliding window length and step [s]; max_offset_s: largest clock offset
    searched [s]; sync_cutoff_hz: low-pass before the offset correlation; scale_cutoff_hz and
    min_scale_signal_dps: low-pass and minimum reference rate s.d. for the scale estimate;
    estimate_offsets: False to trust the time stamps as they are; min_kabsch_condition: below
    this conditioning of the angular rates (``unit_rotation.kabsch_condition``) the rotation is not
    estimated from the data and the declared mounting is used (identity, reported as not
    observable, when there is none); min_align_motion_dps: likewise when the rates' RMS along their
    second principal direction is below this (noise alone would give a random rotation); min_sync_motion_dps / min_sync_corr: the clock offset is
    estimated only when the reference's rate norm varies by at least this s.d. and the norms
    correlate at least this well (a vehicle at rest carries no timing information).
    """
    window_s: float = 1.0
    step_s: float = 0.5
    max_offset_s: float = 0.2
    sync_cutoff_hz: float = 10.0
    scale_cutoff_hz: float = 5.0
    min_scale_signal_dps: float = 3.0
    estimate_offsets: bool = True
    rate_hz: float | None = None
    min_kabsch_condition: float = 0.02
    min_align_motion_dps: float = 1.0
    min_sync_motion_dps: float = 1.0
    min_sync_corr: float = 0.5


@dataclass
class PairResult:
    """Comparison of unit ``ut`` against unit ``ref`` (ut data expressed in ref's axes and clock).

    C_ref_ut: rotation ut axes -> ref axes; offset_s: clock offset of ut against ref
    (``ut(t + offset) ~ ref(t)``); gyro in rad/s, accel in m/s^2; scale: per-axis TLS slope
    ut/ref (NaN where not observable); pcc_signal: True for axes with at least ``PCC_MIN_SIGNAL_WINDOWS``
    gyro windows whose signal stands out of the noise (``WindowSeries.signal``), so that a median
    window PCC means something.
    """
    ref: str
    ut: str
    offset_s: float
    offset_peak_corr: float
    C_ref_ut: np.ndarray
    rotation_source: str
    kabsch_condition: float | None
    gyro: WindowSeries
    accel: WindowSeries
    scale_gyro: np.ndarray
    pcc_signal: np.ndarray
    ref_gyro_sd_rps: np.ndarray = field(default_factory=lambda: np.zeros(3))
    C_declared: np.ndarray | None = None
    offset_estimated: bool = True

    def badness(self) -> dict:
        """Scalar pairwise features (larger = worse) used for consensus scoring.

        noise_*: norm over axes of the upper quartile of the window s.d. of the difference (RMSE
        without the window's mean difference, so constant bias differences do not count);
        bias_drift_rps: norm over axes of the P95 - P5 spread of the window mean differences;
        time_offset_s: |clock offset|; scale_error: largest |scale - 1| over observable axes;
        pcc_deficit: largest 1 - median window PCC over axes with motion, the median over the
        windows where the quieter unit's signal stands out of the noise (``WindowSeries.signal``).
        """
        g_noise = np.percentile(self.gyro.difference_sd(), 75, axis=0)
        a_noise = np.percentile(self.accel.difference_sd(), 75, axis=0)
        drift = robust_range(self.gyro.mean_diff)
        pcc_med, _ = self.gyro.median_pcc()
        sig = self.pcc_signal
        sc = self.scale_gyro[np.isfinite(self.scale_gyro)]
        return {
            "noise_gyro_rps": float(np.linalg.norm(g_noise)),
            "noise_accel_mps2": float(np.linalg.norm(a_noise)),
            "bias_drift_rps": float(np.linalg.norm(drift)),
            "time_offset_s": float(abs(self.offset_s)),
            "scale_error": float(np.max(np.abs(sc - 1.0))) if sc.size else 0.0,
            "pcc_deficit": float(np.max(1.0 - pcc_med[sig])) if sig.any() else 0.0,
        }


def _valid_imu(uid: str, imu: ImuData) -> tuple[ImuData, int]:
    """Drop non-finite or non-increasing samples; return the cleaned data and how many were dropped."""
    t = np.asarray(imu.t_s, float)
    g = np.asarray(imu.gyro_rps, float)
    a = np.asarray(imu.acc_mps2, float)
    ok = np.isfinite(t) & np.all(np.isfinite(g), axis=1) & np.all(np.isfinite(a), axis=1)
    t, g, a = t[ok], g[ok], a[ok]
    if len(t) > 1:
        keep = np.concatenate([[True], np.diff(t) > 0])
        while not keep.all():
            t, g, a = t[keep], g[keep], a[keep]
            keep = np.concatenate([[True], np.diff(t) > 0])
    if len(t) < 16:
        raise ValueError(f"unit {uid!r}: only {len(t)} valid samples, need at least 16")
    return ImuData(t_s=t, acc_mps2=a, gyro_rps=g), int(len(imu.t_s) - len(t))


def compare_pair(ref_id: str, ref: ImuData, ut_id: str, ut: ImuData, cfg: GradeConfig,
                 C_ref_ut_declared: np.ndarray | None = None) -> PairResult:
    """Time-sync, align and compare unit ``ut`` against unit ``ref`` (see module doc)."""
    motion_dps = float(np.degrees(np.std(np.linalg.norm(ref.gyro_rps, axis=1))))
    sync = cfg.estimate_offsets and motion_dps >= cfg.min_sync_motion_dps
    offset, peak = (gyro_norm_offset_s(ref, ut, cfg.max_offset_s, cfg.sync_cutoff_hz)
                    if sync else (0.0, float("nan")))
    if sync and not peak >= cfg.min_sync_corr:
        sync, offset = False, 0.0
    margin = cfg.max_offset_s + 2.0 / median_rate_hz(ut.t_s)
    grid = common_grid({"ref": ref, "ut": ut}, cfg.rate_hz or median_rate_hz(ref.t_s), margin)
    rate = median_rate_hz(grid) if len(grid) > 1 else median_rate_hz(ref.t_s)
    g_ref = resample(ref.t_s, ref.gyro_rps, grid)
    a_ref = resample(ref.t_s, ref.acc_mps2, grid)

    def ut_at(off: float) -> tuple[np.ndarray, np.ndarray]:
        return resample(ut.t_s, ut.gyro_rps, grid + off), resample(ut.t_s, ut.acc_mps2, grid + off)

    g_ut, a_ut = ut_at(offset)
    C_decl = None if C_ref_ut_declared is None else np.asarray(C_ref_ut_declared, float)

    def align(g_u: np.ndarray) -> tuple[np.ndarray, str, float]:
        cond = unit_rotation.kabsch_condition(g_u)
        second_dps = float(np.degrees(unit_rotation.principal_rates_rps(g_u)[1]))
        if cond < cfg.min_kabsch_condition or second_dps < cfg.min_align_motion_dps:
            if C_decl is not None:
                return C_decl, "declared", cond
            return np.eye(3), "not observable (identity assumed)", cond
        return unit_rotation.kabsch_rotation(g_ref, g_u), "estimated", cond

    C, source, cond = align(g_ut)
    if sync and len(grid) > 8 * cfg.window_s * rate:
        fine = vector_offset_s(grid, g_ref, unit_rotation.rotate(g_ut, C), max_lag_s=min(0.05, cfg.max_offset_s),
                               cutoff_hz=cfg.sync_cutoff_hz)
        if abs(fine) > 0.0:
            offset += fine
            g_ut, a_ut = ut_at(offset)
            C, source, cond = align(g_ut)
    g_al = unit_rotation.rotate(g_ut, C)
    a_al = unit_rotation.rotate(a_ut, C)
    wn = max(2, int(round(cfg.window_s * rate)))
    sn = max(1, int(round(cfg.step_s * rate)))
    gw = sliding_window_metrics(grid, g_ref, g_al, wn, sn)
    aw = sliding_window_metrics(grid, a_ref, a_al, wn, sn)
    min_sd = np.radians(cfg.min_scale_signal_dps)
    scale = relative_scale(g_ref, g_al, rate, cfg.scale_cutoff_hz, min_sd)
    sd_ref = np.std(g_ref, axis=0)
    _, n_signal = gw.median_pcc()
    return PairResult(ref=ref_id, ut=ut_id, offset_s=float(offset), offset_peak_corr=float(peak),
                      C_ref_ut=C, rotation_source=source, kabsch_condition=cond, gyro=gw, accel=aw,
                      scale_gyro=scale, pcc_signal=n_signal >= PCC_MIN_SIGNAL_WINDOWS, ref_gyro_sd_rps=sd_ref,
                      C_declared=C_decl, offset_estimated=bool(sync))


def _swap(p: PairResult) -> PairResult:
    """The same comparison seen from the other unit (metrics symmetric, offset/scale inverted).

    Window RMSE/PCC/mean difference are re-expressed approximately: the RMSE and PCC of a pair do
    not depend on which unit is the reference up to the rotation of the axes, which is small for
    nearly co-aligned units and exact for the norms used by the consensus scores.
    """
    inv = lambda s: 1.0 / s if np.isfinite(s) and s != 0 else np.nan  # noqa: E731
    gw, aw = p.gyro.swapped(), p.accel.swapped()
    return PairResult(ref=p.ut, ut=p.ref, offset_s=-p.offset_s, offset_peak_corr=p.offset_peak_corr,
                      offset_estimated=p.offset_estimated,
                      C_ref_ut=p.C_ref_ut.T, rotation_source=p.rotation_source,
                      kabsch_condition=p.kabsch_condition, gyro=gw, accel=aw,
                      scale_gyro=np.array([inv(s) for s in p.scale_gyro]), pcc_signal=p.pcc_signal,
                      ref_gyro_sd_rps=p.ref_gyro_sd_rps,
                      C_declared=None if p.C_declared is None else p.C_declared.T)


@dataclass
class UnitComparison:
    """All pairwise comparisons of a vehicle's units plus per-unit raw-data checks."""
    unit_ids: list[str]
    pairs: dict[tuple[str, str], PairResult]
    flatline: dict[str, dict[str, np.ndarray]]
    units: dict[str, ImuData]
    dropped_samples: dict[str, int]
    rate_hz: dict[str, float]
    duration_s: float

    def pair(self, ref: str, ut: str) -> PairResult:
        """Comparison of ut against ref, in either stored direction."""
        if (ref, ut) in self.pairs:
            return self.pairs[(ref, ut)]
        return _swap(self.pairs[(ut, ref)])

    def pair_direct(self, ref: str, ut: str, cfg: GradeConfig,
                    mounting_xyz_deg: dict | None = None) -> PairResult:
        """Comparison of ut against ref computed in that direction (per-axis values in ref's
        axes); recomputed when only the opposite direction is stored."""
        if (ref, ut) in self.pairs:
            return self.pairs[(ref, ut)]
        m = mounting_xyz_deg or {}
        C = (unit_rotation.relative_from_mounting(unit_rotation.mounting_dcm(m[ref]), unit_rotation.mounting_dcm(m[ut]))
             if m.get(ref) is not None and m.get(ut) is not None else None)
        p = compare_pair(ref, self.units[ref], ut, self.units[ut], cfg, C)
        self.pairs[(ref, ut)] = p
        return p

    def k_partner(self) -> int:
        """k of the k-th smallest rule: ceil((N - 1) / 2), at least 1."""
        return max(1, int(np.ceil((len(self.unit_ids) - 1) / 2)))

    def scores(self) -> dict[str, dict]:
        """Per unit and feature: score (k-th smallest pairwise badness), best partner, baseline."""
        ids = self.unit_ids
        bad = {key: self.pairs[key].badness() for key in self.pairs}

        def d(u: str, v: str, f: str) -> float:
            return bad[(u, v)][f] if (u, v) in bad else bad[(v, u)][f]

        k = self.k_partner()
        out: dict[str, dict] = {}
        features = next(iter(bad.values())).keys() if bad else []
        for u in ids:
            others = [v for v in ids if v != u]
            rest = [(a, b) for a, b in combinations(ids, 2) if u not in (a, b)]
            out[u] = {}
            for f in features:
                vals = sorted((d(u, v, f), v) for v in others)
                base = float(np.median([d(a, b, f) for a, b in rest])) if rest else None
                out[u][f] = {"score": vals[k - 1][0], "partner": vals[0][1], "baseline": base}
        return out


def compare_units(units: dict[str, ImuData], cfg: GradeConfig | None = None,
                  mounting_xyz_deg: dict[str, np.ndarray | None] | None = None) -> UnitComparison:
    """Run ``compare_pair`` on every pair of units and the raw-data checks on every unit.

    mounting_xyz_deg: declared mounting angles per unit (X-Y-Z order, deg, unit -> body); pairs
    where both are declared use them, all others estimate the rotation from the data.
    """
    cfg = cfg or GradeConfig()
    if len(units) < 2:
        raise ValueError(f"grading needs at least two IMU units, got {len(units)}")
    mounting_xyz_deg = mounting_xyz_deg or {}
    clean: dict[str, ImuData] = {}
    dropped: dict[str, int] = {}
    for uid, imu in units.items():
        clean[uid], dropped[uid] = _valid_imu(uid, imu)
    ids = list(clean)
    pairs = {}
    for a, b in combinations(ids, 2):
        ma, mb = mounting_xyz_deg.get(a), mounting_xyz_deg.get(b)
        C_decl = (unit_rotation.relative_from_mounting(unit_rotation.mounting_dcm(ma), unit_rotation.mounting_dcm(mb))
                  if ma is not None and mb is not None else None)
        pairs[(a, b)] = compare_pair(a, clean[a], b, clean[b], cfg, C_decl)
    flat = {}
    for u in ids:
        c = clean[u]
        turning = turning_mask(c.t_s, c.gyro_rps)
        flat[u] = {"gyro": longest_constant_run_s(c.t_s, c.gyro_rps, turning),
                   "accel": longest_constant_run_s(c.t_s, c.acc_mps2, turning)}
    t0 = max(float(c.t_s[0]) for c in clean.values())
    t1 = min(float(c.t_s[-1]) for c in clean.values())
    return UnitComparison(unit_ids=ids, pairs=pairs, flatline=flat, units=clean, dropped_samples=dropped,
                           rate_hz={u: median_rate_hz(clean[u].t_s) for u in ids},
                           duration_s=max(0.0, t1 - t0))
