"""The per-point reading (issue 26) on a seeded façade with a step and a hole, known truth."""

import numpy as np
import pytest

from uncertain_facade_map.datatypes import ExtractedFacade, FacadeFrame
from uncertain_facade_map.errors import InputError
from uncertain_facade_map.params import MapParams, QueryConfig
from uncertain_facade_map.pipeline.step6_surface import fit_facade
from uncertain_facade_map.pipeline.step7_local_surface import LocalSurface, fit_local_planes, for_query, smoothstep
from uncertain_facade_map.pipeline.step7_queries import query_points

NOISE = 0.01
STEP_U, STEP = 4.0, 0.3  # a 30 cm step (a recess) at u = 4 m
HOLE = (6.0, 7.5, 3.0, 4.5)  # an occlusion: (u0, u1, v0, v1) without points


def truth(uv):
    return np.where(uv[:, 0] > STEP_U, -STEP, 0.0)


def in_hole(uv):
    return (uv[:, 0] > HOLE[0]) & (uv[:, 0] < HOLE[1]) & (uv[:, 1] > HOLE[2]) & (uv[:, 1] < HOLE[3])


def make_scene():
    """A 10 m x 6 m façade at 30 points/m^2 (a real sweep's density), its map and a held-out half."""
    rng = np.random.default_rng(7)
    uv = rng.uniform([0, 0], [10, 6], (3600, 2))
    uv = uv[~in_hole(uv)]
    d = truth(uv) + rng.normal(0, NOISE, len(uv))
    frame = FacadeFrame.from_normal(np.array([0.0, 10.0, 0.0]), np.array([0.0, -1.0, 0.0]))
    mapped = rng.random(len(uv)) < 0.5
    pts = frame.to_world(np.c_[uv, d])
    index = np.flatnonzero(mapped)
    e = ExtractedFacade(frame, np.arange(len(index)), np.c_[uv, d][index], np.ones(len(index)), (0, 10, 0, 6))
    model = fit_facade(e, MapParams(), np.random.default_rng(0))
    local = LocalSurface.of([model], {0: pts[index]})
    return model, local, frame, pts[~mapped], uv[~mapped], d[~mapped]


@pytest.fixture(scope='module')
def scene():
    return make_scene()


def test_held_out_points_read_within_their_noise_and_covered(scene):
    model, local, frame, held, uv, d = scene
    q = query_points([model], held, 0.1, 1.0, 2.0, local=local)
    err = q.signed_distance - (d - truth(uv))  # the point's own noise is what it measures
    away = np.abs(uv[:, 0] - STEP_U) > 0.3
    assert np.all(q.facade == 0)
    assert np.sqrt(np.mean(err[away] ** 2)) < 0.6 * NOISE
    cover = np.abs(q.signed_distance) <= 1.96 * np.sqrt(q.variance + q.noise_variance)
    assert 0.93 <= cover.mean() <= 0.985
    # At the step the query's own depth picks its layer: points of both layers within 0.3 m
    # of the step are read within a few centimetres (the raster holds one depth per cell).
    near = ~away
    assert np.sqrt(np.mean(q.signed_distance[near] ** 2)) < 0.05
    raster = query_points([model], held, 0.1, 1.0, 2.0)
    assert np.sqrt(np.mean(q.signed_distance[near] ** 2)) < 0.7 * np.sqrt(np.mean(raster.signed_distance[near] ** 2))


def test_the_calibration_is_learnt_leave_one_out(scene):
    _, local, *_ = scene
    assert 0.8 < local.calibration_ < 2.0
    # Leave-one-out: a stored point is never its own neighbour, duplicates included.
    pts = np.repeat(local.points[:5], 2, axis=0)
    dup = LocalSurface(pts, np.zeros(len(pts), np.int32), np.array([[0.0, -1.0, 0.0]]), neighbours=3)
    _, idx = dup._neighbours(pts, skip=np.arange(len(pts)))
    assert not np.any(idx == np.arange(len(pts))[:, None])


def test_blend_is_continuous_and_variance_grows_into_a_hole(scene):
    """Walking from mapped wall into the hole: no jump in mean or variance, and the variance
    grows; deep in the hole the raster alone answers."""
    model, local, frame, *_ = scene
    u = np.linspace(5.0, 6.75, 1751)  # 1 mm steps, ending in the hole's middle
    walk = frame.to_world(np.c_[u, np.full(len(u), 3.75), np.full(len(u), -STEP)])
    q = query_points([model], walk, 0.1, 1.0, 2.0, local=local)
    r = local.read(walk)
    assert r.weight[0] == 1.0 and r.weight[-1] == 0.0 and ((r.weight > 0) & (r.weight < 1)).sum() > 100
    # The raster itself steps at some cell boundaries (one depth per cell: the paper's); the
    # blend adds no jump of its own: wherever the raster moves by less than 2 mm in a 1 mm
    # step, so do the blended distance and sd (measured: 0.5 and 0.4 mm), the switch
    # between the readings included.
    raster = query_points([model], walk, 0.1, 1.0, 2.0)
    smooth = (np.abs(np.diff(raster.signed_distance)) < 2e-3) & (np.abs(np.diff(np.sqrt(raster.variance))) < 2e-3)
    assert smooth.mean() > 0.9 and (smooth & (r.weight[:-1] > 0) & (r.weight[:-1] < 1)).sum() > 100
    assert np.abs(np.diff(q.signed_distance))[smooth].max() < 2e-3
    assert np.abs(np.diff(np.sqrt(q.variance)))[smooth].max() < 2e-3
    assert q.signed_distance[-1] == raster.signed_distance[-1] and q.variance[-1] == raster.variance[-1]
    # The sd in the hole's middle is far above the sd on the wall.
    sd = np.sqrt(q.variance)
    assert sd[-1] > 3 * sd[:200].max()


def test_smoothstep_and_plane_fit_invariants():
    t = np.linspace(-1, 2, 301)
    s = smoothstep(t)
    assert s.min() == 0 and s.max() == 1 and np.all(np.diff(s) >= 0)
    # Exact plane: zero distance for points on it, the distance for a point off it, any rotation.
    rng = np.random.default_rng(1)
    nb = np.c_[rng.uniform(-1, 1, (1, 13, 2)).reshape(13, 2), np.zeros(13)][None]
    x = np.array([[0.1, 0.2, 0.05]])
    dist = np.linalg.norm(nb[0] - x, axis=1)[None]
    order = np.argsort(dist[0])
    s, normal, scatter, var, _ = fit_local_planes(x, nb[:, order], dist[:, order])
    assert abs(abs(s[0]) - 0.05) < 1e-9 and abs(abs(normal[0, 2]) - 1) < 1e-9
    assert scatter[0] < 1e-7 and var[0] < 1e-7


def test_config_chooses_the_reading(scene):
    model, local, frame, held, *_ = scene
    assert for_query([model], {0: local.points}, QueryConfig(surface='raster')) is None
    built = for_query([model], {0: local.points}, QueryConfig())
    assert isinstance(built, LocalSurface) and built.neighbours == QueryConfig().local_neighbours
    with pytest.raises(InputError, match='local_inner <= local_radius'):
        QueryConfig(local_inner=0.6, local_radius=0.5)
    with pytest.raises(InputError, match='occupancy event'):
        query_points([model], held[:3], 0.1, 1.0, 2.0, event='behind')


def test_surface_event_is_the_same_on_both_sides(scene):
    """p_occupied as 'the surface crosses the voxel' does not hinge on the façade's side."""
    model, local, frame, *_ = scene
    front = frame.to_world(np.array([[2.0, 3.0, 0.3], [2.0, 3.0, 0.0]]))
    back = frame.to_world(np.array([[2.0, 3.0, -0.3], [2.0, 3.0, 0.0]]))
    for loc in (None, local):
        pf = query_points([model], front, 0.1, 1.0, 2.0, local=loc, event='surface').p_occupied
        pb = query_points([model], back, 0.1, 1.0, 2.0, local=loc, event='surface').p_occupied
        assert pf[0] < 0.01 and pb[0] < 0.01 and pf[1] > 0.5
        solid = query_points([model], back, 0.1, 1.0, 2.0, local=loc, event='solid').p_occupied
        assert solid[0] > 0.99


def test_a_wall_piece_too_small_for_a_facade_is_answered(scene):
    """Stored points of a building without a façade (a piece of wall the clustering cut off)
    beside the façade's raster: answered by the local reading alone, with the nearest façade."""
    model, _, frame, *_ = scene
    rng = np.random.default_rng(3)
    uv = rng.uniform([11.0, 0.0], [12.5, 3.0], (150, 2))  # beyond the raster's u extent (0-10 m)
    piece = frame.to_world(np.c_[uv, 0.5 + rng.normal(0, NOISE, len(uv))])  # 0.5 m in front of the plane
    main = frame.to_world(np.c_[rng.uniform([0, 0], [10, 6], (1800, 2)), rng.normal(0, NOISE, 1800)])
    index = np.arange(len(main))
    model = type(model)(**{**{k: getattr(model, k) for k in model.__dataclass_fields__}, 'point_index': index})
    local = LocalSurface.of([model], {0: main, 1: piece})
    probe = frame.to_world(np.c_[rng.uniform([11.2, 0.2], [12.3, 2.8], (50, 2)), np.full(50, 0.52)])
    q = query_points([model], probe, 0.1, 1.0, 0.2, local=local)  # band_front 0.2: the piece is outside the band
    assert np.all(q.facade == 0)
    assert np.sqrt(np.mean((q.signed_distance - 0.02) ** 2)) < 0.02
    assert np.all(np.abs(q.signed_distance) <= 1.96 * np.sqrt(q.variance + q.noise_variance) + 0.03)


def test_a_wall_beyond_the_band_is_not_read_from_the_raster(scene):
    """Stored points of a wall with no façade of its own, before the façade's raster but
    beyond its band (a far wall across the street, behind the near one's (u, v)): the local
    reading answers alone there. The raster would read them metres off its own surface where
    they lie 0.2-0.5 m apart and the local reading's weight is below 1 (here 2.8 m RMSE
    before); on the KITTI sweep kitti_raw_0002_2 that gave real_check an observed RMSE of
    0.29 m (0.033 m now) with errors up to 27 m."""
    model, _, frame, *_ = scene
    rng = np.random.default_rng(4)
    main = frame.to_world(np.c_[rng.uniform([0, 0], [10, 6], (1800, 2)), rng.normal(0, NOISE, 1800)])
    uv = rng.uniform([3.0, 0.5], [6.0, 2.0], (30, 2))  # inside the raster's (u, v) extent, 0.4 m apart
    far = frame.to_world(np.c_[uv, 20.0 + rng.normal(0, NOISE, len(uv))])  # 20 m in front of the plane
    model = type(model)(**{**{k: getattr(model, k) for k in model.__dataclass_fields__},
                           'point_index': np.arange(len(main))})
    local = LocalSurface.of([model], {0: main, 1: far})
    probe = frame.to_world(np.c_[rng.uniform([3.2, 0.7], [5.8, 1.8], (50, 2)), np.full(50, 20.03)])
    q = query_points([model], probe, 0.1, 1.0, 2.0, local=local)
    assert np.all(q.facade == 0)
    assert np.sqrt(np.mean((q.signed_distance - 0.03) ** 2)) < 0.02
    assert np.mean(np.abs(q.signed_distance - 0.03) <= 1.96 * np.sqrt(q.variance + q.noise_variance)) >= 0.9


def test_outliers_well_in_front_of_the_wall_are_not_surface(scene):
    """Chi-squared outliers of the façade model that hold each other on a surface stay in the
    local reading (a window's frame, a sill: centimetres to decimetres off the wall), but not
    more than CLUTTER_FRONT in front of the façade's mean surface: a parked car's side there
    is no façade, and the paper's protocol's later campaigns pass through where it stood
    (on the simulated street the default reading's PR AUC at 0.1 m rose from 0.956 to 0.972)."""
    from uncertain_facade_map.pipeline.step7_local_surface import CLUTTER_FRONT

    model, _, frame, *_ = scene
    rng = np.random.default_rng(5)
    main = frame.to_world(np.c_[rng.uniform([0, 0], [4, 6], (900, 2)), rng.normal(0, NOISE, 900)])
    patch = rng.uniform([1.0, 1.0], [2.5, 2.0], (150, 2))  # 100 points/m^2, a surface of their own
    sill = frame.to_world(np.c_[patch, np.full(len(patch), 0.1) + rng.normal(0, NOISE, len(patch))])
    car = frame.to_world(np.c_[patch + [0.0, 2.5], np.full(len(patch), 1.0) + rng.normal(0, NOISE, len(patch))])
    pts = np.vstack([main, sill, car])
    fields = {k: getattr(model, k) for k in model.__dataclass_fields__}
    flagged = np.arange(len(main), len(pts))
    model = type(model)(**{**fields, 'point_index': np.arange(len(pts)), 'outlier_index': flagged})
    local = LocalSurface.of([model], {0: pts})
    kept = np.zeros(len(pts), bool)
    kept[local.source] = True
    assert kept[:len(main)].all()
    assert kept[len(main):len(main) + len(patch)].all()  # the sill, 0.1 m in front: kept
    assert not kept[len(main) + len(patch):].any()  # the car's side, 1 m in front: left out
    assert 0.1 < CLUTTER_FRONT < 1.0


def test_off_every_raster_the_local_plane_answers_up_to_its_reach_with_the_prior_variance(scene):
    """A point off every raster and band, 0.5-1.5 m from a wall piece with no façade of its
    own: answered from the piece's local plane (query.local_reach), never tightly (the
    façade's prior variance added); beyond the reach, or with reach 0, not at all."""
    model, _, frame, *_ = scene
    rng = np.random.default_rng(6)
    uv = rng.uniform([11.0, 0.0], [13.0, 3.0], (200, 2))  # beyond the raster's u extent (0-10 m)
    piece = frame.to_world(np.c_[uv, rng.normal(0, NOISE, len(uv))])
    main = frame.to_world(np.c_[rng.uniform([0, 0], [10, 6], (1800, 2)), rng.normal(0, NOISE, 1800)])
    model = type(model)(**{**{k: getattr(model, k) for k in model.__dataclass_fields__},
                           'point_index': np.arange(len(main))})
    local = LocalSurface.of([model], {0: main, 1: piece})
    probe = frame.to_world(np.array([[12.0, 1.5, 1.0], [12.0, 1.5, -0.8], [12.0, 1.5, 3.0]]))
    near = query_points([model], probe, 0.1, 1.0, 0.2, local=local, event='surface', reach=1.5)
    assert near.facade[:2].tolist() == [0, 0] and near.facade[2] == -1
    np.testing.assert_allclose(near.signed_distance[:2], [1.0, -0.8], atol=0.05)
    assert np.all(near.variance[:2] >= model.global_var_)
    assert np.all(near.p_occupied[:2] < 0.05)  # 1 m and 0.8 m from a determined plane: free
    none = query_points([model], probe, 0.1, 1.0, 0.2, local=local, event='surface', reach=0.0)
    assert np.all(none.facade == -1) and np.all(none.p_occupied == 0.5)


def test_a_plane_read_across_a_hole_gets_the_variance_of_its_gap():
    """A wall with an 8 cm relief (1.5 m waves) and 1 cm noise, and a 2 m x 2 m hole: the
    held-out points 0-0.5 m inside the hole are covered by the intervals once the gap's
    variance is learnt (and not without it), while the interior keeps its coverage."""
    rng = np.random.default_rng(3)

    def wall(n):
        u, v = rng.uniform(0, 12, n), rng.uniform(0, 6, n)
        depth = 0.08 * np.sin(2 * np.pi * u / 1.5) * np.cos(2 * np.pi * v / 1.7)
        return np.c_[u, depth, v], np.c_[u, depth + rng.normal(0, 0.01, n), v]

    truth, noisy = wall(40_000)
    hole = (np.abs(truth[:, 0] - 6) < 1) & (np.abs(truth[:, 2] - 3) < 1)  # held out as measured (noisy)
    stored = ~hole & (rng.random(len(truth)) < 0.5)
    local = LocalSurface(noisy[stored], np.zeros(stored.sum(), np.int32), np.array([[0.0, 1.0, 0.0]]))
    local.calibrate()
    assert 0.1 < local.gap_slope_ < 2 and 0 < local.gap_start_ < 0.3 and 0 < local.lever_start_ < 0.3
    inside = hole & (np.maximum(np.abs(truth[:, 0] - 6), np.abs(truth[:, 2] - 3)) > 0.5)
    interior = ~hole & ~stored

    def coverage(sel, slope):
        kept = local.gap_slope_
        local.gap_slope_ = slope
        r = local.read(noisy[sel])
        local.gap_slope_ = kept
        ok = r.weight > 0
        return np.mean(np.abs(r.signed_distance[ok]) <= 1.96 * np.sqrt(r.variance[ok] + r.noise_variance[ok]))

    assert coverage(inside, local.gap_slope_) >= 0.9 > 0.85 > coverage(inside, 0.0)
    assert 0.93 <= coverage(interior, local.gap_slope_) <= 0.97
