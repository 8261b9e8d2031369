r"""The diffusion equation on the QuadGraph (Wang et al. 2010, sec. 3 and 4.2-4.3).

Continuous problem (eq. 1 and 2), per colour channel::

    div(kappa grad phi) - mu phi = 0                      in the object
    phi + 2 A kappa dphi/dn = 4 q / (1 - F_dr)            on the boundary

with ``kappa = 1/(3 (sigma_a + sigma_s'))``, ``mu = sigma_a``,
``A = (1 + F_dr)/(1 - F_dr)`` and q the diffused incoming light of eq. 3.

Boundary condition and outgoing radiance, derived
-------------------------------------------------
Near the boundary the diffusion radiance is ``L(w) = phi/(4 pi) + 3/(4 pi) E.w``
with Fick's law ``E = -kappa grad phi``.  Integrating over the hemispheres
gives the partial currents (n the outward normal)::

    J- = phi/4 + (kappa/2) dphi/dn      (into the object)
    J+ = phi/4 - (kappa/2) dphi/dn      (out of the object)

The boundary transmits the incoming light q and reflects a fraction F_dr of
J+ back: ``J- = q + F_dr J+``.  Substituting::

    phi (1 - F_dr)/4 + (kappa/2)(1 + F_dr) dphi/dn = q
    =>  phi + 2 A kappa dphi/dn = 4 q / (1 - F_dr)                    (eq. 2, 6)

so eq. 9's ``4q/(1 + F_dr)`` is a misprint; the derivation (and Kang & Kim
eq. 17) give ``1 - F_dr``.  Eliminating the derivative::

    J+ = (phi - 2 q) / (2 (1 + F_dr)).

J+ leaves through the boundary; radiance crossing from index eta into air is
multiplied by the Fresnel transmittance and divided by eta^2 (L/n^2 is
invariant).  Assuming the exiting radiance is diffuse, ``L_in = J+/pi`` and::

    L_o(w_o) = F_t(w_o) J+ / (pi eta^2)                               (eq. 4, 7 corrected)

The printed eq. 7 has F_r where the transmittance belongs and omits 1/eta^2;
the printed eq. 4 returns eta^2 times too much power.  Check: the power that
leaves is ``int L_o cos dw = J+ (1 - F_dr,ext)/eta^2 = (1 - F_dr) J+`` by the
reciprocity identity of ``fresnel.py``, i.e. exactly the part of J+ the
boundary does not reflect, so a non-absorbing body returns all the power q it
takes in (tested).

Discretisations
---------------
*Paper* (eq. 5 and 6): ``sum_j kappa_j phi_j / d_ij^2 - (w kappa_i + mu_i) phi_i = 0``
with ``w = sum_j 1/d_ij^2``, and eq. 6 at surface nodes.  Not symmetric, and
with ``kappa_j`` of the neighbour inside the sum it is not the conservative
form of div(kappa grad phi): with strong contrast in kappa the row is no
longer diagonally dominant and Jacobi (eq. 8, 9) is not guaranteed to
converge.

*Ours* (default): a finite-volume scheme on the tetrahedra (the QuadGraph is
their dual).  Inner node i (tet volume V_i), link ij crossing a face of area
A_ij, surface node s linked to inner node k::

    sum_j T_ij (phi_i - phi_j) + mu_i V_i phi_i = 0,     T_ij = kappa_ij A_ij / d_ij
    T_sk (phi_s - phi_k) + a_s phi_s / (2A) = 2 a_s q_s / (1 + F_dr)

with ``kappa_ij`` the harmonic mean of the two nodes' kappa (the face
diffusivity of two media in series).  The second row is eq. 6 multiplied by
``a_s/(2A) = a_s (1 - F_dr)/(2 (1 + F_dr))``.  T_ij = T_ji > 0, so the matrix
is a symmetric M-matrix, strictly diagonally dominant at surface nodes and
irreducibly dominant overall: it is positive definite, the discrete maximum
principle holds (phi never exceeds the largest boundary source
``4 q/(1 - F_dr)``), and every Jacobi-preconditioned Chebyshev iteration with
an upper eigenvalue bound from Gershgorin converges -- whatever the contrast
in kappa.  Summing the rows gives the discrete energy balance
``sum_s a_s (q_s - (1 - F_dr) J+_s) = sum_i mu_i V_i phi_i`` exactly.

*Boundary layer.*  Near a lit surface phi falls off like exp(-sigma_tr z).
When a surface link is longer than the diffusion length (sigma_tr d_sk >~ 1:
skin in blue, ketchup, any coarse graph of a dense absorber), the linear
two-point flux ``kappa (phi_s - phi_k)/d`` under-estimates the flux into the
object and the surface node returns light the medium would have absorbed
(measured: +136 % in skin1's blue on a 12 mm sphere, ketchup's green and blue
bright where the exact answer is zero).  The surface end of each surface link
therefore uses the exponentially fitted flux of the 1D equation
``kappa phi'' = mu phi`` over the link (x = sigma_tr d_sk)::

    T_sk = kappa a x / (d sinh x)   (coupling),   C_sk = kappa a x coth(x) / d   (surface diagonal)

which tends to the plain two-point flux as x -> 0 and, as x -> infinity,
to the half-space value ``phi_s = 4q/(1 - F_dr) / (1 + 2 A kappa sigma_tr)``.
Its absorption ``C - T`` overlaps the inner cell's mu V, so the cell gives up
the leading-order overlap ``mu a d / 2`` (at most half its absorption).  The
matrix stays a symmetric M-matrix.  On the sphere the error of the mean goes
from (+0.1, +0.4, +0.9) % to (+0.03, +0.1, +0.3) % for marble on the coarsest
graph, skin1 converges (3.8 % -> 0.6 % worst channel over three levels) where
the plain flux was +136 %, and ketchup's green and blue are ~0.006 where the
exact answer is 0.

Solvers: ``paper`` (Jacobi, eq. 8-9, on the paper's scheme), ``fast``
(Chebyshev semi-iteration on ours) and ``direct`` (scipy sparse LU on ours),
each with the multi-resolution warm start of eq. 10 and a relative-residual
stopping test.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from . import kernels
from .bake import Bake
from .errors import MaterialError, TranslucencyError
from .fresnel import boundary_A, diffuse_reflectance_internal, fresnel_transmittance
from .lights import environment_flux, incident_flux, shadow_visibility
from .materials import Material, diffusion_coefficient
from .quadgraph import GraphLevel

SCHEMES = ("fv", "paper")
SOLVERS = ("fast", "paper", "direct", "jacobi")


@dataclass
class LevelSystem:
    """One level's linear system in kernel form: diag_i x_i - sum_j off_ij x_j = b_i.

    ``b`` is zero at inner nodes and ``b_scale * q`` at surface nodes.
    """

    scheme: str
    level: GraphLevel
    nbr: np.ndarray  # (N, 4) int32
    off: np.ndarray  # (N, 4, 3)
    diag: np.ndarray  # (N, 3)
    b_scale: np.ndarray  # (n_surface, 3)
    sigma_a: np.ndarray  # (N, 3) per mm (for power accounting)
    mm_per_unit: float
    boundary_diag: np.ndarray | None = None  # (n_surface, 3) a_s/(2A), the boundary exchange term
    lam_max: np.ndarray | None = None  # (3,) upper bound of eig(D^-1 A)
    lam_min: np.ndarray | None = None  # (3,) estimate of the smallest eigenvalue

    @property
    def n(self) -> int:
        return self.level.n_nodes

    def apply(self, x: np.ndarray) -> np.ndarray:
        """A x, with scipy CSR products for the off-diagonal part (CPU fast path).

        Same operation as ``kernels.apply_matrix`` on the packed layout (a
        test checks they agree to rounding); CSR is ~3x faster in numpy.
        """
        csr = self.__dict__.get("_off_csr")
        if csr is None:
            from scipy.sparse import csr_matrix

            n = self.n
            rows = np.repeat(np.arange(n), 4)
            cols = self.nbr.ravel().astype(np.int64)
            m = cols >= 0
            csr = [csr_matrix((self.off[:, :, c].ravel()[m], (rows[m], cols[m])), shape=(n, n))
                   for c in range(self.off.shape[2])]
            self.__dict__["_off_csr"] = csr
        out = self.diag * x
        for c in range(x.shape[1]):
            out[:, c] -= csr[c] @ x[:, c]
        return out

    def subset(self, cols: tuple) -> "LevelSystem":
        """The same system restricted to some colour channels (the planner skips the others)."""
        cols = tuple(int(c) for c in cols)
        if cols == (0, 1, 2):
            return self
        cache = self.__dict__.setdefault("_subsets", {})
        if cols not in cache:
            self.apply(np.zeros((self.n, 3)))  # builds the CSR blocks once
            idx = list(cols)
            sub = LevelSystem(scheme=self.scheme, level=self.level, nbr=self.nbr, off=self.off[:, :, idx],
                              diag=self.diag[:, idx], b_scale=self.b_scale[:, idx], sigma_a=self.sigma_a[:, idx],
                              mm_per_unit=self.mm_per_unit,
                              boundary_diag=None if self.boundary_diag is None else self.boundary_diag[:, idx])
            sub.__dict__["_off_csr"] = [self.__dict__["_off_csr"][c] for c in idx]
            if self.lam_max is not None:
                sub.lam_max, sub.lam_min = self.lam_max[idx], self.lam_min[idx]
            cache[cols] = sub
        return cache[cols]

    def absorption_weights(self) -> np.ndarray:
        """Per-node weights w with absorbed power = sum w phi (mm^2; FV scheme only).

        For the symmetric FV matrix, 1^T A phi = (A 1)^T phi; removing the
        boundary exchange term a_s/(2A) leaves what the operator absorbs.
        """
        if self.scheme != "fv":
            raise TranslucencyError("power accounting is defined for the conservative scheme only")
        w = self.apply(np.ones((self.n, 3)))
        w[self.level.n_inner:] -= self.boundary_diag
        return w

    def rhs(self, q: np.ndarray) -> np.ndarray:
        b = np.zeros((self.n, self.diag.shape[1]))
        b[self.level.n_inner:] = self.b_scale * q
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


def assemble(level: GraphLevel, sigma_a: np.ndarray, sigma_s: np.ndarray, eta: float,
             mm_per_unit: float, scheme: str = "fv") -> LevelSystem:
    """Build the level's system for one material sampling (see module docstring)."""
    if scheme not in SCHEMES:
        raise TranslucencyError(f"unknown scheme {scheme!r}")
    s = float(mm_per_unit)
    kappa = diffusion_coefficient(sigma_a, sigma_s)  # (N, 3) mm
    mu = sigma_a
    nbr = level.neighbors.astype(np.int64)
    has = nbr >= 0
    A = boundary_A(eta)
    fdr = diffuse_reflectance_internal(eta)
    nI = level.n_inner
    d = level.edge_length * s  # mm
    k_nb = kernels.gather(nbr, kappa)  # (N, 4, 3)
    if scheme == "fv":
        kf = 2.0 * kappa[:, None, :] * k_nb / np.maximum(kappa[:, None, :] + k_nb, 1e-300)
        # Link length d_ij, not the face-normal distance: on the sphere test
        # the normal distance lowers node-to-node scatter slightly but biases
        # the mean, which then stops converging under refinement.
        G = np.where(has, level.face_area * s * s / np.where(has, d, 1.0), 0.0)  # mm
        off = kf * G[..., None]
        diag = off.sum(axis=1)
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
        a_s = (level.area * s * s)[:, None]
        boundary_diag = np.broadcast_to(a_s / (2.0 * A), (level.n_surface, 3)).copy()
        diag[nI:] += boundary_diag
        b_scale = np.broadcast_to(2.0 * a_s / (1.0 + fdr), (level.n_surface, 3)).copy()
    else:
        inv_d2 = np.where(has, 1.0 / np.where(has, d, 1.0) ** 2, 0.0)
        off = np.zeros((level.n_nodes, 4, 3))
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


# ---------------------------------------------------------------- eigenvalues
def gershgorin_upper(system: LevelSystem) -> np.ndarray:
    """Upper bound of the spectrum of D^-1 A per channel: max_i 1 + sum_j |a_ij| / a_ii (<= 2)."""
    return (1.0 + system.off.sum(axis=1) / system.diag).max(axis=0)


def lanczos_lower(system: LevelSystem, steps: int = 40, seed: int = 0) -> np.ndarray:
    """Estimate the smallest eigenvalue of D^-1 A (per channel) by Lanczos on D^-1/2 A D^-1/2.

    Ritz values lie inside the spectrum, so this slightly over-estimates
    lambda_min; Chebyshev still converges for modes below the interval (only
    more slowly), so the estimate affects speed, never stability.  The
    caller shrinks it by a safety factor.

    The start vector is ``D^1/2 1`` plus a little noise.  The matrix is a
    symmetric M-matrix, so its lowest eigenvector is positive, and when
    lambda_min is small -- little absorption and a weak boundary leak: an
    object small against the diffusion length, albedo near 1 -- it is close
    to ``D^1/2 1`` (``A 1`` is only the absorption and the leak).  From a
    random start, 40 steps over-estimated lambda_min up to 40-fold on such
    graphs (0.1 mm sphere: 2.9e-3 for 6.9e-5); Chebyshev then stopped on a
    small residual while the smooth error mode, which the residual barely
    sees, was not converged (error 4.6x the tolerance) and took 2.7x the
    sweeps (tests/hard_cases).
    """
    rng = np.random.default_rng(seed)
    n = system.n
    steps = int(min(steps, n))
    dinv_sqrt = 1.0 / np.sqrt(system.diag)
    nc = system.diag.shape[1]
    out = np.zeros(nc)
    noise = rng.standard_normal((n, nc))
    smooth = np.sqrt(system.diag)
    v = smooth / np.linalg.norm(smooth, axis=0) + 0.05 * noise / np.linalg.norm(noise, axis=0)
    v /= np.linalg.norm(v, axis=0)
    v_prev = np.zeros_like(v)
    alphas, betas = [], []
    beta = np.zeros(nc)
    for _ in range(steps):
        w = dinv_sqrt * system.apply(dinv_sqrt * v)
        alpha = np.einsum("nc,nc->c", w, v)
        w = w - alpha * v - beta * v_prev
        alphas.append(alpha)
        beta = np.linalg.norm(w, axis=0)
        betas.append(beta)
        if np.all(beta < 1e-14):
            break
        v_prev, v = v, w / np.maximum(beta, 1e-300)
    alphas = np.array(alphas)
    betas = np.array(betas)[:-1]
    for c in range(nc):
        Tm = np.diag(alphas[:, c])
        if len(betas):
            Tm += np.diag(betas[:, c], 1) + np.diag(betas[:, c], -1)
        out[c] = np.linalg.eigvalsh(Tm)[0]
    return np.maximum(out, 1e-12)


def spectral_bounds(system: LevelSystem, safety: float = 0.8):
    if system.lam_max is None:
        system.lam_max = gershgorin_upper(system)
        system.lam_min = np.minimum(safety * lanczos_lower(system), 0.5 * system.lam_max)
    return system.lam_min, system.lam_max


# ------------------------------------------------------------------ deflation
DEFLATION_GAP = 30.0  # deflate where the constant modes lie this far below the rest of the spectrum


@dataclass
class Deflation:
    """The near-null space of a leak-dominated system: one constant vector per graph component.

    With little absorption and a weak boundary leak (an object much smaller
    than its diffusion length: tiny objects, albedo -> 1, optically thin
    media) the constant on each connected piece is an isolated eigenvector
    of D^-1 A: ``A 1`` is only the absorption and the leak, far below the
    diffusion couplings.  Its eigenvalue can lie orders of magnitude below
    the rest of the spectrum (a 17 um sphere with a 100 mm diffusion
    coefficient: lambda_1 = 3e-8, lambda_2 = 2e-4), and Chebyshev on
    [lambda_1, lambda_max] then needs ~1/sqrt(lambda_1) sweeps (over 50,000).
    A Galerkin correction with these vectors removes that mode exactly
    enough that Chebyshev can run on [lambda_2, lambda_max] instead.
    """

    labels: np.ndarray  # (N,) component of every node
    a1: np.ndarray  # (N, C) A 1: absorption + boundary leak per node
    E: np.ndarray  # (n_comp, C) 1_c^T A 1_c (> 0: every piece has surface nodes)
    mask: np.ndarray  # (C,) bool: channels whose constants are deflated
    lam_min: np.ndarray  # (C,) lower end of the rest of the spectrum (estimate, safety applied)

    def correct(self, x: np.ndarray, r: np.ndarray):
        """x += Z E^-1 Z^T r, r -= A Z E^-1 Z^T r (on the deflated channels); exact, no product with A."""
        n_comp = self.E.shape[0]
        for c in np.nonzero(self.mask)[0]:
            alpha = np.bincount(self.labels, weights=r[:, c], minlength=n_comp) / self.E[:, c]
            x[:, c] += alpha[self.labels]
            r[:, c] -= self.a1[:, c] * alpha[self.labels]
        return x, r


def graph_components(level: GraphLevel) -> np.ndarray:
    """Connected-component label of every node of a level (surface nodes with their inner node)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    n = level.n_nodes
    i = np.repeat(np.arange(n), 4)
    j = level.neighbors.ravel().astype(np.int64)
    m = j >= 0
    g = coo_matrix((np.ones(int(m.sum())), (i[m], j[m])), shape=(n, n))
    return connected_components(g, directed=False)[1]


def deflation(system: LevelSystem, safety: float = 0.8, gap: float | None = None,
              steps: int = 40, seed: int = 1) -> Deflation | None:
    """The constant-mode deflation of a leak-dominated level, or ``None`` when it would not help.

    Per channel: the Rayleigh quotient of each component's constant,
    ``rho = 1^T A 1 / 1^T D 1`` (an upper bound of the lowest eigenvalue on
    that piece), against a Lanczos estimate of the bottom of the spectrum
    orthogonal to those constants (by interlacing it is >= lambda_{k+1}).
    The channel is deflated when every ``rho`` is ``gap`` times below it.
    Only looked at when the smallest eigenvalue estimate is small (< 1e-3);
    cached on the system.  Used by the CPU Chebyshev solve only
    (:func:`spectral_bounds`, which the GPU path shares, is unchanged).
    """
    if system.scheme != "fv":
        return None
    gap = DEFLATION_GAP if gap is None else gap
    cache = system.__dict__.get("_deflation", False)
    if cache is not False:
        return cache
    lam_min, _ = spectral_bounds(system)
    out = None
    if np.any(lam_min < 1e-3):
        labels = graph_components(system.level)
        n_comp = int(labels.max()) + 1
        nc = system.diag.shape[1]
        a1 = system.apply(np.ones((system.n, nc)))
        E = np.stack([np.bincount(labels, weights=a1[:, c], minlength=n_comp) for c in range(nc)], axis=1)
        dsum = np.stack([np.bincount(labels, weights=system.diag[:, c], minlength=n_comp) for c in range(nc)], axis=1)
        rho = (E / dsum).max(axis=0)
        # Lanczos on P M P, M = D^-1/2 A D^-1/2, P projecting out u_k = D^1/2 1_k / |.| (disjoint supports).
        sq = np.sqrt(system.diag)

        def project(v):
            for c in range(nc):
                coef = np.bincount(labels, weights=sq[:, c] * v[:, c], minlength=n_comp) / dsum[:, c]
                v[:, c] -= sq[:, c] * coef[labels]
            return v

        rng = np.random.default_rng(seed)
        v = project(rng.standard_normal((system.n, nc)))
        v /= np.linalg.norm(v, axis=0)
        v_prev = np.zeros_like(v)
        beta = np.zeros(nc)
        alphas, betas = [], []
        for _ in range(int(min(steps, system.n - n_comp))):
            w = project(system.apply(v / sq) / sq)
            alpha = np.einsum("nc,nc->c", w, v)
            w = w - alpha * v - beta * v_prev
            alphas.append(alpha)
            beta = np.linalg.norm(w, axis=0)
            betas.append(beta)
            if np.all(beta < 1e-14):
                break
            v_prev, v = v, w / np.maximum(beta, 1e-300)
        if alphas:
            al = np.array(alphas)
            be = np.array(betas)[:-1]
            lam2 = np.array([np.linalg.eigvalsh(np.diag(al[:, c]) + np.diag(be[:, c], 1) + np.diag(be[:, c], -1))[0]
                             for c in range(nc)])
            mask = (gap * rho < lam2) & (E > 0).all(axis=0)
            if mask.any():
                out = Deflation(labels=labels, a1=a1, E=np.where(E > 0, E, 1.0), mask=mask,
                                lam_min=np.where(mask, np.minimum(safety * lam2, 0.5 * system.lam_max), lam_min))
    system.__dict__["_deflation"] = out
    return out


# --------------------------------------------------------------------- solves
@dataclass
class LevelSolve:
    iterations: int
    residual: np.ndarray  # (3,) final relative residual
    history: list  # relative residual (max over channels) at each check
    seconds: float

    @property
    def converged_to(self) -> float:
        return float(np.max(self.residual))

    @property
    def diverged(self) -> bool:
        return not np.all(np.isfinite(self.residual)) or self.history[-1] > 10.0 * max(self.history[0], 1.0)


def relative_residual(system: LevelSystem, b: np.ndarray, x: np.ndarray) -> np.ndarray:
    r = b - system.apply(x)
    bn = np.sqrt(kernels.squared_norms(b))
    return np.sqrt(kernels.squared_norms(r)) / np.where(bn > 0, bn, 1.0)


def solve_jacobi(system, b, x0, tol, max_iter, check_every=8) -> tuple[np.ndarray, LevelSolve]:
    """Plain Jacobi relaxation (eqs. 8-9 when the system is the paper's)."""
    t0 = time.perf_counter()
    x = x0.copy()
    hist = []
    it = 0
    res = relative_residual(system, b, x)
    hist.append(float(res.max()))
    first = max(hist[0], 1.0)
    while it < max_iter and res.max() > tol:
        for _ in range(check_every):
            x = x + (b - system.apply(x)) / system.diag  # = kernels.jacobi_sweep, CSR product
        it += check_every
        res = relative_residual(system, b, x)
        hist.append(float(res.max()))
        if not np.all(np.isfinite(res)) or res.max() > 1e3 * first:
            break  # diverging (the paper's scheme under kappa contrast); reported, not hidden
    return x, LevelSolve(it, res, hist, time.perf_counter() - t0)


def solve_chebyshev(system, b, x0, tol, max_iter, check_every=8) -> tuple[np.ndarray, LevelSolve]:
    """Chebyshev semi-iteration with the Jacobi preconditioner (Saad Alg. 12.1), per channel.

    Needs no dot products (only the occasional residual norm for the
    stopping test), so each step is one GPU dispatch.  Eigenvalue interval:
    Gershgorin above (a guaranteed bound), Lanczos estimate below.

    On a leak-dominated level (:func:`deflation`) the iteration becomes a
    two-level cycle: a Galerkin correction with the per-component constants,
    Chebyshev on the rest of the spectrum down to the tolerance, the true
    residual and the correction again, until the true residual meets the
    tolerance.  A cycle ends at the tolerance or when a deflated channel's
    residual stalls (no 10 % gain in 6 checks: what is left lies in the
    deflated modes).  If a stalled cycle and its correction did not at least
    halve that channel's residual, the constants do not carry its slow modes
    (several weakly coupled regions, e.g. cells of a transparent medium in a
    dense one, rather than one per piece), and the channel goes on over its
    whole spectrum.
    Elsewhere it is the plain iteration, step for step what the GPU kernels do.
    """
    t0 = time.perf_counter()
    lam_min, lam_max = spectral_bounds(system)
    defl = deflation(system)
    deflated = np.zeros(len(lam_max), dtype=bool) if defl is None else defl.mask.copy()

    def interval():
        lo = np.where(deflated, defl.lam_min, lam_min) if defl is not None else lam_min
        theta = 0.5 * (lam_max + lo)
        delta = 0.5 * (lam_max - lo)
        return theta, delta, theta / delta

    theta, delta, sigma = interval()
    x = x0.copy()
    r = b - system.apply(x)
    if defl is not None:
        x, r = defl.correct(x, r)
    bn = np.sqrt(kernels.squared_norms(b))
    bn = np.where(bn > 0, bn, 1.0)
    res = np.sqrt(kernels.squared_norms(r)) / bn
    hist = [float(res.max())]
    it = 0
    while res.max() > tol and it < max_iter:
        start = res.copy()
        rho = 1.0 / sigma
        d = r / system.diag / theta
        best, since = res.copy(), np.zeros(len(res), dtype=int)
        stalled = np.zeros(len(res), dtype=bool)
        while it < max_iter:
            rho_next = 1.0 / (2.0 * sigma - rho)
            coef_d = rho_next * rho
            coef_r = 2.0 * rho_next / delta
            x, r, d = kernels.chebyshev_update(x, r, d, system.apply(d), system.diag, coef_d, coef_r)
            rho = rho_next
            it += 1
            if it % check_every == 0:
                res = np.sqrt(kernels.squared_norms(r)) / bn
                hist.append(float(res.max()))
                if res.max() <= tol:
                    break
                if deflated.any():  # a deflated channel is done with the rest of its spectrum when it stalls
                    gain = res < 0.9 * best
                    best = np.where(gain, res, best)
                    since = np.where(gain, 0, since + 1)
                    stalled = deflated & (since >= 6) & (res > tol)
                    if stalled.any():
                        break
        # The recursively updated r drifts slightly from b - A x; report the true one.
        res = relative_residual(system, b, x)
        if defl is None:
            break
        r = b - system.apply(x)
        x, r = defl.correct(x, r)
        res = np.sqrt(kernels.squared_norms(r)) / bn
        hist.append(float(res.max()))
        give_up = stalled & (res > 0.5 * start)
        if give_up.any():
            deflated &= ~give_up
            theta, delta, sigma = interval()
    return x, LevelSolve(it, res, hist, time.perf_counter() - t0)


def sparse_matrix(system: LevelSystem, channel: int):
    """The system as a scipy CSR matrix for one channel."""
    from scipy.sparse import csr_matrix

    n = system.n
    rows = np.repeat(np.arange(n), 4)
    cols = system.nbr.ravel().astype(np.int64)
    vals = -system.off[:, :, channel].ravel()
    m = cols >= 0
    A = csr_matrix((vals[m], (rows[m], cols[m])), shape=(n, n))
    A = A + csr_matrix((system.diag[:, channel], (np.arange(n), np.arange(n))), shape=(n, n))
    return A.tocsr()


def solve_direct(system, b, *_args, **_kw) -> tuple[np.ndarray, LevelSolve]:
    """Sparse LU (scipy) per channel: the reference the iterative solvers are tested against."""
    from scipy.sparse.linalg import splu

    t0 = time.perf_counter()
    x = np.zeros_like(b)
    for c in range(b.shape[1]):
        lu = getattr(system, "_lu", {}).get(c)
        if lu is None:
            # Minimum-degree ordering on A^T + A suits these structurally
            # symmetric 3D matrices (4x less fill than the COLAMD default).
            sym = system.scheme == "fv"
            lu = splu(sparse_matrix(system, c).tocsc(), permc_spec="MMD_AT_PLUS_A",
                      options={"SymmetricMode": True} if sym else None)
            if not hasattr(system, "_lu"):
                system._lu = {}
            system._lu[c] = lu
        x[:, c] = lu.solve(b[:, c])
    res = relative_residual(system, b, x)
    return x, LevelSolve(1, res, [float(res.max())], time.perf_counter() - t0)


@dataclass
class SolveOptions:
    solver: str = "fast"  # fast | paper | direct | jacobi (Jacobi on our scheme)
    tol: float = 1e-4
    max_iterations: int = 50_000
    check_every: int = 8
    coarse_tol: float | None = None  # tolerance on coarser levels (default: tol)
    levels: str = "all"  # "all": multi-resolution warm start; "finest": single level
    sky_occlusion: bool = True  # use the bake's sky visibility (when baked) for environment light

    def scheme(self) -> str:
        return "paper" if self.solver == "paper" else "fv"


@dataclass
class SolveResult:
    phi: list  # per level (N_l, 3)
    q: list  # per level (n_surface_l, 3)
    level_solves: list
    seconds: dict = field(default_factory=dict)
    scheme: str = "fv"
    warnings: list = field(default_factory=list)  # from the light pass (e.g. a light inside the object)

    @property
    def iterations(self) -> int:
        return int(sum(ls.iterations for ls in self.level_solves))

    @property
    def residual(self) -> np.ndarray:
        return self.level_solves[-1].residual


_SOLVERS = {"fast": solve_chebyshev, "paper": solve_jacobi, "jacobi": solve_jacobi, "direct": solve_direct}


class DiffusionSolver:
    """Multiple scattering for one baked object: material, lights -> radiance per vertex.

    Typical use::

        solver = DiffusionSolver(bake, material, field_values)   # field: per level, or None
        result = solver.solve(lights, environment)
        L = solver.vertex_radiance(result)                        # (n_vertices, 3)

    Changing the material re-samples kappa and mu at the nodes
    (:meth:`set_material`) without a re-bake.
    """

    def __init__(self, bake: Bake, material: Material, field_values=None, options: SolveOptions | None = None):
        self.bake = bake
        self.options = options or SolveOptions()
        if self.options.solver not in SOLVERS:
            raise TranslucencyError(f"unknown solver {self.options.solver!r}; choose one of {', '.join(SOLVERS)}")
        self._shadow_bvh = None
        self.warnings: list[str] = []  # of the latest light pass (incident)
        self.set_material(material, field_values)

    # -- material ------------------------------------------------------------
    def set_material(self, material: Material, field_values=None) -> None:
        """Sample kappa and mu at every node of every level and assemble the systems."""
        self.material = material
        self.eta = material.eta
        self.fdr = diffuse_reflectance_internal(material.eta)
        levels = self.bake.levels
        if field_values is not None and len(field_values) != len(levels):
            raise MaterialError(f"field values needed for {len(levels)} levels, got {len(field_values)}")
        self.systems = []
        for i, lv in enumerate(levels):
            fv = None if field_values is None else np.asarray(field_values[i])
            if fv is not None and fv.shape[0] != lv.n_nodes:
                raise MaterialError(f"level {i}: field has {fv.shape[0]} values for {lv.n_nodes} nodes")
            sa, ss = node_coefficients(material, fv, lv.n_nodes)
            self.systems.append(assemble(lv, sa, ss, material.eta, self.bake.mm_per_unit, self.options.scheme()))

    # -- lights ----------------------------------------------------------------
    def shadow_bvh(self, occluders=None):
        """BVH of the object's own surface plus other objects' triangles (object space).

        ``occluders``: ``None``, an ``(V, F)`` pair, or a prebuilt
        :class:`~.raycast.TriangleBVH` of the whole scene.  The combined BVH is
        cached and rebuilt only when the occluder arrays change.
        """
        from .raycast import TriangleBVH

        if isinstance(occluders, TriangleBVH):
            return occluders
        if occluders is None:
            if self._shadow_bvh is None:
                self._shadow_bvh = TriangleBVH(self.bake.mesh_vertices, self.bake.mesh_faces)
            return self._shadow_bvh
        Vo, Fo = (np.ascontiguousarray(a) for a in occluders)
        key = (Vo.shape, Fo.shape, hash(Vo.tobytes()), hash(Fo.tobytes()))
        cached = getattr(self, "_occluder_cache", None)
        if cached is not None and cached[0] == key:
            return cached[1]
        V = np.vstack([self.bake.mesh_vertices, Vo])
        F = np.vstack([self.bake.mesh_faces, np.asarray(Fo) + len(self.bake.mesh_vertices)])
        bvh = TriangleBVH(V, F)
        self._occluder_cache = (key, bvh)
        return bvh

    def incident(self, lights, environment=None, shadows: bool = True, occluders=None,
                 levels=None, bounce=None) -> list:
        """q (eq. 3) at the surface nodes of the requested levels (default all); None elsewhere.

        Lights inside the object contribute nothing and are named in
        :attr:`warnings` (see :meth:`lights_inside`).  When the bake carries
        sky visibility (``sky_visibility``) and ``options.sky_occlusion`` is
        on, the environment term loses the directions in which the object
        sees itself, and ``bounce`` -- the mesh's vertex radiance from a
        previous solve, (n_vertices, 3) -- adds the light the object sends to
        itself through those directions (one interreflection bounce).
        """
        sky = self.sky
        if sky is None:
            bounce = None
        want = range(len(self.bake.levels)) if levels is None else levels
        lights = list(lights or ())
        inside = self.lights_inside(lights)
        self.warnings = [
            f"light {light.name or light.kind!r} at {tuple(round(float(x), 6) for x in light.position)} is inside "
            "the object: a source inside the medium is not part of the surface-lighting model, so it adds no "
            "light; move it outside the surface" for light in inside]
        if inside:
            lights = [light for light in lights if not any(light is x for x in inside)]
        vis = None
        if shadows and lights:
            diag = float(np.linalg.norm(np.ptp(self.bake.mesh_vertices, axis=0)))
            vis = shadow_visibility(self.shadow_bvh(occluders), offset=1e-4 * diag)
        out = [None] * len(self.bake.levels)
        for i in want:
            lv = self.bake.levels[i]
            if sky is None:
                out[i] = incident_flux(lights, environment, lv.surface_position, lv.normal, self.eta,
                                       self.bake.mm_per_unit, visibility=vis)
                continue
            q = incident_flux(lights, None, lv.surface_position, lv.normal, self.eta, self.bake.mm_per_unit,
                              visibility=vis)
            env = environment if environment is not None and not environment.is_black else None
            q_env = environment_flux(env, lv.normal, self.eta) if env is not None else None
            out[i] = q + sky.correct(i, lv.normal, self.eta, q_env, env, bounce)
        return out

    def lights_inside(self, lights) -> list:
        """The point, spot and area lights whose position lies inside the object.

        Eq. 3's q is the light that reaches the surface from outside.  A
        source inside the medium would be an interior source term of the
        diffusion equation, which this boundary-source model (and its GPU
        kernels, which form b from q at surface nodes only) does not have.
        Counting it through the surface would be wrong: with shadow rays the
        object's own surface blocks it (zero), without them the surface
        elements on the far side of a concavity that face it would be lit as
        if from outside.  So such a light contributes nothing and
        :meth:`incident` says so.  Inside = majority vote of ray parity
        against the user's mesh (``raycast.inside_mesh``, robust to small
        holes); results are cached per position.
        """
        cand = [light for light in lights if light.kind != "sun"]
        if not cand:
            return []
        from .raycast import inside_mesh

        cache = self.__dict__.setdefault("_inside_cache", {})
        keys = [tuple(float(x) for x in light.position) for light in cand]
        todo = sorted({k for k in keys if k not in cache})
        if todo:
            flags = inside_mesh(self.shadow_bvh(None), np.array(todo))
            if len(cache) > 1024:
                cache.clear()
            cache.update(zip(todo, (bool(f) for f in flags)))
        return [light for light, k in zip(cand, keys) if cache[k]]

    @property
    def sky(self):
        """The bake's sky visibility when this solver uses it (baked and ``options.sky_occlusion``), else None."""
        return self.bake.sky if self.options.sky_occlusion else None

    # -- solve -------------------------------------------------------------------
    def can_warm_start(self, warm_start) -> bool:
        """Whether ``warm_start`` carries a finest-level solution this solver can start from."""
        return warm_start is not None and warm_start.phi[-1] is not None

    def solve(self, lights=(), environment=None, *, q=None, warm_start=None, shadows=True,
              occluders=None, channels=None, bounce=None) -> SolveResult:
        """Solve every level coarse to fine (or only the finest, from ``warm_start``).

        ``q``: precomputed incident light per level (skips the light pass).
        ``bounce``: vertex radiance of a previous solve, the light the object
        sends to itself (used only with the bake's sky visibility; see
        :meth:`incident` and :meth:`solve_interreflected`).
        ``warm_start``: a previous :class:`SolveResult` of this solver; its
        finest solution starts the finest level directly (the frame-to-frame
        case), so coarse levels are skipped.
        ``channels``: (bool, bool, bool) from the planner; skipped channels
        cost nothing on the CPU and come out as zero flux.
        """
        t0 = time.perf_counter()
        opts = self.options
        n_lv = len(self.bake.levels)
        usable = self.can_warm_start(warm_start)
        finest_only = opts.levels == "finest" or usable
        active = [n_lv - 1] if finest_only else list(range(n_lv))
        warnings = []
        if q is None:
            q = self.incident(lights, environment, shadows=shadows, occluders=occluders, levels=active,
                              bounce=bounce)
            warnings = list(self.warnings)
        t1 = time.perf_counter()
        mask = (True, True, True) if channels is None else tuple(bool(c) for c in channels)
        self._channels = tuple(c for c in range(3) if mask[c])
        if not self._channels:
            phi = [None if p is None else np.zeros((lv.n_nodes, 3)) for p, lv in
                   zip([q[i] for i in range(n_lv)], self.bake.levels)]
            solves = [LevelSolve(0, np.zeros(3), [0.0], 0.0) for _ in active]
        else:
            phi, solves = self.solve_systems(q, active, warm_start)
            if len(self._channels) < 3:  # a backend that ignores the mask still honours it
                off = [c for c in range(3) if not mask[c]]
                for p in phi:
                    if p is not None:
                        p[:, off] = 0.0
        t2 = time.perf_counter()
        return SolveResult(phi=phi, q=q, level_solves=solves, scheme=self.systems[-1].scheme,
                           seconds={"lights": t1 - t0, "solve": t2 - t1, "total": t2 - t0}, warnings=warnings)

    def solve_interreflected(self, lights=(), environment=None, *, bounces: int = 1, warm_start=None,
                             bounce=None, **kw) -> tuple:
        """Solve, then solve again ``bounces`` times with the object's own radiance as ``bounce``.

        Each pass is warm-started from the previous one.  ``bounce`` (a
        previous frame's vertex radiance) replaces the first plain pass.
        Without sky visibility in the bake this is a single :meth:`solve`.
        Returns ``(SolveResult, vertex radiance along the normals)``.
        """
        res = self.solve(lights, environment, warm_start=warm_start, bounce=bounce, **kw)
        L = self.vertex_radiance(res)
        if self.sky is None:
            return res, L
        for _ in range(int(bounces) - (bounce is not None)):
            res = self.solve(lights, environment, warm_start=res, bounce=L, **kw)
            L = self.vertex_radiance(res)
        return res, L

    def solve_systems(self, q, active, warm_start=None):
        """Run the linear solves on the ``active`` levels, coarse to fine (eq. 10 between them).

        This is the part a GPU backend replaces (``gpu_shaders.solver``); the
        assembly, the light pass and the output stay shared.
        Returns ``(phi per level (None where inactive), [LevelSolve])``.
        """
        opts = self.options
        n_lv = len(self.bake.levels)
        fn = _SOLVERS[opts.solver]
        cols = getattr(self, "_channels", (0, 1, 2))
        phi = [None] * n_lv
        solves = []
        x = None
        for i in active:
            system = self.systems[i].subset(cols)
            b = system.rhs(q[i][:, cols])
            if warm_start is not None and i == n_lv - 1 and warm_start.phi[-1] is not None:
                x0 = np.array(warm_start.phi[-1][:, cols], dtype=np.float64)
            elif x is not None:
                idx, w = self.bake.shepard[i - 1]
                x0 = kernels.shepard_upsample(idx, w, x)
            else:
                x0 = np.zeros((system.n, len(cols)))
            tol = opts.tol if i == n_lv - 1 else (opts.coarse_tol or opts.tol)
            x, info = fn(system, b, x0, tol, opts.max_iterations, opts.check_every)
            full = np.zeros((system.n, 3))
            full[:, cols] = x
            phi[i] = full
            res = np.zeros(3)
            res[list(cols)] = info.residual
            info.residual = res
            solves.append(info)
        return phi, solves

    # -- output ------------------------------------------------------------------
    def surface_partial_current(self, result: SolveResult, level: int = -1) -> np.ndarray:
        """J+ at the level's surface nodes: clamped at 0, scaled so that the clamp adds no power.

        See :func:`clamp_scale`.
        """
        lv = self.bake.levels[level]
        phi_s, q = result.phi[level][lv.n_inner:], result.q[level]
        jplus = kernels.outgoing_partial_current(phi_s, q, self.fdr)
        return jplus * clamp_scale(phi_s, q, lv.area, self.fdr)

    def vertex_radiance(self, result: SolveResult, view_dirs=None) -> np.ndarray:
        """Outgoing radiance (W/(m^2 sr)) at the baked mesh's vertices.

        ``view_dirs``: (n_vertices, 3) unit vectors from the surface towards
        the viewer; default: along the vertex normal.
        """
        idx, w = self.bake.vertex_map
        return self.radiance_at(result, idx, w, self.bake.mesh_normals, view_dirs)

    def radiance_at(self, result: SolveResult, idx, w, normals, view_dirs=None) -> np.ndarray:
        """Outgoing radiance at arbitrary points mapped onto the finest surface nodes.

        ``idx``/``w`` (n, k): surface-node indices and weights (e.g. from
        :func:`.bake.vertex_mapping` for another vertex set, such as a mesh
        before its modifiers); ``normals`` (n, 3); ``view_dirs`` as above.
        """
        jplus = self.surface_partial_current(result)
        j_v = np.einsum("vk,vkc->vc", np.asarray(w, dtype=np.float64), jplus[np.asarray(idx)])
        n = np.asarray(normals, dtype=np.float64)
        cos_o = np.ones(len(n)) if view_dirs is None else np.einsum("vj,vj->v", n, view_dirs)
        return outgoing_radiance(j_v, cos_o, self.eta)

    def power_balance(self, result: SolveResult, level: int = -1, clamp: bool = True) -> dict:
        """Incoming, absorbed and outgoing power (W, per channel) on one level.

        ``out = sum_s a_s (1 - F_dr) J+_s``.  ``absorbed`` is what the
        discrete operator removes: ``(A 1 - a_s/(2A) at surface nodes) . phi``
        (cell absorption mu V plus the absorption inside fitted surface links);
        unclamped, ``in = out + absorbed`` holds to the solver tolerance.
        """
        lv = self.bake.levels[level]
        system = self.systems[level]
        s = self.bake.mm_per_unit * 1e-3  # metres per unit, so powers are in W
        a = lv.area * s * s
        q = result.q[level]
        phi = result.phi[level]
        phi_s = phi[lv.n_inner:]
        jp = (phi_s - 2.0 * q) / (2.0 * (1.0 + self.fdr))
        if clamp:  # what the radiance output emits (surface_partial_current)
            jp = np.maximum(jp, 0.0) * clamp_scale(phi_s, q, lv.area, self.fdr)
        p_in = a @ q
        p_out = a @ ((1.0 - self.fdr) * jp)
        p_abs = np.einsum("nc,nc->c", system.absorption_weights(), phi) * 1e-6  # mm^2 -> m^2
        return {"in": p_in, "out": p_out, "absorbed": p_abs}


def clamp_scale(phi_s: np.ndarray, q: np.ndarray, area: np.ndarray, fdr: float) -> np.ndarray:
    """Per-channel factor (<= 1) that keeps the clamp of J+ from creating power.

    The exact discrete balance gives ``sum_s a_s (1 - F_dr) J+_s = in - absorbed``
    with the unclamped J+.  Clamping its negative values to 0 raises that sum,
    and where the diffusion model fails -- an object much thinner than a
    transport mean free path lit on one side, where the surface node's phi is
    below 2q -- the output then emitted more than came in (fuzz test: 8 % at
    a 4 um sphere with 1 mm mean free paths).  When the unclamped total is
    positive and smaller than the clamped one, the clamped J+ is scaled down
    to it, so the output emits exactly ``in - absorbed``; otherwise (nothing
    was clamped, or the model gives a net inflow: an absorber, where the
    clamped output is already below the light that came in) the factor is 1.
    """
    j = (np.asarray(phi_s) - 2.0 * np.asarray(q)) / (2.0 * (1.0 + fdr))
    a = np.asarray(area, dtype=np.float64)
    unclamped = a @ j
    clamped = a @ np.maximum(j, 0.0)
    ok = (unclamped > 0) & (clamped > unclamped)
    return np.where(ok, unclamped / np.where(ok, clamped, 1.0), 1.0)


def outgoing_radiance(jplus: np.ndarray, cos_o, eta: float) -> np.ndarray:
    """L_o = F_t(w_o) J+ / (pi eta^2) (corrected eq. 4 / 7).

    Rule for phi - 2q < 0: J+ is clamped to 0 before this (kernels.outgoing_partial_current).
    A negative J+ would mean light flowing *into* the object through the
    exitant half-space, which the diffusion approximation cannot resolve; it
    occurs where a link is shorter than 2 kappa (the FV row gives
    ``phi_s - 2q >= 0`` whenever ``phi_k >= q (2 - d_sk/kappa)``), i.e. on
    graphs finer than a transport mean free path, and in strong absorbers.
    The clamp removes no light from lit regions; the power it would add is
    taken back by :func:`clamp_scale` (CPU output).
    """
    ft = fresnel_transmittance(np.clip(cos_o, 0.0, 1.0), eta)
    ft = np.where(np.asarray(cos_o) > 0, ft, 0.0)
    return jplus * (ft / (np.pi * eta * eta))[:, None]
