"""``uncertain-facade-map capacity``: what a city-scale build costs, from measured figures.

A capacity plan is arithmetic on three measured figures, each printed with what it was
measured on:

1. **The scheduler's overhead per task**: no-op tasks on a local Dask cluster of
   ``--overhead-workers`` processes (one thread each), timed end to end: the wall time per
   task with every worker busy, and the round trip of one task alone (submit to result).
2. **The cost per building point and per tile**: from a tiled build's report
   (``build.json`` in the folder that ``build --tiles`` wrote): each tile task's processor seconds
   against its building points, fitted as ``seconds = per_tile + per_point * points`` (least
   squares); the routing tasks' processor seconds (reading, selecting, surveying and spilling each
   input file on a worker) per input point; and the client's serial part (merging the surveys,
   planning) per input point. A report of a build that routed in the client (no ``route_tasks``)
   gives its reading and routing seconds as the routing work, and no client part.
3. **Memory**: the largest peak RSS of a worker and the largest tile's points.

The plan then scales them to a street network (``--km``, ``--points``, ``--workers``) and
states its assumptions: tiles per km and building points per input point as in the measured
build; tasks spread evenly (routing: input files at least as many as workers, each a task); the
client's merging and planning growing with the input points. Routing in one process (the
``--workers 0`` build) is printed beside it.
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np


def _noop(i: int) -> int:
    return i


@dataclass(frozen=True)
class Overhead:
    """The scheduler's overhead measured on a local cluster."""

    workers: int
    tasks: int
    per_task_s: float     # wall seconds per task, every worker busy, times the workers: worker-seconds a task costs
    round_trip_s: float   # median submit-to-result seconds of one task alone
    start_s: float        # seconds to start the cluster


def scheduler_overhead(workers: int = 2, tasks: int = 2000, round_trips: int = 50) -> Overhead:
    """Time no-op tasks on a local Dask cluster of ``workers`` processes (one thread each)."""
    from dask.distributed import Client, LocalCluster

    started = time.perf_counter()
    with LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=None) as cluster, \
            Client(cluster) as client:
        client.wait_for_workers(workers)
        start_s = time.perf_counter() - started
        client.gather(client.map(_noop, range(100), pure=False))  # warm up
        t0 = time.perf_counter()
        client.gather(client.map(_noop, range(tasks), pure=False))
        wall = time.perf_counter() - t0
        trips = []
        for i in range(round_trips):
            t1 = time.perf_counter()
            client.submit(_noop, i, pure=False).result()
            trips.append(time.perf_counter() - t1)
    return Overhead(workers, tasks, wall * workers / tasks, statistics.median(trips), start_s)


@dataclass(frozen=True)
class BuildCosts:
    """Costs fitted from one tiled build's report."""

    input_points: int
    building_points: int
    tiles: int
    street_km: float | None
    per_point_s: float    # worker-seconds per building point of a tile task
    per_tile_s: float     # worker-seconds per tile task on top (reading its points, writing its file)
    route_per_point_s: float  # worker-seconds per input point of the routing tasks (reading, selecting, spilling)
    peak_rss_mb: float
    largest_tile_points: int
    plan_per_point_s: float = 0.0  # client seconds per input point (merging the surveys, planning)


def build_costs(report: dict, street_km: float | None = None) -> BuildCosts:
    """Fit the per-point and per-tile cost of a build's tile tasks (see the module docstring)."""
    tasks = report['tasks']
    points = np.array([t['points'] for t in tasks], dtype=np.float64)
    # Processor seconds: the task's work, whatever else shared the cores while it ran.
    seconds = np.array([t.get('cpu_seconds', t['seconds']) for t in tasks], dtype=np.float64)
    design = np.column_stack([np.ones_like(points), points])
    (per_tile, per_point), *_ = np.linalg.lstsq(design, seconds, rcond=None)
    if per_tile < 0:  # the intercept is not resolved: all the cost per point
        per_tile, per_point = 0.0, float(seconds.sum() / max(points.sum(), 1.0))
    n_input = max(int(report['input_points']), 1)
    if report.get('route_tasks'):  # routed on the workers: their processor seconds, and the client's part
        route_s = sum(float(t['cpu_seconds']) for t in report['route_tasks'])
        plan_s = float(report.get('plan_seconds') or 0.0)
    else:  # routed in the client (an older report): all of it
        route_s = float(report.get('read_seconds', 0.0)) + float(report.get('route_seconds', 0.0))
        plan_s = 0.0
    return BuildCosts(int(report['input_points']), int(report['building_points']), len(tasks),
                      street_km, float(per_point), float(per_tile), route_s / n_input,
                      max(float(t.get('peak_rss_mb', 0.0)) for t in tasks), int(points.max(initial=0)),
                      plan_s / n_input)


def _hours(seconds: float) -> str:
    return f'{seconds / 3600:,.2f} h ({seconds / 60:,.0f} min)'


def plan(costs: BuildCosts, overhead: Overhead, km: float, points: float, workers: int) -> list[tuple[str, str]]:
    """The plan's rows (what, figure) for ``points`` input points over ``km`` of street on ``workers``."""
    building_share = costs.building_points / max(costs.input_points, 1)
    tiles_per_km = costs.tiles / costs.street_km if costs.street_km else float('nan')
    tiles = km * tiles_per_km
    building = points * building_share
    work = building * costs.per_point_s + tiles * (costs.per_tile_s + overhead.per_task_s)
    mapping_s = work / workers
    route_work_s = points * costs.route_per_point_s
    client_s = points * costs.plan_per_point_s
    route_par_s = route_work_s / workers + client_s
    route_one_s = route_work_s + client_s
    tile_cost = (f'{costs.per_tile_s:.2f} s per tile' if costs.per_tile_s > 0 else
                 'no cost per tile resolved by the fit: all of it per point')
    rows = [
        ('building points', f'{building:.3g} ({building_share:.0%} of {points:.3g} input points, as measured)'),
        ('tiles', f'{tiles:,.0f} ({tiles_per_km:.1f} per km of street, as measured)'),
        ('mapping work', f'{work / 3600:,.1f} worker-hours ({costs.per_point_s * 1e6:.1f} µs per building point, '
                         f'{tile_cost}, {overhead.per_task_s * 1e3:.1f} ms scheduler per task)'),
        (f'mapping on {workers} workers', f'{_hours(mapping_s)} (tasks spread evenly; the largest tile, '
                                          f'{costs.largest_tile_points:,} points, takes '
                                          f'{costs.per_tile_s + costs.largest_tile_points * costs.per_point_s:.0f} s)'),
        (f'routing on {workers} workers', f'{_hours(route_par_s)} ({costs.route_per_point_s * 1e6:.2f} µs of worker '
                                          'time per input point: reading, selecting, surveying, spilling, a task per '
                                          f'input file; then {client_s:,.0f} s in the client, merging the surveys and '
                                          f'planning: {costs.plan_per_point_s * 1e9:.2g} ns per input point)'),
        ('routing, one process', f'{_hours(route_one_s)} (the same work in the client: --workers 0)'),
        ('total', f'{_hours(mapping_s + route_par_s)} ({workers} workers routing and mapping)'),
        ('memory per worker', f'{costs.peak_rss_mb:,.0f} MB peak measured (largest tile {costs.largest_tile_points:,} '
                              'points); a city tile of the same buildings needs the same'),
        ('scheduler', f'{tiles:,.0f} tasks x {overhead.per_task_s * 1e3:.1f} ms = '
                      f'{tiles * overhead.per_task_s / 3600:.2f} worker-hours; round trip '
                      f'{overhead.round_trip_s * 1e3:.1f} ms'),
    ]
    return rows


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog='uncertain-facade-map capacity', description=__doc__.split('\n\n')[0])
    p.add_argument('report', help="a tiled build's build.json (in the folder build --tiles wrote)")
    p.add_argument('--street-km', type=float, required=True,
                   help='km of street the measured build covered (the city scene prints it; scene.json "city")')
    p.add_argument('--overhead-workers', type=int, default=2, help='local cluster size for the overhead (default 2)')
    p.add_argument('--overhead-tasks', type=int, default=2000, help='no-op tasks timed (default 2000)')
    p.add_argument('--km', type=float, default=1000.0, help='km of street to plan for (default 1000)')
    p.add_argument('--points', type=float, default=1e10, help='input points to plan for (default 1e10)')
    p.add_argument('--workers', type=int, default=100, help='workers to plan for (default 100)')
    p.add_argument('--json', metavar='FILE', help='also write the figures as JSON')
    args = p.parse_args(argv)
    report = json.loads(Path(args.report).read_text())
    costs = build_costs(report, args.street_km)
    overhead = scheduler_overhead(args.overhead_workers, args.overhead_tasks)
    print(f'scheduler  {overhead.per_task_s * 1e3:.2f} ms per task (worker time, {overhead.tasks} no-op tasks on '
          f'{overhead.workers} local worker processes), round trip {overhead.round_trip_s * 1e3:.1f} ms, '
          f'cluster start {overhead.start_s:.1f} s')
    print(f'measured   {costs.input_points:,} input points, {costs.building_points:,} building points, {costs.tiles} '
          f'tiles{"" if costs.street_km is None else f", {costs.street_km:.2f} km of street"}: '
          f'{costs.per_point_s * 1e6:.2f} µs per building point + {costs.per_tile_s:.3f} s per tile (processor '
          f'seconds of the tile tasks, fitted), routing {costs.route_per_point_s * 1e6:.2f} µs per input point (processor '
          f'seconds of the routing tasks) + {costs.plan_per_point_s * 1e9:.2g} ns in the client, peak RSS '
          f'{costs.peak_rss_mb:.0f} MB')
    rows = plan(costs, overhead, args.km, args.points, args.workers)
    print(f'\nplan: {args.km:,.0f} km of street, {args.points:.3g} input points, {args.workers} workers')
    width = max(len(r[0]) for r in rows)
    for what, figure in rows:
        print(f'  {what:<{width}}  {figure}')
    if args.json:
        Path(args.json).write_text(json.dumps({'overhead': vars(overhead), 'costs': vars(costs),
                                               'plan': dict(rows)}, indent=1, default=float))
    return 0 if math.isfinite(costs.per_point_s) else 1


if __name__ == '__main__':
    raise SystemExit(main())
