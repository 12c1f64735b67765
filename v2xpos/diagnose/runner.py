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


def replay(ds: Dataset, schedule: OutageSchedule | None = None, config: dict | None = None,
           progress: bool = False, record: bool = True, label: str = "replay") -> ReplayOutcome:
    """Run the filter over ``ds``; ``schedule=None`` uses every GNSS epoch.

    config: InsConfig overrides (the dataset's platform, mounting and lever arm are the defaults).
    """
    from v2xpos.ins import InsConfig, InsFilter
    kw = dict(platform=ds.platform if ds.platform in ("car", "pedestrian") else "generic",
              imu_to_body=np.asarray(ds.imu_to_body, float), lever_arm_m=np.asarray(ds.lever_arm_m, float),
              lever_arm_sd_m=float(ds.lever_arm_sd_m), effects=())
    kw.update(config or {})
    filt = InsFilter(InsConfig(**kw))
    rec = ResidualRecorder(kinds=RECORDED_KINDS)
    if record:
        filt.on_update = lambda res, f: rec.record(res, f.nav_state())
    imu, gnss = ds.imu, ds.gnss
    wall0 = time.perf_counter()
    order = np.argsort(gnss.t_s, kind="stable")
    tg = gnss.t_s[order]
    windows = (schedule.intervals(float(tg[0]), float(tg[-1])) if schedule is not None and len(tg) else [])
    pending_end = [w[1] for w in windows]
    outage_err, aided_err = [], []
    i_imu = 0
    n_imu = len(imu)
    it = order
    if progress:
        from tqdm import tqdm
        it = tqdm(order, desc=label, unit="epoch", leave=False)
    for k in it:
        t = float(gnss.t_s[k])
        j = int(np.searchsorted(imu.t_s, t, side="right"))
        if j > i_imu:
            filt.process_imu_batch(imu.t_s[i_imu:j], imu.acc_mps2[i_imu:j], imu.gyro_rps[i_imu:j])
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
        filt.process_imu_batch(imu.t_s[i_imu:], imu.acc_mps2[i_imu:], imu.gyro_rps[i_imu:])
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
