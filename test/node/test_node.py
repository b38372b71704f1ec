"""The facade_mapper node in its own process, driven by this process as a localisation node.

This process publishes a simulated street as scans (PointCloud2, as the simulator's bags
hold them), calls every service and compares the answers with the offline core on the
same points; it checks a late subscriber gets the published maps, that bad input is
refused without losing the map, and that a killed node restarted on its saved map answers
the same queries.
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

pytestmark = pytest.mark.ros

rclpy = pytest.importorskip('rclpy')
pytest.importorskip('uncertain_facade_map.srv')

import msg_adapters as ma  # noqa: E402
from uncertain_facade_map.io.map_file import load_map, save_map  # noqa: E402
from uncertain_facade_map.io.parameter_file import dump_config  # noqa: E402
from uncertain_facade_map.mapping.facade_map import FacadeMap  # noqa: E402
from uncertain_facade_map.mapping.worker import map_scans  # noqa: E402
from uncertain_facade_map.params import (  # noqa: E402
    Config,
    InputConfig,
    QueryConfig,
    map_params,  # noqa: E402  # FIXME
)
from uncertain_facade_map.pipeline.step7_queries import query_points  # noqa: E402
from uncertain_facade_map.simulation.export import split_scans  # noqa: E402
from uncertain_facade_map_apps.ros_client import SpinningClient, answers_of, query_request  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
#: Seconds of the street drive published (the whole drive takes minutes to map incrementally).
DRIVE_SECONDS = 4.0


def scenario_config(**overrides) -> Config:
    """The defaults, with updates of 20 000 points (several in the drive's first seconds,
    so that the node maps block by block before it flushes), plus ``section.name`` overrides."""
    import dataclasses

    config = Config()
    sections = {'update': {'batch_points': 20000}}
    for key, value in overrides.items():
        section, name = key.split('.')
        sections.setdefault(section, {})[name] = value
    for section, values in sections.items():
        config = dataclasses.replace(config, **{section: dataclasses.replace(getattr(config, section), **values)})
    return config


def node_config(tmp: Path, **overrides) -> Path:
    """A parameter file: :func:`scenario_config` with reliable input and a big queue (nothing
    dropped), plus overrides."""
    # A long idle time: a loaded machine (CI) must not pause the stream long enough for a
    # flush in the middle, which would make another map than the offline core's; fixed
    # batches: the map depends on the clouds only, not on when they came (node.batching).
    node = {'node.qos': 'reliable', 'node.queue_size': 10000, 'node.idle_flush': 5.0, 'node.batching': 'fixed',
            'persistence.map_dir': str(tmp)}  # save_map and load_map are confined to it
    path = tmp / f'params_{len(list(tmp.glob("params_*")))}.yaml'
    path.write_text(dump_config(scenario_config(**{**node, **overrides})))
    return path


class NodeProcess:
    """The node, started as `python -m uncertain_facade_map_node.node --ros-args --params-file P`."""

    def __init__(self, params: Path, env: dict, log: Path) -> None:
        self.log = log
        self.proc = subprocess.Popen([sys.executable, '-m', 'uncertain_facade_map_node.node', '--ros-args',
                                      '--params-file', str(params)], env=env, cwd=ROOT,
                                     stdout=open(log, 'ab'), stderr=subprocess.STDOUT)

    def wait_ready(self, client: Client, timeout: float = 60.0) -> None:
        """Wait until the node is up and this client sees its diagnostics (discovery done)."""
        deadline = time.monotonic() + timeout
        while 'façades' not in self.log.read_text():
            assert self.alive() and time.monotonic() < deadline, self.log.read_text()
            time.sleep(0.2)
        client.forget_clients()
        client.wait_for_subscriber()
        diagnostics(client, timeout=timeout)
        time.sleep(0.5)

    def alive(self) -> bool:
        return self.proc.poll() is None

    def kill(self) -> None:
        self.proc.send_signal(signal.SIGKILL)
        self.proc.wait(10)

    def stop(self) -> None:
        if self.alive():
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(15)
            except subprocess.TimeoutExpired:
                self.kill()


class Client(SpinningClient):
    """A localisation node: publishes scans, subscribes to the maps, calls the services."""

    def __init__(self, domain: int) -> None:
        from geometry_msgs.msg import TransformStamped
        from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import PointCloud2

        super().__init__('localisation_client', domain)
        reliable = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
        self.pub = self.node.create_publisher(PointCloud2, 'points', reliable)
        self.pose_pub = self.node.create_publisher(TransformStamped, 'sensor_pose', 100)
        self.latched = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL,
                                  reliability=ReliabilityPolicy.RELIABLE)
        self.clients = {}
        self._start()

    def call(self, srv_type, name, request, timeout=120.0):
        if name not in self.clients:
            self.clients[name] = self.on_spin_thread(lambda: self.node.create_client(srv_type, name))
        client = self.clients[name]
        assert client.wait_for_service(timeout_sec=30.0), f'service {name} not available'
        future = client.call_async(request)
        done = threading.Event()
        future.add_done_callback(lambda _: done.set())
        assert done.wait(timeout), f'service {name} did not answer in {timeout} s'
        return future.result()

    def forget_clients(self):
        """Drop the service clients (after the node was restarted)."""
        clients, self.clients = list(self.clients.values()), {}
        self.on_spin_thread(lambda: [self.node.destroy_client(c) for c in clients])

    def call_retrying(self, srv_type, name, request, attempts=6, timeout=10.0):
        """Call until answered: a killed server may still be known to discovery for a while."""
        for attempt in range(attempts):
            try:
                return self.call(srv_type, name, request, timeout)
            except AssertionError:
                if attempt == attempts - 1:
                    raise
                self.forget_clients()

    def wait_for_message(self, msg_type, topic, timeout=30.0, qos=None):
        got = []
        event = threading.Event()

        def callback(msg):
            got.append(msg)
            event.set()

        sub = self.on_spin_thread(lambda: self.node.create_subscription(msg_type, topic, callback,
                                                                        qos or self.latched))
        try:
            assert event.wait(timeout), f'no message on {topic} within {timeout} s'
        finally:
            self.on_spin_thread(lambda: self.node.destroy_subscription(sub))
        return got[0]

    def wait_for_subscriber(self, timeout=30.0):
        deadline = time.monotonic() + timeout
        while self.pub.get_subscription_count() == 0:
            assert time.monotonic() < deadline, 'the node never subscribed to points'
            time.sleep(0.1)


def diagnostics(client: Client, key: str | None = None, until=None, timeout=120.0) -> dict:
    """The node's latest diagnostic values; with ``until``, wait until until(values) holds."""
    from diagnostic_msgs.msg import DiagnosticArray

    deadline = time.monotonic() + timeout
    while True:
        msg = client.wait_for_message(DiagnosticArray, '/diagnostics', qos=10)
        values = {kv.key: kv.value for kv in msg.status[0].values}
        if until is None or until(values):
            return values
        assert time.monotonic() < deadline, f'diagnostics never reached the condition: {values}'


def assert_answers_equal(a: dict, b: dict) -> None:
    for key in a:
        np.testing.assert_array_equal(np.asarray(a[key]), np.asarray(b[key]), err_msg=key)


# ------------------------------------------------------------------------------------------
# Fixtures
# ------------------------------------------------------------------------------------------
@pytest.fixture(scope='module')
def domain():
    return 100 + os.getpid() % 100


@pytest.fixture(scope='module')
def env(domain):
    env = dict(os.environ)
    env['ROS_DOMAIN_ID'] = str(domain)
    env['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    return env


@pytest.fixture(scope='module')
def workdir(tmp_path_factory):
    return tmp_path_factory.mktemp('node')


@pytest.fixture(scope='module')
def scans(scenes):
    """The first DRIVE_SECONDS of the street drive as 0.1 s PointCloud2 scans (rclpy messages)."""
    cloud = scenes.campaign('street', 0)
    part_of_drive = cloud.select(cloud.points['time'] < cloud.points['time'].min() + DRIVE_SECONDS)
    types = ma.rclpy_types()
    out = []
    for stamp_ns, part in split_scans(part_of_drive, 0.1):
        out.append(ma.pointcloud2_from_structured(part, stamp_ns=stamp_ns, frame_id='map', msg_types=types))
    return out


@pytest.fixture(scope='module')
def client(domain):
    c = Client(domain)
    yield c
    c.close()


@pytest.fixture(scope='module')
def mapped(client, env, workdir, scans):
    """The node, fed the scans; yields (node process, map path saved by the node)."""
    node = NodeProcess(node_config(workdir, **{'service.max_query_points': 20000, 'node.max_cloud_points': 400000}),
                       env, workdir / 'node.log')
    try:
        node.wait_ready(client)
        for msg in scans:
            client.pub.publish(msg)
            time.sleep(0.01)
        diagnostics(client, until=lambda v: int(v['clouds_mapped']) + int(v['clouds_failed'])
                    + int(v['clouds_dropped']) >= len(scans) and v['settled'] == 'True', timeout=300)
        yield node
    finally:
        node.stop()
        print((workdir / 'node.log').read_text()[-3000:])


_OFFLINE: dict = {}


def offline_map(scans) -> FacadeMap:
    key = (id(scans[0]), len(scans))
    if key not in _OFFLINE:
        _OFFLINE[key] = _offline_map(scans)
    return _OFFLINE[key]


def _offline_map(scans) -> FacadeMap:
    """The offline core fed the same scans one by one, as the node's worker is, then flushed
    as the node does when the input pauses."""
    fmap = FacadeMap(map_params(scenario_config()), np.zeros(3))
    map_scans(fmap, (ma.structured_from_pointcloud2(msg) for msg in scans), InputConfig())
    return fmap


def probe_points(fmap: FacadeMap, n: int = 3000) -> np.ndarray:
    rng = np.random.default_rng(0)
    pts = np.vstack(list(fmap.points.values()))
    return pts[rng.choice(len(pts), n, replace=False)] + rng.normal(0, 0.3, (n, 3))


# ------------------------------------------------------------------------------------------
# Tests
# ------------------------------------------------------------------------------------------
def test_every_scan_is_mapped_and_reported(client, mapped, scans):
    values = diagnostics(client)
    assert int(values['clouds_received']) == len(scans)
    assert int(values['clouds_mapped']) == len(scans)
    assert int(values['clouds_dropped']) == 0 and int(values['clouds_failed']) == 0
    # One idle flush after the stream, in its two steps (the held-back points, then the whole
    # refits): none in between (which would make another map).
    assert int(values['flushes']) <= 2
    assert int(values['facades']) >= 3 and int(values['buildings']) >= 2
    assert float(values['last_update_seconds']) > 0 and float(values['last_update_cpu_seconds']) > 0
    assert 0 < int(values['map_points_stored']) <= int(values['map_points'])
    # The map's arrays: its points alone (x, y, z and normals, float64) in the mapping process.
    assert float(values['map_mb']) >= int(values['map_points_stored']) * 48 / 2**20
    assert 0 < float(values['facades_mb']) < float(values['map_mb']) and float(values['published_mb']) > 0


def test_service_answers_equal_the_offline_core(client, mapped, scans, workdir):
    from uncertain_facade_map.srv import SaveMap

    saved = client.call(SaveMap, 'save_map', SaveMap.Request(path=str(workdir / 'live.npz')))
    assert saved.success, saved.message
    live = load_map(workdir / 'live.npz')
    offline = offline_map(scans)
    assert len(live.facades) == len(offline.facades)
    assert live.n_points == offline.n_points
    xyz = probe_points(offline)
    from uncertain_facade_map.srv import QueryPoints

    response = client.call(QueryPoints, 'query_points', query_request(xyz))
    assert response.success, response.message
    # The occupancy's PLSC parameters, learnt as the map grew, are the offline core's too.
    assert offline.occupancy_.learnt and live.occupancy_ == offline.occupancy_
    # So is the scan-to-scan variance (each cloud a scan).
    reg = offline.registration_var_
    assert live.registration_var_ == reg and offline.registration_sums_[0] > 0
    # The node answers as the command line reads a map (query_map: the stored points per point
    # where dense, the surface event, the learnt PLSC), from the offline core's map...
    expected = offline.query(xyz, QueryConfig(), 0.1).as_dict()
    assert (expected['facade'] >= 0).mean() > 0.3
    assert_answers_equal(answers_of(response), expected)
    # ... and from the node's own map file.
    assert_answers_equal(answers_of(response), live.query(xyz, QueryConfig(), 0.1).as_dict())
    # Another resolution.
    response = client.call(QueryPoints, 'query_points', query_request(xyz[:500], 0.05))
    assert_answers_equal(answers_of(response), offline.query(xyz[:500], QueryConfig(), 0.05).as_dict())
    # The points as 3 numbers each (the fast request) get the same answers, normals included.
    flat = answers_of(client.call(QueryPoints, 'query_points', query_request(xyz, flat=True)))
    assert flat['normal'].shape == (len(xyz), 3)
    assert_answers_equal(flat, expected)


def test_get_facades_describes_the_models(client, mapped, scans):
    from uncertain_facade_map.srv import GetFacades

    offline = offline_map(scans)
    response = client.call(GetFacades, 'get_facades', GetFacades.Request(building=-1))
    assert response.success
    assert [f.facade_id for f in response.facades] == [f.facade_id for f in offline.facades]
    for msg, model in zip(response.facades, offline.facades):
        np.testing.assert_allclose(msg.plane[:3], model.frame.normal, atol=1e-12)
        np.testing.assert_allclose(msg.layer_means, model.layers.means_)
        assert msg.points == len(model.point_index) and msg.building == model.building
    one = client.call(GetFacades, 'get_facades', GetFacades.Request(building=offline.facades[0].building))
    assert {f.building for f in one.facades} == {offline.facades[0].building}


def test_late_subscriber_gets_every_map(client, mapped):
    from nav_msgs.msg import OccupancyGrid
    from nav_msgs.srv import GetMap
    from sensor_msgs.msg import PointCloud2
    from visualization_msgs.msg import MarkerArray

    from uncertain_facade_map.msg import FacadeGridArray

    surface = client.wait_for_message(PointCloud2, 'surface')
    fields = [f.name for f in surface.fields]
    assert fields == ['x', 'y', 'z', 'std', 'facade'] and surface.width > 10000
    points = ma.structured_from_pointcloud2(surface)
    assert np.all(points['std'] > 0) and np.all(points['std'] < 1.0)
    mesh = client.wait_for_message(MarkerArray, 'surface_mesh')
    assert len(mesh.markers) >= 2 and sum(len(m.points) for m in mesh.markers[1:]) > 10000
    grids = client.wait_for_message(FacadeGridArray, 'variance_grids')
    assert len(grids.grids) >= 3
    g = grids.grids[0]
    assert len(g.variance) == g.width * g.height and min(g.variance) > 0
    voxels = client.wait_for_message(PointCloud2, 'occupancy_voxels')
    vox = ma.structured_from_pointcloud2(voxels)
    assert len(vox) > 1000 and vox['p_occupied'].min() >= 0 and vox['p_occupied'].max() <= 1
    assert (vox['p_occupied'] > 0.9).any() and (vox['p_occupied'] < 0.1).any()
    grid = client.wait_for_message(OccupancyGrid, 'occupancy_grid')
    data = np.asarray(grid.data)
    assert len(data) == grid.info.width * grid.info.height and (data == 100).any() and (data == 0).any()
    got = client.call(GetMap, 'get_map', GetMap.Request())
    assert got.map.info.width == grid.info.width and list(got.map.data) == list(grid.data)


def test_bad_clouds_are_refused_and_the_map_kept(client, mapped, scans):
    from sensor_msgs.msg import PointCloud2, PointField

    from uncertain_facade_map.srv import QueryPoints

    offline = offline_map(scans)
    xyz = probe_points(offline, 500)
    before = answers_of(client.call(QueryPoints, 'query_points', query_request(xyz)))
    start = diagnostics(client)
    types = ma.rclpy_types()
    good = ma.structured_from_pointcloud2(scans[len(scans) // 2])

    def cloud(points, frame='map'):
        return ma.pointcloud2_from_structured(points, stamp_ns=1, frame_id=frame, msg_types=types)

    no_xyz = np.zeros(10, dtype=[('a', 'f4'), ('b', 'f4')])
    unknown = cloud(good[:10])
    unknown.fields = [PointField(name=f.name, offset=f.offset, datatype=42, count=1) for f in unknown.fields]
    nan = good[:200].copy()
    nan['x'][::2] = np.nan
    nan['y'][1::4] = np.inf
    empty = PointCloud2()
    empty.header.frame_id = 'map'
    oversized = np.resize(good, 400001)
    bad = [cloud(no_xyz), unknown, empty, cloud(oversized), cloud(good[:100], 'velodyne')]
    for msg in bad:
        client.pub.publish(msg)
    client.pub.publish(cloud(nan))
    values = diagnostics(client, until=lambda v: int(v['clouds_rejected']) >= int(start['clouds_rejected']) + 5
                         and int(v['points_nonfinite']) >= int(start['points_nonfinite']) + 150, timeout=60)
    assert int(values['clouds_rejected']) == int(start['clouds_rejected']) + 5
    assert int(values['points_nonfinite']) == int(start['points_nonfinite']) + 150  # 100 NaN x, 50 infinite y
    assert mapped.alive()
    # The NaN cloud's finite points are mapped (they repeat points already there).
    after = answers_of(client.call(QueryPoints, 'query_points', query_request(xyz)))
    assert (after['facade'] == before['facade']).mean() > 0.99
    assert np.nanmax(np.abs(after['mean_depth'] - before['mean_depth'])) < 0.2
    log = mapped.log.read_text()
    for text in ('no x, y, z field', 'empty cloud', 'node.max_cloud_points',
                 'no transform from "velodyne" into the map frame "map"', 'NaN or infinite'):
        assert text in log, text
    assert int(values['clouds_no_transform']) == int(start['clouds_no_transform']) + 1


def test_bad_queries_get_error_responses(client, mapped):
    from uncertain_facade_map.srv import QueryPoints

    nan = client.call(QueryPoints, 'query_points', query_request(np.array([[0.0, 0.0, 0.0], [np.nan, 1.0, 1.0]])))
    assert not nan.success and 'NaN' in nan.message and len(nan.facade) == 0
    many = client.call(QueryPoints, 'query_points', query_request(np.zeros((20001, 3))))
    assert not many.success and '20000' in many.message
    bad_res = client.call(QueryPoints, 'query_points', query_request(np.zeros((3, 3)), -1.0))
    assert not bad_res.success and 'resolution' in bad_res.message
    empty = client.call(QueryPoints, 'query_points', query_request(np.zeros((0, 3))))
    assert empty.success and len(empty.facade) == 0
    assert mapped.alive()


def assert_accounts_add_up(values: dict) -> None:
    """received = mapped + dropped + rejected + failed + waiting, for clouds and points."""
    v = {k: int(x) for k, x in values.items() if k.startswith(('clouds_', 'points_')) and x.lstrip('-').isdigit()}
    assert v['clouds_received'] == sum(v[f'clouds_{k}'] for k in ('mapped', 'dropped', 'rejected', 'failed',
                                                                   'waiting')), values
    assert v['points_received'] == sum(v[f'points_{k}'] for k in ('mapped', 'not_building', 'nonfinite', 'dropped',
                                                                   'rejected', 'failed', 'waiting')), values


def test_absurd_and_byte_swapped_clouds_are_refused_and_the_map_unchanged(client, mapped, scans):
    """A building cloud at 1e30 m, and one whose header says big-endian over little-endian
    data, are refused with a reason (the second names is_bigendian): the map version and
    every answer stay as they were, and the accounts add up."""
    from geometry_msgs.msg import TransformStamped

    from uncertain_facade_map.srv import QueryPoints

    xyz = probe_points(offline_map(scans), 300)
    before = answers_of(client.call(QueryPoints, 'query_points', query_request(xyz)))
    start = diagnostics(client)
    types = ma.rclpy_types()
    good = ma.structured_from_pointcloud2(scans[5])[:2000].copy()
    far = good.copy()
    far['x'][::3] = 1e30
    client.pub.publish(ma.pointcloud2_from_structured(far, stamp_ns=1, frame_id='map', msg_types=types))
    swapped = ma.pointcloud2_from_structured(good, stamp_ns=2, frame_id='map', msg_types=types)
    swapped.is_bigendian = True
    client.pub.publish(swapped)
    pose = TransformStamped()
    pose.header.frame_id, pose.child_frame_id = 'map', 'far_sensor'
    pose.transform.translation.x = 1e12
    pose.transform.rotation.w = 1.0
    client.pose_pub.publish(pose)
    values = diagnostics(client, until=lambda v: int(v['clouds_rejected']) >= int(start['clouds_rejected']) + 2
                         and int(v['poses_rejected']) >= int(start['poses_rejected']) + 1, timeout=60)
    assert int(values['clouds_rejected']) == int(start['clouds_rejected']) + 2
    assert int(values['points_rejected']) == int(start['points_rejected']) + 2 * len(good)
    assert values['map_version'] == start['map_version'] and values['map_points'] == start['map_points']
    assert values['last_error'] and float(values['last_error_age_seconds']) >= 0
    assert_accounts_add_up(values)
    assert_answers_equal(answers_of(client.call(QueryPoints, 'query_points', query_request(xyz))), before)
    log = mapped.log.read_text()
    assert 'beyond node.max_coordinate' in log and 'is_bigendian' in log and 'translation' in log
    assert mapped.alive()


def test_get_map_serves_a_map_of_any_width(client, mapped, workdir):
    """Two small blocks 300 m apart in x and y: at 0.1 m the 2D grid would need 9 M cells,
    more than publish.grid_max_cells; get_map answers a coarser grid instead of killing
    the node."""
    from nav_msgs.srv import GetMap

    from uncertain_facade_map.srv import LoadMap, SaveMap

    assert client.call(SaveMap, 'save_map', SaveMap.Request(path=str(workdir / 'before_wide.npz'))).success
    rng = np.random.default_rng(4)
    blocks = []
    for x0 in (0.0, 300.0):
        n = 3000
        blocks.append(np.c_[x0 + rng.uniform(0, 8, n), x0 + rng.normal(0, 0.01, n), rng.uniform(0, 6, n)])
    wide = FacadeMap(map_params(scenario_config()), np.zeros(3))
    wide.add_points(np.vstack(blocks), np.repeat([0, 1], 3000))
    save_map(wide, workdir / 'wide.npz')
    try:
        loaded = client.call(LoadMap, 'load_map', LoadMap.Request(path=str(workdir / 'wide.npz')))
        assert loaded.success and loaded.facades == 2, loaded.message
        got = client.call(GetMap, 'get_map', GetMap.Request())
        info = got.map.info
        assert info.width * info.height <= 4_000_000 and info.resolution >= 0.2
        assert min(info.width, info.height) * info.resolution > 300 and len(got.map.data) == info.width * info.height
        assert (np.asarray(got.map.data) == 100).any()
        assert mapped.alive() and 'served at' in mapped.log.read_text()
    finally:
        restored = client.call(LoadMap, 'load_map', LoadMap.Request(path=str(workdir / 'before_wide.npz')))
        assert restored.success, restored.message


def test_clouds_in_a_sensor_frame_are_moved_by_its_pose(client, mapped, scans):
    from geometry_msgs.msg import TransformStamped

    from uncertain_facade_map.srv import QueryPoints

    start = diagnostics(client)
    good = ma.structured_from_pointcloud2(scans[5])
    # The sensor frame is the map frame turned 90 degrees about z and shifted.
    c, s = 0.0, 1.0
    rotation = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
    t = np.array([3.0, -2.0, 0.5])
    local = good.copy()
    xyz = np.stack([good['x'], good['y'], good['z']], 1).astype(np.float64)
    moved = (xyz - t) @ rotation  # R^T (x - t)
    local['x'], local['y'], local['z'] = moved.T
    for name in ('origin_x', 'origin_y', 'origin_z'):
        local[name] = np.nan  # origins unknown in the sensor frame: the pose's translation is used
    pose = TransformStamped()
    pose.header.frame_id = 'map'
    pose.header.stamp.sec = 7
    pose.child_frame_id = 'lidar'
    pose.transform.translation.x, pose.transform.translation.y, pose.transform.translation.z = t
    pose.transform.rotation.z = np.sin(np.pi / 4)
    pose.transform.rotation.w = np.cos(np.pi / 4)
    client.pose_pub.publish(pose)
    time.sleep(1.0)
    msg = ma.pointcloud2_from_structured(local, stamp_ns=7 * 10**9, frame_id='lidar', msg_types=ma.rclpy_types())
    client.pub.publish(msg)
    values = diagnostics(client, until=lambda v: int(v['clouds_mapped']) > int(start['clouds_mapped']), timeout=60)
    assert int(values['clouds_rejected']) == int(start['clouds_rejected'])
    # Points of the moved scan are back on the façades they came from.
    probe = xyz[np.isin(good['class'], [1])][:300]
    answer = answers_of(client.call(QueryPoints, 'query_points', query_request(probe)))
    on = answer['facade'] >= 0
    assert on.mean() > 0.8 and np.median(np.abs(answer['signed_distance'][on])) < 0.05


def test_a_cloud_without_classes_is_mapped_as_its_selected_points(client, mapped, workdir):
    """A sweep without the class field, in its sensor's frame: the node maps the points the
    selection keeps (walls), selected in the map frame with the sensor origin from its pose,
    as offline replay does (io.scans.Scan)."""
    from geometry_msgs.msg import TransformStamped
    from support import WALL, unclassified_street

    from uncertain_facade_map.io.scans import Scan
    from uncertain_facade_map.params import SelectionConfig
    from uncertain_facade_map.srv import LoadMap, QueryPoints, SaveMap
    from uncertain_facade_map.transforms import TransformBuffer

    before = workdir / 'before_unclassified.npz'
    assert client.call(SaveMap, 'save_map', SaveMap.Request(path=str(before))).success
    start = diagnostics(client)
    xyz, labels, sensor = unclassified_street(seed=3)
    points = np.zeros(len(xyz), dtype=[('x', 'f4'), ('y', 'f4'), ('z', 'f4')])
    points['x'], points['y'], points['z'] = (xyz - sensor).T  # the sensor frame
    t = np.array([1000.0, 0.0, 1.8])  # far from the street drive's buildings
    tf = TransformBuffer()
    tf.set_transform('map', 'sweep', 9 * 10**9, t, [0, 0, 0, 1])
    scan = Scan.of(points, 'sweep', 9 * 10**9, InputConfig())
    expected = scan.building_points(scan.place(tf, 'map', 0.05), InputConfig(), SelectionConfig(), None)
    pose = TransformStamped()
    pose.header.frame_id = 'map'
    pose.header.stamp.sec = 9
    pose.child_frame_id = 'sweep'
    pose.transform.translation.x, pose.transform.translation.y, pose.transform.translation.z = t
    pose.transform.rotation.w = 1.0
    client.pose_pub.publish(pose)
    time.sleep(1.0)
    client.pub.publish(ma.pointcloud2_from_structured(points, stamp_ns=9 * 10**9, frame_id='sweep',
                                                      msg_types=ma.rclpy_types()))
    values = diagnostics(client, until=lambda v: int(v['clouds_mapped']) > int(start['clouds_mapped'])
                         and v['settled'] == 'True', timeout=120)
    assert int(values['clouds_rejected']) == int(start['clouds_rejected'])
    assert int(values['points_not_building']) - int(start['points_not_building']) == expected.not_building
    assert expected.not_building > 0.55 * len(points)
    # The walls are mapped where they stand, and answer queries.
    probe = xyz[labels == WALL][::50] - sensor + t
    answer = answers_of(client.call(QueryPoints, 'query_points', query_request(probe)))
    on = answer['facade'] >= 0
    assert on.mean() > 0.9 and np.median(np.abs(answer['signed_distance'][on])) < 0.05
    assert 'has no field "class"' in mapped.log.read_text()  # said, not silent
    # The later tests compare the node's map with the street drive's alone.
    assert client.call(LoadMap, 'load_map', LoadMap.Request(path=str(before))).success


def test_a_loaded_map_answers_with_its_own_bands(client, mapped, scans, workdir):
    """A map built with other façade bands, loaded into the node, answers as the command line does."""
    from uncertain_facade_map.srv import LoadMap, QueryPoints, SaveMap
    from uncertain_facade_map_apps import cli

    saved = client.call(SaveMap, 'save_map', SaveMap.Request(path=str(workdir / 'before_bands.npz')))
    assert saved.success, saved.message
    narrow = {'extraction.band_back': 0.3, 'extraction.band_front': 0.6}
    other = FacadeMap(map_params(scenario_config(**narrow)), np.zeros(3))
    map_scans(other, (ma.structured_from_pointcloud2(msg) for msg in scans), InputConfig())
    save_map(other, workdir / 'narrow.npz')
    xyz = probe_points(other, 2000)
    rng = np.random.default_rng(1)
    xyz += rng.normal(0.0, 0.6, xyz.shape)  # reach beyond the narrow bands
    np.save(workdir / 'probe.npy', xyz)
    assert cli.main(['query', str(workdir / 'narrow.npz'), '--points', str(workdir / 'probe.npy'),
                     '--out', str(workdir / 'narrow_answers.npz')]) == 0
    expected = dict(np.load(workdir / 'narrow_answers.npz'))
    # The node's own parameter file has the default bands, which answer otherwise.
    node_bands = query_points(other.facades, xyz, 0.1, 1.0, 2.0).as_dict()
    assert (node_bands['facade'] != expected['facade']).sum() > 20
    loaded = client.call(LoadMap, 'load_map', LoadMap.Request(path=str(workdir / 'narrow.npz')))
    assert loaded.success, loaded.message
    assert_answers_equal(answers_of(client.call(QueryPoints, 'query_points', query_request(xyz))), expected)
    restored = client.call(LoadMap, 'load_map', LoadMap.Request(path=str(workdir / 'before_bands.npz')))
    assert restored.success, restored.message


def _escaping_tiled_map(folder: Path, tile_file: str, link_to: Path | None, fmap: FacadeMap) -> Path:
    """A tiled map's folder whose one tile is ``tile_file`` (a link to ``link_to`` when given)."""
    from uncertain_facade_map.params import map_params_record
    from uncertain_facade_map.tiling.manifest import Manifest, TileRecord, write_manifest

    (folder / 'tiles').mkdir(parents=True)
    if link_to is not None:
        (folder / tile_file).symlink_to(link_to)
    record = TileRecord('tile_0_0', (0, 0), (0.0, 0.0, 50.0, 50.0), (0.0,) * 6, tile_file, '0' * 64,
                        [int(b) for b in fmap.buildings], len(fmap.facades), fmap.n_stored, '')
    write_manifest(folder, Manifest(50.0, (0.0, 0.0, 0.0), map_params_record(fmap.params), {'tile_0_0': record}))
    return folder


def test_services_are_confined_to_the_map_folder(client, mapped, scans, workdir, tmp_path_factory):
    """Issue 38: save_map and load_map, called as any DDS participant may, refuse every path
    that leads out of the map folder (persistence.map_dir, here the work folder), a save over
    a file that is not a map, a name without .npz, a file over persistence.max_load_mb and a
    tiled map whose tiles leave its folder, each with a message naming the rule; the node
    lives on, its answers are unchanged and no file outside the folder is touched. A
    relative name saves into the folder."""
    from uncertain_facade_map.srv import LoadMap, QueryPoints, SaveMap

    outside = tmp_path_factory.mktemp('outside')
    xyz = probe_points(offline_map(scans), 1000)
    before = answers_of(client.call(QueryPoints, 'query_points', query_request(xyz)))
    saved = client.call(SaveMap, 'save_map', SaveMap.Request(path='confined.npz'))
    assert saved.success and saved.path == str((workdir / 'confined.npz').resolve()), saved.message
    shutil.copyfile(workdir / 'confined.npz', outside / 'map.npz')
    (outside / 'victim.txt').write_text('a shell profile\n')
    (outside / 'victim.npz').write_text('not a map\n')
    (workdir / 'notes.npz').write_text('my notes\n')
    (workdir / 'link_out').symlink_to(outside)
    (workdir / 'map_link.npz').symlink_to(outside / 'map.npz')
    with open(workdir / 'huge.npz', 'wb') as fh:
        fh.truncate(2**43)  # 8 TB, sparse: refused before it is read
    fmap = load_map(outside / 'map.npz')
    _escaping_tiled_map(workdir / 'linked_tiles', 'tiles/tile_0_0.npz', outside / 'map.npz', fmap)
    _escaping_tiled_map(workdir / 'dotted_tiles', '../confined.npz', None, fmap)
    up = f'../{outside.name}'
    outside_rule = 'leads outside the map folder'
    cases = [
        (SaveMap, str(outside / 'victim.txt'), outside_rule),
        (SaveMap, str(outside / 'victim.npz'), outside_rule),
        (SaveMap, str(outside / 'new.npz'), outside_rule),
        (SaveMap, f'{up}/new.npz', outside_rule),
        (SaveMap, 'link_out/new.npz', outside_rule),
        (SaveMap, 'notes.npz', 'not a map file'),
        (SaveMap, 'notes.txt', '*.npz only'),
        (LoadMap, str(outside / 'map.npz'), outside_rule),
        (LoadMap, f'{up}/map.npz', outside_rule),
        (LoadMap, 'map_link.npz', outside_rule),
        (LoadMap, 'huge.npz', 'persistence.max_load_mb'),
        (LoadMap, 'linked_tiles', "tiles must lie in its folder"),
        (LoadMap, 'dotted_tiles', 'must be a path inside the map folder'),
    ]
    for srv, path, rule in cases:
        response = client.call(srv, srv.__name__.replace('Map', '_map').lower(), srv.Request(path=path))
        assert not response.success and rule in response.message, (srv.__name__, path, response.message)
        assert mapped.alive()
    assert (outside / 'victim.txt').read_text() == 'a shell profile\n'
    assert (outside / 'victim.npz').read_text() == 'not a map\n'
    assert (workdir / 'notes.npz').read_text() == 'my notes\n'
    assert sorted(p.name for p in outside.iterdir()) == ['map.npz', 'victim.npz', 'victim.txt']
    assert_answers_equal(answers_of(client.call(QueryPoints, 'query_points', query_request(xyz))), before)
    # A map file in the folder is replaced; a relative name loads from it.
    assert client.call(SaveMap, 'save_map', SaveMap.Request(path='confined.npz')).success
    loaded = client.call(LoadMap, 'load_map', LoadMap.Request(path='confined.npz'))
    assert loaded.success, loaded.message
    assert_answers_equal(answers_of(client.call(QueryPoints, 'query_points', query_request(xyz))), before)


def test_save_reset_load_and_restart_answer_the_same(client, mapped, env, workdir, scans):
    from std_srvs.srv import Trigger

    from uncertain_facade_map.srv import LoadMap, QueryPoints, SaveMap

    offline = offline_map(scans)
    xyz = probe_points(offline, 1000)
    saved = client.call(SaveMap, 'save_map', SaveMap.Request(path=str(workdir / 'kept.npz')))
    assert saved.success, saved.message
    before = answers_of(client.call(QueryPoints, 'query_points', query_request(xyz)))
    # Errors leave the map as it is.
    missing = client.call(LoadMap, 'load_map', LoadMap.Request(path=str(workdir / 'missing.npz')))
    assert not missing.success and 'no such file' in missing.message
    (workdir / 'junk.npz').write_bytes(b'not a map')
    junk = client.call(LoadMap, 'load_map', LoadMap.Request(path=str(workdir / 'junk.npz')))
    assert not junk.success and 'not a map file' in junk.message
    nowhere = client.call(SaveMap, 'save_map', SaveMap.Request(path=str(workdir / 'nonexistent' / 'map.npz')))
    assert not nowhere.success and 'does not exist' in nowhere.message
    assert_answers_equal(answers_of(client.call(QueryPoints, 'query_points', query_request(xyz))), before)
    # Reset empties the map; load brings it back.
    assert client.call(Trigger, 'reset', Trigger.Request()).success
    empty = answers_of(client.call(QueryPoints, 'query_points', query_request(xyz)))
    assert np.all(empty['facade'] == -1) and np.all(empty['p_occupied'] == 0.5)
    # A late subscriber gets no old mesh: only the marker that deletes all.
    from visualization_msgs.msg import MarkerArray

    deadline = time.monotonic() + 30
    while len(client.wait_for_message(MarkerArray, 'surface_mesh').markers) != 1:
        assert time.monotonic() < deadline, 'the old surface mesh is still published after reset'
        time.sleep(1.0)
    loaded = client.call(LoadMap, 'load_map', LoadMap.Request(path=str(workdir / 'kept.npz')))
    assert loaded.success and loaded.facades == len(offline.facades)
    assert_answers_equal(answers_of(client.call(QueryPoints, 'query_points', query_request(xyz))), before)
    # Kill the node (no clean shutdown) and start a new one on the saved map.
    mapped.kill()
    restarted = NodeProcess(node_config(workdir, **{'persistence.map_path': str(workdir / 'kept.npz')}), env,
                            workdir / 'restarted.log')
    try:
        restarted.wait_ready(client)
        again = answers_of(client.call_retrying(QueryPoints, 'query_points', query_request(xyz)))
        assert_answers_equal(again, before)
    finally:
        restarted.stop()


def test_autosave_keeps_the_map_up_to_date(client, env, workdir, scans):
    path = workdir / 'auto.npz'
    node = NodeProcess(node_config(workdir, **{'persistence.map_path': str(path),
                                               'persistence.autosave_period': 0.5}), env, workdir / 'auto.log')
    try:
        node.wait_ready(client)
        for msg in scans[:10]:
            client.pub.publish(msg)
        diagnostics(client, until=lambda v: int(v['clouds_mapped']) >= 10, timeout=120)
        deadline = time.monotonic() + 30
        while True:
            if path.exists():
                fmap = load_map(path)
                # All the points, and the idle flush's second step (whole refits, calibration) done.
                if fmap.n_points == offline_map(scans[:10]).n_points and not fmap.needs_consolidation:
                    break
            assert time.monotonic() < deadline, 'autosave never wrote the whole map'
            time.sleep(0.5)
        node.kill()
        assert not list(workdir.glob('.auto.npz.*')), 'a temporary file was left behind'
        # The file the killed node left answers as the offline core fed the same scans.
        xyz = probe_points(fmap, 300)
        raster = QueryConfig(surface='raster')
        expected = offline_map(scans[:10]).query(xyz, raster, 0.1).as_dict()
        assert_answers_equal(fmap.query(xyz, raster, 0.1).as_dict(), expected)
    finally:
        node.stop()


def test_saves_do_not_wait_for_the_queue_and_files_are_clean(client, env, workdir, scans):
    """A stale temporary file of a killed save is removed at start; a save under load
    answers at once with the map as it stands and says how many clouds still wait; the
    file gets the process's umask, not 0600."""
    from uncertain_facade_map.srv import SaveMap

    path = workdir / 'busy.npz'
    stale = workdir / '.busy.npz.abcd1234.tmp'
    stale.write_bytes(b'half a map')
    node = NodeProcess(node_config(workdir, **{'persistence.map_path': str(path), 'node.idle_flush': 30.0}), env,
                       workdir / 'busy.log')
    try:
        node.wait_ready(client)
        assert not stale.exists() and 'removed' in node.log.read_text()
        for msg in scans:
            client.pub.publish(msg)
        diagnostics(client, until=lambda v: int(v['map_version']) >= 1, timeout=120)
        started = time.monotonic()
        saved = client.call(SaveMap, 'save_map', SaveMap.Request(path=''))
        took = time.monotonic() - started
        values = diagnostics(client)
        assert saved.success, saved.message
        assert took < 10.0, f'the save waited {took:.1f} s'
        if int(values['clouds_waiting']) > 0:
            assert 'still wait' in saved.message
        umask = os.umask(0)
        os.umask(umask)
        assert (path.stat().st_mode & 0o777) == (0o666 & ~umask)
        assert load_map(path).n_points > 0
        assert_accounts_add_up(diagnostics(client, until=lambda v: v['clouds_waiting'] == '0', timeout=300))
    finally:
        node.stop()


def test_a_second_mapper_is_warned_of_and_a_misspelt_parameter_refused(client, env, workdir):
    """Two mappers in one domain without namespaces: the second says that the first offers
    its services too. A misspelt parameter stops the node with one line naming it."""
    first = NodeProcess(node_config(workdir), env, workdir / 'first.log')
    second = None
    try:
        first.wait_ready(client)
        second = NodeProcess(node_config(workdir), env, workdir / 'second.log')
        deadline = time.monotonic() + 60
        while 'same services' not in second.log.read_text():
            assert second.alive() and time.monotonic() < deadline, second.log.read_text()
            time.sleep(0.5)
        assert '__ns:=' in second.log.read_text()
    finally:
        for node in (first, second):
            if node is not None:
                node.stop()
    params = workdir / 'misspelt.yaml'
    params.write_text('facade_mapper:\n  ros__parameters:\n    node:\n      queu_size: 5\n')
    run = subprocess.run([sys.executable, '-m', 'uncertain_facade_map_node.node', '--ros-args', '--params-file',
                          str(params)], env=env, cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert run.returncode == 2
    assert 'unknown parameter node.queu_size; did you mean node.queue_size' in run.stderr
    assert 'Traceback' not in run.stderr + run.stdout
