"""``v2xpos replay --smooth``: the replay's figures and solution from the smoothed states.

``SmoothingHook`` is a ``ReplayHook`` beside ``ReplayMetrics``: while the filter runs with a
``smoother.StepRecorder`` it takes taps (the filter's state and the rows of what is scored or
written) and the forward values; after the backward pass (``finish``) it turns them into

* ``smoothed_outage_*``: the antenna error at the END of each outage (as ``outage_*``);
* ``*inside_outage*``: the antenna error at **every RTK-fixed epoch inside the outages**, forward
  (``inside_outage_*``) and smoothed (``smoothed_inside_outage_*``) -- at an outage's end the
  smoother already has the returning fix, inside it has to bridge the gap;
* ``..._within_3sd``: the share of those epochs whose north and east errors are both within 3 sd of
  the smoothed (or forward) antenna covariance ``H P H^T`` (``smoother.antenna_rows``);
* the smoothed solution rows (``--solution``, ``smoothed`` column 1; 0 where a row lies outside a
  smoothed interval and keeps the forward values).

Errors are NED at the reference, antenna position minus the RTK-fixed solution (``replay_metrics``).
"""
from __future__ import annotations

import math

import numpy as np

from v2xpos import geo
from v2xpos.types import Dataset, FixStatus

from .ekf import BA, BG
from .filter import InsFilter
from .replay_engine import ReplayHook
from .replay_metrics import ReplayMetrics, interp_lla, predicted_antenna, rms
from .smoother import StepRecorder, antenna_rows, corrected_reported, reported_rows
from .solution import DEG, EFFECT_COLUMNS, _effect_names, columns, row

TAP_ROWS = 12
"""Rows of every tap: the antenna at the epoch (3), then position, velocity, vehicle attitude (9)."""
KIND_END, KIND_INSIDE, KIND_SOLUTION = 0, 1, 2


def _horizontal(err_ned: np.ndarray) -> np.ndarray:
    return np.hypot(err_ned[:, 0], err_ned[:, 1]) if len(err_ned) else np.zeros(0)


def _within_3sd(err_ned: np.ndarray, cov: np.ndarray) -> float | None:
    """Share of rows whose north and east errors are both within 3 sd."""
    if not len(err_ned):
        return None
    sd_n, sd_e = np.sqrt(np.maximum(cov[:, 0, 0], 0.0)), np.sqrt(np.maximum(cov[:, 1, 1], 0.0))
    return float(np.mean((np.abs(err_ned[:, 0]) <= 3.0 * sd_n) & (np.abs(err_ned[:, 1]) <= 3.0 * sd_e)))


class SmoothingHook(ReplayHook):
    """Taps for the smoothed figures (and rows when ``solution`` is a ``SolutionWriter``; one per
    GNSS epoch after its update, or at the output times with ``at_output_times``)."""

    def __init__(self, recorder: StepRecorder, dataset: Dataset, metrics: ReplayMetrics, solution=None,
                 at_output_times: bool = False):
        self.rec, self.dataset, self.metrics = recorder, dataset, metrics
        self.solution, self.at_output_times = solution, at_output_times
        self.kind: list[int] = []
        self.tap_index: list[int] = []
        self.err_fwd: list[np.ndarray] = []
        self.cov_fwd: list[np.ndarray] = []
        self.rows: list[np.ndarray] = []      # numeric columns of the forward rows (``_row_columns``)
        self.fixes: list[str] = []
        self.effects: tuple = ()
        self._row_columns: list[str] = []

    def _tap(self, f: InsFilter, t_s: float, kind: int) -> np.ndarray:
        H = antenna_rows(f, t_s)
        k = self.rec.tap(f.t_stamp_s, np.vstack([H, reported_rows(f)]))
        self.kind.append(kind)
        self.tap_index.append(k)
        return H

    def _score(self, f: InsFilter, t_s: float, ref_lla: np.ndarray, kind: int) -> None:
        H = self._tap(f, t_s, kind)
        self.err_fwd.append(geo.lla_to_ned(predicted_antenna(f, t_s), ref_lla))
        self.cov_fwd.append(H @ f.P @ H.T)

    def on_outage_end(self, f: InsFilter, t_s: float, i: int) -> None:
        if f.initialized:
            ref = interp_lla(t_s, self.metrics.ref_t, self.metrics.ref_lla)
            if ref is not None:
                self._score(f, t_s, ref, KIND_END)

    def on_gnss_epoch(self, f: InsFilter, t_s: float, k: int, used: bool) -> None:
        gn = self.dataset.gnss
        if f.initialized and not used and int(gn.fix[k]) == FixStatus.FIXED:
            self._score(f, t_s, gn.lla[k], KIND_INSIDE)

    def _solution_row(self, f: InsFilter, used: bool) -> None:
        if self.solution is None or not f.initialized:
            return
        self._tap(f, f.t_s, KIND_SOLUTION)
        r = row(f, used)
        if not self._row_columns:
            self.effects = f.layout.effects
            self._row_columns = [c for c in columns(self.effects) if c != "fix"]
        self.rows.append(np.array([r[c] for c in self._row_columns], float))
        self.fixes.append(r["fix"])

    def after_gnss_epoch(self, f: InsFilter, t_s: float, k: int, used: bool) -> None:
        if not self.at_output_times:
            self._solution_row(f, used)

    def on_output(self, f: InsFilter, t_s: float, used: bool) -> None:
        self._solution_row(f, used)

    def finish(self, f: InsFilter) -> dict:
        """Backward pass; writes the smoothed rows to ``solution`` and returns the summary figures."""
        self.rec.finish(f)
        sm = self.rec.smooth()
        kind = np.asarray(self.kind, int)
        taps = np.asarray(self.tap_index, int)
        out: dict = {"smoothed": True}
        scored = np.flatnonzero(kind != KIND_SOLUTION)
        err_fwd = np.asarray(self.err_fwd).reshape(-1, 3)
        cov_fwd = np.asarray(self.cov_fwd).reshape(-1, 3, 3)
        k_sc = taps[scored]
        ok = sm.smoothed[k_sc]
        err_s = np.where(ok[:, None], err_fwd - sm.y[k_sc, 0:3], err_fwd)
        cov_s = np.where(ok[:, None, None], sm.cov[k_sc, 0:3, 0:3], cov_fwd)
        for name, kd in (("outage", KIND_END), ("inside_outage", KIND_INSIDE)):
            m = kind[scored] == kd
            hf, hs = _horizontal(err_fwd[m]), _horizontal(err_s[m])
            if kd == KIND_INSIDE:
                out["inside_outage_epochs"] = int(m.sum())
                out["inside_outage_h_rms_m"] = rms(hf)
                out["inside_outage_h_max_m"] = float(hf.max()) if len(hf) else None
                out["inside_outage_within_3sd"] = _within_3sd(err_fwd[m], cov_fwd[m])
            out[f"smoothed_{name}_h_rms_m"] = rms(hs)
            out[f"smoothed_{name}_h_max_m"] = float(hs.max()) if len(hs) else None
            out[f"smoothed_{name}_v_rms_m"] = rms(err_s[m][:, 2]) if m.any() else None
            out[f"smoothed_{name}_within_3sd"] = _within_3sd(err_s[m], cov_s[m])
            out[f"smoothed_{name}_not_smoothed"] = int((~ok[m]).sum())
        out["smoothed_inside_outage_h_m"] = _horizontal(err_s[kind[scored] == KIND_INSIDE]).tolist()
        out["smoothing"] = {"nodes": int(self.rec.nodes), "segments": len(self.rec.segments),
                            "taps": int(self.rec.taps), "stored_mib": self.rec.stored_bytes / 2 ** 20,
                            "precision": self.rec.codec.precision}
        if self.solution is not None:
            sol = np.flatnonzero(kind == KIND_SOLUTION)
            for values, fix, k in zip(self.rows, self.fixes, taps[sol]):
                r = dict(zip(self._row_columns, values.tolist()), fix=fix)
                r["gps_week"], r["gnss_used"] = int(r["gps_week"]), int(r["gnss_used"])
                if sm.smoothed[k]:
                    r = smoothed_row(r, self.effects, f.layout, sm.dx[k], sm.sd[k], sm.y[k, 3:12], sm.cov[k, 3:12, 3:12])
                r["smoothed"] = int(bool(sm.smoothed[k]))
                self.solution.write_row(r, self.effects)
            out["smoothed_solution_rows"] = int(sm.smoothed[taps[sol]].sum())
        return out


def smoothed_row(r: dict, effects: tuple, layout, dx: np.ndarray, sd: np.ndarray, y: np.ndarray,
                 cov: np.ndarray) -> dict:
    """A forward solution row (``solution.row``) corrected by the smoothed error: position,
    velocity and vehicle attitude by ``y`` (= J dx with J the reported rows, ``smoother.reported_rows``)
    and their sds from ``cov`` (= J P^s J^T); biases and effects by ``dx`` with the sds ``sd``
    (sqrt of diag P^s), attitude-error sds from the same (as ``solution.row``)."""
    r = dict(r)
    lla, v, rpy = corrected_reported(np.array([math.radians(r["lat_deg"]), math.radians(r["lon_deg"]), r["height_m"]]),
                                     np.array([r["vn_mps"], r["ve_mps"], r["vd_mps"]]),
                                     np.radians([r["roll_deg"], r["pitch_deg"], r["yaw_deg"]]), y)
    r["lat_deg"], r["lon_deg"], r["height_m"] = lla[0] * DEG, lla[1] * DEG, float(lla[2])
    r["vn_mps"], r["ve_mps"], r["vd_mps"] = (float(x) for x in v)
    r["roll_deg"], r["pitch_deg"], r["yaw_deg"] = (float(a) * DEG for a in rpy)
    s = np.sqrt(np.maximum(np.diagonal(cov), 0.0))
    for names, k0 in ((("sd_north_m", "sd_east_m", "sd_down_m"), 0), (("sd_vn_mps", "sd_ve_mps", "sd_vd_mps"), 3)):
        for c, k in zip(names, range(3)):
            r[c] = float(s[k0 + k])
    for c, k in zip(("sd_roll_deg", "sd_pitch_deg", "sd_yaw_deg"), range(3)):
        r[c] = float(sd[6 + k]) * DEG
    dph = DEG * 3600.0
    for a, k in zip("xyz", range(3)):
        r[f"gyro_bias_{a}_dph"] -= float(dx[BG + k]) * dph
        r[f"sd_gyro_bias_{a}_dph"] = float(sd[BG + k]) * dph
        r[f"accel_bias_{a}_mps2"] -= float(dx[BA + k])
        r[f"sd_accel_bias_{a}_mps2"] = float(sd[BA + k])
    for name in effects:
        stem, unit, scale, comps = EFFECT_COLUMNS[name]
        i = layout.at(name)
        for j, c in enumerate(_effect_names(stem, unit, comps)):
            r[c] -= float(dx[i + j]) * scale
            r[f"sd_{c}"] = float(sd[i + j]) * scale
    return r
