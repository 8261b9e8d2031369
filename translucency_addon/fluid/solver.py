"""A particle fluid's frame: particles -> Voronoi-fluid cells -> the shared diffusion solver -> radiance.

Kang & Kim (2013) rebuild the discretisation from the particles every frame
and relax eqs. 16-17 on it.  :class:`FluidSolver` does the same with the
engine's one solver:

1. :func:`.particles.prepare_particles` -- checks, NaN and duplicates, radius;
2. :func:`.cells.build_cells` -- exact cells (volumes, faces, surface faces), their faces in compiled
   code (:mod:`.compiled_faces`, numba) or, where numba is missing, numpy (the stats say which and why);
3. :func:`.cellgraph.build_graph` -- the cells as a graph of the contract;
4. :class:`FluidDiffusionSolver`, the :class:`~..diffusion.DiffusionSolver`
   itself on a one-level :class:`FluidFrame`: the same ``assemble``, light
   pass (``lights.incident_flux`` with shadow rays), default solve (conjugate
   gradients on a cell graph, with a coarse space from 8,000 nodes:
   ``iterative.fast_steps``, ``diffusion/coarse_space.py``) with its
   maximum-principle and energy-balance guard (sparse LU fallback),
   relative-residual stop and output (J+ clamp, corrected eq. 4/7).  Only two
   helpers of the light pass differ for a fluid: the occluder for shadow rays
   and the inside test for lights (:mod:`.occluder`);
5. warm start: phi of the previous frame's cell with the same particle id
   (without ids, the same index where the particle moved less than R/2; else the nearest previous
   particle), and its spectral estimate;
6. output: :mod:`.surface_map` onto the surface mesh's vertices, or per particle.

Everything is in object units with ``mm_per_unit``, lights and environment as
for meshes (:mod:`..lights`), coefficients per mm (:mod:`..materials`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from ..diffusion.solver import DiffusionSolver, SolveOptions, SolveResult
from ..errors import MaterialError, MeshError
from ..scene.materials import check_mm_per_unit
from ..geometry.meshio import DEFAULT_MEMORY_BUDGET_BYTES, vertex_normals
from ..diffusion.radiance import outgoing_radiance
from ..diffusion.spectral import gershgorin_upper
from .cellgraph import FluidGraph, build_graph
from .cells import build_cells
from .occluder import BallOccluder
from .particles import prepare_particles
from .surface_map import KERNEL_RADII, surface_weights


@dataclass
class FluidOptions:
    solver: str = "fast"  # as SolveOptions.solver: fast (Chebyshev + guard), direct, jacobi
    tol: float = 1e-4  # relative residual at which a frame's solve stops
    max_iterations: int = 50_000
    kernel_radii: float = KERNEL_RADII  # output interpolation radius, in particle radii
    memory_budget: int = DEFAULT_MEMORY_BUDGET_BYTES
    cells: str = "auto"  # the cells' faces: auto (compiled where numba is installed), compiled, numpy

    def solve_options(self) -> SolveOptions:
        # A lamp's light enters a fluid at the surface node it reaches (eq. 3 with eq. 6's share): the
        # volume source (diffusion/beam_source.py) casts chords through a triangle mesh, a fluid is balls.
        return SolveOptions(solver=self.solver, tol=self.tol, max_iterations=self.max_iterations,
                            levels="finest", sky_occlusion=False, lamp_source="boundary")


@dataclass
class FluidFrame:
    """What :class:`~..diffusion.DiffusionSolver` reads of a bake, for one fluid frame.

    One level (the cells), no eq. 10 transfers, no sky visibility; the
    "mesh" is the set of output points (surface-mesh vertices or particles).
    """

    levels: list  # [FluidGraph]
    mm_per_unit: float
    mesh_vertices: np.ndarray  # output points
    mesh_normals: np.ndarray
    vertex_map: tuple  # (idx, w) from the surface nodes to the output points
    occluder: BallOccluder
    mesh_faces: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.int64))
    shepard: list = field(default_factory=list)
    sky: object = None
    surface_bvh: object = None  # the fluid's shadow rays go to its BallOccluder, not a mesh BVH


class FluidDiffusionSolver(DiffusionSolver):
    """The engine's diffusion solver on a :class:`FluidFrame`; only the light pass's occluder, where its
    shadow rays start and the inside test of lights are the fluid's (a union of balls, not a mesh)."""

    def shadow_bvh(self, occluders=None):
        from ..geometry.raycast import TriangleBVH

        occ = self.bake.occluder
        if occluders is None:
            return occ
        tri = occluders if isinstance(occluders, TriangleBVH) else TriangleBVH(*occluders)
        both = BallOccluder.__new__(BallOccluder)
        both.__dict__.update(occ.__dict__)
        both.triangles = tri
        return both

    def shadow_offset(self) -> float:
        """Shadow rays leave a surface node one particle radius out along its normal (:mod:`.occluder`)."""
        return self.bake.occluder.radius

    def lights_inside(self, lights) -> list:
        """Point, spot and area lights within a radius of a particle (inside the fluid)."""
        cand = [light for light in lights if light.kind != "sun"]
        if not cand:
            return []
        flags = self.bake.occluder.inside(np.array([light.position for light in cand], dtype=np.float64))
        return [light for light, f in zip(cand, flags) if f]


@dataclass
class FluidState:
    """What the next frame's warm start needs (per particle of the frame's cleaned set)."""

    points: np.ndarray  # (n, 3)
    ids: np.ndarray | None
    phi_cell: np.ndarray  # (n, 3), 0 for cells left out
    surface_points: np.ndarray  # (n_s, 3)
    surface_particle: np.ndarray  # (n_s,)
    phi_surface: np.ndarray  # (n_s, 3)
    lam_min: np.ndarray | None = None  # the Chebyshev interval's lower end
    tree: object = None  # the points' cKDTree (the cells'): the next frame's nearest-particle match reuses it


@dataclass
class FluidResult:
    """One frame.  Per *input* particle (N): ``phi``, ``volume``, ``surface``, ``cell_radiance``;
    ``vertex_radiance`` (per vertex of the surface mesh) or ``point_radiance`` (per particle)."""

    phi: np.ndarray  # (N, 3) cell fluence
    volume: np.ndarray  # (N,) cell volume, object units^3 (0 where left out)
    surface: np.ndarray  # (N,) bool: the cell has a surface node
    cell_radiance: np.ndarray  # (N, 3) outgoing radiance along the normal at surface cells, W/(m^2 sr)
    vertex_radiance: np.ndarray | None
    point_radiance: np.ndarray | None
    state: FluidState | None
    stats: dict
    warnings: list
    graph: FluidGraph | None = None
    solve: SolveResult | None = None
    diffusion: FluidDiffusionSolver | None = None


class FluidSolver:
    """Multiple scattering in a particle fluid, one call per frame (see the module docstring).

    Typical use, per frame::

        fs = FluidSolver(material, radius=0.01, mm_per_unit=1000.0)
        res = fs.solve(points, ids=ids, lights=lights, environment=env,
                       surface=(V, F), warm_start=previous.state if previous else None)
        res.vertex_radiance   # (n_vertices, 3) W/(m^2 sr), for the translucency_radiance attribute
    """

    def __init__(self, material, radius: float, mm_per_unit: float, options: FluidOptions | None = None, *,
                 make_solver=None):
        self.material = material
        self.radius = float(radius)
        self.mm_per_unit = check_mm_per_unit(mm_per_unit)
        self.options = options or FluidOptions()
        # (frame, material, field_values, options) -> the frame's diffusion solver: FluidDiffusionSolver (the
        # CPU), or the GPU's (gpu_shaders.solver.GPUFluidDiffusionSolver)
        self.make_solver = make_solver or FluidDiffusionSolver

    def solve(self, points, *, ids=None, field_values=None, lights=(), environment=None, surface=None,
              surface_normals=None, view_dirs=None, occluders=None, shadows: bool = True,
              warm_start: FluidState | None = None) -> FluidResult:
        """Solve one frame.

        ``points`` (N, 3) object units; ``ids`` (N,) ints for the warm start;
        ``field_values`` (N,) in [0, 1] for a two-media material; ``surface``
        ``(V, F)`` to carry radiance onto (else per particle), with optional
        ``surface_normals`` and ``view_dirs`` (n_vertices, 3); ``occluders``
        other objects' ``(V, F)`` or a TriangleBVH; ``warm_start`` the
        previous frame's ``result.state``.
        """
        t0 = time.perf_counter()
        opts = self.options
        ps = prepare_particles(points, self.radius, ids, field_values, opts.memory_budget)
        if self.material.heterogeneous and ps.field_values is None:
            raise MaterialError("a two-media material needs field values per particle")
        n_in = len(np.asarray(points))
        warnings = list(ps.warnings)
        seconds = {"particles": time.perf_counter() - t0}
        out_pts, out_nrm = self._outputs(surface, surface_normals)
        if out_pts is None:
            out_pts = ps.points
        if ps.n == 0:
            warnings.append("no particles: nothing to solve, radiance 0")
            return self._zero(n_in, out_pts, surface is not None, seconds, warnings, t0)
        t = time.perf_counter()
        from . import compiled_faces

        loaded = compiled_faces.first_call_seconds()
        cells = build_cells(ps.points, ps.radius, method=opts.cells, tree=ps.tree)
        seconds["cells"] = time.perf_counter() - t
        cell_path = {"cell_path": cells.path, "cell_path_note": cells.path_note,
                     "cell_kernel_first_call_s": compiled_faces.first_call_seconds() if not loaded else 0.0}
        seconds.update({f"cells_{k}": v for k, v in cells.seconds.items()})
        t = time.perf_counter()
        graph = build_graph(cells)
        warnings += graph.warnings
        seconds["graph"] = time.perf_counter() - t
        if graph.n_surface == 0:
            warnings.append("no cell has a free surface face: no light can enter, radiance 0")
            return self._zero(n_in, out_pts, surface is not None, seconds, warnings, t0, graph, ps)
        t = time.perf_counter()
        occ = BallOccluder(ps.points, ps.radius, tree=cells.tree, compiled=cells.path == "compiled")
        seconds["occluder"] = time.perf_counter() - t
        t = time.perf_counter()
        if surface is None:  # a point cloud: its particles, surface cells with their normals
            out_nrm = np.zeros((ps.n, 3))
            out_nrm[graph.cell[graph.surface_cell]] = graph.normal
        idx, w, far = self._weights(out_pts, out_nrm, graph, surface is None)
        if surface is not None and far.any():
            warnings.append(f"{int(far.sum()):,} of {len(far):,} surface-mesh vertices have no surface cell within "
                            f"{self.options.kernel_radii * self.radius:.4g} units on their side and take their "
                            "nearest one: the mesh does not match the particles there")
        frame = FluidFrame(levels=[graph], mm_per_unit=self.mm_per_unit, mesh_vertices=out_pts,
                           mesh_normals=out_nrm, vertex_map=(idx, w), occluder=occ)
        seconds["map"] = time.perf_counter() - t
        t = time.perf_counter()
        fv = None if ps.field_values is None else np.concatenate(
            [ps.field_values[graph.cell], ps.field_values[graph.cell[graph.surface_cell]]])
        solver = self.make_solver(frame, self.material, None if fv is None else [fv], opts.solve_options())
        ws, warm = self._warm_start(warm_start, ps, graph, solver)
        seconds["assemble"] = time.perf_counter() - t
        result = solver.solve(lights, environment, warm_start=ws, shadows=shadows, occluders=occluders)
        warnings += result.warnings
        seconds["light"] = result.seconds["lights"]
        seconds["solve"] = result.seconds["solve"]
        t = time.perf_counter()
        out = self._assemble_result(n_in, ps, graph, solver, result, out_pts, out_nrm, view_dirs, surface)
        seconds["output"] = time.perf_counter() - t
        seconds["total"] = time.perf_counter() - t0
        out.stats.update(self._stats(graph, result, warm, seconds, warnings))
        out.stats.update(cell_path)
        out.warnings = warnings
        return out

    # -- parts ---------------------------------------------------------------------------------------
    def _outputs(self, surface, surface_normals):
        """The output points and their normals: the surface mesh's vertices, or (None) the particles."""
        if surface is None:
            return None, None
        V, F = (np.asarray(a) for a in surface)
        if V.ndim != 2 or V.shape[1] != 3 or not np.all(np.isfinite(V)):
            raise MeshError(f"the fluid's surface mesh needs finite (n, 3) vertices, got {V.shape}")
        if F.ndim != 2 or F.shape[1] != 3 or (F.size and (F.min() < 0 or F.max() >= len(V))):
            raise MeshError(f"the fluid's surface mesh has faces {F.shape} with indices outside its {len(V)} vertices")
        V = V.astype(np.float64)
        if surface_normals is None:
            return V, vertex_normals(V, F.astype(np.int64))
        n = np.asarray(surface_normals, dtype=np.float64)
        if n.shape != V.shape:
            raise MeshError(f"surface normals {n.shape} do not match the mesh's vertices {V.shape}")
        return V, n

    def _weights(self, pts, nrm, graph, point_cloud):
        args = (graph.surface_position, graph.normal, graph.area, self.radius, self.options.kernel_radii,
                graph.surface_tree)
        if not point_cloud:
            return surface_weights(pts, nrm, *args)
        has = np.linalg.norm(nrm, axis=1) > 0  # surface particles by their normal, inner ones by distance
        k_idx, k_w, far = surface_weights(pts, None, *args)
        if has.any():
            s_idx, s_w, far[has] = surface_weights(pts[has], nrm[has], *args)
            kk = max(k_idx.shape[1], s_idx.shape[1])
            k_idx, k_w = _pad(k_idx, kk), _pad(k_w, kk)
            k_idx[has], k_w[has] = _pad(s_idx, kk), _pad(s_w, kk)
        return k_idx, k_w, far

    def _warm_start(self, state, ps, graph: FluidGraph, solver):
        """A SolveResult whose finest phi starts this frame: by particle id; without ids, by index where the
        particle count is unchanged and the particle moved less than half the radius (a particle system's
        own order; a k-d tree query of every particle cost ~20 ms a frame at 16k); else the nearest particle.
        Only where the frame starts depends on this, not its answer.  Returns the start and how many particles
        each way matched (empty without a start)."""
        if state is None or len(state.points) == 0:
            return None, {}
        from scipy.spatial import cKDTree

        cells = graph.cell
        prev, matched = None, {}
        if ps.ids is not None and state.ids is not None:
            order = np.argsort(state.ids)
            pos = np.clip(np.searchsorted(state.ids[order], ps.ids), 0, len(order) - 1)
            match = state.ids[order][pos] == ps.ids
            prev = np.where(match, order[pos], -1)
            matched["id"] = int(match.sum())
        elif len(state.points) == ps.n:
            step = ps.points - state.points
            near = np.einsum("ij,ij->i", step, step) < (0.5 * ps.radius) ** 2
            prev = np.where(near, np.arange(ps.n), -1)
            matched["index"] = int(near.sum())
        matched["nearest"] = ps.n - sum(matched.values())
        if prev is None or (prev < 0).any():
            tree = state.tree if state.tree is not None else cKDTree(state.points)
            if prev is None:
                prev = tree.query(ps.points, k=1)[1]
            else:
                lost = np.nonzero(prev < 0)[0]
                prev[lost] = tree.query(ps.points[lost], k=1)[1]
        x0 = np.zeros((graph.n_nodes, 3))
        x0[:graph.n_inner] = state.phi_cell[prev[cells]]
        if len(state.surface_points):
            sp = graph.cell[graph.surface_cell]
            was = np.full(len(state.points), -1, dtype=np.int64)
            was[state.surface_particle] = np.arange(len(state.surface_particle))
            j = was[prev[sp]]
            miss = j < 0
            if miss.any():
                j[miss] = cKDTree(state.surface_points).query(graph.surface_position[miss], k=1)[1]
            x0[graph.n_inner:] = state.phi_surface[j]
        if state.lam_min is not None:  # the spectrum hardly moves between frames: skip the Lanczos estimate
            system = solver.systems[0]
            system.lam_max = gershgorin_upper(system)
            system.lam_min = np.minimum(state.lam_min, 0.5 * system.lam_max)
        return SolveResult(phi=[x0], q=[None], level_solves=[]), matched

    def _assemble_result(self, n_in, ps, graph, solver, result, out_pts, out_nrm, view_dirs, surface):
        phi_nodes = result.phi[0]
        jplus = solver.surface_partial_current(result)
        L_cell = outgoing_radiance(jplus, np.ones(len(jplus)), solver.eta)
        owner = ps.owner
        ok = owner >= 0
        per_cell = np.zeros((ps.n, 3))
        per_cell[graph.cell] = phi_nodes[:graph.n_inner]
        vol = np.zeros(ps.n)
        vol[graph.cell] = graph.volume
        is_s = np.zeros(ps.n, dtype=bool)
        is_s[graph.cell[graph.surface_cell]] = True
        L_c = np.zeros((ps.n, 3))
        L_c[graph.cell[graph.surface_cell]] = L_cell
        idx, w = solver.bake.vertex_map
        L_out = solver.radiance_at(result, idx, w, out_nrm, view_dirs)
        if surface is None:  # particles without a cell in the graph (isolated, unlit) emit nothing
            L_out[~np.isin(np.arange(ps.n), graph.cell)] = 0.0

        def to_input(a):
            full = np.zeros((n_in,) + a.shape[1:], dtype=a.dtype)
            full[ok] = a[owner[ok]]
            return full

        state = FluidState(points=ps.points, ids=ps.ids, phi_cell=per_cell,
                           surface_points=graph.surface_position.copy(),
                           surface_particle=graph.cell[graph.surface_cell], phi_surface=phi_nodes[graph.n_inner:],
                           lam_min=solver.systems[0].lam_min, tree=ps.tree)
        return FluidResult(phi=to_input(per_cell), volume=to_input(vol), surface=to_input(is_s),
                           cell_radiance=to_input(L_c), vertex_radiance=L_out if surface is not None else None,
                           point_radiance=to_input(L_out) if surface is None else None, state=state,
                           stats={}, warnings=[], graph=graph, solve=result, diffusion=solver)

    def _zero(self, n_in, out_pts, has_surface, seconds, warnings, t0, graph=None, ps=None):
        seconds["total"] = time.perf_counter() - t0
        z = np.zeros((n_in, 3))
        stats = {"particles": int(n_in), "cells": 0 if graph is None else int(graph.n_inner), "surface_nodes": 0,
                 "sweeps": 0, "warm_start": False, "seconds": seconds, "warnings": warnings}
        return FluidResult(phi=z, volume=np.zeros(n_in), surface=np.zeros(n_in, dtype=bool), cell_radiance=z.copy(),
                           vertex_radiance=np.zeros((len(out_pts), 3)) if has_surface else None,
                           point_radiance=z.copy() if not has_surface else None, state=None, stats=stats,
                           warnings=warnings, graph=graph)

    def _stats(self, graph, result, warm, seconds, warnings):
        ls = result.level_solves[0] if result.level_solves else None
        st = dict(graph.stats)
        st.update({
            "sweeps": int(ls.iterations) if ls else 0,
            "relative_residual": [float(x) for x in (ls.residual if ls else np.zeros(3))],
            "solver_note": ls.note if ls else "",
            "warm_start": bool(warm),
            "warm_start_match": dict(warm),  # particles matched to the last frame's: {"id" or "index" (if
            # tried), "nearest"}
            "radius": self.radius, "mm_per_unit": self.mm_per_unit,
            "seconds": {k: float(v) for k, v in seconds.items()},
            "warnings": list(warnings),
        })
        return st


def _pad(a, k):
    if a.shape[1] == k:
        return a
    out = np.zeros((a.shape[0], k), dtype=a.dtype)
    out[:, :a.shape[1]] = a
    return out
