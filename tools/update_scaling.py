"""Update time and memory of live mapping against the size of the map (issue 13).

Feeds the street drive to a :class:`~uncertain_facade_map.mapping.facade_map.FacadeMap` the
way the node's worker does (0.1 s scans, ``add_points(..., defer=True)``, so one update per
``update.batch_points`` points), re-driving the same street in several campaigns (lanes and
directions alternate) to reach millions of points, and prints per update: the points
received, the points the map stores, the update's seconds, the process RSS and the bytes per
received point. Ends with medians per range of received points.

    .venv/bin/python tools/update_scaling.py --campaigns 4
    .venv/bin/python tools/update_scaling.py --campaigns 2 --profile /tmp/update.prof
    .venv/bin/python tools/update_scaling.py --campaigns 5 --shuffle

``--shuffle`` feeds each campaign's batches (runs of scans of ``update.batch_points``
points) in a random order, as the node maps clouds from all along the drive when it drops
most of them under load (``make soak``): each update then touches another part of the street.

The campaigns' building points are cached in ``--cache`` (simulating one takes ~15 s).
"""

from __future__ import annotations

import argparse
import cProfile
import os
import pstats
import time
from pathlib import Path

import numpy as np

from uncertain_facade_map.io.scans import select_scan_points
from uncertain_facade_map.mapping.facade_map import FacadeMap
from uncertain_facade_map.params import InputConfig, MapParams, UpdateParams


def rss_mb() -> float:
    """Resident set size of this process, MB (VmRSS of /proc/self/status)."""
    for line in Path('/proc/self/status').read_text().splitlines():
        if line.startswith('VmRSS:'):
            return int(line.split()[1]) / 1024.0
    return float('nan')


def campaign_scans(scene: str, index: int, period: float, cache: Path) -> list[np.ndarray]:
    """The building points of campaign ``index`` as 0.1 s scans (structured arrays, as the node
    receives them), cached as one .npy per campaign."""
    from uncertain_facade_map.io.cloud import Cloud
    from uncertain_facade_map.simulation.campaign import simulate_campaign
    from uncertain_facade_map.simulation.export import split_scans
    from uncertain_facade_map.simulation.scenes import build_scene

    cache.mkdir(parents=True, exist_ok=True)
    path = cache / f'{scene}_c{index}.npy'
    if path.exists():
        points = np.load(path)
        origin = np.zeros(3)
    else:
        cloud = simulate_campaign(build_scene(scene, 0), index)
        keep = ['x', 'y', 'z', 'origin_x', 'origin_y', 'origin_z', 'time', 'building_id', 'class']
        points = np.ascontiguousarray(cloud.points[keep][cloud.points['class'] == 1])
        np.save(path, points)
        origin = cloud.map_origin
    return [part for _, part in split_scans(Cloud(points, origin), period)]


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--scene', default='street')
    ap.add_argument('--campaigns', type=int, default=4, help='drives of the same street, one after the other')
    ap.add_argument('--period', type=float, default=0.1, help='seconds per scan')
    ap.add_argument('--batch-points', type=int, default=UpdateParams().batch_points)
    ap.add_argument('--shuffle', action='store_true', help="feed each campaign's batches in a random order")
    ap.add_argument('--no-ids', action='store_true', help='drop the building ids (clustering path)')
    ap.add_argument('--profile', type=Path, help='write a cProfile of the feeding here and print its top')
    ap.add_argument('--cache', type=Path, default=Path(os.environ.get('TMPDIR', '/tmp')) / 'ufm_update_scaling')
    args = ap.parse_args(argv)

    params = MapParams(update=UpdateParams(batch_points=args.batch_points))
    config = InputConfig(building_id_field='none' if args.no_ids else 'building_id')
    fmap = FacadeMap(params)
    profiler = cProfile.Profile() if args.profile else None
    rows = []
    received = 0
    print(f'{"update":>6} {"received":>10} {"stored":>10} {"seconds":>8} {"cpu_s":>6} {"rss_MB":>8} '
          f'{"B/received":>10} {"B/stored":>9}', flush=True)
    rng = np.random.default_rng(0)
    base = rss_mb()
    for c in range(args.campaigns):
        scans = campaign_scans(args.scene, c, args.period, args.cache)
        if c == 0:
            base = rss_mb()  # the interpreter, numpy and one campaign's scans
        if args.shuffle:
            sizes = np.cumsum([len(s) for s in scans])
            run = sizes // args.batch_points  # scans of one run fill one batch
            starts = np.flatnonzero(np.r_[True, run[1:] != run[:-1]])
            runs = np.split(np.arange(len(scans)), starts[1:])
            scans = [scans[i] for k in rng.permutation(len(runs)) for i in runs[k]]
        for scan in scans:
            pts = select_scan_points(scan, config)
            received += len(pts.xyz)
            t0, cpu0 = time.perf_counter(), time.process_time()
            if profiler:
                profiler.enable()
            done = fmap.add_points(pts.xyz, pts.building_id, pts.sensor_origins, defer=True)
            if profiler:
                profiler.disable()
            if not done:
                continue
            seconds, cpu = time.perf_counter() - t0, time.process_time() - cpu0
            stored = fmap.n_stored if hasattr(fmap, 'n_stored') else fmap.n_points
            rss = rss_mb()
            rows.append((received, stored, seconds, rss, cpu))
            print(f'{len(rows):6d} {received:10,d} {stored:10,d} {seconds:8.2f} {cpu:6.2f} {rss:8.0f} '
                  f'{(rss - base) * 2**20 / received:10.0f} {(rss - base) * 2**20 / max(stored, 1):9.0f}', flush=True)
        del scans
    t0 = time.perf_counter()
    fmap.flush()
    stored = getattr(fmap, 'n_stored', fmap.n_points)
    print(f'flush: {time.perf_counter() - t0:.1f} s, {len(fmap.facades)} façades, {stored:,} points stored '
          f'of {received:,} received')
    r = np.array(rows)
    print(f'\nmedian update seconds by points received (RSS baseline before the map: {base:.0f} MB)')
    for lo, hi in [(0, 0.5e6), (0.5e6, 1e6), (1e6, 2e6), (2e6, 3e6), (3e6, 4e6), (4e6, 5e6), (5e6, 1e12)]:
        sel = (r[:, 0] > lo) & (r[:, 0] <= hi)
        if sel.any():
            print(f'  {lo / 1e6:3.1f}-{min(hi, r[:, 0].max()) / 1e6:3.1f} M: {np.median(r[sel, 2]):6.2f} s '
                  f'(CPU {np.median(r[sel, 4]):6.2f} s) '
                  f'(max {r[sel, 2].max():5.2f}), stored {r[sel, 1].max():10,.0f}, RSS {r[sel, 3].max():6.0f} MB, '
                  f'{(r[sel, 3].max() - base) * 2**20 / r[sel, 0].max():4.0f} B/received point')
    if profiler:
        profiler.dump_stats(args.profile)
        pstats.Stats(str(args.profile)).sort_stats('cumulative').print_stats(35)


if __name__ == '__main__':
    main()
