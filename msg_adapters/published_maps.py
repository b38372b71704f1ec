"""The node's published maps as serialized messages, built where the caller says.

:func:`published_map_messages` computes every product of a map (core:
:func:`~uncertain_facade_map.mapping.products.map_products`), builds the messages and
serializes them with the serializer it is given (the node passes rclpy's
``serialize_message``; this package never imports rclpy), so that the node only hands bytes
to its publishers. The
facade_mapper node runs it in a helper process: building and converting a surface mesh of
200 000 triangles holds an interpreter's lock for about 2 s (1.75 s of it in one call of
rclpy's message conversion), and in the node's own interpreter every query would wait.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Sequence

import numpy as np

from uncertain_facade_map.mapping import products as mp
from uncertain_facade_map.pipeline.step8_occupancy import FIXED, PLSC

from .map_messages import facade_grid_array, rclpy_map_types, triangle_marker_array
from .pointcloud2 import pointcloud2_from_structured, rclpy_types

__all__ = ['PublishedMaps', 'published_map_messages']


@dataclass(frozen=True)
class PublishedMaps:
    """Serialized messages of one map (rclpy's CDR bytes, for ``Publisher.publish``).

    Attributes:
        surface: ``sensor_msgs/PointCloud2`` of the mean surface (x, y, z, std, facade).
        mesh: ``visualization_msgs/MarkerArray`` of the surface mesh (DELETEALL only for a
            map without façades, so that a late subscriber sees no old mesh).
        variance_grids: ``uncertain_facade_map/FacadeGridArray``.
        voxels: ``sensor_msgs/PointCloud2`` of the 3D occupancy shell (x, y, z, p_occupied).
        grid: the 2D occupancy grid's arrays (the node builds and caches its message for
            ``get_map`` too), None for a map without façades.
    """

    surface: bytes
    mesh: bytes
    variance_grids: bytes
    voxels: bytes
    grid: mp.OccupancyGrid2D | None


def published_map_messages(facades: Sequence[Any], publish: Any, band_back: float, band_front: float,
                           frame_id: str, stamp_ns: int, serialize_message: Callable[[Any], bytes],
                           occupancy: PLSC = FIXED, local: Any = None, registration_var: float = 0.0) -> PublishedMaps:
    """Every published map of ``facades`` (see :func:`~uncertain_facade_map.mapping.products.map_products`
    for ``publish`` and the bands), in ``frame_id`` at ``stamp_ns``, serialized by
    ``serialize_message`` (rclpy's ``rclpy.serialization.serialize_message``: a module-level
    function, so that the call pickles to a helper process); ``occupancy``: the PLSC
    parameters of the occupancy (the map's learnt ones or the fixed formula's); ``local``: the
    map's stored points read per point in the occupancy products
    (:class:`~uncertain_facade_map.pipeline.step7_local_surface.LocalSurface`, None: the rasters alone);
    ``registration_var``: the map's scan-to-scan variance, m^2 (``FacadeMap.registration_var_``)."""
    types, cloud_types = rclpy_map_types(), rclpy_types()
    facades = list(facades)
    products = mp.map_products(facades, publish, band_back, band_front, occupancy, local, registration_var)
    surf = products.surface
    table = np.zeros(len(surf.xyz), dtype=[('x', 'f4'), ('y', 'f4'), ('z', 'f4'), ('std', 'f4'), ('facade', 'i4')])
    table['x'], table['y'], table['z'] = surf.xyz.T
    table['std'], table['facade'] = surf.std, surf.facade
    if products.mesh is not None:
        m = products.mesh
        mesh = triangle_marker_array(m.vertices, m.triangles, m.std, m.facade, frame_id, stamp_ns, types)
    else:
        mesh = triangle_marker_array(np.empty((0, 3)), np.empty((0, 3), np.int64), np.empty(0),
                                     np.empty(0, np.int64), frame_id, stamp_ns, types)
    vox = products.voxels
    vt = np.zeros(len(vox.centres), dtype=[('x', 'f4'), ('y', 'f4'), ('z', 'f4'), ('p_occupied', 'f4')])
    vt['x'], vt['y'], vt['z'] = vox.centres.T
    vt['p_occupied'] = vox.p_occupied
    return PublishedMaps(
        surface=serialize_message(pointcloud2_from_structured(table, stamp_ns=stamp_ns, frame_id=frame_id,
                                                              msg_types=cloud_types)),
        mesh=serialize_message(mesh),
        variance_grids=serialize_message(facade_grid_array(facades, frame_id, stamp_ns, types)),
        voxels=serialize_message(pointcloud2_from_structured(vt, stamp_ns=stamp_ns, frame_id=frame_id,
                                                             msg_types=cloud_types)),
        grid=products.grid)
