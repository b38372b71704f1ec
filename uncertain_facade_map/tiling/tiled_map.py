"""Reading a tiled map: merging tile maps, opening a map file or a tiled map, and
:class:`TiledMap`, which loads tiles on demand near the asked points.

**Queries** (:meth:`TiledMap.query`) answer as
:meth:`~uncertain_facade_map.mapping.facade_map.FacadeMap.query` does on one map holding
every building. A tile's map answers only near what it holds: its records' ``extent`` covers
its stored points and its façades' slabs (raster extent x depth band), so the raster reading
of a point involves only tiles whose extent holds the point; the local reading (``query.surface``
'local') reads the ``K + 1`` stored points nearest to a point whose nearest lies within
``query.local_radius``, so it involves the tiles whose extent, grown by the radius and a
margin (:data:`LOCAL_MARGIN`, for the farther neighbours), holds it. The candidate tiles of
a point are those; the points are grouped by their candidate set and each group is answered
by the merged map of its tiles (cached with the tiles; the groups recur as a vehicle moves).
A batch whose points need few tiles in all (``tiles.union_tiles``) is answered by one merged
map of them instead, the same answers (a point's answer involves its candidate tiles only)
in one call of the compiled kernels: each call of the parallel kernels waits for both
cores, which costs about 10 ms when other processes keep them busy (the street drive's
0.1 s scans, load 8 on 2 cores: 44,000 points/s by candidate sets, 104,000 by one merged
map, 100,000 for the one-file map).
Map-wide quantities are the manifest's: the learnt occupancy (``occupancy``), the
scan-to-scan variance (``registration``) and the local reading's leave-one-out calibration (``local_calibration``, when the manifest has it for the
query's settings; else each merged map's own, which differs a little from a one-file map's).

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
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np

from ..datatypes import array_bytes
from ..errors import InputError
from ..mapping.calibration import registration_variance
from ..mapping.facade_map import FacadeMap, query_settings, reading_key
from ..params import MapParams, QueryConfig, TilesConfig, map_params_from_record
from ..pipeline.step7_local_surface import LocalSurface
from ..pipeline.step7_queries import PointQuery
from ..pipeline.step8_occupancy import PLSC
from .grid import TileGrid
from .manifest import Manifest, TileRecord, manifest_path, read_manifest, verify_tile

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



def reading_id(config: QueryConfig) -> str | None:
    """The manifest's key of the local reading's calibration for ``config`` (its
    neighbours, radius and inner radius); None for the raster reading (no calibration)."""
    if config.surface != 'local':
        return None
    return f'local:{config.local_neighbours}:{config.local_radius!r}:{config.local_inner!r}'


def local_calibration(fmap: FacadeMap, configs: Iterable[QueryConfig] = (QueryConfig(),)) -> dict[str, float]:
    """The local reading's map-wide calibration (``LocalSurface.calibration_``) of ``fmap`` for
    each of ``configs`` (local readings only), keyed by :func:`reading_id`, for a manifest."""
    out = {}
    for config in configs:
        key = reading_id(config)
        if key is not None:
            out[key] = float(fmap.local_surface(config).calibration_)
    return out


def _install_local_surface(fmap: FacadeMap, config: QueryConfig, calibration: float) -> None:
    """Give ``fmap`` the local surface of ``config`` with the map-wide ``calibration`` (not
    learnt on ``fmap``'s own points, which are a part of the map): put in the cache that
    :meth:`FacadeMap.local_surface` reads, for the map's present state."""
    surface = LocalSurface.of(fmap.facades, fmap.points, config.local_neighbours, config.local_radius,
                              config.local_inner, calibrate=False)
    surface.calibration_ = float(calibration)
    state = (tuple(fmap.facades), tuple(fmap.points.items()))
    cache = fmap.__dict__.get('_local_cache')
    if cache is None or len(cache[0][0]) != len(state[0]) or any(a is not b for a, b in zip(cache[0][0], state[0])):
        cache = (state, {})
        fmap.__dict__['_local_cache'] = cache
    cache[1][reading_key(config)] = surface


@dataclass(eq=False)
class _Group:
    """A merged map of some tiles (the candidate set of a group of points), its façades'
    global ids and the bytes it adds to its tiles' (its local surfaces, copies)."""

    tiles: tuple[str, ...]
    fmap: FacadeMap
    global_ids: np.ndarray
    extra: int = 0
    readings: set = field(default_factory=set)
    lock: threading.Lock = field(default_factory=threading.Lock)


class TiledMap:
    """A tiled map read on demand: the manifest at opening, the tiles when queries need them,
    through an LRU bounded in bytes (the arrays a loaded tile's map holds, and what merged
    maps of several tiles add: their local surfaces). Thread-safe.

    Attributes:
        folder: the map's folder.
        manifest_: the manifest (read once, at opening).
        params: the map's parameters.
        map_origin: (3,) georeference of the map frame, metres.
        grid: the tile grid.
        cache_mb: the cache bound, MB (at least one tile is kept, whatever its size).
        union_tiles: a query whose points need at most this many tiles in all is answered by
            one merged map of them (``tiles.union_tiles``); else its points are grouped by
            their own candidate tiles.
    """

    def __init__(self, path: str | os.PathLike, cache_mb: float = TilesConfig.cache_mb,
                 union_tiles: int = TilesConfig.union_tiles) -> None:
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
        self.union_tiles = int(union_tiles)
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
        self._groups: OrderedDict[tuple[str, ...], _Group] = OrderedDict()
        self._pins: dict[str, int] = {}
        self._stats = {'hits': 0, 'misses': 0, 'evictions': 0, 'load_seconds': 0.0}

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

    def preload(self, xy: np.ndarray, radius: float) -> list[str]:
        """Load the tiles within ``radius`` of ``xy`` (nearest first, as many as the cache
        holds); returns the ids of those loaded now or already (what a node following its pose calls)."""
        out = []
        budget = self.cache_mb * MB
        used = 0
        for rec in self.tiles_near(xy, radius):
            fmap = self.tile(rec.id)
            with self._lock:
                entry = self._tiles.get(rec.id)
                used += entry[1] if entry is not None else array_bytes(fmap)
            out.append(rec.id)
            if used >= budget:
                break
        return out

    def _bytes(self) -> int:
        return sum(s for _, s in self._tiles.values()) + sum(g.extra for g in self._groups.values())

    def _trim(self, keep: str | None = None) -> None:
        """Evict until the cache is within its bound: merged maps first (least recently used
        first; rebuilt from loaded tiles when needed again), then tiles (least recently used
        first, with the merged maps holding them); the tiles in use by a query (pinned),
        ``keep`` and the last tile stay. Call under the lock."""
        budget = self.cache_mb * MB
        while self._bytes() > budget:
            victim = None
            # The least recently used of the tiles and merged maps not in use.
            for key in self._groups:
                if not any(self._pins.get(t) for t in key) and len(self._groups) > 0:
                    victim = ('group', key)
                    break
            if victim is None:
                candidates = [t for t in self._tiles if t != keep and not self._pins.get(t)]
                if len(self._tiles) <= 1 or not candidates:
                    return
                victim = ('tile', candidates[0])
            self._evict(*victim)

    def _evict(self, kind: str, key) -> None:
        if kind == 'group':
            self._groups.pop(key, None)
            return
        self._tiles.pop(key, None)
        for g in [g for g in self._groups if key in g]:
            self._groups.pop(g, None)
        self._stats['evictions'] += 1

    def cache_info(self) -> dict:
        """What the cache holds: ``tiles`` (ids loaded, least recently used first), ``groups``
        (merged maps, as tuples of ids), ``bytes`` (tiles and merged maps), ``tile_bytes``,
        ``limit_bytes``, ``hits``, ``misses`` and ``evictions`` of tiles, ``load_seconds``."""
        with self._lock:
            return {'tiles': list(self._tiles), 'groups': list(self._groups), 'bytes': self._bytes(),
                    'tile_bytes': sum(s for _, s in self._tiles.values()), 'limit_bytes': int(self.cache_mb * MB),
                    **self._stats}

    # -- merged maps -----------------------------------------------------------------------

    def _global_ids(self, tiles: Sequence[str]) -> np.ndarray:
        parts = [self._offset[self._position[t]] + np.arange(self.manifest_.tiles[t].facades) for t in tiles]
        return np.concatenate(parts).astype(np.int32) if parts else np.empty(0, np.int32)

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
            e = self._extent
            meets = (e[:, 0] <= b[2]) & (e[:, 3] >= b[0]) & (e[:, 1] <= b[3]) & (e[:, 4] >= b[1])
            wanted = {self._ids[i] for i in np.flatnonzero(meets)}
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

    def candidates(self, xyz: np.ndarray, config: QueryConfig | None = None) -> tuple[list[str], np.ndarray]:
        """The tiles that may answer for (N, 3) points: ``(ids, mask)`` with the (T,) ids of
        the tiles any point needs and the (N, T) bool of which each point needs."""
        config = QueryConfig() if config is None else config
        xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
        grow = self.reach(config)
        lo, hi = self._extent[:, :3] - grow, self._extent[:, 3:] + grow
        if not len(xyz) or not len(self._ids):
            return [], np.zeros((len(xyz), 0), bool)
        qlo, qhi = xyz.min(axis=0), xyz.max(axis=0)
        near = np.flatnonzero(np.all((lo <= qhi) & (hi >= qlo), axis=1))
        mask = np.zeros((len(xyz), len(near)), bool)
        x = xyz[:, 0]
        for j, i in enumerate(near):  # x first (one pass over the points), y and z on those within
            k = np.flatnonzero((x >= lo[i, 0]) & (x <= hi[i, 0]))
            p = xyz[k]
            mask[k[(p[:, 1] >= lo[i, 1]) & (p[:, 1] <= hi[i, 1]) & (p[:, 2] >= lo[i, 2]) & (p[:, 2] <= hi[i, 2])], j] = True
        used = mask.any(axis=0)
        return [self._ids[i] for i in near[used]], mask[:, used]

    def _group(self, tiles: tuple[str, ...], maps: list[FacadeMap]) -> _Group:
        with self._lock:
            g = self._groups.get(tiles)
            if g is not None:
                self._groups.move_to_end(tiles)
                return g
        g = _Group(tiles, self._merge(maps), self._global_ids(tiles))
        with self._lock:
            return self._groups.setdefault(tiles, g)

    def _prepare(self, g: _Group, config: QueryConfig) -> None:
        """Build the group's local surface for ``config`` once (with the manifest's
        calibration when it has one) and count its bytes."""
        key = reading_id(config)
        if key is None or key in g.readings:
            return
        with g.lock:
            if key in g.readings:
                return
            calibration = self.manifest_.local_calibration.get(key)
            if calibration is not None:
                _install_local_surface(g.fmap, config, calibration)
            surface = g.fmap.local_surface(config)
            if surface is not None and len(surface.points) > config.local_neighbours + 1:
                surface.grid  # noqa: B018 - built now, counted below (the first read would build it)
            g.readings.add(key)
            extra = array_bytes(surface)
        with self._lock:
            if self._groups.get(g.tiles) is g:
                g.extra += extra

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
        ids, mask = self.candidates(xyz, config)
        n = len(xyz)
        if 0 < len(ids) <= self.union_tiles:
            # One merged map of all the batch's candidate tiles answers every point (the same
            # answers: a point's answer involves its candidates only): one call of the
            # compiled kernels instead of one per candidate set.
            mask = np.ones((n, len(ids)), bool)
        if ids:
            keys = np.packbits(mask, axis=1)
            keys = np.ascontiguousarray(keys).view(np.dtype((np.void, keys.shape[1]))).ravel()
            uniq, inverse = np.unique(keys, return_inverse=True)
            inverse = inverse.ravel()
        else:
            uniq, inverse = np.zeros(1, np.int8), np.zeros(n, np.int64)
        order = np.argsort(inverse, kind='stable')
        cuts = np.searchsorted(inverse[order], np.arange(1, len(uniq)))
        out = {'facade': np.full(n, -1, np.int32), 'mean_depth': np.empty(n), 'variance': np.empty(n),
               'noise_variance': np.empty(n), 'signed_distance': np.empty(n), 'p_occupied': np.empty(n),
               'normal': np.empty((n, 3))}
        needed = sorted(ids)
        with self._lock:
            for t in needed:
                self._pins[t] = self._pins.get(t, 0) + 1
        try:
            for members in np.split(order, cuts):
                tiles = tuple(t for t, m in zip(ids, mask[members[0]]) if m) if ids else ()
                tiles = tuple(sorted(tiles))
                g = self._group(tiles, [self.tile(t) for t in tiles])
                self._prepare(g, config)
                answer = g.fmap.query(xyz[members], config, resolution)
                fid = answer.facade
                out['facade'][members] = np.where(fid >= 0, g.global_ids[np.maximum(fid, 0)] if len(g.global_ids)
                                                  else -1, -1)
                for k in ('mean_depth', 'variance', 'noise_variance', 'signed_distance', 'p_occupied', 'normal'):
                    out[k][members] = getattr(answer, k)
        finally:
            with self._lock:
                for t in needed:
                    self._pins[t] -= 1
                    if not self._pins[t]:
                        del self._pins[t]
                self._trim()
        return PointQuery(**out)

    def __repr__(self) -> str:
        return f'TiledMap({str(self.folder)!r}, {len(self._ids)} tiles, side {self.manifest_.side} m)'
