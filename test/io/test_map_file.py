"""Map files: bit-for-bit round trip, version handling, damaged files, atomic saves."""

import json
import zipfile

import numpy as np
import pytest

from uncertain_facade_map.errors import InputError
from uncertain_facade_map.io.map_file import FORMAT, VERSION, load_map, save_map
from uncertain_facade_map.mapping.facade_map import build_map
from uncertain_facade_map.params import QueryConfig


@pytest.fixture(scope='module')
def fmap(scenes):
    cloud = scenes.campaign('small', 0)
    pts = cloud.points[(cloud.points['class'] == 1) & (cloud.points['building_id'] == 1)]
    return build_map(np.stack([pts['x'], pts['y'], pts['z']], 1), pts['building_id'], None,
                     map_origin=cloud.map_origin)


def arrays_of(path):
    with np.load(path, allow_pickle=False) as npz:
        return {k: npz[k] for k in npz.files}


def test_round_trip_is_bit_for_bit(tmp_path, fmap):
    first = save_map(fmap, tmp_path / 'a.npz')
    loaded = load_map(first)
    second = save_map(loaded, tmp_path / 'b.npz')
    a, b = arrays_of(first), arrays_of(second)
    assert a.keys() == b.keys()
    for key in a:
        assert a[key].dtype == b[key].dtype and a[key].tobytes() == b[key].tobytes(), key
    np.testing.assert_array_equal(loaded.map_origin, fmap.map_origin)
    xyz = np.random.default_rng(0).uniform(fmap.points[1].min(0) - 1, fmap.points[1].max(0) + 1, (20000, 3))
    raster = QueryConfig(surface='raster')
    before = fmap.query(xyz, raster, 0.1).as_dict()
    after = loaded.query(xyz, raster, 0.1).as_dict()
    for key in before:
        np.testing.assert_array_equal(before[key], after[key])
    # The per-point reading (query.surface: local) needs the stored points: the file has them.
    before = fmap.query(xyz, QueryConfig(), 0.1).as_dict()
    after = loaded.query(xyz, QueryConfig(), 0.1).as_dict()
    for key in before:
        np.testing.assert_array_equal(before[key], after[key])
    assert loaded.params == fmap.params


def rewrite_meta(src, dst, change):
    arrays = arrays_of(src)
    meta = json.loads(str(arrays['meta']))
    change(meta)
    arrays['meta'] = np.array(json.dumps(meta))
    np.savez(dst, **arrays)


def test_newer_version_is_refused_clearly(tmp_path, fmap):
    path = save_map(fmap, tmp_path / 'm.npz')
    rewrite_meta(path, tmp_path / 'new.npz', lambda m: m.update(version=VERSION + 1))
    with pytest.raises(InputError, match=f'version {VERSION + 1} was written by a newer'):
        load_map(tmp_path / 'new.npz')


@pytest.mark.parametrize('damage, words', [
    (lambda p: p.write_bytes(b'not a zip'), 'not an NPZ archive'),
    (lambda p: p.write_bytes(p.read_bytes()[:2000]), 'not a map file'),
    (lambda p: np.savez(p, x=np.zeros(3)), 'no meta record'),
])
def test_damaged_files(tmp_path, fmap, damage, words):
    path = save_map(fmap, tmp_path / 'm.npz')
    damage(path)
    with pytest.raises(InputError, match=words):
        load_map(path)


def test_other_format_and_missing_array(tmp_path, fmap):
    path = save_map(fmap, tmp_path / 'm.npz')
    rewrite_meta(path, tmp_path / 'other.npz', lambda m: m.update(format='something.else'))
    with pytest.raises(InputError, match=f'not an {FORMAT} file'):
        load_map(tmp_path / 'other.npz')
    arrays = arrays_of(path)
    arrays.pop('facade/0/surface_mean')
    np.savez(tmp_path / 'short.npz', **arrays)
    with pytest.raises(InputError, match='damaged map file'):
        load_map(tmp_path / 'short.npz')
    with pytest.raises(InputError, match='no such file'):
        load_map(tmp_path / 'missing.npz')


def test_the_same_map_saves_to_the_same_bytes(tmp_path, fmap):
    """Fixed zip timestamps: a tiled map's content hashes compare saves made at any time."""
    a, b = save_map(fmap, tmp_path / 'a.npz'), save_map(fmap, tmp_path / 'b.npz')
    assert a.read_bytes() == b.read_bytes()
    with zipfile.ZipFile(a) as zf:
        assert {i.date_time for i in zf.infolist()} == {(1980, 1, 1, 0, 0, 0)}


def test_save_is_atomic(tmp_path, fmap, monkeypatch):
    path = save_map(fmap, tmp_path / 'm.npz')
    good = path.read_bytes()

    def broken(*args, **kwargs):
        raise OSError('disk full')

    monkeypatch.setattr(np.lib.format, 'write_array', broken)
    with pytest.raises(OSError):
        save_map(fmap, path)
    assert path.read_bytes() == good, 'a failed save must leave the old map'
    assert [p.name for p in tmp_path.iterdir()] == ['m.npz'], 'no temporary file left behind'
    assert zipfile.is_zipfile(path)


def test_the_learnt_occupancy_is_saved_and_a_file_without_it_reads_the_fixed_formula(tmp_path, fmap):
    import dataclasses

    from uncertain_facade_map.pipeline.step8_occupancy import FIXED, PLSC

    learnt = dataclasses.replace(fmap.clone(), occupancy_=PLSC(2.1, 0.045, 3000, 2000), occupancy_stored_=1234)
    loaded = load_map(save_map(learnt, tmp_path / 'l.npz'))
    assert loaded.occupancy_ == learnt.occupancy_ and loaded.occupancy_stored_ == 1234
    rewrite_meta(tmp_path / 'l.npz', tmp_path / 'old.npz', lambda m: m.pop('occupancy'))
    old = load_map(tmp_path / 'old.npz')
    assert old.occupancy_ == FIXED and old.occupancy_stored_ == 0
