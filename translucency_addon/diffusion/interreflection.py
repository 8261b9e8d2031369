# SPDX-License-Identifier: GPL-3.0-or-later
r"""Self-Occlusion's interreflection bounce in one Chebyshev solve (extends eq. 3 and sec. 4.3).

The add-on's bounce (:mod:`.sky_visibility`) is, per frame, a first solve
``A phi0 = S q`` (S = ``b_scale`` on the surface rows), then a second solve
with the light the object sends to itself added to q::

    A phi1 = S (q + q_b),   q_b = G (phi0_s - 2 q),   G = gamma B P / (2 (1 + F_dr))

where ``(phi0_s - 2 q)/(2 (1 + F_dr))`` is J+ (``diffusion.py``), P the
vertex map (finest surface nodes -> mesh vertices), ``gamma = F_t(1)/(pi
eta^2)`` the radiance along the normal (``radiance.outgoing_radiance``) and
B the bounce sum of :meth:`.sky_visibility.LevelSky.bounce`.  q_b is linear
in phi0, so both solves are one block lower-triangular system::

    [ A    0 ] [phi0]   [ S q            ]
    [ -K   A ] [phi1] = [ S q - 2 S G q  ],     K phi0 = S G phi0_s            (1)

which :func:`.iterative.solve_chebyshev` solves as one iteration over 2C
"channels" (:class:`BouncedSystem`): each sweep is one fused product with
the block-diagonal ``-A`` plus the sparse coupling ``S G`` on the surface
nodes.  Where A's default solve is CG (:func:`.iterative.prefers_cg`: the
compiled CG step on a level of 8,000 nodes and more) (1) is solved block by
block instead, ``A phi0 = B0`` then ``A phi1 = B1 + K phi0``, each by CG
(:func:`_block_by_block`): the same answer, in fewer sparse products (a warm
Final bunny frame 88 CG steps over both blocks against 176 block sweeps,
each of which sweeps both).  A frame warm-starts both blocks from the previous frame's pair, so
its initial residual is what the frame changed, not the bounce itself; the
answer depends on the frame's inputs only (the warm start moves the iterate,
not the fixed point).

**Same answer.**  At convergence (1) is exactly the two solves, except that
the two-pass code formed the bounce from the *clamped* J+
(``DiffusionSolver.surface_partial_current``: max(J+, 0) and the
power-preserving scale); (1) uses the linear J+.  They differ only where
J+ < 0 somewhere the object sees itself (graphs finer than a transport mean
free path; ``radiance.outgoing_radiance``); tests/test_sky_visibility.py
holds the two within 1e-6 of the peak on the torus and checks (1) against a
direct sparse LU of the 2N system.

**With the first-scatter split** (:meth:`.diffusion.DiffusionSolver.split_source`, the planner's
channels): the diffusion's source is ``m q`` (m = m(alpha) per surface node and channel, 1 where
the split is off) and the vertex radiance adds the closed-form single scattering ``sigma_v (P q)``,
sigma_v = clip(P alpha) F_t h / (4 pi eta^2) along the normal
(:meth:`.diffusion.split.HalfSpaceSplit.single_radiance`), which is linear in q, and
the diffusion's part leaves with the angular shape of multiple scattering, ``c_v = c(P alpha, 1)``
along the normal (eq. 4 there), so G becomes ``G_c = B diag(c_v) P`` per channel.  The
bounce is then ``q_b = G_c (phi0_s - 2 m q) + H q`` with ``H = B' diag(sigma_v) P`` (B' the bounce sum
without G's ``gamma / (2 (1 + F_dr))``), and the second pass solves for ``m (q + q_b)``::

    [ A        0 ] [phi0]   [ S m q                         ]
    [ -S m G_c A ] [phi1] = [ S m (q - 2 G_c m q + H q)      ]                       (1')

the same block lower-triangular form, with ``S m`` in place of ``S``: the spectrum argument below
holds unchanged.  At convergence (1') is the two passes of the split solve.

**Stability of the Chebyshev iteration on (1).**  With the block Jacobi
preconditioner ``diag(D, D)`` the iteration operator is

    M2 = [[N, 0], [-C, N]],   N = D^-1 A,   C = D^-1 K,

block lower-triangular with both diagonal blocks equal to N, so
``det(M2 - l) = det(N - l)^2``: the spectrum of M2 *is* that of N, real and
inside ``[lambda_min, lambda_max]`` of :mod:`.spectral` (Gershgorin above,
a guaranteed bound; Lanczos below, an estimate that affects speed only).
M2 is not diagonalisable in general, so the error polynomial needs one more
line: for any polynomial p, ``p(M2) = [[p(N), 0], [-E, p(N)]]`` where, in the
D-orthonormal eigenbasis of N (N = V L V^-1), ``(V^-1 E V)_ab =
(V^-1 C V)_ab p[l_a, l_b]`` with the divided difference
``|p[l_a, l_b]| <= max |p'|`` on the interval.  For the Chebyshev residual
polynomial ``p_k(l) = T_k((theta - l)/delta) / T_k(theta/delta)`` Markov's
inequality ``|T_k'| <= k^2`` on [-1, 1] gives

    ||p_k(M2)|| <= eps_k (1 + k^2 ||V^-1 C V|| / delta),   eps_k = 1 / T_k(theta/delta),

so the block iteration converges whenever the plain one does, at the same
asymptotic rate, losing at most ``log(k^2 ||C~|| / delta) / log(1/rate)``
steps to the coupling.  No new bound is estimated; the plain level's are
reused.  A leak-dominated level (the constant-mode deflation of
:func:`.spectral.deflation` active) is not handed to this path: the caller
keeps the two solves there, and says why in the result's note.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from . import kernels
from ..scene.fresnel import fresnel_transmittance
from .iterative import LevelSolve, cg_steps, chebyshev_steps, drain, lit_channels, prefers_cg, relay, start_image
from .spectral import deflation, spectral_bounds
from .sweeps import SweepOperator


def current_to_radiance(solver) -> float:
    """``gamma / (2 (1 + F_dr))``: G's factor from ``phi_s - 2 q`` to the radiance along the normal."""
    gamma = float(fresnel_transmittance(np.array([1.0]), solver.eta)[0]) / (np.pi * solver.eta**2)
    return gamma / (2.0 * (1.0 + solver.fdr))


def bounce_operator(solver):
    """G of (1) as two factors ``(Bg, P)``, ``G = Bg @ P``, cached per eta.

    ``P`` (n_vertices x n_s): the vertex map (finest surface nodes -> mesh vertices); ``Bg`` (n_s x
    n_vertices): the bounce sum of :meth:`.sky_visibility.LevelSky.bounce` times
    ``gamma / (2 (1 + F_dr))``.  The mesh has fewer vertices than the finest level has surface nodes,
    so the two factors hold several times fewer entries than their product (Final bunny: ~0.6M
    against ~2M).
    """
    key = ("G", float(solver.eta))
    cache = solver.cache.setdefault("bounce_G", {})
    if key not in cache:
        bake = solver.bake
        fine = len(bake.levels) - 1
        lv, sky = bake.levels[fine], solver.sky
        ls = sky.levels[fine]
        w = ls.weight(solver.eta, lv.normal, sky.directions)
        nv = len(bake.mesh_vertices)
        Bg = sp.csr_matrix(((w[:, None] * ls.hit_bary).ravel() * current_to_radiance(solver),
                            (np.repeat(ls.node, 3), ls.hit_vertices.ravel())), shape=(ls.n_surface, nv))
        idx, wv = bake.vertex_map
        idx = np.asarray(idx)
        P = sp.csr_matrix((np.asarray(wv, dtype=np.float64).ravel(), (np.repeat(np.arange(nv), idx.shape[1]),
                                                                     idx.ravel())), shape=(nv, lv.n_surface))
        for m in (Bg, P):
            m.sum_duplicates()
            m.sort_indices()
        cache.clear()
        cache[key] = (Bg, P)
    return cache[key]


class BouncedSweepOperator(SweepOperator):
    """(1) laid out for :func:`.iterative.solve_chebyshev`: channels [0, C) are phi0, [C, 2C) phi1.

    The surface nodes are the tail ``[n_inner:]`` of the sweep order, so ``r1 += K d0`` is two
    in-place sparse products per channel (``t = P d0_s``, ``r1_s += diag(S_c) Bg t``), no gather.
    """

    def __init__(self, base, factors, dtype=np.float64, m=None, ms_shape=None):
        super().__init__(base, copies=2, dtype=dtype)
        self.ms_shape = None if ms_shape is None else np.ascontiguousarray(ms_shape.T, dtype=self.dtype)
        Bg, P = factors
        scale = base.b_scale if m is None else base.b_scale * m  # S, or S m with the split (1')
        self.c0 = base.diag.shape[1]
        self.ni = base.level.n_inner
        surf_old = self.perm[self.ni:] - self.ni  # surface index (old) at each sweep position
        self.P = P[:, surf_old].tocsr().astype(self.dtype)
        self.P.sort_indices()
        self.SB = []
        for c in range(self.c0):
            sb = (sp.diags(scale[surf_old, c]) @ Bg[surf_old]).tocsr().astype(self.dtype)
            sb.sort_indices()
            self.SB.append(sb)
        self.t = np.zeros(P.shape[0], dtype=self.dtype)

    def sub_a(self, r, d):
        from .sweeps import _csr_matvec

        super().sub_a(r, d)  # r -= diag(A, A) d
        c0, ni, P, t = self.c0, self.ni, self.P, self.t
        for c in range(c0):  # r1 += K d0
            t[:] = 0.0
            _csr_matvec(P.shape[0], P.shape[1], P.indptr, P.indices, P.data, d[c, ni:], t)
            if self.ms_shape is not None:
                t *= self.ms_shape[c]  # diag(c_v) of (1')
            m = self.SB[c]
            _csr_matvec(m.shape[0], m.shape[1], m.indptr, m.indices, m.data, t, r[c0 + c, ni:])


class BouncedSystem:
    """The 2N block system (1) of one level as :func:`.iterative.solve_chebyshev` sees it."""

    scheme = "bounced"  # not "fv": no deflation of its own (the caller checks the base level's)

    def __init__(self, base, factors, m=None, sigma=None, ms_shape=None):
        """``m`` (n_s, C): the split's source factors (None: no split); ``sigma`` (n_vertices, C): the
        closed-form single scattering per unit q at the vertices along the normal, divided by
        :func:`current_to_radiance` so that ``Bg`` applies B' to it (H of (1'): ``H q = Bg (sigma P q)``);
        ``ms_shape`` (n_vertices, C): c_v of (1'), the multiple-scattering shape along the normal."""
        self.base, self.factors = base, factors
        self.m, self.sigma, self.ms_shape = m, sigma, ms_shape
        self.ms_shape_diffuse = ms_shape
        self.level = base.level
        self.diag = np.tile(base.diag, (1, 2))
        self._ops = {}
        self._bounds = None

    @property
    def lam_min(self) -> np.ndarray:
        """The Chebyshev interval's lower end per channel of (1): A's (its spectrum is A's), from the base
        level's :func:`.spectral.spectral_bounds` on first use -- the block Chebyshev iteration and the GPU
        ask; where the finest level runs CG block by block nothing does, and a first Final frame without
        baked bounds skips their Lanczos estimate (1.4 s on the bunny's 402k-node level)."""
        return self.bounds()[0]

    @property
    def lam_max(self) -> np.ndarray:
        """The interval's upper end per channel of (1): see :attr:`lam_min`."""
        return self.bounds()[1]

    def bounds(self) -> tuple:
        """``(lam_min, lam_max)`` of (1), computed once."""
        if self._bounds is None:
            lo, hi = spectral_bounds(self.base)
            self._bounds = (np.tile(lo, 2), np.tile(hi, 2))
        return self._bounds

    @property
    def n(self) -> int:
        return self.base.n

    @property
    def G(self) -> sp.csr_matrix:
        return (self.factors[0] @ self.factors[1]).tocsr()

    def sweep_operator(self, dtype=np.float64):
        key = np.dtype(dtype).str
        if key not in self._ops:
            self._ops[key] = BouncedSweepOperator(self.base, self.factors, dtype=dtype, m=self.m,
                                                  ms_shape=self.ms_shape)  # set_frame keeps it current
        return self._ops[key]

    def source(self, q: np.ndarray, m=None) -> np.ndarray:
        """The diffusion's source for entering light q (n_s, C): m q with the split (``m``, else the diffuse
        light's factors), else q."""
        return q if self.m is None else (self.m if m is None else m) * q

    def shaped(self, v: np.ndarray) -> np.ndarray:
        """diag(c_v) v (n_vertices, C): the multiple-scattering shape along the normal, where the split runs."""
        return v if self.ms_shape is None else self.ms_shape * v

    def bounce(self, phi0_s: np.ndarray, q: np.ndarray, direct=None) -> np.ndarray:
        """q_b (n_s, C): the light the object sends itself, ``G_c (phi0_s - 2 m q) + H q`` (``direct``: the
        frame's :class:`DirectLight`, see :meth:`rhs`: its m and its H q)."""
        Bg, P = self.factors
        qb = Bg @ self.shaped(P @ (phi0_s - 2.0 * self.source(q, None if direct is None else direct.m)))
        if direct is not None and direct.hq is not None:
            qb = qb + direct.hq
        elif self.sigma is not None:
            qb = qb + Bg @ (self.sigma * (P @ q))
        return qb

    def coupling(self, x0: np.ndarray) -> np.ndarray:
        """K x0 (N, C): S m G_c x0_s on the surface rows, zero inside."""
        ni = self.level.n_inner
        out = np.zeros_like(x0)
        Bg, P = self.factors
        out[ni:] = self.base.b_scale * self.source(Bg @ self.shaped(P @ x0[ni:]))
        return out

    def apply(self, x: np.ndarray) -> np.ndarray:
        c = self.base.diag.shape[1]
        return np.hstack([self.base.apply(x[:, :c]), self.base.apply(x[:, c:]) - self.coupling(x[:, :c])])

    def rhs(self, q: np.ndarray, direct=None, volume=None) -> np.ndarray:
        """The right-hand side of (1) for the level's direct light q (n_s, C), (N, 2C); ``direct``: the
        frame's :class:`DirectLight` where the lamps' incidence changes the split of q (eq. 6 of
        :mod:`.split`), else None; ``volume``: the lamps' volume source at the inner nodes (n_inner, C)
        (:mod:`.beam_source`), which drives phi0 and phi1 alike, or None."""
        s0 = self.source(q, None if direct is None else direct.m)
        qb_const = self.bounce(np.zeros_like(q), q, direct)  # G (0 - 2 m q) + H q: the bounce without phi0
        c = q.shape[1]
        b = np.empty((self.base.n, 2 * c))  # the two blocks written in place (no hstack of two copies)
        self.base.rhs(s0, volume, out=b[:, :c])
        self.base.rhs(s0 + self.source(qb_const), volume, out=b[:, c:])
        return b

    def set_frame(self, direct=None) -> None:
        """c_v of (1') for this frame: the direct light's multiple-scattering shape along the normal, which
        follows the lamps' incidence (``direct.ms_shape``), or the diffuse light's (None).  The block
        operator depends on the frame's lights only through this diagonal, set on the cached operators."""
        shape = self.ms_shape_diffuse if direct is None or direct.ms_shape is None else direct.ms_shape
        self.ms_shape = shape
        for op in self._ops.values():
            op.ms_shape = None if shape is None else np.ascontiguousarray(shape.T, dtype=op.dtype)

    def matrix(self, channel: int) -> sp.csr_matrix:
        """(1) for one channel as a 2N x 2N scipy matrix (the direct solve the tests check against)."""
        from .assembly import sparse_matrix

        A = sparse_matrix(self.base, channel)
        ni, n = self.level.n_inner, self.n
        S = sp.diags(self.base.b_scale[:, channel] * (1.0 if self.m is None else self.m[:, channel]))
        Bg, P = self.factors
        Gc = self.G if self.ms_shape is None else (Bg @ sp.diags(self.ms_shape[:, channel]) @ P).tocsr()
        K = sp.bmat([[sp.csr_matrix((ni, ni)), None], [None, S @ Gc]], format="csr")
        assert K.shape == (n, n)
        return sp.bmat([[A, None], [-K, A]], format="csr")


def bounced_system(solver, cols, single=(False, False, False)) -> BouncedSystem:
    """(1) of the finest level for the channels ``cols`` -- (1') where ``single`` (the split's channels)
    has any -- cached on the solver (per material, eta and split)."""
    from .split import half_space_split

    base = solver.systems[-1].subset(cols)
    cache = solver.cache.setdefault("bounced", {})
    on = np.array([bool(single[c]) for c in cols])
    key = (id(base), tuple(cols), float(solver.eta), tuple(on))
    if key not in cache:
        cache.clear()
        m = sigma = ms_shape = None
        if on.any():
            split = half_space_split(solver.eta)
            alpha = solver.surface_albedo[-1][:, cols]
            m = np.where(on, split.source_factor(alpha), 1.0)
            idx, w = solver.bake.vertex_map
            a_v = np.einsum("vk,vkc->vc", np.asarray(w, dtype=np.float64), alpha[np.asarray(idx)])
            # single_radiance is linear in q: its value for q = 1 along the normal is sigma_v
            sigma = split.single_radiance(np.ones_like(a_v), a_v, np.ones(len(a_v))) * on / current_to_radiance(solver)
            ms_shape = np.where(on, split.multiple_shape(a_v, np.ones(len(a_v))), 1.0)
        cache[key] = BouncedSystem(base, bounce_operator(solver), m=m, sigma=sigma, ms_shape=ms_shape)
    return cache[key]


def one_solve_applies(solver) -> str:
    """'' when ``DiffusionSolver.solve(bounced=True)`` can run for this solver, else why not (for the result's note)."""
    from .solver import DiffusionSolver

    if solver.sky is None:
        return "no sky visibility in the bake"
    if type(solver).solve_systems is not DiffusionSolver.solve_systems:
        return "a backend of its own solves the levels (the GPU): two passes"
    if solver.options.solver != "fast":
        return f"the {solver.options.solver} solver runs the two passes"
    # Chebyshev's concern only: CG (prefers_cg) needs no spectral interval; it adapts to the spectrum it meets
    if not prefers_cg(solver.systems[-1]) and deflation(solver.systems[-1]) is not None:
        return "the finest level is leak-dominated (deflated constants): two passes"
    return ""


@dataclass
class DirectLight:
    """What the lamps' incidence (eq. 6 of :mod:`.split`) changes in (1') for one frame's direct light q:
    ``m`` (n_s, C) its source factors, ``ms_shape`` (n_vertices, C) the shape c_v of phi0's light along the
    normal, ``hq`` (n_s, C) H q, its once-scattered light sent back by the bounce.  The bounce's own light
    is diffuse and keeps the system's m."""

    m: np.ndarray
    ms_shape: np.ndarray
    hq: np.ndarray


def direct_light(solver, system, q_light, beam, cols, single, beam_in_volume: bool = False, beam_at_surface=None):
    """:class:`DirectLight` of the finest level's entering light ``q_light`` (n_s, 3) with the lamps' part
    ``beam`` = (q_beam, mu), as the two-pass solve's output sees it (``split_radiance_at`` along the
    normal); None without a split or without lamps.  ``beam_in_volume``: the lamps' light enters the
    diffusion as a volume source (:mod:`.beam_source`), so m takes none of it but ``beam_at_surface`` (per unit
    of the lamps' light, (n_s, 3), or None: its shallowest collisions, taken at the boundary)."""
    if beam is None or system.m is None:
        return None
    from .split import half_space_split

    split = half_space_split(solver.eta)
    on = np.array([bool(single[c]) for c in cols])
    cl = list(cols)
    m_all = split.source_factors(solver.surface_albedo[-1], q_light, beam, beam_in_volume=beam_in_volume,
                                 beam_at_surface=beam_at_surface)
    idx, w = solver.bake.vertex_map
    shape, single_v = solver.split_terms_at(q_light, beam, idx, w, beam_in_volume=beam_in_volume)
    Bg, _ = system.factors
    hq = Bg @ (np.where(on, single_v[:, cl], 0.0) / current_to_radiance(solver))
    return DirectLight(m=np.where(on, m_all[:, cl], 1.0), ms_shape=np.where(on, shape[:, cl], 1.0), hq=hq)


@dataclass
class FinestStep:
    """What :func:`solve_finest_bounced` hands back to the driver (``DiffusionSolver.solve``), each (n, 3)
    in every channel: phi1 of (1), the diffusion's source (``m q`` with the split), the light that entered
    (the bounce included) and phi0, the pass without the bounce."""

    phi: np.ndarray
    q: np.ndarray
    q_incident: np.ndarray
    first_pass: np.ndarray
    info: LevelSolve


def solve_finest_bounced(solver, q_light, coarser, warm_start, cols, single) -> FinestStep:
    """The finest level of ``DiffusionSolver.solve(bounced=True)``: :func:`finest_bounced_steps` run to its end."""
    return drain(finest_bounced_steps(solver, q_light, coarser, warm_start, cols, single))


def finest_bounced_steps(solver, q_light, coarser, warm_start, cols, single, partial=None, beam=None, volume=None,
                         at_surface=None):
    """The finest level of ``DiffusionSolver.solve(bounced=True)``: the block system (1) -- (1') in the
    split's channels -- by Chebyshev, in the channels ``cols``; a generator that returns the
    :class:`FinestStep` and yields after every sweep (and once before the first, where the start is not
    zero) a function that returns the solve so far through
    ``partial`` (``DiffusionSolver.solve_steps``'s: phi1's iterate, with the source and entering light of
    phi0's; only called when given).

    ``q_light``: the finest level's entering light (before the split; (1') applies m itself);
    ``coarser``: the next coarser level's solution, or None; ``warm_start``: a previous result the
    driver can start from (its ``first_pass`` starts phi0, when it has one), or None; ``beam``: the
    lamps' part of ``q_light`` and their incidence cosines, ``(q_beam, mu)`` or None: the direct light's
    source, its once-scattered light the bounce sends back (H q) and phi0's shape follow their incidence
    (eq. 6 of :mod:`.split`, :class:`DirectLight`); the bounce's own light is diffuse light.  ``volume``:
    the lamps' volume source at the inner nodes (n_inner, 3) (:mod:`.beam_source`), or None: it drives
    phi0 and phi1 alike, and the lamps' part of ``q_light`` then leaves the boundary source but for
    ``at_surface`` (:meth:`DiffusionSolver.lamp_volume`'s, per unit of the lamps' light, or None).
    """
    opts = solver.options
    fine = len(solver.bake.levels) - 1
    system = bounced_system(solver, cols, single)
    base = system.base
    qd = np.asarray(q_light)[:, list(cols)]
    direct = direct_light(solver, system, q_light, beam, cols, single, beam_in_volume=volume is not None,
                          beam_at_surface=at_surface)
    system.set_frame(direct)
    vol = None if volume is None else np.asarray(volume)[:, list(cols)]
    B = system.rhs(qd, direct, vol)
    C = len(cols)
    x1 = solver.initial_guess(fine, cols, coarser, warm_start)
    prev0 = getattr(warm_start, "first_pass", None)
    x0 = x1.copy() if prev0 is None else solver.initial_guess(fine, cols, previous=prev0)
    X = np.hstack([x0, x1])
    X[:, ~lit_channels(B)] = 0.0  # no light in a channel: the answer is exactly 0 (solve_systems)
    if X.any():  # the start is an image already, before the iteration's set-up (its fp64 true residual)
        yield start_image(lambda: _bounced_partial(system, qd, X, C, cols, fine, partial, direct))
    tol = solver.level_tolerance(fine)
    if opts.solver == "fast" and prefers_cg(base):
        x, info = yield from _block_by_block(system, base, B, X, C, tol, opts, qd, cols, fine, partial, direct)
    else:
        steps = chebyshev_steps(system, B, X, tol, opts.max_iterations, opts.check_every)
        x, info = yield from relay(steps, lambda get: lambda: _bounced_partial(system, qd, get(), C, cols, fine,
                                                                               partial, direct))
    phi0, phi1 = x[:, :C], x[:, C:]
    q_dif, q_tot = _entered(system, phi0, qd, direct)
    info = LevelSolve(info.iterations, np.maximum(info.residual[:C], info.residual[C:]), info.history,
                      info.seconds, note="")
    phi1, info = solver.checked_level(fine, base, q_dif, base.rhs(q_dif, vol), phi1, info)
    info.residual = kernels.in_channels(info.residual, cols)
    full = kernels.in_channels
    return FinestStep(phi=full(phi1, cols), q=full(q_dif, cols), q_incident=full(q_tot, cols),
                      first_pass=full(phi0, cols), info=info)


def _block_by_block(system, base, B, X, C, tol, opts, qd, cols, fine, partial, direct):
    """(1) block by block, each block by CG (:func:`.iterative.cg_steps`): ``A phi0 = B0``, then
    ``A phi1 = B1 + K phi0`` -- forward substitution of the lower-triangular system, exact at convergence like
    the block Chebyshev iteration.  phi0 warm-starts from its part of ``X``; phi1 from phi0's answer plus
    the start's ``phi1 - phi0`` (the last frame's bounce, which a light move changes less than phi0), and
    so, while phi0 is solved, the image shows phi0's iterate plus that bounce (phi1's start alone would
    hold the last frame's image until the second block: at Final 3.5 s to come within 5 %, against 0.16 s
    for the block iteration, ``bench.progressive``).  Where the default solve of A is CG
    (:func:`.iterative.prefers_cg`) this takes fewer products than the block iteration, which sweeps both
    blocks every step.  Returns ``(x, info)`` with info over both blocks (2C residuals)."""
    max_iter, every = opts.max_iterations, opts.check_every
    bounce = X[:, C:] - X[:, :C]  # the start's phi1 - phi0
    steps0 = cg_steps(base, np.ascontiguousarray(B[:, :C]), np.ascontiguousarray(X[:, :C]), tol, max_iter, every)
    x0, info0 = yield from relay(steps0, lambda get: lambda: _bounced_partial(
        system, qd, np.hstack([(x := get()), x + bounce]), C, cols, fine, partial, direct))
    b1 = B[:, C:] + system.coupling(x0)
    steps1 = cg_steps(base, b1, x0 + bounce, tol, max(max_iter - info0.iterations, 1), every)
    x1, info1 = yield from relay(steps1, lambda get: lambda: _bounced_partial(
        system, qd, np.hstack([x0, get()]), C, cols, fine, partial, direct))
    info = LevelSolve(info0.iterations + info1.iterations, np.concatenate([info0.residual, info1.residual]),
                      info0.history + info1.history, info0.seconds + info1.seconds)
    return np.hstack([x0, x1]), info


def _entered(system, phi0, qd, direct=None) -> tuple:
    """``(the diffusion's source, the light that entered)`` of (1), the bounce phi0 sends included: the
    direct light ``qd`` split as ``direct`` says (m q with the split), the bounce's as diffuse light."""
    qb = system.bounce(phi0[system.base.level.n_inner:], qd, direct)
    return system.source(qd, None if direct is None else direct.m) + system.source(qb), qd + qb


def _bounced_partial(system, qd, x, C, cols, fine, partial, direct=None):
    """The solve so far from the block iterate ``x`` = [phi0 | phi1]: phi1, with the bounce phi0 sends."""
    q_dif, q_tot = _entered(system, x[:, :C], qd, direct)
    full = kernels.in_channels
    return partial(fine, x[:, C:], full(q_dif, cols), full(q_tot, cols))
