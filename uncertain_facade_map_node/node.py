"""The ``facade_mapper`` node: live façade mapping from classified building PointCloud2.

A thin shell: :mod:`msg_adapters` turns messages into arrays and back, the core
(:mod:`uncertain_facade_map`) does all the modelling, and a
:class:`~uncertain_facade_map.mapping.worker.MapWorker` thread owns the map, so no callback
ever refits a model.

Topics (names relative, remap with ``--ros-args -r``):

- subscribed: ``points`` (sensor_msgs/PointCloud2, QoS ``node.qos``), ``sensor_pose``
  (geometry_msgs/TransformStamped: the pose of a cloud's frame ``child_frame_id`` in the
  map frame, for clouds not in the map frame; there is no tf2 in the wheel set);
- published, transient-local (a late subscriber gets the last map): ``surface``
  (PointCloud2 x, y, z, std, facade), ``surface_mesh`` (visualization_msgs/MarkerArray),
  ``variance_grids`` (uncertain_facade_map/FacadeGridArray), ``occupancy_voxels``
  (PointCloud2 x, y, z, p_occupied), ``occupancy_grid`` (nav_msgs/OccupancyGrid);
  and ``/diagnostics`` (diagnostic_msgs/DiagnosticArray).

Services: ``query_points`` (uncertain_facade_map/QueryPoints), ``get_facades``
(uncertain_facade_map/GetFacades), ``save_map`` / ``load_map``
(uncertain_facade_map/SaveMap, LoadMap), ``reset`` (std_srvs/Trigger) and ``get_map``
(nav_msgs/GetMap, the 2D grid).
"""

from __future__ import annotations

import bisect
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import TransformStamped
from nav_msgs.msg import OccupancyGrid
from nav_msgs.srv import GetMap
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup, ReentrantCallbackGroup
from rclpy.exceptions import ParameterException
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from sensor_msgs.msg import PointCloud2
from std_srvs.srv import Trigger
from visualization_msgs.msg import MarkerArray

import msg_adapters as ma
from msg_adapters import map_messages as mm
from msg_adapters import parameters as mp_params
from uncertain_facade_map.errors import FacadeMapError, InputError
from uncertain_facade_map.io.inputs import select_scan_points
from uncertain_facade_map.io.map_file import load_map, save_map
from uncertain_facade_map.mapping import products as mp
from uncertain_facade_map.mapping.facade_map import FacadeMap
from uncertain_facade_map.mapping.worker import Cloud, MapSnapshot, MapWorker, ReplaceMap
from uncertain_facade_map.msg import FacadeGridArray
from uncertain_facade_map.params import (
    NODE_NAME,
    Config,
    config_from_parameters,
    map_params,
    parameters,
)
from uncertain_facade_map.pipeline.step7_queries import query_points
from uncertain_facade_map.srv import GetFacades, LoadMap, QueryPoints, SaveMap

#: Seconds a service waits for the map worker (save, load, reset) before answering "busy".
COMMAND_TIMEOUT = 120.0


def declare_config(node: Any) -> Config:
    """Declare every parameter on ``node`` (read-only, with its descriptor) and read the configuration.

    The node's parameter path: each parameter's default, description, unit, range and
    relations come from its declaration (:mod:`uncertain_facade_map.params`); rclpy checks
    the advertised range of a ``-p`` or parameter-file override, then the declarations
    check everything (open ends, relations).

    Raises:
        InputError: a parameter of the wrong type, out of its range or breaking a relation,
            with a message naming it.
    """
    types = mp_params.rclpy_parameter_types()
    values = {}
    for info in parameters():
        default = list(info.value) if info.is_list else info.value
        try:
            node.declare_parameter(info.name, default, mp_params.parameter_descriptor(info, types))
        except ParameterException as exc:
            raise InputError(f'parameter {info.name}: {" ".join(str(exc).split())} '
                             f'(allowed: {info.spec.constraint_text() or "any " + info.type.__name__})') from exc
        values[info.name] = mp_params.parameter_value(node.get_parameter(info.name).value)
    return config_from_parameters(values)


def _stamp_ns(header: Any) -> int:
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


class FacadeMapperNode(Node):
    """Subscribes to building clouds, maps them in a worker, publishes and serves the map."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(NODE_NAME, **kwargs)
        self.config = self._read_parameters()
        self.types = mm.rclpy_map_types()
        self.cloud_types = ma.rclpy_types()
        cfg = self.config
        self.params = map_params(cfg)
        self.frame_id = cfg.input.frame_id
        self.counters = {'clouds_rejected': 0, 'points_nonfinite': 0, 'points_not_building': 0,
                         'queries': 0, 'queries_failed': 0, 'saves': 0}
        self.last_error = ''
        self._warned: dict[str, float] = {}
        self._poses: dict[str, tuple[list[int], list[tuple[np.ndarray, np.ndarray]]]] = {}
        self._pose_lock = threading.Lock()
        self._grid: tuple[int, Any] | None = None
        self._published_version = -1
        self._saved_version = 0
        self._last_publish = 0.0
        self._publish_lock = threading.Lock()

        fmap = self._initial_map()
        self.worker = MapWorker(fmap, cfg.node.queue_size, on_error=self._cloud_failed, idle_flush=cfg.node.idle_flush,
                               on_flush=self._flushed)

        latched = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL,
                             reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST)
        self.pub_surface = self.create_publisher(PointCloud2, 'surface', latched)
        self.pub_mesh = self.create_publisher(MarkerArray, 'surface_mesh', latched)
        self.pub_grids = self.create_publisher(FacadeGridArray, 'variance_grids', latched)
        self.pub_voxels = self.create_publisher(PointCloud2, 'occupancy_voxels', latched)
        self.pub_grid = self.create_publisher(OccupancyGrid, 'occupancy_grid', latched)
        self.pub_diag = self.create_publisher(DiagnosticArray, '/diagnostics', 10)

        qos = qos_profile_sensor_data if cfg.node.qos == 'sensor_data' else QoSProfile(
            depth=max(10, cfg.node.queue_size), reliability=ReliabilityPolicy.RELIABLE)
        inputs = MutuallyExclusiveCallbackGroup()
        self.create_subscription(PointCloud2, 'points', self.points_callback, qos, callback_group=inputs)
        self.create_subscription(TransformStamped, 'sensor_pose', self.pose_callback, 100,
                                 callback_group=inputs)
        services = ReentrantCallbackGroup()
        self.create_service(QueryPoints, 'query_points', self.query_callback, callback_group=services)
        self.create_service(GetFacades, 'get_facades', self.get_facades_callback, callback_group=services)
        self.create_service(SaveMap, 'save_map', self.save_callback, callback_group=services)
        self.create_service(LoadMap, 'load_map', self.load_callback, callback_group=services)
        self.create_service(Trigger, 'reset', self.reset_callback, callback_group=services)
        self.create_service(GetMap, 'get_map', self.get_map_callback, callback_group=services)
        # Each timer in a group of its own: a long publication must not hold up diagnostics.
        self.create_timer(max(0.05, min(cfg.publish.period, 1.0) or 0.1), self.publish_callback,
                          callback_group=MutuallyExclusiveCallbackGroup())
        self.create_timer(cfg.publish.diagnostics_period, self.diagnostics_callback,
                          callback_group=MutuallyExclusiveCallbackGroup())
        if cfg.persistence.autosave_period > 0:
            self.create_timer(cfg.persistence.autosave_period, self.autosave_callback,
                              callback_group=MutuallyExclusiveCallbackGroup())
        snap = self.worker.snapshot
        self.get_logger().info(f'mapping clouds on "points" in frame "{self.frame_id}"; '
                               f'{len(snap.facades)} façades, {snap.points} points to start with')

    # -- set-up ---------------------------------------------------------------------
    def _read_parameters(self) -> Config:
        try:
            return declare_config(self)
        except InputError as exc:
            self.get_logger().fatal(f'bad parameters: {exc}')
            raise

    def _initial_map(self) -> FacadeMap:
        cfg = self.config
        path = cfg.persistence.map_path
        if path and Path(path).exists():
            fmap = load_map(path)  # a damaged file stops the node: better than mapping over it
            self.get_logger().info(f'loaded {path}: {len(fmap.facades)} façades, {fmap.n_points} points')
            return fmap
        if path:
            self.get_logger().info(f'{path} does not exist yet; starting an empty map')
        return FacadeMap(self.params, np.asarray(cfg.input.map_origin, dtype=np.float64))

    # -- input ------------------------------------------------------------------------
    def _warn(self, text: str, key: str, period: float = 5.0) -> None:
        """Log a warning, at most once per ``period`` seconds for each kind ``key``."""
        now = time.monotonic()
        if now - self._warned.get(key, -1e9) >= period:
            self._warned[key] = now
            self.get_logger().warning(text)

    def _reject(self, why: str) -> None:
        self.counters['clouds_rejected'] += 1
        self.last_error = why
        self._warn(f'cloud rejected: {why}', why.split(':')[0][:30])

    def pose_callback(self, msg: Any) -> None:
        """Keep the pose of a sensor frame in the map frame (for clouds in that frame)."""
        if msg.header.frame_id != self.frame_id:
            self.get_logger().warning(f'sensor_pose in frame "{msg.header.frame_id}" ignored: '
                                      f'poses must be given in the map frame "{self.frame_id}"',
                                      throttle_duration_sec=5.0)
            return
        try:
            rigid = mm.rigid_from_pose(msg)
        except (InputError, ValueError) as exc:
            self.get_logger().warning(f'sensor_pose ignored: {exc}', throttle_duration_sec=5.0)
            return
        with self._pose_lock:
            stamps, poses = self._poses.setdefault(msg.child_frame_id, ([], []))
            t = _stamp_ns(msg.header)
            i = bisect.bisect_right(stamps, t)
            stamps.insert(i, t)
            poses.insert(i, rigid)
            excess = len(stamps) - self.config.node.pose_buffer
            if excess > 0:
                del stamps[:excess], poses[:excess]

    def _pose_for(self, frame: str, stamp: int) -> tuple[np.ndarray, np.ndarray] | None:
        with self._pose_lock:
            stamps, poses = self._poses.get(frame, ([], []))
            if not stamps:
                return None
            i = bisect.bisect_left(stamps, stamp)
            best = min((j for j in (i - 1, i) if 0 <= j < len(stamps)), key=lambda j: abs(stamps[j] - stamp))
            if abs(stamps[best] - stamp) > self.config.node.pose_tolerance * 1e9:
                return None
            return poses[best]

    def points_callback(self, msg: Any) -> None:
        """Check and convert a cloud, keep its building points, queue it for the worker."""
        cfg = self.config
        n = int(msg.width) * int(msg.height)
        if n > cfg.node.max_cloud_points:
            self._reject(f'{n:,} points, more than node.max_cloud_points = {cfg.node.max_cloud_points:,}')
            return
        if n == 0:
            self._reject('empty cloud')
            return
        frame = msg.header.frame_id
        stamp = _stamp_ns(msg.header)
        pose = None
        if frame != self.frame_id:
            pose = self._pose_for(frame, stamp)
            if pose is None:
                self._reject(f'cloud in frame "{frame}", not the map frame "{self.frame_id}", and no '
                             f'sensor_pose of "{frame}" within {cfg.node.pose_tolerance} s of its stamp')
                return
        try:
            points = ma.structured_from_pointcloud2(msg)
        except (InputError, ValueError, TypeError) as exc:
            self._reject(str(exc))
            return
        try:
            # A cloud in another frame than the map's is in its sensor's (or vehicle's) frame.
            scan = select_scan_points(points, cfg.input, cfg.selection, None if pose is None else np.zeros(3))
        except InputError as exc:
            self._reject(str(exc))
            return
        self.counters['points_not_building'] += scan.not_building
        if scan.nonfinite:
            self.counters['points_nonfinite'] += scan.nonfinite
            self._warn(f'{scan.nonfinite} of {n} points with NaN or infinite coordinates skipped', 'nonfinite')
        if not len(scan.xyz):
            return
        xyz, ids, origins = scan.xyz, scan.building_id, scan.sensor_origins
        if pose is not None:
            rotation, translation = pose
            xyz = mm.transform_points(xyz, rotation, translation)
            origins = (mm.transform_points(origins, rotation, translation) if origins is not None
                       else np.broadcast_to(translation, xyz.shape).copy())
        if not self.worker.put(Cloud(xyz, ids, origins, stamp)):
            self.get_logger().warning('mapping falls behind: dropped the oldest waiting cloud '
                                      f'({self.worker.counters["clouds_dropped"]} so far)',
                                      throttle_duration_sec=5.0)

    def _flushed(self, points: int, refitted: list[int]) -> None:
        self.get_logger().info(f'input idle: mapped the {points} points held back, fitted {len(refitted)} '
                               f'façades whole')

    def _cloud_failed(self, cloud: Cloud, exc: BaseException) -> None:
        self.last_error = f'mapping failed: {exc}'
        self.get_logger().error(f'a cloud of {len(cloud.xyz)} points could not be mapped: {exc}')

    # -- publishing ---------------------------------------------------------------------
    def publish_callback(self) -> None:
        """Publish the maps when the map changed and the period has passed."""
        snap = self.worker.snapshot
        if snap.version == self._published_version:
            return
        if time.monotonic() - self._last_publish < self.config.publish.period:
            return
        self.publish_maps(snap)

    def publish_maps(self, snap: MapSnapshot) -> None:
        """Publish every map product of a snapshot."""
        with self._publish_lock:
            cfg = self.config.publish
            stamp = snap.stamp_ns or self.get_clock().now().nanoseconds
            facades = list(snap.facades)
            started = time.perf_counter()
            try:
                surf = mp.surface_grid(facades, cfg.surface_step)
                table = np.zeros(len(surf.xyz), dtype=[('x', 'f4'), ('y', 'f4'), ('z', 'f4'), ('std', 'f4'),
                                                       ('facade', 'i4')])
                table['x'], table['y'], table['z'] = surf.xyz.T
                table['std'], table['facade'] = surf.std, surf.facade
                self.pub_surface.publish(ma.pointcloud2_from_structured(table, stamp_ns=stamp, frame_id=self.frame_id,
                                                                        msg_types=self.cloud_types))
                if facades:
                    mesh = mp.surface_mesh(facades, cfg.mesh_step)
                    self.pub_mesh.publish(mm.triangle_marker_array(mesh.vertices, mesh.triangles, mesh.std,
                                                                   mesh.facade, self.frame_id, stamp, self.types))
                self.pub_grids.publish(mm.facade_grid_array(facades, self.frame_id, stamp, self.types))
                band = snap.params.extraction
                vox = mp.voxel_occupancy(facades, cfg.voxel_resolution, cfg.voxel_shell,
                                         band_back=band.band_back, band_front=band.band_front)
                vt = np.zeros(len(vox.centres), dtype=[('x', 'f4'), ('y', 'f4'), ('z', 'f4'),
                                                       ('p_occupied', 'f4')])
                vt['x'], vt['y'], vt['z'] = vox.centres.T
                vt['p_occupied'] = vox.p_occupied
                self.pub_voxels.publish(ma.pointcloud2_from_structured(vt, stamp_ns=stamp, frame_id=self.frame_id,
                                                                       msg_types=self.cloud_types))
                grid = self._grid_msg(snap, stamp)
                self.pub_grid.publish(grid)
            except FacadeMapError as exc:
                self.last_error = f'publishing failed: {exc}'
                self.get_logger().error(self.last_error, throttle_duration_sec=10.0)
            self._published_version = snap.version
            self._last_publish = time.monotonic()
            self.get_logger().debug(f'published map version {snap.version} in '
                                    f'{time.perf_counter() - started:.2f} s')

    def _grid_msg(self, snap: MapSnapshot, stamp: int) -> Any:
        """The 2D occupancy grid of a snapshot (cached per version)."""
        if self._grid is not None and self._grid[0] == snap.version:
            return self._grid[1]
        cfg = self.config.publish
        params = snap.params.extraction  # the map's own bands (a loaded map keeps its own)
        if snap.facades:
            g = mp.height_band_grid(list(snap.facades), cfg.grid_resolution, cfg.grid_z_min, cfg.grid_z_max,
                                    band_back=params.band_back, band_front=params.band_front)
            p, origin = g.p, g.origin
        else:
            p, origin = np.full((1, 1), np.nan), np.zeros(2)
        msg = mm.occupancy_grid_msg(p, origin, cfg.grid_resolution, self.frame_id, stamp, self.types,
                                    z=cfg.grid_z_min)
        self._grid = (snap.version, msg)
        return msg

    def diagnostics_callback(self) -> None:
        """Publish the counters: points in, dropped, buildings, façades, update time."""
        snap = self.worker.snapshot
        w = self.worker.counters
        values = {'clouds_in': w['clouds_in'], 'clouds_mapped': w['clouds_mapped'],
                  'clouds_dropped': w['clouds_dropped'], 'clouds_failed': w['clouds_failed'],
                  'flushes': w['flushes'],
                  'clouds_rejected': self.counters['clouds_rejected'], 'clouds_queued': self.worker.queued,
                  'points_in': w['points_in'], 'points_dropped': w['points_dropped'],
                  'points_mapped': w['points_mapped'], 'points_pending': self.worker.pending_points,
                  'settled': self.worker.settled, 'points_nonfinite': self.counters['points_nonfinite'],
                  'points_not_building': self.counters['points_not_building'],
                  'buildings': snap.buildings, 'facades': len(snap.facades), 'map_points': snap.points,
                  'map_version': snap.version, 'last_update_seconds': round(self.worker.last_update_seconds, 4),
                  'queries': self.counters['queries'], 'queries_failed': self.counters['queries_failed'],
                  'last_error': self.last_error}
        dropped = w['clouds_dropped'] or w['clouds_failed'] or self.counters['clouds_rejected']
        level = 1 if dropped else 0
        message = 'mapping' if not dropped else 'clouds dropped or rejected (see values)'
        self.pub_diag.publish(mm.diagnostic_array(f'{NODE_NAME}: map', level, message, values, NODE_NAME,
                                                  self.get_clock().now().nanoseconds, self.types))

    # -- services -----------------------------------------------------------------------
    def query_callback(self, request: Any, response: Any) -> Any:
        """Answer a batch of 3D points from the latest snapshot (never waits for the worker)."""
        self.counters['queries'] += 1
        try:
            xyz = mm.points_from_request(request, self.config.service.max_query_points)
            resolution = float(request.resolution) or self.config.query.resolution
            if not np.isfinite(resolution) or resolution <= 0:
                raise InputError(f'resolution must be a positive number of metres, got {request.resolution}')
            snap = self.worker.snapshot
            params = snap.params.extraction  # the map's own bands (a loaded map keeps its own)
            answers = query_points(list(snap.facades), xyz, resolution, params.band_back, params.band_front)
            mm.fill_query_response(response, answers, f'{len(xyz)} points, map version {snap.version}',
                                   msg_types=self.types)
        except FacadeMapError as exc:
            self.counters['queries_failed'] += 1
            response.success = False
            response.message = str(exc)
        return response

    def get_facades_callback(self, request: Any, response: Any) -> Any:
        """The façade models of one building (or all, building = -1)."""
        snap = self.worker.snapshot
        models = [f for f in snap.facades if request.building < 0 or f.building == request.building]
        response.facades = [mm.facade_msg(f, self.types) for f in models]
        response.success = True
        response.message = f'{len(models)} façades'
        return response

    def _path(self, given: str) -> str:
        path = given or self.config.persistence.map_path
        if not path:
            raise InputError('no path given and the parameter persistence.map_path is empty')
        return path

    def _save(self, path: str) -> int:
        """Save in the worker (the map is consistent between clouds); returns the version."""
        def work(fmap: FacadeMap) -> int:
            save_map(fmap, path)
            return self.worker.snapshot.version
        version = self.worker.call(work, COMMAND_TIMEOUT, changes=False)
        self._saved_version = version
        self.counters['saves'] += 1
        return version

    def save_callback(self, request: Any, response: Any) -> Any:
        """Save the map atomically (after the clouds received so far)."""
        try:
            path = self._path(request.path)
            if not Path(path).parent.exists():
                raise InputError(f'folder {Path(path).parent} does not exist')
            version = self._save(path)
            response.success, response.path = True, str(path)
            response.message = f'saved map version {version} to {path}'
        except (FacadeMapError, OSError, TimeoutError) as exc:
            response.success, response.message = False, f'not saved: {exc}'
        return response

    def load_callback(self, request: Any, response: Any) -> Any:
        """Replace the map by a map file; a bad file leaves the current map as it is."""
        try:
            path = self._path(request.path)
            loaded = load_map(path)
            self.worker.call(lambda _: ReplaceMap(loaded), COMMAND_TIMEOUT)
            response.success, response.facades = True, len(loaded.facades)
            response.message = f'loaded {path}: {len(loaded.facades)} façades, {loaded.n_points} points'
        except (FacadeMapError, OSError, TimeoutError) as exc:
            response.success, response.message = False, f'not loaded: {exc}'
        return response

    def reset_callback(self, request: Any, response: Any) -> Any:
        """Start an empty map (clouds queued before the call are mapped first, then cleared)."""
        empty = FacadeMap(self.params, np.asarray(self.config.input.map_origin, dtype=np.float64))
        try:
            self.worker.call(lambda _: ReplaceMap(empty), COMMAND_TIMEOUT)
            response.success, response.message = True, 'map cleared'
        except TimeoutError as exc:
            response.success, response.message = False, str(exc)
        return response

    def get_map_callback(self, request: Any, response: Any) -> Any:
        """nav_msgs/GetMap: the 2D occupancy grid of the height band."""
        snap = self.worker.snapshot
        response.map = self._grid_msg(snap, snap.stamp_ns or self.get_clock().now().nanoseconds)
        return response

    def autosave_callback(self) -> None:
        """Save to persistence.map_path when the map changed since the last save."""
        if not self.config.persistence.map_path or self.worker.snapshot.version == self._saved_version:
            return
        try:
            self._save(self.config.persistence.map_path)
        except (FacadeMapError, OSError, TimeoutError) as exc:
            self.last_error = f'autosave failed: {exc}'
            self.get_logger().error(self.last_error, throttle_duration_sec=30.0)

    def destroy_node(self) -> None:
        self.worker.stop()
        super().destroy_node()


def main(args: list[str] | None = None) -> None:
    """Run the node until Ctrl-C or shutdown (``ros2 run uncertain_facade_map facade_mapper``)."""
    import rclpy
    from rclpy.executors import ExternalShutdownException, MultiThreadedExecutor

    rclpy.init(args=args)
    node = None
    try:
        node = FacadeMapperNode()
        executor = MultiThreadedExecutor(num_threads=4)
        executor.add_node(node)
        executor.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except FacadeMapError as exc:
        import sys

        print(f'facade_mapper: {exc}', file=sys.stderr)
        raise SystemExit(2) from None
    finally:
        if node is not None:
            node.destroy_node()
        if rclpy.ok():
            rclpy.shutdown()


if __name__ == '__main__':
    main()
