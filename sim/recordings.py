"""Two-car (or N-car) recordings "of the convoy_dev kind": a leader A (the master's vehicle) and
followers B, C, ... on the same road, written in exactly the file formats and layout of
``../shared/data/convoy_dev`` so that every command of the project runs on them unchanged.

Layout of ``DIR``::

    A/ B/ ...   imu.csv, imu.csv.tag, gnss.pos, gnss.ubx, gnss.ubx.tag, dataset.toml (declared facts
                only), truth.csv
    truth_rel.csv            B's IMU point in A's body frame and yaw(B) - yaw(A), every 0.1 s
    truth_rel_C.csv ...      the same for every further follower (N > 2)
    truth_effects.json       undeclared effects (convoy_dev's keys for B at the top level, every
                             vehicle under "vehicles"), the logging model, the route, the seed

How each file is made (``sim.routes`` for the motion, ``sim.sensors`` for the sensors,
``sim.recording_formats`` for the bytes):

* Truth: the IMU point's trajectory from ``sim.trajectory.generate`` (NED mechanization
  equations with Earth rotation, transport rate and normal gravity, Groves 2013 eqs. 5.44-5.54),
  the same equations the project's filter integrates. truth.csv samples it every 0.1 s.
* IMU: ``sim.sensors.simulate_imu`` with the TRUE mounting ``R . imu_to_body`` (R = Rz(yaw)
  Ry(pitch) Rx(roll) of the undeclared misalignment, ``v_body = R . imu_to_body . v_imu``), the
  gyro scale error on the IMU's own axes (measured = (1 + s) true), turn-on biases, bias random
  walk and white noise of the IMU grade; printed with 3 decimals in g and deg/s. Samples are taken
  every 1/rate of the IMU's clock, which runs (1 + drift) fast; the counter counts that clock's ms.
* Logging: a line's last byte is in the logger's buffer at ``t_sample + min_delay + extra_delay +
  jitter`` (jitter exponential; the serial stream keeps its order). ``min_delay`` (a few ms of
  sensor filtering and serial transfer) is part of normal logging and is what the loader's
  lower-envelope clock leaves in its IMU times; ``extra_delay`` is the undeclared "late stamp"
  effect. The logger opens the file while the first line is on the wire (that line keeps only
  its tail) and writes a TIMETAG record each time it polled new lines
  (``recording_formats.logger_records``).
* GNSS: antenna = IMU point + C_nb . true lever arm, velocity + C_nb (w_nb x lever arm)
  (``sim.sensors.simulate_gnss`` without noise), then white noise of the declared sigmas per fix
  status (RTK fixed about 1 cm; float spells with a larger sigma; optionally a Gauss-Markov share
  in float), 10 Hz from ``gnss_start_s``. Heights in gnss.pos and truth.csv are on one and the
  same datum (no geoid separation added), as in convoy_dev.

Random draws come from independent streams keyed by (seed, purpose), so recordings with the same
seed and different presets or effects share route, mountings, noise and logging: ``clean`` and
``dev_like`` of one seed differ only by the undeclared effects.
"""
from __future__ import annotations

import argparse
import json
import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from sim import recording_formats as fmt
from sim.recording_params import (DT_S, EFFECT_NAMES, IMU_GRADES, PRESETS, TRUTH_STEP, ConvoyParams, VehicleSpec,
                                  axis_mountings, draw_params, mounting_name, rng_for)
from sim.routes import (LaneChange, Road, delayed, find_lane_change, follower_trajectory,
                        leader_route, leader_trajectory)
from sim.sensors import GnssErrorModel, ImuErrorModel, simulate_gnss, simulate_imu
from sim.trajectory import Trajectory
from v2xpos import geo, timebase
from v2xpos.rotation import dcm_from_euler_batch, wrap_pi
from v2xpos.types import FixStatus


# ------------------------------------------------------------------------------------------ simulation
@dataclass
class VehicleRecording:
    """A simulated vehicle in memory: its truth and the bytes of its files."""
    spec: VehicleSpec
    truth: Trajectory
    files: dict[str, bytes]
    lane_change: LaneChange | None = None
    notes: dict = field(default_factory=dict)


@dataclass
class ConvoyRecording:
    params: ConvoyParams
    vehicles: list[VehicleRecording]
    top_files: dict[str, bytes]
    route_blocks: list[tuple[float, str]]
    seconds: float = 0.0


def _imu_model(spec: VehicleSpec, rng: np.random.Generator) -> ImuErrorModel:
    g = IMU_GRADES[spec.imu_grade]
    return ImuErrorModel(
        gyro_bias_rps=rng.normal(0.0, math.radians(g.gyro_bias_dps), 3),
        accel_bias_mps2=rng.normal(0.0, g.accel_bias_mps2, 3),
        gyro_scale=np.asarray(spec.effects.gyro_scale, float),
        gyro_noise_rps_rthz=math.radians(g.gyro_noise_dps_rthz),
        accel_noise_mps2_rthz=g.accel_noise_mps2_rthz,
        gyro_bias_rw_rps_rts=math.radians(g.gyro_bias_rw_dps_rts),
        accel_bias_rw_mps2_rts=g.accel_bias_rw_mps2_rts)


def _imu_files(p: ConvoyParams, spec: VehicleSpec, truth: Trajectory) -> tuple[dict[str, bytes], dict]:
    """imu.csv and imu.csv.tag of one vehicle (see module docstring)."""
    rng = rng_for(p.seed, f"imu:{spec.name}")
    log_rng = rng_for(p.seed, f"logging:{spec.name}")
    lg = spec.logging
    drift = lg.clock_drift_ppm * 1e-6
    rate_gps = spec.imu_rate_hz * (1.0 + drift)          # samples per GPS second
    model = _imu_model(spec, rng)
    imu = simulate_imu(truth, model, rate_hz=rate_gps, rng=rng, imu_to_body=spec.true_imu_to_body)
    n = int(math.floor(p.route.duration_s * rate_gps + 1e-9))
    t_true = imu.t_s[:n]
    counter = lg.counter_start_ms + np.round(np.arange(n) * 1000.0 / spec.imu_rate_hz).astype(np.int64)
    lines = fmt.imu_csv_lines(imu.acc_mps2[:n], imu.gyro_rps[:n], counter)
    lines[0] = fmt.cut_head(lines[0], log_rng)
    ends = np.cumsum([len(x) for x in lines])
    jitter = log_rng.exponential(lg.jitter_mean_s, n) if lg.jitter_mean_s > 0 else np.zeros(n)
    avail = np.maximum.accumulate(t_true + lg.min_delay_s + spec.effects.imu_stamp_extra_delay_s + jitter)
    open_gps = float(avail[0] - log_rng.uniform(0.0005, 0.003))
    rec_ms, rec_off = fmt.logger_records(avail, ends, open_gps, log_rng, lg.poll_ms, lg.poll_jitter_mean_ms,
                                         lg.poll_jitter_max_ms)
    files = {"imu.csv": b"".join(lines),
             "imu.csv.tag": fmt.timetag_bytes(open_gps, lg.tick_ms, rec_ms, rec_off)}
    notes = {"imu_samples": n, "imu_first_sample_true_gps_s": float(t_true[0]),
             "gyro_bias_dps": np.degrees(model.gyro_bias_rps).round(4).tolist(),
             "accel_bias_mps2": model.accel_bias_mps2.round(4).tolist()}
    return files, notes


UBX_LATENCY_MIN_S = 0.025
UBX_LATENCY_JITTER_MEAN_S = 0.008
"""NAV-PVT output latency of the simulated receiver: a floor plus a gamma-distributed delay (shape 2)
-- the 20-50 ms a u-blox F9 shows on a lightly loaded port (docs/field.md, section 1)."""


def _ubx_stream(p: ConvoyParams, spec: VehicleSpec, t_gps: np.ndarray, lla: np.ndarray, is_float: np.ndarray,
                ns: np.ndarray, sd_ned: np.ndarray, vel: np.ndarray, vel_sd: np.ndarray) -> tuple[bytes, bytes]:
    """gnss.ubx (the receiver's NAV-PVT stream: the same solutions as gnss.pos) and gnss.ubx.tag (when
    each message reached the logger: epoch + output latency), so that ``v2xpos emulate`` serves the
    vehicle as live devices. Its own random stream: the other files do not change."""
    rng = rng_for(p.seed, f"ubx:{spec.name}")
    frames = [fmt.nav_pvt(float(t_gps[k]), lla[k], 1 if is_float[k] else 2, int(ns[k]), sd_ned[k], vel[k],
                          float(np.max(vel_sd[k]))) for k in range(len(t_gps))]
    arrival = t_gps + UBX_LATENCY_MIN_S + rng.gamma(2.0, UBX_LATENCY_JITTER_MEAN_S / 2.0, len(t_gps))
    arrival = np.maximum.accumulate(arrival)
    open_gps = float(arrival[0] - 0.002)
    rec_ms = np.ceil((arrival - open_gps) * 1e3).astype(np.int64)
    offsets = np.cumsum([len(f) for f in frames])
    return b"".join(frames), fmt.timetag_bytes(open_gps, spec.logging.tick_ms, rec_ms, offsets)


def _gnss_file(p: ConvoyParams, spec: VehicleSpec, truth: Trajectory) -> tuple[bytes, dict]:
    """gnss.pos of one vehicle (see module docstring), and in ``notes["files"]`` its NAV-PVT stream."""
    gs = p.gnss
    rng = rng_for(p.seed, f"gnss:{spec.name}")
    zero = {FixStatus.FIXED: 0.0, FixStatus.FLOAT: 0.0}
    model = GnssErrorModel(rate_hz=gs.rate_hz, sd_h_m=zero, gm_share=0.0, vel_sd_mps=0.0,
                           lever_arm_m=spec.true_lever_arm_m)
    g = simulate_gnss(truth, model, rng=np.random.default_rng(0))
    t0 = float(truth.t_s[0])
    rel = g.t_s - t0
    keep = (rel >= gs.start_s - 1e-6) & (rel <= p.route.duration_s - 1.0 / gs.rate_hz + 1e-6)
    rel = np.round(rel[keep] * gs.rate_hz) / gs.rate_hz
    # the fix status from the exact epoch times (t_s - t0 carries the rounding of GPS seconds)
    is_float = np.zeros(len(rel), dtype=bool)
    for a, b in spec.float_spells_s:
        is_float |= (rel >= a - 1e-6) & (rel < b - 1e-6)
    sd_neu = np.where(is_float[:, None], gs.sd_float_m, gs.sd_fixed_m)
    sd_ned = sd_neu.copy()
    white = rng.normal(0.0, 1.0, (len(rel), 3))
    err = white * sd_ned
    if gs.float_gm_share > 0:
        phi = math.exp(-1.0 / (gs.rate_hz * gs.float_gm_tau_s))
        gm = np.zeros((len(rel), 3))
        drive = rng.normal(0.0, 1.0, (len(rel), 3))
        for k in range(1, len(rel)):
            gm[k] = phi * gm[k - 1] + math.sqrt(1 - phi * phi) * drive[k]
        mixed = math.sqrt(1 - gs.float_gm_share) * white + math.sqrt(gs.float_gm_share) * gm
        err = np.where(is_float[:, None], mixed * sd_ned, err)
    r_ant = geo.lla_to_ned(g.lla[keep], truth.lla0)
    lla = geo.ned_to_lla(r_ant + err, truth.lla0)
    vel_sd = np.tile(gs.vel_sd_mps, (len(rel), 1))
    vel = g.vel_ned_mps[keep] + rng.normal(0.0, 1.0, (len(rel), 3)) * vel_sd
    vel_neu = vel * np.array([1.0, 1.0, -1.0])
    q = np.where(is_float, fmt.RTKLIB_Q["float"], fmt.RTKLIB_Q["fixed"])
    ns = np.where(is_float, spec.satellites - rng.integers(3, 7, len(rel)), spec.satellites)
    t_gps = t0 + rel
    text = fmt.pos_text(t_gps, lla, q, ns, sd_neu, vel_neu, vel_sd)
    ubx, tag = _ubx_stream(p, spec, t_gps, lla, is_float, ns, sd_ned, vel, vel_sd)
    return text.encode("ascii"), {"gnss_epochs": int(len(rel)), "float_epochs": int(is_float.sum()),
                                  "files": {"gnss.ubx": ubx, "gnss.ubx.tag": tag}}


def _grid_rows(duration_s: float) -> np.ndarray:
    """Trajectory sample indices of the truth rows (every 0.1 s over the duration)."""
    n = int(round(duration_s / (DT_S * TRUTH_STEP)))
    return np.arange(n) * TRUTH_STEP


def relative_truth(lla_m: np.ndarray, rpy_m: np.ndarray, lla_s: np.ndarray, rpy_s: np.ndarray) -> tuple:
    """The slave's point in the master's body frame and yaw(slave) - yaw(master) wrapped to
    (-pi, pi]: r_b = C_bn,m C_en,m (r_e,s - r_e,m) (the definition of ``v2xpos.relative``).
    Arrays (N, 3); returns ((N, 3) [m], (N,) [rad])."""
    lat, lon = lla_m[:, 0], lla_m[:, 1]
    sl, cl, so, co = np.sin(lat), np.cos(lat), np.sin(lon), np.cos(lon)
    C_en = np.empty((len(lat), 3, 3))
    C_en[:, 0] = np.stack([-sl * co, -sl * so, cl], axis=1)
    C_en[:, 1] = np.stack([-so, co, np.zeros_like(lat)], axis=1)
    C_en[:, 2] = np.stack([-cl * co, -cl * so, -sl], axis=1)
    d_e = geo.lla_to_ecef(lla_s) - geo.lla_to_ecef(lla_m)
    d_n = np.einsum("nij,nj->ni", C_en, d_e)
    C_nb = dcm_from_euler_batch(rpy_m)
    r_b = np.einsum("nji,nj->ni", C_nb, d_n)
    return r_b, wrap_pi(rpy_s[:, 2] - rpy_m[:, 2])


def simulate(p: ConvoyParams) -> ConvoyRecording:
    """Every vehicle's truth and file bytes (nothing written)."""
    started = time.perf_counter()
    t0 = float(timebase.gps_seconds_from_week_tow(p.gps_week, p.start_tow_s))
    route = leader_route(p.route, rng_for(p.seed, "route"))
    leader = leader_trajectory(route, p.route, p.yaw0_rad, np.asarray(p.origin_lla, float), t0, dt_s=DT_S)
    road = Road(leader)
    t_rel = leader.t_s - leader.t_s[0]
    truths = [leader]
    lanes: list[LaneChange | None] = [None]
    progress, rate = road.sigma_t, leader.speed_mps
    for spec in p.vehicles[1:]:
        lag = int(round(spec.follow_lag_s / DT_S))
        progress = delayed(progress, lag) - spec.follow_gap_m
        rate = delayed(rate, lag)
        lane = None
        if spec.lane_change is not None:
            ramp, hold, offset = spec.lane_change
            lane = find_lane_change(road, t_rel, progress, rate, rng_for(p.seed, f"lane:{spec.name}"), ramp, hold,
                                    offset)
        d, dd = lane.offset(t_rel) if lane else (np.zeros_like(t_rel), np.zeros_like(t_rel))
        truths.append(follower_trajectory(road, progress, rate, d, dd, leader, p.route.roll_per_lat_acc_rad))
        lanes.append(lane)

    rows = _grid_rows(p.route.duration_s)
    tow = np.round(p.start_tow_s + rows * DT_S, 6)
    vehicles = []
    for spec, truth, lane in zip(p.vehicles, truths, lanes):
        files, notes = _imu_files(p, spec, truth)
        files["gnss.pos"], gnotes = _gnss_file(p, spec, truth)
        files.update(gnotes.pop("files"))
        notes.update(gnotes)
        files["truth.csv"] = fmt.truth_text(tow, truth.lla[rows], truth.v_ned_mps[rows],
                                            truth.rpy_rad[rows]).encode("ascii")
        files["dataset.toml"] = fmt.dataset_toml(spec.name, spec.imu_to_body, spec.lever_arm_m,
                                                 spec.lever_arm_sd_m).encode("ascii")
        vehicles.append(VehicleRecording(spec=spec, truth=truth, files=files, lane_change=lane, notes=notes))

    top: dict[str, bytes] = {}
    master = vehicles[0]
    for v in vehicles[1:]:
        r_b, dyaw = relative_truth(master.truth.lla[rows], master.truth.rpy_rad[rows], v.truth.lla[rows],
                                   v.truth.rpy_rad[rows])
        name = "truth_rel.csv" if v is vehicles[1] else f"truth_rel_{v.spec.name}.csv"
        top[name] = fmt.truth_rel_text(tow, r_b, dyaw, v.spec.name, master.spec.name).encode("ascii")
    rec = ConvoyRecording(params=p, vehicles=vehicles, top_files=top, route_blocks=route.blocks)
    top["truth_effects.json"] = (json.dumps(truth_effects(rec), indent=2) + "\n").encode("ascii")
    rec.seconds = time.perf_counter() - started
    return rec


def _vehicle_effects(v: VehicleRecording) -> dict:
    s, e = v.spec, v.spec.effects
    delay_ms = e.imu_stamp_extra_delay_s * 1e3
    axis = "xyz"
    scaled = [f"{axis[k]} of imu.csv: {e.gyro_scale[k]:+g}" for k in range(3) if e.gyro_scale[k]]
    return {
        "imu_misalignment_deg": list(e.misalignment_deg),
        "imu_misalignment_convention": "roll, pitch, yaw of R = Rz(yaw) Ry(pitch) Rx(roll); true mounting: "
                                       "v_body = R . imu_to_body . v_imu",
        "imu_stamp_extra_delay_s": e.imu_stamp_extra_delay_s,
        "imu_stamp_extra_delay_meaning": f"every IMU byte reached the logger {delay_ms:g} ms later than the "
                                         f"declared timing says: the recorded stamps are {delay_ms:g} ms late",
        "gyro_scale": list(e.gyro_scale),
        "gyro_scale_meaning": "scale error on the IMU's own axes (" + ("; ".join(scaled) or "none")
                              + "): measured = (1 + s) true",
        "gnss_lever_arm_m": [round(float(x), 4) for x in s.true_lever_arm_m],
        "gnss_lever_arm_meaning": "true antenna position from the IMU point, body frame (x fwd, y right, z down); "
                                  f"dataset.toml declares {[round(float(x), 4) for x in s.lever_arm_m]}",
    }


def truth_effects(rec: ConvoyRecording) -> dict:
    """truth_effects.json: convoy_dev's keys for the first follower at the top level; every vehicle
    under ``vehicles`` with the same keys plus what else is true and not declared (logging delay,
    biases, float spells, follow behaviour)."""
    p = rec.params
    out: dict = {"vehicle": rec.vehicles[1].spec.name, **_vehicle_effects(rec.vehicles[1])}
    per = {}
    for v in rec.vehicles:
        s = v.spec
        d = _vehicle_effects(v)
        d.update({
            "clean": s.effects.is_clean(),
            "imu_to_body_declared": np.asarray(s.imu_to_body).astype(int).tolist(),
            "gnss_lever_arm_declared_m": [round(float(x), 4) for x in s.lever_arm_m],
            "mounting": mounting_name(s.imu_to_body),
            "imu_grade": s.imu_grade, "imu_rate_hz": s.imu_rate_hz,
            "imu_gyro_bias_dps": v.notes["gyro_bias_dps"], "imu_accel_bias_mps2": v.notes["accel_bias_mps2"],
            "imu_logging": asdict(s.logging),
            "imu_time_late_s": round(s.logging.min_delay_s + s.effects.imu_stamp_extra_delay_s, 6),
            "imu_time_late_meaning": "loader IMU time (lower-envelope clock of the TIMETAG) minus the true "
                                     "sample time is this (logging min delay + extra delay), within about 1 ms",
            "float_spells_s": [list(x) for x in s.float_spells_s],
            "float_spells_meaning": "RTK float (Q 2) from start to end, seconds from the first truth row",
        })
        if v is not rec.vehicles[0]:
            d["follow"] = {"lag_s": s.follow_lag_s, "gap_m": s.follow_gap_m,
                           "meaning": "progress along the leader's road = that of the vehicle ahead lag_s "
                                      "earlier minus gap_m"}
            d["lane_change"] = asdict(v.lane_change) if v.lane_change else None
        per[s.name] = d
    out["vehicles"] = per
    out["generator"] = {
        "module": "sim.recordings", "seed": p.seed, "preset": p.preset, "duration_s": p.route.duration_s,
        "gps_week": p.gps_week, "start_tow_s": p.start_tow_s,
        "origin_lat_lon_deg_h_m": [math.degrees(p.origin_lla[0]), math.degrees(p.origin_lla[1]), p.origin_lla[2]],
        "route_blocks": [[round(t, 2), n] for t, n in rec.route_blocks],
        "max_speed_mps": p.route.max_speed_mps, "max_grade_rad": p.route.max_grade_rad,
        "roll_per_lat_acc_rad": p.route.roll_per_lat_acc_rad,
        "drive_off_radius_m": p.route.drive_off_radius_m, "drive_off_turn_s": p.route.drive_off_turn_s,
        "gnss": asdict(p.gnss),
    }
    return out


def write(rec: ConvoyRecording, out_dir: str | Path) -> list[Path]:
    """Write every file under out_dir (created); returns the paths written."""
    out = Path(out_dir)
    written = []
    for v in rec.vehicles:
        d = out / v.spec.name
        d.mkdir(parents=True, exist_ok=True)
        for name, data in v.files.items():
            fmt.write_bytes(d / name, data)
            written.append(d / name)
    out.mkdir(parents=True, exist_ok=True)
    for name, data in rec.top_files.items():
        fmt.write_bytes(out / name, data)
        written.append(out / name)
    return written


def generate_convoy(out_dir: str | Path, seed: int = 0, preset: str = "dev_like", **kw) -> ConvoyRecording:
    """Draw parameters (``draw_params``), simulate and write a recording; returns it."""
    rec = simulate(draw_params(seed, preset, **kw))
    write(rec, out_dir)
    return rec


# ------------------------------------------------------------------------------------------ CLI
def _parse_vec(text: str, n: int, what: str) -> tuple:
    try:
        vals = tuple(float(x) for x in text.split(","))
    except ValueError:
        raise ValueError(f"{what}: expected {n} comma-separated numbers, got {text!r}") from None
    if len(vals) != n:
        raise ValueError(f"{what}: expected {n} comma-separated numbers, got {len(vals)}")
    return vals


_EFFECT_KEYS = {"misalignment_deg": 3, "imu_stamp_extra_delay_s": 1, "gyro_scale": 3, "lever_arm_error_m": 3}


_ROUTE_KEYS = ("drive_off_radius_m", "drive_off_turn_s")


def apply_overrides(p: ConvoyParams, mountings: list[str], effects: list[str], floats: list[str],
                    routes: list[str] = ()) -> None:
    """CLI overrides: ``V=MOUNTING`` (a name of ``axis_mountings``), ``V.KEY=VALUES`` (a field of
    ``Effects``), ``V=START:END[,START:END]`` float spells (``V=none``: no spell), ``KEY=VALUE`` a
    field of the route (``_ROUTE_KEYS``)."""
    import dataclasses
    for item in routes:
        key, _, val = item.partition("=")
        if key not in _ROUTE_KEYS:
            from v2xpos.schema import did_you_mean
            raise ValueError(f"--route {item!r}: unknown key {key!r}{did_you_mean(key, _ROUTE_KEYS)}; one of {list(_ROUTE_KEYS)}")
        p.route = dataclasses.replace(p.route, **{key: _parse_vec(val, 1, f"--route {item!r}")[0]})
    by_name = {v.name: v for v in p.vehicles}
    mounts = axis_mountings()

    def vehicle(name: str, what: str) -> VehicleSpec:
        if name not in by_name:
            raise ValueError(f"{what}: unknown vehicle {name!r}; vehicles are {sorted(by_name)}")
        return by_name[name]

    for item in mountings:
        name, _, m = item.partition("=")
        if m not in mounts:
            raise ValueError(f"--mounting {item!r}: unknown mounting {m!r}; one of {sorted(mounts)}")
        vehicle(name, f"--mounting {item!r}").imu_to_body = mounts[m]
    for item in effects:
        lhs, _, val = item.partition("=")
        name, _, key = lhs.partition(".")
        v = vehicle(name, f"--effect {item!r}")
        if key not in _EFFECT_KEYS:
            from v2xpos.schema import did_you_mean
            raise ValueError(f"--effect {item!r}: unknown key {key!r}{did_you_mean(key, _EFFECT_KEYS)}; "
                             f"one of {sorted(_EFFECT_KEYS)}")
        vals = _parse_vec(val, _EFFECT_KEYS[key], f"--effect {item!r}")
        setattr(v.effects, key, vals[0] if _EFFECT_KEYS[key] == 1 else vals)
    for item in floats:
        name, _, spans = item.partition("=")
        v = vehicle(name, f"--float {item!r}")
        if spans == "none":
            v.float_spells_s = []
            continue
        spells = []
        for span in spans.split(","):
            a, b = _parse_vec(span.replace(":", ","), 2, f"--float {item!r}")
            if not 0 <= a < b <= p.route.duration_s:
                raise ValueError(f"--float {item!r}: need 0 <= start < end <= duration")
            spells.append((a, b))
        v.float_spells_s = spells


def add_arguments(parser: argparse.ArgumentParser) -> None:
    kinds = parser.add_subparsers(dest="kind", required=True, metavar="KIND",
                                  help="convoy: leader A + followers; sensor: an object list from a convoy's truth")
    from sim.object_sensor import add_sensor_arguments
    add_sensor_arguments(kinds.add_parser("sensor", help="a radar/camera object list with a declared error model "
                                                         "(sim.object_sensor)"))
    parser = kinds.add_parser("convoy", help="leader A + followers in the shared recording formats, with truth")
    parser.add_argument("--out", required=True, help="output directory (A/, B/, truth_rel.csv, ...)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--preset", choices=PRESETS, default="dev_like",
                        help="clean: no undeclared effect; dev_like: effects of development size on the followers")
    parser.add_argument("--duration", type=float, default=200.0, help="seconds (default 200)")
    parser.add_argument("--vehicles", type=int, default=2, help="number of cars (A leads; default 2)")
    parser.add_argument("--effects-on", default=None,
                        help="comma-separated vehicles with undeclared effects (dev_like; default: every follower)")
    parser.add_argument("--effect-kinds", default=",".join(EFFECT_NAMES),
                        help=f"subset of {','.join(EFFECT_NAMES)} drawn by dev_like")
    parser.add_argument("--effect", action="append", default=[], metavar="V.KEY=VALUES",
                        help="set an effect, e.g. B.imu_stamp_extra_delay_s=0.025, B.misalignment_deg=0.4,-0.6,-1, "
                             "B.gyro_scale=0,0,-0.007, B.lever_arm_error_m=0.5,0.3,0 (repeatable)")
    parser.add_argument("--mounting", action="append", default=[], metavar="V=NAME",
                        help="declared mounting, e.g. B=x-backward/z-up (default: drawn from the 24 axis-aligned)")
    parser.add_argument("--float", action="append", default=[], metavar="V=START:END",
                        help="float spells in s from the start, e.g. A=70:73 or B=none (default: one drawn per car)")
    parser.add_argument("--route", action="append", default=[], metavar="KEY=VALUE",
                        help=f"route override, KEY one of {', '.join(_ROUTE_KEYS)} (e.g. drive_off_radius_m=12)")
    parser.add_argument("--no-float", action="store_true", help="RTK fixed throughout")
    parser.add_argument("--imu-grade", default="mems_automotive", choices=sorted(IMU_GRADES))
    parser.add_argument("--imu-rate", type=float, default=100.0, help="IMU sample rate [Hz] of its own clock")
    parser.add_argument("--imu-clock-drift-ppm", type=float, default=0.0,
                        help="the IMU clocks run this fast against GPS time [ppm] (default 0)")
    parser.add_argument("--max-speed", type=float, default=None, help="leader's top speed [m/s] (default 14-19)")
    parser.add_argument("--max-grade-pct", type=float, default=0.0, help="road grades up to this [%%] (default flat)")
    parser.add_argument("--body-roll", action="store_true", help="body roll 0.006 rad per m/s^2 of lateral acc.")
    parser.add_argument("--week", type=int, default=None, help="GPS week (default drawn)")
    parser.add_argument("--tow", type=float, default=None, help="GPS time of week of the start [s] (default drawn)")
    parser.add_argument("--origin", default=None, metavar="LAT,LON,H", help="start point [deg, deg, m] (default drawn)")
    parser.add_argument("--evaluate", action="store_true",
                        help="afterwards run the project's filter on A and each follower and print the relative "
                             "horizontal error against the truth while moving (all, and from 3 s after the start)")


def run(args: argparse.Namespace) -> int:
    import sys
    if args.kind == "sensor":
        from sim.object_sensor import run_sensor
        return run_sensor(args)
    try:
        origin = None
        if args.origin:
            lat, lon, h = _parse_vec(args.origin, 3, "--origin")
            origin = (math.radians(lat), math.radians(lon), h)
        p = draw_params(
            args.seed, args.preset, duration_s=args.duration, n_vehicles=args.vehicles,
            effects_on=tuple(x for x in args.effects_on.split(",") if x) if args.effects_on is not None else None,
            effect_kinds=tuple(x for x in args.effect_kinds.split(",") if x), float_spells=not args.no_float,
            imu_grade=args.imu_grade, imu_rate_hz=args.imu_rate, max_grade_rad=math.atan(args.max_grade_pct / 100.0),
            body_roll=args.body_roll, max_speed_mps=args.max_speed, imu_clock_drift_ppm=args.imu_clock_drift_ppm,
            gps_week=args.week, start_tow_s=args.tow,
            origin_lla=origin)
        apply_overrides(p, args.mounting, args.effect, args.float, args.route)
    except ValueError as exc:
        print(f"v2xpos simulate: {exc}", file=sys.stderr)
        return 2
    rec = simulate(p)
    written = write(rec, args.out)
    out = Path(args.out)
    print(f"wrote {len(written)} files under {out} in {rec.seconds:.1f} s (seed {p.seed}, preset {p.preset}, "
          f"{p.route.duration_s:g} s, GPS week {p.gps_week} tow {p.start_tow_s:.0f})")
    print("route: " + ", ".join(f"{n}@{t:.0f}s" for t, n in rec.route_blocks))
    for v in rec.vehicles:
        s = v.spec
        e = s.effects
        line = (f"  {s.name}/: mounting {mounting_name(s.imu_to_body)}, lever arm declared "
                f"{[round(float(x), 3) for x in s.lever_arm_m]}, float {s.float_spells_s or 'none'}, "
                f"IMU {v.notes['imu_samples']} samples, GNSS {v.notes['gnss_epochs']} epochs")
        if v is not rec.vehicles[0]:
            lc = v.lane_change
            line += (f"; follows lag {s.follow_lag_s} s gap {s.follow_gap_m} m, lane change "
                     + (f"{lc.offset_m:+.1f} m at {lc.t_start_s:.0f}-{lc.t_end_s:.0f} s" if lc else "none"))
        print(line)
        print("      undeclared: " + ("none" if e.is_clean() else
                                      f"misalignment {list(e.misalignment_deg)} deg, stamps "
                                      f"{e.imu_stamp_extra_delay_s * 1e3:g} ms late, gyro scale {list(e.gyro_scale)}, "
                                      f"true lever arm {[round(float(x), 3) for x in s.true_lever_arm_m]}"))
    print(f"  {', '.join(sorted(rec.top_files))}")
    if args.evaluate:
        from sim.recording_eval import evaluate_convoy
        for name, both in evaluate_convoy(out).items():
            for label, res in both.items():
                print(f"  filter: {name} in A's body frame, horizontal error {label:<8} rms {res['horizontal_rms_m']:.3f} m, "
                      f"p50 {res['horizontal_p50_m']:.3f} m, p95 {res['horizontal_p95_m']:.3f} m, max "
                      f"{res['horizontal_max_m']:.3f} m, mean x/y {res['mean_xyz_m'][0]:+.3f}/{res['mean_xyz_m'][1]:+.3f} m "
                      f"({res['epochs']} epochs)")
    return 0
