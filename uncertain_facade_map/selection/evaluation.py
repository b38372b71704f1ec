"""Figures of the selection on real sweeps, against an independent wall picker.

``python -m uncertain_facade_map.selection.evaluation [PLY ...] [--map] [--simulated]`` prints, for each
cloud (default: the Argoverse sweeps in ``../shared/data/real/`` beside the repository and
the KITTI car lidar's in its ``car_lidar/``),
the points in and selected, the ground, the share of the picked wall points the selection
keeps (recall), the share of the selected points within 0.4 m of a picked wall point
(precision; a lower bound: the picker looks only within 40 m and for at most 12 walls),
the same two within 40 m, the time of the selection (its second run: a process's first
loads the compiled kernels), the share of a wall-only cloud (half of the picked wall
points, x, y, z only, as ``../shared/tools/real_check.py`` hands them to ``build``) that
is kept, and with ``--map`` the buildings and façades of the map built from the selected
points.

:func:`pick_walls` is the reference: sequential RANSAC of vertical planes through pairs of
points 1 to 6 m apart, on the points 0.5 m above the lowest point of their 2 m cell and
within 40 m of the sensor; a plane takes the points within 0.4 m of it, and its largest
piece without a gap of 1 m along it is a wall if it is 3 m wide, 2 m tall and holds 300
points. It shares no code and no step with the selection (no ground model, no windows), so
the figures measure one against the other.

``--simulated`` prints the selection's figures on simulated clouds against the simulator's
truth (:func:`simulated_figures`), each cloud selected alone as the node selects a scan: in
the map frame, with each point's sensor origin: the ``residential`` street scanned by the
``hdl64`` lidar (12 sweeps of 0.1 s, 2 s apart), the ``street`` scene scanned by the
mobile-mapping system (10 pieces of 3 s) and by the ``av2`` lidars (11 sweeps, 3 s apart),
each with the field-of-view rule and without it (``selection.fov_margin`` 0, the rule of
before). Recall is the share of the true wall points kept: the points of class building
on a façade (``gt_facade`` >= 0: the walls and their detail, not the roofs) that are no
clutter outlier (``gt_outlier`` 0); precision is the share of the kept points of class
building.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from ..params import SelectionConfig
from .building_points import select_building_points

#: The real sweeps, beside the repository (CC BY-NC-SA: read from there, never copied).
REAL_DATA = Path(__file__).resolve().parents[3] / 'shared' / 'data' / 'real'


def _lowest_in_cell(xyz: np.ndarray, cell: float = 2.0) -> np.ndarray:
    """(N,) lowest z of each point's square cell."""
    _, inverse = np.unique(np.floor(xyz[:, :2] / cell).astype(np.int64), axis=0, return_inverse=True)
    inverse = inverse.ravel()
    low = np.full(inverse.max() + 1, np.inf)
    np.minimum.at(low, inverse, xyz[:, 2])
    return low[inverse]


def pick_walls(xyz: np.ndarray, sensor: np.ndarray, seed: int = 3, max_walls: int = 12, hypotheses: int = 1500,
               reach: float = 40.0) -> np.ndarray:
    """(N,) bool mask of the points of vertical walls (see the module docstring).

    Args:
        xyz: (N, 3) points, metres, z up.
        sensor: (3,) sensor position, same frame.
        seed: seed of the hypotheses.
        max_walls: planes tried at most.
        hypotheses: plane hypotheses per plane.
        reach: only points this close to the sensor (in x, y) are candidates.
    """
    rng = np.random.default_rng(seed)
    above = xyz[:, 2] > _lowest_in_cell(xyz) + 0.5
    near = np.hypot(*(xyz[:, :2] - sensor[:2]).T) < reach
    free = above & near
    walls = np.zeros(len(xyz), dtype=bool)
    for _ in range(max_walls):
        pool = np.flatnonzero(free)
        if len(pool) < 500:
            break
        pairs = rng.choice(pool, size=(hypotheses, 2))
        step = xyz[pairs[:, 1], :2] - xyz[pairs[:, 0], :2]
        length = np.hypot(step[:, 0], step[:, 1])
        ok = (length >= 1.0) & (length <= 6.0)
        if not ok.any():
            break
        normals = np.stack([-step[ok, 1], step[ok, 0]], axis=1) / length[ok, None]
        anchors = xyz[pairs[ok, 0], :2]
        pts = xyz[pool, :2]
        scores = np.concatenate([(np.abs((pts[None] - anchors[k:k + 64, None]) @ normals[k:k + 64, :, None])[..., 0]
                                  < 0.15).sum(axis=1) for k in range(0, len(normals), 64)])
        best = int(np.argmax(scores))
        if scores[best] < 400:
            break
        n, p0 = normals[best], anchors[best]
        band = above & free & (np.abs((xyz[:, :2] - p0) @ n) < 0.4)
        free &= ~band
        members = np.flatnonzero(band)
        u = (xyz[members, :2] - p0) @ np.array([-n[1], n[0]])
        order = np.argsort(u)
        cuts = np.flatnonzero(np.diff(u[order]) > 1.0) + 1
        pieces = np.split(order, cuts)
        piece = members[max(pieces, key=len)]
        width = np.ptp(u[np.isin(members, piece)])
        if width >= 3.0 and np.ptp(xyz[piece, 2]) >= 2.0 and len(piece) >= 300:
            walls[piece] = True
    return walls


def _read(path: Path) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
    """Points, their sensor origins (or None) and the sensor position of a cloud file."""
    from ..io.clouds import read_cloud

    cloud = read_cloud(path)
    origins = cloud.sensor_origins
    sensor = origins.mean(axis=0) if origins is not None else np.r_[np.median(cloud.xyz[:, :2], axis=0), 0.0]
    return cloud.xyz, origins, sensor


def evaluate(path: Path, params: SelectionConfig | None = None, with_map: bool = False) -> dict[str, float]:
    """The figures of one cloud file (see the module docstring)."""
    params = params or SelectionConfig()
    xyz, origins, sensor = _read(path)
    walls = pick_walls(xyz, sensor)
    select_building_points(xyz, origins, params)  # not timed (see the module docstring)
    started = time.perf_counter()
    found = select_building_points(xyz, origins, params)
    seconds = time.perf_counter() - started
    mask = found.mask
    dist, _ = cKDTree(xyz[walls]).query(xyz[mask])
    close = np.hypot(*(xyz[:, :2] - sensor[:2]).T) < 40.0
    dist40, _ = cKDTree(xyz[walls]).query(xyz[mask & close])
    half = walls & (np.random.default_rng(0).random(len(xyz)) < 0.5)
    cut = select_building_points(xyz[half], None, params)
    forced = select_building_points(xyz[half], None, dataclasses.replace(params, min_ground_share=0.0))
    out = {'points': len(xyz), 'selected': int(mask.sum()), 'ground': int(found.ground.sum()),
           'wall_points': int(walls.sum()), 'recall': float(mask[walls].mean()),
           'precision': float((dist < 0.4).mean()), 'recall_40m': float(mask[walls & close].mean()),
           'precision_40m': float((dist40 < 0.4).mean()), 'seconds': seconds,
           'wall_only_kept': float(cut.mask.mean()), 'wall_only_forced': float(forced.mask.mean())}
    if with_map:
        from ..mapping.facade_map import FacadeMap
        from ..params import MapParams

        for name, keep in (('', mask), ('_unselected', np.ones(len(xyz), dtype=bool))):
            fmap = FacadeMap(MapParams())
            fmap.add_points(xyz[keep], None, None if origins is None else origins[keep])
            out['buildings' + name], out['facades' + name] = len(fmap.buildings), len(fmap.facades)
    return out


#: The simulated set-ups of ``--simulated``: name, scene, sensor preset (None: the scene's),
#: seconds of each cloud, seconds between their starts.
SIMULATED = (('residential/hdl64', 'residential', None, 0.1, 2.0), ('street/mms', 'street', None, 3.0, 3.0),
             ('street/av2', 'street', 'av2', 0.1, 3.0))


def simulated_clouds(scene: str, sensor: str | None = None, period: float = 0.1, every: float = 2.0, seed: int = 0,
                     index: int = 0) -> list[np.ndarray]:
    """Clouds of one simulated drive, as a sensor sends them.

    Args:
        scene: a scene of :data:`~uncertain_facade_map.simulation.scenes.SCENES`.
        sensor: a preset of :data:`~uncertain_facade_map.simulation.presets.SENSOR_PRESETS`;
            None for the scene's own.
        period: seconds of each cloud (0.1: a sweep of a 10 Hz lidar).
        every: seconds between the starts of the clouds (from 0.5 s into the drive on).
        seed: the scene's seed.
        index: the campaign.

    Returns:
        The clouds' points (structured arrays with the simulator's fields, map frame).
    """
    from ..simulation.campaign import campaign, drive_duration, simulate_campaign
    from ..simulation.presets import SCENE_SENSORS, SENSOR_PRESETS
    from ..simulation.scenes import build_scene

    built = build_scene(scene, seed)
    preset = SENSOR_PRESETS[sensor] if sensor else SCENE_SENSORS[scene]
    duration = drive_duration(built, campaign(built, index), preset)
    return [simulate_campaign(built, index, preset, window=(t, t + period)).points
            for t in np.arange(0.5, duration - period, every)]


def simulated_figures(clouds: list[np.ndarray], params: SelectionConfig | None = None) -> dict[str, float]:
    """The selection's figures on simulated clouds, each selected alone (see the module docstring).

    Args:
        clouds: structured arrays with ``x, y, z``, ``origin_x, origin_y, origin_z``,
            ``class``, ``gt_facade`` and ``gt_outlier`` (the simulator's fields).
        params: the selection's parameters; defaults if None.

    Returns:
        ``recall`` and ``precision`` over all clouds, ``kept``, ``walls`` (true wall points),
        ``points``, ``seconds`` (median time of one selection) and ``kept_share`` (the least
        share of its non-ground points a cloud kept).
    """
    kept = kept_building = walls = found = 0
    seconds, shares = [], []
    for p in clouds:
        xyz = np.stack([p['x'], p['y'], p['z']], axis=1)
        origins = np.stack([p['origin_x'], p['origin_y'], p['origin_z']], axis=1)
        started = time.perf_counter()
        selection = select_building_points(xyz, origins, params)
        seconds.append(time.perf_counter() - started)
        wall = (p['class'] == 1) & (p['gt_facade'] >= 0) & (p['gt_outlier'] == 0)
        walls += int(wall.sum())
        found += int((selection.mask & wall).sum())
        kept += selection.kept
        kept_building += int((selection.mask & (p['class'] == 1)).sum())
        shares.append(selection.kept / max(selection.non_ground, 1))
    return {'recall': found / max(walls, 1), 'precision': kept_building / max(kept, 1), 'kept': kept, 'walls': walls,
            'points': sum(len(p) for p in clouds), 'seconds': float(np.median(seconds)),
            'kept_share': float(min(shares))}


def main(argv: list[str] | None = None) -> int:
    """Print the figures of each cloud (see the module docstring)."""
    parser = argparse.ArgumentParser(prog='python -m uncertain_facade_map.selection.evaluation',
                                     description=__doc__.split('\n\n')[0])
    parser.add_argument('clouds', nargs='*', type=Path, help='cloud files (default: ../shared/data/real/*.ply and car_lidar/*.ply)')
    parser.add_argument('--map', action='store_true', help='also build maps from all and from the selected points')
    parser.add_argument('--simulated', action='store_true',
                        help='the figures on simulated clouds against their truth instead (see above)')
    args = parser.parse_args(argv)
    if args.simulated:
        for name, scene, sensor, period, every in SIMULATED:
            clouds = simulated_clouds(scene, sensor, period, every)
            for rule, params in (('', SelectionConfig()), (' (without the field-of-view rule)',
                                                           SelectionConfig(fov_margin=0.0))):
                r = simulated_figures(clouds, params)
                print(f'{name}{rule}: {len(clouds)} clouds, {r["points"]:,} points, {r["walls"]:,} true wall points, '
                      f'{r["kept"]:,} kept: recall {r["recall"]:.3f}, precision {r["precision"]:.3f}, least kept '
                      f'share of the non-ground points {r["kept_share"]:.3f}, {r["seconds"]:.2f} s a cloud (median)',
                      flush=True)
        return 0
    paths = args.clouds or sorted(REAL_DATA.glob('*.ply')) + sorted(REAL_DATA.glob('car_lidar/*.ply'))
    if not paths:
        print(f'no clouds given and none in {REAL_DATA}', file=sys.stderr)
        return 2
    for path in paths:
        r = evaluate(path, with_map=args.map)
        print(f'{path.name}: {r["points"]:,} points, {r["selected"]:,} selected, {r["ground"]:,} ground, '
              f'{r["seconds"]:.2f} s; {r["wall_points"]:,} picked wall points: recall {r["recall"]:.3f}, '
              f'precision {r["precision"]:.3f} (within 40 m: {r["recall_40m"]:.3f}, {r["precision_40m"]:.3f}); '
              f'wall-only cloud kept {r["wall_only_kept"]:.3f} (selection forced: {r["wall_only_forced"]:.3f})'
              + (f'; map {r["buildings"]} buildings, {r["facades"]} façades (all points: '
                 f'{r["buildings_unselected"]}, {r["facades_unselected"]})' if args.map else ''))
    return 0


if __name__ == '__main__':
    sys.exit(main())
