"""Reading and writing :class:`~uncertain_facade_map.io.cloud.Cloud` records as PLY, NPZ, LAS/LAZ and PCD files.

Five suffixes are supported, chosen (case-insensitively) by :func:`read_cloud` and
:func:`write_cloud`: ``.npz``, ``.ply``, ``.las``, ``.laz`` and ``.pcd``. Each format has
its own module, whose docstring says what the format keeps and what it loses:
:mod:`~uncertain_facade_map.io.npz`, :mod:`~uncertain_facade_map.io.ply`,
:mod:`~uncertain_facade_map.io.las` (``.las`` and ``.laz``) and
:mod:`~uncertain_facade_map.io.pcd`.

Every failure a user can cause (missing file, unknown suffix, corrupt or truncated file,
unsupported field type) raises :class:`InputError` with a one-line message. laspy and
pypcd4 are imported only when a LAS/LAZ or PCD file is read or written.
"""

from __future__ import annotations

import os
from pathlib import Path

from ..errors import InputError
from ._files import PathLike
from .cloud import Cloud
from .las import read_las, write_las
from .npz import read_npz, write_npz
from .pcd import read_pcd, write_pcd
from .ply import read_ply, write_ply

__all__ = ['SUPPORTED_SUFFIXES', 'read_cloud', 'write_cloud']

#: Suffixes understood by :func:`read_cloud` and :func:`write_cloud`.
SUPPORTED_SUFFIXES = ('.npz', '.ply', '.las', '.laz', '.pcd')


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
# helpers


def _suffix(path: PathLike) -> str:
    """The lower-case suffix of ``path`` if supported, else raise InputError."""
    suffix = Path(path).suffix.lower()
    if suffix not in SUPPORTED_SUFFIXES:
        raise InputError(f'unsupported file type {suffix or "(no suffix)"!r} for {os.fspath(path)}; '
                         f'supported: {", ".join(SUPPORTED_SUFFIXES)}')
    return suffix
