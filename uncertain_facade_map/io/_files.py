"""Helpers shared by the cloud file formats and their dispatcher :mod:`~uncertain_facade_map.io.clouds`.

The path type of the readers and writers, the x, y, z field names, the check that a file to
read exists, and the one-line form of an exception's message for :class:`InputError`.
"""

from __future__ import annotations

import os
from typing import Union

from ..errors import InputError

__all__ = ['PathLike', '_COORDINATES', '_existing_file', '_one_line']

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
