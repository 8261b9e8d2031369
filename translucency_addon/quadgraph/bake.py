"""The QuadGraph bake (Wang et al. 2010, sec. 4.1 and 5.1): mesh in, multi-resolution graph out.

Stages, each reported to the ``progress`` callback:

1. validate the mesh (``meshio.validate_mesh``);
2. resample the surface to the triangle count the quality needs
   (fast_simplification, a quadric decimator) -- the original surface is kept
   for placing surface nodes;
3. tetrahedralise with fTetWild (``tetra.tetrahedralize``) the coarser levels,
   each from a surface with 4x fewer triangles than the next;
4. build the finest levels by nested 1-to-8 refinement (default), or
   tetrahedralise every level independently (``level_mode="independent"``,
   the paper's way);
   snap boundary vertices to the original surface; split C2/C3 tets;
5. build every level's QuadGraph and its GPU block order;
6. Shepard weights between consecutive levels (eq. 10) and the mapping of
   the user's vertices onto the finest surface nodes.

Timings per stage, node counts per level and tet-quality statistics go into
``Bake.stats``.
"""

from __future__ import annotations

import hashlib
import json
import time
from dataclasses import asdict, dataclass, field, replace

import numpy as np

from ..geometry import meshio
from ..geometry import tetra
from ..errors import BakeCancelled, MeshError
from ..scene.materials import check_mm_per_unit
from .levels import BLOCK_SIZE, GraphLevel, build_level
from ..geometry.raycast import KeptThickness, inward_thickness, mesh_bvh, ray_path_note, thickness_digest
from ..diffusion.sweeps import rcm_permutation

BAKE_FORMAT = 1

# Quality presets.  Levels are built coarse to fine; each has ~4x the surface
# nodes of the one below (as in the paper).  The lowest ``levels -
# refinements`` levels are tetrahedralised independently (fTetWild) from
# surfaces resampled to ``base_triangles / 4^k`` triangles; the top
# ``refinements`` levels are nested 1-to-8 refinements of the finest of them.
# ``K`` is interior coarsening: fTetWild's target edge length is (1 + K) times
# the surface triangle size (the role of the paper's K, how much larger
# inner tets are than surface ones).  Refinement multiplies inner nodes by 8
# but surface nodes by 4, so Draft and Preview refine once (a finest graph an
# interactive CPU solve can afford) and Final twice.
QUALITY_PRESETS = {
    "draft": dict(base_triangles=600, K=1.0, levels=3, refinements=1),
    "preview": dict(base_triangles=2000, K=2.0, levels=3, refinements=1),
    "final": dict(base_triangles=1800, K=0.5, levels=3, refinements=2),
}


@dataclass(frozen=True)
class BakeSettings:
    quality: str = "preview"
    levels: int | None = None  # None: the preset's
    refinements: int | None = None  # finer levels made by refinement (level_mode "refine")
    base_triangles: int | None = None
    K: float | None = None
    level_mode: str = "refine"  # "refine" (nested) or "independent" (paper)
    optimize: bool = True  # fTetWild optimisation; False leaves slivers
    opt_iterations: int = 3
    stop_energy: float = 50.0
    snap_to_surface: bool = True
    relax_iterations: int = 0
    block_size: int = BLOCK_SIZE
    mm_per_unit: float = 1.0
    memory_budget: int = meshio.DEFAULT_MEMORY_BUDGET_BYTES
    shepard_surface: int = 4  # b for surface nodes (eq. 10)
    shepard_inner: int = 8  # b for inner nodes (eq. 10)
    vertex_map_k: int = 6
    sky_directions: int = 0  # > 0: also bake sky visibility with this many directions (sky_visibility.py)

    def resolved(self) -> "BakeSettings":
        q = self.quality.lower()
        if q not in QUALITY_PRESETS:
            raise MeshError(f"unknown quality {self.quality!r}; choose one of {', '.join(QUALITY_PRESETS)}")
        p = QUALITY_PRESETS[q]
        r = replace(
            self,
            quality=q,
            levels=int(self.levels if self.levels is not None else p["levels"]),
            refinements=int(self.refinements if self.refinements is not None else p["refinements"]),
            base_triangles=int(self.base_triangles if self.base_triangles is not None else p["base_triangles"]),
            K=float(self.K if self.K is not None else p["K"]),
        )
        if not 1 <= r.levels <= 6:
            raise MeshError(f"levels must be between 1 and 6, got {r.levels}")
        if r.level_mode == "independent":
            r = replace(r, refinements=0)
        else:
            r = replace(r, refinements=min(max(r.refinements, 0), r.levels - 1))
        if r.level_mode not in ("refine", "independent"):
            raise MeshError(f"level_mode must be 'refine' or 'independent', got {r.level_mode!r}")
        check_mm_per_unit(r.mm_per_unit, MeshError)
        if r.K < 0 or r.base_triangles < 20:
            raise MeshError("K must be >= 0 and base_triangles >= 20")
        if r.sky_directions and not 8 <= r.sky_directions <= 4096:
            raise MeshError(f"sky_directions must be 0 (off) or between 8 and 4096, got {r.sky_directions}")
        return r

    def expected_nodes(self) -> int:
        """Rough node count of the finest level (for the memory estimate)."""
        r = self.resolved()
        base = r.base_triangles * (4 ** (r.levels - 1) if r.level_mode == "independent" else 1)
        surf = 1.3 * base * 4**r.refinements
        inner = 8.0 * base / (1 + r.K) ** 2 * 8**r.refinements
        return int(surf + inner)

    def key_dict(self) -> dict:
        """Settings that change the baked graph (mm_per_unit does not)."""
        d = asdict(self.resolved())
        d.pop("mm_per_unit")
        d.pop("memory_budget")
        if not d["sky_directions"]:  # bakes without sky visibility keep the keys they always had
            d.pop("sky_directions")
        return d


@dataclass
class Bake:
    """A baked multi-resolution QuadGraph with everything the solver needs."""

    levels: list[GraphLevel]  # coarse -> fine
    shepard: list[tuple[np.ndarray, np.ndarray]]  # [k]: level k -> k+1, (idx (N_{k+1}, 8), w)
    vertex_map: tuple[np.ndarray, np.ndarray]  # (idx (n_vert, K) into finest surface nodes, w)
    mesh_vertices: np.ndarray  # the user's mesh (object units)
    mesh_faces: np.ndarray
    mesh_normals: np.ndarray
    shadow_vertices: np.ndarray  # resampled surface, used as the self-occluder for shadow rays
    shadow_faces: np.ndarray
    settings: BakeSettings
    mm_per_unit: float
    key: str
    stats: dict = field(default_factory=dict)
    single_scattering: object | None = None  # single_scattering data, when baked
    sky: object | None = None  # sky_visibility.SkyVisibility, when baked (environment self-occlusion)
    surface_bvh: object | None = None  # a prebuilt raycast.TriangleBVH of the mesh (a deformed bake's, refitted)
    mesh_bvh_order: np.ndarray | None = None  # that tree's triangle order (raycast.mesh_bvh), kept in the cache
    # the finest level's thickness at each surface node (object units), what the planner reads: measured
    # once and kept in the cache with the digest of the mesh and nodes (raycast.KeptThickness)
    surface_thickness: object | None = None
    voxel_number_map: object | None = None  # voxel_number_map.VoxelNumberMap, when baked (inner parts)
    composite: object | None = None  # composite_bake.CompositeInfo: inner parts, node labels, cavity exchange
    # the Chebyshev bounds of the baked material's systems, keyed by each system's digest
    # (diffusion.baked_bounds.bounds_record), kept in the cache: a cold frame of that material runs no Lanczos
    spectral_bounds: dict | None = None

    @property
    def finest(self) -> GraphLevel:
        return self.levels[-1]

    def with_scale(self, mm_per_unit: float) -> "Bake":
        """The same bake at another scene scale (no re-bake needed: geometry is in object units)."""
        return replace(self, mm_per_unit=check_mm_per_unit(mm_per_unit))

    def graph_bytes(self) -> int:
        total = sum(lv.nbytes() for lv in self.levels)
        total += sum(i.nbytes + w.nbytes for i, w in self.shepard)
        return int(total + self.vertex_map[0].nbytes + self.vertex_map[1].nbytes)


def mesh_key(V, F, settings: BakeSettings) -> str:
    """Hash of the mesh and the settings that shape the graph: a stale cache has another key."""
    h = hashlib.sha256()
    h.update(f"translucency-bake-{BAKE_FORMAT}".encode())
    h.update(np.ascontiguousarray(V, dtype=np.float64).tobytes())
    h.update(np.ascontiguousarray(F, dtype=np.int64).tobytes())
    h.update(json.dumps(settings.key_dict(), sort_keys=True).encode())
    return h.hexdigest()


INTERMEDIATE_FACTOR = 64  # bake_mesh: a mesh over 2x this times the finest target is decimated once first


def resample_surface(V, F, n_triangles: int, cleaned: bool = False):
    """Decimate to about ``n_triangles`` with quadric edge collapse (fast_simplification).

    Meshes below the target are returned cleaned, and split 1-to-4 (midpoint
    subdivision, same shape) until they have at least a quarter of the
    target: fTetWild's run time is erratic on very coarse inputs (a 12-
    triangle cube took 6-9 s, the same cube subdivided 1-2 s).  ``cleaned``: ``(V, F)`` is already
    :func:`.meshio.clean_mesh`'s output (the validation's ``MeshReport.welded``), not cleaned again.
    """
    Vc, Fc = (V, F) if cleaned else meshio.clean_mesh(V, F)[:2]
    if len(Fc) <= n_triangles:
        while 4 * len(Fc) < n_triangles:
            Vc, Fc = subdivide_midpoint(Vc, Fc)
        return Vc, Fc
    try:
        import fast_simplification
    except ImportError as exc:  # pragma: no cover - depends on the install
        raise MeshError(f"the decimation library (fast_simplification) is not available: {exc}") from exc
    reduction = 1.0 - n_triangles / len(Fc)
    V2, F2 = fast_simplification.simplify(Vc.astype(np.float32), Fc.astype(np.int32), target_reduction=reduction)
    V2 = np.asarray(V2, dtype=np.float64)
    F2 = np.asarray(F2, dtype=np.int64)
    V2, F2, _ = meshio.clean_mesh(V2, F2)
    if len(F2) < 4:
        raise MeshError("surface resampling collapsed the mesh; lower the reduction")
    return V2, F2


def subdivide_midpoint(V, F):
    """Split every triangle into 4 at its edge midpoints (the surface is unchanged)."""
    e = np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1)
    uniq, inv = np.unique(e, axis=0, return_inverse=True)
    m = len(V) + inv.reshape(3, -1).T
    V2 = np.vstack([V, 0.5 * (V[uniq[:, 0]] + V[uniq[:, 1]])])
    a, b, c = F.T
    mab, mbc, mca = m.T
    F2 = np.concatenate([np.stack([a, mab, mca], 1), np.stack([b, mbc, mab], 1),
                         np.stack([c, mca, mbc], 1), np.stack([mab, mbc, mca], 1)])
    return V2, F2


def triangle_size(V, F, n_triangles: int) -> float:
    """Edge length of an equilateral triangle tiling the surface with n triangles."""
    area = float(meshio.triangle_areas(V, F).sum())
    return float(np.sqrt(4.0 * area / (np.sqrt(3.0) * max(n_triangles, 1))))


def shepard_weights(fine: np.ndarray, coarse: np.ndarray, b: int):
    """Inverse-square-distance weights of eq. 10 from b nearest coarse nodes (KD-tree).

    w'_xy = 1 / |n_x - n_y|^2, w_xy = w'_xy / sum_y w'_xy.  A fine node that
    coincides with a coarse node takes that node's value.
    """
    from scipy.spatial import cKDTree

    b = min(b, len(coarse))
    dist, idx = cKDTree(coarse).query(fine, k=b)
    if b == 1:
        dist, idx = dist[:, None], idx[:, None]
    d2 = dist * dist
    exact = d2[:, 0] <= 1e-30
    w = 1.0 / np.maximum(d2, 1e-300)
    w[exact] = 0.0
    w[exact, 0] = 1.0
    w /= w.sum(axis=1, keepdims=True)
    return idx.astype(np.int64), w


def level_transfer(coarse: GraphLevel, fine: GraphLevel, b_surface: int, b_inner: int):
    """Shepard indices/weights from ``coarse`` to ``fine`` (surface and inner nodes separately).

    Returns ``(idx (N_fine, max b) int32 global coarse indices, -1 padded; w float32)``.
    """
    B = max(b_surface, b_inner)
    idx = np.full((fine.n_nodes, B), -1, dtype=np.int64)
    w = np.zeros((fine.n_nodes, B))
    i_idx, i_w = shepard_weights(fine.position[fine.inner], coarse.position[coarse.inner], b_inner)
    idx[: fine.n_inner, : i_idx.shape[1]] = i_idx
    w[: fine.n_inner, : i_w.shape[1]] = i_w
    s_idx, s_w = shepard_weights(fine.surface_position, coarse.surface_position, b_surface)
    idx[fine.n_inner:, : s_idx.shape[1]] = s_idx + coarse.n_inner
    w[fine.n_inner:, : s_w.shape[1]] = s_w
    return idx.astype(np.int32), w.astype(np.float32)


def vertex_mapping(V, normals, level: GraphLevel, k: int = 6):
    """Weights from the finest surface nodes to each vertex of the user's mesh.

    Among the k nearest surface nodes, weight ``max(0, n_v . n_s)^2 / (d^2 + h^2)``
    (h: median surface-node spacing) so that a vertex never takes radiance
    from the other side of a thin part; if all weights vanish it takes its
    nearest node.  Returns ``(idx (n, k) into surface nodes, w (n, k))``.
    """
    from scipy.spatial import cKDTree

    sp = level.surface_position
    k = min(k, len(sp))
    tree = cKDTree(sp)
    dist, idx = tree.query(V, k=k, workers=-1)
    if k == 1:
        dist, idx = dist[:, None], idx[:, None]
    h = float(np.median(tree.query(sp, k=2)[0][:, 1])) if len(sp) > 1 else 1.0
    # n_v . n_s by component, one take each from the nodes' normals: the einsum over level.normal[idx]
    # gathered (n, k, 3) rows, 0.55 s for 655 k vertices against ~0.1 s.
    Nt = np.ascontiguousarray(np.asarray(level.normal, dtype=np.float64).T)
    n = np.asarray(normals, dtype=np.float64)
    agree = n[:, :1] * np.take(Nt[0], idx) + n[:, 1:2] * np.take(Nt[1], idx) + n[:, 2:3] * np.take(Nt[2], idx)
    w = np.maximum(agree, 0.0) ** 2 / (dist * dist + h * h)
    none = w.sum(axis=1) <= 0
    w[none] = 0.0
    w[none, 0] = 1.0
    w /= w.sum(axis=1, keepdims=True)
    return idx.astype(np.int32), w.astype(np.float32)


class _Progress:
    """Stage bookkeeping: forwards (fraction, stage) to the callback and times stages."""

    def __init__(self, callback, plan: list[tuple[str, float]]):
        self.callback = callback
        self.weights = dict(plan)
        total = sum(self.weights.values())
        self.start = {}
        acc = 0.0
        for name, wgt in plan:
            self.start[name] = acc / total
            acc += wgt
        self.total = total
        self.timings: dict[str, float] = {}
        self._t0 = None
        self._stage = None

    def stage(self, name: str):
        self._finish()
        self._stage = name
        self._t0 = time.perf_counter()
        self._emit(self.start.get(name, 0.0), name)

    def within(self, name: str, fraction: float):
        """Report progress ``fraction`` (0..1) of the way through stage ``name``."""
        self._emit(self.start.get(name, 0.0) + fraction * self.weights.get(name, 0.0) / self.total, name)

    def _emit(self, frac, name):
        if self.callback is not None:
            if self.callback(float(min(frac, 1.0)), name) is False:
                raise BakeCancelled(f"bake cancelled during '{name}'")

    def _finish(self):
        if self._stage is not None:
            self.timings[self._stage] = self.timings.get(self._stage, 0.0) + time.perf_counter() - self._t0
            self._stage = None

    def done(self):
        self._finish()
        self._emit(1.0, "done")


def bake_mesh(V, F, settings: BakeSettings = BakeSettings(), progress=None) -> Bake:
    """Bake the multi-resolution QuadGraph of a triangle mesh (object units).

    ``progress(fraction, stage)`` is called between stages; returning False
    (or raising :class:`BakeCancelled`) cancels the bake, which then raises
    :class:`BakeCancelled` and returns nothing.
    """
    s = settings.resolved()
    V = np.asarray(V, dtype=np.float64)
    F = np.asarray(F, dtype=np.int64)
    plan = [("validate", 1), ("resample", 1), ("tetrahedralize", 10), ("levels", 4), ("quadgraph", 6), ("transfer", 2)]
    if s.sky_directions:
        plan.append(("sky visibility", 6))
    pr = _Progress(progress, plan)
    t_start = time.perf_counter()

    pr.stage("validate")
    report = meshio.validate_mesh(V, F, target_nodes=s.expected_nodes(), memory_budget=s.memory_budget)
    key = mesh_key(V, F, s)
    used = np.zeros(len(V), dtype=bool)
    used[F.ravel()] = True
    Fo = F
    normals = meshio.vertex_normals(V, Fo)
    bvh = mesh_bvh(V, Fo)

    pr.stage("resample")
    # Independently tetrahedralised levels, coarse to fine: base / 4^k triangles.
    n_indep = s.levels - s.refinements
    if s.level_mode == "independent":
        targets = [s.base_triangles * 4**k for k in range(n_indep)]
    else:
        targets = [max(20, s.base_triangles // 4 ** (n_indep - 1 - k)) for k in range(n_indep)]
    # A mesh far denser than the finest level is decimated once to an intermediate surface
    # (INTERMEDIATE_FACTOR times the finest target), and every level from that: a 1.3 M-triangle
    # mesh is collapsed once (3.9 s here) instead of once per level, and each level still comes
    # from a surface 64x denser than itself.  Smaller meshes: every level from the user's mesh.
    src = report.welded  # (V, F) welded and cleaned by the validation
    if len(src[1]) > 2 * INTERMEDIATE_FACTOR * max(targets):
        src = resample_surface(*src, INTERMEDIATE_FACTOR * max(targets), cleaned=True)
    surfaces = [resample_surface(*src, t, cleaned=True) for t in targets]
    Vb, Fb = surfaces[-1]

    pr.stage("tetrahedralize")
    tets = []
    for lvl, (Vs, Fs) in enumerate(surfaces):
        h = triangle_size(Vs, Fs, targets[lvl])
        TV, TT = tetra.tetrahedralize(Vs, Fs, edge_length=(1.0 + s.K) * h, optimize=s.optimize,
                                      opt_iterations=s.opt_iterations, stop_energy=s.stop_energy)
        tets.append((TV, TT, h))
        pr.within("tetrahedralize", (lvl + 1) / len(surfaces))

    pr.stage("levels")
    meshes = []  # final (TV, TT, topo) per level
    level_stats = []
    prev = None
    for lvl in range(s.levels):
        st = {}
        if lvl < n_indep:
            TV, TT, h = tets[lvl]
            st["surface_triangles"] = int(len(surfaces[lvl][1]))
            st["built_by"] = "tetrahedralization"
        else:
            TV, TT, _ = tetra.refine(*prev[:2])
            h = prev[2] * 0.5
            st["built_by"] = "refinement"
        topo = tetra.topology(TT, len(TV))
        if s.snap_to_surface:
            TV, moved = tetra.snap_boundary(TV, TT, topo, bvh, max_move=0.5 * h)
            st["snapped_vertices"] = moved
        TV, TT, n_split = tetra.split_multi_boundary(TV, TT, topo)
        st["split_tets"] = int(n_split)
        topo = tetra.topology(TT, len(TV)) if n_split else topo
        meshes.append((TV, TT, topo))
        level_stats.append(st)
        prev = (TV, TT, h)

    pr.stage("quadgraph")
    levels = []
    for lvl, (TV, TT, topo) in enumerate(meshes):
        gl = build_level(TV, TT, bvh, normals, relax_iterations=s.relax_iterations,
                         block_size=s.block_size, topo=topo)
        gl.stats.update(level_stats[lvl])
        gl.sweep_order = rcm_permutation(gl.neighbors, gl.n_inner).astype(np.int32)  # once per bake, not per frame
        levels.append(gl)
        pr.within("quadgraph", (lvl + 1) / len(meshes))

    pr.stage("transfer")
    shepard = [level_transfer(levels[k], levels[k + 1], s.shepard_surface, s.shepard_inner)
               for k in range(len(levels) - 1)]
    vmap = vertex_mapping(V, normals, levels[-1], s.vertex_map_k)
    bake = Bake(levels=levels, shepard=shepard, vertex_map=vmap, mesh_vertices=V, mesh_faces=F,
                mesh_normals=normals, shadow_vertices=Vb, shadow_faces=Fb, settings=s,
                mm_per_unit=float(s.mm_per_unit), key=key, mesh_bvh_order=bvh.leaf_tris.astype(np.int32),
                surface_thickness=kept_thickness(bvh, V, F, levels[-1]))
    if s.sky_directions:
        from ..diffusion.sky_visibility import compute_sky_visibility

        pr.stage("sky visibility")
        bake.sky = compute_sky_visibility(bake, s.sky_directions, bvh=bvh,
                                          progress=lambda f: pr.within("sky visibility", f))
    pr.done()

    bake.stats = stats = {
        "mesh": {
            "vertices": report.n_vertices, "triangles": report.n_triangles, "holes": report.holes,
            "boundary_edges": report.boundary_edges, "warnings": report.warnings,
        },
        "resampled_triangles": [int(len(f)) for _, f in surfaces],
        "levels": [dict(lv.stats) for lv in levels],
        "timings": {k: round(v, 4) for k, v in pr.timings.items()},
        "seconds": round(time.perf_counter() - t_start, 4),
        "settings": asdict(s),
    }
    stats["graph_bytes"] = bake.graph_bytes()
    stats["ray_casts"] = ray_path_note()  # '' when compiled
    return bake


def kept_thickness(bvh, V, F, level: GraphLevel) -> KeptThickness:
    """The planner's thickness of ``level``'s surface nodes (:func:`.raycast.inward_thickness`), measured at
    bake time with the digest of what it was measured on."""
    return KeptThickness(inward_thickness(bvh, V, level.surface_position, level.normal),
                         thickness_digest(V, F, level.surface_position, level.normal))


def format_stats(bake: Bake) -> str:
    """Human-readable bake report (CLI and Info log)."""
    st = bake.stats
    lines = [
        f"mesh: {st['mesh']['vertices']} vertices, {st['mesh']['triangles']} triangles"
        + (f", {st['mesh']['holes']} holes" if st['mesh']['holes'] else ""),
        f"resampled surface: {', '.join(str(x) for x in st['resampled_triangles'])} triangles",
    ]
    for i, lv in enumerate(bake.levels):
        q = lv.stats
        lines.append(
            f"level {i}: N_s={lv.n_surface:,} N_i={lv.n_inner:,} "
            f"tet quality min {q.get('tet_quality_min', 0):.3g} median {q.get('tet_quality_median', 0):.3g}"
            + (f", split {q['split_tets']}" if q.get("split_tets") else "")
        )
    t = st["timings"]
    lines.append("seconds: " + ", ".join(f"{k} {v:.2f}" for k, v in t.items()) + f"; total {st['seconds']:.2f}")
    lines.append(f"graph memory: {bake.graph_bytes() / 2**20:.1f} MiB")
    for w in st["mesh"]["warnings"]:
        lines.append(f"warning: {w}")
    if st.get("ray_casts"):
        lines.append(f"note: {st['ray_casts']}")
    return "\n".join(lines)
