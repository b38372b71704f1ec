"""Fast GPOM (GPOctoMap) as a baseline occupancy method (numpy/scipy re-implementation).

Method: J. Wang and B. Englot, "Fast, accurate Gaussian process occupancy maps via
test-data octrees and nested Bayesian fusion", ICRA 2016 (the ``la3dm`` library's
GPOctoMap), built on S. T. O'Callaghan and F. Ramos, "Gaussian process occupancy maps",
IJRR 31(1), 2012 (GPOM) and on S. Kim and J. Kim's overlapping local GPs. Training data
are the scans' hits, labelled +1, and free-space samples along the beams, labelled -1.
Space is cut into cubic blocks (the leaves of the test-data octree hold the test voxels
of a block); each block with training data has its own GP regression on the training
points inside it, with the Matern 3/2 kernel (Rasmussen and Williams 2006, Eq. 4.17)::

    k(d) = sf2 (1 + sqrt(3) d / ell) exp(-sqrt(3) d / ell)
    m(x) = k_*^T (K + noise I)^-1 y,    v(x) = sf2 - k_*^T (K + noise I)^-1 k_*

(R&W Eq. 2.25-2.26, solved through the Cholesky factor of ``K + noise I``, R&W Alg. 2.1).

A test voxel is predicted by the GPs of its *extended block*: its own block and the 6
blocks sharing a face with it (``la3dm`` ``get_extended_block``). The overlapping
predictions are fused by a Bayesian committee machine (BCM; V. Tresp, "A Bayesian
committee machine", Neural Computation 12(11), 2000), kept as a precision and a
precision-weighted mean per voxel (``la3dm`` ``Occupancy::update``)::

    1/var_f   = 1/max_var + sum_i (1/v_i - 1/sf2),    clamped to at most 1/min_var
    m_f / var_f = sum_i m_i / v_i

starting from the vague prior (mean 0, variance ``max_var``, which thus counts as one more
member of the committee); scans inserted one after the other add their GPs' terms to the
same sums (the "nested" BCM across scans). Voxels whose
extended block holds no training data are not predicted (unknown: p 0.5, variance
``max_var``).

Occupancy probability (``squash``):

- ``'plsc'`` (default): probabilistic least-squares classification (O'Callaghan and Ramos
  2012; Rasmussen and Williams Sec. 6.5, Eq. 6.41), ``p = Phi((alpha m_f + beta) /
  sqrt(1 + alpha^2 var_f))``. As in O'Callaghan and Ramos, ``alpha`` and ``beta`` are
  learnt from the training data by maximising the leave-one-out (LOO) predictive
  probability ``sum_i log Phi(y_i (alpha mu_-i + beta) / sqrt(1 + alpha^2 s_-i^2))``
  (R&W Eq. 6.42), with the LOO means and variances of each block's GP (R&W Eq. 5.12:
  ``mu_-i = y_i - [K^-1 y]_i / [K^-1]_ii``, ``s_-i^2 = 1 / [K^-1]_ii``), over a seeded
  subset of ``loo_blocks`` blocks. No fixed values are published: O'Callaghan and Ramos
  learn them per data set, and the ``la3dm`` code has no PLSC (it uses the logistic below).
- ``'logistic'``: the ``la3dm`` code's own squashing, ``p = 1 / (1 + exp(-l (m_f / var_f) /
  max_ivar))`` with ``max_ivar = 1/min_var`` and the BCM sum ``m_f / var_f`` above
  (``Occupancy::get_prob``; unlike PLSC it ignores the fused variance).

Parameters: the authors' published configuration (``la3dm`` ``config/methods/gpoctomap.yaml``):
resolution 0.1 m (here: the evaluation's resolution), ``block_depth`` 3 (blocks of
2^(3-1) = 4 voxels a side: 0.4 m at 0.1 m), ``sf2`` 1.0, ``ell`` 1.0 m, ``noise`` 0.01,
``l`` 100, ``max_var`` 1000, ``min_var`` 0.001, ``max_known_var`` 0.02, ``free_resolution``
0.3 m, ``ds_resolution`` 0.1 m, ``occupied_thresh`` 0.7 and ``free_thresh`` 0.3 (the yaml
file has the typo ``free_thresh: free_thresh``; 0.3 is the code's default,
``gpoctree_node.cpp``); no maximum range (the method yaml sets none; the nodes' default
is -1). The thresholds and ``max_known_var`` are used only by
:meth:`FastGPOMMethod.classify`.

How the library builds the training data of one scan (``get_training_data``), kept here:
the hits are down-sampled to voxel-grid centroids (PCL ``VoxelGrid``; the ROS server
filters at ``ds_resolution`` and both nodes then pass the *map resolution* as the
down-sampling of ``insert_pointcloud``, so hits are filtered at ``ds_resolution`` and then
at the resolution); each down-sampled hit gives a beam from the scan origin, sampled at
``free_resolution``, 2 ``free_resolution``, ... below the hit's range, plus one sample
``free_resolution`` before the hit, plus the origin itself (``beam_sample``); those free
samples are down-sampled at the resolution.

What was simplified / chosen here:

- **Scans.** The library inserts one scan per sensor pose. Our points carry a sensor origin
  each (a moving vehicle), so rays are grouped into scans by their origins as for the
  BGKOctoMap baseline: origins in the same cube of side ``scan_size`` (default 1 m) form
  one scan. Hits are down-sampled per scan and each beam keeps the mean origin of its
  hits (within 1 m of the real origins), so the free samples lie on the real rays.
- **Nested BCM across scans, as the library.** By default every scan is a batch of its
  own: its training data are built and down-sampled on their own, a GP is trained per
  block holding training data of the scan, and the scans are fused by the nested BCM
  above (on the street: 300 scans, about 1.07 M (scan, block) pairs at 0.1 m).
  ``n_batches`` may instead merge consecutive scans (in time order) into that many
  batches, whose scans' hits and free samples are pooled and down-sampled once at the
  resolution (a voxel seen by many scans then gives one training point per batch); 1
  makes the whole drive one batch.
- **Test voxels are predicted on demand.** The library predicts every voxel of every test
  block when a scan is inserted; here :meth:`FastGPOMMethod.predict` trains the GPs of the
  blocks in the extended blocks of the queried voxels only (a block's GP depends on its
  training data alone, so the answers are the same) and evaluates them at the queried
  points. The GP training time is therefore counted in ``predict``, not ``fit``.
- Blocks are assigned by ``round(x / block_size)`` per axis (``block_to_hash_key``); a
  training point exactly on a block face belongs to one block, not to both (the R-tree's
  closed boxes).
- The BCM subtracts the prior precision ``1/sf2`` per GP (Tresp); the library subtracts
  ``sf2``, the same at its ``sf2`` = 1. The clamp to ``1/min_var`` is applied once after
  the sum; the terms are non-negative, so this equals the library's clamp after each
  update. A GP variance below 1e-12 (numerically impossible with ``noise`` > 0) is raised
  to it.
- The PLSC uses the fused *latent* variance (the library's and the evaluation's
  variance); the LOO variances used to learn ``alpha`` and ``beta`` include the noise
  (R&W Eq. 5.12), as in R&W Sec. 6.5.
- Training inputs are stored as float32 (as the library's); the GPs are computed in
  float64 (the library: float32), batched over blocks: blocks are padded to a few sizes
  with identity rows (which change no answer); triangular solves use ``np.linalg.solve`` on
  the Cholesky factor for small blocks and ``scipy.linalg.solve_triangular`` for large
  ones (the faster of the two), one solve per block giving both ``L^-1 y`` and ``L^-1 k_*``
  (so ``m = (L^-1 k_*)^T (L^-1 y)``).
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
import scipy.linalg
from scipy.special import expit, log_ndtr, ndtr

from ...errors import InputError
from ...threads import one_blas_thread
from ...voxels import pack_keys, unpack_keys
from .base import (
    OccupancyMethod,
    beam_samples,
    check_positive,
    check_queries,
    check_scans,
    group_by_origin,
    voxel_centroids,
)

#: The block itself and its 6 face neighbours (``la3dm`` ``get_extended_block``).
EXTENDED_BLOCK = np.array([[0, 0, 0], [1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]],
                          dtype=np.int64)

#: Bits per axis of a packed block key (block indices within +-2^20 of the origin).
#: Blocks up to this size use np.linalg.solve on the Cholesky factor, larger ones
#: scipy.linalg.solve_triangular (measured: the faster of the two on each side).
_SMALL_BLOCK = 32
#: Smallest GP variance used in the BCM (guards 1/v).
_MIN_GP_VAR = 1e-12
#: The squashing functions.
SQUASHES = ('plsc', 'logistic')


def matern32(d: np.ndarray, sf2: float, ell: float) -> np.ndarray:
    """Matern covariance with nu = 3/2 (R&W Eq. 4.17; ``la3dm`` ``covMaterniso3``).

    Args:
        d: distances, metres (any shape, >= 0).
        sf2: signal variance.
        ell: length scale, metres.

    Returns:
        k(d), the shape of ``d``: ``sf2 (1 + sqrt(3) d / ell) exp(-sqrt(3) d / ell)``.
    """
    r = np.sqrt(3.0) / ell * np.asarray(d, dtype=np.float64)
    return sf2 * (1.0 + r) * np.exp(-r)


def _pack(index: np.ndarray) -> np.ndarray:
    """(N,) int64 key of (N, 3) int64 block indices (:func:`~uncertain_facade_map.voxels.pack_keys`).

    Raises:
        InputError: an index beyond +-2^20 blocks.
    """
    return pack_keys(index, unit='blocks')


_unpack = unpack_keys


def _size_class(n: np.ndarray) -> np.ndarray:
    """Padded GP size of blocks of ``n`` points: the next of 4, 6, 8, 12, 16, 24, 32, ..."""
    n = np.maximum(np.asarray(n, np.int64), 1)
    p = 2 ** np.floor(np.log2(n)).astype(np.int64)
    out = np.where(n <= p, p, np.where(n <= p + p // 2, p + p // 2, 2 * p))
    return np.maximum(out, 4)


def _lower_solve(lower: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """Batched ``L^-1 rhs`` for (B, n, n) lower-triangular Cholesky factors ``L``."""
    if lower.shape[-1] <= _SMALL_BLOCK:
        return np.linalg.solve(lower, rhs)
    return scipy.linalg.solve_triangular(lower, rhs, lower=True, check_finite=False)


def loo_moments(lower: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Leave-one-out predictive means and variances of GPs (R&W Eq. 5.12).

    Args:
        lower: (B, n, n) Cholesky factors of ``K + noise I``.
        y: (B, n) training targets.

    Returns:
        ``(mu, var)``: (B, n) ``y_i - [K^-1 y]_i / [K^-1]_ii`` and ``1 / [K^-1]_ii``, the
        mean and variance (noise included) of ``y_i`` predicted from the other points.
    """
    eye = np.broadcast_to(np.eye(lower.shape[-1]), lower.shape)
    inv_lower = _lower_solve(lower, eye)  # L^-1, for the diagonal of K^-1 (R&W Eq. 5.12)
    k_inv_diag = np.einsum('bji,bji->bi', inv_lower, inv_lower)
    k_inv_y = np.einsum('bji,bj->bi', inv_lower, np.einsum('bij,bj->bi', inv_lower, y))
    return y - k_inv_y / k_inv_diag, 1.0 / k_inv_diag


@dataclass(frozen=True, eq=False)
class _Grid:
    """Voxel keys ordered block by block over a bounding box (block-major, then the voxel
    within its block), so that sorting voxel keys sorts them by block.

    A block of ``c`` voxels a side (``c`` even) holds the voxels ``i`` with
    ``floor((i + c/2) / c) = k`` per axis: the block centred at ``k c r``
    (``block_to_hash_key``: ``floor(x / (c r) + 1/2)``).

    Attributes:
        resolution: voxel side, metres.
        c: voxels per block side.
        lo: (3,) int64 smallest block index of the box.
        dims: (3,) int64 blocks of the box per axis.
    """

    resolution: float
    c: int
    lo: np.ndarray
    dims: np.ndarray

    @classmethod
    def around(cls, lo_voxel: np.ndarray, hi_voxel: np.ndarray, resolution: float, c: int) -> _Grid:
        """The grid over the voxel indices ``lo_voxel`` .. ``hi_voxel`` (and one block more).

        Raises:
            InputError: the box holds too many voxels for a 63-bit key.
        """
        lo = (lo_voxel + c // 2) // c - 1
        hi = (hi_voxel + c // 2) // c + 1
        dims = hi - lo + 1
        if float(dims[0]) * float(dims[1]) * float(dims[2]) * c ** 3 >= 2.0 ** 62:
            raise InputError('the points span too many voxels to down-sample; '
                             'use map-frame coordinates near the origin')
        return cls(float(resolution), int(c), lo.astype(np.int64), dims.astype(np.int64))

    @property
    def cells(self) -> int:
        """Voxels per block."""
        return self.c ** 3

    def key(self, voxel: np.ndarray) -> np.ndarray:
        """(N,) int64 keys of (N, 3) int64 voxel indices ``floor(x / r)``."""
        c = self.c
        block = (voxel + c // 2) // c
        local = voxel + c // 2 - block * c
        block -= self.lo
        flat = (block[:, 0] * self.dims[1] + block[:, 1]) * self.dims[2] + block[:, 2]
        return flat * self.cells + (local[:, 0] * c + local[:, 1]) * c + local[:, 2]

    def block_index(self, flat: np.ndarray) -> np.ndarray:
        """(N, 3) int64 block indices of (N,) flat block numbers ``key // cells``."""
        return np.stack([flat // (self.dims[1] * self.dims[2]), (flat // self.dims[2]) % self.dims[1],
                         flat % self.dims[2]], axis=1) + self.lo

    def centre(self, keys: np.ndarray) -> np.ndarray:
        """(N, 3) float64 centres, metres, of the voxels of (N,) keys."""
        c = self.c
        local = keys % self.cells
        local = np.stack([local // (c * c), (local // c) % c, local % c], axis=1)
        voxel = self.block_index(keys // self.cells) * c - c // 2 + local
        return (voxel + 0.5) * self.resolution


@dataclass(eq=False)
class _Batch:
    """The training data of one batch, sorted by block.

    Attributes:
        x: (T, 3) float32 training inputs, metres, sorted by block key (float32, as the
            library's, to halve the memory).
        y: (T,) float32 labels, +1 hit, -1 free.
        keys: (B,) int64 sorted packed keys of the blocks holding training data.
        start: (B,) int64 offset of each block's points in ``x``.
        count: (B,) int64 number of each block's points.
    """

    x: np.ndarray
    y: np.ndarray
    keys: np.ndarray
    start: np.ndarray
    count: np.ndarray


class FastGPOMMethod(OccupancyMethod):
    """Fast GPOM / GPOctoMap (Wang and Englot, ICRA 2016), re-implemented with numpy/scipy.

    Args:
        resolution: voxel side, metres (> 0); also the down-sampling of the training data.
        block_depth: depth of the test-data octree; blocks have ``2^(block_depth - 1)``
            voxels a side (integer, 2 to 8; at depth 1 the library's blocks would be single
            voxels centred on the voxel grid's corners).
        sf2: signal variance of the Matern 3/2 kernel (> 0).
        ell: length scale of the kernel, metres (> 0).
        noise: noise variance of the GP regression (> 0).
        l: gain of the library's logistic squashing (``squash='logistic'``), > 0.
        min_var: lower clamp of the fused variance (> 0).
        max_var: prior (and upper) variance of the fused estimate (> ``min_var``).
        max_known_var: above this fused variance a voxel is unknown (:meth:`classify`), > 0.
        free_resolution: spacing of the free-space samples along a beam, metres (> 0).
        ds_resolution: voxel side of the hits' first down-sampling, metres (> 0).
        free_thresh: below this p a known voxel is free (:meth:`classify`), (0, 1).
        occupied_thresh: above this p a known voxel is occupied, (free_thresh, 1).
        squash: ``'plsc'`` (PLSC, the default) or ``'logistic'`` (the library's); see the
            module docstring.
        plsc_alpha: PLSC ``alpha`` (> 0), or None to learn it (with ``beta``) by LOO.
        plsc_beta: PLSC ``beta``, or None to learn it; both or neither must be given.
        loo_blocks: blocks (a seeded subset) whose LOO predictions fit ``alpha``, ``beta``.
        n_batches: None (the default, as the library) to fuse every scan as a batch of its
            own by the nested BCM, or an integer >= 1: merge consecutive scans (in time
            order) into that many batches.
        scan_size: side of the origin cubes that group rays into scans, metres (> 0).
        seed: seed of the LOO block subset.
        chunk: about this many matrix entries are handled at once (bounds memory; the result
            is the same), >= 1000.
        free_chunk: free-space samples made at once in ``fit`` (bounds memory), >= 1000.

    Raises:
        InputError: a parameter out of its range.
    """

    name = 'GPOM'
    trains_on_predict = True

    def __init__(self, resolution: float, block_depth: int = 3, sf2: float = 1.0, ell: float = 1.0,
                 noise: float = 0.01, l: float = 100.0, min_var: float = 0.001, max_var: float = 1000.0,
                 max_known_var: float = 0.02, free_resolution: float = 0.3, ds_resolution: float = 0.1,
                 free_thresh: float = 0.3, occupied_thresh: float = 0.7, squash: str = 'plsc',
                 plsc_alpha: float | None = None, plsc_beta: float | None = None, loo_blocks: int = 2000,
                 n_batches: int | None = None, scan_size: float = 1.0, seed: int = 0, chunk: int = 4_000_000,
                 free_chunk: int = 2_000_000) -> None:
        super().__init__(resolution)
        for label, value in (('sf2', sf2), ('ell', ell), ('noise', noise), ('l', l), ('min_var', min_var),
                             ('max_var', max_var), ('max_known_var', max_known_var),
                             ('free_resolution', free_resolution), ('ds_resolution', ds_resolution),
                             ('scan_size', scan_size)):
            check_positive(label, value)
        if min_var >= max_var:
            raise InputError(f'min_var ({min_var!r}) must be below max_var ({max_var!r})')
        if not 0.0 < free_thresh < occupied_thresh < 1.0:
            raise InputError(f'need 0 < free_thresh < occupied_thresh < 1, got {free_thresh!r} and {occupied_thresh!r}')
        for label, value, low in (('block_depth', block_depth, 2), ('loo_blocks', loo_blocks, 1),
                                  ('n_batches', 1 if n_batches is None else n_batches, 1),
                                  ('chunk', chunk, 1000),
                                  ('free_chunk', free_chunk, 1000)):
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < low:
                raise InputError(f'{label} must be an integer >= {low}, got {value!r}')
        if block_depth > 8:
            raise InputError(f'block_depth must be at most 8 (blocks of 128 voxels a side), got {block_depth!r}')
        if squash not in SQUASHES:
            raise InputError(f'squash must be one of {", ".join(SQUASHES)}, got {squash!r}')
        if (plsc_alpha is None) != (plsc_beta is None):
            raise InputError('give both plsc_alpha and plsc_beta, or neither (to learn them)')
        if plsc_alpha is not None:
            if not (np.isfinite(plsc_alpha) and plsc_alpha > 0):
                raise InputError(f'plsc_alpha must be a positive number, got {plsc_alpha!r}')
            if not np.isfinite(plsc_beta):
                raise InputError(f'plsc_beta must be a finite number, got {plsc_beta!r}')
        self.block_depth = int(block_depth)
        self.block_size = float(2 ** (self.block_depth - 1)) * self.resolution
        self.sf2, self.ell, self.noise, self.l = float(sf2), float(ell), float(noise), float(l)
        self.min_var, self.max_var, self.max_known_var = float(min_var), float(max_var), float(max_known_var)
        self.free_resolution, self.ds_resolution = float(free_resolution), float(ds_resolution)
        self.free_thresh, self.occupied_thresh = float(free_thresh), float(occupied_thresh)
        self.squash = squash
        self.plsc_alpha = None if plsc_alpha is None else float(plsc_alpha)
        self.plsc_beta = None if plsc_beta is None else float(plsc_beta)
        self.loo_blocks, self.seed = int(loo_blocks), int(seed)
        self.n_batches = None if n_batches is None else int(n_batches)
        self.scan_size = float(scan_size)
        self.chunk, self.free_chunk = int(chunk), int(free_chunk)
        self.batches_: list[_Batch] | None = None
        self.alpha_: float | None = None
        self.beta_: float | None = None
        self.n_scans_ = 0
        self._last: tuple[np.ndarray, tuple[np.ndarray, np.ndarray, np.ndarray]] | None = None

    # ------------------------------------------------------------------ training data

    def _free_samples(self, hits: np.ndarray, origins: np.ndarray, grid: _Grid) -> tuple[np.ndarray, np.ndarray]:
        """The beams' free samples down-sampled at the resolution (PCL ``VoxelGrid``).

        The samples are ``beam_sample``'s plus the origin of each beam (``get_training_data``
        pushes it per beam); they are made in chunks of beams of about ``free_chunk``
        samples and kept as a grid key and a float32 offset within the voxel each.

        Returns:
            ``(keys, centroids)``: (F,) int64 sorted unique grid keys of the voxels holding
            samples and (F, 3) float32 the centroid of each voxel's samples, metres.
        """
        step, r = self.free_resolution, self.resolution
        length = np.linalg.norm(hits - origins, axis=1)
        n = np.maximum(np.ceil(length / step).astype(np.int64) - 1, 0) + (length > step) + 1
        end = np.cumsum(n)
        keys = np.empty(int(end[-1]), dtype=np.int64)
        offset = np.empty((int(end[-1]), 3), dtype=np.float32)
        cuts = np.searchsorted(end, np.arange(self.free_chunk, end[-1], self.free_chunk), side='right')
        edges = np.unique(np.r_[0, cuts, len(hits)])
        for a, b in zip(edges[:-1].tolist(), edges[1:].tolist()):
            samples = np.concatenate([beam_samples(hits[a:b], origins[a:b], step)[0], origins[a:b]])
            voxel = np.floor(samples / r).astype(np.int64)
            rows = slice(int(end[a] - n[a]), int(end[b - 1]))
            keys[rows] = grid.key(voxel)
            offset[rows] = samples - voxel * r
        order = np.argsort(keys)
        keys = keys[order]
        first = np.flatnonzero(np.r_[True, keys[1:] != keys[:-1]])
        keys = keys[first]
        first = np.r_[first, len(order)]
        centroids = np.empty((len(keys), 3), np.float32)
        for g in range(0, len(keys), self.free_chunk):  # in chunks: bounds the memory
            h = min(g + self.free_chunk, len(keys))
            rows = order[first[g]:first[h]]
            starts = first[g:h] - first[g]
            mean = np.add.reduceat(offset[rows].astype(np.float64), starts, axis=0) / np.diff(first[g:h + 1])[:, None]
            centroids[g:h] = grid.centre(keys[g:h]) - 0.5 * r + mean
        return keys, centroids

    def _batch(self, points: np.ndarray, origins: np.ndarray, scan: np.ndarray) -> _Batch:
        """Training data of the scans of one batch, pooled, down-sampled and sorted by block."""
        r = self.resolution
        # Hits: the server's VoxelGrid at ds_resolution, then get_training_data's at the
        # resolution, per scan; each beam keeps the mean origin of its hits.
        hits, hit_scan, hit_origin = voxel_centroids(points, self.ds_resolution, scan, origins)
        if r != self.ds_resolution:
            hits, hit_scan, hit_origin = voxel_centroids(hits, r, hit_scan, hit_origin)
        both = np.floor(np.concatenate([hits, hit_origin]) / r).astype(np.int64)
        grid = _Grid.around(both.min(axis=0), both.max(axis=0), r, 2 ** (self.block_depth - 1))
        free, free_x = self._free_samples(hits, hit_origin, grid)
        # The batch's hits pooled over its scans and down-sampled once at the resolution.
        hits, _, _ = voxel_centroids(hits, r)
        hit_keys = grid.key(np.floor(hits / r).astype(np.int64))
        order = np.argsort(hit_keys, kind='stable')
        hits, hit_keys = hits[order], hit_keys[order]
        # Merge the hits into the sorted free keys: the grid keys are block-major, so the
        # merged training data come sorted by block.
        total = len(free) + len(hits)
        at = np.searchsorted(free, hit_keys, side='right') + np.arange(len(hits))
        keys = np.empty(total, np.int64)
        x = np.empty((total, 3), np.float32)
        y = np.full(total, -1.0, np.float32)
        keys[at], x[at], y[at] = hit_keys, hits, 1.0
        into = np.arange(len(free)) + np.searchsorted(hit_keys, free, side='left')
        keys[into], x[into] = free, free_x
        del free, free_x, into
        block = keys // grid.cells
        start = np.flatnonzero(np.r_[True, block[1:] != block[:-1]])
        count = np.diff(np.r_[start, total])
        return _Batch(x, y, _pack(grid.block_index(block[start])), start, count)

    # ------------------------------------------------------------------ local GPs

    def _train(self, batch: _Batch, blocks: np.ndarray, size: int
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Cholesky factors of the GPs of ``blocks`` (indices into the batch), padded to ``size``.

        Returns:
            ``(lower, x, y, mask, centre)``: (B, n, n) Cholesky factors of ``K + noise I``
            (identity on padding), (B, n, 3) inputs relative to the block centre (0 on
            padding), (B, n) labels (0 on padding), (B, n) bool real points, (B, 3) centres.
        """
        centre = _unpack(batch.keys[blocks]).astype(np.float64) * self.block_size
        slot = np.arange(size)
        mask = slot[None, :] < batch.count[blocks, None]
        idx = np.where(mask, batch.start[blocks, None] + slot[None, :], 0)
        x = np.where(mask[..., None], batch.x[idx].astype(np.float64) - centre[:, None, :], 0.0)
        y = np.where(mask, batch.y[idx].astype(np.float64), 0.0)
        k = matern32(_distances(x, x), self.sf2, self.ell)
        k *= mask[:, :, None] & mask[:, None, :]
        k[:, slot, slot] += np.where(mask, self.noise, 1.0)
        try:
            lower = np.linalg.cholesky(k)
        except np.linalg.LinAlgError as err:  # pragma: no cover - K + noise I is positive definite
            raise InputError(f'a block GP is not positive definite: {err}') from err
        return lower, x, y, mask, centre

    def _pairs(self, batch: _Batch, tkeys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The GP blocks serving the test blocks ``tkeys`` and which test blocks each serves.

        Returns:
            ``(gp_blocks, served)``: (G,) indices into the batch's blocks, and (G, 7) int64
            index into ``tkeys`` of the test block each serves through each face offset,
            -1 where there is none.
        """
        # A GP at block g serves the test blocks g - offset (the offsets are symmetric).
        neighbours = _pack((_unpack(batch.keys)[:, None, :] - EXTENDED_BLOCK[None]).reshape(-1, 3))
        tpos = np.minimum(np.searchsorted(tkeys, neighbours), len(tkeys) - 1)
        served = np.where(tkeys[tpos] == neighbours, tpos, -1).reshape(-1, len(EXTENDED_BLOCK))
        gp_blocks = np.flatnonzero((served >= 0).any(axis=1))
        served = served[gp_blocks]
        return gp_blocks, served

    def _predict_batch(self, batch: _Batch, xyz: np.ndarray, order: np.ndarray, tkeys: np.ndarray,
                       tstart: np.ndarray, tcount: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Every (query, GP) prediction of one batch.

        Returns:
            ``(query, mean, var)``: (P,) int64 query index, (P,) GP mean and (P,) GP variance
            of each pair of a queried point and a GP of its extended block.
        """
        gp_blocks, served = self._pairs(batch, tkeys)
        if not len(gp_blocks):
            return np.empty(0, np.int64), np.empty(0), np.empty(0)
        n_served = np.where(served >= 0, tcount[np.maximum(served, 0)], 0)
        q = n_served.sum(axis=1)
        size = _size_class(batch.count[gp_blocks])
        out_q, out_m, out_v = [], [], []
        for n in np.unique(size):
            members = np.flatnonzero(size == n)
            members = members[np.argsort(q[members], kind='stable')]
            # Chunks of about self.chunk matrix entries (B n (n + q + 1)).
            cost = np.cumsum(n * (n + q[members] + 1))
            cuts = np.searchsorted(cost, np.arange(self.chunk, cost[-1], self.chunk))
            for part in np.split(members, np.unique(cuts)):
                if len(part):
                    out = self._predict_chunk(batch, gp_blocks[part], int(n), served[part], n_served[part],
                                              xyz, order, tstart)
                    out_q.append(out[0]), out_m.append(out[1]), out_v.append(out[2])
        return np.concatenate(out_q), np.concatenate(out_m), np.concatenate(out_v)

    def _predict_chunk(self, batch: _Batch, blocks: np.ndarray, n: int, served: np.ndarray, n_served: np.ndarray,
                       xyz: np.ndarray, order: np.ndarray, tstart: np.ndarray
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """GP predictions of a chunk of blocks of one padded size at the queries they serve."""
        lower, x, y, mask, centre = self._train(batch, blocks, n)
        n_blocks, n_off = served.shape
        flat = n_served.ravel()
        total = int(flat.sum())
        entry = np.repeat(np.arange(n_blocks * n_off), flat)                 # (block, offset) of each entry
        within = np.arange(total) - np.repeat(np.cumsum(flat) - flat, flat)  # rank within its test block
        query = order[tstart[served.ravel()[entry]] + within]
        block = entry // n_off
        per_block = n_served.sum(axis=1)
        slot = np.arange(total) - np.repeat(np.cumsum(per_block) - per_block, per_block)
        width = int(per_block.max())
        xs = np.zeros((n_blocks, width, 3))
        xs[block, slot] = xyz[query] - centre[block]
        ks = matern32(_distances(x, xs), self.sf2, self.ell) * mask[:, :, None]
        # One triangular solve gives L^-1 y and L^-1 k_*: m = (L^-1 k_*)^T (L^-1 y) and
        # v = sf2 - |L^-1 k_*|^2 (R&W Eq. 2.25-2.26 through the Cholesky factor, Alg. 2.1).
        z = _lower_solve(lower, np.concatenate([y[:, :, None], ks], axis=2))
        w, v = z[:, :, 0], z[:, :, 1:]
        mean = np.einsum('bn,bnq->bq', w, v)[block, slot]
        var = (self.sf2 - np.einsum('bnq,bnq->bq', v, v))[block, slot]
        return query, mean, var

    # ------------------------------------------------------------------ PLSC

    def _loo(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """LOO means, variances (R&W Eq. 5.12) and labels of the training points of a seeded
        subset of blocks (``loo_blocks`` over all batches, each block's own GP)."""
        owners = np.concatenate([np.full(len(b.keys), i) for i, b in enumerate(self.batches_)])
        local = np.concatenate([np.arange(len(b.keys)) for b in self.batches_])
        rng = np.random.default_rng(self.seed)
        pick = rng.choice(len(owners), min(self.loo_blocks, len(owners)), replace=False)
        mus, variances, labels = [], [], []
        for i, batch in enumerate(self.batches_):
            blocks = np.sort(local[pick[owners[pick] == i]])
            size = _size_class(batch.count[blocks])
            for n in np.unique(size):
                lower, _, y, mask, _ = self._train(batch, blocks[size == n], int(n))
                mu, var = loo_moments(lower, y)
                mus.append(mu[mask]), variances.append(var[mask]), labels.append(y[mask])
        return np.concatenate(mus), np.concatenate(variances), np.concatenate(labels)

    def _fit_plsc(self) -> tuple[float, float]:
        """``(alpha, beta)`` maximising the LOO probability of the labels (R&W Eq. 6.42)."""
        from scipy.optimize import minimize  # noqa: PLC0415 - only needed here

        mu, var, y = self._loo()

        def loss(theta: np.ndarray) -> float:
            alpha, beta = np.exp(theta[0]), theta[1]
            return -float(log_ndtr(y * (alpha * mu + beta) / np.sqrt(1.0 + alpha ** 2 * var)).mean())

        best = minimize(loss, np.zeros(2), method='Nelder-Mead', options={'xatol': 1e-4, 'fatol': 1e-9})
        return float(np.exp(best.x[0])), float(best.x[1])

    # ------------------------------------------------------------------ interface

    def fit(self, points: np.ndarray, origins: np.ndarray) -> FastGPOMMethod:
        """Build the training data of every batch of scans and the PLSC parameters.

        Args:
            points: (N, 3) float64 hits, map frame, metres.
            origins: (N, 3) float64 sensor origin of each hit, map frame, metres.

        Returns:
            self, with ``batches_`` (the training data of each batch, by block),
            ``alpha_`` and ``beta_`` (PLSC; learnt unless given) and ``n_scans_``.

        Raises:
            InputError: bad shapes, an empty or non-finite input, or coordinates too far from
                the map origin.
        """
        points, origins = check_scans(points, origins)
        order, starts, _ = group_by_origin(origins, self.scan_size)
        n_scans = len(starts) - 1
        scan = np.empty(len(points), dtype=np.int64)
        scan[order] = np.repeat(np.arange(n_scans), np.diff(starts))
        n_batches = n_scans if self.n_batches is None else min(self.n_batches, n_scans)
        # Batch b holds the scans first[b] .. first[b + 1] - 1 (scans are numbered in time order).
        first = np.arange(n_batches + 1) * n_scans // n_batches
        batches = []
        for b in range(n_batches):
            rows = order[starts[first[b]]:starts[first[b + 1]]]
            batches.append(self._batch(points[rows], origins[rows], scan[rows]))
        self.batches_ = batches
        self.n_scans_ = n_scans
        self._last = None
        if self.plsc_alpha is not None:
            self.alpha_, self.beta_ = self.plsc_alpha, self.plsc_beta
        else:
            with one_blas_thread():
                self.alpha_, self.beta_ = self._fit_plsc()
        return self

    def _posterior(self, xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(M,) fused precision (unclamped, prior included), precision-weighted mean sum, and
        occupancy probability at (M, 3) ``xyz``; cached for the last array asked."""
        if self.batches_ is None:
            raise InputError('fit the method before predicting')
        xyz = check_queries(xyz)
        if self._last is not None and self._last[0] is xyz:
            return self._last[1]
        m = len(xyz)
        precision = np.full(m, 1.0 / self.max_var)
        weighted = np.zeros(m)
        known = np.zeros(m, bool)
        if m:
            qkeys = _pack(np.floor(xyz / self.block_size + 0.5).astype(np.int64))
            order = np.argsort(qkeys, kind='stable')
            tkeys, tstart, tcount = np.unique(qkeys[order], return_index=True, return_counts=True)
            # The batches' GPs are independent: predicted on one thread per core (at most 4;
            # their BLAS calls release the GIL), fused in batch order, so the sums are the same.
            with one_blas_thread(), ThreadPoolExecutor(min(4, os.cpu_count() or 1)) as pool:
                for query, mean, var in pool.map(
                        lambda batch: self._predict_batch(batch, xyz, order, tkeys, tstart, tcount), self.batches_):
                    var = np.maximum(var, _MIN_GP_VAR)
                    # Nested BCM (Tresp 2000; la3dm Occupancy::update): precisions add up.
                    precision += np.bincount(query, 1.0 / var - 1.0 / self.sf2, m)
                    weighted += np.bincount(query, mean / var, m)
                    known[query] = True
        if self.squash == 'logistic':
            # la3dm Occupancy::get_prob: 1 / (1 + exp(-l m_ivar / max_ivar)).
            p = expit(self.l * weighted * self.min_var)
        else:
            # PLSC (R&W Eq. 6.41) on the fused mean and (clamped) variance.
            var_f = 1.0 / np.minimum(precision, 1.0 / self.min_var)
            p = ndtr((self.alpha_ * weighted / precision + self.beta_) / np.sqrt(1.0 + self.alpha_ ** 2 * var_f))
        p = np.where(known, p, 0.5)
        self._last = (xyz, (precision, weighted, p))
        return precision, weighted, p

    def predict(self, xyz: np.ndarray) -> np.ndarray:
        """Occupancy probability of the voxels centred at ``xyz``.

        Args:
            xyz: (M, 3) float64 voxel centres, map frame, metres.

        Returns:
            (M,) float64 in [0, 1] (see ``squash``); 0.5 where no training data lie in the
            voxel's extended block (the voxel is not predicted).

        Raises:
            InputError: not fitted, ``xyz`` not a finite (M, 3) array, or too far from the
                map origin.
        """
        return self._posterior(xyz)[2]

    def predict_variance(self, xyz: np.ndarray) -> np.ndarray:
        """(M,) fused GP variance at ``xyz`` (label units, +-1 labels), in
        ``[min_var, max_var]``; ``max_var`` where the voxel is not predicted."""
        precision = self._posterior(xyz)[0]
        return 1.0 / np.minimum(precision, 1.0 / self.min_var)

    def classify(self, xyz: np.ndarray) -> np.ndarray:
        """(M,) int8 labels as the library draws them: -1 unknown where the fused variance
        exceeds ``max_known_var``, else 1 occupied (p above ``occupied_thresh``), 0 free (p
        below ``free_thresh``), -1 between."""
        p = self.predict(xyz)
        known = self.predict_variance(xyz) <= self.max_known_var
        label = np.where(p > self.occupied_thresh, 1, np.where(p < self.free_thresh, 0, -1))
        return np.where(known, label, -1).astype(np.int8)


def _distances(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(B, n, m) Euclidean distances between (B, n, 3) ``a`` and (B, m, 3) ``b``."""
    sq = (a * a).sum(-1)[:, :, None] + (b * b).sum(-1)[:, None, :] - 2.0 * np.matmul(a, b.transpose(0, 2, 1))
    return np.sqrt(np.maximum(sq, 0.0))
