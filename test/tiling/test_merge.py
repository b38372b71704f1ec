"""merge_maps and subset_map: cutting a map by building and merging the pieces gives the
same answers (façades renumbered), shared labels and mismatched maps refused. About 6 s."""

import dataclasses

import numpy as np
import pytest

from uncertain_facade_map.errors import InputError
from uncertain_facade_map.params import MapParams, QueryConfig
from uncertain_facade_map.pipeline.step7_queries import ANSWER_FIELDS
from uncertain_facade_map.tiling.tiled_map import merge_maps, subset_map


@pytest.fixture(scope='module')
def whole(small_whole):
    return small_whole


def facade_map_of(merged, whole):
    """(F,) id in ``whole`` of each façade of ``merged`` (same building and frame)."""
    out = []
    for f in merged.facades:
        same = [g.facade_id for g in whole.facades if g.building == f.building and g.frame is f.frame]
        assert len(same) == 1
        out.append(same[0])
    return np.array(out, dtype=np.int32)


def probe_points(fmap, n=20000, seed=0):
    pts = np.vstack(list(fmap.points.values()))
    rng = np.random.default_rng(seed)
    near = pts[rng.choice(len(pts), n // 2)] + rng.normal(0, 0.3, (n // 2, 3))
    box = rng.uniform(pts.min(0) - 2, pts.max(0) + 2, (n - n // 2, 3))
    return np.vstack([near, box])


def assert_same_answers(a, b, ids):
    """``a`` answered by the merged map (façade ids ``ids`` maps to ``b``'s), ``b`` by the whole."""
    fa = np.where(a.facade >= 0, ids[np.maximum(a.facade, 0)], -1)
    np.testing.assert_array_equal(fa, b.facade)
    for key in ANSWER_FIELDS[1:]:
        np.testing.assert_array_equal(getattr(a, key), getattr(b, key), err_msg=key)


@pytest.mark.parametrize('config', [QueryConfig(surface='raster'), QueryConfig()])
def test_cut_and_merged_answers_equal_the_whole(whole, config):
    assert len(whole.buildings) == 2
    parts = [subset_map(whole, [b]) for b in reversed(whole.buildings)]  # merged in another order
    for part, b in zip(parts, reversed(whole.buildings)):
        assert [f.facade_id for f in part.facades] == list(range(len(part.facades)))
        assert part.buildings == [b]
    merged = merge_maps(parts)
    assert merged.buildings == whole.buildings and len(merged.facades) == len(whole.facades)
    assert [f.facade_id for f in merged.facades] == list(range(len(merged.facades)))
    assert merged.n_stored == whole.n_stored and merged.occupancy_ == whole.occupancy_
    assert merged.registration_var_ == whole.registration_var_
    xyz = probe_points(whole)
    assert_same_answers(merged.query(xyz, config, 0.1), whole.query(xyz, config, 0.1), facade_map_of(merged, whole))


def test_merge_refuses_shared_buildings_and_mismatches(whole):
    b = whole.buildings[0]
    with pytest.raises(InputError, match=f'sharing building {b}'):
        merge_maps([subset_map(whole, [b]), subset_map(whole, whole.buildings)])
    with pytest.raises(InputError, match='at least one'):
        merge_maps([])
    other = subset_map(whole, [whole.buildings[1]])
    moved = dataclasses.replace(other, map_origin=other.map_origin + 1.0)
    with pytest.raises(InputError, match='map origins'):
        merge_maps([subset_map(whole, [b]), moved])
    params = dataclasses.replace(MapParams(), seed=7)
    with pytest.raises(InputError, match='different parameters'):
        merge_maps([subset_map(whole, [b]), dataclasses.replace(other, params=params)])
    with pytest.raises(InputError, match='no building 999'):
        subset_map(whole, [999])


def test_merge_of_one_map_answers_as_it(whole):
    merged = merge_maps([whole])
    xyz = probe_points(whole, 4000)
    ids = np.arange(len(whole.facades), dtype=np.int32)
    assert_same_answers(merged.query(xyz), whole.query(xyz), ids)
