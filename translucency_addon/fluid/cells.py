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

**How the faces are clipped.**  The straight edges of face ij lie on the
Voronoi edges of particle triangles ijk: the line of points equidistant from
i, j and k.  That line meets the balls only if the triangle's circumradius is
below R, and a particle that cuts it there lies within 2R of all three.  So:

1. neighbour pairs (faces) from ``cKDTree.query_pairs(2R)``, relabelled in a
   spatial order (slabs of 2R) and sorted by (i, j) (the compiled path takes
   every particle's list from the grid of that order instead,
   :func:`.compiled_faces.neighbour_lists`, and clips each face in one place:
   :mod:`.compiled_faces`; the steps below are the numpy path's);
2. the triangles i < j < k of pairs (from the sorted rows, one ``searchsorted``
   for the pair jk), and per triangle, in each of its three faces, whether its
   line cuts the disk (circumradius < R) or leaves the whole disk to the third
   particle (the face is empty) -- :func:`_cut_triangles`;
3. each Voronoi edge's segment, *once*, in the face (i, j) of its two smallest
   particle indices, clipped by every cutting line of that face
   (:func:`.disk_faces.segment_bounds`).  The segment is the same set of
   points in all three faces and, measured from the triangle's circumcentre
   (the foot of the perpendicular from each face's disk centre), has the same
   parameter there up to its direction (:func:`_share_segments`).  Clipped
   per face, as before, the O(m^2) work in the m ~ 10 lines of a face was
   done three times per edge;
4. per face, the fan triangles of its live segments and the arcs left between
   them (:func:`.disk_faces.fan`, :func:`.disk_faces.allowed_arc`).

The work runs in chunks of particle rows (:func:`_face_geometry`), which
bounds the memory and keeps the temporaries in cache.

Ties (lattices: four particles on one circle give one Voronoi edge to four
triangles) need one rule that all three faces of a triangle agree on, since
its segment is decided once: a triangle i < j < k loses its segment when a
fourth particle l < k lies on the same circle on k's side of ij.  The
survivors triangulate every such circle (checked for all orders of up to 7
points on one circle), so each polygon edge of the circle keeps exactly one
segment and its diagonals get segments that cancel.

``scipy.spatial.Voronoi`` (qhull, compiled) was measured as the other exact
route at 16k jittered particles: 0.98 s of CPU for the unclipped diagram
alone, as much as this whole build (0.96 s in the same run; the per-face
clipping before it: 2.07 s), and qhull's merged facets on lattices would need
their own handling.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from ..geometry.extent import bounds

from .disk_faces import TWO_PI, allowed_arc, fan, segment_bounds

TRIANGLE_CHUNK = 1 << 18  # candidate triangles per chunk of face rows (memory: ~ 300 bytes each)
KERNEL_BATCH = 2048  # faces per call of the (m, m_own, faces) clipping kernel
TINY_AREA = 1e-12  # face areas below this fraction of R^2 are no face (lattice ties)
FLAT = 1e-12  # |sin| between a face and a cutting plane below which they are parallel
POINT = 1e-12  # segments shorter than this fraction of the disk radius are points (cospherical particles)
CELL_METHODS = ("auto", "compiled", "numpy")


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
    order: np.ndarray | None = None  # the particles in a spatial order (the graph numbers its nodes so)
    path: str = "numpy"  # where the faces were computed: "compiled" (numba) or "numpy" (cell_path)
    path_note: str = ""  # why the numpy path ran where the compiled one was asked for ("auto"), else ''

    @property
    def n_cells(self) -> int:
        return len(self.points)

    @property
    def n_faces(self) -> np.ndarray:
        """Number of neighbour faces per cell."""
        return np.bincount(np.concatenate([self.face_i, self.face_j]), minlength=self.n_cells)


def neighbour_pairs(points: np.ndarray, radius: float, tree=None):
    """Pairs (i < j) closer than 2R (their balls overlap): ``cKDTree.query_pairs`` (on ``tree``, the points'
    own, where the caller has built it)."""
    from scipy.spatial import cKDTree

    if tree is None:
        tree = cKDTree(points)
    pairs = tree.query_pairs(2.0 * radius, output_type="ndarray")
    if len(pairs) == 0:
        return tree, np.zeros(0, np.int64), np.zeros(0, np.int64)
    return tree, pairs[:, 0].astype(np.int64), pairs[:, 1].astype(np.int64)


@dataclass
class _Faces:
    """Candidate faces: pairs i < j closer than 2R, sorted by (i, j), with their disks and frames.

    Vectors are stored (3, E), one row per coordinate: gathering rows of an
    (E, 3) array with ``a[idx]`` costs 5-10x three 1D ``np.take`` (measured).
    """

    i: np.ndarray
    j: np.ndarray
    key: np.ndarray | None  # i N + j, ascending (the numpy path's; None on the compiled one)
    n: np.ndarray  # (3, E) unit vector i -> j: the face's normal
    d: np.ndarray  # |p_j - p_i|
    # the rest of each face's frame, for the numpy path (the compiled kernel derives them per face: None)
    h: np.ndarray | None = None  # d / 2
    r: np.ndarray | None = None  # disk radius sqrt(R^2 - h^2)
    mid: np.ndarray | None = None  # (3, E) disk centre
    e1: np.ndarray | None = None  # (3, E) in-plane basis, e1 x e2 = n
    e2: np.ndarray | None = None


def _compiled_faces(P, R, lists) -> _Faces:
    """The candidate faces i < j of the compiled path from its neighbour lists (``(start, nbr, dist)``), sorted
    by (i, j), with their distances and normals (:func:`.compiled_faces.upper_faces`); the faces' kernel
    derives the rest of each frame."""
    from .compiled_faces import upper_faces

    start, nbr, _ = lists
    i, j, d, n = upper_faces(P, start, nbr)
    ok = d < 2.0 * R  # the grid's own distance may round the other way at exactly 2R
    if not ok.all():
        i, j, d, n = i[ok], j[ok], d[ok], n[:, ok]
    return _Faces(i=i, j=j, key=None, n=n, d=d)


def _faces(P, R, pi, pj) -> _Faces:
    """The faces of pairs (pi < pj), sorted by (i, j), with their frames (the numpy path)."""
    N = len(P)
    key = pi * N + pj
    order = np.argsort(key)
    i, j, key = pi[order], pj[order], key[order]
    d, n, e1, e2, mid = _face_frames(P, i, j)
    ok = d < 2.0 * R  # the tree's own distance may round the other way at exactly 2R
    if not ok.all():
        i, j, key, d = i[ok], j[ok], key[ok], d[ok]
        n, e1, e2, mid = n[:, ok], e1[:, ok], e2[:, ok], mid[:, ok]
    h = 0.5 * d
    return _Faces(i=i, j=j, key=key, n=n, d=d, h=h, r=np.sqrt(np.maximum(R * R - h * h, 0.0)), mid=mid,
                  e1=e1, e2=e2)


def _face_frames(P, i, j) -> tuple:
    """``(d, n, e1, e2, mid)`` of the faces i -> j in numpy, vectors (3, E): the twin of
    :func:`.compiled_faces.upper_faces` (d, n) and :func:`.compiled_kernels.plane_basis`."""
    delta = P[j] - P[i]
    d = np.sqrt(np.einsum("ij,ij->i", delta, delta))
    n = delta / d[:, None]
    e1, e2 = _plane_basis(n)
    return d, _rows(n), _rows(e1), _rows(e2), _rows(0.5 * (P[i] + P[j]))


def _rows(a):
    return np.ascontiguousarray(a.T)


def _at(a, idx):
    """Columns ``idx`` of a (3, E) array."""
    return np.take(a, idx, axis=1)


def _dot(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def cell_path(method: str = "auto") -> tuple:
    """``(path, why)``: where the faces are computed -- ``"compiled"`` (:mod:`.compiled_faces`, numba) or
    ``"numpy"`` (this module) -- and, when ``method`` "auto" falls back to numpy, why."""
    from . import compiled_faces

    if method not in CELL_METHODS:
        raise ValueError(f"cell method {method!r}: choose one of {', '.join(CELL_METHODS)}")
    if method == "numpy":
        return "numpy", ""
    why = compiled_faces.available()
    if not why:
        return "compiled", ""
    if method == "compiled":
        raise RuntimeError(f"the compiled cell faces are not available: {why}")
    return "numpy", f"{why}: the cells take the numpy path (about 4x slower; install numba to speed it up)"


def build_cells(points: np.ndarray, radius: float, chunk: int = TRIANGLE_CHUNK, method: str = "auto",
                tree=None) -> VoronoiCells:
    """Exact Voronoi-fluid cells of particles ``points`` (N, 3) with ball radius ``radius``.

    The input must be finite, without coincident particles and with a
    positive radius (:func:`.particles.prepare_particles` checks and cleans).
    ``chunk`` bounds the candidate triangles handled at once (memory, numpy path).
    ``method``: ``"auto"`` (compiled where numba is installed, else numpy), ``"compiled"`` or
    ``"numpy"`` (:func:`cell_path`); both give the same cells to rounding.  ``tree``: the points'
    ``cKDTree`` where one is built already (:func:`.particles.prepare_particles`'s).
    """
    path, why = cell_path(method)
    t0 = time.perf_counter()
    P = np.ascontiguousarray(points, dtype=np.float64)
    N = len(P)
    R = float(radius)
    # Work in a spatial order (slabs of 2R): a face's triangles then lie in nearby rows (chunks, cache).
    order, grid = _spatial_order(P, R)
    Q = P[order]
    if path == "compiled":  # each particle's list from the grid, in compiled code; the faces are its pairs i < j
        from .compiled_faces import neighbour_lists

        if tree is None:
            from scipy.spatial import cKDTree

            tree = cKDTree(P)  # not needed for the faces; the graph and the occluder query it
        lists = neighbour_lists(Q, R, grid)
        fc = _compiled_faces(Q, R, lists)
        t1 = time.perf_counter()
        area, omega, seconds = _compiled_face_geometry(Q, R, fc, lists)
    else:
        tree, pi, pj = neighbour_pairs(P, R, tree)
        rank = np.empty(N, dtype=np.int64)
        rank[order] = np.arange(N)
        si, sj = rank[pi], rank[pj]
        fc = _faces(Q, R, np.minimum(si, sj), np.maximum(si, sj))
        t1 = time.perf_counter()
        area, omega, seconds = _face_geometry(Q, R, fc, chunk)
    t2 = time.perf_counter()
    fi, fj, fd, fn = fc.i, fc.j, fc.d, fc.n
    # the sphere part closes the cell: its vector area is minus the faces'
    if path == "compiled":  # one pass over the faces instead of ten bincounts (16k particles: 9 -> 2 ms)
        from .compiled_faces import cell_sums

        sum_omega, cones, vec_sorted = cell_sums(fi, fj, area, omega, fd, fn, N)
        vec = _unsort(vec_sorted, order)
    else:
        sum_omega = np.bincount(fi, omega, N) + np.bincount(fj, omega, N)
        cone = 0.5 * fd * area / 3.0
        cones = np.bincount(fi, cone, N) + np.bincount(fj, cone, N)
        vec = np.zeros((N, 3))
        for a in range(3):
            vec[order, a] = -np.bincount(fi, area * fn[a], N) + np.bincount(fj, area * fn[a], N)
    sphere = R * R * np.maximum(4.0 * np.pi - sum_omega, 0.0)
    volume = cones + R * sphere / 3.0
    keep = np.nonzero(area > TINY_AREA * R * R)[0]
    oi, oj = order[fi[keep]], order[fj[keep]]
    t3 = time.perf_counter()
    seconds.update({"neighbours": t1 - t0, "faces": t2 - t1, "cells": t3 - t2})
    return VoronoiCells(points=P, radius=R, face_i=np.minimum(oi, oj), face_j=np.maximum(oi, oj),
                        face_area=area[keep], face_distance=fd[keep], volume=_unsort(volume, order),
                        sphere_area=_unsort(sphere, order), surface_vector=vec, tree=tree, seconds=seconds,
                        order=order, path=path, path_note=why)


def _compiled_face_geometry(P, R, fc: _Faces, lists):
    """Area and solid angle of every face by :mod:`.compiled_faces`: each face clipped by the lines of its
    first particle's neighbours (``lists`` = ``(start, nbr, dist)``: every particle within 2R of each,
    :func:`.compiled_faces.neighbour_lists`; their rows come back sorted by distance)."""
    from . import compiled_faces

    t = time.perf_counter()
    start, nbr, dist = lists
    area, omega = compiled_faces.face_geometry(P, R, fc.i, fc.j, fc.n, fc.d, start, nbr, dist)
    t2 = time.perf_counter()
    return np.maximum(area, 0.0), np.maximum(omega, 0.0), {"compiled faces": t2 - t}


def _spatial_order(P, R):
    """``(order, (g, keys))``: the particles sorted by slabs, rows and cells of size 2R (a stable sort keeps
    the input order within), and in that order their cells' integer coordinates ``g`` (N, 3) and flat keys
    (ascending)."""
    if len(P) == 0:
        return np.zeros(0, dtype=np.int64), (np.zeros((0, 3), dtype=np.int64), np.zeros(0, dtype=np.int64))
    g = np.floor((P - bounds(P)[0]) / (2.0 * R)).astype(np.int64)
    dims = bounds(g)[1] + 1
    key = (g[:, 2] * dims[1] + g[:, 1]) * dims[0] + g[:, 0]
    order = np.argsort(key, kind="stable")
    return order, (g[order], key[order])


def _unsort(a, order):
    out = np.empty_like(a)
    out[order] = a
    return out


def _face_geometry(P, R, fc: _Faces, chunk: int):
    """Area and solid angle of every face, in one pass over the particles' rows of faces.

    A chunk of rows a in [a0, a1) enumerates the triangles a < b < c whose
    face ab lies in it; their faces ab and ac lie in the chunk too, bc (b > a)
    in it or later.  Every line of a face (x, y) comes from a triangle whose
    smallest particle is at most x, so when the chunk of x comes every line
    and every empty flag of the face is known: the lines of later faces wait
    in ``later`` (with their segments, decided in their triangle's chunk).
    Chunks keep the temporaries small (under the allocator's mmap threshold
    and in cache: at 64k particles the unchunked arrays cost more in page
    faults than in arithmetic).
    """
    N, E = len(P), len(fc.i)
    area, omega = np.zeros(E), np.zeros(E)
    empty = np.zeros(E, dtype=bool)
    seconds = {"triangles": 0.0, "clipping": 0.0, "fans": 0.0}
    if E == 0:
        return area, omega, seconds
    row_start = np.concatenate([[0], np.cumsum(np.bincount(fc.i, minlength=N))])
    after = row_start[fc.i + 1] - np.arange(E) - 1  # faces (a, c) with c > b in row a
    row_work = np.concatenate([[0], np.cumsum(np.bincount(fc.i, after, N))])
    bounds = np.unique(np.concatenate([[0], np.searchsorted(row_work, np.arange(chunk, row_work[-1], chunk)), [N]]))
    later = None
    PT = _rows(P)
    for a0, a1 in zip(bounds[:-1], bounds[1:]):
        f0, f1 = row_start[a0], row_start[a1]
        if f0 == f1:
            continue
        t = time.perf_counter()
        tri = _cut_triangles(PT, R, fc, f0, f1, after, empty)
        new = _incidences(fc, tri)
        t1 = time.perf_counter()
        here, waiting = _lines_of_chunk(later, new, f1, N)
        owner = _owned_segments(fc, here, f0, f1, len(tri["ab"]), empty)
        t2 = time.perf_counter()
        _share_segments(here, True, here, owner)
        _share_segments(new, waiting, here, owner)
        later = {k: np.concatenate([later[k][later["face"] >= f1], new[k][waiting]]) if later else new[k][waiting]
                 for k in _WAITING}
        _fans_and_arcs(fc, R, here, f0, f1, empty, area, omega)
        t3 = time.perf_counter()
        seconds["triangles"] += t1 - t
        seconds["clipping"] += t2 - t1
        seconds["fans"] += t3 - t2
    return np.maximum(area, 0.0), np.maximum(omega, 0.0), seconds


def _cut_triangles(PT, R, fc: _Faces, f0, f1, after, empty):
    """Triangles a < b < c (face ab in ``f0..f1-1``) whose Voronoi edge cuts the balls; sets ``empty``.

    In face (i, j) the plane between i and a third particle k is the line at
    ``c = (d_ij cos - d_ik) / 2`` from the disk centre (``cos = n_ij . n_ik``)
    over ``ell = sin``.  It cuts the disk when ``|c| < r ell`` (the triangle's
    circumradius is below R, the same in its three faces: decided in face
    ab); when ``c >= r ell`` particle k takes the whole disk and the face is
    empty.  Returns the cut triangles' faces ``ab, ac, bc`` and their ``c``
    in those faces.
    """
    N, E = PT.shape[1], len(fc.i)
    cnt = after[f0:f1]
    rep = np.repeat(np.arange(f0, f1), cnt)
    first = np.cumsum(cnt) - cnt
    g = rep + 1 + (np.arange(len(rep)) - np.repeat(first, cnt))
    b, c = fc.j[rep], fc.j[g]
    dbc = _at(PT, c) - _at(PT, b)
    near = np.nonzero(_dot(dbc, dbc) < 4.0 * R * R * (1.0 + 1e-9))[0]
    rep, g, b, c = rep[near], g[near], b[near], c[near]
    q = b * N + c
    h = np.minimum(np.searchsorted(fc.key, q), E - 1)
    pair = np.nonzero(fc.key[h] == q)[0]
    ab, ac, bc = rep[pair], g[pair], h[pair]
    nab = _at(fc.n, ab)
    cos1 = _dot(nab, _at(fc.n, ac))  # face ab, line c and face ac, line b
    cos3 = -_dot(nab, _at(fc.n, bc))  # face bc, line a (seen from b: -n_ab)
    dab, dac, dbc_ = fc.d[ab], fc.d[ac], fc.d[bc]
    ell1 = np.sqrt(np.maximum((1.0 - cos1) * (1.0 + cos1), 0.0))
    ell3 = np.sqrt(np.maximum((1.0 - cos3) * (1.0 + cos3), 0.0))
    c_ab = 0.5 * (dab * cos1 - dac)
    c_ac = 0.5 * (dac * cos1 - dab)
    c_bc = 0.5 * (dbc_ * cos3 - dab)
    for f, cf, ell in ((ab, c_ab, ell1), (ac, c_ac, ell1), (bc, c_bc, ell3)):
        takes_all = np.where(ell < FLAT, cf > FLAT * R, cf >= fc.r[f] * ell)
        empty[f[takes_all]] = True
    cut = np.nonzero((ell1 >= FLAT) & (np.abs(c_ab) < fc.r[ab] * ell1))[0]
    return {"ab": ab[cut], "ac": ac[cut], "bc": bc[cut], "c_ab": c_ab[cut], "c_ac": c_ac[cut], "c_bc": c_bc[cut]}


def _incidences(fc: _Faces, tri):
    """The three (face, triangle) incidences of each cut triangle with the triangle's line in that face.

    Face ab sees line c (link a -> c), face ac line b (a -> b), face bc line a
    (b -> a).  ``nx, ny``: the line's unit normal in the face's basis (e1, e2),
    ``cn``: its offset, as :mod:`.disk_faces` takes them.
    """
    ab, ac, bc = tri["ab"], tri["ac"], tri["bc"]
    T = len(ab)
    face = np.concatenate([ab, ac, bc])
    u = np.concatenate([_at(fc.n, ac), _at(fc.n, ab), -_at(fc.n, ab)], axis=1)
    a = _dot(_at(fc.e1, face), u)
    b = _dot(_at(fc.e2, face), u)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / np.sqrt(a * a + b * b)
    return {"face": face, "third": np.concatenate([fc.j[ac], fc.j[ab], fc.i[ab]]),
            "nx": a * inv, "ny": b * inv, "cn": np.concatenate([tri["c_ab"], tri["c_ac"], tri["c_bc"]]) * inv,
            "tid": np.tile(np.arange(T), 3), "role": np.repeat(np.arange(3, dtype=np.int8), T)}


_WAITING = ("face", "third", "nx", "ny", "cn", "lo", "hi", "live")  # what a line waiting for a later chunk keeps


def _lines_of_chunk(later, new, f1, N):
    """Every line of the chunk's faces (those waiting from earlier chunks and the new ones with face < f1),
    sorted by (face, third particle); and the new lines that wait for a later chunk (a mask of ``new``)."""
    waiting = new["face"] >= f1  # only role bc can lie beyond the chunk
    n_new = len(waiting)
    new["lo"], new["hi"] = np.zeros(n_new), np.zeros(n_new)
    new["live"] = np.zeros(n_new, dtype=bool)
    take = ~waiting
    if later:
        old = later["face"] < f1
        here = {k: np.concatenate([later[k][old], new[k][take]]) for k in _WAITING}
        here["tid"] = np.concatenate([np.full(int(old.sum()), -1), new["tid"][take]])
        here["role"] = np.concatenate([np.full(int(old.sum()), 2, dtype=np.int8), new["role"][take]])
    else:
        here = {k: new[k][take] for k in _WAITING + ("tid", "role")}
    order = np.argsort(here["face"] * N + here["third"], kind="stable")  # runs of sorted keys: timsort is fast
    return {k: v[order] for k, v in here.items()}, waiting


def _owned_segments(fc: _Faces, inc, f0, f1, T, empty):
    """Clip each new triangle's line in its own face (ab) by all the lines of that face (``inc``, sorted).

    Writes ``lo, hi, live`` of the owned lines into ``inc`` (not live where
    face ab is empty: a particle takes the whole disk) and returns, per new
    triangle, the position of its owned line in ``inc``.
    """
    F = f1 - f0
    face = inc["face"] - f0
    nx, ny, cn = inc["nx"], inc["ny"], inc["cn"]
    owned = (inc["role"] == 0) & (inc["tid"] >= 0)
    owner = np.zeros(T, dtype=np.int64)
    owner[inc["tid"][owned]] = np.nonzero(owned)[0]
    m = np.bincount(face, minlength=F)
    start = np.cumsum(m) - m
    own = np.bincount(face[owned], minlength=F)
    faces = np.nonzero((own > 0) & ~empty[f0:f1])[0]
    for fs in _groups(faces, m[faces] * 1024 + own[faces]):
        mm, mo = int(m[fs[0]]), int(own[fs[0]])
        for s in range(0, len(fs), KERNEL_BATCH):  # temporaries of (m, m_own, batch) stay in cache
            fb = fs[s:s + KERNEL_BATCH]
            pos = start[fb][None, :] + np.arange(mm)[:, None]
            lo, hi, live = segment_bounds(fc.r[fb + f0], nx[pos], ny[pos], cn[pos], first=mm - mo)
            t = pos[mm - mo:]
            inc["lo"][t], inc["hi"][t], inc["live"][t] = lo, hi, live
    return owner


def _share_segments(dst, sel, src, owner):
    """The segment ``[lo, hi]`` of the new lines ``dst[sel]`` of roles ac and bc from their triangle's owned
    line in ``src`` (at ``owner[tid]``).

    The closest point of the Voronoi edge to any point of the triangle's
    plane is the triangle's circumcentre, so the foot of the perpendicular
    from every face's disk centre is that one point and the segment's
    parameter is the same in the three faces up to the direction of
    ``rot90(n)``, which is ``n_f x (p_k - p_i)`` for face (i, j) with third
    particle k: ``(b-a) x (c-a)`` in faces ab and bc, its opposite in ac.
    """
    idx = np.nonzero(sel & (dst["tid"] >= 0) & (dst["role"] > 0))[0]
    at = owner[dst["tid"][idx]]
    lo, hi = src["lo"][at], src["hi"][at]
    flip = dst["role"][idx] == 1
    dst["lo"][idx] = np.where(flip, -hi, lo)
    dst["hi"][idx] = np.where(flip, -lo, hi)
    dst["live"][idx] = src["live"][at]


def _fans_and_arcs(fc: _Faces, R, inc, f0, f1, empty, area, omega):
    """Area and solid angle of the faces f0..f1-1 from their lines' segments (fans) and arcs (``inc`` sorted).

    Only the live lines bound the arcs: a line whose segment is empty (or a
    point) is redundant when the face is not empty (the region is convex);
    when a face has lines but none is live, it is empty; with no line at all
    it is the whole disk.
    """
    F = f1 - f0
    face = inc["face"] - f0
    has_lines = np.bincount(face, minlength=F) > 0
    q = np.nonzero(inc["live"])[0]
    f = face[q]
    h, r = fc.h[f0:f1], fc.r[f0:f1]
    cn, lo, hi = inc["cn"][q], inc["lo"][q], inc["hi"][q]
    sa, so = fan(h[f], cn, lo, hi)
    a = np.bincount(f, sa, F).astype(np.float64, copy=False)  # (integer when there is no segment at all)
    o = np.bincount(f, so, F).astype(np.float64, copy=False)
    bound = np.nonzero(hi - lo > POINT * r[f])[0]  # a line touching the region in a point bounds nothing
    q, f = q[bound], f[bound]
    theta = np.where(has_lines, 0.0, TWO_PI)
    L = np.bincount(f, minlength=F)
    start = np.cumsum(L) - L
    nx, ny, cn = inc["nx"][q], inc["ny"][q], inc["cn"][q]
    faces = np.nonzero(L)[0]
    for fs in _groups(faces, L[faces]):
        pos = start[fs][None, :] + np.arange(int(L[fs[0]]))[:, None]
        theta[fs] = allowed_arc(r[fs], nx[pos], ny[pos], cn[pos])
    a += 0.5 * r * r * theta
    o += (1.0 - h / R) * theta
    dead = empty[f0:f1]
    area[f0:f1] = np.where(dead, 0.0, a)
    omega[f0:f1] = np.where(dead, 0.0, o)


def _groups(faces, key):
    """``faces`` in groups of equal ``key`` (the faces one vectorised call takes together)."""
    order = np.argsort(key, kind="stable")
    faces, key = faces[order], key[order]
    return np.split(faces, np.nonzero(np.diff(key))[0] + 1) if len(faces) else []


def _plane_basis(n):
    """Two unit vectors spanning the plane normal to each row of ``n``."""
    axis = np.argmin(np.abs(n), axis=1)
    ref = np.zeros_like(n)
    ref[np.arange(len(n)), axis] = 1.0
    e1 = np.cross(n, ref)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    return e1, np.cross(n, e1)
