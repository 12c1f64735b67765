"""``v2xpos replay``: a recorded drive through the filter with simulated GNSS outages, scored.

``replay`` runs the engine (``replay_engine.run_replay``) with the metrics hook
(``replay_metrics.ReplayMetrics``, whose docstring defines the figures) and, when asked, a
solution writer (``SolutionHook``); ``ReplayResult`` is what it returns.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from v2xpos.types import Dataset

from .config import InsConfig
from .filter import InsFilter
from .profiles import DEFAULT_PROFILE
from .replay_engine import OutageSchedule, ReplayHook, config_for, outage_windows, run_replay
from .replay_metrics import ReplayMetrics


@dataclass
class ReplayResult:
    """Everything a replay produced: the JSON summary and time series for plots/diagnosis."""
    summary: dict
    series: dict = field(default_factory=dict)
    filter: InsFilter | None = None


class SolutionHook(ReplayHook):
    """One ``SolutionWriter`` row per output epoch once the filter is initialised: every GNSS epoch
    (after its update; in an outage without it) or, with ``at_output_times``, at the output times."""

    def __init__(self, writer, at_output_times: bool):
        self.writer, self.at_output_times = writer, at_output_times

    def after_gnss_epoch(self, f: InsFilter, t_s: float, k: int, used: bool) -> None:
        if not self.at_output_times and f.initialized:
            self.writer.write(f, used)

    def on_output(self, f: InsFilter, t_s: float, used: bool) -> None:
        if f.initialized:
            self.writer.write(f, used)


def replay(dataset: Dataset, schedule: OutageSchedule | None = None, cfg: InsConfig | None = None,
           progress: bool = True, keep_series: bool = True, solution=None,
           solution_hz: float | None = None, profile: str = DEFAULT_PROFILE, smooth: bool = False,
           smooth_precision: str = "float32") -> ReplayResult:
    """``v2xpos replay``: the filter over the whole dataset with the outage schedule (default
    ``OutageSchedule()``), scored by ``replay_metrics.ReplayMetrics`` (its docstring defines the
    metrics). The filter is ``cfg``, else the vehicle's configuration in ``profile``
    (``profiles``: default the services' ``service`` profile; ``plain`` without its integrity
    machinery).

    ``solution``: a ``v2xpos.ins.solution.SolutionWriter`` given one row per output epoch once the
    filter is initialised: by default every GNSS epoch (after its update; in an outage without
    it), which leaves the filter exactly as without output; with ``solution_hz`` every
    1 / solution_hz s from the first GNSS epoch (after a GNSS update at the same instant) -- the IMU
    batches are then also split at those times, which moves the result by numerical noise only.

    ``smooth``: the filter records what the backward pass needs (``smoother.StepRecorder``, stored
    in ``smooth_precision``), and after the forward pass a Rauch-Tung-Striebel pass smooths it:
    the summary gets ``replay_smoothing.SmoothingHook``'s figures (``"smoothed": true``, the
    inside-outage errors forward and smoothed, their share within 3 sd, ``smoothing`` with the
    forward and backward times), and ``solution`` gets the smoothed rows. The forward figures are
    those of the same filter (recording does not change it)."""
    cfg_given = cfg
    t_wall0 = time.perf_counter()
    t_cpu0 = time.process_time()
    cfg = cfg or config_for(dataset, profile)
    f = InsFilter(cfg)
    outages, n_scheduled = outage_windows(schedule or OutageSchedule(), dataset)
    metrics = ReplayMetrics(dataset, outages, keep_series)
    hooks: list[ReplayHook] = [metrics]
    output_times = None
    smoothing = None
    if smooth:
        from .replay_smoothing import TAP_ROWS, SmoothingHook
        from .smoother import StepRecorder
        f.recorder = StepRecorder.for_filter(f, TAP_ROWS, smooth_precision)
        smoothing = SmoothingHook(f.recorder, dataset, metrics, solution, bool(solution_hz))
        hooks.append(smoothing)
    elif solution is not None:
        hooks.append(SolutionHook(solution, bool(solution_hz)))
    if solution is not None:
        gn, t_imu = dataset.gnss, dataset.imu.t_s
        if solution_hz and len(gn):
            output_times = np.arange(float(gn.t_s[0]), float(max(gn.t_s[-1], t_imu[-1])), 1.0 / solution_hz)
    run_replay(f, dataset, outages, hooks, output_times=output_times,
               progress=f"replay {dataset.name}" if progress else None)
    wall = time.perf_counter() - t_wall0
    cpu = time.process_time() - t_cpu0
    summary, series = metrics.summary(f, n_scheduled, wall, cpu)
    summary["profile"] = profile if cfg_given is None else "custom"
    if smoothing is not None:
        t0, c0 = time.perf_counter(), time.process_time()
        summary.update(smoothing.finish(f))
        summary["smoothing"].update(forward_s=wall, forward_cpu_s=cpu, backward_s=time.perf_counter() - t0,
                                    backward_cpu_s=time.process_time() - c0)
    return ReplayResult(summary=summary, series=series, filter=f)
