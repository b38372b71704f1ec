"""SE(3) and SO(3): exp and log against scipy's rotations, round trips, the left Jacobians
against finite differences (hypothesis over rotation vectors up to 3 rad)."""

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from scipy.spatial.transform import Rotation

from uncertain_facade_map.localisation import se3

_finite = st.floats(-3.0, 3.0, allow_nan=False, allow_infinity=False)
rotvec = arrays(np.float64, 3, elements=st.floats(-1.7, 1.7, allow_nan=False)).filter(
    lambda v: np.linalg.norm(v) < 3.0)
twist = arrays(np.float64, 6, elements=_finite).filter(lambda v: np.linalg.norm(v[3:]) < 3.0)


@given(rotvec)
def test_so3_exp_is_scipys_rotation(phi):
    np.testing.assert_allclose(se3.so3_exp(phi), Rotation.from_rotvec(phi).as_matrix(), atol=1e-12)


@given(rotvec)
def test_so3_log_inverts_exp(phi):
    np.testing.assert_allclose(se3.so3_log(se3.so3_exp(phi)), phi, atol=1e-9)


def test_so3_log_near_pi_and_zero():
    for phi in (np.array([np.pi - 1e-7, 0, 0]), np.array([0, 0, np.pi]), np.array([1e-9, -2e-9, 0]),
                np.array([1.0, 2.0, 2.0]) / 3.0 * (np.pi - 1e-5)):
        back = se3.so3_log(se3.so3_exp(phi))
        np.testing.assert_allclose(se3.so3_exp(back), se3.so3_exp(phi), atol=1e-9)
        assert np.linalg.norm(back) <= np.pi + 1e-12


def test_skew_is_the_cross_product():
    rng = np.random.default_rng(0)
    v, u = rng.normal(size=(2, 5, 3))
    np.testing.assert_allclose(np.einsum('nij,nj->ni', se3.skew(v), u), np.cross(v, u), atol=1e-14)


@given(twist)
def test_se3_log_inverts_exp(xi):
    pose = se3.se3_exp(xi)
    np.testing.assert_allclose(pose[:3, :3], Rotation.from_rotvec(xi[3:]).as_matrix(), atol=1e-12)
    np.testing.assert_allclose(se3.se3_log(pose), xi, atol=1e-8)


@given(twist, twist)
@settings(max_examples=50)
def test_compose_and_inverse(a, b):
    ta, tb = se3.se3_exp(a), se3.se3_exp(b)
    both = se3.compose(ta, tb)
    np.testing.assert_allclose(both, ta @ tb, atol=1e-10)
    np.testing.assert_allclose(se3.compose(both, se3.inverse(tb)), ta, atol=1e-10)
    pts = np.array([[1.0, 2.0, 3.0], [-4.0, 0.5, 0.0]])
    np.testing.assert_allclose(se3.transform_points(both, pts), se3.transform_points(ta, se3.transform_points(tb, pts)),
                               atol=1e-10)


@given(twist)
@settings(max_examples=50)
def test_left_jacobians_against_finite_differences(xi):
    """exp(xi + d) = exp(J d) exp(xi) and log(exp(d) exp(xi)) = xi + J^-1 d to first order."""
    h = 1e-6
    jac, inv = se3.se3_left_jacobian(xi), se3.se3_left_jacobian_inverse(xi)
    numeric = np.empty((6, 6))
    for k in range(6):
        d = np.zeros(6)
        d[k] = h
        numeric[:, k] = (se3.se3_log(se3.se3_exp(d) @ se3.se3_exp(xi)) -
                         se3.se3_log(se3.se3_exp(-d) @ se3.se3_exp(xi))) / (2 * h)
    np.testing.assert_allclose(numeric, inv, atol=2e-5 * max(1.0, np.abs(inv).max()))
    np.testing.assert_allclose(jac @ inv, np.eye(6), atol=1e-9)
    so3 = se3.so3_left_jacobian(xi[3:])
    np.testing.assert_allclose(so3 @ se3.so3_left_jacobian_inverse(xi[3:]), np.eye(3), atol=1e-9)
