"""bench_tiles: its route through a tiled map's tiles, and a short run on the small scene cut
into two tiles, then the one-file map (the node in its own process; about 25 s)."""

from __future__ import annotations

import json
from types import SimpleNamespace

import numpy as np
import pytest

from uncertain_facade_map_apps.bench_tiles import main, route


def test_the_route_visits_the_tiles_nearest_first_in_steps():
    records = [SimpleNamespace(bounds=b) for b in [(60.0, 0.0, 70.0, 10.0), (0.0, 0.0, 10.0, 10.0),
                                                   (30.0, 0.0, 40.0, 10.0), (0.0, 12.0, 10.0, 22.0)]]
    path = route(records, 5.0)
    np.testing.assert_array_equal(path[0], [5, 5])  # the tile of the smallest x, then y
    stops = [tuple(p) for p in path if tuple(p) in {(5, 5), (5, 17), (35, 5), (65, 5)}]
    assert stops == [(5, 5), (5, 17), (35, 5), (65, 5)]  # greedy: the nearest tile next
    assert len(path) == 1 + 3 + 7 + 6 and np.hypot(*np.diff(path, axis=0).T).max() <= 5.0 + 1e-9
    assert len(route(records, 5.0, max_tiles=2)) == 4 and route([], 5.0).shape == (0, 2)


@pytest.mark.ros
def test_a_short_drive_prints_latency_tiles_and_memory(scenes, tmp_path, capsys):
    pytest.importorskip('rclpy')
    pytest.importorskip('uncertain_facade_map.srv')
    from uncertain_facade_map.io.map_file import save_map
    from uncertain_facade_map.mapping.facade_map import build_map
    from uncertain_facade_map.tiling.cut import cut_map

    cloud = scenes.campaign('small', 0)
    pts = cloud.points[cloud.points['class'] == 1]
    whole = build_map(np.stack([pts['x'], pts['y'], pts['z']], 1), pts['building_id'], None,
                      map_origin=cloud.map_origin)
    cut_map(whole, tmp_path / 'tiled', 20.0)
    save_map(whole, tmp_path / 'whole.npz')
    out = tmp_path / 'figures.json'
    assert main([str(tmp_path / 'tiled'), '--cache-mb', '64', '--radius', '10', '--follow-period', '0.2',
                 '--speed', '20', '--step', '5', '--points', '500', '--json', str(out),
                 '--one-file', str(tmp_path / 'whole.npz')]) == 0
    both = json.loads(out.read_text())
    figures, one = both['tiled'], both['one_file']
    assert one['map'].endswith('whole.npz') and one['tiles_loaded_end'] == 0 and one['steps'] == figures['steps']
    assert one['share_on_a_facade'] == figures['share_on_a_facade']  # the same points, the same answers
    assert figures['tiles'] == 2 and figures['steps'] == 5 and figures['route_m'] == pytest.approx(20.0)
    assert 0 < figures['latency_ms_median'] <= figures['latency_ms_p95'] <= figures['latency_ms_max']
    assert figures['share_on_a_facade'] > 0.5 and figures['tiles_loaded_end'] >= 1
    assert figures['preloads'] >= 1 and figures['node_peak_rss_mb'] >= figures['node_rss_mb_start'] > 50
    assert 'tiled map | one-file map' in capsys.readouterr().out


def test_its_help_prints(capsys):
    from uncertain_facade_map_apps.bench_tiles import main as bench_main

    with pytest.raises(SystemExit) as stop:
        bench_main(['--help'])
    assert stop.value.code == 0 and '--cache-mb' in capsys.readouterr().out
