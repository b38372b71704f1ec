"""Queries per second of a tiled map (cache warm) against the one-file map it was cut from (issue 29).

The query points: a drive's points in scans of ``--scan`` seconds (by its time field), as a
localiser asks them (``--scans`` of them, spread over the drive), and every other point of the
drive in one batch. Prints the median of ``--repeats`` runs of each map, alternated.

    .venv/bin/uncertain-facade-map simulate --scene street --out /tmp/street --formats npz
    .venv/bin/uncertain-facade-map build /tmp/street/campaign0.npz --out /tmp/street.npz
    .venv/bin/uncertain-facade-map tile /tmp/street.npz --out /tmp/street_tiles --side 50
    .venv/bin/python tools/bench_tiles.py /tmp/street.npz /tmp/street_tiles /tmp/street/campaign0.npz

``--view-tiles K`` sets ``tiles.view_tiles`` (the side of the views that answer, in tiles).
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np

from uncertain_facade_map.io.clouds import read_cloud
from uncertain_facade_map.io.map_file import load_map
from uncertain_facade_map.params import QueryConfig, TilesConfig
from uncertain_facade_map.tiling.tiled_map import TiledMap


def _run(fmap, batches, config) -> float:
    t0 = time.perf_counter()
    for b in batches:
        fmap.query(b, config)
    return time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('map', help='the one-file map')
    ap.add_argument('tiled', help='the tiled map cut from it')
    ap.add_argument('cloud', help='a drive (any cloud file with x, y, z, time: NPZ, PLY, ...)')
    ap.add_argument('--tiled-clouds', nargs='+', metavar='CLOUD',
                    help="another drive for the tiled map (the city's segment files), when the tiled map is not cut "
                         'from MAP: each map is then timed on its own drive (issue 29: the tiled city against a '
                         'one-file street)')
    ap.add_argument('--scan', type=float, default=0.1, help='seconds of drive per scan (default 0.1)')
    ap.add_argument('--tiled-scan', type=float, help='seconds of drive per scan of the tiled map\'s own drive (default '
                    '--scan; the city sensor gives fewer points a second than the street\'s)')
    ap.add_argument('--scans', type=int, default=200, help='scans timed, spread over the drive (default 200)')
    ap.add_argument('--repeats', type=int, default=5, help='runs of each map (default 5)')
    ap.add_argument('--surface', default='local', choices=('local', 'raster'), help='query.surface')
    ap.add_argument('--view-tiles', type=int, default=TilesConfig.view_tiles, help='tiles.view_tiles')
    ap.add_argument('--cache-mb', type=float, default=TilesConfig.cache_mb, help='tiles.cache_mb')
    args = ap.parse_args()
    config = QueryConfig(surface=args.surface)
    xyz, scans = _scans([args.cloud], args, args.scan)
    if args.tiled_clouds:
        xyz_t, scans_t = _scans(args.tiled_clouds, args, args.tiled_scan or args.scan)
    else:
        xyz_t, scans_t = xyz, scans
    n_scan, n_scan_t = sum(len(s) for s in scans), sum(len(s) for s in scans_t)
    for what, x, sc, n in (('one-file', xyz, scans, n_scan), ('tiled', xyz_t, scans_t, n_scan_t)):
        print(f'{what}: {len(x):,} points; {len(sc)} scans timed ({n:,} points, median '
              f'{int(np.median([len(s) for s in sc])):,} a scan); query.surface {args.surface}; view_tiles {args.view_tiles}')
    one = load_map(args.map)
    tiled = TiledMap(args.tiled, args.cache_mb, args.view_tiles)
    for name, fmap, sc in (('one-file', one, scans), ('tiled', tiled, scans_t)):
        t0 = time.perf_counter()
        _run(fmap, sc, config)  # warm: every structure built, every tile loaded
        print(f'{name} warm-up {time.perf_counter() - t0:.1f} s')
    info = tiled.cache_info()
    print(f'cache: {len(info["tiles"])} tiles ({info["tile_bytes"] / 1e6:.0f} MB), {len(info["views"])} views, '
          f'{info["bytes"] / 1e6:.0f} MB in all; {info["misses"]} loads in {info["load_seconds"]:.2f} s, '
          f'{info["views_built"]} views built in {info["view_seconds"]:.2f} s')
    work = (('scans', scans, n_scan, scans_t, n_scan_t),
            ('one batch', [xyz[::2]], len(xyz[::2]), [xyz_t[::2]], len(xyz_t[::2])))
    for name, batches, n, batches_t, n_t in work:
        a, b = [], []
        for _ in range(args.repeats):
            a.append(_run(one, batches, config))
            b.append(_run(tiled, batches_t, config))
        ma, mb = statistics.median(a), statistics.median(b)
        ra, rb = n / ma, n_t / mb
        print(f'{name:9s}  one-file {ra:10,.0f} points/s ({ma:.2f} s)  tiled {rb:10,.0f} points/s '
              f'({mb:.2f} s)  tiled / one-file {rb / ra:.2f}  (medians of {args.repeats})')


def _scans(paths: list[str], args: argparse.Namespace, seconds: float) -> tuple[np.ndarray, list[np.ndarray]]:
    """(N, 3) points of the drive files and ``args.scans`` scans of ``seconds`` s spread over them."""
    clouds = [read_cloud(p) for p in paths]
    xyz = np.vstack([c.xyz for c in clouds]).astype(np.float64)
    t = np.concatenate([c.points['time'] for c in clouds])
    scan = np.floor((t - t.min()) / seconds).astype(np.int64)
    order = np.argsort(scan, kind='stable')
    parts = np.split(order, np.flatnonzero(np.diff(scan[order])) + 1)
    pick = np.linspace(0, len(parts) - 1, min(args.scans, len(parts))).astype(int)
    return xyz, [xyz[parts[i]] for i in pick]


if __name__ == '__main__':
    main()
