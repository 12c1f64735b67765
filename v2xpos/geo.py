"""WGS84 Earth model: LLA / ECEF / local NED and ENU, radii of curvature, normal gravity, Earth rate.

Conventions
-----------
* Geodetic coordinates ``lla`` are ``(lat_rad, lon_rad, h_m)`` with ellipsoidal height, unless a
  function name says ``_deg``.
* NED = north, east, down; ENU = east, north, up. Both are local-level frames tangent to the
  ellipsoid at a reference point.
* ``C_en`` rotates a vector from ECEF to NED: ``v_ned = C_en @ v_ecef``.

Sources: NIMA TR8350.2 (WGS84 constants, Somigliana gravity); Groves, *Principles of GNSS,
Inertial, and Multisensor Integrated Navigation Systems*, 2nd ed. (2013), ch. 2 (eqs. 2.105-2.106
radii, 2.111-2.113 ECEF<->LLA, 2.134 gravity with height), ch. 5 (transport rate, eq. 5.44).
"""
from __future__ import annotations

import numpy as np

# WGS84 defining constants (TR8350.2, table 3.1)
A_M = 6378137.0                      # semi-major axis [m]
F = 1.0 / 298.257223563              # flattening
E2 = F * (2.0 - F)                   # first eccentricity squared
B_M = A_M * (1.0 - F)                # semi-minor axis [m]
OMEGA_IE_RPS = 7.292115e-5           # Earth rotation rate [rad/s]
GM_M3PS2 = 3.986004418e14            # gravitational constant [m^3/s^2]
# Somigliana normal gravity (TR8350.2 eq. 4-1)
GAMMA_E_MPS2 = 9.7803253359          # equatorial gravity [m/s^2]
GAMMA_K = 0.00193185265241           # Somigliana constant
G0_MPS2 = 9.80665                    # standard gravity, used for g -> m/s^2 conversions


def radii_m(lat_rad: float | np.ndarray) -> tuple:
    """Meridian radius R_M and prime-vertical radius R_N [m] (Groves eqs. 2.105, 2.106)."""
    s2 = np.sin(lat_rad) ** 2
    w = 1.0 - E2 * s2
    r_n = A_M / np.sqrt(w)
    r_m = A_M * (1.0 - E2) / w ** 1.5
    return r_m, r_n


def normal_gravity_mps2(lat_rad: float | np.ndarray, h_m: float | np.ndarray) -> float | np.ndarray:
    """Magnitude of normal gravity [m/s^2] at latitude and ellipsoidal height.

    Somigliana on the ellipsoid (TR8350.2 eq. 4-1) with the second-order free-air height
    correction (TR8350.2 eq. 4-3).
    """
    s2 = np.sin(lat_rad) ** 2
    g0 = GAMMA_E_MPS2 * (1.0 + GAMMA_K * s2) / np.sqrt(1.0 - E2 * s2)
    m = OMEGA_IE_RPS ** 2 * A_M ** 2 * B_M / GM_M3PS2
    return g0 * (1.0 - 2.0 / A_M * (1.0 + F + m - 2.0 * F * s2) * h_m + 3.0 * h_m ** 2 / A_M ** 2)


def gravity_ned_mps2(lat_rad: float, h_m: float) -> np.ndarray:
    """Normal gravity vector in NED [m/s^2] (down component only; deflection neglected)."""
    return np.array([0.0, 0.0, normal_gravity_mps2(lat_rad, h_m)])


def earth_rate_ned_rps(lat_rad: float) -> np.ndarray:
    """Earth rotation rate omega_ie resolved in NED [rad/s] (Groves eq. 2.123)."""
    return np.array([OMEGA_IE_RPS * np.cos(lat_rad), 0.0, -OMEGA_IE_RPS * np.sin(lat_rad)])


def transport_rate_ned_rps(lat_rad: float, h_m: float, v_ned_mps: np.ndarray) -> np.ndarray:
    """Transport rate omega_en resolved in NED [rad/s] (Groves eq. 5.44)."""
    r_m, r_n = radii_m(lat_rad)
    vn, ve = v_ned_mps[0], v_ned_mps[1]
    return np.array([ve / (r_n + h_m), -vn / (r_m + h_m), -ve * np.tan(lat_rad) / (r_n + h_m)])


def lla_to_ecef(lla: np.ndarray) -> np.ndarray:
    """Geodetic (lat_rad, lon_rad, h_m) -> ECEF [m] (Groves eq. 2.112). Accepts (3,) or (N, 3)."""
    lla = np.asarray(lla, dtype=float)
    lat, lon, h = lla[..., 0], lla[..., 1], lla[..., 2]
    _, r_n = radii_m(lat)
    cl = np.cos(lat)
    x = (r_n + h) * cl * np.cos(lon)
    y = (r_n + h) * cl * np.sin(lon)
    z = (r_n * (1.0 - E2) + h) * np.sin(lat)
    return np.stack([x, y, z], axis=-1)


def ecef_to_lla(r_ecef_m: np.ndarray) -> np.ndarray:
    """ECEF [m] -> geodetic (lat_rad, lon_rad, h_m), closed form of Heikkinen (1982).

    Accurate to well below a millimetre for terrestrial heights. Accepts (3,) or (N, 3).
    """
    r = np.asarray(r_ecef_m, dtype=float)
    x, y, z = r[..., 0], r[..., 1], r[..., 2]
    ep2 = (A_M ** 2 - B_M ** 2) / B_M ** 2
    p = np.hypot(x, y)
    ff = 54.0 * B_M ** 2 * z ** 2
    gg = p ** 2 + (1.0 - E2) * z ** 2 - E2 * (A_M ** 2 - B_M ** 2)
    c = E2 ** 2 * ff * p ** 2 / gg ** 3
    s = np.cbrt(1.0 + c + np.sqrt(c ** 2 + 2.0 * c))
    k = s + 1.0 + 1.0 / s
    pp = ff / (3.0 * k ** 2 * gg ** 2)
    q = np.sqrt(1.0 + 2.0 * E2 ** 2 * pp)
    r0 = -(pp * E2 * p) / (1.0 + q) + np.sqrt(
        0.5 * A_M ** 2 * (1.0 + 1.0 / q) - pp * (1.0 - E2) * z ** 2 / (q * (1.0 + q)) - 0.5 * pp * p ** 2)
    u = np.sqrt((p - E2 * r0) ** 2 + z ** 2)
    v = np.sqrt((p - E2 * r0) ** 2 + (1.0 - E2) * z ** 2)
    z0 = B_M ** 2 * z / (A_M * v)
    h = u * (1.0 - B_M ** 2 / (A_M * v))
    lat = np.arctan2(z + ep2 * z0, p)
    lon = np.arctan2(y, x)
    return np.stack([lat, lon, h], axis=-1)


def dcm_ecef_to_ned(lat_rad: float, lon_rad: float) -> np.ndarray:
    """C_en: rotates ECEF vectors into the NED frame at (lat, lon) (Groves eq. 2.150)."""
    sl, cl = np.sin(lat_rad), np.cos(lat_rad)
    so, co = np.sin(lon_rad), np.cos(lon_rad)
    return np.array([[-sl * co, -sl * so, cl],
                     [-so, co, 0.0],
                     [-cl * co, -cl * so, -sl]])


NED_TO_ENU = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
"""Permutation taking a NED vector to ENU (its own inverse)."""


def lla_to_ned(lla: np.ndarray, lla_ref: np.ndarray) -> np.ndarray:
    """Geodetic points -> NED [m] relative to ``lla_ref`` (exact, through ECEF). (3,) or (N, 3)."""
    d = lla_to_ecef(lla) - lla_to_ecef(lla_ref)
    return d @ dcm_ecef_to_ned(lla_ref[0], lla_ref[1]).T


def ned_to_lla(r_ned_m: np.ndarray, lla_ref: np.ndarray) -> np.ndarray:
    """NED [m] relative to ``lla_ref`` -> geodetic points (exact, through ECEF). (3,) or (N, 3)."""
    r_e = np.asarray(r_ned_m, dtype=float) @ dcm_ecef_to_ned(lla_ref[0], lla_ref[1]) + lla_to_ecef(lla_ref)
    return ecef_to_lla(r_e)


def lla_to_enu(lla: np.ndarray, lla_ref: np.ndarray) -> np.ndarray:
    """Geodetic points -> ENU [m] relative to ``lla_ref``."""
    return lla_to_ned(lla, lla_ref) @ NED_TO_ENU.T
