"""The tiled build's routing and tile tasks (issue 29): with sensor origins, the tiles' buildings
are those of one map of the whole input, bit for bit, however the input is cut.

About 4 s (the `small` scene: 2 buildings, 14,000 points, mapped three times; the three cases of
parts surveyed and spilled apart take 0.1 s each)."""

import json
from pathlib import Path

import numpy as np
import pytest

from uncertain_facade_map.errors import InputError
from uncertain_facade_map.io.map_file import _facade_arrays, load_map
from uncertain_facade_map.mapping.facade_map import build_map
from uncertain_facade_map.params import MapParams, map_params_record
from uncertain_facade_map.pipeline.step1_facades import split_buildings
from uncertain_facade_map.tiling.build import (
    Router,
    build_tile,
    in_bounds,
    in_frame,
    parse_bounds,
    read_parts,
    spill_part,
    survey_part,
)
from uncertain_facade_map.tiling.manifest import Manifest


@pytest.fixture(scope='module')
def street(scenes):
    return *scenes.building_points('small', 0), scenes.campaign('small', 0).map_origin


@pytest.fixture(scope='module')
def whole(street):
    xyz, ids, origins, origin = street
    return build_map(xyz, ids, origins, MapParams(), origin)


def _route(folder, street, cuts, ids=True, side=20.0):
    xyz, given, origins, origin = street
    router = Router(folder, MapParams(), side)
    for a, b in zip(cuts[:-1], cuts[1:]):
        router.add(xyz[a:b], given[a:b] if ids else None, origins[a:b], origin)
    return router, router.spill()


def assert_same_buildings(whole, tile):
    """Every building of ``tile`` is in ``whole`` with the same points, normals, sensor
    origins and façade models (arrays bit for bit, façades in the building's order)."""
    for b in tile.buildings:
        for name in ('points', 'normals', 'sensor_origins'):
            x, y = getattr(whole, name)[b], getattr(tile, name)[b]
            assert x.dtype == y.dtype and x.tobytes() == y.tobytes(), (b, name)
        mine = [f for f in whole.facades if f.building == b]
        theirs = [f for f in tile.facades if f.building == b]
        assert len(mine) == len(theirs)
        for f, g in zip(mine, theirs):
            fa, ga = _facade_arrays(f), _facade_arrays(g)
            assert len(fa) == len(ga)
            for (ka, va), (kb, vb) in zip(sorted(fa.items()), sorted(ga.items())):
                assert ka.split('/')[-1] == kb.split('/')[-1]
                assert va.dtype == vb.dtype and va.tobytes() == vb.tobytes(), (b, f.facade_id, ka)
            assert (f.layers.main_, f.global_mean_, f.global_var_, f.noise_var, f.fitted_points) == \
                (g.layers.main_, g.global_mean_, g.global_var_, g.noise_var, g.fitted_points)


def test_tiles_hold_the_whole_maps_buildings_bit_for_bit(tmp_path, street, whole):
    router, tasks = _route(tmp_path, street, [0, 5000, len(street[0])])
    assert [t.tile_id for t in tasks] == ['tile_0_0', 'tile_1_0']
    seen = []
    for task in tasks:
        result = build_tile(task)
        tile = load_map(tmp_path / result.record.file)
        assert result.record.buildings == tile.buildings
        assert_same_buildings(whole, tile)
        seen += tile.buildings
    assert sorted(seen) == whole.buildings == [0, 1]
    assert all(any(f.building == b for f in whole.facades) for b in seen)


def test_routing_does_not_depend_on_the_cut(tmp_path, street):
    """The same points and labels in every tile however the input is cut into chunks; the
    fingerprint (a hash of the parts' digests, one part per chunk) is the same for the same cut."""
    n = len(street[0])
    _, a = _route(tmp_path / 'a', street, [0, n])
    _, b = _route(tmp_path / 'b', street, [0, 7, 3000, 3001, 9000, n])
    _, c = _route(tmp_path / 'c', street, [0, 7, 3000, 3001, 9000, n])
    assert [t.tile_id for t in a] == [t.tile_id for t in b]
    assert [t.inputs for t in b] == [t.inputs for t in c] != [t.inputs for t in a]
    for ta, tb in zip(a, b):
        for x, y in zip(read_parts(ta.parts), read_parts(tb.parts)):
            assert x.tobytes() == y.tobytes()


def _pieces(street, files, shift=None):
    """The street cut into input files of a few chunks each (file k of ``files``: the chunks'
    (start, stop) rows); with ``shift``, the odd files in a map frame moved by it (metres)."""
    xyz, given, origins, origin = street
    out = []
    for k, cuts in enumerate(files):
        d = np.zeros(3) if shift is None or k % 2 == 0 else np.asarray(shift)
        out.append([(xyz[a:b] - d, given[a:b], origins[a:b] - d, origin + d) for a, b in cuts])
    return out


@pytest.mark.parametrize('ids,shift', [(True, None), (False, None), (True, (10.0, -3.0, 0.5))])
def test_parts_surveyed_and_spilled_apart_route_as_one_router(tmp_path, street, ids, shift):
    """Issue 29's parallel routing: each input file surveyed on its own (here in reverse order,
    as workers may finish), the surveys merged in input order, the files spilled on their own:
    the same labels, tiles, part files and fingerprints as one router fed chunk by chunk; inputs
    of another map origin than the first's are surveyed again in the first's frame."""
    n = len(street[0])
    files = [[(0, 10)], [(10, 3000), (3000, 3001), (3001, 6000)], [], [(6000, 9000), (9000, n)]]
    pieces = _pieces(street, files, shift)
    if not ids:
        pieces = [[(x, None, so, o) for x, _, so, o in chunks] for chunks in pieces]
    serial = Router(tmp_path / 'serial', MapParams(), 20.0)
    for chunks in pieces:
        for chunk in chunks:
            serial.add(*chunk)
    want = serial.spill()
    folder = tmp_path / 'parallel'
    router = Router(folder, MapParams(), 20.0)
    cell = router.cell
    parts = {k: survey_part(folder, k, pieces[k], cell) for k in reversed(range(len(pieces)))}
    origin = parts[0].origin
    assert [in_frame(parts[k], origin) for k in range(len(pieces))] == [True, shift is None, True, shift is None]
    for k in range(len(pieces)):
        if not in_frame(parts[k], origin):
            parts[k] = survey_part(folder, k, pieces[k], cell, origin=origin)
        router.merge(parts[k])
    assert router.plan() == serial._plan
    assert router.points == serial.points == n
    spilled = [spill_part(folder, p.index, p.chunks, router.route_plan, first)
               for p, first in reversed(list(zip(router.parts, router.spill_firsts())))]
    got = router.tasks(spilled)
    assert [t.tile_id for t in got] == [t.tile_id for t in want] and len(got) >= 2
    assert [t.inputs for t in got] == [t.inputs for t in want]
    for tg, tw in zip(got, want):
        assert [Path(p).name for p in tg.parts] == [Path(p).name for p in tw.parts]
        for x, y in zip(read_parts(tg.parts), read_parts(tw.parts)):
            assert x.dtype == y.dtype and x.tobytes() == y.tobytes()
    if not ids:
        labels = np.concatenate([read_parts(t.parts)[1] for t in got])
        assert len(np.unique(labels)) > 2  # clustered: the two buildings and a few stray points
    if shift is not None:
        other = Router(tmp_path / 'refuse', MapParams(), 20.0, map_origin=origin)
        with pytest.raises(ValueError, match='map frame'):
            other.merge(survey_part(other.folder, 1, pieces[1], cell))


def test_points_without_ids_are_clustered_over_the_whole_input(tmp_path, street):
    """Without ids the labels are split_buildings' over the joined input (whatever the cut), so
    the tiles still hold the whole map's buildings bit for bit."""
    xyz, _, origins, origin = street
    n = len(xyz)
    labels = split_buildings(xyz, None, MapParams().extraction.building_cell)
    assert len(np.unique(labels)) > 2  # the two buildings and a few stray points
    _, tasks = _route(tmp_path, street, [0, 4000, 11000, n], ids=False)
    routed = np.concatenate([read_parts(t.parts)[1] for t in tasks])
    assert sorted(routed.tolist()) == sorted(labels.tolist())
    whole = build_map(xyz, None, origins, MapParams(), origin)
    for task in tasks:
        assert_same_buildings(whole, load_map(tmp_path / build_tile(task).record.file))


def test_bounds(tmp_path, street):
    xyz, ids, origins, origin = street
    box = (origin[0] - 1, origin[1] - 100, origin[0] + 20, origin[1] + 100)
    router = Router(tmp_path, MapParams(), 20.0, box)
    kept = router.add(xyz, ids, origins, origin)
    assert kept == int(((xyz[:, 0] < 20)).sum()) and 0 < kept < len(xyz)
    assert parse_bounds('0,1,2,3.5') == (0.0, 1.0, 2.0, 3.5)
    assert in_bounds(np.array([[0.0, 1.0], [2.0, 2.0]]), (0.0, 1.0, 2.0, 3.5)).tolist() == [True, False]
    for bad in ('0,1,2', '0,1,0,3', 'a,b,c,d', '0,1,nan,3'):
        with pytest.raises(InputError, match='MIN_X'):
            parse_bounds(bad)


def test_fingerprint_holds_parameters(tmp_path, street):
    xyz, ids, origins, origin = street
    runs = []
    for seed in (0, 1):
        router = Router(tmp_path / str(seed), MapParams(seed=seed), 20.0)
        router.add(xyz, ids, origins, origin)
        runs.append([t.inputs for t in router.spill()])
    assert all(a != b for a, b in zip(*runs))
    json.dumps(runs)


def test_a_resumed_build_labels_its_clustered_buildings_alike(tmp_path, street):
    """The finished tiles of a killed build put its clustered labels into the manifest; the
    resumed build must still give the same labels (same fingerprints, tiles skipped), while a
    new drive's clusters are numbered past the map's buildings."""
    xyz, _, origins, origin = street
    router = Router(tmp_path, MapParams(), 20.0)
    router.add(xyz, None, origins, origin)
    first = router.spill()
    placed = router._plan
    manifest = Manifest(20.0, tuple(origin), map_params_record(MapParams()), {}, None, dict(placed))
    again = Router(tmp_path, MapParams(), 20.0, existing=manifest)
    again.add(xyz, None, origins, origin)
    assert [t.inputs for t in again.spill()] == [t.inputs for t in first]
    router.cleanup()  # the build completed: the next input is a new drive
    drive = Router(tmp_path, MapParams(), 20.0, existing=manifest)
    drive.add(xyz, None, origins, origin)
    drive.plan()
    assert min(b for b in drive._plan if b not in placed) > max(placed)


def test_the_calibration_tiles_are_the_largest_up_to_the_sample_size(tmp_path):
    """calibration_tiles: the tiles with the most routed points (counted from the part files'
    headers) until they hold 200,000 points; ties to the first id; all of a small map's."""
    from uncertain_facade_map.tiling.build import TileTask, calibration_tiles, routed_points

    def task(name, *rows):
        parts = []
        for k, n in enumerate(rows):
            path = tmp_path / f'{name}_{k}.npz'
            np.savez(path, xyz=np.zeros((n, 3)), building_id=np.zeros(n, np.int64))
            parts.append(str(path))
        return TileTask(str(tmp_path), name, (0, 0), (0, 0, 1, 1), tuple(parts), MapParams(), (0.0, 0.0, 0.0), 'x')

    tasks = [task('tile_a', 30_000), task('tile_b', 90_000, 60_000), task('tile_c', 100_000), task('tile_d', 100_000)]
    assert [routed_points(t) for t in tasks] == [30_000, 150_000, 100_000, 100_000]
    assert calibration_tiles(tasks) == ('tile_b', 'tile_c')  # 150,000 + 100,000 (c before d: ties by id)
    assert calibration_tiles(tasks[:1]) == ('tile_a',) and calibration_tiles([]) == ()
    assert calibration_tiles([tasks[0], tasks[2]]) == ('tile_a', 'tile_c')  # 130,000: all
