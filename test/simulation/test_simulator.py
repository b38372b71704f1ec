"""The scan simulator against its own exact truth: surfaces, noise, shadows, campaigns."""

from dataclasses import replace

import numpy as np
import pytest

from uncertain_facade_map.io.cloud import CLASS_BUILDING
from uncertain_facade_map.simulation.campaign import SCENE_SENSORS, campaign, simulate_campaign
from uncertain_facade_map.simulation.scene import Block, Recess, Round, Slope
from uncertain_facade_map.simulation.scenes import build_scene, parked_cars, zurich_scene

SMALL = SCENE_SENSORS['small']
EXACT = replace(SMALL, range_noise=0.0, outlier_share=0.0)


@pytest.fixture(scope='module')
def small():
    return build_scene('small', 0)


@pytest.fixture(scope='module')
def exact_cloud(small):
    return simulate_campaign(small, 0, EXACT)


@pytest.fixture(scope='module')
def noisy_cloud(small):
    return simulate_campaign(small, 0, SMALL)


def rays_of(cloud):
    origins = cloud.sensor_origins
    d = cloud.xyz - origins
    r = np.linalg.norm(d, axis=1)
    return origins, d / r[:, None], r


def test_noise_free_building_hits_lie_exactly_on_the_surface(small, exact_cloud):
    pts = exact_cloud.points
    b = pts['class'] == CLASS_BUILDING
    assert b.sum() > 5000
    origins, dirs, r = rays_of(exact_cloud.select(b))
    eps = 1e-4
    before = small.inside_building(origins + (r - eps)[:, None] * dirs)
    after = small.inside_building(origins + (r + eps)[:, None] * dirs)
    assert not before.any(), 'a return lies inside a building'
    assert after.mean() > 0.999, 'a return is not on a building surface'


def test_ground_hits_are_on_the_ground(exact_cloud):
    g = exact_cloud.points['class'] == 2
    assert g.sum() > 1000
    np.testing.assert_allclose(exact_cloud.points['z'][g], 0.0, atol=1e-9)


def test_range_noise_has_the_configured_sigma(small, noisy_cloud):
    pts = noisy_cloud.points
    sel = (pts['class'] == CLASS_BUILDING) & (pts['gt_outlier'] == 0)
    origins, dirs, r = rays_of(noisy_cloud.select(sel))
    truth = small.building_caster().cast(origins, dirs).t
    ok = np.isfinite(truth) & (np.abs(r - truth) < 0.2)  # a few rays graze an edge and change surface
    assert ok.mean() > 0.99
    err = r[ok] - truth[ok]
    assert abs(err.mean()) < 0.002
    assert 0.018 < err.std() < 0.022


def test_outliers_have_the_configured_share_and_stand_in_front(small, noisy_cloud):
    pts = noisy_cloud.points
    building = pts['class'] == CLASS_BUILDING
    out = pts['gt_outlier'] == 1
    share = out.sum() / building.sum()
    n = building.sum()
    assert abs(share - SMALL.outlier_share) < 4 * np.sqrt(SMALL.outlier_share / n)
    assert np.all(building[out]), 'outliers are labelled building (misclassified clutter)'
    origins, dirs, r = rays_of(noisy_cloud.select(out))
    truth = small.building_caster().cast(origins, dirs).t
    gap = truth - r
    assert np.all(gap > SMALL.outlier_gap[0] - 0.1) and np.all(gap < SMALL.outlier_gap[1] + 0.1)


def test_occluders_cast_shadows_on_facades(small):
    cloud = simulate_campaign(small, 0, EXACT)
    origins, dirs, _ = rays_of(cloud)
    only_buildings = small.building_caster().cast(origins, dirs)
    labels = cloud.points['class']
    shadowed = np.isfinite(only_buildings.t) & (labels != CLASS_BUILDING) & (labels != 2)
    assert shadowed.sum() > 500, 'trees, poles and cars must hide parts of the façades'
    # The façade grid behind the tree and the cars: cells that lose most of their points.
    facade = small.facades[0]
    hit_b = only_buildings.facade_id == facade.facade_id
    seen = facade.frame.to_facade(origins[hit_b] + only_buildings.t[hit_b, None] * dirs[hit_b])
    got = cloud.points[cloud.points['gt_facade'] == facade.facade_id]
    got_uv = facade.frame.to_facade(np.stack([got['x'], got['y'], got['z']], 1))
    edges = [np.arange(0, facade.frame.length + 1, 1.0), np.arange(0, facade.frame.height + 1, 1.0)]
    free, _, _ = np.histogram2d(seen[:, 0], seen[:, 1], bins=edges)
    real, _, _ = np.histogram2d(got_uv[:, 0], got_uv[:, 1], bins=edges)
    assert ((free > 10) & (real < 0.3 * free)).sum() >= 3, 'no façade cell lies in a shadow'


def test_true_depth_follows_each_feature(small):
    kinds = set()
    for facade in small.facades:
        for f in facade.features:
            if isinstance(f, Recess):
                u, v, expect = (f.u0 + f.u1) / 2, (f.v0 + f.v1) / 2, -f.depth
            elif isinstance(f, Block):
                u, v, expect = (f.u0 + f.u1) / 2, f.v1 - 0.05, f.out
            elif isinstance(f, Slope):
                v = f.v0 + 0.25 * (f.v1 - f.v0)
                u, expect = (f.u0 + f.u1) / 2, f.out0 + 0.25 * (f.out1 - f.out0)
            else:
                u, v, expect = f.uc, (f.v0 + f.v1) / 2, f.nc + f.radius
            depth = small.true_depth(facade.facade_id, np.array([u]), np.array([v]))[0]
            if isinstance(f, Recess) and depth > 0:
                continue  # a balcony stands in front of this window
            assert depth == pytest.approx(expect, abs=1e-9), f
            kinds.add(f.kind if isinstance(f, Round) else type(f).__name__)
    assert kinds >= {'Recess', 'Block', 'Slope', 'bay', 'column'}
    # A plain wall point is at depth 0.
    f0 = small.facades[0]
    assert small.true_depth(0, np.array([0.3]), np.array([f0.frame.height - 0.2]))[0] == pytest.approx(0.0)


def test_recess_depths_and_protrusions_are_in_the_issue_ranges(small):
    street = build_scene('street', 0)
    for scene in (small, street):
        for facade in scene.facades:
            for f in facade.features:
                if isinstance(f, Recess):
                    assert 0.05 <= f.depth <= 0.30
                if isinstance(f, Block):
                    assert 0.3 <= f.out <= 1.5
                if isinstance(f, Slope):
                    assert max(f.out0, f.out1) > 0 and f.v1 > f.v0


def test_same_seed_same_points_other_seed_other_scene(small, noisy_cloud):
    again = simulate_campaign(build_scene('small', 0), 0, SMALL)
    assert again.same_as(noisy_cloud)
    other = build_scene('small', 1)
    assert [len(f.features) for f in other.facades] != [len(f.features) for f in small.facades] or \
        not np.array_equal(other.facades[0].features, small.facades[0].features)


def test_campaigns_differ_but_map_the_same_buildings(small, noisy_cloud):
    second = simulate_campaign(small, 1, SMALL)
    c0, c1 = campaign(small, 0), campaign(small, 1)
    assert (c0.lane, c0.reverse) != (c1.lane, c1.reverse)
    assert second.points['time'].min() > noisy_cloud.points['time'].max()
    cars0 = parked_cars(small, np.random.default_rng([c0.seed, 1]))
    cars1 = parked_cars(small, np.random.default_rng([c1.seed, 1]))
    assert [(c.x, c.y) for c in cars0] != [(c.x, c.y) for c in cars1]
    o0 = noisy_cloud.sensor_origins
    o1 = second.sensor_origins
    assert abs(np.median(o0[:, 1]) - np.median(o1[:, 1])) > 1.0  # other lane
    b0 = set(np.unique(noisy_cloud.points['building_id'][noisy_cloud.points['class'] == CLASS_BUILDING]))
    b1 = set(np.unique(second.points['building_id'][second.points['class'] == CLASS_BUILDING]))
    assert b0 == b1 == {0, 1}


def test_small_scene_stays_under_50k_points(noisy_cloud):
    assert 10_000 < len(noisy_cloud) <= 50_000
    assert (noisy_cloud.points['time'][1:] >= noisy_cloud.points['time'][:-1]).all()


def test_float32_coordinates_keep_millimetres(small, noisy_cloud):
    f4 = simulate_campaign(small, 0, SMALL, xyz_dtype='f4')
    assert f4.points.dtype['x'] == np.float32
    assert np.abs(f4.xyz - noisy_cloud.xyz).max() < 1e-3
    np.testing.assert_array_equal(f4.map_origin, noisy_cloud.map_origin)


@pytest.mark.slow
def test_street_scene_has_the_size_the_issue_asks():
    street = build_scene('street', 0)
    cloud = simulate_campaign(street, 0)
    pts = cloud.points
    assert 1_000_000 <= len(cloud) <= 2_000_000
    b = (pts['class'] == CLASS_BUILDING) & (pts['gt_facade'] >= 0)
    per_facade = np.bincount(pts['gt_facade'][b])
    assert (per_facade >= 1000).sum() >= 10
    assert len(np.unique(pts['building_id'][b])) >= 6
    assert 0.005 < pts['gt_outlier'].sum() / b.sum() < 0.015


def test_zurich_scene_uses_real_footprints():
    scene = zurich_scene(0)
    assert len(scene.buildings) == 8
    assert all(b.source.startswith('UUID_') or b.source for b in scene.buildings)
    assert any(len(b.polygon) > 4 for b in scene.buildings), 'real footprints are not all rectangles'
    coarse = replace(SCENE_SENSORS['zurich'], angular_step_deg=1.0, scan_rate_hz=5.0)
    cloud = simulate_campaign(scene, 0, coarse)
    hit = np.unique(cloud.points['building_id'][cloud.points['class'] == CLASS_BUILDING])
    assert len(hit) >= 7
