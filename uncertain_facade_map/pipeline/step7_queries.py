"""Queries: the surface at façade locations, and everything about 3D points.

At a façade location (u, v) the mean depth and variance come from the façade's raster:
bilinear between the four nearest cell centres when they lie in one facet (smooth
inside a facet), the nearest cell otherwise (a depth step between facets stays a step).

A 3D point belongs to the façade whose band (``band_back`` behind to ``band_front`` in
front of the plane) and raster extent contain it, the nearest plane winning; it gets the
façade id, mean depth, variance, noise variance, signed distance to the mean surface along
the façade normal (positive outside the building) and the occupancy probability of the
voxel centred there (:mod:`~uncertain_facade_map.pipeline.step8_occupancy`).

:func:`query_points` runs the assignment and the raster's reading compiled
(:mod:`~uncertain_facade_map.pipeline.raster_kernels`, the same answers to the last bit);
:func:`assign_facades`, :func:`surface_at` and :func:`nearer_step_faces` are their numpy
reference (and serve the callers that read one raster).
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass
from typing import Sequence

import numpy as np
from scipy import ndimage

from ..datatypes import SOURCE_GLOBAL, FacadeModel, SurfaceRaster
from ..errors import InputError
from ..params import QueryConfig
from .raster_kernels import (
    SERIAL_BELOW,
    PackedRasters,
    assign_all,
    assign_all_serial,
    packed,
    raster_answer_all,
    raster_answer_all_serial,
)
from .step7_local_surface import LocalReading, LocalSurface, for_query, raster_agreement
from .step8_occupancy import FIXED, PLSC, UNKNOWN, half_depth, occupancy_model

#: The answers of a point query, in order (:class:`PointQuery`; ``normal`` is (N, 3), the rest (N,)).
ANSWER_FIELDS = ('facade', 'mean_depth', 'variance', 'noise_variance', 'signed_distance', 'p_occupied', 'normal')

#: What ``p_occupied`` is the probability of (see :func:`query_points`).
EVENTS = ('surface', 'solid')

#: Points handled at once (bounds memory of the (N, F) façade test).
CHUNK = 262_144
#: Depth-step faces further than this within the plane are not searched (metres).
STEP_REACH = 0.3
#: (point, candidate face) pairs :func:`nearer_step_faces` tests at once (bounds its memory).
_CANDIDATES = 1 << 20


def surface_at(raster: SurfaceRaster, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean depth and variance of a façade's surface at (N, 2) locations (u, v), metres.

    Locations outside the raster get the value of the nearest edge cell.

    Returns:
        ``(mean, var)``, each (N,), metres and m^2.
    """
    h, w = raster.mean.shape
    fu = (uv[:, 0] - raster.origin[0]) / raster.cell - 0.5
    fv = (uv[:, 1] - raster.origin[1]) / raster.cell - 0.5
    c0 = np.clip(np.floor(fu).astype(np.int64), 0, max(w - 2, 0))
    r0 = np.clip(np.floor(fv).astype(np.int64), 0, max(h - 2, 0))
    c1 = np.minimum(c0 + 1, w - 1)
    r1 = np.minimum(r0 + 1, h - 1)
    tu = np.clip(fu - c0, 0.0, 1.0)
    tv = np.clip(fv - r0, 0.0, 1.0)
    facet = raster.facet
    same = (facet[r0, c0] == facet[r0, c1]) & (facet[r0, c0] == facet[r1, c0]) & (facet[r0, c0] == facet[r1, c1])
    w00, w01, w10, w11 = (1 - tu) * (1 - tv), tu * (1 - tv), (1 - tu) * tv, tu * tv
    out = []
    for grid in (raster.mean, raster.var):
        bilinear = w00 * grid[r0, c0] + w01 * grid[r0, c1] + w10 * grid[r1, c0] + w11 * grid[r1, c1]
        rn = np.where(tv < 0.5, r0, r1)
        cn = np.where(tu < 0.5, c0, c1)
        out.append(np.where(same, bilinear, grid[rn, cn]))
    return out[0], out[1]


def step_depth_range(raster: SurfaceRaster, reach: float) -> tuple[np.ndarray, np.ndarray]:
    """(H, W) lowest and highest mean depth of the observed cells that
    :func:`nearer_step_faces` searches around each cell (``2 ceil(reach / cell) + 3`` cells
    square), metres; +inf and -inf where there are none."""
    size = 2 * int(np.ceil(reach / raster.cell)) + 3
    observed = raster.source != SOURCE_GLOBAL
    lo = ndimage.minimum_filter(np.where(observed, raster.mean, np.inf), size=size, mode='constant', cval=np.inf)
    hi = ndimage.maximum_filter(np.where(observed, raster.mean, -np.inf), size=size, mode='constant', cval=-np.inf)
    return lo, hi


#: Per raster (the rasters are immutable), its :func:`step_depth_range` per reach: queries
#: of the same map reuse them (the filters cost more than a small query's search).
_DEPTH_RANGES: weakref.WeakKeyDictionary[SurfaceRaster, dict[float, tuple[np.ndarray, np.ndarray]]] = \
    weakref.WeakKeyDictionary()


def cached_step_depth_range(raster: SurfaceRaster, reach: float) -> tuple[np.ndarray, np.ndarray]:
    """:func:`step_depth_range`, computed once per raster and reach (read-only arrays)."""
    per_reach = _DEPTH_RANGES.get(raster)
    if per_reach is None:
        per_reach = _DEPTH_RANGES.setdefault(raster, {})
    out = per_reach.get(reach)
    if out is None:
        lo, hi = step_depth_range(raster, reach)
        lo.setflags(write=False)
        hi.setflags(write=False)
        out = per_reach.setdefault(reach, (lo, hi))
    return out


def nearer_step_faces(raster: SurfaceRaster, uvd: np.ndarray, distance: np.ndarray, var: np.ndarray,
                      reach: float, depth_range: tuple[np.ndarray, np.ndarray] | None = None
                      ) -> tuple[np.ndarray, np.ndarray]:
    """Distances to the faces of depth steps where they are nearer than the surface along the normal.

    The raster is a height field: where the mean depth jumps between two adjacent cells
    (a window's reveal, the side of a pillar or a balcony), the surface between them is
    the face across the cell boundary, perpendicular to the plane. A point on that face
    lies at some depth between the two cells' depths, often far from either along the
    normal, yet on the surface. Its distance is the distance, within the plane, to the
    nearest such face whose depth range holds the point's depth (at most ``reach`` away).
    Faces next to a cell of the global prior are not faces of the observed surface and
    are skipped. The variance there is the larger of the two cells' plus the uniform
    uncertainty of the step's position within a cell, ``cell^2 / 12``.

    Args:
        raster: the façade's raster.
        uvd: (N, 3) points in the façade frame, metres.
        distance: (N,) signed distances along the normal, metres.
        var: (N,) surface variance there, m^2.
        reach: faces further than this within the plane are not searched, metres.
        depth_range: :func:`step_depth_range` of ``raster`` and ``reach``; None: the cached
            one (:func:`cached_step_depth_range`).

    Returns:
        ``(distance, var)``: (N,) signed distances (the sign of the distance along the
        normal: outside or inside) and variances, changed where a face is nearer.
    """
    distance, var = distance.copy(), var.copy()
    cell = raster.cell
    todo = np.flatnonzero(np.abs(distance) > 0.25 * cell)
    if not len(todo) or reach <= 0:
        return distance, var
    h, w = raster.mean.shape
    mean, cell_var = raster.mean, raster.var
    observed = raster.source != SOURCE_GLOBAL
    k = int(np.ceil(reach / cell))
    # A face within reach spans depths within the observed cells' range around the point
    # (the (2k + 3)^2 cells searched below): points outside it, most of them off steps,
    # need no search. Points off the raster are searched.
    lo, hi = cached_step_depth_range(raster, reach) if depth_range is None else depth_range
    r0 = np.floor((uvd[todo, 1] - raster.origin[1]) / cell).astype(np.int64)
    c0 = np.floor((uvd[todo, 0] - raster.origin[0]) / cell).astype(np.int64)
    on = (r0 >= 0) & (r0 < h) & (c0 >= 0) & (c0 < w)
    rc, cc = np.clip(r0, 0, h - 1), np.clip(c0, 0, w - 1)
    d_all = uvd[todo, 2]
    todo = todo[~on | ((lo[rc, cc] <= d_all) & (d_all <= hi[rc, cc]))]
    if not len(todo):
        return distance, var
    u = (uvd[todo, 0] - raster.origin[0]) / cell
    v = (uvd[todo, 1] - raster.origin[1]) / cell
    d = uvd[todo, 2]
    row, col = np.floor(v).astype(np.int64), np.floor(u).astype(np.int64)
    best = np.abs(distance[todo]) / cell
    best_var = var[todo]
    # The candidate faces of every point at once: (K,) offsets of the face's first cell
    # (dr, dc) and its direction (across u: the face at u = c + 1; else at v = r + 1).
    dr, dc, across_u = (a.ravel() for a in np.meshgrid(np.arange(-k - 1, k + 1), np.arange(-k - 1, k + 1),
                                                        [True, False], indexing='ij'))
    step = max(1, _CANDIDATES // len(dr))
    for s in range(0, len(todo), step):
        p = slice(s, s + step)
        r, c = row[p, None] + dr, col[p, None] + dc  # (B, K)
        r2, c2 = r + ~across_u, c + across_u
        ok = (r >= 0) & (c >= 0) & (r2 < h) & (c2 < w)
        ra, ca = np.where(ok, r, 0), np.where(ok, c, 0)
        rb, cb = np.where(ok, r2, 0), np.where(ok, c2, 0)
        ma, mb = mean[ra, ca], mean[rb, cb]
        dp = d[p, None]
        ok &= observed[ra, ca] & observed[rb, cb] & (np.minimum(ma, mb) <= dp) & (dp <= np.maximum(ma, mb))
        # Distances (cell units) to the faces that span the point's depth only.
        i, j = np.nonzero(ok)
        ui, vi, ri, ci = u[p][i], v[p][i], r[i, j], c[i, j]
        g = np.where(across_u[j], np.hypot(ui - (ci + 1), vi - np.clip(vi, ri, ri + 1)),
                     np.hypot(vi - (ri + 1), ui - np.clip(ui, ci, ci + 1)))
        gap = np.full(ok.shape, np.inf)
        gap[i, j] = np.where(g * cell <= reach, g, np.inf)
        # The first nearest face in the order (dr, dc, across u first), as a search that
        # takes a face only when it is strictly nearer than the best so far.
        first = np.argmin(gap, axis=1)
        rows = np.arange(len(first))
        g = gap[rows, first]
        nearer = g < best[p]
        face_var = np.maximum(cell_var[ra[rows, first], ca[rows, first]],
                              cell_var[rb[rows, first], cb[rows, first]]) + cell**2 / 12
        best[p] = np.where(nearer, g, best[p])
        best_var[p] = np.where(nearer, face_var, best_var[p])
    moved = best < np.abs(distance[todo]) / cell
    idx = todo[moved]
    distance[idx] = np.where(distance[idx] < 0, -1.0, 1.0) * best[moved] * cell
    var[idx] = best_var[moved]
    return distance, var


@dataclass(frozen=True, eq=False)
class PointQuery:
    """Answers for N 3D points (the command line's R.npz holds these arrays).

    Attributes:
        facade: (N,) int32 façade id, -1 where the point belongs to no façade.
        mean_depth: (N,) mean surface depth at the point's façade location, metres.
        variance: (N,) surface variance there, m^2.
        noise_variance: (N,) sigma_eta^2, m^2.
        signed_distance: (N,) point depth minus mean depth, metres, positive outside.
        p_occupied: (N,) occupancy probability of the voxel centred at the point.
        normal: (N, 3) unit outward normal of the mean surface at the point, map frame: the
            direction of the gradient of ``signed_distance`` with respect to the point's
            position (``(-dm/du, -dm/dv, 1)`` of the raster's mean depth ``m`` in the façade
            frame; the face's, within the plane, where a depth step's face is nearer; the
            local plane's normal blended in with the local reading's weight); NaN where the
            point belongs to no façade. A localiser's point-to-surface residual is
            ``signed_distance``, its Jacobian with respect to the point ``normal`` (scaled).
            No uncertainty: the rasters hold the mean's marginal variance, not its slopes'.
    """

    facade: np.ndarray
    mean_depth: np.ndarray
    variance: np.ndarray
    noise_variance: np.ndarray
    signed_distance: np.ndarray
    p_occupied: np.ndarray
    normal: np.ndarray

    def as_dict(self) -> dict[str, np.ndarray]:
        """The arrays by name."""
        return {k: getattr(self, k) for k in ANSWER_FIELDS}


def raster_bounds(raster: SurfaceRaster) -> tuple[float, float, float, float]:
    """``(u_min, u_max, v_min, v_max)`` of a raster's cells, metres, façade frame."""
    h, w = raster.mean.shape
    return (raster.origin[0], raster.origin[0] + w * raster.cell, raster.origin[1], raster.origin[1] + h * raster.cell)


#: Metres added to a point's ``|d|`` from a façade without a facet at the point when
#: façades compete for it (:func:`assign_facades`).
NO_FACET_PENALTY = 1.0


def assign_facades(facades: Sequence[FacadeModel], xyz: np.ndarray, band_back: float, band_front: float
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Façade of each 3D point and its façade coordinates.

    Args:
        facades: the façade models.
        xyz: (N, 3) points, metres, map frame.
        band_back: metres behind a plane still belonging to it.
        band_front: metres in front of it.

    Returns:
        ``(facade, uvd)``: (N,) int32 index into ``facades`` (-1 for none) and (N, 3) the
        point in that façade's frame (NaN for none).

    A point within several façades' slabs goes to the one with the smallest ``|d|``, where
    a façade whose raster holds no facet at the point counts ``NO_FACET_PENALTY`` further:
    near a corner, the air in front of one wall lies in the margin of the other wall's
    raster, where only that wall's global prior holds, and would otherwise read as that
    wall's solid; but a hole in a wall (an occlusion) is still the wall's, not that of a
    recess more than the penalty behind it.
    """
    n = len(xyz)
    best = np.full(n, -1, dtype=np.int32)
    best_abs = np.full(n, np.inf)
    uvd = np.full((n, 3), np.nan)
    for i, f in enumerate(facades):
        r = f.surface
        h, w = r.mean.shape
        u0, u1, v0, v1 = raster_bounds(r)
        # Cheap pre-selection by the map-frame box around the façade's slab.
        corners = f.frame.to_world(np.array([[u, v, d] for u in (u0, u1) for v in (v0, v1)
                                             for d in (-band_back, band_front)]))
        lo, hi = corners.min(axis=0), corners.max(axis=0)
        cand = np.flatnonzero(np.all((xyz >= lo) & (xyz <= hi), axis=1))
        if not len(cand):
            continue
        local = f.frame.to_local(xyz[cand])
        inside = ((local[:, 0] >= u0) & (local[:, 0] <= u1) & (local[:, 1] >= v0) & (local[:, 1] <= v1)
                  & (local[:, 2] >= -band_back) & (local[:, 2] <= band_front))
        col = np.clip(((local[:, 0] - u0) / r.cell).astype(np.int64), 0, w - 1)
        row = np.clip(((local[:, 1] - v0) / r.cell).astype(np.int64), 0, h - 1)
        key = np.abs(local[:, 2]) + np.where(r.facet[row, col] >= 0, 0.0, NO_FACET_PENALTY)
        better = inside & (key < best_abs[cand])
        sel = cand[better]
        best[sel] = i
        best_abs[sel] = key[better]
        uvd[sel] = local[better]
    return best, uvd


def query_points(facades: Sequence[FacadeModel], xyz: np.ndarray, resolution: float, band_back: float,
                 band_front: float, occupancy: PLSC = FIXED, local: LocalSurface | None = None,
                 event: str = 'solid', registration_var: float = 0.0, rasters: PackedRasters | None = None,
                 reach: float = 0.0) -> PointQuery:
    """Answer the 3D point query for (N, 3) points in the map frame.

    Args:
        facades: the façade models (``facades[i].facade_id == i``).
        xyz: (N, 3) float64 points, metres, map frame.
        resolution: voxel side for the occupancy probability, metres.
        band_back: see :func:`assign_facades`.
        band_front: see :func:`assign_facades`.
        occupancy: the occupancy's PLSC parameters (the map's learnt ones,
            ``FacadeMap.occupancy_``), or the fixed formula's.
        local: the map's stored points read per point where they are dense
            (:mod:`~uncertain_facade_map.pipeline.step7_local_surface`, ``query.surface``
            'local'), blended with the raster; None: the raster alone (the paper's reading).
        event: what ``p_occupied`` is the probability of (``query.occupancy_event``):
            'surface', that the surface crosses the voxel (the same in front and behind);
            'solid', that the voxel lies at least partly behind the surface.
        rasters: ``facades`` packed (:class:`~.raster_kernels.PackedRasters`) when the caller
            keeps them (a tiled map's views); None: :func:`~.raster_kernels.packed`'s, cached
            for the few most recent maps.
        reach: metres (``query.local_reach``): a point that neither a raster nor the local
            reading within its radius answers is read from the local plane of its nearest
            stored points if the nearest lies within this, with the variance of the plane
            (and of its gap, ``LocalSurface.gap_variance``) plus its façade's prior variance
            (``global_var_``): off every raster, an answer about where the surface is, never
            a tight one far from the data. 0: none.

    Returns:
        The answers; NaN depth, variance, noise variance and distance, and occupancy 0.5,
        where a point belongs to no façade.

    Raises:
        InputError: a non-(N, 3) array, NaN or infinite coordinates, a resolution <= 0 or
            an unknown event.
    """
    xyz = np.asarray(xyz, dtype=np.float64)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise InputError(f'query points must be an (N, 3) array, got shape {xyz.shape}')
    if not np.isfinite(xyz).all():
        raise InputError(f'{int((~np.isfinite(xyz)).any(axis=1).sum())} query points have NaN or infinite coordinates')
    if not resolution > 0:
        raise InputError(f'resolution must be positive, got {resolution}')
    if event not in EVENTS:
        raise InputError(f'occupancy event must be one of {", ".join(EVENTS)}, got {event!r}')
    n = len(xyz)
    facade = np.full(n, -1, dtype=np.int32)
    mean, var, noise, dist = (np.full(n, np.nan) for _ in range(4))
    normal = np.zeros((n, 3))  # the occupancy's (the façade's, the local plane's where it leads)
    surface_normal = np.full((n, 3), np.nan)
    rasters = packed(facades, STEP_REACH) if rasters is None else rasters
    normals = rasters.axes[:, 2]  # the façades' outward normals (FacadeFrame.normal)
    boxes = rasters.boxes(band_back, band_front)
    for start in range(0, n, CHUNK):
        part = slice(start, min(start + CHUNK, n))
        which, uvd = _assign(rasters, boxes, xyz[part], band_back, band_front)
        reading = local.read(xyz[part]) if local is not None else None
        if reading is not None:
            # Points the raster's bands miss but dense stored points hold: their nearest
            # stored point's façade, read in its frame. The raster says nothing there (off
            # its cells: a piece of wall too small to be a façade, beside it; beyond its
            # band: another wall behind or before it, which the raster would read as
            # metres off its own surface): the local reading answers alone, up to the radius.
            weight = reading.weight.copy()
            adopt = (which < 0) & (reading.facade >= 0)
            which[adopt] = reading.facade[adopt]
            weight[adopt] = 1.0
            for i in np.unique(which[adopt]):
                sel = np.flatnonzero(adopt & (which == i))
                uvd[sel] = facades[i].frame.to_local(xyz[part][sel])
        answer, grad = _raster_answer_compiled(rasters, which, uvd)
        if reading is not None:
            answer, grad = _blend(answer, reading, weight, grad)
        facade[part] = which
        mean[part], var[part], noise[part], dist[part] = answer[:4]
        surface_normal[part] = grad / np.linalg.norm(grad, axis=1, keepdims=True)
        normal[part] = np.where((which >= 0)[:, None], normals[np.maximum(which, 0)] if len(normals) else 0.0, 0.0)
        if reading is not None:
            use_local = weight >= 0.5
            normal[part][use_local] = reading.normal[use_local]
            if reach > local.radius:
                _answer_far(facades, local, xyz, np.arange(part.start, part.stop)[which < 0], reach, facade, mean,
                            var, noise, dist, surface_normal, normal)
    var = var + registration_var  # scan-to-scan disagreement (FacadeMap.registration_var_), m^2
    noise0 = np.where(np.isfinite(noise), noise, 0.0)
    if event == 'solid':
        p = occupancy.solid(dist, var, noise0, resolution)
    else:
        p = occupancy.surface(dist, var, noise0, half_depth(normal, resolution), outside=UNKNOWN)
    return PointQuery(facade, mean, var, noise, dist, p, surface_normal)


def _answer_far(facades: Sequence[FacadeModel], local: LocalSurface, xyz: np.ndarray, idx: np.ndarray, reach: float,
                facade: np.ndarray, mean: np.ndarray, var: np.ndarray, noise: np.ndarray, dist: np.ndarray,
                surface_normal: np.ndarray, normal: np.ndarray) -> None:
    """Answer the points ``idx`` of (N, 3) ``xyz`` (none answered yet) whose nearest stored
    point lies within ``reach`` metres from the local plane of their nearest stored points
    (see :func:`query_points`), in place in the (N,) and (N, 3) answer arrays."""
    if not len(idx) or not len(local.points):
        return
    fid, s, scatter, plane_var, n, rho, nearest, offset = local.raw(xyz[idx], radius=reach)
    ok = (fid >= 0) & (nearest < reach) & np.isfinite(s)
    idx, fid, s, scatter, plane_var, n, rho, offset = (a[ok] for a in (idx, fid, s, scatter, plane_var, n, rho,
                                                                       offset))
    if not len(idx):
        return
    c2 = local.calibration_ ** 2
    prior = np.array([f.global_var_ for f in facades])[fid]
    depth = np.einsum('ni,ni->n', xyz[idx] - np.array([facades[i].frame.origin for i in fid]),
                      np.array([facades[i].frame.normal for i in fid]))
    facade[idx] = fid
    dist[idx] = s
    var[idx] = c2 * plane_var + local.gap_variance(rho, offset) + prior
    noise[idx] = c2 * scatter
    mean[idx] = depth - s
    surface_normal[idx] = n
    normal[idx] = n


def _assign(rasters: PackedRasters, boxes: tuple[np.ndarray, np.ndarray], xyz: np.ndarray, band_back: float,
            band_front: float) -> tuple[np.ndarray, np.ndarray]:
    """:func:`assign_facades` by the compiled kernel (:func:`~.raster_kernels.assign_all`)."""
    n = len(xyz)
    which, uvd = np.full(n, -1, np.int32), np.full((n, 3), np.nan)
    kernel = assign_all if n >= SERIAL_BELOW else assign_all_serial
    kernel(np.ascontiguousarray(xyz, dtype=np.float64), rasters.origin, rasters.axes, rasters.corner, rasters.cell,
           rasters.shape, rasters.offset, rasters.facet, boxes[0], boxes[1], float(band_back), float(band_front),
           NO_FACET_PENALTY, which, uvd)
    return which, uvd


def _raster_answer_compiled(rasters: PackedRasters, which: np.ndarray, uvd: np.ndarray
                            ) -> tuple[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray], np.ndarray]:
    """:func:`_raster_answer` by the compiled kernel (:func:`~.raster_kernels.raster_answer_all`),
    and the (N, 3) gradient of the signed distance, map frame (NaN where ``which`` is -1)."""
    n = len(which)
    mean, var, noise, dist = (np.empty(n) for _ in range(4))
    grad = np.empty((n, 3))
    kernel = raster_answer_all if n >= SERIAL_BELOW else raster_answer_all_serial
    kernel(np.ascontiguousarray(which, dtype=np.int32), np.ascontiguousarray(uvd, dtype=np.float64),
           rasters.corner, rasters.cell, rasters.shape, rasters.offset, rasters.mean, rasters.var, rasters.facet,
           rasters.observed, rasters.lo, rasters.hi, rasters.noise, rasters.reach, mean, var, noise, dist, grad)
    # (u, v, d) components to the map frame: the façade's axes' rows are e_u, e_v, n.
    if len(rasters.axes):
        grad = np.einsum('ni,nij->nj', grad, rasters.axes[np.maximum(which, 0)])
    return (mean, var, noise, dist, uvd[:, 2]), grad


def _raster_answer(facades: Sequence[FacadeModel], which: np.ndarray, uvd: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The raster's reading (the paper's) of a chunk's points: ``(mean depth, variance,
    noise variance, signed distance, depth)``, each (N,), NaN where ``which`` is -1."""
    n = len(which)
    mean, var, noise, dist = (np.full(n, np.nan) for _ in range(4))
    for i in np.unique(which[which >= 0]):
        sel = np.flatnonzero(which == i)
        m, v = surface_at(facades[i].surface, uvd[sel, :2])
        mean[sel] = m
        noise[sel] = facades[i].noise_var
        dist[sel], var[sel] = nearer_step_faces(facades[i].surface, uvd[sel], uvd[sel, 2] - m, v, STEP_REACH)
    return mean, var, noise, dist, uvd[:, 2]


def _blend(answer: tuple[np.ndarray, ...], reading: LocalReading, w: np.ndarray, grad: np.ndarray
           ) -> tuple[tuple[np.ndarray, ...], np.ndarray]:
    """The raster's answer blended with the local reading by the (N,) weights ``w`` (the
    reading's, :mod:`~uncertain_facade_map.pipeline.step7_local_surface` step 5, or 1 off
    the raster), the raster's share scaled by its agreement with the local plane
    (:func:`~uncertain_facade_map.pipeline.step7_local_surface.raster_agreement`): the
    mixture's mean and variance, so that neither jumps where the weight moves. The (N, 3)
    gradient of the signed distance blends alike (the local plane's is its normal; the
    weight held fixed)."""
    mean, var, noise, dist, depth = (a.copy() for a in answer)
    grad = grad.copy()
    sel = np.flatnonzero((w > 0) & np.isfinite(dist))
    ws, s_l, s_r = w[sel], reading.signed_distance[sel], dist[sel]
    # The local reading's posterior share: the raster keeps its weight where it agrees with
    # the local plane and loses it where it lies several sigmas off (another layer, a face).
    agree = raster_agreement(s_l, s_r, var[sel] + reading.variance[sel] - reading.gap_variance[sel]
                             + reading.noise_variance[sel])
    ws = ws / (ws + (1.0 - ws) * agree)
    dist[sel] = ws * s_l + (1.0 - ws) * s_r
    var[sel] = ws * reading.variance[sel] + (1.0 - ws) * var[sel] + ws * (1.0 - ws) * np.square(s_l - s_r)
    noise[sel] = ws * reading.noise_variance[sel] + (1.0 - ws) * noise[sel]
    mean[sel] = depth[sel] - dist[sel]
    grad[sel] = ws[:, None] * reading.normal[sel] + (1.0 - ws)[:, None] * grad[sel]
    return (mean, var, noise, dist, depth), grad


def query_map(facades: Sequence[FacadeModel], stored_points: dict[int, np.ndarray], xyz: np.ndarray,
              resolution: float, band_back: float, band_front: float, learnt: PLSC, config: QueryConfig,
              local: LocalSurface | None | bool = True, registration_var: float = 0.0,
              rasters: PackedRasters | None = None) -> PointQuery:
    """What the command line's ``query`` and the node's ``query_points`` answer: :func:`query_points`
    with the ``query.*`` settings (the reading, the occupancy's parameters and event).

    Args:
        facades: the façade models.
        stored_points: per building label, its stored points (``FacadeMap.points``).
        xyz: (N, 3) points, metres, map frame.
        resolution: voxel side of the occupancy probability, metres.
        band_back: the map's band behind a plane, metres.
        band_front: the map's band in front of it, metres.
        learnt: the map's learnt PLSC parameters (``FacadeMap.occupancy_``).
        config: the query settings.
        local: the local surface of ``facades`` and ``stored_points`` when the caller keeps
            one (the node, per snapshot); True: built here as ``config`` says.
        registration_var: the map's scan-to-scan variance (``FacadeMap.registration_var_``),
            m^2, added to every answered point's variance.
        rasters: ``facades`` packed, when the caller keeps them (see :func:`query_points`).
    """
    if local is True:
        local = for_query(facades, stored_points, config)
    return query_points(facades, xyz, resolution, band_back, band_front, occupancy_model(learnt, config.occupancy),
                        local or None, config.occupancy_event, registration_var, rasters, config.local_reach)
