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
``nu = sqrt(1 - (1 - mu^2)/eta^2)``; ``p_j`` below is that distribution, normalised.  (The exact
direction of each light would change the angular shape of the single-scattering term, not its power;
using the same q as the diffusion keeps shadows, self-occlusion and the interreflection bounce alike.)

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
0.0567 q against 0.0566 at alpha = 0.68, eta = 1.3.

**Multiple scattering.**  Light scattered once either leaves (above), or is reflected back by the boundary
(``R_in = 1 - T_in``), or travels deeper; scattered a second time it is the source of everything that
scatters more: ``S2(z) = alpha phi_1(z)`` with ``phi_1`` the once-scattered fluence,
``phi_1(z) = int S1(z') K(z, z') dz'``, ``S1(z') = alpha sum_j p_j e^{-z'/nu_j}/nu_j`` and the plane kernel
of isotropic emission with one boundary reflection
``K = 1/2 int_0^1 [e^{-|z - z'|/m} + R_in(m) e^{-(z + z')/m}] dm/m``.  In the diffusion approximation
(``kappa = 1/(3 sigma_t)``, ``sigma_tr = sqrt(3 sigma_a sigma_t)``, the boundary condition of eq. 2 with
``A = (1 + F_dr)/(1 - F_dr)``) a plane source at depth z sends ``e^{-sigma_tr z}/(1 + 2 A kappa sigma_tr)``
of its power out through the surface (the half-space Green's function: image term chosen to satisfy the
boundary condition).  With ``s = sigma_tr/sigma_t`` all integrals close::

    M(alpha) = alpha^2 / (1 + 2 A s/3) * sum_j p_j int_0^1 1/2 [D(m, nu_j) + R_in(m) m/((1 + s m)(m + nu_j))] dm
    D(m, nu) = 1/((1 + s m)(1 + s nu)) + (1/(1 + s nu) - m/(m + nu)) / (1 - s m)          (3)

the power of multiple scattering that leaves, per unit q.  This is the diffusion of the once-scattered
light's source *minus* what the single-scattering term already outputs: the escaping part of phi_1 never
becomes S2.

**On the graph.**  The graph's boundary-source solve of a half-space returns
``B(alpha) = (1 - F_dr) J+/q`` with ``J+ = (phi_0 - 2q)/(2(1 + F_dr))``,
``phi_0 = 4q/((1 - F_dr)(1 + 2 A kappa sigma_tr))`` (the planner's ``semi_infinite_albedo``).  So the
diffusion runs with the boundary source ``m(alpha) q``, ``m = M/B``: a half-space then returns exactly
``s + M`` -- single plus multiple, each path once -- while the graph still carries the light sideways
through the object's real shape.  m is capped at ``1 - s`` (the source can never exceed the light that
did not leave by single scattering: energy bound), and where B vanishes (alpha below ~0.27 at eta = 1.3,
where the boundary-source diffusion returns nothing) m is the once-scattered light that stays,
``alpha - s``.

**The direction in which multiple scattering leaves.**  The diffusion's output is isotropic inside
(``L_o = F_t J+/(pi eta^2)``, :func:`..radiance.outgoing_radiance`).  Without the split that is close to
transport where it matters most: at alpha -> 1 and eta = 1 a diffusely lit object is a white furnace,
equally bright in every direction.  With the split it is not: the once-scattered light leaves mostly at
grazing angles (eq. 1, ``1/(m + nu)``), so an isotropic remainder makes the sum too dark head-on and too
bright at the rim -- at alpha = 0.999, eta = 1, -4 % along the normal and +7 % at mu_o = 0.22 against the
random walk (``tests/test_scattering_split.py``); on the marble sphere under a uniform world, -6 % along
the normals.  The remainder leaves instead with the angular shape of the light scattered two or more
times.  Its radiance reaching the boundary from inside is the emission integral of the scatterings it
comes from (every second and later scattering is fed by the fluence ``phi_>=1`` of light scattered at
least once)::

    L_ms(m) = alpha/(4 pi) int_0^inf phi_>=1(z) e^{-z/m} dz/m,    phi_>=1 = phi_1 + phi_>=2         (4)

with ``phi_1`` the once-scattered fluence (exact, in closed form over the incoming cosines, below) and
``phi_>=2`` the half-space diffusion of the second-scatter source ``alpha phi_1``: Green's function
``3/(2 s) [e^{-s|z - z'|} + r e^{-s (z + z')}]``, ``r = (2 A s/3 - 1)/(1 + 2 A s/3)`` from the boundary
condition of eq. 2.  The output uses only its *shape*: normalised to the power the diffusion sends out,
``L_o = F_t J+/(pi eta^2) c(alpha, m)`` with ``2 pi int T_in c m dm = pi (1 - F_dr)`` (c = 1 is the isotropic
output), so power, the solve and the planner's budgets are unchanged; only the direction moves.  Against
the random walk (same test): the sum head-on at alpha = 0.999, eta = 1 is -0.2 % instead of -4 %, at the
rim -1.0 % instead of +7 %; at eta = 1.3, where Fresnel shapes both alike, the two are within 1 %.

Against transport (the Monte Carlo random walk, eta = 1.3, diffuse light; docs/accuracy.md): total
returned light at alpha = 0.68, 0.84, 0.96 (skin1's B, G, R) is 0.121, 0.219, 0.441; diffusion alone
gives 0.129, 0.245, 0.481 (+6 %, +12 %, +9 %), the split 0.131, 0.236, 0.463 (+8 %, +8 %, +5 %); at
alpha -> 1 (marble) both tend to the same total, and the split's difference is where and in which
direction the once-scattered light leaves.

Hand-written: scipy has no half-space transport; the integrals are 1D Gauss-Legendre quadratures
(64 nodes, tabulated over alpha once per eta), eq. (4) Gauss-Laguerre in z/m over fluences tabulated on a
graded depth grid (150 depths to 40 mean free paths: the shape agrees with 1,200 depths to 60 to 1e-4).
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from ..fresnel import boundary_A, check_eta, diffuse_reflectance_internal, fresnel_transmittance

N_QUAD = 64
N_ALPHA = 513
N_SHAPE_ALPHA = 65  # eq. (4)'s table: alpha uniform in sqrt(1 - alpha), like the others
N_SHAPE_M = 65  # inside cosines 0..1
N_DEPTH = 150  # graded depths of eq. (4)'s fluences
DEPTH_MAX = 40.0  # mean free paths: e^{-z/m} <= e^{-40}


def inside_transmittance(m, eta: float) -> np.ndarray:
    """Fresnel transmittance of light reaching the boundary from inside at inside cosine ``m``.

    Zero beyond the critical angle; otherwise ``F_t`` at the outside angle (reciprocity).
    """
    m = np.asarray(m, dtype=np.float64)
    s2 = (1.0 - m * m) * eta * eta
    ok = s2 < 1.0
    mu_out = np.sqrt(np.clip(1.0 - s2, 0.0, 1.0))
    return np.where(ok, fresnel_transmittance(mu_out, eta), 0.0)


def refracted_cosine(mu_out, eta: float) -> np.ndarray:
    """Inside cosine of a ray that crosses the boundary at outside cosine ``mu_out``."""
    mu = np.clip(np.asarray(mu_out, dtype=np.float64), 0.0, 1.0)
    return np.sqrt(1.0 - (1.0 - mu * mu) / (eta * eta))


class HalfSpaceSplit:
    """The first-scatter split for one eta: tables over alpha of s (single), M (multiple), B and m.

    ``single_radiance(q, alpha, cos_o)`` is eq. (2); ``source_factor(alpha)`` the m that scales the
    diffusion's boundary source; ``single_escape(alpha)`` s.  alpha: (..., 3) arrays.
    """

    def __init__(self, eta: float, n_quad: int = N_QUAD, n_alpha: int = N_ALPHA):
        self.eta = eta = check_eta(float(eta))
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
        self.M_table = self._multiple(a)
        self._u_grid = np.sqrt(1.0 - a)
        self.B_table = self._boundary(a)
        m = np.where(self.B_table > 1e-9, self.M_table / np.maximum(self.B_table, 1e-300), a - self.s_table)
        self.m_table = np.clip(np.minimum(m, 1.0 - self.s_table), 0.0, None)
        self.shape_m = np.linspace(0.0, 1.0, N_SHAPE_M)
        self._shape_u = np.linspace(0.0, 1.0, N_SHAPE_ALPHA)
        self.shape_table = self._multiple_shape(1.0 - self._shape_u**2)

    # -- the half-space integrals ------------------------------------------------------------
    def _h(self, m) -> np.ndarray:
        """sum_j p_j / (m + nu_j) (eq. 1 without alpha q / 4 pi)."""
        m = np.asarray(m, dtype=np.float64)
        return (self.p / (m[..., None] + self.nu)).sum(axis=-1)

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
        s = np.sqrt(3.0 * np.maximum(1.0 - np.asarray(alpha, dtype=np.float64), 0.0))
        phi0 = 4.0 / ((1.0 - self.fdr) * (1.0 + 2.0 * self.A * s / 3.0))
        return (1.0 - self.fdr) * np.maximum(phi0 - 2.0, 0.0) / (2.0 * (1.0 + self.fdr))

    def _once_scattered_fluence(self, z) -> np.ndarray:
        """phi_1(z)/alpha per unit q: the fluence of light scattered exactly once (eq. 3's ``int S1 K dz'``).

        Integrating the source ``sum_j p_j e^{-z'/nu_j}/nu_j`` against the kernel K in z' closes per (m, nu):
        ``(e^{-z/nu} - e^{-z/m})/(nu - m)`` from above z (``z e^{-z/m}/m^2`` at nu = m),
        ``e^{-z/nu}/(m + nu)`` from below and ``R_in(m) e^{-z/m}/(m + nu)`` by one boundary reflection.
        """
        Z = np.asarray(z, dtype=np.float64)[:, None, None]
        m = self.x[None, :, None]
        nu = self.nu[None, None, :]
        d = nu - m
        same = np.abs(d) < 1e-12
        above = np.where(same, Z * np.exp(-Z / m) / (m * m),
                         (np.exp(-Z / nu) - np.exp(-Z / m)) / np.where(same, 1.0, d))
        below = np.exp(-Z / nu) / (m + nu)
        refl = (1.0 - self.t_in)[None, :, None] * np.exp(-Z / m) / (m + nu)
        return (0.5 * (above + below + refl) * (self.w[None, :, None] * self.p[None, None, :])).sum(axis=(1, 2))

    def _multiple_shape(self, alpha) -> np.ndarray:
        """c(alpha, m) of eq. (4) on ``shape_m`` (rows: alpha): the angular shape of the light that leaves
        after two or more scatterings, relative to the isotropic output, at equal power."""
        z = DEPTH_MAX * np.linspace(0.0, 1.0, N_DEPTH) ** 2
        wz = np.zeros_like(z)
        wz[1:] += 0.5 * np.diff(z)
        wz[:-1] += 0.5 * np.diff(z)
        phi1 = self._once_scattered_fluence(z)  # times alpha
        u, wu = np.polynomial.laguerre.laggauss(48)
        m_all = np.concatenate([self.x, self.shape_m])  # Gauss nodes (normalisation), then the table's m
        mz = m_all[:, None] * u[None, :]
        out = np.empty((len(alpha), len(self.shape_m)))
        for i, a in enumerate(np.asarray(alpha, dtype=np.float64)):
            s = np.sqrt(3.0 * max(1.0 - a, 1e-12))
            r = (2.0 * self.A * s / 3.0 - 1.0) / (1.0 + 2.0 * self.A * s / 3.0)
            zz, zs = np.abs(z[:, None] - z[None, :]), z[:, None] + z[None, :]
            green = 1.5 / s * (np.exp(-s * zz) + r * np.exp(-s * zs))
            phi = a * phi1 + green @ (wz * a * a * phi1)  # phi_1 + phi_>=2 (the common alpha/(4 pi) dropped)
            L = (np.interp(mz, z, phi) * wu[None, :]).sum(axis=1)
            norm = 2.0 * np.sum(self.w * self.t_in * L[: len(self.x)] * self.x) / (1.0 - self.fdr)
            out[i] = L[len(self.x):] / norm if norm > 1e-300 else 1.0  # alpha = 0: nothing scatters twice
        return out

    # -- lookups --------------------------------------------------------------------------------
    def _lookup(self, table, alpha) -> np.ndarray:
        u = np.sqrt(1.0 - np.clip(np.asarray(alpha, dtype=np.float64), 0.0, 1.0))
        return np.interp(-u, -self._u_grid, table)

    def single_escape(self, alpha) -> np.ndarray:
        """s(alpha): the part of q that leaves after one scattering."""
        return self._lookup(self.s_table, alpha)

    def multiple_escape(self, alpha) -> np.ndarray:
        """M(alpha): the part of q that leaves after two or more scatterings (diffusion)."""
        return self._lookup(self.M_table, alpha)

    def boundary_escape(self, alpha) -> np.ndarray:
        """B(alpha): what the boundary-source diffusion alone returns from a half-space."""
        return self._lookup(self.B_table, alpha)

    def source_factor(self, alpha) -> np.ndarray:
        """m(alpha): the diffusion's boundary source is m q when the single-scattering term runs."""
        return self._lookup(self.m_table, alpha)

    def multiple_shape(self, alpha, cos_o) -> np.ndarray:
        """c of eq. (4): the factor on the isotropic output ``F_t J+/(pi eta^2)`` that gives the diffusion's
        light the direction of multiple scattering, at equal power.

        ``alpha`` (n, 3); ``cos_o`` (n,) outside cosine to the viewer.  Bilinear in (sqrt(1 - alpha), m);
        1 where the point faces away (the output is zero there anyway).
        """
        a = np.clip(np.asarray(alpha, dtype=np.float64), 0.0, 1.0)
        c = np.asarray(cos_o, dtype=np.float64)
        m = refracted_cosine(np.clip(c, 0.0, 1.0), self.eta)
        fu = np.sqrt(1.0 - a) * (N_SHAPE_ALPHA - 1)
        i = np.minimum(fu.astype(np.int64), N_SHAPE_ALPHA - 2)
        tu = fu - i
        fm = np.clip(m, 0.0, 1.0) * (N_SHAPE_M - 1)
        j = np.minimum(fm.astype(np.int64), N_SHAPE_M - 2)[:, None]
        tm = (fm - j[:, 0])[:, None]
        T = self.shape_table
        lo = (1 - tm) * T[i, j] + tm * T[i, j + 1]
        hi = (1 - tm) * T[i + 1, j] + tm * T[i + 1, j + 1]
        out = (1 - tu) * lo + tu * hi
        return np.where((c > 0)[:, None], out, 1.0)

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


@lru_cache(maxsize=8)
def half_space_split(eta: float) -> HalfSpaceSplit:
    """The tables for one eta (cached: a few ms to build)."""
    return HalfSpaceSplit(eta)


def albedo(sigma_a, sigma_s) -> np.ndarray:
    """Single-scattering albedo sigma_s'/(sigma_a + sigma_s') (g = 0), per node and channel."""
    sa = np.asarray(sigma_a, dtype=np.float64)
    ss = np.asarray(sigma_s, dtype=np.float64)
    return ss / np.maximum(sa + ss, 1e-300)
