"""The model on real lidar sweeps (``../shared/data/real/``), against a local-plane map.

The sweeps are Argoverse data under CC BY-NC-SA 4.0: they are read where they lie, beside
the repository, never copied into it; without them these tests skip. The hold-out protocol
is the independent checker's (``../shared/tools/real_check.py``: its wall pick, 50 % of
the wall points mapped, one 2 m x 2 m patch cut out of every wall longer than 8 m), run
here in-process on the core. Figures measured at this commit (``real_check.py``):
see docs/real-data.md, "Real scans".
"""

import importlib.util
import sys

import numpy as np
import pytest
from support import REPO

from uncertain_facade_map.mapping.facade_map import build_map
from uncertain_facade_map.params import MapParams
from uncertain_facade_map.pipeline.step7_queries import query_points

SHARED = REPO.parent / 'shared'
REAL = SHARED / 'data' / 'real'
CHECKER = SHARED / 'tools' / 'real_check.py'

pytestmark = pytest.mark.skipif(not (CHECKER.exists() and (REAL / 'av2_7fab_sweep0.ply').exists()),
                                reason='the real sweeps (../shared/data/real) are not here')


def _checker():
    spec = importlib.util.spec_from_file_location('real_check', CHECKER)
    module = importlib.util.module_from_spec(spec)
    sys.modules.setdefault('real_check', module)
    spec.loader.exec_module(module)
    return module


def _split(name: str):
    rc = _checker()
    xyz, origins = rc.read_ply(str(REAL / name))
    sensor = origins.mean(0) if origins is not None else np.array([0.0, 0.0, 1.8])
    rng = np.random.default_rng(3)
    walls = rc.walls(xyz, sensor, rng)
    wall = np.zeros(len(xyz), bool)
    patch = np.zeros(len(xyz), bool)
    for _, p0, piece, u_axis in walls:
        wall |= piece
        u, v = (xyz[piece] - p0) @ u_axis, xyz[piece, 2]
        if np.ptp(u) > 8:
            pu, pv = u.min() + 0.5 * np.ptp(u), v.min() + 0.4 * np.ptp(v)
            sel = np.flatnonzero(piece)
            patch[sel[(np.abs(u - pu) < 1.0) & (np.abs(v - pv) < 1.0)]] = True
    mapped = wall & (rng.random(len(xyz)) < 0.5) & ~patch
    return xyz, mapped, wall & ~mapped, patch


@pytest.mark.parametrize('name, max_rmse, min_cov', [
    ('av2_7fab_sweep0.ply', 0.070, 0.92),
    ('av2_7fab_sweep1.ply', 0.075, 0.93),
    ('av1_sweep.ply', 0.070, 0.92),
])
def test_held_out_wall_points(name, max_rmse, min_cov):
    """Observed areas: RMSE and 95 % coverage of the held-out points' signed distance.

    Before the wall relief, the estimated noise and the step faces the same protocol gave
    0.084, 0.086 and 0.074 m and coverage 0.88, 0.90, 0.91; the local plane gives
    0.035-0.040 m (the issue's bar is 0.8 x that, not reached yet)."""
    xyz, mapped, held, patch = _split(name)
    fmap = build_map(xyz[mapped], params=MapParams())
    ex = fmap.params.extraction
    q = query_points(fmap.facades, xyz[held], 0.1, ex.band_back, ex.band_front)
    observed = (q.facade >= 0) & ~patch[held]
    assert observed.mean() > 0.9
    s = q.signed_distance[observed]
    sd = np.sqrt(q.variance[observed] + q.noise_variance[observed])
    rmse = float(np.sqrt(np.mean(s**2)))
    assert rmse <= max_rmse
    assert np.mean(np.abs(s) <= 1.96 * sd) >= min_cov
    # The noise comes from the data: lidar centimetres, not the paper's fixed 2 cm everywhere.
    noise = np.sqrt([f.noise_var for f in fmap.facades])
    assert np.all((noise > 0.005) & (noise < 0.05)) and np.ptp(noise) > 0.005
    # Mapped without sensor origins (as the checker hands them over), every façade of
    # 500 points or more faces the sensor. Before the other buildings' points turned lone
    # walls, AV2 sweep 1's 5,400-point wall and three of AV1's six faced away.
    origins = _checker().read_ply(str(REAL / name))[1]
    sensor = origins.mean(0) if origins is not None else np.array([0.0, 0.0, 1.8])
    big = [f for f in fmap.facades if len(f.point_index) >= 500]
    assert len(big) >= 3 and all(f.frame.normal @ (sensor - f.frame.origin) > 0 for f in big)
