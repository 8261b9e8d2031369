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
``tests/test_fluid_cells.py`` checks it against cubic and FCC lattices (cubes
and rhombic dodecahedra, to 1e-9), two overlapping balls (closed forms) and a
brute-force count of the nearest particle at sample points (volumes, the
union of balls, face areas).

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
    # Directed links i -> k: unit direction and length; one more, a sentinel, pads the adjacency.
    src = np.concatenate([pi, pj])
    dst = np.concatenate([pj, pi])
    order = np.argsort(src, kind="stable")
    src, dst = src[order], dst[order]
    delta = P[dst] - P[src]
    dist = np.sqrt(np.einsum("ij,ij->i", delta, delta))
    unit = delta / dist[:, None]
    L = len(src)
    counts = np.bincount(src, minlength=N)
    K = int(counts.max()) if L else 0
    start = np.concatenate([[0], np.cumsum(counts)[:-1]])
    slot = np.arange(L) - start[src]
    adj = np.full((max(K, 1), N), L, dtype=np.int64)  # (slot, cell) -> directed link, L = none
    adj[slot, src] = np.arange(L)
    links = _Links(ux=np.append(unit[:, 0], 0.0), uy=np.append(unit[:, 1], 0.0), uz=np.append(unit[:, 2], 0.0),
                   dist=np.append(dist, np.inf), adj=adj)
    # One face per undirected pair: the links with src < dst.
    faces = np.nonzero(src < dst)[0]
    area = np.zeros(len(faces))
    omega = np.zeros(len(faces))
    for s in range(0, len(faces), chunk):
        f = faces[s:s + chunk]
        area[s:s + chunk], omega[s:s + chunk] = _face_geometry(R, src[f], unit[f], dist[f], links)
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


@dataclass
class _Links:
    """Directed links in structure-of-arrays form, with a sentinel (direction 0, length inf) at the end."""

    ux: np.ndarray
    uy: np.ndarray
    uz: np.ndarray
    dist: np.ndarray
    adj: np.ndarray  # (K, N): link index of slot k of cell i, the sentinel where there is none


def _face_geometry(R, fi, n, d, links: _Links):
    """Area and solid angle of the faces (fi, j): the disk cut by the planes of i's other neighbours.

    In the face's frame (origin at the midpoint, basis e1, e2), the plane
    between i and a neighbour k is the line ``a u + b v + c <= 0`` with
    ``(a, b)`` the projection of n_ik and ``c = (d_ij cos(n_ij, n_ik) - d_ik) / 2``.
    Arrays are (K, F): neighbour slot first, so that reductions over a
    face's lines run along the first axis.  The link to j itself and the
    sentinel are parallel to the face with ``c <= 0``: they cut nothing.
    """
    F = len(fi)
    h = 0.5 * d
    r = np.sqrt(np.maximum(R * R - h * h, 0.0))
    e1, e2 = _plane_basis(n)
    lk = links.adj[:, fi]  # (K, F)
    ux, uy, uz = links.ux[lk], links.uy[lk], links.uz[lk]
    a = e1[:, 0] * ux + e1[:, 1] * uy + e1[:, 2] * uz
    b = e2[:, 0] * ux + e2[:, 1] * uy + e2[:, 2] * uz
    cos = n[:, 0] * ux + n[:, 1] * uy + n[:, 2] * uz
    c = 0.5 * (d * cos - links.dist[lk])
    ell = np.sqrt(a * a + b * b)
    flat = ell < 1e-12  # plane_ik parallel to the face: all or nothing
    with np.errstate(divide="ignore", invalid="ignore"):
        cn = c / ell
    empty = ((flat & (c > 1e-12 * R)) | (~flat & (cn >= r))).any(axis=0)
    cut = ~flat & (np.abs(cn) < r) & ~empty
    m_per = cut.sum(axis=0)
    area = np.zeros(F)
    omega = np.zeros(F)
    live = ~empty
    for m in np.unique(m_per[live]):
        rows = np.nonzero(live & (m_per == m))[0]
        for s in range(0, len(rows), KERNEL_BATCH):  # temporaries of (m, m, batch) stay in cache
            bf = rows[s:s + KERNEL_BATCH]
            k = np.nonzero(cut[:, bf].T)[1].reshape(len(bf), m).T  # (m, batch): the cutting lines' slots
            sel = (k, bf[None, :])
            inv = 1.0 / ell[sel]
            area[bf], omega[bf] = clipped_disk(r[bf], h[bf], R, a[sel] * inv, b[sel] * inv, cn[sel])
    return area, omega


def _plane_basis(n):
    """Two unit vectors spanning the plane normal to each row of ``n``."""
    axis = np.argmin(np.abs(n), axis=1)
    ref = np.zeros_like(n)
    ref[np.arange(len(n)), axis] = 1.0
    e1 = np.cross(n, ref)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    return e1, np.cross(n, e1)
