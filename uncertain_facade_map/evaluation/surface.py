"""Accuracy and calibration of a façade map against a simulated scene's exact truth.

For every façade model, the cell centres of its raster inside the extent of its points
are compared with the true surface along the model's own normal
(:meth:`~.scene.Scene.true_surface_along`). Cells within ``observed_radius`` of one of
the façade's points (on the plane) are *observed*; cells further than
``occluded_radius`` are *occluded* (shadows, gaps). Truth that belongs to another façade
of the scene than the one the model façade stands for (around a corner, beyond the end of
a side wall) is left out; the model façade stands for the scene façade facing the same
way whose plane is nearest.

Depth steps (a window edge, a balcony's outline) are scored apart: a cell is *at a step*
when the truth ``step_radius`` to its left, right, below or above differs from its own by
more than ``step_height``. The main figures (RMSE, coverage) are over observed cells off
the steps; the same figures over all observed cells are reported beside them, and the
step test of the issue (no smearing beyond one block) is :func:`step_smear`.

On a hard scene (``street_hard``, ...; :mod:`..simulation.walls`) the truth is the wall as
built: bowed, leaning and undulating; the plaster texture, the returns from inside rooms
through windows and the mixed returns at edges are measurement artefacts, i.e. noise and
outliers with respect to it (the artefacts carry ``gt_outlier`` > 0).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from ..mapping.facade_map import FacadeMap, stored_mask
from ..pipeline.step7_queries import assign_facades, surface_at
from ..simulation.scene import Scene

Z95 = 1.959963984540054
#: A cell is at a depth step when the truth this far (m) to its left, right, below or above ...
STEP_RADIUS = 0.2
#: ... differs from its own by more than this (m) (also the benchmark's test on simulated scenes).
STEP_HEIGHT = 0.03


@dataclass
class SurfaceEvaluation:
    """Figures of one map against the truth.

    Attributes:
        observed_rmse: RMSE of the mean surface in observed cells, metres.
        observed_coverage: share of observed true surface points inside the 95 % interval.
        occluded_coverage: the same in occluded cells.
        occluded_distance: (M,) distance of each compared cell (near or far) to the nearest
            point of its façade, metres.
        occluded_var: (M,) variance there, m^2.
        occluded_var_share: (M,) that variance over its façade's global prior variance (the
            most a façade's variance can be), so that façades can be compared.
        all_rmse: RMSE over all observed cells, steps included, metres.
        all_coverage: coverage over all observed cells, steps included.
        n_observed: number of observed cells off the steps compared.
        n_occluded: number of occluded cells compared.
        per_facade: per façade id, (n observed, rmse, coverage).
    """

    observed_rmse: float
    observed_coverage: float
    occluded_coverage: float
    occluded_distance: np.ndarray
    occluded_var: np.ndarray
    occluded_var_share: np.ndarray
    all_rmse: float
    all_coverage: float
    n_observed: int
    n_occluded: int
    per_facade: dict = field(default_factory=dict)

    def variance_by_distance(self, edges: tuple[float, ...] = (0.0, 0.1, 0.2, 0.3, 0.6, 100.0)
                             ) -> list[tuple[float, float, int]]:
        """Mean variance share (variance over the façade's global prior variance) of cells per
        distance bin to the data: [(lower edge, mean share, count)]."""
        out = []
        for lo, hi in zip(edges[:-1], edges[1:]):
            m = (self.occluded_distance >= lo) & (self.occluded_distance < hi)
            if m.any():
                out.append((lo, float(self.occluded_var_share[m].mean()), int(m.sum())))
        return out


def outlier_removal(fmap: FacadeMap, points: np.ndarray) -> tuple[int, int, int, int]:
    """How many injected outliers and inliers the map rejected.

    Args:
        fmap: the map, built from ``points`` in their order, labelled by ``building_id``.
        points: structured building points with the fields ``building_id`` and ``gt_outlier``
            (any non-zero code is an outlier: clutter, glass or mixed returns).

    Returns:
        ``(outliers rejected, outliers, inliers rejected, inliers)`` over the points the map
        stored (the others were thinned, ``update.store_voxel``, ``update.store_spacing``); rejected means on no
        façade or removed by the outlier test (:meth:`FacadeMap.rejected`).
    """
    removed = total = false_alarms = inliers = 0
    for b in fmap.buildings:
        rejected = fmap.rejected(b)
        mine = points[points['building_id'] == b]
        stored = stored_mask(np.stack([mine['x'], mine['y'], mine['z']], 1).astype(np.float64), fmap.params)
        outlier = mine['gt_outlier'][stored] != 0
        removed += int(rejected[outlier].sum())
        total += int(outlier.sum())
        false_alarms += int(rejected[~outlier].sum())
        inliers += int((~outlier).sum())
    return removed, total, false_alarms, inliers


def _matching_facade(scene: Scene, model) -> int:
    """The scene façade a model façade stands for: facing the same way, nearest plane."""
    best, best_gap = -1, np.inf
    for truth in scene.facades:
        if truth.building_id != model.building or truth.frame.n @ model.frame.normal < 0.9:
            continue
        gap = abs((model.frame.origin - truth.frame.origin) @ truth.frame.n)
        if gap < best_gap:
            best, best_gap = truth.facade_id, gap
    return best


def evaluate_surface(fmap: FacadeMap, scene: Scene, observed_radius: float = 0.1, occluded_radius: float = 0.3,
                     step_radius: float = STEP_RADIUS, step_height: float = STEP_HEIGHT, max_cells: int = 40_000,
                     seed: int = 0) -> SurfaceEvaluation:
    """Compare a map's surfaces with the scene's truth.

    Args:
        fmap: the map (built from the scene's points, building ids as in the scene).
        scene: the simulated scene.
        observed_radius: cells this close to a point of their façade are observed, metres.
        occluded_radius: cells further than this from every point are occluded, metres.
        step_radius: how far around a cell a depth step is looked for, metres.
        step_height: a depth change larger than this is a step, metres.
        max_cells: at most this many cells per façade are compared (a random draw).
        seed: seed of the draw.

    Returns:
        The figures.
    """
    rng = np.random.default_rng(seed)
    band_back, band_front = fmap.params.extraction.band_back, fmap.params.extraction.band_front
    errs, cover, occ_cover, occ_dist, occ_var, occ_share, all_errs, all_cover = [], [], [], [], [], [], [], []
    per_facade = {}
    for b in fmap.buildings:
        points = fmap.points[b]
        models = [f for f in fmap.facades if f.building == b]
        which, uvd = assign_facades(models, points, band_back, band_front)
        for i, f in enumerate(models):
            own = uvd[which == i, :2]
            if len(own) < 10:
                continue
            u0, u1, v0, v1 = f.extent
            cells = f.surface.centres()
            cells = cells[(cells[:, 0] >= u0) & (cells[:, 0] <= u1) & (cells[:, 1] >= v0) & (cells[:, 1] <= v1)]
            if len(cells) > max_cells:
                cells = cells[rng.choice(len(cells), max_cells, replace=False)]
            dist, _ = cKDTree(own).query(cells)
            mean, var = surface_at(f.surface, cells)
            world = f.frame.to_world(np.c_[cells, np.zeros(len(cells))])
            normals = np.tile(f.frame.normal, (len(cells), 1))
            truth, hit_facade = scene.true_surface_hits(world, normals, f.building, reach=band_front + 1.0)
            ok = (np.isfinite(truth) & (truth >= -band_back) & (truth <= band_front)
                  & (hit_facade == _matching_facade(scene, f)))
            smooth = np.ones(len(cells), dtype=bool)
            for axis in range(2):
                for sign in (-1.0, 1.0):
                    shift = np.zeros(3)
                    shift[axis] = sign * step_radius
                    other = scene.true_surface_along(world + shift @ f.frame.axes, normals, f.building,
                                                     reach=band_front + 1.0)
                    smooth &= np.abs(other - truth) <= step_height
            err = mean - truth
            inside = np.abs(err) <= Z95 * np.sqrt(var)
            all_errs.append(err[ok & (dist <= observed_radius)])
            all_cover.append(inside[ok & (dist <= observed_radius)])
            obs = ok & smooth & (dist <= observed_radius)
            occ = ok & (dist > occluded_radius)
            errs.append(err[obs])
            cover.append(inside[obs])
            occ_cover.append(inside[occ])
            every = ok  # distance-variance relation over all compared cells, near and far
            occ_dist.append(dist[every])
            occ_var.append(var[every])
            occ_share.append(var[every] / f.global_var_)
            if obs.any():
                per_facade[f.facade_id] = (int(obs.sum()), float(np.sqrt(np.mean(err[obs] ** 2))),
                                           float(inside[obs].mean()))
    e = np.concatenate(errs) if errs else np.empty(0)
    c = np.concatenate(cover) if cover else np.empty(0, bool)
    oc = np.concatenate(occ_cover) if occ_cover else np.empty(0, bool)
    ae = np.concatenate(all_errs) if all_errs else np.empty(0)
    ac = np.concatenate(all_cover) if all_cover else np.empty(0, bool)
    return SurfaceEvaluation(
        observed_rmse=float(np.sqrt(np.mean(e**2))) if len(e) else float('nan'),
        observed_coverage=float(c.mean()) if len(c) else float('nan'),
        occluded_coverage=float(oc.mean()) if len(oc) else float('nan'),
        occluded_distance=np.concatenate(occ_dist) if occ_dist else np.empty(0),
        occluded_var=np.concatenate(occ_var) if occ_var else np.empty(0),
        occluded_var_share=np.concatenate(occ_share) if occ_share else np.empty(0),
        all_rmse=float(np.sqrt(np.mean(ae**2))) if len(ae) else float('nan'),
        all_coverage=float(ac.mean()) if len(ac) else float('nan'),
        n_observed=int(len(e)), n_occluded=int(len(oc)), per_facade=per_facade)


def main(argv: list[str] | None = None) -> int:
    """Print the figures of a map of a simulated scene (``python -m ...simulation.evaluation``)."""
    import argparse
    import time

    from ..mapping.facade_map import FacadeMap
    from ..params import MapParams
    from ..simulation.campaign import simulate_campaign
    from ..simulation.presets import SENSOR_PRESETS
    from ..simulation.scenes import SCENES, build_scene

    parser = argparse.ArgumentParser(description='Map a simulated scene and print its figures against the truth.')
    parser.add_argument('--scene', default='small', choices=tuple(SCENES),
                        help='a clean scene, or NAME_hard: walls as built and a real error model')
    parser.add_argument('--sensor', choices=tuple(SENSOR_PRESETS), help="sensor preset (default: the scene's)")
    parser.add_argument('--seed', type=int, default=0)
    parser.add_argument('--batch', type=float, default=0.0,
                        help='map incrementally, in batches of this many seconds of the drive (default: one batch)')
    args = parser.parse_args(argv)
    scene = build_scene(args.scene, args.seed)
    cloud = simulate_campaign(scene, 0, SENSOR_PRESETS[args.sensor] if args.sensor else None)
    pts = cloud.points[cloud.points['class'] == 1]
    pts = pts[np.argsort(pts['time'], kind='stable')]
    xyz = np.stack([pts['x'], pts['y'], pts['z']], 1)
    origins = np.stack([pts['origin_x'], pts['origin_y'], pts['origin_z']], 1)
    if args.batch > 0:
        bounds = np.searchsorted(pts['time'], np.arange(pts['time'][0], pts['time'][-1] + args.batch, args.batch)[1:])
        bounds = np.unique(np.r_[0, bounds, len(pts)])
    else:
        bounds = np.array([0, len(pts)])
    fmap = FacadeMap(MapParams(), cloud.map_origin)
    started = time.perf_counter()
    slowest = 0.0
    for a, b in zip(bounds[:-1], bounds[1:]):
        if b > a:
            fmap.add_points(xyz[a:b], pts['building_id'][a:b], origins[a:b], defer=len(bounds) > 2)
            slowest = max(slowest, fmap.last_update.get('seconds', 0.0))
    streamed = time.perf_counter() - started
    fmap.flush()
    seconds = time.perf_counter() - started
    if len(bounds) > 2:
        print(f'{len(bounds) - 1} batches of {args.batch:g} s (updates of >= {fmap.params.update.batch_points:,} '
              f'points): {len(pts) / streamed:,.0f} building points/s while streaming, slowest update '
              f'{slowest:.2f} s; final flush {seconds - streamed:.1f} s')
    ev = evaluate_surface(fmap, scene)
    removed, total, false_alarms, inliers = outlier_removal(fmap, pts)
    print(f'scene {args.scene} seed {args.seed}: {len(cloud):,} points, {len(pts):,} building, '
          f'{len(fmap.facades)} façades, built in {seconds:.1f} s')
    print(f'observed, off steps: RMSE {ev.observed_rmse:.4f} m, 95 % coverage {ev.observed_coverage:.3f} '
          f'({ev.n_observed:,} cells)')
    print(f'observed, all:       RMSE {ev.all_rmse:.4f} m, 95 % coverage {ev.all_coverage:.3f}')
    print(f'occluded:            95 % coverage {ev.occluded_coverage:.3f} ({ev.n_occluded:,} cells)')
    print('variance / global prior variance by distance to data: '
          + ', '.join(f'>= {lo:g} m: {v:.3f} ({n})' for lo, v, n in ev.variance_by_distance()))
    print(f'outliers removed: {removed}/{total} = {removed / max(total, 1):.3f}; '
          f'inliers removed {false_alarms / max(inliers, 1):.3f}')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
