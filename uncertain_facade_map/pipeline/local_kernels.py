"""Compiled kernels of the per-point reading (:mod:`.step7_local_surface`, issue 27).

The same reading as :func:`~.step7_local_surface.fit_local_planes` on the ``K + 1``
nearest stored points, computed point by point in one compiled loop over both cores
instead of numpy passes over (N, K + 1, 3) arrays and a KD-tree query:

- the nearest stored points come from a grid of the stored points (:class:`PointGrid`:
  cells of side ``cell``, the points sorted by cell, each column (x, y) of cells found
  through a dense table per tile of ``TILE`` x ``TILE`` columns and one open-addressing
  hash probe per tile), searched ring by ring of cells around the query's cell until the
  ``K + 1``-th nearest found lies within the searched cube (exact nearest neighbours, as
  the KD-tree's; points whose search would need more than ``MAX_RING`` rings are left to
  the caller, flagged);
- the weighted plane's normal in closed form (the smallest eigenvalue of the 3 x 3
  scatter by Smith's trigonometric formula, its eigenvector as the longest cross product
  of two rows of ``scatter - lambda_min I``), and the in-plane eigenvalues and directions
  for the leverage from the 2 x 2 scatter within the plane; a cyclic Jacobi
  eigen-decomposition where the two smallest eigenvalues nearly coincide (a line or a
  ball of neighbours, no plane to speak of) and the closed form's normal is ill-posed.
  The closed form is 3-4 x faster than Jacobi: the reading's 500,000 street queries took
  1.36 s with Jacobi alone.

The kernels release the GIL (``nogil``): a reading built in a background thread leaves
the interpreter to the threads that answer queries. Calls of the parallel kernel take
turns (:func:`planes`: it uses both cores anyway, and numba's ``workqueue`` threading
layer, where neither ``omp`` nor ``tbb`` is found, stops the process when two threads
launch parallel kernels at once); one-core calls run side by side.

Frames and units as in :mod:`.step7_local_surface`: map frame, metres.
"""

from __future__ import annotations

import contextlib
import threading
from typing import Iterator

import numpy as np
from numba import njit, prange

from ..threads import serial_twin

#: Rings of cells searched at most around a query's cell; beyond, the point is flagged
#: (``status`` 2) for the caller to search again (coarser cells, then a KD-tree).
MAX_RING = 6
#: Cells per axis (from the grid's lower corner) that a packed int64 key holds (21 bits each).
_LIMIT = 1 << 21
_HASH = np.uint64(0x9E3779B97F4A7C15)
#: Points per parallel task (scratch arrays are allocated once per task).
_BATCH = 256
#: Below this many points a call runs on one core (waking the second costs more).
SERIAL_BELOW = 2048


@njit(cache=True, nogil=True, inline='always')
def _slot(key: np.int64, shift: np.uint64) -> np.int64:
    return np.int64((np.uint64(key) * _HASH) >> shift)


@njit(cache=True, nogil=True)
def _build_table(keys: np.ndarray, bits: int) -> np.ndarray:
    """Open-addressing table (2**bits slots) of the sorted unique ``keys``: slot -> index into
    ``keys`` (-1: empty)."""
    size = 1 << bits
    table = np.full(size, -1, np.int64)
    shift = np.uint64(64 - bits)
    mask = size - 1
    for c in range(len(keys)):
        s = _slot(keys[c], shift)
        while table[s] >= 0:
            s = (s + 1) & mask
        table[s] = c
    return table


@njit(cache=True, nogil=True, inline='always')
def _find(table: np.ndarray, keys: np.ndarray, key: np.int64, shift: np.uint64) -> np.int64:
    mask = len(table) - 1
    s = _slot(key, shift)
    while True:
        c = table[s]
        if c < 0:
            return -1
        if keys[c] == key:
            return c
        s = (s + 1) & mask


#: Columns per side of a tile (the columns' table is dense within a tile).
TILE = 8


class PointGrid:
    """The stored points sorted by cell of side ``cell`` (x, then y, then z), found by column.

    A column is the cells of one (x, y); within a tile of ``TILE`` x ``TILE`` columns, a
    dense table gives each column's cells, so the search around a point reads a few
    contiguous runs instead of one hash probe per cell.

    Attributes:
        cell: side of a cell, metres.
        points: (M, 3) the points sorted by cell, metres.
        order: (M,) index of each sorted point in the caller's array.
        zlo: (C,) lowest z cell of each column; ``zoff``: (C,) its first entry in ``zstart``.
        nz: (C,) z cells of each column, ``zhi - zlo + 1``.
        zstart: first sorted point of each z cell of each column, and one past the last.
        tile_keys: (T,) packed keys of the occupied tiles; ``tile_cols``: (T, TILE**2)
            column index of each of a tile's columns (-1: none).
        table: hash slot -> tile index (-1 empty); ``shift``: 64 - bits.
    """

    def __init__(self, points: np.ndarray, cell: float, corner: np.ndarray | None = None) -> None:
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        self.corner = (points.min(axis=0) if len(points) else np.zeros(3)) if corner is None else corner
        extent = float(np.max(points.max(axis=0) - self.corner)) if len(points) else 0.0
        # Cells indexed from the lower corner on 21 bits per axis: cells large enough to hold
        # the extent (2 km at 1 mm cells, 525 km at 0.25 m).
        self.cell = max(float(cell), 2.0 * extent / _LIMIT)
        ijk = np.floor((points - self.corner) / self.cell).astype(np.int64)
        key = (ijk[:, 0] << 42) | (ijk[:, 1] << 21) | ijk[:, 2]
        self.order = np.argsort(key, kind='stable')
        key = key[self.order]
        ijk = ijk[self.order]
        self.points = np.ascontiguousarray(points[self.order], dtype=np.float64)
        col = key >> 21
        first = np.flatnonzero(np.r_[True, col[1:] != col[:-1]]) if len(col) else np.empty(0, np.int64)
        last = np.r_[first[1:], len(col)] - 1
        self.zlo = ijk[first, 2].copy()
        self.nz = ijk[last, 2] - self.zlo + 1
        self.zoff = np.r_[0, np.cumsum(self.nz + 1)[:-1]].astype(np.int64)
        rep = np.repeat(np.arange(len(first)), self.nz + 1)
        z = np.arange(len(rep)) - np.repeat(self.zoff, self.nz + 1) + np.repeat(self.zlo, self.nz + 1)
        self.zstart = np.searchsorted(key, (col[first][rep] << 21) | z).astype(np.int64)
        cx, cy = ijk[first, 0], ijk[first, 1]
        tkey = ((cx // TILE) << 21) | (cy // TILE)
        self.tile_keys, tile_of = np.unique(tkey, return_inverse=True)
        self.tile_cols = np.full((len(self.tile_keys), TILE * TILE), -1, np.int64)
        self.tile_cols[tile_of.ravel(), (cx % TILE) * TILE + cy % TILE] = np.arange(len(first))
        bits = max(4, int(np.ceil(np.log2(max(2 * len(self.tile_keys), 2)))))
        self.table = _build_table(self.tile_keys, bits)
        self.shift = np.uint64(64 - bits)

    def subset(self, keep: np.ndarray) -> PointGrid:
        """The grid of ``points[keep]`` ((M,) bool over the caller's points), same cells
        (its points come already sorted: no new sort of the whole cloud)."""
        kept = keep[self.order]
        new_index = np.cumsum(keep) - 1
        grid = PointGrid(self.points[kept], self.cell, self.corner)
        grid.order = new_index[self.order[kept]][grid.order]
        return grid

    def arrays(self) -> tuple:
        """The arrays the kernels read, in their order."""
        return (self.points, self.corner, self.zlo, self.nz, self.zoff, self.zstart, self.tile_keys, self.tile_cols,
                self.table, self.shift, self.cell)


@njit(cache=True, nogil=True)
def _jacobi3(a: np.ndarray, lam: np.ndarray, vec: np.ndarray) -> None:
    """Eigen-decomposition of the symmetric 3 x 3 ``a`` (overwritten): ``lam`` ascending,
    ``vec[:, i]`` the unit eigenvector of ``lam[i]``."""
    for i in range(3):
        for j in range(3):
            vec[i, j] = 1.0 if i == j else 0.0
    for _ in range(16):
        off = a[0, 1] * a[0, 1] + a[0, 2] * a[0, 2] + a[1, 2] * a[1, 2]
        scale = a[0, 0] * a[0, 0] + a[1, 1] * a[1, 1] + a[2, 2] * a[2, 2]
        if off <= 1e-26 * scale:  # off-diagonal below 1e-13 of the diagonal: converged
            break
        for p in range(2):
            for q in range(p + 1, 3):
                apq = a[p, q]
                if apq == 0.0:
                    continue
                theta = (a[q, q] - a[p, p]) / (2.0 * apq)
                t = 1.0 / (abs(theta) + np.sqrt(theta * theta + 1.0))
                if theta < 0.0:
                    t = -t
                c = 1.0 / np.sqrt(t * t + 1.0)
                s = t * c
                for k in range(3):
                    akp, akq = a[k, p], a[k, q]
                    a[k, p] = c * akp - s * akq
                    a[k, q] = s * akp + c * akq
                for k in range(3):
                    apk, aqk = a[p, k], a[q, k]
                    a[p, k] = c * apk - s * aqk
                    a[q, k] = s * apk + c * aqk
                for k in range(3):
                    vkp, vkq = vec[k, p], vec[k, q]
                    vec[k, p] = c * vkp - s * vkq
                    vec[k, q] = s * vkp + c * vkq
    for i in range(3):
        lam[i] = a[i, i]
    # Sort ascending (three elements: a small insertion sort of the columns).
    for i in range(1, 3):
        j = i
        while j > 0 and lam[j - 1] > lam[j]:
            lam[j - 1], lam[j] = lam[j], lam[j - 1]
            for k in range(3):
                vec[k, j - 1], vec[k, j] = vec[k, j], vec[k, j - 1]
            j -= 1


#: The closed-form normal is used when the gap between the two smallest eigenvalues is at
#: least this share of the spread of all three (else Jacobi: a normal's error grows as
#: rounding / gap, 1e-16 / 1e-6 here, well under the kernels' 1e-9 agreement with numpy).
_GAP = 1e-6


@njit(cache=True, nogil=True)
def _plane_normal(a: np.ndarray, n: np.ndarray) -> bool:
    """The unit eigenvector of the smallest eigenvalue of the symmetric 3 x 3 ``a`` into
    ``n`` (3,), in closed form; False (``n`` not written) where the two smallest
    eigenvalues are closer than ``_GAP`` of the spread (the caller's Jacobi decides)."""
    m = (a[0, 0] + a[1, 1] + a[2, 2]) / 3.0
    b00, b11, b22 = a[0, 0] - m, a[1, 1] - m, a[2, 2] - m
    p1 = a[0, 1] * a[0, 1] + a[0, 2] * a[0, 2] + a[1, 2] * a[1, 2]
    p2 = b00 * b00 + b11 * b11 + b22 * b22 + 2.0 * p1
    if not p2 > 0.0:
        return False  # a multiple of the identity: every direction is an eigenvector
    p = np.sqrt(p2 / 6.0)
    # Smith (1961): the eigenvalues m + 2 p cos(phi + 2 pi k / 3), phi = acos(det(B) / 2) / 3
    # with B = (a - m I) / p.
    det = (b00 * (b11 * b22 - a[1, 2] * a[1, 2]) - a[0, 1] * (a[0, 1] * b22 - a[1, 2] * a[0, 2])
           + a[0, 2] * (a[0, 1] * a[1, 2] - b11 * a[0, 2])) / (p * p * p)
    r = min(max(0.5 * det, -1.0), 1.0)
    phi = np.arccos(r) / 3.0
    lmax = m + 2.0 * p * np.cos(phi)
    lmin = m + 2.0 * p * np.cos(phi + 2.0 * np.pi / 3.0)
    lmid = 3.0 * m - lmax - lmin
    if not lmid - lmin >= _GAP * (lmax - lmin):
        return False
    if not _null_vector(a, lmin, n):
        return False
    # acos loses digits where lmin is near lmid relative to the spread (1e-11 of lmax for a
    # gap of 4e-6 of it: the normal 2e-7 rad off): once more with the Rayleigh quotient of
    # that normal, exact to the square of its error.
    rq = (n[0] * (a[0, 0] * n[0] + a[0, 1] * n[1] + a[0, 2] * n[2])
          + n[1] * (a[1, 0] * n[0] + a[1, 1] * n[1] + a[1, 2] * n[2])
          + n[2] * (a[2, 0] * n[0] + a[2, 1] * n[1] + a[2, 2] * n[2]))
    return _null_vector(a, rq, n)


@njit(cache=True, nogil=True)
def _null_vector(a: np.ndarray, lam: float, n: np.ndarray) -> bool:
    """The unit eigenvector of the simple eigenvalue ``lam`` of the symmetric 3 x 3 ``a`` into
    ``n``; False where all cross products vanish."""
    # The rows of a - lam I span the plane normal to the eigenvector: the longest cross
    # product of two of them is along it.
    lmin = lam
    r00, r01, r02 = a[0, 0] - lmin, a[0, 1], a[0, 2]
    r10, r11, r12 = a[1, 0], a[1, 1] - lmin, a[1, 2]
    r20, r21, r22 = a[2, 0], a[2, 1], a[2, 2] - lmin
    x0, x1, x2 = r01 * r12 - r02 * r11, r02 * r10 - r00 * r12, r00 * r11 - r01 * r10
    y0, y1, y2 = r01 * r22 - r02 * r21, r02 * r20 - r00 * r22, r00 * r21 - r01 * r20
    z0, z1, z2 = r11 * r22 - r12 * r21, r12 * r20 - r10 * r22, r10 * r21 - r11 * r20
    dx, dy, dz = x0 * x0 + x1 * x1 + x2 * x2, y0 * y0 + y1 * y1 + y2 * y2, z0 * z0 + z1 * z1 + z2 * z2
    if dx >= dy and dx >= dz:
        d, n[0], n[1], n[2] = dx, x0, x1, x2
    elif dy >= dz:
        d, n[0], n[1], n[2] = dy, y0, y1, y2
    else:
        d, n[0], n[1], n[2] = dz, z0, z1, z2
    if not d > 0.0:
        return False
    d = 1.0 / np.sqrt(d)
    n[0] *= d
    n[1] *= d
    n[2] *= d
    return True


@njit(cache=True, nogil=True)
def _in_plane(a: np.ndarray, n: np.ndarray, vec: np.ndarray, lam: np.ndarray) -> None:
    """With ``n`` (3,) a unit eigenvector of the symmetric 3 x 3 ``a``: ``vec[:, 0] = n`` and
    ``vec[:, 1:]`` the eigenvectors within the plane normal to ``n``, ``lam[1] <= lam[2]``
    their eigenvalues (from the 2 x 2 scatter in an orthonormal basis of the plane)."""
    # A basis (e, f) of the plane: e from the axis least along n.
    ax = 0
    if abs(n[1]) < abs(n[ax]):
        ax = 1
    if abs(n[2]) < abs(n[ax]):
        ax = 2
    # e = unit(axis - (axis . n) n)
    e0, e1, e2 = -n[ax] * n[0], -n[ax] * n[1], -n[ax] * n[2]
    if ax == 0:
        e0 += 1.0
    elif ax == 1:
        e1 += 1.0
    else:
        e2 += 1.0
    h = 1.0 / np.sqrt(e0 * e0 + e1 * e1 + e2 * e2)
    e0, e1, e2 = e0 * h, e1 * h, e2 * h
    f0, f1, f2 = n[1] * e2 - n[2] * e1, n[2] * e0 - n[0] * e2, n[0] * e1 - n[1] * e0
    ae0 = a[0, 0] * e0 + a[0, 1] * e1 + a[0, 2] * e2
    ae1 = a[1, 0] * e0 + a[1, 1] * e1 + a[1, 2] * e2
    ae2 = a[2, 0] * e0 + a[2, 1] * e1 + a[2, 2] * e2
    af0 = a[0, 0] * f0 + a[0, 1] * f1 + a[0, 2] * f2
    af1 = a[1, 0] * f0 + a[1, 1] * f1 + a[1, 2] * f2
    af2 = a[2, 0] * f0 + a[2, 1] * f1 + a[2, 2] * f2
    m00 = e0 * ae0 + e1 * ae1 + e2 * ae2
    m01 = f0 * ae0 + f1 * ae1 + f2 * ae2
    m11 = f0 * af0 + f1 * af1 + f2 * af2
    half = 0.5 * (m00 - m11)
    d = np.sqrt(half * half + m01 * m01)
    t = 0.5 * (m00 + m11)
    lam[1], lam[2] = t - d, t + d
    theta = 0.5 * np.arctan2(m01, half)  # the direction of lam[2] in (e, f)
    c, s = np.cos(theta), np.sin(theta)
    for k, (ek, fk) in enumerate(((e0, f0), (e1, f1), (e2, f2))):
        vec[k, 0] = n[k]
        vec[k, 2] = c * ek + s * fk
        vec[k, 1] = -s * ek + c * fk


@njit(cache=True, nogil=True)
def _knn(x0: float, x1: float, x2: float, pts: np.ndarray, corner: np.ndarray, zlo: np.ndarray, nz: np.ndarray, zoff: np.ndarray,
         zstart: np.ndarray, tile_keys: np.ndarray, tile_cols: np.ndarray, table: np.ndarray, shift: np.uint64,
         cell: float, kk: int, skip: np.int64, radius: float, max_ring: int, bd: np.ndarray, bi: np.ndarray,
         cut: np.ndarray) -> int:
    """The ``kk`` nearest sorted points to (x0, x1, x2), but ``skip`` and, where ``cut`` (4,)
    is not all zero, the points ``q`` with ``q . cut[:3] > cut[3]`` (a half-space left out),
    into ``bd`` (squared distances, ascending) and ``bi`` (sorted indices), searched ring by
    ring of cells.
    Returns 0: found; 1: no point within ``radius`` (only checked when ``radius`` is
    finite); 2: the search would need more than ``max_ring`` rings."""
    for j in range(kk):
        bd[j] = np.inf
        bi[j] = -1
    cutting = cut[0] != 0.0 or cut[1] != 0.0 or cut[2] != 0.0
    g0, g1, g2 = (x0 - corner[0]) / cell, (x1 - corner[1]) / cell, (x2 - corner[2]) / cell
    if not (abs(g0) < 4.0 * _LIMIT and abs(g1) < 4.0 * _LIMIT and abs(g2) < 4.0 * _LIMIT):
        return 2  # far outside the grid (beyond its int64 cells): the caller's KD-tree
    c0, c1, c2 = int(np.floor(g0)), int(np.floor(g1)), int(np.floor(g2))
    f0, f1, f2 = g0 - c0, g1 - c1, g2 - c2
    margin = min(f0, 1.0 - f0, f1, 1.0 - f1, f2, 1.0 - f2) * cell
    s0 = 1 if f0 >= 0.5 else -1
    s1 = 1 if f1 >= 0.5 else -1
    last_tile = np.int64(-1)
    last_index = np.int64(-1)
    for m in range(max_ring + 1):
        for i0 in range(2 * m + 1):
            # Offsets in the order 0, +-1, -+1, +-2, ...: the nearer side first, so that the
            # K + 1-th distance shrinks early and prunes the cells behind.
            d0 = ((i0 + 1) // 2) * (s0 if i0 % 2 == 1 else -s0)
            e0 = 0.0 if d0 == 0 else ((d0 - f0) if d0 > 0 else (f0 - d0 - 1.0)) * cell
            if e0 * e0 >= bd[kk - 1]:
                continue
            cx = c0 + d0
            for i1 in range(2 * m + 1):
                d1 = ((i1 + 1) // 2) * (s1 if i1 % 2 == 1 else -s1)
                e1 = 0.0 if d1 == 0 else ((d1 - f1) if d1 > 0 else (f1 - d1 - 1.0)) * cell
                e01 = e0 * e0 + e1 * e1
                if e01 >= bd[kk - 1]:
                    continue
                cy = c1 + d1
                if cx < 0 or cy < 0 or cx >= _LIMIT or cy >= _LIMIT:
                    continue  # outside the grid: no points
                tk = (np.int64(cx // TILE) << 21) | np.int64(cy // TILE)
                if tk != last_tile:
                    last_tile = tk
                    last_index = _find(table, tile_keys, tk, shift)
                if last_index < 0:
                    continue
                col = tile_cols[last_index, (cx % TILE) * TILE + cy % TILE]
                if col < 0:
                    continue
                z0, n = zlo[col], nz[col]
                edge = abs(d0) == m or abs(d1) == m
                d2 = -m
                while d2 <= m:
                    if not edge and d2 != -m and d2 != m:
                        d2 = m  # the ring's cells only: jump over the cube searched before
                    z = c2 + d2 - z0
                    if z >= n:
                        break
                    if z >= 0:
                        e2 = 0.0 if d2 == 0 else ((d2 - f2) if d2 > 0 else (f2 - d2 - 1.0)) * cell
                        if e01 + e2 * e2 < bd[kk - 1]:
                            o = zoff[col] + z
                            for p in range(zstart[o], zstart[o + 1]):
                                if p == skip:
                                    continue
                                q0, q1, q2 = pts[p, 0] - x0, pts[p, 1] - x1, pts[p, 2] - x2
                                dd = q0 * q0 + q1 * q1 + q2 * q2
                                if dd < bd[kk - 1]:
                                    if cutting and (pts[p, 0] * cut[0] + pts[p, 1] * cut[1]
                                                    + pts[p, 2] * cut[2] > cut[3]):
                                        continue
                                    j = kk - 1
                                    while j > 0 and bd[j - 1] > dd:
                                        bd[j] = bd[j - 1]
                                        bi[j] = bi[j - 1]
                                        j -= 1
                                    bd[j] = dd
                                    bi[j] = p
                    d2 += 1
        covered = margin + m * cell  # every point nearer than this has been seen
        if bd[kk - 1] <= covered * covered:
            return 0
        if covered >= radius and not bd[0] < radius * radius:
            return 1
    return 2


@njit(cache=True, parallel=True, nogil=True)
def local_planes(rows: np.ndarray, xyz: np.ndarray, skip: np.ndarray, cut: np.ndarray, label: np.ndarray, pts: np.ndarray,
                 corner: np.ndarray,
                 zlo: np.ndarray, nz: np.ndarray, zoff: np.ndarray, zstart: np.ndarray, tile_keys: np.ndarray,
                 tile_cols: np.ndarray, table: np.ndarray, shift: np.uint64, cell: float, k: int, near: int,
                 max_ring: int, normals: np.ndarray, radius: float, min_var: float,
                 fid: np.ndarray, s_out: np.ndarray, scatter_out: np.ndarray, var_out: np.ndarray,
                 normal_out: np.ndarray, rho_out: np.ndarray, nearest_out: np.ndarray, offset_out: np.ndarray,
                 status: np.ndarray) -> None:
    """The reading of :meth:`~.step7_local_surface.LocalSurface._raw` at the rows ``rows``
    of (N, 3) ``xyz`` (the outputs' other rows are not written).

    Args:
        rows: (R,) int64 rows of ``xyz`` to read, in the order they are read (the grid's:
            neighbouring points one after the other read the same cells while cached).
        xyz: (N, 3) query points, metres.
        skip: (N,) sorted index of a stored point left out of each point's neighbours
            (leave-one-out), -1 for none.
        cut: (N, 4) per point a half-space of stored points left out of its neighbours,
            those ``q`` with ``q . cut[i, :3] > cut[i, 3]`` (a hole's edge emulated, metres);
            all zero: none; (0, 4): none for any point.
        label: (M,) façade of each sorted stored point (-1: none).
        pts ... cell: the :class:`PointGrid` of the stored points (``PointGrid.arrays()``).
        k: K (the plane's neighbours; K + 1 are searched, the last for the taper).
        near: ``rho`` is the distance to the ``near + 1``-th nearest stored point.
        max_ring: rings of cells searched at most (``MAX_RING``).
        normals: (F, 3) façade normals (F may be 0).
        radius: points without a stored point nearer than this are not read (``status``
            1); inf: all are.
        min_var: floor of variances, m^2.
        fid, s_out, scatter_out, var_out, normal_out, rho_out: (N,) / (N, 3) outputs as
            ``_raw``'s (uncalibrated), written where ``status`` is 0.
        nearest_out: (N,) distance to the nearest stored point, metres (where ``status`` is 0).
        offset_out: (N,) distance of the point from its neighbours' weighted centroid within
            the plane, metres: the lever arm of a tilt of the plane (where ``status`` is 0).
        status: (N,) int8 output: 0 read, 1 no stored point within ``radius``, 2 not
            searched far enough (``max_ring``).
    """
    n = len(rows)
    nchunks = (n + _BATCH - 1) // _BATCH
    for b in prange(nchunks):
        _local_planes_range(b * _BATCH, min(n, (b + 1) * _BATCH), rows, xyz, skip, cut, label, pts, corner, zlo, nz, zoff, zstart,
                            tile_keys, tile_cols, table, shift, cell, k, near, max_ring, normals, radius, min_var, fid, s_out, scatter_out, var_out, normal_out,
                            rho_out, nearest_out, offset_out, status)


@njit(cache=True, nogil=True)
def _local_planes_range(lo: int, hi: int, rows: np.ndarray, xyz: np.ndarray, skip: np.ndarray, cut: np.ndarray,
                        label: np.ndarray, pts: np.ndarray,
                        corner: np.ndarray, zlo: np.ndarray, nz: np.ndarray, zoff: np.ndarray, zstart: np.ndarray, tile_keys: np.ndarray,
                        tile_cols: np.ndarray, table: np.ndarray, shift: np.uint64, cell: float, k: int, near: int,
                        max_ring: int, normals: np.ndarray, radius: float, min_var: float, fid: np.ndarray,
                        s_out: np.ndarray, scatter_out: np.ndarray, var_out: np.ndarray, normal_out: np.ndarray,
                        rho_out: np.ndarray, nearest_out: np.ndarray, offset_out: np.ndarray, status: np.ndarray) -> None:
    """:func:`local_planes` of the rows ``rows[lo:hi]`` (scratch arrays allocated once)."""
    kk = k + 1
    nf = len(normals)
    bd = np.empty(kk)
    bi = np.empty(kk, np.int64)
    w = np.empty(k)
    r = np.empty(k)
    cov = np.empty((3, 3))
    lam = np.empty(3)
    vec = np.empty((3, 3))
    nv = np.empty(3)
    c = np.empty(3)
    none = np.zeros(4)
    for t in range(lo, hi):
        i = rows[t]
        st = _knn(xyz[i, 0], xyz[i, 1], xyz[i, 2], pts, corner, zlo, nz, zoff, zstart, tile_keys, tile_cols, table, shift,
                  cell, kk, skip[i], radius, max_ring, bd, bi, cut[i] if len(cut) else none)
        status[i] = st
        if st != 0:
            continue
        if bi[kk - 1] < 0:  # fewer stored points than K + 1: the caller's numpy path reads these
            status[i] = 2
            continue
        taper = max(np.sqrt(bd[kk - 1]), 1e-9)
        for j in range(k):
            t = 1.0 - bd[j] / (taper * taper)
            t = min(max(t, 0.0), 1.0)
            w[j] = t * t
        w[0] = max(w[0], 1e-6)
        sw = 0.0
        sigma2 = 0.0
        for rew in range(2):
            sw = 0.0
            c[0] = c[1] = c[2] = 0.0
            for j in range(k):
                p = bi[j]
                sw += w[j]
                for a in range(3):
                    c[a] += w[j] * pts[p, a]
            for a in range(3):
                c[a] /= sw
            for a in range(3):
                for b in range(3):
                    cov[a, b] = 0.0
            for j in range(k):
                p = bi[j]
                e0, e1, e2 = pts[p, 0] - c[0], pts[p, 1] - c[1], pts[p, 2] - c[2]
                wj = w[j]
                cov[0, 0] += wj * e0 * e0
                cov[0, 1] += wj * e0 * e1
                cov[0, 2] += wj * e0 * e2
                cov[1, 1] += wj * e1 * e1
                cov[1, 2] += wj * e1 * e2
                cov[2, 2] += wj * e2 * e2
            cov[1, 0], cov[2, 0], cov[2, 1] = cov[0, 1], cov[0, 2], cov[1, 2]
            for a in range(3):
                for b in range(3):
                    cov[a, b] /= sw
            if _plane_normal(cov, nv):
                if rew == 1:  # the leverage's in-plane eigenvalues and directions
                    _in_plane(cov, nv, vec, lam)
                else:
                    vec[0, 0], vec[1, 0], vec[2, 0] = nv[0], nv[1], nv[2]
            else:
                _jacobi3(cov, lam, vec)
            sigma2 = 0.0
            for j in range(k):
                p = bi[j]
                r[j] = ((pts[p, 0] - c[0]) * vec[0, 0] + (pts[p, 1] - c[1]) * vec[1, 0]
                        + (pts[p, 2] - c[2]) * vec[2, 0])
                sigma2 += w[j] * r[j] * r[j]
            sigma2 /= sw
            if rew == 0:
                for j in range(k):
                    w[j] = w[j] / (1.0 + r[j] * r[j] / (4.0 * sigma2 + min_var))
        sww = 0.0
        for j in range(k):
            sww += w[j] * w[j]
        n_eff = sw * sw / sww
        scatter = max(sigma2 * n_eff / max(n_eff - 3.0, 1.0), min_var)
        o0, o1, o2 = xyz[i, 0] - c[0], xyz[i, 1] - c[1], xyz[i, 2] - c[2]
        s = o0 * vec[0, 0] + o1 * vec[1, 0] + o2 * vec[2, 0]
        u1 = o0 * vec[0, 1] + o1 * vec[1, 1] + o2 * vec[2, 1]
        u2 = o0 * vec[0, 2] + o1 * vec[1, 2] + o2 * vec[2, 2]
        lev = u1 * u1 / max(lam[1], min_var) + u2 * u2 / max(lam[2], min_var)
        # The façade of the nearest neighbour that belongs to one (-1: none does).
        f = -1
        for j in range(kk):
            if label[bi[j]] >= 0:
                f = label[bi[j]]
                break
        sign = 1.0
        if nf > 0:
            fn = max(f, 0)
            if vec[0, 0] * normals[fn, 0] + vec[1, 0] * normals[fn, 1] + vec[2, 0] * normals[fn, 2] < 0.0:
                sign = -1.0
        fid[i] = f
        s_out[i] = sign * s
        scatter_out[i] = scatter
        var_out[i] = scatter * (1.0 + lev) / n_eff
        for a in range(3):
            normal_out[i, a] = sign * vec[a, 0]
        rho_out[i] = np.sqrt(bd[near]) if f >= 0 else np.inf
        nearest_out[i] = np.sqrt(bd[0])
        offset_out[i] = np.sqrt(u1 * u1 + u2 * u2)


#: :func:`local_planes` on one core (``prange`` runs as ``range``): small calls.
local_planes_serial = serial_twin(local_planes, 'local_planes_serial')


_SERIAL = threading.local()


@contextlib.contextmanager
def serial_kernels() -> Iterator[None]:
    """Within it, this thread's readings run on one core (:func:`local_planes_serial`) whatever
    their size: a background build of a reading leaves the other core to the queries."""
    before = getattr(_SERIAL, 'on', False)
    _SERIAL.on = True
    try:
        yield
    finally:
        _SERIAL.on = before


_PARALLEL = threading.Lock()


def planes(rows: np.ndarray, *args: object) -> None:
    """:func:`local_planes` on both cores for ``SERIAL_BELOW`` rows or more, one call at a
    time (outside :func:`serial_kernels`), else :func:`local_planes_serial` (same arguments)."""
    if len(rows) >= SERIAL_BELOW and not getattr(_SERIAL, 'on', False):
        with _PARALLEL:
            local_planes(rows, *args)
    else:
        local_planes_serial(rows, *args)
