"""The commands that take a MAP read a tiled map (its folder or its manifest.json) as they
read the map file it was cut from: query (the same answers), localise (the same poses), plot
(every façade, or the tiles within --bounds); ``tile`` cuts a map file; one-line errors.
About 12 s."""

import json
import sys
from pathlib import Path

import numpy as np
import pytest

from uncertain_facade_map.io.cloud import Cloud
from uncertain_facade_map.io.clouds import write_cloud
from uncertain_facade_map.io.map_file import save_map
from uncertain_facade_map.localisation import xyzrpy_from_pose
from uncertain_facade_map.tiling.manifest import MANIFEST, read_manifest
from uncertain_facade_map.tiling.tiled_map import TiledMap
from uncertain_facade_map_apps.cli import main

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / 'localisation'))
from map_scans import sensor_scan  # noqa: E402

ORIGIN = np.array([500_000.0, 5_400_000.0, 400.0])


@pytest.fixture(scope='module')
def files(scenes, tmp_path_factory):
    """The small scene's map (georeferenced), cut into 10 m tiles by ``tile``, and a scan of campaign 1."""
    out = tmp_path_factory.mktemp('tiled_cli')
    fmap = scenes.building_map('small', 0, ORIGIN)
    save_map(fmap, out / 'map.npz')
    assert main(['tile', str(out / 'map.npz'), '--out', str(out / 'tiled'), '--side', '10', '--quiet']) == 0
    scan, truth = sensor_scan(scenes.scene('small'), scenes.campaign('small', 1), 1, 0.45, 4000)
    points = np.zeros(len(scan), dtype=[('x', 'f8'), ('y', 'f8'), ('z', 'f8')])
    points['x'], points['y'], points['z'] = scan.T
    write_cloud(out / 'scan.ply', Cloud(points))
    return out, fmap, truth


def test_tile_writes_a_tiled_map(files, capsys):
    out, fmap, _ = files
    m = read_manifest(out / 'tiled')
    assert len(m.tiles) == 2 and m.side == 10.0 and sorted(m.building_tiles) == fmap.buildings
    assert m.map_origin == tuple(ORIGIN)
    # Not over an existing one unless --force.
    assert main(['tile', str(out / 'map.npz'), '--out', str(out / 'tiled'), '--quiet']) == 2
    assert 'already holds a tiled map' in capsys.readouterr().err


@pytest.mark.parametrize('which', ['folder', 'manifest'])
def test_query_answers_as_the_map_file(files, tmp_path, which):
    out, fmap, _ = files
    rng = np.random.default_rng(0)
    pts = np.vstack(list(fmap.points.values()))
    xyz = np.vstack([pts[rng.choice(len(pts), 3000)] + rng.normal(0, 0.2, (3000, 3)),
                     rng.uniform(pts.min(0) - 2, pts.max(0) + 2, (2000, 3))])
    np.save(tmp_path / 'p.npy', xyz)
    tiled = out / 'tiled' if which == 'folder' else out / 'tiled' / MANIFEST
    assert main(['query', str(out / 'map.npz'), '--points', str(tmp_path / 'p.npy'), '--out', str(tmp_path / 'a.npz')]) == 0
    assert main(['query', str(tiled), '--points', str(tmp_path / 'p.npy'), '--out', str(tmp_path / 'b.npz')]) == 0
    a, b = np.load(tmp_path / 'a.npz'), np.load(tmp_path / 'b.npz')
    assert sorted(a.files) == sorted(b.files)
    for key in a.files:
        if key == 'facade':  # the tiled map numbers its façades tile by tile
            np.testing.assert_array_equal(a[key] >= 0, b[key] >= 0)
            merged = TiledMap(out / 'tiled').merged()
            on = b[key] >= 0
            frames = np.array([merged.facades[i].frame.origin for i in b[key][on]])
            np.testing.assert_array_equal(frames, np.array([fmap.facades[i].frame.origin for i in a[key][on]]))
        else:
            np.testing.assert_array_equal(a[key], b[key], err_msg=key)


def test_localise_on_the_tiled_map_gives_the_same_pose(files, capsys):
    out, _, truth = files
    v = xyzrpy_from_pose(truth)
    prior = [v[0] + 1.0, v[1] - 0.7, v[2] + 0.2, *np.rad2deg(v[3:5]), np.rad2deg(v[5]) + 2.0]
    args = [str(out / 'scan.ply'), '--prior', ','.join(f'{x:.6f}' for x in prior), '--prior-std', '2,2,2,3,3,3']
    assert main(['localise', str(out / 'map.npz'), *args]) == 0
    one = json.loads(capsys.readouterr().out)
    assert main(['localise', str(out / 'tiled'), *args]) == 0
    tiled = json.loads(capsys.readouterr().out)
    np.testing.assert_allclose(tiled['pose'], one['pose'], atol=1e-9)
    assert tiled['points_used'] == one['points_used'] and tiled['iterations'] == one['iterations']
    assert np.hypot(*(np.array(tiled['xyz'][:2]) - truth[:2, 3])) < 0.1


def test_plot_a_tiled_map_whole_and_within_bounds(files, tmp_path, capsys):
    out, fmap, _ = files
    assert main(['plot', str(out / 'tiled'), '--out', str(tmp_path / 'all'), '--quiet', '--dpi', '40']) == 0
    assert len(list((tmp_path / 'all').glob('facade_*.png'))) == len(fmap.facades)
    assert (tmp_path / 'all' / 'overview.png').exists()
    m = TiledMap(out / 'tiled')
    first = m.records[0]
    x0, y0 = first.extent[0], first.extent[1]
    assert main(['plot', str(out / 'tiled'), '--out', str(tmp_path / 'part'), '--quiet', '--dpi', '40',
                 f'--bounds={x0},{y0},{x0 + 0.5},{y0 + 0.5}']) == 0  # '=': the values may be negative
    n = len(m.merged(bounds=(x0, y0, x0 + 0.5, y0 + 0.5)).facades)
    assert 0 < n < len(fmap.facades)
    assert len(list((tmp_path / 'part').glob('facade_*.png'))) == n
    capsys.readouterr()


@pytest.mark.parametrize('case, words', [
    ('folder without manifest', 'not a tiled map (no manifest.json in the folder)'),
    ('bounds on a map file', '--bounds is for tiled maps'),
    ('bounds outside', 'no tile of'),
    ('damaged manifest', 'damaged manifest'),
])
def test_bad_input_one_line_exit_2(files, tmp_path, capsys, case, words):
    out, _, _ = files
    (tmp_path / 'p.npy').write_bytes(b'')
    np.save(tmp_path / 'p.npy', np.zeros((3, 3)))
    if case == 'folder without manifest':
        (tmp_path / 'empty').mkdir()
        args = ['query', str(tmp_path / 'empty'), '--points', str(tmp_path / 'p.npy'), '--out', str(tmp_path / 'r.npz')]
    elif case == 'bounds on a map file':
        args = ['plot', str(out / 'map.npz'), '--out', str(tmp_path / 'f'), '--quiet', '--bounds', '0,0,1,1']
    elif case == 'bounds outside':
        args = ['plot', str(out / 'tiled'), '--out', str(tmp_path / 'f'), '--quiet', '--bounds', '1e6,1e6,2e6,2e6']
    else:
        (tmp_path / 'bad').mkdir()
        (tmp_path / 'bad' / MANIFEST).write_text('{"format": "uncertain_facade_map.tiles", "version": 1}')
        args = ['localise', str(tmp_path / 'bad'), str(out / 'scan.ply'), '--prior', '0,0,0,0,0,0']
    code = main(args)
    err = capsys.readouterr().err
    assert code == 2, err
    assert err.count('\n') == 1 and err.startswith('uncertain-facade-map: error:') and words in err, err
