"""``uncertain-facade-map localise`` on a small map and scans of another drive: JSON out, the
prior given three ways, georeferenced coordinates, and one-line errors. About 4 s."""

import json
import sys
from pathlib import Path

import numpy as np
import pytest

from uncertain_facade_map.io.cloud import Cloud
from uncertain_facade_map.io.clouds import write_cloud
from uncertain_facade_map.io.map_file import save_map
from uncertain_facade_map.localisation import se3, xyzrpy_from_pose
from uncertain_facade_map.localisation.solver import centred_log
from uncertain_facade_map_apps.cli import main

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / 'localisation'))
from map_scans import sensor_scan  # noqa: E402

ORIGIN = np.array([500_000.0, 5_400_000.0, 400.0])


@pytest.fixture(scope='module')
def files(scenes, tmp_path_factory):
    """A map of the small scene (with a georeference) and two scans of campaign 1 as PLY and NPZ."""
    out = tmp_path_factory.mktemp('localise')
    fmap = scenes.building_map('small', 0, ORIGIN)
    save_map(fmap, out / 'map.npz')
    truths = []
    for k, (frac, suffix) in enumerate(((0.45, '.ply'), (0.6, '.npz'))):
        scan, truth = sensor_scan(scenes.scene('small'), scenes.campaign('small', 1), 1, frac, 4000)
        points = np.zeros(len(scan), dtype=[('x', 'f8'), ('y', 'f8'), ('z', 'f8')])
        points['x'], points['y'], points['z'] = scan.T
        write_cloud(out / f'scan{k}{suffix}', Cloud(points))
        truths.append(truth)
    return out, truths


def _prior_text(truth, offset=(1.2, -0.8, 0.2), turn_deg=2.0, origin=(0.0, 0.0, 0.0)):
    prior = se3.compose(se3.se3_exp(np.array([0, 0, 0, 0, 0, np.deg2rad(turn_deg)])), truth)
    prior[:3, 3] = truth[:3, 3] + np.asarray(offset) + np.asarray(origin)
    v = xyzrpy_from_pose(prior)
    return prior, [*v[:3], *np.rad2deg(v[3:])]


def _check(record, truth):
    pose = np.array(record['pose'])
    d = centred_log(truth, pose, pose[:3, 3])
    assert np.hypot(d[0], d[1]) < 0.1 and np.rad2deg(abs(d[5])) < 0.2, d
    assert record['points_used'] > 100 and record['queries'] >= 2 and isinstance(record['converged'], bool)
    assert np.array(record['covariance']).shape == (6, 6)
    assert abs(d[2]) < 4 * record['std'][2] + 0.02  # the height: as well as the covariance says


def test_one_scan_prior_on_the_command_line(files, capsys):
    out, truths = files
    _, values = _prior_text(truths[0])
    assert main(['localise', str(out / 'map.npz'), str(out / 'scan0.ply'), '--prior', ','.join(f'{v:.6f}' for v in values),
                 '--prior-std', '2,2,2,3,3,3']) == 0
    record = json.loads(capsys.readouterr().out)
    _check(record, truths[0])
    assert record['frame'] == 'map' and record['points'] == 4000
    np.testing.assert_allclose(record['xyz'], np.array(record['pose'])[:3, 3])


def test_prior_as_a_matrix_and_constant_variance(files, capsys):
    out, truths = files
    prior, _ = _prior_text(truths[1])
    np.save(out / 'prior.npy', prior)
    assert main(['localise', str(out / 'map.npz'), str(out / 'scan1.npz'), '--prior', str(out / 'prior.npy'),
                 '--constant-variance', '0.0001', '--out', str(out / 'pose.json')]) == 0
    assert 'localised' in capsys.readouterr().out
    _check(json.loads((out / 'pose.json').read_text()), truths[1])


def test_several_scans_georeferenced(files, capsys):
    out, truths = files
    lines = [' '.join(f'{v:.6f}' for v in _prior_text(t, origin=ORIGIN)[1]) for t in truths]
    (out / 'priors.txt').write_text('# x y z roll pitch yaw\n' + '\n'.join(lines) + '\n')
    assert main(['localise', str(out / 'map.npz'), str(out / 'scan0.ply'), str(out / 'scan1.npz'), '--priors',
                 str(out / 'priors.txt'), '--georeferenced', '--out', str(out / 'poses.jsonl')]) == 0
    records = [json.loads(line) for line in (out / 'poses.jsonl').read_text().splitlines()]
    assert len(records) == 2
    for record, truth in zip(records, truths):
        assert record['frame'] == 'georeferenced'
        pose = np.array(record['pose'])
        pose[:3, 3] -= ORIGIN
        _check({**record, 'pose': pose.tolist()}, truth)


@pytest.mark.parametrize('args, words', [
    (['--prior', '1,2,3'], 'six numbers'),
    ([], 'give the prior pose'),
    (['--prior', '0,0,0,0,0,0', '--prior-std', '1,1,1,1,1,0'], 'must be > 0'),
    (['--priors', 'PRIORS'], '1 prior poses for 2 scans'),
    (['--prior', 'NOPE.npy'], 'no such file'),
    (['--prior', '0,0,0,0,0,0', '--constant-variance', '-1'], '>= 0'),
])
def test_bad_input_one_line_exit_2(files, tmp_path, capsys, args, words):
    out, _ = files
    (tmp_path / 'priors.txt').write_text('0 0 0 0 0 0\n')
    args = [str(tmp_path / 'priors.txt') if a == 'PRIORS' else str(tmp_path / a) if a == 'NOPE.npy' else a
            for a in args]
    scans = [str(out / 'scan0.ply'), str(out / 'scan1.npz')] if 'PRIORS' in str(args) or 'priors' in str(args) \
        else [str(out / 'scan0.ply')]
    code = main(['localise', str(out / 'map.npz'), *scans, *args])
    err = capsys.readouterr().err
    assert code == 2, err
    assert err.count('\n') == 1 and err.startswith('uncertain-facade-map: error:') and words in err, err


def test_missing_scan_one_line(files, capsys):
    out, _ = files
    assert main(['localise', str(out / 'map.npz'), str(out / 'nope.ply'), '--prior', '0,0,0,0,0,0']) == 2
    err = capsys.readouterr().err
    assert err.count('\n') == 1 and 'nope.ply' in err, err


def test_help_tells_how_to_localise_a_drive(capsys):
    with pytest.raises(SystemExit):
        main(['localise', '--help'])
    text = capsys.readouterr().out
    for words in ('SENSOR frame', '--priors', '--georeferenced', 'build', 'converged'):
        assert words in text
