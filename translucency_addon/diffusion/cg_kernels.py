"""The numba kernels of :mod:`.compiled_cg` (see its docstring for what they compute and why): CG's two
vector passes and the sparse product over the graph's link slots (also :class:`.sweeps.SweepOperator`'s).

Imported only by :func:`.compiled_cg._kernel`, inside a guard: importing this module needs numba.  Module-level
functions, so numba's on-disk cache (``cache=True``) finds them again in a new process.  Each kernel splits
the nodes into ``nchunk`` contiguous runs, one task each, and walks a channel's run as one stream.
"""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(parallel=True, cache=True, nogil=True)
def update(X, R, P, Q, alpha, inv_diag, agg, n_agg, nchunk):
    """``x += alpha p``, ``r += alpha q`` per channel (q = -A p), and of the new r: its sums over each
    aggregate (``P_c^T r``), ``|r|^2`` and ``r . D^-1 r``; returns ``(box (C, n_agg), sums (2, C))``."""
    C, n = X.shape
    box = np.zeros((nchunk, C, n_agg))
    sums = np.zeros((nchunk, 2, C))
    for k in numba.prange(nchunk):
        lo, hi = (n * k) // nchunk, (n * (k + 1)) // nchunk
        for c in range(C):
            a = alpha[c]
            s2 = 0.0
            sd = 0.0
            for i in range(lo, hi):
                X[c, i] += a * P[c, i]
                r = R[c, i] + a * Q[c, i]
                R[c, i] = r
                s2 += r * r
                sd += r * r * inv_diag[c, i]
                box[k, c, agg[i]] += r
            sums[k, 0, c] = s2
            sums[k, 1, c] = sd
    return box.sum(axis=0), sums.sum(axis=0)


@numba.njit(parallel=True, cache=True, nogil=True)
def direction(P, R, inv_diag, y, agg, beta, nchunk):
    """``p = beta p + z`` per channel with ``z = M^-1 r = D^-1 r + P_c y`` (y: the coarse solution per
    aggregate; zeros without a coarse space), z never stored."""
    C, n = P.shape
    for k in numba.prange(nchunk):
        lo, hi = (n * k) // nchunk, (n * (k + 1)) // nchunk
        for c in range(C):
            b = beta[c]
            for i in range(lo, hi):
                P[c, i] = b * P[c, i] + inv_diag[c, i] * R[c, i] + y[c, agg[i]]


@numba.njit(parallel=True, cache=True, nogil=True)
def link_product(nbr, off, neg_diag, D, R, accumulate, width, nchunk):
    """``r (+)= -A d`` per channel over the graph's link slots, and ``d . (-A d)`` per channel.

    ``(-A d)_i = -diag_i d_i + sum_k off_ik d_nbr[i,k]`` (slots with ``nbr < 0`` empty): nbr (N, K) in the
    sweep order, off (C0, N, K) and neg_diag (C0, N) per base channel; channel c of d and r (C, N) takes
    base channel ``c % C0`` (the bounce's two copies share one operator).  ``accumulate``: add to r, else
    overwrite it (no zeroing pass).  ``width[i]``: row i's slots from its last non-empty one on are empty
    and not read (a fluid cell fills 14 of 23 on average: 13.3 -> 11.3 ms a product at 262k particles)."""
    C, n = D.shape
    C0 = off.shape[0]
    dots = np.zeros((nchunk, C))
    for k in numba.prange(nchunk):
        lo, hi = (n * k) // nchunk, (n * (k + 1)) // nchunk
        for c in range(C):
            b = c % C0
            s = 0.0
            for i in range(lo, hi):
                acc = neg_diag[b, i] * D[c, i]
                for m in range(width[i]):
                    j = nbr[i, m]
                    if j >= 0:
                        acc += off[b, i, m] * D[c, j]
                s += D[c, i] * acc
                if accumulate:
                    R[c, i] += acc
                else:
                    R[c, i] = acc
            dots[k, c] = s
    return dots.sum(axis=0)


@numba.njit(parallel=True, cache=True, nogil=True)
def to_channel_major(v, perm, out, nchunk):
    """``out[c, i] = v[perm[i], c]``: node-major (N, C) to channel-major (C, N) in the operator's order, cast to
    out's dtype on the way (:meth:`.sweeps.SweepOperator.to_cm`)."""
    n, C = perm.shape[0], v.shape[1]
    for k in numba.prange(nchunk):
        lo, hi = (n * k) // nchunk, (n * (k + 1)) // nchunk
        for i in range(lo, hi):
            p = perm[i]
            for c in range(C):
                out[c, i] = v[p, c]


@numba.njit(parallel=True, cache=True, nogil=True)
def from_channel_major(V, perm, out, nchunk):
    """``out[perm[i], c] = V[c, i]``: :func:`to_channel_major` undone (:meth:`.sweeps.SweepOperator.from_cm`)."""
    C, n = V.shape
    for k in numba.prange(nchunk):
        lo, hi = (n * k) // nchunk, (n * (k + 1)) // nchunk
        for i in range(lo, hi):
            p = perm[i]
            for c in range(C):
                out[p, c] = V[c, i]


@numba.njit(cache=True, nogil=True)
def aggregate_pairs(links, agg, n_agg, mark):
    """The coarse space's occupied (aggregate, aggregate) pairs (:func:`.coarse_space._galerkin`): ``mark[a
    n_agg + b]`` set for every link from aggregate a to b and every node's own (a, a)."""
    N, K = links.shape
    for n in range(N):
        a = agg[n]
        mark[a * (n_agg + 1)] = True
        for k in range(K):
            j = links[n, k]
            if j >= 0:
                mark[a * n_agg + agg[j]] = True


@numba.njit(cache=True, nogil=True)
def aggregate_sums(links, agg, n_agg, rank, off, neg_diag, out):
    """``out[c, rank[a n_agg + b]] = sum`` of channel c's ``-A`` entries from aggregate a to b (``P^T (-A) P``),
    all channels in one pass over the link slots: each node's slots in order, then its diagonal."""
    N, K = links.shape
    C = off.shape[0]
    for c in range(C):
        for e in range(out.shape[1]):
            out[c, e] = 0.0
    for n in range(N):
        a = agg[n]
        for k in range(K):
            j = links[n, k]
            if j >= 0:
                e = rank[a * n_agg + agg[j]]
                for c in range(C):
                    out[c, e] += off[c, n, k]
        e = rank[a * (n_agg + 1)]
        for c in range(C):
            out[c, e] += neg_diag[c, n]


@numba.njit(parallel=True, cache=True, nogil=True)
def permuted_slots(nbr, off, diag, perm, links, off_cm, neg_diag, inv_diag, width):
    """A level's link slots in sweep order ``perm`` (new position -> old node), channel-major, in one pass
    (:class:`.sweeps.SweepOperator`'s layout; numpy's twin, its gathers and transposes, makes five copies of
    (N, K, C)): row r is node perm[r], ``links[r, k]`` its slot k's neighbour's new position (-1: empty),
    ``off_cm[c, r, k]``, ``neg_diag[c, r] = -diag`` and ``inv_diag[c, r] = 1 / diag`` (the sweep precision),
    ``width[r]`` one past its last non-empty slot (:func:`link_product` reads no further)."""
    N, K = nbr.shape
    C = diag.shape[1]
    inv = np.empty(N, dtype=np.int64)
    for r in numba.prange(N):
        inv[perm[r]] = r
    for r in numba.prange(N):
        i = perm[r]
        w = 0
        for k in range(K):
            j = nbr[i, k]
            links[r, k] = inv[j] if j >= 0 else -1
            if j >= 0:
                w = k + 1
            for c in range(C):
                off_cm[c, r, k] = off[i, k, c]
        for c in range(C):
            d = diag[i, c]
            neg_diag[c, r] = -d
            inv_diag[c, r] = 1.0 / d
        width[r] = w
