# SPDX-License-Identifier: GPL-3.0-or-later
"""One object's frame, read from Blender once: :class:`FrameInputs`, made by :func:`gather`.

Everything a frame of one baked object needs -- the scale, the material and
its heterogeneity field, the lights, the world, the occluders, the views,
the planner's passes, channels and regions, and how the finest surface nodes
map to the mesh's vertices -- is read here into one frozen value.  The steps
of :mod:`.runtime` (solve, single scattering, write, publish) take that value
and never go back to the scene.

What costs a walk over the scene is read only for the passes the planner
runs: the occluders when diffusion runs; the viewport's view and the
single-scattering staleness when single scattering runs; the mesh mapping
when either runs.  Kept between frames in the object's :class:`~.state.ObjectState`
(never in the value): the field samples (re-sampled only when the field's
signature changes), the occluder triangles and the mapping to ``obj.data``'s
vertices (re-computed only when those vertices move).
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

import numpy as np

from . import inner_parts, scene_inputs
from . import state
from .state import ObjectState

NOT_BAKED_SS = ("Single Scattering is on but was not baked: press Bake Single Scattering "
                "(or Bake, which bakes both)")


@dataclass(frozen=True)
class FrameInputs:
    """Everything one object's frame needs, read from Blender once (:func:`gather`)."""

    name: str
    n_vertices: int  # of obj.data, whose attribute is written
    mm: float  # millimetres per object unit
    material: object  # translucency_addon.scene.materials.Material
    field_sig: object  # the heterogeneity field's signature (None: homogeneous)
    field_values: list | None  # the field at every level's nodes (sampled when field_sig changed)
    lights: tuple  # translucency_addon.scene.lights.Light, object space
    environment: object | None  # translucency_addon.scene.lights.Environment
    view: tuple | None  # towards the render camera (use_camera), object space; None: along the normals
    ss_view: tuple | None  # single scattering's view: the camera, else the first 3D viewport's eye
    prefer: str  # the scene's Solver setting: AUTO, GPU or CPU
    tolerance: float
    rendering: bool  # a render depsgraph
    off_main: bool  # not on Blender's main thread (a render job)
    want_ms: bool  # the object's Multiple Scattering switch
    want_ss: bool  # the object's Single Scattering switch
    split: bool  # also write single scattering alone (Split Pass)
    ss_order: int  # SH order used: the setting, at most the baked one
    plan: object  # translucency_addon.planner.Plan
    use_ms: bool  # diffusion runs this frame
    use_ss: bool  # single scattering runs this frame
    use_vnm: bool  # the Voxel Number Map runs this frame (an object with inner parts)
    part_media: tuple | None  # the inner parts' roles and media now (ops.inner_parts.part_media); None: no parts
    ms_channels: tuple  # the planner's diffusion channels
    single_channels: tuple  # the channels in which the diffusion solve adds closed-form single scattering (split)
    occluders: object  # other objects' triangles in object space (None without, or when diffusion is off)
    occ_sig: tuple | None
    mapping: object  # translucency_addon.frame.MeshMapping; None when no pass runs
    ss_stale: str  # why the baked single scattering no longer matches ('' when it does)
    warnings: tuple  # scale, world, stale bake, stale single scattering

    @property
    def unseen(self) -> bool:
        """Outside the render camera's view: no work at all this frame."""
        return not self.plan.run and self.plan.reason.startswith("outside the camera view")

    @property
    def env_sig(self) -> tuple | None:
        return scene_inputs.environment_signature(self.environment)

    def solve_options(self):
        """The diffusion solver's options for this frame (the scene's tolerance)."""
        from ..translucency_addon.diffusion.solver import SolveOptions

        return SolveOptions(solver="fast", tol=self.tolerance)

    def weights(self, kind: str) -> np.ndarray:
        """The planner's per-vertex weight of a pass (``"multiple"``, ``"single"``, ``"voxel_number_map"``), on
        ``obj.data``'s vertices."""
        return self.plan.vertex_weights(kind, self.mapping.idx, self.mapping.w)


def gather(obj, scene, depsgraph, st: ObjectState, use_camera: bool) -> FrameInputs:
    """Read one frame of ``obj`` from Blender: inputs, the planner's decision, and what the passes that run need.

    Raises :class:`TranslucencyError` subclasses (a bad material, a field without its texture).
    """
    settings = obj.translucency
    matrix = obj.evaluated_get(depsgraph).matrix_world.copy()
    mm, scale_warning = scene_inputs.mm_per_unit(obj, scene, matrix)
    metres_per_bu = scene_inputs.metres_per_world_unit(obj, scene, mm, matrix)
    material = scene_inputs.build_material(settings)
    part_media = inner_parts.part_media(obj) if st.bake.composite is not None else None
    want_ms = bool(settings.use_multiple_scattering)
    field_sig = _field(obj, settings, depsgraph, st, want_ms)
    off_main = threading.current_thread() is not threading.main_thread()
    rendering = getattr(depsgraph, "mode", "VIEWPORT") == 'RENDER'
    environment, world_warning, world_sun = scene_inputs.world_environment(scene.world, matrix,
                                                                           not (rendering or off_main))
    from ..translucency_addon.frame import lights_at_quality

    lights = lights_at_quality(tuple(scene_inputs.collect_lights(depsgraph, matrix, metres_per_bu)) + world_sun,
                               st.bake.settings.quality)
    in_view = scene_inputs.in_camera_view(scene, depsgraph, obj) if use_camera else True
    plan = make_plan(obj.name, st, settings, material, lights, environment, mm, in_view)

    has_ss = st.bake.single_scattering is not None
    from ..translucency_addon.frame import passes_for  # engine imports stay lazy: the add-on registers without it

    passes = passes_for(plan, st.bake, want_ms)  # the engine's rule (translucency_addon.frame), as the CLI's
    use_ms, use_ss, use_vnm = passes.use_ms, passes.use_ss, passes.use_vnm
    want_ss = bool(settings.use_single_scattering)
    occluders, occ_sig = (scene_inputs.collect_occluders(depsgraph, obj, matrix, st.occluders,
                                                         exclude=inner_parts.part_objects(obj))
                          if use_ms or use_vnm else (None, None))
    view = scene_inputs.camera_view(scene, depsgraph, matrix) if use_camera else None
    ss_view, ss_stale = None, ""
    if use_ss:
        ss_view = view
        if ss_view is None and not use_camera and not rendering and not off_main:
            ss_view = scene_inputs.viewport_view(matrix)
        ss_stale = _ss_staleness(obj, st, settings, depsgraph, material, field_sig, mm, part_media)
    elif want_ss and not has_ss:
        ss_stale = NOT_BAKED_SS
    return FrameInputs(
        name=obj.name, n_vertices=len(obj.data.vertices), mm=mm, material=material, field_sig=field_sig,
        field_values=st.field_values, lights=lights, environment=environment, view=view, ss_view=ss_view,
        prefer=scene.translucency.solver_backend, tolerance=float(scene.translucency.tolerance),
        rendering=rendering, off_main=off_main, want_ms=want_ms, want_ss=want_ss,
        split=bool(settings.ss_split_pass),
        ss_order=min(int(settings.ss_sh_order), st.bake.single_scattering.order) if has_ss else 0,
        plan=plan, use_ms=use_ms, use_ss=use_ss, use_vnm=use_vnm, part_media=part_media,
        ms_channels=passes.ms_channels, single_channels=passes.single_channels,
        occluders=occluders, occ_sig=occ_sig,
        mapping=mesh_mapping(obj, st) if use_ms or use_ss or use_vnm else None,
        ss_stale=ss_stale,
        warnings=tuple(w for w in (scale_warning, world_warning, st.stale_message, ss_stale) if w))


def _field(obj, settings, depsgraph, st: ObjectState, want_ms: bool):
    """The field's signature; its values at every level's nodes are re-sampled into ``st`` when it changed."""
    epoch = state.geometry_epoch(obj.name)
    rest = st.bake.mesh_vertices if st.pose is not None else None  # a pose: the field stays at rest
    field_sig = scene_inputs.field_signature(obj, settings, depsgraph, epoch, rest)
    changed = field_sig != st.field_sig or (field_sig is not None and st.field_values is None)
    if changed and want_ms:
        if field_sig is None:
            st.field_values = None
        else:
            st.field_values = scene_inputs.sample_field(obj, settings, [lv.position for lv in st.bake.levels],
                                                        depsgraph, rest)
            state.count("field_samples")
        st.field_sig = field_sig
    return field_sig


def make_plan(name: str, st: ObjectState, settings, material, lights, environment, mm: float, in_view: bool):
    """The planner's decision for this object and frame (``translucency_addon.planner.plan_object``).

    The object's switches become overrides: a term that is off is forced off;
    with Pass Planning "All" every enabled term runs on every channel.
    """
    from ..translucency_addon.frame import pass_overrides
    from ..translucency_addon.planner import plan_object

    has_ss = st.bake.single_scattering is not None
    every = getattr(settings, "pass_planning", "AUTO") == 'ALL'
    overrides = pass_overrides(multiple=bool(settings.use_multiple_scattering),
                               single=bool(settings.use_single_scattering), has_single=has_ss,
                               voxel_number_map=bool(settings.use_voxel_number_map),
                               has_voxel_number_map=st.bake.voxel_number_map is not None, all_passes=every)
    all_passes = "by the object's Pass Planning setting 'All Passes' (Translucency panel)"
    why = {}  # what forced each override, in the panel's words (the plan says it)
    for kind, prop in (("multiple", "use_multiple_scattering"), ("single", "use_single_scattering"),
                       ("voxel_number_map", "use_voxel_number_map")):
        if kind not in overrides:
            continue
        if overrides[kind]:
            why[kind] = all_passes
        elif kind == "single" and settings.use_single_scattering:
            why[kind] = "because Single Scattering is on but not baked (press Bake Single Scattering)"
        else:
            why[kind] = _off_because(settings, prop)
    return plan_object(st.bake.with_scale(mm), material, list(lights), environment, field_values=st.field_values,
                       has_single_scattering=has_ss, in_view=in_view, enabled=bool(settings.enabled),
                       overrides=overrides, name=name, override_reasons=why)


def _off_because(settings, prop: str) -> str:
    """What turned a pass off: the setting's default (the user never touched it) or the user's setting, by the
    name the panel shows."""
    label = settings.bl_rna.properties[prop].name
    if settings.is_property_set(prop):
        return f"by the user's setting: '{label}' is off (Translucency panel)"
    return f"by default: '{label}' is off unless turned on (Translucency panel)"


def _ss_staleness(obj, st: ObjectState, settings, depsgraph, material, field_sig, mm: float, part_media) -> str:
    """Why the baked single scattering no longer matches the object ('' when it does); with inner parts,
    also their media (:func:`.inner_parts.ss_parts_staleness`)."""
    from ..translucency_addon.single_scattering import stale_message, staleness

    data = st.bake.single_scattering
    try:
        want = scene_inputs.ss_settings(settings)
    except Exception as ex:  # noqa: BLE001 - an invalid or unreadable panel setting is the reason shown, not a crash
        return str(ex)
    field_fp = None
    if material.heterogeneous:
        if st.ss_field_fp is None or st.ss_field_fp[0] != field_sig:
            st.ss_field_fp = (field_sig, scene_inputs.ss_field_fingerprint(obj, settings, depsgraph, field_sig))
        field_fp = st.ss_field_fp[1]
    reasons = staleness(data, settings=want, material=material, field_fp=field_fp, mm_per_unit=mm)
    reasons += inner_parts.ss_parts_staleness(data, part_media)
    return stale_message(reasons)


# ------------------------------------------------------------------ the mesh's vertices


def _original_normals(mesh, V) -> np.ndarray:
    normals = getattr(mesh, "vertex_normals", None)
    if normals is not None and len(normals) == len(V):
        arr = np.empty(len(V) * 3, dtype=np.float32)
        normals.foreach_get("vector", arr)
        return arr.reshape(-1, 3).astype(np.float64)
    _, F = scene_inputs.mesh_arrays(mesh)
    return scene_inputs.mesh_normals(V, F)


def mesh_mapping(obj, st: ObjectState):
    """The finest surface nodes that carry values to ``obj.data``'s vertices (read once per frame).

    The baked (evaluated) mesh's own vertex map when ``obj.data`` has its vertex count (the outer mesh's,
    for a bake with inner parts); otherwise
    a map to ``obj.data``'s vertices (a modifier changed the count), cached in ``st`` until they move.
    """
    from ..translucency_addon.frame import MeshMapping

    bake = st.bake
    n = inner_parts.n_outer_vertices(bake)  # a bake with cavities continues with their walls
    if len(obj.data.vertices) == n:
        idx, w = bake.vertex_map
        return MeshMapping(True, idx[:n], w[:n])
    from ..translucency_addon.quadgraph.bake import vertex_mapping

    mesh = obj.data
    V = scene_inputs.vertex_positions(mesh)
    digest = scene_inputs.array_digest(V)
    if st.orig_map is None or st.orig_map[0] != digest:
        N = _original_normals(mesh, V)
        idx, w = vertex_mapping(V, N, bake.finest, bake.settings.vertex_map_k)
        st.orig_map = (digest, idx, w, V, N)
    digest, idx, w, V, N = st.orig_map
    return MeshMapping(False, idx, w, V, N, digest)
