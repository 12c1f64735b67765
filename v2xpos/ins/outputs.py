"""What ``InsFilter`` reports: the navigation state, the kinematics at the last sample, the antenna
position, the effect estimates and the signals the diagnosis reads.

``Outputs`` is a base class of ``InsFilter`` holding these methods; they only read the filter's
state (documented in ``filter.py``).
"""
from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from v2xpos import geo
from v2xpos.rotation import euler_from_dcm
from v2xpos.types import FilterReason, FixStatus, NavState

from .consistency import INCONSISTENT, VERIFIED
from .mechanization import COR_BA, COR_BG, COR_SA, COR_SG, NAV_H, NAV_LAT
from .reported import correlations, reported_covariance, reported_jacobian

COAST_AFTER_S = 1.0
"""Without a GNSS update for longer than this the reported fix is DEAD_RECKONING (coasting)."""

if TYPE_CHECKING:
    from .config import InsConfig


class Outputs:
    """Output methods of ``InsFilter`` (module docstring)."""

    cfg: InsConfig

    def kinematics_now(self) -> tuple[np.ndarray, np.ndarray]:
        """Body rate w_nb^b [rad/s] (filter body axes, relative to the local-level frame) and
        kinematic acceleration a^n = dv^n/dt [m/s^2, NED] at the last processed IMU sample.

        From that sample compensated with the current bias and scale estimates,
        w_ib = (w~ - b_g)/(1 + s_g), f = (f~ - b_a)/(1 + s_a):
        w_nb^b = w_ib^b - C_bn (w_ie^n + w_en^n) and
        a^n = C_nb f^b + g^n - (2 w_ie^n + w_en^n) x v^n (the velocity equation, Groves eq. 5.54).
        Instantaneous (no smoothing, no lag); its noise is the sensor's per-sample noise.
        """
        if self._last_raw_f_b is None or not self.initialized:
            w = self._last_w_b.copy() if self._last_raw_w_b is None else \
                self._last_raw_w_b - self.corr[COR_BG:COR_BG + 3]
            return w, self.acc_ned_mps2.copy()
        c = self.corr
        w_ib = (self._last_raw_w_b - c[COR_BG:COR_BG + 3]) / (1.0 + c[COR_SG:COR_SG + 3])
        f_b = (self._last_raw_f_b - c[COR_BA:COR_BA + 3]) / (1.0 + c[COR_SA:COR_SA + 3])
        lat, h = float(self.nav[NAV_LAT]), float(self.nav[NAV_H])
        v = self.nav[3:6]
        w_ie = geo.earth_rate_ned_rps(lat)
        w_en = geo.transport_rate_ned_rps(lat, h, v)
        a_n = self.C_nb @ f_b - np.cross(2.0 * w_ie + w_en, v)
        a_n[2] += geo.normal_gravity_mps2(lat, h)
        return w_ib - self.C_nb.T @ (w_ie + w_en), a_n

    def nav_state(self) -> NavState:
        """Solution at the IMU point at the last processed IMU sample (vehicle axes when
        misalignment is estimated); rate and acceleration from ``kinematics_now`` (independent of
        the covariance cadence ``cov_every``). Standard deviations (and the position's correlation
        coefficients) are those of the reported quantities -- position and velocity at the time
        label, vehicle attitude -- from the last covariance step (``reported``: J P J^T), scaled by
        the windowed NIS ratio of the GNSS position updates when it exceeds 1
        (``ConsistencyMonitor.variance_ratio``: the filter's covariance understates its errors)."""
        Rm = self.misalignment_dcm()
        C_nv = self.C_nb @ Rm.T
        w_nb_b, a_n = self.kinematics_now()
        J = reported_jacobian(self.layout, self.C_nb, self.fx.misalignment_rad, self.nav[3:6], a_n, w_nb_b)
        cov = reported_covariance(self.P, J) * self.consistency.variance_ratio()
        sd = np.sqrt(np.abs(np.diag(cov)))
        coasting = (self.t_s - self.last_gnss_t_s) > COAST_AFTER_S
        fix = FixStatus.DEAD_RECKONING if (coasting and self.initialized) else self.last_fix
        return NavState(t_s=float(self.t_s), lla=self.nav[:3].copy(), v_ned_mps=self.nav[3:6].copy(),
                        acc_body_mps2=C_nv.T @ a_n, rate_body_rps=Rm @ w_nb_b,
                        rpy_rad=euler_from_dcm(C_nv), pos_sd_m=sd[0:3].copy(),
                        vel_sd_mps=sd[3:6].copy(), att_sd_rad=sd[6:9].copy(), fix=fix,
                        attitude_ok=bool(self.heading_known), pos_corr=correlations(cov[0:3, 0:3]),
                        consistent=self.consistency.state != INCONSISTENT,
                        verified=self.consistency.state == VERIFIED,
                        reason=self.integrity_reason(coasting), protection_m=self.protection_m())

    def protection_m(self) -> float:
        """Horizontal protection level of the last integrity test [m] (``integrity``; NaN without
        the set-up hypothesis)."""
        sep = getattr(self, "separation", None)
        return float(sep.protection_m) if sep is not None and sep.active else math.nan

    def integrity_reason(self, coasting: bool = False) -> FilterReason:
        """Why the solution is not verified (``FilterReason``), the first that applies: not started,
        heading pending, coasting, a failed innovation test (which kind), the set-up hypothesis
        favoured by the data (a wrong set-up found, not yet excluded), the protection level above
        the alert limit because of the set-up hypothesis (``integrity``: its share of the PL), of an
        IMU time offset still converging (its share of the fault-free position variance, v^2 sd_dt^2),
        of a receiver that is not RTK fixed, or of anything else."""
        if not self.initialized:
            return FilterReason.ALIGNING
        if not self.heading_known:
            return FilterReason.HEADING_PENDING
        if coasting:
            return FilterReason.COASTING
        mon = self.consistency
        if mon.failed:
            return {"gnss_pos": FilterReason.TEST_POSITION, "gnss_vel": FilterReason.TEST_VELOCITY}.get(
                mon.last_failed_kind, FilterReason.TEST_SEPARATION)
        if mon.state == VERIFIED:
            return FilterReason.OK
        sep = getattr(self, "separation", None)
        if sep is not None and sep.active and sep.fault_probability > 0.5:
            return FilterReason.TEST_SEPARATION
        if sep is not None and sep.active and sep.setup_share > 0.5:
            return FilterReason.SETUP_UNVERIFIED
        i_dt = self.layout.at("imu_time_offset")
        sd_main = (sep.last.get("sd_main_m") if sep is not None else None) or []
        if i_dt >= 0 and len(sd_main) == 2:
            v2 = float(self.nav[3] ** 2 + self.nav[4] ** 2)
            if v2 * float(self.P[i_dt, i_dt]) > 0.5 * (sd_main[0] ** 2 + sd_main[1] ** 2):
                return FilterReason.TIME_OFFSET_CONVERGING
        if self.last_fix < FixStatus.FIXED:
            return FilterReason.RECEIVER_FLOAT
        return FilterReason.PROTECTION_EXCEEDED

    def antenna_lla(self) -> np.ndarray:
        """Current antenna position (lat, lon rad; h m) from the IMU point and the lever arm."""
        Cl = self.C_nb @ self.fx.lever_arm_m
        lat, h = self.nav[NAV_LAT], self.nav[NAV_H]
        r_m, r_n = geo.radii_m(lat)
        return self.nav[:3] + np.array([Cl[0] / (r_m + h), Cl[1] / ((r_n + h) * math.cos(lat)), -Cl[2]])

    def effects_report(self) -> dict:
        out = self.fx.as_dict(self.corr)
        out["sd"] = {name: self.sd(name).tolist() for name in self.layout.effects}
        return out
