# SPDX-License-Identifier: GPL-3.0-or-later
"""Per-object runtime state: what one baked object keeps between frames (never a bpy reference).

:class:`ObjectState` per object name in :data:`_STATES`, used only while its
``key`` equals ``obj.translucency.bake_key`` (so undo, which replaces every ID,
never leaves a dangling pointer), the diagnostics counters and the console log.
Everything on the Blender side that keeps memory between frames keeps it here.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field

from . import backend, scene_inputs

_LOCK = threading.RLock()


@dataclass
class ObjectState:
    """What one baked object keeps between solves (never a bpy reference)."""

    name: str
    key: str
    cache_path: str
    bake: object  # translucency_addon.bake.Bake as loaded (baked mm_per_unit)
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
    gpu_failed_in_render: str = ""  # why the GPU solve failed in a render ('' when it did not)
    occluders: scene_inputs.OccluderCache = field(default_factory=scene_inputs.OccluderCache)
    geometry_digest: str = ""
    stale_message: str = ""
    orig_map: tuple | None = None  # (digest, idx, w, positions, normals) for obj.data vertices
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


_STATES: dict[str, ObjectState] = {}
_FAILED: dict[str, tuple] = {}  # name -> (inputs, message): a load that failed is not retried blindly
_LOGGED: set = set()
# Problems found with an object's cache (missing, truncated, stale), by object name; shown
# by the panel.  Runtime only: a file load refills it, the .blend is never modified for it.
CACHE_STATUS: dict[str, str] = {}
# Counters for tests and diagnostics.
COUNTERS = {"solves": 0, "radiance_only": 0, "loads": 0, "field_samples": 0, "writes": 0, "planner_skips": 0}
PLANS: dict = {}  # object name -> the planner's last Plan (shown in the panel)
ERRORS: dict[str, str] = {}  # object name -> why its last solve failed (shown until one succeeds)
LAST_SOLVE: dict = {}  # the last solve of any object: name, seconds, residual, backend (the scene's line)
# Object names whose mesh we just wrote (the handler ignores the update that causes).
OWN_WRITES: set = set()
# Bumped by the handlers when a mesh is edited (vertex-group weights are not hashed each time).
GEOMETRY_EPOCH: dict[str, int] = {}
FRAME_EPOCH = "\0frame"  # a GEOMETRY_EPOCH key no object can have: bumped on every frame change


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


def drop_state(name: str) -> None:
    with _LOCK:
        st = _STATES.pop(name, None)
        _FAILED.pop(name, None)
        ERRORS.pop(name, None)
        if st is not None:
            st.free()


def clear() -> None:
    """Forget every object's runtime state and free GPU memory (file load, unregister)."""
    with _LOCK:
        for name in list(_STATES):
            drop_state(name)
        _FAILED.clear()
        _LOGGED.clear()
        CACHE_STATUS.clear()
        OWN_WRITES.clear()
        GEOMETRY_EPOCH.clear()
        PLANS.clear()
        ERRORS.clear()
        LAST_SOLVE.clear()


def invalidate_views() -> None:
    """After undo/redo the attribute may hold older values: rewrite it on the next check."""
    with _LOCK:
        for st in _STATES.values():
            st.view_sig = None
            st.geometry_digest = ""
        GEOMETRY_EPOCH.update({k: v + 1 for k, v in GEOMETRY_EPOCH.items()})


def prune(existing_names) -> None:
    """Drop states of objects that no longer exist."""
    names = set(existing_names)
    for name in list(_STATES):
        if name not in names:
            drop_state(name)


def install_state(obj, bake, cache_path: str) -> ObjectState:
    """Register a freshly baked ``bake`` for ``obj`` (the bake operator's commit)."""
    with _LOCK:
        drop_state(obj.name)
        CACHE_STATUS.pop(obj.name, None)
        st = ObjectState(name=obj.name, key=bake.key, cache_path=cache_path, bake=bake)
        _STATES[obj.name] = st
        return st


def is_baked(obj) -> bool:
    return (obj is not None and obj.type == 'MESH' and hasattr(obj, "translucency")
            and bool(obj.translucency.cache_filepath) and bool(obj.translucency.bake_key))


def baked_objects(scene):
    return [ob for ob in scene.objects if ob.type == 'MESH' and ob.translucency.enabled and is_baked(ob)]
