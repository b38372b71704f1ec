"""The storage rule's compiled pass (numba): which new points a building stores.

:meth:`~uncertain_facade_map.mapping.facade_map.FacadeMap._thin` states the rule; this
kernel applies it point by point in arrival order, because whether a point is stored
depends on which earlier points were.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from ..voxels import wrapped_keys

#: Bits per axis of a spacing cell's packed key (cells repeat 2^21 cells apart: a key
#: shared by two far cells costs a distance test, never a wrong answer).
_BITS = 21
_MASK = (1 << _BITS) - 1


@njit(cache=True, nogil=True, inline='always')
def _cell_key(ix: int, iy: int, iz: int) -> int:  # pragma: no cover - compiled
    return ((ix & _MASK) << (2 * _BITS)) | ((iy & _MASK) << _BITS) | (iz & _MASK)


@njit(cache=True, nogil=True, inline='always')
def _slot(table_key: np.ndarray, key: int, mask: int) -> int:  # pragma: no cover - compiled
    """The slot of ``key`` in an open-addressing table, or of the empty slot it would take."""
    s = np.int64((np.uint64(key) * np.uint64(0x9E3779B97F4A7C15)) >> np.uint64(32)) & mask
    while table_key[s] != -1 and table_key[s] != key:
        s = (s + 1) & mask
    return s


@njit(cache=True, nogil=True)
def store_pass(new: np.ndarray, group: np.ndarray, have: np.ndarray, cap: int, held: np.ndarray,
               spacing: float) -> np.ndarray:  # pragma: no cover - compiled
    """(N,) int8 outcome of each new point, in arrival order: 1 stored, 0 its storage voxel
    was full, -1 a point already stored (or stored earlier in this pass) lies within
    ``spacing`` of it.

    Args:
        new: (N, 3) float64 new points of one building, metres, map frame, arrival order.
        group: (N,) int64 index of each new point's storage voxel in ``have``.
        have: (G,) int64 points its voxel already stores (counted up as points are stored).
        cap: points a storage voxel stores at most.
        held: (S, 3) float64 stored points near the new ones (at least those within
            ``spacing`` of one), metres, map frame.
        spacing: metres, > 0 (without one, :func:`store` applies the voxel cap alone).
    """
    n, s_held = new.shape[0], held.shape[0]
    out = np.zeros(n, np.int8)
    count = have.copy()
    inv = 1.0 / spacing
    d2 = spacing * spacing
    size = 16
    while size < 2 * (n + s_held):
        size *= 2
    mask = size - 1
    table_key = np.full(size, -1, np.int64)
    table_head = np.full(size, -1, np.int64)
    link = np.full(n + s_held, -1, np.int64)  # the next point of the same cell, -1 at the end
    pts = np.empty((n + s_held, 3))
    used = 0
    for j in range(s_held):  # the held points, by cell
        for a in range(3):
            pts[used, a] = held[j, a]
        k = _cell_key(int(math.floor(held[j, 0] * inv)), int(math.floor(held[j, 1] * inv)),
                      int(math.floor(held[j, 2] * inv)))
        slot = _slot(table_key, k, mask)
        table_key[slot] = k
        link[used] = table_head[slot]
        table_head[slot] = used
        used += 1
    for i in range(n):
        g = group[i]
        if count[g] >= cap:
            continue
        x, y, z = new[i, 0], new[i, 1], new[i, 2]
        cx, cy, cz = int(math.floor(x * inv)), int(math.floor(y * inv)), int(math.floor(z * inv))
        near = False
        for dx in range(-1, 2):
            for dy in range(-1, 2):
                for dz in range(-1, 2):
                    slot = _slot(table_key, _cell_key(cx + dx, cy + dy, cz + dz), mask)
                    p = table_head[slot]
                    while p >= 0:
                        ex, ey, ez = pts[p, 0] - x, pts[p, 1] - y, pts[p, 2] - z
                        if ex * ex + ey * ey + ez * ez < d2:
                            near = True
                            break
                        p = link[p]
                    if near:
                        break
                if near:
                    break
            if near:
                break
        if near:
            out[i] = -1
            continue
        out[i] = 1
        count[g] += 1
        pts[used, 0], pts[used, 1], pts[used, 2] = x, y, z
        slot = _slot(table_key, _cell_key(cx, cy, cz), mask)
        table_key[slot] = _cell_key(cx, cy, cz)
        link[used] = table_head[slot]
        table_head[slot] = used
        used += 1
    return out


def voxel_groups(keys: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points grouped by their (N,) int64 voxel keys, with one stable sort.

    Returns:
        ``(uk, group, order)``: (G,) sorted unique keys, (N,) int64 index of each point's key
        in ``uk``, and (N,) the stable order that sorts the keys (arrival order within a voxel).
    """
    order = np.argsort(keys, kind='stable')
    sk = keys[order]
    first = np.empty(len(sk), dtype=bool)
    first[:1] = True
    first[1:] = sk[1:] != sk[:-1]
    group = np.empty(len(sk), dtype=np.int64)
    group[order] = np.cumsum(first) - 1
    return sk[first], group, order


def store(new: np.ndarray, group: np.ndarray, order: np.ndarray, have: np.ndarray, cap: int, held: np.ndarray,
          spacing: float) -> np.ndarray:
    """(N,) bool: the new points stored, by the rule of :func:`store_pass` (the same
    arguments, and ``order`` of :func:`voxel_groups`).

    Without a spacing the voxel cap alone decides, vectorised (a voxel's first ``cap - have``
    new points in arrival order), and nothing is compiled: the default map's first cloud
    does not wait for the compiler."""
    if spacing > 0:
        return store_pass(new, group, have, cap, held, spacing) > 0
    sg = group[order]
    first = np.empty(len(sg), dtype=bool)
    first[:1] = True
    first[1:] = sg[1:] != sg[:-1]
    starts = np.flatnonzero(first)
    rank = np.arange(len(sg)) - starts[np.cumsum(first) - 1]
    keep = np.empty(len(group), dtype=bool)
    keep[order] = have[sg] + rank < cap
    return keep


def stored_in_order(xyz: np.ndarray, voxel: float, cap: int, spacing: float) -> np.ndarray:
    """(N,) bool: which of (N, 3) points (metres, map frame, arrival order) an empty
    building would store by the rule of :func:`store_pass` (``update.store_voxel``,
    ``update.store_per_voxel``, ``update.store_spacing``)."""
    xyz = np.ascontiguousarray(xyz, dtype=np.float64)
    uk, group, order = voxel_groups(wrapped_keys(xyz, voxel))
    return store(xyz, group, order, np.zeros(len(uk), np.int64), cap, np.empty((0, 3)), spacing)
