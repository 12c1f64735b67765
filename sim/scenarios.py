"""Convoy scenarios for the V2V services: truth trajectories, sensor settings, fix degradations and
link impairments of every actor, rebuilt identically in every process from (parameters, seed).

Actors: the master ``ego`` drives at the back of a single-lane convoy; slaves ``t2..t{N-1}`` drive
ahead of it at a constant time headway ``headway_s`` on the same path (``Trajectory.shifted``); slave
``t1`` starts in the lane to the left, half a headway ahead of ego, and cuts in with a lane change
(a yaw-rate doublet: heading rises to r*T then returns, lateral shift = v r T^2); pedestrian ``p1``
walks at 1.4 m/s on the right-hand side walk against the traffic (one handheld IMU, so not graded).

The lead path repeats a pattern with curves both ways (lateral acceleration 1.6-2 m/s^2), an
S-bend and a braking manoeuvre (20 -> 12.5 m/s at -3 m/s^2 and back at +2.5 m/s^2).

Time: GPS time of the scenario is ``epoch_gps_s + (wall time - start stamp)`` in every process;
truth covers [epoch - history_s - 2 s, epoch + duration + 10 s]: the vehicles have been driving
(and their filters converging) for ``history_s`` before the run starts.

Link model of a slave (applied by the slave before publishing, ``v2xpos.link.LinkImpairment``):
message k is sent at ``max(send_{k-1}, t_k + delay_k)`` with ``delay_k = latency + N(0, jitter)
(clipped to +-3 sigma, >= 0) + spike`` -- a FIFO link: jitter changes spacing, never the order.
An actor's spikes are relative to the scenario epoch; the launcher writes them in GPS seconds.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from sim.trajectory import Segment, Trajectory, generate
from v2xpos.types import FixStatus
from v2xpos.link import LinkImpairment
from v2xpos.wire import Geometry

LANE_WIDTH_M = 3.5
DEFAULT_EPOCH_GPS_S = 1.4e9
PEDESTRIAN_SPEED_MPS = 1.4


@dataclass
class Actor:
    """One vehicle or pedestrian: truth, geometry (body frame), sensor and link settings.

    fix_schedule: (t_start_rel_s, t_end_rel_s, FixStatus) relative to the scenario epoch (FIXED
    elsewhere). imu_grade: ``sim.sensors.ImuErrorModel.preset`` name. lever_arm_m: GNSS antenna
    relative to the reference point (IMU), body frame [m]. seed: sensor noise seed.
    imu_units: IMU units on board (unit 1 feeds the filter; all are streamed for grading);
    imu_fault: (unit index >= 1, ``sim.imu_faults`` fault kind, start rel. epoch [s]) or None.
    gnss_sd_fixed_m: RTK-fixed 1-sigma horizontal noise [m]; gnss_vertical_factor: vertical sd /
    horizontal sd.
    """
    actor_id: str
    kind: str
    role: str
    truth: Trajectory
    geometry: Geometry
    fix_schedule: list[tuple[float, float, FixStatus]] = field(default_factory=list)
    link: LinkImpairment = field(default_factory=LinkImpairment)
    imu_grade: str = "tactical"
    lever_arm_m: np.ndarray = field(default_factory=lambda: np.array([0.5, 0.0, -1.4]))
    gnss_sd_fixed_m: float = 0.01
    gnss_vertical_factor: float = 1.0
    seed: int = 0
    imu_units: int = 3
    imu_fault: tuple | None = None


@dataclass
class Scenario:
    """All actors of a run. ``params`` rebuilds it: ``build(**params)``."""
    name: str
    epoch_gps_s: float
    duration_s: float
    actors: dict[str, Actor]
    master_id: str
    lla0: np.ndarray
    params: dict
    lanes_ned_m: dict[str, np.ndarray] = field(default_factory=dict)
    objects_ned_m: dict[str, np.ndarray] = field(default_factory=dict)

    @property
    def slaves(self) -> list[Actor]:
        return [a for a in self.actors.values() if a.role == "slave"]

    @property
    def master(self) -> Actor:
        return self.actors[self.master_id]

    def fix_schedule_abs(self, actor_id: str) -> list[tuple[float, float, FixStatus]]:
        """Fix schedule of an actor relative to the start of its truth trajectory (the convention of
        ``sim.sensors.simulate_gnss``)."""
        a = self.actors[actor_id]
        off = self.epoch_gps_s - float(a.truth.t_s[0])
        return [(t0 + off, t1 + off, st) for t0, t1, st in a.fix_schedule]


def _pattern() -> list[Segment]:
    """One lap of the lead path: curves both ways, braking, S-bend (34.5 s at 20 m/s)."""
    return [Segment(3.0), Segment(6.0, yaw_rate_rps=-0.08), Segment(3.0),
            Segment(2.5, accel_mps2=-3.0), Segment(2.0), Segment(3.0, accel_mps2=2.5),
            Segment(6.0, yaw_rate_rps=0.10), Segment(3.0),
            Segment(3.0, yaw_rate_rps=-0.10), Segment(3.0, yaw_rate_rps=0.10)]


def _with_yaw_doublet(segments: list[Segment], t_start_s: float, half_s: float, rate_rps: float) -> list[Segment]:
    """Segments with +rate added on [t_start, t_start+half) and -rate on [t_start+half, t_start+2 half)."""
    cuts = [t_start_s, t_start_s + half_s, t_start_s + 2 * half_s]
    out: list[Segment] = []
    t = 0.0
    for seg in segments:
        t_end = t + seg.duration_s
        bounds = [t] + [c for c in cuts if t < c < t_end] + [t_end]
        for a, b in zip(bounds[:-1], bounds[1:]):
            mid = 0.5 * (a + b)
            extra = rate_rps if cuts[0] <= mid < cuts[1] else (-rate_rps if cuts[1] <= mid < cuts[2] else 0.0)
            out.append(Segment(b - a, seg.accel_mps2, seg.yaw_rate_rps + extra, seg.pitch_rad))
        t = t_end
    return out


def _right_unit_ned(yaw_rad: float) -> np.ndarray:
    """Horizontal unit vector to the right of heading yaw (NED)."""
    return np.array([-math.sin(yaw_rad), math.cos(yaw_rad), 0.0])


def check_rtk_vertical_factor(value: float) -> None:
    """Raise ValueError unless ``value`` (simulated vertical / horizontal RTK noise) is finite, >= 0."""
    if not (math.isfinite(value) and value >= 0):
        raise ValueError(f"rtk_vertical_factor must be a finite number >= 0, got {value!r}")


def convoy(vehicles: int = 4, duration_s: float = 40.0, latency_ms: float = 100.0, jitter_ms: float = 5.0,
           speed_mps: float = 20.0, headway_s: float = 1.5, seed: int = 0, cut_in: bool = True,
           pedestrian: bool = True, degradations: bool = True, spikes: bool = True,
           imu_grade: str = "tactical", epoch_gps_s: float = DEFAULT_EPOCH_GPS_S,
           dt_s: float = 0.01, history_s: float = 20.0, imu_fault: str | None = "gyro_scale",
           rtk_vertical_factor: float = 1.0) -> Scenario:
    """Build the convoy scenario (see module docstring). ``vehicles`` counts the master.

    Every receiver's RTK-fixed noise is 1 cm per axis by default (``rtk_vertical_factor`` 1.0, the
    V2V issue's stated condition and e.g. the u-blox ZED-F9P datasheet's 0.01 m + 1 ppm for both
    horizontal and vertical); geodetic receivers are often specified 1.5-2x worse vertically.
    """
    check_rtk_vertical_factor(rtk_vertical_factor)
    if vehicles < 1:
        raise ValueError("vehicles must be >= 1 (the master)")
    params = dict(vehicles=vehicles, duration_s=duration_s, latency_ms=latency_ms, jitter_ms=jitter_ms,
                  speed_mps=speed_mps, headway_s=headway_s, seed=seed, cut_in=cut_in, pedestrian=pedestrian,
                  degradations=degradations, spikes=spikes, imu_grade=imu_grade, epoch_gps_s=epoch_gps_s,
                  dt_s=dt_s, history_s=history_s, imu_fault=imu_fault,
                  rtk_vertical_factor=rtk_vertical_factor)
    n_lane = vehicles - (1 if (cut_in and vehicles >= 2) else 0)
    pre_s = (n_lane - 1) * headway_s + 2.0 + history_s
    lap = _pattern()
    lap_s = sum(s.duration_s for s in lap)
    total_s = pre_s + duration_s + 12.0
    segs = [Segment(2.0)] + lap * int(math.ceil(total_s / lap_s))
    lead_t0 = epoch_gps_s - pre_s
    lead = generate(segs, dt_s=dt_s, speed0_mps=speed_mps, t0_s=lead_t0)
    lla0 = lead.lla0
    actors: dict[str, Actor] = {}
    ego_shift = (n_lane - 1) * headway_s
    body = Geometry.box(front_m=3.8, rear_m=1.0, half_width_m=0.9)

    actors["ego"] = Actor("ego", "vehicle", "master", lead.shifted(ego_shift), body, imu_grade=imu_grade,
                          seed=seed * 1000 + 1)
    in_lane = [f"t{j}" for j in range(2 if (cut_in and vehicles >= 2) else 1, vehicles)]
    for j, name in enumerate(in_lane, start=1):
        shift = ego_shift - j * headway_s
        actors[name] = Actor(name, "vehicle", "slave", lead.shifted(shift), body,
                             link=LinkImpairment(latency_ms, jitter_ms), imu_grade=imu_grade,
                             seed=seed * 1000 + 10 + j)
    if cut_in and vehicles >= 2:
        shift = ego_shift - 0.5 * headway_s
        t_lc_wall_rel = 0.3 * duration_s
        u_lc = (epoch_gps_s + t_lc_wall_rel) - (lead_t0 + shift)
        half_s = 2.0
        rate = LANE_WIDTH_M / (speed_mps * half_s ** 2)
        yaw_lc = float(lead.rpy_rad[lead.index_at(lead_t0 + u_lc), 2])
        r0 = -LANE_WIDTH_M * _right_unit_ned(yaw_lc)
        traj = generate(_with_yaw_doublet(segs, u_lc, half_s, rate), dt_s=dt_s, speed0_mps=speed_mps,
                        t0_s=lead_t0 + shift, lla0=lla0, r0_ned_m=r0)
        actors["t1"] = Actor("t1", "vehicle", "slave", traj, body, link=LinkImpairment(latency_ms, jitter_ms),
                             imu_grade=imu_grade, seed=seed * 1000 + 10)
    slave_names = sorted([a for a in actors if a != "ego"], key=lambda s: int(s[1:]))
    if degradations and slave_names:
        victim = actors[slave_names[-1]]
        t0 = 0.45 * duration_s
        victim.fix_schedule = [(t0, t0 + 3.0, FixStatus.FLOAT), (t0 + 3.0, t0 + 5.0, FixStatus.SINGLE)]
    if imu_fault and slave_names:
        victim = actors[slave_names[len(slave_names) // 2]]
        victim.imu_fault = (2, imu_fault, 0.0)          # the third unit, from the start of the run
    if spikes and slave_names:
        victim = actors[slave_names[0]]
        t0 = 0.65 * duration_s
        victim.link = LinkImpairment(latency_ms, jitter_ms, spikes=[(t0, t0 + 1.5, 300.0)])
    if pedestrian:
        t_meet_rel = 0.6 * duration_s
        ego = actors["ego"].truth
        k = ego.index_at(epoch_gps_s + t_meet_rel)
        yaw = float(ego.rpy_rad[k, 2])
        fwd = np.array([math.cos(yaw), math.sin(yaw), 0.0])
        meet = ego.r_ned_m[k] + 30.0 * fwd + (0.5 * LANE_WIDTH_M + 3.0) * _right_unit_ned(yaw)
        lead_in = 2.0 + history_s
        walk_t0 = epoch_gps_s - lead_in
        start = meet + PEDESTRIAN_SPEED_MPS * (t_meet_rel + lead_in) * fwd
        ped_segs = [Segment(t_meet_rel + lead_in), Segment(4.0, yaw_rate_rps=0.2), Segment(duration_s + 8.0)]
        traj = generate(ped_segs, dt_s=dt_s, speed0_mps=PEDESTRIAN_SPEED_MPS, yaw0_rad=yaw + math.pi,
                        t0_s=walk_t0, lla0=lla0, r0_ned_m=start, smooth_tau_s=0.5, roll_per_lat_acc_rad=0.0)
        actors["p1"] = Actor("p1", "pedestrian", "slave", traj, Geometry(kind="circle", radius_m=0.3),
                             link=LinkImpairment(latency_ms, jitter_ms), imu_grade=imu_grade,
                             lever_arm_m=np.array([0.0, 0.0, -0.3]), seed=seed * 1000 + 99, imu_units=1)
    for a in actors.values():
        a.gnss_vertical_factor = rtk_vertical_factor
    lanes = _lane_lines(lead, lead_t0, total_s)
    sc = Scenario("convoy", epoch_gps_s, duration_s, actors, "ego", lla0, params, lanes)
    sc.objects_ned_m = _roadside_objects(actors["ego"].truth, epoch_gps_s, duration_s)
    return sc


def _roadside_objects(ego: Trajectory, epoch_gps_s: float, duration_s: float) -> dict[str, np.ndarray]:
    """A traffic cone (point) on the right shoulder where ego is at 0.5 duration, and a parked
    trailer footprint (polygon, 6 m x 2.5 m) on the left verge where ego is at 0.8 duration."""
    out = {}
    for name, frac, side, size in (("cone", 0.5, 1.0, None), ("trailer", 0.8, -1.0, (6.0, 2.5))):
        k = ego.index_at(epoch_gps_s + frac * duration_s)
        yaw = float(ego.rpy_rad[k, 2])
        fwd = np.array([math.cos(yaw), math.sin(yaw), 0.0])
        right = _right_unit_ned(yaw)
        c = ego.r_ned_m[k] + side * (0.5 * LANE_WIDTH_M + 1.5) * right
        if size is None:
            out[name] = c[None, :]
        else:
            a, b = 0.5 * size[0] * fwd, 0.5 * size[1] * right
            out[name] = np.array([c + a + b, c + a - b, c - a - b, c - a + b])
    return out


def _lane_lines(lead: Trajectory, t0: float, total_s: float) -> dict[str, np.ndarray]:
    """Lane lines (NED polylines [m]) of the convoy lane: left and right edges, every 0.5 s of the lead
    (10 m at 20 m/s: chord error < 7 cm on the 200 m curves)."""
    idx = np.arange(0, len(lead), max(1, int(round(0.5 / lead.dt_s))))
    yaw = lead.rpy_rad[idx, 2]
    right = np.stack([-np.sin(yaw), np.cos(yaw), np.zeros(len(yaw))], axis=1)
    r = lead.r_ned_m[idx]
    return {"lane_left": r - 0.5 * LANE_WIDTH_M * right, "lane_right": r + 0.5 * LANE_WIDTH_M * right}


BUILDERS = {"convoy": convoy}


class ScenarioError(ValueError):
    """Unknown scenario, unknown parameter or a parameter of the wrong type (named in the message)."""


def check_params(name: str, params: dict, where: str = "") -> None:
    """ScenarioError unless every key of ``params`` is a parameter of scenario ``name`` with a
    value of its default's type (ints for floats; any string or None where the default is None).
    ``where`` (e.g. ``"slave.toml: [source.params]"``) prefixes the message."""
    import inspect

    from v2xpos.schema import did_you_mean
    prefix = f"{where}: " if where else ""
    if name not in BUILDERS:
        raise ScenarioError(f"{prefix}unknown scenario {name!r}{did_you_mean(str(name), BUILDERS)}; "
                            f"known: {sorted(BUILDERS)}")
    sig = inspect.signature(BUILDERS[name]).parameters
    for key, value in params.items():
        if key not in sig:
            raise ScenarioError(f"{prefix}scenario {name!r} has no parameter {key!r}{did_you_mean(str(key), sig)}; "
                                f"parameters: {list(sig)}")
        default = sig[key].default
        if default is None or default is inspect.Parameter.empty:
            ok = value is None or isinstance(value, str)
        elif isinstance(default, bool):
            ok = isinstance(value, bool)
        elif isinstance(default, float):
            ok = isinstance(value, (int, float)) and not isinstance(value, bool)
        else:
            ok = isinstance(value, type(default)) and not isinstance(value, bool)
        ok = ok or (value is None and "None" in str(sig[key].annotation))
        if not ok:
            raise ScenarioError(f"{prefix}scenario {name!r} parameter {key!r}: expected "
                                f"{type(default).__name__ if default is not None else 'a string'}, "
                                f"got {type(value).__name__} {value!r}")


def build(name: str = "convoy", **params) -> Scenario:
    """Scenario by name with keyword parameters (the same in every process); ScenarioError
    (a ValueError) for an unknown scenario or parameter, with a "did you mean"."""
    check_params(name, params)
    return BUILDERS[name](**params)


def scene_geojson(sc: Scenario) -> dict:
    """GeoJSON FeatureCollection (lon/lat degrees, RFC 7946) of the scenario's lane lines (LineString)
    and roadside objects (Point, Polygon), for the master's V2L / V2X stage."""
    from v2xpos import geo
    feats = []
    for name, pts in sc.lanes_ned_m.items():
        lla = geo.ned_to_lla(pts, sc.lla0)
        coords = [[math.degrees(p[1]), math.degrees(p[0]), float(p[2])] for p in lla]
        feats.append({"type": "Feature", "properties": {"id": name, "kind": "lane_line"},
                      "geometry": {"type": "LineString", "coordinates": coords}})
    for name, pts in sc.objects_ned_m.items():
        lla = geo.ned_to_lla(pts, sc.lla0)
        coords = [[math.degrees(p[1]), math.degrees(p[0]), float(p[2])] for p in lla]
        if len(coords) == 1:
            geom = {"type": "Point", "coordinates": coords[0]}
        else:
            geom = {"type": "Polygon", "coordinates": [coords + [coords[0]]]}
        feats.append({"type": "Feature", "properties": {"id": name, "kind": "object"}, "geometry": geom})
    return {"type": "FeatureCollection", "features": feats}
