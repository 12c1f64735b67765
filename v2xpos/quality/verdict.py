"""Verdict: pass / warn / fail per IMU unit from documented thresholds.

Absolute checks (any number of units):
    stuck channel     longest run of identical raw samples    warn > 0.2 s,  fail > 0.5 s
                      while the unit turns (|w| > 2 deg/s)
    clock offset      |offset| to the agreeing partner        warn > 8 ms,   fail > 9 ms
    gyro scale        |TLS slope - 1| (low-passed, >= 3 dps)  warn > 1.5 %,  fail > 2 %
    gyro similarity   median window PCC, axes with motion     warn < 0.75,   fail < 0.5
    fused difference  P90 attitude / position difference     (two units only) warn > 5 deg / 1 m,
                                                              fail > 15 deg / 3 m
    fused plausible   P90 attitude / position difference     fail > 45 deg / 10 m, with any number
                                                              of units (a ratio to equally bad
                                                              units would pass)
    accel similarity  best axis median window accel PCC       warn < 0.5, fail < 0.3 (not the
                      against the reference, with motion      reference itself)
    pose-aided rate   mean |w_pose| - |w_gyro| difference     anomaly -> fail
    bias stability    spread of per-stop gyro biases (>= 2)   warn > 0.1 deg/s, fail > 0.3 deg/s

Consensus checks (three or more units), ratio of the unit's score to the median of the same
feature over the pairs of the other units (floors keep tiny differences from producing large
ratios):
    gyro noise        ratio warn > 1.6, fail > 2.0   (floor 0.02 deg/s)
    accel noise       ratio warn > 1.6, fail > 2.5   (floor 0.01 m/s^2)
    gyro bias drift   ratio warn > 2.5, fail > 4.0   (floor 0.05 deg/s)
    fused attitude    P90 against the reference / median P90 of the other units,
                      ratio warn > 2.0, fail > 3.0   (floor 0.1 deg)
    fused position    same with position, warn > 2.0, fail > 3.0 (floor 0.02 m)

The grade is the worst outcome over the checks. Reasons for the chosen levels are in
docs/quality.md (noise x5 -> ratio ~3.6; 0.5 deg/s step vs. the healthy window-mean spread; the
10 ms skew vs. the real clock offsets between healthy units).
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

GRADES = ("pass", "warn", "fail")


@dataclass
class Thresholds:
    """Warn / fail levels of every check (units in the names)."""
    stuck_warn_s: float = 0.2
    stuck_fail_s: float = 0.5
    offset_warn_ms: float = 8.0
    offset_fail_ms: float = 9.0
    scale_warn: float = 0.015
    scale_fail: float = 0.02
    pcc_warn: float = 0.75
    pcc_fail: float = 0.5
    noise_gyro_warn_ratio: float = 1.6
    noise_gyro_fail_ratio: float = 2.0
    noise_gyro_floor_dps: float = 0.02
    noise_accel_warn_ratio: float = 1.6
    noise_accel_fail_ratio: float = 2.5
    noise_accel_floor_mps2: float = 0.01
    drift_warn_ratio: float = 2.5
    drift_fail_ratio: float = 4.0
    drift_floor_dps: float = 0.05
    bias_spread_warn_dps: float = 0.1
    bias_spread_fail_dps: float = 0.3
    fused_att_warn_deg: float = 5.0
    fused_att_fail_deg: float = 15.0
    fused_pos_warn_m: float = 1.0
    fused_pos_fail_m: float = 3.0
    fused_warn_ratio: float = 2.0
    fused_fail_ratio: float = 3.0
    fused_att_floor_deg: float = 0.1
    fused_pos_floor_m: float = 0.02
    fused_att_implausible_deg: float = 45.0
    fused_pos_implausible_m: float = 10.0
    accel_pcc_warn: float = 0.5
    accel_pcc_fail: float = 0.3

    def as_dict(self) -> dict:
        return asdict(self)


def _level(value: float, warn: float, fail: float, above: bool = True) -> str:
    if value is None or not np.isfinite(value):
        return "pass"
    if above:
        return "fail" if value > fail else "warn" if value > warn else "pass"
    return "fail" if value < fail else "warn" if value < warn else "pass"


def worst(grades: list[str]) -> str:
    """The worst of a list of grades ('pass' for an empty list)."""
    return max(grades, key=GRADES.index) if grades else "pass"


def check(name: str, value: float, warn: float, fail: float, unit: str, above: bool = True,
          **extra) -> dict:
    """One check as a plain dict: name, value, unit, warn/fail levels and the outcome."""
    v = None if value is None or not np.isfinite(value) else float(value)
    return {"name": name, "value": v, "unit": unit, "warn": warn, "fail": fail,
            "grade": _level(v, warn, fail, above), **extra}


def ratio_check(name: str, score: float, baseline: float | None, floor: float, warn: float,
                fail: float) -> dict | None:
    """Consensus check: score / max(baseline, floor); None when there is no baseline (N < 3)."""
    if baseline is None:
        return None
    ratio = score / max(baseline, floor)
    return check(name, ratio, warn, fail, "ratio", score=float(score), baseline=float(baseline))


def unit_checks(unit: str, scores: dict, stuck_s: float, pcc_min: float | None,
                th: Thresholds) -> list[dict]:
    """The first-parameter checks of one unit from its consensus scores (``UnitComparison.scores``)."""
    s = scores
    out = [
        check("stuck_channel", stuck_s, th.stuck_warn_s, th.stuck_fail_s, "s"),
        check("clock_offset", s["time_offset_s"]["score"] * 1e3, th.offset_warn_ms, th.offset_fail_ms, "ms"),
        check("gyro_scale", s["scale_error"]["score"], th.scale_warn, th.scale_fail, "fraction"),
    ]
    if pcc_min is not None:
        out.append(check("gyro_pcc", pcc_min, th.pcc_warn, th.pcc_fail, "pcc", above=False))
    for name, feat, floor, w, f in (
            ("gyro_noise", "noise_gyro_rps", np.radians(th.noise_gyro_floor_dps),
             th.noise_gyro_warn_ratio, th.noise_gyro_fail_ratio),
            ("accel_noise", "noise_accel_mps2", th.noise_accel_floor_mps2,
             th.noise_accel_warn_ratio, th.noise_accel_fail_ratio),
            ("gyro_bias_drift", "bias_drift_rps", np.radians(th.drift_floor_dps),
             th.drift_warn_ratio, th.drift_fail_ratio)):
        c = ratio_check(name, s[feat]["score"], s[feat]["baseline"], floor, w, f)
        if c is not None:
            out.append(c)
    return out


def accel_pcc_check(accel_pcc: list[float], th: Thresholds) -> dict:
    """Absolute accelerometer similarity: the best axis's median window PCC against the reference.
    Healthy units on one frame correlate on the axis with the most motion whatever the others do
    (the quieter axes may not: noise and vibration dominate them)."""
    vals = [v for v in accel_pcc if v is not None and np.isfinite(v)]
    return check("accel_pcc", max(vals) if vals else None, th.accel_pcc_warn, th.accel_pcc_fail, "pcc",
                 above=False)


def fused_checks(unit: str, fused: dict, th: Thresholds) -> list[dict]:
    """Second-parameter checks of one non-reference unit. fused: unit id -> fused_diff entry of
    every non-reference unit. With other non-reference units the P90 is compared with the median
    P90 of the others (consensus ratio), else with the absolute levels."""
    mine = fused[unit]
    others = [v for u, v in fused.items() if u != unit and v is not None]
    out = []
    for key, name, floor, warn_abs, fail_abs in (
            ("att_deg", "fused_attitude", th.fused_att_floor_deg, th.fused_att_warn_deg, th.fused_att_fail_deg),
            ("pos_m", "fused_position", th.fused_pos_floor_m, th.fused_pos_warn_m, th.fused_pos_fail_m)):
        p90 = mine[key]["p90"]
        if p90 is None:
            continue
        if others:
            base = float(np.median([o[key]["p90"] for o in others if o[key]["p90"] is not None]))
            c = ratio_check(name, p90, base, floor, th.fused_warn_ratio, th.fused_fail_ratio)
        else:
            c = check(name, p90, warn_abs, fail_abs, key.split("_")[1])
        out.append(c)
        if others:
            limit = th.fused_att_implausible_deg if key == "att_deg" else th.fused_pos_implausible_m
            out.append(check(f"{name}_plausible", p90, limit, limit, key.split("_")[1]))
    return out
