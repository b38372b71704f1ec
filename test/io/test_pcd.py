"""Tests of uncertain_facade_map.io.pcd: loss-free PCD round trips in every encoding, PCL files and clean errors."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from cloud_support import SETTINGS, clouds, one_line_error, raw_clouds, values_equal_nan_canonical, xyz_points
from hypothesis import given, settings
from hypothesis import strategies as st

from uncertain_facade_map.io.cloud import Cloud, simulated_dtype
from uncertain_facade_map.io.clouds import read_cloud
from uncertain_facade_map.io.pcd import PCD_ENCODINGS, read_pcd, write_pcd


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
