"""BGKOctoMap as a baseline occupancy method (numpy/scipy re-implementation).

Method: K. Doherty, J. Wang, B. Englot, "Bayesian generalized kernel inference for
occupancy map prediction", ICRA 2017 (the ``la3dm`` library's BGKOctoMap). Training data
are the scan's hits, labelled 1, and free-space samples along the beams, labelled 0. The
occupancy of a test voxel at ``x`` is a Beta posterior whose pseudo-counts add the
kernel-weighted labels of the training points near it (paper Eqs. (11)-(13))::

    alpha = alpha_0 + sum_i k(x, x_i) y_i
    beta  = beta_0  + sum_i k(x, x_i) (1 - y_i)
    p     = alpha / (alpha + beta)
    var   = alpha beta / ((alpha + beta)^2 (alpha + beta + 1))

with the sparse kernel of Melkumyan and Ramos (2009), zero beyond the length scale ``ell``
(paper Eq. (14))::

    k(d) = sf2 [ (2 + cos(2 pi d / ell)) / 3 (1 - d / ell) + sin(2 pi d / ell) / (2 pi) ],  d < ell

Parameters: the authors' published configuration (``la3dm`` ``config/methods/bgkoctomap.yaml``):
resolution 0.1 m (here: the evaluation's resolution), block depth 3, ``sf2`` 1.0, ``ell``
0.2 m, free-space sampling every ``free_resolution`` 0.5 m, down-sampling of hits and free
samples to ``ds_resolution`` 0.1 m (PCL voxel-grid centroids), free/occupied thresholds
0.3 / 0.7 (used only by :meth:`BGKOctoMapMethod.classify`), prior pseudo-counts
``prior_A`` = ``prior_B`` = 0.001, no maximum range.

How the library builds the training data of one scan (``get_training_data``), kept here:
the hits are down-sampled to voxel-grid centroids; each down-sampled hit gives a beam from
the origin, sampled every ``free_resolution`` from the origin up to (not including) the
hit and once more ``free_resolution`` before the hit (``beam_sample``,
:func:`.base.beam_samples`), plus the origin itself; those free samples are down-sampled
the same way. Scans add
their pseudo-counts, so a voxel seen in many scans gathers evidence from each.

What was simplified / chosen here:

- **Scans.** The library inserts one scan per sensor pose. Our points carry a sensor origin
  each (a moving vehicle), so rays are grouped into scans by their origins: origins in the
  same cube of side ``scan_size`` (default 1 m, about 0.1 s of the simulated drive, the
  length of the bags' scans) form one scan. Each beam keeps its own origin (the mean of the
  origins of the rays down-sampled into its hit), so the free samples are on the real rays.
- **Blocks and the test-data octree** (block depth 3: blocks of 4 x 4 x 4 voxels) only
  decide which voxels the library predicts: those of blocks whose extended block (the
  block and its 26 neighbours) holds training data. Since the kernel is zero beyond
  ``ell`` <= the block side, the sums above are the same over all training points within
  ``ell``, which is what is computed here (a k-d tree); a voxel with no training point
  within ``ell`` keeps its prior, 0.5, as an unpredicted voxel does in the library.
- All scans are inserted before the voxels are asked; the sums are order-independent, so
  this equals inserting them one after the other.
"""

from __future__ import annotations

import numpy as np

from ...errors import InputError
from .base import (
    OccupancyMethod,
    beam_samples,
    check_positive,
    check_queries,
    check_scans,
    group_by_origin,
    voxel_centroids,
)


def sparse_kernel(d: np.ndarray, sf2: float, ell: float) -> np.ndarray:
    """The sparse kernel of Melkumyan and Ramos (BGKOctoMap paper Eq. (14)).

    Args:
        d: distances, metres (any shape, >= 0).
        sf2: kernel scale (the library's ``sf2``, "sigma_0").
        ell: support radius, metres: the kernel is 0 at and beyond it.

    Returns:
        k(d), the shape of ``d``; ``sf2`` at 0, falling smoothly to 0 at ``ell``.
    """
    t = np.asarray(d, dtype=np.float64) / ell
    k = sf2 * ((2.0 + np.cos(2.0 * np.pi * t)) / 3.0 * (1.0 - t) + np.sin(2.0 * np.pi * t) / (2.0 * np.pi))
    return np.where(t < 1.0, k, 0.0)


class BGKOctoMapMethod(OccupancyMethod):
    """BGKOctoMap (Doherty, Wang and Englot, ICRA 2017), re-implemented with numpy/scipy.

    Args:
        resolution: voxel side, metres (> 0).
        sf2: sparse kernel scale (> 0).
        ell: sparse kernel support radius, metres (> 0).
        free_resolution: spacing of the free-space samples along a beam, metres (> 0).
        ds_resolution: voxel side of the down-sampling of hits and free samples, metres (> 0).
        prior_a: prior pseudo-count of the occupied class (> 0).
        prior_b: prior pseudo-count of the free class (> 0).
        free_thresh: below this a voxel is free (:meth:`classify`), (0, 1).
        occupied_thresh: above this a voxel is occupied (:meth:`classify`), (free_thresh, 1).
        scan_size: side of the origin cubes that group rays into scans, metres (> 0).
        chunk: query voxels handled at once (bounds memory; the result is the same).
        beam_chunk: beams sampled at once (bounds memory; the result is the same).

    Raises:
        InputError: a parameter out of its range.
    """

    name = 'BGKOctoMap'

    def __init__(self, resolution: float, sf2: float = 1.0, ell: float = 0.2, free_resolution: float = 0.5,
                 ds_resolution: float = 0.1, prior_a: float = 0.001, prior_b: float = 0.001,
                 free_thresh: float = 0.3, occupied_thresh: float = 0.7, scan_size: float = 1.0,
                 chunk: int = 50_000, beam_chunk: int = 100_000) -> None:
        super().__init__(resolution)
        for label, value in (('sf2', sf2), ('ell', ell), ('free_resolution', free_resolution),
                             ('ds_resolution', ds_resolution), ('prior_a', prior_a), ('prior_b', prior_b),
                             ('scan_size', scan_size)):
            check_positive(label, value)
        if not 0.0 < free_thresh < occupied_thresh < 1.0:
            raise InputError(f'need 0 < free_thresh < occupied_thresh < 1, got {free_thresh!r} and {occupied_thresh!r}')
        if int(chunk) < 1 or int(beam_chunk) < 1:
            raise InputError(f'chunk and beam_chunk must be >= 1, got {chunk!r} and {beam_chunk!r}')
        self.sf2, self.ell = float(sf2), float(ell)
        self.free_resolution, self.ds_resolution = float(free_resolution), float(ds_resolution)
        self.prior_a, self.prior_b = float(prior_a), float(prior_b)
        self.free_thresh, self.occupied_thresh = float(free_thresh), float(occupied_thresh)
        self.scan_size = float(scan_size)
        self.chunk = int(chunk)
        self.beam_chunk = int(beam_chunk)
        self.train_x_: np.ndarray | None = None
        self.train_y_: np.ndarray | None = None
        self.tree_ = None
        self.n_scans_ = 0
        self._last: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None

    def fit(self, points: np.ndarray, origins: np.ndarray) -> BGKOctoMapMethod:
        """Build the training data of every scan (hits 1, free samples 0).

        Args:
            points: (N, 3) float64 hits, map frame, metres.
            origins: (N, 3) float64 sensor origin of each hit, map frame, metres.

        Returns:
            self, with ``train_x_`` (T, 3), ``train_y_`` (T,) in {0, 1}, ``tree_`` (their
            k-d tree) and ``n_scans_``.

        Raises:
            InputError: bad shapes, an empty or non-finite input.
        """
        from scipy.spatial import cKDTree

        points, origins = check_scans(points, origins)
        order, starts, _ = group_by_origin(origins, self.scan_size)
        scan = np.empty(len(points), dtype=np.int64)
        scan[order] = np.repeat(np.arange(len(starts) - 1), np.diff(starts))
        # get_training_data: down-sampled hits (label 1) ...
        hits, hit_scan, hit_origin = voxel_centroids(points, self.ds_resolution, scan, origins)
        # ... and the free samples of their beams with each beam's origin, down-sampled
        # per scan (label 0); beams in chunks to bound the memory.
        free_parts = []
        for start in range(0, len(hits), self.beam_chunk):
            part = slice(start, start + self.beam_chunk)
            samples, beam = beam_samples(hits[part], hit_origin[part], self.free_resolution)
            free_parts.append((np.concatenate([samples, hit_origin[part]]),
                               np.r_[hit_scan[part][beam], hit_scan[part]]))
        free, free_scan = (np.concatenate(x) for x in zip(*free_parts))
        free, _, _ = voxel_centroids(free, self.ds_resolution, free_scan)
        self.train_x_ = np.concatenate([hits, free])
        self.train_y_ = np.r_[np.ones(len(hits)), np.zeros(len(free))]
        self.tree_ = cKDTree(self.train_x_)
        self.n_scans_ = len(starts) - 1
        self._last = None
        return self

    def _posterior(self, xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(M,) posterior mean and variance at (M, 3) ``xyz`` (Eqs. (11)-(13))."""
        if self.tree_ is None:
            raise InputError('fit the method before predicting')
        xyz = check_queries(xyz)
        if self._last is not None and self._last[0] is xyz:
            return self._last[1], self._last[2]
        from scipy.spatial import cKDTree

        ybar = np.zeros(len(xyz))
        kbar = np.zeros(len(xyz))
        for start in range(0, len(xyz), self.chunk):
            part = xyz[start:start + self.chunk]
            pairs = cKDTree(part).sparse_distance_matrix(self.tree_, self.ell, output_type='ndarray')
            k = sparse_kernel(pairs['v'], self.sf2, self.ell)
            ybar[start:start + len(part)] = np.bincount(pairs['i'], weights=k * self.train_y_[pairs['j']],
                                                        minlength=len(part))
            kbar[start:start + len(part)] = np.bincount(pairs['i'], weights=k, minlength=len(part))
        alpha = self.prior_a + ybar
        beta = self.prior_b + (kbar - ybar)
        total = alpha + beta
        mean = alpha / total
        var = alpha * beta / (total * total * (total + 1.0))
        self._last = (xyz, mean, var)
        return mean, var

    def predict(self, xyz: np.ndarray) -> np.ndarray:
        """Occupancy probability (the Beta posterior mean) of the voxels centred at ``xyz``.

        Args:
            xyz: (M, 3) float64 voxel centres, map frame, metres.

        Returns:
            (M,) float64 in [0, 1]; the prior's 0.5 where no training point is within ``ell``.

        Raises:
            InputError: not fitted, or ``xyz`` not a finite (M, 3) array.
        """
        return self._posterior(xyz)[0]

    def predict_variance(self, xyz: np.ndarray) -> np.ndarray:
        """(M,) variance of the Beta posterior at ``xyz`` (dimensionless, at most 1/4)."""
        return self._posterior(xyz)[1]

    def classify(self, xyz: np.ndarray) -> np.ndarray:
        """(M,) int8 labels as the library draws them: 1 occupied (mean above
        ``occupied_thresh``), 0 free (below ``free_thresh``), -1 unknown otherwise."""
        mean = self.predict(xyz)
        return np.where(mean > self.occupied_thresh, 1, np.where(mean < self.free_thresh, 0, -1)).astype(np.int8)
