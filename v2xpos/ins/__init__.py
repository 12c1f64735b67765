"""Navigation core: strapdown mechanization and the GNSS/INS error-state EKF.

Public interface::

    from v2xpos.ins import InsFilter, InsConfig
    f = InsFilter(InsConfig(platform="car", imu_to_body=..., lever_arm_m=..., lever_arm_sd_m=0.1))
    f.initialize(t_s, lla, v_ned_mps, rpy_rad)        # optional; else aligned from data
    f.process_imu(t_s, acc_mps2, gyro_rps)
    res = f.update_gnss(t_s, lla, sd_ned_m, fix, vel_ned_mps=None, vel_sd_ned_mps=None)
    f.update_wheel_speed(t_s, speed_mps)
    f.initialized, f.nav_state()

Module map: ``mechanization`` (jitted strapdown), ``ekf`` (state layout, covariance propagation),
``updates`` (measurement models, gated update), ``effects`` (augmentable states),
``static_calibration`` (seed 001 stop calibration), ``alignment`` (initial attitude),
``filter`` (the filter class), ``replay`` (the ``v2xpos replay`` command).
"""
from .ekf import ATT, BA, BASE_STATES, BG, EFFECT_SIZES, POS, VEL, StateLayout
from .filter import InsConfig, InsFilter
from .static_calibration import StaticBiasEstimate, StaticCalibrationConfig, StaticCalibrator
from .updates import UpdateResult

__all__ = ["InsFilter", "InsConfig", "UpdateResult", "StateLayout", "StaticCalibrator",
           "StaticCalibrationConfig", "StaticBiasEstimate", "POS", "VEL", "ATT", "BG", "BA",
           "BASE_STATES", "EFFECT_SIZES"]
