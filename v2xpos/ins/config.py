"""``InsConfig``: every setting of the GNSS/INS filter in a few groups, with units in the names.

``InsConfig`` holds one dataclass per concern (the vehicle set-up, the IMU stochastic model, the
consistency test, the integrity model, the effect states, the initial uncertainty, the GNSS
measurement model, the vehicle constraints, stop detection and calibration, numerics); a setting is
read as ``cfg.<group>.<field>``, e.g. ``cfg.imu.gyro_noise_rps_rthz``. A group may be given as its
dataclass or as a dict of some of its fields (the rest keep their defaults), which is how profiles
and callers override a few settings: ``InsConfig(setup={"platform": "car"}, integrity={"alert_limit_m":
0.5})``; ``overridden`` applies such a nested dict to another one.

Defaults are for an automotive MEMS IMU and an RTK receiver; docs/ins.md gives the reasoning for
each group.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, fields
from typing import Any

import numpy as np

from v2xpos.types import FixStatus

from .ekf import check_effect_states
from .effects import DEFAULT_INITIAL_SD, DEFAULT_RANDOM_WALK, PLATFORM_EFFECTS
from .static_calibration import StaticCalibrationConfig

DEFAULT_FIX_SD_SCALE = {FixStatus.FIXED: 1.0, FixStatus.FLOAT: 2.0, FixStatus.DGPS: 2.0,
                        FixStatus.SINGLE: 2.0, FixStatus.DEAD_RECKONING: 10.0, FixStatus.NONE: 10.0}
"""Factor on the receiver's reported position/velocity sd per fix type (receivers are optimistic
about float and code solutions)."""


@dataclass
class VehicleSetup:
    """platform: "car" (NHC on), "pedestrian" or "generic" (no vehicle constraints).
    imu_to_body: v_body = imu_to_body @ v_imu (declared nominal mounting).
    lever_arm_m: antenna relative to the IMU in body axes [m]; lever_arm_sd_m its prior 1-sigma."""
    platform: str = "car"
    imu_to_body: np.ndarray = field(default_factory=lambda: np.eye(3))
    lever_arm_m: np.ndarray = field(default_factory=lambda: np.zeros(3))
    lever_arm_sd_m: float = 0.1


@dataclass
class ImuModel:
    """IMU stochastic model: white noise, first-order Gauss-Markov biases, the online noise meter."""
    gyro_noise_rps_rthz: float = 3e-3
    accel_noise_mps2_rthz: float = 3e-2
    gyro_bias_sd_rps: float = 1e-3
    gyro_bias_tau_s: float = 600.0
    accel_bias_sd_mps2: float = 5e-3
    accel_bias_tau_s: float = 600.0
    gyro_bias_init_sd_rps: float = 0.01
    accel_bias_init_sd_mps2: float = 0.2
    imu_noise_from_data: bool = False             # white-noise densities measured from the samples (ImuNoiseMeter,
    # over noise.NOISE_WINDOW_S), scaled, capped by the two above
    imu_gyro_noise_scale: float = 7.0             # roll/pitch noise = this x the measured body x/y gyro white noise
    imu_yaw_gyro_noise_scale: float = 1.0         # heading noise = this x the measured body z one (docs/integrity.md)
    imu_accel_noise_scale: float = 1.0            # velocity noise = this x the measured accelerometer white noise
    consider_gyro_scale: bool = False             # gyro scale error (sd effects.effect_initial_sd["gyro_scale"])
    # carried in the covariance as a Schmidt consider state, never estimated: a heading sd that grows with the angle turned
    # (ekf.kalman_update); ignored when gyro_scale is an estimated effect (docs/integrity.md: measured, off by default)


@dataclass
class ConsistencyTest:
    """The filter's own consistency test (``consistency.ConsistencyMonitor``) and verification."""
    consistency_window_s: float = 5.0
    consistency_false_alarm_per_hour: float = 1e-3  # of the block NIS and mean tests together (Bonferroni)
    consistency_reverify: bool = True             # a failure is lifted once the evidence is gone (else latched)
    consistency_release_windows: int = 6          # ... i.e. this many consecutive blocks per kind pass at the 1 % level
    verify_detectable_lever_arm_m: float = 0.3    # turning counts while the test would find a lever-arm error this size
    verify_turn_deg: float = 0.0                  # turning that must pass the test before the solution is verified


@dataclass
class IntegrityModel:
    """The set-up hypothesis (fault-tolerant twin), its priors and the protection level (docs/integrity.md)."""
    fault_tolerant_solution: bool = False         # the set-up hypothesis: its twin, P(H1 | data), the protection level
    undeclared_lever_arm_sd_m: float = 0.5        # horizontal lever-arm sd the twin assumes without the declaration
    alert_limit_m: float = 0.30                   # verified only while the horizontal protection level is within this
    integrity_risk: float = 1e-5                  # the protection level's risk budget (both horizontal axes together)
    setup_fault_prior: float = 1e-3               # P(the declared set-up is wrong) when not verified on an earlier drive
    setup_change_prior: float = 1e-6              # ... when verified on an earlier drive (it changed since)
    setup_verified: bool = False                  # the set-up was verified on an earlier drive ([verification] record)
    integrity_false_alarm_per_hour: float = 1e-3  # of the exclusion test (Bonferroni over its tests in an hour)


@dataclass
class EffectStates:
    """Extra error states (``ekf.EFFECT_SIZES``; ``states`` None = the platform default), their
    prior sds, random walks (``effects.DEFAULT_*`` fill what is not given) and starting values."""
    states: tuple | None = None
    effect_initial_sd: dict = field(default_factory=dict)
    initial_time_offset_s: float = 0.0             # starting value of imu_time_offset (e.g. from calibrate)
    align_time_at_drive_off: bool = True           # the time offset from a drive-off's onset (driveoff_timing)
    initial_misalignment_rad: np.ndarray = field(default_factory=lambda: np.zeros(3))
    initial_effects: dict = field(default_factory=dict)   # other starting values: imu_clock_drift [s/s],
    # gnss_latency_s, gnss_vel_latency_s, odometer_scale, gyro_scale (3), accel_scale (3)
    effect_random_walk: dict = field(default_factory=dict)


@dataclass
class InitialUncertainty:
    """Initial state uncertainty and alignment (a start at a stop leaves the yaw open: ``_try_align``)."""
    init_vel_sd_mps: float = 0.3
    init_level_sd_rad: float = math.radians(2.0)
    start_roll_sd_rad: float | None = math.radians(2.0)   # the vehicle's roll at a start, from level: road
    # cross slope (docs/ins.md, Initialisation); with the misalignment state, the mounting's roll learns it (None: not used)
    init_yaw_sd_rad: float | None = None          # None: 5 deg car, 90 deg pedestrian, 20 deg otherwise
    align_min_speed_mps: float | None = None      # None: 1 m/s car, 0.5 m/s otherwise


@dataclass
class GnssModel:
    """GNSS measurement model: sd scales and floors, the gate, rejections and resets, timing."""
    fix_sd_scale: dict = field(default_factory=lambda: dict(DEFAULT_FIX_SD_SCALE))
    gnss_pos_sd_floor_m: float = 0.01
    gnss_vel_sd_floor_mps: float = 0.03
    gnss_vel_sd_scale: float = 1.0
    use_gnss_velocity: bool = True
    gate_probability: float = 0.9999
    gnss_max_consecutive_rejections: int = 8
    timing_min_speed_mps: float = 1.0             # below it the timing states get no H (noise would pass for signal)


@dataclass
class VehicleConstraints:
    """When the non-holonomic and zero-velocity / zero-angular-rate pseudo-measurements run (their
    noise: ``updates.NHC_SD_MPS``, ``ZUPT_SD_MPS``, ``ZARU_SD_RPS``, ``ODOMETER_SD_MPS``)."""
    constraint_rate_hz: float = 10.0
    constraints_on_request: bool = False          # NHC/ZUPT only via apply_vehicle_constraints() (calibration replays)


@dataclass
class Stops:
    """Stop detection (``motion``) and the bias calibration at stops (``static_calibration``)."""
    static_window_s: float = 0.5
    static_acc_std_max_mps2: float = 0.18
    static_gyro_mean_max_rps: float = 0.005
    static_max_speed_mps: float = 1.0
    static_acc_h_max_mps2: float = 0.2           # horizontal specific force in NED (a stop has none)
    static_max_gnss_speed_mps: float = 0.2
    static_gnss_speed_max_age_s: float = 1.0      # the GNSS speed takes part in stop detection while this recent
    static_calibration: StaticCalibrationConfig = field(default_factory=StaticCalibrationConfig)
    apply_static_calibration: bool = True


@dataclass
class Numerics:
    """Covariance propagation cadence (samples per covariance step, docs/ins.md)."""
    cov_every: int = 10


GROUPS: dict[str, type] = {"setup": VehicleSetup, "imu": ImuModel, "consistency": ConsistencyTest,
                           "integrity": IntegrityModel, "effects": EffectStates, "initial": InitialUncertainty,
                           "gnss": GnssModel, "constraints": VehicleConstraints, "stops": Stops,
                           "numerics": Numerics}
"""Group name -> its dataclass: the top level of ``InsConfig``."""


def _group(name: str, value: Any) -> Any:
    """``value`` as the dataclass of group ``name``: a dict of some of its fields (an unknown field
    rejected with a "did you mean") or the dataclass itself."""
    cls = GROUPS[name]
    if isinstance(value, cls):
        return value
    if not isinstance(value, dict):
        raise TypeError(f"InsConfig.{name}: expected {cls.__name__} or a dict of its fields, "
                        f"got {type(value).__name__}")
    from v2xpos.schema import check_keys
    check_keys(value, tuple(f.name for f in fields(cls)), f"InsConfig.{name}", TypeError)
    return cls(**value)


def overridden(base: dict, overrides: dict) -> dict:
    """``base`` (group name -> dict of fields) with ``overrides`` (the same shape) applied field by
    field; the dicts of ``base`` are copied, not changed."""
    out = {g: dict(v) for g, v in base.items()}
    for g, v in overrides.items():
        if isinstance(v, GROUPS.get(g, ())):
            v = {f.name: getattr(v, f.name) for f in fields(v)}
        out.setdefault(g, {}).update(v)
    return out


@dataclass
class InsConfig:
    """Filter configuration in groups (module docstring; ``GROUPS``). Defaults are for an automotive
    MEMS IMU (e.g. ARW ~0.2 deg/sqrt(s) including vehicle vibration, a gyro bias that moves with
    temperature by ~0.05 deg/s over a drive) and an RTK receiver; docs/ins.md gives the reasoning."""
    setup: VehicleSetup = field(default_factory=VehicleSetup)
    imu: ImuModel = field(default_factory=ImuModel)
    consistency: ConsistencyTest = field(default_factory=ConsistencyTest)
    integrity: IntegrityModel = field(default_factory=IntegrityModel)
    effects: EffectStates = field(default_factory=EffectStates)
    initial: InitialUncertainty = field(default_factory=InitialUncertainty)
    gnss: GnssModel = field(default_factory=GnssModel)
    constraints: VehicleConstraints = field(default_factory=VehicleConstraints)
    stops: Stops = field(default_factory=Stops)
    numerics: Numerics = field(default_factory=Numerics)

    def __post_init__(self) -> None:
        for name in GROUPS:
            setattr(self, name, _group(name, getattr(self, name)))
        s, e = self.setup, self.effects
        if s.platform not in PLATFORM_EFFECTS:
            raise ValueError(f"setup.platform {s.platform!r} not one of {sorted(PLATFORM_EFFECTS)}")
        s.imu_to_body = np.asarray(s.imu_to_body, float).reshape(3, 3)
        s.lever_arm_m = np.asarray(s.lever_arm_m, float).reshape(3)
        if e.states is None:
            e.states = PLATFORM_EFFECTS[s.platform]
        check_effect_states(tuple(e.states))
        if "gyro_scale" in e.states:
            self.imu.consider_gyro_scale = False
        e.effect_initial_sd = {**DEFAULT_INITIAL_SD, "lever_arm": s.lever_arm_sd_m, **e.effect_initial_sd}
        e.effect_random_walk = {**DEFAULT_RANDOM_WALK, **e.effect_random_walk}
        i = self.initial
        if i.init_yaw_sd_rad is None:
            i.init_yaw_sd_rad = math.radians({"car": 5.0, "pedestrian": 90.0}.get(s.platform, 20.0))
        if i.align_min_speed_mps is None:
            i.align_min_speed_mps = 1.0 if s.platform == "car" else 0.5
