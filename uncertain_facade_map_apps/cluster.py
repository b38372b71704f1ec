"""The tiled build on Dask (issue 29): the inputs' routing and one task per tile; the client owns the manifest.

:func:`route` reads and routes the inputs (:mod:`uncertain_facade_map.tiling.build`'s three
steps): one survey task per input file (:func:`survey_input`: read, select the building points,
spill them, measure their buildings), the client merging the small surveys in input order and
planning, then one spill task per input file (:func:`~uncertain_facade_map.tiling.build.spill_part`).
:func:`run_tiles` runs :func:`uncertain_facade_map.tiling.build.build_tile` for each tile task.
Both run

* in this process (``workers=0`` and no scheduler: tests, equality checks, small maps), the same
  functions one after the other;
* on a local Dask cluster of ``workers`` processes of one thread each (BLAS, OpenMP and numba
  at one thread in the workers: a tile's matrices are small, the parallelism is the tiles');
* on an existing cluster (``scheduler='tcp://host:8786'``): its workers need this package
  installed (the same version), the inputs readable at the same paths, and the output folder
  shared (same path) with the client, since each task reads its input or its tile's spilled
  points from ``DIR/.work`` and writes ``DIR/.work`` or ``DIR/tiles/<id>.npz`` itself.

One cluster serves the routing and the tiles (:func:`dask_client`, given to both as ``client``).
Each task is submitted with ``retries`` (a task whose worker died is run again, on another
worker if need be: Dask's scheduler reschedules the tasks of a lost worker, and a task that
raised is retried). Writes are atomic (temporary file, renamed), so a tile is written whole
or not at all. After every finished tile the client writes the manifest (atomically), so an
interrupted build resumes where it stopped.
"""

from __future__ import annotations

import os
import time
import uuid
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator

from uncertain_facade_map.tiling.build import (
    Chunk,
    Part,
    Router,
    Spilled,
    TileResult,
    TileTask,
    build_tile,
    calibrate_tile,
    in_frame,
    spill_part,
    survey_part,
)
from uncertain_facade_map.tiling.manifest import Manifest, write_manifest

#: Environment of the worker processes: one thread for BLAS, OpenMP and numba.
ONE_THREAD = dict.fromkeys(('OMP_NUM_THREADS', 'OPENBLAS_NUM_THREADS', 'MKL_NUM_THREADS', 'NUMBA_NUM_THREADS',
                            'VECLIB_MAXIMUM_THREADS', 'NUMEXPR_NUM_THREADS'), '1')
#: Times a task is run again after its worker was lost or it raised.
RETRIES = 3


def in_one_thread(function: Callable, *args):
    """``function(*args)`` in one thread: the map's own parallel parts (k-d tree queries on all
    cores, the GP block kernel in two threads: :func:`uncertain_facade_map.threads.set_threads`)
    and numba's parallel kernels (a worker reads ``NUMBA_NUM_THREADS`` after numba's configuration
    is loaded). Without it a 1-worker build used 30.8 s of CPU in 25.6 s of tasks."""
    import numba

    from uncertain_facade_map.threads import set_threads

    numba.set_num_threads(1)
    set_threads(1)
    return function(*args)


def start_client(workers: int = 0, scheduler: str | None = None) -> tuple[Any, Any]:
    """(client, local cluster or None): a Dask client on a new local cluster of ``workers``
    processes of one thread each (:data:`ONE_THREAD`), or on the cluster at ``scheduler``.

    The local workers keep glibc's own allocator settings: Dask sets ``MALLOC_TRIM_THRESHOLD_``
    (65536) in its workers to hand freed memory back to the system sooner, which also turns off
    glibc's adaptive mmap threshold, so that every large numpy array is a new mapping, its pages
    faulted in again: a tile task then took 1.4x the processor time (three of the city's tiles,
    6.5 s against 4.7 s, the same 0.37 GB peak). An existing cluster keeps its own settings."""
    import dask
    from dask.distributed import Client, LocalCluster

    if scheduler is not None:
        return Client(scheduler), None
    with dask.config.set({'distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_': None}):
        cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=':0',
                               env=dict(ONE_THREAD), silence_logs=40)
    return Client(cluster), cluster


def stop_client(client: Any, cluster: Any) -> None:
    """Close what :func:`start_client` opened."""
    client.close()
    if cluster is not None:
        cluster.close()


@contextmanager
def dask_client(workers: int = 0, scheduler: str | None = None) -> Iterator[Any]:
    """A Dask client for the whole build (:func:`start_client`), closed on leaving; None (run in
    this process) for ``workers=0`` and no scheduler."""
    if scheduler is None and workers <= 0:
        yield None
        return
    client, cluster = start_client(workers, scheduler)
    try:
        yield client
    finally:
        stop_client(client, cluster)


def run_each(client: Any, function: Callable, calls: list[tuple], name: str, retries: int = RETRIES) -> list:
    """``function(*args)`` for each ``args`` of ``calls``, in their order: in this process
    (``client`` None) or as tasks on the cluster (in one thread, with ``retries``)."""
    if client is None:
        return [function(*args) for args in calls]
    run = uuid.uuid4().hex[:8]
    futures = [client.submit(in_one_thread, function, *args, key=f'{name}-{i}-{run}', retries=retries, pure=False)
               for i, args in enumerate(calls)]
    try:
        return client.gather(futures)
    finally:
        for future in futures:
            future.release()


def survey_input(folder: str, index: int, path: str, read: Callable[[str], Iterable[tuple[int, Chunk]]], cell: float,
                 bounds: tuple[float, float, float, float] | None, origin: Any) -> Part:
    """Step 1 for one input file (a task): ``read(path)`` gives its chunks (with the input points
    each was selected from), :func:`~uncertain_facade_map.tiling.build.survey_part` spills and
    measures them; :attr:`Part.read` counts the input points."""
    count = [0]

    def chunks() -> Iterator[Chunk]:
        for n, chunk in read(path):
            count[0] += n
            yield chunk

    part = survey_part(folder, index, chunks(), cell, bounds, origin)
    part.read = count[0]
    return part


@dataclass
class Routed:
    """What :func:`route` did: the tile tasks and the figures of its phases.

    Attributes:
        tasks: one per tile that received points, in tile id order.
        read: input points read.
        read_seconds: wall time of the survey tasks (reading, selecting, spilling, measuring), s.
        plan_seconds: the client's merging of the surveys and planning, s.
        route_seconds: wall time of merging, planning and the spill tasks, s.
        parts: the surveys (:class:`Part`), in input order.
        spilled: the spills (:class:`Spilled`), in input order.
        again: inputs surveyed a second time (another map origin than the first input's).
    """

    tasks: list[TileTask]
    read: int
    read_seconds: float
    plan_seconds: float
    route_seconds: float
    parts: list[Part] = field(default_factory=list)
    spilled: list[Spilled] = field(default_factory=list)
    again: int = 0


def route(router: Router, inputs: list[str], read: Callable[[str], Iterable[tuple[int, Chunk]]], client: Any = None,
          retries: int = RETRIES, calibrate: float | None = None) -> Routed:
    """Survey, plan and spill the inputs (the module's description) into ``router``'s folder.

    The surveys run at once, each in the map frame of its input's first chunk unless the router
    has one (an existing map's); the client merges them in input order, the first input with
    points giving the frame, and surveys again those of another map origin in that frame (the
    same points as a serial routing, bit for bit).

    Args:
        router: a new router (its folder shared with the workers).
        inputs: the input files, in input order (paths the workers can read).
        read: picklable; ``read(path)`` yields (input points read, :data:`Chunk` of building points).
        client: a Dask client (:func:`dask_client`), or None: in this process.
        retries: times a task is run again after a lost worker or an error.
        calibrate: :attr:`TileTask.calibrate` of the tasks.
    """
    started = time.perf_counter()
    folder = str(router.folder)

    def survey(indices: list[int], origin: Any) -> list[Part]:
        calls = [(folder, i, inputs[i], read, router.cell, router.bounds, origin) for i in indices]
        return run_each(client, survey_input, calls, 'survey', retries)

    parts = survey(list(range(len(inputs))), router.map_origin)
    origin = router.map_origin
    if origin is None:
        origin = next((p.origin for p in parts if p.origin is not None), None)
    redo = [p.index for p in parts if not in_frame(p, origin)]
    for p in redo:
        for chunk in p.chunks:
            Path(chunk).unlink(missing_ok=True)
    for p in survey(redo, origin):
        parts[p.index] = p
    read_s = time.perf_counter() - started
    for p in parts:
        router.merge(p)
    router.plan()
    plan_s = time.perf_counter() - started - read_s
    plan = router.route_plan
    if client is not None and router.points:
        [plan] = client.scatter([plan], broadcast=True, hash=False)
    calls = [(folder, p.index, p.chunks, plan, first) for p, first in zip(router.parts, router.spill_firsts())
             if p.chunks]
    spilled = run_each(client, spill_part, calls, 'spill', retries)
    tasks = router.tasks(spilled, calibrate)
    route_s = time.perf_counter() - started - read_s
    return Routed(tasks, sum(p.read for p in parts), read_s, plan_s, route_s, parts, spilled, len(redo))


#: Seconds between two writes of the manifest while tiles finish (and once at the end, or when
#: the build stops): a write per tile made the client's work grow as the square of the tiles
#: (17,000 tiles for 1,000 km of streets); a build killed loses at most this much of finished
#: tiles' records (their files are rebuilt when it resumes).
MANIFEST_PERIOD = 2.0


def record_tile(folder: str | Path, manifest: Manifest, result: TileResult, write: bool = True) -> None:
    """Put a finished tile into the manifest (its buildings placed in it) and write the manifest
    (unless ``write`` is False: the caller writes it later)."""
    record = result.record
    manifest.tiles[record.id] = record
    for b in record.buildings:
        manifest.building_tiles[int(b)] = record.id
    if write:
        write_manifest(folder, manifest)


def run_tiles(tasks: Iterable[TileTask], folder: str | Path, manifest: Manifest, workers: int = 0,
              scheduler: str | None = None, progress: Callable[[TileResult], None] | None = None,
              retries: int = RETRIES, function: Callable[[TileTask], TileResult] = build_tile,
              calibrate: tuple[tuple[str, ...], float | None] | None = None,
              client: Any = None) -> list[TileResult]:
    """Run the tile tasks and record each finished tile in the manifest (written at most every
    :data:`MANIFEST_PERIOD` s, at the end, and when the run stops on an error).

    With ``calibrate``, the map's occupancy PLSC and its local reading's calibration are learnt too
    (:func:`calibrate_tile`, as one more task once those tiles are written, or at once if none is among
    the tasks: on a cluster it runs beside the remaining tiles, which go largest first) and put into
    ``manifest.occupancy`` and ``manifest.local_calibration``.

    Args:
        tasks: the tiles to build.
        folder: the tiled map's folder.
        manifest: the manifest to complete (updated in place and written as it goes).
        workers: local worker processes (0: in this process, no Dask).
        scheduler: address of an existing Dask scheduler (instead of ``workers``).
        progress: called with each finished tile's result.
        retries: times a task is run again after a lost worker or an error.
        function: what runs a task (tests wrap :func:`build_tile`).
        calibrate: (the tiles to learn the calibrations on, the voxel side of the occupancy's labels in m
            or None: no occupancy learnt), or None: not learnt (:func:`~uncertain_facade_map.tiling.build.calibration_tiles`
            chooses).
        client: a Dask client to run the tasks on (:func:`dask_client`; left open), instead of
            ``workers`` and ``scheduler``.

    Returns:
        The results in order of completion.
    """
    # The largest tiles first: the last task to finish is a small one.
    tasks = sorted(tasks, key=lambda t: -sum(os.path.getsize(p) for p in t.parts))
    results: list[TileResult] = []
    learn_on, resolution = calibrate or ((), None)
    waiting = set(learn_on) & {t.tile_id for t in tasks}  # the calibration tiles not written yet

    def files() -> list[str]:
        return [manifest.tiles[t].file for t in learn_on]

    written = [-float('inf'), False]  # the last write's time, and whether records wait to be written

    def flush() -> None:
        if written[1]:
            write_manifest(folder, manifest)
            written[:] = [time.monotonic(), False]

    def done(result: TileResult) -> None:
        record_tile(folder, manifest, result, write=False)
        written[1] = True
        if time.monotonic() - written[0] >= MANIFEST_PERIOD:
            flush()
        results.append(result)
        if progress is not None:
            progress(result)

    def learnt(calibrations: dict) -> None:
        if resolution is not None:  # else not learnt (points without sensor origins): the manifest's kept
            manifest.occupancy = calibrations['occupancy']
        manifest.local_calibration = dict(calibrations['local_calibration'])
        written[1] = True
        flush()

    if not tasks and not learn_on:
        return results
    if client is None and scheduler is None and workers <= 0:
        try:
            for task in tasks:
                done(function(task))
            if learn_on:
                learnt(calibrate_tile(str(folder), files(), resolution))
        finally:
            flush()
        return results
    from dask.distributed import as_completed

    own = client is None
    if own:
        client, cluster = start_client(workers, scheduler)
    try:
        futures = as_completed([client.submit(in_one_thread, function, task,
                                              key=f'tile-{task.tile_id}-{task.inputs[-12:]}', retries=retries,
                                              pure=False) for task in tasks])

        def learn() -> None:
            futures.add(client.submit(in_one_thread, calibrate_tile, str(folder), files(), resolution,
                                      key=f'calibrate-{"-".join(learn_on)}', retries=retries, pure=False))

        if learn_on and not waiting:
            learn()  # built already (a resumed build)
        for future in futures:
            result = future.result()
            future.release()
            if isinstance(result, TileResult):
                done(result)
                if result.record.id in waiting:
                    waiting.discard(result.record.id)
                    if not waiting:
                        learn()
            else:
                learnt(result)
    finally:
        flush()
        if own:
            stop_client(client, cluster)
    return results
