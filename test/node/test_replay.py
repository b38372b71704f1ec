"""`uncertain-facade-map replay`: ROS 1, ROS 2 sqlite3 and mcap bags give the map the core
builds from the same scans; publish mode reaches a node in another process and ends with
the same map; bad bags get one-line errors that list what the bag holds."""

import dataclasses
import os
import subprocess
import sys
import time

import numpy as np
import pytest
from support import assert_same_maps

from msg_adapters.bag_io import write_bag
from uncertain_facade_map.io.map_file import load_map, save_map
from uncertain_facade_map.io.parameter_file import dump_config
from uncertain_facade_map.mapping.facade_map import FacadeMap
from uncertain_facade_map.mapping.worker import map_scans
from uncertain_facade_map.params import Config, UpdateParams, map_params
from uncertain_facade_map.simulation.export import split_scans
from uncertain_facade_map_apps.cli import main

#: Small updates, so that replaying the small scene streams through several of them.
BATCH = 3000


@pytest.fixture(scope='module')
def recording(tmp_path_factory, scenes):
    """The small scene's drive as bags of every format, and a parameter file with small batches."""
    out = tmp_path_factory.mktemp('replay')
    cloud = scenes.campaign('small', 0)
    scans = list(split_scans(cloud, 0.1))
    bags = {storage: write_bag(out / name, scans, storage=storage, map_origin=cloud.map_origin)
            for storage, name in (('rosbag1', 'drive.bag'), ('sqlite3', 'drive_sqlite3'), ('mcap', 'drive_mcap'))}
    config = Config()
    config = dataclasses.replace(config, update=UpdateParams(batch_points=BATCH),
                                 node=dataclasses.replace(config.node, qos='reliable', queue_size=10000,
                                                          idle_flush=5.0, batching='fixed'),
                                 persistence=dataclasses.replace(config.persistence, map_dir=str(out)))
    params = out / 'params.yaml'
    params.write_text(dump_config(config))
    return out, scans, bags, params, cloud.map_origin


def offline_core(scans, map_origin, params):
    from uncertain_facade_map.io.parameter_file import load_config

    config = load_config(params)
    fmap = FacadeMap(map_params(config), map_origin)
    summary = map_scans(fmap, (p for _, p in scans), config.input)
    return fmap, summary


@pytest.mark.parametrize('storage', ['rosbag1', 'sqlite3', 'mcap'])
def test_offline_replay_gives_the_core_map(recording, storage, capsys):
    out, scans, bags, params, origin = recording
    target = out / f'{storage}.npz'
    assert main(['replay', str(bags[storage]), '--out', str(target), '--config', str(params), '--quiet']) == 0
    printed = capsys.readouterr().out
    assert f'replayed {len(scans)} scans of /points' in printed and 'façades' in printed
    expected, summary = offline_core(scans, origin, params)
    assert summary.building_points > 3 * BATCH  # several updates, then the flush
    assert_same_maps(target, save_map(expected, out / f'core_{storage}.npz'))
    np.testing.assert_array_equal(load_map(target).map_origin, origin)


def test_replay_window(recording, capsys):
    out, scans, bags, params, _ = recording
    assert main(['replay', str(bags['mcap']), '--start', '2', '--duration', '3', '--quiet', '--config',
                 str(params)]) == 0
    assert 'replayed 30 scans' in capsys.readouterr().out


def test_bad_bags_get_one_line_errors(recording, tmp_path, capsys):
    out, scans, bags, params, _ = recording
    assert main(['replay', str(bags['sqlite3']), '--topic', '/lidar']) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and '/lidar' in err and '/points' in err and 'PointCloud2' in err
    no_xyz = [(s, np.zeros(5, dtype=[('a', 'f4'), ('b', 'f4')])) for s, _ in scans[:3]]
    bag = write_bag(tmp_path / 'no_xyz.bag', no_xyz, storage='rosbag1')
    assert main(['replay', str(bag)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and 'no x, y, z field' in err and '/points (sensor_msgs/msg/PointCloud2)' in err
    assert main(['replay', str(tmp_path / 'missing.bag')]) == 2
    assert main(['replay', str(bags['mcap']), '--start', '99']) == 2
    assert 'no scans between' in capsys.readouterr().err


@pytest.mark.ros
def test_publish_mode_reaches_a_node_and_gives_the_same_map(recording, tmp_path):
    pytest.importorskip('uncertain_facade_map.srv')
    from test_node import Client, NodeProcess, diagnostics

    from uncertain_facade_map.srv import SaveMap

    out, scans, bags, params, origin = recording
    domain = 150 + os.getpid() % 50
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST')
    client = Client(domain)
    node = NodeProcess(params, env, tmp_path / 'node.log')
    try:
        node.wait_ready(client)
        started = time.monotonic()
        done = subprocess.run([sys.executable, '-m', 'uncertain_facade_map_apps.cli', 'replay', str(bags['mcap']),
                               '--mode', 'publish', '--rate', '4', '--quiet', '--config', str(params)],
                              env=env, capture_output=True, text=True, timeout=120)
        assert done.returncode == 0, done.stderr
        assert f'published {len(scans)} scans' in done.stdout
        assert time.monotonic() - started > (scans[-1][0] - scans[0][0]) / 1e9 / 4 * 0.9  # the recorded timing
        values = diagnostics(client, until=lambda v: int(v['clouds_received']) >= len(scans) and v['settled'] == 'True',
                             timeout=120)
        assert int(values['clouds_dropped']) == 0 and int(values['flushes']) <= 2  # one idle flush: its two steps
        saved = client.call(SaveMap, 'save_map', SaveMap.Request(path='node_live.npz'))  # in the map folder
        assert saved.success, saved.message
    finally:
        node.stop()
        client.close()
    expected, _ = offline_core(scans, np.zeros(3), params)
    node_map = load_map(out / 'node_live.npz')
    expected.map_origin = node_map.map_origin  # the node's origin is its parameter, not the bag's
    assert_same_maps(out / 'node_live.npz', save_map(expected, tmp_path / 'core.npz'))


def test_a_drive_recorded_as_a_robot_replays_to_the_map_frame_drives_map(recording, scenes, tmp_path, capsys):
    """`simulate --robot`: each cloud in the lidar frame, every point moved by the vehicle's pose at
    its own time, /tf map -> base_link at 50 Hz, /tf_static base_link -> lidar. Replay puts each
    point back at its time (motion compensation): the map equals the map-frame drive's to
    float64 time resolution (99 % of answers within 1 mm); with one pose per cloud
    (input.time_field '') it would not (a 5 m/s drive moves 0.5 m in a 0.1 s message)."""
    import dataclasses

    from uncertain_facade_map.io.parameter_file import load_config
    from uncertain_facade_map.pipeline.step7_queries import query_points

    out, scans, bags, params, origin = recording
    assert main(['simulate', '--scene', 'small', '--robot', '--formats', 'mcap', '--out', str(tmp_path), '--quiet']) == 0
    robot = tmp_path / 'campaign0_mcap'
    assert main(['inspect', str(robot), '--config', str(params)]) == 0
    shown = capsys.readouterr().out
    assert 'map -> base_link (dynamic' in shown and '-> lidar (static)' in shown and 'placed   100 of 100' in shown
    plain = out / 'plain_for_robot.npz'
    assert main(['replay', str(bags['mcap']), '--out', str(plain), '--config', str(params), '--quiet']) == 0
    maps = {}
    no_time = tmp_path / 'no_time.yaml'
    config = load_config(params)
    no_time.write_text(dump_config(dataclasses.replace(config, input=dataclasses.replace(config.input, time_field=''))))
    for name, cfg in (('compensated', params), ('one_pose', no_time)):
        maps[name] = tmp_path / f'{name}.npz'
        assert main(['replay', str(robot), '--out', str(maps[name]), '--config', str(cfg), '--quiet']) == 0
    capsys.readouterr()
    reference = load_map(plain)
    pts = np.vstack(list(reference.points.values()))
    rng = np.random.default_rng(7)
    xyz = pts[rng.choice(len(pts), 3000, replace=False)] + rng.normal(0, 0.2, (3000, 3))
    expected = query_points(reference.facades, xyz, 0.1, 0.5, 0.5)
    errors = {}
    for name, path in maps.items():
        fmap = load_map(path)
        got = query_points(fmap.facades, xyz, 0.1, 0.5, 0.5)
        on = (got.facade >= 0) & (expected.facade >= 0)
        errors[name] = np.abs(got.mean_depth[on] - expected.mean_depth[on])
        if name == 'compensated':
            assert len(fmap.facades) == len(reference.facades)
            for k in reference.points:  # every stored point back where the map-frame drive has it
                assert np.abs(fmap.points[k] - reference.points[k]).max() < 2e-6
    assert (errors['compensated'] < 1e-3).mean() > 0.98 and np.median(errors['compensated']) < 1e-6
    # Without compensation 80 % of answers are off by more than 1 mm, half by more than 4.5 mm.
    assert (errors['one_pose'] < 1e-3).mean() < 0.5 and np.median(errors['one_pose']) > 3e-3


class _FakeWatch:
    """A node's diagnostics as publish mode reads them: a fixed count of clouds received."""

    def __init__(self, received: int) -> None:
        self.values = {'clouds_received': str(received), 'clouds_mapped': str(received), 'clouds_waiting': '0',
                       'clouds_dropped': '0', 'clouds_rejected': '0'}

    def received(self) -> int:
        return int(self.values['clouds_received'])


def test_publish_mode_says_how_many_clouds_the_node_received_and_why_some_may_be_lost(monkeypatch):
    from uncertain_facade_map_node.replay import _received

    line, warnings, lost = _received(_FakeWatch(10), 0, 10, 0.2, 5_000_000, True)
    assert line.startswith('the node received 10 of the 10 clouds published') and warnings == [] and not lost
    monkeypatch.delenv('FASTRTPS_DEFAULT_PROFILES_FILE', raising=False)
    line, warnings, lost = _received(_FakeWatch(7), 0, 10, 0.2, 5_000_000, True)
    assert 'received 7 of the 10' in line and warnings[0] == '3 of 10 clouds never reached the node' and lost
    assert 'DDS fragmentation' in warnings[1] and 'fastdds_large_clouds.xml' in warnings[1]
    monkeypatch.setenv('FASTRTPS_DEFAULT_PROFILES_FILE', '/profile.xml')
    _, warnings, lost = _received(_FakeWatch(7), 0, 10, 0.2, 5_000_000, False)
    assert len(warnings) == 2 and '--best-effort' in warnings[1] and lost
    line, warnings, lost = _received(None, None, 10, 0.0, 0, True)
    assert 'not asked' in line and warnings == [] and not lost
    line, _, lost = _received(_FakeWatch(0), None, 10, 0.2, 0, True)
    assert 'no facade_mapper diagnostics' in line


def test_replay_refuses_absurd_and_byte_swapped_scans_as_the_node_does(recording, tmp_path, capsys):
    """A scan with points at 1e30 m, one with finite but absurd ones, and one byte-swapped are
    refused and counted by reason (node.max_coordinate, as the node refuses them); the rest
    are mapped; one line each, never a traceback (issue 25 item 6)."""
    out, scans, bags, params, origin = recording
    bad = [(stamp, points.copy()) for stamp, points in scans[:12]]
    bad[3][1]['x'][:5] = 1e30
    bad[5][1]['z'][:1] = -3e9
    swapped = bad[7][1]
    for c in ('x', 'y', 'z'):
        swapped[c] = swapped[c].byteswap()
    bag = write_bag(tmp_path / 'bad_mcap', bad, storage='mcap', map_origin=origin)
    assert main(['replay', str(bag), '--config', str(params), '--quiet']) == 0
    printed = capsys.readouterr().out
    assert 'replayed 12 scans' in printed
    assert 'rejected 3 scans' in printed and printed.count('beyond node.max_coordinate = 100000 m') == 3
    assert 'is is_bigendian wrong?' in printed
