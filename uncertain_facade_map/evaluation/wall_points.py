"""Wall points of an unclassified lidar sweep, for the benchmark.

Real clouds seldom carry a semantic class: ground, cars, trees, poles and walls come
together. Until a building-point selector lands, the benchmark
(:mod:`~uncertain_facade_map.evaluation.benchmark`) maps the *walls* of such a cloud,
picked by :func:`wall_points`. The pick is the same procedure as ``walls()`` of the
independent checker ``../shared/tools/real_check.py`` (our own, vectorised code; the
checker is not imported), so that the benchmark's reference figures agree with the
checker's:

1. **Candidates**: points more than ``above_ground`` (0.5 m) above the local ground (the
   lowest point of their ``ground_cell`` (2 m) x-y cell) and within ``max_range`` (40 m,
   horizontally) of the sensor.
2. **Sequential RANSAC of vertical planes**, at most ``max_planes`` (12) rounds, while at
   least ``min_candidates`` (500) candidates are left: ``hypotheses`` (1500) draws of two
   distinct candidates; a pair 1 to 6 m apart (horizontally) spans a vertical plane; its
   score is the number of candidates within ``ransac_threshold`` (0.15 m) of it. The best
   plane, if it has at least ``min_inliers`` (400), has its normal turned towards the
   sensor.
3. **The wall**: every candidate-height point (any range) still free within ``band``
   (0.4 m) of the plane is taken out of the pool; its positions along the wall are cut
   at gaps over ``max_gap`` (1 m), and the piece with the most points is a wall if it is
   at least ``min_width`` (3 m) wide, ``min_height`` (2 m) tall and holds ``min_points``
   (300) points.

The result is a per-point wall label and each wall's frame (normal towards the sensor,
``e_u`` horizontal, ``e_v`` up), so that the benchmark can cut occlusion patches per
wall, place the empty voxels in front of it and look for depth steps in its plane.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..datatypes import FacadeFrame
from ..errors import InputError

#: Hypotheses scored at once (bounds memory: about chunk x candidates x 9 bytes).
_CHUNK = 128


@dataclass(frozen=True, eq=False)
class WallPick:
    """Walls found in a cloud.

    Attributes:
        label: (N,) int64 wall index of each point, -1 for none.
        frames: per wall its frame: origin on the plane, normal towards the sensor,
            ``e_u`` horizontal, ``e_v`` up (map frame, metres).
    """

    label: np.ndarray
    frames: list[FacadeFrame]

    @property
    def mask(self) -> np.ndarray:
        """(N,) bool: the point lies on a wall."""
        return self.label >= 0


def local_ground(xyz: np.ndarray, cell: float = 2.0) -> np.ndarray:
    """(N,) height of the local ground under each point: the lowest z of its x-y cell, metres."""
    key = np.floor(xyz[:, :2] / cell).astype(np.int64)
    _, inverse = np.unique(key, axis=0, return_inverse=True)
    inverse = inverse.ravel()
    low = np.full(inverse.max() + 1, np.inf)
    np.minimum.at(low, inverse, xyz[:, 2])
    return low[inverse]


def _best_plane(xy: np.ndarray, rng: np.random.Generator, hypotheses: int, pair_min: float, pair_max: float,
                threshold: float) -> tuple[int, np.ndarray, np.ndarray] | None:
    """(inliers, unit horizontal normal (2,), point (2,)) of the best vertical plane through
    pairs of the (M, 2) candidates, or None when no pair was 1 to 6 m apart."""
    m = len(xy)
    i = rng.integers(m, size=hypotheses)
    j = rng.integers(m - 1, size=hypotheses)
    j += j >= i  # two distinct candidates
    delta = xy[j] - xy[i]
    length = np.hypot(delta[:, 0], delta[:, 1])
    ok = (length >= pair_min) & (length <= pair_max)
    if not ok.any():
        return None
    normals = np.stack([-delta[ok, 1], delta[ok, 0]], axis=1) / length[ok, None]
    offsets = np.einsum('hi,hi->h', normals, xy[i[ok]])
    counts = np.empty(len(normals), dtype=np.int64)
    for start in range(0, len(normals), _CHUNK):
        part = slice(start, start + _CHUNK)
        counts[part] = (np.abs(xy @ normals[part].T - offsets[part]) < threshold).sum(axis=0)
    best = int(np.argmax(counts))
    return int(counts[best]), normals[best], xy[i[ok]][best]


def wall_points(xyz: np.ndarray, sensor: np.ndarray, rng: np.random.Generator, *, max_range: float = 40.0,
                above_ground: float = 0.5, ground_cell: float = 2.0, max_planes: int = 12, hypotheses: int = 1500,
                ransac_threshold: float = 0.15, band: float = 0.4, pair_min: float = 1.0, pair_max: float = 6.0,
                min_candidates: int = 500, min_inliers: int = 400, max_gap: float = 1.0, min_width: float = 3.0,
                min_height: float = 2.0, min_points: int = 300) -> WallPick:
    """Pick the points of vertical walls in an unclassified sweep (see the module docstring).

    Args:
        xyz: (N, 3) float64 points, metres, map frame, z up.
        sensor: (3,) sensor position, metres, map frame (e.g. the mean of the sensor origins).
        rng: random source of the RANSAC draws.
        max_range ... min_points: the pick's thresholds (module docstring), metres or counts.

    Returns:
        The walls: per-point labels and frames.

    Raises:
        InputError: ``xyz`` not (N, 3) or with NaN or infinite coordinates; a bad sensor.
    """
    xyz = np.asarray(xyz, dtype=np.float64)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise InputError(f'points must be an (N, 3) array, got shape {xyz.shape}')
    if not np.isfinite(xyz).all():
        raise InputError(f'{int((~np.isfinite(xyz)).any(axis=1).sum())} points have NaN or infinite coordinates')
    sensor = np.asarray(sensor, dtype=np.float64).reshape(-1)
    if sensor.shape != (3,) or not np.isfinite(sensor).all():
        raise InputError(f'the sensor position must be 3 finite numbers, got {sensor}')
    label = np.full(len(xyz), -1, dtype=np.int64)
    frames: list[FacadeFrame] = []
    if not len(xyz):
        return WallPick(label, frames)
    above = xyz[:, 2] > local_ground(xyz, ground_cell) + above_ground
    near = np.hypot(xyz[:, 0] - sensor[0], xyz[:, 1] - sensor[1]) < max_range
    candidates = np.flatnonzero(above & near)
    free = np.ones(len(xyz), dtype=bool)
    for _ in range(max_planes):
        pool = candidates[free[candidates]]
        if len(pool) < min_candidates:
            break
        best = _best_plane(xyz[pool, :2], rng, hypotheses, pair_min, pair_max, ransac_threshold)
        if best is None or best[0] < min_inliers:
            break
        _, n2, p2 = best
        normal = np.array([n2[0], n2[1], 0.0])
        point = np.array([p2[0], p2[1], 0.0])
        if normal @ (sensor - point) < 0:
            normal = -normal
        depth = (xyz - point) @ normal
        in_band = np.flatnonzero(above & free & (np.abs(depth) < band))
        free[in_band] = False
        if len(in_band) < min_points:
            continue
        u_axis = np.array([-normal[1], normal[0], 0.0])
        u = (xyz[in_band] - point) @ u_axis
        order = np.argsort(u, kind='stable')
        us = u[order]
        cuts = np.flatnonzero(np.diff(us) > max_gap)
        starts, ends = np.r_[0, cuts + 1], np.r_[cuts + 1, len(us)]
        k = int(np.argmax(ends - starts))
        piece = in_band[order[starts[k]:ends[k]]]
        width = us[ends[k] - 1] - us[starts[k]]
        if width >= min_width and np.ptp(xyz[piece, 2]) >= min_height and len(piece) >= min_points:
            label[piece] = len(frames)
            frames.append(FacadeFrame.from_normal(point, normal))
    return WallPick(label, frames)
