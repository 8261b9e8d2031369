"""The numba kernels of :mod:`.compiled_map` (see its docstring): the vertex map's gather and the split's
per-vertex output where the lamps enter through the volume.

Imported only by :func:`.compiled_map._kernel`, inside a guard: importing this module needs numba.  Module-level
functions, so numba's on-disk cache (``cache=True``) finds them again in a new process.
"""

from __future__ import annotations

import numba


@numba.njit(parallel=True, cache=True, nogil=True)
def gather(idx, w, X, out):
    """``out[v, c] = sum_k w[v, k] X[idx[v, k], c]``, the slots summed in order from zero (as the CSR product of
    :func:`.radiance.mapping_operator` sums a row)."""
    n, K = idx.shape
    C = X.shape[1]
    for v in numba.prange(n):
        for c in range(C):
            out[v, c] = 0.0
        for k in range(K):
            j = idx[v, k]
            wk = numba.float64(w[v, k])
            for c in range(C):
                out[v, c] += wk * X[j, c]


@numba.njit(parallel=True, cache=True, nogil=True)
def transported_output(L, shape, single, local, unit, c, fdr, out):
    """The split's output where the lamps enter through the volume, per point and channel, in one pass
    (:meth:`.solver.DiffusionSolver.split_radiance_at`; numpy twin: its own lines and
    :meth:`.split.HalfSpaceSplit.with_transported`, eq. 9 of :mod:`.split`)::

        P = (1 - F_dr) L / unit,  rest = max(P - local, 0),  tot = max(P, local)
        out = ((tot - rest) shape + rest c) / tot * L + single        (shape where tot = 0)

    ``unit`` and ``c``: (n,) per point or (1,) for every point (the view along the normal)."""
    n, C = L.shape
    for v in numba.prange(n):
        u = unit[v] if unit.shape[0] > 1 else unit[0]
        cc = c[v] if c.shape[0] > 1 else c[0]
        for ch in range(C):
            P = (1.0 - fdr) * L[v, ch] / u if u > 0 else 0.0
            loc = local[v, ch]
            rest = P - loc
            if rest < 0.0:
                rest = 0.0
            tot = P if P > loc else loc
            s = shape[v, ch]
            if tot > 0:
                s = ((tot - rest) * s + rest * cc) / tot
            out[v, ch] = s * L[v, ch] + single[v, ch]
