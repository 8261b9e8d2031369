r"""The conjugate gradients' vector work in compiled code (numba): two passes per step instead of about ten.

:func:`.iterative.cg_steps` is the method (Saad Alg. 9.1 with the preconditioner
``M^-1 = D^-1 + P_c A_c^-1 P_c^T`` of :mod:`.coarse_space`); in numpy its step makes some ten passes
over the (C, N) vectors besides the sparse product: the updates of x and r, ``z = M^-1 r``, the dot
products ``r . z`` and ``|r|``, ``p = z + beta p``.  Here the same step is two passes:

1. :func:`update`: ``x += alpha p``, ``r += alpha q`` (q = -A p from the sparse product), and from the
   new r in the same pass its aggregate sums ``s = P_c^T r``, ``|r|^2`` and ``r . D^-1 r``;
2. then, after the coarse solve ``y = A_c^-1 s`` (a few hundred unknowns), ``r . z = r . D^-1 r + s . y``
   exactly (z = D^-1 r + P_c y), so z is never formed, and :func:`direction` writes
   ``p = beta p + D^-1 r + y[aggregate]`` in one pass.

The same arithmetic as the numpy step to rounding (the sums' order differs): ``tests/test_coarse_space.py``
holds the two iterations to each other.  Measured on the Final bunny's finest QuadGraph level (401,888
nodes, fp64, 2 cores, warm, tol 1e-4): 74 steps, 2.0-2.4 s in numpy against 1.15-1.28 s compiled
(176 Chebyshev sweeps in fp32: 1.75 s).  The sparse product is compiled too (:func:`link_product`, over
the graph's link slots as :class:`.sweeps.SweepOperator` keeps them), and it returns ``p . A p`` from the
same pass: 2.5-2.8 ms against 9.1 ms for scipy's block-diagonal CSR product, the zeroing of q and the
dot product (same level, 3 channels).  Why hand-written: scipy has no fused CG step and no product over
a fixed number of link slots shared by the channels.
Where numba is missing (macOS x86-64) or fails to compile, :func:`available` says why and
:func:`.iterative.cg_steps` runs its numpy step.
"""

from __future__ import annotations

import numpy as np

from ..compiled import load_kernels

_KERNEL = {}  # {"update": fn, "direction": fn, "nchunk": int, "first_call_s": float} or {"error": "why not"}


def available() -> str:
    """'' when the compiled step can run, else why not (numba missing, or its compile failed)."""
    _kernel()
    return _KERNEL.get("error", "")


def update(X, R, P, Q, alpha, inv_diag, agg, n_agg) -> tuple:
    """Pass 1 of a step (:mod:`.cg_kernels`): x, r updated in place; returns ``(P_c^T r, (|r|^2, r.D^-1 r))``,
    (C, n_agg) and (2, C).  X, R, P, Q, inv_diag: (C, N) C-contiguous fp64; agg (N,) int64."""
    k = _kernel()
    return k["update"](X, R, P, Q, np.ascontiguousarray(alpha, dtype=np.float64), inv_diag, agg, int(n_agg),
                       k["nchunk"])


def direction(P, R, inv_diag, y, agg, beta) -> None:
    """Pass 2: ``p = beta p + D^-1 r + y[agg]`` in place (y (C, n_agg): the coarse solution, or zeros)."""
    k = _kernel()
    k["direction"](P, R, inv_diag, np.ascontiguousarray(y, dtype=np.float64), agg,
                   np.ascontiguousarray(beta, dtype=np.float64), k["nchunk"])


def link_product(nbr, off, neg_diag, D, R, accumulate: bool, width) -> np.ndarray:
    """``r (+)= -A d`` over the graph's link slots (:func:`.cg_kernels.link_product`; row i's first ``width[i]``
    slots); returns ``d . (-A d)`` per channel.  Arrays as :class:`.sweeps.SweepOperator` keeps them (one
    dtype, C-contiguous)."""
    k = _kernel()
    return k["link_product"](nbr, off, neg_diag, D, R, bool(accumulate), width, k["nchunk"])


def to_channel_major(v, perm, dtype) -> np.ndarray:
    """``v`` (N, C) node-major -> (C, N) channel-major in the order ``perm``, as ``dtype``: one compiled pass
    (:func:`.cg_kernels.to_channel_major`); numpy's ``take`` of the transpose, the fallback, strides through v."""
    k = _kernel()
    v = np.ascontiguousarray(v)
    out = np.empty((v.shape[1], len(perm)), dtype=dtype)
    k["to_channel_major"](v, perm, out, k["nchunk"])
    return out


def from_channel_major(V, perm) -> np.ndarray:
    """(C, N) channel-major in the order ``perm`` -> (N, C) node-major fp64 (:func:`to_channel_major` undone)."""
    k = _kernel()
    out = np.empty((V.shape[1], V.shape[0]))
    k["from_channel_major"](np.ascontiguousarray(V), perm, out, k["nchunk"])
    return out


def permuted_slots(nbr, off, diag, perm, dtype) -> tuple:
    """``(links, off_cm, neg_diag, inv_diag, width)``: a level's link slots in the sweep order ``perm``,
    channel-major, in the sweep precision ``dtype`` (links int32 below 2^31 nodes), and each row's width (one
    past its last non-empty slot), from one compiled pass (:func:`.cg_kernels.permuted_slots`)."""
    k = _kernel()
    N, K = nbr.shape
    C = diag.shape[1]
    links = np.empty((N, K), dtype=np.int32 if N < 2**31 else np.int64)
    off_cm, neg_diag, inv_diag = np.empty((C, N, K), dtype=dtype), np.empty((C, N), dtype=dtype), np.empty(
        (C, N), dtype=dtype)
    width = np.empty(N, dtype=np.int32)
    k["permuted_slots"](np.ascontiguousarray(nbr), np.ascontiguousarray(off, dtype=np.float64),
                        np.ascontiguousarray(diag, dtype=np.float64), np.ascontiguousarray(perm, dtype=np.int64),
                        links, off_cm, neg_diag, inv_diag, width)
    return links, off_cm, neg_diag, inv_diag, width


def galerkin_pattern(links, agg, n_agg: int) -> np.ndarray:
    """The occupied pairs of ``P^T A P`` as marks over the n_agg^2 grid (:func:`.cg_kernels.aggregate_pairs`)."""
    k = _kernel()
    mark = np.zeros(n_agg * n_agg, dtype=bool)
    k["aggregate_pairs"](links, agg, int(n_agg), mark)
    return mark


def galerkin_sums(links, agg, n_agg: int, rank, off, neg_diag, n_occupied: int) -> np.ndarray:
    """(C0, n_occupied): ``P^T (-A) P`` of every base channel at its occupied pairs (``rank``: a pair's place
    among them), one pass over the link slots (:func:`.cg_kernels.aggregate_sums`)."""
    k = _kernel()
    out = np.empty((off.shape[0], n_occupied))
    k["aggregate_sums"](links, agg, int(n_agg), rank, off, neg_diag, out)
    return out


class CompiledStep:
    """:func:`.iterative.cg_steps`'s vector work in the two compiled passes (its numpy twin:
    :class:`.iterative.NumpyStep`, the same calls): the coarse space's aggregates (one aggregate whose
    coarse value stays 0 without one) and the coarse solution ``y`` kept between the two calls of a step."""

    def __init__(self, op, space):
        self.inv_diag = np.ascontiguousarray(op.inv_diag, dtype=np.float64)
        self.space = space
        if space is not None:
            self.agg, self.n_agg = np.ascontiguousarray(space.agg, dtype=np.int64), space.n_agg
        else:  # Jacobi alone
            self.agg, self.n_agg = np.zeros(op.n, dtype=np.int64), 1
        self.y = None

    def advance(self, X, R, P, Q, alpha) -> tuple:
        """Pass 1 and the coarse solve; returns ``(|r|^2, r . z)`` per channel, r . z = r . D^-1 r + s . y."""
        box, sums = update(X, R, P, Q, alpha, self.inv_diag, self.agg, self.n_agg)
        self.y = self.space.solve(box) if self.space is not None else np.zeros((len(R), 1))
        return sums[0], sums[1] + np.einsum("ca,ca->c", box, self.y)

    def direction(self, P, R, beta) -> None:
        """Pass 2: ``p = beta p + D^-1 r + y[aggregate]``."""
        direction(P, R, self.inv_diag, self.y, self.agg, beta)


def _kernel() -> dict:
    """The kernels, imported and run once on a tiny case (numba compiles them, or loads them from its cache);
    ``{"error": why}`` where that fails."""

    def load():
        import numba

        from . import cg_kernels as k

        nchunk = 4 * max(int(numba.get_num_threads()), 1)
        X, agg = np.zeros((1, 4)), np.zeros(4, dtype=np.int64)
        k.update(X, X.copy(), X.copy(), X.copy(), np.zeros(1), X.copy(), agg, 1, nchunk)
        k.direction(X, X.copy(), X.copy(), np.zeros((1, 1)), agg, np.zeros(1), nchunk)
        for dt in (np.float32, np.float64):  # both sweep precisions (sweeps.FP32_TOL)
            D = np.zeros((1, 4), dtype=dt)
            k.link_product(np.full((4, 1), -1, dtype=np.int32), np.zeros((1, 4, 1), dtype=dt), D[:1], D, D.copy(),
                           True, np.zeros(4, dtype=np.int32), nchunk)
        perm, v = np.arange(4), np.zeros((4, 3))
        for dt in (np.float32, np.float64):
            k.to_channel_major(v, perm, np.zeros((3, 4), dtype=dt), nchunk)
            k.from_channel_major(np.zeros((3, 4), dtype=dt), perm, v, nchunk)
        for dt in (np.float32, np.float64):  # the coarse space's Galerkin sums, over either sweep precision
            mark = np.zeros(1, dtype=bool)
            links1 = np.full((4, 1), -1, dtype=np.int32)
            k.aggregate_pairs(links1, agg, 1, mark)
            k.aggregate_sums(links1, agg, 1, np.zeros(1, dtype=np.int32), np.zeros((1, 4, 1), dtype=dt),
                             np.zeros((1, 4), dtype=dt), np.zeros((1, 1)))
            k.permuted_slots(np.zeros((4, 1), dtype=np.int32), np.zeros((4, 1, 1)), np.ones((4, 1)), np.arange(4),
                             np.empty((4, 1), dtype=np.int32), np.empty((1, 4, 1), dtype=dt), np.empty((1, 4), dtype=dt),
                             np.empty((1, 4), dtype=dt), np.empty(4, dtype=np.int32))
        return dict(update=k.update, direction=k.direction, link_product=k.link_product, nchunk=nchunk,
                    aggregate_pairs=k.aggregate_pairs, aggregate_sums=k.aggregate_sums,
                    permuted_slots=k.permuted_slots,
                    to_channel_major=k.to_channel_major, from_channel_major=k.from_channel_major)

    return load_kernels(_KERNEL, load, "the CG kernels")
