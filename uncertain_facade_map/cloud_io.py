"""Reading and writing :class:`~uncertain_facade_map.cloud.Cloud` records as PLY and NPZ files.

Two formats are supported, chosen by the file suffix in :func:`read_cloud` and
:func:`write_cloud`:

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

Every failure a user can cause (missing file, unknown suffix, corrupt or truncated file,
unsupported field type) raises :class:`InputError` with a one-line message.
"""

from __future__ import annotations

import os
import zipfile
import zlib
from pathlib import Path
from typing import Union

import numpy as np
from plyfile import PlyData, PlyElement, PlyListProperty, PlyParseError

from .cloud import Cloud
from .errors import InputError

PathLike = Union[str, 'os.PathLike[str]']

#: Value of the ``format`` array in the NPZ files written by :func:`write_npz`.
NPZ_FORMAT = 'uncertain_facade_map.cloud/1'

#: Suffixes understood by :func:`read_cloud` and :func:`write_cloud`.
SUPPORTED_SUFFIXES = ('.npz', '.ply')

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
    """Read a cloud from a ``.ply`` or ``.npz`` file, chosen by the suffix.

    Args:
        path: file to read; the suffix is matched case-insensitively.

    Returns:
        The cloud; see :func:`read_ply` and :func:`read_npz`.

    Raises:
        InputError: unknown suffix, missing, corrupt or unsupported file.
    """
    suffix = _suffix(path)
    if suffix == '.ply':
        return read_ply(path)
    return read_npz(path)


def write_cloud(path: PathLike, cloud: Cloud) -> None:
    """Write a cloud as binary PLY or NPZ, chosen by the suffix of ``path``.

    Args:
        path: file to write (``.ply`` or ``.npz``, case-insensitive); replaced if it exists.
        cloud: the cloud to write.

    Raises:
        InputError: unknown suffix, fields PLY cannot store, or the file cannot be written.
    """
    suffix = _suffix(path)
    if suffix == '.ply':
        write_ply(path, cloud)
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
