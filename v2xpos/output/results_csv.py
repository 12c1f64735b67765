"""``results.csv``: every result of a master as one CSV row, streamed as it is produced.

Columns, in this order (``COLUMNS``; later columns may be added after these, never between):

=================  ==========================================================================
``t_gps_s``        time of validity of the result: GPS seconds since 1980-01-06 (the master's
                   time the target was compensated to)
``target``         target (slave) id
``status``         ``VALID``, ``FIX_INVALID``, ``TIMEOUT``, ``NO_DATA``, ``FUTURE``,
                   ``ATTITUDE_UNCERTAIN``, ``SIGMA_EXCEEDED``, ``CLOCK_UNSYNCED``, ``INCONSISTENT`` (a
                   filter's consistency test failed), ``UNVERIFIED`` (no test failed, the
                   protection level is still above its limit)
``master_fix``     ``FIXED`` / ``FLOAT`` / ``SINGLE`` / ``DR`` / ``NONE`` (a DGPS solution is a
``target_fix``     code solution and written ``SINGLE``)
``x_m y_m z_m``    the target's reference point (its IMU point) relative to the master's, in the
                   master body frame (x forward, y right, z down) [m]
``sd_x_m ...``     1-sigma of x, y, z [m]
``rel_*_deg``      target attitude relative to the master body: roll, pitch, yaw [deg]
``range_m``        |(x, y, z)| [m]
``age_ms``         master time minus the target's time of validity (latency compensated over)
=================  ==========================================================================

then ``sd_rel_yaw_deg``, ``range_sd_m``, ``vx_mps vy_mps vz_mps`` (relative velocity, master body
frame), ``bearing_deg``, ``ttc_s``, ``fix_side``, ``degraded``, ``seq``, ``source_seq``, and
``reason`` -- which vehicle made a non-VALID status and why (``v2xpos.wire.reason_text``:
``target:SETUP_UNVERIFIED``, ``master:TEST_POSITION``, ``master:COASTING;target:HEADING_PENDING``,
``target:FIX``, ``both:CLOCK``; the status name when it is no vehicle's own, e.g. ``TIMEOUT``; empty
for VALID) -- and ``protection_m`` (horizontal protection level of the relative position, the sum of
both vehicles' [m]; empty when either filter computes none); then a writer's ``extra_columns``
(``v2xpos convoy --in-process --smooth``: ``smoothed``, 1 on a row formed from both vehicles'
smoothed states).
Kinematic columns are empty when the status carries no kinematics (TIMEOUT, NO_DATA, ...).
"""
from __future__ import annotations

import math
from pathlib import Path

from v2xpos.types import FixStatus
from v2xpos.wire import RelativeResult, reason_text

COLUMNS = ("t_gps_s", "target", "status", "master_fix", "target_fix", "x_m", "y_m", "z_m",
           "sd_x_m", "sd_y_m", "sd_z_m", "rel_roll_deg", "rel_pitch_deg", "rel_yaw_deg", "range_m", "age_ms",
           "sd_rel_yaw_deg", "range_sd_m", "vx_mps", "vy_mps", "vz_mps", "bearing_deg", "ttc_s", "fix_side",
           "degraded", "seq", "source_seq", "reason", "protection_m")
FIX_NAMES = {FixStatus.FIXED: "FIXED", FixStatus.FLOAT: "FLOAT", FixStatus.DGPS: "SINGLE",
             FixStatus.SINGLE: "SINGLE", FixStatus.DEAD_RECKONING: "DR", FixStatus.NONE: "NONE"}
DEG = 180.0 / math.pi


def fix_name(fix: FixStatus | int) -> str:
    """Fix status as written in results.csv."""
    try:
        return FIX_NAMES[FixStatus(int(fix))]
    except ValueError:
        return "NONE"


def _num(x: float | None, fmt: str) -> str:
    if x is None or not math.isfinite(x):
        return ""
    return format(x, fmt)


def result_row(res: RelativeResult) -> list[str]:
    """One CSV row (strings, ``COLUMNS`` order) of a result."""
    p, sd, rpy, v = res.rel_pos_body_m, res.rel_pos_sd_m, res.rel_rpy_rad, res.rel_vel_body_mps
    kin = res.has_kinematics
    k = (lambda x, fmt: _num(x, fmt)) if kin else (lambda x, fmt: "")
    return [format(res.t_gps_s, ".4f"), res.target_id, res.status.name, fix_name(res.master_fix),
            fix_name(res.target_fix),
            k(p[0], ".4f"), k(p[1], ".4f"), k(p[2], ".4f"), k(sd[0], ".4f"), k(sd[1], ".4f"), k(sd[2], ".4f"),
            k(rpy[0] * DEG, ".4f"), k(rpy[1] * DEG, ".4f"), k(rpy[2] * DEG, ".4f"), k(res.range_m, ".4f"),
            _num(res.latency_s * 1e3, ".2f"), k(res.rel_yaw_sd_rad * DEG, ".4f"), k(res.range_sd_m, ".4f"),
            k(v[0], ".4f"), k(v[1], ".4f"), k(v[2], ".4f"), k(res.bearing_deg, ".4f"),
            k(res.ttc_s, ".3f") if res.ttc_s is not None else "", str(int(res.fix_side)), str(int(res.degraded)),
            str(res.seq), str(res.source_seq), reason_text(res), _num(res.protection_m, ".4f")]


class ResultsCsvWriter:
    """A master output sink (``write``/``flush``/``close``) appending rows to ``path``; the header is
    written on open, rows are flushed to the file at every pipeline flush so a stopped master
    leaves a complete file. ``extra_columns`` follow ``COLUMNS``; each row takes their values from
    ``extra`` (column -> value) as it is when the row is written."""

    def __init__(self, path: str | Path, extra_columns: tuple[str, ...] = ()):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.extra_columns = tuple(extra_columns)
        self.extra: dict = {c: "" for c in self.extra_columns}
        self._f = open(self.path, "w", newline="")
        self._f.write(",".join(COLUMNS + self.extra_columns) + "\n")
        self.rows = 0

    def write(self, res: RelativeResult) -> None:
        self._f.write(",".join(result_row(res) + [str(self.extra[c]) for c in self.extra_columns]) + "\n")
        self.rows += 1

    def write_scene(self, scene_result, t_gps_s: float, seq: int) -> None:
        """Scene results are not part of results.csv."""

    def flush(self) -> None:
        self._f.flush()

    def close(self) -> None:
        if not self._f.closed:
            self._f.close()


def read_results_csv(path: str | Path):
    """Rows of a results.csv as a dict of numpy arrays (numeric columns as float, NaN where empty;
    ``target``, ``status``, ``master_fix``, ``target_fix``, ``reason`` as string arrays)."""
    import csv

    import numpy as np
    with open(path, newline="") as f:
        reader = csv.reader(f)
        header = next(reader)
        rows = list(reader)
    text = {"target", "status", "master_fix", "target_fix", "reason"}
    out = {}
    for j, name in enumerate(header):
        col = [r[j] if j < len(r) else "" for r in rows]
        if name in text:
            out[name] = np.array(col, dtype=str)
        else:
            out[name] = np.array([float(x) if x else math.nan for x in col], dtype=float)
    return out
