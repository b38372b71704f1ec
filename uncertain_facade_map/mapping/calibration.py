"""Learning the occupancy's PLSC parameters from the mapped scans alone (paper, Section IV.C).

The paper turns its surface map into occupancy by probabilistic least-squares
classification (:class:`~uncertain_facade_map.pipeline.step8_occupancy.PLSC`), whose two
parameters must be learnt from labelled data. The only labels a map may use are its own
scans': the voxels holding mapped points are occupied, the voxels the mapped rays crossed
are free (:func:`~uncertain_facade_map.voxels.reference_voxels`, as the evaluation labels a
reference campaign). Asked about those voxels, a map built on all the points would be
too sure of the occupied ones (it was fitted to them), so :func:`calibrate_occupancy`
holds some out, as R&W fit PLSC on leave-one-out predictions (Section 6.5):

1. **Sample.** At most ``max_points`` points, whole cubes of ``region`` side drawn at
   random (a seeded draw), so that the cost does not grow with the map.
2. **Labels.** The sample's hit voxels (positives) and the voxels its rays crossed
   (negatives, at most ``max_rays`` rays and ``max_negatives`` voxels, weighted). Only the
   last ``reach`` metres of each ray are traced: the fit uses only voxels a façade's band
   holds (``extraction.band_back`` behind its plane to ``band_front`` in front), where the
   surface is the model of occupancy; the air farther out is free by any reading.
3. **Hold-out.** A seeded ``holdout`` share of the hit voxels, with every point in them,
   is left out of a map built on the rest of the sample.
4. **Fit.** That map's signed distance and variance at the held-out hit voxels (each
   weighing ``1 / holdout``, so that they stand for all hit voxels) and at the crossed
   voxels, and :func:`~uncertain_facade_map.pipeline.step8_occupancy.fit_plsc`.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from ..errors import InputError
from ..params import MapParams
from ..pipeline.step7_queries import query_points
from ..pipeline.step8_occupancy import FIXED, PLSC, facade_half_depth, fit_plsc
from ..voxels import ReferenceVoxels, pack_keys, reference_voxels, voxel_index
from .facade_map import build_map

__all__ = ['calibrate_occupancy', 'scan_voxels']


def scan_voxels(xyz: np.ndarray, origins: np.ndarray, resolution: float, max_rays: int = 50_000,
                max_negatives: int = 200_000, reach: float = 5.0, seed: int = 0,
                max_positives: int | None = None) -> ReferenceVoxels:
    """The voxels a scan labels itself (its hit voxels and the voxels crossed by the last
    ``reach`` metres of its rays; :func:`~uncertain_facade_map.voxels.reference_voxels` for
    the other arguments; ``max_positives`` None: all hit voxels)."""
    ray = xyz - origins
    length = np.linalg.norm(ray, axis=1, keepdims=True)
    starts = xyz - ray * np.minimum(1.0, reach / np.maximum(length, 1e-12))
    return reference_voxels(xyz, starts, resolution, max_rays, max_negatives, seed,
                            max_positives=len(xyz) if max_positives is None else max_positives)


def _sample_regions(xyz: np.ndarray, region: float, max_points: int, rng: np.random.Generator) -> np.ndarray:
    """(K,) indices of the points in whole cubes of side ``region`` drawn at random until
    ``max_points`` are reached (all points when there are no more)."""
    if len(xyz) <= max_points:
        return np.arange(len(xyz))
    _, cube, counts = np.unique(pack_keys(voxel_index(xyz, region), 'sampling cubes'), return_inverse=True,
                                return_counts=True)
    order = rng.permutation(len(counts))
    taken = order[:int(np.searchsorted(np.cumsum(counts[order]), max_points)) + 1]
    return np.flatnonzero(np.isin(cube, taken))


def calibrate_occupancy(xyz: np.ndarray, sensor_origins: np.ndarray, params: MapParams | None = None,
                        building_id: np.ndarray | None = None, resolution: float = 0.1,
                        band_front: float | None = None, holdout: float = 0.2, max_points: int = 300_000,
                        region: float = 10.0, max_rays: int = 50_000, max_negatives: int = 200_000,
                        reach: float = 5.0, seed: int = 0, progress: Callable[[str], None] | None = None) -> PLSC:
    """Learn the occupancy's PLSC parameters from mapped points and their rays (module docstring).

    Args:
        xyz: (N, 3) mapped building points, metres, map frame.
        sensor_origins: (N, 3) the sensor origin of each point, metres, map frame.
        params: the map's parameters (default: the defaults).
        building_id: (N,) building labels, or None to cluster.
        resolution: voxel side of the labels, metres.
        band_front: how far in front of a façade plane a voxel still takes its surface,
            metres (default: ``extraction.band_front``).
        holdout: share of the hit voxels held out of the map, in (0, 1).
        max_points: at most this many points are sampled.
        region: side of the sampling cubes, metres.
        max_rays: rays traced for the free voxels.
        max_negatives: free voxels kept (weighted).
        reach: metres of each ray traced, back from its point.
        seed: seed of every draw.
        progress: called with a line of text when done.

    Returns:
        The fitted parameters; :data:`~uncertain_facade_map.pipeline.step8_occupancy.FIXED`
        when the sample holds too few labelled voxels near a façade.

    Raises:
        InputError: bad shapes, non-finite values or settings out of range.
    """
    xyz = np.asarray(xyz, dtype=np.float64)
    origins = np.asarray(sensor_origins, dtype=np.float64)
    if xyz.ndim != 2 or xyz.shape[1] != 3 or origins.shape != xyz.shape:
        raise InputError(f'calibration needs (N, 3) points and sensor origins, got {xyz.shape} and {origins.shape}')
    if not (0.0 < holdout < 1.0):
        raise InputError(f'holdout must be in (0, 1), got {holdout!r}')
    if not all(np.isfinite(x) and x > 0 for x in (resolution, region, reach)):
        raise InputError(f'resolution, region and reach must be positive, got {resolution!r}, {region!r} and {reach!r}')
    params = params or MapParams()
    band_front = params.extraction.band_front if band_front is None else float(band_front)
    rng = np.random.default_rng(seed)
    # 1. Sample whole cubes.
    pick = _sample_regions(xyz, region, max_points, rng)
    xyz, origins = xyz[pick], origins[pick]
    ids = None if building_id is None else np.asarray(building_id)[pick]
    if len(xyz) < params.extraction.min_facade_points:
        return FIXED
    # 2. The sample's own labels: hit voxels and the voxels its rays crossed.
    labels = scan_voxels(xyz, origins, resolution, max_rays, max_negatives, reach, seed)
    hit = labels.centres[labels.positive]
    free, free_weight = labels.centres[~labels.positive], labels.weight[~labels.positive]
    # 3. Hold out a share of the hit voxels with their points; map the rest.
    held = np.sort(rng.choice(len(hit), max(1, int(round(holdout * len(hit)))), replace=False))
    held_keys = pack_keys(voxel_index(hit[held], resolution))
    mapped = ~np.isin(pack_keys(voxel_index(xyz, resolution)), held_keys)
    fmap = build_map(xyz[mapped], None if ids is None else ids[mapped], origins[mapped], params)
    # 4. Ask the held-out map about the held-out hit voxels and the crossed ones.
    centres = np.vstack([hit[held], free])
    positive = np.r_[np.ones(len(held), bool), np.zeros(len(free), bool)]
    weight = np.r_[np.full(len(held), len(hit) / len(held)), free_weight]
    q = query_points(fmap.facades, centres, resolution, params.extraction.band_back, band_front)
    normals = np.array([f.frame.axes[2] for f in fmap.facades]).reshape(-1, 3)
    noise = np.where(np.isfinite(q.noise_variance), q.noise_variance, 0.0)
    fitted = fit_plsc(positive, weight, q.signed_distance, q.variance, noise,
                      facade_half_depth(q.facade, normals, resolution))
    if progress is not None:
        progress(f'occupancy calibration: scale {fitted.scale:.3g}, spread {fitted.spread:.3g} m from '
                 f'{fitted.n_positive:,} held-out hit voxels and {fitted.n_negative:,} crossed voxels '
                 f'({len(xyz):,} points sampled)')
    return fitted
