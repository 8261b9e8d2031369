r"""Single and multiple scattering that add up: the first-scatter split of a locally homogeneous half-space.

Why a split is needed
---------------------
The diffusion solve's boundary source q (Wang et al. eq. 3, :mod:`..diffusion`) is *all* the light that
enters.  Its solution already returns, approximately, every order of scattering, the first one included;
adding a single-scattering pass on top of it counts the once-scattered light twice (docs/accuracy.md:
marble sphere 1.5 % -> 6.6 %, skin1 sphere 11 % -> 29 %).  Counting each path once needs the entering light
split into what scatters once and leaves (the single-scattering term) and what scatters more (the source
of the diffusion term) -- the classical *reduced-intensity split* of radiative transfer (Ishimaru, *Wave
Propagation and Scattering in Random Media*, 1978, ch. 7 and 9: ``L = L_ri + L_d``, the diffuse part
driven by the volume source ``sigma_s phi_ri`` of the uncollided light), as photon beam diffusion does it for
rendering (Habel, Christensen, Jarosz, *Photon Beam Diffusion*, EGSR 2013, sec. 4-5: single scattering
integrated along the refracted beam in closed form, multiple scattering from the first-scatter sources;
pbrt-v3 ``BeamDiffusionSS`` / ``BeamDiffusionMS``).

The medium is taken as locally homogeneous over a half-space at each surface point: the coefficients of
the surface node (per node, so heterogeneous media split node by node), plane boundary with index eta,
isotropic phase (g = 0, so ``sigma_s = sigma_s'``), ``sigma_t = sigma_a + sigma_s'`` and the single-scattering
albedo ``alpha = sigma_s'/sigma_t``.  Lengths in units of ``1/sigma_t``: every quantity below depends on
alpha and eta only, which is why it applies in dense media where the layer in which single scattering
happens (a mean free path: 0.3 mm in marble, 0.14 voxel of a 150 mm bunny) is far below a voxel or a graph
link -- the closed form needs no resolution of that layer at all.

Entering light (q, W/m^2 per unit area, after the Fresnel transmittance) has the angular distribution of
diffuse light refracted into the medium: outside cosine mu with weight ``F_t(mu) 2 mu``, inside cosine
``nu = sqrt(1 - (1 - mu^2)/eta^2)``; ``p_j`` below is that distribution, normalised.  That is the world's
light; a lamp's is a beam of one incidence, eq. (6).

**Single scattering** (exact for the half-space).  A beam entering with inside cosine nu carries
``q_j/nu e^{-z/nu}`` along its path; scattered isotropically at depth z and attenuated on its way back up
at inside cosine m, the radiance reaching the surface from inside is::

    L_in(m) = alpha q / (4 pi) * sum_j p_j / (m + nu_j)                                   (1)

(integrate ``alpha/(4 pi) (q/nu) e^{-z/nu} e^{-z/m} dz/m``).  It leaves with the Fresnel transmittance at
that angle and the 1/eta^2 of radiance crossing into air; seen from outside at cosine mu_o, with
``m = sqrt(1 - (1 - mu_o^2)/eta^2)`` (the view ray refracts)::

    L_ss(mu_o) = F_t(mu_o)/eta^2 * L_in(m(mu_o))                                        (2)

and the power it carries out is ``s(alpha) q`` with
``s = 2 pi int_0^1 L_in(m) T_in(m) m dm / q = alpha/2 int_0^1 T_in(m) m sum_j p_j/(m + nu_j) dm``.
Checked against a Monte Carlo random walk of the same half-space (``tests/test_scattering_split.py``):
0.0565 q against 0.0566 at alpha = 0.68, eta = 1.3.

**Multiple scattering.**  Light scattered once either leaves (above), or is reflected back by the boundary
(``R_in = 1 - T_in``), or travels deeper; scattered a second time it is the source of everything that
scatters more.  M(alpha), the power of that light that leaves per unit q, comes from the transport
solution of the half-space (:mod:`.half_space`: the integral equation of transport with the Fresnel
boundary, solved on a depth grid; against a random walk order by order to its noise,
``tests/test_scattering_split.py``), tabulated over alpha once per eta (0.6 s).

The diffusion approximation of the same M closes in closed form (kept as ``M_diffusion_table``, for the
comparison): ``S2(z) = alpha phi_1(z)`` with the once-scattered fluence
``phi_1(z) = int S1(z') K(z, z') dz'``, ``S1(z') = alpha sum_j p_j e^{-z'/nu_j}/nu_j`` and the plane kernel
of isotropic emission with one boundary reflection
``K = 1/2 int_0^1 [e^{-|z - z'|/m} + R_in(m) e^{-(z + z')/m}] dm/m``; a plane source at depth z sends
``e^{-sigma_tr z}/(1 + 2 A kappa sigma_tr)`` of its power out (``kappa = 1/(3 sigma_t)``,
``sigma_tr = sqrt(3 sigma_a sigma_t)``, ``A = (1 + F_dr)/(1 - F_dr)``, the boundary condition of eq. 2),
and with ``s = sigma_tr/sigma_t``::

    M(alpha) = alpha^2 / (1 + 2 A s/3) * sum_j p_j int_0^1 1/2 [D(m, nu_j) + R_in(m) m/((1 + s m)(m + nu_j))] dm
    D(m, nu) = 1/((1 + s m)(1 + s nu)) + (1/(1 + s nu) - m/(m + nu)) / (1 - s m)          (3)

It is 8.3 % over transport at alpha = 0.68 (skin1's blue) and 4.1 % at 0.84, 0.6 % under at 0.999
(eta = 1.3): the diffusion of light that has scattered only a few times, which the split no longer
inherits.

**On the graph.**  The graph's boundary-source solve of a half-space returns
``B(alpha) = (1 - F_dr) J+/q`` with ``J+ = (phi_0 - 2q)/(2(1 + F_dr))``,
``phi_0 = 4q/((1 - F_dr)(1 + 2 A kappa sigma_tr))`` (the planner's ``semi_infinite_albedo``).  So the
diffusion runs with the boundary source ``m(alpha) q``, ``m = M/B``: a half-space then returns exactly
``s + M`` -- single plus multiple, each path once, as transport returns them -- while the graph still
carries the light sideways through the object's real shape.  m is capped at ``1 - s`` (the source can
never exceed the light that did not leave by single scattering: energy bound), and where B vanishes
(alpha below ~0.27 at eta = 1.3, where the boundary-source diffusion returns nothing) m is the
once-scattered light that stays, ``alpha - s``.

**The direction in which multiple scattering leaves.**  The diffusion's output is isotropic inside
(``L_o = F_t J+/(pi eta^2)``, :func:`..radiance.outgoing_radiance`).  Without the split that is close to
transport where it matters most: at alpha -> 1 and eta = 1 a diffusely lit object is a white furnace,
equally bright in every direction.  With the split it is not: the once-scattered light leaves mostly at
grazing angles (eq. 1, ``1/(m + nu)``), so an isotropic remainder makes the sum too dark head-on and too
bright at the rim -- at alpha = 0.999, eta = 1, -4 % along the normal and +7 % at mu_o = 0.22 against the
random walk; on the marble sphere under a uniform world, -6 % along the normals.  The remainder leaves
instead with the angular shape of the light scattered two or more times, the emission integral of the
scatterings it comes from (every second and later scattering is fed by the fluence ``phi_s`` of light
scattered at least once, the transport solution's)::

    L_ms(m) = alpha/(4 pi) int_0^inf phi_s(z) e^{-z/m} dz/m                                           (4)

The output uses only its *shape*: normalised to the power the diffusion sends out,
``L_o = F_t J+/(pi eta^2) c(alpha, m)`` with ``2 pi int T_in c m dm = pi (1 - F_dr)`` (c = 1 is the
isotropic output), so power, the solve and the planner's budgets are unchanged; only the direction
moves.  Against the random walk, radiance per direction (10 bins, RMS): 3.9 % isotropic against 0.6 %
with eq. 4 at alpha = 0.999, eta = 1; at eta = 1.3, where Fresnel shapes both alike, within the walk's
noise either way.  This is the shape under diffuse light; a lamp's is eq. (6)'s.

**Light carried from elsewhere** leaves in neither: both are the half-space's, for light that entered at the
point itself.  Where the diffusion sends out more than the half-space returns of the point's own light
(``local``: ``M q_d + M_beam q_b``) -- around a lamp's terminator, on the shaded side, in shadowed hollows --
the rest arrived from inside, and leaves with the diffusion's own angular distribution at a boundary it
lights from inside (the P1 radiance ``phi/(4 pi) (1 + 3 F.w/phi)`` with the boundary condition's
``F_n = phi/(2A)``)::

    c_T(m) = (1 + 3m/(2A)) / Z,   2 pi int T_in c_T m dm = pi (1 - F_dr)                                   (9)

at equal power, blended with eq. 4/6's shape by the two parts' power (:meth:`HalfSpaceSplit.with_transported`).
At eta 1 it is ``(2 + 3m)/4``: 1.25 along the normal, where transport's Milne problem (light from a source
deep below, :mod:`.half_space`) gives 1.26 at alpha 0.999 (Chandrasekhar's 1.259); at grazing exit it is 4 %
high (``tests/test_scattering_split.py``).  On the skin sphere under a sun (docs/accuracy.md, Lamps) the
terminator band is 0.89-1.03 of the random walk at Final (0.78-0.86 with eq. 4's shape for all of the
output), and the profile from the lit pole to the terminator 5.3, 4.5, 7.8 % RMS (8.6, 10.0, 13.0 %); the Milne
problem's own shape, which sharpens as the albedo falls (2.3 along the normal at 0.68: light from deep
below), overshot green and blue near the terminator, where light arrives sideways.  Eq. 9 runs where the
lamps' light enters through the volume (:mod:`.beam_source`), the light it moves: under a world alone the
output beyond the local return is mostly diffusion's own excess over transport on a curved surface, and
reshaping it made the dark-sphere sweep 3-5 points brighter (docs/accuracy.md, issue 30).  The sky bounce's
light (:mod:`.interreflection`) keeps eq. 4's shape, as its one-solve block system is linear in phi.

**Where diffusion is invalid** (reduced albedo below the planner's 0.5, or too thin) the single-scattering
pass replaces it, and the orders after the first would be missing (17 % of the light of a 10 mm sphere at
albedo 0.2, eta 1.3, against a random walk; 39 % at 0.45).  The half-space gives their ratio to the
once-scattered light, direction by direction::

    rho(alpha, m) = L_ms(m) / L_ss(m) = 4 M(alpha) c(alpha, m) / ((1 - F_dr) alpha h(m))                  (5)

with ``h(m) = sum_j p_j/(m + nu_j)`` of eq. (1).  The pass's radiance times ``1 + rho`` is the frame's term
there (``frame.orders_after_the_first``): the pass carries the object's shape (a 10 mm sphere returns 25 %
more once-scattered light than a half-space, and 30-40 % more of the rest), the ratio the local depth
distribution of the orders, which is where the half-space and the sphere agree best (0.19 against the
walk's 0.21 at alpha 0.2, eta 1.3).  It vanishes in proportion to alpha as alpha -> 0.

**A lamp's beam: the split follows its incidence.**  A sun, point, spot or area lamp sends each surface
point a beam of one outside incidence cosine mu (inside ``nu(mu)``), not diffuse light, and the shares
depend on it: head-on light goes deeper, so less leaves after one scattering and more is absorbed;
grazing light stays near the surface.  Eq. (1)-(4) hold with ``p_j`` a single beam at ``nu``::

    s(alpha, mu) = alpha/2 int_0^1 T_in(m) m/(m + nu) dm,    L_in(m) = alpha q/(4 pi (m + nu)),
    m(alpha, mu) = M(alpha, mu)/B(alpha),    c(alpha, mu, m)                                          (6)

with M and c from the same transport solves (:mod:`.half_space` takes every entering distribution at
once: the diffuse one and ``N_BEAM`` beams, mu uniform in [0.02, 1]).  The light pass hands over the
lamps' part of q per surface node and its q-weighted mean incidence cosine
(``scene.lights.LampBeams``); the world's light (and the bounce) keeps the diffuse tables, and a node
lit by both mixes them in proportion to q (:meth:`HalfSpaceSplit.source_factors`,
:meth:`HalfSpaceSplit.output_terms`).  Against a random walk of a beam (``tests/test_scattering_split.py``,
200k paths): within 1.2 % in power and 0.6-1.6 % RMS per direction, where the diffuse tables were 18 %
too bright head-on and 20 % too dark at mu = 0.25 (eta 1, alpha 0.84), 8 % either way at eta 1.3,
alpha 0.68.  The Self-Occlusion block solve (:mod:`.interreflection`) takes the frame's direct light
with its own m, H q and phi0's shape c_v (``DirectLight``); the bounce's light stays diffuse.

Against transport (eta = 1.3, diffuse light; the corrected random walk of the tests): total returned
light at alpha = 0.68, 0.84, 0.96 (skin1's B, G, R) is 0.1255, 0.2287, 0.4628; diffusion alone gives
0.1285, 0.2445, 0.4805 (+2.4 %, +6.9 %, +3.8 %), the split 0.1253, 0.2290, 0.4633 (within 0.2 %).  On
the graph what remains is the object's shape: a real object is not a half-space.

Hand-written: scipy has no half-space transport; the integrals are 1D Gauss-Legendre quadratures
(64 nodes, tabulated over alpha once per eta), the transport solution :mod:`.half_space`'s.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from ..scene.fresnel import boundary_A, check_eta, diffuse_reflectance_internal, fresnel_transmittance
from .kernels import outgoing_partial_current

N_QUAD = 64
N_ALPHA = 513
N_TRANSPORT_ALPHA = 65  # transport solves (half_space.py): alpha uniform in sqrt(1 - alpha), like the others
N_SHAPE_M = 65  # inside cosines 0..1 of eq. (4)'s table
H_TABLE_FROM, H_TABLE_SIZE = 0.05, 8193  # HalfSpaceSplit._h's table over the inside cosine m
N_BEAM, BEAM_MU_MIN = 17, 0.02  # eq. (6)'s tables: outside incidence cosines of a lamp's beam, uniform in [0.02, 1]


def inside_transmittance(m, eta: float) -> np.ndarray:
    """Fresnel transmittance of light reaching the boundary from inside at inside cosine ``m``.

    Zero beyond the critical angle; otherwise ``F_t`` at the outside angle (reciprocity).
    """
    m = np.asarray(m, dtype=np.float64)
    s2 = (1.0 - m * m) * eta * eta
    ok = s2 < 1.0
    mu_out = np.sqrt(np.clip(1.0 - s2, 0.0, 1.0))
    return np.where(ok, fresnel_transmittance(mu_out, eta), 0.0)


def albedo_index(alpha, n: int, descending: bool = False) -> tuple:
    """Index and weight of ``alpha`` on a grid of ``n`` albedos uniform in ``u = sqrt(1 - alpha)``: the grid of
    every albedo table here and in :mod:`.beam_source` (their values have a square-root kink at alpha = 1).
    Ascending in u (alpha from 1 down to 0) unless ``descending`` (alpha from 0 up to 1); ``alpha`` is clipped
    to [0, 1].  Returns ``(i, t)``: the value lies between entries i and i + 1, at weight t on i + 1."""
    u = np.sqrt(1.0 - np.clip(np.asarray(alpha, dtype=np.float64), 0.0, 1.0))
    f = ((1.0 - u) if descending else u) * (n - 1)
    i = np.minimum(f.astype(np.int64), n - 2)
    return i, f - i


def refracted_cosine(mu_out, eta: float) -> np.ndarray:
    """Inside cosine of a ray that crosses the boundary at outside cosine ``mu_out``."""
    mu = np.clip(np.asarray(mu_out, dtype=np.float64), 0.0, 1.0)
    return np.sqrt(1.0 - (1.0 - mu * mu) / (eta * eta))


def semi_infinite_albedo(alpha_reduced, eta: float) -> np.ndarray:
    """Fraction of the transmitted light a half-space returns under our diffusion model.

    Solving eq. 1-2 for a half-space lit uniformly: phi(z) = phi0 exp(-sigma_tr z),
    phi0 = 4q/(1 - F_dr) / (1 + 2 A kappa sigma_tr) with kappa sigma_tr = sqrt((1 - alpha')/3);
    the exitant flux is (1 - F_dr) J+ with J+ = max(0, phi0 - 2q)/(2 (1 + F_dr)).
    """
    a = np.clip(np.asarray(alpha_reduced, dtype=np.float64), 0.0, 1.0)
    fdr = diffuse_reflectance_internal(eta)
    phi0 = 4.0 / ((1.0 - fdr) * (1.0 + 2.0 * boundary_A(eta) * np.sqrt((1.0 - a) / 3.0)))
    return (1.0 - fdr) * outgoing_partial_current(phi0, 1.0, fdr)



class HalfSpaceSplit:
    """The first-scatter split for one eta: tables over alpha of s (single), M (multiple), B and m.

    ``single_radiance(q, alpha, cos_o)`` is eq. (2); ``source_factor(alpha)`` the m that scales the
    diffusion's boundary source; ``single_escape(alpha)`` s.  alpha: (..., 3) arrays.
    """

    def __init__(self, eta: float, n_quad: int = N_QUAD, n_alpha: int = N_ALPHA):
        self.eta = eta = check_eta(float(eta))
        self._h_table = None  # _h's table over m, built on its first large call
        x, w = np.polynomial.legendre.leggauss(int(n_quad))
        self.x = 0.5 * (x + 1.0)
        self.w = 0.5 * w
        # entering distribution: outside cosine x with weight F_t(x) 2x, inside cosine nu
        p = fresnel_transmittance(self.x, eta) * 2.0 * self.x * self.w
        self.p = p / p.sum()
        self.nu = refracted_cosine(self.x, eta)
        self.t_in = inside_transmittance(self.x, eta)
        self.fdr = diffuse_reflectance_internal(eta)
        self.A = boundary_A(eta)
        # uniform in sqrt(1 - alpha): M and B have a square-root kink at alpha = 1 (marble: 0.999)
        self.alpha_grid = 1.0 - np.linspace(1.0, 0.0, int(n_alpha)) ** 2
        a = self.alpha_grid
        self.s_table = a * self._single_unit()
        self.M_diffusion_table = self._multiple(a)  # eq. 3: diffusion's M, for comparison (docs, tests)
        self._u_grid = np.sqrt(1.0 - a)
        self.B_table = self._boundary(a)
        self.shape_m = np.linspace(0.0, 1.0, N_SHAPE_M)
        self._shape_u = np.linspace(0.0, 1.0, N_TRANSPORT_ALPHA)
        self.beam_mu = np.linspace(BEAM_MU_MIN, 1.0, N_BEAM)  # eq. (6): a lamp's outside incidence cosine
        self.beam_nu = refracted_cosine(self.beam_mu, eta)
        self.s_beam_unit = 0.5 * (self.w * self.t_in * self.x / (self.x[None, :] + self.beam_nu[:, None])).sum(axis=1)
        key = transport_key(eta, int(n_quad))
        kept = _KEPT.get(key)
        if kept is None:
            kept = _KEPT[key] = self._transport(1.0 - self._shape_u**2)
        M_t, self.shape_table, M_b, self.beam_shape_table = kept
        self.M_table = np.interp(self._u_grid, self._shape_u, M_t)  # M is smooth in sqrt(1 - alpha)
        m = np.where(self.B_table > 1e-9, self.M_table / np.maximum(self.B_table, 1e-300), a - self.s_table)
        self.m_table = np.clip(np.minimum(m, 1.0 - self.s_table), 0.0, None)
        # eq. (6): the same per beam incidence, (alpha grid, N_BEAM)
        self.M_beam_table = np.stack([np.interp(self._u_grid, self._shape_u, M_b[:, k]) for k in range(N_BEAM)], 1)
        s_b = a[:, None] * self.s_beam_unit[None, :]
        m_b = np.where(self.B_table[:, None] > 1e-9, self.M_beam_table / np.maximum(self.B_table[:, None], 1e-300),
                       a[:, None] - s_b)
        self.m_beam_table = np.clip(np.minimum(m_b, 1.0 - s_b), 0.0, None)

    # -- the half-space integrals ------------------------------------------------------------
    def _h(self, m) -> np.ndarray:
        """sum_j p_j / (m + nu_j) (eq. 1 without alpha q / 4 pi).

        Per vertex of a render mesh this sum over the quadrature was most of the split's output time
        (1.3 s for 655 k vertices), so for m >= H_TABLE_FROM it is read from a table of the same sum
        on a uniform grid, linearly interpolated: since h'' <= 2 h / m^2, the relative error is below
        dm^2 / (4 m^2) <= 1.4e-6 there; below it (grazing exits at eta near 1, where h is steep) and for
        small calls the sum is exact.
        """
        m = np.asarray(m, dtype=np.float64)
        if m.size < 4096:
            return self._h_exact(m)
        if self._h_table is None:
            grid = np.linspace(H_TABLE_FROM, 1.0, H_TABLE_SIZE)
            self._h_table = (grid, self._h_exact(grid))
        grid, table = self._h_table
        out = np.interp(m, grid, table)
        low = m < H_TABLE_FROM
        if low.any():
            out[low] = self._h_exact(m[low])
        return out

    def _h_exact(self, m) -> np.ndarray:
        return (self.p / (np.asarray(m, dtype=np.float64)[..., None] + self.nu)).sum(axis=-1)

    def _single_unit(self) -> float:
        """s / alpha: the once-scattered power that leaves, per unit q and unit albedo."""
        return float(0.5 * np.sum(self.w * self.t_in * self.x * self._h(self.x)))

    def _multiple(self, alpha) -> np.ndarray:
        """M(alpha) of eq. (3), for an array of alpha."""
        a = np.asarray(alpha, dtype=np.float64)
        s = np.sqrt(3.0 * np.maximum(1.0 - a, 0.0))[:, None, None]
        m = self.x[None, :, None]
        nu = self.nu[None, None, :]
        den = 1.0 - s * m
        den = np.where(np.abs(den) < 1e-9, 1e-9, den)  # removable singularity at s m = 1
        direct = 1.0 / ((1.0 + s * m) * (1.0 + s * nu)) + (1.0 / (1.0 + s * nu) - m / (m + nu)) / den
        refl = (1.0 - self.t_in)[None, :, None] * m / ((1.0 + s * m) * (m + nu))
        inner = ((direct + refl) * (0.5 * self.w[None, :, None] * self.p[None, None, :])).sum(axis=(1, 2))
        return a * a / (1.0 + 2.0 * self.A * s[:, 0, 0] / 3.0) * inner

    def _boundary(self, alpha) -> np.ndarray:
        """B(alpha): the boundary-source diffusion's half-space return (our graph's model)."""
        return semi_infinite_albedo(alpha, self.eta)

    def _transport(self, alpha):
        """(M, c, M_beam, c_beam) from the transport solution of the half-space (:mod:`.half_space`), rows: alpha.

        M: the power that leaves after two or more scatterings, per unit q; c(alpha, m) on ``shape_m``:
        eq. (4), the angular shape of that light relative to the isotropic output at equal power.
        ``M_beam`` (alpha, N_BEAM) and ``c_beam`` (alpha, N_BEAM, m): the same for a beam entering at each
        outside cosine of ``beam_mu`` (eq. 6); the solve takes every entering distribution at once.
        Two depth grids, the second twice as coarse, combined by Richardson extrapolation (the
        discretisation error is second order in the cell size): within 0.1 % of a grid 7x finer.
        At alpha = 1 nothing is absorbed and M = 1 - s exactly (no solve: the deep field would need an
        infinite grid); at alpha = 0 nothing scatters twice.
        """
        from .half_space import HalfSpaceTransport, depth_grid

        alpha = np.asarray(alpha, dtype=np.float64)
        one = alpha >= 1.0
        solved = (alpha > 0.0) & ~one
        m_eval = np.clip(self.shape_m, 1e-6, None)
        # entering distributions: column 0 diffuse light (p over nu), then one beam per beam_nu
        nu = np.concatenate([self.nu, self.beam_nu])
        P = np.zeros((len(nu), 1 + N_BEAM))
        P[: len(self.nu), 0] = self.p
        P[len(self.nu):, 1:] = np.eye(N_BEAM)
        D = P.shape[1]
        runs = []
        for f in (1.0, 2.0):
            ht = HalfSpaceTransport(self.eta, lambda m: inside_transmittance(m, self.eta),
                                    depth_grid(h0=0.002 * f, growth=1.0 + 0.06 * f, h_max=1.0 * f))
            phi0 = ht.uncollided(nu, P)
            K_phi0 = ht.K @ phi0  # the same for every alpha
            phi_s = np.zeros((len(alpha), len(ht.z), D))
            phi_s[solved] = ht.solve_albedos(alpha[solved], phi0, K_phi0)  # one eigendecomposition, every alpha
            # every alpha's exitance and eq. (4)'s radiance at once (one product each, not one per alpha:
            # small multi-column products per alpha cost more in BLAS threading than they compute)
            M = alpha[:, None] * np.einsum("c,acd->ad", ht.exitance_weights(), phi_s)
            L = alpha[:, None, None] / (4.0 * np.pi) * np.einsum("cm,acd->adm", ht.escape(m_eval), phi_s)
            runs.append((M, L))
        M = (4.0 * runs[0][0] - runs[1][0]) / 3.0
        L = (4.0 * runs[0][1] - runs[1][1]) / 3.0
        M[one, 0] = 1.0 - alpha[one] * self._single_unit()
        M[one, 1:] = 1.0 - alpha[one, None] * self.s_beam_unit[None, :]
        # c = L pi (1 - F_dr) / M: 2 pi int T_in c m dm = pi (1 - F_dr), as the isotropic output
        c = np.where(M[..., None] > 1e-12, L * np.pi * (1.0 - self.fdr) / np.maximum(M[..., None], 1e-300), 1.0)
        if one.any():  # the limit of the largest solved alpha (the shape is continuous in alpha)
            c[one] = c[np.flatnonzero(solved)[np.argmax(alpha[solved])]]
        return M[:, 0], c[:, 0], M[:, 1:], c[:, 1:]

    # -- lookups --------------------------------------------------------------------------------
    def _lookup(self, table, alpha) -> np.ndarray:
        u = np.sqrt(1.0 - np.clip(np.asarray(alpha, dtype=np.float64), 0.0, 1.0))
        return np.interp(-u, -self._u_grid, table)

    def single_escape(self, alpha) -> np.ndarray:
        """s(alpha): the part of q that leaves after one scattering."""
        return self._lookup(self.s_table, alpha)

    def multiple_escape(self, alpha) -> np.ndarray:
        """M(alpha): the part of q that leaves after two or more scatterings (transport, :mod:`.half_space`)."""
        return self._lookup(self.M_table, alpha)

    def boundary_escape(self, alpha) -> np.ndarray:
        """B(alpha): what the boundary-source diffusion alone returns from a half-space."""
        return self._lookup(self.B_table, alpha)

    def source_factor(self, alpha) -> np.ndarray:
        """m(alpha): the diffusion's boundary source is m q when the single-scattering term runs."""
        return self._lookup(self.m_table, alpha)

    def _shape_index(self, alpha, cos_o) -> tuple:
        """The tables of eq. (4)'s shape over (sqrt(1 - alpha), m): index and weight in alpha, (n, 3) each,
        and in the inside cosine m of the exit, (n, 1) each; ``alpha`` (n, 3), ``cos_o`` (n,) outside."""
        m = refracted_cosine(np.clip(np.asarray(cos_o, dtype=np.float64), 0.0, 1.0), self.eta)
        i, tu = albedo_index(alpha, N_TRANSPORT_ALPHA)
        fm = np.clip(m, 0.0, 1.0) * (N_SHAPE_M - 1)
        j = np.minimum(fm.astype(np.int64), N_SHAPE_M - 2)[:, None]
        return i, tu, j, fm[:, None] - j

    def multiple_shape(self, alpha, cos_o) -> np.ndarray:
        """c of eq. (4): the factor on the isotropic output ``F_t J+/(pi eta^2)`` that gives the diffusion's
        light the direction of multiple scattering, at equal power.

        ``alpha`` (n, 3); ``cos_o`` (n,) outside cosine to the viewer.  Bilinear in (sqrt(1 - alpha), m);
        1 where the point faces away (the output is zero there anyway).
        """
        c = np.asarray(cos_o, dtype=np.float64)
        i, tu, j, tm = self._shape_index(alpha, c)
        T = self.shape_table
        lo = (1 - tm) * T[i, j] + tm * T[i, j + 1]
        hi = (1 - tm) * T[i + 1, j] + tm * T[i + 1, j + 1]
        out = (1 - tu) * lo + tu * hi
        return np.where((c > 0)[:, None], out, 1.0)

    def multiple_over_single(self, alpha, cos_o) -> np.ndarray:
        """Eq. (5): the half-space's radiance of light scattered two or more times over its once-scattered
        radiance, seen at outside cosine ``cos_o``,

            rho(alpha, m) = L_ms / L_ss = 4 M(alpha) c(alpha, m) / ((1 - F_dr) alpha h(m))

        (eq. 4's output ``F_t M q c/((1 - F_dr) pi eta^2)`` over eq. 2's ``F_t alpha q h(m)/(4 pi eta^2)``;
        q and the exit factor cancel).  Where diffusion is invalid the single-scattering pass, which sees
        the object's real shape, times rho stands in for the orders after the first.  ``alpha`` (n, 3);
        ``cos_o`` (n,); 0 where the point faces away or nothing scatters.
        """
        a = np.clip(np.asarray(alpha, dtype=np.float64), 0.0, 1.0)
        c = np.asarray(cos_o, dtype=np.float64)
        m = refracted_cosine(np.clip(c, 0.0, 1.0), self.eta)
        num = 4.0 * self.multiple_escape(a) * self.multiple_shape(a, c)
        den = (1.0 - self.fdr) * a * self._h(m)[:, None]
        return np.where((c > 0)[:, None] & (den > 1e-300), num / np.maximum(den, 1e-300), 0.0)

    def single_radiance(self, q, alpha, cos_o) -> np.ndarray:
        """Eq. (2): outgoing single-scattering radiance (W/(m^2 sr)) for entering light q (W/m^2).

        ``q``, ``alpha``: (n, 3); ``cos_o``: (n,) cosine between the normal and the direction to the viewer
        (outside); points facing away get 0.
        """
        c = np.asarray(cos_o, dtype=np.float64)
        m = refracted_cosine(c, self.eta)
        ft = np.where(c > 0, fresnel_transmittance(np.clip(c, 0.0, 1.0), self.eta), 0.0)
        k = ft * self._h(m) / (4.0 * np.pi * self.eta * self.eta)
        return np.asarray(q, dtype=np.float64) * np.clip(np.asarray(alpha, dtype=np.float64), 0.0, 1.0) * k[:, None]


    # -- eq. (6): a lamp's beam -------------------------------------------------------------------
    def _beam_weights(self, mu):
        """Index and weight of the outside incidence cosines ``mu`` (n,) on ``beam_mu``, (n, 1) each."""
        fm = (np.clip(np.asarray(mu, dtype=np.float64), BEAM_MU_MIN, 1.0) - BEAM_MU_MIN) / (1.0 - BEAM_MU_MIN)
        fm = fm * (N_BEAM - 1)
        k = np.minimum(fm.astype(np.int64), N_BEAM - 2)
        return k[:, None], (fm - k)[:, None]

    def _alpha_index(self, alpha) -> tuple:
        """Index and weight of ``alpha`` (n, C) on the fine alpha grid (uniform in sqrt(1 - alpha), descending)."""
        return albedo_index(alpha, len(self.alpha_grid), descending=True)

    @staticmethod
    def _beam_bilinear(table, i, tu, k, tk) -> np.ndarray:
        """A (alpha grid, N_BEAM) table at alpha index/weight ``i, tu`` (n, C) and incidence ``k, tk`` (n, 1),
        gathered from the flattened table."""
        T, nb = table.ravel(), table.shape[1]
        b = i * nb + k
        return (1.0 - tu) * ((1.0 - tk) * T[b] + tk * T[b + 1]) + tu * ((1.0 - tk) * T[b + nb] + tk * T[b + nb + 1])

    def _beam_shape(self, i, tu, k, tk, j, tm) -> np.ndarray:
        """Eq. (6)'s shape table, trilinear: alpha ``i, tu`` (n, C) on the transport grid, incidence ``k, tk``
        and exit cosine ``j, tm`` (n, 1), gathered from the flattened table."""
        T, nb, nm = self.beam_shape_table.ravel(), N_BEAM, N_SHAPE_M
        b = (i * nb + k) * nm + j
        out = 0.0
        for di, wi in ((0, 1.0 - tu), (nb * nm, tu)):
            for dk, wk in ((0, 1.0 - tk), (nm, tk)):
                bb = b + (di + dk)
                out = out + wi * wk * ((1.0 - tm) * T[bb] + tm * T[bb + 1])
        return out

    def lookup_beam(self, table, alpha, mu) -> np.ndarray:
        """Bilinear in (sqrt(1 - alpha), mu) of a (alpha grid, N_BEAM) table; alpha (n, C), mu (n,)."""
        return self._beam_bilinear(table, *self._alpha_index(alpha), *self._beam_weights(mu))

    def beam_single_escape(self, alpha, mu) -> np.ndarray:
        """s of a beam entering at outside cosine ``mu`` (n,): ``alpha/2 int T_in(m) m/(m + nu) dm`` (eq. 6)."""
        k, tk = self._beam_weights(mu)
        unit = (1.0 - tk) * self.s_beam_unit[k] + tk * self.s_beam_unit[k + 1]
        return np.clip(np.asarray(alpha, dtype=np.float64), 0.0, 1.0) * unit

    def beam_source_factor(self, alpha, mu) -> np.ndarray:
        """m of a beam entering at outside cosine ``mu`` (n,): its transport M over the graph's B (eq. 6)."""
        return self.lookup_beam(self.m_beam_table, alpha, mu)

    def beam_multiple_shape(self, alpha, cos_o, mu) -> np.ndarray:
        """c of eq. (4) for the light a beam at outside cosine ``mu`` sends out after two or more
        scatterings, seen at outside cosine ``cos_o``: trilinear in (sqrt(1 - alpha), mu, m)."""
        c = np.asarray(cos_o, dtype=np.float64)
        i, tu, j, tm = self._shape_index(alpha, c)
        out = self._beam_shape(i, tu, *self._beam_weights(mu), j, tm)
        return np.where((c > 0)[:, None], out, 1.0)

    def beam_single_radiance(self, q, alpha, cos_o, mu) -> np.ndarray:
        """Eq. (6)'s single scattering: eq. (2) for a beam at outside cosine ``mu`` (n,),
        ``F_t(mu_o)/eta^2 alpha q/(4 pi (m + nu))``; ``q``, ``alpha`` (n, C), ``cos_o`` (n,)."""
        c = np.asarray(cos_o, dtype=np.float64)
        m = refracted_cosine(c, self.eta)
        nu = refracted_cosine(np.clip(np.asarray(mu, dtype=np.float64), BEAM_MU_MIN, 1.0), self.eta)
        ft = np.where(c > 0, fresnel_transmittance(np.clip(c, 0.0, 1.0), self.eta), 0.0)
        k = ft / ((m + nu) * 4.0 * np.pi * self.eta * self.eta)
        return np.asarray(q, dtype=np.float64) * np.clip(np.asarray(alpha, dtype=np.float64), 0.0, 1.0) * k[:, None]

    # -- diffuse light and the lamps' beams together ---------------------------------------------
    def _parts(self, q, beam):
        """(q_diffuse, q_beam, mu) of the entering light q (n, C) and ``beam`` = (q_beam, mu) or None."""
        q = np.asarray(q, dtype=np.float64)
        if beam is None:
            return q, None, None
        q_b = np.minimum(np.asarray(beam[0], dtype=np.float64), np.maximum(q, 0.0))
        return q - q_b, q_b, np.asarray(beam[1], dtype=np.float64)

    def _mixed(self, diffuse, beam_f, q, beam):
        """(diffuse q_d + beam q_b) / q where q > 0, else the diffuse factor: a factor per unit q."""
        q_d, q_b, mu = self._parts(q, beam)
        if q_b is None:
            return diffuse
        q = np.asarray(q, dtype=np.float64)
        mixed = (diffuse * q_d + beam_f(mu) * q_b) / np.where(q > 0, q, 1.0)
        return np.where(q > 0, mixed, diffuse)

    def source_factors(self, alpha, q, beam=None, beam_in_volume: bool = False, beam_at_surface=None) -> np.ndarray:
        """The diffusion's source per unit entering light q (n, C): ``m(alpha)`` for diffuse light, eq. (6)'s
        ``m(alpha, mu)`` for the part ``beam`` = (q_beam, mu) of q that came from lamps -- or, with
        ``beam_in_volume``, where that part enters the diffusion as a volume source (:mod:`.beam_source`), none
        of it but ``beam_at_surface`` (n, C) per unit q_beam: the beam's shallowest collisions, which the graph
        takes at the boundary (:func:`.beam_source.shallow_to_boundary`)."""
        if beam_in_volume:
            beam_f = (lambda mu: 0.0) if beam_at_surface is None else (lambda mu: beam_at_surface)
        else:
            beam_f = lambda mu: self.beam_source_factor(alpha, mu)  # noqa: E731
        return self._mixed(self.source_factor(alpha), beam_f, q, beam)

    def single_escapes(self, alpha, q, beam=None) -> np.ndarray:
        """The once-scattered light that leaves per unit q (n, C), diffuse and beam parts as in :meth:`source_factors`."""
        return self._mixed(self.single_escape(alpha), lambda mu: self.beam_single_escape(alpha, mu), q, beam)

    def local_return(self, q, alpha, beam=None) -> np.ndarray:
        """The power (per unit area, as q) a half-space sends back after two or more scatterings of the light q
        that enters at the point itself: ``M(alpha) q_d + M_beam(alpha, mu) q_b`` (transport, eqs. 4 and 6);
        ``alpha``, ``q`` (n, C), ``beam`` = (q_beam, mu) or None."""
        q_d, q_b, mu = self._parts(q, beam)
        a = np.clip(np.asarray(alpha, dtype=np.float64), 0.0, 1.0)
        out = self.multiple_escape(a) * q_d
        if q_b is not None:
            out += self.lookup_beam(self.M_beam_table, a, mu) * q_b
        return out

    def transported_shape(self, cos_o) -> np.ndarray:
        """c of eq. (9): the diffusion's own angular distribution at the boundary, for the light it carries to a
        point from elsewhere, at outside cosines ``cos_o`` (n,); normalised like eq. (4)'s c (equal power)."""
        m = refracted_cosine(np.clip(np.asarray(cos_o, dtype=np.float64), 0.0, 1.0), self.eta)
        return (1.0 + 1.5 * m / self.A) / self._transported_norm()

    def _transported_norm(self) -> float:
        """2 int T_in (1 + 3m/(2A)) m dm / (1 - F_dr), Gauss-Legendre from the critical cosine (T_in = 0 below
        it: a kink a rule over [0, 1] would straddle) to 1."""
        z = getattr(self, "_z_transported", None)
        if z is None:
            m_c = np.sqrt(max(0.0, 1.0 - 1.0 / (self.eta * self.eta)))
            x, w = np.polynomial.legendre.leggauss(64)
            m = m_c + (1.0 - m_c) * 0.5 * (x + 1.0)
            integral = float(np.sum((1.0 - m_c) * 0.5 * w * inside_transmittance(m, self.eta)
                                    * (1.0 + 1.5 * m / self.A) * m))
            z = self._z_transported = 2.0 * integral / (1.0 - self.fdr)
        return z

    def with_transported(self, shape, local, out_power, cos_o) -> np.ndarray:
        """Eq. (9): the output's shape where the diffusion sends out ``out_power`` (n, C; ``(1 - F_dr) J+``) of
        which ``local`` (:meth:`local_return`) is the half-space's return of the point's own light, with the
        split's ``shape`` (eqs. 4, 6); the rest, carried from elsewhere, leaves with :meth:`transported_shape`.
        ``cos_o`` (n,) per point or one number for all."""
        P = np.asarray(out_power, dtype=np.float64)
        rest = np.subtract(P, local)
        np.maximum(rest, 0.0, out=rest)
        tot = np.maximum(P, local)
        c = np.asarray(self.transported_shape(cos_o))
        out = np.subtract(tot, rest)  # per render-mesh vertex: in place, each temporary costs
        out *= shape
        rest *= c[:, None] if c.ndim else c
        out += rest
        ok = tot > 0
        np.divide(out, tot, out=out, where=ok)
        if not ok.all():
            out[~ok] = np.broadcast_to(shape, out.shape)[~ok]
        return out

    def output_terms(self, q, alpha, cos_o, beam=None, beam_in_volume: bool = False):
        """``(shape, single)`` at points seen at outside cosine ``cos_o``: the factor c on the diffusion's
        isotropic output (eq. 4; the beams' shapes weighted by the source each feeds) and the single-scattering
        radiance (eq. 2 for the diffuse part, eq. 6 for each beam).  With ``beam_in_volume`` the beams feed
        the diffusion through the volume (:mod:`.beam_source`), not through the local boundary source, and
        the light the diffusion carries to a point has no local beam's shape: it leaves with the diffuse
        light's (measured on the skin sphere under a sun: the terminator band 0.73 of the walk with the
        beam's shape, 0.81 with the diffuse one; the lit cap 0.99 and 1.03).

        Per vertex of a render mesh this is the split's output cost, so with beams the lookups of
        :meth:`source_factor`, :meth:`beam_source_factor` and :meth:`beam_multiple_shape` run only where a
        lamp's light arrives, sharing their grid indices, as gathers from the flattened tables (the
        per-term calls took 0.9 s for 655 k vertices; ``tests/test_scattering_split.py`` checks this
        against them)."""
        q_d, q_b, mu = self._parts(q, beam)
        shape = self.multiple_shape(alpha, cos_o)
        single = self.single_radiance(q_d, alpha, cos_o)
        if q_b is None:
            return shape, single
        lit = np.flatnonzero(q_b.max(axis=1) > 0)  # where a lamp's light arrives
        if lit.size == 0:
            return shape, single
        a = np.clip(np.asarray(alpha, dtype=np.float64)[lit], 0.0, 1.0)
        c = np.asarray(cos_o, dtype=np.float64)[lit]
        qd, qb, mu = q_d[lit], q_b[lit], np.asarray(mu)[lit]
        ia, ta = self._alpha_index(a)
        it, tt, j, tm = self._shape_index(a, c)  # the transport grid, ascending in sqrt(1 - alpha)
        k, tk = self._beam_weights(mu)
        m_d = (1.0 - ta) * self.m_table[ia] + ta * self.m_table[ia + 1]
        m_b = self._beam_bilinear(self.m_beam_table, ia, ta, k, tk)
        c_d = shape[lit]
        c_b = np.where((c > 0)[:, None], self._beam_shape(it, tt, k, tk, j, tm), 1.0)
        w_d, w_b = m_d * qd, (0.0 if beam_in_volume else m_b) * qb
        w = w_d + w_b
        shape[lit] = np.where(w > 0, (w_d * c_d + w_b * c_b) / np.where(w > 0, w, 1.0), c_d)
        single[lit] += self.beam_single_radiance(qb, a, c, mu)
        return shape, single


TRANSPORT_FORMAT = 2  # bump when _transport's grids or rule change: kept tables of another format are ignored
_KEPT: dict = {}  # transport_key -> (M, c): the transport tables of this process, and those a bake cache carried


def transport_key(eta: float, n_quad: int = N_QUAD) -> str:
    """What the transport tables of :class:`HalfSpaceSplit` depend on: eta, the quadrature, the grids."""
    return (f"half-space transport {TRANSPORT_FORMAT}: eta {float(eta)!r}, "
            f"{n_quad} / {N_TRANSPORT_ALPHA} / {N_SHAPE_M} / {N_BEAM}")


def transport_tables(eta: float) -> dict:
    """The transport tables for ``eta`` as arrays a bake cache keeps (``cache.save_bake(etas=...)``):
    the 63 half-space solves behind them are most of a cold frame's set-up (0.6 s), and a render farm
    starts every frame cold."""
    split = half_space_split(eta)
    M_t, c, M_b, c_b = _KEPT[transport_key(split.eta)]
    key = np.frombuffer(transport_key(split.eta).encode("utf-8"), dtype=np.uint8)
    return {"key": key, "M": np.asarray(M_t, dtype=np.float64), "c": np.asarray(c, dtype=np.float64),
            "M_beam": np.asarray(M_b, dtype=np.float64), "c_beam": np.asarray(c_b, dtype=np.float64)}


def has_transport_tables(eta: float) -> bool:
    """Whether this process holds the transport tables for ``eta`` (solved here or adopted from a bake cache)."""
    return transport_key(check_eta(eta)) in _KEPT


def adopt_transport_tables(key: str, M, c, M_beam=None, c_beam=None) -> bool:
    """Keep tables a bake cache carried; False (ignored) when they are of another format or quadrature
    than this code's.  Raises ``ValueError`` for tables of this format with the wrong shape or values
    (or without the beam tables of eq. 6)."""
    if not key.startswith(f"half-space transport {TRANSPORT_FORMAT}: ") or not key.endswith(
            f", {N_QUAD} / {N_TRANSPORT_ALPHA} / {N_SHAPE_M} / {N_BEAM}"):
        return False
    if M_beam is None or c_beam is None:
        raise ValueError("the beam tables (eq. 6) are missing")
    M, c = np.asarray(M, dtype=np.float64), np.asarray(c, dtype=np.float64)
    M_b, c_b = np.asarray(M_beam, dtype=np.float64), np.asarray(c_beam, dtype=np.float64)
    want = {"M": (N_TRANSPORT_ALPHA,), "c": (N_TRANSPORT_ALPHA, N_SHAPE_M), "M_beam": (N_TRANSPORT_ALPHA, N_BEAM),
            "c_beam": (N_TRANSPORT_ALPHA, N_BEAM, N_SHAPE_M)}
    got = {"M": M.shape, "c": c.shape, "M_beam": M_b.shape, "c_beam": c_b.shape}
    if got != want:
        raise ValueError(f"transport tables have shapes {got}, expected {want}")
    for T in (M, c, M_b, c_b):
        if not np.all(np.isfinite(T)) or T.min() < 0:
            raise ValueError("transport tables hold values outside their range (NaN, or negative)")
    if M.max() > 1 or M_b.max() > 1:
        raise ValueError("transport tables hold values outside their range (M above 1)")
    _KEPT.setdefault(key, (M, c, M_b, c_b))
    return True


@lru_cache(maxsize=8)
def half_space_split(eta: float) -> HalfSpaceSplit:
    """The tables for one eta (cached: a few ms to build)."""
    return HalfSpaceSplit(eta)


def albedo(sigma_a, sigma_s) -> np.ndarray:
    """Single-scattering albedo sigma_s'/(sigma_a + sigma_s') (g = 0), per node and channel."""
    sa = np.asarray(sigma_a, dtype=np.float64)
    ss = np.asarray(sigma_s, dtype=np.float64)
    return ss / np.maximum(sa + ss, 1e-300)
