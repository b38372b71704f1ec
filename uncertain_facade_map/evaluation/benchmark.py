"""A surface benchmark for any cloud: hold points out, map the rest, score the held-out points.

The protocol (``uncertain-facade-map benchmark INPUT...``; :func:`run_benchmark`):

1. **Building points** (:func:`benchmark_input`): the points whose class field holds a
   building class (``input.building_classes``), if the cloud has the class field; else the
   points a *selector* picks, by default the walls of :func:`~.wall_points.wall_points`
   (vertical planes by RANSAC, as the independent checker ``real_check.py`` picks them);
   :data:`DEFAULT_SELECTOR` is the one line to change for another selector. Their façades
   (*partition*): the selector's walls, or, for classified points or a selector that
   returns a mask, the package's façade extraction
   (:func:`~uncertain_facade_map.pipeline.step1_facades.extract_facades`) per building.
2. **Hold-out** (:func:`hold_out`): a seeded random ``holdout`` share of the points, plus
   every point in the rectangular *occlusion patches*: on every façade at least two patch
   sides wide and 1.5 tall (robust extent: 0.5 % to 99.5 % quantiles), one
   ``patch_size`` x ``patch_size`` (2 m) patch per ``patch_spacing`` (10 m) of width,
   centred evenly along the wall and, in height, at the median height of the façade's
   points in its strip (inside the extent), so that a patch covers data where the wall
   was scanned (``real_check.py`` cuts one patch per wall longer than 8 m, at mid-width
   and 40 % of the height). Patch points are *occluded*, the others *observed*.
3. **Maps** of the remaining points: this package's (:func:`~uncertain_facade_map.mapping.facade_map.build_map`,
   asked by :func:`~uncertain_facade_map.pipeline.step7_queries.query_points`) read as
   queries read it by default (the stored points per point where they are dense, the
   rasters elsewhere) and, as its own row, by the paper's rasters alone; and two
   references built from the same points (:mod:`.references`): a local plane through the
   12 nearest mapped points (the checker's ``localplane_map.py``) and one PCA plane per
   façade of our map.
4. **Scores** of the held-out points (at most ``max_scored``, a seeded subset), per map,
   for the splits observed / occluded x planar / step: the share answered (points a map
   gives no surface are counted, not dropped), and over the answered ones the RMSE and
   mean (bias) of the signed distance (positive: the point lies outside the map's mean
   surface), the share inside the 68 % and 95 % intervals (sd = sqrt(variance + noise
   variance)), the mean negative log-likelihood (nats) and the CRPS (metres) of the
   Gaussian, the coverage at nominal levels (the calibration curve), and the PR-AUC
   (average precision) of each map's occupancy probability ``p_occupied`` at
   ``resolution`` (0.1 m): positives are the voxels holding held-out points, negatives
   the voxels 2 voxels to ``front_max`` (1 m) in front of them along their façade's
   normal (towards the sensor) that hold no building point (as ``real_check.py``). Our
   ``p_occupied`` is the query's, the solid reading Phi((r/2 - s) / sd); the references'
   is the probability that their surface crosses the voxel (:mod:`.references`).
5. **Exact truth** (simulated scenes, ``scene`` given): the same table once more, every
   scored point replaced by the true surface point at its place on its true façade
   (:meth:`~uncertain_facade_map.simulation.scene.Scene.true_depth` of its ``gt_facade``
   at its (u, v)); the distance is then the map's error, its interval the surface's alone
   (sd = sqrt(variance)); points without truth are counted.

**Depth steps.** A scored point is *at a step* (the 0.2 m around a depth step) when the
building points of its façade within ``step_radius`` (0.2 m) of it in the façade plane
(itself included, mapped and held out alike: the step is a property of the scene, not of
a map) span depths, 10th to 90th percentile, differing by more than ``step_height``
(0.1 m); with fewer than 3 such points it is planar. On simulated scenes the truth
decides instead, with the thresholds of :mod:`.surface` (a step when the true depth
``STEP_RADIUS`` (0.2 m) to the left, right, below or above differs by more than
``STEP_HEIGHT`` (0.03 m), or is missing).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from typing import Callable, Sequence

import numpy as np
from scipy.spatial import cKDTree
from scipy.stats import norm

from ..datatypes import FacadeFrame
from ..errors import InputError
from ..io.cloud import Cloud
from ..io.inputs import select_building_points
from ..mapping.facade_map import FacadeMap, build_map
from ..params import InputConfig, MapParams, QueryConfig
from ..pipeline.step1_facades import extract_facades, split_buildings
from ..voxels import pack_keys, unpack_keys, voxel_index
from .occupancy import pr_auc
from .references import Answers, FacadePlaneMap, LocalPlaneMap
from .surface import STEP_HEIGHT, STEP_RADIUS
from .wall_points import WallPick, wall_points

#: Nominal levels of the calibration curve.
LEVELS = tuple(np.round(np.r_[np.arange(0.05, 0.951, 0.05), 0.99], 2).tolist())
Z68 = float(norm.ppf(0.84))
Z95 = float(norm.ppf(0.975))
#: Sensor position assumed for a cloud without sensor origins: a vehicle-frame sweep.
DEFAULT_SENSOR = (0.0, 0.0, 1.8)
#: Fewest building points the benchmark runs on.
MIN_POINTS = 1000
#: The splits, in table order: everything, observed/occluded, planar/step and their crossings.
SPLITS = ('all', 'observed', 'observed planar', 'observed step', 'occluded', 'occluded planar', 'occluded step',
          'planar', 'step')
#: The splits with a calibration curve.
CALIBRATION_SPLITS = ('all', 'observed', 'occluded')
#: Names of the maps, in table order.
#: The row of the paper's reading alone (the façade rasters, ``query.surface`` 'raster').
RASTER_NAME = 'this package, raster (paper)'
MAP_NAMES = ('this package', RASTER_NAME, LocalPlaneMap.name, FacadePlaneMap.name)

#: Picks building points in a cloud without class field: (xyz (N, 3), sensor (3,), rng) ->
#: a WallPick (points and their walls) or an (N,) bool mask (façades then extracted).
Selector = Callable[[np.ndarray, np.ndarray, np.random.Generator], 'WallPick | np.ndarray']
#: The selector of clouds without a class field (replace it here by a building-point selector).
DEFAULT_SELECTOR: Selector = wall_points


@dataclass(frozen=True)
class BenchmarkSettings:
    """How the benchmark holds out and scores (see the module docstring).

    Attributes:
        holdout: random share of the points held out, in (0, 1).
        seed: seed of every draw (hold-out, subsets, wall RANSAC).
        patch_size: side of an occlusion patch, metres.
        patch_spacing: one patch per this much façade width, metres.
        resolution: voxel side of the occupancy figure, metres.
        front_max: the empty voxels reach this far in front of the held-out points, metres.
        step_radius: neighbourhood of the depth-step test in the façade plane, metres.
        step_height: depth spread (10th to 90th percentile) that makes a step, metres.
        max_scored: at most this many held-out points are scored (a seeded subset).
    """

    holdout: float = 0.5
    seed: int = 0
    patch_size: float = 2.0
    patch_spacing: float = 10.0
    resolution: float = 0.1
    front_max: float = 1.0
    step_radius: float = 0.2
    step_height: float = 0.1
    max_scored: int = 200_000

    def __post_init__(self) -> None:
        if not 0.0 < self.holdout < 1.0:
            raise InputError(f'the held-out share must be between 0 and 1 (exclusive), got {self.holdout}')
        for name in ('patch_size', 'patch_spacing', 'resolution', 'front_max', 'step_radius', 'step_height'):
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0):
                raise InputError(f'{name} must be a positive number, got {value}')
        if self.max_scored < 1:
            raise InputError(f'max_scored must be at least 1, got {self.max_scored}')


@dataclass(frozen=True, eq=False)
class BenchmarkInput:
    """The building points of a cloud and their façades.

    Attributes:
        xyz: (N, 3) float64 building points, metres, map frame.
        building_id: (N,) int64 building ids, or None.
        sensor_origins: (N, 3) sensor origin of each point, metres, or None.
        facade: (N,) int64 façade (partition) of each point, -1 for none.
        frames: per façade its frame, normal outwards (towards the sensor).
        source: how the points were chosen, for the report.
        n_input: number of points of the input cloud.
        map_origin: (3,) georeference of the map frame, metres.
        sensor: (3,) sensor position used by the selector, or None.
        gt_facade: (N,) int64 true scene façade of each point (simulated clouds), or None.
    """

    xyz: np.ndarray
    building_id: np.ndarray | None
    sensor_origins: np.ndarray | None
    facade: np.ndarray
    frames: list[FacadeFrame]
    source: str
    n_input: int
    map_origin: np.ndarray = field(default_factory=lambda: np.zeros(3))
    sensor: np.ndarray | None = None
    gt_facade: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.xyz.shape[0])


def partition_facades(xyz: np.ndarray, building_id: np.ndarray | None, sensor_origins: np.ndarray | None,
                      params: MapParams, seed: int) -> tuple[np.ndarray, list[FacadeFrame]]:
    """Façades of building points by the package's extraction, per building.

    Args:
        xyz: (N, 3) building points, metres, map frame.
        building_id: (N,) ids or None (buildings are then clustered, as the map does).
        sensor_origins: (N, 3) or None (turns the normals towards the sensor).
        params: the map's parameters (extraction section).
        seed: seed of the RANSAC draws.

    Returns:
        ``(facade, frames)``: (N,) int64 façade of each point (-1 for none) and the frames.
    """
    ex = params.extraction
    buildings = split_buildings(xyz, building_id, ex.building_cell)
    label = np.full(len(xyz), -1, dtype=np.int64)
    frames: list[FacadeFrame] = []
    for b in np.unique(buildings):
        index = np.flatnonzero(buildings == b)
        found, _ = extract_facades(xyz[index], ex, rng=np.random.default_rng([seed, int(b)]),
                                   sensor_origins=None if sensor_origins is None else sensor_origins[index])
        for e in found:
            label[index[e.index]] = len(frames)
            frames.append(e.frame)
    return label, frames


def benchmark_input(cloud: Cloud, config: InputConfig, params: MapParams, *, seed: int = 0,
                    sensor: Sequence[float] | None = None, selector: Selector | None = None) -> BenchmarkInput:
    """The building points of a cloud and their façades (step 1 of the module docstring).

    Args:
        cloud: the input cloud.
        config: ``class_field`` and ``building_classes`` choose the building points.
        params: the map's parameters (façade extraction).
        seed: seed of the selector's and the extraction's draws.
        sensor: (3,) sensor position for the selector, metres; default: the mean sensor
            origin, else :data:`DEFAULT_SENSOR`.
        selector: picks the building points of a cloud without class field (default
            :data:`DEFAULT_SELECTOR`).

    Raises:
        InputError: an empty cloud, NaN coordinates, no building point, fewer than
            :data:`MIN_POINTS` building points or no façade among them.
    """
    points = select_building_points(cloud, config)
    gt = cloud.get('gt_facade')
    gt = None if gt is None else gt[points.index].astype(np.int64)
    xyz, origins, ids = points.xyz, points.sensor_origins, points.building_id
    where = None if sensor is None else np.asarray(sensor, dtype=np.float64)
    if config.class_field in cloud.fields:
        source = f'class field {config.class_field!r} in {list(config.building_classes)}'
        _check_count(len(xyz), source)
        label, frames = partition_facades(xyz, ids, origins, params, seed)
    else:
        if where is None:
            where = origins.mean(axis=0) if origins is not None else np.asarray(DEFAULT_SENSOR)
        pick = (selector or DEFAULT_SELECTOR)(xyz, where, np.random.default_rng(seed))
        if isinstance(pick, WallPick):
            keep = pick.mask
            source = f'{len(pick.frames)} walls picked (no class field; sensor at {_xyz_text(where)})'
            if not pick.frames:
                raise InputError(f'no façade found: the cloud has no class field and the wall pick found no '
                                 f'vertical wall near the sensor at {_xyz_text(where)} (give its position)')
        else:
            keep = np.asarray(pick, dtype=bool)
            if keep.shape != (len(xyz),):
                raise InputError(f'the selector returned shape {keep.shape}, expected ({len(xyz)},)')
            source = 'points of the selector (no class field)'
        _check_count(int(keep.sum()), source)
        xyz, gt = xyz[keep], None if gt is None else gt[keep]
        origins = None if origins is None else origins[keep]
        ids = None if ids is None else ids[keep]
        if isinstance(pick, WallPick):
            label, frames = pick.label[keep], pick.frames
        else:
            label, frames = partition_facades(xyz, ids, origins, params, seed)
    if not frames:
        raise InputError(f'no façade found among the {len(xyz):,} building points ({source})')
    return BenchmarkInput(xyz, ids, origins, label, list(frames), source, len(cloud), points.map_origin, where, gt)


def _check_count(n: int, source: str) -> None:
    if n < MIN_POINTS:
        raise InputError(f'too few building points for the benchmark: {n:,} ({source}); it needs at least '
                         f'{MIN_POINTS:,}')


def _xyz_text(v: np.ndarray) -> str:
    return '(' + ', '.join(f'{x:.1f}' for x in v) + ')'


# ----------------------------------------------------------------------------------------
# Hold-out, steps, truth
# ----------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class HoldOut:
    """Which points are held out.

    Attributes:
        held: (N,) bool, held out (not mapped).
        occluded: (N,) bool, in an occlusion patch (always held out).
        patches: (facade, u_min, u_max, v_min, v_max) of each patch, metres, façade frame.
        facades_without_patch: façades too small for a patch.
    """

    held: np.ndarray
    occluded: np.ndarray
    patches: list[tuple[int, float, float, float, float]]
    facades_without_patch: int


def hold_out(xyz: np.ndarray, facade: np.ndarray, frames: Sequence[FacadeFrame], share: float,
             rng: np.random.Generator, patch_size: float = 2.0, patch_spacing: float = 10.0) -> HoldOut:
    """Hold out a random share of the points and occlusion patches on every façade (module docstring).

    Args:
        xyz: (N, 3) points, metres, map frame.
        facade: (N,) façade of each point (-1 for none).
        frames: the façades' frames.
        share: random share held out.
        rng: random source.
        patch_size: side of a patch, metres.
        patch_spacing: one patch per this much façade width, metres.
    """
    n = len(xyz)
    occluded = np.zeros(n, dtype=bool)
    patches: list[tuple[int, float, float, float, float]] = []
    small = 0
    for j, frame in enumerate(frames):
        index = np.flatnonzero(facade == j)
        if not len(index):
            small += 1
            continue
        uv = frame.to_local(xyz[index])[:, :2]
        (u0, v0), (u1, v1) = np.quantile(uv, [0.005, 0.995], axis=0)
        width, height = u1 - u0, v1 - v0
        if width < 2 * patch_size or height < 1.5 * patch_size:
            small += 1
            continue
        count = max(1, int(round(width / patch_spacing)))
        half = patch_size / 2
        for i in range(count):
            uc = u0 + (i + 0.5) * width / count
            strip = np.abs(uv[:, 0] - uc) < half
            if not strip.any():
                continue
            vc = float(np.clip(np.median(uv[strip, 1]), v0 + half, v1 - half))
            inside = strip & (np.abs(uv[:, 1] - vc) < half)
            occluded[index[inside]] = True
            patches.append((j, float(uc - half), float(uc + half), float(vc - half), float(vc + half)))
    held = occluded | (rng.random(n) < share)
    return HoldOut(held, occluded, patches, small)


def steps_from_points(xyz: np.ndarray, facade: np.ndarray, frames: Sequence[FacadeFrame], query: np.ndarray,
                      radius: float = 0.2, height: float = 0.1, max_neighbours: int = 64,
                      min_side: int = 2) -> np.ndarray:
    """Which points lie within ``radius`` of a depth step, judged from the points themselves.

    The depths (along the façade normal) of the façade's points within ``radius`` of a point
    in the façade plane, itself included, are split at their largest gap that leaves at
    least ``min_side`` points on either side; the point is at a step when the medians of
    the two sides differ by more than ``height``. Noise alone seldom does that (a single
    stray return cannot), a wall beside a window recess or a pillar does.

    Args:
        xyz: (N, 3) all building points, metres, map frame.
        facade: (N,) façade of each point (-1 for none).
        frames: the façades' frames.
        query: (M,) indices into ``xyz`` of the points to judge.
        radius: neighbourhood in the façade plane, metres.
        height: a difference of the two sides' median depths above this is a step, metres.
        max_neighbours: the nearest this many within ``radius`` are used.
        min_side: fewest points on either side of the split (so a point with fewer than
            ``2 * min_side`` neighbours is planar).

    Returns:
        (M,) bool, True at a step; False for points on no façade.
    """
    out = np.zeros(len(query), dtype=bool)
    qf = facade[query]
    for j, frame in enumerate(frames):
        mine = np.flatnonzero(qf == j)
        members = np.flatnonzero(facade == j)
        if not len(mine) or len(members) < 2 * min_side:
            continue
        uvd = frame.to_local(xyz[members])
        k = min(max_neighbours, len(members))
        _, idx = cKDTree(uvd[:, :2]).query(frame.to_local(xyz[query[mine]])[:, :2], k=k,
                                           distance_upper_bound=radius)
        idx = idx.reshape(len(mine), k)
        valid = idx < len(members)
        depth = np.sort(np.where(valid, uvd[np.minimum(idx, len(members) - 1), 2], np.inf), axis=1)
        count = valid.sum(axis=1)
        with np.errstate(invalid='ignore'):
            gaps = np.diff(depth, axis=1)  # gap i splits depths 0..i from i+1..count-1
        position = np.arange(k - 1)[None, :]
        allowed = (position >= min_side - 1) & (position <= count[:, None] - min_side - 1)
        split = np.argmax(np.where(allowed, gaps, -np.inf), axis=1)
        rows = np.arange(len(mine))
        last = np.maximum(count - 1, 0)

        def median(a: np.ndarray, b: np.ndarray) -> np.ndarray:
            return 0.5 * (depth[rows, (a + b) // 2] + depth[rows, (a + b + 1) // 2])

        with np.errstate(invalid='ignore'):
            differ = median(split + 1, last) - median(np.zeros_like(split), split) > height
        out[mine] = (count >= 2 * min_side) & differ
    return out


def _scene_uv(scene, gt_facade: np.ndarray, xyz: np.ndarray) -> np.ndarray:
    """(M, 2) (u, v) of each point in the frame of its true scene façade (NaN for none)."""
    uv = np.full((len(xyz), 2), np.nan)
    for f in np.unique(gt_facade[gt_facade >= 0]):
        sel = gt_facade == f
        uv[sel] = scene.facades[int(f)].frame.to_facade(xyz[sel])[:, :2]
    return uv


def truth_points(scene, gt_facade: np.ndarray, xyz: np.ndarray) -> np.ndarray:
    """(M, 3) the true surface point at each point's place on its true scene façade (NaN where none)."""
    uv = _scene_uv(scene, gt_facade, xyz)
    out = np.full((len(xyz), 3), np.nan)
    for f in np.unique(gt_facade[gt_facade >= 0]):
        sel = np.flatnonzero(gt_facade == f)
        depth = scene.true_depth(int(f), uv[sel, 0], uv[sel, 1])
        out[sel] = scene.facades[int(f)].frame.to_world(np.c_[uv[sel], depth])
    return out


def steps_from_truth(scene, gt_facade: np.ndarray, xyz: np.ndarray, radius: float = STEP_RADIUS,
                     height: float = STEP_HEIGHT) -> np.ndarray:
    """(M,) bool: the true depth ``radius`` to the left, right, below or above a point's place
    on its true façade differs from its own by more than ``height`` (or is missing); False
    for points on no scene façade."""
    uv = _scene_uv(scene, gt_facade, xyz)
    out = np.zeros(len(xyz), dtype=bool)
    for f in np.unique(gt_facade[gt_facade >= 0]):
        sel = np.flatnonzero(gt_facade == f)
        u, v = uv[sel, 0], uv[sel, 1]
        own = scene.true_depth(int(f), u, v)
        step = ~np.isfinite(own)
        for du, dv in ((radius, 0.0), (-radius, 0.0), (0.0, radius), (0.0, -radius)):
            other = scene.true_depth(int(f), u + du, v + dv)
            with np.errstate(invalid='ignore'):
                step |= ~(np.abs(other - own) <= height)
        out[sel] = step
    return out


# ----------------------------------------------------------------------------------------
# Scores
# ----------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Metrics:
    """Scores of one map on one split of the scored points.

    Attributes:
        n: points in the split.
        answered: share the map answered.
        rmse: RMSE of the signed distance over the answered points, metres.
        bias: mean signed distance, metres (positive: the points lie outside the mean surface).
        cov68: share of answered points within the 68 % interval.
        cov95: the same for 95 %.
        nll: mean negative log-likelihood of the Gaussian, nats.
        crps: mean continuous ranked probability score, metres.
        pr_auc: average precision of ``p_occupied`` on the split's voxels (NaN without
            positives or negatives).
        positives: voxels holding points of the split.
        negatives: empty voxels in front of them.
    """

    n: int
    answered: float
    rmse: float
    bias: float
    cov68: float
    cov95: float
    nll: float
    crps: float
    pr_auc: float
    positives: int
    negatives: int


@dataclass
class MapResult:
    """One map's scores.

    Attributes:
        name: the map.
        metrics: per split (:data:`SPLITS`) its metrics.
        calibration: per split of :data:`CALIBRATION_SPLITS`, the observed coverage at
            each nominal level of :data:`LEVELS`.
        build_seconds: time to build the map, s.
        query_seconds: time to answer the scored points and the voxels, s.
    """

    name: str
    metrics: dict[str, Metrics]
    calibration: dict[str, list[float]]
    build_seconds: float
    query_seconds: float


@dataclass
class BenchmarkResult:
    """The benchmark of one input against one kind of truth.

    Attributes:
        name: the input.
        against: ``held-out points`` or ``exact truth``.
        counts: numbers of points: ``input``, ``building``, ``facades``, ``mapped``,
            ``held_out``, ``occluded`` (held out in patches), ``patches``, ``scored``,
            ``without_truth`` (exact truth), ``map_facades``.
        source: how the building points were chosen.
        maps: per map its scores, in :data:`MAP_NAMES` order.
        plot: arrays for the figure: ``facade`` (M,) partition façade of each scored point,
            ``uv`` (M, 2) its place on that façade, ``residual`` (M,) our signed distance
            (NaN where not answered), ``occluded`` (M,) bool; ``patches`` list and
            ``frames``.
        settings: the settings used.
    """

    name: str
    against: str
    counts: dict[str, int]
    source: str
    maps: list[MapResult]
    plot: dict = field(default_factory=dict, repr=False)
    settings: BenchmarkSettings = field(default_factory=BenchmarkSettings)

    def map(self, name: str) -> MapResult:
        """The scores of the map ``name``."""
        return next(m for m in self.maps if m.name == name)

    def as_dict(self) -> dict:
        """The figures as plain JSON-able values (NaN as None)."""
        def clean(x):
            return None if isinstance(x, float) and not np.isfinite(x) else x

        return {
            'input': self.name, 'against': self.against, 'source': self.source, 'counts': dict(self.counts),
            'settings': {k: getattr(self.settings, k) for k in self.settings.__dataclass_fields__},
            'levels': list(LEVELS),
            'maps': [{'name': m.name, 'build_seconds': round(m.build_seconds, 3),
                      'query_seconds': round(m.query_seconds, 3),
                      'metrics': {s: {k: clean(v) for k, v in vars(x).items()} for s, x in m.metrics.items()},
                      'calibration': {s: [clean(c) for c in v] for s, v in m.calibration.items()}}
                     for m in self.maps],
        }


def gaussian_scores(residual: np.ndarray, sd: np.ndarray) -> dict[str, float]:
    """RMSE, bias, 68 % and 95 % coverage, mean NLL and CRPS of (K,) residuals with (K,) sd's."""
    if not len(residual):
        return dict.fromkeys(('rmse', 'bias', 'cov68', 'cov95', 'nll', 'crps'), float('nan'))
    z = residual / sd
    crps = sd * (z * (2 * norm.cdf(z) - 1) + 2 * norm.pdf(z) - 1 / np.sqrt(np.pi))
    return {'rmse': float(np.sqrt(np.mean(residual**2))), 'bias': float(np.mean(residual)),
            'cov68': float(np.mean(np.abs(z) <= Z68)), 'cov95': float(np.mean(np.abs(z) <= Z95)),
            'nll': float(np.mean(0.5 * np.log(2 * np.pi * sd**2) + 0.5 * z**2)), 'crps': float(np.mean(crps))}


def coverage_curve(residual: np.ndarray, sd: np.ndarray, levels: Sequence[float] = LEVELS) -> list[float]:
    """Share of (K,) residuals inside the central interval of each nominal level."""
    if not len(residual):
        return [float('nan')] * len(levels)
    z = np.abs(residual / sd)
    return [float(np.mean(z <= norm.ppf(0.5 + lv / 2))) for lv in levels]


@dataclass(frozen=True, eq=False)
class _Voxels:
    """Voxel labels of the scored points: per point its voxel and the voxels in front."""

    own: np.ndarray        # (M,) key of each point's voxel
    front: np.ndarray      # (M, S) keys in front (-1: none)
    occupied: np.ndarray   # sorted keys holding any building point
    keys: np.ndarray       # sorted union of own and front keys
    centres: np.ndarray    # (len(keys), 3) their centres, metres


def _voxels(points: np.ndarray, normals: np.ndarray, occupied_xyz: np.ndarray, resolution: float,
            front_max: float) -> _Voxels:
    own = pack_keys(voxel_index(points, resolution))
    offsets = np.arange(2 * resolution, front_max + 1e-9, resolution)
    ok = np.isfinite(normals).all(axis=1)
    front = np.full((len(points), len(offsets)), -1, dtype=np.int64)
    for i, d in enumerate(offsets):
        front[ok, i] = pack_keys(voxel_index(points[ok] + d * normals[ok], resolution))
    occupied = np.unique(pack_keys(voxel_index(occupied_xyz, resolution)))
    keys = np.unique(np.r_[own, front[front >= 0]])
    return _Voxels(own, front, occupied, keys, (unpack_keys(keys) + 0.5) * resolution)


def _split_voxels(vox: _Voxels, sel: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(positive (K,) bool, index (K,) into vox.keys)`` of the labelled voxels of the points ``sel``:
    the voxels holding them, then the empty voxels in front of them."""
    pos = np.unique(vox.own[sel])
    neg = np.unique(vox.front[sel][vox.front[sel] >= 0])
    neg = neg[~np.isin(neg, vox.occupied, assume_unique=True)]
    return (np.r_[np.ones(len(pos), bool), np.zeros(len(neg), bool)],
            np.searchsorted(vox.keys, np.r_[pos, neg]))


class PackageMap:
    """This package's map behind the references' interface (answers by its query).

    Args:
        fmap: the map.
        query: the query settings: ``surface`` 'local' (the default: the stored points read
            per point where they are dense, :mod:`~uncertain_facade_map.pipeline.step7_local_surface`)
            or 'raster' (the paper's reading alone, its own row), and ``occupancy_event``.
    """

    def __init__(self, fmap: FacadeMap, query: QueryConfig | None = None) -> None:
        self.fmap = fmap
        # The fixed occupancy formula, as the benchmark always scored it (the references have no PLSC).
        self.config = replace(query or QueryConfig(), occupancy='fixed')
        self.name = MAP_NAMES[0] if self.config.surface == 'local' else RASTER_NAME
        fmap.local_surface(self.config)  # built here (the map keeps it for the queries)

    def query(self, xyz: np.ndarray, resolution: float) -> Answers:
        """Answers for (N, 3) points by :func:`~uncertain_facade_map.pipeline.step7_queries.query_map`
        (NaN where on no façade)."""
        q = self.fmap.query(xyz, self.config, resolution)
        return Answers(q.signed_distance, q.variance, q.noise_variance, q.p_occupied)


def _score_map(m, points: np.ndarray, valid: np.ndarray, vox: _Voxels, splits: dict[str, np.ndarray],
               labelled: dict[str, tuple[np.ndarray, np.ndarray]], with_noise: bool, resolution: float,
               build_seconds: float) -> tuple[MapResult, np.ndarray]:
    started = time.perf_counter()
    a = m.query(points[valid], resolution)
    p_vox = m.query(vox.centres, resolution).p_occupied if len(vox.keys) else np.empty(0)
    seconds = time.perf_counter() - started
    n = len(points)
    s = np.full(n, np.nan)
    var = np.full(n, np.nan)
    s[valid] = a.signed_distance
    var[valid] = a.variance + (a.noise_variance if with_noise else 0.0)
    answered = np.isfinite(s) & np.isfinite(var)
    sd = np.sqrt(np.maximum(var, 1e-12))
    metrics, calibration = {}, {}
    for name, sel in splits.items():
        sel = sel & valid
        ok = sel & answered
        positive, index = labelled[name]
        n_pos, n_neg = int(positive.sum()), int((~positive).sum())
        auc = pr_auc(positive, p_vox[index]) if n_pos and n_neg else float('nan')
        metrics[name] = Metrics(n=int(sel.sum()), answered=float(ok.sum() / max(sel.sum(), 1)) if sel.any()
                                else float('nan'), pr_auc=auc, positives=n_pos, negatives=n_neg,
                                **gaussian_scores(s[ok], sd[ok]))
        if name in CALIBRATION_SPLITS:
            calibration[name] = coverage_curve(s[ok], sd[ok])
    return MapResult(m.name, metrics, calibration, build_seconds, seconds), s


def run_benchmark(data: BenchmarkInput, params: MapParams | None = None,
                  settings: BenchmarkSettings | None = None, *, scene=None, name: str = '',
                  say: Callable[[str], None] | None = None,
                  progress: Callable[[int, int], None] | None = None) -> list[BenchmarkResult]:
    """Hold out, map, score (the module docstring).

    Args:
        data: the building points and their façades (:func:`benchmark_input`).
        params: the package map's parameters.
        settings: hold-out and scoring settings.
        scene: the simulated scene the cloud comes from (needs ``data.gt_facade``), for
            the table against the exact truth; None for real data.
        name: the input's name, for the results.
        say: called with a line of progress at each stage.
        progress: called with (buildings mapped, buildings) while our map is built.

    Returns:
        The results against the held-out points, and against the exact truth if ``scene``.

    Raises:
        InputError: too few points to map, or the map finds no façade.
    """
    params = params or MapParams()
    settings = settings or BenchmarkSettings()
    say = say or (lambda _line: None)
    if scene is not None and data.gt_facade is None:
        raise InputError('the exact-truth table needs the points\' gt_facade field (a simulated cloud)')
    rng = np.random.default_rng(settings.seed)
    hold = hold_out(data.xyz, data.facade, data.frames, settings.holdout, rng, settings.patch_size,
                    settings.patch_spacing)
    mapped = ~hold.held
    _check_count(int(mapped.sum()), 'mapped points after the hold-out')
    say(f'holding out {int(hold.held.sum()):,} of {len(data):,} points ({int(hold.occluded.sum()):,} in '
        f'{len(hold.patches)} patches); mapping {int(mapped.sum()):,}')
    started = time.perf_counter()
    fmap = build_map(data.xyz[mapped], None if data.building_id is None else data.building_id[mapped],
                     None if data.sensor_origins is None else data.sensor_origins[mapped], params,
                     data.map_origin, progress=progress)
    build_seconds = {MAP_NAMES[0]: time.perf_counter() - started}
    build_seconds[RASTER_NAME] = build_seconds[MAP_NAMES[0]]
    if not fmap.facades:
        raise InputError(f'no façade found in the {int(mapped.sum()):,} mapped points')
    say(f'mapped {len(fmap.facades)} façades in {build_seconds[MAP_NAMES[0]]:.1f} s; building the references')
    started = time.perf_counter()
    if data.sensor_origins is not None:
        viewpoints = data.sensor_origins[mapped]
    else:
        viewpoints = data.sensor
    local = LocalPlaneMap(data.xyz[mapped], viewpoints)
    build_seconds[LocalPlaneMap.name] = time.perf_counter() - started
    started = time.perf_counter()
    plane = FacadePlaneMap(fmap)
    build_seconds[FacadePlaneMap.name] = time.perf_counter() - started
    maps = (PackageMap(fmap), PackageMap(fmap, QueryConfig(surface='raster')), local, plane)

    scored = np.flatnonzero(hold.held)
    if len(scored) > settings.max_scored:
        scored = np.sort(rng.choice(scored, settings.max_scored, replace=False))
    xyz = data.xyz[scored]
    occluded = hold.occluded[scored]
    step = steps_from_points(data.xyz, data.facade, data.frames, scored, settings.step_radius, settings.step_height)
    if scene is not None:  # the truth decides where there is one
        gt = data.gt_facade[scored]
        step = np.where(gt >= 0, steps_from_truth(scene, gt, xyz), step)
    splits = {'all': np.ones(len(scored), bool), 'observed': ~occluded, 'observed planar': ~occluded & ~step,
              'observed step': ~occluded & step, 'occluded': occluded, 'occluded planar': occluded & ~step,
              'occluded step': occluded & step, 'planar': ~step, 'step': step}
    normals = np.full((len(scored), 3), np.nan)
    on = data.facade[scored] >= 0
    all_normals = np.array([f.normal for f in data.frames])
    normals[on] = all_normals[data.facade[scored][on]]
    counts = {'input': data.n_input, 'building': len(data), 'facades': len(data.frames),
              'mapped': int(mapped.sum()), 'held_out': int(hold.held.sum()), 'occluded': int(hold.occluded.sum()),
              'patches': len(hold.patches), 'scored': len(scored), 'scored_step': int(step.sum()),
              'map_facades': len(fmap.facades)}
    targets = [('held-out points', xyz, True)]
    if scene is not None:
        targets.append(('exact truth', truth_points(scene, data.gt_facade[scored], xyz), False))
    results = []
    for against, points, with_noise in targets:
        valid = np.isfinite(points).all(axis=1)
        occupied = data.xyz if with_noise else np.r_[data.xyz, points[valid]]
        say(f'scoring {int(valid.sum()):,} points against {against} with {len(maps)} maps')
        vox = _voxels(np.where(valid[:, None], points, 0.0), np.where(valid[:, None], normals, np.nan),
                      occupied, settings.resolution, settings.front_max)
        labelled = {split: _split_voxels(vox, sel & valid) for split, sel in splits.items()}
        rows, residual = [], None
        for m in maps:
            row, s = _score_map(m, points, valid, vox, splits, labelled, with_noise, settings.resolution,
                                build_seconds[m.name])
            rows.append(row)
            residual = s if residual is None else residual
        frame_uv = np.full((len(scored), 2), np.nan)
        for j, frame in enumerate(data.frames):
            sel = data.facade[scored] == j
            if sel.any():
                frame_uv[sel] = frame.to_local(xyz[sel])[:, :2]
        c = dict(counts, without_truth=int((~valid).sum()))
        results.append(BenchmarkResult(
            name, against, c, data.source, rows,
            plot={'facade': data.facade[scored], 'uv': frame_uv, 'residual': residual, 'occluded': occluded,
                  'patches': hold.patches, 'frames': data.frames},
            settings=settings))
    return results


#: The splits printed by :func:`format_table` (all of :data:`SPLITS` are in the JSON).
TABLE_SPLITS = ('all', 'observed', 'observed planar', 'observed step', 'occluded', 'occluded planar', 'occluded step')


def format_table(result: BenchmarkResult) -> str:
    """The result as a text table: a heading, then per split of :data:`TABLE_SPLITS` a row per map."""
    c = result.counts
    lines = [f'{result.name}: {result.source}; {c["building"]:,} building points of {c["input"]:,} on '
             f'{c["facades"]} façades; {c["mapped"]:,} mapped ({c["map_facades"]} façades in our map), '
             f'{c["held_out"]:,} held out ({c["occluded"]:,} in {c["patches"]} occlusion patches), '
             f'{c["scored"]:,} scored ({c["scored_step"]:,} within {result.settings.step_radius:g} m of a depth step)']
    if result.against == 'exact truth':
        lines.append(f'against the exact truth (interval: surface variance only; {c["without_truth"]:,} points '
                     'without truth left out):')
    else:
        lines.append('against the held-out points (interval: surface + noise variance):')
    lines.append(f'{"split":<16} {"map":<13} {"points":>7} {"answered":>8} {"RMSE m":>7} {"bias m":>7} {"cov68":>6} '
                 f'{"cov95":>6} {"NLL":>6} {"CRPS m":>7} {"PR-AUC":>6}')

    def number(v: float, fmt: str) -> str:
        return format(v, fmt) if np.isfinite(v) else '-'

    for split in TABLE_SPLITS:
        for i, m in enumerate(result.maps):
            x = m.metrics[split]
            lines.append(f'{split if i == 0 else "":<16} {m.name:<13} {x.n:>7,} {number(x.answered, ".3f"):>8} '
                         f'{number(x.rmse, ".3f"):>7} {number(x.bias, "+.3f"):>7} {number(x.cov68, ".3f"):>6} '
                         f'{number(x.cov95, ".3f"):>6} {number(x.nll, ".2f"):>6} {number(x.crps, ".4f"):>7} '
                         f'{number(x.pr_auc, ".3f"):>6}')
    return '\n'.join(lines)
