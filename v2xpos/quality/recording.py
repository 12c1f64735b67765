"""Grade the IMU units of a multi-IMU recording (the logic behind ``v2xpos grade``, whose command
line is ``v2xpos.commands.grade``): load the recording and its ``[grade]`` table, check each unit's
coverage, grade the units with ``v2xpos.quality.grader``.

The recording: a quadrotor_mimu path folder, or a dataset toml (``layout = "quadrotor_mimu"``) that
may carry a ``[grade]`` table: ``reference = "IMU_1"``, ``window_s``, ``step_s`` and
``[grade.mounting_xyz_deg]`` with ``UNIT = [a, b, c]`` (X-Y-Z order, deg, unit -> body). Unknown
keys are errors naming the file, the table and the key.

Coverage (``check_coverage``): every unit's time span is compared with the recording's span (the
union of all units); a unit covering less than ``COVERAGE_WARN`` of it gets a ``coverage`` check
(warn; fail below ``COVERAGE_FAIL``), every unit is graded on the span all units share, and the
cut is stated in the report (``coverage``, ``warnings``) and on stderr. A common span shorter
than ``MIN_COMMON_S``, a unit with too few samples, an empty or header-only file are errors (exit 2)
naming the file.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from v2xpos.types import MultiImuRecording

from .grader import grade_units
from .unit_comparison import GradeConfig

GRADE_KEYS = ("reference", "window_s", "step_s", "mounting_xyz_deg")
COVERAGE_WARN = 0.95
COVERAGE_FAIL = 0.5
MIN_COMMON_S = 5.0
"""Shortest span all units must share to be graded [s] (a few sliding windows and the clock
offset search margins)."""
MIN_UNIT_SAMPLES = 16


def load_recording(path: str | Path) -> tuple[MultiImuRecording, dict]:
    """(MultiImuRecording, grade options dict) from a folder or a toml (see module doc)."""
    from v2xpos.datasets.loader import load_multi_imu, read_descriptor

    from v2xpos.schema import check_keys

    p = Path(path)
    opts: dict = {}
    if p.is_file():
        opts = read_descriptor(p).get("grade", {})
        if not isinstance(opts, dict):
            raise ValueError(f"{p}: [grade] must be a table")
        check_keys(opts, GRADE_KEYS, f"{p}: [grade]")
        for key in ("window_s", "step_s"):
            v = opts.get(key)
            if v is not None and (isinstance(v, bool) or not isinstance(v, (int, float)) or not v > 0
                                  or not np.isfinite(v)):
                raise ValueError(f"{p}: [grade] {key}: expected a positive number of seconds, got {v!r}")
        if "reference" in opts and not isinstance(opts["reference"], str):
            raise ValueError(f"{p}: [grade] reference: expected a unit id string, got {opts['reference']!r}")
    return load_multi_imu(p), opts


def _unit_file(rec: MultiImuRecording, uid: str) -> str:
    return str(Path(rec.source) / f"{uid}.csv") if rec.source is not None else uid


def check_coverage(rec: MultiImuRecording, cfg: GradeConfig | None = None) -> tuple[MultiImuRecording, dict]:
    """Check every unit's coverage and cut all units to the span they share (see the module doc).

    Returns (recording cut to the common span, ``coverage`` report with ``warnings``). Raises
    ValueError naming the file for a unit with too few samples or a common span that is too short.
    """
    from v2xpos.types import ImuData

    warnings: list[str] = []
    malformed = rec.notes.get("malformed", {}) if isinstance(rec.notes, dict) else {}
    for fname, entry in malformed.items():
        if isinstance(entry, dict) and entry.get("count"):
            shown = "; ".join(f"line {e['line']}: {e['reason']}" for e in entry.get("examples", [])[:3])
            warnings.append(f"{entry.get('source', fname)}: {entry['count']} malformed record(s) skipped ({shown})")
    spans = {}
    for uid, imu in rec.units.items():
        t = np.asarray(imu.t_s, float)
        if len(t) < MIN_UNIT_SAMPLES:
            raise ValueError(f"{_unit_file(rec, uid)}: {len(t)} usable samples, need at least "
                             f"{MIN_UNIT_SAMPLES} (empty, header only or every line malformed)")
        spans[uid] = (float(t[0]), float(t[-1]))
    u0 = min(a for a, _ in spans.values())
    u1 = max(b for _, b in spans.values())
    c0 = max(a for a, _ in spans.values())
    c1 = min(b for _, b in spans.values())
    total = u1 - u0
    units = {}
    for uid, (a, b) in spans.items():
        share = (b - a) / total if total > 0 else 1.0
        units[uid] = {"file": _unit_file(rec, uid), "span_s": [a, b], "share": share,
                      "cut_start_s": max(0.0, c0 - a), "cut_end_s": max(0.0, b - c1)}
    out = {"recording_span_s": [u0, u1], "common_span_s": [c0, c1], "common_s": max(0.0, c1 - c0),
           "recording_s": total, "units": units, "warn_below": COVERAGE_WARN,
           "fail_below": COVERAGE_FAIL, "warnings": warnings}
    short = [uid for uid, u in units.items() if u["share"] < COVERAGE_WARN]
    if c1 - c0 < MIN_COMMON_S:
        limit = min(short or list(units), key=lambda u: units[u]["share"])
        raise ValueError(f"{units[limit]['file']}: covers {spans[limit][0] - u0:.1f}-{spans[limit][1] - u0:.1f} s "
                         f"of the recording's {total:.1f} s; the units share only {max(0.0, c1 - c0):.1f} s "
                         f"(need at least {MIN_COMMON_S:.0f} s to grade)")
    tol = max(0.5, 0.01 * total)
    if short or any(u["cut_start_s"] > tol or u["cut_end_s"] > tol for u in units.values()):
        listed = ", ".join(f"{units[u]['file']} covers {spans[u][0] - u0:.1f}-{spans[u][1] - u0:.1f} s"
                           for u in (short or list(units)))
        warnings.append(f"{rec.source or rec.name}: graded on the span all units share, "
                        f"{c0 - u0:.1f}-{c1 - u0:.1f} s ({c1 - c0:.1f} s of {total:.1f} s): {listed}")
    ref = rec.reference
    if ref is not None and len(getattr(ref, "t_s", [])):
        rt = np.asarray(ref.t_s, float)
        inside = max(0.0, min(c1, rt[-1]) - max(c0, rt[0]))
        out["reference_span_s"] = [float(rt[0]), float(rt[-1])]
        if c1 > c0 and inside < COVERAGE_WARN * (c1 - c0):
            warnings.append(f"{Path(rec.source) / 'GT.csv' if rec.source else 'reference'}: the reference "
                            f"covers {inside:.1f} s of the {c1 - c0:.1f} s graded; fused differences and the "
                            "rate check use that part only")
    cut = {}
    for uid, imu in rec.units.items():
        t = np.asarray(imu.t_s, float)
        keep = (t >= c0) & (t <= c1)
        cut[uid] = ImuData(t_s=t[keep], acc_mps2=np.asarray(imu.acc_mps2)[keep],
                           gyro_rps=np.asarray(imu.gyro_rps)[keep],
                           counter_ms=None if imu.counter_ms is None else np.asarray(imu.counter_ms)[keep])
    import dataclasses
    return dataclasses.replace(rec, units=cut), out


def coverage_checks(coverage: dict) -> dict[str, dict]:
    """Per unit, the ``coverage`` check (share of the recording's span the unit covers)."""
    from .verdict import check
    return {uid: check("coverage", u["share"], COVERAGE_WARN, COVERAGE_FAIL, "fraction", above=False)
            for uid, u in coverage["units"].items()}


def _mounting(opts: dict, source: str) -> dict | None:
    m = opts.get("mounting_xyz_deg")
    if m is None:
        return None
    if not isinstance(m, dict):
        raise ValueError(f"{source}: [grade.mounting_xyz_deg] must be a table of UNIT = [a, b, c], got {m!r}")
    out = {}
    for uid, v in m.items():
        try:
            arr = np.asarray(v, float)
        except (TypeError, ValueError):
            arr = np.zeros(0)
        if arr.shape != (3,) or not np.all(np.isfinite(arr)):
            raise ValueError(f"{source}: [grade.mounting_xyz_deg] {uid} must be three finite numbers, got {v!r}")
        out[uid] = arr
    return out



def reference_rate_checks(rec: MultiImuRecording, window_s: float | None = None) -> dict | None:
    """Pose-aided rate check (``rate_check``) of every unit with the recording's reference attitude
    as the pose source. The quadrotor reference attitude comes at
    10 Hz with 0.1 deg resolution, so by default the whole run is one window."""
    from v2xpos.rotation import dcm_from_euler_batch

    from .rate_check import rate_check

    ref = rec.reference
    if ref is None or getattr(ref, "rpy_rad", None) is None or len(ref.t_s) < 3:
        return None
    poses = np.tile(np.eye(4), (len(ref.t_s), 1, 1))
    poses[:, :3, :3] = dcm_from_euler_batch(np.asarray(ref.rpy_rad, float))
    out = {}
    for uid, imu in rec.units.items():
        try:
            d = rate_check(ref.t_s, poses, imu.t_s, imu.gyro_rps, window_s=window_s).as_dict()
        except ValueError:
            continue
        d["pose_source"] = "reference attitude (GT.csv)"
        out[uid] = d
    return out or None


def prepare_recording(path: str | Path, reference: str | None = None, cfg: GradeConfig | None = None) -> dict:
    """Everything ``grade_recording`` checks before grading (``v2xpos grade --check``): load, the
    ``[grade]`` table, coverage (units cut to the common span), reference and mounting unit ids.
    Returns {'rec', 'coverage', 'reference', 'mounting', 'cfg'}; ValueError naming the file."""
    rec, opts = load_recording(path)
    rec, coverage = check_coverage(rec)
    cfg = cfg or GradeConfig()
    cfg.window_s = float(opts.get("window_s", cfg.window_s))
    cfg.step_s = float(opts.get("step_s", cfg.step_s))
    reference = reference or opts.get("reference")
    if reference is not None and reference not in rec.units:
        from v2xpos.schema import did_you_mean
        raise ValueError(f"{path}: reference unit {reference!r} is not among the units {list(rec.units)}"
                         f"{did_you_mean(reference, rec.units)}")
    mounting = _mounting(opts, str(path))
    for uid in mounting or {}:
        if uid not in rec.units:
            from v2xpos.schema import did_you_mean
            raise ValueError(f"{path}: [grade.mounting_xyz_deg] {uid}: no such unit{did_you_mean(uid, rec.units)}; "
                             f"units {list(rec.units)}")
    return {"rec": rec, "coverage": coverage, "reference": reference, "mounting": mounting, "cfg": cfg}


def grade_recording(path: str | Path, reference: str | None = None, cfg: GradeConfig | None = None,
                    fusion: bool = True) -> dict:
    """Load and grade a multi-IMU recording; returns the full report (with internals)."""
    prep = prepare_recording(path, reference, cfg)
    rec, coverage, reference, mounting, cfg = (prep[k] for k in ("rec", "coverage", "reference", "mounting", "cfg"))
    fixes = None
    if fusion and rec.reference is not None and getattr(rec.reference, "pos_ned_m", None) is not None:
        fixes = {"t_s": rec.reference.t_s, "r_ned_m": rec.reference.pos_ned_m, "sd_m": 0.05,
                 "source": "reference trajectory (GT.csv)"}
    rates = reference_rate_checks(rec) if fusion else None
    rep = grade_units(rec.units, reference, mounting, cfg=cfg, fixes=fixes, rate_check=rates,
                      extra_checks=coverage_checks(coverage))
    rep["recording"] = rec.name
    rep["malformed_lines"] = rec.malformed_lines
    rep["coverage"] = coverage
    rep["warnings"] = coverage["warnings"]
    return rep

