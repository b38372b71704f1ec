"""Local Gaussian processes in blocks (paper, Sections III.B to III.D).

Kernel (paper eq. 4, ARD squared exponential)::

    k0(x, x') = sigma_p^2 exp(-1/2 sum_m b_m (x_m - x'_m)^2),   x in R^2 (u, v)

with sigma_p = sigma_k of the facet's layer, noise sigma_eta (eq. 5), prior mean mu_k of
the layer. Posterior (eqs. 6 and 7, Rasmussen & Williams Algorithm 2.1)::

    L = cholesky(K + sigma_eta^2 I);  alpha = L^T \\ (L \\ (y - mu_k))
    mean = mu_k + k_*^T alpha;        var = k0(x_*, x_*) - |L \\ k_*|^2

(``var`` is the variance of the surface; the noise variance sigma_eta^2 is reported
apart, the paper's eq. 7 adds it.)

Blocks (Section III.D): the block size per axis is the distance at which the kernel with
sigma_p = 1 falls to c_min, ``s_m = sqrt(-2 ln(c_min) / b_m)``; each block is predicted
from the training points of its extended block (itself and its 8 neighbours) of the same
facet. All blocks of a façade are solved in one call of a compiled kernel
(:mod:`~uncertain_facade_map.pipeline._gp_kernels`, block by block without padding, in two
threads); :func:`solve_blocks`, :func:`predict_blocks` and :func:`loo_statistic` are the
same arithmetic batched in numpy, kept as the reference the kernel is tested against.

Hyper-parameters: b_1, b_2 by maximum marginal likelihood in log space within bounds
(L-BFGS-B with the analytic gradient, R&W eq. 5.9), started at 1/b = 0.0025 m^2, on a
small subset of the training points: a few square patches, so that the subset holds
neighbours at the scale being learnt.
"""

from __future__ import annotations

import functools
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
from scipy.linalg import cho_factor, cho_solve
from scipy.optimize import minimize
from scipy.spatial import cKDTree

from ..params import GPParams
from ..threads import kdtree_workers, threads

LOG_2PI = float(np.log(2.0 * np.pi))


def kernel(xa: np.ndarray, xb: np.ndarray, sigma_p: np.ndarray | float, lengthscale2: np.ndarray) -> np.ndarray:
    """ARD squared-exponential kernel, paper eq. 4.

    Args:
        xa: (..., n, 2) inputs (u, v), metres.
        xb: (..., m, 2) inputs, metres.
        sigma_p: prior standard deviation, metres; scalar or (...,) per batch.
        lengthscale2: (2,) or (..., 2) squared length scales 1/b_m, m^2.

    Returns:
        (..., n, m) covariances, m^2.
    """
    scale = np.sqrt(1.0 / np.asarray(lengthscale2, dtype=np.float64))  # sqrt(b_m)
    scale = scale[..., None, :] if scale.ndim > 1 else scale
    a = xa * scale
    b = xb * scale
    # |a - b|^2 = |a|^2 + |b|^2 - 2 a.b, by matrix products instead of an (n, m, 2) difference array.
    sq = (a * a).sum(-1)[..., :, None] + (b * b).sum(-1)[..., None, :] - 2.0 * (a @ np.swapaxes(b, -1, -2))
    s2 = np.asarray(sigma_p, dtype=np.float64) ** 2
    s2 = s2[..., None, None] if np.ndim(s2) else s2
    return s2 * np.exp(-0.5 * np.maximum(sq, 0.0))


def _tri_solve(lower: np.ndarray, rhs: np.ndarray, transpose: bool = False) -> np.ndarray:
    """Solve L X = B (or L^T X = B) for stacks of lower-triangular L (B, n, n), rhs (B, n, k).

    Forward (backward) substitution vectorised over the stack: n steps of (B, k) work.
    numpy has no batched triangular solver, scipy's loops over the stack in Python, and a
    general batched solve redoes an LU factorisation of every L.
    """
    n = lower.shape[-1]
    x = np.empty(np.broadcast_shapes(lower.shape[:-2], rhs.shape[:-2]) + rhs.shape[-2:],
                 dtype=np.result_type(lower, rhs))
    steps = range(n - 1, -1, -1) if transpose else range(n)
    for i in steps:
        if transpose:
            coef = lower[..., i + 1:, i]  # column i below the diagonal = row i of L^T right of it
            acc = np.einsum('bj,bjk->bk', coef, x[..., i + 1:, :]) if i + 1 < n else 0.0
        else:
            coef = lower[..., i, :i]
            acc = np.einsum('bj,bjk->bk', coef, x[..., :i, :]) if i else 0.0
        x[..., i, :] = (rhs[..., i, :] - acc) / lower[..., i, i][..., None]
    return x


#: Neighbours this close to tied (relative distance) count as tied: round-off, not geometry.
TIE_TOLERANCE = 1e-9
#: Neighbours looked at to break ties of the nearest one.
_TIE_CANDIDATES = 4


def _nearest(uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each point's nearest other point: (N,) distance and (N,) index.

    Quantised coordinates (Argoverse 2 stores float16 in the vehicle frame: a 7.8 mm grid)
    give many equidistant neighbours, and a rigid transform keeps the tie only up to
    round-off (1e-13 m): which one a k-d tree returns would then depend on how the points
    were moved into the map frame. Among the neighbours within :data:`TIE_TOLERANCE`
    (relative) of the nearest, the one with the lowest index is taken, so the pairing is
    the same for points moved by any rounding of the same transform.
    """
    k = min(_TIE_CANDIDATES, len(uv))
    dist, idx = cKDTree(uv).query(uv, k=k, workers=kdtree_workers())
    dist, idx = dist[:, 1:], idx[:, 1:]
    tied = dist <= dist[:, :1] * (1.0 + TIE_TOLERANCE) + 1e-12
    pick = np.argmin(np.where(tied, idx, np.iinfo(np.int64).max), axis=1)
    rows = np.arange(len(uv))
    return dist[rows, pick], idx[rows, pick]


def estimate_noise(uv: np.ndarray, depth: np.ndarray, max_lag: float, fallback: float, min_lag: float = 0.0) -> float:
    """sigma_eta from the data: the nugget of the depths' variogram at the shortest lags.

    Two points closer than ``max_lag`` on the plane see nearly the same surface, so half
    the variance of their depth difference is the noise variance (plus the surface's
    change over the lag, small at a few centimetres). Each point is paired with its
    nearest neighbour (on sparse data the 30 closest pairs are used even beyond
    ``max_lag``, up to four times it); the spread of the differences is taken robustly
    (1.4826 x median absolute deviation), so that pairs across a depth step do not count.

    Args:
        uv: (N, 2) locations, metres, façade frame.
        depth: (N,) depths, metres.
        max_lag: pairs further apart than this are not used, metres.
        fallback: returned when fewer than 30 pairs are close enough, metres.
        min_lag: pairs closer than this are not used, metres: the map stores no point within
            ``update.store_spacing`` of a stored one (3-D distance), so two points closer
            than that on the plane were both kept only because their depths differ; their
            differences would inflate sigma_eta (by 14-73 % on a simulated wall).

    Returns:
        sigma_eta, metres.
    """
    if len(uv) < 31:
        return fallback
    lag_of, j = _nearest(uv)
    i = np.arange(len(uv))
    pairs, first = np.unique(np.stack([np.minimum(i, j), np.maximum(i, j)], axis=1), axis=0, return_index=True)
    lag = lag_of[first]
    # Pairs closer than min_lag were kept by the storage rule only where their depths differ.
    apart = lag >= min_lag
    pairs, lag = pairs[apart], lag[apart]
    if len(lag) < 30:
        return fallback
    # The pairs within max_lag; on sparse data, the 30 closest pairs up to 4 max_lag.
    close = lag <= max(max_lag, min(np.sort(lag)[29], 4 * max_lag))
    if close.sum() < 30:
        return fallback
    pairs = pairs[close]
    diff = depth[pairs[:, 0]] - depth[pairs[:, 1]]
    return float(1.4826 * np.median(np.abs(diff - np.median(diff))) / np.sqrt(2.0))


def block_size(lengthscale2: np.ndarray, c_min: float) -> np.ndarray:
    """Block side per axis where exp(-1/2 b r^2) = c_min (paper eq. 9), metres.

    Args:
        lengthscale2: (..., 2) squared length scales 1/b_m, m^2.
        c_min: covariance threshold in (0, 1).
    """
    return np.sqrt(-2.0 * np.log(c_min) * np.asarray(lengthscale2, dtype=np.float64))


# ----------------------------------------------------------------------------------------
# Marginal likelihood and its optimisation
# ----------------------------------------------------------------------------------------
def neg_log_marginal_likelihood(log_b: np.ndarray, patches: list[tuple[np.ndarray, np.ndarray, float]],
                                noise2: float) -> tuple[float, np.ndarray]:
    """Negative log marginal likelihood of independent patches and its gradient in log b.

    R&W eq. 2.30 for the value and eq. 5.9 for the gradient:
    d/d theta = 1/2 tr((K^-1 - alpha alpha^T) dK/d theta), with
    dK/d log b_m = -1/2 b_m (x_m - x'_m)^2 * k0.

    Args:
        log_b: (2,) log of b_1, b_2 (1/m^2).
        patches: per patch (X (n, 2) metres, y (n,) metres centred by the prior mean,
            sigma_p metres).
        noise2: sigma_eta^2, m^2.

    Returns:
        (value, (2,) gradient).
    """
    b = np.exp(log_b)
    value = 0.0
    grad = np.zeros(2)
    for x, y, sigma_p in patches:
        diff2 = (x[:, None, :] - x[None, :, :]) ** 2  # (n, n, 2)
        kf = sigma_p**2 * np.exp(-0.5 * diff2 @ b)
        factor = cho_factor(kf + noise2 * np.eye(len(x)), lower=True, check_finite=False)
        alpha = cho_solve(factor, y, check_finite=False)
        value += 0.5 * y @ alpha + np.log(np.diag(factor[0])).sum() + 0.5 * len(x) * LOG_2PI
        w = cho_solve(factor, np.eye(len(x)), check_finite=False) - np.outer(alpha, alpha)
        for m in range(2):
            grad[m] += 0.5 * np.sum(w * (-0.5 * b[m] * diff2[:, :, m] * kf))
    return value, grad


def optimise_lengthscales(patches: list[tuple[np.ndarray, np.ndarray, float]], params: GPParams) -> np.ndarray:
    """Maximum-marginal-likelihood 1/b_1, 1/b_2 (m^2) for a set of patches.

    Starts at ``initial_lengthscale2`` and keeps the result within the bounds (log space).
    Returns the initial value if there are no patches or the optimiser fails.
    """
    initial = np.full(2, params.initial_lengthscale2)
    if not params.optimise or not patches:
        return initial
    noise2 = params.noise_sigma**2
    bounds = [(-np.log(params.lengthscale2_max), -np.log(params.lengthscale2_min))] * 2
    result = minimize(neg_log_marginal_likelihood, -np.log(initial), args=(patches, noise2), jac=True,
                      method='L-BFGS-B', bounds=bounds, options={'maxiter': 20})
    if not np.all(np.isfinite(result.x)):
        return initial
    return np.exp(-result.x)


def optimisation_patches(uv: np.ndarray, y: np.ndarray, sigma_p: np.ndarray, params: GPParams,
                         rng: np.random.Generator) -> list[tuple[np.ndarray, np.ndarray, float]]:
    """Draw the small optimisation subset: square patches around random training points.

    Args:
        uv: (N, 2) training inputs of one layer, metres.
        y: (N,) targets centred by their facet's prior mean, metres.
        sigma_p: (N,) prior standard deviation of each point's facet, metres.
        params: subset size and patch side.
        rng: random source.

    Returns:
        Patches (X, y, sigma_p) with at most ``opt_points`` points in all.
    """
    patches = []
    budget = params.opt_points
    remaining = np.ones(len(uv), dtype=bool)
    half = params.opt_patch / 2
    per_patch = max(20, params.opt_points // 4)
    while budget >= 10 and remaining.any():
        centre = uv[rng.choice(np.flatnonzero(remaining))]
        near = remaining & np.all(np.abs(uv - centre) <= half, axis=1)
        idx = np.flatnonzero(near)
        remaining &= ~near
        if len(idx) < 10:
            continue
        idx = rng.choice(idx, min(len(idx), per_patch, budget), replace=False)
        patches.append((uv[idx], y[idx], float(np.median(sigma_p[idx]))))
        budget -= len(idx)
    return patches


# ----------------------------------------------------------------------------------------
# Batched block solves
# ----------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class BlockSystem:
    """Factorised GPs of B blocks, padded to n training points each.

    Attributes:
        x: (B, n, 2) training inputs, metres (padding rows are zero).
        mask: (B, n) True for real training points.
        point: (B, n) index of each training point in the caller's arrays, -1 for padding.
        lower: (B, n, n) Cholesky factors of K + sigma_eta^2 I (identity on padding).
        alpha: (B, n) (K + sigma_eta^2 I)^-1 (y - mu), zero on padding.
        sigma_p: (B,) prior standard deviation, metres.
        lengthscale2: (B, 2) 1/b, m^2.
    """

    x: np.ndarray
    mask: np.ndarray
    point: np.ndarray
    lower: np.ndarray
    alpha: np.ndarray
    sigma_p: np.ndarray
    lengthscale2: np.ndarray


def solve_blocks(x: np.ndarray, y: np.ndarray, mask: np.ndarray, point: np.ndarray, sigma_p: np.ndarray,
                 lengthscale2: np.ndarray, noise2: float) -> BlockSystem:
    """Factorise the padded training sets of B blocks (R&W Algorithm 2.1, lines 2 and 3).

    Args:
        x: (B, n, 2) inputs, metres.
        y: (B, n) targets minus the prior mean, metres (anything on padding).
        mask: (B, n) real points.
        point: (B, n) caller's index of each point.
        sigma_p: (B,) metres.
        lengthscale2: (B, 2) m^2.
        noise2: sigma_eta^2, m^2.
    """
    k = kernel(x, x, sigma_p, lengthscale2)
    pair = mask[:, :, None] & mask[:, None, :]
    n = x.shape[1]
    eye = np.eye(n, dtype=bool)[None]
    k = np.where(pair, k, 0.0) + np.where(eye, np.where(mask[:, :, None], noise2, 1.0), 0.0)
    lower = np.linalg.cholesky(k)
    y = np.where(mask, y, 0.0)
    alpha = _tri_solve(lower, _tri_solve(lower, y[..., None]), transpose=True)[..., 0]
    return BlockSystem(x, mask, point, lower, alpha, np.asarray(sigma_p, float), np.asarray(lengthscale2, float))


def predict_blocks(system: BlockSystem, xs: np.ndarray, xs_mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Posterior deviation from the prior mean and variance at B x m test inputs (eqs. 6, 7).

    Args:
        system: factorised blocks.
        xs: (B, m, 2) test inputs, metres.
        xs_mask: (B, m) real test inputs.

    Returns:
        ``(mean, var)``, each (B, m): mean deviation from mu_k (metres) and surface variance
        (m^2, without the noise variance); zero where ``xs_mask`` is False.
    """
    ks = kernel(system.x, xs, system.sigma_p, system.lengthscale2)  # (B, n, m)
    ks = np.where(system.mask[:, :, None] & xs_mask[:, None, :], ks, 0.0)
    mean = np.einsum('bnm,bn->bm', ks, system.alpha)
    v = _tri_solve(system.lower, ks)
    var = system.sigma_p[:, None] ** 2 - np.einsum('bnm,bnm->bm', v, v)
    return np.where(xs_mask, mean, 0.0), np.where(xs_mask, np.maximum(var, 0.0), 0.0)


def loo_statistic(system: BlockSystem) -> np.ndarray:
    """Leave-one-out chi-squared statistic of every training point (R&W eq. 5.12).

    v_i^2 = (y_i - mu_-i)^2 / sigma_-i^2 = alpha_i^2 / [K^-1]_ii, where mu_-i and
    sigma_-i^2 are the mean and variance (noise included) predicted for point i by the
    block's GP without it.

    Returns:
        (B, n) statistics, NaN on padding.
    """
    n = system.x.shape[1]
    l_inv = _tri_solve(system.lower, np.broadcast_to(np.eye(n), system.lower.shape))
    k_inv_diag = np.einsum('bij,bij->bj', l_inv, l_inv)
    return np.where(system.mask, system.alpha**2 / k_inv_diag, np.nan)


# ----------------------------------------------------------------------------------------
# Block assembly: which training points each block sees
# ----------------------------------------------------------------------------------------
_NB = np.int64(1 << 20)  # codes: (facet * NB + bu) * NB + bv, block indices offset by NB/2
_HALF = np.int64(1 << 19)
#: Code offsets of a block's extended block: itself and its 8 neighbours (same facet).
_NEIGHBOURS = np.array([du * _NB + dv for du in (-1, 0, 1) for dv in (-1, 0, 1)], dtype=np.int64)
#: Threads solving blocks (the compiled kernel releases the GIL).
THREADS = 2


def in_sorted(values: np.ndarray, keys: np.ndarray) -> np.ndarray:
    """(N,) bool: which of (N,) ``values`` are among (K,) ``keys`` (``np.isin``), by binary
    search when the keys are sorted and unique (O(N log K) instead of sorting all N + K
    values, which matters when a few block codes are looked up among all of a façade's
    points); other keys are looked up by ``np.isin``."""
    values = np.asarray(values)
    keys = np.asarray(keys)
    if not len(keys):
        return np.zeros(values.shape, dtype=bool)
    if keys.ndim != 1 or (len(keys) > 1 and not np.all(keys[1:] > keys[:-1])):
        return np.isin(values, keys)
    pos = np.minimum(np.searchsorted(keys, values), len(keys) - 1)
    return keys[pos] == values


def block_codes(uv: np.ndarray, facet: np.ndarray, origin: np.ndarray, sizes: np.ndarray) -> np.ndarray:
    """(N,) int64 code of the block holding each location, in its facet's block grid.

    Args:
        uv: (N, 2) locations, metres, façade frame.
        facet: (N,) facet index (>= 0).
        origin: (2,) corner of the block grids, metres.
        sizes: (F, 2) block side per facet and axis, metres.
    """
    b = np.floor((uv - origin) / sizes[facet]).astype(np.int64) + _HALF
    return (facet.astype(np.int64) * _NB + b[:, 0]) * _NB + b[:, 1]


def _ranks(group: np.ndarray) -> np.ndarray:
    """Rank of each element within its run of equal values in a sorted array."""
    start = np.r_[0, np.flatnonzero(np.diff(group)) + 1]
    lengths = np.diff(np.r_[start, len(group)])
    return np.arange(len(group)) - np.repeat(start, lengths)


def gather_blocks(blocks: np.ndarray, train_codes: np.ndarray, cap: int, rng: np.random.Generator
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Training points of each block's extended block (the block and its 8 neighbours).

    Args:
        blocks: (B,) block codes.
        train_codes: (T,) block code of each training point.
        cap: at most this many points per block; points of the block itself are kept
            first, the rest drawn at random.
        rng: random source for the draw.

    Returns:
        ``(block, point, rank)``: flat arrays, one row per (block, member): the block's
        position in ``blocks``, the member's index in the training arrays, and its slot
        (0 .. n_b - 1).
    """
    from ._gp_kernels import gather_capped

    order = np.argsort(train_codes, kind='stable')
    sorted_codes = train_codes[order]
    neighbours = blocks[:, None] + _NEIGHBOURS[None, :]  # (B, 9); facet stays, |du|,|dv| <= 1
    start = np.searchsorted(sorted_codes, neighbours, side='left')
    count = np.searchsorted(sorted_codes, neighbours, side='right') - start
    # One key per (block, neighbour, point); the block's own points sort first (key + 0), the
    # neighbours' after (key + 1), each in random order; the first ``cap`` are kept.
    key = rng.random(int(count.sum()))
    return gather_capped(start, count, order, _NEIGHBOURS == 0, key, int(cap))


@dataclass(frozen=True, eq=False)
class BlockData:
    """Training data of one façade's local GPs, with what each facet's GP needs.

    Attributes:
        uv: (T, 2) training inputs, metres, façade frame.
        y: (T,) depth minus the prior mean mu_k of the point's facet, metres.
        facet: (T,) facet of each point.
        sigma_p: (F,) prior standard deviation per facet, metres.
        lengthscale2: (F, 2) 1/b per facet and axis, m^2.
        origin: (2,) corner of the block grids, metres.
    """

    uv: np.ndarray
    y: np.ndarray
    facet: np.ndarray
    sigma_p: np.ndarray
    lengthscale2: np.ndarray
    origin: np.ndarray

    def sizes(self, c_min: float) -> np.ndarray:
        """(F, 2) block side per facet, metres (paper eq. 9)."""
        return block_size(self.lengthscale2, c_min)

    def subset(self, keep: np.ndarray) -> BlockData:
        """The same GPs with only the training points where ``keep`` holds."""
        return BlockData(self.uv[keep], self.y[keep], self.facet[keep], self.sigma_p, self.lengthscale2, self.origin)


@functools.cache
def _pool() -> ThreadPoolExecutor:
    """The threads solving blocks, started once per process (a thread start costs
    milliseconds on a busy machine, and a façade update calls the kernel twice)."""
    return ThreadPoolExecutor(max_workers=THREADS, thread_name_prefix='gp_blocks')


def _run_blocks(data: BlockData, blocks: np.ndarray, tests: np.ndarray, test_start: np.ndarray, uv: np.ndarray,
                params: GPParams, rng: np.random.Generator, want_loo: bool
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Solve blocks ``blocks`` on their extended blocks' training points and predict at their tests.

    Args:
        data: training data.
        blocks: (B,) block codes.
        tests: (P,) indices into ``uv`` of the test locations, grouped by block.
        test_start: (B + 1,) block b's tests are ``tests[test_start[b]:test_start[b + 1]]``.
        uv: (N, 2) all test locations, metres, façade frame.
        params: GP settings.
        rng: random source for capping large blocks.
        want_loo: compute the leave-one-out statistic of each block's own points too (in its
            extended block: each training point is tested once, by the block it lies in).

    Returns:
        ``(mean, var, solved, members, member_block, loo)``: (P,) deviation and (P,) variance
        at ``tests``; (B,) blocks with training points; (M,) the members (indices into
        ``data``), (M,) their block and (M,) the leave-one-out statistic of the block's own
        points (NaN for the others and without ``want_loo``).
    """
    from ._gp_kernels import solve_predict_blocks

    codes = block_codes(data.uv, data.facet, data.origin, data.sizes(params.c_min))
    block, point, _ = gather_blocks(blocks, codes, params.max_block_points, rng)
    member_start = np.searchsorted(block, np.arange(len(blocks) + 1))
    facet_of_block = (blocks // _NB // _NB).astype(np.int64)
    mean = np.zeros(len(tests))
    var = np.zeros(len(tests))
    loo = np.full(len(point), np.nan)
    own = (codes[point] == blocks[block]) if want_loo else np.zeros(len(point), dtype=bool)
    solved = np.zeros(len(blocks), dtype=bool)
    args = (np.ascontiguousarray(data.uv, dtype=np.float64), np.ascontiguousarray(data.y, dtype=np.float64),
            np.ascontiguousarray(data.sigma_p[facet_of_block], dtype=np.float64),
            np.ascontiguousarray(data.lengthscale2[facet_of_block], dtype=np.float64), float(params.noise_sigma**2),
            member_start, np.ascontiguousarray(point), test_start,
            np.ascontiguousarray(uv[tests], dtype=np.float64), own, mean, var, loo, solved)
    # Two ranges of blocks of about equal work (n^2 (n + m) per block), one per thread.
    n = np.diff(member_start).astype(np.float64)
    work = np.cumsum(n * n * (n + np.diff(test_start)))
    n_threads = threads(THREADS)
    if n_threads <= 1 or len(blocks) < 2 or work[-1] < 1e6:
        solve_predict_blocks(0, len(blocks), *args)
    else:
        cuts = np.r_[0, np.searchsorted(work, work[-1] * np.arange(1, n_threads) / n_threads), len(blocks)]
        list(_pool().map(lambda r: solve_predict_blocks(int(r[0]), int(r[1]), *args), zip(cuts[:-1], cuts[1:])))
    return mean, var, solved, point, block, loo


def fit_surface(data: BlockData, uv: np.ndarray, facet: np.ndarray, params: GPParams, rng: np.random.Generator,
                outlier_alpha: float | None = None, outlier_iterations: int = 0
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Filter outliers and predict each facet's local GPs at test locations, block by block.

    Every block holding test locations is solved once; the same factorisation gives the
    leave-one-out statistic of the block's own training points (outlier test, see
    :mod:`~uncertain_facade_map.pipeline.step5_outliers`) and the prediction. After removing outliers,
    only blocks whose extended block lost a point are solved again.

    Args:
        data: training data and GP parameters.
        uv: (P, 2) test locations, metres, façade frame.
        facet: (P,) facet of each test location (>= 0).
        params: GP settings.
        rng: random source for capping large blocks.
        outlier_alpha: significance level of the chi-squared test; None for no test.
        outlier_iterations: test-remove rounds.

    Returns:
        ``(mean, var, seen, outlier)``: (P,) deviation from the facet's prior mean
        (metres), (P,) surface variance (m^2), (P,) whether the block's GP had training
        points (else mean 0 and var sigma_p^2), and (T,) bool training points removed as
        outliers.
    """
    from .step5_outliers import flag_outliers

    sizes = data.sizes(params.c_min)
    codes = block_codes(uv, facet, data.origin, sizes)
    blocks, inverse = np.unique(codes, return_inverse=True)
    order = np.argsort(inverse, kind='stable')
    starts = np.searchsorted(inverse[order], np.arange(len(blocks) + 1))
    train_codes = block_codes(data.uv, data.facet, data.origin, sizes)
    mean = np.zeros(len(uv))
    var = data.sigma_p[facet] ** 2
    seen = np.zeros(len(uv), dtype=bool)
    removed = np.zeros(len(data.y), dtype=bool)
    active = np.ones(len(data.y), dtype=bool)
    todo = np.arange(len(blocks))
    for round_ in range(outlier_iterations + 1):
        test = outlier_alpha is not None and round_ < outlier_iterations
        live = np.flatnonzero(active)
        # The test locations of the blocks to do, grouped by block.
        counts = starts[todo + 1] - starts[todo]
        test_start = np.r_[0, np.cumsum(counts)]
        tests = order[np.repeat(starts[todo] - test_start[:-1], counts) + np.arange(test_start[-1])]
        mu, v, solved, members, member_block, loo = _run_blocks(data.subset(active), blocks[todo], tests,
                                                                test_start, uv, params, rng, test)
        # Blocks solved again get their prediction replaced; blocks left without training points revert.
        got = np.repeat(solved, counts)
        cells = tests[got]
        mean[cells] = mu[got]
        var[cells] = v[got]
        seen[cells] = True
        lost = tests[~got]
        mean[lost] = 0.0
        var[lost] = data.sigma_p[facet[lost]] ** 2
        seen[lost] = False
        if not test:
            break
        # Each training point is tested by the block that owns it (R&W eq. 5.12 in its extended block).
        stat = np.full(len(data.y), np.nan)
        own = solved[member_block] & np.isfinite(loo)
        stat[live[members[own]]] = loo[own]
        flagged = flag_outliers(stat, outlier_alpha) & active
        if not flagged.any():
            break
        removed |= flagged
        active &= ~flagged
        # Blocks whose extended block held a removed point are solved again.
        hit = np.unique(train_codes[flagged][:, None] + _NEIGHBOURS[None, :])
        todo = np.flatnonzero(in_sorted(blocks, hit))  # hit: sorted, unique
    return mean, var, seen, removed
