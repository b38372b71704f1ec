"""The compiled per-point reading (issue 27) against the KD-tree and numpy reference, seeded."""

import numpy as np

from uncertain_facade_map.pipeline.local_kernels import PointGrid
from uncertain_facade_map.pipeline.step7_local_surface import LocalSurface


def walls(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Two walls at a corner with a 0.3 m recess and a few stray points far from them."""
    a = np.c_[rng.uniform(0, 8, 3000), rng.normal(0, 0.01, 3000), rng.uniform(0, 5, 3000)]
    a[a[:, 0] > 4, 1] -= 0.3
    b = np.c_[rng.normal(8, 0.01, 2000), rng.uniform(0, 6, 2000), rng.uniform(0, 5, 2000)]
    stray = rng.uniform([-20, -20, 0], [30, 30, 10], (5, 3))
    return np.r_[a, b, stray], np.r_[np.zeros(3000, np.int32), np.ones(2000, np.int32), np.full(5, -1, np.int32)]


def test_kernels_read_as_the_kd_tree_does():
    """Same neighbours, planes, leverage, signs and façades as the reference, to 1e-9 m,
    for points near the walls, off them, far from everything, and leave-one-out."""
    rng = np.random.default_rng(5)
    pts, fid = walls(rng)
    local = LocalSurface(pts, fid, np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0]]), neighbours=12)
    q = np.r_[pts[rng.choice(len(pts), 2000)] + rng.normal(0, 0.3, (2000, 3)),
              rng.uniform([-30, -30, -5], [40, 40, 15], (200, 3))]
    for skip in (None, np.arange(0, len(pts), 7)):
        x = q if skip is None else pts[skip]
        got = local._raw(x, skip)
        want = local._raw_kd(x, skip)
        assert np.array_equal(got[0], want[0])
        for a, b in zip(got[1:], want[1:]):
            assert np.allclose(a, b, rtol=1e-9, atol=1e-9, equal_nan=True)
    # With a radius: points without a stored point within it are not read.
    got = local._raw(q, radius=0.5)
    near = got[6] < 0.5
    want = local._raw_kd(q[near])
    assert np.array_equal(np.sort(np.flatnonzero(near)), np.flatnonzero(local._raw_kd(q)[6] < 0.5))
    for a, b in zip(got[1:6], want[1:6]):
        assert np.allclose(a[near], b, rtol=1e-9, atol=1e-9)


def test_grid_subset_and_tiny_maps():
    rng = np.random.default_rng(2)
    pts, fid = walls(rng)
    grid = PointGrid(pts, 0.2)
    assert np.array_equal(np.sort(grid.order), np.arange(len(pts)))
    assert np.array_equal(grid.points, pts[grid.order])
    keep = rng.random(len(pts)) < 0.7
    sub = grid.subset(keep)
    assert np.array_equal(sub.points, pts[keep][sub.order])
    # Fewer stored points than K + 2: the numpy reading answers, as before.
    tiny = LocalSurface(pts[:8], fid[:8], np.array([[0.0, 1.0, 0.0]]), neighbours=12)
    r = tiny.read(pts[:3] + 0.01)
    assert np.all(np.isfinite(r.signed_distance))


def test_far_coordinates_and_far_queries():
    """A map in UTM-like coordinates (hundreds of km from the origin), queries beside it and
    absurdly far away: the same reading as the KD-tree's."""
    rng = np.random.default_rng(4)
    pts, fid = walls(rng)
    pts = pts + np.array([512_345.0, 5_412_345.0, 250.0])
    local = LocalSurface(pts, fid, np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0]]), neighbours=12)
    q = np.r_[pts[:500] + rng.normal(0, 0.2, (500, 3)), [[0.0, 0.0, 0.0], [1e12, -1e12, 3.0]]]
    got, want = local._raw(q), local._raw_kd(q)
    assert np.array_equal(got[0], want[0])
    for a, b in zip(got[1:], want[1:]):
        assert np.allclose(a, b, rtol=1e-9, atol=1e-7, equal_nan=True)
    r = local.read(q)
    assert np.all(r.weight[-2:] == 0) and np.all(r.facade[-2:] == -1)


def test_closed_form_normal_and_in_plane_axes_against_numpy():
    """The closed-form normal (and the 2 x 2 in-plane eigen-decomposition) against numpy's
    eigh on seeded scatters from flat to nearly degenerate (the two smallest eigenvalues
    1e-9 to 1 of the spread apart, in metres of a UTM-like map and of a room): the same
    axes to 1e-9 where it answers, and it leaves the near-degenerate ones to Jacobi."""
    from uncertain_facade_map.pipeline.local_kernels import _GAP, _in_plane, _plane_normal

    rng = np.random.default_rng(11)
    answered = 0
    for _ in range(3000):
        q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        top = 10.0 ** rng.uniform(-4, 2)
        lam = np.sort(top * np.array([10.0 ** rng.uniform(-12, 0), 10.0 ** rng.uniform(-9, 0), 1.0]))
        a = (q * lam) @ q.T
        a = 0.5 * (a + a.T)
        want_lam, want = np.linalg.eigh(a)
        n = np.zeros(3)
        ok = _plane_normal(a.copy(), n)
        gap = (want_lam[1] - want_lam[0]) / (want_lam[2] - want_lam[0])
        if gap < 0.1 * _GAP:
            assert not ok
        if not ok:
            assert gap < 10 * _GAP
            continue
        answered += 1
        assert abs(np.linalg.norm(n) - 1.0) < 1e-12
        # The angle error of an eigenvector is rounding / gap, numpy's as the closed form's.
        assert np.linalg.norm(np.cross(n, want[:, 0])) < 1e-10 + 1e-13 / gap
        vec, got_lam = np.zeros((3, 3)), np.zeros(3)
        _in_plane(a, n, vec, got_lam)
        assert np.allclose(got_lam[1:], want_lam[1:], rtol=1e-9, atol=1e-12 * top)
        if want_lam[2] - want_lam[1] > 1e-6 * top:  # distinct in-plane axes: the same directions
            assert np.linalg.norm(np.cross(vec[:, 2], want[:, 2])) < 1e-10 + 1e-13 * top / (want_lam[2] - want_lam[1])
        assert np.allclose(vec.T @ vec, np.eye(3), atol=1e-12)
    assert answered > 2000


def test_a_cut_leaves_its_half_space_out_as_a_smaller_map_would():
    """With a half-space cut per point, the reading equals the reading of the stored points
    outside it (the KD-tree reference on that subset), for each of a few cuts."""
    rng = np.random.default_rng(8)
    pts, fid = walls(rng)
    normals = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])
    local = LocalSurface(pts, fid, normals, neighbours=12)
    x = pts[rng.choice(3000, 40)] + rng.normal(0, 0.05, (40, 3))
    along = np.array([1.0, 0.0, 0.0])
    for gap in (0.0, 0.2, 0.45):
        cut = np.c_[np.tile(along, (len(x), 1)), x @ along - gap]
        got = local._raw(x, cut=cut)
        for i in range(0, len(x), 8):
            keep = pts @ along <= cut[i, 3]
            want = LocalSurface(pts[keep], fid[keep], normals, neighbours=12)._raw_kd(x[i:i + 1])
            assert got[0][i] == want[0][0]
            for a, b in zip(got[1:], want[1:]):
                assert np.allclose(a[i], b[0], rtol=1e-9, atol=1e-9)
            assert got[7][i] >= gap  # the lever arm spans the cut's gap at least
