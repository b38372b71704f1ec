"""Bounded cost and memory (issues 13 and 37): a building stores at most
``update.store_per_voxel`` points per voxel of ``update.store_voxel``, the first to arrive,
none within ``update.store_spacing`` of a stored point, and counts the others; so scanning
the same façades again and again stops growing the stored map and the cost of an update,
and the live map (many calls) stores what the offline build (one call) stores."""

import time

import numpy as np
import pytest
from support import assert_same_maps, wall_scan

from uncertain_facade_map.io.map_file import load_map, save_map
from uncertain_facade_map.mapping.facade_map import FacadeMap, build_map
from uncertain_facade_map.params import MapParams, UpdateParams


def passes(n: int, rays: int = 400) -> list[tuple[np.ndarray, np.ndarray]]:
    """``n`` scans of the same 10 m x 6 m wall, each with its own noise."""
    return [wall_scan(rays=rays, seed=s) for s in range(n)]


def stored_by_rule(xyz: np.ndarray, voxel: float, cap: int, spacing: float) -> np.ndarray:
    """(N,) bool: the storage rule, point by point in arrival order: a point is stored when
    its voxel holds fewer than ``cap`` stored points and no stored point lies within
    ``spacing`` (<= ``voxel``: such a point lies in one of the 27 voxels around it)."""
    held: dict[tuple[int, int, int], list[np.ndarray]] = {}
    keep = np.zeros(len(xyz), dtype=bool)
    offsets = [(a, b, c) for a in (-1, 0, 1) for b in (-1, 0, 1) for c in (-1, 0, 1)]
    for i, key in enumerate(map(tuple, np.floor(xyz / voxel).astype(np.int64))):
        if len(held.get(key, [])) >= cap:
            continue
        near = [p for o in offsets for p in held.get((key[0] + o[0], key[1] + o[1], key[2] + o[2]), [])]
        if near and np.min(np.sum((np.array(near) - xyz[i]) ** 2, axis=1)) < spacing ** 2:
            continue
        held.setdefault(key, []).append(xyz[i])
        keep[i] = True
    return keep


@pytest.mark.parametrize('spacing', [0.0, 0.03])
def test_the_first_points_of_each_voxel_are_stored_and_the_others_counted(spacing):
    params = MapParams(update=UpdateParams(store_voxel=0.1, store_per_voxel=3, store_spacing=spacing))
    scans = passes(4)
    fmap = FacadeMap(params)
    for xyz, origins in scans:
        fmap.add_points(xyz, np.zeros(len(xyz), np.int64), origins)
    everything = np.concatenate([s[0] for s in scans])
    keep = stored_by_rule(everything, 0.1, 3, spacing)
    np.testing.assert_array_equal(fmap.points[0], everything[keep])
    np.testing.assert_array_equal(fmap.sensor_origins[0], np.concatenate([s[1] for s in scans])[keep])
    assert fmap.thinned == {0: int((~keep).sum())} and fmap.n_thinned > 0
    assert fmap.n_points == len(everything) and fmap.n_stored == int(keep.sum())
    assert fmap.last_update['thinned'] == int((~keep[-len(scans[-1][0]):]).sum())


def test_scanning_the_same_wall_again_stops_growing_the_stored_map():
    fmap = FacadeMap(MapParams())
    stored = []
    for xyz, origins in passes(12):
        fmap.add_points(xyz, None, origins)
        stored.append(fmap.n_stored)
    received = 12 * len(passes(1)[0][0])
    assert fmap.n_points + fmap.n_pending == received
    # The voxels fill up: the last four passes add less than the first one.
    assert stored[-1] - stored[-5] < 0.5 * stored[0], stored
    assert stored[-1] < 0.6 * received, stored
    # Never more than the cap per voxel.
    _, counts = np.unique(np.floor(np.concatenate(list(fmap.points.values())) / 0.1).astype(np.int64), axis=0,
                          return_counts=True)
    assert counts.max() <= MapParams().update.store_per_voxel
    assert len(fmap.facades) == 1 and len(fmap.facades[0].point_index) <= fmap.n_stored


def test_the_same_spots_seen_again_add_next_to_nothing():
    """A street driven again samples its walls near the same spots: each later pass here is
    the first one with 1 cm of fresh noise. Within ``update.store_spacing`` (3 cm here) of
    a stored point a new point is counted, not stored, so from the third pass on the passes
    add a few per cent; with the voxel cap alone they add most of the first pass again."""
    from scipy.spatial import cKDTree

    xyz, origins = wall_scan(seed=0)
    grown = {}
    for spacing in (0.0, 0.03):
        fmap = FacadeMap(MapParams(update=UpdateParams(store_spacing=spacing)))
        stored = []
        for p in range(5):
            fmap.store_points(xyz if p == 0 else xyz + np.random.default_rng(p).normal(0.0, 0.01, xyz.shape),
                              None, origins)
            stored.append(fmap.n_stored)
        grown[spacing] = (stored[-1] - stored[1]) / stored[0]
        assert fmap.n_points == 5 * len(xyz)  # the others are counted
        if spacing:
            pairs = cKDTree(fmap.points[0]).query(fmap.points[0], 2)[0][:, 1]
            assert pairs.min() >= spacing
    # measured: passes 3-5 add 14.6 % of the first pass's stored points, 75 % without the spacing
    assert grown[0.03] < 0.2 and grown[0.0] > 0.5, grown


def test_many_calls_store_what_one_call_stores(tmp_path):
    params = MapParams(update=UpdateParams(store_per_voxel=2))
    scans = passes(5)
    xyz = np.concatenate([s[0] for s in scans])
    origins = np.concatenate([s[1] for s in scans])
    parts = np.array_split(np.arange(len(xyz)), 17)
    # Each deferred call is a scan (FacadeMap.registration_var_): one call labels them so.
    whole = build_map(xyz, None, origins, params, scan=np.repeat(np.arange(17), [len(p) for p in parts]))
    live = FacadeMap(params)
    for part in parts:
        live.add_points(xyz[part], None, origins[part], defer=True)
    live.flush()
    assert live.thinned == whole.thinned and whole.n_thinned > 0
    for b in whole.points:
        np.testing.assert_array_equal(live.points[b], whole.points[b])
    # The deferred calls come to one update here, so the maps are the same bit for bit;
    # live mapping learnt the occupancy's PLSC parameters once past 20,000 stored points,
    # which build_map leaves to its caller: learnt by the same rule, they are the same too.
    assert live.occupancy_stored_ == live.n_stored > 20_000 and whole.occupancy_stored_ == 0
    assert whole.calibrate_when_grown()
    assert_same_maps(save_map(live, tmp_path / 'live.npz'), save_map(whole, tmp_path / 'whole.npz'))


def test_a_loaded_map_thins_as_the_saved_one_would(tmp_path):
    params = MapParams(update=UpdateParams(store_per_voxel=2))
    scans = passes(6)
    live = FacadeMap(params)
    for xyz, origins in scans[:3]:
        live.add_points(xyz, None, origins)
    restored = load_map(save_map(live, tmp_path / 'half.npz'))
    assert restored.thinned == live.thinned and restored.n_points == live.n_points
    for m in (live, restored):
        for xyz, origins in scans[3:]:
            m.add_points(xyz, None, origins)
    assert_same_maps(save_map(live, tmp_path / 'a.npz'), save_map(restored, tmp_path / 'b.npz'))


@pytest.fixture(scope='module')
def redriven(scenes):
    """The small street driven eight times (campaigns 0-7: lanes and directions alternate),
    fed as 0.1 s scans the way the node's worker feeds them, an update per 4000 points, at
    most 2 points stored per voxel (the small drive is sparse);
    per update: (campaign, points received, points stored, seconds)."""
    params = MapParams(update=UpdateParams(batch_points=4000, store_per_voxel=2))
    fmap = FacadeMap(params, scenes.campaign('small', 0).map_origin)
    rows, received = [], 0
    for c in range(DRIVES):
        pts = scenes.campaign('small', c).points
        pts = pts[pts['class'] == 1]
        pts = pts[np.argsort(pts['time'], kind='stable')]
        xyz = np.stack([pts['x'], pts['y'], pts['z']], 1)
        origins = np.stack([pts['origin_x'], pts['origin_y'], pts['origin_z']], 1)
        slot = np.floor((pts['time'] - pts['time'][0]) / 0.1)
        bounds = np.r_[0, np.flatnonzero(np.diff(slot)) + 1, len(pts)]
        for a, b in zip(bounds[:-1], bounds[1:]):
            received += b - a
            t0 = time.perf_counter()
            if fmap.add_points(xyz[a:b], pts['building_id'][a:b], origins[a:b], defer=True):
                rows.append((c, received, fmap.n_stored, time.perf_counter() - t0))
    return fmap, received, np.array(rows)


DRIVES = 8


def test_redriving_the_street_keeps_the_stored_map_and_the_update_time_flat(redriven):
    fmap, received, rows = redriven
    campaign, _, stored, seconds = rows.T
    assert fmap.n_points + fmap.n_pending == received
    # Stored points: the last two drives add about half what the first two did (their points
    # mostly fall in full voxels).
    first_two = stored[campaign <= 1].max()
    last_two = stored[-1] - stored[campaign <= DRIVES - 3].max()
    assert last_two < 0.6 * first_two, (first_two, last_two)  # measured: 15 255 against 32 586
    # Update seconds: the last two drives' median within 2.5x the first two's (timings are
    # noisy on a shared machine); without the cap the stored map, and the work of an
    # update, grow with every drive.
    early, late = np.median(seconds[campaign <= 1]), np.median(seconds[campaign >= DRIVES - 2])
    assert late <= 2.5 * early, (early, late, rows)
