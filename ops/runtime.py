# SPDX-License-Identifier: GPL-3.0-or-later
"""A frame's path for one object: inputs -> plan -> solve -> single scattering -> attribute -> status.

:func:`solve_object` takes one baked object through named steps:

1. :func:`.frame.gather` reads everything the frame needs from Blender once
   (scale, material, field, lights, world, views, the planner's passes and
   channels, the occluders and the mesh mapping for the passes that run)
   into a frozen :class:`~.frame.FrameInputs`;
2. :func:`_prepare_solver`: the object's diffusion solver for those inputs,
   made, re-made or told about a material change, on the backend
   :mod:`.backend` places it on;
3. :func:`_diffuse`: the multiple-scattering solve (or the last one reused
   when nothing it depends on changed), its radiance at the mesh's vertices,
   weighted by the planner's region;
4. :func:`_single_scatter`: the single-scattering term (Bernabei et al.),
   weighted by the planner's region;
5. :func:`_voxel_number_map`: for an object with inner parts, the Voxel
   Number Map's term (Mochida et al.; :func:`.inner_parts.vnm_radiance`),
   weighted by the planner's region;
6. :func:`_write`: the radiance attributes (:mod:`.attributes`);
7. :func:`_record` and :func:`.status.publish`: the runtime state the panel
   reads, and a redraw.

An object with inner parts (:mod:`.inner_parts`) solves the same way: its
solver gets the per-node media of the parts (read every frame, so a part's
material change needs no re-bake), its diffusion runs through
``cavity.solve_with_cavities`` when the bake has a cavity exchange, and every
pass writes only the outer mesh's vertices (the bake's ``mesh_vertices``
continue with the cavity walls).

:func:`solve_scene` does this for every enabled, baked object of a scene
(what ``live`` and ``handlers`` call), and for every enabled Fluid-source
object it runs :func:`.fluid_runtime.solve_fluid` (particles rebuilt into
cells every frame, nothing baked); :func:`solve_object` hands a fluid object
there too.  Nothing here calls back up into ``live``, ``handlers``, the
operators or the panels.

State lives in :mod:`.state`, keyed by **object name**, and is only used
while its ``key`` equals ``obj.translucency.bake_key``.  No ``bpy`` reference
is kept, so undo (which replaces every ID) never leaves a dangling pointer: a
state whose key no longer matches is dropped and the bake is re-loaded from
the cache file on first use.  The solver is told only what changed: a
material or field edit re-samples the coefficients (``set_material``, no
re-bake); light, world or occluder edits re-solve, warm-started from the last
result; a view change (render camera) only re-evaluates the radiance.

Single scattering (baked into the same cache) is evaluated after the
diffusion: toward the render camera in renders (and with Solve's "Towards
Camera"), toward the first 3D viewport's eye in live solves when there is
one, and along each vertex normal otherwise.  View rays are cached per view,
so a change of the lights only costs the light term and the ray pass.  A
change of the material, its field, the scale or the single-scattering
settings since the bake makes the baked optical depth stale: the term keeps
using the old bake, and the panel, the log and the Solve operator say that
single scattering needs a re-bake ("Bake Single Scattering").
"""

from __future__ import annotations

import threading
import time
import traceback
from dataclasses import dataclass

import bpy
import numpy as np

from . import attributes, backend, cache_files, deformation, fluid_runtime, inner_parts, state, status
from .frame import FrameInputs, gather


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
    deformed: str = ""  # a deformed frame: its pose's line (worst link stretch); "" at the baked pose
    vnm_seconds: float = 0.0  # the Voxel Number Map's evaluation (0: not evaluated)
    vnm_backend: str = ""
    refining: bool = False  # a progressive frame: the solution so far was written, later steps refine it

    def describe(self) -> str:
        """One line for the Info log and the status bar; a skip never reads as a solve."""
        if self.skipped:
            return f"'{self.name}' skipped, nothing computed: {self.skipped}"
        parts = []
        if self.ms_ran and self.refining:
            parts.append(f"refining on the {self.backend}: the solve so far after {self.seconds:.3f} s, "
                         "later redraws refine it")
        elif self.ms_ran:
            parts.append(f"solved on the {self.backend} in {self.seconds:.3f} s "
                         f"({self.iterations} iterations, residual {self.residual:.2e})"
                         + ("" if self.solved else "; that solution reused, nothing it depends on changed"))
        if self.ss_backend:
            parts.append(f"single scattering {1000 * self.ss_seconds:.1f} ms on the {self.ss_backend}")
        if self.vnm_backend:
            parts.append(f"Voxel Number Map {1000 * self.vnm_seconds:.1f} ms on the {self.vnm_backend}")
        if not parts:
            parts.append("diffusion turned off and no other pass baked or on, so nothing was evaluated (turn "
                         "Multiple Scattering back on, or bake Single Scattering and turn it on)")
        if self.deformed:
            parts.append(self.deformed[0].lower() + self.deformed[1:])
        return f"'{self.name}' " + "; ".join(parts)


@dataclass
class Diffusion:
    """What :func:`_diffuse` produced this frame."""

    rgb: np.ndarray  # (n_vertices, 3) radiance, weighted by the planner's region
    solver: object  # the solver that produced it (the object's, or its CPU twin)
    solved: bool  # False: the last solution was reused
    seconds: float
    result: object = None
    backend: str = ""  # where it ran when not on the object's own solver or its CPU twin (a deformed frame)
    partial: bool = False  # a progressive frame's solution so far (not converged; never recorded as the solve)


def solve_object(obj, scene=None, depsgraph=None, *, use_camera: bool = False, force: bool = False,
                 retry_load: bool = False, budget: float | None = None) -> SolveReport | None:
    """Solve ``obj`` for the current scene and write its radiance attribute.

    ``depsgraph``: where lights, world, occluders and the object's transform
    are read (default: the context's evaluated depsgraph; a render depsgraph
    during renders).  ``use_camera``: view-dependent radiance towards the
    scene camera (renders); otherwise along the normal.  Returns ``None``
    when nothing changed since the last solve and the attribute is current;
    ``force`` re-solves anyway.  ``budget`` (seconds; the viewport's live checks only): a progressive
    frame (:mod:`translucency_addon.progressive`): the diffusion runs about that long and the solution
    so far is written; the report says ``refining`` until a later call with the same inputs converges.
    Raises :class:`TranslucencyError` subclasses with user-facing messages.
    """
    scene = scene or bpy.context.scene
    if depsgraph is None:
        depsgraph = bpy.context.evaluated_depsgraph_get()
    if state.is_fluid(obj):
        return fluid_runtime.solve_fluid(obj, scene, depsgraph, use_camera=use_camera, force=force)
    if obj.mode == 'EDIT':
        return None  # attribute writes are lost when leaving edit mode; solve afterwards
    with state.lock():
        return _solve_locked(obj, scene, depsgraph, use_camera, force, retry_load, budget)


def _solve_locked(obj, scene, depsgraph, use_camera, force, retry_load, budget=None):
    st = cache_files.ensure_state(obj, retry=retry_load)
    stale = cache_files.update_staleness(obj, st, depsgraph)  # and whether the evaluated mesh is a pose of the bake
    if stale:
        _refuse_stale(obj, st, stale)
    frame = gather(obj, scene, depsgraph, st, use_camera)
    st.plan = frame.plan
    state.set_plan(obj.name, frame.plan)
    if frame.unseen:
        state.count("planner_skips")
        return None  # unseen in this render: no work at all
    deformed = st.pose is not None  # solved on the baked graph deformed to the pose (ops.deformation)
    if deformed:
        frame = deformation.at_pose(st, frame)
    st.ss_stale = frame.ss_stale
    solver = _prepare_solver(st, frame) if frame.want_ms and not deformed else None
    solve_sig, view_sig = _signatures(st, frame)
    for w in frame.warnings:
        state.log(f"'{obj.name}': {w}", once_key=("warn", obj.name, w))
    previous_sig = st.deformation.solve_sig if deformed else _previous(st, solver)[1]
    if _up_to_date(obj, st, frame, previous_sig, solve_sig, view_sig, force):
        return None
    ms = Diffusion(None, None, False, 0.0)

    def multiple():  # this object's diffusion step: its solver, last solution and GPU retry (or the pose's)
        nonlocal ms
        if deformed:
            rgb, pose_solver, solved, seconds, result = deformation.diffuse(st, frame, scene.frame_current,
                                                                            solve_sig, force)
            ms = Diffusion(rgb, pose_solver, solved, seconds, result, backend=st.frame_backend)
        else:
            ms = _diffuse(st, frame, solver, solve_sig, force, None if frame.rendering else budget)
        return ms.rgb

    # The frame is the engine's (translucency_addon.frame.render_frame), as the CLI's: which terms run, in
    # what order, weighted and summed there; this object's steps keep their state between frames.
    from ..translucency_addon.frame import render_frame

    rendered = render_frame(st.bake, frame.plan, _passes(frame), frame.mapping, multiple=multiple,
                            single=lambda: _single_scatter(st, frame),
                            rest_sources={"single": lambda: st.ss, "voxel_number_map": lambda: st.vnm},
                            voxel_number_map=lambda: inner_parts.vnm_radiance(st, frame), n=frame.n_vertices,
                            eta=float(frame.material.eta), ss_view=frame.ss_view, name=frame.name)
    terms = rendered.terms
    ms.rgb = terms.multiple
    ss_rgb = terms.single
    _write(obj, frame, terms.total, ss_rgb)
    st.deformation.solved_frame = scene.frame_current
    _record(st, frame, view_sig, ms, ss_rgb)
    if not frame.off_main:
        status.publish(st)
    return _report(st, frame, ms)


def _refuse_stale(obj, st: state.ObjectState, message: str) -> None:
    """A bake that no longer matches the object is never solved as if it were current.

    Every path comes through here (the live viewport, Solve, F12, ``blender -b``): the radiance attributes
    are removed (the overlay and the render pass show nothing rather than a stale solution), the panel's
    cache line says Stale, and :class:`CacheError` says why and what to do.  A render then applies the
    scene's Cache Missing in Render policy (``handlers``): exit 1 under ``-b``, or the frame without the pass.
    """
    from ..translucency_addon.errors import CacheError

    st.view_sig = None  # whatever the attribute held is gone: the next valid frame writes and reports
    state.set_cache_problem(obj.name, f"Stale: {message}")
    for name in (attributes.ATTRIBUTE_NAME, attributes.SS_ATTRIBUTE_NAME):
        if attributes.remove_attribute(obj, name):
            state.mark_own_write(obj.name)
    raise CacheError(f"stale bake: {message}. Nothing was solved, and the object shows no Translucency radiance "
                     "until it is re-baked (Bake in the Translucency panel) or the change is undone")


# ------------------------------------------------------------------ the steps


def _solver_sig(frame: FrameInputs) -> tuple:
    """What the object's solver is built for: the scale, the Solver setting and the tolerance."""
    return (round(frame.mm, 9), frame.prefer, frame.tolerance)


def _prepare_solver(st: state.ObjectState, frame: FrameInputs):
    """The solver this frame's diffusion runs on: the object's own (made or re-made when the scale, the
    Solver setting or the tolerance changed; told about a material or field change), or its CPU twin
    where :func:`.backend.placement` keeps the GPU out (off the main thread, after a GPU failure in
    this render)."""
    solver_sig = _solver_sig(frame)
    if st.solver is None or st.solver_sig != solver_sig:
        _free_solvers(st)
        solver, name, message = backend.make_solver(st.bake.with_scale(frame.mm), *_solver_material(st, frame),
                                                    frame.solve_options(), frame.prefer, off_main=frame.off_main)
        st.solver, st.backend, st.backend_message = solver, name, message
        st.solver_sig, st.material, st.solver_field = solver_sig, frame.material, frame.field_values
        st.part_media = frame.part_media
        st.result = st.result_solver = st.solve_sig = st.view_sig = None
        st.progressive = None  # its solution so far is another solver's
        st.announced = False
    elif (frame.material != st.material or frame.field_values is not st.solver_field
          or frame.part_media != st.part_media):
        material = _solver_material(st, frame)
        st.solver.set_material(*material)
        if st.render_solver is not None:
            st.render_solver.set_material(*material)
        st.material, st.solver_field, st.part_media = frame.material, frame.field_values, frame.part_media
    if not st.announced:
        state.log(f"'{st.name}' solves on the {st.backend}"
                  + (f" ({st.backend_message})" if st.backend_message else ""))
        st.announced = True
    if st.backend == "CPU":
        return st.solver
    where = backend.placement(frame.prefer, off_main=frame.off_main, built=True,
                              failed_in_render=st.gpu_failed_in_render if frame.rendering else "")
    if where.gpu:
        return st.solver
    state.log(f"'{st.name}': {where.reason}", once_key=("twin", st.name, where.reason))
    return _cpu_twin(st, frame)


def _solver_material(st: state.ObjectState, frame: FrameInputs) -> tuple:
    """``(material, field_values)`` the diffusion solver takes: the frame's, or, for an object with inner
    parts, the per-node media of the parts (:func:`.inner_parts.diffusion_inputs`)."""
    return inner_parts.diffusion_inputs(st.bake, frame.material, frame.field_values, frame.part_media)


def _free_solvers(st: state.ObjectState) -> None:
    if st.solver is not None:
        backend.free_solver(st.solver)
        st.solver = None
    if st.render_solver is not None:
        backend.free_solver(st.render_solver)
        st.render_solver = st.render_result = st.render_solve_sig = None


def _cpu_twin(st: state.ObjectState, frame: FrameInputs):
    """The CPU solver used where the GPU one cannot run (render thread, no GPU context)."""
    if st.render_solver is None:
        st.render_solver = backend.cpu_solver(st.bake.with_scale(frame.mm), *_solver_material(st, frame),
                                              frame.solve_options())
        st.render_result = st.render_solve_sig = None
    return st.render_solver


def _signatures(st: state.ObjectState, frame: FrameInputs) -> tuple:
    """``(solve_sig, view_sig)``: what the diffusion solution and the written attribute depend on."""
    solve_sig = None
    if frame.use_ms:
        # Only the lights that reach the object enter it: moving a light re-solves only the objects
        # it lights (planner.light_reaching: range, spot cone, area facing).
        reaching = set(frame.plan.facts.get("lights_reaching", ()))
        lights_sig = tuple(light for light in frame.lights if light.name in reaching)
        solve_sig = (_solver_sig(frame), frame.material, frame.field_sig, frame.part_media,
                     lights_sig, frame.env_sig, frame.occ_sig, frame.ms_channels, frame.single_channels,
                     st.geometry_digest if st.pose is not None else None)  # a pose: its positions
    ss_sig = (frame.want_ss, frame.use_ss, frame.split)
    if frame.use_ss:
        ss_sig += (st.bake.key, frame.ss_order, frame.prefer, float(frame.material.eta), round(frame.mm, 9),
                   frame.lights, frame.env_sig, frame.ss_view)
    vnm_sig = None
    if frame.use_vnm:
        vnm_sig = (st.bake.key, frame.material, frame.part_media, frame.prefer, round(frame.mm, 9), frame.lights,
                   frame.env_sig, frame.occ_sig, frame.view)
    plan = frame.plan
    view_sig = (solve_sig, frame.view, frame.n_vertices, frame.use_ms, ss_sig, vnm_sig, plan.run,
                plan.single.channels if plan.single is not None else None,
                plan.voxel_number_map.channels if plan.voxel_number_map is not None else None)
    return solve_sig, view_sig


def _previous(st: state.ObjectState, solver) -> tuple:
    """(last result, its signature) of ``solver`` (the object's own or its CPU twin)."""
    if solver is st.render_solver:
        return st.render_result, st.render_solve_sig
    return (st.result, st.solve_sig) if st.result_solver is solver else (None, None)


def _up_to_date(obj, st, frame: FrameInputs, previous_sig, solve_sig, view_sig, force: bool) -> bool:
    """Nothing this frame depends on changed and the attributes hold the last frame's values.

    ``previous_sig``: what the last diffusion solution this frame would reuse was solved for (None: none).
    """
    if force or view_sig != st.view_sig or not attributes.attribute_ok(obj):
        return False
    if frame.use_ss and frame.split and not attributes.attribute_ok(obj, attributes.SS_ATTRIBUTE_NAME):
        return False
    if not frame.use_ms:
        return True
    return previous_sig is not None and solve_sig == previous_sig


def _diffuse(st: state.ObjectState, frame: FrameInputs, solver, solve_sig, force: bool,
             budget: float | None = None) -> Diffusion:
    """Multiple scattering at ``obj.data``'s vertices: solved, or the last solution reused when its inputs
    are this frame's; a GPU solve that raises is redone on the CPU (:func:`.backend.after_gpu_failure`).
    ``budget``: a progressive frame's time slice (:func:`_solve`); its solution so far is ``partial``."""
    from ..translucency_addon.errors import TranslucencyError

    partial = False
    for attempt in (0, 1):
        previous, previous_sig = _previous(st, solver)
        solved, seconds = False, 0.0
        try:
            if not force and previous is not None and solve_sig == previous_sig:
                result = previous
            else:
                t0 = time.perf_counter()
                result, partial, job_seconds = _solve(st, solver, frame, previous, solve_sig, budget)
                seconds = time.perf_counter() - t0 if job_seconds is None else job_seconds
                solved = not partial
            rgb = radiance_for_mesh(st, solver, result, frame)
            break
        except TranslucencyError:
            raise
        except Exception as ex:  # noqa: BLE001 - a GPU failure (e.g. no GPU context during a render)
            where = backend.after_gpu_failure(ex, rendering=frame.rendering,
                                              on_gpu=solver is st.solver and st.backend != "CPU")
            if attempt or where is None:
                raise
            solver = _retry_on_the_cpu(st, frame, where)
    if solved:
        if solver is st.render_solver:
            st.render_result, st.render_solve_sig = result, solve_sig
        else:
            st.result, st.result_solver, st.solve_sig = result, solver, solve_sig
    return Diffusion(rgb, solver, solved, seconds, result, partial=partial)


def _retry_on_the_cpu(st: state.ObjectState, frame: FrameInputs, where):
    """The CPU solver to retry on after the GPU solver raised, as :func:`.backend.after_gpu_failure` placed it."""
    state.log(f"'{st.name}': {where.reason}")
    if frame.rendering:
        st.gpu_failed_in_render = where.reason
        return _cpu_twin(st, frame)
    backend.free_solver(st.solver)
    st.solver = backend.cpu_solver(st.bake.with_scale(frame.mm), *_solver_material(st, frame),
                                   frame.solve_options())
    st.backend, st.backend_message = "CPU", where.reason
    st.result = st.result_solver = None
    return st.solver


def _passes(frame: FrameInputs):
    from ..translucency_addon.frame import FramePasses

    return FramePasses(frame.use_ms, frame.use_ss, frame.use_vnm, frame.ms_channels, frame.single_channels)


def _solve(st: state.ObjectState, solver, frame: FrameInputs, previous, solve_sig=None, budget=None) -> tuple:
    """One multiple-scattering solve of the frame: the engine's :func:`~translucency_addon.frame.diffuse`
    (the split, the interreflection bounce, the cavity exchange), warm-started from ``previous``;
    ``(result, partial, seconds)``, ``seconds`` None for a blocking solve (the caller times it) and a
    progressive one's time in all its slices so far.

    With a ``budget`` (seconds) it is a progressive frame's slice: the object's
    :class:`~translucency_addon.progressive.ProgressiveSolve` for these inputs goes on (or starts, from the
    solution so far of one for other inputs, else ``previous``) and the solution so far comes back with
    ``partial`` True until it converges; the converged result is the blocking solve's.
    """
    from ..translucency_addon.frame import diffuse, diffuse_steps

    kw = {"tol": frame.tolerance, "occluders": frame.occluders, "shadows": True}
    if budget is None:
        st.progressive = None
        result, bounce, _cavity = diffuse(solver, st.bake, frame.lights, frame.environment, _passes(frame),
                                          warm_start=previous, **kw)
        partial, seconds = False, None
    else:
        from ..translucency_addon.progressive import ProgressiveSolve

        key = (solve_sig, id(solver))
        job = st.progressive
        if job is None or not job.continues(key):
            mid_solve = job is not None and job.latest is not None and job.key[1] == id(solver)
            start = job.latest if mid_solve else previous
            # from a converged frame the first image is the start itself (it comes within the light pass's
            # time); from an unfinished one (a drag) every slice sweeps, so the drag's redraws refine it
            job = ProgressiveSolve(diffuse_steps(solver, st.bake, frame.lights, frame.environment, _passes(frame),
                                                 warm_start=start, **kw), key, show_start=not mid_solve)
        out, done = job.advance(budget)
        st.progressive = None if done else job
        if not done:
            return out, True, job.seconds
        result, bounce, _cavity = out
        partial, seconds = False, job.seconds
    if bounce is not None:
        st.bounce = bounce
    return result, partial, seconds


def radiance_for_mesh(st: state.ObjectState, solver, result, frame: FrameInputs) -> np.ndarray:
    """(n_vertices, 3) outgoing radiance for the original mesh's vertices (the engine's
    :func:`~translucency_addon.frame.multiple_radiance`)."""
    from ..translucency_addon.frame import multiple_radiance

    return multiple_radiance(solver, result, st.bake, frame.mapping, frame.view)


def _single_scatter(st: state.ObjectState, frame: FrameInputs) -> np.ndarray:
    """The single-scattering radiance at ``obj.data``'s vertices, (n, 3) (weighted by the planner's region in
    ``compose``); the evaluator is kept in ``st`` per bake, SH order, Solver setting and vertex set."""
    bake = st.bake
    data = bake.single_scattering
    m = frame.mapping
    key = (bake.key, frame.ss_order, (frame.prefer or "AUTO").upper(), None if m.same else m.digest)
    if st.ss is None or st.ss_key != key:
        if st.ss is not None:
            st.ss.free()
            st.ss = None
        data_o = data if frame.ss_order == data.order else data.with_order(frame.ss_order)
        integrator, name, message = backend.make_integrator(data_o, frame.prefer, off_main=frame.off_main)
        from ..translucency_addon.frame import single_evaluator

        ev = single_evaluator(bake, frame.ss_order, m, integrator=integrator)
        st.ss, st.ss_key, st.ss_backend_message = ev, key, message
        state.log(f"'{frame.name}': single scattering on the {name}" + (f" ({message})" if message else ""),
                  once_key=("ss-backend", frame.name, name, message))
    t0 = time.perf_counter()
    rgb = st.ss.radiance(list(frame.lights), frame.environment, float(frame.material.eta), frame.mm, frame.ss_view,
                         use_gpu=not frame.off_main)
    st.ss_seconds = time.perf_counter() - t0
    st.ss_backend = st.ss.backend
    msg = getattr(st.ss.integrator, "message", "")
    if msg:
        st.ss_backend_message = msg
    st.ss_rgb = rgb
    return rgb  # weighted by the planner's channels and region in compose


def _write(obj, frame: FrameInputs, rgb: np.ndarray, ss_rgb: np.ndarray | None) -> None:
    """The radiance attributes: the total, and single scattering alone with Split Pass."""
    attributes.write_radiance(obj, rgb)
    if ss_rgb is not None and frame.split:
        attributes.write_radiance(obj, ss_rgb, attributes.SS_ATTRIBUTE_NAME)
    elif not frame.off_main and obj.data.attributes.get(attributes.SS_ATTRIBUTE_NAME) is not None:
        attributes.remove_attribute(obj, attributes.SS_ATTRIBUTE_NAME)  # no stale single-scattering pass


def _record(st: state.ObjectState, frame: FrameInputs, view_sig, ms: Diffusion, ss_rgb) -> None:
    """What the panel and the next frame read: the runtime state (never saved) and the counters.  A
    progressive frame's solution so far leaves the view unrecorded, so the next check goes on with it."""
    st.view_sig = None if ms.partial else view_sig
    st.warnings = frame.warnings
    if ss_rgb is None:
        st.ss_seconds, st.ss_rgb = 0.0, None
    if not frame.use_vnm:
        st.vnm_seconds, st.vnm_backend = 0.0, ""
    if ms.partial:
        state.count("progressive_steps")
    elif ms.solved:
        st.solves += 1
        state.count("solves")
        st.seconds = ms.seconds
        st.residual = float(np.max(np.asarray(ms.result.residual)))
        st.iterations = int(ms.result.iterations)
    else:
        state.count("radiance_only")


def _report(st: state.ObjectState, frame: FrameInputs, ms: Diffusion) -> SolveReport:
    if frame.use_ms:
        report_backend = ms.backend or ("CPU" if ms.solver is st.render_solver else st.backend)
    else:
        report_backend = st.ss_backend if frame.use_ss else st.vnm_backend if frame.use_vnm else ""
    seconds = (ms.seconds if ms.partial else st.seconds) if frame.use_ms else 0.0
    return SolveReport(name=frame.name, backend=report_backend, seconds=seconds,
                       residual=st.residual if frame.use_ms else 0.0,
                       iterations=st.iterations if frame.use_ms else 0, solved=ms.solved,
                       view="CAMERA" if frame.view is not None else "NORMAL", vertices=frame.n_vertices,
                       ss_seconds=st.ss_seconds if frame.use_ss else 0.0,
                       ss_backend=st.ss_backend if frame.use_ss else "",
                       skipped="" if frame.plan.run else frame.plan.reason, ms_ran=frame.use_ms,
                       deformed=st.deformation.describe() if st.pose is not None else "",
                       vnm_seconds=st.vnm_seconds if frame.use_vnm else 0.0,
                       vnm_backend=st.vnm_backend if frame.use_vnm else "", refining=ms.partial)


# ------------------------------------------------------------------ every object of a scene


def solve_scene(scene=None, depsgraph=None, *, use_camera: bool = False, force: bool = False,
                playback: bool = False, failed: list | None = None, budget: float | None = None) -> list:
    """Solve every enabled, baked object and every enabled fluid of ``scene``; errors are logged, never raised.

    ``playback``: the viewport is playing the animation; a fluid whose last frame took longer than
    :data:`.status.FLUID_LIVE_BUDGET` is not solved now but reported ``deferred`` (the caller leaves it to
    the throttled live check, so playback does not wait for it).  Returns the :class:`SolveReport` (or
    :class:`.fluid_runtime.FluidReport`) of every object that was (re-)solved or deferred.
    ``failed``: a list that receives ``(object name, message, cache problem?)`` for every object whose
    solve raised (a cache problem: :class:`CacheError`, missing, stale, unreadable, another version's),
    for the render's policy (``handlers``).  ``budget``: the viewport's progressive frames
    (:func:`solve_object`); ``None`` (renders, frame changes, scripts) solves to convergence.
    """
    from ..translucency_addon.errors import CacheError, TranslucencyError

    scene = scene or bpy.context.scene
    if depsgraph is None:
        depsgraph = bpy.context.evaluated_depsgraph_get()
    reports = []
    for obj in state.baked_objects(scene) + state.fluid_objects(scene):
        fluid = state.fluid_state_of(obj.name) if state.is_fluid(obj) else None
        if playback and fluid is not None and fluid.seconds > status.FLUID_LIVE_BUDGET:
            reports.append(fluid_runtime.deferred_report(obj, fluid, scene.frame_current))
            continue
        try:
            report = solve_object(obj, scene, depsgraph, use_camera=use_camera, force=force, budget=budget)
        except TranslucencyError as ex:
            _report_error(obj, str(ex))
            if failed is not None:
                failed.append((obj.name, str(ex), isinstance(ex, CacheError)))
            continue
        except Exception as ex:  # noqa: BLE001 - a handler must never raise into Blender
            _report_error(obj, f"{type(ex).__name__}: {ex}", tb=traceback.format_exc())
            if failed is not None:
                failed.append((obj.name, f"{type(ex).__name__}: {ex}", False))
            continue
        if report is not None:
            reports.append(report)
    return reports


def _report_error(obj, message: str, tb: str | None = None) -> None:
    state.log(f"'{obj.name}': {message}", once_key=("error", obj.name, message))
    if tb:
        state.log(tb, once_key=("tb", obj.name, message))
    if threading.current_thread() is threading.main_thread():
        status.report_error(obj.name, message)
