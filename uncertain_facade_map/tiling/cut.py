"""Cutting a one-file map into a tiled map (``uncertain-facade-map tile``; tests).

Each building goes to the tile of the centre of its stored points' bounding box (x, y),
whole (as ``tiles.side`` says); each tile's file holds its buildings
(:func:`~.tiled_map.subset_map`); the manifest carries the map's learnt occupancy and its
local reading's calibration, so that the tiled map answers as the one-file map does.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path
from typing import Callable, Iterable

import numpy as np

from ..errors import InputError
from ..mapping.facade_map import FacadeMap
from ..params import QueryConfig, map_params_record
from .grid import TileGrid, tile_id
from .manifest import MANIFEST, Manifest, save_tile, write_manifest
from .tiled_map import local_calibration, subset_map

__all__ = ['building_tiles', 'cut_map']


def building_tiles(fmap: FacadeMap, grid: TileGrid) -> dict[int, tuple[int, int]]:
    """Per building label, the ``(ix, iy)`` of the tile of the centre of its stored points'
    bounding box (map frame x, y); buildings without stored points are left out."""
    labels = [b for b in fmap.buildings if len(fmap.points[b])]
    if not labels:
        return {}
    centres = np.array([(fmap.points[b].min(axis=0) + fmap.points[b].max(axis=0)) / 2 for b in labels])
    idx = grid.index(centres[:, :2])
    return {b: (int(i[0]), int(i[1])) for b, i in zip(labels, idx)}


def _fingerprint(fmap: FacadeMap) -> str:
    digest = hashlib.sha256()
    for b in fmap.buildings:
        digest.update(np.int64(b).tobytes())
        digest.update(np.ascontiguousarray(fmap.points[b]).tobytes())
    return digest.hexdigest()


def cut_map(fmap: FacadeMap, folder: str | os.PathLike, side: float,
            configs: Iterable[QueryConfig] = (QueryConfig(),), overwrite: bool = False,
            progress: Callable[[int, int], None] | None = None) -> Manifest:
    """Write ``fmap`` as a tiled map in ``folder`` (tiles of ``side`` metres) and return its
    manifest. The local reading's calibration is recorded for ``configs``.

    Raises:
        InputError: held-back points in the map (flush it first), a folder that already holds
            a tiled map (unless ``overwrite``), or a bad side.
    """
    folder = Path(folder)
    grid = TileGrid(side)
    if fmap.pending:
        raise InputError('the map holds points not yet mapped (pending); flush it before cutting it into tiles')
    if (folder / MANIFEST).exists() and not overwrite:
        raise InputError(f'{folder} already holds a tiled map; choose another folder')
    if folder.exists() and not folder.is_dir():
        raise InputError(f'{folder} is a file, not a folder')
    where = building_tiles(fmap, grid)
    empty = [b for b in fmap.buildings if b not in where]
    per_tile: dict[tuple[int, int], list[int]] = {}
    for b, ij in where.items():
        per_tile.setdefault(ij, []).append(b)
    if empty:  # no stored points: no centre; kept with the first tile so that nothing is lost
        first = min(per_tile) if per_tile else (0, 0)
        per_tile.setdefault(first, []).extend(empty)
    tiles = {}
    for k, ij in enumerate(sorted(per_tile)):
        part = subset_map(fmap, per_tile[ij])
        tid = tile_id(*ij)
        tiles[tid] = save_tile(folder, tid, ij, grid.bounds(*ij), part, _fingerprint(part))
        if progress is not None:
            progress(k + 1, len(per_tile))
    occupancy = dict(fmap.occupancy_.as_dict())
    manifest = Manifest(side=grid.side, map_origin=tuple(float(x) for x in fmap.map_origin),
                        params=map_params_record(fmap.params), tiles=tiles, occupancy=occupancy,
                        building_tiles={b: tid for tid, rec in tiles.items() for b in rec.buildings},
                        local_calibration=local_calibration(fmap, configs),
                        registration={'var': float(fmap.registration_var_),
                                      'sums': [float(x) for x in fmap.registration_sums_]})
    write_manifest(folder, manifest)
    return manifest
