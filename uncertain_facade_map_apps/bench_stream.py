"""Streaming benchmark (``make bench``, stage ``stream``): a drive fed to the mapper as the node is fed.

A drive is cut into the clouds its sensor sent (0.1 s of points each, by the points' ``time``
field, as :func:`~uncertain_facade_map.simulation.export.split_scans` cuts it for the
replay), reduced to its **building points** (class 1, as the node is fed classified building
clouds: :func:`~uncertain_facade_map.io.scans.select_scan_points`, done before the timed part,
as the node's selection runs in its own callbacks) and handed to a
:class:`~uncertain_facade_map.mapping.worker.MapWorker` built as the facade_mapper node builds
it, from the default parameters (``node.queue_size`` clouds and ``node.queue_points`` points at
most, the oldest waiting cloud dropped when full;
``node.mapping_process``: the map updated in a child process at ``node.mapping_nice``;
``node.idle_flush``; ``update.batch_points`` held back per update, ``add_points(defer=True)``;
the points are in the map frame already, so no pose is looked up). A feeder thread (the
caller's) puts cloud ``i`` at ``(stamp_i - stamp_0) / rate`` seconds after the first, for each
rate factor in turn, each rate with a fresh map and mapping process.

Per drive and rate: clouds in, mapped, dropped; building points/s mapped (building points
mapped divided by the wall time from the first cloud's arrival until the last mapped cloud is
queryable, i.e. in the worker's snapshot); the latency from a cloud's arrival
(:meth:`MapWorker.put`) to its points being queryable (the worker's own ``latencies``, here
kept for every cloud instead of the node's window of the last 200); peak memory (VmHWM of this
process, reset at the start of each rate, plus VmHWM of the mapping process). A rate is given up
(and marked so) once the newest cloud in the map arrived more than ``give_up`` seconds ago while
clouds still wait: the mapper is hopelessly behind (dropping or not: the queue holds up to
``node.queue_points`` points, the whole street drive).

Accuracy, so that speed never hides a loss of quality: the streamed map of each rate that
finished and the map built in one batch from all the drive's building points, both against the
simulated truth (:func:`~uncertain_facade_map.evaluation.surface.evaluate_surface`: RMSE of the
mean surface and coverage of its 95 % interval at raster cells within 0.1 m of a façade's
points, off depth steps, against the scene's exact surface). Real sweeps
(``../shared/data/real/*.ply``): :func:`real_check` runs ``../shared/tools/real_check.py`` twice,
once with this module's ``build`` (the same training points streamed through a ``MapWorker``
in clouds cut by azimuth about the sensor) and once with the package's own command line.
"""

from __future__ import annotations

import argparse
import pickle
import re
import subprocess
import sys
import tempfile
import time
from collections import deque
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

#: Rate factors of the recorded rate, in the order they run.
RATES = (1.0, 2.0, 4.0, 8.0, 16.0)
#: Seconds of sensor time of the real-rate drives (``av2``: 2 x 32 beams, about 275,000 building
#: points/s of the street; ``hdl64``: about 110,000/s): 100 clouds each, five times the node's
#: queue, so that a mapper slower than the sensor drops clouds within the drive.
REAL_RATE_SECONDS = {'av2': 10.0, 'hdl64': 10.0}
#: Seconds of sensor time simulated at once (the returns of a window are held until its building
#: points are taken: 2 s of ``av2`` are 1.4 M returns, 95 MB).
SIMULATE_WINDOW = 2.0
#: Drives of the bench: name -> (scene, sensor preset or None for the scene's own, seconds or None for all).
DRIVES: dict[str, tuple[str, str | None, float | None]] = {
    'street': ('street', None, None),
    'av2': ('street', 'av2', REAL_RATE_SECONDS['av2']),
    'hdl64': ('street', 'hdl64', REAL_RATE_SECONDS['hdl64']),
}
#: Seconds of data per cloud: the simulated sensors turn (or sweep their lines) at 10 Hz.
PERIOD = 0.1
#: Raster cells per façade the accuracy compares at most (a seeded draw; the evaluation's
#: default of 40,000 takes 7 s on street, this about a fifth).
ACCURACY_CELLS = 8000
#: The independent checker of the real sweeps, beside the repository.
SHARED = Path(__file__).resolve().parents[1].parent / 'shared'


@dataclass
class Drive:
    """A simulated drive cut into the building clouds its sensor sent.

    Attributes:
        name: what the drive is (``street``, ``av2``, ...).
        scene: the scene's name (for its truth).
        sensor: the sensor preset's name.
        clouds: the clouds in recorded order (``Cloud`` of the worker, ``arrived`` unset).
        offsets: (C,) seconds of each cloud's stamp after the first's.
        seconds: sensor time of the drive (its clouds' span plus one period), s.
        points: all returns of the drive, building or not.
        building_points: the building points (class 1) in the clouds.
        map_origin: (3,) georeference of the map frame, metres.
    """

    name: str
    scene: str
    sensor: str
    clouds: list
    offsets: np.ndarray
    seconds: float
    points: int
    building_points: int
    map_origin: np.ndarray

    @property
    def rate(self) -> float:
        """Building points per second of sensor time at the recorded rate."""
        return self.building_points / self.seconds

    def describe(self) -> str:
        per = self.building_points / max(len(self.clouds), 1)
        return (f'{self.name} ({self.scene} scene, {self.sensor} sensor): {len(self.clouds)} clouds of {PERIOD:g} s, '
                f'{self.seconds:.1f} s of sensor time, {self.building_points:,} building points (class 1) of '
                f'{self.points:,} returns, {per:,.0f} per cloud, {self.rate:,.0f} building points/s at 1x')


#: Fields of the simulated returns the drive keeps (of its building points).
_KEEP = ('x', 'y', 'z', 'origin_x', 'origin_y', 'origin_z', 'time', 'building_id', 'class')


def simulate_drive(name: str = 'street', scene: str | None = None, sensor: str | None = None,
                   seconds: float | None = None, period: float = PERIOD, cloud: Any = None) -> Drive:
    """Simulate campaign 0 of a scene and cut its building points into the sensor's clouds.

    Args:
        name: the drive's name; with ``scene`` None, a key of :data:`DRIVES`.
        scene: scene name; None: from :data:`DRIVES`.
        sensor: a key of :data:`~uncertain_facade_map.simulation.presets.SENSOR_PRESETS`; None:
            the scene's own sensor.
        seconds: sensor time from the start of the drive, simulated in windows of
            :data:`SIMULATE_WINDOW` s; None: the whole drive in one call (as the bench's
            ``simulate`` stage and ``simulate_campaign(scene, 0)``).
        period: seconds of data per cloud.
        cloud: the drive simulated already (an :class:`~uncertain_facade_map.io.cloud.Cloud` of
            the whole drive: the ``simulate`` stage's), or None.

    Returns:
        The drive.
    """
    from uncertain_facade_map.simulation.campaign import simulate_campaign
    from uncertain_facade_map.simulation.presets import SCENE_SENSORS, SENSOR_PRESETS
    from uncertain_facade_map.simulation.scenes import build_scene

    if scene is None:
        scene, sensor, seconds = DRIVES[name]
    preset = SENSOR_PRESETS[sensor] if sensor is not None else SCENE_SENSORS[scene]
    sensor_name = sensor or next(k for k, v in SENSOR_PRESETS.items() if v == preset)
    the_scene = build_scene(scene, 0)
    windows = [None] if seconds is None else \
        [(float(t), float(min(t + SIMULATE_WINDOW, seconds))) for t in np.arange(0.0, seconds, SIMULATE_WINDOW)]
    parts, n_points, first, last, origin = [], 0, np.inf, -np.inf, np.zeros(3)
    for window in windows:  # the returns of one window at a time
        sim = cloud if cloud is not None and window is None else \
            simulate_campaign(the_scene, 0, preset, window=window)
        if len(sim):
            n_points += len(sim)
            first, last = min(first, sim.points['time'].min()), max(last, sim.points['time'].max())
            parts.append(np.ascontiguousarray(sim.points[list(_KEEP)][sim.points['class'] == 1]))
            origin = np.asarray(sim.map_origin, dtype=np.float64)
        del sim
    building = np.concatenate(parts) if parts else np.empty(0, np.dtype([(k, 'f8') for k in _KEEP]))
    return drive_of(name, scene, sensor_name, building, origin, n_points, float(last - first) + period if n_points
                    else 0.0, period)


def drive_of(name: str, scene: str, sensor: str, building: np.ndarray, map_origin: np.ndarray, points: int,
             seconds: float, period: float = PERIOD) -> Drive:
    """A drive of building points (structured, time-ordered, with a ``time`` field), cut into
    clouds of ``period`` s as a sensor sends them and reduced as the node reduces them
    (:func:`~uncertain_facade_map.io.scans.select_scan_points`)."""
    from uncertain_facade_map.io.cloud import Cloud as PointCloud
    from uncertain_facade_map.io.scans import select_scan_points
    from uncertain_facade_map.mapping.worker import Cloud
    from uncertain_facade_map.params import InputConfig
    from uncertain_facade_map.simulation.export import split_scans

    config = InputConfig()
    clouds, stamps = [], []
    for stamp_ns, part in split_scans(PointCloud(building, map_origin), period):
        found = select_scan_points(part, config)
        if len(found.xyz):
            clouds.append(Cloud(found.xyz, found.building_id, found.sensor_origins, stamp_ns))
            stamps.append(stamp_ns)
    offsets = (np.asarray(stamps, dtype=np.int64) - (stamps[0] if stamps else 0)) / 1e9
    return Drive(name, scene, sensor, clouds, offsets, seconds, points, int(sum(len(c.xyz) for c in clouds)),
                 np.asarray(map_origin, dtype=np.float64))


# ------------------------------------------------------------------------------------------
# Streaming one drive at one rate
# ------------------------------------------------------------------------------------------
def _vm_kb(pid: int | str, key: str = 'VmHWM') -> int:
    """``key`` (kB) of /proc/PID/status; 0 where unreadable."""
    try:
        text = Path(f'/proc/{pid}/status').read_text()
    except OSError:
        return 0
    found = re.search(rf'^{key}:\s+(\d+)', text, re.M)
    return int(found.group(1)) if found else 0


def _reset_peak() -> None:
    """Reset this process's VmHWM to its current RSS (Linux >= 4.0), best effort."""
    try:
        Path('/proc/self/clear_refs').write_text('5')
    except OSError:
        pass


@dataclass
class StreamRun:
    """What streaming a drive at one rate gave.

    Attributes:
        drive: the drive's name.
        rate: the rate factor (2.0: twice the recorded rate).
        clouds_in, clouds_mapped, clouds_dropped, clouds_failed: the worker's accounts.
        clouds_discarded: clouds still waiting when the rate was given up (0 otherwise).
        points_in, points_mapped, points_dropped: building points, the same.
        seconds: wall time from the first cloud's arrival until the last mapped cloud was
            queryable (until the rate was given up, if it was), s.
        latencies: (clouds_mapped,) seconds from each mapped cloud's arrival to its points
            being queryable, in mapping order.
        peak_parent_mb, peak_child_mb: VmHWM of this process (reset at the start of the rate)
            and of the mapping process, MB.
        stopped: why the rate was given up, '' if it ran to the end.
        fmap: the streamed map once settled (None if given up).
        settle_seconds: from the last cloud's arrival until the map settled (every stored
            point modelled, the idle flush done: ``node.idle_flush`` of it is the wait for
            more clouds), s; NaN if given up.
    """

    drive: str
    rate: float
    clouds_in: int
    clouds_mapped: int
    clouds_dropped: int
    clouds_failed: int
    clouds_discarded: int
    points_in: int
    points_mapped: int
    points_dropped: int
    seconds: float
    latencies: np.ndarray
    peak_parent_mb: float
    peak_child_mb: float
    stopped: str = ''
    fmap: Any = None
    settle_seconds: float = float('nan')

    @property
    def points_per_second(self) -> float:
        """Building points mapped per second of wall time (see ``seconds``)."""
        return self.points_mapped / self.seconds if self.seconds > 0 else float('nan')

    def latency(self, q: float) -> float:
        """The ``q`` quantile (0-1) of the latencies, s (NaN if none)."""
        return float(np.quantile(self.latencies, q)) if len(self.latencies) else float('nan')

    @property
    def peak_mb(self) -> float:
        return self.peak_parent_mb + self.peak_child_mb

    def record(self) -> dict:
        """The figures as a JSON-ready dict (no map)."""
        return {'drive': self.drive, 'rate': self.rate, 'clouds_in': self.clouds_in,
                'clouds_mapped': self.clouds_mapped, 'clouds_dropped': self.clouds_dropped,
                'clouds_failed': self.clouds_failed, 'clouds_discarded': self.clouds_discarded,
                'building_points_in': self.points_in, 'building_points_mapped': self.points_mapped,
                'building_points_dropped': self.points_dropped, 'seconds': self.seconds,
                'building_points_per_s': self.points_per_second,
                'latency_p50_s': self.latency(0.5), 'latency_p95_s': self.latency(0.95),
                'latency_max_s': self.latency(1.0), 'peak_mb': self.peak_mb,
                'peak_parent_mb': self.peak_parent_mb, 'peak_child_mb': self.peak_child_mb, 'stopped': self.stopped,
                'settle_s': self.settle_seconds}


def stream_drive(drive: Drive, rate: float, config: Any = None, give_up: float = 60.0,
                 settle_timeout: float = 300.0, keep_map: bool = True) -> StreamRun:
    """Feed a drive's clouds to a ``MapWorker`` built as the node builds it, at ``rate`` x the recorded rate.

    Args:
        drive: the drive.
        rate: rate factor (> 0).
        config: a :class:`~uncertain_facade_map.params.Config`; None: the defaults (the node's).
        give_up: stop when the newest cloud in the map arrived more than this (s) ago while
            clouds still wait (dropped or not).
        settle_timeout: seconds after the last cloud to wait at most for the map to settle
            (every cloud queryable, nothing held back); then the rate is given up too.
        keep_map: fetch the settled map from the mapping process (for the accuracy).

    Returns:
        The figures.
    """
    from uncertain_facade_map.mapping.facade_map import FacadeMap
    from uncertain_facade_map.mapping.worker import Cloud, MapWorker
    from uncertain_facade_map.params import Config, map_params

    if rate <= 0:
        raise ValueError(f'rate must be positive, got {rate}')
    cfg = config or Config()
    node = cfg.node
    published: list[tuple[float, int, float]] = []  # (monotonic, clouds queryable, arrival of the newest)

    def on_change(_snapshot: Any) -> None:  # in the worker's thread, right after it noted the latencies
        now = time.monotonic()
        lat = worker.latencies
        published.append((now, len(lat), now - lat[-1] if lat else float('nan')))

    fmap = FacadeMap(map_params(cfg), drive.map_origin)
    worker = MapWorker(fmap, node.queue_size, on_change=on_change, idle_flush=node.idle_flush,
                       process=node.mapping_process, nice=node.mapping_nice, queue_points=node.queue_points,
                       batching=node.batching)
    worker.latencies = deque()  # every cloud's latency, not the node's window of the latest 200
    stopped = ''
    try:
        worker.committed()  # the mapping process is up (spawned and importing) before the clock starts
        _reset_peak()
        first = time.monotonic()
        schedule = first + drive.offsets / rate

        def behind(now: float) -> bool:
            """Clouds wait and the newest cloud in the map arrived more than ``give_up`` s ago."""
            if not worker.accounts()['clouds_waiting']:
                return False
            newest = published[-1][2] if published and published[-1][1] else first
            return now - newest > give_up

        for cloud, due in zip(drive.clouds, schedule):
            wait = due - time.monotonic()
            if wait > 0:
                time.sleep(wait)
            worker.put(Cloud(cloud.xyz, cloud.building_id, cloud.sensor_origins, cloud.stamp_ns))
            if behind(time.monotonic()):
                stopped = f'given up while feeding: the map over {give_up:g} s behind'
                break
        fed = time.monotonic()
        settle = float('nan')
        while not stopped:
            acc = worker.accounts()
            if (not acc['clouds_waiting'] and not acc['points_pending'] and len(worker.latencies) >= acc['clouds_mapped']
                    and worker.settled):
                settle = time.monotonic() - fed
                break
            now = time.monotonic()
            if behind(now):
                stopped = f'given up: the map over {give_up:g} s behind'
            elif now - fed > settle_timeout:
                stopped = f'given up: not settled {settle_timeout:g} s after the last cloud'
            else:
                time.sleep(0.02)
        acc = worker.accounts()
        if stopped:
            end = time.monotonic()
        else:
            mapped = acc['clouds_mapped']
            end = next((t for t, n, _ in published if n >= mapped), time.monotonic()) if mapped else first
        peak_parent = _vm_kb('self') / 1024.0
        pid = worker.process_id
        peak_child = _vm_kb(pid) / 1024.0 if pid is not None else 0.0
        settled = worker.committed()[0] if keep_map and not stopped else None
    finally:
        worker.stop(5.0 if stopped else 30.0)
    latencies = np.asarray(worker.latencies, dtype=np.float64)
    return StreamRun(drive.name, rate, acc['clouds_in'], acc['clouds_mapped'], acc['clouds_dropped'],
                     acc['clouds_failed'], acc['clouds_waiting'] if stopped else 0, acc['points_in'],
                     acc['points_mapped'], acc['points_dropped'], max(end - first, 1e-9),
                     latencies, peak_parent, peak_child, stopped, settled, settle)


# ------------------------------------------------------------------------------------------
# Accuracy against the simulated truth
# ------------------------------------------------------------------------------------------
def batch_map(drive: Drive, config: Any = None) -> tuple[Any, float]:
    """The map of all the drive's building points added in one batch (as ``build`` does).

    Returns:
        (map, seconds of ``add_points``).
    """
    from uncertain_facade_map.mapping.facade_map import FacadeMap
    from uncertain_facade_map.params import Config, map_params

    cfg = config or Config()
    xyz = np.concatenate([c.xyz for c in drive.clouds])
    ids = np.concatenate([c.building_id for c in drive.clouds])
    origins = np.concatenate([c.sensor_origins for c in drive.clouds])
    fmap = FacadeMap(map_params(cfg), drive.map_origin)
    started = time.perf_counter()
    fmap.add_points(xyz, ids, origins)
    return fmap, time.perf_counter() - started


def accuracy(fmap: Any, scene: Any, max_cells: int = ACCURACY_CELLS) -> dict:
    """RMSE (m) and 95 % coverage of a map's mean surface against a scene's truth, at observed
    cells off the depth steps (:func:`~uncertain_facade_map.evaluation.surface.evaluate_surface`)."""
    from uncertain_facade_map.evaluation.surface import evaluate_surface

    ev = evaluate_surface(fmap, scene, max_cells=max_cells, seed=0)
    return {'rmse_m': ev.observed_rmse, 'coverage95': ev.observed_coverage, 'cells': ev.n_observed,
            'facades': len(fmap.facades)}


def measure_drive(drive: Drive, rates: tuple[float, ...] = RATES, config: Any = None, give_up: float = 60.0,
                  settle_timeout: float = 300.0, batch: Any = None, say: Any = None) -> dict:
    """Stream a drive at each rate, then score each streamed map and the batch map against the truth.

    Rates run in the order given; once a rate was given up or dropped a cloud, the higher ones
    are skipped (the sustained rate is known then, and a mapper that cannot follow a rate
    cannot follow a higher one), so that the bench stays within minutes with a slow mapper.

    Args:
        drive: the drive.
        rates: rate factors, in the order they run.
        config: parameters (None: the node's defaults).
        give_up, settle_timeout: see :func:`stream_drive`.
        batch: a batch map of the same points built already (the build stage's), or None:
            built here (timed) when a streamed map finished, to compare with.
        say: called with each table line as it is measured, or None.

    Returns:
        ``{'drive': description, 'runs': [StreamRun.record() and its 'accuracy', or
        {'rate', 'skipped'}], 'sustained': rate or None, 'batch': {'accuracy', 'seconds',
        'building_points_per_s'} or None}`` and the drive's figures.
    """
    from uncertain_facade_map.simulation.scenes import build_scene

    scene = build_scene(drive.scene, 0)
    runs: list[dict] = []
    skip = ''
    for rate in rates:
        if skip:
            rec = {'drive': drive.name, 'rate': rate, 'skipped': skip}
        else:
            run = stream_drive(drive, rate, config, give_up, settle_timeout)
            rec = run.record()
            rec['accuracy'] = accuracy(run.fmap, scene) if run.fmap is not None else None
            if run.stopped or run.clouds_dropped:
                skip = f'skipped: {rate:g}x ' + ('was given up' if run.stopped else
                                                  f'dropped {run.clouds_dropped} of {run.clouds_in} clouds')
            del run
        runs.append(rec)
        if say is not None:
            say(format_run(rec))
    out = {'drive': drive.describe(), 'name': drive.name, 'building_points': drive.building_points,
           'clouds': len(drive.clouds), 'sensor_seconds': drive.seconds, 'runs': runs, 'sustained': sustained(runs),
           'batch': None}
    batch_seconds = float('nan')
    if batch is None and any(r.get('accuracy') for r in runs):
        batch, batch_seconds = batch_map(drive, config)
    if batch is not None:
        out['batch'] = {'accuracy': accuracy(batch, scene), 'seconds': batch_seconds,
                        'building_points_per_s': drive.building_points / batch_seconds}
    return out


def sustained(runs: list[dict], max_p95: float | None = None) -> float | None:
    """The highest rate that ran to the end with no cloud dropped (or failed), and with a p95
    latency of at most ``max_p95`` seconds if given; None if none did."""
    ok = [r['rate'] for r in runs
          if 'skipped' not in r and not r['clouds_dropped'] and not r['clouds_failed'] and not r['stopped']
          and (max_p95 is None or r['latency_p95_s'] <= max_p95)]
    return max(ok) if ok else None


#: The issue's latency target at the sustained rate: p95 from arrival to queryable, s.
TARGET_P95 = 1.0


HEADER = (f'{"rate":>5s} {"clouds":>7s} {"mapped":>7s} {"dropped":>7s} {"bld pts/s":>10s} {"lat p50":>8s} '
          f'{"p95":>6s} {"max":>6s} {"settled":>8s} {"peak MB":>11s} {"RMSE":>7s} {"cov95":>6s}  note')


def format_run(r: dict) -> str:
    """One table line of a run (see :data:`HEADER`)."""
    if 'skipped' in r:
        return f'{r["rate"]:>4g}x {"-":>7s} {"-":>7s} {"-":>7s} {"-":>10s} {"-":>8s} {"-":>6s} {"-":>6s} {"-":>8s} {"-":>11s} ' \
               f'{"-":>7s} {"-":>6s}  {r["skipped"]}'
    acc = r.get('accuracy')
    rmse = f'{acc["rmse_m"] * 100:5.2f}cm' if acc else '      -'
    cov = f'{acc["coverage95"]:6.3f}' if acc else '     -'
    note = r['stopped'] or ''
    if r['clouds_failed']:
        note = f'{r["clouds_failed"]} failed; ' + note
    if r['clouds_discarded']:
        note += f' ({r["clouds_discarded"]} waiting discarded)'
    return (f'{r["rate"]:>4g}x {r["clouds_in"]:>7,} {r["clouds_mapped"]:>7,} {r["clouds_dropped"]:>7,} '
            f'{r["building_points_per_s"]:>10,.0f} {r["latency_p50_s"]:>7.2f}s {r["latency_p95_s"]:>5.1f}s '
            f'{r["latency_max_s"]:>5.1f}s {r.get("settle_s", float("nan")):>7.1f}s '
            f'{r["peak_parent_mb"]:>5.0f}+{r["peak_child_mb"]:<5.0f} {rmse} {cov}  {note}')


def format_drive(result: dict) -> list[str]:
    """The table of one drive, its sustained rate and its accuracy lines."""
    lines = [f'stream {result["drive"]}', HEADER]
    lines += [format_run(r) for r in result['runs']]
    best = result['sustained']
    rate_1x = result['building_points'] / result['sensor_seconds']
    first = result['runs'][0]
    if best is None:
        lines.append(f'sustained: none of the rates tried; at {first["rate"]:g}x {first["clouds_dropped"]:,} of '
                     f'{first["clouds_in"]:,} clouds dropped' + (f', {first["stopped"]}' if first['stopped'] else ''))
    else:
        run = next(r for r in result['runs'] if r['rate'] == best)
        note = ''
        if run['building_points_per_s'] < 0.5 * best * rate_1x:  # the queue, not the mapper, kept up
            note = (f'; but it mapped {run["building_points_per_s"]:,.0f}/s: the queue (node.queue_points) held the '
                    'backlog, a longer drive would drop clouds')
        lines.append(f'sustained: {best:g}x with no dropped cloud ({best * rate_1x:,.0f} building points/s of input; '
                     f'latency p95 {run["latency_p95_s"]:.2f} s{note})')
    fast = sustained(result['runs'], TARGET_P95)
    lines.append(f'sustained with latency p95 <= {TARGET_P95:g} s: ' +
                 (f'{fast:g}x ({fast * rate_1x:,.0f} building points/s of input)' if fast else 'none of the rates tried'))
    b = result['batch']
    if b is None:
        lines.append('accuracy: no streamed map finished (and no batch map built to compare with)')
    else:
        acc = b['accuracy']
        timed = f'built in {b["seconds"]:.1f} s, {b["building_points_per_s"]:,.0f} building points/s' \
            if np.isfinite(b['seconds']) else "the build stage's map"
        lines.append(f'accuracy vs simulated truth (mean surface at raster cells within 0.1 m of the points, off depth '
                     f'steps): batch map of all {result["building_points"]:,} building points '
                     f'{acc["rmse_m"] * 100:.2f} cm RMSE, coverage {acc["coverage95"]:.3f} ({acc["cells"]:,} cells, '
                     f'{acc["facades"]} façades; {timed})')
        for r in result['runs']:
            a = r.get('accuracy')
            if a:
                lines.append(f'  streamed {r["rate"]:g}x: {a["rmse_m"] * 100:.2f} cm RMSE '
                             f'({a["rmse_m"] / acc["rmse_m"]:.2f}x the batch map), coverage {a["coverage95"]:.3f} '
                             f'({a["cells"]:,} cells, {a["facades"]} façades; {r["building_points_mapped"]:,} '
                             f'building points mapped)')
    lines.append('latency: from a cloud\'s arrival to its points stored and queryable; settled: from the last cloud\'s '
                 'arrival until every stored point was modelled and the idle flush (node.idle_flush) done')
    lines.append('peak MB: this process (reset per rate; it holds the drive) + the mapping process')
    return lines


# ------------------------------------------------------------------------------------------
# Laps: the cost of driving the same street again
# ------------------------------------------------------------------------------------------
#: Laps of the street the ``stream_laps`` stage drives.
LAPS = 5
#: Metres of fresh Gaussian noise on every coordinate of each lap after the first.
LAP_NOISE = 0.01


def drive_laps(drive: Drive, laps: int = LAPS, noise: float = LAP_NOISE, config: Any = None) -> list[dict]:
    """Drive the same street ``laps`` times through the live path's two tiers, in one process:
    each cloud stored (``FacadeMap.store_points``), then modelled until the model has caught
    up (``model_step`` while it has work), as the worker does when no cloud waits. Every lap
    after the first adds ``noise`` m of fresh Gaussian noise (seeded per lap).

    Returns:
        Per lap: ``lap``, ``cpu_s`` (process CPU seconds of the lap), ``building_points`` (fed),
        ``stored`` (building points stored in the map at the lap's end), ``map_mb`` (the map's
        own size then: its pickle, MB, measured outside the lap's CPU), ``rss_mb`` (this
        process's resident memory then, MB: the drive's clouds and the allocator's slack too).
    """
    from uncertain_facade_map.mapping.facade_map import FacadeMap
    from uncertain_facade_map.params import Config, map_params

    cfg = config or Config()
    fmap = FacadeMap(map_params(cfg), drive.map_origin)
    step = fmap.params.update.step_points
    out = []
    for lap in range(laps):
        rng = np.random.default_rng([lap])
        cpu = time.process_time()
        for cloud in drive.clouds:
            xyz = cloud.xyz if lap == 0 else cloud.xyz + rng.normal(0.0, noise, cloud.xyz.shape)
            fmap.store_points(xyz, cloud.building_id, cloud.sensor_origins)
            while fmap.needs_model:
                fmap.model_step(step)
        cpu = time.process_time() - cpu
        out.append({'lap': lap + 1, 'cpu_s': cpu, 'building_points': drive.building_points,
                    'stored': fmap.n_stored, 'map_mb': len(pickle.dumps(fmap, pickle.HIGHEST_PROTOCOL)) / 1e6,
                    'rss_mb': _vm_kb('self', 'VmRSS') / 1024.0})
    return out


def format_laps(rows: list[dict]) -> list[str]:
    """The laps table (see :func:`drive_laps`)."""
    lines = ['stream laps (the street driven again, 1 cm of fresh noise a lap; one process: each cloud stored, '
             'then modelled until caught up)',
             f'{"lap":>4s} {"CPU s":>7s} {"x lap 1":>8s} {"stored":>11s} {"map MB":>7s} {"RSS MB":>7s}']
    for r in rows:
        lines.append(f'{r["lap"]:>4d} {r["cpu_s"]:>7.1f} {r["cpu_s"] / rows[0]["cpu_s"]:>7.2f}x {r["stored"]:>11,} '
                     f'{r["map_mb"]:>7.0f} {r["rss_mb"]:>7.0f}')
    return lines


# ------------------------------------------------------------------------------------------
# Real sweeps: ../shared/tools/real_check.py with a streamed build
# ------------------------------------------------------------------------------------------
#: Clouds a real sweep is cut into (by azimuth about the sensor, as a spinning lidar sends it).
REAL_CLOUDS = 10


def real_sweeps(shared: Path = SHARED) -> list[Path]:
    """The shared real sweeps (``shared/data/real/*.ply``), [] when absent."""
    folder = shared / 'data' / 'real'
    return sorted(folder.glob('*.ply')) if folder.is_dir() else []


def _load_real_check(shared: Path = SHARED) -> Any:
    """The independent checker's module, imported from its file (its functions, not a copy)."""
    import importlib.util

    path = shared / 'tools' / 'real_check.py'
    spec = importlib.util.spec_from_file_location('real_check', path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def sweep_sensor(ply: Path, shared: Path = SHARED) -> np.ndarray:
    """(3,) the sensor position real_check.py takes for a sweep: the mean of its origin fields,
    else (0, 0, 1.8) (a sweep in its vehicle's frame)."""
    _, origins = _load_real_check(shared).read_ply(str(ply))
    return origins.mean(0) if origins is not None else np.array([0.0, 0.0, 1.8])


_ROW = re.compile(r'^(this package|local plane \(12 nn\))\s+([-\d.na]+)m\s+([-\d.na]+)\s+([-\d.na]+)m\s+([-\d.na]+)'
                  r'\s+([-\d.na]+)\s+([-\d.na]+)\s*$')
_KEYS = ('obs_rmse_m', 'obs_cov95', 'patch_rmse_m', 'patch_cov95', 'prauc', 'answered')


def parse_real_check(text: str) -> dict:
    """real_check.py's table as {row name: {figure: value}}, and its first line as 'about'."""
    out: dict = {'about': text.splitlines()[0] if text.strip() else ''}
    for line in text.splitlines():
        m = _ROW.match(line.strip())
        if m:
            out[m.group(1)] = dict(zip(_KEYS, (float(v) for v in m.groups()[1:])))
    return out


def real_check(ply: Path, shared: Path = SHARED, clouds: int = REAL_CLOUDS, timeout: float = 600.0) -> dict:
    """real_check.py on one sweep, with the map streamed (this module's ``build``) and built in
    one batch (the package's command line).

    Returns:
        ``{'file', 'about', 'streamed': {...}, 'batch': {...}, 'local plane': {...}, 'seconds'}``,
        the figures as real_check.py prints them (RMSE in m).
    """
    script = shared / 'tools' / 'real_check.py'
    sensor = sweep_sensor(ply, shared)
    out: dict = {'file': ply.name}
    started = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix='ufm-real-') as work:
        wrapper = Path(work) / 'streamed-build'
        at = ','.join(f'{v:.6f}' for v in sensor)
        wrapper.write_text(f'#!/bin/sh\nexec "{sys.executable}" -m uncertain_facade_map_apps.bench_stream '
                           f'--clouds {clouds} --sensor {at} "$@"\n')
        wrapper.chmod(0o755)
        cli = Path(sys.executable).with_name('uncertain-facade-map')
        for name, command in (('streamed', wrapper), ('batch', cli)):
            done = subprocess.run([sys.executable, str(script), '--ply', str(ply), '--cli', str(command)],
                                  capture_output=True, text=True, timeout=timeout)
            if done.returncode != 0:
                raise RuntimeError(f'real_check.py failed on {ply.name} ({name}): {done.stdout[-800:]}'
                                   f'{done.stderr[-800:]}')
            table = parse_real_check(done.stdout)
            out['about'] = table['about']
            out[name] = table.get('this package')
            out['local plane'] = table.get('local plane (12 nn)')
    out['seconds'] = time.perf_counter() - started
    return out


def format_real(results: list[dict]) -> list[str]:
    """The real sweeps' table."""
    lines = [f'stream real sweeps (../shared/tools/real_check.py; streamed: its training points cut by azimuth about '
             f'the sensor into {REAL_CLOUDS} clouds, fed through a MapWorker as the node is fed)',
             f'{"sweep":22s} {"map":18s} {"obs RMSE":>9s} {"obs cov95":>9s} {"patch RMSE":>10s} {"patch cov95":>11s} '
             f'{"PR-AUC.1":>8s} {"answered":>8s}']
    for r in results:
        for name in ('streamed', 'batch', 'local plane'):
            m = r.get(name)
            if m:
                lines.append(f'{r["file"]:22s} {name:18s} {m["obs_rmse_m"]:>8.3f}m {m["obs_cov95"]:>9.3f} '
                             f'{m["patch_rmse_m"]:>9.3f}m {m["patch_cov95"]:>11.3f} {m["prauc"]:>8.3f} '
                             f'{m["answered"]:>8.3f}')
    return lines


# ------------------------------------------------------------------------------------------
# The command line real_check.py calls: build (streamed) and query (the package's)
# ------------------------------------------------------------------------------------------
def azimuth_clouds(xyz: np.ndarray, sensor: np.ndarray, clouds: int) -> list[np.ndarray]:
    """Indices of ``xyz`` (N, 3) cut into ``clouds`` sectors of azimuth about ``sensor`` (3,),
    in turning order (a spinning lidar's packets of one sweep); empty sectors left out."""
    azimuth = np.arctan2(xyz[:, 1] - sensor[1], xyz[:, 0] - sensor[0])  # -pi..pi
    sector = np.minimum(((azimuth + np.pi) / (2 * np.pi) * clouds).astype(np.int64), clouds - 1)
    order = np.argsort(sector, kind='stable')
    bounds = np.searchsorted(sector[order], np.arange(1, clouds))
    return [part for part in np.split(order, bounds) if len(part)]


def _cmd_build(args: argparse.Namespace) -> int:
    """``build INPUT --out MAP``: as the package's ``build`` (same reading and selection), but the
    building points streamed through a ``MapWorker`` built as the node builds it."""
    from msg_adapters.bag_io import load_inputs
    from uncertain_facade_map.io.inputs import select_building_points
    from uncertain_facade_map.io.map_file import save_map
    from uncertain_facade_map.io.parameter_file import load_config
    from uncertain_facade_map.mapping.worker import Cloud

    config = load_config(None)
    cloud = load_inputs(args.inputs, max_distance=config.input.max_distance, warn=print, config=config)
    points = select_building_points(cloud, config.input, config.selection)
    sensor = np.asarray(args.sensor, dtype=np.float64) - points.map_origin
    parts = azimuth_clouds(points.xyz, sensor, args.clouds)

    def pick(a: np.ndarray | None, idx: np.ndarray) -> np.ndarray | None:
        return None if a is None else a[idx]

    clouds = [Cloud(points.xyz[i], pick(points.building_id, i), pick(points.sensor_origins, i), k)
              for k, i in enumerate(parts)]
    sweep = Drive('real', '', 'real', clouds, np.arange(len(clouds)) * (PERIOD / len(clouds)), PERIOD, len(cloud),
                  len(points), points.map_origin)
    run = stream_drive(sweep, 1.0, config)
    if run.stopped or run.fmap is None:
        print(f'streaming did not finish: {run.stopped}', file=sys.stderr)
        return 1
    save_map(run.fmap, Path(args.out))
    print(f'streamed {run.clouds_in} clouds ({run.clouds_mapped} mapped, {run.clouds_dropped} dropped) of '
          f'{len(points):,} building points: {len(run.fmap.facades)} façades, latency p50 {run.latency(0.5):.2f} s, '
          f'max {run.latency(1.0):.2f} s')
    return 0


def _sensor(text: str) -> tuple[float, float, float]:
    values = tuple(float(v) for v in text.split(','))
    if len(values) != 3:
        raise argparse.ArgumentTypeError(f'expected X,Y,Z, got {text!r}')
    return values  # type: ignore[return-value]


def main(argv: list[str] | None = None) -> int:
    """``build`` (streamed) or ``query`` (the package's), as real_check.py calls its ``--cli``."""
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = argparse.ArgumentParser(prog='python -m uncertain_facade_map_apps.bench_stream',
                                     description='build a map streamed as the node maps (for real_check.py); '
                                                 'query: the package\'s own command')
    parser.add_argument('--clouds', type=int, default=REAL_CLOUDS, help='clouds per input, cut by azimuth')
    parser.add_argument('--sensor', type=_sensor, default=(0.0, 0.0, 1.8), metavar='X,Y,Z',
                        help='sensor position (georeferenced, as the input), the centre of the azimuth cut')
    parser.add_argument('command', choices=('build', 'query'))
    args, rest = parser.parse_known_args(argv)
    if args.command == 'query':
        from uncertain_facade_map_apps.cli import main as cli_main

        return cli_main(['query', *rest])
    build = argparse.ArgumentParser(prog='build')
    build.add_argument('inputs', nargs='+')
    build.add_argument('--out', required=True)
    build_args = build.parse_args(rest)
    build_args.clouds, build_args.sensor = args.clouds, args.sensor
    return _cmd_build(build_args)


if __name__ == '__main__':
    raise SystemExit(main())


__all__ = ['DRIVES', 'RATES', 'Drive', 'StreamRun', 'accuracy', 'batch_map', 'format_drive', 'format_real',
           'measure_drive', 'real_check', 'real_sweeps', 'simulate_drive', 'stream_drive', 'sustained']
