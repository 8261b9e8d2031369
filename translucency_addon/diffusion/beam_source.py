r"""A lamp's light inside the volume: the uncollided beam along its chords, as the diffusion's volume source.

Why
---
The boundary source (Wang et al. eq. 3, :mod:`.assembly`) puts all the light a lamp sends into the object
at the surface node where it enters; the split (:mod:`.split` eq. 6) then says how much of it scatters once
and leaves, and how much feeds the diffusion.  That is the local half-space.  A lamp's beam is collimated:
it travels on along its refracted direction, through the volume, and light that entered near the
terminator scatters for the first time under the surface *past* it.  The index-matched skin sphere under a
sun (docs/accuracy.md, the lamps section) comes out at 0.5 of a random walk around the terminator with the
boundary source, and at 0.97 with the beam as a volume source.

What is solved
--------------
The reduced-intensity split of radiative transfer (Ishimaru 1978, ch. 7 and 9; photon beam diffusion,
Habel et al. 2013, sec. 4): the uncollided beam entering at a surface point with power ``P`` (``q_beam``
times the node's area) along the refracted direction ``w`` has its first collisions at distance t with
density ``P sigma_t e^{-sigma_t t}`` up to where the chord leaves the object (length ``L``, ray-traced).
A collision scatters with probability ``alpha``; of the once-scattered light the part ``e1`` leaves at once
(the split's closed-form single scattering, which the output adds) and the rest is *diffuse light inside
the medium*, the diffusion's source::

    S(t) = P sigma_t e^{-sigma_t t} alpha (1 - e1(sigma_t z)),   e1(tau) = 1/2 int_0^1 T_in(m) e^{-tau/m} dm   (7)

with z = t nu the depth below the entry point's tangent plane (nu the inside incidence cosine) and
``T_in`` the Fresnel transmittance from inside (zero past the critical angle: total internal reflection
keeps that light in).  The volume source of the finite-volume system (:mod:`.assembly`, ``sum T (phi_i -
phi_j) + mu V phi_i = b_i``) is the power S deposits in each inner node's cell.

**Calibrated to transport, depth by depth.**  Diffusion returns light that scattered a few times near the
surface too readily (the split's docstring: 8 % over transport at alpha 0.68), and at low albedo carries
too little from deep (its decay ``s = sqrt(3 (1 - alpha))`` per mean free path exceeds transport's nu_0:
0.98 against 0.85 at alpha 0.68).  On a half-space (units of the mean free path) a plane source at depth
tau fed to the diffusion sends ``P_d(tau) = e^{-s tau}/(1 + 2 A s/3)`` of its power out; transport sends
out, of light scattered once at tau that does not leave at once, ``G(tau)``: by linearity, the exitance of
the fluence it causes,::

    G(tau_j) = alpha w^T (I - alpha K)^{-1} K e_j / h_j,       W(alpha, tau) = G(tau) / P_d(tau)        (8)

with K, the cells h and the exitance weights w of :class:`.half_space.HalfSpaceTransport` (eq. 1-2 there:
``K e_j / h_j`` is the uncollided fluence of a unit isotropic source in cell j, ``(I - alpha K)^{-1}`` adds
every later scattering; G <= 1 - e1).  The deposits are eq. (7)'s collisions weighted by W at their depth,
``P sigma_t e^{-sigma_t t} alpha W(alpha, sigma_t z)``, in place of ``alpha (1 - e1)``; of them a half-space
returns ``int P sigma_t e^{-sigma_t t} alpha G dt``: transport's multiple scattering, at every incidence.
``tests/test_beam_source.py`` checks that against the split's beam tables (within 0.5 %: the split
extrapolates from two depth grids, W comes from one) and G against a random walk.  A single factor per
incidence, the return's ratio M/R (what this module did before), got the total right but took light from
deep sources with the shallow ones: on the skin sphere under a sun (Final) the shaded half came out at 0.71,
0.69, 0.50 of the walk in R, G, B, with W at 0.73, 0.75, 0.57 (docs/accuracy.md, Lamps).  At eta 1, W at
the surface is 0.23 (alpha 0.68) to 0.49 (alpha 0.999), where about half the once-scattered light leaves at
once; a few mean free paths deep it is about 1 for alpha >= 0.96, and at low albedo it grows with depth
(2.6 at tau 10 for alpha 0.68, where the beam has kept e^{-10} of its light), where diffusion's decay is
too fast.

**Discretised** so that no power is lost to the graph's resolution (the part of the beam shallower than
the first inner node is most of it in dense media: marble's mean free path is 0.45 mm): each chord is cut
into ``N_SEGMENTS`` pieces of equal collision probability at the smallest sigma_t of the three channels
(the channel that reaches deepest; at the mean sigma_t red's deep tail fell into one piece and the skin
sphere's shaded half came out 15 % darker than with 96 pieces); each piece's collisions are integrated
exactly per channel and deposited, with eq. (8)'s weight at their mean depth, at their mean distance along the chord, in the
cell of the nearest inner node (scipy's k-d tree).  16 pieces are within 3 % of 96 on that sphere.  The medium is taken as homogeneous along each
chord with the entry node's coefficients, as the split takes it at the surface node.

**Collisions the graph cannot place.**  A deposit nearer to the surface than to the inner node whose cell
holds it sits, for the diffusion, at that node's depth, and comes back ``P_d`` of the node's depth, not of its
own: where the nodes lie far apart against the mean free path (a 40 mm skin sphere at Draft or Preview,
nodes ~5 mm apart against 0.7-1.3 mm) the lit cap came out at 0.62-0.89 of the walk.  Such a deposit, where its
entry node is also the surface node nearest to it (a grazing beam's deposits far along the chord are not: the
boundary would move their light back towards the lamp), enters the diffusion at its entry node as a boundary
source instead (:func:`shallow_to_boundary`), of the strength
whose half-space return ``B`` (the boundary source's, which the graph's fitted surface links reproduce) is the
deposit's calibrated return::

    q_s = sum over the node's shallow deposits of  power P_d(tau) / (B a_s)                            (9)

(the split's ``m`` carries it: :meth:`.split.HalfSpaceSplit.source_factors` ``beam_at_surface``), on the level
the beams are traced from; a coarser level, only the finer one's starting guess, keeps all of it in its cells.
On the 40 mm sphere the cap comes to 0.93-0.99 at Draft and Preview (``tests/test_beam_source.py``); on the
10 mm sphere of docs/accuracy.md (the same bakes before and after) the sun's profile RMS at Final goes from 5.5,
4.4, 7.9 % to 5.5, 4.0, 7.0 %, and at Preview, whose nodes lie ~1 mm apart, blue's cap from 0.97 to 1.03.

Where it runs: the diffusion solve of :class:`.solver.DiffusionSolver` in the split's channels (option
``lamp_source="volume"``), on the CPU and the GPU (the source rides in the inner nodes' texels of the
``q`` texture).  A point light's or area light's beam is taken at each node as one beam from the
q-weighted mean direction of its light (exact for a sun or point light; patches of an area light differ by
a few degrees).

Hand-written: the chord integrals are closed forms, the ray casts :mod:`..geometry.raycast`'s, the cells
scipy's ``cKDTree``.
"""

from __future__ import annotations

from functools import lru_cache
from typing import NamedTuple

import numpy as np

from ..scene.fresnel import boundary_A, refract_into
from .split import albedo_index, inside_transmittance

N_SEGMENTS = 16  # pieces of equal collision probability per chord
COARSE_GROUP = 4  # a coarser level (the finer one's starting guess) takes the pieces merged this many at a time
_TAU_MAX = 60.0


@lru_cache(maxsize=8)
def _escape_table(eta: float):
    """(tau grid, e1(tau)) of eq. (7), 1/2 int T_in(m) e^{-tau/m} dm by 128-point Gauss-Legendre on m from
    the critical cosine (T_in = 0 below it: a kink the rule must not straddle) to 1."""
    m_c = np.sqrt(max(0.0, 1.0 - 1.0 / (eta * eta)))
    x, w = np.polynomial.legendre.leggauss(128)
    m, w = m_c + 0.5 * (1.0 - m_c) * (x + 1.0), 0.5 * (1.0 - m_c) * w
    tau = np.concatenate([[0.0], np.geomspace(1e-5, _TAU_MAX, 600)])
    e1 = 0.5 * (w * inside_transmittance(m, eta) * np.exp(-tau[:, None] / m[None, :])).sum(axis=1)
    return tau, e1


def escape_once(tau, eta: float) -> np.ndarray:
    """e1 of eq. (7): the part of light scattered isotropically at optical depth ``tau`` below a plane
    boundary of index ``eta`` that leaves without another collision."""
    grid, e1 = _escape_table(float(eta))  # interpolated in log: e1 falls off like e^{-tau}/tau
    return np.exp(np.interp(np.asarray(tau, dtype=np.float64), grid, np.log(e1), right=-np.inf))


N_ALPHA = 49  # albedos of eq. (8)'s table, uniform in sqrt(1 - alpha) (as the split's)


@lru_cache(maxsize=8)
def _depth_weight_table(eta: float) -> tuple:
    """(tau grid, W (N_ALPHA, tau)) of eq. (8) on the half-space's depth grid up to _TAU_MAX; one dense solve per
    albedo on a grid 160 mean free paths deep (~0.1 s per eta, once per process; W within 1e-3 of the
    400-deep grid's up to tau 60)."""
    from scipy import linalg

    from .half_space import HalfSpaceTransport, depth_grid

    ht = HalfSpaceTransport(float(eta), lambda m: inside_transmittance(m, float(eta)), depth_grid(depth=160.0))
    keep = ht.z <= _TAU_MAX
    w = ht.exitance_weights()
    n = len(ht.z)
    alpha = 1.0 - np.linspace(0.0, 1.0, N_ALPHA) ** 2  # 1 -> 0
    W = np.zeros((N_ALPHA, int(keep.sum())))
    for i, a in enumerate(alpha):
        if a >= 1.0:  # nothing absorbed: all of it leaves (G = 1 - e1, s = 0); the grid's bottom would lose it
            W[i] = 1.0 - escape_once(ht.z[keep], eta)
        elif a > 0.0:
            y = linalg.solve((np.eye(n) - a * ht.K).T, w)
            G = a * (y @ ht.K) / ht.h
            W[i] = G[keep] / diffusion_return(a, ht.z[keep], eta)  # e^{-s tau} >= e^{-105} up to _TAU_MAX
            s = np.sqrt(3.0 * (1.0 - a))  # the diffusion's decay per mean free path, as in diffusion_return
            if s > 1.0:  # G's rounding (~1e-17) times e^{s tau} would outgrow the beam's e^{-tau} past here:
                deep = ht.z[keep] > 25.0 / (s - 1.0)  # hold W (deposits there carry < e^{-25} of the beam)
                if deep.any():
                    W[i, deep] = W[i, np.argmax(deep) - 1]
    return ht.z[keep], W


def diffusion_return(alpha, tau, eta: float) -> np.ndarray:
    """``P_d = e^{-s tau}/(1 + 2 A s/3)``, ``s = sqrt(3 (1 - alpha))``: the part of a plane source's power at optical
    depth ``tau`` below a half-space's boundary that the diffusion (eq. 1-2) sends out (eq. 8's denominator)."""
    a = np.clip(np.asarray(alpha, dtype=np.float64), 0.0, 1.0)
    s = np.sqrt(3.0 * (1.0 - a))
    return np.exp(-s * np.asarray(tau, dtype=np.float64)) / (1.0 + 2.0 * boundary_A(eta) * s / 3.0)


def depth_weight(alpha, tau, eta: float) -> np.ndarray:
    """W(alpha, tau) of eq. (8), bilinear in (sqrt(1 - alpha), tau); ``alpha`` and ``tau`` broadcast together
    (tau the optical depth below the entry point's tangent plane, clamped to the table's range)."""
    z, W = _depth_weight_table(float(eta))
    i, ta = albedo_index(alpha, N_ALPHA)
    tau = np.clip(np.asarray(tau, dtype=np.float64), z[0], z[-1])
    j = np.clip(np.searchsorted(z, tau) - 1, 0, len(z) - 2)
    tt = (tau - z[j]) / (z[j + 1] - z[j])
    i, ta, j, tt = np.broadcast_arrays(i, ta, j, tt)
    flat = W.reshape(-1)
    nz = len(z)

    def at(ii):
        return (1.0 - tt) * flat[ii * nz + j] + tt * flat[ii * nz + j + 1]

    return (1.0 - ta) * at(i) + ta * at(i + 1)


def refract_inward(to_light: np.ndarray, normals: np.ndarray, eta: float) -> tuple:
    """(inside direction of the beam, inside cosine nu): light arriving from ``to_light`` (unit, towards
    the lamp) through a surface of outward ``normals``, refracted by Snell's law (:func:`..scene.fresnel.refract_into`)."""
    return refract_into(to_light, normals, eta)


def chord_lengths(bvh, points, normals, directions, diag: float) -> np.ndarray:
    """Length (object units) from each surface point along ``directions`` (pointing inside) to where the
    ray leaves the mesh.  One cast from the point itself: its first hit is the exit.  A point a little
    outside the mesh (a graph's surface node lies within the tetrahedralisation's envelope of it) first
    meets the surface where the ray enters: those rays -- a first hit closer than ``2e-3 diag / nu`` --
    are cast again from there (as :func:`..geometry.raycast.inward_thickness` measures from the entry).
    A ray that finds no exit (a hole, a grazing edge) takes the median of the others."""
    tiny = 1e-7 * diag
    t, tri, _, _ = bvh.intersect(points, directions, tmin=tiny)
    nu = np.clip(-np.einsum("ij,ij->i", directions, normals), 0.05, 1.0)
    near = np.flatnonzero((tri >= 0) & (t < 2e-3 * diag / nu))
    if near.size:
        entry = points[near] + (t[near] + 1e-6 * diag)[:, None] * directions[near]
        t2, tri2, _, _ = bvh.intersect(entry, directions[near], tmin=tiny)
        t[near] = np.where(tri2 >= 0, t2, t[near])
        tri[near] = np.where(tri2 >= 0, tri2, tri[near])
    hit = tri >= 0
    return np.where(hit, t, np.median(t[hit]) if hit.any() else diag)


class Deposits(NamedTuple):
    """:func:`beam_deposits`' point deposits; per deposit: ``points`` (m, 3) object units, ``power`` (m, 3) in the
    units of the system's right-hand side (mm^2 W/m^2), ``entry`` (m,) the surface node its beam entered at,
    ``depth`` (m,) mm below that node's tangent plane, ``tau`` and ``alpha`` (m, 3) its optical depth and the
    entry node's albedo per channel."""

    points: np.ndarray
    power: np.ndarray
    entry: np.ndarray
    depth: np.ndarray
    tau: np.ndarray
    alpha: np.ndarray


def beam_deposits(level, bvh, mm_per_unit: float, beam, sigma_t_s, alpha_s, eta: float, diag: float,
                  n_segments: int = N_SEGMENTS) -> Deposits:
    """The lamps' calibrated volume source (eq. 7 with eq. 8's depth weight W) as point deposits (:class:`Deposits`).

    ``level``: the graph level whose surface nodes the beams enter at; ``beam``: ``(q_beam, mu, to_light)``
    there (:class:`..scene.lights.LampBeams`): the lamps' entering light (W/m^2, after the Fresnel
    transmittance), their q-weighted outside incidence cosine and mean direction; ``sigma_t_s``,
    ``alpha_s``: (n_surface, 3) at those nodes (per mm); ``bvh``: the mesh's
    :class:`..geometry.raycast.TriangleBVH`; ``diag``: the mesh's diagonal (object units).
    """
    q_b, mu, to_light = (np.asarray(a, dtype=np.float64) for a in beam)
    lit = np.flatnonzero(q_b.mean(axis=1) > 0)
    if lit.size == 0:
        return Deposits(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0, dtype=np.int64), np.zeros(0),
                        np.zeros((0, 3)), np.zeros((0, 3)))
    s = float(mm_per_unit)
    n = np.asarray(level.normal, dtype=np.float64)[lit]
    p = np.asarray(level.surface_position, dtype=np.float64)[lit]
    w, nu = refract_inward(to_light[lit], n, eta)
    L = chord_lengths(bvh, p, n, w, diag) * s  # mm
    st = np.asarray(sigma_t_s, dtype=np.float64)[lit]
    al = np.asarray(alpha_s, dtype=np.float64)[lit]
    power = q_b[lit] * (np.asarray(level.area, dtype=np.float64)[lit] * s * s)[:, None]
    power *= al
    st_min = st.min(axis=1)
    reach = -np.expm1(-st_min * L)  # the most penetrating channel's collision probability along the chord
    k = np.arange(n_segments) / n_segments
    edges = np.empty((len(L), n_segments + 1))  # (n, K+1) mm; the last edge is where the chord leaves
    edges[:, :-1] = -np.log1p(-k[None, :] * reach[:, None]) / st_min[:, None]
    edges[:, -1] = L
    # each piece's collisions sit at their mean distance (at the mean sigma_t): its first moment kept
    a, width = edges[:, :-1], np.diff(edges, axis=1)
    sw = st_min[:, None] * width
    mid = a + np.where(sw > 1e-6, 1.0 / st_min[:, None] - width / np.expm1(np.minimum(sw, 700.0)), 0.5 * width)
    through = np.exp(-st[:, None, :] * edges[:, :, None])  # (n, K+1, C) uncollided fraction
    collided = through[:, :-1] - through[:, 1:]  # (n, K, C) exact per channel
    depth = mid * nu[:, None]  # (n, K) mm below the entry point's tangent plane
    tau = st[:, None, :] * depth[:, :, None]
    weight = depth_weight(al[:, None, :], tau, eta)  # eq. (8)
    x = p[:, None, :] + (mid / s)[:, :, None] * w[:, None, :]
    return Deposits(x.reshape(-1, 3), (power[:, None, :] * collided * weight).reshape(-1, 3),
                    np.repeat(lit, n_segments), depth.reshape(-1), tau.reshape(-1, 3),
                    np.repeat(al, n_segments, axis=0))


def shallow_to_boundary(dep: Deposits, node_distance_mm: np.ndarray, area_mm2: np.ndarray, eta: float,
                        at_entry=True) -> tuple:
    """``(power left in the volume (m, 3), boundary source (n_surface, 3) in W/m^2)``: eq. (9) of the module
    docstring.  A deposit nearer to the surface than to the inner node whose cell would hold it
    (``node_distance_mm``, per deposit) is a source the graph cannot place: its cell's node sits deeper, and the
    diffusion would return ``P_d`` of the node's depth, not of the deposit's (a 40 mm skin sphere at Preview,
    nodes ~4 mm apart against a 0.7-1.3 mm mean free path: 0.66-0.87 of a random walk at the lit pole).  It
    enters as a boundary source at its entry node instead, of the strength whose half-space return B
    (:func:`.split.semi_infinite_albedo`, what the graph's fitted surface links reproduce) is the deposit's
    calibrated return ``power P_d(tau)`` (:func:`diffusion_return`); where B vanishes (low albedo at eta > 1)
    the deposit stays in the volume.  ``at_entry`` (per deposit, or True): whether the entry node is the surface
    node nearest to the deposit; one a grazing beam carried sideways past it stays in the volume (the boundary
    source would move its light back towards the lamp)."""
    from .split import semi_infinite_albedo

    B = semi_infinite_albedo(dep.alpha, eta)
    move = ((dep.depth < node_distance_mm) & at_entry)[:, None] & (B > 1e-3)
    moved = np.where(move, dep.power * diffusion_return(dep.alpha, dep.tau, eta) / np.where(B > 1e-3, B, 1.0), 0.0)
    q = np.zeros((len(area_mm2), 3))
    for c in range(3):
        q[:, c] = np.bincount(dep.entry, moved[:, c], len(area_mm2))
    q /= np.asarray(area_mm2, dtype=np.float64)[:, None]
    return np.where(move, 0.0, dep.power), q


def merged_pieces(points, power, n_segments: int = N_SEGMENTS, group: int = COARSE_GROUP) -> tuple:
    """``(points, power)`` of :func:`beam_deposits`' pieces merged ``group`` consecutive ones of a chord at a time:
    their powers summed and their position the power-weighted mean (summed over the channels), so each merged
    deposit keeps its pieces' power and first moment along the chord.  A coarser level's cells are the finer
    one's starting guess only (:meth:`.solver.DiffusionSolver.lamp_volume`), and several times larger than the
    pieces' spacing near the surface: binning a quarter of the deposits saves two thirds of the volume source's
    k-d tree queries there (the Final sphere: 60 -> 15 ms per coarser level).  ``points`` (m, 3), ``power``
    (m, C) in chord-major order, m a multiple of ``n_segments``; ``group`` must divide ``n_segments``."""
    points, power = np.asarray(points, dtype=np.float64), np.asarray(power, dtype=np.float64)
    if group <= 1 or len(points) == 0:
        return points, power
    if n_segments % group or len(points) % n_segments:
        raise ValueError(f"merged_pieces: {len(points)} deposits, {n_segments} per chord, groups of {group}")
    X = points.reshape(-1, group, 3)
    Pw = power.reshape(-1, group, power.shape[1])
    weight = Pw.sum(axis=2)  # (m / group, group)
    total = weight.sum(axis=1, keepdims=True)
    weight = np.where(total > 0, weight / np.where(total > 0, total, 1.0), 1.0 / group)
    return np.einsum("gk,gkd->gd", weight, X), Pw.sum(axis=1)


def deposit_in_cells(inner_tree, n_inner: int, points, power, cell=None) -> np.ndarray:
    """(n_inner, 3): each deposit's power in the cell of its nearest inner node (``inner_tree``: a k-d tree
    of the level's inner node positions, object units; ``cell``: those nodes where already queried)."""
    out = np.zeros((n_inner, 3))
    if len(points) == 0 or n_inner == 0:
        return out
    if cell is None:
        _, cell = inner_tree.query(points, workers=-1)
    for c in range(3):
        out[:, c] = np.bincount(cell, weights=power[:, c], minlength=n_inner)
    return out
