"""The BGKOctoMap baseline: its kernel, its training data and its map of a scanned wall."""

from __future__ import annotations

import numpy as np
import pytest
from support import WALL_Y, labelled_voxels, wall_scan

from uncertain_facade_map.errors import InputError
from uncertain_facade_map.evaluation.baselines.base import beam_samples, voxel_centroids
from uncertain_facade_map.evaluation.baselines.bgk_octomap import BGKOctoMapMethod, sparse_kernel
from uncertain_facade_map.evaluation.occupancy import pr_auc


@pytest.fixture(scope='module')
def fitted():
    hits, origins = wall_scan()
    return BGKOctoMapMethod(0.1).fit(hits, origins)


def test_the_sparse_kernel_is_sf2_at_zero_smooth_and_zero_beyond_ell():
    d = np.linspace(0, 0.3, 301)
    k = sparse_kernel(d, 2.0, 0.2)
    assert k[0] == pytest.approx(2.0) and np.all(k[d >= 0.2] == 0) and np.all(np.diff(k) <= 1e-12)
    # Continuous with a zero slope at the support radius.
    assert sparse_kernel(np.array([0.2 - 1e-6]), 2.0, 0.2)[0] < 1e-9
    # Positive semi-definite on a random set (Melkumyan and Ramos: a valid covariance in 3D).
    x = np.random.default_rng(0).uniform(0, 0.5, (200, 3))
    gram = sparse_kernel(np.linalg.norm(x[:, None] - x[None], axis=-1), 1.0, 0.2)
    assert np.linalg.eigvalsh(gram).min() > -1e-9


def test_training_data_are_downsampled_hits_and_beam_samples():
    # Two rays of one scan into one 0.1 m voxel, 1.05 m from the origin.
    hits = np.array([[1.02, 0.02, 0.02], [1.04, 0.04, 0.04]])
    centroid, group, origin = voxel_centroids(hits, 0.1, np.zeros(2, np.int64), np.zeros((2, 3)))
    np.testing.assert_allclose(centroid, [[1.03, 0.03, 0.03]]) and np.testing.assert_allclose(origin, 0)
    # Different scans are not merged.
    assert len(voxel_centroids(hits, 0.1, np.array([0, 1]))[0]) == 2
    # The library's beam_sample: every step below the length, and one step before the hit.
    samples, beam = beam_samples(np.array([[1.2, 0, 0], [0.3, 0, 0]]), np.zeros((2, 3)), 0.5)
    np.testing.assert_allclose(samples[:, 0], [0.5, 1.0, 0.7]) and np.testing.assert_array_equal(beam, 0)
    assert np.allclose(samples[:, 1:], 0)


def test_the_posterior_is_the_beta_of_the_kernel_weighted_counts():
    method = BGKOctoMapMethod(0.1, ds_resolution=0.01, free_resolution=0.5)
    method.fit(np.array([[1.2, 0.0, 0.0]]), np.zeros((1, 3)))
    # Training: the hit (1) and free samples at 0 (the origin), 0.5, 0.7 and 1.0 m (0).
    assert sorted(method.train_y_.tolist()) == [0, 0, 0, 0, 1]
    np.testing.assert_allclose(np.sort(method.train_x_[method.train_y_ == 0, 0]), [0.0, 0.5, 0.7, 1.0])
    x = np.array([[1.1, 0.0, 0.0], [3.0, 0.0, 0.0]])
    k_hit = sparse_kernel(np.array([0.1]), 1.0, 0.2)[0]
    k_free = sparse_kernel(np.array([0.1]), 1.0, 0.2)[0]  # the sample at 1.0 m (0.7 m is beyond ell)
    alpha, beta = 0.001 + k_hit, 0.001 + k_free
    np.testing.assert_allclose(method.predict(x), [alpha / (alpha + beta), 0.5])
    np.testing.assert_allclose(method.predict_variance(x)[0], alpha * beta / ((alpha + beta) ** 2 * (alpha + beta + 1)))
    assert method.predict_variance(x)[1] == pytest.approx(0.25 * 0.002 ** 2 / (0.002 ** 2 * 1.002))


def test_the_wall_is_occupied_and_the_space_before_it_free(fitted):
    centres, on_wall = labelled_voxels(0.1)
    p = fitted.predict(centres)
    assert p.shape == (len(centres),) and np.all((p >= 0) & (p <= 1))
    # Measured: mean p 0.92 on the wall, 0.04 before it, PR AUC 0.89.
    assert np.all(p[on_wall] > 0.5) and p[on_wall].mean() > 0.85 and p[~on_wall].mean() < 0.1
    assert pr_auc(on_wall, p) > 0.8
    labels = fitted.classify(centres)
    assert (labels[on_wall] == 1).mean() > 0.9 and (labels[~on_wall] == 0).mean() > 0.9
    # Nothing within ell: the prior.
    far = np.array([[5.05, WALL_Y + 1.05, 2.05], [50.0, 50.0, 50.0]])
    assert fitted.predict(far).tolist() == [0.5, 0.5]
    # Chunked queries give the same answers.
    chunked = BGKOctoMapMethod(0.1, chunk=333)
    chunked.train_x_, chunked.train_y_, chunked.tree_ = fitted.train_x_, fitted.train_y_, fitted.tree_
    np.testing.assert_allclose(chunked.predict(centres), p)


def test_bad_use_is_refused(fitted):
    with pytest.raises(InputError, match='fit the method'):
        BGKOctoMapMethod(0.1).predict(np.zeros((1, 3)))
    with pytest.raises(InputError, match='finite'):
        fitted.predict(np.full((1, 3), np.inf))
    for kwargs, match in (({'ell': 0}, 'ell'), ({'sf2': -1}, 'sf2'), ({'free_thresh': 0.8}, 'free_thresh'),
                          ({'prior_a': np.nan}, 'prior_a'), ({'chunk': 0}, 'chunk')):
        with pytest.raises(InputError, match=match):
            BGKOctoMapMethod(0.1, **kwargs)
    with pytest.raises(InputError, match='non-empty'):
        BGKOctoMapMethod(0.1).fit(np.zeros((0, 3)), np.zeros((0, 3)))
