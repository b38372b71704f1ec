"""Live mapping: a worker thread that owns the map, fed through a bounded queue.

The facade_mapper node (and the replay command) hand clouds of building points to a
:class:`MapWorker`; the worker applies them to its :class:`~uncertain_facade_map.mapping.facade_map.FacadeMap` one at a
time, in arrival order, so that a node fed the same clouds builds the same map as the
offline core fed them in one loop. Nothing slow runs in the caller's thread.

**Drop policy.** At most ``queue_size`` clouds and ``queue_points`` points wait. When a
cloud arrives at a full queue,
the *oldest* waiting cloud is dropped: a live map should follow the newest data, and the
cloud that waited longest is the one most likely covered again by what follows. Drops are
counted (:attr:`MapWorker.counters`). Commands (save, load, reset, any function given to
:meth:`MapWorker.call`) are never dropped and run in order with the clouds.

**Two tiers** (``batching='latency'``, the node's default). A cloud is *stored* in the first
item after its arrival, with every cloud that came meanwhile
(:meth:`FacadeMap.store_points`: labelled, thinned, appended; no façade touched), and its
latency ends with the snapshot that follows: its points are queryable from there. The
façades are *modelled* after, one bounded piece at a time
(:meth:`FacadeMap.model_step`: one building's stored points, at most ``update.step_points``,
or one scan of the comparison, or one building's pool), whenever no cloud waits, so that a
cloud waits for one piece at most and the model catches up whenever the input leaves room.
``batching='fixed'`` holds points back for whole batches instead (the map then depends only
on the clouds, as offline replay's).

Readers never wait for the worker: after every change the worker publishes an immutable
:class:`MapSnapshot` (the façade models are frozen), which queries read, and after every
cloud or command a clone of the whole map (:meth:`MapWorker.committed`, points held back
included), which a save writes at once, without waiting for the queue.

**Failures change nothing.** A cloud or command that raises leaves the map exactly as it
was before it (the worker puts the clone back: an update that fails half way, in a
linear-algebra routine say, cannot leave a half-updated map); the cloud is counted as
failed and handed to ``on_error``.

**Accounts** (:meth:`MapWorker.accounts`, read under the worker's lock so that they add
up at any moment): ``clouds_in = clouds_mapped + clouds_dropped + clouds_failed +
clouds_waiting`` (queued or being mapped), and the same for points. A cloud held back for
the next batch update (``defer``) counts as mapped; its points are in ``points_pending``
until the update. Latency is measured from a cloud's arrival (:meth:`MapWorker.put`) to
the update that brings its points into the snapshot.
"""

from __future__ import annotations

import threading
import time
from collections import Counter, deque
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from ..datatypes import FacadeModel
from ..errors import InputError
from ..params import MapParams, QueryConfig
from ..pipeline.step7_local_surface import LocalSurface, for_query
from ..pipeline.step7_queries import PointQuery, query_map
from ..pipeline.step8_occupancy import FIXED, PLSC
from .engine import LocalEngine, MapView, ProcessEngine, ReplaceMap, replace_with
from .facade_map import FacadeMap, query_settings, reading_key

__all__ = ['Cloud', 'MapSnapshot', 'MapWorker', 'ReplaceMap', 'ReplaySummary', 'map_scans', 'replace_with']

#: Clouds whose arrival-to-map latency :attr:`MapWorker.latencies` keeps.
LATENCY_WINDOW = 200
#: Seconds over which the mapper's busy share is measured (/diagnostics).
LOAD_WINDOW = 5.0


@dataclass(frozen=True)
class MapSnapshot:
    """The map as it stood after one update, shared read-only with other threads.

    Attributes:
        version: number of changes the worker has made (0: the initial map).
        facades: the façade models (frozen), ``facades[i].facade_id == i``.
        map_origin: (3,) georeference of the map frame, metres.
        buildings: number of buildings.
        points: number of building points in the map.
        stamp_ns: stamp of the newest cloud in the map, nanoseconds (0 if unknown).
        params: the map's own modelling parameters (a loaded map keeps those it was built
            with): its façade bands answer its queries.
        stored: number of building points stored (``points`` less those thinned).
        map_bytes: bytes of the map's arrays where it is updated (``MapView.map_bytes``).
        occupancy: the occupancy's PLSC parameters the map has learnt (``MapView.occupancy``).
        stored_points: per building label, its stored points (``MapView.stored_points``).
        registration_var: the map's variance of scan-to-scan disagreement, m^2
            (``MapView.registration_var``).
    """

    version: int
    facades: tuple[FacadeModel, ...]
    map_origin: np.ndarray
    buildings: int
    points: int
    stamp_ns: int = 0
    params: MapParams = field(default_factory=MapParams)
    stored: int = 0
    map_bytes: int = 0
    occupancy: PLSC = FIXED
    stored_points: dict[int, np.ndarray] = field(default_factory=dict)
    registration_var: float = 0.0
    #: Its local surfaces by reading settings (:meth:`local_surface`; a snapshot never changes).
    _local: dict = field(default_factory=dict, repr=False, compare=False)

    def query(self, xyz: np.ndarray, config: QueryConfig | None = None, resolution: float | None = None,
              event: str | None = None, local: LocalSurface | None = None) -> PointQuery:
        """Answer the 3D point query for (N, 3) points (metres, map frame) from this snapshot,
        as :meth:`FacadeMap.query <uncertain_facade_map.mapping.facade_map.FacadeMap.query>`
        answers from the map (its own bands, learnt occupancy and registration variance).

        ``local``: a reading of the stored points to use instead of this snapshot's own (an
        earlier snapshot's, while the map is being updated: the node's ``node.local_refresh``).

        Raises:
            InputError: bad points, resolution or event.
        """
        config, resolution = query_settings(config, resolution, event)
        ex = self.params.extraction
        if local is None or config.surface != 'local':
            local = self.local_surface(config)
        return query_map(self.facades, self.stored_points, xyz, resolution, ex.band_back, ex.band_front,
                         self.occupancy, config, local, self.registration_var)

    def local_surface(self, config: QueryConfig | None = None) -> LocalSurface | None:
        """The stored points read per point as queries with ``config`` read them (None for
        ``query.surface`` 'raster'), built at the first query that needs it."""
        config = QueryConfig() if config is None else config
        key = reading_key(config)
        if key not in self._local:
            self._local[key] = for_query(self.facades, self.stored_points, config)
        return self._local[key]


@dataclass
class Cloud:
    """Building points waiting to be mapped.

    Attributes:
        xyz: (N, 3) float64 points, metres, map frame.
        building_id: (N,) int64 building ids (negative: none), or None.
        sensor_origins: (N, 3) sensor positions, metres, map frame, or None.
        stamp_ns: acquisition stamp, nanoseconds.
        arrived: ``time.monotonic()`` when it arrived (the node's gate sets it; else
            :meth:`MapWorker.put` does): latencies count from it.
    """

    xyz: np.ndarray
    building_id: np.ndarray | None = None
    sensor_origins: np.ndarray | None = None
    stamp_ns: int = 0
    arrived: float = 0.0


@dataclass
class _Command:
    fn: Callable[[FacadeMap], Any] | None  # None: the idle flush
    changes: bool = True
    done: threading.Event = field(default_factory=threading.Event)
    result: Any = None
    error: BaseException | None = None


class MapWorker:
    """Owns a :class:`FacadeMap` and updates it in a thread of its own.

    Args:
        fmap: the map to grow (the worker owns it from now on; read :attr:`snapshot`).
        queue_size: clouds waiting at most (>= 1); see the module's drop policy.
        queue_points: points waiting at most (a cloud is queued even when it alone holds more).
        on_change: called in the worker thread with each new snapshot.
        on_error: called in the worker thread with (cloud, exception) when a cloud cannot
            be mapped; the cloud is skipped and the map is left exactly as it was.
        idle_flush: once no cloud has arrived for this many seconds (the drive paused or
            ended) and none waits, the points held back are mapped; after as long again, the
            façades updated block by block are fitted whole and the occupancy calibrated
            (:meth:`FacadeMap.flush`); <= 0: never.
        on_flush: called in the worker thread with (points held back, façades fitted
            whole) after an idle flush.
        on_flush_error: called in the worker thread with the exception when an idle flush
            fails (the map is left as before it, and the flush is tried again when idle).
        process: update the map in a child process (:class:`~uncertain_facade_map.mapping.engine.ProcessEngine`)
            instead of this worker's thread; :meth:`call` functions must then pickle.
        nice: niceness added to the child process's.
        batching: ``'fixed'``: points are held back until ``update.batch_points`` have come
            (the map depends only on the clouds); ``'latency'``: the two tiers (see the
            module's text): clouds stored at once, façades modelled in pieces while no cloud
            waits (``node.batching``).
    """

    def __init__(self, fmap: FacadeMap, queue_size: int = 20,
                 on_change: Callable[[MapSnapshot], None] | None = None,
                 on_error: Callable[[Cloud, BaseException], None] | None = None, idle_flush: float = 1.0,
                 on_flush: Callable[[int, list[int]], None] | None = None,
                 on_flush_error: Callable[[BaseException], None] | None = None, process: bool = False,
                 nice: int = 0, queue_points: int | None = None, batching: str = 'fixed') -> None:
        if queue_size < 1:
            raise ValueError(f'queue_size must be >= 1, got {queue_size}')
        if queue_points is not None and queue_points < 1:
            raise ValueError(f'queue_points must be >= 1, got {queue_points}')
        if batching not in ('fixed', 'latency'):
            raise ValueError(f"batching must be 'fixed' or 'latency', got {batching!r}")
        self._latency = batching == 'latency'
        self._model_failed = False  # a model step failed: none until the next cloud
        self._work: deque[tuple[float, float]] = deque()  # (start, end) of the latest items, monotonic
        self._engine: LocalEngine | ProcessEngine = ProcessEngine(fmap, nice) if process else LocalEngine(fmap)
        self._queue: deque[Cloud | _Command] = deque()
        self._clouds = 0
        self._points = 0  # points of the clouds waiting
        self._size = queue_size
        self._max_points = queue_points
        self._cond = threading.Condition()
        self._on_change = on_change
        self._on_error = on_error
        self._on_flush = on_flush
        self._on_flush_error = on_flush_error
        self._stop = False
        self._busy = False
        self._stamp = 0
        self._idle_flush = idle_flush
        self._last_cloud = time.monotonic()
        self._idle_since = time.monotonic()
        self.counters = {'clouds_in': 0, 'clouds_dropped': 0, 'clouds_mapped': 0, 'clouds_failed': 0,
                         'points_in': 0, 'points_dropped': 0, 'points_mapped': 0, 'points_failed': 0,
                         'flushes': 0, 'flushes_failed': 0, 'commands_failed': 0}
        self.last_update_seconds = 0.0
        #: Times the map was replaced (a command returned ReplaceMap: load, reset).
        self.replacements = 0
        #: CPU seconds of the last update in the process that mapped (see ``MapView.cpu_seconds``).
        self.last_update_cpu_seconds = 0.0
        self.pending_points = self._engine.view.pending
        self._working: list[Cloud] = []  # the clouds being mapped
        self._held: list[float] = []  # arrival times of the clouds whose points are held back
        #: Seconds from arrival to map of the latest clouds (newest last).
        self.latencies: deque[float] = deque(maxlen=LATENCY_WINDOW)
        self._items = 0  # the engine's count of items done, as of the last one this worker saw end
        self._versions = {0: 0}  # snapshot version after the latest items, by that count
        self.snapshot = self._snapshot(0)
        self._thread = threading.Thread(target=self._run, name='map_worker', daemon=True)
        self._thread.start()

    # -- producers ----------------------------------------------------------------------
    def put(self, cloud: Cloud) -> bool:
        """Queue a cloud for mapping.

        Returns:
            False if the queue was full and the oldest waiting cloud was dropped.
        """
        cloud.arrived = cloud.arrived or time.monotonic()
        with self._cond:
            self.counters['clouds_in'] += 1
            self.counters['points_in'] += len(cloud.xyz)
            kept = True
            while self._clouds and (self._clouds >= self._size or self._over_points(len(cloud.xyz))):
                oldest = next(i for i, item in enumerate(self._queue) if isinstance(item, Cloud))
                item = self._queue[oldest]
                del self._queue[oldest]
                self._clouds -= 1
                self._points -= len(item.xyz)
                self.counters['clouds_dropped'] += 1
                self.counters['points_dropped'] += len(item.xyz)
                kept = False
            self._queue.append(cloud)
            self._clouds += 1
            self._points += len(cloud.xyz)
            self._last_cloud = time.monotonic()
            self._cond.notify_all()
        return kept

    def _over_points(self, arriving: int) -> bool:
        return self._max_points is not None and self._points + arriving > self._max_points

    def call(self, fn: Callable[[FacadeMap], Any], timeout: float | None = None, changes: bool = True) -> Any:
        """Run ``fn(map)`` in the worker after the clouds queued so far, and return its result.

        Args:
            fn: the function; it may replace the map by returning ``ReplaceMap(new_map)``.
            timeout: seconds to wait at most; None waits for ever.
            changes: whether ``fn`` may change the map (a new snapshot follows).

        Raises:
            TimeoutError: the worker did not get to it in time (it still runs later).
            Exception: whatever ``fn`` raised.
        """
        command = _Command(fn, changes)
        with self._cond:
            if self._stop:
                raise RuntimeError('the map worker has stopped')
            self._queue.append(command)
            self._cond.notify_all()
        if not command.done.wait(timeout):
            raise TimeoutError(f'the map worker did not answer within {timeout} s')
        if command.error is not None:
            raise command.error
        return command.result

    def wait_idle(self, timeout: float | None = None) -> bool:
        """Wait until every queued cloud and command is done; False on timeout."""
        deadline = None if timeout is None else time.monotonic() + timeout
        with self._cond:
            while self._queue or self._busy:
                left = None if deadline is None else deadline - time.monotonic()
                if left is not None and left <= 0:
                    return False
                self._cond.wait(left)
        return True

    @property
    def settled(self) -> bool:
        """Whether nothing waits: no cloud queued, no point held back, every façade fitted whole."""
        with self._cond:
            return not self._queue and not self._busy and not self._needs_flush()

    @property
    def queued(self) -> int:
        """Clouds waiting."""
        return self._clouds

    def accounts(self) -> dict[str, int]:
        """The counters, read at one moment, with ``clouds_waiting`` and ``points_waiting``
        (queued or being mapped): ``clouds_in = clouds_mapped + clouds_dropped +
        clouds_failed + clouds_waiting``, the same for points; ``points_pending``: mapped
        points held back for the next batch update."""
        with self._cond:
            out = dict(self.counters)
            waiting = [c for c in self._queue if isinstance(c, Cloud)]
            waiting.extend(self._working)
            out['clouds_waiting'] = len(waiting)
            out['points_waiting'] = int(sum(len(c.xyz) for c in waiting))
            out['points_pending'] = self.pending_points
            out['points_unmodelled'] = self._engine.view.unmodelled
            return out

    def committed(self) -> tuple[FacadeMap, int, int]:
        """The map after the last cloud or command, for saving it while the worker maps on.

        Returns:
            (map, version, clouds waiting): a clone nobody changes (save it, do not map
            into it), the snapshot version it holds, and the clouds queued or being mapped
            that it does not hold yet.
        """
        done, fmap = self._engine.committed()
        with self._cond:
            # The engine answered item ``done`` already; its version follows at once.
            while done not in self._versions and done > self._items and not self._stop:
                self._cond.wait(1.0)
            waiting = self._clouds + len(self._working)
            return fmap, self._versions.get(done, self.snapshot.version), waiting

    @property
    def committed_version(self) -> int:
        """The snapshot version of the map :meth:`committed` would hand out now."""
        with self._cond:
            return self._versions[self._items]

    def stop(self, timeout: float | None = 10.0) -> None:
        """Stop after the current item; queued items are discarded (a mapping process is
        stopped too, killed if it does not end within ``timeout``: if the current item is
        still running then, the mapping process is killed at once and the item fails)."""
        with self._cond:
            self._stop = True
            self._cond.notify_all()
        self._thread.join(timeout)
        self._engine.close(10.0 if timeout is None else timeout, wait=not self._thread.is_alive())

    @property
    def process_id(self) -> int | None:
        """The mapping process's id (None: the map is updated in this process)."""
        return getattr(self._engine, 'pid', None)

    # -- the worker ---------------------------------------------------------------------
    def _snapshot(self, version: int) -> MapSnapshot:
        view: MapView = self._engine.view
        return MapSnapshot(version, view.facades, view.map_origin, view.buildings, view.points, self._stamp,
                           view.params, view.stored, view.map_bytes, view.occupancy, view.stored_points,
                           view.registration_var)

    def _publish(self) -> None:
        self.snapshot = self._snapshot(self.snapshot.version + 1)
        if self._on_change is not None:
            self._on_change(self.snapshot)

    def _run(self) -> None:
        while True:
            with self._cond:
                while not self._queue and not self._stop:
                    if self._latency and self._engine.view.needs_model and not self._model_failed:
                        break  # the second tier: model a piece while no cloud waits
                    if self._idle_flush > 0 and self._needs_flush():
                        # Idle since the last cloud came *and* since the last work ended: while
                        # the worker was busy, clouds may have waited upstream (in DDS, for the
                        # node's callbacks); they get idle_flush seconds to arrive.
                        left = max(self._last_cloud, self._idle_since) + self._idle_flush - time.monotonic()
                        if left <= 0:
                            break
                        self._cond.wait(left)
                    else:
                        self._cond.wait()
                if self._stop:
                    return
                # An empty queue here means a model step is due or the idle time passed: flush.
                model = not self._queue and self._latency and self._engine.view.needs_model and not self._model_failed
                idle_flush = not self._queue and not model
                item = _Command(None) if idle_flush or model else self._queue.popleft()
                clouds: list[Cloud] = []
                if isinstance(item, Cloud):
                    clouds.append(item)
                    # The first tier takes every cloud waiting, in one store.
                    while self._latency and self._queue and isinstance(self._queue[0], Cloud):
                        clouds.append(self._queue.popleft())
                    self._clouds -= len(clouds)
                    self._points -= sum(len(c.xyz) for c in clouds)
                    self._working = clouds
                self._busy = True
            began = time.monotonic()
            try:
                if clouds and self._latency:
                    self._store_clouds(clouds)
                elif clouds:
                    self._map_cloud(item)
                elif model:
                    self._model_step()
                else:
                    self._run_command(item)
                    if idle_flush and item.error is not None:
                        self.counters['flushes_failed'] += 1
                        if self._on_flush_error is not None:  # nobody waits for this command
                            self._on_flush_error(item.error)
            finally:
                with self._cond:
                    self.pending_points = self._engine.view.pending
                    self._idle_since = time.monotonic()
                    self._work.append((began, self._idle_since))
                    self._working = []
                    self._busy = False
                    self._cond.notify_all()

    def busy_share(self, now: float | None = None) -> float:
        """Share of the last :data:`LOAD_WINDOW` seconds the mapper spent on clouds and
        commands (0-1)."""
        now = time.monotonic() if now is None else now
        start = now - LOAD_WINDOW
        with self._cond:  # reentrant: also called by the worker under it
            while self._work and self._work[0][1] < start:
                self._work.popleft()
            return sum(min(end, now) - max(begin, start) for begin, end in self._work) / LOAD_WINDOW

    def _needs_flush(self) -> bool:
        return self._engine.view.needs_flush

    def _item_done(self) -> None:
        """The engine finished an item (and kept its map, or the one before on failure)."""
        with self._cond:
            self._items = self._engine.done
            self._versions[self._items] = self.snapshot.version
            self._versions.pop(self._items - 16, None)
            self._cond.notify_all()

    def _mapped(self) -> None:
        """The held-back clouds are in the map now: their latencies."""
        now = time.monotonic()
        self.latencies.extend(now - t for t in self._held)
        self._held = []

    def _map_cloud(self, cloud: Cloud) -> None:
        started = time.perf_counter()
        try:
            updated = self._engine.add_points(cloud.xyz, cloud.building_id, cloud.sensor_origins)
        except Exception as exc:  # noqa: BLE001 - reported, the node keeps running
            self._item_done()
            with self._cond:
                self.counters['clouds_failed'] += 1
                self.counters['points_failed'] += len(cloud.xyz)
                self._working = []
            if self._on_error is not None:
                self._on_error(cloud, exc)
            return
        with self._cond:
            self.counters['clouds_mapped'] += 1
            self.counters['points_mapped'] += len(cloud.xyz)
            self._working = []
        self._held.append(cloud.arrived or time.monotonic())
        self._stamp = max(self._stamp, int(cloud.stamp_ns))
        if updated:  # an update ran (or nothing is held back): the held-back points are mapped
            self.last_update_seconds = time.perf_counter() - started
            self.last_update_cpu_seconds = self._engine.view.cpu_seconds
            self._mapped()
            self._publish()
        self._item_done()

    def _store_clouds(self, clouds: list[Cloud]) -> None:
        """The first tier (batching 'latency'): store the clouds at once; their points are
        queryable from the snapshot that follows (their latency ends here)."""
        started = time.perf_counter()
        try:
            refused = self._engine.store([(c.xyz, c.building_id, c.sensor_origins) for c in clouds])
        except Exception as exc:  # noqa: BLE001 - reported, the node keeps running; the map is as before
            refused = [exc] * len(clouds)
        self._item_done()
        self._model_failed = False  # new points: the second tier tries again
        now = time.monotonic()
        failed = []
        with self._cond:
            for cloud, why in zip(clouds, refused):
                if why is None:
                    self.counters['clouds_mapped'] += 1
                    self.counters['points_mapped'] += len(cloud.xyz)
                    self.latencies.append(now - (cloud.arrived or now))
                    self._stamp = max(self._stamp, int(cloud.stamp_ns))
                else:
                    self.counters['clouds_failed'] += 1
                    self.counters['points_failed'] += len(cloud.xyz)
                    failed.append((cloud, why if isinstance(why, BaseException) else InputError(why)))
            self._working = []
        self.last_update_seconds = time.perf_counter() - started
        self.last_update_cpu_seconds = self._engine.view.cpu_seconds
        if len(failed) < len(clouds):
            self._publish()
        if self._on_error is not None:
            for cloud, exc in failed:
                self._on_error(cloud, exc)

    def _model_step(self) -> None:
        """The second tier (batching 'latency'): one piece of modelling, while no cloud waits."""
        try:
            done = self._engine.model_step(self._engine.view.params.update.step_points)
        except Exception as exc:  # noqa: BLE001 - the map is as before; tried again after the next cloud
            self._item_done()
            self._model_failed = True
            self.counters['flushes_failed'] += 1
            if self._on_flush_error is not None:
                self._on_flush_error(exc)
            return
        self._item_done()
        if done or not self._engine.view.needs_model:
            self._publish()

    def _run_command(self, command: _Command) -> None:
        try:
            if command.fn is None:  # the idle flush
                started = time.perf_counter()
                # In two steps, each after idle_flush seconds without clouds, when there are
                # both points held back and façades updated block by block: the points first
                # (queryable at once: their latency), then the whole refits and the occupancy's
                # calibration, which new clouds would otherwise wait behind.
                view = self._engine.view
                split = bool(view.pending) and view.block_updated
                pending, refitted = self._engine.flush(consolidate=not split)
                self.last_update_seconds = time.perf_counter() - started
                self.last_update_cpu_seconds = self._engine.view.cpu_seconds
                self.counters['flushes'] += 1
                if self._on_flush is not None:
                    self._on_flush(pending, refitted)
                result, replaced, changes = refitted, False, True
            else:
                result, replaced = self._engine.run(command.fn)
                changes = command.changes
            if replaced:
                self._stamp = 0
                self._held = []
                self.replacements += 1
            command.result = result
            if changes or replaced:
                if not self._engine.view.pending:
                    self._mapped()
                self._publish()
        except BaseException as exc:  # noqa: BLE001 - handed to the caller
            self.counters['commands_failed'] += 1
            command.error = exc
        finally:
            self._item_done()
            command.done.set()


@dataclass(frozen=True)
class ReplaySummary:
    """What feeding a recording to a map did.

    Attributes:
        scans: scans read.
        points: points in the scans.
        building_points: building points mapped.
        nonfinite: points skipped for NaN or infinite coordinates.
        buildings: buildings in the map.
        facades: façades in the map.
        seconds: wall time of mapping, flush included.
        rejected: scans refused (no transform into the map frame, absurd coordinates, bad
            fields), as the node refuses them.
        reasons: why, with a count of each reason (the first line of each distinct message).
        notes: scans placed otherwise than exactly (a pose held within node.pose_tolerance,
            one pose for a sweep), with a count of each note.
        non_ground: non-ground points of the scans that went through the selection.
        selected: of those, the points the selection kept.
        thin_selections: scans of which the selection kept less than
            ``selection.warn_kept_share`` of the non-ground points.
        selection_warning: the first such scan's warning (``selection_warning``), '' if none.
        frames: the scans' frames, with the number of scans in each.
    """

    scans: int
    points: int
    building_points: int
    nonfinite: int
    buildings: int
    facades: int
    seconds: float
    rejected: int = 0
    reasons: dict[str, int] = field(default_factory=dict)
    notes: dict[str, int] = field(default_factory=dict)
    non_ground: int = 0
    selected: int = 0
    thin_selections: int = 0
    selection_warning: str = ''
    frames: dict[str, int] = field(default_factory=dict)


def map_scans(fmap: FacadeMap, scans: Any, config: Any, progress: Callable[[int], None] | None = None,
              selection: Any = None, *, buffer: Any = None, map_frame: str | None = None, tolerance: float = 0.0,
              max_coordinate: float | None = None) -> ReplaySummary:
    """Feed scans to a map one by one, as the node's worker does, then flush.

    The node maps the clouds it receives exactly so (each placed in the map frame and
    reduced to its building points by :class:`~uncertain_facade_map.io.scans.Scan`,
    ``add_points(defer=True)`` per cloud, a flush when the input pauses), so a node fed the
    same scans and transforms without drops ends with the same map. A scan the node would
    refuse (no transform into the map frame, a point beyond ``max_coordinate``, fields that
    cannot be read) is refused and counted here too.

    Args:
        fmap: the map to grow.
        scans: iterable of scans in recorded order: ``(stamp_ns, points, frame_id)`` tuples,
            or plain structured arrays (in the map frame, stamp 0); points as a PointCloud2
            gives them (x, y, z and optionally the class, building id, sensor origin and time
            fields of ``config``).
        config: an :class:`~uncertain_facade_map.params.InputConfig`.
        progress: called with the number of scans done after each one.
        selection: a :class:`~uncertain_facade_map.params.SelectionConfig` for scans
            without the class field, as the node passes it; None: such scans are all building.
        buffer: the recording's transforms (a
            :class:`~uncertain_facade_map.transforms.TransformBuffer` holding all of them);
            None for none.
        map_frame: the map frame; None for ``config.frame_id``.
        tolerance: seconds a pose may be held beyond the transforms (``node.pose_tolerance``).
        max_coordinate: metres (``node.max_coordinate``); None for no bound.

    Returns:
        The summary.
    """
    from ..io.scans import Scan
    from ..selection import selection_warning

    frame = config.frame_id if map_frame is None else map_frame
    started = time.perf_counter()
    n_scans = n_points = n_building = n_bad = 0
    rejected: Counter[str] = Counter()
    notes: Counter[str] = Counter()
    non_ground = selected = 0
    warnings: Counter[str] = Counter()
    frames: Counter[str] = Counter()
    first_warning = ''
    for item in scans:
        stamp, points, scan_frame = (0, item, frame) if isinstance(item, np.ndarray) else item
        frames[scan_frame] += 1
        n_scans += 1
        n_points += len(points)
        try:
            scan = Scan.of(points, scan_frame, stamp, config)
            placement = scan.place(buffer, frame, tolerance)
            found = scan.building_points(placement, config, selection, max_coordinate)
        except InputError as exc:
            rejected[str(exc).splitlines()[0]] += 1
        else:
            if placement.note:
                notes[placement.note] += 1
            n_bad += found.nonfinite
            if found.selection is not None and found.selection.applied:
                non_ground += found.selection.non_ground
                selected += found.selection.kept
                warning = selection_warning(found.selection, selection)
                if warning is not None:
                    warnings[warning.split(';')[-1].strip()] += 1
                    first_warning = first_warning or warning
            if len(found.xyz):
                n_building += len(found.xyz)
                fmap.add_points(found.xyz, found.building_id, found.sensor_origins, defer=True)
        if progress is not None:
            progress(n_scans)
    fmap.flush()
    return ReplaySummary(n_scans, n_points, n_building, n_bad, len(fmap.points), len(fmap.facades),
                         time.perf_counter() - started, sum(rejected.values()), dict(rejected), dict(notes),
                         non_ground, selected, sum(warnings.values()), first_warning, dict(frames))
