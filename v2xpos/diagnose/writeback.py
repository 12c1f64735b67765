"""Calibration results back into the vehicle: a ``[calibration]`` table and a dataset descriptor.

``calibration_table(fit, ...)`` turns the fit into ``v2xpos.datasets.calibration.CalibrationTable``
(the names, signs and units of ``calibrate --json``, angles in degrees); ``write_dataset`` writes a
descriptor with the input's declared tables (paths rewritten relative to the new file) and that
table, which ``v2xpos replay``, ``calibrate`` and the services' sources apply through
``v2xpos.ins.calibrated.ins_config``.

What is written, per component:
* significant effect: its value and sd (the values the "after" figures use);
* determined but not significant: value 0 and its sd (the drive shows it is small);
* not determined (the drive could not tell, e.g. a vertical lever arm on a flat road): value 0
  and the sd the declaration already had (for the lever arm the descriptor's ``lever_arm_sd_m``),
  otherwise the fit's prior sd -- the calibration adds no information there.
"""
from __future__ import annotations

import datetime as _dt
import os
import subprocess
from pathlib import Path
from typing import Any

import numpy as np

from v2xpos.datasets.calibration import CalibrationEntry, CalibrationTable

from .inject import (P_ACCEL_SCALE, P_CLOCK_DRIFT, P_GNSS_LATENCY, P_GYRO_SCALE, P_LEVER_ARM, P_MISALIGN,
                     P_TIME_OFFSET)

EFFECT_SLICES: dict[str, tuple[Any, float]] = {
    "imu_time_offset_s": (P_TIME_OFFSET, 1.0),
    "imu_clock_drift_ppm": (P_CLOCK_DRIFT, 1.0),
    "gnss_latency_s": (P_GNSS_LATENCY, 1.0),
    "imu_misalignment_deg": (P_MISALIGN, 180.0 / np.pi),
    "gnss_lever_arm_m": (P_LEVER_ARM, 1.0),
    "gyro_scale": (P_GYRO_SCALE, 1.0),
    "accel_scale": (P_ACCEL_SCALE, 1.0),
}
"""JSON / [calibration] effect name -> (parameter index or slice, factor from parameter units)."""

PATH_KEYS = (("", "path"), ("imu", "file"), ("imu", "timetag"), ("gnss", "file"), ("gnss", "timetag"),
             ("gnss", "raw"), ("gnss", "raw_timetag"))
"""Descriptor fields that name files relative to the descriptor (``datasets.loader``)."""


def software_version() -> str:
    """``v2xpos <version>`` plus the git commit of the checkout when there is one."""
    try:
        from importlib.metadata import version
        v = version("v2xpos")
    except Exception:  # noqa: BLE001 - not installed as a distribution
        v = "unknown"
    try:
        here = Path(__file__).resolve().parent
        sha = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=here, capture_output=True, text=True,
                             timeout=5).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        sha = ""
    return f"v2xpos {v}" + (f" (git {sha})" if sha else "")


def calibration_table(theta: np.ndarray, sd: np.ndarray, significant: np.ndarray, determined: np.ndarray,
                      prior_sd: np.ndarray, declared_lever_sd_m: float, source: str,
                      date: str | None = None, software: str | None = None,
                      imu_noise: tuple[float, float, int] | None = None,
                      imu_allan: tuple[float, float, float, float] | None = None) -> CalibrationTable:
    """The ``[calibration]`` table of a fit (parameter vectors in the ``inject.P_*`` layout).
    ``imu_noise``: (gyro [rad/s/sqrt(Hz)], accelerometer [m/s^2/sqrt(Hz)], samples) measured from
    the recording (``tuning.imu_noise_density``), written as the vehicle's IMU noise with the sd of
    a variance estimate from that many samples (relative sd of the density 1/sqrt(2 n)).
    ``imu_allan``: (gyro, accelerometer density, their relative sds) that cover the Allan deviation
    measured at the recording's stops (``tuning.AllanAtStops.covering``), written as
    ``imu_gyro_allan_rps_rthz`` / ``imu_accel_allan_mps2_rthz``; NaN entries are left out."""
    theta, sd, prior_sd = (np.asarray(x, float) for x in (theta, sd, prior_sd))
    sig, det = np.asarray(significant, bool), np.asarray(determined, bool)
    value = np.where(sig, theta, 0.0)
    undetermined_sd = prior_sd.copy()
    undetermined_sd[P_LEVER_ARM] = min(float(declared_lever_sd_m), float(np.min(prior_sd[P_LEVER_ARM])))
    out_sd = np.where(det, sd, undetermined_sd)
    table = CalibrationTable(source=source, date=date or _dt.date.today().isoformat(),
                             software=software if software is not None else software_version())
    for name, (sl, k) in EFFECT_SLICES.items():
        if isinstance(sl, slice):
            table.effects[name] = CalibrationEntry(tuple(float(x) * k for x in value[sl]),
                                                   tuple(float(x) * k for x in out_sd[sl]))
        else:
            table.effects[name] = CalibrationEntry(float(value[sl]) * k, float(out_sd[sl]) * k)
    if imu_noise is not None:
        g, a, n = imu_noise
        rel = 1.0 / np.sqrt(2.0 * max(int(n), 1))
        if np.isfinite(g) and g > 0:
            table.effects["imu_gyro_noise_rps_rthz"] = CalibrationEntry(float(g), float(g * rel))
        if np.isfinite(a) and a > 0:
            table.effects["imu_accel_noise_mps2_rthz"] = CalibrationEntry(float(a), float(a * rel))
    if imu_allan is not None:
        g, a, rg, ra = imu_allan
        for key, v, r in (("imu_gyro_allan_rps_rthz", g, rg), ("imu_accel_allan_mps2_rthz", a, ra)):
            if np.isfinite(v) and v > 0:
                table.effects[key] = CalibrationEntry(float(v), float(v * r) if np.isfinite(r) else float(v))
    return table


def theta_from_table(table: CalibrationTable) -> tuple[np.ndarray, np.ndarray]:
    """(values, sds) in the ``inject.P_*`` parameter layout (radians) from a table; absent effects 0."""
    from .inject import N_PARAMS
    th, sd = np.zeros(N_PARAMS), np.zeros(N_PARAMS)
    for name, (sl, k) in EFFECT_SLICES.items():
        if name in table.effects:
            e = table.effects[name]
            th[sl] = np.asarray(e.value, float) / k
            sd[sl] = np.asarray(e.sd, float) / k
    return th, sd


def _rebased(value: str, src_dir: Path, out_dir: Path) -> str:
    p = Path(value)
    p = p if p.is_absolute() else (src_dir / p)
    return os.path.relpath(p.resolve(), out_dir.resolve())


def write_dataset(src_toml: str | Path, out_toml: str | Path, table: CalibrationTable,
                  verify: bool = True) -> Path:
    """Write ``out_toml``: the declared tables of ``src_toml`` (its own ``[calibration]`` and
    ``[verification]`` replaced), every file path rewritten so that it resolves from
    ``out_toml``'s folder, and ``table``; with ``verify`` also the ``[verification]`` record of the
    calibrated set-up (``verification_of``)."""
    import tomli_w
    from v2xpos.datasets.loader import read_descriptor
    src, out = Path(src_toml), Path(out_toml)
    desc = read_descriptor(src)
    desc.pop("calibration", None)
    desc.pop("verification", None)
    out.parent.mkdir(parents=True, exist_ok=True)
    for tab, key in PATH_KEYS:
        t = desc if not tab else desc.get(tab)
        if isinstance(t, dict) and isinstance(t.get(key), str):
            t[key] = _rebased(t[key], src.parent, out.parent)
    header = (f"# written by v2xpos calibrate from {src} on {table.date}: the declared tables of that file\n"
              f"# (file paths relative to this one) and the effects it estimated, as corrections to them.\n\n")
    out.write_text(header + tomli_w.dumps(desc) + "\n" + table.to_toml())
    if verify:
        record = verification_of(out, drive=str(src))
        out.write_text(out.read_text() + "\n" + record.to_toml())
    return out


def verification_of(dataset_toml: str | Path, drive: str | None = None):
    """The ``[verification]`` record (``v2xpos.datasets.verification``) of a recording's set-up as
    its descriptor states it (with its ``[calibration]``): the recording through the services'
    filter (``dataset_ins_config(integrity=True)``), and what that filter vouches for at its end."""
    from v2xpos.datasets.loader import load_dataset
    from v2xpos.datasets.verification import record_from_filter
    from v2xpos.ins import InsFilter
    from v2xpos.ins.calibrated import dataset_ins_config
    from v2xpos.ins.replay_engine import run_replay
    ds = load_dataset(dataset_toml)
    ds.verification = None
    flt = InsFilter(dataset_ins_config(ds, integrity=True))
    run_replay(flt, ds, [], wheel=True)
    return record_from_filter(flt, drive or str(dataset_toml), software_version())
