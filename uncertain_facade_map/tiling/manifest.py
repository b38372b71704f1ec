"""The manifest of a tiled map: ``<folder>/manifest.json``, and the tiles' files.

A tiled map is a folder::

    manifest.json        this module's record (format, version, tiles, hashes)
    tiles/<id>.npz       one ordinary map file per tile (io.map_file: load_map reads it)

The manifest is JSON::

    {"format": "uncertain_facade_map.tiles", "version": 1,
     "side": 50.0, "map_origin": [x, y, z], "params": {... map_params_record ...},
     "occupancy": {"scale": ..., "spread": ..., "n_positive": ..., "n_negative": ...} or null,
     "building_tiles": {"<label>": "<tile id>", ...},
     "local_calibration": {"<reading key>": {"scale": ..., "gap_slope": ..., "gap_start": ...,
                                             "lever_start": ...}, ...},
     "registration": {"var": m^2, "sums": [n, cross, within]} or null,
     "tiles": [{"id": "tile_0_m1", "index": [0, -1], "bounds": [min_x, min_y, max_x, max_y],
                "extent": [min_x, min_y, min_z, max_x, max_y, max_z], "file": "tiles/tile_0_m1.npz",
                "sha256": "<hex>", "buildings": [..], "facades": F, "points": N,
                "inputs": "<hex>"}, ...]}

It is written atomically (:func:`write_manifest`: a temporary file in the folder, fsync,
rename), so a reader sees the old manifest or the new one, never a part; a build writes
each tile's file first (:func:`save_tile`, itself atomic) and the manifest after, so an
interrupted build leaves a manifest that lists whole tiles only. :func:`read_manifest`
refuses missing, damaged, foreign and newer manifests with a one-line
:class:`~uncertain_facade_map.errors.InputError`; :func:`verify_tile` checks a tile's file
against its hash before it is read.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath
from typing import Any

import numpy as np

from ..errors import InputError
from ..io._files import atomic_write
from ..mapping.facade_map import FacadeMap
from ..pipeline.step7_local_surface import ReadingCalibration
from . import grid as _grid
from .grid import tile_file, tile_id

__all__ = ['MANIFEST', 'FORMAT', 'VERSION', 'TileRecord', 'Manifest', 'is_tiled_map', 'manifest_path',
           'read_manifest', 'write_manifest', 'save_tile', 'verify_tile', 'sha256_file', 'map_extent']

MANIFEST = 'manifest.json'
FORMAT = 'uncertain_facade_map.tiles'
VERSION = 1


@dataclass
class TileRecord:
    """One tile of a tiled map.

    Attributes:
        id: ``tile_{ix}_{iy}`` (:func:`~.grid.tile_id`).
        index: ``(ix, iy)`` on the grid.
        bounds: ``(min_x, min_y, max_x, max_y)`` of the tile's square, metres, map frame.
        extent: (6,) ``min x, y, z, max x, y, z`` of what the tile's map answers for, metres,
            map frame: its stored points and its façades' slabs (raster extent x depth band,
            :func:`map_extent`). Its buildings are whole, so it may reach past ``bounds``.
            Queries pick tiles by it.
        file: the tile's map file, relative to the map's folder (``tiles/<id>.npz``).
        sha256: hex SHA-256 of that file.
        buildings: labels of the tile's buildings.
        facades: number of façades in the tile's file.
        points: stored points in the tile's file.
        inputs: fingerprint (hex SHA-256) of the routed points that built it: of the map
            parameters, the map origin and its part files' digests in input order
            (:attr:`~.build.TileTask.inputs`); a tile built by several drives lists one per run,
            joined by ``+``.
    """

    id: str
    index: tuple[int, int]
    bounds: tuple[float, float, float, float]
    extent: tuple[float, ...]
    file: str
    sha256: str
    buildings: list[int]
    facades: int
    points: int
    inputs: str

    def as_dict(self) -> dict[str, Any]:
        """The JSON record."""
        return {'id': self.id, 'index': [int(i) for i in self.index], 'bounds': [float(b) for b in self.bounds],
                'extent': [float(e) for e in self.extent], 'file': self.file, 'sha256': self.sha256,
                'buildings': [int(b) for b in self.buildings], 'facades': int(self.facades),
                'points': int(self.points), 'inputs': self.inputs}


@dataclass
class Manifest:
    """The manifest of a tiled map.

    Attributes:
        side: tile side, metres.
        map_origin: (3,) georeference of the map frame, metres.
        params: the map's parameters (:func:`~uncertain_facade_map.params.map_params_record`).
        tiles: by tile id, its record.
        occupancy: the occupancy's PLSC parameters for all tiles (``PLSC.as_dict()``), or None
            (each tile's own).
        building_tiles: building label -> id of the tile it lives in (set at its first build).
        local_calibration: the map-wide calibration of the local reading
            (``LocalSurface.calibration()``) per reading key (:func:`reading_id`), when known
            (a map cut from one file knows it; a reader without it uses the merged tiles' own).
        registration: the map-wide scan-to-scan variance (``{'var': m^2, 'sums': [3 floats]}``,
            ``FacadeMap.registration_var_`` and ``registration_sums_``; a build sums its tiles'
            sums), or None (merged tiles: their own, :func:`~.tiled_map.merge_maps`).
    """

    side: float
    map_origin: tuple[float, float, float]
    params: dict
    tiles: dict[str, TileRecord]
    occupancy: dict | None = None
    building_tiles: dict[int, str] = field(default_factory=dict)
    local_calibration: dict[str, ReadingCalibration] = field(default_factory=dict)
    registration: dict | None = None

    def as_dict(self) -> dict[str, Any]:
        """The JSON document."""
        return {'format': FORMAT, 'version': VERSION, 'side': float(self.side),
                'map_origin': [float(x) for x in self.map_origin], 'params': self.params,
                'occupancy': self.occupancy,
                'building_tiles': {str(int(b)): t for b, t in sorted(self.building_tiles.items())},
                'local_calibration': {str(k): v.as_dict() for k, v in sorted(self.local_calibration.items())},
                'registration': self.registration,
                'tiles': [self.tiles[k].as_dict() for k in sorted(self.tiles)]}


def manifest_path(path: str | os.PathLike) -> Path:
    """The manifest of a tiled map given as its folder or its ``manifest.json``."""
    path = Path(path)
    return path if path.name == MANIFEST and not path.is_dir() else path / MANIFEST


def is_tiled_map(path: str | os.PathLike) -> bool:
    """True for a folder holding ``manifest.json``, or a ``manifest.json`` file."""
    return manifest_path(path).is_file()


def sha256_file(path: str | os.PathLike) -> str:
    """Hex SHA-256 of a file's bytes."""
    digest = hashlib.sha256()
    with open(path, 'rb') as fh:
        for block in iter(lambda: fh.read(1 << 20), b''):
            digest.update(block)
    return digest.hexdigest()


def _fsync_dir(folder: Path) -> None:
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def write_manifest(folder: str | os.PathLike, manifest: Manifest) -> Path:
    """Write ``manifest`` to ``folder/manifest.json`` atomically (a temporary file in the
    folder, flushed and fsynced, renamed over the old one; the folder fsynced). The folder is
    created if missing.

    Returns:
        The manifest's path.
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    target = folder / MANIFEST
    text = json.dumps(manifest.as_dict(), indent=1, allow_nan=False)

    def write(name: str) -> None:
        with open(name, 'w', encoding='utf-8') as fh:
            fh.write(text)
            fh.write('\n')

    atomic_write(target, write, mode=0o644)
    _fsync_dir(folder)
    return target


def _floats(value: Any, n: int, name: str) -> tuple[float, ...]:
    if not isinstance(value, list) or len(value) != n:
        raise ValueError(f'{name} must be a list of {n} numbers')
    out = tuple(float(x) for x in value)
    if not all(math.isfinite(x) for x in out) or any(isinstance(x, bool) for x in value):
        raise ValueError(f'{name} must hold finite numbers')
    return out


def _int(value: Any, name: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise ValueError(f'{name} must be an integer')
    return value


def _text(value: Any, name: str) -> str:
    if not isinstance(value, str):
        raise ValueError(f'{name} must be a string')
    return value


def _relative_file(value: Any, name: str) -> str:
    text = _text(value, name)
    p = PurePosixPath(text)
    if not text or p.is_absolute() or '..' in p.parts or '\\' in text:
        raise ValueError(f'{name} must be a path inside the map folder, got {text!r}')
    return text


def _hex(value: Any, name: str) -> str:
    text = _text(value, name)
    if len(text) != 64 or any(c not in '0123456789abcdef' for c in text):
        raise ValueError(f'{name} must be 64 lowercase hex digits')
    return text


def _record(d: Any) -> TileRecord:
    if not isinstance(d, dict):
        raise ValueError('a tile record must be an object')
    tid = _text(d['id'], 'tile id')
    index = tuple(_int(i, f'{tid} index') for i in d['index']) if isinstance(d['index'], list) else ()
    if len(index) != 2:
        raise ValueError(f'{tid}: index must be two integers')
    if tile_id(*index) != tid:
        raise ValueError(f'tile id {tid!r} does not match its index {list(index)}')
    buildings = d['buildings']
    if not isinstance(buildings, list):
        raise ValueError(f'{tid}: buildings must be a list')
    counts = [_int(d[k], f'{tid} {k}') for k in ('facades', 'points')]
    if min(counts) < 0:
        raise ValueError(f'{tid}: negative counts')
    return TileRecord(id=tid, index=(index[0], index[1]), bounds=_floats(d['bounds'], 4, f'{tid} bounds'),
                      extent=_floats(d['extent'], 6, f'{tid} extent'), file=_relative_file(d['file'], f'{tid} file'),
                      sha256=_hex(d['sha256'], f'{tid} sha256'),
                      buildings=[_int(b, f'{tid} building') for b in buildings],
                      facades=counts[0], points=counts[1], inputs=_text(d['inputs'], f'{tid} inputs'))


def _from_dict(doc: dict) -> Manifest:
    side = float(doc['side'])
    if isinstance(doc['side'], bool) or not (math.isfinite(side) and side > 0):
        raise ValueError('side must be a number of metres > 0')
    params = doc['params']
    if not isinstance(params, dict):
        raise ValueError('params must be an object')
    occupancy = doc.get('occupancy')
    if occupancy is not None and not isinstance(occupancy, dict):
        raise ValueError('occupancy must be an object or null')
    if not isinstance(doc['tiles'], list):
        raise ValueError('tiles must be a list')
    tiles: dict[str, TileRecord] = {}
    for d in doc['tiles']:
        rec = _record(d)
        if rec.id in tiles:
            raise ValueError(f'tile {rec.id} listed twice')
        tiles[rec.id] = rec
    bt = doc.get('building_tiles', {})
    if not isinstance(bt, dict):
        raise ValueError('building_tiles must be an object')
    building_tiles = {}
    for b, t in bt.items():
        if t not in tiles:
            raise ValueError(f'building {b} lives in tile {t!r}, which is not listed')
        building_tiles[int(b)] = t
    calibration = doc.get('local_calibration', {})
    if not isinstance(calibration, dict):
        raise ValueError('local_calibration must be an object')
    registration = doc.get('registration')
    if registration is not None:
        if not isinstance(registration, dict):
            raise ValueError('registration must be an object or null')
        registration = {'var': _floats([registration['var']], 1, 'registration var')[0],
                        'sums': list(_floats(registration['sums'], 3, 'registration sums'))}
    return Manifest(side=side, map_origin=_floats(doc['map_origin'], 3, 'map_origin'), params=params, tiles=tiles,
                    occupancy=occupancy, building_tiles=building_tiles,
                    local_calibration={str(k): ReadingCalibration.parse(v) for k, v in calibration.items()},
                    registration=registration)


def read_manifest(path: str | os.PathLike) -> Manifest:
    """Read a tiled map's manifest (``path``: the map's folder or its ``manifest.json``).

    Raises:
        InputError: missing, unreadable, not JSON, not a tiled map's manifest, of a newer
            version, or with missing or malformed fields (one line each).
    """
    target = manifest_path(path)
    if not target.is_file():
        if Path(path).is_dir():
            raise InputError(f'{path}: not a tiled map (no {MANIFEST} in the folder); give a map file or a '
                             f'tiled map\'s folder')
        raise InputError(f'no such tiled map: {path} (no {target})')
    try:
        text = target.read_text(encoding='utf-8')
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f'{target}: cannot read the manifest ({type(exc).__name__}: '
                         f'{" ".join(str(exc).split())})') from exc
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as exc:
        raise InputError(f'{target}: damaged manifest (not JSON: {exc.msg} at line {exc.lineno})') from exc
    if not isinstance(doc, dict) or doc.get('format') != FORMAT:
        raise InputError(f'{target}: not an {FORMAT} manifest')
    version = doc.get('version')
    if isinstance(version, bool) or not isinstance(version, int) or version < 1:
        raise InputError(f'{target}: damaged manifest (version {version!r})')
    if version > VERSION:
        raise InputError(f'{target}: tiled map version {version} was written by a newer uncertain_facade_map; '
                         f'this one reads versions 1 to {VERSION}')
    try:
        return _from_dict(doc)
    except KeyError as exc:
        raise InputError(f'{target}: damaged manifest (missing field {exc.args[0]!r})') from exc
    except (ValueError, TypeError, AttributeError) as exc:
        raise InputError(f'{target}: damaged manifest ({" ".join(str(exc).split())})') from exc


def map_extent(fmap: FacadeMap) -> tuple[float, ...]:
    """(6,) ``min x, y, z, max x, y, z`` of what a map answers for, metres, map frame: its
    stored points and each façade's slab (its raster's extent, ``extraction.band_back``
    behind the plane to ``band_front`` in front). All zeros for an empty map."""
    from ..pipeline.step7_queries import raster_bounds

    ex = fmap.params.extraction
    parts = [p for p in fmap.points.values() if len(p)]
    for f in fmap.facades:
        u0, u1, v0, v1 = raster_bounds(f.surface)
        parts.append(f.frame.to_world(np.array([[u, v, d] for u in (u0, u1) for v in (v0, v1)
                                                for d in (-ex.band_back, ex.band_front)])))
    if not parts:
        return (0.0,) * 6
    lo = np.min([p.min(axis=0) for p in parts], axis=0)
    hi = np.max([p.max(axis=0) for p in parts], axis=0)
    return tuple(float(x) for x in np.concatenate([lo, hi]))


def save_tile(folder: str | os.PathLike, tile_id: str, index: tuple[int, int],
              grid_bounds: tuple[float, float, float, float], fmap: FacadeMap, inputs: str) -> TileRecord:
    """Write one tile's map into ``folder/tiles/<tile_id>.npz`` (atomically,
    :func:`~uncertain_facade_map.io.map_file.save_map`), hash it and return its record. The
    manifest is not touched (workers write tiles; the client owns the manifest).

    Args:
        folder: the tiled map's folder (created if missing).
        tile_id: the tile's id (:func:`~.grid.tile_id` of ``index``).
        index: ``(ix, iy)``.
        grid_bounds: the tile's square (``TileGrid.bounds``), metres.
        fmap: the map of the tile's buildings.
        inputs: fingerprint of the points that built it (hex SHA-256).
    """
    from ..io.map_file import save_map

    ix, iy = int(index[0]), int(index[1])
    if _grid.tile_id(ix, iy) != tile_id:
        raise InputError(f'tile id {tile_id!r} does not match its index {[ix, iy]}')
    rel = tile_file(tile_id)
    target = Path(folder) / rel
    target.parent.mkdir(parents=True, exist_ok=True)
    save_map(fmap, target)
    return TileRecord(id=tile_id, index=(ix, iy), bounds=tuple(float(b) for b in grid_bounds),
                      extent=map_extent(fmap), file=rel, sha256=sha256_file(target),
                      buildings=[int(b) for b in fmap.buildings], facades=len(fmap.facades),
                      points=fmap.n_stored, inputs=str(inputs))


def verify_tile(folder: str | os.PathLike, record: TileRecord) -> Path:
    """The path of a tile's file, checked against the manifest's hash.

    Raises:
        InputError: the file is missing or its content is not the one the manifest lists.
    """
    path = Path(folder) / record.file
    if not path.is_file():
        raise InputError(f'{path}: tile {record.id} listed in the manifest is missing; rebuild the map '
                         f'(an interrupted build resumes)')
    if sha256_file(path) != record.sha256:
        raise InputError(f'{path}: tile {record.id} does not match the manifest\'s hash (damaged or replaced); '
                         f'rebuild that tile')
    return path
