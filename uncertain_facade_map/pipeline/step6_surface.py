"""One façade's uncertain surface: steps 2 to 5 of the pipeline, predicted onto a raster.

The surface of a façade is d(x) = g(x) + f(x) (paper eq. 2): g = mu_k of the facet's
layer, f the facet's local GP. Where no facet covers a location, the global GP prior holds:
the main layer's mean with the variance of all the façade's depths about it.

:func:`fit_facade` fits a façade whole; :func:`update_facade` adds points to a fitted
façade and recomputes only the blocks the new points touch. The caller
(:class:`~uncertain_facade_map.mapping.facade_map.FacadeMap`) decides which one to use.
"""

from __future__ import annotations

import time

import numpy as np
from scipy import ndimage

from ..datatypes import (
    SOURCE_FACET_PRIOR,
    SOURCE_GLOBAL,
    SOURCE_GP,
    ExtractedFacade,
    FacadeModel,
    SurfaceRaster,
)
from ..errors import InputError
from ..params import MapParams
from .step2_layers import find_facets, fit_layers
from .step3_training import _thin_planar, select_training
from .step4_gp_blocks import (
    _NEIGHBOURS,
    BlockData,
    block_codes,
    block_size,
    fit_surface,
    optimisation_patches,
    optimise_lengthscales,
)


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
