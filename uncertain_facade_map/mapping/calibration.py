"""Learning the occupancy's PLSC parameters from the mapped scans alone (paper, Section IV.C).

The paper turns its surface map into occupancy by probabilistic least-squares
classification (:class:`~uncertain_facade_map.pipeline.step8_occupancy.PLSC`), whose two
parameters must be learnt from labelled data. The only labels a map may use are its own
scans': the voxels holding mapped points are occupied, the voxels the mapped rays crossed
are free (:func:`~uncertain_facade_map.voxels.reference_voxels`, as the evaluation labels a
reference campaign). Asked about those voxels, a map built on all the points would be
too sure of the occupied ones (it was fitted to them), so the calibration holds some
out, as R&W fit PLSC on leave-one-out predictions (Section 6.5):

1. **Sample.** At most ``max_points`` points, whole cubes of ``region`` side drawn at
   random (a seeded draw), so that the cost does not grow with the map.
2. **Labels.** The sample's hit voxels (positives) and the voxels its rays crossed
   (negatives, at most ``max_rays`` rays and ``max_negatives`` voxels, weighted). Only the
   last ``reach`` metres of each ray are traced: the fit uses only voxels a façade's band
   holds (``extraction.band_back`` behind its plane to ``band_front`` in front), where the
   surface is the model of occupancy; the air farther out is free by any reading.
3. **Hold-out.** A seeded ``holdout`` share of the hit voxels, with every point in them,
   is left out of a map built on the rest of the sample (:func:`hold_out` draws steps 1
   and 3; the map builder, :meth:`FacadeMap.calibrate_occupancy
   <uncertain_facade_map.mapping.facade_map.FacadeMap.calibrate_occupancy>`, maps the rest
   and calls :func:`fit_occupancy`: this module does not build maps).
4. **Fit.** That map's signed distance and variance at the held-out hit voxels (each
   weighing ``1 / holdout``, so that they stand for all hit voxels) and at the crossed
   voxels, and :func:`~uncertain_facade_map.pipeline.step8_occupancy.fit_plsc`.

:func:`fit_free_space` learns, with the same sample and hold-out, the weight of the
free-space extension (beyond the paper): how much each mapped ray through a voxel lowers
its occupancy (:func:`~uncertain_facade_map.pipeline.step8_occupancy.carve`).

:func:`scan_disagreement` measures, beyond the paper, how much scans disagree where they
see the same surface (pose and registration noise between scans, which no within-scan
fit sees) beyond what the queries' local reading predicts for a point of another scan: a
map keeps its running sums and adds their excess to every answer's variance
(``FacadeMap.registration_var_``, :func:`registration_variance`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np

from ..datatypes import FacadeModel
from ..errors import InputError
from ..params import MapParams
from ..pipeline.step4_gp_blocks import in_sorted
from ..pipeline.step7_local_surface import LocalSurface
from ..pipeline.step7_queries import PointQuery, query_points
from ..pipeline.step8_occupancy import FIT_BAND, PLSC, facade_half_depth, fit_carving, fit_plsc
from ..voxels import (
    ReferenceVoxels,
    near_keys,
    pack_keys,
    ray_crossings,
    reference_voxels,
    unpack_keys,
    voxel_index,
    wrapped_keys,
)
from ._storage_kernel import stored_in_order

__all__ = ['HeldOut', 'Settings', 'fit_free_space', 'fit_occupancy', 'hold_out', 'registration_variance',
           'scan_disagreement', 'scan_voxels', 'surface_terms']


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


@dataclass(frozen=True)
class Settings:
    """How the calibration samples, holds out and labels (module docstring).

    Attributes:
        band_front: how far in front of a façade plane a voxel still takes its surface,
            metres (None: the map's ``extraction.band_front``).
        holdout: share of the hit voxels held out of the map, in (0, 1).
        max_points: at most this many points are sampled.
        region: side of the sampling cubes, metres.
        max_rays: rays traced for the free voxels.
        max_negatives: free voxels kept (weighted).
        reach: metres of each ray traced, back from its point.

    Raises:
        InputError: a holdout outside (0, 1), or a region or reach that is not positive.
    """

    band_front: float | None = None
    holdout: float = 0.2
    max_points: int = 200_000
    region: float = 10.0
    max_rays: int = 50_000
    max_negatives: int = 200_000
    reach: float = 5.0

    def __post_init__(self) -> None:
        if not (0.0 < self.holdout < 1.0):
            raise InputError(f'holdout must be in (0, 1), got {self.holdout!r}')
        if not all(np.isfinite(x) and x > 0 for x in (self.region, self.reach)):
            raise InputError(f'region and reach must be positive, got {self.region!r} and {self.reach!r}')


def _checked(xyz: np.ndarray, origins: np.ndarray, resolution: float) -> tuple[np.ndarray, np.ndarray]:
    xyz = np.asarray(xyz, dtype=np.float64)
    origins = np.asarray(origins, dtype=np.float64)
    if xyz.ndim != 2 or xyz.shape[1] != 3 or origins.shape != xyz.shape:
        raise InputError(f'calibration needs (N, 3) points and sensor origins, got {xyz.shape} and {origins.shape}')
    if not (np.isfinite(resolution) and resolution > 0):
        raise InputError(f'resolution must be positive, got {resolution!r}')
    return xyz, origins


@dataclass(frozen=True, eq=False)
class HeldOut:
    """Steps 1 and 3 of the module docstring: the sample and what is held out of it (the
    map of the rest is the caller's: :meth:`~uncertain_facade_map.mapping.facade_map.FacadeMap.calibrate_occupancy`
    builds it).

    Attributes:
        xyz, origins, ids: the sampled points (M, 3), their sensor origins (M, 3) and
            building labels (M,) or None.
        hit_keys: (H,) sorted keys of the voxels holding sampled points.
        held_keys: (h,) sorted keys of the hit voxels held out.
        mapped: (M,) bool, the points outside the held-out voxels (those to map).
        n_points: number of points the sample was drawn from.
        resolution: voxel side of the keys, metres.
    """

    xyz: np.ndarray
    origins: np.ndarray
    ids: np.ndarray | None
    hit_keys: np.ndarray
    held_keys: np.ndarray
    mapped: np.ndarray
    n_points: int
    resolution: float


#: The free-space evidence takes at most about this many of a map's stored rays (every
#: :func:`ray_step`-th, in calibration and use alike), so that its cost stays bounded.
RAY_BUDGET = 600_000


def ray_step(n_stored: int) -> int:
    """Every how many stored rays the free-space evidence takes, for a map of ``n_stored``
    stored points: 1 (all) up to :data:`RAY_BUDGET`, then enough to keep to about that."""
    return max(1, -(-int(n_stored) // RAY_BUDGET))


def hold_out(xyz: np.ndarray, sensor_origins: np.ndarray, building_id: np.ndarray | None, params: MapParams,
             resolution: float, settings: Settings = Settings(), seed: int = 0) -> HeldOut | None:
    """Sample whole cubes of (N, 3) mapped points (metres, map frame) with their (N, 3) sensor
    origins and (N,) building labels (or None), and hold out a share of their hit voxels
    (module docstring, steps 1 and 3; seeded by ``seed``). None: too few points to map.

    Raises:
        InputError: bad shapes, non-finite values or a resolution that is not positive.
    """
    xyz, origins = _checked(xyz, sensor_origins, resolution)
    rng = np.random.default_rng(seed)
    pick = _sample_regions(xyz, settings.region, settings.max_points, rng)
    n_points = len(xyz)
    xyz, origins = xyz[pick], origins[pick]
    ids = None if building_id is None else np.asarray(building_id)[pick]
    if len(xyz) < params.extraction.min_facade_points:
        return None
    point_keys = pack_keys(voxel_index(xyz, resolution))
    hit_keys = np.unique(point_keys)
    held_keys = np.sort(rng.choice(hit_keys, max(1, int(round(settings.holdout * len(hit_keys)))), replace=False))
    mapped = ~np.isin(point_keys, held_keys)
    return HeldOut(xyz, origins, ids, hit_keys, held_keys, mapped, n_points, float(resolution))


def surface_terms(facades: Sequence[FacadeModel], answers: PointQuery, resolution: float
                  ) -> tuple[np.ndarray, np.ndarray]:
    """What the surface reading takes besides a query's signed distance and variance:
    ``(noise, half)``, each (N,): the answers' noise variance (0 where no façade holds the
    point, m^2) and the voxel's half extent along its façade's normal (metres,
    :func:`~uncertain_facade_map.pipeline.step8_occupancy.facade_half_depth`)."""
    noise = np.where(np.isfinite(answers.noise_variance), answers.noise_variance, 0.0)
    normals = np.array([f.frame.axes[2] for f in facades]).reshape(-1, 3)
    return noise, facade_half_depth(answers.facade, normals, resolution)


def _ask(h: HeldOut, facades: Sequence[FacadeModel], keys: np.ndarray, band_back: float, band_front: float
         ) -> tuple[PointQuery, np.ndarray, np.ndarray]:
    """The held-out map's answers (its ``facades``, the raster reading) at the voxels of
    ``keys``: ``(query, noise, half)`` (:func:`surface_terms`)."""
    centres = (unpack_keys(keys) + 0.5) * h.resolution
    q = query_points(facades, centres, h.resolution, band_back, band_front)
    return (q, *surface_terms(facades, q, h.resolution))


def _crossed(xyz: np.ndarray, origins: np.ndarray, resolution: float, max_rays: int, max_negatives: int,
             reach: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """``(keys, weight)``, each (F,): the voxels the last ``reach`` metres of the rays of
    (M, 3) points crossed, holding none of them (:func:`scan_voxels`), and their weights."""
    labels = scan_voxels(xyz, origins, resolution, max_rays, max_negatives, reach, seed)
    free = ~labels.positive
    return pack_keys(voxel_index(labels.centres[free], resolution)), labels.weight[free]


def fit_occupancy(h: HeldOut, facades: Sequence[FacadeModel], params: MapParams, settings: Settings = Settings(),
                  seed: int = 0, progress: Callable[[str], None] | None = None) -> PLSC:
    """Learn the occupancy's PLSC parameters (module docstring, steps 2 and 4) from a hold-out
    and the façades of the map of its mapped points.

    Args:
        h: the sample and its hold-out (:func:`hold_out`).
        facades: the façade models of the map of ``h.xyz[h.mapped]``.
        params: that map's parameters (its bands).
        settings: the labels' settings.
        seed: seed of the rays' draw.
        progress: called with a line of text when done.

    Returns:
        The fitted parameters; :data:`~uncertain_facade_map.pipeline.step8_occupancy.FIXED`
        when the sample holds too few labelled voxels near a façade.
    """
    ex = params.extraction
    band_front = ex.band_front if settings.band_front is None else float(settings.band_front)
    # 2. The sample's own labels: the held-out hit voxels and the voxels its rays crossed.
    free, free_weight = _crossed(h.xyz, h.origins, h.resolution, settings.max_rays, settings.max_negatives,
                                 settings.reach, seed)
    # 4. Ask the held-out map about them (each held-out hit voxel stands for 1 / holdout of all).
    keys = np.r_[h.held_keys, free]
    positive = np.r_[np.ones(len(h.held_keys), bool), np.zeros(len(free), bool)]
    weight = np.r_[np.full(len(h.held_keys), len(h.hit_keys) / len(h.held_keys)), free_weight]
    q, noise, half = _ask(h, facades, keys, ex.band_back, band_front)
    fitted = fit_plsc(positive, weight, q.signed_distance, q.variance, noise, half)
    if progress is not None:
        progress(f'occupancy calibration: scale {fitted.scale:.3g}, spread {fitted.spread:.3g} m from '
                 f'{fitted.n_positive:,} held-out hit voxels and {fitted.n_negative:,} crossed voxels '
                 f'({len(h.xyz):,} points sampled)')
    return fitted


def fit_free_space(h: HeldOut, facades: Sequence[FacadeModel], plsc: PLSC, params: MapParams,
                   settings: Settings = Settings(), seed: int = 0) -> float:
    """Learn the free-space extension's weight (:func:`~uncertain_facade_map.pipeline.step8_occupancy.carve`;
    beyond the paper) from the mapped points alone, with the same sample and hold-out as
    :func:`fit_occupancy` (same arguments; ``plsc``: the occupancy it carves).

    The labels come from the held-out points only, the evidence from the others: the
    held-out hit voxels are occupied and the voxels the held-out points' rays crossed
    (holding no sampled point) free; each is asked of the map of the other points, and
    counted against the rays of the other points through it (every :func:`ray_step`-th
    ray, as the map uses them; :func:`~uncertain_facade_map.voxels.ray_crossings`). So a voxel counts as free only
    by rays the carving did not see, as in the evaluation, where the reference's rays
    are not the mapped ones.

    Returns:
        The weight in log-odds per ray (0 when nothing can be learnt).
    """
    if h.mapped.all():
        return 0.0
    ex = params.extraction
    band_front = ex.band_front if settings.band_front is None else float(settings.band_front)
    resolution = h.resolution
    held = ~h.mapped
    free, free_weight = _crossed(h.xyz[held], h.origins[held], resolution, settings.max_rays, settings.max_negatives,
                                 settings.reach, seed)
    keep = ~np.isin(free, h.hit_keys)
    free, free_weight = free[keep], free_weight[keep]
    keys = np.r_[h.held_keys, free]
    positive = np.r_[np.ones(len(h.held_keys), bool), np.zeros(len(free), bool)]
    weight = np.r_[np.ones(len(h.held_keys)), free_weight]
    q, noise, half = _ask(h, facades, keys, ex.band_back, band_front)
    near = np.isfinite(q.signed_distance) & (np.abs(q.signed_distance) <= FIT_BAND)
    p = plsc.surface(q.signed_distance, q.variance, noise, half)
    step = ray_step(h.n_points)  # as the whole map takes them
    crossings = ray_crossings(h.xyz[h.mapped][::step], h.origins[h.mapped][::step], resolution, keys, settings.reach)
    return fit_carving(positive[near], weight[near], p[near], crossings[near])


#: Scan disagreement: a sampled point counts where its other-scan neighbours lie within
#: :data:`_REACH` (metres), spread over a surface (middle eigenvalue at least :data:`_SPREAD`
#: times the largest: a patch, not one or two scan lines) no thicker than :data:`_THICK` (rms
#: along the normal, metres: a wall both scans see, not foliage), and the point lies among
#: them (its offset from their centroid within their plane at most :data:`_INSIDE` times
#: their largest standard deviation: read, not extrapolated). A plane through neighbours along one or two scan lines,
#: or read beyond their end, misses a later scan by more than its variance says whatever the
#: poses: on the simulated street streamed live (no registration error), points with a spread
#: under 0.2 or an offset over 1.5 deviations missed by 5.7-11 cm rms against 3-4 cm
#: predicted, and the map learnt a scan-to-scan std of 2.8 cm from them (0 with these tests).
#: The bounds are absolute, not relative to the neighbourhood's extent, which shrinks as the
#: map grows denser.
_REACH = 1.0
_SPREAD = 0.3
_THICK = 0.1
_INSIDE = 1.0
#: Residuals beyond this many robust standard deviations (1.4826 x the median absolute
#: residual) are left out of a second moment (edges, the other side of a thin wall); for
#: Gaussian residuals the moment loses 0.1 %.
_TRIM = 4.0
#: Cells (metres) by which the points near a sample are picked before the KD-tree: the
#: cells of the samples and their neighbours hold every point within :data:`_REACH`.
_CROP_CELL = _REACH
#: The sample is drawn in clusters, up to this many points in each of random cells of
#: :data:`_CLUSTER_CELL` metres, so that the points near it, the KD-tree's, stay few
#: however dense the stored points are.
_PER_CLUSTER = 8
_CLUSTER_CELL = 1.0
#: The other scans' local reading learns its calibration on at most this many of their
#: points near the sample (leave-one-out), so that an update's cost does not grow with
#: the map's density.
_CALIBRATION_POINTS = 2000
#: Scans compared per call at most (a seeded draw among its scans): each costs a local
#: reading of the other scans' points near its sample (about 35 ms on the street), and a
#: live update holds ~18 scans of 0.1 s; the running sums gather the rest over updates.
MAX_SCANS = 4


def _cell_keys(xyz: np.ndarray, side: float = _CROP_CELL) -> np.ndarray:
    return wrapped_keys(xyz, side)


def _near_cells(sample: np.ndarray) -> np.ndarray:
    """Sorted keys of the crop cells of (S, 3) points and of their 26 neighbours."""
    return near_keys(sample, _CROP_CELL)


def _clustered_sample(index: np.ndarray, xyz: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    """About ``n`` of the points ``index`` (into (N, 3) ``xyz``), in clusters: random cells
    of side :data:`_CLUSTER_CELL`, the same random share of the points of each (about
    :data:`_PER_CLUSTER` a cell on average)."""
    if len(index) <= n:
        return index
    if len(index) > 64 * n:  # a large scan: its clusters drawn from a uniform subsample
        index = np.sort(rng.choice(index, 64 * n, replace=False))
    order = rng.permutation(len(index))
    keys = _cell_keys(xyz[index[order]], _CLUSTER_CELL)
    by_cell = np.argsort(keys, kind='stable')  # stable: random order within a cell
    sk = keys[by_cell]
    first = np.r_[True, sk[1:] != sk[:-1]]
    group = np.cumsum(first) - 1
    rank = np.arange(len(sk)) - np.flatnonzero(first)[group]
    # Cells in a random order, each giving the same share of its points (about
    # _PER_CLUSTER on average, rounded at random): every point has the same odds, however
    # the cells cut the surface.
    counts = np.bincount(group)
    share = max(_PER_CLUSTER / counts.mean(), n / len(index))  # few cells: more of each
    quota = np.floor(counts * share + rng.random(len(counts))).astype(np.int64)
    cells = rng.permutation(len(counts))
    cells = cells[:int(np.searchsorted(np.cumsum(quota[cells]), n)) + 1]  # cells enough for n points
    chosen = np.zeros(len(counts), bool)
    chosen[cells] = True
    take = (rank < quota[group]) & chosen[group]
    return index[order[by_cell[take]]]  # a few more than n: cut in key order, the sample would lean


def _trimmed_moments(s: np.ndarray, var: np.ndarray) -> tuple[float, float]:
    """Robust means of (n,) residuals' squares and of their (n,) predicted variances, m^2,
    over the same points: those with |s| <= :data:`_TRIM` x 1.4826 x median |s| and
    var <= :data:`_TRIM`^2 x median var (edges, the other side of a thin wall, a plane
    fitted across a corner)."""
    keep = (np.abs(s) <= _TRIM * 1.4826 * np.median(np.abs(s))) & (var <= _TRIM ** 2 * np.median(var))
    return float(np.mean(s[keep] ** 2)), float(np.mean(var[keep]))


def scans_to_compare(scan: np.ndarray, n_earlier: int, max_points: int, rng: np.random.Generator
                     ) -> tuple[np.ndarray, int]:
    """The scans :func:`scan_disagreement` compares (at most :data:`MAX_SCANS` of the (N,)
    labels ``scan``, a seeded draw; none when there is nothing to compare them with) and the
    points it samples of each."""
    labels = np.unique(scan)
    if max_points <= 0 or (len(labels) < 2 and not n_earlier):
        return labels[:0], 0
    if len(labels) > MAX_SCANS:
        labels = np.sort(rng.choice(labels, MAX_SCANS, replace=False))
    return labels, max(1, int(max_points) // len(labels))


def scan_disagreement(xyz: np.ndarray, scan: np.ndarray, earlier: np.ndarray, k: int = 12,
                      max_points: int = 2000, rng: np.random.Generator | None = None,
                      inner: float = 0.2, store_voxel: float = 0.0, store_per_voxel: int = 0, *,
                      store_spacing: float = 0.0, scans: np.ndarray | None = None, per_scan: int | None = None) -> np.ndarray:
    """How far scans lie off each other's surface beyond what the map's reading predicts, as sums.

    For each scan of the new points (at most :data:`MAX_SCANS`, a seeded draw), up to
    ``max_points / scans`` of its points (a seeded
    draw, in clusters: :func:`_clustered_sample`) are read, where the other scans saw the
    same wall, from the *other* scans' points (``earlier`` and the new points of the other
    scans) as the queries read the map where it holds dense data: the local reading
    (:class:`~uncertain_facade_map.pipeline.step7_local_surface.LocalSurface`, ``k``
    neighbours picked in 3-D, its variances scaled by a factor learnt leave-one-out on those
    other-scan points, as the map's is on its stored points). Only points the local reading
    answers alone count (a stored point within ``inner``), where the other scans' ``k``
    nearest lie within :data:`_REACH` on a wall-like patch (:data:`_SPREAD`, :data:`_THICK`).

    - cross: the square of the point's signed distance ``s`` to the reading;
    - within: what the reading predicts for it, ``variance + noise_variance``.

    The reading's calibrated variances hold the other scans' own scatter and whatever of
    their offsets from each other the leave-one-out residuals saw; a later scan's points
    miss it by that and by their own offset. So E[s^2] - E[variance + noise] is the
    variance a later scan's points need besides the reading's (pose and registration
    noise). Both means are over the same points, trimmed (:func:`_trimmed_moments`):
    median-based, so that edges and outliers do not dominate.

    Args:
        xyz: (N, 3) new points, metres, map frame.
        scan: (N,) int scan label of each new point.
        earlier: (M, 3) points of earlier scans (the map's stored points), metres, map frame.
        k: neighbours of each local plane (``query.local_neighbours``).
        max_points: points sampled in all.
        rng: the draw (default: seeded 0).
        inner: a point counts where a stored point lies within this (``query.local_inner``),
            metres.
        store_voxel, store_per_voxel, store_spacing: the map's storage rule
            (``update.store_voxel``, ``update.store_per_voxel``, ``update.store_spacing``):
            the other scans' points are read as the map would store them
            (:func:`~._storage_kernel.stored_in_order`), ``earlier`` first, then the new
            points in arrival order (a car lidar's scans repeat the same walls: most of
            their points are never stored, and reading them all cost as much as mapping).
            0: all are read.

        scans, per_scan: compare these scans only, ``per_scan`` points of each (a part of a
            comparison drawn by :func:`scans_to_compare`, done in pieces); None: draw them here.

    Returns:
        (3,) float: [n, n * E[s^2], n * E[variance + noise]] with n the points that counted
        (m^2 for the sums); zeros when no scan overlaps another.
    """
    rng = np.random.default_rng(0) if rng is None else rng
    out = np.zeros(3)
    if scans is None or per_scan is None:
        labels, per_scan = scans_to_compare(scan, len(earlier), max_points, rng)
    else:
        labels = np.asarray(scans)
    if not len(labels):
        return out
    picks = []
    for s in labels:
        own_idx = np.flatnonzero(scan == s)
        picks.append(_clustered_sample(own_idx, xyz, per_scan, rng))
    # The points near any sample, once (the stored points may be many).
    sample = xyz[np.concatenate(picks)]
    cells = _near_cells(sample)  # the sample's cells and their neighbours
    lo, hi = sample.min(axis=0) - 2 * _CROP_CELL, sample.max(axis=0) + 2 * _CROP_CELL
    near_new = np.flatnonzero(np.all((xyz >= lo) & (xyz <= hi), axis=1))
    new_keys = _cell_keys(xyz[near_new])
    keep = in_sorted(new_keys, cells)  # cells: sorted, unique
    near_new, new_keys = near_new[keep], new_keys[keep]
    near_old = earlier[np.all((earlier >= lo) & (earlier <= hi), axis=1)] if len(earlier) else np.empty((0, 3))
    old_keys = _cell_keys(near_old)
    keep = in_sorted(old_keys, cells)
    near_old, old_keys = near_old[keep], old_keys[keep]
    for s, pick in zip(labels, picks):
        mine = _near_cells(xyz[pick])
        in_cells = in_sorted(new_keys, mine)
        others = np.vstack([near_old[in_sorted(old_keys, mine)], xyz[near_new[in_cells & (scan[near_new] != s)]]])
        if store_voxel > 0 and store_per_voxel > 0 and len(others):
            others = others[stored_in_order(others, store_voxel, store_per_voxel, store_spacing)]
        if len(others) <= k:
            continue
        p = xyz[pick]
        # The other scans read as the queries read the map: one façade (labels and normal
        # only turn the sign; only s^2 counts), calibrated leave-one-out on these points.
        surface = LocalSurface(others, np.zeros(len(others), np.int32), np.array([[0.0, 0.0, 1.0]]), k, inner,
                               inner)
        d_o, i_o = surface.tree.query(p, k)
        nb = others[i_o]  # (S, k, 3)
        centre = nb.mean(axis=1)
        dev = nb - centre[:, None]
        w, axes = np.linalg.eigh(np.einsum('ski,skj->sij', dev, dev))  # k x the scatter's eigenvalues
        off = p - centre
        in_plane = np.sum(np.square(off), axis=1) - np.square(np.einsum('si,si->s', off, axes[:, :, 0]))
        inside = in_plane <= _INSIDE ** 2 * w[:, 2] / k
        ok = (d_o[:, -1] <= _REACH) & (w[:, 1] >= _SPREAD * w[:, 2]) & (w[:, 0] <= k * _THICK ** 2) & inside
        if ok.sum() < 10:
            continue
        surface.calibrate(max_points=_CALIBRATION_POINTS)
        reading = surface.read(p[ok])
        alone = reading.weight >= 1.0
        if alone.sum() < 10:
            continue
        cross, within = _trimmed_moments(reading.signed_distance[alone],
                                         reading.variance[alone] + reading.noise_variance[alone])
        n = int(alone.sum())
        out += [n, n * cross, n * within]
    return out


def registration_variance(sums: np.ndarray, max_std: float, min_points: int = 100) -> float:
    """The registration variance (m^2) of running :func:`scan_disagreement` sums: the excess
    of the cross-scan second moment over the within-scan one, 0 below ``min_points``
    compared points or when negative, at most ``max_std``^2."""
    n, cross, within = (float(x) for x in np.asarray(sums, dtype=np.float64).reshape(3))
    if n < min_points:
        return 0.0
    return float(min(max(0.0, (cross - within) / n), max_std ** 2))
