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
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from .errors import InputError
from .facade_extraction import ExtractedFacade, ExtractionParams, extract_facades, split_buildings
from .frames import FacadeFrame
from .gp_blocks import BlockData, GPParams, _ranks, block_codes, block_size, fit_surface, optimisation_patches, optimise_lengthscales
from .layers import DepthLayers, Facets, LayerParams, find_facets, fit_layers
from .outliers import OutlierParams

#: Source of a raster cell's value.
SOURCE_GLOBAL, SOURCE_FACET_PRIOR, SOURCE_GP = 0, 1, 2


@dataclass(frozen=True)
class MapParams:
    """All modelling parameters, by stage."""

    extraction: ExtractionParams = field(default_factory=ExtractionParams)
    layers: LayerParams = field(default_factory=LayerParams)
    gp: GPParams = field(default_factory=GPParams)
    outliers: OutlierParams = field(default_factory=OutlierParams)
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


def fit_facade(extracted: ExtractedFacade, params: MapParams, rng: np.random.Generator, facade_id: int = 0,
               building: int = 0, raster_margin: float = 1.0) -> FacadeModel:
    """Fit the uncertain surface of one façade.

    Args:
        extracted: the façade's frame and its points' façade coordinates and normals.
        params: modelling parameters.
        rng: random source (EM subsample, optimisation subset, block caps).
        facade_id: index in the map.
        building: building label.
        raster_margin: the raster reaches this far beyond the points' extent, metres.

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
    extent = (float(uv[:, 0].min()), float(uv[:, 0].max()), float(uv[:, 1].min()), float(uv[:, 1].max()))
    raster_extent = (extent[0] - raster_margin, extent[1] + raster_margin,
                     extent[2] - raster_margin, extent[3] + raster_margin)
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
    planar = _thin_planar(uv, np.maximum(point_facet, 0), has_facet & ~training, origin, sizes,
                          gp.planar_per_block, rng)
    used = training | planar
    data = BlockData(uv[used], centred[used], point_facet[used], facet_sigma, facet_l2, origin)

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
                       np.asarray(extracted.index, dtype=np.int64), outlier_index, stats)


@dataclass(eq=False)
class FacadeMap:
    """Façade models of all buildings, built from building points.

    Attributes:
        params: modelling parameters.
        map_origin: (3,) georeference of the map frame, metres.
        facades: all façade models; ``facades[i].facade_id == i``.
        points: per building label, the building's points (N, 3), metres, map frame.
        sensor_origins: per building label, (N, 3) sensor origins or None.
    """

    params: MapParams = field(default_factory=MapParams)
    map_origin: np.ndarray = field(default_factory=lambda: np.zeros(3))
    facades: list[FacadeModel] = field(default_factory=list)
    points: dict[int, np.ndarray] = field(default_factory=dict)
    sensor_origins: dict[int, np.ndarray | None] = field(default_factory=dict)

    def add_points(self, xyz: np.ndarray, building_id: np.ndarray | None = None,
                   sensor_origins: np.ndarray | None = None,
                   progress: Callable[[int, int], None] | None = None) -> list[int]:
        """Add building points and refit the buildings that received them.

        Args:
            xyz: (N, 3) building points, metres, map frame.
            building_id: (N,) building labels, or None to cluster.
            sensor_origins: (N, 3) sensor origins, or None.
            progress: called with (buildings refitted, buildings to refit) after each one.

        Returns:
            The labels of the buildings refitted.

        Raises:
            InputError: empty input, wrong shapes or non-finite coordinates.
        """
        xyz = np.asarray(xyz, dtype=np.float64)
        if xyz.ndim != 2 or xyz.shape[1] != 3:
            raise InputError(f'points must be an (N, 3) array, got shape {xyz.shape}')
        if not len(xyz):
            raise InputError('no building points to map')
        if not np.isfinite(xyz).all():
            raise InputError(f'{int((~np.isfinite(xyz)).any(axis=1).sum())} points have NaN or infinite coordinates')
        labels = split_buildings(xyz, building_id, self.params.extraction.building_cell)
        changed = []
        for label in np.unique(labels):
            sel = labels == label
            b = int(label)
            old = self.points.get(b)
            self.points[b] = xyz[sel] if old is None else np.vstack([old, xyz[sel]])
            so = None if sensor_origins is None else np.asarray(sensor_origins, dtype=np.float64)[sel]
            old_so = self.sensor_origins.get(b)
            self.sensor_origins[b] = so if old is None else (None if so is None or old_so is None
                                                             else np.vstack([old_so, so]))
            changed.append(b)
        fitted: dict[int, list[FacadeModel]] = {}
        for done, b in enumerate(changed, 1):
            fitted[b] = fit_building(self.points[b], self.sensor_origins.get(b), self.params, b)
            if progress is not None:
                progress(done, len(changed))
        kept = [f for f in self.facades if f.building not in fitted]
        new = [m for b in changed for m in fitted[b]]
        self.facades = [_with_id(f, i) for i, f in enumerate(kept + new)]
        return changed

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


def fit_building(points: np.ndarray, sensor_origins: np.ndarray | None, params: MapParams,
                 building: int) -> list[FacadeModel]:
    """Extract the façades of one building and fit each one's surface.

    Args:
        points: (N, 3) the building's points, metres, map frame.
        sensor_origins: (N, 3) their sensor origins, or None.
        params: modelling parameters.
        building: building label (also seeds the random draws).

    Returns:
        The building's façade models (ids to be set by the caller).
    """
    rng = np.random.default_rng([params.seed, building])
    extracted, _ = extract_facades(points, params.extraction, sensor_origins=sensor_origins, rng=rng)
    return [fit_facade(e, params, rng, building=building) for e in extracted]


def _with_id(model: FacadeModel, facade_id: int) -> FacadeModel:
    if model.facade_id == facade_id:
        return model
    from dataclasses import replace

    return replace(model, facade_id=facade_id)


def build_map(xyz: np.ndarray, building_id: np.ndarray | None = None, sensor_origins: np.ndarray | None = None,
              params: MapParams | None = None, map_origin: np.ndarray | None = None,
              progress: Callable[[int, int], None] | None = None) -> FacadeMap:
    """Build a map from building points in one go (see :meth:`FacadeMap.add_points`)."""
    fmap = FacadeMap(params or MapParams(), np.zeros(3) if map_origin is None else np.asarray(map_origin, float))
    fmap.add_points(xyz, building_id, sensor_origins, progress)
    return fmap
