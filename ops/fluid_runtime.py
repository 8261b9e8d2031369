# SPDX-License-Identifier: GPL-3.0-or-later
"""A Fluid source's frame: particles -> plan -> Voronoi-fluid cells and diffusion -> attribute -> status.

The Blender side of Kang & Kim (2013) (the engine is ``translucency_addon.fluid``).
Nothing is baked: every frame rebuilds the cells from the particles.
:func:`solve_fluid` takes one fluid object (the *target*, whose vertices or
points get the radiance) through named steps:

1. :func:`gather` reads the frame from Blender once (:mod:`.fluid_sources`
   for the particles and the target's evaluated geometry; :mod:`.scene_inputs`
   for the scale, the material, the lights, the world, the occluders and the
   view towards the camera in renders) and asks the planner
   (``planner.plan_fluid``: lit, in view, diffusion valid) into a frozen
   :class:`FluidInputs`;
2. :func:`_solve`: ``FluidSolver.solve``, its diffusion where
   :func:`.backend.placement` puts it (on the GPU the cells' 15-25 links
   travel in link pages; a GPU failure sends the fluid to the CPU, with the
   reason), warm-started from the last frame
   by particle id where the source gives ids (the nearest previous particle
   otherwise) while the material and the scale stay the same;
3. :func:`_write`: the ``translucency_radiance`` attribute on ``obj.data``,
   or through the carrier modifier where modifiers generate what renders
   (Mantaflow's liquid mesh, Geometry Nodes; :mod:`.attributes`);
4. :func:`_record` and :func:`.status.publish`: the runtime state the panel
   reads (what the frame cost, stage by stage), and a redraw.

A frame whose inputs (particles, radius, material, lights, world,
occluders, view, the target's geometry) are those of the frame the
attribute holds is not solved again.  No particles at this frame (outside
the particle cache's frame range, before emission) is not an error: the
fluid is not there, its radiance is 0, and the panel and the log say why.
Bad input (NaN, planar or sparse particles, a radius of 0 or larger than the
fluid, too many particles, a source of the wrong kind) raises
:class:`ParticleError` before anything in the scene changes.

Called from :mod:`.runtime` (``solve_object``, ``solve_scene``); it calls
only modules below it.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass

import bpy
import numpy as np

from . import attributes, backend, fluid_sources, scene_inputs, state, status

MEMORY_BUDGET: int | None = None  # bytes a frame's cells may take; None: the engine's default (4 GiB)


@dataclass(frozen=True)
class FluidInputs:
    """Everything one fluid frame needs, read from Blender once (:func:`gather`)."""

    name: str
    frame: int
    mm: float  # millimetres per object unit of the target
    scale: float  # scene (world) units per object unit
    material: object
    particles: fluid_sources.Particles
    field: np.ndarray | None  # the mixing field per particle (None: homogeneous)
    radius: float  # object units; 0 when there is nothing to solve
    suggested: float  # the radius Auto Radius gives at this frame, object units (0: fewer than two particles)
    auto: bool
    output: fluid_sources.Output
    use_points: bool  # the radiance goes onto the particles themselves (a point cloud that is its own source)
    carried: bool  # through the carrier modifier (generated geometry)
    lights: tuple
    environment: object | None
    view: tuple | None  # towards the render camera (renders), object space
    occluders: object
    occ_sig: tuple | None
    plan: object | None  # None when there is nothing to plan (no particles)
    empty: str  # why there is nothing to solve ('' when there is)
    tolerance: float
    rendering: bool
    off_main: bool
    warnings: tuple
    prefer: str = "AUTO"  # Scene > Translucency > Solver (AUTO, GPU, CPU)


@dataclass
class FluidReport:
    """What one fluid frame did, for the Info log, the console and the Solve operator."""

    name: str
    frame: int
    seconds: float
    particles: int
    output: str
    solved: bool = True  # False: the radiance was re-evaluated towards a new view, or the frame deferred
    sweeps: int = 0
    residual: float = 0.0
    warm: bool = False
    stages: dict | None = None
    view: str = "NORMAL"
    skipped: str = ""  # the planner's reason when nothing ran
    empty: str = ""  # why there were no particles
    deferred: bool = False  # left to the throttled live check (playback; the frame is slow)
    backend: str = "CPU"

    def describe(self) -> str:
        if self.deferred:
            return (f"'{self.name}' fluid frame {self.frame} left to the live check: a frame takes "
                    f"{self.seconds:.2f} s, so playback does not wait for it")
        if self.skipped:
            return f"'{self.name}' skipped, nothing computed: {self.skipped}"
        if self.empty:
            return f"'{self.name}' fluid frame {self.frame}: {self.empty}; radiance 0"
        if not self.solved:
            return (f"'{self.name}' fluid frame {self.frame}: radiance re-evaluated towards the camera (the particles, "
                    "lights and material are those of the last solve)")
        stages = self.stages or {}
        parts = ", ".join(f"{k} {stages[k]:.2f} s" for k in ("cells", "solve", "light", "output") if k in stages)
        return (f"'{self.name}' fluid frame {self.frame}: {self.particles:,} particles -> {self.output}, solved on the "
                f"{self.backend} in {self.seconds:.3f} s ({parts}; {self.sweeps} sweeps, residual "
                f"{self.residual:.2e}{', warm start' if self.warm else ''})")


def length_text(scene, value: float) -> str:
    """A length in scene units as Blender shows it (``value`` in world units)."""
    units = scene.unit_settings
    if units.system == 'NONE':
        return f"{value:.4g}"
    return bpy.utils.units.to_string(units.system, 'LENGTH', value * units.scale_length, precision=4)


# ------------------------------------------------------------------ the frame


def solve_fluid(obj, scene=None, depsgraph=None, *, use_camera: bool = False, force: bool = False):
    """Solve one frame of the fluid ``obj`` shows and write its radiance; ``None`` when nothing changed.

    Raises :class:`TranslucencyError` subclasses with user-facing messages; the scene is then unchanged.
    """
    scene = scene or bpy.context.scene
    if depsgraph is None:
        depsgraph = bpy.context.evaluated_depsgraph_get()
    if obj.mode == 'EDIT':
        return None  # attribute writes are lost when leaving edit mode
    t0 = time.perf_counter()
    with state.lock():
        st = state.fluid_state(obj)
        frame = gather(obj, scene, depsgraph, st, use_camera)
        state.set_plan(obj.name, frame.plan)
        if frame.plan is not None:
            if not frame.plan.run and frame.plan.reason.startswith("outside the camera view"):
                state.count("planner_skips")
                return None
        solve_sig = _signature(frame)
        sig = (solve_sig, frame.view)
        if not force and sig == st.sig and _written(obj, frame):
            return None
        if not force and solve_sig == st.solve_sig and st.result is not None:
            _write(obj, frame, _towards_the_view(frame, st.result))  # only the view changed: no new cells
            st.sig = sig
            return _report(st, frame, None, solved=False)
        result = _solve(st, frame) if not frame.empty and frame.plan.run else None
        rgb = _radiance(frame, result)
        _write(obj, frame, rgb)
        _record(st, frame, sig, result, time.perf_counter() - t0)
        st.solve_sig = solve_sig
        st.result = result if result is not None and not frame.use_points else None
        if not frame.off_main:
            status.publish(st)
        return _report(st, frame, result)


def gather(obj, scene, depsgraph, st: state.FluidObjectState, use_camera: bool) -> FluidInputs:
    """Read one fluid frame from Blender (see the module docstring); raises on bad input."""
    from ..translucency_addon.fluid import suggest_radius

    settings = obj.translucency
    matrix = obj.evaluated_get(depsgraph).matrix_world.copy()
    mm, scale_warning = scene_inputs.mm_per_unit(obj, scene, matrix)
    scale, _ = scene_inputs.object_scale(obj, matrix)
    material = scene_inputs.build_material(settings)
    attribute = settings.field_attribute if settings.use_heterogeneity and settings.field_source == 'ATTRIBUTE' else None
    particles = fluid_sources.read_particles(obj, scene, depsgraph, attribute or None)
    output = fluid_sources.read_output(obj, depsgraph)
    use_points = output.kind == "points"
    if use_points and (fluid_sources.source_object(obj) != obj or len(output.positions) != particles.n):
        raise _particle_error("a point cloud carries only its own particles' radiance: make it its own Source "
                              "Object, or give the fluid a mesh to shade")
    field = fluid_sources.particle_field(settings, particles)
    finite = particles.points[np.isfinite(particles.points).all(axis=1)]
    if particles.n and not len(finite):
        raise _particle_error(f"all {particles.n:,} particles ({particles.source}) have NaN or Inf positions: the "
                              "particle data is broken")
    suggested = suggest_radius(finite) if len(finite) >= 2 else 0.0
    auto = bool(settings.fluid_radius_auto)
    radius = suggested if auto else float(settings.fluid_radius) / max(scale, 1e-30)
    empty = particles.empty
    if not empty and len(finite) == 1 and auto:
        empty = ("one particle: Auto Radius needs two or more to measure their spacing, and a single ball has no "
                 "inside for the light to diffuse in")
    if not empty and radius <= 0.0:
        raise _particle_error(_zero_radius(scene, auto, suggested * scale))
    environment, world_warning, world_sun = scene_inputs.world_environment(
        scene.world, matrix, getattr(depsgraph, "mode", "VIEWPORT") != 'RENDER'
        and threading.current_thread() is threading.main_thread())
    lights = tuple(scene_inputs.collect_lights(depsgraph, matrix,
                                               scene_inputs.metres_per_world_unit(obj, scene, mm, matrix))) + world_sun
    plan = None
    occluders = occ_sig = None
    if not empty:
        from ..translucency_addon.planner import plan_fluid

        in_view = scene_inputs.in_camera_view(scene, depsgraph, obj) if use_camera else True
        overrides = {} if settings.use_multiple_scattering else {"multiple": False}
        fin = np.isfinite(particles.points).all(axis=1)
        plan = plan_fluid(finite, radius, mm, material, list(lights), environment,
                          field_values=None if field is None else field[fin], in_view=in_view,
                          enabled=bool(settings.enabled), overrides=overrides, name=obj.name)
        if plan.run:
            occluders, occ_sig = scene_inputs.collect_occluders(depsgraph, obj, matrix, st.occluders,
                                                                exclude={particles.source_name})
    return FluidInputs(
        name=obj.name, frame=int(scene.frame_current), mm=mm, scale=scale, material=material, particles=particles,
        field=field, radius=radius, suggested=suggested, auto=auto, output=output,
        use_points=use_points, carried=attributes.uses_carrier(obj, len(output.positions)), lights=lights,
        environment=environment, view=scene_inputs.camera_view(scene, depsgraph, matrix) if use_camera else None,
        occluders=occluders, occ_sig=occ_sig, plan=plan, empty=empty,
        tolerance=float(scene.translucency.tolerance), rendering=getattr(depsgraph, "mode", "VIEWPORT") == 'RENDER',
        off_main=threading.current_thread() is not threading.main_thread(),
        warnings=tuple(w for w in (scale_warning, world_warning) if w),
        prefer=str(scene.translucency.solver_backend))


def _particle_error(message: str):
    from ..translucency_addon.errors import ParticleError

    return ParticleError(message)


def _zero_radius(scene, auto: bool, suggested_world: float) -> str:
    if auto:
        return ("every particle sits at the same place, so their spacing, which Auto Radius uses, is 0: the particle "
                "data is broken, or set a Radius by hand")
    hint = (f" (Auto Radius would use {length_text(scene, suggested_world)} at this frame)" if suggested_world > 0
            else "")
    return f"the particle Radius is 0: set it to about the spacing between particles{hint}"


def _digest(a) -> str | None:
    return None if a is None else scene_inputs.array_digest(np.asarray(a))


def _signature(frame: FluidInputs) -> tuple:
    """What the solve depends on (all but the view): a frame with the same inputs is not solved again."""
    plan = frame.plan
    reaching = set(plan.facts.get("lights_reaching", ())) if plan is not None else set()
    return (_digest(frame.particles.points), _digest(frame.particles.ids), _digest(frame.field), round(frame.radius, 12),
            frame.material, round(frame.mm, 9), tuple(light for light in frame.lights if light.name in reaching),
            scene_inputs.environment_signature(frame.environment), frame.occ_sig,
            _digest(frame.output.positions), frame.carried, frame.tolerance, frame.empty,
            None if plan is None else (plan.run, plan.multiple.channels if plan.multiple is not None else None))


def _written(obj, frame: FluidInputs) -> bool:
    n = len(frame.output.positions)
    return attributes.carrier_ok(obj, n) if frame.carried else attributes.attribute_ok(obj)


def _solver_sig(frame: FluidInputs) -> tuple:
    """What the warm start's phi and spectrum belong to: the material, its field and the scale."""
    return (frame.material, frame.field is None, round(frame.mm, 9))


def _solve(st: state.FluidObjectState, frame: FluidInputs):
    """``FluidSolver.solve`` for this frame, warm-started from the last one where that is the same fluid."""
    from ..translucency_addon.errors import ParticleError, RadiusError
    from ..translucency_addon.fluid import FluidOptions, FluidSolver

    options = FluidOptions(tol=frame.tolerance)
    if MEMORY_BUDGET is not None:
        options.memory_budget = MEMORY_BUDGET
    warm = st.warm if st.solver_sig == _solver_sig(frame) and _similar_radius(st, frame) else None
    out = frame.output
    view_dirs = scene_inputs.view_directions(frame.view, out.positions)
    def solve():
        make = None
        if _placement(st, frame).gpu:
            from ..gpu_shaders.solver import GPUFluidDiffusionSolver as make
        if st.result is not None:
            backend.free_solver(st.result.diffusion)  # the last frame's textures: a new graph every frame
        return FluidSolver(frame.material, frame.radius, frame.mm, options, make_solver=make).solve(
            frame.particles.points, ids=frame.particles.ids, field_values=frame.field, lights=list(frame.lights),
            environment=frame.environment, surface=None if frame.use_points else (out.positions, out.faces),
            view_dirs=view_dirs, occluders=frame.occluders, shadows=True, warm_start=warm)

    def gpu_failed(reason):
        st.gpu_failed = reason
        state.log(f"'{frame.name}': {reason}")

    try:
        return backend.solve_with_cpu_retry(solve, on_gpu=lambda: st.backend == "GPU", rendering=frame.rendering,
                                            gpu_failed=gpu_failed)
    except RadiusError as ex:  # in scene units, with one suggestion: the panel's settings
        scene = bpy.context.scene
        text = ex.describe(lambda x: length_text(scene, x * frame.scale),
                           "turn on Auto Radius, or set Radius to about {spacing}")
        raise ParticleError(f"{frame.particles.source}, frame {frame.frame}: {text}") from None
    except ParticleError as ex:
        hint = ""
        if "radius" in str(ex) and frame.suggested > 0:
            hint = f" [Auto Radius gives {length_text(bpy.context.scene, frame.suggested * frame.scale)} here]"
        raise ParticleError(f"{frame.particles.source}, frame {frame.frame}: {ex}{hint}") from None


def _placement(st: state.FluidObjectState, frame: FluidInputs):
    """Where this frame's diffusion solves (:func:`.backend.placement`, as an object's): the GPU solver takes
    the cells' 15-25 links in link pages; after a failed GPU solve, the CPU with the reason."""
    where = backend.placement(frame.prefer, off_main=frame.off_main, gpu_failed=st.gpu_failed)
    st.backend, st.backend_message = where.backend, "" if where.gpu else where.reason
    if st.backend_message:
        state.log(f"'{frame.name}': {where.reason}", once_key=("fluid placement", frame.name, where.reason))
    return where


def _similar_radius(st: state.FluidObjectState, frame: FluidInputs) -> bool:
    previous = st.radius / max(frame.scale, 1e-30)
    return previous > 0 and abs(frame.radius - previous) <= 0.25 * previous


def _radiance(frame: FluidInputs, result) -> np.ndarray:
    """(n, 3) radiance at the target's points: the engine's :func:`~translucency_addon.frame.fluid_radiance`
    (the solve's, the planner's channels only; 0 when nothing ran), as the CLI's ``fluid`` writes it."""
    from ..translucency_addon.frame import fluid_radiance

    return fluid_radiance(result, frame.plan, frame.use_points, len(frame.output.positions))


def _towards_the_view(frame: FluidInputs, result) -> np.ndarray:
    """The last solve's radiance at the mesh's vertices towards this frame's view (corrected eq. 4/7 through
    the solver's ``radiance_at``, as the solve's own output): a render after the viewport's solve of the same
    frame does not rebuild the cells."""
    solver = result.diffusion
    idx, w = solver.bake.vertex_map
    rgb = solver.radiance_at(result.solve, idx, w, solver.bake.mesh_normals,
                             scene_inputs.view_directions(frame.view, frame.output.positions))
    return np.asarray(rgb, dtype=np.float64) * frame.plan.channel_mask("multiple")


def _write(obj, frame: FluidInputs, rgb: np.ndarray) -> None:
    """The attribute on ``obj.data``, or through the carrier where modifiers generate the geometry."""
    if frame.carried:
        attributes.write_radiance_carried(obj, rgb)
        return
    attributes.write_radiance(obj, rgb)
    if not frame.off_main and attributes.carrier_modifier(obj) is not None:
        attributes.remove_carrier(obj)  # its stale values would overwrite the attribute on obj.data


def _record(st: state.FluidObjectState, frame: FluidInputs, sig, result, seconds: float) -> None:
    """What the panel and the next frame read (runtime state, never saved)."""
    if frame.empty and not st.empty:
        state.queue_info('WARNING', f"'{frame.name}': {frame.empty}; its radiance is 0")
        state.log(f"'{frame.name}': {frame.empty}; radiance 0", once_key=("fluid-empty", frame.name, frame.empty))
    st.sig, st.frame, st.empty = sig, frame.frame, frame.empty
    st.seconds = seconds
    st.particles = frame.particles.n
    st.source = frame.particles.source
    st.radius = frame.radius * frame.scale
    st.carried = frame.carried
    st.output = f"{len(frame.output.positions):,} {frame.output.kind}"
    warnings = list(frame.warnings)
    if result is None:
        st.warm, st.solver_sig, st.warm_started = None, None, False
        st.stages, st.cells, st.surface_cells, st.iterations, st.residual = {}, 0, 0, 0, 0.0
    else:
        stats = result.stats
        st.warm, st.solver_sig = result.state, _solver_sig(frame)
        st.warm_started = bool(stats.get("warm_start"))
        st.stages = dict(stats.get("seconds", {}))
        st.cells = int(stats.get("cells", 0))
        st.surface_cells = int(stats.get("surface_nodes", 0))
        st.iterations = int(stats.get("sweeps", 0))
        st.residual = float(max(stats.get("relative_residual", [0.0]) or [0.0]))
        warnings += list(result.warnings)
        if stats.get("cell_path_note"):  # the cells' numpy fallback (no numba in this Blender): why, and the fix
            warnings.append(stats["cell_path_note"])
        if stats.get("cell_kernel_first_call_s"):
            state.log(f"'{frame.name}': the fluid cells' compiled kernels were compiled, or loaded from numba's "
                      f"cache, for this session ({stats['cell_kernel_first_call_s']:.1f} s: about 3 s the first "
                      "time on a machine, 0.2 s later; later frames do not pay it)")
        st.solves += 1
        state.count("solves")
    st.warnings = tuple(warnings)
    for w in warnings:
        state.log(f"'{frame.name}': {w}", once_key=("fluid-warn", frame.name, w))


def _report(st: state.FluidObjectState, frame: FluidInputs, result, solved: bool = True) -> FluidReport:
    plan = frame.plan
    return FluidReport(name=frame.name, frame=frame.frame, seconds=st.seconds, particles=frame.particles.n,
                       output=st.output + (" (through the carrier modifier)" if frame.carried else ""),
                       solved=solved, sweeps=st.iterations, residual=st.residual, warm=st.warm_started,
                       stages=st.stages, view="CAMERA" if frame.view is not None else "NORMAL",
                       skipped="" if plan is None or plan.run else plan.reason, empty=frame.empty,
                       backend=st.backend)


def deferred_report(obj, st: state.FluidObjectState, frame: int) -> FluidReport:
    """A frame left to the throttled live check (see ``runtime.solve_scene``)."""
    st.deferred += 1
    return FluidReport(name=obj.name, frame=frame, seconds=st.seconds, particles=st.particles, output=st.output,
                       solved=False, deferred=True)
