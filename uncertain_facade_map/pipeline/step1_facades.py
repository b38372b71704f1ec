"""Façade extraction: buildings split into façades, each in its own 2.5D frame.

Paper, Section III: "For each individual building, each façade plane is extracted by using
a Random Sample Consensus (RANSAC) approach, where points are allocated to the
corresponding façades"; Section III.A / IV.B: the façade normal is "determined by a
principal component analysis (PCA), using the eigenvector belonging to the smallest
component", and a map point becomes P = {x, d}: (u, v) on the plane and the depth d along
the normal (:class:`~uncertain_facade_map.datatypes.FacadeFrame`).

Pipeline of :func:`extract_facades` (one building, all coordinates metres, map frame):

1. **Sequential RANSAC** on a random subsample of at most ``ransac_sample`` points.
   Each round draws ``ransac_iterations`` hypotheses, planes through 3 points: a random
   point not yet explained and two random points of its voxel (*local* sampling; voxels
   of 1 m, halved or doubled until a typical voxel holds 10 to 60 subsample points).
   Three points drawn from the whole building would all lie on a small side wall only
   once in thousands of draws. Hypotheses tilted more than ``max_tilt_deg`` from
   vertical are rejected before scoring. Scoring is preemptive: all hypotheses are
   counted on 2 000 random pool points, the best 8 on the whole pool; the score is the
   number of points within ``ransac_threshold``. The winner is refined by PCA of its
   inliers (3 passes), cut to its largest connected piece (8-connected cells of
   ``2 * extent_margin`` in (u, v)) and turned outwards (5.). Rejected, with their
   inliers taken out of the pool: pieces narrower than 0.5 m (points along a line, e.g.
   a wall's foot, fit any plane through it), and pieces facing within 60 degrees of an
   earlier plane and lying mostly in its band within 0.25 m of its box (the remains of
   its detail, e.g. the foot of a sloped plinth). *Choice:* instead of only its inliers,
   a round removes every pool point in the plane's band
   (``-band_back <= d <= band_front``) within the piece's box, so balcony fronts, oriel
   sides, window backs, slopes and round bays of a found wall are never proposed as
   planes of their own; beyond the box nothing is removed, so that a short or oblique
   adjacent wall (a 1 m chamfer) is still found. Rounds stop after ``max_facades``
   planes or when the best plane has fewer than ``min_facade_points / 2`` inliers,
   scaled to the subsample. Boxes are robust: the 10th point from either end (at most
   the 0.2 % quantile), so that stray returns on a plane's extension do not stretch it.
2. **Merging**: a plane within ``merge_angle_deg`` of a larger one (same outward side),
   closer than ``merge_offset`` to it along its normal and no further than
   ``merge_offset`` from its box in ``u`` joins it: one façade (balcony and oriel fronts
   are depth layers of their wall, as in the paper's GMM), unless it lies beyond the
   allocation band of the group's plane with at least a fifth of the largest plane's
   support (then it is a façade of its own: its points would otherwise belong to none;
   a smaller one, such as a room seen through windows, stays and loses them), or unless
   it lies ``STOREY_OFFSET`` (0.5 m) or more in front of or behind the group's plane with
   that support and each occupies its own part of the wall (:func:`side_by_side`; upper
   storeys over a set-back ground floor: as a layer, the storeys' holes would be filled
   from the ground floor's depth and the ground floor's extent would leave them out;
   balcony fronts, oriels, window backs and recessed entrances lie among the wall's
   cells and stay its layers). *Choice:* the façade's plane
   is the group's back-most plane with at least a fifth of the largest one's support
   and at least half its width in ``u``, not simply the largest: behind deep balconies a
   wall can have fewer inliers than the balcony fronts, and the band must reach back
   from the wall; but a wall spans its façade, so a narrow plane behind it (a recessed
   entrance, a shop's back wall seen through its window, as on real scans) is not one.
3. **Allocation** (:func:`assign_to_facades`, also used for incremental mapping): a point
   belongs to a façade if ``-band_back <= d <= band_front`` and (u, v) lies within the
   façade's *plane extent* grown by ``extent_margin``; among several such façades the
   smallest ``|d|`` wins (ties: the earlier façade), which settles building corners.
   Horizontal balcony undersides lie in the band of the wall they stand out of.
   *Choice:* the plane extent (``ExtractedFacade.plane_extent``) is the robust box of
   the building's points within ``ransac_threshold`` of the final plane near the
   subsample's extent -- the wall itself. It does not depend on the allocation, so the
   allocation is one pass and cannot creep: an extent taken from the allocated points
   grows by up to the margin with every pass along anything in the band (an adjacent
   wall's balconies, a plinth), and a fixed point of it swallows them.
   ``ExtractedFacade.extent`` is the box of all allocated points, as documented.
4. **Frames**: the paper derives the normal "by the PCA using all façade points".
   *Choice:* PCA of all allocated points is pulled by balconies, oriels and slopes, so
   the final normal is the PCA of the allocated points within ``ransac_threshold`` of
   the main plane (the façade's dominant depth layer, like the paper's main GMM
   component), iterated; then refined within half the threshold from two starts, the
   least-squares plane and the mean point normal of its points at their densest depth
   layer, keeping the one with more points (on a narrow strip of wall the least-squares
   plane can settle obliquely across the wall and the window backs, 5 degrees off; the
   point normals of both layers agree); then once more within three robust sigmas of
   the wall's noise. These points are taken from the subsample's allocation: tens of
   thousands of points fix a plane to well under 0.01 degree, the full cloud would only
   cost time. Façades with fewer than ``min_facade_points`` allocated points are
   dropped (and the rest allocated again). The frame origin is the projection of the
   allocated points' centroid onto the plane.
5. **Outward normal**: towards the mean sensor origin of the plane's points if the sensor
   origins are known (positive mean of ``(origin - point) . n``). *Choice:* without
   them, not "away from the building's centroid" -- the points' centroid of a building
   scanned from one street lies near its street façade, in front of it if it has deep
   balconies -- but from the building's shape around the plane, within its extent (plus
   margin): the side with fewer of the building's points further than the wider side
   of the band (the other walls lie behind a wall), counting with them the points of
   the other buildings within 40 m along the wall and of it, on the side opposite
   (what a sensor saw beyond a wall, such as the houses across the street, lies in
   front of it: it saw the wall from there; a building with 30 % of those points
   within the band straddles the plane, a neighbour in line with the wall whose side
   walls lie behind the line, and does not vote); if that is undecided (a lone wall),
   the side with more points between 0.35 m and that distance (balconies and oriels
   stand out, window recesses are shallower); else up (``n_z >= 0``, right for walls
   leaning back). Then a sloped plane (tilted more than 15 degrees: a roof band, a
   mansard, a sloped plinth) with a vertical wall adjoining it (inliers within 3 m,
   horizontal normals within 30 degrees; found with it or before) faces, horizontally,
   like that wall: below and behind a roof band lies the same building, so its shape
   cannot tell its outside, and "up" would be wrong for a face that looks down.
6. **Point normals** (:func:`point_normals`): PCA of the ``normal_neighbours`` nearest
   points (the point itself included), once per building, with a closed-form 3x3
   eigen-solver; ``normal_cos = |n_point . n_facade|`` (the paper's eq. 8 ``n_z``).
   Note the noise floor of small neighbourhoods: at 2 cm noise and 300 points/m² the
   median error is about 11 degrees for k = 10, 5 for k = 20 and 3 for k = 30.

:func:`split_buildings` gives the per-point building label that the pipeline calls
:func:`extract_facades` with.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np
from scipy import ndimage
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from ..datatypes import ExtractedFacade, FacadeFrame
from ..errors import InputError
from ..params import ExtractionParams
from ..threads import kdtree_workers

#: Points on which all hypotheses are scored before the best few are scored on the pool.
_PREEMPTIVE_POINTS = 2000
#: Hypotheses scored on the whole pool.
_PREEMPTIVE_KEEP = 8
#: Points (at most a share) of a plane left out at each end of its extent (stray returns).
_TRIM_POINTS = 10
_TRIM = 0.002
#: Depth (m) beyond which a point in a façade's band is taken for a protrusion or a recess
#: (window recesses are shallower) when the outward side must be guessed from the shape.
_PROTRUSION = 0.35
#: A group's façade plane has at least this share of its largest plane's support and width.
_MAIN_SUPPORT_SHARE = 0.2
_MAIN_WIDTH_SHARE = 0.5
#: Other buildings' points this far (m) beyond a wall's ends and from its plane vote on its outward side.
_CONTEXT_REACH = 40.0
#: A plane within 60 degrees of an earlier one's normal can be that façade's detail.
_DETAIL_COS = 0.5
#: Planes narrower than this in u or v (m) are slivers, e.g. the points along a wall's foot.
_MIN_SIDE = 0.5
#: How far (m) beyond an earlier plane's box a RANSAC plane's points still count as at
#: its edge (see ``_DETAIL_COS``).
_EDGE_TOLERANCE = 0.25
#: Two planes of one façade group at least this far apart along the normal (m), a storey's
#: setback rather than a window reveal, ...
STOREY_OFFSET = 0.5
#: ... are separate façades when each occupies its own part of the wall: at most this share
#: of either's occupied cells of ``_TILE_CELL`` metres lies within one cell of the other's.
#: Balcony fronts, oriels, window backs and recessed entrances lie among their wall's cells.
_TILE_SHARE = 0.5
_TILE_CELL = 0.5
#: Voxel (m) of the occupied-cell sketch a RANSAC plane keeps of its inliers (voxels of at
#: least two inliers: a stray return occupies nothing).
_SKETCH_VOXEL = 0.25
#: Without sensor origins, a plane tilted more than this from vertical (degrees; a roof band,
#: a mansard, a sloped plinth) faces like the vertical wall it adjoins: a wall within
#: ``_WALL_DEG`` of vertical whose horizontal normal lies within ``_ADJOIN_DEG`` of its own
#: (either sign) and whose inliers come within ``_ADJOIN_GAP`` metres of its inliers (the
#: nearest such wall). The gap is wide because the wall's round took the sloped plane's foot
#: out of the pool (its points up to ``band_back`` behind the wall: 2.8 m of slope at 20
#: degrees), and narrower than a building's depth, so that a band on the back crowns the back wall.
_TILTED_DEG = 15.0
_WALL_DEG = 10.0
_ADJOIN_DEG = 30.0
_ADJOIN_GAP = 3.0
#: Another building with at least this share of its points (near the wall) within the
#: wall's band straddles the wall's plane: a neighbour beside it (its street wall in line
#: with this one), not what the sensor saw beyond the wall; it does not vote.
_BESIDE_SHARE = 0.3
#: Least-squares refinement passes (RANSAC winner and final frames).
_REFINE_PASSES = 3
#: Points per chunk of the normal computation (memory: about chunk * k * 28 bytes).
_NORMAL_CHUNK = 200_000
#: Largest dense occupancy grid of :func:`split_buildings`; larger clouds use a sparse graph.
_MAX_DENSE_CELLS = 20_000_000


# ----------------------------------------------------------------------------------------
# Input checks
# ----------------------------------------------------------------------------------------
def _check_xyz(xyz: np.ndarray, name: str = 'xyz', *, allow_empty: bool = False) -> np.ndarray:
    """``xyz`` as an (N, 3) finite float64 array, or InputError naming ``name``."""
    try:
        arr = np.asarray(xyz, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(f'{name} must be an (N, 3) array of numbers: {exc}') from None
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise InputError(f'{name} must have shape (N, 3), got {arr.shape}')
    if not allow_empty and arr.shape[0] == 0:
        raise InputError(f'{name} is empty: no points to extract façades from')
    if np.isfinite(arr).all():
        return arr
    bad = ~np.isfinite(arr).all(axis=1)
    if bad.any():
        raise InputError(f'{name}: {int(bad.sum())} of {arr.shape[0]} points have NaN or infinite coordinates')
    return arr


# ----------------------------------------------------------------------------------------
# Normals
# ----------------------------------------------------------------------------------------
def _smallest_eigenvectors(a00: np.ndarray, a11: np.ndarray, a22: np.ndarray, a01: np.ndarray,
                           a02: np.ndarray, a12: np.ndarray) -> np.ndarray:
    """Unit eigenvectors of the smallest eigenvalue of symmetric 3x3 matrices.

    Closed form: trigonometric eigenvalues, the eigenvector as the longest cross product
    of two rows of ``C - lambda I``; several times faster than ``np.linalg.eigh`` on
    millions of matrices. Matrices where that cross product is lost in round-off (two
    equal smallest eigenvalues) fall back to ``eigh``.

    Args:
        a00, a11, a22, a01, a02, a12: (N,) float32 or float64, the six distinct entries of
            symmetric positive semi-definite matrices.

    Returns:
        (N, 3) float64 unit vectors, sign arbitrary.
    """
    q = (a00 + a11 + a22) / 3.0
    b00, b11, b22 = a00 - q, a11 - q, a22 - q
    p1 = a01 * a01 + a02 * a02 + a12 * a12
    p = np.sqrt((b00 * b00 + b11 * b11 + b22 * b22 + 2.0 * p1) / 6.0)
    # det(B / p) / 2 with B = A - q I, computed as det(B) / (2 p^3).
    det_b = (b00 * (b11 * b22 - a12 * a12) - a01 * (a01 * b22 - a12 * a02) + a02 * (a01 * a12 - b11 * a02))
    with np.errstate(divide='ignore', invalid='ignore'):
        r = np.where(p > 0, det_b / (2.0 * p * p * p), 0.0)
    phi = np.arccos(np.clip(r, -1.0, 1.0)) / 3.0
    lam = q + 2.0 * p * np.cos(phi + 2.0 * np.pi / 3.0)  # the smallest eigenvalue
    d00, d11, d22 = a00 - lam, a11 - lam, a22 - lam
    # Rows r0 = (d00, a01, a02), r1 = (a01, d11, a12), r2 = (a02, a12, d22); their cross
    # products r0 x r1, r0 x r2, r1 x r2, component by component.
    c01 = (a01 * a12 - a02 * d11, a02 * a01 - d00 * a12, d00 * d11 - a01 * a01)
    c02 = (a01 * d22 - a02 * a12, a02 * a02 - d00 * d22, d00 * a12 - a01 * a02)
    c12 = (d11 * d22 - a12 * a12, a12 * a02 - a01 * d22, a01 * a12 - d11 * a02)
    n01 = c01[0] * c01[0] + c01[1] * c01[1] + c01[2] * c01[2]
    n02 = c02[0] * c02[0] + c02[1] * c02[1] + c02[2] * c02[2]
    n12 = c12[0] * c12[0] + c12[1] * c12[1] + c12[2] * c12[2]
    first = n01 >= n02
    norm2 = np.where(first, n01, n02)
    last = n12 > norm2
    norm2 = np.where(last, n12, norm2)
    # Trust the closed form only when the cross product is well above round-off.
    scale2 = a00 * a00 + a11 * a11 + a22 * a22 + 2.0 * p1
    tol = 1e-12 if norm2.dtype == np.float64 else 1e-6
    good = norm2 > tol * scale2 * scale2
    vec = np.empty((len(a00), 3), dtype=np.float64)
    for i in range(3):
        vec[:, i] = np.where(last, c12[i], np.where(first, c01[i], c02[i]))
    # Normalised in float64, so that the normals are unit vectors to round-off.
    vec[good] /= np.sqrt(np.einsum('ij,ij->i', vec[good], vec[good]))[:, None]
    if not good.all():
        bad = np.flatnonzero(~good)
        cov = np.empty((len(bad), 3, 3))
        for (i, j), a in zip(((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2)), (a00, a11, a22, a01, a02, a12)):
            cov[:, i, j] = cov[:, j, i] = a[bad]
        vec[bad] = np.linalg.eigh(cov)[1][:, :, 0]
    return vec


def point_normals(xyz: np.ndarray, k: int) -> np.ndarray:
    """Unit normals by PCA of each point's k nearest neighbours.

    Args:
        xyz: (N, 3) points, metres, map frame.
        k: neighbourhood size, the point itself included (clipped to N); at least 3.

    Returns:
        (N, 3) float64 unit normals (map frame), sign arbitrary: the eigenvector of the
        smallest eigenvalue of the neighbourhood covariance.

    Raises:
        InputError: ``xyz`` is not (N, 3) finite, is empty or has fewer than 3 points, or
            ``k`` < 3.
    """
    xyz = _check_xyz(xyz)
    if isinstance(k, bool) or int(k) != k or k < 3:
        raise InputError(f'point_normals: k must be an integer >= 3, got {k!r}')
    n = xyz.shape[0]
    if n < 3:
        raise InputError(f'point_normals needs at least 3 points, got {n}')
    return _point_normals(xyz, int(min(k, n)))


def _point_normals(xyz: np.ndarray, k: int, rows: np.ndarray | None = None) -> np.ndarray:
    """:func:`point_normals` of checked (N, 3) float64 points, 3 <= k <= N.

    ``rows``: (M,) sorted indices of the points whose normals are wanted (their neighbours
    are still sought among all N points); None: all. Returns (M, 3), or (N, 3) for None;
    a point's normal does not depend on which others are asked for."""
    n = xyz.shape[0]
    tree = cKDTree(xyz, balanced_tree=False, compact_nodes=False)
    # Query in the tree's own order so that consecutive queries touch the same memory.
    order = tree.indices
    if rows is not None:
        wanted = np.zeros(n, dtype=bool)
        wanted[rows] = True
        order = order[wanted[order]]
    # float32 relative coordinates: half the memory traffic; their round-off (micrometres
    # within kilometres of the centroid) is far below any scanner's noise.
    centred = xyz - xyz.mean(axis=0)
    columns = [centred[:, i].astype(np.float32) for i in range(3)]
    normals = np.empty((n, 3), dtype=np.float64)
    for start in range(0, len(order), _NORMAL_CHUNK):
        sel = order[start:start + _NORMAL_CHUNK]
        _, nb = tree.query(xyz[sel], k=k, workers=kdtree_workers())
        # Column 0 is the point itself (relative position 0); the others as (k - 1, c)
        # rows, relative to the query point (no cancellation in the covariance).
        others = np.ascontiguousarray(nb[:, 1:].T)
        rel = [c[others] - c[sel] for c in columns]
        mean = [r.sum(axis=0) / k for r in rel]
        cov = [np.einsum('ji,ji->i', rel[a], rel[b]) / k - mean[a] * mean[b]
               for a, b in ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))]
        normals[sel] = _smallest_eigenvectors(*cov)
    return normals if rows is None else normals[rows]


# ----------------------------------------------------------------------------------------
# Buildings
# ----------------------------------------------------------------------------------------
def _grid_components(cells: np.ndarray) -> np.ndarray:
    """8-connected components of occupied 2D cells.

    Args:
        cells: (M, 2) int64 cell coordinates (repeats allowed).

    Returns:
        (M,) int64 component label per row, 0-based, numbered in order of first cell.
    """
    lo = cells.min(axis=0)
    cells = cells - lo
    shape = cells.max(axis=0) + 1
    if int(shape[0]) * int(shape[1]) <= _MAX_DENSE_CELLS:
        grid = np.zeros(tuple(int(s) for s in shape), dtype=bool)
        grid[cells[:, 0], cells[:, 1]] = True
        labels, _ = ndimage.label(grid, structure=np.ones((3, 3), dtype=bool))
        lab = labels[cells[:, 0], cells[:, 1]].astype(np.int64) - 1
    else:  # huge extents: a graph over the occupied cells only
        uniq, inverse = np.unique(cells, axis=0, return_inverse=True)
        inverse = inverse.reshape(-1)
        key = uniq[:, 0] * (int(shape[1]) + 2) + uniq[:, 1]
        order = np.argsort(key)
        rows, cols = [], []
        for dx, dy in ((0, 1), (1, -1), (1, 0), (1, 1)):
            nkey = (uniq[:, 0] + dx) * (int(shape[1]) + 2) + (uniq[:, 1] + dy)
            pos = np.clip(np.searchsorted(key[order], nkey), 0, len(key) - 1)
            hit = key[order][pos] == nkey
            rows.append(np.flatnonzero(hit))
            cols.append(order[pos[hit]])
        r, c = np.concatenate(rows), np.concatenate(cols)
        graph = coo_matrix((np.ones(len(r), dtype=np.int8), (r, c)), shape=(len(uniq), len(uniq)))
        _, comp = connected_components(graph, directed=False)
        lab = comp[inverse].astype(np.int64)
    # Renumber by first appearance so that labels do not depend on the grid's origin.
    _, first, inv = np.unique(lab, return_index=True, return_inverse=True)
    rank = np.empty(len(first), dtype=np.int64)
    rank[np.argsort(first, kind='stable')] = np.arange(len(first))
    return rank[inv.reshape(-1)]


def check_building_ids(building_id: np.ndarray, n: int) -> np.ndarray:
    """Building ids of n points as a new (n,) int64 array.

    Raises:
        InputError: another shape, or values that are not integers (floats must be
            finite and integral).
    """
    ids = np.asarray(building_id)
    if ids.shape != (n,):
        raise InputError(f'building_id must have shape ({n},), got {ids.shape}')
    if ids.dtype.kind not in 'iu':
        if ids.dtype.kind != 'f' or not np.all(np.isfinite(ids)) or np.any(ids != np.round(ids)):
            raise InputError('building_id must hold integers')
    return ids.astype(np.int64)


#: Offsets of a clustering cell's 3x3 neighbourhood in :func:`building_cells` keys.
_CELL_NEIGHBOURS = np.array([du * (1 << 32) + dv for du in (-1, 0, 1) for dv in (-1, 0, 1)], dtype=np.int64)


def building_cells(xyz: np.ndarray, cell: float) -> np.ndarray:
    """(N,) int64 keys of the (x, y) grid cells of ``cell`` metres holding (N, 3) points
    (metres, map frame), offset to be >= 0: the cells :func:`split_buildings` clusters."""
    c = np.floor(xyz[:, :2] / float(cell)).astype(np.int64) + (1 << 30)
    return c[:, 0] * (1 << 32) + c[:, 1]


def split_buildings(xyz: np.ndarray, building_id: np.ndarray | None, cell: float,
                    mapped: dict[int, np.ndarray] | None = None) -> np.ndarray:
    """Building label of every point.

    Points with a building id (>= 0) keep it; the others are clustered by 8-connected
    components of the occupied cells of an (x, y) grid of ``cell`` metres
    (``scipy.ndimage.label``). A cluster that touches (shares or borders) cells of
    ``mapped`` buildings joins the one whose cells it touches most (the map's incremental
    clustering); the others are numbered from ``max(building_id, mapped labels) + 1`` on,
    in order of first point, so that the labels never collide with the given ids.

    Args:
        xyz: (N, 3) points, metres, map frame.
        building_id: (N,) integer ids, -1 (any negative) for none; or None for no ids.
        cell: grid cell size, metres (> 0).
        mapped: per label of an already mapped building, the sorted :func:`building_cells`
            keys of its points; None: none.

    Returns:
        (N,) int64 labels, all >= 0.

    Raises:
        InputError: bad shapes, NaN coordinates, non-integer ids or ``cell`` <= 0.
    """
    xyz = _check_xyz(xyz, allow_empty=True)
    if not (np.isfinite(cell) and cell > 0):
        raise InputError(f'split_buildings: cell must be a positive number of metres, got {cell!r}')
    n = xyz.shape[0]
    if building_id is None:
        labels = np.full(n, -1, dtype=np.int64)
    else:
        labels = check_building_ids(building_id, n)
        labels[labels < 0] = -1
    free = np.flatnonzero(labels < 0)
    if not len(free):
        return labels
    keys = building_cells(xyz[free], cell)
    comp = _grid_components(np.stack([keys >> 32, keys & 0xFFFFFFFF], axis=1))
    target = np.full(int(comp.max()) + 1, -1, dtype=np.int64)
    if mapped:
        near = (keys[:, None] + _CELL_NEIGHBOURS[None, :]).ravel()
        comp_near = np.repeat(comp, len(_CELL_NEIGHBOURS))
        best: dict[int, int] = {}
        for b, cells in mapped.items():
            for c, count in zip(*np.unique(comp_near[np.isin(near, cells)], return_counts=True)):
                if count > best.get(int(c), 0):
                    best[int(c)] = int(count)
                    target[c] = b
    new = target < 0
    target[new] = max([int(labels.max()), *(mapped or {}), -1]) + 1 + np.arange(int(new.sum()))
    labels[free] = target[comp]
    return labels


# ----------------------------------------------------------------------------------------
# Planes
# ----------------------------------------------------------------------------------------
def _pca_plane(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(normal (3,), centroid (3,)) of the least-squares plane of (M, 3) points, M >= 3."""
    centroid = points.mean(axis=0)
    rel = points - centroid
    _, vecs = np.linalg.eigh(rel.T @ rel)
    return vecs[:, 0], centroid


def _vertical_ok(normal: np.ndarray, max_tilt_deg: float) -> bool | np.ndarray:
    """True where a plane with unit ``normal`` is within ``max_tilt_deg`` of vertical."""
    return np.abs(normal[..., 2]) <= np.sin(np.deg2rad(max_tilt_deg)) + 1e-12


def _faces_outwards(frame: FacadeFrame, box: np.ndarray, xyz: np.ndarray, origins: np.ndarray | None,
                    params: ExtractionParams, context: np.ndarray | None = None,
                    context_labels: np.ndarray | None = None) -> bool:
    """Whether ``frame.normal`` points out of the building (module docstring, item 5).

    Args:
        frame: the plane's frame.
        box: (4,) u_min, u_max, v_min, v_max of the plane's points, metres.
        xyz: (M, 3) points of the plane (``origins`` given) or of the whole building.
        origins: (M, 3) sensor origins of the plane's points, or None.
        params: gives the band and the margin.
        context: (C, 3) points of the other buildings, or None. A sensor sees a wall from
            its front, so what it saw beyond the band (the houses across the street)
            lies mostly in front; the building's own other walls lie behind.
        context_labels: (C,) int building of each context point, or None. A building
            with ``_BESIDE_SHARE`` of its points near the wall within the band straddles the
            wall's plane (a neighbour in line with it, whose side walls lie behind the line
            like this building's) and does not vote.
    """
    if origins is not None:
        score = float(np.mean(np.einsum('ij,j->i', origins - xyz, frame.normal)))
        if score != 0.0:
            return score > 0
    uvd = _to_local(xyz, frame)
    m = params.extent_margin
    d = uvd[(uvd[:, 0] >= box[0] - m) & (uvd[:, 0] <= box[1] + m)
            & (uvd[:, 1] >= box[2] - m) & (uvd[:, 1] <= box[3] + m), 2]
    # The rest of the building lies behind a wall, the other buildings in front of it;
    # then protrusions stand out in front. (Symmetric limits: the normal may point
    # either way yet.)
    band = max(params.band_front, params.band_back)
    front, back = np.count_nonzero(d > band), np.count_nonzero(d < -band)
    if context is not None and len(context):
        c = _to_local(context, frame)
        reach = _CONTEXT_REACH
        near = (c[:, 0] >= box[0] - reach) & (c[:, 0] <= box[1] + reach) & (np.abs(c[:, 2]) <= reach)
        if context_labels is not None and near.any():
            # A neighbour beside the wall (its street wall in line with it, within the
            # band) lies behind the line like this building: it does not vote.
            rows = np.flatnonzero(near)
            _, lab = np.unique(context_labels[rows], return_inverse=True)
            lab = lab.reshape(-1)
            in_band = np.bincount(lab, weights=np.abs(c[rows, 2]) <= band)
            beside = in_band >= _BESIDE_SHARE * np.bincount(lab)
            near[rows[beside[lab]]] = False
        # Seen beyond the wall in front speaks for outwards, as the building behind does.
        back += np.count_nonzero(near & (c[:, 2] > band))
        front += np.count_nonzero(near & (c[:, 2] < -band))
    for ahead, behind in ((front, back),
                          (np.count_nonzero((d > _PROTRUSION) & (d <= band)),
                           np.count_nonzero((d < -_PROTRUSION) & (d >= -band)))):
        if abs(ahead - behind) > max(10, 0.1 * (ahead + behind)):
            return behind > ahead
    return frame.normal[2] >= 0.0


@dataclass
class _Plane:
    """A RANSAC plane during extraction: oriented frame and the (u, v) box it explains."""

    frame: FacadeFrame
    box: np.ndarray  # (4,) u_min, u_max, v_min, v_max of its inliers
    support: int     # inliers in the subsample
    sketch: np.ndarray = field(default_factory=lambda: np.empty((0, 3)))  # (K, 3) occupied voxel centres


def _sketch(xyz: np.ndarray) -> np.ndarray:
    """(K, 3) centres of the ``_SKETCH_VOXEL`` voxels holding two or more of the (M, 3) points (same frame)."""
    if not len(xyz):
        return np.empty((0, 3))
    _, first, counts = np.unique(_voxel_keys(xyz, _SKETCH_VOXEL), return_index=True, return_counts=True)
    return (np.floor(xyz[first[counts >= 2]] / _SKETCH_VOXEL) + 0.5) * _SKETCH_VOXEL


def side_by_side(uv_a: np.ndarray, uv_b: np.ndarray, cell: float = _TILE_CELL) -> bool:
    """Whether two parallel planes occupy separate parts of a façade (stacked storeys, a
    set-back wing) rather than one lying among the other's cells (balcony fronts, window
    backs, a recessed entrance): at most ``_TILE_SHARE`` of either's occupied ``cell``
    cells lies within one cell (8-neighbourhood) of the other's.

    Args:
        uv_a: (M, 2) (u, v) of the points of one plane, metres, in a frame both share.
        uv_b: (K, 2) the same for the other plane.
        cell: cell size, metres.

    Returns:
        False if either has no points.
    """
    if not len(uv_a) or not len(uv_b):
        return False
    ca = np.unique(np.floor(np.asarray(uv_a)[:, :2] / cell).astype(np.int64), axis=0)
    cb = np.unique(np.floor(np.asarray(uv_b)[:, :2] / cell).astype(np.int64), axis=0)
    lo = np.minimum(ca.min(axis=0), cb.min(axis=0)) - 1
    width = int(max(ca[:, 1].max(), cb[:, 1].max()) - lo[1]) + 2

    def key(c: np.ndarray) -> np.ndarray:
        return (c[:, 0] - lo[0]) * width + (c[:, 1] - lo[1])

    def near_share(c: np.ndarray, other: np.ndarray) -> float:
        grown = np.concatenate([key(other + np.array([di, dj])) for di in (-1, 0, 1) for dj in (-1, 0, 1)])
        return float(np.isin(key(c), grown).mean())

    return max(near_share(ca, cb), near_share(cb, ca)) <= _TILE_SHARE


def _to_local(xyz: np.ndarray, frame: FacadeFrame) -> np.ndarray:
    """(N, 3) (u, v, d) of (N, 3) points: ``frame.to_local`` as three matrix-vector products,
    several times faster than numpy's (N, 3) @ (3, 3) path."""
    out = np.empty((xyz.shape[0], 3))
    for i in range(3):
        axis = frame.axes[i]
        out[:, i] = xyz @ axis - float(axis @ frame.origin)
    return out


def _in_band_and_box(uvd: np.ndarray, box: np.ndarray, params: ExtractionParams, m: float) -> np.ndarray:
    """(N,) bool: (u, v, d) within the depth band and within ``box`` grown by ``m``."""
    d = uvd[:, 2]
    return ((d >= -params.band_back) & (d <= params.band_front)
            & (uvd[:, 0] >= box[0] - m) & (uvd[:, 0] <= box[1] + m)
            & (uvd[:, 1] >= box[2] - m) & (uvd[:, 1] <= box[3] + m))


def _largest_piece(uv: np.ndarray, cell: float) -> np.ndarray:
    """Bool mask of the (M, 2) points in the largest 8-connected piece of ``cell`` cells."""
    if len(uv) == 0:
        return np.zeros(0, dtype=bool)
    lab = _grid_components(np.floor(uv / cell).astype(np.int64))
    counts = np.bincount(lab)
    return lab == int(np.argmax(counts))


def _voxel_keys(xyz: np.ndarray, cell: float) -> np.ndarray:
    """(N,) int64 key of the ``cell``-metre voxel of each point (within 2**20 cells of 0)."""
    v = np.floor(xyz / cell).astype(np.int64) + (1 << 20)
    return (v[:, 0] << 42) | (v[:, 1] << 21) | v[:, 2]


def _sampling_cell(xyz: np.ndarray) -> float:
    """Voxel size (m) whose voxels hold a typical point together with 10 to 60 others."""
    cell = 1.0
    for _ in range(6):
        _, inverse, counts = np.unique(_voxel_keys(xyz, cell), return_inverse=True, return_counts=True)
        typical = float(np.median(counts[inverse.reshape(-1)]))
        if typical < 10 and cell < 8.0:
            cell *= 2.0
        elif typical > 60 and cell > 0.25:
            cell /= 2.0
        else:
            break
    return cell


def _hypotheses(pool_xyz: np.ndarray, cell: float, count: int, rng: np.random.Generator
                ) -> tuple[np.ndarray, np.ndarray]:
    """Planes through three points of one voxel: a random pool point and two of its voxel.

    Args:
        pool_xyz: (M, 3) points not yet explained by a plane.
        cell: voxel size, metres.
        count: hypotheses drawn (fewer come back: duplicates and collinear triples go).
        rng: random source.

    Returns:
        (H, 3) unit normals and (H,) offsets c of the planes x . n = c, H <= count.
    """
    keys = _voxel_keys(pool_xyz, cell)
    order = np.argsort(keys, kind='stable')
    _, starts, inverse, counts = np.unique(keys[order], return_index=True, return_inverse=True,
                                           return_counts=True)
    group = np.empty(len(keys), dtype=np.int64)
    group[order] = inverse.reshape(-1)
    seeds = rng.integers(0, len(keys), size=count)
    g = group[seeds]
    size = counts[g]
    b = order[starts[g] + (rng.random(count) * size).astype(np.int64)]
    c = order[starts[g] + (rng.random(count) * size).astype(np.int64)]
    ok = (size >= 3) & (b != seeds) & (c != seeds) & (b != c)
    p0, p1, p2 = pool_xyz[seeds[ok]], pool_xyz[b[ok]], pool_xyz[c[ok]]
    normal = np.cross(p1 - p0, p2 - p0)
    norm = np.linalg.norm(normal, axis=1)
    # Drop nearly collinear triples (sine of the triangle's angle under about 0.1).
    spread = np.linalg.norm(p1 - p0, axis=1) * np.linalg.norm(p2 - p0, axis=1)
    keep = norm > 0.1 * spread
    normal = normal[keep] / norm[keep, None]
    return normal, np.einsum('ij,ij->i', normal, p0[keep])


def _refine(points: np.ndarray, normal: np.ndarray, offset: float, threshold: float
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """Iterated PCA on the points within ``threshold``: (normal, centroid, inlier mask) or None."""
    inl = np.abs(points @ normal - offset) < threshold
    centroid = None
    for _ in range(_REFINE_PASSES):
        if inl.sum() < 3:
            return None
        new_normal, centroid = _pca_plane(points[inl])
        normal = new_normal if new_normal @ normal >= 0 else -new_normal
        offset = float(normal @ centroid)
        inl = np.abs(points @ normal - offset) < threshold
    if inl.sum() < 3 or centroid is None:
        return None
    return normal, centroid, inl


def _ransac(xyz: np.ndarray, origins: np.ndarray | None, n_total: int, params: ExtractionParams,
            rng: np.random.Generator, context: np.ndarray | None = None,
            context_labels: np.ndarray | None = None) -> list[_Plane]:
    """Sequential RANSAC on the subsample ``xyz`` (see module docstring, item 1); ``context``:
    points of other buildings in the same frame, ``context_labels`` their buildings (turn
    normals without sensor origins)."""
    m = len(xyz)
    min_support = max(3, int(np.ceil(0.5 * params.min_facade_points * m / max(n_total, 1))))
    if m < max(3, min_support):
        return []
    cell = _sampling_cell(xyz)
    alive = np.ones(m, dtype=bool)
    planes: list[_Plane] = []
    piece_cell = max(2.0 * params.extent_margin, 0.5)
    thr = params.ransac_threshold
    while len(planes) < params.max_facades:
        pool = np.flatnonzero(alive)
        if len(pool) < min_support:
            break
        pool_xyz = xyz[pool]
        normals, offsets = _hypotheses(pool_xyz, cell, params.ransac_iterations, rng)
        vertical = _vertical_ok(normals, params.max_tilt_deg)
        normals, offsets = normals[vertical], offsets[vertical]
        if not len(normals):
            break
        probe = pool_xyz if len(pool) <= _PREEMPTIVE_POINTS else pool_xyz[
            rng.integers(0, len(pool), size=_PREEMPTIVE_POINTS)]
        dist = probe.astype(np.float32) @ normals.T.astype(np.float32)
        dist -= offsets.astype(np.float32)
        np.abs(dist, out=dist)
        score = np.count_nonzero(dist < thr, axis=0)
        top = np.argsort(-score, kind='stable')[:_PREEMPTIVE_KEEP]
        full = (np.abs(pool_xyz @ normals[top].T - offsets[top]) < thr).sum(axis=0)
        found = None
        for j in top[np.argsort(-full, kind='stable')]:
            refined = _refine(pool_xyz, normals[j], float(offsets[j]), thr)
            if refined is None or not _vertical_ok(refined[0], params.max_tilt_deg):
                continue
            found = refined
            break
        if found is None:
            break
        normal, centroid, inl = found
        if inl.sum() < min_support:
            break
        inl_xyz = pool_xyz[inl]
        frame = FacadeFrame.from_normal(centroid, normal)
        uv = _to_local(inl_xyz, frame)[:, :2]
        piece = _largest_piece(uv, piece_cell)
        box = np.array(_plane_box(uv[piece])) if piece.any() else np.zeros(4)
        if piece.sum() < min_support or min(box[1] - box[0], box[3] - box[2]) < _MIN_SIDE:
            # Scattered support, or a sliver (points along a line fit any plane through
            # it): drop its inliers so that the next round moves on.
            alive[pool[inl]] = False
            continue
        if origins is not None:
            outwards = _faces_outwards(frame, box, inl_xyz, origins[pool[inl]], params)
        else:
            outwards = _faces_outwards(frame, box, xyz, None, params, context, context_labels)
        if not outwards:  # turn round: u and d change sign, v stays
            normal = -normal
            frame = FacadeFrame.from_normal(centroid, normal)
            box = np.array([-box[1], -box[0], box[2], box[3]])
        piece_xyz = inl_xyz[piece]
        if any(normal @ q.frame.normal > _DETAIL_COS
               and _in_band_and_box(_to_local(piece_xyz, q.frame), q.box, params, _EDGE_TOLERANCE).mean() > 0.5
               for q in planes):
            # Facing the same way as a façade found before and mostly in its band at the
            # edge of its extent: its detail (the foot of a sloped plinth), not a façade.
            # (A short adjacent wall is turned further away or lies beyond the edge.)
            alive[pool[inl]] = False
            continue
        planes.append(_Plane(frame, box, int(piece.sum()), _sketch(piece_xyz)))
        # Everything in the band in front of and behind the plane's piece is its detail;
        # beyond the piece's ends (no margin here) an adjacent wall, even a short or
        # oblique one, may start.
        explained = _in_band_and_box(_to_local(pool_xyz, frame), box, params, 0.0)
        alive[pool[explained]] = False
    return planes


def _turned(plane: _Plane) -> _Plane:
    """The plane facing the other way (u and d change sign, v stays)."""
    b = plane.box
    return _Plane(FacadeFrame.from_normal(plane.frame.origin, -plane.frame.normal),
                  np.array([-b[1], -b[0], b[2], b[3]]), plane.support, plane.sketch)


def _face_like_walls(planes: list[_Plane], known: Sequence[_Plane] = ()) -> list[_Plane]:
    """Sloped planes (tilted more than ``_TILTED_DEG``) turned to face, horizontally, like the
    vertical wall they adjoin (see ``_TILTED_DEG``; the nearest if several); the others,
    and sloped ones with no such wall, as they are.

    Without sensor origins the shape of the building around a roof band or a mansard does
    not tell its outside: the building lies below it as much as behind it. It crowns
    (or, a sloped plinth, stands at the foot of) a wall whose outside is better known, and
    its outside is the same street. ("Up" would be wrong for an overhang facing down.)
    ``known``: walls found before (incremental mapping), adjoining as well.
    """
    sin_wall, sin_tilted = np.sin(np.deg2rad(_WALL_DEG)), np.sin(np.deg2rad(_TILTED_DEG))
    cos_adjoin = np.cos(np.deg2rad(_ADJOIN_DEG))
    walls = [p for p in [*planes, *known] if abs(p.frame.normal[2]) <= sin_wall and len(p.sketch)]
    out = []
    for p in planes:
        h = p.frame.normal[:2]
        if abs(p.frame.normal[2]) < sin_tilted or not len(p.sketch) or not walls:
            out.append(p)
            continue
        tree = cKDTree(p.sketch)
        best, gap = None, _ADJOIN_GAP
        for w in walls:
            wh = w.frame.normal[:2]
            if abs(wh @ h) < cos_adjoin * np.linalg.norm(wh) * np.linalg.norm(h):
                continue
            dist = float(tree.query(w.sketch, distance_upper_bound=_ADJOIN_GAP)[0].min())
            if dist <= gap:
                best, gap = w, dist
        out.append(_turned(p) if best is not None and best.frame.normal[:2] @ h < 0 else p)
    return out


def _box_in(plane: _Plane, frame: FacadeFrame) -> np.ndarray:
    """(4, 2) (u, v) of the corners of ``plane``'s box (on its plane) in ``frame``."""
    b = plane.box
    corners = plane.frame.to_world(np.array([[b[0], b[2], 0.0], [b[1], b[2], 0.0],
                                             [b[0], b[3], 0.0], [b[1], b[3], 0.0]]))
    return frame.to_local(corners)[:, :2]


def _merge(planes: list[_Plane], params: ExtractionParams) -> list[_Plane]:
    """Fold near-parallel, nearby planes into one façade (module docstring, item 2).

    Planes are taken largest first; one joins the first group whose largest plane is
    within ``merge_angle_deg`` (same outward side), closer than ``merge_offset`` along
    its normal and no further than ``merge_offset`` from its box in ``u``. A group's
    façade plane is its back-most plane with at least a fifth of the largest one's
    support and half its width: a wall hidden behind deep balconies may have fewer
    inliers than the balcony fronts, and the band must reach back from the wall, not
    from the balconies; a narrow plane behind (a recess) is not the wall.
    """
    cos_max = np.cos(np.deg2rad(params.merge_angle_deg))
    groups: list[list[_Plane]] = []
    for plane in sorted(planes, key=lambda p: -p.support):
        for group in groups:
            big = group[0]
            if float(plane.frame.normal @ big.frame.normal) < cos_max:
                continue
            uv = _box_in(plane, big.frame)
            centre_d = float(big.frame.to_local(plane.frame.origin[None])[0, 2])
            u_gap = max(big.box[0] - uv[:, 0].max(), uv[:, 0].min() - big.box[1], 0.0)
            if abs(centre_d) < params.merge_offset and u_gap <= params.merge_offset:
                group.append(plane)
                break
        else:
            groups.append([plane])
    merged = []
    for group in groups:
        big = group[0]
        width = _MAIN_WIDTH_SHARE * (big.box[1] - big.box[0])
        able = [p for p in group if p.support >= _MAIN_SUPPORT_SHARE * big.support and p.box[1] - p.box[0] >= width]
        main = min(able, key=lambda p: float(big.frame.to_local(p.frame.origin[None])[0, 2]))
        # A large member beyond the façade plane's allocation band would lose its points
        # to no façade: it is a façade of its own (a set-back ground floor deeper than
        # band_back). Small ones stay (and lose them): rooms seen through windows. So is
        # a large member a storey's setback or more away that occupies its own part of
        # the wall (upper storeys over a set-back ground floor): as a layer of the wall's
        # façade, its holes would be filled from the wall's depth, and the wall's extent
        # would leave it out.
        depth = [float(main.frame.to_local(p.frame.origin[None])[0, 2]) for p in group]
        main_uv = main.frame.to_local(main.sketch)[:, :2]
        apart = [p for p, d in zip(group, depth) if p.support >= _MAIN_SUPPORT_SHARE * big.support and p is not main
                 and (not -params.band_back <= d <= params.band_front
                      or abs(d) >= STOREY_OFFSET and side_by_side(main.frame.to_local(p.sketch)[:, :2], main_uv))]
        if apart:
            merged += _merge(apart, params)
            group = [p for p in group if all(p is not q for q in apart)]
        uv = np.vstack([_box_in(p, main.frame) for p in group])
        box = np.array([uv[:, 0].min(), uv[:, 0].max(), uv[:, 1].min(), uv[:, 1].max()])
        merged.append(_Plane(main.frame, box, sum(p.support for p in group), np.vstack([p.sketch for p in group])))
    return merged


# ----------------------------------------------------------------------------------------
# Allocation
# ----------------------------------------------------------------------------------------
class _Bands:
    """Points within the depth band of each of a fixed set of façade frames.

    For every frame, the indices of the points with ``-band_back <= d <= band_front``,
    their (u, v, d) and ``|d|``; allocation for any set of extents then only tests boxes.
    """

    def __init__(self, xyz: np.ndarray, frames: Sequence[FacadeFrame], params: ExtractionParams) -> None:
        self.n = xyz.shape[0]
        self.margin = params.extent_margin
        self.threshold = params.ransac_threshold
        self.idx: list[np.ndarray] = []
        self.uvd: list[np.ndarray] = []
        self.absd: list[np.ndarray] = []
        for frame in frames:
            e_u, e_v, normal = frame.axes
            d = xyz @ normal - float(normal @ frame.origin)
            cand = np.flatnonzero((d >= -params.band_back) & (d <= params.band_front))
            pts = xyz[cand]
            uvd = np.empty((len(cand), 3))
            uvd[:, 0] = pts @ e_u - float(e_u @ frame.origin)
            uvd[:, 1] = pts @ e_v - float(e_v @ frame.origin)
            uvd[:, 2] = d[cand]
            self.idx.append(cand)
            self.uvd.append(uvd)
            self.absd.append(np.abs(uvd[:, 2]))

    def subset(self, keep: Sequence[int]) -> _Bands:
        """The bands of the frames ``keep`` only (no recomputation)."""
        out = object.__new__(_Bands)
        out.n, out.margin, out.threshold = self.n, self.margin, self.threshold
        out.idx = [self.idx[j] for j in keep]
        out.uvd = [self.uvd[j] for j in keep]
        out.absd = [self.absd[j] for j in keep]
        return out

    def allocate(self, boxes: Sequence[Sequence[float]]) -> np.ndarray:
        """(N,) int64 index of the façade each point goes to, -1 for none (the rule of
        :func:`assign_to_facades`).

        Args:
            boxes: per frame, the plane extent (u_min, u_max, v_min, v_max), metres.
        """
        which = np.full(self.n, -1, dtype=np.int64)
        best = np.full(self.n, np.inf)
        m = self.margin
        for j, (cand, uvd, absd) in enumerate(zip(self.idx, self.uvd, self.absd)):
            b = boxes[j]
            u, v = uvd[:, 0], uvd[:, 1]
            take = (u >= b[0] - m) & (u <= b[1] + m) & (v >= b[2] - m) & (v <= b[3] + m)
            take &= absd < best[cand]
            sel = cand[take]
            which[sel] = j
            best[sel] = absd[take]
        return which

    def members(self, which: np.ndarray, j: int) -> tuple[np.ndarray, np.ndarray]:
        """(M,) indices and (M, 3) (u, v, d) of the points allocated to façade ``j``."""
        mine = which[self.idx[j]] == j
        return self.idx[j][mine], self.uvd[j][mine]

    def plane_extent(self, j: int, box: Sequence[float]) -> tuple[float, float, float, float] | None:
        """Robust extent of frame ``j``'s plane: its points within the threshold of the plane
        and within ``box`` grown by the margin (None if there are fewer than 3)."""
        uvd, m = self.uvd[j], self.margin
        near = ((np.abs(uvd[:, 2]) <= self.threshold) & (uvd[:, 0] >= box[0] - m) & (uvd[:, 0] <= box[1] + m)
                & (uvd[:, 1] >= box[2] - m) & (uvd[:, 1] <= box[3] + m))
        return _plane_box(uvd[near]) if near.sum() >= 3 else None


def assign_to_facades(xyz: np.ndarray, facades: Sequence[ExtractedFacade],
                      params: ExtractionParams) -> tuple[np.ndarray, np.ndarray]:
    """Allocate points to existing façades (incremental mapping, 3D queries).

    A point belongs to a façade if it lies in the façade's depth band
    (``-band_back <= d <= band_front``) and within its ``plane_extent`` grown by
    ``extent_margin`` in u and v; if several façades qualify, the one with the smallest
    ``|d|`` (ties: the lower index). This is the rule :func:`extract_facades` allocates
    with, so both agree on the same points.

    Args:
        xyz: (N, 3) points, metres, map frame.
        facades: the façades (``frame`` and ``plane_extent`` are used).
        params: gives ``band_front``, ``band_back``, ``extent_margin`` and ``ransac_threshold``.

    Returns:
        ``(facade_index, uvd)``: (N,) int64 index into ``facades``, -1 for none, and
        (N, 3) float64 (u, v, d) in the frame of the chosen façade, metres (zeros where
        none).

    Raises:
        InputError: ``xyz`` is not (N, 3) or has NaN or infinite coordinates.
    """
    xyz = _check_xyz(xyz, allow_empty=True)
    bands = _Bands(xyz, [f.frame for f in facades], params)
    which = bands.allocate([f.plane_extent for f in facades])
    uvd = np.zeros((xyz.shape[0], 3))
    for j in range(len(facades)):
        index, local = bands.members(which, j)
        uvd[index] = local
    return which, uvd


def _plane_box(uv: np.ndarray) -> tuple[float, float, float, float]:
    """Robust (u_min, u_max, v_min, v_max) of a plane's (M, 2+) points.

    The ``_TRIM_POINTS``-th point from either end (at most the ``_TRIM`` quantile): a few
    stray returns on the plane's extension (clutter, the edge of an adjacent wall) do not
    stretch the façade, while a wall whose ends are sparse (occluded, or hidden behind an
    oriel) keeps them.
    """
    q = min(_TRIM, _TRIM_POINTS / max(len(uv) - 1, 1))
    lo, hi = np.quantile(uv[:, :2], [q, 1.0 - q], axis=0)
    return (float(lo[0]), float(hi[0]), float(lo[1]), float(hi[1]))


def _box_of(uvd: np.ndarray) -> tuple[float, float, float, float]:
    return (float(uvd[:, 0].min()), float(uvd[:, 0].max()), float(uvd[:, 1].min()), float(uvd[:, 1].max()))


def _dominant_layer(depth: np.ndarray, half_width: float) -> float:
    """Centre (m) of the densest ``2 * half_width`` window of the (M,) depths."""
    order = np.sort(depth)
    # For every point, how many points lie within 2 * half_width above it.
    count = np.searchsorted(order, order + 2.0 * half_width, side='right') - np.arange(len(order))
    i = int(np.argmax(count))
    return float(np.median(order[i:i + count[i]]))


def _final_frame(points: np.ndarray, normals: np.ndarray, frame: FacadeFrame,
                 params: ExtractionParams) -> FacadeFrame | None:
    """Robust PCA frame of a façade's allocated points (module docstring, item 4).

    Args:
        points: (M, 3) allocated points, metres.
        normals: (M, 3) their unit normals (any sign).
        frame: the RANSAC plane's frame (normal outwards).
        params: gives ``ransac_threshold`` and ``max_tilt_deg``.

    Returns:
        The frame (normal turned like ``frame``'s, origin the centroid's projection onto the
        plane), or None if too few points are near the plane or it is too tilted.
    """
    thr = params.ransac_threshold
    refined = _refine(points, frame.normal, float(frame.normal @ frame.origin), thr)
    if refined is None:
        return None
    normal, centroid, inl = refined
    # Two candidates, refined within half the threshold: the least-squares plane, and a
    # restart from the mean point normal of its points at their densest depth layer. On
    # a narrow strip of wall the least-squares plane can settle obliquely across two
    # layers (wall and window backs) while the point normals of both layers agree; the
    # candidate with more points within half the threshold wins.
    candidates = [_refine(points, normal, float(normal @ centroid), 0.5 * thr)]
    nrm = normals[inl] * np.sign(normals[inl] @ normal)[:, None]
    start = nrm.mean(axis=0)
    if np.linalg.norm(start) > 0.5:
        start /= np.linalg.norm(start)
        candidates.append(_refine(points, start, _dominant_layer(points[inl] @ start, 0.25 * thr), 0.5 * thr))
    candidates = [c for c in candidates if c is not None]
    if candidates:
        refined = max(candidates, key=lambda c: int(c[2].sum()))
    # Then tighten to three robust sigmas of the wall's own noise.
    normal, centroid, inl = refined
    resid = (points[inl] - centroid) @ normal
    sigma = 1.4826 * float(np.median(np.abs(resid - np.median(resid))))
    tight = max(3.0 * sigma, 1e-3)
    if tight < 0.5 * thr:
        refined = _refine(points, normal, float(normal @ centroid), tight) or refined
    normal = refined[0]
    if normal @ frame.normal < 0:
        normal = -normal
    if not _vertical_ok(normal, params.max_tilt_deg):
        return None
    centroid = points.mean(axis=0)
    origin = centroid - ((centroid - refined[1]) @ normal) * normal
    return FacadeFrame.from_normal(origin, normal)


def extract_facades(xyz: np.ndarray, params: ExtractionParams, *, sensor_origins: np.ndarray | None = None,
                    rng: np.random.Generator, context: np.ndarray | None = None,
                    context_labels: np.ndarray | None = None, walls: Sequence[tuple[FacadeFrame, np.ndarray]] = (),
                    normals: np.ndarray | None = None) -> tuple[list[ExtractedFacade], np.ndarray]:
    """Extract the façades of ONE building.

    Args:
        xyz: (N, 3) float64 points of the building, metres, map frame.
        params: extraction parameters.
        sensor_origins: (N, 3) sensor position of each return, metres, map frame; used to
            turn the normals outwards (towards the sensor). None: away from the building's
            (x, y) centroid.
        rng: random source of the subsample and the hypotheses.
        context: (C, 3) points of the other buildings, metres, map frame, or None; without
            sensor origins they help to turn the normals (what the sensor saw beyond a
            wall lies mostly in front of it).
        context_labels: (C,) int building of each context point, or None: a building
            beside the wall (in line with it) does not vote.
        walls: the building's façades found before (incremental mapping) as (frame, (K, 3)
            points on its plane, metres, map frame); without sensor origins a sloped façade
            faces like the wall it adjoins, among these too.
        normals: (N, 3) unit point normals (any sign) when the caller has them (the map
            keeps every building point's, :func:`point_normals` with ``normal_neighbours``
            among the building's points); None: computed here among ``xyz``.

    Returns:
        ``(facades, unallocated)``: the façades, most points first, and an (N,) bool mask
        of the points allocated to none. Every point is in at most one façade's ``index``;
        :func:`assign_to_facades` with the returned façades reproduces the allocation.

    Raises:
        InputError: ``xyz`` is empty, not (N, 3) or has NaN or infinite coordinates;
            ``sensor_origins`` has another shape or NaNs; ``rng`` is no Generator.
    """
    xyz = _check_xyz(xyz)
    n = xyz.shape[0]
    origins = None
    if sensor_origins is not None:
        origins = _check_xyz(sensor_origins, 'sensor_origins')
        if origins.shape != xyz.shape:
            raise InputError(f'sensor_origins must have the shape of xyz {xyz.shape}, got {origins.shape}')
    if not isinstance(rng, np.random.Generator):
        raise InputError('extract_facades needs rng=np.random.Generator')
    unallocated = np.ones(n, dtype=bool)
    if n < params.min_facade_points:
        return [], unallocated
    # Work relative to the building centroid (planes far from 0 lose precision).
    centre = xyz.mean(axis=0)
    local = xyz - centre
    sub = np.sort(rng.choice(n, params.ransac_sample, replace=False)) if n > params.ransac_sample else np.arange(n)
    sub_xyz = local[sub]
    sub_origins = None if origins is None else origins[sub] - centre
    sub_context = None if context is None or origins is not None else np.asarray(context, np.float64) - centre
    sub_labels = None if sub_context is None or context_labels is None else np.asarray(context_labels)
    if sub_labels is not None and sub_labels.shape != (len(sub_context),):
        raise InputError(f'context_labels must have shape ({len(sub_context)},), got {sub_labels.shape}')
    planes = _ransac(sub_xyz, sub_origins, n, params, rng, sub_context, sub_labels)
    if origins is None:
        known = [_Plane(frame, np.zeros(4), 0, _sketch(np.asarray(pts, np.float64) - centre)) for frame, pts in walls]
        planes = _face_like_walls(planes, known)
    planes = _merge(planes, params)
    if not planes:
        return [], unallocated
    # Final frames from the subsample's allocation (the subsample pins a plane down to
    # well under 0.01 degree; the full cloud would only cost time).
    if normals is None:
        normals = _point_normals(local, min(params.normal_neighbours, n))
    elif np.shape(normals) != xyz.shape:
        raise InputError(f'normals must have the shape of xyz {xyz.shape}, got {np.shape(normals)}')
    which = _Bands(sub_xyz, [p.frame for p in planes], params).allocate([p.box for p in planes])
    frames: list[FacadeFrame] = []
    boxes: list[tuple[float, float, float, float]] = []
    for j, plane in enumerate(planes):
        mine = which == j
        if mine.sum() < 3:
            continue
        pts = sub_xyz[mine]
        frame = _final_frame(pts, normals[sub[mine]], plane.frame, params)
        if frame is None:
            continue
        uvd = _to_local(pts, frame)
        uvd = uvd[np.abs(uvd[:, 2]) <= params.ransac_threshold]
        if len(uvd):
            frames.append(frame)
            boxes.append(_plane_box(uvd))
    # Plane extents from all points: the building's points within ransac_threshold of
    # each final plane, near the subsample's extent. They do not depend on the
    # competition between façades, so the allocation is a single pass (repeated only if
    # a façade falls under min_facade_points and is dropped). The frames' origins only
    # move within their planes afterwards, which changes no allocation.
    bands = _Bands(local, frames, params)
    plane_boxes = [bands.plane_extent(j, box) for j, box in enumerate(boxes)]
    keep = [j for j, box in enumerate(plane_boxes) if box is not None]
    frames, boxes, bands = [frames[j] for j in keep], [plane_boxes[j] for j in keep], bands.subset(keep)
    which = np.full(n, -1, dtype=np.int64)
    while frames:
        which = bands.allocate(boxes)
        counts = np.bincount(which[which >= 0], minlength=len(frames))
        keep = [j for j in range(len(frames)) if counts[j] >= params.min_facade_points]
        if len(keep) == len(frames):
            break
        frames, boxes, bands = [frames[j] for j in keep], [boxes[j] for j in keep], bands.subset(keep)
    if not frames:
        return [], unallocated
    facades = []
    for j, frame in enumerate(frames):
        index, f_uvd = bands.members(which, j)
        if not len(index):
            continue
        shift = np.array([f_uvd[:, 0].mean(), f_uvd[:, 1].mean(), 0.0])
        origin = frame.origin + shift[0] * frame.axes[0] + shift[1] * frame.axes[1] + centre
        f_uvd = f_uvd - shift
        box = boxes[j]
        plane_extent = (box[0] - shift[0], box[1] - shift[0], box[2] - shift[1], box[3] - shift[1])
        cos = np.minimum(np.abs(normals[index] @ frame.normal), 1.0)
        facades.append(ExtractedFacade(FacadeFrame(origin, frame.axes), index, f_uvd, cos, _box_of(f_uvd),
                                       plane_extent))
    facades.sort(key=lambda f: -len(f))
    return facades, which < 0
