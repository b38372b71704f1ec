"""The Argoverse 2 bag "as the vehicle recorded it" (uncertain_facade_map_apps.av2_bag) on the real log.

Needs ../shared/data/real/raw/av2_7fab beside the repository (skips without it). Checks:
the reference clouds (io.av2.reference_clouds) equal the real-data folder's PLY files
(convert.py's own path, scipy rotations, float16 -> float64 points) within float32 rounding;
each bag, for every --poses mode and storage, read back with rosbags has the topics, types,
frames, counts and QoS it should; the transforms in the bag, applied by hand (scipy), take
the bag's lidar-frame points onto the reference within 1e-6 m.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[2]
REAL = REPO.parent / 'shared' / 'data' / 'real'
RAW = REAL / 'raw' / 'av2_7fab'

pytestmark = pytest.mark.skipif(not RAW.is_dir(), reason=f'no Argoverse 2 raw log at {RAW}')

STORAGES = ('mcap', 'sqlite3', 'rosbag1')
POSES = ('tf', 'pose', 'odometry')
LIDARS = ('up_lidar', 'down_lidar')
#: The log's facts: two sweeps, their points per lidar, the map origin convert.py chose.
SWEEPS = [315966265259836000, 315966265360032000]
POINTS = {SWEEPS[0]: {'up_lidar': 51785, 'down_lidar': 47444}, SWEEPS[1]: {'up_lidar': 51807, 'down_lidar': 47659}}
MAP_ORIGIN = [5224.0, 2385.0, 69.0]
#: Ego poses from 0.2 s before the first sweep to 0.2 s after the last.
EGO_POSES = 86


@pytest.fixture(scope='module')
def log():
    from uncertain_facade_map.io.av2 import read_av2_log

    return read_av2_log(RAW)


@pytest.fixture(scope='module')
def reference(log):
    from uncertain_facade_map.io.av2 import reference_clouds

    return dict(reference_clouds(log))


def xyz(points: np.ndarray, prefix: str = '') -> np.ndarray:
    return np.stack([points[prefix + c].astype(np.float64) for c in 'xyz'], axis=1)


def test_the_log(log):
    assert [s.stamp_ns for s in log.sweeps] == SWEEPS
    assert {'up_lidar', 'down_lidar'} <= set(log.extrinsics)
    # The ego poses include the sweep stamps exactly: convert.py's nearest pose is the pose at the stamp.
    assert set(SWEEPS) <= set(log.poses.stamps_ns.tolist())
    assert len(log.poses.stamps_ns) == 2706
    from uncertain_facade_map.io.av2 import map_origin_of

    assert map_origin_of(log).tolist() == MAP_ORIGIN


def test_reference_equals_the_ply_files_within_float32_rounding(log, reference):
    from plyfile import PlyData

    from uncertain_facade_map.io.av2 import lidar_clouds

    worst = []
    for k, sweep in enumerate(log.sweeps):
        ply = PlyData.read(str(REAL / f'av2_7fab_sweep{k}.ply'))
        assert ply.comments == ['map_origin ' + ' '.join(repr(v) for v in MAP_ORIGIN)]
        # The reference has the up lidar's points, then the down lidar's, each in sweep order.
        order = np.concatenate([np.flatnonzero(sweep.laser_number < 32), np.flatnonzero(sweep.laser_number >= 32)])
        truth = ply['vertex'].data[order]
        ours = reference[sweep.stamp_ns]
        assert len(ours) == len(truth) == sum(POINTS[sweep.stamp_ns].values())
        # float32 rounding of the lidar-frame coordinates: at most half a float32 step of each
        # (2**-24 relative) per coordinate, mixed by the rotations: bounded by eps * range.
        local = np.concatenate([xyz(p) for p in lidar_clouds(log, sweep).values()])
        error = np.linalg.norm(xyz(ours) - xyz(truth), axis=1)
        assert (error <= np.finfo(np.float32).eps * np.linalg.norm(local, axis=1) + 1e-9).all()
        worst.append(error.max())
        up = np.arange(len(ours)) < (sweep.laser_number < 32).sum()
        assert np.array_equal(ours['ring'] + np.where(up, 0, 32), truth['ring'])
        assert np.array_equal(ours['intensity'], truth['intensity'])
        # The sensor origins: each lidar's position at the sweep stamp; the PLY's are at each
        # point's firing time (the car moves some centimetres within a 0.1 s sweep).
        gap = np.linalg.norm(xyz(ours, 'origin_') - xyz(truth, 'origin_'), axis=1)
        assert gap.max() < 0.1
        for lidar in (up, ~up):
            assert len(np.unique(xyz(ours[lidar], 'origin_'), axis=0)) == 1
    print(f'reference vs PLY: max {max(worst):.2e} m')
    # float32 steps are 1.5e-5 m at 128-256 m (the farthest points, 215 m): half a step on each of
    # three coordinates is at most 1.3e-5 m.
    assert 1e-6 < max(worst) < 1.3e-5


def read_bag(path: Path) -> dict:
    """Every message of a bag, decoded, by topic; and each topic's connection."""
    from rosbags.highlevel import AnyReader

    out: dict = {'messages': {}, 'connections': {}}
    with AnyReader([path]) as reader:
        for conn in reader.connections:
            out['connections'][conn.topic] = conn
        for conn, time_ns, raw in reader.messages():
            out['messages'].setdefault(conn.topic, []).append((time_ns, reader.deserialize(raw, conn.msgtype), raw))
    return out


def stamp(msg) -> int:
    return int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec)


def matrix(translation, rotation) -> np.ndarray:
    """4x4 pose from a geometry_msgs Vector3/Point and Quaternion, by scipy."""
    from scipy.spatial.transform import Rotation

    out = np.eye(4)
    out[:3, :3] = Rotation.from_quat([rotation.x, rotation.y, rotation.z, rotation.w]).as_matrix()
    out[:3, 3] = [translation.x, translation.y, translation.z]
    return out


@pytest.fixture(scope='module')
def bags(tmp_path_factory):
    from uncertain_facade_map_apps.av2_bag import write_av2_bag

    out = {}
    folder = tmp_path_factory.mktemp('av2')
    for poses in POSES:
        for storage in STORAGES:
            path = folder / (f'{poses}_{storage}' + ('.bag' if storage == 'rosbag1' else ''))
            summary = write_av2_bag(RAW, path, storage=storage, poses=poses)
            out[poses, storage] = (summary, read_bag(path))
    return out


@pytest.mark.parametrize('storage', STORAGES)
@pytest.mark.parametrize('poses', POSES)
def test_bag_layout(bags, poses, storage):
    summary, bag = bags[poses, storage]
    expected = {'/points': 'sensor_msgs/msg/PointCloud2', '/map_origin': 'geometry_msgs/msg/PointStamped'}
    expected.update({'tf': {'/tf': 'tf2_msgs/msg/TFMessage', '/tf_static': 'tf2_msgs/msg/TFMessage'},
                     'pose': {'/sensor_pose': 'geometry_msgs/msg/TransformStamped'},
                     'odometry': {'/odom': 'nav_msgs/msg/Odometry', '/tf_static': 'tf2_msgs/msg/TFMessage'}}[poses])
    assert {t: c.msgtype for t, c in bag['connections'].items()} == expected
    counts = {t: len(m) for t, m in bag['messages'].items()}
    assert counts == summary['topics']
    assert counts['/points'] == 4 and counts['/map_origin'] == 1
    assert counts.get('/tf', EGO_POSES) == counts.get('/odom', EGO_POSES) == EGO_POSES
    assert counts.get('/sensor_pose', 4) == 4 and counts.get('/tf_static', 1) == 1

    clouds = [msg for _t, msg, _r in bag['messages']['/points']]
    assert [(stamp(m), m.header.frame_id, m.width) for m in clouds] == [
        (s, lidar, POINTS[s][lidar]) for s in SWEEPS for lidar in LIDARS]
    for msg in clouds:
        assert [(f.name, f.datatype) for f in msg.fields] == [('x', 7), ('y', 7), ('z', 7), ('intensity', 7),
                                                              ('ring', 4)]
    assert [t for t, _m, _r in bag['messages']['/points']] == [stamp(m) for m in clouds]
    origin = bag['messages']['/map_origin'][0][1]
    assert [origin.point.x, origin.point.y, origin.point.z] == MAP_ORIGIN and origin.header.frame_id == 'map'

    for topic in ('/tf', '/odom'):
        for time_ns, msg, _raw in bag['messages'].get(topic, []):
            one = msg.transforms[0] if topic == '/tf' else msg
            assert (one.header.frame_id, one.child_frame_id) == ('map', 'egovehicle')
            assert stamp(one) == time_ns
            assert SWEEPS[0] - 200_000_000 <= time_ns <= SWEEPS[-1] + 200_000_000
    if '/tf_static' in bag['connections']:
        (time_ns, msg, _raw), = bag['messages']['/tf_static']
        assert [(t.header.frame_id, t.child_frame_id) for t in msg.transforms] == [
            ('egovehicle', 'up_lidar'), ('egovehicle', 'down_lidar')]
        first = min(t for m in bag['messages'].values() for t, _m, _r in m)
        assert time_ns == first  # before anything that needs it
        conn = bag['connections']['/tf_static']
        if storage == 'rosbag1':
            assert conn.ext.latching == 1 and conn.digest == '94810edda583a504dfda3829e70d7eec'
        else:
            from rosbags.interfaces import QosDurability, QosReliability

            (qos,) = conn.ext.offered_qos_profiles
            assert (qos.durability, qos.reliability, qos.depth) == (QosDurability.TRANSIENT_LOCAL,
                                                                    QosReliability.RELIABLE, 1)
            assert conn.digest == 'RIHS01_e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087'
    for time_ns, msg, _raw in bag['messages'].get('/sensor_pose', []):
        assert msg.header.frame_id == 'map' and msg.child_frame_id in LIDARS and stamp(msg) == time_ns in SWEEPS


@pytest.mark.parametrize('storage', STORAGES)
@pytest.mark.parametrize('poses', POSES)
def test_the_bags_transforms_give_the_reference(bags, reference, poses, storage):
    _summary, bag = bags[poses, storage]
    messages = bag['messages']
    static = {}
    for _t, msg, _r in messages.get('/tf_static', []):
        static.update({t.child_frame_id: matrix(t.transform.translation, t.transform.rotation)
                       for t in msg.transforms})
    from msg_adapters.pointcloud2 import structured_from_pointcloud2

    got: dict[int, list[np.ndarray]] = {}
    origins: dict[int, list[np.ndarray]] = {}
    for _t, cloud, _r in messages['/points']:
        when, frame = stamp(cloud), cloud.header.frame_id
        if poses == 'pose':
            (pose,) = [m for _t, m, _r in messages['/sensor_pose'] if stamp(m) == when and m.child_frame_id == frame]
            map_lidar = matrix(pose.transform.translation, pose.transform.rotation)
        else:
            # The ego pose at the cloud's stamp: the log has one at each sweep stamp exactly.
            if poses == 'tf':
                (ego,) = [m.transforms[0].transform for _t, m, _r in messages['/tf']
                          if stamp(m.transforms[0]) == when]
                map_ego = matrix(ego.translation, ego.rotation)
            else:
                (odom,) = [m.pose.pose for _t, m, _r in messages['/odom'] if stamp(m) == when]
                map_ego = matrix(odom.position, odom.orientation)
            map_lidar = map_ego @ static[frame]
        points = structured_from_pointcloud2(cloud)
        got.setdefault(when, []).append(xyz(points) @ map_lidar[:3, :3].T + map_lidar[:3, 3])
        origins.setdefault(when, []).append(np.broadcast_to(map_lidar[:3, 3], (len(points), 3)))
    assert sorted(got) == SWEEPS
    for when, parts in got.items():
        want = reference[when]
        assert np.abs(np.concatenate(parts) - xyz(want)).max() < 1e-6
        assert np.abs(np.concatenate(origins[when]) - xyz(want, 'origin_')).max() < 1e-6


@pytest.mark.ros
def test_rclpy_decodes_the_bags_tf_messages(bags):
    """The recorded /tf and /odom bytes are what a Jazzy subscriber takes (our generated tf2_msgs)."""
    pytest.importorskip('tf2_msgs.msg')
    from nav_msgs.msg import Odometry
    from rclpy.serialization import deserialize_message
    from tf2_msgs.msg import TFMessage

    messages = bags['tf', 'mcap'][1]['messages']
    for _t, msg, raw in messages['/tf'] + messages['/tf_static']:
        decoded = deserialize_message(bytes(raw), TFMessage)
        assert [(t.child_frame_id, t.transform.translation.x) for t in decoded.transforms] == [
            (t.child_frame_id, t.transform.translation.x) for t in msg.transforms]
    for _t, msg, raw in bags['odometry', 'sqlite3'][1]['messages']['/odom'][:5]:
        assert deserialize_message(bytes(raw), Odometry).pose.pose.position.x == msg.pose.pose.position.x


def test_reference_outputs_and_the_command(tmp_path, log, reference, capsys):
    from msg_adapters.bag_io import read_bag as read_clouds
    from uncertain_facade_map.io.npz import read_npz
    from uncertain_facade_map_apps.av2_bag import main

    out = tmp_path / 'car.bag'
    assert main([str(RAW), str(out), '--storage', 'rosbag1', '--poses', 'tf', '--map-frame', 'world',
                 '--reference', str(tmp_path / 'reference.npz')]) == 0
    printed = capsys.readouterr().out
    assert 'wrote' in printed and '/tf: 86' in printed and '/points: 4' in printed
    bag = read_bag(out)
    assert {m.transforms[0].header.frame_id for _t, m, _r in bag['messages']['/tf']} == {'world'}
    cloud = read_npz(tmp_path / 'reference.npz')
    assert cloud.map_origin.tolist() == MAP_ORIGIN
    assert cloud.points.tobytes() == np.concatenate([reference[s] for s in SWEEPS]).tobytes()

    from uncertain_facade_map_apps.av2_bag import write_reference

    clouds = read_clouds(write_reference(log, tmp_path / 'reference_mcap', storage='mcap'))
    assert clouds.map_origin.tolist() == MAP_ORIGIN
    assert [(s, p.tobytes()) for s, p in clouds.scans] == [(s, reference[s].tobytes()) for s in SWEEPS]

    # A log without calibration/ (some public sample logs): the documented lidar layout, a
    # warning, and the same points (the sweeps are in the ego frame; the lidar frames' float32
    # rounding aside, only the sensor origins move, by 4.1 cm at most on this car).
    bare = tmp_path / 'bare'
    bare.mkdir()
    (bare / 'sensors').symlink_to(RAW / 'sensors')
    (bare / 'city_SE3_egovehicle.feather').symlink_to(RAW / 'city_SE3_egovehicle.feather')
    assert main([str(bare), str(tmp_path / 'bare_bag'), '--reference', str(tmp_path / 'bare.npz')]) == 0
    err = capsys.readouterr().err
    assert err.count('\n') == 1 and 'warning:' in err and 'no calibration/ folder' in err
    bare_cloud = read_npz(tmp_path / 'bare.npz')
    np.testing.assert_allclose(xyz(bare_cloud.points), xyz(cloud.points), rtol=0, atol=5e-5)
    assert np.abs(xyz(bare_cloud.points, 'origin_') - xyz(cloud.points, 'origin_')).max() < 0.05

    # Errors a user can make: one line, exit status 2.
    assert main([str(RAW), str(out), '--storage', 'rosbag1']) == 2
    assert 'exists already' in capsys.readouterr().err
    assert main([str(tmp_path / 'nowhere'), str(tmp_path / 'x')]) == 2
    err = capsys.readouterr().err
    assert err.count('\n') == 1 and 'not a folder' in err
