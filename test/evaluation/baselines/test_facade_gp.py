"""Our map behind the evaluation's interface: PLSC, the fixed formula, free space."""

import numpy as np
import pytest

from uncertain_facade_map.evaluation.baselines.facade_gp import (
    FacadeGPFixedMethod,
    FacadeGPFreeSpaceMethod,
    FacadeGPMethod,
)
from uncertain_facade_map.evaluation.occupancy import pr_auc
from uncertain_facade_map.voxels import voxel_index

WALL_Y, BACK_Y, R = 8.0, 12.0, 0.1
HOLE = ((4.0, 6.0), (2.0, 4.0))  # x and z extent of the opening in the front wall


def _in_hole(x, z):
    return (x > HOLE[0][0]) & (x < HOLE[0][1]) & (z > HOLE[1][0]) & (z < HOLE[1][1])


@pytest.fixture(scope='module')
def scan():
    """A front wall (y = 8, x 0-10, z 0-6) with a 2 m x 2 m opening, a back wall (y = 12)
    seen through it, 2 cm range noise; the sensor drives along y = 0 at z = 2."""
    rng = np.random.default_rng(0)
    origins = np.repeat(np.stack([np.linspace(1, 9, 60), np.zeros(60), np.full(60, 2.0)], 1), 500, axis=0)
    target = np.stack([rng.uniform(0, 10, len(origins)), np.full(len(origins), WALL_Y),
                       rng.uniform(0, 6, len(origins))], 1)
    d = target - origins
    through = _in_hole(target[:, 0], target[:, 2])
    scale = np.where(through, (BACK_Y - origins[:, 1]) / d[:, 1], 1.0)  # on to the back wall
    hits = origins + d * scale[:, None]
    hits += d / np.linalg.norm(d, axis=1, keepdims=True) * rng.normal(0, 0.02, (len(d), 1))
    return hits, origins


def test_free_space_carves_the_opening_the_surface_closes(scan):
    points, origins = scan
    # The paper's raster closes the opening (the per-point reading leaves less to carve).
    plain = FacadeGPMethod(R, surface='raster').fit(points, origins)
    free = FacadeGPFreeSpaceMethod(R, surface='raster').fit(points, origins)
    assert free.map_ is plain.map_, 'the readings of one map share it'
    assert free.carve_ > 0.05, 'a weight learnt from the mapped rays alone'
    # Voxels of the front wall's layer: the wall (occupied) and the opening (free, rays passed).
    xs, zs = np.meshgrid(np.arange(0.5, 9.5, R) + R / 2, np.arange(0.5, 5.5, R) + R / 2)
    centres = np.stack([xs.ravel(), np.full(xs.size, (np.floor(WALL_Y / R) + 0.5) * R), zs.ravel()], 1)
    occupied = ~_in_hole(centres[:, 0], centres[:, 2])
    p_plain, p_free = plain.predict(centres), free.predict(centres)
    hole = ~occupied & _in_hole(centres[:, 0] - 0.3, centres[:, 2] - 0.3) & _in_hole(centres[:, 0] + 0.3,
                                                                                      centres[:, 2] + 0.3)
    assert np.median(p_free[hole]) < 0.6 * np.median(p_plain[hole])
    assert pr_auc(occupied, p_free) > pr_auc(occupied, p_plain) + 0.02
    # A voxel holding a stored point is never carved (the map stores the points it keeps:
    # update.store_per_voxel, update.store_spacing).
    stored = np.concatenate(list(free.map_.points.values()))
    held = np.isin(voxel_index(centres, R).view([('', np.int64)] * 3).ravel(),
                   voxel_index(stored, R).view([('', np.int64)] * 3).ravel())
    np.testing.assert_array_equal(p_free[held & occupied], p_plain[held & occupied])


def test_the_fixed_formula_reads_the_same_map_without_plsc(scan):
    points, origins = scan
    learnt = FacadeGPMethod(R).fit(points, origins)
    fixed = FacadeGPFixedMethod(R).fit(points, origins)
    assert learnt.plsc_.learnt and fixed.plsc_ is None
    centres = points[::97] + np.array([0.0, -0.05, 0.0])
    assert not np.allclose(learnt.predict(centres), fixed.predict(centres))
