"""LARD Hilbert map as a baseline occupancy method (numpy/scipy/scikit-learn re-implementation).

Method: V. Guizilini and F. Ramos, "Towards real-time 3D continuous occupancy mapping
using Hilbert maps", IJRR 37(6), 2018 (the features on local automatic relevance
determination, LARD), on the Hilbert maps of F. Ramos and L. Ott, "Hilbert maps: scalable
continuous occupancy mapping with stochastic gradient descent", IJRR 35(14), 2016. A
Hilbert map is a logistic regression on a feature vector of the point::

    p(occupied | x) = 1 / (1 + exp(-(w^T phi(x) + b)))

learnt by stochastic gradient descent from the hits (label 1) and points sampled along the
rays (label 0). In LARD the features are Gaussian kernels on *clusters* of the training
data, each with its own length-scale matrix, the cluster's covariance (a local automatic
relevance determination), and the feature vector is sparse: only the ``k`` clusters
nearest to ``x`` are evaluated::

    phi_j(x) = exp(-(x - mu_j)^T (c Sigma_j)^-1 (x - mu_j))   for the k nearest mu_j, else 0

Where the parameters come from. The paper's text was not among the searchable sources;
its first author's own implementation is (the ``cvpp`` library of V. Guizilini, a copy at
github.com/peterzxli/cvpp: ``algorithms/hilbert_maps/lard/`` and
``algorithms/clustering/quick_means.h``, with the LARD examples that use them), and the
defaults are taken from it:

- kernel ``exp(-d^T S d)`` with ``S = (5 Sigma)^-1`` (``c`` = ``covariance_scale`` 5,
  ``hm_lard_regr_logistic.h``); a cluster whose ``S`` is not positive or has
  ``det(S) >= 1e10`` (a degenerate, e.g. perfectly flat, covariance) gets ``S = 1e6 I``
  instead, the library's regularisation (``degenerate_precision``);
- ``k`` = 5 nearest clusters (``HMfeatSqExp(5)``, the LARD examples; one uses 3);
- plain SGD, one pass, constant learning rate 0.5 (``HMregrLogistic`` default; examples
  use 0.5 or 0.9), weights and intercept starting at 0, no regulariser: the LARD
  regressor has none. Ramos and Ott's own code (``SparseHilbertMap``) uses an elastic net,
  ``alpha`` 1e-4, ``l1_ratio`` 0.8, with scikit-learn's decaying ``'optimal'`` rate; it is
  exposed (``alpha``, ``l1_ratio``) but off by default, because with the LARD library's
  constant rate 0.5 its L2 part alone shrinks every weight by ``(1 - 0.5 * 1e-4 * 0.2)``
  per sample, ``e^-90`` over one pass of the street's 9 M samples;
- free-space samples: per ray ``max(1, floor(0.5 * length))`` points uniformly at random
  along the ray, labelled 0, plus its end point labelled 1 (``HMlard::makeDataset``,
  ``step`` 0.5, i.e. one sample per 2 m, the same rule as Ramos and Ott's
  ``free_space_points``: ``max(1, int(distance / 2))``);
- clusters by the library's *quick-means*: a random point not yet covered seeds a cluster
  of all points within ``r_o`` of it (kept if it has more than ``min_points``), the points
  within ``r_i`` of the seed are covered; repeated until every point is covered; each
  cluster gives a mean and a covariance. The occupied radii are those of the author's 3D
  LiDAR examples, ``quick_means(pts, ..., 0.10, 0.05, ...)`` in FLANN's squared L2
  distances, i.e. ``r_o`` = sqrt(0.10) = 0.316 m and ``r_i`` = sqrt(0.05) = 0.224 m
  (``r_i^2 = r_o^2 / 2``, as in the library's ``cluster_data``), ``min_points`` 3
  (``cluster_data``).

What was simplified / chosen here:

- **Free-space clusters.** The occupied and the free training points are clustered
  separately (a cluster holds one label), as the method describes. The library's examples
  cluster only the hits and give no radius for free points. Chosen here, before any
  scoring and not tuned: ``free_outer_radius`` 1.0 m = half the spacing of one ray's free
  samples (one per 2 m), so that a free cluster is about one sample step of the rays
  crossing it (``r_i^2 = r_o^2 / 2`` again). On the street scene this makes 38 k free
  clusters (median 129 of the clustered samples each) beside 59 k occupied ones (median
  70 hits).
- **Clustering a subset.** Each label's points are clustered from a seeded random subset
  of at most ``max_cluster_points`` (1 M) of them: on the street the 7.9 M free samples
  (a random subset of uniform samples along the rays is again such samples, at a lower
  rate); the 1.1 M hits are clustered in full up to that bound. All samples are learnt.
- **One batch.** The method is incremental (each scan adds its clusters and is learnt
  once); here all rays are clustered and learnt in one pass, the samples in a seeded
  random order (scikit-learn's ``SGDClassifier``, ``shuffle=True``) instead of time order.
  With one constant-rate pass the order only moves the shared intercept.
- **Solver.** ``SGDClassifier(loss='log_loss', learning_rate='constant', eta0=0.5,
  max_iter=1, penalty=None)`` makes the library's update ``w += eta (y - p) phi(x)``,
  ``b += eta (y - p)`` per sample (``HMregrLogistic::train``: the stochastic gradient
  step of the logistic loss; the papers' equation numbers could not be checked, their
  texts not being available). The intercept is a constant feature (value 1) with its own
  weight, because scikit-learn damps intercept updates by 0.01 on sparse inputs, which
  the library does not.
- **Unknown space.** A Hilbert map gives about ``sigmoid(b)`` where its features vanish.
  The interface wants 0.5 where the method knows nothing, so a query that no cluster's
  kernel reaches gets 0.5: its ``k`` features, and the kernels of the nearest occupied and
  the nearest free cluster, are all below ``feature_cutoff`` (1e-3, the cutoff of Ramos
  and Ott's sparse feature, ``distance_cutoff``). The nearest cluster of each label is
  asked too because the ``k`` nearest means are often all small occupied clusters whose
  kernels do not reach a point 10 cm in front of a wall that the larger free clusters
  cover; there the original's value, ``sigmoid(w^T phi + b)``, is kept. Elsewhere the
  probability is the original's.
- **Scale.** On the street scene (1.1 M rays) every ray is used: 1.1 M hits and 7.9 M free
  samples; ``max_rays`` (default: all) subsamples rays, seeded, if a budget needs it.
  Features are computed in float32 (coordinates to ~1e-5 m at 100 m from the origin).
- The resolution of the evaluation does not enter the map (a continuous map); it is only
  validated.
"""

from __future__ import annotations

import itertools
import warnings

import numpy as np
from scipy import sparse
from scipy.spatial import cKDTree

from ...errors import InputError
from .base import OccupancyMethod, check_positive, check_queries, check_scans

#: Threads for the k-d tree queries.
_WORKERS = 2



def sample_free_space(points: np.ndarray, origins: np.ndarray, step: float,
                      rng: np.random.Generator) -> np.ndarray:
    """Free-space samples along the rays (``HMlard::makeDataset``).

    Args:
        points: (N, 3) float64 ray end points, metres.
        origins: (N, 3) float64 ray origins, metres.
        step: samples per metre of ray (0.5: one per 2 m); each ray gets
            ``max(1, floor(step * length))`` samples.
        rng: random generator.

    Returns:
        (F, 3) float64 samples, uniformly at random on the segments origin -> end point
        (the end point itself excluded), grouped by ray in input order.
    """
    delta = points - origins
    counts = np.maximum(np.floor(step * np.linalg.norm(delta, axis=1)), 1.0).astype(np.int64)
    ray = np.repeat(np.arange(len(points)), counts)
    return origins[ray] + rng.random(len(ray))[:, None] * delta[ray]


def quick_means(points: np.ndarray, outer_radius: float, inner_radius: float, min_points: int,
                rng: np.random.Generator, chunk: int = 20_000) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Quick-means clustering (the ``cvpp`` library's ``quick_means``).

    A point not yet covered, at random, seeds a cluster of the points within
    ``outer_radius`` of it; the points within ``inner_radius`` are covered; until every point
    is covered. Clusters with ``min_points`` points or fewer are dropped (the point cover
    still counts). Visiting the points in a random permutation and seeding at every point
    not yet covered picks the same random seeds as drawing among the uncovered points.

    Args:
        points: (N, 3) float64 points, metres.
        outer_radius: radius of a cluster around its seed, metres.
        inner_radius: radius of the points a seed covers, metres (<= outer_radius).
        min_points: a cluster needs more points than this.
        rng: random generator (the seed order).
        chunk: seeds whose neighbourhoods are gathered at once (bounds memory).

    Returns:
        ``(means, covs, counts)``: (C, 3) float64 cluster means, (C, 3, 3) float64 sample
        covariances (divided by n - 1), (C,) int64 points per cluster.
    """
    tree = cKDTree(points)
    covered = np.zeros(len(points), dtype=bool)
    seeds = []
    query = tree.query_ball_point
    for i in rng.permutation(len(points)).tolist():
        if covered[i]:
            continue
        seeds.append(i)
        covered[query(points[i], inner_radius)] = True
    seeds = np.asarray(seeds, dtype=np.int64)

    means, covs, counts = [], [], []
    for start in range(0, len(seeds), chunk):
        block = seeds[start:start + chunk]
        centre = points[block]
        members = tree.query_ball_point(centre, outer_radius, workers=_WORKERS, return_sorted=False)
        n = np.fromiter(map(len, members), dtype=np.int64, count=len(block))
        idx = np.fromiter(itertools.chain.from_iterable(members), dtype=np.int64, count=int(n.sum()))
        del members
        owner = np.repeat(np.arange(len(block)), n)
        # Coordinates relative to the seed: no cancellation in the second moments.
        local = tree.data[idx] - centre[owner]
        first = np.stack([np.bincount(owner, local[:, a], len(block)) for a in range(3)], axis=1)
        second = np.empty((len(block), 3, 3))
        for a in range(3):
            for b in range(a, 3):
                second[:, a, b] = second[:, b, a] = np.bincount(owner, local[:, a] * local[:, b], len(block))
        keep = n > min_points
        nk = n[keep].astype(np.float64)
        mean_local = first[keep] / nk[:, None]
        cov = (second[keep] - nk[:, None, None] * mean_local[:, :, None] * mean_local[:, None, :]) \
            / (nk[:, None, None] - 1.0)
        means.append(centre[keep] + mean_local)
        covs.append(cov)
        counts.append(n[keep])
    if not means:
        return np.empty((0, 3)), np.empty((0, 3, 3)), np.empty(0, np.int64)
    return np.concatenate(means), np.concatenate(covs), np.concatenate(counts)


def kernel_factors(covs: np.ndarray, scale: float, degenerate_precision: float,
                   max_precision_det: float = 1e10) -> tuple[np.ndarray, np.ndarray]:
    """Cholesky factors of the kernels' length-scale matrices ``scale * Sigma``.

    The kernel ``exp(-d^T S d)`` has ``S = (scale Sigma)^-1`` (``hm_lard_regr_logistic.h``);
    with ``scale Sigma = L L^T``, ``d^T S d = |L^-1 d|^2``. A covariance that is not
    positive definite or whose ``det(S) >= max_precision_det`` is replaced, as in the
    library, by ``S = degenerate_precision * I`` (``L = I / sqrt(degenerate_precision)``).

    Args:
        covs: (C, 3, 3) float64 cluster covariances, m^2.
        scale: factor on the covariances (5).
        degenerate_precision: precision of a degenerate cluster's kernel, m^-2 (1e6).
        max_precision_det: largest ``det(S)`` accepted, m^-6 (1e10).

    Returns:
        ``(factors, degenerate)``: (C, 3, 3) float64 lower-triangular ``L``, metres, and
        (C,) bool, True where the fallback was used.
    """
    scaled = scale * covs
    eig = np.linalg.eigvalsh(scaled) if len(scaled) else np.empty((0, 3))
    ok = np.all(np.isfinite(scaled), axis=(1, 2))
    ok[ok] = (eig[ok, 0] > 0) & (np.prod(eig[ok], axis=1) > 1.0 / max_precision_det)
    factors = np.broadcast_to(np.eye(3) / np.sqrt(degenerate_precision), scaled.shape).copy()
    if ok.any():
        factors[ok] = np.linalg.cholesky(scaled[ok])
    return factors, ~ok


def kernel_table(means: np.ndarray, factors: np.ndarray) -> np.ndarray:
    """(C, 9) float32 rows ``[mu_x, mu_y, mu_z, L00, L10, L11, L20, L21, L22]`` of each
    cluster: its mean (metres) and the lower triangle of its kernel's Cholesky factor
    (metres), gathered together for :func:`lard_features`."""
    rows, cols = np.tril_indices(3)
    return np.concatenate([means, factors[:, rows, cols]], axis=1).astype(np.float32)


def lard_features(xyz: np.ndarray, tree: cKDTree, table: np.ndarray, k: int,
                  chunk: int = 250_000) -> tuple[np.ndarray, np.ndarray]:
    """Sparse LARD features: the kernels of the ``k`` clusters nearest to each point.

    Args:
        xyz: (M, 3) float64 points, metres.
        tree: k-d tree of the (C, 3) cluster means, metres.
        table: (C, 9) float32 cluster means and Cholesky factors of ``scale * Sigma``
            (:func:`kernel_table`, :func:`kernel_factors`).
        k: clusters per point (<= C).
        chunk: points handled at once (bounds memory).

    Returns:
        ``(index, value)``: (M, k) int32 cluster indices and (M, k) float32 kernel values
        ``exp(-|L_j^-1 (x - mu_j)|^2)`` in [0, 1] (float32: the kernel's and the
        coordinates' precision, ~1e-7 relative, is far below the data's).
    """
    index = np.empty((len(xyz), k), dtype=np.int32)
    value = np.empty((len(xyz), k), dtype=np.float32)
    for start in range(0, len(xyz), chunk):
        x = xyz[start:start + chunk]
        _, idx = tree.query(x, k, workers=_WORKERS)
        idx = idx.reshape(len(x), k)
        rows = table[idx]
        d = x.astype(np.float32)[:, None, :] - rows[..., :3]
        # Forward substitution L y = d (3 x 3 lower triangular, all pairs at once).
        y0 = d[..., 0] / rows[..., 3]
        y1 = (d[..., 1] - rows[..., 4] * y0) / rows[..., 5]
        y2 = (d[..., 2] - rows[..., 6] * y0 - rows[..., 7] * y1) / rows[..., 8]
        index[start:start + chunk] = idx
        value[start:start + chunk] = np.exp(-(y0 * y0 + y1 * y1 + y2 * y2))
    return index, value


class LARDHilbertMapMethod(OccupancyMethod):
    """Hilbert map on local-ARD cluster features (Guizilini and Ramos 2018).

    Args:
        resolution: voxel side of the evaluation, metres (> 0; the map is continuous).
        occupied_outer_radius: quick-means cluster radius for the hits, metres.
        free_outer_radius: quick-means cluster radius for the free samples, metres.
        inner_ratio: ``r_i / r_o`` of quick-means (sqrt(0.5)).
        min_points: a cluster needs more points than this.
        n_neighbours: clusters evaluated per point (``k``).
        covariance_scale: factor ``c`` on the cluster covariances in the kernel.
        degenerate_precision: kernel precision of degenerate clusters, m^-2.
        learning_rate: constant SGD learning rate.
        free_step: free samples per metre of ray.
        alpha: elastic-net strength (0: none, the LARD library; Ramos and Ott use 1e-4).
        l1_ratio: elastic-net mixing, used when ``alpha`` > 0 (Ramos and Ott: 0.8).
        feature_cutoff: a query that no cluster's kernel reaches with this value is unknown
            (0.5); see the module docstring.
        max_cluster_points: each label's points are clustered from a seeded random subset
            of at most this many of them, or None for all (all are used for learning).
        max_rays: use at most this many rays (a seeded subset), or None for all.
        seed: seed of the free samples, the cluster seeds, the SGD order and ``max_rays``.

    Raises:
        InputError: a parameter out of its range.
    """

    name = 'LARD-HM'

    def __init__(self, resolution: float, occupied_outer_radius: float = float(np.sqrt(0.10)),
                 free_outer_radius: float = 1.0, inner_ratio: float = float(np.sqrt(0.5)), min_points: int = 3,
                 n_neighbours: int = 5, covariance_scale: float = 5.0, degenerate_precision: float = 1e6,
                 learning_rate: float = 0.5, free_step: float = 0.5, alpha: float = 0.0, l1_ratio: float = 0.8,
                 feature_cutoff: float = 1e-3, max_cluster_points: int | None = 1_000_000, max_rays: int | None = None,
                 seed: int = 0) -> None:
        super().__init__(resolution)
        self.occupied_outer_radius = check_positive('occupied_outer_radius', occupied_outer_radius)
        self.free_outer_radius = check_positive('free_outer_radius', free_outer_radius)
        self.inner_ratio = check_positive('inner_ratio', inner_ratio)
        if self.inner_ratio > 1.0:
            raise InputError(f'inner_ratio must be in (0, 1], got {inner_ratio!r}')
        if int(min_points) != min_points or min_points < 1:
            raise InputError(f'min_points must be an integer >= 1 (a covariance needs 2 points), got {min_points!r}')
        self.min_points = int(min_points)
        if int(n_neighbours) != n_neighbours or n_neighbours < 1:
            raise InputError(f'n_neighbours must be an integer >= 1, got {n_neighbours!r}')
        self.n_neighbours = int(n_neighbours)
        self.covariance_scale = check_positive('covariance_scale', covariance_scale)
        self.degenerate_precision = check_positive('degenerate_precision', degenerate_precision)
        self.learning_rate = check_positive('learning_rate', learning_rate)
        self.free_step = check_positive('free_step', free_step)
        if not (np.isfinite(alpha) and alpha >= 0):
            raise InputError(f'alpha must be >= 0, got {alpha!r}')
        self.alpha = float(alpha)
        if not (np.isfinite(l1_ratio) and 0.0 <= l1_ratio <= 1.0):
            raise InputError(f'l1_ratio must be in [0, 1], got {l1_ratio!r}')
        self.l1_ratio = float(l1_ratio)
        if not (np.isfinite(feature_cutoff) and 0.0 <= feature_cutoff < 1.0):
            raise InputError(f'feature_cutoff must be in [0, 1), got {feature_cutoff!r}')
        self.feature_cutoff = float(feature_cutoff)
        if max_cluster_points is not None and (int(max_cluster_points) != max_cluster_points
                                               or max_cluster_points < 1):
            raise InputError(f'max_cluster_points must be None or an integer >= 1, got {max_cluster_points!r}')
        self.max_cluster_points = None if max_cluster_points is None else int(max_cluster_points)
        if max_rays is not None and (int(max_rays) != max_rays or max_rays < 1):
            raise InputError(f'max_rays must be None or an integer >= 1, got {max_rays!r}')
        self.max_rays = None if max_rays is None else int(max_rays)
        self.seed = int(seed)
        self.means_: np.ndarray | None = None
        self.factors_: np.ndarray | None = None
        self.labels_: np.ndarray | None = None
        self.degenerate_: np.ndarray | None = None
        self.weights_: np.ndarray | None = None
        self.intercept_ = 0.0
        self.tree_: cKDTree | None = None
        self.table_: np.ndarray | None = None
        self.reach_ = float('inf')
        self.label_trees_: list[tuple[cKDTree, np.ndarray]] = []
        self.n_samples_ = (0, 0)

    def fit(self, points: np.ndarray, origins: np.ndarray) -> LARDHilbertMapMethod:
        """Cluster the training data and learn the weights.

        Args:
            points: (N, 3) float64 ray end points (hits), map frame, metres.
            origins: (N, 3) float64 sensor origin of each ray, map frame, metres.

        Returns:
            self, with ``means_`` (C, 3) cluster means (metres), ``factors_`` (C, 3, 3)
            Cholesky factors of their kernels (metres), ``labels_`` (C,) 1 for occupied and 0
            for free clusters, ``degenerate_`` (C,) bool, ``weights_`` (C,) and
            ``intercept_`` of the logistic regression, ``n_samples_`` (hits, free samples),
            ``reach_`` the farthest any kernel reaches ``feature_cutoff`` (metres).

        Raises:
            InputError: bad shapes, an empty or non-finite input, or too few points for
                ``n_neighbours`` clusters.
        """
        from sklearn.exceptions import ConvergenceWarning
        from sklearn.linear_model import SGDClassifier

        points, origins = check_scans(points, origins)
        rng = np.random.default_rng(self.seed)
        if self.max_rays is not None and len(points) > self.max_rays:
            pick = np.sort(rng.choice(len(points), self.max_rays, replace=False))
            points, origins = points[pick], origins[pick]
        free = sample_free_space(points, origins, self.free_step, rng)

        clusters = []
        for data, radius, label in ((points, self.occupied_outer_radius, 1), (free, self.free_outer_radius, 0)):
            if self.max_cluster_points is not None and len(data) > self.max_cluster_points:
                data = data[rng.choice(len(data), self.max_cluster_points, replace=False)]
            means, covs, _ = quick_means(data, radius, self.inner_ratio * radius, self.min_points, rng)
            clusters.append((means, covs, np.full(len(means), label, dtype=np.int8)))
        means = np.concatenate([c[0] for c in clusters])
        covs = np.concatenate([c[1] for c in clusters])
        labels = np.concatenate([c[2] for c in clusters])
        if len(means) < self.n_neighbours:
            raise InputError(f'the points form {len(means)} clusters, fewer than n_neighbours={self.n_neighbours}; '
                             'give more points or smaller cluster radii')
        factors, degenerate = kernel_factors(covs, self.covariance_scale, self.degenerate_precision)
        tree = cKDTree(means)
        table = kernel_table(means, factors)

        # Training set: hits (1) and free samples (0); features of the k nearest clusters
        # plus a constant 1 for the intercept (column C).
        x = np.concatenate([points, free])
        y = np.r_[np.ones(len(points), np.int8), np.zeros(len(free), np.int8)]
        del free
        index, value = lard_features(x, tree, table, self.n_neighbours)
        del x
        n, k, c = len(y), self.n_neighbours, len(means)
        data = np.empty((n, k + 1))
        data[:, :k] = value
        data[:, k] = 1.0
        cols = np.empty((n, k + 1), dtype=np.int32)
        cols[:, :k] = index
        cols[:, k] = c
        del index, value
        design = sparse.csr_matrix((data.reshape(-1), cols.reshape(-1), np.arange(0, n * (k + 1) + 1, k + 1)),
                                   shape=(n, c + 1))
        del data, cols
        # One pass of per-sample SGD on the logistic loss (HMregrLogistic::train); with alpha > 0
        # the elastic net also reaches the intercept column (Ramos and Ott's code leaves b out).
        penalty = 'elasticnet' if self.alpha > 0 else None
        sgd = SGDClassifier(loss='log_loss', penalty=penalty, alpha=self.alpha, l1_ratio=self.l1_ratio,
                            fit_intercept=False, learning_rate='constant', eta0=self.learning_rate, max_iter=1,
                            tol=None, shuffle=True, random_state=self.seed)
        with warnings.catch_warnings():
            warnings.simplefilter('ignore', ConvergenceWarning)
            sgd.fit(design, y)
        coef = sgd.coef_.reshape(-1)

        self.means_, self.factors_, self.labels_, self.degenerate_ = means, factors, labels, degenerate
        self.weights_, self.intercept_ = coef[:c].copy(), float(coef[c])
        self.tree_, self.table_ = tree, table
        # Farthest a kernel reaches: exp(-d^T S d) >= cutoff needs |d|^2 <= ln(1/cutoff) * lambda_max(c Sigma).
        widest = float(np.linalg.eigvalsh(factors @ np.swapaxes(factors, 1, 2))[:, -1].max())
        self.reach_ = float(np.sqrt(-np.log(self.feature_cutoff) * widest)) * (1 + 1e-6) + 1e-9 \
            if self.feature_cutoff > 0 else float('inf')
        self.label_trees_ = [(cKDTree(means[labels == label]), table[labels == label]) for label in (1, 0)]
        self.n_samples_ = (int(y.sum()), int(len(y) - y.sum()))
        return self

    def decision_function(self, xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Latent ``w^T phi(x) + b`` and whether a cluster's kernel reaches ``feature_cutoff``
        (a feature, or the nearest occupied or free cluster; see the module docstring).

        Args:
            xyz: (M, 3) float64 points, map frame, metres.

        Returns:
            ``(z, known)``: (M,) float64 and (M,) bool. Points farther than ``reach_`` from
            every cluster mean, where every kernel is below ``feature_cutoff``, are not
            evaluated (a k-d tree search far from the data is slow): ``z = b`` there, and
            they are unknown.

        Raises:
            InputError: not fitted, or ``xyz`` not a finite (M, 3) array.
        """
        if self.tree_ is None:
            raise InputError('fit the method before predicting')
        xyz = check_queries(xyz)
        z = np.full(len(xyz), self.intercept_)
        known = np.zeros(len(xyz), dtype=bool)
        if not len(xyz):
            return z, known
        if np.isfinite(self.reach_):
            nearest, _ = self.tree_.query(xyz, 1, distance_upper_bound=self.reach_, workers=_WORKERS)
            near = np.flatnonzero(np.isfinite(nearest))
        else:
            near = np.arange(len(xyz))
        x = xyz[near]
        index, value = lard_features(x, self.tree_, self.table_, self.n_neighbours)
        z[near] += (value * self.weights_[index]).sum(axis=1, dtype=np.float64)
        reached = value.max(axis=1, initial=0.0) >= self.feature_cutoff
        for tree, table in self.label_trees_:
            if len(table) and not reached.all():
                ask = np.flatnonzero(~reached)
                reached[ask] = lard_features(x[ask], tree, table, 1)[1][:, 0] >= self.feature_cutoff
        known[near] = reached
        return z, known

    def predict(self, xyz: np.ndarray) -> np.ndarray:
        """Occupancy probability at the voxel centres ``xyz``.

        Args:
            xyz: (M, 3) float64 voxel centres, map frame, metres.

        Returns:
            (M,) float64 ``1 / (1 + exp(-z))`` in [0, 1]; 0.5 where no cluster's kernel
            reaches ``feature_cutoff`` (unknown).

        Raises:
            InputError: not fitted, or ``xyz`` not a finite (M, 3) array.
        """
        z, known = self.decision_function(xyz)
        p = 0.5 * (1.0 + np.tanh(0.5 * z))  # the logistic function, without overflow
        return np.where(known, p, 0.5)
