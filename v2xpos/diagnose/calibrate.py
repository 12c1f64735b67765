"""``v2xpos calibrate``: residuals -> missing effects -> calibrated model, before and after.

Pipeline (docs/calibration.md gives the reasoning):

1. *before*: replay with the declared model only (no effect states), with the outage schedule.
2. *coarse*: one replay with the filter's own augmented effect states (lever arm, IMU time offset,
   misalignment, gyro and accelerometer scale) gives a starting point theta_c for large effects.
3. *batch fit*: at theta_c the inputs are corrected (``inject.correct``) and replayed without
   outages; the whitened innovations r(theta) and their finite-difference Jacobian through the
   replay give a Gauss-Newton/MAP estimate (``identify``), refined by chord iterations with the
   same Jacobian and a last step (with the sds) from a central-difference Jacobian at the final
   iterate (``Estimator.refine``). Robust sd, 3-sd + cross-validated significance, first/second half estimates.
4. *after*: the significant effects are corrected and the outage replay is run again.

Before and after are ``v2xpos replay``'s own metrics (``metrics_replay``); the fit replays run the
same replay engine (``runner``). The estimator is ``estimator.Estimator``, its data vector
``rows.residual_rows``; the command line is ``v2xpos.commands.calibrate``.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from v2xpos.ins.profiles import DEFAULT_PROFILE
from v2xpos.types import Dataset

from . import identify
from .estimator import Estimator, Progress, active_parameters
from .identify import Fit, LinearProblem
from .inject import N_PARAMS, P_CLOCK_DRIFT, P_TIME_OFFSET, PARAM_NAMES, EffectSet
from .residuals import ResidualLog
from .runner import OutageSchedule


# ---------------------------------------------------------------------------------- calibration
@dataclass
class Calibration:
    """Everything the report needs."""
    dataset: str
    fit: Fit
    problem: LinearProblem
    theta_coarse: np.ndarray
    fit_first: Fit
    fit_second: Fit
    effects_significant: EffectSet
    before: dict = field(default_factory=dict)
    after: dict = field(default_factory=dict)
    log_before: ResidualLog | None = None
    log_after: ResidualLog | None = None
    coarse_report: dict = field(default_factory=dict)
    replays: int = 0
    table: object | None = None          # datasets.calibration.CalibrationTable written back
    tuning: dict = field(default_factory=dict)
    source: str = ""
    online: list = field(default_factory=list)    # ``agreement`` rows: offline vs the live filter's states
    profile: str = DEFAULT_PROFILE                 # the filter profile of before, after and online


def metrics_replay(ds: Dataset, schedule: OutageSchedule, progress: bool | Progress = False,
                   label: str = "outage replay", profile: str = DEFAULT_PROFILE) -> dict:
    """Outage metrics exactly as ``v2xpos replay`` computes them (the vehicle's filter in
    ``profile``, default the services' one, the dataset's ``[calibration]`` applied by
    ``ins_config``), plus ``nis_mean`` of the accepted GNSS position and velocity updates."""
    from v2xpos.ins.replay_engine import OutageSchedule as InsSchedule
    from v2xpos.ins.replay import replay as ins_replay
    sched = InsSchedule(schedule.length_s, schedule.every_s, schedule.first_s)
    bar = progress if isinstance(progress, Progress) else None
    if bar:
        bar.start(label)
    res = ins_replay(ds, sched, progress=bool(progress) and bar is None, keep_series=False, profile=profile)
    if bar:
        bar.done()
    out = dict(res.summary)
    nis = [r.nis for r in res.filter.residuals if r.accepted and r.kind in ("gnss_pos", "gnss_vel")]
    out["nis_mean"] = float(np.mean(nis)) if nis else float("nan")
    return out


def with_calibration(ds: Dataset, table) -> Dataset:
    """A shallow copy of ``ds`` carrying ``table`` as its ``[calibration]`` (replaces any other)."""
    import copy
    out = copy.copy(ds)
    out.calibration = table
    return out


def calibrate_dataset(ds: Dataset, schedule: OutageSchedule, progress: bool = True,
                      gn_iterations: int = 2, profile: str = DEFAULT_PROFILE) -> Calibration:
    """The full pipeline of the module docstring. *before* is the vehicle as configured (declared
    values and the dataset's own ``[calibration]``, if any); *after* is the same replay with the
    table this calibration writes back (``ins_config``), i.e. exactly what ``v2xpos replay`` gives
    on the ``--write-dataset`` descriptor. Before, after and the online agreement run the
    vehicle's filter in ``profile`` (``v2xpos.ins.profiles``: default the services' one); the fit
    replays run the ``fit`` profile."""
    from .tuning import allan_at_stops
    from .writeback import calibration_table
    n_active = int(active_parameters(ds.platform).sum())
    bar = Progress(progress, total=6 + gn_iterations * (n_active + 4) + 3 + 2 * n_active + 8)
    try:
        est = Estimator(ds, progress=bar, profile=profile)
        before = metrics_replay(ds, schedule, bar, "before: the vehicle as declared", profile)
        theta_c = est.coarse()
        theta = est.gauss_newton(theta_c, iterations=gn_iterations)
        f, prob, out_fit = est.refine(ds, theta, iterations=2)
        f = identify.applied(prob, est.confirm(ds, f, prob))
        a, b = identify.halves(prob)
        f1 = identify.fit(a, systematic_sd=est.systematic_sd())
        f2 = identify.fit(b, systematic_sd=est.systematic_sd())
        sig = EffectSet.from_vector(np.where(f.significant, f.theta, 0.0))
        source = str(getattr(ds, "source", "") or ds.name)
        noise = None
        tuned = est.config.get("imu", {})
        if "gyro_noise_rps_rthz" in tuned:
            # the predictor's IMU noise (``Estimator.tune``) goes back into the vehicle with the fit
            noise = (tuned["gyro_noise_rps_rthz"], tuned["accel_noise_mps2_rthz"], len(ds.imu.t_s))
        # the Allan deviation at the stops: what the process noise must cover beyond the white part
        allan = allan_at_stops(ds.imu, ds.gnss)
        cover = None
        if noise is not None:
            (gc, gr), (ac, ar) = allan.covering("gyro", noise[0]), allan.covering("accel", noise[1])
            cover = (gc, ac, gr, ar)
        tuning = {**est.tuning, "allan": allan, "allan_cover": cover}
        table = calibration_table(f.theta, f.sd, f.significant, f.determined, est.prior_sd, ds.lever_arm_sd_m,
                                  source=source, imu_noise=noise, imu_allan=cover)
        after = metrics_replay(with_calibration(ds, table), schedule, bar, "after: the calibrated vehicle", profile)
        online = agreement(f, est.online(), est.online_t_end_s)
        base_fit = est._replay(ds, np.zeros(N_PARAMS), "declared model (report)")
    finally:
        bar.close()
    return Calibration(dataset=ds.name, fit=f, problem=prob, theta_coarse=theta_c, fit_first=f1,
                       fit_second=f2, effects_significant=sig, before=before, after=after,
                       log_before=base_fit.log, log_after=out_fit.log, coarse_report=est.coarse_report,
                       replays=est.replays + 2, table=table, tuning=tuning, source=source, online=online,
                       profile=profile)


def agreement(f: Fit, online: dict, t_end_s: float) -> list[dict]:
    """Offline estimate against the live filter's state per effect: ``z = (online - offline) /
    sqrt(sd_on^2 + sd_off^2)``, agreeing when |z| <= 2. The offline IMU offset is moved to the end
    of the drive with its clock drift (the online state is the offset at that time). A row whose
    offline value is not determined (``Fit.determined``) is not judged: ``agree`` is None."""
    rows = []
    for i, (v_on, sd_on) in sorted(online.items()):
        v_off, var_off = float(f.theta[i]), float(f.sd[i]) ** 2
        if i == P_TIME_OFFSET:
            g = np.zeros(N_PARAMS)
            g[P_TIME_OFFSET], g[P_CLOCK_DRIFT] = 1.0, 1e-6 * t_end_s
            v_off = float(g @ f.theta)
            var_off = max(float(g @ f.cov @ g), var_off)
        comb = np.sqrt(var_off + sd_on ** 2)
        z = (v_on - v_off) / comb if comb > 0 else np.inf
        rows.append({"index": int(i), "name": PARAM_NAMES[i], "offline": v_off, "offline_sd": float(np.sqrt(var_off)),
                     "online": v_on, "online_sd": sd_on, "z": float(z),
                     "agree": bool(abs(z) <= 2.0) if f.determined[i] else None, "determined": bool(f.determined[i])})
    return rows


# ---------------------------------------------------------------------------------- JSON
def _entry(f: Fit, sl, scale: float = 1.0) -> dict:
    if isinstance(sl, slice):
        return {"value": (f.theta[sl] * scale).tolist(), "sd": (f.sd[sl] * scale).tolist(),
                "significant": [bool(x) for x in f.significant[sl]],
                "determined": [bool(x) for x in f.determined[sl]]}
    return {"value": float(f.theta[sl] * scale), "sd": float(f.sd[sl] * scale), "significant": bool(f.significant[sl]),
            "determined": bool(f.determined[sl])}


def effects_json(f: Fit) -> dict:
    """The ``effects`` object of the calibrate JSON (angles in degrees). ``determined`` is false where
    the recording could not tell the effect (sd not below half the prior's: the value is then the
    prior's, not a measurement; ``identify.DETERMINED_RATIO``)."""
    from .writeback import EFFECT_SLICES
    return {name: _entry(f, sl, k) for name, (sl, k) in EFFECT_SLICES.items()}


METRIC_KEYS = ("outage_h_rms_m", "outage_h_max_m", "aided_h_rms_m", "nis_mean")


def to_json(cal: Calibration) -> dict:
    return {"dataset": cal.dataset,
            "profile": getattr(cal, "profile", DEFAULT_PROFILE),
            "effects": effects_json(cal.fit),
            "before": {k: cal.before[k] for k in METRIC_KEYS},
            "after": {k: cal.after[k] for k in METRIC_KEYS},
            "online_agreement": {r["name"]: {k: r[k] for k in ("offline", "offline_sd", "online", "online_sd", "z", "agree", "determined")}
                                 for r in cal.online}}

