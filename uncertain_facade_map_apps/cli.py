"""The ``uncertain-facade-map`` command line.

Sub-commands:
    simulate   scan a built-in scene in one or more campaigns and write clouds and bags
    build      build a façade map from classified point clouds or bags
    query      answer point queries against a map
    localise   localise scans against a map: 6-DoF pose and covariance from a prior pose
    replay     replay bags into a map (offline) or to a running facade_mapper (publish)
    inspect    what a bag holds (clouds, frames, transforms) and whether its clouds can be mapped
    plot       draw a map's façades and an overview as PNG figures
    evaluate   compare the map's occupancy with the baselines' against a reference scan
    benchmark  hold points out of a cloud, map the rest, score the held-out points beside reference maps
    export     write a map's mean surface for other localisers (Autoware PCD tiles + metadata YAML)

Every error a user can cause ends in one line on stderr and exit status 2; nothing ends in
a traceback. Bag formats need ``msg_adapters`` (rosbags), imported only when asked for.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import math
import os
import shutil
import sys
import time
from pathlib import Path
from typing import Callable, Iterator, Sequence

from uncertain_facade_map.errors import FacadeMapError

PROG = 'uncertain-facade-map'
CLOUD_FORMATS = ('npz', 'ply')
BAG_FORMATS = ('sqlite3', 'mcap', 'rosbag1')
#: Output name of each format after the campaign stem (ROS 2 bags are folders).
#: Formats of the mapped campaign by default (a city: ply, one file per street segment).
DEFAULT_FORMATS = ('npz', 'ply', 'sqlite3', 'mcap')
SUFFIXES = {'npz': '.npz', 'ply': '.ply', 'sqlite3': '_sqlite3', 'mcap': '_mcap', 'rosbag1': '.bag'}


class CliError(FacadeMapError):
    """A usage error found after argument parsing."""


def _formats(text: str) -> tuple[str, ...]:
    items = tuple(x.strip() for x in text.split(',') if x.strip())
    bad = [x for x in items if x not in CLOUD_FORMATS + BAG_FORMATS]
    if bad or not items:
        raise argparse.ArgumentTypeError(
            f'unknown format {", ".join(bad) or "(none)"}; choose from {", ".join(CLOUD_FORMATS + BAG_FORMATS)}')
    return items


def _progress_bar(total: float, desc: str, quiet: bool) -> tuple[Callable[[float], None], Callable[[], None]]:
    """A tqdm bar over ``total`` units driven by absolute positions; no-ops when quiet."""
    if quiet:
        return (lambda _pos: None), (lambda: None)
    from tqdm import tqdm

    bar = tqdm(total=round(total, 1), desc=desc, unit='s', leave=False, file=sys.stderr,
               bar_format='{desc}: {percentage:3.0f}%|{bar}| {n:.1f}/{total:.1f} s of drive [{elapsed}<{remaining}]')

    def update(pos: float) -> None:
        bar.update(round(pos, 1) - bar.n)

    return update, bar.close


@contextlib.contextmanager
def _counter(desc: str, unit: str, quiet: bool, total: int | None = None) -> Iterator[Callable[..., None]]:
    """A tqdm bar over counted items on stderr, as ``update(done, total=None)``; a no-op when quiet."""
    if quiet:
        yield lambda done, total=None: None
        return
    from tqdm import tqdm

    bar = tqdm(total=total, desc=desc, unit=unit, leave=False, file=sys.stderr)

    def update(done: int, total: int | None = None) -> None:
        if total is not None:
            bar.total = total
        bar.update(done - bar.n)

    try:
        yield update
    finally:
        bar.close()


def _output_path(out: Path, name: str, force: bool) -> Path:
    path = out / name
    if path.exists():
        if not force:
            raise CliError(f'{path} exists; use --force to replace it')
        shutil.rmtree(path) if path.is_dir() else path.unlink()
    return path


def cmd_simulate(args: argparse.Namespace) -> int:
    """Simulate campaigns of a scene and write them (see ``simulate --help``)."""
    from uncertain_facade_map.io.npz import write_npz
    from uncertain_facade_map.io.ply import write_ply
    from uncertain_facade_map.simulation.campaign import (
        SCENE_SENSORS,
        SensorConfig,
        campaign,
        drive_duration,
        simulate_campaign,
        with_overrides,
    )
    from uncertain_facade_map.simulation.city import CITY_PRESETS
    from uncertain_facade_map.simulation.export import scene_description, split_scans, write_scene_json
    from uncertain_facade_map.simulation.presets import SENSOR_PRESETS
    from uncertain_facade_map.simulation.scenes import build_scene

    def sensor_of(name: str) -> SensorConfig:
        preset = SENSOR_PRESETS[args.sensor] if args.sensor else SCENE_SENSORS.get(name, SensorConfig())
        return with_overrides(preset, range_noise=args.range_noise,
                              outlier_share=args.outlier_share, range_max=args.range_max,
                              angular_step_deg=args.angular_step, scan_rate_hz=args.scan_rate, speed=args.speed)

    if args.scene in CITY_PRESETS:
        return _simulate_city(args, sensor_of(args.scene))
    if args.city_blocks is not None or args.city_block is not None or args.jobs is not None:
        raise CliError('--city-blocks, --city-block and --jobs are for --scene city or city_small')
    scene = build_scene(args.scene, args.seed, args.cityjson if args.scene.startswith('zurich') else None)
    sensor = sensor_of(scene.name)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    written = []
    for index in range(1 if args.campaigns is None else args.campaigns):
        drive = campaign(scene, index)
        formats = (args.formats or DEFAULT_FORMATS) if index == 0 else args.reference_formats
        stem = f'campaign{index}'
        targets = {fmt: _output_path(out, stem + SUFFIXES[fmt], args.force) for fmt in formats}
        update, close = _progress_bar(drive_duration(scene, drive, sensor),
                                      f'{scene.name} campaign {index}', args.quiet)
        started = time.perf_counter()
        try:
            cloud = simulate_campaign(scene, index, sensor, xyz_dtype=args.dtype, progress=update)
        finally:
            close()
        elapsed = time.perf_counter() - started
        files = {}
        for fmt, path in targets.items():
            if fmt == 'npz':
                write_npz(path, cloud)
            elif fmt == 'ply':
                write_ply(path, cloud)
            elif args.robot:
                _write_robot_bag(path, fmt, cloud, scene, drive, sensor, args)
            else:
                from msg_adapters.bag_io import write_bag

                write_bag(path, split_scans(cloud, args.scan_period), storage=fmt, topic=args.topic,
                          frame_id='map', map_origin=tuple(cloud.map_origin))
            files[fmt] = path.name
        written.append((drive, len(cloud), files))
        role = 'mapped' if index == 0 else 'reference'
        print(f'campaign {index} ({role}): {len(cloud):,} points in {elapsed:.1f} s, lane {drive.lane:+.2f} m'
              f'{" reversed" if drive.reverse else ""}')
        for fmt, name in files.items():
            print(f'  {fmt:8s} {out / name}')
    scene_json = write_scene_json(out / 'scene.json', scene_description(scene, sensor, written))
    print(f'scene    {scene_json}  ({len(scene.buildings)} buildings, {len(scene.facades)} façades, seed {scene.seed})')
    return 0


def _simulate_city(args: argparse.Namespace, sensor) -> int:
    """``simulate --scene city``: every segment of every drive to its own file, in a process pool."""
    from concurrent.futures import ProcessPoolExecutor
    from multiprocessing import get_context

    from uncertain_facade_map.simulation.campaign import campaign
    from uncertain_facade_map.simulation.city import (
        CITY_FORMATS,
        CITY_PRESETS,
        CityConfig,
        SegmentTask,
        build_city,
        segment_file,
        write_segment,
    )
    from uncertain_facade_map.simulation.export import scene_description, write_scene_json

    preset = CITY_PRESETS[args.scene]
    config = CityConfig(preset.blocks if args.city_blocks is None else args.city_blocks,
                        preset.block if args.city_block is None else args.city_block)
    formats = args.formats or ('ply',)
    if len(formats) != 1 or formats[0] not in CITY_FORMATS:
        raise CliError(f'a city is written as one file per street segment: give --formats {" or ".join(CITY_FORMATS)}')
    if args.robot:
        raise CliError('--robot writes bags; a city is written as one cloud file per street segment')
    campaigns = 2 if args.campaigns is None else args.campaigns
    jobs = args.jobs or 1
    if jobs < 1 or campaigns < 1:
        raise CliError('--jobs and --campaigns must be at least 1')
    started = time.perf_counter()
    city = build_city(args.seed, config, args.scene)
    out = Path(args.out)
    tasks = []
    for index in range(campaigns):
        folder = out / f'campaign{index}'
        if folder.exists():
            if not args.force:
                raise CliError(f'{folder} exists; use --force to replace it')
            shutil.rmtree(folder)
        tasks += [SegmentTask(args.seed, config, args.scene, sensor, index, seg.index,
                              segment_file(out, index, seg.index, formats[0]), args.dtype) for seg in city.segments]
    out.mkdir(parents=True, exist_ok=True)
    if not args.quiet:
        print(f'{args.scene}: {config.blocks[0]} x {config.blocks[1]} blocks of {config.block:g} m, '
              f'{config.street_length / 1000:.2f} km of street in {len(city.segments)} segments, '
              f'{len(city.scene.buildings)} buildings; {campaigns} drives, {len(tasks)} files, {jobs} jobs',
              file=sys.stderr)
    results: list[tuple[int, float]] = []
    with _counter('segments', 'segment', args.quiet, len(tasks)) as update:
        if jobs == 1:
            for task in tasks:
                results.append(write_segment(task))
                update(len(results))
        else:
            with ProcessPoolExecutor(jobs, mp_context=get_context('spawn')) as pool:
                for result in pool.map(write_segment, tasks):
                    results.append(result)
                    update(len(results))
    elapsed = time.perf_counter() - started
    written, per_segment = [], {}
    for index in range(campaigns):
        mine = [(t, r) for t, r in zip(tasks, results) if t.index == index]
        files = [str(t.path.relative_to(out)) for t, _ in mine]
        points = sum(n for _, (n, _) in mine)
        written.append((campaign(city.scene, index), points, files))
        per_segment[str(index)] = [n for _, (n, _) in mine]
        print(f'campaign {index} ({"mapped" if index == 0 else "reference"}): {points:,} points in {len(files)} '
              f'files {out / f"campaign{index}"}/seg_*.{formats[0]}, lane {written[-1][0].lane:+.2f} m'
              f'{" reversed" if written[-1][0].reverse else ""}')
    description = scene_description(city.scene, sensor, written)
    description['city'] = dict(city.describe(), segment_points=per_segment)
    scene_json = write_scene_json(out / 'scene.json', description)
    total = sum(n for n, _ in results)
    print(f'scene    {scene_json}  ({len(city.scene.buildings)} buildings, {len(city.scene.facades)} façades, '
          f'{config.street_length / 1000:.2f} km of street, seed {args.seed})')
    print(f'wrote    {total:,} points in {len(results)} files in {elapsed:.1f} s '
          f'({sum(s for _, s in results):.1f} s of simulation over {jobs} job{"s" if jobs > 1 else ""})')
    return 0


def _city_blocks(text: str) -> tuple[int, int]:
    try:
        nx, ny = (int(v) for v in text.split(','))
    except ValueError:
        raise argparse.ArgumentTypeError(f'expected NX,NY (two whole numbers), got {text!r}') from None
    if nx < 1 or ny < 1:
        raise argparse.ArgumentTypeError(f'block counts must be at least 1, got {text!r}')
    return nx, ny


def _write_robot_bag(path: Path, storage: str, cloud, scene, drive, sensor, args: argparse.Namespace) -> None:
    """A campaign as a robot records it: clouds in the lidar frame, /tf map -> base_link, /tf_static."""
    from msg_adapters.bag_io import TFMESSAGE, pose_message, write_bag
    from msg_adapters.transforms import StampedTransform
    from uncertain_facade_map.simulation.export import LIDAR_FRAME, VEHICLE_FRAME, robot_recording

    rec = robot_recording(cloud, scene, drive, sensor, args.scan_period)
    stamps, translations, quaternions = rec.vehicle
    extra = [pose_message('/tf_static', TFMESSAGE, [StampedTransform(VEHICLE_FRAME, LIDAR_FRAME, int(stamps[0]),
                                                                      *rec.mount)])]
    extra += [pose_message('/tf', TFMESSAGE, [StampedTransform('map', VEHICLE_FRAME, int(s), t, q)])
              for s, t, q in zip(stamps, translations, quaternions)]
    write_bag(path, rec.scans, storage=storage, topic=args.topic, frame_id='map', map_origin=tuple(cloud.map_origin),
              extra=extra, extra_qos={'/tf_static': 'latched', '/tf': 'reliable'})


def cmd_build(args: argparse.Namespace) -> int:
    """Build a map from inputs and save it (see ``build --help``)."""
    import numpy as np

    from msg_adapters.bag_io import load_inputs
    from uncertain_facade_map.io.inputs import select_building_points
    from uncertain_facade_map.io.map_file import save_map
    from uncertain_facade_map.io.parameter_file import load_config
    from uncertain_facade_map.io.trajectory import read_trajectory
    from uncertain_facade_map.mapping.facade_map import FacadeMap
    from uncertain_facade_map.params import map_params

    config = load_config(args.config)
    if (args.out is None) == (args.tiles is None):
        raise CliError('give --out MAP (one map file) or --tiles DIR (a tiled map), one of them')
    if args.tiles is not None:
        return _build_tiles(args, config)
    for name in ('side', 'workers', 'scheduler', 'bounds'):
        if getattr(args, name) is not None:
            raise CliError(f'--{name} goes with --tiles DIR')
    out = Path(args.out)
    if not out.parent.exists():
        raise CliError(f'output folder {out.parent} does not exist')
    if args.sensor is not None and args.trajectory is not None:
        raise CliError('give --sensor or --trajectory, not both')
    trajectory = None if args.trajectory is None else read_trajectory(args.trajectory)
    started = time.perf_counter()
    cloud = load_inputs(args.inputs, topic=args.topic, max_distance=config.input.max_distance, warn=print,
                        config=config)
    selection = config.selection if args.select is None else dataclasses.replace(config.selection, mode=args.select)
    points = select_building_points(cloud, config.input, selection, sensor=args.sensor, trajectory=trajectory)
    read_s = time.perf_counter() - started
    fmap = FacadeMap(map_params(config), points.map_origin)
    with _counter('buildings', 'building', args.quiet) as update:
        fmap.add_points(points.xyz, points.building_id, points.sensor_origins, progress=update)
    build_s = time.perf_counter() - started - read_s
    occupancy = 'not learnt, the fixed formula (no sensor origins to learn free space from)'
    if points.sensor_origins is not None and fmap.facades:
        learnt = fmap.calibrate_occupancy(config.query.resolution)
        occupancy = (f'scale {learnt.scale:.3g}, spread {learnt.spread * 100:.1f} cm, learnt on '
                     f'{learnt.n_positive:,} held-out hit voxels and {learnt.n_negative:,} crossed voxels'
                     if learnt.learnt else 'not learnt, the fixed formula (too few labelled voxels near a façade)')
    calibrate_s = time.perf_counter() - started - read_s - build_s
    save_map(fmap, out)
    total_s = time.perf_counter() - started
    stats = [f.stats for f in fmap.facades]
    print(f'read     {len(cloud):,} points ({len(points):,} building) from {len(args.inputs)} input(s) in {read_s:.1f} s')
    if points.selection is not None:
        from uncertain_facade_map.selection import selection_warning

        found = points.selection
        print(f'selected {len(points):,} points on {found.walls} wall segments, {found.ground.sum():,} ground'
              if found.applied else
              f'selected all: no class field, but {found.ground_share:.1%} ground, so building points cut already')
        warning = selection_warning(found, selection)
        if warning is not None:
            print(f'warning: {warning}', file=sys.stderr)
    print(f'mapped   {len(fmap.buildings)} buildings, {len(fmap.facades)} façades in {build_s:.1f} s '
          f'({len(cloud) / max(build_s, 1e-9):,.0f} points/s)')
    print(f'gp       {sum(s["training"] for s in stats):,} training points, '
          f'{sum(s["outliers_removed"] for s in stats):,} removed as outliers')
    var = np.concatenate([f.surface.var[f.surface.source == 2].ravel() for f in fmap.facades] or [np.empty(0)])
    if len(var):
        print(f'surface  median std {np.sqrt(np.median(var)) * 100:.1f} cm where observed')
    print(f'plsc     {occupancy} ({calibrate_s:.1f} s)')
    print(f'map      {out} ({out.stat().st_size / 1e6:.1f} MB, {total_s:.1f} s in all)')
    return 0


def _write_build_report(folder: Path, args: argparse.Namespace, n_read: int, n_building: int, read_s: float,
                        route_s: float, map_s: float, total_s: float, results: list, routed=None,
                        start_s: float = 0.0) -> Path:
    """Write ``DIR/build.json``: this run's figures (``start_seconds``: starting the cluster;
    ``read_seconds``, ``route_seconds``: wall time of the survey tasks, and of merging, planning
    and the spill tasks, ``plan_seconds`` of which the client's merging and planning), per tile
    task its building points, seconds, processor seconds and its worker's peak memory, per routing
    task (``route_tasks``) its input, points, seconds and processor seconds
    (:mod:`uncertain_facade_map_apps.capacity` fits the costs on them)."""
    import json
    import os

    route_tasks = []
    if routed is not None:
        route_tasks = [{'step': 'survey', 'input': p.index, 'points': p.read, 'building_points': p.points,
                        'seconds': p.seconds, 'cpu_seconds': p.cpu_seconds, 'pid': p.pid} for p in routed.parts]
        route_tasks += [{'step': 'spill', 'input': s.index, 'seconds': s.seconds, 'cpu_seconds': s.cpu_seconds,
                         'pid': s.pid} for s in routed.spilled]
    report = {
        'inputs': [str(p) for p in args.inputs], 'workers': args.workers or 0, 'scheduler': args.scheduler,
        'cpus': os.cpu_count(), 'input_points': n_read, 'building_points': n_building,
        'start_seconds': start_s, 'read_seconds': read_s, 'route_seconds': route_s,
        'plan_seconds': None if routed is None else routed.plan_seconds, 'map_seconds': map_s,
        'total_seconds': total_s,
        'tasks': [{'tile': r.record.id, 'points': r.points, 'seconds': r.map_seconds + r.write_seconds,
                   'map_seconds': r.map_seconds, 'write_seconds': r.write_seconds, 'cpu_seconds': r.cpu_seconds,
                   'pid': r.pid, 'peak_rss_mb': r.max_rss_kb / 1024} for r in results],
        'route_tasks': route_tasks,
    }
    path = folder / 'build.json'
    path.write_text(json.dumps(report, indent=1))
    return path


def _build_tiles(args: argparse.Namespace, config) -> int:
    """``build --tiles DIR``: route the inputs' building points to tiles, map the tiles (in this
    process or on Dask: one cluster for both), write the tiles and the manifest; resume or update
    an existing one."""
    from uncertain_facade_map.io.map_file import remove_stale_temporaries
    from uncertain_facade_map.io.trajectory import read_trajectory
    from uncertain_facade_map.params import map_params, map_params_record
    from uncertain_facade_map.tiling.build import Router, calibration_tiles, check_params, done_already, parse_bounds
    from uncertain_facade_map.tiling.manifest import MANIFEST, Manifest, is_tiled_map, read_manifest, write_manifest

    from .cluster import dask_client, route, run_tiles
    from .las_chunks import BuildingChunks

    if args.sensor is not None and args.trajectory is not None:
        raise CliError('give --sensor or --trajectory, not both')
    if args.workers is not None and args.workers < 0:
        raise CliError(f'--workers must be 0 or more, got {args.workers}')
    if args.workers and args.scheduler:
        raise CliError('give --workers N (a local cluster) or --scheduler ADDRESS (an existing one), not both')
    folder = Path(args.tiles)
    if not folder.parent.exists():
        raise CliError(f'output folder {folder.parent} does not exist')
    folder.mkdir(exist_ok=True)
    params = map_params(config)
    existing = read_manifest(folder) if is_tiled_map(folder) else None
    side = float(args.side if args.side is not None else (existing.side if existing else config.tiles.side))
    if existing is not None:
        check_params(existing, params, side)
    for stale in (folder / MANIFEST, folder / 'tiles' / '*.npz'):
        remove_stale_temporaries(stale)  # of writes a killed build left
    bounds = None if args.bounds is None else parse_bounds(args.bounds)
    trajectory = None if args.trajectory is None else read_trajectory(args.trajectory)
    selection = config.selection if args.select is None else dataclasses.replace(config.selection, mode=args.select)
    reader = BuildingChunks(config, selection, bounds, args.topic, args.sensor, trajectory)
    router = Router(folder, params, side, bounds, existing)
    started = time.perf_counter()
    with dask_client(args.workers or 0, args.scheduler) as client:  # one cluster: routing and tiles
        start_s = time.perf_counter() - started
        routed = route(router, [str(Path(p).absolute()) for p in args.inputs], reader, client)
        if not router.points:
            raise CliError('no building points in the inputs' + ('' if bounds is None else ' within --bounds'))
        tasks, n_read, read_s, route_s = routed.tasks, routed.read, routed.read_seconds, routed.route_seconds
        manifest = existing or Manifest(side, tuple(float(v) for v in router.map_origin), map_params_record(params),
                                        {}, None, {})
        todo = [t for t in tasks if not done_already(folder, existing, t)]
        skipped = len(tasks) - len(todo)
        if existing is None:
            write_manifest(folder, manifest)
        with _counter('tiles', 'tile', args.quiet, total=len(todo)) as update:
            count = iter(range(1, len(todo) + 1))
            results = run_tiles(todo, folder, manifest, progress=lambda _r: update(next(count)),
                                calibrate=None if not todo and manifest.local_calibration else
                                (calibration_tiles(tasks), config.query.resolution if router.has_origins else None),
                                client=client)
        map_s = time.perf_counter() - started - start_s - read_s - route_s
    plsc = manifest.occupancy
    occupancy = ('the fixed formula' if plsc is None else
                 f'scale {plsc["scale"]:.3g}, spread {plsc["spread"] * 100:.1f} cm, learnt on the largest tiles')
    router.cleanup()
    total_s = time.perf_counter() - started
    n_building = router.points
    where = 'in this process' if client is None else 'as tasks'
    print(f'read     {n_read:,} points ({n_building:,} building) from {len(args.inputs)} input(s) in {read_s:.1f} s '
          f'({where}{"" if client is None else f", after {start_s:.1f} s starting the cluster"})')
    print(f'route    {len(tasks)} tiles, {len(router._plan):,} buildings in {route_s:.1f} s '
          f'({routed.plan_seconds:.1f} s merging and planning)')
    print(f'map      {len(results)} tiles written, {skipped} skipped (built already) in {map_s:.1f} s '
          f'({sum(r.points for r in results) / max(map_s, 1e-9):,.0f} building points/s; tasks: '
          f'{sum(r.map_seconds for r in results):.1f} s mapping, {sum(r.write_seconds for r in results):.1f} s writing)')
    per_worker: dict[int, list] = {}
    for r in results:
        per_worker.setdefault(r.pid, []).append(r)
    for pid, rs in sorted(per_worker.items()):
        big = max(rs, key=lambda r: r.points)
        print(f'worker   pid {pid}: {len(rs)} tiles in {sum(r.cpu_seconds for r in rs):.1f} s of CPU, peak RSS '
              f'{max(r.max_rss_kb for r in rs) / 1024:.0f} MB, largest tile {big.record.id} ({big.points:,} points)')
    print(f'plsc     {occupancy} (for all tiles)')
    report = _write_build_report(folder, args, n_read, n_building, read_s, route_s, map_s, total_s, results, routed,
                                 start_s)
    print(f'report   {report} (what uncertain-facade-map capacity plans from)')
    facades = sum(r.facades for r in manifest.tiles.values())
    print(f'tiles    {folder} ({len(manifest.tiles)} tiles, {facades} façades, '
          f'{sum(r.points for r in manifest.tiles.values()):,} points stored; {total_s:.1f} s in all)')
    return 0


def cmd_query(args: argparse.Namespace) -> int:
    """Answer point queries (see ``query --help``)."""
    import numpy as np

    from uncertain_facade_map.io.parameter_file import load_config
    from uncertain_facade_map.tiling.tiled_map import open_map

    config = load_config(args.config)
    fmap = open_map(args.map, config.tiles.cache_mb)
    path = Path(args.points)
    if not path.exists():
        raise CliError(f'no such file: {path}')
    try:
        xyz = np.load(path, allow_pickle=False)
    except (ValueError, OSError, EOFError) as exc:
        raise CliError(f'{path}: not a .npy array ({exc})') from None
    if xyz.dtype != np.float64 or xyz.ndim != 2 or xyz.shape[1] != 3:
        raise CliError(f'{path}: expected a float64 (N, 3) array, got {xyz.dtype} {xyz.shape}')
    query = config.query
    resolution = args.resolution if args.resolution is not None else query.resolution
    started = time.perf_counter()
    result = fmap.query(xyz, query, resolution)
    seconds = time.perf_counter() - started
    out = Path(args.out)
    with open(out, 'wb') as fh:
        np.savez(fh, **result.as_dict())
    print(f'queried  {len(xyz):,} points in {seconds:.2f} s ({len(xyz) / max(seconds, 1e-9):,.0f} points/s), '
          f'{int((result.facade >= 0).sum()):,} on a façade')
    print(f'answers  {out}')
    return 0


def _read_bags(paths: Sequence[str], topic: str | None, poses: Sequence[str] | None = None):
    """The bags' transforms, map origin, topic and pose topics, with their first clouds (the
    frames and fields; the clouds are streamed by :func:`_stream_bags`); checks the fields."""
    from msg_adapters.bag_io import BagClouds, list_topics, read_bag

    joined, origin = BagClouds([]), None
    for path in paths:
        bag = read_bag(path, topic=topic, poses=poses, clouds=False)
        if not bag.scans:
            raise CliError(f'{path}: no messages on {bag.topic}')
        names = bag.scans[0][1].dtype.names or ()
        missing = [c for c in ('x', 'y', 'z') if c not in names]
        if missing:
            topics = ', '.join(f'{t} ({m})' for t, m in list_topics(path).items())
            raise CliError(f'{path}: the clouds on {bag.topic} have no {", ".join(missing)} field (fields: '
                           f'{", ".join(names)}); topics: {topics}')
        joined.scans += bag.scans
        joined.frame_ids += bag.frame_ids
        joined.n_clouds += bag.n_clouds
        joined.transforms += bag.transforms
        joined.pose_topics.update(bag.pose_topics)
        origin = bag.map_origin if origin is None else origin
        joined.topic = bag.topic
    joined.map_origin = origin
    return joined


def _stream_bags(paths: Sequence[str], topic: str, start: float = 0.0, duration: float | None = None):
    """A function streaming the bags' clouds ``(stamp_ns, points, frame_id)`` one after the other,
    from ``start`` seconds after the first cloud for ``duration`` seconds (None: to the end)."""
    from msg_adapters.bag_io import stream_scans

    if start < 0:
        raise CliError(f'--start must be >= 0 s, got {start}')
    if duration is not None and duration <= 0:
        raise CliError(f'--duration must be > 0 s, got {duration}')

    def scans():
        first = None
        for path in paths:
            for item in stream_scans(path, topic):
                first = item[0] if first is None else first
                t = (item[0] - first) / 1e9
                if t >= start and (duration is None or t < start + duration):
                    yield item
    return scans


def _poses_option(text: str | None) -> list[str] | None:
    """``--poses``: None (every pose topic), [] (``none``) or the topics listed."""
    if text is None:
        return None
    return [] if text.strip() == 'none' else [t.strip() for t in text.split(',') if t.strip()]


def _print_poses(bag, buffer) -> None:
    """The bag's pose topics and the tree of their transforms (the buffer's repr, indented)."""
    print(f'poses    {len(bag.transforms):,} transforms from {", ".join(bag.pose_topics)}:')
    print('\n'.join(f'         {line}' for line in repr(buffer).split('\n')[1:]))


def _share(part: int, whole: int) -> str:
    return f'{part / whole:.0%}' if whole else '-'


def cmd_replay(args: argparse.Namespace) -> int:
    """Replay bags offline into a map, or publish them to a running node (see ``replay --help``)."""
    from msg_adapters.bag_io import refuse_unplaceable
    from uncertain_facade_map.io.map_file import save_map
    from uncertain_facade_map.io.parameter_file import load_config
    from uncertain_facade_map.mapping.facade_map import FacadeMap
    from uncertain_facade_map.mapping.worker import map_scans
    from uncertain_facade_map.params import map_params

    config = load_config(args.config)
    if args.out and not Path(args.out).parent.exists():
        raise CliError(f'output folder {Path(args.out).parent} does not exist')
    bag = _read_bags(args.bags, args.topic, _poses_option(args.poses))
    map_frame = config.input.frame_id
    buffer, refused = bag.transform_buffer()
    refuse_unplaceable(', '.join(args.bags), bag, buffer, map_frame)
    for why in refused[:3]:
        print(f'warning: transform refused: {why}', file=sys.stderr)
    if len(refused) > 3:
        print(f'warning: {len(refused) - 3} more transforms refused', file=sys.stderr)
    if args.loop and args.mode != 'publish':
        raise CliError('--loop is for --mode publish')
    windowed = bool(args.start) or args.duration is not None
    scans = _stream_bags(args.bags, bag.topic, args.start, args.duration)
    total = None if windowed else bag.n_clouds
    if args.mode == 'publish':
        from uncertain_facade_map_node.replay import publish_recording

        first = bag.scans[0][0] + int(round(args.start * 1e9))
        window = (first, first + int(round(args.duration * 1e9))) if args.duration is not None else None
        with _counter('published', 'scan', args.quiet, total) as update:
            done = publish_recording(scans, bag.transforms, pose_types=bag.pose_topics,
                                     topic=args.publish_topic or bag.topic, rate=args.rate, loop=args.loop,
                                     reliable=not args.best_effort, progress=update, wait_node=args.wait_node,
                                     window=window if windowed else None)
        if not done['published']:
            raise CliError(f'no scans between {args.start} s and '
                           f'{"the end" if args.duration is None else f"{args.start + args.duration} s"} of the recording')
        print(f'published {done["published"]:,} scans of {bag.topic} on {done["topic"]} in {done["seconds"]:.1f} s '
              f'(rate {args.rate:g}), with {done["transforms"]:,} transforms ({", ".join(done["pose_topics"]) or "none"})')
        print(done['received'])
        for line in done['warnings']:
            print(f'warning: {line}', file=sys.stderr)
        return 1 if done['lost'] else 0
    fmap = FacadeMap(map_params(config), bag.map_origin)
    with _counter('mapped', 'scan', args.quiet, total) as update:
        summary = map_scans(fmap, scans(), config.input, update, config.selection, buffer=buffer,
                            tolerance=config.node.pose_tolerance, max_coordinate=config.node.max_coordinate)
    if not summary.scans:
        raise CliError(f'no scans between {args.start} s and '
                       f'{"the end" if args.duration is None else f"{args.start + args.duration} s"} of the recording')
    frames = ', '.join(f'{f} ({n})' for f, n in summary.frames.items())
    print(f'replayed {summary.scans:,} scans of {bag.topic}: {summary.points:,} points, {summary.building_points:,} '
          f'building, {summary.nonfinite:,} skipped (NaN/Inf)')
    print(f'frames   clouds in {frames}; map frame "{map_frame}"')
    if bag.pose_topics:
        _print_poses(bag, buffer)
    if summary.non_ground:
        print(f'selected {summary.selected:,} of {summary.non_ground:,} non-ground points '
              f'({_share(summary.selected, summary.non_ground)}) as building')
    if summary.thin_selections:
        print(f'warning: in {summary.thin_selections} scans {summary.selection_warning}', file=sys.stderr)
    for note, count in summary.notes.items():
        print(f'placed   {count} scans: {note}')
    if summary.rejected:
        print(f'rejected {summary.rejected:,} scans: ' + '; '.join(f'{n} x {why}' for why, n in summary.reasons.items()))
    print(f'mapped   {summary.buildings} buildings, {summary.facades} façades in {summary.seconds:.1f} s '
          f'({summary.points / max(summary.seconds, 1e-9):,.0f} points/s)')
    if args.out:
        save_map(fmap, args.out)
        print(f'map      {args.out}')
    return 0


def cmd_inspect(args: argparse.Namespace) -> int:
    """What a bag holds and whether its clouds can be mapped (see ``inspect --help``)."""
    from collections import Counter

    import numpy as np

    from msg_adapters.bag_io import list_topics, read_bag
    from uncertain_facade_map.errors import InputError
    from uncertain_facade_map.io.parameter_file import load_config
    from uncertain_facade_map.io.scans import Scan, frames_without_transform

    config = load_config(args.config)
    map_frame = config.input.frame_id
    topics = list_topics(args.bag)
    print(f'bag      {args.bag}')
    for name, kind in topics.items():
        print(f'  {name:<30s} {kind}')
    bag = read_bag(args.bag, topic=args.topic, poses=_poses_option(args.poses))
    if not bag.scans:
        raise CliError(f'{args.bag}: no messages on {bag.topic}')
    fields = bag.scans[0][1].dtype.names or ()
    stamps = [s for s, _ in bag.scans]
    span = (max(stamps) - min(stamps)) / 1e9
    rates = []
    for frame in bag.cloud_frames():
        own = [s for s, f in zip(stamps, bag.frame_ids) if f == frame]
        if len(own) > 1 and max(own) > min(own):
            rates.append((len(own) - 1) / ((max(own) - min(own)) / 1e9))
    rate = f', {float(np.median(rates)):.1f} Hz per frame' if rates else ''
    print(f'clouds   {len(bag.scans):,} on {bag.topic} over {span:.1f} s{rate}, '
          f'{sum(len(p) for _, p in bag.scans) / len(bag.scans):,.0f} points each on average')
    print(f'fields   {", ".join(fields)}')
    classes = config.input.class_field in fields
    moved = any(f != map_frame for f in bag.frame_ids)
    likely = [f for f in ('time', 't', 'timestamp', 'time_stamp', 'offset_time') if f in fields]
    times = ('; clouds in the map frame: no pose needed' if not moved else
             f'; each point placed at its time from field {config.input.time_field!r} (input.time_field)'
             if config.input.time_field and config.input.time_field in fields else
             '; no per-point time field (input.time_field): one pose per cloud, at its stamp'
             + (f'; set input.time_field: {likely[0]} for the per-point times' if likely else ''))
    print(f'classes  {"field " + repr(config.input.class_field) + " (input.class_field)" if classes else "none: the building points are selected (selection.mode: " + config.selection.mode + ")"}'
          + times)
    print(f'frames   {", ".join(f"{f} ({n})" for f, n in bag.cloud_frames().items())}; map frame "{map_frame}" '
          '(input.frame_id)')
    buffer, refused = bag.transform_buffer()
    if bag.pose_topics:
        _print_poses(bag, buffer)
    elif args.poses is not None:
        print('poses    none read (--poses)')
    else:
        print('poses    none (no tf2_msgs/TFMessage, TransformStamped or Odometry topic)')
    for why in refused[:3]:
        print(f'refused  {why}')
    missing = frames_without_transform(bag.cloud_frames(), buffer, map_frame)
    placed, failed = 0, Counter()
    for stamp, points, frame in bag.located_scans:
        try:
            Scan.of(points, frame, stamp, config.input).place(buffer, map_frame, config.node.pose_tolerance)
            placed += 1
        except InputError as exc:
            failed[str(exc).splitlines()[0]] += 1
    print(f'placed   {placed:,} of {len(bag.scans):,} clouds can be put into "{map_frame}"')
    for why, n in failed.most_common(3):
        print(f'         {n} cannot: {why}')
    if missing:
        print(f'hint     no transform connects {", ".join(missing)} with "{map_frame}": set input.frame_id to the root of '
              'the transforms above, or record /tf and /tf_static (or sensor_pose) with the clouds')
    print(f'origin   {bag.map_origin.tolist()} (the map frame\'s georeference, /map_origin)')
    return 0 if placed else 2


def _facade_ids(text: str) -> list[int]:
    """``0,3,5-7`` -> [0, 3, 5, 6, 7]."""
    ids: list[int] = []
    for item in (x.strip() for x in text.split(',')):
        a, _, b = item.partition('-') if item.find('-') > 0 else (item, '', '')
        try:
            first, last = int(a), int(b or a)
        except ValueError:
            first, last = 0, -1
        if last < first:
            raise CliError(f'--facades takes façade ids like 0,3,5-7, got {text!r}')
        ids += range(first, last + 1)
    return ids


def _six(text: str, what: str) -> tuple[float, ...]:
    """Six comma- or space-separated finite numbers (``--prior``, ``--prior-std``)."""
    try:
        values = tuple(float(x) for x in text.replace(',', ' ').split())
    except ValueError:
        values = ()
    if len(values) != 6 or not all(math.isfinite(v) for v in values):
        raise CliError(f'{what}: expected six numbers {"X,Y,Z,ROLL,PITCH,YAW" if what == "--prior" else "SX,SY,SZ,SROLL,SPITCH,SYAW"} '
                       f'(metres and degrees), got {text!r}')
    return values


def _prior_poses(args: argparse.Namespace, n_scans: int):
    """The prior pose of each scan, (4, 4) sensor -> map (metres, map frame unless --georeferenced)."""
    import numpy as np

    from uncertain_facade_map.localisation import pose_from_xyzrpy

    def from_values(values) -> np.ndarray:
        return pose_from_xyzrpy(np.array([*values[:3], *np.deg2rad(values[3:])]))

    if (args.prior is None) == (args.priors is None):
        raise CliError('give the prior pose: --prior X,Y,Z,ROLL,PITCH,YAW (or a 4x4 .npy/.txt file) for one scan, or '
                       '--priors FILE with one line per scan')
    if args.priors is not None:
        path = Path(args.priors)
        if not path.is_file():
            raise CliError(f'no such file: {path}')
        lines = [ln.split('#')[0].strip() for ln in path.read_text(encoding='utf-8', errors='replace').splitlines()]
        lines = [ln for ln in lines if ln]
        if len(lines) != n_scans:
            raise CliError(f'{path}: {len(lines)} prior poses for {n_scans} scans; give one line X Y Z ROLL PITCH YAW '
                           '(metres, degrees) per scan, in the order of the scans')
        return [from_values(_six(ln, f'{path} line {i + 1}')) for i, ln in enumerate(lines)]
    if n_scans != 1:
        raise CliError(f'--prior gives one pose for {n_scans} scans; use --priors FILE with one line per scan')
    path = Path(args.prior)
    if path.suffix.lower() in ('.npy', '.txt') or path.exists():
        if not path.is_file():
            raise CliError(f'no such file: {path}')
        try:
            matrix = np.load(path, allow_pickle=False) if path.suffix.lower() == '.npy' else np.loadtxt(path)
        except (ValueError, OSError, EOFError) as exc:
            raise CliError(f'{path}: not a 4x4 matrix ({exc})') from None
        matrix = np.asarray(matrix, dtype=np.float64)
        if matrix.shape != (4, 4):
            raise CliError(f'{path}: expected a 4x4 pose matrix (sensor -> map), got shape {matrix.shape}')
        return [matrix]
    return [from_values(_six(args.prior, '--prior'))]


def cmd_localise(args: argparse.Namespace) -> int:
    """Localise scans against a map (see ``localise --help``)."""
    import json

    import numpy as np

    from uncertain_facade_map.io.clouds import read_cloud
    from uncertain_facade_map.io.parameter_file import load_config
    from uncertain_facade_map.localisation import covariance_from_std, localise, map_query, xyzrpy_from_pose
    from uncertain_facade_map.params import LOCALIZER_NAME
    from uncertain_facade_map.tiling.tiled_map import open_map

    config = load_config(args.config, LOCALIZER_NAME)
    params = config.localise
    if args.max_points is not None:
        params = dataclasses.replace(params, max_points=args.max_points)
    if args.out and not Path(args.out).resolve().parent.exists():
        raise CliError(f'output folder {Path(args.out).parent} does not exist')
    if args.constant_variance is not None and not args.constant_variance >= 0:
        raise CliError(f'--constant-variance must be >= 0 m^2, got {args.constant_variance}')
    std = (_six(args.prior_std, '--prior-std') if args.prior_std is not None
           else (*params.prior_position_std, *params.prior_rotation_std))
    if not all(v > 0 for v in std):
        raise CliError(f'--prior-std: every standard deviation must be > 0, got {args.prior_std!r}')
    priors = _prior_poses(args, len(args.scans))
    prior_cov = covariance_from_std([*std[:3], *np.deg2rad(std[3:])])
    fmap = open_map(args.map, config.tiles.cache_mb)  # a tiled map loads the tiles near each scan
    origin = np.asarray(fmap.map_origin, dtype=np.float64)
    if args.georeferenced:
        for prior in priors:
            prior[:3, 3] -= origin
    query = map_query(fmap, config.query)
    records = []
    for path, prior in zip(args.scans, priors):
        cloud = read_cloud(path)
        if not len(cloud):
            raise CliError(f'{path}: no points')
        est = localise(cloud.xyz, prior, prior_cov, query, params, constant_variance=args.constant_variance)
        pose = est.pose.copy()
        if args.georeferenced:
            pose[:3, 3] += origin
        xyzrpy = xyzrpy_from_pose(pose)
        cov = est.covariance
        records.append({
            'scan': str(path), 'frame': 'georeferenced' if args.georeferenced else 'map',
            'pose': pose.tolist(), 'xyz': xyzrpy[:3].tolist(), 'rpy_deg': np.rad2deg(xyzrpy[3:]).tolist(),
            'covariance': cov.tolist(),
            'std': [*np.sqrt(np.diag(cov))[:3].tolist(), *np.rad2deg(np.sqrt(np.diag(cov))[3:]).tolist()],
            'moved_from_prior': float(np.linalg.norm(est.pose[:3, 3] - prior[:3, 3])),
            'iterations': est.iterations, 'queries': est.queries, 'points': len(cloud),
            'points_used': est.points_used, 'converged': est.converged, 'status': est.status,
            'residual_ratio': est.residual_ratio,
            'alternatives_xyz': [a[:3, 3].tolist() for a in est.alternatives],
            'cost': est.cost, 'seconds': est.seconds,
        })
    text = '\n'.join(json.dumps(r) for r in records) if len(records) > 1 else json.dumps(records[0], indent=2)
    if args.out:
        Path(args.out).write_text(text + '\n', encoding='utf-8')
        for r in records:
            print(f'localised {r["scan"]}: x {r["xyz"][0]:.3f} y {r["xyz"][1]:.3f} z {r["xyz"][2]:.3f} m, yaw '
                  f'{r["rpy_deg"][2]:.2f} deg (std {r["std"][0] * 100:.1f}, {r["std"][1] * 100:.1f}, '
                  f'{r["std"][2] * 100:.1f} cm, {r["std"][5]:.3f} deg), {r["points_used"]:,} points used, '
                  f'{"converged" if r["converged"] else "NOT converged"}, {r["seconds"] * 1e3:.0f} ms')
        print(f'poses    {args.out}')
    else:
        print(text)
    return 0


def cmd_plot(args: argparse.Namespace) -> int:
    """Draw a map's façades and an overview (see ``plot --help``)."""
    from uncertain_facade_map.tiling.tiled_map import TiledMap, open_map

    from .plots import DPI_RANGE, output_folder, plot_map, select_facades

    if not DPI_RANGE[0] <= args.dpi <= DPI_RANGE[1]:
        raise CliError(f'--dpi must be from {DPI_RANGE[0]} to {DPI_RANGE[1]}, got {args.dpi}')
    ids = None if args.facades is None else _facade_ids(args.facades)
    fmap = open_map(args.map)
    if isinstance(fmap, TiledMap):  # one map of its tiles (those meeting --bounds)
        fmap = fmap.merged(bounds=args.bounds)
        if not fmap.buildings and args.bounds is not None:
            raise CliError(f'no tile of {args.map} meets --bounds {",".join(f"{b:g}" for b in args.bounds)}')
    elif args.bounds is not None:
        raise CliError('--bounds is for tiled maps (a map file is plotted whole)')
    ids = select_facades(fmap, ids)
    output_folder(args.out)
    if not fmap.facades:
        print(f'{PROG}: note: {args.map} has no façades; writing only the overview', file=sys.stderr)
    started = time.perf_counter()
    with _counter('façades', 'façade', args.quiet, len(ids)) as update:
        paths = plot_map(fmap, args.out, ids, dpi=args.dpi, progress=update)
    for path in paths:
        print(path)
    if not args.quiet:
        print(f'plotted  {len(paths) - 1} façades and the overview in {time.perf_counter() - started:.1f} s',
              file=sys.stderr)
    return 0


def cmd_export(args: argparse.Namespace) -> int:
    """Export a map for other localisers (see ``export --help``)."""
    from uncertain_facade_map.io.autoware import export_autoware

    if args.format != 'autoware':  # argparse's choices keep this unreachable; one format for now
        raise CliError(f'unknown export format {args.format!r}')
    started = time.perf_counter()
    with _counter('map tiles', 'tile', args.quiet) as update:
        result = export_autoware(args.map, args.out, args.grid, args.prefix, step=args.step, force=args.force,
                                 progress=update)
    seconds = time.perf_counter() - started
    for f in result.files:
        print(f'{result.folder / f.name}  {f.points:,} points  cell [{f.min_xy[0]}, {f.min_xy[1]}]')
    print(f'metadata {result.metadata}')
    b = result.bounds
    print(f'exported {result.points:,} points in {len(result.files)} files of {result.grid:g} m in {seconds:.2f} s; '
          f'bounds x {b[0]:.3f}..{b[3]:.3f} y {b[1]:.3f}..{b[4]:.3f} z {b[2]:.3f}..{b[5]:.3f} m (map frame, origin '
          f'{" ".join(f"{v:.3f}" for v in result.map_origin)})')
    if result.grid > 100:
        print(f'{PROG}: note: Autoware\'s loader discourages cells over 100 m (it asks for about 20 m)',
              file=sys.stderr)
    return 0


def _bounds(text: str) -> tuple[float, float, float, float]:
    try:
        values = tuple(float(x) for x in text.split(','))
    except ValueError:
        values = ()
    if len(values) != 4 or not all(math.isfinite(v) for v in values) or values[0] > values[2] \
            or values[1] > values[3]:
        raise argparse.ArgumentTypeError(f'expected MIN_X,MIN_Y,MAX_X,MAX_Y in metres (min <= max), got {text!r}')
    return values  # type: ignore[return-value]


def cmd_tile(args: argparse.Namespace) -> int:
    """Cut a map file into a tiled map (see ``tile --help``)."""
    from uncertain_facade_map.io.map_file import load_map
    from uncertain_facade_map.io.parameter_file import load_config
    from uncertain_facade_map.tiling.cut import cut_map

    config = load_config(args.config)
    side = config.tiles.side if args.side is None else args.side
    fmap = load_map(args.map)
    started = time.perf_counter()
    with _counter('tiles', 'tile', args.quiet) as update:
        manifest = cut_map(fmap, args.out, side, (config.query,), overwrite=args.force,
                           progress=lambda done, total: update(done, total))
    print(f'tiled    {len(fmap.buildings)} buildings, {len(fmap.facades)} façades into {len(manifest.tiles)} tiles '
          f'of {manifest.side:g} m in {time.perf_counter() - started:.1f} s')
    print(f'map      {Path(args.out) / "manifest.json"}')
    return 0


def _timed_campaign(scene, index: int):
    """``(cloud, seconds)``: campaign ``index`` of ``scene`` simulated (in a worker process)."""
    from uncertain_facade_map.simulation.campaign import simulate_campaign

    t0 = time.perf_counter()
    cloud = simulate_campaign(scene, index)
    return cloud, time.perf_counter() - t0


def _evaluation_points(cloud, config, what: str, drop_outliers: bool):
    """(N, 3) building points and their (N, 3) sensor origins of a cloud: its building class,
    or, for a cloud without a class field, the points the selection keeps (as ``build``)."""
    from uncertain_facade_map.io.inputs import select_building_points

    if drop_outliers and 'gt_outlier' in (cloud.points.dtype.names or ()):
        cloud = cloud.select(cloud.points['gt_outlier'] == 0)
    points = select_building_points(cloud, config.input, config.selection)
    if points.sensor_origins is None:
        raise CliError(f'the {what} cloud has no origin_x, origin_y, origin_z fields: the evaluation traces rays '
                       'from the sensor origins')
    return points.xyz, points.sensor_origins


def _float_list(text: str) -> tuple[float, ...]:
    try:
        values = tuple(float(x) for x in text.split(',') if x.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(f'expected comma-separated numbers, got {text!r}') from None
    if not values or not all(v > 0 for v in values):
        raise argparse.ArgumentTypeError(f'expected positive numbers, got {text!r}')
    return values


def cmd_evaluate(args: argparse.Namespace) -> int:
    """Evaluate every method's occupancy against a reference scan (see ``evaluate --help``)."""
    import numpy as np

    from msg_adapters.bag_io import load_inputs
    from uncertain_facade_map.evaluation.baselines import METHODS, make_method
    from uncertain_facade_map.evaluation.occupancy import (
        PROTOCOLS,
        distance_to_points,
        evaluate,
        protocol_label,
        subset_auc,
    )
    from uncertain_facade_map.evaluation.report import OURS, accurate_label, write_report
    from uncertain_facade_map.io.parameter_file import load_config

    config = load_config(args.config)
    methods = [m.strip() for m in args.methods.split(',') if m.strip()]
    unknown = [m for m in methods if m not in METHODS]
    if unknown or not methods:
        raise CliError(f'unknown method {", ".join(unknown) or "(none)"}; choose from {", ".join(METHODS)}')
    if args.report is not None and not Path(args.report).parent.exists():
        raise CliError(f'output folder {Path(args.report).parent} does not exist')
    started = time.perf_counter()
    say = (lambda line: None) if args.quiet else (lambda line: print(line, file=sys.stderr, flush=True))
    if args.scene is not None:
        if args.clouds:
            raise CliError('give either --scene or MAPPED REFERENCE, not both')
        from concurrent.futures import ProcessPoolExecutor
        from multiprocessing import get_context

        from uncertain_facade_map.simulation.scenes import build_scene

        n_ref = PROTOCOLS[args.protocol]
        scene = build_scene(args.scene, args.seed)
        clouds = []
        # The campaigns are independent (each seeded by its number): one process per core.
        with ProcessPoolExecutor(min(n_ref + 1, os.cpu_count() or 1), mp_context=get_context('spawn')) as pool:
            for i, (cloud, seconds) in enumerate(pool.map(_timed_campaign, [scene] * (n_ref + 1), range(n_ref + 1))):
                clouds.append(cloud)
                say(f'campaign {i} of {args.scene} ({"mapped" if i == 0 else "reference"}): {len(cloud):,} points '
                    f'simulated in {seconds:.1f} s')
        mapped, references = clouds[0], clouds[1:]
        del clouds
        what = (f'scene {args.scene} (seed {args.seed}), {protocol_label(n_ref)}: campaign 0 mapped, '
                f'{"campaign 1" if n_ref == 1 else f"campaigns 1-{n_ref}"} as the reference')
    else:
        if len(args.clouds) < 2:
            raise CliError('give the MAPPED cloud and one or more REFERENCE clouds, or --scene')
        bound = config.input.max_distance
        mapped = load_inputs([args.clouds[0]], max_distance=bound, warn=say)
        references = [load_inputs([c], max_distance=bound, warn=say) for c in args.clouds[1:]]
        what = (f'{protocol_label(len(references))}: {args.clouds[0]} mapped, '
                f'{", ".join(args.clouds[1:])} as the reference')
    pts, org = _evaluation_points(mapped, config, 'mapped', drop_outliers=False)
    parts = [_evaluation_points(c, config, 'reference', drop_outliers=True) for c in references]
    ref_pts, ref_org = np.concatenate([a for a, _ in parts]), np.concatenate([b for _, b in parts])
    del mapped, references, parts  # only the arrays are needed from here (OctoMap at 0.05 m takes GBs)
    say(f'{what}: {len(pts):,} mapped and {len(ref_pts):,} reference building points')
    factories = [lambda r, m=m: make_method(m, r) for m in methods]
    if args.scene is not None and not args.no_truth:  # the ceiling: the scene's exact geometry as a map
        from uncertain_facade_map.evaluation.truth_map import TruthMethod
        from uncertain_facade_map.simulation.presets import SCENE_SENSORS
        from uncertain_facade_map.simulation.sensor import SensorConfig

        noise_sd = SCENE_SENSORS.get(scene.name, SensorConfig()).range_noise
        factories += [lambda r, how=how, occ=occ: TruthMethod(r, scene, noise_sd, how, occupancy=occ)
                      for how, occ in (('surface', 'fixed'), ('surface', 'plsc'), ('solid', 'fixed'))]
    refs, results = evaluate(factories, pts, org, ref_pts, ref_org, args.resolutions, args.rays, args.negatives,
                             args.seed, progress=say, max_positives=args.positives)
    by = {(r.name, r.resolution): r for r in results}
    names = list(dict.fromkeys(r.name for r in results))
    width = max(len(n) for n in ['method', *names])
    print(f'{"method":<{width}}' + ''.join(f'  PR AUC {res:<5g}  ROC AUC {res:<5g}  train s  test s'
                                           for res in args.resolutions))
    for name in names:
        print(f'{name:<{width}}' + ''.join(f'  {by[(name, res)].pr_auc:12.3f}  {by[(name, res)].roc_auc:13.3f}'
                                                 f'  {by[(name, res)].fit_seconds:7.1f}  {by[(name, res)].predict_seconds:6.1f}'
                                                 for res in args.resolutions))
    for res in args.resolutions:
        ours = by.get((OURS, res))
        if ours is not None and ours.variance is not None:
            auc, share = subset_auc(ours, refs[res], ours.variance <= args.variance_threshold)
            print(f'{accurate_label(args.variance_threshold)} at {res:g} m: PR AUC {auc:.3f} over {share:.0%} of the voxels')
    if args.report is not None:
        distances = {res: distance_to_points(refs[res].centres, pts) for res in args.resolutions}
        notes = [what, f'{len(pts):,} mapped and {len(ref_pts):,} reference building points '
                       '(reference points flagged gt_outlier by the simulator left out)',
                 f'command: uncertain-facade-map evaluate {" ".join(sys.argv[2:]) if len(sys.argv) > 2 else ""}'.rstrip(),
                 f'{time.perf_counter() - started:.0f} s in all']
        path = write_report(args.report, refs, results, distances, args.variance_threshold,
                            'Occupancy evaluation against the baselines', notes)
        print(f'report   {path}')
    return 0


def _sensor(text: str) -> tuple[float, float, float]:
    try:
        values = tuple(float(x) for x in text.split(','))
    except ValueError:
        values = ()
    if len(values) != 3 or not all(math.isfinite(v) for v in values):
        raise argparse.ArgumentTypeError(f'expected X,Y,Z in metres, got {text!r}')
    return values  # type: ignore[return-value]


def _unique_stem(name: str, used: set[str]) -> str:
    stem, i = name, 1
    while stem in used:
        i += 1
        stem = f'{name}_{i}'
    used.add(stem)
    return stem


def cmd_benchmark(args: argparse.Namespace) -> int:
    """Hold points out, map the rest, score them beside reference maps (see ``benchmark --help``)."""
    import json

    from msg_adapters.bag_io import load_inputs
    from uncertain_facade_map.evaluation.benchmark import (
        BenchmarkSettings,
        benchmark_input,
        format_table,
        run_benchmark,
    )
    from uncertain_facade_map.io.parameter_file import load_config
    from uncertain_facade_map.params import map_params

    from .plots import output_folder, plot_benchmark

    if args.scene is None and not args.inputs:
        raise CliError('give INPUT clouds or --scene')
    if args.scene is not None and args.inputs:
        raise CliError('give either INPUT clouds or --scene, not both')
    config = load_config(args.config)
    params = map_params(config)
    settings = BenchmarkSettings(holdout=args.holdout, seed=args.seed, max_scored=args.max_scored)
    out = output_folder(args.out)
    say = (lambda line: None) if args.quiet else (lambda line: print(f'  {line}', file=sys.stderr, flush=True))
    jobs = [(f'scene {args.scene}', None)] if args.scene is not None else [(p, p) for p in args.inputs]
    used: set[str] = set()
    for name, path in jobs:
        started = time.perf_counter()
        scene = None
        if path is None:
            from uncertain_facade_map.simulation.campaign import (
                SCENE_SENSORS,
                SensorConfig,
                campaign,
                drive_duration,
                simulate_campaign,
            )
            from uncertain_facade_map.simulation.scenes import build_scene

            scene = build_scene(args.scene, args.seed)
            update, close = _progress_bar(drive_duration(scene, campaign(scene, 0),
                                                         SCENE_SENSORS.get(scene.name, SensorConfig())),
                                          f'{scene.name} campaign 0', args.quiet)
            try:
                cloud = simulate_campaign(scene, 0, progress=update)
            finally:
                close()
            stem = _unique_stem(f'scene_{args.scene}', used)
        else:
            cloud = load_inputs([path], topic=args.topic, max_distance=config.input.max_distance, warn=say)
            stem = _unique_stem(Path(path).name.split('.')[0] or 'input', used)
        say(f'{name}: {len(cloud):,} points read; choosing the building points')
        data = benchmark_input(cloud, config.input, params, seed=args.seed, sensor=args.sensor)
        with _counter('buildings mapped', 'building', args.quiet) as update:
            results = run_benchmark(data, params, settings, scene=scene, name=name, say=say, progress=update)
        json_path = out / f'{stem}.json'
        json_path.write_text(json.dumps({'command': 'uncertain-facade-map benchmark ' + ' '.join(sys.argv[2:]),
                                         'results': [r.as_dict() for r in results]}, indent=1, allow_nan=False)
                             + '\n')
        png_path = plot_benchmark(results, out / f'{stem}.png')
        for r in results:
            print(format_table(r))
            print()
        print(f'written  {json_path}, {png_path} ({time.perf_counter() - started:.1f} s)')
        print()
    return 0


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of all sub-commands."""
    from uncertain_facade_map.evaluation.baselines import METHODS
    from uncertain_facade_map.evaluation.occupancy import PROTOCOLS
    from uncertain_facade_map.simulation.city import CITY_PRESETS
    from uncertain_facade_map.simulation.presets import SENSOR_PRESETS
    from uncertain_facade_map.simulation.scenes import SCENES

    parser = argparse.ArgumentParser(prog=PROG, description='Façade maps with calibrated uncertainty.')
    sub = parser.add_subparsers(dest='command', required=True, metavar='COMMAND')

    sim = sub.add_parser('simulate', help='scan a built-in scene with a simulated mobile-mapping system',
                         description='Scan a built-in scene (deterministic by seed) in one or more campaigns. '
                                     'Campaign 0 is the mapped one, the others are the reference.')
    sim.add_argument('--scene', default='street', choices=tuple(SCENES) + tuple(CITY_PRESETS),
                     help='street: ~1.7 M points, 7 buildings (default); small: < 50 000 points; '
                          'zurich: real CityJSON footprints; residential: detached houses behind front yards, '
                          'scanned by the hdl64 car lidar (walls seen to 2-3 m); NAME_hard: the same with walls as '
                          'built and a real error model (see docs/simulator.md); city: a grid of streets, 4 x 3 blocks, '
                          '3.35 km of street, ~22 M points in 2 drives, one file per street segment '
                          '(OUT/campaignK/seg_SSS.ply); city_small: 2 x 1 blocks, 0.34 km, ~0.55 M points in 2 drives')
    sim.add_argument('--sensor', choices=tuple(SENSOR_PRESETS),
                     help="sensor preset (default: the scene's; see docs/simulator.md, \"Hard simulator\")")
    sim.add_argument('--seed', type=int, default=0, help='scene seed (default 0)')
    sim.add_argument('--campaigns', type=int, help='number of drives, 1 mapped + references (default 1; city: 2)')
    sim.add_argument('--out', default='output/simulation', help='output folder (default output/simulation)')
    sim.add_argument('--formats', type=_formats,
                     help='formats of the mapped campaign, comma-separated from '
                          f'{",".join(CLOUD_FORMATS + BAG_FORMATS)} (default npz,ply,sqlite3,mcap; city: ply or npz, '
                          'one of them, for every drive)')
    sim.add_argument('--reference-formats', type=_formats, default=('npz',),
                     help='formats of the reference campaigns (default npz)')
    sim.add_argument('--dtype', choices=('f8', 'f4'), default='f8',
                     help='coordinate type: f8 (float64) or f4 (float32, map frame near the map origin)')
    sim.add_argument('--scan-period', type=float, default=0.1, help='seconds of data per bag message (default 0.1)')
    sim.add_argument('--topic', default='/points', help='PointCloud2 topic in bags (default /points)')
    sim.add_argument('--robot', action='store_true',
                     help='bags as a robot records them: each cloud in the lidar frame (every point moved by the '
                          'vehicle pose at its own time), /tf map -> base_link at 50 Hz and /tf_static base_link -> '
                          'lidar (default: clouds in the map frame)')
    sim.add_argument('--range-noise', type=float, help='range noise sigma, metres (default 0.02)')
    sim.add_argument('--outlier-share', type=float, help='share of building returns turned into outliers (default 0.01)')
    sim.add_argument('--range-max', type=float, help='range limit, metres (default 60)')
    sim.add_argument('--angular-step', type=float, help='angle between shots, degrees')
    sim.add_argument('--scan-rate', type=float, help='profiles per second per scanner')
    sim.add_argument('--speed', type=float, help='driving speed, m/s (default 5)')
    sim.add_argument('--cityjson',
                     help='CityJSON file for --scene zurich or zurich_hard (default: the Zurich subset shipped '
                          'with the package)')
    sim.add_argument('--city-blocks', type=_city_blocks, metavar='NX,NY',
                     help='city: blocks along x and y (default 4,3; city_small 2,1)')
    sim.add_argument('--city-block', type=float, metavar='M',
                     help='city: side of a block between its façade lines, metres (default 90; city_small 30)')
    sim.add_argument('--jobs', type=int, help='city: segments simulated at once in worker processes (default 1)')
    sim.add_argument('--force', action='store_true', help='replace existing output files')
    sim.add_argument('--quiet', action='store_true', help='no progress bar')
    sim.set_defaults(func=cmd_simulate)

    build = sub.add_parser('build', help='build a façade map from classified point clouds or bags',
                           description='Build the uncertain façade map from PLY, LAS/LAZ, PCD, NPZ files or ROS bags '
                                       '(ROS 1 .bag, ROS 2 folders, .db3, .mcap) of PointCloud2. In a cloud without the '
                                       'class field the building points are selected: ground removed (Patchwork++), '
                                       'points on tall vertical planes kept (--select).')
    build.add_argument('inputs', nargs='+', metavar='INPUT', help='point clouds or bags')
    build.add_argument('--out', metavar='MAP', help='map file to write (.npz)')
    build.add_argument('--tiles', metavar='DIR',
                       help='write a tiled map into folder DIR instead (a manifest and one map file per tile; '
                            'created if missing): an existing tiled map there is resumed (tiles already built from '
                            'the same points are skipped) or, given new drives, its tiles whose buildings received '
                            'points are updated')
    build.add_argument('--side', type=float, metavar='M', help='--tiles: tile side, metres (default tiles.side)')
    build.add_argument('--workers', type=int, metavar='N',
                       help='--tiles: read and route the inputs (one task per input file) and map the tiles on a '
                            'local Dask cluster of N processes of one thread (default 0: in this process)')
    build.add_argument('--scheduler', metavar='ADDRESS',
                       help='--tiles: read, route and map on an existing Dask cluster (e.g. tcp://host:8786); its '
                            'workers need this package installed, the inputs readable and DIR shared at the same '
                            'paths')
    build.add_argument('--bounds', metavar='MIN_X,MIN_Y,MAX_X,MAX_Y',
                       help='--tiles: build only the points in this area (the inputs\' georeferenced x, y, metres; '
                            'COPC files are read by area)')
    build.add_argument('--config', metavar='YAML', help='ROS 2 parameter file (default: config/facade_mapper.yaml)')
    build.add_argument('--topic', help='PointCloud2 topic of bag inputs (default: the only one)')
    build.add_argument('--select', choices=('auto', 'on', 'off'),
                       help='building points of clouds without classes (selection.mode; default from the config: '
                            'auto, i.e. for clouds without the class field)')
    build.add_argument('--sensor', type=_sensor, metavar='X,Y,Z',
                       help='sensor position (map frame, metres) for clouds without per-point sensor origins, such '
                            'as one sweep in its vehicle frame (0,0,1.8); turns the façades towards it (default: '
                            'from the buildings\' shapes)')
    build.add_argument('--trajectory', metavar='FILE',
                       help='sensor trajectory for clouds without per-point sensor origins but with a time field: '
                            'text, "t x y z ..." per line (TUM format works), t on the clouds\' time base, x y z in '
                            'their coordinates; each point\'s origin is the position at its time')
    build.add_argument('--quiet', action='store_true', help='no progress bar')
    build.set_defaults(func=cmd_build)

    query = sub.add_parser('query', help='answer point queries against a map',
                           description='For each point of P.npy (float64 (N, 3), map frame) write to R.npz: facade '
                                       '(-1 for none), mean_depth, variance, noise_variance, signed_distance '
                                       '(positive outside the building) and p_occupied.')
    query.add_argument('map', metavar='MAP', help='map file from build, or a tiled map (its folder or its manifest.json)')
    query.add_argument('--points', required=True, metavar='P.npy', help='float64 (N, 3) points, map frame')
    query.add_argument('--out', required=True, metavar='R.npz', help='answers to write')
    query.add_argument('--resolution', type=float, metavar='R', help='voxel side for p_occupied, metres (default 0.1)')
    query.add_argument('--config', metavar='YAML', help='ROS 2 parameter file (for the default resolution)')
    query.set_defaults(func=cmd_query)

    replay = sub.add_parser('replay', help='replay bags into a map (offline) or to a running facade_mapper (publish)',
                            description='Replay the PointCloud2 scans of ROS 1 (.bag) and ROS 2 (folder, .db3, .mcap) '
                                        'bags. offline: feed the mapper directly, as fast as it goes, as the node '
                                        'would (the same map); publish: republish them to a running facade_mapper '
                                        'with their recorded timing.')
    replay.add_argument('bags', nargs='+', metavar='BAG', help='bags, replayed one after the other')
    replay.add_argument('--topic', help='PointCloud2 topic to read (default: the only one)')
    replay.add_argument('--mode', choices=('offline', 'publish'), default='offline',
                        help='default offline; publish exits with status 1 when the node\'s diagnostics count fewer '
                             'clouds than were published')
    replay.add_argument('--out', metavar='MAP', help='offline: map file to write')
    replay.add_argument('--config', metavar='YAML', help='ROS 2 parameter file (default: config/facade_mapper.yaml)')
    replay.add_argument('--rate', type=float, default=1.0, help='publish: speed factor of the recorded timing')
    replay.add_argument('--loop', action='store_true', help='publish: start again after the last scan')
    replay.add_argument('--start', type=float, default=0.0, help='seconds into the recording to start at')
    replay.add_argument('--duration', type=float, help='seconds of recording to replay (default: all)')
    replay.add_argument('--publish-topic', help="publish: topic to publish the clouds on (default: the bag's own)")
    replay.add_argument('--poses', metavar='TOPICS',
                        help='pose topics to read, comma-separated, or none (default: every tf2_msgs/TFMessage, '
                             'geometry_msgs/TransformStamped and nav_msgs/Odometry topic; a topic named tf_static holds '
                             'static transforms)')
    replay.add_argument('--wait-node', type=float, default=10.0,
                        help="publish: after the last cloud, read the node's diagnostics until it counted every cloud, "
                             'or none more for this many seconds, to report how many it received (default 10; 0: do '
                             'not wait)')
    replay.add_argument('--best-effort', action='store_true', help='publish: best-effort QoS (default reliable)')
    replay.add_argument('--quiet', action='store_true', help='no progress bar')
    replay.set_defaults(func=cmd_replay)

    inspect = sub.add_parser('inspect', help='what a bag holds and whether its clouds can be mapped',
                             description='List the topics of a bag, its PointCloud2 clouds (rate, fields, frames), '
                                         'the transforms of its pose topics as a tree, and how many clouds can be put '
                                         'into the map frame (input.frame_id) as replay and the node would. Exit '
                                         'status 2 when none can.')
    inspect.add_argument('bag', metavar='BAG', help='ROS 1 (.bag) or ROS 2 (folder, .db3, .mcap) bag')
    inspect.add_argument('--topic', help='PointCloud2 topic (default: the only one)')
    inspect.add_argument('--poses', metavar='TOPICS', help='pose topics to read, comma-separated, or none (default: all)')
    inspect.add_argument('--config', metavar='YAML', help='ROS 2 parameter file (default: config/facade_mapper.yaml)')
    inspect.set_defaults(func=cmd_inspect)

    loc = sub.add_parser(
        'localise', help='localise scans against a map: 6-DoF pose and its covariance from a prior pose',
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description='Estimate the pose of a lidar scan against a map from build (MAP estimate with the prior pose as a '
                    'Gaussian factor; robust point-to-surface residuals weighted by 1 / (map variance + sensor '
                    'noise); points the map does not answer weigh nothing). Prints JSON: pose (4x4, sensor -> map), '
                    'xyz, rpy_deg, covariance (6x6: x, y, z in m, rotations about the map\'s X, Y, Z axes in rad, '
                    'at the sensor), std (m, deg), iterations, queries, points, points_used, converged, seconds; one '
                    'JSON line per scan when several are given.',
        epilog="""how to localise your own drive:
  1. Map the street: uncertain-facade-map build DRIVE1.ply ... --out map.npz (or replay bags). The map
     frame is the frame of those clouds (georeferenced = map + the map's origin, printed by build).
  2. Export each scan to localise as PLY, PCD, NPZ or LAS/LAZ with its points in the SENSOR frame
     (x, y, z fields, metres; de-skewed if the sensor moved during the sweep; every class may stay:
     ground, cars and trees find no façade and weigh nothing).
  3. Give each scan's prior pose of the sensor in the map frame, from GNSS/INS or odometry:
       --prior X,Y,Z,ROLL,PITCH,YAW     metres and degrees (ROS: R = Rz(yaw) Ry(pitch) Rx(roll))
       --prior pose.npy | pose.txt      a 4x4 sensor -> map matrix
       --priors poses.txt               one line "X Y Z ROLL PITCH YAW" per scan, in the order given
     with --georeferenced if those coordinates are georeferenced (the map's CRS, e.g. UTM), and its
     standard deviations --prior-std SX,SY,SZ,SROLL,SPITCH,SYAW (m, deg; default localise.prior_*,
     2 m / 3 deg: GNSS in a street canyon). The map answers only near its façades (about 1 m behind
     and 2 m in front): priors up to localise.search_radius (3 m) and search_yaw (5 deg) off are
     searched; further off, give a better prior.
  4. uncertain-facade-map localise map.npz scan_*.ply --priors poses.txt --out poses.jsonl
     and read the poses. Check "converged" and "std": vertical façades leave the height (and along
     a straight street without cross walls, the position along it) to the prior, and the
     covariance says so.
  Parameters: the localise section of the parameter file (--config), docs/parameters.md.""")
    loc.add_argument('map', metavar='MAP', help='map file from build, or a tiled map (its folder or its manifest.json): its tiles load as the scans need them')
    loc.add_argument('scans', nargs='+', metavar='SCAN', help='scans (PLY, PCD, NPZ, LAS/LAZ), points in the sensor frame')
    loc.add_argument('--prior', metavar='POSE',
                     help='prior pose of one scan: X,Y,Z,ROLL,PITCH,YAW (metres, degrees) or a 4x4 .npy/.txt file')
    loc.add_argument('--priors', metavar='FILE', help='prior poses, one line "X Y Z ROLL PITCH YAW" per scan')
    loc.add_argument('--prior-std', metavar='SX,SY,SZ,SROLL,SPITCH,SYAW',
                     help='standard deviations of the prior, metres and degrees (default: localise.prior_position_std '
                          'and prior_rotation_std, 2 m / 3 deg)')
    loc.add_argument('--georeferenced', action='store_true',
                     help="prior and output positions are georeferenced (map frame + the map's origin)")
    loc.add_argument('--constant-variance', type=float, metavar='V',
                     help='take the map as exact: every answer\'s variance is V m^2 (a baseline; default: the map\'s '
                          'own variance)')
    loc.add_argument('--max-points', type=int, metavar='N', help='scan points used at most (default localise.max_points)')
    loc.add_argument('--out', metavar='JSON', help='write the JSON here (default: print it)')
    loc.add_argument('--config', metavar='YAML', help='ROS 2 parameter file of the localiser (its localise section; '
                     'default: config/facade_localizer.yaml)')
    loc.set_defaults(func=cmd_localise)

    plot = sub.add_parser('plot', help="draw a map's façades and an overview as PNG figures",
                          description='Write per façade facade_<id>.png (points by GMM layer, GP training points '
                                      'and outliers, local GP blocks, mean surface, standard deviation, depth '
                                      'histogram with the GMM) and overview.png (the map from above and in 3D, '
                                      'coloured by standard deviation); print their paths. A map without façades '
                                      'gives only the overview.')
    plot.add_argument('map', metavar='MAP', help='map file from build, or a tiled map (its folder or its manifest.json)')
    plot.add_argument('--bounds', type=_bounds, metavar='MIN_X,MIN_Y,MAX_X,MAX_Y',
                      help='tiled map: plot the tiles whose content meets this box (map frame, metres; default all; '
                           "the façades are then numbered within those tiles; negative values: --bounds=-10,...)")
    plot.add_argument('--out', required=True, metavar='DIR', help='output folder (created if its parent exists)')
    plot.add_argument('--facades', metavar='IDS', help='façade ids to draw, e.g. 0,3,5-7 (default: all)')
    plot.add_argument('--dpi', type=int, default=100, help='resolution of the PNG files (default 100)')
    plot.add_argument('--quiet', action='store_true', help='no progress bar')
    plot.set_defaults(func=cmd_plot)

    ev = sub.add_parser('evaluate', help="compare the map's occupancy with the baselines' against a reference scan",
                        description='Map the same points with every method, turn each map into voxel occupancy '
                                    'probabilities and score them against a reference scan: positives are voxels '
                                    'holding reference points, negatives voxels its rays passed through. Prints PR '
                                    'and ROC AUC and training/testing times per method and resolution, and the '
                                    'accurate-inference AUC of our map; --report writes report.md with figures.')
    ev.add_argument('clouds', nargs='*', metavar='CLOUD',
                    help='the MAPPED cloud, then one or more REFERENCE clouds (with origin_x/y/z)')
    ev.add_argument('--scene', choices=tuple(SCENES),
                    help='simulate this scene instead: campaign 0 mapped, the next ones as the reference')
    ev.add_argument('--protocol', choices=tuple(PROTOCOLS), default='paper',
                    help="with --scene: 'paper' takes campaigns 1-4 as the reference (the paper's protocol, "
                         "default), 'one-campaign' campaign 1 only")
    ev.add_argument('--seed', type=int, default=0, help='scene seed and seed of the voxel subsets (default 0)')
    ev.add_argument('--methods', default=','.join(METHODS),
                    help=f'comma-separated from {",".join(METHODS)} (default: all)')
    ev.add_argument('--resolutions', type=_float_list, default=(0.1, 0.05), help='voxel sides, metres (default 0.1,0.05)')
    ev.add_argument('--variance-threshold', type=float, default=0.01,
                    help='accurate inference: voxels with a variance at most this, m^2 (default 0.01)')
    ev.add_argument('--rays', type=int, default=50_000, help='reference rays traced (default 50000)')
    ev.add_argument('--negatives', type=int, default=400_000,
                    help='free voxels kept at most, a weighted subset (default 400000)')
    ev.add_argument('--positives', type=int, default=400_000,
                    help='occupied voxels kept at most, a weighted subset (default 400000)')
    ev.add_argument('--no-truth', action='store_true',
                    help="with --scene: leave out the ceiling (the scene's exact geometry read as a map)")
    ev.add_argument('--report', metavar='DIR', help='write DIR/report.md and its figures')
    ev.add_argument('--config', metavar='YAML', help='ROS 2 parameter file (input and selection sections)')
    ev.add_argument('--quiet', action='store_true', help='no progress lines')
    ev.set_defaults(func=cmd_evaluate)

    tile = sub.add_parser('tile', help='cut a map file into a tiled map (a manifest and one map file per tile)',
                          description='Write MAP as a tiled map in DIR: DIR/manifest.json and DIR/tiles/<id>.npz, '
                                      'one ordinary map file per square tile of the map frame; each building goes '
                                      'whole to the tile of the centre of its points\' bounding box. Every command '
                                      'that takes a MAP reads the folder too, loading tiles as they are needed.')
    tile.add_argument('map', metavar='MAP', help='map file from build')
    tile.add_argument('--out', required=True, metavar='DIR', help='folder of the tiled map')
    tile.add_argument('--side', type=float, metavar='M', help='tile side, metres (default: tiles.side of the config)')
    tile.add_argument('--config', metavar='YAML', help='ROS 2 parameter file (default: config/facade_mapper.yaml)')
    tile.add_argument('--force', action='store_true', help='replace a tiled map already in DIR')
    tile.add_argument('--quiet', action='store_true', help='no progress bar')
    tile.set_defaults(func=cmd_tile)

    bm = sub.add_parser('benchmark', help='hold points out of a cloud, map the rest, score the held-out points',
                        description='For each INPUT (or a simulated --scene): take its building points (the class '
                                    'field if present, else the walls picked by RANSAC of vertical planes), hold out '
                                    'a random share and occlusion patches on every façade, map the rest with this '
                                    'package and two reference maps (a local plane through the 12 nearest mapped '
                                    'points; one PCA plane per façade), and score the held-out points: share '
                                    'answered, RMSE and bias of the signed distance, 68 %% and 95 %% interval '
                                    'coverage, NLL, CRPS and occupancy PR-AUC, observed and occluded, planar and '
                                    'near depth steps apart; a simulated scene is also scored against its exact '
                                    'truth. Prints a table per input, writes DIR/NAME.json and DIR/NAME.png.')
    bm.add_argument('inputs', nargs='*', metavar='INPUT', help='point clouds or bags, each benchmarked on its own')
    bm.add_argument('--scene', choices=tuple(SCENES),
                    help='simulate this scene (campaign 0) instead and score against its exact truth too')
    bm.add_argument('--holdout', type=float, default=0.5, help='random share of points held out (default 0.5)')
    bm.add_argument('--seed', type=int, default=0, help='seed of the hold-out, the wall pick and the scene (default 0)')
    bm.add_argument('--out', default='output/benchmark', metavar='DIR',
                    help='folder of the JSON and PNG files (created if its parent exists; default output/benchmark)')
    bm.add_argument('--config', metavar='YAML', help='ROS 2 parameter file (default: config/facade_mapper.yaml)')
    bm.add_argument('--sensor', type=_sensor, metavar='X,Y,Z',
                    help='sensor position for the wall pick of clouds without class field (default: the mean '
                         'sensor origin, else 0,0,1.8 as in a vehicle-frame sweep)')
    bm.add_argument('--max-scored', type=int, default=200_000,
                    help='score at most this many held-out points, a seeded subset (default 200000)')
    bm.add_argument('--topic', help='PointCloud2 topic of bag inputs (default: the only one)')
    bm.add_argument('--quiet', action='store_true', help='no progress lines')
    bm.set_defaults(func=cmd_benchmark)
    ex = sub.add_parser('export', help="write a map's mean surface for other localisers (Autoware PCD tiles)",
                        description="Write the map's mean surface (the facet cells of every façade's surface raster) "
                                    "for Autoware's pointcloud_map_loader: one binary PCD per GRID x GRID m cell, "
                                    'named PREFIX_<min_x>_<min_y>.pcd (the pointcloud_divider\'s names; a point goes '
                                    'to floor(x / GRID) * GRID), fields x, y, z, std (float32, metres, map frame; std '
                                    'is the standard deviation of the surface), plus pointcloud_map_metadata.yaml '
                                    '(x_resolution, y_resolution, per file [min_x, min_y]; the map origin in a '
                                    'comment). Load it with pcd_paths_or_directory:=[DIR] '
                                    'pcd_metadata_path:=DIR/pointcloud_map_metadata.yaml. Prints the files, points '
                                    'and bounds.')
    ex.add_argument('map', metavar='MAP', help="map file from build, or a tiled map's folder (or its manifest.json)")
    ex.add_argument('--out', required=True, metavar='DIR', help='export folder (created if its parent exists)')
    ex.add_argument('--format', default='autoware', choices=('autoware',), help='export format (default autoware)')
    ex.add_argument('--grid', type=float, default=20.0,
                    help="cell side, whole metres (default 20, Autoware's; over 100 is discouraged)")
    ex.add_argument('--prefix', default='pointcloud_map', metavar='NAME',
                    help='start of the PCD file names (default pointcloud_map)')
    ex.add_argument('--step', type=float,
                    help="surface sampling step on the façade planes, metres (default: each raster's cell)")
    ex.add_argument('--force', action='store_true', help='replace an earlier export in DIR (its .pcd files and metadata)')
    ex.add_argument('--quiet', action='store_true', help='no progress bar')
    ex.set_defaults(func=cmd_export)
    return parser


def _linalg_error() -> type[Exception]:
    import numpy as np

    return np.linalg.LinAlgError


def run_reporting(prog: str, command: Callable[[], int]) -> int:
    """Run a command; every error a user can cause ends in one line on stderr, none in a traceback.

    Returns:
        The command's exit status; 2 for bad input (a FacadeMapError), 1 for an I/O failure
        or a fit that failed anyway, 130 when interrupted.
    """
    try:
        return int(command())
    except FacadeMapError as exc:
        print(f'{prog}: error: {exc}', file=sys.stderr)
        return 2
    except OSError as exc:
        print(f'{prog}: error: {exc.strerror or exc}{f": {exc.filename}" if exc.filename else ""}', file=sys.stderr)
        return 1
    except (ArithmeticError, _linalg_error()) as exc:  # a fit failed on data the checks let through
        print(f'{prog}: error: a fit failed ({type(exc).__name__}: {exc}); the input may hold corrupted points '
              '(see input.max_distance)', file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f'{prog}: interrupted', file=sys.stderr)
        return 130


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line; returns the exit status (0 ok, 2 bad input, 1 I/O failure)."""
    parser = build_parser()
    args = parser.parse_args(argv)
    for name in ('campaigns', 'jobs'):
        if getattr(args, name, None) is not None and getattr(args, name) < 1:
            parser.error(f'--{name} must be at least 1')
    return run_reporting(PROG, lambda: args.func(args))

if __name__ == '__main__':
    sys.exit(main())
