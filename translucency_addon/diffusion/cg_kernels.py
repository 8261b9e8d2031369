"""The numba kernels of :mod:`.compiled_cg` (see its docstring for what they compute and why).

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
