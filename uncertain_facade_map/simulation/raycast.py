"""Vectorised ray intersection with the simulator's solids.

A ray is ``x(t) = o + t d`` with ``o`` the origin (metres, map frame) and ``d`` a unit
direction, so ``t`` is the range in metres. Every function takes ``origins`` and
``directions`` of shape (N, 3) and returns per-ray arrays of shape (N,); a miss is
``inf``. Rays are assumed to start outside the solid they are tested against (the
scanner is never inside a building), and only hits with ``t > T_MIN`` count.
"""

from __future__ import annotations

import numpy as np

#: Smallest range that counts as a hit, metres.
T_MIN = 1e-6
INF = np.inf


def ray_aabb(origins: np.ndarray, inv_directions: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Entry range of rays into an axis-aligned box (slab method).

    Args:
        origins: (N, 3) ray origins, metres.
        inv_directions: (N, 3) element-wise reciprocal of the ray directions, from
            :func:`inverse_directions`.
        lo: (3,) lower corner, metres.
        hi: (3,) upper corner, metres.

    Returns:
        (N,) range at which the ray enters the box (negative for an origin inside),
        ``inf`` where it misses the box or the box lies behind the origin.
    """
    with np.errstate(over='ignore'):
        t1 = (lo - origins) * inv_directions
        t2 = (hi - origins) * inv_directions
    t_enter = np.minimum(t1, t2).max(axis=1)
    t_exit = np.maximum(t1, t2).min(axis=1)
    return np.where((t_enter <= t_exit) & (t_exit > 0.0), t_enter, INF)


def inverse_directions(directions: np.ndarray) -> np.ndarray:
    """(N, 3) element-wise reciprocal of directions for :func:`ray_aabb`.

    A zero component becomes 1e300 rather than ``inf``: a ray lying in a slab plane then
    gives ``0 * 1e300 = 0`` (a hit on the boundary) instead of ``0 * inf = nan``.
    """
    return 1.0 / np.where(directions == 0.0, 1e-300, directions)


def ray_convex(
    origins: np.ndarray, directions: np.ndarray, normals: np.ndarray, offsets: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Intersect rays with a convex polyhedron given as half-spaces (Cyrus-Beck clipping).

    The solid is ``{x : normals[j] . x <= offsets[j] for all j}``.

    Args:
        origins: (N, 3) ray origins, metres.
        directions: (N, 3) unit ray directions.
        normals: (P, 3) outward unit normals of the faces.
        offsets: (P,) plane offsets, metres.

    Returns:
        ``(t_enter, t_exit)``, each (N,) metres; ``inf`` for both where the ray misses.
        ``t_enter`` may be negative for a ray starting inside.
    """
    denom = directions @ normals.T  # (N, P)
    num = offsets[None, :] - origins @ normals.T  # >= 0 where the origin is inside plane j
    with np.errstate(divide='ignore', invalid='ignore'):
        ratio = num / denom
    t_enter = np.where(denom < 0.0, ratio, -INF).max(axis=1)
    t_exit = np.where(denom > 0.0, ratio, INF).min(axis=1)
    blocked = ((denom == 0.0) & (num < 0.0)).any(axis=1)
    hit = ~blocked & (t_enter <= t_exit) & (t_exit > T_MIN)
    return np.where(hit, t_enter, INF), np.where(hit, t_exit, INF)


def ray_vertical_cylinder(
    origins: np.ndarray, directions: np.ndarray, centre: np.ndarray, radius: float, z0: float, z1: float
) -> np.ndarray:
    """First entry of rays into a solid vertical cylinder with flat caps.

    Args:
        origins: (N, 3) ray origins, metres.
        directions: (N, 3) unit ray directions.
        centre: (2,) axis position x, y, metres.
        radius: metres.
        z0: bottom cap height, metres.
        z1: top cap height, metres.

    Returns:
        (N,) entry range, metres; ``inf`` for a miss.
    """
    ox = origins[:, 0] - centre[0]
    oy = origins[:, 1] - centre[1]
    dx, dy, dz = directions[:, 0], directions[:, 1], directions[:, 2]
    a = dx * dx + dy * dy
    b = 2.0 * (ox * dx + oy * dy)
    c = ox * ox + oy * oy - radius * radius
    disc = b * b - 4.0 * a * c
    with np.errstate(divide='ignore', invalid='ignore'):
        t_side = (-b - np.sqrt(np.maximum(disc, 0.0))) / (2.0 * a)
    z_side = origins[:, 2] + t_side * dz
    side_ok = (disc >= 0.0) & (a > 0.0) & (t_side > T_MIN) & (z_side >= z0) & (z_side <= z1)
    best = np.where(side_ok, t_side, INF)
    for z_cap, facing in ((z1, dz < 0.0), (z0, dz > 0.0)):
        with np.errstate(divide='ignore', invalid='ignore'):
            t_cap = (z_cap - origins[:, 2]) / dz
            px = ox + t_cap * dx
            py = oy + t_cap * dy
        cap_ok = facing & (t_cap > T_MIN) & (px * px + py * py <= radius * radius)
        best = np.where(cap_ok & (t_cap < best), t_cap, best)
    return best


def ray_sphere(
    origins: np.ndarray, directions: np.ndarray, centre: np.ndarray, radius: float
) -> tuple[np.ndarray, np.ndarray]:
    """Entry and exit ranges of rays through a sphere.

    Args:
        origins: (N, 3) ray origins, metres.
        directions: (N, 3) unit ray directions.
        centre: (3,) metres.
        radius: metres.

    Returns:
        ``(t0, t1)``, each (N,) metres, ``inf`` where the ray misses or the sphere lies
        behind the origin; ``t0`` is clipped at 0 for an origin inside.
    """
    oc = origins - centre
    b = np.einsum('ij,ij->i', oc, directions)
    c = np.einsum('ij,ij->i', oc, oc) - radius * radius
    disc = b * b - c
    root = np.sqrt(np.maximum(disc, 0.0))
    t0 = np.maximum(-b - root, 0.0)
    t1 = -b + root
    hit = (disc > 0.0) & (t1 > T_MIN)
    return np.where(hit, t0, INF), np.where(hit, t1, INF)


def points_in_polygon(points: np.ndarray, polygon: np.ndarray) -> np.ndarray:
    """Even-odd point-in-polygon test.

    Args:
        points: (N, 2) query points, metres.
        polygon: (M, 2) vertices of a simple polygon, not closed.

    Returns:
        (N,) bool, True inside.
    """
    x = points[:, 0:1]
    y = points[:, 1:2]
    ax, ay = polygon[:, 0], polygon[:, 1]
    bx, by = np.roll(ax, -1), np.roll(ay, -1)
    straddle = (ay > y) != (by > y)
    with np.errstate(divide='ignore', invalid='ignore'):
        x_cross = ax + (y - ay) * (bx - ax) / (by - ay)
    crossings = straddle & (x < x_cross)
    return (crossings.sum(axis=1) % 2) == 1


def ray_prism(
    origins: np.ndarray, directions: np.ndarray, polygon: np.ndarray, z0: float, z1: float
) -> tuple[np.ndarray, np.ndarray]:
    """First entry of rays into a vertical prism over a simple polygon.

    Args:
        origins: (N, 3) ray origins outside the prism, metres.
        directions: (N, 3) unit ray directions.
        polygon: (M, 2) counter-clockwise footprint, not closed, metres.
        z0: floor height, metres.
        z1: roof height, metres.

    Returns:
        ``(t, face)``: (N,) entry range in metres (``inf`` for a miss) and (N,) int face
        index: ``j`` for the wall from vertex ``j`` to ``j + 1``, ``M`` for the roof,
        ``M + 1`` for the floor, ``-1`` for a miss.
    """
    a = polygon
    e = np.roll(polygon, -1, axis=0) - a  # (M, 2) edge vectors
    length2 = np.einsum('ij,ij->i', e, e)
    outward = np.stack([e[:, 1], -e[:, 0]], axis=1)  # right of the edge: outside for CCW
    o2 = origins[:, :2]
    d2 = directions[:, :2]
    denom = d2 @ outward.T  # (N, M); < 0 when the ray crosses the wall inwards
    num = np.einsum('mj,mj->m', outward, a)[None, :] - o2 @ outward.T
    with np.errstate(divide='ignore', invalid='ignore'):
        t = num / denom
        px = o2[:, 0:1] + t * d2[:, 0:1]
        py = o2[:, 1:2] + t * d2[:, 1:2]
        s = ((px - a[:, 0]) * e[:, 0] + (py - a[:, 1]) * e[:, 1]) / length2
        z = origins[:, 2:3] + t * directions[:, 2:3]
    ok = (denom < 0.0) & (t > T_MIN) & (s >= 0.0) & (s <= 1.0) & (z >= z0) & (z <= z1)
    t_wall = np.where(ok, t, INF)
    face = np.argmin(t_wall, axis=1)
    best = t_wall[np.arange(len(t_wall)), face]
    m = len(polygon)
    for z_cap, facing, index in ((z1, directions[:, 2] < 0.0, m), (z0, directions[:, 2] > 0.0, m + 1)):
        if not facing.any():
            continue
        with np.errstate(divide='ignore', invalid='ignore'):
            t_cap = (z_cap - origins[:, 2]) / directions[:, 2]
        cand = facing & (t_cap > T_MIN) & (t_cap < best)
        if cand.any():
            idx = np.flatnonzero(cand)
            p = origins[idx, :2] + t_cap[idx, None] * d2[idx]
            inside = points_in_polygon(p, polygon)
            idx = idx[inside]
            best[idx] = t_cap[idx]
            face[idx] = index
    face = np.where(np.isfinite(best), face, -1)
    return best, face
