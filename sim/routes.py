"""Convoy routes: a leader's drive assembled from manoeuvre blocks, and followers driving the
leader's road behind it.

Leader. A random sequence of blocks (``BLOCKS``) after a standstill start, ending stopped:
stop-and-go, a tight loop (a full circle of 7-12 m radius), 90 deg turns at walking-to-town
speeds, sweeping curves at road speeds, lane changes (a yaw-rate doublet), cruise stretches
(speed change + straight), optionally a road grade per block. Each block is a list of
``sim.trajectory.Segment`` (piecewise-constant acceleration / yaw rate, smoothed by the
trajectory's first-order lag) and the whole list is integrated by ``sim.trajectory.generate``,
so the leader's truth and ideal inertial outputs are exactly those of that module. The first
moving segment is a straight acceleration: the heading at rest is the direction the car drives
off in; with ``RouteSpec.drive_off_radius_m`` it turns from its onset instead (out of a parking
space). Turns only start above 3 m/s and are followed by >= 2 s straight so that the lagged yaw
rate has died out (< 0.2 %) before any stop.

Followers. The leader's path defines a road: heading psi(sigma), curvature kappa = dpsi/dsigma
and grade theta(sigma) as functions of the arc length sigma travelled (cubic splines through the
leader's samples, a straight line behind its start for sigma < 0). A follower's progress along
the road is the vehicle ahead's progress delayed by ``lag_s`` and set back by ``gap_m``
(sigma_k(t) = sigma_{k-1}(t - lag) - gap), which keeps it at gap + lag * speed behind and makes it
stop ``gap_m`` behind when the one ahead stops for longer than ``lag_s``. A lateral offset d(t)
(right positive; a lane change is a cycloidal ramp of d) is driven on the parallel curve:

    along-road speed  u = dsigma/dt (1 - kappa d)          (arc length of the parallel curve)
    speed             s = sqrt(u^2 + d'^2),   heading psi_k = psi(sigma) + atan2(d', u)

so the follower's reference point moves along P(sigma) + d N(sigma) with no side-slip. Its speed,
heading rate (central differences of these smooth samples) and grade are handed to
``generate`` one sample at a time (no smoothing; the grade command is the exact inverse of
``generate``'s 1 s grade lag), so the follower's truth is integrated by the same equations as the
leader's. The road is followed to the integration error of the trapezoid rule (sub-cm over
200 s); the truth files are the integrated trajectories, exact by construction.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.interpolate import CubicSpline

from sim.trajectory import Segment, Trajectory, generate

BLOCKS = ("stop_and_go", "tight_loop", "turn90", "curve", "lane_change", "cruise")
"""Manoeuvre blocks a leader's route is drawn from."""
REQUIRED_BLOCKS = ("cruise", "stop_and_go", "tight_loop", "turn90", "curve", "lane_change")
"""Blocks every route contains once (in random order) when the duration allows; the rest of the
time is filled with random blocks. ``cruise`` comes first: a long straight stretch where a
follower can change lanes."""
GRADE_LAG_S = 1.0
"""The first-order lag ``sim.trajectory.generate`` applies to the grade command (max(tau, 1 s))."""


@dataclass
class RouteSpec:
    """What a leader's route may contain. Speeds [m/s], accelerations [m/s^2], angles [rad]."""
    duration_s: float = 200.0
    max_speed_mps: float = 17.0
    max_lat_acc_mps2: float = 3.0
    max_yaw_rate_rps: float = 0.45
    static_start_s: tuple[float, float] = (8.0, 20.0)
    static_end_s: float = 6.0
    accel_mps2: tuple[float, float] = (1.2, 2.5)
    brake_mps2: tuple[float, float] = (1.5, 3.0)
    max_grade_rad: float = 0.0
    roll_per_lat_acc_rad: float = 0.0
    smooth_tau_s: float = 0.3
    blocks: tuple[str, ...] = BLOCKS
    min_dwell_s: float = 3.0
    drive_off_radius_m: float = 0.0
    """The leader drives off on a circle of this radius (out of a parking space; + right, - left)
    for its first ``drive_off_turn_s`` of motion, accelerating at the lowest of ``accel_mps2``; 0:
    straight. A radius, not a yaw rate, so that a follower passing the same spot faster meets the
    same path at a lateral acceleration ``v^2 / R`` a car can take."""
    drive_off_turn_s: float = 2.0

    def __post_init__(self) -> None:
        unknown = sorted(set(self.blocks) - set(BLOCKS))
        if unknown:
            raise ValueError(f"unknown route block(s) {unknown}; choose from {list(BLOCKS)}")
        if self.duration_s < 20.0:
            raise ValueError(f"duration_s {self.duration_s} too short (>= 20 s: static start, a drive, a stop)")
        if (self.drive_off_radius_m and abs(self.drive_off_radius_m) < 5.0) or not 0.0 < self.drive_off_turn_s <= 10.0:
            raise ValueError(f"drive-off turn of radius {self.drive_off_radius_m} m for {self.drive_off_turn_s} s: "
                             f"need |radius| >= 5 m (0: straight) and 0 < duration <= 10 s")


@dataclass
class Route:
    """A leader's segments and a log of the blocks (start time relative to the start [s], name)."""
    segments: list[Segment]
    blocks: list[tuple[float, str]] = field(default_factory=list)


class _Builder:
    def __init__(self, spec: RouteSpec, rng: np.random.Generator):
        self.spec, self.rng = spec, rng
        self.segs: list[Segment] = []
        self.t = 0.0
        self.v = 0.0
        self.log: list[tuple[float, str]] = []

    # -- primitive pieces (each returns segments and the speed after them) ----------------------
    def speed_change(self, v_from: float, v_to: float, to_stop: bool = False) -> list[Segment]:
        lo, hi = self.spec.brake_mps2 if v_to < v_from else self.spec.accel_mps2
        a = float(self.rng.uniform(lo, hi))
        dv = v_to - v_from
        if abs(dv) < 1e-6:
            return []
        # a stop brakes 0.3 s longer: the lagged deceleration then reaches zero speed exactly
        return [Segment(abs(dv) / a + (0.3 if to_stop else 0.0), accel_mps2=math.copysign(a, dv))]

    def end_reserve(self, v: float) -> float:
        return (v / self.spec.brake_mps2[0] + 0.3 if v > 0 else 0.0) + self.spec.static_end_s

    def turn_rate(self, v: float, lat_acc: float, min_radius_m: float) -> float:
        radius = max(v * v / lat_acc, v / self.spec.max_yaw_rate_rps, min_radius_m)
        return v / radius

    def grade(self) -> float | None:
        g = self.spec.max_grade_rad
        if g <= 0 or self.rng.random() < 0.5:
            return None
        return float(self.rng.uniform(-g, g))

    # -- blocks ---------------------------------------------------------------------------------
    def block(self, name: str) -> tuple[list[Segment], float]:
        sp, rng, v = self.spec, self.rng, self.v
        vmax = sp.max_speed_mps
        sign = 1.0 if rng.random() < 0.5 else -1.0
        if name == "cruise":
            v1 = float(rng.uniform(min(8.0, vmax), vmax))
            segs = self.speed_change(v, v1) + [Segment(float(rng.uniform(12.0, 18.0)))]
            return segs, v1
        if name == "stop_and_go":
            v1 = float(rng.uniform(min(5.0, vmax), vmax))
            segs = (self.speed_change(v, 0.0, to_stop=True)
                    + [Segment(float(rng.uniform(sp.min_dwell_s, sp.min_dwell_s + 4.0)))]
                    + self.speed_change(0.0, v1) + [Segment(2.0)])
            return segs, v1
        if name == "tight_loop":
            radius = float(rng.uniform(7.0, 12.0))
            v1 = min(float(rng.uniform(3.5, 6.0)), math.sqrt(sp.max_lat_acc_mps2 * radius),
                     sp.max_yaw_rate_rps * radius)
            w = v1 / radius
            segs = self.speed_change(v, v1) + [Segment(1.5), Segment(2 * math.pi / w, yaw_rate_rps=sign * w),
                                               Segment(2.0)]
            return segs, v1
        if name == "turn90":
            v1 = float(rng.uniform(4.0, min(9.0, vmax)))
            w = self.turn_rate(v1, float(rng.uniform(1.5, sp.max_lat_acc_mps2)), 8.0)
            segs = self.speed_change(v, v1) + [Segment(1.5), Segment(0.5 * math.pi / w, yaw_rate_rps=sign * w),
                                               Segment(2.0)]
            return segs, v1
        if name == "curve":
            v1 = float(rng.uniform(min(9.0, vmax), vmax))
            w = self.turn_rate(v1, float(rng.uniform(1.0, sp.max_lat_acc_mps2)), 15.0)
            angle = math.radians(float(rng.uniform(30.0, 120.0)))
            segs = self.speed_change(v, v1) + [Segment(1.0), Segment(angle / w, yaw_rate_rps=sign * w),
                                               Segment(2.0)]
            return segs, v1
        if name == "lane_change":
            v1 = v if v >= 8.0 else float(rng.uniform(min(8.0, vmax), vmax))
            width = float(rng.uniform(3.0, 3.7))
            t_lc = float(rng.uniform(3.0, 5.0))
            w = 4.0 * width / (v1 * t_lc * t_lc)          # lateral shift of a doublet: v w T^2 / 4
            segs = self.speed_change(v, v1) + [Segment(1.0), Segment(t_lc / 2, yaw_rate_rps=sign * w),
                                               Segment(t_lc / 2, yaw_rate_rps=-sign * w), Segment(2.0)]
            return segs, v1
        raise ValueError(f"unknown block {name!r}")

    def try_add(self, name: str) -> bool:
        segs, v1 = self.block(name)
        dur = sum(s.duration_s for s in segs)
        if self.t + dur + self.end_reserve(v1) > self.spec.duration_s:
            return False
        g = self.grade()
        if g is not None and segs:
            segs[0].pitch_rad = g
        self.log.append((self.t, name))
        self.segs += segs
        self.t += dur
        self.v = v1
        return True


def leader_route(spec: RouteSpec, rng: np.random.Generator) -> Route:
    """A random route of total duration ``spec.duration_s`` (see module docstring)."""
    b = _Builder(spec, rng)
    t_static = float(rng.uniform(*spec.static_start_s))
    b.segs.append(Segment(t_static, pitch_rad=0.0))
    b.t = t_static
    b.log.append((0.0, "static"))
    if spec.drive_off_radius_m:
        a = spec.accel_mps2[0]
        n = max(1, int(round(spec.drive_off_turn_s / 0.1)))
        step = spec.drive_off_turn_s / n
        # yaw rate = speed / radius, piecewise constant at each step's mid speed
        b.segs += [Segment(step, accel_mps2=a, yaw_rate_rps=a * (k + 0.5) * step / spec.drive_off_radius_m)
                   for k in range(n)]
        b.log.append((b.t, "drive_off_turn"))
        b.t += spec.drive_off_turn_s
        b.v = a * spec.drive_off_turn_s
    required = [n for n in REQUIRED_BLOCKS if n in spec.blocks]
    rest = [n for n in required[1:]]
    rng.shuffle(rest)
    for name in required[:1] + rest:
        b.try_add(name)
    failures = 0
    while failures < 8:
        if not b.try_add(str(rng.choice(list(spec.blocks)))):
            failures += 1
    fill = spec.duration_s - b.t - b.end_reserve(b.v)
    if fill > 0:
        b.segs.append(Segment(fill))
        b.t += fill
    if b.v > 0:
        b.log.append((b.t, "stop"))
        b.segs += b.speed_change(b.v, 0.0, to_stop=True)
        b.t = sum(s.duration_s for s in b.segs)
    b.segs.append(Segment(max(spec.duration_s - b.t, 0.0)))
    return Route(segments=b.segs, blocks=b.log)


def leader_trajectory(route: Route, spec: RouteSpec, yaw0_rad: float, lla0: np.ndarray, t0_s: float,
                      dt_s: float = 0.01, margin_s: float = 1.0) -> Trajectory:
    """Integrate the route (plus ``margin_s`` standing still at the end, so that samples up to
    the duration are interior) with ``sim.trajectory.generate``."""
    segs = list(route.segments) + [Segment(margin_s)]
    return generate(segs, dt_s=dt_s, lla0=lla0, speed0_mps=0.0, yaw0_rad=yaw0_rad, pitch0_rad=0.0,
                    t0_s=t0_s, smooth_tau_s=spec.smooth_tau_s, roll_per_lat_acc_rad=spec.roll_per_lat_acc_rad)


class Road:
    """The leader's path as a function of arc length sigma [m]: heading psi [rad, unwrapped],
    curvature kappa = dpsi/dsigma [1/m] and grade theta [rad] (cubic splines through the leader's
    samples at least 1 mm apart); for sigma < 0 the straight line behind the start."""

    def __init__(self, leader: Trajectory):
        dt = leader.dt_s
        s = leader.speed_mps
        sigma = np.concatenate([[0.0], np.cumsum(0.5 * (s[1:] + s[:-1]) * dt)])
        psi = np.unwrap(leader.rpy_rad[:, 2])
        theta = leader.rpy_rad[:, 1]
        keep = [0]
        for k in range(1, len(sigma)):
            if sigma[k] - sigma[keep[-1]] >= 1e-3:
                keep.append(k)
        keep = np.asarray(keep)
        self.sigma_t = sigma
        self.sigma_end = float(sigma[keep[-1]])
        self.psi0 = float(psi[0])
        self.theta0 = float(theta[0])
        if len(keep) < 4:
            raise ValueError("the leader hardly moves: no road to follow")
        self._psi = CubicSpline(sigma[keep], psi[keep])
        self._kappa = self._psi.derivative()
        self._theta = CubicSpline(sigma[keep], theta[keep])

    def heading(self, sigma: np.ndarray) -> np.ndarray:
        sigma = np.asarray(sigma, float)
        return np.where(sigma <= 0, self.psi0, self._psi(np.clip(sigma, 0.0, self.sigma_end)))

    def curvature(self, sigma: np.ndarray) -> np.ndarray:
        sigma = np.asarray(sigma, float)
        return np.where(sigma <= 0, 0.0, self._kappa(np.clip(sigma, 0.0, self.sigma_end)))

    def grade(self, sigma: np.ndarray) -> np.ndarray:
        sigma = np.asarray(sigma, float)
        return np.where(sigma <= 0, self.theta0, self._theta(np.clip(sigma, 0.0, self.sigma_end)))


@dataclass
class LaneChange:
    """A lane change and back: the offset ramps to ``offset_m`` (right positive, so negative = to
    the left) over ``ramp_s`` from ``t_start_s`` (relative to the start), holds ``hold_s``, ramps
    back. Each ramp is cycloidal, d = W (u - sin(2 pi u) / (2 pi)) for u = 0..1: lateral velocity
    and acceleration start and end at zero, so yaw rate and body roll stay continuous."""
    t_start_s: float
    ramp_s: float
    hold_s: float
    offset_m: float

    @property
    def t_end_s(self) -> float:
        return self.t_start_s + 2 * self.ramp_s + self.hold_s

    def _ramp(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        two_pi = 2.0 * np.pi
        return (self.offset_m * (u - np.sin(two_pi * u) / two_pi),
                self.offset_m / self.ramp_s * (1.0 - np.cos(two_pi * u)))

    def offset(self, t_rel_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(d [m], d' [m/s]) at times relative to the start."""
        t = np.asarray(t_rel_s, float)
        d = np.zeros_like(t)
        dd = np.zeros_like(t)
        t1 = self.t_start_s + self.ramp_s
        t2 = t1 + self.hold_s
        up = (t >= self.t_start_s) & (t < t1)
        d[up], dd[up] = self._ramp((t[up] - self.t_start_s) / self.ramp_s)
        d[(t >= t1) & (t < t2)] = self.offset_m
        down = (t >= t2) & (t < self.t_end_s)
        back, back_rate = self._ramp((t[down] - t2) / self.ramp_s)
        d[down], dd[down] = self.offset_m - back, -back_rate
        return d, dd


def delayed(x: np.ndarray, lag_samples: int) -> np.ndarray:
    """x shifted later by lag_samples, the first value held before the start."""
    if lag_samples <= 0:
        return x.copy()
    return np.concatenate([np.full(lag_samples, x[0]), x[:-lag_samples]])


def find_lane_change(road: Road, t_rel_s: np.ndarray, progress_m: np.ndarray, rate_mps: np.ndarray,
                     rng: np.random.Generator, ramp_s: float, hold_s: float, offset_m: float,
                     min_speed_mps: float = 8.0, max_curvature: float = 1.0 / 40.0,
                     t_window: tuple[float, float] | None = None) -> LaneChange | None:
    """A lane change placed at random where the follower keeps >= min_speed_mps and the road's
    |curvature| <= max_curvature for the whole manoeuvre (the hold shortened down to 2 s if it does
    not fit); None when no such stretch exists."""
    dt = float(t_rel_s[1] - t_rel_s[0])
    ok = (rate_mps >= min_speed_mps) & (np.abs(road.curvature(progress_m)) <= max_curvature)
    if t_window is not None:
        ok &= (t_rel_s >= t_window[0]) & (t_rel_s <= t_window[1])
    # run length of consecutive ok samples starting at each index
    run = np.zeros(len(ok) + 1, dtype=int)
    for k in range(len(ok) - 1, -1, -1):
        run[k] = run[k + 1] + 1 if ok[k] else 0
    for hold in (hold_s, 0.5 * hold_s, 2.0):
        need = int(math.ceil((2 * ramp_s + hold) / dt)) + 1
        starts = np.flatnonzero(run[:-1] >= need)
        if starts.size:
            k = int(rng.choice(starts))
            return LaneChange(float(t_rel_s[k]), ramp_s, hold, offset_m)
    return None


def follower_trajectory(road: Road, progress_m: np.ndarray, rate_mps: np.ndarray, offset_m: np.ndarray,
                        offset_rate_mps: np.ndarray, like: Trajectory,
                        roll_per_lat_acc_rad: float = 0.0) -> Trajectory:
    """A follower's truth on the leader's road (see module docstring), sampled on ``like``'s time
    grid: progress sigma(t) [m] and its rate [m/s] along the road, lateral offset d(t) [m, right
    positive] and its rate."""
    dt = like.dt_s
    kappa = road.curvature(progress_m)
    along = rate_mps * (1.0 - kappa * offset_m)
    if np.any(along < -1e-9):
        raise ValueError("lateral offset beyond the road's radius of curvature")
    speed = np.hypot(along, offset_rate_mps)
    psi = road.heading(progress_m) + np.arctan2(offset_rate_mps, np.maximum(along, 0.0))
    theta = road.grade(progress_m)
    acc_cmd = np.gradient(speed, dt)
    yaw_rate_cmd = np.gradient(psi, dt)
    a = math.exp(-dt / GRADE_LAG_S)
    theta_cmd = np.empty_like(theta)
    theta_cmd[0] = theta[0]
    theta_cmd[1:] = (theta[1:] - a * theta[:-1]) / (1.0 - a)
    n = len(like.t_s)
    segs = [Segment(dt, float(acc_cmd[k]), float(yaw_rate_cmd[k]), float(theta_cmd[k])) for k in range(n - 1)]
    # start point: on the straight behind the leader's start, offset to the right by d
    s0 = float(progress_m[0])
    if s0 > 0:
        raise ValueError("a follower starts behind the leader (progress <= 0 at the start)")
    psi0 = float(road.heading(s0))
    c = math.cos(road.theta0)
    r0 = np.array([s0 * c * math.cos(psi0), s0 * c * math.sin(psi0), -s0 * math.sin(road.theta0)])
    r0 += float(offset_m[0]) * np.array([-math.sin(psi0), math.cos(psi0), 0.0])
    return generate(segs, dt_s=dt, lla0=like.lla0, speed0_mps=float(speed[0]), yaw0_rad=float(psi[0]),
                    pitch0_rad=float(theta[0]), t0_s=float(like.t_s[0]), smooth_tau_s=0.0,
                    roll_per_lat_acc_rad=roll_per_lat_acc_rad, r0_ned_m=r0)
