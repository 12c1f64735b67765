"""IMU-to-GNSS timing and yaw-rate scale from heading increments (no filter involved).

Between two GNSS epochs t_a < t_b the course over ground turns by dpsi_k = psi(t_b) - psi(t_a)
(psi = atan2(v_E, v_N), no side-slip); the vehicle-frame yaw gyro integrates to the same angle
over the same GPS interval. With the IMU stamp of GPS time t being ``t - delta(t)``,
``delta(t) = tau + 1e-6 d (t - t0)`` (tau = IMU offset + GNSS latency, see docs/calibration.md):

    dpsi_k = (1 + s_z) [Psi(t_b - delta_b) - Psi(t_a - delta_a)] + b (t_b - t_a) + e_k

where Psi is the cumulative integral of the vehicle yaw rate over the IMU stamps, s_z the yaw-gyro
scale and b a residual yaw bias. Gauss-Newton on (tau, d, s_z, b) with the analytic Jacobian
(dPsi/dt = omega_z) after a grid search over tau; weights from the course noise
sd(dpsi) = sqrt(2) sd_v / speed; 5-MAD outlier rejection; sd inflated by the lag-1 residual
autocorrelation, (1 + rho) / (1 - rho) (Wilks 2011 eq. 5.12). The course rate differs from the
body yaw rate by 1/cos(pitch) and roll terms (road grade, Groves 2013 eq. 2.56), which
``SCALE_SYSTEMATIC_SD`` accounts for.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from v2xpos.rotation import wrap_pi
from v2xpos.types import GnssData, ImuData

SCALE_SYSTEMATIC_SD = 1.5e-3
"""Course rate vs body yaw rate on graded roads: 1/cos(pitch) - 1 ~ 1e-3 at 4.5 % grade."""


@dataclass
class TimingFit:
    """Estimates and 1-sigma: tau_s (IMU offset + GNSS latency), drift_ppm, gyro_scale_z, yaw
    bias_rps; n pairs used; t_mid_s the mean GPS time of the pairs."""
    tau_s: float
    tau_sd_s: float
    drift_ppm: float
    drift_sd_ppm: float
    gyro_scale_z: float
    gyro_scale_z_sd: float
    bias_rps: float
    n: int
    t_mid_s: float


def course_from_positions(gnss: GnssData) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Course over ground at each GNSS epoch from the central difference of the positions
    (t, psi [rad], horizontal speed [m/s]); receiver velocities are not used because an RTK
    engine may smooth them with a lag."""
    from v2xpos import geo
    r = geo.lla_to_ned(np.asarray(gnss.lla, float), np.asarray(gnss.lla, float)[0])
    t = np.asarray(gnss.t_s, float)
    n = len(t)
    psi = np.full(n, np.nan)
    sp = np.zeros(n)
    if n >= 3:
        d = r[2:] - r[:-2]
        dt = t[2:] - t[:-2]
        ok = (dt > 0) & (dt < 1.2)
        vel = d[:, :2] / np.where(ok, dt, np.inf)[:, None]
        psi[1:-1] = np.where(ok, np.arctan2(vel[:, 1], vel[:, 0]), np.nan)
        sp[1:-1] = np.hypot(vel[:, 0], vel[:, 1])
    return t, psi, sp


def heading_pairs(gnss: GnssData, min_speed_mps: float = 2.0, max_gap_s: float = 0.6,
                  pos_sd_m: float = 0.02, source: str = "positions") -> tuple:
    """(t_a, t_b, dpsi, sd_dpsi) over consecutive GNSS epochs when both are moving; course from
    positions (``course_from_positions``, sd from the position noise over the chord) or, with
    source="velocities", from the receiver's velocities (sd from their sigmas)."""
    if source == "velocities":
        if gnss.vel_ned_mps is None:
            return (np.zeros(0),) * 4
        v = np.asarray(gnss.vel_ned_mps, float)
        t = np.asarray(gnss.t_s, float)
        psi = np.arctan2(v[:, 1], v[:, 0])
        sp = np.hypot(v[:, 0], v[:, 1])
        sd_v = (np.full(len(v), 0.05) if gnss.vel_sd_ned_mps is None
                else np.maximum(np.asarray(gnss.vel_sd_ned_mps, float)[:, :2].max(axis=1), 0.01))
        a, b = np.arange(len(t) - 1), np.arange(1, len(t))
        dt = t[b] - t[a]
        ok = (sp[a] > min_speed_mps) & (sp[b] > min_speed_mps) & (dt > 0) & (dt < max_gap_s)
        a, b = a[ok], b[ok]
        return t[a], t[b], np.asarray(wrap_pi(psi[b] - psi[a]), float), np.hypot(sd_v[a] / sp[a], sd_v[b] / sp[b])
    t, psi, sp = course_from_positions(gnss)
    if len(t) < 4:
        return (np.zeros(0),) * 4
    a, b = np.arange(len(t) - 1), np.arange(1, len(t))
    dt = t[b] - t[a]
    ok = (sp[a] > min_speed_mps) & (sp[b] > min_speed_mps) & (dt > 0) & (dt < max_gap_s) & \
        np.isfinite(psi[a]) & np.isfinite(psi[b])
    a, b = a[ok], b[ok]
    dpsi = wrap_pi(psi[b] - psi[a])
    chord_a = sp[a] * 2 * dt[ok]
    chord_b = sp[b] * 2 * dt[ok]
    sd = np.hypot(np.sqrt(2) * pos_sd_m / chord_a, np.sqrt(2) * pos_sd_m / chord_b)
    return t[a], t[b], np.asarray(dpsi, float), sd


def yaw_integral(imu: ImuData, C_vehicle_imu: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(stamps, vehicle yaw rate [rad/s], cumulative yaw angle [rad], trapezoid) of the IMU."""
    w = np.asarray(imu.gyro_rps, float) @ np.asarray(C_vehicle_imu, float).T
    wz = w[:, 2]
    t = np.asarray(imu.t_s, float)
    cum = np.concatenate([[0.0], np.cumsum(0.5 * (wz[1:] + wz[:-1]) * np.diff(t))])
    return t, wz, cum


def fit_timing(imu: ImuData, gnss: GnssData, C_vehicle_imu: np.ndarray, t0_s: float | None = None,
               tau_search_s: float = 0.5, estimate_drift: bool = True,
               t_range_s: tuple[float, float] | None = None, source: str = "positions") -> TimingFit | None:
    """Estimate (tau, drift, yaw-gyro scale, yaw bias) as in the module docstring.

    t_range_s limits the GNSS pairs to a GPS time interval (e.g. one half of the drive).
    Returns None when fewer than 50 usable pairs exist.
    """
    ta, tb, dpsi, sd = heading_pairs(gnss, source=source)
    if t_range_s is not None:
        keep = (ta >= t_range_s[0]) & (tb <= t_range_s[1])
        ta, tb, dpsi, sd = ta[keep], tb[keep], dpsi[keep], sd[keep]
    t_imu, wz, cum = yaw_integral(imu, C_vehicle_imu)
    t0 = float(t_imu[0]) if t0_s is None else float(t0_s)
    inside = (ta - tau_search_s > t_imu[0]) & (tb + tau_search_s < t_imu[-1])
    ta, tb, dpsi, sd = ta[inside], tb[inside], dpsi[inside], sd[inside]
    if len(ta) < 50:
        return None
    w = 1.0 / sd

    def model_parts(tau: float, d: float):
        da = tau + 1e-6 * d * (ta - t0)
        db = tau + 1e-6 * d * (tb - t0)
        dP = np.interp(tb - db, t_imu, cum) - np.interp(ta - da, t_imu, cum)
        wa = np.interp(ta - da, t_imu, wz)
        wb = np.interp(tb - db, t_imu, wz)
        return dP, wa, wb

    def linear(tau: float, d: float, mask: np.ndarray):
        dP, _, _ = model_parts(tau, d)
        A = np.column_stack([dP, tb - ta]) * w[:, None]
        y = dpsi * w
        coef, *_ = np.linalg.lstsq(A[mask], y[mask], rcond=None)
        res = y - A @ coef
        return coef, res

    mask = np.ones(len(ta), bool)
    grid = np.arange(-tau_search_s, tau_search_s + 1e-9, 0.005)
    costs = []
    for tau in grid:
        _, res = linear(tau, 0.0, mask)
        costs.append(float(res[mask] @ res[mask]))
    tau = float(grid[int(np.argmin(costs))])
    d = 0.0
    theta = None
    for it in range(8):
        coef, res = linear(tau, d, mask)
        scale, bias = coef
        if it in (1, 3):
            mad = np.median(np.abs(res[mask] - np.median(res[mask])))
            mask = np.abs(res) < 5.0 * 1.4826 * max(mad, 1e-12)
        dP, wa, wb = model_parts(tau, d)
        J_tau = -scale * (wb - wa)
        J_d = -scale * 1e-6 * (wb * (tb - t0) - wa * (ta - t0))
        cols = [J_tau, J_d, dP, tb - ta] if estimate_drift else [J_tau, dP, tb - ta]
        J = np.column_stack(cols) * w[:, None]
        step, *_ = np.linalg.lstsq(J[mask], res[mask], rcond=None)
        tau += float(step[0])
        if estimate_drift:
            d += float(step[1])
        theta = J
        if abs(step[0]) < 1e-6:
            break
    coef, res = linear(tau, d, mask)
    scale, bias = coef
    r = res[mask]
    m, k = int(mask.sum()), theta.shape[1]
    s2 = float(r @ r) / max(m - k, 1)
    rho = float(np.corrcoef(r[:-1], r[1:])[0, 1]) if m > 3 else 0.0
    infl = (1 + max(rho, 0.0)) / (1 - min(max(rho, 0.0), 0.95))
    cov = np.linalg.inv(theta[mask].T @ theta[mask]) * max(s2, 1.0) * infl
    sdv = np.sqrt(np.diag(cov))
    i_s = 2 if estimate_drift else 1
    return TimingFit(tau_s=tau, tau_sd_s=float(sdv[0]), drift_ppm=d,
                     drift_sd_ppm=float(sdv[1]) if estimate_drift else float("inf"),
                     gyro_scale_z=float(1.0 / scale - 1.0), gyro_scale_z_sd=float(sdv[i_s]),
                     bias_rps=float(bias), n=m, t_mid_s=float(np.mean(0.5 * (ta + tb)[mask])))


def velocity_lag(imu: ImuData, gnss: GnssData, C_vehicle_imu: np.ndarray) -> tuple[float, float] | None:
    """Lag of the receiver's velocities behind its positions [s] and its sd: the difference of the
    timing fitted with the course from velocities and from positions (same gyro, same epochs)."""
    fp = fit_timing(imu, gnss, C_vehicle_imu, estimate_drift=False)
    fv = fit_timing(imu, gnss, C_vehicle_imu, estimate_drift=False, source="velocities")
    if fp is None or fv is None:
        return None
    return fv.tau_s - fp.tau_s, float(np.hypot(fp.tau_sd_s, fv.tau_sd_s))
