# SPDX-License-Identifier: GPL-3.0-or-later
"""Deformed frames: a baked object posed by an armature, shape keys, a lattice or deform modifiers,
solved on its baked graph deformed to the pose, without a re-bake (Wang et al. 2010, sec. 6.4).

:mod:`.cache_files` tells a pose (the baked vertices and polygons at other
positions) from a change of topology (a re-bake message) and keeps it in
``ObjectState.pose``: the evaluated positions, object space, in the baked
order.  For such a frame :mod:`.runtime` calls here instead of using the
object's own solver:

1. :func:`at_pose`: the frame's inputs at the pose.  Single scattering is off:
   it was baked for the rest pose and is not deformed (a deformed bake carries
   none), and the frame's warnings say so.
2. :func:`diffuse`: the engine's
   :class:`~translucency_addon.deformation.frames.DeformationFrames` -- pose ->
   deformed graph -> the one ``DiffusionSolver`` on it, warm-started from the
   last valid frame -> radiance at the posed vertices.  Its rig (attachments
   and a factorised stiffness per level, up to a few seconds at Preview) is
   built once per loaded bake, on the first deformed frame, and the log says
   so.  It runs where :func:`.backend.placement` puts diffusion: on the GPU the
   first pose's solver is rebound to every next pose (its graph textures stay,
   the coefficients travel); a GPU solve that fails sends the poses to the CPU,
   and the log says why.  Shadows of other objects: one BVH of the posed
   object and the occluders, refitted to each pose while the occluders stay
   (a rebuild sorts every triangle again).

Attached to the rest pose, as the paper has it ("the material changing due to
deformation is not considered"): the material and its heterogeneity field
(``frame.gather`` samples it at the rest nodes, and a mesh field at the rest
positions), the sky visibility (turned with the surface by the engine), and
the planner's decision (made on the rest bake, whose thickness cache stays
valid).

A pose the engine refuses -- a fold, a link stretched beyond the limit, NaN
vertices from a broken rig, a bone scaled to zero -- raises its
:class:`~translucency_addon.errors.DeformationError` with the frame and the
numbers, and nothing is written: in the viewport the attribute keeps the last
valid frame's radiance, which the message, the log and the panel
(:meth:`.state.DeformationState.describe`) name; in a render the frame fails or
renders without the pass (``handlers``), never with another frame's radiance.
"""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np

from . import backend, state
from .frame import FrameInputs
from .scene_inputs import view_directions

SS_OFF = ("single scattering is off on deformed frames: it was baked for the rest pose and is not deformed "
          "(diffusion is solved on the deformed graph); it comes back at the baked pose, or after a re-bake in "
          "this pose")


def at_pose(st: state.ObjectState, frame: FrameInputs) -> FrameInputs:
    """The frame's inputs at a pose: single scattering off, and the warnings say why."""
    if not frame.use_ss and not (frame.want_ss and st.bake.single_scattering is not None):
        return frame
    return replace(frame, use_ss=False, warnings=frame.warnings + (SS_OFF,))


def diffuse(st: state.ObjectState, frame: FrameInputs, number: int, solve_sig, force: bool) -> tuple:
    """Multiple scattering at ``obj.data``'s vertices in the pose ``st.pose`` of scene frame ``number``.

    Returns ``(rgb, solver, solved, seconds, result)``: solved on the deformed graph, or the last
    valid frame's solution reused when ``solve_sig`` (its inputs and the pose) is that frame's and only
    the view changed.  Raises the engine's :class:`DeformationError`/:class:`GraphFolded` for a pose it
    refuses, with the frame, the numbers and which result the object keeps.
    """
    from ..translucency_addon.errors import DeformationError, GraphFolded

    d = st.deformation
    d.frame = number
    V = st.pose
    same = frame.mapping.same
    t0 = time.perf_counter()
    try:
        frames = _frames(st, frame)  # a cache without the tet mesh (format 1) cannot deform: re-bake
        last = frames.last
        if not force and last is not None and d.solve_sig == solve_sig:
            d.report, d.refused = last.report, ""
            return _radiance(st, last, frame), last.solver, False, 0.0, last.result
        def solve():  # the frames again after a GPU failure: the CPU's
            return _frames(st, frame).solve(
                V, list(frame.lights), frame.environment, frame=number,
                view_dirs=view_directions(frame.view, V) if same else None, shadows=True,
                occluders=_shadow_bvh(d, V, st.bake.mesh_faces, frame), channels=frame.ms_channels,
                single=frame.single_channels)

        def gpu_failed(reason):
            d.gpu_failed = reason
            state.log(f"'{st.name}': deformed frames: {reason}")

        out = backend.solve_with_cpu_retry(solve, on_gpu=lambda: d.backend == "GPU", rendering=frame.rendering,
                                           gpu_failed=gpu_failed)
    except DeformationError as ex:
        d.report = ex.report if isinstance(ex, GraphFolded) else None
        d.refused = str(ex)
        st.view_sig = None  # the attribute no longer shows this frame: the next valid one writes and reports
        if frame.rendering:  # a render never shows another frame's radiance (handlers: fail, or no pass)
            message = f"{ex}; nothing was solved for this frame"
        else:
            kept = (f"frame {d.solved_frame}'s radiance" if d.solved_frame is not None else "its last radiance")
            message = f"{ex}; the object keeps {kept}, nothing was written"
        raise (GraphFolded(message, ex.report) if isinstance(ex, GraphFolded) else DeformationError(message)) from None
    seconds = time.perf_counter() - t0
    d.report, d.refused, d.solve_sig = out.report, "", solve_sig
    rgb = out.radiance if same else _radiance(st, out, frame)
    return rgb, out.solver, True, seconds, out.result


def _frames(st: state.ObjectState, frame: FrameInputs):
    """The object's ``DeformationFrames`` for this frame's scale, tolerance, material and field.

    The rig is built on the first deformed frame of a loaded bake (logged: it takes a moment); the
    frames are re-made over it when the scale or the tolerance changes.
    """
    from ..translucency_addon.deformation.pose import DeformationRig
    from ..translucency_addon.deformation.frames import DeformationFrames

    d = st.deformation
    bake = st.bake
    if d.rig is None:
        tets = sum(len(lv.tets) for lv in bake.levels if lv.tets is not None)
        state.log(f"'{st.name}' is deformed: building its deformation rig, once per loaded bake ({tets:,} tets in "
                  f"{len(bake.levels)} levels; up to a few seconds at Preview) ...")
        t0 = time.perf_counter()
        d.rig = DeformationRig(bake)
        d.rig_seconds = time.perf_counter() - t0
        state.log(f"'{st.name}': deformation rig built in {d.rig_seconds:.2f} s; deformed frames solve on it")
    options = frame.solve_options()
    where = backend.placement(frame.prefer, solver=options.solver, off_main=frame.off_main, gpu_failed=d.gpu_failed)
    sig = (round(frame.mm, 9), frame.tolerance, where.backend)
    if d.frames is None or d.frames_sig != sig:
        d.free()  # the last pose solver's GPU textures, if any
        d.backend, d.reason = where.backend, where.reason
        d.frames = DeformationFrames(bake, frame.material, frame.field_values, options, rig=d.rig.with_scale(frame.mm),
                                     make_solver=_gpu_pose_solver(st, frame) if where.gpu else None)
        d.frames_sig, d.solve_sig = sig, None
    if d.reason:
        state.log(f"'{st.name}': deformed frames: {d.reason}", once_key=("deformed placement", st.name, d.reason))
    d.frames.material, d.frames.field_values = frame.material, frame.field_values
    return d.frames


def _gpu_pose_solver(st: state.ObjectState, frame: FrameInputs):
    """The deformed frames' solver maker on the GPU: the first pose's solver, rebound to every next pose
    (``DiffusionSolver.rebind``); where the GPU solver cannot start, the CPU's, and the reason."""
    d = st.deformation

    def make(bake, material, field_values, options):
        solver, name, message = backend.make_solver(bake, material, field_values, options, frame.prefer,
                                                    off_main=frame.off_main)
        d.backend, d.reason = name, message if name == "CPU" else ""
        if name == "CPU":
            d.gpu_failed = message  # the next frame's frames are the CPU's, and say why
        return solver

    return make


def _shadow_bvh(d: state.DeformationState, V, F, frame: FrameInputs):
    """One BVH of the posed object and the other objects' triangles for shadow rays, or None without them.

    Built when the occluders change; refitted to the pose otherwise (``TriangleBVH.refit``: the same
    tree over moved vertices, about 20x cheaper than a rebuild).  None for a pose with NaN vertices,
    which the engine refuses with its own message.
    """
    if frame.occluders is None or not np.all(np.isfinite(V)):
        return None
    from ..translucency_addon.geometry.raycast import TriangleBVH

    if d.occluders is not None and d.occluders[0] == frame.occ_sig:
        return d.occluders[2].refit(np.vstack([V, d.occluders[1]]))
    Vo, Fo = (np.asarray(a) for a in frame.occluders)
    bvh = TriangleBVH(np.vstack([V, Vo]), np.vstack([F, Fo + len(V)]))
    d.occluders = (frame.occ_sig, Vo, bvh)
    return bvh


def _radiance(st: state.ObjectState, out, frame: FrameInputs) -> np.ndarray:
    """(n, 3) radiance of a solved pose at ``obj.data``'s vertices, toward the frame's view.

    ``obj.data`` with the baked vertex count: the posed mesh's own vertices.  Otherwise (a modifier
    after the deformation changed the count) the frame's map from ``obj.data``'s rest vertices to the
    finest surface nodes, with each vertex moved and turned as the nodes it maps to moved and turned.
    """
    m = frame.mapping
    solver, result = out.solver, out.result
    if m.same:
        return np.asarray(solver.vertex_radiance(result, view_directions(frame.view, out.pose.bake.mesh_vertices)))
    rest, posed = st.bake.levels[-1], out.pose.bake.levels[-1]
    w = np.asarray(m.w, dtype=np.float64)
    moved = np.einsum("vk,vkc->vc", w, (posed.surface_position - rest.surface_position)[m.idx])
    turned = m.normals + np.einsum("vk,vkc->vc", w, (posed.normal - rest.normal)[m.idx])
    normals = turned / np.maximum(np.linalg.norm(turned, axis=1, keepdims=True), 1e-300)
    return np.asarray(solver.radiance_at(result, m.idx, m.w, normals, view_directions(frame.view, m.positions + moved)))
