"""Plausibility of a loaded recording before any processing: an error stops the command (exit 2)
with the file and the key named; a warning is stated in the command's report (JSON), not only in
the log.

Checks (``check_dataset``):

* **time overlap** of the IMU and GNSS spans. ``share`` = common span / union span. Below
  ``min_overlap_share`` it is an error (a run on a small part of the recording is not what the
  user asked for); otherwise every uncovered span is a warning, and the commands use the common
  span only (``restrict_to_imu_coverage``: GNSS epochs without IMU data are dropped, and
  ``v2xpos replay`` scores an outage only when the IMU covers it, ``imu_coverage``).
* **mounting against gravity**: at the first static period (``find_static``) the accelerometers
  measure the specific force f = -g, so the down direction in IMU axes is ``-f / |f|``; the
  declared ``imu_to_body`` must bring it within ``max_down_angle_deg`` (20 deg) of body +z (body
  z points down). A wrong or missing matrix (identity for an IMU mounted z-up) shows as ~180 deg.
  Without a static period the mean specific force of the whole recording is used (vehicle
  accelerations average out over minutes) and the report says so.
* **gravity magnitude**: the same specific force within 20 % of standard gravity (an IMU file in
  m/s^2 read as g, or shifted columns, is an error naming the IMU file).
* **sample rates and gaps**: rates from the median spacing; IMU gaps longer than
  ``IMU_GAP_S`` and GNSS gaps longer than ``GNSS_GAP_S`` (and 10 spacings) are warnings with their
  spans.
* **records skipped by the readers** (malformed lines) and a timetag that does not cover the
  whole IMU file are warnings naming the file.

Times in messages are seconds from the first GNSS epoch (or the first IMU sample without GNSS).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from v2xpos.geo import G0_MPS2
from v2xpos.types import Dataset

MIN_OVERLAP_SHARE = 0.25
"""Default: the IMU and GNSS must have at least a quarter of the recording's span in common (an
IMU file cut in half still gives a result for its half, stated; one cut to a few per cent does
not). ``v2xpos replay/calibrate --min-overlap`` sets it."""
UNCOVERED_TOLERANCE_S = 5.0
"""Uncovered spans up to this long at the start or end (a logger started a few seconds after the
receiver) are listed in the report's details, not warned about, and change nothing."""
MAX_DOWN_ANGLE_DEG = 20.0
MAX_GRAVITY_ERROR = 0.2
"""The measured specific force at rest (or averaged over the recording) must be standard gravity
within this fraction: a factor 9.8 (m/s^2 read as g) or a swapped column shows at once."""
IMU_GAP_S = 1.0
"""An IMU spacing longer than this is a gap: the IMU does not cover it (no outage scored there)."""
GNSS_GAP_S = 2.0
STATIC_WINDOW_S = 1.0
STATIC_GYRO_SD_RPS = np.radians(2.0)
STATIC_ACC_SD_MPS2 = 0.3
STATIC_G_TOL_MPS2 = 1.0
MIN_TIMETAG_COVERAGE = 0.99
MAX_LISTED = 5


@dataclass
class Finding:
    """One outcome: ``level`` "error" or "warning", the check's name and a one-line message."""
    level: str
    check: str
    message: str

    def as_dict(self) -> dict:
        return {"level": self.level, "check": self.check, "message": self.message}


@dataclass
class InputCheck:
    """Everything ``check_dataset`` found; ``as_dict`` is what the reports carry."""
    source: str
    findings: list[Finding] = field(default_factory=list)
    details: dict = field(default_factory=dict)

    @property
    def errors(self) -> list[Finding]:
        return [f for f in self.findings if f.level == "error"]

    @property
    def warnings(self) -> list[Finding]:
        return [f for f in self.findings if f.level == "warning"]

    def add(self, level: str, check: str, message: str) -> None:
        self.findings.append(Finding(level, check, message))

    def as_dict(self) -> dict:
        return {"source": self.source, "errors": [f.message for f in self.errors],
                "warnings": [f.message for f in self.warnings],
                "findings": [f.as_dict() for f in self.findings], **self.details}


def _fmt_span(a: float, b: float) -> str:
    return f"{a:.1f}-{b:.1f} s"


def imu_coverage(t_s: np.ndarray, max_gap_s: float = IMU_GAP_S) -> list[tuple[float, float]]:
    """[start, end] GPS times [s] of the stretches without a spacing longer than ``max_gap_s``."""
    t = np.asarray(t_s, float)
    t = t[np.isfinite(t)]
    if len(t) < 2:
        return []
    breaks = np.flatnonzero(np.diff(t) > max_gap_s)
    starts = np.concatenate(([0], breaks + 1))
    ends = np.concatenate((breaks, [len(t) - 1]))
    return [(float(t[a]), float(t[b])) for a, b in zip(starts, ends) if b > a]


def covered(a: float, b: float, coverage: list[tuple[float, float]]) -> bool:
    """Whether [a, b] lies inside one stretch of ``coverage``."""
    return any(c0 <= a and b <= c1 for c0, c1 in coverage)


def _gaps(t: np.ndarray, min_gap_s: float) -> list[tuple[float, float]]:
    d = np.diff(t)
    k = np.flatnonzero(d > min_gap_s)
    return [(float(t[i]), float(t[i + 1])) for i in k]


def find_static(t_s: np.ndarray, acc_mps2: np.ndarray, gyro_rps: np.ndarray,
                window_s: float = STATIC_WINDOW_S) -> tuple[int, int] | None:
    """Index range [i0, i1) of the first window of ``window_s`` in which every gyro axis varies by
    less than 2 deg/s (s.d.), every accelerometer axis by less than 0.3 m/s^2 and the mean specific
    force is within 1 m/s^2 of standard gravity; extended while the next windows stay static
    (at most 5 windows). None when the recording never rests."""
    t = np.asarray(t_s, float)
    if len(t) < 10:
        return None
    dt = float(np.median(np.diff(t)))
    if not np.isfinite(dt) or dt <= 0:
        return None
    n = max(5, int(round(window_s / dt)))

    def static(i: int) -> bool:
        a, g = acc_mps2[i:i + n], gyro_rps[i:i + n]
        if len(a) < n or t[i + n - 1] - t[i] > 2.0 * window_s:
            return False
        return (bool(np.all(np.std(g, axis=0) < STATIC_GYRO_SD_RPS))
                and bool(np.all(np.std(a, axis=0) < STATIC_ACC_SD_MPS2))
                and abs(float(np.linalg.norm(a.mean(axis=0))) - G0_MPS2) < STATIC_G_TOL_MPS2)

    for i in range(0, len(t) - n + 1, max(1, n // 2)):
        if static(i):
            j = i + n
            while j + n <= len(t) and j - i < 5 * n and static(j):
                j += n
            return i, j
    return None


def _descriptor_name(ds: Dataset) -> str:
    return str(ds.source) if ds.source is not None else ds.name


def _check_overlap(ds: Dataset, out: InputCheck, t_ref: float, min_share: float) -> None:
    ti, tg = np.asarray(ds.imu.t_s, float), np.asarray(ds.gnss.t_s, float)
    src = _descriptor_name(ds)
    if len(tg) == 0:
        out.add("error", "overlap", f"{src}: no GNSS epochs: nothing to align or score the IMU against")
        return
    i0, i1, g0, g1 = float(ti[0]), float(ti[-1]), float(tg[0]), float(tg[-1])
    c0, c1 = max(i0, g0), min(i1, g1)
    u0, u1 = min(i0, g0), max(i1, g1)
    common = max(0.0, c1 - c0)
    share = common / (u1 - u0) if u1 > u0 else 0.0
    rel = (lambda a, b: _fmt_span(a - t_ref, b - t_ref))
    out.details["overlap"] = {"imu_span_s": [i0, i1], "gnss_span_s": [g0, g1],
                              "common_span_s": [c0, c1] if common > 0 else None, "share": share,
                              "min_share": min_share, "uncovered": []}
    files = ds.notes.get("files", {})
    imu_name = f"IMU ({Path(files['imu']).name}" + (f", stamped by {Path(files['imu_timetag']).name}"
                                                     if "imu_timetag" in files else "") + ")" \
        if "imu" in files else "IMU"
    gnss_name = f"GNSS ({Path(files['gnss']).name})" if "gnss" in files else "GNSS"
    spans = f"{imu_name} {rel(i0, i1)}, {gnss_name} {rel(g0, g1)} (s from the first GNSS epoch)"
    if share < min_share:
        hint = ""
        if common == 0 and "imu_time" in ds.notes:
            hint = f"; {ds.notes['imu_time']} (declare [imu] timetag)"
        out.add("error", "overlap",
                f"{src}: IMU and GNSS have {common:.1f} s in common, {100 * share:.0f} % of the "
                f"recording (minimum {100 * min_share:.0f} %): {spans}{hint}")
        return
    uncovered = []
    for a, b, what in ((g0, i0, "GNSS without IMU"), (i1, g1, "GNSS without IMU"),
                       (i0, g0, "IMU without GNSS"), (g1, i1, "IMU without GNSS")):
        if b - a > IMU_GAP_S:
            uncovered.append({"span_s": [a, b], "what": what, "warned": b - a > UNCOVERED_TOLERANCE_S})
    out.details["overlap"]["uncovered"] = uncovered
    if any(u["warned"] for u in uncovered):
        listed = ", ".join(f"{u['what']} {rel(*u['span_s'])}" for u in uncovered)
        out.add("warning", "overlap",
                f"{src}: IMU and GNSS cover different spans ({spans}); uncovered: {listed}; "
                "GNSS epochs without IMU data are not used and outages are scored only where "
                f"both exist (common span {rel(c0, c1)})")


def _check_gaps_and_rates(ds: Dataset, out: InputCheck, t_ref: float) -> None:
    src = _descriptor_name(ds)
    rates: dict = {}
    for kind, t, gap_s in (("imu", np.asarray(ds.imu.t_s, float), IMU_GAP_S),
                           ("gnss", np.asarray(ds.gnss.t_s, float), GNSS_GAP_S)):
        if len(t) < 2:
            continue
        d = np.diff(t)
        med = float(np.median(d))
        rates[f"{kind}_rate_hz"] = 1.0 / med if med > 0 else None
        limit = max(gap_s, 10.0 * med) if kind == "gnss" else gap_s
        gaps = _gaps(t, limit)
        rates[f"{kind}_gaps"] = {"threshold_s": limit, "count": len(gaps),
                                 "total_s": float(sum(b - a for a, b in gaps)),
                                 "largest_s": [[a, b] for a, b in sorted(gaps, key=lambda g: g[0] - g[1])
                                               [:MAX_LISTED]]}
        if gaps:
            listed = ", ".join(_fmt_span(a - t_ref, b - t_ref) for a, b in gaps[:MAX_LISTED])
            more = f" and {len(gaps) - MAX_LISTED} more" if len(gaps) > MAX_LISTED else ""
            fname = ds.notes.get("files", {}).get(kind, src)
            out.add("warning", f"{kind}_gaps",
                    f"{fname}: {len(gaps)} {kind.upper()} gap(s) longer than {limit:.2g} s "
                    f"({sum(b - a for a, b in gaps):.1f} s in all): {listed}{more}")
    imu_note = ds.notes.get("imu") if isinstance(ds.notes.get("imu"), dict) else {}
    if imu_note.get("rate_hz") is not None:
        rates["imu_counter_rate_hz"] = imu_note["rate_hz"]
    out.details["rates"] = rates


def _check_mounting(ds: Dataset, out: InputCheck, t_ref: float, max_angle_deg: float) -> None:
    imu = ds.imu
    t = np.asarray(imu.t_s, float)
    acc = np.asarray(imu.acc_mps2, float)
    gyr = np.asarray(imu.gyro_rps, float)
    if len(t) < 2:
        return
    win = find_static(t, acc, gyr)
    if win is not None:
        f_imu = acc[win[0]:win[1]].mean(axis=0)
        how = f"at the first static period ({_fmt_span(t[win[0]] - t_ref, t[win[1] - 1] - t_ref)})"
    else:
        f_imu = acc.mean(axis=0)
        how = "from the mean specific force of the whole recording (no static period found)"
    norm = float(np.linalg.norm(f_imu))
    if not np.isfinite(norm) or abs(norm - G0_MPS2) > MAX_GRAVITY_ERROR * G0_MPS2:
        fname = ds.notes.get("files", {}).get("imu", _descriptor_name(ds))
        out.add("error", "gravity",
                f"{fname}: the specific force {how} is {norm:.2f} m/s^2, not gravity "
                f"({G0_MPS2:.2f} m/s^2 +- {100 * MAX_GRAVITY_ERROR:.0f} %): accelerometer units or "
                "columns do not match the declared [imu] format")
        return
    down_imu = -f_imu / norm
    C = np.asarray(ds.imu_to_body, float)
    down_body = C @ down_imu
    angle = float(np.degrees(np.arccos(np.clip(down_body[2], -1.0, 1.0))))
    out.details["mounting"] = {"method": "static" if win is not None else "mean",
                               "down_imu": down_imu.tolist(), "down_body": down_body.tolist(),
                               "angle_from_body_z_deg": angle, "max_deg": max_angle_deg}
    if angle > max_angle_deg:
        field_name = "[imu] imu_to_body" if ds.source is not None and Path(ds.source).suffix == ".toml" \
            else "imu_to_body"
        out.add("error", "mounting",
                f"{_descriptor_name(ds)}: field {field_name} disagrees with gravity: {how} the "
                f"measured down direction is {np.round(down_imu, 3).tolist()} in IMU axes, which "
                f"the declared imu_to_body maps to {np.round(down_body, 3).tolist()} in the body "
                f"frame, {angle:.0f} deg from body +z (down; limit {max_angle_deg:.0f} deg)")


def _check_readers(ds: Dataset, out: InputCheck) -> None:
    for entry in ds.notes.get("malformed", []) or []:
        if isinstance(entry, dict) and entry.get("count"):
            shown = "; ".join(f"line {e['line']}: {e['reason']}" for e in entry.get("examples", [])[:3])
            out.add("warning", "malformed",
                    f"{entry['source']}: {entry['count']} malformed record(s) skipped ({shown})")
    cov = ds.notes.get("imu_timetag_coverage")
    if cov is not None and cov < MIN_TIMETAG_COVERAGE:
        out.add("warning", "timetag",
                f"{_descriptor_name(ds)}: the [imu] timetag covers {100 * cov:.1f} % of the IMU "
                "lines; the others are stamped by the extrapolated counter clock")


def check_dataset(ds: Dataset, min_overlap_share: float = MIN_OVERLAP_SHARE,
                  max_down_angle_deg: float = MAX_DOWN_ANGLE_DEG) -> InputCheck:
    """Run every check of the module doc on a loaded dataset (see ``InputCheck``)."""
    out = InputCheck(source=_descriptor_name(ds))
    t_ref = float(ds.gnss.t_s[0]) if len(ds.gnss) else (float(ds.imu.t_s[0]) if len(ds.imu) else 0.0)
    out.details["time_reference_s"] = t_ref
    if len(ds.imu) < 2:
        out.add("error", "imu", f"{out.source}: {len(ds.imu)} IMU samples")
        return out
    _check_readers(ds, out)
    _check_overlap(ds, out, t_ref, min_overlap_share)
    _check_gaps_and_rates(ds, out, t_ref)
    _check_mounting(ds, out, t_ref, max_down_angle_deg)
    return out


def restrict_to_imu_coverage(ds: Dataset, tolerance_s: float = UNCOVERED_TOLERANCE_S) -> tuple[Dataset, int]:
    """The dataset without the GNSS epochs outside the IMU's span (the filter cannot use them;
    scoring them would score extrapolation) when such a stretch at the start or the end is longer
    than ``tolerance_s``; returns (dataset, epochs dropped)."""
    tg = np.asarray(ds.gnss.t_s, float)
    if not len(ds.imu) or not len(tg):
        return ds, 0
    i0, i1 = float(ds.imu.t_s[0]), float(ds.imu.t_s[-1])
    keep = np.ones(len(tg), bool)
    if i0 - tg[0] > tolerance_s:
        keep &= tg >= i0
    if tg[-1] - i1 > tolerance_s:
        keep &= tg <= i1
    dropped = int((~keep).sum())
    if not dropped:
        return ds, 0
    g = ds.gnss
    n = len(tg)
    gnss = dataclasses.replace(g, **{f.name: getattr(g, f.name)[keep] for f in dataclasses.fields(g)
                                     if isinstance(getattr(g, f.name), np.ndarray)
                                     and len(getattr(g, f.name)) == n})
    return dataclasses.replace(ds, gnss=gnss), dropped
