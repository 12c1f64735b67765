"""Simulated spinning lidar: ray casting into a simple scene, scans along a truth trajectory.

Scene primitives (all in the local NED frame of the trajectory, metres): the ground plane
z = ground_d_m (NED z positive down), axis-aligned boxes, and vertical cylinders. A scan is cast
instantaneously from the sensor pose (no motion during the sweep, so no deskewing is needed):
rays at the beam elevations x the azimuth steps, intersected analytically (plane: t = (d - p.n)/(u.n);
box: slab method, Kay & Kajiya 1986; cylinder: the quadratic in the horizontal components), the
nearest hit within max range kept, range noise added.

Frames: sensor frame = vehicle body frame (x forward, y right, z down) at lever arm ``mount_b_m``;
the points of a scan are returned in the sensor frame. ``scan_poses`` gives the true sensor poses
T_n_s (4x4, sensor -> NED) for checks.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .trajectory import Trajectory


@dataclass
class Box:
    """Axis-aligned box [m] in NED: min and max corners."""
    lo: np.ndarray
    hi: np.ndarray


@dataclass
class Cylinder:
    """Vertical cylinder: centre (north, east) [m], radius [m], z from z_top (up, negative) to z_bottom."""
    center_ne_m: np.ndarray
    radius_m: float
    z_top_m: float = -6.0
    z_bottom_m: float = 0.0


@dataclass
class Scene:
    """Ground plane at NED z = ground_z_m (None: no ground returns, e.g. filtered out) plus boxes
    (walls are thin boxes) and cylinders."""
    ground_z_m: float | None = 0.0
    boxes: list = field(default_factory=list)
    cylinders: list = field(default_factory=list)


def courtyard(half_size_m: float = 40.0, wall_height_m: float = 6.0, seed: int = 0,
              n_boxes: int = 6, n_cylinders: int = 8, keep_clear_m: float = 22.0,
              ground: bool = True) -> Scene:
    """A walled square (four thin-box walls) with boxes and pillars placed at random outside a
    central disc of radius keep_clear_m (where the vehicle drives)."""
    rng = np.random.default_rng(seed)
    h, th = half_size_m, 0.5
    top = -wall_height_m
    boxes = [Box(np.array([-h, -h, top]), np.array([h, -h + th, 0.0])),
             Box(np.array([-h, h - th, top]), np.array([h, h, 0.0])),
             Box(np.array([-h, -h, top]), np.array([-h + th, h, 0.0])),
             Box(np.array([h - th, -h, top]), np.array([h, h, 0.0]))]
    cylinders = []

    def spot() -> np.ndarray:
        while True:
            p = rng.uniform(-h + 4.0, h - 4.0, 2)
            if np.hypot(*p) > keep_clear_m:
                return p

    for _ in range(n_boxes):
        c = spot()
        size = rng.uniform(1.5, 4.0, 2)
        height = rng.uniform(1.0, 4.0)
        boxes.append(Box(np.array([c[0] - size[0] / 2, c[1] - size[1] / 2, -height]),
                         np.array([c[0] + size[0] / 2, c[1] + size[1] / 2, 0.0])))
    for _ in range(n_cylinders):
        cylinders.append(Cylinder(spot(), float(rng.uniform(0.3, 1.0)), -float(rng.uniform(2.0, 6.0))))
    return Scene(0.0 if ground else None, boxes, cylinders)


@dataclass
class LidarModel:
    """Beam layout and errors: elevations [deg] (positive up), azimuth step [deg], max range [m],
    range noise 1-sigma [m], scan rate [Hz], mounting lever arm in the body frame [m]."""
    elevations_deg: np.ndarray = field(default_factory=lambda: np.linspace(-15.0, 15.0, 16))
    azimuth_step_deg: float = 0.4
    max_range_m: float = 80.0
    range_noise_m: float = 0.01
    rate_hz: float = 10.0
    mount_b_m: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, -1.8]))

    def ray_directions_s(self) -> np.ndarray:
        """Unit ray directions in the sensor frame (x fwd, y right, z down), (M, 3)."""
        el = np.radians(np.asarray(self.elevations_deg, float))
        az = np.radians(np.arange(0.0, 360.0, self.azimuth_step_deg))
        E, A = np.meshgrid(el, az, indexing="ij")
        return np.stack([np.cos(E) * np.cos(A), np.cos(E) * np.sin(A), -np.sin(E)], axis=-1).reshape(-1, 3)


def cast(scene: Scene, origin_n: np.ndarray, dirs_n: np.ndarray, max_range_m: float) -> np.ndarray:
    """Range [m] along each ray (M, 3 unit vectors, NED) from origin_n to the nearest surface;
    inf where nothing is hit within max_range_m."""
    o = np.asarray(origin_n, float)
    d = np.asarray(dirs_n, float)
    best = np.full(len(d), np.inf)
    if scene.ground_z_m is not None:
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (scene.ground_z_m - o[2]) / d[:, 2]
        best = np.where((t > 0) & np.isfinite(t), np.minimum(best, t), best)
    safe = np.where(np.abs(d) < 1e-12, 1e-12, d)
    inv = 1.0 / safe
    for b in scene.boxes:
        t1 = (b.lo - o) * inv
        t2 = (b.hi - o) * inv
        tmin = np.max(np.minimum(t1, t2), axis=1)
        tmax = np.min(np.maximum(t1, t2), axis=1)
        hit = (tmax >= np.maximum(tmin, 0.0)) & (tmin > 0)
        best = np.where(hit, np.minimum(best, tmin), best)
    for c in scene.cylinders:
        px, py = o[0] - c.center_ne_m[0], o[1] - c.center_ne_m[1]
        a = d[:, 0] ** 2 + d[:, 1] ** 2
        bq = 2.0 * (px * d[:, 0] + py * d[:, 1])
        cq = px * px + py * py - c.radius_m ** 2
        disc = bq * bq - 4.0 * a * cq
        ok = (disc >= 0) & (a > 1e-12)
        with np.errstate(invalid="ignore", divide="ignore"):
            t = (-bq - np.sqrt(np.where(ok, disc, 0.0))) / (2.0 * np.where(ok, a, 1.0))
        z = o[2] + t * d[:, 2]
        hit = ok & (t > 0) & (z >= c.z_top_m) & (z <= c.z_bottom_m)
        best = np.where(hit, np.minimum(best, t), best)
    return np.where(best <= max_range_m, best, np.inf)


@dataclass
class ScanSequence:
    """Scans (list of (M_k, 3) points in the sensor frame), their times [s], true poses T_n_s."""
    t_s: np.ndarray
    scans: list
    poses_true: np.ndarray


def simulate_scans(traj: Trajectory, scene: Scene, model: LidarModel | None = None,
                   rng: np.random.Generator | None = None, t_start_s: float | None = None,
                   duration_s: float | None = None) -> ScanSequence:
    """Scans at model.rate_hz along traj between t_start_s and t_start_s + duration_s."""
    model = model or LidarModel()
    rng = rng or np.random.default_rng(0)
    t0 = traj.t_s[0] if t_start_s is None else t_start_s
    t1 = traj.t_s[-1] if duration_s is None else min(traj.t_s[-1], t0 + duration_s)
    times = np.arange(t0, t1 + 1e-9, 1.0 / model.rate_hz)
    s = traj.sample(times)
    dirs_s = model.ray_directions_s()
    scans, poses = [], []
    for k in range(len(times)):
        C_ns = s["C_nb"][k]
        origin = s["r_ned_m"][k] + C_ns @ model.mount_b_m
        r = cast(scene, origin, dirs_s @ C_ns.T, model.max_range_m)
        hit = np.isfinite(r)
        rr = r[hit] + rng.normal(0.0, model.range_noise_m, int(hit.sum()))
        scans.append(dirs_s[hit] * rr[:, None])
        T = np.eye(4)
        T[:3, :3] = C_ns
        T[:3, 3] = origin
        poses.append(T)
    return ScanSequence(times, scans, np.array(poses))


def kiss_icp_poses(seq: ScanSequence, max_range_m: float = 80.0, voxel_size_m: float = 0.5,
                   max_threads: int = 1, convergence: float = 1e-4,
                   fixed_threshold_m: float | None = None) -> np.ndarray:
    """Odometry poses (N, 4, 4) of the scan sequence from KISS-ICP (Vizzo et al. 2023, RA-L 8(2)),
    relative to the first scan's sensor frame: T_s0_sk."""
    from kiss_icp.config import KISSConfig
    from kiss_icp.kiss_icp import KissICP

    cfg = KISSConfig()
    cfg.data.max_range = max_range_m
    cfg.data.min_range = 0.5
    cfg.data.deskew = False
    cfg.mapping.voxel_size = voxel_size_m
    cfg.registration.max_num_threads = max_threads
    cfg.registration.convergence_criterion = convergence
    cfg.adaptive_threshold.fixed_threshold = fixed_threshold_m
    odo = KissICP(cfg)
    poses = []
    for pts in seq.scans:
        odo.register_frame(np.ascontiguousarray(pts, dtype=np.float64), np.zeros(len(pts)))
        poses.append(odo.last_pose.copy())
    return np.array(poses)
