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
                                                          idle_flush=5.0))
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
        assert int(values['clouds_dropped']) == 0 and int(values['flushes']) == 1
        saved = client.call(SaveMap, 'save_map', SaveMap.Request(path=str(tmp_path / 'node.npz')))
        assert saved.success, saved.message
    finally:
        node.stop()
        client.close()
    expected, _ = offline_core(scans, np.zeros(3), params)
    node_map = load_map(tmp_path / 'node.npz')
    expected.map_origin = node_map.map_origin  # the node's origin is its parameter, not the bag's
    assert_same_maps(tmp_path / 'node.npz', save_map(expected, tmp_path / 'core.npz'))
