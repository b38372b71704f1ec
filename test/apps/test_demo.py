"""`make demo`'s job on the small scene: simulate, node, publish replay, queries, map, figures."""

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from uncertain_facade_map.io.map_file import load_map

pytestmark = pytest.mark.ros


def test_demo_produces_the_folder(tmp_path):
    pytest.importorskip('uncertain_facade_map.srv')
    out = tmp_path / 'demo'
    env = dict(os.environ, ROS_DOMAIN_ID=str(20 + os.getpid() % 10))
    done = subprocess.run([sys.executable, '-m', 'uncertain_facade_map_apps.demo', '--scene', 'small', '--out',
                           str(out)], env=env, capture_output=True, text=True, timeout=300,
                          cwd=Path(__file__).resolve().parents[2])
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-2000:]
    text = done.stdout
    assert 'demo done' in text and '0 scans dropped' in text
    fmap = load_map(out / 'map.npz')
    assert len(fmap.facades) == 4 and fmap.n_pending == 0
    answers = np.load(out / 'queries.npz')
    assert (answers['facade'] >= 0).mean() > 0.9
    assert np.all(np.isfinite(answers['variance'][answers['facade'] >= 0]))
    for line in text.splitlines():
        if line.strip().startswith(('map ', 'figure ')):
            assert Path(line.split()[-1]).exists(), line
    # The last step: scans of another drive localised by facade_localizer through the map's service.
    assert (out / 'figures' / 'localisation.png').exists()
    line = next(x for x in text.splitlines() if x.strip().startswith('localise '))
    within = int(line.split('% within')[0].split()[-1])
    assert within >= 75, line
