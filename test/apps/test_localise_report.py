"""The localisation report end to end on a tiny run (scene small, two scans, every row):
its files, its structure, row (d) equal to the perturbations, the localiser's own row
better than the prior; a failing row is recorded, not fatal. About 4 s (4.0-4.4 s, three runs on a busy machine)."""

import contextlib
import io
import json

import numpy as np
import pytest

from uncertain_facade_map.evaluation import localisation as L
from uncertain_facade_map_apps import localise_report as app


@pytest.fixture(scope='module')
def report(tmp_path_factory):
    out = tmp_path_factory.mktemp('loc') / 'report'
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        code = app.main(['--out', str(out), '--scenes', 'small', '--campaigns', '1', '--scans-per-drive', '2',
                         '--max-points', '3000', '--real', 'off', '--seed', '2'])
    assert code == 0
    return out, json.loads((out / 'report.json').read_text()), printed.getvalue()


def test_files_and_structure(report):
    out, data, printed = report
    assert (out / 'localisation.png').stat().st_size > 10_000
    md = (out / 'report.md').read_text()
    assert md.startswith('# Localisation against the uncertain map')
    assert 'Command: `python -m uncertain_facade_map_apps.localise_report --out' in md
    for row in app.ROW_NAMES.values():
        # the scenario's and the pooled table (and the scan-by-scan one for (b), (c), (e))
        assert md.count(f'| {row} |') == (3 if row[1] in 'bce' else 2)
    assert set(data['summary']) == {'small'}
    assert list(data['summary']['small']) == list(app.ROW_NAMES.values())
    assert len(data['scans']) == 2 * len(app.ROW_NAMES)
    for s in data['summary']['small'].values():
        assert s['n'] == 2
        assert set(s) >= {'position_median', 'position_p95', 'heading_median', 'heading_p95', 'good_share',
                          'nees_mean', 'nees_in_band', 'ms_median'}
    assert data['summary']['small'][app.ROW_NAMES['c']]['nees_mean'] is None     # GICP: no covariance
    assert '| (c) GICP raw points | 2 |' in md and 'n/a' in md
    assert data['summary']['small'][app.ROW_NAMES['e']]['nees_mean'] is None
    assert 'small' in data['meta']['constant_variance']
    assert '## Scan by scan' in md and '| clean | (b) map, constant variance | 2 |' in md


def test_prior_row_is_the_perturbation_and_the_localiser_beats_it(report):
    _, data, _ = report
    prior = [s for s in data['scans'] if s['row'] == app.ROW_NAMES['d']]
    for s in prior:
        assert s['error'] == pytest.approx(s['prior_error'], abs=1e-12)
        assert s['position'] == pytest.approx(np.linalg.norm(s['prior_error'][:3]))
        assert 0.5 - 0.06 <= np.hypot(*s['prior_error'][:2]) <= 3.0
    ours = [s for s in data['scans'] if s['row'] == app.ROW_NAMES['a']]
    assert np.median([s['position'] for s in ours]) < 0.5 * np.median([s['position'] for s in prior])


def test_a_failing_row_is_recorded():
    scenario = L.simulated_scenario('small', campaigns=(1,), scans_per_drive=1, max_points=500)

    def broken(scan, prior, cov, sc):
        raise RuntimeError('no map')

    lines = []
    (out,) = L.run([scenario], {'broken': broken}, progress=lines.append)
    assert out.converged is False and np.isnan(out.nees)
    np.testing.assert_allclose(out.error, scenario.cases[0].delta, atol=1e-12)
    assert any('failed (RuntimeError: no map)' in line for line in lines)


def test_bad_rows_exit_2(tmp_path, capsys):
    assert app.main(['--out', str(tmp_path), '--rows', 'a,z', '--quick']) == 2
    assert 'unknown rows' in capsys.readouterr().err
