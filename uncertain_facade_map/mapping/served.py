"""The per-point reading a live map answers its queries with, kept while the map changes.

A snapshot of a live map (:class:`~.worker.MapSnapshot`) answers queries from its façade
rasters and from a reading of its stored points (``query.surface`` 'local',
:class:`~uncertain_facade_map.pipeline.step7_local_surface.LocalSurface`). Building a
reading costs about 1 s per million stored points, and every update of the map makes a new
snapshot, so a node cannot build one per snapshot. :class:`ServedReading` holds the latest
reading built and decides when to build the next (issue 37):

- a map's first reading (after a start, a load or a reset) is built by the query that needs
  it (``node.local_refresh`` 0: every snapshot's is);
- while the map changes, the held reading serves the newer snapshots (their rasters are
  always their own), and the newest snapshot's is built in the background once the held one
  is ``node.local_refresh`` old **and** the map has stored ``node.local_growth`` more points
  (any more after :data:`STALE_REFRESHES` refreshes): the rebuilds then cost a bounded
  multiple of building the final reading once, not a share of the CPU for as long as the
  drive lasts;
- once the map has settled, its own reading is built in the background at once, and
  :attr:`ServedReading.current` says when queries read it (the node's ``settled``).

A background build runs niced (:data:`BUILD_NICE`) on one core
(:func:`~uncertain_facade_map.pipeline.local_kernels.serial_kernels`); the reading's kernels
release the interpreter lock, so the threads that answer queries run meanwhile.
"""

from __future__ import annotations

import contextlib
import os
import threading
import time
from dataclasses import dataclass
from typing import Any, Callable

from ..params import NodeConfig, QueryConfig
from ..pipeline.local_kernels import serial_kernels
from ..pipeline.step7_local_surface import LocalSurface
from .engine import Kept

__all__ = ['BUILD_NICE', 'STALE_REFRESHES', 'ServedReading']

#: Refreshes of ``node.local_refresh`` after which any gain of stored points rebuilds the reading.
STALE_REFRESHES = 6
#: Niceness of a thread that builds a reading in the background (the queries' threads come first).
BUILD_NICE = 10


@dataclass(frozen=True)
class _Reading:
    snapshot: Any  # MapSnapshot
    reading: LocalSurface | None
    built: float  # time.monotonic()
    replacements: int  # the worker's map replacements (loads, resets) then


class ServedReading:
    """The reading of the stored points a live map's queries read (see the module's text).

    Args:
        worker: the map's worker (:class:`~.worker.MapWorker`: ``snapshot``, ``settled``,
            ``replacements``).
        query: the queries' settings (``query.*``).
        node: ``node.local_refresh`` and ``node.local_growth``.
        on_error: called with the exception when a background build fails (the next query
            or refresh tries again).
    """

    def __init__(self, worker: Any, query: QueryConfig, node: NodeConfig,
                 on_error: Callable[[BaseException], None] | None = None) -> None:
        self._worker = worker
        self._query = query
        self._refresh = node.local_refresh
        self._growth = node.local_growth
        self._on_error = on_error
        self._lock = threading.Lock()
        self._held: _Reading | None = None
        self._building = False
        self._builds = (0, 0.0)

    @property
    def builds(self) -> tuple[int, float]:
        """(background builds so far, seconds the last one took)."""
        return self._builds

    @property
    def current(self) -> bool:
        """Whether queries read the worker's newest snapshot's own stored points (True when
        the queries read no stored points, or build every snapshot's reading)."""
        if self._query.surface != 'local' or self._refresh <= 0:
            return True
        with self._lock:
            return self._held is not None and self._held.snapshot is self._worker.snapshot

    def for_snapshot(self, snap: Any) -> LocalSurface | None:
        """The reading ``snap``'s queries read (None for ``query.surface`` 'raster')."""
        if self._query.surface != 'local':
            return None
        replacements = self._worker.replacements
        with self._lock:
            held = self._held
            if held is not None and held.snapshot is snap:
                return held.reading
            if self._refresh > 0 and held is not None and held.replacements == replacements:
                if self._due(held, snap):
                    self._start(snap)
                return held.reading
        local = snap.local_surface(self._query)
        self._keep(snap, local, replacements)
        return local

    def kept(self, snap: Any) -> Kept:
        """``snap``'s reading as a helper process keeps it (:class:`~.engine.Kept`): sent,
        without its search structures, only when it is another reading."""
        local = self.for_snapshot(snap)
        return Kept('local', local, None if local is None else local.without_caches())

    def refresh(self) -> None:
        """Once the map has settled, build its reading in the background if queries do not
        read it yet (call it periodically: :attr:`current` turns True then)."""
        if self._query.surface != 'local' or self._refresh <= 0 or not self._worker.settled:
            return
        snap = self._worker.snapshot
        with self._lock:
            if (self._held is None or self._held.snapshot is not snap) and not self._building:
                self._start(snap)

    # -- internals (under _lock where said) --------------------------------------------
    def _due(self, held: _Reading, snap: Any) -> bool:
        """Whether to build ``snap``'s reading now, ``held`` serving (under ``_lock``)."""
        if self._building:
            return False
        if self._worker.settled and snap is self._worker.snapshot:
            return True
        age, grown = time.monotonic() - held.built, snap.stored - held.snapshot.stored
        return age >= self._refresh and (grown >= self._growth * held.snapshot.stored
                                         or (grown > 0 and age >= STALE_REFRESHES * self._refresh))

    def _start(self, snap: Any) -> None:
        """Build ``snap``'s reading in a thread of its own (under ``_lock``)."""
        self._building = True
        threading.Thread(target=self._build, args=(snap,), daemon=True, name='local_reading').start()

    def _keep(self, snap: Any, local: LocalSurface | None, replacements: int) -> None:
        """Hold a snapshot's reading unless a newer one of the same map is held already."""
        with self._lock:
            held = self._held
            if held is None or held.replacements != replacements or held.snapshot.version <= snap.version:
                self._held = _Reading(snap, local, time.monotonic(), replacements)

    def _build(self, snap: Any) -> None:
        """Build a snapshot's reading: niced below the queries' threads, on one core."""
        with contextlib.suppress(OSError, AttributeError):  # Linux: a thread's own niceness
            os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), BUILD_NICE)
        try:
            replacements = self._worker.replacements
            started = time.perf_counter()
            with serial_kernels():
                local = snap.local_surface(self._query)
            self._keep(snap, local, replacements)
            self._builds = (self._builds[0] + 1, time.perf_counter() - started)
        except Exception as exc:  # noqa: BLE001 - reported; the next query or refresh tries again
            if self._on_error is not None:
                self._on_error(exc)
        finally:
            with self._lock:
                self._building = False
