"""The ``city`` scene (issue 29): layout, ids, truth, determinism, the default size (about 10 s)."""

import json

import numpy as np
import pytest

from uncertain_facade_map.errors import InputError
from uncertain_facade_map.simulation.campaign import campaign
from uncertain_facade_map.simulation.city import (
    CITY_PRESETS,
    CityConfig,
    SegmentTask,
    build_city,
    city_files,
    estimate_points,
    segment_file,
    segment_scene,
    simulate_segment,
    write_segment,
)
from uncertain_facade_map.simulation.presets import SCENE_SENSORS
from uncertain_facade_map.simulation.scenes import parked_cars

SMALL = CITY_PRESETS['city_small']
SENSOR = SCENE_SENSORS['city_small']


@pytest.fixture(scope='module')
def small():
    return build_city(0, SMALL, 'city_small')


@pytest.fixture(scope='module')
def drive(small):
    """Campaign 0 of the small city, segment by segment."""
    return [simulate_segment(small, 0, k, SENSOR) for k in range(len(small.segments))]


def test_layout_of_the_small_city(small):
    # 2 x 1 blocks of 30 m: pitch 48 m, 2 * 2 x-segments and 3 * 1 y-segments.
    assert SMALL.pitch == 48.0
    assert [s.axis for s in small.segments] == ['x'] * 4 + ['y'] * 3
    assert SMALL.street_length == pytest.approx(sum(s.length for s in small.segments)) == 7 * 48.0
    ids = [b.building_id for b in small.scene.buildings]
    assert ids == list(range(len(ids))) and len(ids) >= 8
    assert [f.facade_id for f in small.scene.facades] == list(range(len(small.scene.facades)))
    # Every building stands inside a block, between the façade lines of its streets.
    for b in small.scene.buildings:
        local = np.mod(b.polygon, SMALL.pitch)
        assert np.all(local >= 9.0 - 1e-9) and np.all(local <= 9.0 + SMALL.block + 1e-9)


def test_default_city_size_and_points():
    """The issue's figures: at least 3 km of street and 20 M points in the 2 default drives
    (estimated from 2 segments simulated, one on the boundary, one inside, so the test stays in seconds)."""
    config = CITY_PRESETS['city']
    assert config.street_length == 3348.0 >= 3000.0
    city = build_city(0)
    assert len(city.segments) == 31
    sizes = np.array([np.ptp(b.polygon, axis=0).max() for b in city.scene.buildings])
    assert len(sizes) >= 150 and sizes.min() < 9.0 and (sizes > 35.0).sum() >= 5  # some small, a few large
    assert estimate_points(city, campaigns=2, sample=1) >= 22e6


def test_ids_and_truth(small, drive):
    """Every point carries its sensor origin and the city-wide ids of what it hit: the whole
    city's buildings, cast from the origin towards the point, meet the same building at the
    point's range within the noise."""
    pts = np.concatenate([c.points for c in drive])
    assert {'origin_x', 'origin_y', 'origin_z', 'building_id', 'gt_facade'} <= set(pts.dtype.names)
    ids = {b.building_id for b in small.scene.buildings}
    on = pts['building_id'] >= 0
    assert set(np.unique(pts['building_id'][on])) == ids  # every building seen, no other id
    owner = np.array([f.building_id for f in small.scene.facades])
    fac = pts['gt_facade'] >= 0
    np.testing.assert_array_equal(owner[pts['gt_facade'][fac]], pts['building_id'][fac])
    clean = pts[on & (pts['gt_outlier'] == 0)]
    xyz = np.stack([clean['x'], clean['y'], clean['z']], axis=1)
    origin = np.stack([clean['origin_x'], clean['origin_y'], clean['origin_z']], axis=1)
    r = np.linalg.norm(xyz - origin, axis=1)
    hits = small.scene.building_caster().cast(origin, (xyz - origin) / r[:, None])
    np.testing.assert_array_equal(hits.building_id, clean['building_id'])
    np.testing.assert_array_equal(hits.facade_id, clean['gt_facade'])
    err = r - hits.t
    assert np.abs(err).max() < 6 * SENSOR.range_noise
    assert np.std(err) == pytest.approx(SENSOR.range_noise, rel=0.1)


def test_drive_follows_the_segments(small, drive):
    times = [(c.points['time'].min(), c.points['time'].max()) for c in drive]
    assert all(a[1] < b[0] for a, b in zip(times, times[1:]))  # one drive, segment after segment
    for seg, cloud in zip(small.segments, drive):
        origin = np.stack([cloud.points['origin_x'], cloud.points['origin_y']], axis=1)
        a, b = np.array(seg.start), np.array(seg.end)
        u = (b - a) / seg.length
        lateral = (origin - a) @ np.array([-u[1], u[0]])
        along = (origin - a) @ u
        # Campaign 0 drives the right lane (1.75 m right of the centreline); the scanners sit 0.3 m aside.
        assert np.all(np.abs(lateral + 1.75) <= 0.31) and along.min() > -1.0 and along.max() < seg.length + 1.0


def test_parked_cars_follow_a_street_along_y(small):
    seg = next(s for s in small.segments if s.axis == 'y')
    scene, _, _ = segment_scene(small, seg.index, SENSOR)
    cars = parked_cars(scene, np.random.default_rng([campaign(scene, 0).seed, 1]))
    assert cars
    xy = np.array([[c.x, c.y] for c in cars])
    assert np.all(np.abs(np.abs(xy[:, 0] - seg.start[0]) - 6.55) < 0.6)  # on the kerbs either side
    assert np.all((xy[:, 1] > seg.start[1] + 12.0) & (xy[:, 1] < seg.end[1] - 12.0))  # clear of the crossings
    assert np.allclose([c.yaw for c in cars], np.pi / 2, atol=0.15)


def test_same_seed_same_bytes(small, tmp_path):
    paths = []
    for run in ('a', 'b'):
        task = SegmentTask(0, SMALL, 'city_small', SENSOR, 1, 5, segment_file(tmp_path / run, 1, 5))
        n, _ = write_segment(task)
        assert n > 10_000
        paths.append(task.path)
    assert paths[0].read_bytes() == paths[1].read_bytes()
    other = simulate_segment(build_city(1, SMALL, 'city_small'), 1, 5, SENSOR)
    assert len(other) != n


def test_city_files_lists_the_run(tmp_path):
    from uncertain_facade_map_apps.cli import main

    out = tmp_path / 'city'
    assert main(['simulate', '--scene', 'city_small', '--city-blocks', '1,1', '--city-block', '20',
                 '--campaigns', '2', '--formats', 'npz', '--out', str(out), '--quiet']) == 0
    files = city_files(out)
    assert [p.relative_to(out).as_posix() for p in files] == [
        f'campaign{k}/seg_{s:03d}.npz' for k in (0, 1) for s in range(4)]
    assert city_files(out, [1]) == files[4:]
    desc = json.loads((out / 'scene.json').read_text())
    assert desc['city']['street_length'] == 4 * 38.0 and len(desc['buildings']) >= 4
    assert sum(desc['city']['segment_points']['0']) == desc['campaigns'][0]['points']
    with pytest.raises(InputError, match='no campaign 2'):
        city_files(out, [2])


def test_bad_sizes():
    with pytest.raises(InputError, match='at least 1'):
        CityConfig((0, 2))
    with pytest.raises(InputError, match='at least 20 m'):
        CityConfig((2, 2), 10.0)
