"""Real spherical harmonics up to order 4 (25 coefficients) and sphere sampling.

Used by single scattering (Bernabei et al. sec. 3.1: the per-sample
attenuation psi_i(w) = exp(-tau(b_i, w)) is stored as SH coefficients) and by
the environment light (irradiance from 9 coefficients, Ramamoorthi & Hanrahan
2001).  The polynomial forms are the standard orthonormal real SH without the
Condon-Shortley phase (Sloan, "Stupid Spherical Harmonics Tricks", 2008); the
GLSL kernel uses the same constants, and a test checks orthonormality.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

# Orthonormality normalisation constants, index = l*l + l + m.
_C = {
    "c00": 0.282094791773878,
    "c1": 0.488602511902920,
    "c2a": 1.092548430592079,
    "c20": 0.315391565252520,
    "c22": 0.546274215296040,
    "c33": 0.590043589926644,
    "c32": 2.890611442640554,
    "c31": 0.457045799464466,
    "c30": 0.373176332590115,
    "c32b": 1.445305721320277,
    "c44": 2.503342941796705,
    "c43": 1.770130769779931,
    "c42": 0.946174695757560,
    "c41": 0.669046543557289,
    "c40": 0.105785546915204,
    "c42b": 0.473087347878780,
    "c44b": 0.625835735449176,
}


def n_coefficients(order: int) -> int:
    """(order + 1)^2: 9 for order 2, 16 for 3, 25 for 4."""
    if order not in (0, 1, 2, 3, 4):
        raise ValueError(f"SH order must be 0..4, got {order}")
    return (order + 1) ** 2


def sh_basis(dirs: np.ndarray, order: int) -> np.ndarray:
    """Real SH basis at unit directions, (n, (order+1)^2)."""
    d = np.asarray(dirs, dtype=np.float64).reshape(-1, 3)
    x, y, z = d[:, 0], d[:, 1], d[:, 2]
    c = _C
    cols = [np.full(len(d), c["c00"])]
    if order >= 1:
        cols += [c["c1"] * y, c["c1"] * z, c["c1"] * x]
    if order >= 2:
        cols += [
            c["c2a"] * x * y,
            c["c2a"] * y * z,
            c["c20"] * (3 * z * z - 1),
            c["c2a"] * x * z,
            c["c22"] * (x * x - y * y),
        ]
    if order >= 3:
        cols += [
            c["c33"] * y * (3 * x * x - y * y),
            c["c32"] * x * y * z,
            c["c31"] * y * (5 * z * z - 1),
            c["c30"] * z * (5 * z * z - 3),
            c["c31"] * x * (5 * z * z - 1),
            c["c32b"] * z * (x * x - y * y),
            c["c33"] * x * (x * x - 3 * y * y),
        ]
    if order >= 4:
        z2 = z * z
        cols += [
            c["c44"] * x * y * (x * x - y * y),
            c["c43"] * y * z * (3 * x * x - y * y),
            c["c42"] * x * y * (7 * z2 - 1),
            c["c41"] * y * z * (7 * z2 - 3),
            c["c40"] * (35 * z2 * z2 - 30 * z2 + 3),
            c["c41"] * x * z * (7 * z2 - 3),
            c["c42b"] * (x * x - y * y) * (7 * z2 - 1),
            c["c43"] * x * z * (x * x - 3 * y * y),
            c["c44b"] * (x * x * (x * x - 3 * y * y) - y * y * (3 * x * x - y * y)),
        ]
    return np.stack(cols, axis=1)


def fibonacci_directions(n: int) -> np.ndarray:
    """n nearly uniform unit directions on the sphere (spherical Fibonacci lattice)."""
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    r = np.sqrt(np.maximum(0.0, 1.0 - z * z))
    phi = i * np.pi * (3.0 - np.sqrt(5.0))
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def project(values: np.ndarray, dirs: np.ndarray, order: int) -> np.ndarray:
    """SH coefficients of a function sampled at uniform ``dirs``.

    ``values`` is (n_dirs, ...) -> returns ((order+1)^2, ...) using equal
    quadrature weights 4 pi / n_dirs.
    """
    Y = sh_basis(dirs, order)
    v = np.asarray(values, dtype=np.float64)
    return np.tensordot(Y.T * (4.0 * np.pi / len(dirs)), v, axes=(1, 0))


def evaluate(coeffs: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """Evaluate SH coefficients (k, ...) at directions (n, 3) -> (n, ...)."""
    k = coeffs.shape[0]
    order = int(round(np.sqrt(k))) - 1
    return np.tensordot(sh_basis(dirs, order), coeffs, axes=(1, 0))


# Clamped-cosine convolution weights A_l (Ramamoorthi & Hanrahan 2001).
_A = np.array([np.pi] + [2.0 * np.pi / 3.0] * 3 + [np.pi / 4.0] * 5)


@lru_cache(maxsize=64)
def transmission_kernel(eta: float, order: int = 2) -> np.ndarray:
    """Zonal kernel of q (eq. 3) for SH radiance: A_l = 2 pi int_0^1 mu F_t(mu) P_l(mu) dmu.

    By the Funk-Hecke theorem, for a radiance L(w) = sum L_lm Y_lm(w) the
    transmitted diffuse flux of eq. 3 is exactly q(n) = sum_lm A_l L_lm Y_lm(n).
    With F_t = 1 this gives Ramamoorthi & Hanrahan's pi, 2 pi/3, pi/4.
    Cached per (eta, order), read-only: the 128-point Gauss-Legendre rule alone (an eigenvalue problem
    in numpy) cost ~15 ms of every frame's light pass.
    """
    from .fresnel import fresnel_transmittance

    x, w = np.polynomial.legendre.leggauss(128)
    mu = 0.5 * (x + 1.0)
    wt = 0.5 * w * mu * fresnel_transmittance(mu, eta)
    A = np.array([2.0 * np.pi * np.sum(wt * np.polynomial.legendre.Legendre.basis(l)(mu)) for l in range(order + 1)])
    out = np.repeat(A, [2 * l + 1 for l in range(order + 1)])
    out.flags.writeable = False
    return out


def transmitted_flux_from_sh(sh: np.ndarray, normals: np.ndarray, eta: float) -> np.ndarray:
    """q(n) of eq. 3 for SH radiance coefficients (k, 3), exact for band-limited radiance."""
    sh = np.asarray(sh)
    order = int(round(np.sqrt(sh.shape[0]))) - 1
    Y = sh_basis(normals, order)
    return np.maximum(Y @ (transmission_kernel(float(eta), int(order))[:, None] * sh), 0.0)
