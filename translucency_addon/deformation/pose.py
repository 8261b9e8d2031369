"""Deforming a baked object without a re-bake (Wang et al. 2010, sec. 6.4 and Fig. 15).

The paper solves the diffusion equation every frame, so "any deformation
algorithm that is able to apply a deformation field to the object volume ...
can be applied to drive the deformation of QuadGraph", as long as the
deformation "does not break the underlying tetrahedralization"; the Shepard
weights between levels (eq. 10) "are invariant to smooth shape deformation"
(sec. 4.3), and "the material changing due to deformation ... is not
considered" (sec. 6.4).  This module is that deformation field and what a
frame recomputes from it.

What the user gives: the deformed positions of the baked mesh's vertices
(same count and order, object units), e.g. Blender's evaluated mesh after an
armature, shape keys or a lattice.  That moves only the surface; the field
inside is ours to choose.

The deformation field: the tetrahedral mesh's own vertices, moved harmonically
----------------------------------------------------------------------------
Every level of the bake is the dual of a tetrahedral mesh (inner node = its
tet's centroid, surface node = where the ray through a boundary face meets
the user's mesh; :mod:`.quadgraph`), which the bake stores since cache format
2 (``GraphLevel.tet_vertices``, ``GraphLevel.tets``).  A pose moves:

* **points on the surface** -- the tet mesh's boundary vertices, the surface
  nodes and the resampled shadow surface -- with the user's mesh: each keeps
  its closest triangle, its barycentric coordinates there and its (tiny)
  offset (:class:`~.mesh_attachment.SurfaceAttachment`), so a surface node
  stays on the deformed surface exactly where it was placed;
* **the tet mesh's inner vertices** by the harmonic extension of the boundary
  displacement: ``K_II u_I = -K_IB u_B`` with K the P1 finite-element
  stiffness of the rest tet mesh (the cotangent Laplacian in 3D), factorised
  once per bake (scipy's sparse LU); a frame costs one forward and back
  substitution per level (about a millisecond at Preview).  P1 stiffness has
  linear precision: an affine pose of the surface (a rigid motion, a uniform
  scale) moves every inner vertex by exactly that affine map, so a rigid
  motion changes nothing but the frame of reference;
* **inner nodes** with their tets (fixed barycentric coordinates: the
  centroid stays the centroid).

Why harmonic on the tet mesh, not on the graph: the tets are what the
paper's validity condition talks about (an inverted tet is a fold we can
detect exactly), the stiffness of the P1 elements gives the linear precision
above (a graph Laplacian with uniform weights does not), and the nodes'
links, face areas and cell volumes are then the dual of a valid tet mesh,
exactly as after a bake.  A biharmonic field would be smoother across the
blend region of a bend but needs a second boundary condition (the normal
derivative), which a pose does not give us.  An as-rigid-as-possible
refinement (per-tet rotations, the same factorisation) was tried on a bar
bent by 90 degrees: it did not remove the few inverted tets, which have all
four vertices on the surface, where no interior field moves them, and it
costs a 3x3 SVD per tet per iteration (0.2 s at Preview in numpy).  For the
bends, squash and twist of docs/accuracy.md the harmonic field is as close
to a re-bake as two re-bakes are to each other.

Per frame (:meth:`DeformationRig.deform`): link lengths, face areas and cell
volumes from the deformed tets (the same functions as the bake), surface
normals from the deformed mesh's vertex normals at each surface node (or its
boundary face, where the bake used that), surface areas, the mesh's vertex
normals, a refitted BVH for shadow rays.  The Shepard weights (eq. 10), the
vertex map and the node order are kept (one graph of the :mod:`.graph`
contract, solved by the one :class:`~.diffusion.DiffusionSolver`).

Attached to the rest pose: the material and its heterogeneity field (sample
them at the rest positions, ``bake.levels[i].position``, once), and the sky
visibility.  Its hidden directions were cast in the rest pose's object space;
a deformed surface turns them with it: per surface node the rotation of its
mesh triangle's frame (:class:`~.deformed_sky.DeformedSky`), so the hidden
part of a directional sky moves with the surface it belongs to.  Which
directions are hidden is not cast again: a pose that opens or closes a
concavity keeps the rest pose's occlusion (docs/accuracy.md, "Deformation":
the bar bent by 90 degrees, whose arms come to see each other, is 9 % from a
re-bake with it, 4 % -- the re-bake's own variation -- without).  Single
scattering is not deformed: a deformed bake carries none.

Validity (:class:`DeformationReport`, the finest level's figures: the image
comes from it; a coarser level only starts its iteration).  Refused with
:class:`~.errors.GraphFolded`, which carries the report and says "re-bake in
this pose or at rest":

* a fold: inverted (or flattened to 1e-6 of their rest volume) tets holding
  more than :data:`FOLD_VOLUME` of the volume, or more than :data:`FOLD_LINKS`
  of the links turned against the face they cross where they did not at rest.
  Below that they are slivers, which fTetWild leaves at any quality and which
  turn over under the smallest non-affine motion; they get a small positive
  volume and are counted in the report;
* a link between inner nodes stretched or compressed beyond ``stretch_limit``
  (:data:`STRETCH_LIMIT`, 3x).  Surface links are left out of the stretch:
  their length is where the bake's ray met the surface, down to a few per cent
  of their neighbours'.  The limit is about resolution, not stability: the
  bar stretched 2.9x along its length was still within 1 % of a re-bake's own
  variation (docs/bench_deformation.md), but the graph there is a third as
  fine as the bake made it.

A changed vertex count, NaN vertices or a collapsed object (a zero scale)
raise :class:`~.errors.DeformationError`.  Nothing of the rig changes either
way; :class:`~.deformation_frames.DeformationFrames` keeps the last valid frame.
"""

from __future__ import annotations

import copy
import time
from dataclasses import dataclass, field, replace

import numpy as np
import scipy.sparse as sp

from ..quadgraph.bake import Bake
from .sky import DeformedSky
from ..errors import DeformationError, GraphFolded
from .attachment import SurfaceAttachment, TriangleGeometry, triangle_frames, unit
from ..quadgraph.levels import FACE_VERTS, GraphLevel, link_lengths, tet_face_vectors
from ..geometry.tetra import signed_volumes

STRETCH_LIMIT = 3.0  # a link longer than 3x or shorter than 1/3 of its rest length refuses the pose
FLAT_FRACTION = 1e-6  # a tet at or below this fraction of its rest volume counts as inverted
FOLD_VOLUME = 1e-3  # inverted tets holding more than this fraction of the finest level's volume fold it
FOLD_LINKS = 1e-2  # as do more than this fraction of its links turned inside out
COLLAPSE_FRACTION = 1e-6  # a pose whose bounding box shrinks below this fraction of the rest one is collapsed


# -- the rest pose's data per level ----------------------------------------------------------------
def p1_stiffness(TV, TT):
    """The P1 finite-element stiffness matrix of a tet mesh, ``K_ab = sum_t |t| grad phi_a . grad phi_b``.

    Written here (a few lines of numpy) because scipy has no finite elements; the harmonic
    extension it defines reproduces affine maps exactly (linear precision).
    """
    P = TV[TT]
    M = np.stack([P[:, 1] - P[:, 0], P[:, 2] - P[:, 0], P[:, 3] - P[:, 0]], axis=2)  # columns: edges
    vol = np.abs(np.linalg.det(M)) / 6.0
    G3 = np.linalg.inv(M)  # row i: gradient of barycentric coordinate i + 1
    G = np.concatenate([-G3.sum(axis=1, keepdims=True), G3], axis=1)  # (T, 4, 3)
    Kl = vol[:, None, None] * np.einsum("tai,tbi->tab", G, G)
    rows = np.repeat(TT, 4, axis=1).ravel()
    cols = np.tile(TT, (1, 4)).ravel()
    n = len(TV)
    return sp.csr_matrix((Kl.ravel(), (rows, cols)), shape=(n, n))


def outward_sign(TV, tets, fv) -> np.ndarray:
    """+-1 per (tet, face k): the sign that turns ``tet_face_vectors`` away from the opposite vertex."""
    P = TV[tets]  # (T, 4, 3)
    cen = P[:, FACE_VERTS].mean(axis=2)  # (T, 4, 3) face centroids
    return np.where(np.einsum("tki,tki->tk", fv, cen - P) > 0, 1.0, -1.0)


@dataclass
class LevelRig:
    """What one level needs to follow a pose (built once per bake by :class:`DeformationRig`)."""

    surface_inner: np.ndarray  # (n_surface,) inner node of each surface node
    surface_slot: np.ndarray  # (n_surface,) the inner node's link slot (= tet face) that points back
    surface: SurfaceAttachment  # surface nodes on the user's mesh
    face_normal_nodes: np.ndarray  # (n_surface,) bool: the bake gave these nodes their face's normal
    boundary: np.ndarray  # tet vertices on boundary faces
    boundary_attach: SurfaceAttachment
    interior: np.ndarray  # the other tet vertices (of some tet)
    K_IB: object  # sparse (n_interior, n_boundary) block of the stiffness
    lu: object  # splu of the interior block (None when there are no interior vertices)
    inner_bary: np.ndarray  # (n_inner, 4) each inner node in its tet
    face_sign: np.ndarray  # (n_inner, 4) +-1 turning tet_face_vectors outward
    rest_volume: np.ndarray  # (n_inner,)
    rest_length: np.ndarray  # (N, 4) rest link lengths (1 where a slot is empty)
    rest_face_normal: np.ndarray  # (n_face_normal_nodes, 3) their boundary face's outward normal at rest
    rest_interp_normal: np.ndarray  # (n_surface, 3) the mesh's vertex normals interpolated there, unit, at rest
    rest_crossing: np.ndarray  # (n_inner, 4) bool: links that cross their face outward at rest (see level_strain)

    @classmethod
    def build(cls, lv: GraphLevel, bvh, geo, F, mesh_normals) -> "LevelRig":
        from scipy.sparse.linalg import splu

        TV = np.asarray(lv.tet_vertices, dtype=np.float64)
        tets = np.asarray(lv.tets, dtype=np.int64)
        ni = lv.n_inner
        s_inner = lv.neighbors[ni:, 0].astype(np.int64)
        s_slot = np.argmax(lv.neighbors[s_inner] == np.arange(ni, lv.n_nodes)[:, None], axis=1)
        surface = SurfaceAttachment.locate(bvh, lv.surface_position, geo)
        fv = tet_face_vectors(TV, tets)
        sign = outward_sign(TV, tets, fv)
        # The bake's normal of a surface node is the mesh's interpolated vertex normal, or its
        # boundary face's where that faced inward (quadgraph.place_surface_nodes): follow the same one.
        fn = unit(fv[s_inner, s_slot] * sign[s_inner, s_slot][:, None])
        interp = unit(surface.interpolate(mesh_normals))
        face_nodes = np.linalg.norm(lv.normal - fn, axis=1) < np.linalg.norm(lv.normal - interp, axis=1)
        boundary = np.unique(tets[s_inner[:, None], FACE_VERTS[s_slot]])
        used = np.zeros(len(TV), dtype=bool)
        used[tets.ravel()] = True
        used[boundary] = False
        interior = np.nonzero(used)[0]
        K = p1_stiffness(TV, tets)
        lu = None
        if len(interior):
            lu = splu(K[interior][:, interior].tocsc(), permc_spec="MMD_AT_PLUS_A",
                      options={"SymmetricMode": True})
        P = TV[tets]
        M = np.stack([P[:, 1] - P[:, 0], P[:, 2] - P[:, 0], P[:, 3] - P[:, 0]], axis=2)
        lam = np.linalg.solve(M, (lv.position[:ni] - P[:, 0])[..., None])[..., 0]
        has = lv.neighbors >= 0
        vec = lv.position[np.maximum(lv.neighbors[:ni], 0)] - lv.position[:ni, None, :]
        crossing = has[:ni] & (np.einsum("tki,tki->tk", vec, fv * sign[..., None]) > 0)
        return cls(surface_inner=s_inner, surface_slot=s_slot, surface=surface, face_normal_nodes=face_nodes,
                   boundary=boundary, boundary_attach=SurfaceAttachment.locate(bvh, TV[boundary], geo),
                   interior=interior, K_IB=K[interior][:, boundary].tocsr(), lu=lu,
                   inner_bary=np.concatenate([1.0 - lam.sum(axis=1, keepdims=True), lam], axis=1),
                   face_sign=sign, rest_volume=signed_volumes(TV, tets),
                   rest_length=np.where(has, lv.edge_length, 1.0), rest_face_normal=fn[face_nodes],
                   rest_interp_normal=interp, rest_crossing=crossing)


# -- validity ---------------------------------------------------------------------------------------
@dataclass
class DeformationReport:
    """How far a pose strains the baked graph; ``valid`` when it neither folds nor overstretches.

    The figures are the finest level's: it is the one the image comes from; a coarser level
    only starts its iteration (eq. 10), so a fold there costs iterations, not accuracy (it is
    repaired the same way and listed in ``per_level``).  Slivers (tets of nearly no volume,
    which fTetWild leaves at any quality) can turn over under the smallest non-affine motion;
    they are counted, given a small positive volume (their rest volume times the level's
    volume change) and tolerated while all of them together hold at most :data:`FOLD_VOLUME`
    of the level's volume and at most :data:`FOLD_LINKS` of its links turn.  A real fold
    turns over tets of substance.
    """

    worst_stretch: float = 1.0  # max over links between inner nodes of max(d/d0, d0/d)
    worst_ratio: float = 1.0  # d/d0 of that link: above 1 stretched, below 1 compressed
    inverted_tets: int = 0  # volume <= FLAT_FRACTION x rest volume
    inverted_volume: float = 0.0  # their rest volume / the level's
    inverted_links: int = 0  # links turned against the face they cross
    inverted_link_fraction: float = 0.0  # of the level's links
    stretched_links: int = 0  # beyond stretch_limit
    stretch_limit: float = STRETCH_LIMIT
    per_level: list = field(default_factory=list)  # the same figures for every level, coarse to fine
    seconds: dict = field(default_factory=dict)

    @classmethod
    def combine(cls, per_level: list, stretch_limit: float) -> "DeformationReport":
        return cls(**per_level[-1], stretch_limit=stretch_limit, per_level=per_level)

    @property
    def folded(self) -> bool:
        return self.inverted_volume > FOLD_VOLUME or self.inverted_link_fraction > FOLD_LINKS

    @property
    def valid(self) -> bool:
        return not (self.folded or self.stretched_links)

    def describe(self, frame=None) -> str:
        """One line for the Info log and the panel."""
        at = f" at frame {frame}" if frame is not None else ""
        inv = (f"{self.inverted_tets} tets inverted ({100 * self.inverted_volume:.2g} % of the volume), "
               f"{self.inverted_links} links turned inside out ({100 * self.inverted_link_fraction:.2g} %)")
        stretch = self.worst_link()
        stretch += f", {self.stretched_links} links beyond)" if self.stretched_links else ")"
        turned = self.inverted_tets or self.inverted_links
        if self.valid:
            return f"deformation{at}: {stretch}" + (f"; {inv}: slivers, tolerated" if turned else "")
        what = "folds" if self.folded else "overstretches"
        return (f"the deformation{at} {what} the baked graph: " + (f"{inv}, " if turned else "")
                + f"{stretch}; re-bake in this pose or at rest")


    def worst_link(self) -> str:
        """The worst link as the panel and the log say it, with the limit's bracket left open: stretched
        (``worst link stretch 2.30x (limit 3x``) or compressed (``worst link compressed to 0.10x of its rest
        length (limit 0.33x``), never a compression called a stretch."""
        if self.worst_stretch >= 1e6:
            return ("worst link stretch unbounded (links shrunk to nothing: a zero scale?) "
                    f"(limit {self.stretch_limit:g}x")
        if self.worst_ratio < 1.0:
            return (f"worst link compressed to {self.worst_ratio:.2f}x of its rest length "
                    f"(limit {1.0 / self.stretch_limit:.2f}x")
        return f"worst link stretch {self.worst_stretch:.2f}x (limit {self.stretch_limit:g}x"


def level_strain(rig: LevelRig, lv: GraphLevel, vol, fv, stretch_limit: float) -> dict:
    """Inverted tets, inverted links and stretch of one deformed level (see :class:`DeformationReport`)."""
    ni = lv.n_inner
    nbr = lv.neighbors
    has = nbr >= 0
    # Stretch of the links between inner nodes (a surface link's length depends on where the
    # bake's ray met the surface, down to a few per cent of its neighbours': no measure of strain).
    inner = has[:ni] & (nbr[:ni] < ni)
    ratio = np.where(inner, lv.edge_length[:ni] / rig.rest_length[:ni], 1.0)
    strain = np.maximum(ratio, 1.0 / np.maximum(ratio, 1e-300))
    # A link must still cross its face from the inside out, (p_j - p_i) . n_face > 0, where it did at rest.
    out = fv * rig.face_sign[..., None]  # (n_inner, 4, 3) outward at rest, turns over with its tet
    vec = lv.position[np.maximum(nbr[:ni], 0)] - lv.position[:ni, None, :]
    turned = rig.rest_crossing & (np.einsum("tki,tki->tk", vec, out) <= 0)
    flat = vol <= FLAT_FRACTION * rig.rest_volume
    return {"inverted_tets": int(np.count_nonzero(flat)),
            "inverted_volume": float(rig.rest_volume[flat].sum() / rig.rest_volume.sum()),
            "inverted_links": int(np.count_nonzero(turned)),
            "inverted_link_fraction": float(np.count_nonzero(turned) / max(np.count_nonzero(rig.rest_crossing), 1)),
            # plus any link (surface links too) of no length or no number: the solver could not use it
            "stretched_links": int(np.count_nonzero(strain > stretch_limit)
                                   + np.count_nonzero(has & ~(np.isfinite(lv.edge_length) & (lv.edge_length > 0)))),
            "worst_stretch": float(strain.max()) if strain.size else 1.0,
            "worst_ratio": float(ratio.flat[int(np.argmax(strain))]) if strain.size else 1.0}


# -- the rig and a pose ------------------------------------------------------------------------------
@dataclass
class DeformedPose:
    """A bake deformed to one pose (``bake``: a :class:`~.bake.Bake` the solver takes as it is)."""

    bake: Bake
    report: DeformationReport
    seconds: dict


class DeformationRig:
    """The rest pose's data every pose of a bake needs: attachments, factorised stiffness per level.

    Build it once per loaded bake (a fraction of a second at Preview), then call
    :meth:`deform` per frame.
    """

    def __init__(self, bake: Bake, stretch_limit: float = STRETCH_LIMIT):
        missing = [i for i, lv in enumerate(bake.levels) if lv.tet_vertices is None or lv.tets is None]
        if missing:
            raise DeformationError(
                "this bake was written before deformation support (cache format 1: it holds no tetrahedral "
                "mesh); re-bake the object to deform it without a re-bake per frame")
        if not (np.isfinite(stretch_limit) and stretch_limit > 1.0):
            raise DeformationError(f"the stretch limit must be a number > 1, got {stretch_limit}")
        from ..geometry.raycast import mesh_bvh

        t0 = time.perf_counter()
        self.bake = bake
        self.stretch_limit = float(stretch_limit)
        self.V = np.asarray(bake.mesh_vertices, dtype=np.float64)
        self.F = np.asarray(bake.mesh_faces, dtype=np.int64)
        self.bvh = bake.surface_bvh if bake.surface_bvh is not None else mesh_bvh(
            self.V, self.F, getattr(bake, "mesh_bvh_order", None))
        self.geo = TriangleGeometry.of(self.V, self.F)
        self.used = np.unique(self.F)
        nv, nf = len(self.V), len(self.F)
        self.incidence = sp.csr_matrix((np.ones(3 * nf), (self.F.T.ravel(), np.tile(np.arange(nf), 3))),
                                       shape=(nv, nf))
        self.levels = [LevelRig.build(lv, self.bvh, self.geo, self.F, bake.mesh_normals) for lv in bake.levels]
        self.shadow = SurfaceAttachment.locate(self.bvh, bake.shadow_vertices, self.geo)
        self._sky_moments = {}  # DeformedSky's rest-pose moments, per (level, eta)
        ext = np.ptp(self.V[self.used], axis=0)
        self.rest_diagonal = float(np.linalg.norm(ext))
        self.seconds = time.perf_counter() - t0

    def with_scale(self, mm_per_unit: float) -> "DeformationRig":
        """The same rig for the bake at another scene scale (``Bake.with_scale``): poses are in object
        units and nothing the rig holds depends on the scale, so nothing is rebuilt."""
        rig = copy.copy(self)
        rig.bake = self.bake.with_scale(mm_per_unit)
        return rig

    # -- input checks ---------------------------------------------------------------------------
    def check_pose(self, V) -> np.ndarray:
        """The pose as a float64 (n, 3) array, or :class:`DeformationError` naming what is wrong."""
        V = np.asarray(V, dtype=np.float64)
        n = len(self.V)
        if V.ndim != 2 or V.shape[1] != 3:
            raise DeformationError(f"a pose needs (n, 3) vertex positions, got shape {V.shape}")
        if len(V) != n:
            raise DeformationError(
                f"the pose has {len(V)} vertices, the bake {n}: the topology changed (a modifier that adds or "
                "removes vertices, or another mesh); re-bake the object")
        bad = ~np.all(np.isfinite(V), axis=1)
        if bad.any():
            raise DeformationError(
                f"{int(bad.sum())} of {n} posed vertices are NaN or infinite (first: vertex {int(np.argmax(bad))}); "
                "check the rig (a bone or shape key driven by an invalid value)")
        diag = float(np.linalg.norm(np.ptp(V[self.used], axis=0)))
        if diag <= COLLAPSE_FRACTION * self.rest_diagonal:
            raise DeformationError(
                f"the pose collapses the object to a point (bounding box {diag:.3g} against {self.rest_diagonal:.3g} "
                "at rest; a zero scale on the object or its bone?)")
        return V

    # -- one pose ----------------------------------------------------------------------------------
    def deform(self, V, *, refuse_folds: bool = True) -> DeformedPose:
        """The bake deformed to vertex positions ``V`` (the baked mesh's order, object units).

        Raises :class:`DeformationError` for a bad pose and :class:`GraphFolded` (with its report)
        for a pose that folds or overstretches the graph, unless ``refuse_folds`` is False (then
        the report says so and the caller decides).  Nothing of the rig changes either way.
        """
        t0 = time.perf_counter()
        V = self.check_pose(V)
        F = self.F
        D = V - self.V
        geo = TriangleGeometry.of(V, F)
        cross = geo.cross
        # Mesh vertex normals: recomputed where an incident triangle changed, the bake's elsewhere.
        moved = (self.incidence @ np.abs(cross - self.geo.cross).sum(axis=1)) > 0
        normals = np.array(self.bake.mesh_normals, dtype=np.float64)
        if moved.any():
            vn = (self.incidence @ cross)[moved]
            ln = np.linalg.norm(vn, axis=1, keepdims=True)
            normals[moved] = np.where(ln > 0, vn / np.maximum(ln, 1e-300), (0.0, 0.0, 1.0))
        t1 = time.perf_counter()
        levels, per_level = [], []
        for rig, lv in zip(self.levels, self.bake.levels):
            new, strain = self._deform_level(rig, lv, D, geo, normals)
            levels.append(new)
            per_level.append(strain)
        t2 = time.perf_counter()
        bvh = self.bvh.refit(V)
        Vs = np.asarray(self.bake.shadow_vertices) + self.shadow.displacement(D, self.geo, geo)
        sky = None
        if self.bake.sky is not None:
            sky = DeformedSky(self.bake.sky, self.bake.levels, self._rotations(V), self._sky_moments)
        t3 = time.perf_counter()
        report = DeformationReport.combine(per_level, self.stretch_limit)
        seconds = {"mesh": t1 - t0, "graph": t2 - t1, "bvh": t3 - t2, "total": t3 - t0}
        report.seconds = seconds
        if refuse_folds and not report.valid:
            raise GraphFolded(report.describe(), report)
        bake = replace(self.bake, levels=levels, mesh_vertices=V, mesh_normals=normals, shadow_vertices=Vs,
                       sky=sky, single_scattering=None, surface_bvh=bvh, surface_thickness=None,
                       spectral_bounds=None,  # the rest pose's systems: a pose carries the last frame's instead
                       stats={**self.bake.stats, "deformation": {"worst_stretch": report.worst_stretch}})
        return DeformedPose(bake=bake, report=report, seconds=seconds)

    def _deform_level(self, rig: LevelRig, lv: GraphLevel, D, geo, normals):
        """One level at the pose: tet vertices, node positions, links, faces, volumes, normals."""
        TV0 = lv.tet_vertices
        u = np.zeros_like(TV0)
        u[rig.boundary] = rig.boundary_attach.displacement(D, self.geo, geo)
        if rig.lu is not None:
            u[rig.interior] = rig.lu.solve(-(rig.K_IB @ u[rig.boundary]))
        tv = TV0 + u
        tets = lv.tets
        ni = lv.n_inner
        position = np.empty_like(lv.position)
        position[:ni] = lv.position[:ni] + np.einsum("tk,tki->ti", rig.inner_bary, u[tets])
        position[ni:] = lv.position[ni:] + rig.surface.displacement(D, self.geo, geo)
        fv = tet_face_vectors(tv, tets)
        areas = 0.5 * np.linalg.norm(fv, axis=2)
        face_area = np.zeros_like(lv.face_area)
        face_area[:ni] = areas
        s_area = areas[rig.surface_inner, rig.surface_slot]
        face_area[ni:, 0] = s_area
        # Surface normals: the bake's, moved by the change of their source (vertex normals or face).
        src = unit(rig.surface.interpolate(normals)) - rig.rest_interp_normal
        face = rig.face_normal_nodes
        if face.any():
            k, slot = rig.surface_inner[face], rig.surface_slot[face]
            src[face] = unit(fv[k, slot] * rig.face_sign[k, slot][:, None]) - rig.rest_face_normal
        changed = np.any(src != 0.0, axis=1)
        normal = np.array(lv.normal)
        normal[changed] = unit(normal[changed] + src[changed])
        # = tetra.signed_volumes(tv, tets), bit for bit, from the face vector already at hand (face 3 = e01 x e02)
        vol = np.einsum("ij,ij->i", fv[:, 3], tv[tets[:, 3]] - tv[tets[:, 0]]) / 6.0
        new = replace(lv, position=position, edge_length=link_lengths(position, lv.neighbors), face_area=face_area,
                      volume=vol, normal=normal, area=s_area, tet_vertices=tv, stats={**lv.stats})
        strain = level_strain(rig, new, vol, fv, self.stretch_limit)
        if strain["inverted_tets"]:  # slivers turned over: a small positive volume (DeformationReport)
            flat = vol <= FLAT_FRACTION * rig.rest_volume
            change = 1.0
            if (~flat).any():
                change = max(float(vol[~flat].sum() / rig.rest_volume[~flat].sum()), FLAT_FRACTION)
            new.volume = np.where(flat, rig.rest_volume * change, vol)
        return new, strain

    def _rotations(self, V):
        """level -> (n_surface, 3, 3) rotation of each surface node's triangle from rest to the pose ``V``
        (None when no such triangle moved)."""
        cache = {}

        def rotations(level):
            if level not in cache:
                tri = self.levels[level].surface.tri
                rest, posed = triangle_frames(self.V, self.F, tri), triangle_frames(V, self.F, tri)
                cache[level] = None if np.array_equal(rest, posed) else np.einsum("mki,mkj->mij", posed, rest)
            return cache[level]

        return rotations


def deform_from_obj(bake: Bake, path) -> DeformedPose:
    """The bake deformed to the pose in an OBJ file with the baked mesh's vertices and faces (the CLI's
    ``solve --deformed``).  Raises :class:`DeformationError` when its topology differs."""
    from ..geometry.meshio import load_obj

    V, F = load_obj(path)
    rig = DeformationRig(bake)
    rig.check_pose(V)
    if F.shape != bake.mesh_faces.shape or not np.array_equal(F, bake.mesh_faces):
        raise DeformationError(f"{path}: its faces differ from the baked mesh's ({len(F)} against "
                               f"{len(bake.mesh_faces)} triangles): the topology changed; re-bake the object")
    return rig.deform(V)
