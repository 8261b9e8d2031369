# SPDX-License-Identifier: GPL-3.0-or-later
"""Cheap CPU sweeps for the Chebyshev iteration: the layout one level's system is swept in.

A Chebyshev step (:func:`.iterative.solve_chebyshev`) is ``x += d``,
``r -= A d``, ``d = c_d d + c_r D^-1 r``: one sparse product and a few
vector updates, all bound by memory traffic.  The (N, 3) node-major layout
of :class:`.assembly.LevelSystem` costs three strided CSR products per step
plus a temporary for every term.  Here the level is laid out once so that a
step touches each array as few times as possible:

* **channel-major** vectors ``(C, N)``, and ``r -= A d`` one call for all channels: where numba runs,
  one compiled pass over the graph's link slots (:func:`.cg_kernels.link_product`: a node's neighbours
  read once for the three channels, both cores; 2.5-2.8 ms against 8.2-8.7 ms on the Final bunny's
  finest level); elsewhere ``-A`` (diagonal included) as one block-diagonal CSR over the channels and
  scipy's compiled CSR kernel, which *accumulates* into ``r`` in place
  (``scipy.sparse._sparsetools.csr_matvec``: the kernel behind ``csr @ x``;
  the public product would allocate ``A d`` and subtract it: two more passes);
* **reverse Cuthill-McKee order** (``scipy.sparse.csgraph``): the tetrahedral
  graph's nodes come in fTetWild's order, where a link spans on average
  ~13,000 rows of the Final bunny; RCM brings that to ~2,000, so the gathered
  ``d[j]`` mostly hit cache (the product alone 1.9x faster, measured on the
  Final bunny, 388k nodes);
* the remaining updates in place (``out=``), no temporaries beyond one buffer;
* **fp32** where the tolerance allows (:data:`FP32_TOL`): the sweeps stream
  half the bytes; the solution is then checked, and the iteration restarted
  if needed, against the fp64 residual ``b - A x`` (mixed-precision iterative
  refinement), so the tolerance a solve reports is always the fp64 one.  At 1e-5 fp32 was
  not enough: on tests/hard_cases' sliver graph (cell diagonals over many decades) its
  rounding moved single vertices by 1.7e-4 of the peak, above the GPU comparison's 1.3e-4.

The arithmetic is the same as the node-major loop's (a test holds them equal
to rounding); only the order of the sums changes.  Hand-written because no
library offers a fused Chebyshev step or a product over link slots shared by the channels.
"""

from __future__ import annotations

import weakref

import numpy as np
import scipy.sparse as sp

try:  # the compiled kernel of ``csr @ x``, which accumulates y += A x in place
    from scipy.sparse._sparsetools import csr_matvec as _csr_matvec
except ImportError:  # pragma: no cover - a scipy that moved it: the public product (one more pass)
    _csr_matvec = None

COMPILED_PERM_MIN_NODES = 4096  # to_cm / from_cm compiled from this many nodes (a call into numba costs microseconds)


def rcm_order(system) -> np.ndarray:
    """Reverse Cuthill-McKee order of a level's graph (new position -> old node), cached on the system.

    Inner nodes first, then surface nodes, so the surface is the slice ``[n_inner:]`` in this order too.
    A bake's level carries it (``GraphLevel.sweep_order``, :func:`rcm_permutation` at bake time, kept in the
    cache): a farm's cold frame then pays no RCM (0.1-0.3 s on the Final bunny's three levels).
    """
    perm = system.cache.get("rcm")
    if perm is None and getattr(system.level, "local_order", False):
        # a graph already numbered in a spatial order, inner nodes first (a fluid frame's cells): RCM would
        # only cost its time (~10 ms a frame at 16k cells) for the same locality
        perm = system.cache["rcm"] = np.arange(system.n, dtype=np.int64)
    if perm is None:
        kept = getattr(system.level, "sweep_order", None)
        if kept is not None and len(kept) == system.n:
            perm = np.asarray(kept, dtype=np.int64)
        else:
            perm = rcm_permutation(system.nbr, system.level.n_inner)
        system.cache["rcm"] = perm
    return perm


def rcm_permutation(neighbors: np.ndarray, n_inner: int) -> np.ndarray:
    """Reverse Cuthill-McKee order (scipy's) of the graph whose link slots are ``neighbors`` (N, K), -1 empty:
    new position -> old node, inner nodes ``< n_inner`` first, then the surface nodes, each group in RCM order
    (the boundary couplings, the interreflection bounce, then act on one contiguous slice)."""
    from scipy.sparse.csgraph import reverse_cuthill_mckee

    nbr = np.asarray(neighbors, dtype=np.int64)
    n = len(nbr)
    rows = np.repeat(np.arange(n), nbr.shape[1])
    cols = nbr.ravel()
    m = cols >= 0
    g = sp.csr_matrix((np.ones(int(m.sum())), (rows[m], cols[m])), shape=(n, n))
    perm = np.asarray(reverse_cuthill_mckee((g + g.T).tocsr(), symmetric_mode=True), dtype=np.int64)
    return np.concatenate([perm[perm < n_inner], perm[perm >= n_inner]])


def check_sweep_order(order: np.ndarray, n_nodes: int, n_inner: int) -> str:
    """Why ``order`` is not a sweep order of a level of ``n_nodes`` nodes (a permutation, inner nodes first),
    or "" when it is."""
    o = np.asarray(order)
    if o.shape != (n_nodes,) or o.dtype.kind not in "iu":
        return f"has shape {o.shape} and type {o.dtype}, not ({n_nodes},) integers"
    if n_nodes and (o.min() < 0 or o.max() >= n_nodes or np.bincount(o, minlength=n_nodes).max() != 1):
        return "is not a permutation of the level's nodes"
    if n_inner and o[:n_inner].max() >= n_inner:
        return "does not put the inner nodes first"
    return ""


FP32_TOL = 5e-5  # at or above this relative residual the sweeps run in fp32 (the add-on default 1e-4); below, fp64


def sweep_pattern(system):
    """The sparsity pattern of ``-A`` for one channel in RCM order, cached on the system.

    ``(indptr, indices, src)``: CSR rows in sweep order (each row's link slots, then its diagonal) and, for every
    entry, its place in ``[off[:, :, c].ravel(), diag[:, c]]`` -- so a channel's values are one
    gather, and the block-diagonal operator over channels and copies is these arrays repeated with
    offsets: no COO -> CSR conversion (sort and duplicate sum over 2-4 x 10^7 entries) per operator.
    Duplicate links (two slots naming the same neighbour) stay separate entries, which the product
    sums as the COO conversion did.
    """
    pat = system.cache.get("sweep_pattern")
    if pat is None:
        n = system.n
        links = sweep_links(system)
        K = links.shape[1]
        # row r of the sweep order is node perm[r]: its K link slots, then its diagonal, taken in that
        # order -- the rows come out grouped without a sort (their columns are not sorted; the
        # product does not need them to be)
        idx_t = np.int32 if n * (K + 1) < 2**31 else np.int64
        cols = np.empty((n, K + 1), dtype=idx_t)
        cols[:, :K] = links
        cols[:, K] = np.arange(n, dtype=idx_t)
        src = np.arange(n * (K + 1), dtype=idx_t).reshape(n, K + 1)
        src -= np.arange(n, dtype=idx_t)[:, None]  # slot k of node i: i K + k
        src[:, K] = n * K + np.arange(n, dtype=idx_t)  # its diagonal: n K + i
        perm = rcm_order(system)
        if not _identity(perm):
            src = np.take(src, perm, axis=0)
        m = cols >= 0
        indptr = np.zeros(n + 1, dtype=np.int64)
        np.cumsum(np.count_nonzero(m, axis=1), out=indptr[1:])
        pat = (indptr, cols[m], src[m])
        system.cache["sweep_pattern"] = pat
    return pat


def sweep_links(system) -> np.ndarray:
    """The graph's link slots in sweep order, (N, K): row r holds the sweep positions of node ``perm[r]``'s
    neighbours (-1: an empty slot); int32 below 2^31 nodes.  Cached on the system."""
    links = system.cache.get("sweep_links")
    if links is None:
        perm = rcm_order(system)
        nbr = np.asarray(system.nbr)
        idx_t = np.int32 if system.n < 2**31 else np.int64
        if _identity(perm):  # a graph in spatial order already (a fluid frame): no gathers
            links = np.ascontiguousarray(nbr, dtype=idx_t)
        else:  # np.take: several times faster than fancy indexing on (N, K)
            inv = np.empty_like(perm)
            inv[perm] = np.arange(len(perm))
            links = np.where(nbr >= 0, np.take(inv, np.maximum(nbr, 0)), -1).astype(idx_t)
            links = np.take(links, perm, axis=0)
        system.cache["sweep_links"] = links
    return links


def _identity(perm) -> bool:
    return bool(len(perm) == 0 or (perm[0] == 0 and perm[-1] == len(perm) - 1 and (np.diff(perm) == 1).all()))


class SweepOperator:
    """``-A`` of one level (C channels) in RCM order, applied to channel-major ``(C, N)`` vectors.

    Where numba runs (:mod:`.compiled_cg`) it keeps the graph's link slots -- ``nbr`` (N, K) in sweep
    order, ``off`` (C0, N, K) and ``-diag`` (C0, N) per base channel -- and ``r -= A d`` is one compiled
    pass over them for all channels (:func:`.cg_kernels.link_product`: a node's neighbours read once for
    the three channels, both cores).  Measured on the Final bunny's finest level (401,888 nodes, 3
    channels, fp64, 2 cores): 2.5-2.8 ms against 8.2-8.7 ms for scipy's block-diagonal CSR product.
    Elsewhere it is that CSR (:attr:`neg_a`, built on first use on either path).
    """

    def __init__(self, system, copies: int = 1, dtype=np.float64):
        from . import compiled_cg

        self.dtype = np.dtype(dtype)
        self.perm = rcm_order(system)
        n, C = system.n, system.diag.shape[1]
        self.n, self.C, self.copies = n, C * copies, copies
        self._system = weakref.ref(system)  # for the CSR built on first use; no cycle through system.cache
        self._neg_a = None
        self.links = None
        if not compiled_cg.available():  # the slots, reordered and channel-major, in one compiled pass (the Final
            # bunny's first frame: its three operators 357 -> ~100 ms, the first touch of their pages included)
            links, off_cm, neg_diag, inv_diag, self.width = compiled_cg.permuted_slots(
                system.nbr, system.off, system.diag, self.perm, self.dtype)
            links = system.cache.setdefault("sweep_links", links)  # the graph's, shared with the coarse space
            self.links = (links, off_cm, neg_diag)
            self.inv_diag = inv_diag if copies == 1 else np.ascontiguousarray(np.tile(inv_diag, (copies, 1)))
            return
        in_order = _identity(self.perm)  # a graph in spatial order already (a fluid frame): no gathers
        diag = np.asarray(system.diag) if in_order else np.take(system.diag, self.perm, axis=0)
        self._neg_a = self._block_csr()
        self.inv_diag = np.ascontiguousarray(np.tile(1.0 / diag.T, (copies, 1)), dtype=self.dtype)

    @property
    def neg_a(self) -> sp.csr_matrix:
        """``-A`` as one channel-major block-diagonal CSR (copies included); built on first use where the
        compiled product runs (diagnostics and benchmarks ask for it)."""
        if self._neg_a is None:
            self._neg_a = self._block_csr()
        return self._neg_a

    def _block_csr(self) -> sp.csr_matrix:
        """The one-channel pattern (:func:`sweep_pattern`, built once per system) repeated per block, with
        offsets: no COO -> CSR conversion."""
        system, n, blocks = self._system(), self.n, self.C
        C = system.diag.shape[1]
        indptr, indices, src = sweep_pattern(system)
        nnz = len(indices)
        idx_t = np.int32 if max(n * blocks, nnz * blocks) < 2**31 else np.int64
        flat = np.empty((C, len(system.off) * system.off.shape[1] + n), dtype=self.dtype)
        flat[:, :-n] = system.off.reshape(-1, C).T  # channel-major [off, -diag]: one gather for all channels
        np.negative(system.diag.T, out=flat[:, -n:])
        data = np.take(flat, src, axis=1).reshape(-1)
        if self.copies > 1:
            data = np.tile(data, self.copies)
        ind = np.empty(nnz * blocks, dtype=idx_t)
        ptr = np.empty(n * blocks + 1, dtype=idx_t)
        for b in range(blocks):
            np.add(indices, b * n, out=ind[b * nnz:(b + 1) * nnz], casting="unsafe")
            np.add(indptr[:-1], b * nnz, out=ptr[b * n:(b + 1) * n], casting="unsafe")
        ptr[-1] = nnz * blocks
        return sp.csr_matrix((data, ind, ptr), shape=(n * blocks, n * blocks), copy=False)

    def slot_values(self, c: int) -> tuple:
        """``-A`` of channel ``c`` by link slot in sweep order: ``(off (N, K), -diag (N,))``, with
        :func:`sweep_links` naming each slot's neighbour (the coarse space's Galerkin sums read these)."""
        if self.links is not None:
            _, off, neg_diag = self.links
            b = c % off.shape[0]
            return off[b], neg_diag[b]
        system = self._system()
        b = c % system.diag.shape[1]
        return np.take(system.off[:, :, b], self.perm, axis=0), -np.take(system.diag[:, b], self.perm)

    @property
    def nbytes(self) -> int:
        """Bytes of the operator's arrays (the CSR's where it was built, the link slots', the inverse diagonal)."""
        arrays = [self.inv_diag] + ([] if self.links is None else list(self.links))
        if self._neg_a is not None:
            arrays += [self._neg_a.data, self._neg_a.indices, self._neg_a.indptr]
        return sum(a.nbytes for a in arrays)

    def to_cm(self, v: np.ndarray, dtype=None) -> np.ndarray:
        """(N, C) node-major -> (C, N) channel-major, RCM order (a copy), in the sweep precision."""
        # one gather along the rows of v's transpose (2.4x faster at 800k nodes than gathering v's rows and
        # transposing the copy); compiled, one pass over v's rows (the Final bunny's bounce system, 800k
        # nodes: 2 against 16 ms, six times a warm frame)
        v = np.asarray(v)
        if v.ndim == 2 and self._perm_compiled():
            from .compiled_cg import to_channel_major

            return to_channel_major(v, self.perm, dtype or self.dtype)
        out = np.take(v.T, self.perm, axis=1)
        return out if out.dtype == np.dtype(dtype or self.dtype) else out.astype(dtype or self.dtype)

    def from_cm(self, v: np.ndarray) -> np.ndarray:
        """(C, N) channel-major in the operator's order -> (N, C) node-major fp64 (:meth:`to_cm` undone)."""
        if self._perm_compiled():
            from .compiled_cg import from_channel_major

            return from_channel_major(v, self.perm)
        out = np.empty((self.n, v.shape[0]))
        out[self.perm] = v.T
        return out

    def _perm_compiled(self) -> bool:
        """Whether :meth:`to_cm` and :meth:`from_cm` run compiled: where numba runs, on graphs big enough for
        it to pay (a call into numba costs some microseconds)."""
        from . import compiled_cg

        return self.n >= COMPILED_PERM_MIN_NODES and not compiled_cg.available()

    def sub_a(self, r: np.ndarray, d: np.ndarray) -> None:
        """``r -= A d`` in place; r, d (C, N) C-contiguous, in the sweep precision."""
        if self._compiled():
            from .compiled_cg import link_product

            link_product(*self.links, d, r, True, self.width)
            return
        m = self.neg_a
        if _csr_matvec is not None:
            _csr_matvec(m.shape[0], m.shape[1], m.indptr, m.indices, m.data, d.reshape(-1), r.reshape(-1))
        else:  # pragma: no cover
            r += (m @ d.reshape(-1)).reshape(r.shape)

    def _compiled(self) -> bool:
        """Whether the link slots are kept and the compiled product runs (else the CSR)."""
        from . import compiled_cg

        return self.links is not None and not compiled_cg.available()

    def product(self, d: np.ndarray, out: np.ndarray) -> np.ndarray:
        """``out = -A d`` (overwritten) and ``d . A d`` per channel, (C,): CG's product and its curvature in
        one pass where the link slots are kept (no zeroing pass, no dot-product pass)."""
        if self._compiled() and type(self).sub_a is SweepOperator.sub_a:
            from .compiled_cg import link_product

            return -link_product(*self.links, d, out, False, self.width)
        out.fill(0.0)
        self.sub_a(out, d)
        return -np.einsum("cn,cn->c", d, out)
