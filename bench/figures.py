"""``v2xpos bench figures [--quick]``: run the benchmarks behind the figures the README and docs
state and write ``docs/figures.md``.

Every figure has a stable key (``replay.drive_0708.outage_h_rms_m``); the README and ``docs/*.md``
cite a figure as a Markdown link to its key, ``[2.69 m](figures.md#replay.drive_0708.outage_h_rms_m)``,
and ``tests/test_figures.py`` checks that each cited key is in ``docs/figures.md`` and that the
value agrees to the digits stated. One row per figure: the value, its unit, the target and the
issue that set it, the command that produced it, the date, the commit (``git rev-parse``, ``-dirty``
when a tracked file other than Markdown differs from it) and the machine (cores, CPU model, 1-minute load average when
the command started).

Each command runs as its own process from the project root (the relative ``../shared/data`` paths
of the docs), and its machine-readable output (``--json``, ``report.json``, ``coverage.json``) is
read where it has one; only ``bench replay`` is read from its printed lines. ``--quick`` runs the
jobs cheap enough for CI (a few minutes); the full run runs every job. Rows of jobs not run, or
whose command failed, are carried from the previous ``docs/figures.md`` with their own date,
commit and machine, and marked as carried. The file is rewritten after every job, so an
interrupted run keeps what it measured. Run the full set niced on a shared machine:
``nice -n 10 v2xpos bench figures``.
"""
from __future__ import annotations

import argparse
import datetime as _dt
import json
import os
import re
import shlex
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

ROOT = Path(__file__).resolve().parents[1]
FIGURES_MD = ROOT / "docs" / "figures.md"
DATA = "../shared/data"
DRIVE = f"{DATA}/drive_0708/dataset.toml"
CONVOY = f"{DATA}/convoy_dev"
NOT_MEASURED = "not measured"
COLUMNS = ("key", "value", "unit", "target", "issue", "what", "command", "date (UTC)", "commit", "machine", "run")


@dataclass(frozen=True)
class Figure:
    """One figure: ``pick`` takes the job's parsed output and returns the value (None: absent)."""
    key: str
    what: str
    unit: str
    pick: Callable[[dict], float | int | None]
    digits: int = 3
    target: str = ""
    issue: str = ""


@dataclass(frozen=True)
class Job:
    """One command. ``argv`` is the documented command (``v2xpos ...`` or ``python -m ...``) with
    ``{json}`` / ``{out}`` standing for a temporary file / folder; ``read`` turns the run (stdout
    text, the temporary paths) into the dict the figures pick from."""
    name: str
    argv: tuple[str, ...]
    read: Callable[[str, Path, Path], dict]
    figures: tuple[Figure, ...]
    quick: bool = False
    quick_argv: tuple[str, ...] | None = None
    accept_rc: tuple[int, ...] = (0, 1)
    extra: dict = field(default_factory=dict)


# ------------------------------------------------------------------------------------- readers
def _json(stdout: str, js: Path, out: Path) -> dict:
    return json.loads(js.read_text())


def _report(stdout: str, js: Path, out: Path) -> dict:
    return json.loads((out / "report.json").read_text())


def _coverage(stdout: str, js: Path, out: Path) -> dict:
    return json.loads((out / "coverage.json").read_text())


def _number(pattern: str, text: str) -> float | None:
    m = re.search(pattern, text)
    return float(m.group(1).replace(",", "")) if m else None


def _bench_replay(stdout: str, js: Path, out: Path) -> dict:
    return {"wall": _number(r"end to end replay[^:]*: ([\d,]+) IMU samples/s wall", stdout),
            "cpu": _number(r"([\d,]+) IMU samples per CPU second", stdout),
            "cost_wall": _number(r"smoothing cost[^:]*: ([\d.]+) x wall", stdout),
            "cost_cpu": _number(r"x wall, ([\d.]+) x CPU", stdout)}


def _get(*path: str | int, scale: float = 1.0) -> Callable[[dict], float | None]:
    """Picker of a nested value (None when any step is missing), times ``scale``."""
    def pick(d: dict):
        for p in path:
            if not isinstance(d, (dict, list)):
                return None
            try:
                d = d[p]
            except (KeyError, IndexError, TypeError):
                return None
        return None if d is None else d * scale
    return pick


def _target_of(report: dict) -> dict:
    """The scored target of a two-vehicle convoy report (the one that is not the master)."""
    targets = (report.get("score") or {}).get("targets") or {}
    return next(iter(targets.values()), {})


def _within_3sd(s: dict) -> float | None:
    vals = [s.get("within_3sd_x"), s.get("within_3sd_y")]
    return min(vals) if all(v is not None for v in vals) else None


def _mc_pool(rows: dict, preset: str) -> list[dict]:
    return [b for name, b in rows.items() if name.split(" ")[0] == preset]


def _mc(preset: str, stat: Callable, item: Callable[[dict], float | None], scale: float = 1.0):
    """Picker of a statistic over the integrity Monte-Carlo cases of one preset."""
    def pick(rows: dict):
        vals = [v for v in (item(b) for b in _mc_pool(rows, preset)) if v is not None]
        return stat(vals) * scale if vals else None
    return pick


def _median(v: list[float]) -> float:
    s = sorted(v)
    n = len(s)
    return s[n // 2] if n % 2 else 0.5 * (s[n // 2 - 1] + s[n // 2])


def _in3(b: dict) -> float | None:
    return None if b.get("in3x") is None or b.get("in3y") is None else min(b["in3x"], b["in3y"])


def _evaluate_count(kind: str) -> Callable[[list], int]:
    def pick(rows: list) -> int:
        if kind == "outside":
            return sum(1 for r in rows for w in r["within"].values() if not w)
        if kind == "false":
            return sum(len(r["false_significant"]) for r in rows)
        return len(rows)
    return pick


def _demo_target(target_id: str, key: str) -> Callable[[dict], float | None]:
    def pick(report: dict):
        t = next((t for t in report.get("targets", []) if t.get("id") == target_id), None)
        return None if t is None else t.get(key)
    return pick


def _demo_figures() -> tuple[Figure, ...]:
    out = []
    for tid, what in (("t1", "t1 (cut-in, 10–15 m)"), ("t2", "t2 (19–30 m)"), ("t3", "t3 (40–60 m, fix degraded)"),
                      ("p1", "p1 (pedestrian)")):
        vehicle = tid != "p1"
        out += [Figure(f"demo.seed0.{tid}.rel_pos_err_rms_m", f"demo seed 0, {what}: relative position RMS", "m",
                       _demo_target(tid, "rel_pos_err_rms_m"), 3, "≤ 0.03" if vehicle else "", "#4" if vehicle else ""),
                Figure(f"demo.seed0.{tid}.gnss_floor_m", f"demo seed 0, {what}: GNSS floor gnss_rel_err_rms_1s_m", "m",
                       _demo_target(tid, "gnss_rel_err_rms_1s_m"), 3),
                Figure(f"demo.seed0.{tid}.uncompensated_m", f"demo seed 0, {what}: uncompensated RMS", "m",
                       _demo_target(tid, "uncompensated_rel_pos_err_rms_m"), 2)]
    out.append(Figure("demo.seed0.master_pipeline_ms_p99", "demo seed 0: master pipeline p99 (arrival -> outputs)", "ms",
                      _get("master_pipeline_ms_p99"), 2, "≤ 2", "#4"))
    return tuple(out)


# ------------------------------------------------------------------------------------ the jobs
def _integrity_figures(preset: str, targets: bool, mode: str = "", what: str = "",
                       bound: bool = False) -> tuple[Figure, ...]:
    """The integrity Monte-Carlo's figures of one preset; ``mode`` / ``what``: a run whose set-ups
    were verified (or calibrated) on an earlier drive, or whose routes differ, in the key and the
    label; ``bound``: with the share of the moving time after both cars turned (the runs whose
    set-ups were never verified)."""
    k = f"integrity_mc.{preset}" + (f"_{mode}" if mode else "")
    label = f"{preset} pairs" + (f", {what}" if what else "")
    return (
        Figure(f"{k}.valid_moving_min_pct", f"{label}: lowest VALID share while both move", "%",
               _mc(preset, min, lambda b: b.get("valid_moving"), 100.0), 1, "≥ 90" if targets else "", "#27"),
        Figure(f"{k}.valid_moving_median_pct", f"{label}: median VALID share while both move", "%",
               _mc(preset, _median, lambda b: b.get("valid_moving"), 100.0), 1),
    ) + ((
        Figure(f"{k}.after_turn_max_pct", f"{label}: largest share of the time both move after both have turned "
               "by 1° (the most a never-verified set-up can be VALID)", "%",
               _mc(preset, max, lambda b: b.get("after_turn"), 100.0), 1),
        Figure(f"{k}.after_turn_median_pct", f"{label}: median share of the time both move after both have turned", "%",
               _mc(preset, _median, lambda b: b.get("after_turn"), 100.0), 1),
    ) if bound else ()) + (
        Figure(f"{k}.first_valid_max_s", f"{label}: longest time to the first VALID row", "s",
               _mc(preset, max, lambda b: b.get("first_valid_s")), 1),
        Figure(f"{k}.h_rms_median_m", f"{label}: median h RMS while both move", "m",
               _mc(preset, _median, lambda b: b.get("h_rms_m")), 3),
        Figure(f"{k}.h_rms_max_m", f"{label}: largest h RMS while both move", "m",
               _mc(preset, max, lambda b: b.get("h_rms_m")), 3, "≤ 0.03" if targets else "", "#27" if targets else ""),
        Figure(f"{k}.within_3sd_min", f"{label}: lowest share within 3 sd (x, y)", "",
               _mc(preset, min, _in3), 3, "≥ 0.98", "#15"),
        Figure(f"{k}.sigma_ratio_max", f"{label}: largest median sigma_h / h RMS", "",
               _mc(preset, max, lambda b: b.get("sig_ratio")), 1, "≤ 3" if targets else "", "#15" if targets else ""),
        Figure(f"{k}.violations", f"{label}: VALID rows beyond max(0.3 m, 4 sigma), all cases", "",
               _mc(preset, sum, lambda b: b.get("violations")), 0, "0", "#27"),
        Figure(f"{k}.cases", f"{preset}" + (f", {what}" if what else "") + ": cases", "", _mc(preset, len, lambda b: 1), 0),
    )


def _real_pair_figures(delay: str) -> tuple[Figure, ...]:
    k, d = f"real_pair.drive_0708.d{delay}", ("delays", delay)
    return (
        Figure(f"{k}.computed_rms_m", f"delay {delay} s: range error RMS, every computed row", "m",
               _get(*d, "computed", "rms_m"), 4, "≤ 0.02", "#26"),
        Figure(f"{k}.computed_max_m", f"delay {delay} s: range error max, every computed row", "m",
               _get(*d, "computed", "max_m"), 4, "≤ 0.08", "#26"),
        Figure(f"{k}.valid_share_pct", f"delay {delay} s: VALID share of the scored epochs", "%",
               _get(*d, "valid_share", scale=100.0), 1, "≥ 80", "#26"),
        Figure(f"{k}.valid_within_3sd", f"delay {delay} s: VALID rows within 3 sd", "",
               _get(*d, "valid", "within_3sd"), 3, "≥ 0.98", "#26"),
        Figure(f"{k}.violations", f"delay {delay} s: VALID rows beyond max(0.3 m, 4 sd)", "",
               _get(*d, "violations"), 0, "0", "#26"),
    )


def _convoy_figures(prefix: str, what: str) -> tuple[Figure, ...]:
    return (
        Figure(f"{prefix}.valid_pct", f"{what}: VALID share of B's rows", "%", lambda r: _get("valid_fraction", scale=100.0)(_target_of(r)), 1),
        Figure(f"{prefix}.valid_moving_pct", f"{what}: VALID share while both move", "%",
               lambda r: _get("moving_valid_fraction", scale=100.0)(_target_of(r)), 1),
        Figure(f"{prefix}.h_rms_m", f"{what}: h RMS over VALID rows while both move (B's 0.8 m antenna offset undeclared)",
               "m", lambda r: _get("moving", "h_rms_m")(_target_of(r)), 3),
        Figure(f"{prefix}.within_3sd_min", f"{what}: VALID rows within 3 sd (lower of x, y)", "",
               lambda r: _within_3sd(_target_of(r)), 3, "≥ 0.98", "#15"),
        Figure(f"{prefix}.violations", f"{what}: VALID rows beyond max(0.3 m, 4 sigma)", "",
               lambda r: _get("violations")(_target_of(r)), 0, "0", "#27"),
    )


def _calibrate_figures(prefix: str, what: str, target: str = "", issue: str = "") -> tuple[Figure, ...]:
    return (
        Figure(f"{prefix}.before_outage_h_rms_m", f"{what}: outage h RMS before calibration", "m",
               _get("before", "outage_h_rms_m"), 3),
        Figure(f"{prefix}.after_outage_h_rms_m", f"{what}: outage h RMS with the written table", "m",
               _get("after", "outage_h_rms_m"), 3, target, issue),
    )


_CONVOY_ARGV = ("v2xpos", "convoy", f"{CONVOY}/A/dataset.toml", f"{CONVOY}/B/dataset.toml", "--out", "{out}",
                "--truth", f"{CONVOY}/truth_rel.csv", "--in-process")

JOBS: tuple[Job, ...] = (
    Job("replay", ("v2xpos", "replay", DRIVE, "--json", "{json}"), _json, (
        Figure("replay.drive_0708.outage_h_rms_m", "drive_0708, 11 outages of 15 s: h error at the outage ends, RMS",
               "m", _get("outage_h_rms_m"), 3, "≤ 5.0", "#2"),
        Figure("replay.drive_0708.outage_h_max_m", "drive_0708: h error at the outage ends, max", "m", _get("outage_h_max_m"), 3),
        Figure("replay.drive_0708.aided_h_rms_m", "drive_0708: h error while GNSS aids (before each update), RMS", "m",
               _get("aided_h_rms_m"), 3),
        Figure("replay.drive_0708.outage_count", "drive_0708: outages scored", "", _get("outage_count"), 0),
    ), quick=True),
    Job("bench-replay", ("v2xpos", "bench", "replay", DRIVE), _bench_replay, (
        Figure("bench_replay.drive_0708.imu_samples_per_s", "replay throughput end to end, wall (best of 2)", "samples/s",
               _get("wall"), 0, "≥ 25,000", "#2"),
        Figure("bench_replay.drive_0708.imu_samples_per_cpu_s", "replay throughput per CPU second of one core",
               "samples/s", _get("cpu"), 0),
    ), quick=True),
    Job("convoy", _CONVOY_ARGV, _report, _convoy_figures("convoy.convoy_dev", "convoy_dev as declared, in process"),
        quick=True),
    Job("real-pair", ("v2xpos", "bench", "real-pair", DRIVE, "--delay", "1", "2", "3", "--json", "{json}"), _json,
        _real_pair_figures("1") + _real_pair_figures("2") + _real_pair_figures("3"), quick=True,
        quick_argv=("v2xpos", "bench", "real-pair", DRIVE, "--delay", "1", "--json", "{json}")),
    Job("replay-smooth", ("v2xpos", "replay", DRIVE, "--smooth", "--json", "{json}"), _json, (
        Figure("smooth.drive_0708.inside_outage_h_rms_m", "drive_0708 smoothed, every RTK-fixed epoch inside the outages: h RMS",
               "m", _get("smoothed_inside_outage_h_rms_m"), 3, "≤ 0.3", "#32"),
        Figure("smooth.drive_0708.inside_outage_h_max_m", "drive_0708 smoothed, inside the outages: h max", "m",
               _get("smoothed_inside_outage_h_max_m"), 3, "≤ 1.0", "#32"),
        Figure("smooth.drive_0708.inside_outage_within_3sd", "drive_0708 smoothed, inside the outages: within 3 sd", "",
               _get("smoothed_inside_outage_within_3sd"), 3, "≥ 0.95", "#32"),
        Figure("smooth.drive_0708.forward_inside_outage_h_rms_m", "drive_0708 forward, inside the outages: h RMS", "m",
               _get("inside_outage_h_rms_m"), 3),
        Figure("smooth.drive_0708.inside_outage_epochs", "drive_0708: RTK-fixed epochs inside the outages", "",
               _get("inside_outage_epochs"), 0),
    )),
    Job("bench-replay-smooth", ("v2xpos", "bench", "replay", DRIVE, "--smooth"), _bench_replay, (
        Figure("bench_replay.drive_0708.smoothing_cost_wall", "(smoothed - forward) / forward replay time, wall", "",
               _get("cost_wall"), 2, "≤ 2", "#32"),
        Figure("bench_replay.drive_0708.smoothing_cost_cpu", "(smoothed - forward) / forward replay time, CPU", "",
               _get("cost_cpu"), 2, "≤ 2", "#32"),
    )),
    Job("calibrate-drive", ("v2xpos", "calibrate", DRIVE, "--json", "{json}"), _json,
        _calibrate_figures("calibrate.drive_0708", "drive_0708", "≤ 2.2", "#16")),
    Job("calibrate-convoy-b", ("v2xpos", "calibrate", f"{CONVOY}/B/dataset.toml", "--json", "{json}"), _json,
        _calibrate_figures("calibrate.convoy_dev_b", "convoy_dev B")),
    Job("evaluate", ("v2xpos", "bench", "evaluate", "--json", "{json}"), _json, (
        Figure("evaluate.mc.runs", "simulated sensors: runs (seeds x error models)", "", _evaluate_count("runs"), 0),
        Figure("evaluate.mc.outside_tolerance", "simulated sensors: effects recovered outside tolerance", "",
               _evaluate_count("outside"), 0, "0", "#28"),
        Figure("evaluate.mc.false_significant", "simulated sensors: absent effects reported significant", "",
               _evaluate_count("false"), 0, "0", "#28"),
    )),
    Job("evaluate-speed", ("v2xpos", "bench", "evaluate", "--speed", "--json", "{json}"), _json, (
        Figure("evaluate.speed.cpu_s", "30 min of a 20 Hz 32-object sensor: CPU time, no plots", "s",
               _get("no_plots", "cpu_s"), 1, "< 60", "#28"),
    )),
    Job("demo", ("v2xpos", "demo", "--seed", "0", "--no-live", "--out", "{out}"), _report, _demo_figures()),
    Job("bench-monitor", ("v2xpos", "bench", "monitor", "--json", "{json}"), _json, (
        Figure("monitor.cpu_pct", "monitor on 64 targets x 100 Hz: CPU of one core", "%",
               _get("monitor_cpu_percent_of_one_core"), 1, "< 10", "#18"),
        Figure("monitor.change_to_snapshot_max_s", "status change -> monitor snapshot, max", "s",
               _get("change_to_snapshot_s_max"), 2, "< 0.5", "#18"),
        Figure("monitor.missed_changes", "status changes not shown", "", _get("missed_changes"), 0, "0", "#18"),
    )),
    Job("bench-corpus", ("v2xpos", "bench", "corpus", "--json", "{json}"), _json, (
        Figure("corpus.cases", "broken inputs run through the commands", "", _get("cases"), 0, "≥ 500", "#17"),
        Figure("corpus.tracebacks", "runs that ended in a traceback", "", _get("tracebacks"), 0, "0", "#17"),
        Figure("corpus.silent", "runs that exited 0 without saying anything", "", _get("silent"), 0, "0", "#17"),
    )),
    Job("bench-trust", ("v2xpos", "bench", "trust", "--skip-soak", "--json", "{json}"), _json, (
        Figure("trust.forged_accepted", "forged messages accepted", "", _get("forged_accepted"), 0, "0", "#6"),
        Figure("trust.replayed_accepted", "replayed messages accepted", "", _get("replayed_accepted"), 0, "0", "#6"),
        Figure("trust.fuzz_crashes", "fuzzed inputs that crashed a decoder", "", _get("fuzz_crashes"), 0, "0", "#6"),
        Figure("trust.faults_passed", "fault scenarios passed", "",
               lambda r: sum(1 for f in r.get("faults", []) if f.get("passed")), 0),
        Figure("trust.faults", "fault scenarios run", "", lambda r: len(r.get("faults", [])), 0),
    )),
    Job("grading-faults", ("v2xpos", "bench", "grading", "faults", "--seeds", "20", "--json", "{json}"), _json, (
        Figure("grading.faults.faulty_missed", "simulated faulty IMU units (5 faults x 20 seeds) not graded fail", "",
               lambda r: sum(v["runs"] - v["detected"] for k, v in r["faults"].items() if k != "none"), 0, "0", "#5"),
        Figure("grading.faults.healthy_failed", "healthy units graded fail, all runs", "",
               lambda r: sum(v["healthy_fail"] for v in r["faults"].values()), 0, "0", "#5"),
    )),
    Job("grading-lidar", ("v2xpos", "bench", "grading", "lidar", "--json", "{json}"), _json, (
        Figure("grading.lidar.yaw_rate_rel_error_pct", "KISS-ICP yaw rate against the truth", "%",
               _get("yaw_rate_rel_error", scale=100.0), 2),
        Figure("grading.lidar.scale_fault_flagged", "3 % gyro scale flagged by the pose-aided rate check (1 yes)", "",
               lambda r: int(bool(r["scale_fault"]["anomaly"])), 0, "1", "#5"),
    )),
    Job("integrity-mc", ("python", "-m", "bench.integrity_mc", "--presets", "clean,dev_like", "--seeds", "0-9",
                         "--real", CONVOY, "--work", "{out}", "--json", "{json}"), _json,
        _integrity_figures("clean", True, bound=True) + _integrity_figures("dev_like", False, bound=True) + (
            Figure("integrity_mc.convoy_dev.valid_pct", "convoy_dev as declared: VALID share of rows", "%",
                   _get("convoy_dev", "valid", scale=100.0), 1),
            Figure("integrity_mc.convoy_dev.h_rms_m", "convoy_dev as declared: h RMS while both move", "m",
                   _get("convoy_dev", "h_rms_m"), 3),
            Figure("integrity_mc.convoy_dev.violations", "convoy_dev as declared: violations", "",
                   _get("convoy_dev", "violations"), 0, "0", "#27"))),
    Job("integrity-mc-verified", ("python", "-m", "bench.integrity_mc", "--presets", "clean", "--seeds", "0-9",
                                  "--verified", "--work", "{out}", "--json", "{json}"), _json,
        _integrity_figures("clean", True, "verified", "set-ups verified on an earlier drive")),
    Job("integrity-mc-calibrated", ("python", "-m", "bench.integrity_mc", "--presets", "dev_like", "--seeds", "0-9",
                                    "--verified", "--calibrate", "--work", "{out}", "--json", "{json}"), _json,
        _integrity_figures("dev_like", False, "calibrated", "the follower's calibrate --write-dataset table applied")),
    Job("integrity-mc-parking-exit", ("python", "-m", "bench.integrity_mc", "--presets", "clean,dev_like", "--seeds", "0-9",
                                      "--route", "drive_off_radius_m=16", "--route", "drive_off_turn_s=3",
                                      "--work", "{out}", "--json", "{json}"), _json,
        _integrity_figures("clean", False, "parking_exit", "the leader drives off on a 16 m circle", bound=True)
        + _integrity_figures("dev_like", False, "parking_exit", "the leader drives off on a 16 m circle", bound=True)),
    Job("driveoff-timing", ("python", "-m", "bench.driveoff_timing", "--presets", "clean,dev_like", "--seeds", "10-18",
                            "--work", "{out}", "--json", "{json}"), _json, (
        Figure("driveoff_timing.after_5s.z_rms", "IMU time offset 5 s after the drive-off's heading reset, generated "
               "followers (seeds 10-18, clean and dev_like): RMS of (estimate - truth) / sd (honest ~1)", "",
               _get("summary", "5.0", "z_rms"), 2),
        Figure("driveoff_timing.after_5s.z_abs_max", "the same: largest |estimate - truth| / sd", "",
               _get("summary", "5.0", "z_abs_max"), 1),
        Figure("driveoff_timing.after_5s.beyond_3sd", "the same: followers beyond 3 sd", "",
               _get("summary", "5.0", "beyond_3"), 0),
        Figure("driveoff_timing.after_10s.z_rms", "the same 10 s after the reset (after the first change of speed)", "",
               _get("summary", "10.0", "z_rms"), 2),
    )),
    Job("bench-calibration", ("v2xpos", "bench", "calibration", "--seeds", "20", "--fresh", "--out", "{out}"),
        _coverage, (
            Figure("calibration_mc.runs", "simulated drives fitted", "", _get("runs"), 0, "≥ 20", "#16"),
            Figure("calibration_mc.min_coverage_pct", "lowest share of runs with the truth within 2 sd, over the effects",
                   "%", _get("min_coverage", scale=100.0), 0, "≥ 90", "#16"),
            Figure("calibration_mc.false_positive_runs", "runs with an absent effect reported significant", "",
                   _get("false_positive_runs"), 0, "≤ 1", "#16"),
        )),
)

FIGURES: dict[str, Figure] = {f.key: f for j in JOBS for f in j.figures}


# ------------------------------------------------------------------------------ provenance
def machine() -> str:
    """Cores, CPU model and the 1-minute load average now."""
    model = "unknown CPU"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    return f"{os.cpu_count()} cores, {model}, load {load:.2f}"


def commit() -> str:
    """Short commit of HEAD, ``-dirty`` when a tracked file that can change a figure differs from it
    (anything but Markdown: editing the docs while the figures run does not make them dirty)."""
    def git(*a: str) -> str:
        return subprocess.run(["git", *a], cwd=ROOT, capture_output=True, text=True, check=False).stdout.strip()
    head = git("rev-parse", "--short=10", "HEAD") or "unknown"
    changed = [ln[3:] for ln in git("status", "--porcelain", "--untracked-files=no").splitlines()]
    return head + ("-dirty" if any(not c.endswith(".md") for c in changed) else "")


# ------------------------------------------------------------------------------ figures.md
def fmt(value: float | int | None, digits: int) -> str:
    if value is None or (isinstance(value, float) and value != value):
        return "-"
    return f"{value:.{digits}f}"


def _cells(line: str) -> list[str]:
    """The cells of a Markdown table row (``\\|`` is a pipe inside a cell)."""
    parts = re.split(r"(?<!\\)\|", line.strip())[1:-1]
    return [p.strip().replace("\\|", "|") for p in parts]


def read_rows(path: Path) -> dict[str, dict[str, str]]:
    """The rows of a figures.md by key (column name -> cell text, the key without its anchor)."""
    rows: dict[str, dict[str, str]] = {}
    if not path.is_file():
        return rows
    for line in path.read_text().splitlines():
        if not line.startswith("| <a id="):
            continue
        cells = _cells(line)
        if len(cells) != len(COLUMNS):
            continue
        row = dict(zip(COLUMNS, cells))
        m = re.search(r"`([^`]+)`", row["key"])
        if m:
            row["key"] = m.group(1)
            row["command"] = row["command"].strip("`")
            rows[row["key"]] = row
    return rows


def render(rows: dict[str, dict[str, str]]) -> str:
    """docs/figures.md from the rows (in the order of FIGURES, then any unknown carried key)."""
    head = ("# Measured figures\n\n"
            "Written by `v2xpos bench figures` (`--quick`: the subset CI can afford; the rest carried). Do not\n"
            "edit by hand: run the command. Each row is one figure with the command that measured it, when,\n"
            "on which commit (`-dirty`: with uncommitted changes) and on which machine (cores, CPU, 1-minute\n"
            "load average when the command started; the machine is shared, so times vary with the load).\n"
            "`carried` rows were not re-run by the last invocation and keep their own date and commit;\n"
            "`not measured` rows are figures whose command has not completed in any run yet.\n"
            "`target` is what the issue in the `issue` column asks of the figure.\n\n"
            "The README and `docs/*.md` cite a figure as a link to its key, e.g.\n"
            "`[VALUE UNIT](figures.md#KEY)` (from the README `docs/figures.md#KEY`), or `[words](figures.md#KEY)`\n"
            "to name it without stating it; `tests/test_figures.py` fails when a cited key is missing here or a\n"
            "stated value differs from this file's at the digits stated.\n\n")
    lines = ["| " + " | ".join(COLUMNS) + " |", "|" + "---|" * len(COLUMNS)]
    order = list(FIGURES) + [k for k in rows if k not in FIGURES]
    for key in order:
        r = rows.get(key)
        if r is None:
            continue
        f = FIGURES.get(key)
        if f is not None:   # the definition (unit, target, issue, what) is the code's; the value the run's
            r = {**r, "unit": f.unit, "target": f.target, "issue": f.issue, "what": f.what}
        cells = [f'<a id="{key}"></a>`{key}`'] + [r.get(c, "") for c in COLUMNS[1:]]
        cells[COLUMNS.index("command")] = f"`{r.get('command', '')}`"
        lines.append("| " + " | ".join(c.replace("|", "\\|") for c in cells) + " |")
    return head + "\n".join(lines) + "\n"


# ------------------------------------------------------------------------------ running
def _command_text(argv: tuple[str, ...]) -> str:
    return " ".join(shlex.quote(a) if a not in ("{json}", "{out}") else {"{json}": "F.json", "{out}": "DIR"}[a]
                    for a in argv)


def _exec_argv(argv: tuple[str, ...], js: Path, out: Path) -> list[str]:
    real = [str(js) if a == "{json}" else str(out) if a == "{out}" else a for a in argv]
    if real[0] == "v2xpos":
        return [sys.executable, "-m", "v2xpos", *real[1:]]
    if real[0] == "python":
        return [sys.executable, *real[1:]]
    return real


def run_job(job: Job, quick: bool, log=print) -> tuple[dict[str, dict[str, str]], str]:
    """Run one job; returns (rows by key, a one-line account). No rows when the command failed."""
    argv = job.quick_argv if quick and job.quick_argv else job.argv
    started = _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%d %H:%M")
    where, rev = machine(), commit()
    t0 = time.time()
    with tempfile.TemporaryDirectory(prefix=f"v2xpos-figures-{job.name}-") as tmp:
        js, out = Path(tmp) / "figures.json", Path(tmp) / "out"
        proc = subprocess.run(_exec_argv(argv, js, out), cwd=ROOT, capture_output=True, text=True, check=False)
        took = time.time() - t0
        if proc.returncode not in job.accept_rc:
            tail = (proc.stderr or proc.stdout).strip().splitlines()[-3:]
            return {}, f"{job.name}: exit {proc.returncode} after {took:.0f} s: {' / '.join(tail)}"
        try:
            data = job.read(proc.stdout, js, out)
        except (OSError, ValueError, KeyError) as exc:
            return {}, f"{job.name}: output not readable after {took:.0f} s: {exc}"
    rows = {}
    for f in job.figures:
        try:
            value = f.pick(data)
        except (KeyError, TypeError, ValueError, IndexError):
            value = None
        if value is None:
            continue
        rows[f.key] = {"value": fmt(value, f.digits), "unit": f.unit, "target": f.target, "issue": f.issue,
                       "what": f.what, "command": _command_text(argv), "date (UTC)": started, "commit": rev,
                       "machine": where, "run": "measured"}
    missing = [f.key for f in job.figures if f.key not in rows]
    return rows, (f"{job.name}: {len(rows)} figures in {took:.0f} s (exit {proc.returncode})"
                  + (f"; absent: {', '.join(missing)}" if missing else ""))


def not_measured(job: Job, figure: Figure) -> dict[str, str]:
    """The row of a figure no run has measured yet: its definition, no value."""
    return {"value": "-", "unit": figure.unit, "target": figure.target, "issue": figure.issue, "what": figure.what,
            "command": _command_text(job.argv), "date (UTC)": "-", "commit": "-", "machine": "-", "run": NOT_MEASURED}


def _write(path: Path, rows: dict[str, dict[str, str]]) -> None:
    """Write the figures file; a defined figure without a row gets a ``not measured`` row."""
    for job in JOBS:
        for f in job.figures:
            rows.setdefault(f.key, not_measured(job, f))
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(render(rows))


def add_bench_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``v2xpos bench figures``."""
    parser.add_argument("--quick", action="store_true",
                        help="only the jobs cheap enough for CI (a few minutes); carry the other rows")
    parser.add_argument("--only", help="comma-separated job names to run (see --list; '' runs none and only "
                                       "rewrites the file); carry the other rows")
    parser.add_argument("--list", action="store_true", help="list the jobs and their figures, run nothing")
    parser.add_argument("--out", default=str(FIGURES_MD), help="the figures file to write (default docs/figures.md)")


def run_bench(args: argparse.Namespace) -> int:
    """Run the chosen jobs, rewriting the figures file after each; exit 1 when a command failed."""
    if args.list:
        for j in JOBS:
            print(f"{j.name}{' (quick)' if j.quick else ''}: {_command_text(j.argv)}")
            for f in j.figures:
                print(f"    {f.key}  [{f.unit or '-'}] {f.target} {f.issue}")
        return 0
    names = {j.name for j in JOBS}
    chosen = [j for j in JOBS if (j.quick or not args.quick)]
    if args.only is not None:
        wanted = [w.strip() for w in args.only.split(",") if w.strip()]
        unknown = [w for w in wanted if w not in names]
        if unknown:
            print(f"v2xpos bench figures: unknown job(s) {unknown}; jobs: {', '.join(sorted(names))}", file=sys.stderr)
            return 2
        chosen = [j for j in chosen if j.name in wanted]
    path = Path(args.out)
    previous = read_rows(path)
    # rows not re-run by this invocation are carried; a rewrite alone (--only '') keeps the marks
    rows = {k: {**r, "run": "carried" if r.get("run") != NOT_MEASURED and chosen else r.get("run", "carried")}
            for k, r in previous.items()}
    failed = 0
    t_start = time.time()
    for job in chosen:
        print(f"[{time.time() - t_start:6.0f} s] {job.name}: {_command_text(job.quick_argv if args.quick and job.quick_argv else job.argv)}",
              flush=True)
        new, account = run_job(job, args.quick)
        failed += not new
        rows.update(new)
        print(f"    {account}", flush=True)
        _write(path, rows)
    if not chosen:
        _write(path, rows)
    print(f"figures: {len(chosen)} job(s) in {time.time() - t_start:.0f} s, {failed} failed; "
          f"{sum(r['run'] == 'measured' for r in rows.values())} measured, "
          f"{sum(r['run'] == 'carried' for r in rows.values())} carried, "
          f"{sum(r['run'] == NOT_MEASURED for r in rows.values())} not measured -> {path}")
    return 1 if failed else 0
