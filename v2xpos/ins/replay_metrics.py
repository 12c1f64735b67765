"""The metrics of ``v2xpos replay``: a ``ReplayHook`` that scores the filter's antenna position.

* ``outage_*``: filter antenna position at the END of each outage minus the RTK-FIXED solution
  linearly interpolated to that time (the reference pose when the dataset has no fixed epochs);
* ``aided_h_rms_m``: the same error while GNSS is used, just before each update, at every
  RTK-FIXED epoch; ``aided_h_rms_steady_m`` without the ``REACQUIRE_S`` after each outage;
* ``reference_*``: with a reference pose, the filter's IMU point against it at the GNSS epochs.

The antenna position is extrapolated from the filter's time label to the event time with the
filter velocity (curvilinear increments, Groves 2013 eq. 2.119). Errors are NED at the reference.
"""
from __future__ import annotations

import math

import numpy as np

from v2xpos import geo
from v2xpos.types import Dataset, FixStatus

from .filter import InsFilter
from .replay_engine import ReplayHook

REACQUIRE_S = 5.0
"""Re-convergence time after an outage left out of ``aided_h_rms_steady_m``."""
REFERENCE_MAX_GAP_S = 1.0
"""Longest reference interval interpolated over."""
REFERENCE_MAX_AGE_S = 0.1
"""A GNSS epoch is compared with the reference pose only with a reference sample this recent."""

SERIES_KEYS = ("t", "ant_lla", "err_ned", "aided", "bg", "ba", "dt", "lever", "mis", "fix", "ref_t",
               "ref_err_ned", "vel_err_ned", "pos_sd_m", "speed_mps", "yaw_rate_rps")


def interp_lla(t_q: float, t: np.ndarray, lla: np.ndarray,
               max_gap_s: float = REFERENCE_MAX_GAP_S) -> np.ndarray | None:
    """Linear interpolation of a reference trajectory; None when t_q is not bracketed closely."""
    k = int(np.searchsorted(t, t_q))
    if k == 0 or k >= len(t):
        if k < len(t) and abs(t[k] - t_q) < 1e-6:
            return lla[k].copy()
        return None
    t0, t1 = t[k - 1], t[k]
    if t1 - t0 > max_gap_s:
        return None
    a = (t_q - t0) / (t1 - t0)
    return lla[k - 1] + a * (lla[k] - lla[k - 1])


def predicted_antenna(f: InsFilter, t_s: float) -> np.ndarray:
    """Filter antenna position extrapolated from its time label to GPS time t_s."""
    ant = f.antenna_lla()
    gap = t_s - f.t_s
    lat, h = ant[0], ant[2]
    r_m, r_n = geo.radii_m(lat)
    v = f.nav[3:6]
    return ant + gap * np.array([v[0] / (r_m + h), v[1] / ((r_n + h) * math.cos(lat)), -v[2]])


def rms(x: np.ndarray) -> float | None:
    """Root mean square, None for no values."""
    x = np.asarray(x, float)
    return float(np.sqrt(np.mean(x ** 2))) if len(x) else None


class ReplayMetrics(ReplayHook):
    """Collects the module docstring's errors (and, with ``keep_series``, the per-epoch series of
    the plots) during ``run_replay``; ``summary`` turns them into ``v2xpos replay``'s JSON."""

    def __init__(self, dataset: Dataset, outages: list[tuple[float, float]], keep_series: bool = True):
        self.dataset = dataset
        self.outages = outages
        self.keep_series = keep_series
        gn = dataset.gnss
        self.vel = gn.vel_ned_mps
        fixed = np.asarray(gn.fix) == int(FixStatus.FIXED)
        if fixed.sum() >= 2:
            self.ref_t, self.ref_lla = np.asarray(gn.t_s)[fixed], np.asarray(gn.lla)[fixed]
        elif dataset.reference is not None:
            self.ref_t, self.ref_lla = np.asarray(dataset.reference.t_s), np.asarray(dataset.reference.lla)
        else:
            self.ref_t, self.ref_lla = np.zeros(0), np.zeros((0, 3))
        self.out_ends = np.array([b for _, b in outages]) if outages else np.zeros(0)
        self.has_ref_pose = dataset.reference is not None
        self.ref_pose_t = np.asarray(dataset.reference.t_s) if self.has_ref_pose else None
        self.ref_pose_lla = np.asarray(dataset.reference.lla) if self.has_ref_pose else None
        self.ref_pose_next = 0
        self.S: dict[str, list] = {k: [] for k in SERIES_KEYS}
        self.outage_err: list = []
        self.aided_err: list = []
        self.aided_steady: list = []
        self.ref_err: list = []

    def on_outage_end(self, f: InsFilter, t_s: float, i: int) -> None:
        if f.initialized:
            ref = interp_lla(t_s, self.ref_t, self.ref_lla)
            if ref is not None:
                self.outage_err.append(geo.lla_to_ned(predicted_antenna(f, t_s), ref))

    def on_gnss_epoch(self, f: InsFilter, t_s: float, k: int, used: bool) -> None:
        if not f.initialized:
            return
        gn = self.dataset.gnss
        fix = int(gn.fix[k])
        ant = predicted_antenna(f, t_s)
        err = geo.lla_to_ned(ant, gn.lla[k])
        if used and fix == FixStatus.FIXED:
            self.aided_err.append(err)
            k_out = int(np.searchsorted(self.out_ends, t_s, side="right")) - 1
            if k_out < 0 or t_s - self.out_ends[k_out] > REACQUIRE_S:
                self.aided_steady.append(err)
        S = self.S
        if self.keep_series:
            S["t"].append(t_s)
            S["ant_lla"].append(ant)
            S["err_ned"].append(err)
            S["aided"].append(used)
            S["fix"].append(fix)
            S["bg"].append(f.gyro_bias_rps)
            S["ba"].append(f.accel_bias_mps2)
            S["dt"].append(f.fx.imu_time_offset_s)
            S["lever"].append(f.fx.lever_arm_m.copy())
            S["mis"].append(f.fx.misalignment_rad.copy())
            S["vel_err_ned"].append(f.nav[3:6] - self.vel[k] if self.vel is not None else np.full(3, np.nan))
            S["pos_sd_m"].append(np.sqrt(np.abs(np.diag(f.P)[0:3])))
            S["speed_mps"].append(float(np.linalg.norm(f.nav[3:6])))
            S["yaw_rate_rps"].append(float(f.mem[2]))
        if self.has_ref_pose:
            while self.ref_pose_next < len(self.ref_pose_t) and self.ref_pose_t[self.ref_pose_next] <= t_s:
                self.ref_pose_next += 1
            rk = self.ref_pose_next - 1
            if rk >= 0 and t_s - self.ref_pose_t[rk] < REFERENCE_MAX_AGE_S:
                r = interp_lla(t_s, self.ref_pose_t, self.ref_pose_lla)
                if r is not None:
                    e_ref = geo.lla_to_ned(f.lla, r)
                    self.ref_err.append(e_ref)
                    S["ref_t"].append(t_s)
                    S["ref_err_ned"].append(e_ref)

    def summary(self, f: InsFilter, n_scheduled: int, wall_s: float, cpu_s: float) -> tuple[dict, dict]:
        """(summary, series) of the finished replay of filter ``f``; ``n_scheduled`` outages were
        scheduled, ``wall_s`` / ``cpu_s`` the replay's wall-clock and CPU time."""
        ds, gn = self.dataset, self.dataset.gnss
        n_imu = len(ds.imu.t_s)
        oe = np.array(self.outage_err).reshape(-1, 3)
        ae = np.array(self.aided_err).reshape(-1, 3)
        oh = np.hypot(oe[:, 0], oe[:, 1])
        summary = {
            "dataset": ds.name,
            "imu_samples": int(n_imu),
            "gnss_epochs": int(len(gn)),
            "malformed_lines": int(ds.malformed_lines),
            "outage_count": int(len(oe)),
            "outages_skipped_no_imu": int(n_scheduled - len(self.outages)),
            "outage_h_rms_m": rms(oh),
            "outage_h_max_m": float(oh.max()) if len(oh) else None,
            "outage_v_rms_m": rms(oe[:, 2]),
            "aided_h_rms_m": rms(np.hypot(ae[:, 0], ae[:, 1])),
            "aided_h_rms_steady_m": rms(np.hypot(*np.array(self.aided_steady).reshape(-1, 3)[:, :2].T)),
            "wall_s": wall_s,
            "imu_samples_per_s": n_imu / wall_s if wall_s > 0 else None,
            "cpu_s": cpu_s,
        }
        if self.has_ref_pose:
            re = np.array(self.ref_err).reshape(-1, 3)
            summary["reference_h_rms_m"] = rms(np.hypot(re[:, 0], re[:, 1]))
            summary["reference_h_max_m"] = float(np.hypot(re[:, 0], re[:, 1]).max()) if len(re) else None
            summary["reference_v_rms_m"] = rms(re[:, 2])
        if "input_check" in ds.notes:
            summary["input_checks"] = ds.notes["input_check"]
            summary["warnings"] = len(ds.notes["input_check"].get("warnings", []))
        summary["outage_h_m"] = oh.tolist()
        summary["effects"] = f.effects_report()
        summary["static_calibration"] = [e.as_dict() for e in f.calibrator.estimates]
        summary["static_calibration_not_level"] = [s.as_dict() for s in f.calibrator.not_level]
        summary["counts"] = dict(f.counts)
        series = {k: np.array(v) for k, v in self.S.items()}
        series["outages"] = self.outages
        series["outage_err_ned"] = oe
        series["gnss_lla"] = np.asarray(gn.lla)
        series["gnss_t"] = np.asarray(gn.t_s)
        series["residuals"] = f.residuals
        return summary, series
