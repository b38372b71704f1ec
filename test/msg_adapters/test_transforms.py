"""Tests of msg_adapters.transforms: transform messages <-> StampedTransform <-> buffer (~3 s).

rclpy's classes are tested for TransformStamped and Odometry (tf2_msgs may not be built in
the venv); TFMessage with rosbags' ROS 2 Jazzy typestore. Round trips go through the real
serialisations (CDR by rosbags, rclpy's C type support).
"""

from __future__ import annotations

import sys
from types import SimpleNamespace

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from msg_adapters.transforms import (
    StampedTransform,
    feed,
    odometry_msg,
    pose_stamped_msg,
    stamped_transforms,
    tf_message,
    transform_arrays,
    transform_stamped_msg,
    transform_types_rclpy,
    transform_types_rosbags,
)
from uncertain_facade_map.errors import InputError
from uncertain_facade_map.transforms import TransformBuffer
from uncertain_facade_map.transforms import rotations as rot

ROSBAGS = transform_types_rosbags()
STORE = ROSBAGS.typestore


def rclpy_types_or_skip() -> SimpleNamespace:
    try:
        return transform_types_rclpy(require_tf2_msgs=False)
    except ImportError as err:  # pragma: no cover - the project venv has them
        pytest.skip(f'ROS 2 message packages not importable: {err}')


RCLPY = rclpy_types_or_skip()


def rosbags_round_trip(msg):
    return STORE.deserialize_cdr(STORE.serialize_cdr(msg, msg.__msgtype__), msg.__msgtype__)


def rclpy_round_trip(msg):
    from rclpy.serialization import deserialize_message, serialize_message
    return deserialize_message(serialize_message(msg), type(msg))


def sample(k: int = 3, seed: int = 0) -> list[StampedTransform]:
    rng = np.random.default_rng(seed)
    out = []
    for i in range(k):
        q = rng.normal(size=4)
        out.append(StampedTransform(f'parent{i}', f'child{i}', 1_700_000_000_123_456_789 + i, rng.normal(size=3),
                                    q / np.linalg.norm(q)))
    return out


# --------------------------------------------------------------------------------------
# round trips
# --------------------------------------------------------------------------------------


def test_tf_message_round_trip_rosbags():
    ts = sample(4)
    msg = rosbags_round_trip(tf_message(ts, ROSBAGS))
    assert msg.__msgtype__ == 'tf2_msgs/msg/TFMessage'
    assert stamped_transforms(msg) == ts
    assert stamped_transforms(tf_message([], ROSBAGS)) == []


@pytest.mark.parametrize('types, round_trip', [(ROSBAGS, rosbags_round_trip), (RCLPY, rclpy_round_trip)],
                         ids=['rosbags', 'rclpy'])
def test_transform_stamped_and_odometry_round_trips(types, round_trip):
    t = sample(1)[0]
    msg = round_trip(transform_stamped_msg(t, types))
    assert (msg.header.frame_id, msg.child_frame_id, msg.header.stamp.sec, msg.header.stamp.nanosec) == (
        'parent0', 'child0', 1_700_000_000, 123_456_789)
    assert stamped_transforms(msg) == [t]
    odo = round_trip(odometry_msg(t, types))
    assert stamped_transforms(odo) == [t]
    assert not np.asarray(odo.pose.covariance).any() and odo.twist.twist.linear.x == 0.0
    pose = round_trip(pose_stamped_msg(t, types))
    assert stamped_transforms(pose, child_frame='child0') == [t]


def test_rclpy_messages_pass_its_field_checks(monkeypatch):
    """With ROS_PYTHON_CHECK_FIELDS on, rclpy asserts every field's type when it is set."""
    for cls in vars(RCLPY).values():
        module = sys.modules.get(getattr(cls, '__module__', '') or '')
        if module is not None and hasattr(module, 'ros_python_check_fields'):
            monkeypatch.setattr(module, 'ros_python_check_fields', '1')
    t = sample(1)[0]
    assert stamped_transforms(odometry_msg(t, RCLPY)) == [t]
    assert stamped_transforms(transform_stamped_msg(t, RCLPY)) == [t]


def test_pose_messages_need_a_child_frame():
    t = sample(1)[0]
    pose = pose_stamped_msg(t, ROSBAGS)
    with pytest.raises(InputError, match='pass child_frame'):
        stamped_transforms(pose)
    from geometry_msgs.msg import PoseWithCovarianceStamped
    cov = PoseWithCovarianceStamped()
    cov.header.frame_id = 'map'
    cov.pose.pose.position.x = 4.0
    cov.pose.pose.orientation.w = 1.0
    (got,) = stamped_transforms(cov, child_frame='base_link')
    assert (got.parent, got.child, got.translation.tolist()) == ('map', 'base_link', [4.0, 0.0, 0.0])
    odo = odometry_msg(StampedTransform('odom', '', 5, [1, 2, 3], [0, 0, 0, 1]), ROSBAGS)
    with pytest.raises(InputError, match='empty child_frame_id'):
        stamped_transforms(odo)
    assert stamped_transforms(odo, child_frame='base_link')[0].child == 'base_link'


def test_other_messages_are_refused():
    with pytest.raises(InputError, match='is not a transform message'):
        stamped_transforms(SimpleNamespace(header=None, data=[1]))
    with pytest.raises(InputError, match='not a TransformStamped'):
        stamped_transforms(SimpleNamespace(transforms=[SimpleNamespace(x=1)]))


def test_ros1_typestore_wraps_the_header():
    from rosbags.typesys import Stores, get_typestore
    ros1 = transform_types_rosbags(get_typestore(Stores.ROS1_NOETIC))
    msg = transform_stamped_msg(sample(1)[0], ros1)
    assert msg.header.seq == 0
    assert ros1.TFMessage is None  # rosbags' ROS 1 store has no tf2_msgs
    with pytest.raises(InputError, match='tf2_msgs'):
        tf_message(sample(1), ros1)


def test_missing_tf2_msgs_is_named(monkeypatch):
    monkeypatch.setitem(sys.modules, 'tf2_msgs', None)  # makes the import fail
    monkeypatch.setitem(sys.modules, 'tf2_msgs.msg', None)
    with pytest.raises(InputError, match='tf2_msgs is not importable'):
        transform_types_rclpy()
    types = transform_types_rclpy(require_tf2_msgs=False)
    assert types.TFMessage is None and types.Odometry is not None
    with pytest.raises(InputError, match='tf2_msgs'):
        tf_message(sample(1), types)


# --------------------------------------------------------------------------------------
# feeding a buffer
# --------------------------------------------------------------------------------------


def test_feed_keeps_the_good_transforms_of_a_message_and_says_why_not_the_others():
    good = sample(2)
    bad_q = StampedTransform('map', 'x', 5, [0, 0, 0], [0, 0, 0, 2])
    self_tf = StampedTransform('map', 'map', 5, [0, 0, 0], [0, 0, 0, 1])
    nan = StampedTransform('map', 'y', 5, [0, np.nan, 0], [0, 0, 0, 1])
    buf = TransformBuffer()
    accepted, reasons = feed(buf, tf_message([good[0], bad_q, self_tf, nan, good[1]], ROSBAGS))
    assert accepted == 2 and len(reasons) == 3
    assert 'not a rotation' in reasons[0] and 'to itself' in reasons[1] and 'NaN' in reasons[2]
    assert buf.frames() == {'child0': 'parent0', 'child1': 'parent1'}
    accepted, reasons = feed(buf, transform_stamped_msg(StampedTransform('a', 'b', 0, [1, 0, 0], [0, 0, 0, 1]),
                                                         RCLPY), static=True)
    assert (accepted, reasons) == (1, []) and buf.time_range('b') is None
    with pytest.raises(InputError):
        feed(buf, SimpleNamespace(data=1))


def test_transform_arrays_feed_set_transforms_like_feed():
    ts = [StampedTransform('odom', 'base', 1_000 + 10 * i, [i, 0, 0], [0, 0, 0, 1]) for i in range(20)]
    one, bulk = TransformBuffer(), TransformBuffer()
    for t in ts:
        feed(one, transform_stamped_msg(t, ROSBAGS))
    assert bulk.set_transforms(**transform_arrays(ts)) == 20
    assert repr(one) == repr(bulk)
    np.testing.assert_array_equal(bulk.lookup('odom', 'base', 1_055).translation, [5.5, 0, 0])
    arrays = transform_arrays([])
    assert arrays['translations'].shape == (0, 3) and arrays['rotations'].shape == (0, 4)


# --------------------------------------------------------------------------------------
# property tests
# --------------------------------------------------------------------------------------

finite = st.floats(allow_nan=False, allow_infinity=False, width=64)
names = st.text(st.characters(blacklist_categories=('Cs',), blacklist_characters='\x00'), max_size=12)
stamps = st.integers(0, 2**31 * 1_000_000_000 - 1)


@st.composite
def transforms(draw) -> StampedTransform:
    return StampedTransform(draw(names), draw(names), draw(stamps), draw(st.lists(finite, min_size=3, max_size=3)),
                            draw(st.lists(finite, min_size=4, max_size=4)))


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(transforms(), max_size=4))
def test_any_finite_transforms_survive_a_tf_message_rosbags(ts):
    assert stamped_transforms(rosbags_round_trip(tf_message(ts, ROSBAGS))) == ts


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(transforms(), st.sampled_from(['rosbags', 'rclpy']), st.sampled_from(['transform', 'odometry']))
def test_any_finite_transform_survives_each_message(t, impl, kind):
    types, round_trip = (ROSBAGS, rosbags_round_trip) if impl == 'rosbags' else (RCLPY, rclpy_round_trip)
    build = transform_stamped_msg if kind == 'transform' else odometry_msg
    child = t.child if (kind == 'transform' or t.child) else 'fallback'
    expected = StampedTransform(t.parent, child, t.stamp_ns, t.translation, t.rotation)
    assert stamped_transforms(round_trip(build(t, types)), child_frame=None if t.child else 'fallback') == [expected]


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.integers(1, 10**12), st.lists(st.floats(-1e3, 1e3), min_size=3, max_size=3),
                          st.lists(st.floats(-1, 1), min_size=4, max_size=4)), min_size=1, max_size=8))
def test_fed_unit_transforms_are_what_lookups_return(rows):
    """(Stamps from 1 ns: a lookup at 0 means the latest time.)"""
    buf = TransformBuffer(cache_time=float('inf'))
    expected = {}
    for stamp, xyz, q in rows:
        q = np.array(q)
        if np.linalg.norm(q) < 0.1:
            continue
        q = q / np.linalg.norm(q)
        t = StampedTransform('/map', 'robot', stamp, xyz, q)
        assert feed(buf, odometry_msg(t, ROSBAGS)) == (1, [])
        expected[stamp] = (np.array(xyz), q)
    for stamp, (xyz, q) in expected.items():
        got = buf.lookup('map', 'robot', stamp)
        np.testing.assert_allclose(got.translation, xyz, atol=1e-12)
        np.testing.assert_allclose(got.rotation, rot.to_matrix(q), atol=1e-12)
