"""Reading a tiled map: merging tile maps, opening a map file or a tiled map, and
:class:`TiledMap`, which loads tiles on demand near the asked points.

**Queries** (:meth:`TiledMap.query`) answer as
:meth:`~uncertain_facade_map.mapping.facade_map.FacadeMap.query` does on one map holding
every building. A tile's map answers only near what it holds: its records' ``extent`` covers
its stored points and its façades' slabs (raster extent x depth band), so the raster reading
of a point involves only the façades whose slab holds it; the local reading (``query.surface``
'local') reads the ``K + 1`` stored points nearest to a point whose nearest lies within
``query.local_radius``, which lie within the radius and a margin (:data:`LOCAL_MARGIN`, for
the farther neighbours). The points of a batch are answered by **views** (:mod:`.views`): the
squares of ``tiles.view_tiles`` x ``view_tiles`` tiles of the grid that hold them, each with
the façades and stored points within that reach of its square, built once from the loaded
tiles and kept in the cache (a vehicle's scans fall in one or two squares: one call of the
compiled kernels each). Each tile's local reading (its stored points' labels, the outliers
that stand alone) is prepared once and kept with the tile.
Map-wide quantities are the manifest's: the learnt occupancy (``occupancy``), the
scan-to-scan variance (``registration``) and the local reading's leave-one-out calibration
(``local_calibration``, when the manifest has it for the query's settings; else learnt once on
the tile with the most stored points, for every view).

**Façade ids** of a tiled map: the tiles in the order of their ids (sorted), each tile's
façades in its file's order; :meth:`TiledMap.merged` numbers its façades the same way
when it holds every tile.

:func:`merge_maps` joins maps of disjoint buildings into one in-memory
:class:`~uncertain_facade_map.mapping.facade_map.FacadeMap` (façades renumbered in order);
:func:`subset_map` is its inverse (the buildings asked, façades renumbered), what cuts a
one-file map into tiles.
"""

from __future__ import annotations

import os
import threading
import time
from collections import OrderedDict
from dataclasses import replace
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np

from ..datatypes import array_bytes
from ..errors import InputError
from ..mapping.calibration import registration_variance
from ..mapping.facade_map import FacadeMap, query_settings, reading_key
from ..params import MapParams, QueryConfig, TilesConfig, map_params_from_record
from ..pipeline.step7_local_surface import LocalSurface, ReadingCalibration, noise_floor_of
from ..pipeline.step7_queries import PointQuery, query_map
from ..pipeline.step8_occupancy import PLSC
from .grid import TileGrid
from .manifest import Manifest, TileRecord, manifest_path, read_manifest, verify_tile
from .views import TilePart, View, make_view, stored_points, tile_part

__all__ = ['merge_maps', 'subset_map', 'open_map', 'TiledMap', 'reading_id', 'LOCAL_MARGIN']

#: Metres beyond ``query.local_radius`` that a tile's extent is grown by to hold a point whose
#: local reading may read its stored points: the ``K + 1`` nearest stored points of a point
#: lie within its nearest's distance plus the spread of those neighbours (a few decimetres on
#: a scanned wall; where a tile's points are sparser than that, a neighbour farther away may be
#: missed).
LOCAL_MARGIN = 2.0

#: Bytes in a MB (``tiles.cache_mb``).
MB = 1_000_000


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
    occupancy, sums, reg_var = joint_map_wide(maps)
    return FacadeMap(first.params, first.map_origin.copy(), facades, points, origins, normals, pool,
                     pending=pending, thinned=thinned, occupancy_=occupancy,
                     occupancy_stored_=int(sum(m.occupancy_stored_ for m in maps)),
                     registration_sums_=sums, registration_var_=reg_var)


def joint_map_wide(maps: Sequence[FacadeMap]) -> tuple[PLSC, np.ndarray, float]:
    """The map-wide quantities of maps joined (:func:`merge_maps`): the learnt occupancy (the
    maps' own when they agree, else that of the map with the most points stored at its
    calibration), the scan-to-scan sums (added) and variance (the maps' own when they agree,
    else learnt again from the sums, m^2)."""
    first = maps[0]
    if all(m.occupancy_ == first.occupancy_ for m in maps):
        occupancy = first.occupancy_
    else:
        occupancy = max(maps, key=lambda m: m.occupancy_stored_).occupancy_
    sums = np.sum([m.registration_sums_ for m in maps], axis=0)
    if all(m.registration_var_ == first.registration_var_ for m in maps):
        reg_var = first.registration_var_
    else:
        reg_var = registration_variance(sums, first.params.update.registration_max_std)
    return occupancy, sums, reg_var


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



def reading_id(config: QueryConfig) -> str | None:
    """The manifest's key of the local reading's calibration for ``config`` (its
    neighbours, radius and inner radius); None for the raster reading (no calibration)."""
    if config.surface != 'local':
        return None
    return f'local:{config.local_neighbours}:{config.local_radius!r}:{config.local_inner!r}'


def local_calibration(fmap: FacadeMap, configs: Iterable[QueryConfig] = (QueryConfig(),)
                      ) -> dict[str, ReadingCalibration]:
    """The local reading's map-wide calibration (``LocalSurface.calibration()``) of ``fmap`` for
    each of ``configs`` (local readings only), keyed by :func:`reading_id`, for a manifest."""
    out = {}
    for config in configs:
        key = reading_id(config)
        if key is not None:
            out[key] = fmap.local_surface(config).calibration()
    return out


def _install_local_surface(fmap: FacadeMap, config: QueryConfig, calibration: ReadingCalibration) -> None:
    """Give ``fmap`` the local surface of ``config`` with the map-wide ``calibration`` (not
    learnt on ``fmap``'s own points, which are a part of the map): put in the cache that
    :meth:`FacadeMap.local_surface` reads, for the map's present state."""
    surface = LocalSurface.of(fmap.facades, fmap.points, config.local_neighbours, config.local_radius,
                              config.local_inner, calibrate=False).calibrate_with(calibration)
    state = (tuple(fmap.facades), tuple(fmap.points.items()))
    cache = fmap.__dict__.get('_local_cache')
    if cache is None or len(cache[0][0]) != len(state[0]) or any(a is not b for a, b in zip(cache[0][0], state[0])):
        cache = (state, {})
        fmap.__dict__['_local_cache'] = cache
    cache[1][reading_key(config)] = surface


class TiledMap:
    """A tiled map read on demand: the manifest at opening, the tiles when queries need them,
    through an LRU bounded in bytes (the arrays a loaded tile's map holds with its local
    reading's stored points, and what the views add: packed rasters, the stored points within
    their square and their grid). Thread-safe.

    Attributes:
        folder: the map's folder.
        manifest_: the manifest (read once, at opening).
        params: the map's parameters.
        map_origin: (3,) georeference of the map frame, metres.
        grid: the tile grid.
        cache_mb: the cache bound, MB (at least one tile is kept, whatever its size).
        view_tiles: the side of a view, in tiles (``tiles.view_tiles``, :mod:`.views`).
    """

    def __init__(self, path: str | os.PathLike, cache_mb: float = TilesConfig.cache_mb,
                 view_tiles: int = TilesConfig.view_tiles) -> None:
        self.manifest_: Manifest = read_manifest(path)
        target = manifest_path(path)
        self.folder = target.parent
        try:
            self.params: MapParams = map_params_from_record(self.manifest_.params)
        except InputError as exc:
            raise InputError(f'{target}: {exc}') from exc
        if not (isinstance(cache_mb, (int, float)) and cache_mb > 0):
            raise InputError(f'cache_mb must be a number of MB > 0, got {cache_mb!r}')
        self.cache_mb = float(cache_mb)
        if isinstance(view_tiles, bool) or not isinstance(view_tiles, (int, np.integer)) or view_tiles < 1:
            raise InputError(f'view_tiles must be a whole number of tiles >= 1, got {view_tiles!r}')
        self.view_tiles = int(view_tiles)
        self.map_origin = np.asarray(self.manifest_.map_origin, dtype=np.float64)
        self.grid = TileGrid(self.manifest_.side)
        occupancy = self.manifest_.occupancy
        try:
            self._occupancy = None if occupancy is None else PLSC(**occupancy)
        except (TypeError, InputError) as exc:
            raise InputError(f'{target}: damaged manifest (occupancy: {exc})') from exc
        reg = self.manifest_.registration
        self._registration = None if reg is None else (float(reg['var']), np.asarray(reg['sums'], np.float64))
        self._ids = sorted(self.manifest_.tiles)
        self._records = [self.manifest_.tiles[t] for t in self._ids]
        self._position = {t: i for i, t in enumerate(self._ids)}
        counts = np.array([r.facades for r in self._records], dtype=np.int64)
        self._offset = np.r_[0, np.cumsum(counts)[:-1]] if len(counts) else np.empty(0, np.int64)
        self._extent = np.array([r.extent for r in self._records], dtype=np.float64).reshape(-1, 6)
        self._bounds = np.array([r.bounds for r in self._records], dtype=np.float64).reshape(-1, 4)
        self._lock = threading.RLock()
        self._loading: dict[str, threading.Lock] = {}
        self._tiles: OrderedDict[str, tuple[FacadeMap, int]] = OrderedDict()
        self._parts: dict[tuple[str, tuple], tuple[TilePart, int]] = {}  # (tile, reading) -> part, bytes
        self._views: OrderedDict[tuple, View] = OrderedDict()
        self._calibration: dict[str, ReadingCalibration] = dict(self.manifest_.local_calibration)
        self._pins: dict[str, int] = {}
        self._stats = {'hits': 0, 'misses': 0, 'evictions': 0, 'load_seconds': 0.0, 'views_built': 0,
                       'view_seconds': 0.0}

    # -- tiles ---------------------------------------------------------------------------

    @property
    def records(self) -> list[TileRecord]:
        """The tiles' records, in id order."""
        return list(self._records)

    def tiles_near(self, xy: np.ndarray, radius: float) -> list[TileRecord]:
        """The tiles whose square lies within ``radius`` (metres) of the map-frame point
        ``xy`` ((2,) or more: x, y), nearest first."""
        xy = np.asarray(xy, dtype=np.float64).reshape(-1)[:2]
        if not np.isfinite(xy).all():
            raise InputError('tiles_near needs a finite x, y')
        if not len(self._records):
            return []
        dx = np.maximum(np.maximum(self._bounds[:, 0] - xy[0], xy[0] - self._bounds[:, 2]), 0.0)
        dy = np.maximum(np.maximum(self._bounds[:, 1] - xy[1], xy[1] - self._bounds[:, 3]), 0.0)
        d = np.hypot(dx, dy)
        near = np.flatnonzero(d <= radius)
        return [self._records[i] for i in near[np.argsort(d[near], kind='stable')]]

    def _load(self, tile_id: str) -> FacadeMap:
        """A tile's map from its file (hash checked), the manifest's map-wide occupancy set."""
        from ..io.map_file import load_map

        rec = self.manifest_.tiles[tile_id]
        fmap = load_map(verify_tile(self.folder, rec))
        if fmap.params != self.params:
            raise InputError(f'{self.folder / rec.file}: tile {tile_id} was built with other parameters than the '
                             f'manifest lists; rebuild it')
        self._map_wide(fmap)
        return fmap

    def _map_wide(self, fmap: FacadeMap) -> None:
        """Set the manifest's map-wide occupancy and scan-to-scan variance on a tile's or a merged map."""
        if self._occupancy is not None:
            fmap.occupancy_ = self._occupancy
        if self._registration is not None:
            fmap.registration_var_, fmap.registration_sums_ = self._registration[0], self._registration[1].copy()

    def _hit(self, tile_id: str) -> FacadeMap | None:
        """The tile's map if it is loaded (counted as a hit, made the most recently used), else
        None; called with ``_lock`` held."""
        hit = self._tiles.get(tile_id)
        if hit is None:
            return None
        self._tiles.move_to_end(tile_id)
        self._stats['hits'] += 1
        return hit[0]

    def tile(self, tile_id: str) -> FacadeMap:
        """A tile's map, loaded through the cache (do not modify it).

        Raises:
            InputError: an unknown tile, a missing or damaged file.
        """
        if tile_id not in self.manifest_.tiles:
            raise InputError(f'the tiled map {self.folder} has no tile {tile_id!r}')
        with self._lock:
            hit = self._hit(tile_id)
            if hit is not None:
                return hit
            loading = self._loading.setdefault(tile_id, threading.Lock())
        with loading:  # one load per tile at a time; other tiles load meanwhile
            with self._lock:
                hit = self._hit(tile_id)  # loaded by another thread while this one waited
                if hit is not None:
                    return hit
            start = time.perf_counter()
            fmap = self._load(tile_id)
            size = array_bytes(fmap)
            with self._lock:
                self._stats['misses'] += 1
                self._stats['load_seconds'] += time.perf_counter() - start
                self._tiles[tile_id] = (fmap, size)
                self._trim(keep=tile_id)
        return fmap

    def preload(self, xy: np.ndarray, radius: float, config: QueryConfig | None = None) -> list[str]:
        """Load the tiles within ``radius`` of ``xy`` (nearest first, as many as the cache
        holds); returns the ids of those loaded now or already (what a node following its pose
        calls). With ``config`` (the queries' settings), also prepare those tiles' local reading
        (:func:`~.views.tile_part`) and build the view holding ``xy`` (:mod:`.views`) when its
        tiles are among those, so that queries near the pose find them ready."""
        out = []
        budget = self.cache_mb * MB
        used = 0
        for rec in self.tiles_near(xy, radius):
            fmap = self.tile(rec.id)
            if config is not None:
                self._part(rec.id, fmap, config)
            with self._lock:
                entry = self._tiles.get(rec.id)
                used += entry[1] if entry is not None else array_bytes(fmap)
                part = self._parts.get((rec.id, reading_key(config))) if config is not None else None
                used += part[1] if part is not None else 0
            out.append(rec.id)
            if used >= budget:
                break
        if config is not None and out:
            here = np.asarray(xy, dtype=np.float64).reshape(1, -1)[:, :2]
            key = self._split(np.c_[here, np.zeros(1)], config)[0][0]
            if set(self._view_tiles(key, config)) <= set(out):  # not when the cache cannot hold its tiles too
                self._view(key, config)
        return out

    def _bytes(self) -> int:
        return (sum(s for _, s in self._tiles.values()) + sum(s for _, s in self._parts.values())
                + sum(v.nbytes for v in self._views.values()))

    def _trim(self, keep: str | None = None) -> None:
        """Evict until the cache is within its bound: views first (least recently used first;
        built again from loaded tiles when needed), then tiles (least recently used first, with
        their local reading's points and the views holding them); the most recently used view,
        the tiles in use by a query (pinned), ``keep`` and the last tile stay. Call under the lock."""
        budget = self.cache_mb * MB
        while self._bytes() > budget:
            if len(self._views) > 1:
                self._views.popitem(last=False)
                continue
            candidates = [t for t in self._tiles if t != keep and not self._pins.get(t)]
            if len(self._tiles) <= 1 or not candidates:
                return
            self._evict(candidates[0])

    def _evict(self, tile_id: str) -> None:
        self._tiles.pop(tile_id, None)
        for key in [k for k in self._parts if k[0] == tile_id]:
            del self._parts[key]
        for key in [k for k, v in self._views.items() if tile_id in v.tiles]:
            del self._views[key]
        self._stats['evictions'] += 1

    def cache_info(self) -> dict:
        """What the cache holds: ``tiles`` (ids loaded, least recently used first), ``views``
        (keys ``(i0, j0, reading)`` of the views built, :mod:`.views`), ``bytes`` (tiles, their
        local reading's points and views), ``tile_bytes``, ``limit_bytes``, ``hits``,
        ``misses`` and ``evictions`` of tiles, ``load_seconds``, ``views_built`` and
        ``view_seconds`` (building them)."""
        with self._lock:
            return {'tiles': list(self._tiles), 'views': list(self._views), 'bytes': self._bytes(),
                    'tile_bytes': sum(s for _, s in self._tiles.values()), 'limit_bytes': int(self.cache_mb * MB),
                    **self._stats}

    # -- merged maps -----------------------------------------------------------------------

    def _merge(self, maps: Sequence[FacadeMap]) -> FacadeMap:
        fmap = merge_maps(maps) if maps else FacadeMap(self.params, self.map_origin.copy())
        self._map_wide(fmap)
        return fmap

    def merged(self, tile_ids: Iterable[str] | None = None,
               bounds: tuple[float, float, float, float] | None = None) -> FacadeMap:
        """One in-memory map of some tiles (for plots, evaluation, exports): ``tile_ids``, or
        those whose extent meets ``bounds`` (``min_x, min_y, max_x, max_y``, metres, map
        frame), or every tile (neither given; its façade ids are then the tiled map's).
        Tiles not in the cache are read without entering it (a map of everything would
        evict all the rest).

        Raises:
            InputError: an unknown tile id, bad bounds.
        """
        if tile_ids is not None:
            ids = sorted(set(tile_ids))
            unknown = [t for t in ids if t not in self.manifest_.tiles]
            if unknown:
                raise InputError(f'the tiled map {self.folder} has no tile {unknown[0]!r}')
        else:
            ids = list(self._ids)
        if bounds is not None:
            b = np.asarray(bounds, dtype=np.float64).reshape(-1)
            if b.shape != (4,) or not np.isfinite(b).all() or b[0] > b[2] or b[1] > b[3]:
                raise InputError(f'bounds must be MIN_X,MIN_Y,MAX_X,MAX_Y with min <= max, got {list(bounds)}')
            wanted = set(self._meeting(b))
            ids = [t for t in ids if t in wanted]
        maps = []
        for t in ids:
            with self._lock:
                hit = self._tiles.get(t)
            maps.append(hit[0] if hit is not None else self._load(t))
        fmap = self._merge(maps)
        config = QueryConfig()
        calibration = self.manifest_.local_calibration.get(reading_id(config) or '')
        if calibration is not None and maps:
            _install_local_surface(fmap, config, calibration)
        return fmap

    # -- queries -----------------------------------------------------------------------------

    def reach(self, config: QueryConfig) -> float:
        """Metres a tile's extent is grown by to hold the points its tiles may answer for
        with ``config`` (0 for the raster reading: the extent holds the façades' slabs)."""
        return config.local_radius + LOCAL_MARGIN if config.surface == 'local' else 0.0

    def _part(self, tile_id: str, fmap: FacadeMap, config: QueryConfig) -> TilePart:
        """The tile's local reading's stored points (:func:`~.views.tile_part`), cached with the tile."""
        key = (tile_id, reading_key(config))
        with self._lock:
            hit = self._parts.get(key)
        if hit is not None:
            return hit[0]
        part = tile_part(fmap, config)
        with self._lock:
            if tile_id in self._tiles:  # kept with its tile (not when the tile was evicted meanwhile)
                hit = self._parts.setdefault(key, (part, array_bytes(part)))
                return hit[0]
        return part

    def local_calibration(self, config: QueryConfig) -> ReadingCalibration:
        """The local reading's map-wide calibration for ``config``: the manifest's
        (``local_calibration``), else learnt once (leave-one-out,
        :meth:`~uncertain_facade_map.pipeline.step7_local_surface.LocalSurface.calibrate`) on the
        tile with the most stored points, for every view alike."""
        key = reading_id(config) or ''
        with self._lock:
            hit = self._calibration.get(key)
        if hit is not None:
            return hit
        if not self._records:
            return ReadingCalibration()
        largest = max(self._records, key=lambda r: (r.points, r.id))
        fmap = self.tile(largest.id)
        part = self._part(largest.id, fmap, config)
        normals = np.array([f.frame.normal for f in fmap.facades]).reshape(-1, 3)
        surface = LocalSurface(stored_points(fmap)[0][part.index], part.facade, normals, config.local_neighbours,
                               config.local_radius, config.local_inner, noise_floor=noise_floor_of(fmap.facades))
        surface.calibrate()
        value = surface.calibration()
        with self._lock:
            return self._calibration.setdefault(key, value)

    def _square(self, i0: int, j0: int) -> tuple[float, float, float, float]:
        lo = self.grid.bounds(i0, j0)
        hi = self.grid.bounds(i0 + self.view_tiles - 1, j0 + self.view_tiles - 1)
        return lo[0], lo[1], hi[2], hi[3]

    def _split(self, xyz: np.ndarray, config: QueryConfig) -> list[tuple[tuple, np.ndarray]]:
        """The views that answer (N, 3) points, and which points each: the squares of
        ``view_tiles`` x ``view_tiles`` tiles of the grid that hold them."""
        block = np.floor_divide(self.grid.index(xyz[:, :2]), self.view_tiles)
        reading = reading_key(config)
        k = self.view_tiles
        code = (block[:, 0] << 32) + (block[:, 1] & 0xFFFFFFFF)  # one int64 per square
        if (code == code[0]).all():
            return [((int(block[0, 0]) * k, int(block[0, 1]) * k, reading), np.arange(len(xyz)))]
        order = np.argsort(code, kind='stable')
        cuts = np.flatnonzero(np.diff(code[order])) + 1
        return [((int(block[m[0], 0]) * k, int(block[m[0], 1]) * k, reading), m) for m in np.split(order, cuts)]

    def _view_tiles(self, key: tuple, config: QueryConfig) -> list[str]:
        """The tiles a view reads: those whose extent meets its square grown by the reach."""
        x0, y0, x1, y1 = self._square(key[0], key[1])
        pad = self.reach(config)
        return self._meeting((x0 - pad, y0 - pad, x1 + pad, y1 + pad))

    def _meeting(self, box: Sequence[float]) -> list[str]:
        """The ids (sorted) of the tiles whose extent meets ``box`` (min_x, min_y, max_x, max_y;
        metres, map frame)."""
        e = self._extent
        meets = (e[:, 0] <= box[2]) & (e[:, 3] >= box[0]) & (e[:, 1] <= box[3]) & (e[:, 4] >= box[1])
        return [self._ids[i] for i in np.flatnonzero(meets)]

    def _view(self, key: tuple, config: QueryConfig) -> View:
        """The view of ``key``, from the cache or built (its tiles loaded)."""
        with self._lock:
            hit = self._views.get(key)
            if hit is not None:
                self._views.move_to_end(key)
                for t in hit.tiles:  # its tiles are in use too (evicting one drops the view)
                    if t in self._tiles:
                        self._tiles.move_to_end(t)
                return hit
        start = time.perf_counter()
        square = self._square(key[0], key[1])
        pad = self.reach(config)
        tiles = self._view_tiles(key, config)
        with self._lock:
            for t in tiles:
                self._pins[t] = self._pins.get(t, 0) + 1
        try:
            maps = [self.tile(t) for t in tiles]
            parts = [self._part(t, m, config) for t, m in zip(tiles, maps)]
            calibration = (self.local_calibration(config) if config.surface == 'local' and maps
                           else ReadingCalibration())
            occupancy, _, reg_var = joint_map_wide(maps) if maps else (FacadeMap(self.params).occupancy_, None, 0.0)
            if self._occupancy is not None:
                occupancy = self._occupancy
            if self._registration is not None:
                reg_var = self._registration[0]
            offsets = [int(self._offset[self._position[t]]) for t in tiles]
            view = make_view(key, tiles, maps, parts, offsets, square, pad, config, calibration, occupancy, reg_var)
        finally:
            with self._lock:
                for t in tiles:
                    self._pins[t] -= 1
                    if not self._pins[t]:
                        del self._pins[t]
        with self._lock:
            self._stats['views_built'] += 1
            self._stats['view_seconds'] += time.perf_counter() - start
            view = self._views.setdefault(key, view)
            self._views.move_to_end(key)
            self._trim()
        return view

    def query(self, xyz: np.ndarray, config: QueryConfig | None = None, resolution: float | None = None,
              event: str | None = None) -> PointQuery:
        """Answer the 3D point query for (N, 3) points (metres, map frame) as
        :meth:`FacadeMap.query` on one map of every building would (see the module's text);
        façade ids are the tiled map's (:meth:`merged`'s of every tile). Loads the tiles the
        points need.

        Raises:
            InputError: bad points, resolution or event; a missing or damaged tile.
        """
        config, resolution = query_settings(config, resolution, event)
        xyz = np.asarray(xyz, dtype=np.float64)
        if xyz.ndim != 2 or xyz.shape[1] != 3 or not np.isfinite(xyz).all() or not len(xyz):
            return self._merge([]).query(xyz, config, resolution)  # its own checks and messages
        n = len(xyz)
        out = {'facade': np.full(n, -1, np.int32), 'mean_depth': np.empty(n), 'variance': np.empty(n),
               'noise_variance': np.empty(n), 'signed_distance': np.empty(n), 'p_occupied': np.empty(n),
               'normal': np.empty((n, 3))}
        ex = self.params.extraction
        for key, members in self._split(xyz, config):
            view = self._view(key, config)
            answer = query_map(view.facades, {}, xyz[members], resolution, ex.band_back, ex.band_front, view.occupancy,
                               config, view.local, view.registration_var, view.rasters)
            fid = answer.facade
            ids = view.global_ids
            out['facade'][members] = np.where(fid >= 0, ids[np.maximum(fid, 0)] if len(ids) else -1, -1)
            for k in ('mean_depth', 'variance', 'noise_variance', 'signed_distance', 'p_occupied', 'normal'):
                out[k][members] = getattr(answer, k)
        return PointQuery(**out)

    def __repr__(self) -> str:
        return f'TiledMap({str(self.folder)!r}, {len(self._ids)} tiles, side {self.manifest_.side} m)'
