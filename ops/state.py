# SPDX-License-Identifier: GPL-3.0-or-later
"""Per-object runtime state: what one object keeps between frames (never a bpy reference).

:class:`ObjectState` per baked object name in :data:`_STATES`, used only while its
``key`` equals ``obj.translucency.bake_key`` (so undo, which replaces every ID,
never leaves a dangling pointer); :class:`FluidObjectState` per Fluid-source
object name in :data:`_FLUIDS` (no bake: the last frame's warm start and what
it cost); the diagnostics counters and the console log.  Everything on the
Blender side that keeps memory between frames keeps it here.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field

from . import backend, scene_inputs

_LOCK = threading.RLock()


@dataclass
class DeformationState:
    """One object's deformed frames (:mod:`.deformation`): kept between frames, never saved.

    ``frames`` is the engine's ``DeformationFrames`` (its rig is built once per loaded bake, on the
    first deformed frame); the rest is what the panel and the log say about the current frame.
    """

    rig: object | None = None  # translucency_addon.deformation.pose.DeformationRig of the loaded bake
    rig_seconds: float = 0.0
    frames: object | None = None  # translucency_addon.deformation.frames.DeformationFrames at the frame's scale
    frames_sig: tuple | None = None  # (mm per unit, tolerance, backend) the frames were made for
    backend: str = "CPU"  # where deformed frames solve (ops.backend.placement)
    reason: str = ""  # why not on the GPU
    gpu_failed: str = ""  # why a GPU solve of a pose failed (then the poses stay on the CPU)
    frame: int | None = None  # the scene frame of the current pose
    report: object | None = None  # its DeformationReport (None when the pose could not be deformed at all)
    refused: str = ""  # why the current pose was not solved ('' when it was)
    solved_frame: int | None = None  # the frame whose radiance the attribute holds
    solve_sig: tuple | None = None  # what frames.last was solved for
    occluders: tuple | None = None  # (occluder signature, their vertices, BVH of the posed object + them)

    def free(self) -> None:
        """Release the pose solver's GPU textures (no-op on the CPU); the frames are made again when needed."""
        last = getattr(self.frames, "last", None)
        if last is not None:
            backend.free_solver(last.solver)
        self.frames = self.frames_sig = self.solve_sig = None

    def describe(self) -> str:
        """The panel's line about the current pose ('' before the first deformed frame)."""
        if self.frame is None:
            return ""
        at = f"Deformed, frame {self.frame}"
        if self.refused:
            kept = (f"the attribute keeps frame {self.solved_frame}" if self.solved_frame is not None
                    else "the attribute keeps its last values")
            if self.report is not None:
                return f"{at}: refused ({self.report.worst_link()})); {kept}"
            return f"{at}: refused; {kept}"
        if self.report is None:
            return at
        slivers = self.report.inverted_tets
        return (f"{at}: {self.report.worst_link()})"
                + (f", {slivers} sliver tets turned over (tolerated)" if slivers else ""))


@dataclass
class ObjectState:
    """What one baked object keeps between solves (never a bpy reference)."""

    name: str
    key: str
    cache_path: str
    bake: object  # translucency_addon.quadgraph.bake.Bake as loaded (baked mm_per_unit)
    solver: object | None = None
    solver_sig: tuple | None = None
    backend: str = ""
    backend_message: str = ""
    announced: bool = False
    material: object | None = None  # what the solver was last given
    solver_field: list | None = None  # the field values the solver was last given
    field_sig: object = None  # the signature of the field samples below
    field_values: list | None = None  # the field at every level's nodes (ops.frame samples it)
    solve_sig: tuple | None = None
    view_sig: tuple | None = None
    result: object | None = None
    result_solver: object | None = None
    render_solver: object | None = None  # CPU twin for solves off the main thread
    render_result: object | None = None
    render_solve_sig: tuple | None = None
    bounce: object | None = None  # vertex radiance (along the normals) of the last interreflected solve
    progressive: object | None = None  # the viewport's solve in progress (engine's ProgressiveSolve), or None
    gpu_failed_in_render: str = ""  # why the GPU solve failed in a render ('' when it did not)
    occluders: scene_inputs.OccluderCache = field(default_factory=scene_inputs.OccluderCache)
    geometry_digest: str = ""
    stale_message: str = ""
    orig_map: tuple | None = None  # (digest, idx, w, positions, normals) for obj.data vertices
    # the evaluated mesh's positions when they are a pose of the bake (ops.cache_files; None at rest)
    pose: object | None = None
    deformation: DeformationState = field(default_factory=DeformationState)
    # the solve status the panel shows (ops.status.solve_status; never saved)
    seconds: float = 0.0
    residual: float = 0.0
    iterations: int = 0
    solves: int = 0
    warnings: tuple = ()
    # single scattering
    ss: object | None = None  # translucency_addon.single_scattering.FrameEvaluator
    ss_key: tuple | None = None
    ss_backend: str = ""
    ss_backend_message: str = ""
    ss_seconds: float = 0.0
    ss_stale: str = ""
    ss_field_fp: tuple | None = None  # (field_sig, fingerprint)
    ss_rgb: object | None = None  # last single-scattering radiance (n_vertices, 3)
    plan: object | None = None  # translucency_addon.planner.Plan of the last solve
    # inner parts (ops.inner_parts): the parts' media the solver was last given, the Voxel Number Map's evaluator
    part_media: tuple | None = None
    vnm: object | None = None  # translucency_addon.voxel_number_map.VoxelNumberMapEvaluator
    vnm_key: tuple | None = None
    vnm_inputs: tuple | None = None  # (material, part media) the evaluator was last given
    vnm_backend: str = ""
    vnm_backend_message: str = ""
    vnm_seconds: float = 0.0

    @property
    def frame_backend(self) -> str:
        """Where this frame's diffusion runs: the deformed frames' backend at a pose, the object's solver's
        otherwise."""
        return self.deformation.backend if self.pose is not None else self.backend

    @property
    def frame_backend_message(self) -> str:
        return self.deformation.reason if self.pose is not None else self.backend_message

    def free(self) -> None:
        for solver in (self.solver, self.render_solver):
            if solver is not None:
                backend.free_solver(solver)
        self.solver = self.render_solver = None
        self.result = self.render_result = self.result_solver = None
        if self.ss is not None:
            try:
                self.ss.free()
            except Exception as ex:  # noqa: BLE001 - freeing must not break cleanup paths
                print(f"Translucency: freeing the single-scattering data failed: {type(ex).__name__}: {ex}")
        self.ss = self.ss_key = self.ss_rgb = None
        if self.vnm is not None:
            backend.free_solver(self.vnm)  # the evaluator's GPU transmission (no-op on the CPU)
        self.vnm = self.vnm_key = self.vnm_inputs = None
        self.deformation.free()
        self.deformation = DeformationState()


@dataclass
class FluidObjectState:
    """What one Fluid-source object keeps between frames (never a bpy reference; never saved).

    ``name``, ``seconds``, ``residual``, ``frame_backend`` and ``stale_message`` are
    what ``status.publish`` reads of any object's state.
    """

    name: str
    backend: str = "CPU"  # where the last frame's diffusion solved (ops.backend.placement)
    backend_message: str = ""  # why not on the GPU ('' when it was, or when the CPU was chosen)
    gpu_failed: str = ""  # why a GPU solve of this fluid failed (its frames then stay on the CPU)
    stale_message: str = ""
    sig: tuple | None = None  # the inputs of the frame the attribute holds (the solve's and the view)
    solve_sig: tuple | None = None  # the inputs of the last solve (all but the view)
    result: object | None = None  # its FluidResult (mesh outputs): a new view only re-evaluates the radiance
    solver_sig: tuple | None = None  # material, field and scale the warm start was solved with
    warm: object | None = None  # translucency_addon.fluid.FluidState of the last frame
    frame: int = 0  # the scene frame of the last solve
    seconds: float = 0.0  # the last frame's wall-clock time (particles to attribute)
    stages: dict = field(default_factory=dict)  # the engine's seconds per stage
    residual: float = 0.0
    iterations: int = 0
    particles: int = 0
    cells: int = 0
    surface_cells: int = 0
    radius: float = 0.0  # the radius used, scene units
    source: str = ""  # what the particles were: "particle system 'P' of 'Emitter'"
    output: str = ""  # what the radiance went onto: "642 vertices" / "300 points"
    carried: bool = False  # written through the carrier modifier (generated geometry)
    warm_started: bool = False
    empty: str = ""  # why there were no particles ('' when there were)
    warnings: tuple = ()
    solves: int = 0
    deferred: int = 0  # frames left to the throttled live check while playback ran
    occluders: scene_inputs.OccluderCache = field(default_factory=scene_inputs.OccluderCache)

    @property
    def frame_backend(self) -> str:
        """Where this frame solved (``ObjectState`` keeps it apart from the object's solver for deformed
        frames; a fluid always solves where ``backend`` says)."""
        return self.backend

    def free(self) -> None:
        if self.result is not None:
            backend.free_solver(self.result.diffusion)  # the last frame's GPU textures (no-op on the CPU)
        self.warm = self.result = None


# Everything below is private to this module: the rest of the add-on reads and writes it through the
# functions that follow (one interface; tests/test_ops_house.py holds every other module to it).
_STATES: dict[str, ObjectState] = {}
_FLUIDS: dict[str, FluidObjectState] = {}
_FAILED: dict[str, tuple] = {}  # name -> (inputs, message): a load that failed is not retried blindly
_LOGGED: set = set()
# Problems found with an object's cache (missing, truncated, stale), by object name; shown
# by the panel.  Runtime only: a file load refills it, the .blend is never modified for it.
_CACHE_STATUS: dict[str, str] = {}
# Counters for tests and diagnostics.
_COUNTERS = {"solves": 0, "radiance_only": 0, "loads": 0, "field_samples": 0, "writes": 0, "planner_skips": 0,
             "progressive_steps": 0}
_PLANS: dict = {}  # object name -> the planner's last Plan (shown in the panel)
_ERRORS: dict[str, str] = {}  # object name -> why its last solve failed (shown until one succeeds)
_LAST_SOLVE: dict = {}  # the last solve of any object: name, seconds, residual, backend (the scene's line)
# (level, message) for Blender's Info log: handlers and timers are not operators, so ``live.report_info``
# hands these to the ``translucency.report`` operator from a timer (the console has them at once).
_INFO: list = []
# Object names whose mesh we just wrote (the handler ignores the update that causes).
_OWN_WRITES: set = set()
# Bumped by the handlers when a mesh is edited (vertex-group weights are not hashed each time).
_GEOMETRY_EPOCH: dict[str, int] = {}
_FRAME_EPOCH = "\0frame"  # a _GEOMETRY_EPOCH key no object can have: bumped on every frame change


def failed_load(name: str) -> tuple | None:
    """``(inputs, message)`` of the object's last failed cache load (not retried while the inputs are the same)."""
    return _FAILED.get(name)


def remember_failed_load(name: str, inputs: tuple, message: str) -> None:
    _FAILED[name] = (inputs, message)
    _CACHE_STATUS[name] = f"Cache problem: {message}"


def lock():
    """The lock every change of an object's state holds (a render thread and the main thread both solve)."""
    return _LOCK


# -- what the panel shows: a cache's problem, a solve's error, the last plan, the last solve ---------------
def cache_problem(name: str) -> str | None:
    """What is wrong with the object's cache ('Stale: ...', 'Cache problem: ...'), or None."""
    return _CACHE_STATUS.get(name)


def set_cache_problem(name: str, problem: str | None) -> None:
    """Record the cache's problem (None: the cache is fine)."""
    if problem is None:
        _CACHE_STATUS.pop(name, None)
    else:
        _CACHE_STATUS[name] = problem


def solve_error(name: str) -> str:
    """Why the object's last solve failed ('' when it did not)."""
    return _ERRORS.get(name, "")


def solve_errors() -> dict:
    """Every object's last solve error, by name (a copy)."""
    return dict(_ERRORS)


def set_solve_error(name: str, message: str | None) -> bool:
    """Record why the last solve failed (None: it succeeded); True when the message is new."""
    if message is None:
        _ERRORS.pop(name, None)
        return False
    new = _ERRORS.get(name) != message
    _ERRORS[name] = message
    return new


def last_plan(name: str):
    """The planner's last Plan for the object, or None before its first frame."""
    return _PLANS.get(name)


def set_plan(name: str, plan) -> None:
    if plan is None:
        _PLANS.pop(name, None)
    else:
        _PLANS[name] = plan


def last_solve() -> dict:
    """The last solve of any object: ``{"name", "seconds", "residual", "backend"}`` (empty before one)."""
    return dict(_LAST_SOLVE)


def set_last_solve(**record) -> None:
    _LAST_SOLVE.update(record)


# -- diagnostics and the Info log ----------------------------------------------------------------------
def count(event: str) -> None:
    """Count one ``event`` (a key of :func:`counters`)."""
    _COUNTERS[event] += 1


def counters() -> dict:
    """How often each event happened this session: solves, radiance-only updates, cache loads, field
    samplings, attribute writes, frames the planner skipped (a copy)."""
    return dict(_COUNTERS)


def queue_info(level: str, message: str) -> None:
    """A message for Blender's Info log, handed on from a timer (``live.report_info``)."""
    _INFO.append((level, message))


def take_info() -> list:
    """The queued Info messages, oldest first, and the queue emptied."""
    out = list(_INFO)
    _INFO.clear()
    return out


def queued_info() -> list:
    """The queued Info messages, left queued (a copy)."""
    return list(_INFO)


def has_info() -> bool:
    return bool(_INFO)


# -- the handlers' bookkeeping ---------------------------------------------------------------------------
def mark_own_write(name: str) -> None:
    """Our attribute write to ``name``'s mesh: the update it causes is not an edit."""
    _OWN_WRITES.add(name)


def take_own_writes() -> set:
    """The names written since the last depsgraph update, and the set emptied."""
    out = set(_OWN_WRITES)
    _OWN_WRITES.clear()
    return out


def bump_geometry_epoch(name: str | None = None) -> None:
    """A mesh edit of ``name`` (None: a frame change, which every object sees)."""
    key = _FRAME_EPOCH if name is None else name
    _GEOMETRY_EPOCH[key] = _GEOMETRY_EPOCH.get(key, 0) + 1


def geometry_epoch(name: str) -> tuple:
    """``(edits of the object, frame changes)``: stands for the vertex-group weights in a field's signature."""
    return (_GEOMETRY_EPOCH.get(name, 0), _GEOMETRY_EPOCH.get(_FRAME_EPOCH, 0))


def log(message: str, once_key=None) -> None:
    """Print to the console (the log of ``blender -b``); ``once_key``: only the first time."""
    if once_key is not None:
        if once_key in _LOGGED:
            return
        _LOGGED.add(once_key)
    print(f"Translucency: {message}", flush=True)


# ------------------------------------------------------------------ state bookkeeping


def get_state(obj) -> ObjectState | None:
    st = _STATES.get(obj.name)
    if st is not None and st.key and st.key == obj.translucency.bake_key:
        return st
    return None


def fluid_state_of(name: str) -> FluidObjectState | None:
    """The runtime state of the Fluid-source object ``name``, or None before its first frame."""
    return _FLUIDS.get(name)


def object_states() -> list:
    """Every baked object's runtime state (a list: safe to drop states while iterating)."""
    return list(_STATES.values())


def all_states() -> list:
    """Every object's runtime state, baked and Fluid-source."""
    return list(_STATES.values()) + list(_FLUIDS.values())


def fluid_state(obj) -> FluidObjectState:
    """The runtime state of a Fluid-source object (made on first use)."""
    st = _FLUIDS.get(obj.name)
    if st is None:
        st = _FLUIDS[obj.name] = FluidObjectState(name=obj.name)
    return st


def drop_state(name: str) -> None:
    with _LOCK:
        _FLUIDS.pop(name, None)
        st = _STATES.pop(name, None)
        _FAILED.pop(name, None)
        _ERRORS.pop(name, None)
        if st is not None:
            st.free()


def clear() -> None:
    """Forget every object's runtime state and free GPU memory (file load, unregister)."""
    with _LOCK:
        for name in list(_STATES) + list(_FLUIDS):
            drop_state(name)
        _FAILED.clear()
        _LOGGED.clear()
        _CACHE_STATUS.clear()
        _OWN_WRITES.clear()
        _GEOMETRY_EPOCH.clear()
        _PLANS.clear()
        _ERRORS.clear()
        _LAST_SOLVE.clear()
        _INFO.clear()


def invalidate_views() -> None:
    """After undo/redo the attribute may hold older values: rewrite it on the next check."""
    with _LOCK:
        for st in _STATES.values():
            st.view_sig = None
            st.geometry_digest = ""
        for fl in _FLUIDS.values():
            fl.sig = fl.solve_sig = None
        _GEOMETRY_EPOCH.update({k: v + 1 for k, v in _GEOMETRY_EPOCH.items()})


def prune(existing_names) -> None:
    """Drop states of objects that no longer exist."""
    names = set(existing_names)
    for name in list(_STATES) + list(_FLUIDS):
        if name not in names:
            drop_state(name)


def install_state(obj, bake, cache_path: str) -> ObjectState:
    """Register a freshly baked ``bake`` for ``obj`` (the bake operator's commit)."""
    with _LOCK:
        drop_state(obj.name)
        _CACHE_STATUS.pop(obj.name, None)
        st = ObjectState(name=obj.name, key=bake.key, cache_path=cache_path, bake=bake)
        _STATES[obj.name] = st
        return st


def is_baked(obj) -> bool:
    return (obj is not None and obj.type == 'MESH' and hasattr(obj, "translucency")
            and bool(obj.translucency.cache_filepath) and bool(obj.translucency.bake_key))


def is_fluid(obj) -> bool:
    """A mesh or point cloud whose Translucency source is a particle fluid (no bake)."""
    return (obj is not None and obj.type in {'MESH', 'POINTCLOUD'} and hasattr(obj, "translucency")
            and obj.translucency.source == 'FLUID')


def baked_objects(scene):
    return [ob for ob in scene.objects if ob.type == 'MESH' and ob.translucency.enabled and is_baked(ob)
            and not is_fluid(ob)]


def fluid_objects(scene):
    """The scene's enabled Fluid-source objects (solved every frame, nothing baked)."""
    return [ob for ob in scene.objects if is_fluid(ob) and ob.translucency.enabled]
