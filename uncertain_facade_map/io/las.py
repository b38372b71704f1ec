"""Reading and writing clouds as LAS and LAZ files (ASPRS LAS 1.0-1.4; LAZ through ``laspy`` with ``lazrs``).

The map origin of a read cloud is the header *offset* (the file's own georeference
anchor), so x, y, z (float64, metres) are the integer coordinates times the scale,
exact to the file's quantum and, as writers put the offset near the data, small enough
for float32 downstream. Every other point dimension, standard or extra bytes, becomes
a field of its own type, with two renames: ``classification`` becomes ``class`` and
``gps_time`` becomes ``time`` (values unchanged: ``time`` then holds the file's GPS
time, not UNIX time), each unless the file has an extra dimension of that name already. ASPRS class 6 is *building*, whereas the
default ``input.building_classes`` is ``[1]`` (the simulator's convention): for LAS input
set ``input.building_classes: [6]``. :func:`write_las` writes LAS 1.4 point format 6
with scale 0.0001 m and offset = map origin: **coordinates are quantised to 0.1 mm**;
other fields go into the standard dimensions where they fit loss-free (see there) and
into extra bytes otherwise, so fields come back exactly (standard dimensions with the
LAS type, e.g. ``class`` as u1).

Every failure a user can cause (missing file, corrupt or truncated file, unsupported
field type) raises :class:`InputError` with a one-line message. laspy is imported only
when a LAS/LAZ file is read or written. The suffixes ``.las`` and ``.laz`` are dispatched
here by :mod:`~uncertain_facade_map.io.clouds`.
"""

from __future__ import annotations

import os
import struct
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from ..errors import InputError
from ._files import _COORDINATES, PathLike, _existing_file, _one_line
from .cloud import Cloud

__all__ = ['LAS_EXTRA_TYPES', 'LAS_POINT_FORMAT', 'LAS_RENAMES', 'LAS_SCALE', 'LAS_VERSION', 'read_las',
           'write_las']

#: Quantum of the coordinates written by :func:`write_las`, metres (0.1 mm).
LAS_SCALE = 1e-4
#: LAS point format and version written by :func:`write_las`.
LAS_POINT_FORMAT = 6
LAS_VERSION = '1.4'
#: Renames applied by :func:`read_las` (LAS dimension -> field) and undone by :func:`write_las`.
LAS_RENAMES = {'classification': 'class', 'gps_time': 'time'}
#: numpy types LAS extra bytes can hold (bool fields are written as u1).
LAS_EXTRA_TYPES = ('i1', 'u1', 'i2', 'u2', 'i4', 'u4', 'i8', 'u8', 'f4', 'f8')

#: Names a field cannot have in a LAS file written by :func:`write_las` (the raw coordinates).
_LAS_RESERVED = ('X', 'Y', 'Z')
_LAS_EXTRA_NAME_BYTES = 32
#: Points read per laspy call (bounds the memory a damaged point count can claim).
_LAS_CHUNK_POINTS = 1 << 20


def _import_laspy(name: str) -> Any:
    """Import laspy lazily; raise InputError if it is not installed."""
    try:
        import laspy
    except ImportError as exc:
        raise InputError(f'cannot handle {name}: LAS/LAZ files need laspy and lazrs '
                         f'({_one_line(exc)})') from exc
    return laspy


def _check_las_header(name: str) -> None:
    """Refuse LAS headers whose counts cannot fit the file, before laspy trusts them.

    laspy reads as many VLRs and EVLRs as the header announces, one by one, even past the
    end of the file (a damaged count takes hours), and logs rather than raises when an
    uncompressed file holds fewer points than announced. Files that are no LAS at all are
    left to laspy, which reports them.

    Raises:
        InputError: more VLRs (54 bytes each) or EVLRs (60 bytes each) than the file has
            bytes for, or an uncompressed file too short for its announced points.
    """
    size = os.path.getsize(name)
    try:
        with open(name, 'rb') as stream:
            head = stream.read(255)
    except OSError as exc:
        raise InputError(f'cannot read LAS file {name}: {_one_line(exc)}') from exc
    if len(head) < 227 or head[:4] != b'LASF':
        return
    offset, n_vlrs = struct.unpack_from('<II', head, 96)
    format_id, record_length, count = struct.unpack_from('<BHI', head, 104)
    n_evlrs = 0
    if head[25] >= 4 and len(head) >= 255:  # LAS 1.4: EVLRs and a 64-bit point count
        n_evlrs, count = struct.unpack_from('<IQ', head, 243)
    compressed = format_id & 0xC0 == 0x80  # laspy's test: bit 7 set, bit 6 clear
    problem = ''
    if n_vlrs * 54 > size:
        problem = f'header announces {n_vlrs} VLRs, more than the file of {size} bytes can hold'
    elif n_evlrs * 60 > size:
        problem = f'header announces {n_evlrs} EVLRs, more than the file of {size} bytes can hold'
    elif not compressed and offset + count * record_length > size:
        problem = (f'header announces {count} points of {record_length} bytes from byte {offset}, '
                   f'the file is truncated at {size} bytes')
    elif compressed:
        chunks = _laz_chunk_count(name, offset, size)
        if chunks is not None and chunks * 20 > size:
            problem = (f'LAZ chunk table announces {chunks} chunks, more than the file of {size} '
                       'bytes can hold')
    if problem:
        raise InputError(f'cannot read LAS file {name}: {problem}')


def _laz_chunk_count(name: str, offset: int, size: int) -> int | None:
    """The number of chunks a LAZ chunk table announces, or None if there is no table.

    lazrs allocates 16 bytes per announced chunk before reading any, and a failed
    allocation aborts the process; a real chunk holds at least one raw point of 20 or
    more bytes, which bounds the count by the file size.
    """
    try:
        with open(name, 'rb') as stream:
            stream.seek(offset)
            raw = stream.read(8)
            if len(raw) < 8:
                return None
            start = struct.unpack('<q', raw)[0]
            if start == -1 and size >= 8:  # written by a streaming writer: offset at the end
                stream.seek(size - 8)
                start = struct.unpack('<q', stream.read(8))[0]
            if not 0 < start <= size - 8:
                return None
            stream.seek(start)
            _version, chunks = struct.unpack('<II', stream.read(8))
    except (OSError, struct.error) as exc:
        raise InputError(f'cannot read LAS file {name}: {_one_line(exc)}') from exc
    return chunks


def _las_errors(laspy: Any) -> tuple[type[BaseException], ...]:
    """What laspy and lazrs raise for unreadable files.

    LaspyException and its subclasses (bad signature, unsupported version or point format,
    incoherent sizes), RuntimeError (lazrs.LazrsError: corrupt or truncated LAZ data, which
    laspy does not wrap; lazrs panics come as pyo3's PanicException, a BaseException,
    handled where this is used), ValueError (inconsistent header and VLR
    sizes, buffers too short for the announced points, bad extra-bytes types), EOFError
    and struct.error (truncated header), OSError (I/O), IndexError and KeyError (malformed
    VLRs), MemoryError and OverflowError (absurd point counts).
    """
    return (laspy.errors.LaspyException, RuntimeError, ValueError, EOFError, struct.error,
            OSError, IndexError, KeyError, MemoryError, OverflowError)


def read_las(path: PathLike) -> Cloud:
    """Read a LAS or LAZ file (any LAS version and point format laspy knows) as a cloud.

    The map origin is the header offset, the file's own georeference anchor: x, y, z are
    the stored integer coordinates times the header scale (float64, metres, map frame;
    divided by 1/scale where that is an integer, so that they round correctly),
    so georeferenced = map + origin, exact to the file's quantum, and float32 copies keep
    millimetres wherever the offset lies near the data (as LAS writers arrange).

    Every other dimension (standard ones such as intensity, return_number, scan_angle,
    point_source_id, red/green/blue, and every extra-bytes dimension) becomes a field of
    its laspy type, in file order; bit fields and flags become u1, scaled extra bytes
    float64 (scaled values), and array extra bytes ``name`` of length k become ``name_0``
    .. ``name_{k-1}``. Two dimensions are renamed to the names the mapper reads:
    ``classification`` -> ``class`` (u1) and ``gps_time`` -> ``time`` (f8, the file's GPS
    time unchanged, not UNIX time); each rename is skipped if the file has an extra
    dimension with the new name already. Nothing is dropped, so the reading is loss-free.

    ASPRS class 6 is *building*; the default configuration's ``input.building_classes``
    is ``[1]`` (the simulator's convention), so for LAS input set
    ``input.building_classes: [6]``.

    LAZ is decompressed with lazrs' sequential decoder: its parallel one aborts the whole
    process on some damaged files. A LAZ file damaged inside its compressed data can
    still make lazrs allocate (up to 4 GiB per layer) before it fails.

    Args:
        path: ``.las`` or ``.laz`` file.

    Returns:
        The cloud: packed native structured points with x, y, z (f8, metres, map frame)
        first, then the other dimensions; map origin (3,) = header offsets, metres.

    Raises:
        InputError: missing, corrupt or truncated file, unsupported version or point
            format, non-finite header offsets, or laspy (or lazrs for LAZ) not installed.
    """
    name = _existing_file(path)
    laspy = _import_laspy(name)
    _check_las_header(name)
    try:
        with laspy.open(name, laz_backend=laspy.LazBackend.Lazrs) as reader:
            scales = np.array(reader.header.scales, dtype=np.float64)
            offsets = np.array(reader.header.offsets, dtype=np.float64)
            announced = int(reader.header.point_count)
            dims = list(reader.header.point_format.dimension_names)
            chunks: list[dict[str, np.ndarray]] = []
            left = announced
            while left > 0:  # in chunks: memory follows the data, not the header's count
                record = reader.read_points(min(left, _LAS_CHUNK_POINTS))
                if len(record) == 0:
                    break
                chunks.append({dim: np.asarray(record[dim]) for dim in dims})
                left -= len(record)
            if not chunks:
                record = reader.read_points(0)
                chunks.append({dim: np.asarray(record[dim]) for dim in dims})
    except BaseException as exc:  # noqa: B036 - lazrs panics raise pyo3's PanicException
        if not isinstance(exc, _las_errors(laspy)) and type(exc).__name__ != 'PanicException':
            raise
        raise InputError(f'cannot read LAS file {name}: {_one_line(exc)}') from exc
    columns = {dim: np.concatenate([c[dim] for c in chunks]) for dim in dims}
    n = int(columns['X'].shape[0])
    if n != announced:
        raise InputError(f'cannot read LAS file {name}: header announces {announced} points, '
                         f'the file holds {n}')
    return _las_cloud(name, columns, dims, scales, offsets)


def iter_las(path: PathLike, chunk_points: int = _LAS_CHUNK_POINTS,
             bounds: tuple[float, float, float, float] | None = None) -> Iterator[Cloud]:
    """A LAS or LAZ file as clouds of at most ``chunk_points`` points each, in file order (the
    fields and map origin of :func:`read_las`); a COPC file (``.copc.laz``) with ``bounds``
    (min_x, min_y, max_x, max_y, georeferenced metres) yields only the points of the octree
    nodes that meet them (laspy's ``CopcReader.query``; points just outside may come too).

    Raises:
        InputError: as :func:`read_las`.
    """
    name = _existing_file(path)
    laspy = _import_laspy(name)
    _check_las_header(name)
    try:
        if bounds is not None and name.lower().endswith('.copc.laz'):
            from laspy.copc import Bounds, CopcReader

            with CopcReader.open(name) as reader:
                header = reader.header
                dims = list(header.point_format.dimension_names)
                area = _storable_area(bounds, np.array(header.scales, np.float64),
                                      np.array(header.offsets, np.float64))
                record = (laspy.ScaleAwarePointRecord.zeros(0, header=header) if area is None else
                          reader.query(bounds=Bounds(mins=area[:2], maxs=area[2:])))
                columns = {dim: np.asarray(record[dim]) for dim in dims}
                yield _las_cloud(name, columns, dims, np.array(header.scales, np.float64),
                                 np.array(header.offsets, np.float64))
            return
        with laspy.open(name, laz_backend=laspy.LazBackend.Lazrs) as reader:
            scales = np.array(reader.header.scales, dtype=np.float64)
            offsets = np.array(reader.header.offsets, dtype=np.float64)
            dims = list(reader.header.point_format.dimension_names)
            for record in reader.chunk_iterator(chunk_points):
                if len(record) == 0:
                    break
                columns = {dim: np.asarray(record[dim]) for dim in dims}
                yield _las_cloud(name, columns, dims, scales, offsets)
    except BaseException as exc:  # noqa: B036 - lazrs panics raise pyo3's PanicException
        if not isinstance(exc, _las_errors(laspy)) and type(exc).__name__ != 'PanicException':
            raise
        raise InputError(f'cannot read LAS file {name}: {_one_line(exc)}') from exc


def _storable_area(bounds: tuple[float, float, float, float], scales: np.ndarray,
                   offsets: np.ndarray) -> np.ndarray | None:
    """``bounds`` (min_x, min_y, max_x, max_y, georeferenced metres) cut to the x, y a LAS file of
    these header ``scales`` and ``offsets`` can store (int32 coordinates: offset + scale *
    [-(2^31 - 1), 2^31 - 1]), as (4,) float64, or None if they do not meet it.

    laspy's COPC query turns its bounds into int32 coordinates without a check: bounds reaching
    past that range (past 214 km from the offset at a 0.1 mm scale, e.g. ``0,0,1e7,1e7``)
    overflow, and the query returns no point at all. No point lies outside the range, so the
    cut bounds select the same points.
    """
    reach = np.abs(scales[:2]) * (2.0**31 - 1)
    low = np.maximum(np.asarray(bounds[:2], np.float64), offsets[:2] - reach)
    high = np.minimum(np.asarray(bounds[2:], np.float64), offsets[:2] + reach)
    if np.any(low > high):
        return None
    return np.concatenate([low, high])


def _las_cloud(name: str, columns: dict[str, np.ndarray], dims: list[str], scales: np.ndarray,
               offsets: np.ndarray) -> Cloud:
    """The cloud of LAS columns (see :func:`read_las`)."""
    n = int(columns['X'].shape[0])
    fields: list[tuple[str, np.ndarray]] = [
        (c, _las_unscale(columns[c.upper()], scales[i])) for i, c in enumerate(_COORDINATES)
    ]
    taken = set(dims)
    for dim in dims:
        if dim in _LAS_RESERVED:
            continue
        values = columns[dim]
        if values.dtype.kind == 'b':
            values = values.astype(np.uint8)
        values = values.astype(values.dtype.newbyteorder('='), copy=False)
        target = LAS_RENAMES.get(dim, dim)
        if target != dim and target in taken:
            target = dim
        if values.ndim == 1:
            fields.append((target, values))
        else:
            values = values.reshape(n, int(np.prod(values.shape[1:])))
            fields.extend((f'{target}_{k}', values[:, k]) for k in range(values.shape[1]))
    names = [f for f, _ in fields]
    clash = sorted({f for f in names if names.count(f) > 1})
    if clash:
        raise InputError(f'{name}: LAS dimensions give the field name {", ".join(clash)} twice')
    points = np.empty(n, dtype=np.dtype([(f, v.dtype) for f, v in fields]))
    for f, v in fields:
        points[f] = v
    try:
        return Cloud(points, offsets)
    except InputError as exc:
        raise InputError(f'{name}: {exc}') from None


def _las_unscale(raw: np.ndarray, scale: float) -> np.ndarray:
    """Integer LAS coordinates times ``scale``, float64.

    For the usual decimal scales (0.01, 0.001, 0.0001: 1/scale an integer) this divides by
    1/scale instead, which rounds correctly: 12346 at scale 0.0001 gives 1.2346, not
    1.2346000000000001.
    """
    values = raw.astype(np.float64)
    inverse = 1.0 / scale if scale != 0 else 0.0
    if np.isfinite(inverse) and inverse >= 1 and abs(inverse - round(inverse)) <= 1e-9 * inverse:
        return values / round(inverse)
    return values * scale


def _las_fits(values: np.ndarray, dim: Any) -> bool:
    """True if ``values`` (1-D) go into the standard LAS dimension ``dim`` without loss."""
    kind = values.dtype.kind
    if kind not in 'iuf' or values.ndim != 1:
        return False
    if dim.dtype is not None and np.dtype(dim.dtype).kind == 'f':
        if kind == 'f' and np.any((values == 0) & np.signbit(values)):
            return False  # the LAZ GPS-time codec does not keep the sign of zero; use extra bytes
        if kind == 'f':
            return values.dtype.itemsize <= 8
        return values.dtype.itemsize <= 4 or bool(
            np.array_equal(values.astype(np.float64).astype(values.dtype), values))
    if values.size == 0:
        return True
    if kind == 'f' and not (np.isfinite(values).all() and np.array_equal(values, np.trunc(values))):
        return False
    return bool(values.min() >= dim.min and values.max() <= dim.max)


def write_las(path: PathLike, cloud: Cloud, *, compress: bool | None = None) -> None:
    """Write a cloud as a LAS 1.4 file with point format 6, or as LAZ.

    The header offset is the map origin and the scale :data:`LAS_SCALE` (0.0001 m) on
    every axis: LAS stores integer coordinates, so x, y, z are **quantised to 0.1 mm**
    (rounded to the nearest multiple) and must lie within +-214 km of the map origin.
    The other fields are stored loss-free:

    * a field named like a standard dimension of point format 6 (``intensity``,
      ``return_number``, ``classification``, ``user_data``, ``scan_angle``,
      ``point_source_id``, ``gps_time``, ...) goes into that dimension and must fit it
      (integer values in its range; any float or small integer for ``gps_time``);
    * ``class`` goes into ``classification`` and ``time`` into ``gps_time`` (the
      reverse of :func:`read_las`' renames) if the cloud has no field of the LAS name and
      the values fit, else they become extra bytes under their own names;
    * every other field becomes an extra-bytes dimension of its own type (i1, u1, i2, u2,
      i4, u4, i8, u8, f4, f8; bool as u1), bit for bit.

    Reading the file back gives x, y, z within 0.05 mm, the fields above with the
    standard dimensions' types, and every standard dimension the cloud did not have, as
    zeros. ``time`` is copied into ``gps_time`` unchanged (other LAS tools will take it
    for GPS time).

    Args:
        path: file to write; replaced if it exists.
        cloud: the cloud to write.
        compress: write LAZ (lazrs); by default if the suffix is ``.laz``.

    Raises:
        InputError: coordinates that LAS cannot store (NaN, infinite, too far from the map
            origin), a field that fits neither its standard dimension nor extra bytes
            (type, sub-array, name longer than 32 bytes or not ASCII, or named X, Y, Z),
            laspy/lazrs not installed, or the file cannot be written.
    """
    name = os.fspath(path)
    if compress is None:
        compress = Path(name).suffix.lower() == '.laz'
    points = cloud.points
    n = len(cloud)
    quantised: list[np.ndarray] = []
    for c in _COORDINATES:
        with np.errstate(invalid='ignore', over='ignore'):
            q = np.rint(points[c].astype(np.float64) / LAS_SCALE)
            bad = ~(np.isfinite(q) & (q >= -2**31) & (q <= 2**31 - 1))
        if bad.any():
            raise InputError(f'cannot write {name}: {int(bad.sum())} of {n} points have a {c} '
                             'that LAS cannot store (NaN, infinite, or over 214 km from the map origin)')
        quantised.append(q.astype(np.int32))

    laspy = _import_laspy(name)
    standard = {d.name: d for d in laspy.PointFormat(LAS_POINT_FORMAT).dimensions}
    renames = {v: k for k, v in LAS_RENAMES.items()}  # class -> classification, time -> gps_time
    into_standard: dict[str, np.ndarray] = {}
    extra: list[tuple[str, np.dtype]] = []
    for f in cloud.fields:
        if f in _COORDINATES:
            continue
        values = points[f]
        if values.dtype.kind == 'b':
            values = values.astype(np.uint8)
        if f in _LAS_RESERVED:
            raise InputError(f'cannot write {name}: field name {f!r} is reserved in LAS (raw coordinates)')
        if f in standard:
            if not _las_fits(values, standard[f]):
                dim = standard[f]
                rng = 'a float' if dim.dtype is not None and np.dtype(dim.dtype).kind == 'f' \
                    else f'an integer in [{dim.min}, {dim.max}]'
                raise InputError(f'cannot write {name}: field {f!r} ({values.dtype}) does not fit the '
                                 f'LAS dimension {f}, which holds {rng}')
            into_standard[f] = values
            continue
        target = renames.get(f)
        if target is not None and target not in cloud.fields and _las_fits(values, standard[target]):
            into_standard[target] = values
            continue
        code = f'{values.dtype.kind}{values.dtype.itemsize}'
        if values.dtype.subdtype is not None or values.ndim != 1 or code not in LAS_EXTRA_TYPES:
            raise InputError(f'cannot write {name}: field {f!r} has type {points.dtype.fields[f][0]}, '
                             f'which LAS extra bytes cannot store (supported: {", ".join(LAS_EXTRA_TYPES)} and bool)')
        if not f.isascii() or not f.isprintable() or not 0 < len(f) <= _LAS_EXTRA_NAME_BYTES:
            raise InputError(f'cannot write {name}: field name {f!r} cannot be a LAS extra-bytes name '
                             f'(needs 1 to {_LAS_EXTRA_NAME_BYTES} printable ASCII characters)')
        extra.append((f, np.dtype(code)))

    header = laspy.LasHeader(point_format=LAS_POINT_FORMAT, version=LAS_VERSION)
    header.offsets = np.asarray(cloud.map_origin, dtype=np.float64)
    header.scales = np.full(3, LAS_SCALE)
    if extra:
        header.add_extra_dims([laspy.ExtraBytesParams(name=f, type=t) for f, t in extra])
    record = laspy.ScaleAwarePointRecord.zeros(n, header=header)
    for c, q in zip(_COORDINATES, quantised):
        record[c.upper()] = q
    for dim, values in into_standard.items():
        target_type = standard[dim].dtype if standard[dim].dtype is not None else np.uint8
        record[dim] = values.astype(target_type)
    for f, t in extra:
        record[f] = points[f].astype(t)  # native byte order, same type: bit for bit
    las = laspy.LasData(header=header, points=record)
    try:
        las.write(name, do_compress=compress, laz_backend=laspy.LazBackend.Lazrs)
    except (OSError, laspy.errors.LaspyException) as exc:
        raise InputError(f'cannot write {name}: {_one_line(exc)}') from exc

