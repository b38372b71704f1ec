"""The simulator's packaged data: the zurich scene's CityJSON ships with the package.

The Zurich LoD2 subset (cjio test data, MIT) lives in ``uncertain_facade_map/simulation/data/``
with its licence, so a fresh clone simulates every scene without the shared data folder
beside the repository; where that folder exists, the packaged copy must be identical to it.
"""

from __future__ import annotations

import fnmatch
import json
import os
import re
import runpy
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import setuptools
from support import REPO

import uncertain_facade_map.simulation as simulation
from uncertain_facade_map.simulation.scenes import DEFAULT_CITYJSON, build_scene

DATA = Path(simulation.__file__).resolve().parent / 'data'
LICENCE = DATA / 'LICENSE-cjio-MIT.txt'
SHARED = REPO.parent / 'shared' / 'data' / 'cityjson'


def test_default_cityjson_lies_inside_the_package() -> None:
    assert DEFAULT_CITYJSON == DATA / 'zurich_subset_lod2.json'
    assert DEFAULT_CITYJSON.is_file() and DEFAULT_CITYJSON.stat().st_size > 1_000_000
    assert 'shared' not in DEFAULT_CITYJSON.relative_to(REPO).parts
    assert LICENCE.read_text().startswith('MIT License')
    readme = (DATA / 'README.md').read_text()
    assert 'cjio' in readme and 'MIT' in readme and LICENCE.name in readme and DEFAULT_CITYJSON.name in readme


def test_zurich_scene_builds_from_the_packaged_file() -> None:
    doc = json.loads(DEFAULT_CITYJSON.read_text())
    buildings = {k for k, v in doc['CityObjects'].items() if v['type'] == 'Building'}
    scene = build_scene('zurich', 0)
    assert scene.name == 'zurich' and len(scene.buildings) == 8
    assert {b.source for b in scene.buildings} <= buildings


def test_zurich_scene_builds_in_a_copy_without_shared_data(tmp_path: Path) -> None:
    # The package alone, copied where no shared folder lies beside it (as in a fresh clone).
    clone = tmp_path / 'clone'
    shutil.copytree(REPO / 'uncertain_facade_map', clone / 'uncertain_facade_map',
                    ignore=shutil.ignore_patterns('__pycache__'))
    for parent in clone.parents:
        assert not (parent / 'shared' / 'data' / 'cityjson').exists()
    code = '\n'.join([
        'import json',
        'from uncertain_facade_map.simulation import scenes',
        "scene = scenes.build_scene('zurich', 0)",
        "print(json.dumps({'module': scenes.__file__, 'default': str(scenes.DEFAULT_CITYJSON),",
        "                  'sources': [b.source for b in scene.buildings]}))",
    ])
    env = {'PATH': '/usr/bin:/bin', 'HOME': os.environ.get('HOME', '/tmp'), 'LANG': 'C.UTF-8',
           'PYTHONPATH': str(clone)}
    result = subprocess.run([sys.executable, '-c', code], cwd=tmp_path, env=env, capture_output=True,
                            text=True, timeout=120)
    assert result.returncode == 0, result.stdout + result.stderr
    out = json.loads(result.stdout.strip().splitlines()[-1])
    assert Path(out['module']).is_relative_to(clone)
    assert out['default'] == str(clone / 'uncertain_facade_map' / 'simulation' / 'data' / 'zurich_subset_lod2.json')
    assert out['sources'] == [b.source for b in build_scene('zurich', 0).buildings]


@pytest.mark.skipif(not (SHARED / 'zurich_subset_lod2.json').is_file(), reason=f'{SHARED} not available')
def test_packaged_file_is_the_shared_file_byte_for_byte() -> None:
    assert DEFAULT_CITYJSON.read_bytes() == (SHARED / 'zurich_subset_lod2.json').read_bytes()
    if (SHARED / LICENCE.name).is_file():
        assert LICENCE.read_bytes() == (SHARED / LICENCE.name).read_bytes()


def test_setup_py_ships_the_data(monkeypatch: pytest.MonkeyPatch) -> None:
    captured: dict = {}
    monkeypatch.setattr(setuptools, 'setup', lambda **kwargs: captured.update(kwargs))
    monkeypatch.chdir(REPO)  # find_packages() looks in the current directory
    runpy.run_path(str(REPO / 'setup.py'))
    assert 'uncertain_facade_map.simulation' in captured['packages']
    patterns = captured['package_data']['uncertain_facade_map.simulation']
    files = sorted(p.relative_to(DATA.parent).as_posix() for p in DATA.iterdir() if p.is_file())
    assert {'data/zurich_subset_lod2.json', 'data/LICENSE-cjio-MIT.txt', 'data/README.md'} <= set(files)
    for name in files:
        assert any(fnmatch.fnmatch(name, pattern) for pattern in patterns), name


def test_cmake_installs_the_data() -> None:
    text = (REPO / 'CMakeLists.txt').read_text()
    install = re.search(r'install\(DIRECTORY ([^\n]*)\n(.*?)\)', text, re.S)
    assert install and 'uncertain_facade_map' in install.group(1).split()
    excluded = re.findall(r'PATTERN\s+"([^"]+)"\s+EXCLUDE', install.group(2))
    assert 'REGEX' not in install.group(2) and 'FILES_MATCHING' not in install.group(2)
    for path in DATA.iterdir():
        assert not any(fnmatch.fnmatch(path.name, pattern) for pattern in excluded), path.name
