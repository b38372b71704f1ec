"""``sensor_msgs/msg/PointCloud2`` <-> numpy structured arrays.

The functions read and set message *attributes* only and never check message classes, so
they work alike with rclpy's generated classes (``sensor_msgs.msg.PointCloud2``) and with
rosbags' typestore dataclasses (``typestore.types['sensor_msgs/msg/PointCloud2']``).

Layout conventions:

* Decoding gives a *packed* one-dimensional structured array of ``height * width`` points
  (row-major, rows first), in native byte order, with the fields in the order of
  ``msg.fields``. Padding between fields, after the last field (``point_step`` larger than
  the fields) and at row ends (``row_step`` larger than ``width * point_step``) is dropped.
* A field with ``count > 1`` becomes a sub-array field of shape ``(count,)`` (e.g.
  ``('rgb', 'u1', (3,))``) rather than ``name_0, name_1, ...``, so that names stay those of
  the message and encoding gives the same ``PointField`` back.
* Encoding writes a packed little-endian message with ``height = 1``; multi-dimensional
  sub-array fields are flattened into one ``count``.
* Values are copied byte for byte, also when the byte order is swapped, so NaN payloads and
  signalling NaNs survive a round trip unchanged.
"""

from __future__ import annotations

import dataclasses
import sys
from array import array
from types import SimpleNamespace
from typing import Any, Callable, Sequence

import numpy as np

from uncertain_facade_map.errors import InputError

#: ``sensor_msgs/msg/PointField`` datatype constant -> numpy type (without byte order).
POINTFIELD_TYPES: dict[int, str] = {
    1: 'i1',  # INT8
    2: 'u1',  # UINT8
    3: 'i2',  # INT16
    4: 'u2',  # UINT16
    5: 'i4',  # INT32
    6: 'u4',  # UINT32
    7: 'f4',  # FLOAT32
    8: 'f8',  # FLOAT64
}

#: numpy ``(kind, itemsize)`` -> ``PointField`` datatype constant.
_DATATYPE_OF: dict[tuple[str, int], int] = {
    (np.dtype(t).kind, np.dtype(t).itemsize): code for code, t in POINTFIELD_TYPES.items()
}

_HOST_LITTLE = sys.byteorder == 'little'

#: A PointField as plain values: (name, offset in bytes, datatype constant, count).
FieldSpec = tuple[str, int, int, int]


# --------------------------------------------------------------------------------------
# helpers
# --------------------------------------------------------------------------------------


def _is_little(dt: np.dtype) -> bool:
    """True if the scalar dtype ``dt`` stores its bytes little endian (or has one byte)."""
    order = dt.byteorder
    return order in ('<', '|') or (order == '=' and _HOST_LITTLE)


def _uint8_buffer(data: Any) -> np.ndarray:
    """Return ``data`` as a 1-D uint8 array without a per-element Python loop.

    Args:
        data: bytes, bytearray, memoryview, ``array.array('B')``, a numpy array of bytes,
            or a sequence of ints in 0..255.

    Returns:
        1-D uint8 array (possibly a read-only view of ``data``).

    Raises:
        InputError: ``data`` is not a sequence of bytes.
    """
    try:
        view = memoryview(data)
    except TypeError:
        view = None
    if view is not None and view.itemsize == 1 and view.c_contiguous:
        return np.frombuffer(view.cast('B') if view.ndim != 1 else view, dtype=np.uint8)
    try:
        arr = np.asarray(data)
    except (TypeError, ValueError) as err:
        raise InputError(f'PointCloud2 data is not a byte sequence: {err}') from None
    if arr.dtype == np.uint8:
        return arr.reshape(-1)
    if arr.size == 0:
        return np.zeros(0, dtype=np.uint8)
    if arr.dtype.kind not in 'iub':
        raise InputError(f'PointCloud2 data must hold bytes, got values of type {arr.dtype}')
    if int(arr.min()) < 0 or int(arr.max()) > 255:
        raise InputError('PointCloud2 data holds values outside 0..255')
    return arr.astype(np.uint8).reshape(-1)


def _repack(
    raw: np.ndarray,
    moves: Sequence[tuple[int, int, int, int, bool]],
    itemsize: int,
) -> np.ndarray:
    """Copy byte columns of records into a new packed record buffer.

    Args:
        raw: (N, stride) uint8, one record a row.
        moves: per field ``(src_offset, dst_offset, element_size, count, swap)``; ``swap``
            reverses the bytes of every element (byte-order change, bit exact).
        itemsize: bytes per output record.

    Returns:
        (N, itemsize) uint8, C-contiguous.
    """
    n = raw.shape[0]
    out = np.zeros((n, itemsize), dtype=np.uint8)
    for src, dst, size, count, swap in moves:
        nbytes = size * count
        cols = raw[:, src:src + nbytes]
        if swap and size > 1:
            cols = cols.reshape(n, count, size)[:, :, ::-1].reshape(n, nbytes)
        out[:, dst:dst + nbytes] = cols
    return out


# --------------------------------------------------------------------------------------
# decoding
# --------------------------------------------------------------------------------------


def structured_from_pointcloud2(msg: Any) -> np.ndarray:
    """Decode a PointCloud2 message into a packed structured array.

    Reads ``msg.fields[i].name/offset/datatype/count``, ``msg.point_step``,
    ``msg.row_step``, ``msg.width``, ``msg.height``, ``msg.is_bigendian`` and ``msg.data``
    (bytes, bytearray, ``array.array('B')``, a list of ints or a uint8 numpy array).

    Args:
        msg: a ``sensor_msgs/msg/PointCloud2`` of any implementation (rclpy, rosbags, ...).

    Returns:
        Structured array, shape (height * width,), rows first; one field per PointField in
        message order, native byte order, packed (no padding); a field with ``count > 1``
        is a sub-array field of shape (count,). The array owns its memory.

    Raises:
        InputError: no fields, a duplicate or empty field name, an unknown datatype, a
            count below 1, a field running past ``point_step``, ``row_step`` shorter than
            ``width * point_step``, or ``len(data) != row_step * height``.
    """
    height, width = int(msg.height), int(msg.width)
    point_step, row_step = int(msg.point_step), int(msg.row_step)
    big = bool(msg.is_bigendian)
    if height < 0 or width < 0 or point_step < 0 or row_step < 0:
        raise InputError(
            f'PointCloud2 has a negative size (height {height}, width {width}, '
            f'point_step {point_step}, row_step {row_step})'
        )

    specs: list[FieldSpec] = [
        (str(f.name), int(f.offset), int(f.datatype), int(f.count)) for f in msg.fields
    ]
    if not specs:
        raise InputError('PointCloud2 has no fields')
    names = [s[0] for s in specs]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise InputError(f'PointCloud2 has duplicate field names: {", ".join(dup)}')

    packed: list[tuple[str, np.dtype]] = []
    moves: list[tuple[int, int, int, int, bool]] = []
    dst = 0
    for name, offset, datatype, count in specs:
        if not name:
            raise InputError('PointCloud2 has a field with an empty name')
        if datatype not in POINTFIELD_TYPES:
            raise InputError(
                f'PointCloud2 field {name!r} has unknown datatype {datatype} '
                f'(known: 1..8 = INT8, UINT8, INT16, UINT16, INT32, UINT32, FLOAT32, FLOAT64)'
            )
        if count < 1:
            raise InputError(f'PointCloud2 field {name!r} has count {count}, must be at least 1')
        base = np.dtype(POINTFIELD_TYPES[datatype])
        end = offset + base.itemsize * count
        if offset < 0 or end > point_step:
            raise InputError(
                f'PointCloud2 field {name!r} spans bytes {offset}..{end} '
                f'but point_step is {point_step}'
            )
        packed.append((name, base if count == 1 else np.dtype((base, (count,)))))
        swap = big == _HOST_LITTLE and base.itemsize > 1
        moves.append((offset, dst, base.itemsize, count, swap))
        dst += base.itemsize * count
    out_dtype = np.dtype(packed)

    if row_step < width * point_step:
        raise InputError(
            f'PointCloud2 row_step {row_step} is shorter than width {width} * '
            f'point_step {point_step}'
        )
    buf = _uint8_buffer(msg.data)
    if buf.size != row_step * height:
        raise InputError(
            f'PointCloud2 data has {buf.size} bytes, expected row_step {row_step} * '
            f'height {height} = {row_step * height}'
        )

    n = height * width
    if n == 0:
        return np.zeros(0, dtype=out_dtype)
    rows = buf.reshape(height, row_step)[:, :width * point_step]
    raw = rows.reshape(n, point_step)
    return _repack(raw, moves, out_dtype.itemsize).reshape(-1).view(out_dtype)


# --------------------------------------------------------------------------------------
# encoding
# --------------------------------------------------------------------------------------


def _field_layout(dtype: np.dtype) -> list[tuple[str, int, np.dtype, int, int]]:
    """Per field ``(name, src_offset, base_dtype, count, datatype)``, in dtype order.

    Raises:
        InputError: not a structured dtype, or a field type PointCloud2 cannot hold.
    """
    dtype = np.dtype(dtype)
    if dtype.names is None:
        raise InputError(f'PointCloud2 needs a structured dtype, got {dtype}')
    if not dtype.names:
        raise InputError('PointCloud2 needs at least one field')
    out = []
    for name in dtype.names:
        fdtype, offset = dtype.fields[name][:2]
        base = fdtype.base
        count = int(np.prod(fdtype.shape, dtype=np.int64)) if fdtype.shape else 1
        code = _DATATYPE_OF.get((base.kind, base.itemsize)) if base.names is None else None
        if code is None:
            raise InputError(
                f'field {name!r} of type {fdtype} has no PointField datatype '
                f'(supported: i1, u1, i2, u2, i4, u4, f4, f8)'
            )
        if count < 1:
            raise InputError(f'field {name!r} has an empty sub-array shape {fdtype.shape}')
        out.append((name, int(offset), base, count, code))
    return out


def pointcloud2_fields(dtype: np.dtype) -> list[FieldSpec]:
    """Return the PointFields that :func:`pointcloud2_from_structured` writes for ``dtype``.

    Fields are in dtype order and packed: each offset is the sum of the sizes before it
    (padding of a padded dtype is dropped). A sub-array field gets ``count`` = number of
    its elements.

    Args:
        dtype: a structured dtype with fields of types i1, u1, i2, u2, i4, u4, f4, f8
            (any byte order), optionally sub-arrays of these.

    Returns:
        ``[(name, offset_bytes, datatype, count), ...]`` with ``datatype`` the
        ``sensor_msgs/msg/PointField`` constant (INT8=1 ... FLOAT64=8).

    Raises:
        InputError: ``dtype`` is not structured, has no fields, or has a field of another
            type (e.g. bool, int64, float16, nested records, strings).
    """
    specs = []
    offset = 0
    for name, _src, base, count, code in _field_layout(dtype):
        specs.append((name, offset, code, count))
        offset += base.itemsize * count
    return specs


def _data_encoder(msg_types: Any) -> Callable[[np.ndarray], Any]:
    """Return the function turning packed uint8 bytes into the ``data`` value of a message.

    Uses ``msg_types.encode_data`` when given; otherwise a numpy array for dataclass message
    classes (rosbags) and ``array.array('B')`` for others (rclpy).
    """
    encode = getattr(msg_types, 'encode_data', None)
    if encode is not None:
        return encode
    if dataclasses.is_dataclass(msg_types.PointCloud2):
        return _encode_numpy
    return _encode_array


def _encode_numpy(data: np.ndarray) -> np.ndarray:
    """Return ``data`` as a 1-D uint8 numpy array (rosbags' type for ``uint8[]``)."""
    return np.ascontiguousarray(data, dtype=np.uint8).reshape(-1)


def _encode_array(data: np.ndarray) -> array:
    """Return ``data`` as ``array.array('B')`` (rclpy's type for ``uint8[]``), one copy."""
    out = array('B')
    out.frombytes(np.ascontiguousarray(data, dtype=np.uint8).reshape(-1))
    return out


def pointcloud2_from_structured(
    points: np.ndarray,
    *,
    stamp_ns: int,
    frame_id: str,
    msg_types: Any,
) -> Any:
    """Build a PointCloud2 message from a structured array.

    The message has ``height = 1``, ``width = N``, little-endian packed data with the
    fields of :func:`pointcloud2_fields`, ``point_step`` = the packed record size and
    ``is_dense`` True when no x, y or z value (those present) is NaN or infinite.

    Args:
        points: structured array, shape (N,), fields as accepted by
            :func:`pointcloud2_fields`.
        stamp_ns: header stamp, integer nanoseconds since the UNIX epoch, 0 <= stamp_ns <
            2**31 s.
        frame_id: header frame id.
        msg_types: object with attributes ``PointCloud2``, ``PointField``, ``Header`` and
            ``Time`` (message classes or factories taking keyword arguments), and
            optionally ``encode_data`` (uint8 array -> value of ``data``); see
            :func:`rosbags_types` and :func:`rclpy_types`.

    Returns:
        A ``PointCloud2`` instance of ``msg_types.PointCloud2``.

    Raises:
        InputError: ``points`` is not a 1-D structured array, has an unsupported field,
            or ``stamp_ns`` is out of range.
    """
    if not isinstance(points, np.ndarray) or points.dtype.names is None or points.ndim != 1:
        raise InputError('PointCloud2 needs a one-dimensional structured array of points')
    stamp_ns = int(stamp_ns)
    sec, nanosec = divmod(stamp_ns, 1_000_000_000)
    if not 0 <= sec < 2**31:
        raise InputError(f'stamp {stamp_ns} ns is outside 0 .. 2**31 s')

    layout = _field_layout(points.dtype)
    specs = pointcloud2_fields(points.dtype)
    point_step = sum(base.itemsize * count for _n, _o, base, count, _c in layout)
    n = points.shape[0]

    src = np.ascontiguousarray(points)
    raw = src.view(np.uint8).reshape(n, src.dtype.itemsize) if n else np.zeros(
        (0, src.dtype.itemsize), np.uint8)
    moves = [
        (src_off, spec[1], base.itemsize, count, not _is_little(base))
        for (_n, src_off, base, count, _c), spec in zip(layout, specs)
    ]
    data = _repack(raw, moves, point_step).reshape(-1)

    dense = True
    for name in ('x', 'y', 'z'):
        if name in points.dtype.names and points.dtype[name].kind == 'f' and n:
            if not np.isfinite(points[name]).all():
                dense = False

    t = msg_types
    fields = [
        t.PointField(name=name, offset=int(offset), datatype=int(code), count=int(count))
        for name, offset, code, count in specs
    ]
    return t.PointCloud2(
        header=t.Header(stamp=t.Time(sec=int(sec), nanosec=int(nanosec)), frame_id=str(frame_id)),
        height=1,
        width=int(n),
        fields=fields,
        is_bigendian=False,
        point_step=int(point_step),
        row_step=int(point_step * n),
        data=_data_encoder(t)(data),
        is_dense=dense,
    )


# --------------------------------------------------------------------------------------
# message-class namespaces
# --------------------------------------------------------------------------------------


def rosbags_types(typestore: Any = None) -> SimpleNamespace:
    """Message classes of a rosbags typestore, for :func:`pointcloud2_from_structured`.

    Args:
        typestore: a ``rosbags.typesys`` typestore; None for ``Stores.ROS2_JAZZY``. With a
            ROS 1 store (Header has ``seq``) ``Header`` is wrapped to set ``seq=0``.

    Returns:
        Namespace with ``PointCloud2``, ``PointField``, ``Header``, ``Time``,
        ``PointStamped``, ``Point``, ``encode_data`` (uint8 numpy array, as rosbags
        expects) and ``typestore``.

    Raises:
        InputError: the typestore lacks one of the message types.
    """
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_JAZZY) if typestore is None else typestore
    names = {
        'PointCloud2': 'sensor_msgs/msg/PointCloud2',
        'PointField': 'sensor_msgs/msg/PointField',
        'Header': 'std_msgs/msg/Header',
        'Time': 'builtin_interfaces/msg/Time',
        'PointStamped': 'geometry_msgs/msg/PointStamped',
        'Point': 'geometry_msgs/msg/Point',
    }
    try:
        classes = {key: store.types[msgtype] for key, msgtype in names.items()}
    except KeyError as err:
        raise InputError(f'typestore has no message type {err.args[0]}') from None
    classes['Header'] = header_maker(classes['Header'])
    return SimpleNamespace(**classes, encode_data=_encode_numpy, typestore=store)


def header_maker(header_cls: Any) -> Any:
    """A rosbags typestore's ``std_msgs/msg/Header`` class, or for ROS 1 (whose header has a
    sequence number) a maker that sets ``seq=0``, so that builders call it alike."""
    if 'seq' not in {f.name for f in dataclasses.fields(header_cls)}:
        return header_cls

    def ros1_header(**kwargs: Any) -> Any:
        kwargs.setdefault('seq', 0)
        return header_cls(**kwargs)

    return ros1_header


def rclpy_types() -> SimpleNamespace:
    """Message classes of rclpy (ROS 2 Python), for :func:`pointcloud2_from_structured`.

    The ROS 2 message packages are imported here, lazily, so that this module loads
    without a ROS 2 installation.

    Returns:
        Namespace with ``PointCloud2``, ``PointField``, ``Header``, ``Time``,
        ``PointStamped``, ``Point`` and ``encode_data`` (``array.array('B')``, as rclpy
        stores ``uint8[]``).

    Raises:
        ImportError: the ROS 2 message packages are not installed.
    """
    from builtin_interfaces.msg import Time
    from geometry_msgs.msg import Point, PointStamped
    from sensor_msgs.msg import PointCloud2, PointField
    from std_msgs.msg import Header

    return SimpleNamespace(
        PointCloud2=PointCloud2,
        PointField=PointField,
        Header=Header,
        Time=Time,
        PointStamped=PointStamped,
        Point=Point,
        encode_data=_encode_array,
    )
