"""Small closed test meshes (outward oriented) for the single-scattering tests and bench.

Kept inside this package so the tests do not depend on other modules' helpers.
"""

from __future__ import annotations

import numpy as np


def uv_sphere(radius: float = 1.0, n_lat: int = 24, n_lon: int = 48, center=(0.0, 0.0, 0.0)):
    """Latitude/longitude sphere with poles (closed, outward)."""
    th = np.linspace(0, np.pi, n_lat + 1)[1:-1]
    ph = np.linspace(0, 2 * np.pi, n_lon, endpoint=False)
    T, Pp = np.meshgrid(th, ph, indexing="ij")
    V = np.stack([np.sin(T) * np.cos(Pp), np.sin(T) * np.sin(Pp), np.cos(T)], -1).reshape(-1, 3)
    V = np.vstack([[0, 0, 1.0], V, [0, 0, -1.0]])
    F = []
    idx = lambda i, j: 1 + i * n_lon + (j % n_lon)  # noqa: E731
    for j in range(n_lon):
        F.append([0, idx(0, j), idx(0, j + 1)])
        F.append([len(V) - 1, idx(n_lat - 2, j + 1), idx(n_lat - 2, j)])
    for i in range(n_lat - 2):
        for j in range(n_lon):
            a, b, c, d = idx(i, j), idx(i + 1, j), idx(i + 1, j + 1), idx(i, j + 1)
            F.append([a, b, c])
            F.append([a, c, d])
    return V * radius + np.asarray(center, dtype=np.float64), np.asarray(F, dtype=np.int64)


def box(size=(1.0, 1.0, 1.0), center=(0.0, 0.0, 0.0), n: int = 8):
    """Axis-aligned box, each face split into n x n quads, shared vertices merged."""
    g = np.linspace(-0.5, 0.5, n + 1)
    Vs, Fs, off = [], [], 0
    for axis in range(3):
        for sign in (-1.0, 1.0):
            u, v = [a for a in range(3) if a != axis]
            U, W = np.meshgrid(g, g, indexing="ij")
            P = np.zeros((n + 1, n + 1, 3))
            P[..., axis] = 0.5 * sign
            P[..., u] = U
            P[..., v] = W
            k = np.arange((n + 1) ** 2).reshape(n + 1, n + 1) + off
            a, b, c, d = k[:-1, :-1], k[1:, :-1], k[1:, 1:], k[:-1, 1:]
            tris = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
            nrm = np.cross(np.eye(3)[u], np.eye(3)[v])
            if np.dot(nrm, np.eye(3)[axis]) * sign < 0:
                tris = tris[:, [0, 2, 1]]
            Vs.append(P.reshape(-1, 3))
            Fs.append(tris)
            off += (n + 1) ** 2
    V = np.concatenate(Vs)
    F = np.concatenate(Fs)
    key = np.round(V * 4 * n).astype(np.int64)
    _, first, inv = np.unique(key, axis=0, return_index=True, return_inverse=True)
    V = V[first] * np.asarray(size, dtype=np.float64) + np.asarray(center, dtype=np.float64)
    return V, inv.reshape(-1)[F]


def torus(major: float = 1.0, minor: float = 0.3, n_major: int = 48, n_minor: int = 16, center=(0.0, 0.0, 0.0), axis: int = 2):
    """Torus around ``axis`` (closed, outward)."""
    u = np.linspace(0, 2 * np.pi, n_major, endpoint=False)
    v = np.linspace(0, 2 * np.pi, n_minor, endpoint=False)
    U, W = np.meshgrid(u, v, indexing="ij")
    x = (major + minor * np.cos(W)) * np.cos(U)
    y = (major + minor * np.cos(W)) * np.sin(U)
    z = minor * np.sin(W)
    V = np.stack([x, y, z], -1).reshape(-1, 3)
    i, j = np.meshgrid(np.arange(n_major), np.arange(n_minor), indexing="ij")
    a = i * n_minor + j
    b = ((i + 1) % n_major) * n_minor + j
    c = ((i + 1) % n_major) * n_minor + (j + 1) % n_minor
    d = i * n_minor + (j + 1) % n_minor
    F = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
    if axis != 2:
        perm = {0: [2, 0, 1], 1: [1, 2, 0]}[axis]
        V = V[:, perm]
    return V + np.asarray(center, dtype=np.float64), F
