r"""Voronoi-fluid cells from particles (Kang & Kim 2013 sec. 4.1 and 5.1), exact.

The fluid is the union of the particles' balls of radius R.  Cell i is the
part of the fluid nearer to particle i than to any other particle: its
Voronoi cell cut by its ball, ``C_i = Vor(i) ∩ B(p_i, R)`` (within Vor(i) the
nearest particle is i, so a point of the union lies in ball i).  The cells
therefore **partition the fluid exactly**: their volumes sum to the volume of
the union of balls, the fluid volume this module defines.

Per cell (all exact up to rounding, in object units):

* neighbour faces: on the bisecting plane of i and j (d = |p_j - p_i| < 2R),
  the disk of radius ``sqrt(R^2 - d^2/4)`` clipped by the bisecting planes of
  their common neighbours (:mod:`.disk_faces`): area ``S_ij`` and the solid
  angle ``Omega_ij`` it subtends from either particle;
* the surface face: the part of the sphere |x - p_i| = R inside Vor(i), of
  area ``S_is = R^2 (4 pi - sum_j Omega_ij)`` (seen from p_i every direction
  meets exactly one face or the sphere: the cell is convex);
* the volume, as cones from p_i over the faces:
  ``V_i = sum_j (d_ij/2) S_ij / 3 + R S_is / 3``;
* the surface face's vector area ``sum over the sphere part of n dS =
  -sum_j S_ij n_ij`` (the cell's boundary is closed), whose direction is the
  surface normal and whose length is the area of the surface face projected
  on it (see :mod:`.cellgraph` for why the light uses that).

The paper instead counts live samples after a cut-off (64 per cell volume,
36 per face), an estimate with errors of several percent per cell that jump
as particles move; here every quantity is exact and continuous in the
particle positions, which keeps frame-to-frame flicker out of the geometry.
``tests/test_fluid_cells.py`` checks it against a regular lattice (cubes of
volume s^3, faces s^2), two and three overlapping balls (closed forms) and a
voxel count of the union of balls.

Neighbours come from ``scipy.spatial.cKDTree.query_pairs(2R)``.  A full 3D
Voronoi diagram (``scipy.spatial.Voronoi``/``Delaunay``, qhull) was measured
at 400-1100 ms for 16k jittered particles here -- far over the frame budget --
and the ball cut would still be needed on top, so the faces are clipped
directly, in chunks that bound the memory.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from .disk_faces import clipped_disk

FACE_CHUNK = 32768  # faces per vectorised batch (memory: ~ chunk x neighbours x 200 bytes)
KERNEL_BATCH = 2048  # faces per call of the (m, m, faces) clipping kernel
TINY_AREA = 1e-12  # face areas below this fraction of R^2 are no face (lattice ties)


@dataclass
class VoronoiCells:
    """The cells of one frame (object units); cell i belongs to particle i of ``points``."""

    points: np.ndarray  # (N, 3)
    radius: float
    face_i: np.ndarray  # (P,) int64, i < j, faces with area > 0
    face_j: np.ndarray  # (P,)
    face_area: np.ndarray  # (P,) S_ij
    face_distance: np.ndarray  # (P,) d_ij = |p_j - p_i|
    volume: np.ndarray  # (N,) V_i
    sphere_area: np.ndarray  # (N,) S_is: area of the cell's part of the fluid surface (the sphere)
    surface_vector: np.ndarray  # (N, 3) its vector area (outward), = -sum_j S_ij n_ij
    tree: object = None  # the particles' cKDTree (reused by the graph and the occluder)
    seconds: dict = field(default_factory=dict)

    @property
    def n_cells(self) -> int:
        return len(self.points)

    @property
    def n_faces(self) -> np.ndarray:
        """Number of neighbour faces per cell."""
        return np.bincount(np.concatenate([self.face_i, self.face_j]), minlength=self.n_cells)


def neighbour_pairs(points: np.ndarray, radius: float):
    """Pairs (i < j) closer than 2R (their balls overlap): ``cKDTree.query_pairs``."""
    from scipy.spatial import cKDTree

    tree = cKDTree(points)
    pairs = tree.query_pairs(2.0 * radius, output_type="ndarray")
    if len(pairs) == 0:
        return tree, np.zeros(0, np.int64), np.zeros(0, np.int64)
    return tree, pairs[:, 0].astype(np.int64), pairs[:, 1].astype(np.int64)


def build_cells(points: np.ndarray, radius: float, chunk: int = FACE_CHUNK) -> VoronoiCells:
    """Exact Voronoi-fluid cells of particles ``points`` (N, 3) with ball radius ``radius``.

    The input must be finite, without coincident particles and with a
    positive radius (:func:`.particles.prepare_particles` checks and cleans).
    """
    t0 = time.perf_counter()
    P = np.ascontiguousarray(points, dtype=np.float64)
    N = len(P)
    R = float(radius)
    tree, pi, pj = neighbour_pairs(P, R)
    t1 = time.perf_counter()
    # Directed links i -> k: unit direction and length.
    src = np.concatenate([pi, pj])
    dst = np.concatenate([pj, pi])
    order = np.argsort(src, kind="stable")
    src, dst = src[order], dst[order]
    delta = P[dst] - P[src]
    dist = np.sqrt(np.einsum("ij,ij->i", delta, delta))
    unit = delta / dist[:, None]
    counts = np.bincount(src, minlength=N)
    K = int(counts.max()) if len(src) else 0
    start = np.concatenate([[0], np.cumsum(counts)[:-1]])
    slot = np.arange(len(src)) - start[src]
    adj = np.full((N, max(K, 1)), -1, dtype=np.int64)  # directed-link index per (cell, slot)
    adj[src, slot] = np.arange(len(src))
    # One face per undirected pair: the links with src < dst.
    faces = np.nonzero(src < dst)[0]
    area = np.zeros(len(faces))
    omega = np.zeros(len(faces))
    for s in range(0, len(faces), chunk):
        f = faces[s:s + chunk]
        area[s:s + chunk], omega[s:s + chunk] = _face_geometry(R, src[f], dst[f], unit[f], dist[f],
                                                               adj, dst, unit, dist)
    t2 = time.perf_counter()
    fi, fj, fd, fn = src[faces], dst[faces], dist[faces], unit[faces]
    sum_omega = np.bincount(fi, omega, N) + np.bincount(fj, omega, N)
    sphere = R * R * np.maximum(4.0 * np.pi - sum_omega, 0.0)
    cone = 0.5 * fd * area / 3.0
    volume = np.bincount(fi, cone, N) + np.bincount(fj, cone, N) + R * sphere / 3.0
    vec = np.zeros((N, 3))
    for a in range(3):  # the sphere part closes the cell: its vector area is minus the faces'
        vec[:, a] = -np.bincount(fi, area * fn[:, a], N) + np.bincount(fj, area * fn[:, a], N)
    keep = area > TINY_AREA * R * R
    t3 = time.perf_counter()
    return VoronoiCells(points=P, radius=R, face_i=fi[keep], face_j=fj[keep], face_area=area[keep],
                        face_distance=fd[keep], volume=volume, sphere_area=sphere, surface_vector=vec,
                        tree=tree, seconds={"neighbours": t1 - t0, "faces": t2 - t1, "cells": t3 - t2})


def _face_geometry(R, fi, fj, n, d, adj, dst, unit, dist):
    """Area and solid angle of the faces (fi, fj): the disk cut by the common neighbours' planes.

    In the face's frame (origin at the midpoint, basis e1, e2), the plane
    between i and a neighbour k is the line ``a u + b v + c <= 0`` with
    ``(a, b)`` the projection of n_ik and ``c = (d_ij cos(n_ij, n_ik) - d_ik) / 2``.
    """
    F = len(fi)
    h = 0.5 * d
    r = np.sqrt(np.maximum(R * R - h * h, 0.0))
    e1, e2 = _plane_basis(n)
    links = adj[fi]  # (F, K) links i -> k
    valid = links >= 0
    lk = np.where(valid, links, 0)
    valid &= dst[lk] != fj[:, None]
    basis = np.stack([e1, e2, n], axis=2)  # (F, 3, 3), columns e1, e2, n
    proj = np.matmul(unit[lk], basis)  # (F, K, 3): a, b, cos
    a, b = proj[..., 0], proj[..., 1]
    c = 0.5 * (d[:, None] * proj[..., 2] - dist[lk])
    ell = np.sqrt(a * a + b * b)
    flat = ell < 1e-12  # plane_ik parallel to the face: all or nothing
    cn = c / np.where(flat, 1.0, ell)
    rr = r[:, None]
    empty = (valid & ((flat & (c > 0)) | (~flat & (cn >= rr)))).any(axis=1)
    cut = valid & ~flat & (np.abs(cn) < rr) & ~empty[:, None]
    m_per = cut.sum(axis=1)
    mmax = int(m_per.max()) if F else 0
    sel = np.argsort(~cut, axis=1, kind="stable")[:, :mmax]  # the cutting lines first
    inv = 1.0 / np.where(flat, 1.0, ell)
    nx = np.take_along_axis(a * inv, sel, 1)
    ny = np.take_along_axis(b * inv, sel, 1)
    cc = np.take_along_axis(cn, sel, 1)
    area = np.zeros(F)
    omega = np.zeros(F)
    live = ~empty
    for m in np.unique(m_per[live]):
        rows = np.nonzero(live & (m_per == m))[0]
        for s in range(0, len(rows), KERNEL_BATCH):  # temporaries of (m, m, batch) stay in cache
            b = rows[s:s + KERNEL_BATCH]
            area[b], omega[b] = clipped_disk(r[b], h[b], R, nx[b, :m].T, ny[b, :m].T, cc[b, :m].T)
    return area, omega


def _plane_basis(n):
    """Two unit vectors spanning the plane normal to each row of ``n``."""
    axis = np.argmin(np.abs(n), axis=1)
    ref = np.zeros_like(n)
    ref[np.arange(len(n)), axis] = 1.0
    e1 = np.cross(n, ref)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    return e1, np.cross(n, e1)
