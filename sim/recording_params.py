"""What a simulated convoy recording is made of (``sim.recordings`` simulates and writes it): the
axis mountings, IMU grades, undeclared effects, logging model, GNSS and vehicle specifications,
and their random draws per seed and preset. Every draw comes from an independent stream keyed by
(seed, purpose), so recordings with the same seed and different presets or effects share route,
mountings, noise and logging.
"""
from __future__ import annotations

import math
import zlib
from dataclasses import dataclass, field, replace

import numpy as np

from sim.routes import RouteSpec
from sim.sensors import ImuErrorModel
from v2xpos import timebase
from v2xpos.rotation import dcm_from_euler

PRESETS = ("clean", "dev_like")
EFFECT_NAMES = ("misalignment", "delay", "gyro_scale", "lever_arm")
DT_S = 0.01
"""Truth trajectory step [s]."""
TRUTH_STEP = 10
"""truth.csv / truth_rel.csv every TRUTH_STEP trajectory samples (0.1 s)."""

_AXIS_WORDS = {(0, 1): "forward", (0, -1): "backward", (1, 1): "right", (1, -1): "left", (2, 1): "down",
               (2, -1): "up"}


# ------------------------------------------------------------------------------------------ mountings
def _direction_word(col: np.ndarray) -> str:
    i = int(np.argmax(np.abs(col)))
    return _AXIS_WORDS[(i, int(np.sign(col[i])))]


def axis_mountings() -> dict[str, np.ndarray]:
    """The 24 axis-aligned mountings ``imu_to_body`` (signed permutations with det +1), named by
    where the IMU's x and z axes point in the body (x forward, y right, z down), e.g.
    ``x-backward/z-up`` = [[-1,0,0],[0,1,0],[0,0,-1]]."""
    out = {}
    eye = np.eye(3)
    for perm in ((0, 1, 2), (0, 2, 1), (1, 0, 2), (1, 2, 0), (2, 0, 1), (2, 1, 0)):
        for signs in np.ndindex(2, 2, 2):
            m = np.zeros((3, 3))
            for col, row in enumerate(perm):
                m[:, col] = eye[row] * (1 - 2 * signs[col])
            if np.linalg.det(m) > 0:
                out[f"x-{_direction_word(m[:, 0])}/z-{_direction_word(m[:, 2])}"] = m
    return dict(sorted(out.items()))


def mounting_name(imu_to_body: np.ndarray) -> str:
    return f"x-{_direction_word(imu_to_body[:, 0])}/z-{_direction_word(imu_to_body[:, 2])}"


# ------------------------------------------------------------------------------------------ IMU grades
@dataclass(frozen=True)
class ImuGrade:
    """White noise densities and 1-sigma turn-on biases / bias random walks of an IMU model."""
    gyro_noise_dps_rthz: float
    accel_noise_mps2_rthz: float
    gyro_bias_dps: float
    accel_bias_mps2: float
    gyro_bias_rw_dps_rts: float
    accel_bias_rw_mps2_rts: float


IMU_GRADES: dict[str, ImuGrade] = {
    # Automotive-qualified 6-axis MEMS (datasheet class of ST ASM330LHH / Bosch SMI230: rate noise
    # density ~5 mdps/rtHz = 0.3 deg/rt-h, acceleration noise 60-90 ug/rtHz); residual turn-on bias
    # after factory trimming 0.05 deg/s and ~3 mg; bias random walks giving ~3e-3 deg/s and
    # ~3e-3 m/s^2 over 200 s.
    "mems_automotive": ImuGrade(0.005, 80e-6 * 9.80665, 0.05, 0.03, 2e-4, 2e-4),
    "ideal": ImuGrade(0.0, 0.0, 0.0, 0.0, 0.0, 0.0),
}
for _name in ("tactical", "automotive", "consumer"):
    _m = ImuErrorModel.preset(_name, np.random.default_rng(0))
    _bias = {"tactical": (1.0 / 3600, 0.0005 * 9.81), "automotive": (0.05, 0.01), "consumer": (0.3, 0.05)}[_name]
    IMU_GRADES[_name] = ImuGrade(math.degrees(_m.gyro_noise_rps_rthz), _m.accel_noise_mps2_rthz, _bias[0], _bias[1],
                                 0.0, 0.0)


# ------------------------------------------------------------------------------------------ parameters
@dataclass
class Effects:
    """Undeclared effects of one vehicle (each zero = absent).

    misalignment_deg: (roll, pitch, yaw) of R = Rz Ry Rx, true mounting v_body = R imu_to_body v_imu;
    imu_stamp_extra_delay_s: every IMU line reaches the logger this much later than normal logging;
    gyro_scale: (sx, sy, sz) on the IMU's own axes, measured = (1 + s) true;
    lever_arm_error_m: true antenna lever arm minus the declared one, body frame (x fwd, y right, z down).
    """
    misalignment_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)
    imu_stamp_extra_delay_s: float = 0.0
    gyro_scale: tuple[float, float, float] = (0.0, 0.0, 0.0)
    lever_arm_error_m: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def is_clean(self) -> bool:
        return (not any(self.misalignment_deg) and not self.imu_stamp_extra_delay_s and not any(self.gyro_scale)
                and not any(self.lever_arm_error_m))

    def without(self, names: set[str]) -> "Effects":
        """A copy with the named effects (``EFFECT_NAMES``) set to zero."""
        out = replace(self)
        if "misalignment" in names:
            out.misalignment_deg = (0.0, 0.0, 0.0)
        if "delay" in names:
            out.imu_stamp_extra_delay_s = 0.0
        if "gyro_scale" in names:
            out.gyro_scale = (0.0, 0.0, 0.0)
        if "lever_arm" in names:
            out.lever_arm_error_m = (0.0, 0.0, 0.0)
        return out


@dataclass
class LoggingModel:
    """How a vehicle's IMU lines reach the logging computer (see module docstring)."""
    min_delay_s: float = 0.005
    jitter_mean_s: float = 0.001
    poll_ms: int = 16
    poll_jitter_mean_ms: float = 6.0
    poll_jitter_max_ms: int = 19
    counter_start_ms: int = 100000
    clock_drift_ppm: float = 0.0
    tick_ms: int = 1000


@dataclass
class GnssSpec:
    """Receiver output: rate, first epoch after the start, declared sigmas (north, east, up) per
    status [m, m/s], satellites, Gauss-Markov share / time constant of the float error."""
    rate_hz: float = 10.0
    start_s: float = 1.0
    sd_fixed_m: tuple[float, float, float] = (0.01, 0.01, 0.02)
    sd_float_m: tuple[float, float, float] = (0.2, 0.2, 0.4)
    vel_sd_mps: tuple[float, float, float] = (0.02, 0.02, 0.03)
    float_gm_share: float = 0.0
    float_gm_tau_s: float = 3.0


@dataclass
class VehicleSpec:
    """One vehicle: declared mounting and lever arm, undeclared effects, IMU, logging, GNSS,
    float spells [(start, end) s from the start], and for a follower how it follows."""
    name: str
    imu_to_body: np.ndarray
    lever_arm_m: np.ndarray
    lever_arm_sd_m: float = 0.02
    effects: Effects = field(default_factory=Effects)
    imu_grade: str = "mems_automotive"
    imu_rate_hz: float = 100.0
    logging: LoggingModel = field(default_factory=LoggingModel)
    float_spells_s: list[tuple[float, float]] = field(default_factory=list)
    satellites: int = 20
    follow_lag_s: float = 1.0
    follow_gap_m: float = 10.0
    lane_change: tuple[float, float, float] | None = None
    """(ramp_s, hold_s, offset_m) of a lane change and back (offset right positive), placed where
    it fits; None: stays in lane."""

    @property
    def true_lever_arm_m(self) -> np.ndarray:
        return np.asarray(self.lever_arm_m, float) + np.asarray(self.effects.lever_arm_error_m, float)

    @property
    def true_imu_to_body(self) -> np.ndarray:
        r, p, y = np.radians(self.effects.misalignment_deg)
        return dcm_from_euler(r, p, y) @ np.asarray(self.imu_to_body, float)


@dataclass
class ConvoyParams:
    """Everything a convoy recording is made from (``draw_params`` fills it from a seed)."""
    seed: int
    preset: str
    route: RouteSpec
    vehicles: list[VehicleSpec]
    gps_week: int = 2374
    start_tow_s: float = 250000.0
    origin_lla: tuple[float, float, float] = (math.radians(40.0), math.radians(-105.0), 1600.0)
    yaw0_rad: float = 0.0
    gnss: GnssSpec = field(default_factory=GnssSpec)


def rng_for(seed: int, purpose: str) -> np.random.Generator:
    """An independent stream per (seed, purpose): changing one draw never shifts another."""
    return np.random.default_rng([int(seed), zlib.crc32(purpose.encode())])


def vehicle_names(n: int) -> list[str]:
    if not 2 <= n <= 26:
        raise ValueError(f"vehicles must be 2..26, got {n}")
    return [chr(ord("A") + k) for k in range(n)]


def draw_effects(seed: int, name: str, imu_to_body: np.ndarray) -> Effects:
    """Undeclared effects of the size seen in development (dev_like): misalignment 0.3-1.2 deg per
    axis, IMU stamps 10-40 ms late, a 0.3-1 % gyro scale error on the IMU axis that is vertical in
    the body (plus, one time in three, on another axis), the antenna 0.2-0.6 m off its declared
    position forward and sideways (and up to 0.1 m vertically one time in two)."""
    rng = rng_for(seed, f"effects:{name}")

    def signed(lo: float, hi: float, digits: int) -> float:
        return round((1.0 if rng.random() < 0.5 else -1.0) * float(rng.uniform(lo, hi)), digits)

    mis = (signed(0.3, 1.2, 2), signed(0.3, 1.2, 2), signed(0.3, 1.2, 2))
    delay = round(float(rng.uniform(0.010, 0.040)), 3)
    vertical_z = round(float(rng.uniform(-0.1, 0.1)), 2)
    lever = (signed(0.2, 0.6, 2), signed(0.2, 0.6, 2), vertical_z if rng.random() < 0.5 else 0.0)
    scales = (signed(0.003, 0.010, 4), signed(0.003, 0.010, 4))
    other, with_other = int(rng.integers(0, 2)), rng.random() < 1.0 / 3.0
    vertical = int(np.argmax(np.abs(np.asarray(imu_to_body)[2, :])))     # the IMU axis along body z
    gyro = [0.0, 0.0, 0.0]
    gyro[vertical] = scales[0]
    if with_other:
        gyro[[k for k in range(3) if k != vertical][other]] = scales[1]
    return Effects(misalignment_deg=mis, imu_stamp_extra_delay_s=delay, gyro_scale=tuple(gyro),
                   lever_arm_error_m=lever)


def draw_params(seed: int, preset: str = "dev_like", duration_s: float = 200.0, n_vehicles: int = 2,
                effects_on: tuple[str, ...] | None = None, effect_kinds: tuple[str, ...] = EFFECT_NAMES,
                float_spells: bool = True, imu_grade: str = "mems_automotive", imu_rate_hz: float = 100.0,
                max_grade_rad: float = 0.0, body_roll: bool = False, max_speed_mps: float | None = None,
                imu_clock_drift_ppm: float = 0.0,
                gps_week: int | None = None, start_tow_s: float | None = None,
                origin_lla: tuple[float, float, float] | None = None) -> ConvoyParams:
    """Draw a recording's parameters from ``seed``.

    preset: ``clean`` (no undeclared effect anywhere) or ``dev_like`` (undeclared effects of
    development size, ``draw_effects``, on the vehicles ``effects_on``: by default every follower,
    the leader clean, as in convoy_dev). effect_kinds: the subset of ``EFFECT_NAMES`` applied.
    Route, site, mountings, lever arms, IMU noise, logging, float spells and follow behaviour are
    drawn the same way for both presets.
    """
    if preset not in PRESETS:
        raise ValueError(f"preset {preset!r}: choose one of {PRESETS}")
    if imu_grade not in IMU_GRADES:
        raise ValueError(f"IMU grade {imu_grade!r}: choose one of {sorted(IMU_GRADES)}")
    unknown = sorted(set(effect_kinds) - set(EFFECT_NAMES))
    if unknown:
        raise ValueError(f"unknown effect kind(s) {unknown}; choose from {list(EFFECT_NAMES)}")
    names = vehicle_names(n_vehicles)
    site = rng_for(seed, "site")
    week = int(site.integers(2200, 2450)) if gps_week is None else int(gps_week)
    tow = float(site.integers(0, int(timebase.SECONDS_PER_WEEK - duration_s - 60))) if start_tow_s is None \
        else float(start_tow_s)
    if not 0 <= tow <= timebase.SECONDS_PER_WEEK - duration_s:
        raise ValueError(f"start time of week {tow} s: the recording must end within the week")
    lla = (math.radians(float(site.uniform(-60.0, 60.0))), math.radians(float(site.uniform(-180.0, 180.0))),
           float(site.uniform(0.0, 2500.0))) if origin_lla is None else tuple(origin_lla)
    yaw0 = float(site.uniform(0.0, 2 * math.pi))
    rr = rng_for(seed, "route-spec")
    route = RouteSpec(duration_s=float(duration_s),
                      max_speed_mps=float(rr.uniform(14.0, 19.0)) if max_speed_mps is None else float(max_speed_mps),
                      max_grade_rad=float(max_grade_rad), roll_per_lat_acc_rad=0.006 if body_roll else 0.0)
    mounts = axis_mountings()
    mount_names = sorted(mounts)
    gnss = GnssSpec()
    effects_on = set(names[1:] if effects_on is None else effects_on)
    bad = sorted(effects_on - set(names))
    if bad:
        raise ValueError(f"effects_on names unknown vehicle(s) {bad}; vehicles are {names}")
    vehicles = []
    for k, name in enumerate(names):
        r = rng_for(seed, f"vehicle:{name}")
        imu_to_body = mounts[mount_names[int(r.integers(0, len(mount_names)))]]
        lever = np.array([round(float(r.uniform(-1.2, 0.8)) / 0.05) * 0.05,
                          round(float(r.uniform(-0.3, 0.3)) / 0.05) * 0.05,
                          round(float(r.uniform(-1.6, -0.4)) / 0.05) * 0.05]) + 0.0
        logging = LoggingModel(min_delay_s=round(float(r.uniform(0.002, 0.008)), 4),
                               jitter_mean_s=float(r.uniform(0.0005, 0.0015)),
                               counter_start_ms=int(r.integers(10_000, 5_000_000)),
                               clock_drift_ppm=float(imu_clock_drift_ppm),
                               tick_ms=int(r.integers(1_000, 100_000_000)))
        spells = []
        if float_spells:
            length = float(r.integers(20, 61)) / 10.0
            start = round(float(r.uniform(0.2, 0.85)) * duration_s, 1)
            spells = [(start, round(min(start + length, duration_s), 1))]
        lane = None
        if k > 0:
            lane = (float(r.uniform(3.0, 5.0)), float(r.uniform(5.0, 12.0)),
                    (-1.0 if r.random() < 0.75 else 1.0) * float(r.uniform(3.0, 3.7)))
        eff = Effects()
        if preset == "dev_like" and name in effects_on:
            eff = draw_effects(seed, name, imu_to_body).without(set(EFFECT_NAMES) - set(effect_kinds))
        vehicles.append(VehicleSpec(
            name=name, imu_to_body=imu_to_body, lever_arm_m=lever, effects=eff, imu_grade=imu_grade,
            imu_rate_hz=float(imu_rate_hz), logging=logging, float_spells_s=spells,
            satellites=int(r.integers(14, 25)), follow_lag_s=round(float(r.uniform(0.8, 1.3)), 2),
            follow_gap_m=round(float(r.uniform(8.0, 12.0)), 2), lane_change=lane))
    return ConvoyParams(seed=int(seed), preset=preset, route=route, vehicles=vehicles, gps_week=week,
                        start_tow_s=tow, origin_lla=lla, yaw0_rad=yaw0, gnss=gnss)
