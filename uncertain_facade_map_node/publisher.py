"""The live map's products on their latched topics, made in a helper process.

:class:`MapPublisher` publishes, when the map changed and ``publish.period`` has passed, the
mean surface (``surface``, PointCloud2 x, y, z, std, facade), its mesh (``surface_mesh``,
visualization_msgs/MarkerArray), the variance grids (``variance_grids``,
uncertain_facade_map/FacadeGridArray), the occupancy voxels (``occupancy_voxels``,
PointCloud2 x, y, z, p_occupied) and the 2D grid of the height band (``occupancy_grid``,
nav_msgs/OccupancyGrid, also what ``get_map`` answers). All are transient local: a late
subscriber gets the last map. They are built and serialized in a helper process
(``node.mapping_process``), which keeps the per-point reading it is sent once per reading:
their numpy work would otherwise hold the node's interpreter lock for seconds on a large map.
"""

from __future__ import annotations

import threading
import time
from typing import Any, Callable

import numpy as np
from nav_msgs.msg import OccupancyGrid
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.serialization import serialize_message
from sensor_msgs.msg import PointCloud2
from visualization_msgs.msg import MarkerArray

from msg_adapters import map_messages as mm
from msg_adapters.published_maps import published_map_messages
from uncertain_facade_map.datatypes import array_bytes
from uncertain_facade_map.errors import FacadeMapError
from uncertain_facade_map.mapping import products as mp
from uncertain_facade_map.mapping.accounts import Accounts
from uncertain_facade_map.mapping.engine import HelperProcess, unkept
from uncertain_facade_map.mapping.served import ServedReading
from uncertain_facade_map.mapping.worker import MapSnapshot
from uncertain_facade_map.msg import FacadeGridArray
from uncertain_facade_map.params import Config
from uncertain_facade_map.pipeline.step8_occupancy import PLSC, occupancy_model

__all__ = ['MapPublisher']


class MapPublisher:
    """The publishers of the map products, and the helper process that makes them.

    Args:
        node: the rclpy node the publishers belong to.
        config: the configuration (``publish.*``, ``query.occupancy``, ``node.mapping_process``,
            ``node.mapping_nice``).
        frame_id: the map frame.
        reading: the live map's reading (sent to the helper once per reading).
        accounts: where a failed publication is told.
        types: the node's message types (``msg_adapters.map_messages.rclpy_map_types()``).
    """

    def __init__(self, node: Any, config: Config, frame_id: str, reading: ServedReading, accounts: Accounts,
                 types: Any) -> None:
        self._node = node
        self._config = config
        self.frame_id = frame_id
        self._reading = reading
        self._accounts = accounts
        self.types = types
        self._helper = (HelperProcess('facade_products', config.node.mapping_nice)
                        if config.node.mapping_process else None)
        latched = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL,
                             reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST)
        self._surface = node.create_publisher(PointCloud2, 'surface', latched)
        self._mesh = node.create_publisher(MarkerArray, 'surface_mesh', latched)
        self._grids = node.create_publisher(FacadeGridArray, 'variance_grids', latched)
        self._voxels = node.create_publisher(PointCloud2, 'occupancy_voxels', latched)
        self._grid_pub = node.create_publisher(OccupancyGrid, 'occupancy_grid', latched)
        self._lock = threading.Lock()
        self._grid: tuple[int, Any] | None = None  # (snapshot version, OccupancyGrid)
        self._facades_size: tuple[int, float] = (-1, 0.0)  # (snapshot version, MB of its façade arrays)
        self.published_bytes = 0  # of the latest published maps (serialized; the grid's cells)
        self.published_version = -1
        self._last = 0.0  # time.monotonic() of the last publication

    def publish_if_due(self, snap: MapSnapshot) -> None:
        """Publish the maps of ``snap`` when they changed and ``publish.period`` has passed."""
        if snap.version != self.published_version and time.monotonic() - self._last >= self._config.publish.period:
            self.publish(snap)

    def publish(self, snap: MapSnapshot) -> None:
        """Publish every map product of a snapshot."""
        with self._lock:
            cfg = self._config.publish
            stamp = snap.stamp_ns or self._node.get_clock().now().nanoseconds
            started = time.perf_counter()
            band = snap.params.extraction  # the map's own bands (a loaded map keeps its own)
            try:
                # Built and serialized in the helper process: here only bytes are handed over.
                maps = self._compute(published_map_messages, list(snap.facades), cfg, band.band_back,
                                     band.band_front, self.frame_id, stamp, serialize_message, self._occupancy(snap),
                                     self._reading.kept(snap), snap.registration_var)
                # The latched publishers keep these (and the grid) until the next ones.
                self.published_bytes = (len(maps.surface) + len(maps.mesh) + len(maps.variance_grids)
                                        + len(maps.voxels) + (maps.grid.p.size if maps.grid is not None else 0))
                self._surface.publish(maps.surface)
                self._mesh.publish(maps.mesh)
                self._grids.publish(maps.variance_grids)
                self._voxels.publish(maps.voxels)
                self._grid_pub.publish(self.grid_msg(snap, stamp, maps.grid))
            except FacadeMapError as exc:
                self._accounts.event('failed', f'publishing failed: {exc}')
                self._node.get_logger().error(f'publishing failed: {exc}', throttle_duration_sec=10.0)
            self.published_version = snap.version
            self._last = time.monotonic()
            self._node.get_logger().debug(f'published map version {snap.version} in '
                                          f'{time.perf_counter() - started:.2f} s')

    def _occupancy(self, snap: MapSnapshot) -> PLSC:
        """The occupancy's PLSC parameters for a snapshot's answers (``query.occupancy``)."""
        return occupancy_model(snap.occupancy, self._config.query.occupancy)

    def _compute(self, fn: Callable[..., Any], *args: Any) -> Any:
        """``fn(*args)`` in the helper process (``node.mapping_process``), else here."""
        return fn(*unkept(args)) if self._helper is None else self._helper.call(fn, *args)

    def grid_msg(self, snap: MapSnapshot, stamp: int, grid: mp.OccupancyGrid2D | None = None) -> Any:
        """The 2D occupancy grid of a snapshot (cached per version; ``grid``: computed already),
        at ``grid_resolution`` or, for a map too wide for ``grid_max_cells`` cells, at the
        finest of 2, 4, 8, ... times it."""
        cached = self._grid
        if cached is not None and cached[0] == snap.version:
            return cached[1]
        cfg = self._config.publish
        params = snap.params.extraction  # the map's own bands (a loaded map keeps its own)
        p, origin, resolution = np.full((1, 1), np.nan), np.zeros(2), cfg.grid_resolution
        if snap.facades:
            g = grid or self._compute(mp.band_grid, list(snap.facades), cfg, params.band_back, params.band_front,
                                      self._occupancy(snap), self._reading.kept(snap), snap.registration_var)
            p, origin, resolution = g.p, g.origin, g.resolution
            if resolution != cfg.grid_resolution:
                self._accounts.warn(f'the 2D grid of this map would have more than publish.grid_max_cells = '
                                    f'{cfg.grid_max_cells:,} cells at {cfg.grid_resolution:g} m: served at '
                                    f'{resolution:g} m ({p.shape[1]} x {p.shape[0]} cells)', 'coarse grid', 60.0)
        msg = mm.occupancy_grid_msg(p, origin, resolution, self.frame_id, stamp, self.types, z=cfg.grid_z_min)
        self._grid = (snap.version, msg)
        return msg

    def values(self, snap: MapSnapshot) -> dict[str, float]:
        """The diagnostics of the published maps: MB published, MB of the façade models held."""
        if self._facades_size[0] != snap.version:
            self._facades_size = (snap.version, round(array_bytes(snap.facades) / 2**20, 1))
        return {'facades_mb': self._facades_size[1], 'published_mb': round(self.published_bytes / 2**20, 1)}

    def close(self) -> None:
        """End the helper process."""
        if self._helper is not None:
            self._helper.close()
