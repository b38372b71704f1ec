"""Helpers shared by the cloud file formats and their dispatcher :mod:`~uncertain_facade_map.io.clouds`.

The path type of the readers and writers, the x, y, z field names, the check that a file to
read exists, the one-line form of an exception's message for :class:`InputError`, and the
atomic write of a file (the map file, the tiled map's manifest, the Autoware export).
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path
from typing import Callable, Union

from ..errors import InputError

__all__ = ['PathLike', '_COORDINATES', '_existing_file', '_one_line', 'atomic_write', 'temporary_name', 'umask']

PathLike = Union[str, 'os.PathLike[str]']

_COORDINATES = ('x', 'y', 'z')


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


def umask() -> int:
    """The process's umask (read from /proc where it can be, without changing it)."""
    try:
        with open('/proc/self/status', encoding='ascii') as f:
            for line in f:
                if line.startswith('Umask:'):
                    return int(line.split()[1], 8)
    except (OSError, ValueError):
        pass
    mask = os.umask(0o022)  # elsewhere: read by setting it (briefly)
    os.umask(mask)
    return mask


def temporary_name(path: Path) -> tuple[str, str]:
    """(prefix, suffix) of the temporary files :func:`atomic_write` writes next to ``path``:
    ``.NAME.XXXXXXXX.tmp``."""
    return f'.{path.name}.', '.tmp'


def atomic_write(path: PathLike, write: Callable[[str], None], mode: int | None = None,
                 before_replace: Callable[[Path], None] | None = None) -> Path:
    """Write ``path`` atomically: ``write(name)`` fills a temporary file next to it
    (:func:`temporary_name`), which is flushed to disk, given ``mode`` (None: the permissions
    the process's umask allows, as ``open`` would give them) and renamed over ``path``. A
    failure deletes the temporary file; a kill leaves it (the writers' own clean-ups remove it).
    ``before_replace(path)``, if given, runs just before the rename and may refuse it by
    raising (what the rename would replace is checked as late as possible).

    Returns:
        The path written.
    """
    path = Path(path)
    prefix, suffix = temporary_name(path)
    fd, tmp = tempfile.mkstemp(prefix=prefix, suffix=suffix, dir=path.parent)
    os.close(fd)
    try:
        write(tmp)
        with open(tmp, 'rb+') as fh:
            os.fsync(fh.fileno())
        os.chmod(tmp, 0o666 & ~umask() if mode is None else mode)
        if before_replace is not None:
            before_replace(path)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path
