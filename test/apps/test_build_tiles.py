"""``build --tiles``: a tiled build resumes after a kill (same tiles, bit for bit), a second drive
updates only the tiles whose buildings it saw, and a worker killed during a task on Dask leaves
the same map. Input: three copies of the `small` scene, 60 m apart in x (6 buildings, 6 tiles).

About 55 s (six in-process builds of 6 tiles, two Dask builds with a cluster of 2 workers, one on
an existing cluster of 1 worker: --scheduler). The routing on the workers gives the same tiles as
in this process (one input file or four); the manifest is written in batches."""

import hashlib
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from uncertain_facade_map.io.cloud import Cloud
from uncertain_facade_map.io.map_file import load_map
from uncertain_facade_map.io.npz import read_npz, write_npz
from uncertain_facade_map.params import QueryConfig
from uncertain_facade_map.tiling.manifest import MANIFEST, read_manifest
from uncertain_facade_map.tiling.tiled_map import local_calibration, merge_maps, reading_id
from uncertain_facade_map_apps.cli import main

COPIES = 3
SHIFT = 60.0


def _copies(cloud, copies):
    parts = []
    for k in range(copies):
        p = cloud.points.copy()
        p['x'] += SHIFT * k
        p['origin_x'] += SHIFT * k
        p['building_id'] = np.where(p['building_id'] >= 0, p['building_id'] + 2 * k, p['building_id'])
        parts.append(p)
    return Cloud(np.concatenate(parts), cloud.map_origin)


@pytest.fixture(scope='module')
def drives(scenes, tmp_path_factory):
    folder = tmp_path_factory.mktemp('drives')
    write_npz(folder / 'drive1.npz', _copies(scenes.campaign('small', 0), COPIES))
    write_npz(folder / 'drive2.npz', _copies(scenes.campaign('small', 1), 1))  # the first copy's street only
    return folder


def _hashes(folder):
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted((Path(folder) / 'tiles').glob('*.npz'))}


@pytest.fixture(scope='module')
def built(drives, tmp_path_factory):
    out = tmp_path_factory.mktemp('built') / 'map'
    assert main(['build', str(drives / 'drive1.npz'), '--tiles', str(out), '--side', '20', '--quiet']) == 0
    return out


def test_a_build_lists_its_tiles(built):
    manifest = read_manifest(built)
    assert len(manifest.tiles) == 2 * COPIES
    assert sorted(manifest.building_tiles) == list(range(2 * COPIES))
    assert not (built / '.work').exists()
    for record in manifest.tiles.values():
        assert load_map(built / record.file).buildings == record.buildings
    # The local reading's calibration: that of the largest tiles joined (6 small tiles: all of them,
    # 200,000 points not reached), as the one-file map of the whole learns it.
    joined = merge_maps([load_map(built / r.file) for r in manifest.tiles.values()])
    assert manifest.local_calibration == local_calibration(joined)
    assert 0.5 < manifest.local_calibration[reading_id(QueryConfig())].scale < 5


def test_a_killed_build_resumes_to_the_same_tiles(drives, built, tmp_path, capsys):
    out = tmp_path / 'map'
    cmd = [sys.executable, '-m', 'uncertain_facade_map_apps.cli', 'build', str(drives / 'drive1.npz'), '--tiles',
           str(out), '--side', '20', '--quiet']
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 120
    try:
        while time.monotonic() < deadline:
            if (out / MANIFEST).exists() and read_manifest(out).tiles:
                break
            time.sleep(0.05)
        os.kill(proc.pid, signal.SIGKILL)
    finally:
        proc.wait()
    listed = len(read_manifest(out).tiles)
    assert 1 <= listed < 2 * COPIES, 'killed while the tiles were written'
    stale = out / 'tiles' / '.tile_2_0.npz.deadbeef.tmp'  # what a write killed midway leaves
    stale.write_bytes(b'partial')
    assert main(['build', str(drives / 'drive1.npz'), '--tiles', str(out), '--quiet']) == 0
    printed = capsys.readouterr().out
    assert f'{2 * COPIES - listed} tiles written, {listed} skipped' in printed
    assert not stale.exists()
    assert _hashes(out) == _hashes(built)
    assert read_manifest(out).tiles == read_manifest(built).tiles
    assert read_manifest(out).occupancy == read_manifest(built).occupancy is not None
    assert read_manifest(out).local_calibration == read_manifest(built).local_calibration != {}


def test_a_second_drive_updates_only_the_tiles_it_saw(drives, built, tmp_path, capsys):
    out = tmp_path / 'map'
    shutil.copytree(built, out)  # copy2: bytes and mtimes kept
    before = {p.name: (p.read_bytes(), p.stat().st_mtime_ns) for p in (out / 'tiles').glob('*.npz')}
    first = read_manifest(out)
    assert main(['build', str(drives / 'drive2.npz'), '--tiles', str(out), '--quiet']) == 0
    after = read_manifest(out)
    seen = {first.building_tiles[0], first.building_tiles[1]}
    assert len(seen) == 2
    for name, (data, mtime) in before.items():
        tid = name[:-4]
        path = out / 'tiles' / name
        if tid in seen:
            assert path.read_bytes() != data
            assert after.tiles[tid].inputs.startswith(first.tiles[tid].inputs + '+')
            old, new = load_map(built / 'tiles' / name), load_map(path)
            assert new.n_points > old.n_points and new.buildings == old.buildings
        else:
            assert path.read_bytes() == data and path.stat().st_mtime_ns == mtime, name
            assert after.tiles[tid] == first.tiles[tid]
    # Again: nothing to do (the run's points are in those tiles already).
    capsys.readouterr()
    assert main(['build', str(drives / 'drive2.npz'), '--tiles', str(out), '--quiet']) == 0
    assert '0 tiles written, 2 skipped' in capsys.readouterr().out


@pytest.fixture(scope='module')
def drive_files(drives):
    """drive1.npz cut into four input files (its copies, the second in two): the same points in
    the same order."""
    cloud = read_npz(drives / 'drive1.npz')
    n = len(cloud.points) // COPIES
    cuts = [0, n, n + n // 3, 2 * n, len(cloud.points)]
    paths = []
    for k, (a, b) in enumerate(zip(cuts[:-1], cuts[1:])):
        paths.append(drives / f'drive1_{k}.npz')
        write_npz(paths[-1], Cloud(cloud.points[a:b], cloud.map_origin))
    return paths


def test_routing_on_the_workers_gives_the_same_tiles(drive_files, built, tmp_path, capsys):
    """Issue 29: the inputs read and routed as tasks (one per file, 2 workers) give the tiles of
    the in-process build (0 workers) of the same files, records and fingerprints alike, and of the
    one-file build, bit for bit; build.json times the routing tasks."""
    runs = {}
    for workers in (0, 2):
        out = tmp_path / f'w{workers}'
        assert main(['build', *map(str, drive_files), '--tiles', str(out), '--side', '20', '--quiet',
                     '--workers', str(workers)]) == 0
        runs[workers] = out
    assert 'as tasks' in capsys.readouterr().out
    assert _hashes(runs[0]) == _hashes(runs[2]) == _hashes(built)
    assert read_manifest(runs[0]).tiles == read_manifest(runs[2]).tiles
    assert read_manifest(runs[2]).building_tiles == read_manifest(built).building_tiles
    # (learnt on the tile of the largest part files: the one-file build may choose another of the same points)
    assert read_manifest(runs[0]).occupancy == read_manifest(runs[2]).occupancy is not None
    report = json.loads((runs[2] / 'build.json').read_text())
    surveys = [t for t in report['route_tasks'] if t['step'] == 'survey']
    assert [t['input'] for t in surveys] == list(range(len(drive_files)))
    assert sum(t['points'] for t in surveys) == report['input_points']
    assert sum(t['building_points'] for t in surveys) == report['building_points']
    assert len({t['pid'] for t in report['route_tasks']} | {t['pid'] for t in report['tasks']}) == 2  # one cluster
    assert report['read_seconds'] > 0 and report['route_seconds'] >= report['plan_seconds'] >= 0


def _routed(drives, tmp_path):
    """(config, the tiled map's folder, its tile tasks, a new manifest): drive1 routed in this
    process into 20 m tiles, the map not built."""
    from uncertain_facade_map.io.inputs import select_building_points
    from uncertain_facade_map.io.parameter_file import load_config
    from uncertain_facade_map.params import map_params, map_params_record
    from uncertain_facade_map.tiling.build import Router
    from uncertain_facade_map.tiling.manifest import Manifest

    config = load_config(None)
    params = map_params(config)
    out = tmp_path / 'map'
    out.mkdir()
    router = Router(out, params, 20.0)
    pts = select_building_points(read_npz(drives / 'drive1.npz'), config.input)
    router.add(pts.xyz, pts.building_id, pts.sensor_origins, pts.map_origin)
    manifest = Manifest(20.0, tuple(router.map_origin), map_params_record(params), {}, None, {})
    return config, out, router.spill(), manifest


def _dying_build(task):
    """build_tile, but the first attempt at tile_0_0 kills its worker process."""
    from uncertain_facade_map.tiling.build import build_tile

    marker = Path(task.folder) / 'killed_once'
    if task.tile_id == 'tile_0_0' and not marker.exists():
        marker.write_text(str(os.getpid()))
        os.kill(os.getpid(), signal.SIGKILL)
    return build_tile(task)


def test_a_lost_worker_is_replaced_and_the_map_is_the_same(drives, built, tmp_path):
    import cloudpickle

    from uncertain_facade_map.tiling.build import calibration_tiles
    from uncertain_facade_map_apps.cluster import run_tiles

    cloudpickle.register_pickle_by_value(sys.modules[__name__])
    config, out, tasks, manifest = _routed(drives, tmp_path)
    results = run_tiles(tasks, out, manifest, workers=2, function=_dying_build,
                        calibrate=(calibration_tiles(tasks), config.query.resolution))
    assert (out / 'killed_once').exists()
    assert len(results) == len(tasks) == 2 * COPIES
    killed = int((out / 'killed_once').read_text())
    # tile_0_0 was run again by another process (the other worker, or the killed one's replacement:
    # which one depends on how fast the tasks go, so no count of processes is asserted)
    assert killed not in {r.pid for r in results}
    assert _hashes(out) == _hashes(built)
    assert manifest.occupancy == read_manifest(built).occupancy is not None
    assert manifest.local_calibration == read_manifest(built).local_calibration != {}


def test_the_manifest_is_written_in_batches(drives, built, tmp_path, monkeypatch):
    """run_tiles writes the manifest at most every MANIFEST_PERIOD s (the first tile at once), once
    more at the end and with the calibrations: not once per tile (quadratic for a city of 17,000
    tiles); the manifest written equals the per-tile build's."""
    import uncertain_facade_map_apps.cluster as cluster
    from uncertain_facade_map.tiling.build import calibration_tiles
    from uncertain_facade_map.tiling.manifest import write_manifest

    writes = []
    monkeypatch.setattr(cluster, 'write_manifest', lambda folder, m: (writes.append(len(m.tiles)),
                                                                     write_manifest(folder, m)))
    monkeypatch.setattr(cluster, 'MANIFEST_PERIOD', 1e9)
    config, out, tasks, manifest = _routed(drives, tmp_path)
    cluster.run_tiles(tasks, out, manifest, calibrate=(calibration_tiles(tasks), config.query.resolution))
    assert len(tasks) == 2 * COPIES
    assert writes == [1, 2 * COPIES]  # the first tile, then all of them with the calibrations
    assert read_manifest(out).tiles == read_manifest(built).tiles
    assert read_manifest(out).local_calibration == read_manifest(built).local_calibration


def test_a_build_on_an_existing_cluster(drives, built, tmp_path):
    """``--scheduler ADDRESS``: the build runs on a cluster it did not start (here a local one
    started by the test, as a user's SSH/SLURM/Kubernetes cluster would be), which it leaves
    running; the same tiles as the in-process build."""
    from dask.distributed import LocalCluster

    from uncertain_facade_map_apps.cluster import ONE_THREAD

    with LocalCluster(n_workers=1, threads_per_worker=1, processes=True, dashboard_address=':0',
                      env=dict(ONE_THREAD), silence_logs=40) as cluster:
        out = tmp_path / 'map'
        assert main(['build', str(drives / 'drive1.npz'), '--tiles', str(out), '--side', '20', '--quiet',
                     '--scheduler', cluster.scheduler_address]) == 0
        assert cluster.scheduler.status.name == 'running' and len(cluster.workers) == 1  # left running
    assert _hashes(out) == _hashes(built)
    assert read_manifest(out).tiles == read_manifest(built).tiles
    report = json.loads((out / 'build.json').read_text())
    assert report['scheduler'] == cluster.scheduler_address and report['workers'] in (0, None)
