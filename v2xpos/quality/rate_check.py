"""Pose-aided angular-rate check: a unit's gyro against the rates differentiated from a pose source.

From consecutive poses T(k) (4x4, sensor -> world) of any pose source (lidar odometry such as
KISS-ICP, another INS, a reference):

    dT_k = T(k-1)^-1 T(k),   phi_k = log(dR_k) (Rodrigues, ``v2xpos.rotation.log_so3``),
    w_pose,k = phi_k / (t_k - t_{k-1})     [rad/s, in the sensor frame of scan k-1]

The gyro is averaged over the same interval, w_imu,k = (1/dt) int w dt, and the two norm curves
|w_pose,k| and |w_imu,k| are compared (norms do not depend on the unknown sensor-to-IMU rotation).
Over a window the mean difference  m = mean_k(|w_imu,k| - |w_pose,k|)  is tested against the
threshold  max(abs_dps, rel * mean_k |w_pose,k|): above it the unit is anomalous (a scale error
of s shows as m ~ s |w|; a bias as m ~ the bias component along the rotation axis).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from v2xpos.rotation import log_so3


def angular_rates_from_poses(t_s: np.ndarray, poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(t_mid_s (N-1,), w_rps (N-1, 3)) from poses (N, 4, 4) at times t_s (see module doc)."""
    t = np.asarray(t_s, float)
    T = np.asarray(poses, float)
    if len(t) != len(T) or len(t) < 2:
        raise ValueError(f"need >= 2 poses with one time each, got {len(T)} poses and {len(t)} times")
    w = np.empty((len(t) - 1, 3))
    for k in range(1, len(t)):
        dR = T[k - 1, :3, :3].T @ T[k, :3, :3]
        w[k - 1] = log_so3(dR) / (t[k] - t[k - 1])
    return 0.5 * (t[1:] + t[:-1]), w


def interval_mean_rate(t_imu_s: np.ndarray, gyro_rps: np.ndarray, t_edges_s: np.ndarray) -> np.ndarray:
    """Mean gyro vector over each interval [t_edges[k-1], t_edges[k]] (trapezoid integral of the
    linearly interpolated samples / dt), (len(t_edges) - 1, 3)."""
    t = np.asarray(t_imu_s, float)
    g = np.asarray(gyro_rps, float)
    cum = np.concatenate([np.zeros((1, 3)), np.cumsum(0.5 * (g[1:] + g[:-1]) * np.diff(t)[:, None], axis=0)])
    e = np.asarray(t_edges_s, float)
    integ = np.stack([np.interp(e, t, cum[:, k]) for k in range(3)], axis=1)
    return np.diff(integ, axis=0) / np.diff(e)[:, None]


@dataclass
class RateCheckResult:
    """t_s: interval mid times; norm_pose_dps / norm_imu_dps: the two norm curves; windows of
    (t_start, t_end, mean_diff_dps, threshold_dps, anomaly)."""
    t_s: np.ndarray
    norm_pose_dps: np.ndarray
    norm_imu_dps: np.ndarray
    mean_diff_dps: float
    threshold_dps: float
    anomaly: bool
    windows: list

    def as_dict(self) -> dict:
        """The JSON ``rate_check`` entry."""
        return {"mean_diff_dps": float(self.mean_diff_dps), "threshold_dps": float(self.threshold_dps),
                "anomaly": bool(self.anomaly), "mean_pose_rate_dps": float(np.mean(self.norm_pose_dps)),
                "mean_imu_rate_dps": float(np.mean(self.norm_imu_dps)),
                "relative_diff": float(self.mean_diff_dps / max(np.mean(self.norm_pose_dps), 1e-9)),
                "n_intervals": int(len(self.t_s)),
                "windows": [{"t_start_s": a, "t_end_s": b, "mean_diff_dps": m, "anomaly": bool(x)}
                            for a, b, m, _, x in self.windows]}


def rate_check(t_pose_s: np.ndarray, poses: np.ndarray, t_imu_s: np.ndarray, gyro_rps: np.ndarray,
               window_s: float | None = None, abs_threshold_dps: float = 0.1,
               rel_threshold: float = 0.015) -> RateCheckResult:
    """Compare the gyro norm with the pose-derived angular-rate norm (module doc).

    window_s: length of the test windows (default: the whole overlap as one window; a last window
    shorter than half the length is dropped); the result's mean_diff_dps / anomaly are those of the
    window with the largest |mean difference|.
    """
    t_mid, w_pose = angular_rates_from_poses(t_pose_s, poses)
    t_edges = np.asarray(t_pose_s, float)
    inside = (t_edges[:-1] >= t_imu_s[0]) & (t_edges[1:] <= t_imu_s[-1])
    if not inside.any():
        raise ValueError("rate_check: the pose times do not overlap the IMU samples")
    idx = np.flatnonzero(inside)
    w_imu = interval_mean_rate(t_imu_s, gyro_rps, t_edges)[idx]
    t_mid, w_pose = t_mid[idx], w_pose[idx]
    n_pose = np.degrees(np.linalg.norm(w_pose, axis=1))
    n_imu = np.degrees(np.linalg.norm(w_imu, axis=1))
    diff = n_imu - n_pose
    if window_s is None:
        bounds = [(t_mid[0], t_mid[-1] + 1e-9)]
    else:
        starts = np.arange(t_mid[0], t_mid[-1], window_s)
        bounds = [(a, a + window_s) for a in starts]
    windows = []
    for a, b in bounds:
        sel = (t_mid >= a) & (t_mid < b)
        if sel.sum() < 2 or (window_s is not None and t_mid[sel][-1] - t_mid[sel][0] < 0.5 * window_s):
            continue
        m = float(diff[sel].mean())
        thr = max(abs_threshold_dps, rel_threshold * float(n_pose[sel].mean()))
        windows.append((float(a), float(b), m, thr, abs(m) > thr))
    if not windows:
        raise ValueError("rate_check: no window with at least two pose intervals")
    worst_w = max(windows, key=lambda w: abs(w[2]))
    return RateCheckResult(t_mid, n_pose, n_imu, worst_w[2], worst_w[3], worst_w[4], windows)
