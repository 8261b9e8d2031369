"""Tetrahedral meshes: fTetWild (pytetwild), boundary faces, splitting, refinement.

Wang et al. sec. 4.1 builds the QuadGraph from a tetrahedralisation in which
every tetrahedron has 0 or 1 faces on the boundary (Fig. 4): tets with 2 or 3
boundary faces (C2, C3) are split at their centroid.  The paper's levels are
tetrahedralised independently; we also offer nested levels made by regular
1-to-8 ("red") refinement of the coarsest one, which keeps tet quality within
a bounded factor, is orders of magnitude faster than a fresh
tetrahedralisation, and makes coarse and fine levels share geometry
(``BakeSettings.level_mode``).

Face ``k`` of tet ``(v0, v1, v2, v3)`` is the face opposite ``v_k``.
Tets are stored positively oriented: ``det[v1-v0, v2-v0, v3-v0] > 0``.
"""

from __future__ import annotations

import os
import tempfile
import threading
from dataclasses import dataclass

import numpy as np

from ..errors import MeshError

# Face k is opposite vertex k.  (Outward normals are computed against the
# opposite vertex wherever they are needed, not from this vertex order.)
FACE_VERTS = np.array([[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]])
EDGES = np.array([[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]])
_TETWILD_LOCK = threading.Lock()


# A tet whose quality (``tet_quality``) is at most this is flat: fTetWild works in exact arithmetic and
# rounds its output to float64, which (rarely, and not every run: its threads change the mesh) leaves a
# tet of zero volume; the QuadGraph has no well-defined face normal or volume there.  Even unoptimised
# meshes' slivers stay above ~1e-6.
FLAT_QUALITY = 1e-10
TETWILD_TRIES = 3


def tetrahedralize(V, F, *, edge_length: float, optimize: bool = True, opt_iterations: int = 3,
                   stop_energy: float = 50.0, epsilon: float = 1e-3):
    """Run fTetWild (pytetwild) and return positively oriented ``(TV, TT)`` with no flat tet.

    ``edge_length`` is fTetWild's ideal edge length in object units.
    ``optimize=False`` skips fTetWild's mesh improvement: much faster, but
    it leaves slivers (median quality ~0.01-0.02), which the solver must
    tolerate.  Output with a flat tet (quality <= ``FLAT_QUALITY``) is made
    again with the edge length 1 % longer, up to ``TETWILD_TRIES`` times, then refused.
    """
    try:
        import pytetwild
    except ImportError as exc:  # pragma: no cover - depends on the install
        raise MeshError(f"the tetrahedralizer (pytetwild) is not available: {exc}") from exc
    flat = 0
    for attempt in range(TETWILD_TRIES):
        length = float(edge_length) * (1.0 + 0.01 * attempt)
        kw = dict(edge_length_abs=length, optimize=bool(optimize), quiet=True, epsilon=float(epsilon))
        if optimize:
            kw.update(num_opt_iter=int(opt_iterations), stop_energy=float(stop_energy))
        TV, TT = _run_tetwild(pytetwild, V, F, kw)
        if len(TT) == 0:
            raise MeshError("the tetrahedralizer produced no tetrahedra: the mesh encloses no volume")
        TT = orient(TV, TT)
        flat = int(np.count_nonzero(tet_quality(TV, TT) <= FLAT_QUALITY))
        if flat == 0:
            return TV, TT
    raise MeshError(f"the tetrahedralizer left {flat:,} flat tetrahedra (quality <= {FLAT_QUALITY:g}) in "
                    f"{TETWILD_TRIES} tries at edge lengths {edge_length:.4g} to {length:.4g} object units; "
                    "change the bake quality (another edge length) or remesh the object")


def _run_tetwild(pytetwild, V, F, kw):
    """fTetWild's ``(TV float64, TT int64)``.  It writes a debug file (__tracked_surface.stl) into the working
    directory: run from a private temporary directory so nothing of the user's is littered (the lock
    serialises the process-wide chdir)."""
    with _TETWILD_LOCK, tempfile.TemporaryDirectory(prefix="translucency-tetwild-") as tmp:
        cwd = os.getcwd()
        os.chdir(tmp)
        try:
            TV, TT = pytetwild.tetrahedralize(np.ascontiguousarray(V, dtype=np.float64),
                                              np.ascontiguousarray(F, dtype=np.int32), **kw)
        finally:
            os.chdir(cwd)
    return np.asarray(TV, dtype=np.float64), np.asarray(TT, dtype=np.int64)


def signed_volumes(TV, TT) -> np.ndarray:
    p = TV[TT]
    return np.einsum("ij,ij->i", np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), p[:, 3] - p[:, 0]) / 6.0


def orient(TV, TT) -> np.ndarray:
    """Swap two vertices of every negatively oriented tet."""
    TT = TT.copy()
    neg = signed_volumes(TV, TT) < 0
    TT[neg, 1], TT[neg, 2] = TT[neg, 2], TT[neg, 1].copy()
    return TT


def tet_quality(TV, TT) -> np.ndarray:
    """6 sqrt(2) |volume| / (longest edge)^3: 1 for a regular tet, 0 for a flat one."""
    p = TV[TT]
    L = np.max([np.linalg.norm(p[:, a] - p[:, b], axis=1) for a, b in EDGES], axis=0)
    return 6.0 * np.sqrt(2.0) * np.abs(signed_volumes(TV, TT)) / np.maximum(L, 1e-300) ** 3


@dataclass
class TetTopology:
    """Face adjacency of a tet mesh.

    ``neighbor[t, k]`` is the tet across face k of tet t, or -1 on the boundary.
    """

    neighbor: np.ndarray  # (T, 4) int64
    boundary_count: np.ndarray  # (T,) number of boundary faces


def _face_keys(TT: np.ndarray, n_verts: int) -> np.ndarray:
    faces = np.sort(TT[:, FACE_VERTS].reshape(-1, 3), axis=1)
    n = np.int64(n_verts)
    if n > 2_000_000:
        raise MeshError("tet mesh too large for face keys (> 2M vertices)")
    return (faces[:, 0] * n + faces[:, 1]) * n + faces[:, 2]


def topology(TT: np.ndarray, n_verts: int) -> TetTopology:
    """Match every tet face with its twin (vectorised sort of face keys)."""
    T = len(TT)
    key = _face_keys(TT, n_verts)
    order = np.argsort(key, kind="stable")
    ks = key[order]
    same = ks[1:] == ks[:-1]
    if np.any(same[1:] & same[:-1]):
        raise MeshError("non-manifold tet mesh: a face is shared by more than two tets")
    neighbor = np.full(4 * T, -1, dtype=np.int64)
    a = order[:-1][same]
    b = order[1:][same]
    neighbor[a] = b // 4
    neighbor[b] = a // 4
    neighbor = neighbor.reshape(T, 4)
    return TetTopology(neighbor=neighbor, boundary_count=(neighbor < 0).sum(axis=1))


def split_multi_boundary(TV, TT, topo: TetTopology | None = None):
    """Split every tet with 2 or more boundary faces at its centroid (Fig. 4).

    Replacing each vertex in turn by the centroid gives 4 sub-tets; sub-tet
    k keeps only the original face k, so each has at most one boundary face.
    A C2 tet yields two C0 and two C1 tets, a C3 tet one C0 and three C1.
    Returns ``(TV, TT, n_split)``.
    """
    if topo is None:
        topo = topology(TT, len(TV))
    bad = np.nonzero(topo.boundary_count >= 2)[0]
    if len(bad) == 0:
        return TV, TT, 0
    centroids = TV[TT[bad]].mean(axis=1)
    new_ids = len(TV) + np.arange(len(bad))
    TV2 = np.vstack([TV, centroids])
    subs = np.repeat(TT[bad][:, None, :], 4, axis=1)  # (b, 4, 4)
    for k in range(4):
        subs[:, k, k] = new_ids
    keep = np.ones(len(TT), dtype=bool)
    keep[bad] = False
    TT2 = np.vstack([TT[keep], subs.reshape(-1, 4)])
    return TV2, TT2, len(bad)


def refine(TV, TT):
    """Regular 1-to-8 refinement (Bey's red refinement).

    Four corner tets plus the inner octahedron cut along its shortest
    diagonal.  Returns ``(TV2, TT2, parent_edge)`` where ``parent_edge`` (E, 2)
    lists, for every new vertex ``len(TV) + e``, the two old vertices it
    bisects (so callers can tell boundary midpoints).
    """
    T = len(TT)
    e = np.sort(TT[:, EDGES].reshape(-1, 2), axis=1)
    uniq, inv = np.unique(e, axis=0, return_inverse=True)
    inv = inv.reshape(T, 6)
    mid = len(TV) + inv  # (T, 6): m01 m02 m03 m12 m13 m23
    TV2 = np.vstack([TV, 0.5 * (TV[uniq[:, 0]] + TV[uniq[:, 1]])])
    v0, v1, v2, v3 = TT.T
    m01, m02, m03, m12, m13, m23 = mid.T
    corners = [
        np.stack([v0, m01, m02, m03], 1),
        np.stack([m01, v1, m12, m13], 1),
        np.stack([m02, m12, v2, m23], 1),
        np.stack([m03, m13, m23, v3], 1),
    ]
    P = TV2
    d_a = np.linalg.norm(P[m01] - P[m23], axis=1)
    d_b = np.linalg.norm(P[m02] - P[m13], axis=1)
    d_c = np.linalg.norm(P[m03] - P[m12], axis=1)
    choice = np.argmin(np.stack([d_a, d_b, d_c], 1), axis=1)
    # For each diagonal (p, q), the equator in cyclic order (a, b, c, d).
    diag = [
        (m01, m23, m02, m03, m13, m12),
        (m02, m13, m01, m03, m23, m12),
        (m03, m12, m01, m02, m23, m13),
    ]
    octa = np.zeros((T, 4, 4), dtype=np.int64)
    for c, (p, q, a, b, cc, d) in enumerate(diag):
        sel = choice == c
        ring = [a, b, cc, d]
        for k in range(4):
            octa[sel, k] = np.stack([p[sel], q[sel], ring[k][sel], ring[(k + 1) % 4][sel]], 1)
    TT2 = np.vstack(corners + [octa.reshape(-1, 4)])
    return TV2, orient(TV2, TT2), uniq


def boundary_faces(TT, topo: TetTopology):
    """``(tet index, face index k)`` of every boundary face."""
    t, k = np.nonzero(topo.neighbor < 0)
    return t, k


def boundary_vertices(TT, topo: TetTopology) -> np.ndarray:
    t, k = boundary_faces(TT, topo)
    return np.unique(TT[t][np.arange(len(t))[:, None], FACE_VERTS[k]])


def snap_boundary(TV, TT, topo: TetTopology, surface_bvh, max_move: np.ndarray | float,
                  min_quality_ratio: float = 0.25):
    """Move boundary vertices onto the original surface where that is safe.

    A vertex moves to its closest point on ``surface_bvh`` if that is within
    ``max_move`` (so hole caps made by the tetrahedralizer stay put), and the
    move is undone for every vertex whose incident tets would invert or lose
    more than ``1 - min_quality_ratio`` of their quality.  Returns
    ``(TV, n_moved)``.
    """
    bv = boundary_vertices(TT, topo)
    if len(bv) == 0:
        return TV, 0
    target, _, dist = surface_bvh.closest_point(TV[bv])
    lim = max_move if np.isscalar(max_move) else np.asarray(max_move)[bv]
    movable = dist <= lim
    bv, target = bv[movable], target[movable]
    q_before = tet_quality(TV, TT)
    TV2 = TV.copy()
    # Tets touching each moved vertex (vertex -> tets incidence, CSR style).
    for _ in range(4):
        TV2[bv] = target
        vol = signed_volumes(TV2, TT)
        q = tet_quality(TV2, TT)
        bad_tets = (vol <= 0) | (q < min_quality_ratio * q_before)
        if not bad_tets.any():
            break
        bad_verts = np.unique(TT[bad_tets])
        revert = np.isin(bv, bad_verts)
        if not revert.any():
            break
        # Try half the move for offending vertices, then give up on them.
        target = target.copy()
        target[revert] = 0.5 * (TV[bv[revert]] + target[revert])
        if _ == 2:
            target[revert] = TV[bv[revert]]
    TV2[bv] = target
    # Reverting a vertex can invert a neighbour that kept its move, so
    # revert whole tets until none is inverted (terminates: the original is valid).
    while True:
        bad = signed_volumes(TV2, TT) <= 0
        if not bad.any():
            break
        bad_verts = np.unique(TT[bad])
        if np.array_equal(TV2[bad_verts], TV[bad_verts]):
            break  # inverted in the input already; nothing to undo
        TV2[bad_verts] = TV[bad_verts]
    moved = int(np.count_nonzero(np.any(TV2[bv] != TV[bv], axis=1)))
    return TV2, moved
