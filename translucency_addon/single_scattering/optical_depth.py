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

**Two passes, as in the paper's Table 2.**  ``first_moment`` (stage "ddod")
accumulates the first moment of eq. 4, ``T(x) = integral psi(x, w) w dw``
with psi = exp(-tau) averaged over RGB, at every voxel (quadrature weight
4 pi / n); its divergence ``rho = |div T|`` by central differences gives the
sampling density.  Once the samples are placed, ``sample_sh`` (stage "sh")
recomputes tau per direction, interpolates it at the sample centres along
the lattice rays and projects psi_i(w) = exp(-tau(b_i, w)) on real SH.
Interpolating tau rather than psi matters in dense media, where tau grows by
several units per voxel and a linear interpolation of exp(-tau) across a
voxel would overestimate the light that reaches a sample by a large factor.
"""

from __future__ import annotations

import numpy as np

from ..scene import sh as shmod


class Lattice:
    """tau on the sheared ray lattice of one direction (see the module docstring)."""

    def __init__(self, S: np.ndarray, w: np.ndarray, h_mm: float):
        w = np.asarray(w, dtype=np.float64)
        w = w / np.linalg.norm(w)
        axis, sign, a, b, perm = _frames(w)
        self.perm, self.sign, self.a, self.b = perm, sign, a, b
        St = np.transpose(S, perm + [3])
        if sign < 0:
            St = St[::-1]
        St = np.ascontiguousarray(St, dtype=np.float32)
        self.shape = St.shape[:3]
        n0, n1, n2, C = St.shape
        ka = a * np.arange(n0)
        kb = b * np.arange(n0)
        self.I = np.floor(ka).astype(np.int64)
        self.J = np.floor(kb).astype(np.int64)
        self.fa = ka - self.I
        self.fb = kb - self.J
        # Lattice index ranges (generous by one on each side).
        self.p_lo = int(np.floor(min(0.0, -ka[-1]))) - 1
        p_hi = int(np.ceil(n1 - 1 + max(0.0, -ka[-1]))) + 1
        self.q_lo = int(np.floor(min(0.0, -kb[-1]))) - 1
        q_hi = int(np.ceil(n2 - 1 + max(0.0, -kb[-1]))) + 1
        P1, P2 = p_hi - self.p_lo + 1, q_hi - self.q_lo + 1
        M = n0 + 4
        Spad = np.zeros((n0, n1 + 2 * M, n2 + 2 * M, C), dtype=np.float32)
        Spad[:, M : M + n1, M : M + n2] = St
        L = np.empty((n0, P1, P2, C), dtype=np.float32)
        for k in range(n0):
            x0 = M + self.p_lo + self.I[k]
            y0 = M + self.q_lo + self.J[k]
            sl = Spad[k]
            f, g = np.float32(self.fa[k]), np.float32(self.fb[k])
            L[k] = ((1 - f) * (1 - g)) * sl[x0 : x0 + P1, y0 : y0 + P2]
            if f:
                L[k] += (f * (1 - g)) * sl[x0 + 1 : x0 + 1 + P1, y0 : y0 + P2]
            if g:
                L[k] += ((1 - f) * g) * sl[x0 : x0 + P1, y0 + 1 : y0 + 1 + P2]
            if f and g:
                L[k] += (f * g) * sl[x0 + 1 : x0 + 1 + P1, y0 + 1 : y0 + 1 + P2]
        # tau(k) = step * (sum_{k' >= k} L[k'] - L[k] / 2)   (trapezoid to infinity)
        T = np.cumsum(L[::-1], axis=0)[::-1]
        T -= 0.5 * L
        T *= np.float32(h_mm / abs(w[axis]))
        self.T = T

    def at_voxels(self) -> np.ndarray:
        """tau at every voxel centre, in the original (x, y, z) order, (nx, ny, nz, C)."""
        n0, n1, n2 = self.shape
        T = self.T
        out = np.empty((n0, n1, n2, T.shape[3]), dtype=np.float32)
        for k in range(n0):
            # voxel x sits at lattice coordinate x - ka - p_lo = (x - p_lo - I - 1) + (1 - fa)
            bx = -self.p_lo - self.I[k] - 1
            by = -self.q_lo - self.J[k] - 1
            f, g = np.float32(self.fa[k]), np.float32(self.fb[k])
            t = T[k]
            # weights: fa on the lower lattice point, (1 - fa) on the upper one
            out[k] = (f * g) * t[bx : bx + n1, by : by + n2]
            out[k] += ((1 - f) * g) * t[bx + 1 : bx + 1 + n1, by : by + n2]
            out[k] += (f * (1 - g)) * t[bx : bx + n1, by + 1 : by + 1 + n2]
            out[k] += ((1 - f) * (1 - g)) * t[bx + 1 : bx + 1 + n1, by + 1 : by + 1 + n2]
        if self.sign < 0:
            out = out[::-1]
        return np.transpose(out, list(np.argsort(self.perm)) + [3])

    def at_points(self, u: np.ndarray) -> np.ndarray:
        """tau at points given in voxel-index coordinates (centre of voxel (0,0,0) = 0), (n, C).

        Interpolated along the lattice rays: the ray through a point has the
        same lattice coordinates in the slices before and after it, so tau is
        bilinear across rays and linear along them (exactly the trapezoid
        construction).
        """
        n0 = self.shape[0]
        v = np.asarray(u, dtype=np.float64)[:, self.perm]
        if self.sign < 0:
            v[:, 0] = (n0 - 1) - v[:, 0]
        u0 = np.clip(v[:, 0], 0.0, n0 - 1.0)
        k0 = np.minimum(np.floor(u0).astype(np.int64), max(n0 - 2, 0))
        t = u0 - k0
        P = v[:, 1] - v[:, 0] * self.a - self.p_lo
        Q = v[:, 2] - v[:, 0] * self.b - self.q_lo
        P1, P2 = self.T.shape[1:3]
        P = np.clip(P, 0.0, P1 - 1.000001)
        Q = np.clip(Q, 0.0, P2 - 1.000001)
        p0 = np.floor(P).astype(np.int64)
        q0 = np.floor(Q).astype(np.int64)
        fp = (P - p0)[:, None]
        fq = (Q - q0)[:, None]
        out = 0.0
        for k, wk in ((k0, 1.0 - t), (np.minimum(k0 + 1, n0 - 1), t)):
            Tk = self.T
            val = ((1 - fp) * (1 - fq) * Tk[k, p0, q0] + fp * (1 - fq) * Tk[k, p0 + 1, q0]
                   + (1 - fp) * fq * Tk[k, p0, q0 + 1] + fp * fq * Tk[k, p0 + 1, q0 + 1])
            out = out + wk[:, None] * val
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
    return Lattice(sigma_t, w, h_mm).at_voxels()


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


def _field(volume):
    fac = _channel_factor(volume.sigma_t, volume.medium)
    return fac if fac is not None else (volume.sigma_t, None)


def first_moment(volume, directions: np.ndarray, *, progress=None) -> np.ndarray:
    """T(x) = integral psi(x, w) w dw (eq. 4) at every voxel centre, RGB mean of psi, (nx, ny, nz, 3).

    Quadrature over the ``directions`` (uniform, weight 4 pi / n).
    ``progress(fraction)`` is called every few directions (it may raise).
    """
    dirs = np.asarray(directions, dtype=np.float64)
    n = len(dirs)
    field, rgb = _field(volume)
    h_mm = volume.h * volume.mm_per_unit
    T = np.zeros(tuple(volume.shape) + (3,), dtype=np.float64)
    wq = 4.0 * np.pi / n
    for j, w in enumerate(dirs):
        tau = Lattice(field, w, h_mm).at_voxels()
        if rgb is not None:
            psi = np.exp(-tau * rgb).mean(axis=-1)
        else:
            psi = np.exp(-tau).mean(axis=-1)
        for c in range(3):
            T[..., c] += (wq * w[c]) * psi
        if progress is not None and (j % 8 == 7 or j == n - 1):
            progress((j + 1) / n)
    return T


PSI_NEGLIGIBLE = 1e-7  # sample_sh: a chord this black adds < 1e-6 of the world's light to any coefficient
# sample_sh: the SH order of the world's light reflected inside (entry.py eq. 3): the engine's environment is
# order 2 (scene.environment_map.ENGINE_ORDER: a World's SH beside its extracted sun, a lamp), so higher
# coefficients of that term would multiply zeros; kept to order 2 they cost a third of order 4's
REFLECTED_ORDER = 2


def sample_sh(volume, directions: np.ndarray, points: np.ndarray, order: int, *, batch: int = 32,
              progress=None, entry=None):
    """SH coefficients of psi_i(w) = exp(-tau(b_i, w)) at ``points`` (N, 3), ((N, K, 3) float32).

    tau is recomputed per direction on the lattice and interpolated at the
    points (in tau, not in exp(-tau): the exponential of an interpolated depth
    stays right where tau grows by several units per voxel, as in dense media).
    ``entry``: a :class:`.entry.WorldEntry` of the points (eq. 2: the world light's weight g and the outside
    direction w_out its light comes from, per point and direction; eq. 3: the same for the chord's light
    reflected inside, its reflected chords' depth by :func:`.chords.segment_depth`); then the coefficients of
    ``g psi`` on the SH basis at ``w_out`` too, summed over eq. 3's terms, from the same depths:
    ``(psi's, g psi's)``.  Its chords are cast only where psi reaches :data:`PSI_NEGLIGIBLE` in some channel
    (in dense media most chords into the object are black).
    """
    dirs = np.asarray(directions, dtype=np.float64)
    n = len(dirs)
    K = shmod.n_coefficients(order)
    Y = (shmod.sh_basis(dirs, order) * (4.0 * np.pi / n)).astype(np.float64)  # (n, K)
    field, rgb = _field(volume)
    h_mm = volume.h * volume.mm_per_unit
    u = (np.asarray(points, dtype=np.float64) - volume.origin) / volume.h - 0.5
    N = len(u)
    coef = np.zeros((K, N * 3), dtype=np.float64)
    coef_entry = None if entry is None else np.zeros((N, K, 3), dtype=np.float64)  # point-major: row updates
    if entry is not None:
        from .chords import ChordField, segment_depth

        chord_field = ChordField.of_volume(volume)

        def depth(a, b):
            return segment_depth(chord_field, a, b)
    for start in range(0, n, batch):
        idx = np.arange(start, min(n, start + batch))
        psi = np.empty((len(idx), N * 3), dtype=np.float64)
        for j, di in enumerate(idx):
            tau = Lattice(field, dirs[di], h_mm).at_points(u)
            if rgb is not None:
                tau = tau * rgb
            psi[j] = np.exp(-tau).reshape(-1)
        coef += Y[idx].T @ psi
        if coef_entry is not None:
            for j, di in enumerate(idx):  # the basis at each point's outside direction, times g psi
                p3 = psi[j].reshape(N, 3)
                need = np.flatnonzero(p3.max(axis=1) > PSI_NEGLIGIBLE)
                if not need.size:
                    continue
                for k, (rows, g, w_out) in enumerate(entry.paths(dirs[di], need, p3[need], depth)):
                    at = need[rows]
                    o = order if k == 0 else min(order, REFLECTED_ORDER)
                    Yo = shmod.sh_basis(w_out, o) * (4.0 * np.pi / n)  # (m, K or fewer)
                    gp = (g[:, None] if g.ndim == 1 else g) * p3[at]
                    coef_entry[at, :Yo.shape[1]] += Yo[:, :, None] * gp[:, None, :]  # rows of (K, 3)
        if progress is not None:
            progress(float(idx[-1] + 1) / n)
    sh = np.ascontiguousarray(coef.reshape(K, N, 3).transpose(1, 0, 2)).astype(np.float32)
    return sh if coef_entry is None else (sh, coef_entry.astype(np.float32))


def divergence_density(T: np.ndarray, h: float) -> np.ndarray:
    """rho = |div T| by central differences (one-sided at the grid border), (nx, ny, nz)."""
    div = np.zeros(T.shape[:3], dtype=np.float64)
    for ax in range(3):
        div += np.gradient(T[..., ax].astype(np.float64), h, axis=ax)
    return np.abs(div)
