"""The rotation between the axes of two IMU units on one body (their relative mounting).

Two units on one rigid body measure the same angular rate in different axes:
``w_ref = C_ref_ut @ w_ut`` where ``C_ref_ut`` takes vectors from the unit under test (ut) to the
reference unit's axes. It comes either from declared mounting angles or, when the mounting is not
declared, from the data by solving Wahba's problem on angular-rate pairs with the SVD
(Kabsch 1976, Acta Cryst. A32; Markley 1988, J. Astronaut. Sci. 36):

    C = argmin_R  sum_k w_k |a_k - R b_k|^2,   H = sum_k w_k b_k a_k^T = U S V^T,
    C = V diag(1, 1, det(V U^T)) U^T.

Mounting angles are given "in X-Y-Z order" (intrinsic): ``C_body_unit = Rx(a) Ry(b) Rz(c)``
(``v2xpos.rotation.dcm_from_euler_xyz``), the DCM taking vectors from the unit's axes to the
vehicle body axes.
"""
from __future__ import annotations

import numpy as np

from v2xpos.rotation import dcm_from_euler_xyz


def mounting_dcm(angles_xyz_deg: np.ndarray) -> np.ndarray:
    """C_body_unit from mounting angles (a, b, c) [deg] of the intrinsic X-Y-Z sequence."""
    return dcm_from_euler_xyz(np.radians(np.asarray(angles_xyz_deg, float)))


def euler_xyz_deg_from_dcm(C: np.ndarray) -> np.ndarray:
    """Inverse of ``mounting_dcm``: (a, b, c) [deg] with C = Rx(a) Ry(b) Rz(c), b in [-90, 90]."""
    a = np.arctan2(-C[1, 2], C[2, 2])
    b = np.arcsin(np.clip(C[0, 2], -1.0, 1.0))
    c = np.arctan2(-C[0, 1], C[0, 0])
    return np.degrees(np.array([a, b, c]))


def relative_from_mounting(C_body_ref: np.ndarray, C_body_ut: np.ndarray) -> np.ndarray:
    """C_ref_ut = C_body_ref^T C_body_ut (unit under test -> reference unit axes)."""
    return np.asarray(C_body_ref).T @ np.asarray(C_body_ut)


def kabsch_rotation(a: np.ndarray, b: np.ndarray, weights: np.ndarray | None = None,
                    center: bool = True) -> np.ndarray:
    """Rotation C (3x3, det +1) minimising sum_k w_k |a_k - C b_k|^2 (Wahba / Kabsch, SVD).

    a, b: (N, 3) paired vectors (a in the target frame, b in the source frame), e.g. reference
    and unit-under-test angular rates at the same instants; the result is C_target_source.
    center: remove the (weighted) means first, so constant biases do not tilt the fit.
    """
    a = np.asarray(a, float)
    b = np.asarray(b, float)
    if a.shape != b.shape or a.ndim != 2 or a.shape[1] != 3:
        raise ValueError(f"kabsch_rotation: expected two (N, 3) arrays, got {a.shape} and {b.shape}")
    w = np.ones(len(a)) if weights is None else np.asarray(weights, float)
    if center:
        a = a - np.average(a, axis=0, weights=w)
        b = b - np.average(b, axis=0, weights=w)
    H = (b * w[:, None]).T @ a
    return kabsch_from_cross_covariance(H)


def kabsch_from_cross_covariance(H: np.ndarray) -> np.ndarray:
    """Rotation from the accumulated cross-covariance H = sum_k w_k b_k a_k^T (see module doc)."""
    U, _, Vt = np.linalg.svd(H)
    d = 1.0 if np.linalg.det(Vt.T @ U.T) >= 0 else -1.0
    return Vt.T @ np.diag([1.0, 1.0, d]) @ U.T


def kabsch_condition(b: np.ndarray) -> float:
    """Ratio smallest/largest singular value of the centred source vectors (0: rotation about
    one axis only, the fit is not unique about that axis; > ~0.05: well determined)."""
    b = np.asarray(b, float)
    s = np.linalg.svd(b - b.mean(axis=0), compute_uv=False)
    return float(s[-1] / max(s[0], 1e-300))


def principal_rates_rps(b: np.ndarray) -> np.ndarray:
    """RMS of the centred vectors along their three principal directions (singular values /
    sqrt(N)), largest first: the motion available to the fit in each direction."""
    b = np.asarray(b, float)
    return np.linalg.svd(b - b.mean(axis=0), compute_uv=False) / np.sqrt(max(len(b), 1))


def rotate(v: np.ndarray, C: np.ndarray) -> np.ndarray:
    """Rotate (N, 3) row vectors: returns rows C @ v_k."""
    return np.asarray(v, float) @ np.asarray(C).T


def rotation_angle_deg(C: np.ndarray) -> float:
    """Angle of the rotation C [deg] (0 for identity)."""
    return float(np.degrees(np.arccos(np.clip((np.trace(C) - 1.0) / 2.0, -1.0, 1.0))))
