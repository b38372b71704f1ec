"""GPIS map baseline (uncertain_facade_map.evaluation.baselines.gpis_map) on a seeded synthetic wall."""

from __future__ import annotations

import copy

import numpy as np
import pytest

from uncertain_facade_map.errors import InputError
from uncertain_facade_map.evaluation.baselines import make_method
from uncertain_facade_map.evaluation.baselines.gpis_map import (
    GPISMapMethod,
    GPISMapSolidMethod,
    LocalGPIS,
    _first_per_cell,
    joint_covariance,
)
from uncertain_facade_map.evaluation.occupancy import pr_auc, reference_voxels

RES = 0.1
#: Sensor origins 5 m in front of a wall in the plane x = 0 (the solid is x < 0).
ORIGINS = np.array([[5.0, 1.0, 1.5], [5.0, 3.0, 1.5], [5.0, 5.0, 1.5]])


def _scan(seed: int, n: int = 6000, noise: float = 0.01) -> tuple[np.ndarray, np.ndarray]:
    """Hits on the wall x = 0, 0 <= y <= 6, 0 <= z <= 3 (metres) and their origins."""
    rng = np.random.default_rng(seed)
    org = ORIGINS[rng.integers(len(ORIGINS), size=n)]
    pts = np.c_[rng.normal(0.0, noise, n), rng.uniform(0.0, 6.0, n), rng.uniform(0.0, 3.0, n)]
    return pts, org


@pytest.fixture(scope='module')
def fitted() -> GPISMapMethod:
    pts, org = _scan(0)
    return GPISMapMethod(RES).fit(pts, org)


def test_registered():
    assert isinstance(make_method('gpis', RES), GPISMapMethod)
    assert GPISMapMethod.name == 'GPIS'


def test_wall_voxels_score_above_free_space(fitted):
    ref_pts, ref_org = _scan(1)
    ref = reference_voxels(ref_pts, ref_org, RES, max_rays=3000, max_negatives=20000, seed=0)
    p = fitted.predict(ref.centres)
    assert p.shape == (len(ref.centres),)
    assert np.all((p >= 0) & (p <= 1))
    # Measured 0.86-0.87 (four seed pairs); a constant map scores the positives' share (0.09).
    assert pr_auc(ref.positive, p, ref.weight) > 0.75
    # Measured difference 0.37-0.38.
    assert p[ref.positive].mean() > p[~ref.positive].mean() + 0.25


def test_field_sign_and_normals(fitted):
    # Normals point out of the solid, towards the sensors (+x).
    n = fitted.normals_[fitted.has_normal_]
    assert fitted.has_normal_.mean() > 0.95
    assert np.all(n[:, 0] > 0.9)
    # f ~ 0 on the wall, > 0 in front (sensor side), < 0 just behind it.
    q = np.array([[0.0, 3.0, 1.5], [0.5, 3.0, 1.5], [-0.3, 3.0, 1.5]])
    f = fitted.signed_distance(q)
    assert abs(f[0]) < 0.03
    assert f[1] > 0.3
    assert f[2] < -0.15
    var = fitted.predict_variance(q)
    assert np.all(var > 0) and var[0] < 0.05
    # The surface reading: the wall's voxel holds the surface, the others do not; the
    # solid reading: the wall and what lies behind it are occupied.
    p = fitted.predict(q)
    assert p[0] > 0.3 and max(p[1], p[2]) < p[0] / 2
    solid = copy.copy(fitted)
    solid.reading = 'solid'
    p = solid.predict(q)
    assert p[2] > p[0] > 0.5 > p[1]


def test_unknown_far_from_data(fitted):
    q = np.array([[60.0, 60.0, 60.0], [-40.0, 3.0, 1.5]])
    assert np.all(fitted.predict(q) == 0.0)  # no surface modelled there
    assert np.all(GPISMapSolidMethod(RES).fit(*_scan(2, n=500)).predict(q) == 0.5)  # unknown
    assert np.allclose(fitted.predict_variance(q), 1.0 + fitted.map_noise)
    assert np.all(np.isnan(fitted.signed_distance(q)))


def test_variance_grows_away_from_data(fitted):
    q = np.array([[0.0, 3.0, 1.5], [1.0, 3.0, 1.5], [2.5, 3.0, 1.5]])
    var = fitted.predict_variance(q)
    assert var[0] < var[1] < var[2] <= 1.0 + 1e-3 + 1e-9


def test_predict_before_fit_and_bad_queries():
    m = GPISMapMethod(RES)
    with pytest.raises(InputError):
        m.predict(np.zeros((3, 3)))
    with pytest.raises(InputError):
        m.predict_variance(np.zeros((3, 3)))
    pts, org = _scan(2, n=500)
    m.fit(pts, org)
    with pytest.raises(InputError):
        m.predict(np.zeros((3, 2)))
    with pytest.raises(InputError):
        m.predict(np.array([[np.nan, 0.0, 0.0]]))
    assert m.predict(np.zeros((0, 3))).shape == (0,)


def test_small_training_balls_and_single_point():
    pts, org = _scan(6, n=800)
    p = GPISMapMethod(RES, rtimes=1.0).fit(pts, org).predict(np.array([[0.0, 3.0, 1.5]]))
    assert 0.0 <= p[0] <= 1.0
    one = GPISMapMethod(RES).fit(pts[:1], org[:1])
    assert not one.has_normal_[0] and len(one.gps_) == 1
    assert 0.0 <= one.predict(pts[:1])[0] <= 1.0


@pytest.mark.parametrize('kwargs', [
    {'resolution': 0.0}, {'resolution': float('nan')}, {'length_scale': 0.0}, {'length_scale': -1.0},
    {'cluster_half_length': 0.0}, {'min_half_length': -0.1}, {'min_half_length': 5.0}, {'rtimes': 0.5},
    {'fbias': float('inf')}, {'min_pos_noise': 0.0}, {'min_grad_noise': -1e-2}, {'map_noise': 0.0},
    {'var_threshold': 0.0}, {'normal_neighbours': 3}, {'normal_neighbours': 7.5},
])
def test_bad_parameters(kwargs):
    args = {'resolution': RES, **kwargs}
    with pytest.raises(InputError):
        GPISMapMethod(**args)


def test_bad_scans():
    m = GPISMapMethod(RES)
    with pytest.raises(InputError):
        m.fit(np.zeros((0, 3)), np.zeros((0, 3)))
    with pytest.raises(InputError):
        m.fit(np.zeros((4, 3)), np.zeros((3, 3)))


def _k(x, y, ell):
    r = np.linalg.norm(x - y)
    a = np.sqrt(3.0) / ell
    return (1.0 + a * r) * np.exp(-a * r)


def test_derivative_kernel_matches_finite_differences():
    rng = np.random.default_rng(3)
    ell, h = 1.2, 1e-5
    xa = rng.normal(size=(4, 3))
    xb = rng.normal(size=(3, 3))
    ga = np.array([True, False, True, True])
    gb = np.array([True, True, False])
    k = joint_covariance(xa, ga, xb, gb, ell)
    na, nb = len(xa), len(xb)
    assert k.shape == (na + 3 * ga.sum(), nb + 3 * gb.sum())
    e = np.eye(3) * h
    ia, ib = np.flatnonzero(ga), np.flatnonzero(gb)
    for p in range(na):
        for q in range(nb):
            assert k[p, q] == pytest.approx(_k(xa[p], xb[q], ell), rel=1e-12)
            if q in ib:  # cov(f(xa), df(xb)/dxb_i)
                g = list(ib).index(q)
                for i in range(3):
                    fd = (_k(xa[p], xb[q] + e[i], ell) - _k(xa[p], xb[q] - e[i], ell)) / (2 * h)
                    assert k[p, nb + 3 * g + i] == pytest.approx(fd, rel=1e-6, abs=1e-9)
            if p in ia:  # cov(df(xa)/dxa_i, f(xb))
                g = list(ia).index(p)
                for i in range(3):
                    fd = (_k(xa[p] + e[i], xb[q], ell) - _k(xa[p] - e[i], xb[q], ell)) / (2 * h)
                    assert k[na + 3 * g + i, q] == pytest.approx(fd, rel=1e-6, abs=1e-9)
    h2 = 1e-4
    e2 = np.eye(3) * h2
    for ga_i, p in enumerate(ia):
        for gb_j, q in enumerate(ib):
            for i in range(3):
                for j in range(3):
                    fd = (_k(xa[p] + e2[i], xb[q] + e2[j], ell) - _k(xa[p] + e2[i], xb[q] - e2[j], ell)
                          - _k(xa[p] - e2[i], xb[q] + e2[j], ell) + _k(xa[p] - e2[i], xb[q] - e2[j], ell)
                          ) / (4 * h2 * h2)
                    assert k[na + 3 * ga_i + i, nb + 3 * gb_j + j] == pytest.approx(fd, rel=1e-4, abs=1e-6)
    # At r = 0: no value-gradient covariance, gradient variance a^2 = 3 / ell^2.
    k0 = joint_covariance(xa[:1], ga[:1], xa[:1], ga[:1], ell)
    assert np.allclose(k0[0, 1:], 0.0)
    assert np.allclose(k0[1:, 1:], 3.0 / ell ** 2 * np.eye(3))


def test_prior_and_posterior_covariances_are_psd(fitted):
    rng = np.random.default_rng(4)
    x = rng.uniform(-1, 1, size=(30, 3))
    g = rng.random(30) < 0.7
    prior = joint_covariance(x, g, x, g, 1.2)
    assert np.allclose(prior, prior.T)
    assert np.linalg.eigvalsh(prior).min() > -1e-9
    gp = max(fitted.gps_, key=lambda gp: len(gp.x))
    centre = gp.x.mean(axis=0)
    q = centre + rng.normal(scale=0.8, size=(60, 3))
    post = gp.posterior_covariance(q)
    assert np.allclose(post, post.T, atol=1e-10)
    assert np.linalg.eigvalsh(post).min() > -1e-8
    mean, var = gp.predict(q)
    assert np.allclose(var, np.diag(post) + 1e-3)
    assert np.all(var <= 1.0 + 1e-3 + 1e-12)


def test_local_gp_interpolates_a_plane():
    # Points on z = 0 with value -0.2 and normal +z: f = mean + 0.2 ~ z near the plane.
    rng = np.random.default_rng(5)
    x = np.c_[rng.uniform(-1, 1, (40, 2)), np.zeros(40)]
    gp = LocalGPIS.train(x, np.full(40, -0.2), np.tile([0.0, 0.0, 1.0], (40, 1)), np.ones(40, bool),
                         np.full(40, 1e-3), np.full(40, 1e-2), 1.2)
    mean, _ = gp.predict(np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.1], [0.0, 0.0, -0.1]]))
    f = mean + 0.2
    assert abs(f[0]) < 0.01
    assert f[1] == pytest.approx(0.1, abs=0.02)
    assert f[2] == pytest.approx(-0.1, abs=0.02)


def test_first_per_cell_keeps_first_point_of_each_cube():
    xyz = np.array([[0.1, 0.1, 0.1], [0.2, 0.2, 0.2], [0.5, 0.1, 0.1], [0.45, 0.3, 0.1], [0.05, 0.3, 0.3]])
    assert list(_first_per_cell(xyz, 0.4)) == [0, 2]
