"""Navigation core: strapdown mechanization and the GNSS/INS error-state EKF.

Public interface::

    from v2xpos.ins import InsFilter, InsConfig
    f = InsFilter(InsConfig(setup={"platform": "car", "imu_to_body": ..., "lever_arm_m": ..., "lever_arm_sd_m": 0.1}))
    f.initialize(t_s, lla, v_ned_mps, rpy_rad)        # optional; else aligned from data
    f.process_imu(t_s, acc_mps2, gyro_rps)
    res = f.update_gnss(t_s, lla, sd_ned_m, fix, vel_ned_mps=None, vel_sd_ned_mps=None)
    f.update_wheel_speed(t_s, speed_mps)
    f.initialized, f.nav_state()

Sources and commands do not call these in their own loops: they push events into the one driver
(``driver.InsDriver``), which orders them and calls the filter.

Module map: ``config`` (``InsConfig``), ``mechanization`` (jitted strapdown), ``ekf`` (state
layout, covariance propagation, gated Kalman update), ``noise`` (process noise, measured IMU
noise), ``updates`` (measurement models: pure builders of H, d, R), ``motion`` (stop detection),
``effects`` (augmentable states), ``static_calibration`` (bias calibration at stops),
``alignment`` (coarse attitude, GNSS course), ``initialization`` (start, alignment, resets),
``imu_path`` (IMU input, chunk steps), ``filter`` (``InsFilter``, which runs the steps),
``outputs`` (``nav_state`` and other outputs),
``consistency`` / ``reported`` (own consistency test, covariance of what is reported),
``driver`` (``InsDriver``: the one event loop that feeds the filter, offline and live),
``profiles`` (one configuration per vehicle and the named profiles), ``replay_engine`` (dataset
through the driver with hooks), ``replay`` / ``replay_metrics`` (the ``v2xpos replay`` run and its
figures), ``calibrated`` (config from a dataset's calibration).
"""
from .config import InsConfig
from .ekf import ATT, BA, BASE_STATES, BG, EFFECT_SIZES, POS, VEL, StateLayout
from .filter import InsFilter
from .static_calibration import StaticBiasEstimate, StaticCalibrationConfig, StaticCalibrator
from .updates import UpdateResult

__all__ = ["InsFilter", "InsConfig", "UpdateResult", "StateLayout", "StaticCalibrator",
           "StaticCalibrationConfig", "StaticBiasEstimate", "POS", "VEL", "ATT", "BG", "BA",
           "BASE_STATES", "EFFECT_SIZES"]
