"""The calibration fit's predictor: filter noise settings that match the recording.

Why (docs/calibration.md, "Root cause of the false vertical lever arm"): the batch fit is a
prediction-error method. It is consistent only when the predictor is (close to) the optimal
filter of the true system; with a mistuned filter the fit minimises the prediction errors by any
parameter that changes the filter's *gains*, not only by those that describe the data. A vertical
lever arm on a flat road changes no predicted measurement, but it sets how strongly the horizontal
GNSS position innovations are fed into roll and pitch (``H_att = [C l x]``); with the default
automotive noise (gyro 3e-3 rad/s/sqrt(Hz)) on an IMU whose noise is 35 times lower, each GNSS
epoch jerked the pitch, the NHC rows saw it as ``v dtheta``, and the fit "found" the lever arm
that switched that channel off (convoy_dev B: +1.2 m at 7 sd). So before the fit:

1. IMU white noise from the data itself (``imu_noise_density``);
2. measurement noise of GNSS position and GNSS velocity rescaled so that the filter's own
   innovation covariances S match the innovations it produces (innovation-based adaptive
   estimation, Mehra 1970, IEEE TAC 15(2); Mohamed & Schwarz 1999, J. Geodesy 73).

The vehicle constraints (NHC) keep the filter's declared noise: they are a model of the car, not a
measurement, and their violations are systematic -- the body pitches against its velocity when the
car accelerates or brakes (suspension squat/dive) and slips sideways in curves. Matching the NHC
noise to one drive's innovation rms made the vertical row a near-hard constraint, which the squat
then bent: on drive_0708 the fit absorbed it as an accelerometer x scale of +4.6 % (a pitch of
0.27 deg per m/s^2 looks like ``g x 0.0047 = 4.6 %`` of the acceleration), and applying that made
the outages worse (2.60 m against 2.01 m without it).
"""
from __future__ import annotations

import numpy as np

from v2xpos.ins.config import DEFAULT_FIX_SD_SCALE
from v2xpos.ins.noise import density_from_mean_square, second_differences
from v2xpos.types import ImuData

from .residuals import ResidualLog


def imu_noise_density(imu: ImuData) -> tuple[float, float]:
    """White-noise densities (gyro [rad/s/sqrt(Hz)], accelerometer [m/s^2/sqrt(Hz)]) of a recording.

    From second differences of the samples: for white noise of variance s^2 per sample,
    ``var(x[k+1] - 2 x[k] + x[k-1]) = 6 s^2``, while the vehicle's own motion (smooth at the
    sample rate) contributes ``(x'' dt^2)^2``, negligible. The variance (not a robust scale) is
    used because vibration is heavy-tailed and the filter needs its power; the three axes are
    pooled (the filter's noise is isotropic) and the density is ``s sqrt(dt)``. The same estimator
    runs online per axis in ``v2xpos.ins.noise.ImuNoiseMeter`` (services without this calibration).
    """
    t = np.asarray(imu.t_s, float)
    dt = float(np.median(np.diff(t))) if len(t) > 2 else 0.01
    out = []
    for x in (np.asarray(imu.gyro_rps, float), np.asarray(imu.acc_mps2, float)):
        if len(x) < 10:
            out.append(float("nan"))
            continue
        d2 = second_differences(x)
        out.append(float(density_from_mean_square(float(np.mean(np.var(d2, axis=0))), dt)))
    return out[0], out[1]


def innovation_scale(log: ResidualLog) -> dict[str, float]:
    """Root mean square of the whitened accepted innovations (innovation / sqrt(diag S)) per row
    kind: 1 for a filter whose measurement model matches its innovations."""
    out = {}
    for kind in ("gnss_pos", "gnss_vel"):
        if kind not in log:
            continue
        s = log[kind]
        w = s.innovation / np.where(s.sd > 0, s.sd, np.nan)
        w = w[s.accepted]
        w = w[np.isfinite(w)]
        if len(w) >= 20:
            out[kind] = float(np.sqrt(np.mean(w ** 2)))
    return out


def rescaled_config(config: dict, base: dict, factors: dict[str, float]) -> dict:
    """``config`` with the GNSS position / velocity noise multiplied by its factor (the covariance by
    factor^2: the fix scales and the floors); ``base`` holds the InsConfig defaults of the fields."""
    c = dict(config)
    f = factors
    if "gnss_pos" in f:
        scale = c.get("fix_sd_scale", dict(DEFAULT_FIX_SD_SCALE))
        c["fix_sd_scale"] = {k: v * f["gnss_pos"] for k, v in scale.items()}
        c["gnss_pos_sd_floor_m"] = c.get("gnss_pos_sd_floor_m", base["gnss_pos_sd_floor_m"]) * f["gnss_pos"]
    if "gnss_vel" in f:
        c["gnss_vel_sd_scale"] = c.get("gnss_vel_sd_scale", base["gnss_vel_sd_scale"]) * f["gnss_vel"]
        c["gnss_vel_sd_floor_mps"] = c.get("gnss_vel_sd_floor_mps", base["gnss_vel_sd_floor_mps"]) * f["gnss_vel"]
    return c
