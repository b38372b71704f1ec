"""The small interface every occupancy method of the evaluation implements.

A method is built for one voxel resolution, fitted once on the mapped points (hits, map
frame, with each point's sensor origin, so ray-based methods can trace the free space),
then asked for the occupancy probability of voxel centres. The evaluation
(:mod:`uncertain_facade_map.evaluation.occupancy`) times ``fit`` (training) and
``predict`` (testing) separately.
"""

from __future__ import annotations

import abc
from typing import ClassVar

import numpy as np

from ...errors import InputError


class OccupancyMethod(abc.ABC):
    """An occupancy mapping method: fit on scans, predict p(occupied) at voxel centres.

    Attributes:
        name: short label used in tables and figures (class attribute).
        trains_on_predict: True for a method that defers part of its training to the
            first ``predict`` (only what the asked voxels need), so its testing time holds
            that training (class attribute; the report says so).
        resolution: voxel side, metres.
    """

    name: ClassVar[str] = ''
    trains_on_predict: ClassVar[bool] = False

    def __init__(self, resolution: float) -> None:
        if not (np.isfinite(resolution) and resolution > 0):
            raise InputError(f'resolution must be a positive number of metres, got {resolution!r}')
        self.resolution = float(resolution)

    @abc.abstractmethod
    def fit(self, points: np.ndarray, origins: np.ndarray) -> OccupancyMethod:
        """Build the map.

        Args:
            points: (N, 3) float64 measured points (ray end points), map frame, metres.
            origins: (N, 3) float64 sensor origin of each point's ray, map frame, metres.

        Returns:
            self.
        """

    @abc.abstractmethod
    def predict(self, xyz: np.ndarray) -> np.ndarray:
        """Occupancy probability of the voxels centred at ``xyz``.

        Args:
            xyz: (M, 3) float64 voxel centres, map frame, metres.

        Returns:
            (M,) float64 in [0, 1]; 0.5 where the method knows nothing.
        """

    def predict_variance(self, xyz: np.ndarray) -> np.ndarray | None:
        """(M,) variance of the method's latent estimate at ``xyz`` (its own units), or None
        for methods without one. Used for the accurate-inference curves."""
        return None

    def diagnostics(self, xyz: np.ndarray) -> dict[str, np.ndarray]:
        """Per-voxel quantities for the report beyond p and variance, each (M,), by name
        (none by default). Not timed."""
        return {}


def check_positive(name: str, value: float) -> float:
    """A parameter that must be a positive, finite number, as a float.

    Raises:
        InputError: ``value`` is not positive and finite (naming ``name``).
    """
    value = float(value)
    if not (np.isfinite(value) and value > 0):
        raise InputError(f'{name} must be a positive number, got {value!r}')
    return value


def check_scans(points: np.ndarray, origins: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Validate the arguments of :meth:`OccupancyMethod.fit`.

    Returns:
        ``(points, origins)`` as float64 arrays.

    Raises:
        InputError: shapes differ, are not (N, 3), N is 0, or values are not finite.
    """
    points = np.asarray(points, dtype=np.float64)
    origins = np.asarray(origins, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3 or not len(points):
        raise InputError(f'points must be a non-empty (N, 3) array, got shape {points.shape}')
    if origins.shape != points.shape:
        raise InputError(f'origins must have the shape of the points {points.shape}, got {origins.shape}')
    if not (np.isfinite(points).all() and np.isfinite(origins).all()):
        raise InputError('points and origins must be finite')
    return points, origins


def check_queries(xyz: np.ndarray) -> np.ndarray:
    """Validate the argument of :meth:`OccupancyMethod.predict`; returns it as float64.

    Raises:
        InputError: not (M, 3) or not finite.
    """
    xyz = np.asarray(xyz, dtype=np.float64)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise InputError(f'query points must be an (M, 3) array, got shape {xyz.shape}')
    if not np.isfinite(xyz).all():
        raise InputError('query points must be finite')
    return xyz


def group_by_origin(origins: np.ndarray, quantum: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Group rays whose sensor origins fall in the same cube of side ``quantum``.

    Args:
        origins: (N, 3) float64 sensor origins, map frame, metres.
        quantum: side of the cubes, metres (> 0).

    Returns:
        ``(order, starts, mean_origins)``: (N,) int64 ray indices sorted by group (groups in
        the order of their first ray, rays in input order within a group), (G + 1,) int64
        offsets of each group in ``order``, and (G, 3) float64 mean origin of each group.
    """
    cells = np.floor(origins / quantum).astype(np.int64)
    _, first, inverse = np.unique(cells, axis=0, return_index=True, return_inverse=True)
    inverse = inverse.reshape(-1)
    # Renumber the groups by their first ray, so scans are inserted in input (time) order.
    rank = np.empty(len(first), dtype=np.int64)
    rank[np.argsort(first, kind='stable')] = np.arange(len(first))
    group = rank[inverse]
    order = np.argsort(group, kind='stable')
    counts = np.bincount(group, minlength=len(first))
    starts = np.r_[0, np.cumsum(counts)]
    sums = np.stack([np.bincount(group, weights=origins[:, k], minlength=len(first)) for k in range(3)], axis=1)
    return order, starts, sums / counts[:, None]


def beam_samples(hits: np.ndarray, origins: np.ndarray, step: float) -> tuple[np.ndarray, np.ndarray]:
    """Free-space samples of beams by the ``la3dm`` library's rule (``beam_sample`` of
    BGKOctoMap and GPOctoMap): at ``step``, ``2 step``, ... while below the beam's length,
    plus one at ``length - step`` when the beam is longer than ``step``. The origin itself
    is not included (the library adds it separately).

    Args:
        hits: (N, 3) float64 beam end points, metres.
        origins: (N, 3) float64 beam origins, metres.
        step: spacing of the samples, metres (> 0).

    Returns:
        ``(samples, beam)``: (S, 3) float64 samples, the regular ones beam by beam, then the
        last one of each beam longer than ``step``; (S,) int64 the beam of each.
    """
    direction = hits - origins
    length = np.linalg.norm(direction, axis=1)
    unit = direction / np.maximum(length, 1e-12)[:, None]
    # d = step, 2 step, ... while d < length (the library's float loop: the count of k >= 1
    # with k step < length), then length - step.
    n = np.maximum(np.ceil(length / step).astype(np.int64) - 1, 0)
    d = (np.arange(int(n.sum())) - np.repeat(np.cumsum(n) - n, n) + 1.0) * step
    body = np.repeat(unit, n, axis=0)
    body *= d[:, None]
    body += np.repeat(origins, n, axis=0)
    long = np.flatnonzero(length > step)
    beam = np.r_[np.repeat(np.arange(len(hits)), n), long]
    return np.concatenate([body, hits[long] - unit[long] * step]), beam


def voxel_centroids(points: np.ndarray, cell: float, group: np.ndarray | None = None,
                    extra: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Voxel-grid down-sampling (PCL ``VoxelGrid``: the centroid of each cell's points),
    within groups when given.

    Args:
        points: (N, 3) float64 points, metres.
        cell: voxel side, metres.
        group: (N,) int64 group (scan) of each point, >= 0; None: one group.
        extra: (N, K) float64 values averaged the same way (e.g. sensor origins), or None.

    Returns:
        ``(centroids, groups, extra_means)``: (M, 3) centroids, (M,) int64 their groups and
        (M, K) means of ``extra`` (None when it was None), one row per occupied (group, cell),
        sorted by group, then cell.

    Raises:
        InputError: the points span too many cells to be keyed.
    """
    n = len(points)
    group = np.zeros(n, np.int64) if group is None else np.asarray(group, np.int64)
    if not n:
        return points.reshape(0, 3), group[:0], None if extra is None else extra.reshape(0, extra.shape[1])
    idx = np.floor(points / cell).astype(np.int64)
    idx -= idx.min(axis=0)
    dims = idx.max(axis=0) + 1
    n_cells = int(dims[0]) * int(dims[1]) * int(dims[2])
    if n_cells * (int(group.max()) + 1) >= 1 << 62:
        raise InputError('the points span too many voxels to down-sample; use map-frame coordinates near the origin')
    key = group * n_cells + (idx[:, 0] * dims[1] + idx[:, 1]) * dims[2] + idx[:, 2]
    _, first, inverse, counts = np.unique(key, return_index=True, return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)

    def mean(values: np.ndarray) -> np.ndarray:
        return np.stack([np.bincount(inverse, weights=values[:, k], minlength=len(counts))
                         for k in range(values.shape[1])], axis=1) / counts[:, None]

    return mean(points), group[first], None if extra is None else mean(extra)
