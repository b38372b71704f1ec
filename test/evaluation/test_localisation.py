"""The localisation comparison's pieces (issue 28 item 3): metrics against hand-computed
values, the priors' ranges and seeding, scenarios whose scans lie on the map at the true
pose, and row (d) scoring exactly the perturbation. About 4 s (3.5-4.0 s, three runs on a busy machine)."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from scipy.stats import chi2

from uncertain_facade_map.errors import InputError
from uncertain_facade_map.evaluation import localisation as L
from uncertain_facade_map.localisation import map_query, se3


def _outcome(position, heading, nees=float('nan'), seconds=0.01, converged=None):
    return L.Outcome('s', 'r', 'x', np.array([position, 0, 0, 0, 0, 0]), position, heading, nees, seconds, converged,
                     np.zeros(6))


def test_heading_wraps():
    assert L.wrap_degrees(190.0) == pytest.approx(-170.0)
    assert L.wrap_degrees(-180.0) == pytest.approx(180.0)
    assert L.wrap_degrees(540.0) == pytest.approx(180.0)
    assert L.wrap_degrees(-359.0) == pytest.approx(1.0)
    truth = L.yaw_pose(10.0, 0.0, 0.0, np.deg2rad(-179.0))
    estimate = L.yaw_pose(10.0, 0.0, 0.0, np.deg2rad(179.0))
    case = L.ScanCase('x', np.zeros((1, 3)), truth, truth, np.eye(6), np.zeros(6))
    out = L.score(L.Estimate(estimate, None, 0.0), case, 's', 'r')
    assert out.heading_deg == pytest.approx(-2.0)          # not 358
    assert out.position == pytest.approx(0.0, abs=1e-12)
    assert np.isnan(out.nees)


def test_pose_error_by_hand():
    truth = L.yaw_pose(100.0, -50.0, 2.0, 0.3)
    rot = Rotation.from_rotvec([0.0, 0.01, 0.02]).as_matrix()
    estimate = L.pose_matrix(rot @ truth[:3, :3], truth[:3, 3] + [0.3, -0.4, 0.0])
    err = L.pose_error(estimate, truth)
    np.testing.assert_allclose(err, [0.3, -0.4, 0.0, 0.0, 0.01, 0.02], atol=1e-12)
    # The localiser's centred error: exactly minus the offset for a translation, about minus
    # the error for a small turn, and it maps the estimate onto the truth.
    shifted = L.pose_matrix(truth[:3, :3], truth[:3, 3] + [0.3, -0.4, 0.1])
    np.testing.assert_allclose(L.centred_error(shifted, truth), [-0.3, 0.4, -0.1, 0, 0, 0], atol=1e-12)
    delta = L.centred_error(estimate, truth)
    np.testing.assert_allclose(delta, -err, atol=0.01)
    from uncertain_facade_map.localisation import se3

    c = L.pose_matrix(np.eye(3), estimate[:3, 3])
    back = c @ se3.se3_exp(delta) @ se3.inverse(c) @ estimate
    np.testing.assert_allclose(back, truth, atol=1e-9)


def test_nees_by_hand_and_of_a_gaussian_sample():
    assert L.nees(np.array([1.0, 2.0, 0, 0, 0, 3.0]), np.eye(6)) == pytest.approx(14.0)
    assert L.nees(np.ones(6), np.diag([4.0] * 6)) == pytest.approx(1.5)
    assert np.isnan(L.nees(np.ones(6), None))
    assert np.isnan(L.nees(np.ones(6), -np.eye(6)))
    assert np.isnan(L.nees(np.ones(6), np.full((6, 6), np.nan)))
    rng = np.random.default_rng(5)
    a = rng.normal(size=(6, 6))
    cov = a @ a.T + 0.1 * np.eye(6)
    sample = rng.multivariate_normal(np.zeros(6), cov, size=4000)
    values = np.array([L.nees(e, cov) for e in sample])
    lo, hi = L.mean_nees_band(len(values))
    assert lo < values.mean() < hi
    inside = np.mean((values >= L.NEES_BAND[0]) & (values <= L.NEES_BAND[1]))
    assert inside == pytest.approx(0.95, abs=0.015)
    # An overconfident covariance (a tenth of the variance) is caught.
    assert np.mean([L.nees(e, cov / 10) for e in sample[:200]]) > hi
    assert L.mean_nees_band(1) == pytest.approx(L.NEES_BAND)
    np.testing.assert_allclose(L.NEES_BAND, (chi2.ppf(0.025, 6), chi2.ppf(0.975, 6)))


def test_summary_by_hand():
    outs = [_outcome(0.1, 0.5, 5.0, 0.010, True), _outcome(0.3, -0.2, 20.0, 0.020, False),
            _outcome(0.05, 2.0, 0.5, 0.030, True), _outcome(1.0, -0.1, 7.0, 0.040, True)]
    s = L.summarise(outs)
    assert s['n'] == 4
    assert s['position_median'] == pytest.approx(0.2)
    assert s['heading_median'] == pytest.approx(0.35)      # of |heading|: 0.1 0.2 0.5 2.0
    assert s['good_share'] == pytest.approx(0.25)          # only the first is within both
    assert s['nees_mean'] == pytest.approx(8.125)
    assert s['nees_in_band'] == pytest.approx(0.5)         # 5 and 7
    assert s['ms_median'] == pytest.approx(25.0)
    assert s['converged_share'] == pytest.approx(0.75)
    assert s['nees_mean_converged'] == pytest.approx(12.5 / 3)    # 5, 0.5, 7: the second is flagged
    assert s['failures'] == 3 and s['failures_flagged'] == 1     # 0.3 m (flagged), 2 deg, 1 m
    assert s['horizontal_p95_kept'] == pytest.approx(np.percentile([0.1, 0.05, 1.0], 95))
    assert s['position_p95'] == pytest.approx(np.percentile([0.1, 0.3, 0.05, 1.0], 95))
    no_cov = L.summarise([_outcome(0.1, 0.1)])
    assert np.isnan(no_cov['nees_mean']) and np.isnan(no_cov['nees_in_band']) and no_cov['nees_n'] == 0
    assert np.isnan(no_cov['converged_share'])


def test_perturbations_in_range_and_seeded():
    truth = L.yaw_pose(30.0, 4.0, 2.4, 0.7)
    spec = L.Perturbation()
    rng = np.random.default_rng(3)
    draws = [L.perturb(truth, rng, spec) for _ in range(500)]
    horizontal = np.array([np.hypot(*d[:2]) for _, d in draws])
    turns = np.array([np.rad2deg(L.heading(p) - L.heading(truth)) for p, _ in draws])
    turns = L.wrap_degrees(turns)
    assert horizontal.min() >= 0.5 and horizontal.max() <= 3.0
    assert horizontal.min() < 0.6 and horizontal.max() > 2.9          # the whole range is drawn
    assert np.abs(turns).min() >= 1.0 - 0.01 and np.abs(turns).max() <= 5.0 + 0.01
    assert (turns > 0).mean() == pytest.approx(0.5, abs=0.1)
    assert np.std([d[2] for _, d in draws]) == pytest.approx(0.05, rel=0.2)
    for prior, delta in draws[:20]:
        np.testing.assert_allclose(L.pose_error(prior, truth), delta, atol=1e-12)
        np.testing.assert_allclose(prior[:3, :3] @ prior[:3, :3].T, np.eye(3), atol=1e-12)
    again = [L.perturb(truth, np.random.default_rng(3), spec)[1] for _ in range(1)]
    np.testing.assert_array_equal(again[0], draws[0][1])
    other = L.perturb(truth, np.random.default_rng(4), spec)[1]
    assert not np.allclose(other, draws[0][1])
    cov = L.prior_covariance(spec)
    np.testing.assert_allclose(np.sqrt(np.diag(cov)), [1.5, 1.5, 0.05, np.deg2rad(0.2), np.deg2rad(0.2),
                                                       np.deg2rad(2.5)])
    with pytest.raises(InputError):
        L.Perturbation(position=(3.0, 0.5))


@pytest.fixture(scope='module')
def small():
    return L.simulated_scenario('small', campaigns=(1, 2), scans_per_drive=2, max_points=2000, seed=1)


def test_scans_lie_on_the_map_at_the_true_pose_and_not_at_the_prior(small):
    assert len(small.cases) == 4 and small.kind == 'clean'
    query = map_query(small.fmap)
    for case in small.cases:
        assert case.points.shape == (2000, 3)
        assert np.linalg.norm(case.points, axis=1).max() < 80.0               # sensor frame
        at_truth = query(se3.transform_points(case.truth, case.points))
        hit = at_truth.facade >= 0
        assert hit.mean() > 0.3
        assert np.median(np.abs(at_truth.signed_distance[hit])) < 0.03
        normals = at_truth.normal[hit]
        np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-9)
        assert np.all(np.isnan(at_truth.normal[~hit]))
        plane = map_query(small.fmap, plane_normals=True)(se3.transform_points(case.truth, case.points))
        expected = np.array([f.frame.normal for f in small.fmap.facades])[at_truth.facade[hit]]
        np.testing.assert_allclose(plane.normal[hit], expected)
        np.testing.assert_array_equal(plane.signed_distance, at_truth.signed_distance)
        assert np.median(np.sum(normals * expected, axis=1)) > 0.95   # the surface's: mostly the wall's
    # Seeded: the same arguments give the same scans and priors.
    again = L.simulated_scenario('small', campaigns=(1,), scans_per_drive=1, max_points=2000, seed=1)
    one = L.simulated_scenario('small', campaigns=(1,), scans_per_drive=1, max_points=2000, seed=1)
    np.testing.assert_array_equal(again.cases[0].points, one.cases[0].points)
    np.testing.assert_array_equal(again.cases[0].prior, one.cases[0].prior)


def test_prior_row_scores_the_perturbation(small):
    outs = L.run([small], {'d': L.prior_row})
    for out, case in zip(outs, small.cases):
        np.testing.assert_allclose(out.error, case.delta, atol=1e-12)
        assert out.position == pytest.approx(np.linalg.norm(case.delta[:3]))
        assert abs(out.heading_deg) == pytest.approx(np.rad2deg(abs(case.delta[5])), abs=0.01)
        assert np.isfinite(out.nees)


def test_bad_arguments():
    with pytest.raises(InputError):
        L.simulated_scenario('small', campaigns=(0, 1))
    with pytest.raises(InputError):
        L.simulated_scenario('nowhere')
    with pytest.raises(InputError):
        L.simulated_scenario('small', scans_per_drive=0)


def test_horizontal_and_vertical_parts():
    outs = [L.Outcome('s', 'r', 'x', np.array([0.3, 0.4, 1.2, 0, 0, 0]), 1.3, 0.5, 1.0, 0.0, None, np.zeros(6)),
            L.Outcome('s', 'r', 'x', np.array([0.1, 0.0, -0.1, 0, 0, 0]), np.hypot(0.1, 0.1), 0.5, 1.0, 0.0, None,
                      np.zeros(6))]
    s = L.summarise(outs)
    assert s['horizontal_median'] == pytest.approx(0.3)
    assert s['vertical_median'] == pytest.approx(0.65)
    assert s['good_share'] == pytest.approx(0.5)              # the first is 1.3 m off in 3-D
    assert s['good_share_horizontal'] == pytest.approx(0.5)   # ... and 0.5 m horizontally


def test_paired_counts():
    def out(row, label, x, heading=0.0):
        return L.Outcome('s', row, label, np.array([x, 0, 0, 0, 0, 0]), x, heading, 1.0, 0.0, None, np.zeros(6))

    outs = [out('a', '1', 0.1), out('b', '1', 0.5),            # only a
            out('a', '2', 0.5), out('b', '2', 0.1),            # only b
            out('a', '3', 0.1, 2.0), out('b', '3', 0.3),       # both failed (a by its heading)
            out('a', '4', 0.0), out('b', '4', 0.0), out('a', '5', 0.0)]   # both fine; 5 has no pair
    assert L.paired(outs, 'a', 'b') == {'scans': 4, 'first_only': 1, 'second_only': 1, 'both_failed': 1}
