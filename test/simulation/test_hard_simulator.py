"""The hard simulator: walls as built (relief, plaster, glass) and the real error model
(mixed returns, range- and incidence-dependent noise, quantisation, registration offsets,
spinning lidars), each against its set figures."""

from dataclasses import replace

import numpy as np
import pytest

from uncertain_facade_map.io.cloud import CLASS_BUILDING
from uncertain_facade_map.simulation.campaign import (
    OUTLIER_GLASS,
    OUTLIER_MIXED,
    campaign,
    poses,
    simulate_campaign,
)
from uncertain_facade_map.simulation.presets import (
    SCENE_SENSORS,
    SENSOR_PRESETS,
    VLP32C_ELEVATIONS_DEG,
    WALL_PRESETS,
)
from uncertain_facade_map.simulation.scene import Recess, Scene
from uncertain_facade_map.simulation.scenes import SCENES, build_scene, with_walls
from uncertain_facade_map.simulation.sensor import SensorConfig, mixed_returns, quantise_float16, range_sigma
from uncertain_facade_map.simulation.walls import FacadeRelief, WallRealism

HARD = WALL_PRESETS['hard']
SMALL_HARD = SCENE_SENSORS['small_hard']
#: The small sensor's error model with every random term off.
EXACT = replace(SMALL_HARD, range_noise=0.0, range_noise_per_m=0.0, beam_divergence_mrad=0.0, beam_bias=0.0,
                outlier_share=0.0)


def rays_of(cloud):
    origins = cloud.sensor_origins
    d = cloud.xyz - origins
    r = np.linalg.norm(d, axis=1)
    return origins, d / r[:, None], r


@pytest.fixture(scope='module')
def small_hard():
    return build_scene('small_hard', 0)


@pytest.fixture(scope='module')
def bent_only(small_hard):
    """small_hard with relief but neither plaster nor glass."""
    walls = replace(small_hard.walls, plaster=0.0, glass_share=0.0)
    return Scene('bent', 0, small_hard.buildings, small_hard.static_occluders, small_hard.street,
                 small_hard.map_origin, walls=walls)


@pytest.fixture(scope='module')
def hard_cloud(small_hard):
    return simulate_campaign(small_hard, 0)


def test_hard_scenes_are_the_clean_geometry_with_walls_as_built():
    assert {'street_hard', 'zurich_hard', 'small_hard'} <= set(SCENES)
    clean, hard = build_scene('small', 0), build_scene('small_hard', 0)
    assert clean.walls is None and not clean.reliefs
    assert hard.walls == HARD and set(hard.reliefs) == {f.facade_id for f in hard.facades}
    assert [f.features for f in clean.facades] == [f.features for f in hard.facades]
    assert hard.name == 'small_hard' and SCENE_SENSORS['small_hard'] is SENSOR_PRESETS['vmx250-small']
    assert SCENE_SENSORS['street_hard'].scan_rate_hz == SCENE_SENSORS['street'].scan_rate_hz


def test_relief_is_in_the_truth_and_within_the_set_range(small_hard):
    clean = build_scene('small', 0)
    for facade in small_hard.facades:
        fr = facade.frame
        relief = small_hard.reliefs[facade.facade_id]
        assert HARD.bow[0] <= abs(relief.bow) <= HARD.bow[1]
        assert HARD.lean[0] <= abs(relief.lean) <= HARD.lean[1]
        u, v = np.meshgrid(np.linspace(0.3, fr.length - 0.3, 40), np.linspace(0.3, fr.height - 0.3, 30))
        u, v = u.ravel(), v.ravel()
        plain = clean.true_depth(facade.facade_id, u, v)
        wall = plain == 0.0  # the wall itself, not a window, balcony or column
        bent = small_hard.true_depth(facade.facade_id, u[wall], v[wall])
        np.testing.assert_allclose(bent, small_hard.relief_at(facade.facade_id, u[wall], v[wall]), atol=1e-6)
        # Centimetres over metres: at most bow + lean x height + the undulations.
        most = HARD.bow[1] + HARD.lean[1] * fr.height + HARD.waves * HARD.waviness[1]
        assert 0.005 < np.abs(bent).max() <= most
        # Recesses move with the wall.
        for f in facade.features:
            if isinstance(f, Recess) and f.u1 - f.u0 > 0.2:
                uc, vc = np.array([(f.u0 + f.u1) / 2]), np.array([(f.v0 + f.v1) / 2])
                if clean.true_depth(facade.facade_id, uc, vc)[0] == pytest.approx(-f.depth):
                    assert small_hard.true_depth(facade.facade_id, uc, vc)[0] == pytest.approx(
                        -f.depth + small_hard.relief_at(facade.facade_id, uc, vc)[0], abs=1e-6)


def test_noise_free_returns_lie_on_the_bent_walls(bent_only):
    cloud = simulate_campaign(bent_only, 0, EXACT)
    pts = cloud.points
    checked = 0
    for fid in np.unique(pts['gt_facade'][pts['gt_facade'] >= 0]):
        sel = pts['gt_facade'] == fid
        uvn = bent_only.facades[fid].frame.to_facade(cloud.xyz[sel])
        err = uvn[:, 2] - bent_only.true_depth(int(fid), uvn[:, 0], uvn[:, 1])
        exact = np.abs(err) < 1e-6
        # The rest hit the sides of recesses, balconies and columns (the truth looks along the normal).
        assert exact.mean() > 0.85
        assert (np.abs(err) < 0.01).sum() - exact.sum() < 0.02 * exact.sum()
        checked += exact.sum()
    assert checked > 10_000


def test_relief_gradient_matches_finite_differences():
    relief = FacadeRelief.draw(HARD, 20.0, 12.0, np.random.default_rng(3))
    u, v = np.random.default_rng(4).uniform([0.5, 0.5], [19.5, 11.5], size=(200, 2)).T
    r, du, dv = relief.depth(u, v)
    h = 1e-6
    np.testing.assert_allclose(du, (relief.depth(u + h, v)[0] - relief.depth(u - h, v)[0]) / (2 * h), atol=1e-7)
    np.testing.assert_allclose(dv, (relief.depth(u, v + h)[0] - relief.depth(u, v - h)[0]) / (2 * h), atol=1e-7)


def test_plaster_texture_has_the_set_spread_and_repeats():
    relief = FacadeRelief.draw(HARD, 20.0, 12.0, np.random.default_rng(5))
    u, v = np.random.default_rng(6).uniform(0, 10, size=(2, 100_000))
    tex = relief.plaster(u, v, 0.002, 0.02)
    assert tex.std() == pytest.approx(0.002, rel=0.1)
    assert abs(tex.mean()) < 1e-4
    np.testing.assert_array_equal(tex, relief.plaster(u, v, 0.002, 0.02))  # the same wall every campaign
    # Smooth below the cell: points 2 mm apart differ far less than the spread.
    assert np.abs(relief.plaster(u + 0.002, v, 0.002, 0.02) - tex).mean() < 0.3 * 0.002


def test_glass_returns_come_from_behind_the_panes_at_the_set_share(small_hard, hard_cloud):
    pts = hard_cloud.points
    glass = pts['gt_outlier'] == OUTLIER_GLASS
    assert glass.sum() > 200
    assert np.all(pts['class'][glass] == CLASS_BUILDING)
    origins, dirs, r = rays_of(hard_cloud)
    cand = np.flatnonzero((pts['class'] == CLASS_BUILDING) & ((pts['gt_outlier'] == 0) | glass))
    truth = small_hard.building_caster().cast(origins[cand], dirs[cand])
    on_pane = np.zeros(len(cand), dtype=bool)
    for fid in np.unique(truth.facade_id[truth.facade_id >= 0]):
        rows = np.flatnonzero(truth.facade_id == fid)
        on_pane[rows] = small_hard.glass(int(fid), origins[cand[rows]] + truth.t[rows, None] * dirs[cand[rows]])
    through = glass[cand]
    assert np.all(on_pane[through]), 'a glass return whose ray did not meet a pane'
    share = through[on_pane].mean()
    n = on_pane.sum()
    assert abs(share - HARD.glass_share) < 4 * np.sqrt(0.25 / n)
    behind = r[cand][through] - truth.t[through]
    sigma = 0.02  # the noise of the small scene's sensor at these ranges is well under this
    assert behind.min() > HARD.room_depth[0] - sigma and behind.max() < HARD.room_depth[1] + sigma
    # Behind the façade: inside the building's footprint or at least behind its wall plane.
    for fid in np.unique(pts['gt_facade'][glass]):
        sel = glass & (pts['gt_facade'] == fid)
        depth = small_hard.facades[fid].frame.to_facade(hard_cloud.xyz[sel])[:, 2]
        assert np.all(depth < -0.3)


def test_mixed_returns_only_at_depth_edges_at_the_set_probability():
    rng = np.random.default_rng(0)
    edges = 4000
    # Profiles of 20 shots: a smooth oblique ramp, then a 0.3 m step between shots 9 and 10.
    ramp = 10.0 + 0.15 * np.arange(20)
    t = np.tile(np.where(np.arange(20) >= 10, ramp + 0.3, ramp), edges)
    nb = np.arange(len(t)) + 1
    nb[19::20] = -1
    rows, ranges = mixed_returns(t, nb, (0.05, 2.0), 0.4, rng)
    assert np.all(rows % 20 == 9), 'mixed away from the edge'
    assert len(rows) / edges == pytest.approx(0.4, abs=4 * np.sqrt(0.24 / edges))
    assert np.all((ranges > t[rows]) & (ranges < t[rows + 1]))
    # Too far apart (two echoes): no mixing; a smooth surface: none either.
    far = np.tile(np.where(np.arange(20) >= 10, ramp + 3.0, ramp), 100)
    assert len(mixed_returns(far, nb[:2000], (0.05, 2.0), 1.0, rng)[0]) == 0
    assert len(mixed_returns(np.tile(ramp, 100), nb[:2000], (0.05, 2.0), 1.0, rng)[0]) == 0


def test_mixed_returns_in_a_campaign_lie_between_surfaces(small_hard, hard_cloud):
    pts = hard_cloud.points
    mixed = pts['gt_outlier'] == OUTLIER_MIXED
    p = SMALL_HARD.mixed_probability
    assert p == pytest.approx(0.35e-3 / np.deg2rad(0.5))
    assert mixed.sum() > 50
    origins, dirs, r = rays_of(hard_cloud.select(mixed))
    truth = small_hard.caster().cast(origins, dirs)  # without parked cars: other surfaces differ
    gap = r - truth.t
    assert np.median(np.abs(gap[np.isfinite(gap)])) > 0.02


def test_range_and_incidence_noise_has_the_set_sigma(bent_only):
    vmx = SENSOR_PRESETS['vmx250']
    assert range_sigma(vmx, np.array([50.0]), np.array([1.0]))[0] == pytest.approx(0.005, rel=0.01)
    assert range_sigma(vmx, np.array([5.0]), np.array([1.0]))[0] == pytest.approx(0.004, rel=0.01)
    r = np.full(3, 20.0)
    grown = range_sigma(vmx, r, np.cos(np.deg2rad([0.0, 60.0, 80.0])))
    assert grown[0] < grown[1] < grown[2]
    # footprint term: r beta tan(alpha) / sqrt(12)
    extra = np.sqrt(grown[2] ** 2 - grown[0] ** 2)
    assert extra == pytest.approx(20.0 * 0.35e-3 * np.tan(np.deg2rad(80.0)) / np.sqrt(12), rel=1e-6)
    # In a campaign: the errors of wall returns over their predicted sigma are standard normal.
    noisy = replace(EXACT, range_noise=0.01, range_noise_per_m=0.001, beam_divergence_mrad=2.0)
    noisy = replace(noisy, mixed_gap=(1e3, 1e3))  # no mixed returns, to compare the noise alone
    cloud = simulate_campaign(bent_only, 0, noisy)
    pts = cloud.points
    sel = (pts['gt_facade'] >= 0) & (pts['gt_outlier'] == 0)
    origins, dirs, r = rays_of(cloud.select(sel))
    truth = bent_only.building_caster().cast(origins, dirs)
    normals = np.array([f.frame.n for f in bent_only.facades])[pts['gt_facade'][sel]]
    sigma = range_sigma(noisy, truth.t, np.abs(np.einsum('ij,ij->i', dirs, normals)))
    z = (r - truth.t) / sigma
    z = z[np.isfinite(z) & (np.abs(r - truth.t) < 0.2)]
    assert len(z) > 10_000
    assert abs(z.mean()) < 0.03 and z.std() == pytest.approx(1.0, abs=0.05)


def test_float16_quantisation_steps_are_argoverse_ones():
    x = 10.0 + np.arange(2000) * 1e-4
    pts = np.stack([x, np.zeros_like(x), np.zeros_like(x)], axis=1)
    q = quantise_float16(pts, np.zeros((len(x), 2)), np.zeros(len(x)))
    steps = np.diff(np.unique(q[:, 0]))
    assert steps == pytest.approx(0.0078125)  # 7.8 mm at 8-16 m
    q20 = quantise_float16(pts + [10.0, 0, 0], np.zeros((len(x), 2)), np.zeros(len(x)))
    assert np.diff(np.unique(q20[:, 0])) == pytest.approx(0.015625)  # 15.6 mm at 16-32 m
    # In the vehicle frame: a turned vehicle elsewhere quantises the same offsets.
    yaw = np.full(len(x), 0.7)
    at = np.array([[100.0, -40.0]]).repeat(len(x), 0)
    world = np.stack([100.0 + np.cos(0.7) * x, -40.0 + np.sin(0.7) * x, np.zeros_like(x)], axis=1)
    back = quantise_float16(world, at, yaw)
    local = np.cos(0.7) * (back[:, 0] - 100.0) + np.sin(0.7) * (back[:, 1] + 40.0)
    np.testing.assert_allclose(local, q[:, 0], atol=1e-9)


def test_av2_sweep_is_two_vlp32c_with_float16_coordinates():
    scene = build_scene('small_hard', 0)
    av2 = SENSOR_PRESETS['av2']
    sweep = simulate_campaign(scene, 0, av2, window=(3.0, 3.1))
    shots = 2 * 32 * 1800
    assert 0.5 * shots < len(sweep) < shots
    assert np.ptp(sweep.points['time']) <= 0.1
    # Beam elevations: the VLP-32C's, once upright (upper lidar) and once upside down.
    origins, dirs, r = rays_of(sweep)
    el = np.rad2deg(np.arcsin(dirs[:, 2]))
    upper = origins[:, 2] > 1.9
    table = np.asarray(VLP32C_ELEVATIONS_DEG)
    assert np.abs(el[upper][:, None] - table).min(axis=1).max() < 0.3  # noise moves points a little
    assert np.abs(el[~upper][:, None] + table).min(axis=1).max() < 0.3
    # Coordinates in the vehicle frame are float16 values: multiples of 7.8 mm at 8-16 m.
    drive = campaign(scene, 0)
    xy, yaw = poses(scene, drive, av2, sweep.points['time'] - drive.start_time)
    dx, dy = sweep.xyz[:, 0] - xy[:, 0], sweep.xyz[:, 1] - xy[:, 1]
    forward = np.cos(yaw) * dx + np.sin(yaw) * dy
    band = (np.abs(forward) >= 8) & (np.abs(forward) < 16)
    assert band.sum() > 1000
    steps = forward[band] / 0.0078125
    np.testing.assert_allclose(steps, np.round(steps), atol=1e-6)


def test_campaigns_after_the_first_are_offset_by_a_few_centimetres(small_hard):
    unregistered = replace(SMALL_HARD, registration_sigma=(0.0, 0.0, 0.0))
    first = simulate_campaign(small_hard, 0, SMALL_HARD)
    assert first.same_as(simulate_campaign(small_hard, 0, unregistered)), 'campaign 0 defines the frame'
    moved = simulate_campaign(small_hard, 1, SMALL_HARD)
    plain = simulate_campaign(small_hard, 1, unregistered)
    # Rigid: the ranges and the distances between points are kept.
    np.testing.assert_allclose(rays_of(moved)[2], rays_of(plain)[2], atol=1e-9)
    pick = np.random.default_rng(0).choice(len(moved), (2, 2000))
    np.testing.assert_allclose(np.linalg.norm(moved.xyz[pick[0]] - moved.xyz[pick[1]], axis=1),
                               np.linalg.norm(plain.xyz[pick[0]] - plain.xyz[pick[1]], axis=1), atol=1e-9)
    size = np.linalg.norm(moved.xyz - plain.xyz, axis=1)
    assert 0.005 < size.mean() < 0.15 and np.ptp(size) < 0.02


def test_every_sensor_preset_is_valid_and_bad_settings_are_refused():
    for name, sensor in SENSOR_PRESETS.items():
        assert isinstance(sensor, SensorConfig), name
    from uncertain_facade_map.errors import InputError

    for bad in ({'pattern': 'helix'}, {'pattern': 'spinning'}, {'quantise': 'float8'},
                {'registration_sigma': (0.1, -1.0, 0.0)}, {'beam_divergence_mrad': -1.0}):
        with pytest.raises(InputError):
            SensorConfig(**bad)
    with pytest.raises(InputError):
        WallRealism(glass_share=1.5)
    with pytest.raises(InputError):
        with_walls(build_scene('small', 0), 'nope')
