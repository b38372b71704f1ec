"""The facade_mapper node serving a tiled map (issue 29), in its own process (about 25 s).

The small scene's map (two buildings) is cut into 20 m tiles, one building each; the node
starts on the tiled map (``persistence.map_path``, a cache of 1 MB: one tile) and this
process, as a localiser would, queries it (the answers must equal the TiledMap's and the
one-file map's), moves the sensor's pose from one building to the other (the node loads the
tiles near it and evicts the far one), lists the tiles near positions, and loads a folder
without a manifest (refused, the map kept), the one-file map and the tiled map again.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np
import pytest

pytestmark = pytest.mark.ros

rclpy = pytest.importorskip('rclpy')
pytest.importorskip('uncertain_facade_map.srv')

from test_node import Client, NodeProcess, diagnostics, node_config  # noqa: E402

from uncertain_facade_map.io.map_file import save_map  # noqa: E402
from uncertain_facade_map.params import QueryConfig  # noqa: E402
from uncertain_facade_map.pipeline.step7_queries import ANSWER_FIELDS  # noqa: E402
from uncertain_facade_map.tiling.cut import cut_map  # noqa: E402
from uncertain_facade_map.tiling.tiled_map import TiledMap  # noqa: E402
from uncertain_facade_map_apps.ros_client import answers_of, list_tiles_request, query_request, tiles_of  # noqa: E402

SIDE = 20.0
#: Where the sensor stands beside each building (map frame x, y), metres.
NEAR = {'tile_0_0': (9.0, 11.0), 'tile_1_0': (31.0, 11.0)}


@pytest.fixture(scope='module')
def maps(scenes, tmp_path_factory):
    """(work folder, the one-file map, its file, the tiled map's folder)."""
    work = tmp_path_factory.mktemp('tiled_node')
    whole = scenes.building_map('small', 0)
    save_map(whole, work / 'whole.npz')
    manifest = cut_map(whole, work / 'tiled', SIDE)
    assert sorted(manifest.tiles) == sorted(NEAR)
    return work, whole, work / 'whole.npz', work / 'tiled'


@pytest.fixture(scope='module')
def running(maps):
    work, _, _, folder = maps
    domain = 100 + (os.getpid() + 53) % 100
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST')
    params = node_config(work, **{'persistence.map_path': str(folder), 'persistence.autosave_period': 0.5,
                                  'tiles.cache_mb': 1.0, 'tiles.radius': 5.0, 'tiles.follow_period': 0.1,
                                  'tiles.follow_frame': 'base_link',
                                  'publish.diagnostics_period': 0.2, 'service.max_query_points': 20000})
    client = Client(domain)
    node = NodeProcess(params, env, work / 'node.log')
    try:
        node.wait_ready(client)
        yield client, node
    finally:
        node.stop()
        client.close()
        print((work / 'node.log').read_text()[-3000:])


def probe(whole, n=4000, seed=0):
    """Points near the stored points and in the box around them, both buildings."""
    pts = np.vstack(list(whole.points.values()))
    rng = np.random.default_rng(seed)
    near = pts[rng.choice(len(pts), n // 2)] + rng.normal(0, 0.3, (n // 2, 3))
    return np.vstack([near, rng.uniform(pts.min(0) - 2, pts.max(0) + 2, (n - n // 2, 3))])


def query(client, xyz):
    from uncertain_facade_map.srv import QueryPoints

    response = client.call(QueryPoints, 'query_points', query_request(xyz, flat=True))
    assert response.success, response.message
    return answers_of(response), response.message


def list_tiles(client, x, y, radius=0.0):
    from uncertain_facade_map.srv import ListTiles

    return client.call(ListTiles, 'list_tiles', list_tiles_request(x, y, radius))


def same_facades(got, whole):
    """Façade ids of the tiled answers as (building, rank in the building) keys of ``whole``."""
    key = {f.facade_id: (f.building, sum(g.building == f.building for g in whole.facades[:f.facade_id]))
           for f in whole.facades}
    return [key.get(int(i)) for i in got]


def test_queries_equal_the_tiled_map_and_the_one_file_map(running, maps):
    client, _ = running
    _, whole, _, folder = maps
    xyz = probe(whole)
    got, message = query(client, xyz)
    assert 'tiled map' in message
    want = TiledMap(folder).query(xyz, QueryConfig())
    for key in ANSWER_FIELDS:
        np.testing.assert_array_equal(got[key], getattr(want, key), err_msg=key)
    one = whole.query(xyz, QueryConfig())
    assert same_facades(got['facade'], whole) == same_facades(one.facade, whole)
    assert (got['facade'] >= 0).sum() > 500
    # get_facades of a building: its tile's models, numbered as the tiled answers number them
    from uncertain_facade_map.srv import GetFacades

    merged = TiledMap(folder).merged()
    for b in whole.buildings:
        response = client.call(GetFacades, 'get_facades', GetFacades.Request(building=int(b)))
        assert response.success and {f.building for f in response.facades} == {b}
        assert sorted(f.facade_id for f in response.facades) == [f.facade_id for f in merged.facades if f.building == b]
        hit = got['facade'][np.isin(got['facade'], [f.facade_id for f in response.facades])]
        assert len(hit) > 100  # the answers name these ids
    for key in ANSWER_FIELDS[1:]:
        np.testing.assert_array_equal(got[key], getattr(one, key), err_msg=key)


def loaded_near(client):
    out = tiles_of(list_tiles(client, 20.0, 11.0, 100.0))
    return {t for t, flag in zip(out['ids'], out['loaded']) if flag}


def test_the_node_follows_its_pose_and_evicts_the_far_tile(running):
    from geometry_msgs.msg import TransformStamped

    client, _ = running
    for k, (tile, (x, y)) in enumerate(list(NEAR.items()) * 2):
        pose = TransformStamped()
        pose.header.frame_id, pose.child_frame_id = 'map', 'lidar'
        pose.header.stamp.sec = 10 + k
        pose.transform.translation.x, pose.transform.translation.y = x, y
        pose.transform.rotation.w = 1.0
        client.pose_pub.publish(pose)
        deadline = time.monotonic() + 20
        while loaded_near(client) != {tile}:  # 1 MB of cache: the tile near the pose, the other evicted
            assert time.monotonic() < deadline, loaded_near(client)
            time.sleep(0.1)
    values = diagnostics(client, until=lambda v: float(v['tiles_follow_x']) == NEAR['tile_1_0'][0])
    assert values['tiled_map'] and int(values['tiles']) == 2 and int(values['tiles_loaded']) == 1
    assert int(values['tiles_preloads']) >= 4 and int(values['tiles_evictions']) >= 3
    assert 0 < float(values['tiles_cache_mb']) < 3 and float(values['tiles_cache_limit_mb']) == 1.0
    assert float(values['tiles_preload_max_seconds']) > 0 and int(values['tiles_preload_failures']) == 0


def test_the_node_follows_a_frame_on_tf_alone(running):
    """A robot that publishes /tf only (clouds in the map frame, no sensor_pose): with
    tiles.follow_frame the node follows that frame's position in its transform buffer (which
    comes first, before the sensor_pose child of the test above)."""
    from geometry_msgs.msg import TransformStamped
    from tf2_msgs.msg import TFMessage

    client, _ = running
    tf_pub = client.on_spin_thread(lambda: client.node.create_publisher(TFMessage, '/tf', 100))
    for k, tile in enumerate(['tile_0_0', 'tile_1_0', 'tile_0_0']):
        x, y = NEAR[tile]
        t = TransformStamped()
        t.header.frame_id, t.child_frame_id = 'map', 'base_link'
        t.header.stamp.sec = 100 + k
        t.transform.translation.x, t.transform.translation.y = x + 0.5, y
        t.transform.rotation.w = 1.0
        deadline = time.monotonic() + 20
        while loaded_near(client) != {tile}:
            assert time.monotonic() < deadline, loaded_near(client)
            tf_pub.publish(TFMessage(transforms=[t]))
            time.sleep(0.1)
    values = diagnostics(client, until=lambda v: float(v['tiles_follow_x']) == NEAR['tile_0_0'][0] + 0.5)
    assert int(values['tiles_loaded']) == 1


def test_list_tiles_answers_the_tiles_within_the_radius(running, maps):
    client, _ = running
    folder = maps[3]
    near = tiles_of(list_tiles(client, 9.0, 11.0, 1.0))
    assert near['ids'] == ['tile_0_0']
    np.testing.assert_array_equal(near['bounds'], [[0.0, 0.0, SIDE, SIDE]])
    assert near['files'] == [str((folder / 'tiles' / 'tile_0_0.npz').resolve())] and Path(near['files'][0]).is_file()
    assert tiles_of(list_tiles(client, 9.0, 11.0))['ids'] == ['tile_0_0']  # radius 0: tiles.radius, 5 m
    both = tiles_of(list_tiles(client, 9.0, 11.0, 12.0))  # tile_1_0's square is 11 m away
    assert both['ids'] == ['tile_0_0', 'tile_1_0']
    np.testing.assert_array_equal(both['bounds'][1], [SIDE, 0.0, 2 * SIDE, SIDE])
    assert tiles_of(list_tiles(client, 500.0, 11.0, 10.0))['ids'] == []
    bad = list_tiles(client, 9.0, 11.0, -3.0)
    assert not bad.success and 'radius' in bad.message


def test_load_map_of_a_folder_without_a_manifest_fails_and_keeps_the_map(running, maps):
    from uncertain_facade_map.srv import LoadMap, SaveMap

    client, _ = running
    work, whole, one_file, folder = maps
    xyz = probe(whole, 500, seed=1)
    before, _ = query(client, xyz)
    empty = work / 'not_a_map'
    empty.mkdir()
    response = client.call(LoadMap, 'load_map', LoadMap.Request(path=str(empty)))
    assert not response.success and 'manifest.json' in response.message and '\n' not in response.message
    after, message = query(client, xyz)
    assert 'tiled map' in message
    for key in ANSWER_FIELDS:
        np.testing.assert_array_equal(after[key], before[key], err_msg=key)
    # save_map never writes into the tiled map (persistence.map_path): it wants a path
    refused = client.call(SaveMap, 'save_map', SaveMap.Request(path=''))
    assert not refused.success and 'read-only' in refused.message
    assert sorted(p.name for p in folder.iterdir()) == ['manifest.json', 'tiles']
    saved = client.call(SaveMap, 'save_map', SaveMap.Request(path=str(work / 'live.npz')))
    assert saved.success, saved.message
    # a one-file map replaces the tiled map (list_tiles then fails), the tiled map comes back
    response = client.call(LoadMap, 'load_map', LoadMap.Request(path=str(one_file)))
    assert response.success and response.facades == len(whole.facades)
    assert 'no tiled map' in list_tiles(client, 9.0, 11.0).message
    single, message = query(client, xyz)
    assert 'tiled' not in message
    for key in ANSWER_FIELDS[1:]:
        np.testing.assert_array_equal(single[key], before[key], err_msg=key)
    response = client.call(LoadMap, 'load_map', LoadMap.Request(path=str(folder / 'manifest.json')))
    assert response.success and 'tiled map' in response.message and response.facades == len(whole.facades)
    again, _ = query(client, xyz)
    np.testing.assert_array_equal(again['facade'], before['facade'])
