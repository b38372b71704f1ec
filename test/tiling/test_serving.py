"""The node's pieces for a served tiled map, without ROS (about 1 s): answers combined with
the live map's, the list of tiles near a position, and the thread that follows the pose (it
loads the tiles near each pose and the cache evicts the far ones)."""

from __future__ import annotations

import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from uncertain_facade_map.errors import InputError
from uncertain_facade_map.params import TilesConfig
from uncertain_facade_map.pipeline.step7_queries import ANSWER_FIELDS, PointQuery
from uncertain_facade_map.tiling.serving import (
    LIVE_FACADE_OFFSET,
    TileFollower,
    check_radius,
    combine_answers,
    tiles_near_listing,
)


def answers(facade, value):
    n = len(facade)
    facade = np.asarray(facade, np.int32)
    nan = np.where(facade >= 0, value, np.nan)
    return PointQuery(facade, nan, nan * 2, nan * 3, nan * 4, np.where(facade >= 0, 0.9, 0.5),
                      np.tile(nan[:, None], (1, 3)) if n else np.empty((0, 3)))


def test_the_live_map_answers_only_where_the_tiled_map_found_no_facade():
    tiled = answers([3, -1, -1, 7, -1], 1.0)
    asked = np.flatnonzero(tiled.facade < 0)  # 1, 2, 4
    live = answers([0, -1, 2], 5.0)  # the live map finds façades for points 1 and 4
    out = combine_answers(tiled, live, asked)
    np.testing.assert_array_equal(out['facade'], [3, LIVE_FACADE_OFFSET, -1, 7, LIVE_FACADE_OFFSET + 2])
    np.testing.assert_array_equal(out['mean_depth'], [1.0, 5.0, np.nan, 1.0, 5.0])
    np.testing.assert_array_equal(out['p_occupied'], [0.9, 0.9, 0.5, 0.9, 0.9])
    np.testing.assert_array_equal(out['normal'][:, 0], [1.0, 5.0, np.nan, 1.0, 5.0])
    assert set(out) == set(ANSWER_FIELDS) and out['facade'].dtype == np.int32
    # nothing asked, or no live map: the tiled answers as they are (copies)
    for same in (combine_answers(tiled, None, np.zeros(0, int)), combine_answers(tiled.as_dict(), live, [])):
        for key in ANSWER_FIELDS:
            np.testing.assert_array_equal(same[key], getattr(tiled, key))
    assert combine_answers(tiled, None, [])['facade'] is not tiled.facade


class FakeTiled:
    """What the node uses of a TiledMap: squares of 10 m on a row, a cache of ``room`` tiles."""

    def __init__(self, n=6, room=2):
        self.records = [SimpleNamespace(id=f'tile_{i}_0', bounds=(10.0 * i, 0.0, 10.0 * i + 10, 10.0), facades=1,
                                        file=f'tiles/tile_{i}_0.npz') for i in range(n)]
        self.room = room
        self.cache: list[str] = []
        self.preloaded: list[tuple[float, float]] = []

    def tiles_near(self, xy, radius):
        box = np.array([r.bounds for r in self.records])
        d = np.hypot(np.maximum(np.maximum(box[:, 0] - xy[0], xy[0] - box[:, 2]), 0),
                     np.maximum(np.maximum(box[:, 1] - xy[1], xy[1] - box[:, 3]), 0))
        return [self.records[i] for i in np.argsort(d, kind='stable') if d[i] <= radius][::-1]  # any order

    def preload(self, xy, radius, config=None):
        self.preloaded.append(tuple(xy))
        ids = [r.id for r in sorted(self.tiles_near(xy, radius), key=lambda r: abs(r.bounds[0] + 5 - xy[0]))]
        for t in ids:
            if t in self.cache:
                self.cache.remove(t)
            self.cache.append(t)
            del self.cache[:-self.room]
        return ids

    def cache_info(self):
        return {'tiles': list(self.cache)}


def test_tiles_near_are_listed_nearest_first_with_absolute_files(tmp_path):
    tiled = FakeTiled()
    tiled.cache = ['tile_2_0']
    ids, bounds, files, loaded = tiles_near_listing(tiled, tmp_path / 'manifest.json', np.array([23.0, 5.0]), 8.0)
    assert ids == ['tile_2_0', 'tile_1_0', 'tile_3_0']  # 0 m, 3 m, 7 m away
    np.testing.assert_array_equal(bounds, [[20, 0, 30, 10], [10, 0, 20, 10], [30, 0, 40, 10]])
    assert files == [str(tmp_path.resolve() / 'tiles' / f'{t}.npz') for t in ids] and Path(files[0]).is_absolute()
    assert loaded == [True, False, False]
    ids, bounds, files, loaded = tiles_near_listing(tiled, tmp_path, np.array([500.0, 5.0]), 8.0)
    assert ids == [] and bounds.shape == (0, 4) and files == [] and loaded == []


def test_radius_zero_takes_the_parameter_and_bad_ones_are_refused():
    assert check_radius(0.0, 150.0) == 150.0 and check_radius(3.5, 150.0) == 3.5
    for bad in (-1.0, np.nan, np.inf):
        with pytest.raises(InputError, match='radius'):
            check_radius(bad, 150.0)


def test_the_follower_loads_the_tiles_near_each_pose_in_its_thread():
    tiled = FakeTiled(room=1)
    pose = {'xy': None}
    warnings = []
    follower = TileFollower(tiled, TilesConfig(radius=4.0, follow_period=0.02), lambda: pose['xy'], warnings.append)
    assert follower.follow_once() is None and follower.preloads == 0  # no pose yet: nothing loaded
    follower.start()
    try:
        time.sleep(0.1)
        assert tiled.preloaded == []
        pose['xy'] = np.array([5.0, 5.0])
        deadline = time.monotonic() + 5
        while 'tile_0_0' not in tiled.cache:
            assert time.monotonic() < deadline
            time.sleep(0.01)
        pose['xy'] = np.array([45.0, 5.0])  # 40 m on: tile 4 (and the far ones evicted by the cache)
        while tiled.cache != ['tile_4_0']:
            assert time.monotonic() < deadline, tiled.cache
            time.sleep(0.01)
    finally:
        follower.stop()
    values = follower.values()
    assert values['tiles_preloads'] >= 2 and values['tiles_follow_x'] == 45.0 and not warnings
    assert values['tiles_preload_max_seconds'] >= values['tiles_preload_mean_seconds'] >= 0
    assert not follower._thread.is_alive()


def test_a_failing_preload_is_counted_and_the_follower_lives_on():
    tiled = FakeTiled()
    calls = []

    def preload(xy, radius, config=None):
        calls.append(1)
        if len(calls) == 1:
            raise InputError('tile_0_0 is damaged')
        return []

    tiled.preload = preload
    warnings = []
    follower = TileFollower(tiled, TilesConfig(follow_period=0.02), lambda: np.zeros(2), warnings.append)
    follower.start()
    deadline = time.monotonic() + 5
    while len(calls) < 3:
        assert time.monotonic() < deadline
        time.sleep(0.01)
    follower.stop()
    assert follower.failures == 1 and 'damaged' in warnings[0] and follower.preloads >= 2
    idle = TileFollower(tiled, TilesConfig(follow_period=0.0), lambda: np.zeros(2), warnings.append)
    idle.start()  # follow_period 0: no thread
    assert idle._thread is None
    idle.stop()
