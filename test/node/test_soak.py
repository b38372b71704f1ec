"""The soak and fault suite's quick version (issue 13), about a minute: ``make soak`` runs the
long one (``uncertain_facade_map_apps.soak``).

One run of :func:`uncertain_facade_map_apps.soak.run` with :func:`quick_options` (the node in
its own process with the default parameter file, faster diagnostics and idle flush): a short
soak, SIGKILLs during ``save_map`` with restarts on the saved file, and the quick share of the
fuzz cases. Each property the issue asks for is one test, each fuzz case one parameter.

Against the node before issue 13's fixes, 2 properties (points adding up, temporary files
after a killed save) and 7 fuzz cases (1e30 m and 1e300 m coordinates, 1e30 m origins, x
read as INT32, a non-unit quaternion, a pose 1e30 m away, get_map on a map 200 m wide)
failed.
"""

from __future__ import annotations

from pathlib import Path

import pytest

pytestmark = pytest.mark.ros

pytest.importorskip('rclpy')
pytest.importorskip('uncertain_facade_map.srv')

from uncertain_facade_map_apps import soak  # noqa: E402

#: The properties of issue 13 (keys of the report's summary), fuzz cases apart.
PROPERTIES = ('soak_node_alive', 'soak_published_equals_received', 'soak_clouds_add_up', 'soak_points_add_up',
              'soak_queries_answered', 'kills_file_whole', 'kills_no_tmp_after_restart', 'kills_answers_identical',
              'kills_restarted')

@pytest.fixture(scope='module')
def report(tmp_path_factory):
    out = tmp_path_factory.mktemp('soak')
    result = soak.run(soak.quick_options(out, quiet=True))
    print(Path(result['files']['table']).read_text())
    return result


def test_the_quick_suite_runs_every_section(report):
    assert not report['errors'], report['errors']
    for section in soak.SECTIONS:
        assert report.get(section), section
    assert Path(report['files']['json']).exists() and Path(report['files']['png']).exists()
    assert len(report['soak']['samples']) >= 2
    assert set(report['fuzz']['cases']) == set(soak.QUICK_CASES)


def test_the_full_fuzz_list_is_long_enough():
    cases = soak.fuzz_cases()
    assert sum(not c.valid for c in cases) >= 84
    assert set(soak.QUICK_CASES) <= {c.name for c in cases}


@pytest.mark.parametrize('prop', PROPERTIES)
def test_property(report, prop):
    details = {'soak': report['soak'].get('accounting'), 'kills': report['kills'].get('kills')}
    assert report['summary'].get(prop) is True, details[prop.split('_')[0]]


@pytest.mark.parametrize('name', soak.QUICK_CASES)
def test_fuzz_case(report, name):
    case = report['fuzz']['cases'][name]
    assert case['passed'], f'{case["outcome"]}: {case.get("exception") or case.get("detail")}'
