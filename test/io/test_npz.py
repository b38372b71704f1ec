"""Tests of uncertain_facade_map.io.npz: loss-free NPZ round trips, foreign archives and clean errors."""

from __future__ import annotations

import io
import zipfile
from pathlib import Path

import numpy as np
import pytest
from cloud_support import SETTINGS, TYPES, clouds, dtypes, one_line_error, xyz_points
from hypothesis import given
from hypothesis import strategies as st

from uncertain_facade_map.errors import InputError
from uncertain_facade_map.io.cloud import Cloud, simulated_dtype
from uncertain_facade_map.io.clouds import read_cloud, write_cloud
from uncertain_facade_map.io.npz import NPZ_FORMAT, read_npz, write_npz

# --------------------------------------------------------------------------------------
# strategies


@st.composite
def exotic_dtypes(draw: st.DrawFn) -> np.dtype:
    """Structured dtypes PLY cannot hold but NPZ must: padding, byte order, i8, sub-arrays."""
    base = draw(dtypes())
    fields = []
    for name in base.names:
        code = draw(st.sampled_from(TYPES + ['i8', 'u8', 'f2', '?']))
        order = draw(st.sampled_from(['<', '>'])) if code not in ('?', 'i1', 'u1') else '|'
        fields.append((name, np.dtype(order + code)))
    if draw(st.booleans()):
        fields.append(('rgb', np.dtype('u1'), (3,)))
    return np.dtype(fields, align=draw(st.booleans()))


# --------------------------------------------------------------------------------------
# round trips


@SETTINGS
@given(cloud=clouds())
def test_npz_round_trip_is_bit_exact(tmp_path: Path, cloud: Cloud) -> None:
    path = tmp_path / 'c.npz'
    write_cloud(path, cloud)
    back = read_cloud(path)
    assert back.same_as(cloud)
    assert back.fields == cloud.fields
    assert back.map_origin.tobytes() == cloud.map_origin.tobytes()


@SETTINGS
@given(cloud=clouds(exotic_dtypes()), compress=st.booleans())
def test_npz_round_trip_keeps_any_dtype(tmp_path: Path, cloud: Cloud, compress: bool) -> None:
    path = tmp_path / 'c.npz'
    write_npz(path, cloud, compress=compress)
    back = read_npz(path)
    assert back.points.dtype == cloud.points.dtype  # offsets, itemsize, byte order too
    for name in cloud.fields:  # every field bit for bit (padding bytes are no data)
        assert back.points[name].tobytes() == cloud.points[name].tobytes(), name
    assert back.points.tobytes() == read_npz(path).points.tobytes()  # padding is zeroed
    assert np.array_equal(back.map_origin, cloud.map_origin)


def test_npz_is_readable_without_pickle_and_has_documented_layout(tmp_path: Path) -> None:
    cloud = Cloud(xyz_points(), [1.0, 2.0, 3.0])
    write_npz(tmp_path / 'c.npz', cloud)
    with np.load(tmp_path / 'c.npz', allow_pickle=False) as archive:
        assert sorted(archive.files) == ['format', 'map_origin', 'points']
        assert str(archive['format']) == NPZ_FORMAT
        assert archive['map_origin'].tolist() == [1.0, 2.0, 3.0]


def test_npz_writes_exactly_the_given_path(tmp_path: Path) -> None:
    write_npz(tmp_path / 'cloud.data', Cloud(xyz_points()))
    assert (tmp_path / 'cloud.data').is_file()
    assert not (tmp_path / 'cloud.data.npz').exists()


# --------------------------------------------------------------------------------------
# foreign files


def test_foreign_npz_with_xyz_and_fields(tmp_path: Path) -> None:
    xyz = np.arange(12, dtype=np.float32).reshape(4, 3)
    intensity = np.array([1, 2, 3, 4], dtype=np.uint16)
    label = np.array([0, 1, 1, 0], dtype=np.uint8)
    np.savez(tmp_path / 'f.npz', xyz=xyz, intensity=intensity, label=label)
    cloud = read_cloud(tmp_path / 'f.npz')
    assert cloud.fields == ('x', 'y', 'z', 'intensity', 'label')
    assert cloud.points.dtype['x'] == np.float32
    assert np.array_equal(cloud.xyz, xyz)
    assert cloud.points['intensity'].tolist() == [1, 2, 3, 4]
    assert cloud.points['label'].dtype == np.uint8
    assert np.array_equal(cloud.map_origin, np.zeros(3))


def test_foreign_npz_with_points_array_and_origin(tmp_path: Path) -> None:
    xyz = np.random.default_rng(0).normal(size=(7, 3))
    np.savez(tmp_path / 'f.npz', points=xyz, map_origin=np.array([10.0, 20.0, 30.0]))
    cloud = read_npz(tmp_path / 'f.npz')
    assert cloud.fields == ('x', 'y', 'z')
    assert np.array_equal(cloud.xyz, xyz)
    assert cloud.map_origin.tolist() == [10.0, 20.0, 30.0]


def test_npz_with_plain_structured_points(tmp_path: Path) -> None:
    pts = xyz_points()
    np.savez(tmp_path / 'f.npz', points=pts)
    assert read_npz(tmp_path / 'f.npz').same_as(Cloud(pts))


@pytest.mark.parametrize('arrays, message', [
    ({'foo': np.zeros((3, 3))}, 'no "xyz" or "points" array'),
    ({}, 'no arrays'),
    ({'xyz': np.zeros((3, 3)), 'points': np.zeros((3, 3))}, 'both'),
    ({'xyz': np.zeros((3, 2))}, '(N, 3) float'),
    ({'xyz': np.zeros((3, 3), dtype=np.int32)}, '(N, 3) float'),
    ({'xyz': np.zeros((3, 3)), 'normals': np.zeros((3, 3))}, '"normals" (3, 3)'),
    ({'xyz': np.zeros((3, 3)), 'i': np.zeros(4)}, '"i" (4,)'),
    ({'xyz': np.zeros((3, 3)), 'x': np.zeros(3)}, '"x"'),
    ({'xyz': np.zeros((3, 3)), 'name': np.array(['a', 'b', 'c'])}, '"name"'),
    ({'xyz': np.zeros((3, 3)), 'map_origin': np.zeros(2)}, 'map_origin'),
    ({'format': np.array('uncertain_facade_map.io.cloud/99'), 'points': xyz_points()}, 'unsupported format'),
    ({'format': np.array(NPZ_FORMAT), 'xyz': np.zeros((3, 3))}, 'no structured "points"'),
    ({'points': xyz_points(), 'other': np.zeros(4)}, 'unexpected arrays other'),
    ({'points': np.zeros(4, dtype=[('a', 'f4')])}, 'no field x, y, z'),
])
def test_npz_that_is_no_cloud_is_refused(tmp_path: Path, arrays: dict, message: str) -> None:
    np.savez(tmp_path / 'f.npz', **arrays)
    with pytest.raises(InputError, match='^[^\n]*$') as err:
        read_npz(tmp_path / 'f.npz')
    assert message in str(err.value)


# --------------------------------------------------------------------------------------
# errors


def test_truncated_and_corrupt_npz(tmp_path: Path) -> None:
    pts = np.zeros(200, dtype=simulated_dtype())
    write_npz(tmp_path / 'c.npz', Cloud(pts))
    data = (tmp_path / 'c.npz').read_bytes()
    for cut in (0, 2, 30, len(data) // 2, len(data) - 30):
        (tmp_path / 't.npz').write_bytes(data[:cut])
        assert 'cannot read NPZ file' in one_line_error(read_cloud, tmp_path / 't.npz'), cut
    (tmp_path / 'g.npz').write_bytes(b'this is not a zip archive at all\n' * 10)
    assert 'cannot read NPZ file' in one_line_error(read_cloud, tmp_path / 'g.npz')


def test_corrupt_compressed_npz(tmp_path: Path) -> None:
    rng = np.random.default_rng(3)
    pts = np.zeros(500, dtype=simulated_dtype())
    pts['x'] = rng.integers(0, 3, 500)
    write_npz(tmp_path / 'c.npz', Cloud(pts), compress=True)
    data = bytearray((tmp_path / 'c.npz').read_bytes())
    with zipfile.ZipFile(io.BytesIO(bytes(data))) as archive:
        info = archive.getinfo('points.npy')
    start = info.header_offset + 30 + len(info.filename) + len(info.extra) + 10
    data[start:start + 40] = bytes(40)
    (tmp_path / 'x.npz').write_bytes(bytes(data))
    assert 'cannot read NPZ file' in one_line_error(read_npz, tmp_path / 'x.npz')


def test_pickled_npz_is_refused(tmp_path: Path) -> None:
    np.savez(tmp_path / 'p.npz', xyz=np.array([{'a': 1}], dtype=object))
    assert 'cannot read NPZ file' in one_line_error(read_npz, tmp_path / 'p.npz')
    obj = np.zeros(2, dtype=[('x', 'f8'), ('y', 'f8'), ('z', 'f8'), ('o', 'O')])
    assert 'object' in one_line_error(write_npz, tmp_path / 'o.npz', Cloud(obj))


def test_npy_file_is_refused(tmp_path: Path) -> None:
    with open(tmp_path / 'a.npz', 'wb') as stream:
        np.save(stream, np.zeros((3, 3)))
    assert 'not an NPZ archive' in one_line_error(read_npz, tmp_path / 'a.npz')
