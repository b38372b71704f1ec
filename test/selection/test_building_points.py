"""Tests of uncertain_facade_map.selection: building points of clouds without classes.

A seeded synthetic street (ground, walls, a car, a pole, a tree) with known labels; input
validation by hypothesis; and the real Argoverse sweeps of ``../shared/data/real/`` (skipped
without them) against the independent wall picker of ``selection.evaluation``.
"""

from __future__ import annotations

import dataclasses
import sys

import hypothesis.extra.numpy as hnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from support import CAR, GROUND, POLE, TREE, WALL, unclassified_street

from uncertain_facade_map.errors import InputError
from uncertain_facade_map.params import SelectionConfig
from uncertain_facade_map.selection import Selection, select_building_points
from uncertain_facade_map.selection import building_points as bp
from uncertain_facade_map.selection.evaluation import REAL_DATA, evaluate, pick_walls

#: A city frame far from the origin (float32 there keeps only decimetres).
CITY = np.array([2683000.0, 1247000.0, 400.0])


@pytest.fixture(scope='module')
def street():
    return unclassified_street(seed=0)


def shares(mask: np.ndarray, labels: np.ndarray) -> dict[int, float]:
    return {k: float(mask[labels == k].mean()) for k in (GROUND, WALL, CAR, POLE, TREE)}


def test_keeps_the_walls_and_drops_ground_car_pole_and_tree(street):
    xyz, labels, sensor = street
    found = select_building_points(xyz, sensor)
    assert isinstance(found, Selection) and found.applied
    assert found.mask.dtype == bool and found.mask.shape == (len(xyz),)
    kept = shares(found.mask, labels)
    assert kept[WALL] >= 0.97  # measured 0.987 (the walls' feet go with the ground)
    assert (labels[found.mask] == WALL).mean() >= 0.99  # precision, measured 1.0
    assert kept[GROUND] <= 0.005 and kept[CAR] <= 0.02 and kept[POLE] <= 0.02 and kept[TREE] <= 0.05
    assert found.walls == 3
    # Patchwork++ finds the ground: half the points, hardly a wall point among them.
    assert found.ground[labels == GROUND].mean() >= 0.95
    assert found.ground[labels == WALL].mean() <= 0.03
    assert 0.45 <= found.ground_share <= 0.5


def test_any_frame_and_any_form_of_the_sensor_origin(street):
    xyz, labels, sensor = street
    reference = select_building_points(xyz, sensor).mask
    # The same scan in a city frame: the same selection (it works in local coordinates).
    assert np.array_equal(select_building_points(xyz + CITY, sensor + CITY).mask, reference)
    # One origin per point is one scan, centred on it.
    assert np.array_equal(select_building_points(xyz, np.tile(sensor, (len(xyz), 1))).mask, reference)
    # Without the sensor: centred on the points' median, nearly the same.
    blind = select_building_points(xyz + CITY).mask
    assert shares(blind, labels)[WALL] >= 0.97 and (labels[blind] == WALL).mean() >= 0.99
    # Deterministic: a fresh Patchwork++ per scan, no state carried over.
    assert np.array_equal(select_building_points(xyz, sensor).mask, reference)


def test_scans_by_sensor_origin_and_tiles(street):
    xyz, labels, sensor = street
    # Two drives 100 m apart, each with its origins: two scans, each centred on its sensor.
    shift = np.array([100.0, 0.0, 0.0])
    both = np.concatenate([xyz, xyz + shift])
    origins = np.concatenate([np.tile(sensor, (len(xyz), 1)), np.tile(sensor + shift, (len(xyz), 1))])
    assert len(list(bp._scans(both, origins, SelectionConfig()))) == 2
    found = select_building_points(both, origins)
    single = select_building_points(xyz, sensor).mask
    assert np.array_equal(found.mask, np.concatenate([single, single]))
    # Without origins, a cloud wider than twice max_range is cut into tiles of max_range.
    tiles = list(bp._scans(both, None, SelectionConfig(max_range=40.0)))
    assert len(tiles) >= 4 and sum(len(idx) for idx, _ in tiles) == len(both)
    wide = select_building_points(both, None, SelectionConfig(max_range=40.0)).mask
    assert shares(wide, np.concatenate([labels, labels]))[WALL] >= 0.9


def test_a_cloud_of_building_points_is_kept_whole(street):
    xyz, labels, _ = street
    walls = xyz[labels == WALL]
    found = select_building_points(walls)
    assert not found.applied and found.mask.all() and found.walls == 0
    assert found.ground_share < SelectionConfig().min_ground_share
    # Forced to select, the selection itself keeps nearly all of them too.
    forced = select_building_points(walls, None, SelectionConfig(min_ground_share=0.0))
    assert forced.applied and forced.mask.mean() >= 0.99


def test_parameters_steer_the_selection(street):
    xyz, labels, sensor = street
    # Walls lower than the structure height are not walls: 9 m walls with a 10 m threshold.
    assert not select_building_points(xyz, sensor, SelectionConfig(min_structure_height=10.0)).mask.any()
    # Segments shorter than the minimum are dropped: the 8 m side wall with a 10 m minimum.
    found = select_building_points(xyz, sensor, SelectionConfig(min_segment_length=10.0))
    side = (labels == WALL) & (np.abs(xyz[:, 0] - 20) < 0.5) & (xyz[:, 1] > -10) & (xyz[:, 1] < 0)
    assert found.walls == 2 and found.mask[side].mean() < 0.02
    # The car passes once the structure height is below its 1.5 m roof.
    low = select_building_points(xyz, sensor, SelectionConfig(min_structure_height=1.0, min_segment_length=1.0))
    assert shares(low.mask, labels)[CAR] > 0.3


def test_patchwork_output_is_silenced(street, capfd):
    xyz, _, sensor = street
    select_building_points(xyz[:2000], sensor)
    assert 'INITIALIZATION' not in capfd.readouterr().out


def test_a_missing_library_is_a_clean_error(street, monkeypatch):
    xyz, _, sensor = street
    monkeypatch.setitem(sys.modules, 'pypatchworkpp', None)
    with pytest.raises(InputError, match='needs pypatchworkpp.*selection.mode: off') as err:
        select_building_points(xyz, sensor)
    assert isinstance(err.value.__cause__, ImportError)


# --------------------------------------------------------------------------------------
# Input validation
finite = st.floats(-1e4, 1e4, allow_nan=False, allow_infinity=False)


@settings(max_examples=40, deadline=None)
@given(points=hnp.arrays(np.float64, st.tuples(st.integers(0, 60), st.just(3)), elements=finite))
def test_any_finite_cloud_gives_a_mask(points):
    found = select_building_points(points)
    assert found.mask.shape == found.ground.shape == (len(points),)
    assert found.mask.dtype == bool and found.ground.dtype == bool


@settings(max_examples=40, deadline=None)
@given(points=hnp.arrays(np.float64, st.tuples(st.integers(1, 30), st.just(3)), elements=finite),
       data=st.data())
def test_nan_and_inf_are_refused_with_their_count(points, data):
    bad = data.draw(st.lists(st.tuples(st.integers(0, len(points) - 1), st.integers(0, 2)), min_size=1, max_size=5))
    for i, k in bad:
        points[i, k] = data.draw(st.sampled_from([np.nan, np.inf, -np.inf]))
    rows = len({i for i, _ in bad})
    with pytest.raises(InputError, match=f'^{rows} of {len(points)} points have NaN or infinite coordinates$'):
        select_building_points(points)
    with pytest.raises(InputError, match='sensor origins have NaN'):
        select_building_points(np.zeros((len(points), 3)), points)


@settings(max_examples=40, deadline=None)
@given(shape=st.lists(st.integers(0, 5), min_size=0, max_size=3).map(tuple).filter(
    lambda s: not (len(s) == 2 and s[1] == 3)))
def test_wrong_shapes_are_refused(shape):
    with pytest.raises(InputError, match=r'points must be of shape \(N, 3\), got'):
        select_building_points(np.zeros(shape))


def test_wrong_origins_and_types_are_refused():
    with pytest.raises(InputError, match=r'2 sensor origins for 3 points'):
        select_building_points(np.zeros((3, 3)), np.zeros((2, 3)))
    with pytest.raises(InputError, match=r'sensor origins must be of shape \(N, 3\) or \(3,\), got \(2,\)'):
        select_building_points(np.zeros((3, 3)), np.zeros(2))
    with pytest.raises(InputError, match='points must be numbers'):
        select_building_points(np.array([['a', 'b', 'c']]))
    assert len(select_building_points(np.zeros((0, 3))).mask) == 0


# --------------------------------------------------------------------------------------
# Real sweeps (Argoverse and KITTI, CC BY-NC-SA: read from ../shared beside the repository)
REAL = sorted(REAL_DATA.glob('*.ply')) + sorted(REAL_DATA.glob('car_lidar/*.ply')) if REAL_DATA.is_dir() else []


@pytest.mark.skipif(not REAL, reason=f'no real sweeps in {REAL_DATA}')
@pytest.mark.parametrize('path', REAL, ids=[p.stem for p in REAL])
def test_real_sweeps_against_an_independent_wall_picker(path):
    figures = evaluate(path)
    # Measured (python -m uncertain_facade_map.selection.evaluation): recall 0.959-0.995,
    # precision 0.81-0.82 (0.85-0.94 within 40 m, where the picker looks) on the Argoverse
    # sweeps; on the KITTI HDL-64E sweeps (car_lidar/, walls seen up to 2.5-4 m) recall
    # 0.911-0.953, precision 0.94-0.96 (0.81-0.87 before the top of the view was a line).
    assert figures['recall'] >= 0.9
    assert figures['precision'] >= 0.75 and figures['precision_40m'] >= 0.8
    # Ground (17-23 % of a sweep) is gone, and with it half the cloud.
    assert figures['ground'] >= 0.15 * figures['points']
    assert figures['selected'] <= 0.55 * figures['points']
    # Wall points cut already (real_check.py's input to build) are kept whole.
    assert figures['wall_only_kept'] >= 0.97
    assert figures['seconds'] < 5.0


def test_the_wall_picker_finds_the_synthetic_walls(street):
    xyz, labels, sensor = street
    walls = pick_walls(xyz, sensor)
    assert walls[labels == WALL].mean() >= 0.9
    # Measured 0.956: a slab through the tree's crown passes for a wall too (a weakness of
    # picking planes alone, which the selection's thickness test avoids).
    assert (labels[walls] == WALL).mean() >= 0.93


def test_evaluation_prints_a_line_per_cloud(tmp_path, capsys, street):
    from uncertain_facade_map.io.cloud import Cloud
    from uncertain_facade_map.io.ply import write_ply
    from uncertain_facade_map.selection.evaluation import main

    xyz, _, _ = street
    pts = np.zeros(len(xyz), dtype=[('x', 'f8'), ('y', 'f8'), ('z', 'f8')])
    pts['x'], pts['y'], pts['z'] = xyz.T
    write_ply(tmp_path / 'street.ply', Cloud(pts))
    assert main([str(tmp_path / 'street.ply')]) == 0
    out = capsys.readouterr().out
    assert out.startswith('street.ply: 41,000 points,') and 'wall-only cloud kept 1.000' in out


def test_params_section_is_checked():
    with pytest.raises(InputError, match='parameter selection.mode: expected one of auto, on, off'):
        SelectionConfig(mode='sometimes')
    with pytest.raises(InputError, match='need max_thickness <= band'):
        SelectionConfig(band=0.1, max_thickness=0.2)
    assert dataclasses.replace(SelectionConfig(), mode='off').mode == 'off'
