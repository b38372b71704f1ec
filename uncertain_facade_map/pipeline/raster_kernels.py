"""Compiled kernels of the raster's reading (:mod:`.step7_queries`, issue 27).

The façade assignment (:func:`~.step7_queries.assign_facades`), the surface at a point
(:func:`~.step7_queries.surface_at`) and the search of nearer depth-step faces
(:func:`~.step7_queries.nearer_step_faces`) point by point in one compiled loop over both
cores, on all façades' rasters packed into flat arrays (:class:`PackedRasters`, built once
per map). The numpy functions stay the reference: same formulas, same order of the
candidate faces, same ties.
"""

from __future__ import annotations

import threading
import weakref
from typing import Sequence

import numpy as np
from numba import njit, prange

from ..datatypes import SOURCE_GLOBAL, FacadeModel
from ..threads import serial_twin

_BATCH = 512


class PackedRasters:
    """All façades' frames and rasters in flat arrays (read by the kernels).

    Attributes:
        origin: (F, 3) façade frame origins, map frame, metres; ``axes``: (F, 3, 3) rows
            e_u, e_v, n.
        corner: (F, 2) raster origin (u, v), metres; ``cell``: (F,) cell side, metres;
            ``shape``: (F, 2) (H, W); ``offset``: (F,) first cell of each raster in the flat
            arrays (row-major).
        mean, var: flat mean depth (metres) and variance (m^2) of all cells.
        facet: flat int32 facet (-1 global prior); ``observed``: flat bool (not the global
            prior).
        lo, hi: flat :func:`~.step7_queries.step_depth_range` of each raster at ``reach``.
        noise: (F,) noise variance of each façade, m^2.
        reach: the step faces' search reach, metres.
    """

    def __init__(self, facades: Sequence[FacadeModel], reach: float) -> None:
        from .step7_queries import cached_step_depth_range

        f = len(facades)
        self.reach = float(reach)
        self.origin, self.axes, self.corner, self.cell, self.shape = _geometry(facades)
        sizes = self.shape[:, 0] * self.shape[:, 1]
        self.offset = np.r_[0, np.cumsum(sizes)[:-1]].astype(np.int64) if f else np.empty(0, np.int64)

        def flat(get, dtype):
            return np.concatenate([np.ravel(get(m)) for m in facades]).astype(dtype) if f else np.empty(0, dtype)

        self.mean = flat(lambda m: m.surface.mean, np.float64)
        self.var = flat(lambda m: m.surface.var, np.float64)
        self.facet = flat(lambda m: m.surface.facet, np.int32)
        self.observed = flat(lambda m: m.surface.source != SOURCE_GLOBAL, np.bool_)
        self.lo = flat(lambda m: cached_step_depth_range(m.surface, reach)[0], np.float64)
        self.hi = flat(lambda m: cached_step_depth_range(m.surface, reach)[1], np.float64)
        self.noise = np.array([m.noise_var for m in facades], np.float64)
        self._boxes: dict[tuple[float, float], tuple[np.ndarray, np.ndarray]] = {}

    def boxes(self, band_back: float, band_front: float) -> tuple[np.ndarray, np.ndarray]:
        """(F, 3) lower and upper map-frame corners of each façade's slab (raster extent x
        band), as :func:`~.step7_queries.assign_facades` pre-selects with (computed once per band)."""
        key = (float(band_back), float(band_front))
        hit = self._boxes.get(key)
        if hit is None:
            hit = self._boxes[key] = self._slabs(*key)
        return hit

    def _slabs(self, band_back: float, band_front: float) -> tuple[np.ndarray, np.ndarray]:
        return slab_boxes(self.origin, self.axes, self.corner, self.cell, self.shape, band_back, band_front)


def slab_boxes(origin: np.ndarray, axes: np.ndarray, corner: np.ndarray, cell: np.ndarray, shape: np.ndarray,
               band_back: float, band_front: float) -> tuple[np.ndarray, np.ndarray]:
    """(F, 3) lower and upper map-frame corners of F façades' slabs (raster extent x band, metres)
    from their frames' (F, 3) origins and (F, 3, 3) axes and their rasters' (F, 2) corners, (F,)
    cells and (F, 2) shapes (as :class:`PackedRasters` holds them)."""
    f = len(cell)
    lo, hi = np.empty((f, 3)), np.empty((f, 3))
    for i in range(f):
        h, w = shape[i]
        u0, v0 = corner[i]
        u1, v1 = u0 + w * cell[i], v0 + h * cell[i]
        uvd = np.array([[u, v, d] for u in (u0, u1) for v in (v0, v1) for d in (-band_back, band_front)])
        corners = uvd @ axes[i] + origin[i]
        lo[i], hi[i] = corners.min(axis=0), corners.max(axis=0)
    return lo, hi


def _geometry(facades: Sequence[FacadeModel]) -> tuple[np.ndarray, ...]:
    """The F façades' frames and raster geometry as :class:`PackedRasters` holds them: (F, 3)
    origins, (F, 3, 3) axes, (F, 2) raster corners, (F,) cells, (F, 2) shapes."""
    f = len(facades)
    return (np.array([m.frame.origin for m in facades], np.float64).reshape(f, 3),
            np.array([m.frame.axes for m in facades], np.float64).reshape(f, 3, 3),
            np.array([m.surface.origin for m in facades], np.float64).reshape(f, 2),
            np.array([m.surface.cell for m in facades], np.float64),
            np.array([m.surface.mean.shape for m in facades], np.int64).reshape(f, 2))


def facade_boxes(facades: Sequence[FacadeModel], band_back: float, band_front: float) -> tuple[np.ndarray, np.ndarray]:
    """:func:`slab_boxes` of façade models, without packing their rasters."""
    return slab_boxes(*_geometry(facades), band_back, band_front)


#: Packed rasters per map (its tuple of façade models), the few most recent (the node's
#: query and mapping threads share it: under a lock).
_LOCK = threading.Lock()
_PACKED: dict[tuple[int, ...], tuple[list[weakref.ref], PackedRasters]] = {}


def packed(facades: Sequence[FacadeModel], reach: float) -> PackedRasters:
    """:class:`PackedRasters` of ``facades``, packed once per map (the models are immutable)."""
    key = tuple(id(f) for f in facades) + (hash(reach),)
    with _LOCK:
        hit = _PACKED.get(key)
    if hit is not None and all(r() is f for r, f in zip(hit[0], facades)):
        return hit[1]
    out = PackedRasters(facades, reach)
    with _LOCK:
        while len(_PACKED) >= 4:
            _PACKED.pop(next(iter(_PACKED)))
        _PACKED[key] = ([weakref.ref(f) for f in facades], out)
    return out


@njit(cache=True, parallel=True)
def assign_all(xyz, origin, axes, corner, cell, shape, offset, facet, box_lo, box_hi, band_back, band_front,
               no_facet_penalty, best, uvd):
    """:func:`~.step7_queries.assign_facades` of (N, 3) ``xyz``: ``best`` (N,) int32 and
    ``uvd`` (N, 3) written (-1 and NaN where no façade)."""
    n = len(xyz)
    for b in prange((n + _BATCH - 1) // _BATCH):
        for i in range(b * _BATCH, min(n, (b + 1) * _BATCH)):
            best[i] = -1
            best_abs = np.inf
            uvd[i, 0] = uvd[i, 1] = uvd[i, 2] = np.nan
            x0, x1, x2 = xyz[i, 0], xyz[i, 1], xyz[i, 2]
            for f in range(len(cell)):
                if not (box_lo[f, 0] <= x0 <= box_hi[f, 0] and box_lo[f, 1] <= x1 <= box_hi[f, 1]
                        and box_lo[f, 2] <= x2 <= box_hi[f, 2]):
                    continue
                y0, y1, y2 = x0 - origin[f, 0], x1 - origin[f, 1], x2 - origin[f, 2]
                u = y0 * axes[f, 0, 0] + y1 * axes[f, 0, 1] + y2 * axes[f, 0, 2]
                v = y0 * axes[f, 1, 0] + y1 * axes[f, 1, 1] + y2 * axes[f, 1, 2]
                d = y0 * axes[f, 2, 0] + y1 * axes[f, 2, 1] + y2 * axes[f, 2, 2]
                h, w = shape[f, 0], shape[f, 1]
                u0, v0 = corner[f, 0], corner[f, 1]
                if not (u0 <= u <= u0 + w * cell[f] and v0 <= v <= v0 + h * cell[f] and -band_back <= d <= band_front):
                    continue
                col = min(max(int((u - u0) / cell[f]), 0), w - 1)
                row = min(max(int((v - v0) / cell[f]), 0), h - 1)
                key = abs(d) + (0.0 if facet[offset[f] + row * w + col] >= 0 else no_facet_penalty)
                if key < best_abs:
                    best[i] = f
                    best_abs = key
                    uvd[i, 0], uvd[i, 1], uvd[i, 2] = u, v, d


@njit(cache=True)
def _surface_at(f, u, v, corner, cell, shape, offset, mean, var, facet):
    """Mean depth, variance and the mean's slopes (dm/du, dm/dv) at (u, v) of façade ``f``:
    bilinear inside one facet (its slopes; 0 where the location is clamped to the raster's
    edge), the nearest cell otherwise (flat: slopes 0)."""
    h, w = shape[f, 0], shape[f, 1]
    o = offset[f]
    cl = cell[f]
    fu = (u - corner[f, 0]) / cl - 0.5
    fv = (v - corner[f, 1]) / cl - 0.5
    c0 = min(max(int(np.floor(fu)), 0), max(w - 2, 0))
    r0 = min(max(int(np.floor(fv)), 0), max(h - 2, 0))
    c1 = min(c0 + 1, w - 1)
    r1 = min(r0 + 1, h - 1)
    tu = min(max(fu - c0, 0.0), 1.0)
    tv = min(max(fv - r0, 0.0), 1.0)
    a, b, c, d = o + r0 * w + c0, o + r0 * w + c1, o + r1 * w + c0, o + r1 * w + c1
    same = facet[a] == facet[b] and facet[a] == facet[c] and facet[a] == facet[d]
    if same:
        w00, w01, w10, w11 = (1 - tu) * (1 - tv), tu * (1 - tv), (1 - tu) * tv, tu * tv
        m = w00 * mean[a] + w01 * mean[b] + w10 * mean[c] + w11 * mean[d]
        s = w00 * var[a] + w01 * var[b] + w10 * var[c] + w11 * var[d]
        du = ((1 - tv) * (mean[b] - mean[a]) + tv * (mean[d] - mean[c])) / cl if 0.0 < fu - c0 < 1.0 else 0.0
        dv = ((1 - tu) * (mean[c] - mean[a]) + tu * (mean[d] - mean[b])) / cl if 0.0 < fv - r0 < 1.0 else 0.0
        return m, s, du, dv
    rn = r0 if tv < 0.5 else r1
    cn = c0 if tu < 0.5 else c1
    return mean[o + rn * w + cn], var[o + rn * w + cn], 0.0, 0.0


@njit(cache=True, parallel=True)
def raster_answer_all(which, uvd, corner, cell, shape, offset, mean, var, facet, observed, lo, hi, noise, reach,
                      mean_out, var_out, noise_out, dist_out, grad_out):
    """:func:`~.step7_queries._raster_answer`: (N,) mean depth, variance, noise variance
    and signed distance (the nearer step faces searched within ``reach``) written where
    ``which`` >= 0, NaN elsewhere; and (N, 3) ``grad_out``, the gradient of the signed
    distance with respect to the point, façade frame (u, v, d): ``(-dm/du, -dm/dv, 1)``
    off the step faces, the unit direction within the plane from the nearest face's
    nearest point to the point (times the distance's sign) where a face is nearer; NaN
    where ``which`` is -1."""
    n = len(which)
    for b in prange((n + _BATCH - 1) // _BATCH):
        for i in range(b * _BATCH, min(n, (b + 1) * _BATCH)):
            f = which[i]
            if f < 0:
                mean_out[i] = var_out[i] = noise_out[i] = dist_out[i] = np.nan
                grad_out[i, 0] = grad_out[i, 1] = grad_out[i, 2] = np.nan
                continue
            u, v, d = uvd[i, 0], uvd[i, 1], uvd[i, 2]
            m, s, du, dv = _surface_at(f, u, v, corner, cell, shape, offset, mean, var, facet)
            grad_out[i, 0], grad_out[i, 1], grad_out[i, 2] = -du, -dv, 1.0
            mean_out[i] = m
            noise_out[i] = noise[f]
            distance = d - m
            dist_out[i] = distance
            var_out[i] = s
            cl = cell[f]
            if not abs(distance) > 0.25 * cl or reach <= 0:
                continue
            h, w = shape[f, 0], shape[f, 1]
            o = offset[f]
            r0 = int(np.floor((v - corner[f, 1]) / cl))
            c0 = int(np.floor((u - corner[f, 0]) / cl))
            if 0 <= r0 < h and 0 <= c0 < w and not (lo[o + r0 * w + c0] <= d <= hi[o + r0 * w + c0]):
                continue
            uu = (u - corner[f, 0]) / cl
            vv = (v - corner[f, 1]) / cl
            row, col = int(np.floor(vv)), int(np.floor(uu))
            start = abs(distance) / cl
            best, best_var = start, s
            gu, gv = 0.0, 0.0  # in-plane offset of the point from the best face's nearest point (cells)
            k = int(np.ceil(reach / cl))
            for dr in range(-k - 1, k + 1):
                for dc in range(-k - 1, k + 1):
                    for across in range(2):  # across u first (the face at u = c + 1), then v
                        r, c = row + dr, col + dc
                        r2, c2 = (r, c + 1) if across == 0 else (r + 1, c)
                        if not (r >= 0 and c >= 0 and r2 < h and c2 < w):
                            continue
                        ia, ib = o + r * w + c, o + r2 * w + c2
                        if not (observed[ia] and observed[ib]):
                            continue
                        ma, mb = mean[ia], mean[ib]
                        if not (min(ma, mb) <= d <= max(ma, mb)):
                            continue
                        if across == 0:
                            ou, ov = uu - (c + 1), vv - min(max(vv, r), r + 1)
                        else:
                            ou, ov = uu - min(max(uu, c), c + 1), vv - (r + 1)
                        g = np.hypot(ou, ov)
                        if not g * cl <= reach:
                            continue
                        if g < best:
                            best = g
                            best_var = max(var[ia], var[ib]) + cl * cl / 12
                            gu, gv = ou, ov
            if best < start:
                sign = -1.0 if distance < 0 else 1.0
                dist_out[i] = sign * best * cl
                var_out[i] = best_var
                if best > 0:
                    grad_out[i, 0], grad_out[i, 1], grad_out[i, 2] = sign * gu / best, sign * gv / best, 0.0


#: The kernels on one core (``prange`` runs as ``range``): small calls, where waking the
#: second core costs more than it saves.
SERIAL_BELOW = 2048
assign_all_serial = serial_twin(assign_all, 'assign_all_serial')
raster_answer_all_serial = serial_twin(raster_answer_all, 'raster_answer_all_serial')
