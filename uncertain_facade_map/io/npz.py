"""Reading and writing clouds as NPZ files (numpy archives, never pickled).

Written as three arrays: ``format`` (the string :data:`NPZ_FORMAT`), ``points`` (the
structured point array itself) and ``map_origin`` ((3,) float64, metres). This is
loss-free bit for bit for every structured dtype numpy can store without pickle: any
field order, byte order, offsets and item size, sub-array fields, NaN payloads. (The
padding bytes between fields are not data; numpy does not keep them, and a read cloud
has them zeroed.) :func:`read_npz` also accepts *foreign* archives (see there).

Every failure a user can cause (missing file, corrupt or truncated file, arrays that are
no cloud) raises :class:`InputError` with a one-line message. The suffix ``.npz`` is
dispatched here by :mod:`~uncertain_facade_map.io.clouds`.
"""

from __future__ import annotations

import os
import zipfile
import zlib

import numpy as np

from ..errors import InputError
from ._files import _COORDINATES, PathLike, _existing_file, _one_line
from .cloud import Cloud

__all__ = ['NPZ_FORMAT', 'read_npz', 'write_npz']

#: Value of the ``format`` array in the NPZ files written by :func:`write_npz`.
NPZ_FORMAT = 'uncertain_facade_map.io.cloud/1'

# What numpy and zipfile raise for unreadable archives: OSError (I/O), ValueError (bad
# header, pickled data, short data), EOFError (truncated member), BadZipFile (broken
# archive), zlib.error (corrupt compressed member), MemoryError (absurd array shape).
_NPZ_ERRORS = (OSError, ValueError, EOFError, zipfile.BadZipFile, zlib.error, MemoryError)


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

