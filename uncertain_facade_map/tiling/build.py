"""The tiled build's plain pieces (issue 29): routing points to tiles by area, and one tile's task.

No Dask here (the core imports numpy, scipy, sklearn only): ``uncertain_facade_map_apps.cluster``
runs the survey and spill of each input (:func:`survey_part`, :func:`spill_part`) and
:func:`build_tile` on Dask's workers, or in this process, and owns the manifest.

The build goes in three steps:

1. **Survey** (:func:`survey_part`, one piece of the input at a time -- an input file on a
   worker, or a chunk given to :meth:`Router.add`): each chunk of building points is shifted
   into the build's map frame, limited to ``bounds``, spilled to ``DIR/.work/chunks/`` and its
   buildings measured (:class:`Survey`): per given building id its (x, y) bounding box; points
   without an id add their ``extraction.building_cell`` cells (in order of first point) with
   each cell's bounding box. The client merges the pieces' surveys in input order
   (:meth:`Router.merge`: the same survey as the whole input's, bit for bit); it holds cells and
   boxes, never the points.
2. **Plan** (:meth:`Router.plan`, in the client): the cells are clustered over the whole input
   (8-connected components, numbered in order of first point from ``max(id) + 1``: the labels
   :func:`~uncertain_facade_map.pipeline.step1_facades.split_buildings` gives the joined input,
   whatever the cut into inputs and chunks); each building goes to the tile of the centre of its
   bounding box (``tiles.side``), or stays in the tile an existing tiled map gives it
   (``building_tiles``). The result, :class:`RoutePlan`, is what every spill needs.
3. **Spill** (:func:`spill_part`, per piece, on a worker or in this process): the piece's
   chunks are read back one at a time and each tile's points (xyz, building label, sensor
   origins; input order) written to ``DIR/.work/tiles/<id>/part_<k>.npz`` files, each hashed;
   :meth:`Router.tasks` puts the parts in input order and fingerprints each tile by its parts'
   digests.

A task (:class:`TileTask`, picklable) then maps one tile's buildings in one
:class:`~uncertain_facade_map.mapping.facade_map.FacadeMap` (or continues the tile's saved map:
a second drive) and writes the tile with :func:`~.manifest.save_tile` (:func:`build_tile`).

With sensor origins a building's façades depend on its own points only (the façade seeds are
building-local), so a tile's buildings are bit for bit those of a single-process build of the
whole input. Without sensor origins, walls are turned by the other buildings' points
(``FacadeMap._context``): a tile uses its own buildings as that context, so a building near a
tile's edge may differ from the single-process build.
"""

from __future__ import annotations

import hashlib
import json
import os
import resource
import shutil
import time
from collections.abc import Iterable
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..params import MapParams, map_params_record
from ..pipeline.step1_facades import _grid_components, building_cells
from .grid import TileGrid, tile_id
from .manifest import Manifest, TileRecord, save_tile, sha256_file

#: The build's work folder inside the tiled map's folder (spilled points; removed when done).
WORK = '.work'
#: The running build's record in the tiled map's folder: the first label of its clustered buildings.
RUN = '.build_run.json'
#: Separator of the per-run fingerprints in :attr:`TileRecord.inputs` (a tile built by two drives
#: lists two).
RUNS = '+'


def parse_bounds(text: str) -> tuple[float, float, float, float]:
    """``MIN_X,MIN_Y,MAX_X,MAX_Y`` (metres, the inputs' georeferenced coordinates) as four floats.

    Raises:
        InputError: not four finite numbers with min < max.
    """
    try:
        values = tuple(float(v) for v in text.split(','))
    except ValueError as err:
        raise InputError(f'bounds must be MIN_X,MIN_Y,MAX_X,MAX_Y in metres, got {text!r}') from err
    if len(values) != 4 or not np.isfinite(values).all() or values[0] >= values[2] or values[1] >= values[3]:
        raise InputError(f'bounds must be four finite numbers MIN_X,MIN_Y,MAX_X,MAX_Y with MIN < MAX, got {text!r}')
    return values  # type: ignore[return-value]


def in_bounds(xy: np.ndarray, bounds: tuple[float, float, float, float] | None) -> np.ndarray:
    """(N,) bool: which (N, 2+) georeferenced x, y lie in ``[min_x, max_x) x [min_y, max_y)``."""
    if bounds is None:
        return np.ones(len(xy), dtype=bool)
    return (xy[:, 0] >= bounds[0]) & (xy[:, 0] < bounds[2]) & (xy[:, 1] >= bounds[1]) & (xy[:, 1] < bounds[3])


@dataclass(frozen=True)
class TileTask:
    """One tile's work: everything :func:`build_tile` needs, picklable.

    Attributes:
        folder: the tiled map's folder (shared with the workers).
        tile_id: e.g. ``'tile_3_m1'``.
        index: (ix, iy) of the tile in the grid.
        bounds: the tile square (min_x, min_y, max_x, max_y), map frame, m.
        parts: the tile's spilled point files, in input order (``.npz``: xyz, building_id,
            sensor_origins if known).
        params: the map's parameters.
        map_origin: (3,) the map's georeference, m.
        inputs: the fingerprint the record gets (earlier runs' and this run's, :data:`RUNS`). A
            run's fingerprint is the sha256 of the map parameters' record, the map origin and the
            sha256 digests of the tile's part files' rows (:func:`_rows`) in input order
            (:meth:`Router.tasks`): the same for the same inputs whatever runs the routing, and
            whatever the number of workers; it depends on the cut of the input into chunks (one
            part per chunk), which a resumed build or a repeated drive reads alike.
        previous: the tile's saved map to continue (a second drive), or None: a new map.
        calibrate: voxel side of a PLSC calibration of the tile's own, or None (the command
            line: one for the whole map, :func:`city_occupancy`).
    """

    folder: str
    tile_id: str
    index: tuple[int, int]
    bounds: tuple[float, float, float, float]
    parts: tuple[str, ...]
    params: MapParams
    map_origin: tuple[float, float, float]
    inputs: str
    previous: str | None = None
    calibrate: float | None = None


@dataclass(frozen=True)
class TileResult:
    """What a task gives back: the tile's record and how the worker fared.

    Attributes:
        record: the tile's manifest record (the file is written).
        pid: the worker process.
        max_rss_kb: its peak resident memory so far (``ru_maxrss``, KiB on Linux).
        points: building points the task mapped.
        map_seconds: mapping (and calibrating) time, s.
        write_seconds: saving time, s.
        cpu_seconds: the task's processor time (user and system, this process), s: its work,
            whatever else shares the cores.
    """

    record: TileRecord
    pid: int
    max_rss_kb: int
    points: int
    map_seconds: float
    write_seconds: float
    cpu_seconds: float = 0.0


def read_parts(parts: tuple[str, ...] | list[str]) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """A tile's spilled points: (N, 3) xyz, (N,) int64 labels, (N, 3) sensor origins or None."""
    xyz, ids, origins = [], [], []
    for part in parts:
        with np.load(part) as z:
            xyz.append(z['xyz'])
            ids.append(z['building_id'])
            origins.append(z['sensor_origins'] if 'sensor_origins' in z.files else None)
    so = None if any(o is None for o in origins) else np.vstack(origins)
    return np.vstack(xyz), np.concatenate(ids), so


def build_tile(task: TileTask) -> TileResult:
    """Map one tile's buildings and write the tile (:func:`~.manifest.save_tile`); the manifest
    is the caller's. A second drive continues the saved tile (``add_points``, as a live map)."""
    from ..io.map_file import load_map, remove_stale_temporaries
    from ..mapping.facade_map import FacadeMap

    started, cpu = time.perf_counter(), time.process_time()
    xyz, ids, origins = read_parts(task.parts)
    if task.previous is not None:
        fmap = load_map(Path(task.folder) / task.previous)
    else:
        fmap = FacadeMap(task.params, np.asarray(task.map_origin, dtype=np.float64))
    fmap.add_points(xyz, ids, origins)
    if task.calibrate is not None and fmap.facades and fmap._has_rays:
        fmap.calibrate_occupancy(task.calibrate)
    mapped = time.perf_counter()
    without_timings(fmap)
    remove_stale_temporaries(Path(task.folder) / 'tiles' / f'{task.tile_id}.npz')
    record = save_tile(task.folder, task.tile_id, task.index, task.bounds, fmap, task.inputs)
    written = time.perf_counter()
    return TileResult(record, os.getpid(), int(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss), len(xyz),
                      mapped - started, written - mapped, time.process_time() - cpu)


def calibrate_tile(folder: str, files: str | list[str] | tuple[str, ...], resolution: float | None) -> dict:
    """The tiled map's map-wide calibrations (what :class:`~.tiled_map.TiledMap` answers every
    tile with), learnt on the build's largest tiles joined (:func:`calibration_tiles`): one
    calibration on a sample of the size a one-file map's draws, whatever the number of tiles,
    where one per tile cost five times the mapping.

    - ``occupancy``: the occupancy's PLSC (``Manifest.occupancy``), learnt as ``build`` learns a
      map's (:meth:`~uncertain_facade_map.mapping.facade_map.FacadeMap.calibrate_occupancy`); None:
      no ``resolution`` given, points without sensor origins, or too few labelled voxels (the
      fixed formula).
    - ``local_calibration``: the local reading's leave-one-out factor for the default query
      settings (``Manifest.local_calibration``, :func:`~.tiled_map.local_calibration`).

    Args:
        folder: the tiled map's folder.
        files: the tiles' files, relative to ``folder``.
        resolution: voxel side of the occupancy's labels, m, or None: no occupancy learnt.
    """
    from ..io.map_file import load_map
    from .tiled_map import local_calibration, merge_maps

    maps = [load_map(Path(folder) / f) for f in ([files] if isinstance(files, str) else files)]
    fmap = maps[0] if len(maps) == 1 else merge_maps(maps)
    occupancy = None
    if resolution is not None and fmap.facades and fmap._has_rays:
        plsc = fmap.calibrate_occupancy(resolution)
        occupancy = plsc.as_dict() if plsc.learnt else None
    return {'occupancy': occupancy, 'local_calibration': local_calibration(fmap) if fmap.facades else {}}


def routed_points(task: TileTask) -> int:
    """The points routed to a task's tile (its spilled parts' rows, read from their headers)."""
    import zipfile

    n = 0
    for part in task.parts:
        with zipfile.ZipFile(part) as z, z.open('building_id.npy') as f:
            version = np.lib.format.read_magic(f)
            shape = np.lib.format.read_array_header_1_0(f)[0] if version == (1, 0) else \
                np.lib.format.read_array_header_2_0(f)[0]
            n += int(shape[0])
    return n


def calibration_tiles(tasks: list[TileTask]) -> tuple[str, ...]:
    """The tiles the run learns the map-wide calibrations on (:func:`calibrate_tile`): the
    largest (most routed points; ties to the first id) until they hold the occupancy sample's
    size (``mapping.calibration.Settings.max_points``, 200,000 points) between them, chosen
    among all the run's tiles, built already or not, so that a resumed build learns on the
    ones the uninterrupted build would. One tile of the simulated city is enough; a small map
    cut into small tiles is learnt on all of them (as its one-file map: on a real sweep cut into
    10 m tiles, the largest alone cost PR-AUC 0.95 -> 0.92)."""
    from ..mapping.calibration import Settings

    if not tasks:
        return ()
    sizes = {t.tile_id: routed_points(t) for t in tasks}
    out, total = [], 0
    for t in sorted(tasks, key=lambda t: (-sizes[t.tile_id], t.tile_id)):
        out.append(t.tile_id)
        total += sizes[t.tile_id]
        if total >= Settings.max_points:
            break
    return tuple(sorted(out))


def without_timings(fmap) -> None:
    """Drop the fits' timings (``stats['seconds']``) from the map's façade models, so that a
    tile's bytes depend on its content only: a resumed or repeated build writes the same file
    (the same sha256) as an uninterrupted one."""
    for i, f in enumerate(fmap.facades):
        if 'seconds' in f.stats:
            fmap.facades[i] = replace(f, stats={k: v for k, v in f.stats.items() if k != 'seconds'})


def intact(folder: str | Path, record: TileRecord) -> bool:
    """Whether the tile's file exists and has the sha256 its record gives."""
    path = Path(folder) / record.file
    return path.is_file() and sha256_file(path) == record.sha256


@dataclass
class Survey:
    """What routing keeps of building points (map frame), never the points: per given building
    id its (x, y) bounding box, and the ``extraction.building_cell`` cells of the points without
    an id, in order of first point, each with its bounding box.

    One survey measures chunks in input order (:meth:`measure`); surveys of consecutive pieces
    of the input merge into the survey of their union (:meth:`merge`, in input order): boxes are
    unions (minimum and maximum, exact) and a cell keeps the place of its first point, so the
    merged survey is bit for bit the one of the whole input measured chunk by chunk.
    """

    box: dict[int, np.ndarray] = field(default_factory=dict)  # id -> (4,) min x, min y, max x, max y
    cells: list[np.ndarray] = field(default_factory=list)  # new cell keys per piece, order of first point
    cell_keys: np.ndarray = field(default_factory=lambda: np.empty(0, np.int64))  # sorted
    cell_order: np.ndarray = field(default_factory=lambda: np.empty(0, np.int64))  # rank of each sorted key
    cell_box: np.ndarray = field(default_factory=lambda: np.empty((0, 4)))  # (C, 4) per rank

    def measure(self, xyz: np.ndarray, ids: np.ndarray, cell: float) -> None:
        """Add one chunk: (N, 3) xyz (m, map frame), (N,) int64 ids (negative: none), the
        clustering cell side (m)."""
        given = ids >= 0
        if given.any():
            labels, inverse = np.unique(ids[given], return_inverse=True)
            self._add_boxes(labels.tolist(), _boxes(xyz[given, :2], inverse, len(labels)))
        free = ~given
        if not free.any():
            return
        keys = building_cells(xyz[free], cell)
        uniq, first, inverse = np.unique(keys, return_index=True, return_inverse=True)
        self._add_cells(uniq, first, _boxes(xyz[free, :2], inverse.reshape(-1), len(uniq)))

    def merge(self, other: Survey) -> None:
        """Add the survey of the input's next piece (the pieces in input order)."""
        self._add_boxes(sorted(other.box), [other.box[b] for b in sorted(other.box)])
        keys = other.cell_list()
        if len(keys):
            self._add_cells(keys, np.arange(len(keys)), other.cell_box)

    def cell_list(self) -> np.ndarray:
        """(C,) int64 the cell keys in order of first point."""
        return np.concatenate(self.cells) if self.cells else np.empty(0, np.int64)

    def _add_boxes(self, labels: list[int], boxes) -> None:
        for b, bx in zip(labels, boxes):
            old = self.box.get(b)
            self.box[b] = bx if old is None else np.r_[np.minimum(old[:2], bx[:2]), np.maximum(old[2:], bx[2:])]

    def _add_cells(self, uniq: np.ndarray, first: np.ndarray, box: np.ndarray) -> None:
        """(K,) distinct keys, (K,) the place of each one's first point, (K, 4) their boxes."""
        pos = np.searchsorted(self.cell_keys, uniq)
        known = np.zeros(len(uniq), dtype=bool)
        if len(self.cell_keys):
            known = self.cell_keys[np.minimum(pos, len(self.cell_keys) - 1)] == uniq
        rank = self.cell_order[pos[known]]
        old = self.cell_box[rank]
        self.cell_box[rank] = np.c_[np.minimum(old[:, :2], box[known, :2]), np.maximum(old[:, 2:], box[known, 2:])]
        new = np.flatnonzero(~known)
        new = new[np.argsort(first[new], kind='stable')]  # order of first point
        if len(new):
            ranks = len(self.cell_box) + np.arange(len(new))
            self.cells.append(uniq[new])
            self.cell_box = np.vstack([self.cell_box, box[new]])
            at = np.searchsorted(self.cell_keys, uniq[new])
            order = np.argsort(uniq[new])
            self.cell_keys = np.insert(self.cell_keys, at[order], uniq[new][order])
            self.cell_order = np.insert(self.cell_order, at[order], ranks[order])


@dataclass
class Part:
    """One piece of the input (an input file, or one :meth:`Router.add` chunk) surveyed and
    spilled by :func:`survey_part`: what goes back to the client (small: no points).

    Attributes:
        index: the piece's place in the input (the parts are merged in this order).
        origin: (3,) the map frame its points were shifted into (m), or None: it had no chunk.
        chunks: its spilled chunk files (``DIR/.work/chunks/``), in input order.
        points: building points kept (inside ``bounds``).
        has_origins: whether every chunk had sensor origins.
        survey: its :class:`Survey`.
        read: input points read (before the building points were selected; the reader's count).
        seconds: wall time of the survey, s.
        cpu_seconds: its processor time (this process), s.
        pid: the process that ran it.
    """

    index: int
    origin: np.ndarray | None
    chunks: list[str]
    points: int
    has_origins: bool
    survey: Survey
    read: int = 0
    seconds: float = 0.0
    cpu_seconds: float = 0.0
    pid: int = 0


#: One chunk of building points for :func:`survey_part`: (N, 3) xyz (m, the chunk's map frame),
#: (N,) ids (negative: none) or None, (N, 3) sensor origins or None, (3,) the chunk's map origin.
Chunk = tuple[np.ndarray, 'np.ndarray | None', 'np.ndarray | None', np.ndarray]


def survey_part(folder: str | Path, index: int, chunks: Iterable[Chunk], cell: float,
                bounds: tuple[float, float, float, float] | None = None, origin: np.ndarray | None = None) -> Part:
    """Step 1 for one piece of the input, wherever it runs (a Dask worker, or the client): each
    chunk is limited to ``bounds`` (georeferenced x, y), shifted into the map frame ``origin``
    (None: the piece's first chunk's), spilled to ``DIR/.work/chunks/part_<index>_<j>.npz`` and
    measured (:class:`Survey`, clustering cell ``cell`` m)."""
    started, cpu = time.perf_counter(), time.process_time()
    work = Path(folder) / WORK / 'chunks'
    origin = None if origin is None else np.asarray(origin, dtype=np.float64)
    survey, paths, points, has_origins = Survey(), [], 0, True
    for xyz, building_id, sensor_origins, map_origin in chunks:
        map_origin = np.asarray(map_origin, dtype=np.float64)
        if origin is None:
            origin = map_origin.copy()
        xyz = np.asarray(xyz, dtype=np.float64)
        shift = map_origin - origin
        keep = in_bounds(xyz[:, :2] + map_origin[:2], bounds)
        if not keep.all():
            xyz = xyz[keep]
        if shift.any():
            xyz = xyz + shift
        n = len(xyz)
        ids = np.full(n, -1, np.int64) if building_id is None else np.asarray(building_id, np.int64)[keep]
        so = None
        if sensor_origins is None:
            has_origins = False
        else:
            so = np.asarray(sensor_origins, dtype=np.float64)[keep] + shift
        if not n:
            continue
        path = work / f'part_{index:06d}_{len(paths):06d}.npz'
        arrays = {'xyz': xyz, 'building_id': ids}
        if so is not None:
            arrays['sensor_origins'] = so
        np.savez(path, **arrays)
        paths.append(str(path))
        points += n
        survey.measure(xyz, ids, cell)
    return Part(index, origin, paths, points, has_origins, survey, seconds=time.perf_counter() - started,
                cpu_seconds=time.process_time() - cpu, pid=os.getpid())


def in_frame(part: Part, origin: np.ndarray | None) -> bool:
    """Whether ``part`` was surveyed in the map frame ``origin`` (None: any), or holds no points:
    else it must be surveyed again with that origin (inputs of several map origins)."""
    return part.origin is None or origin is None or not part.points or bool(np.array_equal(part.origin, origin))


@dataclass(frozen=True)
class RoutePlan:
    """Step 2's result, what every spill needs (picklable): labels and tiles of the points.

    Attributes:
        cell: the clustering cell side, m.
        cell_keys: (C,) sorted cell keys of the points without ids.
        cell_label: (C,) the building label of each.
        tiles: building label -> tile id (this run's and the existing map's buildings).
        origin: (3,) the map origin, m.
        has_origins: whether every chunk had sensor origins (else none are spilled).
        params_record: the map parameters' record (JSON bytes), the start of every fingerprint.
    """

    cell: float
    cell_keys: np.ndarray
    cell_label: np.ndarray
    tiles: dict[int, str]
    origin: tuple[float, float, float]
    has_origins: bool
    params_record: bytes

    def labels(self, ids: np.ndarray, xyz: np.ndarray) -> np.ndarray:
        """(N,) building labels of a chunk's points (given ids, else their cell's component)."""
        free = ids < 0
        if not free.any():
            return ids
        out = ids.copy()
        out[free] = self.cell_label[np.searchsorted(self.cell_keys, building_cells(xyz[free], self.cell))]
        return out


@dataclass
class Spilled:
    """What :func:`spill_part` gives back: per tile, in input order, its new part files, each
    with the sha256 digest of its rows (:func:`_rows`); and the time it took."""

    index: int
    parts: dict[str, list[tuple[str, str]]]
    seconds: float = 0.0
    cpu_seconds: float = 0.0
    pid: int = 0


def spill_part(folder: str | Path, index: int, chunks: list[str], plan: RoutePlan, first: int) -> Spilled:
    """Step 3 for one piece (``index``, :attr:`Part.index`): its chunk files (:attr:`Part.chunks`)
    are read back in order, labelled (``plan``), cut by tile, and each tile's points (xyz, label,
    sensor origins) written to ``DIR/.work/tiles/<id>/part_<k>.npz``, ``k`` counting the run's
    chunks from ``first``; the chunk files are then removed."""
    started, cpu = time.perf_counter(), time.process_time()
    work = Path(folder) / WORK / 'tiles'
    out: dict[str, list[tuple[str, str]]] = {}
    for k, path in enumerate(chunks, start=first):
        with np.load(path) as z:
            xyz, ids = z['xyz'], z['building_id']
            so = z['sensor_origins'] if plan.has_origins else None
        labels = plan.labels(ids, xyz)
        uniq, inverse = np.unique(labels, return_inverse=True)
        of_label = [plan.tiles[b] for b in uniq.tolist()]
        names = sorted(set(of_label))
        code = np.searchsorted(np.array(names), np.array(of_label))[inverse.reshape(-1)]
        order = np.argsort(code, kind='stable')  # by tile, input order within each
        cut = np.searchsorted(code[order], np.arange(len(names) + 1))
        for i, t in enumerate(names):
            sel = order[cut[i]:cut[i + 1]]
            (work / t).mkdir(parents=True, exist_ok=True)
            target = work / t / f'part_{k:06d}.npz'
            arrays = {'xyz': xyz[sel], 'building_id': labels[sel]}
            if so is not None:
                arrays['sensor_origins'] = so[sel]
            np.savez(target, **arrays)
            out.setdefault(t, []).append((str(target), hashlib.sha256(_rows(arrays)).hexdigest()))
        Path(path).unlink()
    return Spilled(index, out, time.perf_counter() - started, time.process_time() - cpu, os.getpid())


@dataclass
class Router:
    """Routes building points to tiles by area, spilling them to the work folder
    (see the module's description). One router per build.

    The client surveys and spills in this process (:meth:`add`, then :meth:`spill`), or merges
    parts surveyed elsewhere (:func:`survey_part` on workers, :meth:`merge` in input order),
    plans (:meth:`plan`) and turns the parts spilled elsewhere (:func:`spill_part`, with
    :meth:`spill_firsts` and :attr:`route_plan`) into tasks (:meth:`tasks`): the same points,
    labels, part files and fingerprints either way.

    Args:
        folder: the tiled map's folder (created by the caller).
        params: the map's parameters (``extraction.building_cell`` clusters points without ids).
        side: the tile side, m.
        bounds: (min_x, min_y, max_x, max_y) of the area to build, georeferenced m, or None.
        existing: the folder's manifest (a second drive, or a resumed build), or None.
    """

    folder: Path
    params: MapParams
    side: float
    bounds: tuple[float, float, float, float] | None = None
    existing: Manifest | None = None
    map_origin: np.ndarray | None = None
    parts: list[Part] = field(default_factory=list)
    points: int = 0
    has_origins: bool = True
    survey: Survey = field(default_factory=Survey)
    route_plan: RoutePlan | None = None
    _plan: dict | None = None

    def __post_init__(self) -> None:
        self.folder = Path(self.folder)
        self.work = self.folder / WORK
        shutil.rmtree(self.work, ignore_errors=True)  # a killed build's spill: routing starts again
        (self.work / 'chunks').mkdir(parents=True)
        if self.existing is not None:
            self.map_origin = np.asarray(self.existing.map_origin, dtype=np.float64)

    @property
    def cell(self) -> float:
        """The clustering cell side of points without ids, m."""
        return self.params.extraction.building_cell

    # -- 1. survey -----------------------------------------------------------------------
    def add(self, xyz: np.ndarray, building_id: np.ndarray | None, sensor_origins: np.ndarray | None,
            map_origin: np.ndarray) -> int:
        """Take one chunk of building points (in input order): (N, 3) xyz (metres, the chunk's
        map frame), (N,) ids (negative: none) or None, (N, 3) sensor origins or None, (3,) the
        chunk's map origin. Returns the points kept (inside ``bounds``)."""
        part = survey_part(self.folder, len(self.parts), [(xyz, building_id, sensor_origins, map_origin)], self.cell,
                           self.bounds, self.map_origin)
        self.merge(part)
        return part.points

    def fits(self, part: Part) -> bool:
        """Whether ``part`` was surveyed in this router's map frame (:func:`in_frame`)."""
        return in_frame(part, self.map_origin)

    def merge(self, part: Part) -> None:
        """Take the next piece of the input surveyed by :func:`survey_part` (in input order).

        Raises:
            ValueError: surveyed in another map frame (see :meth:`fits`).
        """
        if not self.fits(part):
            raise ValueError(f'part {part.index} was surveyed in map frame {part.origin}, not {self.map_origin}')
        if self.map_origin is None and part.origin is not None:
            self.map_origin = np.asarray(part.origin, dtype=np.float64).copy()
        self.parts.append(part)
        self.points += part.points
        self.has_origins &= part.has_origins
        self.survey.merge(part.survey)

    # -- 2. plan -------------------------------------------------------------------------
    def plan(self) -> dict[int, str]:
        """Label the points without ids and give every building its tile; returns
        building label -> tile id (the new ones and the existing map's). Sets
        :attr:`route_plan`."""
        grid = TileGrid(self.side)
        cells = self.survey.cell_list()
        known = [] if self.existing is None else list(self.existing.building_tiles)
        base = self._base_label(cells, max([*self.survey.box, *known, -1]) + 1)
        boxes = dict(self.survey.box)
        cell_label = np.empty(0, np.int64)
        if len(cells):
            comp = _grid_components(np.stack([cells >> 32, cells & 0xFFFFFFFF], axis=1))
            cbox = _merge_boxes(self.survey.cell_box, comp, int(comp.max()) + 1)
            boxes.update({base + c: cbox[c] for c in range(len(cbox))})
            cell_label = base + comp[self.survey.cell_order]
        placed = {} if self.existing is None else dict(self.existing.building_tiles)
        labels = sorted(boxes)
        if labels:
            centres = np.array([[(boxes[b][0] + boxes[b][2]) / 2, (boxes[b][1] + boxes[b][3]) / 2] for b in labels])
            index = grid.index(centres)
            for b, (ix, iy) in zip(labels, index.tolist()):
                if b not in placed:
                    placed[b] = tile_id(ix, iy)
            self._index = {tile_id(ix, iy): (ix, iy) for ix, iy in index.tolist()}
        else:
            self._index = {}
        if self.existing is not None:
            self._index.update({t: tuple(r.index) for t, r in self.existing.tiles.items()})
        self._plan = placed
        origin = (0.0, 0.0, 0.0) if self.map_origin is None else tuple(float(v) for v in self.map_origin)
        self.route_plan = RoutePlan(self.cell, self.survey.cell_keys, cell_label, placed, origin, self.has_origins,
                                    json.dumps(map_params_record(self.params), sort_keys=True).encode())
        return placed

    def _base_label(self, cells: np.ndarray, base: int) -> int:
        """The first label of the clustered buildings: ``base`` (past every given id and every
        building of the existing map), unless this very input was planned before in this folder
        (a resumed build, whose finished tiles have added this run's own labels to the map): then
        the base it had, so that the points get the same labels and the finished tiles are skipped.
        Kept in ``DIR/RUN`` until the build completes."""
        h = hashlib.sha256(cells.tobytes())
        for b in sorted(self.survey.box):
            h.update(np.r_[float(b), self.survey.box[b]].tobytes())
        survey = h.hexdigest()
        path = self.folder / RUN
        try:
            saved = json.loads(path.read_text())
            if saved.get('survey') == survey:
                return int(saved['base'])
        except (OSError, ValueError, KeyError, TypeError):
            pass
        path.write_text(json.dumps({'survey': survey, 'base': base}))
        return base

    def labels(self, ids: np.ndarray, xyz: np.ndarray) -> np.ndarray:
        """(N,) building labels of a chunk's points (given ids, else their cell's component)."""
        if self.route_plan is None:
            self.plan()
        return self.route_plan.labels(ids, xyz)

    # -- 3. spill ------------------------------------------------------------------------
    def spill_firsts(self) -> list[int]:
        """Per merged part, the run-wide number of its first chunk (``first`` of :func:`spill_part`)."""
        return np.r_[0, np.cumsum([len(p.chunks) for p in self.parts])][:-1].astype(int).tolist()

    def spill(self, calibrate: float | None = None) -> list[TileTask]:
        """Spill every merged part in this process (:func:`spill_part`, in input order) and
        return the tasks (:meth:`tasks`)."""
        if self.route_plan is None:
            self.plan()
        return self.tasks([spill_part(self.folder, part.index, part.chunks, self.route_plan, first)
                           for part, first in zip(self.parts, self.spill_firsts())], calibrate)

    def tasks(self, spilled: Iterable[Spilled], calibrate: float | None = None) -> list[TileTask]:
        """The tasks, one per tile that received points, in tile id order, from every part's
        :func:`spill_part` (any order: they are put back in input order). A tile's fingerprint
        for this run (see :attr:`TileTask.inputs`) is the sha256 of the map parameters' record,
        the map origin and the digests of its part files in input order."""
        if self.route_plan is None:
            self.plan()
        plan = self.route_plan
        parts: dict[str, list[tuple[str, str]]] = {}
        for s in sorted(spilled, key=lambda s: s.index):
            for t, files in s.parts.items():
                parts.setdefault(t, []).extend(files)
        grid = TileGrid(self.side)
        tasks = []
        for t in sorted(parts):
            h = hashlib.sha256(plan.params_record + np.asarray(plan.origin, dtype=np.float64).tobytes())
            for _, digest in parts[t]:
                h.update(bytes.fromhex(digest))
            run = h.hexdigest()
            old = None if self.existing is None else self.existing.tiles.get(t)
            inputs = run if old is None else old.inputs + RUNS + run
            ix, iy = self._index[t]
            tasks.append(TileTask(str(self.folder), t, (ix, iy), grid.bounds(ix, iy), tuple(p for p, _ in parts[t]),
                                  self.params, plan.origin, inputs, None if old is None else old.file, calibrate))
        return tasks

    def cleanup(self) -> None:
        """Remove the work folder and the run's record (after a complete build)."""
        shutil.rmtree(self.work, ignore_errors=True)
        (self.folder / RUN).unlink(missing_ok=True)


def run_fingerprint(task: TileTask) -> str:
    """This run's fingerprint of the tile's routed points (the last of :attr:`TileTask.inputs`)."""
    return task.inputs.rsplit(RUNS, 1)[-1]


def done_already(folder: str | Path, manifest: Manifest | None, task: TileTask) -> bool:
    """Whether the folder's manifest lists the tile built from this run's points already (a
    resumed build) with an intact file: the task is skipped."""
    if manifest is None or task.tile_id not in manifest.tiles:
        return False
    record = manifest.tiles[task.tile_id]
    return run_fingerprint(task) in record.inputs.split(RUNS) and intact(folder, record)


def check_params(manifest: Manifest, params: MapParams, side: float) -> None:
    """Refuse to add to a tiled map built with other parameters or another tile side.

    Raises:
        InputError: they differ.
    """
    if json.dumps(manifest.params, sort_keys=True) != json.dumps(map_params_record(params), sort_keys=True):
        raise InputError('the tiled map was built with other map parameters than the configuration\'s: build into '
                         'a new folder, or use the configuration it was built with')
    if float(manifest.side) != float(side):
        raise InputError(f'the tiled map has tiles of {manifest.side:g} m, not {side:g} m: drop --side or build into '
                         'a new folder')


def _rows(arrays: dict[str, np.ndarray]) -> bytes:
    """The points' bytes row by row (x, y, z, label, sensor origin of each point in turn): what a
    part file's digest hashes (its content, not the ``.npz`` container's bytes)."""
    fields = [(name, a.dtype, a.shape[1:]) for name, a in arrays.items()]
    rows = np.empty(len(arrays['xyz']), dtype=np.dtype(fields))
    for name, a in arrays.items():
        rows[name] = a
    return rows.tobytes()


def _boxes(xy: np.ndarray, group: np.ndarray, n: int) -> np.ndarray:
    """(n, 4) min x, min y, max x, max y of the (N, 2) points of each of n groups."""
    out = np.empty((n, 4))
    out[:, :2] = np.inf
    out[:, 2:] = -np.inf
    for d in range(2):
        np.minimum.at(out[:, d], group, xy[:, d])
        np.maximum.at(out[:, 2 + d], group, xy[:, d])
    return out


def _merge_boxes(box: np.ndarray, group: np.ndarray, n: int) -> np.ndarray:
    """(n, 4) union of the (M, 4) boxes of each of n groups."""
    out = np.empty((n, 4))
    out[:, :2] = np.inf
    out[:, 2:] = -np.inf
    for d in range(2):
        np.minimum.at(out[:, d], group, box[:, d])
        np.maximum.at(out[:, 2 + d], group, box[:, 2 + d])
    return out
