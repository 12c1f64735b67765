"""The project's filter on a convoy recording, scored against its truth_rel files.

Each vehicle's ``dataset.toml`` goes through the project's recording source
(``v2xpos.sources.recording.RecordingSource``, before it lands ``slave.source.DatasetSource``:
``load_dataset`` + ``v2xpos.ins.InsFilter`` with the declared mounting and lever arm, aligning
itself from the data). At every truth_rel time T the last state of each vehicle at or before T is
predicted to T (``v2xpos.relative.predict_state``, CTRA) and the slave is expressed in the
master's body frame (``v2xpos.relative.relative_kinematics``); the error is that minus the
truth_rel row. Scored while the master's truth speed is above ``min_speed_mps`` (the figures
quoted for convoy_dev are "while moving"), optionally from ``settle_s`` after the master first
exceeds it: the filter cannot know its heading at rest and acquires it in the first second of
motion, when the relative vector (10+ m) is turned by the heading error (a 10 m spike on
convoy_dev, the same on generated recordings). Nothing here is tuned: it reports what the filter
does.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from v2xpos import timebase


def nav_states(toml: str | Path) -> list:
    """Every NavState the project's recording source produces for one dataset, oldest first."""
    from v2xpos.sources.recording import RecordingSource
    return RecordingSource(str(toml)).advance(1e12)


def _truth_speed(truth_csv: Path) -> tuple[np.ndarray, np.ndarray]:
    t = np.loadtxt(truth_csv, delimiter=",", comments="#")
    return t[:, 0], np.hypot(t[:, 4], t[:, 5])


def score_pair(master_states: list, slave_states: list, truth_rel_csv: str | Path, master_truth_csv: str | Path,
               gps_week: int, min_speed_mps: float = 1.0, settle_s: float = 0.0) -> dict:
    """Relative position error of the filter pair against truth_rel (see module docstring)."""
    from v2xpos.relative import predict_state, relative_kinematics
    rel = np.loadtxt(truth_rel_csv, delimiter=",", comments="#", ndmin=2)
    tow_m, speed_m = _truth_speed(Path(master_truth_csv))
    moving = np.flatnonzero(speed_m > min_speed_mps)
    t_settled = tow_m[moving[0]] + settle_s if moving.size else np.inf
    week0 = float(timebase.gps_seconds_from_week_tow(gps_week, 0.0))
    t_m = np.array([s.t_s for s in master_states])
    t_s = np.array([s.t_s for s in slave_states])
    errors, kept_tow = [], []
    for row in rel:
        T = week0 + row[0]
        i = int(np.searchsorted(t_m, T, side="right")) - 1
        j = int(np.searchsorted(t_s, T, side="right")) - 1
        if i < 0 or j < 0:
            continue
        speed = float(np.interp(row[0], tow_m, speed_m))
        if speed <= min_speed_mps or row[0] < t_settled:
            continue
        r = relative_kinematics(predict_state(master_states[i], T - t_m[i]),
                                predict_state(slave_states[j], T - t_s[j]))
        errors.append(np.asarray(r.rel_pos_body_m) - row[1:4])
        kept_tow.append(row[0])
    e = np.asarray(errors).reshape(-1, 3)
    if not len(e):
        raise ValueError(f"{truth_rel_csv}: no epoch with both filters running and the master moving")
    h = np.hypot(e[:, 0], e[:, 1])
    return {"epochs": int(len(e)), "horizontal_rms_m": float(np.sqrt(np.mean(h * h))),
            "horizontal_p50_m": float(np.median(h)), "horizontal_p95_m": float(np.percentile(h, 95)),
            "horizontal_max_m": float(h.max()), "mean_xyz_m": e.mean(axis=0).round(4).tolist(),
            "tow_s": np.asarray(kept_tow), "error_xyz_m": e}


def evaluate_convoy(folder: str | Path, min_speed_mps: float = 1.0, settle_s: float = 3.0) -> dict[str, dict]:
    """Score every follower of a convoy recording against the leader A: {"B": {"moving": {...},
    "settled": {...}}, ...}: every epoch while moving, and from ``settle_s`` after the first motion."""
    import json
    folder = Path(folder)
    meta = json.loads((folder / "truth_effects.json").read_text())
    week = int(meta["generator"]["gps_week"])
    names = sorted(meta["vehicles"])
    master = nav_states(folder / names[0] / "dataset.toml")
    out = {}
    for k, name in enumerate(names[1:]):
        rel = folder / ("truth_rel.csv" if k == 0 else f"truth_rel_{name}.csv")
        slave = nav_states(folder / name / "dataset.toml")
        out[name] = {}
        for label, settle in (("moving", 0.0), ("settled", settle_s)):
            res = score_pair(master, slave, rel, folder / names[0] / "truth.csv", week, min_speed_mps, settle)
            out[name][label] = {k2: v for k2, v in res.items() if k2 not in ("tow_s", "error_xyz_m")}
    return out
