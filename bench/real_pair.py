"""``v2xpos bench real-pair DATASET_TOML [--delay S ...] [--link] [--json F] [--plots DIR]``: a real
two-vehicle case from one real recording, scored against the RTK.

Every real recording holds a two-vehicle case: **the same car, a few seconds behind itself**.
Vehicle A is the recording as it is; vehicle B is the same recording re-stamped ``delay`` seconds
later (every GPS time + delay: the ``.pos`` epochs and the TIMETAG file-open time; the IMU counter
unchanged). At GPS time t, B is where the car was at t - delay, so the truth of their separation is
the RTK antenna-to-antenna range |r(t) - r(t - delay)| between two fixed epochs (1-2 cm each). The
pair keeps everything real -- IMU noise and vibration, the IMU's time offset, the mounting, the
lever arm -- and nothing is simulated.

Scored epochs: the RTK epochs t of A such that t - delay is also an epoch, both are RTK fixed,
the car moves faster than ``--min-speed`` at both, and its course changed less than
``--max-turn-deg`` between them. There the result's range (B's IMU point from A's, ``range_m`` of
``results.csv``) is the antenna range to millimetres: with both antennas at the same lever arm on
the same car, the two offsets are the same vector when the heading is the same (a turn of 2 deg
moves a 0.1 m lever arm's end by 3.5 mm). Epochs left out are counted by reason.

Per delay: range error (result minus truth) RMS / max / bias over every computed row and over
VALID rows, the VALID share of the scored epochs, the share within 3 sd of ``range_sd_m``, the
worst error in units of max(0.3 m, 4 sd) (> 1 is a violation: a VALID row farther off than the
reference may ever be), and a plot of the range error and the status over time.

The pair goes through the master pipeline in one process (``master.convoy.run_in_process``, the
default) or, with ``--link``, as a master and a slave process over zenoh on loopback
(``master.convoy.run_processes``, at ``--speed`` times real time).

``--smooth`` (in process): B gets GNSS outages (``--outage``; by default the replay's schedule), the
pair runs once forward and once from both vehicles' smoothed states (``master.smoothed_convoy``),
and both are scored: every computed and VALID row of each, the epochs both computed, and the
smoothed rows inside B's outages (where the forward pipeline has none: B is dead reckoning).
"""
from __future__ import annotations

import argparse
import json
import math
import shutil
import struct
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

DEFAULT_DELAYS_S = (1.0, 2.0, 3.0)
MIN_SPEED_MPS = 2.0
MAX_TURN_DEG = 2.0
MATCH_TOLERANCE_S = 0.05
"""A scored epoch takes the result rows bracketing it when they are this close (results come at the
slave's state rate, 100 Hz: 10 ms apart)."""
COURSE_BASELINE_S = 0.5
"""A's course for the cross-range truth: the direction of its RTK antenna track from t - 0.5 s to
t + 0.5 s (a 10 m chord at 10 m/s: 2 mrad from 1.4 cm of noise per fix), taken as A's heading --
exact for a car without side slip on a straight road, which the scored epochs are."""
VIOLATION_FLOOR_M = 0.3
VIOLATION_SIGMAS = 4.0
TIMETAG_OPEN_OFFSET = 64
"""Byte offset of the TIMETAG file-open time (uint32 seconds + float64 fraction, ``datasets.timetag``)."""


class PairError(ValueError):
    """A recording that cannot make a real pair (the message names the file and why)."""


# ---------------------------------------------------------------------------------------- building
def _shift_pos_line(line: str, delay_s: float) -> str:
    """One RTKLIB solution line with its time moved by ``delay_s`` (calendar ``YYYY/MM/DD HH:MM:SS.sss``
    or ``week tow``), the rest of the line unchanged."""
    import datetime
    tok = line.split()
    if "/" in tok[0]:
        head = f"{tok[0]} {tok[1]}"
        decimals = len(tok[1].partition(".")[2])
        t = datetime.datetime.strptime(head, "%Y/%m/%d %H:%M:%S" + (".%f" if decimals else ""))
        t += datetime.timedelta(seconds=delay_s)
        new = t.strftime("%Y/%m/%d %H:%M:%S")
        if decimals:
            new += "." + f"{t.microsecond:06d}"[:decimals]
    else:
        head = f"{tok[0]} {tok[1]}"
        decimals = len(tok[1].partition(".")[2])
        week, tow = int(tok[0]), float(tok[1]) + delay_s
        week += int(tow // 604800.0)
        new = f"{week} {tow % 604800.0:.{decimals}f}".rjust(len(head))
    i = line.index(head)
    return line[:i] + new + line[i + len(head):]


def _pos_line_time_s(line: str) -> float:
    """Time of an RTKLIB solution line [s] (calendar: POSIX seconds of the stamp as written; week/tow:
    GPS seconds) -- only differences of it are used."""
    import datetime
    tok = line.split()
    if "/" in tok[0]:
        fmt = "%Y/%m/%d %H:%M:%S" + (".%f" if "." in tok[1] else "")
        t = datetime.datetime.strptime(f"{tok[0]} {tok[1]}", fmt).replace(tzinfo=datetime.timezone.utc)
        return t.timestamp()
    return int(tok[0]) * 604800.0 + float(tok[1])


def restamp_dataset(toml_path: str | Path, delay_s: float, out_dir: Path, name: str,
                    outages: tuple = ()) -> Path:
    """A copy of the recording ``toml_path`` re-stamped ``delay_s`` later, as ``out_dir/dataset.toml``
    named ``name``: the ``.pos`` epochs and the IMU TIMETAG's file-open time + delay (the IMU csv
    and its counter are the original's, read in place). A raw receiver stream is left out (its
    own times would need re-stamping too; the recording source does not read it). ``outages``:
    (start, length) pairs [s from the first epoch]: the epochs inside [start, start + length) are
    left out of the copy (a GNSS outage of this vehicle)."""
    import tomli_w
    from v2xpos.compat import tomllib
    src = Path(toml_path)
    if src.is_dir():
        src = src / "dataset.toml"
    try:
        desc = tomllib.loads(src.read_text())
    except (OSError, ValueError) as exc:
        raise PairError(f"{src}: cannot read the descriptor: {exc}") from None
    base = src.parent.resolve()
    imu, gnss = dict(desc.get("imu", {})), dict(desc.get("gnss", {}))
    if gnss.get("format") != "rtklib_pos":
        raise PairError(f"{src}: [gnss] format {gnss.get('format')!r}: a real pair needs an RTKLIB .pos "
                        f"(format = \"rtklib_pos\") to re-stamp and to score against")
    if not imu.get("timetag"):
        raise PairError(f"{src}: [imu] timetag missing: the IMU's GPS time comes from its TIMETAG, which "
                        f"is what re-stamps vehicle B")
    out_dir.mkdir(parents=True, exist_ok=True)
    tag = bytearray((base / imu["timetag"]).read_bytes())
    if len(tag) < TIMETAG_OPEN_OFFSET + 12:
        raise PairError(f"{base / imu['timetag']}: too short for a TIMETAG header")
    sec, = struct.unpack_from("<I", tag, TIMETAG_OPEN_OFFSET)
    frac, = struct.unpack_from("<d", tag, TIMETAG_OPEN_OFFSET + 4)
    whole, part = divmod(sec + frac + delay_s, 1.0)
    struct.pack_into("<I", tag, TIMETAG_OPEN_OFFSET, int(whole))
    struct.pack_into("<d", tag, TIMETAG_OPEN_OFFSET + 4, part)
    (out_dir / "imu.csv.tag").write_bytes(bytes(tag))
    lines = []
    t_first = None
    for line in (base / gnss["file"]).read_text().splitlines(keepends=True):
        body = line.strip()
        if body and not body.startswith("%") and outages:
            t = _pos_line_time_s(line)
            t_first = t if t_first is None else t_first
            if any(a <= t - t_first < a + n for a, n in outages):
                continue
        lines.append(line if not body or body.startswith("%") else _shift_pos_line(line, delay_s))
    (out_dir / "gnss.pos").write_text("".join(lines))
    imu["file"] = str(base / imu["file"])
    imu["timetag"] = str(out_dir / "imu.csv.tag")
    gnss["file"] = str(out_dir / "gnss.pos")
    for key in ("raw", "raw_timetag", "timetag"):
        gnss.pop(key, None)
    desc.update(name=name, imu=imu, gnss=gnss)
    out = out_dir / "dataset.toml"
    out.write_bytes(tomli_w.dumps(desc).encode())
    return out


# ---------------------------------------------------------------------------------------- truth
@dataclass
class PairTruth:
    """The scored epochs of one delay: ``t_s`` (A's epochs), the antenna range [m], B's antenna
    across A's course [m, right positive] (``cross_m``), and the count of epochs left out per reason."""
    t_s: np.ndarray
    range_m: np.ndarray
    skipped: dict
    cross_m: np.ndarray | None = None


def pair_truth(gnss, delay_s: float, min_speed_mps: float = MIN_SPEED_MPS,
               max_turn_deg: float = MAX_TURN_DEG) -> PairTruth:
    """Scored epochs and their true range for a pair at ``delay_s`` (module docstring) from the
    original recording's GNSS solution ``gnss`` (``GnssData``). The course is the GNSS velocity's
    (from position differences when the solution has none)."""
    from v2xpos import geo
    from v2xpos.types import FixStatus
    t = np.asarray(gnss.t_s, float)
    lla = np.asarray(gnss.lla, float)
    fix = np.asarray(gnss.fix)
    ecef = np.array([geo.lla_to_ecef(x) for x in lla]) if len(t) else np.zeros((0, 3))
    if gnss.vel_ned_mps is not None:
        v = np.asarray(gnss.vel_ned_mps, float)[:, :2]
    else:
        ned = np.array([geo.lla_to_ned(x, lla[0]) for x in lla])[:, :2]
        v = np.gradient(ned, t, axis=0) if len(t) > 1 else np.zeros((len(t), 2))
    speed = np.hypot(v[:, 0], v[:, 1])
    course = np.arctan2(v[:, 1], v[:, 0])
    ms = np.round(t * 1000.0).astype(np.int64)
    index = {int(k): i for i, k in enumerate(ms)}
    d_ms = int(round(delay_s * 1000.0))
    skipped = {"no_epoch_at_t_minus_delay": 0, "not_fixed": 0, "slow": 0, "turning": 0}
    keep_t, keep_r, keep_c = [], [], []
    course_ms = int(round(COURSE_BASELINE_S * 1000.0))
    for i in range(len(t)):
        j = index.get(int(ms[i]) - d_ms)
        if j is None:
            skipped["no_epoch_at_t_minus_delay"] += 1
        elif fix[i] != FixStatus.FIXED or fix[j] != FixStatus.FIXED:
            skipped["not_fixed"] += 1
        elif speed[i] < min_speed_mps or speed[j] < min_speed_mps:
            skipped["slow"] += 1
        elif abs(math.degrees(math.remainder(course[i] - course[j], 2 * math.pi))) >= max_turn_deg:
            skipped["turning"] += 1
        else:
            keep_t.append(t[i])
            keep_r.append(float(np.linalg.norm(ecef[i] - ecef[j])))
            a, b = index.get(int(ms[i]) - course_ms), index.get(int(ms[i]) + course_ms)
            cross = math.nan
            if a is not None and b is not None and fix[a] == FixStatus.FIXED and fix[b] == FixStatus.FIXED:
                C = geo.dcm_ecef_to_ned(lla[i][0], lla[i][1])
                u = (C @ (ecef[b] - ecef[a]))[:2]
                r = (C @ (ecef[j] - ecef[i]))[:2]
                cross = float((u[0] * r[1] - u[1] * r[0]) / max(float(np.hypot(u[0], u[1])), 1e-9))
            keep_c.append(cross)
    return PairTruth(np.asarray(keep_t, float), np.asarray(keep_r, float), skipped, np.asarray(keep_c, float))


# ---------------------------------------------------------------------------------------- scoring
def _rows(results_csv: Path, target: str) -> dict:
    import csv
    cols = {"t": [], "range": [], "sd": [], "status": [], "y": [], "sd_y": []}
    with open(results_csv, newline="") as fh:
        for row in csv.DictReader(fh):
            if row.get("target") != target:
                continue
            try:
                cols["t"].append(float(row["t_gps_s"]))
            except (TypeError, ValueError):
                continue
            cols["range"].append(float(row["range_m"]) if row.get("range_m") else math.nan)
            cols["sd"].append(float(row["range_sd_m"]) if row.get("range_sd_m") else math.nan)
            cols["status"].append(row.get("status", ""))
            cols["y"].append(float(row["y_m"]) if row.get("y_m") else math.nan)
            cols["sd_y"].append(float(row["sd_y_m"]) if row.get("sd_y_m") else math.nan)
    t = np.asarray(cols["t"], float)
    o = np.argsort(t, kind="stable")
    return {"t": t[o], "range": np.asarray(cols["range"], float)[o], "sd": np.asarray(cols["sd"], float)[o],
            "status": np.asarray(cols["status"], object)[o], "y": np.asarray(cols["y"], float)[o],
            "sd_y": np.asarray(cols["sd_y"], float)[o]}


def _figures(err: np.ndarray, sd: np.ndarray) -> dict:
    if not len(err):
        return {"n": 0, "rms_m": None, "max_m": None, "bias_m": None, "within_3sd": None, "worst_bound_ratio": None}
    bound = np.maximum(VIOLATION_FLOOR_M, VIOLATION_SIGMAS * np.nan_to_num(sd, nan=0.0))
    return {"n": int(len(err)), "rms_m": float(np.sqrt(np.mean(err ** 2))), "max_m": float(np.max(np.abs(err))),
            "bias_m": float(np.mean(err)), "within_3sd": float(np.mean(np.abs(err) <= 3.0 * sd)),
            "worst_bound_ratio": float(np.max(np.abs(err) / bound))}


def _cross_figures(r: dict, k: np.ndarray, w: np.ndarray, near: np.ndarray, ok: np.ndarray, status: np.ndarray,
                   truth: PairTruth) -> dict:
    """B's position across A's heading (``y_m``) against the RTK course (``COURSE_BASELINE_S``): the
    check of the master's heading and of ``sd_y_m``, which the range does not see."""
    if truth.cross_m is None:
        return {}
    y = (1.0 - w) * r["y"][k - 1] + w * r["y"][k]
    err = y - truth.cross_m
    sd = r["sd_y"][near]
    m = ok & np.isfinite(err)
    return {"computed": _figures(err[m], sd[m]), "valid": _figures(err[m & (status == "VALID")], sd[m & (status == "VALID")])}


def score_pair(results_csv: Path, target: str, truth: PairTruth) -> dict:
    """Range errors at the scored epochs (``pair_truth``) from ``results.csv`` rows of ``target``: the
    range interpolated linearly between the two rows bracketing each epoch (when both are within
    ``MATCH_TOLERANCE_S``), the status and sd of the nearer one."""
    r = _rows(results_csv, target)
    t = r["t"]
    n_scored = len(truth.t_s)
    out = {"scored_epochs": n_scored, "skipped": dict(truth.skipped)}
    if not len(t) or not n_scored:
        out.update(no_result_row=n_scored, computed=_figures(np.zeros(0), np.zeros(0)),
                   valid=_figures(np.zeros(0), np.zeros(0)), valid_share=0.0, status_counts={}, series=None)
        return out
    k = np.clip(np.searchsorted(t, truth.t_s), 1, len(t) - 1)
    t0, t1 = t[k - 1], t[k]
    ok = (truth.t_s - t0 <= MATCH_TOLERANCE_S) & (t1 - truth.t_s <= MATCH_TOLERANCE_S) & (t1 > t0)
    w = np.where(t1 > t0, (truth.t_s - t0) / np.where(t1 > t0, t1 - t0, 1.0), 0.0)
    rng = (1.0 - w) * r["range"][k - 1] + w * r["range"][k]
    near = np.where(w < 0.5, k - 1, k)
    status = r["status"][near]
    sd = r["sd"][near]
    err = rng - truth.range_m
    computed = ok & np.isfinite(err)
    valid = computed & (status == "VALID")
    from collections import Counter
    out.update(no_result_row=int(n_scored - ok.sum()),
               computed=_figures(err[computed], sd[computed]),
               valid=_figures(err[valid], sd[valid]),
               valid_share=float(valid.sum() / n_scored),
               violations=int(np.sum(np.abs(err[valid]) > np.maximum(VIOLATION_FLOOR_M, VIOLATION_SIGMAS * sd[valid]))),
               status_counts=dict(Counter(str(s) for s in status[ok])),
               cross_range=_cross_figures(r, k, w, near, ok, status, truth),
               series={"t_s": truth.t_s[ok], "err_m": err[ok], "sd_m": sd[ok], "status": status[ok]})
    return out


# ---------------------------------------------------------------------------------------- running
def run_pair(dataset: Path, delay_s: float, work: Path, link: bool = False, speed: float = 5.0,
             log=None, smooth: bool = False, outages: tuple = ()) -> tuple[Path, str, dict]:
    """Build the pair at ``delay_s`` in ``work`` (B without GNSS in ``outages``, ``restamp_dataset``)
    and run it through the master pipeline; returns (results.csv, B's id, the run's facts). With
    ``smooth`` the in-process run is the smoothed one (``master.smoothed_convoy``): results.csv from
    the smoothed states, results_forward.csv beside it from the forward ones. ``log``: progress
    lines (default the current ``sys.stderr``)."""
    log = sys.stderr if log is None else log
    from master.convoy import dataset_identity, run_in_process, run_processes
    from v2xpos.datasets.loader import read_descriptor
    name = str(read_descriptor(dataset).get("name") or "A")
    b_name = f"{name}_plus{int(round(delay_s * 1000))}ms"
    b_toml = restamp_dataset(dataset, delay_s, work / "B", b_name, outages)
    master, slave = dataset_identity(dataset), dataset_identity(b_toml)
    out = work / "run"
    facts = (run_processes(out, master, [slave], speed, log=log) if link
             else run_in_process(out, master, [slave], log=log, smooth=smooth))
    return out / "results.csv", b_name, facts


def plot_pair(series: dict, delay_s: float, name: str, path: Path) -> None:
    """Range error and status over time for one delay (the VALID rows' 3-sd band shaded)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    t = series["t_s"] - series["t_s"][0]
    err, sd, status = series["err_m"], series["sd_m"], series["status"]
    fig, (ax, ax2) = plt.subplots(2, 1, figsize=(11, 5.5), sharex=True, gridspec_kw={"height_ratios": [3, 1]})
    ax.fill_between(t, -3 * sd, 3 * sd, color="0.85", label="±3 sd (range_sd_m)", step="mid")
    for st, colour in (("VALID", "tab:green"),):
        m = status == st
        ax.plot(t[m], err[m], ".", ms=3, color=colour, label=st)
    m = status != "VALID"
    ax.plot(t[m], err[m], ".", ms=3, color="tab:red", label="not VALID")
    ax.axhline(0, color="k", lw=0.5)
    ax.set_ylabel("range error [m]")
    ax.set_title(f"{name}: real pair at delay {delay_s:g} s (range minus RTK antenna range)")
    ax.legend(loc="upper right", fontsize=8)
    names = sorted(set(str(s) for s in status))
    ax2.plot(t, [names.index(str(s)) for s in status], "|", ms=6)
    ax2.set_yticks(range(len(names)), names, fontsize=7)
    ax2.set_xlabel("s from the first scored epoch")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _fmt(v, d: int = 4) -> str:
    return "-" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:.{d}f}"


def add_bench_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``v2xpos bench real-pair``."""
    parser.add_argument("dataset", help="dataset.toml of a real recording with an RTKLIB .pos and an IMU TIMETAG")
    parser.add_argument("--delay", type=float, nargs="+", default=list(DEFAULT_DELAYS_S), metavar="S",
                        help=f"B's delay behind A [s] (default {' '.join(f'{d:g}' for d in DEFAULT_DELAYS_S)})")
    parser.add_argument("--link", action="store_true",
                        help="master and slave as processes over zenoh on loopback (default: in process)")
    parser.add_argument("--speed", type=float, default=5.0, help="with --link: times real time (default 5)")
    parser.add_argument("--min-speed", type=float, default=MIN_SPEED_MPS, help="scored above this speed [m/s]")
    parser.add_argument("--max-turn-deg", type=float, default=MAX_TURN_DEG,
                        help="scored where the course changed less than this over the delay [deg]")
    parser.add_argument("--json", help="write the figures to this JSON file")
    parser.add_argument("--plots", help="write one plot per delay into this directory")
    parser.add_argument("--keep", help="keep the pair and its results in this directory (default: a temporary one)")
    parser.add_argument("--smooth", action="store_true",
                        help="in process: also the results from both vehicles' smoothed states (master.smoothed_convoy), "
                             "scored beside the forward ones, with GNSS outages in B (--outage)")
    parser.add_argument("--outage", action="append", metavar="START:LENGTH",
                        help="a GNSS outage of B [s from its first epoch] (repeatable; 'none' for none; default with "
                             "--smooth: the replay's schedule, 15 s every 45 s from 40 s)")


def parse_outages(values: list[str] | None, smooth: bool) -> tuple:
    """(start, length) pairs from ``--outage`` values; without any, the replay's default schedule
    (``OutageSchedule``) over a day when smoothing (only those inside the recording matter), else
    none. ValueError naming a bad value."""
    if not values:
        if not smooth:
            return ()
        from v2xpos.ins.replay_engine import OutageSchedule
        sched = OutageSchedule()
        return tuple((a, sched.length_s) for a, _ in sched.intervals(0.0, 86400.0))
    out = []
    for v in values:
        if v == "none":
            continue
        try:
            a, n = (float(x) for x in v.split(":"))
        except ValueError:
            raise ValueError(f"--outage {v!r}: expected START:LENGTH in seconds, e.g. 100:15") from None
        if not (a >= 0 and n > 0):
            raise ValueError(f"--outage {v!r}: START must be >= 0 and LENGTH > 0")
        out.append((a, n))
    return tuple(out)


def compare_smoothed(forward: dict, smoothed: dict, t0_s: float, outages: tuple) -> dict:
    """Forward against smoothed results of one delay (``score_pair`` of each, with their series):
    over the epochs both computed, over those VALID in both, and at the scored epochs inside B's outages (``t0_s``: B's first
    epoch, where the outages' starts count from), where the forward pipeline gives no kinematics
    (B dead reckoning: FIX_INVALID)."""
    fs, ss = forward.get("series"), smoothed.get("series")
    if fs is None or ss is None:
        return {}
    tf, ts = np.asarray(fs["t_s"]), np.asarray(ss["t_s"])
    common, i_f, i_s = np.intersect1d(tf, ts, return_indices=True)
    ef, es = np.asarray(fs["err_m"])[i_f], np.asarray(ss["err_m"])[i_s]
    both = np.isfinite(ef) & np.isfinite(es)
    sdf, sds = np.asarray(fs["sd_m"])[i_f], np.asarray(ss["sd_m"])[i_s]
    valid = both & (np.asarray(fs["status"])[i_f] == "VALID") & (np.asarray(ss["status"])[i_s] == "VALID")
    out = {"both_computed": {"forward": _figures(ef[both], sdf[both]), "smoothed": _figures(es[both], sds[both])},
           "both_valid": {"forward": _figures(ef[valid], sdf[valid]), "smoothed": _figures(es[valid], sds[valid])}}
    inside = np.zeros(len(ts), bool)
    for a, n in outages:
        inside |= (ts - t0_s >= a) & (ts - t0_s < a + n)
    e_in, sd_in = np.asarray(ss["err_m"])[inside], np.asarray(ss["sd_m"])[inside]
    ok = np.isfinite(e_in)
    f_in = np.isin(tf, ts[inside]) & np.isfinite(np.asarray(fs["err_m"]))
    out["inside_outages"] = {"scored": int(inside.sum()), "forward_computed": int(f_in.sum()),
                             "smoothed": _figures(e_in[ok], sd_in[ok]),
                             "smoothed_valid": int(np.sum(np.asarray(ss["status"])[inside][ok] == "VALID"))}
    return out


def _outages_within(outages: tuple, span_s: float) -> int:
    return sum(1 for a, _ in outages if a < span_s)


def _print_score(label: str, score: dict) -> None:
    c, v = score["computed"], score["valid"]
    print(f"  {label}every computed row: n {c['n']}  RMS {_fmt(c['rms_m'])} m  max {_fmt(c['max_m'])} m  "
          f"bias {_fmt(c['bias_m'])} m  within 3 sd {_fmt(c['within_3sd'], 3)}\n"
          f"  {label}VALID rows:         n {v['n']}  RMS {_fmt(v['rms_m'])} m  max {_fmt(v['max_m'])} m  "
          f"bias {_fmt(v['bias_m'])} m  within 3 sd {_fmt(v['within_3sd'], 3)}  "
          f"worst / max(0.3 m, 4 sd) {_fmt(v['worst_bound_ratio'], 3)}\n"
          f"  {label}across A's course (heading check, RTK course as truth): every computed row RMS "
          f"{_fmt((score.get('cross_range') or {}).get('computed', {}).get('rms_m'))} m, within 3 sd_y "
          f"{_fmt((score.get('cross_range') or {}).get('computed', {}).get('within_3sd'), 3)}\n"
          f"  {label}VALID share {100 * score['valid_share']:.1f} %  violations {score.get('violations', 0)}  "
          f"statuses {score['status_counts']}", flush=True)


def run_bench(args: argparse.Namespace) -> int:
    from v2xpos.datasets.loader import load_dataset
    from v2xpos.types import FixStatus
    dataset = Path(args.dataset)
    if dataset.is_dir():
        dataset = dataset / "dataset.toml"
    delays = [round(float(d), 3) for d in args.delay]
    if any(not d > 0 for d in delays):
        print(f"v2xpos bench real-pair: --delay must be > 0 s, got {args.delay}", file=sys.stderr)
        return 2
    try:
        ds = load_dataset(dataset)
    except (OSError, ValueError) as exc:
        print(f"v2xpos bench real-pair: {exc}", file=sys.stderr)
        return 2
    gnss_file = (ds.notes.get("files", {}) or {}).get("gnss", str(dataset))
    if not np.any(np.asarray(ds.gnss.fix) == FixStatus.FIXED):
        print(f"v2xpos bench real-pair: {gnss_file}: no RTK fixed epoch: nothing to score against", file=sys.stderr)
        return 2
    if args.smooth and args.link:
        print("v2xpos bench real-pair: --smooth runs in process (the smoother needs each whole recording); "
              "leave out --link", file=sys.stderr)
        return 2
    try:
        outages = parse_outages(args.outage, args.smooth)
    except ValueError as exc:
        print(f"v2xpos bench real-pair: {exc}", file=sys.stderr)
        return 2
    keep = Path(args.keep).resolve() if args.keep else None
    report = {"dataset": str(dataset), "name": ds.name, "mode": "link" if args.link else "in_process",
              "min_speed_mps": args.min_speed, "max_turn_deg": args.max_turn_deg, "smoothed": bool(args.smooth),
              "outages_b": [list(o) for o in outages], "delays": {}}
    plots = Path(args.plots) if args.plots else None
    if plots:
        plots.mkdir(parents=True, exist_ok=True)
    for d in delays:
        truth = pair_truth(ds.gnss, d, args.min_speed, args.max_turn_deg)
        span = float(ds.gnss.t_s[-1] - ds.gnss.t_s[0]) if len(ds.gnss.t_s) else 0.0
        if d >= span or not len(truth.t_s):
            why = (f"the two vehicles share no time (delay {d:g} s, GNSS span {span:.1f} s)" if d >= span
                   else f"no epoch to score at delay {d:g} s (left out: {truth.skipped})")
            print(f"v2xpos bench real-pair: {gnss_file}: {why}", file=sys.stderr)
            return 2
        work = (keep / f"delay_{d:g}") if keep else Path(tempfile.mkdtemp(prefix="v2xpos-real-pair-"))
        if work.exists() and keep:
            shutil.rmtree(work)
        t0 = time.time()
        try:
            results, b_name, facts = run_pair(dataset, d, work, link=args.link, speed=args.speed, smooth=args.smooth,
                                              outages=outages)
            score = score_pair(results.with_name("results_forward.csv") if args.smooth else results, b_name, truth)
            smoothed = score_pair(results, b_name, truth) if args.smooth else None
        except (OSError, ValueError) as exc:
            print(f"v2xpos bench real-pair: {exc}", file=sys.stderr)
            return 2
        finally:
            if not keep:
                shutil.rmtree(work, ignore_errors=True)
        if smoothed is not None:
            t0_b = float(np.min(ds.gnss.t_s)) + d
            score["smoothing"] = compare_smoothed(score, smoothed, t0_b, outages)
            score["smoothing"]["pipeline"] = facts.get("smoothing")
            sm_series = smoothed.pop("series")
            score["smoothed"] = smoothed
            if plots and sm_series is not None and len(sm_series["t_s"]):
                plot_pair(sm_series, d, f"{ds.name} smoothed", plots / f"real_pair_{ds.name}_{d:g}s_smoothed.png")
        series = score.pop("series")
        if plots and series is not None and len(series["t_s"]):
            plot_pair(series, d, ds.name, plots / f"real_pair_{ds.name}_{d:g}s.png")
        score["wall_s"] = time.time() - t0
        score["pipeline"] = {k: v for k, v in facts.items() if k in ("processed", "rejected", "exit_codes", "forward")}
        report["delays"][f"{d:g}"] = score
        print(f"delay {d:g} s: {score['scored_epochs']} epochs scored (left out {score['skipped']}, "
              f"no result row {score['no_result_row']}; {score['wall_s']:.0f} s)"
              + (f", B without GNSS in {_outages_within(outages, span)} outage(s)" if outages else ""), flush=True)
        _print_score("forward:  " if smoothed is not None else "", score)
        if smoothed is not None:
            _print_score("smoothed: ", smoothed)
            cmp = score["smoothing"]
            if cmp:
                bf, bs = cmp["both_computed"]["forward"], cmp["both_computed"]["smoothed"]
                vf, vs = cmp["both_valid"]["forward"], cmp["both_valid"]["smoothed"]
                ins = cmp["inside_outages"]
                print(f"  epochs both computed: n {bf['n']}  RMS forward {_fmt(bf['rms_m'])} m, smoothed "
                      f"{_fmt(bs['rms_m'])} m; max forward {_fmt(bf['max_m'])} m, smoothed {_fmt(bs['max_m'])} m\n"
                      f"  epochs VALID in both: n {vf['n']}  RMS forward {_fmt(vf['rms_m'])} m, smoothed "
                      f"{_fmt(vs['rms_m'])} m; max forward {_fmt(vf['max_m'])} m, smoothed {_fmt(vs['max_m'])} m\n"
                      f"  inside B's outages: {ins['scored']} scored epochs, forward computed {ins['forward_computed']}, "
                      f"smoothed n {ins['smoothed']['n']}  RMS {_fmt(ins['smoothed']['rms_m'])} m  max "
                      f"{_fmt(ins['smoothed']['max_m'])} m  within 3 sd {_fmt(ins['smoothed']['within_3sd'], 3)}  "
                      f"VALID {ins['smoothed_valid']}", flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(report, indent=1))
    return 0
