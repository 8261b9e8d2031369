"""Numpy twins of the GPU compute kernels (``gpu_shaders/*.glsl``).

Each function here does, for all nodes at once, exactly what one dispatch of
the matching GLSL kernel does per texel, on the same packed data:

* ``nbr`` (N, 4) int: neighbour node indices, -1 where there is none;
* ``off`` (N, 4, 3): the positive off-diagonal coefficients c_ij per channel;
* ``diag`` (N, 3): the diagonal a_ii;
* a row reads  ``diag_i phi_i - sum_j c_ij phi_j = b_i``.

Both discretisations (the paper's eq. 5/6 and our conservative one) are
expressed in this form, so the kernels do not know which one they run.  The
CPU solver calls these functions; the GPU path dispatches the GLSL twins; the
parity tests run both on the same inputs.
"""

from __future__ import annotations

import numpy as np


def gather(nbr: np.ndarray, x: np.ndarray) -> np.ndarray:
    """x at the 4 neighbours of every node, zero where there is no neighbour: (N, 4, C)."""
    xp = np.concatenate([x, np.zeros((1,) + x.shape[1:], dtype=x.dtype)])
    return np.take(xp, nbr, axis=0)  # index -1 picks the zero row; take: ~7x faster than xp[nbr] (numpy 2.3)


def offdiag_product(nbr, off, x) -> np.ndarray:
    """sum_j c_ij x_j for every node: (N, C)."""
    return np.einsum("nkc,nkc->nc", off, gather(nbr, x))


def apply_matrix(nbr, off, diag, x) -> np.ndarray:
    """A x = diag x - sum_j c_ij x_j."""
    return diag * x - offdiag_product(nbr, off, x)


def jacobi_sweep(nbr, off, diag, b, x) -> np.ndarray:
    """One Jacobi relaxation: x_i <- (b_i + sum_j c_ij x_j) / diag_i.

    With the paper's coefficients this is exactly eqs. 8 and 9 (kernel
    ``jacobi.glsl``).
    """
    return (b + offdiag_product(nbr, off, x)) / diag


def residual(nbr, off, diag, b, x) -> np.ndarray:
    """r = b - A x (kernel ``residual.glsl``)."""
    return b - apply_matrix(nbr, off, diag, x)


def chebyshev_step(nbr, off, diag, x, r, d, coef_d, coef_r):
    """One fused step of Chebyshev semi-iteration (kernel ``chebyshev.glsl``).

    x' = x + d;  r' = r - A d;  d' = coef_d * d + coef_r * r' / diag

    (Saad, *Iterative Methods for Sparse Linear Systems*, 2nd ed., Alg. 12.1,
    with the Jacobi preconditioner D; ``coef_d = rho_{k+1} rho_k`` and
    ``coef_r = 2 rho_{k+1} / delta`` are per channel scalars computed on the
    host.)  Every output of node i needs only its own x, r, d and the d of its
    4 neighbours, so one dispatch does the whole step.
    """
    return chebyshev_update(x, r, d, apply_matrix(nbr, off, diag, d), diag, coef_d, coef_r)


def chebyshev_update(x, r, d, Ad, diag, coef_d, coef_r):
    """The vector part of :func:`chebyshev_step` given ``Ad = A d`` (shared by CPU and twin)."""
    x2 = x + d
    r2 = r - Ad
    d2 = coef_d * d + coef_r * r2 / diag
    return x2, r2, d2


def squared_norms(v: np.ndarray) -> np.ndarray:
    """Per-channel sum of squares (the reduction of ``reduce.glsl``)."""
    return np.einsum("nc,nc->c", v, v)


def shepard_upsample(idx: np.ndarray, w: np.ndarray, x_coarse: np.ndarray) -> np.ndarray:
    """Eq. 10: x_fine = sum_y w_xy x_coarse[y] over b coarse nodes (kernel ``upsample.glsl``)."""
    return np.einsum("nb,nbc->nc", w.astype(x_coarse.dtype), gather(idx, x_coarse))


def shepard_matrix(idx: np.ndarray, w: np.ndarray, n_coarse: int):
    """Eq. 10 as a sparse (N_fine, N_coarse) matrix: row x holds w_xy at its b coarse nodes y (an empty slot,
    idx -1, holds 0), so ``M @ x_coarse`` is :func:`shepard_upsample` in one sparse product (the CPU driver's
    form, built once per bake level: 12 against 80 ms on the Final bunny's 402k-node level, which the
    gather of (N, 8, 3) values spends on memory)."""
    import scipy.sparse as sp

    n, b = idx.shape
    data = np.where(idx >= 0, np.asarray(w, dtype=np.float64), 0.0).ravel()
    cols = np.maximum(idx, 0).astype(np.int32 if n_coarse < 2**31 else np.int64).ravel()
    return sp.csr_matrix((data, cols, np.arange(0, n * b + 1, b)), shape=(n, n_coarse))


def partial_current(phi_s, q, fdr: float) -> np.ndarray:
    """J+ = (phi - 2 q) / (2 (1 + F_dr)), unclamped: the outgoing partial current of the
    diffusive-source boundary condition (derived in ``diffusion.py``; the corrected eq. 6/9).

    The one place this formula is written in Python; the energy balances use it unclamped, the
    output through :func:`outgoing_partial_current` (its GLSL twin: ``jplus.glsl``).
    """
    return (np.asarray(phi_s) - 2.0 * np.asarray(q)) / (2.0 * (1.0 + fdr))


def outgoing_partial_current(phi_s: np.ndarray, q: np.ndarray, fdr: float) -> np.ndarray:
    """J+ = max(0, phi - 2 q) / (2 (1 + F_dr)) at surface nodes (kernel ``radiance.glsl``).

    :func:`partial_current` clamped at zero (see ``radiance.outgoing_radiance`` for when it can
    be negative and why).
    """
    return np.maximum(partial_current(phi_s, q, fdr), 0.0)


def in_channels(x, cols) -> np.ndarray:
    """``x`` (n, len(cols)) or (len(cols),) written into the channels ``cols`` of zeros with 3 channels."""
    x = np.asarray(x)
    cols = tuple(int(c) for c in cols)
    if cols == (0, 1, 2):  # all channels: a copy (a fancy-indexed assignment cost ~10 ms at 800k nodes)
        return np.array(x, dtype=np.float64)
    full = np.zeros(x.shape[:-1] + (3,))
    for k, c in enumerate(cols):
        full[..., c] = x[..., k]
    return full
