"""The table a person reads after ``v2xpos calibrate``: every effect with value, sd, unit and
verdict (angles in degrees, times in ms, scale factors in %), and the errors before / after.

The same rows go to the terminal and to report.md (``summary_rows`` / ``markdown_tables``).
"""
from __future__ import annotations

import numpy as np

from .inject import N_PARAMS

DISPLAY: tuple[tuple[int, str, str, float], ...] = (
    (0, "IMU time offset", "ms", 1e3),
    (1, "IMU clock drift", "ppm", 1.0),
    (2, "GNSS latency", "ms", 1e3),
    (3, "mounting roll", "deg", 180.0 / np.pi),
    (4, "mounting pitch", "deg", 180.0 / np.pi),
    (5, "mounting yaw", "deg", 180.0 / np.pi),
    (6, "lever arm x (forward)", "m", 1.0),
    (7, "lever arm y (right)", "m", 1.0),
    (8, "lever arm z (down)", "m", 1.0),
    (9, "gyro scale x", "%", 100.0),
    (10, "gyro scale y", "%", 100.0),
    (11, "gyro scale z", "%", 100.0),
    (12, "accel scale x", "%", 100.0),
    (13, "accel scale y", "%", 100.0),
    (14, "accel scale z", "%", 100.0),
)
"""Parameter index (``inject.P_*`` layout), label, display unit, factor from parameter units."""
assert len(DISPLAY) == N_PARAMS

METRICS = (("outage_h_rms_m", "outage horizontal RMS", "m"), ("outage_h_max_m", "outage horizontal max", "m"),
           ("aided_h_rms_m", "aided horizontal RMS", "m"), ("nis_mean", "mean NIS (3 expected)", ""))


NOT_DETERMINED = "not determined"
"""What a row shows, in place of a value and a verdict, for an effect the recording cannot
determine (``Fit.determined`` false: its sd is not below half the prior's, so the value is the
prior's pull and no test on it means anything)."""


def summary_rows(fit, active: np.ndarray | None = None) -> list[tuple[str, str, str, str, str]]:
    """(effect, value, sd, unit, verdict) strings per parameter; a not-determined effect is
    neither "YES" nor "no" but ``NOT_DETERMINED`` (whatever its flags say)."""
    rows = []
    active = np.ones(N_PARAMS, bool) if active is None else np.asarray(active, bool)
    for i, label, unit, k in DISPLAY:
        if not active[i]:
            rows.append((label, "-", "-", unit, "not estimated"))
        elif not fit.determined[i]:
            rows.append((label, NOT_DETERMINED, f"{fit.sd[i] * k:.3g}", unit, NOT_DETERMINED))
        else:
            rows.append((label, f"{fit.theta[i] * k:+.4g}", f"{fit.sd[i] * k:.3g}", unit,
                         "YES" if fit.significant[i] else "no"))
    return rows


AGREEMENT_HEADER = ("effect", "offline", "online (end of drive)", "unit", "z", "within 2 sd")


def agreement_rows(online: list[dict]) -> list[tuple[str, str, str, str, str, str]]:
    """Rows of the online-agreement table from ``calibrate.agreement``: a row whose offline value
    is not determined is not judged (offline, z and verdict ``NOT_DETERMINED``): there is no
    offline measurement to agree or disagree with."""
    rows = []
    for r in online:
        _, label, unit, k = DISPLAY[r["index"]]
        on = f"{r['online'] * k:+.4g} +- {r['online_sd'] * k:.2g}"
        if not r.get("determined", True):
            rows.append((label, NOT_DETERMINED, on, unit, "-", NOT_DETERMINED))
        else:
            rows.append((label, f"{r['offline'] * k:+.4g} +- {r['offline_sd'] * k:.2g}", on, unit,
                         f"{r['z']:+.1f}", "yes" if r["agree"] else "NO"))
    return rows


def metric_rows(before: dict, after: dict) -> list[tuple[str, str, str, str]]:
    """(metric, before, after, unit) strings."""
    out = []
    for key, label, unit in METRICS:
        b, a = before.get(key), after.get(key)
        fmt = (lambda v: "-" if v is None or not np.isfinite(v) else f"{v:.3f}")
        out.append((label, fmt(b), fmt(a), unit))
    return out


def _table(header: tuple, rows: list[tuple]) -> list[str]:
    w = [max(len(str(x)) for x in col) for col in zip(header, *rows)]
    line = lambda r: "  ".join(str(x).ljust(w[j]) if j == 0 else str(x).rjust(w[j]) for j, x in enumerate(r))  # noqa: E731
    return [line(header), "  ".join("-" * x for x in w)] + [line(r) for r in rows]


def summary_text(cal) -> str:
    """The terminal summary of a ``calibrate.Calibration``."""
    f = cal.fit
    lines = [f"calibration of {cal.dataset}" + (f" ({cal.source})" if cal.source else ""), ""]
    lines += _table(("effect", "value", "sd", "unit", "significant"), summary_rows(f, cal.problem.active))
    lines += ["", "significant: beyond the t(dof) equivalent of 3 sd and confirmed by replays without it (docs/calibration.md); "
              "not determined: the recording cannot tell it (sd not below half the prior's)", ""]
    lines += _table(("error", "before", "after", "unit"), metric_rows(cal.before, cal.after))
    if getattr(cal, "online", None):
        lines += ["", "the live filter's own effect states (v2xpos replay's filter, same priors) against this calibration:"]
        lines += _table(AGREEMENT_HEADER, agreement_rows(cal.online))
    t = cal.tuning or {}
    if t.get("gyro_noise_rps_rthz") is not None:
        lines += ["", f"fit predictor: IMU noise from the samples, gyro {np.degrees(t['gyro_noise_rps_rthz']):.2e} "
                      f"deg/s/sqrt(Hz), accel {t['accel_noise_mps2_rthz']:.2e} m/s^2/sqrt(Hz); {cal.replays} replays"]
    lines += allan_lines(t.get("allan"), t.get("gyro_noise_rps_rthz"), t.get("accel_noise_mps2_rthz"))
    return "\n".join(lines)


def allan_lines(allan, gyro_white: float | None = None, accel_white: float | None = None) -> list[str]:
    """What the Allan deviation at the stops says (``tuning.AllanAtStops``), angles in degrees:
    white noise at tau = 1 s, the density that covers a significant excess over the white noise
    of the second differences for tau >= 1 s (written to the table) and the bias instability, an
    upper bound when the stops end before the flat part."""
    if allan is None:
        return []
    if not allan.stops_s:
        return ["", "IMU at stops (Allan deviation): no stop long enough; the table carries the white noise only"]
    out = ["", f"IMU at stops (Allan deviation, IEEE 952; {len(allan.stops_s)} stops, {allan.stop_time_s:.0f} s):"]
    for which, white, unit, k, bunit, bk in (
            ("gyro", gyro_white, "deg/s/sqrt(Hz)", np.degrees(1.0), "deg/h", np.degrees(3600.0)),
            ("accel", accel_white, "m/s^2/sqrt(Hz)", 1.0, "mg", 1e3 / 9.80665)):
        w = allan.white(which)
        b, bound = allan.bias_instability(which)
        fmt = (lambda v, u: "not determined (stops shorter than 1 s)" if not np.isfinite(v) else f"{v:.2e} {u}")
        line = f"  {which}: white (tau 1 s) {fmt(w * k, unit)}; bias instability {'<= ' if bound else ''}{fmt(b * bk, bunit)}"
        line += " (stops too short for the flat part)" if bound and np.isfinite(b) else ""
        if white is not None and np.isfinite(white):
            c, _r = allan.covering(which, white)
            line += (f"; above the white noise (tau >= 1 s, 3 sd): {fmt(c * k, unit)} written to the table"
                     if np.isfinite(c) else "; nothing above the white noise at tau >= 1 s (3 sd)")
        out.append(line)
    return out


def markdown_tables(cal) -> list[str]:
    """The same tables as markdown lines (for report.md): errors, effects and, when the live
    filter's states were compared, the online agreement."""
    def md(header, rows):
        return ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)] + \
               ["| " + " | ".join(str(x) for x in r) + " |" for r in rows]
    out = (md(("error", "before", "after", "unit"), metric_rows(cal.before, cal.after)) + [""] +
           md(("effect", "value", "sd", "unit", "significant"), summary_rows(cal.fit, cal.problem.active)))
    if getattr(cal, "online", None):
        out += ["", "The live filter's own effect states (v2xpos replay's filter, same priors) against this "
                    "calibration:", ""] + md(AGREEMENT_HEADER, agreement_rows(cal.online))
    return out
