"""How hard a cloud is: point density on walls and residual spread of planar wall patches.

The same measurement for real and simulated clouds, so that the simulator's sensor presets
(:mod:`..simulation.presets`) can be checked against real samples. No labels are used:
walls are found the way one would in an unclassified real sweep.

1. *Ground and candidates*: the local ground is the lowest point of each 2 m x 2 m column;
   candidates are the points more than ``above_ground`` (0.5 m) above it and within
   ``min_range`` to ``max_range`` (2-40 m) of the sensor, horizontally.
2. *Walls*: sequential RANSAC for vertical planes: a trial plane goes through two
   candidates 1-5 m apart horizontally (the second drawn among the first one's
   neighbours) and scores the candidates within ``threshold`` (0.1 m); the best of
   ``trials`` is refined by a line fit (PCA) of its inliers seen from above; its points
   within ``band`` (0.15 m) are split into pieces along the wall at gaps over 1 m, and a
   piece is a wall if it is at least 3 m wide, 2 m tall and has 200 points, and its plane
   is at least ``min_distance`` (3 m) from the sensor (nothing real stands that close to a
   road, but the scan planes of profile scanners pass through the sensor). A plane's band
   points leave the candidates whether or not a piece was kept; up to ``max_walls`` planes.
3. *Figures per wall*, on a 1 m x 1 m grid over the wall (along it x height):
   density = the wall's points over the area of the cells holding at least one of them
   (points/m^2, for one sweep: the cloud given); per occupied cell its density (points in
   it per m^2) and its range (from the sensor to the mean of its points); and for every
   cell with at least ``min_patch_points`` (15) points the residual spread of a plane
   fitted by PCA: the square root of the smallest eigenvalue of the cell's covariance
   (metres); and the points seen *through* it: 0.3 to 5 m behind its plane (away from
   the sensor) whose ray crosses the plane in one of the wall's occupied cells and that
   are on none of the walls found, i.e. returns from inside rooms through windows (or from
   behind anything else in the wall's plane: a parked truck taken for a wall leaves out
   the façade behind it, which is a wall found, but not the car or tree behind a fence).

The figures reported are the median over walls of the density (with its range), the
median cell density in range bands (5-10, 10-15 and 15-25 m: the density falls with range,
so clouds whose walls stand at other distances are compared band by band), and the median
over all patches of the residual spread, and the points seen through the walls as a share
of the points on them. Walls keep their detail (windows, sills, pipes):
the residual spread of a real wall is sensor noise plus everything that is not flat within
a metre, which is why the simulated walls carry their detail too.

``python -m uncertain_facade_map.evaluation.realism`` prints the comparison table of
docs/simulator.md ("Against the real samples"): the real samples (``../shared/data/real/`` beside the
repository, when present) and simulated sweeps of each sensor preset.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np
from scipy.spatial import cKDTree

from ..errors import InputError
from .wall_points import local_ground


@dataclass(frozen=True)
class Wall:
    """A vertical wall found in a cloud.

    Attributes:
        normal: (3,) horizontal unit normal, towards the sensor.
        point: (3,) a point of the wall plane, metres.
        members: (K,) indices of the cloud's points on the wall.
        width: extent along the wall, metres.
        height: extent in z, metres.
        distance: horizontal distance of the sensor from the wall plane, metres.
    """

    normal: np.ndarray
    point: np.ndarray
    members: np.ndarray
    width: float
    height: float
    distance: float


@dataclass(frozen=True)
class CloudFigures:
    """Density and residual spread of the walls of one cloud.

    Attributes:
        name: what was measured.
        n_points: points in the cloud.
        walls: the walls found.
        density: (W,) points/m^2 per wall (over its occupied 1 m cells).
        patch_std: (P,) residual spread of every 1 m patch with enough points, metres.
        cell_density: (C,) points/m^2 of every occupied 1 m cell of the walls.
        cell_range: (C,) range of each of those cells from the sensor, metres.
        behind: (W,) points seen through each wall (see the module docstring).
    """

    name: str
    n_points: int
    walls: tuple[Wall, ...]
    density: np.ndarray
    patch_std: np.ndarray
    cell_density: np.ndarray
    cell_range: np.ndarray
    behind: np.ndarray

    @property
    def wall_points(self) -> int:
        """Points on the walls found."""
        return int(sum(len(w.members) for w in self.walls))

    @property
    def median_density(self) -> float:
        """Median over walls of the density, points/m^2 (NaN without walls)."""
        return float(np.median(self.density)) if len(self.density) else float('nan')

    @property
    def median_patch_std(self) -> float:
        """Median over patches of the residual spread, metres (NaN without patches)."""
        return float(np.median(self.patch_std)) if len(self.patch_std) else float('nan')

    @property
    def distances(self) -> np.ndarray:
        """(W,) distance of the sensor from each wall, metres."""
        return np.array([w.distance for w in self.walls])

    @property
    def behind_share(self) -> float:
        """Points seen through the walls over points on them (NaN without walls)."""
        return float(self.behind.sum() / self.wall_points) if self.walls else float('nan')

    def density_between(self, near: float, far: float) -> float:
        """Median density of the wall cells at ``near`` to ``far`` metres from the sensor,
        points/m^2 (NaN for none)."""
        sel = (self.cell_range >= near) & (self.cell_range < far)
        return float(np.median(self.cell_density[sel])) if sel.any() else float('nan')


def find_walls(xyz: np.ndarray, sensor: np.ndarray, rng: np.random.Generator, *, max_walls: int = 12,
               trials: int = 600, threshold: float = 0.1, band: float = 0.15, above_ground: float = 0.5,
               min_range: float = 2.0, max_range: float = 40.0, min_width: float = 3.0, min_height: float = 2.0,
               min_points: int = 200, min_distance: float = 3.0, score_sample: int = 20_000) -> list[Wall]:
    """Vertical walls of an unclassified cloud by sequential RANSAC (see the module docstring).

    Args:
        xyz: (N, 3) points, metres, z up.
        sensor: (3,) sensor position in the same frame, metres.
        rng: random source of the trials.
        max_walls: planes tried at most.
        trials: RANSAC trials per plane.
        threshold: inlier distance of the trials, metres.
        band: half-width of the band a wall's points lie in, metres.
        above_ground: candidates lie this much above the local ground, metres.
        min_range: horizontal range of the candidates from the sensor, from, metres.
        max_range: ... to, metres.
        min_width: a wall piece is at least this wide, metres.
        min_height: ... this tall, metres.
        min_points: ... and has this many points.
        min_distance: ... and its plane is this far from the sensor, metres.
        score_sample: trials are scored on at most this many candidates (a random subset).

    Returns:
        The walls, largest plane first.
    """
    xyz = np.asarray(xyz, dtype=np.float64)
    sensor = np.asarray(sensor, dtype=np.float64)
    if xyz.ndim != 2 or xyz.shape[1] != 3 or not len(xyz):
        raise InputError(f'need a non-empty (N, 3) array of points, got shape {xyz.shape}')
    horizontal = np.hypot(xyz[:, 0] - sensor[0], xyz[:, 1] - sensor[1])
    above = xyz[:, 2] > local_ground(xyz) + above_ground
    free = above & (horizontal >= min_range) & (horizontal <= max_range)
    walls: list[Wall] = []
    for _ in range(max_walls):
        cand = np.flatnonzero(free)
        if len(cand) < min_points:
            break
        score = cand if len(cand) <= score_sample else rng.choice(cand, score_sample, replace=False)
        tree = cKDTree(xyz[cand, :2])
        first = rng.choice(len(cand), trials)
        near = tree.query_ball_point(xyz[cand[first], :2], 5.0)
        second = np.array([nb[int(rng.integers(len(nb)))] for nb in near])
        dxy = xyz[cand[second], :2] - xyz[cand[first], :2]
        length = np.hypot(dxy[:, 0], dxy[:, 1])
        usable = length >= 1.0
        if not usable.any():
            break
        normals = np.stack([-dxy[usable, 1], dxy[usable, 0], np.zeros(int(usable.sum()))], axis=1)
        normals /= length[usable, None]
        offsets = np.einsum('ij,ij->i', xyz[cand[first[usable]]], normals)
        points = xyz[score]
        counts = np.concatenate([(np.abs(points @ normals[k:k + 100].T - offsets[k:k + 100]) < threshold).sum(axis=0)
                                 for k in range(0, len(normals), 100)])
        best = int(np.argmax(counts))
        n, p0 = normals[best], xyz[cand[first[usable][best]]]
        inl = cand[np.abs((xyz[cand] - p0) @ n) < threshold]
        # Refine: a line through the inliers seen from above (PCA in xy).
        centre = xyz[inl].mean(axis=0)
        cov = np.cov((xyz[inl, :2] - centre[:2]).T)
        direction = np.linalg.eigh(cov)[1][:, -1]
        n = np.array([-direction[1], direction[0], 0.0])
        if n @ (sensor - centre) < 0:
            n = -n
        u_axis = np.array([-n[1], n[0], 0.0])
        on_plane = free & (np.abs((xyz - centre) @ n) < band)
        free &= ~on_plane
        members = np.flatnonzero(on_plane)
        distance = float(abs((sensor - centre) @ n))
        if len(members) < min_points or distance < min_distance:
            continue
        u = (xyz[members] - centre) @ u_axis
        order = np.argsort(u)
        cuts = np.flatnonzero(np.diff(u[order]) > 1.0) + 1
        for piece in np.split(order, cuts):
            idx = members[piece]
            width = float(np.ptp(u[piece])) if len(piece) else 0.0
            height = float(np.ptp(xyz[idx, 2])) if len(piece) else 0.0
            if len(idx) >= min_points and width >= min_width and height >= min_height:
                walls.append(Wall(n, centre, idx, width, height, distance))
    return walls


def _cells(xyz: np.ndarray, wall: Wall, cell: float) -> np.ndarray:
    """(K,) index of the 1 m cell (along the wall x height) of each of the wall's points."""
    u_axis = np.array([-wall.normal[1], wall.normal[0], 0.0])
    p = xyz[wall.members]
    key = np.stack([np.floor(((p - wall.point) @ u_axis) / cell), np.floor(p[:, 2] / cell)], axis=1)
    return np.unique(key.astype(np.int64), axis=0, return_inverse=True)[1].ravel()


def wall_density(xyz: np.ndarray, wall: Wall, cell: float = 1.0) -> float:
    """Points per square metre of a wall, over the ``cell``-sized cells it has points in."""
    occupied = len(np.unique(_cells(xyz, wall, cell)))
    return len(wall.members) / (occupied * cell * cell)


def cell_densities(xyz: np.ndarray, wall: Wall, sensor: np.ndarray, cell: float = 1.0
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Density (points/m^2) and range from the sensor (metres) of each occupied cell of a wall,
    (C,) each; a cell's range is that of the mean of its points."""
    inverse = _cells(xyz, wall, cell)
    count = np.bincount(inverse)
    centre = np.stack([np.bincount(inverse, weights=xyz[wall.members, k]) for k in range(3)], axis=1) / count[:, None]
    return count / (cell * cell), np.linalg.norm(centre - sensor, axis=1)


def points_behind(xyz: np.ndarray, wall: Wall, sensor: np.ndarray, near: float = 0.3, far: float = 5.0,
                  cell: float = 1.0, exclude: np.ndarray | None = None) -> int:
    """Points seen through a wall: ``near`` to ``far`` metres behind its plane, whose ray
    from the sensor crosses the plane in one of the wall's occupied ``cell`` cells (so
    through the wall, not through a gap beside it), leaving out the points flagged in
    ``exclude`` ((N,) bool; the points of the walls found)."""
    u_axis = np.array([-wall.normal[1], wall.normal[0], 0.0])
    d = (xyz - wall.point) @ wall.normal
    mask = (d <= -near) & (d >= -far)
    if exclude is not None:
        mask &= ~exclude
    back = np.flatnonzero(mask)
    if not len(back):
        return 0
    ray = xyz[back] - sensor
    s = ((wall.point - sensor) @ wall.normal) / (ray @ wall.normal)
    cross = sensor + s[:, None] * ray
    own = xyz[wall.members]
    key = lambda p: np.stack([np.floor(((p - wall.point) @ u_axis) / cell),  # noqa: E731
                              np.floor(p[:, 2] / cell)], axis=1).astype(np.int64)
    occupied = np.unique(key(own), axis=0)
    crossed = key(cross)
    # Rows of ``crossed`` that are occupied cells: a sorted search over the packed keys.
    base = np.int64(1 << 32)
    packed_own = np.sort(occupied[:, 0] * base + occupied[:, 1])
    packed = crossed[:, 0] * base + crossed[:, 1]
    at = np.clip(np.searchsorted(packed_own, packed), 0, len(packed_own) - 1)
    return int(((packed_own[at] == packed) & (s > 0) & (s < 1)).sum())


def patch_spread(xyz: np.ndarray, wall: Wall, cell: float = 1.0, min_points: int = 15) -> np.ndarray:
    """Residual spread of a plane fitted by PCA to each cell of a wall with enough points.

    Returns:
        (P,) the square root of the smallest eigenvalue of each cell's covariance, metres.
    """
    inverse = _cells(xyz, wall, cell)
    p = xyz[wall.members] - wall.point
    count = np.bincount(inverse)
    keep = count >= min_points
    if not keep.any():
        return np.empty(0)
    sums = np.zeros((len(count), 3))
    outer = np.zeros((len(count), 3, 3))
    np.add.at(sums, inverse, p)
    np.add.at(outer, inverse, p[:, :, None] * p[:, None, :])
    mean = sums[keep] / count[keep, None]
    cov = outer[keep] / count[keep, None, None] - mean[:, :, None] * mean[:, None, :]
    return np.sqrt(np.maximum(np.linalg.eigvalsh(cov)[:, 0], 0.0))


def measure(xyz: np.ndarray, sensor: np.ndarray, name: str = 'cloud', seed: int = 0, **wall_options) -> CloudFigures:
    """Walls, density and patch spread of one cloud (one sweep).

    Args:
        xyz: (N, 3) points, metres, z up.
        sensor: (3,) sensor position, metres, same frame.
        name: label of the figures.
        seed: seed of the RANSAC trials.
        wall_options: passed to :func:`find_walls`.
    """
    xyz = np.asarray(xyz, dtype=np.float64)
    sensor = np.asarray(sensor, dtype=np.float64)
    walls = find_walls(xyz, sensor, np.random.default_rng(seed), **wall_options)
    density = np.array([wall_density(xyz, w) for w in walls])
    spread = [patch_spread(xyz, w) for w in walls]
    cells = [cell_densities(xyz, w, sensor) for w in walls]
    on_walls = np.zeros(len(xyz), dtype=bool)
    for w in walls:
        on_walls[w.members] = True
    behind = np.array([points_behind(xyz, w, sensor, exclude=on_walls) for w in walls], dtype=np.int64)
    return CloudFigures(name, len(xyz), tuple(walls), density, _joined(spread),
                        _joined([c[0] for c in cells]), _joined([c[1] for c in cells]), behind)


def _joined(arrays: Sequence[np.ndarray]) -> np.ndarray:
    return np.concatenate(arrays) if len(arrays) else np.empty(0)


def pooled(name: str, figures: Sequence[CloudFigures]) -> CloudFigures:
    """Several sweeps' figures as one (walls, densities, cells and patches pooled; points per sweep)."""
    return CloudFigures(name, int(sum(f.n_points for f in figures)) // max(len(figures), 1),
                        tuple(w for f in figures for w in f.walls), _joined([f.density for f in figures]),
                        _joined([f.patch_std for f in figures]), _joined([f.cell_density for f in figures]),
                        _joined([f.cell_range for f in figures]),
                        _joined([f.behind for f in figures]).astype(np.int64))


def measure_file(path: str | Path, seed: int = 0) -> CloudFigures:
    """:func:`measure` on a cloud file; the sensor is the mean of the points' origins if
    the file has them, else the frame's origin (a cloud in the vehicle frame)."""
    from ..io.clouds import read_cloud

    cloud = read_cloud(path)
    origins = cloud.sensor_origins
    sensor = origins.mean(axis=0) if origins is not None else np.zeros(3)
    return measure(cloud.xyz, sensor, name=Path(path).name, seed=seed)


def simulated_sweeps(preset: str, scene_name: str = 'street_hard', seed: int = 0, count: int = 4,
                     sweep: float | None = None) -> list[CloudFigures]:
    """Figures of ``count`` simulated sweeps of a sensor preset along a scene's drive.

    A sweep is ``sweep`` seconds of data: by default one revolution for a spinning lidar
    (0.1 s at 10 Hz), and 1 s (5 m of drive, each wall strip scanned once by each scanner)
    for profile scanners. The sweeps start at ``count`` evenly spaced times of campaign 0
    between 20 % and 80 % of the drive, away from the street's ends.
    """
    from ..simulation.campaign import campaign, drive_duration, simulate_campaign
    from ..simulation.presets import SENSOR_PRESETS
    from ..simulation.scenes import build_scene

    try:
        sensor = SENSOR_PRESETS[preset]
    except KeyError:
        raise InputError(f'unknown sensor preset {preset!r}; choose one of {", ".join(SENSOR_PRESETS)}') from None
    if sweep is None:
        sweep = 1.0 / sensor.scan_rate_hz if sensor.pattern == 'spinning' else 1.0
    scene = build_scene(scene_name, seed)
    duration = drive_duration(scene, campaign(scene, 0), sensor)
    out = []
    for k, t0 in enumerate(np.linspace(0.2, 0.8, count) * duration):
        cloud = simulate_campaign(scene, 0, sensor, window=(float(t0), float(t0) + sweep))
        origin = cloud.sensor_origins.mean(axis=0)
        out.append(measure(cloud.xyz, origin, name=f'{preset} sweep {k}', seed=seed + k))
    return out


#: Where the real samples are: ``../shared/data/real`` beside the repository.
REAL_DATA = Path(__file__).resolve().parents[2].parent / 'shared' / 'data' / 'real'
#: The real files measured, with what they are.
REAL_FILES = {
    'av2_7fab_sweep0.ply': 'AV2 sweep 0 (real)',
    'av2_7fab_sweep1.ply': 'AV2 sweep 1 (real)',
    'av1_sweep.ply': 'AV1 sweep (real)',
}


#: Range bands of the cell densities in the table, metres.
BANDS = ((5.0, 10.0), (10.0, 15.0), (15.0, 25.0))


def _row(label: str, f: CloudFigures) -> str:
    d = f.density
    dens = f'{np.median(d):.0f} ({d.min():.0f}-{d.max():.0f})' if len(d) else '-'
    bands = ' / '.join('-' if np.isnan(v) else f'{v:.0f}' for v in (f.density_between(a, b) for a, b in BANDS))
    dist = f.distances
    ranges = f'{dist.min():.0f}-{dist.max():.0f}' if len(dist) else '-'
    return (f'| {label} | {f.n_points:,} | {len(f.walls)} | {f.wall_points:,} | {ranges} | {dens} | {bands} | '
            f'{1000 * f.median_patch_std:.1f} ({len(f.patch_std)}) | {100 * f.behind_share:.1f} % |')


def main(argv: list[str] | None = None) -> int:
    """Print the realism table (``python -m uncertain_facade_map.evaluation.realism``)."""
    parser = argparse.ArgumentParser(description='Wall density and planar-patch residual spread of the real '
                                                 'samples and of simulated sweeps of the sensor presets.')
    parser.add_argument('--real', type=Path, default=REAL_DATA, help=f'folder of the real samples (default {REAL_DATA})')
    parser.add_argument('--presets', default='av2,vmx250',
                        help='sensor presets to simulate, comma-separated (default av2,vmx250)')
    parser.add_argument('--scene', default='street_hard', help='scene the presets drive (default street_hard)')
    parser.add_argument('--sweeps', type=int, default=4, help='simulated sweeps per preset (default 4)')
    parser.add_argument('--seed', type=int, default=0)
    args = parser.parse_args(argv)
    from ..simulation.presets import SENSOR_PRESETS

    print('| cloud | points per sweep | walls | wall points | wall distance, m | density, pts/m² per sweep: '
          'median (range) over walls | cell density at ' + ' / '.join(f'{a:.0f}-{b:.0f}' for a, b in BANDS)
          + ' m: median | patch residual std, mm: median (patches) | points seen through the walls |')
    print('|---|---:|---:|---:|---:|---:|---:|---:|---:|')
    for name, label in REAL_FILES.items():
        path = args.real / name
        if path.exists():
            print(_row(label, measure_file(path, seed=args.seed)), flush=True)
        else:
            print(f'| {label} | absent: {path} | | | | | | | |')
    for preset in [p for p in args.presets.split(',') if p]:
        sweeps = simulated_sweeps(preset, args.scene, args.seed, args.sweeps)
        sensor = SENSOR_PRESETS[preset]
        what = (f'{args.sweeps} sweeps of 0.1 s' if sensor.pattern == 'spinning'
                else f'{args.sweeps} x 1 s of drive (5 m)')
        print(_row(f'{preset} on {args.scene}, {what} (simulated)', pooled(preset, sweeps)), flush=True)
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
