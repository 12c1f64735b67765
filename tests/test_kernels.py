"""The compiled navigation math (v2xpos.kernels) agrees with its readable numpy reference
(v2xpos.geo, v2xpos.rotation) on random inputs, and the SO(3) integrals are what they claim:
the integrals of the exponential, checked by quadrature of rotation.exp_so3."""
from __future__ import annotations

import numpy as np
import pytest

from v2xpos import geo, kernels, rotation


@pytest.fixture(scope="module")
def rng():
    return np.random.default_rng(7)


def _flat(M: np.ndarray) -> np.ndarray:
    return np.asarray(M, float).reshape(9)


def test_earth_model_matches_geo(rng):
    for lat, lon, h in zip(rng.uniform(-1.5, 1.5, 50), rng.uniform(-3.1, 3.1, 50), rng.uniform(-100, 9000, 50)):
        r_m, r_n = geo.radii_m(lat)
        assert np.allclose(kernels.radii(lat), (r_m, r_n), rtol=1e-15, atol=0)
        assert kernels.normal_gravity(lat, h) == pytest.approx(geo.normal_gravity_mps2(lat, h), rel=1e-14)
        assert np.allclose(kernels.c_en(lat, lon), _flat(geo.dcm_ecef_to_ned(lat, lon)), rtol=0, atol=1e-15)
        assert np.allclose(kernels.lla_to_ecef(lat, lon, h), geo.lla_to_ecef(np.array([lat, lon, h])),
                           rtol=0, atol=1e-8)


def test_rotations_match_rotation(rng):
    for roll, pitch, yaw in zip(rng.uniform(-3, 3, 50), rng.uniform(-1.5, 1.5, 50), rng.uniform(-3, 3, 50)):
        C = rotation.dcm_from_euler(roll, pitch, yaw)
        assert np.allclose(kernels.dcm_from_euler(roll, pitch, yaw), _flat(C), rtol=0, atol=1e-15)
        assert np.allclose(kernels.euler_from_dcm(_flat(C)), rotation.euler_from_dcm(C), rtol=0, atol=1e-12)


def test_matrix_products_and_cross(rng):
    A, B = rng.normal(size=(3, 3)), rng.normal(size=(3, 3))
    v = rng.normal(size=3)
    for ta in (False, True):
        for tb in (False, True):
            ref = (A.T if ta else A) @ (B.T if tb else B)
            assert np.allclose(kernels.matmul(_flat(A), _flat(B), ta, tb), _flat(ref), rtol=1e-14, atol=1e-14)
    assert np.allclose(kernels.mv(_flat(A), *v), A @ v, rtol=1e-14)
    assert np.allclose(kernels.mtv(_flat(A), *v), A.T @ v, rtol=1e-14)
    assert kernels.quadratic_form(_flat(A), *v) == pytest.approx(v @ A @ v, rel=1e-13)
    out = np.empty(3)
    kernels.cross_into(v, B[0], out)
    assert np.allclose(out, np.cross(v, B[0]), rtol=1e-14)


@pytest.mark.parametrize("angle_rad", [0.0, 1e-9, 3e-5, 2e-4, 3e-3, 0.099, 0.101, 0.3, 2.5])
def test_so3_exp_and_integrals(rng, angle_rad):
    axis = rng.normal(size=3)
    phi = angle_rad * axis / np.linalg.norm(axis)
    E, G1, G2 = (np.asarray(M).reshape(3, 3) for M in kernels.so3_integrals(*phi))
    assert np.allclose(kernels.exp_so3(*phi), _flat(rotation.exp_so3(phi)), rtol=0, atol=1e-15)
    E_ref, G1_ref, G2_ref = rotation.so3_integrals(phi)
    for M, ref in ((E, E_ref), (G1, G1_ref), (G2, G2_ref)):
        assert np.allclose(M, ref, rtol=0, atol=1e-13)
    # independent check: Gamma1 = int_0^1 exp(s K) ds, Gamma2 = int_0^1 (1 - s) exp(s K) ds (Gauss-Legendre)
    nodes, weights = np.polynomial.legendre.leggauss(12)
    s = 0.5 * (nodes + 1.0)
    expo = [rotation.exp_so3(si * phi) for si in s]
    G1_q = sum(0.5 * w * X for w, X in zip(weights, expo))
    G2_q = sum(0.5 * w * (1.0 - si) * X for w, si, X in zip(weights, s, expo))
    assert np.allclose(G1, G1_q, rtol=0, atol=1e-12)
    assert np.allclose(G2, G2_q, rtol=0, atol=1e-12)
