"""``make bench``: throughput and peak memory of the hot paths, printed as a table.

A benchmark, not a test: it asserts nothing and prints figures to quote in commit messages
and closing notes. Stages run one after the other, each in a fresh child process, so that
its peak memory (max RSS) is its own:

- ``simulate``: one campaign of the default ``street`` scene (written to a temporary NPZ);
- ``build``: the façade map of that campaign (reading the NPZ is not timed);
- ``query``: 500 000 points near the façades against the saved map (loading not timed), as
  the command line's ``query`` answers them (``query.surface`` 'local': the stored points
  read per point where dense; the set-up of their grid and calibration, once per map
  version, timed apart and printed in the note), and a localiser's call of 20 000 of them
  ('20k batch', median of 20 calls);
- ``query raster``: the same read from the façade rasters alone (the paper's reading);
- ``select``: the building selection of clouds without classes, per sweep (simulated 64-beam
  car lidar sweeps; the real ones of ``../shared/data/real`` too when present).

Rates are input points per second of the timed part.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import platform
import resource
import tempfile
import time
from pathlib import Path


def _simulate(work: Path, scene_name: str) -> dict:
    from uncertain_facade_map.io.npz import write_npz
    from uncertain_facade_map.simulation.campaign import SCENE_SENSORS, simulate_campaign
    from uncertain_facade_map.simulation.scenes import build_scene

    scene = build_scene(scene_name, 0)
    started = time.perf_counter()
    cloud = simulate_campaign(scene, 0)
    seconds = time.perf_counter() - started
    write_npz(work / 'cloud.npz', cloud)
    sensor = SCENE_SENSORS[scene_name]
    return {'stage': f'simulate {scene_name}', 'items': len(cloud), 'unit': 'points', 'seconds': seconds,
            'note': f'{sensor.scan_rate_hz:g} Hz x {len(sensor.mount)} scanners, {sensor.angular_step_deg:g} deg'}


def _build(work: Path, scene_name: str) -> dict:
    from uncertain_facade_map.io.inputs import select_building_points
    from uncertain_facade_map.io.map_file import save_map
    from uncertain_facade_map.io.npz import read_npz
    from uncertain_facade_map.mapping.facade_map import FacadeMap
    from uncertain_facade_map.params import Config, MapParams

    cloud = read_npz(work / 'cloud.npz')
    started = time.perf_counter()
    points = select_building_points(cloud, Config().input)
    fmap = FacadeMap(MapParams(), points.map_origin)
    fmap.add_points(points.xyz, points.building_id, points.sensor_origins)
    seconds = time.perf_counter() - started
    save_map(fmap, work / 'map.npz')
    return {'stage': f'build {scene_name}', 'items': len(cloud), 'unit': 'points', 'seconds': seconds,
            'note': f'{len(points):,} building points, {len(fmap.facades)} façades'}


def _query(work: Path, scene_name: str, surface: str = 'local') -> dict:
    import numpy as np

    from uncertain_facade_map.io.map_file import load_map
    from uncertain_facade_map.io.npz import read_npz
    from uncertain_facade_map.params import QueryConfig
    from uncertain_facade_map.pipeline.step7_local_surface import LocalSurface

    fmap = load_map(work / 'map.npz')
    cloud = read_npz(work / 'cloud.npz')
    xyz = cloud.xyz[cloud.points['class'] == 1]
    rng = np.random.default_rng(0)
    pts = xyz[rng.choice(len(xyz), 500_000)] + rng.normal(0.0, 0.3, (500_000, 3))
    config = QueryConfig(surface=surface)
    # The compiled kernels loaded from numba's cache (one core and both: small and large
    # calls), not timed: on a few stored points and the rasters alone.
    few = np.concatenate(list(fmap.points.values()))[:5000]
    warm = LocalSurface(few, np.zeros(len(few), np.int32), np.array([[0.0, 0.0, 1.0]]))
    for n in (10, 5000):
        warm.read(few[:n])
        fmap.query(pts[:n], QueryConfig(surface='raster'), 0.1)
    started = time.perf_counter()
    fmap.local_surface(config)  # once per map version (kept by the map; the node: per snapshot)
    setup = time.perf_counter() - started
    started = time.perf_counter()
    res = fmap.query(pts, config, 0.1)
    seconds = time.perf_counter() - started
    # A localiser's call: 20,000 points, median of 20 calls after one warm-up call.
    batch = pts[:20_000]
    fmap.query(batch, config, 0.1)
    calls = []
    for _ in range(20):
        started = time.perf_counter()
        fmap.query(batch, config, 0.1)
        calls.append(time.perf_counter() - started)
    batch_ms = 1000.0 * float(np.median(calls))
    what = (f'the stored points per point where dense, set-up {setup:.2f} s not in the rate' if surface == 'local'
            else 'rasters alone')
    return {'stage': f'query {scene_name}' + ('' if surface == 'local' else ' raster'), 'items': len(pts),
            'unit': 'points', 'seconds': seconds, 'setup_s': setup, 'batch_ms': batch_ms,
            'note': f'20k batch {batch_ms:.1f} ms; {(res.facade >= 0).mean():.0%} on a façade, '
                    f'{len(fmap.facades)} façades; {what}'}


def _query_raster(work: Path, scene_name: str) -> dict:
    return _query(work, scene_name, 'raster')


def _select(work: Path, scene_name: str) -> dict:
    """The building selection of clouds without classes, one sweep at a time as the node
    selects them: 4 simulated sweeps of the 64-beam car lidar on ``residential`` (whatever
    ``--scene``; simulating not timed), each 3 times, and the real sweeps of
    ``../shared/data/real`` when they are there (read from there: non-commercial). The first
    call (loading the compiled kernels) is not timed."""
    import numpy as np

    from uncertain_facade_map.selection import select_building_points
    from uncertain_facade_map.selection.evaluation import REAL_DATA, simulated_clouds

    def seconds(xyz: np.ndarray, origins: np.ndarray | None, runs: int = 3) -> list[float]:
        times = []
        for _ in range(runs):
            started = time.perf_counter()
            select_building_points(xyz, origins)
            times.append(time.perf_counter() - started)
        return times

    sweeps = [(np.stack([p['x'], p['y'], p['z']], axis=1), np.stack([p['origin_x'], p['origin_y'], p['origin_z']],
                                                                     axis=1))
              for p in simulated_clouds('residential', 'hdl64', 0.1, 6.0)]
    select_building_points(*sweeps[0])
    timed = [(len(xyz), t) for xyz, origins in sweeps for t in seconds(xyz, origins)]
    per_100k = [t / n * 1e5 for n, t in timed]
    note = f'{len(sweeps)} hdl64 sweeps: {np.median(per_100k) * 1e3:.0f} ms per 100,000 points (median)'
    real = sorted(REAL_DATA.glob('*.ply')) if REAL_DATA.is_dir() else []
    if real:
        from uncertain_facade_map.io.clouds import read_cloud

        clouds = [read_cloud(path) for path in real]
        ms = [np.median(seconds(c.xyz, c.sensor_origins)) / len(c.xyz) * 1e8 for c in clouds]
        note += '; real: ' + ', '.join(f'{path.stem} {m:.0f}' for path, m in zip(real, ms)) + ' ms (median of 3)'
    return {'stage': 'select hdl64', 'items': sum(n for n, _ in timed), 'unit': 'points',
            'seconds': sum(t for _, t in timed), 'note': note}


STAGES = {'simulate': _simulate, 'build': _build, 'query': _query, 'query_raster': _query_raster,
          'select': _select}


def _run(stage: str, work: str, scene: str, queue: mp.Queue) -> None:
    result = STAGES[stage](Path(work), scene)
    result['peak_mb'] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    queue.put(result)


def run_stage(stage: str, work: Path, scene: str) -> dict:
    """Run one stage in a fresh process and return its figures."""
    ctx = mp.get_context('spawn')
    queue = ctx.Queue()
    proc = ctx.Process(target=_run, args=(stage, str(work), scene, queue))
    proc.start()
    result = queue.get()
    proc.join()
    return result


def main(argv: list[str] | None = None) -> int:
    """Print the benchmark table (and JSON lines with ``--json``)."""
    parser = argparse.ArgumentParser(prog='python -m uncertain_facade_map_apps.bench', description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('--scene', default='street', choices=('street', 'small', 'zurich'))
    parser.add_argument('--json', action='store_true', help='print JSON lines instead of a table')
    args = parser.parse_args(argv)
    print(f'# {platform.node()}: {mp.cpu_count()} cores, Python {platform.python_version()}')
    print(f'{"stage":18s} {"items":>12s} {"seconds":>8s} {"per second":>14s} {"peak MB":>8s}  note')
    with tempfile.TemporaryDirectory(prefix='ufm-bench-') as work:
        for stage in STAGES:
            r = run_stage(stage, Path(work), args.scene)
            if args.json:
                print(json.dumps(r))
                continue
            rate = r['items'] / r['seconds']
            print(f'{r["stage"]:18s} {r["items"]:>12,} {r["seconds"]:>8.1f} {rate:>10,.0f} pt/s '
                  f'{r["peak_mb"]:>8.0f}  {r["note"]}', flush=True)
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
