"""The map a live mapper serves (the ``facade_mapper`` node's): its live map, a tiled map
beside it (issue 29), the per-point reading, and the thread that follows the pose.

:class:`ServedMap` is what the node's services read and change, with one :meth:`~ServedMap.query`:

- ``query_points`` is answered by the live map's latest snapshot with its reading
  (:class:`~uncertain_facade_map.mapping.served.ServedReading`); with a tiled map served
  (:class:`~uncertain_facade_map.tiling.tiled_map.TiledMap`: a folder with ``manifest.json``
  and one map file per tile, **read-only**) by the tiled map (tiles loaded on demand, at most
  ``tiles.cache_mb`` kept, least recently used first out), and a point the tiled map leaves
  on no façade by the live map when that has façades (its façade id then carries
  :data:`LIVE_FACADE_OFFSET`, so that the two maps' ids never mix);
- clouds still map into the live map (which starts empty, with the tiled map's parameters
  and map origin); ``save_map`` saves the live map into the map folder, never into a tiled
  map; the published maps and ``get_map`` are the live map's;
- ``get_facades`` answers from the tile holding the building (or, for building -1, the
  tiles loaded now), then the live map's;
- ``list_tiles`` lists the tiles near a position (ids, squares, files, loaded flags).

:class:`TileFollower` looks at the node's latest pose every ``tiles.follow_period`` s, in a
thread of its own (never in a query's or a cloud's path), and loads the tiles within
``tiles.radius`` m of it, with their local reading prepared and the view holding the pose built
(:meth:`TiledMap.preload`); the cache evicts the least recently used.
"""

from __future__ import annotations

import dataclasses
import functools
import threading
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

from ..errors import InputError
from ..io.map_file import save_map
from ..io.map_folder import MapFolder
from ..mapping.facade_map import FacadeMap
from ..mapping.served import ServedReading
from ..mapping.worker import replace_with
from ..params import Config, QueryConfig, TilesConfig, map_params
from .manifest import is_tiled_map, manifest_path
from .tiled_map import TiledMap, open_map

__all__ = ['LIVE_FACADE_OFFSET', 'ServedMap', 'TileFollower', 'check_radius', 'combine_answers', 'loaded_ids', 'tile_facades',
           'tiles_near_listing']

#: Added to the façade id of a point the live map answers while a tiled map is served.
LIVE_FACADE_OFFSET = 1 << 30


def combine_answers(tiled: Any, live: Any, asked: np.ndarray) -> dict[str, np.ndarray]:
    """The tiled map's answers with those of the live map where the tiled map found no façade.

    Args:
        tiled: the tiled map's answers for N points (``PointQuery`` or its ``as_dict()``).
        live: the live map's answers for the points ``asked`` selects (M of them), or None.
        asked: (M,) indices into the N points that the live map was asked.

    Returns:
        The answers by name, (N,) arrays (``normal`` (N, 3)); a point the live map puts on a
        façade takes all the live answers, its façade id plus :data:`LIVE_FACADE_OFFSET`.
    """
    out = {k: np.array(v) for k, v in (tiled.as_dict() if hasattr(tiled, 'as_dict') else tiled).items()}
    if live is None or not len(asked):
        return out
    live = live.as_dict() if hasattr(live, 'as_dict') else live
    on = np.asarray(live['facade']) >= 0
    rows = np.asarray(asked)[on]
    for key, value in live.items():
        if key in out:
            out[key][rows] = np.asarray(value)[on]
    out['facade'][rows] = (np.asarray(live['facade'])[on].astype(np.int64) + LIVE_FACADE_OFFSET).astype(
        out['facade'].dtype)
    return out


def tiles_near_listing(tiled: Any, path: str | Path, xy: np.ndarray, radius: float) -> tuple[
        list[str], np.ndarray, list[str], list[bool]]:
    """The tiles of ``tiled`` (opened from ``path``, its folder or manifest) whose square comes
    within ``radius`` m of ``xy`` (map frame), nearest first (ties by id): ids, (K, 4) squares,
    absolute files, loaded flags."""
    records = list(tiled.tiles_near(np.asarray(xy, dtype=np.float64), float(radius)))
    if records:
        box = np.array([r.bounds for r in records], dtype=np.float64)
        gap = np.maximum(np.maximum(box[:, :2] - xy, xy - box[:, 2:]), 0.0)
        order = sorted(range(len(records)), key=lambda i: (float(np.hypot(*gap[i])), records[i].id))
        records = [records[i] for i in order]
    folder = manifest_path(path).parent.resolve()
    loaded = set(loaded_ids(tiled))
    return ([r.id for r in records], np.array([r.bounds for r in records], dtype=np.float64).reshape(-1, 4),
            [str(folder / r.file) for r in records], [r.id in loaded for r in records])


def loaded_ids(tiled: Any) -> list[str]:
    """Ids of the tiles a TiledMap holds loaded now (least recently used first)."""
    return [str(t) for t in tiled.cache_info()['tiles']]


def tile_facades(tiled: Any, tile_ids: list[str], building: int = -1) -> list[Any]:
    """The façade models of some tiles (loaded through the cache), of one building (-1: all),
    their ids the tiled map's (as its queries and ``merged()`` of every tile number them: the
    tiles in id order, each tile's façades in its file's order)."""
    import dataclasses

    records = tiled.records  # in id order
    offsets = dict(zip((r.id for r in records), np.cumsum([0] + [r.facades for r in records])[:-1].tolist()))
    out = []
    for t in tile_ids:
        shift = int(offsets[t])
        out.extend(dataclasses.replace(f, facade_id=f.facade_id + shift) if shift else f
                   for f in tiled.tile(t).facades if building < 0 or f.building == building)
    return out


class TileFollower:
    """Keeps the tiles near the node's latest pose loaded, in a thread of its own.

    Args:
        tiled: the served tiled map (thread-safe: queries run beside the preloads).
        config: ``tiles.*`` (radius, follow period).
        pose: returns the node's latest (x, y) in the map frame, metres, or None (no pose yet).
        log: called with a warning's text when a preload fails.
        query: the queries' settings (``query.*``): the tiles' local reading and the view
            holding the pose are prepared too (:meth:`TiledMap.preload`); None: tiles only.
    """

    def __init__(self, tiled: Any, config: TilesConfig, pose: Callable[[], np.ndarray | None],
                 log: Callable[[str], None], query: QueryConfig | None = None) -> None:
        self.tiled = tiled
        self.config = config
        self.query = query
        self.pose = pose
        self.log = log
        self.preloads = 0  # preloads done (each loads what is missing within the radius)
        self.tiles_preloaded = 0  # tiles the preloads found near the pose, summed
        self.failures = 0
        self.last_seconds = 0.0
        self.max_seconds = 0.0
        self.total_seconds = 0.0
        self.last_xy: np.ndarray | None = None
        self.near = (0, 0)  # (tiles the last preload holds, tiles within the radius of its pose)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        """Start following (nothing when ``tiles.follow_period`` is 0)."""
        if self.config.follow_period > 0 and self._thread is None:
            self._thread = threading.Thread(target=self._run, daemon=True, name='tile_follower')
            self._thread.start()

    def stop(self, timeout: float = 10.0) -> None:
        """Stop following (waits for a preload under way, at most ``timeout`` s)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout)

    def _run(self) -> None:
        while not self._stop.wait(self.config.follow_period):
            try:
                self.follow_once()
            except Exception as exc:  # noqa: BLE001 - the thread must live on; the next look tries again
                self.failures += 1
                self.log(f'loading the tiles near the pose failed: {type(exc).__name__}: {exc}')

    def follow_once(self) -> list[str] | None:
        """Load the tiles within ``tiles.radius`` of the latest pose; None without a pose."""
        xy = self.pose()
        if xy is None:
            return None
        xy = np.asarray(xy, dtype=np.float64)[:2]
        started = time.perf_counter()
        ids = list(self.tiled.preload(xy, self.config.radius, self.query))
        seconds = time.perf_counter() - started
        near = len(self.tiled.tiles_near(xy, self.config.radius))
        if len(ids) < near:
            self.log(f'tiles.cache_mb = {self.config.cache_mb:g} MB holds {len(ids)} of the {near} tiles within '
                     f'tiles.radius = {self.config.radius:g} m of the pose: queries there load and evict tiles '
                     'in turn (slow); raise tiles.cache_mb or lower tiles.radius')
        self.near = (len(ids), near)
        self.last_xy = xy
        self.preloads += 1
        self.tiles_preloaded += len(ids)
        self.last_seconds = seconds
        self.max_seconds = max(self.max_seconds, seconds)
        self.total_seconds += seconds
        return ids

    def values(self) -> dict[str, Any]:
        """The diagnostics' values of the following."""
        xy = self.last_xy
        return {'tiles_preloads': self.preloads, 'tiles_preload_failures': self.failures,
                'tiles_preload_last_seconds': round(self.last_seconds, 4),
                'tiles_preload_max_seconds': round(self.max_seconds, 4),
                'tiles_preload_mean_seconds': round(self.total_seconds / self.preloads, 4) if self.preloads else 0.0,
                'tiles_near_pose': self.near[1], 'tiles_near_pose_loaded': self.near[0],
                'tiles_follow_x': round(float(xy[0]), 2) if xy is not None else '',
                'tiles_follow_y': round(float(xy[1]), 2) if xy is not None else ''}


def check_radius(radius: float, default: float) -> float:
    """A list_tiles radius, metres: 0 takes ``default``; negative or not finite is refused."""
    r = float(radius)
    if not np.isfinite(r) or r < 0:
        raise InputError(f'radius must be 0 (tiles.radius) or a positive number of metres, got {radius}')
    return r or float(default)


#: Seconds a command to the map worker (load, reset) waits before it is answered "busy".
COMMAND_TIMEOUT = 120.0


def open_any(path: str | Path, tiles: TilesConfig) -> FacadeMap | TiledMap:
    """A map file, or a tiled map read through ``tiles.cache_mb`` and ``tiles.view_tiles``.

    Raises:
        InputError: a damaged file or manifest, a folder without a manifest (one line each).
    """
    return TiledMap(path, tiles.cache_mb, tiles.view_tiles) if is_tiled_map(path) else open_map(path, tiles.cache_mb)


def live_map_beside(tiled: TiledMap) -> FacadeMap:
    """The empty live map beside a served tiled map: its parameters and map origin."""
    return FacadeMap(tiled.params, np.asarray(tiled.map_origin, dtype=np.float64).copy())


def initial_map(config: Config, log: Callable[[str], None]) -> tuple[FacadeMap, TiledMap | None]:
    """The live map a mapper starts with (``persistence.map_path``: a map file loaded, a tiled
    map served beside an empty live map, or an empty map when the path does not exist yet),
    and the tiled map served (or None).

    Raises:
        InputError: a damaged file (better than mapping over it) or a folder that is no tiled map.
    """
    path = config.persistence.map_path
    if path and Path(path).exists():
        opened = open_any(path, config.tiles)
        if isinstance(opened, TiledMap):
            log(f'serving the tiled map {path} read-only: {len(opened.manifest_.tiles)} tiles, at most '
                f'{config.tiles.cache_mb:g} MB loaded; persistence.map_path is not autosaved, save_map needs a '
                'path; clouds map into a live map')
            return live_map_beside(opened), opened
        log(f'loaded {path}: {len(opened.facades)} façades, {opened.n_points} points')
        return opened, None
    if path:
        log(f'{path} does not exist yet; starting an empty map')
    return FacadeMap(map_params(config), np.asarray(config.input.map_origin, dtype=np.float64)), None


class ServedMap:
    """The live map (its worker's snapshots and the reading), a tiled map beside it, and the
    map folder its saves and loads go through: what a mapper's services read and change.

    Args:
        worker: the live map's worker (:class:`~uncertain_facade_map.mapping.worker.MapWorker`).
        reading: the reading of the live map's stored points.
        config: the configuration (``query``, ``tiles``, ``persistence``, ``input``).
        tiled: the tiled map served from the start (or None), opened from ``persistence.map_path``.
        pose_xy: returns the map-frame (x, y) the tiles follow, or None (see :class:`TileFollower`).
        warn: logs a warning (its text, a kind, a period in s: throttled per kind).
    """

    def __init__(self, worker: Any, reading: ServedReading, config: Config, tiled: TiledMap | None,
                 pose_xy: Callable[[], np.ndarray | None], warn: Callable[[str, str, float], None]) -> None:
        self.worker = worker
        self.reading = reading
        self.config = config
        per = config.persistence
        #: Where save_map and load_map read and write (any DDS participant may call them).
        self.folder = MapFolder.of(per.map_dir, per.map_path, per.allow_any_path, per.max_load_mb)
        self._pose_xy = pose_xy
        self._warn = warn
        self._lock = threading.Lock()  # the tiled map, its path and its follower change together
        self._save_lock = threading.Lock()
        self.saved_version = 0
        self.tiled: TiledMap | None = None
        self.tiled_path = ''
        self.follower: TileFollower | None = None
        if tiled is not None:
            self.serve_tiled(tiled, per.map_path)

    # -- the tiled map -----------------------------------------------------------------------
    def serve_tiled(self, tiled: TiledMap | None, path: str | Path = '') -> None:
        """Serve ``tiled`` (None: no tiled map) from now on, following the pose for it
        (``tiles.follow_period`` > 0) and stopping the previous follower."""
        with self._lock:
            old = self.follower
            follower = None if tiled is None else TileFollower(
                tiled, self.config.tiles, self._pose_xy, lambda text: self._warn(text, 'tile follower', 30.0),
                self.config.query)
            self.tiled, self.tiled_path, self.follower = tiled, str(path) if tiled is not None else '', follower
            if old is not None:
                old.stop()
            if follower is not None:
                follower.start()

    def read_only(self, path: str | Path) -> bool:
        """True when ``path`` is the served tiled map or a tiled map, or lies in one (never saved over)."""
        return (is_tiled_map(path) or any(is_tiled_map(p) for p in Path(path).parents)
                or (bool(self.tiled_path) and Path(path).resolve() == Path(self.tiled_path).resolve()))

    def tiles_values(self) -> dict[str, Any]:
        """The diagnostics of the served tiled map: tiles loaded, cache MB, preloads and their time."""
        tiled, follower = self.tiled, self.follower
        if tiled is None:
            return {'tiled_map': ''}
        info = tiled.cache_info()
        values = {'tiled_map': self.tiled_path, 'tiles': len(tiled.manifest_.tiles),
                  'tiles_loaded': len(info['tiles']),
                  'tiles_cache_mb': round(info['bytes'] / 2**20, 1),
                  'tiles_cache_limit_mb': round(info['limit_bytes'] / 2**20, 1),
                  'tiles_views': len(info['views']), 'tiles_views_built': info['views_built'],
                  'tiles_hits': info['hits'], 'tiles_misses': info['misses'], 'tiles_evictions': info['evictions'],
                  'tiles_load_seconds': round(info['load_seconds'], 3)}
        if follower is not None:
            values.update(follower.values())
        return values

    # -- reading ---------------------------------------------------------------------------------
    def query(self, xyz: np.ndarray, resolution: float) -> tuple[Any, str]:
        """Answers for (N, 3) map-frame points, metres, from the latest snapshot (never waits
        for the worker) and the tiled map when one is served; and a line saying what answered.

        Returns:
            (answers: a ``PointQuery`` or its fields by name, message).
        """
        snap = self.worker.snapshot
        tiled, path = self.tiled, self.tiled_path
        if tiled is None:
            # Its own bands (a loaded map keeps its own); the local reading as ServedReading says.
            answers = snap.query(xyz, self.config.query, resolution, local=self.reading.for_snapshot(snap))
            return answers, f'{len(xyz)} points, map version {snap.version}'
        answers = tiled.query(xyz, self.config.query, resolution)
        asked = np.flatnonzero(np.asarray(answers.facade) < 0) if snap.facades else np.zeros(0, np.int64)
        live = (snap.query(xyz[asked], self.config.query, resolution, local=self.reading.for_snapshot(snap))
                if len(asked) else None)
        out = combine_answers(answers, live, asked)
        by_live = int((np.asarray(live.facade) >= 0).sum()) if live is not None else 0
        return out, (f'{len(xyz)} points, tiled map {path}'
                     + (f'; {by_live} answered by the live map (version {snap.version})' if by_live else ''))

    def facades(self, building: int) -> tuple[list[Any], str]:
        """The façade models of one building (or all, -1) and a note. With a tiled map served:
        the building's tile's (or, for -1, those of the tiles loaded now), ids the tiled map's
        as its queries answer them, then the live map's (ids plus :data:`LIVE_FACADE_OFFSET`)."""
        models = [f for f in self.worker.snapshot.facades if building < 0 or f.building == building]
        tiled = self.tiled
        if tiled is None:
            return models, ''
        models = [dataclasses.replace(f, facade_id=f.facade_id + LIVE_FACADE_OFFSET) for f in models]
        if building >= 0:
            tiles = tiled.manifest_.building_tiles
            tile_ids = [tiles[building]] if building in tiles else []
        else:
            tile_ids = loaded_ids(tiled)
        from_tiles = tile_facades(tiled, tile_ids, building)
        return from_tiles + models, (f' ({len(from_tiles)} of the tiled map\'s tiles '
                                     f'{", ".join(tile_ids) or "(none loaded)"})')

    def tiles_near(self, xy: np.ndarray, radius: float) -> tuple[list[str], np.ndarray, list[str], list[bool], str]:
        """The served tiled map's tiles within ``radius`` m of map-frame ``xy`` (0: ``tiles.radius``):
        ids, (K, 4) squares, files, loaded flags and a line.

        Raises:
            InputError: no tiled map served, a position or radius that is not a number.
        """
        tiled, path = self.tiled, self.tiled_path
        if tiled is None:
            raise InputError('no tiled map is served: load one with load_map (a folder with manifest.json) '
                             'or start with persistence.map_path naming one')
        xy = np.asarray(xy, dtype=np.float64)
        if not np.isfinite(xy).all():
            raise InputError(f'x and y must be finite, got {xy[0]}, {xy[1]}')
        radius = check_radius(radius, self.config.tiles.radius)
        ids, bounds, files, loaded = tiles_near_listing(tiled, path, xy, radius)
        return ids, bounds, files, loaded, (f'{len(ids)} tiles within {radius:g} m of ({xy[0]:g}, {xy[1]:g}), '
                                            f'{sum(loaded)} loaded')

    # -- saving and loading ----------------------------------------------------------------------
    def _path(self, given: str) -> str:
        """``persistence.map_path`` (the operator's) when no path is given."""
        path = given or self.config.persistence.map_path
        if not path:
            raise InputError('no path given and the parameter persistence.map_path is empty')
        return path

    def save_path(self, given: str) -> str:
        """Where save_map writes the live map: in the map folder (:class:`MapFolder`), over
        nothing but a map file, never into a tiled map (served read-only).

        Raises:
            InputError: a path outside the map folder, over another file, in a tiled map, or
                in a folder that does not exist.
        """
        path = str(self.folder.save_path(given)) if given else self._path(given)
        if self.read_only(path):
            raise InputError(f'{path} is a tiled map or lies in one, read-only: save_map writes the live map to a '
                             'map file of its own; give it another path')
        if Path(path).parent == self.folder.root:
            self.folder.root.mkdir(parents=True, exist_ok=True)
        if not Path(path).parent.exists():
            raise InputError(f'folder {Path(path).parent} does not exist')
        return path

    def save(self, path: str) -> tuple[int, int]:
        """Save the live map as it stands now, atomically, without waiting for the queue (the
        worker keeps a clone after every cloud, which is written while it maps on); one save
        at a time.

        Returns:
            (map version saved, clouds waiting that the file does not hold).
        """
        with self._save_lock:
            fmap, version, waiting = self.worker.committed()
            save_map(fmap, path, replace_only_maps=True)
            self.saved_version = version
            return version, waiting

    def autosave(self) -> bool:
        """Save to ``persistence.map_path`` when the map changed since the last save (never
        over a tiled map); returns whether it saved."""
        path = self.config.persistence.map_path
        if not path or self.worker.committed_version == self.saved_version or self.read_only(path):
            return False
        self.save(path)
        return True

    def load(self, given: str) -> tuple[int, str]:
        """Replace the live map by a map file, or serve a tiled map (read-only; the live map
        starts empty beside it); a bad file or a folder without a manifest leaves everything
        as it is. Returns (façades, a line).

        Raises:
            InputError: a path outside the map folder, a damaged file or manifest.
            TimeoutError: the worker did not take the new map within :data:`COMMAND_TIMEOUT` s.
        """
        path = str(self.folder.load_path(given)) if given else self._path(given)
        opened = open_any(path, self.config.tiles)
        if isinstance(opened, TiledMap):
            self.worker.call(functools.partial(replace_with, live_map_beside(opened), None), COMMAND_TIMEOUT)
            self.serve_tiled(opened, path)
            facades = sum(t.facades for t in opened.manifest_.tiles.values())
            return facades, (f'serving the tiled map {path} read-only: {len(opened.manifest_.tiles)} tiles, '
                             f'{facades} façades; the live map starts empty')
        self.worker.call(functools.partial(replace_with, opened, None), COMMAND_TIMEOUT)
        self.serve_tiled(None)
        return len(opened.facades), f'loaded {path}: {len(opened.facades)} façades, {opened.n_points} points'

    def reset(self) -> None:
        """Start an empty live map (clouds queued before are mapped first, then cleared); a
        served tiled map stays (read-only), the live map restarts with its parameters.

        Raises:
            TimeoutError: the worker did not get to it within :data:`COMMAND_TIMEOUT` s.
        """
        tiled = self.tiled
        empty = (FacadeMap(map_params(self.config), np.asarray(self.config.input.map_origin, dtype=np.float64))
                 if tiled is None else live_map_beside(tiled))
        self.worker.call(functools.partial(replace_with, empty, None), COMMAND_TIMEOUT)

    def close(self) -> None:
        """Stop following the pose."""
        self.serve_tiled(None)
