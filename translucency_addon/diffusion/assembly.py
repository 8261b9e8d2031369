r"""Assembly: one linear system per graph level from a material sampling (Wang et al. 2010 sec. 3-4).

Per colour channel the continuous problem is eq. 1 with the diffusive-source
boundary condition of eq. 2 (derived in :mod:`.diffusion`)::

    div(kappa grad phi) - mu phi = 0,     phi + 2 A kappa dphi/dn = 4 q / (1 - F_dr)

*Ours* (``scheme="fv"``, the default): the finite-volume form on any graph of
the contract (:mod:`.graph`)::

    sum_j T_ij (phi_i - phi_j) + mu_i V_i phi_i = 0,     T_ij = kappa_ij A_ij / d_ij
    T_sk (phi_s - phi_k) + a_s phi_s / (2A) = 2 a_s q_s / (1 + F_dr)

with ``kappa_ij`` the harmonic mean (two media in series); surface links use
the exponentially fitted flux (:func:`_fitted_link`).  A symmetric M-matrix.

*Paper* (``scheme="paper"``): eq. 5 with the neighbour's kappa inside the
sum, and eq. 6 at surface nodes (with eq. 9's ``1 + F_dr`` corrected).

The module docstring of :mod:`.diffusion` derives both and says why ours.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from . import kernels
from ..errors import MaterialError, TranslucencyError
from ..scene.fresnel import boundary_A, diffuse_reflectance_internal
from .graph import DiffusionGraph, check_graph
from ..scene.materials import Material, diffusion_coefficient

SCHEMES = ("fv", "paper")
COMPILED_ASSEMBLY_MIN_NODES = 4096  # from this many nodes the compiled links (:mod:`.assembly_kernels`) run


@dataclass
class LevelSystem:
    """One level's linear system in kernel form: diag_i x_i - sum_j off_ij x_j = b_i.

    ``b`` is ``b_scale * q`` at surface nodes and zero at inner nodes, or a volume source there (:meth:`rhs`).
    """

    scheme: str
    level: DiffusionGraph
    nbr: np.ndarray  # (N, K) int32, K link slots (4 on the QuadGraph)
    off: np.ndarray  # (N, K, 3)
    diag: np.ndarray  # (N, 3)
    b_scale: np.ndarray  # (n_surface, 3)
    sigma_a: np.ndarray  # (N, 3) per mm (for power accounting)
    mm_per_unit: float
    boundary_diag: np.ndarray | None = None  # (n_surface, 3) a_s/(2A), the boundary exchange term
    lam_max: np.ndarray | None = None  # (3,) upper bound of eig(D^-1 A)
    lam_min: np.ndarray | None = None  # (3,) estimate of the smallest eigenvalue
    # What is derived from the system once and reused, owned here: "off_csr" (the off-diagonal part per
    # channel, :meth:`apply`), "sweep_ops" (:meth:`sweep_operator` per dtype), "subsets" (:meth:`subset`),
    # "rcm" and "sweep_pattern" (``sweeps``, the graph's, shared by channel subsets), "deflation"
    # (``spectral.deflation``), "absorption_w" (:meth:`absorption_weights`), "links_per_node"
    # (``iterative.links_per_node``: which iteration the default solve runs).
    cache: dict = field(default_factory=dict, compare=False, repr=False)

    @property
    def n(self) -> int:
        return self.level.n_nodes

    def apply(self, x: np.ndarray) -> np.ndarray:
        """A x, with scipy CSR products for the off-diagonal part (CPU fast path).

        Same operation as ``kernels.apply_matrix`` on the packed layout (a
        test checks they agree to rounding); CSR is ~3x faster in numpy.  Where the fp64 sweeps' operator
        is built already (the CG solve's, :func:`.iterative.cg_steps`) it is that product, so a system
        solved once (a fluid's frame) never builds the per-channel CSR as well.
        """
        op = self.cache.get("sweep_ops", {}).get(np.dtype(np.float64).str)
        if "off_csr" not in self.cache and op is not None and x.shape[1] == op.C:  # the fp64 sweeps' layout
            r = np.zeros((op.C, op.n))
            op.sub_a(r, op.to_cm(x))
            return -op.from_cm(r)
        csr = self.off_csr()
        out = self.diag * x
        for c in range(x.shape[1]):
            out[:, c] -= csr[c] @ x[:, c]
        return out

    def off_csr(self) -> list:
        """The off-diagonal part per channel as scipy CSR matrices (``sum_j off_ij x_j``), cached."""
        csr = self.cache.get("off_csr")
        if csr is None:
            from scipy.sparse import csr_matrix

            n = self.n
            rows = np.repeat(np.arange(n), self.nbr.shape[1])
            cols = self.nbr.ravel().astype(np.int64)
            m = cols >= 0
            csr = [csr_matrix((self.off[:, :, c].ravel()[m], (rows[m], cols[m])), shape=(n, n))
                   for c in range(self.off.shape[2])]
            self.cache["off_csr"] = csr
        return csr

    def sweep_operator(self, dtype=np.float64):
        """The level laid out for fast CPU Chebyshev sweeps (:class:`.sweeps.SweepOperator`), cached per dtype."""
        ops = self.cache.setdefault("sweep_ops", {})
        key = np.dtype(dtype).str
        if key not in ops:
            from .sweeps import SweepOperator

            ops[key] = SweepOperator(self, dtype=dtype)
        return ops[key]

    def subset(self, cols: tuple) -> "LevelSystem":
        """The same system restricted to some colour channels (the planner skips the others)."""
        cols = tuple(int(c) for c in cols)
        if cols == (0, 1, 2):
            return self
        cache = self.cache.setdefault("subsets", {})
        if cols not in cache:
            off_csr = self.off_csr()
            idx = list(cols)
            sub = LevelSystem(scheme=self.scheme, level=self.level, nbr=self.nbr, off=self.off[:, :, idx],
                              diag=self.diag[:, idx], b_scale=self.b_scale[:, idx], sigma_a=self.sigma_a[:, idx],
                              mm_per_unit=self.mm_per_unit,
                              boundary_diag=None if self.boundary_diag is None else self.boundary_diag[:, idx])
            sub.cache["off_csr"] = [off_csr[c] for c in idx]
            for k in ("rcm", "sweep_links", "sweep_pattern"):  # the graph's, shared by every channel subset
                if k in self.cache:
                    sub.cache[k] = self.cache[k]
            if self.lam_max is not None:
                sub.lam_max, sub.lam_min = self.lam_max[idx], self.lam_min[idx]
            cache[cols] = sub
        return cache[cols]

    def absorption_weights(self) -> np.ndarray:
        """Per-node weights w with absorbed power = sum w phi (mm^2; FV scheme only).

        For the symmetric FV matrix, 1^T A phi = (A 1)^T phi; removing the
        boundary exchange term a_s/(2A) leaves what the operator absorbs.  In this system's channels (a
        subset may hold fewer than 3); computed once and kept in ``cache["absorption_w"]`` (read-only).
        """
        if self.scheme != "fv":
            raise TranslucencyError("power accounting is defined for the conservative scheme only")
        w = self.cache.get("absorption_w")
        if w is None:
            w = self.apply(np.ones((self.n, self.diag.shape[1])))
            w[self.level.n_inner:] -= self.boundary_diag
            self.cache["absorption_w"] = w
        return w

    def rhs(self, q: np.ndarray, volume: np.ndarray | None = None, out: np.ndarray | None = None) -> np.ndarray:
        """b: ``b_scale q`` at the surface nodes, and ``volume`` (n_inner, C) -- a volume source's power in
        each inner node's cell (``diffusion.beam_source``) -- or zero at the inner nodes; written into
        ``out`` (n, C) where given (a block of a larger system's right-hand side)."""
        b = np.empty((self.n, self.diag.shape[1])) if out is None else out
        ni = self.level.n_inner
        b[ni:] = self.b_scale * q
        if volume is not None:
            b[:ni] = volume
        else:
            b[:ni] = 0.0
        return b



def node_coefficients(material: Material, field_values, n: int):
    """(sigma_a, sigma_s') at n nodes (per mm), checked for NaN and negatives."""
    sa, ss = material.coefficients(field_values, n=n)
    if sa.shape != (n, 3):
        raise MaterialError(f"expected coefficients for {n} nodes, got {sa.shape}")
    if not (np.all(np.isfinite(sa)) and np.all(np.isfinite(ss))):
        raise MaterialError("material coefficients at the nodes contain NaN or Inf")
    if np.any(sa < 0) or np.any(ss < 0) or np.any(sa + ss <= 0):
        raise MaterialError("material coefficients at the nodes are negative or zero")
    return sa, ss


def assemble(level: DiffusionGraph, sigma_a: np.ndarray, sigma_s: np.ndarray, eta: float,
             mm_per_unit: float, scheme: str = "fv", compiled: bool | None = None) -> LevelSystem:
    """Build the level's system for one material sampling (see module docstring).

    ``level`` is any graph of the contract (:func:`.graph.check_graph`).  ``compiled``: the conservative
    scheme's links in one compiled pass (:mod:`.assembly_kernels`, numba) instead of numpy's; ``None`` (auto)
    takes it from :data:`COMPILED_ASSEMBLY_MIN_NODES` nodes where numba runs.  Both give the same system to
    rounding.
    """
    if scheme not in SCHEMES:
        raise TranslucencyError(f"unknown scheme {scheme!r}")
    check_graph(level, "graph level")
    s = float(mm_per_unit)
    kappa = diffusion_coefficient(sigma_a, sigma_s)  # (N, 3) mm
    mu = sigma_a
    A = boundary_A(eta)
    fdr = diffuse_reflectance_internal(eta)
    nI = level.n_inner
    if scheme == "fv":
        if compiled is None:
            compiled = level.n_nodes >= COMPILED_ASSEMBLY_MIN_NODES and not available()
        off, diag = (_compiled_fv if compiled else _numpy_fv)(level, kappa, mu, s)
        a_s = (level.area * s * s)[:, None]
        boundary_diag = np.broadcast_to(a_s / (2.0 * A), (level.n_surface, 3)).copy()
        diag[nI:] += boundary_diag
        b_scale = np.broadcast_to(2.0 * a_s / (1.0 + fdr), (level.n_surface, 3)).copy()
    else:
        nbr = level.neighbors.astype(np.int64)
        has = nbr >= 0
        d = level.edge_length * s  # mm
        k_nb = kernels.gather(nbr, kappa)  # (N, K, 3)
        inv_d2 = np.where(has, 1.0 / np.where(has, d, 1.0) ** 2, 0.0)
        off = np.zeros((level.n_nodes, nbr.shape[1], 3))
        off[:nI] = k_nb[:nI] * inv_d2[:nI, :, None]  # kappa(n_j) / d_ij^2 (eq. 5)
        diag = np.zeros((level.n_nodes, 3))
        w = inv_d2[:nI].sum(axis=1)
        diag[:nI] = w[:, None] * kappa[:nI] + mu[:nI]
        dsk = d[nI:, 0][:, None]
        ks = kappa[nI:]
        off[nI:, 0] = 2.0 * A * ks  # eq. 6 / 9: 2 A kappa(n_s) phi(n_k)
        diag[nI:] = 2.0 * A * ks + dsk
        b_scale = 4.0 * dsk / (1.0 - fdr) * np.ones((1, 3))  # d_sk 4 q / (1 - F_dr), corrected
        boundary_diag = None
    return LevelSystem(scheme=scheme, level=level, nbr=level.neighbors.astype(np.int32), off=off, diag=diag,
                       b_scale=b_scale, sigma_a=sigma_a, mm_per_unit=s, boundary_diag=boundary_diag)


def available() -> str:
    """'' when the compiled assembly (:mod:`.assembly_kernels`) can run, else why not (numba missing, or its
    compile failed)."""
    return _kernel().get("error", "")


def _numpy_fv(level: DiffusionGraph, kappa: np.ndarray, mu: np.ndarray, s: float):
    """``(off, diag)`` of the conservative scheme, the surface links fitted, before the boundary exchange term,
    in numpy (the twin of :func:`_compiled_fv`)."""
    nI = level.n_inner
    nbr = level.neighbors.astype(np.int64)
    has = nbr >= 0
    d = level.edge_length * s  # mm
    # the face's kappa, the harmonic mean 2 k_i k_j / (k_i + k_j) = 2 / (1/k_i + 1/k_j): one gather of
    # 1/kappa (inf where a slot has no neighbour, so kf = 0 there) and two passes over (N, K, C)
    inv = 1.0 / kappa
    kf = np.take(np.concatenate([inv, np.full((1, inv.shape[1]), np.inf)]), nbr, axis=0)
    kf += inv[:, None, :]
    np.divide(2.0, kf, out=kf)
    # Link length d_ij, not the face-normal distance: on the sphere test
    # the normal distance lowers node-to-node scatter slightly but biases
    # the mean, which then stops converging under refinement.
    G = np.where(has, level.face_area * s * s / np.where(has, d, 1.0), 0.0)  # mm
    off = kf * G[..., None]
    diag = np.einsum("nkc->nc", off)  # = off.sum(axis=1), ~5x faster over the middle axis (numpy 2.3)
    diag[:nI] += mu[:nI] * (level.volume * s**3)[:, None]
    # Surface links: exponentially fitted flux at the surface end (module docstring).
    si = np.arange(nI, level.n_nodes)
    k_in = nbr[nI:, 0]
    slot = np.argmax(nbr[k_in] == si[:, None], axis=1)  # which of the inner node's links points back
    kf_s = kf[nI:, 0]  # face kappa of the link
    mu_s = 0.5 * (mu[nI:] + mu[k_in])
    x = np.sqrt(mu_s / kf_s) * d[nI:, 0][:, None]  # sigma_tr d
    T0 = G[nI:, 0][:, None] * kf_s
    T, C = _fitted_link(T0, x)
    off[nI:, 0] = T
    off[k_in, slot] = T
    diag[nI:] += C - T0  # surface row: C phi_s - T phi_k
    diag[k_in] += T - T0  # inner row: plain coupling T
    # The link's absorption (C - T) overlaps the cell's: remove its leading
    # order (mu a d / 2) from the cell, never more than half the cell's.
    lead = 0.5 * mu_s * (level.face_area[nI:, 0] * s * s * d[nI:, 0])[:, None]
    cell = mu[k_in] * (level.volume[k_in] * s**3)[:, None]
    np.subtract.at(diag, k_in, np.minimum(np.minimum(C - T, lead), 0.5 * cell))
    return off, diag


def _compiled_fv(level: DiffusionGraph, kappa: np.ndarray, mu: np.ndarray, s: float):
    """``(off, diag)`` of the conservative scheme, the surface links fitted, before the boundary exchange term:
    :func:`.assembly_kernels.fv_links` then :func:`.assembly_kernels.fv_surface_links`, the same arithmetic as
    :func:`_numpy_fv`'s lines.  Why hand-written: numpy makes some ten passes over (N, K, C) temporaries
    for what is one pass over the link slots (19k fluid cells, 23 slots: 20 ms against ~2)."""
    k = _kernel()
    if "error" in k:
        raise RuntimeError(f"the compiled assembly is not available: {k['error']}")
    nbr = np.ascontiguousarray(level.neighbors)
    N, K = nbr.shape
    C = kappa.shape[1]
    args = (nbr, np.ascontiguousarray(1.0 / kappa), np.ascontiguousarray(mu, dtype=np.float64),
            np.ascontiguousarray(level.face_area, dtype=np.float64),
            np.ascontiguousarray(level.edge_length, dtype=np.float64),
            np.ascontiguousarray(level.volume, dtype=np.float64), float(s), int(level.n_inner))
    off, diag = np.empty((N, K, C)), np.empty((N, C))
    k["fv_links"](*args, off, diag)
    k["fv_surface_links"](*args, off, diag)
    return off, diag


_KERNEL = {}  # {"fv_links": fn, "fv_surface_links": fn, "first_call_s": float} or {"error": "why not"}


def _kernel() -> dict:
    def load():
        from . import assembly_kernels as m

        for it in (np.int32, np.int64):  # a QuadGraph's neighbours are int32, others' may be int64
            nbr = np.array([[1], [0]], dtype=it)
            args = (nbr, np.ones((2, 3)), np.ones((2, 3)), np.ones((2, 1)), np.ones((2, 1)), np.ones(1), 1.0, 1)
            off, diag = np.empty((2, 1, 3)), np.empty((2, 3))
            m.fv_links(*args, off, diag)
            m.fv_surface_links(*args, off, diag)
        return {"fv_links": m.fv_links, "fv_surface_links": m.fv_surface_links}

    from ..compiled import load_kernels

    return load_kernels(_KERNEL, load, "the assembly's kernel")


def _fitted_link(T0: np.ndarray, x: np.ndarray):
    """Exponentially fitted link coefficients for a link of optical length x = sigma_tr d.

    Solving kappa phi'' = mu phi exactly between the two nodes gives the
    fluxes ``T0 x / sinh(x) (phi_a cosh(x) - phi_b)`` at either end, i.e. an
    off-diagonal ``T = T0 x / sinh x`` and a diagonal ``C = T0 x coth x`` per
    end; ``C - T`` is the absorption inside the link.  ``T0 = kappa A / d``
    is the plain two-point coefficient, recovered as x -> 0.
    """
    x = np.maximum(x, 1e-8)
    small = x < 1e-3
    xs = np.where(small, 1.0, x)
    with np.errstate(over="ignore"):
        T = np.where(small, T0 * (1.0 - x * x / 6.0), T0 * xs / np.sinh(np.minimum(xs, 700.0)))
        C = np.where(small, T0 * (1.0 + x * x / 3.0), T0 * xs / np.tanh(xs))
    T = np.where(x > 700.0, 0.0, T)
    return T, C



def sparse_matrix(system: LevelSystem, channel: int):
    """The system as a scipy CSR matrix for one channel."""
    from scipy.sparse import csr_matrix

    n = system.n
    rows = np.repeat(np.arange(n), system.nbr.shape[1])
    cols = system.nbr.ravel().astype(np.int64)
    vals = -system.off[:, :, channel].ravel()
    m = cols >= 0
    A = csr_matrix((vals[m], (rows[m], cols[m])), shape=(n, n))
    A = A + csr_matrix((system.diag[:, channel], (np.arange(n), np.arange(n))), shape=(n, n))
    return A.tocsr()

