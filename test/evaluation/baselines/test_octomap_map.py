"""The OctoMap baseline (the real library through octomap-python) on a scanned wall."""

from __future__ import annotations

import numpy as np
import pytest
from support import WALL_Y, labelled_voxels, wall_scan

from uncertain_facade_map.errors import InputError
from uncertain_facade_map.evaluation.baselines.base import group_by_origin
from uncertain_facade_map.evaluation.baselines.octomap_map import OctoMapMethod
from uncertain_facade_map.evaluation.occupancy import pr_auc

pytest.importorskip('octomap')


@pytest.fixture(scope='module')
def fitted():
    hits, origins = wall_scan()
    return OctoMapMethod(0.1).fit(hits, origins)


def test_the_wall_is_occupied_the_space_before_it_free_and_the_rest_unknown(fitted):
    centres, on_wall = labelled_voxels(0.1)
    p = fitted.predict(centres)
    assert p.shape == (len(centres),) and np.all((p >= 0.12 - 1e-6) & (p <= 0.97 + 1e-6))
    # 16 000 rays on 60 m^2 of wall at 0.1 m: most wall voxels are hit, free space is
    # crossed (measured: mean p 0.71 on the wall and 0.19 before it, PR AUC 0.67; rays
    # grazing the wall's noisy voxels mark some of them free).
    assert p[on_wall].mean() > 0.65 and p[~on_wall].mean() < 0.25 and np.median(p[~on_wall]) < 0.13
    assert pr_auc(on_wall, p) > 0.6
    # Behind the wall and far away nothing was observed: unknown.
    behind = np.array([[5.05, WALL_Y + 1.05, 2.05], [50.0, 50.0, 50.0]])
    assert fitted.predict(behind).tolist() == [0.5, 0.5]


def test_a_single_ray_follows_the_log_odds_of_the_paper():
    # One hit 1 m away: the end voxel takes prob_hit once, the voxels on the way prob_miss.
    method = OctoMapMethod(0.1).fit(np.array([[1.05, 0.05, 0.05]]), np.array([[0.05, 0.05, 0.05]]))
    p = method.predict(np.array([[1.05, 0.05, 0.05], [0.55, 0.05, 0.05]]))
    np.testing.assert_allclose(p, [0.7, 0.4], atol=1e-5)
    # Repeated hits clamp at 0.97 (Eq. 5).
    # Within one scan (one origin) a voxel is updated once, however many rays end in it.
    once = OctoMapMethod(0.1).fit(np.repeat([[1.05, 0.05, 0.05]], 20, 0), np.repeat([[0.05, 0.05, 0.05]], 20, 0))
    assert once.n_scans_ == 1 and once.predict(np.array([[1.05, 0.05, 0.05]]))[0] == pytest.approx(0.7, abs=1e-5)
    # Over 20 scans the hits add up and clamp at 0.97 (Eq. 5).
    origins = np.array([[0.05, 0.05, 0.05]]) + np.arange(20)[:, None] * np.array([[0.0, 0.0, 0.1]])
    clamped = OctoMapMethod(0.1, origin_quantum=0.05).fit(np.repeat([[1.05, 0.05, 0.05]], 20, 0), origins)
    assert clamped.n_scans_ == 20
    assert clamped.predict(np.array([[1.05, 0.05, 0.05]]))[0] == pytest.approx(0.97, abs=1e-4)


def test_rays_are_grouped_by_origin_in_input_order():
    origins = np.array([[0.0, 0, 0], [5.0, 0, 0], [0.01, 0, 0], [5.02, 0, 0], [9.0, 0, 0]])
    order, starts, mean = group_by_origin(origins, 0.05)
    assert order.tolist() == [0, 2, 1, 3, 4] and starts.tolist() == [0, 2, 4, 5]
    np.testing.assert_allclose(mean, [[0.005, 0, 0], [5.01, 0, 0], [9.0, 0, 0]])


def test_bad_use_is_refused(fitted):
    with pytest.raises(InputError, match='fit the method'):
        OctoMapMethod(0.1).predict(np.zeros((1, 3)))
    with pytest.raises(InputError, match='finite'):
        fitted.predict(np.full((1, 3), np.nan))
    for kwargs, match in (({'prob_hit': 0.4}, 'prob_hit'), ({'prob_miss': 0.6}, 'prob_miss'),
                          ({'clamp_min': 0.9, 'clamp_max': 0.5}, 'clamp_min'), ({'origin_quantum': 0}, 'origin_quantum'),
                          ({'prob_hit': 1.5}, 'probability')):
        with pytest.raises(InputError, match=match):
            OctoMapMethod(0.1, **kwargs)
    with pytest.raises(InputError, match='resolution'):
        OctoMapMethod(-0.1)
    with pytest.raises(InputError, match='local map-frame'):
        OctoMapMethod(0.1).fit(np.array([[5000.0, 0, 0]]), np.zeros((1, 3)))
