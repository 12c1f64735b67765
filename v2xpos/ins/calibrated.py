"""The filter configuration of a calibrated vehicle: declared values + a ``[calibration]`` table.

One function, :func:`ins_config`, used by ``v2xpos replay``, ``v2xpos calibrate``, the services'
``recording`` and ``device`` sources and any live vehicle config, so that a calibration is applied
the same way to a recording and to a live stream: it never rewrites samples, it sets the filter's
mounting, lever arm and the *starting values and 1-sigma* of its own effect states
(``InsConfig.effects.initial_time_offset_s``, ``initial_misalignment_rad``, ``initial_effects``,
``effect_initial_sd``), which the filter then keeps refining online within those sds.

Conventions are those of ``v2xpos calibrate`` and ``v2xpos.datasets.calibration`` (every entry is
a correction to what the descriptor declares, not a total):

* mounting: ``v_vehicle = R imu_to_body v_imu`` with ``R = Rz(yaw) Ry(pitch) Rx(roll)`` from
  ``imu_misalignment_deg``; the calibrated mounting ``R imu_to_body`` becomes the filter's body
  frame, so that the filter body *is* the vehicle frame (the lever arm and the scale factors are
  given in vehicle axes) and the filter's misalignment state starts at zero with the calibration's
  sd (a residual correction);
* lever arm: ``declared + gnss_lever_arm_m`` [vehicle frame, m], per-axis sd = the calibration's;
* IMU time: ``t_gps = t_stamp + imu_time_offset_s + 1e-6 imu_clock_drift_ppm (t - t_start)``;
  the filter integrates the drift from its own start (for a recording that starts within seconds
  of the first stamp the difference is ``drift x seconds``, e.g. 50 ppm x 5 s = 0.25 ms);
* GNSS latency: a solution tagged t is valid at ``t - gnss_latency_s``;
* scale factors: ``measured = (1 + s) true`` per vehicle axis (the filter's correction vector);
* IMU white noise (``imu_gyro_noise_rps_rthz``, ``imu_accel_noise_mps2_rthz``, measured by
  ``calibrate`` from the samples): the filter's process noise instead of its automotive default;
  with ``imu_gyro_allan_rps_rthz`` / ``imu_accel_allan_mps2_rthz`` (the white density whose Allan
  line covers the Allan deviation measured at the recording's stops for tau >= 1 s,
  ``v2xpos.diagnose.tuning.AllanAtStops``) the larger of the two, before the margin and cap below.
  A filter whose attitude noise is far above the sensor's (e.g. 3e-3 against 8.7e-5 rad/s/sqrt(Hz))
  lets every GNSS epoch move its roll, pitch and heading; for two cars 10-27 m apart that heading
  noise was most of the relative error (convoy-kind recording: 0.053 m with the defaults, 0.024 m
  with both vehicles' measured noise).

An entry's sd of 0 makes the corresponding state exact (zero initial variance).
"""
from __future__ import annotations

from typing import Any

import numpy as np

from v2xpos.rotation import dcm_from_euler

from .effects import PLATFORM_EFFECTS
from .config import ImuModel, InsConfig, overridden

_TIMING_STATES = ("imu_time_offset", "imu_clock_drift")


def _vec(v: Any) -> np.ndarray:
    return np.asarray(v, float).reshape(3)


def ins_config(platform: str, imu_to_body: np.ndarray, lever_arm_m: np.ndarray, lever_arm_sd_m: float,
               calibration: Any = None, service: bool = False, verification: Any = None,
               **overrides: Any) -> InsConfig:
    """``InsConfig`` of a vehicle from its declared mounting and antenna lever arm and an optional
    ``CalibrationTable`` (``v2xpos.datasets.calibration``; None = declared values only) and an
    optional ``VerificationRecord`` (``v2xpos.datasets.verification``: a set-up verified on an earlier
    drive starts with the prior of a change since, ``InsConfig.integrity.setup_change_prior``).

    platform: "car", "pedestrian" or anything else (-> "generic"); imu_to_body: declared nominal
    ``v_body = imu_to_body v_imu``; lever_arm_m: declared antenna position from the IMU [m, vehicle
    frame x fwd, y right, z down] with 1-sigma lever_arm_sd_m; overrides: ``InsConfig`` groups, each a
    dict of some of its fields (they win over the calibration field by field, e.g. ``effects={"states":
    ()}`` for a filter without effect states; ``config.overridden``).
    service: the filter of a service whose states feed the master's results (docs/integrity.md):
    the IMU white noise is measured online from the samples (``v2xpos.ins.noise.ImuNoiseMeter``)
    unless the calibration carries the noise measured offline by the same estimator -- that one
    wins, it was tuned together with the rest of the table --, a failed consistency test
    re-opens a verified set-up (``InsFilter._on_inconsistency``) and the filter carries the set-up
    hypothesis whose protection level verifies it (``integrity.FaultTolerantSolution``).
    """
    plat = platform if platform in ("car", "pedestrian") else "generic"
    B = np.asarray(imu_to_body, float).reshape(3, 3)
    kw: dict[str, dict[str, Any]] = {"setup": dict(platform=plat, imu_to_body=B, lever_arm_m=_vec(lever_arm_m),
                                                   lever_arm_sd_m=float(lever_arm_sd_m))}
    if calibration is not None and calibration.effects:
        kw = overridden(kw, _calibrated_fields(plat, B, _vec(lever_arm_m), float(lever_arm_sd_m), calibration))
    imu, effects = kw.setdefault("imu", {}), kw.setdefault("effects", {})
    integ = kw.setdefault("integrity", {})
    if verification is not None and getattr(verification, "verified", False):
        integ["setup_verified"] = True          # verified on an earlier drive (``datasets.verification``)
    if service:
        imu["imu_noise_from_data"] = "gyro_noise_rps_rthz" not in imu and "accel_noise_mps2_rthz" not in imu
        integ["fault_tolerant_solution"] = True  # the set-up hypothesis and the protection level
        # the heading error of a gyro scale error grows with the angle turned: estimated, from the
        # calibration's value and sd or the datasheet-class prior (docs/integrity.md)
        states = tuple(effects.get("states") or PLATFORM_EFFECTS[plat])
        effects["states"] = states + (("gyro_scale",) if "gyro_scale" not in states else ())
    # The calibration's noise is the sensor's white noise, as the online meter measures it; every
    # filter that runs with the table takes the same margin over it and the same cap
    # (docs/integrity.md, "The IMU noise behind it"): the bare measured noise leaves out what the
    # white-noise figure does not hold (vibration, bias instability, the integration of a vehicle's
    # motion), so a filter given it is overconfident in its IMU -- the calibrated convoy_dev leader
    # failed its own consistency test and was never VALID, and on generated recordings with nothing
    # undeclared the outage error after calibration was several times the one before
    # (docs/calibration.md, Known shortfalls).
    for key, scale in (("gyro_noise_rps_rthz", "imu_gyro_noise_scale"),
                       ("accel_noise_mps2_rthz", "imu_accel_noise_scale")):
        if key in imu:
            imu[key] = min(getattr(ImuModel, scale) * imu[key], getattr(ImuModel, key))
    overrides = overridden({}, overrides)                      # every group as a dict of fields
    over = dict(overrides.get("effects", {}))
    for key in ("effect_initial_sd", "initial_effects"):     # merged with the calibration's, entry by entry
        if key in over and key in effects:
            over[key] = {**effects[key], **over[key]}
    return InsConfig(**overridden(kw, {**overrides, **({"effects": over} if over else {})}))


def _calibrated_fields(platform: str, B: np.ndarray, lever: np.ndarray, lever_sd: float, cal: Any) -> dict:
    """The groups of ``InsConfig`` a calibration table sets (module docstring)."""
    eff = cal.effects
    setup: dict[str, Any] = {}
    imu: dict[str, Any] = {}
    sd0: dict[str, Any] = {}
    init: dict[str, Any] = {}
    time_offset_s = None
    states = list(PLATFORM_EFFECTS[platform])
    if "imu_misalignment_deg" in eff:
        e = eff["imu_misalignment_deg"]
        setup["imu_to_body"] = dcm_from_euler(*np.radians(_vec(e.value))) @ B
        sd0["misalignment"] = np.radians(_vec(e.sd))
    if "gnss_lever_arm_m" in eff:
        e = eff["gnss_lever_arm_m"]
        setup["lever_arm_m"] = lever + _vec(e.value)
        sd = _vec(e.sd)
        setup["lever_arm_sd_m"] = float(np.max(sd))
        sd0["lever_arm"] = sd
    if "imu_time_offset_s" in eff:
        e = eff["imu_time_offset_s"]
        time_offset_s = float(e.value)
        sd0["imu_time_offset"] = float(e.sd)
    if "imu_clock_drift_ppm" in eff:
        e = eff["imu_clock_drift_ppm"]
        init["imu_clock_drift"] = 1e-6 * float(e.value)
        sd0["imu_clock_drift"] = 1e-6 * float(e.sd)
        if float(e.value) != 0.0:
            # the filter applies a drift only through its timing states (``InsFilter._flush_covariance``)
            states += [s for s in _TIMING_STATES if s not in states]
    if "gnss_latency_s" in eff:
        e = eff["gnss_latency_s"]
        init["gnss_latency_s"] = float(e.value)
        sd0["gnss_latency"] = float(e.sd)
    for name in ("gyro_scale", "accel_scale"):
        if name in eff:
            init[name] = _vec(eff[name].value)
            sd0[name] = _vec(eff[name].sd)
    for keys, field_name in ((("imu_gyro_noise_rps_rthz", "imu_gyro_allan_rps_rthz"), "gyro_noise_rps_rthz"),
                             (("imu_accel_noise_mps2_rthz", "imu_accel_allan_mps2_rthz"), "accel_noise_mps2_rthz")):
        # the larger of the white noise (second differences) and the density whose Allan line
        # covers the deviation measured at the stops (``v2xpos.diagnose.tuning.AllanAtStops``)
        v = [float(eff[k].value) for k in keys if k in eff and float(eff[k].value) > 0]
        if v:
            imu[field_name] = max(v)
    effects = {"states": tuple(states), "effect_initial_sd": sd0, "initial_effects": init}
    if time_offset_s is not None:
        effects["initial_time_offset_s"] = time_offset_s
    return {"setup": setup, "imu": imu, "effects": effects}


def dataset_ins_config(dataset: Any, service: bool = False, **overrides: Any) -> InsConfig:
    """:func:`ins_config` of a loaded ``Dataset`` (its declared values and ``Dataset.calibration``)."""
    return ins_config(dataset.platform, dataset.imu_to_body, dataset.lever_arm_m, dataset.lever_arm_sd_m,
                      getattr(dataset, "calibration", None), service=service,
                      verification=getattr(dataset, "verification", None), **overrides)

