r"""A coarse space for the conjugate gradients: aggregates of nearby nodes and their Galerkin operator.

Jacobi-preconditioned CG (:func:`.iterative.cg_steps`) removes an error's short wavelengths in a few
steps and its long ones slowly: a fluid frame's warm start leaves both (every particle re-jittered), and
the long ones set the step count.  The two-level additive preconditioner

.. math::  M^{-1} = D^{-1} + P A_c^{-1} P^T, \qquad A_c = P^T A P

adds a coarse solve for them (Nicolaides 1987, *Deflation of conjugate gradients with applications to
boundary value problems*; the two-level additive Schwarz method of Toselli & Widlund 2005, ch. 2).  P
is piecewise constant on **aggregates**: the nodes that fall in one box of a grid laid over the graph's
node positions, one box per :data:`NODES_PER_AGGREGATE` nodes within
[:data:`MIN_AGGREGATES`, :data:`MAX_AGGREGATES`].  P has full column rank (no empty aggregate), so
A_c is symmetric positive definite when A is, and M^{-1} is too: CG stays CG.  A_c (a few hundred rows,
each box coupled to its 26 neighbours at most) is summed into its occupied entries and factored once per system and channel by
SuperLU (scipy); a step then costs per channel one restriction (a ``bincount``), one small sparse solve and
one gather.  Not LAPACK's dense Cholesky, though it is as fast here: at 128 rows and more it runs blocked on
OpenBLAS's threads, which then spin for a while after the call and took the cores from the next frame's
compiled (numba) cells, 37 -> 70-92 ms at 4k particles (measured; with OPENBLAS_NUM_THREADS=1 they did not).

Measured on a warm frame of ``bench/fluid.py`` (tol 1e-4, 2 cores, set-up included, one process, min of 9):
at 16k particles (19k nodes) 44 Jacobi CG steps, 68 ms, against 22 / 19 / 18 / 16 steps and
50 / 55 / 69 / 124 ms with grids of 128 / 256 / 512 / 1024 boxes (the ball fills about half of them); at 65k
particles 46 steps, 326 ms, against 29 / 25 / 22 / 20 steps and 272 / 251 / 239 / 266 ms.  Past a few hundred
aggregates the coarse factor costs more than the steps it saves, hence a box per 128 nodes, 128 to 512
boxes; under :data:`MIN_NODES` (a 4k-particle frame: 17 steps against 36, 13 ms against 11) not at all.  On a QuadGraph level (3-5 links per node, where :func:`.iterative.fast_steps` keeps Chebyshev) it
does not pay: the Preview bunny's finest level (42k nodes) warm 64 Chebyshev sweeps, 52 ms, against 42 CG
steps, 71 ms, and 31 with the coarse space (512 boxes), 82 ms; the Final bunny's (396k nodes) warm 160 sweeps,
1.9-2.0 s, against 95 CG steps, 2.3 s, and 52 / 46 / 43 with the coarse space (268 / 869 / 1,587
aggregates), 1.8 / 1.7 / 1.6 s.  A CG step there cost about three Chebyshev sweeps in numpy (fp64, and its
vector passes outweigh a sparse product of 4-5 links per row); with the step's vector work compiled
(:mod:`.compiled_cg`: two passes) the same level takes 74 steps in 1.07 s against 176 sweeps in 1.75 s, so
:func:`.iterative.prefers_cg` runs CG with this coarse space on QuadGraph levels (of 8,000 nodes and more since the
sparse product is compiled too), and
the bounce's block system block by block (:mod:`.interreflection`).  There the set-up is paid once per
material, not per frame, and with the sparse product compiled too (:mod:`.sweeps`) a step costs ~8 ms
against 0.06-0.5 ms for the coarse solve, so a level kept across frames gets finer boxes (one per
:data:`NODES_PER_AGGREGATE_KEPT` nodes, up to :data:`MAX_AGGREGATES_KEPT`): warm Final frame (sky turned
5 degrees, both blocks) with 267 / 478 / 872 / 1,258 / 1,587 / 2,309 aggregates 113 / 108 / 99 / 93 / 88 /
86 steps, 1.25-1.28 s with 267 against 1.03-1.09 s with 1,587 (set-up 208 against 242 ms, the coarse solve
0.06 against 0.5 ms a step for three channels); 2,309 cost more than they saved.  A fluid's graph, built
every frame (``built_per_frame``), keeps the rule above.  Why hand-written: the
well-kept alternative, PyAMG's smoothed aggregation, is not a dependency of the extension, and its set-up
per frame (a fluid's graph changes every frame) costs more than the steps it saves at these sizes (issue
33's measurements); this set-up is a few milliseconds.
"""

from __future__ import annotations

import numpy as np

from ..geometry.extent import bounds

NODES_PER_AGGREGATE = 128  # boxes aimed at: one per this many nodes (fewer where the graph fills its box partly),
MIN_AGGREGATES, MAX_AGGREGATES = 128, 512  # within these (see the module docstring for the measurements)
# a graph whose systems are kept from frame to frame (a bake's QuadGraph level: the set-up is paid once per
# material), not built anew each frame (a fluid's cells): finer boxes, up to more of them
NODES_PER_AGGREGATE_KEPT, MAX_AGGREGATES_KEPT = 64, 4096
MIN_NODES = 8000  # below this, Jacobi alone: the coarse solve costs about what it saves (4k particles)


def aggregates(position: np.ndarray, target: int) -> tuple[np.ndarray, int]:
    """``(agg, n_agg)``: each node's aggregate (its box in a grid of at most ``2 target`` cubic boxes over
    the positions' bounding box, about ``target`` where the graph fills it; empty boxes are not numbered)
    and how many there are.  A flat or thin graph gets bigger boxes (the grid's count, not the volume, is
    held to the target)."""
    X = np.asarray(position, dtype=np.float64)
    lo, hi = bounds(X)
    ext = hi - lo
    h = (float(np.prod(ext)) / max(target, 1)) ** (1.0 / 3.0)
    h = max(h, float(ext.max()) / max(target, 1), 1e-300)
    dims = np.floor(ext / h).astype(np.int64) + 1
    while np.prod(dims) > 2 * max(target, 1):  # a flat graph: its thin side holds one box, not h's share
        h *= 1.25
        dims = np.floor(ext / h).astype(np.int64) + 1
    g = np.minimum(np.floor((X - lo) / h).astype(np.int64), dims - 1)
    key = (g[:, 0] * dims[1] + g[:, 1]) * dims[2] + g[:, 2]
    used = np.zeros(int(np.prod(dims)), dtype=np.int64)
    used[key] = 1
    number = np.cumsum(used) - 1  # boxes in key order, empty ones skipped: no sort of the nodes
    return number[key], int(used.sum())


class CoarseSpace:
    """The coarse correction ``P A_c^{-1} P^T`` of one system, in a :class:`.sweeps.SweepOperator`'s
    layout (channel-major, its node order).  Build it with :func:`coarse_space`."""

    def __init__(self, agg: np.ndarray, n_agg: int, factors: list):
        self.agg = agg  # (N,) aggregate of each node, in the operator's order
        self.n_agg = n_agg
        self.factors = factors  # per channel A_c's sparse LU (scipy's SuperLU)

    def add_correction(self, R: np.ndarray, Z: np.ndarray) -> None:
        """``Z += P A_c^{-1} P^T R`` for channel-major R, Z (C, N)."""
        y = self.solve(np.stack([np.bincount(self.agg, r, self.n_agg) for r in R]))  # A_c^-1 P^T r
        Z += np.take(y, self.agg, axis=1)  # P y

    def solve(self, sums: np.ndarray) -> np.ndarray:
        """``A_c^{-1} s`` per channel for the aggregate sums ``s = P^T r`` (C, n_agg): the coarse solve of
        :meth:`add_correction` and of the compiled CG step (:mod:`.compiled_cg`)."""
        return np.stack([self.factors[c].solve(np.ascontiguousarray(s)) for c, s in enumerate(sums)])


def coarse_space(system, op) -> CoarseSpace | None:
    """The system's :class:`CoarseSpace` for the operator ``op`` (cached on the system), or None where the
    graph is too small for one to pay (:data:`MIN_NODES`), the graph has no node positions, or A_c is not
    numerically positive definite (then CG runs with Jacobi alone: the answer is the same, the steps more)."""
    cache = system.cache
    if "coarse_space" in cache:
        return cache["coarse_space"]
    space = None
    position = getattr(system.level, "position", None)
    if system.n >= MIN_NODES and position is not None and len(position) == system.n:
        if getattr(system.level, "built_per_frame", False):
            per, most = NODES_PER_AGGREGATE, MAX_AGGREGATES
        else:
            per, most = NODES_PER_AGGREGATE_KEPT, MAX_AGGREGATES_KEPT
        target = int(np.clip(system.n // per, MIN_AGGREGATES, most))
        agg, n_agg = aggregates(np.asarray(position)[op.perm], target)
        space = _galerkin(system, op, agg, n_agg)
    cache["coarse_space"] = space
    return space


def _galerkin(system, op, agg, n_agg) -> CoarseSpace | None:
    """A_c = P^T A P per channel, summed link slot by link slot into the occupied (aggregate, aggregate) pairs
    only, and its sparse LU (SuperLU: a box couples to its 26 neighbours at most).

    The pairs are found once for all channels (a mark per pair of the n_agg^2 grid, then their ranks), so a
    channel is one ``bincount`` into a few times n_agg entries and a CSR built from them, not a dense n_agg^2
    sum and its scan for non-zeros (the Final bunny's 1,587 aggregates: 2.5 M entries per channel).  Where
    the operator keeps the compiled sweeps' link slots (numba runs), the marks and every channel's sums are
    two compiled passes over the slots (:func:`.compiled_cg.galerkin_pattern`,
    :func:`.compiled_cg.galerkin_sums`) instead of numpy's masks and gathers over (N, K): at 16k particles
    (19k nodes, 23 slots) the whole set-up (aggregates, sums, three LUs) 18 -> 5.5 ms.  The same sums in
    another order: the same A_c to rounding (the test of the correction against P^T A P runs both)."""
    import scipy.sparse as sp
    from scipy.sparse.linalg import splu

    from .sweeps import sweep_links

    links = sweep_links(system)
    agg = np.ascontiguousarray(agg, dtype=np.int64)
    if op.links is not None:  # the compiled sweeps' layout: the pairs and every channel's sums in compiled passes
        from . import compiled_cg

        mark = compiled_cg.galerkin_pattern(links, agg, n_agg)
    else:
        valid = links >= 0
        rows = np.broadcast_to(agg[:, None], links.shape)[valid]
        pair = np.concatenate([rows * n_agg + np.take(agg, links[valid]),  # each occupied slot's (aggregate, aggregate)
                               agg * (n_agg + 1)])  # each node's diagonal
        mark = np.zeros(n_agg * n_agg, dtype=bool)
        mark[pair] = True
    occupied = np.flatnonzero(mark)  # ascending: row-major, so CSR order
    # each pair's rank among the occupied ones, written only where a pair is (a cumulative sum over all
    # n_agg^2 marks, 7.4 M on the Final sphere, cost 40 ms warm and 330 ms in a fresh process's first frame;
    # this, 19 and 67 ms)
    rank = np.empty(n_agg * n_agg, dtype=np.int32 if len(occupied) < 2**31 else np.int64)
    rank[occupied] = np.arange(len(occupied), dtype=rank.dtype)
    indptr = np.zeros(n_agg + 1, dtype=np.int64)
    np.cumsum(np.bincount(occupied // n_agg, minlength=n_agg), out=indptr[1:])
    cols = occupied % n_agg
    if op.links is not None:
        _, off_all, neg_diag_all = op.links
        sums = compiled_cg.galerkin_sums(links, agg, n_agg, rank, off_all, neg_diag_all, len(occupied))
        channel_sums = [sums[c % len(sums)] for c in range(op.C)]
    else:
        entry = rank[pair]
        channel_sums = []
        for c in range(op.C):
            off, neg_diag = op.slot_values(c)
            channel_sums.append(np.bincount(entry, np.concatenate([off[valid], neg_diag]), len(occupied)))
    factors = []
    for values in channel_sums:
        Ac = sp.csr_matrix((-values, cols, indptr), shape=(n_agg, n_agg)).tocsc()
        try:  # SuperLU's settings for a symmetric matrix: diagonal pivots, a symmetric ordering
            lu = splu(Ac, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options={"SymmetricMode": True})
        except RuntimeError:  # exactly singular
            return None
        u = lu.U.diagonal()
        if not (np.all(np.isfinite(u)) and np.all(u > 0)):  # not positive definite
            return None
        factors.append(lu)
    return CoarseSpace(agg, n_agg, factors)
