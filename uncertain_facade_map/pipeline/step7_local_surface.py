"""Queries, where the map has data: the surface read per point from the stored points near it.

**A departure from the paper** (issue 26; docs/model.md, "Where the map departs from the
paper"). The paper reads the surface from each façade's raster (GMM prior + local GP
blocks, :mod:`~uncertain_facade_map.pipeline.step7_queries`). On real scans the raster's
body is as good as a plane through the nearest points, but its tails are not: at raster
borders, depth steps, window reveals and the sides of recesses, one depth per cell cannot
hold the surface, and a 2.5-D point's (u, v) picks the cell, not its depth. Where the map
holds dense data, the surface is therefore read per point from the stored building points
picked in 3-D near the query, so that the query's own depth chooses the layer at a step
and the distance is measured along the local normal; the raster answers where the data
are sparse or missing (occlusions, holes, far range), and the two blend continuously.

The reading at a point ``x`` (compiled, :mod:`~.local_kernels`: a grid search of the exact
nearest stored points and the plane per point on both cores; :func:`fit_local_planes` and
:meth:`LocalSurface._raw_kd`, the KD-tree and numpy, are the reference it reproduces):

1. its ``K + 1`` nearest stored points; the ``K`` nearest weigh
   ``w_j = (1 - (d_j / d_{K+1})^2)^2`` (a taper to 0 at the ``K + 1``-th, so that the fit
   is continuous in ``x`` as neighbours enter and leave);
2. a weighted plane by PCA: centroid ``c``, normal ``n`` (the smallest eigenvector of the
   weighted scatter), refitted once with the weights times ``1 / (1 + (r_j / 2 sigma)^2)``
   (a Cauchy reweighting: neighbours on another layer across a step weigh little);
3. the signed distance ``s_l = (x - c) . n`` (``n`` turned like the façade of the nearest
   stored point, so positive outside), the scatter ``sigma^2 = sum w r^2 / sum w`` with the
   weights' effective number ``n_eff = (sum w)^2 / sum w^2`` correcting its bias
   (``n_eff / (n_eff - 3)``), and the variance of the plane at ``x``, the regression's
   prediction variance ``sigma^2 (1 + l) / n_eff`` with the leverage
   ``l = delta_1^2 / lambda_1 + delta_2^2 / lambda_2`` of ``x``'s in-plane offset from
   the centroid (it grows with the distance from the data);
4. both scaled by one factor ``calibration_`` learnt on the stored points themselves,
   leave-one-out (:meth:`LocalSurface.calibrate`): the factor that puts 95 % of the
   stored points' leave-one-out residuals inside ``1.96 sqrt(sigma^2 + var)``; and, where
   the point lies farther from the data than the stored points lie from each other, the
   variance of a plane carried across a gap (issue 39), ``(gap_slope_ g)^2`` with the gap
   ``g = max(rho - gap_start_, offset - lever_start_, 0)``: ``offset`` is the point's
   distance from its neighbours' weighted centroid within the plane (the lever arm of a
   tilt of the plane), and both starts are what the stored points themselves read
   leave-one-out (the sampling, not a distance in metres fixed for all data: a far wall's
   sparse rings read as its own spacing). The slope is learnt on the same stored points
   read with every neighbour beyond a straight edge cut away (:meth:`LocalSurface.calibrate`),
   so that the plane is read one-sided across a gap of known width, as at the edge of a
   hole. The plane's own leverage (step 3) assumes the plane holds beyond its neighbours; a
   wall's relief, a second layer and a plane tilted by neighbours along one scan line do not
   (on the real sweeps: 95 % of such readings 0.43-0.47 m off at 0.45 m from the data);
5. the blend weight ``w = smoothstep((radius - rho) / (radius - inner))``, where ``rho`` is
   the distance to the ``NEAR``-th nearest stored point: 1 where those lie within
   ``inner``, 0 beyond ``radius`` (the raster alone), continuous between. The blended
   answer is the mixture's: ``s = w s_l + (1 - w) s_r`` and
   ``var = w var_l + (1 - w) var_r + w (1 - w) (s_l - s_r)^2``, so that a disagreement
   of the two readings widens the interval instead of jumping. The weight is the
   local reading's posterior share, ``w / (w + (1 - w) a)``, with the raster's agreement
   ``a = exp(-(s_l - s_r)^2 / (2 AGREEMENT^2 (var_r + var_l + noise_l)))`` (floored at
   ``MIN_AGREEMENT``, which bounds the slope in ``w``): where the raster lies several
   sigmas off the dense points' plane it holds another layer or misses a face, and the
   local plane answers (measured on the real sweeps, docs/model.md: AV1's observed RMSE
   0.047 -> 0.040 m, sweep 1's 0.035 -> 0.034 m, sweep 0's unchanged).
"""

from __future__ import annotations

import copy
import dataclasses
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np
from scipy.spatial import cKDTree

from ..datatypes import FacadeModel
from ..errors import InputError
from ..params import QueryConfig
from .local_kernels import MAX_RING, TILE, PointGrid, planes

#: The blend weight depends on the distance to this many-th nearest stored point (1: the
#: nearest, which tells a hole from sparse data better than the 12th: measured on the
#: real sweeps, docs/model.md).
NEAR = 1
#: Stored points (a seeded draw) the leave-one-out calibration reads at most.
CALIBRATION_POINTS = 20_000
#: The coverage the calibration aims at, and its interval's half width in sigmas.
COVERAGE, Z95 = 0.95, 1.959963984540054
#: A point lies across a gap where it is farther from the data than most stored points are
#: from their neighbours (leave-one-out): its ``rho`` beyond this quantile of theirs, or its
#: offset from its neighbours' centroid beyond this quantile of theirs (step 4).
GAP_QUANTILES = (0.75, 0.95)
#: Gap slope's search bound (extra standard deviation per metre of gap; AV1, AV2 sweep 0 and
#: KITTI 1 learn 0.61, 0.65 and 0.79).
MAX_GAP_SLOPE = 4.0
#: Sigmas of disagreement at which the raster's share in the blend falls to exp(-1/2).
AGREEMENT = 3.0
#: Leave-one-out sigmas (uncalibrated) beyond which a chi-squared outlier of the façade
#: model stands alone and is left out of the local reading.
OUTLIER_Z = 3.0
#: Metres in front of its façade's mean surface beyond which a chi-squared outlier of the
#: façade model is left out of the local reading whatever its neighbours: a window's frame,
#: a sill or a reveal stands a few centimetres to decimetres off the wall; a parked car, a
#: person or a bin before it is no façade, and a later scan passes through where it stood.
CLUTTER_FRONT = 0.5
#: Share of its façade's noise variance (``noise_var``, sigma_eta^2, learnt on the whole
#: façade) below which a local plane's scatter is not believed: neighbours that lie exactly on
#: a plane are quantised coordinates (Argoverse's float16: 7.8-15.6 mm steps, a wall along an
#: axis on one value), not a surface known to a millimetre; such planes answered held-out
#: points in the AV2 sweep's occlusions 10-20 cm off with a 0.5-1.3 mm standard deviation.
NOISE_FLOOR = 0.25
#: Floor of the agreement factor: bounds the blend's slope in the weight (1 / it).
MIN_AGREEMENT = 0.05
#: Points read at once (bounds the (B, K + 1, 3) neighbour arrays: about 20 MB each at K = 12).
CHUNK = 65_536
#: Floor of the scatter sigma^2, m^2 (exactly coplanar neighbours give 0).
MIN_VAR = 1e-8
#: Side of the grid cells that the compiled reading searches, as a multiple of the stored
#: points' median distance to their ``K + 1``-th nearest (street map, 1.1 M stored points,
#: 500,000 queries near the façades: 1, 2 and 3 tried, 2 the fastest; speed only, the
#: reading is exact whatever the cell).
GRID_CELL = 2.0
#: Stored points (a seeded draw) whose spacing sets the grid's cells.
GRID_SAMPLE = 20_000
#: Cells of the second, coarser grid, in cells of the first: with ``MAX_RING`` rings, the
#: neighbours of a point are searched up to about 6 x 8 x 0.25 = 12 m away on the street map
#: (beyond, the KD-tree reads it).
COARSE = 8.0


@dataclass(frozen=True)
class LocalReading:
    """The per-point reading at N points (NaN where the map holds no stored point nearby).

    Attributes:
        facade: (N,) int32 façade of the nearest stored point, -1 where no stored point.
        signed_distance: (N,) ``s_l``, metres, positive outside (along ``normal``).
        variance: (N,) variance of the local plane at the point, m^2 (calibrated, its gap's
            included).
        gap_variance: (N,) the part of ``variance`` that is the gap's
            (:meth:`LocalSurface.gap_variance`), m^2.
        noise_variance: (N,) scatter of the stored points about it, m^2 (calibrated).
        normal: (N, 3) unit local normal, map frame, turned like the façade's.
        weight: (N,) blend weight in [0, 1] (1: the local reading alone; 0: the raster).
    """

    facade: np.ndarray
    signed_distance: np.ndarray
    variance: np.ndarray
    noise_variance: np.ndarray
    normal: np.ndarray
    weight: np.ndarray
    gap_variance: np.ndarray


@dataclass(frozen=True)
class ReadingCalibration:
    """What :meth:`LocalSurface.calibrate` learns, to read another surface with (a tiled
    map's views read with the map-wide values; ``LocalSurface`` fields of the same names
    ending in ``_``).

    Attributes:
        scale: the variances' leave-one-out factor (``calibration_``).
        gap_slope: extra standard deviation per metre of gap (``gap_slope_``).
        gap_start: metres of ``rho`` where the gap starts (``gap_start_``).
        lever_start: metres of offset from the neighbours' centroid where it starts
            (``lever_start_``).
    """

    scale: float = 1.0
    gap_slope: float = 0.0
    gap_start: float = 0.0
    lever_start: float = 0.0

    def as_dict(self) -> dict[str, float]:
        """The JSON object (a tiled map's manifest)."""
        return dataclasses.asdict(self)

    @classmethod
    def parse(cls, value: object) -> ReadingCalibration:
        """From :meth:`as_dict`'s object, or a number (a manifest written before the gap:
        the scale alone). Raises ValueError on anything else or a non-finite value."""
        if isinstance(value, dict):
            unknown = set(value) - {f.name for f in dataclasses.fields(cls)}
            if unknown:
                raise ValueError(f'unknown calibration fields {sorted(unknown)}')
            out = cls(**{k: float(v) for k, v in value.items()})
        elif isinstance(value, (int, float)) and not isinstance(value, bool):
            out = cls(float(value))
        else:
            raise ValueError(f'a calibration is a number or an object, got {value!r}')
        if not all(np.isfinite(v) for v in out.as_dict().values()):
            raise ValueError(f'a calibration must be finite, got {out.as_dict()}')
        return out


def smoothstep(t: np.ndarray) -> np.ndarray:
    """``3 t^2 - 2 t^3`` of ``t`` clipped to [0, 1]: continuous with a continuous slope."""
    t = np.clip(t, 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def raster_agreement(s_local: np.ndarray, s_raster: np.ndarray, spread: np.ndarray) -> np.ndarray:
    """(N,) agreement in [MIN_AGREEMENT, 1] of the raster with the local plane: ``exp(-d^2 /
    (2 AGREEMENT^2 spread))`` of the two readings' difference ``d`` (metres) over their
    summed variance ``spread`` (m^2), floored; continuous in both."""
    return np.maximum(np.exp(-0.5 * np.square(s_local - s_raster) / (AGREEMENT**2 * np.maximum(spread, MIN_VAR))),
                      MIN_AGREEMENT)


def fit_local_planes(x: np.ndarray, nb: np.ndarray, dist: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Weighted, once reweighted planes through each point's neighbours (steps 1-3 above).

    Args:
        x: (N, 3) query points, metres.
        nb: (N, K + 1, 3) their K + 1 nearest stored points, nearest first, metres.
        dist: (N, K + 1) their distances, metres.

    Returns:
        ``(s, normal, scatter, plane_var, offset)``: (N,) signed distance of ``x`` to the
        plane along ``normal`` (sign not yet turned), (N, 3) unit normals, (N,) scatter
        ``sigma^2`` (bias corrected), (N,) variance of the plane at ``x`` (uncalibrated,
        m^2) and (N,) distance of ``x`` from the neighbours' weighted centroid within the
        plane, metres.
    """
    taper = np.maximum(dist[:, -1:], 1e-9)
    w = np.square(np.clip(1.0 - np.square(dist[:, :-1] / taper), 0.0, 1.0))
    w[:, 0] = np.maximum(w[:, 0], 1e-6)  # a lone nearest neighbour still defines a centroid
    nbk = nb[:, :-1]
    for reweight in (False, True):
        sw = w.sum(axis=1)
        c = np.einsum('nk,nki->ni', w, nbk) / sw[:, None]
        dev = nbk - c[:, None]
        cov = np.einsum('nk,nki,nkj->nij', w, dev, dev) / sw[:, None, None]
        lam, vec = np.linalg.eigh(cov)
        normal = vec[:, :, 0]
        r = np.einsum('nki,ni->nk', dev, normal)
        sigma2 = np.einsum('nk,nk->n', w, r * r) / sw
        if not reweight:
            w = w / (1.0 + r * r / (4.0 * sigma2[:, None] + MIN_VAR))
    n_eff = np.square(sw) / np.einsum('nk,nk->n', w, w)
    scatter = np.maximum(sigma2 * n_eff / np.maximum(n_eff - 3.0, 1.0), MIN_VAR)
    off = x - c
    s = np.einsum('ni,ni->n', off, normal)
    lev = (np.square(np.einsum('ni,ni->n', off, vec[:, :, 1])) / np.maximum(lam[:, 1], MIN_VAR)
           + np.square(np.einsum('ni,ni->n', off, vec[:, :, 2])) / np.maximum(lam[:, 2], MIN_VAR))
    offset = np.sqrt(np.maximum(np.einsum('ni,ni->n', off, off) - s * s, 0.0))
    return s, normal, scatter, scatter * (1.0 + lev) / n_eff, offset


@dataclass(eq=False)
class LocalSurface:
    """The stored building points of a map, read per query point (see the module's text).

    Attributes:
        points: (M, 3) stored building points (the chi-squared outliers that stand alone or
            more than :data:`CLUTTER_FRONT` in front of their façade
            left out, :meth:`of`), metres, map frame.
        facade: (M,) int32 façade id of each (of the nearest point on a façade for those on
            none).
        normals: (F, 3) outward unit normal of each façade, map frame.
        neighbours: K, the stored points a plane is fitted to.
        radius: beyond this distance of the ``NEAR``-th nearest stored point the raster
            answers alone, metres.
        inner: within it the local reading answers alone, metres (equal to ``radius``: a
            switch between the two readings instead of a blend).
        calibration_: the leave-one-out scale of the variances (:meth:`calibrate`;
            1 until then).
        gap_slope_: extra standard deviation of a plane read across a gap, per metre of
            gap (:meth:`gap_variance`, :meth:`calibrate`; 0 until then, dimensionless).
        gap_start_, lever_start_: the stored points' own ``rho`` and offset from their
            neighbours' centroid (leave-one-out) at ``GAP_QUANTILES``: the gap counts from
            there, metres (:meth:`calibrate`).
        source: (M,) int64 index of each point in the map's stored points concatenated in
            building label order (:meth:`of`; None: the points as given).
        noise_floor: (F,) per façade, the least scatter a local plane on it is read with, m^2
            (:func:`noise_floor_of`; None: no floor).
    """

    points: np.ndarray
    facade: np.ndarray
    normals: np.ndarray
    neighbours: int = 12
    radius: float = 0.5
    inner: float = 0.2
    calibration_: float = 1.0
    gap_slope_: float = 0.0
    gap_start_: float = 0.0
    lever_start_: float = 0.0
    source: np.ndarray | None = field(default=None, repr=False)
    noise_floor: np.ndarray | None = field(default=None, repr=False)
    _tree: cKDTree | None = field(default=None, init=False, repr=False)
    _grid: PointGrid | None = field(default=None, init=False, repr=False)
    _coarse: PointGrid | None = field(default=None, init=False, repr=False)
    _orders: dict = field(default_factory=dict, init=False, repr=False)  # per grid: (grid, labels, inverse)

    def __post_init__(self) -> None:
        if self.neighbours < 3:
            raise InputError(f'the local surface needs at least 3 neighbours, got {self.neighbours}')
        if not 0 <= self.inner <= self.radius:
            raise InputError(f'the local surface needs 0 <= inner <= radius, got {self.inner} and {self.radius}')

    @classmethod
    def of(cls, facades: Sequence[FacadeModel], points: dict[int, np.ndarray], neighbours: int = 12,
           radius: float = 0.5, inner: float = 0.2, calibrate: bool = True, join: bool = True) -> LocalSurface:
        """The local surface of a map's façades.

        Args:
            facades: the façade models (``facades[i].facade_id == i``).
            points: per building label, its stored points (N_b, 3), metres, map frame
                (``FacadeMap.points``); ``facades[i].point_index`` indexes them.
            neighbours: K.
            radius: see the class.
            inner: see the class.
            calibrate: learn ``calibration_`` now.
            join: count the points of a building with no façade with the nearest façade; False:
                leave them at -1 (a part of a larger map, which joins them over its own points:
                a tiled map's views, :mod:`~uncertain_facade_map.tiling.views`).
        """
        parts, ids, flags, fronts = [], [], [], []
        for b in sorted(points):
            pts = points[b]
            label = np.full(len(pts), -1, dtype=np.int32)
            flagged = np.zeros(len(pts), bool)
            front = np.zeros(len(pts), bool)
            for f in facades:
                if f.building == b and len(f.point_index):
                    label[f.point_index[f.point_index < len(pts)]] = f.facade_id
                    out_idx = f.outlier_index[f.outlier_index < len(pts)]
                    flagged[out_idx] = True
                    front[out_idx[_in_front(f, pts[out_idx])]] = True
            flags.append(flagged)
            fronts.append(front)
            mapped = np.flatnonzero(label >= 0)
            if len(mapped) and len(mapped) < len(pts):
                # A stored point on no façade (a wall piece too small to be one, a reveal)
                # counts with the façade of its nearest stored point that is on one.
                free = np.flatnonzero(label < 0)
                label[free] = label[mapped[cKDTree(pts[mapped]).query(pts[free])[1]]]
            parts.append(pts)
            ids.append(label)
        xyz = np.concatenate(parts) if parts else np.empty((0, 3))
        fid = np.concatenate(ids) if ids else np.empty(0, np.int32)
        mapped = np.flatnonzero(fid >= 0)
        if join and len(mapped) and len(mapped) < len(fid):
            # A building too small for a façade of its own (often a piece of a neighbour's
            # wall that the clustering cut off): its points count with the nearest façade.
            free = np.flatnonzero(fid < 0)
            fid[free] = fid[mapped[cKDTree(xyz[mapped]).query(xyz[free])[1]]]
        normals = np.array([f.frame.normal for f in facades]).reshape(-1, 3)
        floor = noise_floor_of(facades)
        out = cls(xyz, fid, normals, neighbours, radius, inner, noise_floor=floor)
        flagged = np.flatnonzero(np.concatenate(flags)) if flags else np.empty(0, np.int64)
        if len(flagged) and len(xyz) > neighbours + 2:
            # The chi-squared test's outliers (step 5) stay where the stored points around
            # them hold them on a surface (a reveal, a face the raster cannot hold: most of
            # them on real walls) and go where they stand alone (clutter, a stray return)
            # or well in front of their façade (CLUTTER_FRONT: a car, a person before it).
            z = np.empty(len(flagged))
            for start in range(0, len(flagged), CHUNK):
                p = flagged[start:start + CHUNK]
                _, s, scatter, plane_var, _, _, _, _ = out.raw(xyz[p], skip=p)
                z[start:start + CHUNK] = np.abs(s) / np.sqrt(scatter + plane_var)
            alone = flagged[(z > OUTLIER_Z) | np.concatenate(fronts)[flagged]]
            if len(alone):
                keep = np.ones(len(xyz), bool)
                keep[alone] = False
                grid = out.grid
                out = cls(xyz[keep], fid[keep], normals, neighbours, radius, inner, source=np.flatnonzero(keep),
                          noise_floor=floor)
                out._grid = grid.subset(keep)
        if out.source is None:
            out.source = np.arange(len(xyz))
        if calibrate:
            out.calibrate()
        return out

    def in_grid_order(self) -> LocalSurface:
        """The same surface with its points held in its grid's order (:attr:`grid`, built now),
        once: the grid's own array, not a second copy (a tiled map's views, which hold many
        points and are read, never calibrated on their own points; ``source`` is not carried).
        Itself when it has too few points for a grid."""
        if len(self.points) <= self.neighbours + 1:
            return self
        grid = copy.copy(self.grid)  # the arrays shared; this one's order is the identity
        out = LocalSurface(grid.points, self.facade[grid.order].astype(np.int32), self.normals, self.neighbours,
                           self.radius, self.inner, noise_floor=self.noise_floor).calibrate_with(self.calibration())
        grid.order = np.arange(len(grid.points), dtype=np.int32)
        out._grid = grid
        out._orders[id(grid)] = [grid, out.facade, None]  # the labels in the grid's order: its own
        return out

    def without_caches(self) -> LocalSurface:
        """The same surface without the search structures it builds on first use (KD-tree,
        grids): a lighter copy to hand to another process, which builds them as it reads."""
        out = copy.copy(self)
        out._tree = out._grid = out._coarse = None
        out._orders = {}
        return out

    @property
    def tree(self) -> cKDTree:
        """KD-tree of the stored points (built on first use)."""
        if self._tree is None:
            self._tree = cKDTree(self.points)
        return self._tree

    @property
    def grid(self) -> PointGrid:
        """Grid of the stored points the compiled reading searches (built on first use; its
        cells' side: ``GRID_CELL`` times the stored points' median distance to their
        ``K + 1``-th nearest other, estimated on a sample)."""
        if self._grid is None:
            # The spacing from a sample's own KD-tree (not the map's: cheap), scaled to all
            # points as on a surface (spacing ~ 1 / sqrt(density)).
            m = len(self.points)
            sample = self.points[np.random.default_rng(0).choice(m, min(m, GRID_SAMPLE), replace=False)]
            d, _ = cKDTree(sample).query(sample[:2000], k=min(self.neighbours + 2, len(sample)))
            spacing = float(np.median(np.reshape(d, (min(len(sample), 2000), -1))[:, -1])) * np.sqrt(len(sample) / m)
            self._grid = PointGrid(self.points, max(GRID_CELL * spacing, 1e-3))
        return self._grid

    @property
    def coarse_grid(self) -> PointGrid:
        """The stored points on cells ``COARSE`` times the grid's (built on first use): the
        second search of the few points whose ``K + 1`` nearest lie beyond ``MAX_RING`` cells."""
        if self._coarse is None:
            self._coarse = PointGrid(self.points, COARSE * self.grid.cell)
        return self._coarse

    def _in_grid_order(self, grid: PointGrid, inverse: bool = False) -> tuple[np.ndarray, np.ndarray | None]:
        """(M,) façade of each stored point in ``grid``'s order, and (M,) the position in that
        order of each stored point (with ``inverse``, for leave-one-out reads; else None), cached per grid."""
        hit = self._orders.get(id(grid))
        if hit is None or hit[0] is not grid:
            hit = self._orders[id(grid)] = [grid, self.facade[grid.order].astype(np.int32), None]
        if inverse and hit[2] is None:
            pos = np.empty(len(grid.order), np.int64)
            pos[grid.order] = np.arange(len(grid.order))
            hit[2] = pos
        return hit[1], hit[2]

    def _neighbours(self, xyz: np.ndarray, skip: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(N, K + 1) distances and indices of each point's nearest stored points, without
        the stored point ``skip[i]`` itself (leave-one-out; it may have duplicates)."""
        k = self.neighbours + 1
        extra = 0 if skip is None else 1
        m = len(self.points)
        dist, idx = self.tree.query(xyz, k=min(k + extra, m), workers=-1)
        dist, idx = dist.reshape(len(xyz), -1), idx.reshape(len(xyz), -1)
        if skip is not None:
            keep = idx != skip[:, None]
            # Keep the first K + 1 entries that are not the point itself (stable order).
            order = np.argsort(~keep, axis=1, kind='stable')[:, :k]
            dist, idx = np.take_along_axis(dist, order, 1), np.take_along_axis(idx, order, 1)
        if idx.shape[1] < k:  # fewer stored points than K + 1: repeat the farthest
            pad = k - idx.shape[1]
            dist = np.concatenate([dist, np.repeat(dist[:, -1:], pad, 1)], axis=1)
            idx = np.concatenate([idx, np.repeat(idx[:, -1:], pad, 1)], axis=1)
        return dist, idx

    def _raw(self, xyz: np.ndarray, skip: np.ndarray | None = None, radius: float = np.inf,
             cut: np.ndarray | None = None) -> tuple[np.ndarray, ...]:
        """``(fid, s, scatter, plane_var, normal, rho, nearest, offset)`` at (N, 3) points (leaving the
        stored points ``skip`` out, leave-one-out): the compiled kernels
        (:func:`~.local_kernels.local_planes`), the KD-tree's numpy reading
        (:meth:`_raw_kd`) for the few points the grid's search does not reach. Points with no
        stored point within ``radius`` get NaN and ``nearest`` inf. ``cut``: (N, 4) per point
        a half-space of stored points left out (:func:`~.local_kernels.local_planes`); its
        points the grids do not reach get NaN (no KD-tree reading)."""
        n = len(xyz)
        if len(self.points) < self.neighbours + 2:
            return self._raw_kd(xyz, skip)
        g = self.grid
        fid = np.full(n, -1, np.int32)
        s, scatter, plane_var, rho, nearest, offset = (np.full(n, np.nan) for _ in range(6))
        nearest[:] = np.inf
        normal = np.full((n, 3), np.nan)
        status = np.zeros(n, np.int8)
        normals = np.ascontiguousarray(self.normals, dtype=np.float64).reshape(-1, 3)
        # Points read in the grid's order (by tile of columns, then height): neighbouring
        # points read the same cells while they are in the cache (2-3 x faster than random order).
        ijk = np.clip(np.floor((xyz - g.corner) / (g.cell * np.array([TILE, TILE, 1.0]))), -1, 1 << 20).astype(np.int64)
        order = np.argsort(((ijk[:, 0] + 1) << 42) | ((ijk[:, 1] + 1) << 21) | (ijk[:, 2] + 1))
        x = np.ascontiguousarray(xyz, dtype=np.float64)
        none = np.zeros((0, 4))
        if cut is not None:
            cut = np.ascontiguousarray(cut, dtype=np.float64).reshape(n, 4)
        for coarse in (False, True):  # the few points far from K + 1 stored points: again, on coarser cells
            grid = self.coarse_grid if coarse else g
            labels, inverse = self._in_grid_order(grid, inverse=skip is not None)
            sk = np.full(n, -1, np.int64) if skip is None else inverse[skip]
            planes(order, x, sk, none if cut is None else cut, labels, *grid.arrays(), self.neighbours, min(NEAR, self.neighbours) - 1, MAX_RING,
                   normals, float(radius), MIN_VAR, fid, s, scatter, plane_var, normal, rho, nearest, offset, status)
            order = order[status[order] == 2]
            if not len(order):
                break
        far = np.flatnonzero(status == 2)
        if len(far) and cut is None:
            out = self._raw_kd(xyz[far], None if skip is None else skip[far])
            for a, b in zip((fid, s, scatter, plane_var, normal, rho, nearest, offset), out):
                a[far] = b
        return fid, s, scatter, plane_var, normal, rho, nearest, offset

    def raw(self, xyz: np.ndarray, skip: np.ndarray | None = None, radius: float = np.inf,
            cut: np.ndarray | None = None) -> tuple[np.ndarray, ...]:
        """:meth:`_raw` with the scatter (and the plane's variance with it) floored at the
        façade's :attr:`noise_floor` (uncalibrated, m^2)."""
        fid, s, scatter, plane_var, normal, rho, nearest, offset = self._raw(xyz, skip, radius, cut)
        if self.noise_floor is not None and len(self.noise_floor):
            floor = np.where(fid >= 0, self.noise_floor[np.maximum(fid, 0)], 0.0)
            ratio = np.maximum(scatter, floor) / np.maximum(scatter, MIN_VAR)
            ratio = np.where(np.isfinite(ratio) & (ratio > 1.0), ratio, 1.0)
            scatter, plane_var = scatter * ratio, plane_var * ratio
        return fid, s, scatter, plane_var, normal, rho, nearest, offset

    def _raw_kd(self, xyz: np.ndarray, skip: np.ndarray | None = None) -> tuple[np.ndarray, ...]:
        """:meth:`_raw` by the KD-tree and numpy (the reference the kernels reproduce)."""
        dist, idx = self._neighbours(xyz, skip)
        s, normal, scatter, plane_var, offset = fit_local_planes(xyz, self.points[idx], dist)
        # The façade of the nearest neighbour that belongs to one (-1: none does).
        labels = self.facade[idx]
        first = np.argmax(labels >= 0, axis=1)
        fid = labels[np.arange(len(idx)), first]
        flip = np.einsum('ni,ni->n', normal, self.normals[np.maximum(fid, 0)]) < 0 if len(self.normals) else \
            np.zeros(len(idx), bool)
        s = np.where(flip, -s, s)
        normal = np.where(flip[:, None], -normal, normal)
        rho = dist[:, min(NEAR, self.neighbours) - 1]
        rho = np.where(fid >= 0, rho, np.inf)
        return fid, s, scatter, plane_var, normal, rho, dist[:, 0], offset

    def calibrate(self, seed: int = 0, max_points: int = CALIBRATION_POINTS) -> float:
        """Learn ``calibration_`` leave-one-out on (at most ``max_points`` of) the stored
        points where the local reading answers alone, the gap's starts from the same
        readings, and ``gap_slope_`` on the same points read across a gap
        (:meth:`_calibrate_gap`); returns ``calibration_`` (1 with too few points)."""
        m = len(self.points)
        self.calibration_, self.gap_slope_, self.gap_start_, self.lever_start_ = 1.0, 0.0, 0.0, 0.0
        if m <= self.neighbours + 2:
            return self.calibration_
        rng = np.random.default_rng(seed)
        pick = np.sort(rng.choice(m, max_points, replace=False)) if m > max_points else np.arange(m)
        z, rhos, levers = [], [], []
        for start in range(0, len(pick), CHUNK):
            p = pick[start:start + CHUNK]
            _, s, scatter, plane_var, _, rho, _, offset = self.raw(self.points[p], skip=p)
            used = rho <= self.inner
            z.append(np.abs(s[used]) / np.sqrt(scatter[used] + plane_var[used]))
            read = np.isfinite(rho) & np.isfinite(offset)
            rhos.append(rho[read])
            levers.append(offset[read])
        z = np.concatenate(z)
        if len(z) >= 50:
            self.calibration_ = float(np.quantile(z, COVERAGE) / Z95)
        rhos, levers = np.concatenate(rhos), np.concatenate(levers)
        if len(rhos) >= 50 and len(self.normals):
            self.gap_start_ = float(np.quantile(rhos, GAP_QUANTILES[0]))
            self.lever_start_ = float(np.quantile(levers, GAP_QUANTILES[1]))
            self.gap_slope_ = self._calibrate_gap(pick, rng)
        return self.calibration_

    def _calibrate_gap(self, pick: np.ndarray, rng: np.random.Generator) -> float:
        """The gap slope: the stored points ``pick`` read with their neighbours beyond a
        straight edge cut away, the edge a gap ``g`` (uniform in [0, ``radius``]) from the
        point across its façade's plane in a random direction (a hole's edge); the least
        slope that puts 95 % of those across a gap (``g > 0``, :meth:`gap`) inside
        ``1.96 sqrt(c^2 (sigma^2 + var) + (slope g)^2)`` (bisection: coverage grows with
        the slope). 0 with fewer than 50 such readings."""
        pts = self.points[pick]
        normal = self.normals[np.maximum(self.facade[pick], 0)]
        along = rng.normal(size=(len(pick), 3))
        along -= np.einsum('ni,ni->n', along, normal)[:, None] * normal
        along /= np.maximum(np.linalg.norm(along, axis=1), 1e-12)[:, None]
        gap = rng.uniform(0.0, self.radius, len(pick))
        # Left out: the stored points q with (q - p) . along > -gap.
        cut = np.c_[along, np.einsum('ni,ni->n', pts, along) - gap]
        s, base, gaps = [], [], []
        for start in range(0, len(pick), CHUNK):
            part = slice(start, start + CHUNK)
            _, si, scatter, plane_var, _, rho, _, offset = self.raw(pts[part], skip=pick[part], cut=cut[part])
            s.append(si)
            base.append(self.calibration_ ** 2 * (scatter + plane_var))
            gaps.append(self.gap(rho, offset))
        s, base, excess = np.concatenate(s), np.concatenate(base), np.concatenate(gaps)
        over = np.isfinite(s) & (excess > 0)
        if over.sum() < 50:
            return 0.0
        s, base, excess = np.abs(s[over]), base[over], excess[over]

        def covered(slope: float) -> float:
            return float(np.mean(s <= Z95 * np.sqrt(base + np.square(slope * excess))))

        if covered(0.0) >= COVERAGE:
            return 0.0
        lo, hi = 0.0, MAX_GAP_SLOPE
        for _ in range(40):
            mid = 0.5 * (lo + hi)
            lo, hi = (lo, mid) if covered(mid) >= COVERAGE else (mid, hi)
        return hi

    def calibration(self) -> ReadingCalibration:
        """What :meth:`calibrate` learnt (or was given)."""
        return ReadingCalibration(float(self.calibration_), float(self.gap_slope_), float(self.gap_start_),
                                  float(self.lever_start_))

    def calibrate_with(self, calibration: ReadingCalibration) -> LocalSurface:
        """Read with ``calibration`` (learnt elsewhere: a tiled map's map-wide values); itself."""
        self.calibration_, self.gap_slope_ = calibration.scale, calibration.gap_slope
        self.gap_start_, self.lever_start_ = calibration.gap_start, calibration.lever_start
        return self

    def gap(self, rho: np.ndarray, offset: np.ndarray) -> np.ndarray:
        """(N,) metres a point lies across a gap in the data, from its ``rho`` and ``offset``
        (N,) (:meth:`raw`): ``max(rho - gap_start_, offset - lever_start_, 0)`` (0 where
        either is not finite)."""
        g = np.maximum(np.asarray(rho) - self.gap_start_, np.asarray(offset) - self.lever_start_)
        return np.where(np.isfinite(g), np.maximum(g, 0.0), 0.0)

    def gap_variance(self, rho: np.ndarray, offset: np.ndarray) -> np.ndarray:
        """(N,) variance of a plane read across a gap, ``(gap_slope_ g)^2`` of the gap
        :meth:`gap` at (N,) ``rho`` and ``offset``, m^2."""
        return np.square(self.gap_slope_ * self.gap(rho, offset))

    def read(self, xyz: np.ndarray) -> LocalReading:
        """The local reading at (N, 3) points, metres, map frame."""
        n = len(xyz)
        out = LocalReading(np.full(n, -1, np.int32), np.full(n, np.nan), np.full(n, np.nan), np.full(n, np.nan),
                           np.full((n, 3), np.nan), np.zeros(n), np.zeros(n))
        if not len(self.points):
            return out
        c2 = self.calibration_ ** 2
        # Only points with a stored point within the radius are read (the others weigh 0).
        for start in range(0, n, CHUNK):
            fid, s, scatter, plane_var, normal, rho, nearest, offset = self.raw(xyz[start:start + CHUNK], radius=self.radius)
            near = np.flatnonzero(nearest < self.radius)
            part = start + near
            fid, s, scatter, plane_var, normal, rho, offset = (a[near] for a in (fid, s, scatter, plane_var, normal, rho,
                                                                                offset))
            if self.radius > self.inner:
                w = smoothstep((self.radius - rho) / (self.radius - self.inner))
            else:  # inner == radius: a switch
                w = (rho <= self.radius).astype(np.float64)
            out.facade[part] = np.where(w > 0, fid, -1)
            out.signed_distance[part] = s
            out.gap_variance[part] = self.gap_variance(rho, offset)
            out.variance[part] = c2 * plane_var + out.gap_variance[part]
            out.noise_variance[part] = c2 * scatter
            out.normal[part] = normal
            out.weight[part] = w
        return out


def noise_floor_of(facades: Sequence[FacadeModel]) -> np.ndarray:
    """(F,) the least scatter a local plane on each façade is read with: :data:`NOISE_FLOOR`
    times its noise variance, m^2."""
    return NOISE_FLOOR * np.array([f.noise_var for f in facades], dtype=np.float64)


def _in_front(facade: FacadeModel, xyz: np.ndarray) -> np.ndarray:
    """(N,) bool: the (N, 3) points (metres, map frame) lie more than :data:`CLUTTER_FRONT`
    in front of the façade's mean surface (its raster's nearest cell; off the raster, the
    nearest edge cell's)."""
    r = facade.surface
    uvd = facade.frame.to_local(xyz)
    h, w = r.mean.shape
    col = np.clip(((uvd[:, 0] - r.origin[0]) / r.cell).astype(np.int64), 0, w - 1)
    row = np.clip(((uvd[:, 1] - r.origin[1]) / r.cell).astype(np.int64), 0, h - 1)
    return uvd[:, 2] - r.mean[row, col] > CLUTTER_FRONT


def for_query(facades: Sequence[FacadeModel], points: dict[int, np.ndarray], config: QueryConfig
              ) -> LocalSurface | None:
    """The local surface a query with ``config`` (``query.*``) reads, calibrated; None for
    ``query.surface`` 'raster' (the paper's reading)."""
    if config.surface == 'raster':
        return None
    return LocalSurface.of(facades, points, config.local_neighbours, config.local_radius, config.local_inner)
