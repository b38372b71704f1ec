"""The ``facade_mapper`` node: live façade mapping from classified building PointCloud2.

Wiring of parts, as octomap_server's node composes tf2's buffer, listener and message filter
(topics, services and parameters: docs/node.md):

- :class:`~uncertain_facade_map_node.listener.PoseListener`: ``sensor_pose``, ``/tf``,
  ``/tf_static`` and odometry into one transform buffer;
- :class:`~uncertain_facade_map.mapping.gate.CloudGate`: a received cloud waits for its
  transform, is placed, reduced to its building points and handed to the worker, in a thread
  of its own (``points`` only converts and counts, so clouds are taken in at the sensor's rate);
- :class:`~uncertain_facade_map.mapping.worker.MapWorker`: owns the map and models it (in a
  mapping process, ``node.mapping_process``), so no callback ever refits a model;
- :class:`~uncertain_facade_map.tiling.serving.ServedMap`: the live snapshot, its reading and a
  tiled map beside it: what the services read, save and load;
- :class:`~uncertain_facade_map_node.publisher.MapPublisher`: the latched map products;
- :class:`~uncertain_facade_map.mapping.accounts.Accounts`: counters that add up,
  ``/diagnostics`` and the summary line every ``node.log_period`` s.

No exception escapes a callback: a failure is logged, counted (``callback_errors``) and
answered as a failure. Input that cannot be right is refused and counted before it reaches
the map; an update that fails anyway leaves the map as it was (the worker rolls back).
"""

from __future__ import annotations

import sys
import time
from typing import Any

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from nav_msgs.srv import GetMap
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup, ReentrantCallbackGroup
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from sensor_msgs.msg import PointCloud2
from std_srvs.srv import Trigger

import msg_adapters as ma
from msg_adapters import map_messages as mm
from uncertain_facade_map.errors import FacadeMapError, InputError
from uncertain_facade_map.io.map_file import remove_stale_temporaries
from uncertain_facade_map.io.scans import Scan
from uncertain_facade_map.mapping.accounts import Accounts
from uncertain_facade_map.mapping.allocator import limit_heap_growth, release_free_memory
from uncertain_facade_map.mapping.gate import CloudGate, Outcome
from uncertain_facade_map.mapping.served import ServedReading
from uncertain_facade_map.mapping.worker import Cloud, MapWorker
from uncertain_facade_map.params import NODE_NAME, Config
from uncertain_facade_map.srv import GetFacades, ListTiles, LoadMap, QueryPoints, SaveMap
from uncertain_facade_map.tiling.manifest import is_tiled_map
from uncertain_facade_map.tiling.serving import ServedMap, initial_map
from uncertain_facade_map_node.listener import PoseListener
from uncertain_facade_map_node.publisher import MapPublisher
from uncertain_facade_map_node.replay import dds_profile_hint
from uncertain_facade_map_node.runtime import ServiceCheck, declare_config, failed, guarded, spin

#: Seconds between the interpreter's thread switches in the node (Python's default: 0.005).
SWITCH_INTERVAL = 0.0005


def _sensor_qos(config: Any) -> QoSProfile:
    """The clouds' QoS: best effort (sensor data) or reliable; either way the reader keeps as
    many clouds as the node's queue (up to 100: DDS holds them whole, whatever their size)."""
    depth = min(max(10, config.queue_size), 100)
    if config.qos == 'reliable':
        return QoSProfile(depth=depth, reliability=ReliabilityPolicy.RELIABLE)
    return QoSProfile(depth=depth, reliability=qos_profile_sensor_data.reliability,
                      durability=qos_profile_sensor_data.durability, history=qos_profile_sensor_data.history)


class FacadeMapperNode(Node):
    """Subscribes to building clouds, maps them in a worker, publishes and serves the map."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(NODE_NAME, **kwargs)
        try:
            self.config: Config = declare_config(self)
        except InputError as exc:
            self.get_logger().fatal(f'bad parameters: {exc}')
            raise
        cfg = self.config
        self.frame_id = cfg.input.frame_id
        self.stopping = False  # set by destroy_node: callbacks still running then fail quietly
        self.types = mm.rclpy_map_types()
        self.accounts = Accounts(self.get_logger().warning)
        path = cfg.persistence.map_path
        if path and not is_tiled_map(path):
            for stale in remove_stale_temporaries(path):
                self.get_logger().warning(f'removed {stale}, the temporary file of a save that did not finish')
        fmap, tiled = initial_map(cfg, self.get_logger().info)  # a damaged file stops the node
        self.worker = MapWorker(fmap, cfg.node.queue_size, on_error=self._cloud_failed, idle_flush=cfg.node.idle_flush,
                                on_flush=self._flushed, on_flush_error=self._flush_failed,
                                process=cfg.node.mapping_process, nice=cfg.node.mapping_nice,
                                queue_points=cfg.node.queue_points, batching=cfg.node.batching)
        self.reading = ServedReading(self.worker, cfg.query, cfg.node, on_error=self._reading_failed)
        self.listener = PoseListener(self, cfg.node, self.accounts)
        self._cloud_frame = ''  # the frame of the latest cloud (the tiles' last choice of a pose)
        self.served = ServedMap(self.worker, self.reading, cfg, tiled, self._pose_xy, self.accounts.warn)
        self.publisher = MapPublisher(self, cfg, self.frame_id, self.reading, self.accounts, self.types)
        self.gate = CloudGate(self.listener.buffer, self.frame_id, cfg, self.worker, self.accounts,
                              on_outcome=self._outcome,
                              on_error=lambda exc: failed(self, self.accounts, 'cloud gate', exc)).start()
        self.pub_diag = self.create_publisher(DiagnosticArray, '/diagnostics', 10)

        self.create_subscription(PointCloud2, 'points', self.points_callback, _sensor_qos(cfg.node),
                                 callback_group=MutuallyExclusiveCallbackGroup())
        services = ((QueryPoints, 'query_points', self.query_callback),  # relative names (remap with -r)
                    (GetFacades, 'get_facades', self.get_facades_callback),
                    (SaveMap, 'save_map', self.save_callback),
                    (LoadMap, 'load_map', self.load_callback),
                    (Trigger, 'reset', self.reset_callback),
                    (GetMap, 'get_map', self.get_map_callback),
                    (ListTiles, 'list_tiles', self.list_tiles_callback))
        group = ReentrantCallbackGroup()
        for kind, name, callback in services:
            self.create_service(kind, name, callback, callback_group=group)
        # Each timer in a group of its own: a long publication must not hold up diagnostics.
        for period, callback in ((max(0.05, min(cfg.publish.period, 1.0) or 0.1), self.publish_callback),
                                 (cfg.publish.diagnostics_period, self.diagnostics_callback),
                                 (cfg.node.log_period, self.summary_callback),
                                 (cfg.persistence.autosave_period, self.autosave_callback)):
            if period > 0:
                self.create_timer(period, callback, callback_group=MutuallyExclusiveCallbackGroup())
        self.service_check = ServiceCheck(self, tuple(name for _, name, _ in services),
                                          MutuallyExclusiveCallbackGroup())
        snap = self.worker.snapshot
        self.accounts.start_summary(self.worker)
        self.get_logger().info(f'mapping clouds on "{self.resolve_topic_name("points")}" into frame "{self.frame_id}" '
                               f'with the transforms of {", ".join(self.listener.sources)}; '
                               f'{len(snap.facades)} façades, {snap.points} points to start with')

    def _pose_xy(self) -> np.ndarray | None:
        """Where the tiles follow: ``tiles.follow_frame``, else the sensor of the latest pose
        message, else the frame of the latest cloud (map-frame x, y; None: none placed yet)."""
        return self.listener.xy(self.frame_id, self.config.tiles.follow_frame, self.listener.follow_frame,
                                self._cloud_frame)

    # -- clouds ---------------------------------------------------------------------------
    @guarded
    def points_callback(self, msg: Any) -> None:
        """Count and convert a cloud and hand it to the gate (which places and selects it).

        Every cloud is counted once: received, then rejected, mapped without building
        points, or handed to the worker (which counts it mapped, dropped or failed); while
        it waits for its transform it counts as waiting.
        """
        n = int(msg.width) * int(msg.height)
        frame, stamp = str(msg.header.frame_id), ma.header_stamp_ns(msg.header)
        self._cloud_frame = frame
        scan: Scan | None = None
        why = ''
        try:  # converted before the lock: the gate and the diagnostics wait for the lock only
            scan = self._scan(msg, n, stamp)
        except (InputError, ValueError, TypeError) as exc:
            why = str(exc)
        with self.accounts.lock:  # counted received and queued (or rejected) at one moment
            missed = self.accounts.received(frame, stamp, n)
            if scan is not None:
                self.gate.add(scan, n)
            else:
                self.accounts.reject(why, n)
        hint = dds_profile_hint(len(msg.data)) if missed else None
        if hint is not None:
            self.accounts.warn(f'about {missed} clouds of "{msg.header.frame_id}" were lost before they reached the '
                               f'node (a gap in their stamps); {hint}', 'dds losses', 60.0)

    def _scan(self, msg: Any, n: int, stamp: int) -> Scan:
        """A cloud of ``n`` points as a scan (its points, frame and ``stamp``, ns); InputError
        when it cannot be one."""
        cfg = self.config
        if n > cfg.node.max_cloud_points:
            raise InputError(f'{n:,} points, more than node.max_cloud_points = {cfg.node.max_cloud_points:,}')
        if n == 0:
            raise InputError('empty cloud')
        points = ma.structured_from_pointcloud2(msg)
        names = points.dtype.names or ()
        if cfg.input.class_field not in names:
            what = ('its building points are selected (selection.mode: auto)' if cfg.selection.mode != 'off'
                    else 'every point is taken as building (selection.mode: off)')
            self.accounts.warn(f'a cloud has no field "{cfg.input.class_field}" (input.class_field; fields: '
                               f'{", ".join(names)}): {what}', 'class field', 60.0)
        return Scan.of(points, msg.header.frame_id, stamp, cfg.input)

    def _outcome(self, outcome: Outcome) -> None:
        self.get_logger().debug(outcome.line())

    @guarded
    def summary_callback(self) -> None:
        """Every ``node.log_period`` s while clouds come or the map changed: one info line of what happened."""
        line = self.accounts.summary(self.worker, self.gate, self.config.node.log_period)
        if line is not None:
            self.get_logger().info(line)

    def _flushed(self, points: int, refitted: list[int]) -> None:
        held = f'mapped the {points} points held back, ' if points else ''
        self.get_logger().info(f'input idle: {held}fitted {len(refitted)} façades whole')

    def _flush_failed(self, exc: BaseException) -> None:
        self.accounts.event('failed', f'idle flush failed: {type(exc).__name__}: {exc}')
        self.get_logger().error(f'the idle flush failed, the map is left as it was: {type(exc).__name__}: {exc}',
                                throttle_duration_sec=30.0)

    def _cloud_failed(self, cloud: Cloud, exc: BaseException) -> None:
        self.accounts.event('failed', f'mapping failed: {type(exc).__name__}: {exc}')
        self.get_logger().error(f'a cloud of {len(cloud.xyz)} points could not be mapped, the map is left as it '
                                f'was: {type(exc).__name__}: {exc}')

    def _reading_failed(self, exc: BaseException) -> None:
        self.get_logger().warning(f'building the local reading failed: {exc}', throttle_duration_sec=10.0)

    # -- publishing ---------------------------------------------------------------------
    @guarded
    def publish_callback(self) -> None:
        """Publish the maps when the map changed and the period has passed."""
        self.publisher.publish_if_due(self.worker.snapshot)

    @guarded
    def diagnostics_callback(self) -> None:
        """Publish the accounts, the map's size, update time and latency, and a level that
        tells of the recent window (``publish.diagnostics_window``)."""
        values, level, message = self.accounts.diagnostics(self.worker, self.gate, self.reading,
                                                           self.config.publish.diagnostics_window)
        values.update(self.publisher.values(self.worker.snapshot))
        values.update(self.served.tiles_values())
        self.pub_diag.publish(mm.diagnostic_array(f'{NODE_NAME}: map', level, message, values, NODE_NAME,
                                                  self.get_clock().now().nanoseconds, self.types))
        release_free_memory()  # the dropped clouds' and answered queries' buffers, back to the system

    # -- services -----------------------------------------------------------------------
    @guarded
    def query_callback(self, request: Any, response: Any) -> Any:
        """Answer a batch of 3D points from the latest snapshot (never waits for the worker)."""
        started = time.perf_counter()
        self.accounts.count('queries')
        try:
            xyz = mm.points_from_request(request, self.config.service.max_query_points)
            resolution = float(request.resolution) or self.config.query.resolution
            if not np.isfinite(resolution) or resolution <= 0:
                raise InputError(f'resolution must be a positive number of metres, got {request.resolution}')
            answers, message = self.served.query(xyz, resolution)
            mm.fill_query_response(response, answers, message, msg_types=self.types)
            self.accounts.query_seconds.append(time.perf_counter() - started)
        except FacadeMapError as exc:
            self.accounts.count('queries_failed')
            response.success, response.message = False, str(exc)
        return response

    @guarded
    def get_facades_callback(self, request: Any, response: Any) -> Any:
        """The façade models of one building (or all, building = -1); see ServedMap.facades."""
        models, note = self.served.facades(int(request.building))
        response.facades = [mm.facade_msg(f, self.types) for f in models]
        response.success, response.message = True, f'{len(models)} façades{note}'
        return response

    @guarded
    def list_tiles_callback(self, request: Any, response: Any) -> Any:
        """The served tiled map's tiles near a map-frame position (ids, squares, files, loaded)."""
        try:
            found = self.served.tiles_near(np.array([request.x, request.y], dtype=np.float64), request.radius)
            mm.fill_list_tiles_response(response, *found, msg_types=self.types)
        except FacadeMapError as exc:
            response.success, response.message = False, str(exc)
        return response

    @guarded
    def save_callback(self, request: Any, response: Any) -> Any:
        """Save the map atomically, at once, into the map folder: the clouds mapped so far and
        the points held back; the message says how many received clouds are not in it."""
        try:
            path = self.served.save_path(request.path)
            version, waiting = self.served.save(path)
            self.accounts.count('saves')
            response.success, response.path = True, str(path)
            response.message = (f'saved map version {version} to {path}'
                                + (f'; {waiting} received clouds still wait and are not in it' if waiting else ''))
        except (FacadeMapError, OSError) as exc:
            response.success, response.message = False, f'not saved: {exc}'
        return response

    @guarded
    def load_callback(self, request: Any, response: Any) -> Any:
        """Replace the map by a map file, or serve a tiled map beside an empty live map."""
        try:
            facades, message = self.served.load(request.path)
            response.success, response.facades, response.message = True, min(facades, 2**32 - 1), message
        except (FacadeMapError, OSError, TimeoutError) as exc:
            response.success, response.message = False, f'not loaded: {exc}'
        return response

    @guarded
    def reset_callback(self, request: Any, response: Any) -> Any:
        """Start an empty map (clouds queued before the call are mapped first, then cleared)."""
        try:
            self.served.reset()
            response.success, response.message = True, 'map cleared'
        except TimeoutError as exc:
            response.success, response.message = False, str(exc)
        return response

    @guarded
    def get_map_callback(self, request: Any, response: Any) -> Any:
        """nav_msgs/GetMap: the 2D occupancy grid of the height band."""
        snap = self.worker.snapshot
        response.map = self.publisher.grid_msg(snap, snap.stamp_ns or self.get_clock().now().nanoseconds)
        return response

    @guarded
    def autosave_callback(self) -> None:
        """Save to persistence.map_path when the map changed since the last save."""
        try:
            if self.served.autosave():
                self.accounts.count('saves')
        except (FacadeMapError, OSError) as exc:
            self.accounts.event('failed', f'autosave failed: {exc}')
            self.get_logger().error(f'autosave failed: {exc}', throttle_duration_sec=30.0)

    def destroy_node(self) -> None:
        self.stopping = True  # callbacks still running fail quietly from now on (see guarded)
        self.gate.stop()
        waiting = self.accounts.values(self.worker, self.gate)['clouds_waiting']
        if waiting:
            self.get_logger().warning(f'stopping: {waiting} received clouds were still waiting and are not mapped')
        self.served.close()
        self.worker.stop()
        self.publisher.close()
        super().destroy_node()


def main(args: list[str] | None = None) -> None:
    """Run the node until Ctrl-C or shutdown (``ros2 run uncertain_facade_map facade_mapper``)."""
    limit_heap_growth()  # before rclpy starts its threads
    # Queries and input share this interpreter with the worker thread (and, with
    # node.mapping_process false, with the mapping itself): at the default 5 ms a query's
    # numpy calls each wait up to a switch interval for the lock while another thread runs
    # Python code; 0.5 ms shortens those waits.
    sys.setswitchinterval(SWITCH_INTERVAL)
    spin(FacadeMapperNode, NODE_NAME, args, threads=4)


if __name__ == '__main__':
    main()
