"""Compiled kernels of the local GPs in blocks (numba), one block at a time.

The street's blocks hold under 64 training points each: with numpy, the cost of a block
solve is the calls (kernel, batched Cholesky, n-step triangular solves, einsum), not the
flops. These kernels do the same arithmetic (R&W Algorithm 2.1; paper eqs. 4, 6 and 7;
the leave-one-out statistic of R&W eq. 5.12) block by block in compiled loops, without
padding. They release the GIL (``nogil``), so the caller runs them over disjoint ranges of
blocks in threads; each block's arithmetic is sequential and independent of the others,
so results do not depend on the number of threads or their timing.

:func:`~uncertain_facade_map.pipeline.step4_gp_blocks.solve_blocks`,
``predict_blocks`` and ``loo_statistic`` are the batched numpy reference the tests compare
these kernels with.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True, nogil=True, fastmath=True)
def _cholesky_in_place(a: np.ndarray, n: int) -> bool:  # pragma: no cover - compiled
    """Lower Cholesky factor of a[:n, :n] (lower triangle read) in place; False if not PD."""
    for j in range(n):
        s = a[j, j]
        for k in range(j):
            s -= a[j, k] * a[j, k]
        if s <= 0.0:
            return False
        d = math.sqrt(s)
        a[j, j] = d
        for i in range(j + 1, n):
            s = a[i, j]
            for k in range(j):
                s -= a[i, k] * a[j, k]
            a[i, j] = s / d
    return True


@njit(cache=True, nogil=True, fastmath=True)
def solve_predict_blocks(first: int, last: int, uv: np.ndarray, y: np.ndarray, sigma_p: np.ndarray,
                         lengthscale2: np.ndarray, noise2: float, member_start: np.ndarray, members: np.ndarray,
                         test_start: np.ndarray, test_uv: np.ndarray, loo_of: np.ndarray, mean: np.ndarray,
                         var: np.ndarray, loo: np.ndarray, solved: np.ndarray) -> None:  # pragma: no cover
    """Factorise blocks ``first .. last - 1`` and predict at their test locations.

    Args:
        first, last: the range of blocks to do.
        uv: (T, 2) training inputs, metres, façade frame.
        y: (T,) targets minus the prior mean, metres.
        sigma_p: (B,) prior standard deviation of each block's facet, metres.
        lengthscale2: (B, 2) 1/b of each block's facet, m^2.
        noise2: sigma_eta^2, m^2.
        member_start: (B + 1,) block b's training points are ``members[member_start[b]:member_start[b + 1]]``.
        members: (M,) indices into ``uv``/``y``.
        test_start: (B + 1,) block b's test locations are ``test_uv[test_start[b]:test_start[b + 1]]``.
        test_uv: (P, 2) test locations grouped by block, metres.
        loo_of: (M,) bool, the members whose leave-one-out statistic is wanted (all False:
            none; each costs (n - rank)^2 / 2 with the members factorised in reverse order,
            so a block's own points, listed first, are cheap).
        mean: (P,) out: posterior deviation from the prior mean (eq. 6), metres.
        var: (P,) out: posterior variance of the surface, noise excluded (eq. 7), m^2.
        loo: (M,) out: (y_i - mu_-i)^2 / sigma_-i^2 with the noise in sigma_-i^2 (R&W eq. 5.12),
            where ``loo_of``.
        solved: (B,) out: True for blocks with training points (others are left alone).
    """
    n_max = 0
    for b in range(first, last):
        n_max = max(n_max, member_start[b + 1] - member_start[b])
    low = np.empty((n_max, n_max))
    alpha = np.empty(n_max)
    ks = np.empty(n_max)
    for b in range(first, last):
        m0 = member_start[b]
        n = member_start[b + 1] - m0
        if n == 0:
            continue
        s2 = sigma_p[b] * sigma_p[b]
        b0 = 1.0 / lengthscale2[b, 0]
        b1 = 1.0 / lengthscale2[b, 1]
        # K + sigma_eta^2 I (eq. 4 with the noise of eq. 5), lower triangle; then L (Alg. 2.1 line 2).
        # Members in reverse order: the block's own points (listed first) factorised last.
        last_member = m0 + n - 1
        for i in range(n):
            pi = members[last_member - i]
            ui = uv[pi, 0]
            vi = uv[pi, 1]
            for j in range(i + 1):
                pj = members[last_member - j]
                du = ui - uv[pj, 0]
                dv = vi - uv[pj, 1]
                low[i, j] = s2 * math.exp(-0.5 * (b0 * du * du + b1 * dv * dv))
            low[i, i] += noise2
        if not _cholesky_in_place(low, n):
            continue
        solved[b] = True
        # alpha = L^T \ (L \ y) (Alg. 2.1 line 3).
        for i in range(n):
            s = y[members[last_member - i]]
            for k in range(i):
                s -= low[i, k] * alpha[k]
            alpha[i] = s / low[i, i]
        for i in range(n - 1, -1, -1):
            s = alpha[i]
            for k in range(i + 1, n):
                s -= low[k, i] * alpha[k]
            alpha[i] = s / low[i, i]
        # Predictions: mean = k*^T alpha (eq. 6), var = k(x*, x*) - |L \ k*|^2 (eq. 7).
        for t in range(test_start[b], test_start[b + 1]):
            ut = test_uv[t, 0]
            vt = test_uv[t, 1]
            mu = 0.0
            for i in range(n):
                pi = members[last_member - i]
                du = uv[pi, 0] - ut
                dv = uv[pi, 1] - vt
                ks[i] = s2 * math.exp(-0.5 * (b0 * du * du + b1 * dv * dv))
                mu += ks[i] * alpha[i]
            q = 0.0
            for i in range(n):
                s = ks[i]
                for k in range(i):
                    s -= low[i, k] * ks[k]
                ks[i] = s / low[i, i]
                q += ks[i] * ks[i]
            mean[t] = mu
            var[t] = max(s2 - q, 0.0)
        # [K^-1]_ii = sum_r (L^-1)_ri^2; column i of L^-1 by forward substitution of e_i.
        for i in range(n):
            if not loo_of[last_member - i]:
                continue
            q = 0.0
            for r in range(i, n):
                s = 1.0 if r == i else 0.0
                for k in range(i, r):
                    s -= low[r, k] * ks[k]
                ks[r] = s / low[r, r]
                q += ks[r] * ks[r]
            loo[last_member - i] = alpha[i] * alpha[i] / q


@njit(cache=True, nogil=True)
def gather_capped(start: np.ndarray, count: np.ndarray, order: np.ndarray, central: np.ndarray, key: np.ndarray,
                  cap: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # pragma: no cover - compiled
    """Members of each block's extended block, at most ``cap``: the block's own points
    first, then its neighbours'; where more than ``cap``, those of lowest random key.

    Args:
        start, count: (B, 9) where each of a block's 9 neighbour blocks starts in ``order``
            and how many points it holds.
        order: (T,) training point indices sorted by block code.
        central: (9,) True for the neighbour offset that is the block itself.
        key: (sum(count),) random numbers in [0, 1), one per (block, neighbour, point) in
            that nested order; a point of the block itself sorts before the neighbours'.
        cap: at most this many members per block.

    Returns:
        ``(block, point, rank)`` as :func:`~uncertain_facade_map.pipeline.step4_gp_blocks.gather_blocks`.
    """
    n_blocks = start.shape[0]
    kept = np.empty(n_blocks, np.int64)
    for b in range(n_blocks):
        kept[b] = min(cap, count[b].sum())
    total = kept.sum()
    out_block = np.empty(total, np.int64)
    out_point = np.empty(total, np.int64)
    out_rank = np.empty(total, np.int64)
    n_max = 0
    for b in range(n_blocks):
        n_max = max(n_max, count[b].sum())
    cand = np.empty(n_max, np.int64)
    ck = np.empty(n_max)
    pos = 0  # position in key
    out = 0
    for b in range(n_blocks):
        n = count[b].sum()
        # Own points first, then the neighbours': only a block over the cap is sorted, and
        # only the part of it that the cap cuts (R&W's blocks hold a few dozen points; most
        # extended blocks are under the cap and need no order at all).
        base = pos
        c = 0
        n_own = 0
        for own_pass in (True, False):
            off = base
            for j in range(9):
                if central[j] == own_pass:
                    for t in range(count[b, j]):
                        cand[c] = order[start[b, j] + t]
                        ck[c] = key[off + t]
                        c += 1
                off += count[b, j]
            if own_pass:
                n_own = c
        pos = base + n
        if n > cap:
            if n_own >= cap:
                arrange = np.argsort(ck[:n_own], kind='mergesort')[:cap]
            else:
                arrange = np.concatenate((np.arange(n_own), n_own + np.argsort(ck[n_own:n], kind='mergesort')))[:cap]
            cand[:cap] = cand[arrange]
        for r in range(kept[b]):
            out_block[out] = b
            out_point[out] = cand[r]
            out_rank[out] = r
            out += 1
    return out_block, out_point, out_rank


@njit(cache=True, nogil=True)
def capped_draw(codes: np.ndarray, key: np.ndarray, cap: int) -> np.ndarray:  # pragma: no cover - compiled
    """(N,) bool: per block code, the ``cap`` points of smallest ``key`` (ties: the first).

    The selection of sorting by ``(codes, key)`` (``np.lexsort((key, codes))``, stable) and
    keeping each code's first ``cap``, in O(N) instead of a sort of all N: codes are
    grouped through an open-addressing table, and only the points of a block holding more
    than ``cap`` are sorted, among themselves.

    Args:
        codes: (N,) int64 block codes.
        key: (N,) float64 random keys.
        cap: points kept per code at most (>= 1).
    """
    n = len(codes)
    size = 16
    while size < 2 * n:
        size *= 2
    mask = size - 1
    table = np.full(size, -1, np.int64)  # slot -> group
    group_code = np.empty(n, np.int64)
    group = np.empty(n, np.int64)
    n_groups = 0
    for i in range(n):
        c = codes[i]
        s = np.int64((np.uint64(c) * np.uint64(0x9E3779B97F4A7C15)) >> np.uint64(32)) & mask
        while True:
            g = table[s]
            if g < 0:
                table[s] = n_groups
                group_code[n_groups] = c
                group[i] = n_groups
                n_groups += 1
                break
            if group_code[g] == c:
                group[i] = g
                break
            s = (s + 1) & mask
    count = np.zeros(n_groups, np.int64)
    for i in range(n):
        count[group[i]] += 1
    keep = np.ones(n, np.bool_)
    full = 0
    for g in range(n_groups):
        if count[g] > cap:
            full += 1
    if full == 0:
        return keep
    # The members of the full groups, group by group in index order (a counting sort).
    start = np.zeros(n_groups + 1, np.int64)
    for g in range(n_groups):
        start[g + 1] = start[g] + (count[g] if count[g] > cap else 0)
    fill = start[:-1].copy()
    members = np.empty(start[-1], np.int64)
    for i in range(n):
        g = group[i]
        if count[g] > cap:
            members[fill[g]] = i
            fill[g] += 1
    for g in range(n_groups):
        if count[g] <= cap:
            continue
        m = members[start[g]:start[g + 1]]
        k = np.empty(len(m))
        for t in range(len(m)):
            k[t] = key[m[t]]
        order = np.argsort(k, kind='mergesort')
        for t in range(cap, len(m)):
            keep[m[order[t]]] = False
    return keep
