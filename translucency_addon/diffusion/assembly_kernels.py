"""The numba kernel of :func:`.assembly.assemble`'s conservative scheme (``scheme="fv"``): every link's
coefficient and every row's diagonal in one pass over the graph's link slots.

Imported only by :func:`.assembly._kernel`, inside a guard: importing this module needs numba.  Module-level
functions, so numba's on-disk cache (``cache=True``) finds them again in a new process.  The arithmetic is
:func:`.assembly._numpy_fv`'s lines, term by term and in their order, so the two agree to rounding (a row's
diagonal sums its links in slot order, numpy's ``einsum`` in its own): ``tests/test_diffusion.py``.
"""

from __future__ import annotations

import math

import numba


@numba.njit(cache=True, nogil=True, inline="always")
def fitted_link(T0, x):
    """``(T, C)`` of a link of optical length x = sigma_tr d (:func:`.assembly._fitted_link`, one value)."""
    x = max(x, 1e-8)
    if x < 1e-3:
        return T0 * (1.0 - x * x / 6.0), T0 * (1.0 + x * x / 3.0)
    T = T0 * x / math.sinh(min(x, 700.0))
    C = T0 * x / math.tanh(x)
    if x > 700.0:
        T = 0.0
    return T, C


@numba.njit(parallel=True, cache=True, nogil=True)
def fv_links(nbr, inv_kappa, mu, face_area, edge_length, volume, s, n_inner, off, diag):
    """Eq. 1's finite-volume links, every node's row in parallel::

        off_ik = kappa_ij A_ij / d_ij,   kappa_ij = 2 / (1/kappa_i + 1/kappa_j)   (0 where slot k is empty)
        diag_i = sum_k off_ik  (+ mu_i V_i at inner nodes)

    in mm (``s`` mm per object unit).  ``off`` (N, K, C) and ``diag`` (N, C) are written."""
    N, K = nbr.shape
    C = inv_kappa.shape[1]
    s3 = s ** 3
    for n in numba.prange(N):
        for c in range(C):
            diag[n, c] = 0.0
        for k in range(K):
            j = nbr[n, k]
            if j < 0:
                for c in range(C):
                    off[n, k, c] = 0.0
                continue
            G = face_area[n, k] * s * s / (edge_length[n, k] * s)
            for c in range(C):
                o = 2.0 / (inv_kappa[j, c] + inv_kappa[n, c]) * G
                off[n, k, c] = o
                diag[n, c] += o
        if n < n_inner:
            vs = volume[n] * s3
            for c in range(C):
                diag[n, c] += mu[n, c] * vs


@numba.njit(cache=True, nogil=True)
def fv_surface_links(nbr, inv_kappa, mu, face_area, edge_length, volume, s, n_inner, off, diag):
    """The surface links' exponentially fitted flux (:func:`.assembly._fitted_link`) on the rows
    :func:`fv_links` wrote, surface node after surface node (two may share an inner node): slot 0 of a surface
    node and the inner node's slot back to it take T, the surface row gains ``C - T0``, the inner row
    ``T - T0`` less the link's leading absorption ``min(C - T, mu a d / 2, mu V / 2)``."""
    N, K = nbr.shape
    C = inv_kappa.shape[1]
    s3 = s ** 3
    for i in range(n_inner, N):
        kin = nbr[i, 0]
        slot = 0
        for k in range(K):
            if nbr[kin, k] == i:
                slot = k
                break
        d = edge_length[i, 0] * s
        G = face_area[i, 0] * s * s / d
        for c in range(C):
            kf = 2.0 / (inv_kappa[kin, c] + inv_kappa[i, c])
            mu_s = 0.5 * (mu[i, c] + mu[kin, c])
            x = math.sqrt(mu_s / kf) * d
            T0 = G * kf
            T, Cf = fitted_link(T0, x)
            off[i, 0, c] = T
            off[kin, slot, c] = T
            diag[i, c] += Cf - T0
            diag[kin, c] += T - T0
            lead = 0.5 * mu_s * (face_area[i, 0] * s * s * d)
            cell = mu[kin, c] * (volume[kin] * s3)
            diag[kin, c] -= min(min(Cf - T, lead), 0.5 * cell)
