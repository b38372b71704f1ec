"""Tests of msg_adapters.pointcloud2: PointCloud2 <-> structured numpy arrays."""

from __future__ import annotations

import array
import struct
import sys
from contextlib import contextmanager
from types import SimpleNamespace
from typing import Iterator

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from msg_adapters.pointcloud2 import (
    POINTFIELD_TYPES,
    pointcloud2_fields,
    pointcloud2_from_structured,
    rclpy_types,
    rosbags_types,
    structured_from_pointcloud2,
)
from uncertain_facade_map.errors import InputError

ROSBAGS = rosbags_types()


def _rclpy_types_or_skip() -> SimpleNamespace:
    try:
        return rclpy_types()
    except ImportError as err:  # pragma: no cover - the project venv has them
        pytest.skip(f'ROS 2 message packages not importable: {err}')


@contextmanager
def rclpy_field_checks(types: SimpleNamespace) -> Iterator[None]:
    """Turn on rclpy's per-field type assertions (ROS_PYTHON_CHECK_FIELDS=1) for ``types``."""
    with pytest.MonkeyPatch.context() as mp:
        for name in ('PointCloud2', 'PointField', 'Header', 'Time'):
            module = sys.modules[getattr(types, name).__module__]
            mp.setattr(module, 'ros_python_check_fields', '1')
        yield


def field(name: str, offset: int, datatype: int, count: int = 1) -> SimpleNamespace:
    return SimpleNamespace(name=name, offset=offset, datatype=datatype, count=count)


def message(fields, *, data, point_step, width, height=1, row_step=None, big=False):
    """A PointCloud2 look-alike: the adapters only read attributes."""
    return SimpleNamespace(
        fields=fields, data=data, point_step=point_step, width=width, height=height,
        row_step=point_step * width if row_step is None else row_step, is_bigendian=big,
        is_dense=True,
    )


# --------------------------------------------------------------------------------------
# property tests
# --------------------------------------------------------------------------------------

NAME_ALPHABET = 'abcdefghijklmnopqrstuvwxyz_0123456789'


@st.composite
def structured_arrays(draw, byteorder: str = '<') -> np.ndarray:
    """Random structured array: 1..6 fields of the 8 PointField types, N in 0..50.

    The values are random bytes, so floats include NaN (with payloads), inf and denormals.
    """
    names = draw(st.lists(st.text(NAME_ALPHABET, min_size=1, max_size=8),
                          min_size=1, max_size=6, unique=True))
    fields = []
    for name in names:
        base = np.dtype(POINTFIELD_TYPES[draw(st.integers(1, 8))]).newbyteorder(byteorder)
        count = draw(st.sampled_from([1, 1, 1, 2, 3]))
        fields.append((name, base) if count == 1 else (name, base, (count,)))
    dtype = np.dtype(fields)
    n = draw(st.integers(0, 50))
    raw = draw(st.binary(min_size=n * dtype.itemsize, max_size=n * dtype.itemsize))
    return np.frombuffer(raw, dtype=dtype).copy()


def _native(dtype: np.dtype) -> np.dtype:
    return np.dtype([(n, dtype[n].base.newbyteorder('='), dtype[n].shape) for n in dtype.names])


@settings(max_examples=50, deadline=None)
@given(points=structured_arrays())
def test_round_trip_rosbags_types_is_bit_exact(points: np.ndarray) -> None:
    msg = pointcloud2_from_structured(points, stamp_ns=1_700_000_000_123_456_789,
                                      frame_id='map', msg_types=ROSBAGS)
    assert isinstance(msg.data, np.ndarray) and msg.data.dtype == np.uint8
    assert (msg.height, msg.width, msg.is_bigendian) == (1, len(points), False)
    assert msg.row_step == msg.point_step * len(points) == len(msg.data)
    back = structured_from_pointcloud2(msg)
    assert back.dtype == points.dtype
    assert back.tobytes() == points.tobytes()


@settings(max_examples=50, deadline=None)
@given(points=structured_arrays())
def test_round_trip_rclpy_types_is_bit_exact(points: np.ndarray) -> None:
    types = _rclpy_types_or_skip()
    with rclpy_field_checks(types):
        msg = pointcloud2_from_structured(points, stamp_ns=1_700_000_000_123_456_789,
                                          frame_id='map', msg_types=types)
    assert isinstance(msg, types.PointCloud2)
    assert isinstance(msg.data, array.array) and msg.data.typecode == 'B'
    back = structured_from_pointcloud2(msg)
    assert back.dtype == points.dtype
    assert back.tobytes() == points.tobytes()


@settings(max_examples=50, deadline=None)
@given(points=structured_arrays(byteorder='>'))
def test_big_endian_input_round_trips_to_native_bit_exact(points: np.ndarray) -> None:
    expected = points.astype(_native(points.dtype))
    msg = pointcloud2_from_structured(points, stamp_ns=0, frame_id='map', msg_types=ROSBAGS)
    back = structured_from_pointcloud2(msg)
    assert back.dtype == expected.dtype
    assert back.tobytes() == expected.tobytes()


@settings(max_examples=50, deadline=None)
@given(points=structured_arrays())
def test_cdr_round_trip_keeps_data(points: np.ndarray) -> None:
    ts = ROSBAGS.typestore
    msg = pointcloud2_from_structured(points, stamp_ns=42_000_000_007, frame_id='lidar',
                                      msg_types=ROSBAGS)
    raw = ts.serialize_cdr(msg, 'sensor_msgs/msg/PointCloud2')
    again = ts.deserialize_cdr(raw, 'sensor_msgs/msg/PointCloud2')
    assert (again.header.stamp.sec, again.header.stamp.nanosec) == (42, 7)
    assert again.header.frame_id == 'lidar'
    back = structured_from_pointcloud2(again)
    assert back.dtype == points.dtype and back.tobytes() == points.tobytes()


# --------------------------------------------------------------------------------------
# hand-made messages
# --------------------------------------------------------------------------------------


def test_padding_between_fields_and_after_last_field() -> None:
    # x f4 @0, 4 pad bytes, intensity u2 @8, ring u1 @10, 5 pad bytes: point_step 16
    fields = [field('x', 0, 7), field('intensity', 8, 4), field('ring', 10, 2)]
    rows = [(1.5, 7, 3), (-2.25, 65535, 255), (float('nan'), 0, 0)]
    data = b''.join(struct.pack('<f4xHB5x', *r) for r in rows)
    assert len(data) == 48
    out = structured_from_pointcloud2(message(fields, data=data, point_step=16, width=3))
    assert out.dtype == np.dtype([('x', 'f4'), ('intensity', 'u2'), ('ring', 'u1')])
    assert out.dtype.itemsize == 7
    np.testing.assert_array_equal(out['x'], np.array([1.5, -2.25, np.nan], dtype=np.float32))
    np.testing.assert_array_equal(out['intensity'], [7, 65535, 0])
    np.testing.assert_array_equal(out['ring'], [3, 255, 0])


def test_fields_out_of_offset_order_keep_message_order() -> None:
    fields = [field('b', 4, 5), field('a', 0, 7)]
    data = struct.pack('<fi', 0.5, -9)
    out = structured_from_pointcloud2(message(fields, data=data, point_step=8, width=1))
    assert out.dtype.names == ('b', 'a')
    assert out['b'][0] == -9 and out['a'][0] == 0.5


def test_big_endian_message() -> None:
    fields = [field('x', 0, 8), field('y', 8, 7), field('i', 12, 3), field('u', 14, 6),
              field('c', 18, 1)]
    rows = [(1.0e6 + 0.125, -3.5, -2, 4_000_000_000, -128), (-0.0, 2.0, 300, 1, 127)]
    data = b''.join(struct.pack('>dfhIbx', *r) for r in rows)
    out = structured_from_pointcloud2(message(fields, data=data, point_step=20, width=2,
                                              big=True))
    assert all(out.dtype[n].isnative for n in out.dtype.names)
    for name, col in zip(('x', 'y', 'i', 'u', 'c'), zip(*rows)):
        np.testing.assert_array_equal(out[name], col)
    assert np.signbit(out['x'][1])


def test_big_endian_nan_payload_is_kept() -> None:
    bits = 0x7FF0_0000_0000_0ABC  # signalling NaN with a payload
    data = struct.pack('>Q', bits)
    out = structured_from_pointcloud2(message([field('x', 0, 8)], data=data, point_step=8,
                                              width=1, big=True))
    assert out['x'].view(np.uint64)[0] == bits


def test_height_above_one_with_row_padding() -> None:
    fields = [field('x', 0, 7), field('y', 4, 7)]
    height, width, point_step, row_step = 2, 3, 8, 3 * 8 + 5
    values = np.arange(height * width * 2, dtype=np.float32).reshape(height, width, 2)
    data = b''.join(values[r].tobytes() + b'\xee' * 5 for r in range(height))
    msg = message(fields, data=data, point_step=point_step, width=width, height=height,
                  row_step=row_step)
    out = structured_from_pointcloud2(msg)
    assert out.shape == (6,)
    np.testing.assert_array_equal(out['x'], values[..., 0].reshape(-1))
    np.testing.assert_array_equal(out['y'], values[..., 1].reshape(-1))


def test_count_above_one_is_a_sub_array_field() -> None:
    fields = [field('x', 0, 7), field('rgb', 4, 2, count=3)]
    data = struct.pack('<f3Bx', 1.0, 10, 20, 30) + struct.pack('<f3Bx', 2.0, 1, 2, 3)
    out = structured_from_pointcloud2(message(fields, data=data, point_step=8, width=2))
    assert out.dtype['rgb'].shape == (3,)
    np.testing.assert_array_equal(out['rgb'], [[10, 20, 30], [1, 2, 3]])
    msg = pointcloud2_from_structured(out, stamp_ns=0, frame_id='map', msg_types=ROSBAGS)
    assert [(f.name, f.offset, f.datatype, f.count) for f in msg.fields] == [
        ('x', 0, 7, 1), ('rgb', 4, 2, 3)]


@pytest.mark.parametrize('kind', ['bytes', 'bytearray', 'array', 'list', 'numpy', 'memoryview',
                                  'numpy_strided'])
def test_data_containers(kind: str) -> None:
    raw = struct.pack('<ff', 1.25, -4.0)
    data = {
        'bytes': raw,
        'bytearray': bytearray(raw),
        'array': array.array('B', raw),
        'list': list(raw),
        'numpy': np.frombuffer(raw, dtype=np.uint8),
        'memoryview': memoryview(raw),
        'numpy_strided': np.repeat(np.frombuffer(raw, dtype=np.uint8), 2)[::2],
    }[kind]
    out = structured_from_pointcloud2(message([field('x', 0, 7)], data=data, point_step=4,
                                              width=2))
    np.testing.assert_array_equal(out['x'], [1.25, -4.0])


def test_empty_cloud() -> None:
    out = structured_from_pointcloud2(message([field('x', 0, 7)], data=b'', point_step=4,
                                              width=0))
    assert out.shape == (0,) and out.dtype == np.dtype([('x', 'f4')])


def test_output_owns_its_memory() -> None:
    raw = bytearray(struct.pack('<f', 3.0))
    out = structured_from_pointcloud2(message([field('x', 0, 7)], data=raw, point_step=4,
                                              width=1))
    raw[:] = b'\x00' * 4
    assert out['x'][0] == 3.0


# --------------------------------------------------------------------------------------
# encoding details
# --------------------------------------------------------------------------------------


def test_pointcloud2_fields_packs_a_padded_dtype() -> None:
    dtype = np.dtype({'names': ['x', 'i', 'rgb'], 'formats': ['<f8', '>u2', ('u1', (2, 2))],
                      'offsets': [0, 16, 20], 'itemsize': 32})
    assert pointcloud2_fields(dtype) == [('x', 0, 8, 1), ('i', 8, 4, 1), ('rgb', 10, 2, 4)]
    pts = np.zeros(2, dtype)
    pts['x'] = [1.0, 2.0]
    pts['i'] = [513, 7]
    msg = pointcloud2_from_structured(pts, stamp_ns=0, frame_id='map', msg_types=ROSBAGS)
    assert msg.point_step == 14
    back = structured_from_pointcloud2(msg)
    np.testing.assert_array_equal(back['x'], pts['x'])
    np.testing.assert_array_equal(back['i'], pts['i'])
    assert back['rgb'].shape == (2, 4)


@pytest.mark.parametrize('bad', ['i8', 'u8', '?', 'f2', 'S4', 'c8'])
def test_pointcloud2_fields_rejects_unsupported_types(bad: str) -> None:
    with pytest.raises(InputError, match="field 'v'"):
        pointcloud2_fields(np.dtype([('x', 'f4'), ('v', bad)]))


def test_pointcloud2_from_structured_rejects_non_structured() -> None:
    with pytest.raises(InputError):
        pointcloud2_from_structured(np.zeros(3), stamp_ns=0, frame_id='map', msg_types=ROSBAGS)
    with pytest.raises(InputError):
        pointcloud2_from_structured(np.zeros((2, 2), [('x', 'f4')]), stamp_ns=0,
                                    frame_id='map', msg_types=ROSBAGS)
    with pytest.raises(InputError, match='stamp'):
        pointcloud2_from_structured(np.zeros(1, [('x', 'f4')]), stamp_ns=-1,
                                    frame_id='map', msg_types=ROSBAGS)


def test_header_and_is_dense() -> None:
    pts = np.zeros(3, [('x', 'f8'), ('y', 'f8'), ('z', 'f4'), ('time', 'f8')])
    pts['time'] = np.nan  # not a coordinate: does not make the cloud sparse
    msg = pointcloud2_from_structured(pts, stamp_ns=12 * 10**9 + 34, frame_id='odom',
                                      msg_types=ROSBAGS)
    assert msg.is_dense is True
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec, msg.header.frame_id) == (
        12, 34, 'odom')
    pts['z'][1] = np.inf
    assert pointcloud2_from_structured(pts, stamp_ns=0, frame_id='m',
                                       msg_types=ROSBAGS).is_dense is False
    pts['z'][1] = 0
    pts['y'][2] = np.nan
    assert pointcloud2_from_structured(pts, stamp_ns=0, frame_id='m',
                                       msg_types=ROSBAGS).is_dense is False


def test_ros1_typestore_and_serialization() -> None:
    from rosbags.typesys import Stores, get_typestore

    types = rosbags_types(get_typestore(Stores.ROS1_NOETIC))
    pts = np.zeros(4, [('x', 'f4'), ('y', 'f4'), ('z', 'f4'), ('id', 'i4')])
    pts['x'] = np.arange(4)
    pts['id'] = [-1, 0, 1, 2]
    msg = pointcloud2_from_structured(pts, stamp_ns=5 * 10**9, frame_id='map', msg_types=types)
    assert msg.header.seq == 0
    raw = types.typestore.serialize_ros1(msg, 'sensor_msgs/msg/PointCloud2')
    again = types.typestore.deserialize_ros1(raw, 'sensor_msgs/msg/PointCloud2')
    assert structured_from_pointcloud2(again).tobytes() == pts.tobytes()


@pytest.mark.filterwarnings('ignore::DeprecationWarning')
def test_rclpy_message_decodes_and_serializes() -> None:
    types = _rclpy_types_or_skip()
    pts = np.zeros(5, [('x', 'f8'), ('y', 'f8'), ('z', 'f8'), ('class', 'u1')])
    pts['x'] = np.linspace(0, 1, 5)
    pts['class'] = [0, 1, 2, 3, 4]
    with rclpy_field_checks(types):
        with pytest.raises(AssertionError):  # the checks are on
            types.Time(sec=1.5, nanosec=0)
        msg = pointcloud2_from_structured(pts, stamp_ns=1_000_000_001, frame_id='map',
                                          msg_types=types)
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == (1, 1)
    assert structured_from_pointcloud2(msg).tobytes() == pts.tobytes()
    try:
        from rclpy.serialization import deserialize_message, serialize_message
    except ImportError:  # pragma: no cover
        return
    again = deserialize_message(serialize_message(msg), types.PointCloud2)
    assert structured_from_pointcloud2(again).tobytes() == pts.tobytes()


def test_importing_msg_adapters_does_not_import_rclpy() -> None:
    import subprocess

    code = ('import sys, msg_adapters; '
            'bad = [m for m in sys.modules if m.split(".")[0] in '
            '("rclpy", "sensor_msgs", "std_msgs", "builtin_interfaces")]; '
            'assert not bad, bad')
    subprocess.run([sys.executable, '-c', code], check=True, cwd=_repo_root())


def _repo_root() -> str:
    from pathlib import Path

    return str(Path(__file__).resolve().parents[2])


# --------------------------------------------------------------------------------------
# malformed messages
# --------------------------------------------------------------------------------------

GOOD_FIELDS = [field('x', 0, 7), field('y', 4, 7)]


@pytest.mark.parametrize(
    ('fields', 'kwargs', 'match'),
    [
        ([field('x', 0, 9)], {}, 'unknown datatype 9'),
        ([field('x', 0, 0)], {}, 'unknown datatype 0'),
        ([field('x', 0, 7), field('y', 6, 7)], {}, "field 'y' spans bytes 6..10"),
        ([field('x', 4, 8)], {}, "field 'x' spans bytes 4..12"),
        ([field('x', 0, 7, count=3)], {}, 'spans bytes 0..12'),
        ([field('x', 0, 7), field('x', 4, 7)], {}, 'duplicate field names: x'),
        ([field('x', 0, 7, count=0)], {}, 'count 0'),
        ([field('', 0, 7)], {}, 'empty name'),
        ([], {}, 'no fields'),
        (GOOD_FIELDS, {'data': b'\x00' * 15}, 'data has 15 bytes, expected'),
        (GOOD_FIELDS, {'data': b'\x00' * 17}, 'data has 17 bytes, expected'),
        (GOOD_FIELDS, {'row_step': 12}, 'row_step 12 is shorter'),
        (GOOD_FIELDS, {'data': [0] * 15 + [256]}, 'outside 0..255'),
        (GOOD_FIELDS, {'data': [0.5] * 16}, 'must hold bytes'),
    ],
)
def test_malformed_messages_raise_input_error(fields, kwargs, match) -> None:
    args = {'data': b'\x00' * 16, 'point_step': 8, 'width': 2}
    args.update(kwargs)
    with pytest.raises(InputError, match=match) as info:
        structured_from_pointcloud2(message(fields, **args))
    assert '\n' not in str(info.value)
