"""Reading and writing clouds as PCD files (Point Cloud Library format, via ``pypcd4``).

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

Every failure a user can cause (missing file, corrupt or truncated file, unsupported
field type) raises :class:`InputError` with a one-line message. pypcd4 is imported only
when a PCD file is read or written. The suffix ``.pcd`` is dispatched here by
:mod:`~uncertain_facade_map.io.clouds`.
"""

from __future__ import annotations

import os
import re
import struct
import warnings
from typing import Any

import numpy as np

from ..errors import InputError
from ._files import _COORDINATES, PathLike, _existing_file, _one_line
from .cloud import Cloud

__all__ = ['PCD_ENCODINGS', 'PCD_TYPES', 'read_pcd', 'write_pcd']

#: numpy type code -> (PCD TYPE, SIZE), the types a PCD field can have.
PCD_TYPES = {
    'i1': ('I', 1), 'u1': ('U', 1), 'i2': ('I', 2), 'u2': ('U', 2), 'i4': ('I', 4),
    'u4': ('U', 4), 'i8': ('I', 8), 'u8': ('U', 8), 'f4': ('F', 4), 'f8': ('F', 8),
}
#: PCD data encodings read and written.
PCD_ENCODINGS = ('ascii', 'binary', 'binary_compressed')

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

