"""A tiled map served by the facade_mapper node (issue 29), and the thread that follows its pose.

The node serves a tiled map (:class:`~uncertain_facade_map.tiling.tiled_map.TiledMap`: a
folder with ``manifest.json`` and one map file per tile) **read-only**, beside its live map:

- ``query_points`` is answered by the tiled map (tiles loaded on demand, at most
  ``tiles.cache_mb`` kept, least recently used first out); a point the tiled map leaves on no
  façade is answered by the live map when the live map has façades (its façade id then
  carries :data:`LIVE_FACADE_OFFSET`, so that the two maps' ids never mix);
- clouds still map into the live map (which starts empty, with the tiled map's parameters
  and map origin); ``save_map`` saves the live map, never into the tiled map; the published
  maps and ``get_map`` are the live map's;
- ``get_facades`` answers from the tile holding the building (or, for building -1, the
  tiles loaded now), then the live map's;
- ``list_tiles`` lists the tiles near a position (ids, squares, files, loaded flags).

:class:`TileFollower` looks at the node's latest pose every ``tiles.follow_period`` s, in a
thread of its own (never in a query's or a cloud's path), and loads the tiles within
``tiles.radius`` m of it, with their local reading prepared and the view holding the pose built
(:meth:`TiledMap.preload`); the cache evicts the least recently used.
"""

from __future__ import annotations

import threading
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

from uncertain_facade_map.errors import InputError
from uncertain_facade_map.params import QueryConfig, TilesConfig
from uncertain_facade_map.tiling.manifest import manifest_path

__all__ = ['LIVE_FACADE_OFFSET', 'TileFollower', 'check_radius', 'combine_answers', 'loaded_ids', 'tile_facades',
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
