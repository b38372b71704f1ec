"""Tests of uncertain_facade_map.transforms.buffer: chains, interpolation, time 0, errors (~3 s).

The tree of most tests (stamps in seconds):

    map -> odom        dynamic, 1 Hz, 10..13 s   (a localiser's correction)
    odom -> base_link  dynamic, 10 Hz, 10..13.5 s (odometry)
    base_link -> lidar static
    base_link -> camera static

Expected answers are composed by hand from 4x4 matrices built with Rodrigues' formula.
"""

from __future__ import annotations

import math
import pickle
import time

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from support import axis_angle, rodrigues

from uncertain_facade_map.errors import (
    ConnectivityError,
    ExtrapolationError,
    InputError,
    TransformError,
    UnknownFrameError,
)
from uncertain_facade_map.transforms import Rigid, TransformBuffer
from uncertain_facade_map.transforms import rotations as rot

S = 1_000_000_000  # ns per second


def homogeneous(axis, angle, t) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3] = rodrigues(axis, angle)
    out[:3, 3] = t
    return out


def assert_rigid(rigid: Rigid, expected: np.ndarray, atol: float = 1e-12) -> None:
    np.testing.assert_allclose(rigid.rotation, expected[:3, :3], atol=atol)
    np.testing.assert_allclose(rigid.translation, expected[:3, 3], atol=atol)


# the poses of the edges, in closed form
def map_odom(t: float):
    return [0, 0, 1], 0.01 * (t - 10), [0.1 * (t - 10), -0.05 * (t - 10), 0.0]


def odom_base(t: float):
    return [0.1, -0.2, 1.0], 0.3 * (t - 10), [10.0 * (t - 10), 2.0 * (t - 10) ** 2, 0.01]


LIDAR = ([0, 1, 0], 0.05, [0.5, 0.0, 1.8])
CAMERA = ([1, 0, 1], -0.4, [0.7, 0.3, 1.2])
MAP_TIMES = [10.0, 11.0, 12.0, 13.0]
ODOM_TIMES = [10.0 + 0.1 * i for i in range(36)]


def ns(t: float) -> int:
    return int(round(t * S))


def make_buffer(**kwargs) -> TransformBuffer:
    buf = TransformBuffer(**kwargs)
    for t in MAP_TIMES:
        axis, angle, xyz = map_odom(t)
        buf.set_transform('map', 'odom', ns(t), xyz, axis_angle(axis, angle))
    for t in ODOM_TIMES:
        axis, angle, xyz = odom_base(t)
        buf.set_transform('odom', 'base_link', ns(t), xyz, axis_angle(axis, angle))
    buf.set_transform('base_link', 'lidar', 0, LIDAR[2], axis_angle(*LIDAR[:2]), static=True)
    buf.set_transform('base_link', 'camera', 0, CAMERA[2], axis_angle(*CAMERA[:2]), static=True)
    return buf


@pytest.fixture
def buf() -> TransformBuffer:
    return make_buffer()


def hand(t: float) -> dict[str, np.ndarray]:
    """Each frame's pose in map at a time that is a sample of both dynamic edges."""
    m_o = homogeneous(*map_odom(t))
    o_b = homogeneous(*odom_base(t))
    m_b = m_o @ o_b
    return {'map': np.eye(4), 'odom': m_o, 'base_link': m_b, 'lidar': m_b @ homogeneous(*LIDAR),
            'camera': m_b @ homogeneous(*CAMERA)}


# --------------------------------------------------------------------------------------
# chains
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize('target, source', [
    ('map', 'lidar'), ('lidar', 'map'), ('odom', 'lidar'), ('base_link', 'map'), ('camera', 'lidar'),
    ('lidar', 'camera'), ('map', 'odom'), ('odom', 'map'), ('camera', 'odom')])
def test_lookup_equals_the_chain_composed_by_hand(buf, target, source):
    for t in (11.0, 12.0):
        poses = hand(t)
        expected = np.linalg.inv(poses[target]) @ poses[source]
        got = buf.lookup(target, source, ns(t))
        assert_rigid(got, expected)
        # the result maps points of source to target
        p = np.array([[1.0, 2.0, 3.0], [-4.0, 0.5, 0.0]])
        ph = np.c_[p, np.ones(2)]
        np.testing.assert_allclose(got.apply(p), (ph @ expected.T)[:, :3], atol=1e-12)


def test_siblings_do_not_need_the_edges_above_their_common_parent(buf):
    # at 13.4 s map -> odom has no data, but camera <- lidar only walks up to base_link
    expected = np.linalg.inv(homogeneous(*CAMERA)) @ homogeneous(*LIDAR)
    assert_rigid(buf.lookup('camera', 'lidar', ns(13.4)), expected)
    with pytest.raises(ExtrapolationError):
        buf.lookup('map', 'lidar', ns(13.4))


def test_equal_frames_give_the_identity_even_unknown_ones(buf):
    for frame in ('map', 'lidar', 'never_seen', '/map'):
        assert_rigid(buf.lookup(frame, frame, 123), np.eye(4), atol=0)
    assert_rigid(buf.lookup('/map', 'map', 5), np.eye(4), atol=0)  # one leading '/' is dropped


def test_a_lookup_at_a_sample_returns_the_sample(buf):
    axis, angle, xyz = odom_base(ODOM_TIMES[7])
    got = buf.lookup('odom', 'base_link', ns(ODOM_TIMES[7]))
    np.testing.assert_allclose(got.rotation, rodrigues(axis, angle), atol=1e-15)
    np.testing.assert_allclose(got.translation, xyz, atol=1e-15)


# --------------------------------------------------------------------------------------
# interpolation
# --------------------------------------------------------------------------------------


def test_halfway_between_samples_is_the_midpoint_and_half_the_angle():
    buf = TransformBuffer()
    axis = [0.2, 0.9, -0.3]
    buf.set_transform('a', 'b', 100 * S, [1.0, 2.0, 3.0], axis_angle(axis, 0.2))
    buf.set_transform('a', 'b', 101 * S, [3.0, -2.0, 4.0], axis_angle(axis, 1.0))
    got = buf.lookup('a', 'b', 100 * S + S // 2)
    np.testing.assert_allclose(got.translation, [2.0, 0.0, 3.5], atol=1e-15)
    np.testing.assert_allclose(got.rotation, rodrigues(axis, 0.6), atol=1e-15)
    quarter = buf.lookup('a', 'b', 100 * S + S // 4)
    np.testing.assert_allclose(quarter.translation, [1.5, 1.0, 3.25], atol=1e-15)
    np.testing.assert_allclose(quarter.rotation, rodrigues(axis, 0.4), atol=1e-15)


def test_interpolation_inside_a_chain(buf):
    # halfway between two odometry samples (map -> odom is linear in t, so also exact there)
    t0, t1 = ODOM_TIMES[12], ODOM_TIMES[13]
    tm = (t0 + t1) / 2
    a0, a1 = odom_base(t0), odom_base(t1)
    o_b = np.eye(4)
    o_b[:3, :3] = rodrigues(a0[0], (a0[1] + a1[1]) / 2)
    o_b[:3, 3] = (np.array(a0[2]) + np.array(a1[2])) / 2
    expected = homogeneous(*map_odom(tm)) @ o_b @ homogeneous(*LIDAR)
    assert_rigid(buf.lookup('map', 'lidar', ns(tm)), expected)


def test_out_of_order_inserts_and_replaced_stamps():
    rng = np.random.default_rng(3)
    stamps = rng.permutation(np.arange(50)) * 10_000_000 + S
    q = rot.normalise(rng.normal(size=(50, 4)))
    x = rng.normal(size=(50, 3))
    shuffled, ordered = TransformBuffer(), TransformBuffer()
    for i in range(50):
        shuffled.set_transform('p', 'c', int(stamps[i]), x[i], q[i])
    for i in np.argsort(stamps):
        ordered.set_transform('p', 'c', int(stamps[i]), x[i], q[i])
    probe = np.linspace(stamps.min(), stamps.max(), 301).astype(np.int64)
    for a, b in zip(shuffled.lookup_many('p', 'c', probe), ordered.lookup_many('p', 'c', probe)):
        assert np.array_equal(a, b)
    # a sample at an existing stamp replaces it
    shuffled.set_transform('p', 'c', int(stamps[0]), [9.0, 9.0, 9.0], [0, 0, 0, 1])
    assert_rigid(shuffled.lookup('p', 'c', int(stamps[0])), homogeneous([0, 0, 1], 0.0, [9, 9, 9]))
    assert shuffled.time_range('c') == (int(stamps.min()), int(stamps.max()))
    assert len(shuffled._tracks['c']) == 50


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.integers(0, 40), st.floats(-5, 5)), min_size=1, max_size=60))
def test_track_keeps_the_last_value_per_stamp_within_the_cache(ops):
    """Random inserts against a dict model with tf2's pruning (cache 10 units)."""
    buf = TransformBuffer(cache_time=10e-9)  # 10 ns
    model: dict[int, float] = {}
    for stamp, value in ops:
        newest = max(model) if model else None
        if newest is not None and stamp < newest - 10:
            with pytest.raises(TransformError, match='older than the cache keeps'):
                buf.set_transform('p', 'c', stamp, [value, 0, 0], [0, 0, 0, 1])
            continue
        buf.set_transform('p', 'c', stamp, [value, 0, 0], [0, 0, 0, 1])
        model[stamp] = value
        newest = max(model)
        model = {s: v for s, v in model.items() if s >= newest - 10}
    stamps, xyz, _ = buf._tracks['c'].view()
    assert stamps.tolist() == sorted(model)
    assert xyz[:, 0].tolist() == [model[s] for s in sorted(model)]


# --------------------------------------------------------------------------------------
# many times at once
# --------------------------------------------------------------------------------------

CHAIN_PAIRS = [('map', 'lidar'), ('lidar', 'map'), ('camera', 'odom'), ('odom', 'base_link'), ('camera', 'lidar')]


@settings(max_examples=40, deadline=None)
@given(st.sampled_from(CHAIN_PAIRS),
       st.lists(st.one_of(st.integers(ns(10.0), ns(13.0)), st.just(0)), min_size=1, max_size=30))
def test_lookup_many_equals_lookup_at_each_time(pair, stamps):
    buf = BUFFER
    rots, trans = buf.lookup_many(*pair, np.array(stamps, dtype=np.int64))
    assert rots.shape == (len(stamps), 3, 3) and trans.shape == (len(stamps), 3)
    for k, t in enumerate(stamps):
        one = buf.lookup(*pair, t)
        np.testing.assert_allclose(rots[k], one.rotation, rtol=0, atol=1e-12)
        np.testing.assert_allclose(trans[k], one.translation, rtol=0, atol=1e-12)


BUFFER = make_buffer()


def test_lookup_many_of_nothing_and_of_equal_frames(buf):
    r, t = buf.lookup_many('map', 'lidar', np.zeros(0, dtype=np.int64))
    assert r.shape == (0, 3, 3) and t.shape == (0, 3)
    r, t = buf.lookup_many('x', 'x', np.array([1, 2]))
    assert np.array_equal(r, np.tile(np.eye(3), (2, 1, 1))) and not t.any()
    with pytest.raises(InputError, match='integer nanoseconds'):
        buf.lookup_many('map', 'lidar', np.array([1.5]))
    with pytest.raises(UnknownFrameError):
        buf.lookup_many('map', 'nowhere', np.zeros(0, dtype=np.int64))


def test_results_and_inputs_are_never_shared_with_the_buffer():
    buf = TransformBuffer()
    xyz = np.array([1.0, 2.0, 3.0])
    buf.set_transform('a', 'b', 5, xyz, [0, 0, 0, 1])
    buf.set_transform('b', 'c', 0, xyz, [0, 0, 0, 1], static=True)
    xyz[:] = 0.0  # the caller reuses its array
    for source in ('b', 'c'):
        rots, trans = buf.lookup_many('a' if source == 'b' else 'b', source, np.array([5]))
        assert rots.flags.writeable and trans.flags.writeable
        trans[:] = -1.0
        rots[:] = 0.0
    buf.set_transform('a', 'b', 5, [7.0, 7.0, 7.0], [0, 0, 0, 1])  # rewrites the sample in place
    np.testing.assert_array_equal(buf.lookup('b', 'c', 0).translation, [1, 2, 3])
    np.testing.assert_array_equal(buf.lookup('b', 'c', 0).rotation, np.eye(3))


def test_lookup_many_names_the_times_it_cannot_answer(buf):
    stamps = np.array([ns(10.5), ns(13.2), ns(13.3), ns(12.0)])
    with pytest.raises(ExtrapolationError) as info:
        buf.lookup_many('map', 'lidar', stamps)
    err = info.value
    assert err.future and err.frame == 'odom' and err.stamp_ns == ns(13.3)
    assert '2 of 4 times' in str(err)


def test_lookup_many_is_fast():
    """K = 100,000 sorted times over 100,000 samples: tens of milliseconds (measured ~25 ms)."""
    k = 100_000
    rng = np.random.default_rng(0)
    big = TransformBuffer(cache_time=math.inf)
    stamps = np.arange(k, dtype=np.int64) * 10_000_000 + S
    big.set_transforms('map', 'base', stamps, rng.normal(size=(k, 3)), rot.normalise(rng.normal(size=(k, 4))))
    big.set_transform('base', 'lidar', 0, [0, 0, 1], [0, 0, 0, 1], static=True)
    probe = np.sort(rng.integers(stamps[0], stamps[-1], k))
    times = []
    for _ in range(3):
        start = time.perf_counter()
        big.lookup_many('map', 'lidar', probe)
        times.append(time.perf_counter() - start)
    assert min(times) < 0.5, times


# --------------------------------------------------------------------------------------
# time 0, extrapolation, cache
# --------------------------------------------------------------------------------------


def test_time_zero_is_the_latest_time_the_whole_chain_has(buf):
    # map -> odom ends at 13.0 s, odom -> base_link at 13.5 s
    assert buf.latest_common_time('map', 'lidar') == ns(13.0)
    assert buf.latest_common_time('odom', 'lidar') == ns(13.5)
    assert buf.latest_common_time('camera', 'lidar') == 0  # static chain
    assert_rigid(buf.lookup('map', 'lidar', 0), np.linalg.inv(hand(13.0)['map']) @ hand(13.0)['lidar'])
    expected = homogeneous(*odom_base(13.5)) @ homogeneous(*LIDAR)
    assert_rigid(buf.lookup('odom', 'lidar', 0), expected)
    assert_rigid(buf.lookup('camera', 'lidar', 0), np.linalg.inv(homogeneous(*CAMERA)) @ homogeneous(*LIDAR))


def test_extrapolation_into_the_past_and_the_future(buf):
    with pytest.raises(ExtrapolationError) as past:
        buf.lookup('map', 'lidar', ns(9.5))
    err = past.value
    assert not err.future
    assert err.frame in ('odom', 'base_link') and err.stamp_ns == ns(9.5)
    assert (err.first_ns, err.last_ns) == ((ns(10.0), ns(13.0)) if err.frame == 'odom' else (ns(10.0), ns(13.5)))
    assert '9.500 s' in str(err) and '"lidar" in "map"' in str(err)
    with pytest.raises(ExtrapolationError) as future:
        buf.lookup('map', 'lidar', ns(13.25))
    err = future.value
    assert err.future and err.frame == 'odom' and err.parent == 'map'
    assert (err.first_ns, err.last_ns, err.stamp_ns) == (ns(10.0), ns(13.0), ns(13.25))
    assert str(err) == ('lookup of "lidar" in "map" at 13.250 s needs "odom" in "map", whose samples span '
                        '10.000-13.000 s: 0.250 s after the newest sample (wait for newer data)')
    # an edge lacking old data is named before one lacking new data: it never resolves
    buf.set_transform('map', 'odom', ns(14.0), [0, 0, 0], [0, 0, 0, 1])
    with pytest.raises(ExtrapolationError) as both:
        buf.lookup('map', 'lidar', ns(13.8))
    assert both.value.future and both.value.frame == 'base_link'


def test_max_extrapolation_holds_the_edge_sample():
    buf = make_buffer(max_extrapolation=0.05)
    at_end = buf.lookup('odom', 'base_link', ns(13.5))
    held = buf.lookup('odom', 'base_link', ns(13.54))
    assert np.array_equal(held.rotation, at_end.rotation) and np.array_equal(held.translation, at_end.translation)
    at_start = buf.lookup('odom', 'base_link', ns(10.0))
    before = buf.lookup('odom', 'base_link', ns(9.96))
    assert np.array_equal(before.translation, at_start.translation)
    with pytest.raises(ExtrapolationError, match='max_extrapolation 0.05 s') as info:
        buf.lookup('odom', 'base_link', ns(13.56))
    assert info.value.future
    r, t = buf.lookup_many('odom', 'base_link', np.array([ns(9.96), ns(13.54)]))
    assert np.array_equal(t, np.stack([at_start.translation, at_end.translation]))
    # a single sample answers only its own time, or within max_extrapolation
    tight, loose = TransformBuffer(), TransformBuffer(max_extrapolation=0.1)
    for b in (tight, loose):
        b.set_transform('a', 'b', 5 * S, [1, 2, 3], [0, 0, 0, 1])
        assert_rigid(b.lookup('a', 'b', 5 * S), homogeneous([0, 0, 1], 0, [1, 2, 3]))
    assert not tight.can_transform('a', 'b', 5 * S + 1)
    assert_rigid(loose.lookup('a', 'b', 5 * S + S // 20), homogeneous([0, 0, 1], 0, [1, 2, 3]))


def test_a_call_may_hold_the_edge_samples_longer_or_not_at_all():
    """``max_extrapolation`` per call (the node waits strictly, then holds within its tolerance)."""
    strict, holding = make_buffer(), make_buffer(max_extrapolation=0.05)
    at_end = strict.lookup('odom', 'base_link', ns(13.5))
    assert not strict.can_transform('odom', 'base_link', ns(13.54))
    assert strict.can_transform('odom', 'base_link', ns(13.54), max_extrapolation=0.05)
    held = strict.lookup('odom', 'base_link', ns(13.54), max_extrapolation=0.05)
    assert np.array_equal(held.translation, at_end.translation)
    _, t = strict.lookup_many('odom', 'base_link', np.array([ns(13.54)]), max_extrapolation=0.05)
    assert np.array_equal(t[0], at_end.translation)
    with pytest.raises(ExtrapolationError, match='max_extrapolation 0.05 s'):
        strict.lookup_many('odom', 'base_link', np.array([ns(13.56)]), max_extrapolation=0.05)
    assert not holding.can_transform('odom', 'base_link', ns(13.54), max_extrapolation=0.0)
    with pytest.raises(InputError, match='max_extrapolation must be >= 0'):
        strict.lookup('odom', 'base_link', ns(13.5), max_extrapolation=-1.0)


def test_max_samples_keeps_the_newest():
    buf = TransformBuffer(cache_time=math.inf, max_samples=3)
    for k in range(10):
        buf.set_transform('map', 'base', ns(1.0 + k), [k, 0, 0], [0, 0, 0, 1])
    assert buf.time_range('base') == (ns(8.0), ns(10.0))
    buf.set_transforms('map', 'base', [ns(11.0), ns(12.0)], [[11, 0, 0], [12, 0, 0]], [[0, 0, 0, 1]] * 2)
    assert buf.time_range('base') == (ns(10.0), ns(12.0))
    newest = TransformBuffer(max_samples=1, max_extrapolation=0.05)
    for k in range(3):
        newest.set_transform('map', 'base', ns(1.0 + k), [k, 0, 0], [0, 0, 0, 1])
    assert newest.time_range('base') == (ns(3.0), ns(3.0))
    assert newest.lookup('map', 'base', ns(3.02)).translation[0] == 2.0
    with pytest.raises(InputError, match='max_samples must be >= 1'):
        TransformBuffer(max_samples=0)


def test_cache_time_prunes_old_samples():
    buf = make_buffer(cache_time=1.0)
    assert buf.time_range('base_link') == (ns(12.5), ns(13.5))
    assert buf.time_range('odom') == (ns(12.0), ns(13.0))
    with pytest.raises(ExtrapolationError, match='cache_time 1 s') as info:
        buf.lookup('odom', 'base_link', ns(12.0))
    assert not info.value.future
    with pytest.raises(TransformError, match='older than the cache keeps'):
        buf.set_transform('odom', 'base_link', ns(12.0), [0, 0, 0], [0, 0, 0, 1])
    buf.set_transform('odom', 'base_link', ns(12.6), [0, 0, 0], [0, 0, 0, 1])  # within the cache: fine
    keep_all = make_buffer(cache_time=math.inf)
    assert keep_all.time_range('base_link') == (ns(10.0), ns(13.5))
    assert keep_all.time_range('lidar') is None and keep_all.time_range('map') is None
    with pytest.raises(InputError):
        TransformBuffer(cache_time=0)
    with pytest.raises(InputError):
        TransformBuffer(max_extrapolation=-1)


def test_can_transform_and_why_not_over_a_sweep(buf):
    assert buf.can_transform('map', 'lidar', ns(12.0), ns(12.9))
    assert buf.can_transform('map', 'lidar', 0)
    assert not buf.can_transform('map', 'lidar', ns(12.95), ns(13.05))
    err = buf.why_not('map', 'lidar', ns(12.95), ns(13.05))
    assert isinstance(err, ExtrapolationError) and err.future and err.stamp_ns == ns(13.05)
    assert isinstance(buf.why_not('map', 'nowhere', ns(12.0)), UnknownFrameError)
    assert buf.why_not('x', 'x', 5) is None
    with pytest.raises(InputError, match='before start'):
        buf.why_not('map', 'lidar', ns(12.0), ns(11.0))


# --------------------------------------------------------------------------------------
# refused lookups and transforms
# --------------------------------------------------------------------------------------


def test_unknown_frames_are_named_with_the_known_ones(buf):
    with pytest.raises(UnknownFrameError) as info:
        buf.lookup('map', 'velodyne', ns(11.0))
    assert info.value.frame == 'velodyne'
    assert info.value.known == ('base_link', 'camera', 'lidar', 'map', 'odom')
    assert 'velodyne' in str(info.value) and 'base_link, camera, lidar, map, odom' in str(info.value)
    with pytest.raises(UnknownFrameError, match='no transform is known'):
        TransformBuffer().lookup('map', 'lidar', 0)


def test_disconnected_trees_are_named_by_their_roots(buf):
    buf.set_transform('world', 'gps', 5, [0, 0, 0], [0, 0, 0, 1], static=True)
    with pytest.raises(ConnectivityError) as info:
        buf.lookup('gps', 'lidar', ns(11.0))
    err = info.value
    assert (err.target, err.source, err.target_root, err.source_root) == ('gps', 'lidar', 'world', 'map')
    assert '"world"' in str(err) and '"map"' in str(err)
    assert isinstance(buf.why_not('gps', 'lidar', ns(11.0)), ConnectivityError)


def test_a_second_parent_and_loops_are_refused(buf):
    with pytest.raises(TransformError, match='"base_link" already has parent "odom"') as info:
        buf.set_transform('odom2', 'base_link', ns(11.0), [0, 0, 0], [0, 0, 0, 1])
    assert '"odom2"' in str(info.value)
    with pytest.raises(TransformError, match='loop'):
        buf.set_transform('lidar', 'map', 5, [0, 0, 0], [0, 0, 0, 1])
    assert buf.frames()['base_link'] == 'odom' and 'map' not in buf.frames()


def test_static_and_dynamic_samples_of_one_edge_are_refused(buf):
    with pytest.raises(TransformError, match='already has dynamic samples'):
        buf.set_transform('odom', 'base_link', 0, [0, 0, 0], [0, 0, 0, 1], static=True)
    with pytest.raises(TransformError, match='that edge is static'):
        buf.set_transform('base_link', 'lidar', ns(11.0), [0, 0, 0], [0, 0, 0, 1])
    # a static transform may be replaced by a newer static one
    buf.set_transform('base_link', 'lidar', 0, [1, 1, 1], [0, 0, 0, 1], static=True)
    assert_rigid(buf.lookup('base_link', 'lidar', 0), homogeneous([0, 0, 1], 0, [1, 1, 1]))


@pytest.mark.parametrize('parent, child, t, q, match', [
    ('', 'b', [0, 0, 0], [0, 0, 0, 1], 'empty frame name'),
    ('a', '/', [0, 0, 0], [0, 0, 0, 1], 'empty frame name'),
    ('a', '/a', [0, 0, 0], [0, 0, 0, 1], 'to itself'),
    ('a', 'b', [0, np.nan, 0], [0, 0, 0, 1], 'NaN or infinite'),
    ('a', 'b', [0, 0, 0], [0, 0, np.inf, 1], 'NaN or infinite'),
    ('a', 'b', [0, 0, 0], [0, 0, 0, 1.01], 'squared norm 1.02'),
    ('a', 'b', [0, 0, 0], [0, 0, 0, 0], 'not a rotation'),
    ('a', 'b', [0, 0], [0, 0, 0, 1], '3 values'),
])
def test_malformed_transforms_are_refused(parent, child, t, q, match):
    buf = TransformBuffer()
    with pytest.raises(TransformError, match=match):
        buf.set_transform(parent, child, 1, t, q)
    assert buf.frames() == {}
    with pytest.raises(TransformError, match='not an integer'):
        buf.set_transform('a', 'b', 1.5, [0, 0, 0], [0, 0, 0, 1])
    with pytest.raises(TransformError, match='negative'):
        buf.set_transform('a', 'b', -1, [0, 0, 0], [0, 0, 0, 1])


def test_near_unit_quaternions_are_normalised_and_slashes_dropped():
    buf = TransformBuffer()
    q = np.array([0.0, 0.0, 0.0, 1.004])  # squared norm 1.008: within tf2's 0.01
    buf.set_transform('/map', '/odom', 1, [1, 2, 3], q)
    assert buf.frames() == {'odom': 'map'} and buf.has_frame('/odom') and buf.has_frame('map')
    got = buf.lookup('map', '/odom', 1)
    assert np.array_equal(got.rotation, np.eye(3))


def test_errors_keep_their_attributes_through_pickle(buf):
    with pytest.raises(ExtrapolationError) as info:
        buf.lookup('map', 'lidar', ns(20.0))
    back = pickle.loads(pickle.dumps(info.value))
    assert (back.frame, back.stamp_ns, back.last_ns, back.future, str(back)) == (
        info.value.frame, info.value.stamp_ns, info.value.last_ns, True, str(info.value))
    assert isinstance(back, InputError)


# --------------------------------------------------------------------------------------
# bulk inserts
# --------------------------------------------------------------------------------------


def test_set_transforms_equals_one_by_one_in_any_order():
    rng = np.random.default_rng(1)
    k = 400
    stamps = rng.integers(0, 300, k) * 1_000_000 + S  # repeats on purpose
    pairs = [('map', 'odom'), ('odom', 'base')]
    which = rng.integers(0, 2, k)
    parents = [pairs[w][0] for w in which]
    children = [pairs[w][1] for w in which]
    x, q = rng.normal(size=(k, 3)), rot.normalise(rng.normal(size=(k, 4)))
    bulk, single = TransformBuffer(), TransformBuffer()
    assert bulk.set_transforms(parents, children, stamps, x, q) == k
    for i in np.argsort(stamps, kind='stable'):
        single.set_transform(parents[i], children[i], int(stamps[i]), x[i], q[i])
    for child in ('odom', 'base'):
        a, b = bulk._tracks[child].view(), single._tracks[child].view()
        for u, v in zip(a, b):
            np.testing.assert_array_equal(u, v)
    assert repr(bulk) == repr(single)


def test_set_transforms_strict_refuses_all_and_lenient_skips():
    buf = make_buffer()
    before = repr(buf)
    k = 5
    x = np.zeros((k, 3))
    q = np.tile([0.0, 0, 0, 1], (k, 1))
    q[2] = [0, 0, 0, 2]
    children = ['x1', 'x2', 'x3', 'base_link', 'x5']  # base_link already has parent odom
    stamps = np.arange(k, dtype=np.int64) + S
    with pytest.raises(TransformError, match='^transform 2 of 5: .*not a rotation'):
        buf.set_transforms('lidar', children, stamps, x, q)
    assert repr(buf) == before
    refused: list[str] = []
    assert buf.set_transforms('lidar', children, stamps, x, q, strict=False, refused=refused) == 3
    assert refused[0].startswith('2: ') and refused[1].startswith('3: ') and 'already has parent' in refused[1]
    assert buf.frames()['x5'] == 'lidar' and 'x3' not in buf.frames()
    # static batches keep the last transform of each edge
    n = buf.set_transforms(['base_link'] * 2, ['imu', 'imu'], np.array([7, 3]), [[1, 0, 0], [2, 0, 0]],
                           [[0, 0, 0, 1]] * 2, static=True)
    assert n == 2 and buf.time_range('imu') is None
    assert_rigid(buf.lookup('base_link', 'imu', 0), homogeneous([0, 0, 1], 0, [2, 0, 0]))
    with pytest.raises(InputError, match='integer nanoseconds'):
        buf.set_transforms('a', 'b', np.array([1.0]), x[:1], q[:1])
    with pytest.raises(InputError, match=r'\(K, 3\)'):
        buf.set_transforms('a', 'b', np.array([1]), x, q)


def test_set_transforms_takes_100k_samples_well_under_a_second():
    """100,000 samples of 3 edges from Python lists (measured ~40 ms)."""
    k = 100_000
    rng = np.random.default_rng(2)
    names = [('map', 'odom'), ('odom', 'base'), ('base', 'wheel')]
    parents = [names[i % 3][0] for i in range(k)]
    children = [names[i % 3][1] for i in range(k)]
    stamps = np.arange(k, dtype=np.int64) * 1_000_000
    x, q = rng.normal(size=(k, 3)), rot.normalise(rng.normal(size=(k, 4)))
    buf = TransformBuffer(cache_time=math.inf)
    start = time.perf_counter()
    assert buf.set_transforms(parents, children, stamps, x, q) == k
    assert time.perf_counter() - start < 1.0
    assert len(buf._tracks['base']) == k // 3 + (1 if k % 3 > 1 else 0)


# --------------------------------------------------------------------------------------
# the rest
# --------------------------------------------------------------------------------------


def test_clear_forgets_dynamic_edges_and_keeps_static_ones(buf):
    buf.clear()
    assert buf.frames() == {'lidar': 'base_link', 'camera': 'base_link'}
    assert buf.can_transform('camera', 'lidar', 0)
    buf.set_transform('odom2', 'base_link', 5, [0, 0, 0], [0, 0, 0, 1])  # a new parent is fine now
    buf.clear(static=True)
    assert buf.frames() == {} and not buf.has_frame('lidar')


def test_repr_shows_the_tree(buf):
    text = repr(buf)
    assert text.startswith('TransformBuffer(cache_time=10 s, max_extrapolation=0 s, 5 frames):')
    assert ('map -> odom (dynamic, 4 samples, 10.000-13.000 s) -> base_link (dynamic, 36 samples, '
            '10.000-13.500 s) -> camera (static)') in text
    lines = text.splitlines()
    assert lines[-1].strip() == 'base_link -> lidar (static)'
    assert lines[-1].index('base_link') == lines[-2].index('base_link')
    assert repr(TransformBuffer()).endswith('no transforms')


def test_rigid_apply_inverse_compose():
    rng = np.random.default_rng(5)
    a = Rigid.from_quaternion(rng.normal(size=3), rot.normalise(rng.normal(size=4)))
    b = Rigid.from_quaternion(rng.normal(size=3), rot.normalise(rng.normal(size=4)))
    p = rng.normal(size=(10, 3))
    np.testing.assert_allclose(a.compose(b).apply(p), a.apply(b.apply(p)), atol=1e-13)
    np.testing.assert_allclose(a.inverse().apply(a.apply(p)), p, atol=1e-13)
    np.testing.assert_allclose(a.matrix() @ b.matrix(), a.compose(b).matrix(), atol=1e-13)
    np.testing.assert_allclose(Rigid.from_quaternion(a.translation, a.quaternion()).rotation, a.rotation, atol=1e-14)
    with pytest.raises(ValueError):
        a.rotation[0, 0] = 2.0  # read-only
    with pytest.raises(InputError):
        Rigid(np.eye(2), np.zeros(3))
