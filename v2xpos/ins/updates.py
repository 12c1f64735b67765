"""Measurement models and the gated Kalman update of the error-state filter.

Conventions: errors are estimate minus truth (``ekf.py``); every model returns ``H`` and the
prediction-minus-measurement ``d = h(x_est) - z`` so that ``d ~ H dx + noise``. Reported
innovations are ``z - h(x_est)`` (measurement minus prediction).

Models (C = C_nb estimate, l = lever arm in body, w = compensated body rate, v = NED velocity,
R_m = misalignment DCM vehicle <- body, v_b = C^T v):

* GNSS position at the antenna (Groves 2013 eq. 14.121 with our signs), with
  gap = t_meas - latency - (t_stamp + dt) from the state label to the epoch the fix describes:
  h = r + C l + v_IMU * gap;  H_r = I, H_phi = [(C l) x], H_l = C, H_dt = H_lat = -v
  (both shorten the gap).
* GNSS velocity at the antenna: h = v + C (w x l) + a (gap - vel_latency);  H_v = I,
  H_phi = [(C (w x l)) x], H_bg = C [l x], H_l = C [w x], H_dt = H_lat = H_vel_lat = -a.
* Non-holonomic constraint (Shin 2001 sec. 4.3; Dissanayake et al. 2001): the vehicle-frame lateral
  and vertical velocity are zero: h = (R_m C^T v)_{y,z};
  H_v = R_m C^T, H_phi = -R_m C^T [v x], H_mis = -[v_b x].
* Odometer (wheel speed = (1 + s_odo) x forward speed): h = (1 + s_odo) (R_m C^T v)_x;
  H as the NHC rows (x component) times (1 + s_odo), H_s = (R_m C^T v)_x.
* ZUPT: h = v, H_v = I. ZARU: h = w - C^T w_ie, H_bg = -I.

The update is P <- P - K H P, symmetrised (the Joseph form costs two more n^3 products per
update; with the gate and symmetrisation it has not been needed), with a chi-square gate on the
normalised innovation squared NIS = d^T S^-1 d, S = H P H^T + R.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class UpdateResult:
    """Outcome of one measurement update.

    innovation: z - h(x) in the measurement's units and axes; innovation_sd: sqrt(diag(S));
    nis: normalised innovation squared; accepted: False when the chi-square gate rejected it.
    """
    kind: str
    t_s: float
    accepted: bool
    nis: float
    innovation: np.ndarray = field(default_factory=lambda: np.zeros(0))
    innovation_sd: np.ndarray = field(default_factory=lambda: np.zeros(0))
    reason: str = ""
    innovation_cov: np.ndarray | None = None   # S = H P H^T + R


def kalman_update(P: np.ndarray, H: np.ndarray, d: np.ndarray, R: np.ndarray,
                  gate_chi2: float | None, force: bool = False) -> tuple:
    """Gated error-state update. Returns (dx, P_new, nis, S, accepted); dx is None when rejected."""
    PHt = P @ H.T
    S = H @ PHt + R
    try:
        S_inv = np.linalg.inv(S)
    except np.linalg.LinAlgError:
        return None, P, float("inf"), S, False
    nis = float(d @ S_inv @ d)
    if not force and gate_chi2 is not None and (not np.isfinite(nis) or nis > gate_chi2):
        return None, P, nis, S, False
    K = PHt @ S_inv
    dx = K @ d
    P_new = P - K @ PHt.T
    return dx, 0.5 * (P_new + P_new.T), nis, S, True
