"""Figures of the first parameter: boxplots of window RMSE, histograms of window PCC,
and the pose-aided rate curves. matplotlib with the Agg backend, PNG files."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from .unit_comparison import AXES, UnitComparison, GradeConfig


def _plt():
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


def plot_first_parameter(fc: UnitComparison, reference: str, out_dir: str | Path,
                         cfg: GradeConfig | None = None, mounting: dict | None = None) -> list[Path]:
    """rmse_boxplot_{gyro,accel}.png and pcc_hist_{gyro,accel}.png of every unit against the
    reference (per axis); returns the written paths."""
    plt = _plt()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    cfg = cfg or GradeConfig()
    others = [u for u in fc.unit_ids if u != reference]
    pairs = {u: fc.pair_direct(reference, u, cfg, mounting) for u in others}
    written = []
    for sensor, scale, unit in (("gyro", np.degrees(1.0), "deg/s"), ("accel", 1.0, "m/s^2")):
        fig, axes = plt.subplots(1, 3, figsize=(12, 4), sharey=False)
        for k, ax in enumerate(axes):
            data = [getattr(pairs[u], sensor).rmse[:, k] * scale for u in others]
            ax.boxplot(data, whis=1.5)
            ax.set_xticks(range(1, len(others) + 1), others, rotation=30)
            ax.set_title(f"{sensor} {AXES[k]}")
            ax.set_ylabel(f"window RMSE [{unit}]")
            ax.grid(alpha=0.3)
        fig.suptitle(f"RMSE per {cfg.window_s:g} s window against {reference}")
        fig.tight_layout()
        p = out / f"rmse_boxplot_{sensor}.png"
        fig.savefig(p, dpi=110)
        plt.close(fig)
        written.append(p)
        fig, axes = plt.subplots(1, 3, figsize=(12, 4))
        for k, ax in enumerate(axes):
            lo = min([0.5] + [float(np.min(getattr(pairs[u], sensor).pcc[:, k])) for u in others
                              if len(getattr(pairs[u], sensor).pcc)])
            lo = max(-1.0, np.floor(lo * 10.0) / 10.0)
            for u in others:
                ax.hist(getattr(pairs[u], sensor).pcc[:, k], bins=40, range=(lo, 1.0), alpha=0.5, label=u)
            ax.set_title(f"{sensor} {AXES[k]}")
            ax.set_xlabel("window PCC")
            ax.grid(alpha=0.3)
        axes[0].legend(fontsize=8)
        fig.suptitle(f"PCC per {cfg.window_s:g} s window against {reference}")
        fig.tight_layout()
        p = out / f"pcc_hist_{sensor}.png"
        fig.savefig(p, dpi=110)
        plt.close(fig)
        written.append(p)
    return written


def plot_rate_check(results: dict, out_path: str | Path) -> Path:
    """Norm curves |w_pose| and |w_imu| per unit (results: unit id -> RateCheckResult)."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(9, 4))
    first = True
    for uid, r in results.items():
        t = r.t_s - r.t_s[0]
        if first:
            ax.plot(t, r.norm_pose_dps, "k-", lw=2, label="pose (lidar odometry)")
            first = False
        ax.plot(t, r.norm_imu_dps, lw=1, label=f"{uid} gyro ({'anomaly' if r.anomaly else 'ok'})")
    ax.set_xlabel("time [s]")
    ax.set_ylabel("|angular rate| [deg/s]")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    out = Path(out_path)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out
