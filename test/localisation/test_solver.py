"""The localiser on a seeded world of planes with an analytic map (plane_world.py): the
Jacobian against finite differences, poses recovered from GNSS-like priors, the covariance's
consistency (NEES against its chi-square band, with and without correlated map errors),
unanswered points ignored, a corridor left to the prior, bad inputs refused. About 3 s."""

import dataclasses

import numpy as np
import pytest
from plane_world import World, perturbed, street
from scipy.linalg import cho_factor, cho_solve
from scipy.stats import chi2

from uncertain_facade_map.errors import InputError
from uncertain_facade_map.localisation import covariance_from_std, localise, se3
from uncertain_facade_map.localisation.solver import (
    _centred_exp,
    centred_log,
    patch_counts,
    point_jacobian,
    robust_weights,
    subsample,
)
from uncertain_facade_map.params import LocaliseParams

PRIOR_COV = covariance_from_std([2.0, 2.0, 2.0, *np.deg2rad([3.0, 3.0, 3.0])])
SENSOR_NOISE = 0.03


def _truth(rng) -> np.ndarray:
    pose = np.eye(4)
    pose[:3, :3] = se3.so3_exp(np.array([0.0, 0.0, rng.uniform(-np.pi, np.pi)]))
    pose[:3, 3] = [rng.uniform(-10, 10), rng.uniform(-3, 3), 2.0]
    return pose


def _error(truth, est):
    """(6,) the truth as a perturbation of the estimate, in the covariance's convention."""
    return centred_log(truth, est.pose, est.pose[:3, 3])


def _nees(truth, est) -> float:
    d = _error(truth, est)
    return float(d @ cho_solve(cho_factor(est.covariance), d))


def test_point_jacobian_against_finite_differences():
    rng = np.random.default_rng(0)
    pose = se3.se3_exp(rng.normal(size=6))
    scan = rng.normal(0, 10, (50, 3))
    normals = rng.normal(size=(50, 3))
    normals /= np.linalg.norm(normals, axis=1)[:, None]
    centre = rng.normal(0, 5, 3)
    p0 = se3.transform_points(pose, scan)
    numeric = np.empty((50, 6))
    h = 1e-6
    for k in range(6):
        d = np.zeros(6)
        d[k] = h
        plus = se3.transform_points(_centred_exp(d, pose, centre), scan)
        minus = se3.transform_points(_centred_exp(-d, pose, centre), scan)
        numeric[:, k] = np.einsum('ij,ij->i', normals, plus - minus) / (2 * h)
    np.testing.assert_allclose(point_jacobian(p0, normals, centre), numeric, atol=1e-6)


def test_centred_perturbation_round_trip():
    rng = np.random.default_rng(1)
    pose = se3.se3_exp(rng.normal(size=6))
    centre = rng.normal(0, 50, 3)
    delta = rng.normal(0, 0.3, 6)
    moved = _centred_exp(delta, pose, centre)
    np.testing.assert_allclose(centred_log(moved, pose, centre), delta, atol=1e-10)
    # translation part is the move of the point at the centre: rotation about the centre, not the origin
    only_turn = _centred_exp(np.array([0, 0, 0, 0, 0, 0.5]), np.eye(4), centre)
    np.testing.assert_allclose(se3.transform_points(only_turn, centre[None])[0], centre, atol=1e-12)


def test_robust_weights_and_pieces():
    u = np.array([0.0, 1.0, 3.0, 30.0])
    for kernel in ('geman', 'cauchy', 'huber', 'none'):
        w, rho = robust_weights(u, kernel, 3.0)
        assert w[0] == 1.0 and np.all(np.diff(w) <= 0) and np.all(rho >= 0)
    w, _ = robust_weights(u, 'geman', 3.0)
    assert w[2] == pytest.approx(0.25) and w[3] < 1e-3
    pts = np.random.default_rng(2).uniform(0, 10, (20000, 3))
    keep = subsample(pts, 0.5, 1000, seed=3)
    assert len(keep) == 1000 and np.all(np.diff(keep) > 0)
    np.testing.assert_array_equal(keep, subsample(pts, 0.5, 1000, seed=3))
    counts = patch_counts(np.array([[0.1, 0, 0], [0.2, 0, 0], [3, 0, 0], [0.1, 0, 0]]), np.array([0, 0, 0, 1]), 2.0)
    np.testing.assert_array_equal(counts, [2, 2, 1, 1])


@pytest.fixture(scope='module')
def trials():
    """Twelve seeded trials in the street of planes: independent map errors (patch 5 cm)."""
    rng = np.random.default_rng(7)
    out = []
    for seed in range(12):
        world = World(street(), seed=seed, patch=0.05)
        truth = _truth(rng)
        scan = world.scan(truth, 20000, SENSOR_NOISE, clutter=300)
        prior = perturbed(truth, rng)
        params = LocaliseParams(sensor_noise=SENSOR_NOISE, correlation_length=0.0, facade_offsets=False)
        out.append((world, truth, prior, localise(scan, prior, PRIOR_COV, world.query, params)))
    return out


def test_pose_recovered_from_gnss_like_priors(trials):
    for world, truth, prior, est in trials:
        d = _error(truth, est)
        start = centred_log(truth, prior, prior[:3, 3])
        assert np.linalg.norm(start[:3]) > 0.5 and np.linalg.norm(start[3:]) > np.deg2rad(0.9)
        assert np.linalg.norm(d[:3]) < 0.02, d
        assert np.rad2deg(np.linalg.norm(d[3:])) < 0.1, d
        p = LocaliseParams()  # the search, then each solve's rounds and its common cost
        assert est.converged and est.status == 'converged'
        assert est.queries <= 1 + (1 + p.alternatives) * (p.max_queries + 1)
        assert est.points_used <= LocaliseParams().max_points


def test_nees_of_independent_map_errors_inside_its_band(trials):
    nees = np.array([_nees(truth, est) for _, truth, _, est in trials])
    k = len(nees)
    lo, hi = chi2.ppf([0.025, 0.975], 6 * k) / k
    assert lo <= nees.mean() <= hi, (nees.mean(), lo, hi)


def _nees_mean(patch: float, correlation_length: float, n: int = 16, facade_offsets: bool = False) -> float:
    rng = np.random.default_rng(11)
    params = LocaliseParams(sensor_noise=SENSOR_NOISE, correlation_length=correlation_length,
                            facade_offsets=facade_offsets)
    values = []
    for seed in range(n):
        world = World(street(), seed=100 + seed, patch=patch)
        truth = _truth(rng)
        scan = world.scan(truth, 8000, SENSOR_NOISE)
        values.append(_nees(truth, localise(scan, perturbed(truth, rng), PRIOR_COV, world.query, params)))
    return float(np.mean(values))


def test_correlated_map_errors_need_the_correlation_length():
    """Map errors alike over 3 m patches: the plain Hessian is overconfident (NEES far above
    its band); counting each patch once (correlation_length 3 m) brings it inside."""
    n = 16
    lo, hi = chi2.ppf([0.025, 0.975], 6 * n) / n
    plain = _nees_mean(3.0, 0.0, n)
    corrected = _nees_mean(3.0, 3.0, n)
    assert plain > 1.5 * hi, plain
    assert lo <= corrected <= hi, (corrected, lo, hi)


def test_whole_facade_offsets_are_marginalised():
    """Map errors shared by each whole plane (one offset per wall, N(0, its variance)): the
    covariance that counts points as independent is overconfident (NEES far above its band);
    with each façade's offset marginalised out (``facade_offsets``) it is inside its band,
    and with the patch correlation on top (the defaults) a little cautious, not above it."""
    n = 16
    lo, hi = chi2.ppf([0.025, 0.975], 6 * n) / n
    plain = _nees_mean(np.inf, 0.0, n)
    offsets = _nees_mean(np.inf, 0.0, n, facade_offsets=True)
    both = _nees_mean(np.inf, 2.0, n, facade_offsets=True)
    assert plain > 1.5 * hi, plain
    assert lo <= offsets <= hi, (offsets, lo, hi)
    assert 0.5 * lo <= both <= hi, (both, lo, hi)


def test_unanswered_points_weigh_nothing():
    rng = np.random.default_rng(3)
    world = World(street(), seed=3, patch=0.05)
    truth = _truth(rng)
    scan = world.scan(truth, 10000, SENSOR_NOISE)
    prior = perturbed(truth, rng)

    def holes(xyz):  # a third of the answers are -1 with garbage in every other field
        ans = world.query(xyz)
        drop = np.random.default_rng(len(xyz)).random(len(xyz)) < 1 / 3
        ans.facade = np.where(drop, -1, ans.facade)
        ans.signed_distance = np.where(drop, 1e6, ans.signed_distance)
        ans.variance = np.where(drop, np.nan, ans.variance)
        ans.normal = np.where(drop[:, None], np.nan, ans.normal)
        return ans

    est = localise(scan, prior, PRIOR_COV, holes, LocaliseParams(correlation_length=0.0))
    d = _error(truth, est)
    assert np.linalg.norm(d[:3]) < 0.02 and np.rad2deg(np.linalg.norm(d[3:])) < 0.1
    assert np.isfinite(est.covariance).all()


def test_a_corridor_leaves_the_along_track_position_to_the_prior():
    """Only the two long walls and the ground: x (along the street) is the prior's, and the
    covariance says so; y, z and the rotations come from the map."""
    world = World(street(corridor=True), seed=5, patch=0.05)
    truth = np.eye(4)
    truth[:3, 3] = [0.0, 1.0, 2.0]
    scan = world.scan(truth, 20000, SENSOR_NOISE)
    prior = truth.copy()
    prior[:3, 3] += [1.5, -1.0, 0.3]
    prior[:3, :3] = se3.so3_exp(np.deg2rad([0.5, -0.5, 2.0]))
    est = localise(scan, prior, PRIOR_COV, world.query, LocaliseParams(correlation_length=0.0, facade_offsets=False))
    std = np.sqrt(np.diag(est.covariance))
    assert std[0] == pytest.approx(2.0, rel=0.05)  # the prior's 2 m
    assert std[1] < 0.01 and std[2] < 0.01 and np.rad2deg(std[3:]).max() < 0.05
    d = _error(truth, est)
    assert abs(d[1]) < 0.02 and abs(d[2]) < 0.02 and np.rad2deg(np.abs(d[3:])).max() < 0.1
    assert abs(est.pose[0, 3] - prior[0, 3]) < 0.1  # x stays where the prior put it


def test_constant_variance_and_batches():
    rng = np.random.default_rng(9)
    world = World(street(), seed=9, patch=0.05)
    truth = _truth(rng)
    scan = world.scan(truth, 5000, SENSOR_NOISE)
    prior = perturbed(truth, rng)
    params = dataclasses.replace(LocaliseParams(), batch_points=400, correlation_length=0.0)
    est = localise(scan, prior, PRIOR_COV, world.query, params, constant_variance=0.0)
    assert np.linalg.norm(_error(truth, est)[:3]) < 0.02
    assert est.queries == world.calls and est.queries >= 4 + 2 * int(np.ceil(1500 / 400))
    assert est.seconds > 0 and est.iterations >= est.queries // 10


def test_bad_inputs_are_refused():
    world = World(street(), seed=0)
    scan = world.scan(np.eye(4), 100, 0.01)
    ok = covariance_from_std([1, 1, 1, 0.1, 0.1, 0.1])
    with pytest.raises(InputError, match='scan'):
        localise(scan[:, :2], np.eye(4), ok, world.query)
    with pytest.raises(InputError, match='rigid'):
        localise(scan, np.diag([2.0, 1, 1, 1]), ok, world.query)
    with pytest.raises(InputError, match='positive definite'):
        localise(scan, np.eye(4), np.diag([1.0, 1, 1, 1, 1, 0]), world.query)
    with pytest.raises(InputError, match='symmetric'):
        localise(scan, np.eye(4), np.ones((6, 5)), world.query)
    with pytest.raises(InputError, match='constant_variance'):
        localise(scan, np.eye(4), ok, world.query, constant_variance=-1.0)

    @dataclasses.dataclass
    class NoNormals:  # a PointQuery before issue 28's item 1
        facade: np.ndarray
        signed_distance: np.ndarray
        variance: np.ndarray
        noise_variance: np.ndarray

    def no_normals(xyz):
        ans = world.query(xyz)
        return NoNormals(ans.facade, ans.signed_distance, ans.variance, ans.noise_variance)

    with pytest.raises(InputError, match='normal'):
        localise(scan, np.eye(4), ok, no_normals)
