# SPDX-License-Identifier: GPL-3.0-or-later
"""A frame's path for one object: scene inputs -> plan -> solve -> single scattering -> attribute -> panel.

The modules around it, each called from here and never calling back:
``scene_inputs`` (Blender lights, world, occluders, fields -> engine inputs),
``state`` (per-object :class:`ObjectState`, counters, log), ``cache_files``
(bake caches next to the .blend, loading, staleness), ``attributes`` (the
radiance attributes), ``backend`` (the GPU/CPU solver), and the engine's
planner and solvers.  Their public names are re-exported here.

Public API (also used by the overlay and render-pass code):

* :data:`ATTRIBUTE_NAME` = ``"translucency_radiance"``: a ``FLOAT_COLOR``
  attribute on the ``POINT`` domain of the object's **original** mesh
  (``obj.data``), RGB = outgoing radiance in W/(m^2 sr), alpha = 1.  Modifiers
  propagate it to the evaluated mesh, so ``obj.evaluated_get(dg).data`` has it
  too.
* :func:`solve_object(obj, ...) <solve_object>`: solve one object now (loads
  its cache if needed) and write the attribute; returns a :class:`SolveReport`
  or ``None`` when nothing changed since the last solve.
* :func:`solve_scene(scene, ...) <solve_scene>`: the same for every enabled,
  baked object of a scene (what the handlers call).
* :data:`SS_ATTRIBUTE_NAME` = ``"translucency_radiance_ss"``: the
  single-scattering term alone, written when the object's "Split Pass" is on
  (``render_pass`` turns it into the ``Translucency_SS`` AOV).
  :data:`ATTRIBUTE_NAME` holds the total: diffusion (when "Multiple
  Scattering" is on) plus single scattering (when "Single Scattering" is on
  and baked).
* :func:`request_update` (in ``handlers``) schedules a throttled re-solve.
* :func:`is_baked`, :func:`get_state`, :func:`clear`, :func:`drop_state`.

State lives in :data:`_STATES`, keyed by **object name**, and is only used
while its ``key`` equals ``obj.translucency.bake_key``.  No ``bpy`` reference
is kept, so undo (which replaces every ID) never leaves a dangling pointer: a
state whose key no longer matches is dropped and the bake is re-loaded from
the cache file on first use.  The solver is told only what changed: a
material or field edit re-samples the coefficients (``set_material``, no
re-bake); light, world or occluder edits re-solve, warm-started from the last
result; a view change (render camera) only re-evaluates the radiance.

Single scattering (Bernabei et al., baked into the same cache) is evaluated
after the diffusion: toward the render camera in renders (and with Solve's
"Towards Camera"), toward the first 3D viewport's eye in live solves when
there is one, and along each vertex normal otherwise.  Its ray pass runs on
the GPU kernel when ``gpu_shaders.single_scattering`` can (the scene's
Solver setting; numpy on software rasterisers and off the main thread) and
falls back to numpy per call.  View rays are cached per view, so a change of
the lights only costs the light term and the ray pass.  A change of the
material, its field, the scale or the single-scattering settings since the
bake makes the baked optical depth stale: the term keeps using the old bake,
and the panel, the log and the Solve operator say that single scattering
needs a re-bake ("Bake Single Scattering").
"""

from __future__ import annotations

import threading
import time
import traceback
from dataclasses import dataclass

import bpy
import numpy as np

from . import backend, scene_inputs
from .attributes import (ATTRIBUTE_DOMAIN, ATTRIBUTE_NAME, ATTRIBUTE_TYPE, SS_ATTRIBUTE_NAME,  # noqa: F401
                         attribute_ok, read_radiance, remove_attribute, write_radiance)
from .cache_files import (DEFAULT_CACHE_DIRECTORY, cache_directory, cache_file_name, check_cache,  # noqa: F401
                          ensure_state, resolve_cache_path, stored_cache_path, update_staleness)
from .state import (_FAILED, _LOCK, _LOGGED, _STATES, CACHE_STATUS, COUNTERS, FRAME_EPOCH,  # noqa: F401
                    GEOMETRY_EPOCH, OWN_WRITES, PLANS, ObjectState, baked_objects, clear, drop_state, get_state,
                    install_state, invalidate_views, is_baked, log, prune)


@dataclass
class SolveReport:
    name: str
    backend: str
    seconds: float
    residual: float
    iterations: int
    solved: bool  # False: only the view changed (radiance re-evaluated, no solve)
    view: str  # "NORMAL" or "CAMERA"
    vertices: int
    ss_seconds: float = 0.0  # single-scattering evaluation (0: not evaluated)
    ss_backend: str = ""
    skipped: str = ""  # why no pass ran (the planner's reason, with its numbers); "" when one ran
    ms_ran: bool = True  # the diffusion pass ran (False: single scattering only, or skipped)

    def describe(self) -> str:
        """One line for the Info log and the status bar; a skip never reads as a solve."""
        if self.skipped:
            return f"'{self.name}' skipped, nothing computed: {self.skipped}"
        parts = []
        if self.ms_ran:
            parts.append(f"solved on the {self.backend} in {self.seconds:.3f} s "
                         f"({self.iterations} iterations, residual {self.residual:.2e})"
                         + ("" if self.solved else "; that solution reused, nothing it depends on changed"))
        if self.ss_backend:
            parts.append(f"single scattering {1000 * self.ss_seconds:.1f} ms on the {self.ss_backend}")
        if not parts:
            parts.append("diffusion turned off; nothing else to evaluate")
        return f"'{self.name}' " + "; ".join(parts)


# ------------------------------------------------------------------ solving


def _original_normals(mesh, V) -> np.ndarray:
    normals = getattr(mesh, "vertex_normals", None)
    if normals is not None and len(normals) == len(V):
        arr = np.empty(len(V) * 3, dtype=np.float32)
        normals.foreach_get("vector", arr)
        return arr.reshape(-1, 3).astype(np.float64)
    _, F = scene_inputs.mesh_arrays(mesh)
    return scene_inputs.mesh_normals(V, F)


def _original_mapping(obj, st: ObjectState):
    """Mapping from the finest surface nodes to ``obj.data``'s vertices (when its
    vertex count differs from the baked, evaluated mesh's)."""
    from ..translucency_addon.bake import vertex_mapping

    mesh = obj.data
    V = scene_inputs.vertex_positions(mesh)
    digest = scene_inputs.array_digest(V)
    if st.orig_map is None or st.orig_map[0] != digest:
        N = _original_normals(mesh, V)
        idx, w = vertex_mapping(V, N, st.bake.finest, st.bake.settings.vertex_map_k)
        st.orig_map = (digest, idx, w, V, N)
    return st.orig_map


def _solve(st: ObjectState, solver, lights, environment, previous, occluders, channels):
    """One multiple-scattering solve, with the interreflection bounce when the bake has sky visibility.

    The bounce comes from a first solve of the same frame (``DiffusionSolver.
    solve_interreflected``; the second solve is warm-started from the first),
    never from an earlier frame, so a frame's result depends only on that
    frame's inputs (renders of single frames and of animations agree).
    """
    if solver.sky is None:
        return solver.solve(lights, environment, warm_start=previous, shadows=True, occluders=occluders,
                            channels=channels)
    result, st.bounce = solver.solve_interreflected(lights, environment, warm_start=previous, shadows=True,
                                                    occluders=occluders, channels=channels)
    return result


def _vertex_map(obj, st: ObjectState):
    """(idx, w): the finest surface nodes that carry values to ``obj.data``'s vertices."""
    if len(obj.data.vertices) == len(st.bake.mesh_vertices):
        return st.bake.vertex_map
    _, idx, w, _V, _N = _original_mapping(obj, st)
    return idx, w


def radiance_for_mesh(obj, st: ObjectState, solver, result, view) -> np.ndarray:
    """(len(obj.data.vertices), 3) outgoing radiance for the original mesh's vertices.

    The baked (evaluated) mesh's own vertex map, or one to ``obj.data``'s vertices when a modifier
    changed the vertex count; either way the solver's ``radiance_at`` (corrected eq. 4/7).
    """
    bake = st.bake
    n_orig = len(obj.data.vertices)
    if n_orig == len(bake.mesh_vertices):
        dirs = scene_inputs.view_directions(view, np.asarray(bake.mesh_vertices))
        return np.asarray(solver.vertex_radiance(result, dirs))
    _, idx, w, V, N = _original_mapping(obj, st)
    return np.asarray(solver.radiance_at(result, idx, w, N, scene_inputs.view_directions(view, V)))


def _cpu_twin(st: ObjectState, mm: float, material, scene):
    """The CPU solver used where the GPU one cannot run (render thread, no GPU context)."""
    if st.render_solver is None:
        st.render_solver = backend.cpu_solver(st.bake.with_scale(mm), material, st.field_values, _options(scene))
        st.render_result = st.render_solve_sig = None
    return st.render_solver


def _options(scene):
    from ..translucency_addon.diffusion import SolveOptions

    return SolveOptions(solver="fast", tol=float(scene.translucency.tolerance))


def _set_if_changed(owner, attr: str, value) -> None:
    try:
        current = getattr(owner, attr)
    except AttributeError:
        return
    if isinstance(value, float):
        if abs(current - value) <= 1e-12 * max(1.0, abs(value)):
            return
    elif current == value:
        return
    setattr(owner, attr, value)


def solve_object(obj, scene=None, depsgraph=None, *, use_camera: bool = False, force: bool = False,
                 retry_load: bool = False) -> SolveReport | None:
    """Solve ``obj`` for the current scene and write :data:`ATTRIBUTE_NAME`.

    ``depsgraph``: where lights, world, occluders and the object's transform
    are read (default: the context's evaluated depsgraph; a render depsgraph
    during renders).  ``use_camera``: view-dependent radiance towards the
    scene camera (renders); otherwise along the normal.  Returns ``None``
    when nothing changed since the last solve and the attribute is current;
    ``force`` re-solves anyway.  Raises :class:`TranslucencyError` subclasses
    with user-facing messages.
    """
    scene = scene or bpy.context.scene
    if depsgraph is None:
        depsgraph = bpy.context.evaluated_depsgraph_get()
    if obj.mode == 'EDIT':
        return None  # attribute writes are lost when leaving edit mode; solve afterwards
    with _LOCK:
        return _solve_locked(obj, scene, depsgraph, use_camera, force, retry_load)


def _solve_locked(obj, scene, depsgraph, use_camera, force, retry_load):
    from ..translucency_addon.errors import TranslucencyError

    settings = obj.translucency
    st = ensure_state(obj, retry=retry_load)
    obj_eval = obj.evaluated_get(depsgraph)
    matrix = obj_eval.matrix_world.copy()
    mm, scale_warning = scene_inputs.mm_per_unit(obj, scene, matrix)
    metres_per_bu = scene_inputs.metres_per_world_unit(obj, scene, mm, matrix)
    update_staleness(obj, st, depsgraph)

    want_ss = bool(settings.use_single_scattering)
    split = bool(settings.ss_split_pass)

    material = scene_inputs.build_material(settings)
    epoch = (GEOMETRY_EPOCH.get(obj.name, 0), GEOMETRY_EPOCH.get(FRAME_EPOCH, 0))
    field_sig = scene_inputs.field_signature(obj, settings, depsgraph, epoch)
    field_changed = field_sig != st.field_sig or (field_sig is not None and st.field_values is None)
    use_ms = bool(settings.use_multiple_scattering)  # refined by the planner below
    if field_changed and use_ms:
        if field_sig is None:
            st.field_values = None
        else:
            st.field_values = scene_inputs.sample_field(
                obj, settings, [lv.position for lv in st.bake.levels], depsgraph)
            COUNTERS["field_samples"] += 1

    off_main = threading.current_thread() is not threading.main_thread()
    prefer = scene.translucency.solver_backend
    solver_sig = (round(mm, 9), prefer, float(scene.translucency.tolerance))
    rendering = getattr(depsgraph, "mode", "VIEWPORT") == 'RENDER'
    solver = None
    if use_ms:
        if st.solver is None or st.solver_sig != solver_sig:
            if st.solver is not None:
                backend.free_solver(st.solver)
                st.solver = None
            if st.render_solver is not None:
                backend.free_solver(st.render_solver)
                st.render_solver = st.render_result = st.render_solve_sig = None
            bake = st.bake.with_scale(mm)
            solver, name, message = backend.make_solver(bake, material, st.field_values, _options(scene),
                                                        prefer="CPU" if off_main else prefer)
            st.solver, st.backend, st.backend_message = solver, name, message
            st.solver_sig, st.material, st.result, st.result_solver = solver_sig, material, None, None
            st.solve_sig = st.view_sig = None
            st.announced = False
        elif material != st.material or field_changed:
            st.solver.set_material(material, st.field_values)
            if st.render_solver is not None:
                st.render_solver.set_material(material, st.field_values)
            st.material = material
        st.field_sig = field_sig
        if not st.announced:
            log(f"'{obj.name}' solves on the {st.backend}"
                + (f" ({st.backend_message})" if st.backend_message else ""))
            st.announced = True
        solver = st.solver
        if st.backend != "CPU" and (off_main or (rendering and st.gpu_failed_in_render)):
            solver = _cpu_twin(st, mm, material, scene)

    lights = scene_inputs.collect_lights(depsgraph, matrix, metres_per_bu)
    environment, world_warning = scene_inputs.world_environment(scene.world)
    env_sig = None if environment is None else tuple(environment.radiance)

    # The planner: which passes and channels this object needs this frame, and why.
    plan = make_plan(obj, st, settings, material, lights, environment, mm, scene, depsgraph, use_camera)
    st.plan = plan
    PLANS[obj.name] = plan
    if not plan.run and plan.reason.startswith("outside the camera view"):
        COUNTERS["planner_skips"] += 1
        return None  # unseen in this render: no work at all
    use_ms = use_ms and plan.run and plan.multiple.runs
    use_ss = plan.run and plan.single.runs and st.bake.single_scattering is not None
    ms_channels = plan.multiple.channels if plan.multiple is not None else (False, False, False)
    # Only the lights that reach the object enter its signature: moving a light re-solves
    # only the objects it lights (planner.light_reaching: range, spot cone, area facing).
    reaching = set(plan.facts.get("lights_reaching", ()))
    lights_sig = tuple(light for light in lights if light.name in reaching)
    if use_ms:
        occluders, occ_sig = scene_inputs.collect_occluders(depsgraph, obj, matrix, st.occluders)
        solve_sig = (solver_sig, material, field_sig, lights_sig, env_sig, occ_sig, ms_channels)
    else:
        occluders, solve_sig = None, None
    view = scene_inputs.camera_view(scene, depsgraph, matrix) if use_camera else None

    # single scattering: its view, staleness and signature
    ss_view = None
    ss_sig = (want_ss, use_ss, split)
    st.ss_stale = ""
    if use_ss:
        ss_view = view
        if ss_view is None and not use_camera and not rendering and not off_main:
            ss_view = scene_inputs.viewport_view(matrix)
        st.ss_stale = _ss_staleness(obj, st, settings, depsgraph, material, field_sig, mm)
        ss_sig += (st.bake.key, min(int(settings.ss_sh_order), st.bake.single_scattering.order), prefer,
                   float(material.eta), round(mm, 9), tuple(lights), env_sig, ss_view)
    elif want_ss:
        st.ss_stale = ("Single Scattering is on but was not baked: press Bake Single Scattering "
                       "(or Bake, which bakes both)")
    view_sig = (solve_sig, view, len(obj.data.vertices), use_ms, ss_sig, plan.run, plan.single.channels
                if plan.single is not None else None)
    warnings = tuple(w for w in (scale_warning, world_warning, st.stale_message, st.ss_stale) if w)
    for w in warnings:
        log(f"'{obj.name}': {w}", once_key=("warn", obj.name, w))

    def current() -> bool:
        return (not force and view_sig == st.view_sig and attribute_ok(obj)
                and (not (use_ss and split) or attribute_ok(obj, SS_ATTRIBUTE_NAME)))

    def previous_for(s):
        """(last result, its signature) of solver ``s`` (the GPU/main one or the CPU twin)."""
        if s is st.render_solver:
            return st.render_result, st.render_solve_sig
        return (st.result, st.solve_sig) if st.result_solver is s else (None, None)

    solved = False
    seconds = 0.0
    n_vertices = len(obj.data.vertices)
    result = None
    if use_ms:
        for attempt in (0, 1):
            previous, previous_sig = previous_for(solver)
            try:
                if not force and previous is not None and solve_sig == previous_sig:
                    if current():
                        return None
                    result = previous
                else:
                    t0 = time.perf_counter()
                    result = _solve(st, solver, lights, environment, previous, occluders, ms_channels)
                    seconds = time.perf_counter() - t0
                    solved = True
                rgb = radiance_for_mesh(obj, st, solver, result, view)
                break
            except TranslucencyError:
                raise
            except Exception as ex:  # noqa: BLE001 - a GPU failure (e.g. no GPU context during a render)
                if attempt or solver is not st.solver or st.backend == "CPU":
                    raise
                message = f"the GPU solve failed ({type(ex).__name__}: {ex}); using the CPU solver"
                log(f"'{obj.name}': {message}" + (" for renders" if rendering else ""))
                if rendering:
                    st.gpu_failed_in_render = True
                else:
                    backend.free_solver(st.solver)
                    st.solver = backend.cpu_solver(st.bake.with_scale(mm), material, st.field_values, _options(scene))
                    st.backend, st.backend_message = "CPU", message
                    st.result = st.result_solver = None
                solver = _cpu_twin(st, mm, material, scene) if rendering else st.solver
                solved = False
        if solved:
            if solver is st.render_solver:
                st.render_result, st.render_solve_sig = result, solve_sig
            else:
                st.result, st.result_solver, st.solve_sig = result, solver, solve_sig
    else:
        if current():
            return None
        rgb = np.zeros((n_vertices, 3))
    rgb = np.asarray(rgb, dtype=np.float64)
    if use_ms and plan.multiple.weights is not None:  # diffusion only where the planner keeps it
        rgb = rgb * plan.vertex_weights("multiple", *_vertex_map(obj, st))
    if not np.all(np.isfinite(rgb)):
        raise TranslucencyError(f"'{obj.name}': the solve produced NaN or Inf radiance; check the material")

    ss_rgb = None
    if use_ss:
        ss_rgb = _single_scattering(obj, st, material, lights, environment, mm, ss_view, prefer, off_main)
        if not np.all(np.isfinite(ss_rgb)):
            raise TranslucencyError(f"'{obj.name}': single scattering produced NaN or Inf radiance")
        ss_rgb = ss_rgb * plan.vertex_weights("single", *_vertex_map(obj, st))  # the planner's channels and region
        rgb = rgb + ss_rgb
    else:
        st.ss_seconds, st.ss_rgb = 0.0, None
    write_radiance(obj, rgb)
    if use_ss and split:
        write_radiance(obj, ss_rgb, SS_ATTRIBUTE_NAME)
    elif not off_main and obj.data.attributes.get(SS_ATTRIBUTE_NAME) is not None:
        remove_attribute(obj, SS_ATTRIBUTE_NAME)  # no stale single-scattering pass
    st.view_sig = view_sig
    st.warnings = warnings
    if solved:
        st.solves += 1
        COUNTERS["solves"] += 1
        st.seconds = seconds
        st.residual = float(np.max(np.asarray(result.residual)))
        st.iterations = int(result.iterations)
    else:
        COUNTERS["radiance_only"] += 1
    if not off_main:
        _publish(obj, scene, st)
    if use_ms:
        report_backend = "CPU" if solver is st.render_solver else st.backend
    else:
        report_backend = st.ss_backend if use_ss else ""
    return SolveReport(name=obj.name, backend=report_backend, seconds=st.seconds if use_ms else 0.0,
                       residual=st.residual if use_ms else 0.0, iterations=st.iterations if use_ms else 0,
                       solved=solved, view="CAMERA" if view is not None else "NORMAL", vertices=len(rgb),
                       ss_seconds=st.ss_seconds if use_ss else 0.0, ss_backend=st.ss_backend if use_ss else "",
                       skipped="" if plan.run else plan.reason, ms_ran=use_ms)


# ------------------------------------------------------------------ single scattering


def make_plan(obj, st: ObjectState, settings, material, lights, environment, mm: float, scene, depsgraph,
              use_camera: bool):
    """The planner's decision for this object and frame (``translucency_addon.planner.plan_object``).

    The object's switches become overrides: a term that is off is forced off;
    with Pass Planning "All" every enabled term runs on every channel.
    """
    from ..translucency_addon.planner import plan_object

    has_ss = st.bake.single_scattering is not None
    overrides = {}
    every = getattr(settings, "pass_planning", "AUTO") == 'ALL'
    if not settings.use_multiple_scattering:
        overrides["multiple"] = False
    elif every:
        overrides["multiple"] = True
    if not (settings.use_single_scattering and has_ss):
        overrides["single"] = False
    elif every:
        overrides["single"] = True
    in_view = scene_inputs.in_camera_view(scene, depsgraph, obj) if use_camera else True
    return plan_object(st.bake.with_scale(mm), material, lights, environment, field_values=st.field_values,
                       has_single_scattering=has_ss, in_view=in_view, enabled=bool(settings.enabled),
                       overrides=overrides, name=obj.name)


def plan_summary(name: str) -> str:
    """The last plan of an object as text for the panel ('' when it has not been solved)."""
    from ..translucency_addon.planner import describe_plan

    plan = PLANS.get(name)
    return describe_plan(plan) if plan is not None else ""


def _ss_staleness(obj, st: ObjectState, settings, depsgraph, material, field_sig, mm: float) -> str:
    """Why the baked single scattering no longer matches the object ('' when it does)."""
    from ..translucency_addon.single_scattering import stale_message, staleness

    data = st.bake.single_scattering
    try:
        want = scene_inputs.ss_settings(settings)
    except Exception as ex:  # noqa: BLE001
        return str(ex)
    field_fp = None
    if material.heterogeneous:
        if st.ss_field_fp is None or st.ss_field_fp[0] != field_sig:
            st.ss_field_fp = (field_sig, scene_inputs.ss_field_fingerprint(obj, settings, depsgraph, field_sig))
        field_fp = st.ss_field_fp[1]
    reasons = staleness(data, settings=want, material=material, field_fp=field_fp, mm_per_unit=mm)
    return stale_message(reasons)


def _ss_integrator(data, prefer: str):
    """``(integrator, backend, message)``: the GPU kernel's dispatcher (with a per-call numpy fallback)
    when possible, else the numpy twin.  Never raises for GPU trouble."""
    from ..translucency_addon.single_scattering import CPUIntegrator

    prefer = (prefer or "AUTO").upper()
    if prefer == "CPU":
        return CPUIntegrator(data), "CPU", ""
    try:
        from ..gpu_shaders import single_scattering as gss
    except Exception as ex:  # noqa: BLE001 - missing or broken GPU layer
        return CPUIntegrator(data), "CPU", f"single-scattering GPU kernel not available ({type(ex).__name__}: {ex})"
    try:
        if prefer == "GPU":  # no software-rasteriser preference, still with the per-call fallback
            integ, name, message = gss.make_integrator(data, "GPU")
            return gss.AutoIntegrator(data, integ, ""), name, message
        return gss.make_integrator(data, "AUTO")
    except Exception as ex:  # noqa: BLE001
        message = f"single-scattering GPU kernel unavailable ({type(ex).__name__}: {ex}); using numpy"
        log(message, once_key=("ss-gpu", message))
        return CPUIntegrator(data), "CPU", message


def _single_scattering(obj, st: ObjectState, material, lights, environment, mm: float, view, prefer: str,
                       off_main: bool) -> np.ndarray:
    """The single-scattering radiance at ``obj.data``'s vertices, (n, 3)."""
    from ..translucency_addon.single_scattering import FrameEvaluator

    bake = st.bake
    data = bake.single_scattering
    order = min(int(obj.translucency.ss_sh_order), data.order)
    mesh = obj.data
    same = len(mesh.vertices) == len(bake.mesh_vertices)
    geo = None
    if not same:
        V = scene_inputs.vertex_positions(mesh)
        geo = scene_inputs.array_digest(V)
    key = (bake.key, order, (prefer or "AUTO").upper(), geo)
    if st.ss is None or st.ss_key != key:
        if st.ss is not None:
            st.ss.free()
            st.ss = None
        data_o = data if order == data.order else data.with_order(order)
        integrator, name, message = _ss_integrator(data_o, "CPU" if off_main else prefer)
        if same:
            ev = FrameEvaluator(data_o, bake.mesh_vertices, bake.mesh_faces, bake.mesh_normals, integrator=integrator)
        else:
            ev = FrameEvaluator(data_o, bake.mesh_vertices, bake.mesh_faces, points=V,
                                point_normals=_original_normals(mesh, V), integrator=integrator)
        st.ss, st.ss_key, st.ss_backend_message = ev, key, message
        log(f"'{obj.name}': single scattering on the {name}" + (f" ({message})" if message else ""),
            once_key=("ss-backend", obj.name, name, message))
    t0 = time.perf_counter()
    rgb = st.ss.radiance(lights, environment, float(material.eta), mm, view, use_gpu=not off_main)
    st.ss_seconds = time.perf_counter() - t0
    st.ss_backend = st.ss.backend
    msg = getattr(st.ss.integrator, "message", "")
    if msg:
        st.ss_backend_message = msg
    st.ss_rgb = rgb
    return rgb


def _publish(obj, scene, st: ObjectState) -> None:
    """Copy the solve status into the panel's properties (only values that changed)."""
    s = obj.translucency
    _set_if_changed(s, "solve_seconds", float(st.seconds))
    _set_if_changed(s, "solve_residual", float(st.residual))
    _set_if_changed(s, "solve_iterations", int(st.iterations))
    _set_if_changed(s, "solve_backend", st.backend)
    message = st.backend_message
    if st.stale_message:
        message = (message + "; " if message else "") + "stale bake: " + st.stale_message
    _set_if_changed(s, "solve_message", message)
    if st.stale_message:
        CACHE_STATUS[obj.name] = f"Stale: {st.stale_message}"
    else:
        CACHE_STATUS.pop(obj.name, None)
    _set_if_changed(s, "ss_solve_seconds", float(st.ss_seconds))
    _set_if_changed(s, "ss_backend", st.ss_backend if st.ss_rgb is not None else "")
    ss_message = st.ss_stale or (st.ss_backend_message if st.ss_rgb is not None else "")
    _set_if_changed(s, "ss_message", ss_message)
    t = scene.translucency
    _set_if_changed(t, "last_solve_time", float(st.seconds))
    _set_if_changed(t, "last_residual", float(st.residual))
    _set_if_changed(t, "last_backend", st.backend)


def solve_scene(scene=None, depsgraph=None, *, use_camera: bool = False, force: bool = False) -> list:
    """Solve every enabled, baked object of ``scene``; errors are logged, never raised.

    Returns the :class:`SolveReport` of every object that was (re-)solved.
    """
    from ..translucency_addon.errors import TranslucencyError

    scene = scene or bpy.context.scene
    if depsgraph is None:
        depsgraph = bpy.context.evaluated_depsgraph_get()
    reports = []
    for obj in baked_objects(scene):
        try:
            report = solve_object(obj, scene, depsgraph, use_camera=use_camera, force=force)
        except TranslucencyError as ex:
            _report_error(obj, str(ex))
            continue
        except Exception as ex:  # noqa: BLE001 - a handler must never raise into Blender
            _report_error(obj, f"{type(ex).__name__}: {ex}", tb=traceback.format_exc())
            continue
        if report is not None:
            reports.append(report)
    return reports


def _report_error(obj, message: str, tb: str | None = None) -> None:
    log(f"'{obj.name}': {message}", once_key=("error", obj.name, message))
    if tb:
        log(tb, once_key=("tb", obj.name, message))
    if threading.current_thread() is threading.main_thread():
        try:
            _set_if_changed(obj.translucency, "solve_message", message)
        except Exception:  # noqa: BLE001 - read-only context (e.g. during drawing)
            pass
