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
  car lidar sweeps; the real ones of ``../shared/data/real`` too when present);
- ``stream_street``, ``stream_av2``, ``stream_hdl64`` (``--stages stream``: all three): a drive
  fed to the mapper as the node is fed, cloud by cloud at its recorded times divided by a rate
  factor (1x, 2x, 4x, 8x, 16x, each with a fresh map and mapping process; the rates above one
  that dropped a cloud or was given up are skipped): the street drive
  (the ``simulate`` stage's, in 0.1 s clouds) and 10 s of the street seen by the simulator's
  real-rate sensors (the 2 x 32-beam ``av2`` robot preset, the 64-beam ``hdl64`` car preset).
  Building points only (class 1), counted as such. Per rate: clouds in, mapped, dropped;
  building points/s mapped; latency from a cloud's arrival to its points being queryable (p50,
  p95, max); peak memory; then the highest rate sustained with no dropped cloud and the surface
  error against the simulated truth of each streamed map beside the batch map of the same
  drive (see :mod:`uncertain_facade_map_apps.bench_stream`);
- ``stream_laps``: the street driven five times (1 cm of fresh noise a lap), each cloud stored
  and then modelled until caught up, in one process: CPU, stored points and memory per lap;
- ``stream_real`` (with ``--real``, or named in ``--stages``; needs ``../shared/data/real``):
  each shared real sweep streamed, scored by ``../shared/tools/real_check.py`` beside the map
  built in one batch.

Rates of the first five stages are input points per second of the timed part.
"""

from __future__ import annotations

import argparse
import json
import math
import multiprocessing as mp
import platform
import resource
import tempfile
import time
from pathlib import Path
from typing import Any


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


def _stream(work: Path, scene_name: str, drive: str, live: bool = False) -> dict:
    """Stream one drive at every rate (``bench_stream.measure_drive``); ``street`` streams the
    bench's scene, reusing the ``simulate`` stage's drive and the ``build`` stage's map if they ran."""
    from uncertain_facade_map.io.map_file import load_map
    from uncertain_facade_map.io.npz import read_npz

    from . import bench_stream as bs

    say = (lambda line: print(line, flush=True)) if live else None
    if drive == 'street':
        cloud = read_npz(work / 'cloud.npz') if (work / 'cloud.npz').exists() else None
        d = bs.simulate_drive(scene_name, scene=scene_name, cloud=cloud)
        del cloud
        batch = load_map(work / 'map.npz') if (work / 'map.npz').exists() else None
    else:
        d = bs.simulate_drive(drive)
        batch = None
    if say is not None:
        say(f'stream {d.describe()}')
        say(bs.HEADER)
    result = bs.measure_drive(d, batch=batch, say=say)
    return {'stage': f'stream {d.name}', 'stream': result}


def _stream_street(work: Path, scene_name: str, live: bool = False) -> dict:
    return _stream(work, scene_name, 'street', live)


def _stream_av2(work: Path, scene_name: str, live: bool = False) -> dict:
    return _stream(work, scene_name, 'av2', live)


def _stream_hdl64(work: Path, scene_name: str, live: bool = False) -> dict:
    return _stream(work, scene_name, 'hdl64', live)


def _stream_laps(work: Path, scene_name: str, live: bool = False) -> dict:
    from uncertain_facade_map.io.npz import read_npz

    from . import bench_stream as bs

    cloud = read_npz(work / 'cloud.npz') if (work / 'cloud.npz').exists() else None
    d = bs.simulate_drive(scene_name, scene=scene_name, cloud=cloud)
    del cloud
    return {'stage': 'stream laps', 'laps': bs.drive_laps(d)}


def _stream_real(work: Path, scene_name: str, live: bool = False) -> dict:
    from . import bench_stream as bs

    sweeps = bs.real_sweeps()
    results = []
    for ply in sweeps:
        results.append(bs.real_check(ply))
        if live:
            print(f'# {ply.name}: real_check.py twice in {results[-1]["seconds"]:.0f} s', flush=True)
    return {'stage': 'stream real', 'real': results}


STAGES = {'simulate': _simulate, 'build': _build, 'query': _query, 'query_raster': _query_raster,
          'select': _select, 'stream_street': _stream_street, 'stream_av2': _stream_av2, 'stream_hdl64': _stream_hdl64,
          'stream_laps': _stream_laps, 'stream_real': _stream_real}
#: Names ``--stages`` takes for several stages.
GROUPS = {'stream': ('stream_street', 'stream_av2', 'stream_hdl64', 'stream_laps', 'stream_real'),
          'query_all': ('query', 'query_raster')}
#: Stages that read what others wrote (added when asked for alone).
NEEDS = {'build': ('simulate',), 'query': ('build',), 'query_raster': ('build',)}


def _run(stage: str, work: str, scene: str, queue: mp.Queue, live: bool) -> None:
    fn = STAGES[stage]
    result = fn(Path(work), scene, live) if stage.startswith('stream') else fn(Path(work), scene)
    result['peak_mb'] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    queue.put(result)


def run_stage(stage: str, work: Path, scene: str, live: bool = False) -> dict:
    """Run one stage in a fresh process and return its figures (``live``: a stream stage
    prints its table lines as it measures them)."""
    ctx = mp.get_context('spawn')
    queue = ctx.Queue()
    proc = ctx.Process(target=_run, args=(stage, str(work), scene, queue, live))
    proc.start()
    result = queue.get()
    proc.join()
    return result


def stages_of(text: str | None, real: bool) -> list[str]:
    """The stages to run, in the bench's order: ``text`` is a comma-separated list of stage
    names and groups (:data:`GROUPS`), None for all; ``stream_real`` only when ``real``."""
    if text is None:
        wanted = set(STAGES)
    else:
        wanted = set()
        for name in (n.strip() for n in text.split(',') if n.strip()):
            if name not in STAGES and name not in GROUPS:
                raise SystemExit(f'bench: unknown stage {name!r}; stages: {", ".join([*STAGES, *GROUPS])}')
            wanted.update(GROUPS.get(name, (name,)))
    if not real:
        wanted.discard('stream_real')
    for _ in range(len(NEEDS)):
        wanted.update(*(NEEDS.get(name, ()) for name in list(wanted)))
    return [s for s in STAGES if s in wanted]


def _finite(value: Any) -> Any:
    """``value`` with every NaN or infinite float replaced by None (strict JSON)."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_finite(v) for v in value]
    return value


def _print_stream(r: dict, as_json: bool, live: bool) -> None:
    from . import bench_stream as bs

    if 'laps' in r:
        if as_json:
            for one in r['laps']:
                print(json.dumps(_finite({'stage': f'stream laps {one["lap"]}', **one})))
        else:
            print('\n'.join(bs.format_laps(r['laps'])), flush=True)
        return
    if 'real' in r:
        if as_json:
            for one in r['real']:
                print(json.dumps(_finite({'stage': f'stream real {one["file"]}', **one})))
        else:
            print('\n'.join(bs.format_real(r['real'])), flush=True)
        return
    result = r['stream']
    if as_json:
        for run in result['runs']:
            print(json.dumps(_finite({'stage': f'stream {result["name"]} {run["rate"]:g}x',
                                      'items': run.get('building_points_in'), 'unit': 'building points', **run})))
        summary = {k: v for k, v in result.items() if k != 'runs'}
        print(json.dumps(_finite({'stage': f'stream {result["name"]}', 'sustained_rate': result['sustained'],
                                  'sustained_rate_p95_1s': bs.sustained(result['runs'], bs.TARGET_P95),
                                  'peak_mb': r['peak_mb'], **summary})))
        return
    lines = bs.format_drive(result)
    skip = 2 + len(result['runs']) if live else 0  # the header and rows were printed as measured
    print('\n'.join(lines[skip:]), flush=True)


def main(argv: list[str] | None = None) -> int:
    """Print the benchmark table (and JSON lines with ``--json``)."""
    parser = argparse.ArgumentParser(prog='python -m uncertain_facade_map_apps.bench', description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('--scene', default='street', choices=('street', 'small', 'zurich'))
    parser.add_argument('--json', action='store_true', help='print JSON lines instead of a table')
    groups = ', '.join(f'{k} ({"+".join(v)})' for k, v in GROUPS.items())
    parser.add_argument('--stages', metavar='LIST',
                        help=f'comma-separated stages to run (default: all): {", ".join(STAGES)}, or the groups '
                             f'{groups}')
    parser.add_argument('--real', action='store_true',
                        help='also stream the shared real sweeps (../shared/data/real/*.ply) and score them with '
                             '../shared/tools/real_check.py beside the batch map (stage stream_real; 1-2 minutes '
                             'per sweep on two cores today, so not by default)')
    args = parser.parse_args(argv)
    from .bench_stream import real_sweeps

    have_real = bool(real_sweeps())
    if args.real and not have_real:
        parser.error('--real: no ../shared/data/real/*.ply beside the repository')
    asked = args.real or 'stream_real' in (args.stages or '').split(',')
    stages = stages_of(args.stages, have_real and asked)
    if args.real and 'stream_real' not in stages:
        stages.append('stream_real')
    if asked and not have_real:
        print('# stream_real: no ../shared/data/real/*.ply beside the repository; skipped')
    print(f'# {platform.node()}: {mp.cpu_count()} cores, Python {platform.python_version()}; stages: '
          f'{", ".join(stages)}', flush=True)
    header = f'{"stage":18s} {"items":>12s} {"seconds":>8s} {"per second":>14s} {"peak MB":>8s}  note'
    if not args.json and any(not s.startswith('stream') for s in stages):
        print(header, flush=True)
    with tempfile.TemporaryDirectory(prefix='ufm-bench-') as work:
        for stage in stages:
            started = time.perf_counter()
            live = stage.startswith('stream') and not args.json
            if live:
                print(flush=True)
            r = run_stage(stage, Path(work), args.scene, live)
            if stage.startswith('stream'):
                _print_stream(r, args.json, live)
                if live:
                    print(f'# {stage}: {time.perf_counter() - started:.0f} s, peak {r["peak_mb"]:.0f} MB '
                          '(this stage\'s process)', flush=True)
                continue
            if args.json:
                print(json.dumps(r))
                continue
            rate = r['items'] / r['seconds']
            print(f'{r["stage"]:18s} {r["items"]:>12,} {r["seconds"]:>8.1f} {rate:>10,.0f} pt/s '
                  f'{r["peak_mb"]:>8.0f}  {r["note"]}', flush=True)
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
