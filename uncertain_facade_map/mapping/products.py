"""Map products: the arrays the ROS node publishes, computed from the façade models.

The façade models keep each surface as a raster in its own façade frame
(:class:`~uncertain_facade_map.datatypes.SurfaceRaster`). A ROS user wants map-frame products instead; this
module computes them as plain arrays (the node turns them into messages elsewhere). All
coordinates are in the map frame, in metres; every product is a pure function of a list of
:class:`~uncertain_facade_map.datatypes.FacadeModel`.

Products and how each is derived:

* **Surface points** (:func:`surface_grid`, for a ``sensor_msgs/PointCloud2`` with
  ``x, y, z, std, facade``): every façade's mean surface sampled on a regular grid of its
  plane, world point = ``frame.to_world((u, v, mean_depth))``, with the standard deviation
  ``sqrt(var)`` of the surface (the measurement noise not included). Grid nodes start at
  the raster's first cell centre and are ``step`` apart; when ``step`` is a multiple of
  the raster cell (the default: the cell itself) the nodes are cell centres and carry the
  raster's own values, otherwise :func:`~uncertain_facade_map.pipeline.step7_queries.surface_at` interpolates them (bilinear
  inside a facet, nearest cell across a facet boundary). Only nodes whose cell holds a
  facet are surface: where the global prior holds there is no observed surface to draw.
* **Surface mesh** (:func:`surface_mesh`, for a ``visualization_msgs/Marker`` of type
  ``TRIANGLE_LIST``, coloured by ``std``): the same grid nodes as vertices, two triangles
  per grid square whose four corners lie in one facet of the façade (so a depth step
  between facets, e.g. a balcony's edge, is left open instead of bridged by long sloped
  triangles), wound counter-clockwise seen from outside: the right-hand normal of every
  triangle points out of the building, along the façade normal.
* **3D occupancy** (:func:`voxel_occupancy`, for a ``PointCloud2`` of voxel centres with
  ``p_occupied`` or a ``CUBE_LIST`` marker): the voxels of an axis-aligned map-frame grid of
  side ``resolution`` (centres at ``(i + 0.5) * resolution``) whose centre lies within
  ``shell`` metres of some façade's mean surface along that façade's normal, where a facet
  exists; each voxel once, with the occupancy probability :func:`~uncertain_facade_map.pipeline.step7_queries.query_points`
  gives at its centre (so it equals the point-query service's answer exactly).
* **2D occupancy of a height band** (:func:`height_band_grid`, for a
  ``nav_msgs/OccupancyGrid``): cells of side ``resolution`` aligned with the voxel columns;
  a cell's probability is the largest :func:`~uncertain_facade_map.pipeline.step7_queries.query_points` probability over the
  voxels of its column that overlap the band ``z_min..z_max``, among those a façade's band
  covers; NaN (unknown) where none is covered.

Both occupancy products take the point query's answers as they are. Where two façades
meet, the query gives a point to the nearer plane, whose raster may reach past the corner
with only its global prior there: a little air just in front of one wall near the corner
can then come out occupied from the other wall's side (``test_map_products`` marks this as
an expected failure of :mod:`~uncertain_facade_map.pipeline.step7_queries`, not of this module).

Products are bounded: each function refuses, with :class:`~.errors.InputError` and a
message saying how far to coarsen, to produce more than its ``max_*`` argument.

Costs on the ``street`` scene's map (19 façades, 0.49 M facet cells of 0.1 m; one core,
busy machine): surface grid 0.1 s (0.49 M points), mesh 0.15 s (0.49 M vertices, 0.89 M
triangles), voxels with a 0.3 m shell 1 s at 0.2 m (0.36 M voxels) and 10 to 12 s at
0.1 m (2.9 M voxels, over the default ``max_voxels``; two thirds of it the point query),
height band 0.2 to 2 m at 0.1 m 2 to 3 s (449 x 1401 cells).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np
from scipy.ndimage import maximum_filter, minimum_filter

from ..datatypes import FacadeFrame, FacadeModel, SurfaceRaster
from ..errors import InputError
from ..params import ExtractionParams
from ..pipeline.step7_local_surface import LocalSurface
from ..pipeline.step7_queries import query_points, surface_at
from ..pipeline.step8_occupancy import FIXED, PLSC

#: Defaults of the query band, as the map's extraction parameters have them.
BAND_BACK = ExtractionParams.band_back
BAND_FRONT = ExtractionParams.band_front

#: Side of the façade tiles the voxel enumeration works in, metres (at least two voxels).
_TILE = 0.4

#: Voxels handled at once (candidates of a façade, points of a query).
_BATCH = 500_000

#: Tolerance of the voxel enumeration, in voxel units (the exact test follows it).
_EPS = 1e-6


# --------------------------------------------------------------------------- results


@dataclass(frozen=True, eq=False)
class SurfaceGrid:
    """The mean surfaces of the façades sampled on a regular grid of each façade's plane.

    Attributes:
        xyz: (N, 3) float64 surface points, metres, map frame.
        std: (N,) float64 standard deviation of the surface there, metres (sqrt of the
            surface variance, measurement noise not included).
        facade: (N,) int32 façade id (``FacadeModel.facade_id``).
        facet: (N,) int32 facet of the point within its façade.
        step: grid spacing on the façade planes, metres; None where each façade's raster
            cell was used.
    """

    xyz: np.ndarray
    std: np.ndarray
    facade: np.ndarray
    facet: np.ndarray
    step: float | None

    def __len__(self) -> int:
        return len(self.xyz)


@dataclass(frozen=True, eq=False)
class SurfaceMesh:
    """A triangle mesh of the façades' mean surfaces.

    Attributes:
        vertices: (V, 3) float64 vertices, metres, map frame; each is a node of
            :func:`surface_grid` with the same step.
        triangles: (T, 3) int32 vertex indices; counter-clockwise seen from outside, so the
            right-hand normal ``(b - a) x (c - a)`` points along the façade's outward normal.
        std: (V,) float64 standard deviation of the surface at each vertex, metres.
        facade: (V,) int32 façade id of each vertex.
        facet: (V,) int32 facet of each vertex within its façade; the three vertices of a
            triangle share façade and facet.
        step: grid spacing on the façade planes, metres; None where each façade's raster
            cell was used.
    """

    vertices: np.ndarray
    triangles: np.ndarray
    std: np.ndarray
    facade: np.ndarray
    facet: np.ndarray
    step: float | None

    def triangle_points(self) -> np.ndarray:
        """(3T, 3) float64 corners of the triangles in order, metres, map frame.

        The ``points`` of a ``TRIANGLE_LIST`` marker; per-corner values (e.g. colours from
        ``std``) follow as ``std[triangles.ravel()]``.
        """
        return self.vertices[self.triangles.ravel()]


@dataclass(frozen=True, eq=False)
class VoxelOccupancy:
    """Occupancy of the voxels around the façades' mean surfaces.

    Attributes:
        centres: (M, 3) float64 voxel centres ``(index + 0.5) * resolution``, metres, map frame.
        index: (M, 3) int64 integer voxel indices (i, j, k) along x, y, z.
        p_occupied: (M,) float64 occupancy probability of each voxel, in [0, 1].
        facade: (M,) int32 façade id the point query assigned the voxel to.
        resolution: voxel side, metres.
        shell: half thickness of the shell around the surfaces, metres.
    """

    centres: np.ndarray
    index: np.ndarray
    p_occupied: np.ndarray
    facade: np.ndarray
    resolution: float
    shell: float

    def __len__(self) -> int:
        return len(self.centres)


@dataclass(frozen=True, eq=False)
class OccupancyGrid2D:
    """2D occupancy of a height band, laid out as ``nav_msgs/OccupancyGrid``.

    Attributes:
        p: (H, W) float64 occupancy probability in [0, 1], NaN where unknown; row = y,
            column = x, row 0 at ``origin``'s y (row-major from the origin, x fastest).
        origin: (2,) float64 (x, y) of the lower-left corner of cell (0, 0), metres, map
            frame (a multiple of ``resolution``: cells are the voxel columns of
            :func:`voxel_occupancy`).
        resolution: cell side, metres.
        z_min: lower end of the height band, metres, map frame.
        z_max: upper end of the height band, metres, map frame.
    """

    p: np.ndarray
    origin: np.ndarray
    resolution: float
    z_min: float
    z_max: float

    def cell_centres(self) -> tuple[np.ndarray, np.ndarray]:
        """(W,) x and (H,) y of the cell centres, metres, map frame."""
        h, w = self.p.shape
        x = (np.round(self.origin[0] / self.resolution) + np.arange(w) + 0.5) * self.resolution
        y = (np.round(self.origin[1] / self.resolution) + np.arange(h) + 0.5) * self.resolution
        return x, y

    def occupancy_values(self) -> np.ndarray:
        """(H * W,) int8 the ``nav_msgs/OccupancyGrid`` data: ``round(100 p)``, -1 where unknown."""
        flat = self.p.ravel()
        out = np.full(flat.shape, -1, dtype=np.int8)
        known = np.isfinite(flat)
        out[known] = np.rint(100.0 * flat[known]).astype(np.int8)
        return out


# --------------------------------------------------------------------------- checks


def _positive(name: str, value: float) -> float:
    try:
        value = float(value)
    except (TypeError, ValueError):
        raise InputError(f'{name} must be a number, got {value!r}') from None
    if not (np.isfinite(value) and value > 0):
        raise InputError(f'{name} must be positive and finite, got {value}')
    return value


def _band(band_back: float, band_front: float) -> tuple[float, float]:
    back, front = float(band_back), float(band_front)
    if not (np.isfinite(back) and np.isfinite(front) and back >= 0 and front >= 0 and back + front > 0):
        raise InputError(f'the query band needs band_back, band_front >= 0 and wider than 0, got {back}, {front}')
    return back, front


def _limit(name: str, value: int) -> int:
    if int(value) < 1:
        raise InputError(f'{name} must be >= 1, got {value}')
    return int(value)


# --------------------------------------------------------------------------- surface grid and mesh


def _nearest_cell(raster: SurfaceRaster, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(row, column) of the cell :func:`~uncertain_facade_map.pipeline.step7_queries.surface_at` takes across a facet boundary.

    That is the cell containing the location (clipped to the raster), computed with the
    very arithmetic of ``surface_at`` so that boundaries fall the same way.
    """
    h, w = raster.mean.shape
    out = []
    for axis, n in ((1, h), (0, w)):
        f = (uv[:, axis] - raster.origin[axis]) / raster.cell - 0.5
        i0 = np.clip(np.floor(f).astype(np.int64), 0, max(n - 2, 0))
        i1 = np.minimum(i0 + 1, n - 1)
        t = np.clip(f - i0, 0.0, 1.0)
        out.append(np.where(t < 0.5, i0, i1))
    return out[0], out[1]


def _node_counts(raster: SurfaceRaster, step: float) -> tuple[int, int]:
    """Grid nodes (rows along v, columns along u) from the first to the last cell centre."""
    h, w = raster.mean.shape
    ratio = step / raster.cell
    return (int(np.floor((h - 1) / ratio + 1e-9)) + 1, int(np.floor((w - 1) / ratio + 1e-9)) + 1)


def _facade_nodes(f: FacadeModel, step: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The grid nodes of one façade.

    Returns:
        ``(uvd, var, facet)``: (n_v, n_u, 3) façade coordinates of the nodes with the mean
        depth (NaN off facets), (n_v, n_u) surface variance (NaN off facets) and (n_v, n_u)
        int32 facet (-1 where none). Row = v, column = u.
    """
    r = f.surface
    n_v, n_u = _node_counts(r, step)
    ratio = step / r.cell
    fc = np.arange(n_u) * ratio  # node positions in cell units from the first cell centre
    fr = np.arange(n_v) * ratio
    ic, ir = np.rint(fc).astype(np.int64), np.rint(fr).astype(np.int64)
    centred = bool(np.all(np.abs(fc - ic) < 1e-9) and np.all(np.abs(fr - ir) < 1e-9))
    if centred:  # exactly the cell centres of SurfaceRaster.centres()
        fc, fr = ic.astype(np.float64), ir.astype(np.float64)
    u = r.origin[0] + (fc + 0.5) * r.cell
    v = r.origin[1] + (fr + 0.5) * r.cell
    uu, vv = np.meshgrid(u, v)
    mean = np.full((n_v, n_u), np.nan)
    var = np.full((n_v, n_u), np.nan)
    if centred:
        # Nodes on cell centres: the raster's own values.
        facet = r.facet[np.ix_(ir, ic)].astype(np.int32)
        on = facet >= 0
        mean[on] = r.mean[np.ix_(ir, ic)][on]
        var[on] = r.var[np.ix_(ir, ic)][on]
    else:
        uv = np.stack([uu.ravel(), vv.ravel()], axis=1)
        rows, cols = _nearest_cell(r, uv)
        facet = r.facet[rows, cols].astype(np.int32).reshape(n_v, n_u)
        on = facet >= 0
        m, s2 = surface_at(r, uv[on.ravel()])
        mean[on], var[on] = m, s2
    return np.stack([uu, vv, mean], axis=-1), var, facet


def _grid_steps(facades: Sequence[FacadeModel], step: float | None, max_points: int) -> list[float]:
    """Each façade's grid step (its raster cell for None), checked against ``max_points`` nodes."""
    max_points = _limit('max_points', max_points)
    if step is not None:
        step = _positive('step', step)
    steps = [f.surface.cell if step is None else step for f in facades]
    total = sum(int(np.prod(_node_counts(f.surface, s))) for f, s in zip(facades, steps))
    if total > max_points:
        factor = np.sqrt(total / max_points)
        raise InputError(f'the surface grid would have {total:,} nodes, more than max_points={max_points:,}: '
                         f'coarsen the step {max(steps)} m by a factor of {factor:.2f} or more '
                         f'(to at least {max(steps) * factor:.3g} m)')
    return steps


def surface_grid(facades: Sequence[FacadeModel], step: float | None = None, *,
                 max_points: int = 20_000_000) -> SurfaceGrid:
    """Sample every façade's mean surface on a regular grid of its plane.

    Grid nodes lie at ``u = u_0 + (j * step / cell + 0.5) * cell`` (likewise v), from the
    raster's first cell centre (``u_0`` its lower-left corner, ``cell`` its side) to its last.
    With ``step`` a multiple of the cell the nodes are cell centres and take the raster's
    values exactly; otherwise :func:`~uncertain_facade_map.pipeline.step7_queries.surface_at` interpolates. Only nodes whose
    cell (the one ``surface_at`` takes across a facet boundary) holds a facet are returned.

    Args:
        facades: the façade models.
        step: grid spacing on each façade plane, metres; None for each raster's own cell
            (``gp.grid_resolution``, 0.1 m by default).
        max_points: most grid nodes (before keeping the facet ones) to consider.

    Returns:
        The surface points: world point ``frame.to_world((u, v, mean_depth))`` (map frame,
        metres), ``std = sqrt(var)`` (metres), façade id and facet; façade by façade, each
        row-major (v rows, u fastest).

    Raises:
        InputError: ``step`` not positive and finite, or more than ``max_points`` nodes.
    """
    steps = _grid_steps(facades, step, max_points)
    xyz, std, facade, facet = [], [], [], []
    for f, s in zip(facades, steps):
        uvd, var, node_facet = _facade_nodes(f, s)
        on = node_facet >= 0
        xyz.append(f.frame.to_world(uvd[on]))
        std.append(np.sqrt(var[on]))
        facade.append(np.full(int(on.sum()), f.facade_id, np.int32))
        facet.append(node_facet[on])
    return SurfaceGrid(_cat(xyz, (0, 3)), _cat(std, (0,)), _cat(facade, (0,), np.int32), _cat(facet, (0,), np.int32),
                       None if step is None else float(step))


def _cat(parts: list[np.ndarray], empty_shape: tuple[int, ...], dtype=np.float64) -> np.ndarray:
    return np.concatenate(parts).astype(dtype, copy=False) if parts else np.empty(empty_shape, dtype)


def surface_mesh(facades: Sequence[FacadeModel], step: float | None = None, *,
                 max_points: int = 20_000_000) -> SurfaceMesh:
    """Triangulate every façade's mean surface on the grid of :func:`surface_grid`.

    Each grid square whose four corner nodes hold the same facet gives two triangles
    (split along the diagonal from its (u, v) lower-left to its upper-right corner).
    Squares with a corner off the facets or in another facet are left out, so depth steps
    between facets are not bridged. Vertices are the nodes used by a triangle; triangles
    are wound counter-clockwise in (u, v) for a right-handed façade frame (e_u x e_v = n),
    so their right-hand normals point outwards (a left-handed frame gets the other winding).

    Args:
        facades: the façade models.
        step: grid spacing on each façade plane, metres; None for each raster's own cell.
        max_points: most grid nodes to consider.

    Returns:
        The mesh: vertices (V, 3) map frame, metres; triangles (T, 3) int32; per-vertex
        std (metres), façade id and facet.

    Raises:
        InputError: ``step`` not positive and finite, or more than ``max_points`` nodes.
    """
    steps = _grid_steps(facades, step, max_points)
    vertices, triangles, std, facade, facet = [], [], [], [], []
    offset = 0
    for f, s in zip(facades, steps):
        uvd, var, node_facet = _facade_nodes(f, s)
        n_v, n_u = node_facet.shape
        if n_v < 2 or n_u < 2:
            continue
        a = node_facet[:-1, :-1]
        square = (a >= 0) & (a == node_facet[:-1, 1:]) & (a == node_facet[1:, :-1]) & (a == node_facet[1:, 1:])
        rows, cols = np.nonzero(square)
        if not len(rows):
            continue
        p00 = rows * n_u + cols
        p01, p10, p11 = p00 + 1, p00 + n_u, p00 + n_u + 1
        if np.linalg.det(f.frame.axes) > 0:
            tri = np.concatenate([np.stack([p00, p01, p11], 1), np.stack([p00, p11, p10], 1)])
        else:
            tri = np.concatenate([np.stack([p00, p11, p01], 1), np.stack([p00, p10, p11], 1)])
        used = np.zeros(n_v * n_u, dtype=bool)
        used[tri.ravel()] = True
        renumber = np.cumsum(used) - 1
        used = np.flatnonzero(used)
        local = renumber[tri]
        flat_uvd = uvd.reshape(-1, 3)[used]
        vertices.append(f.frame.to_world(flat_uvd))
        std.append(np.sqrt(var.ravel()[used]))
        facade.append(np.full(len(used), f.facade_id, np.int32))
        facet.append(node_facet.ravel()[used])
        triangles.append(local.reshape(-1, 3) + offset)
        offset += len(used)
    return SurfaceMesh(_cat(vertices, (0, 3)), _cat(triangles, (0, 3), np.int32), _cat(std, (0,)),
                       _cat(facade, (0,), np.int32), _cat(facet, (0,), np.int32),
                       None if step is None else float(step))


# --------------------------------------------------------------------------- voxels


def _depth_bounds(r: SurfaceRaster, shell: float) -> tuple[np.ndarray, np.ndarray]:
    """Per cell, bounds of the depth of voxel centres in that cell that can be in the shell.

    ``surface_at`` inside a cell blends cells of its 3 x 3 neighbourhood that hold one
    facet (or takes the cell itself), so the mean there lies between the neighbourhood's
    smallest and largest facet-cell mean. (H, W) arrays; +inf / -inf at cells off facets.
    """
    on = r.facet >= 0
    lo = minimum_filter(np.where(on, r.mean, np.inf), size=3, mode='constant', cval=np.inf) - shell
    hi = maximum_filter(np.where(on, r.mean, -np.inf), size=3, mode='constant', cval=-np.inf) + shell
    return np.where(on, lo, np.inf), np.where(on, hi, -np.inf)


def _expand(counts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For items with ``counts`` entries each: the item of every entry and its rank in the item."""
    item = np.repeat(np.arange(len(counts)), counts)
    starts = np.cumsum(counts) - counts
    return item, np.arange(int(counts.sum())) - starts[item]


def _shell_tiles(r: SurfaceRaster, shell: float, tile: int) -> tuple[np.ndarray, np.ndarray]:
    """Boxes in the façade frame that hold every voxel centre of the shell.

    A box is a tile of ``tile`` x ``tile`` raster cells (clipped to the raster) holding a
    facet cell, times the depth bounds of its facet cells (:func:`_depth_bounds`).

    Returns:
        ``(lower, upper)``: (B, 3) corners (u, v, d) of the boxes, metres, façade frame.
    """
    h, w = r.mean.shape
    lo, hi = _depth_bounds(r, shell)
    th, tw = -(-h // tile), -(-w // tile)
    lo_p = np.full((th * tile, tw * tile), np.inf)
    hi_p = np.full((th * tile, tw * tile), -np.inf)
    lo_p[:h, :w], hi_p[:h, :w] = lo, hi
    tlo = lo_p.reshape(th, tile, tw, tile).min(axis=(1, 3))
    thi = hi_p.reshape(th, tile, tw, tile).max(axis=(1, 3))
    ti, tj = np.nonzero(np.isfinite(tlo))
    lower = np.stack([r.origin[0] + tj * tile * r.cell, r.origin[1] + ti * tile * r.cell, tlo[ti, tj]], axis=1)
    upper = np.stack([r.origin[0] + np.minimum((tj + 1) * tile, w) * r.cell,
                      r.origin[1] + np.minimum((ti + 1) * tile, h) * r.cell, thi[ti, tj]], axis=1)
    return lower, upper


def _voxels_in_boxes(frame: FacadeFrame, lower: np.ndarray, upper: np.ndarray, resolution: float) -> np.ndarray:
    """Integer indices (K, 3) of the voxels whose centre lies in one of the façade-frame boxes.

    Walks the lines of voxel centres along the map axis closest to the façade normal that
    pass the boxes' map-frame bounds, and clips each line to its box (a slab test on the
    three pairs of faces). A centre on two boxes' common face may be listed twice.
    """
    axes, origin = frame.axes, frame.origin
    a = int(np.argmax(np.abs(axes[2])))  # lines run along this map axis
    b, c = [k for k in range(3) if k != a]
    bits = np.array([[(k >> m) & 1 for m in range(3)] for k in range(8)], dtype=bool)
    corners = np.where(bits[None], upper[:, None, :], lower[:, None, :]) @ axes + origin  # (B, 8, 3)
    bc_lo = corners[:, :, [b, c]].min(axis=1) / resolution - 0.5
    bc_hi = corners[:, :, [b, c]].max(axis=1) / resolution - 0.5
    j0 = np.ceil(bc_lo - _EPS).astype(np.int64)
    n = np.maximum(np.floor(bc_hi + _EPS).astype(np.int64) - j0 + 1, 0)
    box_of, rank = _expand(n[:, 0] * n[:, 1])
    jb = j0[box_of, 0] + rank // n[box_of, 1]
    jc = j0[box_of, 1] + rank % n[box_of, 1]

    # Line p(t) = base + t e_a; in façade coordinates q(t) = q0 + t * axes[:, a].
    base = np.zeros((len(jb), 3))
    base[:, b] = (jb + 0.5) * resolution
    base[:, c] = (jc + 0.5) * resolution
    q0 = (base - origin) @ axes.T
    t_min = np.full(len(jb), -np.inf)
    t_max = np.full(len(jb), np.inf)
    for k in range(3):
        slope = axes[k, a]
        lk, uk = lower[box_of, k], upper[box_of, k]
        if abs(slope) > 1e-12:
            t1, t2 = (lk - q0[:, k]) / slope, (uk - q0[:, k]) / slope
            t_min = np.maximum(t_min, np.minimum(t1, t2))
            t_max = np.minimum(t_max, np.maximum(t1, t2))
        else:
            out = (q0[:, k] < lk - 1e-9) | (q0[:, k] > uk + 1e-9)
            t_min[out], t_max[out] = np.inf, -np.inf
    k0 = np.ceil(t_min / resolution - 0.5 - _EPS)
    k1 = np.floor(t_max / resolution - 0.5 + _EPS)
    ok = k1 >= k0  # the normal's own axis bounds every line, so k0 and k1 are finite here
    count = np.zeros(len(jb), np.int64)
    count[ok] = (k1[ok] - k0[ok]).astype(np.int64) + 1
    line_of, rank = _expand(count)
    idx = np.empty((len(line_of), 3), np.int64)
    idx[:, a] = k0[line_of].astype(np.int64) + rank
    idx[:, b] = jb[line_of]
    idx[:, c] = jc[line_of]
    return idx


def _in_shell(f: FacadeModel, idx: np.ndarray, resolution: float, shell: float) -> np.ndarray:
    """(K,) bool: the voxel's centre is within ``f``'s raster, its nearest cell holds a facet,
    and its depth is within ``shell`` of the mean surface there."""
    r = f.surface
    h, w = r.mean.shape
    local = f.frame.to_local((idx + 0.5) * resolution)
    keep = ((local[:, 0] >= r.origin[0]) & (local[:, 0] <= r.origin[0] + w * r.cell)
            & (local[:, 1] >= r.origin[1]) & (local[:, 1] <= r.origin[1] + h * r.cell))
    sel = np.flatnonzero(keep)
    rows, cols = _nearest_cell(r, local[sel, :2])
    sel = sel[r.facet[rows, cols] >= 0]
    mean, _ = surface_at(r, local[sel, :2])
    keep[:] = False
    keep[sel[np.abs(local[sel, 2] - mean) <= shell]] = True
    return keep


def _shell_voxels(f: FacadeModel, resolution: float, shell: float) -> np.ndarray:
    """Integer indices (K, 3) of the voxels whose centre is within ``shell`` of ``f``'s surface.

    Candidates are enumerated exactly inside the boxes of :func:`_shell_tiles` (tiles of
    about :data:`_TILE` metres, at least two voxels), a batch of boxes at a time to bound
    memory; the exact test (:func:`_in_shell`) keeps the shell's. A voxel on a face two
    boxes share may be listed twice; the caller deduplicates.
    """
    tile = max(1, int(round(max(_TILE, 2 * resolution) / f.surface.cell)))
    lower, upper = _shell_tiles(f.surface, shell, tile)
    if not len(lower):
        return np.empty((0, 3), np.int64)
    # Batches of boxes holding about _BATCH candidate voxels each.
    volume = np.prod(upper - lower, axis=1) / resolution**3 + 1.0
    batch = np.floor(np.cumsum(volume) / _BATCH).astype(np.int64)
    parts = []
    for sel in np.split(np.arange(len(lower)), np.flatnonzero(np.diff(batch)) + 1):
        idx = _voxels_in_boxes(f.frame, lower[sel], upper[sel], resolution)
        parts.append(idx[_in_shell(f, idx, resolution, shell)])
    return np.concatenate(parts)


def _too_many(what: str, count: int, noun: str, name: str, limit: int, resolution: float, power: int) -> InputError:
    """The error for a product over its limit, with the factor to coarsen the resolution by.

    ``power`` is how the size scales with 1 / resolution (3 for voxels, 2 for cells).
    """
    factor = (count / limit) ** (1.0 / power)
    return InputError(f'{what} would hold {count:,} {noun}, more than {name}={limit:,}: coarsen the resolution '
                      f'{resolution:g} m by a factor of {factor:.2f} or more (to at least {resolution * factor:.3g} m)')


def voxel_occupancy(facades: Sequence[FacadeModel], resolution: float = 0.1, shell: float = 0.3, *,
                    band_back: float = BAND_BACK, band_front: float = BAND_FRONT,
                    max_voxels: int = 2_000_000, occupancy: PLSC = FIXED,
                    local: LocalSurface | None = None, registration_var: float = 0.0) -> VoxelOccupancy:
    """Occupancy of the map-frame voxels around the façades' mean surfaces.

    The grid is axis-aligned in the map frame, voxel (i, j, k) centred at
    ``((i, j, k) + 0.5) * resolution``. A voxel is kept when its centre, in some façade's
    frame, lies within that façade's raster, its nearest raster cell (the one
    :func:`~uncertain_facade_map.pipeline.step7_queries.surface_at` takes across a facet boundary) holds a facet, and its depth
    is within ``shell`` of the mean surface there. Each voxel is listed once (sorted by
    index, x slowest), however many façades it is near. Its probability is
    :func:`~uncertain_facade_map.pipeline.step7_queries.query_points` at its centre with the same ``resolution`` and band,
    i.e. the point-query service's answer; the query assigns a voxel to the nearest
    façade plane, which at a corner can be another façade than the one that selected it.
    Voxels the query assigns to no façade (possible only where the shell reaches past the
    band) are left out: their probability would only be the unknown 0.5.

    Args:
        facades: the façade models (``facades[i].facade_id == i``, as for ``query_points``).
        resolution: voxel side, metres.
        shell: half thickness of the shell around each surface along its normal, metres.
        band_back: query band behind a plane, metres (the map's ``extraction.band_back``).
        band_front: query band in front of it, metres (the map's ``extraction.band_front``).
        max_voxels: most voxels to produce.
        occupancy: the query's PLSC parameters (the map's learnt ones or the fixed formula's).
        local: the map's stored points read per point (``query.surface`` 'local'), as the
            query reads them; None: the rasters alone.
        registration_var: the map's scan-to-scan variance, m^2 (``FacadeMap.registration_var_``).

    Returns:
        The voxels: centres (M, 3) map frame, metres; integer indices (M, 3); p_occupied
        (M,); façade id (M,) int32 from the query.

    Raises:
        InputError: a non-positive resolution or shell, a bad band, or more voxels than
            ``max_voxels`` (checked first on an estimate, facet area times 2 * shell over
            resolution cubed, then on the count), with the factor to coarsen by.
    """
    resolution = _positive('resolution', resolution)
    shell = _positive('shell', shell)
    band_back, band_front = _band(band_back, band_front)
    max_voxels = _limit('max_voxels', max_voxels)
    area = sum(float((f.surface.facet >= 0).sum()) * f.surface.cell**2 for f in facades)
    estimate = int(area * 2 * shell / resolution**3)
    if estimate > 1.5 * max_voxels:
        raise _too_many('the voxel map (estimated from the facet area)', estimate, 'voxels', 'max_voxels', max_voxels,
                        resolution, 3)
    parts = [_shell_voxels(f, resolution, shell) for f in facades]
    idx = np.concatenate(parts) if parts else np.empty((0, 3), np.int64)
    if len(idx):  # one entry per voxel: sort the linear keys (np.unique hashes, and is far slower here)
        lo = idx.min(axis=0)
        span = idx.max(axis=0) - lo + 1
        keys = np.sort(((idx[:, 0] - lo[0]) * span[1] + (idx[:, 1] - lo[1])) * span[2] + (idx[:, 2] - lo[2]))
        keys = keys[np.r_[True, keys[1:] != keys[:-1]]]
        idx = np.stack([keys // (span[1] * span[2]), (keys // span[2]) % span[1], keys % span[2]], axis=1) + lo
    if len(idx) > max_voxels:
        raise _too_many('the voxel map', len(idx), 'voxels', 'max_voxels', max_voxels, resolution, 3)
    centres = (idx + 0.5) * resolution
    p = np.empty(len(idx))
    facade = np.empty(len(idx), np.int32)
    for start in range(0, len(idx), _BATCH):  # the query is pointwise: batches bound its memory
        part = slice(start, start + _BATCH)
        res = query_points(facades, centres[part], resolution, band_back, band_front, occupancy, local,
                           registration_var=registration_var)
        p[part], facade[part] = res.p_occupied, res.facade
    keep = facade >= 0
    return VoxelOccupancy(centres[keep], idx[keep], p[keep], facade[keep], resolution, shell)


# --------------------------------------------------------------------------- 2D grid of a height band


def _slab_corners(f: FacadeModel, band_back: float, band_front: float) -> np.ndarray:
    """(8, 3) map-frame corners of the box a façade's point query covers."""
    r = f.surface
    h, w = r.mean.shape
    u = (r.origin[0], r.origin[0] + w * r.cell)
    v = (r.origin[1], r.origin[1] + h * r.cell)
    return f.frame.to_world(np.array([[uu, vv, d] for uu in u for vv in v for d in (-band_back, band_front)]))


def _band_grid_cells(boxes: np.ndarray, resolution: float, z_min: float, z_max: float, margin: float,
                     max_cells: int, max_samples: int
                     ) -> tuple[np.ndarray, tuple[int, int], np.ndarray, np.ndarray, np.ndarray]:
    """The cells of :func:`height_band_grid` at one resolution.

    Args:
        boxes: (F, 8, 3) map-frame corners of each façade's query box (:func:`_slab_corners`).

    Returns:
        i0 (2,) int64 index of the lower-left cell; the grid's (H, W); (L,) layer centres,
        metres; rows and cols (C,) of the columns some façade's box reaches.

    Raises:
        InputError: more than ``max_cells`` cells or ``max_samples`` query points.
    """
    lo_xy = boxes[:, :, :2].min(axis=(0, 1))
    hi_xy = boxes[:, :, :2].max(axis=(0, 1))
    i0 = np.floor((lo_xy - margin) / resolution).astype(np.int64)
    i1 = np.ceil((hi_xy + margin) / resolution).astype(np.int64)
    width, height = (int(n) for n in i1 - i0)
    if width * height > max_cells:
        raise _too_many(f'the height band grid ({height} x {width})', width * height, 'cells', 'max_cells', max_cells,
                        resolution, 2)
    k0 = int(np.floor(z_min / resolution + 1e-9))
    k1 = max(int(np.ceil(z_max / resolution - 1e-9)), k0 + 1)
    layers = (np.arange(k0, k1) + 0.5) * resolution

    # Columns a façade's query region can reach (its xy box), the rest stays unknown.
    candidate = np.zeros((height, width), dtype=bool)
    for box in boxes:
        if box[:, 2].max() < layers[0] or box[:, 2].min() > layers[-1]:
            continue
        c0, r0 = (np.floor(box[:, :2].min(axis=0) / resolution).astype(np.int64) - i0).clip(0)
        c1, r1 = np.ceil(box[:, :2].max(axis=0) / resolution).astype(np.int64) - i0
        candidate[r0:r1, c0:c1] = True
    rows, cols = np.nonzero(candidate)
    if len(rows) * len(layers) > max_samples:
        factor = (len(rows) * len(layers) / max_samples) ** (1 / 3)
        raise InputError(f'the height band grid would query {len(rows):,} columns x {len(layers)} layers, more than '
                         f'max_samples={max_samples:,}: coarsen the resolution {resolution:g} m by a factor of '
                         f'{factor:.2f} or more (to at least {resolution * factor:.3g} m) or narrow the band')
    return i0, (height, width), layers, rows, cols


#: Doublings of the resolution :func:`height_band_grid` tries with ``coarsen``.
MAX_COARSENING = 40


def height_band_grid(facades: Sequence[FacadeModel], resolution: float, z_min: float, z_max: float, *,
                     margin: float = 1.0, band_back: float = BAND_BACK, band_front: float = BAND_FRONT,
                     max_cells: int = 4_000_000, max_samples: int = 50_000_000,
                     coarsen: bool = False, occupancy: PLSC = FIXED,
                     local: LocalSurface | None = None, registration_var: float = 0.0) -> OccupancyGrid2D:
    """2D occupancy grid of the height band ``z_min..z_max`` (map frame z).

    Cells are the voxel columns of :func:`voxel_occupancy` (side ``resolution``, cell
    (row, col) centred at ``((i0 + col + 0.5), (j0 + row + 0.5)) * resolution``). The band is
    sampled at the voxel layers that overlap it, centres ``(k + 0.5) * resolution``; a
    cell's probability is the largest :func:`~uncertain_facade_map.pipeline.step7_queries.query_points` probability (voxel side
    ``resolution``) over the layers whose centre some façade's band covers, NaN where none
    is. So the cell the wall passes through and those behind it (up to ``band_back``) are
    occupied, those in front (up to ``band_front``) free. The grid covers the map-frame xy
    box of every façade's query region (raster times band) grown by ``margin`` and snapped
    outwards to the cells; with no façades it is empty (0 x 0, origin 0).

    Args:
        facades: the façade models (``facades[i].facade_id == i``).
        resolution: cell side and vertical sampling step, metres.
        z_min: lower end of the band, metres, map frame.
        z_max: upper end of the band, metres, map frame (> ``z_min``).
        margin: unknown border around the façades' footprints, metres.
        band_back: query band behind a plane, metres (the map's ``extraction.band_back``).
        band_front: query band in front of it, metres (the map's ``extraction.band_front``).
        max_cells: most cells (H * W) of the grid.
        max_samples: most query points (columns a façade's query box reaches, times layers).
        coarsen: over either limit, try 2, 4, 8, ... times ``resolution`` (up to
            :data:`MAX_COARSENING` doublings) instead of raising; the grid's
            ``resolution`` says which was taken.
        occupancy: the query's PLSC parameters (the map's learnt ones or the fixed formula's).

    Returns:
        The grid: p (H, W) float64 in [0, 1] or NaN, row = y, column = x; origin (2,) of the
        lower-left corner, metres, map frame; its resolution.

    Raises:
        InputError: a non-positive resolution, ``z_max <= z_min``, non-finite bounds, a
            negative margin, a bad band, more than ``max_cells`` cells or more than
            ``max_samples`` query points (with ``coarsen``: still so after
            :data:`MAX_COARSENING` doublings).
    """
    resolution = _positive('resolution', resolution)
    z_min, z_max = float(z_min), float(z_max)
    if not (np.isfinite(z_min) and np.isfinite(z_max) and z_max > z_min):
        raise InputError(f'the height band needs finite z_min < z_max, got {z_min}, {z_max}')
    margin = float(margin)
    if not (np.isfinite(margin) and margin >= 0):
        raise InputError(f'margin must be >= 0, got {margin}')
    band_back, band_front = _band(band_back, band_front)
    max_cells = _limit('max_cells', max_cells)
    max_samples = _limit('max_samples', max_samples)
    if not len(facades):
        return OccupancyGrid2D(np.empty((0, 0)), np.zeros(2), resolution, z_min, z_max)
    boxes = np.stack([_slab_corners(f, band_back, band_front) for f in facades])  # (F, 8, 3)
    doublings = MAX_COARSENING if coarsen else 0
    for doubling in range(doublings + 1):
        try:
            i0, shape, layers, rows, cols = _band_grid_cells(boxes, resolution, z_min, z_max, margin, max_cells,
                                                             max_samples)
            break
        except InputError:
            if doubling == doublings:
                raise
            resolution *= 2.0
    x = (i0[0] + cols + 0.5) * resolution
    y = (i0[1] + rows + 0.5) * resolution
    best = np.full(len(rows), -np.inf)
    for start in range(0, len(rows), _BATCH):  # batches bound the query's memory
        part = slice(start, start + _BATCH)
        xy = np.stack([x[part], y[part]], axis=1)
        for z in layers:
            res = query_points(facades, np.c_[xy, np.full(len(xy), z)], resolution, band_back, band_front,
                               occupancy, local, registration_var=registration_var)
            best[part] = np.where(res.facade >= 0, np.maximum(best[part], res.p_occupied), best[part])
    p = np.full(shape, np.nan)
    p[rows, cols] = np.where(np.isfinite(best), best, np.nan)
    return OccupancyGrid2D(p, i0 * resolution, resolution, z_min, z_max)


@dataclass(frozen=True, eq=False)
class MapProducts:
    """Everything the node publishes about a map, as arrays (:func:`map_products`).

    Attributes:
        surface: the mean-surface samples (:func:`surface_grid`).
        mesh: the surface mesh (:func:`surface_mesh`), None for a map without façades.
        voxels: the 3D occupancy shell (:func:`voxel_occupancy`).
        grid: the 2D occupancy grid of the height band (:func:`height_band_grid`), None
            for a map without façades.
    """

    surface: SurfaceGrid
    mesh: SurfaceMesh | None
    voxels: VoxelOccupancy
    grid: OccupancyGrid2D | None


def map_products(facades: Sequence[FacadeModel], publish: Any, band_back: float = BAND_BACK,
                 band_front: float = BAND_FRONT, occupancy: PLSC = FIXED,
                 local: LocalSurface | None = None, registration_var: float = 0.0) -> MapProducts:
    """Every published product of a map at once (the node computes them in a helper process).

    Args:
        facades: the façade models.
        publish: the node's publish settings (attributes ``surface_step``, ``mesh_step``,
            ``voxel_resolution``, ``voxel_shell``, ``grid_resolution``, ``grid_z_min``,
            ``grid_z_max``, ``grid_max_cells``; a :class:`~uncertain_facade_map.params.PublishConfig`).
        band_back: the map's band behind a plane, metres.
        band_front: the map's band in front of it, metres.
        occupancy: the query's PLSC parameters (the map's learnt ones or the fixed formula's).
        local: the map's stored points read per point, for the occupancy products (None:
            the rasters alone). The occupancy products keep the solid event (a building is
            solid behind its façades for a planner), whatever ``query.occupancy_event`` says.
        registration_var: the map's variance of scan-to-scan disagreement
            (``FacadeMap.registration_var_``), m^2, added to every answer's.
    """
    facades = list(facades)
    return MapProducts(
        surface=surface_grid(facades, publish.surface_step),
        mesh=surface_mesh(facades, publish.mesh_step) if facades else None,
        voxels=voxel_occupancy(facades, publish.voxel_resolution, publish.voxel_shell, band_back=band_back,
                               band_front=band_front, occupancy=occupancy, local=local,
                               registration_var=registration_var),
        grid=band_grid(facades, publish, band_back, band_front, occupancy, local, registration_var) if facades else None)


def band_grid(facades: Sequence[FacadeModel], publish: Any, band_back: float = BAND_BACK,
              band_front: float = BAND_FRONT, occupancy: PLSC = FIXED,
              local: LocalSurface | None = None, registration_var: float = 0.0) -> OccupancyGrid2D:
    """The node's 2D grid: :func:`height_band_grid` at ``publish.grid_resolution`` or, for a
    map too wide for ``publish.grid_max_cells`` cells, at the finest of 2, 4, 8, ... times it."""
    return height_band_grid(list(facades), publish.grid_resolution, publish.grid_z_min, publish.grid_z_max,
                            band_back=band_back, band_front=band_front, max_cells=publish.grid_max_cells,
                            max_samples=max(50_000_000, 25 * publish.grid_max_cells), coarsen=True,
                            occupancy=occupancy, local=local, registration_var=registration_var)
