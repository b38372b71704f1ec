"""The whole map: buildings, their façades, and each façade's uncertain surface.

The orchestrator only sees arrays. Per building it extracts façades
(:mod:`.facade_extraction`); per façade it fits the depth layers and facets
(:mod:`.layers`), selects the GP training points (paper eqs. 7 and 8), fits the layers'
length scales, filters outliers (:mod:`.outliers`) and predicts the surface of every
facet's local GPs in blocks (:mod:`.gp_blocks`) on a raster. Queries
(:mod:`.queries`) read the rasters.

The surface of a façade is d(x) = g(x) + f(x) (paper eq. 2): g = mu_k of the facet's
layer, f the facet's local GP. Where no facet covers a location, the global GP prior
holds: the main layer's mean with the variance of all the façade's depths.

**Incremental mapping** (:meth:`FacadeMap.add_points`): new points go to the façade whose
depth band and grown plane extent hold them (:func:`~.facade_extraction.assign_to_facades`,
the extraction's own rule); the rest wait in the building's pool, where RANSAC runs again
once the pool has grown enough. A façade's frame and its block grid's anchor never move,
so cells and blocks keep their identity. A façade whose points have grown by
``refit_growth`` since its last whole fit is fitted whole again (layers, length scales,
every block); otherwise only the blocks whose extended block received a new training
point, and the cells whose facet changed, are recomputed (:func:`update_facade`), so the
cost of an update follows the new data. Whole refits at geometric steps cost a bounded
multiple of one batch build in all.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
from scipy import ndimage

from .errors import InputError
from .facade_extraction import (ExtractedFacade, ExtractionParams, _final_frame, _grid_components, _plane_box,
                                _point_normals, assign_to_facades, check_building_ids, extract_facades)
from .frames import FacadeFrame
from .gp_blocks import (_NEIGHBOURS, BlockData, GPParams, _ranks, block_codes, block_size, fit_surface,
                        optimisation_patches, optimise_lengthscales)
from .layers import DepthLayers, Facets, LayerParams, find_facets, fit_layers
from .outliers import OutlierParams

#: Offsets of a clustering cell's 3x3 neighbourhood in cell keys (see FacadeMap._cell_keys).
_CELL_NEIGHBOURS = np.array([du * (1 << 32) + dv for du in (-1, 0, 1) for dv in (-1, 0, 1)], dtype=np.int64)

#: Source of a raster cell's value.
SOURCE_GLOBAL, SOURCE_FACET_PRIOR, SOURCE_GP = 0, 1, 2


@dataclass(frozen=True)
class UpdateParams:
    """How the map grows with new points (incremental mapping).

    Attributes:
        refit_growth: a façade is fitted whole again (GMM layers, length scales, every
            block) once its points have grown by this share since its last whole fit;
            below it only the blocks near new training points and the cells whose facet
            changed are recomputed.
        extraction_growth: RANSAC runs again on a building's unallocated points once
            they have grown by this share (and by at least ``min_facade_points``) since
            the last run.
        normal_reach: new points' normals use the building's points within this distance
            of the new points' bounding box, metres.
        batch_points: live mapping (``add_points(..., defer=True)``) holds new points back
            until at least this many have arrived, then maps them in one update: an update
            recomputes every block near a new training point, and the points of a few
            scans fall all over a façade, so small batches would solve the same blocks
            again and again (100 000: about 3 s of the street drive; 3x the throughput of
            20 000 there).

    Raises:
        InputError: a parameter is out of range.
    """

    refit_growth: float = 1.0
    extraction_growth: float = 0.5
    normal_reach: float = 1.0
    batch_points: int = 100000

    def __post_init__(self) -> None:
        for name in ('refit_growth', 'extraction_growth', 'normal_reach'):
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0):
                raise InputError(f'update.{name} must be a positive number, got {value!r}')
        if isinstance(self.batch_points, bool) or not isinstance(self.batch_points, int) or self.batch_points < 1:
            raise InputError(f'update.batch_points must be an integer >= 1, got {self.batch_points!r}')


@dataclass(frozen=True)
class MapParams:
    """All modelling parameters, by stage."""

    extraction: ExtractionParams = field(default_factory=ExtractionParams)
    layers: LayerParams = field(default_factory=LayerParams)
    gp: GPParams = field(default_factory=GPParams)
    outliers: OutlierParams = field(default_factory=OutlierParams)
    update: UpdateParams = field(default_factory=UpdateParams)
    seed: int = 0


@dataclass(frozen=True, eq=False)
class SurfaceRaster:
    """A façade's surface predicted on a regular raster of its plane.

    Attributes:
        origin: (2,) (u, v) of the lower-left corner, metres, façade frame.
        cell: cell side, metres.
        mean: (H, W) mean depth d(x), metres (row = v, column = u).
        var: (H, W) variance of the surface, m^2 (without noise).
        facet: (H, W) int32 facet of the cell, -1 where the global prior holds.
        source: (H, W) int8: 0 global prior, 1 facet prior (no data near), 2 GP posterior.
    """

    origin: np.ndarray
    cell: float
    mean: np.ndarray
    var: np.ndarray
    facet: np.ndarray
    source: np.ndarray

    def centres(self) -> np.ndarray:
        """(H*W, 2) cell centres (u, v), metres, row-major."""
        h, w = self.mean.shape
        cu = self.origin[0] + (np.arange(w) + 0.5) * self.cell
        cv = self.origin[1] + (np.arange(h) + 0.5) * self.cell
        uu, vv = np.meshgrid(cu, cv)
        return np.stack([uu.ravel(), vv.ravel()], axis=1)


@dataclass(frozen=True, eq=False)
class FacadeModel:
    """The uncertain surface model of one façade.

    Attributes:
        facade_id: index in the map.
        building: building label.
        frame: façade frame (PCA, normal outwards).
        extent: (u_min, u_max, v_min, v_max) of the façade's points, metres.
        layers: GMM depth layers.
        facets: facets of the layers on the plane.
        lengthscale2_: (K, 2) fitted 1/b_1, 1/b_2 per layer, m^2.
        global_mean_: main layer's mean depth, metres (global prior mean).
        global_var_: mean squared deviation of all the façade's depths from the main layer,
            m^2 (global prior variance).
        noise_var: sigma_eta^2, m^2.
        surface: the predicted raster.
        point_index: (M,) int64 indices of the façade's points in its building's points.
        outlier_index: (R,) int64 indices (in the building's points) of the training points
            the chi-squared test removed.
        stats: counts (points, training points, outliers removed) and timings.
        plane_extent: (u_min, u_max, v_min, v_max) of the wall itself, metres: the extent
            that, grown by ``extent_margin``, takes new points (None: ``extent``).
        anchor: (2,) (u, v) corner of the block grid, metres, façade frame; fixed at the
            first fit so that blocks and cells keep their identity as the map grows
            (None: the surface raster's origin).
        fitted_points: number of points at the last whole fit (0: ``len(point_index)``).
    """

    facade_id: int
    building: int
    frame: FacadeFrame
    extent: tuple[float, float, float, float]
    layers: DepthLayers
    facets: Facets
    lengthscale2_: np.ndarray
    global_mean_: float
    global_var_: float
    noise_var: float
    surface: SurfaceRaster
    point_index: np.ndarray = field(default_factory=lambda: np.empty(0, np.int64))
    outlier_index: np.ndarray = field(default_factory=lambda: np.empty(0, np.int64))
    stats: dict = field(default_factory=dict)
    plane_extent: tuple[float, float, float, float] | None = None
    anchor: np.ndarray | None = None
    fitted_points: int = 0

    def __post_init__(self) -> None:
        if self.plane_extent is None:
            object.__setattr__(self, 'plane_extent', tuple(self.extent))
        if self.anchor is None:
            object.__setattr__(self, 'anchor', np.asarray(self.surface.origin, dtype=np.float64).copy())
        if not self.fitted_points:
            object.__setattr__(self, 'fitted_points', int(len(self.point_index)))


def select_training(depth: np.ndarray, normal_cos: np.ndarray, layer: np.ndarray, layers: DepthLayers,
                    gp: GPParams) -> np.ndarray:
    """GP training points: not explained by their facet's layer (paper eqs. 7 and 8).

    Args:
        depth: (N,) depths, metres.
        normal_cos: (N,) |cos| of the angle between point normal and façade normal.
        layer: (N,) layer of the facet each point lies in.
        layers: the GMM.
        gp: thresholds (inlier_sigmas, alpha_z_deg).

    Returns:
        (N,) bool, True for training points: |d - mu_k| > 1.96 sigma_k or n_z < cos(alpha_z).
        For a layer wider than ``max_planar_sigma`` (EM also fits components to slopes,
        round bays and to a wall merged with shallow recesses), sigma_k in the first test is
        replaced by ``max_planar_sigma``: only the points that a plane of that spread
        explains are left to the layer, the rest go to the GP.
    """
    spread = np.minimum(layers.sigmas_[layer], gp.max_planar_sigma)
    far = np.abs(depth - layers.means_[layer]) > gp.inlier_sigmas * spread
    tilted = normal_cos < np.cos(np.deg2rad(gp.alpha_z_deg))
    return far | tilted


def _thin_planar(uv: np.ndarray, facet: np.ndarray, candidates: np.ndarray, origin: np.ndarray,
                 sizes: np.ndarray, per_block: int, rng: np.random.Generator) -> np.ndarray:
    """Pick at most ``per_block`` of the candidate points in every block (a random draw)."""
    idx = np.flatnonzero(candidates)
    if per_block <= 0 or not len(idx):
        return np.zeros(len(uv), dtype=bool)
    codes = block_codes(uv[idx], facet[idx], origin, sizes)
    order = np.lexsort((rng.random(len(idx)), codes))
    keep = idx[order[_ranks(codes[order]) < per_block]]
    out = np.zeros(len(uv), dtype=bool)
    out[keep] = True
    return out


def _raster_extent(extent: tuple[float, float, float, float], margin: float, anchor: np.ndarray, cell: float,
                   cover: tuple[float, float, float, float] | None = None) -> tuple[float, float, float, float]:
    """The points' extent grown by ``margin`` (and by ``cover``), snapped outwards to the
    cell grid through ``anchor``, metres, façade frame."""
    lo = np.array([extent[0] - margin, extent[2] - margin])
    hi = np.array([extent[1] + margin, extent[3] + margin])
    if cover is not None:
        lo = np.minimum(lo, [cover[0], cover[2]])
        hi = np.maximum(hi, [cover[1], cover[3]])
    lo = anchor + np.floor((lo - anchor) / cell + 1e-9) * cell
    hi = anchor + np.ceil((hi - anchor) / cell - 1e-9) * cell
    return (float(lo[0]), float(hi[0]), float(lo[1]), float(hi[1]))


def _extent(uv: np.ndarray) -> tuple[float, float, float, float]:
    return (float(uv[:, 0].min()), float(uv[:, 0].max()), float(uv[:, 1].min()), float(uv[:, 1].max()))


def fit_facade(extracted: ExtractedFacade, params: MapParams, rng: np.random.Generator, facade_id: int = 0,
               building: int = 0, raster_margin: float = 1.0, anchor: np.ndarray | None = None) -> FacadeModel:
    """Fit the uncertain surface of one façade whole.

    Args:
        extracted: the façade's frame and its points' façade coordinates and normals.
        params: modelling parameters.
        rng: random source (EM subsample, optimisation subset, block caps).
        facade_id: index in the map.
        building: building label.
        raster_margin: the raster reaches this far beyond the points' extent, metres.
        anchor: (2,) (u, v) corner of the block grid, metres, façade frame (a refit keeps
            the first fit's); None: the lower-left corner of the raster.

    Returns:
        The façade model.

    Raises:
        InputError: too few points.
    """
    t0 = time.perf_counter()
    uvd = extracted.uvd
    uv, depth = uvd[:, :2], uvd[:, 2]
    if len(depth) < 10:
        raise InputError(f'façade {facade_id} has {len(depth)} points, at least 10 are needed')
    gp = params.gp
    layers = fit_layers(depth, params.layers, rng)
    extent = _extent(uv)
    if anchor is None:
        anchor = np.array([extent[0] - raster_margin, extent[2] - raster_margin])
    anchor = np.asarray(anchor, dtype=np.float64)
    raster_extent = _raster_extent(extent, raster_margin, anchor, gp.grid_resolution)
    facets = find_facets(uv, layers.predict(depth), layers.n_layers, raster_extent, params.layers)
    point_facet = facets.facet_at(uv)
    has_facet = point_facet >= 0
    point_layer = np.where(has_facet, facets.layer_of_facet[np.maximum(point_facet, 0)], layers.main_)
    training = select_training(depth, extracted.normal_cos, point_layer, layers, gp) & has_facet
    t1 = time.perf_counter()

    # Length scales per layer, by maximum marginal likelihood on a few patches of its training points.
    centred = depth - layers.means_[point_layer]
    sigma_point = layers.sigmas_[point_layer]
    l2_layer = np.empty((layers.n_layers, 2))
    for k in range(layers.n_layers):
        sel = training & (point_layer == k)
        patches = optimisation_patches(uv[sel], centred[sel], sigma_point[sel], gp, rng) if sel.sum() >= 10 else []
        l2_layer[k] = optimise_lengthscales(patches, gp)
    facet_sigma = layers.sigmas_[facets.layer_of_facet]  # sigma_p = sigma_k (paper, Section III.C)
    facet_l2 = l2_layer[facets.layer_of_facet] if facets.n_facets else np.empty((0, 2))
    t2 = time.perf_counter()

    origin = np.array([raster_extent[0], raster_extent[2]])
    sizes = block_size(facet_l2, gp.c_min) if facets.n_facets else np.ones((1, 2))
    planar = _thin_planar(uv, np.maximum(point_facet, 0), has_facet & ~training, anchor, sizes,
                          gp.planar_per_block, rng)
    used = training | planar
    data = BlockData(uv[used], centred[used], point_facet[used], facet_sigma, facet_l2, anchor)

    cell = gp.grid_resolution
    width = max(1, int(np.ceil((raster_extent[1] - raster_extent[0]) / cell)))
    height = max(1, int(np.ceil((raster_extent[3] - raster_extent[2]) / cell)))
    raster = SurfaceRaster(origin, cell, np.empty((height, width)), np.empty((height, width)),
                           np.empty((height, width), np.int32), np.empty((height, width), np.int8))
    centres = raster.centres()
    cell_facet = facets.facet_at(centres)
    mean = np.full(len(centres), layers.means_[layers.main_])
    # The global prior is centred on the main layer, so its variance is the spread of all
    # depths about that layer (not about their own mean): paper, Section III.C.
    global_var = float(np.mean((depth - layers.means_[layers.main_]) ** 2))
    var = np.full(len(centres), global_var)
    source = np.full(len(centres), SOURCE_GLOBAL, np.int8)
    inside = cell_facet >= 0
    removed = 0
    outlier_index = np.empty(0, np.int64)
    t3 = time.perf_counter()
    if inside.any():
        dev, v, seen, outlier = fit_surface(data, centres[inside], cell_facet[inside], gp, rng,
                                            params.outliers.alpha, params.outliers.iterations)
        removed = int(outlier.sum())
        outlier_index = np.asarray(extracted.index, dtype=np.int64)[np.flatnonzero(used)[outlier]]
        mean[inside] = layers.means_[facets.layer_of_facet[cell_facet[inside]]] + dev
        var[inside] = v
        source[inside] = np.where(seen, SOURCE_GP, SOURCE_FACET_PRIOR)
    raster.mean[...] = mean.reshape(height, width)
    raster.var[...] = var.reshape(height, width)
    raster.facet[...] = cell_facet.reshape(height, width)
    raster.source[...] = source.reshape(height, width)
    t4 = time.perf_counter()
    stats = {'points': len(depth), 'training': int(training.sum()), 'planar_in_gp': int(planar.sum()),
             'outliers_removed': removed, 'layers': layers.n_layers, 'facets': facets.n_facets,
             'seconds': {'layers': t1 - t0, 'hyper': t2 - t1, 'setup': t3 - t2, 'gp': t4 - t3}}
    return FacadeModel(facade_id, building, extracted.frame, extent, layers, facets, l2_layer,
                       float(layers.means_[layers.main_]), global_var, gp.noise_sigma**2, raster,
                       np.asarray(extracted.index, dtype=np.int64), outlier_index, stats,
                       tuple(extracted.plane_extent), anchor, len(depth))


def _changed_cells(old: FacadeModel, offset: tuple[int, int], facet: np.ndarray, layer_of_facet: np.ndarray
                   ) -> np.ndarray:
    """(H, W) bool: cells of the new raster whose facet changed since ``old``'s.

    A cell changed if it is new, if its layer changed, or if its facet was split, merged
    or joined (facet ids are renumbered at every update; a facet is the same if it pairs
    with exactly one facet of the other raster).
    """
    h0, w0 = old.surface.facet.shape
    r0, c0 = offset
    old_facet = np.full(facet.shape, -2, dtype=np.int64)
    old_facet[r0:r0 + h0, c0:c0 + w0] = old.surface.facet
    old_layer = np.where(old_facet >= 0, old.facets.layer_of_facet[np.maximum(old_facet, 0)], old_facet)
    new_layer = np.where(facet >= 0, layer_of_facet[np.maximum(facet, 0)], -1)
    changed = (old_layer != new_layer) & ~((old_facet == -2) & (facet < 0))
    both = (old_facet >= 0) & (facet >= 0)
    pairs = np.unique(old_facet[both] * (1 << 31) + facet[both])
    old_ids, new_ids = pairs >> 31, pairs & ((1 << 31) - 1)
    o, oc = np.unique(old_ids, return_counts=True)
    n, nc = np.unique(new_ids, return_counts=True)
    changed |= np.isin(old_facet, o[oc > 1]) | np.isin(facet, n[nc > 1])
    return changed


def update_facade(model: FacadeModel, extracted: ExtractedFacade, new: np.ndarray, params: MapParams,
                  rng: np.random.Generator, raster_margin: float = 1.0) -> FacadeModel:
    """Update a façade with new points, recomputing only what they change.

    The caller decides when a façade has grown enough to be fitted whole instead
    (:meth:`FacadeMap._refit_whole`, at ``params.update.refit_growth``). Here the GMM
    layers and length scales are kept; the facets are found again on all points
    (raster operations, cheap); and the local GPs (paper eqs. 4-6) and the outlier test
    are recomputed for the blocks whose extended block holds a new training point, plus
    the cells whose facet changed and one block around them. Points previously removed as
    outliers stay removed unless their block is tested again. The raster grows to cover
    new points, on the same cell grid.

    Args:
        model: the façade as fitted so far.
        extracted: all its points (old and new) in its frame: ``frame`` is ``model.frame``,
            ``index`` sorted building indices, ``plane_extent`` the grown wall extent.
        new: (M,) bool over ``extracted``'s points, True for those added since ``model``.
        params: modelling parameters.
        rng: random source (block caps).
        raster_margin: the raster reaches this far beyond the points' extent, metres.

    Returns:
        The updated model (same id, building, frame and anchor).
    """
    n = len(extracted.index)
    t0 = time.perf_counter()
    gp = params.gp
    uv, depth = extracted.uvd[:, :2], extracted.uvd[:, 2]
    layers, anchor, old = model.layers, model.anchor, model.surface
    cell = old.cell
    extent = _extent(uv)
    h0, w0 = old.mean.shape
    old_extent = (old.origin[0], old.origin[0] + w0 * cell, old.origin[1], old.origin[1] + h0 * cell)
    raster_extent = _raster_extent(extent, raster_margin, anchor, cell, cover=old_extent)
    facets = find_facets(uv, layers.predict(depth), layers.n_layers, raster_extent, params.layers)
    point_facet = facets.facet_at(uv)
    has_facet = point_facet >= 0
    point_layer = np.where(has_facet, facets.layer_of_facet[np.maximum(point_facet, 0)], layers.main_)
    training = select_training(depth, extracted.normal_cos, point_layer, layers, gp) & has_facet
    centred = depth - layers.means_[point_layer]
    facet_sigma = layers.sigmas_[facets.layer_of_facet]
    facet_l2 = model.lengthscale2_[facets.layer_of_facet] if facets.n_facets else np.empty((0, 2))
    sizes = block_size(facet_l2, gp.c_min) if facets.n_facets else np.ones((1, 2))
    planar = _thin_planar(uv, np.maximum(point_facet, 0), has_facet & ~training, anchor, sizes,
                          gp.planar_per_block, rng)
    used = training | planar

    origin = np.array([raster_extent[0], raster_extent[2]])
    width = int(round((raster_extent[1] - raster_extent[0]) / cell))
    height = int(round((raster_extent[3] - raster_extent[2]) / cell))
    offset = (int(round((old.origin[1] - origin[1]) / cell)), int(round((old.origin[0] - origin[0]) / cell)))
    raster = SurfaceRaster(origin, cell, np.empty((height, width)), np.empty((height, width)),
                           np.empty((height, width), np.int32), np.empty((height, width), np.int8))
    centres = raster.centres()
    cell_facet = facets.facet_at(centres).reshape(height, width)
    changed = _changed_cells(model, offset, cell_facet, facets.layer_of_facet)
    # One block's reach around changed cells: their points may have moved between facets,
    # which changes the extended blocks of their neighbours.
    reach = int(np.ceil(sizes.max() / cell)) if facets.n_facets else 0
    if reach and changed.any():
        changed = ndimage.maximum_filter(changed, size=2 * reach + 1)
    inside = cell_facet.ravel() >= 0
    cell_codes = np.full(len(centres), -1, dtype=np.int64)
    cell_codes[inside] = block_codes(centres[inside], cell_facet.ravel()[inside], anchor, sizes)
    train_codes = np.full(n, -1, dtype=np.int64)
    train_codes[used] = block_codes(uv[used], point_facet[used], anchor, sizes)
    fresh = used & new
    dirty = np.union1d((train_codes[fresh][:, None] + _NEIGHBOURS[None, :]).ravel(),
                       cell_codes[changed.ravel() & inside])
    test = inside & np.isin(cell_codes, dirty)
    # Training data: the dirty blocks' extended blocks. Points removed before keep their
    # verdict unless they are tested again (own points of a dirty block).
    own = used & np.isin(train_codes, dirty)
    ring = used & np.isin(train_codes, np.unique((dirty[:, None] + _NEIGHBOURS[None, :]).ravel()))
    removed_before = np.isin(extracted.index, model.outlier_index)
    take = ring & ~(removed_before & ~own)
    t1 = time.perf_counter()

    # Start from the old raster; the global prior holds where no facet is.
    global_mean = float(layers.means_[layers.main_])
    global_var = float(np.mean((depth - global_mean) ** 2))
    mean = np.full((height, width), global_mean)
    var = np.full((height, width), global_var)
    source = np.full((height, width), SOURCE_GLOBAL, np.int8)
    r0, c0 = offset
    mean[r0:r0 + h0, c0:c0 + w0] = old.mean
    var[r0:r0 + h0, c0:c0 + w0] = old.var
    source[r0:r0 + h0, c0:c0 + w0] = old.source
    mean, var, source = mean.ravel(), var.ravel(), source.ravel()
    mean[~inside], var[~inside], source[~inside] = global_mean, global_var, SOURCE_GLOBAL
    flagged = np.zeros(n, dtype=bool)
    if test.any():
        data = BlockData(uv[take], centred[take], point_facet[take], facet_sigma, facet_l2, anchor)
        f = cell_facet.ravel()[test]
        dev, v, seen, outlier = fit_surface(data, centres[test], f, gp, rng, params.outliers.alpha,
                                            params.outliers.iterations)
        flagged[np.flatnonzero(take)[outlier]] = True
        mean[test] = layers.means_[facets.layer_of_facet[f]] + dev
        var[test] = v
        source[test] = np.where(seen, SOURCE_GP, SOURCE_FACET_PRIOR)
    outliers = (removed_before & ~own & used) | flagged
    raster.mean[...] = mean.reshape(height, width)
    raster.var[...] = var.reshape(height, width)
    raster.facet[...] = cell_facet
    raster.source[...] = source.reshape(height, width)
    t2 = time.perf_counter()
    stats = {'points': n, 'training': int(training.sum()), 'planar_in_gp': int(planar.sum()),
             'outliers_removed': int(outliers.sum()), 'layers': layers.n_layers, 'facets': facets.n_facets,
             'updated_cells': int(test.sum()), 'updated_training': int(take.sum()),
             'seconds': {'setup': t1 - t0, 'gp': t2 - t1}}
    return FacadeModel(model.facade_id, model.building, model.frame, extent, layers, facets, model.lengthscale2_,
                       global_mean, global_var, model.noise_var, raster,
                       np.asarray(extracted.index, dtype=np.int64),
                       np.asarray(extracted.index, dtype=np.int64)[outliers], stats,
                       tuple(extracted.plane_extent), anchor, model.fitted_points)


@dataclass(eq=False)
class FacadeMap:
    """Façade models of all buildings, built incrementally from building points.

    Attributes:
        params: modelling parameters.
        map_origin: (3,) georeference of the map frame, metres.
        facades: all façade models; ``facades[i].facade_id == i``; ids never change.
        points: per building label, the building's points (N, 3), metres, map frame.
        sensor_origins: per building label, (N, 3) sensor origins or None.
        normals: per building label, (N, 3) unit point normals (sign arbitrary).
        pool_checked: per building label, the number of unallocated points at the last
            RANSAC run on them.
        last_update: what the last :meth:`add_points` did: ``buildings``, ``facades_new``,
            ``facades_refitted`` (whole), ``facades_updated`` (blocks only),
            ``updated_cells`` and ``seconds``.
        pending: points held back by ``add_points(..., defer=True)``, in arrival order:
            (xyz, building_id or None, sensor_origins or None) per call.
    """

    params: MapParams = field(default_factory=MapParams)
    map_origin: np.ndarray = field(default_factory=lambda: np.zeros(3))
    facades: list[FacadeModel] = field(default_factory=list)
    points: dict[int, np.ndarray] = field(default_factory=dict)
    sensor_origins: dict[int, np.ndarray | None] = field(default_factory=dict)
    normals: dict[int, np.ndarray] = field(default_factory=dict)
    pool_checked: dict[int, int] = field(default_factory=dict)
    last_update: dict = field(default_factory=dict)
    pending: list[tuple[np.ndarray, np.ndarray | None, np.ndarray | None]] = field(default_factory=list)

    def add_points(self, xyz: np.ndarray, building_id: np.ndarray | None = None,
                   sensor_origins: np.ndarray | None = None,
                   progress: Callable[[int, int], None] | None = None, defer: bool = False) -> list[int]:
        """Add building points and update the façades they touch.

        Args:
            xyz: (N, 3) building points, metres, map frame.
            building_id: (N,) building labels (negative: none), or None to cluster; points
                without a label join the mapped building whose cells they touch, or form
                new buildings.
            sensor_origins: (N, 3) sensor origins, or None.
            progress: called with (buildings updated, buildings to update) after each one.
            defer: hold the points back (:attr:`pending`) until ``update.batch_points``
                points are pending, then map them all in one update (live mapping; see
                :meth:`flush`). The map then depends only on the sequence of calls, not
                on their timing.

        Returns:
            The labels of the buildings updated (none while points are held back).

        Raises:
            InputError: empty input, wrong shapes or non-finite coordinates (checked
                before anything changes).
        """
        xyz, building_id, sensor_origins = self._checked(xyz, building_id, sensor_origins)
        if defer:
            self.pending.append((xyz, building_id, sensor_origins))
            if self.n_pending < self.params.update.batch_points:
                return []
            return self._map_pending(progress)
        if self.pending:
            self.pending.append((xyz, building_id, sensor_origins))
            return self._map_pending(progress)
        return self._add(xyz, building_id, sensor_origins, progress)

    @property
    def n_pending(self) -> int:
        """Number of points held back."""
        return int(sum(len(p[0]) for p in self.pending))

    def _map_pending(self, progress: Callable[[int, int], None] | None = None) -> list[int]:
        parts, self.pending = self.pending, []
        if not parts:
            return []
        xyz = np.vstack([p[0] for p in parts])
        ids = None
        if any(p[1] is not None for p in parts):
            ids = np.concatenate([p[1] if p[1] is not None else np.full(len(p[0]), -1, np.int64) for p in parts])
        origins = None if any(p[2] is None for p in parts) else np.vstack([p[2] for p in parts])
        return self._add(xyz, ids, origins, progress)

    def flush(self, consolidate: bool = True) -> list[int]:
        """Map the points held back, then (``consolidate``) fit whole every façade that
        was only updated block by block since its last whole fit, so that the map is as
        good as one built in one go from the same points.

        Returns:
            The ids of the façades fitted whole.
        """
        self._map_pending()
        if not consolidate:
            return []
        done = []
        for f in list(self.facades):
            if f.fitted_points != len(f.point_index):
                self._refit_whole(f.building, f.facade_id, f.point_index, f.plane_extent)
                done.append(f.facade_id)
        return done

    def _checked(self, xyz: np.ndarray, building_id: np.ndarray | None, sensor_origins: np.ndarray | None
                 ) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
        xyz = np.asarray(xyz, dtype=np.float64)
        if xyz.ndim != 2 or xyz.shape[1] != 3:
            raise InputError(f'points must be an (N, 3) array, got shape {xyz.shape}')
        if not len(xyz):
            raise InputError('no building points to map')
        if not np.isfinite(xyz).all():
            raise InputError(f'{int((~np.isfinite(xyz)).any(axis=1).sum())} points have NaN or infinite coordinates')
        if sensor_origins is not None:
            sensor_origins = np.asarray(sensor_origins, dtype=np.float64)
            if sensor_origins.shape != xyz.shape:
                raise InputError(f'sensor_origins must have the shape of the points {xyz.shape}, '
                                 f'got {sensor_origins.shape}')
        if building_id is not None:
            building_id = check_building_ids(building_id, len(xyz))
        return xyz, building_id, sensor_origins

    def _add(self, xyz: np.ndarray, building_id: np.ndarray | None, sensor_origins: np.ndarray | None,
             progress: Callable[[int, int], None] | None) -> list[int]:
        t0 = time.perf_counter()
        labels = self._labels(xyz, building_id)
        self.last_update = {'buildings': [], 'facades_new': [], 'facades_refitted': [], 'facades_updated': [],
                            'updated_cells': 0}
        changed = [int(b) for b in np.unique(labels)]
        for done, b in enumerate(changed, 1):
            sel = labels == b
            first = self._append(b, xyz[sel], None if sensor_origins is None else sensor_origins[sel])
            self._update_building(b, first)
            if progress is not None:
                progress(done, len(changed))
        self.last_update['buildings'] = changed
        self.last_update['seconds'] = time.perf_counter() - t0
        return changed

    def _labels(self, xyz: np.ndarray, building_id: np.ndarray | None) -> np.ndarray:
        """Building label of each new point: its id, else the clustered building it touches."""
        n = len(xyz)
        if building_id is None:
            labels = np.full(n, -1, dtype=np.int64)
        else:
            labels = np.where(building_id < 0, -1, building_id)
        free = np.flatnonzero(labels < 0)
        if not len(free):
            return labels
        cells = self._cell_keys(xyz[free])
        comp = _grid_components(np.stack([cells >> 32, cells & 0xFFFFFFFF], axis=1))
        near = (cells[:, None] + _CELL_NEIGHBOURS[None, :]).ravel()
        comp_near = np.repeat(comp, 9)
        # A cluster joins the mapped building whose cells it touches most.
        mapping: dict[int, tuple[int, int]] = {}
        for b, keys in self._cells.items():
            hit = np.isin(near, keys)
            for c, count in zip(*np.unique(comp_near[hit], return_counts=True)):
                if count > mapping.get(int(c), (0, -1))[0]:
                    mapping[int(c)] = (int(count), b)
        out = np.empty(len(free), dtype=np.int64)
        next_label = max([int(labels.max()), *self.points.keys(), -1]) + 1
        for c in np.unique(comp):
            if int(c) in mapping:
                out[comp == c] = mapping[int(c)][1]
            else:
                out[comp == c] = next_label
                next_label += 1
        labels[free] = out
        return labels

    def _cell_keys(self, xyz: np.ndarray) -> np.ndarray:
        """(N,) int64 keys of the clustering grid cells of (N, 3) points (offset to be >= 0)."""
        c = np.floor(xyz[:, :2] / self.params.extraction.building_cell).astype(np.int64) + (1 << 30)
        return c[:, 0] * (1 << 32) + c[:, 1]

    @property
    def _cells(self) -> dict[int, np.ndarray]:
        """Per building, the sorted keys of its occupied clustering cells (cached)."""
        cache = self.__dict__.setdefault('_cell_cache', {})
        for b, pts in self.points.items():
            if cache.get(b, (None, -1))[1] != len(pts):
                cache[b] = (np.unique(self._cell_keys(pts)), len(pts))
        return {b: keys for b, (keys, _) in cache.items() if b in self.points}

    def _append(self, b: int, xyz: np.ndarray, origins: np.ndarray | None) -> int:
        """Append a building's new points (and their normals); returns the first new index."""
        old = self.points.get(b)
        first = 0 if old is None else len(old)
        pts = xyz if old is None else np.vstack([old, xyz])
        self.points[b] = pts
        old_so = self.sensor_origins.get(b)
        self.sensor_origins[b] = origins if old is None else (None if origins is None or old_so is None
                                                              else np.vstack([old_so, origins]))
        k = self.params.extraction.normal_neighbours
        if old is None:
            normals = _point_normals(pts - pts.mean(axis=0), min(k, len(pts))) if len(pts) >= 3 else \
                np.tile([0.0, 0.0, 1.0], (len(pts), 1))
        else:
            # Neighbours from the building's points near the new ones only.
            reach = self.params.update.normal_reach
            lo, hi = xyz.min(axis=0) - reach, xyz.max(axis=0) + reach
            near = np.flatnonzero(np.all((old >= lo) & (old <= hi), axis=1))
            local = np.vstack([old[near], xyz])
            centre = local.mean(axis=0)
            normals = np.vstack([self.normals[b], np.zeros((len(xyz), 3))])
            if len(local) >= 3:
                normals[first:] = _point_normals(local - centre, min(k, len(local)))[len(near):]
            else:
                normals[first:] = [0.0, 0.0, 1.0]
        self.normals[b] = normals
        return first

    def facade_of_points(self, building: int) -> np.ndarray:
        """(N,) int64 façade id of each of a building's points, -1 for none."""
        out = np.full(len(self.points[building]), -1, dtype=np.int64)
        for f in self.facades:
            if f.building == building:
                out[f.point_index] = f.facade_id
        return out

    def _extracted(self, b: int, index: np.ndarray, frame: FacadeFrame,
                   plane_extent: tuple[float, float, float, float]) -> ExtractedFacade:
        uvd = frame.to_local(self.points[b][index])
        cos = np.minimum(np.abs(self.normals[b][index] @ frame.normal), 1.0)
        return ExtractedFacade(frame, index, uvd, cos, _extent(uvd[:, :2]), plane_extent)

    def _update_building(self, b: int, first: int) -> None:
        """Allocate a building's points from ``first`` on, extract new façades from its pool,
        and update the façades that received points."""
        ex, params = self.params.extraction, self.params
        pts = self.points[b]
        n = len(pts)
        owner = self.facade_of_points(b)
        mine = [f.facade_id for f in self.facades if f.building == b]
        if mine and first < n:
            which, _ = assign_to_facades(pts[first:], [self.facades[i] for i in mine], ex)
            owner[first:] = np.where(which >= 0, np.asarray(mine)[np.maximum(which, 0)], -1)
        grown: dict[int, tuple[float, float, float, float]] = {}
        pool = np.flatnonzero(owner < 0)
        checked = self.pool_checked.get(b, 0)
        step = max(ex.min_facade_points, params.update.extraction_growth * checked)
        if len(pool) >= ex.min_facade_points and len(pool) >= checked + step:
            rng = np.random.default_rng([params.seed, b, n])
            so = self.sensor_origins.get(b)
            extracted, _ = extract_facades(pts[pool], ex, sensor_origins=None if so is None else so[pool], rng=rng)
            for e in extracted:
                index = pool[e.index]
                target = self._coplanar(b, e)
                if target is None:
                    fid = len(self.facades)
                    model = fit_facade(self._extracted(b, index, e.frame, e.plane_extent), params,
                                       np.random.default_rng([params.seed, b, fid, len(index)]), fid, b)
                    self.facades.append(model)
                    owner[index] = fid
                    self.last_update['facades_new'].append(fid)
                    continue
                t = self.facades[target]
                d = t.frame.to_local(pts[index])[:, 2]
                fits = (d >= -ex.band_back) & (d <= ex.band_front)
                owner[index[fits]] = target
                grown[target] = _union(grown.get(target, t.plane_extent), _extent(_plane_corners_in(e, t.frame)))
            self.pool_checked[b] = int((owner < 0).sum())
        new_ids = set(self.last_update['facades_new'])
        for fid in sorted(set(np.unique(owner[first:][owner[first:] >= 0]).tolist()) | set(grown)):
            if fid in new_ids:
                continue
            model = self.facades[fid]
            index = np.flatnonzero(owner == fid)
            fresh = ~np.isin(index, model.point_index)
            if not fresh.any():
                continue
            # The wall's extent grows with the new points on the plane.
            plane = grown.get(fid, model.plane_extent)
            uvd_new = model.frame.to_local(pts[index[fresh]])
            on_plane = uvd_new[np.abs(uvd_new[:, 2]) <= ex.ransac_threshold]
            if len(on_plane) >= 3:
                plane = _union(plane, _plane_box(on_plane))
            if len(index) >= (1.0 + params.update.refit_growth) * model.fitted_points:
                updated = self._refit_whole(b, fid, index, plane)
            else:
                rng = np.random.default_rng([params.seed, b, fid, len(index)])
                updated = update_facade(model, self._extracted(b, index, model.frame, plane), fresh, params, rng)
                self.facades[fid] = updated
            key = 'facades_refitted' if updated.fitted_points == len(index) else 'facades_updated'
            self.last_update[key].append(fid)
            self.last_update['updated_cells'] += int(updated.stats.get('updated_cells', updated.surface.mean.size))

    def _refit_whole(self, b: int, fid: int, index: np.ndarray, plane: tuple[float, float, float, float]
                     ) -> FacadeModel:
        """Fit façade ``fid`` whole on the points ``index``, its frame estimated again (the
        first came from a part of the wall, and a small tilt smears the depth layers)."""
        ex, pts, model = self.params.extraction, self.points[b], self.facades[fid]
        rng = np.random.default_rng([self.params.seed, b, fid, len(index)])
        frame = _final_frame(pts[index], self.normals[b][index], model.frame, ex) or model.frame
        uvd = frame.to_local(pts[index])
        wall = uvd[np.abs(uvd[:, 2]) <= ex.ransac_threshold]
        if len(wall) >= 3:
            plane = _plane_box(wall)
        elif frame is not model.frame:
            frame, plane = model.frame, plane
        updated = fit_facade(self._extracted(b, index, frame, plane), self.params, rng, fid, b)
        self.facades[fid] = updated
        return updated

    def _coplanar(self, b: int, e: ExtractedFacade) -> int | None:
        """Id of the building's façade that a newly extracted one continues (the merge rule
        of the extraction: parallel within ``merge_angle_deg``, closer than ``merge_offset``
        along the normal and in u), or None."""
        ex = self.params.extraction
        cos_max = np.cos(np.deg2rad(ex.merge_angle_deg))
        best = None
        for f in self.facades:
            if f.building != b or float(e.frame.normal @ f.frame.normal) < cos_max:
                continue
            box = _plane_corners_in(e, f.frame)
            d = float(f.frame.to_local(e.frame.origin[None])[0, 2])
            gap = max(f.plane_extent[0] - box[:, 0].max(), box[:, 0].min() - f.plane_extent[1], 0.0)
            if abs(d) < ex.merge_offset and gap <= ex.merge_offset:
                if best is None or len(f.point_index) > len(self.facades[best].point_index):
                    best = f.facade_id
        return best

    def rejected(self, building: int) -> np.ndarray:
        """(N,) bool over a building's points: on no façade, or removed by the outlier test."""
        n = len(self.points[building])
        on_facade = np.zeros(n, dtype=bool)
        removed = np.zeros(n, dtype=bool)
        for f in self.facades:
            if f.building == building:
                on_facade[f.point_index] = True
                removed[f.outlier_index] = True
        return removed | ~on_facade

    @property
    def buildings(self) -> list[int]:
        """Labels of the mapped buildings."""
        return sorted(self.points)

    @property
    def n_points(self) -> int:
        """Number of building points in the map."""
        return int(sum(len(p) for p in self.points.values()))


def _plane_corners_in(e: ExtractedFacade, frame: FacadeFrame) -> np.ndarray:
    """(4, 2) (u, v) in ``frame`` of the corners of ``e``'s wall extent (on its plane)."""
    b = e.plane_extent
    corners = np.array([[b[i], b[j], 0.0] for i in (0, 1) for j in (2, 3)])
    return frame.to_local(e.frame.to_world(corners))[:, :2]


def _union(a: tuple[float, float, float, float], b: tuple[float, float, float, float]
           ) -> tuple[float, float, float, float]:
    return (min(a[0], b[0]), max(a[1], b[1]), min(a[2], b[2]), max(a[3], b[3]))


def build_map(xyz: np.ndarray, building_id: np.ndarray | None = None, sensor_origins: np.ndarray | None = None,
              params: MapParams | None = None, map_origin: np.ndarray | None = None,
              progress: Callable[[int, int], None] | None = None) -> FacadeMap:
    """Build a map from building points in one go (see :meth:`FacadeMap.add_points`)."""
    fmap = FacadeMap(params or MapParams(), np.zeros(3) if map_origin is None else np.asarray(map_origin, float))
    fmap.add_points(xyz, building_id, sensor_origins, progress)
    return fmap
