"""``v2xpos replay``: run a recorded dataset through the GNSS/INS EKF with simulated GNSS outages.

Outage schedule (seconds from the first GNSS epoch): outage i covers
``[first + i every, first + i every + length)``; GNSS is not used inside. Only outages that end
before the last GNSS epoch and that the IMU covers without a gap (``datasets.checks.imu_coverage``)
count; the others are counted in ``outages_skipped_no_imu``.

Inputs are checked before the run (``load_for_command``: descriptor, files, and the plausibility
checks of ``v2xpos.datasets.checks``): an error stops the command with exit code 2 and a message
naming the file and the key; warnings are printed and carried in the summary (``input_checks``). Metrics (antenna position, horizontal/vertical):

* ``outage_*``: filter antenna position at the END of each outage minus the RTK-FIXED solution
  linearly interpolated to that time (the reference pose when the dataset has no fixed epochs);
* ``aided_h_rms_m``: the same error while GNSS is used, just before each update, at every
  RTK-FIXED epoch.

``v2xpos bench replay`` prints throughput (IMU samples/s) end to end and per stage.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from v2xpos import geo
from v2xpos.types import Dataset, FixStatus

from .filter import InsConfig, InsFilter

DEFAULT_DRIVE = Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "drive_0708" / "dataset.toml"


@dataclass
class OutageSchedule:
    """GNSS outages of ``length_s`` every ``every_s`` from ``first_s`` after the first GNSS epoch."""
    length_s: float = 15.0
    every_s: float = 45.0
    first_s: float = 40.0

    def intervals(self, t_first_s: float, t_last_s: float) -> list[tuple[float, float]]:
        """[start, end) GPS times [s] of the outages that end no later than t_last_s."""
        if self.length_s <= 0 or self.every_s <= 0:
            return []
        out, k = [], 0
        while True:
            a = t_first_s + self.first_s + k * self.every_s
            b = a + self.length_s
            if b > t_last_s:
                return out
            out.append((a, b))
            k += 1


@dataclass
class ReplayResult:
    """Everything a replay produced: the JSON summary and time series for plots/diagnosis."""
    summary: dict
    series: dict = field(default_factory=dict)
    filter: InsFilter | None = None


def config_for(dataset: Dataset, **overrides) -> InsConfig:
    """InsConfig from what the dataset declares (platform, mounting, lever arm) and its
    ``[calibration]`` table (``calibrated.ins_config``), plus overrides."""
    from .calibrated import dataset_ins_config
    kw = {}
    if dataset.wheel is not None and dataset.platform == "car":
        base = dataset_ins_config(dataset).effects
        kw["effects"] = tuple(base) + ("odometer_scale",)
    kw.update(overrides)
    return dataset_ins_config(dataset, **kw)


def _interp_lla(t_q: float, t: np.ndarray, lla: np.ndarray, max_gap_s: float = 1.0) -> np.ndarray | None:
    """Linear interpolation of a reference trajectory; None when t_q is not bracketed closely."""
    k = int(np.searchsorted(t, t_q))
    if k == 0 or k >= len(t):
        if k < len(t) and abs(t[k] - t_q) < 1e-6:
            return lla[k].copy()
        return None
    t0, t1 = t[k - 1], t[k]
    if t1 - t0 > max_gap_s:
        return None
    a = (t_q - t0) / (t1 - t0)
    return lla[k - 1] + a * (lla[k] - lla[k - 1])


def _ned_error(lla_est: np.ndarray, lla_ref: np.ndarray) -> np.ndarray:
    return geo.lla_to_ned(lla_est, lla_ref)


def replay(dataset: Dataset, schedule: OutageSchedule | None = None, cfg: InsConfig | None = None,
           progress: bool = True, keep_series: bool = True, solution=None,
           solution_hz: float | None = None) -> ReplayResult:
    """Run the filter over the whole dataset; see the module docstring for the metrics.

    ``solution``: a ``v2xpos.ins.solution.SolutionWriter`` given one row per output epoch once the
    filter is initialised: by default every GNSS epoch (after its update; in an outage without
    it), which leaves the filter exactly as without output; with ``solution_hz`` every
    1 / solution_hz s from the first GNSS epoch (after a GNSS update at the same instant) -- the IMU
    batches are then also split at those times, which moves the result by numerical noise
    (drive_0708 outage RMS 2.482 -> 2.480 m at 10 Hz)."""
    t_wall0 = time.perf_counter()
    t_cpu0 = time.process_time()
    schedule = schedule or OutageSchedule()
    cfg = cfg or config_for(dataset)
    f = InsFilter(cfg)
    imu, gn = dataset.imu, dataset.gnss
    t_imu = np.asarray(imu.t_s, float)
    acc = np.ascontiguousarray(imu.acc_mps2, dtype=float)
    gyr = np.ascontiguousarray(imu.gyro_rps, dtype=float)
    fixed = np.asarray(gn.fix) == int(FixStatus.FIXED)
    use_fixed_ref = fixed.sum() >= 2
    if use_fixed_ref:
        ref_t, ref_lla = np.asarray(gn.t_s)[fixed], np.asarray(gn.lla)[fixed]
    elif dataset.reference is not None:
        ref_t, ref_lla = np.asarray(dataset.reference.t_s), np.asarray(dataset.reference.lla)
    else:
        ref_t, ref_lla = np.zeros(0), np.zeros((0, 3))
    from v2xpos.datasets.checks import covered, imu_coverage
    outages = schedule.intervals(float(gn.t_s[0]), float(gn.t_s[-1])) if len(gn) else []
    coverage = imu_coverage(t_imu)
    n_scheduled = len(outages)
    outages = [o for o in outages if covered(o[0], o[1], coverage)]
    # only GnssData's own velocity is used (comma2k19's speed/bearing in the notes turned the heading
    # away by 25 deg on its highway segment: docs/ins.md); without it the alignment uses the course tracker
    vel, vel_sd = gn.vel_ned_mps, gn.vel_sd_ned_mps

    # events: (time, kind, index); kinds: 0 gnss, 1 outage end evaluation, 2 wheel, 3 solution output
    ev_t = [np.asarray(gn.t_s, float), np.array([b for _, b in outages], float)]
    ev_k = [np.zeros(len(gn), int), np.ones(len(outages), int)]
    ev_i = [np.arange(len(gn)), np.arange(len(outages))]
    if solution is not None and solution_hz and len(gn):
        t_out = np.arange(float(gn.t_s[0]), float(max(gn.t_s[-1], t_imu[-1])), 1.0 / solution_hz)
        ev_t.append(t_out)
        ev_k.append(np.full(len(t_out), 3))
        ev_i.append(np.arange(len(t_out)))
    if dataset.wheel is not None and cfg.platform == "car":
        ev_t.append(np.asarray(dataset.wheel.t_s, float))
        ev_k.append(np.full(len(dataset.wheel.t_s), 2))
        ev_i.append(np.arange(len(dataset.wheel.t_s)))
    ev_t, ev_k, ev_i = np.concatenate(ev_t), np.concatenate(ev_k), np.concatenate(ev_i)
    # at the same time: outage evaluation, then the GNSS epoch, then the solution output
    order = np.lexsort((np.where(ev_k == 3, 1, -ev_k), ev_t))
    out_starts = np.array([a for a, _ in outages]) if outages else np.zeros(0)
    out_ends = np.array([b for _, b in outages]) if outages else np.zeros(0)

    def in_outage(t: float) -> bool:
        k = int(np.searchsorted(out_starts, t, side="right")) - 1
        return k >= 0 and t < out_ends[k]

    S: dict[str, list] = {k: [] for k in ("t", "ant_lla", "err_ned", "aided", "bg", "ba", "dt", "lever",
                                           "mis", "fix", "ref_t", "ref_err_ned",
                                           "vel_err_ned", "pos_sd_m", "speed_mps", "yaw_rate_rps")}
    outage_err = []
    aided_err = []
    aided_steady = []     # the same, excluding the 5 s after each outage (re-convergence)
    ref_err = []
    i_imu = 0
    n_imu = len(t_imu)
    bar = None
    if progress:
        from tqdm import tqdm
        bar = tqdm(total=n_imu, unit="imu", desc=f"replay {dataset.name}", file=sys.stderr, mininterval=0.5)
    has_ref_pose = dataset.reference is not None
    ref_pose_t = np.asarray(dataset.reference.t_s) if has_ref_pose else None
    ref_pose_next = 0
    wheel_next_t = -np.inf
    wheel_period_s = 1.0 / cfg.constraint_rate_hz

    for e in order:
        t_ev, kind, idx = float(ev_t[e]), int(ev_k[e]), int(ev_i[e])
        j = int(np.searchsorted(t_imu, t_ev - f.fx.imu_time_offset_s - f.fx.gnss_latency_s * (kind == 0),
                                side="right"))
        if j > i_imu:
            f.process_imu_batch(t_imu[i_imu:j], acc[i_imu:j], gyr[i_imu:j])
            if bar is not None:
                bar.update(j - i_imu)
            i_imu = j
        if kind == 1:
            if f.initialized:
                ref = _interp_lla(t_ev, ref_t, ref_lla)
                if ref is not None:
                    ant = _predicted_antenna(f, t_ev)
                    outage_err.append(_ned_error(ant, ref))
            continue
        if kind == 3:
            if f.initialized:
                solution.write(f, not in_outage(t_ev))
            continue
        if kind == 2:   # used at the constraint rate: odometer errors are correlated at higher rates
            if t_ev >= wheel_next_t:
                f.update_wheel_speed(t_ev, float(dataset.wheel.speed_mps[idx]))
                wheel_next_t = t_ev + wheel_period_s
            continue
        fix = FixStatus(int(gn.fix[idx]))
        used = not in_outage(t_ev)
        if f.initialized:
            ant = _predicted_antenna(f, t_ev)
            err = _ned_error(ant, gn.lla[idx])
            if used and fix == FixStatus.FIXED:
                aided_err.append(err)
                k_out = int(np.searchsorted(out_ends, t_ev, side="right")) - 1
                if k_out < 0 or t_ev - out_ends[k_out] > 5.0:
                    aided_steady.append(err)
            if keep_series:
                S["t"].append(t_ev)
                S["ant_lla"].append(ant)
                S["err_ned"].append(err)
                S["aided"].append(used)
                S["fix"].append(int(fix))
                S["bg"].append(f.gyro_bias_rps)
                S["ba"].append(f.accel_bias_mps2)
                S["dt"].append(f.fx.imu_time_offset_s)
                S["lever"].append(f.fx.lever_arm_m.copy())
                S["mis"].append(f.fx.misalignment_rad.copy())
                S["vel_err_ned"].append(f.nav[3:6] - vel[idx] if vel is not None else np.full(3, np.nan))
                S["pos_sd_m"].append(np.sqrt(np.abs(np.diag(f.P)[0:3])))
                S["speed_mps"].append(float(np.linalg.norm(f.nav[3:6])))
                S["yaw_rate_rps"].append(float(f.mem[2]))
            if has_ref_pose:
                while ref_pose_next < len(ref_pose_t) and ref_pose_t[ref_pose_next] <= t_ev:
                    ref_pose_next += 1
                rk = ref_pose_next - 1
                if rk >= 0 and t_ev - ref_pose_t[rk] < 0.1:
                    r = _interp_lla(t_ev, ref_pose_t, np.asarray(dataset.reference.lla))
                    if r is not None:
                        e_ref = _ned_error(f.lla, r)
                        ref_err.append(e_ref)
                        S["ref_t"].append(t_ev)
                        S["ref_err_ned"].append(e_ref)
        if used:
            f.update_gnss(t_ev, gn.lla[idx], gn.sd_ned_m[idx], fix,
                          None if vel is None else vel[idx], None if vel_sd is None else vel_sd[idx])
        if solution is not None and not solution_hz and f.initialized:
            solution.write(f, used)
    if i_imu < n_imu:
        f.process_imu_batch(t_imu[i_imu:], acc[i_imu:], gyr[i_imu:])
        if bar is not None:
            bar.update(n_imu - i_imu)
    if bar is not None:
        bar.close()
    wall = time.perf_counter() - t_wall0
    cpu = time.process_time() - t_cpu0

    oe = np.array(outage_err).reshape(-1, 3)
    ae = np.array(aided_err).reshape(-1, 3)
    oh = np.hypot(oe[:, 0], oe[:, 1])
    summary = {
        "dataset": dataset.name,
        "imu_samples": int(n_imu),
        "gnss_epochs": int(len(gn)),
        "malformed_lines": int(dataset.malformed_lines),
        "outage_count": int(len(oe)),
        "outages_skipped_no_imu": int(n_scheduled - len(outages)),
        "outage_h_rms_m": _rms(oh),
        "outage_h_max_m": float(oh.max()) if len(oh) else None,
        "outage_v_rms_m": _rms(oe[:, 2]),
        "aided_h_rms_m": _rms(np.hypot(ae[:, 0], ae[:, 1])),
        "aided_h_rms_steady_m": _rms(np.hypot(*np.array(aided_steady).reshape(-1, 3)[:, :2].T)),
        "wall_s": wall,
        "imu_samples_per_s": n_imu / wall if wall > 0 else None,
        "cpu_s": cpu,
    }
    if has_ref_pose:
        re = np.array(ref_err).reshape(-1, 3)
        summary["reference_h_rms_m"] = _rms(np.hypot(re[:, 0], re[:, 1]))
        summary["reference_h_max_m"] = float(np.hypot(re[:, 0], re[:, 1]).max()) if len(re) else None
        summary["reference_v_rms_m"] = _rms(re[:, 2])
    if "input_check" in dataset.notes:
        summary["input_checks"] = dataset.notes["input_check"]
        summary["warnings"] = len(dataset.notes["input_check"].get("warnings", []))
    summary["outage_h_m"] = oh.tolist()
    summary["effects"] = f.effects_report()
    summary["static_calibration"] = [e.as_dict() for e in f.calibrator.estimates]
    summary["counts"] = dict(f.counts)
    series = {k: np.array(v) for k, v in S.items()}
    series["outages"] = outages
    series["outage_err_ned"] = oe
    series["gnss_lla"] = np.asarray(gn.lla)
    series["gnss_t"] = np.asarray(gn.t_s)
    series["residuals"] = f.residuals
    return ReplayResult(summary=summary, series=series, filter=f)


def _rms(x: np.ndarray) -> float | None:
    x = np.asarray(x, float)
    return float(np.sqrt(np.mean(x ** 2))) if len(x) else None


def _predicted_antenna(f: InsFilter, t_s: float) -> np.ndarray:
    """Filter antenna position extrapolated from its time label to GPS time t_s."""
    ant = f.antenna_lla()
    gap = t_s - f.t_s
    lat, h = ant[0], ant[2]
    r_m, r_n = geo.radii_m(lat)
    v = f.nav[3:6]
    return ant + gap * np.array([v[0] / (r_m + h), v[1] / ((r_n + h) * math.cos(lat)), -v[2]])


# ---------------------------------------------------------------------- plots
def write_plots(result: ReplayResult, out_dir: str | Path) -> list[Path]:
    """Trajectory with outages, error vs time, innovations, bias/effect estimates (PNG)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    S = result.series
    name = result.summary["dataset"]
    files = []
    if len(S["t"]) == 0:
        return files
    lla0 = S["gnss_lla"][0]
    g_ned = geo.lla_to_ned(S["gnss_lla"], lla0)
    f_ned = geo.lla_to_ned(S["ant_lla"], lla0)
    t0 = S["gnss_t"][0]
    t = S["t"] - t0

    fig, ax = plt.subplots(figsize=(8, 8))
    ax.plot(g_ned[:, 1], g_ned[:, 0], ".", ms=2, color="0.6", label="GNSS")
    ax.plot(f_ned[:, 1], f_ned[:, 0], "-", lw=0.8, color="C0", label="EKF antenna")
    for k, (a, b) in enumerate(S["outages"]):
        m = (S["t"] >= a) & (S["t"] <= b)
        ax.plot(f_ned[m, 1], f_ned[m, 0], "-", lw=2, color="C3", label="outage (coasting)" if k == 0 else None)
    ax.set_xlabel("east [m]")
    ax.set_ylabel("north [m]")
    ax.set_aspect("equal")
    ax.legend()
    ax.set_title(f"{name}: trajectory, outages in red")
    files.append(out / "trajectory.png")
    fig.savefig(files[-1], dpi=110)
    plt.close(fig)

    err = S["err_ned"]
    fig, ax = plt.subplots(2, 1, figsize=(10, 6), sharex=True)
    ax[0].plot(t, np.hypot(err[:, 0], err[:, 1]), lw=0.7, label="horizontal")
    ax[0].plot(t, np.abs(err[:, 2]), lw=0.7, label="|vertical|")
    for a, b in S["outages"]:
        ax[0].axvspan(a - t0, b - t0, color="C3", alpha=0.15)
    if len(S["ref_t"]):
        re_ = S["ref_err_ned"]
        ax[0].plot(S["ref_t"] - t0, np.hypot(re_[:, 0], re_[:, 1]), lw=0.9, color="k",
                   label="IMU point vs reference pose (horizontal)")
    ax[0].set_yscale("log")
    ax[0].set_ylabel("antenna error before update [m]")
    ax[0].legend()
    oe = S["outage_err_ned"]
    if len(oe):
        ends = np.array([b for _, b in S["outages"]])[:len(oe)] - t0
        ax[1].bar(ends, np.hypot(oe[:, 0], oe[:, 1]), width=6, color="C3")
    ax[1].set_ylabel("error at outage end [m]")
    ax[1].set_xlabel("time since first GNSS epoch [s]")
    rms = result.summary["outage_h_rms_m"]
    ax[0].set_title(f"{name}: outage h RMS " + ("n/a" if rms is None else f"{rms:.2f} m"))
    files.append(out / "error_vs_time.png")
    fig.savefig(files[-1], dpi=110)
    plt.close(fig)

    res = [r for r in S["residuals"] if r.kind == "gnss_pos" and len(r.innovation) == 3]
    if res:
        tt = np.array([r.t_s for r in res]) - t0   # same time axis as the other plots
        inn = np.array([r.innovation for r in res])
        nis = np.array([r.nis for r in res])
        acc = np.array([r.accepted for r in res])
        fig, ax = plt.subplots(2, 1, figsize=(10, 6), sharex=True)
        for k, lab in enumerate("NED"):
            ax[0].plot(tt, inn[:, k], ".", ms=2, label=lab)
        ax[0].set_ylabel("position innovation [m]")
        ax[0].set_ylim(-1, 1)
        ax[0].legend(markerscale=5)
        ax[1].semilogy(tt[acc], nis[acc], ".", ms=2, label="accepted")
        ax[1].semilogy(tt[~acc], nis[~acc], "x", ms=3, color="C3", label="rejected")
        ax[1].set_ylabel("NIS (chi-square, 3 dof)")
        ax[1].set_xlabel("time since first GNSS epoch [s]")
        ax[1].legend(markerscale=3)
        ax[0].set_title(f"{name}: GNSS position innovations (z - h(x), NED) and their NIS")
        files.append(out / "innovations.png")
        fig.savefig(files[-1], dpi=110)
        plt.close(fig)

    # one quantity (one unit) per panel, one labelled line per component
    panels = (("gyro bias [deg/h]", np.degrees(S["bg"]) * 3600, ("x", "y", "z")),
              ("accel bias [m/s^2]", S["ba"], ("x", "y", "z")),
              ("IMU time offset [ms]", S["dt"].reshape(-1, 1) * 1e3, ("IMU time offset",)),
              ("lever arm, body [cm]", S["lever"] * 100, ("x (forward)", "y (right)", "z (down)")),
              ("misalignment [deg]", np.degrees(S["mis"]), ("roll", "pitch", "yaw")))
    fig, ax = plt.subplots(len(panels), 1, figsize=(10, 12), sharex=True)
    for a, (ylabel, values, names) in zip(ax, panels):
        for k, lab in enumerate(names):
            a.plot(t, values[:, k], lw=0.8, label=lab)
        a.set_ylabel(ylabel)
        a.legend(fontsize=7, loc="upper right")
        a.grid(alpha=0.3)
    ax[-1].set_xlabel("time since first GNSS epoch [s]")
    ax[0].set_title(f"{name}: IMU bias and effect estimates (filter states)")
    fig.tight_layout()
    files.append(out / "bias_estimates.png")
    fig.savefig(files[-1], dpi=110)
    plt.close(fig)
    return files


# ---------------------------------------------------------------------- command
def add_schedule_arguments(parser: argparse.ArgumentParser) -> None:
    """The outage-schedule options shared by ``v2xpos replay`` and ``v2xpos calibrate``."""
    parser.add_argument("--outage-length", type=float, default=15.0, help="outage length [s] (default 15)")
    parser.add_argument("--outage-every", type=float, default=45.0, help="outage period [s] (default 45)")
    parser.add_argument("--outage-first", type=float, default=40.0,
                        help="start of the first outage after the first GNSS epoch [s] (default 40)")


def schedule_from_args(args: argparse.Namespace) -> OutageSchedule:
    """OutageSchedule from the options of ``add_schedule_arguments``."""
    return OutageSchedule(args.outage_length, args.outage_every, args.outage_first)


def add_input_arguments(parser: argparse.ArgumentParser) -> None:
    """Input-check options shared by ``v2xpos replay`` and ``v2xpos calibrate``."""
    from v2xpos.datasets.checks import MIN_OVERLAP_SHARE
    parser.add_argument("--check", action="store_true",
                        help="only check the inputs (descriptor, files, time overlap, mounting against "
                             "gravity, rates and gaps): exit 2 on an error, 0 otherwise")
    parser.add_argument("--min-overlap", type=float, default=MIN_OVERLAP_SHARE,
                        help="least share of the recording that IMU and GNSS must have in common "
                             f"(default {MIN_OVERLAP_SHARE})")


def load_for_command(path: str, command: str, min_overlap_share: float | None = None) -> Dataset | None:
    """Load a dataset for a command and check it (``v2xpos.datasets.checks``). On an error print
    one line per problem (naming the file and the key) and return None; print the warnings, keep
    the check in ``notes["input_check"]`` for the report, and drop GNSS epochs the IMU does not
    cover (``restrict_to_imu_coverage``)."""
    from v2xpos.datasets import load_dataset
    from v2xpos.datasets.checks import MIN_OVERLAP_SHARE, check_dataset, restrict_to_imu_coverage
    import logging
    loader_log = logging.getLogger("v2xpos.datasets.loader")
    level = loader_log.level
    loader_log.setLevel(logging.ERROR)   # the checks below restate its warnings, in the report too
    try:
        ds = load_dataset(path)
    except (OSError, ValueError) as e:
        msg = " ".join(str(e).split())
        print(f"v2xpos {command}: cannot load {msg if str(path) in msg else f'{path}: {msg}'}",
              file=sys.stderr)
        return None
    finally:
        loader_log.setLevel(level)
    chk = check_dataset(ds, MIN_OVERLAP_SHARE if min_overlap_share is None else min_overlap_share)
    for f in chk.errors:
        print(f"v2xpos {command}: {f.message}", file=sys.stderr)
    if chk.errors:
        return None
    ds, dropped = restrict_to_imu_coverage(ds)
    if dropped:
        chk.add("warning", "overlap", f"{chk.source}: {dropped} GNSS epoch(s) outside the IMU's span not used")
    for f in chk.warnings:
        print(f"v2xpos {command}: warning: {f.message}", file=sys.stderr)
    ds.notes["input_check"] = chk.as_dict()
    return ds


def note_warning(summary: dict, command: str, message: str) -> None:
    """Print a warning found while running and add it to the summary's ``input_checks``."""
    print(f"v2xpos {command}: warning: {message}", file=sys.stderr)
    summary.setdefault("input_checks", {}).setdefault("warnings", []).append(message)
    summary["warnings"] = len(summary["input_checks"]["warnings"])


def check_only(ds: Dataset, command: str, json_path: str | None) -> int:
    """``--check``: the inputs passed (errors were already reported); print the summary."""
    chk = ds.notes.get("input_check", {})
    rates = chk.get("rates", {})
    ov = chk.get("overlap") or {}
    print(f"v2xpos {command}: inputs OK: {ds.name}, {len(ds.imu)} IMU samples "
          f"({rates.get('imu_rate_hz') or float('nan'):.1f} Hz), {len(ds.gnss)} GNSS epochs "
          f"({rates.get('gnss_rate_hz') or float('nan'):.1f} Hz), IMU/GNSS overlap "
          f"{100 * ov.get('share', float('nan')):.0f} %, {len(chk.get('warnings', []))} warning(s)")
    if json_path:
        Path(json_path).parent.mkdir(parents=True, exist_ok=True)
        Path(json_path).write_text(json.dumps({"dataset": ds.name, "input_checks": chk}, indent=2))
    return 0


def command_provenance(command: str, args: argparse.Namespace) -> dict:
    """``v2xpos.provenance`` object of a dataset command: the dataset descriptor's hash (its
    ``dataset.toml``; a directory without one: path only) and the command's options."""
    from v2xpos.provenance import provenance
    ds = Path(args.dataset)
    descriptor = ds / "dataset.toml" if ds.is_dir() and (ds / "dataset.toml").is_file() else ds
    options = {k: v for k, v in sorted(vars(args).items()) if k not in ("dataset", "func") and not callable(v)}
    return provenance(command, {"dataset": descriptor, "options": options})


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``v2xpos replay``."""
    parser.add_argument("dataset", help="dataset.toml (or a dataset directory, e.g. a comma2k19 segment)")
    add_schedule_arguments(parser)
    add_input_arguments(parser)
    parser.add_argument("--json", help="write the summary JSON here")
    parser.add_argument("--plots", help="write PNG plots into this directory")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.add_argument("--solution", metavar="FILE",
                        help="write the per-epoch solution (time, position, velocity, attitude, sigmas, fix, "
                             "effect states) to FILE: .csv or .mcap")
    parser.add_argument("--solution-hz", type=float, default=None,
                        help="solution output rate [Hz] (default: every GNSS epoch, the filter's own epochs)")


def run(args: argparse.Namespace) -> int:
    """``v2xpos replay``: print the summary, optionally write the JSON and plots; 2 if the inputs
    cannot be used (the message names the file and the key)."""
    ds = load_for_command(args.dataset, "replay", args.min_overlap)
    if ds is None:
        return 2
    if args.check:
        return check_only(ds, "replay", args.json)
    sched = schedule_from_args(args)
    writer = None
    if args.solution:
        from .solution import SolutionWriter
        if args.solution_hz is not None and not args.solution_hz > 0:
            print("v2xpos replay: --solution-hz must be > 0", file=sys.stderr)
            return 2
        try:
            writer = SolutionWriter(args.solution)
        except (OSError, ValueError) as exc:
            print(f"v2xpos replay: {exc}", file=sys.stderr)
            return 2
    try:
        res = replay(ds, sched, progress=not args.no_progress, solution=writer, solution_hz=args.solution_hz)
    finally:
        if writer is not None:
            writer.close()
    if writer is not None:
        print(f"{'solution':>20}: {writer.rows} epochs -> {args.solution}")
    if res.summary["outage_count"] == 0:
        note_warning(res.summary, "replay",
                     f"{ds.source or ds.name}: no outage was scored ({res.summary['outages_skipped_no_imu']} "
                     "scheduled outage(s) not covered by the IMU); the recording may be shorter than "
                     "--outage-first + --outage-length")
    keys = ("dataset", "imu_samples", "gnss_epochs", "malformed_lines", "warnings", "outage_count",
            "outages_skipped_no_imu", "outage_h_rms_m",
            "outage_h_max_m", "outage_v_rms_m", "aided_h_rms_m", "aided_h_rms_steady_m", "wall_s",
            "imu_samples_per_s",
            "reference_h_rms_m")
    for k in keys:
        if k in res.summary:
            v = res.summary[k]
            print(f"{k:>20}: {v:.4g}" if isinstance(v, float) else
                  f"{k:>20}: {'n/a' if v is None else v}")
    eff = res.summary["effects"]
    print(f"{'effects':>20}: time offset {eff['imu_time_offset_s'] * 1e3:.1f} ms, lever arm "
          f"{np.round(eff['lever_arm_m'], 3).tolist()} m, misalignment "
          f"{np.round(np.degrees(eff['misalignment_rad']), 2).tolist()} deg")
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps({**res.summary, "provenance": command_provenance("replay", args)},
                                              indent=2))
    if args.plots:
        for p in write_plots(res, args.plots):
            print(f"{'plot':>20}: {p}")
    return 0


def add_bench_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``v2xpos bench replay``."""
    parser.add_argument("dataset", nargs="?", default=str(DEFAULT_DRIVE), help="dataset.toml (default drive_0708)")
    parser.add_argument("--repeat", type=int, default=2, help="replays to time (best is reported)")


def run_bench(args: argparse.Namespace) -> int:
    """``v2xpos bench replay``: throughput per stage and end to end [IMU samples/s]."""
    from .ekf import propagate_covariance
    from .mechanization import MEM_SIZE, strapdown_batch
    from v2xpos.datasets import load_dataset
    t0 = time.perf_counter()
    ds = load_dataset(args.dataset)
    t_load = time.perf_counter() - t0
    n = len(ds.imu)
    print(f"dataset {ds.name}: {n} IMU samples, {len(ds.gnss)} GNSS epochs, load {t_load:.2f} s")
    cfg = config_for(ds)
    f = InsFilter(cfg)
    f_b = np.ascontiguousarray(ds.imu.acc_mps2 @ cfg.imu_to_body.T)
    w_b = np.ascontiguousarray(ds.imu.gyro_rps @ cfg.imu_to_body.T)
    t = np.ascontiguousarray(ds.imu.t_s, dtype=float)
    nav = np.array([ds.gnss.lla[0][0], ds.gnss.lla[0][1], ds.gnss.lla[0][2], 0, 0, 0], float)
    A = np.zeros((f.layout.n, f.layout.n))
    for _ in range(2):   # first call compiles (or loads the cache)
        C = np.eye(3)
        mem = np.zeros(MEM_SIZE)
        t1 = time.perf_counter()
        strapdown_batch(t, f_b, w_b, 0, n, t[0], nav.copy(), C, np.zeros(12), mem, A, f.kidx, 1e-3, 1e-3)
        t_mech = time.perf_counter() - t1
    print(f"  strapdown + F accumulation (jitted): {n / t_mech:,.0f} samples/s")
    P = np.eye(f.layout.n)
    reps = 2000
    t1 = time.perf_counter()
    for _ in range(reps):
        P = propagate_covariance(P * 0 + np.eye(f.layout.n), A * 0, f.q_c, 0.1)
    t_cov = (time.perf_counter() - t1) / reps
    print(f"  covariance propagation ({f.layout.n} states): {t_cov * 1e6:.1f} us per call, "
          f"every {cfg.cov_every} samples -> {cfg.cov_every / t_cov:,.0f} samples/s")
    best = None
    for _ in range(max(1, args.repeat)):
        r = replay(ds, OutageSchedule(), cfg=config_for(ds), progress=False, keep_series=False)
        if best is None or r.summary["wall_s"] < best.summary["wall_s"]:
            best = r
    s = best.summary
    print(f"  end to end replay (filter + updates, no loading): {s['imu_samples_per_s']:,.0f} IMU samples/s "
          f"wall ({s['wall_s']:.2f} s), {n / s['cpu_s']:,.0f} IMU samples per CPU second of one core "
          f"({s['cpu_s']:.2f} s); target >= 25,000")
    print(f"  end to end including loading: {n / (s['wall_s'] + t_load):,.0f} IMU samples/s")
    st = best.filter.stage_s
    other = s["wall_s"] - sum(st.values())
    for name, sec in list(st.items()) + [("python glue (events, stop detection, H/R building)", other)]:
        print(f"    stage {name:<52} {sec:6.3f} s  ({100 * sec / s['wall_s']:4.1f} %)  -> {n / max(sec, 1e-9):>12,.0f} samples/s")
    print(f"  outage_h_rms_m {s['outage_h_rms_m']:.3f}")
    return 0
