"""Tests of msg_adapters.localisation: the localiser's pose and query messages <-> arrays (~2 s).

Round trips go through the real serialisations (rclpy's C type support, rosbags' CDR)."""

from __future__ import annotations

import array
from types import SimpleNamespace

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from msg_adapters.localisation import fill_query_request, pose_with_covariance_msg, prior_from_msg, query_answers
from msg_adapters.transforms import transform_types_rclpy, transform_types_rosbags
from uncertain_facade_map.errors import InputError

ROSBAGS = transform_types_rosbags()
RCLPY = transform_types_rclpy(require_tf2_msgs=False)
SETTINGS = settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def random_pose(rng: np.random.Generator) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    pose = np.eye(4)
    pose[:3, :3] = Rotation.from_rotvec(rng.normal(0, 1.5, 3)).as_matrix()
    pose[:3, 3] = rng.uniform(-1e4, 1e4, 3)
    return pose


def random_covariance(rng: np.random.Generator) -> np.ndarray:
    a = rng.normal(0, 1, (6, 6))
    return a @ a.T + 0.01 * np.eye(6)


def round_trip(msg, types):
    if types is ROSBAGS:
        store = types.typestore
        return store.deserialize_cdr(store.serialize_cdr(msg, msg.__msgtype__), msg.__msgtype__)
    from rclpy.serialization import deserialize_message, serialize_message
    return deserialize_message(serialize_message(msg), type(msg))


@given(seed=st.integers(0, 2**32 - 1), stamp=st.integers(0, 2**31 * 10**9 - 1), rosbags=st.booleans())
@SETTINGS
def test_pose_with_covariance_round_trip(seed, stamp, rosbags):
    rng = np.random.default_rng(seed)
    pose, cov = random_pose(rng), random_covariance(rng)
    types = ROSBAGS if rosbags else RCLPY
    msg = round_trip(pose_with_covariance_msg('map', stamp, pose, cov, types), types)
    prior = prior_from_msg(msg)
    assert prior.frame_id == 'map' and prior.stamp_ns == stamp
    np.testing.assert_allclose(prior.pose, pose, atol=1e-9)
    np.testing.assert_array_equal(prior.covariance, cov)


def test_priors_that_cannot_be_right_are_refused():
    rng = np.random.default_rng(0)
    good = pose_with_covariance_msg('map', 1, random_pose(rng), random_covariance(rng), RCLPY)
    unknown = pose_with_covariance_msg('map', 1, np.eye(4), np.zeros((6, 6)), RCLPY)
    assert prior_from_msg(unknown).covariance is None  # all zeros: unknown, the default applies
    for change, match in [(lambda m: setattr(m.pose.pose.orientation, 'w', 0.0) or
                           [setattr(m.pose.pose.orientation, k, 0.0) for k in 'xyz'], 'zero quaternion'),
                          (lambda m: setattr(m.pose.pose.position, 'x', float('nan')), 'NaN'),
                          (lambda m: m.pose.covariance.__setitem__(1, 5.0), 'symmetric'),
                          (lambda m: m.pose.covariance.__setitem__(0, -1.0), 'positive definite')]:
        msg = round_trip(good, RCLPY)
        change(msg)
        with pytest.raises(InputError, match=match):
            prior_from_msg(msg)
    with pytest.raises(InputError, match='PoseWithCovarianceStamped'):
        prior_from_msg(SimpleNamespace(header=None))


def test_query_request_and_answers():
    from uncertain_facade_map.srv import QueryPoints

    xyz = np.random.default_rng(1).normal(0, 10, (7, 3))
    request = fill_query_request(QueryPoints.Request(), xyz, 0.2)
    assert len(request.points) == 0 and request.resolution == 0.2
    np.testing.assert_array_equal(np.asarray(request.xyz).reshape(-1, 3), xyz)
    response = SimpleNamespace(success=True, message='', facade=array.array('i', [0, -1]),
                               mean_depth=[0.1, np.nan], variance=[1e-4, np.nan], noise_variance=[1e-4, np.nan],
                               signed_distance=[0.02, np.nan], p_occupied=[0.9, 0.5],
                               normal=[0.0, -1.0, 0.0, np.nan, np.nan, np.nan])
    got = query_answers(response, 2)
    assert got.facade.tolist() == [0, -1] and got.normal.shape == (2, 3)
    with pytest.raises(InputError, match='older'):
        query_answers(SimpleNamespace(**{**vars(response), 'normal': []}), 2)
    with pytest.raises(InputError, match='for 3 points'):
        query_answers(response, 3)
    with pytest.raises(InputError, match='refused: busy'):
        query_answers(SimpleNamespace(success=False, message='busy'), 2)
