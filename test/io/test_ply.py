"""Tests of uncertain_facade_map.io.ply: loss-free PLY round trips, files from other tools and clean errors."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from cloud_support import SETTINGS, clouds, one_line_error, values_equal_nan_canonical, xyz_points
from hypothesis import given, settings
from plyfile import PlyData, PlyElement

from uncertain_facade_map.io.cloud import Cloud, simulated_dtype
from uncertain_facade_map.io.clouds import read_cloud, write_cloud
from uncertain_facade_map.io.ply import read_ply, write_ply

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


def write_plyfile(path: Path, elements: list[PlyElement], **kwargs: object) -> None:
    """Write a PLY with plyfile directly, as a foreign tool would."""
    PlyData(elements, **kwargs).write(str(path))


# --------------------------------------------------------------------------------------
# round trips


@SETTINGS
@given(cloud=clouds())
def test_binary_ply_round_trip_is_bit_exact(tmp_path: Path, cloud: Cloud) -> None:
    path = tmp_path / 'c.ply'
    write_cloud(path, cloud)
    back = read_cloud(path)
    assert back.same_as(cloud)
    assert back.map_origin.tobytes() == cloud.map_origin.tobytes()


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


# --------------------------------------------------------------------------------------
# errors


@pytest.mark.parametrize('binary', [True, False])
def test_truncated_ply(tmp_path: Path, binary: bool) -> None:
    pts = np.zeros(20, dtype=simulated_dtype())
    write_ply(tmp_path / 'c.ply', Cloud(pts), binary=binary)
    data = (tmp_path / 'c.ply').read_bytes()
    header_end = data.index(b'end_header')
    for cut in (0, 3, 10, header_end, header_end + 11, len(data) // 2, len(data) - 5):
        (tmp_path / 't.ply').write_bytes(data[:cut])
        assert 'cannot read PLY file' in one_line_error(read_cloud, tmp_path / 't.ply'), cut


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
