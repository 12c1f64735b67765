"""The replay engine: a recorded dataset through ``InsFilter`` in time order, with GNSS outages.

One event loop (``run_replay``) serves ``v2xpos replay`` (``replay.replay``, scored by
``replay_metrics``) and the fit replays of ``v2xpos calibrate`` (``diagnose.runner``); what each
wants to see it takes through ``ReplayHook`` callbacks:

* per epoch: ``on_gnss_epoch`` (the state before the GNSS update, which is skipped inside an
  outage), ``after_gnss_epoch``, ``on_outage_end`` and ``on_output`` (extra output times);
* per measurement update: ``on_update(result, filter)`` (the filter's ``on_update``).

Events, in time order; at the same time: wheel speed, outage end, GNSS epoch, output, then a
vehicle-constraint time. Before each event the IMU samples up to it are integrated: up to
``t - imu_time_offset`` (the filter's current IMU stamp offset), and for a GNSS epoch also minus
the filter's GNSS latency.

Outage schedule (seconds from the first GNSS epoch): outage i covers
``[first + i every, first + i every + length)``; GNSS is not used inside. With ``need_imu`` only
outages that end before the last GNSS epoch and that the IMU covers without a gap
(``datasets.checks.imu_coverage``) are kept.
"""
from __future__ import annotations

import sys
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from v2xpos.types import Dataset, FixStatus

from .config import InsConfig
from .filter import InsFilter
from .updates import UpdateResult


@dataclass
class OutageSchedule:
    """GNSS outages of ``length_s`` every ``every_s`` from ``first_s`` after the first GNSS epoch."""
    length_s: float = 15.0
    every_s: float = 45.0
    first_s: float = 40.0

    def intervals(self, t_first_s: float, t_last_s: float) -> list[tuple[float, float]]:
        """[start, end) GPS times [s] of the outages that end no later than t_last_s."""
        if self.length_s <= 0 or self.every_s <= 0:
            return []
        out, k = [], 0
        while True:
            a = t_first_s + self.first_s + k * self.every_s
            b = a + self.length_s
            if b > t_last_s:
                return out
            out.append((a, b))
            k += 1


class ReplayHook:
    """What a replay shows its observers; every callback does nothing unless overridden.
    ``f`` is the filter, ``t_s`` the event's GPS time [s], ``k`` the GNSS epoch's index in the
    dataset, ``used`` whether the epoch's GNSS is used (outside the outages)."""

    def on_gnss_epoch(self, f: InsFilter, t_s: float, k: int, used: bool) -> None:
        """At a GNSS epoch, before its update."""

    def after_gnss_epoch(self, f: InsFilter, t_s: float, k: int, used: bool) -> None:
        """At a GNSS epoch, after its update (if used)."""

    def on_outage_end(self, f: InsFilter, t_s: float, i: int) -> None:
        """At the end of outage i."""

    def on_output(self, f: InsFilter, t_s: float, used: bool) -> None:
        """At an output time (``output_times`` of ``run_replay``)."""

    def on_update(self, result: UpdateResult, f: InsFilter) -> None:
        """After every measurement update (GNSS, vehicle constraints, odometer, static calibration)."""


def config_for(dataset: Dataset, **overrides) -> InsConfig:
    """InsConfig from what the dataset declares (platform, mounting, lever arm) and its
    ``[calibration]`` table (``calibrated.ins_config``), plus overrides."""
    from .calibrated import dataset_ins_config
    kw = {}
    if dataset.wheel is not None and dataset.platform == "car":
        base = dataset_ins_config(dataset).effects
        kw["effects"] = tuple(base) + ("odometer_scale",)
    kw.update(overrides)
    return dataset_ins_config(dataset, **kw)


def outage_windows(schedule: OutageSchedule | None, dataset: Dataset,
                   need_imu: bool = True) -> tuple[list[tuple[float, float]], int]:
    """(outages used, outages scheduled): the schedule's [start, end) GPS times over the dataset's
    GNSS span; with ``need_imu`` only those the IMU covers without a gap."""
    t_gnss = np.sort(np.asarray(dataset.gnss.t_s, float), kind="stable")
    if schedule is None or not len(t_gnss):
        return [], 0
    outages = schedule.intervals(float(t_gnss[0]), float(t_gnss[-1]))
    n_scheduled = len(outages)
    if need_imu:
        from v2xpos.datasets.checks import covered, imu_coverage
        coverage = imu_coverage(np.asarray(dataset.imu.t_s, float))
        outages = [o for o in outages if covered(o[0], o[1], coverage)]
    return outages, n_scheduled


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


# event kinds, numbered in their order at the same time
EV_WHEEL, EV_OUTAGE_END, EV_GNSS, EV_OUTPUT, EV_CONSTRAINT = range(5)


def _overrides(hook: ReplayHook, name: str) -> bool:
    return getattr(type(hook), name) is not getattr(ReplayHook, name)


def run_replay(f: InsFilter, dataset: Dataset, outages: Sequence[tuple[float, float]],
               hooks: Sequence[ReplayHook] = (), *, wheel: bool = True, outage_end_events: bool = True,
               output_times: np.ndarray | None = None, exact_epochs: bool = False,
               progress: str | None = None) -> None:
    """Run ``f`` over ``dataset`` (see the module docstring), calling ``hooks`` in their order.

    wheel: use the odometer (a car with wheel speeds), at most at the constraint rate (odometer
    errors are correlated at higher rates). outage_end_events: stop at each outage end for
    ``on_outage_end`` (the IMU batch is split there). exact_epochs: the filter state is brought
    exactly to every GNSS epoch (an interpolated IMU sample is inserted there, so no extrapolation
    over the gap to the last sample) and the vehicle constraints are applied mid-way between GNSS
    epochs (``constraint_times``; needs ``cfg.constraints_on_request``): then a shift of the IMU
    stamps changes the replay continuously. progress: a progress bar's label (None: no bar).
    """
    if exact_epochs and not f.cfg.constraints_on_request:
        raise ValueError("run_replay(exact_epochs=True) needs InsConfig(constraints_on_request=True)")
    imu, gn = dataset.imu, dataset.gnss
    t_imu = np.asarray(imu.t_s, float)
    acc = np.ascontiguousarray(imu.acc_mps2, dtype=float)
    gyr = np.ascontiguousarray(imu.gyro_rps, dtype=float)
    t_gnss = np.asarray(gn.t_s, float)
    t_constr = np.zeros(0)
    if exact_epochs and len(t_imu) > 1:
        t_constr = constraint_times(np.sort(t_gnss, kind="stable"), f.cfg.constraint_rate_hz)
        t_imu, acc, gyr = with_samples_at(t_imu, acc, gyr, np.concatenate([t_gnss, t_constr]))
    use_wheel = wheel and dataset.wheel is not None and f.cfg.platform == "car"
    ev = [(t_gnss, EV_GNSS), (np.array([b for _, b in outages], float) if outage_end_events else np.zeros(0),
                              EV_OUTAGE_END),
          (np.zeros(0) if output_times is None else np.asarray(output_times, float), EV_OUTPUT),
          (np.asarray(dataset.wheel.t_s, float) if use_wheel else np.zeros(0), EV_WHEEL),
          (t_constr, EV_CONSTRAINT)]
    ev_t = np.concatenate([t for t, _ in ev])
    ev_k = np.concatenate([np.full(len(t), k) for t, k in ev])
    ev_i = np.concatenate([np.arange(len(t)) for t, _ in ev])
    order = np.lexsort((ev_k, ev_t))
    out_starts = np.array([a for a, _ in outages], float)
    out_ends = np.array([b for _, b in outages], float)
    update_hooks = [h for h in hooks if _overrides(h, "on_update")]
    if update_hooks:
        def on_update(res: UpdateResult, filt: InsFilter) -> None:
            for h in update_hooks:
                h.on_update(res, filt)
        f.on_update = on_update
    vel, vel_sd = gn.vel_ned_mps, gn.vel_sd_ned_mps
    n_imu = len(t_imu)
    bar = None
    if progress:
        from tqdm import tqdm
        bar = tqdm(total=n_imu, unit="imu", desc=progress, file=sys.stderr, mininterval=0.5, leave=False)
    wheel_next_t = -np.inf
    wheel_period_s = 1.0 / f.cfg.constraint_rate_hz
    i_imu = 0
    for e in order:
        t_ev, kind, idx = float(ev_t[e]), int(ev_k[e]), int(ev_i[e])
        j = int(np.searchsorted(t_imu, t_ev - f.fx.imu_time_offset_s - f.fx.gnss_latency_s * (kind == EV_GNSS),
                                side="right"))
        if j > i_imu:
            f.process_imu_batch(t_imu[i_imu:j], acc[i_imu:j], gyr[i_imu:j])
            if bar is not None:
                bar.update(j - i_imu)
            i_imu = j
        if kind == EV_CONSTRAINT:
            f.apply_vehicle_constraints()
            continue
        if kind == EV_WHEEL:
            if t_ev >= wheel_next_t:
                f.update_wheel_speed(t_ev, float(dataset.wheel.speed_mps[idx]))
                wheel_next_t = t_ev + wheel_period_s
            continue
        k_out = int(np.searchsorted(out_starts, t_ev, side="right")) - 1
        used = not (k_out >= 0 and t_ev < out_ends[k_out])
        if kind == EV_OUTAGE_END:
            for h in hooks:
                h.on_outage_end(f, t_ev, idx)
            continue
        if kind == EV_OUTPUT:
            for h in hooks:
                h.on_output(f, t_ev, used)
            continue
        for h in hooks:
            h.on_gnss_epoch(f, t_ev, idx, used)
        if used:
            f.update_gnss(t_ev, gn.lla[idx], gn.sd_ned_m[idx], FixStatus(int(gn.fix[idx])),
                          None if vel is None else vel[idx], None if vel_sd is None else vel_sd[idx])
        for h in hooks:
            h.after_gnss_epoch(f, t_ev, idx, used)
    if i_imu < n_imu:
        f.process_imu_batch(t_imu[i_imu:], acc[i_imu:], gyr[i_imu:])
        if bar is not None:
            bar.update(n_imu - i_imu)
    if bar is not None:
        bar.close()
