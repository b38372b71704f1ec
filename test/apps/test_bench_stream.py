"""The streaming benchmark (``make bench``, ``--stages stream``): a small drive fed to a
``MapWorker`` as the node feeds it, at two rates; its accounts, latencies and accuracy.

About 20 s on the idle 2-core machine (two mapping processes spawned, each waiting
``node.idle_flush`` after the last cloud); several times that under the load of other runs, as
the mapping process runs at ``node.mapping_nice``."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from uncertain_facade_map.params import Config
from uncertain_facade_map_apps import bench_stream as bs
from uncertain_facade_map_apps.bench import stages_of


@pytest.fixture(scope='module')
def drive():
    # The small scene's first 3 s: 30 clouds of about 140 building points.
    return bs.simulate_drive('small', scene='small', seconds=3.0)


@pytest.fixture(scope='module')
def measured(drive):
    return bs.measure_drive(drive, rates=(2.0, 8.0))


def test_drive_is_cut_into_the_sensors_clouds_of_building_points(drive):
    assert len(drive.clouds) == 30
    assert drive.building_points == sum(len(c.xyz) for c in drive.clouds) > 2000
    assert drive.points > drive.building_points  # ground and clutter were left out, building points counted
    assert np.all(np.diff(drive.offsets) > 0) and drive.offsets[0] == 0.0
    assert drive.offsets[-1] == pytest.approx(2.9, abs=0.11)  # 10 Hz clouds
    assert drive.seconds == pytest.approx(3.0, abs=0.11)
    assert all(c.building_id is not None and c.sensor_origins is not None for c in drive.clouds)


def test_accounts_add_up_and_latencies_are_positive(measured, drive):
    runs = measured['runs']
    assert [r['rate'] for r in runs] == [2.0, 8.0]
    for r in runs:
        assert 'skipped' not in r and r['stopped'] == ''
        assert r['clouds_in'] == len(drive.clouds)
        assert r['clouds_in'] == r['clouds_mapped'] + r['clouds_dropped'] + r['clouds_failed']
        assert r['building_points_in'] == drive.building_points
        assert r['building_points_in'] == r['building_points_mapped'] + r['building_points_dropped']
        assert r['clouds_failed'] == 0 and r['clouds_discarded'] == 0
        # Every mapped cloud's latency, none from another run.
        assert 0.0 < r['latency_p50_s'] <= r['latency_p95_s'] <= r['latency_max_s'] < r['seconds'] + 1e-6
        assert r['building_points_per_s'] == pytest.approx(r['building_points_mapped'] / r['seconds'])
        assert r['peak_child_mb'] > 50 and r['peak_parent_mb'] > 50
    # 30 clouds of 140 points are far below the default batch of 100,000, but with the node's
    # default node.batching 'latency' a cloud is mapped as soon as the mapper is free: queryable
    # well before the idle flush (node.idle_flush = 2 s after the last cloud) would map it. At 2x
    # (a cloud every 50 ms) none is dropped; at 8x the per-cloud round trip may not keep up.
    slow = runs[0]
    assert slow['clouds_dropped'] == 0
    assert Config().node.batching == 'latency' and slow['latency_p95_s'] < Config().node.idle_flush
    assert measured['sustained'] == (8.0 if runs[1]['clouds_dropped'] == 0 else 2.0)


def test_streamed_map_is_as_accurate_as_the_batch_map(measured):
    batch = measured['batch']['accuracy']
    assert 0.005 < batch['rmse_m'] < 0.05 and batch['coverage95'] > 0.9 and batch['cells'] > 1000
    # The map streamed with no dropped cloud holds the same points as the batch map.
    acc = measured['runs'][0]['accuracy']
    assert acc is not None and acc['facades'] == batch['facades']
    assert acc['rmse_m'] <= 1.5 * batch['rmse_m']
    assert acc['coverage95'] >= batch['coverage95'] - 0.05


def test_table_has_a_line_per_rate_the_sustained_rate_and_accuracy(measured):
    text = '\n'.join(bs.format_drive(measured))
    assert text.count('\n   2x ') == 1 and text.count('\n   8x ') == 1
    assert f'sustained: {measured["sustained"]:g}x with no dropped cloud' in text
    # A cloud is mapped when the mapper is free (node.batching 'latency'), not at the idle flush.
    fast = bs.sustained(measured['runs'], bs.TARGET_P95)
    assert fast in (2.0, 8.0) and f'sustained with latency p95 <= 1 s: {fast:g}x' in text
    assert 'batch map of all' in text and 'streamed 2x:' in text


def test_a_hopeless_rate_is_given_up_and_the_higher_ones_skipped(drive):
    # Fed at 50x, each cloud an update of its own: clouds wait at once; giving up once the map
    # is 0 s behind stops it. (The map updated in the worker's thread: no third mapping process
    # to wait for.)
    cfg = Config()
    cfg = dataclasses.replace(cfg, node=dataclasses.replace(cfg.node, mapping_process=False),
                              update=dataclasses.replace(cfg.update, batch_points=1))
    out = bs.measure_drive(drive, rates=(50.0, 100.0), config=cfg, give_up=0.0)
    first, second = out['runs']
    assert first['stopped'].startswith('given up') and first['accuracy'] is None
    assert first['clouds_discarded'] > 0 and first['clouds_in'] < len(drive.clouds)
    assert first['clouds_in'] == (first['clouds_mapped'] + first['clouds_dropped'] + first['clouds_failed']
                                  + first['clouds_discarded'])
    assert second == {'drive': 'small', 'rate': 100.0, 'skipped': 'skipped: 50x was given up'}
    assert out['sustained'] is None and out['batch'] is None
    assert 'skipped: 50x was given up' in '\n'.join(bs.format_drive(out))


def test_sustained_is_the_highest_rate_without_a_drop():
    def run(rate, dropped=0, stopped=''):
        return {'rate': rate, 'clouds_dropped': dropped, 'clouds_failed': 0, 'stopped': stopped}

    assert bs.sustained([run(1), run(2), run(4, 3), {'rate': 8, 'skipped': 'x'}]) == 2
    assert bs.sustained([run(1, 1), run(2, 5)]) is None
    assert bs.sustained([run(1), run(2, 0, 'given up')]) == 1
    timed = [dict(run(1), latency_p95_s=0.5), dict(run(2), latency_p95_s=3.0)]
    assert bs.sustained(timed) == 2 and bs.sustained(timed, 1.0) == 1 and bs.sustained(timed, 0.1) is None


def test_azimuth_clouds_partition_a_sweep_in_turning_order():
    rng = np.random.default_rng(0)
    xyz = rng.normal(0.0, 10.0, (1000, 3))
    sensor = np.array([1.0, -2.0, 1.8])
    parts = bs.azimuth_clouds(xyz, sensor, 8)
    assert sorted(np.concatenate(parts).tolist()) == list(range(1000))
    azimuth = np.arctan2(xyz[:, 1] - sensor[1], xyz[:, 0] - sensor[0])
    assert all(azimuth[a].max() <= azimuth[b].min() for a, b in zip(parts, parts[1:]))
    assert len(parts) == 8


def test_real_check_table_is_parsed():
    text = ('av2_7fab_sweep0.ply: 9 walls, 38433 wall points, 18951 mapped, 19482 held out (263 in patches)\n'
            'map                   obs RMSE obs cov95  patch RMSE patch cov95  PR-AUC.1 answered\n'
            'this package            0.034m     0.947      0.079m       0.905     0.951    0.999\n'
            'local plane (12 nn)     0.040m     0.997      0.138m       0.962     0.940    1.000\n')
    got = bs.parse_real_check(text)
    assert got['about'].startswith('av2_7fab_sweep0.ply: 9 walls')
    assert got['this package'] == {'obs_rmse_m': 0.034, 'obs_cov95': 0.947, 'patch_rmse_m': 0.079,
                                   'patch_cov95': 0.905, 'prauc': 0.951, 'answered': 0.999}
    assert got['local plane (12 nn)']['patch_rmse_m'] == 0.138


def test_stages_option_selects_stages_groups_and_what_they_read():
    assert stages_of('stream', False) == ['stream_street', 'stream_av2', 'stream_hdl64', 'stream_laps']
    assert stages_of('stream', True)[-1] == 'stream_real'
    assert stages_of('query', False) == ['simulate', 'build', 'query']
    assert stages_of(None, False)[:4] == ['simulate', 'build', 'query', 'query_raster']
    with pytest.raises(SystemExit, match='unknown stage'):
        stages_of('nope', False)


def test_json_lines_are_strict_json_one_per_rate_and_one_per_drive(measured, capsys):
    from uncertain_facade_map_apps.bench import _print_stream

    _print_stream({'stage': 'stream small', 'stream': measured, 'peak_mb': 100.0}, as_json=True, live=False)
    lines = capsys.readouterr().out.splitlines()
    records = [json.loads(line, parse_constant=lambda c: pytest.fail(f'{c} in a JSON line')) for line in lines]
    assert [r['stage'] for r in records] == ['stream small 2x', 'stream small 8x', 'stream small']
    assert records[0]['items'] == measured['building_points'] and records[0]['unit'] == 'building points'
    assert records[-1]['sustained_rate'] == measured['sustained'] and records[-1]['sustained_rate_p95_1s'] == bs.sustained(measured['runs'], bs.TARGET_P95)
    assert records[-1]['batch']['seconds'] > 0


def test_laps_print_their_cost_stored_points_and_memory(drive, capsys):
    """stream_laps: a lap's CPU, the stored points after it and memory, one JSON line a lap."""
    from uncertain_facade_map_apps.bench import _print_stream

    rows = bs.drive_laps(drive, laps=2)
    assert [r['lap'] for r in rows] == [1, 2] and rows[0]['stored'] > 0
    assert rows[1]['stored'] >= rows[0]['stored'] and all(r['cpu_s'] > 0 and r['map_mb'] > 0 for r in rows)
    _print_stream({'stage': 'stream laps', 'laps': rows, 'peak_mb': 1.0}, as_json=True, live=False)
    lines = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert [line['stage'] for line in lines] == ['stream laps 1', 'stream laps 2']
    text = '\n'.join(bs.format_laps(rows))
    assert 'x lap 1' in text and f'{rows[1]["stored"]:,}' in text
