"""Compiled loops of the building selection (:mod:`.building_points`; numba, one core).

The wall windows' sums (steps 3-5) are taken one window at a time, over the points of its
cells, in the order ``numpy.bincount`` took them over (point, window) pairs before (the
offsets of :func:`window_offsets` in turn, the points of each cell by ascending index), with
the same arithmetic (no fused multiply-adds, no reordered sums): the selection is bit for
bit what the vectorised numpy version gave, without its ~9 x M pair arrays, sorted lookups
and scattered sums. The trigonometry of the windows' lines stays in numpy (whose SIMD code
may round otherwise than libm), between the calls. The ground's cells (steps 1-2) are
summed in a dense grid, in point order, likewise.

Serial and ``nogil``: a cloud's selection takes tens of milliseconds, Patchwork++ holds the
GIL for a third of it, and the node maps on the other core meanwhile; a thread pool of
numba's own (OpenMP or workqueue) would compete with that, and its workqueue layer aborts
when two threads launch kernels at once.

Shapes: M points, C occupied cells (= windows), K cell offsets. The points are read in cell
order (the caller gathers them by ``members``, :func:`group_cells`): the points of cell
``c`` are rows ``start[c]:start[c + 1]``, by ascending index.
"""

from __future__ import annotations

import numpy as np
from numba import njit


def window_offsets(radius: int) -> np.ndarray:
    """(K, 2) int64 cell offsets (dx, dy) of a window, in the order its points are summed."""
    return np.array([(dx, dy) for dx in range(-radius, radius + 1) for dy in range(-radius, radius + 1)],
                     dtype=np.int64).reshape(-1, 2)


@njit(cache=True, nogil=True)
def group_cells(codes: np.ndarray, order: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cells of points from their cell codes in order.

    Args:
        codes: (M,) int64 each point's cell code, sorted.
        order: (M,) int64 the points in that order (by ascending index for equal codes).

    Returns:
        ``(cells, start, of_point)``: (C,) int64 the distinct codes, (C + 1,) int64 the
        bounds of each cell's points in ``order`` (which is ``members``), (M,) int64 each
        point's cell.
    """
    m = len(codes)
    cells = np.empty(m, dtype=np.int64)
    start = np.empty(m + 1, dtype=np.int64)
    of_point = np.empty(m, dtype=np.int64)
    c = -1
    for i in range(m):
        if c < 0 or codes[i] != cells[c]:
            c += 1
            cells[c] = codes[i]
            start[c] = i
        of_point[order[i]] = c
    start[c + 1] = m
    return cells[:c + 1].copy(), start[:c + 2].copy(), of_point


@njit(cache=True, nogil=True)
def neighbours(codes: np.ndarray, rows: np.ndarray, deltas: np.ndarray) -> np.ndarray:
    """(R, K) int64 index of the cell whose code is ``codes[rows[r]] + deltas[k]``, -1 where
    there is none.

    Args:
        codes: (C,) int64 sorted distinct cell codes.
        rows: (R,) int64 ascending indices of the cells asked about.
        deltas: (K,) int64 code steps.
    """
    n = len(codes)
    out = np.full((len(rows), len(deltas)), -1, dtype=np.int64)
    for k in range(len(deltas)):
        step = deltas[k]
        j = 0
        for i in range(len(rows)):
            target = codes[rows[i]] + step
            while j < n and codes[j] < target:
                j += 1
            if j == n:
                break
            if codes[j] == target:
                out[i, k] = j
    return out


@njit(cache=True, nogil=True)
def moments(xy: np.ndarray, centres: np.ndarray, start: np.ndarray, nbr: np.ndarray,
            mean0: np.ndarray, normal0: np.ndarray, band: float, first: bool
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """One pass of the windows' line fits: weighted mean and second moments of their points.

    Args:
        xy: (M, 2) points in cell order, metres. centres: (C, 2) cell centres.
        start: (C + 1,) the cells' rows (module docstring). nbr: (C, K) each window's cells.
        mean0, normal0: (C, 2) the last pass's mean (relative to the centre) and unit normal
            of each window's line; the points within ``band`` of it weigh 1, the others 0.
        first: True on the first pass: every point weighs 1 (``mean0``, ``normal0`` unread).

    Returns:
        ``(total, mean, sxx, syy, sxy)``: (C,) weight (at least 1e-12), (C, 2) mean relative
        to the centre, (C,) each of the weighted second central moments.
    """
    n_cells = len(centres)
    total = np.empty(n_cells)
    mean = np.empty((n_cells, 2))
    sxx = np.empty(n_cells)
    syy = np.empty(n_cells)
    sxy = np.empty(n_cells)
    for w in range(n_cells):
        cx = centres[w, 0]
        cy = centres[w, 1]
        m0 = mean0[w, 0]
        m1 = mean0[w, 1]
        n0 = normal0[w, 0]
        n1 = normal0[w, 1]
        t = 0.0
        sx = 0.0
        sy = 0.0
        for k in range(nbr.shape[1]):
            c = nbr[w, k]
            if c < 0:
                continue
            for j in range(start[c], start[c + 1]):
                rx = xy[j, 0] - cx
                ry = xy[j, 1] - cy
                wgt = 1.0 if first or abs((rx - m0) * n0 + (ry - m1) * n1) < band else 0.0
                t += wgt
                sx += wgt * rx
                sy += wgt * ry
        t = max(t, 1e-12)
        ax = sx / t
        ay = sy / t
        a = 0.0
        b = 0.0
        e = 0.0
        for k in range(nbr.shape[1]):
            c = nbr[w, k]
            if c < 0:
                continue
            for j in range(start[c], start[c + 1]):
                rx = xy[j, 0] - cx
                ry = xy[j, 1] - cy
                wgt = 1.0 if first or abs((rx - m0) * n0 + (ry - m1) * n1) < band else 0.0
                dx = rx - ax
                dy = ry - ay
                a += wgt * (dx * dx)  # numpy's weight * d ** 2: a weight of 0 adds a zero, as skipping
                b += wgt * (dy * dy)
                e += wgt * dx * dy
        total[w] = t
        mean[w, 0] = ax
        mean[w, 1] = ay
        sxx[w] = a / t
        syy[w] = b / t
        sxy[w] = e / t
    return total, mean, sxx, syy, sxy


@njit(cache=True, nogil=True)
def band_stats(xyz: np.ndarray, centres: np.ndarray, start: np.ndarray, nbr: np.ndarray,
               mean: np.ndarray, normal: np.ndarray, band: float, at_top: np.ndarray, origin: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """What each window's band holds: the points within ``band`` of its line.

    Args:
        xyz: (M, 3) points in cell order, metres. centres, start, nbr: as :func:`moments`.
        mean, normal: (C, 2) each window's line (the last pass's).
        band: half-width of the band, metres.
        at_top: (M,) bool the points at the top of the field of view (may be all False), in
            cell order.
        origin: (M, 2) x, y of each point's sensor origin (read where ``at_top``), in cell order.

    Returns:
        ``(points, count, sq, top, bottom, n_top, origin_sum)``: (C,) int64 points of the
        window, (C,) float band points, (C,) sum of their squared distances to the line,
        (C,) their highest and lowest z (-inf, inf if none), (C,) int64 band points at the
        top of the view and (C, 2) the sum of their origins.
    """
    n_cells = len(centres)
    points = np.zeros(n_cells, dtype=np.int64)
    count = np.zeros(n_cells)
    sq = np.zeros(n_cells)
    top = np.full(n_cells, -np.inf)
    bottom = np.full(n_cells, np.inf)
    n_top = np.zeros(n_cells, dtype=np.int64)
    origin_sum = np.zeros((n_cells, 2))
    for w in range(n_cells):
        cx = centres[w, 0]
        cy = centres[w, 1]
        m0 = mean[w, 0]
        m1 = mean[w, 1]
        n0 = normal[w, 0]
        n1 = normal[w, 1]
        npts = 0
        cnt = 0.0
        s = 0.0
        hi = -np.inf
        lo = np.inf
        nt = 0
        ox = 0.0
        oy = 0.0
        for k in range(nbr.shape[1]):
            c = nbr[w, k]
            if c < 0:
                continue
            npts += start[c + 1] - start[c]
            for j in range(start[c], start[c + 1]):
                dist = (xyz[j, 0] - cx - m0) * n0 + (xyz[j, 1] - cy - m1) * n1
                if not abs(dist) < band:
                    continue
                cnt += 1.0
                s += dist * dist
                z = xyz[j, 2]
                hi = max(hi, z)
                lo = min(lo, z)
                if at_top[j]:
                    nt += 1
                    ox += origin[j, 0]
                    oy += origin[j, 1]
        points[w] = npts
        count[w] = cnt
        sq[w] = s
        top[w] = hi
        bottom[w] = lo
        n_top[w] = nt
        origin_sum[w, 0] = ox
        origin_sum[w, 1] = oy
    return points, count, sq, top, bottom, n_top, origin_sum


@njit(cache=True, nogil=True)
def band_points(xy: np.ndarray, centres: np.ndarray, start: np.ndarray, nbr: np.ndarray,
                mean: np.ndarray, normal: np.ndarray, band: float, windows: np.ndarray) -> np.ndarray:
    """(M,) bool, in cell order: the points within ``band`` of the line of any of the ``windows``
    (int64 indices)."""
    keep = np.zeros(len(xy), dtype=np.bool_)
    for i in range(len(windows)):
        w = windows[i]
        cx = centres[w, 0]
        cy = centres[w, 1]
        m0 = mean[w, 0]
        m1 = mean[w, 1]
        n0 = normal[w, 0]
        n1 = normal[w, 1]
        for k in range(nbr.shape[1]):
            c = nbr[w, k]
            if c < 0:
                continue
            for j in range(start[c], start[c + 1]):
                if abs((xy[j, 0] - cx - m0) * n0 + (xy[j, 1] - cy - m1) * n1) < band:
                    keep[j] = True
    return keep


@njit(cache=True, nogil=True)
def links(idx: np.ndarray, wall: np.ndarray, nbr: np.ndarray, centroid: np.ndarray, normal: np.ndarray,
          cos_max: float, band: float) -> tuple[np.ndarray, np.ndarray]:
    """Links between wall windows: planes within the angle, centroids in each other's band.

    Args:
        idx: (W,) int64 the wall windows. wall: (C,) bool. nbr: (W, K) the cells at the link
            offsets of each of them (-1 where empty).
        centroid, normal: (C, 2) each window's line.
        cos_max: least |cos| of the angle between linked planes. band: metres.

    Returns:
        ``(a, b)``: (L,) int64 the linked pairs of windows.
    """
    a = np.empty(len(idx) * nbr.shape[1], dtype=np.int64)
    b = np.empty_like(a)
    n = 0
    for k in range(nbr.shape[1]):
        for i in range(len(idx)):
            u = idx[i]
            v = nbr[i, k]
            if v < 0 or not wall[v]:
                continue
            sx = centroid[v, 0] - centroid[u, 0]
            sy = centroid[v, 1] - centroid[u, 1]
            if (abs(normal[u, 0] * normal[v, 0] + normal[u, 1] * normal[v, 1]) >= cos_max
                    and abs(sx * normal[u, 0] + sy * normal[u, 1]) < band
                    and abs(sx * normal[v, 0] + sy * normal[v, 1]) < band):
                a[n] = u
                b[n] = v
                n += 1
    return a[:n].copy(), b[:n].copy()


# ----------------------------------------------------------------------------------------
# Ground (steps 1-2): cells of a dense grid, summed in point order as numpy did
# ----------------------------------------------------------------------------------------
#: Largest dense grid (cells) the ground kernels allocate; wider clouds take numpy's path.
MAX_GRID = 1 << 24


@njit(cache=True, nogil=True)
def column_means(a: np.ndarray) -> tuple[float, float]:
    """The means of the two columns of (N, 2) ``a``, summed row by row (numpy's
    ``a.mean(axis=0)`` on a C-contiguous array)."""
    s0 = 0.0
    s1 = 0.0
    for i in range(a.shape[0]):
        s0 += a[i, 0]
        s1 += a[i, 1]
    return s0 / a.shape[0], s1 / a.shape[0]


@njit(cache=True, nogil=True)
def lowest_per_cell(xyz: np.ndarray, cx: float, cy: float, radius: float, cell: float, least: int) -> np.ndarray:
    """The lowest z of each occupied ``cell`` of the points within ``radius`` (x, y) of
    (``cx``, ``cy``) (of all points if fewer than ``least`` are), in no particular order;
    empty if the grid would exceed :data:`MAX_GRID` cells (the caller takes numpy's path).

    Args:
        xyz: (N, 3) points, metres.
    """
    n = len(xyz)
    near = np.empty(n, dtype=np.bool_)
    r2 = radius ** 2
    m = 0
    for i in range(n):
        dx = xyz[i, 0] - cx
        dy = xyz[i, 1] - cy
        near[i] = dx * dx + dy * dy <= r2
        m += near[i]
    if m < least:
        near[:] = True
    lo0 = lo1 = np.iinfo(np.int64).max
    hi0 = hi1 = np.iinfo(np.int64).min
    kx = np.empty(n, dtype=np.int64)
    ky = np.empty(n, dtype=np.int64)
    for i in range(n):
        if near[i]:
            kx[i] = np.int64(np.floor(xyz[i, 0] / cell))
            ky[i] = np.int64(np.floor(xyz[i, 1] / cell))
            lo0 = min(lo0, kx[i])
            hi0 = max(hi0, kx[i])
            lo1 = min(lo1, ky[i])
            hi1 = max(hi1, ky[i])
    w0 = hi0 - lo0 + 1
    w1 = hi1 - lo1 + 1
    if w0 * w1 > MAX_GRID:
        return np.empty(0)
    low = np.full(w0 * w1, np.inf)
    for i in range(n):
        if near[i]:
            c = (kx[i] - lo0) * w1 + (ky[i] - lo1)
            low[c] = min(low[c], xyz[i, 2])
    out = np.empty(len(low))
    k = 0
    for c in range(len(low)):
        if low[c] < np.inf:
            out[k] = low[c]
            k += 1
    return out[:k].copy()


@njit(cache=True, nogil=True)
def mean_height_per_cell(xyz: np.ndarray, cell: float) -> tuple[np.ndarray, np.ndarray]:
    """The occupied ``cell`` s of (G, 3) points, by (x, y) key, and the mean z of each.

    Returns:
        ``(keys, height)``: (C, 2) int64 and (C,) metres; both empty if the grid would exceed
        :data:`MAX_GRID` cells (the caller takes numpy's path).
    """
    n = len(xyz)
    kx = np.empty(n, dtype=np.int64)
    ky = np.empty(n, dtype=np.int64)
    for i in range(n):
        kx[i] = np.int64(np.floor(xyz[i, 0] / cell))
        ky[i] = np.int64(np.floor(xyz[i, 1] / cell))
    lo0 = kx.min()
    lo1 = ky.min()
    w0 = kx.max() - lo0 + 1
    w1 = ky.max() - lo1 + 1
    if w0 * w1 > MAX_GRID:
        return np.empty((0, 2), dtype=np.int64), np.empty(0)
    total = np.zeros(w0 * w1)
    count = np.zeros(w0 * w1, dtype=np.int64)
    for i in range(n):
        c = (kx[i] - lo0) * w1 + (ky[i] - lo1)
        total[c] += xyz[i, 2]
        count[c] += 1
    keys = np.empty((n, 2), dtype=np.int64)
    height = np.empty(n)
    k = 0
    for c in range(w0 * w1):
        if count[c]:
            keys[k, 0] = c // w1 + lo0
            keys[k, 1] = c % w1 + lo1
            height[k] = total[c] / count[c]
            k += 1
    return keys[:k].copy(), height[:k].copy()
