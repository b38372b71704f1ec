"""The ``facade_mapper`` node: live façade mapping from classified building PointCloud2.

A thin shell: :mod:`msg_adapters` turns messages into arrays and back, the core
(:mod:`uncertain_facade_map`) does all the modelling, and a
:class:`~uncertain_facade_map.mapping.worker.MapWorker` thread owns the map, so no callback
ever refits a model.

Topics (names relative, remap with ``--ros-args -r``):

- subscribed: ``points`` (sensor_msgs/PointCloud2 in any frame, QoS ``node.qos``), and the
  poses that put a cloud's frame into the map frame, all into one
  :class:`~uncertain_facade_map.transforms.TransformBuffer` (tf2's BufferCore semantics; tf2
  itself is not in the wheel set): ``/tf`` and ``/tf_static`` (tf2_msgs/TFMessage, the
  static ones transient local, ``node.use_tf``), ``sensor_pose``
  (geometry_msgs/TransformStamped) and ``node.odometry_topic`` (nav_msgs/Odometry);
- published, transient-local (a late subscriber gets the last map): ``surface``
  (PointCloud2 x, y, z, std, facade), ``surface_mesh`` (visualization_msgs/MarkerArray),
  ``variance_grids`` (uncertain_facade_map/FacadeGridArray), ``occupancy_voxels``
  (PointCloud2 x, y, z, p_occupied), ``occupancy_grid`` (nav_msgs/OccupancyGrid);
  and ``/diagnostics`` (diagnostic_msgs/DiagnosticArray).

Services: ``query_points`` (uncertain_facade_map/QueryPoints), ``get_facades``
(uncertain_facade_map/GetFacades), ``save_map`` / ``load_map``
(uncertain_facade_map/SaveMap, LoadMap), ``reset`` (std_srvs/Trigger), ``get_map``
(nav_msgs/GetMap, the 2D grid) and ``list_tiles`` (uncertain_facade_map/ListTiles).

A tiled map (a folder with ``manifest.json``, or the manifest; ``persistence.map_path`` or
``load_map``) is served read-only beside the live map, its tiles loaded on demand and near
the node's pose (``tiles.*``): see :mod:`uncertain_facade_map_node.tiled`. Their names are relative: two mappers in one domain need
namespaces (``--ros-args -r __ns:=/robot1``); the node warns when another node already
offers one of its services under the same name. No exception escapes a callback: a
failure is logged, counted (``callback_errors``) and answered as a failure.

A cloud not in the map frame waits for its transform (at its stamp and its points' times,
``input.time_field``) in a queue of its own (``node.transform_queue``, at most
``node.transform_timeout`` s) while the poses come in on another callback group; then it is
placed, moved into the map frame and reduced to its building points exactly as offline
replay does (:class:`~uncertain_facade_map.io.scans.Scan`), or rejected with the frames it
needed. Input that cannot be right is refused and counted before it reaches the map: clouds
with a coordinate beyond ``node.max_coordinate`` of the map origin (a corrupted cloud: 1e30
m, or data whose byte order differs from ``is_bigendian``, which the message then names),
poses likewise; an update that fails anyway leaves the map as it was (the worker rolls back).
What happened is logged: each cloud at debug level, a summary every ``node.log_period`` s.
"""

from __future__ import annotations

import difflib
import functools
import sys
import threading
import time
from collections import Counter, deque
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import TransformStamped
from nav_msgs.msg import OccupancyGrid, Odometry
from nav_msgs.srv import GetMap
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup, ReentrantCallbackGroup
from rclpy.exceptions import ParameterException
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from rclpy.serialization import serialize_message
from sensor_msgs.msg import PointCloud2
from std_srvs.srv import Trigger
from visualization_msgs.msg import MarkerArray

import msg_adapters as ma
from msg_adapters import map_messages as mm
from msg_adapters import parameters as mp_params
from msg_adapters import transforms as mt
from msg_adapters.published_maps import published_map_messages
from uncertain_facade_map.datatypes import array_bytes
from uncertain_facade_map.errors import FacadeMapError, InputError, TransformError
from uncertain_facade_map.io.map_file import remove_stale_temporaries, save_map
from uncertain_facade_map.io.map_folder import MapFolder
from uncertain_facade_map.io.scans import Scan, ScanPoints
from uncertain_facade_map.mapping import products as mp
from uncertain_facade_map.mapping.allocator import limit_heap_growth, release_free_memory
from uncertain_facade_map.mapping.engine import HelperProcess, unkept
from uncertain_facade_map.mapping.facade_map import FacadeMap
from uncertain_facade_map.mapping.served import ServedReading
from uncertain_facade_map.mapping.worker import Cloud, MapSnapshot, MapWorker, replace_with
from uncertain_facade_map.msg import FacadeGridArray
from uncertain_facade_map.params import (
    NODE_NAME,
    Config,
    config_from_parameters,
    map_params,
    node_sections,
    parameters,
)
from uncertain_facade_map.pipeline.step8_occupancy import PLSC, occupancy_model
from uncertain_facade_map.srv import GetFacades, ListTiles, LoadMap, QueryPoints, SaveMap
from uncertain_facade_map.tiling.manifest import is_tiled_map
from uncertain_facade_map.tiling.tiled_map import TiledMap, open_map
from uncertain_facade_map.transforms import Placement, TransformBuffer
from uncertain_facade_map_node import tiled as nt
from uncertain_facade_map_node.replay import dds_profile_hint

#: Seconds a service waits for the map worker (load, reset) before answering "busy".
COMMAND_TIMEOUT = 120.0
#: Seconds between the interpreter's thread switches in the node (Python's default: 0.005).
SWITCH_INTERVAL = 0.0005
#: Seconds between the node's looks for other nodes offering its services, after start.
SERVICE_CHECK_DELAY = 3.0
#: How many looks (discovery may take several seconds; a warning ends them).
SERVICE_CHECKS = 20
#: Parameters every rclpy node has, besides the declared ones.
_BUILTIN_PARAMETERS = frozenset({'use_sim_time', 'start_type_description_service'})
#: Seconds between the looks at the clouds waiting for their transform.
TRANSFORM_POLL = 0.01
#: Kinds of event that make the diagnostic level WARN while they are recent.
_WARN_EVENTS = ('dropped', 'rejected', 'failed', 'callback_error')


def declare_config(node: Any, sections: tuple[str, ...] | None = None) -> Config:
    """Declare every parameter of ``sections`` (default: the mapper's, :func:`node_sections`) on
    ``node`` (read-only, with its descriptor) and read the configuration (the other
    sections at their defaults).

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
    for info in parameters(sections=node_sections() if sections is None else sections):
        default = list(info.value) if info.is_list else info.value
        try:
            node.declare_parameter(info.name, default, mp_params.parameter_descriptor(info, types))
        except ParameterException as exc:
            raise InputError(f'parameter {info.name}: {" ".join(str(exc).split())} '
                             f'(allowed: {info.spec.constraint_text() or "any " + info.type.__name__})') from exc
        values[info.name] = mp_params.parameter_value(node.get_parameter(info.name).value)
    _refuse_unknown_overrides(node, set(values))
    return config_from_parameters(values)


def _refuse_unknown_overrides(node: Any, declared: set[str]) -> None:
    """Raise InputError for a ``-p`` or parameter-file override that names no parameter
    (rclpy would ignore it silently), with the closest declared names."""
    overrides = getattr(node, '_parameter_overrides', None) or {}
    unknown = sorted(set(overrides) - declared - _BUILTIN_PARAMETERS)
    if unknown:
        name = unknown[0]
        close = difflib.get_close_matches(name, sorted(declared), n=3, cutoff=0.6)
        hint = f'; did you mean {" or ".join(close)}?' if close else ''
        more = f' (and {", ".join(unknown[1:])})' if len(unknown) > 1 else ''
        raise InputError(f'unknown parameter {name}{more}{hint}')


def _stamp_ns(header: Any) -> int:
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def _guarded(callback: Callable[..., Any]) -> Callable[..., Any]:
    """No exception escapes ``callback`` (it would end the executor, and the node): it is
    logged and counted, and a service answers ``success = False`` with the reason."""
    @functools.wraps(callback)
    def run(self: FacadeMapperNode, *args: Any) -> Any:
        try:
            return callback(self, *args)
        except Exception as exc:  # noqa: BLE001 - the node must live on
            if self._stopping or not self.context.ok():
                # Shutting down (Ctrl-C): the context, publishers and helper processes are going, not broken.
                return args[1] if len(args) == 2 else None
            self._event('callback_error', f'{callback.__name__} failed: {type(exc).__name__}: {exc}')
            self.get_logger().error(f'{callback.__name__} failed: {type(exc).__name__}: {exc}',
                                    throttle_duration_sec=5.0)
            response = args[1] if len(args) == 2 else None
            if response is not None and hasattr(response, 'success'):
                response.success = False
                if hasattr(response, 'message'):
                    response.message = f'internal error: {type(exc).__name__}: {exc}'
            return response
    return run


@dataclass
class _Waiting:
    """A received cloud waiting for its transform into the map frame."""

    scan: Scan
    points: int  # width * height
    arrived: float  # time.monotonic()


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
        self.counters = {'clouds_received': 0, 'points_received': 0, 'clouds_rejected': 0, 'points_rejected': 0,
                         'clouds_no_building': 0, 'points_nonfinite': 0, 'points_not_building': 0,
                         'clouds_missed_estimate': 0, 'queries': 0, 'queries_failed': 0,
                         'saves': 0, 'callback_errors': 0, 'clouds_no_transform': 0}
        # The pose callbacks count under a lock of their own: _count_lock is held while a cloud
        # is placed and selected, and a pose must never wait for that.
        self.pose_counters = {'poses_rejected': 0, 'transforms_received': 0}
        self._pose_count_lock = threading.Lock()
        self._count_lock = threading.Lock()
        self._events: deque[tuple[float, str, str]] = deque(maxlen=1000)  # (monotonic, kind, text)
        self._last_stamp: dict[str, tuple[int, deque[int]]] = {}  # frame -> (last stamp, recent periods)
        self._warned: dict[str, float] = {}
        # Every pose source feeds one buffer (it has its own lock: the pose callbacks run beside the clouds').
        self.transforms = TransformBuffer(cache_time=cfg.node.transform_cache, max_samples=cfg.node.pose_buffer)
        self._waiting: deque[_Waiting] = deque()  # clouds waiting for their transform, in arrival order
        self._interval = self._new_interval()  # what the next summary line tells
        self._summary_version = -1  # the map version the last summary line told of (set at the end)
        self._summary_mapped = 0  # the worker's clouds mapped at the last summary line
        self._stopping = False  # set by destroy_node: callbacks still running then fail quietly
        self._grid: tuple[int, Any] | None = None
        self._facades_size: tuple[int, float] = (-1, 0.0)  # (snapshot version, MB of its façade arrays)
        self._published_bytes = 0  # of the latest published maps (serialized; the grid's cells)
        self._query_seconds: deque[float] = deque(maxlen=200)  # time in the node of the latest queries
        self._published_version = -1
        self._saved_version = 0
        self._last_publish = 0.0
        self._publish_lock = threading.Lock()
        self._save_lock = threading.Lock()

        # The tiled map served read-only (None: none), the path it was opened from, and the
        # thread keeping the tiles near the pose loaded; replaced together under _tiled_lock.
        self._tiled: TiledMap | None = None
        self._tiled_path = ''
        self._follower: nt.TileFollower | None = None
        self._tiled_lock = threading.Lock()
        self._follow_frame = ''  # the frame whose pose the follower takes (latest sensor_pose / odometry child)
        self._cloud_frame = ''  # the frame of the latest cloud (the follower's fallback)
        per = cfg.persistence
        # Where save_map and load_map read and write (any DDS participant may call them).
        self.map_folder = MapFolder.of(per.map_dir, per.map_path, per.allow_any_path, per.max_load_mb)
        tiled_start = bool(cfg.persistence.map_path) and is_tiled_map(cfg.persistence.map_path)
        for stale in remove_stale_temporaries(cfg.persistence.map_path) if cfg.persistence.map_path \
                and not tiled_start else ():
            self.get_logger().warning(f'removed {stale}, the temporary file of a save that did not finish')
        fmap = self._initial_map()
        # The published maps are computed in a helper process too: their numpy work would
        # hold this process's interpreter lock for seconds on a large map.
        self._helper = HelperProcess('facade_products', cfg.node.mapping_nice) if cfg.node.mapping_process else None
        self.worker = MapWorker(fmap, cfg.node.queue_size, on_error=self._cloud_failed, idle_flush=cfg.node.idle_flush,
                               on_flush=self._flushed, on_flush_error=self._flush_failed,
                               process=cfg.node.mapping_process, nice=cfg.node.mapping_nice,
                               queue_points=cfg.node.queue_points, batching=cfg.node.batching)
        # The per-point reading the queries read, and when it is built again.
        self.reading = ServedReading(self.worker, cfg.query, cfg.node, on_error=self._reading_failed)

        latched = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL,
                             reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST)
        self.pub_surface = self.create_publisher(PointCloud2, 'surface', latched)
        self.pub_mesh = self.create_publisher(MarkerArray, 'surface_mesh', latched)
        self.pub_grids = self.create_publisher(FacadeGridArray, 'variance_grids', latched)
        self.pub_voxels = self.create_publisher(PointCloud2, 'occupancy_voxels', latched)
        self.pub_grid = self.create_publisher(OccupancyGrid, 'occupancy_grid', latched)
        self.pub_diag = self.create_publisher(DiagnosticArray, '/diagnostics', 10)

        # Best effort (sensor data) or reliable; either way the reader keeps as many clouds as the
        # node's queue (up to 100: DDS holds them whole, whatever their size), so that a cloud
        # placed or selected for a while (0.1-0.5 s) does not make DDS drop the ones behind it
        # unseen (sensor data's own depth is 5).
        depth = min(max(10, cfg.node.queue_size), 100)
        qos = QoSProfile(depth=depth, reliability=ReliabilityPolicy.RELIABLE) if cfg.node.qos == 'reliable' else \
            QoSProfile(depth=depth, reliability=qos_profile_sensor_data.reliability,
                       durability=qos_profile_sensor_data.durability, history=qos_profile_sensor_data.history)
        # Clouds (and their wait for a transform) in one group, poses in another: a cloud's
        # selection must never hold up the pose it waits for.
        inputs = MutuallyExclusiveCallbackGroup()
        self.create_subscription(PointCloud2, 'points', self.points_callback, qos, callback_group=inputs)
        self.create_timer(TRANSFORM_POLL, self.waiting_callback, callback_group=inputs)
        poses = MutuallyExclusiveCallbackGroup()
        self.create_subscription(TransformStamped, 'sensor_pose', self.pose_callback, 100, callback_group=poses)
        self._pose_sources = ['sensor_pose']
        if cfg.node.use_tf:
            self._subscribe_tf(poses)
        if cfg.node.odometry_topic:
            self.create_subscription(Odometry, cfg.node.odometry_topic, self.odometry_callback, 100,
                                     callback_group=poses)
            self._pose_sources.append(cfg.node.odometry_topic)
        if cfg.node.log_period > 0:
            self.create_timer(cfg.node.log_period, self.summary_callback, callback_group=MutuallyExclusiveCallbackGroup())
        services = ReentrantCallbackGroup()
        self.create_service(QueryPoints, 'query_points', self.query_callback, callback_group=services)
        self.create_service(GetFacades, 'get_facades', self.get_facades_callback, callback_group=services)
        self.create_service(SaveMap, 'save_map', self.save_callback, callback_group=services)
        self.create_service(LoadMap, 'load_map', self.load_callback, callback_group=services)
        self.create_service(Trigger, 'reset', self.reset_callback, callback_group=services)
        self.create_service(GetMap, 'get_map', self.get_map_callback, callback_group=services)
        self.create_service(ListTiles, 'list_tiles', self.list_tiles_callback, callback_group=services)
        # Each timer in a group of its own: a long publication must not hold up diagnostics.
        self.create_timer(max(0.05, min(cfg.publish.period, 1.0) or 0.1), self.publish_callback,
                          callback_group=MutuallyExclusiveCallbackGroup())
        self.create_timer(cfg.publish.diagnostics_period, self.diagnostics_callback,
                          callback_group=MutuallyExclusiveCallbackGroup())
        if cfg.persistence.autosave_period > 0:
            self.create_timer(cfg.persistence.autosave_period, self.autosave_callback,
                              callback_group=MutuallyExclusiveCallbackGroup())
        self._service_names = ('query_points', 'get_facades', 'save_map', 'load_map', 'reset', 'get_map', 'list_tiles')
        self._service_checks = 0
        self._service_check = self.create_timer(SERVICE_CHECK_DELAY, self.service_check_callback,
                                                callback_group=MutuallyExclusiveCallbackGroup())
        snap = self.worker.snapshot
        self._summary_version = snap.version
        if self._tiled is not None:
            self._start_follower()
        self.get_logger().info(f'mapping clouds on "{self.resolve_topic_name("points")}" into frame "{self.frame_id}" '
                               f'with the transforms of {", ".join(self._pose_sources)}; '
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
            # A damaged file (or a folder that is no tiled map) stops the node: better than mapping over it.
            opened = self._open_map(path)
            if isinstance(opened, TiledMap):
                self._tiled, self._tiled_path = opened, str(path)
                self.get_logger().info(f'serving the tiled map {path} read-only: {len(opened.manifest_.tiles)} tiles, '
                                       f'at most {cfg.tiles.cache_mb:g} MB loaded; persistence.map_path is not '
                                       'autosaved, save_map needs a path; clouds map into a live map')
                return self._live_map_for(opened)
            self.get_logger().info(f'loaded {path}: {len(opened.facades)} façades, {opened.n_points} points')
            return opened
        if path:
            self.get_logger().info(f'{path} does not exist yet; starting an empty map')
        return FacadeMap(self.params, np.asarray(cfg.input.map_origin, dtype=np.float64))

    def _open_map(self, path: str) -> FacadeMap | TiledMap:
        """A map file, or a tiled map read through ``tiles.cache_mb`` and ``tiles.view_tiles``.

        Raises:
            InputError: a damaged file or manifest, a folder without a manifest (one line each).
        """
        t = self.config.tiles
        return TiledMap(path, t.cache_mb, t.view_tiles) if is_tiled_map(path) else open_map(path, t.cache_mb)

    @staticmethod
    def _live_map_for(tiled: TiledMap) -> FacadeMap:
        """The empty live map beside a served tiled map: its parameters and map origin."""
        return FacadeMap(tiled.params, np.asarray(tiled.map_origin, dtype=np.float64).copy())

    def _start_follower(self) -> None:
        """Follow the pose for the served tiled map (``tiles.follow_period`` > 0)."""
        if self._tiled is None:
            return
        follower = nt.TileFollower(self._tiled, self.config.tiles, self._pose_xy,
                                   lambda text: self._warn(text, 'tile follower', period=30.0), self.config.query)
        self._follower = follower
        follower.start()

    def _serve_tiled(self, tiled: TiledMap | None, path: str = '') -> None:
        """Serve ``tiled`` (None: no tiled map) from now on, stopping the previous follower."""
        with self._tiled_lock:
            old = self._follower
            self._tiled, self._tiled_path, self._follower = tiled, str(path), None
            if old is not None:
                old.stop()
            if tiled is not None:
                self._start_follower()

    def _pose_xy(self) -> np.ndarray | None:
        """The latest map-frame (x, y) of the frame the tiles follow: ``tiles.follow_frame`` when
        set and the transform buffer holds it (a robot publishing /tf only), else the child frame
        of the latest ``sensor_pose`` or odometry message, else the frame of the latest cloud;
        None while the transform buffer cannot put any of them in the map frame."""
        for frame in (self.config.tiles.follow_frame, self._follow_frame, self._cloud_frame):
            if not frame or frame == self.frame_id:
                continue
            try:
                return np.asarray(self.transforms.lookup(self.frame_id, frame, 0).translation, dtype=np.float64)[:2]
            except TransformError:
                continue
        return None

    def _tiled_target(self, path: str) -> bool:
        """True when ``path`` is the served tiled map or a tiled map (never saved over)."""
        return is_tiled_map(path) or (bool(self._tiled_path) and Path(path).resolve() == Path(self._tiled_path).resolve())

    # -- input ------------------------------------------------------------------------
    def _warn(self, text: str, key: str, period: float = 5.0) -> None:
        """Log a warning, at most once per ``period`` seconds for each kind ``key``."""
        now = time.monotonic()
        if now - self._warned.get(key, -1e9) >= period:
            self._warned[key] = now
            self.get_logger().warning(text)

    def _event(self, kind: str, text: str) -> None:
        """Remember a drop, rejection or failure for the diagnostics' recent window."""
        self._events.append((time.monotonic(), kind, text))
        if kind == 'callback_error':
            with self._count_lock:
                self.counters['callback_errors'] += 1

    def _reject(self, why: str, points: int, kind: str | None = None) -> None:
        """Count a refused cloud of ``points`` points (the caller holds ``_count_lock``);
        ``kind`` names the reason in the summary line (default: the reason's first words)."""
        self.counters['clouds_rejected'] += 1
        self.counters['points_rejected'] += points
        self._interval['rejected'][kind or why.split(':')[0][:40]] += 1
        self._event('rejected', f'cloud rejected: {why}')
        self._warn(f'cloud rejected: {why}', kind or why.split(':')[0][:30])

    def _count_gap(self, frame: str, stamp: int, size: int = 0) -> None:
        """Estimate clouds lost before they reached the node from the gaps between stamps
        (a gap of k typical periods means k - 1 lost). The typical period is the 10th
        percentile of the last 50 gaps: when most clouds are lost the median gap is itself
        a gap, the short ones are still the sensor's period. Large clouds (``size`` bytes)
        lost without the DDS profile for large clouds get a warning pointing to it."""
        last, periods = self._last_stamp.get(frame, (None, deque(maxlen=50)))
        if last is not None and stamp > last:
            gap = stamp - last
            if len(periods) >= 5:
                typical = float(np.percentile(periods, 10))
                if typical > 0 and gap > 1.5 * typical:
                    missed = int(round(gap / typical)) - 1
                    self.counters['clouds_missed_estimate'] += missed
                    hint = dds_profile_hint(size)
                    if hint is not None:
                        self._warn(f'about {missed} clouds of "{frame}" were lost before they reached the node (a gap '
                                   f'in their stamps); {hint}', 'dds losses', period=60.0)
            periods.append(gap)
        if last is None or stamp > last:
            self._last_stamp[frame] = (stamp, periods)

    # -- poses ------------------------------------------------------------------------
    def _subscribe_tf(self, group: Any) -> None:
        """Subscribe to /tf and /tf_static as tf2's TransformListener does (depth 100; static
        transient local), if tf2_msgs imports."""
        try:
            from tf2_msgs.msg import TFMessage
        except ImportError:
            self.get_logger().warning('tf2_msgs does not import: /tf and /tf_static are not read (node.use_tf); '
                                      'clouds in other frames need sensor_pose or node.odometry_topic')
            return
        dynamic = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
        static = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE,
                            durability=DurabilityPolicy.TRANSIENT_LOCAL)
        self.create_subscription(TFMessage, '/tf', self.tf_callback, dynamic, callback_group=group)
        self.create_subscription(TFMessage, '/tf_static', self.tf_static_callback, static, callback_group=group)
        self._pose_sources += ['/tf', '/tf_static']

    def _reject_pose(self, source: str, why: str) -> None:
        with self._pose_count_lock:
            self.pose_counters['poses_rejected'] += 1
        self._event('rejected', f'{source} rejected: {why}')
        self._warn(f'{source} rejected: {why}', f'pose {source} {why[:20]}')

    def _add_poses(self, msg: Any, source: str, static: bool = False) -> None:
        """Put the transforms of a message into the buffer; refuse (and count) the bad ones."""
        try:
            transforms = mt.stamped_transforms(msg)
        except (InputError, ValueError, TypeError) as exc:
            self._reject_pose(source, str(exc))
            return
        bound = self.config.node.max_coordinate
        for t in transforms:
            if not np.all(np.abs(t.translation) <= bound):
                self._reject_pose(source, f'"{t.parent}" -> "{t.child}": translation {t.translation.tolist()} beyond '
                                          f'node.max_coordinate = {bound:g} m')
                continue
            try:
                self.transforms.set_transform(t.parent, t.child, t.stamp_ns, t.translation, t.rotation, static=static)
            except TransformError as exc:
                self._reject_pose(source, str(exc))
                continue
            with self._pose_count_lock:
                self.pose_counters['transforms_received'] += 1
            if source != '/tf' and not static:
                self._follow_frame = t.child  # sensor_pose and odometry: the sensor's pose

    @_guarded
    def pose_callback(self, msg: Any) -> None:
        """A pose of a frame (``child_frame_id``) in another (``header.frame_id``), into the transforms."""
        self._add_poses(msg, 'sensor_pose')

    @_guarded
    def tf_callback(self, msg: Any) -> None:
        """The transforms of /tf."""
        self._add_poses(msg, '/tf')

    @_guarded
    def tf_static_callback(self, msg: Any) -> None:
        """The static transforms of /tf_static."""
        self._add_poses(msg, '/tf_static', static=True)

    @_guarded
    def odometry_callback(self, msg: Any) -> None:
        """The pose of an odometry message (``child_frame_id`` in ``header.frame_id``)."""
        self._add_poses(msg, self.config.node.odometry_topic)

    # -- clouds -------------------------------------------------------------------------
    @staticmethod
    def _new_interval() -> dict[str, Any]:
        return {'in': 0, 'queued': 0, 'rejected': Counter(), 'dropped': 0, 'non_ground': 0, 'selected': 0,
                'notes': Counter(), 'points': 0, 'building': 0}

    @_guarded
    def points_callback(self, msg: Any) -> None:
        """Check and convert a cloud, and queue it for its transform (then the worker).

        Every cloud is counted once: received, then rejected, mapped without building
        points, or handed to the worker (which counts it mapped, dropped or failed); while
        it waits for its transform it counts as waiting.
        """
        with self._count_lock:  # the diagnostics read the counts between two clouds
            n = int(msg.width) * int(msg.height)
            self.counters['clouds_received'] += 1
            self.counters['points_received'] += n
            self._interval['in'] += 1
            self._count_gap(msg.header.frame_id, _stamp_ns(msg.header), len(msg.data))
            self._cloud_frame = str(msg.header.frame_id)
            why = self._receive(msg, n)
            if why is not None:
                self._reject(why, n)
            self._drain()

    @_guarded
    def waiting_callback(self) -> None:
        """Map the clouds whose transform has come; reject those that waited too long."""
        if self._waiting:
            with self._count_lock:
                self._drain()

    def _receive(self, msg: Any, n: int) -> str | None:
        """Queue a cloud to wait for its transform; returns why it was refused, or None."""
        cfg = self.config
        if n > cfg.node.max_cloud_points:
            return f'{n:,} points, more than node.max_cloud_points = {cfg.node.max_cloud_points:,}'
        if n == 0:
            return 'empty cloud'
        try:
            points = ma.structured_from_pointcloud2(msg)
            scan = Scan.of(points, msg.header.frame_id, _stamp_ns(msg.header), cfg.input)
        except (InputError, ValueError, TypeError) as exc:
            return str(exc)
        names = points.dtype.names or ()
        if cfg.input.class_field not in names:
            what = ('its building points are selected (selection.mode: auto)' if cfg.selection.mode != 'off'
                    else 'every point is taken as building (selection.mode: off)')
            self._warn(f'a cloud has no field "{cfg.input.class_field}" (input.class_field; fields: '
                       f'{", ".join(names)}): {what}', 'class field', period=60.0)
        self._waiting.append(_Waiting(scan, n, time.monotonic()))
        if len(self._waiting) > cfg.node.transform_queue:
            old = self._waiting.popleft()
            self._no_transform(old, f'more than node.transform_queue = {cfg.node.transform_queue} clouds wait for '
                                    'their transform: the oldest is given up')
        return None

    def _drain(self) -> None:
        """Place the waiting clouds in arrival order (the caller holds ``_count_lock``): the
        first whose transform has not come yet stops the others behind it, so that clouds
        reach the map in the order they came, as offline replay maps them."""
        cfg = self.config.node
        while self._waiting:
            head = self._waiting[0]
            final = time.monotonic() - head.arrived >= cfg.transform_timeout
            try:
                placement = head.scan.place(self.transforms, self.frame_id, cfg.pose_tolerance, final=final)
            except TransformError as exc:
                self._waiting.popleft()
                self._no_transform(head, str(exc))
                continue
            except InputError as exc:  # a time field that cannot be read
                self._waiting.popleft()
                self._reject(str(exc), head.points)
                continue
            if placement is None:
                return
            self._waiting.popleft()
            why = self._map(head, placement)
            if why is not None:
                self._reject(why, head.points)

    def _no_transform(self, item: _Waiting, why: str) -> None:
        """Reject a cloud whose transform never came (the caller holds ``_count_lock``)."""
        scan = item.scan
        self.counters['clouds_no_transform'] += 1
        self._reject(f'no transform from "{scan.frame_id}" into the map frame "{self.frame_id}" at '
                     f'{scan.stamp_ns / 1e9:.3f} s after {time.monotonic() - item.arrived:.2f} s: {why}', item.points,
                     kind='no transform')

    def _map(self, item: _Waiting, placement: Placement) -> str | None:
        """A placed cloud's building points to the worker; returns why it was refused, or None."""
        cfg = self.config
        scan = item.scan
        try:
            found = scan.building_points(placement, cfg.input, cfg.selection, cfg.node.max_coordinate)
        except InputError as exc:
            return str(exc)
        interval = self._interval
        if placement.note:
            interval['notes'][placement.note] += 1
            self._warn(f'a cloud in "{scan.frame_id}" at {scan.stamp_ns / 1e9:.3f} s: {placement.note}',
                       'placement ' + placement.note[:12], period=30.0)
        self.counters['points_not_building'] += found.not_building
        if found.nonfinite:
            self.counters['points_nonfinite'] += found.nonfinite
            self._warn(f'{found.nonfinite} of {item.points} points with NaN or infinite coordinates skipped',
                       'nonfinite')
        self._selection_note(found)
        self.get_logger().debug(self._cloud_line(item, placement, found))
        interval['points'] += item.points
        interval['building'] += len(found.xyz)
        if not len(found.xyz):
            self.counters['clouds_no_building'] += 1
            interval['queued'] += 1
            return None
        if not self.worker.put(Cloud(found.xyz, found.building_id, found.sensor_origins, scan.stamp_ns)):
            dropped = self.worker.counters['clouds_dropped']
            interval['dropped'] += 1
            self._event('dropped', f'mapping falls behind: {dropped} clouds dropped so far')
            self.get_logger().warning(f'mapping falls behind: dropped the oldest waiting cloud ({dropped} so far; '
                                      'a larger node.queue_size or update.batch_points may help)',
                                      throttle_duration_sec=5.0)
        interval['queued'] += 1
        return None

    def _selection_note(self, found: ScanPoints) -> None:
        """Count what the selection kept of a cloud without classes, and warn when it kept little."""
        from uncertain_facade_map.selection import selection_warning

        sel = found.selection
        if sel is None or not sel.applied:
            return
        self._interval['non_ground'] += sel.non_ground
        self._interval['selected'] += sel.kept
        warning = selection_warning(sel, self.config.selection)
        if warning is not None:
            self._warn(warning, 'selection share', period=30.0)

    def _cloud_line(self, item: _Waiting, placement: Placement, found: ScanPoints) -> str:
        """One debug line per cloud: its frame, points kept, pose and wait."""
        scan = item.scan
        pose = 'in the map frame'
        if placement.pose is not None:
            t = placement.pose.translations[0]
            pose = (f'frame "{scan.frame_id}" at ({t[0]:.2f}, {t[1]:.2f}, {t[2]:.2f}) m'
                    + (f', {len(placement.pose.translations)} poses over its points\' times' if not placement.pose.single
                       else ''))
        sel = found.selection
        kept = (f', the selection kept {sel.kept:,} of {sel.non_ground:,} non-ground points'
                if sel is not None and sel.applied else '')
        return (f'cloud at {scan.stamp_ns / 1e9:.3f} s: {item.points:,} points, {len(found.xyz):,} building{kept}; '
                f'{pose}; waited {time.monotonic() - item.arrived:.3f} s'
                + (f' ({placement.note})' if placement.note else ''))

    @_guarded
    def summary_callback(self) -> None:
        """Every ``node.log_period`` s while clouds come or the map changed: one info line of what happened."""
        with self._count_lock:
            interval, self._interval = self._interval, self._new_interval()
            waiting = len(self._waiting)
        snap = self.worker.snapshot
        mapped = self.worker.counters['clouds_mapped'] + self.counters['clouds_no_building']  # as /diagnostics
        if not interval['in'] and not interval['queued'] and not interval['rejected'] \
                and snap.version == self._summary_version and mapped == self._summary_mapped:
            return
        self._summary_version = snap.version
        mapped, self._summary_mapped = mapped - self._summary_mapped, mapped
        rejected = sum(interval['rejected'].values())
        why = '; '.join(f'{n} {kind}' for kind, n in interval['rejected'].most_common(3))
        # queued: placed and handed to the mapper; mapped: taken into the map by the mapper
        parts = [f'last {self.config.node.log_period:g} s: {interval["in"]} clouds in, {interval["queued"]} queued, '
                 f'{mapped} mapped',
                 f'{waiting} waiting for a transform', f'{interval["dropped"]} dropped',
                 f'{rejected} rejected' + (f' ({why})' if why else '')]
        if interval['non_ground']:
            parts.append(f'the selection kept {interval["selected"] / interval["non_ground"]:.0%} of the non-ground '
                         'points')
        elif interval['points']:
            parts.append(f'{interval["building"] / interval["points"]:.0%} of the points building')
        parts.append(f'map: {snap.buildings} buildings, {len(snap.facades)} façades, {snap.points:,} points')
        self.get_logger().info(', '.join(parts))

    def _flushed(self, points: int, refitted: list[int]) -> None:
        held = f'mapped the {points} points held back, ' if points else ''
        self.get_logger().info(f'input idle: {held}fitted {len(refitted)} façades whole')

    def _flush_failed(self, exc: BaseException) -> None:
        self._event('failed', f'idle flush failed: {type(exc).__name__}: {exc}')
        self.get_logger().error(f'the idle flush failed, the map is left as it was: {type(exc).__name__}: {exc}',
                                throttle_duration_sec=30.0)

    def _cloud_failed(self, cloud: Cloud, exc: BaseException) -> None:
        self._event('failed', f'mapping failed: {type(exc).__name__}: {exc}')
        self.get_logger().error(f'a cloud of {len(cloud.xyz)} points could not be mapped, the map is left as it '
                                f'was: {type(exc).__name__}: {exc}')

    # -- publishing ---------------------------------------------------------------------
    @_guarded
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
            band = snap.params.extraction  # the map's own bands (a loaded map keeps its own)
            try:
                # Built and serialized in the helper process: here only bytes are handed over.
                maps = self._compute(published_map_messages, facades, cfg, band.band_back, band.band_front,
                                     self.frame_id, stamp, serialize_message, self._occupancy(snap),
                                     self.reading.kept(snap), snap.registration_var)
                # The latched publishers keep these (and the grid) until the next ones.
                self._published_bytes = (len(maps.surface) + len(maps.mesh) + len(maps.variance_grids)
                                         + len(maps.voxels) + (maps.grid.p.size if maps.grid is not None else 0))
                self.pub_surface.publish(maps.surface)
                self.pub_mesh.publish(maps.mesh)
                self.pub_grids.publish(maps.variance_grids)
                self.pub_voxels.publish(maps.voxels)
                grid = self._grid_msg(snap, stamp, maps.grid)
                self.pub_grid.publish(grid)
            except FacadeMapError as exc:
                self._event('failed', f'publishing failed: {exc}')
                self.get_logger().error(f'publishing failed: {exc}', throttle_duration_sec=10.0)
            self._published_version = snap.version
            self._last_publish = time.monotonic()
            self.get_logger().debug(f'published map version {snap.version} in '
                                    f'{time.perf_counter() - started:.2f} s')

    def _reading_failed(self, exc: BaseException) -> None:
        self.get_logger().warning(f'building the local reading failed: {exc}', throttle_duration_sec=10.0)

    def _occupancy(self, snap: MapSnapshot) -> PLSC:
        """The occupancy's PLSC parameters for a snapshot's answers (``query.occupancy``)."""
        return occupancy_model(snap.occupancy, self.config.query.occupancy)

    def _compute(self, fn: Callable[..., Any], *args: Any) -> Any:
        """``fn(*args)`` in the helper process (``node.mapping_process``), else here."""
        return fn(*unkept(args)) if self._helper is None else self._helper.call(fn, *args)

    def _grid_msg(self, snap: MapSnapshot, stamp: int, grid: mp.OccupancyGrid2D | None = None) -> Any:
        """The 2D occupancy grid of a snapshot (cached per version; ``grid``: computed already),
        at ``grid_resolution`` or, for a map too wide for ``grid_max_cells`` cells, at the
        finest of 2, 4, 8, ... times it."""
        if self._grid is not None and self._grid[0] == snap.version:
            return self._grid[1]
        cfg = self.config.publish
        params = snap.params.extraction  # the map's own bands (a loaded map keeps its own)
        p, origin, resolution = np.full((1, 1), np.nan), np.zeros(2), cfg.grid_resolution
        if snap.facades:
            g = grid or self._compute(mp.band_grid, list(snap.facades), cfg, params.band_back, params.band_front,
                                      self._occupancy(snap), self.reading.kept(snap), snap.registration_var)
            p, origin, resolution = g.p, g.origin, g.resolution
            if resolution != cfg.grid_resolution:
                self._warn(f'the 2D grid of this map would have more than publish.grid_max_cells = '
                           f'{cfg.grid_max_cells:,} cells at {cfg.grid_resolution:g} m: served at {resolution:g} m '
                           f'({p.shape[1]} x {p.shape[0]} cells)', 'coarse grid', period=60.0)
        msg = mm.occupancy_grid_msg(p, origin, resolution, self.frame_id, stamp, self.types, z=cfg.grid_z_min)
        self._grid = (snap.version, msg)
        return msg

    def service_check_callback(self) -> None:
        """For the first minute after start: warn (once) when another node offers one of
        this node's services."""
        self._service_checks += 1
        if self._service_checks >= SERVICE_CHECKS:
            self._service_check.cancel()
        try:
            mine = {self.resolve_service_name(n) for n in self._service_names}
            me = (self.get_name(), self.get_namespace())
            advice = ('clients may reach either node. Give each mapper its own namespace '
                      '(--ros-args -r __ns:=/robot1) or remap the services')
            nodes = self.get_node_names_and_namespaces()
            if nodes.count(me) > 1:  # a twin: same name, hence the same services
                self._service_check.cancel()
                self.get_logger().warning(f'another node is called {self.get_fully_qualified_name()} and offers '
                                          f'the same services: {advice}')
            for name, namespace in set(nodes) - {me}:
                offered = {s for s, _ in self.get_service_names_and_types_by_node(name, namespace)}
                shared = sorted(mine & offered)
                if shared:
                    self._service_check.cancel()
                    full = namespace.rstrip('/') + '/' + name
                    self.get_logger().warning(f'node {full} offers {", ".join(shared)} too: {advice}')
        except Exception as exc:  # noqa: BLE001 - a check, not a duty
            self.get_logger().debug(f'service check skipped: {exc}')

    def accounts(self) -> dict[str, Any]:
        """Clouds and points received, mapped, dropped, rejected, failed and waiting, read
        at one moment so that they add up (``received = mapped + dropped + rejected + failed
        + waiting``, for points also ``+ not_building + nonfinite``)."""
        with self._count_lock:
            c = dict(self.counters)
            w = self.worker.accounts()
            waiting, waiting_points = len(self._waiting), sum(item.points for item in self._waiting)
        with self._pose_count_lock:
            poses = dict(self.pose_counters)
        return {
            'clouds_received': c['clouds_received'], 'clouds_mapped': w['clouds_mapped'] + c['clouds_no_building'],
            'clouds_dropped': w['clouds_dropped'], 'clouds_rejected': c['clouds_rejected'],
            'clouds_failed': w['clouds_failed'], 'clouds_waiting': w['clouds_waiting'] + waiting,
            'clouds_waiting_transform': waiting, 'clouds_no_transform': c['clouds_no_transform'],
            'clouds_missed_estimate': c['clouds_missed_estimate'],
            'points_received': c['points_received'], 'points_mapped': w['points_mapped'],
            'points_not_building': c['points_not_building'], 'points_nonfinite': c['points_nonfinite'],
            'points_dropped': w['points_dropped'], 'points_rejected': c['points_rejected'],
            'points_failed': w['points_failed'],
            'points_waiting': w['points_waiting'] + waiting_points,
            'points_pending': w['points_pending'], 'points_unmodelled': w['points_unmodelled'],
            'poses_rejected': poses['poses_rejected'],
            'transforms_received': poses['transforms_received'],
            'flushes': w['flushes'], 'queries': c['queries'], 'queries_failed': c['queries_failed'],
            'saves': c['saves'], 'callback_errors': c['callback_errors'],
        }

    @_guarded
    def diagnostics_callback(self) -> None:
        """Publish the accounts, the map's size, update time and latency, and a level that
        tells of the recent window (``publish.diagnostics_window``)."""
        self.reading.refresh()
        snap = self.worker.snapshot
        window = self.config.publish.diagnostics_window
        now = time.monotonic()
        recent = [(t, kind, text) for t, kind, text in list(self._events) if now - t <= window]
        latencies = np.array(list(self.worker.latencies))
        queries = np.array(list(self._query_seconds))
        values = dict(self.accounts())
        values.update({
            'map_points': snap.points, 'map_points_stored': snap.stored,
            'map_mb': round(snap.map_bytes / 2**20, 1), 'facades_mb': self._facades_mb(snap),
            'published_mb': round(self._published_bytes / 2**20, 1), 'buildings': snap.buildings, 'facades': len(snap.facades),
            'map_version': snap.version, 'settled': self.worker.settled and self.reading.current,
            'reading_builds': self.reading.builds[0], 'reading_build_seconds': round(self.reading.builds[1], 2),
            'last_update_seconds': round(self.worker.last_update_seconds, 4),
            'last_update_cpu_seconds': round(self.worker.last_update_cpu_seconds, 4),
            'latency_seconds': round(float(latencies[-1]), 3) if len(latencies) else 0.0,
            'latency_p50_seconds': round(float(np.percentile(latencies, 50)), 3) if len(latencies) else 0.0,
            'latency_p95_seconds': round(float(np.percentile(latencies, 95)), 3) if len(latencies) else 0.0,
            'latency_max_seconds': round(float(np.max(latencies)), 3) if len(latencies) else 0.0,
            'mapper_busy_share': round(self.worker.busy_share(), 3),
            'query_p95_ms': round(1e3 * float(np.percentile(queries, 95)), 1) if len(queries) else 0.0,
            'mapping_pid': self.worker.process_id or 0,
            'recent_window_seconds': window,
            **{f'recent_{kind}': sum(1 for _, k, _ in recent if k == kind) for kind in _WARN_EVENTS},
            'last_error': recent[-1][2] if recent else '',
            'last_error_age_seconds': round(now - recent[-1][0], 1) if recent else -1,
        })
        values.update(self._tiles_values())
        level = 1 if recent else 0
        message = ('mapping' if not recent else
                   f'{len(recent)} drops, rejections or failures in the last {window:g} s (see values)')
        self.pub_diag.publish(mm.diagnostic_array(f'{NODE_NAME}: map', level, message, values, NODE_NAME,
                                                  self.get_clock().now().nanoseconds, self.types))
        release_free_memory()  # the dropped clouds' and answered queries' buffers, back to the system

    def _tiles_values(self) -> dict[str, Any]:
        """The diagnostics of the served tiled map: tiles loaded, cache MB, preloads and their time."""
        tiled, follower = self._tiled, self._follower
        if tiled is None:
            return {'tiled_map': ''}
        info = tiled.cache_info()
        values = {'tiled_map': self._tiled_path, 'tiles': len(tiled.manifest_.tiles),
                  'tiles_loaded': len(info['tiles']),
                  'tiles_cache_mb': round(info['bytes'] / 2**20, 1),
                  'tiles_cache_limit_mb': round(info['limit_bytes'] / 2**20, 1),
                  'tiles_views': len(info['views']), 'tiles_views_built': info['views_built'],
                  'tiles_hits': info['hits'], 'tiles_misses': info['misses'], 'tiles_evictions': info['evictions'],
                  'tiles_load_seconds': round(info['load_seconds'], 3)}
        if follower is not None:
            values.update(follower.values())
        return values

    def _facades_mb(self, snap: MapSnapshot) -> float:
        """MB of the arrays of the snapshot's façade models held here (cached per version)."""
        if self._facades_size[0] != snap.version:
            self._facades_size = (snap.version, round(array_bytes(snap.facades) / 2**20, 1))
        return self._facades_size[1]

    # -- services -----------------------------------------------------------------------
    @_guarded
    def query_callback(self, request: Any, response: Any) -> Any:
        """Answer a batch of 3D points from the latest snapshot (never waits for the worker)."""
        started = time.perf_counter()
        with self._count_lock:
            self.counters['queries'] += 1
        try:
            xyz = mm.points_from_request(request, self.config.service.max_query_points)
            resolution = float(request.resolution) or self.config.query.resolution
            if not np.isfinite(resolution) or resolution <= 0:
                raise InputError(f'resolution must be a positive number of metres, got {request.resolution}')
            snap = self.worker.snapshot
            tiled = self._tiled
            if tiled is None:
                # Its own bands (a loaded map keeps its own); the local reading as self.reading says.
                answers = snap.query(xyz, self.config.query, resolution, local=self.reading.for_snapshot(snap))
                message = f'{len(xyz)} points, map version {snap.version}'
            else:
                answers, message = self._tiled_query(tiled, snap, xyz, resolution)
            mm.fill_query_response(response, answers, message, msg_types=self.types)
            self._query_seconds.append(time.perf_counter() - started)
        except FacadeMapError as exc:
            with self._count_lock:
                self.counters['queries_failed'] += 1
            response.success = False
            response.message = str(exc)
        return response

    def _tiled_query(self, tiled: TiledMap, snap: MapSnapshot, xyz: np.ndarray,
                     resolution: float) -> tuple[dict[str, np.ndarray], str]:
        """Answers from the served tiled map; the points it leaves on no façade from the live
        map when that has façades (ids plus :data:`~.tiled.LIVE_FACADE_OFFSET`)."""
        answers = tiled.query(xyz, self.config.query, resolution)
        asked = np.flatnonzero(np.asarray(answers.facade) < 0) if snap.facades else np.zeros(0, np.int64)
        live = (snap.query(xyz[asked], self.config.query, resolution, local=self.reading.for_snapshot(snap))
                if len(asked) else None)
        out = nt.combine_answers(answers, live, asked)
        by_live = int((np.asarray(live.facade) >= 0).sum()) if live is not None else 0
        return out, (f'{len(xyz)} points, tiled map {self._tiled_path}'
                     + (f'; {by_live} answered by the live map (version {snap.version})' if by_live else ''))

    @_guarded
    def get_facades_callback(self, request: Any, response: Any) -> Any:
        """The façade models of one building (or all, building = -1). With a tiled map
        served: the building's tile's (or, for -1, those of the tiles loaded now), ids the tiled
        map's as its queries answer them, then the live map's (ids plus LIVE_FACADE_OFFSET)."""
        snap = self.worker.snapshot
        building = int(request.building)
        models = [f for f in snap.facades if building < 0 or f.building == building]
        note = ''
        tiled = self._tiled
        if tiled is not None:
            import dataclasses

            models = [dataclasses.replace(f, facade_id=f.facade_id + nt.LIVE_FACADE_OFFSET) for f in models]
            if building >= 0:
                tile_ids = [tiled.manifest_.building_tiles[building]] if building in tiled.manifest_.building_tiles \
                    else []
            else:
                tile_ids = nt.loaded_ids(tiled)
            from_tiles = nt.tile_facades(tiled, tile_ids, building)
            models = from_tiles + models
            note = f' ({len(from_tiles)} of the tiled map\'s tiles {", ".join(tile_ids) or "(none loaded)"})'
        response.facades = [mm.facade_msg(f, self.types) for f in models]
        response.success = True
        response.message = f'{len(models)} façades{note}'
        return response

    @_guarded
    def list_tiles_callback(self, request: Any, response: Any) -> Any:
        """The served tiled map's tiles near a map-frame position (ids, squares, files, loaded)."""
        tiled, path = self._tiled, self._tiled_path
        try:
            if tiled is None:
                raise InputError('no tiled map is served: load one with load_map (a folder with manifest.json) '
                                 'or start with persistence.map_path naming one')
            xy = np.array([request.x, request.y], dtype=np.float64)
            if not np.isfinite(xy).all():
                raise InputError(f'x and y must be finite, got {request.x}, {request.y}')
            radius = nt.check_radius(request.radius, self.config.tiles.radius)
            ids, bounds, files, loaded = nt.tiles_near_listing(tiled, path, xy, radius)
            mm.fill_list_tiles_response(response, ids, bounds, files, loaded,
                                        f'{len(ids)} tiles within {radius:g} m of ({xy[0]:g}, {xy[1]:g}), '
                                        f'{sum(loaded)} loaded', msg_types=self.types)
        except FacadeMapError as exc:
            response.success, response.message = False, str(exc)
        return response

    def _path(self, given: str) -> str:
        """``persistence.map_path`` (the operator's) when no path is given."""
        path = given or self.config.persistence.map_path
        if not path:
            raise InputError('no path given and the parameter persistence.map_path is empty')
        return path

    def _save_path(self, given: str) -> str:
        """Where save_map writes the live map: in the map folder (:class:`MapFolder`), over
        nothing but a map file, never into a tiled map (served read-only)."""
        path = str(self.map_folder.save_path(given)) if given else self._path(given)
        if self._tiled_target(path) or any(is_tiled_map(p) for p in Path(path).parents):
            raise InputError(f'{path} is a tiled map or lies in one, read-only: save_map writes the live map to a '
                             'map file of its own; give it another path')
        if Path(path).parent == self.map_folder.root:
            self.map_folder.root.mkdir(parents=True, exist_ok=True)
        return path

    def _load_path(self, given: str) -> str:
        """What load_map reads: in the map folder, within persistence.max_load_mb."""
        return str(self.map_folder.load_path(given)) if given else self._path(given)

    def _save(self, path: str) -> tuple[int, int]:
        """Save the map as it stands now, without waiting for the queue (the worker keeps a
        clone after every cloud, which is written while it maps on); one save at a time.

        Returns:
            (map version saved, clouds waiting that the file does not hold).
        """
        with self._save_lock:
            fmap, version, waiting = self.worker.committed()
            save_map(fmap, path, replace_only_maps=True)
            self._saved_version = version
            with self._count_lock:
                self.counters['saves'] += 1
            return version, waiting

    @_guarded
    def save_callback(self, request: Any, response: Any) -> Any:
        """Save the map atomically, at once: the clouds mapped so far and the points held
        back; the message says how many received clouds still wait and are not in it."""
        try:
            path = self._save_path(request.path)
            if not Path(path).parent.exists():
                raise InputError(f'folder {Path(path).parent} does not exist')
            version, waiting = self._save(path)
            response.success, response.path = True, str(path)
            response.message = (f'saved map version {version} to {path}'
                                + (f'; {waiting} received clouds still wait and are not in it' if waiting else ''))
        except (FacadeMapError, OSError) as exc:
            response.success, response.message = False, f'not saved: {exc}'
        return response

    @_guarded
    def load_callback(self, request: Any, response: Any) -> Any:
        """Replace the map by a map file, or serve a tiled map (read-only; the live map starts
        empty beside it); a bad file or a folder without a manifest leaves everything as it is."""
        try:
            path = self._load_path(request.path)
            opened = self._open_map(path)
            if isinstance(opened, TiledMap):
                self.worker.call(functools.partial(replace_with, self._live_map_for(opened), None), COMMAND_TIMEOUT)
                self._serve_tiled(opened, path)
                facades = sum(t.facades for t in opened.manifest_.tiles.values())
                response.success, response.facades = True, min(facades, 2**32 - 1)
                response.message = (f'serving the tiled map {path} read-only: {len(opened.manifest_.tiles)} tiles, '
                                     f'{facades} façades; the live map starts empty')
            else:
                self.worker.call(functools.partial(replace_with, opened, None), COMMAND_TIMEOUT)
                self._serve_tiled(None)
                response.success, response.facades = True, len(opened.facades)
                response.message = f'loaded {path}: {len(opened.facades)} façades, {opened.n_points} points'
        except (FacadeMapError, OSError, TimeoutError) as exc:
            response.success, response.message = False, f'not loaded: {exc}'
        return response

    @_guarded
    def reset_callback(self, request: Any, response: Any) -> Any:
        """Start an empty map (clouds queued before the call are mapped first, then cleared);
        a served tiled map stays (read-only), the live map restarts with its parameters."""
        tiled = self._tiled
        empty = FacadeMap(self.params, np.asarray(self.config.input.map_origin, dtype=np.float64)) if tiled is None \
            else self._live_map_for(tiled)
        try:
            self.worker.call(functools.partial(replace_with, empty, None), COMMAND_TIMEOUT)
            response.success, response.message = True, 'map cleared'
        except TimeoutError as exc:
            response.success, response.message = False, str(exc)
        return response

    @_guarded
    def get_map_callback(self, request: Any, response: Any) -> Any:
        """nav_msgs/GetMap: the 2D occupancy grid of the height band."""
        snap = self.worker.snapshot
        response.map = self._grid_msg(snap, snap.stamp_ns or self.get_clock().now().nanoseconds)
        return response

    @_guarded
    def autosave_callback(self) -> None:
        """Save to persistence.map_path when the map changed since the last save."""
        if not self.config.persistence.map_path or self.worker.committed_version == self._saved_version:
            return
        if self._tiled_target(self.config.persistence.map_path):
            return  # a tiled map is served read-only, never saved over
        try:
            self._save(self.config.persistence.map_path)
        except (FacadeMapError, OSError) as exc:
            self._event('failed', f'autosave failed: {exc}')
            self.get_logger().error(f'autosave failed: {exc}', throttle_duration_sec=30.0)

    def destroy_node(self) -> None:
        self._stopping = True  # callbacks still running fail quietly from now on (see _guarded)
        waiting = self.worker.accounts()['clouds_waiting']
        if waiting:
            self.get_logger().warning(f'stopping: {waiting} received clouds were still waiting and are not mapped')
        self._serve_tiled(None)
        self.worker.stop()
        if self._helper is not None:
            self._helper.close()
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


def spin(factory: Callable[[], Any], name: str, args: list[str] | None = None, threads: int = 4) -> None:
    """Start rclpy, run the node ``factory()`` on a multi-threaded executor until Ctrl-C or
    shutdown, and clean up; a :class:`FacadeMapError` (bad parameters, say) ends the process
    with its message and status 2."""
    import rclpy
    from rclpy.executors import ExternalShutdownException, MultiThreadedExecutor

    rclpy.init(args=args)
    node = None
    try:
        node = factory()
        executor = MultiThreadedExecutor(num_threads=threads)
        executor.add_node(node)
        executor.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except FacadeMapError as exc:
        print(f'{name}: {exc}', file=sys.stderr)
        raise SystemExit(2) from None
    finally:
        if node is not None:
            node.destroy_node()
        if rclpy.ok():
            rclpy.shutdown()

if __name__ == '__main__':
    main()
