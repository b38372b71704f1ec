"""``simulate`` on the hard scenes and with sensor presets."""

import json

import numpy as np

from uncertain_facade_map.io.npz import read_npz
from uncertain_facade_map_apps.cli import main


def test_simulate_a_hard_scene_with_another_sensor(tmp_path, capsys):
    out = tmp_path / 'hard'
    assert main(['simulate', '--scene', 'small_hard', '--sensor', 'vmx250-small', '--campaigns', '2',
                 '--formats', 'npz', '--out', str(out), '--quiet']) == 0
    desc = json.loads((out / 'scene.json').read_text())
    assert desc['scene'] == 'small_hard'
    assert desc['walls']['glass_share'] == 0.25 and len(desc['reliefs']) == 8
    assert desc['sensor']['beam_divergence_mrad'] == 0.35 and desc['sensor']['registration_sigma'][0] == 0.03
    codes = np.bincount(read_npz(out / 'campaign0.npz').points['gt_outlier'], minlength=4)
    assert (codes[1:] > 50).all(), 'clutter, glass and mixed returns are all there'


def test_clean_scene_description_has_no_walls(tmp_path):
    assert main(['simulate', '--scene', 'small', '--formats', 'npz', '--out', str(tmp_path), '--quiet']) == 0
    assert 'walls' not in json.loads((tmp_path / 'scene.json').read_text())
