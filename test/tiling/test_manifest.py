"""The manifest of a tiled map: round trip (hypothesis), atomic writes, one-line refusals of
missing, damaged, foreign and newer manifests, tiles written and checked by hash. About 4 s."""

import json
import os

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from uncertain_facade_map.errors import InputError
from uncertain_facade_map.io.map_file import load_map
from uncertain_facade_map.mapping.facade_map import build_map
from uncertain_facade_map.params import MapParams, map_params_record
from uncertain_facade_map.pipeline.step7_local_surface import ReadingCalibration
from uncertain_facade_map.tiling.grid import TileGrid, tile_id
from uncertain_facade_map.tiling.manifest import (
    FORMAT,
    MANIFEST,
    VERSION,
    Manifest,
    TileRecord,
    is_tiled_map,
    map_extent,
    read_manifest,
    save_tile,
    verify_tile,
    write_manifest,
)

finite = st.floats(-1e7, 1e7, allow_nan=False, allow_infinity=False)
hexes = st.text('0123456789abcdef', min_size=64, max_size=64)


@st.composite
def records(draw):
    ix, iy = draw(st.integers(-10**6, 10**6)), draw(st.integers(-10**6, 10**6))
    tid = tile_id(ix, iy)
    return TileRecord(id=tid, index=(ix, iy), bounds=tuple(draw(st.lists(finite, min_size=4, max_size=4))),
                      extent=tuple(draw(st.lists(finite, min_size=6, max_size=6))), file=f'tiles/{tid}.npz',
                      sha256=draw(hexes), buildings=draw(st.lists(st.integers(-2**40, 2**40), max_size=5)),
                      facades=draw(st.integers(0, 10**6)), points=draw(st.integers(0, 10**12)),
                      inputs=draw(st.text(max_size=70)))


@st.composite
def manifests(draw):
    recs = draw(st.lists(records(), max_size=6, unique_by=lambda r: r.id))
    tiles = {r.id: r for r in recs}
    labels = draw(st.lists(st.integers(-2**40, 2**40), max_size=8, unique=True)) if tiles else []
    ids = sorted(tiles)
    building_tiles = {b: ids[draw(st.integers(0, len(ids) - 1))] for b in labels}
    occupancy = draw(st.one_of(st.none(), st.fixed_dictionaries({'scale': st.floats(0.05, 20.0),
                                                                  'spread': st.floats(0.0, 2.0),
                                                                  'n_positive': st.integers(0, 10**6),
                                                                  'n_negative': st.integers(0, 10**6)})))
    calibration = draw(st.dictionaries(st.text(min_size=1, max_size=20),
                                       st.builds(ReadingCalibration, st.floats(0.01, 100.0), st.floats(0.0, 4.0),
                                                 st.floats(0.0, 2.0), st.floats(0.0, 2.0)), max_size=3))
    registration = draw(st.one_of(st.none(), st.fixed_dictionaries({'var': st.floats(0.0, 1.0),
                                                                     'sums': st.lists(finite, min_size=3, max_size=3)})))
    return Manifest(side=draw(st.floats(0.1, 1e5)), map_origin=tuple(draw(st.lists(finite, min_size=3, max_size=3))),
                    params=map_params_record(MapParams()), tiles=tiles, occupancy=occupancy,
                    building_tiles=building_tiles, local_calibration=calibration, registration=registration)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(manifests())
def test_round_trip(tmp_path, manifest):
    path = write_manifest(tmp_path, manifest)
    assert path == tmp_path / MANIFEST and is_tiled_map(tmp_path) and is_tiled_map(path)
    for where in (tmp_path, path, str(path)):
        assert read_manifest(where) == manifest
    assert [p.name for p in tmp_path.iterdir()] == [MANIFEST]  # no temporary left


def test_write_is_atomic_and_replaces(tmp_path, monkeypatch):
    m = Manifest(side=50.0, map_origin=(1.0, 2.0, 3.0), params={}, tiles={})
    write_manifest(tmp_path, m)
    before = (tmp_path / MANIFEST).read_text()

    def fail(*args):
        raise OSError('disk full')

    monkeypatch.setattr(os, 'replace', fail)
    with pytest.raises(OSError, match='disk full'):
        write_manifest(tmp_path, Manifest(side=20.0, map_origin=(0.0, 0.0, 0.0), params={}, tiles={}))
    assert (tmp_path / MANIFEST).read_text() == before  # the old one stands
    assert [p.name for p in tmp_path.iterdir()] == [MANIFEST]  # the temporary removed


def good_doc():
    rec = TileRecord('tile_0_m1', (0, -1), (0.0, -50.0, 50.0, 0.0), (0.0,) * 6, 'tiles/tile_0_m1.npz', 'a' * 64,
                     [3], 2, 10, 'b' * 64)
    return Manifest(50.0, (0.0, 0.0, 0.0), {}, {rec.id: rec}, building_tiles={3: rec.id}).as_dict()


def write_doc(tmp_path, doc):
    (tmp_path / MANIFEST).write_text(doc if isinstance(doc, str) else json.dumps(doc))
    return tmp_path


def edit(change):
    doc = good_doc()
    change(doc)
    return doc


@pytest.mark.parametrize('doc, message', [
    ('{"format": ', 'damaged manifest \\(not JSON'),
    ('[]', 'not an uncertain_facade_map.tiles manifest'),
    (edit(lambda d: d.update(format='uncertain_facade_map.map')), 'not an uncertain_facade_map.tiles manifest'),
    (edit(lambda d: d.update(version=VERSION + 1)), 'version 2 was written by a newer'),
    (edit(lambda d: d.update(version='1')), "damaged manifest \\(version '1'\\)"),
    (edit(lambda d: d.pop('side')), "missing field 'side'"),
    (edit(lambda d: d.update(side=-1)), 'side must be'),
    (edit(lambda d: d['tiles'][0].pop('sha256')), "missing field 'sha256'"),
    (edit(lambda d: d['tiles'][0].update(sha256='xyz')), 'sha256 must be 64'),
    (edit(lambda d: d['tiles'][0].update(file='../../etc/passwd')), 'inside the map folder'),
    (edit(lambda d: d['tiles'][0].update(file='/tmp/x.npz')), 'inside the map folder'),
    (edit(lambda d: d['tiles'][0].update(id='tile_0_1')), 'does not match its index'),
    (edit(lambda d: d['tiles'][0].update(extent=[0, 0, 0])), 'extent must be a list of 6'),
    (edit(lambda d: d['tiles'].append(d['tiles'][0])), 'listed twice'),
    (edit(lambda d: d.update(building_tiles={'3': 'tile_9_9'})), 'not listed'),
    (edit(lambda d: d.update(map_origin=[0, 0, None])), 'damaged manifest'),
    (edit(lambda d: d.update(registration={'var': 0.1})), "missing field 'sums'"),
    (edit(lambda d: d.update(local_calibration={'local': 'x'})), 'a calibration is a number or an object'),
    (edit(lambda d: d.update(local_calibration={'local': {'scale': 1.0, 'slope': 2.0}})), 'unknown calibration'),
    (edit(lambda d: d.update(local_calibration={'local': {'scale': float('nan')}})), 'must be finite'),
])
def test_bad_manifests_are_refused_in_one_line(tmp_path, doc, message):
    write_doc(tmp_path, doc)
    with pytest.raises(InputError, match=message) as err:
        read_manifest(tmp_path)
    assert '\n' not in str(err.value) and str(tmp_path) in str(err.value)


def test_good_doc_reads(tmp_path):
    m = read_manifest(write_doc(tmp_path, good_doc()))
    assert m.tiles['tile_0_m1'].index == (0, -1) and m.building_tiles == {3: 'tile_0_m1'}


def test_a_calibration_written_before_the_gap_reads_as_its_scale(tmp_path):
    doc = edit(lambda d: d.update(local_calibration={'local:12:0.5:0.2': 1.25}))
    m = read_manifest(write_doc(tmp_path, doc))
    assert m.local_calibration == {'local:12:0.5:0.2': ReadingCalibration(1.25)}


def test_missing_manifests(tmp_path):
    with pytest.raises(InputError, match='not a tiled map \\(no manifest.json in the folder\\)'):
        read_manifest(tmp_path)
    with pytest.raises(InputError, match='no such tiled map'):
        read_manifest(tmp_path / 'nowhere')
    assert not is_tiled_map(tmp_path) and not is_tiled_map(tmp_path / 'nowhere')


@pytest.fixture(scope='module')
def small_map(scenes):
    cloud = scenes.campaign('small', 0)
    pts = cloud.points[(cloud.points['class'] == 1) & (cloud.points['building_id'] == 1)]
    return build_map(np.stack([pts['x'], pts['y'], pts['z']], 1), pts['building_id'], None,
                     map_origin=cloud.map_origin)


def test_save_tile_writes_a_map_file_and_its_record(tmp_path, small_map):
    grid = TileGrid(50.0)
    ix, iy = (int(i) for i in grid.index(small_map.points[1].mean(0)[None])[0])
    tid = tile_id(ix, iy)
    rec = save_tile(tmp_path, tid, (ix, iy), grid.bounds(ix, iy), small_map, 'c' * 64)
    assert rec.file == f'tiles/{tid}.npz' and rec.buildings == [1] and rec.facades == len(small_map.facades)
    assert rec.points == small_map.n_stored and rec.bounds == grid.bounds(ix, iy)
    lo, hi = np.array(rec.extent[:3]), np.array(rec.extent[3:])
    pts = small_map.points[1]
    assert (pts >= lo).all() and (pts <= hi).all() and rec.extent == map_extent(small_map)
    path = verify_tile(tmp_path, rec)
    assert load_map(path).n_stored == small_map.n_stored
    assert not (tmp_path / MANIFEST).exists()  # save_tile leaves the manifest to its caller
    # A damaged or missing tile is refused by its hash.
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0xFF
    path.write_bytes(bytes(data))
    with pytest.raises(InputError, match='does not match the manifest'):
        verify_tile(tmp_path, rec)
    path.unlink()
    with pytest.raises(InputError, match='missing'):
        verify_tile(tmp_path, rec)
    with pytest.raises(InputError, match='does not match its index'):
        save_tile(tmp_path, 'tile_0_0', (1, 0), grid.bounds(1, 0), small_map, '')


def test_format_constant():
    assert FORMAT == 'uncertain_facade_map.tiles' and MANIFEST == 'manifest.json' and VERSION == 1
