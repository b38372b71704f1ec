"""The tiled build's tasks on Dask (issue 29): one task per tile, the client owns the manifest.

:func:`run_tiles` runs :func:`uncertain_facade_map.tiling.build.build_tile` for each task

* in this process (``workers=0`` and no scheduler: tests, equality checks, small maps);
* on a local Dask cluster of ``workers`` processes of one thread each (BLAS, OpenMP and numba
  at one thread in the workers: a tile's matrices are small, the parallelism is the tiles');
* on an existing cluster (``scheduler='tcp://host:8786'``): its workers need this package
  installed (the same version) and the output folder shared (same path) with the client,
  since each task reads its tile's spilled points from ``DIR/.work`` and writes
  ``DIR/tiles/<id>.npz`` itself.

Each task is submitted with ``retries`` (a task whose worker died is run again, on another
worker if need be: Dask's scheduler reschedules the tasks of a lost worker, and a task that
raised is retried). Writes are atomic (temporary file, renamed), so a tile is written whole
or not at all. After every finished tile the client writes the manifest (atomically), so an
interrupted build resumes where it stopped.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Callable, Iterable

from uncertain_facade_map.tiling.build import TileResult, TileTask, build_tile, calibrate_tile
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


def record_tile(folder: str | Path, manifest: Manifest, result: TileResult) -> None:
    """Put a finished tile into the manifest (its buildings placed in it) and write the manifest."""
    record = result.record
    manifest.tiles[record.id] = record
    for b in record.buildings:
        manifest.building_tiles[int(b)] = record.id
    write_manifest(folder, manifest)


def run_tiles(tasks: Iterable[TileTask], folder: str | Path, manifest: Manifest, workers: int = 0,
              scheduler: str | None = None, progress: Callable[[TileResult], None] | None = None,
              retries: int = RETRIES, function: Callable[[TileTask], TileResult] = build_tile,
              calibrate: tuple[tuple[str, ...], float | None] | None = None) -> list[TileResult]:
    """Run the tile tasks and record each finished tile in the manifest (written after each).

    With ``calibrate``, the map's occupancy PLSC and its local reading's calibration are learnt too
    (:func:`calibrate_tile`, as one more task once those tiles are written, or at once if none is among
    the tasks: on a cluster it runs beside the remaining tiles, which go largest first) and put into
    ``manifest.occupancy`` and ``manifest.local_calibration``.

    Args:
        tasks: the tiles to build.
        folder: the tiled map's folder.
        manifest: the manifest to complete (updated in place and written after every tile).
        workers: local worker processes (0: in this process, no Dask).
        scheduler: address of an existing Dask scheduler (instead of ``workers``).
        progress: called with each finished tile's result.
        retries: times a task is run again after a lost worker or an error.
        function: what runs a task (tests wrap :func:`build_tile`).
        calibrate: (the tiles to learn the calibrations on, the voxel side of the occupancy's labels in m
            or None: no occupancy learnt), or None: not learnt (:func:`~uncertain_facade_map.tiling.build.calibration_tiles`
            chooses).

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

    def done(result: TileResult) -> None:
        record_tile(folder, manifest, result)
        results.append(result)
        if progress is not None:
            progress(result)

    def learnt(calibrations: dict) -> None:
        if resolution is not None:  # else not learnt (points without sensor origins): the manifest's kept
            manifest.occupancy = calibrations['occupancy']
        manifest.local_calibration = dict(calibrations['local_calibration'])
        write_manifest(folder, manifest)

    if not tasks and not learn_on:
        return results
    if scheduler is None and workers <= 0:
        for task in tasks:
            done(function(task))
        if learn_on:
            learnt(calibrate_tile(str(folder), files(), resolution))
        return results
    from dask.distributed import Client, LocalCluster, as_completed

    cluster = None
    if scheduler is None:
        cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=':0',
                               env=dict(ONE_THREAD), silence_logs=40)
        client = Client(cluster)
    else:
        client = Client(scheduler)
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
        client.close()
        if cluster is not None:
            cluster.close()
    return results
