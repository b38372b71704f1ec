"""The map file: the whole map in one NPZ file (a zip of .npy arrays), versioned.

An open format any numpy (or any zip + .npy reader) can read, no pickle. It holds:

- ``meta``: a JSON document (format name, version, map origin, parameters, façade list);
- per façade ``i``: ``facade/<i>/<name>`` arrays (frame, layers, facets, length scales,
  surface raster: mean, variance, facet, source);
- ``pending/xyz`` (and ``pending/building_id``, ``pending/sensor_origins``): points
  received but held back for the next update (live mapping), ``pending/scan`` the number
  of the call (a scan) that brought each;
- per building ``b``: ``building/<b>/points``, ``building/<b>/normals`` and, if known,
  ``building/<b>/sensor_origins`` (kept so that a loaded map goes on mapping exactly as
  the map that was saved would have); ``meta`` counts per building the points thinned
  (counted, not stored: see ``update.store_voxel``), 0 when absent; and the occupancy's
  learnt PLSC parameters (``occupancy``: scale, spread, the voxels they were learnt on and
  the points stored then; the fixed formula's when absent); and the variance of
  scan-to-scan disagreement (``registration``: ``var`` in m^2 and the running ``sums`` it
  was learnt from, ``FacadeMap.registration_var_``); per building the first stored row live
  mapping had not modelled yet (``unmodelled``, absent when none: the rows from it on have NaN
  normals until modelled, ``FacadeMap.store_points``).

Version 2 added what incremental mapping needs (per façade the wall's ``plane_extent``,
the block grid's ``anchor`` and the points at the last whole fit; per building the point
normals and the pool size at the last RANSAC run); version 3 the wall's relief per façade
(``relief_origin``, ``relief_values``, ``relief_spacing``); version 4 the scan-to-scan
disagreement (``registration``). Older files are upgraded on load.

Loading gives back every array bit for bit. A file of a newer version is refused with a
message saying so; older versions are upgraded by the functions in :data:`MIGRATIONS`.
Saving is atomic: the file is written next to the target and renamed over it.
"""

from __future__ import annotations

import json
import os
import zipfile
from pathlib import Path
from typing import Any, Callable

import numpy as np

from ..datatypes import DepthLayers, FacadeFrame, FacadeModel, Facets, Relief, SurfaceRaster
from ..errors import InputError
from ..mapping.facade_map import FacadeMap
from ..params import map_params_from_record, map_params_record
from ..pipeline.step8_occupancy import PLSC
from ._files import atomic_write, temporary_name

FORMAT = 'uncertain_facade_map.map'
VERSION = 4
#: Upgrades of older files: version -> function(meta, arrays) returning the next version's.
MIGRATIONS: dict[int, Callable[[dict, dict], tuple[dict, dict]]] = {}


def _facade_arrays(f: FacadeModel) -> dict[str, np.ndarray]:
    p = f'facade/{f.facade_id}/'
    s = f.surface
    return {
        p + 'frame': f.frame.as_array(),
        p + 'extent': np.asarray(f.extent, dtype=np.float64),
        p + 'layers': np.stack([f.layers.weights_, f.layers.means_, f.layers.sigmas_]),
        p + 'facets': f.facets.facet,
        p + 'facets_origin': f.facets.origin,
        p + 'layer_of_facet': f.facets.layer_of_facet,
        p + 'lengthscale2': f.lengthscale2_,
        p + 'surface_origin': s.origin,
        p + 'surface_mean': s.mean,
        p + 'surface_var': s.var,
        p + 'surface_facet': s.facet,
        p + 'surface_source': s.source,
        p + 'point_index': f.point_index,
        p + 'outlier_index': f.outlier_index,
        p + 'plane_extent': np.asarray(f.plane_extent, dtype=np.float64),
        p + 'anchor': np.asarray(f.anchor, dtype=np.float64),
        p + 'relief_origin': np.asarray(f.relief.origin, dtype=np.float64),
        p + 'relief_values': np.asarray(f.relief.values, dtype=np.float64),
    }


def remove_stale_temporaries(path: str | Path) -> list[Path]:
    """Delete the temporary files that saves of ``path`` left behind (a process killed while
    saving leaves one: ``.NAME.XXXXXXXX.tmp`` next to ``path``). Call it when no save of
    ``path`` is running. The name may be a glob pattern (``DIR/*.npz``: every map file's in DIR).

    Returns:
        The files deleted.
    """
    path = Path(path)
    prefix, suffix = temporary_name(path)
    removed = []
    if path.parent.is_dir():
        for stale in path.parent.glob(f'{prefix}*{suffix}'):
            try:
                stale.unlink()
                removed.append(stale)
            except OSError:
                pass
    return removed


def _write_npz(fh, arrays: dict[str, np.ndarray]) -> None:
    """``np.savez`` with fixed zip timestamps: the same map gives the same bytes whenever it is
    saved (a tiled map's content hashes, and a resumed build's tiles, compare files)."""
    with zipfile.ZipFile(fh, mode='w', compression=zipfile.ZIP_STORED, allowZip64=True) as zf:
        for name, value in arrays.items():
            info = zipfile.ZipInfo(name + '.npy', date_time=(1980, 1, 1, 0, 0, 0))
            info.external_attr = 0o600 << 16
            with zf.open(info, 'w', force_zip64=True) as out:
                np.lib.format.write_array(out, np.asanyarray(value), allow_pickle=False)


#: Largest ``meta`` record :func:`is_map_file` reads, bytes (a map's is a few kB per façade).
_META_MAX = 256 * 2**20


def save_map(fmap: FacadeMap, path: str | Path, replace_only_maps: bool = False) -> Path:
    """Write the map atomically to ``path`` (conventionally ``*.npz``): into a temporary
    file next to it, then renamed; the file gets the permissions the process's umask
    allows (as ``open`` would give it). A failure deletes the temporary file; a kill
    leaves it, for :func:`remove_stale_temporaries`.

    ``replace_only_maps``: refuse to replace an existing file that is not a map file
    (:func:`is_map_file`, checked just before the rename; the node's ``save_map`` service).

    Returns:
        The path written.

    Raises:
        OSError: the folder is missing or not writable.
        InputError: ``replace_only_maps`` and ``path`` is something else than a map file.
    """
    path = Path(path)
    meta: dict[str, Any] = {
        'format': FORMAT,
        'version': VERSION,
        'map_origin': fmap.map_origin.tolist(),
        'params': map_params_record(fmap.params),
        'buildings': [int(b) for b in fmap.buildings],
        'facades': [{'facade_id': f.facade_id, 'building': f.building, 'main_layer': f.layers.main_,
                     'facet_cell': f.facets.cell, 'surface_cell': f.surface.cell,
                     'global_mean': f.global_mean_, 'global_var': f.global_var_, 'noise_var': f.noise_var,
                     'fitted_points': f.fitted_points, 'relief_spacing': f.relief.spacing,
                     'stats': f.stats} for f in fmap.facades],
        'pool_checked': {str(b): int(n) for b, n in fmap.pool_checked.items()},
        'thinned': {str(b): int(n) for b, n in fmap.thinned.items()},
        'unmodelled': {str(b): int(n) for b, n in fmap.unmodelled_rows.items()},
        'occupancy': dict(fmap.occupancy_.as_dict(), stored=fmap.occupancy_stored_),
        'registration': {'var': float(fmap.registration_var_),
                         'sums': [float(x) for x in fmap.registration_sums_]},
    }
    arrays: dict[str, np.ndarray] = {'meta': np.array(json.dumps(meta))}
    for f in fmap.facades:
        arrays.update(_facade_arrays(f))
    for b in fmap.buildings:
        arrays[f'building/{b}/points'] = fmap.points[b]
        arrays[f'building/{b}/normals'] = fmap.normals[b]
        so = fmap.sensor_origins.get(b)
        if so is not None:
            arrays[f'building/{b}/sensor_origins'] = so
    if fmap.pending:
        # Points held back for the next update, as one batch (merging is what the next
        # update does first, so the loaded map goes on exactly as this one would).
        xyz = np.vstack([p[0] for p in fmap.pending])
        arrays['pending/xyz'] = xyz
        if any(p[1] is not None for p in fmap.pending):
            arrays['pending/building_id'] = np.concatenate(
                [p[1] if p[1] is not None else np.full(len(p[0]), -1, np.int64) for p in fmap.pending])
        if all(p[2] is not None for p in fmap.pending):
            arrays['pending/sensor_origins'] = np.vstack([p[2] for p in fmap.pending])
        # Each call held back is one scan (FacadeMap.registration_var_): its number per point.
        arrays['pending/scan'] = np.repeat(np.arange(len(fmap.pending), dtype=np.int64),
                                           [len(p[0]) for p in fmap.pending])

    def write(name: str) -> None:
        with open(name, 'wb') as fh:
            _write_npz(fh, arrays)

    atomic_write(path, write, before_replace=_only_maps if replace_only_maps else None)
    return path


def _only_maps(path: Path) -> None:
    if os.path.lexists(path) and not is_map_file(path):
        raise InputError(f'{path} exists and is not a map file of uncertain_facade_map: not replaced '
                         '(save_map replaces map files only)')


def is_map_file(path: str | Path) -> bool:
    """Whether ``path`` is a regular file (not a link) holding a map file's ``meta`` record
    (any version): read from the archive's directory and that one member, not the whole file."""
    path = Path(path)
    if path.is_symlink() or not path.is_file() or not zipfile.is_zipfile(path):
        return False
    try:
        with zipfile.ZipFile(path) as zf:
            info = zf.getinfo('meta.npy')
            if info.file_size > _META_MAX:
                return False
            with zf.open(info) as fh:
                meta = json.loads(str(np.lib.format.read_array(fh, allow_pickle=False)))
    except (KeyError, ValueError, OSError, EOFError, zipfile.BadZipFile, json.JSONDecodeError):
        return False
    return isinstance(meta, dict) and meta.get('format') == FORMAT


def unpacked_bytes(path: str | Path) -> int:
    """Bytes a map file holds once read: its size on disk, or the sum of its archive's
    members when larger (read from the zip's directory only)."""
    path = Path(path)
    size = path.stat().st_size
    try:
        with zipfile.ZipFile(path) as zf:
            return max(size, sum(i.file_size for i in zf.infolist()))
    except (zipfile.BadZipFile, OSError, ValueError):
        return size


def load_map(path: str | Path) -> FacadeMap:
    """Read a map file.

    Raises:
        InputError: missing file, not a map file, damaged, or of a newer version.
    """
    path = Path(path)
    if not path.exists():
        raise InputError(f'no such file: {path}')
    if not zipfile.is_zipfile(path):
        raise InputError(f'{path}: not a map file (not an NPZ archive)')
    try:
        with np.load(path, allow_pickle=False) as npz:
            arrays = {k: npz[k] for k in npz.files}
    except (zipfile.BadZipFile, ValueError, OSError, EOFError) as exc:
        raise InputError(f'{path}: not a map file ({str(exc).splitlines()[0] if str(exc) else type(exc).__name__})') from None
    if 'meta' not in arrays:
        raise InputError(f'{path}: not a map file (no meta record)')
    try:
        meta = json.loads(str(arrays['meta']))
    except json.JSONDecodeError:
        raise InputError(f'{path}: damaged map file (meta is not JSON)') from None
    if not isinstance(meta, dict) or meta.get('format') != FORMAT:
        raise InputError(f'{path}: not an {FORMAT} file')
    version = meta.get('version')
    if not isinstance(version, int) or version < 1:
        raise InputError(f'{path}: damaged map file (version {version!r})')
    if version > VERSION:
        raise InputError(f'{path}: map file version {version} was written by a newer uncertain_facade_map; '
                         f'this one reads versions 1 to {VERSION}')
    while version < VERSION:
        meta, arrays = MIGRATIONS[version](meta, arrays)
        version = meta['version']
    try:
        return _from_records(meta, arrays)
    except InputError as exc:  # a parameter record that the declarations refuse
        raise InputError(f'{path}: {exc}') from exc
    except (KeyError, ValueError, TypeError, IndexError) as exc:
        raise InputError(f'{path}: damaged map file ({type(exc).__name__}: {exc})') from None


def _from_records(meta: dict, arrays: dict[str, np.ndarray]) -> FacadeMap:
    params = map_params_from_record(meta['params'])
    facades = []
    for info in meta['facades']:
        p = f'facade/{info["facade_id"]}/'
        lay = arrays[p + 'layers']
        layers = DepthLayers(weights_=lay[0], means_=lay[1], sigmas_=lay[2], main_=int(info['main_layer']))
        facets = Facets(origin=arrays[p + 'facets_origin'], cell=float(info['facet_cell']), facet=arrays[p + 'facets'],
                        layer_of_facet=arrays[p + 'layer_of_facet'])
        surface = SurfaceRaster(origin=arrays[p + 'surface_origin'], cell=float(info['surface_cell']),
                                mean=arrays[p + 'surface_mean'], var=arrays[p + 'surface_var'],
                                facet=arrays[p + 'surface_facet'], source=arrays[p + 'surface_source'])
        facades.append(FacadeModel(
            facade_id=int(info['facade_id']), building=int(info['building']),
            frame=FacadeFrame.from_array(arrays[p + 'frame']), extent=tuple(float(x) for x in arrays[p + 'extent']),
            layers=layers, facets=facets, lengthscale2_=arrays[p + 'lengthscale2'],
            global_mean_=float(info['global_mean']), global_var_=float(info['global_var']),
            noise_var=float(info['noise_var']), surface=surface, point_index=arrays[p + 'point_index'],
            outlier_index=arrays[p + 'outlier_index'], stats=info.get('stats', {}),
            plane_extent=tuple(float(x) for x in arrays[p + 'plane_extent']), anchor=arrays[p + 'anchor'],
            fitted_points=int(info['fitted_points']),
            relief=Relief(arrays[p + 'relief_origin'], float(info['relief_spacing']), arrays[p + 'relief_values'])))
    points = {int(b): arrays[f'building/{b}/points'] for b in meta['buildings']}
    origins = {int(b): arrays.get(f'building/{b}/sensor_origins') for b in meta['buildings']}
    normals = {int(b): arrays[f'building/{b}/normals'] for b in meta['buildings']}
    pool = {int(b): int(n) for b, n in meta['pool_checked'].items()}
    thinned = {int(b): int(n) for b, n in meta.get('thinned', {}).items()}  # absent before issue 13
    pending = []
    if 'pending/xyz' in arrays:
        xyz, ids, so = arrays['pending/xyz'], arrays.get('pending/building_id'), arrays.get('pending/sensor_origins')
        scan = arrays.get('pending/scan', np.zeros(len(xyz), np.int64))  # absent before version 4: one part
        cuts = np.flatnonzero(np.diff(scan)) + 1
        for part in np.split(np.arange(len(xyz)), cuts):
            pending.append((xyz[part], None if ids is None else ids[part], None if so is None else so[part]))
    occupancy = dict(meta.get('occupancy', {}))  # absent before issue 14: the fixed formula
    stored = int(occupancy.pop('stored', 0))
    registration = meta['registration']
    fmap = FacadeMap(params, np.asarray(meta['map_origin'], dtype=np.float64), facades, points, origins, normals,
                     pool, pending=pending, thinned=thinned, occupancy_=PLSC(**occupancy), occupancy_stored_=stored,
                     registration_sums_=np.asarray(registration['sums'], dtype=np.float64).reshape(3),
                     registration_var_=float(registration['var']))
    # Stored points live mapping had not modelled yet (absent: none), modelled when it goes on.
    fmap.unmodelled_rows = {int(b): int(n) for b, n in meta.get('unmodelled', {}).items()}
    return fmap


def _upgrade_1(meta: dict, arrays: dict[str, np.ndarray]) -> tuple[dict, dict]:
    """Version 1 -> 2: plane extents are the façades' extents, anchors the rasters'
    origins, every façade counts as fitted whole, normals are estimated from the points, and
    the pools count as checked."""
    from ..pipeline.step1_facades import point_normals

    k = int(meta['params'].get('extraction', {}).get('normal_neighbours', 10))
    for info in meta['facades']:
        p = f'facade/{info["facade_id"]}/'
        arrays[p + 'plane_extent'] = arrays[p + 'extent']
        arrays[p + 'anchor'] = arrays[p + 'surface_origin']
        info['fitted_points'] = int(len(arrays[p + 'point_index']))
    pool = {}
    for b in meta['buildings']:
        pts = arrays[f'building/{b}/points']
        arrays[f'building/{b}/normals'] = point_normals(pts - pts.mean(axis=0), k) if len(pts) >= 3 else \
            np.tile([0.0, 0.0, 1.0], (len(pts), 1))
        owned = np.zeros(len(pts), dtype=bool)
        for info in meta['facades']:
            if int(info['building']) == int(b):
                owned[arrays[f'facade/{info["facade_id"]}/point_index']] = True
        pool[str(b)] = int((~owned).sum())
    meta = dict(meta, version=2, pool_checked=pool)
    return meta, arrays


MIGRATIONS[1] = _upgrade_1


def _upgrade_2(meta: dict, arrays: dict[str, np.ndarray]) -> tuple[dict, dict]:
    """Version 2 -> 3: the façades' walls are flat (no relief) and their noise was the
    configured sigma_eta; the parameters say so, so that the map goes on as it was built."""
    for info in meta['facades']:
        p = f'facade/{info["facade_id"]}/'
        arrays[p + 'relief_origin'] = np.zeros(2)
        arrays[p + 'relief_values'] = np.zeros((1, 1))
        info['relief_spacing'] = 1.0
    record = meta['params']
    record['layers'] = dict(record.get('layers', {}), relief_spacing=0.0)
    record['gp'] = dict(record.get('gp', {}), estimate_noise=False)
    record['gp'].setdefault('planar_per_block', 0)
    return dict(meta, version=3), arrays


MIGRATIONS[2] = _upgrade_2


def _upgrade_3(meta: dict, arrays: dict[str, np.ndarray]) -> tuple[dict, dict]:
    """Version 3 -> 4: no scan-to-scan disagreement was learnt (variance 0), and the
    parameters say none is, so that the map goes on as it was built."""
    record = meta['params']
    record['update'] = dict(record.get('update', {}), registration_points=0)
    return dict(meta, version=4, registration={'var': 0.0, 'sums': [0.0, 0.0, 0.0]}), arrays


MIGRATIONS[3] = _upgrade_3
