"""Direction-dependent optical depth, its SH projection and the first moment (sec. 4.1-4.2).

For each of ``n`` uniform directions w (spherical Fibonacci set) we need, at
every voxel centre x,

    tau(x, w) = integral_0^inf sigma_t(x + s w) ds                 (per mm, RGB)

i.e. the optical depth from x *towards* w, to infinity.  Integrating to
infinity (not to the first exit) is the attenuation of light arriving from a
source outside the object along -w, also in a concave object whose ray leaves
and re-enters; for a view direction w it is the attenuation towards a camera
that sees the exit point.

**Sheared ray lattice (no loop per ray).**  For a direction whose dominant
axis is ``a`` (|w_a| is the largest component), the grid is permuted so that
``a`` comes first and flipped so that w_a > 0.  Rays of the lattice are
parallel to w and pass through the slice planes of voxel centres k = 0 .. n0-1
at index positions ``(k, p + k*wx/w_a, q + k*wy/w_a)`` for integer (p, q):
the lattice spacing across the rays is at most one voxel.  In slice k every
ray sits at the same fractional offset from the voxel centres, so sampling
sigma_t there (bilinear in the slice = the trilinear voxel field) is a
weighted sum of four shifted copies of the slice, for all rays at once.  A
reverse cumulative sum along k (trapezoid rule, step ``h / |w_a|``) gives tau
to infinity on the lattice, and the same four-shift interpolation brings it
back to the voxel centres.  The Python loop runs over slices (n0 per
direction), never over rays.

**Projection.**  psi(x, w) = exp(-tau(x, w)) is accumulated into real SH
coefficients at every voxel (equal quadrature weights 4 pi / n), in batches
of directions with one matrix product.  The first moment of eq. 4,
``T(x) = integral psi(x, w) w dw``, is read off the order-1 coefficients
(Y_1m are c1*(y, z, x), c1 = sqrt(3 / (4 pi))), averaged over RGB; its
divergence ``rho = |div T|`` by central differences gives the sampling density.
"""

from __future__ import annotations

import numpy as np

from .. import sh as shmod


def _lattice_tau(S: np.ndarray, a: float, b: float, step: float) -> np.ndarray:
    """tau to infinity along +axis-0 sheared by (a, b) per slice, at voxel centres.

    ``S`` is (n0, n1, n2, C) sigma_t in the permuted frame; returns the same shape.
    """
    n0, n1, n2, C = S.shape
    ka = a * np.arange(n0)
    kb = b * np.arange(n0)
    I = np.floor(ka).astype(np.int64)
    J = np.floor(kb).astype(np.int64)
    fa = ka - I
    fb = kb - J
    # Lattice index ranges (generous by one on each side).
    p_lo = int(np.floor(min(0.0, -ka[-1]))) - 1
    p_hi = int(np.ceil(n1 - 1 + max(0.0, -ka[-1]))) + 1
    q_lo = int(np.floor(min(0.0, -kb[-1]))) - 1
    q_hi = int(np.ceil(n2 - 1 + max(0.0, -kb[-1]))) + 1
    P1, P2 = p_hi - p_lo + 1, q_hi - q_lo + 1
    M = n0 + 4
    Spad = np.zeros((n0, n1 + 2 * M, n2 + 2 * M, C), dtype=np.float32)
    Spad[:, M : M + n1, M : M + n2] = S
    L = np.empty((n0, P1, P2, C), dtype=np.float32)
    for k in range(n0):
        x0 = M + p_lo + I[k]
        y0 = M + q_lo + J[k]
        s = Spad[k]
        f, g = np.float32(fa[k]), np.float32(fb[k])
        L[k] = ((1 - f) * (1 - g)) * s[x0 : x0 + P1, y0 : y0 + P2]
        if f:
            L[k] += (f * (1 - g)) * s[x0 + 1 : x0 + 1 + P1, y0 : y0 + P2]
        if g:
            L[k] += ((1 - f) * g) * s[x0 : x0 + P1, y0 + 1 : y0 + 1 + P2]
        if f and g:
            L[k] += (f * g) * s[x0 + 1 : x0 + 1 + P1, y0 + 1 : y0 + 1 + P2]
    # tau(k) = step * (sum_{k' >= k} L[k'] - L[k] / 2)   (trapezoid to infinity)
    T = np.cumsum(L[::-1], axis=0)[::-1]
    T -= 0.5 * L
    T *= np.float32(step)
    out = np.empty((n0, n1, n2, C), dtype=np.float32)
    for k in range(n0):
        # voxel x sits at lattice coordinate x - ka - p_lo = (x - p_lo - I - 1) + (1 - fa)
        bx = -p_lo - I[k] - 1
        by = -q_lo - J[k] - 1
        f, g = np.float32(fa[k]), np.float32(fb[k])
        t = T[k]
        # weights: fa on the lower lattice point, (1 - fa) on the upper one
        out[k] = (f * g) * t[bx : bx + n1, by : by + n2]
        out[k] += ((1 - f) * g) * t[bx + 1 : bx + 1 + n1, by : by + n2]
        out[k] += (f * (1 - g)) * t[bx : bx + n1, by + 1 : by + 1 + n2]
        out[k] += ((1 - f) * (1 - g)) * t[bx + 1 : bx + 1 + n1, by + 1 : by + 1 + n2]
    return out


def _frames(w: np.ndarray):
    """Permutation, flip and shear for a direction: (axis, sign, a, b, perm)."""
    axis = int(np.argmax(np.abs(w)))
    sign = 1.0 if w[axis] >= 0 else -1.0
    others = [i for i in range(3) if i != axis]
    a = w[others[0]] / abs(w[axis])
    b = w[others[1]] / abs(w[axis])
    return axis, sign, a, b, [axis] + others


def optical_depth(sigma_t: np.ndarray, h_mm: float, w) -> np.ndarray:
    """tau(x, w) to infinity at every voxel centre of ``sigma_t`` (nx, ny, nz, C) for unit ``w``."""
    w = np.asarray(w, dtype=np.float64)
    w = w / np.linalg.norm(w)
    axis, sign, a, b, perm = _frames(w)
    S = np.transpose(sigma_t, perm + [3])
    if sign < 0:
        S = S[::-1]
    tau = _lattice_tau(np.ascontiguousarray(S, dtype=np.float32), a, b, h_mm / abs(w[axis]))
    if sign < 0:
        tau = tau[::-1]
    inv = np.argsort(perm)
    return np.transpose(tau, list(inv) + [3])


def _channel_factor(sigma_t: np.ndarray, medium: np.ndarray):
    """If sigma_t is one scalar field times an RGB constant, return (scalar, rgb); else None."""
    st = sigma_t.reshape(-1, 3)
    m = medium.reshape(-1)
    if not m.any():
        return None
    ref = st[m][0].astype(np.float64)
    if np.any(ref <= 0):
        return None
    ratio = st[m] / ref
    if np.ptp(ratio, axis=1).max() > 1e-5 * max(1.0, float(ratio.max())):
        return None
    rgb = ref / ref.max()
    scalar = sigma_t[..., int(np.argmax(ref))][..., None]  # blockers keep their huge value
    return scalar.astype(np.float32), rgb.astype(np.float32)


def directional_sh(volume, directions: np.ndarray, order: int, *, batch: int = 16, progress=None):
    """SH coefficients of psi = exp(-tau) at every voxel, ((order+1)^2, nx, ny, nz, 3) float32.

    ``progress(fraction)`` is called after every batch of directions (it may raise).
    """
    dirs = np.asarray(directions, dtype=np.float64)
    n = len(dirs)
    K = shmod.n_coefficients(order)
    Y = shmod.sh_basis(dirs, order) * (4.0 * np.pi / n)  # (n, K)
    shape = tuple(volume.shape)
    nvox = int(np.prod(shape))
    h_mm = volume.h * volume.mm_per_unit
    fac = _channel_factor(volume.sigma_t, volume.medium)
    if fac is not None:
        field, rgb = fac
    else:
        field, rgb = volume.sigma_t, None
    coef = np.zeros((K, nvox * 3), dtype=np.float32)
    # Group directions by (axis, sign) so permuted copies are made once per group.
    for start in range(0, n, batch):
        idx = np.arange(start, min(n, start + batch))
        psi = np.empty((len(idx), nvox * 3), dtype=np.float32)
        for j, di in enumerate(idx):
            tau = optical_depth(field, h_mm, dirs[di])  # (nx, ny, nz, C)
            if rgb is not None:
                tau = tau * rgb  # broadcast (.., 1) * (3,)
            np.exp(-tau, out=psi[j].reshape(shape + (3,)))
        coef += Y[idx].T.astype(np.float32) @ psi
        if progress is not None:
            progress(float(idx[-1] + 1) / n)
    return coef.reshape((K,) + shape + (3,))


def first_moment(coef: np.ndarray) -> np.ndarray:
    """T(x) = integral psi(x, w) w dw (eq. 4) from the order-1 SH coefficients, RGB mean, (nx, ny, nz, 3)."""
    c1 = np.sqrt(3.0 / (4.0 * np.pi))
    m = coef[1:4].mean(axis=-1)  # (3, nx, ny, nz): coefficients of y, z, x
    return np.stack([m[2], m[0], m[1]], axis=-1) / c1


def divergence_density(T: np.ndarray, h: float) -> np.ndarray:
    """rho = |div T| by central differences (one-sided at the grid border), (nx, ny, nz)."""
    div = np.zeros(T.shape[:3], dtype=np.float64)
    for ax in range(3):
        div += np.gradient(T[..., ax].astype(np.float64), h, axis=ax)
    return np.abs(div)
