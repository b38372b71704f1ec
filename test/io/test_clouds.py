"""Tests of uncertain_facade_map.io.clouds: loss-free PLY/NPZ round trips and clean errors."""

from __future__ import annotations

import io
import struct
import zipfile
from pathlib import Path

import hypothesis.extra.numpy as hnp
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from plyfile import PlyData, PlyElement

from uncertain_facade_map.errors import InputError
from uncertain_facade_map.io.cloud import Cloud, simulated_dtype
from uncertain_facade_map.io.clouds import (
    LAS_SCALE,
    NPZ_FORMAT,
    PCD_ENCODINGS,
    PLY_TYPES,
    read_cloud,
    read_las,
    read_npz,
    read_pcd,
    read_ply,
    write_cloud,
    write_las,
    write_npz,
    write_pcd,
    write_ply,
)

SETTINGS = settings(max_examples=40, deadline=None,
                    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])

TYPES = list(PLY_TYPES)  # i1 u1 i2 u2 i4 u4 f4 f8
EXTRA_NAMES = ['class', 'intensity', 'time', 'building_id', 'gt_facade', 'ring', 'r', 'g', 'b',
               'origin_x', 'return_number', 'a_1', 'Z2']


# --------------------------------------------------------------------------------------
# strategies


@st.composite
def dtypes(draw: st.DrawFn) -> np.dtype:
    """Packed structured dtypes: x, y, z plus 1..8 other fields, random types and order."""
    extra = draw(st.lists(st.sampled_from(EXTRA_NAMES), min_size=1, max_size=8, unique=True))
    names = draw(st.permutations(['x', 'y', 'z'] + extra))
    return np.dtype([(n, draw(st.sampled_from(TYPES))) for n in names])


@st.composite
def clouds(draw: st.DrawFn, dtype_strategy: st.SearchStrategy[np.dtype] | None = None) -> Cloud:
    """Clouds of 0..100 points whose values include NaN, +-inf, -0.0, subnormals, extremes."""
    dtype = draw(dtype_strategy if dtype_strategy is not None else dtypes())
    n = draw(st.integers(0, 100))
    points = np.zeros(n, dtype=dtype)  # zeroed so that padding bytes are defined
    for name in dtype.names:
        ftype = dtype.fields[name][0]
        points[name] = draw(hnp.arrays(ftype.base, (n,) + ftype.shape))
    origin = draw(st.lists(st.floats(allow_nan=False, allow_infinity=False, width=64),
                           min_size=3, max_size=3))
    return Cloud(points, np.array(origin))


@st.composite
def raw_clouds(draw: st.DrawFn) -> Cloud:
    """Clouds whose bytes are arbitrary (every NaN payload and sign bit)."""
    dtype = draw(dtypes())
    n = draw(st.integers(0, 30))
    raw = draw(st.binary(min_size=n * dtype.itemsize, max_size=n * dtype.itemsize))
    return Cloud(np.frombuffer(raw, dtype=dtype).copy(), np.array([1.5, -2.25, 1e7]))


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
# helpers


def bits_equal(a: np.ndarray, b: np.ndarray) -> bool:
    """Field-by-field, bit-for-bit equality of two structured arrays (padding ignored)."""
    if a.dtype.names != b.dtype.names or a.shape != b.shape:
        return False
    for name in a.dtype.names:
        fa, fb = a[name], b[name]
        if fa.dtype.newbyteorder('=') != fb.dtype.newbyteorder('='):
            return False
        native = fa.dtype.newbyteorder('=')
        if fa.astype(native).tobytes() != fb.astype(native).tobytes():
            return False
    return True


def values_equal_nan_canonical(a: np.ndarray, b: np.ndarray) -> bool:
    """Bit equality except that any NaN equals any NaN (ASCII PLY drops NaN sign/payload)."""
    if a.dtype != b.dtype:
        return False
    for name in a.dtype.names:
        fa, fb = a[name], b[name]
        if fa.dtype.kind == 'f':
            nan_a, nan_b = np.isnan(fa), np.isnan(fb)
            if not np.array_equal(nan_a, nan_b):
                return False
            if fa[~nan_a].tobytes() != fb[~nan_b].tobytes():
                return False
        elif fa.tobytes() != fb.tobytes():
            return False
    return True


def write_plyfile(path: Path, elements: list[PlyElement], **kwargs: object) -> None:
    """Write a PLY with plyfile directly, as a foreign tool would."""
    PlyData(elements, **kwargs).write(str(path))


def xyz_points(n: int = 4, dtype: str = 'f4') -> np.ndarray:
    """A small plain (x, y, z) structured array."""
    pts = np.zeros(n, dtype=[('x', dtype), ('y', dtype), ('z', dtype)])
    pts['x'] = np.arange(n) + 0.5
    pts['y'] = -np.arange(n) * 0.25
    pts['z'] = 1e-3
    return pts


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


@SETTINGS
@given(cloud=clouds())
def test_binary_ply_round_trip_is_bit_exact(tmp_path: Path, cloud: Cloud) -> None:
    path = tmp_path / 'c.ply'
    write_cloud(path, cloud)
    back = read_cloud(path)
    assert back.same_as(cloud)
    assert back.map_origin.tobytes() == cloud.map_origin.tobytes()


@settings(SETTINGS, max_examples=30)
@given(cloud=raw_clouds())
def test_binary_formats_keep_every_bit_pattern(tmp_path: Path, cloud: Cloud) -> None:
    for name in ('c.ply', 'c.npz'):
        write_cloud(tmp_path / name, cloud)
        assert read_cloud(tmp_path / name).same_as(cloud), name


@settings(SETTINGS, max_examples=30)
@given(cloud=clouds())
def test_ascii_ply_round_trip_is_exact_up_to_nan_payloads(tmp_path: Path, cloud: Cloud) -> None:
    path = tmp_path / 'c.ply'
    write_ply(path, cloud, binary=False)
    assert path.read_bytes().startswith(b'ply\nformat ascii 1.0\n')
    back = read_ply(path)
    assert values_equal_nan_canonical(back.points, cloud.points)
    assert back.map_origin.tobytes() == cloud.map_origin.tobytes()


def test_ascii_ply_keeps_special_floats(tmp_path: Path) -> None:
    pts = np.zeros(6, dtype=[('x', 'f8'), ('y', 'f4'), ('z', 'f8'), ('class', 'u1')])
    special = [np.nan, -0.0, np.inf, -np.inf, 5e-324, np.finfo(np.float64).max]
    pts['x'] = special
    pts['y'] = [np.nan, -0.0, np.inf, -np.inf, 1e-45, np.finfo(np.float32).max]
    pts['z'] = 0.1
    pts['class'] = [0, 1, 2, 3, 254, 255]
    cloud = Cloud(pts, [2683000.123, 1247000.456, 408.789])
    write_ply(tmp_path / 'c.ply', cloud, binary=False)
    back = read_ply(tmp_path / 'c.ply')
    assert values_equal_nan_canonical(back.points, pts)
    assert np.signbit(back.points['x'][1]) and np.signbit(back.points['y'][1])
    assert np.array_equal(back.map_origin, cloud.map_origin)


def test_simulated_cloud_round_trips_through_every_format(tmp_path: Path) -> None:
    pts = np.zeros(50, dtype=simulated_dtype('f4'))
    rng = np.random.default_rng(1)
    for name in pts.dtype.names:
        pts[name] = rng.integers(0, 5, 50)
    pts['x'] = rng.normal(size=50)
    cloud = Cloud(pts, [2683000.0, 1247000.0, 400.0])
    for name in ('a.ply', 'a.npz', 'A.PLY', 'A.NPZ'):
        write_cloud(tmp_path / name, cloud)
        assert read_cloud(tmp_path / name).same_as(cloud)


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


def test_ply_header_has_types_and_origin_comment(tmp_path: Path) -> None:
    pts = np.zeros(2, dtype=[('x', 'f8'), ('y', 'f8'), ('z', 'f8'), ('class', 'u1'), ('t', 'i2')])
    write_ply(tmp_path / 'c.ply', Cloud(pts, [2683000.1, 0.3, -0.0]))
    header = (tmp_path / 'c.ply').read_bytes().split(b'end_header')[0].decode()
    assert 'format binary_little_endian 1.0' in header
    assert 'comment map_origin 2683000.1 0.3 -0.0' in header
    assert 'property uchar class' in header and 'property short t' in header
    assert 'property double x' in header


def test_bool_fields_become_uchar(tmp_path: Path) -> None:
    pts = np.zeros(3, dtype=[('x', 'f4'), ('y', 'f4'), ('z', 'f4'), ('flag', '?')])
    pts['flag'] = [True, False, True]
    write_ply(tmp_path / 'c.ply', Cloud(pts))
    back = read_ply(tmp_path / 'c.ply')
    assert back.points.dtype['flag'] == np.dtype('u1')
    assert back.points['flag'].tolist() == [1, 0, 1]


def test_non_native_byte_order_is_written_and_read_native(tmp_path: Path) -> None:
    pts = np.zeros(3, dtype=[('x', '>f8'), ('y', '>f4'), ('z', '<f8'), ('n', '>u4')])
    pts['x'] = [1.5, -2.0, np.pi]
    pts['n'] = [1, 2**32 - 1, 7]
    write_ply(tmp_path / 'c.ply', Cloud(pts))
    back = read_ply(tmp_path / 'c.ply')
    assert all(back.points.dtype[n].isnative for n in back.fields)
    assert bits_equal(back.points, pts)


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


def test_big_endian_ply_from_plyfile(tmp_path: Path) -> None:
    pts = np.zeros(5, dtype=[('x', '>f8'), ('y', '>f8'), ('z', '>f4'), ('class', 'u1'), ('i', '>i4')])
    pts['x'] = np.linspace(-1, 1, 5)
    pts['y'] = [np.nan, -0.0, np.inf, 1e300, -7]
    pts['z'] = 3.25
    pts['class'] = [0, 1, 2, 3, 4]
    pts['i'] = [-2**31, 2**31 - 1, 0, -1, 5]
    write_plyfile(tmp_path / 'be.ply', [PlyElement.describe(pts, 'vertex')], byte_order='>',
                  comments=['map_origin 1.0 2.0 3.0'])
    assert b'binary_big_endian' in (tmp_path / 'be.ply').read_bytes()[:40]
    cloud = read_cloud(tmp_path / 'be.ply')
    assert all(cloud.points.dtype[n].isnative for n in cloud.fields)
    assert bits_equal(cloud.points, pts)
    assert cloud.map_origin.tolist() == [1.0, 2.0, 3.0]


@pytest.mark.parametrize('text', [False, True])
def test_ply_with_faces_and_other_elements(tmp_path: Path, text: bool) -> None:
    pts = np.zeros(4, dtype=[('x', 'f4'), ('y', 'f4'), ('z', 'f4'), ('red', 'u1')])
    pts['x'] = [0, 1, 0, 1]
    pts['y'] = [0, 0, 1, 1]
    pts['red'] = [10, 20, 30, 40]
    faces = np.array([([0, 1, 2],), ([1, 3, 2],)], dtype=[('vertex_indices', 'O')])
    faces['vertex_indices'] = [np.array([0, 1, 2], 'i4'), np.array([1, 3, 2], 'i4')]
    edges = np.array([(0, 1), (1, 3)], dtype=[('vertex1', 'i4'), ('vertex2', 'i4')])
    write_plyfile(tmp_path / 'm.ply', [
        PlyElement.describe(faces, 'face'),  # before the vertices, on purpose
        PlyElement.describe(pts, 'vertex'),
        PlyElement.describe(edges, 'edge'),
    ], text=text, comments=['made by another tool'])
    cloud = read_ply(tmp_path / 'm.ply')
    assert cloud.same_as(Cloud(pts))


def test_ply_vertex_list_properties_are_ignored(tmp_path: Path) -> None:
    (tmp_path / 'l.ply').write_bytes(
        b'ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty list uchar int ids\n'
        b'property float y\nproperty float z\nend_header\n1 2 7 8 2 3\n4 1 9 5 6\n')
    cloud = read_ply(tmp_path / 'l.ply')
    assert cloud.fields == ('x', 'y', 'z')
    assert cloud.xyz.tolist() == [[1, 2, 3], [4, 5, 6]]


def test_ply_with_crlf_header_and_other_comments(tmp_path: Path) -> None:
    (tmp_path / 'w.ply').write_bytes(
        b'ply\r\nformat ascii 1.0\r\ncomment exported\r\nelement vertex 1\r\n'
        b'property double x\r\ncomment map_origin 5 6 7\r\nproperty double y\r\nproperty double z\r\n'
        b'end_header\r\n1.25 2.5 3.75\r\n')
    cloud = read_ply(tmp_path / 'w.ply')
    assert cloud.xyz.tolist() == [[1.25, 2.5, 3.75]]
    assert cloud.map_origin.tolist() == [5.0, 6.0, 7.0]


def test_empty_cloud(tmp_path: Path) -> None:
    cloud = Cloud(xyz_points(0))
    for name in ('e.ply', 'e.npz'):
        write_cloud(tmp_path / name, cloud)
        assert read_cloud(tmp_path / name).same_as(cloud)
    write_ply(tmp_path / 'e.ply', cloud, binary=False)
    assert read_cloud(tmp_path / 'e.ply').same_as(cloud)


# --------------------------------------------------------------------------------------
# errors


def one_line_error(func, *args, **kwargs) -> str:
    """Call ``func``, expect an InputError with a one-line message, return the message."""
    with pytest.raises(InputError) as err:
        func(*args, **kwargs)
    message = str(err.value)
    assert message and '\n' not in message and 'Traceback' not in message
    return message


@pytest.mark.parametrize('reader', [read_cloud, read_ply, read_npz])
@pytest.mark.parametrize('name', ['missing.ply', 'missing.npz'])
def test_missing_file(tmp_path: Path, reader, name: str) -> None:
    assert one_line_error(reader, tmp_path / name).startswith('no such file: ')


def test_directory_is_not_a_file(tmp_path: Path) -> None:
    (tmp_path / 'd.ply').mkdir()
    assert 'not a file' in one_line_error(read_cloud, tmp_path / 'd.ply')


@pytest.mark.parametrize('name', ['c.xyz', 'c', 'c.ply.gz', 'c.txt', 'c.las.gz'])
def test_unknown_suffix(tmp_path: Path, name: str) -> None:
    (tmp_path / name).write_bytes(b'x')
    for message in (one_line_error(read_cloud, tmp_path / name),
                    one_line_error(write_cloud, tmp_path / name, Cloud(xyz_points()))):
        assert 'unsupported file type' in message and '.npz' in message and '.ply' in message
        assert '.las' in message and '.laz' in message and '.pcd' in message


@pytest.mark.parametrize('binary', [True, False])
def test_truncated_ply(tmp_path: Path, binary: bool) -> None:
    pts = np.zeros(20, dtype=simulated_dtype())
    write_ply(tmp_path / 'c.ply', Cloud(pts), binary=binary)
    data = (tmp_path / 'c.ply').read_bytes()
    header_end = data.index(b'end_header')
    for cut in (0, 3, 10, header_end, header_end + 11, len(data) // 2, len(data) - 5):
        (tmp_path / 't.ply').write_bytes(data[:cut])
        assert 'cannot read PLY file' in one_line_error(read_cloud, tmp_path / 't.ply'), cut


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


def test_ply_without_vertex_element(tmp_path: Path) -> None:
    faces = np.zeros(2, dtype=[('a', 'i4'), ('b', 'i4')])
    write_plyfile(tmp_path / 'f.ply', [PlyElement.describe(faces, 'face')])
    assert 'no vertex element (elements: face)' in one_line_error(read_cloud, tmp_path / 'f.ply')


def test_ply_vertex_without_z(tmp_path: Path) -> None:
    pts = np.zeros(2, dtype=[('x', 'f4'), ('y', 'f4'), ('intensity', 'u2')])
    write_plyfile(tmp_path / 'v.ply', [PlyElement.describe(pts, 'vertex')])
    assert 'vertex element has no z' in one_line_error(read_ply, tmp_path / 'v.ply')


@pytest.mark.parametrize('comment', ['map_origin 1 2', 'map_origin a b c', 'map_origin 1 2 nan'])
def test_malformed_origin_comment(tmp_path: Path, comment: str) -> None:
    write_plyfile(tmp_path / 'o.ply', [PlyElement.describe(xyz_points(), 'vertex')], comments=[comment])
    assert 'map_origin' in one_line_error(read_ply, tmp_path / 'o.ply')


@pytest.mark.parametrize('body', [
    b'ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\n'
    b'end_header\n1 2 abc\n',
    b'ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty uchar z\n'
    b'end_header\n1 2 300\n',
    b'ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\n'
    b'end_header\n1 2\n',
    b'ply\nformat ascii 1.0\nelement vertex 1\nproperty float128 x\nend_header\n1\n',
    b'ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float x\nend_header\n1 2\n',
    b'ply\nformat binary_middle_endian 1.0\nelement vertex 0\nproperty float x\nend_header\n',
    b'ply\nformat ascii 1.0\nelement vertex many\nend_header\n',
    b'ply\nformat ascii 1.0\ncomment \xff\xfe\nelement vertex 0\nend_header\n',
    b'ply\nformat ascii 1.0\nelement vertex 100000000000\nproperty float x\nend_header\n1\n',
    b'ply\nformat ascii 1.0\nelement vertex -5\nproperty float x\nend_header\n1\n',
    b'PK\x03\x04 this is a zip',
    b'',
])
def test_malformed_ply(tmp_path: Path, body: bytes) -> None:
    (tmp_path / 'm.ply').write_bytes(body)
    assert 'cannot read PLY file' in one_line_error(read_ply, tmp_path / 'm.ply')


@settings(SETTINGS, max_examples=60)
@given(data=st.data())
def test_damaged_files_raise_only_input_errors(tmp_path: Path, data: st.DataObject) -> None:
    """Random truncation and byte damage: a cloud or an InputError, never anything else."""
    suffix = data.draw(st.sampled_from(['.ply', '.ply-ascii', '.npz', '.npz-z']))
    pts = np.zeros(8, dtype=simulated_dtype('f4'))
    cloud = Cloud(pts, [1.0, 2.0, 3.0])
    path = tmp_path / ('d' + suffix[:4])
    if suffix == '.ply-ascii':
        write_ply(path, cloud, binary=False)
    elif suffix == '.npz-z':
        write_npz(path, cloud, compress=True)
    else:
        write_cloud(path, cloud)
    raw = bytearray(path.read_bytes())
    cut = data.draw(st.integers(0, len(raw)))
    raw = raw[:cut]
    for _ in range(data.draw(st.integers(0, 4))):
        if raw:
            raw[data.draw(st.integers(0, len(raw) - 1))] = data.draw(st.integers(0, 255))
    path.write_bytes(bytes(raw))
    try:
        back = read_cloud(path)
    except InputError as err:
        assert '\n' not in str(err)
    else:
        assert isinstance(back, Cloud)


@pytest.mark.parametrize('dtype, message', [
    ([('x', 'f8'), ('y', 'f8'), ('z', 'f8'), ('id', 'i8')], "'id' has type int64"),
    ([('x', 'f8'), ('y', 'f8'), ('z', 'f8'), ('n', 'u8')], "'n' has type uint64"),
    ([('x', 'f2'), ('y', 'f8'), ('z', 'f8')], "'x' has type float16"),
    ([('x', 'f8'), ('y', 'f8'), ('z', 'f8'), ('rgb', 'u1', (3,))], "'rgb'"),
    ([('x', 'f8'), ('y', 'f8'), ('z', 'f8'), ('s', 'U3')], "'s'"),
    ([('x', 'f8'), ('y', 'f8'), ('z', 'f8'), ('a b', 'f4')], "'a b' cannot be a PLY property name"),
    ([('x', 'f8'), ('y', 'f8'), ('z', 'f8'), ('é', 'f4')], 'cannot be a PLY property name'),
])
def test_ply_refuses_unsupported_fields(tmp_path: Path, dtype: list, message: str) -> None:
    cloud = Cloud(np.zeros(2, dtype=dtype))
    assert message in one_line_error(write_ply, tmp_path / 'u.ply', cloud)
    assert not (tmp_path / 'u.ply').exists()


def test_unwritable_path(tmp_path: Path) -> None:
    cloud = Cloud(xyz_points())
    for name in ('no/such/dir/c.ply', 'no/such/dir/c.npz'):
        assert 'cannot write' in one_line_error(write_cloud, tmp_path / name, cloud)


# --------------------------------------------------------------------------------------
# PCD


@SETTINGS
@given(cloud=clouds(), encoding=st.sampled_from(['binary', 'binary_compressed']))
def test_binary_pcd_round_trip_is_bit_exact(tmp_path: Path, cloud: Cloud, encoding: str) -> None:
    path = tmp_path / 'c.pcd'
    write_pcd(path, cloud, encoding=encoding)
    assert f'\nDATA {encoding}\n'.encode() in path.read_bytes()
    back = read_pcd(path)
    assert back.same_as(cloud)
    assert back.fields == cloud.fields
    assert back.map_origin.tobytes() == cloud.map_origin.tobytes()


@settings(SETTINGS, max_examples=30)
@given(cloud=raw_clouds(), encoding=st.sampled_from(['binary', 'binary_compressed']))
def test_binary_pcd_keeps_every_bit_pattern(tmp_path: Path, cloud: Cloud, encoding: str) -> None:
    write_pcd(tmp_path / 'c.pcd', cloud, encoding=encoding)
    assert read_pcd(tmp_path / 'c.pcd').same_as(cloud)


@SETTINGS
@given(cloud=clouds())
def test_ascii_pcd_round_trip_is_exact_up_to_nan_payloads(tmp_path: Path, cloud: Cloud) -> None:
    path = tmp_path / 'c.pcd'
    write_pcd(path, cloud, encoding='ascii')
    assert b'\nDATA ascii\n' in path.read_bytes()
    back = read_pcd(path)
    assert values_equal_nan_canonical(back.points, cloud.points)  # every other bit exact
    assert back.map_origin.tobytes() == cloud.map_origin.tobytes()


@pytest.mark.parametrize('encoding', PCD_ENCODINGS)
def test_pcd_special_values_integers_and_byte_order(tmp_path: Path, encoding: str) -> None:
    pts = np.zeros(6, dtype=[('x', '>f8'), ('y', 'f4'), ('z', 'f8'), ('i', '>i8'), ('u', 'u8'),
                             ('flag', '?'), ('s', '>i2')])
    pts['x'] = [-0.0, np.inf, -np.inf, 5e-324, np.finfo(np.float64).max, 0.1]
    pts['y'] = [1e-45, -0.0, np.finfo(np.float32).max, np.nan, 3.4028235e38, -1.5]
    pts['i'] = [-2**63, 2**63 - 1, 0, -1, 7, 1]
    pts['u'] = [2**64 - 1, 0, 1, 2**63, 5, 6]
    pts['flag'] = [True, False, True, False, True, False]
    pts['s'] = [-32768, 32767, 0, 1, -1, 2]
    cloud = Cloud(pts, [2683000.123, -1247000.456, 1e-300])
    write_pcd(tmp_path / 'c.pcd', cloud, encoding=encoding)
    back = read_pcd(tmp_path / 'c.pcd')
    assert all(back.points.dtype[n].isnative for n in back.fields)
    assert back.points.dtype['flag'] == np.dtype('u1')
    assert back.points['flag'].tolist() == [1, 0, 1, 0, 1, 0]
    expected = {n: pts[n].astype(pts.dtype[n].newbyteorder('=')) for n in pts.dtype.names if n != 'flag'}
    for name, values in expected.items():
        if encoding == 'ascii' and values.dtype.kind == 'f':
            assert np.array_equal(np.isnan(back.points[name]), np.isnan(values))
            keep = ~np.isnan(values)
            assert back.points[name][keep].tobytes() == values[keep].tobytes(), name
        else:
            assert back.points[name].tobytes() == values.tobytes(), name
    assert np.signbit(back.points['x'][0]) and np.signbit(back.points['y'][1])
    assert back.map_origin.tolist() == [2683000.123, -1247000.456, 1e-300]


def test_pcd_header_is_pcl_style(tmp_path: Path) -> None:
    pts = np.zeros(3, dtype=[('x', 'f8'), ('y', 'f8'), ('z', 'f4'), ('class', 'u1'), ('t', 'i2')])
    write_pcd(tmp_path / 'c.pcd', Cloud(pts, [2683000.1, 0.3, -0.0]))
    header = (tmp_path / 'c.pcd').read_bytes().split(b'DATA binary\n')[0].decode()
    assert header.startswith('# .PCD v0.7')
    for line in ('VERSION 0.7', 'FIELDS x y z class t', 'SIZE 8 8 4 1 2', 'TYPE F F F U I',
                 'COUNT 1 1 1 1 1', 'WIDTH 3', 'HEIGHT 1', 'POINTS 3',
                 'VIEWPOINT 2683000.1 0.3 -0.0 1.0 0.0 0.0 0.0'):
        assert f'\n{line}\n' in header, line


def test_empty_cloud_in_every_pcd_encoding(tmp_path: Path) -> None:
    cloud = Cloud(xyz_points(0), [1.0, 2.0, 3.0])
    for encoding in PCD_ENCODINGS:
        write_pcd(tmp_path / 'e.pcd', cloud, encoding=encoding)
        assert read_pcd(tmp_path / 'e.pcd').same_as(cloud), encoding


def pcl_header(fields: str, size: str, type_: str, count: str, width: int, height: int,
               data: str, viewpoint: str = '0 0 0 1 0 0 0') -> bytes:
    """A PCD header as PCL writes it."""
    return (f'# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS {fields}\nSIZE {size}\n'
            f'TYPE {type_}\nCOUNT {count}\nWIDTH {width}\nHEIGHT {height}\nVIEWPOINT {viewpoint}\n'
            f'POINTS {width * height}\nDATA {data}\n').encode()


def test_organized_pcl_cloud_with_padding_and_counts(tmp_path: Path) -> None:
    raw = np.zeros(4, dtype=[('x', '<f4'), ('y', '<f4'), ('z', '<f4'), ('pad', 'u1', (4,)),
                             ('normal', '<f4', (3,)), ('label', '<u4')])
    raw['x'] = [1, 2, 3, np.nan]
    raw['pad'] = 0xAB
    raw['normal'] = np.arange(12).reshape(4, 3)
    raw['label'] = [7, 8, 9, 10]
    (tmp_path / 'o.pcd').write_bytes(
        pcl_header('x y z _ normal label', '4 4 4 1 4 4', 'F F F U F U', '1 1 1 4 3 1', 2, 2, 'binary')
        + raw.tobytes())
    cloud = read_cloud(tmp_path / 'o.pcd')
    assert cloud.fields == ('x', 'y', 'z', 'normal__0000', 'normal__0001', 'normal__0002', 'label')
    assert np.array_equal(cloud.points['x'], raw['x'], equal_nan=True)
    assert cloud.points['normal__0002'].tolist() == [2, 5, 8, 11]
    assert cloud.points['label'].tolist() == [7, 8, 9, 10]
    assert cloud.map_origin.tolist() == [0.0, 0.0, 0.0]


def test_ascii_pcd_with_one_point_and_viewpoint_translation(tmp_path: Path) -> None:
    (tmp_path / 'a.pcd').write_bytes(
        pcl_header('x y z intensity', '4 4 4 2', 'F F F U', '1 1 1 1', 1, 1, 'ascii',
                   viewpoint='10.5 -3 2e+06 1 0 0 0') + b'0.25 -1.5 3 65535\n')
    cloud = read_pcd(tmp_path / 'a.pcd')
    assert cloud.xyz.tolist() == [[0.25, -1.5, 3.0]]
    assert cloud.points['intensity'].tolist() == [65535]
    assert cloud.map_origin.tolist() == [10.5, -3.0, 2e6]


def test_pcd_viewpoint_with_rotation_is_refused(tmp_path: Path) -> None:
    (tmp_path / 'r.pcd').write_bytes(
        pcl_header('x y z', '4 4 4', 'F F F', '1 1 1', 1, 1, 'ascii',
                   viewpoint='1 2 3 0.7071068 0 0 0.7071068') + b'1 2 3\n')
    assert 'VIEWPOINT has a rotation' in one_line_error(read_cloud, tmp_path / 'r.pcd')


def test_pcd_without_z(tmp_path: Path) -> None:
    (tmp_path / 'n.pcd').write_bytes(
        pcl_header('x y intensity', '4 4 4', 'F F F', '1 1 1', 1, 1, 'ascii') + b'1 2 3\n')
    assert 'PCD file has no field z (fields: x, y, intensity)' in one_line_error(read_pcd, tmp_path / 'n.pcd')


@pytest.mark.parametrize('encoding', PCD_ENCODINGS)
def test_truncated_pcd(tmp_path: Path, encoding: str) -> None:
    pts = np.zeros(20, dtype=simulated_dtype())
    pts['x'] = np.random.default_rng(5).normal(size=20)
    write_pcd(tmp_path / 'c.pcd', Cloud(pts), encoding=encoding)
    data = (tmp_path / 'c.pcd').read_bytes()
    body = data.index(f'DATA {encoding}\n'.encode()) + len(f'DATA {encoding}\n')
    cuts = [0, 3, 30, body - 5, body]
    if encoding == 'ascii':  # whole lines: a cut inside the last value cannot be noticed
        cuts += [i + 1 for i in range(body, len(data) - 1) if data[i] == ord('\n')][::5]
    else:
        cuts += [body + 4, body + 11, (body + len(data)) // 2, len(data) - 1]
    for cut in cuts:
        (tmp_path / 't.pcd').write_bytes(data[:cut])
        assert 'cannot read PCD file' in one_line_error(read_cloud, tmp_path / 't.pcd'), cut


@pytest.mark.parametrize('body', [
    b'',
    b'ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nend_header\n1\n',
    b'VERSION 0.7\nFIELDS x y z\nSIZE 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 1\nHEIGHT 1\nPOINTS 1\nDATA ascii\n1 2 3\n',
    b'VERSION 0.7\nFIELDS x y z\nSIZE 4 4 2\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 1\nHEIGHT 1\nPOINTS 1\nDATA ascii\n1 2 3\n',
    b'VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F X\nCOUNT 1 1 1\nWIDTH 1\nHEIGHT 1\nPOINTS 1\nDATA ascii\n1 2 3\n',
    b'VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 1\nHEIGHT 1\nPOINTS 1\nDATA ascii\n1 2 abc\n',
    b'VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 1\nHEIGHT 1\nPOINTS 3\nDATA ascii\n1 2 3\n',
    b'VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 1\nHEIGHT 1\nPOINTS 1\nDATA ascii\n1 2 3\n4 5 6\n',
    b'VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 1\nHEIGHT 1\nPOINTS -1\nDATA ascii\n',
    b'VERSION 0.7\nFIELDS x x z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 1\nHEIGHT 1\nPOINTS 1\nDATA binary\n' + bytes(12),
    b'VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 1\nHEIGHT 1\nPOINTS 1\nDATA binary_compressed\n'
    + b'\x05\x00\x00\x00\x0c\x00\x00\x00garbage',
    b'VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 1\nHEIGHT 1\nPOINTS 1\nDATA binary_compressed\n'
    + b'\xff\xff\x00\x00\xff\xff\xff\x00',
    b'VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 1\nHEIGHT 1\nPOINTS 1\nDATA lzma\n' + bytes(12),
    b'VERSION 0.7\nFIELDS x y z\ncomment \xff\xfe\n',
])
def test_malformed_pcd(tmp_path: Path, body: bytes) -> None:
    (tmp_path / 'm.pcd').write_bytes(body)
    assert 'cannot read PCD file' in one_line_error(read_pcd, tmp_path / 'm.pcd')


@pytest.mark.parametrize('dtype, message', [
    ([('x', 'f2'), ('y', 'f8'), ('z', 'f8')], "'x' has type float16"),
    ([('x', 'f8'), ('y', 'f8'), ('z', 'f8'), ('rgb', 'u1', (3,))], "'rgb'"),
    ([('x', 'f8'), ('y', 'f8'), ('z', 'f8'), ('s', 'U3')], "'s'"),
    ([('x', 'f8'), ('y', 'f8'), ('z', 'f8'), ('a b', 'f4')], "'a b' cannot be a PCD field name"),
    ([('x', 'f8'), ('y', 'f8'), ('z', 'f8'), ('é', 'f4')], 'cannot be a PCD field name'),
    ([('x', 'f8'), ('y', 'f8'), ('z', 'f8'), ('_', 'f4')], 'cannot be a PCD field name'),
])
def test_pcd_refuses_unsupported_fields(tmp_path: Path, dtype: list, message: str) -> None:
    cloud = Cloud(np.zeros(2, dtype=dtype))
    assert message in one_line_error(write_pcd, tmp_path / 'u.pcd', cloud)
    assert not (tmp_path / 'u.pcd').exists()


def test_pcd_unknown_encoding(tmp_path: Path) -> None:
    message = one_line_error(write_pcd, tmp_path / 'u.pcd', Cloud(xyz_points()), encoding='binaryscompressed')
    assert 'unknown PCD encoding' in message and 'binary_compressed' in message


# --------------------------------------------------------------------------------------
# LAS / LAZ

LAS_FIELD_NAMES = ['building_id', 'gt_facade', 'ring', 'r', 'g', 'b', 'origin_x', 'a_1', 'Z2',
                   'class', 'time']


@st.composite
def las_clouds(draw: st.DrawFn) -> Cloud:
    """Clouds LAS can hold: coordinates within 200 km of the origin, any other fields."""
    extra = draw(st.lists(st.sampled_from(LAS_FIELD_NAMES), max_size=6, unique=True))
    names = draw(st.permutations(['x', 'y', 'z'] + extra))
    dtype = np.dtype([(n, draw(st.sampled_from(['f4', 'f8'] if n in 'xyz' else TYPES))) for n in names])
    n = draw(st.integers(0, 100))
    points = np.zeros(n, dtype=dtype)
    for name in names:
        ftype = dtype[name]
        if name in ('x', 'y', 'z'):
            width = 8 * ftype.itemsize
            points[name] = draw(hnp.arrays(ftype, n, elements=st.floats(-2e5, 2e5, width=width)))
        elif name == 'class' and draw(st.booleans()):
            points[name] = draw(hnp.arrays(ftype, n, elements=st.integers(0, 127)))
        else:
            points[name] = draw(hnp.arrays(ftype, n))
    origin = draw(st.lists(st.floats(-1e7, 1e7), min_size=3, max_size=3))
    return Cloud(points, np.array(origin))


def fits_classification(values: np.ndarray) -> bool:
    """Whether write_las may put ``class`` into the u1 classification dimension."""
    if values.size == 0:
        return True
    if values.dtype.kind == 'f' and not (np.isfinite(values).all() and np.array_equal(values, np.trunc(values))):
        return False
    return bool(values.min() >= 0 and values.max() <= 255)


@settings(SETTINGS, max_examples=30)
@given(cloud=las_clouds(), suffix=st.sampled_from(['.las', '.laz', '.LAZ']))
def test_las_round_trip(tmp_path: Path, cloud: Cloud, suffix: str) -> None:
    path = tmp_path / ('c' + suffix)
    write_cloud(path, cloud)
    assert path.read_bytes()[:4] == b'LASF'
    back = read_cloud(path)
    assert back.map_origin.tobytes() == cloud.map_origin.tobytes()
    assert back.points.dtype['x'] == np.float64
    assert np.all(np.abs(back.xyz - cloud.xyz) <= LAS_SCALE / 2 + 1e-9)
    for name in cloud.fields:
        if name in ('x', 'y', 'z'):
            continue
        values = cloud.points[name]
        if name == 'time' and np.any((values == 0) & np.signbit(values)):  # -0.0: kept as extra bytes
            assert back.points['time'].tobytes() == values.tobytes()
        elif name == 'time':  # into gps_time (f8), and back
            assert back.points['time'].dtype == np.float64
            assert back.points['time'].tobytes() == values.astype(np.float64).tobytes()
        elif name == 'class' and fits_classification(values):  # into classification (u1)
            assert back.points['class'].dtype == np.uint8
            assert np.array_equal(back.points['class'], values)
            assert 'classification' not in back.fields
        else:  # extra bytes, bit for bit
            assert back.points[name].dtype == values.dtype, name
            assert back.points[name].tobytes() == values.tobytes(), name
            if name == 'class':
                assert not back.points['classification'].any()
    assert 'intensity' in back.fields and 'return_number' in back.fields


def test_las_header_and_class_field(tmp_path: Path) -> None:
    import laspy

    pts = np.zeros(4, dtype=[('x', 'f8'), ('y', 'f8'), ('z', 'f8'), ('class', 'u1'),
                             ('building_id', 'i4'), ('intensity', 'u2'), ('return_number', 'u1')])
    pts['x'] = [0.0, 1.23456, -1000.00004, 214000.0]
    pts['class'] = [1, 6, 2, 255]
    pts['building_id'] = [-1, 3, 3, 2**31 - 1]
    pts['intensity'] = [0, 1, 65535, 7]
    pts['return_number'] = [0, 1, 15, 2]
    cloud = Cloud(pts, [2683000.123, 1247000.456, 408.789])
    write_las(tmp_path / 'c.las', cloud)
    las = laspy.read(tmp_path / 'c.las')
    assert las.header.point_format.id == 6 and str(las.header.version) == '1.4'
    assert las.header.offsets.tolist() == [2683000.123, 1247000.456, 408.789]
    assert las.header.scales.tolist() == [LAS_SCALE] * 3
    assert list(las.point_format.extra_dimension_names) == ['building_id']
    assert las.classification.tolist() == [1, 6, 2, 255]
    assert las.X.tolist() == [0, 12346, -10000000, 2140000000]
    back = read_las(tmp_path / 'c.las')
    assert back.points['class'].tolist() == [1, 6, 2, 255]
    assert back.points['intensity'].tolist() == [0, 1, 65535, 7]
    assert back.points['return_number'].tolist() == [0, 1, 15, 2]
    assert back.points['building_id'].tolist() == [-1, 3, 3, 2**31 - 1]
    assert back.points['x'].tolist() == [0.0, 1.2346, -1000.0, 214000.0]


def test_class_that_does_not_fit_classification_stays_extra_bytes(tmp_path: Path) -> None:
    pts = np.zeros(3, dtype=[('x', 'f4'), ('y', 'f4'), ('z', 'f4'), ('class', 'i4'), ('time', 'f4')])
    pts['class'] = [-1, 300, 6]
    pts['time'] = [0.5, np.inf, -2.0]
    write_cloud(tmp_path / 'c.laz', Cloud(pts))
    back = read_cloud(tmp_path / 'c.laz')
    assert back.points['class'].dtype == np.int32 and back.points['class'].tolist() == [-1, 300, 6]
    assert back.points['classification'].tolist() == [0, 0, 0]
    assert back.points['time'].tolist() == [0.5, np.inf, -2.0]
    assert 'gps_time' not in back.fields


def test_foreign_las_format_1_with_scaled_and_array_extra_bytes(tmp_path: Path) -> None:
    import laspy

    header = laspy.LasHeader(point_format=1, version='1.2')
    header.offsets = np.array([2683000.0, 1247000.0, 400.0])
    header.scales = np.array([0.01, 0.01, 0.001])
    header.add_extra_dims([laspy.ExtraBytesParams('range', 'u2', scales=np.array([0.005]),
                                                  offsets=np.array([1.0])),
                           laspy.ExtraBytesParams('normal', '3f4')])
    las = laspy.LasData(header)
    las.points = laspy.ScaleAwarePointRecord.zeros(3, header=header)
    las.X = [100, -250, 123456]
    las.Y = [0, 1, 2]
    las.Z = [5000, 5001, -5002]
    las.classification = [2, 6, 31]
    las.gps_time = [3.5e8, 3.5e8 + 0.25, 3.5e8 + 1e-6]
    las.intensity = [10, 20, 30]
    las['range'] = np.array([1.0, 2.0, 328.675])
    las['normal'] = np.arange(9, dtype=np.float32).reshape(3, 3)
    las.write(tmp_path / 'f.laz')
    cloud = read_cloud(tmp_path / 'f.laz')
    assert cloud.map_origin.tolist() == [2683000.0, 1247000.0, 400.0]
    assert cloud.points['x'].tolist() == [1.0, -2.5, 1234.56]
    assert cloud.points['z'].tolist() == [5.0, 5.001, -5.002]
    assert cloud.points['class'].tolist() == [2, 6, 31]
    assert cloud.points['time'].tolist() == [3.5e8, 3.5e8 + 0.25, 3.5e8 + 1e-6]
    assert 'classification' not in cloud.fields and 'gps_time' not in cloud.fields
    assert cloud.points['scan_angle_rank'].dtype == np.int8
    assert np.allclose(cloud.points['range'], [1.0, 2.0, 328.675], atol=0.0025)
    assert [cloud.points[f'normal_{k}'].tolist() for k in range(3)] == [[0, 3, 6], [1, 4, 7], [2, 5, 8]]
    georeferenced = cloud.xyz + cloud.map_origin
    assert np.allclose(georeferenced, np.column_stack([las.x, las.y, las.z]), rtol=0, atol=1e-9)


@pytest.mark.parametrize('points, message', [
    ({'x': [0.0, np.nan, 1.0]}, '1 of 3 points have a x that LAS cannot store'),
    ({'z': [np.inf, 0.0, 0.0]}, '1 of 3 points have a z'),
    ({'y': [3e5, -3e5, 0.0]}, '2 of 3 points have a y'),
])
def test_las_refuses_coordinates_it_cannot_store(tmp_path: Path, points: dict, message: str) -> None:
    pts = np.zeros(3, dtype=[('x', 'f8'), ('y', 'f8'), ('z', 'f8')])
    for name, values in points.items():
        pts[name] = values
    assert message in one_line_error(write_las, tmp_path / 'c.las', Cloud(pts))
    assert not (tmp_path / 'c.las').exists()


@pytest.mark.parametrize('field, values, message', [
    (('intensity', 'f4'), [0.5, 1], "'intensity' (float32) does not fit the LAS dimension intensity"),
    (('intensity', 'i4'), [-1, 1], 'an integer in [0, 65535]'),
    (('return_number', 'u1'), [16, 1], 'LAS dimension return_number, which holds an integer in [0, 15]'),
    (('rgb', 'u1', (3,)), [(1, 2, 3), (4, 5, 6)], "'rgb'"),
    (('h', 'f2'), [1, 2], "'h' has type float16"),
    (('X', 'f8'), [1, 2], "'X' is reserved"),
    (('n' * 33, 'u1'), [1, 2], 'cannot be a LAS extra-bytes name'),
    (('é', 'u1'), [1, 2], 'cannot be a LAS extra-bytes name'),
])
def test_las_refuses_fields_it_cannot_store(tmp_path: Path, field: tuple, values: list, message: str) -> None:
    pts = np.zeros(2, dtype=[('x', 'f8'), ('y', 'f8'), ('z', 'f8'), field])
    pts[field[0]] = values
    assert message in one_line_error(write_las, tmp_path / 'c.las', Cloud(pts))
    assert not (tmp_path / 'c.las').exists()


def test_simulated_cloud_through_las_laz_and_pcd(tmp_path: Path) -> None:
    pts = np.zeros(50, dtype=simulated_dtype('f4'))
    rng = np.random.default_rng(1)
    for name in pts.dtype.names:
        pts[name] = rng.integers(0, 5, 50)
    pts['x'] = rng.normal(size=50)
    cloud = Cloud(pts, [2683000.0, 1247000.0, 400.0])
    for name in ('a.pcd', 'A.PCD'):
        write_cloud(tmp_path / name, cloud)
        assert read_cloud(tmp_path / name).same_as(cloud)
    for name in ('a.las', 'a.laz', 'A.LAS'):
        write_cloud(tmp_path / name, cloud)
        back = read_cloud(tmp_path / name)
        assert np.all(np.abs(back.xyz - cloud.xyz) <= LAS_SCALE / 2 + 1e-9)
        for field in cloud.fields[3:]:
            assert np.array_equal(back.points[field], cloud.points[field]), field


@pytest.mark.parametrize('suffix', ['.las', '.laz'])
def test_truncated_las(tmp_path: Path, suffix: str) -> None:
    pts = np.zeros(300, dtype=simulated_dtype())
    pts['x'] = np.random.default_rng(2).normal(size=300)
    write_cloud(tmp_path / ('c' + suffix), Cloud(pts, [1.0, 2.0, 3.0]))
    data = (tmp_path / ('c' + suffix)).read_bytes()
    for cut in (0, 3, 100, 226, 300, 400, len(data) // 2, len(data) - 9, len(data) - 1):
        (tmp_path / ('t' + suffix)).write_bytes(data[:cut])
        assert 'cannot read LAS file' in one_line_error(read_cloud, tmp_path / ('t' + suffix)), cut


def damaged(data: bytes, offset: int, fmt: str, value: int) -> bytes:
    """``data`` with ``value`` packed at ``offset``."""
    raw = bytearray(data)
    struct.pack_into(fmt, raw, offset, value)
    return bytes(raw)


def test_las_with_impossible_counts(tmp_path: Path) -> None:
    """Counts that laspy or lazrs would trust: a VLR loop of hours, huge allocations, aborts."""
    cloud = Cloud(np.zeros(20, dtype=simulated_dtype('f4')), [1.0, 2.0, 3.0])
    write_cloud(tmp_path / 'c.las', cloud)
    write_cloud(tmp_path / 'c.laz', cloud)
    las = (tmp_path / 'c.las').read_bytes()
    laz = (tmp_path / 'c.laz').read_bytes()
    chunk_table = struct.unpack_from('<q', laz, struct.unpack_from('<I', laz, 96)[0])[0]
    cases = [
        ('v.las', damaged(las, 100, '<I', 2**32 - 1), 'VLRs, more than the file'),
        ('e.las', damaged(las, 243, '<I', 2**32 - 1), 'EVLRs, more than the file'),
        ('p.las', damaged(las, 247, '<Q', 2**60), 'header announces 1152921504606846976 points'),
        ('v.laz', damaged(laz, 100, '<I', 2**31), 'VLRs, more than the file'),
        ('c.laz', damaged(laz, chunk_table + 4, '<I', 2**32 - 16), 'LAZ chunk table announces'),
        ('g.las', b'LASF' + bytes(10), 'cannot read LAS file'),
        ('t.laz', b'not a LAS file at all\n' * 20, 'cannot read LAS file'),
    ]
    for name, data, message in cases:
        (tmp_path / name).write_bytes(data)
        assert message in one_line_error(read_cloud, tmp_path / name), name


def test_laz_with_absurd_chunk_size_does_not_abort(tmp_path: Path) -> None:
    """lazrs' parallel decoder aborts the process on this; the sequential one copes."""
    cloud = Cloud(np.zeros(20, dtype=simulated_dtype('f4')), [1.0, 2.0, 3.0])
    write_cloud(tmp_path / 'c.laz', cloud)
    laz = (tmp_path / 'c.laz').read_bytes()
    vlr_data = laz.index(b'laszip encoded') - 2 + 54
    for chunk_size in (2**32 - 16, 1, 0):
        (tmp_path / 'k.laz').write_bytes(damaged(laz, vlr_data + 12, '<I', chunk_size))
        try:
            back = read_cloud(tmp_path / 'k.laz')
        except InputError as err:
            assert 'cannot read LAS file' in str(err) and '\n' not in str(err)
        else:
            assert len(back) == 20


@settings(SETTINGS, max_examples=60)
@given(data=st.data())
def test_damaged_las_and_pcd_raise_only_input_errors(tmp_path: Path, data: st.DataObject) -> None:
    """Random truncation and byte damage (LAZ: truncation only, see read_las on lazrs)."""
    kind = data.draw(st.sampled_from(['las', 'laz', 'ascii', 'binary', 'binary_compressed']))
    pts = np.zeros(8, dtype=simulated_dtype('f4'))
    pts['x'] = np.arange(8)
    cloud = Cloud(pts, [1.0, 2.0, 3.0])
    path = tmp_path / ('d.' + (kind if kind in ('las', 'laz') else 'pcd'))
    if kind in ('las', 'laz'):
        write_cloud(path, cloud)
    else:
        write_pcd(path, cloud, encoding=kind)
    raw = bytearray(path.read_bytes())
    raw = raw[:data.draw(st.integers(0, len(raw)))]
    if kind != 'laz':
        for _ in range(data.draw(st.integers(0, 4))):
            if raw:
                raw[data.draw(st.integers(0, len(raw) - 1))] = data.draw(st.integers(0, 255))
    path.write_bytes(bytes(raw))
    try:
        back = read_cloud(path)
    except InputError as err:
        assert '\n' not in str(err)
    else:
        assert isinstance(back, Cloud)


@pytest.mark.parametrize('reader', [read_cloud, read_las, read_pcd])
@pytest.mark.parametrize('name', ['missing.las', 'missing.laz', 'missing.pcd'])
def test_missing_las_and_pcd(tmp_path: Path, reader, name: str) -> None:
    assert one_line_error(reader, tmp_path / name) == f'no such file: {tmp_path / name}'


def test_unwritable_las_and_pcd(tmp_path: Path) -> None:
    cloud = Cloud(xyz_points())
    for name in ('no/such/dir/c.las', 'no/such/dir/c.laz', 'no/such/dir/c.pcd'):
        assert 'cannot write' in one_line_error(write_cloud, tmp_path / name, cloud)
