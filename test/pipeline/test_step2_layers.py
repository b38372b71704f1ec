"""GMM depth layers and facets on synthetic façades with known layers."""

import numpy as np
import pytest

from uncertain_facade_map.params import LayerParams
from uncertain_facade_map.pipeline.step2_layers import count_peaks, find_facets, fit_layers


def three_layer_depths(rng, n=30000):
    share = rng.random(n)
    depth = np.where(share < 0.7, 0.0, np.where(share < 0.9, -0.2, 1.2))
    return depth + rng.normal(0, 0.02, n), depth


def test_peaks_give_the_number_of_layers():
    rng = np.random.default_rng(0)
    noisy, _ = three_layer_depths(rng)
    peaks = count_peaks(noisy, LayerParams())
    assert len(peaks) == 3
    np.testing.assert_allclose(np.sort(peaks), [-0.2, 0.0, 1.2], atol=0.015)


def test_em_recovers_means_weights_and_sigmas():
    rng = np.random.default_rng(1)
    noisy, _ = three_layer_depths(rng)
    layers = fit_layers(noisy, LayerParams(), rng)
    assert layers.n_layers == 3
    np.testing.assert_allclose(layers.means_, [-0.2, 0.0, 1.2], atol=0.003)
    np.testing.assert_allclose(layers.weights_, [0.2, 0.7, 0.1], atol=0.01)
    np.testing.assert_allclose(layers.sigmas_, 0.02, rtol=0.1)
    assert layers.means_[layers.main_] == pytest.approx(0.0, abs=0.003)


def test_single_plane_is_one_layer():
    rng = np.random.default_rng(2)
    layers = fit_layers(rng.normal(0.3, 0.02, 5000), LayerParams(), rng)
    assert layers.n_layers == 1 and layers.main_ == 0


def test_facets_are_connected_regions_of_each_layer():
    rng = np.random.default_rng(3)
    # A 10 x 6 m wall (layer 1) with two window recesses (layer 0) and a gap with no points.
    uv = rng.uniform([0, 0], [10, 6], (60000, 2))
    windows = [((1, 3), (2, 4)), ((6, 8), (2, 4))]
    label = np.ones(len(uv), dtype=np.int64)
    for (u0, u1), (v0, v1) in windows:
        label[(uv[:, 0] > u0) & (uv[:, 0] < u1) & (uv[:, 1] > v0) & (uv[:, 1] < v1)] = 0
    hole = (uv[:, 0] > 4) & (uv[:, 0] < 5.5) & (uv[:, 1] > 0.5) & (uv[:, 1] < 5)
    uv, label = uv[~hole], label[~hole]
    facets = find_facets(uv, label, 2, (0, 10, 0, 6), LayerParams())
    assert sorted(facets.layer_of_facet.tolist()) == [0, 0, 1]
    at = facets.facet_at(np.array([[2, 3], [7, 3], [0.5, 0.5], [4.75, 3.0], [4.1, 3.0]]))
    assert at[0] != at[1] and facets.layer_of_facet[at[0]] == facets.layer_of_facet[at[1]] == 0
    assert facets.layer_of_facet[at[2]] == 1
    assert at[3] == -1, 'the middle of a 1.5 m gap is beyond fill_distance: no facet'
    assert at[4] >= 0, 'the edge of the gap is filled from its neighbours'
    bounds = facets.boundaries()
    assert len(bounds) == 3
    window = bounds[at[0]]
    assert window[:, 0].min() == pytest.approx(1.05, abs=0.11) and window[:, 0].max() == pytest.approx(2.95, abs=0.11)


def test_too_few_points():
    from uncertain_facade_map.errors import InputError

    with pytest.raises(InputError):
        fit_layers(np.array([0.1]), LayerParams(), np.random.default_rng(0))


def test_a_lone_outlier_cell_is_no_facet():
    rng = np.random.default_rng(4)
    uv = rng.uniform([0, 0], [4, 4], (4000, 2))
    uv = uv[np.abs(uv - 2.05).max(axis=1) > 0.15]  # a gap of 3 x 3 cells around (2.05, 2.05)
    label = np.zeros(len(uv), dtype=np.int64)
    uv = np.vstack([uv, [[2.05, 2.05]]])  # one return of clutter in it, voted to layer 1
    label = np.r_[label, 1]
    facets = find_facets(uv, label, 2, (0, 4, 0, 4), LayerParams())
    assert facets.n_facets == 1 and facets.layer_of_facet.tolist() == [0]
    kept = find_facets(uv, label, 2, (0, 4, 0, 4), LayerParams(min_facet_cells=1))
    assert kept.n_facets == 2
