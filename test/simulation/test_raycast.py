"""Ray intersection against independent oracles (brute-force marching, matplotlib paths)."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from matplotlib.path import Path as MplPath

from uncertain_facade_map.simulation.raycast import (
    INF,
    inverse_directions,
    points_in_polygon,
    ray_aabb,
    ray_convex,
    ray_prism,
    ray_sphere,
    ray_vertical_cylinder,
)

L_SHAPE = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 8.0], [6.0, 8.0], [6.0, 3.0], [0.0, 3.0]])


def random_rays(rng, n, centre, spread=20.0):
    origins = centre + rng.uniform(-spread, spread, size=(n, 3))
    target = centre + rng.normal(0, 2.0, size=(n, 3))
    d = target - origins
    return origins, d / np.linalg.norm(d, axis=1, keepdims=True)


def first_inside_by_marching(origins, dirs, inside, t_max=60.0, step=1e-3):
    """Oracle: first t on a fine grid where ``inside`` holds."""
    ts = np.arange(0.0, t_max, step)
    out = np.full(len(origins), INF)
    for i in range(len(origins)):
        pts = origins[i] + ts[:, None] * dirs[i]
        hit = np.flatnonzero(inside(pts))
        if len(hit):
            out[i] = ts[hit[0]]
    return out


def box_planes(lo, hi):
    normals = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], float)
    offsets = np.array([hi[0], -lo[0], hi[1], -lo[1], hi[2], -lo[2]])
    return normals, offsets


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31 - 1))
def test_convex_box_matches_aabb_and_hits_the_boundary(seed):
    rng = np.random.default_rng(seed)
    lo = rng.uniform(-5, 0, 3)
    hi = lo + rng.uniform(0.1, 5, 3)
    origins, dirs = random_rays(rng, 200, (lo + hi) / 2)
    outside = np.any((origins < lo) | (origins > hi), axis=1)
    origins, dirs = origins[outside], dirs[outside]
    t_enter, t_exit = ray_convex(origins, dirs, *box_planes(lo, hi))
    t_box = ray_aabb(origins, inverse_directions(dirs), lo, hi)
    np.testing.assert_allclose(t_enter, t_box, rtol=0, atol=1e-9)
    hit = np.isfinite(t_enter)
    assert hit.any()
    p = origins[hit] + t_enter[hit, None] * dirs[hit]
    # On the boundary: inside within 1e-9, and on at least one face.
    gap = np.maximum(lo - p, p - hi).max(axis=1)
    np.testing.assert_allclose(gap, 0.0, atol=1e-9)
    assert np.all(t_exit[hit] >= t_enter[hit])


def test_aabb_handles_axis_parallel_rays():
    lo, hi = np.zeros(3), np.ones(3)
    origins = np.array([[-1.0, 0.5, 0.5], [-1.0, 1.5, 0.5], [-1.0, 0.0, 0.5], [0.5, 0.5, 0.5]])
    dirs = np.array([[1.0, 0.0, 0.0]] * 4)
    t = ray_aabb(origins, inverse_directions(dirs), lo, hi)
    assert t[0] == pytest.approx(1.0)
    assert t[1] == INF
    assert t[2] == pytest.approx(1.0)  # a ray in the plane of the face y = 0: no nan, a hit
    assert t[3] < 0  # origin inside


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 2**31 - 1))
def test_cylinder_against_marching(seed):
    rng = np.random.default_rng(seed)
    centre, radius, z0, z1 = rng.uniform(-2, 2, 2), rng.uniform(0.2, 2), 0.0, rng.uniform(1, 6)
    origins, dirs = random_rays(rng, 30, np.array([*centre, z1 / 2]), spread=8.0)

    def inside(p):
        return (((p[:, :2] - centre) ** 2).sum(1) <= radius**2) & (p[:, 2] >= z0) & (p[:, 2] <= z1)

    start_inside = inside(origins)
    origins, dirs = origins[~start_inside], dirs[~start_inside]
    t = ray_vertical_cylinder(origins, dirs, centre, radius, z0, z1)
    oracle = first_inside_by_marching(origins, dirs, inside, t_max=30.0)
    both = np.isfinite(oracle)
    # A ray grazing the cylinder (its chord shorter than the oracle's 1 mm step) can fall
    # between the oracle's samples: a hit the oracle misses counts if the hit point is on the
    # cylinder and the ray leaves it within a step (seed 64354 found one).
    grazing = np.isfinite(t) & ~both
    for i in np.flatnonzero(grazing):
        on = origins[i] + t[i] * dirs[i]
        assert abs(np.hypot(*(on[:2] - centre)) - radius) < 1e-6 or min(abs(on[2] - z0), abs(on[2] - z1)) < 1e-6
        assert not inside((origins[i] + (t[i] + 1e-3) * dirs[i])[None])[0]
    np.testing.assert_array_equal(np.isfinite(t) & ~grazing, both)
    np.testing.assert_allclose(t[both], oracle[both], atol=2e-3)


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 2**31 - 1))
def test_prism_against_marching(seed):
    rng = np.random.default_rng(seed)
    height = rng.uniform(3, 12)
    origins, dirs = random_rays(rng, 30, np.array([5.0, 4.0, height / 2]), spread=15.0)

    def inside(p):
        return points_in_polygon(p[:, :2], L_SHAPE) & (p[:, 2] >= 0) & (p[:, 2] <= height)

    keep = ~inside(origins)
    origins, dirs = origins[keep], dirs[keep]
    t, face = ray_prism(origins, dirs, L_SHAPE, 0.0, height)
    oracle = first_inside_by_marching(origins, dirs, inside, t_max=50.0)
    both = np.isfinite(oracle)
    np.testing.assert_array_equal(np.isfinite(t), both)
    np.testing.assert_allclose(t[both], oracle[both], atol=2e-3)
    assert np.all(face[both] >= 0) and np.all(face[~both] == -1)


def test_prism_face_index_names_the_wall():
    origins = np.array([[5.0, -5.0, 1.0], [12.0, 4.0, 1.0], [3.0, 1.5, 20.0]])
    dirs = np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
    t, face = ray_prism(origins, dirs, L_SHAPE, 0.0, 9.0)
    np.testing.assert_allclose(t, [5.0, 2.0, 11.0])
    assert face.tolist() == [0, 1, len(L_SHAPE)]


def test_points_in_polygon_matches_matplotlib():
    rng = np.random.default_rng(3)
    pts = rng.uniform(-2, 12, size=(5000, 2))
    expected = MplPath(L_SHAPE).contains_points(pts)
    np.testing.assert_array_equal(points_in_polygon(pts, L_SHAPE), expected)


def test_sphere_entry_and_exit():
    t0, t1 = ray_sphere(np.array([[-5.0, 0, 0], [-5.0, 3, 0]]), np.array([[1.0, 0, 0], [1.0, 0, 0]]),
                        np.zeros(3), 2.0)
    assert (t0[0], t1[0]) == pytest.approx((3.0, 7.0))
    assert t0[1] == INF and t1[1] == INF
