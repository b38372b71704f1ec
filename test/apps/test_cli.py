"""The command line: simulate writes every format loss-free; bad input is one line, exit 2."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from msg_adapters.bag_io import read_bag, read_bag_cloud
from uncertain_facade_map.io.npz import read_npz
from uncertain_facade_map.io.ply import read_ply
from uncertain_facade_map_apps.cli import main


@pytest.fixture(scope='module')
def simulated(tmp_path_factory):
    out = tmp_path_factory.mktemp('sim')
    code = main(['simulate', '--scene', 'small', '--out', str(out), '--campaigns', '2',
                 '--formats', 'npz,ply,sqlite3,mcap,rosbag1', '--quiet'])
    assert code == 0
    return out


def test_simulate_writes_all_formats_and_they_agree(simulated):
    npz = read_npz(simulated / 'campaign0.npz')
    assert len(npz) > 10_000
    ply = read_ply(simulated / 'campaign0.ply')
    assert ply.same_as(npz)
    for bag in ('campaign0_sqlite3', 'campaign0_mcap', 'campaign0.bag'):
        cloud = read_bag_cloud([simulated / bag])
        assert cloud.same_as(npz), bag
    assert (simulated / 'campaign1.npz').exists() and not (simulated / 'campaign1.ply').exists()


def test_bag_messages_are_scans_of_a_tenth_of_a_second(simulated):
    bag = read_bag([simulated / 'campaign0_mcap'])
    stamps = np.array([s for s, _ in bag.scans])
    assert len(bag.scans) > 50
    assert np.all(np.diff(stamps) >= 100_000_000 - 1)
    for stamp, pts in bag.scans:
        span = pts['time'] - stamp * 1e-9
        assert span.min() >= -1e-6 and span.max() < 0.1 + 1e-6


def test_scene_json_describes_campaigns_and_truth(simulated):
    desc = json.loads((simulated / 'scene.json').read_text())
    assert desc['scene'] == 'small' and desc['seed'] == 0
    assert [c['role'] for c in desc['campaigns']] == ['mapped', 'reference']
    assert desc['campaigns'][0]['points'] == len(read_npz(simulated / 'campaign0.npz'))
    assert len(desc['buildings']) == 2
    kinds = {f['type'] for b in desc['buildings'] for fa in b['facades'] for f in fa['features']}
    assert {'Recess', 'Block', 'Slope', 'Round'} <= kinds


def test_existing_output_needs_force(simulated, capsys):
    code = main(['simulate', '--scene', 'small', '--out', str(simulated), '--formats', 'npz', '--quiet'])
    err = capsys.readouterr().err
    assert code == 2
    assert err.count('\n') == 1 and 'use --force' in err
    assert main(['simulate', '--scene', 'small', '--out', str(simulated), '--formats', 'npz', '--quiet',
                 '--force']) == 0


@pytest.mark.parametrize('args, words', [
    (['--campaigns', '0'], '--campaigns'),
    (['--formats', 'xyz'], 'unknown format'),
    (['--scene', 'moon'], 'invalid choice'),
    (['--range-noise', '-1'], 'range_noise'),
    (['--scan-period', '0'], 'scan period'),
])
def test_bad_arguments_give_one_line_and_exit_2(tmp_path, capsys, args, words):
    try:
        code = main(['simulate', '--scene', 'small', '--out', str(tmp_path), '--quiet', '--formats', 'sqlite3', *args])
    except SystemExit as exc:  # argparse errors
        code = exc.code
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2
    assert words in err[-1] and 'Traceback' not in '\n'.join(err)


def test_console_script_is_installed(tmp_path):
    script = Path(sys.executable).parent / 'uncertain-facade-map'
    assert script.exists(), 'run make venv (pip install -e .)'
    result = subprocess.run([str(script), 'simulate', '--help'], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0 and '--campaigns' in result.stdout


@pytest.fixture(scope='module')
def built(simulated):
    out = simulated / 'map.npz'
    assert main(['build', str(simulated / 'campaign0.npz'), '--out', str(out), '--quiet']) == 0
    return out


def test_build_from_a_bag_gives_the_same_map(simulated, built):
    from uncertain_facade_map.io.map_file import load_map

    out = simulated / 'map_bag.npz'
    assert main(['build', str(simulated / 'campaign0_mcap'), '--out', str(out), '--quiet']) == 0
    a, b = load_map(built), load_map(out)
    assert len(a.facades) == len(b.facades) > 0
    for fa, fb in zip(a.facades, b.facades):
        np.testing.assert_array_equal(fa.surface.mean, fb.surface.mean)


def test_query_contract(simulated, built, tmp_path):
    pts = read_npz(simulated / 'campaign0.npz').xyz[::50]
    np.save(tmp_path / 'p.npy', pts)
    assert main(['query', str(built), '--points', str(tmp_path / 'p.npy'), '--out', str(tmp_path / 'r.npz'),
                 '--resolution', '0.05']) == 0
    with np.load(tmp_path / 'r.npz') as r:
        assert set(r.files) == {'facade', 'mean_depth', 'variance', 'noise_variance', 'signed_distance', 'p_occupied',
                                'normal'}
        assert all(r[k].shape == ((len(pts), 3) if k == 'normal' else (len(pts),)) for k in r.files)
        assert np.issubdtype(r['facade'].dtype, np.integer)
        on = r['facade'] >= 0
        assert on.mean() > 0.3
        assert np.nanmedian(np.abs(r['signed_distance'][on])) < 0.05
        np.testing.assert_allclose(np.linalg.norm(r['normal'][on], axis=1), 1.0, atol=1e-12)
        assert np.isnan(r['normal'][~on]).all()
        # mostly horizontal: façades are vertical
        assert np.median(np.abs(r['normal'][on, 2])) < 0.2


def test_query_reads_the_learnt_plsc_unless_the_configuration_says_fixed(simulated, built, tmp_path):
    from uncertain_facade_map.io.map_file import load_map
    from uncertain_facade_map.pipeline.step8_occupancy import FIXED

    learnt = load_map(built).occupancy_
    assert learnt.learnt and learnt != FIXED, 'build learns the PLSC parameters from points with sensor origins'
    pts = read_npz(simulated / 'campaign0.npz').xyz[::50]
    np.save(tmp_path / 'p.npy', pts)
    # The solid event (the default, surface, is tested in test/pipeline/test_step7_local_surface.py).
    head = 'facade_mapper:\n  ros__parameters:\n    query:\n      occupancy_event: solid\n'
    (tmp_path / 'plsc.yaml').write_text(head)
    (tmp_path / 'fixed.yaml').write_text(head + '      occupancy: fixed\n')
    for name in ('plsc', 'fixed'):
        extra = ['--config', str(tmp_path / f'{name}.yaml')]
        assert main(['query', str(built), '--points', str(tmp_path / 'p.npy'), '--out', str(tmp_path / f'{name}.npz'),
                     *extra]) == 0
    with np.load(tmp_path / 'plsc.npz') as a, np.load(tmp_path / 'fixed.npz') as b:
        on = a['facade'] >= 0
        noise = a['noise_variance'][on]
        np.testing.assert_array_equal(a['p_occupied'][on],
                                      learnt.solid(a['signed_distance'][on], a['variance'][on], noise, 0.1))
        np.testing.assert_array_equal(b['p_occupied'][on],
                                      FIXED.solid(b['signed_distance'][on], b['variance'][on], noise, 0.1))


def test_cloud_without_class_is_all_building(tmp_path, simulated, capsys):
    from uncertain_facade_map.io.cloud import Cloud
    from uncertain_facade_map.io.npz import write_npz

    cloud = read_npz(simulated / 'campaign0.npz')
    pts = cloud.points[cloud.points['class'] == 1][['x', 'y', 'z']]
    write_npz(tmp_path / 'plain.npz', Cloud(pts.copy(), cloud.map_origin))
    assert main(['build', str(tmp_path / 'plain.npz'), '--out', str(tmp_path / 'm.npz'), '--quiet']) == 0
    # No class field, but hardly any ground: building points cut already, kept whole.
    out = capsys.readouterr().out
    assert f'({len(pts):,} building)' in out and 'selected all: no class field, but' in out


def test_build_selects_the_walls_of_a_cloud_without_classes(tmp_path, capsys):
    from support import unclassified_street

    from uncertain_facade_map.io.cloud import Cloud
    from uncertain_facade_map.io.ply import write_ply

    xyz, labels, _ = unclassified_street(seed=0)
    pts = np.zeros(len(xyz), dtype=[('x', 'f8'), ('y', 'f8'), ('z', 'f8')])
    pts['x'], pts['y'], pts['z'] = xyz.T
    write_ply(tmp_path / 'sweep.ply', Cloud(pts))
    assert main(['build', str(tmp_path / 'sweep.ply'), '--out', str(tmp_path / 'm.npz'), '--quiet']) == 0
    out = capsys.readouterr().out
    assert 'read     41,000 points (16,' in out and 'on 3 wall segments' in out
    assert 'mapped   2 buildings, 3 façades' in out  # the side wall and its corner are one building
    assert main(['build', str(tmp_path / 'sweep.ply'), '--out', str(tmp_path / 'm.npz'), '--quiet',
                 '--select', 'off']) == 0
    out = capsys.readouterr().out
    assert 'read     41,000 points (41,000 building)' in out and 'selected' not in out


def street_walls() -> np.ndarray:
    """(12000, 3) points of two 30 m x 9 m walls at y = -9 and y = 11 m (1 cm noise), metres."""
    rng = np.random.default_rng(2)
    walls = []
    for y in (-9.0, 11.0):
        u, z = rng.uniform(-15, 15, 6000), rng.uniform(0, 9, 6000)
        walls.append(np.c_[u, y + rng.normal(0, 0.01, 6000), z])
    return np.vstack(walls)


def test_build_turns_the_facades_to_a_given_sensor(tmp_path, capsys):
    """Two walls across a street in one cloud without origins or building ids, as one real
    sweep in its vehicle frame: from the shape alone each looks like the back of the other;
    with --sensor both face the street."""
    from uncertain_facade_map.io.cloud import Cloud
    from uncertain_facade_map.io.map_file import load_map
    from uncertain_facade_map.io.ply import write_ply

    xyz = street_walls()
    pts = np.zeros(len(xyz), dtype=[('x', 'f8'), ('y', 'f8'), ('z', 'f8')])
    pts['x'], pts['y'], pts['z'] = xyz.T
    write_ply(tmp_path / 'sweep.ply', Cloud(pts))
    assert main(['build', str(tmp_path / 'sweep.ply'), '--out', str(tmp_path / 'm.npz'), '--quiet',
                 '--select', 'off', '--sensor', '0,0,1.8']) == 0
    capsys.readouterr()
    facades = load_map(tmp_path / 'm.npz').facades
    assert len(facades) == 2
    for f in facades:
        assert f.frame.normal @ (np.array([0.0, 0.0, 1.8]) - f.frame.origin) > 0
    with pytest.raises(SystemExit) as exit_:
        main(['build', str(tmp_path / 'sweep.ply'), '--out', str(tmp_path / 'm.npz'), '--sensor', '0,0'])
    assert exit_.value.code == 2 and 'expected X,Y,Z' in capsys.readouterr().err


def test_build_turns_the_facades_to_a_trajectory(tmp_path, capsys):
    """The two walls of the test above, now with per-point times and no origins: a vehicle
    driving down the street between them (a TUM file) turns both to the street; the same
    drive 9 m beyond the north wall turns both to the north. Both options together are
    refused."""
    from uncertain_facade_map.io.cloud import Cloud
    from uncertain_facade_map.io.map_file import load_map
    from uncertain_facade_map.io.ply import write_ply

    xyz = street_walls()
    pts = np.zeros(len(xyz), dtype=[('x', 'f8'), ('y', 'f8'), ('z', 'f8'), ('time', 'f8')])
    pts['x'], pts['y'], pts['z'] = xyz.T
    pts['time'] = 100.0 + (xyz[:, 0] + 15) / 3  # seen as the vehicle passes at 3 m/s
    write_ply(tmp_path / 'sweep.ply', Cloud(pts))
    for street_y in (0.0, 20.0):
        t = np.linspace(100.0, 110.0, 11)
        poses = np.c_[t, 3 * (t - 100) - 15, np.full(11, street_y), np.full(11, 1.8), np.zeros((11, 3)), np.ones(11)]
        np.savetxt(tmp_path / 'poses.txt', poses, header='timestamp tx ty tz qx qy qz qw')
        assert main(['build', str(tmp_path / 'sweep.ply'), '--out', str(tmp_path / 'm.npz'), '--quiet',
                     '--select', 'off', '--trajectory', str(tmp_path / 'poses.txt')]) == 0
        capsys.readouterr()
        facades = load_map(tmp_path / 'm.npz').facades
        assert len(facades) == 2
        for f in facades:
            side = np.sign(street_y - f.frame.origin[1])
            assert f.frame.normal[1] * side > 0.9
    assert main(['build', str(tmp_path / 'sweep.ply'), '--out', str(tmp_path / 'm.npz'), '--sensor', '0,0,1',
                 '--trajectory', str(tmp_path / 'poses.txt')]) == 2
    assert 'not both' in capsys.readouterr().err


@pytest.mark.parametrize('case', ['missing input', 'nan points', 'float32 points', 'bad map', 'empty cloud',
                                  'missing config', 'bad config'])
def test_build_and_query_bad_input_one_line_exit_2(tmp_path, built, simulated, capsys, case):
    from uncertain_facade_map.io.cloud import Cloud
    from uncertain_facade_map.io.npz import write_npz

    good_points = tmp_path / 'p.npy'
    np.save(good_points, np.zeros((3, 3)))
    if case == 'missing input':
        args = ['build', str(tmp_path / 'nope.ply'), '--out', str(tmp_path / 'm.npz')]
    elif case == 'nan points':
        np.save(tmp_path / 'n.npy', np.array([[0.0, np.nan, 1.0]]))
        args = ['query', str(built), '--points', str(tmp_path / 'n.npy'), '--out', str(tmp_path / 'r.npz')]
    elif case == 'float32 points':
        np.save(tmp_path / 'f.npy', np.zeros((3, 3), np.float32))
        args = ['query', str(built), '--points', str(tmp_path / 'f.npy'), '--out', str(tmp_path / 'r.npz')]
    elif case == 'bad map':
        (tmp_path / 'bad.npz').write_bytes(b'garbage')
        args = ['query', str(tmp_path / 'bad.npz'), '--points', str(good_points), '--out', str(tmp_path / 'r.npz')]
    elif case == 'empty cloud':
        write_npz(tmp_path / 'e.npz', Cloud(np.zeros(0, dtype=[('x', 'f8'), ('y', 'f8'), ('z', 'f8')])))
        args = ['build', str(tmp_path / 'e.npz'), '--out', str(tmp_path / 'm.npz')]
    elif case == 'missing config':
        args = ['build', str(simulated / 'campaign0.npz'), '--out', str(tmp_path / 'm.npz'), '--config', 'nope.yaml']
    else:
        (tmp_path / 'c.yaml').write_text('facade_mapper:\n  ros__parameters:\n    gp:\n      c_min: 2.0\n')
        args = ['build', str(simulated / 'campaign0.npz'), '--out', str(tmp_path / 'm.npz'), '--config',
                str(tmp_path / 'c.yaml')]
    code = main([*args, '--quiet'] if args[0] == 'build' else args)
    err = capsys.readouterr().err
    assert code == 2, err
    assert err.count('\n') == 1 and err.startswith('uncertain-facade-map: error:'), err
