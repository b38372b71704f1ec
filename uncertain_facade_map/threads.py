"""Threads of the numerical libraries.

The map's linear algebra is many small matrices (GP blocks of at most 64 points, marginal
likelihood patches of a few hundred): a multi-threaded BLAS spends more on synchronising its
threads than on them, and on a busy 2-core machine its spinning threads make a 150 x 150
Cholesky solve 20-100 times slower (measured: the street build's length-scale fits went from
0.3 s to 5 s while two other processes ran). The map uses its cores itself instead (the
compiled block kernel in two threads, the mapping process beside the node's).
"""

from __future__ import annotations

import types
from contextlib import AbstractContextManager, nullcontext
from typing import Any


def one_blas_thread() -> AbstractContextManager:
    """Context limiting BLAS to one thread (threadpoolctl, a scikit-learn dependency).

    The loaded libraries are looked up once per process (:func:`_controller`): threadpoolctl
    scans the process's shared objects at every ``threadpool_limits``, 4 ms a call, which
    live mapping's small pieces paid hundreds of times a lap."""
    controller = _controller()
    if controller is None:  # pragma: no cover - depends on the environment
        return nullcontext()
    return controller.limit(limits=1, user_api='blas')


_CONTROLLER: list = []


def _controller():  # noqa: ANN202 - threadpoolctl's ThreadpoolController or None
    """The process's threadpoolctl controller, made at the first call (after numpy and scipy
    have loaded their BLAS); None without threadpoolctl."""
    if not _CONTROLLER:
        try:
            from threadpoolctl import ThreadpoolController  # noqa: PLC0415 - scikit-learn's dependency
        except ImportError:  # pragma: no cover - depends on the environment
            return None
        _CONTROLLER.append(ThreadpoolController())
    return _CONTROLLER[0]


#: Threads of the map's own parallel parts in this process (k-d tree queries, the GP block
#: kernel); None: their defaults (all cores for the k-d trees, two for the blocks).
_THREADS: int | None = None


def set_threads(n: int | None) -> None:
    """Run the map's own parallel parts in ``n`` threads in this process (None: the defaults).
    A worker of a tiled build (one process per core) sets 1: its parallelism is the tiles'."""
    global _THREADS
    _THREADS = None if n is None else max(1, int(n))


def threads(default: int) -> int:
    """Threads a parallel part whose own default is ``default`` uses (see :func:`set_threads`)."""
    return default if _THREADS is None else _THREADS


def kdtree_workers() -> int:
    """The ``workers`` of scipy's k-d tree queries: -1 (all cores) unless :func:`set_threads` set a number."""
    return -1 if _THREADS is None else _THREADS


def serial_twin(kernel: Any, name: str) -> Any:
    """The one-core twin of the parallel compiled ``kernel`` (``prange`` runs as ``range``;
    its other options, ``nogil`` among them, as the kernel's), cached under its own ``name``.

    numba names a kernel's cache entry after the function's qualified name and first line and
    keys it by signature and source, not by its ``parallel`` flag: a twin compiled from the
    same ``py_func`` shares the parallel kernel's entry, and whichever of the two is compiled
    first is loaded for both from then on. The kernels' warm-up calls are small (one-core), so
    the parallel kernels ran on one core (the query's reading took the same 60 ms per 20,000
    points with one core or two). A copy of the function under another name has its own entry.

    Args:
        kernel: a ``numba.njit(parallel=True, cache=True)`` dispatcher.
        name: the twin's name in its module (its cache entry's).
    """
    from numba import njit  # noqa: PLC0415 - the compiled kernels' modules import numba anyway

    f = kernel.py_func
    twin = types.FunctionType(f.__code__, f.__globals__, name, f.__defaults__, f.__closure__)
    twin.__qualname__ = name
    twin.__doc__ = f'{f.__name__} on one core (``prange`` runs as ``range``).'
    options = {k: v for k, v in kernel.targetoptions.items() if k not in ('parallel', 'nopython')}
    return njit(cache=True, **options)(twin)
