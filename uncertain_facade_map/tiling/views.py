"""Views of a tiled map: what answers a batch of query points (issue 29).

A **view** is a square of ``k x k`` tiles of the grid (``tiles.view_tiles``), lower left tile
``(i0, j0)``, holding what a query at a point of the square reads on a map of every building:

- of the tiles whose extent (stored points and façade slabs) meets the square grown by the
  local reading's reach (:data:`~.tiled_map.LOCAL_MARGIN` past ``query.local_radius``), the
  façades whose slabs meet that grown square or that a kept stored point belongs to (the
  models shared with the tiles, not copied), their rasters packed once
  (:class:`~uncertain_facade_map.pipeline.raster_kernels.PackedRasters`);
- the stored points the local reading reads
  (:class:`~uncertain_facade_map.pipeline.step7_local_surface.LocalSurface`), those of the
  same tiles inside the grown square, in building label order (as one map holding every
  building concatenates them), and their search grid.

The local reading's per-point labels and its test of the chi-squared outliers
(:meth:`LocalSurface.of <uncertain_facade_map.pipeline.step7_local_surface.LocalSurface.of>`)
are computed once per tile (:func:`tile_part`, kept with the tile in the cache), so that a view
costs the crop, the packing and one sort of its points, not the whole reading's set-up: on the
simulated city a view of 3 x 3 tiles is built in a fraction of a second, where a merged map
of four tiles took 1-3 s (docs/city-scale.md).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
from scipy.spatial import cKDTree

from ..datatypes import FacadeModel, array_bytes
from ..mapping.facade_map import FacadeMap
from ..params import QueryConfig
from ..pipeline.raster_kernels import PackedRasters, facade_boxes
from ..pipeline.step7_local_surface import LocalSurface, ReadingCalibration, noise_floor_of
from ..pipeline.step7_queries import STEP_REACH
from ..pipeline.step8_occupancy import PLSC


@dataclass(eq=False)
class TilePart:
    """One tile's stored points as the local reading reads them, and its façades' slabs
    (:func:`tile_part`).

    Attributes:
        index: (M,) int32 the stored points kept (the outliers that stand alone left out):
            their index in the tile's stored points concatenated in building label order.
        facade: (M,) int32 the tile's façade id of each (its file's order); -1 for those of a
            building with no façade (the view counts them with the nearest façade among its
            points, as a whole map does among all of its own: a neighbour tile's façade may be
            the nearest).
        box_lo, box_hi: (F, 3) lower and upper corners of the tile's façades' slabs, metres, map frame.
    """

    index: np.ndarray
    facade: np.ndarray
    box_lo: np.ndarray
    box_hi: np.ndarray


def stored_points(fmap: FacadeMap) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) a map's stored points concatenated in building label order (metres, map frame)
    and (N,) int64 the building label of each."""
    labels = sorted(fmap.points)
    xyz = np.concatenate([fmap.points[b] for b in labels]) if labels else np.empty((0, 3))
    return xyz, np.repeat(np.asarray(labels, np.int64), [len(fmap.points[b]) for b in labels])


def tile_part(fmap: FacadeMap, config: QueryConfig) -> TilePart:
    """The local reading's stored points of one tile's map for the settings ``config``
    (``query.local_*``; :meth:`LocalSurface.of` on the tile alone, uncalibrated; none for the
    raster reading) and its façades' slabs."""
    ex = fmap.params.extraction
    lo, hi = facade_boxes(fmap.facades, ex.band_back, ex.band_front)
    if config.surface != 'local':
        return TilePart(np.empty(0, np.int32), np.empty(0, np.int32), lo, hi)
    surface = LocalSurface.of(fmap.facades, fmap.points, config.local_neighbours, config.local_radius,
                              config.local_inner, calibrate=False, join=False)
    return TilePart(surface.source.astype(np.int32), surface.facade.astype(np.int32), lo, hi)


@dataclass(eq=False)
class View:
    """What a square of tiles answers from (see the module's text).

    Attributes:
        key: ``(i0, j0, reading)``: the lower left tile of the square and the local reading's
            settings (:func:`~uncertain_facade_map.mapping.facade_map.reading_key`).
        tiles: the ids of the tiles it reads, sorted.
        facades: the façade models whose slabs meet the grown square or that a kept stored
            point belongs to, in the tiled map's order.
        global_ids: (F,) int32 the tiled map's id of each.
        rasters: their rasters, packed.
        local: the local reading's stored points within the grown square (in the order of its
            grid), or None: the raster reading.
        occupancy: the occupancy's PLSC parameters; ``registration_var``: the scan-to-scan
            variance, m^2 (the manifest's, else its tiles' joined as
            :func:`~.tiled_map.merge_maps` joins them).
        nbytes: what it adds to its tiles' arrays (packed rasters, the local reading), bytes.
    """

    key: tuple
    tiles: tuple[str, ...]
    facades: list[FacadeModel]
    global_ids: np.ndarray
    rasters: PackedRasters
    local: LocalSurface | None
    occupancy: PLSC
    registration_var: float
    nbytes: int


def make_view(key: tuple, tiles: Sequence[str], maps: Sequence[FacadeMap], parts: Sequence[TilePart],
              offsets: Sequence[int], square: tuple[float, float, float, float], pad: float, config: QueryConfig,
              calibration: ReadingCalibration, occupancy: PLSC, registration_var: float) -> View:
    """Build a view.

    Args:
        key: the view's key (see :class:`View`).
        tiles: the tiles' ids, sorted; ``maps`` their maps, ``parts`` their :func:`tile_part`,
            ``offsets`` the tiled map's id of each one's first façade.
        square: (min_x, min_y, max_x, max_y) of the view's tiles, metres, map frame.
        pad: metres the square is grown by (the local reading's reach).
        config: the query settings.
        calibration: the local reading's map-wide calibration.
        occupancy: the PLSC parameters; ``registration_var``: the scan-to-scan variance, m^2.
    """
    x0, y0, x1, y1 = square[0] - pad, square[1] - pad, square[2] + pad, square[3] + pad
    local = config.surface == 'local'
    chosen, xyz, fid, building = [], [], [], []
    for fmap, part, offset in zip(maps, parts, offsets):
        meets = (part.box_lo[:, 0] <= x1) & (part.box_hi[:, 0] >= x0) & (part.box_lo[:, 1] <= y1) & (part.box_hi[:, 1] >= y0)
        chosen.append(offset + np.flatnonzero(meets))
        if not local:
            continue
        pts, labels = stored_points(fmap)
        p = pts[part.index]
        inside = np.flatnonzero((p[:, 0] >= x0) & (p[:, 0] <= x1) & (p[:, 1] >= y0) & (p[:, 1] <= y1))
        xyz.append(p[inside])
        f = part.facade[inside].astype(np.int64)
        fid.append(np.where(f >= 0, offset + f, -1))  # -1: a building with no façade
        building.append(labels[part.index[inside]])
    fid_all = np.concatenate(fid) if fid else np.empty(0, np.int64)
    # The façades whose slabs meet the grown square (all a point of the square may be assigned
    # to), and those a kept stored point belongs to (a point the bands miss takes its nearest
    # stored point's façade), in the tiled map's order.
    global_ids = np.union1d(np.concatenate(chosen) if chosen else np.empty(0, np.int64),
                            fid_all[fid_all >= 0]).astype(np.int32)
    starts = np.asarray(offsets, np.int64)
    owner = np.searchsorted(starts, global_ids, side='right') - 1
    facades = [maps[o].facades[g - starts[o]] for o, g in zip(owner.tolist(), global_ids.tolist())]
    rasters = PackedRasters(facades, STEP_REACH)
    if maps:
        rasters.boxes(maps[0].params.extraction.band_back, maps[0].params.extraction.band_front)  # computed now
    surface = None
    if local:
        b_all = np.concatenate(building) if building else np.empty(0, np.int64)
        # Building label order, as a map of every building concatenates its stored points
        # (each tile's are in that order already, and tiles hold disjoint buildings).
        order = np.argsort(b_all, kind='stable')
        pts = np.concatenate(xyz)[order] if xyz else np.empty((0, 3))
        f = fid_all[order]
        labels = np.where(f >= 0, np.searchsorted(global_ids, f), -1).astype(np.int32)
        free, mapped = np.flatnonzero(labels < 0), np.flatnonzero(labels >= 0)
        if len(free) and len(mapped):
            # Points of buildings with no façade count with the façade of their nearest stored
            # point on one, here among the view's points (a neighbour tile's façade may be the
            # nearest), as LocalSurface.of counts them among all of a whole map's.
            labels[free] = labels[mapped[cKDTree(pts[mapped]).query(pts[free])[1]]]
        normals = np.ascontiguousarray(rasters.axes[:, 2])
        surface = LocalSurface(pts, labels, normals, config.local_neighbours, config.local_radius, config.local_inner,
                               noise_floor=noise_floor_of(facades)).calibrate_with(calibration).in_grid_order()
    nbytes = array_bytes(rasters) + (array_bytes(surface) if surface is not None else 0)
    return View(key, tuple(tiles), facades, global_ids, rasters, surface, occupancy, float(registration_var), nbytes)
