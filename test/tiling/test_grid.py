"""The tile grid: a point's index and its square's bounds agree to the last bit (negative
coordinates included), and tile ids round-trip. About 2 s."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from uncertain_facade_map.errors import InputError
from uncertain_facade_map.tiling.grid import TileGrid, parse_tile_id, tile_file, tile_id

coords = st.floats(-1e6, 1e6, allow_nan=False, allow_infinity=False)
sides = st.one_of(st.floats(1.0, 1e4), st.sampled_from([0.1, 0.3, 1.0, 20.0, 50.0, 100.0, 7.7]))


@settings(max_examples=300, deadline=None)
@given(sides, st.lists(st.tuples(coords, coords), min_size=1, max_size=20))
def test_a_point_lies_in_the_bounds_of_its_index(side, pts):
    grid = TileGrid(side)
    xy = np.array(pts, dtype=np.float64)
    idx = grid.index(xy)
    assert idx.dtype == np.int64 and idx.shape == (len(pts), 2)
    for (x, y), (ix, iy) in zip(xy, idx):
        x0, y0, x1, y1 = grid.bounds(int(ix), int(iy))
        assert x0 <= x < x1 and y0 <= y < y1
        assert math.isclose(x1 - x0, side, rel_tol=1e-6, abs_tol=1e-6)


@settings(max_examples=200, deadline=None)
@given(sides, st.integers(-10**5, 10**5), st.integers(-10**5, 10**5))
def test_the_corners_of_a_square_index_back_to_it(side, ix, iy):
    grid = TileGrid(side)
    x0, y0, x1, y1 = grid.bounds(ix, iy)
    if x0 == x1 or y0 == y1:  # squares too small to tell apart at this magnitude
        return
    assert grid.index(np.array([[x0, y0]])).tolist() == [[ix, iy]]
    # The max is exclusive: it belongs to the next square.
    assert grid.index(np.array([[x1, y1]])).tolist() == [[ix + 1, iy + 1]]


def test_known_indices_with_negatives():
    grid = TileGrid(50.0)
    xy = np.array([[0.0, 0.0], [49.999, 50.0], [-0.001, -50.0], [-50.001, 125.0]])
    assert grid.index(xy).tolist() == [[0, 0], [0, 1], [-1, -1], [-2, 2]]
    assert grid.bounds(-1, 2) == (-50.0, 100.0, 0.0, 150.0)
    assert grid.index(np.array([3.0, -3.0, 7.0])).tolist() == [[0, -1]]  # (3,) with z: one point


@given(st.integers(-10**9, 10**9), st.integers(-10**9, 10**9))
def test_tile_ids_round_trip(ix, iy):
    text = tile_id(ix, iy)
    assert parse_tile_id(text) == (ix, iy)
    assert '-' not in text and tile_file(text) == f'tiles/{text}.npz'


def test_tile_id_format():
    assert tile_id(-3, 12) == 'tile_m3_12' and tile_id(0, -1) == 'tile_0_m1'


@pytest.mark.parametrize('text', ['tile_1', 'tile_-1_2', 'tile_m0_1', 'x_1_2', 'tile_1_2.npz'])
def test_bad_ids_are_refused(text):
    with pytest.raises(InputError, match='not a tile id'):
        parse_tile_id(text)


@pytest.mark.parametrize('side', [0.0, -1.0, math.nan, math.inf, 'a'])
def test_bad_sides_are_refused(side):
    with pytest.raises(InputError, match='tile side'):
        TileGrid(side)


def test_bad_points_are_refused():
    grid = TileGrid(10.0)
    with pytest.raises(InputError, match='finite'):
        grid.index(np.array([[np.nan, 0.0]]))
    with pytest.raises(InputError, match='shape'):
        grid.index(np.zeros((3, 1)))
