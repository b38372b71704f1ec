"""One façade's uncertain surface: steps 2 to 5 of the pipeline, predicted onto a raster.

The surface of a façade is d(x) = g(x) + f(x) (paper eq. 2): g = mu_k of the facet's
layer, f the facet's local GP. Where no facet covers a location, the global GP prior holds:
the main layer's mean with the variance of all the façade's depths about it.

:func:`fit_facade` fits a façade whole; :func:`update_facade` adds points to a fitted
façade and recomputes only the blocks the new points touch. The caller
(:class:`~uncertain_facade_map.mapping.facade_map.FacadeMap`) decides which one to use.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from ..datatypes import (
    SOURCE_FACET_PRIOR,
    SOURCE_GLOBAL,
    SOURCE_GP,
    DepthLayers,
    ExtractedFacade,
    FacadeModel,
    Facets,
    SurfaceRaster,
    cell_centres,
)
from ..errors import InputError
from ..params import MapParams
from .step2_layers import count_peaks, find_facets, fit_layers, fit_relief
from .step3_training import _thin_planar, select_training
from .step4_gp_blocks import (
    _NEIGHBOURS,
    BlockData,
    block_codes,
    block_size,
    estimate_noise,
    fit_surface,
    in_sorted,
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


def _raster_shape(raster_extent: tuple[float, float, float, float], cell: float) -> tuple[int, int]:
    """(rows, columns) of the raster over a snapped extent (its ends lie on the cell grid)."""
    width = max(1, int(round((raster_extent[1] - raster_extent[0]) / cell)))
    height = max(1, int(round((raster_extent[3] - raster_extent[2]) / cell)))
    return height, width


def _global_prior(depth: np.ndarray, layers: DepthLayers) -> tuple[float, float]:
    """Mean and variance of the global GP prior, metres and m^2 (paper, Section III.C).

    The prior is centred on the main layer, so its variance is the spread of all depths
    about that layer (not about their own mean).
    """
    mean = float(layers.means_[layers.main_])
    return mean, float(np.mean((depth - mean) ** 2))


def _noise_sigma(uv: np.ndarray, depth: np.ndarray, params: MapParams) -> float:
    """sigma_eta of a façade, metres: estimated from its points (``gp.estimate_noise``; pairs
    at lags from ``update.store_spacing`` to ``gp.noise_lag``, at least twice the spacing), or
    ``gp.noise_sigma``."""
    gp = params.gp
    if not gp.estimate_noise:
        return gp.noise_sigma
    return max(estimate_noise(uv, depth, max(gp.noise_lag, 2 * params.update.store_spacing), gp.noise_sigma,
                              params.update.store_spacing), gp.min_noise_sigma)


def _with_noise(params: MapParams, noise_sigma: float) -> MapParams:
    """``params`` with the façade's sigma_eta, metres."""
    return dataclasses.replace(params, gp=dataclasses.replace(params.gp, noise_sigma=noise_sigma))


@dataclass(frozen=True, eq=False)
class _LayeredPoints:
    """A façade's points read through its depth layers and facets (steps 2 and 3).

    Attributes:
        uv: (N, 2) locations on the plane, metres, façade frame.
        depth: (N,) depths from the wall's relief, metres.
        facets: the facets of the layers on the raster.
        point_facet: (N,) facet of each point, -1 outside every facet.
        point_layer: (N,) layer of each point's facet (the main layer outside facets).
        training: (N,) bool, GP training points (eqs. 7 and 8), inside a facet.
        centred: (N,) depth minus the mean of the point's layer, metres.
    """

    uv: np.ndarray
    depth: np.ndarray
    facets: Facets
    point_facet: np.ndarray
    point_layer: np.ndarray
    training: np.ndarray
    centred: np.ndarray


def _layered_points(extracted: ExtractedFacade, depth: np.ndarray, layers: DepthLayers,
                    raster_extent: tuple[float, float, float, float], params: MapParams,
                    labels: np.ndarray | None = None) -> _LayeredPoints:
    """Facets of the layers on the raster, and the GP training points (eqs. 7 and 8).

    ``depth``: (N,) the points' depths from the wall's relief, metres; ``labels``: (N,)
    their most responsible layers if known (``layers.predict(depth)``)."""
    uv = extracted.uvd[:, :2]
    labels = layers.predict(depth) if labels is None else labels
    facets = find_facets(uv, labels, layers.n_layers, raster_extent, params.layers)
    point_facet = facets.facet_at(uv)
    has_facet = point_facet >= 0
    point_layer = np.where(has_facet, facets.layer_of_facet[np.maximum(point_facet, 0)], layers.main_)
    training = select_training(depth, extracted.normal_cos, point_layer, layers, params.gp) & has_facet
    return _LayeredPoints(uv, depth, facets, point_facet, point_layer, training, depth - layers.means_[point_layer])


def _fit_lengthscales(pts: _LayeredPoints, layers: DepthLayers, params: MapParams, rng: np.random.Generator
                      ) -> np.ndarray:
    """(K, 2) 1/b_1, 1/b_2 per layer, m^2: maximum marginal likelihood on a few patches of
    the layer's training points (pooled over its facets)."""
    sigma_point = layers.sigmas_[pts.point_layer]
    l2_layer = np.empty((layers.n_layers, 2))
    for k in range(layers.n_layers):
        sel = pts.training & (pts.point_layer == k)
        patches = (optimisation_patches(pts.uv[sel], pts.centred[sel], sigma_point[sel], params.gp, rng)
                   if sel.sum() >= 10 else [])
        l2_layer[k] = optimise_lengthscales(patches, params.gp)
    return l2_layer


@dataclass(frozen=True, eq=False)
class _GPSetup:
    """The local GPs' data: per facet its prior and length scales, the block sizes, and the
    points that train them.

    Attributes:
        facet_sigma: (F,) sigma_p of each facet = sigma_k of its layer (paper, Section III.C), metres.
        facet_l2: (F, 2) 1/b_1, 1/b_2 of each facet (its layer's), m^2.
        sizes: (F, 2) block sides per facet, metres.
        planar: (N,) bool, planar points added to the training points (``gp.planar_per_block``).
        used: (N,) bool, the points that train the GPs.
    """

    facet_sigma: np.ndarray
    facet_l2: np.ndarray
    sizes: np.ndarray
    planar: np.ndarray
    used: np.ndarray


def _gp_setup(pts: _LayeredPoints, layers: DepthLayers, l2_layer: np.ndarray, anchor: np.ndarray, params: MapParams,
              rng: np.random.Generator) -> _GPSetup:
    """Priors, length scales and block sizes per facet (Section III.D), and the training points."""
    facets, gp = pts.facets, params.gp
    facet_sigma = layers.sigmas_[facets.layer_of_facet]
    facet_l2 = l2_layer[facets.layer_of_facet] if facets.n_facets else np.empty((0, 2))
    sizes = block_size(facet_l2, gp.c_min) if facets.n_facets else np.ones((1, 2))
    has_facet = pts.point_facet >= 0
    planar = _thin_planar(pts.uv, np.maximum(pts.point_facet, 0), has_facet & ~pts.training, anchor, sizes,
                          gp.planar_per_block, rng)
    return _GPSetup(facet_sigma, facet_l2, sizes, planar, pts.training | planar)


def _block_data(pts: _LayeredPoints, setup: _GPSetup, take: np.ndarray, anchor: np.ndarray) -> BlockData:
    return BlockData(pts.uv[take], pts.centred[take], pts.point_facet[take], setup.facet_sigma, setup.facet_l2, anchor)


def _predict_cells(data: BlockData, centres: np.ndarray, cell_facet: np.ndarray, cells: np.ndarray,
                   layers: DepthLayers, facets: Facets, params: MapParams, rng: np.random.Generator,
                   relief: np.ndarray, mean: np.ndarray, var: np.ndarray, source: np.ndarray) -> np.ndarray:
    """Test the training points for outliers and predict the local GPs at the raster cells
    ``cells`` (steps 4 and 5), writing mean, variance and source there.

    Args:
        data: the training points of the blocks of those cells.
        centres: (C, 2) all cell centres, metres, façade frame.
        cell_facet: (C,) facet of every cell.
        cells: (C,) bool, the cells to predict (inside a facet).
        relief: (C,) depth of the wall's relief at every cell, metres.
        mean, var, source: (C,) the raster's values, written at ``cells``.

    Returns:
        (T,) bool over ``data``'s points: removed as outliers.
    """
    f = cell_facet[cells]
    dev, v, seen, outlier = fit_surface(data, centres[cells], f, params.gp, rng, params.outliers.alpha,
                                        params.outliers.iterations)
    # d(x) = g(x) + f(x), eq. 2, with g = the relief plus the layer's offset mu_k.
    mean[cells] = relief[cells] + layers.means_[facets.layer_of_facet[f]] + dev
    var[cells] = v
    source[cells] = np.where(seen, SOURCE_GP, SOURCE_FACET_PRIOR)
    return outlier


def _raster(origin: np.ndarray, cell: float, shape: tuple[int, int], mean: np.ndarray, var: np.ndarray,
            cell_facet: np.ndarray, source: np.ndarray) -> SurfaceRaster:
    return SurfaceRaster(origin=origin, cell=cell, mean=mean.reshape(shape), var=var.reshape(shape),
                         facet=cell_facet.reshape(shape), source=source.reshape(shape))


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
    uv, raw_depth = extracted.uvd[:, :2], extracted.uvd[:, 2]
    if len(raw_depth) < 10:
        raise InputError(f'façade {facade_id} has {len(raw_depth)} points, at least 10 are needed')
    cell = params.gp.grid_resolution
    # The noise from the data (or the configured sigma_eta): the GPs of this façade use it.
    params = _with_noise(params, _noise_sigma(uv, raw_depth, params))
    # Step 2: the wall's relief, then the GMM of depth layers (eq. 3) as offsets from it.
    relief = fit_relief(uv, raw_depth, float(count_peaks(raw_depth, params.layers)[0]), params.gp.noise_sigma,
                        params.layers, rng)
    depth = raw_depth - relief.at(uv)
    layers = fit_layers(depth, params.layers, rng)
    extent = _extent(uv)
    if anchor is None:
        anchor = np.array([extent[0] - raster_margin, extent[2] - raster_margin])
    anchor = np.asarray(anchor, dtype=np.float64)
    raster_extent = _raster_extent(extent, raster_margin, anchor, cell)
    # Steps 2-3: facets of the layers, training points (eqs. 7, 8).
    pts = _layered_points(extracted, depth, layers, raster_extent, params)
    t1 = time.perf_counter()
    # Step 4: length scales per layer by maximum marginal likelihood; blocks per facet.
    l2_layer = _fit_lengthscales(pts, layers, params, rng)
    t2 = time.perf_counter()
    setup = _gp_setup(pts, layers, l2_layer, anchor, params, rng)
    data = _block_data(pts, setup, setup.used, anchor)
    # The raster: the global prior everywhere, the facets' GPs where a facet is.
    origin = np.array([raster_extent[0], raster_extent[2]])
    shape = _raster_shape(raster_extent, cell)
    centres = cell_centres(origin, cell, shape)
    cell_facet = pts.facets.facet_at(centres)
    global_mean, global_var = _global_prior(depth, layers)
    base = relief.at(centres)
    mean = base + global_mean
    var = np.full(len(centres), global_var)
    source = np.full(len(centres), SOURCE_GLOBAL, np.int8)
    inside = cell_facet >= 0
    outlier = np.zeros(int(setup.used.sum()), dtype=bool)
    t3 = time.perf_counter()
    # Steps 4-5: outliers by the chi-squared test, then the GPs' posterior on the cells.
    if inside.any():
        outlier = _predict_cells(data, centres, cell_facet, inside, layers, pts.facets, params, rng, base, mean, var,
                                 source)
    t4 = time.perf_counter()
    index = np.asarray(extracted.index, dtype=np.int64)
    stats = {'points': len(depth), 'training': int(pts.training.sum()), 'planar_in_gp': int(setup.planar.sum()),
             'outliers_removed': int(outlier.sum()), 'layers': layers.n_layers, 'facets': pts.facets.n_facets,
             'noise_sigma': params.gp.noise_sigma, 'relief_range': float(np.ptp(relief.values)),
             'seconds': {'layers': t1 - t0, 'hyper': t2 - t1, 'setup': t3 - t2, 'gp': t4 - t3}}
    return FacadeModel(
        facade_id=facade_id, building=building, frame=extracted.frame, extent=extent, layers=layers,
        facets=pts.facets, lengthscale2_=l2_layer, global_mean_=global_mean, global_var_=global_var,
        noise_var=params.gp.noise_sigma**2,
        surface=_raster(origin, cell, shape, mean, var, cell_facet, source),
        point_index=index, outlier_index=index[np.flatnonzero(setup.used)[outlier]], stats=stats,
        plane_extent=tuple(extracted.plane_extent), anchor=anchor, fitted_points=len(depth), relief=relief)


def _changed_cells(old: FacadeModel, offset: tuple[int, int], facet: np.ndarray, layer_of_facet: np.ndarray,
                   centres: np.ndarray, anchor: np.ndarray, layer_sizes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Cells of the new raster whose GP must be computed again because the facets changed since ``old``'s.

    Facet ids are renumbered at every update, and a block's GP is trained on the points of
    its own facet in its extended block (itself and its 8 neighbours, paper Section III.D).
    So a cell's prediction changes with the facets only if its layer changed (its prior
    mean and block grid), or if the points that share a facet within its block's extended
    block are not the same ones as before: facets merged or split *there*. A merge far away
    (a wall's two parts joined by new points at one end) relabels the rest without changing
    any of its GPs.

    Args:
        old: the façade before the update.
        offset: (rows, columns) of ``old``'s raster within the new one.
        facet: (H, W) new facet of each cell (-1: none).
        layer_of_facet: (F,) layer of each new facet.
        centres: (H * W, 2) cell centres, metres, façade frame.
        anchor: (2,) corner of the block grids, metres.
        layer_sizes: (K, 2) block sides per layer, metres (the layers' length scales are kept).

    Returns:
        ``(layer_changed, regrouped)``: (H, W) bool each; cells that are new, lost their facet
        or changed layer (the caller computes one block around them again: their points may
        have moved between facets, which changes the extended blocks of their neighbours);
        and cells of a block whose extended block's same-facet membership changed (merged
        or split facets within reach), to compute again as they are.
    """
    h0, w0 = old.surface.facet.shape
    r0, c0 = offset
    old_facet = np.full(facet.shape, -2, dtype=np.int64)
    old_facet[r0:r0 + h0, c0:c0 + w0] = old.surface.facet
    old_layer = np.where(old_facet >= 0, old.facets.layer_of_facet[np.maximum(old_facet, 0)], old_facet)
    new_layer = np.where(facet >= 0, layer_of_facet[np.maximum(facet, 0)], -1)
    layer_changed = (old_layer != new_layer) & ~((old_facet == -2) & (facet < 0))
    # Cells that kept their layer and a facet: (layer, block) in the layer's grid, old and new facet.
    both = ((old_facet >= 0) & (facet >= 0) & ~layer_changed).ravel()
    regrouped = np.zeros(facet.size, dtype=bool)
    if not both.any():
        return layer_changed, regrouped.reshape(facet.shape)
    k = new_layer.ravel()[both].astype(np.int64)
    blk = np.floor((centres[both] - anchor) / layer_sizes[k]).astype(np.int64)
    blk -= blk.min(axis=0) - 1  # from 1: a neighbour's index stays >= 0
    n_u, n_v = int(blk[:, 0].max()) + 2, int(blk[:, 1].max()) + 2
    o = old_facet.ravel()[both]
    f = facet.ravel()[both].astype(np.int64)
    n_o, n_f = int(o.max()) + 1, int(f.max()) + 1
    if float(k.max() + 1) * n_u * n_v * n_o * n_f > 2.0 ** 62:  # keys would overflow: compute all again
        regrouped[both] = True
        return layer_changed, regrouped.reshape(facet.shape)
    # One int64 per (layer, block, old facet, new facet): 1-D sorts instead of row-wise ones.
    block = (k * n_u + blk[:, 0]) * n_v + blk[:, 1]
    rows = np.unique((block * n_o + o) * n_f + f)
    # Each row seen from the 9 blocks whose extended block holds its block.
    shifts = (np.array([-1, 0, 1])[:, None] * n_v + np.array([-1, 0, 1])[None, :]).ravel() * n_o * n_f
    seen = np.unique((rows[:, None] + shifts[None, :]).ravel())
    window, of = np.divmod(seen, n_o * n_f)
    so, sf = np.divmod(of, n_f)
    # Per window and new facet, more than one old facet: merged there; per window and old
    # facet, more than one new facet: split there.
    dirty = np.zeros(len(seen), dtype=bool)
    for key in (window * n_f + sf, window * n_o + so):
        _, inverse, counts = np.unique(key, return_inverse=True, return_counts=True)
        dirty |= counts[inverse] > 1
    bad = np.unique(window[dirty] * n_f + sf[dirty])  # (window = block, new facet) to compute again
    regrouped[np.flatnonzero(both)] = in_sorted(block * n_f + f, bad)
    return layer_changed, regrouped.reshape(facet.shape)


def update_facade(model: FacadeModel, extracted: ExtractedFacade, new: np.ndarray, params: MapParams,
                  rng: np.random.Generator, raster_margin: float = 1.0, depth: np.ndarray | None = None,
                  labels: np.ndarray | None = None) -> FacadeModel:
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
        depth: (N,) the points' depths from the model's relief, metres, if the caller keeps
            them (``d - model.relief.at(u, v)``); None: computed here.
        labels: (N,) their most responsible layers (``model.layers.predict(depth)``), or None.

    Returns:
        The updated model (same id, building, frame and anchor).
    """
    n = len(extracted.index)
    t0 = time.perf_counter()
    layers, anchor, old = model.layers, model.anchor, model.surface
    cell = old.cell
    uv = extracted.uvd[:, :2]
    extent = _extent(uv)
    # The raster grows to cover the new points, on the same cell grid.
    h0, w0 = old.mean.shape
    old_extent = (old.origin[0], old.origin[0] + w0 * cell, old.origin[1], old.origin[1] + h0 * cell)
    raster_extent = _raster_extent(extent, raster_margin, anchor, cell, cover=old_extent)
    # Steps 2-3 with the relief, noise and layers kept: facets found again, training points (eqs. 7, 8).
    params = _with_noise(params, float(np.sqrt(model.noise_var)))
    depth = extracted.uvd[:, 2] - model.relief.at(uv) if depth is None else depth
    pts = _layered_points(extracted, depth, layers, raster_extent, params, labels)
    # Step 4 with the length scales kept.
    setup = _gp_setup(pts, layers, model.lengthscale2_, anchor, params, rng)
    facets, used = pts.facets, setup.used
    origin = np.array([raster_extent[0], raster_extent[2]])
    shape = _raster_shape(raster_extent, cell)
    offset = (int(round((old.origin[1] - origin[1]) / cell)), int(round((old.origin[0] - origin[0]) / cell)))
    centres = cell_centres(origin, cell, shape)
    cell_facet = facets.facet_at(centres).reshape(shape)
    # What must be computed again: the blocks near new training points, and the cells
    # whose facet changed with one block's reach around them (their points may have moved
    # between facets, which changes the extended blocks of their neighbours).
    changed, regrouped = _changed_cells(model, offset, cell_facet, facets.layer_of_facet, centres, anchor,
                                        block_size(model.lengthscale2_, params.gp.c_min))
    reach = int(np.ceil(setup.sizes.max() / cell)) if facets.n_facets else 0
    if reach and changed.any():
        changed = ndimage.maximum_filter(changed, size=2 * reach + 1)
    changed |= regrouped
    inside = cell_facet.ravel() >= 0
    cell_codes = np.full(len(centres), -1, dtype=np.int64)
    cell_codes[inside] = block_codes(centres[inside], cell_facet.ravel()[inside], anchor, setup.sizes)
    train_codes = np.full(n, -1, dtype=np.int64)
    train_codes[used] = block_codes(pts.uv[used], pts.point_facet[used], anchor, setup.sizes)
    fresh = used & new
    near = np.unique((train_codes[fresh][:, None] + _NEIGHBOURS[None, :]).ravel())  # blocks near new training points
    dirty = np.union1d(near, cell_codes[changed.ravel() & inside])
    test = inside & in_sorted(cell_codes, dirty)  # dirty: sorted and unique (union1d)
    near_new = inside & in_sorted(cell_codes, near)
    # Training data: the dirty blocks' extended blocks. Points removed before keep their
    # verdict unless they are tested again (own points of a dirty block).
    own = used & in_sorted(train_codes, dirty)
    ring = used & in_sorted(train_codes, np.unique((dirty[:, None] + _NEIGHBOURS[None, :]).ravel()))
    removed_before = in_sorted(extracted.index, model.outlier_index)  # both sorted building indices
    take = ring & ~(removed_before & ~own)
    t1 = time.perf_counter()

    # The raster: the old one where it was, the global prior where no facet is.
    global_mean, global_var = _global_prior(pts.depth, layers)
    base = model.relief.at(centres)
    mean = np.full(shape, global_mean)
    var = np.full(shape, global_var)
    source = np.full(shape, SOURCE_GLOBAL, np.int8)
    r0, c0 = offset
    mean[r0:r0 + h0, c0:c0 + w0] = old.mean
    var[r0:r0 + h0, c0:c0 + w0] = old.var
    source[r0:r0 + h0, c0:c0 + w0] = old.source
    mean, var, source = mean.ravel(), var.ravel(), source.ravel()
    mean[~inside], var[~inside], source[~inside] = base[~inside] + global_mean, global_var, SOURCE_GLOBAL
    # Steps 4-5 on the cells to compute again.
    flagged = np.zeros(n, dtype=bool)
    if test.any():
        outlier = _predict_cells(_block_data(pts, setup, take, anchor), centres, cell_facet.ravel(), test, layers,
                                 facets, params, rng, base, mean, var, source)
        flagged[np.flatnonzero(take)[outlier]] = True
    outliers = (removed_before & ~own & used) | flagged
    t2 = time.perf_counter()
    index = np.asarray(extracted.index, dtype=np.int64)
    stats = {'points': n, 'training': int(pts.training.sum()), 'planar_in_gp': int(setup.planar.sum()),
             'outliers_removed': int(outliers.sum()), 'layers': layers.n_layers, 'facets': facets.n_facets,
             'updated_cells': int(test.sum()), 'updated_training': int(take.sum()),
             'cells_near_new': int(near_new.sum()), 'cells_facet_changed': int((changed.ravel() & inside).sum()),
             'seconds': {'setup': t1 - t0, 'gp': t2 - t1}}
    return FacadeModel(
        facade_id=model.facade_id, building=model.building, frame=model.frame, extent=extent, layers=layers,
        facets=facets, lengthscale2_=model.lengthscale2_, global_mean_=global_mean, global_var_=global_var,
        noise_var=model.noise_var, surface=_raster(origin, cell, shape, mean, var, cell_facet, source),
        point_index=index, outlier_index=index[outliers], stats=stats, plane_extent=tuple(extracted.plane_extent),
        anchor=anchor, fitted_points=model.fitted_points, relief=model.relief)
