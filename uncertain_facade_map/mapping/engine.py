"""Where the live map is updated: in the worker's thread, or in a process of its own.

A :class:`~uncertain_facade_map.mapping.worker.MapWorker` hands every cloud, command and idle
flush to an engine and waits for it. Both engines keep the same promises:

- **Transactional.** After every item the engine keeps a clone of the map (:meth:`committed`);
  an item that raises puts the clone back, so the map is exactly as before it.
- **A view after every item** (:class:`MapView`): the façade models (frozen) and the few
  numbers the worker's snapshot and idle flush need.

:class:`LocalEngine` updates the map in the calling thread. :class:`ProcessEngine` updates it
in a child process (``spawn``: no ROS state is inherited), so that the update's Python code
never holds the interpreter lock of the node, whose callbacks answer queries and take in
clouds meanwhile: a query then waits for CPU only, never for the map's update (issue 13). It
sends each item down a pipe and waits for the answer (the wait releases the lock); the view
comes back with the façade models that changed only. A second pipe, served by a thread of the
child, hands out the committed map while the child maps on (saves never wait for an update).
The child ends when the parent's pipes close (the parent stopped or died).
"""

from __future__ import annotations

import dataclasses
import multiprocessing
import os
import pickle
import signal
import threading
import time
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from ..datatypes import FacadeModel, array_bytes
from ..errors import FacadeMapError, InputError
from ..params import MapParams
from ..pipeline.step8_occupancy import FIXED, PLSC
from .allocator import limit_heap_growth, release_free_memory
from .facade_map import FacadeMap


class MappingProcessError(FacadeMapError):
    """The mapping process ended or could not be reached."""


@dataclass(frozen=True)
class MapView:
    """What the worker reads of the map after an item.

    Attributes:
        facades: the façade models (frozen), ``facades[i].facade_id == i``.
        map_origin: (3,) georeference of the map frame, metres (read-only).
        buildings: number of buildings.
        points: number of building points mapped (stored and thinned).
        params: the map's modelling parameters.
        pending: points held back for the next batch update.
        block_updated: a façade was updated block by block since its last whole fit
            (:attr:`FacadeMap.needs_consolidation`), or pools and scans wait for a full
            update (:attr:`FacadeMap.needs_full_update`): what the idle flush does.
        stored: number of building points stored (the rest were thinned).
        cpu_seconds: CPU time of the last item in the process that did it (all its threads;
            in the node's own process, :class:`LocalEngine`, the node's other threads count
            too), seconds: unlike its wall time, it does not grow when other processes take
            the CPU.
        map_bytes: bytes of the map's arrays in the process that holds it
            (:func:`~uncertain_facade_map.datatypes.array_bytes`: points, normals, sensor
            origins, voxel index, façade models).
        occupancy: the occupancy's PLSC parameters the map has learnt (``FacadeMap.occupancy_``).
        stored_points: per building label, its stored points (``FacadeMap.points``: the
            arrays, shared, never written), which queries read per point
            (:mod:`~uncertain_facade_map.pipeline.step7_local_surface`).
        registration_var: the map's variance of scan-to-scan disagreement, m^2
            (``FacadeMap.registration_var_``), added to every answer's variance.
        unmodelled: stored points no model step has allocated yet (``FacadeMap.n_unmodelled``).
        needs_model: a model step has work (``FacadeMap.needs_model``).
    """

    facades: tuple[FacadeModel, ...]
    map_origin: np.ndarray
    buildings: int
    points: int
    params: MapParams
    pending: int
    block_updated: bool
    stored: int = 0
    cpu_seconds: float = 0.0
    map_bytes: int = 0
    occupancy: PLSC = FIXED
    stored_points: dict[int, np.ndarray] = field(default_factory=dict)
    registration_var: float = 0.0
    unmodelled: int = 0
    needs_model: bool = False

    @property
    def needs_flush(self) -> bool:
        """Points are held back or a façade was updated block by block only."""
        return bool(self.pending) or self.block_updated


def view_of(fmap: FacadeMap, cpu_seconds: float = 0.0) -> MapView:
    """The :class:`MapView` of a map as it stands (``cpu_seconds``: of the item that made it)."""
    origin = np.asarray(fmap.map_origin, dtype=np.float64).copy()
    origin.setflags(write=False)  # the façade models' arrays are read-only already
    return MapView(tuple(fmap.facades), origin, len(fmap.points), fmap.n_points, fmap.params, fmap.n_pending,
                   fmap.needs_consolidation or fmap.needs_full_update,
                   fmap.n_stored, cpu_seconds, array_bytes(fmap), fmap.occupancy_, dict(fmap.points),
                   fmap.registration_var_, fmap.n_unmodelled, fmap.needs_model)


@dataclass(frozen=True)
class ReplaceMap:
    """Returned by a :meth:`MapWorker.call` function to replace the worker's map.

    Attributes:
        fmap: the new map.
        result: what :meth:`MapWorker.call` returns.
    """

    fmap: FacadeMap
    result: Any = None


def replace_with(new: FacadeMap, result: Any, _old: FacadeMap) -> ReplaceMap:
    """A :meth:`MapWorker.call` function that replaces the map by ``new`` (picklable with
    :func:`functools.partial`, so that it reaches a :class:`ProcessEngine` too)."""
    return ReplaceMap(new, result)


class LocalEngine:
    """The map, updated in the calling thread.

    Args:
        fmap: the map (the engine owns it from now on).
    """

    def __init__(self, fmap: FacadeMap) -> None:
        self._fmap = fmap
        self._committed = fmap.clone()
        self._done = 0
        self.view = view_of(fmap)

    def add_points(self, xyz: np.ndarray, building_id: np.ndarray | None, sensor_origins: np.ndarray | None,
                   map_now: bool = False) -> bool:
        """Add a cloud (``FacadeMap.add_points(..., defer=True, map_now=map_now)``); True when
        an update ran or nothing is held back. Raises what the map raised, the map rolled back."""
        def add() -> bool:
            return bool(self._fmap.add_points(xyz, building_id, sensor_origins, defer=True, map_now=map_now)) \
                or not self._fmap.pending
        return self._item(add)

    def store(self, clouds: list[tuple[np.ndarray, np.ndarray | None, np.ndarray | None]]) -> list[str | None]:
        """Store clouds of (xyz, building ids or None, sensor origins or None) at once
        (``FacadeMap.store_points``, each cloud one scan): live mapping's first tier. Returns,
        per cloud, None or why it was refused (bad input: the others are stored); raises what
        else the map raised, the map rolled back."""
        def store() -> list[str | None]:
            out: list[str | None] = []
            for xyz, building_id, sensor_origins in clouds:
                try:
                    self._fmap.store_points(xyz, building_id, sensor_origins)
                    out.append(None)
                except InputError as exc:  # checked before anything changed
                    out.append(str(exc))
            return out
        return self._item(store)

    def model_step(self, max_points: int | None = None) -> list[int]:
        """One piece of modelling (``FacadeMap.model_step``): live mapping's second tier."""
        return self._item(lambda: self._fmap.model_step(max_points))

    def run(self, fn: Callable[[FacadeMap], Any]) -> tuple[Any, bool]:
        """Run ``fn(map)``; returns (its result, whether the map was replaced)."""
        def call() -> tuple[Any, bool]:
            result = fn(self._fmap)
            if not isinstance(result, ReplaceMap):
                return result, False
            self._fmap = result.fmap
            return result.result, True
        return self._item(call)

    def flush(self, consolidate: bool = True) -> tuple[int, list[int]]:
        """Map the points held back and (``consolidate``) fit whole the façades updated
        block by block (:meth:`FacadeMap.flush`); returns (points that were held back,
        façades fitted whole)."""
        return self._item(lambda: (self._fmap.n_pending, self._fmap.flush(consolidate)))

    @property
    def done(self) -> int:
        """Items done (failed ones included)."""
        return self._done

    def committed(self) -> tuple[int, FacadeMap]:
        """(items done, a clone of the map after the last of them): nobody changes the clone
        (save it, do not map into it)."""
        return self._done, self._committed

    def close(self, timeout: float = 0.0, wait: bool = True) -> None:
        """Nothing to release."""

    def _item(self, work: Callable[[], Any]) -> Any:
        """One item as a transaction: on success keep a clone of the map (and its view), on
        failure put the last clone back and raise."""
        cpu = time.process_time()
        try:
            out = work()
        except BaseException:
            self._fmap = self._committed.clone()
            self._done += 1
            raise
        self._committed, self._done = self._fmap.clone(), self._done + 1
        self.view = view_of(self._fmap, time.process_time() - cpu)
        return out


def _picklable(exc: BaseException) -> BaseException:
    """``exc`` if it survives pickling, else a RuntimeError with its type and message."""
    try:
        pickle.loads(pickle.dumps(exc))
        return exc
    except Exception:  # noqa: BLE001 - any pickling failure
        return RuntimeError(f'{type(exc).__name__}: {exc}')


def _lower_priority(nice: int) -> None:
    """Raise this process's niceness by ``nice`` (best effort): the parent's latency-bound
    work (queries, input) then gets the CPU first when both want it."""
    if nice > 0:
        try:
            os.nice(nice)
        except OSError:
            pass


def _child_main(conn: Any, service: Any, nice: int = 0) -> None:
    """The mapping process: items from ``conn`` (one at a time), committed maps from ``service``."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent decides when to stop
    _lower_priority(nice)
    limit_heap_growth()
    kind, fmap = conn.recv()
    engine = LocalEngine(fmap)
    lock = threading.Lock()  # a committed map is handed out only once its item's answer is sent
    answered = engine.committed()

    def serve() -> None:
        while True:
            try:
                service.recv()
            except (EOFError, OSError):
                os._exit(0)  # the parent is gone: stop at once, mid-update or not
            with lock:
                held = answered
            try:
                service.send(held)
            except (EOFError, OSError):
                os._exit(0)

    threading.Thread(target=serve, name='committed_map', daemon=True).start()
    sent: tuple[FacadeModel, ...] = engine.view.facades
    sent_points: dict[int, np.ndarray] = dict(engine.view.stored_points)
    while True:
        try:
            request = conn.recv()
        except (EOFError, OSError):
            os._exit(0)
        kind = request[0]
        if kind == 'stop':
            conn.send(('stopped', None, None))
            return
        try:
            if kind == 'add':
                result: Any = engine.add_points(*request[1:])
            elif kind == 'store':
                result = engine.store(request[1])
            elif kind == 'model':
                result = engine.model_step(request[1])
            elif kind == 'run':
                result = engine.run(request[1])
            elif kind == 'flush':
                result = engine.flush(*request[1:])
            else:
                raise ValueError(f'unknown request {kind!r}')
            error = None
        except BaseException as exc:  # noqa: BLE001 - handed to the parent
            result, error = None, _picklable(exc)
        view = engine.view
        # Only the façade models that changed travel back (the others are the same objects),
        # and of the stored points only the rows appended by a cloud or a flush.
        changed = {i: f for i, f in enumerate(view.facades) if i >= len(sent) or sent[i] is not f}
        points = _points_delta(sent_points, view.stored_points, appended=kind in ('add', 'flush', 'store', 'model'))
        delta = (len(view.facades), changed, points, dataclasses.replace(view, facades=(), stored_points={}))
        with lock:
            try:
                conn.send(('error', error, delta) if error is not None else ('ok', result, delta))
            except (EOFError, OSError):
                os._exit(0)  # the parent is gone or stopping
            except Exception as exc:  # noqa: BLE001 - e.g. a result that does not pickle
                conn.send(('error', RuntimeError(f'the answer could not be sent: {exc}'), delta))
            answered = engine.committed()
        sent, sent_points = view.facades, dict(view.stored_points)
        del request, result, delta, points
        release_free_memory()  # the item's temporary arrays, back to the system


def _points_delta(sent: dict[int, np.ndarray], now: dict[int, np.ndarray], appended: bool
                  ) -> tuple[tuple[int, ...], dict[int, tuple[int, np.ndarray]]]:
    """What the parent needs to hold the stored points ``now`` (per building label, (N, 3)
    arrays) when it holds ``sent``: (the labels now, in order; per label whose array changed,
    (rows it keeps of its copy, rows to append)). ``appended``: the item only appended rows
    to the arrays (a cloud, a flush: :meth:`FacadeMap._append`), so only the new rows travel;
    otherwise (any function run on the map) a changed array travels whole."""
    out = {}
    for b, pts in now.items():
        old = sent.get(b)
        if old is pts:
            continue
        keep = len(old) if appended and old is not None and len(old) <= len(pts) else 0
        out[b] = (keep, pts[keep:])
    return tuple(now), out


def _apply_points_delta(held: dict[int, np.ndarray],
                        delta: tuple[tuple[int, ...], dict[int, tuple[int, np.ndarray]]]) -> dict[int, np.ndarray]:
    """The stored points after :func:`_points_delta` ``delta`` of ``held`` (new arrays for the
    changed labels, read-only; the others shared)."""
    labels, changed = delta
    out = {}
    for b in labels:
        if b not in changed:
            out[b] = held[b]
            continue
        keep, rows = changed[b]
        pts = rows if not keep else np.concatenate([held[b][:keep], rows])
        pts.setflags(write=False)
        out[b] = pts
    return out


class ProcessEngine:
    """The map, updated in a child process (see the module's description).

    Args:
        fmap: the initial map (sent to the child; the caller must not change it).
        nice: niceness added to the child's (0: the parent's priority).

    Raises:
        MappingProcessError: the child could not be reached.
    """

    def __init__(self, fmap: FacadeMap, nice: int = 0) -> None:
        ctx = multiprocessing.get_context('spawn')
        self._conn, child_conn = ctx.Pipe()
        self._service, child_service = ctx.Pipe()
        self._process = ctx.Process(target=_child_main, args=(child_conn, child_service, nice), name='facade_map',
                                    daemon=True)
        self._process.start()
        child_conn.close()
        child_service.close()
        self._done = 0  # requests the child answered (it counts the same)
        self._service_lock = threading.Lock()
        self._send(('init', fmap))
        self.view = view_of(fmap)

    @property
    def pid(self) -> int | None:
        """The child's process id."""
        return self._process.pid

    def add_points(self, xyz: np.ndarray, building_id: np.ndarray | None, sensor_origins: np.ndarray | None,
                   map_now: bool = False) -> bool:
        """See :meth:`LocalEngine.add_points`."""
        return bool(self._request('add', xyz, building_id, sensor_origins, map_now))

    def store(self, clouds: list[tuple[np.ndarray, np.ndarray | None, np.ndarray | None]]) -> list[str | None]:
        """See :meth:`LocalEngine.store`."""
        return self._request('store', clouds)

    def model_step(self, max_points: int | None = None) -> list[int]:
        """See :meth:`LocalEngine.model_step`."""
        return self._request('model', max_points)

    def run(self, fn: Callable[[FacadeMap], Any]) -> tuple[Any, bool]:
        """See :meth:`LocalEngine.run` (``fn`` must pickle: a module-level function or a
        :func:`functools.partial` of one, e.g. :func:`replace_with`)."""
        result, replaced = self._request('run', fn)
        return result, replaced

    def flush(self, consolidate: bool = True) -> tuple[int, list[int]]:
        """See :meth:`LocalEngine.flush`."""
        pending, refitted = self._request('flush', consolidate)
        return pending, refitted

    @property
    def done(self) -> int:
        """Items the child has done (a request that never reached it is not one)."""
        return self._done

    def committed(self) -> tuple[int, FacadeMap]:
        """(items done, the child's map after the last of them), fetched now while the child
        maps on; the answer to that item has been sent already."""
        with self._service_lock:
            try:
                self._service.send('committed')
                return self._service.recv()
            except (EOFError, OSError) as exc:
                self._process.join(1.0)
                raise MappingProcessError(self._ended('handing out the committed map')) from exc

    def close(self, timeout: float = 10.0, wait: bool = True) -> None:
        """Stop the child (after its current item), killing it after ``timeout`` seconds.

        ``wait=False`` when another thread is still in a request (waiting for the child's
        answer on the same pipe): the child is killed at once, unasked, as a second reader of
        the pipe would take that answer or garble it (that thread's request then fails with
        :class:`MappingProcessError`)."""
        if self._process.is_alive() and wait:
            try:
                self._send(('stop',))
                if self._conn.poll(timeout):
                    self._conn.recv()
            except (MappingProcessError, EOFError, OSError):
                pass  # it ended meanwhile
            self._process.join(timeout)
        if self._process.is_alive():
            self._process.kill()
            self._process.join(timeout)
        for conn in (self._conn, self._service):
            conn.close()

    def _ended(self, doing: str) -> str:
        return (f'the mapping process ended (exit code {self._process.exitcode}) while {doing}: the map it held '
                f'since the last save is lost; restart the node')

    def _send(self, message: Any) -> None:
        try:
            self._conn.send(message)  # pickled whole before anything is written
        except (pickle.PicklingError, AttributeError, TypeError) as exc:  # lambdas, local functions
            raise MappingProcessError(f'a {message[0]!r} request for the mapping process must pickle: {exc}') from exc
        except (EOFError, OSError) as exc:
            self._process.join(1.0)
            raise MappingProcessError(self._ended(f'sending it a {message[0]!r} request')) from exc

    def _request(self, kind: str, *args: Any) -> Any:
        self._send((kind, *args))
        try:
            status, result, delta = self._conn.recv()
        except (EOFError, OSError) as exc:
            self._process.join(1.0)
            raise MappingProcessError(self._ended(f'working on a {kind!r} request')) from exc
        n_facades, changed, points, rest = delta
        facades = list(self.view.facades[:n_facades])
        facades.extend([None] * (n_facades - len(facades)))  # type: ignore[list-item]
        for i, f in changed.items():
            facades[i] = f
        self.view = dataclasses.replace(rest, facades=tuple(facades),
                                        stored_points=_apply_points_delta(self.view.stored_points, points))
        self._done += 1
        if status == 'error':
            raise result  # the exception as the child raised it
        return result


@dataclass(frozen=True)
class Kept:
    """An argument of :meth:`HelperProcess.call` that the helper keeps: sent the first time
    (and whenever ``ident`` is another object), named by ``key`` after. For large inputs that
    change seldom and are used at every call (the node's per-point reading of millions of
    stored points, handed to every publication of the maps: pickled each time, it held the
    node's interpreter for tenths of a second every ``publish.period``).

    Attributes:
        key: the helper's slot for it.
        ident: the object it stands for (compared by identity); a call made in this
            process (:func:`unkept`) receives it.
        value: what crosses to the helper for it (``ident`` itself or a lighter copy).
    """

    key: str
    ident: Any
    value: Any


@dataclass(frozen=True)
class _Held:
    key: str


def unkept(args: tuple) -> tuple:
    """``args`` with each :class:`Kept` replaced by the object it stands for (a call made
    here: the object itself, with whatever it has built, not the copy made to cross)."""
    return tuple(a.ident if isinstance(a, Kept) else a for a in args)


def _helper_main(conn: Any, nice: int = 0) -> None:
    """A helper process: ``(function, args, kwargs)`` from ``conn``, its result (or the
    exception it raised) back; ends when the parent's pipe closes. Keeps the values of
    :class:`Kept` arguments by key and passes them where a later call names them."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    _lower_priority(nice)
    limit_heap_growth()
    kept: dict[str, Any] = {}
    while True:
        try:
            fn, args, kwargs = conn.recv()
        except (EOFError, OSError):
            os._exit(0)
        try:
            for a in args:
                if isinstance(a, Kept):
                    kept[a.key] = a.value
            args = tuple(kept[a.key] if isinstance(a, (Kept, _Held)) else a for a in args)
            answer: tuple[str, Any] = ('ok', fn(*args, **kwargs))
        except BaseException as exc:  # noqa: BLE001 - handed to the caller
            answer = ('error', _picklable(exc))
        try:
            conn.send(answer)
        except (EOFError, OSError):
            os._exit(0)  # the parent closed the pipe (it is stopping) during the call
        except Exception as exc:  # noqa: BLE001 - a result that does not pickle
            conn.send(('error', RuntimeError(f'the result could not be sent: {exc}')))
        del fn, args, kwargs, answer
        release_free_memory()


class HelperProcess:
    """Runs picklable functions in a child process, one call at a time (callers wait their
    turn): heavy numpy work that would otherwise hold the caller's interpreter lock, such
    as the node's published maps. The child is started on the first call (and again after
    it died) and ends when this object is closed or its process ends.

    Args:
        name: the child's process name.
        nice: niceness added to the child's (0: the parent's priority).
    """

    def __init__(self, name: str = 'helper', nice: int = 0) -> None:
        self._name = name
        self._nice = nice
        self._lock = threading.Lock()
        self._process: Any = None
        self._conn: Any = None
        self._closed = False
        self._kept: dict[str, Any] = {}  # key -> the object the child holds (Kept)

    @property
    def pid(self) -> int | None:
        """The child's process id (None before the first call)."""
        return None if self._process is None else self._process.pid

    def call(self, fn: Callable[..., Any], *args: Any, **kwargs: Any) -> Any:
        """``fn(*args, **kwargs)`` in the child; raises what it raised there.

        Raises:
            MappingProcessError: the child ended during the call (it is started again on the
                next one).
        """
        with self._lock:
            if self._closed:
                raise MappingProcessError(f'the {self._name} process was closed')
            if self._process is None or not self._process.is_alive():
                self._start()
            process, conn = self._process, self._conn
            new = {a.key: a.ident for a in args if isinstance(a, Kept) and self._kept.get(a.key) is not a.ident}
            sent = tuple((Kept(a.key, None, a.value) if a.key in new else _Held(a.key))  # the value, not the object
                         if isinstance(a, Kept) else a for a in args)
            try:
                conn.send((fn, sent, kwargs))
                status, result = conn.recv()
                self._kept.update(new)
            except (EOFError, OSError, TypeError) as exc:  # TypeError: closed by close() meanwhile
                process.join(1.0)
                self._process = None
                why = 'was closed' if self._closed else f'ended (exit code {process.exitcode})'
                raise MappingProcessError(f'the {self._name} process {why} during a call') from exc
        if status == 'error':
            raise result
        return result

    def close(self, timeout: float = 5.0) -> None:
        """End the child (killed after ``timeout`` seconds if a call still runs)."""
        self._closed = True
        got = self._lock.acquire(timeout=timeout)
        try:
            process, self._process = self._process, None
            if process is None:
                return
            self._conn.close()  # the child sees the pipe close and ends
            process.join(timeout)
            if process.is_alive():
                process.kill()
                process.join(timeout)
        finally:
            if got:
                self._lock.release()

    def _start(self) -> None:
        self._kept = {}
        ctx = multiprocessing.get_context('spawn')
        self._conn, child = ctx.Pipe()
        self._process = ctx.Process(target=_helper_main, args=(child, self._nice), name=self._name, daemon=True)
        self._process.start()
        child.close()
