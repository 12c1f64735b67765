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

from dataclasses import dataclass

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
    factor^2: the fix scales and the floors; ``InsConfig`` overrides, group -> fields, the GNSS ones
    in ``gnss``); ``base`` holds the InsConfig defaults of the fields."""
    c = dict(config.get("gnss", {}))
    f = factors
    if "gnss_pos" in f:
        scale = c.get("fix_sd_scale", dict(DEFAULT_FIX_SD_SCALE))
        c["fix_sd_scale"] = {k: v * f["gnss_pos"] for k, v in scale.items()}
        c["gnss_pos_sd_floor_m"] = c.get("gnss_pos_sd_floor_m", base["gnss_pos_sd_floor_m"]) * f["gnss_pos"]
    if "gnss_vel" in f:
        c["gnss_vel_sd_scale"] = c.get("gnss_vel_sd_scale", base["gnss_vel_sd_scale"]) * f["gnss_vel"]
        c["gnss_vel_sd_floor_mps"] = c.get("gnss_vel_sd_floor_mps", base["gnss_vel_sd_floor_mps"]) * f["gnss_vel"]
    return {**config, "gnss": c}


# ------------------------------------------------------------------ Allan deviation at stops
# What the written table's IMU noise must cover. The filter models the gyro as white noise (its
# attitude process noise, ``InsConfig.imu.gyro_noise_rps_rthz``) plus a bias that is a first-order
# Gauss-Markov state (``gyro_bias_sd_rps`` 1e-3 rad/s, ``gyro_bias_tau_s`` 600 s: over seconds a
# rate random walk of 5.8e-5 rad/s/sqrt(s)). The second differences (``imu_noise_density``) see
# only the white part; an outage integrates the error over 15 s, so whatever the Allan deviation
# shows above the white line at tau of seconds (bias instability, a flat floor sigma = 0.664 B;
# rate random walk, slope +1/2; IEEE Std 952-1997 Annex C, El-Sheimy et al. 2008, IEEE TIM 57(1);
# Groves 2013 sec. 4.4) must be in the filter's white noise too, which is integrated over the same
# horizon: the Allan variance at tau is half the mean square change of the tau-averaged rate, i.e.
# of the angle drift from one tau-long interval to the next, so a white density n whose line
# n / sqrt(tau) lies on or above the measured sigma(tau) at every tau up to the horizon predicts
# at least the measured drift there (``AllanAtStops.covering``). The stops of a drive bound the horizon the
# recording can show (tau <= stop / 4); beyond it the Gauss-Markov bias states carry the wander.
# What the recordings' stops show, and when an entry is written: docs/calibration.md, "What the
# IMU noise must cover (Allan deviation at the stops)".
BIAS_INSTABILITY_FACTOR = 0.664
"""sqrt(2 ln 2 / pi): the flat floor of the Allan deviation is 0.664 x the bias instability
(IEEE Std 952-1997, Annex C.1.4; El-Sheimy et al. 2008, Table 1)."""
STOP_MAX_SPEED_MPS = 0.06
"""GNSS horizontal speed (median over ~1 s) below which the vehicle is taken to stand still."""
STOP_EDGE_S = 0.5
"""Trimmed from each end of a stop (the car settling, the GNSS speed lagging)."""
COVER_MIN_TAU_S = 1.0
"""From this cluster time on the Allan deviation is compared with the white-noise line (below it
the second differences measure the white noise directly)."""
EXCESS_Z = 3.0
"""How many sds of its estimate (``AllanAtStops.relative_sd``) the Allan deviation must rise above
the white-noise line before it counts as more than white noise (one-sided 0.13 % per axis and tau:
a white sensor keeps its white noise)."""
CLUSTERS_PER_STOP = 4
"""A stop takes part in the Allan variance at tau only if it is at least this many tau long."""


@dataclass
class AllanAtStops:
    """Overlapping Allan deviation of the IMU at the recording's stops, pooled over stops.

    tau_s: cluster times [s]; gyro_adev_rps / accel_adev_mps2: (len(tau), 3) per IMU axis; terms:
    the number of second differences pooled per tau; clusters: non-overlapping clusters of length
    tau in the stops (sum over stops of floor(samples / m)), which sets the estimate's uncertainty;
    stops_s: the (start, end) GPS times used.
    """
    tau_s: np.ndarray
    gyro_adev_rps: np.ndarray
    accel_adev_mps2: np.ndarray
    terms: np.ndarray
    clusters: np.ndarray
    stops_s: list

    @property
    def stop_time_s(self) -> float:
        return float(sum(b - a for a, b in self.stops_s))

    def white(self, which: str = "gyro") -> float:
        """White-noise density: the Allan deviation at tau = 1 s (slope -1/2 there; IEEE 952 C.1.1),
        interpolated log-log and pooled over the axes as a mean square; NaN without 1 s of data."""
        a = self._adev(which)
        ok = np.all(np.isfinite(a), axis=1)
        if ok.sum() < 2 or self.tau_s[ok][-1] < 1.0:
            return float("nan")
        la = np.array([np.interp(0.0, np.log(self.tau_s[ok]), np.log(a[ok, k])) for k in range(a.shape[1])])
        return float(np.sqrt(np.mean(np.exp(2 * la))))

    def bias_instability(self, which: str = "gyro") -> tuple[float, bool]:
        """(B, bound): per axis the minimum of the Allan deviation over tau / 0.664, the largest
        axis (the filter's bias model is isotropic). ``bound`` is True when the minimum lies at
        the longest tau the stops allow -- the curve was still falling, the flat part was not
        reached, and B is an upper bound of the instability, not a measurement of it."""
        a = self._adev(which)
        ok = np.all(np.isfinite(a), axis=1)
        if not ok.any():
            return float("nan"), True
        a = a[ok]
        k = int(np.argmax(np.min(a, axis=0)))
        i = int(np.argmin(a[:, k]))
        return float(a[i, k] / BIAS_INSTABILITY_FACTOR), bool(i == len(a) - 1)

    def relative_sd(self) -> np.ndarray:
        """Relative 1-sigma of the Allan deviation estimate per tau, ``1 / sqrt(2 (K - 1))`` for K
        non-overlapping clusters (IEEE 952 C.2; the overlapping estimate is somewhat better, so
        this errs on the wide side)."""
        k = np.asarray(self.clusters, float)
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(k > 1, 1.0 / np.sqrt(2.0 * (k - 1.0)), np.inf)

    def covering(self, which: str, white: float, min_tau_s: float = COVER_MIN_TAU_S,
                 z: float = EXCESS_Z) -> tuple[float, float]:
        """(n, rel_sd): the white-noise density whose Allan line ``n / sqrt(tau)`` lies on or above
        the deviation measured at every tau from ``min_tau_s`` on where it rises significantly above
        the Allan line of ``white`` (the density the filter already models): ``max sigma(tau)
        sqrt(tau)`` over the taus and axes where ``sigma > (white / sqrt(tau)) (1 + z rel_sd)``,
        and the relative sd of the deviation that sets it. (NaN, NaN) when nothing rises above
        the white line by ``z`` sds (the white noise covers what the stops resolve) or the stops
        do not reach ``min_tau_s``."""
        a = self._adev(which)
        sel = (self.tau_s >= min_tau_s * (1 - 1e-3)) & np.all(np.isfinite(a), axis=1) & (self.clusters > 1)
        if not sel.any() or not np.isfinite(white):
            return float("nan"), float("nan")
        a, tau, rel = a[sel], self.tau_s[sel], self.relative_sd()[sel]
        excess = a > (white / np.sqrt(tau) * (1.0 + z * rel))[:, None]
        if not excess.any():
            return float("nan"), float("nan")
        cover = np.where(excess, a * np.sqrt(tau)[:, None], 0.0)
        i = int(np.unravel_index(np.argmax(cover), cover.shape)[0])
        return float(np.max(cover)), float(rel[i])

    def _adev(self, which: str) -> np.ndarray:
        return self.gyro_adev_rps if which == "gyro" else self.accel_adev_mps2


def stops(gnss, max_speed_mps: float = STOP_MAX_SPEED_MPS, edge_s: float = STOP_EDGE_S,
          min_s: float = 2.0) -> list[tuple[float, float]]:
    """(start, end) GPS times where the GNSS horizontal speed, median-filtered over about 1 s,
    stays below ``max_speed_mps``, each end trimmed by ``edge_s``; [] without receiver velocities."""
    from scipy.ndimage import median_filter
    if gnss is None or gnss.vel_ned_mps is None or len(gnss.t_s) < 5:
        return []
    t = np.asarray(gnss.t_s, float)
    v = np.hypot(gnss.vel_ned_mps[:, 0], gnss.vel_ned_mps[:, 1])
    rate = 1.0 / max(float(np.median(np.diff(t))), 1e-3)
    still = median_filter(np.nan_to_num(v, nan=np.inf), size=max(3, int(round(rate)) | 1)) < max_speed_mps
    out, i = [], 0
    while i < len(t):
        if not still[i]:
            i += 1
            continue
        j = i
        while j + 1 < len(t) and still[j + 1] and t[j + 1] - t[j] < 2.0 / rate + 0.5:
            j += 1
        a, b = t[i] + edge_s, t[j] - edge_s
        if b - a >= min_s:
            out.append((float(a), float(b)))
        i = j + 1
    return out


def allan_at_stops(imu: ImuData, gnss, taus_s: np.ndarray | None = None) -> AllanAtStops:
    """Overlapping Allan deviation (``v2xpos.ins.noise.allan_sums``) of gyro and accelerometer at
    the recording's stops (``stops``), every stop's second differences pooled per tau.

    The samples' own times are used: the rate is integrated with the actual spacing and the
    integral resampled on an even grid (loggers stamp 8-11 ms apart), so a jittered stamp does not
    read as noise. The constant part of a stop (bias, gravity, earth rate) drops out of the second
    differences."""
    from v2xpos.ins.noise import allan_sums_theta
    t = np.asarray(imu.t_s, float)
    dt = float(np.median(np.diff(t))) if len(t) > 2 else 0.01
    if taus_s is None:
        taus_s = np.array([1, 2, 5, 10, 20, 50, 100, 200, 500, 1000, 2000, 5000]) * 1e-2
    ms = np.unique(np.maximum(1, np.round(np.asarray(taus_s, float) / dt).astype(int)))
    sums = np.zeros((len(ms), 6))
    terms = np.zeros(len(ms), int)
    clusters = np.zeros(len(ms), int)
    segs = stops(gnss)
    x_all = np.hstack((np.asarray(imu.gyro_rps, float), np.asarray(imu.acc_mps2, float)))
    used = []
    for a, b in segs:
        sel = (t >= a) & (t <= b)
        if sel.sum() < 20:
            continue
        ts, xs = t[sel], x_all[sel]
        # integral of the rate with the samples' own spacing, on an even grid
        th = np.vstack((np.zeros((1, 6)), np.cumsum(xs[1:] * np.diff(ts)[:, None], axis=0)))
        grid = np.arange(ts[0], ts[-1], dt)
        thg = np.column_stack([np.interp(grid, ts, th[:, k]) for k in range(6)])
        used.append((float(ts[0]), float(ts[-1])))
        for i, m in enumerate(ms):
            if len(grid) < CLUSTERS_PER_STOP * m:
                continue
            s, n = allan_sums_theta(thg, int(m))
            sums[i] += s
            terms[i] += n
            clusters[i] += len(grid) // int(m)
    tau = ms * dt
    with np.errstate(invalid="ignore", divide="ignore"):
        adev = np.sqrt(sums / (2.0 * tau[:, None] ** 2 * terms[:, None]))
    adev[terms == 0] = np.nan
    return AllanAtStops(tau_s=tau, gyro_adev_rps=adev[:, :3], accel_adev_mps2=adev[:, 3:], terms=terms,
                        clusters=clusters, stops_s=used)
