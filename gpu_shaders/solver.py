"""The diffusion solve on the GPU: ``GPUDiffusionSolver(DiffusionSolver)``.

Only the linear solves (and, optionally, the radiance output) move to the
GPU; assembly, material sampling, the light pass and the CPU output stay in
``diffusion.DiffusionSolver``, so the physics is written once.  Same rules as
the CPU path:

* ``options.solver == "fast"``: Chebyshev semi-iteration with the Jacobi
  preconditioner and the bounds of ``spectral.spectral_bounds`` (in fp16 the
  upper bound is raised to the Gershgorin bound of the *stored* matrix if
  that is larger, so rounding can never push an eigenvalue out of the
  interval); ``"paper"``/``"jacobi"``: Jacobi sweeps (eqs. 8-9 on the
  paper's scheme); ``"direct"`` has no GPU form and runs on the CPU.
* stopping rule: relative residual ``|b - A x| / |b|`` per channel <= tol
  (``coarse_tol`` on coarser levels), tested every ``check_every`` steps
  (recursive residual for Chebyshev; then the true residual is computed,
  and if fp32 drift left it above tol the iteration restarts from it, at
  most 3 times);
  Jacobi stops early if it diverges (residual above 1e3 times max(1, the
  initial one), or not finite), as ``iterative.solve_jacobi`` does.
* the solution checks after each level: the default ("fast") solver's level is read back and
  passed to ``DiffusionSolver.checked_level``, the step the CPU path takes too (discrete maximum
  principle, energy balance); a level that fails is redone by sparse LU on the CPU and uploaded as
  the level's iterate, so the finer levels and the output start from it;
* multi-level warm start: coarse to fine with eq. 10 between levels; a
  ``warm_start`` result starts the finest level directly -- from the
  texture still on the GPU when it is this solver's latest result, else from
  its ``phi[-1]`` (uploaded).

Per frame only q is uploaded; after :meth:`set_material` only the
coefficients.  Read back: the few numbers of each convergence test, each
level's phi for the solution checks (the default solver; Jacobi is not
checked), the finest level's surface values (always), and the vertex
radiance in :meth:`vertex_radiance`; ``readback="phi"`` also keeps every
level's phi in the result.
"""

from __future__ import annotations

import time
import weakref
from collections import Counter
from dataclasses import dataclass, field, replace

import numpy as np

from . import device, pack, runtime
from ._engine import diffusion, errors, fluid, iterative, kernels, quadgraph, spectral

READBACKS = ("surface", "phi", "none")
_LIVE = weakref.WeakSet()  # every GPU solver, for free_all()


@dataclass
class GPUSolveResult(diffusion.SolveResult):
    """A :class:`diffusion.SolveResult` from the GPU.

    ``phi[i]`` is a numpy array only where it was read back (``readback="phi"``);
    ``phi_surface[i]`` holds the surface values (finest level always).
    ``generation`` identifies the solve whose iterate is still on the GPU.
    """

    phi_surface: list = field(default_factory=list)
    backend: str = "GPU"
    precision: str = "fp32"
    generation: int = -1
    solver_id: int = 0

    def surface_phi(self, level: int = -1) -> np.ndarray | None:
        if self.phi_surface and self.phi_surface[level] is not None:
            return self.phi_surface[level]
        return None

    def plus_finest(self, response: "diffusion.SolveResult") -> "diffusion.SolveResult":
        """:meth:`diffusion.SolveResult.plus_finest` (the cavity exchange's sum), with the read-back surface
        values summed too; the sum is no solve's iterate, so it is never resident on the GPU (the output then
        reads its phi, as the CPU does)."""
        out = super().plus_finest(response)
        mine = list(self.phi_surface) if self.phi_surface else []
        theirs = response.surface_phi(-1) if isinstance(response, GPUSolveResult) else None
        if mine:
            mine[-1] = None if mine[-1] is None or theirs is None else mine[-1] + theirs
        return replace(out, phi_surface=mine, generation=-1)


def default_readback(bake) -> str:
    """``"phi"`` for a bake with a cavity exchange, else ``"surface"``.

    The exchange (``inner_parts/cavity.py``) sums a frame's solution and its wall response on the CPU
    (``SolveResult.plus_finest``) and reads the solution at the walls after each GMRES step: every solve's
    finest phi comes back (a few MB per solve).  Elsewhere the frame needs the surface only."""
    exchange = getattr(getattr(bake, "composite", None), "exchange", None)
    return "phi" if exchange is not None and exchange.m > 0 else "surface"


class GPUDiffusionSolver(diffusion.DiffusionSolver):
    """``DiffusionSolver`` whose linear solves run as compute shaders (Blender ``gpu`` module).

    Extra keyword arguments:

    * ``precision``: ``"fp32"`` (default) or ``"fp16"`` (coefficients, q and
      Shepard weights in RGBA16F; see ``pack.py``);
    * ``readback``: ``"surface"``, ``"phi"`` or ``"none"``; by default :func:`default_readback`;
    * ``max_texture_size`` / ``max_layers``: override the device limits
      (tests; levels that do not fit are split into layers or refused with
      :class:`errors.GraphTooLarge`).

    Construct it through :func:`gpu_shaders.make_solver`, which falls back to
    the CPU when no GPU context can be had.  Call :meth:`free` when the object,
    the bake or the add-on goes away (safe to call twice; a later solve
    uploads everything again).
    """

    backend = "GPU"
    #: a pose of the bake (deformed frames) re-uploads the coefficients only: the links, the transfers and
    #: the vertex map are the rest pose's (``DiffusionSolver.rebind``, :func:`set_material`)
    rebinds_poses = True

    def __init__(self, bake, material, field_values=None, options=None, *, precision: str = "fp32",
                 readback: str | None = None, max_texture_size: int | None = None, max_layers: int | None = None):
        if precision not in pack.PRECISIONS:
            raise errors.TranslucencyError(f"unknown GPU precision {precision!r}; choose fp32 or fp16")
        if readback is None:
            readback = default_readback(bake)
        if readback not in READBACKS:
            raise errors.TranslucencyError(f"unknown readback {readback!r}; choose one of {', '.join(READBACKS)}")
        self.precision = precision
        self.readback = readback
        self._limits = (max_texture_size, max_layers)
        self._gpu_levels = None
        self._vmap = None
        self._generation = 0
        self._resident_generation = -1
        self._freed = False
        self.uploads = Counter()
        self.last_surface = None
        super().__init__(bake, material, field_values, options)
        self.layouts, self.vertex_layout = self._plan()
        self._upload_graph()
        self._upload_coefficients()
        _LIVE.add(self)

    # ------------------------------------------------------------ resources
    def _plan(self):
        max_size, max_layers = self._limits
        if max_size is None or max_layers is None:
            import gpu

            if max_size is None:
                max_size = gpu.capabilities.max_texture_size_get()
            if max_layers is None:
                max_layers = gpu.capabilities.max_texture_layers_get()
        layouts = []
        for i, lv in enumerate(self.bake.levels):
            pages = pack.link_pages(np.asarray(lv.neighbors).shape[1])  # the link pages share the layer budget
            lay = pack.plan_layout(lv.n_inner, lv.n_surface, getattr(lv, "block_size", quadgraph.BLOCK_SIZE),
                                   max_size, max(1, max_layers // pages), what=f"level {i}")
            layouts.append(lay)
        idx = self.bake.vertex_map[0]
        # A vertex map of more than 8 nodes per point (a fluid's surface map: up to 24) has no GPU packing:
        # its output is the CPU formula on the read-back surface (vertex_radiance).
        vl = pack.plan_vertex_layout(len(idx), max_size) if np.asarray(idx).shape[1] <= 8 else None
        return layouts, vl

    def _upload_graph(self) -> None:
        """Graph textures: neighbours, Shepard transfer, vertex map (once per bake)."""
        levels = []
        for i, (lv, lay) in enumerate(zip(self.bake.levels, self.layouts)):
            g = device.GPULevel(lay, lv.neighbors, self.precision)
            if i > 0:
                idx, w = self.bake.shepard[i - 1]
                g.set_transfer(self.layouts[i - 1], idx, w)
            levels.append(g)
        idx, w = self.bake.vertex_map
        self._vmap = None if self.vertex_layout is None else device.GPUVertexMap(self.vertex_layout,
                                                                                  self.layouts[-1], idx, w)
        self._gpu_levels = levels
        self._resident_generation = -1
        self._freed = False
        self.uploads["graph"] += 1

    def _upload_coefficients(self) -> None:
        for g, system in zip(self._gpu_levels, self.systems):
            g.upload_coefficients(system.off, system.diag, system.b_scale)
        self.uploads["coefficients"] += 1

    def _ensure(self) -> None:
        if self._gpu_levels is None:
            self._upload_graph()
            self._upload_coefficients()
            _LIVE.add(self)

    def set_material(self, material, field_values=None) -> None:
        """Re-sample kappa and mu (CPU, shared) and re-upload only the coefficient textures."""
        super().set_material(material, field_values)
        if getattr(self, "_gpu_levels", None) is not None:
            self._upload_coefficients()

    def free(self) -> None:
        """Release every GPU texture of this solver.  Safe to call more than once."""
        if self._gpu_levels is not None:
            for g in self._gpu_levels:
                g.free()
        if self._vmap is not None:
            self._vmap.free()
        self._gpu_levels = None
        self._vmap = None
        self._resident_generation = -1
        self._freed = True
        _LIVE.discard(self)

    @property
    def is_freed(self) -> bool:
        return self._gpu_levels is None

    @property
    def gpu_levels(self) -> list:
        self._ensure()
        return self._gpu_levels

    def gpu_bytes(self) -> int:
        return sum(pack.texture_bytes(lay, self.precision, transfer=i > 0,
                                      pages=pack.link_pages(np.asarray(lv.neighbors).shape[1]))
                   for i, (lay, lv) in enumerate(zip(self.layouts, self.bake.levels)))  # freed or not: no upload

    # ------------------------------------------------------------ solve
    def solve_steps(self, lights=(), environment=None, **kw):
        """The driver's own steps (the levels run on the GPU without yielding), its result as a
        :class:`GPUSolveResult` (``solve``, ``frame.diffuse`` and the progressive frames all come here)."""
        res = yield from super().solve_steps(lights, environment, **kw)
        if self.options.solver == "direct":
            return res
        return GPUSolveResult(phi=res.phi, q=res.q, level_solves=res.level_solves, seconds=res.seconds,
                              scheme=res.scheme, warnings=res.warnings, phi_surface=self.last_surface,
                              q_incident=res.q_incident, single=res.single, beams=res.beams,
                              volume=res.volume, precision=self.precision,
                              generation=self._resident_generation, solver_id=id(self))

    def can_warm_start(self, warm_start) -> bool:
        """A result read back with phi, or one of this solver's still resident on the GPU."""
        return super().can_warm_start(warm_start) or self._is_resident(warm_start)

    def _is_resident(self, ws) -> bool:
        return (isinstance(ws, GPUSolveResult) and ws.solver_id == id(self) and ws.generation >= 0
                and ws.generation == self._resident_generation)

    def _q_scale(self, q, active, volume=None) -> float:
        if self.precision != "fp16":
            return 1.0
        m = max((float(np.abs(q[i]).max(initial=0.0)) for i in active if q[i] is not None), default=0.0)
        if volume is not None:  # stored over the inner nodes' unit (pack.pack_coefficients; after _ensure)
            m = max([m] + [float(np.abs(volume[i]).max(initial=0.0)) / self._gpu_levels[i].coef.inner_unit
                           for i in active if volume[i] is not None])
        return pack.pow2_scale(m)

    def solve_systems(self, q, active, warm_start=None, cols=(0, 1, 2), volume=None):
        """The GPU replacement of ``DiffusionSolver.solve_systems`` (same contract).  Every channel is solved
        whatever ``cols`` says (the kernels run on vec4s: three channels cost one); the driver zeroes the
        channels the planner turned off.  ``volume``: the lamps' volume source per level, uploaded in the
        inner nodes' texels of q."""
        opts = self.options
        if opts.solver == "direct":
            return super().solve_systems(q, active, warm_start, cols, volume)
        self._ensure()
        n_lv = len(self.bake.levels)
        phi = [None] * n_lv
        surface = [None] * n_lv
        solves = []
        sq = self._q_scale(q, active, volume)
        prev = None
        for i in active:
            t0 = time.perf_counter()
            g = self._gpu_levels[i]
            system = self.systems[i]
            old_scale = g.q_scale
            vol = None if volume is None else volume[i]
            g.upload_q(q[i], sq, vol)
            self.uploads["q"] += 1
            if not np.any(q[i]) and (vol is None or not np.any(vol)):  # no light: exactly 0 (as on the CPU)
                g.clear_x()
            elif warm_start is not None and i == n_lv - 1:
                self._warm(g, warm_start, old_scale, sq)
            elif prev is not None:
                g.upsample_from(prev)
            else:
                g.clear_x()
            tol = self.level_tolerance(i)
            bn = np.sqrt(kernels.squared_norms(g.stored_rhs()))
            bn = np.where(bn > 0, bn, 1.0)
            if opts.solver == "fast":
                info = self._chebyshev(g, system, bn, tol, opts.max_iterations, opts.check_every)
            else:
                info = self._jacobi(g, bn, tol, opts.max_iterations, opts.check_every)
            x = g.read(g.x_current).astype(np.float64) / sq if self.readback == "phi" or self.guards_solutions \
                else None
            if self.guards_solutions:  # the shared checks, on the level read back; a redo goes back to the GPU
                checked, info = self.checked_level(i, system, q[i], system.rhs(q[i], vol), x, info)
                if checked is not x:
                    g.set_x(checked * sq)
                    x = checked
            if self.readback == "phi":
                phi[i] = x
            info.seconds = time.perf_counter() - t0
            solves.append(info)
            prev = g
        last = active[-1]
        g = self._gpu_levels[last]
        if self.readback == "phi":
            surface[last] = phi[last][g.layout.n_inner:]
        elif self.readback == "surface":
            surface[last] = g.read_nodes(g.x_current, g.layout.n_inner, g.layout.n_surface).astype(np.float64) / sq
        self._generation += 1
        self._resident_generation = self._generation if last == n_lv - 1 else -1
        self.last_surface = surface
        return phi, solves

    def _warm(self, g: device.GPULevel, ws, old_scale: float, new_scale: float) -> None:
        if self._is_resident(ws):
            if new_scale != old_scale:  # the iterate on the GPU is in units of the old q scale
                g.scale_x(new_scale / old_scale)
            return
        x0 = ws.phi[-1] if ws.phi else None
        if x0 is not None:
            g.set_x(np.asarray(x0, dtype=np.float64) * new_scale)
        else:
            g.clear_x()  # a result without phi that is no longer resident: start from zero

    def _chebyshev(self, g: device.GPULevel, system, bn, tol, max_iter, check_every,
                   replacements: int = 3) -> iterative.LevelSolve:
        """Chebyshev as iterative.solve_chebyshev, plus residual replacement.

        When the recursive residual meets ``tol`` the true residual b - A x is
        computed; in fp32 the recursive one can drift below it, and then the
        iteration restarts from the true residual (at most ``replacements``
        times, and only while that helps), so the reported residual is the
        true one and meets ``tol`` wherever fp32 can reach it.
        """
        lam_min, lam_max = spectral.spectral_bounds(system)
        if self.precision == "fp16":
            lam_max = np.maximum(lam_max, g.coef.gershgorin)
        theta = 0.5 * (lam_max + lam_min)
        delta = 0.5 * (lam_max - lam_min)
        sigma = theta / delta
        g.residual()
        res = np.sqrt(g.norm2(g.r)) / bn
        hist = [float(res.max())]
        it = 0
        restarts = 0
        while res.max() > tol and it < max_iter:
            rho = 1.0 / sigma
            skip = it + iterative.first_check(res, tol, sigma, check_every)  # fewer reductions/read-backs
            g.cheb_init(theta)
            a, b = 0, 1
            while it < max_iter:
                rho_next = 1.0 / (2.0 * sigma - rho)
                g.chebyshev(g.d[a], g.d[b], rho_next * rho, 2.0 * rho_next / delta)
                a, b = b, a
                rho = rho_next
                it += 1
                if it % check_every == 0 and it >= skip:
                    rec = np.sqrt(g.norm2(g.r)) / bn
                    hist.append(float(rec.max()))
                    if rec.max() <= tol or not np.all(np.isfinite(rec)):
                        break
            previous = res
            g.residual()  # the recursive r drifts from b - A x; use and report the true one
            res = np.sqrt(g.norm2(g.r)) / bn
            restarts += 1
            if restarts > replacements or not res.max() < 0.5 * previous.max():
                break
        return iterative.LevelSolve(it, res, hist, 0.0)

    def _jacobi(self, g: device.GPULevel, bn, tol, max_iter, check_every) -> iterative.LevelSolve:
        g.residual()
        res = np.sqrt(g.norm2(g.r)) / bn
        hist = [float(res.max())]
        first = max(hist[0], 1.0)
        it = 0
        while it < max_iter and res.max() > tol:
            for _ in range(check_every):
                g.jacobi_step()
            it += check_every
            g.residual()
            res = np.sqrt(g.norm2(g.r)) / bn
            hist.append(float(res.max()))
            if not np.all(np.isfinite(res)) or res.max() > 1e3 * first:
                break  # diverging (the paper's scheme under kappa contrast), as iterative.solve_jacobi
        return iterative.LevelSolve(it, res, hist, 0.0)

    # ------------------------------------------------------------ output
    def is_resident(self, result) -> bool:
        """True when ``result``'s finest iterate is still on the GPU."""
        return (isinstance(result, GPUSolveResult) and result.solver_id == id(self)
                and self._gpu_levels is not None and result.generation >= 0
                and result.generation == self._resident_generation)

    def read_phi(self, result, level: int = -1) -> np.ndarray:
        """Full phi of a level: from the result if it was read back, else from the GPU (finest, resident)."""
        if result.phi[level] is not None:
            return result.phi[level]
        n_lv = len(self.bake.levels)
        if (level % n_lv) != n_lv - 1 or not self.is_resident(result):
            raise errors.TranslucencyError("phi of this level was not read back and is no longer on the GPU; "
                                           "solve with readback='phi'")
        g = self._gpu_levels[-1]
        return g.read(g.x_current).astype(np.float64) / g.q_scale

    def surface_phi(self, result, level: int = -1) -> np.ndarray:
        """Surface phi of a level: read back with every solve (finest level), else from the GPU."""
        phi_s = result.surface_phi(level) if isinstance(result, GPUSolveResult) else None
        if phi_s is None:
            phi_s = self.read_phi(result, level)[self.bake.levels[level].n_inner:]
        return phi_s

    def vertex_radiance(self, result, view_dirs=None, transported: bool = True) -> np.ndarray:
        """L_o at the user's vertices: on the GPU when the result is resident, else the CPU formula;
        ``transported`` as ``DiffusionSolver.split_radiance_at``."""
        if not self.is_resident(result) or self._vmap is None:
            return super().vertex_radiance(result, view_dirs, transported)
        g = self._gpu_levels[-1]
        cos_o = None
        if view_dirs is not None:
            cos_o = np.einsum("vj,vj->v", self.bake.mesh_normals, np.asarray(view_dirs, dtype=np.float64))
        g.jplus(self.fdr)  # J+ into the scratch residual texture
        out_scale = 1.0 / (np.pi * self.eta * self.eta * g.q_scale)
        L = self._vmap.radiance(g.r, self.eta, out_scale, cos_o).astype(np.float64)
        L *= self.output_clamp(result)[None, :]  # the CPU output's power-preserving clamp, on the read-back phi_s
        idx, w = self.bake.vertex_map
        return self.split_radiance_at(result, L, idx, w, self.bake.mesh_normals, view_dirs,  # closed form, CPU
                                      transported)

    def power_balance(self, result, level: int = -1, clamp: bool = True) -> dict:
        if result.phi[level] is None:
            phi = list(result.phi)
            phi[level] = self.read_phi(result, level)
            result = diffusion.SolveResult(phi=phi, q=result.q, level_solves=result.level_solves,
                                           scheme=result.scheme, q_incident=result.q_incident, single=result.single,
                                           beams=result.beams, volume=result.volume)
        return super().power_balance(result, level, clamp)


class GPUFluidDiffusionSolver(fluid.FluidDiffusionSolver, GPUDiffusionSolver):
    """A particle fluid's frame (Kang & Kim 2013) with its diffusion solved on the GPU: the light pass is the
    fluid's (its ball occluder, ``fluid.FluidDiffusionSolver``), the solve this module's.  The Voronoi-fluid
    cells have 15-25 links each, packed in link pages (``pack.link_pages``); the graph is new every frame,
    so it is uploaded every frame, and phi comes back (``readback="phi"``: the next frame's warm start and
    the per-particle output read it).  Pass it to ``FluidSolver(make_solver=...)``."""

    def __init__(self, frame, material, field_values=None, options=None, **gpu_options):
        gpu_options.setdefault("readback", "phi")
        super().__init__(frame, material, field_values, options, **gpu_options)


def free_all() -> int:
    """Free every live GPU solver's textures and the compiled kernels (add-on unregister)."""
    n = 0
    for s in list(_LIVE):
        s.free()
        n += 1
    runtime.free_shaders()
    return n
