"""Error-state layout and covariance propagation of the GNSS/INS EKF.

Error state (all errors are *estimate minus truth*), base block of 15:

    POS  0..2   dr^n   position error, NED [m]
    VEL  3..5   dv^n   velocity error, NED [m/s]
    ATT  6..8   phi    attitude error, NED [rad], C_nb_est = (I - [phi x]) C_nb
    BG   9..11  db_g   gyro bias error, body [rad/s]
    BA  12..14  db_a   accelerometer bias error, body [m/s^2]

followed by the optional effect blocks of ``effects.py`` in the order they are enabled.

Continuous dynamics (Groves 2013 ch. 14.2 / Shin 2001 ch. 3, written for est-minus-truth errors
and the compensation w = (w~ - b_g)/(1 + s_g), f = (f~ - b_a)/(1 + s_a)):

    d(dr)/dt  = dv
    d(dv)/dt  = [f^n x] phi - C_nb db_a - C_nb diag(f) ds_a - [(2 w_ie + w_en) x] dv + (2 g / R) dr_D e_D
    d(phi)/dt = -[w_in x] phi + C_nb db_g + C_nb diag(w) ds_g
    d(db)/dt  = -db / tau + w_b         (first-order Gauss-Markov)
    effects:   random constants with a small random walk

Covariance propagation: ``mechanization.strapdown_batch`` accumulates A = sum F_k dt_k; every
``cov_every`` samples (and before every update) P <- Phi P Phi^T + Q with Phi = I + A + A^2/2,
Q = Q_c dt_total, split half before and half after the transition (trapezoid); Q_c is
``noise.process_noise_density``.

Measurement update (``kalman_update``; the models that give H, d, R are in ``updates``):
S = H P H^T + R, NIS = d^T S^-1 d against a chi-square gate, K = P H^T S^-1, dx = K d,
P <- P - K H P, symmetrised (the Joseph form costs two more n^3 products per update; with the
gate and symmetrisation it has not been needed). Groves 2013 eqs. 3.29-3.33 (sec. 3.2.2) with
d = h(x_est) - z, so that dx is the error estimate (est minus truth) to subtract.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

POS, VEL, ATT, BG, BA = 0, 3, 6, 9, 12
BASE_STATES = 15

EFFECT_SIZES: dict[str, int] = {
    "lever_arm": 3,          # GNSS antenna relative to the IMU, body [m]
    "imu_time_offset": 1,    # t_gps = t_stamp + dt [s]
    "imu_clock_drift": 1,    # d(dt)/dt [s/s]: the IMU stamps run at (1 - drift) of GPS time
    "misalignment": 3,       # vehicle <- filter body small rotation (roll, pitch, yaw) [rad]
    "gyro_scale": 3,         # per axis, measured = (1 + s) true
    "accel_scale": 3,
    "gnss_latency": 1,       # the GNSS solution stamped t describes t - latency [s]
    "gnss_vel_latency": 1,   # the GNSS velocity stamped t describes t - latency [s] (e.g. a mean over the epoch)
    "odometer_scale": 1,     # wheel speed measured = (1 + s) true
    "rear_axle_distance": 1, # the IMU's distance ahead of the rear axle [m]: its lateral velocity in a turn
    "rear_slip_compliance": 1,  # the rear tyres' slip angle per lateral acceleration [rad per m/s^2]
}

EFFECT_NEEDS: dict[str, str] = {
    "imu_clock_drift": "imu_time_offset",          # the drift moves the time offset (d(dt)/dt = drift)
    "rear_slip_compliance": "rear_axle_distance",  # the NHC's model is v_y = omega (d - k v^2): k is a correction to d
}
"""Effect -> the effect it acts through; one without the other has no column in any measurement."""


def check_effect_states(states: tuple) -> None:
    """ValueError naming the effect when ``states`` holds an unknown effect, or one without the
    effect it acts through (``EFFECT_NEEDS``): such a state would stay at its prior, unseen."""
    for name in states:
        if name not in EFFECT_SIZES:
            raise ValueError(f"unknown effect {name!r}; choose from {sorted(EFFECT_SIZES)}")
        needed = EFFECT_NEEDS.get(name)
        if needed is not None and needed not in states:
            raise ValueError(f"effect {name!r} needs {needed!r} among the states (v2xpos/ins/effects.py); "
                             f"got {tuple(states)}")


@dataclass
class StateLayout:
    """Indices of the error-state blocks; ``index[name]`` for effects, -1 when absent."""
    effects: tuple = ()
    index: dict = field(default_factory=dict)
    n: int = BASE_STATES

    @classmethod
    def build(cls, effects: tuple | list) -> "StateLayout":
        check_effect_states(tuple(effects))
        idx, n = {}, BASE_STATES
        for name in effects:
            if name in idx:
                continue
            idx[name] = n
            n += EFFECT_SIZES[name]
        return cls(effects=tuple(idx), index=idx, n=n)

    def at(self, name: str) -> int:
        return self.index.get(name, -1)

    def kernel_index(self) -> np.ndarray:
        """Block offsets in the order expected by ``mechanization.strapdown_batch``."""
        return np.array([POS, VEL, ATT, BG, BA, self.at("gyro_scale"), self.at("accel_scale")], dtype=np.int64)

    def names(self) -> list[str]:
        out = [f"{b}_{a}" for b in ("pos", "vel", "att", "bg", "ba") for a in "xyz"]
        for name in self.effects:
            k = EFFECT_SIZES[name]
            out += [name] if k == 1 else [f"{name}_{a}" for a in "xyz"[:k]]
        return out


def transition_matrix(A: np.ndarray) -> np.ndarray:
    """Phi = I + A + A^2/2: the second-order transition of the error state over a chunk, A = sum F dt."""
    n = A.shape[0]
    Phi = A @ A
    Phi *= 0.5
    Phi += A
    Phi.flat[::n + 1] += 1.0
    return Phi


def propagate_with_transition(P: np.ndarray, Phi: np.ndarray, q_c: np.ndarray, dt_s: float) -> np.ndarray:
    """P <- Phi (P + Q/2) Phi^T + Q/2 with Q = diag(q_c) dt (trapezoidal process noise), symmetrised."""
    n = P.shape[0]
    Qh = 0.5 * q_c * dt_s
    P1 = P.copy()
    P1.flat[::n + 1] += Qh
    P_new = Phi @ P1 @ Phi.T
    P_new.flat[::n + 1] += Qh
    P_new += P_new.T
    P_new *= 0.5
    return P_new


def propagate_covariance(P: np.ndarray, A: np.ndarray, q_c: np.ndarray, dt_s: float) -> np.ndarray:
    """P <- Phi (P + Q/2) Phi^T + Q/2 with Phi = I + A + A^2/2 and Q = diag(q_c) dt (in place on A: reset)."""
    Phi = transition_matrix(A)
    A[:] = 0.0
    return propagate_with_transition(P, Phi, q_c, dt_s)


def kalman_update(P: np.ndarray, H: np.ndarray, d: np.ndarray, R: np.ndarray,
                  gate_chi2: float | None, force: bool = False, consider: slice | None = None) -> tuple:
    """Gated error-state update (module docstring). Returns (dx, P_new, nis, S, accepted); dx is
    None when rejected: S singular, or NIS non-finite or above ``gate_chi2`` unless ``force``.

    consider: the states carried in the covariance but never estimated (Schmidt 1966, the
    Schmidt-Kalman "consider" filter; Bierman 1977 ch. VIII; Brown & Hwang 2012 sec. 9.2): their
    rows of the gain are 0, so dx is 0 there and their variance never shrinks, while the other
    states' gain and covariance account for their uncertainty through the cross-covariances. With
    that suboptimal gain ``P - K H P`` no longer holds; the covariance is the Joseph form
    ``(I - K H) P (I - K H)^T + K R K^T = P - K H P - P H^T K^T + K S K^T``, exact for any gain."""
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
    if consider is None:
        dx = K @ d
        P_new = P - K @ PHt.T
        return dx, 0.5 * (P_new + P_new.T), nis, S, True
    K[consider] = 0.0
    dx = K @ d
    KHP = K @ PHt.T
    P_new = P - KHP - KHP.T + K @ S @ K.T
    return dx, 0.5 * (P_new + P_new.T), nis, S, True
