"""Figures of the localiser on a simulated scene: accuracy, NEES and time per scan.

Maps campaign 0 of a scene, takes seeded scans of campaign 1 (the other lane, driven the
other way) in the lidar frame (``test/localisation/map_scans.py``), perturbs each true pose
like GNSS in a street canyon (0.5-3 m, 1-5 degrees; ``test/localisation/plane_world.py``),
localises it through the map's own query and prints one line per scan and a summary::

    .venv/bin/python tools/localise_check.py --scene street --scans 30 --points 20000
    .venv/bin/python tools/localise_check.py --scene street --constant-variance 0.0004   # the map taken as exact
    .venv/bin/python tools/localise_check.py --scene street --correlation-length 0       # the plain Hessian

Errors are the truth as a perturbation of the estimate, in the covariance's convention (map
axes at the sensor); NEES is that error's squared Mahalanobis length under the output
covariance (chi-square with 6 degrees of freedom if consistent). Times are wall times of
localise(), queries included (the map's local surface is set up before the first scan).
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import numpy as np
from scipy.linalg import cho_factor, cho_solve
from scipy.stats import chi2

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / 'test' / 'localisation'))

from map_scans import sensor_scan  # noqa: E402
from plane_world import perturbed  # noqa: E402

from uncertain_facade_map.localisation import covariance_from_std, localise, map_query  # noqa: E402
from uncertain_facade_map.localisation.solver import centred_log  # noqa: E402
from uncertain_facade_map.mapping.facade_map import build_map  # noqa: E402
from uncertain_facade_map.params import LocaliseParams, MapParams  # noqa: E402
from uncertain_facade_map.simulation.campaign import simulate_campaign  # noqa: E402
from uncertain_facade_map.simulation.scenes import build_scene  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--scene', default='street')
    parser.add_argument('--scans', type=int, default=30)
    parser.add_argument('--points', type=int, default=20000, help='points per scan')
    parser.add_argument('--seed', type=int, default=1)
    parser.add_argument('--constant-variance', type=float, help='m^2 (row b: the map taken as exact)')
    parser.add_argument('--correlation-length', type=float, help='m (default: the parameter\'s)')
    parser.add_argument('--max-queries', type=int)
    args = parser.parse_args(argv)
    params = LocaliseParams()
    if args.correlation_length is not None:
        params = dataclasses.replace(params, correlation_length=args.correlation_length)
    if args.max_queries is not None:
        params = dataclasses.replace(params, max_queries=args.max_queries)
    scene = build_scene(args.scene, 0)
    mapped = simulate_campaign(scene, 0)
    pts = mapped.points[mapped.points['class'] == 1]
    started = time.perf_counter()
    fmap = build_map(np.stack([pts['x'], pts['y'], pts['z']], 1), pts['building_id'],
                     np.stack([pts['origin_x'], pts['origin_y'], pts['origin_z']], 1), MapParams(), mapped.map_origin)
    print(f'map of {args.scene} campaign 0: {len(fmap.facades)} façades in {time.perf_counter() - started:.1f} s')
    cloud = simulate_campaign(scene, 1)
    query = map_query(fmap)
    query(fmap.facades[0].frame.origin[None])  # the local surface's set-up
    prior_cov = covariance_from_std([2.0, 2.0, 2.0, *np.deg2rad([3.0, 3.0, 3.0])])
    rng = np.random.default_rng(args.seed)
    rows = []
    for k in range(args.scans):
        scan, truth = sensor_scan(scene, cloud, 1, rng.uniform(0.1, 0.9), args.points)
        prior = perturbed(truth, rng)
        est = localise(scan, prior, prior_cov, query, params, constant_variance=args.constant_variance)
        d = centred_log(truth, est.pose, est.pose[:3, 3])
        nees = float(d @ cho_solve(cho_factor(est.covariance), d))
        std = np.sqrt(np.diag(est.covariance))
        rows.append((np.hypot(d[0], d[1]), abs(d[2]), np.rad2deg(abs(d[5])), nees, est.seconds, est.queries,
                     est.converged))
        print(f'{k:3d} horizontal {rows[-1][0] * 100:6.1f} cm (std x {std[0] * 100:.1f} y {std[1] * 100:.1f}) '
              f'height {rows[-1][1] * 100:5.1f} cm yaw {rows[-1][2]:.3f} deg NEES {nees:9.1f} '
              f'{est.queries} queries {"converged" if est.converged else "NOT converged"} {est.seconds * 1e3:.0f} ms')
    r = np.array(rows, dtype=float)
    lo, hi = chi2.ppf([0.025, 0.975], 6)
    print(f'{args.scans} scans of {args.points:,} points: horizontal error median {np.median(r[:, 0]) * 100:.1f} cm, '
          f'p95 {np.percentile(r[:, 0], 95) * 100:.1f} cm; yaw median {np.median(r[:, 2]):.3f} deg, '
          f'p95 {np.percentile(r[:, 2], 95):.3f} deg; within 0.2 m and 1 deg: {np.mean((r[:, 0] < 0.2) & (r[:, 2] < 1)):.0%}')
    print(f'NEES median {np.median(r[:, 3]):.1f} (chi2(6) median {chi2.median(6):.1f}); inside the 95 % band '
          f'[{lo:.2f}, {hi:.1f}]: {np.mean((r[:, 3] > lo) & (r[:, 3] < hi)):.0%}; converged {np.mean(r[:, 6]):.0%}')
    print(f'time per scan: median {np.median(r[:, 4]) * 1e3:.0f} ms, {np.median(r[:, 5]):.0f} query calls')
    return 0


if __name__ == '__main__':
    sys.exit(main())
