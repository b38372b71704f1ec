"""Reading and writing :class:`~uncertain_facade_map.io.cloud.Cloud` records as PLY, NPZ, LAS/LAZ and PCD files.

Five suffixes are supported, chosen (case-insensitively) by :func:`read_cloud` and
:func:`write_cloud`: ``.npz``, ``.ply``, ``.las``, ``.laz`` and ``.pcd``.

``.npz`` (numpy archive, never pickled)
    Written as three arrays: ``format`` (the string :data:`NPZ_FORMAT`), ``points`` (the
    structured point array itself) and ``map_origin`` ((3,) float64, metres). This is
    loss-free bit for bit for every structured dtype numpy can store without pickle: any
    field order, byte order, offsets and item size, sub-array fields, NaN payloads. (The
    padding bytes between fields are not data; numpy does not keep them, and a read cloud
    has them zeroed.) :func:`read_npz` also accepts *foreign* archives (see there).

``.ply`` (Stanford polygon file, via ``plyfile``)
    One ``vertex`` element with one scalar property per field, in field order. PLY knows
    the types char/uchar/short/ushort/int/uint/float/double (numpy i1/u1/i2/u2/i4/u4/f4/f8);
    bool fields are written as uchar (0/1) and read back as u1; any other dtype (i8, u8,
    f2, strings, sub-arrays) is refused with an :class:`InputError`. The map origin is
    stored as the header comment ``comment map_origin <x> <y> <z>`` with ``repr`` floats,
    so it is loss-free; a PLY without that comment reads with origin (0, 0, 0).

    Binary PLY (little endian) is loss-free bit for bit for the supported types, except
    that the points come back packed and in native byte order. ASCII PLY (plyfile prints
    every value with ``'%.18g'``) round-trips every finite value, -0.0 and +-inf exactly,
    but a NaN comes back as the canonical quiet NaN: its sign and payload are lost.
    ASCII PLY is also slow (plyfile formats and parses it one line at a time); use it for
    small files and for exchange with tools that need it.

    :func:`read_ply` reads ASCII and binary (little and big endian) files from any tool,
    ignores every element but ``vertex`` (faces, edges, ...) and every list property of
    the vertex element, and returns the fields in native byte order.

``.las`` / ``.laz`` (ASPRS LAS 1.0-1.4, LAZ through ``laspy`` with the ``lazrs`` backend)
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

``.pcd`` (Point Cloud Library format, via ``pypcd4``)
    ``ascii``, ``binary`` and ``binary_compressed`` are read and written. Field types are
    those of PCD (i1/u1/i2/u2/i4/u4/i8/u8/f4/f8; bool is written as u1); PCL padding fields
    named ``_`` are dropped and fields with ``COUNT`` > 1 become ``name__0000``,
    ``name__0001``, ... (pypcd4's naming). PCD has no georeference: the map origin is the
    translation of the ``VIEWPOINT`` header (PCL's viewers draw a cloud shifted by it, and
    it is (0, 0, 0) unless set); :func:`write_pcd` stores the map origin there (``repr``
    floats, loss-free) with the identity rotation. A ``VIEWPOINT`` with a rotation is
    refused rather than silently ignored. Binary encodings are loss-free bit for bit; ASCII
    round-trips every value except NaN sign and payload (floats are printed with 9 / 17
    significant digits, ints exactly).

Every failure a user can cause (missing file, unknown suffix, corrupt or truncated file,
unsupported field type) raises :class:`InputError` with a one-line message. laspy and
pypcd4 are imported only when a LAS/LAZ or PCD file is read or written.
"""

from __future__ import annotations

import os
import re
import struct
import warnings
import zipfile
import zlib
from pathlib import Path
from typing import Any, Union

import numpy as np
from plyfile import PlyData, PlyElement, PlyListProperty, PlyParseError

from ..errors import InputError
from .cloud import Cloud

PathLike = Union[str, 'os.PathLike[str]']

#: Value of the ``format`` array in the NPZ files written by :func:`write_npz`.
NPZ_FORMAT = 'uncertain_facade_map.io.cloud/1'

#: Suffixes understood by :func:`read_cloud` and :func:`write_cloud`.
SUPPORTED_SUFFIXES = ('.npz', '.ply', '.las', '.laz', '.pcd')

#: Quantum of the coordinates written by :func:`write_las`, metres (0.1 mm).
LAS_SCALE = 1e-4
#: LAS point format and version written by :func:`write_las`.
LAS_POINT_FORMAT = 6
LAS_VERSION = '1.4'
#: Renames applied by :func:`read_las` (LAS dimension -> field) and undone by :func:`write_las`.
LAS_RENAMES = {'classification': 'class', 'gps_time': 'time'}
#: numpy types LAS extra bytes can hold (bool fields are written as u1).
LAS_EXTRA_TYPES = ('i1', 'u1', 'i2', 'u2', 'i4', 'u4', 'i8', 'u8', 'f4', 'f8')

#: numpy type code -> (PCD TYPE, SIZE), the types a PCD field can have.
PCD_TYPES = {
    'i1': ('I', 1), 'u1': ('U', 1), 'i2': ('I', 2), 'u2': ('U', 2), 'i4': ('I', 4),
    'u4': ('U', 4), 'i8': ('I', 8), 'u8': ('U', 8), 'f4': ('F', 4), 'f8': ('F', 8),
}
#: PCD data encodings read and written.
PCD_ENCODINGS = ('ascii', 'binary', 'binary_compressed')

#: numpy type code -> PLY type name, the types a PLY vertex property can have.
PLY_TYPES = {
    'i1': 'char', 'u1': 'uchar', 'i2': 'short', 'u2': 'ushort',
    'i4': 'int', 'u4': 'uint', 'f4': 'float', 'f8': 'double',
}

_ORIGIN_COMMENT = 'map_origin'
_COORDINATES = ('x', 'y', 'z')

# What numpy and zipfile raise for unreadable archives: OSError (I/O), ValueError (bad
# header, pickled data, short data), EOFError (truncated member), BadZipFile (broken
# archive), zlib.error (corrupt compressed member), MemoryError (absurd array shape).
_NPZ_ERRORS = (OSError, ValueError, EOFError, zipfile.BadZipFile, zlib.error, MemoryError)
# What plyfile raises for unreadable files: PlyParseError (header or data), ValueError
# (bad type names, duplicate names, negative or huge counts, non-ASCII header via
# UnicodeDecodeError), OverflowError (ASCII value out of range of its type), OSError (I/O),
# MemoryError (an ASCII element count too large to allocate).
_PLY_ERRORS = (PlyParseError, ValueError, OverflowError, OSError, MemoryError)


def read_cloud(path: PathLike) -> Cloud:
    """Read a cloud from a ``.ply``, ``.npz``, ``.las``, ``.laz`` or ``.pcd`` file.

    Args:
        path: file to read; the format is chosen by the suffix, matched case-insensitively.

    Returns:
        The cloud; see :func:`read_ply`, :func:`read_npz`, :func:`read_las` and
        :func:`read_pcd`.

    Raises:
        InputError: unknown suffix, missing, corrupt or unsupported file.
    """
    suffix = _suffix(path)
    if suffix == '.ply':
        return read_ply(path)
    if suffix in ('.las', '.laz'):
        return read_las(path)
    if suffix == '.pcd':
        return read_pcd(path)
    return read_npz(path)


def write_cloud(path: PathLike, cloud: Cloud) -> None:
    """Write a cloud as binary PLY, NPZ, LAS, LAZ or binary PCD, chosen by the suffix.

    Args:
        path: file to write (``.ply``, ``.npz``, ``.las``, ``.laz`` or ``.pcd``,
            case-insensitive); replaced if it exists.
        cloud: the cloud to write.

    Raises:
        InputError: unknown suffix, fields the format cannot store, or the file cannot be
            written.
    """
    suffix = _suffix(path)
    if suffix == '.ply':
        write_ply(path, cloud)
    elif suffix in ('.las', '.laz'):
        write_las(path, cloud)
    elif suffix == '.pcd':
        write_pcd(path, cloud)
    else:
        write_npz(path, cloud)


# --------------------------------------------------------------------------------------
# NPZ


def write_npz(path: PathLike, cloud: Cloud, *, compress: bool = False) -> None:
    """Write a cloud to an NPZ archive, loss-free bit for bit.

    The archive holds ``format`` (0-d string :data:`NPZ_FORMAT`), ``points`` (the
    structured array, shape (N,), as it is) and ``map_origin`` ((3,) float64, metres).
    The file is written under exactly ``path`` (numpy's habit of appending ``.npz`` does
    not apply).

    Args:
        path: file to write; replaced if it exists.
        cloud: the cloud to write.
        compress: deflate the arrays (smaller, slower).

    Raises:
        InputError: the points have object fields (not storable without pickle), or the
            file cannot be written.
    """
    if cloud.points.dtype.hasobject:
        raise InputError('cannot write a cloud with Python-object fields to NPZ')
    save = np.savez_compressed if compress else np.savez
    try:
        with open(path, 'wb') as stream:
            save(stream, format=np.array(NPZ_FORMAT), points=cloud.points,
                 map_origin=np.asarray(cloud.map_origin, dtype=np.float64))
    except OSError as exc:
        raise InputError(f'cannot write {os.fspath(path)}: {_one_line(exc)}') from exc


def read_npz(path: PathLike) -> Cloud:
    """Read a cloud from an NPZ archive (never unpickling anything).

    Three layouts are understood:

    * as written by :func:`write_npz`: ``format``, ``points``, ``map_origin``;
    * a structured 1-D array ``points`` with fields x, y, z (and any others), optionally
      with a (3,) ``map_origin``, and nothing else;
    * a *foreign* archive: an (N, 3) float array ``xyz`` or ``points`` (metres, map
      frame), an optional (3,) float ``map_origin`` and any number of 1-D numeric
      (bool, integer or float) arrays of length N, which become fields after x, y, z in
      archive order. Coordinates keep float32 or float64, other float widths become
      float64.

    Args:
        path: archive to read.

    Returns:
        The cloud, its points in the stored byte order and field order.

    Raises:
        InputError: missing or unreadable file, a ``.npy`` instead of an archive, an
            unsupported ``format``, or arrays that fit none of the layouts (the message
            lists what was found).
    """
    name = _existing_file(path)
    try:
        with open(name, 'rb') as stream:
            loaded = np.load(stream, allow_pickle=False)
            if not isinstance(loaded, np.lib.npyio.NpzFile):
                raise InputError(f'{name}: a single .npy array, not an NPZ archive')
            with loaded:
                arrays = {key: loaded[key] for key in loaded.files}
    except InputError:
        raise
    except _NPZ_ERRORS as exc:
        raise InputError(f'cannot read NPZ file {name}: {_one_line(exc)}') from exc
    return _cloud_from_arrays(arrays, name)


def _cloud_from_arrays(arrays: dict[str, np.ndarray], name: str) -> Cloud:
    """Interpret the arrays of an NPZ archive as a cloud (see :func:`read_npz`)."""
    fmt = arrays.get('format')
    if fmt is not None and fmt.shape == () and fmt.dtype.kind == 'U':
        if str(fmt) != NPZ_FORMAT:
            raise InputError(f'{name}: unsupported format {str(fmt)!r}, expected {NPZ_FORMAT!r}')
        points = arrays.get('points')
        if points is None or points.dtype.names is None:
            raise InputError(f'{name}: format {NPZ_FORMAT!r} but no structured "points" array '
                             f'(found {_describe(arrays)})')
        return Cloud(_zero_padding(points), _origin(arrays, name))

    points = arrays.get('points')
    if points is not None and points.dtype.names is not None:
        extra = sorted(set(arrays) - {'points', 'map_origin'})
        if extra:
            raise InputError(f'{name}: structured "points" with unexpected arrays {", ".join(extra)}')
        return Cloud(_zero_padding(points), _origin(arrays, name))

    candidates = [k for k in ('xyz', 'points') if k in arrays]
    if len(candidates) != 1:
        what = 'both "xyz" and "points"' if candidates else 'no "xyz" or "points" array'
        raise InputError(f'{name}: not a point cloud archive, {what} (found {_describe(arrays)})')
    key = candidates[0]
    xyz = arrays[key]
    if xyz.ndim != 2 or xyz.shape[1] != 3 or xyz.dtype.kind != 'f':
        raise InputError(f'{name}: "{key}" must be an (N, 3) float array, found {_describe({key: xyz})}')
    n = xyz.shape[0]
    coord_type = xyz.dtype if xyz.dtype.itemsize in (4, 8) else np.dtype(np.float64)
    fields: list[tuple[str, np.dtype]] = [(c, coord_type) for c in _COORDINATES]
    others = [k for k in arrays if k not in (key, 'map_origin')]
    for k in others:
        arr = arrays[k]
        if k in _COORDINATES or arr.shape != (n,) or arr.dtype.kind not in 'biuf':
            raise InputError(f'{name}: cannot use {_describe({k: arr})} as a field of {n} points '
                             f'(fields must be 1-D numeric arrays of length N, not named x, y or z)')
        fields.append((k, arr.dtype))
    points = np.empty(n, dtype=np.dtype(fields))
    for i, c in enumerate(_COORDINATES):
        points[c] = xyz[:, i]
    for k in others:
        points[k] = arrays[k]
    return Cloud(points, _origin(arrays, name))


def _zero_padding(points: np.ndarray) -> np.ndarray:
    """``points`` with zeroed padding bytes if its dtype has gaps between fields.

    numpy leaves the padding of a loaded array undefined; zeroing it makes the bytes of a
    read cloud reproducible. The fields are copied bit for bit.
    """
    dtype = points.dtype
    if dtype.itemsize == sum(dtype.fields[n][0].itemsize for n in dtype.names):
        return points
    clean = np.zeros(points.shape, dtype=dtype)
    for fname in dtype.names:
        clean[fname] = points[fname]
    return clean


def _origin(arrays: dict[str, np.ndarray], name: str) -> np.ndarray:
    """The (3,) float64 ``map_origin`` of an archive, zeros if there is none."""
    origin = arrays.get('map_origin')
    if origin is None:
        return np.zeros(3)
    if origin.shape != (3,) or origin.dtype.kind not in 'iuf':
        raise InputError(f'{name}: map_origin must be 3 numbers, found {_describe({"map_origin": origin})}')
    return origin.astype(np.float64)


def _describe(arrays: dict[str, np.ndarray]) -> str:
    """One-line list of array names, shapes and dtypes, for error messages."""
    if not arrays:
        return 'no arrays'
    return ', '.join(f'"{k}" {a.shape} {a.dtype}' for k, a in arrays.items())


# --------------------------------------------------------------------------------------
# PLY


def write_ply(path: PathLike, cloud: Cloud, *, binary: bool = True) -> None:
    """Write a cloud as a PLY file with one ``vertex`` element.

    Every field becomes a scalar vertex property of the same name and type (bool fields
    become uchar 0/1); the map origin becomes the header comment
    ``map_origin <x> <y> <z>`` (``repr`` floats, loss-free). Binary files are little
    endian.

    Args:
        path: file to write; replaced if it exists.
        cloud: the cloud to write.
        binary: binary little endian if True, else ASCII (see the module notes on NaN).

    Raises:
        InputError: a field type PLY cannot store (e.g. i8, u8, f2, strings, sub-arrays),
            a field name PLY cannot hold (empty, whitespace, non-ASCII), or the file cannot
            be written.
    """
    points = cloud.points
    fields: list[tuple[str, str]] = []
    for fname in points.dtype.names:
        ftype = points.dtype.fields[fname][0]
        if not fname or not fname.isascii() or not fname.isprintable() or any(c.isspace() for c in fname):
            raise InputError(f'field name {fname!r} cannot be a PLY property name '
                             '(needs printable ASCII without whitespace)')
        if ftype.kind == 'b':
            code = 'u1'
        else:
            code = f'{ftype.kind}{ftype.itemsize}'
            if ftype.subdtype is not None or code not in PLY_TYPES:
                raise InputError(f'field {fname!r} has type {ftype}, which PLY cannot store '
                                 f'(supported: {", ".join(PLY_TYPES)} and bool)')
        fields.append((fname, '<' + code))
    data = np.empty(len(points), dtype=np.dtype(fields))
    for fname in points.dtype.names:
        data[fname] = points[fname]
    origin = ' '.join(repr(float(v)) for v in cloud.map_origin)
    ply = PlyData([PlyElement.describe(data, 'vertex')], text=not binary, byte_order='<',
                  comments=[f'{_ORIGIN_COMMENT} {origin}'])
    try:
        with open(path, 'wb') as stream:
            ply.write(stream)
    except OSError as exc:
        raise InputError(f'cannot write {os.fspath(path)}: {_one_line(exc)}') from exc


def read_ply(path: PathLike) -> Cloud:
    """Read the ``vertex`` element of a PLY file as a cloud.

    Args:
        path: ASCII or binary (either byte order) PLY file from any tool. Elements other
            than ``vertex`` and list properties of ``vertex`` are ignored.

    Returns:
        The cloud: one field per scalar vertex property, in file order, native byte order,
        packed; map origin from the ``map_origin`` header comment, else (0, 0, 0).

    Raises:
        InputError: missing, corrupt or truncated file, no ``vertex`` element, no x, y or
            z property, or a malformed ``map_origin`` comment.
    """
    name = _existing_file(path)
    try:
        ply = PlyData.read(name)
    except _PLY_ERRORS as exc:
        raise InputError(f'cannot read PLY file {name}: {_one_line(exc)}') from exc
    elements = [e.name for e in ply.elements]
    if 'vertex' not in elements:
        raise InputError(f'{name}: no vertex element (elements: {", ".join(elements) or "none"})')
    vertex = ply['vertex']
    props = [p for p in vertex.properties if not isinstance(p, PlyListProperty)]
    names = [p.name for p in props]
    missing = [c for c in _COORDINATES if c not in names]
    if missing:
        raise InputError(f'{name}: vertex element has no {", ".join(missing)} '
                         f'(properties: {", ".join(names) or "none"})')
    dtype = np.dtype([(p.name, np.dtype(p.val_dtype).newbyteorder('=')) for p in props])
    points = np.empty(vertex.count, dtype=dtype)
    for p in props:
        points[p.name] = vertex.data[p.name]
    comments = list(ply.comments) + [c for e in ply.elements for c in e.comments]
    return Cloud(points, _origin_from_comments(comments, name))


def _origin_from_comments(comments: list[str], name: str) -> np.ndarray:
    """Parse the ``map_origin x y z`` header comment; zeros if there is none."""
    found = [c.split() for c in comments if c.split()[:1] == [_ORIGIN_COMMENT]]
    if not found:
        return np.zeros(3)
    if len(found) > 1:
        raise InputError(f'{name}: {len(found)} map_origin comments, expected one')
    words = found[0][1:]
    try:
        origin = np.array([float(w) for w in words], dtype=np.float64)
    except ValueError:
        origin = np.empty(0)
    if origin.shape != (3,) or not np.all(np.isfinite(origin)):
        raise InputError(f'{name}: malformed comment "{" ".join(found[0])}", expected 3 finite numbers')
    return origin


# --------------------------------------------------------------------------------------
# LAS / LAZ

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


# --------------------------------------------------------------------------------------
# PCD

#: Characters pypcd4's header parser accepts in a field name.
_PCD_NAME = re.compile(r'[A-Za-z0-9_.+*?-]+')
#: Prefix pypcd4 gives to PCL padding fields (named ``_`` in the file).
_PCD_PADDING = '#$%&~~'
_PCD_COMMENT = '# .PCD v0.7 - Point Cloud Data file format\n'
#: printf formats of the ASCII encoding: enough digits to round-trip every value.
_PCD_ASCII_FORMATS = {'f4': '%.9g', 'f8': '%.17g'}
# What pypcd4 (with pydantic, numpy and lzf) raises for unreadable files: ValueError
# (pydantic's ValidationError for a bad header, UnicodeDecodeError, numpy's loadtxt and
# frombuffer errors, lzf's "error in compressed data"), TypeError (lzf output longer than
# announced), KeyError (unknown TYPE/SIZE pair), IndexError (FIELDS, SIZE, TYPE, COUNT of
# different lengths), RuntimeError (decompressed size mismatch), struct.error (truncated
# compressed block), OSError (I/O), MemoryError and OverflowError (absurd point counts).
_PCD_ERRORS = (ValueError, TypeError, KeyError, IndexError, RuntimeError, struct.error, OSError,
               MemoryError, OverflowError, EOFError)


def _import_pypcd4(name: str) -> Any:
    """Import pypcd4 lazily; raise InputError if it is not installed."""
    try:
        import pypcd4
    except ImportError as exc:
        raise InputError(f'cannot handle {name}: PCD files need pypcd4 ({_one_line(exc)})') from exc
    return pypcd4


def read_pcd(path: PathLike) -> Cloud:
    """Read a PCD file (``ascii``, ``binary`` or ``binary_compressed``) as a cloud.

    PCD carries no georeference. The map origin is the translation (tx, ty, tz) of the
    ``VIEWPOINT`` header line, which PCL's viewers add to the points (it is (0, 0, 0)
    unless a tool set it); :func:`write_pcd` stores the map origin there. A VIEWPOINT
    with a rotation (quaternion other than identity) is refused, since the points would
    have to be rotated to be in the map frame.

    Args:
        path: PCD file from PCL or any other tool (version 0.7 header).

    Returns:
        The cloud: one field per PCD field, in file order, native byte order, packed
        (PCL padding fields ``_`` dropped, fields with COUNT k > 1 split into
        ``name__0000`` .. by pypcd4); an organized cloud (HEIGHT > 1) is flattened row by
        row. Map origin (3,) float64, metres, from VIEWPOINT.

    Raises:
        InputError: missing, corrupt or truncated file, no x, y or z field, a VIEWPOINT
            with a rotation or non-finite translation, or pypcd4 not installed.
    """
    name = _existing_file(path)
    pypcd4 = _import_pypcd4(name)
    try:
        with warnings.catch_warnings():  # numpy warns on ASCII data without rows; we raise
            warnings.simplefilter('ignore')
            pc = pypcd4.PointCloud.from_path(name)
        meta = pc.metadata
        data = np.asarray(pc.pc_data).reshape(-1)  # one ASCII row comes back 0-d
        announced = int(meta.points)
        viewpoint = tuple(float(v) for v in meta.viewpoint)
    except _PCD_ERRORS as exc:
        raise InputError(f'cannot read PCD file {name}: {_one_line(exc)}') from exc
    if data.shape[0] != announced:
        raise InputError(f'cannot read PCD file {name}: header announces {announced} points, '
                         f'the data holds {data.shape[0]}')
    names = [f for f in data.dtype.names if not f.startswith(_PCD_PADDING)]
    missing = [c for c in _COORDINATES if c not in names]
    if missing:
        raise InputError(f'{name}: PCD file has no field {", ".join(missing)} '
                         f'(fields: {", ".join(names) or "none"})')
    rotation = viewpoint[3:]
    if rotation not in ((1.0, 0.0, 0.0, 0.0), (-1.0, 0.0, 0.0, 0.0)):
        raise InputError(f'{name}: VIEWPOINT has a rotation (qw qx qy qz = '
                         f'{" ".join(repr(v) for v in rotation)}); only a translation (the map '
                         'origin) is supported, transform the points into the map frame')
    points = np.empty(data.shape[0], dtype=np.dtype([(f, data.dtype[f].newbyteorder('=')) for f in names]))
    for f in names:
        points[f] = data[f]
    try:
        return Cloud(points, viewpoint[:3])
    except InputError as exc:
        raise InputError(f'{name}: VIEWPOINT: {exc}') from None


def write_pcd(path: PathLike, cloud: Cloud, *, encoding: str = 'binary') -> None:
    """Write a cloud as a PCD 0.7 file (unorganized: WIDTH = points, HEIGHT = 1).

    Every field becomes a PCD field of the same name and type (COUNT 1), in field order
    and little endian; bool fields become U 1. The map origin is written as the
    ``VIEWPOINT`` translation (``repr`` floats, loss-free) with the identity rotation.
    Binary encodings are loss-free bit for bit. ``ascii`` prints floats with 9 (f4) or 17
    (f8) significant digits and integers exactly, so every value round-trips except that
    NaN comes back as the canonical quiet NaN. ``binary_compressed`` is LZF-compressed
    column by column, as PCL does (written here rather than by pypcd4, which falls back
    to ``binary`` when LZF does not shrink the data; pypcd4 also prints ASCII floats with
    only 10 decimals, hence the own ASCII writer).

    Args:
        path: file to write; replaced if it exists.
        cloud: the cloud to write.
        encoding: ``'ascii'``, ``'binary'`` or ``'binary_compressed'``.

    Raises:
        InputError: unknown encoding, a field type PCD cannot store (f2, strings,
            sub-arrays, ...), a field name PCD cannot hold (only ASCII letters, digits and
            ``_ . + - * ?``, not ``_`` alone), pypcd4 not installed, or the file cannot be
            written.
    """
    name = os.fspath(path)
    if encoding not in PCD_ENCODINGS:
        raise InputError(f'unknown PCD encoding {encoding!r} (choose from {", ".join(PCD_ENCODINGS)})')
    points = cloud.points
    fields: list[tuple[str, str]] = []
    for fname in points.dtype.names:
        ftype = points.dtype.fields[fname][0]
        if not _PCD_NAME.fullmatch(fname) or fname == '_':
            raise InputError(f'field name {fname!r} cannot be a PCD field name '
                             '(needs ASCII letters, digits and _ . + - * ?, not "_" alone)')
        code = 'u1' if ftype.kind == 'b' else f'{ftype.kind}{ftype.itemsize}'
        if ftype.subdtype is not None or code not in PCD_TYPES:
            raise InputError(f'field {fname!r} has type {ftype}, which PCD cannot store '
                             f'(supported: {", ".join(PCD_TYPES)} and bool)')
        fields.append((fname, code))
    data = np.empty(len(points), dtype=np.dtype([(f, '<' + c) for f, c in fields]))
    for fname in points.dtype.names:
        data[fname] = points[fname]

    pypcd4 = _import_pypcd4(name)
    meta = pypcd4.MetaData(
        fields=tuple(f for f, _ in fields),
        size=tuple(PCD_TYPES[c][1] for _, c in fields),
        type=tuple(PCD_TYPES[c][0] for _, c in fields),
        count=(1,) * len(fields),
        points=len(data), width=len(data), height=1,
        viewpoint=(*(float(v) for v in cloud.map_origin), 1.0, 0.0, 0.0, 0.0),
        data=encoding,
    )
    try:
        with open(name, 'wb') as stream:
            stream.write((_PCD_COMMENT + meta.compose_header()).encode('ascii'))
            if len(data) == 0:
                return
            if encoding == 'binary':
                stream.write(data.tobytes())
            elif encoding == 'binary_compressed':
                import lzf  # pypcd4's own LZF binding

                raw = b''.join(np.ascontiguousarray(data[f]).tobytes() for f, _ in fields)
                packed = lzf.compress(raw, len(raw) + len(raw) // 16 + 64)  # never None
                stream.write(struct.pack('<II', len(packed), len(raw)))
                stream.write(packed)
            else:
                formats = [_PCD_ASCII_FORMATS.get(c, '%d') for _, c in fields]
                np.savetxt(stream, data, fmt=formats, delimiter=' ')
    except OSError as exc:
        raise InputError(f'cannot write {name}: {_one_line(exc)}') from exc


# --------------------------------------------------------------------------------------
# helpers


def _suffix(path: PathLike) -> str:
    """The lower-case suffix of ``path`` if supported, else raise InputError."""
    suffix = Path(path).suffix.lower()
    if suffix not in SUPPORTED_SUFFIXES:
        raise InputError(f'unsupported file type {suffix or "(no suffix)"!r} for {os.fspath(path)}; '
                         f'supported: {", ".join(SUPPORTED_SUFFIXES)}')
    return suffix


def _existing_file(path: PathLike) -> str:
    """``path`` as a string if it is an existing file, else raise InputError."""
    name = os.fspath(path)
    if not os.path.exists(name):
        raise InputError(f'no such file: {name}')
    if not os.path.isfile(name):
        raise InputError(f'not a file: {name}')
    return name


def _one_line(exc: BaseException) -> str:
    """The message of ``exc`` on one line, with its type if the message is empty."""
    text = ' '.join(str(exc).split())
    return text or type(exc).__name__
