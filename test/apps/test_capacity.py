"""The capacity plan (:mod:`uncertain_facade_map_apps.capacity`) on a tiled build's report: the
fitted cost per point and per tile recover known figures, and the plan's arithmetic holds; a
real ``build --tiles`` report (the `small` scene) gives every tile task. About 3 s."""

import json

import numpy as np
import pytest

from uncertain_facade_map.io.npz import write_npz
from uncertain_facade_map_apps import capacity
from uncertain_facade_map_apps.cli import main


def _report(per_tile, per_point, points):
    return {'input_points': 4 * int(sum(points)), 'building_points': int(sum(points)), 'read_seconds': 2.0,
            'route_seconds': 2.0,
            'tasks': [{'tile': f't{i}', 'points': int(n), 'seconds': 99.0, 'cpu_seconds': per_tile + per_point * n,
                       'peak_rss_mb': 100.0 + n / 1000} for i, n in enumerate(points)]}


def test_the_fit_recovers_the_cost_per_tile_and_per_point():
    points = np.random.default_rng(0).integers(1_000, 500_000, 40)
    costs = capacity.build_costs(_report(0.8, 8e-6, points), street_km=2.0)
    assert costs.per_tile_s == pytest.approx(0.8, rel=1e-6)
    assert costs.per_point_s == pytest.approx(8e-6, rel=1e-6)  # processor seconds, not the wall's 99 s
    assert costs.route_per_point_s == pytest.approx(4.0 / (4 * points.sum()))
    assert costs.largest_tile_points == points.max() and costs.tiles == 40


def test_the_plan_scales_the_measured_costs():
    costs = capacity.build_costs(_report(1.0, 1e-5, [100_000] * 10), street_km=1.0)  # 10 tiles a km
    overhead = capacity.Overhead(2, 100, per_task_s=0.01, round_trip_s=0.02, start_s=1.0)
    rows = dict(capacity.plan(costs, overhead, km=100.0, points=4e8, workers=10))
    # 1e8 building points x 1e-5 s + 1000 tiles x (1 + 0.01) s = 2010 worker-s, over 10 workers
    assert rows['mapping work'].startswith(f'{2010 / 3600:,.1f} worker-hours')
    assert rows['mapping on 10 workers'].startswith(f'{2010 / 10 / 3600:,.2f} h ({2010 / 10 / 60:,.0f} min)')
    assert rows['tiles'].startswith('1,000')


def test_routing_on_the_workers_divides_by_the_workers():
    """A report with routing tasks: their processor seconds are the routing work (spread over the
    workers), the client's merging and planning is added whole; an older report's client routing
    counts as routing work."""
    report = _report(1.0, 1e-5, [100_000] * 10)  # 4e6 input points
    report['route_tasks'] = [{'step': 'survey', 'cpu_seconds': 3.0}, {'step': 'spill', 'cpu_seconds': 1.0}]
    report['plan_seconds'] = 0.4
    costs = capacity.build_costs(report, street_km=1.0)
    assert costs.route_per_point_s == pytest.approx(4.0 / 4e6) and costs.plan_per_point_s == pytest.approx(0.1 / 1e6)
    overhead = capacity.Overhead(2, 100, per_task_s=0.01, round_trip_s=0.02, start_s=1.0)
    rows = dict(capacity.plan(costs, overhead, km=100.0, points=4e8, workers=10))
    # 4e8 points x 1 µs = 400 worker-s over 10 workers, + 4e8 x 0.1 µs = 40 s in the client
    assert rows['routing on 10 workers'].startswith(f'{80 / 3600:,.2f} h (1 min)')
    assert rows['routing, one process'].startswith(f'{440 / 3600:,.2f} h (7 min)')
    assert rows['total'].startswith(f'{(2010 / 10 + 80) / 3600:,.2f} h')
    old = capacity.build_costs(_report(1.0, 1e-5, [100_000] * 10), street_km=1.0)
    assert old.route_per_point_s == pytest.approx(4.0 / 4e6) and old.plan_per_point_s == 0.0


def test_a_tiled_build_writes_the_report_the_plan_reads(scenes, tmp_path, monkeypatch, capsys):
    write_npz(tmp_path / 'drive.npz', scenes.campaign('small', 0))
    out = tmp_path / 'map'
    assert main(['build', str(tmp_path / 'drive.npz'), '--tiles', str(out), '--side', '20', '--quiet']) == 0
    report = json.loads((out / 'build.json').read_text())
    assert sum(t['points'] for t in report['tasks']) == report['building_points'] > 0
    assert {t['tile'] for t in report['tasks']} == {p.stem for p in (out / 'tiles').glob('*.npz')}
    monkeypatch.setattr(capacity, 'scheduler_overhead', lambda *a: capacity.Overhead(2, 10, 0.01, 0.02, 1.0))
    capsys.readouterr()
    assert capacity.main([str(out / 'build.json'), '--street-km', '0.05']) == 0
    printed = capsys.readouterr().out
    assert 'plan: 1,000 km of street' in printed and 'memory per worker' in printed
    assert 'routing on 100 workers' in printed and 'in the client' in printed
