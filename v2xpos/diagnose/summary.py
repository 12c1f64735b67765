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
        lines += ["", f"fit predictor: IMU noise from the samples, gyro {t['gyro_noise_rps_rthz']:.2e} rad/s/sqrt(Hz), "
                      f"accel {t['accel_noise_mps2_rthz']:.2e} m/s^2/sqrt(Hz); {cal.replays} replays"]
    return "\n".join(lines)


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
