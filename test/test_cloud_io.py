"""Tests of uncertain_facade_map.cloud_io: loss-free PLY/NPZ round trips and clean errors."""

from __future__ import annotations

import io
import zipfile
from pathlib import Path

import hypothesis.extra.numpy as hnp
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from plyfile import PlyData, PlyElement

from uncertain_facade_map.cloud import Cloud, simulated_dtype
from uncertain_facade_map.cloud_io import (
    NPZ_FORMAT, PLY_TYPES, read_cloud, read_npz, read_ply, write_cloud, write_npz, write_ply,
)
from uncertain_facade_map.errors import InputError

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
    ({'format': np.array('uncertain_facade_map.cloud/99'), 'points': xyz_points()}, 'unsupported format'),
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


@pytest.mark.parametrize('name', ['c.las', 'c', 'c.ply.gz', 'c.txt'])
def test_unknown_suffix(tmp_path: Path, name: str) -> None:
    (tmp_path / name).write_bytes(b'x')
    for message in (one_line_error(read_cloud, tmp_path / name),
                    one_line_error(write_cloud, tmp_path / name, Cloud(xyz_points()))):
        assert 'unsupported file type' in message and '.npz' in message and '.ply' in message


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
