"""Spectral bounds and deflation of a level's system (what the Chebyshev iteration needs).

For ``A x = b`` with the Jacobi preconditioner D = diag(A), Chebyshev runs on
an interval ``[lambda_min, lambda_max]`` of the spectrum of ``D^-1 A``:

* :func:`gershgorin_upper`: ``lambda_max <= max_i 1 + sum_j |a_ij| / a_ii`` (a
  guaranteed bound, <= 2 for the symmetric M-matrix of :mod:`.assembly`);
* :func:`lanczos_lower`: an estimate of ``lambda_min`` by Lanczos on
  ``D^-1/2 A D^-1/2``;
* :func:`deflation`: on leak-dominated levels, the per-component constants
  carry an isolated bottom eigenvalue; a Galerkin correction removes it so
  Chebyshev runs on ``[lambda_2, lambda_max]``.

One Lanczos loop (:func:`lanczos_bottom`) serves both estimates.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .assembly import LevelSystem
from .graph import graph_components


def gershgorin_upper(system: LevelSystem) -> np.ndarray:
    """Upper bound of the spectrum of D^-1 A per channel: max_i 1 + sum_j |a_ij| / a_ii (<= 2)."""
    return (1.0 + system.off.sum(axis=1) / system.diag).max(axis=0)


def lanczos_bottom(matvec, v: np.ndarray, steps: int) -> np.ndarray:
    """Smallest Ritz value per channel of a symmetric operator, from the unit start vectors ``v`` (n, C).

    Plain Lanczos (no re-orthogonalisation; only the bottom value is used):
    ``steps`` products, stopping early when every channel's beta vanishes.
    """
    nc = v.shape[1]
    v_prev = np.zeros_like(v)
    beta = np.zeros(nc)
    alphas, betas = [], []
    tmp = np.empty_like(v)
    for _ in range(int(steps)):
        w = matvec(v)
        alpha = np.einsum("nc,nc->c", w, v)
        w -= np.multiply(alpha, v, out=tmp)  # w - alpha v - beta v_prev, in place (same order of operations)
        w -= np.multiply(beta, v_prev, out=tmp)
        alphas.append(alpha)
        beta = np.linalg.norm(w, axis=0)
        betas.append(beta)
        if np.all(beta < 1e-14):
            break
        w /= np.maximum(beta, 1e-300)
        v_prev, v = v, w
    out = np.zeros(nc)
    if not alphas:
        return np.full(nc, np.nan)
    al = np.array(alphas)
    be = np.array(betas)[:-1]
    for c in range(nc):
        Tm = np.diag(al[:, c])
        if len(be):
            Tm += np.diag(be[:, c], 1) + np.diag(be[:, c], -1)
        out[c] = np.linalg.eigvalsh(Tm)[0]
    return out


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
    nc = system.diag.shape[1]
    noise = rng.standard_normal((n, nc))
    smooth = np.sqrt(system.diag)
    v = smooth / np.linalg.norm(smooth, axis=0) + 0.05 * noise / np.linalg.norm(noise, axis=0)
    v /= np.linalg.norm(v, axis=0)
    matvec, v = scaled_operator(system, v)
    out = lanczos_bottom(matvec, v, steps)
    return np.maximum(out, 1e-12)


def scaled_operator(system: LevelSystem, v: np.ndarray):
    """``u -> D^-1/2 A D^-1/2 u`` as one fp64 CSR product, and ``v`` (n, C) in its node order.

    The sweeps' layout (:func:`.sweeps.sweep_pattern`: channels one block-diagonal CSR, nodes in
    reverse Cuthill-McKee order) with each entry scaled by ``d_i^-1/2 d_j^-1/2``, so a Lanczos step is
    one compiled product over contiguous channel rows instead of ``LevelSystem.apply``'s three strided
    ones and four scalings (Final bunny, 408k nodes: the 40 steps of :func:`lanczos_lower` ~2x faster).
    The vectors are (n, C) views of channel-major (C, n) arrays; a permutation of the nodes leaves the
    Ritz values as they are.  Systems without the kernel arrays (``nbr``/``off``) keep ``apply``.
    """
    import scipy.sparse as sp

    from .sweeps import rcm_order, sweep_pattern

    if getattr(system, "nbr", None) is None or getattr(system, "off", None) is None:
        dinv_sqrt = 1.0 / np.sqrt(system.diag)
        return (lambda u: dinv_sqrt * system.apply(dinv_sqrt * u)), v
    n, nc = system.n, system.diag.shape[1]
    perm = rcm_order(system)
    indptr, indices, src = sweep_pattern(system)
    rows = np.repeat(np.arange(n), np.diff(indptr))
    dis = 1.0 / np.sqrt(system.diag[perm])
    nnz = len(indices)
    data = np.empty(nnz * nc)
    for c in range(nc):  # -A's entries of channel c, scaled: -(D^-1/2 A D^-1/2)
        vals = np.concatenate([system.off[:, :, c].ravel(), -system.diag[:, c]])[src]
        data[c * nnz:(c + 1) * nnz] = vals * dis[rows, c] * dis[indices, c]
    ind = np.concatenate([indices + c * n for c in range(nc)])
    ptr = np.concatenate([indptr[:-1] + c * nnz for c in range(nc)] + [[nnz * nc]])
    neg_m = sp.csr_matrix((data, ind, ptr), shape=(n * nc, n * nc))

    def matvec(u):  # u (n, C), any layout -> (n, C) view of a (C, n) array
        return -(neg_m @ np.ascontiguousarray(u.T).reshape(-1)).reshape(nc, n).T

    return matvec, np.ascontiguousarray(v[perm].T).T


def spectral_bounds(system: LevelSystem, safety: float = 0.8):
    if system.lam_max is None:
        system.lam_max = gershgorin_upper(system)
        system.lam_min = np.minimum(safety * lanczos_lower(system), 0.5 * system.lam_max)
    return system.lam_min, system.lam_max



def linear_rayleigh_bound(system: LevelSystem, labels: np.ndarray, dsum: np.ndarray) -> np.ndarray:
    """An upper bound of lambda_2 (the bottom of D^-1 A orthogonal to each component's constant), per channel.

    The Rayleigh quotient ``v^T A v / v^T D v`` of any v that is D-orthogonal to the constant on every
    component bounds from above the smallest eigenvalue on that subspace (Courant-Fischer), so it is
    >= the lambda_2 that :func:`deflation` asks Lanczos for.  Here v is each coordinate x, y, z of the
    node positions minus its D-weighted mean per component (a smooth, slowly varying mode): three
    products with A, O(nnz), against the check's 40 Lanczos steps.  On an object large against its
    diffusion length (the bunny in marble) absorption dominates both this quotient and rho, so it lands
    within 2x of rho and the check is decided without Lanczos (Final bunny: 2.2 s of a first frame);
    on a leak-dominated piece the couplings dominate it, it says nothing, and Lanczos runs as before.
    """
    n_comp = dsum.shape[0]
    nc = system.diag.shape[1]
    pos = np.asarray(system.level.position, dtype=np.float64)
    best = np.full(nc, np.inf)
    for k in range(pos.shape[1]):
        v = np.repeat(pos[:, k:k + 1], nc, axis=1)
        for c in range(nc):
            mean = np.bincount(labels, weights=system.diag[:, c] * v[:, c], minlength=n_comp) / dsum[:, c]
            v[:, c] -= mean[labels]
        den = np.einsum("nc,nc,nc->c", v, system.diag, v)
        num = np.einsum("nc,nc->c", v, system.apply(v))
        ok = den > 0
        best = np.where(ok, np.minimum(best, num / np.where(ok, den, 1.0)), best)
    return best


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



def deflation(system: LevelSystem, safety: float = 0.8, gap: float | None = None,
              steps: int = 40, seed: int = 1) -> Deflation | None:
    """The constant-mode deflation of a leak-dominated level, or ``None`` when it would not help.

    Per channel: the Rayleigh quotient of each component's constant,
    ``rho = 1^T A 1 / 1^T D 1`` (an upper bound of the lowest eigenvalue on
    that piece), against a Lanczos estimate of the bottom of the spectrum
    orthogonal to those constants (by interlacing it is >= lambda_{k+1}).
    The channel is deflated when every ``rho`` is ``gap`` times below it.
    Only looked at when the smallest eigenvalue estimate is small (< 1e-3), and the
    Lanczos run skipped when an O(nnz) upper bound of lambda_2 (:func:`linear_rayleigh_bound`)
    already fails the test on every channel; cached on the system.  Used by the CPU Chebyshev solve only
    (:func:`spectral_bounds`, which the GPU path shares, is unchanged).
    """
    if system.scheme != "fv":
        return None
    gap = DEFLATION_GAP if gap is None else gap
    cache = system.cache.get("deflation", False)
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
        # Lanczos below looks for lam2 = the bottom of the spectrum orthogonal to the constants.  Any
        # vector orthogonal to them bounds lam2 from above by its Rayleigh quotient; a channel whose
        # bound is already within ``gap`` of rho cannot pass the test, whatever Lanczos finds.
        upper = linear_rayleigh_bound(system, labels, dsum)
        if not np.any(gap * rho < upper):
            system.cache["deflation"] = None
            return None
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
        steps_left = int(min(steps, system.n - n_comp))
        if steps_left > 0:
            lam2 = lanczos_bottom(lambda u: project(system.apply(u / sq) / sq), v, steps_left)
            mask = (gap * rho < lam2) & (E > 0).all(axis=0)
            if mask.any():
                out = Deflation(labels=labels, a1=a1, E=np.where(E > 0, E, 1.0), mask=mask,
                                lam_min=np.where(mask, np.minimum(safety * lam2, 0.5 * system.lam_max), lam_min))
    system.cache["deflation"] = out
    return out

