"""Reading a tiled map: merging tile maps, opening a map file or a tiled map, and
:class:`TiledMap`, which loads tiles on demand near the asked points.

:func:`merge_maps` joins maps of disjoint buildings into one in-memory
:class:`~uncertain_facade_map.mapping.facade_map.FacadeMap` (façades renumbered in order);
:func:`subset_map` is its inverse (the buildings asked, façades renumbered), what cuts a
one-file map into tiles.
"""

from __future__ import annotations

import os
from dataclasses import replace
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np

from ..errors import InputError
from ..mapping.calibration import registration_variance
from ..mapping.facade_map import FacadeMap

__all__ = ['merge_maps', 'subset_map', 'open_map']


def merge_maps(maps: Sequence[FacadeMap]) -> FacadeMap:
    """One map holding the buildings of ``maps`` (which must not share a building label).

    Façades are renumbered in order: those of ``maps[0]`` first (their ids kept), then those
    of ``maps[1]`` shifted by ``len(maps[0].facades)``, and so on. Per-building arrays
    (points, normals, sensor origins) are shared, not copied (a map never writes an array
    it holds). The buildings are held in label order, as a map built in one go holds them.
    Held-back points are joined in order. The learnt occupancy: the maps' own when they
    agree, else that of the map with the most points stored at its calibration (a tiled
    map's reader sets the manifest's); the scan-to-scan sums add up, the variance is the
    maps' own when they agree, else learnt again from the summed sums.

    Raises:
        InputError: no maps, two maps holding one building label, or maps of different
            parameters or map origins.
    """
    maps = list(maps)
    if not maps:
        raise InputError('merge_maps needs at least one map')
    first = maps[0]
    owner: dict[int, int] = {}
    for i, m in enumerate(maps):
        if m.params != first.params:
            raise InputError(f'cannot merge maps built with different parameters (map {i} differs from map 0)')
        if not np.array_equal(m.map_origin, first.map_origin):
            raise InputError(f'cannot merge maps of different map origins (map {i}: {m.map_origin.tolist()}, '
                             f'map 0: {first.map_origin.tolist()})')
        for b in m.points:
            if b in owner:
                raise InputError(f'cannot merge maps sharing building {b} (maps {owner[b]} and {i})')
            owner[b] = i
    facades = []
    for m in maps:
        shift = len(facades)
        facades.extend(f if shift == 0 else replace(f, facade_id=f.facade_id + shift) for f in m.facades)
    labels = sorted(owner)
    points = {b: maps[owner[b]].points[b] for b in labels}
    normals = {b: maps[owner[b]].normals[b] for b in labels}
    origins = {b: maps[owner[b]].sensor_origins.get(b) for b in labels}
    pool = {b: maps[owner[b]].pool_checked[b] for b in labels if b in maps[owner[b]].pool_checked}
    thinned = {b: maps[owner[b]].thinned[b] for b in labels if b in maps[owner[b]].thinned}
    pending = [p for m in maps for p in m.pending]
    if all(m.occupancy_ == first.occupancy_ for m in maps):
        occupancy = first.occupancy_
    else:
        occupancy = max(maps, key=lambda m: m.occupancy_stored_).occupancy_
    sums = np.sum([m.registration_sums_ for m in maps], axis=0)
    if all(m.registration_var_ == first.registration_var_ for m in maps):
        reg_var = first.registration_var_
    else:
        reg_var = registration_variance(sums, first.params.update.registration_max_std)
    return FacadeMap(first.params, first.map_origin.copy(), facades, points, origins, normals, pool,
                     pending=pending, thinned=thinned, occupancy_=occupancy,
                     occupancy_stored_=int(sum(m.occupancy_stored_ for m in maps)),
                     registration_sums_=sums, registration_var_=reg_var)


def subset_map(fmap: FacadeMap, buildings: Iterable[int]) -> FacadeMap:
    """The map of some of ``fmap``'s buildings (labels; unknown ones refused), façades in
    their order in ``fmap`` renumbered from 0; arrays shared. Occupancy and scan-to-scan
    variance are ``fmap``'s (map-wide quantities); held-back points are not carried.

    Raises:
        InputError: a label ``fmap`` does not hold.
    """
    wanted = sorted({int(b) for b in buildings})
    missing = [b for b in wanted if b not in fmap.points]
    if missing:
        raise InputError(f'the map holds no building {missing[0]}')
    keep = set(wanted)
    facades = [f for f in fmap.facades if f.building in keep]
    facades = [f if f.facade_id == i else replace(f, facade_id=i) for i, f in enumerate(facades)]
    return FacadeMap(fmap.params, fmap.map_origin.copy(), facades, {b: fmap.points[b] for b in wanted},
                     {b: fmap.sensor_origins.get(b) for b in wanted}, {b: fmap.normals[b] for b in wanted},
                     {b: fmap.pool_checked[b] for b in wanted if b in fmap.pool_checked},
                     thinned={b: fmap.thinned[b] for b in wanted if b in fmap.thinned},
                     occupancy_=fmap.occupancy_, occupancy_stored_=fmap.occupancy_stored_,
                     registration_sums_=fmap.registration_sums_.copy(), registration_var_=fmap.registration_var_)


def open_map(path: str | os.PathLike, cache_mb: float | None = None):
    """A map file (:func:`~uncertain_facade_map.io.map_file.load_map`) or a tiled map
    (its folder or its ``manifest.json``: a :class:`TiledMap` reading tiles on demand).

    Args:
        path: the map.
        cache_mb: the tiled map's cache bound, MB (default ``tiles.cache_mb``).

    Raises:
        InputError: missing path, a folder without a manifest, a damaged map or manifest.
    """
    from ..io.map_file import load_map
    from .manifest import MANIFEST, is_tiled_map

    p = Path(path)
    if is_tiled_map(p):
        return TiledMap(p) if cache_mb is None else TiledMap(p, cache_mb)
    if p.is_dir():
        raise InputError(f'{p}: not a tiled map (no {MANIFEST} in the folder); give a map file (.npz) or a '
                         f'tiled map\'s folder')
    if p.name == MANIFEST and not p.exists():
        raise InputError(f'no such tiled map: {p}')
    return load_map(p)


class TiledMap:  # placeholder until the reader lands (same commit series); open_map refers to it
    def __init__(self, path, cache_mb: float | None = None) -> None:
        raise InputError('tiled maps cannot be read yet by this version')
