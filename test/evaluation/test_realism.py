"""The realism measurement on a wall of known density and noise, and the AV2 preset against
the real AV2 sample (skipped without ``../shared/data/real``)."""

from pathlib import Path

import numpy as np
import pytest

from uncertain_facade_map.errors import InputError
from uncertain_facade_map.evaluation.realism import REAL_DATA, measure, measure_file, pooled, simulated_sweeps

#: The real samples beside the repository (CC BY-NC-SA: read there, never copied).
REAL = Path(__file__).resolve().parents[3] / 'shared' / 'data' / 'real'


def synthetic_street(rng, spacing=0.1, sigma=0.01):
    """A 12 m x 6 m wall 10 m from the sensor on a 10 cm grid (100 points/m^2) with
    Gaussian noise across it, a ground plane and a scatter of clutter."""
    u, z = np.meshgrid(np.arange(0, 12, spacing), np.arange(0.05, 6, spacing))
    wall = np.stack([u.ravel() - 6, np.full(u.size, 10.0) + rng.normal(0, sigma, u.size), z.ravel()], axis=1)
    gx, gy = np.meshgrid(np.arange(-15, 15, 0.3), np.arange(-5, 9.9, 0.3))  # hidden behind the wall
    ground = np.stack([gx.ravel(), gy.ravel(), rng.normal(0, 0.01, gx.size)], axis=1)
    clutter = rng.uniform([-15, -5, 0], [15, 9, 4], size=(2000, 3))
    rooms = rng.uniform([-4, 10.5, 1.0], [4, 14, 4.0], size=(300, 3))  # seen through windows
    return np.vstack([wall, ground, clutter, rooms]), len(wall)


def test_a_known_wall_gives_its_density_and_noise():
    rng = np.random.default_rng(0)
    xyz, n_wall = synthetic_street(rng)
    f = measure(xyz, np.array([0.0, 0.0, 1.8]))
    assert len(f.walls) == 1
    wall = f.walls[0]
    assert wall.distance == pytest.approx(10.0, abs=0.02)
    assert abs(wall.normal[1]) == pytest.approx(1.0, abs=1e-3) and wall.normal[1] < 0  # towards the sensor
    assert wall.width == pytest.approx(11.9, abs=0.1)
    # The wall's points above 0.5 m over the ground, with a few clutter points in the band.
    assert len(wall.members) == pytest.approx(n_wall * 5.45 / 5.95, rel=0.02)
    # 100 points/m^2; the cells along the wall's edges are partly filled, which lowers it a little.
    assert 90.0 < f.median_density <= 100.0
    assert f.density_between(9.0, 20.0) == pytest.approx(100.0)  # full cells hold 100 points
    assert np.isnan(f.density_between(30.0, 40.0))
    assert f.median_patch_std == pytest.approx(0.01, rel=0.1)
    assert f.behind[0] == 300 and f.behind_share == pytest.approx(300 / len(wall.members))


def test_no_walls_no_figures_and_bad_input_refused():
    rng = np.random.default_rng(1)
    f = measure(rng.uniform(-10, 10, size=(3000, 3)), np.zeros(3))
    assert f.walls == () and np.isnan(f.median_density) and np.isnan(f.median_patch_std)
    with pytest.raises(InputError):
        measure(np.zeros((0, 3)), np.zeros(3))
    with pytest.raises(InputError):
        simulated_sweeps('no-such-sensor')


@pytest.mark.skipif(not (REAL / 'av2_7fab_sweep0.ply').exists(), reason='the real samples are not beside the repository')
def test_av2_preset_is_within_a_factor_of_the_real_av2_sweep():
    assert REAL_DATA.resolve() == REAL.resolve() or not REAL_DATA.exists()
    real = measure_file(REAL / 'av2_7fab_sweep0.ply')
    # The real sweep: see the table of python -m uncertain_facade_map.evaluation.realism.
    assert len(real.walls) >= 10
    assert 15 < real.median_density < 30 and 0.018 < real.median_patch_std < 0.03
    sim = pooled('av2', simulated_sweeps('av2', 'street_hard', count=2))
    assert 0.75 < sim.n_points / real.n_points < 1.33
    for near, far in ((5.0, 10.0), (10.0, 15.0)):
        assert 0.5 < sim.density_between(near, far) / real.density_between(near, far) < 2.0
    assert 0.5 < sim.median_density / real.median_density < 2.0
    assert 0.67 < sim.median_patch_std / real.median_patch_std < 1.5
    assert 0.5 < sim.behind_share / real.behind_share < 2.0  # returns through windows
