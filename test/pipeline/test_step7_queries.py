"""Queries at façade locations and 3D points on a hand-made façade model."""

import numpy as np
import pytest

from uncertain_facade_map.datatypes import ExtractedFacade, FacadeFrame
from uncertain_facade_map.errors import InputError
from uncertain_facade_map.params import MapParams
from uncertain_facade_map.pipeline.step6_surface import fit_facade
from uncertain_facade_map.pipeline.step7_queries import query_points, surface_at


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
    for arr in res.as_dict().values():
        assert arr.shape == (5,)


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
