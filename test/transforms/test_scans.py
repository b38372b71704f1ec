"""Tests of uncertain_facade_map.transforms.scans: point times and motion compensation (~1 s)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from uncertain_facade_map.errors import ExtrapolationError, InputError
from uncertain_facade_map.transforms import ScanPose, TransformBuffer, locate_scan, point_times

S = 1_000_000_000
STAMP = 1_700_000_000 * S + 123_456_789  # a UNIX time, ns


def cloud(field: str, values) -> np.ndarray:
    values = np.asarray(values)
    out = np.zeros(values.shape[0], dtype=[('x', 'f4'), ('y', 'f4'), ('z', 'f4'), (field, values.dtype)])
    out[field] = values
    return out


# --------------------------------------------------------------------------------------
# point_times
# --------------------------------------------------------------------------------------


def test_float32_offsets_in_seconds_velodyne():
    offsets = np.linspace(-0.05, 0.05, 101).astype(np.float32)
    got = point_times(cloud('time', offsets), STAMP, 'time')
    assert got.dtype == np.int64
    np.testing.assert_array_equal(got, STAMP + np.rint(offsets.astype(np.float64) * 1e9).astype(np.int64))
    assert abs(int(got[-1]) - (STAMP + 50_000_000)) < 10  # float32 keeps ~ns at 0.05 s


def test_uint32_offsets_in_nanoseconds_ouster():
    t = np.arange(0, 100_000_000, 97_656, dtype=np.uint32)
    np.testing.assert_array_equal(point_times(cloud('t', t), STAMP, 't'), STAMP + t.astype(np.int64))


def test_float64_absolute_seconds_hesai():
    truth = STAMP + np.arange(0, 100_000_000, 1_000_003, dtype=np.int64)
    seconds = truth / 1e9  # float64 UNIX seconds: ~240 ns resolution
    got = point_times(cloud('timestamp', seconds), 0, 'timestamp')
    assert np.abs(got - truth).max() < 300


def test_float64_absolute_nanoseconds_livox():
    truth = STAMP + np.arange(0, 100_000_000, 1_000_003, dtype=np.int64)
    got = point_times(cloud('timestamp', truth.astype(np.float64)), 0, 'timestamp')
    assert np.abs(got - truth).max() <= 128  # a double's spacing at 1.7e18 is 256


def test_int64_absolute_nanoseconds():
    truth = STAMP + np.arange(5, dtype=np.int64) * 1000
    np.testing.assert_array_equal(point_times(cloud('t', truth), 7, 't'), truth)
    np.testing.assert_array_equal(point_times(cloud('t', np.arange(3, dtype=np.int16)), STAMP, 't'),
                                  STAMP + np.arange(3))


def test_absent_or_unset_fields_give_none():
    c = cloud('time', np.zeros(3, np.float32))
    assert point_times(c, STAMP, '') is None
    assert point_times(c, STAMP, 'timestamp') is None
    assert point_times(c[:0], STAMP, 'time').shape == (0,)


@pytest.mark.parametrize('values, match', [
    (np.array([0.0, np.nan, 0.1], np.float32), '1 NaN or infinite values of 3'),
    (np.array([0.01, 1.7e9], np.float64), 'mixes absolute times'),
    (np.array([1, 2, STAMP], np.int64), 'mixes absolute times'),
    (np.array([1.7e9, 1.7e9 + 0.1], np.float32), 'absolute UNIX seconds in float32'),
])
def test_unusable_time_fields_are_refused_by_name(values, match):
    with pytest.raises(InputError, match=match) as info:
        point_times(cloud('stamp', values), STAMP, 'stamp')
    assert '"stamp"' in str(info.value)


def test_a_time_field_must_be_one_number_per_point():
    points = np.zeros(2, dtype=[('x', 'f4'), ('t', 'f8', (2,))])
    with pytest.raises(InputError, match='one number per point'):
        point_times(points, STAMP, 't')


# --------------------------------------------------------------------------------------
# motion compensation
# --------------------------------------------------------------------------------------

SPEED = 10.0  # m/s along map x
YAW_RATE = 0.8  # rad/s
T0 = STAMP  # start of the sweep
MOUNT_R = np.array([[math.cos(0.1), 0.0, math.sin(0.1)], [0.0, 1.0, 0.0], [-math.sin(0.1), 0.0, math.cos(0.1)]])
MOUNT_T = np.array([0.5, 0.0, 1.8])


def vehicle(t_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The sensor's pose in map at each time, in closed form: (K, 3, 3), (K, 3).

    The vehicle moves straight at 10 m/s while turning at a constant yaw rate, so the
    buffer's interpolation (linear in translation, slerp about a fixed axis) is exact
    between any two of its samples.
    """
    dt = (np.asarray(t_ns) - T0) / 1e9
    c, s = np.cos(YAW_RATE * dt), np.sin(YAW_RATE * dt)
    r_mb = np.zeros((dt.shape[0], 3, 3))
    r_mb[:, 0, 0], r_mb[:, 0, 1], r_mb[:, 1, 0], r_mb[:, 1, 1], r_mb[:, 2, 2] = c, -s, s, c, 1.0
    t_mb = np.stack([SPEED * dt, np.zeros_like(dt), np.zeros_like(dt)], 1)
    return r_mb @ MOUNT_R, np.einsum('kij,j->ki', r_mb, MOUNT_T) + t_mb


@pytest.fixture(scope='module')
def moving() -> TransformBuffer:
    """map -> base_link at 100 Hz over [T0 - 0.1 s, T0 + 0.2 s]; base_link -> lidar static."""
    buf = TransformBuffer()
    stamps = T0 + np.arange(-10, 21, dtype=np.int64) * 10_000_000
    dt = (stamps - T0) / 1e9
    yaw = YAW_RATE * dt
    quats = np.stack([np.zeros_like(yaw), np.zeros_like(yaw), np.sin(yaw / 2), np.cos(yaw / 2)], 1)
    xyz = np.stack([SPEED * dt, np.zeros_like(dt), np.zeros_like(dt)], 1)
    buf.set_transforms('map', 'base_link', stamps, xyz, quats)
    mount_q = [0.0, math.sin(0.05), 0.0, math.cos(0.05)]  # 0.1 rad about y, as MOUNT_R
    buf.set_transform('base_link', 'lidar', 0, MOUNT_T, mount_q, static=True)
    return buf


def sweep(n: int = 20_000, seed: int = 0):
    """Points of a wall (plane x = 25 in map) seen over a 0.1 s sweep from the moving lidar."""
    rng = np.random.default_rng(seed)
    wall = np.stack([np.full(n, 25.0), rng.uniform(-15, 15, n), rng.uniform(0, 8, n)], 1)
    offsets = np.sort(rng.integers(0, 100_000_000, n)).astype(np.uint32)  # Ouster-style t
    times = T0 + offsets.astype(np.int64)
    r, t = vehicle(times)
    in_lidar = np.einsum('kji,kj->ki', r, wall - t)  # R^T (p - t)
    points = np.zeros(n, dtype=[('x', 'f8'), ('y', 'f8'), ('z', 'f8'), ('t', 'u4')])
    points['x'], points['y'], points['z'], points['t'] = *in_lidar.T, offsets
    return points, wall, t


def test_per_point_poses_put_the_sweep_back_on_the_wall(moving):
    points, wall, origins = sweep()
    times = point_times(points, T0, 't')
    pose = locate_scan(moving, 'map', 'lidar', T0, times)
    xyz = np.stack([points['x'], points['y'], points['z']], 1)
    assert pose.rotations.shape[0] == np.unique(times).shape[0] and pose.index.shape == (len(points),)
    assert np.abs(pose.apply(xyz) - wall).max() < 1e-9
    assert np.abs(pose.origins() - origins).max() < 1e-9
    # without compensation (one pose at the stamp) the wall is smeared by about a metre
    one = locate_scan(moving, 'map', 'lidar', T0, n_points=len(points))
    assert one.single and one.origins().shape == (len(points), 3)
    assert np.abs(one.apply(xyz) - wall).max() > 0.5


def test_origins_carried_by_the_cloud_and_selections(moving):
    points, wall, origins = sweep(2_000, seed=1)
    pose = locate_scan(moving, 'map', 'lidar', T0, point_times(points, T0, 't'))
    np.testing.assert_allclose(pose.transform_origins(np.zeros((len(points), 3))), origins, atol=1e-9)
    keep = np.arange(len(points)) % 3 == 0
    sub = pose.select(keep)
    xyz = np.stack([points['x'], points['y'], points['z']], 1)
    assert np.abs(sub.apply(xyz[keep]) - wall[keep]).max() < 1e-9
    assert sub.n == int(keep.sum())
    with pytest.raises(InputError, match='rows'):
        sub.apply(xyz)


def test_a_sweep_beyond_the_poses_is_refused(moving):
    times = T0 + np.array([0, 150_000_000, 250_000_000], dtype=np.int64)
    with pytest.raises(ExtrapolationError) as info:
        locate_scan(moving, 'map', 'lidar', T0, times)
    assert info.value.future and info.value.frame == 'base_link' and info.value.stamp_ns == times[-1]


def test_identity_and_single_poses():
    ident = ScanPose.identity(4)
    p = np.arange(12.0).reshape(4, 3)
    assert np.array_equal(ident.apply(p), p) and np.array_equal(ident.origins(), np.zeros((4, 3)))
    assert ScanPose.identity().origins(2).shape == (2, 3)
    with pytest.raises(InputError, match='unknown'):
        ScanPose.identity().origins()
    assert ident.select(np.array([True, False, True, False])).n == 2
    with pytest.raises(InputError, match='need an index'):
        ScanPose(np.tile(np.eye(3), (2, 1, 1)), np.zeros((2, 3)))
    with pytest.raises(InputError, match='outside'):
        ScanPose(np.eye(3)[None], np.zeros((1, 3)), np.array([0, 1]))
    buf = TransformBuffer()
    buf.set_transform('map', 'lidar', 5, [1, 2, 3], [0, 0, 0, 1])
    pose = locate_scan(buf, 'map', 'lidar', 5, np.zeros(0, dtype=np.int64))
    assert pose.apply(np.zeros((0, 3))).shape == (0, 3)
    same = locate_scan(buf, 'lidar', 'lidar', 0, np.array([1, 2], dtype=np.int64))
    assert np.array_equal(same.apply(p[:2]), p[:2])
