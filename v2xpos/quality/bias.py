"""Bias stability between stops (the static detection of the navigation filter, used for grading).

Static test per sample: with the rates and specific force averaged over a short
window, |w| < ``gyro_thr_dps`` and | |f| - g | < ``acc_thr_mps2``. Runs of static samples longer
than ``min_stop_s`` are stops; over each stop (trimmed by ``trim_s`` at both ends) the mean gyro
output is the bias estimate of that stop (plus the Earth rate projection, <= 0.004 deg/s, which
changes between stops only with the heading). The stability is the spread max - min of the
per-stop means, per axis.

When the navigation filter's online calibration (``v2xpos.ins.StaticCalibrator``) provides per-stop
bias estimates, they can be passed to ``bias_stability`` directly instead of the means.
"""
from __future__ import annotations

import numpy as np

from v2xpos.geo import G0_MPS2
from v2xpos.types import ImuData

STANDARD_GRAVITY_MPS2 = G0_MPS2


def _moving_average(x: np.ndarray, n: int) -> np.ndarray:
    if n <= 1:
        return x
    k = np.ones(n) / n
    return np.stack([np.convolve(x[:, i], k, mode="same") for i in range(x.shape[1])], axis=1)


def find_stops(imu: ImuData, gyro_thr_dps: float = 1.0, acc_thr_mps2: float = 0.3,
               min_stop_s: float = 2.0, smooth_s: float = 0.2,
               gravity_mps2: float = STANDARD_GRAVITY_MPS2) -> list[tuple[int, int]]:
    """(start, end) sample index pairs (end exclusive) of the stops in imu."""
    t = np.asarray(imu.t_s, float)
    if len(t) < 3:
        return []
    rate = 1.0 / float(np.median(np.diff(t)))
    n = max(1, int(round(smooth_s * rate)))
    w = _moving_average(np.asarray(imu.gyro_rps, float), n)
    f = _moving_average(np.asarray(imu.acc_mps2, float), n)
    static = (np.linalg.norm(w, axis=1) < np.radians(gyro_thr_dps)) & \
             (np.abs(np.linalg.norm(f, axis=1) - gravity_mps2) < acc_thr_mps2)
    edges = np.diff(np.concatenate([[0], static.astype(np.int8), [0]]))
    starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    return [(int(s), int(e)) for s, e in zip(starts, ends) if t[e - 1] - t[s] >= min_stop_s]


def stop_biases(imu: ImuData, stops: list[tuple[int, int]], trim_s: float = 0.5) -> np.ndarray:
    """Mean gyro output [rad/s] over each stop, (n_stops, 3)."""
    t = np.asarray(imu.t_s, float)
    out = []
    for s, e in stops:
        sel = (t >= t[s] + trim_s) & (t <= t[e - 1] - trim_s)
        if sel.sum() >= 2:
            out.append(np.asarray(imu.gyro_rps, float)[sel].mean(axis=0))
    return np.array(out).reshape(-1, 3)


def bias_stability(per_stop_bias_rps: np.ndarray) -> dict:
    """Spread of the per-stop gyro biases: {'n_stops', 'spread_dps': per axis, 'max_spread_dps'};
    spreads are None with fewer than two stops."""
    b = np.asarray(per_stop_bias_rps, float).reshape(-1, 3)
    if len(b) < 2:
        return {"n_stops": int(len(b)), "spread_dps": None, "max_spread_dps": None}
    spread = np.degrees(b.max(axis=0) - b.min(axis=0))
    return {"n_stops": int(len(b)), "spread_dps": spread.tolist(), "max_spread_dps": float(spread.max())}


def calibrator_stop_biases(imu: ImuData, C_body_imu: np.ndarray | None = None,
                           chunk: int = 50) -> tuple[np.ndarray, list]:
    """Per-stop gyro biases [rad/s] (unit axes) from the navigation filter's stop calibrator
    (``v2xpos.ins.StaticCalibrator``) fed with the unit's samples in body axes; and the stop spans."""
    from v2xpos.ins import StaticCalibrator

    C = np.eye(3) if C_body_imu is None else np.asarray(C_body_imu, float)
    cal = StaticCalibrator()
    t = np.asarray(imu.t_s, float)
    f = np.asarray(imu.acc_mps2, float) @ C.T
    w = np.asarray(imu.gyro_rps, float) @ C.T
    for k in range(0, len(t), chunk):
        cal.feed(t[k:k + chunk], f[k:k + chunk], w[k:k + chunk])
    cal.finish()
    biases = np.array([e.gyro_bias_rps @ C for e in cal.estimates]).reshape(-1, 3)
    return biases, [[e.t_start_s, e.t_end_s] for e in cal.estimates]


def unit_bias_stability(imu: ImuData, C_body_imu: np.ndarray | None = None, **kw) -> dict:
    """``bias_stability`` of one unit from its stops: the stop calibrator's per-stop estimates
    (``calibrator_stop_biases``); when it finds no level stop (e.g. unknown, tilted mounting), the
    means over ``find_stops`` stops (keyword arguments of ``find_stops``)."""
    biases, spans = calibrator_stop_biases(imu, C_body_imu)
    method = "ins.StaticCalibrator (seed 001)"
    if len(biases) == 0:
        stops = find_stops(imu, **kw)
        biases = stop_biases(imu, stops)
        spans = [[float(imu.t_s[s]), float(imu.t_s[e - 1])] for s, e in stops]
        method = "static-window means"
    res = bias_stability(biases)
    res["stops_s"] = spans
    res["method"] = method
    return res
