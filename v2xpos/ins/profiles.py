"""One filter configuration per vehicle, and the few named profiles a path may choose instead.

A vehicle's filter is configured from what it declares (platform, mounting, lever arm and its
sd), its ``[calibration]`` table (``calibrated.ins_config``) and whether it has wheel speeds. On
top of that, a profile, chosen by name:

* ``service`` (the default everywhere): the filter the services run -- ``ins_config(...,
  service=True)``: the IMU white noise measured online unless the calibration carries it, the
  gyro-scale state, the fault-tolerant twin, the multiple-hypothesis protection level
  (docs/integrity.md). ``v2xpos replay`` and ``v2xpos calibrate`` report it by default, the
  ``recording`` and ``device`` sources run it.
* ``plain``: the same vehicle without the integrity machinery (``service=False``: the
  configured IMU noise, no fault-tolerant solution or protection level, no gyro-scale state) -- what
  ``v2xpos replay`` ran before there was one profile (``replay --profile plain``).
* ``fit``: the declared model exactly, without effect states and without the calibration table
  (``effects={"states": ()}``): calibrate's fit replays (``diagnose.runner``), whose effects are applied to
  the samples by ``diagnose.inject`` instead.

With wheel speeds on a car (``service``, ``plain``) the odometer scale is estimated too.
"""
from __future__ import annotations

from typing import Any

import numpy as np

from .calibrated import ins_config
from .config import InsConfig, overridden

PROFILES = ("service", "plain", "fit")
DEFAULT_PROFILE = "service"


def vehicle_config(platform: str, imu_to_body: np.ndarray, lever_arm_m: np.ndarray, lever_arm_sd_m: float,
                   calibration: Any = None, wheel: bool = False, profile: str = DEFAULT_PROFILE,
                   verification: Any = None, **overrides: Any) -> InsConfig:
    """``InsConfig`` of a vehicle (declared values, calibration table, wheel speeds or not, the
    ``[verification]`` record of its set-up) in the named ``profile`` (module docstring);
    ``overrides``: ``InsConfig`` groups as dicts of some of their fields, applied last."""
    if profile not in PROFILES:
        from v2xpos.schema import did_you_mean
        raise ValueError(f"profile {profile!r} is not one of {list(PROFILES)}{did_you_mean(str(profile), PROFILES)}")
    if profile == "fit":
        return ins_config(platform, imu_to_body, lever_arm_m, lever_arm_sd_m, None,
                          **overridden({"effects": {"states": ()}}, overrides))
    service = profile == "service"
    overrides = overridden({}, overrides)                      # every group as a dict of fields
    if wheel and platform == "car" and "states" not in overrides.get("effects", {}):
        base = ins_config(platform, imu_to_body, lever_arm_m, lever_arm_sd_m, calibration, service=service,
                          verification=verification).effects.states
        if "odometer_scale" not in base:
            overrides = overridden(overrides, {"effects": {"states": tuple(base) + ("odometer_scale",)}})
    return ins_config(platform, imu_to_body, lever_arm_m, lever_arm_sd_m, calibration, service=service,
                      verification=verification, **overrides)


def dataset_config(dataset: Any, profile: str = DEFAULT_PROFILE, **overrides: Any) -> InsConfig:
    """:func:`vehicle_config` of a loaded ``Dataset`` (its declarations, ``[calibration]``, wheel
    speeds and ``[verification]``); an override of a declared value (``setup``: ``platform``,
    ``imu_to_body``, ``lever_arm_m``, ``lever_arm_sd_m``) replaces it."""
    declared = {"platform": dataset.platform, "imu_to_body": dataset.imu_to_body,
                "lever_arm_m": dataset.lever_arm_m, "lever_arm_sd_m": dataset.lever_arm_sd_m}
    overrides = overridden({}, overrides)                      # every group as a dict of fields
    declared.update(overrides.pop("setup", {}))
    return vehicle_config(**declared, calibration=getattr(dataset, "calibration", None),
                          wheel=getattr(dataset, "wheel", None) is not None, profile=profile,
                          verification=getattr(dataset, "verification", None), **overrides)
