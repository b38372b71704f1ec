"""GPIS map (GPisMap) as a baseline occupancy method (numpy/scipy re-implementation).

Method: B. Lee, C. Zhang, Z. Huang, D. D. Lee, "Online continuous mapping using Gaussian
process implicit surfaces", ICRA 2019 (the authors' code: github.com/leebhoram/GPisMap,
``GPisMap`` for 2D LiDAR scans, ``GPisMap3`` for 3D). The surface is the zero level set of
a field f modelled by local Gaussian processes (GPs) on an octree of surface points:

- **Surface points.** Hits are inserted into an octree whose smallest nodes hold one point
  each (a point is refused when its leaf is taken): the map's own down-sampling. Every
  surface point carries the value observation ``-fbias`` (the GP has zero prior mean, so
  the field ``f = mean + fbias`` is 0 on the surface and tends to ``fbias`` far from it)
  and, as a derivative observation, its unit surface normal, pointing out of the solid
  (towards the sensor). Noise of a point (``GPisMap3::evalPoints``)::

      sigma_x^2 = min_pos_noise * clip(range, 1, 100) + min_pos_noise * (1 - c^2) / c^2
      sigma_g^2 = min_grad_noise

  with ``c = max(cos(incidence angle), 0.1)``. A point without a normal keeps only its
  value observation, with noise 2.0 (``OnGPIS::train``).
- **Local GPs.** Each non-empty octree node of half side ``cluster_half_length`` (a
  "cluster") holds a GP trained on the surface points within ``rtimes *
  cluster_half_length`` of its centre (``GPisMap3::updateGPs_kernel``), with the Matérn 3/2
  kernel and its derivatives (``covFnc.cpp``, ``matern32_sparse_deriv1``; derivative
  observations as in Rasmussen & Williams 2006, Sec. 9.4)::

      k(r) = (1 + a r) exp(-a r),                    a = sqrt(3) / length_scale
      cov(f(x), df(x')/dx'_i)       =  a^2 d_i exp(-a r),           d = x - x'
      cov(df(x)/dx_i, f(x'))        = -a^2 d_i exp(-a r)
      cov(df(x)/dx_i, df(x')/dx'_j) =  a^2 (delta_ij - a d_i d_j / r) exp(-a r)

  The posterior at a query x* is the standard GP prediction (R&W Eqs. (2.25)-(2.26), by
  Cholesky, their Algorithm 2.1): ``mean = k*^T alpha``, ``var = 1.001 - |L^-1 k*|^2``
  (``OnGPIS::testSinglePoint``: prior variance 1 plus 0.001).
- **Queries** (``GPisMap3::test_kernel``): the clusters whose box meets the query's box of
  half side ``3 * cluster_half_length`` are candidates; the nearest (by centre) answers.
  If its variance exceeds ``var_threshold`` (0.5) and there are other candidates, the up
  to 3 nearest are asked; the one with the lowest variance answers if that is below the
  threshold, else the two lowest are blended with weights ``(var_other - thr)``.

Occupancy: the same two readings as our map (:mod:`.facade_gp`, :mod:`~uncertain_facade_map.pipeline.step8_occupancy`), so
the two implicit-surface maps are read by one rule. With f the field at the voxel centre
(positive outside, on the sensor side), var its variance and sigma^2 = var + map_noise
(GPisMap's map noise parameter, the floor it puts on a fused surface point's noise; our
choice of noise term):

- ``surface`` (default, :class:`GPISMapMethod`): the probability that the voxel holds
  the surface, ``Phi((r/2 - f)/sigma) - Phi((-r/2 - f)/sigma)``; a voxel with no
  candidate cluster holds no modelled surface: 0.
- ``solid`` (:class:`GPISMapSolidMethod`): ``Phi((r/2 - f)/sigma)``, the solid behind the
  surface; a voxel with no candidate cluster is unknown, 0.5.

(r/2 is the voxel's half extent along f's gradient for walls along the grid; f's
gradient is not evaluated at queries.) Where no cluster is near, the code returns f = 0
and var = 1 + map_noise, which :meth:`GPISMapMethod.predict_variance` reports. f is a
signed distance only near the surface (its gradient is observed as a unit normal there);
away from it, it returns to ``fbias`` and its variance to the prior's 1.

Parameters (``cpp/include/params.h`` of leebhoram/GPisMap, and the source files named):

- From ``GPisMap3`` (3D): ``rtimes`` 2.0 (GPISMAP3_RTIMES), ``fbias`` 0.2
  (GPISMAP3_FBIAS), ``min_pos_noise`` 1e-3 (GPISMAP3_MIN_POS_NOISE), ``min_grad_noise``
  1e-2 (GPISMAP3_MIN_GRAD_NOISE), ``map_noise`` 5e-3 (GPISMAP3_MAP_NOISE), query box half
  side 3 clusters and ``var_threshold`` 0.5 (``GPisMap3::test_kernel``), gradient-noise
  limit 0.1001 and value noise 2.0 for points without a normal (``OnGPIS::train``).
- Spatial scale from ``GPisMap`` (the authors' LiDAR configuration): ``length_scale`` 1.2 m
  (GPISMAP_MAP_SCALE), ``cluster_half_length`` 0.8 m (GPISMAP_TREE_CLUSTER_HALF_LENGTH).
  GPisMap3's own values (GPISMAP3_MAP_SCALE 0.04 m, cluster half side 0.025 m, minimum
  node half side 0.00625 m) are sized for a depth camera looking at a table-top object at
  0.4-4 m: on a street scanned from 10-25 m their kernel's correlation would fall to 0.07
  at 10 cm and every voxel more than ~0.1 m from a cluster would be unknown. The
  authors' own setting for a laser scanner (up to
  30 m) is what they would use here; the two configurations share their proportions
  (length scale ~1.5 cluster half sides, minimum node = cluster / 4).

What was simplified / chosen here:

- **Minimum node half side 0.4 m** instead of the published 0.2 m
  (GPISMAP_TREE_MIN_HALF_LENGTH), for the evaluation's budget (90 s, 4 GB): the octree's
  down-sampling keeps one surface point per 0.4 m cube. On the street (1.1 M hits) that
  gives 50 k surface points, 3 429 clusters and local GP systems of 180 rows on average
  (at most 488; 1.3 GB of Cholesky factors); with 0.2 m it would be 205 k points and
  784 rows on average (at most 1 964): 1.4 Tflop of Cholesky factorisations and 26 GB of
  factors. With a 1.2 m length scale, points 0.4 m apart still sample the smooth GP
  surface three times per length scale.
- **Plain down-sampling, no observation GP.** GPisMap3 first regresses each depth image
  with an "observation GP" (inverse depth over the image), drops points where its variance
  exceeds GPISMAP3_OBS_VAR_THRE and takes the normal from finite differences of it. Our
  points come without image structure, so the octree takes the first hit (input order)
  of each leaf cube of side ``min_half_length`` (the octree's first-come rule; its extra
  test that refuses a point within ``min_half_length`` of a point in a neighbouring leaf
  is dropped), and the normal is the smallest principal axis of the ``normal_neighbours``
  (16) nearest raw hits within ``min_half_length`` (fewer than 5: no normal), turned
  towards the point's sensor origin. The observation GP's gradient noise is ~0 on smooth
  surfaces, where the code clips it to ``min_grad_noise``; that value is used for every
  point with a normal. Isolated hits (the clutter in front of walls) take leaves of
  their own and, without a normal, enter as value-only observations with noise 2.0 (on
  the street ~8 k of the 50 k surface points have fewer than 5 hits within 0.4 m).
- **Batch, not online.** All hits are inserted at once; GPisMap's re-evaluation of stored
  points by later scans (``reEvalPoints``: moving points along the normal and fusing
  their noise) has no batch counterpart and is left out. No range gate (GPisMap3's
  0.4-4 m belongs to its depth camera).
- Every non-empty cluster is trained once after all points are in, which equals the
  state of the online map after its last update. The local GPs are small, so BLAS runs
  single-threaded inside ``fit`` and ``predict`` (threadpoolctl, which scikit-learn
  installs): a multi-threaded BLAS made the 3 429 Cholesky factors ~60x slower on the
  busy 2-core machine (74 s against 1.2 s).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.linalg import cho_factor, solve_triangular
from scipy.spatial import cKDTree

from ...errors import InputError
from ...pipeline.step8_occupancy import READINGS, occupancy_probability, surface_probability
from ...threads import one_blas_thread
from .base import OccupancyMethod, check_positive, check_queries, check_scans

#: ``OnGPIS::testSinglePoint`` (3D): prior variance of f plus this constant ("Noise param!").
_TEST_NOISE = 1e-3
#: ``OnGPIS::train``: points whose gradient noise exceeds this carry no gradient observation ...
_GRAD_NOISE_LIMIT = 0.1001
#: ... and get this value noise instead.
_NO_GRADIENT_NOISE = 2.0
#: ``GPisMap3::evalPoints``: clipping of the range term and of the incidence cosine.
_RANGE_CLIP = (1.0, 100.0)
_MIN_VIEW_COS = 0.1
#: ``GPisMap3::test_kernel``: query box half side in clusters, and at most 3 GPs asked.
_SEARCH_CLUSTERS = 3.0
_MAX_GPS = 3
#: Fewest raw hits for a PCA normal (our choice).
_MIN_NORMAL_NEIGHBOURS = 5
#: Bound on (training rows x queries) handled at once in prediction (memory).
_CHUNK_ELEMENTS = 4_000_000


def joint_covariance(xa: np.ndarray, grad_a: np.ndarray, xb: np.ndarray, grad_b: np.ndarray,
                     length_scale: float) -> np.ndarray:
    """Matérn 3/2 covariance between value and gradient observations of f (``covFnc.cpp``).

    Rows (columns) are the values of f at all ``xa`` (``xb``), followed by the gradients at
    the points flagged in ``grad_a`` (``grad_b``), point-major: row ``n_a + 3 g + i`` is
    ``df/dx_i`` at the g-th flagged point.

    Args:
        xa: (Na, 3) float64 points, metres.
        grad_a: (Na,) bool, True where a gradient observation is attached.
        xb: (Nb, 3) float64 points, metres.
        grad_b: (Nb,) bool.
        length_scale: Matérn length scale, metres (``a = sqrt(3) / length_scale``).

    Returns:
        (Na + 3 Ga, Nb + 3 Gb) float64 covariance, Ga and Gb the numbers of flagged points.
    """
    a = np.sqrt(3.0) / length_scale
    d = xa[:, None, :] - xb[None, :, :]                      # (Na, Nb, 3), d = x - x'
    r = np.sqrt(np.einsum('abk,abk->ab', d, d))
    e = np.exp(-a * r)
    ia, ib = np.flatnonzero(grad_a), np.flatnonzero(grad_b)
    na, nb, ga, gb = len(xa), len(xb), len(ia), len(ib)
    out = np.empty((na + 3 * ga, nb + 3 * gb))
    out[:na, :nb] = (1.0 + a * r) * e                         # k(r)
    a2 = a * a
    if gb:   # cov(f(x), df(x')/dx'_i) = a^2 d_i exp(-a r)
        out[:na, nb:] = (a2 * d[:, ib, :] * e[:, ib, None]).reshape(na, 3 * gb)
    if ga:   # cov(df(x)/dx_i, f(x')) = -a^2 d_i exp(-a r)
        out[na:, :nb] = (-a2 * d[ia] * e[ia][..., None]).transpose(0, 2, 1).reshape(3 * ga, nb)
    if ga and gb:   # cov(df/dx_i, df/dx'_j) = a^2 (delta_ij - a d_i d_j / r) exp(-a r); 0/0 -> 0
        dd = d[ia][:, ib]
        rr = r[ia][:, ib]
        inv_r = np.divide(1.0, rr, out=np.zeros_like(rr), where=rr > 0)
        kgg = np.eye(3) - a * dd[..., :, None] * dd[..., None, :] * inv_r[..., None, None]
        kgg *= a2 * e[ia][:, ib][..., None, None]
        out[na:, nb:] = kgg.transpose(0, 2, 1, 3).reshape(3 * ga, 3 * gb)
    return out


@dataclass(eq=False)
class LocalGPIS:
    """One cluster's GP (``OnGPIS``): value and gradient observations of f.

    Attributes:
        x: (n, 3) float64 training points, metres.
        has_grad: (n,) bool, True where the normal is an observation.
        length_scale: Matérn length scale, metres.
        chol: (m, m) lower Cholesky factor of the training covariance, m = n + 3 G.
        alpha: (m,) ``K^-1 y``.
    """

    x: np.ndarray
    has_grad: np.ndarray
    length_scale: float
    chol: np.ndarray
    alpha: np.ndarray

    @classmethod
    def train(cls, x: np.ndarray, value: np.ndarray, normal: np.ndarray, has_grad: np.ndarray,
              value_noise: np.ndarray, grad_noise: np.ndarray, length_scale: float) -> LocalGPIS:
        """Train on (n, 3) points with (n,) values, (n, 3) normals (used where ``has_grad``)
        and (n,) noise variances of the values and of each gradient component.

        Raises:
            InputError: the covariance is not positive definite even with jitter.
        """
        k = joint_covariance(x, has_grad, x, has_grad, length_scale)
        noise = np.r_[value_noise, np.repeat(grad_noise[has_grad], 3)]
        k[np.diag_indices_from(k)] += noise
        y = np.r_[value, normal[has_grad].reshape(-1)]
        jitter = 0.0
        for _ in range(4):
            try:
                chol, _lower = cho_factor(k + jitter * np.eye(len(k)), lower=True, check_finite=False)
                break
            except np.linalg.LinAlgError:
                jitter = max(1e-8, 10.0 * jitter)
        else:  # pragma: no cover - noise on the diagonal keeps K well conditioned
            raise InputError('a local GP covariance is not positive definite')
        chol = np.tril(chol)
        # R&W Algorithm 2.1: alpha = L^T \ (L \ y).
        alpha = solve_triangular(chol.T, solve_triangular(chol, y, lower=True, check_finite=False),
                                 lower=False, check_finite=False)
        return cls(x, has_grad, length_scale, chol, alpha)

    def _cross(self, xq: np.ndarray) -> np.ndarray:
        return joint_covariance(self.x, self.has_grad, xq, np.zeros(len(xq), bool), self.length_scale)

    def predict(self, xq: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(mean, var)`` of the GP (without ``fbias``) at (q, 3) points, each (q,).

        R&W Eqs. (2.25)-(2.26): ``mean = k*^T alpha``, ``var = k(x*, x*) - v^T v`` with
        ``v = L \\ k*``; the prior variance is ``1 + 0.001`` (``OnGPIS::testSinglePoint``).
        """
        mean = np.empty(len(xq))
        var = np.empty(len(xq))
        step = max(1, _CHUNK_ELEMENTS // len(self.chol))
        for s in range(0, len(xq), step):
            ks = self._cross(xq[s:s + step])
            mean[s:s + step] = ks.T @ self.alpha
            v = solve_triangular(self.chol, ks, lower=True, check_finite=False)
            var[s:s + step] = 1.0 + _TEST_NOISE - np.einsum('ij,ij->j', v, v)
        return mean, var

    def posterior_covariance(self, xq: np.ndarray) -> np.ndarray:
        """(q, q) posterior covariance of f at (q, 3) points (no test noise added)."""
        ks = self._cross(xq)
        v = solve_triangular(self.chol, ks, lower=True, check_finite=False)
        prior = joint_covariance(xq, np.zeros(len(xq), bool), xq, np.zeros(len(xq), bool), self.length_scale)
        return prior - v.T @ v


def _first_per_cell(xyz: np.ndarray, side: float) -> np.ndarray:
    """(K,) sorted indices of the first point (in input order) of each cube of ``side``."""
    cells = np.floor(xyz / side).astype(np.int64)
    cells -= cells.min(axis=0)
    dims = cells.max(axis=0) + 1
    if float(np.prod(dims.astype(np.float64))) < 2.0 ** 62:
        keys = np.ravel_multi_index(cells.T, dims)
        _, first = np.unique(keys, return_index=True)
    else:  # pragma: no cover - only for scenes of enormous extent
        _, first = np.unique(cells, axis=0, return_index=True)
    return np.sort(first)


class GPISMapMethod(OccupancyMethod):
    """GPIS map (Lee et al. 2019, GPisMap3) as an occupancy method.

    Args:
        resolution: voxel side of the evaluation, metres (> 0); enters only the occupancy.
        length_scale: Matérn 3/2 length scale (``map_scale_param``), metres.
        cluster_half_length: half side of the octree nodes holding a GP, metres.
        min_half_length: side of the cubes keeping one surface point each, metres.
        rtimes: a cluster's GP is trained on the points within ``rtimes *
            cluster_half_length`` of its centre (>= 1).
        fbias: value observation ``-fbias`` at surface points; the field ``f`` adds it back.
        min_pos_noise: factor of a point's value noise (range and incidence terms).
        min_grad_noise: noise variance of each gradient component.
        map_noise: map noise parameter; variance added in the occupancy.
        var_threshold: variance above which neighbouring clusters' GPs are asked.
        normal_neighbours: raw hits for the PCA normal of a surface point (>= 5).
        reading: ``'surface'`` or ``'solid'`` (see the module docstring; default: the
            class's).

    Raises:
        InputError: a parameter out of its range.
    """

    name = 'GPIS'
    reading_default = 'surface'

    def __init__(self, resolution: float, length_scale: float = 1.2, cluster_half_length: float = 0.8,
                 min_half_length: float = 0.4, rtimes: float = 2.0, fbias: float = 0.2,
                 min_pos_noise: float = 1e-3, min_grad_noise: float = 1e-2, map_noise: float = 5e-3,
                 var_threshold: float = 0.5, normal_neighbours: int = 16, reading: str | None = None) -> None:
        super().__init__(resolution)
        self.reading = self.reading_default if reading is None else reading
        if self.reading not in READINGS:
            raise InputError(f'reading must be one of {", ".join(READINGS)}, got {reading!r}')
        self.length_scale = check_positive('length_scale', length_scale)
        self.cluster_half_length = check_positive('cluster_half_length', cluster_half_length)
        self.min_half_length = check_positive('min_half_length', min_half_length)
        self.rtimes = check_positive('rtimes', rtimes)
        if self.rtimes < 1.0:
            raise InputError(f'rtimes must be at least 1 (a GP must cover its cluster), got {rtimes!r}')
        if self.min_half_length > 2 * self.cluster_half_length:
            raise InputError(f'min_half_length ({min_half_length!r}) must not exceed the cluster side '
                             f'({2 * self.cluster_half_length!r})')
        self.fbias = float(fbias)
        if not np.isfinite(self.fbias):
            raise InputError(f'fbias must be finite, got {fbias!r}')
        self.min_pos_noise = check_positive('min_pos_noise', min_pos_noise)
        self.min_grad_noise = check_positive('min_grad_noise', min_grad_noise)
        self.map_noise = check_positive('map_noise', map_noise)
        self.var_threshold = check_positive('var_threshold', var_threshold)
        if int(normal_neighbours) != normal_neighbours or normal_neighbours < _MIN_NORMAL_NEIGHBOURS:
            raise InputError(f'normal_neighbours must be an integer >= {_MIN_NORMAL_NEIGHBOURS}, '
                             f'got {normal_neighbours!r}')
        self.normal_neighbours = int(normal_neighbours)
        self.surface_points_: np.ndarray | None = None
        self.normals_: np.ndarray | None = None
        self.has_normal_: np.ndarray | None = None
        self.cluster_centres_: np.ndarray | None = None
        self.gps_: list[LocalGPIS] = []
        self._cluster_tree = None
        self._cache = None

    # ----------------------------------------------------------------------------- fit
    def _normals(self, points: np.ndarray, surface: np.ndarray, surface_origins: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray]:
        """(S, 3) unit normals towards the sensor and (S,) bool validity of the surface points."""
        k = min(self.normal_neighbours, len(points))
        dist, idx = cKDTree(points).query(surface, k=k, distance_upper_bound=self.min_half_length, workers=-1)
        dist, idx = dist.reshape(len(surface), k), idx.reshape(len(surface), k)
        valid = np.isfinite(dist)
        count = valid.sum(axis=1)
        nb = points[np.where(valid, idx, 0)]                                 # (S, k, 3)
        w = valid[..., None].astype(np.float64)
        mean = (nb * w).sum(axis=1) / np.maximum(count, 1)[:, None]
        c = (nb - mean[:, None, :]) * w
        cov = np.einsum('ski,skj->sij', c, c)
        _, vecs = np.linalg.eigh(cov)
        normal = vecs[:, :, 0]                                               # smallest eigenvalue
        ok = count >= _MIN_NORMAL_NEIGHBOURS
        to_sensor = surface_origins - surface
        flip = np.einsum('ij,ij->i', normal, to_sensor) < 0
        normal[flip] *= -1.0
        normal[~ok] = 0.0
        return normal, ok

    def fit(self, points: np.ndarray, origins: np.ndarray) -> GPISMapMethod:
        """Build the octree of surface points and train every cluster's GP.

        Args:
            points: (N, 3) float64 ray end points (hits), map frame, metres.
            origins: (N, 3) float64 sensor origin of each ray, map frame, metres.

        Returns:
            self, with ``surface_points_`` (S, 3), ``normals_`` (S, 3) (outward, towards
            the sensor; 0 where ``has_normal_`` is False), ``cluster_centres_`` (C, 3) and
            ``gps_`` (C local GPs).

        Raises:
            InputError: bad shapes, an empty or non-finite input.
        """
        points, origins = check_scans(points, origins)
        with one_blas_thread():
            self._fit(points, origins)
        return self

    def _fit(self, points: np.ndarray, origins: np.ndarray) -> None:
        keep = _first_per_cell(points, self.min_half_length)
        surface, surface_org = points[keep], origins[keep]
        normal, has_normal = self._normals(points, surface, surface_org)

        # GPisMap3::evalPoints: value noise from range and incidence, gradient noise floor.
        ray = surface_org - surface
        rng = np.linalg.norm(ray, axis=1)
        cos = np.einsum('ij,ij->i', normal, ray) / np.maximum(rng, 1e-12)
        cos = np.maximum(cos, _MIN_VIEW_COS)
        value_noise = (self.min_pos_noise * np.clip(rng, *_RANGE_CLIP)
                       + self.min_pos_noise * (1.0 - cos ** 2) / cos ** 2)
        grad_noise = np.full(len(surface), self.min_grad_noise)
        # OnGPIS::train: no gradient observation for a missing normal or a noisy gradient.
        has_grad = has_normal & (grad_noise <= _GRAD_NOISE_LIMIT)
        value_noise[~has_grad] = _NO_GRADIENT_NOISE

        side = 2.0 * self.cluster_half_length
        cells = np.unique(np.floor(surface / side).astype(np.int64), axis=0)
        centres = (cells + 0.5) * side
        members = cKDTree(surface).query_ball_point(centres, self.rtimes * self.cluster_half_length,
                                                    workers=-1)
        value = np.full(len(surface), -self.fbias)
        gps, kept = [], []
        for c, m in enumerate(members):
            if not m:   # a ball smaller than its cube (rtimes < sqrt 3) may miss it: no GP
                continue
            m = np.sort(np.asarray(m, dtype=np.int64))
            gps.append(LocalGPIS.train(surface[m], value[m], normal[m], has_grad[m], value_noise[m],
                                       grad_noise[m], self.length_scale))
            kept.append(c)
        self.surface_points_, self.normals_, self.has_normal_ = surface, normal, has_normal
        self.cluster_centres_ = centres[kept]
        self.gps_ = gps
        self._cluster_tree = cKDTree(self.cluster_centres_.reshape(-1, 3))
        self._cache = None

    # ------------------------------------------------------------------------- predict
    def _evaluate(self, xyz: np.ndarray, query: np.ndarray, cluster: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray]:
        """Mean and variance of GP ``cluster[j]`` at ``xyz[query[j]]``, each (J,)."""
        mean = np.empty(len(query))
        var = np.empty(len(query))
        order = np.argsort(cluster, kind='stable')
        bounds = np.flatnonzero(np.diff(cluster[order])) + 1
        for part in np.split(order, bounds):
            if len(part):
                mean[part], var[part] = self.gps_[cluster[part[0]]].predict(xyz[query[part]])
        return mean, var

    def _answers(self, xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(f, var)`` at (M, 3) points: f NaN and var ``1 + map_noise`` with no cluster."""
        if self._cluster_tree is None:
            raise InputError('fit the method before predicting')
        xyz = check_queries(xyz)
        if self._cache is not None and self._cache[0] is xyz:
            return self._cache[1]
        with one_blas_thread():
            out = self._query(xyz)
        self._cache = (xyz, out)
        return out

    def _query(self, xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        m = len(xyz)
        f = np.full(m, np.nan)
        var = np.full(m, 1.0 + self.map_noise)      # GPisMap3::test_kernel default
        n_clusters = len(self.cluster_centres_)
        if m and n_clusters:
            # Candidates: clusters whose box meets the query box (half side 3 clusters),
            # i.e. centre within 4 cluster half sides per axis; nearest first by centre.
            reach = (_SEARCH_CLUSTERS + 1.0) * self.cluster_half_length
            k = min(8, n_clusters)
            dist, idx = self._cluster_tree.query(xyz, k=k, distance_upper_bound=reach * np.sqrt(3.0),
                                                 workers=-1)
            dist, idx = dist.reshape(m, k), idx.reshape(m, k)
            ok = np.isfinite(dist)
            safe = np.where(ok, idx, 0)
            cheb = np.abs(self.cluster_centres_[safe] - xyz[:, None, :]).max(axis=2)
            ok &= cheb <= reach + 1e-9
            rank = np.cumsum(ok, axis=1)
            ok &= rank <= _MAX_GPS
            n_cand = ok.sum(axis=1)
            # Compact the (up to 3) candidates to the left, nearest first.
            cand = np.full((m, _MAX_GPS), -1, dtype=np.int64)
            rows, cols = np.nonzero(ok)
            cand[rows, rank[rows, cols] - 1] = idx[rows, cols]

            fs = np.full((m, _MAX_GPS), np.nan)
            vs = np.full((m, _MAX_GPS), np.inf)
            first = np.flatnonzero(n_cand >= 1)
            fs[first, 0], vs[first, 0] = self._evaluate(xyz, first, cand[first, 0])
            # Ask the other candidates where the nearest GP is uncertain.
            more = first[(n_cand[first] >= 2) & (vs[first, 0] > self.var_threshold)]
            for j in range(1, _MAX_GPS):
                q = more[n_cand[more] > j]
                if len(q):
                    fs[q, j], vs[q, j] = self._evaluate(xyz, q, cand[q, j])
            mean, v = fs[:, 0].copy(), vs[:, 0].copy()
            if len(more):
                order = np.argsort(vs[more], axis=1, kind='stable')
                fa = np.take_along_axis(fs[more], order[:, :1], axis=1)[:, 0]
                va = np.take_along_axis(vs[more], order[:, :1], axis=1)[:, 0]
                fb = np.take_along_axis(fs[more], order[:, 1:2], axis=1)[:, 0]
                vb = np.take_along_axis(vs[more], order[:, 1:2], axis=1)[:, 0]
                w1, w2 = va - self.var_threshold, vb - self.var_threshold
                w12 = w1 + w2
                blend = (va >= self.var_threshold) & (w12 > 0)
                with np.errstate(invalid='ignore', divide='ignore'):
                    mean[more] = np.where(blend, (w2 * fa + w1 * fb) / w12, fa)
                    v[more] = np.where(blend, (w2 * va + w1 * vb) / w12, va)
            f[first] = mean[first] + self.fbias
            var[first] = v[first]
        return f, var

    def signed_distance(self, xyz: np.ndarray) -> np.ndarray:
        """(M,) field value f at (M, 3) points (metres near the surface, positive on the
        sensor side); NaN where no cluster is near.

        Raises:
            InputError: not fitted, or ``xyz`` not a finite (M, 3) array.
        """
        return self._answers(xyz)[0]

    def predict(self, xyz: np.ndarray) -> np.ndarray:
        """Occupancy probability of the voxels centred at ``xyz``.

        Args:
            xyz: (M, 3) float64 voxel centres, map frame, metres.

        Returns:
            (M,) float64 in the method's reading (module docstring): the probability that
            the voxel holds the surface (0 where no cluster's box meets the query box), or
            ``Phi((r/2 - f) / sqrt(var + map_noise))`` (0.5 there).

        Raises:
            InputError: not fitted, or ``xyz`` not a finite (M, 3) array.
        """
        f, var = self._answers(xyz)
        var = np.maximum(var, 0.0)
        if self.reading == 'surface':
            return surface_probability(f, var, self.map_noise, 0.5 * self.resolution, outside=0.0)
        return occupancy_probability(f, var, self.map_noise, self.resolution)

    def predict_variance(self, xyz: np.ndarray) -> np.ndarray:
        """(M,) GPIS variance of f at ``xyz`` (units of f^2, ~m^2 near the surface; prior
        ``1 + 0.001``); ``1 + map_noise`` where no cluster is near (GPisMap3's default).

        Raises:
            InputError: not fitted, or ``xyz`` not a finite (M, 3) array.
        """
        return self._answers(xyz)[1].copy()


class GPISMapSolidMethod(GPISMapMethod):
    """:class:`GPISMapMethod` in the ``solid`` reading (the solid behind the surface)."""

    name = 'GPIS (solid)'
    reading_default = 'solid'
