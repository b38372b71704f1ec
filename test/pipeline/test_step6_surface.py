"""Which cells a façade update computes again when the facets change (step 6, issue 37)."""

from types import SimpleNamespace

import numpy as np

from uncertain_facade_map.datatypes import cell_centres
from uncertain_facade_map.pipeline.step6_surface import _changed_cells

CELL = 0.1
SIZE = np.array([[0.5, 0.5]])  # one layer, blocks of 5 x 5 cells


def _old(facet: np.ndarray) -> SimpleNamespace:
    return SimpleNamespace(surface=SimpleNamespace(facet=facet), facets=SimpleNamespace(
        layer_of_facet=np.zeros(int(facet.max()) + 1, dtype=np.int32)))


def _changed(old_facet: np.ndarray, new_facet: np.ndarray):
    centres = cell_centres(np.zeros(2), CELL, new_facet.shape)
    return _changed_cells(_old(old_facet), (0, 0), new_facet, np.zeros(int(new_facet.max()) + 1, np.int32),
                          centres, np.zeros(2), SIZE)


def test_a_merge_far_away_recomputes_only_the_blocks_that_see_both_parts():
    """Two parts of one wall (facets 0 and 1, 6 m long each) joined into one facet: only the
    blocks whose extended block (3 x 3 blocks of 0.5 m) holds cells of both parts compute
    again, not the whole merged facet (the rule before marked all of its 2,400 cells)."""
    old = np.zeros((20, 120), dtype=np.int32)
    old[:, 60:] = 1
    new = np.zeros((20, 120), dtype=np.int32)
    layer_changed, regrouped = _changed(old, new)
    assert not layer_changed.any()
    cols = np.flatnonzero(regrouped.any(axis=0))
    # The junction lies between columns 59 and 60: the blocks of columns 55-59 and 60-64 hold
    # both parts in their extended block; those of 50-54 and 65-69 may (the rule is per block,
    # over the blocks around it); none further away.
    assert cols.min() >= 50 and cols.max() <= 69 and regrouped[:, 55:65].all()
    assert not regrouped[:, :50].any() and not regrouped[:, 70:].any()


def test_a_split_recomputes_the_blocks_that_lose_the_other_part_and_relabels_nothing_else():
    old = np.zeros((20, 120), dtype=np.int32)
    new = np.zeros((20, 120), dtype=np.int32)
    new[:, 60:] = 1
    _, regrouped = _changed(old, new)
    assert regrouped[:, 55:65].all() and not regrouped[:, :50].any() and not regrouped[:, 70:].any()
    # Renumbered facets alone (0 <-> 1) change nothing.
    old2 = np.where(new == 0, 1, 0).astype(np.int32)
    layer_changed, regrouped = _changed(old2, new)
    assert not layer_changed.any() and not regrouped.any()


def test_new_and_lost_cells_are_layer_changes():
    old = np.zeros((10, 40), dtype=np.int32)
    old[:, 30:] = -1
    new = np.zeros((10, 40), dtype=np.int32)
    new[:, :5] = -1
    layer_changed, _ = _changed(old, new)
    assert layer_changed[:, 30:].all() and layer_changed[:, :5].all() and not layer_changed[:, 5:30].any()
