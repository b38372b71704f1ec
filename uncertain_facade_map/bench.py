"""``make bench``: throughput and peak memory of the hot paths, printed as a table.

A benchmark, not a test: it asserts nothing and prints figures to quote in commit messages
and closing notes. Each stage runs in a child process so that its peak memory (max RSS)
is its own.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import platform
import resource
import time


def _simulate(scene_name: str) -> dict:
    from .simulation.campaign import SCENE_SENSORS, simulate_campaign
    from .simulation.scenes import build_scene

    scene = build_scene(scene_name, 0)
    started = time.perf_counter()
    cloud = simulate_campaign(scene, 0)
    seconds = time.perf_counter() - started
    sensor = SCENE_SENSORS[scene_name]
    return {'stage': f'simulate {scene_name}', 'items': len(cloud), 'unit': 'points', 'seconds': seconds,
            'note': f'{sensor.scan_rate_hz:g} Hz x {len(sensor.mount)} scanners, {sensor.angular_step_deg:g} deg'}


def _run(stage: str, arg: str, queue: mp.Queue) -> None:
    result = {'simulate': _simulate}[stage](arg)
    result['peak_mb'] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    queue.put(result)


def run_stage(stage: str, arg: str) -> dict:
    """Run one stage in a fresh process and return its figures."""
    ctx = mp.get_context('spawn')
    queue = ctx.Queue()
    proc = ctx.Process(target=_run, args=(stage, arg, queue))
    proc.start()
    result = queue.get()
    proc.join()
    return result


def main(argv: list[str] | None = None) -> int:
    """Print the benchmark table (and JSON lines with ``--json``)."""
    parser = argparse.ArgumentParser(prog='python -m uncertain_facade_map.bench', description=__doc__)
    parser.add_argument('--json', action='store_true', help='print JSON lines instead of a table')
    args = parser.parse_args(argv)
    stages = [('simulate', 'street')]
    print(f'# {platform.node()}: {mp.cpu_count()} cores, Python {platform.python_version()}')
    print(f'{"stage":24s} {"items":>12s} {"seconds":>8s} {"per second":>14s} {"peak MB":>8s}  note')
    for stage, arg in stages:
        r = run_stage(stage, arg)
        if args.json:
            print(json.dumps(r))
            continue
        rate = r['items'] / r['seconds']
        print(f'{r["stage"]:24s} {r["items"]:>12,} {r["seconds"]:>8.1f} {rate:>10,.0f} {r["unit"][:3]}/s '
              f'{r["peak_mb"]:>8.0f}  {r["note"]}')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
