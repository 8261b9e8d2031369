"""The QuadGraph (Wang et al. 2010, sec. 4.1, Fig. 3 and 5) and its GPU block order (sec. 5.1).

One *inner node* per tetrahedron, at its centroid, linked to the four
face-neighbours.  A tetrahedron with one boundary face (C1) is linked, across
that face, to a *surface node*: the point where the ray from the inner node
through the boundary face first meets the **original** surface mesh.  Every
inner node therefore has exactly 4 links and every surface node exactly 1.

Besides the paper's per-node data (position, kind, 4 neighbour indices, edge
lengths d_ij, surface normal and area) we keep, per link, the area of the
tet face it crosses and, per inner node, the tet volume.  The conservative
discretisation (``diffusion.py``) needs them; the paper's scheme ignores them.

Node order is the GPU packing order: inner nodes first, then surface nodes,
each group filled into r x r blocks (r = 32) breadth-first over connectivity
(inner nodes) or over boundary-face adjacency, i.e. surface proximity
(surface nodes).
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

import numpy as np

from ..errors import MeshError
from ..geometry.tetra import FACE_VERTS, TetTopology, signed_volumes, tet_quality, topology

BLOCK_SIZE = 32  # r of sec. 5.1: blocks of r x r texels


@dataclass
class GraphLevel:
    """One level of the multi-resolution QuadGraph (arrays in packing order)."""

    n_inner: int
    n_surface: int
    position: np.ndarray  # (N, 3) object units
    neighbors: np.ndarray  # (N, 4) int32, -1 where there is none
    edge_length: np.ndarray  # (N, 4) d_ij, object units, 0 where there is no link
    face_area: np.ndarray  # (N, 4) area of the tet face a link crosses, units^2
    volume: np.ndarray  # (n_inner,) tet volumes, units^3
    normal: np.ndarray  # (n_surface, 3) outward surface normal at surface nodes
    area: np.ndarray  # (n_surface,) area weight of surface nodes (boundary face area), units^2
    block_size: int = BLOCK_SIZE
    stats: dict = field(default_factory=dict)
    # The tetrahedral mesh the level is the dual of (what a deformation moves, deformation.py):
    # its vertices (object units) and, per inner node in node order, its tet (column k lies
    # opposite link slot k).  None in caches written before it was stored (format 1).
    tet_vertices: np.ndarray | None = None  # (n_tet_vertices, 3)
    tets: np.ndarray | None = None  # (n_inner, 4) int32
    # The order the solver sweeps the nodes in (RCM, inner nodes first: diffusion.sweeps.rcm_permutation),
    # computed once at bake time and kept in the cache; None in older caches (the solver computes it).
    sweep_order: np.ndarray | None = None  # (N,) int32

    ARRAYS = ("position", "neighbors", "edge_length", "face_area", "volume", "normal", "area")
    TET_ARRAYS = ("tet_vertices", "tets")
    OPTIONAL_ARRAYS = TET_ARRAYS + ("sweep_order",)

    @property
    def n_nodes(self) -> int:
        return self.n_inner + self.n_surface

    @property
    def inner(self) -> slice:
        return slice(0, self.n_inner)

    @property
    def surface(self) -> slice:
        return slice(self.n_inner, self.n_nodes)

    @property
    def surface_position(self) -> np.ndarray:
        return self.position[self.n_inner:]

    @property
    def surface_inner(self) -> np.ndarray:
        """Index of the inner node each surface node is linked to."""
        return self.neighbors[self.n_inner:, 0]

    def nbytes(self) -> int:
        return int(sum(getattr(self, a).nbytes for a in self.ARRAYS))

    def to_arrays(self, prefix: str) -> dict:
        d = {prefix + a: getattr(self, a) for a in self.ARRAYS}
        d.update({prefix + a: getattr(self, a) for a in self.OPTIONAL_ARRAYS if getattr(self, a) is not None})
        d[prefix + "counts"] = np.array([self.n_inner, self.n_surface, self.block_size], dtype=np.int64)
        return d

    @classmethod
    def from_arrays(cls, d, prefix: str, stats: dict | None = None) -> "GraphLevel":
        n_inner, n_surface, block = (int(x) for x in d[prefix + "counts"])
        kw = {a: np.asarray(d[prefix + a]) for a in cls.ARRAYS}
        kw.update({a: np.asarray(d[prefix + a]) for a in cls.OPTIONAL_ARRAYS if prefix + a in d})
        return cls(n_inner=n_inner, n_surface=n_surface, block_size=block, stats=stats or {}, **kw)


def _face_geometry(TV, TT, t, k):
    """Centroid, area and outward unit normal of faces k of tets t."""
    tri = TV[TT[t][np.arange(len(t))[:, None], FACE_VERTS[k]]]  # (n, 3, 3)
    c = tri.mean(axis=1)
    nrm = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    area = 0.5 * np.linalg.norm(nrm, axis=1)
    nrm = nrm / np.maximum(2.0 * area, 1e-300)[:, None]
    opposite = TV[TT[t, k]]
    flip = np.einsum("ij,ij->i", nrm, opposite - c) > 0
    nrm[flip] *= -1.0
    return c, area, nrm


def tet_face_vectors(TV, TT) -> np.ndarray:
    """(T, 4, 3): for face k (opposite vertex k, vertices in ``FACE_VERTS`` order) of every tet, the
    cross product of its edges; its length is twice the face area."""
    p0, p1, p2, p3 = (TV[TT[:, k]] for k in range(4))
    e01, e02, e03 = p1 - p0, p2 - p0, p3 - p0
    out = np.empty((len(TT), 4, 3))
    out[:, 0] = np.cross(p2 - p1, p3 - p1)  # the same differences as (tri[1] - tri[0]) x (tri[2] - tri[0])
    out[:, 1] = np.cross(e02, e03)
    out[:, 2] = np.cross(e01, e03)
    out[:, 3] = np.cross(e01, e02)
    return out


def tet_face_areas(TV, TT) -> np.ndarray:
    """(T, 4) area of face k (opposite vertex k) of every tet: the A_ij of its links."""
    return 0.5 * np.linalg.norm(tet_face_vectors(TV, TT), axis=2)


def link_lengths(position, neighbors) -> np.ndarray:
    """(N, K) link lengths d_ij between node positions, 0 where a slot is empty."""
    has = neighbors >= 0
    return np.where(has, np.linalg.norm(position[:, None, :] - position[np.maximum(neighbors, 0)], axis=2), 0.0)


def greedy_bfs_blocks(adjacency, n: int, block: int, seed_order=None) -> np.ndarray:
    """Order n nodes into blocks of ``block`` nodes, each grown breadth-first (sec. 5.1).

    A block is filled by a breadth-first traversal over not-yet-placed nodes
    from a seed; if the traversal runs dry, the next unplaced node of
    ``seed_order`` (a space-filling-curve order, so it is nearby) continues
    the block.  The first node left in the queue of a full block seeds the
    next block, so consecutive blocks are neighbours too.  Returns the new
    order, a permutation of ``range(n)``.
    """
    if isinstance(adjacency, np.ndarray):
        adjacency = adjacency.tolist()
    seeds = list(range(n)) if seed_order is None else [int(x) for x in seed_order]
    placed = bytearray(n)
    mark = [-1] * n
    order: list[int] = []
    sp = 0
    next_seed = None
    blk = 0

    def next_global_seed():
        nonlocal sp
        while sp < n and placed[seeds[sp]]:
            sp += 1
        return seeds[sp] if sp < n else None

    while len(order) < n:
        start = next_seed if next_seed is not None and not placed[next_seed] else next_global_seed()
        queue: deque[int] = deque([start])
        mark[start] = blk
        count = 0
        while count < block:
            if not queue:
                s = next_global_seed()
                if s is None:
                    break
                queue.append(s)
                mark[s] = blk
            u = queue.popleft()
            if placed[u]:
                continue
            placed[u] = 1
            order.append(u)
            count += 1
            for v in adjacency[u]:
                if v >= 0 and not placed[v] and mark[v] != blk:
                    mark[v] = blk
                    queue.append(v)
        next_seed = None
        while queue:
            u = queue.popleft()
            if not placed[u]:
                next_seed = u
                break
        blk += 1
    return np.asarray(order, dtype=np.int64)


def _morton_order(p: np.ndarray) -> np.ndarray:
    from ..geometry.raycast import _morton_codes

    return np.argsort(_morton_codes(p), kind="stable")


def place_surface_nodes(inner_pos, face_centroid, face_normal, surface_bvh, vertex_normals, local_size):
    """Surface node positions and normals (Fig. 5, right).

    Cast the ray from the inner node through its boundary face onto the
    original surface and take the first hit.  A hit closer than a quarter of
    the way to the face is pushed out to that quarter, so every link keeps a
    positive length.  Rays that miss (holes, caps made by the
    tetrahedraliser) fall back to the closest surface point when it is
    within ``local_size``, otherwise to the face centroid.
    Returns ``(position, normal, stats)``.
    """
    d = face_centroid - inner_pos
    t, tri, u, v = surface_bvh.intersect(inner_pos, d, tmin=1e-6, tmax=4.0)
    hit = tri >= 0
    pos = face_centroid.copy()
    nrm = face_normal.copy()
    tc = np.maximum(t[hit], 0.25)
    pos[hit] = inner_pos[hit] + tc[:, None] * d[hit]
    F = surface_bvh.F
    tri_h = tri[hit]
    w = np.stack([1.0 - u[hit] - v[hit], u[hit], v[hit]], 1)
    n_h = np.einsum("ij,ijk->ik", w, vertex_normals[F[tri_h]])
    ln = np.linalg.norm(n_h, axis=1)
    good = ln > 1e-12
    n_h[good] /= ln[good, None]
    n_h[~good] = face_normal[hit][~good]
    # An interpolated normal that faces inward (thin parts, folds) is replaced by the face normal.
    inward = np.einsum("ij,ij->i", n_h, face_normal[hit]) <= 0
    n_h[inward] = face_normal[hit][inward]
    nrm[hit] = n_h
    miss = np.nonzero(~hit)[0]
    n_close = 0
    if len(miss):
        cp, _, dist = surface_bvh.closest_point(face_centroid[miss])
        close = dist <= local_size[miss]
        pos[miss[close]] = cp[close]
        n_close = int(close.sum())
    stats = {
        "surface_rays_hit": int(hit.sum()),
        "surface_rays_clamped": int((t[hit] < 0.25).sum()),
        "surface_rays_missed_snapped": n_close,
        "surface_rays_missed_kept_face": int(len(miss) - n_close),
    }
    return pos, nrm, stats


def relax_inner_nodes(TV, TT, pos, neighbors_tet, iterations: int, step: float = 0.5, min_bary: float = 0.05):
    """Move inner nodes so that their links to inner neighbours even out.

    The paper uses reaction-diffusion (Turk 1991) for this.  We use damped
    springs towards each node's mean link length, and keep every node inside
    its own tetrahedron
    (barycentric coordinates >= ``min_bary``), so nodes stay inside the volume
    and the link geometry stays valid.
    """
    if iterations <= 0:
        return pos
    P = TV[TT]  # (T, 4, 3)
    M = np.stack([P[:, 1] - P[:, 0], P[:, 2] - P[:, 0], P[:, 3] - P[:, 0]], axis=2)  # (T, 3, 3)
    Minv = np.linalg.inv(M)
    nb = neighbors_tet
    has = nb >= 0
    cnt = np.maximum(has.sum(axis=1), 1)
    for _ in range(iterations):
        # Springs towards the node's mean link length: links longer than it pull,
        # shorter ones push, so the (up to) 4 distances of every node even out.
        delta = np.where(has[..., None], pos[np.maximum(nb, 0)] - pos[:, None, :], 0.0)
        d = np.linalg.norm(delta, axis=2)
        dbar = np.where(has, d, 0.0).sum(axis=1) / cnt
        with np.errstate(divide="ignore", invalid="ignore"):
            pull = np.where(has & (d > 0), 1.0 - dbar[:, None] / d, 0.0)
        target = pos + step * (pull[..., None] * delta).sum(axis=1) / cnt[:, None]
        # Barycentric coordinates of the target in the node's own tet.
        lam = np.einsum("tij,tj->ti", Minv, target - P[:, 0])
        bary = np.concatenate([1.0 - lam.sum(axis=1, keepdims=True), lam], axis=1)
        # Pull back towards the current position until every coordinate >= min_bary.
        lam0 = np.einsum("tij,tj->ti", Minv, pos - P[:, 0])
        bary0 = np.concatenate([1.0 - lam0.sum(axis=1, keepdims=True), lam0], axis=1)
        with np.errstate(divide="ignore", invalid="ignore"):
            s = np.where(bary < min_bary, (bary0 - min_bary) / (bary0 - bary), 1.0)
        s = np.clip(np.nan_to_num(s.min(axis=1), nan=0.0), 0.0, 1.0)
        pos = pos + s[:, None] * (target - pos)
    return pos


def build_level(TV, TT, surface_bvh, vertex_normals, *, relax_iterations: int = 0,
                block_size: int = BLOCK_SIZE, topo: TetTopology | None = None) -> GraphLevel:
    """Build one QuadGraph level from a tet mesh whose tets have 0 or 1 boundary faces."""
    if topo is None:
        topo = topology(TT, len(TV))
    if np.any(topo.boundary_count >= 2):
        raise MeshError("internal error: tets with 2+ boundary faces must be split before building the QuadGraph")
    T = len(TT)
    vol = signed_volumes(TV, TT)
    if np.any(vol <= 0):
        raise MeshError(f"internal error: {int((vol <= 0).sum())} inverted or flat tetrahedra")
    centroid = TV[TT].mean(axis=1)
    bt, bk = np.nonzero(topo.neighbor < 0)
    S = len(bt)
    face_area_tet = tet_face_areas(TV, TT)
    fc, _, fnrm = _face_geometry(TV, TT, bt, bk)
    farea = face_area_tet[bt, bk]

    inner_pos = relax_inner_nodes(TV, TT, centroid, topo.neighbor, relax_iterations)
    # Local size, used to bound fallbacks: twice the longest edge of the boundary face.
    ftri = TV[TT[bt][np.arange(S)[:, None], FACE_VERTS[bk]]]
    local = 2.0 * np.max(np.linalg.norm(ftri - np.roll(ftri, 1, axis=1), axis=2), axis=1)
    spos, snrm, sstats = place_surface_nodes(inner_pos[bt], fc, fnrm, surface_bvh, vertex_normals, local)

    # --- packing order -------------------------------------------------
    inner_order = greedy_bfs_blocks(topo.neighbor, T, block_size * block_size, seed_order=_morton_order(inner_pos))
    # Surface adjacency: boundary faces sharing an edge.
    tri = np.sort(TT[bt][np.arange(S)[:, None], FACE_VERTS[bk]], axis=1)
    edges = np.concatenate([tri[:, [0, 1]], tri[:, [0, 2]], tri[:, [1, 2]]])
    owner = np.tile(np.arange(S), 3)
    n = np.int64(len(TV))
    ekey = edges[:, 0] * n + edges[:, 1]
    o = np.argsort(ekey, kind="stable")
    same = ekey[o][1:] == ekey[o][:-1]
    a, b = owner[o][:-1][same], owner[o][1:][same]
    adj: list[list[int]] = [[] for _ in range(S)]
    for x, y in zip(a.tolist(), b.tolist()):
        adj[x].append(y)
        adj[y].append(x)
    surf_order = greedy_bfs_blocks(adj, S, block_size * block_size, seed_order=_morton_order(spos))

    inner_new = np.empty(T, dtype=np.int64)
    inner_new[inner_order] = np.arange(T)
    surf_new = np.empty(S, dtype=np.int64)
    surf_new[surf_order] = np.arange(S)

    N = T + S
    # Neighbour table in tet/face terms, then renumbered.
    nb = topo.neighbor.copy()
    nb_new = np.where(nb >= 0, inner_new[np.maximum(nb, 0)], -1)
    surf_id_of_face = np.full((T, 4), -1, dtype=np.int64)
    surf_id_of_face[bt, bk] = T + surf_new
    nb_new = np.where(nb < 0, surf_id_of_face, nb_new)

    position = np.empty((N, 3))
    position[inner_new] = inner_pos
    position[T + surf_new] = spos
    neighbors = np.full((N, 4), -1, dtype=np.int32)
    neighbors[inner_new] = nb_new
    neighbors[T + surf_new, 0] = inner_new[bt]
    face_area = np.zeros((N, 4))
    face_area[inner_new] = face_area_tet
    face_area[T + surf_new, 0] = farea
    has = neighbors >= 0
    edge_length = link_lengths(position, neighbors)
    volume = np.empty(T)
    volume[inner_new] = vol
    normal = np.empty((S, 3))
    normal[surf_new] = snrm
    area = np.empty(S)
    area[surf_new] = farea

    q = tet_quality(TV, TT)
    stats = dict(sstats)
    stats.update(
        n_tets=int(T), n_inner=int(T), n_surface=int(S),
        tet_quality_min=float(q.min()), tet_quality_median=float(np.median(q)),
        tet_quality_p05=float(np.percentile(q, 5)),
        edge_length_min=float(edge_length[has].min()),
    )
    level = GraphLevel(n_inner=T, n_surface=S, position=position, neighbors=neighbors,
                       edge_length=edge_length, face_area=face_area, volume=volume, normal=normal,
                       area=area, block_size=block_size, stats=stats,
                       tet_vertices=np.asarray(TV, dtype=np.float64), tets=TT[inner_order].astype(np.int32))
    return level


def check_invariants(level: GraphLevel) -> list[str]:
    """Return a list of violated QuadGraph invariants (empty when the graph is valid)."""
    problems = []
    nb = level.neighbors
    inner = nb[: level.n_inner]
    surf = nb[level.n_inner:]
    if np.any(inner < 0):
        problems.append(f"{int((inner < 0).any(axis=1).sum())} inner nodes have fewer than 4 links")
    if np.any(surf[:, 0] < 0) or np.any(surf[:, 1:] >= 0):
        problems.append("surface nodes must have exactly 1 link")
    if np.any(surf[:, 0] >= level.n_inner):
        problems.append("a surface node is linked to another surface node")
    # Links are symmetric.
    i = np.repeat(np.arange(level.n_nodes), 4)
    j = nb.ravel()
    m = j >= 0
    back = (nb[j[m]] == i[m][:, None]).any(axis=1)
    if not back.all():
        problems.append(f"{int((~back).sum())} links are not symmetric")
    # Each inner node has at most one surface neighbour (tets have 0 or 1 boundary faces).
    n_surf_links = (inner >= level.n_inner).sum(axis=1)
    if np.any(n_surf_links > 1):
        problems.append(f"{int((n_surf_links > 1).sum())} inner nodes link to 2+ surface nodes (unsplit C2/C3 tets)")
    if np.any(level.edge_length[nb >= 0] <= 0):
        problems.append("non-positive edge length")
    if np.any(level.volume <= 0):
        problems.append("non-positive tet volume")
    if np.any(level.area <= 0):
        problems.append("non-positive surface area weight")
    return problems


def tex_layout(n_inner: int, n_surface: int, block_size: int = BLOCK_SIZE, max_width: int = 16384):
    """Texture size for a level packed in r x r blocks (sec. 5.1, Fig. 7).

    Inner blocks fill rows of blocks first; surface blocks start on a new
    block row, so the node kind follows from the texel row (the paper splits
    the texture along v).  Returns ``(width, height, blocks_per_row,
    surface_first_block_row)``.
    """
    B = block_size * block_size
    nb_inner = -(-n_inner // B)
    nb_surf = -(-n_surface // B)
    total = nb_inner + nb_surf
    per_row = max(1, min(max_width // block_size, int(np.ceil(np.sqrt(total)))))
    rows_inner = -(-nb_inner // per_row)
    rows_surf = -(-nb_surf // per_row)
    return per_row * block_size, (rows_inner + rows_surf) * block_size, per_row, rows_inner
