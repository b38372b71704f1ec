"""The occupancy's PLSC parameters learnt from the mapped scans alone."""

import numpy as np
import pytest
from support import wall_scan

from uncertain_facade_map.errors import InputError
from uncertain_facade_map.mapping.calibration import _sample_regions, scan_voxels
from uncertain_facade_map.mapping.facade_map import build_map, calibrate_occupancy
from uncertain_facade_map.params import QueryConfig
from uncertain_facade_map.pipeline.step7_queries import query_points
from uncertain_facade_map.pipeline.step8_occupancy import FIXED, PLSC, facade_half_depth, plsc_log_likelihood


def _log_likelihood(model: PLSC, fmap, labels, resolution: float) -> float:
    """Mean log-likelihood of a scan's own voxel labels under a map read with ``model``."""
    q = fmap.query(labels.centres, QueryConfig(surface='raster'), resolution)  # its own bands, 1 and 2 m
    normals = np.array([f.frame.axes[2] for f in fmap.facades]).reshape(-1, 3)
    use = np.isfinite(q.signed_distance) & (np.abs(q.signed_distance) <= 0.5)
    sd2 = q.variance + q.noise_variance
    theta = np.log([model.scale, max(model.spread, 1e-4)])
    h = facade_half_depth(q.facade, normals, resolution)
    return plsc_log_likelihood(theta, labels.positive[use], labels.weight[use], q.signed_distance[use], sd2[use],
                               h[use]) / labels.weight[use].sum()


def test_learnt_parameters_explain_another_scan_better_than_the_fixed_formula():
    # Map one seeded scan of a flat wall (2 cm noise) and learn PLSC from it alone; then label
    # a second, independent scan of the same wall and compare the likelihood of its labels.
    xyz, origins = wall_scan(seed=0)
    learnt = calibrate_occupancy(xyz, origins, resolution=0.1)
    assert learnt.learnt and learnt.n_positive > 100 and learnt.n_negative > 100
    assert 0.5 < learnt.scale < 5.0 and learnt.spread < 0.1
    assert calibrate_occupancy(xyz, origins, resolution=0.1) == learnt, 'seeded: the same parameters again'
    fmap = build_map(xyz, None, origins)
    other, other_origins = wall_scan(seed=1)
    labels = scan_voxels(other, other_origins, 0.1)
    assert _log_likelihood(learnt, fmap, labels, 0.1) > _log_likelihood(FIXED, fmap, labels, 0.1)


def test_the_sample_is_whole_cubes_and_at_least_the_asked_size():
    rng = np.random.default_rng(0)
    xyz = rng.uniform(0, 100, (20_000, 3))
    pick = _sample_regions(xyz, 10.0, 3_000, np.random.default_rng(1))
    assert 3_000 <= len(pick) < 20_000
    cubes = {tuple(c) for c in np.floor(xyz[pick] / 10.0).astype(int)}
    whole = np.isin(np.arange(len(xyz)), pick) == np.array([tuple(c) in cubes for c in
                                                            np.floor(xyz / 10.0).astype(int)])
    assert whole.all(), 'a cube is taken whole or not at all'
    assert len(_sample_regions(xyz, 10.0, 50_000, np.random.default_rng(1))) == len(xyz)


def test_bad_settings_are_refused():
    xyz, origins = wall_scan(n_origins=4, rays=100)
    for kwargs in (dict(holdout=0.0), dict(holdout=1.0), dict(resolution=0.0), dict(reach=-1.0)):
        with pytest.raises(InputError):
            calibrate_occupancy(xyz, origins, **kwargs)
    with pytest.raises(InputError):
        calibrate_occupancy(xyz, origins[:-1])


def test_the_map_learns_at_each_doubling_and_needs_sensor_origins():
    xyz, origins = wall_scan(seed=0)
    fmap = build_map(xyz[:8000], None, origins[:8000])
    assert fmap.occupancy_ is FIXED and not fmap.calibrate_when_grown(min_points=100_000)
    assert fmap.calibrate_when_grown(min_points=1000) and fmap.occupancy_.learnt
    assert fmap.occupancy_stored_ == fmap.n_stored
    assert not fmap.calibrate_when_grown(min_points=1000), 'not grown since'
    fmap.add_points(xyz[8000:], None, origins[8000:])
    assert fmap.n_stored >= 2 * fmap.occupancy_stored_ or not fmap.calibrate_when_grown(min_points=1000)
    blind = build_map(xyz, None, None)
    with pytest.raises(InputError, match='sensor origin'):
        blind.calibrate_occupancy()
    assert not blind.calibrate_when_grown(min_points=1000)


def test_queries_read_the_occupancy_with_the_given_parameters():
    xyz, origins = wall_scan(seed=0)
    fmap = build_map(xyz, None, origins)
    probe = np.array([[5.0, 8.0 - d, 3.0] for d in (-0.3, -0.05, 0.0, 0.05, 0.1, 0.3)])
    model = PLSC(2.0, 0.05)
    q = query_points(fmap.facades, probe, 0.1, 1.0, 2.0, model)
    noise = np.where(np.isfinite(q.noise_variance), q.noise_variance, 0.0)
    assert np.array_equal(q.p_occupied, model.solid(q.signed_distance, q.variance, noise, 0.1))
    fixed = query_points(fmap.facades, probe, 0.1, 1.0, 2.0)
    assert not np.allclose(q.p_occupied, fixed.p_occupied)
