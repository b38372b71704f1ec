"""The fast GPOM (GPOctoMap) baseline: its kernel, training data, local GPs, BCM fusion,
PLSC and its map of a scanned wall."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.linalg import cho_factor, cho_solve
from scipy.special import ndtr
from support import WALL_Y, labelled_voxels, wall_scan

from uncertain_facade_map.errors import InputError
from uncertain_facade_map.evaluation.baselines.base import beam_samples
from uncertain_facade_map.evaluation.baselines.gpom import (
    EXTENDED_BLOCK,
    FastGPOMMethod,
    _pack,
    loo_moments,
    matern32,
    voxel_centroids,
)
from uncertain_facade_map.evaluation.occupancy import pr_auc


@pytest.fixture(scope='module')
def scan():
    return wall_scan(n_origins=20, rays=300)


@pytest.fixture(scope='module')
def fitted(scan):
    return FastGPOMMethod(0.1).fit(*scan)


def test_the_matern_kernel_is_sf2_at_zero_decreasing_and_positive_definite():
    d = np.linspace(0, 5, 501)
    k = matern32(d, 2.0, 1.0)
    assert k[0] == pytest.approx(2.0) and np.all(np.diff(k) < 0) and np.all(k > 0)
    assert matern32(np.array([1.0]), 1.0, 1.0)[0] == pytest.approx((1 + np.sqrt(3)) * np.exp(-np.sqrt(3)))
    x = np.random.default_rng(0).uniform(0, 0.4, (200, 3))
    gram = matern32(np.linalg.norm(x[:, None] - x[None], axis=-1), 1.0, 1.0)
    assert np.linalg.eigvalsh(gram).min() > -1e-9


def test_training_data_are_downsampled_hits_and_beam_samples():
    # la3dm beam_sample: every 0.3 m below the range, and one 0.3 m before the hit.
    samples, beam = beam_samples(np.array([[1.0, 0, 0]]), np.zeros((1, 3)), 0.3)
    assert beam.tolist() == [0, 0, 0, 0]
    np.testing.assert_allclose(samples[:, 0], [0.3, 0.6, 0.9, 0.7]) and np.testing.assert_allclose(samples[:, 1:], 0)
    assert len(beam_samples(np.array([[0.2, 0, 0]]), np.zeros((1, 3)), 0.3)[0]) == 0
    hits = np.array([[1.02, 0.02, 0.02], [1.04, 0.04, 0.04]])
    centroid, group, origin = voxel_centroids(hits, 0.1, np.zeros(2, np.int64), np.zeros((2, 3)))
    np.testing.assert_allclose(centroid, [[1.03, 0.03, 0.03]]) and np.testing.assert_allclose(origin, 0)
    assert len(voxel_centroids(hits, 0.1, np.array([0, 1]))[0]) == 2  # scans are not merged
    # One ray from (0.05, 0.05, 0.05) to a hit 1.18 m away along x: the hit (+1) and free
    # samples (-1) at the origin, 0.3, 0.6, 0.9 and 0.88 m (the last two share a voxel).
    origin = np.full((1, 3), 0.05)
    method = FastGPOMMethod(0.1, plsc_alpha=1.0, plsc_beta=0.0).fit(origin + [1.18, 0, 0], origin)
    batch = method.batches_[0]
    order = np.argsort(batch.x[:, 0])
    np.testing.assert_allclose(batch.x[order, 0], [0.05, 0.35, 0.65, 0.94, 1.23], atol=1e-6)
    np.testing.assert_allclose(batch.x[:, 1:], 0.05, atol=1e-6)
    assert batch.y[order].tolist() == [-1, -1, -1, -1, 1]
    # Blocks of 4 voxels (0.4 m) centred on multiples of 0.4 m: round(x / 0.4).
    assert batch.keys.tolist() == sorted(_pack(np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0]])).tolist())
    assert batch.count.tolist() == [1, 1, 2, 1] and method.block_size == pytest.approx(0.4)


def _reference_posterior(method, xyz):
    """Precision and precision-weighted mean of each query by dense GPs (scipy cho_factor)
    of the blocks of its extended block, fused by the BCM as la3dm does."""
    precision = np.full(len(xyz), 1.0 / method.max_var)
    weighted = np.zeros(len(xyz))
    for batch in method.batches_:
        block_of = dict(zip(batch.keys.tolist(), range(len(batch.keys))))
        for i, point in enumerate(xyz):
            own = np.floor(point / method.block_size + 0.5).astype(np.int64)
            for key in _pack(own + EXTENDED_BLOCK).tolist():
                if key not in block_of:
                    continue
                b = block_of[key]
                rows = slice(batch.start[b], batch.start[b] + batch.count[b])
                x, y = batch.x[rows].astype(float), batch.y[rows].astype(float)
                gram = matern32(np.linalg.norm(x[:, None] - x[None], axis=-1), method.sf2, method.ell)
                factor = cho_factor(gram + method.noise * np.eye(len(x)), lower=True)
                k_star = matern32(np.linalg.norm(x - point, axis=1), method.sf2, method.ell)
                mean = k_star @ cho_solve(factor, y)
                var = method.sf2 - k_star @ cho_solve(factor, k_star)
                precision[i] += 1.0 / var - 1.0 / method.sf2
                weighted[i] += mean / var
    return precision, weighted


def test_the_fused_posterior_is_the_bcm_of_the_dense_block_gps(fitted):
    rng = np.random.default_rng(3)
    # Points on, before and behind the wall, at block faces and in between.
    xyz = np.concatenate([rng.uniform([1, WALL_Y - 1.5, 0.5], [9, WALL_Y + 0.5, 5.5], (150, 3)),
                          [[4.2, WALL_Y - 0.2, 2.2], [4.6, 7.8, 1.4], [30.0, 30.0, 30.0]]])
    precision, weighted, p = fitted._posterior(xyz)
    ref_precision, ref_weighted = _reference_posterior(fitted, xyz)
    np.testing.assert_allclose(precision, ref_precision, rtol=1e-6)
    np.testing.assert_allclose(weighted, ref_weighted, rtol=1e-6, atol=1e-6)
    # PLSC of the fused mean and (clamped) variance; unknown (0.5, max_var) far away.
    var = np.clip(1.0 / ref_precision, fitted.min_var, fitted.max_var)
    expected = ndtr((fitted.alpha_ * ref_weighted / ref_precision + fitted.beta_)
                    / np.sqrt(1 + fitted.alpha_ ** 2 * var))
    expected[-1] = 0.5
    np.testing.assert_allclose(fitted.predict(xyz), expected, rtol=1e-6)
    np.testing.assert_allclose(fitted.predict_variance(xyz), var, rtol=1e-6)
    assert fitted.predict_variance(xyz)[-1] == fitted.max_var
    # Chunking the matrices differently changes nothing.
    small = FastGPOMMethod(0.1, chunk=1000)
    small.batches_, small.alpha_, small.beta_ = fitted.batches_, fitted.alpha_, fitted.beta_
    np.testing.assert_allclose(small._posterior(xyz.copy())[0], precision, rtol=1e-10)


def test_loo_moments_are_the_gp_trained_without_the_point():
    rng = np.random.default_rng(4)
    x = rng.uniform(0, 0.4, (12, 3))
    y = np.where(rng.random(12) < 0.3, 1.0, -1.0)
    gram = matern32(np.linalg.norm(x[:, None] - x[None], axis=-1), 1.0, 1.0) + 0.01 * np.eye(12)
    mu, var = loo_moments(np.linalg.cholesky(gram)[None], y[None])
    for i in range(12):
        keep = np.arange(12) != i
        factor = cho_factor(gram[np.ix_(keep, keep)])
        assert mu[0, i] == pytest.approx(gram[i, keep] @ cho_solve(factor, y[keep]))
        assert var[0, i] == pytest.approx(gram[i, i] - gram[i, keep] @ cho_solve(factor, gram[keep, i]))


def test_batches_of_scans_are_fused_by_the_nested_bcm():
    # Two scans 4 m apart: by default (as la3dm) each scan is a batch of its own.
    a_hits, a_origins = wall_scan(n_origins=1, rays=1500, seed=1)
    b_hits, b_origins = wall_scan(n_origins=1, rays=1500, seed=2)
    b_hits, b_origins = b_hits + [4.0, 0, 0], b_origins + [4.0, 0, 0]
    fixed = {'plsc_alpha': 1.0, 'plsc_beta': 0.0}
    hits, origins = np.r_[a_hits, b_hits], np.r_[a_origins, b_origins]
    both = FastGPOMMethod(0.1, **fixed).fit(hits, origins)
    assert len(both.batches_) == 2 and both.n_scans_ == 2
    # One batch pools both scans' training data (fewer points: shared voxels merge).
    pooled = FastGPOMMethod(0.1, n_batches=1, **fixed).fit(hits, origins)
    assert len(pooled.batches_) == 1 and len(pooled.batches_[0].x) < sum(len(b.x) for b in both.batches_)
    one_a = FastGPOMMethod(0.1, **fixed).fit(a_hits, a_origins)
    one_b = FastGPOMMethod(0.1, **fixed).fit(b_hits, b_origins)
    xyz = np.random.default_rng(5).uniform([2, WALL_Y - 2, 0.5], [7, WALL_Y + 0.3, 5.5], (300, 3))
    precision, weighted, _ = both._posterior(xyz)
    prior = 1.0 / both.max_var
    parts = (one_a._posterior(xyz)[0] - prior) + (one_b._posterior(xyz)[0] - prior)
    np.testing.assert_allclose(precision - prior, parts, rtol=1e-9)
    np.testing.assert_allclose(weighted, one_a._posterior(xyz)[1] + one_b._posterior(xyz)[1], rtol=1e-9, atol=1e-12)


def test_the_wall_is_occupied_and_the_space_before_it_free(fitted):
    centres, on_wall = labelled_voxels(0.1)
    p = fitted.predict(centres)
    assert p.shape == (len(centres),) and np.all((p >= 0) & (p <= 1))
    # Measured: PR AUC 0.9998; p on the wall: mean 0.60, 5th percentile 0.48; before it:
    # mean 0.018, 95th percentile 0.088, max 0.46; alpha 1.48, beta -0.91. PLSC with the
    # LOO-learnt beta < 0 (free samples outnumber hits) puts the wall just above 0.5.
    assert pr_auc(on_wall, p) > 0.99
    assert p[on_wall].mean() > 0.5 and p[~on_wall].mean() < 0.05 and np.percentile(p[~on_wall], 95) < 0.2
    assert fitted.alpha_ > 0 and fitted.beta_ < 0
    var = fitted.predict_variance(centres)
    assert np.all((var >= fitted.min_var) & (var <= fitted.max_var))
    assert (fitted.classify(centres)[~on_wall] == 0).mean() > 0.95  # measured 0.996
    # The library's logistic squashing (its thresholds are meant for it) on the same map:
    # measured PR AUC 0.992, every wall voxel above 0.96 and classified occupied.
    logistic = FastGPOMMethod(0.1, squash='logistic')
    logistic.batches_ = fitted.batches_
    q = logistic.predict(centres)
    assert np.all((q >= 0) & (q <= 1)) and pr_auc(on_wall, q) > 0.98
    labels = logistic.classify(centres)
    assert (labels[on_wall] == 1).mean() > 0.95 and (labels[~on_wall] == 0).mean() > 0.9  # measured 1.0, 0.96
    # No training data in the extended block: unknown.
    far = np.array([[50.0, 50.0, 50.0], [5.0, WALL_Y + 3.0, 2.0]])
    assert fitted.predict(far).tolist() == [0.5, 0.5]
    assert fitted.predict(np.zeros((0, 3))).shape == (0,)


def test_bad_use_is_refused(fitted):
    with pytest.raises(InputError, match='fit the method'):
        FastGPOMMethod(0.1).predict(np.zeros((1, 3)))
    with pytest.raises(InputError, match='finite'):
        fitted.predict(np.full((1, 3), np.nan))
    for kwargs, match in (({'ell': 0}, 'ell'), ({'noise': -1}, 'noise'), ({'block_depth': 1}, 'block_depth'),
                          ({'min_var': 10.0, 'max_var': 1.0}, 'min_var'), ({'squash': 'probit'}, 'squash'),
                          ({'plsc_alpha': 1.0}, 'both'), ({'plsc_alpha': -1.0, 'plsc_beta': 0.0}, 'plsc_alpha'),
                          ({'n_batches': 0}, 'n_batches'), ({'free_thresh': 0.9}, 'free_thresh'),
                          ({'free_resolution': np.nan}, 'free_resolution')):
        with pytest.raises(InputError, match=match):
            FastGPOMMethod(0.1, **kwargs)
    with pytest.raises(InputError, match='resolution'):
        FastGPOMMethod(0.0)
    with pytest.raises(InputError, match='non-empty'):
        FastGPOMMethod(0.1).fit(np.zeros((0, 3)), np.zeros((0, 3)))
