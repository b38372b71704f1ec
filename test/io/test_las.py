"""Tests of uncertain_facade_map.io.las: LAS/LAZ round trips, files from other tools and clean errors."""

from __future__ import annotations

import struct
from pathlib import Path

import hypothesis.extra.numpy as hnp
import numpy as np
import pytest
from cloud_support import SETTINGS, TYPES, one_line_error
from hypothesis import given, settings
from hypothesis import strategies as st

from uncertain_facade_map.errors import InputError
from uncertain_facade_map.io.cloud import Cloud, simulated_dtype
from uncertain_facade_map.io.clouds import read_cloud, write_cloud
from uncertain_facade_map.io.las import LAS_SCALE, iter_las, read_las, write_las

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


@settings(SETTINGS, max_examples=15)
@given(cloud=las_clouds(), suffix=st.sampled_from(['.las', '.laz']), chunk=st.integers(1, 40))
def test_las_in_chunks_is_the_whole_file(tmp_path: Path, cloud: Cloud, suffix: str, chunk: int) -> None:
    """iter_las (the tiled build's reader): the chunks joined are read_las's cloud, bit for bit."""
    path = tmp_path / ('c' + suffix)
    write_cloud(path, cloud)
    whole = read_las(path)
    parts = list(iter_las(path, chunk))
    assert all(0 < len(p) <= chunk for p in parts)
    assert sum(len(p) for p in parts) == len(whole)
    if parts:
        joined = np.concatenate([p.points for p in parts])
        assert joined.dtype == whole.points.dtype and joined.tobytes() == whole.points.tobytes()
        assert all(p.map_origin.tobytes() == whole.map_origin.tobytes() for p in parts)
