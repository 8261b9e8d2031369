"""The view rays' sums over their (ray, sample) pairs in compiled code (numba): one pass for the three channels.

Imported only by :func:`.runtime._pair_kernel`, inside a guard: importing this module needs numba.  The same
products, added per ray in the same (pair) order as ``numpy.bincount`` does in
:func:`.runtime.integrate_view_rays`, so the sums are the same bit for bit (``tests/test_single_scattering.py``
holds the two paths to each other).
"""

from __future__ import annotations

import numba


@numba.njit(cache=True, nogil=True)
def sum_view(r, s, g, A, out):
    """``out[c, r_p] += A[c, s_p] g_p`` over the pairs p (A: light term times view term, (3, N))."""
    for p in range(r.shape[0]):
        i, j, w = r[p], s[p], g[p]
        out[0, i] += A[0, j] * w
        out[1, i] += A[1, j] * w
        out[2, i] += A[2, j] * w


@numba.njit(cache=True, nogil=True)
def sum_weighted(r, s, LT, pw, out):
    """``out[c, r_p] += LT[s_p, c] pw[p, c]`` over the pairs p (pw: psi towards the ray's origin times the
    ray's integral of the Gaussian, per pair and channel, float32 as kept)."""
    for p in range(r.shape[0]):
        i, j = r[p], s[p]
        out[0, i] += LT[j, 0] * float(pw[p, 0])
        out[1, i] += LT[j, 1] * float(pw[p, 1])
        out[2, i] += LT[j, 2] * float(pw[p, 2])
