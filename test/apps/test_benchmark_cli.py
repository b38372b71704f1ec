"""``uncertain-facade-map benchmark``: a table per input, the JSON and the figure, the simulated
scene against its truth, and one-line errors."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest

from uncertain_facade_map.evaluation.benchmark import LEVELS, MAP_NAMES, SPLITS
from uncertain_facade_map.io.cloud import Cloud
from uncertain_facade_map.io.npz import write_npz
from uncertain_facade_map_apps.cli import main


@pytest.fixture(scope='module')
def scene_run(tmp_path_factory):
    out = tmp_path_factory.mktemp('bench') / 'out'  # does not exist yet: its parent does
    import contextlib
    import io

    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        code = main(['benchmark', '--scene', 'small', '--out', str(out), '--quiet', '--holdout', '0.4'])
    assert code == 0
    return out, printed.getvalue()


def test_scene_prints_both_tables_and_writes_json_and_png(scene_run):
    out, text = scene_run
    assert sorted(p.name for p in out.iterdir()) == ['scene_small.json', 'scene_small.png']
    assert 'against the held-out points' in text and 'against the exact truth' in text
    rows = re.findall(r'^(?:\S.{15}|\s{16}) (this package|local plane|façade plane)\s+[0-9,]+\s+', text, re.M)
    assert len(rows) == 2 * 7 * 3
    record = json.loads((out / 'scene_small.json').read_text())
    assert record['command'].startswith('uncertain-facade-map benchmark')
    held, truth = record['results']
    assert held['against'] == 'held-out points' and truth['against'] == 'exact truth'
    assert held['settings']['holdout'] == 0.4 and held['levels'] == list(LEVELS)
    assert [m['name'] for m in held['maps']] == list(MAP_NAMES)
    local = held['maps'][MAP_NAMES.index('local plane')]
    assert set(local['metrics']) == set(SPLITS)
    assert 0.95 < local['metrics']['observed']['cov95'] <= 1.0
    assert len(local['calibration']['occluded']) == len(LEVELS)
    # The table prints what the JSON holds (RMSE of the local plane, observed, to 3 decimals).
    line = re.search(r'^observed\s+this package.*\n.*\n\s+local plane\s+[0-9,]+\s+[0-9.]+\s+([0-9.]+)', text, re.M)
    assert float(line.group(1)) == pytest.approx(local['metrics']['observed']['rmse'], abs=5e-4)
    from matplotlib.image import imread

    img = imread(out / 'scene_small.png')
    assert img.shape[0] > 600 and img.shape[1] > 1000


def test_inputs_each_get_their_table(scenes, tmp_path, capsys):
    """A classified cloud file is mapped from its class field; two inputs, two tables and files."""
    cloud = scenes.campaign('small', 0)
    for name, b in (('a', 1), ('b', 0)):
        write_npz(tmp_path / f'{name}.npz', Cloud(cloud.points[cloud.points['building_id'] == b], cloud.map_origin))
    n_a = int(((cloud.points['building_id'] == 1) & (cloud.points['class'] == 1)).sum())
    assert main(['benchmark', str(tmp_path / 'a.npz'), str(tmp_path / 'b.npz'), '--out', str(tmp_path / 'o'),
                 '--quiet', '--max-scored', '2000']) == 0
    text = capsys.readouterr().out
    assert text.count('against the held-out points') == 2 and 'exact truth' not in text
    assert "class field 'class' in [1]" in text
    assert re.search(rf'a\.npz: .* {n_a:,} building points', text) and '2,000 scored' in text
    assert sorted(p.name for p in (tmp_path / 'o').iterdir()) == ['a.json', 'a.png', 'b.json', 'b.png']


@pytest.mark.parametrize('args, words', [
    (['benchmark'], 'give INPUT clouds or --scene'),
    (['benchmark', 'missing.ply'], 'no such file: missing.ply'),
    (['benchmark', '--scene', 'small', 'x.ply'], 'not both'),
    (['benchmark', '--scene', 'small', '--holdout', '1.5'], 'held-out share'),
    (['benchmark', 'few.npz'], 'too few building points for the benchmark: 300'),
    (['benchmark', 'flat.npz'], 'no façade found'),
])
def test_bad_input_gives_one_line_and_exit_2(tmp_path, capsys, monkeypatch, args, words):
    monkeypatch.chdir(tmp_path)
    rng = np.random.default_rng(0)
    for name, xyz in (('few.npz', rng.uniform(0, 10, (300, 3))),
                      ('flat.npz', rng.uniform(-20, 20, (5000, 3)) * [1, 1, 0])):
        points = np.zeros(len(xyz), dtype=[('x', 'f8'), ('y', 'f8'), ('z', 'f8'), ('class', 'u1')])
        points['x'], points['y'], points['z'] = xyz.T
        if name == 'flat.npz':  # no class field: the wall pick finds no wall
            points = points[['x', 'y', 'z']]
        else:
            points['class'] = 1
        write_npz(tmp_path / name, Cloud(points, np.zeros(3)))
    code = main(args + ['--out', str(tmp_path / 'o'), '--quiet'])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1, err
    assert err[0].startswith('uncertain-facade-map: error: ') and words in err[0], err


def test_bad_sensor_is_refused_by_the_parser(capsys):
    with pytest.raises(SystemExit) as exc:
        main(['benchmark', 'x.ply', '--sensor', '1,2'])
    assert exc.value.code == 2 and 'expected X,Y,Z' in capsys.readouterr().err
