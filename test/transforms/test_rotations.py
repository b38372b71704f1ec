"""Tests of uncertain_facade_map.transforms.rotations against scipy and closed forms (~1 s)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation, Slerp
from support import axis_angle, rodrigues

from uncertain_facade_map.errors import InputError
from uncertain_facade_map.transforms import rotations as rot


def random_quaternions(n: int, seed: int = 0) -> np.ndarray:
    q = np.random.default_rng(seed).normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


unit_quaternions = st.lists(st.floats(-1, 1), min_size=4, max_size=4).filter(
    lambda v: np.linalg.norm(v) > 0.1).map(lambda v: np.array(v) / np.linalg.norm(v))


def test_to_matrix_equals_scipy_and_rodrigues():
    q = random_quaternions(500)
    np.testing.assert_allclose(rot.to_matrix(q), Rotation.from_quat(q).as_matrix(), atol=1e-14)
    np.testing.assert_allclose(rot.to_matrix(axis_angle([1, 2, 3], 0.7)), rodrigues([1, 2, 3], 0.7), atol=1e-15)
    # a quaternion of any non-zero length gives the rotation of its normalised self
    np.testing.assert_allclose(rot.to_matrix(3.0 * q[:5]), rot.to_matrix(q[:5]), atol=1e-14)
    assert rot.to_matrix(q.reshape(50, 10, 4)).shape == (50, 10, 3, 3)


def test_from_matrix_inverts_to_matrix_also_near_half_turns():
    q = np.concatenate([random_quaternions(300, 1),
                        [axis_angle([1, 0, 0], math.pi), axis_angle([0, 1, 1], math.pi - 1e-9),
                         axis_angle([0, 0, 1], 0.0), axis_angle([1, 1, 0], math.pi)]])
    back = rot.from_matrix(rot.to_matrix(q))
    assert np.all(back[:, 3] >= 0)
    np.testing.assert_allclose(np.abs(np.einsum('ij,ij->i', back, q)), 1.0, atol=1e-12)  # same up to sign
    np.testing.assert_allclose(rot.to_matrix(back), rot.to_matrix(q), atol=1e-13)


def test_multiply_conjugate_rotate_normalise():
    a, b = random_quaternions(200, 2), random_quaternions(200, 3)
    np.testing.assert_allclose(rot.to_matrix(rot.multiply(a, b)), rot.to_matrix(a) @ rot.to_matrix(b), atol=1e-14)
    np.testing.assert_allclose(rot.multiply(a, rot.conjugate(a)), np.tile([0, 0, 0, 1.0], (200, 1)), atol=1e-15)
    v = np.random.default_rng(4).normal(size=(200, 3))
    np.testing.assert_allclose(rot.rotate(a, v), np.einsum('kij,kj->ki', rot.to_matrix(a), v), atol=1e-14)
    np.testing.assert_allclose(rot.rotate(axis_angle([0, 0, 1], math.pi / 2), [1.0, 0, 0]), [0, 1, 0], atol=1e-15)
    np.testing.assert_allclose(np.linalg.norm(rot.normalise(5 * a), axis=1), 1.0, atol=1e-15)
    with pytest.raises(InputError, match='last axis of 4'):
        rot.to_matrix(np.zeros((2, 3)))


def test_slerp_equals_scipy_slerp():
    q0, q1 = random_quaternions(400, 5), random_quaternions(400, 6)
    u = np.random.default_rng(7).uniform(0, 1, 400)
    ours = rot.to_matrix(rot.slerp(q0, q1, u))
    theirs = np.stack([Slerp([0.0, 1.0], Rotation.from_quat([a, b]))([t]).as_matrix()[0]
                       for a, b, t in zip(q0, q1, u)])
    np.testing.assert_allclose(ours, theirs, atol=1e-12)


def test_slerp_half_way_is_half_the_angle_about_the_same_axis():
    axis = [0.3, -0.5, 0.8]
    q0, q1 = axis_angle(axis, 0.2), axis_angle(axis, 1.4)
    np.testing.assert_allclose(rot.to_matrix(rot.slerp(q0, q1, 0.5)), rodrigues(axis, 0.8), atol=1e-15)
    np.testing.assert_allclose(rot.to_matrix(rot.slerp(q0, q1, 0.25)), rodrigues(axis, 0.5), atol=1e-15)


def test_slerp_takes_the_short_way_and_hits_its_ends_exactly():
    q0, q1 = axis_angle([0, 0, 1], 0.1), axis_angle([0, 0, 1], 0.5)
    # -q1 is the same rotation: the path must not go the long way round
    np.testing.assert_allclose(rot.to_matrix(rot.slerp(q0, -q1, 0.5)), rodrigues([0, 0, 1], 0.3), atol=1e-15)
    assert np.array_equal(rot.slerp(q0, q1, 0.0), q0)
    assert np.array_equal(rot.slerp(q0, -q1, 1.0), q1)


def test_slerp_falls_back_to_lerp_for_tiny_angles():
    q0 = axis_angle([1, 2, 3], 0.4)
    for tiny in (0.0, 1e-13, 1e-10):
        q1 = rot.multiply(q0, axis_angle([0, 0, 1], tiny))
        out = rot.slerp(q0, q1, np.array([0.0, 0.3, 1.0]))
        assert np.isfinite(out).all()
        np.testing.assert_allclose(np.linalg.norm(out, axis=-1), 1.0, atol=1e-15)
        np.testing.assert_allclose(out, np.tile(q0, (3, 1)), atol=1e-12)


@settings(max_examples=200, deadline=None)
@given(unit_quaternions, unit_quaternions, st.floats(0, 1))
def test_slerp_moves_at_constant_angular_speed(q0, q1, u):
    def angle(a, b):
        return 2 * math.atan2(np.linalg.norm(a - b * np.sign(a @ b or 1)), np.linalg.norm(a + b * np.sign(a @ b or 1)))
    q = rot.slerp(q0, q1, u)
    assert abs(np.linalg.norm(q) - 1) < 1e-14
    total = angle(q0, q1)
    assert abs(angle(q0, q) - u * total) < 1e-9
    assert abs(angle(q, q1) - (1 - u) * total) < 1e-9
