"""Queries at façade locations and 3D points on a hand-made façade model."""

import numpy as np
import pytest

from uncertain_facade_map.datatypes import SOURCE_GLOBAL, ExtractedFacade, FacadeFrame, SurfaceRaster
from uncertain_facade_map.errors import InputError
from uncertain_facade_map.params import MapParams
from uncertain_facade_map.pipeline.step6_surface import fit_facade
from uncertain_facade_map.pipeline.step7_queries import (
    STEP_REACH,
    cached_step_depth_range,
    nearer_step_faces,
    query_points,
    surface_at,
)


@pytest.fixture(scope='module')
def model():
    rng = np.random.default_rng(0)
    uv = rng.uniform(0, 8, (40000, 2))
    truth = np.where(uv[:, 0] > 4, 0.5, 0.0)  # a 50 cm step in the middle
    d = truth + rng.normal(0, 0.02, len(uv))
    frame = FacadeFrame.from_normal(np.array([0.0, 10.0, 0.0]), np.array([0.0, -1.0, 0.0]))
    extracted = ExtractedFacade(frame, np.arange(len(uv)), np.c_[uv, d], np.ones(len(uv)), (0, 8, 0, 8))
    return fit_facade(extracted, MapParams(), rng)


def test_surface_follows_both_sides_of_a_step(model):
    mean, var = surface_at(model.surface, np.array([[2.0, 4.0], [6.0, 4.0], [3.9, 4.0], [4.1, 4.0]]))
    assert mean[0] == pytest.approx(0.0, abs=0.03) and mean[1] == pytest.approx(0.5, abs=0.03)
    assert mean[2] < 0.25 < mean[3], 'bilinear interpolation must not blend across facets'
    assert np.all(var > 0) and np.all(var < 0.01)


def test_point_query_answers(model):
    frame = model.frame
    local = np.array([[2.0, 4.0, 0.3], [2.0, 4.0, -0.3], [6.0, 4.0, 0.5], [20.0, 4.0, 0.0], [2.0, 4.0, 5.0]])
    xyz = frame.to_world(local)
    res = query_points([model], xyz, 0.1, 1.0, 2.0)
    assert res.facade.tolist() == [0, 0, 0, -1, -1]
    assert res.signed_distance[0] == pytest.approx(0.3, abs=0.03)
    assert res.signed_distance[1] == pytest.approx(-0.3, abs=0.03)
    assert res.signed_distance[2] == pytest.approx(0.0, abs=0.03)
    assert res.p_occupied[0] < 0.01 and res.p_occupied[1] > 0.99 and res.p_occupied[2] > 0.5
    from scipy.special import ndtr

    sigma = np.sqrt(res.variance[:3] + res.noise_variance[:3])
    np.testing.assert_allclose(res.p_occupied[:3], ndtr((0.05 - res.signed_distance[:3]) / sigma))
    # sigma_eta is estimated from the points (their noise is 2 cm).
    np.testing.assert_allclose(np.sqrt(res.noise_variance[:3]), 0.02, rtol=0.1)
    assert np.isnan(res.mean_depth[3]) and res.p_occupied[3] == 0.5
    for key, arr in res.as_dict().items():
        assert arr.shape == ((5, 3) if key == 'normal' else (5,))
    np.testing.assert_allclose(res.normal[:3] @ frame.normal, 1.0, atol=0.05)  # a flat wall's answers
    assert np.isnan(res.normal[3:]).all()


def test_points_on_the_face_of_a_step_are_on_the_surface(model):
    """The face of the 50 cm step at u = 4 m is surface: points on it are near, not 25 cm off."""
    depth = np.array([0.1, 0.25, 0.4])
    on_face = np.c_[np.full(3, 4.0), np.full(3, 4.0), depth]
    beside = np.c_[np.full(3, 3.6), np.full(3, 4.0), depth]  # 40 cm from the face, on its low side
    res = query_points([model], model.frame.to_world(np.vstack([on_face, beside])), 0.1, 1.0, 2.0)
    assert np.all(np.abs(res.signed_distance[:3]) <= 0.1)  # within a cell of the face
    np.testing.assert_allclose(res.signed_distance[3:], depth, atol=0.03)  # the wall below is nearer
    assert np.all(res.signed_distance[3:] > 0)  # outside
    assert np.all(res.variance[:3] >= 0.1**2 / 12)  # the face's position is known to a cell


def test_bad_query_points(model):
    with pytest.raises(InputError, match='NaN or infinite'):
        query_points([model], np.array([[0.0, np.nan, 0.0]]), 0.1, 1.0, 2.0)
    with pytest.raises(InputError, match=r'\(N, 3\)'):
        query_points([model], np.zeros((4, 2)), 0.1, 1.0, 2.0)
    with pytest.raises(InputError, match='resolution'):
        query_points([model], np.zeros((1, 3)), 0.0, 1.0, 2.0)


def _nearer_step_faces_one_face_at_a_time(raster, uvd, distance, var, reach):
    """The search as first written, one candidate face per numpy pass: the reference the
    vectorised :func:`nearer_step_faces` must equal exactly."""
    distance, var = distance.copy(), var.copy()
    cell = raster.cell
    todo = np.flatnonzero(np.abs(distance) > 0.25 * cell)
    h, w = raster.mean.shape
    observed = raster.source != SOURCE_GLOBAL
    k = int(np.ceil(reach / cell))
    u = (uvd[todo, 0] - raster.origin[0]) / cell
    v = (uvd[todo, 1] - raster.origin[1]) / cell
    d = uvd[todo, 2]
    row, col = np.floor(v).astype(np.int64), np.floor(u).astype(np.int64)
    best, best_var = np.abs(distance[todo]) / cell, var[todo]
    for dr in range(-k - 1, k + 1):
        for dc in range(-k - 1, k + 1):
            r, c = row + dr, col + dc
            for across_u in (True, False):
                r2, c2 = (r, c + 1) if across_u else (r + 1, c)
                ok = (r >= 0) & (c >= 0) & (r2 < h) & (c2 < w)
                ra, ca, rb, cb = (np.where(ok, x, 0) for x in (r, c, r2, c2))
                ma, mb = raster.mean[ra, ca], raster.mean[rb, cb]
                ok &= observed[ra, ca] & observed[rb, cb] & (np.minimum(ma, mb) <= d) & (d <= np.maximum(ma, mb))
                if across_u:
                    gap = np.hypot(u - (c + 1), v - np.clip(v, r, r + 1))
                else:
                    gap = np.hypot(v - (r + 1), u - np.clip(u, c, c + 1))
                nearer = ok & (gap < best) & (gap * cell <= reach)
                best = np.where(nearer, gap, best)
                best_var = np.where(nearer, np.maximum(raster.var[ra, ca], raster.var[rb, cb]) + cell**2 / 12,
                                    best_var)
    moved = best < np.abs(distance[todo]) / cell
    idx = todo[moved]
    distance[idx] = np.where(distance[idx] < 0, -1.0, 1.0) * best[moved] * cell
    var[idx] = best_var[moved]
    return distance, var


@pytest.mark.parametrize('seed', range(5))
def test_step_face_search_equals_the_face_by_face_search(seed):
    """Random stepped rasters (quantised depths, so that ties between faces occur, and some
    global-prior cells) and points on, off and around them: the same distances and variances
    to the last bit, the depth range cached or not."""
    rng = np.random.default_rng(seed)
    h, w, cell = rng.integers(3, 30), rng.integers(3, 30), float(rng.choice([0.05, 0.1, 0.2]))
    mean = np.round(rng.normal(0, 0.3, (h, w)) * 4) / 4
    source = np.where(rng.random((h, w)) < 0.1, SOURCE_GLOBAL, 2).astype(np.int8)
    raster = SurfaceRaster(np.array([-1.0, 0.5]), cell, mean, rng.uniform(1e-4, 1e-2, (h, w)),
                           np.zeros((h, w), np.int32), source)
    n = 3000
    uvd = np.column_stack([rng.uniform(-1.5, -1.0 + (w + 5) * cell, n), rng.uniform(0.0, 0.5 + (h + 5) * cell, n),
                           rng.normal(0, 0.4, n)])
    m, v = surface_at(raster, uvd[:, :2])
    reach = float(rng.choice([0.1, STEP_REACH, 0.5]))
    want = _nearer_step_faces_one_face_at_a_time(raster, uvd, uvd[:, 2] - m, v, reach)
    assert (want[0] != uvd[:, 2] - m).sum() > 20  # the search moved points: the case is not empty
    for depth_range in (None, cached_step_depth_range(raster, reach)):
        got = nearer_step_faces(raster, uvd, uvd[:, 2] - m, v, reach, depth_range)
        np.testing.assert_array_equal(got[0], want[0])
        np.testing.assert_array_equal(got[1], want[1])
    assert cached_step_depth_range(raster, reach) is cached_step_depth_range(raster, reach)
