"""Fit replays of ``v2xpos calibrate``: a recording through ``v2xpos.ins.InsFilter`` on the replay
engine of ``v2xpos replay`` (``ins.replay_engine.run_replay``), capturing every update's residual.

GNSS is not used inside the outages of the schedule (the windows are not thinned by IMU coverage:
the fit compares replays of the same recording). The filter runs without augmented effect states
(``effects=()``): the model is exactly what the dataset declares, so that the effects calibrate
finds are applied by ``inject.correct`` alone. Outage and aided position errors are scored by
``v2xpos replay`` itself (``calibrate.metrics_replay``), not here.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

from v2xpos.ins.config import overridden
from v2xpos.ins.profiles import dataset_config
from v2xpos.ins.replay_engine import OutageSchedule, ReplayHook, outage_windows, run_replay
from v2xpos.types import Dataset

from .residuals import ResidualLog, ResidualRecorder

RECORDED_KINDS = ("gnss_pos", "gnss_vel", "nhc")


@dataclass
class ReplayOutcome:
    """Metrics (dict), residual log and the filter's final effect report of one replay."""
    metrics: dict
    log: ResidualLog
    effects_report: dict = field(default_factory=dict)


class ResidualHook(ReplayHook):
    """Every update's residual, with the filter's motion state, into a ``ResidualRecorder``."""

    def __init__(self, recorder: ResidualRecorder):
        self.recorder = recorder

    def on_update(self, result, f) -> None:
        self.recorder.record(result, f.nav_state())


def replay(ds: Dataset, schedule: OutageSchedule | None = None, config: dict | None = None,
           progress: bool = False, record: bool = True, label: str = "replay",
           exact_epochs: bool = False) -> ReplayOutcome:
    """Run the declared model over ``ds``; ``schedule=None`` uses every GNSS epoch.

    config: InsConfig overrides (group -> dict of fields) of the vehicle's ``fit`` profile (``v2xpos.ins.profiles``: the
    dataset's platform, mounting and lever arm, no effect states, no calibration table).
    exact_epochs: ``run_replay(exact_epochs=True)``: the state exactly at every GNSS epoch and the
    vehicle constraints mid-way between epochs, so that a shift of the IMU stamps changes the
    replay continuously: no update moves to another sample, and no constraint swaps order with a
    GNSS update (calibration fit replays). The odometer is not used.
    Metrics: ``nis_mean`` (accepted GNSS position and velocity updates), ``outage_count``
    (windows without GNSS), ``wall_s``, ``counts`` (the filter's update counters).
    """
    from v2xpos.ins import InsFilter
    kw = dict(config or {})
    if exact_epochs:
        kw = overridden(kw, {"constraints": {"constraints_on_request": True}})
    filt = InsFilter(dataset_config(ds, "fit", **kw))
    rec = ResidualRecorder(kinds=RECORDED_KINDS)
    wall0 = time.perf_counter()
    outages, _ = outage_windows(schedule, ds, need_imu=False)
    run_replay(filt, ds, outages, [ResidualHook(rec)] if record else [], wheel=False, outage_end_events=False,
               exact_epochs=exact_epochs, progress=label if progress else None)
    log = rec.finish()
    metrics = {
        "outage_count": len(outages),
        "nis_mean": log.nis_mean(),
        "wall_s": time.perf_counter() - wall0,
        "counts": dict(filt.counts),
    }
    return ReplayOutcome(metrics=metrics, log=log, effects_report=filt.effects_report())
