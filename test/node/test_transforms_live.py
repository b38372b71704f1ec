"""Clouds in a moving sensor frame, as robots publish them: the node waits for their poses.

A node in its own process is fed 10 Hz clouds of the small scene in a lidar frame that
moves (a straight drive with a constant yaw rate) with their poses as robots send them: on
``sensor_pose`` 5 ms before each cloud, on ``sensor_pose`` 20 ms after it, and only on
``/tf`` (map -> base_link at 20 Hz, out of step with the clouds, so each cloud's pose is
interpolated) with ``/tf_static`` (base_link -> lidar, transient local), and on odometry
(``node.odometry_topic``). No cloud may be rejected for its transform (issue 25), and the map
of the /tf run must equal, bit for bit, offline replay's of the same clouds and transforms.
Clouds whose transform never comes are rejected naming the frames, the oldest first when
more than ``node.transform_queue`` wait.
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
pytest.importorskip('tf2_msgs.msg')

from support import assert_same_maps  # noqa: E402
from test_node import Client, NodeProcess, diagnostics, node_config  # noqa: E402

import msg_adapters as ma  # noqa: E402
from msg_adapters import transforms as mt  # noqa: E402
from uncertain_facade_map.io.map_file import save_map  # noqa: E402
from uncertain_facade_map.io.parameter_file import load_config  # noqa: E402
from uncertain_facade_map.mapping.facade_map import FacadeMap  # noqa: E402
from uncertain_facade_map.mapping.worker import map_scans  # noqa: E402
from uncertain_facade_map.params import map_params  # noqa: E402
from uncertain_facade_map.simulation.export import split_scans  # noqa: E402
from uncertain_facade_map.transforms import TransformBuffer, rotations  # noqa: E402

#: Clouds published per run (3 s at 10 Hz).
CLOUDS = 30
#: The lidar on the vehicle: base_link -> velodyne (the /tf run's cloud frame; the sensor_pose
#: runs give their clouds' frame "lidar" its pose in the map frame directly, and a frame has
#: one parent).
MOUNT = mt.StampedTransform('base_link', 'velodyne', 0, np.array([0.6, 0.1, 1.8]),
                            np.array([0.0, 0.0, np.sin(np.radians(5.0)), np.cos(np.radians(5.0))]))


def vehicle(stamp_ns: int, t0: int) -> mt.StampedTransform:
    """map -> base_link at a time: 4 m/s along x and 0.05 rad/s of yaw (linear in time, so that
    interpolating between any two samples gives the pose exactly)."""
    s = (stamp_ns - t0) / 1e9
    yaw = 0.05 * s
    return mt.StampedTransform('map', 'base_link', stamp_ns, np.array([2.0 + 4.0 * s, 1.0, 0.0]),
                               np.array([0.0, 0.0, np.sin(yaw / 2), np.cos(yaw / 2)]))


def lidar_pose(stamp_ns: int, t0: int) -> tuple[np.ndarray, np.ndarray]:
    """Rotation (3, 3) and translation (3,) of the lidar (MOUNT) in the map frame at a time."""
    v = vehicle(stamp_ns, t0)
    r_v, r_m = rotations.to_matrix(v.rotation), rotations.to_matrix(MOUNT.rotation)
    return r_v @ r_m, r_v @ MOUNT.translation + v.translation


@pytest.fixture(scope='module')
def drive(scenes):
    """The small scene's first CLOUDS scans, classified, without sensor origins and times, in
    the moving lidar frame: [(stamp_ns, map-frame points, lidar-frame points)]."""
    cloud = scenes.campaign('small', 0)
    keep = [n for n in cloud.points.dtype.names if n not in ('origin_x', 'origin_y', 'origin_z', 'time')]
    out = []
    scans = list(split_scans(cloud, 0.1))[:CLOUDS]
    t0 = scans[0][0]
    for stamp, part in scans:
        points = np.ascontiguousarray(part[keep])
        xyz = np.stack([points[c] for c in 'xyz'], 1).astype(np.float64)
        r, t = lidar_pose(stamp, t0)
        local = points.copy()
        local['x'], local['y'], local['z'] = ((xyz - t) @ r).T  # R^T (p - t)
        out.append((stamp, points, local))
    return out


@pytest.fixture(scope='module')
def running(tmp_path_factory, drive):
    domain = 100 + (os.getpid() + 37) % 100
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST')
    work = tmp_path_factory.mktemp('transforms_live')
    params = node_config(work, **{'update.batch_points': 3000, 'node.idle_flush': 2.0, 'node.odometry_topic': '/odom'})
    client = Client(domain)
    node = NodeProcess(params, env, work / 'node.log')
    try:
        node.wait_ready(client)
        yield client, node, work, params
    finally:
        node.stop()
        client.close()
        print((work / 'node.log').read_text()[-3000:])


def _run(client: Client, drive, publish_pose, frame: str, settle: float = 0.0) -> dict:
    """Reset the map, publish the clouds at 10 Hz in the lidar frame with ``publish_pose(k, stamp)``
    called around each, and wait until the node has placed them all."""
    from std_srvs.srv import Trigger

    assert client.call(Trigger, 'reset', Trigger.Request()).success
    start = diagnostics(client)
    types = ma.rclpy_types()
    began = time.monotonic()
    for k, (stamp, _points, local) in enumerate(drive):
        due = began + 0.1 * k
        time.sleep(max(0.0, due - time.monotonic()))
        publish_pose(k, stamp, 'before')
        client.pub.publish(ma.pointcloud2_from_structured(local, stamp_ns=stamp, frame_id=frame, msg_types=types))
        publish_pose(k, stamp, 'after')
    time.sleep(settle)
    values = diagnostics(client, until=lambda v: int(v['clouds_received']) >= int(start['clouds_received']) + CLOUDS
                         and int(v['clouds_waiting']) == 0 and v['settled'] == 'True', timeout=120)
    return {key: int(values[key]) - int(start[key]) for key in
            ('clouds_received', 'clouds_mapped', 'clouds_rejected', 'clouds_no_transform', 'poses_rejected')}


def publish_static(client: Client, types, transform: mt.StampedTransform) -> None:
    """A static transform on /tf_static, latched as tf2's static broadcaster publishes it."""
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

    latched = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL, reliability=ReliabilityPolicy.RELIABLE)
    client.node.create_publisher(types.TFMessage, '/tf_static', latched).publish(mt.tf_message([transform], types))


def _assert_all_placed(delta: dict) -> None:
    assert delta['clouds_received'] == CLOUDS
    assert delta['clouds_no_transform'] == 0 and delta['clouds_rejected'] == 0, delta
    assert delta['clouds_mapped'] == CLOUDS and delta['poses_rejected'] == 0, delta


@pytest.mark.parametrize('when, delay', [('before', 0.005), ('after', 0.020)])
def test_poses_shortly_before_or_after_their_clouds_reject_none(running, drive, when, delay):
    """sensor_pose (map -> lidar at each cloud's stamp) published 5 ms before or 20 ms after it."""
    client, _node, _work, _params = running
    types = mt.transform_types_rclpy()
    t0 = drive[0][0]

    def publish(k, stamp, moment):
        if moment != when:
            return
        if when == 'after':
            time.sleep(delay)  # the cloud went out first
        r, t = lidar_pose(stamp, t0)
        pose = mt.StampedTransform('map', 'lidar', stamp, t, rotations.from_matrix(r))
        client.pose_pub.publish(mt.transform_stamped_msg(pose, types))
        if when == 'before':
            time.sleep(delay)  # the cloud follows

    _assert_all_placed(_run(client, drive, publish, 'lidar'))


def test_poses_only_on_tf_reject_none_and_map_as_offline_replay(running, drive):
    """/tf (map -> base_link at 20 Hz, 25 ms out of step) and /tf_static (base_link -> lidar):
    every cloud interpolated, and the node's map equals offline replay's bit for bit."""
    from uncertain_facade_map.srv import SaveMap

    client, _node, work, params = running
    types = mt.transform_types_rclpy()
    t0 = drive[0][0]
    tf_pub = client.node.create_publisher(types.TFMessage, '/tf', 100)
    publish_static(client, types, MOUNT)
    sent: list[mt.StampedTransform] = []

    def publish(k, stamp, moment):
        if moment != 'after':
            return
        # Two vehicle poses per cloud period, 25 ms and 75 ms after the cloud's stamp, sent
        # 25 ms after the cloud (the first cloud's pose thus comes after it).
        if k == 0:
            first = vehicle(stamp - 25_000_000, t0)
            tf_pub.publish(mt.tf_message([first], types))
            sent.append(first)
        time.sleep(0.025)
        for offset in (25_000_000, 75_000_000):
            v = vehicle(stamp + offset, t0)
            tf_pub.publish(mt.tf_message([v], types))
            sent.append(v)

    delta = _run(client, drive, publish, 'velodyne')
    _assert_all_placed(delta)
    saved = client.call(SaveMap, 'save_map', SaveMap.Request(path=str(work / 'node_tf.npz')))
    assert saved.success, saved.message
    # Offline replay of the same clouds with the same transforms (map_scans, as `replay` does).
    config = load_config(params)
    buffer = TransformBuffer(cache_time=np.inf)
    buffer.set_transform('base_link', 'velodyne', 0, MOUNT.translation, MOUNT.rotation, static=True)
    buffer.set_transforms(**mt.transform_arrays(sent))
    fmap = FacadeMap(map_params(config), np.zeros(3))
    summary = map_scans(fmap, [(stamp, local, 'velodyne') for stamp, _p, local in drive], config.input, None,
                        config.selection, buffer=buffer, tolerance=config.node.pose_tolerance,
                        max_coordinate=config.node.max_coordinate)
    assert summary.rejected == 0 and not summary.notes
    assert_same_maps(work / 'node_tf.npz', save_map(fmap, Path(work) / 'offline_tf.npz'))
    # And the points are where they were: the same drive given in the map frame, with the
    # lidar's position as each point's sensor origin, maps to the same façades.
    direct = FacadeMap(map_params(config), np.zeros(3))
    map_scans(direct, [with_origin(points, lidar_pose(stamp, t0)[1]) for stamp, points, _l in drive], config.input)
    assert len(direct.facades) == len(fmap.facades) >= 2
    for a, b in zip(direct.facades, fmap.facades):
        np.testing.assert_allclose(a.frame.normal, b.frame.normal, atol=1e-9)
        np.testing.assert_allclose(a.surface.mean, b.surface.mean, atol=1e-6)


def with_origin(points: np.ndarray, origin: np.ndarray) -> np.ndarray:
    """The points with origin_x/y/z fields set to one sensor position."""
    from numpy.lib import recfunctions

    out = recfunctions.append_fields(points, ['origin_x', 'origin_y', 'origin_z'],
                                     [np.full(len(points), v) for v in origin], usemask=False)
    return np.ascontiguousarray(out)


def test_poses_on_odometry_reject_none(running, drive):
    """nav_msgs/Odometry on node.odometry_topic (map -> base_odom at 20 Hz) with /tf_static."""
    client, _node, _work, _params = running
    types = mt.transform_types_rclpy()
    t0 = drive[0][0]
    odom = client.node.create_publisher(types.Odometry, '/odom', 100)
    publish_static(client, types, mt.StampedTransform('base_odom', 'velodyne_odom', 0, MOUNT.translation,
                                                      MOUNT.rotation))

    def publish(k, stamp, moment):
        if moment != 'after':
            return
        for offset in ((-25_000_000, 25_000_000, 75_000_000) if k == 0 else (25_000_000, 75_000_000)):
            v = vehicle(stamp + offset, t0)
            odom.publish(mt.odometry_msg(mt.StampedTransform('map', 'base_odom', v.stamp_ns, v.translation,
                                                             v.rotation), types))

    _assert_all_placed(_run(client, drive, publish, 'velodyne_odom'))


def test_clouds_whose_transform_never_comes_are_rejected_naming_the_frames(running, drive):
    """25 clouds in a frame nobody publishes: node.transform_queue (20) wait, the 5 oldest are given
    up at once, the others after node.transform_timeout; each one counted and named."""
    client, node, _work, _params = running
    start = diagnostics(client)
    types = ma.rclpy_types()
    for stamp, _points, local in drive[:25]:
        client.pub.publish(ma.pointcloud2_from_structured(local, stamp_ns=stamp, frame_id='nowhere', msg_types=types))
    values = diagnostics(client, until=lambda v: int(v['clouds_no_transform']) >= int(start['clouds_no_transform'])
                         + 25, timeout=60)
    assert int(values['clouds_rejected']) - int(start['clouds_rejected']) == 25
    assert int(values['clouds_waiting']) == 0
    log = node.log.read_text()
    assert 'no transform from "nowhere" into the map frame "map"' in log and 'node.transform_queue = 20' in log
