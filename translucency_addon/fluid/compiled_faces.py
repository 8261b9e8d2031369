r"""The faces of the Voronoi-fluid cells in compiled code (numba), one face per thread: the fast path.

Same quantities as :func:`.cells._face_geometry` (the numpy path, kept as the fallback where numba is
not installed): for every pair i < j closer than 2R, the area ``S_ij`` of the disk of radius
``rho = sqrt(R^2 - d^2/4)`` on their bisecting plane that is nearer to i and j than to any other
particle, and the solid angle ``Omega_ij`` it subtends from p_i (Kang & Kim 2013 sec. 4.1, 5.1).

Per face, in the plane's basis (e1, e2) with the disk centre at the origin:

1. the cutting lines.  A particle k takes the points x of the plane with ``|x - p_k| < |x - p_i|``,
   the half-plane ``a u + b v > c`` with ``(a, b) = (e1, e2) . (p_k - p_i)`` and
   ``c = |p_k - p_i|^2 / 2 - (d/2) n . (p_k - p_i)``.  A point of the disk lies within R of p_i, so
   only particles within 2R of i cut it: the cell's neighbour list holds every line.  A line farther
   than rho from the centre on the far side bounds nothing; one as far on the near side takes the
   whole disk (the face is empty);
2. the region: a square of half-side 2 rho (the disk inside it) clipped by the lines that cross the
   disk (Sutherland-Hodgman: the region is convex, so one pass per line);
3. the region's intersection with the disk, from its edges (A -> B, counter-clockwise): per edge the
   triangle (0, A, B) cut by the disk is a circular sector from A to where AB enters the disk, the
   straight triangle (0, P1, P2) inside it, and a sector from where AB leaves to B (the classic
   polygon-circle intersection).  A sector of angle phi has area ``rho^2 phi / 2`` and subtends
   ``phi (1 - h/R)`` from p_i at height h = d/2 (a cone of half-angle acos(h/R)); the straight
   triangle subtends ``2 atan2(h (P1 x P2), h r1 r2 + h^2 (r1 + r2) + h (h^2 + P1.P2))``
   (Van Oosterom and Strackee 1983, apex at p_i, r_k = sqrt(h^2 + |P_k|^2)).

Why hand-written: no well-kept library computes Voronoi cells cut by balls.  Measured at 17k
jittered particles on 2 cores: scipy's Qhull Delaunay alone takes 0.67 s (with the per-face closed
forms above, vectorised in numpy, 1.37 s: the numpy path takes 0.95 s), freud's voro++ 0.53 s at
8k for the plain Voronoi cells (no ball, no faces' polygons, and no wheel for Python 3.11).  numba
compiles these loops once per machine (``cache=True``, :mod:`.compiled_kernels`: about 3 s the first
time, 0.2 s to load them in a later process).  The extension's zips bundle
numba and llvmlite where PyPI has them (not for macOS x86-64: there, and wherever numba is missing or fails to
compile, :func:`.cells.cell_path` takes the numpy path and says why).

Exact up to rounding, like the numpy path: lattice ties (four particles on one circle) need no rule
here, since each face is clipped by all its lines in one place and coincident lines clip twice to the
same edge.  ``tests/test_fluid_cells.py`` runs the closed forms and lattices on both paths and holds
them to each other.
"""

from __future__ import annotations

import numpy as np

from ..compiled import load_kernels
from ..geometry.extent import bounds

_KERNEL = {}  # the compiled kernel, built at the first call ({"fn": ...} or {"error": "why not"})


def available() -> str:
    """'' when the compiled path can run, else why not (numba missing, or its compile failed)."""
    _kernel()
    return _KERNEL.get("error", "")


def version() -> str:
    try:
        import numba
    except ImportError:
        return ""
    return str(numba.__version__)


def face_geometry(P, R, fi, fj, normal, d, nbr_start, nbr, nbr_distance):
    """Area and solid angle of each face (i, j) = (``fi[f]``, ``fj[f]``); see the module docstring.

    ``normal``: (3, E) unit normal (i -> j), ``d``: the particles' distance (the kernel derives the disk's
    height d/2, radius and in-plane basis from these, as ``cells._faces`` does in numpy);
    ``nbr[nbr_start[i]:nbr_start[i + 1]]``: every particle within 2R of i, at ``nbr_distance`` from it
    (each list is sorted by it here, **in place** where the arrays are int64 and float64 already, as
    :func:`neighbour_lists` returns them: the nearest particles empty a face soonest, and a copy of the lists
    cost 30 ms a frame at 262k particles).  Returns ``(area, omega)``, (E,) each.
    """
    fn = _kernel().get("fn")
    if fn is None:
        raise RuntimeError(f"the compiled cell faces are not available: {_KERNEL['error']}")
    E = len(fi)
    area, omega = np.zeros(E), np.zeros(E)
    if E:
        start, nbr = np.ascontiguousarray(nbr_start, dtype=np.int64), np.ascontiguousarray(nbr, dtype=np.int64)
        _KERNEL["sort"](start, nbr, np.ascontiguousarray(nbr_distance, dtype=np.float64))
        fn(np.ascontiguousarray(P, dtype=np.float64), float(R), np.ascontiguousarray(fi, dtype=np.int64),
           np.ascontiguousarray(fj, dtype=np.int64),
           np.ascontiguousarray(normal), np.ascontiguousarray(d, dtype=np.float64), start, nbr, area,
           omega)  # one signature: C-contiguous float64/int64 (numba compiles once per signature)
    return area, omega


def neighbour_lists(P, R, grid) -> tuple:
    """``(start, nbr, dist)``: every particle's neighbours closer than 2R (``nbr[start[i]:start[i + 1]]``,
    ascending) and their distances, ``|p_k - p_i|`` as :func:`upper_faces` computes it.

    ``P`` is sorted by the cells of size 2R that ``grid`` = ``(g, keys)`` gives (``g`` (N, 3) int64 cell
    coordinates, ``keys`` their flat keys, ascending: :func:`.cells._spatial_order`), so each cell is one
    run of rows and its 26 neighbours hold every particle within 2R.  Why not ``cKDTree.query_pairs``: the
    faces need each particle's list, which from the tree's pairs takes a sort by (i, j) and another by
    source (measured at 16k particles: the tree's pairs and those sorts ~50 ms, this ~10 ms).
    """
    k = _kernel()
    if "lists" not in k:
        raise RuntimeError(f"the compiled cell faces are not available: {_KERNEL['error']}")
    g, keys = grid
    N = len(P)
    start = np.zeros(N + 1, dtype=np.int64)
    if N == 0:
        return start, np.zeros(0, dtype=np.int64), np.zeros(0)
    dims = bounds(g)[1].astype(np.int64) + 1
    first = np.concatenate([[0], np.flatnonzero(np.diff(keys)) + 1])
    ukeys = np.ascontiguousarray(keys[first], dtype=np.int64)
    ustart = np.concatenate([first, [N]]).astype(np.int64)
    nbr, dist = k["lists"](np.ascontiguousarray(P, dtype=np.float64), float(R), np.ascontiguousarray(g, np.int64),
                           dims, ukeys, ustart, start)
    return start, nbr, dist


def upper_faces(P, start, nbr) -> tuple:
    """``(i, j, d, n)``: the candidate faces i < j of the neighbour lists ``nbr[start[i]:start[i + 1]]``
    (ascending), sorted by (i, j), with the particles' distances and the unit normals (3, E), in two compiled
    passes (a count, then the faces) instead of numpy's row indices, mask and gathers over every list entry."""
    k = _kernel()
    N = len(start) - 1
    count = np.empty(N, dtype=np.int64)
    k["count_upper"](start, nbr, count)
    first = np.zeros(N + 1, dtype=np.int64)
    np.cumsum(count, out=first[1:])
    E = int(first[-1])
    i, j, d, n = np.empty(E, dtype=np.int64), np.empty(E, dtype=np.int64), np.empty(E), np.empty((3, E))
    k["upper_faces"](np.ascontiguousarray(P, dtype=np.float64), start, nbr, first, i, j, d, n)
    return i, j, d, n


def first_call_seconds() -> float:
    """What this process's first use took (the kernels compiled, or loaded from numba's cache, and run
    once); 0 before it."""
    return float(_KERNEL.get("first_call_s", 0.0))


def _kernel() -> dict:
    """The kernels, imported and run once on a tiny case (numba compiles them, or loads them from its
    cache, at their first call: timed for the log); ``{"error": why}`` where that fails."""

    def load():
        from . import compiled_kernels as k

        _warm_up(k)
        return dict(fn=k.faces, sort=k.sort_rows, count_upper=k.count_upper,
                    upper_faces=k.upper_faces, voxels=k.ball_voxels, lists=k.neighbour_lists,
                    directed_links=k.directed_links, fill_slots=k.fill_slots, cell_sums=k.cell_sums)

    return load_kernels(_KERNEL, load, "the kernel")


def directed_links(a, b, n: int) -> tuple:
    """``(src, dst, link, first)``: both directions of every face (a[f], b[f]) sorted by (source,
    destination), each link's face and the rows' starts (:func:`.compiled_kernels.directed_links`)."""
    k = _kernel()
    E = len(a)
    src, dst, link = (np.empty(2 * E, dtype=np.int64) for _ in range(3))
    first = np.empty(n + 1, dtype=np.int64)
    k["directed_links"](np.ascontiguousarray(a, dtype=np.int64), np.ascontiguousarray(b, dtype=np.int64), int(n),
                        src, dst, link, first)
    return src, dst, link, first


def fill_slots(first, dst, link, face_distance, face_area, nbr, d, A) -> None:
    """Each row's links into its first slots of ``nbr``, ``d``, ``A`` (:func:`.compiled_kernels.fill_slots`)."""
    _kernel()["fill_slots"](first, dst, link, np.ascontiguousarray(face_distance, dtype=np.float64),
                            np.ascontiguousarray(face_area, dtype=np.float64), nbr, d, A)


def cell_sums(fi, fj, area, omega, fd, n, N: int) -> tuple:
    """``(sum_omega, cone, vec)`` per cell of N: its faces' solid angles, cone volumes and vector area
    (:func:`.compiled_kernels.cell_sums`)."""
    out = (np.empty(N), np.empty(N), np.empty((N, 3)))
    _kernel()["cell_sums"](np.ascontiguousarray(fi, dtype=np.int64), np.ascontiguousarray(fj, dtype=np.int64),
                           area, omega, fd, np.ascontiguousarray(n), *out)
    return out


def ball_voxels():
    """The compiled stencil of :meth:`.occluder.BallOccluder._voxelise` (loaded with the faces' kernels,
    :mod:`.compiled_kernels`), or None where they cannot run (:func:`available` says why)."""
    return _kernel().get("voxels")


def _warm_up(k) -> None:
    """Two particles, one face: every kernel's first call, with the types the cells pass."""
    P = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    i, j = np.array([0], dtype=np.int64), np.array([1], dtype=np.int64)
    d, n = np.ones(1), np.array([[1.0], [0.0], [0.0]])
    two = np.array([0, 1, 2], dtype=np.int64)
    k.count_upper(two, np.array([1, 0], dtype=np.int64), np.empty(2, dtype=np.int64))
    k.upper_faces(P, two, np.array([1, 0], dtype=np.int64), np.array([0, 1, 1], dtype=np.int64), np.empty(1, np.int64),
                  np.empty(1, np.int64), np.empty(1), np.empty((3, 1)))
    start, nbr = np.array([0, 1, 2], dtype=np.int64), np.array([1, 0], dtype=np.int64)
    k.sort_rows(start, nbr, np.array([1.0, 1.0]))
    area, omega = np.zeros(1), np.zeros(1)
    k.faces(P, 1.0, i, j, n, d, start, nbr, area, omega)
    k.neighbour_lists(P, 1.0, np.zeros((2, 3), dtype=np.int64), np.ones(3, dtype=np.int64),
                      np.zeros(1, dtype=np.int64), np.array([0, 2], dtype=np.int64), np.zeros(3, dtype=np.int64))
    src, dst, link, first = (np.empty(2, dtype=np.int64) for _ in range(4))
    k.directed_links(i, j, 2, src, dst, link, np.empty(3, dtype=np.int64))
    k.fill_slots(np.array([0, 1, 2], dtype=np.int64), dst, link, np.ones(1), np.ones(1),
                 np.full((2, 1), -1, dtype=np.int32), np.zeros((2, 1)), np.zeros((2, 1)))
    k.cell_sums(i, j, np.ones(1), np.ones(1), d, n, np.empty(2), np.empty(2), np.empty((2, 3)))
    off = np.zeros((1, 3), dtype=np.int64)
    k.ball_voxels(P, np.full(3, -2.0), 0.5, 1.0, np.array([49, 7, 1], dtype=np.int64), off,
                  np.zeros(1, dtype=np.int64), np.zeros(1), np.zeros(7 ** 3, dtype=bool))
