"""The calibrate report: per effect, the residual before and after against the motion signal that
reveals it; the error table before/after; estimates, sd, halves. PNG (matplotlib Agg) + report.md.

Residual <-> signal pairs (innovations z - h(x) resolved in the filter's body frame; Groves 2013
ch. 14 for the GNSS/INS measurement models, Shin 2001 for NHC):
* IMU time offset: along-track velocity innovation ~ a_x dt.
* GNSS latency: along-track position innovation ~ -speed x latency (the fix describes an earlier
  antenna position).
* IMU clock drift: the along-track slope above, per 60 s block, against time.
* misalignment pitch / yaw: NHC vertical / lateral innovation ~ -speed * angle.
* misalignment roll: block-mean vehicle roll (level-road assumption) against time.
* lever arm x / y: lateral / along-track velocity innovation ~ yaw rate x lever.
* lever arm z: vertical position innovation (a bias).
* gyro z scale: lateral velocity innovation ~ heading error built up in turns ~ speed * yaw rate.
* accelerometer x / y scale: along-track / lateral velocity innovation ~ specific force.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from . import structure
from .inject import PARAM_NAMES
from .residuals import ResidualLog
from .summary import DISPLAY, markdown_tables

MIN_SPEED_MPS = 2.0


def _vel_body(log: ResidualLog) -> tuple:
    s = log["gnss_vel"]
    ok = s.accepted & (s.speed_mps > MIN_SPEED_MPS)
    return s.select(ok), s.select(ok).in_body()


def _pairs(log: ResidualLog) -> dict[str, tuple]:
    """effect name -> (residual, signal, residual label, signal label, t_s)."""
    out = {}
    if "gnss_vel" in log:
        s, vb = _vel_body(log)
        ax = s.acc_body_mps2[:, 0]
        yr = s.rate_body_rps[:, 2]
        out["imu_time_offset_s"] = (vb[:, 0], ax, "along-track vel. innovation [m/s]", "a_x [m/s^2]", s.t_s)
        out["lever_arm_x_m"] = (vb[:, 1], np.degrees(yr), "lateral vel. innovation [m/s]", "yaw rate [deg/s]", s.t_s)
        out["lever_arm_y_m"] = (vb[:, 0], np.degrees(yr), "along-track vel. innovation [m/s]", "yaw rate [deg/s]",
                                s.t_s)
        out["gyro_scale_z"] = (vb[:, 1], s.speed_mps * yr, "lateral vel. innovation [m/s]",
                               "speed x yaw rate [m/s^2]", s.t_s)
        out["accel_scale_x"] = (vb[:, 0], s.f_body_mps2[:, 0], "along-track vel. innovation [m/s]", "f_x [m/s^2]", s.t_s)
        out["accel_scale_y"] = (vb[:, 1], s.f_body_mps2[:, 1], "lateral vel. innovation [m/s]", "f_y [m/s^2]", s.t_s)
    if "gnss_pos" in log:
        p = log["gnss_pos"]
        ok = p.accepted & (p.speed_mps > MIN_SPEED_MPS)
        p = p.select(ok)
        pb = p.in_body()
        if "gnss_vel" not in log:
            # position innovations when the fit ran without receiver velocities: a time offset
            # moves the antenna along track by v dt, a lever arm by a constant in the body frame
            yr = p.rate_body_rps[:, 2]
            out["imu_time_offset_s"] = (pb[:, 0], p.speed_mps, "along-track pos. innovation [m]", "speed [m/s]", p.t_s)
            out["gnss_latency_s"] = out["imu_time_offset_s"]
            out["lever_arm_x_m"] = (pb[:, 0], p.speed_mps, "along-track pos. innovation [m] (intercept)",
                                    "speed [m/s]", p.t_s)
            out["lever_arm_y_m"] = (pb[:, 1], np.degrees(yr), "lateral pos. innovation [m]", "yaw rate [deg/s]", p.t_s)
            out["gyro_scale_z"] = (pb[:, 1], p.speed_mps * yr, "lateral pos. innovation [m]",
                                   "speed x yaw rate [m/s^2]", p.t_s)
            out["accel_scale_x"] = (pb[:, 0], p.f_body_mps2[:, 0], "along-track pos. innovation [m]", "f_x [m/s^2]", p.t_s)
            out["accel_scale_y"] = (pb[:, 1], p.f_body_mps2[:, 1], "lateral pos. innovation [m]", "f_y [m/s^2]", p.t_s)
        if "gnss_vel" in log:
            # a late GNSS position lags the antenna by speed x latency along track, while the IMU
            # offset shows in the velocity innovations against acceleration (above); without
            # receiver velocities both have this signature, and the latency gets no figure of its own
            out["gnss_latency_s"] = (pb[:, 0], p.speed_mps, "along-track pos. innovation [m]", "speed [m/s]", p.t_s)
        out["lever_arm_z_m"] = (pb[:, 2], p.speed_mps, "vertical pos. innovation [m]", "speed [m/s]", p.t_s)
        out["misalign_roll_rad"] = (np.degrees(p.rpy_rad[:, 0]), p.t_s - p.t_s[0] if len(p) else p.t_s,
                                    "vehicle roll [deg]", "time [s]", p.t_s)
    if "nhc" in log:
        n = log["nhc"]
        ok = n.accepted & (n.speed_mps > MIN_SPEED_MPS)
        n = n.select(ok)
        out["misalign_pitch_rad"] = (n.innovation[:, 1], n.speed_mps, "NHC vertical innovation [m/s]", "speed [m/s]", n.t_s)
        out["misalign_yaw_rad"] = (n.innovation[:, 0], n.speed_mps, "NHC lateral innovation [m/s]", "speed [m/s]", n.t_s)
    if "imu_time_offset_s" in out:
        r, a, _, _, t = out["imu_time_offset_s"]
        out["imu_clock_drift_ppm"] = _block_slopes(r, a, t)
    return out


def _block_slopes(r: np.ndarray, a: np.ndarray, t: np.ndarray, block_s: float = 60.0) -> tuple:
    """Along-track slope residual/a_x [s] per block, against block time: a drift makes it a ramp."""
    if len(t) == 0:
        return (np.zeros(0), np.zeros(0), "slope dv/a_x per block [s]", "time [s]", np.zeros(0))
    b = np.floor((t - t[0]) / block_s).astype(int)
    sl, tt = [], []
    for k in np.unique(b):
        sel = b == k
        if sel.sum() > 20 and np.std(a[sel]) > 0.05:
            c = structure.correlation(r[sel], a[sel])
            sl.append(c.detail["slope"])
            tt.append(float(np.mean(t[sel] - t[0])))
    return (np.asarray(sl), np.asarray(tt), "slope dv/a_x per 60 s block [s]", "time [s]", np.asarray(tt) + t[0])


MIN_POINTS = 5
"""Residual/signal pairs needed before the report tests their correlation (fewer: "not determined")."""


def residual_structure(log: ResidualLog) -> dict:
    """For every effect: correlation of its residual with its signal (structure.correlation) and the
    whiteness / bias of the residual."""
    out = {}
    for name, (r, x, *_rest) in _pairs(log).items():
        if len(r) < MIN_POINTS:
            continue
        out[name] = {"correlation": structure.correlation(r, x).as_dict(),
                     "ljung_box": structure.ljung_box(r).as_dict(),
                     "mean_bias": structure.mean_bias(r).as_dict()}
    return out


def _points(pairs: dict, name: str) -> str:
    n = len(pairs[name][0]) if name in pairs else 0
    what = "60-s blocks with enough acceleration" if name == "imu_clock_drift_ppm" else "innovations above 2 m/s"
    return f"{n} {what}"


def signal_rows(before: dict, after: dict, s_before: dict, s_after: dict) -> list[str]:
    """Markdown rows (effect, signal, r and p before / after) of the residual-against-signal table.
    An effect whose correlation could not be computed on either side (fewer than ``MIN_POINTS``
    pairs, e.g. the clock drift's 60-s blocks on a short drive, or a constant signal) gets a row
    that says so instead of NaN figures."""
    rows = []
    for name in PARAM_NAMES:
        if name not in before or name not in after:
            continue
        shown = DISPLAY[PARAM_NAMES.index(name)][1]
        cells = []
        for pairs, st in ((before, s_before), (after, s_after)):
            c = st.get(name, {}).get("correlation", {})
            r, p = c.get("detail", {}).get("r"), c.get("p_value")
            if r is None or p is None or not (np.isfinite(r) and np.isfinite(p)) or c.get("n", 0) < MIN_POINTS:
                cells.append(f"not determined ({_points(pairs, name)}, {MIN_POINTS} needed) | -")
            elif not np.isfinite(c.get("detail", {}).get("slope_sd", 0.0)):
                cells.append("not determined (the signal or the residual is constant) | -")
            else:
                cells.append(f"{r:+.3f} | {p:.1e}")
        rows.append(f"| {shown} | {before[name][3]} | {cells[0]} | {cells[1]} |")
    return rows


def allan_markdown(allan, gyro_white: float | None = None, accel_white: float | None = None) -> list[str]:
    """The report's section on the IMU's Allan deviation at the stops (gyro in deg/s, accelerometer
    in m/s^2, per IMU axis and cluster time; only the cluster times the stops resolve)."""
    if allan is None:
        return []
    from .summary import allan_lines
    md = ["", "## IMU noise at the stops (overlapping Allan deviation, IEEE Std 952-1997)", ""]
    md += [x.strip() for x in allan_lines(allan, gyro_white, accel_white)[1:]]
    ok = np.isfinite(allan.gyro_adev_rps[:, 0])
    if ok.any():
        md += ["", "| tau [s] | clusters | gyro x | gyro y | gyro z [deg/s] | accel x | accel y | accel z [m/s^2] |",
               "|---|---|---|---|---|---|---|---|"]
        for i in np.flatnonzero(ok):
            g = np.degrees(allan.gyro_adev_rps[i])
            a = allan.accel_adev_mps2[i]
            md.append(f"| {allan.tau_s[i]:.3g} | {int(allan.clusters[i])} | " + " | ".join(f"{v:.2e}" for v in g) + " | "
                      + " | ".join(f"{v:.2e}" for v in a) + " |")
    return md


def _binned(x: np.ndarray, y: np.ndarray, n_bins: int = 15) -> tuple:
    ok = np.isfinite(x) & np.isfinite(y)
    x, y = x[ok], y[ok]
    if len(x) < 2 * n_bins:
        return x, y, np.zeros_like(y)
    edges = np.quantile(x, np.linspace(0, 1, n_bins + 1))
    idx = np.clip(np.searchsorted(edges, x, side="right") - 1, 0, n_bins - 1)
    xm, ym, ye = [], [], []
    for k in range(n_bins):
        sel = idx == k
        if sel.sum() >= 3:
            xm.append(x[sel].mean())
            ym.append(y[sel].mean())
            ye.append(y[sel].std(ddof=1) / np.sqrt(sel.sum()))
    return np.array(xm), np.array(ym), np.array(ye)


def write_report(cal, out_dir: Path) -> Path:
    """Write the figures and report.md for a ``calibrate.Calibration``; returns the markdown path."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    f = cal.fit
    before = _pairs(cal.log_before) if cal.log_before is not None else {}
    after = _pairs(cal.log_after) if cal.log_after is not None else {}
    s_before = residual_structure(cal.log_before) if cal.log_before is not None else {}
    s_after = residual_structure(cal.log_after) if cal.log_after is not None else {}
    figures = []
    for name in PARAM_NAMES:
        if name not in before or name not in after:
            continue
        fig, axes = plt.subplots(1, 2, figsize=(11, 4))
        for ax, pairs, title in ((axes[0], before, "declared model"), (axes[1], after, "calibrated model")):
            r, x, ylab, xlab, _t = pairs[name]
            ax.plot(x, r, ".", ms=1.5, alpha=0.25, color="0.5", label="innovations")
            xm, ym, ye = _binned(np.asarray(x), np.asarray(r))
            ax.errorbar(xm, ym, yerr=ye, fmt="o-", color="C3" if title.startswith("declared") else "C2", ms=4,
                        label="mean per quantile bin +- s.e.")
            ax.legend(fontsize=7, markerscale=2, loc="best")
            c = structure.correlation(r, x)
            ax.set_title(f"{title}: r={c.detail['r']:+.2f}, p={c.p_value:.1e}", fontsize=9)
            ax.set_xlabel(xlab)
            ax.grid(alpha=0.3)
            lo, hi = np.nanpercentile(r, [1, 99]) if len(r) else (0, 1)
            pad = 0.2 * (hi - lo + 1e-9)
            ax.set_ylim(lo - pad, hi + pad)
        axes[0].set_ylabel(before[name][2])
        axes[1].set_ylabel(after[name][2])
        i = PARAM_NAMES.index(name)
        _, label, unit, k = DISPLAY[i]
        verdict = ("not determined" if not f.determined[i] else
                   "significant" if f.significant[i] else "not significant")
        value = "" if not f.determined[i] else f"{f.theta[i] * k:+.4g} "
        fig.suptitle(f"{label}: {value}+- {f.sd[i] * k:.2g} {unit} ({verdict}) -- "
                     f"{before[name][2]} against {before[name][3]}", fontsize=10)
        fig.tight_layout()
        p = out_dir / f"effect_{name}.png"
        fig.savefig(p, dpi=110)
        plt.close(fig)
        figures.append((name, p.name))

    ob = np.asarray(cal.before.get("outage_h_m") or [], float)
    oa = np.asarray(cal.after.get("outage_h_m") or [], float)
    if len(ob) and len(oa):
        fig, ax = plt.subplots(figsize=(8, 3.5))
        k = np.arange(max(len(ob), len(oa)))
        ax.bar(k[:len(ob)] - 0.2, ob, 0.4, label=f"before (RMS {cal.before['outage_h_rms_m']:.2f} m)", color="C3")
        ax.bar(k[:len(oa)] + 0.2, oa, 0.4, label=f"after (RMS {cal.after['outage_h_rms_m']:.2f} m)", color="C2")
        ax.set_xlabel("outage #")
        ax.set_ylabel("horizontal error at outage end [m]")
        ax.set_title(f"{cal.dataset}: horizontal error at the end of each simulated GNSS outage", fontsize=10)
        ax.legend()
        ax.grid(alpha=0.3, axis="y")
        fig.tight_layout()
        fig.savefig(out_dir / "outage_errors.png", dpi=110)
        plt.close(fig)

    md = [f"# Calibration report: {cal.dataset}", "",
          "Effects estimated by a batch maximum-likelihood fit over the EKF innovations "
          "(docs/calibration.md). Significant = beyond 3 sd and confirmed by replays without it; "
          "not determined = the recording cannot tell the effect (its sd is not below half the prior's).",
          "", "## Errors before / after and effects", ""]
    md += markdown_tables(cal)
    t = cal.tuning or {}
    md += allan_markdown(t.get("allan"), t.get("gyro_noise_rps_rthz"), t.get("accel_noise_mps2_rthz"))
    md += ["", "![outage errors](outage_errors.png)" if len(ob) else "", "",
           "## Halves of the recording", "",
           "| effect | unit | first half | second half | halves diff / combined sd | residual-cost gain |",
           "|---|---|---|---|---|---|"]
    from .identify import compare
    z = compare(cal.fit_first, cal.fit_second)
    for i, label, unit, k in DISPLAY:
        md.append(f"| {label} | {unit} | {cal.fit_first.theta[i] * k:+.4g} | {cal.fit_second.theta[i] * k:+.4g} | "
                  f"{z[i]:.2f} | {f.cv_gain[i]:.3g} |")
    md += ["", f"Rows in the fit: {f.n_rows}; reduced chi-square {f.reduced_chi2:.2f}; "
           f"replays: {cal.replays}.", "",
           "## Residual against the signal that reveals each effect", "",
           "| effect | signal | r before | p before | r after | p after |", "|---|---|---|---|---|---|"]
    md += signal_rows(before, after, s_before, s_after)
    md.append("")
    for name, png in figures:
        name_shown = DISPLAY[PARAM_NAMES.index(name)][1]
        md += [f"### {name_shown}", "", f"![{name_shown}]({png})", ""]
    path = out_dir / "report.md"
    path.write_text("\n".join(md) + "\n")
    return path
