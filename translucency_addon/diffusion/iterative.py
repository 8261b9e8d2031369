"""Iterative and direct solvers of one level's system ``A x = b`` (Wang et al. 2010 sec. 4.3).

Each takes ``(system, b, x0, tol, max_iter, check_every)`` and returns
``(x, LevelSolve)``; all stop on the relative residual ``|b - A x| / |b| <= tol``:

* :func:`solve_jacobi`: ``x <- x + D^-1 (b - A x)`` (eqs. 8-9, the paper's relaxation);
* :func:`solve_chebyshev`: Jacobi-preconditioned Chebyshev semi-iteration
  (Saad, *Iterative Methods for Sparse Linear Systems*, Alg. 12.1) on the
  interval of :mod:`.spectral`, with its deflation where it helps;
* :func:`solve_direct`: scipy's sparse LU, the reference the others are tested against.

They see a system only through ``system.apply``, ``system.diag`` and, for the
direct solve, :func:`.assembly.sparse_matrix`: any graph of the contract works.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from ..geometry.extent import bounds
from . import compiled_cg, kernels
from .assembly import LevelSystem, sparse_matrix
from .coarse_space import coarse_space
from .spectral import deflation, spectral_bounds
from .sweeps import FP32_TOL


@dataclass
class LevelSolve:
    iterations: int
    residual: np.ndarray  # (3,) final relative residual
    history: list  # relative residual (max over channels) at each check
    seconds: float
    note: str = ""  # what went wrong and what was done instead (e.g. the direct fallback)

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


def lit_channels(b: np.ndarray) -> np.ndarray:
    """The channels of a node-major (N, C) right-hand side with any light: ``|b|^2 > 0`` per channel (one
    fused pass, ~4x faster at 400k x 6 than ``(b != 0).any(axis=0)``; a channel whose every value is below
    1e-154 counts as dark, where its squares underflow -- light no image can show)."""
    return kernels.squared_norms(b) > 0.0


def _cm_norms(v: np.ndarray) -> np.ndarray:
    """``|v|`` per channel of a channel-major (C, N) array, in fp64 (the sweeps' layout, any precision)."""
    return np.sqrt(np.einsum("cn,cn->c", v, v, dtype=np.float64))


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


def first_check(res: np.ndarray, tol: float, sigma: np.ndarray, check_every: int) -> int:
    """The step before which a Chebyshev cycle needs no residual check.

    On the interval the residual polynomial is at most ``1 / T_k(sigma)`` with
    ``sigma = theta / delta`` (Saad sec. 12.3), so reaching ``tol`` from a
    relative residual ``res`` takes at least ``acosh(res/tol) / acosh(sigma)``
    steps where every mode lies at the bottom of the interval; half of that,
    rounded down to a check, is skipped without a look.  A check is a
    reduction and, on the GPU, a read-back that stalls the queue
    (gpu_shaders/solver.py), so this saves dispatches; the CPU uses the same
    rule so both stop after the same step.
    """
    r = np.asarray(res, dtype=np.float64)
    need = r > tol
    if tol <= 0.0 or not need.any():  # tol 0: a fixed number of sweeps (max_iter), checked as before
        return 0
    k = np.arccosh(np.maximum(r[need] / tol, 1.0)) / np.arccosh(np.maximum(np.asarray(sigma)[need], 1.0 + 1e-15))
    k = float(np.max(k))
    if not np.isfinite(k):
        return 0
    return int(check_every * np.floor(0.5 * k / check_every))


def drain(steps):
    """Run a generator of :func:`chebyshev_steps` (or of a driver built on it) to its end; its return value."""
    while True:
        try:
            next(steps)
        except StopIteration as stop:
            return stop.value


def relay(steps, wrap):
    """Yield ``wrap(get)`` for every ``get`` a :func:`chebyshev_steps` generator yields (a driver turns an
    iterate into its solution so far); return that generator's ``(x, LevelSolve)``."""
    while True:
        try:
            get = next(steps)
        except StopIteration as stop:
            return stop.value
        yield wrap(get)


def start_image(get):
    """Mark a yielded ``get`` as the solve's start, not a sweep's iterate (``progressive`` ends a first slice
    there, and never another)."""
    get.is_start = True
    return get


def solve_chebyshev(system, b, x0, tol, max_iter, check_every=8) -> tuple[np.ndarray, LevelSolve]:
    """Chebyshev semi-iteration with the Jacobi preconditioner: :func:`chebyshev_steps` run to its end."""
    return drain(chebyshev_steps(system, b, x0, tol, max_iter, check_every))


def chebyshev_steps(system, b, x0, tol, max_iter, check_every=8):
    """Chebyshev semi-iteration with the Jacobi preconditioner (Saad Alg. 12.1), per channel, as a generator.

    After every sweep it yields a function that returns the current iterate (node-major, fp64; nothing is
    computed unless it is called), so a caller can stop after any sweep and resume later (the viewport's
    progressive frames: a Final-quality sweep of the bunny is ~20 ms); it returns ``(x, LevelSolve)``.  Run to its end
    (:func:`solve_chebyshev`) it is the same arithmetic whether or not anyone looked.

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
    The sweeps run on :class:`.sweeps.SweepOperator` (channel-major, RCM order,
    one fused sparse product per step); the iterates equal the node-major
    ``kernels.chebyshev_update`` loop's to rounding.
    """
    t0 = time.perf_counter()
    lam_min, lam_max = spectral_bounds(system)
    defl = deflation(system)
    deflated = np.zeros(len(lam_max), dtype=bool) if defl is None else defl.mask.copy()
    # channel-major, RCM order, fused r -= A d; fp32 where the tolerance allows (sweeps.py)
    op = system.sweep_operator(np.float32 if tol >= FP32_TOL else np.float64)

    def interval():
        lo = np.where(deflated, defl.lam_min, lam_min) if defl is not None else lam_min
        theta = 0.5 * (lam_max + lo)
        delta = 0.5 * (lam_max - lo)
        return theta, delta, theta / delta

    def correct(x, R):  # the deflation's Galerkin correction works node-major; only at cycle ends
        x, r = defl.correct(x, op.from_cm(R))
        return x, op.to_cm(r)

    def true_residual(x):  # in fp64, node-major: what the solve reports, whatever the sweep precision
        return op.to_cm(b - system.apply(x))

    theta, delta, sigma = interval()
    x = np.array(x0, dtype=np.float64)
    R = true_residual(x)
    if defl is not None:
        x, R = correct(x, R)
    bn = np.sqrt(kernels.squared_norms(b))  # a norm needs no reordering
    bn = np.where(bn > 0, bn, 1.0)
    res = _cm_norms(R) / bn
    hist = [float(res.max())]
    it = 0
    D = np.empty_like(R)
    T = np.empty_like(R)
    restarts = 0
    while res.max() > tol and it < max_iter:
        start = res.copy()
        X = np.zeros_like(R)  # the correction this cycle adds to x (the sweep precision)
        rho = 1.0 / sigma
        skip = it + first_check(res, tol, sigma, check_every)
        np.multiply(R, op.inv_diag, out=D)
        D /= theta[:, None]
        best, since = res.copy(), np.zeros(len(res), dtype=int)
        stalled = np.zeros(len(res), dtype=bool)
        while it < max_iter:
            rho_next = 1.0 / (2.0 * sigma - rho)
            coef_d = rho_next * rho
            coef_r = 2.0 * rho_next / delta
            # = kernels.chebyshev_update: x += d, r -= A d, d = coef_d d + coef_r D^-1 r
            op.sub_a(R, D)
            X += D
            np.multiply(R, op.inv_diag, out=T)
            T *= coef_r[:, None]
            D *= coef_d[:, None]
            D += T
            rho = rho_next
            it += 1
            yield lambda x=x, X=X: x + op.from_cm(X)  # the iterate now (X is updated in place)
            if it % check_every == 0 and it >= skip:
                res = _cm_norms(R) / bn
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
        # The recursively updated r drifts slightly from b - A x (more so in fp32); report the true one,
        # and go on from it while it misses the tolerance (iterative refinement).
        x += op.from_cm(X)
        R = true_residual(x)
        res = _cm_norms(R) / bn
        if defl is None:
            restarts += 1
            hist.append(float(res.max()))
            if res.max() <= tol or restarts > 20:
                break
            continue
        x, R = correct(x, R)
        res = _cm_norms(R) / bn
        hist.append(float(res.max()))
        give_up = stalled & (res > 0.5 * start)
        if give_up.any():
            deflated &= ~give_up
            theta, delta, sigma = interval()
    return x, LevelSolve(it, res, hist, time.perf_counter() - t0)


def solve_cg(system, b, x0, tol, max_iter, check_every=8, coarse: bool = True) -> tuple[np.ndarray, LevelSolve]:
    """Preconditioned conjugate gradients: :func:`cg_steps` run to its end."""
    return drain(cg_steps(system, b, x0, tol, max_iter, check_every, coarse))


def cg_steps(system, b, x0, tol, max_iter, check_every=8, coarse: bool = True, compiled: bool = True):
    """Preconditioned conjugate gradients (Saad Alg. 9.1), per channel, as a generator.

    Solves ``A x = b`` for the symmetric M-matrix of the finite-volume scheme (:mod:`.assembly`; the
    graph contract makes every link's two slots equal, so A is symmetric positive definite): each
    channel is its own CG run, ``alpha = (r.z) / (p.A p)``, ``x += alpha p``, ``r -= alpha A p``,
    ``z = M^-1 r``, ``p = z + (r.z)_new / (r.z) p``, all channels in one fused sparse product per step
    (:class:`.sweeps.SweepOperator`, fp64: CG's recurrences lose their orthogonality in fp32); the vector
    work of a step in two compiled passes where numba runs (:mod:`.compiled_cg`; ``compiled=False``: the
    numpy step, which is also the fallback, for comparisons).  M^-1 is
    Jacobi's ``D^-1`` plus, on graphs of some thousands of nodes, the coarse correction
    ``P A_c^-1 P^T`` of :mod:`.coarse_space` (fewer than half the steps on a fluid frame; ``coarse=False``:
    Jacobi alone, for comparisons).

    Why the CPU's default over :func:`chebyshev_steps` on this scheme: Chebyshev needs the spectrum's
    interval and takes the steps that interval asks for whatever the start; CG adapts to the right-hand
    side and the start, so a warm start (the last frame's solution) and sources on the surface only cut
    its steps.  Measured on a warm 16k-particle fluid frame (tol 1e-4): 26-39 steps against
    Chebyshev's 112 (``docs/bench_fluid.md``).  It needs two dot products per step, which the GPU's
    dispatches avoid (``gpu_shaders`` keeps Chebyshev); on the CPU they cost less than a tenth of the
    step.  Yields after every step, like :func:`chebyshev_steps`, a function returning the iterate
    (node-major, fp64), and returns ``(x, LevelSolve)``; the relative residual is checked every step
    (the dot products give it) and the reported one is the true ``b - A x``.
    """
    t0 = time.perf_counter()
    op = system.sweep_operator(np.float64)
    space = coarse_space(system, op) if coarse else None
    step = compiled_cg.CompiledStep(op, space) if compiled and not compiled_cg.available() else NumpyStep(op, space)

    def true_residual(X):  # b - A x, channel-major
        R = op.to_cm(b)
        op.sub_a(R, X)
        return R

    X = op.to_cm(x0)
    bn = np.sqrt(kernels.squared_norms(b))  # a norm needs no reordering
    bn = np.where(bn > 0, bn, 1.0)
    R = true_residual(X)
    res = _cm_norms(R) / bn
    hist = [float(res.max())]
    it = restarts = 0
    P, Q = np.zeros_like(R), np.zeros_like(R)
    zero = np.zeros(len(R))
    while res.max() > tol and it < max_iter:
        # (re)started from the true residual (the recursive one drifts from b - A x by rounding): alpha 0
        # leaves x and r as they are and gives r . z, and beta 0 makes p = z
        P[:] = 0.0
        _, rz = step.advance(X, R, P, Q, zero)
        step.direction(P, R, zero)
        while it < max_iter:
            pap = op.product(P, Q)  # Q = -A P, and p . A p
            live = (res > tol) & (pap > 0.0)  # a converged (or source-free) channel stays where it is
            alpha = np.where(live, rz / np.where(live, pap, 1.0), 0.0)
            rr, rz_new = step.advance(X, R, P, Q, alpha)
            beta = np.where(live & (rz > 0.0), rz_new / np.where(rz > 0.0, rz, 1.0), 0.0)
            step.direction(P, R, beta)
            rz = rz_new
            it += 1
            res = np.where(live, np.sqrt(rr) / bn, res)
            yield lambda X=X: op.from_cm(X)  # the iterate now (X is updated in place)
            if it % check_every == 0:
                hist.append(float(res.max()))
            if not (live & (res > tol)).any():
                break
        R = true_residual(X)
        res = _cm_norms(R) / bn
        hist.append(float(res.max()))
        restarts += 1
        if restarts > 5:
            break
    return op.from_cm(X), LevelSolve(it, res, hist, time.perf_counter() - t0)


class NumpyStep:
    """:func:`cg_steps`'s vector work in numpy (and the fallback of :class:`.compiled_cg.CompiledStep`, the
    same arithmetic in two compiled passes): ``z = M^-1 r`` kept between the two calls of a step."""

    def __init__(self, op, space):
        self.op, self.space = op, space
        self.Z = np.empty((op.C, op.n))

    def advance(self, X, R, P, Q, alpha) -> tuple:
        """``x += alpha p``, ``r += alpha q`` (q = -A p), ``z = M^-1 r``; returns ``(|r|^2, r . z)`` per channel."""
        X += alpha[:, None] * P
        R += alpha[:, None] * Q
        np.multiply(R, self.op.inv_diag, out=self.Z)  # Jacobi, plus the coarse correction where there is one
        if self.space is not None:
            self.space.add_correction(R, self.Z)
        return np.einsum("cn,cn->c", R, R), np.einsum("cn,cn->c", R, self.Z)

    def direction(self, P, R, beta) -> None:
        """``p = beta p + z``."""
        P *= beta[:, None]
        P += self.Z


CG_MIN_LINKS = 8.0  # links per node from which the default solve is CG (fast_steps)


def fast_steps(system, b, x0, tol, max_iter, check_every=8):
    """The default ("fast") CPU solve as a generator: :func:`cg_steps` or :func:`chebyshev_steps`.

    CG needs about half of Chebyshev's steps (a third from a warm start), but a CG step makes about
    twenty passes over the (C, N) vectors in fp64 against Chebyshev's ten in fp32.  Where a node has
    many links the sparse product outweighs those passes and CG wins; where it has few the passes
    decide and Chebyshev wins.  Measured on 2 cores, tol 1e-4: a 16k-particle fluid frame (13-15 links
    per cell) 44 CG steps, 67 ms, against 112 Chebyshev sweeps, 148 ms; the Preview bunny's finest
    QuadGraph level (4-5 links per node), warm, 34-47 CG steps, 54-104 ms, against 72 sweeps, 53-60 ms.
    So: CG on the symmetric finite-volume scheme with at least :data:`CG_MIN_LINKS` links per node, or on
    levels of :data:`CG_MIN_NODES` nodes where its step is compiled (:func:`prefers_cg`: a compiled step is
    two passes and its sparse product returns p.A p), Chebyshev elsewhere (and always on the paper's scheme,
    which is not symmetric).
    """
    if prefers_cg(system):
        return cg_steps(system, b, x0, tol, max_iter, check_every)
    return chebyshev_steps(system, b, x0, tol, max_iter, check_every)


CG_MIN_NODES = 8_000  # nodes from which CG with its compiled step is the default on a QuadGraph level


def prefers_cg(system) -> bool:
    """Whether the default solve of ``system`` is CG (else Chebyshev): the symmetric finite-volume scheme, and
    either :data:`CG_MIN_LINKS` links per node or, with the compiled step (:mod:`.compiled_cg`), at least
    :data:`CG_MIN_NODES` nodes (where the coarse space starts, :data:`.coarse_space.MIN_NODES`).  Measured
    on the bunny (3-5 links per node, tol 1e-4, 2 cores, with the bounce, the sky turned 5 degrees and back),
    with both the CG step and the Chebyshev sweep's sparse product compiled (:mod:`.sweeps`): the Draft
    finest level (15,928 nodes) first frame 83-85 against 138-566 ms, warm 31-130 against 54-150 ms (50 against
    64 steps); Preview (41,544) first 196 against 338-767 ms, warm 79-176 against 140-238 ms (67 against 72);
    the Final (401,888) 88 steps, 1.03-1.09 s a warm frame, against 176 block sweeps; every level CG
    (threshold 0) measured the same as 8,000 within the noise.  (With scipy's CSR product the Preview
    finest level was a tie, 145 against 140 ms, hence 50,000 until then.)"""
    if getattr(system, "scheme", None) != "fv":
        return False
    if links_per_node(system) >= CG_MIN_LINKS:
        return True
    return system.n >= CG_MIN_NODES and not compiled_cg.available()


def links_per_node(system) -> float:
    """The mean number of links of a node of the system's graph (its off-diagonal entries per row), cached
    on the system (every frame's solve asks)."""
    k = system.cache.get("links_per_node")
    if k is None:
        nbr = np.asarray(system.nbr)
        k = system.cache["links_per_node"] = float(np.count_nonzero(nbr >= 0)) / max(len(nbr), 1)
    return k


def solve_fast(system, b, x0, tol, max_iter, check_every=8) -> tuple[np.ndarray, LevelSolve]:
    """:func:`fast_steps` run to its end: the solver ``SolveOptions(solver="fast")`` runs on the CPU."""
    return drain(fast_steps(system, b, x0, tol, max_iter, check_every))


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



SOLVER_FUNCTIONS = {"fast": solve_fast, "paper": solve_jacobi, "jacobi": solve_jacobi, "direct": solve_direct}
# the solvers that also run step by step (a progressive frame looks at the iterate after any step)
STEPS_FUNCTIONS = {solve_fast: fast_steps, solve_chebyshev: chebyshev_steps, solve_cg: cg_steps}


def outside_maximum_principle(system: LevelSystem, b: np.ndarray, x: np.ndarray, slack: float = 1e-3) -> bool:
    """True if ``x`` breaks the discrete maximum principle of the FV system, i.e. cannot be its solution.

    The FV matrix of :mod:`.assembly` is a symmetric M-matrix whose surface rows
    are ``... = b_s`` with ``b_s = b_scale q_s``: its solution satisfies
    ``0 <= phi <= max_s b_s / boundary_diag_s`` (= ``max 4 q / (1 - F_dr)``),
    per channel.  With a volume source (``b`` nonzero at inner nodes, :mod:`.beam_source`) the bound
    is ``max_i b_i / r_i`` over those rows too, ``r = A 1`` the row's absorption (an M-matrix with
    ``A (x - c 1) <= 0`` for ``c`` at least that).  An iterate outside those bounds by more than ``slack`` of the
    bound (or not finite) has gone wrong, whatever its residual says.
    """
    if system.scheme != "fv" or system.boundary_diag is None:
        return False
    if not np.all(np.isfinite(x)):
        return True
    bound = maximum_principle_bound(system, b)
    tiny = 1e-300
    lo, hi = bounds(x)
    return bool(np.any(hi > bound * (1.0 + slack) + tiny) or np.any(lo < -slack * bound - tiny))


def maximum_principle_bound(system: LevelSystem, b: np.ndarray) -> np.ndarray:
    """The upper bound of :func:`outside_maximum_principle` per channel, (C,): ``max_s b_s / boundary_diag_s``
    (``max 4 q / (1 - F_dr)``) and, where ``b`` holds a volume source, ``max_i b_i / r_i`` over those rows
    too.  FV scheme only."""
    ni = system.level.n_inner
    bound = (b[ni:] / system.boundary_diag).max(axis=0, initial=0.0)
    if np.any(b[:ni] > 0):
        r = system.absorption_weights()[:ni]
        bound = np.maximum(bound, np.where(b[:ni] > 0, b[:ni] / np.maximum(r, 1e-300), 0.0).max(axis=0))
    return np.maximum(bound, 0.0)


BALANCE_TOL = 1e-3  # the discrete energy balance an iterative FV solve must keep (fraction of the light in)


def energy_imbalance(system: LevelSystem, q: np.ndarray, x: np.ndarray, fdr: float, volume=None) -> float:
    """``max_c |in - out - absorbed| / in`` of a level's FV solution (0 for the paper's scheme).

    Summing the FV rows gives exactly ``sum_s a_s q_s + sum_i v_i = sum_s a_s (1 - F_dr) J+_s + sum_i w_i phi_i``
    with the unclamped ``J+ = (phi_s - 2 q)/(2 (1 + F_dr))``, ``v`` the volume source at the inner nodes
    (or none) and ``w = A 1 - boundary term``
    (:meth:`.assembly.LevelSystem.absorption_weights`, mm^2): a solution that misses it by more than
    the solver tolerance allows has not converged, whatever its residual norm says.
    """
    if system.scheme != "fv" or system.boundary_diag is None:
        return 0.0
    ni = system.level.n_inner
    w = system.absorption_weights()
    a = system.level.area * system.mm_per_unit**2
    p_in = a @ q
    if volume is not None:
        p_in = p_in + np.asarray(volume).sum(axis=0)
    jp = kernels.partial_current(x[ni:], q, fdr)
    gap = np.abs(p_in - a @ ((1.0 - fdr) * jp) - np.einsum("nc,nc->c", w, x))
    lit = p_in > 0
    return float(np.max(gap[lit] / p_in[lit])) if lit.any() else 0.0
