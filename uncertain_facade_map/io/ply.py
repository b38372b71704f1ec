"""Reading and writing clouds as PLY files (Stanford polygon file format, via ``plyfile``).

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

Every failure a user can cause (missing file, corrupt or truncated file, unsupported
field type) raises :class:`InputError` with a one-line message. The suffix ``.ply`` is
dispatched here by :mod:`~uncertain_facade_map.io.clouds`.
"""

from __future__ import annotations

import os

import numpy as np
from plyfile import PlyData, PlyElement, PlyListProperty, PlyParseError

from ..errors import InputError
from ._files import _COORDINATES, PathLike, _existing_file, _one_line
from .cloud import Cloud

__all__ = ['PLY_TYPES', 'read_ply', 'write_ply']

#: numpy type code -> PLY type name, the types a PLY vertex property can have.
PLY_TYPES = {
    'i1': 'char', 'u1': 'uchar', 'i2': 'short', 'u2': 'ushort',
    'i4': 'int', 'u4': 'uint', 'f4': 'float', 'f8': 'double',
}

_ORIGIN_COMMENT = 'map_origin'

# What plyfile raises for unreadable files: PlyParseError (header or data), ValueError
# (bad type names, duplicate names, negative or huge counts, non-ASCII header via
# UnicodeDecodeError), OverflowError (ASCII value out of range of its type), OSError (I/O),
# MemoryError (an ASCII element count too large to allocate).
_PLY_ERRORS = (PlyParseError, ValueError, OverflowError, OSError, MemoryError)


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

