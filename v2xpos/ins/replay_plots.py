"""Figures of a ``v2xpos replay`` run (``--plots``): trajectory with the outages, antenna error
against time, GNSS innovations and their NIS, bias and effect estimates (PNG)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from v2xpos import geo

from .replay import ReplayResult


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

