"""The replay engine: a recorded dataset through ``InsFilter`` with GNSS outages, on the driver.

``run_replay`` is a thin layer over the one event loop (``driver.InsDriver``, whose docstring
gives the events, their times of validity and their order): it pushes the recording's IMU
samples, GNSS epochs (not used inside the outages), wheel speeds, the outage ends and output
times its hooks read, and calibrate's scheduled constraints, then runs the driver. It serves
``v2xpos replay`` (``replay.replay``, scored by ``replay_metrics``) and the fit replays of
``v2xpos calibrate`` (``diagnose.runner``); what each wants to see it takes through
``ReplayHook`` callbacks:

* per epoch: ``on_gnss_epoch`` (the state before the GNSS update, which is skipped inside an
  outage), ``after_gnss_epoch``, ``on_outage_end`` and ``on_output`` (extra output times);
* per measurement update: ``on_update(result, filter)`` (the filter's ``on_update``);
* per IMU sample: ``on_state(filter, nav)`` (only when a hook asks for it).

The filter configuration is a named profile of the vehicle (``config_for``, ``profiles``): by
default the services' ``service`` profile.

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

from v2xpos.types import Dataset

from .config import InsConfig
from .driver import CONSTRAINT, OUTAGE_END, OUTPUT, DriverHook, InsDriver, push_dataset
from .filter import InsFilter
from .profiles import DEFAULT_PROFILE, dataset_config


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


class ReplayHook(DriverHook):
    """What a replay shows its observers: the driver's hooks (``driver.DriverHook``): per epoch
    ``on_gnss_epoch`` (the state before the GNSS update, which is skipped inside an outage),
    ``after_gnss_epoch``, ``on_outage_end``, ``on_output`` (extra output times), per update
    ``on_update(result, filter)``, per IMU sample ``on_state`` (asking for it makes the replay emit
    a state per sample)."""


def config_for(dataset: Dataset, profile: str = DEFAULT_PROFILE, **overrides) -> InsConfig:
    """The vehicle's filter configuration in a named profile (``profiles.dataset_config``: default
    the services' ``service`` profile), plus overrides."""
    return dataset_config(dataset, profile, **overrides)


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


def run_replay(f: InsFilter, dataset: Dataset, outages: Sequence[tuple[float, float]],
               hooks: Sequence[ReplayHook] = (), *, wheel: bool = True, outage_end_events: bool = True,
               output_times: np.ndarray | None = None, exact_epochs: bool = False,
               progress: str | None = None) -> InsDriver:
    """Run ``f`` over ``dataset`` through the driver (``driver.InsDriver``, whose docstring gives the
    event order), calling ``hooks`` in their order; returns the driver (its ``counts``).

    wheel: use the odometer (a car with wheel speeds), at most at the constraint rate (odometer
    errors are correlated at higher rates). outage_end_events: stop at each outage end for
    ``on_outage_end``. exact_epochs: the filter state is brought exactly to every GNSS epoch (an
    interpolated IMU sample is inserted there, so no extrapolation over the gap to the last sample)
    and the vehicle constraints are applied mid-way between GNSS epochs (``constraint_times``;
    needs ``cfg.constraints.constraints_on_request``): then a shift of the IMU stamps changes the replay
    continuously. progress: a progress bar's label (None: no bar).
    """
    if exact_epochs and not f.cfg.constraints.constraints_on_request:
        raise ValueError("run_replay(exact_epochs=True) needs InsConfig(constraints_on_request=True)")
    imu, gn = dataset.imu, dataset.gnss
    t_imu = np.asarray(imu.t_s, float)
    acc = np.ascontiguousarray(imu.acc_mps2, dtype=float)
    gyr = np.ascontiguousarray(imu.gyro_rps, dtype=float)
    t_gnss = np.asarray(gn.t_s, float)
    t_constr = np.zeros(0)
    if exact_epochs and len(t_imu) > 1:
        t_constr = constraint_times(np.sort(t_gnss, kind="stable"), f.cfg.constraints.constraint_rate_hz)
        t_imu, acc, gyr = with_samples_at(t_imu, acc, gyr, np.concatenate([t_gnss, t_constr]))
    bar = None
    if progress:
        from tqdm import tqdm
        bar = tqdm(total=len(t_imu), unit="imu", desc=progress, file=sys.stderr, mininterval=0.5, leave=False)
    drv = InsDriver(f, complete=True, hooks=hooks, imu_progress=None if bar is None else bar.update)
    out_starts = np.array([a for a, _ in outages], float)
    out_ends = np.array([b for _, b in outages], float)

    def used_at(t: float) -> bool:
        k = int(np.searchsorted(out_starts, t, side="right")) - 1
        return not (k >= 0 and t < out_ends[k])

    push_dataset(drv, dataset, imu=(t_imu, acc, gyr), wheel=wheel, gnss_used=used_at)
    if outage_end_events and hooks:
        for i, b in enumerate(out_ends):
            drv.push_mark(OUTAGE_END, float(b), _call_hooks(hooks, "on_outage_end", float(b), i))
    if output_times is not None and hooks:
        for t in np.asarray(output_times, float):
            drv.push_mark(OUTPUT, float(t), _call_hooks(hooks, "on_output", float(t), used_at(float(t))))
    for t in t_constr:
        drv.push_mark(CONSTRAINT, float(t), InsFilter.apply_vehicle_constraints)
    drv.run()
    if bar is not None:
        bar.close()
    return drv


def _call_hooks(hooks: Sequence[ReplayHook], name: str, t: float, arg) -> "callable":
    def call(f: InsFilter) -> None:
        for h in hooks:
            getattr(h, name)(f, t, arg)
    return call
