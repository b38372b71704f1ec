"""Occupancy from the uncertain surface."""

import numpy as np
import pytest

from uncertain_facade_map.pipeline.step8_occupancy import UNKNOWN, occupancy_probability


def test_occupancy_is_a_cumulative_gaussian_of_the_signed_distance():
    s = np.array([-1.0, 0.0, 0.05, 0.1, 1.0, np.nan])
    p = occupancy_probability(s, np.full(6, 0.0), 0.02**2, 0.1)
    assert p[0] == pytest.approx(1.0) and p[4] == pytest.approx(0.0)
    assert p[2] == pytest.approx(0.5)  # the voxel's outer face on the surface
    assert p[1] > 0.99 and p[3] < 0.01
    assert p[5] == UNKNOWN
    assert np.all(np.diff(p[:5]) <= 0), 'occupancy falls with the distance outside'
    wide = occupancy_probability(np.array([0.2]), np.array([0.04]), 0.0, 0.1)
    narrow = occupancy_probability(np.array([0.2]), np.array([0.0001]), 0.0, 0.1)
    assert wide[0] > narrow[0], 'more variance, less certainty of free space'


def test_surface_probabilities_of_a_column_of_voxels_add_up_to_one():
    from uncertain_facade_map.pipeline.step8_occupancy import half_depth, surface_probability

    # Voxels stacked along the normal partition the depth axis: the surface is in one of them.
    rng = np.random.default_rng(3)
    for _ in range(20):
        h, offset, var, noise = rng.uniform(0.02, 0.1), rng.uniform(-0.1, 0.1), rng.uniform(0, 0.01), 4e-4
        s = offset + 2 * h * np.arange(-200, 201)
        p = surface_probability(s, np.full(len(s), var), noise, h)
        assert p.sum() == pytest.approx(1.0, abs=1e-9) and np.all((p >= 0) & (p <= 1))
        # The voxel holding the mean surface is the likeliest.
        assert np.argmax(p) == np.argmin(np.abs(s))
    assert surface_probability(np.array([np.nan]), np.array([np.nan]), 0.0, 0.05).tolist() == [0.0]
    assert half_depth(np.array([[0.0, 1.0, 0.0], [np.sqrt(0.5), np.sqrt(0.5), 0.0]]), 0.1) == pytest.approx(
        [0.05, 0.1 / np.sqrt(2)])


def test_each_voxel_takes_the_half_depth_of_its_facade_or_half_a_voxel_without_one():
    from uncertain_facade_map.pipeline.step8_occupancy import facade_half_depth

    normals = np.array([[0.0, 1.0, 0.0], [np.sqrt(0.5), np.sqrt(0.5), 0.0]])
    h = facade_half_depth(np.array([1, -1, 0, 1]), normals, 0.1)
    np.testing.assert_allclose(h, [0.1 / np.sqrt(2), 0.05, 0.05, 0.1 / np.sqrt(2)])
    assert facade_half_depth(np.array([-1, -1]), np.empty((0, 3)), 0.2).tolist() == [0.1, 0.1]
