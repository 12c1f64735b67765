"""The reference: every target's track in the master's body frame from a ``results.csv`` (any
master's, ``v2xpos convoy``'s, or a smoothed one) or a session MCAP, and the point the sensor
reports of it, in the sensor frame, at any time.

Only ``VALID`` rows are the reference; the others are counted per status (reference gaps).
Columns are read by name: extra columns are ignored, and a trailing ``smoothed`` column with 1s
marks a post-processed reference (used as it is; ``reference_smoothed`` in metrics.json).

Interpolation (``ReferenceTrack.at``): cubic Hermite between the two VALID rows around the time,
with the rows' relative velocities as the end slopes (de Boor 1978, "A Practical Guide to Splines",
ch. IV): its error is O(h^4) in the position, against a h^2 / 8 of the relative acceleration for
linear interpolation (~4 mm at 3 m/s^2 between 10 Hz rows). Two rows further apart than
``MAX_GAP_S`` are not bridged: the reference is absent there. Relative attitude is interpolated
linearly (yaw unwrapped).

The reported point (``reported_point``): P = p + C_ms rp, with p the target's IMU point and C_ms
its attitude relative to the master (``rel_roll/pitch/yaw``); rp the declared
``reference_point_m`` or, for ``reference = "nearest"``, the point of the target's outline nearest
to the sensor origin at that time. Its velocity in the master's body frame is v + w_rel x (C_ms rp)
with w_rel = d(rel_yaw)/dt about z (flat-road relative rotation; roll and pitch rates of a few
deg/s move a 1 m offset by cm/s). In the sensor frame (x boresight, y right, z down):
q = Rz(mount_yaw)^T (P - mount_m), dq/dt = Rz(mount_yaw)^T dP/dt.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from v2xpos.rotation import dcm_from_euler_batch

from .config import SensorConfig, TargetDecl
from .objects import read_csv_table

MAX_GAP_S = 0.25
"""Longest time between two VALID rows the interpolation bridges: 2.5 rows of a 10 Hz reference,
25 of a 100 Hz one; beyond it the CTRA-like motion between rows is not known to cm."""

REQUIRED = ("t_gps_s", "target", "status", "x_m", "y_m", "z_m")


class ReferenceFileError(ValueError):
    """A reference file that cannot be used (names the file)."""


@dataclass
class ReferenceTrack:
    """One target's VALID rows: t_s (N,), pos_m/vel_mps/rpy_rad/sd_m (N, 3), outline (K, 3) or None."""
    target: str
    t_s: np.ndarray
    pos_m: np.ndarray
    vel_mps: np.ndarray
    rpy_rad: np.ndarray
    sd_m: np.ndarray
    rows_total: int = 0
    status_counts: dict = field(default_factory=dict)
    outline_m: np.ndarray | None = None
    yaw_rate_rps: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.rpy_rad = self.rpy_rad.copy()
        if len(self.t_s):
            self.rpy_rad[:, 2] = np.unwrap(self.rpy_rad[:, 2])
        if not np.all(np.isfinite(self.vel_mps)):
            self.vel_mps = _gradient(self.pos_m, self.t_s)
        self.yaw_rate_rps = _gradient(self.rpy_rad[:, 2:3], self.t_s)[:, 0] if len(self.t_s) else np.zeros(0)

    def bracket(self, tq: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(ok, i, u): the row i before tq, the fraction u in [0, 1] to row i + 1; ok where both
        rows exist and are at most MAX_GAP_S apart."""
        n = len(self.t_s)
        if n < 2:
            return np.zeros(len(tq), bool), np.zeros(len(tq), int), np.zeros(len(tq))
        i = np.clip(np.searchsorted(self.t_s, tq, side="right") - 1, 0, n - 2)
        h = self.t_s[i + 1] - self.t_s[i]
        u = (tq - self.t_s[i]) / h
        ok = (u >= 0.0) & (u <= 1.0) & (h <= MAX_GAP_S)
        return ok, i, np.clip(u, 0.0, 1.0)

    def at(self, tq: np.ndarray) -> dict:
        """Interpolated pos_m, vel_mps, rpy_rad, yaw_rate_rps, sd_m at tq and ``ok``."""
        tq = np.asarray(tq, float)
        ok, i, u = self.bracket(tq)
        if len(self.t_s) < 2:
            nan3 = np.full((len(tq), 3), np.nan)
            return {"ok": ok, "pos_m": nan3, "vel_mps": nan3, "rpy_rad": nan3, "yaw_rate_rps": nan3[:, 0],
                    "sd_m": nan3}
        h = (self.t_s[i + 1] - self.t_s[i])[:, None]
        uu = u[:, None]
        p0, p1 = self.pos_m[i], self.pos_m[i + 1]
        m0, m1 = self.vel_mps[i] * h, self.vel_mps[i + 1] * h
        u2, u3 = uu * uu, uu * uu * uu
        pos = (2 * u3 - 3 * u2 + 1) * p0 + (u3 - 2 * u2 + uu) * m0 + (-2 * u3 + 3 * u2) * p1 + (u3 - u2) * m1
        vel = ((6 * u2 - 6 * uu) * p0 + (3 * u2 - 4 * uu + 1) * m0 + (-6 * u2 + 6 * uu) * p1
               + (3 * u2 - 2 * uu) * m1) / h
        lin = lambda a: a[i] + uu * (a[i + 1] - a[i])  # noqa: E731
        rate = self.yaw_rate_rps[i] + u * (self.yaw_rate_rps[i + 1] - self.yaw_rate_rps[i])
        return {"ok": ok, "pos_m": pos, "vel_mps": vel, "rpy_rad": lin(self.rpy_rad), "yaw_rate_rps": rate,
                "sd_m": lin(self.sd_m)}


@dataclass
class Reference:
    path: Path
    kind: str
    tracks: dict[str, ReferenceTrack]
    smoothed: bool = False
    rows: int = 0

    def span(self) -> tuple[float, float]:
        ts = [tr.t_s for tr in self.tracks.values() if len(tr.t_s)]
        if not ts:
            return math.nan, math.nan
        return float(min(t[0] for t in ts)), float(max(t[-1] for t in ts))


def _gradient(y: np.ndarray, t: np.ndarray) -> np.ndarray:
    if len(t) < 2:
        return np.zeros_like(y)
    return np.gradient(y, t, axis=0)


def _track(target: str, t, pos, vel, rpy, sd, statuses: np.ndarray, outline=None) -> ReferenceTrack:
    valid = (statuses == "VALID") & np.isfinite(t) & np.all(np.isfinite(pos), axis=1)
    order = np.argsort(t[valid], kind="stable")
    sel = lambda a: np.asarray(a, float)[valid][order]  # noqa: E731
    t_v = sel(t)
    keep = np.concatenate([[True], np.diff(t_v) > 0]) if len(t_v) else np.zeros(0, bool)  # no repeated stamps
    names, counts = np.unique(statuses[statuses != "VALID"], return_counts=True)
    rpy_v = sel(rpy)
    rpy_v[~np.isfinite(rpy_v)] = 0.0
    sd_v = sel(sd)
    return ReferenceTrack(target, t_v[keep], sel(pos)[keep], sel(vel)[keep], rpy_v[keep], sd_v[keep],
                          rows_total=int(len(t)), status_counts={str(k): int(c) for k, c in zip(names, counts)},
                          outline_m=outline)


def read_results_csv_reference(path: Path) -> Reference:
    """results.csv: columns by name (module docstring)."""
    header, rows = read_csv_table(path, REQUIRED, ReferenceFileError)
    col = {name: j for j, name in enumerate(header)}
    width = len(header)
    j_target, j_status = col["target"], col["status"]
    rows = [r for r in rows if len(r) > max(j_target, j_status)]
    targets = np.array([r[j_target].strip() for r in rows], dtype=str)
    status = np.array([r[j_status].strip() for r in rows], dtype=str)
    valid_idx = np.flatnonzero(status == "VALID")
    valid_rows = [rows[i] if len(rows[i]) == width else (rows[i] + [""] * width)[:width] for i in valid_idx]

    def num(name: str) -> np.ndarray:
        """The VALID rows' values of a column (NaN where empty or absent)."""
        if name not in col:
            return np.full(len(valid_rows), np.nan)
        j = col[name]
        try:
            return np.array([float(r[j]) if r[j].strip() else math.nan for r in valid_rows], dtype=float)
        except ValueError:
            raise ReferenceFileError(f"{path}: column {name!r} holds text in a VALID row") from None

    t = num("t_gps_s")
    pos = np.stack([num("x_m"), num("y_m"), num("z_m")], axis=1)
    vel = np.stack([num("vx_mps"), num("vy_mps"), num("vz_mps")], axis=1)
    rpy = np.radians(np.stack([num("rel_roll_deg"), num("rel_pitch_deg"), num("rel_yaw_deg")], axis=1))
    sd = np.stack([num("sd_x_m"), num("sd_y_m"), num("sd_z_m")], axis=1)
    smoothed_col = num("smoothed") if "smoothed" in col else None
    tracks = {}
    for tid in sorted(set(targets.tolist())):
        valid_of = targets[valid_idx] == tid
        others = status[(targets == tid) & (status != "VALID")]
        tr = _track(tid, t[valid_of], pos[valid_of], vel[valid_of], rpy[valid_of], sd[valid_of],
                    np.full(int(valid_of.sum()), "VALID"))
        names, counts = np.unique(others, return_counts=True)
        tr.rows_total = int(valid_of.sum()) + len(others)
        tr.status_counts = {str(k): int(c) for k, c in zip(names, counts)}
        tracks[tid] = tr
    smoothed = bool(smoothed_col is not None and np.any(smoothed_col == 1))
    return Reference(path, "results.csv", tracks, smoothed=smoothed, rows=len(rows))


def read_mcap_reference(path: Path) -> Reference:
    """A session MCAP: ``/v2xpos/out/relative`` documents, outlines from ``/v2xpos/rx``."""
    from v2xpos.output.recorder import read_recording
    from v2xpos.output.recording_schema import TOPIC_RELATIVE, TOPIC_RX
    per: dict[str, list] = {}
    outlines: dict[str, np.ndarray] = {}
    errors: list[str] = []
    for m in read_recording(path, topics=(TOPIC_RELATIVE, TOPIC_RX), errors=errors):
        d = m.doc or {}
        if m.topic == TOPIC_RX:
            msg = d.get("message") or {}
            g = msg.get("geometry") or {}
            if msg.get("vehicle_id") and g.get("kind") in ("polygon", "points") and len(g.get("points_body_m", [])) >= 3:
                outlines[str(msg["vehicle_id"])] = np.asarray(g["points_body_m"], float)
            continue
        if d.get("error") or not d.get("target_id"):
            continue                                  # an output the recorder could not decode
        per.setdefault(str(d["target_id"]), []).append(d)
    if not per:
        raise ReferenceFileError(f"{path}: no /v2xpos/out/relative message (a master's session MCAP?)"
                              + (f"; {errors[0]}" if errors else ""))
    nan3 = [math.nan] * 3
    tracks = {}
    rows = 0
    for tid, docs in sorted(per.items()):
        rows += len(docs)
        t = np.array([float(d.get("t_gps_s", math.nan)) for d in docs])
        status = np.array([str(d.get("status", "unknown")).upper() for d in docs])
        v3 = lambda k: np.array([[math.nan if x is None else float(x) for x in (d.get(k) or nan3)] for d in docs])  # noqa: E731
        tracks[tid] = _track(tid, t, v3("rel_pos_body_m"), v3("rel_vel_body_mps"),
                             np.radians(v3("rel_roll_pitch_yaw_deg")), v3("rel_pos_sd_m"), status, outlines.get(tid))
    return Reference(path, "mcap", tracks, rows=rows)


def read_reference(path: str | Path) -> Reference:
    path = Path(path)
    if not path.is_file():
        raise ReferenceFileError(f"{path}: file not found")
    if path.suffix.lower() == ".mcap":
        return read_mcap_reference(path)
    return read_results_csv_reference(path)


def _nearest_on_outline(outline: np.ndarray, s_xy: np.ndarray) -> np.ndarray:
    """Per time, the point (x, y, z of the outline's mean) of the closed polygon ``outline`` (K, 3)
    nearest to s_xy (N, 2), all in the target's body frame."""
    a = outline[:, :2]
    b = np.roll(a, -1, axis=0)
    e = b - a                                              # (K, 2)
    L2 = np.maximum(np.sum(e * e, axis=1), 1e-12)
    w = s_xy[:, None, :] - a[None, :, :]                   # (N, K, 2)
    u = np.clip(np.einsum("nkj,kj->nk", w, e) / L2, 0.0, 1.0)
    c = a[None] + u[..., None] * e[None]                   # (N, K, 2)
    k = np.argmin(np.sum((c - s_xy[:, None, :]) ** 2, axis=2), axis=1)
    pt = c[np.arange(len(s_xy)), k]
    return np.column_stack([pt, np.full(len(pt), float(np.mean(outline[:, 2])))])


def reported_point(track: ReferenceTrack, decl: TargetDecl, cfg: SensorConfig, tq: np.ndarray) -> dict:
    """The reported point of the target in the sensor frame at tq (module docstring): ``q`` (N, 3)
    [m], ``q_dot`` (N, 3) [m/s], ``ok`` (N,)."""
    r = track.at(tq)
    C_ms = dcm_from_euler_batch(r["rpy_rad"])
    if decl.nearest:
        outline = decl.outline_m if decl.outline_m is not None else track.outline_m
        if outline is None:
            raise ReferenceFileError(f"{cfg.path}: [targets.{track.target}] reference = \"nearest\" needs an outline: "
                                  "outline_m, or a session MCAP whose target messages carry one")
        s_t = np.einsum("nji,nj->ni", C_ms, cfg.mount_m[None, :] - r["pos_m"])   # sensor origin, target frame
        rp = _nearest_on_outline(outline, s_t[:, :2])
        off = np.einsum("nij,nj->ni", C_ms, rp)
    else:
        off = C_ms @ decl.reference_point_m
    P = r["pos_m"] + off
    w = r["yaw_rate_rps"]
    P_dot = r["vel_mps"] + np.column_stack([-w * off[:, 1], w * off[:, 0], np.zeros(len(w))])
    c, s = math.cos(cfg.mount_yaw_rad), math.sin(cfg.mount_yaw_rad)
    R_sb = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])   # master body -> sensor (declared)
    q = (P - cfg.mount_m) @ R_sb.T
    q_dot = P_dot @ R_sb.T
    ok = r["ok"] & np.all(np.isfinite(q), axis=1) & np.all(np.isfinite(q_dot), axis=1)
    return {"q": q, "q_dot": q_dot, "ok": ok, "sd_m": r["sd_m"]}
