# SPDX-License-Identifier: GPL-3.0-or-later
"""Our side of the accuracy benchmark: bake, solve, per-vertex radiance toward the camera, raster.

One :class:`Evaluator` per run memoises bakes (in memory, and on disk under
``bench/out/accuracy_bakes`` so re-runs skip fTetWild; the bake time reported
is the one measured when the bake was made, stored in ``Bake.stats``) and
the field values per level.  :meth:`Evaluator.run` renders one configuration
of one matched scene and times it the way the add-on uses it:

* ``first_ms``: the first frame: light pass (q at every level), the solve of
  all levels coarse to fine from zero (multi-resolution warm start, eq. 10),
  the vertex radiance toward the camera;
* ``frame_ms``: the frame-to-frame case: the sky turned by 5 degrees and back,
  each frame warm-started from the previous one (finest level only); the
  mean of the two frames.  Its image is the one compared (it ends at the
  scene's sky), so the iteration error a warm start leaves is included.

Radiance is per vertex of the scene mesh with per-vertex view directions
toward the camera (``DiffusionSolver.vertex_radiance(result, view_dirs)``),
rasterised with ``bench/reference/raster.py`` from the reference's camera.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from bench.reference.raster import rasterize
from bench.reference.scene import sky_environment

ROOT = Path(__file__).resolve().parents[1]
BAKE_CACHE = ROOT / "bench" / "out" / "accuracy_bakes"
SUPERSAMPLE = 4
# Every term on, as the add-on's planner runs it on these scenes (issue 17): the diffusion solve splits off the
# closed-form single scattering (DiffusionSolver.solve(single=...), diffusion/split.py).  A
# configuration asks for diffusion alone with solve_options single_scattering=False.
ALL_TERMS = True


def view_dirs(scene) -> np.ndarray:
    """Unit vectors from each vertex toward the camera."""
    cam = scene.camera
    _, _, f = cam.basis()
    if cam.kind == "orthographic":
        return np.broadcast_to(-f, scene.V.shape).copy()
    d = np.asarray(cam.position)[None, :] - scene.V
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def rotate(v, axis, deg):
    a = np.deg2rad(deg)
    k = np.asarray(axis, float) / np.linalg.norm(axis)
    v = np.asarray(v, float)
    return v * np.cos(a) + np.cross(k, v) * np.sin(a) + k * (k @ v) * (1 - np.cos(a))


def environment_turned(scene, deg: float):
    """The scene's sky turned by ``deg`` about the camera's up axis (a uniform one unchanged)."""
    env = scene.environment
    if env.sh is None or deg == 0:
        return env
    from bench.accuracy_scenes import SKY_DIR

    return sky_environment(rotate(SKY_DIR, (0.0, 1.0, 0.0), deg), lobe=2, irradiance=np.pi)



# The add-on's default: bakes carry sky visibility (Object > Translucency > Self-Occlusion) and each
# solve adds one interreflection bounce (ops/runtime._solve).  BakeSettings(sky_directions=0) and
# SolveOptions(sky_occlusion=False) measure the engine without it.
from translucency_addon.diffusion.sky_visibility import DEFAULT_DIRECTIONS as SKY_DIRECTIONS  # noqa: E402


def solve(solver, **kw):
    """A solve as the add-on runs it: ``(result, result)`` (the pair keeps the callers' shape).

    ``DiffusionSolver.solve_interreflected``: with sky visibility in the bake, the first pass and
    the pass with its interreflection bounce are one block solve (``interreflection.py``; the GPU
    backend still runs two passes), so the iterations reported are those of that one solve.
    """
    res, _ = solver.solve_interreflected(**kw)
    return res, res

@dataclass
class Render:
    image: np.ndarray  # (H, W, 3)
    mask: np.ndarray
    vertex: np.ndarray  # (n, 3)
    bake_s: float = 0.0
    first_ms: float = 0.0
    frame_ms: float = 0.0
    iterations: int = 0  # finest level, first frame
    frame_iterations: float = 0.0
    residual: float = 0.0
    diverged: bool = False
    nodes: tuple = ()  # (n_surface, n_inner) of the finest level
    extra: dict = field(default_factory=dict)


class Evaluator:
    def __init__(self, bake_cache: Path | None = BAKE_CACHE, log=print):
        self.bake_cache = Path(bake_cache) if bake_cache else None
        self._bakes = {}
        self._fields = {}
        self._ss = {}
        self.log = log

    # -- bakes -------------------------------------------------------------------------
    def bake(self, scene, **settings):
        """``(Bake, seconds)`` of the scene's mesh with BakeSettings(**settings)."""
        from translucency_addon.quadgraph import bake as bake_mod
        from translucency_addon import cache
        from translucency_addon.diffusion.split import has_transport_tables

        settings.setdefault("sky_directions", SKY_DIRECTIONS)
        s = bake_mod.BakeSettings(mm_per_unit=scene.mm_per_unit, **settings)
        key = bake_mod.mesh_key(scene.V, scene.F, s)
        if key in self._bakes:
            return self._bakes[key]
        path = self.bake_cache / f"{key[:24]}.npz" if self.bake_cache else None
        bk = None
        if path is not None and path.exists():
            try:
                bk = cache.load_bake(str(path), expected_key=key)
            except Exception as ex:  # noqa: BLE001 - stale cache: bake again
                self.log(f"  (bake cache {path.name} unusable: {str(ex)[:80]})")
        if bk is None:
            t0 = time.perf_counter()
            bk = bake_mod.bake_mesh(scene.V, scene.F, s)
            bk.stats["bench_seconds"] = time.perf_counter() - t0
            if path is not None:
                path.parent.mkdir(parents=True, exist_ok=True)
                cache.save_bake(str(path), bk, etas=(scene.material.eta,))
        elif path is not None and not has_transport_tables(scene.material.eta):
            # a cache written before the bench kept the split's tables: keep them now, as the add-on's and the
            # command line's bakes do for the object's material, so a first frame here is a user's first frame
            # after loading a bake (the tables' 63 half-space solves, ~0.6-1 s a process, are the bake's)
            cache.save_bake(str(path), bk, etas=(scene.material.eta,))
        bk = bk.with_scale(scene.mm_per_unit)
        seconds = float(bk.stats.get("bench_seconds", bk.stats.get("seconds", 0.0)))
        self._bakes[key] = (bk, seconds)
        return bk, seconds

    def field_values(self, scene, bk):
        if scene.field is None:
            return None
        k = (bk.key, repr(scene.field))
        if k not in self._fields:
            from translucency_addon.scene.fields import evaluate_field

            self._fields[k] = [evaluate_field(scene.field, lv.position) for lv in bk.levels]
        return self._fields[k]

    # -- single scattering ------------------------------------------------------------------
    def ss_bake(self, scene, **ss_settings):
        from translucency_addon.scene.fields import evaluate_field
        from translucency_addon.single_scattering import SingleScatteringSettings, bake_single_scattering

        k = (scene.name.split("_sa")[0], repr(scene.material), repr(sorted(ss_settings.items())))
        if k not in self._ss:
            fld = None if scene.field is None else (lambda p, spec=scene.field: evaluate_field(spec, p))
            t0 = time.perf_counter()
            data = bake_single_scattering(scene.V, scene.F, scene.material, fld,
                                          SingleScatteringSettings(**ss_settings), mm_per_unit=scene.mm_per_unit)
            self._ss[k] = (data, time.perf_counter() - t0)
        return self._ss[k]

    # -- one configuration ----------------------------------------------------------------
    def make_solver(self, bk, scene, options, backend: str):
        from translucency_addon.diffusion.solver import DiffusionSolver

        fv = self.field_values(scene, bk)
        if backend == "cpu":
            return DiffusionSolver(bk, scene.material, fv, options)
        import gpu_shaders

        precision = {"gpu32": "fp32", "gpu16": "fp16"}[backend]
        solver, name, msg = gpu_shaders.make_solver(bk, scene.material, fv, options, prefer="GPU",
                                                    precision=precision)
        return solver

    def run(self, scene, bake_settings: dict, solve_options: dict | None = None, backend: str = "cpu",
            ss: dict | None = None, frames: bool = True, keep: bool = False) -> Render:
        from translucency_addon.diffusion.solver import SolveOptions
        from translucency_addon.geometry.meshio import vertex_normals

        bk, bake_s = self.bake(scene, **bake_settings)
        opts = SolveOptions(**{"single_scattering": ALL_TERMS, **(solve_options or {})})
        solver = self.make_solver(bk, scene, opts, backend)
        vd = view_dirs(scene)
        env = scene.environment
        # First frame: the best of two runs on graphs below 150k nodes (the machine is shared; the
        # minimum is the least disturbed), and always twice on the GPU (the first call compiles the
        # kernels and uploads the graph).
        repeats = 2 if (backend != "cpu" or bk.finest.n_nodes < 150_000) else 1
        first = np.inf
        for _ in range(repeats):
            t0 = time.perf_counter()
            res, res1 = solve(solver, environment=env)
            L = solver.vertex_radiance(res, vd)
            first = min(first, time.perf_counter() - t0)
        out = Render(image=None, mask=None, vertex=L, bake_s=bake_s, first_ms=1e3 * first,
                     iterations=int(res1.level_solves[-1].iterations), residual=float(np.max(res.residual)),
                     diverged=any(ls.diverged for ls in res.level_solves + res1.level_solves)
                     or not np.all(np.isfinite(L)), nodes=(bk.finest.n_surface, bk.finest.n_inner))
        out.extra["level_iterations"] = [int(ls.iterations) for ls in res1.level_solves]
        out.extra["bounce_iterations"] = int(res.level_solves[-1].iterations) if res is not res1 else 0
        if frames and not out.diverged:
            times, its = [], []
            prev = res
            for deg in (5.0, 0.0):
                e = environment_turned(scene, deg)
                t0 = time.perf_counter()
                r, r1 = solve(solver, environment=e, warm_start=prev)
                L2 = solver.vertex_radiance(r, vd)
                times.append(time.perf_counter() - t0)
                its.append(r1.level_solves[-1].iterations)
                prev = r
            out.frame_ms = 1e3 * float(np.mean(times))
            out.frame_iterations = float(np.mean(its))
            out.vertex = L2
        else:
            out.frame_ms = out.first_ms
        if ss is not None:
            from translucency_addon.single_scattering import render_vertices, view_rays

            data, ss_s = self.ss_bake(scene, **ss)
            normals = vertex_normals(scene.V, scene.F)
            rays = view_rays(scene.V, scene.F, normals, view_dir=vd[0])
            Lss = render_vertices(data, scene.V, scene.F, normals, [], env, scene.material, rays=rays,
                                  cache_pairs=True)
            t0 = time.perf_counter()  # a frame: light term + cached ray-sample pairs
            Lss = render_vertices(data, scene.V, scene.F, normals, [], env, scene.material, rays=rays,
                                  cache_pairs=True)
            ss_ms = 1e3 * (time.perf_counter() - t0)
            out.vertex = out.vertex + Lss
            out.bake_s += ss_s
            out.frame_ms += ss_ms
            out.first_ms += ss_ms
            out.extra.update(ss_bake_s=ss_s, ss_frame_ms=ss_ms,
                             ss_mfp_voxels=float(data.stats.get("mean_free_path_voxels", np.nan)),
                             ss_samples=int(data.stats.get("n_samples", 0)), ss_vertex=Lss)
        if keep:  # the caller continues this solve (bench/accuracy.py: the converged image)
            out.extra.update(solver=solver, result=prev if frames and not out.diverged else res)
        elif hasattr(solver, "free"):
            solver.free()
        # 4 x 4 samples per pixel: the reference pixels are box-filtered area averages
        ras = rasterize(scene.V, scene.F, out.vertex, scene.camera, scene.resolution, supersample=SUPERSAMPLE)
        out.image, out.mask = ras.image, ras.mask
        return out
