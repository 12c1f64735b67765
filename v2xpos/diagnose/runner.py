"""Replay a recording through ``v2xpos.ins.InsFilter`` with the outage schedule of ``v2xpos replay``
and capture every update's residual.

Metrics follow issue 2: outages are measured from the first GNSS epoch (start at
``first + k * every``, length ``length``, only whole outages inside the recording); GNSS is not used
inside an outage; the outage error is the horizontal antenna position error at the first RTK-fixed
epoch at or after the outage end, before that epoch's update; the aided error is the same before
every fixed update outside outages; ``nis_mean`` is the mean NIS of the accepted GNSS position and
velocity updates (3 dof each, 3 expected for a consistent filter).
The filter runs without augmented effect states (``effects=()``): the model is exactly what the
dataset declares, so that the effects calibrate finds are applied by ``inject.correct`` alone.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from v2xpos import geo
from v2xpos.ins.replay import OutageSchedule
from v2xpos.types import Dataset, FixStatus

from .residuals import ResidualLog, ResidualRecorder

RECORDED_KINDS = ("gnss_pos", "gnss_vel", "nhc")


@dataclass
class ReplayOutcome:
    """Metrics (dict), residual log and the filter's final effect report of one replay."""
    metrics: dict
    log: ResidualLog
    effects_report: dict = field(default_factory=dict)


def _h_error_m(lla_est: np.ndarray, lla_ref: np.ndarray) -> float:
    d = geo.lla_to_ned(np.asarray(lla_est, float)[None, :], np.asarray(lla_ref, float))[0]
    return float(np.hypot(d[0], d[1]))


def constraint_times(t_gnss_s: np.ndarray, rate_hz: float) -> np.ndarray:
    """Vehicle-constraint times kept away from the GNSS epochs: each interval between consecutive
    epochs gets ``m = max(1, round(interval x rate))`` points at fractions (j + 1/2)/m."""
    tg = np.unique(np.asarray(t_gnss_s, float))
    if len(tg) < 2:
        return np.zeros(0)
    dt = np.diff(tg)
    m = np.maximum(1, np.round(dt * rate_hz)).astype(int)
    start = np.repeat(tg[:-1], m)
    step = np.repeat(dt / m, m)
    j = np.arange(int(m.sum())) - np.repeat(np.cumsum(m) - m, m)
    return start + (j + 0.5) * step


def with_samples_at(t_s: np.ndarray, acc: np.ndarray, gyro: np.ndarray, t_new_s: np.ndarray,
                    min_sep_s: float = 1e-7) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """IMU samples with linearly interpolated ones inserted at ``t_new_s`` (inside the recording,
    not within ``min_sep_s`` of a real sample). The trapezoid increments over a split interval equal
    those of the whole interval, so the strapdown is unchanged while the state exists at t_new_s."""
    t_new_s = np.unique(t_new_s[(t_new_s > t_s[0]) & (t_new_s < t_s[-1])])
    i = np.searchsorted(t_s, t_new_s)
    keep = (t_new_s - t_s[i - 1] > min_sep_s) & (t_s[i] - t_new_s > min_sep_s)
    t_new_s, i = t_new_s[keep], i[keep]
    w = ((t_new_s - t_s[i - 1]) / (t_s[i] - t_s[i - 1]))[:, None]
    a_new = (1.0 - w) * acc[i - 1] + w * acc[i]
    g_new = (1.0 - w) * gyro[i - 1] + w * gyro[i]
    t = np.concatenate([t_s, t_new_s])
    o = np.argsort(t, kind="stable")
    return t[o], np.concatenate([acc, a_new])[o], np.concatenate([gyro, g_new])[o]


def replay(ds: Dataset, schedule: OutageSchedule | None = None, config: dict | None = None,
           progress: bool = False, record: bool = True, label: str = "replay",
           exact_epochs: bool = False) -> ReplayOutcome:
    """Run the filter over ``ds``; ``schedule=None`` uses every GNSS epoch.

    config: InsConfig overrides (the dataset's platform, mounting and lever arm are the defaults).
    exact_epochs: the filter state is brought exactly to every GNSS epoch (an interpolated IMU
    sample is inserted there, so no extrapolation over the gap to the last sample), and the
    vehicle constraints are applied mid-way between GNSS epochs (``constraint_times``) instead of
    at chunk ends. Then a shift of the IMU stamps changes the replay continuously: no update moves
    to another sample, and no constraint swaps order with a GNSS update (calibration fit replays).
    """
    from v2xpos.ins import InsConfig, InsFilter
    kw = dict(platform=ds.platform if ds.platform in ("car", "pedestrian") else "generic",
              imu_to_body=np.asarray(ds.imu_to_body, float), lever_arm_m=np.asarray(ds.lever_arm_m, float),
              lever_arm_sd_m=float(ds.lever_arm_sd_m), effects=())
    kw.update(config or {})
    if exact_epochs:
        kw["constraints_on_request"] = True
    filt = InsFilter(InsConfig(**kw))
    rec = ResidualRecorder(kinds=RECORDED_KINDS)
    if record:
        filt.on_update = lambda res, f: rec.record(res, f.nav_state())
    imu, gnss = ds.imu, ds.gnss
    wall0 = time.perf_counter()
    order = np.argsort(gnss.t_s, kind="stable")
    tg = gnss.t_s[order]
    imu_t, imu_a, imu_w = imu.t_s, imu.acc_mps2, imu.gyro_rps
    t_constr = np.zeros(0)
    if exact_epochs and len(imu_t) > 1:
        t_constr = constraint_times(tg, filt.cfg.constraint_rate_hz)
        imu_t, imu_a, imu_w = with_samples_at(imu_t, imu_a, imu_w, np.concatenate([tg, t_constr]))
    i_constr = 0
    windows = (schedule.intervals(float(tg[0]), float(tg[-1])) if schedule is not None and len(tg) else [])
    pending_end = [w[1] for w in windows]
    outage_err, aided_err = [], []
    i_imu = 0
    n_imu = len(imu_t)
    it = order
    if progress:
        from tqdm import tqdm
        it = tqdm(order, desc=label, unit="epoch", leave=False)
    for k in it:
        t = float(gnss.t_s[k])
        while i_constr < len(t_constr) and t_constr[i_constr] < t:
            j = int(np.searchsorted(imu_t, t_constr[i_constr], side="right"))
            if j > i_imu:
                filt.process_imu_batch(imu_t[i_imu:j], imu_a[i_imu:j], imu_w[i_imu:j])
                i_imu = j
            filt.apply_vehicle_constraints()
            i_constr += 1
        j = int(np.searchsorted(imu_t, t, side="right"))
        if j > i_imu:
            filt.process_imu_batch(imu_t[i_imu:j], imu_a[i_imu:j], imu_w[i_imu:j])
            i_imu = j
        in_outage = any(a <= t < b for a, b in windows)
        if in_outage:
            continue
        fixed = int(gnss.fix[k]) == int(FixStatus.FIXED)
        if filt.initialized and fixed:
            pred = filt.antenna_lla()
            v = filt.v_ned_mps
            gap = t - filt.t_s
            r_m, r_n = geo.radii_m(pred[0])
            pred = pred + np.array([v[0] / (r_m + pred[2]), v[1] / ((r_n + pred[2]) * np.cos(pred[0])), -v[2]]) * gap
            err = _h_error_m(pred, gnss.lla[k])
            if pending_end and t >= pending_end[0]:
                outage_err.append(err)
                pending_end.pop(0)
            else:
                aided_err.append(err)
        while pending_end and t >= pending_end[0] + 2.0:
            pending_end.pop(0)
        vel = None if gnss.vel_ned_mps is None else gnss.vel_ned_mps[k]
        vsd = None if gnss.vel_sd_ned_mps is None else gnss.vel_sd_ned_mps[k]
        filt.update_gnss(t, gnss.lla[k], gnss.sd_ned_m[k], int(gnss.fix[k]), vel_ned_mps=vel, vel_sd_ned_mps=vsd)
    if i_imu < n_imu:
        filt.process_imu_batch(imu_t[i_imu:], imu_a[i_imu:], imu_w[i_imu:])
    log = rec.finish()
    oe = np.asarray(outage_err)
    ae = np.asarray(aided_err)
    metrics = {
        "outage_count": len(windows),
        "outage_evaluated": int(len(oe)),
        "outage_h_rms_m": float(np.sqrt(np.mean(oe ** 2))) if len(oe) else float("nan"),
        "outage_h_max_m": float(np.max(oe)) if len(oe) else float("nan"),
        "aided_h_rms_m": float(np.sqrt(np.mean(ae ** 2))) if len(ae) else float("nan"),
        "nis_mean": log.nis_mean(),
        "outage_errors_m": oe.tolist(),
        "wall_s": time.perf_counter() - wall0,
        "counts": dict(filt.counts),
    }
    return ReplayOutcome(metrics=metrics, log=log, effects_report=filt.effects_report())
