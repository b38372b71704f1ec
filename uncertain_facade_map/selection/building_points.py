"""The building points of a cloud without classes: no ground, tall, thin, straight and vertical.

:func:`select_building_points` takes every point of a lidar scan (or of several, with
their sensor origins) in any frame with z up, and keeps the points of façades:

1. **Ground** by Patchwork++ (Lee, Lim and Myung, RA-L 2022; ``pypatchworkpp`` from PyPI,
   the authors' C++ library): it fits ground planes in the bins of a concentric zone model
   around the sensor and tests them for uprightness, elevation and flatness. The points
   are cut into scans: by their sensor origins in square cells of ``scan_cell`` when
   known; else one scan, or tiles of ``max_range`` when the cloud is wider than twice
   that. Each scan is centred on its sensor (the mean origin, the given origin, or the
   points' median) in x and y, and ``sensor_height`` above the ground found around it in
   z (the median of the lowest point of each 1 m cell within 20 m), so that clouds far
   from their frame's origin (city frames) and sensors of any height look to Patchwork++
   like the scans it was made for. A fresh estimator per scan: Patchwork++ adapts its
   thresholds from scan to scan, and a selection must not depend on what came before.
2. **Ground height**: the mean z of the ground points in cells of ``ground_cell``; a
   place without ground takes the nearest cell's.
3. **Wall windows**: a window is an occupied cell of side ``cell`` with ``window_radius``
   cells around it, holding the non-ground points of its cells. A vertical plane is fitted
   to them (a line through their x, y by PCA, three passes, each after the first on the
   points within ``band`` of the last line). The window is a wall if its band points are
   at least ``min_window_points`` and ``min_share`` of its points, lie within
   ``max_thickness`` of the plane (RMS; tree crowns are thicker), extend at least
   ``min_window_length`` along it (poles are narrower), reach ``min_structure_height``
   above the ground (cars and hedges are lower) and extend ``min_extent`` up it (cables).
   The ground here is the lower of the ground height and the window's lowest band point,
   so a wall with no ground around it is measured from its foot.

   A car's lidar sees a wall only as high as its vertical field of view reaches: a
   Velodyne HDL-64E 1.73 m up with its top beam at +2 degrees sees a house 10 m away up
   to 2.1 m, below ``min_structure_height``. So, when the points have sensor origins, the
   selection finds the top of the field of view: the line (height over range from the
   origins, of the points at least 3 m away in x, y) that the highest point of each degree
   of azimuth follows, by quantile regression, if the sensor sees almost nothing above it,
   a quarter of those points lie on it and the points within ``fov_margin`` below it lie in
   at least 90 distinct degrees of azimuth (a spinning lidar's top beam hits walls all
   around; the top of one tall object alone, or a profile scanner's zenith, is no such
   edge; :func:`_field_of_view`). A window with a band point within
   ``fov_margin`` below that top is **cut off by the field of view**: the sensor saw it as
   high as it could see at that distance, so it may be a wall however low it looks. It
   passes ``min_structure_height`` if its plane passes at least ``min_cut_distance`` from
   the sensor (the mean origin of those top points): a van parked along the road reaches
   the top of the view too, but its side lies along the road, near the sensor's path,
   while a house front stands behind its front yard; and it needs half of
   ``min_extent`` (hedges and cars hide the lower part of such a wall). A car or a hedge
   lies below what the sensor could see above it and stays judged by
   ``min_structure_height``. Sensors that see whole walls (profile scanners, the
   Argoverse 2 car's lidars with top beams at +15 and +25 degrees) show no such top, or
   see their walls taller than ``min_structure_height`` before its top: the rule changes
   nothing for them. Without sensor origins only ``min_structure_height`` applies.
4. **Wall segments**: wall windows whose planes differ by less than ``segment_angle``,
   whose centre cells are within ``link_distance`` and whose centroids lie in each other's
   band are linked; a connected set shorter than ``min_segment_length`` along its mean
   direction is dropped (the straight pieces of a tree crown's shell, signs).
5. **Building points**: the non-ground points within ``band`` of the plane of a wall
   window of a kept segment.

A cloud in which Patchwork++ finds less than ``min_ground_share`` of ground is no raw scan
but building points cut already (a wall picker's output, a segmented file): it is kept
whole (:attr:`Selection.applied` is False), so the selection never thins a cloud that
needs none.

Every call says why it dropped what it dropped (:attr:`Selection.dropped_by`: each
non-ground point not kept, under the first rule of :data:`DROP_RULES` its own window
failed), and :func:`selection_warning` turns a cloud that kept less than
``warn_kept_share`` of its non-ground points into a one-line warning naming the rule that
dropped most of them, for the node and the command line to log.

On the Argoverse sweeps of ``../shared/data/real/`` it keeps 96-99.5 % of the wall points
an independent RANSAC wall picker finds, and 81-82 % of what it keeps lies within 0.4 m of
them (85-94 % within the picker's 40 m); see docs/selection.md for the figures and the command that prints them (:mod:`.evaluation`). On the simulated
``residential`` street scanned by the ``hdl64`` sensor, sweep by sweep, it keeps 82-88 %
of the wall points and 98-100 % of what it keeps is building (without the field-of-view
rule: under 3 % of the wall points; ``python -m uncertain_facade_map.selection.evaluation
--simulated``).

The loops over cells and windows are compiled (:mod:`._kernels`, numba), summing as the
numpy version did, so that the selection is the same bit for bit; Patchwork++ is about a
third of the time left (``make bench``, stage ``select``: the time per 100,000 points).
"""

from __future__ import annotations

import contextlib
import math
import os
import sys
import threading
from dataclasses import dataclass, field
from typing import Iterator

import numpy as np
from scipy.optimize import linprog
from scipy.sparse import coo_matrix, csr_matrix, hstack, identity
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from ..errors import InputError
from ..params import SelectionConfig
from . import _kernels

__all__ = ['DROP_RULES', 'Selection', 'select_building_points', 'selection_warning']

#: Radius (m) around a scan's centre in which its ground level is taken, and the cell (m)
#: whose lowest point is one sample of it.
_LEVEL_RADIUS = 20.0
_LEVEL_CELL = 1.0
#: Plane fits per window: the first on all of its points, the others on its band points.
_PASSES = 3
#: Patchwork++ prints to the C++ standard output when built; one scan is built at a time.
_STDOUT_LOCK = threading.Lock()
#: The top of the field of view is sought among the points at least this far (m, in x, y)
#: from their origins (closer, a centimetre of noise or quantisation turns the elevation).
_FOV_MIN_RANGE = 3.0
#: Its line (height above the origin against range) is the quantile regression of the
#: highest point of each degree of azimuth, at the first of these levels whose line passes
#: the tests below. Those points are the top beam's returns where it hits something, lower
#: beams' where it does not (open road: at the start of the simulated residential street two
#: thirds of the degrees, where only the first level fits the beam), and a few strays above it
#: (4 % of the degrees tilt the first level's line through them; the second fits the beam).
_FOV_QUANTILES = (0.95, 0.85)
#: It is a top only if at most this share of those highest points lie above it by more than
#: ``fov_margin`` (a sensor sees nothing above its top beam but a few strays) ...
_FOV_MAX_ABOVE = 0.05
#: ... and at least this share lie within ``fov_margin`` of it (a beam's returns line up;
#: the tops of walls do not: 3-6 % on the Argoverse sweeps, 33-87 % on car lidars) ...
_FOV_MIN_ON_LINE = 0.25
#: ... and its height at the origin lies within this many metres of the origin's (the beams'
#: apex: a lidar's upper lasers sit some centimetres above its frame, a base frame given as
#: the origin a metre or two below it) ...
_FOV_MAX_APEX = 3.0
#: ... and the points within ``fov_margin`` below it lie in at least this many distinct
#: degrees of azimuth around their origins: a spinning lidar's top beam hits walls all
#: around, while the top of one tall object alone is no field of view.
_FOV_MIN_AZIMUTH = 90

#: The rules of :attr:`Selection.dropped_by`, in the order a dropped point is attributed.
DROP_RULES = (
    'selection.min_window_points', 'selection.min_share', 'selection.max_thickness', 'selection.min_window_length',
    'selection.min_structure_height', 'selection.min_extent', 'selection.min_segment_length', 'selection.band',
)


@dataclass(frozen=True, eq=False)
class Selection:
    """What :func:`select_building_points` found in a cloud.

    Attributes:
        mask: (N,) bool, True for building points.
        ground: (N,) bool, True for the points Patchwork++ took as ground.
        applied: False when the cloud had less than ``min_ground_share`` of ground and was
            kept whole as building points cut already (``mask`` all True).
        walls: number of wall segments kept (0 when not applied).
        dropped_by: the non-ground points not kept, by the rule that dropped them: full
            parameter names in :data:`DROP_RULES` order, each with its count (all of them,
            zeros too, when applied; empty when not). A point is counted under the first
            rule its own window (the one centred on its cell) failed; a point whose window
            is a wall of a kept segment but that lies outside every kept band is counted
            under ``selection.band``. The counts add up to ``non_ground - kept``.
        fov_top: top of the sensor's vertical field of view found in the cloud, degrees of
            elevation from the sensor origins; None without origins, or when no top is seen
            all around (then only ``min_structure_height`` judges the height of a wall).
    """

    mask: np.ndarray
    ground: np.ndarray
    applied: bool
    walls: int
    dropped_by: dict[str, int] = field(default_factory=dict)
    fov_top: float | None = None

    @property
    def ground_share(self) -> float:
        """Share of the points taken as ground (0 for an empty cloud)."""
        return float(self.ground.mean()) if len(self.ground) else 0.0

    @property
    def non_ground(self) -> int:
        """Number of points not taken as ground."""
        return int(len(self.ground) - np.count_nonzero(self.ground))

    @property
    def kept(self) -> int:
        """Number of points kept as building points."""
        return int(np.count_nonzero(self.mask))


def select_building_points(xyz: np.ndarray, sensor_origins: np.ndarray | None = None,
                           params: SelectionConfig | None = None) -> Selection:
    """The building points of an unclassified cloud (see the module docstring for the steps).

    Args:
        xyz: (N, 3) float points, metres, any frame with z up (one scan or several).
        sensor_origins: the sensor position at each point, (N, 3), or one for all, (3,),
            metres, same frame; None if unknown (the scan is centred on the points' median).
        params: the selection's parameters (``mode`` is not read here); defaults if None.

    Returns:
        The selection: the (N,) mask of building points and what was found.

    Raises:
        InputError: ``xyz`` not of shape (N, 3), ``sensor_origins`` of neither shape,
            non-numeric values, NaN or infinite coordinates (the message says how many).
    """
    params = params or SelectionConfig()
    xyz = _points(xyz, 'points')
    n = len(xyz)
    origins = None
    if sensor_origins is not None:
        origins = _points(sensor_origins, 'sensor origins', single=True)
        if origins.ndim == 2 and len(origins) != n:
            raise InputError(f'{len(origins)} sensor origins for {n} points')
    if n == 0:
        empty = np.zeros(0, dtype=bool)
        return Selection(empty, empty.copy(), True, 0, dict.fromkeys(DROP_RULES, 0))
    # Local coordinates: a city frame's 1e6 m would cost the float32 Patchwork++ its millimetres.
    offset = np.round(np.median(xyz, axis=0))
    local = xyz - offset
    if origins is not None:
        origins = origins - offset
    ground, level = _ground(local, origins, params)
    if ground.sum() < params.min_ground_share * n:
        return Selection(np.ones(n, dtype=bool), ground, False, 0)
    view = _field_of_view(local, origins, params)
    rest = np.flatnonzero(~ground)
    mask = np.zeros(n, dtype=bool)
    walls = 0
    dropped = np.zeros(len(DROP_RULES), dtype=np.int64)
    if len(rest):
        keep, walls, reason = _walls(local[rest], local[ground], level, None if view is None else view.subset(rest),
                                     params)
        mask[rest[keep]] = True
        dropped = np.bincount(reason[~keep], minlength=len(DROP_RULES))
    return Selection(mask, ground, True, walls, dict(zip(DROP_RULES, (int(k) for k in dropped))),
                     None if view is None else math.degrees(view.top))


def selection_warning(selection: Selection, params: SelectionConfig | None = None) -> str | None:
    """A one-line warning when a selection kept less than ``warn_kept_share`` of the
    non-ground points, naming the rule that dropped most of them; None otherwise.

    Args:
        selection: what :func:`select_building_points` found in one cloud.
        params: the parameters it was called with (their ``warn_kept_share`` and the value
            of the rule named); defaults if None.

    Returns:
        E.g. ``'the building selection kept 292 of 61,204 non-ground points (0.5 %, below
        selection.warn_kept_share 5 %); most were dropped by selection.min_structure_height
        = 3 m (58,310 points)'``, or None (enough kept, nothing to select from, the cloud
        kept whole, or ``warn_kept_share`` 0).
    """
    params = params or SelectionConfig()
    total = selection.non_ground
    if not selection.applied or total == 0 or selection.kept >= params.warn_kept_share * total:
        return None
    line = (f'the building selection kept {selection.kept:,} of {total:,} non-ground points '
            f'({100 * selection.kept / total:.1f} %, below selection.warn_kept_share '
            f'{100 * params.warn_kept_share:g} %)')
    if not selection.dropped_by or not any(selection.dropped_by.values()):
        return line
    rule, count = max(selection.dropped_by.items(), key=lambda item: item[1])
    name = rule.split('.', 1)[1]
    unit = SelectionConfig.__dataclass_fields__[name].metadata['param'].unit
    value = f'{getattr(params, name):g}' + (f' {unit}' if unit else '')
    return f'{line}; most were dropped by {rule} = {value} ({count:,} points)'


def _points(values: np.ndarray, what: str, single: bool = False) -> np.ndarray:
    """``values`` as finite float64 (N, 3) (or (3,) when ``single``)."""
    arr = np.asarray(values)
    shape_ok = (arr.ndim == 2 and arr.shape[1] == 3) or (single and arr.shape == (3,))
    if not shape_ok:
        raise InputError(f'{what} must be of shape (N, 3){" or (3,)" if single else ""}, got {arr.shape}')
    if arr.dtype.kind not in 'iuf':
        raise InputError(f'{what} must be numbers, got type {arr.dtype}')
    arr = arr.astype(np.float64, copy=False)
    if np.isfinite(arr).all():
        return arr
    bad = ~np.isfinite(arr).all(axis=-1)
    if bad.any():
        raise InputError(f'{int(np.sum(bad))} of {bad.size} {what} have NaN or infinite coordinates')
    return arr


# ----------------------------------------------------------------------------------------
# 1.-2. Ground
# ----------------------------------------------------------------------------------------
def _scans(xyz: np.ndarray, origins: np.ndarray | None, params: SelectionConfig) -> Iterator[tuple[np.ndarray,
                                                                                                   np.ndarray]]:
    """(indices, centre x, y) of each scan of a cloud (see the module docstring, step 1)."""
    n = len(xyz)
    if origins is not None and origins.ndim == 1:
        yield np.arange(n), origins[:2]
        return
    if origins is not None:
        keys = np.floor(origins[:, :2] / params.scan_cell).astype(np.int64)
        if (keys == keys[0]).all():  # one cell: the usual sweep
            yield np.arange(n), np.array(_kernels.column_means(origins[:, :2]))
            return
    elif max(np.ptp(xyz[:, 0]), np.ptp(xyz[:, 1])) > 2 * params.max_range:
        keys = np.floor(xyz[:, :2] / params.max_range).astype(np.int64)
    else:
        yield np.arange(n), np.median(xyz[:, :2], axis=0)
        return
    low = np.array([keys[:, 0].min(), keys[:, 1].min()])
    rel = keys - low
    codes, order = _grouped(rel[:, 0] * (int(rel[:, 1].max()) + 1) + rel[:, 1])
    for idx in np.split(order, np.flatnonzero(np.diff(codes)) + 1):
        centre = origins[idx, :2].mean(axis=0) if origins is not None else np.median(xyz[idx, :2], axis=0)
        yield idx, centre


def _grouped(codes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(M,) non-negative int64 ``codes`` sorted, and the (M,) order that sorts them, by
    ascending index among equal codes (a stable argsort)."""
    n = len(codes)
    if n and (int(codes.max()) + 1) * n < 2 ** 62:  # one sort of code * n + index: faster than a stable argsort
        return np.divmod(np.sort(codes * n + np.arange(n)), n)
    order = np.argsort(codes, kind='stable')  # a cloud thousands of kilometres wide
    return codes[order], order


def _cell_index(xy: np.ndarray, cell: float) -> tuple[np.ndarray, np.ndarray]:
    """The occupied square cells of (M, 2) places: their (C, 2) int64 keys (sorted) and
    each place's cell index (M,)."""
    keys = np.floor(xy / cell).astype(np.int64)
    low = np.array([keys[:, 0].min(), keys[:, 1].min()])  # (axis=0 is slow on 2 columns)
    rel = keys - low
    width = int(rel[:, 1].max()) + 1
    codes, first, inverse = np.unique(rel[:, 0] * width + rel[:, 1], return_index=True, return_inverse=True)
    return keys[first], inverse.ravel()


def _ground_level(xyz: np.ndarray, centre: np.ndarray) -> float:
    """Ground level around ``centre`` (x, y): the median of the lowest point of each 1 m
    cell within 20 m (of all cells if fewer than 10 points are that close)."""
    low = _kernels.lowest_per_cell(xyz, float(centre[0]), float(centre[1]), _LEVEL_RADIUS, _LEVEL_CELL, 10)
    if not len(low):  # wider than the dense grid: numpy's way
        near = np.sum((xyz[:, :2] - centre) ** 2, axis=1) <= _LEVEL_RADIUS ** 2
        pts = xyz[near] if near.sum() >= 10 else xyz
        _, cell = _cell_index(pts[:, :2], _LEVEL_CELL)
        low = np.full(cell.max() + 1, np.inf)
        np.minimum.at(low, cell, pts[:, 2])
    return float(np.median(low))


@contextlib.contextmanager
def _quiet_stdout() -> Iterator[None]:
    """Send what C++ code prints on file descriptor 1 to the null device meanwhile."""
    with _STDOUT_LOCK:
        sys.stdout.flush()
        saved = os.dup(1)
        try:
            with open(os.devnull, 'wb') as null:
                os.dup2(null.fileno(), 1)
            yield
        finally:
            os.dup2(saved, 1)
            os.close(saved)


def _patchwork(points: np.ndarray, params: SelectionConfig) -> np.ndarray:
    """(M,) bool ground mask of one scan's (M, 3) points, sensor at the origin."""
    try:
        import pypatchworkpp
    except ImportError as err:
        raise InputError('selecting building points in a cloud without classes needs pypatchworkpp '
                         '(pip install pypatchworkpp), or set selection.mode: off') from err
    config = pypatchworkpp.Parameters()
    config.sensor_height = params.sensor_height
    config.max_range = params.max_range
    config.enable_RNR = False  # reflected-noise removal needs intensities
    config.verbose = False
    with _quiet_stdout():
        estimator = pypatchworkpp.patchworkpp(config)
    estimator.estimateGround(np.ascontiguousarray(points, dtype=np.float32))
    ground = np.zeros(len(points), dtype=bool)
    ground[np.asarray(estimator.getGroundIndices(), dtype=np.int64)] = True
    return ground


def _ground(xyz: np.ndarray, origins: np.ndarray | None, params: SelectionConfig) -> tuple[np.ndarray, float]:
    """(N,) ground mask, and the median ground level of the scans (the fallback height)."""
    ground = np.zeros(len(xyz), dtype=bool)
    levels = []
    for idx, centre in _scans(xyz, origins, params):
        pts = xyz if len(idx) == len(xyz) else xyz[idx]  # one scan: idx is arange(N)
        level = _ground_level(pts, centre)
        levels.append(level)
        ground[idx] = _patchwork(pts - np.array([centre[0], centre[1], level + params.sensor_height]), params)
    return ground, float(np.median(levels))


def _ground_height(xy: np.ndarray, ground: np.ndarray, fallback: float, cell: float) -> np.ndarray:
    """Ground height (M,) at (M, 2) places: mean z of the ground points in their ``cell``,
    else in the nearest cell with ground; ``fallback`` everywhere without ground points."""
    if not len(ground):
        return np.full(len(xy), fallback)
    keys, height = _kernels.mean_height_per_cell(ground, cell)  # keys in (x, y) order, as _cell_index's
    if not len(keys):  # wider than the dense grid: numpy's way
        keys, inverse = _cell_index(ground[:, :2], cell)
        height = np.bincount(inverse, ground[:, 2]) / np.bincount(inverse)
    _, nearest = cKDTree((keys + 0.5) * cell).query(xy)
    return height[nearest]


@dataclass(frozen=True, eq=False)
class _View:
    """The top of the sensor's vertical field of view, as the points show it.

    Attributes:
        top: its elevation from the sensor origins, radians.
        at_top: (N,) bool, the points seen within ``fov_margin`` below it.
        origin: (N, 2) x, y of each point's sensor origin, metres.
    """

    top: float
    at_top: np.ndarray
    origin: np.ndarray

    def subset(self, idx: np.ndarray) -> _View:
        """The same view for the points ``idx``."""
        return _View(self.top, self.at_top[idx], self.origin[idx])


def _field_of_view(xyz: np.ndarray, origins: np.ndarray | None, params: SelectionConfig) -> _View | None:
    """The top of the sensor's vertical field of view, if the cloud shows one (see the
    module docstring, step 3).

    The top beam is a cone whose apex sits near, not at, the origin (the HDL-64E's upper
    lasers about 0.2 m above its frame): seen from the origin its returns rise from 2.1
    degrees at 60 m to 2.9 at 12 m. So the top is a line, the height ``apex + r tan(top)``
    above the origin at range r, fitted to the highest point of each degree of azimuth by
    quantile regression (:data:`_FOV_QUANTILES`), not the highest elevation seen: a few
    returns above the top beam, or a base frame as the origin, do not move it.

    Args:
        xyz: (N, 3) points, metres, z up.
        origins: (N, 3) or (3,) their sensor origins, same frame; None if unknown.
        params: ``fov_margin`` is used.

    Returns:
        The view; None without origins, with ``fov_margin`` 0, or when no top is seen all
        around.
    """
    if origins is None or params.fov_margin <= 0:
        return None
    origins = np.broadcast_to(origins, xyz.shape)
    rel = xyz - origins
    reach = np.hypot(rel[:, 0], rel[:, 1])
    far = np.flatnonzero(reach >= _FOV_MIN_RANGE)
    if len(far) < _FOV_MIN_AZIMUTH:
        return None
    elevation = np.arctan2(rel[far, 2], reach[far])
    azimuth = np.floor(np.degrees(np.arctan2(rel[far, 1], rel[far, 0]))).astype(np.int64) % 360
    # The highest point of each degree of azimuth (the first, if several are as high).
    top_of = np.full(360, -np.inf)
    np.maximum.at(top_of, azimuth, elevation)
    tops = np.flatnonzero(elevation == top_of[azimuth])
    highest = far[tops[np.unique(azimuth[tops], return_index=True)[1]]]
    if len(highest) < _FOV_MIN_AZIMUTH:
        return None
    r = np.maximum(reach, 1e-6)
    elevation = np.arctan2(rel[:, 2], r)
    margin = math.radians(params.fov_margin)
    for level in _FOV_QUANTILES:
        fit = _quantile_line(reach[highest], rel[highest, 2], level)
        if fit is None or abs(fit[0]) > _FOV_MAX_APEX:
            continue
        apex, slope = fit
        below_top = elevation - np.arctan2(apex + slope * r, r)  # radians, at each point's range
        off = below_top[highest]
        if np.mean(off > margin) > _FOV_MAX_ABOVE or np.mean(np.abs(off) <= margin) < _FOV_MIN_ON_LINE:
            continue  # not a line the sensor sees nothing above: the tops of walls, not a beam
        at_top = below_top >= -margin
        near = far[at_top[far]]
        degrees = np.floor(np.degrees(np.arctan2(rel[near, 1], rel[near, 0]))).astype(np.int64) % 360
        if np.count_nonzero(np.bincount(degrees, minlength=360)) >= _FOV_MIN_AZIMUTH:
            return _View(math.atan(slope), at_top, origins[:, :2])
    return None


def _quantile_line(x: np.ndarray, y: np.ndarray, q: float) -> tuple[float, float] | None:
    """(a, b) of the line ``a + b x`` that minimises the quantile (check) loss at level
    ``q`` of (n,) samples y at (n,) x: a linear programme (Koenker and Bassett 1978), solved
    by HiGHS; None if it fails."""
    n = len(x)
    cost = np.concatenate([[0.0, 0.0], np.full(n, q), np.full(n, 1.0 - q)])
    eye = identity(n, format='csr')
    a_eq = hstack([csr_matrix(np.column_stack([np.ones(n), x])), eye, -eye], format='csc')
    bounds = [(None, None)] * 2 + [(0.0, None)] * (2 * n)
    res = linprog(cost, A_eq=a_eq, b_eq=y, bounds=bounds, method='highs')
    if not res.success:
        return None
    return float(res.x[0]), float(res.x[1])


# ----------------------------------------------------------------------------------------
# 3.-5. Walls
# ----------------------------------------------------------------------------------------
class _Cells:
    """Occupied square cells: their sorted int64 codes, keys and centres, each point's cell,
    and the points of each cell (``start``, ``members``: see :mod:`._kernels`)."""

    def __init__(self, xy: np.ndarray, cell: float, margin: int):
        keys = np.floor(xy / cell).astype(np.int64)
        self.low = np.array([keys[:, 0].min(), keys[:, 1].min()]) - margin  # (axis=0 is slow on 2 columns)
        self.width = int(keys[:, 1].max() - self.low[1]) + margin + 1
        codes = self.code(keys)
        sorted_codes, self.members = _grouped(codes)
        self.codes, self.start, self.of_point = _kernels.group_cells(sorted_codes, self.members)
        rel_x, rel_y = np.divmod(self.codes, self.width)
        self.keys = np.stack([rel_x + self.low[0], rel_y + self.low[1]], axis=1)
        self.centres = (self.keys + 0.5) * cell

    def code(self, keys: np.ndarray) -> np.ndarray:
        rel = keys - self.low
        return rel[:, 0] * self.width + rel[:, 1]

    def neighbours(self, offsets: np.ndarray, rows: np.ndarray | None = None) -> np.ndarray:
        """(R, K) index of the cell at each of the (K, 2) ``offsets`` (dx, dy) from each of the
        cells ``rows`` (ascending; all if None), -1 for an empty one (offsets up to the margin)."""
        rows = np.arange(len(self.codes)) if rows is None else rows
        return _kernels.neighbours(self.codes, rows, offsets[:, 0] * self.width + offsets[:, 1])


def _walls(q: np.ndarray, ground: np.ndarray, level: float, view: _View | None,
           params: SelectionConfig) -> tuple[np.ndarray, int, np.ndarray]:
    """Which of the non-ground points ``q`` (M, 3) lie on walls.

    Args:
        q: (M, 3) non-ground points, metres, local frame.
        ground: (G, 3) ground points, same frame.
        level: fallback ground height, metres.
        view: the field of view, for the points ``q``; None if none was found.
        params: the selection's parameters.

    Returns:
        ``(keep, segments, reason)``: (M,) bool wall points, the number of wall segments
        kept, and (M,) int the index in :data:`DROP_RULES` of the rule each point's own
        window failed (``selection.band`` when it failed none; meaningless where kept).
    """
    link = math.ceil(params.link_distance / params.cell)
    cells = _Cells(q[:, :2], params.cell, max(params.window_radius, link) + 1)
    n_cells = len(cells.codes)
    # Each window holds the points of the cells within window_radius of its own (the loops in
    # _kernels), read in cell order.
    nbr = cells.neighbours(_kernels.window_offsets(params.window_radius))
    order = cells.members
    xyz = q[order]
    xy = np.ascontiguousarray(xyz[:, :2])
    fit = (cells.centres, cells.start, nbr)
    mean = normal = np.zeros((n_cells, 2))
    for k in range(_PASSES):
        total, mean, sxx, syy, sxy = _kernels.moments(xy, *fit, mean, normal, params.band, k == 0)
        angle = 0.5 * np.arctan2(2 * sxy, sxx - syy)  # of the line's direction
        normal = np.stack([-np.sin(angle), np.cos(angle)], axis=1)
    if view is not None:
        at_top, origin = view.at_top[order], view.origin[order]
    else:
        at_top, origin = np.zeros(len(q), dtype=bool), np.zeros((len(q), 2))
    points, count, sq, top, bottom, n_top, origin_sum = _kernels.band_stats(
        xyz, *fit, mean, normal, params.band, at_top, origin)
    thickness = np.sqrt(sq / np.maximum(count, 1))
    spread = 0.5 * (sxx + syy) + np.sqrt(0.25 * (sxx - syy) ** 2 + sxy ** 2)  # along the line
    length = np.sqrt(12.0 * spread)
    foot = np.minimum(_ground_height(cells.centres, ground, level, params.ground_cell), bottom)
    tall = top - foot >= params.min_structure_height
    cut = np.zeros(n_cells, dtype=bool)
    if view is not None:
        # Cut off by the field of view: seen as high as the sensor could see it. A wall if its
        # plane passes far enough from the sensor: a van's side, along the road, passes near.
        rows = np.flatnonzero(n_top)
        origin = origin_sum[rows] / n_top[rows, None]
        plane = np.abs(np.einsum('ij,ij->i', cells.centres[rows] + mean[rows] - origin, normal[rows]))
        cut[rows] = plane >= params.min_cut_distance
    # A wall cut off at the top shows its lower part only where hedges and cars leave it.
    extent = np.where(cut & ~tall, 0.5 * params.min_extent, params.min_extent)
    checks = (count >= params.min_window_points, count >= params.min_share * points,
              thickness <= params.max_thickness, length >= params.min_window_length, tall | cut,
              top - bottom >= extent)
    failed = np.full(n_cells, len(checks))  # index of the first check failed (in DROP_RULES order)
    for k in range(len(checks) - 1, -1, -1):
        failed[~checks[k]] = k
    wall = failed == len(checks)
    kept, segments, short = _segments(wall, cells, cells.centres + mean, normal, link, params)
    failed[short] = DROP_RULES.index('selection.min_segment_length')
    failed[kept] = DROP_RULES.index('selection.band')
    keep = np.zeros(len(q), dtype=bool)
    keep[order] = _kernels.band_points(xy, *fit, mean, normal, params.band, np.flatnonzero(kept))
    return keep, segments, failed[cells.of_point]


def _segments(wall: np.ndarray, cells: _Cells, centroid: np.ndarray, normal: np.ndarray, link: int,
              params: SelectionConfig) -> tuple[np.ndarray, int, np.ndarray]:
    """The wall windows in segments of at least ``min_segment_length``, the number of those,
    and (C,) bool the wall windows dropped for their segment's length."""
    idx = np.flatnonzero(wall)
    if not len(idx):
        return wall, 0, np.zeros_like(wall)
    cos_max = math.cos(math.radians(params.segment_angle))
    reach2 = (params.link_distance / params.cell) ** 2
    offsets = np.array([(dx, dy) for dx in range(0, link + 1) for dy in range(-link, link + 1)
                        if not (dx == 0 and dy <= 0) and dx * dx + dy * dy <= reach2], dtype=np.int64).reshape(-1, 2)
    a, b = _kernels.links(idx, wall, cells.neighbours(offsets, idx), np.ascontiguousarray(centroid), normal, cos_max,
                          params.band)
    a, b = np.r_[idx, a], np.r_[idx, b]
    n_cells = len(wall)
    graph = coo_matrix((np.ones(len(a)), (a, b)), shape=(n_cells, n_cells))
    _, label = connected_components(graph, directed=False)
    _, segment = np.unique(label[idx], return_inverse=True)
    segment = segment.ravel()
    n_seg = int(segment.max()) + 1
    # Mean direction of each segment's lines (angles doubled: a line has no sign).
    doubled = 2 * np.arctan2(normal[idx, 1], normal[idx, 0])
    mean = 0.5 * np.arctan2(np.bincount(segment, np.sin(doubled), n_seg), np.bincount(segment, np.cos(doubled), n_seg))
    along = -np.sin(mean)[segment] * cells.centres[idx, 0] + np.cos(mean)[segment] * cells.centres[idx, 1]
    lo = np.full(n_seg, np.inf)
    hi = np.full(n_seg, -np.inf)
    np.minimum.at(lo, segment, along)
    np.maximum.at(hi, segment, along)
    long = (hi - lo + params.cell) >= params.min_segment_length
    out = np.zeros_like(wall)
    out[idx[long[segment]]] = True
    return out, int(long.sum()), wall & ~out
