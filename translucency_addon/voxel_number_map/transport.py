r"""The Voxel Number Map's transport kernel: a radiance, derived (Mochida et al., run-time step 2).

The poster computes

    L(x_out, w_out) = (1/pi) F_t(eta, w_out) int_S E(x_in) R_d(x_in, x_out) dx_in,   R_d = exp(-tau)

which is not a radiance: with E in W/m^2 and dx_in in m^2 the integral is a
power, and nothing falls off with the distance between x_in and x_out.  We
derive the kernel from single scattering, the regime the method assumes
("single-scattering effects are dominant"), per colour channel, isotropic
phase function (g = 0, so sigma_s = sigma_s' as everywhere in the engine).

**Exitance of once-scattered light.**  The flux density leaving the medium at a
surface point x_o (inside the boundary, before the Fresnel exit) is

    J+(x_o) = int_V sigma_s(x) Phi(x) / (4 pi) exp(-tau(x, x_o)) cos th_o(x) / |x - x_o|^2 dV     (1)

with Phi the fluence (W/m^2) of the light that entered unscattered and
th_o the angle between the outward normal at x_o and the direction from x
to x_o.  About x_o, dV = r^2 dr dw, and every direction w into the object
ends at a surface point x_i (the chord's far end; cavities have sigma = 0
and their walls do not refract, see below), whose patch subtends
dw = cos th_i dA_i / R^2 (R = |x_i - x_o|).  Exactly, then,

    J+(x_o) = int_S dA_i  cos th_i cos th_o / (4 pi R^2)  int_0^R sigma_s Phi exp(-tau(x, x_o)) dr       (2)

The Voxel Number Map's approximation is that the light on a chord is the
light that entered at the chord's two ends and travelled along it:

    Phi(x) ~ Phi_i exp(-tau(x_i, x)) + Phi_o exp(-(cos th_o / mu_o) tau(x_o, x))                        (3)

``Phi_i = F_t(mu_i) E_perp(x_i)`` is the light transmitted at x_i
(``E_perp``: irradiance on a plane facing the light, ``lights.light_irradiance``,
shadowed; mu_i = n_i . w_light).  For the first term the chord stands for the
light's direction inside (exact for light entering along the chord, and in the
optically thin limit whatever the direction); this keeps the pair kernel
independent of the lights, so a frame is one matrix-vector product.  The
second term is the light entering at x_o itself; for it the light's real
incidence mu_o is known, and ``cos th_o / mu_o`` is the exact ratio of depth
along the light to distance along the chord below a locally flat surface.
Since ``tau(x_i, x) + tau(x, x_o) = tau_io`` on the chord, the first term
integrates exactly, whatever the media along the chord:

    int_0^R sigma_s Phi_i exp(-tau(x_i, x) - tau(x, x_o)) dr = Phi_i tau_s,io exp(-tau_io)               (4)

(tau_s: the scattering depth, int sigma_s dr along the chord), and the second,
with the chord's mean albedo a = tau_s / tau and c = cos th_o / mu_o,

    int_0^R sigma_s Phi_o exp(-(1 + c) tau(x_o, x)) dr ~ Phi_o a (1 - exp(-(1 + c) tau_io)) / (1 + c)    (5)

(exact for a homogeneous chord).  On the surface voxels (area A_i):

    J+_o = sum_i A_i S_io Phi_i  +  rho_o(mu_o) Phi_o                                                    (6)
    S_io = cos th_i cos th_o tau_s,io exp(-tau_io) / (4 pi R_io^2)            (symmetric: one packed LUT)
    rho_o(mu) = sum_i A_i cos th_i cos th_o / (4 pi R_io^2) a_io (1 - exp(-(1 + c) tau_io)) / (1 + c)

and, assuming the exitant radiance is diffuse (L = J+/pi inside), the same
output query as the diffusion pass (``radiance.outgoing_radiance``):

    L_o(w_o) = F_t(n . w_o, eta) J+ / (pi eta^2)        W/(m^2 sr)                                        (7)

This is the poster's sum with R_d -> tau_s cos th_i cos th_o exp(-tau) / (4 pi R^2)
(1/m^2, falling off with distance and vanishing without scattering), E -> the
fluence Phi, plus the light scattered back near the point where it entered
(rho).  Checks: for a half-space, rho(mu) -> (a mu / 2)(1 - mu ln(1 + 1/mu)),
the exact single-scattering exitance; a chord through an opaque part has
tau = infinity, S = 0: the part casts its shadow inside the medium.

**Energy (out <= in).**  A surface voxel lit with fluence Phi_i sends
``A_i Phi_i (s_i + rho_i(mu_i))`` out (``s_i = sum_o A_o S_io``) and took in
``A_i E_i = A_i Phi_i mu_i``.  Approximation (3) does not fall with the
light's incidence, so at grazing light it could return more than came in; each
light's Phi_i is therefore scaled by ``min(1, mu_i / (s_i + rho_i(mu_i)))``
(the clamp acts only where ``mu_i < s_i + rho_i``, i.e. beyond ~75 deg
incidence for albedo 1: ``s_i <= a/(4e)``, ``rho_i <= a/4``).  The boundary
then lets ``(1 - F_dr,int) J+`` leave, so the power out never exceeds the
power in (``tests/test_voxel_number_map.py``).

**What it neglects.**  Multiple scattering (the method's premise; the
diffusion pass covers it); refraction of the rays at the outer surface and at
interfaces between media (straight chords, as the poster; its future work);
Fresnel reflection at inner interfaces and cavity walls; the angular shape of
the exitant radiance (diffuse exit, eq. 7); the light's real direction inside
for the chord sources (3); light that leaves a concave outer surface and
re-enters (the chord's stretch through the air counts as sigma = 0, without
Fresnel losses); opaque parts in the near-entry term (5), whose chords are
attenuated but not cut.  The brute-force single-scattering reference
(``single_scattering.reference``) has none of the approximations (3)-(5) and
(7); ``tests/test_voxel_number_map.py`` and ``docs/accuracy.md`` measure the
difference.

rho is tabulated at ``MU_NODES`` per surface voxel and channel and
interpolated linearly (below the first node it falls linearly to 0, as the
half-space formula does).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..scene.fresnel import diffuse_reflectance_external, fresnel_transmittance
from . import lut as lutmod

MU_NODES = np.array([0.02, 0.05, 0.1, 0.2, 0.35, 0.5, 0.7, 1.0])
PAIRS_PER_BLOCK = 200_000


@dataclass
class Coefficients:
    """Per-component coefficients (C, 3), per mm, and the voxel edge in mm."""

    sigma_t: np.ndarray
    sigma_s: np.ndarray
    h_mm: float


def pair_kernel(P, N, I, J, lengths, blocked, coef: Coefficients):
    """``(S (m, 3), G (m,), a (m, 3), tau (m, 3), cos_i, cos_j)`` for pairs (I, J) (eq. 6).

    ``P``/``N``: surface-voxel positions (object units) and normals; ``lengths``
    (C, m) chord lengths per component in voxel units; ``blocked`` (m,) bool.
    ``G = cos th_i cos th_o / (4 pi R^2)`` (1/units^2); S = G tau_s exp(-tau).
    This is the function the GLSL kernel (``gpu_shaders/voxel_number_map.glsl``) mirrors.
    """
    d = P[J] - P[I]
    R2 = np.einsum("ij,ij->i", d, d)
    R = np.sqrt(R2)
    dh = d / np.maximum(R, 1e-300)[:, None]
    cos_i = np.maximum(-np.einsum("ij,ij->i", N[I], dh), 0.0)
    cos_j = np.maximum(np.einsum("ij,ij->i", N[J], dh), 0.0)
    G = np.where(R2 > 0, cos_i * cos_j / (4.0 * np.pi * np.maximum(R2, 1e-300)), 0.0)
    tau = np.zeros((len(I), 3), dtype=np.float32)
    tau_s = np.zeros((len(I), 3), dtype=np.float32)
    for c, ln in enumerate(np.asarray(lengths)):  # tau = h sum_c sigma_c l_c, per channel
        ln32 = ln.astype(np.float32)[:, None]
        tau += ln32 * (coef.h_mm * coef.sigma_t[c]).astype(np.float32)
        tau_s += ln32 * (coef.h_mm * coef.sigma_s[c]).astype(np.float32)
    S = np.where(np.asarray(blocked)[:, None], np.float32(0.0), G.astype(np.float32)[:, None] * tau_s * np.exp(-tau))
    a = np.divide(tau_s, tau, out=np.zeros_like(tau), where=tau > 0)
    return S, G, a, tau, cos_i, cos_j


def near_entry_factor(a, tau, cos_o, mu):
    """``a (1 - exp(-(1 + c) tau)) / (1 + c)`` with ``c = cos_o / mu`` (eq. 5); broadcasts."""
    k = 1.0 + cos_o / mu
    return a * -np.expm1(-k * tau) / k


def _segment_sums(keys: np.ndarray, values: np.ndarray, n: int) -> np.ndarray:
    """Sum the columns of ``values`` (q, m) per key (m,) into (n, q) (one ``bincount`` per row)."""
    return np.stack([np.bincount(keys, weights=row, minlength=n) for row in values], axis=1)


@dataclass
class PreparedKernel:
    """Everything a frame needs for one material: the packed kernel, rho tables, clamp sums."""

    S: np.ndarray  # (3, n(n+1)/2) float32, packed upper triangle with diagonal (BLAS sspmv layout)
    rho: np.ndarray  # (n, len(MU_NODES), 3) rho_o(mu) per channel
    s: np.ndarray  # (n, 3) sum_o A_o S_io: the share of Phi_i that leaves through other voxels
    area: np.ndarray  # (n,) units^2
    n: int

    @property
    def nbytes(self) -> int:
        return int(self.S.nbytes + self.rho.nbytes + self.s.nbytes)

    def rho_at(self, mu: np.ndarray) -> np.ndarray:
        """rho_o at per-voxel incidences ``mu`` (n,) or (n, D) -> (n, 3) or (n, D, 3)."""
        mu = np.asarray(mu, dtype=np.float64)
        nodes = MU_NODES
        m = np.clip(mu, nodes[0], 1.0)
        k = np.clip(np.searchsorted(nodes, m) - 1, 0, len(nodes) - 2)
        t = (m - nodes[k]) / (nodes[k + 1] - nodes[k])
        rows = np.arange(self.n).reshape((-1,) + (1,) * (mu.ndim - 1))
        r = (1.0 - t)[..., None] * self.rho[rows, k] + t[..., None] * self.rho[rows, k + 1]
        below = np.clip(mu / nodes[0], 0.0, 1.0)  # rho ~ mu as mu -> 0
        return np.where((mu < nodes[0])[..., None], self.rho[rows, 0] * below[..., None], r)

    def clamp(self, mu: np.ndarray, rho=None) -> np.ndarray:
        """``min(1, mu / (s + rho(mu)))`` per voxel and channel: the power a voxel returns <= what it took in.

        ``rho``: :meth:`rho_at` of the same ``mu``, when the caller has it already."""
        mu = np.asarray(mu, dtype=np.float64)
        out = self.s.reshape((self.n,) + (1,) * (mu.ndim - 1) + (3,)) + (self.rho_at(mu) if rho is None else rho)
        return np.minimum(1.0, np.divide(mu[..., None], out, out=np.ones_like(out), where=out > 0))

    def product(self, x: np.ndarray) -> np.ndarray:
        """``J_o = sum_i S_io x_i`` per channel (x = A Phi), by BLAS's packed symmetric product."""
        from scipy.linalg import blas

        x = np.asarray(x, dtype=np.float32)
        out = np.empty((self.n, 3))
        for c in range(3):
            out[:, c] = blas.sspmv(self.n, 1.0, self.S[c], x[:, c], lower=1)
        return out


def prepare_kernel(surf, lengths: np.ndarray, blocked_bits: np.ndarray, coef: Coefficients,
                   progress=None) -> PreparedKernel:
    """Evaluate eq. 6 for every pair: the packed kernel S, the rho tables and the clamp sums s."""
    P = np.asarray(surf.position, dtype=np.float64)
    N = np.asarray(surf.normal, dtype=np.float64)
    A = np.asarray(surf.area, dtype=np.float64)
    n = len(P)
    blocked = lutmod.unpack_blocked(blocked_bits, n)
    S = np.zeros((3, lutmod.n_pairs(n)), dtype=np.float32)
    rho = np.zeros((n, len(MU_NODES), 3))
    for i0, i1 in lutmod.row_blocks(n, PAIRS_PER_BLOCK):
        I, J, k0 = lutmod.row_block(n, i0, i1)
        sl = slice(k0, k0 + len(I))
        Sb, G, a, tau, cos_i, cos_j = pair_kernel(P, N, I, J, lengths[:, sl], blocked[sl], coef)
        S[:, sl] = Sb.T
        use = G > 0  # pairs that see each other (the diagonal and same-plane pairs do not)
        a32, tau32 = np.ascontiguousarray(a[use].T), np.ascontiguousarray(tau[use].T)
        for exit_, entry, cos_o in ((J[use], I[use], cos_j[use]), (I[use], J[use], cos_i[use])):
            w = (A[entry] * G[use]).astype(np.float32)
            c32 = cos_o.astype(np.float32)
            f = np.empty((len(MU_NODES) * 3, len(w)), dtype=np.float32)  # row k * 3 + channel
            for k, mu in enumerate(MU_NODES):
                for ch in range(3):
                    f[3 * k + ch] = w * near_entry_factor(a32[ch], tau32[ch], c32, np.float32(mu))
            rho += _segment_sums(exit_, f, n).reshape(rho.shape)
        if progress is not None:
            progress(float(k0 + len(I)) / S.shape[1])
    kern = PreparedKernel(S=S, rho=rho, s=np.zeros((n, 3)), area=A, n=n)
    kern.s = kern.product(np.broadcast_to(A[:, None], (n, 3)))
    return kern


def environment_weights(kern: PreparedKernel, normals, visible, directions, eta: float):
    """Per voxel and direction: the unclamped weight (n, D) and the fluence and near-entry weights (n, D, 3).

    Direction d carries ``w = c_i (4 pi / D) F_t(mu) V`` (times the
    environment's radiance from d, per frame): the fluence it brings, clamped
    per direction like a light.  ``c_i`` normalises the quadrature so an
    unoccluded hemisphere brings exactly ``pi (1 - F_dr,ext) L`` of irradiance
    (as ``sky_visibility`` does for eq. 3).
    """
    N = np.asarray(normals, dtype=np.float64)
    dirs = np.asarray(directions, dtype=np.float64)
    mu = N @ dirs.T  # (n, D)
    up = mu > 0
    ft = np.where(up, fresnel_transmittance(np.clip(mu, 0.0, 1.0), eta), 0.0)
    quad = (ft * np.where(up, mu, 0.0)).sum(axis=1) * (4.0 * np.pi / len(dirs))
    c = np.divide(np.pi * (1.0 - diffuse_reflectance_external(eta)), quad, out=np.zeros_like(quad), where=quad > 0)
    w = c[:, None] * (4.0 * np.pi / len(dirs)) * ft * np.asarray(visible, dtype=np.float64)
    mu_c = np.clip(mu, 0.0, 1.0)
    rho = kern.rho_at(mu_c)
    phi = w[..., None] * kern.clamp(mu_c, rho)
    return w, phi, phi * rho
