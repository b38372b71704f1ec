"""Export a map for Autoware's point-cloud map loader: the mean surface as PCD tiles and their metadata YAML.

Localisers that know nothing of our façade models (Autoware's NDT scan matcher, through
``autoware_map_loader``'s ``pointcloud_map_loader``) read a point-cloud map cut into square
PCD files listed in a metadata YAML. :func:`export_autoware` writes the map's mean surface
(:func:`~uncertain_facade_map.mapping.products.surface_grid`: the facet cells of every
façade's surface raster, at their mean depth, in the map frame) that way, with the standard
deviation of the surface in an extra field.

What the loader and the divider expect (sources: ``autowarefoundation/autoware.universe``,
``map/autoware_map_loader``; ``autowarefoundation/autoware_tools``,
``map/autoware_pointcloud_divider``):

* Metadata format (loader ``src/pointcloud_map_loader/utils.cpp``, ``load_pcd_metadata``):
  every top-level key other than ``x_resolution`` and ``y_resolution`` is taken as a file
  name whose value is read with ``as<std::vector<int>>()`` as ``[min_x, min_y]``; the cell is
  ``min .. min + x_resolution`` (``y_resolution``), the resolutions read as floats. Hence the
  minima must be YAML integers (yaml-cpp refuses ``1200.0`` as an int) and the YAML may hold
  no other key: the map's georeference is a comment. Here: ``grid`` must be a whole number of
  metres, so every cell corner is an integer.
* File names (same file, ``replace_with_absolute_path``): a metadata key is matched against
  the base name of each PCD file found; a key without a file stops the loader ("Missing PCD
  segments"). The loader lists a folder's ``.pcd`` / ``.PCD`` files, not recursively
  (``pointcloud_map_loader_node.cpp``, ``get_pcd_paths``), so the metadata YAML and the
  temporary files (``.NAME.XXXX.tmp``) may share the folder. The loader's README names the
  metadata ``pointcloud_map_metadata.yaml`` (as here); the divider writes
  ``<prefix>_metadata.yaml`` (``src/pcd_divider.cpp``, ``run``) and its README says
  ``pointcloud_data_metadata.yaml``.
* The divider's file names and bounds (``include/autoware/pointcloud_divider/grid_info.hpp``,
  ``pointToGrid2``: ``static_cast<int>(std::floor(p.x / res_x) * res_x)``;
  ``src/pcd_divider.cpp``, ``makeFileName`` / ``mergeAndDownsample``:
  ``<prefix>_<min_x>_<min_y>.pcd``): a file is named by its cell's lower-left corner in
  metres (not the cell index; negative as ``-20``), and a point goes to the cell
  ``floor(x / res)``, i.e. the half-open ``min_x <= x < min_x + res``. The conventions
  differ: the divider's README writes the cells closed (``1200 <= x <= 1300``), the loader's
  README open (``1200 < x < 1220``), and the loader's area test
  (``utils.cpp``, ``cylinder_and_box_overlap_exists``) treats the box as closed (``<=``).
  This export follows the divider's code: names ``<prefix>_<min_x>_<min_y>.pcd`` and the
  floor rule on the float32 coordinates written, so every point of a file satisfies
  ``min <= x < min + grid`` exactly (and thus every reading above). Our own tiles
  (``tiling.grid.tile_id``) are named by index instead (``tile_m3_12``); the two do not mix.
* Fields: the loader reads each file into a ``sensor_msgs/PointCloud2`` whatever its fields
  (``pcl::io::loadPCDFile``, ``differential_map_loader_module.cpp``) and its whole-map load
  concatenates the files' raw data (``pointcloud_map_loader_module.cpp``,
  ``load_pcd_files``), so every file must have the same fields (here: always). The NDT scan
  matcher converts the map to ``pcl::PointXYZ``
  (``localization/autoware_ndt_scan_matcher/include/autoware/ndt_scan_matcher/map_update_module.hpp``,
  ``PointTarget``): it needs x, y, z only, extra fields are ignored; no ``intensity`` is
  written. The divider reads ``PointXYZ`` or ``PointXYZI`` only (its README) and drops
  other fields: dividing our files again loses ``std``.

Coordinates are float32, as Autoware's ``pcl::PointXYZ``: points farther than
:data:`MAX_COORDINATE` (131 km, where float32 keeps 7.8 mm) from the map frame's origin are
refused rather than rounded (a map whose origin is not near its data).

The PCD files (binary, via :func:`~uncertain_facade_map.io.pcd.write_pcd`) hold
``x, y, z`` (float32, metres, map frame) and ``std`` (float32, metres: ``sqrt`` of the
surface raster's variance at the cell, the measurement noise not included). ``VIEWPOINT`` is
the identity (as Autoware's maps have it; PCL's viewers would shift the points by a
translation there), so the map origin is stated in the YAML's comment only. A tile's
points come façade by façade, each raster row-major (:func:`surface_grid`'s order).

Every file is written atomically (temporary file in the folder, fsync, rename); the
metadata last, so a folder with metadata is a complete export. A tiled map is exported one
map tile at a time: its cells' points are spilled to temporary files in the folder and each
PCD is written from its spill, so memory holds one map tile and one PCD cell at a time.
"""

from __future__ import annotations

import math
import os
import re
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterator

import numpy as np

from ..errors import InputError
from ..mapping.facade_map import FacadeMap
from ..mapping.products import surface_grid
from ._files import _one_line, atomic_write
from .cloud import Cloud
from .pcd import write_pcd

__all__ = ['AUTOWARE_GRID', 'MAX_COORDINATE', 'METADATA_NAME', 'PCD_DTYPE', 'AutowareExport', 'ExportedFile', 'cell_file_name',
           'export_autoware']

#: Autoware's cell side, metres (the divider's default ``grid_size_x``; the loader's README
#: asks for about 20 m and discourages over 100 m).
AUTOWARE_GRID = 20.0
#: Name of the metadata YAML (the loader README's ``pointcloud_map_metadata.yaml``).
METADATA_NAME = 'pointcloud_map_metadata.yaml'
#: Default prefix of the PCD file names.
DEFAULT_PREFIX = 'pointcloud_map'
#: Fields of every PCD file: x, y, z (metres, map frame) and std (metres), float32.
PCD_DTYPE = np.dtype([('x', '<f4'), ('y', '<f4'), ('z', '<f4'), ('std', '<f4')])

#: Largest distance from the map frame's origin written, metres: float32 spacing is 7.8 mm
#: below it (Autoware's MGRS-local map frames span 100 km).
MAX_COORDINATE = 131_072.0

_PREFIX = re.compile(r'[A-Za-z0-9_][A-Za-z0-9_.-]*')
_SPILL = '.autoware-export-spill'


@dataclass(frozen=True)
class ExportedFile:
    """One PCD file of an export.

    Attributes:
        name: file name in the export folder, ``<prefix>_<min_x>_<min_y>.pcd``.
        min_xy: (min_x, min_y) of its cell, integer metres, map frame (the metadata's value).
        points: points in the file.
    """

    name: str
    min_xy: tuple[int, int]
    points: int


@dataclass(frozen=True)
class AutowareExport:
    """What :func:`export_autoware` wrote.

    Attributes:
        folder: the export folder (PCD files and metadata).
        metadata: the metadata YAML's path.
        grid: cell side, metres.
        files: the PCD files, sorted by (min_x, min_y).
        points: points written in all.
        bounds: (6,) min x, y, z, max x, y, z of the points written (float32 values),
            metres, map frame; NaN for an export without points.
        map_origin: (3,) the map frame's georeference, metres.
    """

    folder: Path
    metadata: Path
    grid: float
    files: list[ExportedFile]
    points: int
    bounds: tuple[float, ...]
    map_origin: tuple[float, float, float]


def cell_file_name(prefix: str, min_x: int, min_y: int) -> str:
    """The divider's file name of the cell with lower-left corner (min_x, min_y) (integer metres)."""
    return f'{prefix}_{int(min_x)}_{int(min_y)}.pcd'


def _checked_grid(grid: float) -> int:
    try:
        value = float(grid)
    except (TypeError, ValueError) as exc:
        raise InputError(f'grid must be a number of metres, got {grid!r}') from exc
    if not math.isfinite(value) or value < 1 or not value.is_integer():
        raise InputError(f'grid must be a whole number of metres >= 1, got {grid!r} (Autoware\'s metadata holds the '
                         'cell corners as integers; 20 is Autoware\'s default)')
    return int(value)


def _checked_prefix(prefix: str) -> str:
    if prefix != '' and not _PREFIX.fullmatch(prefix):
        raise InputError(f'prefix {prefix!r} cannot start a PCD file name (use ASCII letters, digits and _ . -, '
                         'not starting with . or -)')
    return prefix


def _pieces(source: Any) -> tuple[np.ndarray, Iterator[FacadeMap], int]:
    """(map origin, the maps to export one at a time, how many) of ``source``.

    A path is a map file or a tiled map (its folder or ``manifest.json``); a tiled map read
    from its path loads each tile once, checked against the manifest's hash, and keeps none
    (no reader cache: the export reads every tile once).
    """
    if isinstance(source, FacadeMap):
        return np.asarray(source.map_origin, np.float64), iter([source]), 1
    if isinstance(source, (str, os.PathLike)):
        from ..tiling.manifest import is_tiled_map, manifest_path, read_manifest, verify_tile
        from ..tiling.tiled_map import open_map
        from .map_file import load_map

        if not is_tiled_map(source):
            return _pieces(open_map(source))  # a map file; a folder without manifest is refused
        manifest = read_manifest(source)
        folder = manifest_path(source).parent
        records = [manifest.tiles[t] for t in sorted(manifest.tiles)]
        return (np.asarray(manifest.map_origin, np.float64),
                (load_map(verify_tile(folder, r)) for r in records), len(records))
    manifest = getattr(source, 'manifest_', None)
    if manifest is None or not hasattr(source, 'tile'):
        raise InputError(f'cannot export a {type(source).__name__}: give a FacadeMap, a tiled map or a map path')
    ids = sorted(manifest.tiles)
    return np.asarray(source.map_origin, np.float64), (source.tile(t) for t in ids), len(ids)


def _surface_rows(fmap: FacadeMap, step: float | None) -> np.ndarray:
    """The map's mean-surface points as PCD rows (float32 x, y, z, std)."""
    grid = surface_grid(fmap.facades, step)
    _check_float32(grid.xyz)
    rows = np.empty(len(grid), PCD_DTYPE)
    for i, name in enumerate('xyz'):
        rows[name] = grid.xyz[:, i]
    rows['std'] = grid.std
    return rows


def _check_float32(xyz: np.ndarray) -> None:
    """Refuse (N, 3) map-frame points (metres) that float32 would round by more than 8 mm."""
    far = float(np.abs(xyz).max()) if len(xyz) else 0.0
    if not far < MAX_COORDINATE:
        spacing = float(np.spacing(np.float32(min(far, 3e38))))
        raise InputError(f'surface points lie up to {far:,.0f} m from the map frame\'s origin, where float32 (PCD '
                         f'x, y, z) keeps only {spacing * 100:.3g} cm: give the map a map origin near its data '
                         f'(within {MAX_COORDINATE:,.0f} m)')


def _cells(rows: np.ndarray, grid: int) -> np.ndarray:
    """(N, 2) int64 cell corners (min_x, min_y), metres: the floor rule on the float32 values."""
    xy = np.stack([rows['x'].astype(np.float64), rows['y'].astype(np.float64)], axis=1)
    return np.floor(xy / grid).astype(np.int64) * grid


def _group(rows: np.ndarray, grid: int) -> Iterator[tuple[tuple[int, int], np.ndarray]]:
    """The rows of each cell (sorted by corner), in their order."""
    if len(rows) == 0:
        return
    cells = _cells(rows, grid)
    keys, inverse = np.unique(cells, axis=0, return_inverse=True)
    inverse = inverse.reshape(-1)
    order = np.argsort(inverse, kind='stable')
    starts = np.searchsorted(inverse[order], np.arange(len(keys) + 1))
    for k, key in enumerate(keys):
        yield (int(key[0]), int(key[1])), rows[order[starts[k]:starts[k + 1]]]


def _write_cell(folder: Path, prefix: str, corner: tuple[int, int], rows: np.ndarray) -> ExportedFile:
    name = cell_file_name(prefix, *corner)
    cloud = Cloud(np.ascontiguousarray(rows), np.zeros(3))
    atomic_write(folder / name, lambda tmp: write_pcd(tmp, cloud, encoding='binary'))
    return ExportedFile(name, corner, len(rows))


def _metadata_text(files: list[ExportedFile], grid: int, map_origin: np.ndarray, bounds: tuple[float, ...]) -> str:
    origin = ' '.join(repr(float(v)) for v in map_origin)
    lines = [
        "# Point-cloud map metadata for Autoware's pointcloud_map_loader (written by uncertain_facade_map).",
        '# Each file: [min_x, min_y] of its cell; points satisfy min_x <= x < min_x + x_resolution (likewise y).',
        '# Points: x, y, z float32, metres, map frame; std float32, metres (standard deviation of the mean',
        '# surface, sqrt of the surface variance, measurement noise not included).',
        f'# Map frame georeference (map_origin, metres; add it to x, y, z): {origin}',
        '# Bounds of the points (min x y z, max x y z): ' + ' '.join(f'{v:.3f}' for v in bounds),
        f'x_resolution: {float(grid)!r}',
        f'y_resolution: {float(grid)!r}',
    ]
    lines += [f'{f.name}: [{f.min_xy[0]}, {f.min_xy[1]}]' for f in files]
    return '\n'.join(lines) + '\n'


def _prepare(folder: Path, force: bool) -> None:
    """Create ``folder`` (its parent must exist) or check that it holds no earlier export."""
    if folder.exists() and not folder.is_dir():
        raise InputError(f'{folder} is not a folder')
    if not folder.exists():
        if not folder.parent.is_dir():
            raise InputError(f'cannot create {folder}: no folder {folder.parent}')
        folder.mkdir()
        return
    old = [p for p in folder.iterdir() if p.suffix.lower() == '.pcd' or p.name == METADATA_NAME or p.name == _SPILL]
    if old and not force:
        raise InputError(f'{folder} already holds an export ({len(old)} PCD/metadata files; the loader would read '
                         'them all): choose an empty folder or replace them (--force)')
    # With them go the temporary files a killed export left (``.NAME.pcd.XXXX.tmp``).
    stale = [p for p in folder.iterdir() if p.name.startswith('.') and p.name.endswith('.tmp')
             and ('.pcd.' in p.name or p.name.startswith(f'.{METADATA_NAME}.'))]
    for p in old + stale:
        shutil.rmtree(p) if p.is_dir() else p.unlink()


def export_autoware(source: FacadeMap | str | os.PathLike[str] | Any, out: str | os.PathLike[str], grid: float = AUTOWARE_GRID,
                    prefix: str = DEFAULT_PREFIX, *, step: float | None = None, force: bool = False,
                    progress: Callable[[int, int], None] | None = None) -> AutowareExport:
    """Write the map's mean surface as Autoware PCD tiles plus ``pointcloud_map_metadata.yaml``.

    One binary PCD per ``grid`` x ``grid`` m cell (map frame, corners at multiples of
    ``grid``) holding surface points, named ``<prefix>_<min_x>_<min_y>.pcd``; a point of
    float32 coordinates (x, y) goes to the cell ``floor(x / grid) * grid``,
    ``floor(y / grid) * grid``. Fields x, y, z, std (float32, metres, map frame). See the
    module docstring for the loader's and the divider's conventions and their sources.

    Args:
        source: a :class:`FacadeMap`; a tiled map (``tiling.tiled_map.TiledMap``:
            ``manifest_.tiles``, ``tile(id)``, ``map_origin``), read one tile at a time; or
            the path of a map file or of a tiled map (its folder or ``manifest.json``), whose
            tiles are loaded one at a time (each checked against the manifest's hash).
        out: export folder; created if missing (its parent must exist).
        grid: cell side, whole metres (default 20, Autoware's).
        prefix: start of the PCD file names (ASCII letters, digits, ``_ . -``; may be empty,
            as the divider's default).
        step: surface sampling step on each façade plane, metres; None (default) for each
            raster's own cells (the raster's values exactly).
        force: replace an earlier export in ``out`` (its ``.pcd`` files, metadata and the
            temporary files of a killed export); otherwise such a folder is refused. Other
            files in ``out`` are left alone.
        progress: called with (map pieces done, pieces) after each map tile.

    Returns:
        What was written (:class:`AutowareExport`).

    Raises:
        InputError: a bad grid or prefix, a missing or damaged map, surface points
            ``MAX_COORDINATE`` m or more from the map frame's origin (float32 would round
            them by more than 8 mm), an unusable folder, a folder holding an earlier export
            without ``force``, or a file that cannot be written.
    """
    grid_m = _checked_grid(grid)
    prefix = _checked_prefix(prefix)
    folder = Path(out)
    map_origin, pieces, n_pieces = _pieces(source)
    try:
        _prepare(folder, force)
        if n_pieces == 1:
            rows = _surface_rows(next(pieces), step)
            files = [_write_cell(folder, prefix, corner, cell) for corner, cell in _group(rows, grid_m)]
            lo, hi = _row_bounds(rows)
            if progress is not None:
                progress(1, 1)
        else:
            files, lo, hi = _export_spilled(folder, prefix, grid_m, pieces, n_pieces, step, progress)
        files.sort(key=lambda f: f.min_xy)
        bounds = tuple(float(v) for v in (*lo, *hi))
        metadata = folder / METADATA_NAME
        text = _metadata_text(files, grid_m, map_origin, bounds)

        def write_text(tmp: str) -> None:
            Path(tmp).write_text(text, encoding='ascii')

        atomic_write(metadata, write_text)
    except OSError as exc:
        raise InputError(f'cannot write the export to {folder}: {_one_line(exc)}') from exc
    return AutowareExport(folder, metadata, float(grid_m), files, sum(f.points for f in files), bounds,
                          tuple(float(v) for v in map_origin))


def _row_bounds(rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    if len(rows) == 0:
        return np.full(3, np.nan), np.full(3, np.nan)
    xyz = np.stack([rows[c].astype(np.float64) for c in 'xyz'], axis=1)
    return xyz.min(axis=0), xyz.max(axis=0)


def _export_spilled(folder: Path, prefix: str, grid: int, pieces: Iterator[FacadeMap], n_pieces: int,
                    step: float | None, progress: Callable[[int, int], None] | None
                    ) -> tuple[list[ExportedFile], np.ndarray, np.ndarray]:
    """Export map tiles one at a time: rows appended per cell to spill files, then one PCD per spill."""
    spill = folder / _SPILL
    spill.mkdir()
    lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
    corners: set[tuple[int, int]] = set()
    try:
        for done, fmap in enumerate(pieces, 1):
            rows = _surface_rows(fmap, step)
            del fmap
            if len(rows):
                a, b = _row_bounds(rows)
                lo, hi = np.minimum(lo, a), np.maximum(hi, b)
            for corner, cell in _group(rows, grid):
                with open(spill / f'{corner[0]}_{corner[1]}.bin', 'ab') as fh:
                    fh.write(cell.tobytes())
                corners.add(corner)
            if progress is not None:
                progress(done, n_pieces)
        files = []
        for corner in sorted(corners):
            part = spill / f'{corner[0]}_{corner[1]}.bin'
            rows = np.fromfile(part, dtype=PCD_DTYPE)
            files.append(_write_cell(folder, prefix, corner, rows))
            part.unlink()
    finally:
        shutil.rmtree(spill, ignore_errors=True)
    if not corners:
        lo, hi = np.full(3, np.nan), np.full(3, np.nan)
    return files, lo, hi
