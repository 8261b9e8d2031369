r"""One frame's Voronoi-fluid cells as a graph of the solver's contract (:mod:`..graph`).

Kang & Kim (2013) put the boundary on the surface cell itself (eqs. 12-15,
17): a surface cell's row gets the surface face's flux ``S`` beside the
neighbour fluxes.  The contract (``graph.DiffusionGraph``) models a boundary
as a *surface node* linked to one inner node instead, and that is what this
module builds, so that the fluid goes through the very same assembly,
boundary condition, solvers and output as a QuadGraph level, unchanged:

* every cell is an **inner node** at its particle, with volume ``V_i`` and one
  link per neighbour face: length ``d_ij`` (the particles' distance; the face
  is perpendicular to it, so the two-point flux ``kappa_ij S_ij / d_ij`` is
  consistent), area ``S_ij``.  The face coefficient is the conservative
  harmonic mean of :func:`..assembly.assemble`, not the paper's
  ``kappa(x_j)`` inside the sum (eqs. 11, 16-17), which is not a flux;
* a cell on the free surface gets one **surface node** on its surface face,
  linked in slot 0: boundary area ``a_s = |S_vec|`` (``S_vec`` the surface
  face's vector area, :mod:`.cells`) and position ``p_i + d S_vec/|S_vec|``
  with ``d = R |S_vec| / S_is``, the height of the face's centroid above the
  particle (the link length).  Its normal, which only the light pass and the
  output read, is ``S_vec/|S_vec|`` averaged over the surface nodes within
  two radii on the same side (:func:`.surface_map.smooth_normals`).

Why a surface node rather than a cell-level term: the diffusive-source
condition (eq. 5) holds *on* the surface, where the assembly's fitted
surface link resolves the boundary layer over the distance d, and the output
(eq. 6, corrected) reads phi there.  The paper reads phi at the particle,
half a cell inside, which over-estimates J+ by the gradient times d.

Why ``|S_vec|`` and not the curved area ``S_is``: the union of balls is bumpy
on the particle scale; light from a uniform sky or a sun falls on the
*projected* area of a locally flat surface (bumps shade each other), so a
flat layer of a cubic lattice gets exactly s^2 per cell.  Where the surface
curves on the particle scale (a filament or a sheet one particle thick, a
droplet) the projection loses area and such parts receive less light; the
statistics and a warning report how much.

Left out, with a warning each (their radiance is zero):

* surface faces of **interior voids** -- when the radius is below a cell's
  circumradius the balls leave small holes inside; a surface face counts only
  if the point one radius beyond it lies outside the fluid;
* **cells with no neighbours** and pieces with no surface node (no light can
  enter them; with zero absorption their system would be singular).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .cells import TINY_AREA, VoronoiCells
from .surface_map import smooth_normals

THIN = 0.3  # |S_vec| / S_is below this: a surface face that wraps around its particle (thin parts)


@dataclass
class FluidGraph:
    """A frame's cells in the contract's layout: inner nodes (cells) first, then surface nodes."""

    n_inner: int
    n_surface: int
    position: np.ndarray  # (N, 3)
    neighbors: np.ndarray  # (N, K) int32, -1 where there is none
    edge_length: np.ndarray  # (N, K)
    face_area: np.ndarray  # (N, K)
    volume: np.ndarray  # (n_inner,)
    normal: np.ndarray  # (n_surface, 3)
    area: np.ndarray  # (n_surface,)
    cell: np.ndarray  # (n_inner,) cell (particle of the ParticleSet) of each inner node
    surface_cell: np.ndarray  # (n_surface,) inner node each surface node closes
    surface_tree: object = None  # cKDTree of the surface nodes' positions
    local_order: bool = True  # nodes numbered in the cells' spatial order: the sweeps keep it (sweeps.rcm_order)
    built_per_frame: bool = True  # a new graph every frame: its solver set-ups are paid per frame (coarse_space)
    stats: dict = field(default_factory=dict)
    warnings: list = field(default_factory=list)

    @property
    def n_nodes(self) -> int:
        return self.n_inner + self.n_surface

    @property
    def surface_position(self) -> np.ndarray:
        return self.position[self.n_inner:]


def _void_warning(n_void: int, R: float, cells: VoronoiCells) -> str:
    """What to change when surface faces enclose voids: a radius below the particle spacing
    leaves holes on any lattice, so raise it to the spacing; a radius already at the spacing
    (what Auto Radius and ``suggest_radius`` choose) leaves them only where the particles are
    spread unevenly, so the spacing is no longer the answer: a radius above it is (a lattice
    jittered by 45 % of its spacing keeps voids at the spacing and none at 1.1 times it)."""
    from .particles import particle_spacing

    spacing = particle_spacing(cells.points, cells.tree)
    head = f"{n_void:,} surface faces enclose interior voids and get no light: "
    if R < 0.95 * spacing:
        return head + (f"the radius {R:.4g} is below the particle spacing {spacing:.4g} (object units) and leaves "
                       f"holes between the balls; a radius near the spacing ({spacing:.4g}) closes them")
    return head + (f"the radius {R:.4g} is already the particle spacing ({spacing:.4g} object units), but the "
                   "particles are spread unevenly and leave gaps between the balls; a radius 10 % or more above "
                   f"the spacing (about {1.1 * spacing:.4g}; with Auto Radius, turn it off to set it), or more "
                   "particles, closes them")


def build_graph(cells: VoronoiCells) -> FluidGraph:
    """The contract graph of ``cells`` (see the module docstring)."""
    P, R, N = cells.points, cells.radius, cells.n_cells
    warnings = []
    S = cells.sphere_area
    vec = cells.surface_vector
    vlen = np.linalg.norm(vec, axis=1)
    surf = (S > TINY_AREA * R * R) & (vlen > TINY_AREA * R * R)
    normal = np.where(surf[:, None], vec / np.where(vlen > 0, vlen, 1.0)[:, None], 0.0)
    height = np.where(surf, R * vlen / np.where(S > 0, S, 1.0), 0.0)
    n_void = 0
    if surf.any():
        idx = np.nonzero(surf)[0]
        probe = P[idx] + (height[idx] + R)[:, None] * normal[idx]
        dist, _ = cells.tree.query(probe, k=1, distance_upper_bound=R)
        void = dist < R * (1.0 - 1e-9)
        n_void = int(void.sum())
        surf[idx[void]] = False
    if n_void:
        warnings.append(_void_warning(n_void, R, cells))
    # Directed face links, numbered in the cells' spatial order (the solver's sparse products stay in cache)
    # and ranked per source for the slots: one sort serves the pieces below and the graph's layout.
    spatial = np.arange(N) if cells.order is None else cells.order
    rank = np.empty(N, dtype=np.int64)
    rank[spatial] = np.arange(N)
    a, b = rank[cells.face_i], rank[cells.face_j]
    compiled = cells.path == "compiled"  # the cells' kernels are loaded: the links' sort and slots compiled too
    if compiled:
        from . import compiled_faces

        src, dst, link, first = compiled_faces.directed_links(a, b, N)
        count = np.diff(first)
    else:
        src = np.concatenate([a, b])
        dst = np.concatenate([b, a])
        order = np.argsort(src * max(N, 1) + dst)  # by (src, dst): one int64 key sorts ~2x faster than lexsort
        src, dst = src[order], dst[order]
        link = order % max(len(a), 1)  # the face of each link
        count = np.bincount(src, minlength=N)
        first = np.zeros(N + 1, dtype=np.int64)
        np.cumsum(count, out=first[1:])
    # Pieces (faces' connected components) that have no surface node receive no light: leave them out.  The
    # links' CSR rows are the graph's as they are; they hold both directions of every face, so the strong
    # components are the pieces, and csgraph need not symmetrise (with the COO of the faces i < j and
    # directed=False: 8 ms at 16k cells, this 3 ms).
    from scipy.sparse import csr_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    idx_t = np.int32 if len(dst) < 2**31 else np.int64  # csgraph's own index type: no conversion
    g = csr_matrix((np.ones(len(dst)), dst.astype(idx_t), first.astype(idx_t)), shape=(N, N))
    n_comp, label = connected_components(g, directed=True, connection="strong")
    lit = np.zeros(n_comp, dtype=bool)
    lit[label[rank[surf]]] = True
    keep_rank = lit[label]  # per cell in spatial order
    keep = keep_rank[rank]
    nf = count[rank]  # faces per cell (cells.n_faces, from the links already counted)
    n_iso = int((nf == 0).sum())
    if n_iso:
        warnings.append(f"{n_iso:,} of {N:,} particles have no neighbour within twice the radius ({2 * R:.4g}): "
                        "isolated droplets, which diffusion cannot resolve; their radiance is 0 (use a radius "
                        "near the particle spacing, or more particles)")
    n_dark = int((~keep & (nf > 0)).sum())
    if n_dark:
        warnings.append(f"{n_dark:,} cells lie in pieces without a free surface face and get no light")
    thin = surf & (vlen < THIN * S)
    if thin.any():
        lost = 1.0 - float(vlen[thin].sum() / S[thin].sum())
        warnings.append(f"{int(thin.sum()):,} surface cells are one particle thick (filaments, thin sheets, "
                        f"droplets): their surface faces wrap around the particle and {lost:.0%} of their area is "
                        "lost to the flat projection; they receive less light")
    surf &= keep
    inner = spatial[keep_rank]  # the kept cells, in spatial order
    n_in = len(inner)
    node_of = np.full(N, -1, dtype=np.int64)
    node_of[inner] = np.arange(n_in)
    scells = inner[surf[inner]]
    n_s = len(scells)
    if n_in < N:  # a link's two cells lie in one piece: keep the links whose source is kept
        fk = keep_rank[src]
        new = np.cumsum(keep_rank) - 1
        src, dst, link = new[src[fk]], new[dst[fk]], link[fk]
        count = np.bincount(src, minlength=n_in)
        first = np.zeros(n_in + 1, dtype=np.int64)
        np.cumsum(count, out=first[1:])
    has_s = np.zeros(n_in, dtype=bool)
    has_s[node_of[scells]] = True
    K = int(max((count + has_s).max(initial=0), 1))
    n = n_in + n_s
    nbr = np.full((n, K), -1, dtype=np.int32)
    d = np.zeros((n, K))
    A = np.zeros((n, K))
    if compiled:
        compiled_faces.fill_slots(first, dst, link, cells.face_distance, cells.face_area, nbr, d, A)
    else:
        slot = np.arange(len(src)) - first[src]
        flat = src * K + slot  # one flat index per link: 1-D scatters, ~3x faster than (src, slot) pairs
        nbr.reshape(-1)[flat] = dst
        d.reshape(-1)[flat] = cells.face_distance[link]
        A.reshape(-1)[flat] = cells.face_area[link]
    s_nodes = n_in + np.arange(n_s)
    s_inner = node_of[scells]
    s_slot = count[s_inner]
    nbr[s_inner, s_slot] = s_nodes
    nbr[s_nodes, 0] = s_inner
    a_s = vlen[scells]
    d_s = height[scells]
    d[s_inner, s_slot] = d[s_nodes, 0] = d_s
    A[s_inner, s_slot] = A[s_nodes, 0] = a_s
    pos = np.vstack([P[inner], P[scells] + d_s[:, None] * normal[scells]])
    surface_tree = cKDTree(pos[n_in:]) if n_s else None  # the normals' and the output's (solver._weights)
    smooth = smooth_normals(pos[n_in:], normal[scells], a_s, R, tree=surface_tree)
    stats = {
        "particles": int(N), "cells": int(n_in), "surface_nodes": int(n_s), "faces": int(len(src) // 2),
        "faces_per_cell": float(len(src) / max(n_in, 1)), "link_slots": K,
        "fluid_volume": float(cells.volume.sum()), "surface_area": float(a_s.sum()),
        "curved_surface_area": float(S[scells].sum()), "voids": n_void, "isolated": n_iso, "unlit": n_dark,
    }
    return FluidGraph(n_inner=n_in, n_surface=n_s, position=pos, neighbors=nbr, edge_length=d, face_area=A,
                      volume=cells.volume[inner].copy(), normal=smooth, area=a_s, cell=inner,
                      surface_cell=s_inner, surface_tree=surface_tree, stats=stats, warnings=warnings)
