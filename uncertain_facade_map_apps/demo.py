"""``make demo``: the main job on the built-in default, end to end through ROS.

1. simulate the default street drive and record it as a ROS 2 bag (mcap);
2. start the facade_mapper node in its own process;
3. replay the bag to it in publish mode, with the recorded timing;
4. act as a localisation node: wait for the map to settle, then query it with points
   along the façades through the ``query_points`` service;
5. save the map through ``save_map`` and draw its figures (:mod:`uncertain_facade_map_apps.plots`);
6. localise scans of another drive against it with the ``facade_localizer`` node
   (:mod:`uncertain_facade_map_apps.demo_localise`) and draw the trajectory and its errors;
7. print a short summary with the paths.

Everything lands in one folder (default ``output/demo``).
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent


def _config_file(out: Path) -> Path:
    """The demo's parameter file: the defaults, a reliable input and a queue the whole drive fits in."""
    from uncertain_facade_map.io.parameter_file import dump_config
    from uncertain_facade_map.params import Config

    config = Config()
    # Maps are published every 20 s: drawing the street's maps takes seconds the mapping needs.
    config = dataclasses.replace(config, node=dataclasses.replace(config.node, qos='reliable', queue_size=2000),
                                 publish=dataclasses.replace(config.publish, period=20.0),
                                 persistence=dataclasses.replace(config.persistence, map_path=str(out / 'map.npz')))
    path = out / 'facade_mapper.yaml'
    path.write_text(dump_config(config))
    return path


class _Localisation:
    """A minimal localisation node: reads diagnostics, calls the map's services."""

    def __init__(self) -> None:
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray

        self.rclpy = rclpy
        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        self.node = rclpy.create_node('demo_localisation', context=self.context)
        self.values: dict[str, str] = {}
        self.node.create_subscription(DiagnosticArray, '/diagnostics', self._diagnostics_callback, 10)
        self._stop = False
        self._thread = threading.Thread(target=self._spin, daemon=True)
        self._thread.start()

    def _spin(self) -> None:
        from rclpy.executors import SingleThreadedExecutor

        executor = SingleThreadedExecutor(context=self.context)
        executor.add_node(self.node)
        while not self._stop and self.context.ok():
            executor.spin_once(timeout_sec=0.05)

    def _diagnostics_callback(self, msg) -> None:
        from uncertain_facade_map.params import NODE_NAME

        if msg.status and msg.status[0].hardware_id == NODE_NAME:
            self.values = {kv.key: kv.value for kv in msg.status[0].values}

    def call(self, srv_type, name: str, request, timeout: float = 300.0):
        client = self.node.create_client(srv_type, name)
        if not client.wait_for_service(timeout_sec=60.0):
            raise RuntimeError(f'service {name} is not available')
        future = client.call_async(request)
        done = threading.Event()
        future.add_done_callback(lambda _: done.set())
        if not done.wait(timeout):
            raise RuntimeError(f'service {name} did not answer within {timeout} s')
        return future.result()

    def close(self) -> None:
        self._stop = True
        self._thread.join(5)
        self.node.destroy_node()
        self.rclpy.shutdown(context=self.context)


def main(argv: list[str] | None = None) -> int:
    """Run the demo; returns the exit status."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--out', default='output/demo', help='output folder (default output/demo)')
    parser.add_argument('--scene', default='street', choices=('street', 'small', 'zurich'))
    parser.add_argument('--rate', type=float, default=1.0, help='replay speed factor (default 1: as recorded)')
    parser.add_argument('--localise', type=int, default=12, metavar='N',
                        help='scans of another drive localised against the map at the end (default 12; 0: none)')
    args = parser.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    started = time.monotonic()
    env = dict(os.environ)
    env.setdefault('ROS_DOMAIN_ID', str(30 + os.getpid() % 60))
    env.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    os.environ.update({k: env[k] for k in ('ROS_DOMAIN_ID', 'ROS_AUTOMATIC_DISCOVERY_RANGE')})

    from uncertain_facade_map_apps.cli import main as cli

    print(f'[1/6] simulating the {args.scene} drive into {out}', flush=True)
    if cli(['simulate', '--scene', args.scene, '--out', str(out), '--formats', 'mcap,npz', '--force',
            '--quiet']) != 0:
        return 2
    bag = out / 'campaign0_mcap'
    for stale in (out / 'map.npz',):
        stale.unlink(missing_ok=True)

    print('[2/6] starting facade_mapper', flush=True)
    params = _config_file(out)
    log = open(out / 'facade_mapper.log', 'wb')
    node = subprocess.Popen([sys.executable, '-m', 'uncertain_facade_map_node.node', '--ros-args', '--params-file',
                             str(params)], env=env, cwd=ROOT, stdout=log, stderr=subprocess.STDOUT)
    loc = None
    try:
        loc = _Localisation()
        print(f'[3/6] replaying {bag.name} to it (publish mode, rate {args.rate:g})', flush=True)
        quiet = [] if sys.stderr.isatty() else ['--quiet']
        if cli(['replay', str(bag), '--mode', 'publish', '--rate', str(args.rate), '--config', str(params)]
               + quiet) != 0:
            return 2
        t_replayed = time.monotonic()
        print('      waiting for the map to settle', flush=True)
        deadline = time.monotonic() + 900
        while loc.values.get('settled') != 'True' or int(loc.values.get('clouds_waiting', 1)):
            if node.poll() is not None:
                raise RuntimeError(f'facade_mapper exited with {node.returncode}; see {out / "facade_mapper.log"}')
            if time.monotonic() > deadline:
                raise RuntimeError('the map did not settle within 15 minutes')
            time.sleep(0.5)
        diag = dict(loc.values)
        settle_seconds = time.monotonic() - t_replayed
        print('[4/6] querying the map as a localisation node', flush=True)
        answers, query_seconds, n_query = _query(loc, out)
        print('[5/6] saving the map and drawing it', flush=True)
        from uncertain_facade_map.srv import SaveMap

        # A name in the node's map folder (persistence.map_dir: the folder of its map_path, out).
        saved = loc.call(SaveMap, 'save_map', SaveMap.Request(path='map.npz'))
        if not saved.success:
            raise RuntimeError(saved.message)
        figures = _figures(out)
        localised = []
        if args.localise > 0:
            from uncertain_facade_map.io.map_file import load_map
            from uncertain_facade_map_apps.demo_localise import localise_drive, plot_localisation

            print(f'[6/6] localising {args.localise} scans of another drive with facade_localizer', flush=True)
            localised = localise_drive(args.scene, out, env, args.localise)
            figures.append(plot_localisation(localised, load_map(out / 'map.npz'), out / 'figures' / 'localisation.png'))
    finally:
        if loc is not None:
            loc.close()
        node.send_signal(2)
        try:
            node.wait(20)
        except subprocess.TimeoutExpired:
            node.kill()
        log.close()
    on = answers['facade'] >= 0
    std = np.sqrt(answers['variance'][on])
    print()
    print(f'demo done in {time.monotonic() - started:.0f} s; everything is in {out}/')
    print(f'  drive    {bag} ({diag.get("clouds_received")} scans, {int(diag.get("points_mapped", 0)):,} building points)')
    print(f'  mapping  {diag.get("buildings")} buildings, {diag.get("facades")} façades; '
          f'{diag.get("clouds_dropped")} scans dropped; settled {settle_seconds:.0f} s after the replay')
    print(f'  queries  {n_query:,} points in {query_seconds:.2f} s: {on.mean():.0%} on a façade, surface std median '
          f'{np.median(std) * 100:.1f} cm (5-95 %: {np.quantile(std, 0.05) * 100:.1f}-'
          f'{np.quantile(std, 0.95) * 100:.1f} cm) -> {out / "queries.npz"}')
    print(f'  map      {out / "map.npz"}')
    if localised:
        from uncertain_facade_map_apps.demo_localise import summary

        print(f'  localise {summary(localised)}')
    for path in figures:
        print(f'  figure   {path}')
    return 0


def _query(loc: _Localisation, out: Path) -> tuple[dict[str, np.ndarray], float, int]:
    """Query points a localisation filter would test: map points of the drive, jittered 10 cm."""
    from uncertain_facade_map.io.clouds import read_cloud
    from uncertain_facade_map.srv import QueryPoints
    from uncertain_facade_map_apps.ros_client import answers_of, query_request

    cloud = read_cloud(out / 'campaign0.npz')
    building = cloud.points[cloud.points['class'] == 1]
    rng = np.random.default_rng(0)
    pick = building[rng.choice(len(building), min(20000, len(building)), replace=False)]
    xyz = np.stack([pick['x'], pick['y'], pick['z']], 1).astype(np.float64) + rng.normal(0, 0.1, (len(pick), 3))
    request = query_request(xyz)
    t0 = time.monotonic()
    response = loc.call(QueryPoints, 'query_points', request)
    seconds = time.monotonic() - t0
    if not response.success:
        raise RuntimeError(response.message)
    answers = answers_of(response)
    np.savez(out / 'queries.npz', points=xyz, **answers)
    return answers, seconds, len(xyz)


def _figures(out: Path) -> list[Path]:
    """The map's figures (``uncertain-facade-map plot``)."""
    from uncertain_facade_map.io.map_file import load_map
    from uncertain_facade_map_apps.plots import plot_map

    return plot_map(load_map(out / 'map.npz'), out / 'figures')


if __name__ == '__main__':
    raise SystemExit(main())
