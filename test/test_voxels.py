"""Voxel keys and the voxels a scan's rays label or cross."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from uncertain_facade_map.voxels import pack_keys, ray_crossings, reference_voxels, unpack_keys, voxel_index


@settings(max_examples=50, deadline=None)
@given(st.lists(st.tuples(*[st.integers(-(1 << 20), (1 << 20) - 1)] * 3), min_size=1, max_size=50))
def test_keys_unpack_to_their_indices(index):
    index = np.array(index, dtype=np.int64)
    np.testing.assert_array_equal(unpack_keys(pack_keys(index)), index)


def test_rays_count_once_per_voxel_over_their_last_metres():
    r = 0.1
    # Three rays along +x from x = 0 to points at x = 10.03 (in voxel 100), one more to
    # x = 3.02 (voxel 30); y and z inside voxel (0, 0).
    points = np.array([[10.03, 0.05, 0.05]] * 3 + [[3.02, 0.05, 0.05]])
    origins = np.array([[0.0, 0.05, 0.05]] * 4)
    i = np.arange(0, 101)
    keys = pack_keys(np.stack([i, np.zeros_like(i), np.zeros_like(i)], 1))
    n = ray_crossings(points, origins, r, keys, reach=5.0)
    # Samples every r/3 from the origin up to r/2 before the point: the long rays' last 5 m
    # cross voxels 50..99, the short ray voxels 0..29.
    expected = np.zeros(101, dtype=np.int64)
    expected[50:100] += 3
    expected[0:30] += 1
    np.testing.assert_array_equal(n, expected)
    # With the whole rays traced, the free voxels are those reference_voxels finds.
    whole = ray_crossings(points, origins, r, keys, reach=100.0)
    labels = reference_voxels(points, origins, r)
    free = pack_keys(voxel_index(labels.centres[~labels.positive], r))
    hits = set(pack_keys(voxel_index(points, r)).tolist())  # reference_voxels leaves them out of the free ones
    assert set(keys[whole > 0].tolist()) - hits == set(free.tolist())
    assert whole[:30].tolist() == [4] * 30 and whole[30:100].tolist() == [3] * 70


def test_carving_takes_log_odds_per_ray_and_its_weight_is_learnt():
    from uncertain_facade_map.pipeline.step8_occupancy import carve, fit_carving

    p = np.array([0.5, 0.9, 0.0, 1.0 - 1e-9])
    out = carve(p, np.array([1, 2, 5, 0]), np.log(3.0))
    assert out[0] == pytest.approx(0.25) and out[1] == pytest.approx(0.5) and out[2] == 0.0
    assert out[3] == pytest.approx(p[3])
    rng = np.random.default_rng(0)
    n = 50_000
    p0 = rng.uniform(0.05, 0.95, n)
    k = rng.integers(0, 4, n)
    labels = rng.random(n) < carve(p0, k, 0.8)
    assert fit_carving(labels, np.ones(n), p0, k) == pytest.approx(0.8, abs=0.08)
    assert fit_carving(labels, np.ones(n), p0, np.zeros(n, int)) == 0.0


def test_near_keys_hold_every_point_within_a_cell_side():
    """The cells near_keys gives hold every point within ``side`` of one of the points (the
    old points a new point's normal may need), wrapped keys included, and no cell more
    than one cell away."""
    from uncertain_facade_map.voxels import near_keys, wrapped_keys

    rng = np.random.default_rng(12)
    for side, offset in ((1.0, 0.0), (0.1, -3.0e4), (0.5, 5.2e5)):
        xyz = offset + rng.uniform(-5.0, 5.0, (300, 3))
        keys = near_keys(xyz, side)
        assert np.all(keys[1:] > keys[:-1]), 'sorted and unique'
        direction = rng.normal(size=(300, 3))
        within = xyz + direction / np.linalg.norm(direction, axis=1)[:, None] * rng.uniform(0, side, (300, 1))
        assert np.isin(wrapped_keys(within, side), keys).all()
        far = xyz + np.array([2.01 * side, 0.0, 0.0])
        lonely = np.linalg.norm(far[:, None] - xyz[None], axis=2).min(axis=1) > 3.5 * side
        assert not np.isin(wrapped_keys(far[lonely], side), keys).any()
