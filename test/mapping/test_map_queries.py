"""The map answers its own queries (FacadeMap.query, MapSnapshot.query): the core's query_map
with the map's bands, learnt occupancy and registration variance, its local surface kept
while the map stands and read again once it changes."""

import dataclasses

import numpy as np
import pytest
from support import wall_scan

from uncertain_facade_map.errors import InputError
from uncertain_facade_map.mapping.engine import view_of
from uncertain_facade_map.mapping.facade_map import build_map
from uncertain_facade_map.mapping.worker import MapSnapshot
from uncertain_facade_map.params import MapParams, QueryConfig
from uncertain_facade_map.pipeline.step7_queries import query_map
from uncertain_facade_map.pipeline.step8_occupancy import PLSC


def _assert_same(a, b) -> None:
    for key, value in a.as_dict().items():
        np.testing.assert_array_equal(value, b.as_dict()[key], err_msg=key)


@pytest.fixture(scope='module')
def wall():
    xyz, origins = wall_scan(seed=0)
    rng = np.random.default_rng(4)
    probe = xyz[rng.choice(len(xyz), 2000, replace=False)] + rng.normal(0.0, 0.3, (2000, 3))
    return xyz, origins, probe


def _by_hand(fmap, xyz, config, resolution):
    ex = fmap.params.extraction
    return query_map(fmap.facades, fmap.points, xyz, resolution, ex.band_back, ex.band_front, fmap.occupancy_, config,
                     registration_var=fmap.registration_var_)


def test_the_map_answers_with_its_own_bands_occupancy_and_variance(wall):
    xyz, origins, probe = wall
    params = MapParams()
    narrow = dataclasses.replace(params, extraction=dataclasses.replace(params.extraction, band_back=0.2,
                                                                        band_front=0.3))
    fmap = build_map(xyz, None, origins, narrow)
    fmap.occupancy_ = PLSC(2.0, 0.05)
    fmap.registration_var_ = 0.01**2
    for config in (QueryConfig(), QueryConfig(surface='raster', occupancy_event='solid'),
                   QueryConfig(occupancy='fixed')):
        _assert_same(fmap.query(probe, config, 0.2), _by_hand(fmap, probe, config, 0.2))
    _assert_same(fmap.query(probe), _by_hand(fmap, probe, QueryConfig(), 0.1))  # query.resolution, surface event
    raster = QueryConfig(surface='raster')
    wide = build_map(xyz, None, origins)
    share = [(m.query(probe, raster).facade >= 0).mean() for m in (fmap, wide)]
    assert share[0] < 0.8 < share[1], f'the narrow bands leave points out: {share}'
    _assert_same(fmap.query(probe, event='solid'), _by_hand(fmap, probe, QueryConfig(occupancy_event='solid'), 0.1))
    with pytest.raises(InputError):
        fmap.query(probe, event='behind')


def test_the_local_surface_is_kept_until_the_map_changes(wall):
    xyz, origins, probe = wall
    fmap = build_map(xyz[:6000], None, origins[:6000])
    first = fmap.local_surface()
    assert first is not None and fmap.local_surface(QueryConfig()) is first
    assert fmap.local_surface(QueryConfig(surface='raster')) is None
    assert fmap.local_surface(QueryConfig(local_neighbours=20)) is not first
    fmap.add_points(xyz[6000:], None, origins[6000:])
    assert fmap.local_surface() is not first
    _assert_same(fmap.query(probe), _by_hand(fmap, probe, QueryConfig(), 0.1))
    clone = fmap.clone()
    assert clone.local_surface() is fmap.local_surface(), 'a clone shares the arrays, and so the reading'


def test_a_snapshot_answers_as_its_map(wall):
    xyz, origins, probe = wall
    fmap = build_map(xyz, None, origins)
    fmap.occupancy_ = PLSC(1.5, 0.02)
    view = view_of(fmap)
    snap = MapSnapshot(1, view.facades, view.map_origin, view.buildings, view.points, 0, view.params, view.stored,
                       view.map_bytes, view.occupancy, view.stored_points, view.registration_var)
    for config in (QueryConfig(), QueryConfig(surface='raster')):
        _assert_same(snap.query(probe, config, 0.05), fmap.query(probe, config, 0.05))
    assert snap.local_surface() is snap.local_surface()


def test_normals_of_a_flat_wall_are_its_normal(wall):
    """A flat wall scanned from y < WALL_Y with 2 cm noise: the answers' normals (raster alone
    and with the local reading blended in) are unit vectors around the wall's outward normal
    (towards the sensor, -y; their mean within 1 degree of it; each one the slope of a mean
    surface fitted to noisy points at the cell's or the 12 neighbours' scale: 4.6 and 7.6
    degrees off in the median), NaN exactly where no façade answers; the signed distance
    grows by the step taken along them."""
    xyz, origins, probe = wall
    fmap = build_map(xyz, None, origins)
    outward = np.array([0.0, -1.0, 0.0])
    for config in (QueryConfig(), QueryConfig(surface='raster')):
        got = fmap.query(probe, config)
        hit = got.facade >= 0
        assert hit.mean() > 0.8
        assert np.isnan(got.normal[~hit]).all() and np.isfinite(got.normal[hit]).all()
        np.testing.assert_allclose(np.linalg.norm(got.normal[hit], axis=1), 1.0, atol=1e-12)
        angle = np.degrees(np.arccos(np.clip(got.normal[hit] @ outward, -1.0, 1.0)))
        mean = got.normal[hit].mean(axis=0)
        assert np.degrees(np.arccos(mean @ outward / np.linalg.norm(mean))) < 1.0
        assert np.median(angle) < 10.0 and np.percentile(angle, 90) < 25.0, (config.surface, np.median(angle))
        # 1 cm along the normal moves the signed distance by about 1 cm
        moved = fmap.query(probe[hit] + 0.01 * got.normal[hit], config)
        same = moved.facade == got.facade[hit]
        change = moved.signed_distance[same] - got.signed_distance[hit][same]
        assert np.median(np.abs(change - 0.01)) < 1e-3
