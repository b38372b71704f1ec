"""The map folder of the node's save_map and load_map (issue 38): what a name resolves to,
and each refusal, without a node (test/node/test_node.py calls them through the services)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from uncertain_facade_map.io.map_file import is_map_file, save_map, unpacked_bytes
from uncertain_facade_map.io.map_folder import DEFAULT_DIR, MapFolder, PathRefused
from uncertain_facade_map.mapping.facade_map import FacadeMap
from uncertain_facade_map.params import Config, map_params


@pytest.fixture(scope='module')
def tree(tmp_path_factory):
    """base/maps (the folder) with a map, a text file, links in and out, a sub-folder; base/outside."""
    base = tmp_path_factory.mktemp('folder')
    root, outside = base / 'maps', base / 'outside'
    (root / 'sub').mkdir(parents=True)
    outside.mkdir()
    save_map(FacadeMap(map_params(Config()), np.zeros(3)), root / 'a.npz')
    (root / 'notes.npz').write_text('not a map')
    (outside / 'victim.npz').write_text('not a map either')
    (root / 'out').symlink_to(outside)
    (root / 'in').symlink_to(root / 'sub')
    (root / 'victim_link.npz').symlink_to(outside / 'victim.npz')
    return root, outside


def test_names_resolve_in_the_folder_and_out_is_refused(tree):
    root, outside = tree
    folder = MapFolder.of(str(root), '')
    real = Path(os.path.realpath(root))
    assert folder.resolve('a.npz') == real / 'a.npz'
    assert folder.resolve('sub/../a.npz') == real / 'a.npz'
    assert folder.resolve('in/new.npz') == real / 'sub' / 'new.npz'  # a link that stays inside
    assert folder.resolve(str(root / 'a.npz')) == real / 'a.npz'
    for name in ('../outside/x.npz', str(outside / 'x.npz'), 'out/x.npz', 'victim_link.npz', '/etc/passwd',
                 'sub/../../outside/x.npz'):
        with pytest.raises(PathRefused, match='leads outside the map folder .*persistence.allow_any_path'):
            folder.resolve(name)
    for name in ('', '   ', 'a\x00.npz'):
        with pytest.raises(PathRefused, match='not a file name'):
            folder.resolve(name)
    anywhere = MapFolder.of(str(root), '', allow_any=True)
    assert anywhere.resolve(str(outside / 'x.npz')) == Path(os.path.realpath(outside)) / 'x.npz'


def test_default_folder():
    assert MapFolder.of('', '', cwd='/w').root == Path('/w') / DEFAULT_DIR
    assert MapFolder.of('', 'maps/city.npz', cwd='/w').root == Path('/w/maps')
    assert MapFolder.of('', '/data/city.npz', cwd='/w').root == Path('/data')
    assert MapFolder.of('/srv/maps', '/data/city.npz', cwd='/w').root == Path('/srv/maps')


def test_saves_replace_map_files_only(tree):
    root, outside = tree
    folder = MapFolder.of(str(root), '')
    assert folder.save_path('a.npz').name == 'a.npz' and is_map_file(root / 'a.npz')
    assert folder.save_path('new.npz').name == 'new.npz'
    with pytest.raises(PathRefused, match='not a map file of uncertain_facade_map'):
        folder.save_path('notes.npz')
    with pytest.raises(PathRefused, match=r'\*\.npz only'):
        folder.save_path('a.txt')
    with pytest.raises(PathRefused, match=r'\*\.npz only'):
        folder.save_path('sub')  # a folder without the suffix: refused for the suffix
    (root / 'dir.npz').mkdir(exist_ok=True)
    with pytest.raises(PathRefused, match='is a folder'):
        folder.save_path('dir.npz')
    # allow_any_path lifts the folder rule, not the others.
    anywhere = MapFolder.of(str(root), '', allow_any=True)
    with pytest.raises(PathRefused, match='not a map file'):
        anywhere.save_path(str(outside / 'victim.npz'))
    # The check is made again just before the rename (a file put there after it).
    fmap = FacadeMap(map_params(Config()), np.zeros(3))
    (root / 'late.npz').write_text('came late')
    from uncertain_facade_map.errors import InputError

    with pytest.raises(InputError, match='not replaced'):
        save_map(fmap, root / 'late.npz', replace_only_maps=True)
    assert (root / 'late.npz').read_text() == 'came late'
    assert not [p for p in root.iterdir() if p.name.endswith('.tmp')]


def test_loads_are_bounded(tree):
    root, _ = tree
    size = unpacked_bytes(root / 'a.npz')
    assert size >= (root / 'a.npz').stat().st_size
    assert MapFolder.of(str(root), '', max_load_mb=size / 2**20 * 1.01).load_path('a.npz').name == 'a.npz'
    with pytest.raises(PathRefused, match='persistence.max_load_mb'):
        MapFolder.of(str(root), '', max_load_mb=size / 2**20 * 0.99).load_path('a.npz')


def test_is_map_file(tree):
    root, outside = tree
    assert is_map_file(root / 'a.npz')
    assert not is_map_file(root / 'notes.npz') and not is_map_file(root / 'sub') and not is_map_file(root / 'no.npz')
    assert not is_map_file(root / 'victim_link.npz')  # a link is never replaced
    np.savez(outside / 'other.npz', x=np.arange(3))
    assert not is_map_file(outside / 'other.npz')


_SEGMENTS = st.sampled_from(['..', '.', 'a.npz', 'sub', 'in', 'out', 'victim_link.npz', 'x', '', '...', '~'])


@settings(max_examples=400, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(parts=st.lists(_SEGMENTS, min_size=1, max_size=6), absolute=st.sampled_from(['', 'root', '/', 'outside']),
       text=st.text(min_size=0, max_size=8))
def test_no_accepted_name_resolves_outside(tree, parts, absolute, text):
    """Property: whatever the name (segments, links, '..', absolute prefixes, arbitrary text),
    a name the folder accepts resolves inside it, through every link."""
    root, outside = tree
    prefix = {'': '', 'root': str(root) + '/', '/': '/', 'outside': str(outside) + '/'}[absolute]
    name = prefix + '/'.join(parts) + text
    folder = MapFolder.of(str(root), '')
    try:
        path = folder.resolve(name)
    except PathRefused:
        return
    real_root = Path(os.path.realpath(root))
    assert Path(os.path.realpath(path)) == path
    assert path == real_root or real_root in path.parents
