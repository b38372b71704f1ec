"""Freed memory given back to the system by the C allocator of a long-running process.

glibc's ``malloc`` raises its mmap threshold each time a large block is freed (up to 32 MB
on 64-bit), so after a few updates the map's temporary arrays (up to tens of MB each) come
from the heap and its arenas instead of mappings of their own, and the heap keeps what
they freed wherever a live block sits above it: under ``make soak`` the node and its two
children grew from 1.6 GB after the first minute to 2.5 GB after ten, of which the map's
own arrays were 0.25 GB (issue 13).

- :func:`limit_heap_growth`, once at the start of a process: blocks of
  :data:`MMAP_THRESHOLD` or more get mappings of their own (returned when freed), and the
  threads share at most :data:`ARENA_MAX` arenas;
- :func:`release_free_memory` (``malloc_trim(0)``), after each item of work: every whole
  free page of every arena goes back.

glibc only; elsewhere (musl, macOS) both do nothing. A user's ``GLIBC_TUNABLES`` that sets
a ``glibc.malloc`` tunable is left alone by :func:`limit_heap_growth`.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os

__all__ = ['ARENA_MAX', 'MMAP_THRESHOLD', 'limit_heap_growth', 'release_free_memory']

#: Bytes from which a block gets a mapping of its own (fixed: glibc's own grows to 32 MB).
MMAP_THRESHOLD = 4 * 2**20
#: Allocator arenas shared by a process's threads (glibc's default: 8 per core).
ARENA_MAX = 2

# mallopt parameters (glibc's malloc.h).
_M_MMAP_THRESHOLD = -3
_M_ARENA_MAX = -8


def _libc_function(name: str, argtypes: tuple):
    try:
        fn = getattr(ctypes.CDLL(ctypes.util.find_library('c')), name)
    except (OSError, AttributeError, TypeError):
        return None
    fn.argtypes, fn.restype = argtypes, ctypes.c_int
    return fn


_MALLOPT = _libc_function('mallopt', (ctypes.c_int, ctypes.c_int))
_TRIM = _libc_function('malloc_trim', (ctypes.c_size_t,))


def limit_heap_growth() -> bool:
    """Fix this process's mmap threshold and cap its arenas (see the module).

    Returns:
        True when both were set; False when this is not glibc, or ``GLIBC_TUNABLES``
        configures malloc.
    """
    if _MALLOPT is None or 'glibc.malloc.' in os.environ.get('GLIBC_TUNABLES', ''):
        return False
    return _MALLOPT(_M_MMAP_THRESHOLD, MMAP_THRESHOLD) == 1 and _MALLOPT(_M_ARENA_MAX, ARENA_MAX) == 1


def release_free_memory() -> bool:
    """Give the allocator's free pages back to the system (``malloc_trim(0)``).

    Returns:
        True when memory was released; False when there was none, or this is not glibc.
    """
    return bool(_TRIM(0)) if _TRIM is not None else False
