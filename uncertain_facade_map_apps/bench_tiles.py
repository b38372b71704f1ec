"""The facade_mapper node serving a tiled map while its sensor drives: query latency and memory.

``python -m uncertain_facade_map_apps.bench_tiles MAP [--cache-mb MB] [--radius M] ...``

Starts the node (its own process, ``persistence.map_path`` = MAP, a tiled map's folder or
manifest; ``tiles.cache_mb``, ``tiles.radius``, ``tiles.follow_period`` as given) and then, as
a robot and its localiser would, moves the sensor's pose along a route through the map
(``sensor_pose``, ``map`` -> ``lidar``, at ``--speed`` m/s) and at every ``--step`` metres asks
``query_points`` for ``--points`` points near the pose (stored points of the tiles within
``--query-radius`` m, 0.3 m of noise; sampled in this process, before the timed call).

The route: the tiles' squares' centres, visited greedily nearest-first from the tile of the
smallest x, y (the tiles hold buildings, so the route follows the built-up blocks, as streets
do), walked in straight legs. ``--route-tiles`` bounds how many tiles it visits.

Prints, per run: queries, points per query, the latency of ``query_points`` as this client
sees it (median, p95, max; ms), the node's own query p95 (its diagnostics), tiles loaded at
the end and at most, the cache's MB, preloads and their time, and the node process's peak
resident memory (``VmHWM`` of /proc/PID/status) with its resident memory before the drive.
``--json PATH`` writes the figures. ``--one-file MAP_FILE`` drives again, same route and
query points, with the node serving a one-file map (the tiled map's source) and prints the
two side by side. Works on any tiled map; the lead runs it on the city.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from .ros_client import SpinningClient, answers_of, list_tiles_request, query_request, tiles_of

ROOT = Path(__file__).resolve().parents[1]


def route(records: list[Any], step: float, max_tiles: int = 0) -> np.ndarray:
    """(K, 2) map-frame positions every ``step`` metres along a greedy nearest-first tour of
    the tiles' square centres (from the tile of the smallest x, then y)."""
    centres = np.array([[(r.bounds[0] + r.bounds[2]) / 2, (r.bounds[1] + r.bounds[3]) / 2] for r in records])
    if not len(centres):
        return np.zeros((0, 2))
    left = list(range(len(centres)))
    current = min(left, key=lambda i: (centres[i, 0], centres[i, 1]))
    order = [current]
    left.remove(current)
    while left and (not max_tiles or len(order) < max_tiles):
        d = np.hypot(*(centres[left] - centres[current]).T)
        current = left.pop(int(np.argmin(d)))
        order.append(current)
    stops = centres[order]
    out = [stops[0]]
    for a, b in zip(stops[:-1], stops[1:]):
        n = max(1, int(np.ceil(np.hypot(*(b - a)) / step)))
        out.extend(a + (b - a) * (k / n) for k in range(1, n + 1))
    return np.array(out)


def vm_kb(pid: int, key: str) -> int:
    """``VmHWM`` / ``VmRSS`` of a process, kB (0 when it cannot be read)."""
    try:
        for line in Path(f'/proc/{pid}/status').read_text().splitlines():
            if line.startswith(key + ':'):
                return int(line.split()[1])
    except OSError:
        pass
    return 0


class Robot(SpinningClient):
    """Publishes the sensor's pose; calls query_points and list_tiles; keeps the diagnostics."""

    def __init__(self, domain: int) -> None:
        from diagnostic_msgs.msg import DiagnosticArray
        from geometry_msgs.msg import TransformStamped

        super().__init__('bench_tiles_robot', domain)
        self.pose_pub = self.node.create_publisher(TransformStamped, 'sensor_pose', 100)
        self.diag: dict[str, str] = {}
        self.node.create_subscription(DiagnosticArray, '/diagnostics', self._diag, 10)
        self.clients: dict[str, Any] = {}
        self._start()

    def _diag(self, msg: Any) -> None:
        if msg.status and msg.status[0].hardware_id == 'facade_mapper':
            self.diag = {kv.key: kv.value for kv in msg.status[0].values}

    def call(self, srv_type: Any, name: str, request: Any, timeout: float = 120.0) -> Any:
        if name not in self.clients:
            self.clients[name] = self.on_spin_thread(lambda: self.node.create_client(srv_type, name))
        client = self.clients[name]
        if not client.wait_for_service(timeout_sec=60.0):
            raise RuntimeError(f'service {name} not available')
        future = client.call_async(request)
        done = threading.Event()
        future.add_done_callback(lambda _: done.set())
        if not done.wait(timeout):
            raise RuntimeError(f'service {name} did not answer in {timeout} s')
        return future.result()

    def publish_pose(self, xy: np.ndarray, stamp_ns: int) -> None:
        from geometry_msgs.msg import TransformStamped

        pose = TransformStamped()
        pose.header.frame_id, pose.child_frame_id = 'map', 'lidar'
        pose.header.stamp.sec, pose.header.stamp.nanosec = divmod(int(stamp_ns), 10**9)
        pose.transform.translation.x, pose.transform.translation.y = float(xy[0]), float(xy[1])
        pose.transform.translation.z = 1.8
        pose.transform.rotation.w = 1.0
        self.pose_pub.publish(pose)


def node_params(path: Path, folder: str, args: argparse.Namespace) -> Path:
    """The node's parameter file: the defaults with the tiled map and the tiles' settings."""
    from uncertain_facade_map.io.parameter_file import dump_config
    from uncertain_facade_map.params import Config

    config = Config()
    config = dataclasses.replace(
        config,
        persistence=dataclasses.replace(config.persistence, map_path=str(folder), autosave_period=0.0),
        tiles=dataclasses.replace(config.tiles, cache_mb=args.cache_mb, radius=args.radius,
                                  follow_period=args.follow_period,
                                  **({'view_tiles': args.view_tiles} if args.view_tiles else {})),
        service=dataclasses.replace(config.service, max_query_points=max(args.points, config.service.max_query_points)),
        publish=dataclasses.replace(config.publish, diagnostics_period=0.5))
    path.write_text(dump_config(config))
    return path


def sample_near(tiled: Any, xy: np.ndarray, radius: float, n: int, rng: np.random.Generator) -> np.ndarray:
    """(n, 3) points near ``xy``: stored points of the tiles within ``radius`` m (those within
    ``radius`` of it in x, y when there are any), 0.3 m of noise; uniform in a box without any."""
    parts = []
    for rec in tiled.tiles_near(xy, radius):
        for pts in tiled.tile(rec.id).points.values():
            parts.append(pts)
    if parts:
        pts = np.vstack(parts)
        close = pts[np.hypot(*(pts[:, :2] - xy).T) <= radius]
        pts = close if len(close) else pts
        return pts[rng.integers(0, len(pts), n)] + rng.normal(0.0, 0.3, (n, 3))
    return np.column_stack([xy + rng.uniform(-radius, radius, (n, 2)), rng.uniform(0.0, 10.0, n)])


def run(args: argparse.Namespace, served: str | None = None) -> dict[str, Any]:
    """One drive of the node serving ``served`` (default: the tiled map ``args.map``; a one-file
    map for the comparison) along the tiled map's route, with the same query points."""
    from uncertain_facade_map.srv import ListTiles, QueryPoints
    from uncertain_facade_map.tiling.tiled_map import TiledMap

    folder = str(Path(args.map).resolve())
    tiled = served is None
    served = folder if tiled else str(Path(served).resolve())
    # This process's own reader (for the route and the query points): a small cache of its own.
    reader = TiledMap(folder, cache_mb=args.reader_cache_mb)
    path = route(reader.records, args.step, args.route_tiles)
    if args.max_steps:
        path = path[:args.max_steps]
    domain = args.domain if args.domain >= 0 else 100 + os.getpid() % 100
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST')
    work = Path(tempfile.mkdtemp(prefix='bench_tiles_'))
    log = work / 'node.log'
    params = node_params(work / 'params.yaml', served, args)
    rng = np.random.default_rng(args.seed)
    robot = Robot(domain)
    proc = subprocess.Popen([sys.executable, '-m', 'uncertain_facade_map_node.node', '--ros-args', '--params-file',
                             str(params)], env=env, cwd=ROOT, stdout=open(log, 'ab'), stderr=subprocess.STDOUT)
    latencies, tiles_max, rss_samples, answered = [], 0, [], 0
    try:
        deadline = time.monotonic() + 120
        while 'façades' not in log.read_text():
            if proc.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f'the node did not start:\n{log.read_text()[-3000:]}')
            time.sleep(0.2)
        first = robot.call(ListTiles, 'list_tiles', list_tiles_request(*path[0], 1.0))
        if first.success != tiled:
            raise RuntimeError(f'the node serves {"no" if tiled else "a"} tiled map: {first.message}')
        rss_start = vm_kb(proc.pid, 'VmRSS')
        stamp = time.time_ns()
        began = time.monotonic()
        for k, xy in enumerate(path):
            due = began + k * args.step / args.speed
            time.sleep(max(0.0, due - time.monotonic()))
            robot.publish_pose(xy, stamp + int((time.monotonic() - began) * 1e9))
            xyz = sample_near(reader, xy, args.query_radius, args.points, rng)
            t0 = time.perf_counter()
            response = robot.call(QueryPoints, 'query_points', query_request(xyz, flat=True))
            latencies.append(time.perf_counter() - t0)
            if not response.success:
                raise RuntimeError(f'query failed: {response.message}')
            answered += int((answers_of(response)['facade'] >= 0).sum())
            tiles_max = max(tiles_max, int(robot.diag.get('tiles_loaded', 0) or 0))
            rss_samples.append(vm_kb(proc.pid, 'VmRSS'))
            if args.verbose and k % max(1, len(path) // 20) == 0:
                print(f'  step {k}/{len(path)} at ({xy[0]:.0f}, {xy[1]:.0f}): {1e3 * latencies[-1]:.1f} ms, '
                      f'{robot.diag.get("tiles_loaded", "?")} tiles loaded, RSS {rss_samples[-1] / 1024:.0f} MB',
                      flush=True)
        time.sleep(1.5 * max(0.5, args.follow_period))
        near = tiles_of(robot.call(ListTiles, 'list_tiles', list_tiles_request(*path[-1], 0.0))) if tiled \
            else {'ids': [], 'loaded': np.zeros(0, bool)}
        peak_kb = vm_kb(proc.pid, 'VmHWM')
        diag = dict(robot.diag)
    finally:
        robot.close()
        if proc.poll() is None:
            proc.send_signal(2)
            try:
                proc.wait(20)
            except subprocess.TimeoutExpired:
                proc.kill()
    ms = 1e3 * np.array(latencies)
    return {
        'map': served, 'tiles': len(reader.records), 'cache_mb': args.cache_mb, 'radius_m': args.radius,
        'view_tiles': args.view_tiles or 'default',
        'follow_period_s': args.follow_period, 'route_m': float(np.sum(np.hypot(*np.diff(path, axis=0).T))),
        'steps': len(path), 'points_per_query': args.points,
        'share_on_a_facade': round(answered / max(1, args.points * len(path)), 3),
        'latency_ms_median': round(float(np.median(ms)), 2) if len(ms) else None,
        'latency_ms_p95': round(float(np.percentile(ms, 95)), 2) if len(ms) else None,
        'latency_ms_max': round(float(ms.max()), 2) if len(ms) else None,
        'node_query_p95_ms': float(diag.get('query_p95_ms', 'nan')),
        'tiles_loaded_end': int(diag.get('tiles_loaded', 0) or 0), 'tiles_loaded_max': tiles_max,
        'tiles_near_end_loaded': f'{int(near["loaded"].sum())} of {len(near["ids"])}',
        'cache_mb_end': float(diag.get('tiles_cache_mb', 'nan')),
        'preloads': int(diag.get('tiles_preloads', 0) or 0),
        'preload_mean_s': float(diag.get('tiles_preload_mean_seconds', 'nan')),
        'preload_max_s': float(diag.get('tiles_preload_max_seconds', 'nan')),
        'tile_misses': int(diag.get('tiles_misses', 0) or 0), 'tile_evictions': int(diag.get('tiles_evictions', 0) or 0),
        'node_rss_mb_start': round(rss_start / 1024, 1), 'node_rss_mb_max_sampled': round(max(rss_samples, default=0) / 1024, 1),
        'node_peak_rss_mb': round(peak_kb / 1024, 1), 'node_log': str(log),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog='python -m uncertain_facade_map_apps.bench_tiles',
                                     description=__doc__.split('\n\n')[1],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('map', help="a tiled map's folder (or its manifest.json)")
    parser.add_argument('--cache-mb', type=float, default=512.0, help='tiles.cache_mb of the node (default 512)')
    parser.add_argument('--radius', type=float, default=150.0, help='tiles.radius of the node, m (default 150)')
    parser.add_argument('--follow-period', type=float, default=1.0, help='tiles.follow_period, s (default 1)')
    parser.add_argument('--view-tiles', type=int, default=0,
                        help="tiles.view_tiles of the node (0: the parameter's default)")
    parser.add_argument('--speed', type=float, default=10.0, help='the sensor moves at this speed, m/s (default 10)')
    parser.add_argument('--step', type=float, default=5.0, help='a query every STEP metres (default 5)')
    parser.add_argument('--points', type=int, default=2000, help='points per query (default 2000)')
    parser.add_argument('--query-radius', type=float, default=40.0,
                        help='query points within this distance of the pose, m (default 40)')
    parser.add_argument('--route-tiles', type=int, default=0, help='visit at most this many tiles (0: all)')
    parser.add_argument('--max-steps', type=int, default=0, help='stop after this many queries (0: the whole route)')
    parser.add_argument('--reader-cache-mb', type=float, default=256.0,
                        help="this process's own reader's cache (for the query points), MB")
    parser.add_argument('--domain', type=int, default=-1, help='ROS_DOMAIN_ID (default: 100 + pid %% 100)')
    parser.add_argument('--seed', type=int, default=0)
    parser.add_argument('--one-file', metavar='MAP_FILE',
                        help='then drive the same route with the same queries against the node serving this one-file '
                             'map (the tiled map\'s source, say) and print both')
    parser.add_argument('--json', type=Path, help='write the figures here')
    parser.add_argument('--verbose', action='store_true', help='a line every 5 %% of the route')
    args = parser.parse_args(argv)
    figures = run(args)
    if args.one_file:
        one = run(args, args.one_file)
        figures = {'tiled': figures, 'one_file': one}
        width = max(map(len, one))
        print(f'{"":{width}}  tiled map | one-file map')
        for key in one:
            print(f'{key:{width}}  {figures["tiled"][key]} | {one[key]}')
    else:
        for key, value in figures.items():
            print(f'{key}: {value}')
    if args.json:
        args.json.write_text(json.dumps(figures, indent=1) + '\n')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
