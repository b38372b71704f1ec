"""Tests of uncertain_facade_map.io.autoware: the mean surface as Autoware PCD tiles and their metadata.

The map is the ``small`` scene's (campaign 0, 4 façades, 54,029 facet cells of 0.1 m; x from
-0.011 to 40.09 m, y 7.65 to 15.23 m in the map frame), so a 20 m grid gives the cells
-20, 0, 20 and 40 (one of them for a few points just left of x = 0) and a 50 m grid the
cells -50 and 0. The metadata is read with the rule of Autoware's loader
(autowarefoundation/autoware.universe, map/autoware_map_loader/src/pointcloud_map_loader/utils.cpp,
``load_pcd_metadata`` and ``replace_with_absolute_path``; pointcloud_map_loader_node.cpp,
``get_pcd_paths``), replicated in :func:`loader_metadata`. About 3 s of tests (most of it simulating and
building the map), 9 to 11 s wall with pytest's start-up (median 9.6 s of 3 runs, busy machine).
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st

from uncertain_facade_map.errors import InputError
from uncertain_facade_map.io.autoware import (
    METADATA_NAME,
    PCD_DTYPE,
    _cells,
    _check_float32,
    cell_file_name,
    export_autoware,
)
from uncertain_facade_map.io.map_file import save_map
from uncertain_facade_map.io.pcd import read_pcd
from uncertain_facade_map.mapping.facade_map import FacadeMap
from uncertain_facade_map.mapping.products import surface_grid
from uncertain_facade_map_apps.cli import main


@pytest.fixture(scope='module')
def small_map(scenes, tmp_path_factory):
    """The small scene's map and its file."""
    fmap = scenes.building_map('small', 0)
    path = save_map(fmap, tmp_path_factory.mktemp('autoware') / 'map.npz')
    return fmap, path


def loader_metadata(folder: Path, metadata: Path) -> dict[str, tuple[float, float, float, float]]:
    """The metadata as Autoware's loader reads it: base name -> (min_x, min_y, max_x, max_y).

    ``load_pcd_metadata``: every key but x_resolution / y_resolution is a file whose value
    is read ``as<std::vector<int>>()`` (so YAML integers only: yaml-cpp refuses 1200.0 or
    true as int), max = min + resolution (``as<float>``). ``get_pcd_paths`` lists the
    folder's .pcd / .PCD files (not recursively); ``replace_with_absolute_path`` matches each
    key to a file's base name and the node stops when a key has no file.
    """
    doc = yaml.safe_load(metadata.read_text())
    assert isinstance(doc, dict)
    xr, yr = float(doc['x_resolution']), float(doc['y_resolution'])
    out = {}
    for key, value in doc.items():
        if key in ('x_resolution', 'y_resolution'):
            continue
        assert isinstance(key, str)
        assert isinstance(value, list) and len(value) >= 2
        assert all(type(v) is int for v in value), f'{key}: {value} are not YAML integers'
        out[key] = (float(value[0]), float(value[1]), float(value[0]) + xr, float(value[1]) + yr)
    pcds = {p.name for p in folder.iterdir() if p.is_file() and p.suffix in ('.pcd', '.PCD')}
    assert set(out) <= pcds, f'segments missing from the input PCDs: {sorted(set(out) - pcds)}'
    assert pcds == set(out), f'PCD files the whole-map load would read but the metadata lacks: {pcds - set(out)}'
    return out


def _rows_sorted(rows: np.ndarray) -> np.ndarray:
    return rows[np.lexsort([rows[c] for c in ('std', 'z', 'y', 'x')])]


def _expected_rows(fmap) -> np.ndarray:
    g = surface_grid(fmap.facades)
    rows = np.empty(len(g), PCD_DTYPE)
    rows['x'], rows['y'], rows['z'] = g.xyz[:, 0], g.xyz[:, 1], g.xyz[:, 2]
    rows['std'] = g.std
    return rows


def _read_export(folder: Path, grid: float) -> tuple[dict, dict[str, np.ndarray]]:
    meta = loader_metadata(folder, folder / METADATA_NAME)
    rows = {}
    for name in meta:
        import pypcd4

        pc = pypcd4.PointCloud.from_path(folder / name)
        assert pc.metadata.fields == ('x', 'y', 'z', 'std')
        assert pc.metadata.type == ('F',) * 4 and pc.metadata.size == (4,) * 4
        assert pc.metadata.data == 'binary'
        data = np.asarray(pc.pc_data)
        cloud = read_pcd(folder / name)  # our reader agrees, VIEWPOINT is the identity
        assert cloud.map_origin.tolist() == [0.0, 0.0, 0.0]
        assert all(np.array_equal(cloud.points[c], data[c]) for c in PCD_DTYPE.names)
        r = np.empty(len(data), PCD_DTYPE)
        for c in PCD_DTYPE.names:
            r[c] = data[c]
        rows[name] = r
    return meta, rows


@pytest.mark.parametrize('grid, cells', [(20, [(-20, 0), (0, 0), (20, 0), (40, 0)]), (50, [(-50, 0), (0, 0)])])
def test_export_tiles_the_surface_points_by_the_loaders_rule(small_map, tmp_path, grid, cells):
    fmap, _ = small_map
    out = tmp_path / 'pcd'
    result = export_autoware(fmap, out, grid, prefix='small')
    meta, rows = _read_export(out, grid)
    assert sorted(f.min_xy for f in result.files) == cells
    assert set(meta) == {cell_file_name('small', *c) for c in cells} == {f'small_{x}_{y}.pcd' for x, y in cells}
    for name, (x0, y0, x1, y1) in meta.items():
        r = rows[name]
        assert len(r) > 0
        # The divider's half-open cells (hence also the loader's closed box) on the values written.
        x, y = r['x'].astype(np.float64), r['y'].astype(np.float64)
        assert np.all((x >= x0) & (x < x1) & (y >= y0) & (y < y1)), name
        m = re.fullmatch(r'small_(-?\d+)_(-?\d+)\.pcd', name)
        assert (int(m[1]), int(m[2])) == (x0, y0)
    union = np.concatenate(list(rows.values()))
    expected = _expected_rows(fmap)
    assert len(union) == result.points == len(expected) == 54_029
    assert np.array_equal(_rows_sorted(union), _rows_sorted(expected))
    # std is sqrt of the rasters' variance at the facet cells, read from the rasters directly.
    var = np.concatenate([f.surface.var[f.surface.facet >= 0] for f in fmap.facades])
    assert np.array_equal(np.sort(union['std']), np.sort(np.sqrt(var).astype(np.float32)))
    assert float(union['std'].min()) > 0.0 and float(union['std'].max()) < 0.25
    # Bounds and georeference as reported and as the YAML's comment states them.
    assert result.bounds == pytest.approx((-0.011265, 7.654047, -0.147345, 40.087254, 15.230634, 12.265805), abs=1e-5)
    assert result.map_origin == (550000.0, 5804000.0, 55.0)
    text = (out / METADATA_NAME).read_text()
    assert '# Map frame georeference (map_origin, metres; add it to x, y, z): 550000.0 5804000.0 55.0' in text
    assert f'x_resolution: {float(grid)}\n' in text
    assert not [p for p in out.iterdir() if p.name.startswith('.')]  # no temporary or spill file left


def test_twenty_metre_cells_split_the_fifty_metre_ones(small_map, tmp_path):
    fmap, _ = small_map
    _, fine = _read_export(export_autoware(fmap, tmp_path / 'a', 20, prefix='p').folder, 20)
    _, coarse = _read_export(export_autoware(fmap, tmp_path / 'b', 50, prefix='p').folder, 50)
    for name, rows in coarse.items():
        x0, y0 = (int(v) for v in re.fullmatch(r'p_(-?\d+)_(-?\d+)\.pcd', name).groups())
        parts = [r for n, r in fine.items()
                 if x0 <= int(n.split('_')[1]) < x0 + 50 and y0 <= int(n.split('_')[2][:-4]) < y0 + 50]
        assert np.array_equal(_rows_sorted(np.concatenate(parts)), _rows_sorted(rows))
    assert [len(coarse[n]) for n in sorted(coarse)] == [87, 53_942]


def test_a_tiled_map_exports_as_its_one_file_map(small_map, tmp_path, capsys):
    from uncertain_facade_map.tiling.cut import cut_map
    from uncertain_facade_map.tiling.tiled_map import TiledMap

    fmap, _ = small_map
    folder = tmp_path / 'tiled'
    manifest = cut_map(fmap, folder, 10.0)
    assert sorted(manifest.tiles) == ['tile_0_1', 'tile_3_1']  # the two buildings; the first reaches x < 0
    for grid in (50, 20):  # at 50 m the cell [0, 0] takes points of both tiles (through the spill files)
        done = []
        result = export_autoware(folder, tmp_path / f'out{grid}', grid, progress=lambda d, n: done.append((d, n)))
        assert done == [(1, 2), (2, 2)]
        _, tiled = _read_export(tmp_path / f'out{grid}', grid)
        _, whole = _read_export(export_autoware(fmap, tmp_path / f'one{grid}', grid).folder, grid)
        assert tiled.keys() == whole.keys()
        assert all(np.array_equal(_rows_sorted(tiled[n]), _rows_sorted(whole[n])) for n in whole)
    assert result.map_origin == (550000.0, 5804000.0, 55.0) and result.points == 54_029
    assert not [p for p in (tmp_path / 'out20').iterdir() if p.name.startswith('.')]  # spill files removed
    # Through the reader (its LRU bounded to one tile), and from the command line.
    _, via_reader = _read_export(export_autoware(TiledMap(folder, cache_mb=1e-6), tmp_path / 'reader').folder, 20)
    assert all(np.array_equal(via_reader[n], tiled[n]) for n in tiled)
    assert main(['export', str(folder / 'manifest.json'), '--out', str(tmp_path / 'cli'), '--quiet']) == 0
    assert 'exported 54,029 points in 4 files of 20 m' in capsys.readouterr().out


def test_cli_export_prints_files_points_and_bounds(small_map, tmp_path, capsys):
    _, path = small_map
    out = tmp_path / 'cli'
    assert main(['export', str(path), '--out', str(out), '--format', 'autoware', '--grid', '50', '--prefix', 'street',
                 '--quiet']) == 0
    text = capsys.readouterr().out
    assert f'{out / "street_-50_0.pcd"}  87 points  cell [-50, 0]' in text
    assert 'exported 54,029 points in 2 files of 50 m' in text
    assert 'bounds x -0.011..40.087 y 7.654..15.231 z -0.147..12.266 m' in text
    assert main(['export', str(path), '--out', str(out), '--quiet']) == 2  # an earlier export is kept
    assert 'already holds an export' in capsys.readouterr().err
    (out / 'stale_1000_1000.pcd').write_bytes(b'')
    (out / '.street_0_0.pcd.k3j2.tmp').write_bytes(b'')  # what a killed export leaves
    (out / 'notes.txt').write_text('kept')
    assert main(['export', str(path), '--out', str(out), '--quiet', '--force']) == 0
    assert sorted(p.name for p in out.iterdir()) == ['notes.txt', *(f'pointcloud_map_{x}_0.pcd' for x in (-20, 0, 20, 40)),
                                                     METADATA_NAME]


@pytest.mark.parametrize('kwargs, words', [
    (dict(grid=12.5), 'whole number of metres'), (dict(grid=0), 'whole number'), (dict(grid=float('nan')), 'whole'),
    (dict(prefix='../up'), 'cannot start a PCD file name'), (dict(prefix='-x'), 'cannot start'),
])
def test_bad_settings_are_input_errors(small_map, tmp_path, kwargs, words):
    with pytest.raises(InputError, match=words):
        export_autoware(small_map[0], tmp_path / 'x', **kwargs)
    assert not (tmp_path / 'x').exists()


def test_bad_places_are_input_errors(small_map, tmp_path):
    with pytest.raises(InputError, match='no folder'):
        export_autoware(small_map[0], tmp_path / 'missing' / 'x')
    (tmp_path / 'file').write_text('')
    with pytest.raises(InputError, match='not a folder'):
        export_autoware(small_map[0], tmp_path / 'file')
    with pytest.raises(InputError, match='no such'):
        export_autoware(tmp_path / 'nothing.npz', tmp_path / 'y')


def test_points_far_from_the_map_origin_are_refused_not_rounded():
    _check_float32(np.array([[131_071.9, -5.0, 3.0], [0.0, -100_000.0, 0.0]]))
    with pytest.raises(InputError, match=r'200,000 m .* keeps only 1.56 cm: give the map a map origin near its data'):
        _check_float32(np.array([[1.0, -200_000.0, 3.0]]))
    with pytest.raises(InputError, match='float32'):
        _check_float32(np.array([[np.nan, 0.0, 0.0]]))


def test_an_empty_map_gives_metadata_without_files(tmp_path):
    result = export_autoware(FacadeMap(), tmp_path / "e")
    assert result.files == [] and result.points == 0
    assert loader_metadata(tmp_path / 'e', result.metadata) == {}


@settings(max_examples=200, deadline=None)
@given(x=st.floats(-1e4, 1e4), y=st.floats(-1e4, 1e4), grid=st.sampled_from([1, 20, 50, 100]),
       shift=st.sampled_from([0.0, -1e-7, 1e-7]))
def test_a_point_goes_to_the_cell_holding_its_float32_value(x, y, grid, shift):
    rows = np.zeros(3, PCD_DTYPE)
    # The point itself, and points right on / just off a cell corner near it.
    corner = np.floor(x / grid) * grid
    rows['x'] = [x, corner, corner + shift]
    rows['y'] = [y, np.floor(y / grid) * grid, y]
    cells = _cells(rows, grid)
    for r, (cx, cy) in zip(rows, cells):
        assert cx % grid == 0 and cy % grid == 0
        assert cx <= float(r['x']) < cx + grid and cy <= float(r['y']) < cy + grid
