"""Occupancy from the uncertain surface."""

import numpy as np
import pytest

from uncertain_facade_map.pipeline.step8_occupancy import UNKNOWN, occupancy_probability


def test_occupancy_is_a_cumulative_gaussian_of_the_signed_distance():
    s = np.array([-1.0, 0.0, 0.05, 0.1, 1.0, np.nan])
    p = occupancy_probability(s, np.full(6, 0.0), 0.02**2, 0.1)
    assert p[0] == pytest.approx(1.0) and p[4] == pytest.approx(0.0)
    assert p[2] == pytest.approx(0.5)  # the voxel's outer face on the surface
    assert p[1] > 0.99 and p[3] < 0.01
    assert p[5] == UNKNOWN
    assert np.all(np.diff(p[:5]) <= 0), 'occupancy falls with the distance outside'
    wide = occupancy_probability(np.array([0.2]), np.array([0.04]), 0.0, 0.1)
    narrow = occupancy_probability(np.array([0.2]), np.array([0.0001]), 0.0, 0.1)
    assert wide[0] > narrow[0], 'more variance, less certainty of free space'


def test_surface_probabilities_of_a_column_of_voxels_add_up_to_one():
    from uncertain_facade_map.pipeline.step8_occupancy import half_depth, surface_probability

    # Voxels stacked along the normal partition the depth axis: the surface is in one of them.
    rng = np.random.default_rng(3)
    for _ in range(20):
        h, offset, var, noise = rng.uniform(0.02, 0.1), rng.uniform(-0.1, 0.1), rng.uniform(0, 0.01), 4e-4
        s = offset + 2 * h * np.arange(-200, 201)
        p = surface_probability(s, np.full(len(s), var), noise, h)
        assert p.sum() == pytest.approx(1.0, abs=1e-9) and np.all((p >= 0) & (p <= 1))
        # The voxel holding the mean surface is the likeliest.
        assert np.argmax(p) == np.argmin(np.abs(s))
    assert surface_probability(np.array([np.nan]), np.array([np.nan]), 0.0, 0.05).tolist() == [0.0]
    assert half_depth(np.array([[0.0, 1.0, 0.0], [np.sqrt(0.5), np.sqrt(0.5), 0.0]]), 0.1) == pytest.approx(
        [0.05, 0.1 / np.sqrt(2)])


def test_each_voxel_takes_the_half_depth_of_its_facade_or_half_a_voxel_without_one():
    from uncertain_facade_map.pipeline.step8_occupancy import facade_half_depth

    normals = np.array([[0.0, 1.0, 0.0], [np.sqrt(0.5), np.sqrt(0.5), 0.0]])
    h = facade_half_depth(np.array([1, -1, 0, 1]), normals, 0.1)
    np.testing.assert_allclose(h, [0.1 / np.sqrt(2), 0.05, 0.05, 0.1 / np.sqrt(2)])
    assert facade_half_depth(np.array([-1, -1]), np.empty((0, 3)), 0.2).tolist() == [0.1, 0.1]


def test_plsc_with_its_fixed_parameters_is_the_fixed_formula():
    from uncertain_facade_map.pipeline.step8_occupancy import FIXED, surface_probability

    rng = np.random.default_rng(0)
    s, var, h = rng.normal(0, 0.2, 500), rng.uniform(0, 0.01, 500), rng.uniform(0.05, 0.087, 500)
    s[:5] = np.nan
    assert np.array_equal(FIXED.surface(s, var, 4e-4, h), surface_probability(s, var, 4e-4, h))
    assert np.array_equal(FIXED.solid(s, var, 4e-4, 0.1), occupancy_probability(s, var, 4e-4, 0.1))
    assert not FIXED.learnt


def _labels(truth, n: int, seed: int):
    """Seeded voxels and labels drawn from the surface reading of ``truth`` (a PLSC)."""
    rng = np.random.default_rng(seed)
    s = np.r_[rng.normal(0, 0.05, n // 2), rng.uniform(-0.5, 2.0, n - n // 2)]
    var = rng.uniform(0, 0.002, n)
    h = rng.uniform(0.05, 0.087, n)
    positive = rng.random(n) < truth.surface(s, var, 4e-4, h)
    return positive, np.ones(n), s, var, np.full(n, 4e-4), h


@pytest.mark.parametrize('scale, spread', [(1.0, 0.001), (1.5, 0.03), (0.7, 0.08)])
def test_plsc_recovers_the_parameters_its_labels_were_drawn_with(scale, spread):
    from uncertain_facade_map.pipeline.step8_occupancy import PLSC, fit_plsc, plsc_log_likelihood

    data = _labels(PLSC(scale, spread), 60_000, seed=int(scale * 10))
    fitted = fit_plsc(*data)
    assert fitted.learnt and fitted.n_positive == int(data[0].sum())
    assert fitted.scale == pytest.approx(scale, rel=0.1)
    assert fitted.spread == pytest.approx(spread, abs=0.012)
    # The fit's likelihood is at least the truth's and the fixed formula's.
    ll = lambda p: plsc_log_likelihood(np.log([p.scale, max(p.spread, 1e-4)]), *data[:3],  # noqa: E731
                                       data[3] + data[4], data[5])
    assert ll(fitted) >= ll(PLSC(scale, spread)) - 1e-6 and ll(fitted) >= ll(PLSC()) - 1e-6


def test_plsc_likelihood_is_finite_far_from_the_surface_and_learning_needs_both_labels():
    from uncertain_facade_map.pipeline.step8_occupancy import FIXED, fit_plsc, plsc_log_likelihood

    s = np.array([-50.0, 50.0, 0.0, -3.0])
    ll = plsc_log_likelihood(np.log([1.0, 1e-4]), np.array([True, True, False, False]), np.ones(4), s,
                             np.full(4, 1e-8), np.full(4, 0.05))
    assert np.isfinite(ll) and ll < -100
    few = np.r_[np.ones(5, bool), np.zeros(100, bool)]
    assert fit_plsc(few, np.ones(105), np.zeros(105), np.zeros(105), np.zeros(105), np.full(105, 0.05)) is FIXED
    nan = np.full(200, np.nan)
    assert fit_plsc(np.arange(200) % 2 == 0, np.ones(200), nan, nan, nan, np.full(200, 0.05)) is FIXED


def test_plsc_parameters_are_checked():
    from uncertain_facade_map.errors import InputError
    from uncertain_facade_map.pipeline.step8_occupancy import PLSC

    for bad in [dict(scale=0.0), dict(scale=np.nan), dict(spread=-0.1), dict(spread=np.inf)]:
        with pytest.raises(InputError):
            PLSC(**bad)
