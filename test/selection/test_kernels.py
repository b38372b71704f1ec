"""Tests of uncertain_facade_map.selection._kernels: the compiled loops give what numpy's
reductions give, bit for bit (the selection's figures depend on it), on seeded clouds of
dense and sparse cells. About 3 s (the kernels load from numba's cache; 10 s when compiled).
"""

from __future__ import annotations

import numpy as np
import pytest

from uncertain_facade_map.selection import _kernels
from uncertain_facade_map.selection import building_points as bp


def cloud(seed: int, n: int = 4000) -> np.ndarray:
    """(n, 3) points: a dense wall, a sparse scatter and a few far outliers, metres."""
    rng = np.random.default_rng(seed)
    wall = np.c_[rng.uniform(0, 12, n // 2), 3.0 + rng.normal(0, 0.05, n // 2), rng.uniform(0, 6, n // 2)]
    scatter = rng.uniform([-20, -20, 0], [20, 20, 3], (n // 2 - 5, 3))
    far = rng.uniform([-300, -300, 0], [300, 300, 5], (5, 3))
    return np.r_[wall, scatter, far] + rng.uniform(-1000, 1000, 3).round()


@pytest.mark.parametrize('seed', range(3))
def test_cells_group_the_points_as_numpy_unique_does(seed):
    xy = cloud(seed)[:, :2]
    cells = bp._Cells(xy, 0.5, 6)
    codes, inverse = np.unique(cells.code(np.floor(xy / 0.5).astype(np.int64)), return_inverse=True)
    assert np.array_equal(cells.codes, codes)
    assert np.array_equal(cells.of_point, inverse.ravel())
    assert np.array_equal(cells.members, np.argsort(inverse.ravel(), kind='stable'))
    assert np.array_equal(cells.keys, np.floor(xy / 0.5).astype(np.int64)[cells.members[cells.start[:-1]]])
    offsets = _kernels.window_offsets(1)
    found = cells.neighbours(offsets)
    for k, (dx, dy) in enumerate(offsets):
        want = cells.code(cells.keys + [dx, dy])
        pos = np.minimum(np.searchsorted(cells.codes, want), len(cells.codes) - 1)
        assert np.array_equal(found[:, k], np.where(cells.codes[pos] == want, pos, -1))


@pytest.mark.parametrize('seed', range(3))
def test_window_sums_equal_numpy_bincount_over_point_window_pairs(seed):
    """The line fits of the windows, as the numpy version took them (bincount over pairs)."""
    q = cloud(seed)
    q = q - np.round(np.median(q, axis=0))
    band = 0.4
    cells = bp._Cells(q[:, :2], 0.5, 6)
    n_cells = len(cells.codes)
    offsets = _kernels.window_offsets(1)
    nbr = cells.neighbours(offsets)
    point_keys = cells.keys[cells.of_point]
    pi, wi = [], []
    for dx, dy in offsets:
        pos = np.searchsorted(cells.codes, cells.code(point_keys - [dx, dy]))
        pos = np.minimum(pos, n_cells - 1)
        ok = cells.codes[pos] == cells.code(point_keys - [dx, dy])
        pi.append(np.flatnonzero(ok))
        wi.append(pos[ok])
    pi, wi = np.concatenate(pi), np.concatenate(wi)
    rel = q[pi, :2] - cells.centres[wi]
    weight = np.ones(len(pi))
    xy = np.ascontiguousarray(q[cells.members, :2])
    mean = normal = np.zeros((n_cells, 2))
    for k in range(3):
        total = np.maximum(np.bincount(wi, weight, n_cells), 1e-12)
        want_mean = np.stack([np.bincount(wi, weight * rel[:, j], n_cells) / total for j in (0, 1)], axis=1)
        d = rel - want_mean[wi]
        want = [np.bincount(wi, weight * d[:, 0] ** 2, n_cells) / total,
                np.bincount(wi, weight * d[:, 1] ** 2, n_cells) / total,
                np.bincount(wi, weight * d[:, 0] * d[:, 1], n_cells) / total]
        got_total, mean, *got = _kernels.moments(xy, cells.centres, cells.start, nbr, mean, normal, band, k == 0)
        assert np.array_equal(got_total, total)
        assert np.array_equal(mean, want_mean)
        for a, b in zip(got, want):
            assert np.array_equal(a, b)
        angle = 0.5 * np.arctan2(2 * got[2], got[0] - got[1])
        normal = np.stack([-np.sin(angle), np.cos(angle)], axis=1)
        dist = np.einsum('ij,ij->i', d, normal[wi])
        weight = (np.abs(dist) < band).astype(np.float64)
    inside = weight > 0
    at_top = np.random.default_rng(seed).random(len(q)) < 0.3
    origin = np.random.default_rng(seed + 1).normal(0, 5, (len(q), 2))
    points, count, sq, top, bottom, n_top, origin_sum = _kernels.band_stats(
        q[cells.members], cells.centres, cells.start, nbr, mean, normal, band, at_top[cells.members],
        origin[cells.members])
    assert np.array_equal(points, np.bincount(wi, minlength=n_cells))
    assert np.array_equal(count, np.bincount(wi, inside, n_cells))
    assert np.array_equal(sq, np.bincount(wi, inside * dist ** 2, n_cells))
    want_top = np.full(n_cells, -np.inf)
    np.maximum.at(want_top, wi[inside], q[pi[inside], 2])
    assert np.array_equal(top, want_top)
    seen = inside & at_top[pi]
    assert np.array_equal(n_top, np.bincount(wi[seen], minlength=n_cells))
    assert np.array_equal(origin_sum[:, 1], np.bincount(wi[seen], origin[pi[seen], 1], n_cells))
    windows = np.flatnonzero(count >= 10)
    keep = np.zeros(len(q), dtype=bool)
    keep[cells.members] = _kernels.band_points(xy, cells.centres, cells.start, nbr, mean, normal, band, windows)
    want_keep = np.zeros(len(q), dtype=bool)
    want_keep[pi[inside & np.isin(wi, windows)]] = True
    assert np.array_equal(keep, want_keep)


@pytest.mark.parametrize('seed', range(3))
def test_ground_cells_equal_numpy(seed):
    pts = cloud(seed)
    pts = pts - np.round(np.median(pts, axis=0))
    centre = np.median(pts[:, :2], axis=0)
    near = np.sum((pts[:, :2] - centre) ** 2, axis=1) <= 20.0 ** 2
    _, cell = bp._cell_index(pts[near, :2], 1.0)
    low = np.full(cell.max() + 1, np.inf)
    np.minimum.at(low, cell, pts[near, 2])
    got = _kernels.lowest_per_cell(pts, centre[0], centre[1], 20.0, 1.0, 10)
    assert np.array_equal(np.sort(got), np.sort(low))
    keys, inverse = bp._cell_index(pts[:, :2], 2.0)
    got_keys, height = _kernels.mean_height_per_cell(pts, 2.0)
    assert np.array_equal(got_keys, keys)
    assert np.array_equal(height, np.bincount(inverse, pts[:, 2]) / np.bincount(inverse))
    assert _kernels.column_means(pts[:, :2]) == tuple(pts[np.arange(len(pts)), :2].mean(axis=0))


def test_a_scan_wider_than_the_dense_grid_takes_numpys_way():
    """A cloud with two points 10,000 km apart: the grid kernels decline, numpy answers."""
    pts = np.array([[0.0, 0.0, 1.0], [1e7, 1e7, 2.0], [0.5, 0.5, 0.5]])
    assert len(_kernels.lowest_per_cell(pts, 0.0, 0.0, 1.0, 1.0, 10)) == 0
    assert len(_kernels.mean_height_per_cell(pts, 1.0)[0]) == 0
    assert bp._ground_level(pts, np.zeros(2)) == 1.25  # lowest of the two cells: 0.5 and 2.0
    assert bp._ground_height(np.zeros((1, 2)), pts, 0.0, 1.0).tolist() == [0.75]


def test_grouping_is_a_stable_argsort_also_for_codes_too_large_to_pack():
    rng = np.random.default_rng(0)
    for codes in (rng.integers(0, 50, 1000), np.array([2 ** 61, 0, 2 ** 61, 5, 0])):
        order = np.argsort(codes, kind='stable')
        got_codes, got_order = bp._grouped(codes)
        assert np.array_equal(got_order, order) and np.array_equal(got_codes, codes[order])
