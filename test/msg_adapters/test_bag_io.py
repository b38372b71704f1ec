"""Tests of msg_adapters.bag_io: point clouds in ROS 1 / ROS 2 bags (sqlite3, mcap)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from msg_adapters.bag_io import (
    ORIGIN_KEY,
    ORIGIN_TOPIC,
    BagClouds,
    list_topics,
    read_bag,
    read_bag_cloud,
    write_bag,
)
from msg_adapters.pointcloud2 import pointcloud2_from_structured, rosbags_types
from uncertain_facade_map.errors import InputError
from uncertain_facade_map.io.cloud import Cloud

ORIGIN = (2683000.125, 1247000.5, 400.0)
DTYPE = np.dtype([('x', 'f8'), ('y', 'f8'), ('z', 'f8'), ('time', 'f8'),
                  ('building_id', 'i4'), ('class', 'u1')])
T0 = 1_700_000_000_123_456_789


def make_scans(count: int = 3, n: int = 200) -> list[tuple[int, np.ndarray]]:
    rng = np.random.default_rng(7)
    scans = []
    for k in range(count):
        pts = np.zeros(n + k, DTYPE)
        for name in ('x', 'y', 'z'):
            pts[name] = rng.normal(scale=50.0, size=len(pts))
        pts['x'][0] = np.nan  # a non-finite value survives too
        pts['time'] = T0 / 1e9 + k * 0.1 + rng.uniform(0, 0.1, len(pts))
        pts['building_id'] = rng.integers(-1, 40, len(pts))
        pts['class'] = rng.integers(0, 6, len(pts))
        scans.append((T0 + k * 100_000_000, pts))
    return scans


def bag_path(tmp_path: Path, storage: str, name: str = 'scans') -> Path:
    return tmp_path / (f'{name}.bag' if storage == 'rosbag1' else name)


def string_msg(text: str):
    return lambda typestore: typestore.types['std_msgs/msg/String'](data=text)


@pytest.mark.parametrize('storage', ['sqlite3', 'mcap', 'rosbag1'])
def test_round_trip(tmp_path: Path, storage: str) -> None:
    scans = make_scans()
    path = write_bag(bag_path(tmp_path, storage), scans, storage=storage, map_origin=ORIGIN,
                     frame_id='map')
    assert path.exists()
    bag = read_bag(path)
    assert isinstance(bag, BagClouds)
    assert bag.topic == '/points'
    assert bag.map_origin.dtype == np.float64
    assert bag.map_origin.tolist() == list(ORIGIN)
    assert [s for s, _ in bag.scans] == [s for s, _ in scans]
    for (_, want), (_, got) in zip(scans, bag.scans):
        assert got.dtype == want.dtype
        assert got.tobytes() == want.tobytes()

    cloud = read_bag_cloud([path])
    assert isinstance(cloud, Cloud)
    assert cloud.same_as(Cloud(np.concatenate([p for _, p in scans]), np.array(ORIGIN)))

    assert list_topics(path) == {
        ORIGIN_TOPIC: 'geometry_msgs/msg/PointStamped',
        '/points': 'sensor_msgs/msg/PointCloud2',
    }


@pytest.mark.parametrize('storage', ['sqlite3', 'mcap'])
def test_ros2_metadata_holds_origin(tmp_path: Path, storage: str) -> None:
    from rosbags.rosbag2 import Reader

    path = write_bag(tmp_path / 'b', make_scans(1, 5), storage=storage, map_origin=ORIGIN)
    with Reader(path) as reader:
        custom = reader.storage.metadata.custom
        assert custom[ORIGIN_KEY] == '2683000.125 1247000.5 400.0'
        assert tuple(float(v) for v in custom[ORIGIN_KEY].split()) == ORIGIN
    text = (path / 'metadata.yaml').read_text()
    assert f'storage_identifier: {storage}' in text
    assert 'version: 9' in text


def test_origin_from_custom_data_without_origin_topic(tmp_path: Path) -> None:
    from rosbags.rosbag2 import Writer

    types = rosbags_types()
    pts = make_scans(1, 4)[0][1]
    msg = pointcloud2_from_structured(pts, stamp_ns=T0, frame_id='map', msg_types=types)
    path = tmp_path / 'custom'
    with Writer(path, version=9) as writer:
        writer.set_custom_data(ORIGIN_KEY, '1.5 -2.25 1e3')
        conn = writer.add_connection('/cloud', 'sensor_msgs/msg/PointCloud2',
                                     typestore=types.typestore)
        writer.write(conn, T0, types.typestore.serialize_cdr(msg, 'sensor_msgs/msg/PointCloud2'))
    bag = read_bag(path)
    assert bag.topic == '/cloud'
    assert bag.map_origin.tolist() == [1.5, -2.25, 1000.0]
    assert bag.scans[0][1].tobytes() == pts.tobytes()


def test_no_origin_gives_zeros(tmp_path: Path) -> None:
    from rosbags.rosbag2 import Writer

    types = rosbags_types()
    pts = make_scans(1, 4)[0][1]
    msg = pointcloud2_from_structured(pts, stamp_ns=T0, frame_id='map', msg_types=types)
    path = tmp_path / 'plain'
    with Writer(path, version=9) as writer:
        conn = writer.add_connection('/cloud', 'sensor_msgs/msg/PointCloud2',
                                     typestore=types.typestore)
        writer.write(conn, T0, types.typestore.serialize_cdr(msg, 'sensor_msgs/msg/PointCloud2'))
    assert read_bag(path).map_origin.tolist() == [0.0, 0.0, 0.0]


@pytest.mark.parametrize('storage', ['sqlite3', 'rosbag1'])
def test_extra_topics_and_topic_choice(tmp_path: Path, storage: str) -> None:
    scans = make_scans(2, 10)
    other = make_scans(1, 3)[0][1]

    def other_cloud(typestore):
        return pointcloud2_from_structured(other, stamp_ns=T0, frame_id='map',
                                           msg_types=rosbags_types(typestore))

    path = write_bag(bag_path(tmp_path, storage), scans, storage=storage, topic='/lidar',
                     map_origin=ORIGIN,
                     extra=[('/chatter', 'std_msgs/msg/String', T0 + 1, string_msg('hi')),
                            ('/other', 'sensor_msgs/msg/PointCloud2', T0, other_cloud)])
    assert set(list_topics(path)) == {'/chatter', '/lidar', '/map_origin', '/other'}
    with pytest.raises(InputError, match='2 sensor_msgs/msg/PointCloud2 topics') as info:
        read_bag(path)
    assert '/lidar (sensor_msgs/msg/PointCloud2)' in str(info.value)
    assert '/other (sensor_msgs/msg/PointCloud2)' in str(info.value)
    bag = read_bag(path, topic='/lidar')
    assert [p.tobytes() for _, p in bag.scans] == [p.tobytes() for _, p in scans]
    assert bag.map_origin.tolist() == list(ORIGIN)
    assert read_bag(path, topic='/other').scans[0][1].tobytes() == other.tobytes()
    with pytest.raises(InputError, match="no sensor_msgs/msg/PointCloud2 topic '/chatter'"):
        read_bag(path, topic='/chatter')


def test_empty_scan_and_no_scans(tmp_path: Path) -> None:
    empty = np.zeros(0, DTYPE)
    bag = read_bag(write_bag(tmp_path / 'a', [(T0, empty)], storage='mcap'))
    assert len(bag.scans) == 1 and bag.scans[0][1].dtype == DTYPE and len(bag.scans[0][1]) == 0
    path = write_bag(tmp_path / 'b', [], storage='sqlite3', map_origin=ORIGIN)
    bag = read_bag(path)
    assert bag.scans == [] and bag.map_origin.tolist() == list(ORIGIN)
    with pytest.raises(InputError, match='no messages'):
        read_bag_cloud(path)


# --------------------------------------------------------------------------------------
# errors
# --------------------------------------------------------------------------------------


def test_missing_path(tmp_path: Path) -> None:
    with pytest.raises(InputError, match='bag not found: .*nope') as info:
        read_bag(tmp_path / 'nope')
    assert '\n' not in str(info.value)
    with pytest.raises(InputError, match='bag not found'):
        list_topics([tmp_path / 'nope.bag'])
    with pytest.raises(InputError, match='no bag path'):
        read_bag([])


def test_directory_without_bag(tmp_path: Path) -> None:
    (tmp_path / 'dir').mkdir()
    (tmp_path / 'dir' / 'notes.txt').write_text('no bag here')
    with pytest.raises(InputError, match='not a ROS 2 bag') as info:
        read_bag(tmp_path / 'dir')
    assert '\n' not in str(info.value)


@pytest.mark.parametrize('name', ['cloud.bag', 'cloud.db3', 'cloud.mcap', 'cloud.txt'])
def test_file_that_is_not_a_bag(tmp_path: Path, name: str) -> None:
    path = tmp_path / name
    path.write_bytes(b'this is not a bag\n' * 20)
    with pytest.raises(InputError, match='cannot read .* as a ROS 1 or ROS 2 bag') as info:
        read_bag(path)
    assert '\n' not in str(info.value)


def test_broken_metadata(tmp_path: Path) -> None:
    (tmp_path / 'b').mkdir()
    (tmp_path / 'b' / 'metadata.yaml').write_text('just: [a, list\n')
    with pytest.raises(InputError, match='cannot read'):
        read_bag(tmp_path / 'b')


@pytest.mark.parametrize('storage', ['sqlite3', 'rosbag1'])
def test_bag_without_pointcloud2_topic(tmp_path: Path, storage: str) -> None:
    from rosbags.typesys import Stores, get_typestore

    path = bag_path(tmp_path, storage, 'chat')
    if storage == 'rosbag1':
        from rosbags.rosbag1 import Writer as Writer1

        typestore = get_typestore(Stores.ROS1_NOETIC)
        writer, serialize = Writer1(path), typestore.serialize_ros1
    else:
        from rosbags.rosbag2 import Writer as Writer2

        typestore = get_typestore(Stores.ROS2_JAZZY)
        writer, serialize = Writer2(path, version=9), typestore.serialize_cdr
    with writer:
        conn = writer.add_connection('/chatter', 'std_msgs/msg/String', typestore=typestore)
        msg = typestore.types['std_msgs/msg/String'](data='hello')
        writer.write(conn, T0, serialize(msg, 'std_msgs/msg/String'))

    assert list_topics(path) == {'/chatter': 'std_msgs/msg/String'}
    with pytest.raises(InputError, match='no sensor_msgs/msg/PointCloud2 topics') as info:
        read_bag(path)
    assert '/chatter (std_msgs/msg/String)' in str(info.value)
    assert '\n' not in str(info.value)
    with pytest.raises(InputError, match='/chatter'):
        read_bag_cloud(path)


def test_write_bag_errors(tmp_path: Path) -> None:
    scans = make_scans(1, 2)
    with pytest.raises(InputError, match='unknown bag storage'):
        write_bag(tmp_path / 'x', scans, storage='zip')
    (tmp_path / 'exists').mkdir()
    with pytest.raises(InputError, match='exists already'):
        write_bag(tmp_path / 'exists', scans, storage='sqlite3')
    with pytest.raises(InputError, match='map origin'):
        write_bag(tmp_path / 'y', scans, storage='mcap', map_origin=(0.0, np.nan, 0.0))
    with pytest.raises(InputError, match='map origin'):
        write_bag(tmp_path / 'z', scans, storage='mcap', map_origin=(0.0, 1.0))
    with pytest.raises(InputError, match="unknown QoS profile 'durable'"):
        write_bag(tmp_path / 'q', scans, storage='mcap', extra_qos={'/chatter': 'durable'})
    assert not (tmp_path / 'q').exists()


@pytest.mark.parametrize('storage', ['sqlite3', 'mcap', 'rosbag1'])
def test_failed_write_leaves_nothing(tmp_path: Path, storage: str) -> None:
    good = make_scans(1, 2)[0]
    bad = (T0 + 1, np.zeros(2, [('x', 'f8'), ('flag', '?')]))
    path = bag_path(tmp_path, storage)
    with pytest.raises(InputError, match="field 'flag'"):
        write_bag(path, [good, bad], storage=storage)
    assert not path.exists()


def tf_msg(parent: str, child: str, x: float):
    """A tf2_msgs/msg/TFMessage of one transform, from a ROS 1 or ROS 2 typestore."""
    def make(typestore):
        t = typestore.types
        header = rosbags_types(typestore).Header(stamp=t['builtin_interfaces/msg/Time'](sec=1, nanosec=2),
                                                 frame_id=parent)
        transform = t['geometry_msgs/msg/Transform'](translation=t['geometry_msgs/msg/Vector3'](x, 0.0, 0.0),
                                                     rotation=t['geometry_msgs/msg/Quaternion'](0.0, 0.0, 0.0, 1.0))
        one = t['geometry_msgs/msg/TransformStamped'](header=header, child_frame_id=child, transform=transform)
        return t['tf2_msgs/msg/TFMessage'](transforms=[one])
    return make


@pytest.mark.parametrize('storage', ['sqlite3', 'mcap', 'rosbag1'])
def test_clouds_in_their_own_frames_and_the_qos_of_extra_topics(tmp_path: Path, storage: str) -> None:
    from rosbags.highlevel import AnyReader
    from rosbags.interfaces import QosDurability, QosReliability

    (s0, p0), (s1, p1), (s2, p2) = make_scans(3, 4)
    path = write_bag(bag_path(tmp_path, storage), [(s0, p0, 'up_lidar'), (s1, p1), (s2, p2, 'down_lidar')],
                     storage=storage, frame_id='world', map_origin=ORIGIN,
                     extra=[('/tf_static', 'tf2_msgs/msg/TFMessage', T0, tf_msg('base', 'up_lidar', 1.5)),
                            ('/tf', 'tf2_msgs/msg/TFMessage', T0 + 5, tf_msg('world', 'base', -2.0)),
                            ('/chatter', 'std_msgs/msg/String', T0 + 1, string_msg('hi')),
                            ('/cloud2', 'std_msgs/msg/String', T0 + 2, string_msg('x'))],
                     extra_qos={'/tf_static': 'latched', '/tf': 'reliable', '/cloud2': 'sensor'})
    with AnyReader([path]) as reader:
        conns = {c.topic: c for c in reader.connections}
        frames = [reader.deserialize(raw, c.msgtype).header.frame_id
                  for c, _t, raw in reader.messages(connections=[conns['/points']])]
        tf = {c.topic: reader.deserialize(raw, c.msgtype).transforms[0]
              for c, _t, raw in reader.messages(connections=[conns['/tf'], conns['/tf_static']])}
    assert frames == ['up_lidar', 'world', 'down_lidar']  # the pairs keep frame_id
    assert (tf['/tf_static'].header.frame_id, tf['/tf_static'].child_frame_id) == ('base', 'up_lidar')
    assert tf['/tf_static'].transform.translation.x == 1.5 and tf['/tf'].transform.translation.x == -2.0
    assert read_bag(path).map_origin.tolist() == list(ORIGIN)
    if storage == 'rosbag1':
        assert {t: c.ext.latching for t, c in conns.items()} == {
            '/points': None, '/map_origin': 1, '/tf_static': 1, '/tf': None, '/chatter': None, '/cloud2': None}
        assert conns['/tf'].digest == '94810edda583a504dfda3829e70d7eec'  # tf2_msgs/TFMessage of ROS 1
        return
    profiles = {t: [(q.reliability, q.durability, q.depth) for q in c.ext.offered_qos_profiles]
                for t, c in conns.items()}
    assert profiles == {
        '/points': [(QosReliability.BEST_EFFORT, QosDurability.VOLATILE, 5)],
        '/map_origin': [(QosReliability.RELIABLE, QosDurability.TRANSIENT_LOCAL, 1)],
        '/tf_static': [(QosReliability.RELIABLE, QosDurability.TRANSIENT_LOCAL, 1)],
        '/tf': [(QosReliability.RELIABLE, QosDurability.VOLATILE, 10)],
        '/chatter': [],
        '/cloud2': [(QosReliability.BEST_EFFORT, QosDurability.VOLATILE, 5)],
    }
