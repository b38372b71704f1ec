"""Voxel keys and the labelling of voxels by a scan's rays (shared by calibration and evaluation).

A scan labels voxels (:func:`reference_voxels`): **positives** are the voxels holding its
points, **negatives** the voxels its rays passed through on their way (sensor origin to
point) and that hold no point. The occupancy evaluation
(:mod:`~uncertain_facade_map.evaluation.occupancy`) labels the reference campaigns' voxels
so; the occupancy calibration (:mod:`~uncertain_facade_map.mapping.calibration`) labels
the mapped scans' own.

- Voxels form a grid aligned with the map frame's origin (voxel ``floor(x / r)``).
- Rays are a seeded subset (``max_rays``); a ray marks the voxels of samples every
  ``r / 3`` from the origin to ``r / 2`` before its point.
- Free voxels far outnumber the occupied ones. When there are more than ``max_negatives``,
  a seeded subset is kept and each kept negative weighs ``n_negatives / max_negatives``,
  so that sums over them estimate sums over all; the same for more than ``max_positives``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Iterator

import numpy as np

from .errors import InputError

#: Bits per axis of a packed voxel key (voxel indices within +-2^20 of the origin).
_BITS = 21
_OFFSET = 1 << (_BITS - 1)

__all__ = ['ReferenceVoxels', 'pack_keys', 'ray_crossings', 'reference_voxels', 'unpack_keys', 'voxel_index',
           'wrapped_keys']


def voxel_index(xyz: np.ndarray, resolution: float) -> np.ndarray:
    """(N, 3) int64 index of the voxel holding each point: ``floor(x / r)`` per axis."""
    return np.floor(np.asarray(xyz, dtype=np.float64) / resolution).astype(np.int64)


def wrapped_keys(xyz: np.ndarray, side: float) -> np.ndarray:
    """(N,) int64 keys of the ``side``-metre cells of (N, 3) points, metres: 21 bits per axis
    that wrap, so keys repeat only 2^21 cells apart (105 km at 0.05 m), further than the
    points compared by key lie; unlike :func:`pack_keys`, never refused."""
    return _wrap(np.floor(xyz / side).astype(np.int64))


def _wrap(cells: np.ndarray) -> np.ndarray:
    """(N,) int64 :func:`wrapped_keys` of (N, 3) int64 cell indices (21 bits per axis that wrap)."""
    c = cells & ((1 << _BITS) - 1)
    return (c[:, 0] << (2 * _BITS)) | (c[:, 1] << _BITS) | c[:, 2]


def near_keys(xyz: np.ndarray, side: float) -> np.ndarray:
    """Sorted unique :func:`wrapped_keys` of the ``side``-metre cells of (N, 3) points,
    metres, and of their 26 neighbours: the cells of every point within ``side`` of one of
    them."""
    mask = (1 << _BITS) - 1
    keys = np.unique(wrapped_keys(xyz, side))
    cells = np.stack([keys >> (2 * _BITS), (keys >> _BITS) & mask, keys & mask], axis=1)
    off = np.stack(np.meshgrid(*([np.arange(-1, 2)] * 3), indexing='ij'), axis=-1).reshape(-1, 3)
    return np.unique(_wrap((cells[:, None, :] + off[None]).reshape(-1, 3)))


def pack_keys(index: np.ndarray, unit: str = 'voxels') -> np.ndarray:
    """(N,) int64 key of (N, 3) voxel indices (one number per voxel, for np.unique).

    Args:
        index: (N, 3) int64 cell indices.
        unit: what a cell is, for the error message.

    Raises:
        InputError: an index beyond +-2^20 cells (the scene is too large for the resolution).
    """
    shifted = index + _OFFSET
    if len(shifted) and (shifted.min() < 0 or shifted.max() >= (1 << _BITS)):
        raise InputError(f'the points reach beyond {_OFFSET:,} {unit} from the map origin; '
                         'use map-frame coordinates near the origin or a coarser resolution')
    return (shifted[:, 0] << (2 * _BITS)) | (shifted[:, 1] << _BITS) | shifted[:, 2]


def unpack_keys(keys: np.ndarray) -> np.ndarray:
    """(N, 3) int64 voxel indices of (N,) packed keys (inverse of :func:`pack_keys`)."""
    mask = (1 << _BITS) - 1
    return np.stack([(keys >> (2 * _BITS)) & mask, (keys >> _BITS) & mask, keys & mask], axis=1) - _OFFSET


@dataclass(frozen=True, eq=False)
class ReferenceVoxels:
    """The labelled voxels of one resolution.

    Attributes:
        resolution: voxel side, metres.
        centres: (K, 3) float64 voxel centres, map frame, metres.
        positive: (K,) bool, True for voxels holding reference points.
        weight: (K,) float64 weight of each voxel in the curves (1, or more for the
            negatives when they were subsampled).
        n_rays: reference rays used.
        n_negatives: free voxels found along those rays (before subsampling).
        n_positives: voxels holding reference points (before subsampling).
    """

    resolution: float
    centres: np.ndarray
    positive: np.ndarray
    weight: np.ndarray
    n_rays: int
    n_negatives: int
    n_positives: int


def reference_voxels(points: np.ndarray, origins: np.ndarray, resolution: float, max_rays: int = 50_000,
                     max_negatives: int = 400_000, seed: int = 0, samples_per_chunk: int = 4_000_000,
                     max_positives: int = 400_000) -> ReferenceVoxels:
    """Label voxels by a reference scan.

    Args:
        points: (N, 3) float64 reference points, map frame, metres.
        origins: (N, 3) float64 sensor origin of each point, map frame, metres.
        resolution: voxel side, metres.
        max_rays: at most this many rays (a seeded subset) are traced.
        max_negatives: at most this many free voxels are kept (a seeded subset, weighted).
        seed: seed of the subsets.
        samples_per_chunk: ray samples handled at once (bounds memory).
        max_positives: at most this many occupied voxels are kept (a seeded subset, weighted).

    Returns:
        The labelled voxels.

    Raises:
        InputError: bad shapes, non-finite values, no points, or bad limits.
    """
    points = np.asarray(points, dtype=np.float64)
    origins = np.asarray(origins, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3 or not len(points):
        raise InputError(f'reference points must be a non-empty (N, 3) array, got shape {points.shape}')
    if origins.shape != points.shape:
        raise InputError(f'reference origins must have the shape of the points {points.shape}, got {origins.shape}')
    if not (np.isfinite(points).all() and np.isfinite(origins).all()):
        raise InputError('reference points and origins must be finite (the reference needs sensor origins)')
    if not (np.isfinite(resolution) and resolution > 0):
        raise InputError(f'resolution must be positive, got {resolution!r}')
    if min(max_rays, max_negatives, max_positives) < 1:
        raise InputError(f'max_rays, max_negatives and max_positives must be >= 1, got {max_rays}, '
                         f'{max_negatives} and {max_positives}')
    rng = np.random.default_rng(seed)
    pos_keys = np.unique(pack_keys(voxel_index(points, resolution)))  # every point's voxel
    if len(points) > max_rays:
        pick = np.sort(rng.choice(len(points), max_rays, replace=False))
        points, origins = points[pick], origins[pick]

    # Free space: samples every r/3 along each ray, up to r/2 before its point.
    free_parts = [np.unique(keys) for _, keys in _ray_samples(points, origins, resolution, np.inf,
                                                               samples_per_chunk)]
    free = np.unique(np.concatenate(free_parts)) if free_parts else np.empty(0, np.int64)
    free = free[~np.isin(free, pos_keys, assume_unique=True)]
    n_negatives, n_positives = len(free), len(pos_keys)
    free, weight_negative = _subsample(rng, free, max_negatives)
    pos_keys, weight_positive = _subsample(rng, pos_keys, max_positives)
    keys = np.concatenate([pos_keys, free])
    centres = (unpack_keys(keys) + 0.5) * resolution
    positive = np.r_[np.ones(len(pos_keys), bool), np.zeros(len(free), bool)]
    weight = np.where(positive, weight_positive, weight_negative)
    return ReferenceVoxels(float(resolution), centres, positive, weight, len(points), n_negatives, n_positives)


def _subsample(rng: np.random.Generator, keys: np.ndarray, limit: int) -> tuple[np.ndarray, float]:
    """At most ``limit`` of (K,) sorted keys (a seeded subset, sorted) and the weight of each."""
    if len(keys) <= limit:
        return keys, 1.0
    return np.sort(rng.choice(keys, limit, replace=False)), len(keys) / limit


def ray_crossings(points: np.ndarray, origins: np.ndarray, resolution: float, keys: np.ndarray,
                  reach: float = 5.0, samples_per_chunk: int = 4_000_000) -> np.ndarray:
    """How many rays pass through each of the given voxels.

    Rays are sampled at the samples of :func:`reference_voxels` (every ``r / 3`` from the
    origin, up to ``r / 2`` before the point) that lie within ``reach`` of the point; a ray counts once per voxel (a
    straight line leaves a convex voxel once, so consecutive equal samples are one).

    Args:
        points: (N, 3) float64 ray end points, map frame, metres.
        origins: (N, 3) float64 their sensor origins.
        resolution: voxel side, metres.
        keys: (K,) int64 packed keys of the voxels to count (:func:`pack_keys`).
        reach: metres of each ray traced, back from its point.
        samples_per_chunk: ray samples handled at once (bounds memory).

    Returns:
        (K,) int64 number of rays through each voxel.
    """
    order = np.argsort(keys)
    wanted = np.asarray(keys, dtype=np.int64)[order]
    counts = np.zeros(len(wanted), dtype=np.int64)
    for ray, k in _ray_samples(np.asarray(points, dtype=np.float64), np.asarray(origins, dtype=np.float64),
                               resolution, reach, samples_per_chunk):
        first = np.r_[True, (k[1:] != k[:-1]) | (ray[1:] != ray[:-1])]
        k = k[first]
        at = np.searchsorted(wanted, k)
        hit = at < len(wanted)
        hit[hit] = wanted[at[hit]] == k[hit]
        counts += np.bincount(at[hit], minlength=len(wanted))
    out = np.empty_like(counts)
    out[order] = counts
    return out


def _ray_samples(points: np.ndarray, origins: np.ndarray, resolution: float, reach: float,
                 samples_per_chunk: int) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """The samples of the rays, chunk by chunk: ``(ray index, packed voxel key)``, (S,) each,
    in ray order and along each ray from its origin. A ray from origin o to point x is
    sampled at ``t = j * r / 3`` from o, up to ``r / 2`` before x, those within ``reach``
    of x (``np.inf``: all)."""
    step = resolution / 3.0
    direction = points - origins
    length = np.linalg.norm(direction, axis=1)
    unit = direction / np.maximum(length, 1e-12)[:, None]
    first_j = np.maximum(np.ceil((length - reach) / step), 0.0).astype(np.int64)
    last_j = np.floor((length - 0.5 * resolution) / step).astype(np.int64)
    n_samples = np.maximum(last_j - first_j + 1, 0)
    cum = np.cumsum(n_samples)
    start = 0
    while start < len(points):
        before = int(cum[start] - n_samples[start])
        stop = max(start + 1, int(np.searchsorted(cum, before + samples_per_chunk, side='right')))
        c = n_samples[start:stop]
        ray = np.repeat(np.arange(start, stop), c)
        t = (first_j[ray] + np.arange(int(c.sum())) - np.repeat(np.cumsum(c) - c, c)) * step
        yield ray, pack_keys(voxel_index(origins[ray] + unit[ray] * t[:, None], resolution))
        start = stop
