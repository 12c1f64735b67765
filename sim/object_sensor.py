"""``v2xpos simulate sensor``: a radar-like object list from a convoy's truth, with a declared error
model, for ``v2xpos evaluate``'s tests, benches and the demo.

Truth: every target's IMU point in the master's body frame and its yaw relative to the master
(``truth_rel*.csv`` of a convoy recording, or sampled from a scenario), a cubic spline through
them; the reported point is P = p + Rz(rel_yaw) rp (flat roads: relative roll and pitch left out),
its velocity in the master's body frame dP/dt from the spline.

Error model (``SensorErrorModel``), per cycle of ``rate_hz`` at the true measurement time t:

* the sensor's true boresight is the declared one turned by ``mount_yaw_error_deg`` (+ right);
  a target is visible within the field of view and the range of the declaration, measured in that
  true frame;
* detected with probability ``detection_probability``; range + ``range_bias_m`` + N(0,
  ``range_sd_m``), azimuth + ``azimuth_bias_deg`` + N(0, ``azimuth_sd_deg``), relative velocity
  (turned with the position) + N(0, ``velocity_sd_mps``) per axis;
* stamped t + ``latency_s`` (+ N(0, ``latency_jitter_s``)), rounded to 0.1 ms;
* each target keeps its track id until it is missed ``track_loss_cycles`` cycles in a row, then
  gets a new one (an identity switch at its next detection);
* ghost objects: born as a Poisson process of ``ghosts_per_min``, uniform in the field of view
  (range and azimuth), constant random velocity, alive an exponential ``ghost_lifetime_s``, each
  with an id of its own.

Everything injected is written to ``sensor_truth.json``: the model, and what it realised (cycles
with each target in view, detections, identity switches, ghost ids per minute) -- for measuring
``evaluate``, never read by it. A mounting yaw and a constant azimuth bias rotate the measurements
alike: the observable yaw is ``mount_yaw_error_deg - azimuth_bias_deg`` (``expected``).
"""
from __future__ import annotations

import argparse
import json
import math
import sys
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path

import numpy as np
from scipy.interpolate import CubicSpline

OBJECT_DBC = """VERSION ""

NS_ :

BS_:

BU_: SENSOR

BO_ 1280 SensorStatus: 8 SENSOR
 SG_ Cycle : 0|16@1+ (1,0) [0|65535] "" Vector__XXX

BO_ 1536 ObjectList: 8 SENSOR
 SG_ ObjectId : 0|12@1+ (1,0) [0|4095] "" Vector__XXX
 SG_ DistLong : 12|16@1- (0.01,0) [-327.68|327.67] "m" Vector__XXX
 SG_ DistLat : 28|16@1- (0.01,0) [-327.68|327.67] "m" Vector__XXX
 SG_ VrelLong : 44|10@1- (0.1,0) [-51.2|51.1] "m/s" Vector__XXX
 SG_ VrelLat : 54|10@1- (0.1,0) [-51.2|51.1] "m/s" Vector__XXX

"""
"""The simulated sensor's DBC: one frame per object (cm in position, 0.1 m/s in velocity, as a
typical radar object interface); its DistLat is positive to the left, as on many radars, so the
signal map of sensor.toml flips it (scale -1)."""

RESOLUTION = {"x_m": 0.01, "y_m": 0.01, "vx_mps": 0.1, "vy_mps": 0.1}


@dataclass
class SensorErrorModel:
    rate_hz: float = 20.0
    latency_s: float = 0.08
    latency_jitter_s: float = 0.0
    range_sd_m: float = 0.10
    azimuth_sd_deg: float = 0.3
    range_bias_m: float = 0.0
    azimuth_bias_deg: float = 0.0
    mount_yaw_error_deg: float = 0.0
    velocity_sd_mps: float = 0.1
    detection_probability: float = 0.95
    ghosts_per_min: float = 6.0
    ghost_lifetime_s: float = 1.0
    track_loss_cycles: int = 3


MODELS: dict[str, SensorErrorModel] = {
    "ideal": SensorErrorModel(latency_s=0.0, range_sd_m=0.02, azimuth_sd_deg=0.05, velocity_sd_mps=0.02,
                              detection_probability=1.0, ghosts_per_min=0.0),
    "radar": SensorErrorModel(),
    "radar_biased": SensorErrorModel(latency_s=0.12, range_bias_m=0.25, mount_yaw_error_deg=1.0,
                                     detection_probability=0.9, ghosts_per_min=10.0),
    "radar_azimuth_bias": SensorErrorModel(latency_s=0.05, azimuth_bias_deg=-0.6, range_sd_m=0.15,
                                           detection_probability=0.85, ghosts_per_min=3.0),
    "camera": SensorErrorModel(rate_hz=30.0, latency_s=0.15, latency_jitter_s=0.005, range_sd_m=0.25,
                               azimuth_sd_deg=0.1, range_bias_m=-0.3, detection_probability=0.97,
                               ghosts_per_min=2.0, ghost_lifetime_s=0.3),
}
"""Named error models (``--model``); every field can be overridden on the command line."""


@dataclass
class TargetTruth:
    """A target relative to the master: IMU point (body frame) and relative yaw, as splines."""
    target: str
    t_s: np.ndarray
    pos_m: np.ndarray
    rel_yaw_rad: np.ndarray
    reference_point_m: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def __post_init__(self) -> None:
        self._p = CubicSpline(self.t_s, self.pos_m, axis=0)
        self._y = CubicSpline(self.t_s, np.unwrap(self.rel_yaw_rad))

    def point(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The reported point (module docstring) and its velocity in the master body frame."""
        yaw, rate = self._y(t), self._y(t, 1)
        c, s = np.cos(yaw), np.sin(yaw)
        rp = self.reference_point_m
        off = np.column_stack([c * rp[0] - s * rp[1], s * rp[0] + c * rp[1], np.full(len(t), rp[2])])
        P = self._p(t) + off
        V = self._p(t, 1) + np.column_stack([-rate * off[:, 1], rate * off[:, 0], np.zeros(len(t))])
        return P, V


@dataclass
class DeclaredSensor:
    """The declaration written to sensor.toml (what evaluate is told)."""
    name: str = "sim_radar"
    mount_m: tuple = (3.7, 0.0, -0.5)
    mount_yaw_deg: float = 0.0
    field_of_view_deg: float = 120.0
    max_range_m: float = 150.0


def convoy_truth(folder: str | Path, reference_points: dict[str, np.ndarray]) -> dict[str, TargetTruth]:
    """Every follower of a convoy recording (``truth_rel.csv`` is B's, ``truth_rel_X.csv`` X's)."""
    from v2xpos.diagnose.truth import read_truth_rel
    folder = Path(folder)
    week = convoy_gps_week(folder)
    out = {}
    names = sorted(p.name for p in folder.iterdir() if p.is_dir() and (p / "truth.csv").exists())
    for k, name in enumerate(names[1:]):
        rel = folder / ("truth_rel.csv" if k == 0 else f"truth_rel_{name}.csv")
        tr = read_truth_rel(rel, week)
        pos = np.column_stack([tr.cols["x_m"], tr.cols["y_m"], tr.cols["z_m"]])
        out[name] = TargetTruth(name, tr.t_s, pos, np.radians(tr.cols["rel_yaw_deg"]),
                                np.asarray(reference_points.get(name, np.zeros(3)), float))
    if not out:
        raise ValueError(f"{folder}: no convoy recording (vehicle folders with truth.csv and truth_rel.csv)")
    return out


def scenario_truth(sc, t_from_s: float, t_to_s: float, step_s: float = 0.02) -> dict[str, TargetTruth]:
    """Every slave of a ``sim.scenarios`` scenario relative to its master, reporting its rear
    bumper's centre (vehicles: the rear of their declared outline) or its centre (pedestrians)."""
    from sim.evaluate import truth_relative
    t = np.arange(t_from_s, t_to_s + step_s / 2, step_s)
    yaw_m = sc.master.truth.sample(t)["rpy_rad"][:, 2]
    out = {}
    for a in sc.slaves:
        rel = truth_relative(sc, a.actor_id, t)
        pts = np.asarray(a.geometry.points_body_m, float)
        rp = np.array([pts[:, 0].min(), 0.0, 0.0]) if a.kind == "vehicle" and len(pts) else np.zeros(3)
        yaw = a.truth.sample(t)["rpy_rad"][:, 2] - yaw_m
        out[a.actor_id] = TargetTruth(a.actor_id, t, rel["rel_pos_b_m"], yaw, rp)
    return out


def convoy_gps_week(folder: Path) -> int:
    """The GPS week of a convoy recording: its generator's, else from the leader's first GNSS epoch."""
    from v2xpos import timebase
    meta = folder / "truth_effects.json"
    if meta.exists():
        gen = json.loads(meta.read_text()).get("generator", {})
        if "gps_week" in gen:
            return int(gen["gps_week"])
    leader = sorted(p for p in folder.iterdir() if p.is_dir() and (p / "gnss.pos").exists())[0]
    for line in (leader / "gnss.pos").read_text().splitlines():
        if line.strip() and not line.startswith("%"):
            date, time_ = line.split()[:2]
            y, mo, d = (int(x) for x in date.split("/"))
            hh, mm, ss = time_.split(":")
            t = timebase.gpst_calendar_to_gps_seconds(y, mo, d, int(hh), int(mm), float(ss))
            return int(t // timebase.SECONDS_PER_WEEK)
    raise ValueError(f"{leader / 'gnss.pos'}: no epoch")


@dataclass
class SimulatedObjects:
    t_s: np.ndarray
    object_id: np.ndarray
    x_m: np.ndarray
    y_m: np.ndarray
    vx_mps: np.ndarray
    vy_mps: np.ndarray
    truth: dict = field(default_factory=dict)


def simulate_objects(truths: dict[str, TargetTruth], sensor: DeclaredSensor, model: SensorErrorModel,
                     seed: int = 0, t_from_s: float | None = None, t_to_s: float | None = None) -> SimulatedObjects:
    """The object list (module docstring), rows in stamp order, values on the DBC's resolution."""
    rng = np.random.default_rng([seed, 0x5E5])
    t0 = max(tr.t_s[0] for tr in truths.values()) if t_from_s is None else t_from_s
    t1 = min(tr.t_s[-1] for tr in truths.values()) if t_to_s is None else t_to_s
    period = 1.0 / model.rate_hz
    t_meas = t0 + period * np.arange(int(math.floor((t1 - t0) / period)) + 1)
    n = len(t_meas)
    yaw_true = math.radians(sensor.mount_yaw_deg + model.mount_yaw_error_deg)
    c, s = math.cos(yaw_true), math.sin(yaw_true)
    R_sb = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])      # body -> true sensor frame
    half_fov = math.radians(sensor.field_of_view_deg) / 2.0
    b_az = math.radians(model.azimuth_bias_deg)
    sd_az = math.radians(model.azimuth_sd_deg)
    stamp = t_meas + model.latency_s + (rng.normal(0.0, model.latency_jitter_s, n) if model.latency_jitter_s else 0.0)
    cols: dict[str, list] = {k: [] for k in ("t_s", "object_id", "x_m", "y_m", "vx_mps", "vy_mps")}
    next_id = 1
    realised: dict = {}

    def emit(k_cycle, ids, r, az, v_s):
        cols["t_s"].append(np.full(len(ids), stamp[k_cycle]))
        cols["object_id"].append(np.asarray(ids))
        cols["x_m"].append(r * np.cos(az))
        cols["y_m"].append(r * np.sin(az))
        cols["vx_mps"].append(v_s[:, 0])
        cols["vy_mps"].append(v_s[:, 1])

    per_target = {}
    for tid, tr in truths.items():
        P, V = tr.point(t_meas)
        q = (P - np.asarray(sensor.mount_m, float)) @ R_sb.T
        qd = V @ R_sb.T
        r = np.hypot(q[:, 0], q[:, 1])
        az = np.arctan2(q[:, 1], q[:, 0])
        view = (np.abs(az) <= half_fov) & (r <= sensor.max_range_m)
        det = view & (rng.random(n) < model.detection_probability)
        per_target[tid] = (r, az, qd, view, det)
    # track ids: a new id after track_loss_cycles misses in a row
    ids_of = {}
    for tid, (r, az, qd, view, det) in per_target.items():
        ids = np.zeros(n, int)
        current, misses, switches, prev_det_id = None, 0, 0, None
        for k in range(n):
            if det[k]:
                if current is None or misses >= model.track_loss_cycles:
                    current = next_id
                    next_id += 1
                ids[k] = current
                if prev_det_id is not None and prev_det_id != current:
                    switches += 1
                prev_det_id = current
                misses = 0
            else:
                misses += 1
        ids_of[tid] = ids
        realised[tid] = {"cycles_in_view": int(view.sum()), "cycles_detected": int(det.sum()),
                         "detection_rate": float(det.sum() / view.sum()) if view.any() else None,
                         "id_switches": switches, "object_ids": int(len(np.unique(ids[det])))}
    # ghosts
    span_s = float(t_meas[-1] - t_meas[0]) + period
    n_ghosts = rng.poisson(model.ghosts_per_min * span_s / 60.0)
    g_birth = np.sort(rng.uniform(t_meas[0], t_meas[-1] + period, n_ghosts))
    g_life = np.maximum(rng.exponential(model.ghost_lifetime_s, n_ghosts), period)
    g_r0 = rng.uniform(1.0, sensor.max_range_m, n_ghosts)
    g_az0 = rng.uniform(-half_fov, half_fov, n_ghosts)
    g_v = rng.uniform(-5.0, 5.0, (n_ghosts, 2))
    g_id = np.arange(next_id, next_id + n_ghosts)
    ghost_rows = {}
    for j in range(n_ghosts):
        ks = np.flatnonzero((t_meas >= g_birth[j]) & (t_meas < g_birth[j] + g_life[j]))
        if not len(ks):
            ks = np.array([min(int(np.searchsorted(t_meas, g_birth[j])), n - 1)])
        x0, y0 = g_r0[j] * math.cos(g_az0[j]), g_r0[j] * math.sin(g_az0[j])
        dt = t_meas[ks] - t_meas[ks[0]]
        for k, tt in zip(ks, dt):
            ghost_rows.setdefault(int(k), []).append((g_id[j], x0 + g_v[j, 0] * tt, y0 + g_v[j, 1] * tt, g_v[j]))
    # measurements per cycle, in cycle order
    for k in range(n):
        ids, rr, aa, vv = [], [], [], []
        for tid, (r, az, qd, view, det) in per_target.items():
            if det[k]:
                ids.append(ids_of[tid][k])
                rr.append(r[k] + model.range_bias_m + rng.normal(0.0, model.range_sd_m))
                turn = b_az + rng.normal(0.0, sd_az)
                aa.append(az[k] + turn)
                cz, sz = math.cos(b_az), math.sin(b_az)
                vv.append([cz * qd[k, 0] - sz * qd[k, 1], sz * qd[k, 0] + cz * qd[k, 1]]
                          + rng.normal(0.0, model.velocity_sd_mps, 2))
        for gid, gx, gy, gv in ghost_rows.get(k, []):
            ids.append(gid)
            rr.append(math.hypot(gx, gy))
            aa.append(math.atan2(gy, gx))
            vv.append(list(gv))
        if ids:
            emit(k, ids, np.asarray(rr), np.asarray(aa), np.asarray(vv, float).reshape(-1, 2))
    cat = {k: np.concatenate(v) if v else np.zeros(0) for k, v in cols.items()}
    t_stamp = np.round(cat["t_s"], 4)
    order = np.argsort(t_stamp, kind="stable")
    out = SimulatedObjects(t_s=t_stamp[order], object_id=cat["object_id"].astype(int)[order],
                           **{k: np.round(np.round(cat[k][order] / RESOLUTION[k]) * RESOLUTION[k], 6)
                              for k in RESOLUTION})
    truth = {"model": asdict(model), "declared": asdict(sensor), "seed": seed,
             "span_s": span_s, "cycles": n, "targets": realised,
             "ghost_ids": int(n_ghosts), "ghost_ids_per_min": n_ghosts / (span_s / 60.0),
             "expected": {"latency_ms": (model.latency_s) * 1e3, "range_bias_m": model.range_bias_m,
                          "mount_yaw_deg": model.mount_yaw_error_deg - model.azimuth_bias_deg,
                          "azimuth_bias_deg": model.azimuth_bias_deg - model.mount_yaw_error_deg,
                          "range_sd_m": model.range_sd_m},
             "meaning": "what the simulated sensor realised, for measuring v2xpos evaluate (never its input); "
                        "mount_yaw_deg: a mounting yaw and an azimuth bias rotate alike (yaw - azimuth bias)"}
    out.truth = truth
    return out


# ----------------------------------------------------------------------------- writers
def write_csv(objs: SimulatedObjects, path: Path) -> None:
    lines = ["t_gps_s,object_id,x_m,y_m,vx_mps,vy_mps"]
    for t, i, x, y, vx, vy in zip(objs.t_s.tolist(), objs.object_id.tolist(), objs.x_m.tolist(), objs.y_m.tolist(),
                                  objs.vx_mps.tolist(), objs.vy_mps.tolist()):
        lines.append(f"{t:.4f},{i},{x:.2f},{y:.2f},{vx:.1f},{vy:.1f}")
    path.write_text("\n".join(lines) + "\n")


def can_frames(objs: SimulatedObjects):
    """python-can Messages: a status frame on the first whole millisecond before the first object
    (ASC stores its start time to the millisecond), then one ObjectList frame per object."""
    import can
    import cantools
    db = cantools.database.load_string(OBJECT_DBC, "dbc")
    msg = db.get_message_by_name("ObjectList")
    status = db.get_message_by_name("SensorStatus")
    t_first = math.floor(float(objs.t_s[0]) * 1000.0) / 1000.0 - 0.001
    frames = [can.Message(timestamp=t_first, arbitration_id=status.frame_id, is_extended_id=False,
                          data=status.encode({"Cycle": 0}), channel=1)]
    for t, i, x, y, vx, vy in zip(objs.t_s.tolist(), objs.object_id.tolist(), objs.x_m.tolist(), objs.y_m.tolist(),
                                  objs.vx_mps.tolist(), objs.vy_mps.tolist()):
        data = msg.encode({"ObjectId": i % 4096, "DistLong": x, "DistLat": -y, "VrelLong": vx, "VrelLat": -vy},
                          strict=False)
        frames.append(can.Message(timestamp=t, arbitration_id=msg.frame_id, is_extended_id=False, data=data,
                                  channel=1))
    return frames


def write_can_log(objs: SimulatedObjects, path: Path) -> None:
    """ASC, BLF or MF4 (by suffix) with python-can's writers (MF4 through asammdf)."""
    import can
    path.unlink(missing_ok=True)
    writer = can.Logger(str(path))
    try:
        for fr in can_frames(objs):
            writer.on_message_received(fr)
    finally:
        writer.stop()


def sensor_toml(sensor: DeclaredSensor, reference_points: dict[str, np.ndarray], dbc: str | None) -> str:
    lines = ["[sensor]", f'name = "{sensor.name}"', f"mount_m = {[float(x) for x in sensor.mount_m]}",
             f"mount_yaw_deg = {float(sensor.mount_yaw_deg)!r}", 'clock = "gps"',
             f"field_of_view_deg = {float(sensor.field_of_view_deg)!r}", f"max_range_m = {float(sensor.max_range_m)!r}"]
    for tid, rp in sorted(reference_points.items()):
        lines += ["", f"[targets.{tid}]", f"reference_point_m = {[float(x) for x in rp]}"]
    if dbc:
        lines += ["", "[can]", f'dbc = "{dbc}"', "", "[can.signals]", 'object_id = "ObjectList.ObjectId"',
                  'x_m = "ObjectList.DistLong"', 'y_m = { signal = "ObjectList.DistLat", scale = -1.0 }',
                  'vx_mps = "ObjectList.VrelLong"', 'vy_mps = { signal = "ObjectList.VrelLat", scale = -1.0 }']
    return "\n".join(lines) + "\n"


def truth_results_csv(truths: dict[str, TargetTruth], path: Path, rate_hz: float = 100.0) -> None:
    """The truth as a results.csv (every row VALID): a perfect reference, to measure evaluate alone."""
    from v2xpos.output.results_csv import COLUMNS
    t0 = max(tr.t_s[0] for tr in truths.values())
    t1 = min(tr.t_s[-1] for tr in truths.values())
    t = t0 + np.arange(int((t1 - t0) * rate_hz) + 1) / rate_hz
    idx = {c: j for j, c in enumerate(COLUMNS)}
    lines = [",".join(COLUMNS)]
    for tid, tr in sorted(truths.items()):
        p, v = tr._p(t), tr._p(t, 1)
        yaw = np.degrees(tr._y(t))
        for k in range(len(t)):
            row = [""] * len(COLUMNS)
            row[idx["t_gps_s"]], row[idx["target"]], row[idx["status"]] = f"{t[k]:.4f}", tid, "VALID"
            for j, c in enumerate(("x_m", "y_m", "z_m")):
                row[idx[c]] = f"{p[k, j]:.4f}"
            for j, c in enumerate(("vx_mps", "vy_mps", "vz_mps")):
                row[idx[c]] = f"{v[k, j]:.4f}"
            row[idx["rel_roll_deg"]], row[idx["rel_pitch_deg"]] = "0.0", "0.0"
            row[idx["rel_yaw_deg"]] = f"{yaw[k]:.4f}"
            for c in ("sd_x_m", "sd_y_m", "sd_z_m"):
                row[idx[c]] = "0.0000"
            lines.append(",".join(row))
    path.write_text("\n".join(lines) + "\n")


def write_sensor(objs: SimulatedObjects, out: Path, sensor: DeclaredSensor, reference_points: dict,
                 formats: tuple[str, ...] = ("csv",)) -> list[Path]:
    """objects.<fmt> for each format, sensor.toml (+ sensor.dbc for CAN formats), sensor_truth.json."""
    out.mkdir(parents=True, exist_ok=True)
    written = []
    can_fmt = [f for f in formats if f != "csv"]
    for f in formats:
        p = out / f"objects.{f}"
        (write_csv if f == "csv" else write_can_log)(objs, p)
        written.append(p)
    if can_fmt:
        (out / "sensor.dbc").write_text(OBJECT_DBC)
        written.append(out / "sensor.dbc")
    (out / "sensor.toml").write_text(sensor_toml(sensor, reference_points, "sensor.dbc" if can_fmt else None))
    (out / "sensor_truth.json").write_text(json.dumps(objs.truth, indent=2) + "\n")
    return written + [out / "sensor.toml", out / "sensor_truth.json"]


def rear_sensor() -> DeclaredSensor:
    """A rear-facing radar on the leader (the convoy's followers are behind the master)."""
    return DeclaredSensor(name="sim_rear_radar", mount_m=(-1.0, 0.0, -0.5), mount_yaw_deg=180.0)


# ----------------------------------------------------------------------------- CLI
def add_sensor_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--convoy", required=True, help="a convoy recording (v2xpos simulate convoy, convoy_dev)")
    parser.add_argument("--out", required=True, help="output directory (objects.*, sensor.toml, sensor_truth.json)")
    parser.add_argument("--model", choices=sorted(MODELS), default="radar", help="named error model (default radar)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--format", default="csv", help="comma-separated: csv, asc, blf, mf4 (default csv)")
    parser.add_argument("--truth-reference", action="store_true",
                        help="also write the truth as DIR/reference_truth.csv (a results.csv, every row VALID)")
    parser.add_argument("--reference-point", default="1.8,0,0",
                        help="the point reported of every follower, its body frame [m] (default its front 1.8,0,0)")
    for f in fields(SensorErrorModel):
        parser.add_argument(f"--{f.name.replace('_', '-')}", type=type(f.default), default=None,
                            help=f"error model: {f.name} (default: the model's)")


def model_from_args(args: argparse.Namespace) -> SensorErrorModel:
    base = asdict(MODELS[args.model])
    for f in fields(SensorErrorModel):
        v = getattr(args, f.name, None)
        if v is not None:
            base[f.name] = v
    return SensorErrorModel(**base)


def run_sensor(args: argparse.Namespace) -> int:
    formats = tuple(x.strip().lower() for x in args.format.split(",") if x.strip())
    bad = [f for f in formats if f not in ("csv", "asc", "blf", "mf4")]
    if bad or not formats:
        print(f"v2xpos simulate sensor: --format: unknown {bad or formats}; csv, asc, blf, mf4", file=sys.stderr)
        return 2
    try:
        rp = np.array([float(x) for x in args.reference_point.split(",")])
        if rp.shape != (3,):
            raise ValueError
    except ValueError:
        print(f"v2xpos simulate sensor: --reference-point: expected x,y,z, got {args.reference_point!r}", file=sys.stderr)
        return 2
    model = model_from_args(args)
    try:
        names = convoy_truth(args.convoy, {})
    except (OSError, ValueError) as exc:
        print(f"v2xpos simulate sensor: {exc}", file=sys.stderr)
        return 2
    points = {k: rp for k in names}
    truths = convoy_truth(args.convoy, points)
    sensor = rear_sensor()
    objs = simulate_objects(truths, sensor, model, seed=args.seed)
    out = Path(args.out)
    written = write_sensor(objs, out, sensor, points, formats)
    if args.truth_reference:
        truth_results_csv(truths, out / "reference_truth.csv")
        written.append(out / "reference_truth.csv")
    tr = objs.truth
    print(f"wrote {', '.join(str(p) for p in written)}")
    print(f"  {tr['cycles']} cycles at {model.rate_hz:g} Hz, {len(objs.t_s)} objects; latency {model.latency_s * 1e3:g} ms, "
          f"range bias {model.range_bias_m:g} m, mounting yaw {model.mount_yaw_error_deg:g} deg, azimuth bias "
          f"{model.azimuth_bias_deg:g} deg, ghosts {tr['ghost_ids_per_min']:.1f}/min")
    for tid, t in tr["targets"].items():
        print(f"  {tid}: in view {t['cycles_in_view']} cycles, detected {t['cycles_detected']}, "
              f"id switches {t['id_switches']}")
    return 0
