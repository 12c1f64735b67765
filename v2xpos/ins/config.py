"""``InsConfig``: every setting of the GNSS/INS filter, with units in the names.

Defaults are for an automotive MEMS IMU and an RTK receiver; docs/ins.md gives the reasoning for
each group (IMU stochastic model, consistency test, initial uncertainty, GNSS measurement model,
vehicle constraints and stops, numerics).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from v2xpos.types import FixStatus

from .effects import DEFAULT_INITIAL_SD, DEFAULT_RANDOM_WALK, PLATFORM_EFFECTS
from .static_calibration import StaticCalibrationConfig

DEFAULT_FIX_SD_SCALE = {FixStatus.FIXED: 1.0, FixStatus.FLOAT: 2.0, FixStatus.DGPS: 2.0,
                        FixStatus.SINGLE: 2.0, FixStatus.DEAD_RECKONING: 10.0, FixStatus.NONE: 10.0}
"""Factor on the receiver's reported position/velocity sd per fix type (receivers are optimistic
about float and code solutions)."""


@dataclass
class InsConfig:
    """Filter configuration. Units in the names; defaults are for an automotive MEMS IMU
    (e.g. ARW ~0.2 deg/sqrt(s) including vehicle vibration, a gyro bias that moves with temperature
    by ~0.05 deg/s over a drive) and an RTK receiver; docs/ins.md gives the reasoning.

    platform: "car" (NHC on), "pedestrian" or "generic" (no vehicle constraints).
    imu_to_body: v_body = imu_to_body @ v_imu (declared nominal mounting).
    lever_arm_m: antenna relative to the IMU in body axes [m]; lever_arm_sd_m its prior 1-sigma.
    effects: extra error states (``ekf.EFFECT_SIZES``); None = the platform default.
    """
    platform: str = "car"
    imu_to_body: np.ndarray = field(default_factory=lambda: np.eye(3))
    lever_arm_m: np.ndarray = field(default_factory=lambda: np.zeros(3))
    lever_arm_sd_m: float = 0.1
    effects: tuple | None = None
    # IMU stochastic model
    gyro_noise_rps_rthz: float = 3e-3
    accel_noise_mps2_rthz: float = 3e-2
    gyro_bias_sd_rps: float = 1e-3
    gyro_bias_tau_s: float = 600.0
    accel_bias_sd_mps2: float = 5e-3
    accel_bias_tau_s: float = 600.0
    gyro_bias_init_sd_rps: float = 0.01
    accel_bias_init_sd_mps2: float = 0.2
    imu_noise_from_data: bool = False             # white-noise densities measured from the samples (ImuNoiseMeter),
    imu_noise_window_s: float = 10.0              # averaged over this time constant, scaled, capped by the two above
    imu_gyro_noise_scale: float = 7.0             # roll/pitch noise = this x the measured body x/y gyro white noise
    imu_yaw_gyro_noise_scale: float = 1.0         # heading noise = this x the measured body z one (docs/integrity.md)
    imu_accel_noise_scale: float = 1.0            # velocity noise = this x the measured accelerometer white noise
    consider_gyro_scale: bool = False             # gyro scale error (sd effect_initial_sd["gyro_scale"]) carried in the
    # covariance as a Schmidt consider state, never estimated: a heading sd that grows with the angle turned
    # (ekf.kalman_update); ignored when gyro_scale is an estimated effect (docs/integrity.md: measured, off by default)
    # own consistency test (consistency.ConsistencyMonitor)
    consistency_window_s: float = 5.0
    consistency_false_alarm_per_hour: float = 1e-3  # of the block NIS and mean tests together (Bonferroni)
    consistency_reverify: bool = True             # a failure is lifted once the evidence is gone (else latched)
    consistency_release_windows: int = 6          # ... i.e. this many consecutive blocks per kind pass at the 1 % level
    verify_detectable_lever_arm_m: float = 0.3    # turning counts while the test would find a lever-arm error this size
    verify_turn_deg: float = 0.0                  # turning that must pass the test before the solution is verified
    fault_tolerant_solution: bool = False         # the set-up hypothesis: its twin, P(H1 | data), the protection level
    undeclared_lever_arm_sd_m: float = 0.5        # horizontal lever-arm sd the twin assumes without the declaration
    alert_limit_m: float = 0.30                   # verified only while the horizontal protection level is within this
    integrity_risk: float = 1e-5                  # the protection level's risk budget (both horizontal axes together)
    setup_fault_prior: float = 1e-3               # P(the declared set-up is wrong) when not verified on an earlier drive
    setup_change_prior: float = 1e-6              # ... when verified on an earlier drive (it changed since)
    setup_verified: bool = False                  # the set-up was verified on an earlier drive ([verification] record)
    integrity_false_alarm_per_hour: float = 1e-3  # of the exclusion test (Bonferroni over its tests in an hour)
    effect_initial_sd: dict = field(default_factory=dict)
    initial_time_offset_s: float = 0.0             # starting value of imu_time_offset (e.g. from calibrate)
    initial_misalignment_rad: np.ndarray = field(default_factory=lambda: np.zeros(3))
    initial_effects: dict = field(default_factory=dict)   # other starting values: imu_clock_drift [s/s],
    # gnss_latency_s, gnss_vel_latency_s, odometer_scale, gyro_scale (3), accel_scale (3)
    effect_random_walk: dict = field(default_factory=dict)
    # initial state uncertainty
    init_vel_sd_mps: float = 0.3
    init_level_sd_rad: float = math.radians(2.0)
    init_yaw_sd_rad: float | None = None          # None: 5 deg car, 20 deg otherwise
    align_min_speed_mps: float | None = None      # None: 1 m/s car, 0.5 m/s otherwise
    # GNSS measurement model
    fix_sd_scale: dict = field(default_factory=lambda: dict(DEFAULT_FIX_SD_SCALE))
    gnss_pos_sd_floor_m: float = 0.01
    gnss_vel_sd_floor_mps: float = 0.03
    gnss_vel_sd_scale: float = 1.0
    use_gnss_velocity: bool = True
    gate_probability: float = 0.9999
    gnss_max_consecutive_rejections: int = 8
    gnss_reset_distance_m: float = 30.0           # a forced fix further than this resets position instead
    # vehicle constraints and stops
    constraint_rate_hz: float = 10.0
    constraints_on_request: bool = False          # NHC/ZUPT only via apply_vehicle_constraints() (calibration replays)
    nhc_sd_mps: tuple = (0.05, 0.5)               # lateral, vertical (body pitch varies with load/braking); docs/ins.md
    nhc_sd_per_yaw_rate_m: float = 1.0            # adds |yaw rate| x 1 m to the lateral sd (IMU off the rear axle)
    nhc_min_speed_mps: float = 0.5
    odometer_sd_mps: float = 0.05
    zupt_sd_mps: float = 0.02
    zaru_sd_rps: float = 2e-3
    static_window_s: float = 0.5
    static_acc_std_max_mps2: float = 0.18
    static_gyro_mean_max_rps: float = 0.005
    static_max_speed_mps: float = 1.0
    static_acc_h_max_mps2: float = 0.2           # horizontal specific force in NED (a stop has none)
    static_max_gnss_speed_mps: float = 0.2
    static_gnss_speed_max_age_s: float = 1.0      # the GNSS speed takes part in stop detection while this recent
    calibration_moving_speed_mps: float = 0.5     # above this filter speed the stop calibrator is told "moving"
    static_calibration: StaticCalibrationConfig = field(default_factory=StaticCalibrationConfig)
    apply_static_calibration: bool = True
    timing_min_speed_mps: float = 1.0             # below it the timing states get no H (noise would pass for signal)
    acc_smoothing_tau_s: float = 0.2              # low-pass of the acceleration used in H (not in nav_state)
    static_start: bool = True                     # start at a stop with the yaw open (see _try_align)
    # numerics
    cov_every: int = 10
    coast_after_s: float = 1.0
    log_residuals: bool = True

    def __post_init__(self) -> None:
        if self.platform not in PLATFORM_EFFECTS:
            raise ValueError(f"platform {self.platform!r} not one of {sorted(PLATFORM_EFFECTS)}")
        self.imu_to_body = np.asarray(self.imu_to_body, float).reshape(3, 3)
        self.lever_arm_m = np.asarray(self.lever_arm_m, float).reshape(3)
        if self.effects is None:
            self.effects = PLATFORM_EFFECTS[self.platform]
        if "gyro_scale" in self.effects:
            self.consider_gyro_scale = False
        self.effect_initial_sd = {**DEFAULT_INITIAL_SD, "lever_arm": self.lever_arm_sd_m, **self.effect_initial_sd}
        self.effect_random_walk = {**DEFAULT_RANDOM_WALK, **self.effect_random_walk}
        if self.init_yaw_sd_rad is None:
            self.init_yaw_sd_rad = math.radians(5.0 if self.platform == "car" else 20.0)
        if self.align_min_speed_mps is None:
            self.align_min_speed_mps = 1.0 if self.platform == "car" else 0.5
