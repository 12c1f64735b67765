"""What ``v2xpos evaluate`` writes to DIR, all or nothing: ``metrics.json``, ``matches.csv``, the
plots (``*.png``) and ``report.html``, a single self-contained page (figures embedded) for a test
record.

Everything is written into a fresh sibling directory first and moved into DIR only when complete
(``os.replace`` per file, DIR created by a rename when it did not exist), so a failure leaves DIR
as it was. metrics.json holds the figures; its ``inputs`` (paths, SHA-256) and ``provenance``
(software, time) are the only keys that differ between two runs on the same data.
"""
from __future__ import annotations

import base64
import html
import json
import math
import os
import shutil
import tempfile
from pathlib import Path

import numpy as np

from .evaluation import Evaluation

MATCH_FORMATS = {"t_gps_s": ".6f", "cycle": "d", "x_m": ".3f", "y_m": ".3f", "ref_x_m": ".4f", "ref_y_m": ".4f",
                 "range_m": ".3f", "ref_range_m": ".4f", "azimuth_deg": ".4f", "range_error_m": ".4f",
                 "azimuth_error_deg": ".4f", "longitudinal_error_m": ".4f", "lateral_error_m": ".4f",
                 "range_rate_error_mps": ".4f", "id_switch": "d", "gate_d2": ".3f"}
PLOTS = ("errors_vs_range.png", "errors_vs_time.png", "detection_timeline.png", "birds_eye.png", "latency_search.png")


def _json_safe(x):
    if isinstance(x, dict):
        return {str(k): _json_safe(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_json_safe(v) for v in x]
    if isinstance(x, (np.floating, float)):
        return float(x) if math.isfinite(float(x)) else None
    if isinstance(x, np.integer):
        return int(x)
    if isinstance(x, np.bool_):
        return bool(x)
    return x


def write_matches(matches: dict, path: Path) -> None:
    names = list(matches)
    cols = []
    for n in names:
        fmt = MATCH_FORMATS.get(n)
        v = matches[n]
        if fmt is None:
            cols.append([str(x) for x in v])
        elif fmt == "d":
            cols.append([str(int(x)) for x in v])
        else:
            cols.append(["" if not np.isfinite(x) else format(x, fmt) for x in np.asarray(v, float).tolist()])
    with open(path, "w") as f:
        f.write(",".join(names) + "\n")
        for row in zip(*cols):
            f.write(",".join(row) + "\n")


def write_outputs(ev: Evaluation, out: Path, inputs: dict, fmt: str, plots: bool = True) -> Path:
    """Everything into a temporary sibling of ``out``, then moved in (module docstring)."""
    from v2xpos.provenance import file_sha256, provenance
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
    try:
        metrics = dict(ev.metrics)
        metrics["inputs"] = {k: {"path": str(p), "sha256": file_sha256(p)} for k, p in inputs.items()}
        metrics["inputs"]["sensor"]["format"] = fmt
        metrics["provenance"] = provenance("evaluate", {k: Path(p) for k, p in inputs.items()})
        metrics = _json_safe(metrics)
        (tmp / "metrics.json").write_text(json.dumps(metrics, indent=2) + "\n")
        write_matches(ev.matches, tmp / "matches.csv")
        if plots:
            figures = make_plots(ev, tmp)
            (tmp / "report.html").write_text(html_report(metrics, figures, tmp))
        if not out.exists():
            os.replace(tmp, out)
            return out
        for f in sorted(tmp.iterdir()):
            os.replace(f, out / f.name)
        for stale in PLOTS + ("report.html",):
            if not plots and (out / stale).exists():
                (out / stale).unlink()
        return out
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)


# ----------------------------------------------------------------------------- text
def _fmt(v, spec: str = ".3f") -> str:
    return "-" if v is None else format(v, spec)


def effect_line(name: str, d: dict, unit: str, spec: str) -> str:
    sig = "significant" if d.get("significant") else "not significant"
    return f"{name} {_fmt(d.get('value'), spec)} +- {_fmt(d.get('sd'), spec)} {unit} ({sig})"


def summary_text(m: dict) -> str:
    lines = [f"sensor {m['sensor']}: " + "; ".join([
        effect_line("latency", m["latency_ms"], "ms", ".1f"),
        effect_line("mounting yaw", m["mount_yaw_deg"], "deg", ".3f"),
        effect_line("range bias", m["range_bias_m"], "m", ".3f")]),
        f"  latency compensated: {m['latency_ms']['compensated_ms']:.1f} ms; false objects "
        f"{_fmt(m['false_objects_per_min'], '.2f')}/min ({m['false_objects']} ids); reference "
        f"{m['reference']['kind']}{' (smoothed)' if m['reference_smoothed'] else ''}"]
    for tid, t in m["targets"].items():
        r, a = t["range_error_m"], t["azimuth_error_deg"]
        lines.append(f"  {tid}: detection {_fmt(t['detection_rate'], '.3f')} ({t['cycles_detected']}/{t['cycles_in_view']}"
                     f" cycles in view), id switches {t['id_switches']}, range error bias {_fmt(r['bias'])} sd "
                     f"{_fmt(r['sd'])} p99 {_fmt(r['p99'])} m, azimuth error bias {_fmt(a['bias'])} sd {_fmt(a['sd'])} deg, "
                     f"reference gaps {t['reference_gaps']['seconds']:.1f} s")
    return "\n".join(lines)


# ----------------------------------------------------------------------------- plots
def make_plots(ev: Evaluation, out: Path) -> list[tuple[str, str]]:
    """The figures (file, caption)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    m, s = ev.matches, ev.series
    targets = s["targets"]
    t0 = s["t0"]
    figs = []
    panels = (("range_error_m", "range error [m]"), ("azimuth_error_deg", "azimuth error [deg]"),
              ("lateral_error_m", "lateral error [m]"), ("range_rate_error_mps", "range-rate error [m/s]"))

    def save(fig, name, caption):
        fig.tight_layout()
        fig.savefig(out / name, dpi=100)
        plt.close(fig)
        figs.append((name, caption))

    for xkey, xlabel, name, caption in (
            ("ref_range_m", "reference range [m]", "errors_vs_range.png", "Errors (sensor minus reference) against range"),
            ("t_gps_s", "time since the first object [s]", "errors_vs_time.png", "Errors against time")):
        fig, axes = plt.subplots(2, 2, figsize=(11, 6.5), sharex=True)
        for ax, (key, label) in zip(axes.ravel(), panels):
            for k, tid in enumerate(targets):
                sel = m["target"] == tid
                x = m[xkey][sel] - (t0 if xkey == "t_gps_s" else 0.0)
                ax.plot(x, m[key][sel], ".", ms=1.5, color=f"C{k}", label=tid)
            ax.axhline(0.0, color="k", lw=0.6)
            ax.set_ylabel(label)
            ax.grid(alpha=0.3)
        for ax in axes[1]:
            ax.set_xlabel(xlabel)
        axes[0, 0].legend(markerscale=6, fontsize=8)
        save(fig, name, caption)

    fig, ax = plt.subplots(figsize=(11, 1.2 + 0.6 * max(len(targets), 1)))
    tg = s["grid_t"] - t0
    for k, tid in enumerate(targets):
        view, det = s["in_view"][k], s["detected"][k]
        ax.plot(tg[view & det], np.full((view & det).sum(), k), "|", color="tab:green", ms=10, label="detected")
        ax.plot(tg[view & ~det], np.full((view & ~det).sum(), k), "|", color="tab:red", ms=10, label="missed")
        ax.plot(tg[~view], np.full((~view).sum(), k), "|", color="0.85", ms=10, label="not in view / no reference")
    handles = {h.get_label(): h for h in ax.get_lines()}
    ax.legend(handles.values(), handles.keys(), fontsize=7, loc="upper right", ncol=3)
    ax.set_yticks(range(len(targets)))
    ax.set_yticklabels(targets)
    ax.set_ylim(-0.7, len(targets) - 0.3 + 0.6)
    ax.set_xlabel("time since the first object [s]")
    save(fig, "detection_timeline.png", "Detection timeline per target (each cycle)")

    fig, ax = plt.subplots(figsize=(7, 7))
    for k, tid in enumerate(targets):
        view = s["in_view"][k]
        ax.plot(np.where(view, s["ref_y"][k], np.nan), np.where(view, s["ref_x"][k], np.nan), "-", lw=0.6,
                color=f"C{k}", label=f"{tid} reference (in view)")
        sel = m["target"] == tid
        ax.plot(m["y_m"][sel], m["x_m"][sel], ".", ms=1.5, color=f"C{k}", alpha=0.4)
    fr = s.get("false_rows_xy")
    if fr is not None and len(fr[0]):
        ax.plot(fr[1], fr[0], "x", ms=3, color="tab:red", label="false objects")
    half, rng = s["fov_rad"] / 2.0, s["max_range_m"]
    arc = np.linspace(-half, half, 50)
    ax.plot(np.concatenate([[0], rng * np.sin(arc), [0]]), np.concatenate([[0], rng * np.cos(arc), [0]]), "k:", lw=0.7,
            label="declared field of view")
    ax.plot([0], [0], "k^", ms=5, label="sensor")
    ax.set_xlabel("y (right) [m], sensor frame")
    ax.set_ylabel("x (boresight) [m], sensor frame")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    save(fig, "birds_eye.png", "Bird's-eye view of the run in the sensor frame (declared mount)")

    fig, ax = plt.subplots(figsize=(7, 3.5))
    g, c = s["latency_grid_s"], s["latency_cost"]
    order = np.argsort(g)
    ax.plot(g[order] * 1e3, np.sqrt(np.where(np.isfinite(c[order]), c[order], np.nan)), "-", lw=1)
    ax.set_xlabel("latency tried [ms]")
    ax.set_ylabel("residual spread [m]")
    ax.grid(alpha=0.3)
    save(fig, "latency_search.png", "Coarse latency search: residual spread against the latency tried")
    return figs


# ----------------------------------------------------------------------------- HTML
def _stat_cells(d: dict, spec: str) -> str:
    return "".join(f"<td>{_fmt(d.get(k), spec)}</td>" for k in ("bias", "sd", "rms", "p50", "p90", "p99"))


def html_report(m: dict, figures: list[tuple[str, str]], directory: Path) -> str:
    """One page: what was evaluated, against what, the effects, the metrics, the gaps, the figures."""
    e = html.escape
    prov = m.get("provenance", {})
    sw = prov.get("software", {})
    inputs = "".join(f"<tr><th>{e(k)}</th><td><code>{e(str(v['path']))}</code></td><td><code>{e(str(v['sha256']))}"
                     f"</code></td></tr>" for k, v in m.get("inputs", {}).items())
    rows = []
    for name, key, unit, spec in (("Latency", "latency_ms", "ms", ".1f"), ("Mounting yaw", "mount_yaw_deg", "deg", ".3f"),
                                  ("Range bias", "range_bias_m", "m", ".3f")):
        d = m[key]
        rows.append(f"<tr><th>{name}</th><td>{_fmt(d['value'], spec)}</td><td>{_fmt(d['sd'], spec)}</td><td>{unit}</td>"
                    f"<td class='{'sig' if d['significant'] else 'nsig'}'>{'yes' if d['significant'] else 'no'}</td></tr>")
    tgt_rows, err_rows = [], []
    quantities = (("range_error_m", "range [m]", ".3f"), ("azimuth_error_deg", "azimuth [deg]", ".3f"),
                  ("longitudinal_error_m", "longitudinal [m]", ".3f"), ("lateral_error_m", "lateral [m]", ".3f"),
                  ("range_rate_error_mps", "range rate [m/s]", ".3f"))
    for tid, t in m["targets"].items():
        gaps = t["reference_gaps"]
        tgt_rows.append(f"<tr><th>{e(tid)}</th><td>{t['span_s']:.1f}</td><td>{t['reference_rows']}</td>"
                        f"<td>{t['cycles_in_view']}</td><td>{t['cycles_detected']}</td><td>{_fmt(t['detection_rate'], '.3f')}"
                        f"</td><td>{t['id_switches']}</td><td>{gaps['seconds']:.1f} s in {gaps['spans']} spans</td></tr>")
        for key, label, spec in quantities:
            err_rows.append(f"<tr><th>{e(tid)}</th><td>{label}</td>{_stat_cells(t[key], spec)}<td>{t[key]['n']}</td></tr>")
    warnings = []
    if not m["latency_ms"]["significant"]:
        warnings.append("Latency not significant: errors are computed without latency compensation.")
    for tid, t in m["targets"].items():
        if t["reference_gaps"]["seconds"] > 0.2 * max(t["span_s"], 1e-9):
            warnings.append(f"Target {e(tid)}: the reference is absent for {t['reference_gaps']['seconds']:.1f} s "
                            f"(not VALID); those cycles are not scored.")
        if t["cycles_in_view"] and t["cycles_in_view"] < 200:
            warnings.append(f"Target {e(tid)}: only {t['cycles_in_view']} cycles in view: its detection rate is known "
                            f"to about +-{1.0 / math.sqrt(t['cycles_in_view']):.2f}.")
        if t["detection_rate"] is None:
            warnings.append(f"Target {e(tid)} was never in the declared field of view with a reference.")
    if m["reference"]["covered_min"] < 5.0:
        warnings.append(f"False objects counted over {m['reference']['covered_min']:.2f} min only: the rate is known to "
                        f"about +-{math.sqrt(max(m['false_objects'], 1)) / max(m['reference']['covered_min'], 1e-9):.1f}"
                        f" per minute (Poisson).")
    figs = "".join(f"<figure><img src='data:image/png;base64,{base64.b64encode((directory / n).read_bytes()).decode()}' "
                   f"alt='{e(c)}'><figcaption>{e(c)}</figcaption></figure>" for n, c in figures)
    decl = m.get("declared", {})
    a = m["association"]
    o = m["objects"]
    return f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>Sensor evaluation: {e(m['sensor'])}</title>
<style>body{{font-family:sans-serif;max-width:1100px;margin:1em auto;font-size:13px}}table{{border-collapse:collapse;margin:.5em 0}}
td,th{{border:1px solid #bbb;padding:2px 6px;text-align:right}}th{{background:#f3f3f3}}code{{font-size:11px}}
.sig{{color:#a00;font-weight:bold}}.nsig{{color:#070}}figure{{display:inline-block;vertical-align:top;margin:4px;width:48%}}img{{width:100%}}
.warn{{background:#fff4e0;padding:4px 8px;border-left:4px solid #e90}}</style></head><body>
<h1>Sensor evaluation: {e(m['sensor'])}</h1>
<p>Sensor under test against the v2xpos reference ({e(m['reference']['kind'])}{', smoothed' if m['reference_smoothed'] else ''}).
Errors are sensor minus reference in the sensor frame with the declared mount, after the latency below is compensated
(when significant). Written {e(str(prov.get('written_utc')))} by {e(str(sw.get('name')))} {e(str(sw.get('version')))}
(git {e(str(sw.get('git_revision'))[:12])}{' dirty' if sw.get('git_dirty') else ''}); method: docs/evaluate.md.
Command: <code>{e(' '.join(prov.get('argv') or []))}</code></p>
<h2>Inputs</h2><table><tr><th>role</th><th>path</th><th>SHA-256</th></tr>{inputs}</table>
<p>Declared: mount {decl.get('mount_m')} m, boresight yaw {_fmt(decl.get('mount_yaw_deg'), '.2f')} deg, field of view
{_fmt(decl.get('field_of_view_deg'), '.1f')} deg, range {_fmt(decl.get('max_range_m'), '.1f')} m, clock {e(str(decl.get('clock')))};
targets {e(json.dumps(decl.get('targets', {})))}.
Object list: {o['rows']} rows ({o['rows_skipped']} skipped), {o['object_ids']} ids, {o['cycles']} cycles of
{_fmt(o['cycle_period_s'], '.4f')} s ({o['cycles_empty']} empty cycles re-inserted), {o['span_s']:.1f} s.</p>
{''.join(f"<p class='warn'>{w}</p>" for w in warnings)}
<h2>Sensor effects (estimated from the data)</h2>
<table><tr><th>effect</th><th>value</th><th>sd</th><th>unit</th><th>significant</th></tr>{''.join(rows)}</table>
<p>Compensated latency {m['latency_ms']['compensated_ms']:.1f} ms. A constant azimuth bias and a mounting yaw rotate the
measurements alike; the mounting yaw is their combination. Significance as in <code>v2xpos calibrate</code>: beyond the
t(dof) equivalent of a 3-sigma test and supported by both halves of the run.</p>
<h2>Detection and identity</h2>
<table><tr><th>target</th><th>span [s]</th><th>reference rows</th><th>cycles in view</th><th>detected</th>
<th>detection rate</th><th>id switches</th><th>reference gaps</th></tr>{''.join(tgt_rows)}</table>
<p>False objects (ids never associated with a target, seen while every target had a reference):
{m['false_objects']} ids, {_fmt(m['false_objects_per_min'], '.2f')} per minute over {m['reference']['covered_min']:.2f} min.
Association: {a['pairs']} pairs, gated GNN, first gate {a['gate_m']} m, then chi2 {a['gate_chi2']} on range / azimuth with
sigma {a['sigma_range_m']:.3f} m / {a['sigma_azimuth_deg']:.3f} deg.</p>
<h2>Errors</h2>
<table><tr><th>target</th><th>quantity</th><th>bias</th><th>sd</th><th>rms</th><th>p50 |e|</th><th>p90 |e|</th><th>p99 |e|</th><th>n</th></tr>
{''.join(err_rows)}</table>
<h2>Figures</h2>{figs}
</body></html>
"""
