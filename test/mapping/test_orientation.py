"""Façade normals without sensor origins: a lone wall is turned by what else was scanned."""

import numpy as np

from uncertain_facade_map.mapping.facade_map import build_map
from uncertain_facade_map.params import MapParams


def _wall(y: float, rng: np.random.Generator, n: int = 6000) -> np.ndarray:
    return np.c_[rng.uniform(-15, 15, n), y + rng.normal(0, 0.01, n), rng.uniform(0, 9, n)]


def test_lone_walls_across_a_street_face_each_other():
    """Two walls 20 m apart, each its own building, no origins: each wall's shape cannot
    tell its sides apart (a lone plane), but the other wall was seen from the street, so
    it lies in front. (Before, both turned by the fallback and one faced away.)"""
    rng = np.random.default_rng(2)
    xyz = np.vstack([_wall(-9.0, rng), _wall(11.0, rng)])
    fmap = build_map(xyz, None, None, MapParams())
    assert len(fmap.facades) == 2 and len({f.building for f in fmap.facades}) == 2
    street = np.array([0.0, 1.0, 1.8])
    for f in fmap.facades:
        assert f.frame.normal @ (street - f.frame.origin) > 0, f.frame.normal


def test_origins_decide_over_the_context():
    """With sensor origins the other buildings' points are not asked: a wall seen from
    behind the other one (origins at y = 30) faces that way."""
    rng = np.random.default_rng(3)
    xyz = np.vstack([_wall(-9.0, rng), _wall(11.0, rng)])
    origins = np.tile([0.0, 30.0, 1.8], (len(xyz), 1))
    fmap = build_map(xyz, None, origins, MapParams())
    assert all(f.frame.normal[1] > 0.99 for f in fmap.facades)


def test_a_sloped_face_mapped_later_faces_like_its_wall():
    """Incremental mapping without origins: a wall first, then a sloped face over it that
    leans out (27 degrees, facing down and out, like a corbel under a projecting storey).
    Its points alone cannot tell its outside (the fallback 'up' would turn it into the
    building); it faces like the wall mapped before (FacadeMap._walls)."""
    rng = np.random.default_rng(5)
    n = 8000
    wall = np.c_[rng.uniform(0, 20, n), rng.normal(0, 0.01, n), rng.uniform(0, 9, n)]
    fmap = build_map(wall, np.zeros(n, int), None, MapParams())
    assert len(fmap.facades) == 1 and fmap.facades[0].frame.normal[1] < -0.99
    t = rng.uniform(0, 1, 2500)
    slope = np.c_[rng.uniform(0, 20, 2500), -1.5 * t + rng.normal(0, 0.01, 2500), 9.0 + 3.0 * t]
    fmap.add_points(slope, np.zeros(len(slope), int))
    sloped = [f for f in fmap.facades if abs(f.frame.normal[2]) > 0.2]
    truth = np.array([0.0, -2.0, -1.0]) / np.sqrt(5.0)
    assert len(sloped) == 1 and sloped[0].frame.normal @ truth > np.cos(np.deg2rad(2.0)), sloped[0].frame.normal
