r"""Light transport in a half-space, solved exactly in 1D: what diffusion gets wrong at low albedo.

The first-scatter split (:mod:`.split`) hands the diffusion solve the light that scatters two or
more times.  Calibrated with the diffusion's own half-space solution (eq. 3 there), it inherits
diffusion's error for that light: +8 % at albedo 0.68, +4 % at 0.84 (eta = 1.3) against a random walk
(``tests/test_scattering_split.py``) -- skin1's blue and green, the largest model errors in
docs/accuracy.md.  This module solves the same half-space by transport instead, so the split can be
calibrated on the exact answer: the graph then carries the light sideways through the object's shape,
and a half-space returns what transport returns.

The problem (units of the mean free path, sigma_t = 1; isotropic phase; single-scattering albedo alpha;
smooth boundary of relative index eta with the Fresnel transmittance ``T_in(m)`` for light reaching it
from inside at cosine m, ``R_in = 1 - T_in``).  Light q enters with the distribution ``p_j`` over the
inside cosines ``nu_j``; its uncollided fluence is ``phi_0(z) = sum_j p_j e^{-z/nu_j}/nu_j``.  The
fluence of scattered light phi_s solves the integral form of the transport equation (Chandrasekhar,
*Radiative Transfer*, 1960, ch. 1 and 2; the Milne problem with a reflecting boundary)::

    phi_s = alpha K (phi_0 + phi_s),
    K f(z) = 1/2 int_0^inf f(z') int_0^1 [e^{-|z - z'|/m} + R_in(m) e^{-(z + z')/m}] dm/m dz'       (1)

(isotropic emission ``alpha (phi_0 + phi_s)/(4 pi)`` per unit volume and solid angle, carried along
straight paths directly or after one reflection at the boundary).  What leaves towards cosine m inside,
and crosses with ``T_in(m)``::

    L_in(m) = alpha/(4 pi) int_0^inf (phi_0 + phi_s)(z) e^{-z/m} dz/m                                  (2)

Light scattered once is the ``phi_0`` part of (2), the closed form of :mod:`.split` eq. 1; light
scattered two or more times is the ``phi_s`` part, whose power M and angular shape the split needs.

Discretisation: phi_s constant on cells of a depth grid graded from 0.002 mean free paths at the
surface to 1 deep, to 400 deep (:func:`depth_grid`; the light that reaches the bottom is lost, about
e^{-400 sigma_tr}: below 1e-4 for every alpha the split's tables solve, alpha <= 0.99976), collocated
at cell centres.  The direct part of K integrates in closed form over a cell,
``int_0^1 e^{-|z - z'|/m} dm/m = E_1(|z - z'|)`` and ``int E_1 = E_2`` (``scipy.special.expn``); the
reflected part splits into the total internal reflection below the critical cosine
``m_c = sqrt(1 - 1/eta^2)`` (``R_in = 1``: again E_2, scaled by m_c) and the Fresnel part above it
(Gauss-Legendre in m, smooth).  The uncollided source is averaged over each cell.  The error is second
order in the cell size (0.6 % of M at alpha 0.999 on the default grid, 0.16 % at half the cells'
size), so :mod:`.split` extrapolates from two grids.  Against the random walk
(``tests/test_scattering_split.py``): every scattering order to the walk's noise.

Hand-written: scipy has no radiative-transfer solver; the linear system is ``scipy.linalg.lu_factor``
(dense, a few hundred cells).
"""

from __future__ import annotations

import numpy as np
from scipy import linalg
from scipy.special import expn

N_FRESNEL = 48  # Gauss nodes of the Fresnel part of the reflected kernel and of the exitance


def depth_grid(h0: float = 0.002, growth: float = 1.06, h_max: float = 1.0, depth: float = 400.0) -> np.ndarray:
    """Cell edges from 0 to ``depth``: ``h0`` at the surface, growing by ``growth`` up to ``h_max``."""
    edges = [0.0]
    h = h0
    while edges[-1] < depth:
        edges.append(edges[-1] + h)
        h = min(h * growth, h_max)
    return np.array(edges)


def _e2_interval(d0, d1) -> np.ndarray:
    """int_{d0}^{d1} E_1(t) dt = E_2(d0) - E_2(d1) for 0 <= d0 <= d1."""
    return expn(2, d0) - expn(2, d1)


def _e1_abs_antiderivative(t) -> np.ndarray:
    """An antiderivative of E_1(|t|) over the whole line: sign(t) (1 - E_2(|t|)) (E_2' = -E_1, E_2(0) = 1)."""
    return np.sign(t) * (1.0 - expn(2, np.abs(t)))


class HalfSpaceTransport:
    """Eq. (1)-(2) for one eta on a fixed depth grid; :meth:`solve` for one alpha and entering distribution.

    ``transmittance_in(m)``: ``T_in`` at inside cosines m (``split.inside_transmittance``).
    """

    def __init__(self, eta: float, transmittance_in, edges: np.ndarray | None = None):
        self.eta = float(eta)
        self.edges = depth_grid() if edges is None else np.asarray(edges, dtype=np.float64)
        a, b = self.edges[:-1], self.edges[1:]
        self.h = b - a
        self.z = 0.5 * (a + b)
        # -- K of (1), collocated at the cell centres --------------------------------------------------
        zi, aj, bj = self.z[:, None], a[None, :], b[None, :]
        direct = _e1_abs_antiderivative(bj - zi) - _e1_abs_antiderivative(aj - zi)  # int_cell E_1(|z - z'|) dz'
        self.m_c = float(np.sqrt(max(1.0 - 1.0 / self.eta**2, 0.0)))
        refl = np.zeros_like(direct)
        if self.m_c > 0.0:  # total internal reflection below m_c: int_0^{m_c} e^{-d/m} dm/m = E_1(d/m_c)
            refl += self.m_c * _e2_interval((zi + aj) / self.m_c, (zi + bj) / self.m_c)
        x, w = np.polynomial.legendre.leggauss(N_FRESNEL)
        self.mf = self.m_c + (1.0 - self.m_c) * 0.5 * (x + 1.0)  # Fresnel part: m in [m_c, 1]
        self.wf = (1.0 - self.m_c) * 0.5 * w
        self.t_f = np.asarray(transmittance_in(self.mf), dtype=np.float64)
        r = 1.0 - self.t_f
        for mk, wk, rk in zip(self.mf, self.wf, r):
            if rk > 0.0:
                refl += wk * rk * (np.exp(-(zi + aj) / mk) - np.exp(-(zi + bj) / mk))
        self.K = 0.5 * (direct + refl)

    def uncollided(self, nu, p) -> np.ndarray:
        """phi_0 averaged over each cell, (cells, distributions): ``p`` (J, D) weights over the cosines nu (J,)."""
        a, b = self.edges[:-1, None], self.edges[1:, None]
        nu = np.asarray(nu, dtype=np.float64)[None, :]
        cell = (np.exp(-a / nu) - np.exp(-b / nu)) / self.h[:, None]  # (1/h) int e^{-z/nu}/nu dz
        return cell @ np.asarray(p, dtype=np.float64)

    def escape(self, m) -> np.ndarray:
        """(cells, len(m)): ``int_cell e^{-z/m} dz/m``, the cell's weight in (2) towards inside cosine m."""
        m = np.asarray(m, dtype=np.float64)[None, :]
        return np.exp(-self.edges[:-1, None] / m) - np.exp(-self.edges[1:, None] / m)

    def solve(self, alpha: float, phi0: np.ndarray, K_phi0: np.ndarray | None = None) -> np.ndarray:
        """phi_s of (1) for one alpha, (cells, distributions); ``K_phi0``: ``K @ phi0`` when the caller
        solves several alphas for the same entering light (it does not depend on alpha)."""
        lu = linalg.lu_factor(np.eye(len(self.z)) - alpha * self.K)
        return linalg.lu_solve(lu, alpha * (self.K @ phi0 if K_phi0 is None else K_phi0))

    def solve_albedos(self, alphas, phi0: np.ndarray, K_phi0: np.ndarray | None = None) -> np.ndarray:
        """phi_s of (1) for every alpha in ``alphas``, (len(alphas), cells, distributions): :meth:`solve` for
        many albedos through one eigendecomposition of K, ``(I - alpha K)^-1 = V (I - alpha W)^-1 V^-1``,
        instead of one dense LU per albedo.  K is similar to a symmetric positive operator (the half-space's
        kernel), so W and V come out real and V well conditioned (cond 24 on the split's 491-cell grid at
        eta 1.3; the answers within 4e-12 of the LU's, 0.17 against 0.57 s for 63 albedos); where they do
        not (complex W, cond(V) > 1e6), each albedo gets its LU as in :meth:`solve`."""
        alphas = np.asarray(alphas, dtype=np.float64)
        rhs = self.K @ phi0 if K_phi0 is None else K_phi0
        w, V = np.linalg.eig(self.K)
        if np.iscomplexobj(w) and np.abs(w.imag).max() > 0.0 or np.linalg.cond(V) > 1e6:
            return np.stack([self.solve(a, phi0, rhs) for a in alphas])
        w, V = w.real, V.real
        coef = np.linalg.solve(V, rhs)  # V^-1 K phi0
        return np.stack([a * (V * (1.0 / (1.0 - a * w))) @ coef for a in alphas])

    def exitance_weights(self) -> np.ndarray:
        """v (cells,) with :meth:`exitance` = ``alpha v . phi``: (2) integrated over the Fresnel part of the
        exit cosines (below m_c nothing leaves)."""
        return 0.5 * (self.escape(self.mf) @ (self.wf * self.t_f * self.mf))

    def exitance(self, alpha: float, phi) -> np.ndarray:
        """Power leaving per unit q (distributions,) from the emission ``alpha phi/(4 pi)`` by (2)."""
        L = alpha / (4.0 * np.pi) * (self.escape(self.mf).T @ phi)  # (m, D)
        return 2.0 * np.pi * np.einsum("m,m,m,md->d", self.wf, self.t_f, self.mf, L)
