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
   ``min_window_length`` along it (poles are narrower) and ``min_extent`` up it (cables),
   and reach ``min_structure_height`` above the ground (cars are lower). The ground here
   is the lower of the ground height and the window's lowest band point, so a wall with
   no ground around it is measured from its foot.
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

On the Argoverse sweeps of ``../shared/data/real/`` it keeps 96-99.5 % of the wall points
an independent RANSAC wall picker finds, and 81-82 % of what it keeps lies within 0.4 m of
them (85-94 % within the picker's 40 m); see docs/selection.md for the
figures and the command that prints them (:mod:`.evaluation`).
"""

from __future__ import annotations

import contextlib
import math
import os
import sys
import threading
from dataclasses import dataclass
from typing import Iterator

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from ..errors import InputError
from ..params import SelectionConfig

__all__ = ['Selection', 'select_building_points']

#: Radius (m) around a scan's centre in which its ground level is taken, and the cell (m)
#: whose lowest point is one sample of it.
_LEVEL_RADIUS = 20.0
_LEVEL_CELL = 1.0
#: Plane fits per window: the first on all of its points, the others on its band points.
_PASSES = 3
#: Patchwork++ prints to the C++ standard output when built; one scan is built at a time.
_STDOUT_LOCK = threading.Lock()


@dataclass(frozen=True, eq=False)
class Selection:
    """What :func:`select_building_points` found in a cloud.

    Attributes:
        mask: (N,) bool, True for building points.
        ground: (N,) bool, True for the points Patchwork++ took as ground.
        applied: False when the cloud had less than ``min_ground_share`` of ground and was
            kept whole as building points cut already (``mask`` all True).
        walls: number of wall segments kept (0 when not applied).
    """

    mask: np.ndarray
    ground: np.ndarray
    applied: bool
    walls: int

    @property
    def ground_share(self) -> float:
        """Share of the points taken as ground (0 for an empty cloud)."""
        return float(self.ground.mean()) if len(self.ground) else 0.0


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
        return Selection(empty, empty.copy(), True, 0)
    # Local coordinates: a city frame's 1e6 m would cost the float32 Patchwork++ its millimetres.
    offset = np.round(np.median(xyz, axis=0))
    local = xyz - offset
    if origins is not None:
        origins = origins - offset
    ground, level = _ground(local, origins, params)
    if ground.sum() < params.min_ground_share * n:
        return Selection(np.ones(n, dtype=bool), ground, False, 0)
    rest = np.flatnonzero(~ground)
    mask = np.zeros(n, dtype=bool)
    walls = 0
    if len(rest):
        keep, walls = _walls(local[rest], local[ground], level, params)
        mask[rest[keep]] = True
    return Selection(mask, ground, True, walls)


def _points(values: np.ndarray, what: str, single: bool = False) -> np.ndarray:
    """``values`` as finite float64 (N, 3) (or (3,) when ``single``)."""
    arr = np.asarray(values)
    shape_ok = (arr.ndim == 2 and arr.shape[1] == 3) or (single and arr.shape == (3,))
    if not shape_ok:
        raise InputError(f'{what} must be of shape (N, 3){" or (3,)" if single else ""}, got {arr.shape}')
    if arr.dtype.kind not in 'iuf':
        raise InputError(f'{what} must be numbers, got type {arr.dtype}')
    arr = arr.astype(np.float64)
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
    elif np.ptp(xyz[:, :2], axis=0).max() > 2 * params.max_range:
        keys = np.floor(xyz[:, :2] / params.max_range).astype(np.int64)
    else:
        yield np.arange(n), np.median(xyz[:, :2], axis=0)
        return
    _, group = _cell_index(keys, 1.0)
    order = np.argsort(group, kind='stable')
    bounds = np.flatnonzero(np.diff(group[order])) + 1
    for idx in np.split(order, bounds):
        centre = origins[idx, :2].mean(axis=0) if origins is not None else np.median(xyz[idx, :2], axis=0)
        yield idx, centre


def _cell_index(xy: np.ndarray, cell: float) -> tuple[np.ndarray, np.ndarray]:
    """The occupied square cells of (M, 2) places: their (C, 2) int64 keys (sorted) and
    each place's cell index (M,)."""
    keys = np.floor(xy / cell).astype(np.int64)
    low = keys.min(axis=0)
    rel = keys - low
    width = int(rel[:, 1].max()) + 1
    codes, first, inverse = np.unique(rel[:, 0] * width + rel[:, 1], return_index=True, return_inverse=True)
    return keys[first], inverse.ravel()


def _ground_level(xyz: np.ndarray, centre: np.ndarray) -> float:
    """Ground level around ``centre`` (x, y): the median of the lowest point of each 1 m
    cell within 20 m (of all cells if fewer than 10 points are that close)."""
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
        pts = xyz[idx]
        level = _ground_level(pts, centre)
        levels.append(level)
        ground[idx] = _patchwork(pts - np.array([centre[0], centre[1], level + params.sensor_height]), params)
    return ground, float(np.median(levels))


def _ground_height(xy: np.ndarray, ground: np.ndarray, fallback: float, cell: float) -> np.ndarray:
    """Ground height (M,) at (M, 2) places: mean z of the ground points in their ``cell``,
    else in the nearest cell with ground; ``fallback`` everywhere without ground points."""
    if not len(ground):
        return np.full(len(xy), fallback)
    keys, inverse = _cell_index(ground[:, :2], cell)
    height = np.bincount(inverse, ground[:, 2]) / np.bincount(inverse)
    _, nearest = cKDTree((keys + 0.5) * cell).query(xy)
    return height[nearest]


# ----------------------------------------------------------------------------------------
# 3.-5. Walls
# ----------------------------------------------------------------------------------------
class _Cells:
    """Occupied square cells, as sorted int64 codes, and lookups of neighbours by offset."""

    def __init__(self, xy: np.ndarray, cell: float, margin: int):
        keys = np.floor(xy / cell).astype(np.int64)
        self.low = keys.min(axis=0) - margin
        self.width = int(keys[:, 1].max() - self.low[1]) + margin + 1
        codes = self.code(keys)
        self.codes, self.of_point = np.unique(codes, return_inverse=True)
        self.of_point = self.of_point.ravel()
        self.keys = keys[np.unique(self.of_point, return_index=True)[1]]
        self.centres = (self.keys + 0.5) * cell

    def code(self, keys: np.ndarray) -> np.ndarray:
        rel = keys - self.low
        return rel[:, 0] * self.width + rel[:, 1]

    def find(self, keys: np.ndarray) -> np.ndarray:
        """Index of the cell of each (M, 2) key, -1 for an empty one."""
        codes = self.code(keys)
        pos = np.minimum(np.searchsorted(self.codes, codes), len(self.codes) - 1)
        return np.where(self.codes[pos] == codes, pos, -1)


def _walls(q: np.ndarray, ground: np.ndarray, level: float, params: SelectionConfig) -> tuple[np.ndarray, int]:
    """(M,) bool mask of the non-ground points ``q`` that lie on walls, and the number of wall segments."""
    link = math.ceil(params.link_distance / params.cell)
    cells = _Cells(q[:, :2], params.cell, max(params.window_radius, link) + 1)
    n_cells = len(cells.codes)
    point_keys = cells.keys[cells.of_point]
    # (point, window) pairs: each point is in the window of every cell within window_radius of its own.
    r = params.window_radius
    pairs_p, pairs_w = [], []
    for dx in range(-r, r + 1):
        for dy in range(-r, r + 1):
            window = cells.find(point_keys - np.array([dx, dy]))
            ok = window >= 0
            pairs_p.append(np.flatnonzero(ok))
            pairs_w.append(window[ok])
    pi, wi = np.concatenate(pairs_p), np.concatenate(pairs_w)
    rel = q[pi, :2] - cells.centres[wi]
    weight = np.ones(len(pi))
    for _ in range(_PASSES):
        total = np.maximum(np.bincount(wi, weight, n_cells), 1e-12)
        mean = np.stack([np.bincount(wi, weight * rel[:, k], n_cells) / total for k in (0, 1)], axis=1)
        d = rel - mean[wi]
        sxx = np.bincount(wi, weight * d[:, 0] ** 2, n_cells) / total
        syy = np.bincount(wi, weight * d[:, 1] ** 2, n_cells) / total
        sxy = np.bincount(wi, weight * d[:, 0] * d[:, 1], n_cells) / total
        angle = 0.5 * np.arctan2(2 * sxy, sxx - syy)  # of the line's direction
        normal = np.stack([-np.sin(angle), np.cos(angle)], axis=1)
        dist = np.einsum('ij,ij->i', d, normal[wi])
        weight = (np.abs(dist) < params.band).astype(np.float64)
    band = weight > 0
    count = np.bincount(wi, band, n_cells)
    points = np.bincount(wi, minlength=n_cells)
    thickness = np.sqrt(np.bincount(wi, band * dist ** 2, n_cells) / np.maximum(count, 1))
    spread = 0.5 * (sxx + syy) + np.sqrt(0.25 * (sxx - syy) ** 2 + sxy ** 2)  # along the line
    length = np.sqrt(12.0 * spread)
    z = q[pi[band], 2]
    top = np.full(n_cells, -np.inf)
    bottom = np.full(n_cells, np.inf)
    np.maximum.at(top, wi[band], z)
    np.minimum.at(bottom, wi[band], z)
    foot = np.minimum(_ground_height(cells.centres, ground, level, params.ground_cell), bottom)
    wall = ((count >= params.min_window_points) & (count >= params.min_share * points)
            & (thickness <= params.max_thickness) & (length >= params.min_window_length)
            & (top - bottom >= params.min_extent) & (top - foot >= params.min_structure_height))
    wall, segments = _segments(wall, cells, cells.centres + mean, normal, link, params)
    keep = np.zeros(len(q), dtype=bool)
    keep[pi[band & wall[wi]]] = True
    return keep, segments


def _segments(wall: np.ndarray, cells: _Cells, centroid: np.ndarray, normal: np.ndarray, link: int,
              params: SelectionConfig) -> tuple[np.ndarray, int]:
    """The wall windows in segments of at least ``min_segment_length``, and the number of those."""
    idx = np.flatnonzero(wall)
    if not len(idx):
        return wall, 0
    cos_max = math.cos(math.radians(params.segment_angle))
    reach2 = (params.link_distance / params.cell) ** 2
    a_all, b_all = [idx], [idx]
    for dx in range(0, link + 1):
        for dy in range(-link, link + 1):
            if (dx == 0 and dy <= 0) or dx * dx + dy * dy > reach2:
                continue
            other = cells.find(cells.keys[idx] + np.array([dx, dy]))
            ok = other >= 0
            a, b = idx[ok], other[ok]
            ok = wall[b]
            a, b = a[ok], b[ok]
            step = centroid[b] - centroid[a]
            ok = ((np.abs(np.einsum('ij,ij->i', normal[a], normal[b])) >= cos_max)
                  & (np.abs(np.einsum('ij,ij->i', step, normal[a])) < params.band)
                  & (np.abs(np.einsum('ij,ij->i', step, normal[b])) < params.band))
            a_all.append(a[ok])
            b_all.append(b[ok])
    a, b = np.concatenate(a_all), np.concatenate(b_all)
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
    return out, int(long.sum())
