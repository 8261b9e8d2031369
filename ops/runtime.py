# SPDX-License-Identifier: GPL-3.0-or-later
"""Per-object runtime state and the solve -> attribute path.

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

import os
import re
import tempfile
import threading
import time
import traceback
from dataclasses import dataclass, field

import bpy
import numpy as np

from . import backend, scene_inputs

ATTRIBUTE_NAME = "translucency_radiance"
SS_ATTRIBUTE_NAME = "translucency_radiance_ss"
ATTRIBUTE_DOMAIN = 'POINT'
ATTRIBUTE_TYPE = 'FLOAT_COLOR'
DEFAULT_CACHE_DIRECTORY = "//translucency_cache/"

_LOCK = threading.RLock()


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
    material: object | None = None
    field_sig: object = None
    field_values: list | None = None
    solve_sig: tuple | None = None
    view_sig: tuple | None = None
    result: object | None = None
    result_solver: object | None = None
    render_solver: object | None = None  # CPU twin for solves off the main thread
    render_result: object | None = None
    render_solve_sig: tuple | None = None
    bounce: object | None = None  # vertex radiance (along the normals) of the last interreflected solve
    gpu_failed_in_render: bool = False
    occluders: scene_inputs.OccluderCache = field(default_factory=scene_inputs.OccluderCache)
    geometry_digest: str = ""
    stale_message: str = ""
    orig_map: tuple | None = None  # (digest, idx, w, positions, normals) for obj.data vertices
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


_STATES: dict[str, ObjectState] = {}
_FAILED: dict[str, tuple] = {}  # name -> (inputs, message): a load that failed is not retried blindly
_LOGGED: set = set()
# Problems found with an object's cache (missing, truncated, stale), by object name; shown
# by the panel.  Runtime only: a file load refills it, the .blend is never modified for it.
CACHE_STATUS: dict[str, str] = {}
# Counters for tests and diagnostics.
COUNTERS = {"solves": 0, "radiance_only": 0, "loads": 0, "field_samples": 0, "writes": 0, "planner_skips": 0}
PLANS: dict = {}  # object name -> the planner's last Plan (shown in the panel)
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


# ------------------------------------------------------------------ cache files


def cache_directory(scene) -> tuple[str, str | None]:
    """``(absolute directory, note)``.  A blend-relative directory of an unsaved
    .blend resolves to a temporary folder, and ``note`` says so."""
    directory = scene.translucency.cache_directory or DEFAULT_CACHE_DIRECTORY
    if directory.startswith("//") and not bpy.data.filepath:
        tmp = os.path.join(tempfile.gettempdir(), "translucency_cache")
        return tmp, (f"the .blend file is not saved, so the cache was written to the temporary folder "
                     f"{tmp}; save the .blend and bake again to keep the cache next to it")
    return os.path.normpath(bpy.path.abspath(directory)), None


def cache_file_name(obj_name: str, key: str) -> str:
    safe = re.sub(r"[^A-Za-z0-9_.-]+", "_", obj_name).strip("._") or "object"
    return f"{safe}_{key[:16]}.npz"


def stored_cache_path(abs_path: str) -> str:
    """The path as stored in the .blend: blend-relative when the .blend is saved."""
    if bpy.data.filepath:
        try:
            return bpy.path.relpath(abs_path)
        except ValueError:  # another drive on Windows
            return abs_path
    return abs_path


def resolve_cache_path(obj) -> str:
    path = obj.translucency.cache_filepath
    return os.path.normpath(bpy.path.abspath(path)) if path else ""


def ensure_state(obj, retry: bool = False) -> ObjectState:
    """The object's state, loading its bake from the cache file when needed.

    Raises :class:`CacheError` (missing, truncated, stale, ...) with a message
    naming the file.  A failed load is remembered and not retried until the
    file, the key or ``retry`` changes.
    """
    from ..translucency_addon.cache import load_bake
    from ..translucency_addon.errors import CacheError

    with _LOCK:
        st = get_state(obj)
        if st is not None:
            return st
        drop_state(obj.name)
        settings = obj.translucency
        path = resolve_cache_path(obj)
        if not path or not settings.bake_key:
            raise CacheError(f"'{obj.name}' is not baked yet: press Bake in the Translucency panel")
        try:
            mtime = os.path.getmtime(path)
        except OSError:
            mtime = None
        inputs = (path, settings.bake_key, mtime)
        failed = _FAILED.get(obj.name)
        if failed is not None and failed[0] == inputs and not retry:
            raise CacheError(failed[1])
        try:
            bake = load_bake(path, expected_key=settings.bake_key)
        except CacheError as ex:
            _FAILED[obj.name] = (inputs, str(ex))
            CACHE_STATUS[obj.name] = f"Cache problem: {ex}"
            raise
        COUNTERS["loads"] += 1
        CACHE_STATUS.pop(obj.name, None)
        st = ObjectState(name=obj.name, key=bake.key, cache_path=path, bake=bake)
        _STATES[obj.name] = st
        log(f"loaded the bake of '{obj.name}' from {path}")
        return st


def check_cache(obj, depsgraph=None) -> str:
    """Look for the object's cache without loading it all; returns a status line.

    Used after a file load: reports a missing, unreadable or stale cache.
    """
    from ..translucency_addon.cache import read_meta
    from ..translucency_addon.errors import TranslucencyError

    settings = obj.translucency
    path = resolve_cache_path(obj)
    if not path:
        return "Not baked"
    try:
        meta = read_meta(path)
    except TranslucencyError as ex:
        return f"Cache problem: {ex}"
    if settings.bake_key and meta.get("key") != settings.bake_key:
        return (f"Stale cache: {path} holds another bake than this object's (key "
                f"{str(meta.get('key'))[:12]} != {settings.bake_key[:12]}); re-bake")
    if depsgraph is not None:
        from ..translucency_addon.bake import BakeSettings

        try:
            baked = BakeSettings(**meta["settings"])
            message = _staleness(obj, depsgraph, (meta.get("stats") or {}).get("graph_key") or meta["key"], baked)
        except Exception as ex:  # noqa: BLE001 - a status line must not raise
            message = f"could not compare the mesh with the bake ({type(ex).__name__}: {ex})"
        if message:
            return f"Stale: {message}"
    return f"Baked (cache found: {os.path.basename(path)})"


def _staleness(obj, depsgraph, key: str, baked_settings) -> str:
    """Why the bake no longer matches the object (empty when it still does).

    ``key``: the QuadGraph key (``single_scattering.graph_key``: a bake holding
    single scattering has a combined key of its own)."""
    from dataclasses import replace

    from ..translucency_addon.bake import mesh_key

    V, F = scene_inputs.evaluated_triangles(obj, depsgraph)
    if mesh_key(V, F, baked_settings) != key:
        return "the mesh changed since it was baked (modifiers included); re-bake to update the graph"
    s = obj.translucency
    wanted = replace(baked_settings, quality=s.quality.lower(), levels=int(s.levels))
    if (wanted.quality, wanted.levels) != (baked_settings.quality, baked_settings.levels):
        return (f"the bake settings changed (baked: {baked_settings.quality}, {baked_settings.levels} levels); "
                "re-bake to apply them")
    return ""


def update_staleness(obj, st: ObjectState, depsgraph) -> str:
    """Re-check staleness when the evaluated geometry changed; cheap otherwise."""
    positions = scene_inputs.evaluated_positions(obj, depsgraph)
    digest = scene_inputs.array_digest(positions) + f"|{obj.translucency.quality}|{obj.translucency.levels}"
    if digest != st.geometry_digest:
        st.geometry_digest = digest
        try:
            from ..translucency_addon.single_scattering import graph_key

            st.stale_message = _staleness(obj, depsgraph, graph_key(st.bake), st.bake.settings)
        except Exception as ex:  # noqa: BLE001
            st.stale_message = f"could not compare the mesh with the bake ({type(ex).__name__}: {ex})"
        if st.stale_message:
            log(f"'{obj.name}': {st.stale_message}", once_key=("stale", obj.name, st.stale_message))
    return st.stale_message


# ------------------------------------------------------------------ attribute


def write_radiance(obj, rgb: np.ndarray, name: str = ATTRIBUTE_NAME) -> None:
    """Write (n, 3) radiance into ``obj.data``'s ``translucency_radiance`` attribute.

    Only the attribute's values change: never the topology, never another
    attribute.  A layer of the wrong type or domain under our name is replaced.
    """
    mesh = obj.data
    n = len(mesh.vertices)
    rgb = np.asarray(rgb, dtype=np.float32)
    if rgb.shape != (n, 3):
        raise ValueError(f"radiance has shape {rgb.shape}, the mesh has {n} vertices")
    attr = mesh.attributes.get(name)
    if attr is not None and (attr.domain != ATTRIBUTE_DOMAIN or attr.data_type != ATTRIBUTE_TYPE):
        mesh.attributes.remove(attr)
        attr = None
    if attr is None:
        attr = mesh.attributes.new(name, ATTRIBUTE_TYPE, ATTRIBUTE_DOMAIN)
    rgba = np.ones((n, 4), dtype=np.float32)
    rgba[:, :3] = np.nan_to_num(rgb, nan=0.0, posinf=0.0, neginf=0.0)
    attr.data.foreach_set("color", rgba.ravel())
    OWN_WRITES.add(obj.name)
    COUNTERS["writes"] += 1
    mesh.update_tag()


def read_radiance(obj, name: str = ATTRIBUTE_NAME) -> np.ndarray | None:
    """The attribute (default: the total radiance) as (n, 3) float32, or None."""
    mesh = obj.data
    attr = mesh.attributes.get(name) if mesh is not None else None
    if attr is None or attr.domain != ATTRIBUTE_DOMAIN or attr.data_type != ATTRIBUTE_TYPE:
        return None
    rgba = np.empty(len(attr.data) * 4, dtype=np.float32)
    attr.data.foreach_get("color", rgba)
    return rgba.reshape(-1, 4)[:, :3].copy()


def remove_attribute(obj, name: str = ATTRIBUTE_NAME) -> bool:
    mesh = obj.data
    attr = mesh.attributes.get(name) if mesh is not None else None
    if attr is None:
        return False
    mesh.attributes.remove(attr)
    mesh.update_tag()
    return True


def _attribute_ok(obj, name: str = ATTRIBUTE_NAME) -> bool:
    attr = obj.data.attributes.get(name)
    return (attr is not None and attr.domain == ATTRIBUTE_DOMAIN and attr.data_type == ATTRIBUTE_TYPE
            and len(attr.data) == len(obj.data.vertices))


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


def _partial_current(solver, result, bake) -> np.ndarray:
    fn = getattr(solver, "surface_partial_current", None)
    if callable(fn):
        return np.asarray(fn(result))
    from ..translucency_addon.fresnel import diffuse_reflectance_internal
    from ..translucency_addon.kernels import outgoing_partial_current

    lv = bake.finest
    return outgoing_partial_current(np.asarray(result.phi[-1])[lv.n_inner:], np.asarray(result.q[-1]),
                                    diffuse_reflectance_internal(solver.eta))


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
    """(len(obj.data.vertices), 3) outgoing radiance for the original mesh's vertices."""
    from ..translucency_addon.diffusion import outgoing_radiance

    bake = st.bake
    n_orig = len(obj.data.vertices)
    if n_orig == len(bake.mesh_vertices):
        dirs = scene_inputs.view_directions(view, np.asarray(bake.mesh_vertices))
        return np.asarray(solver.vertex_radiance(result, dirs))
    _, idx, w, V, N = _original_mapping(obj, st)
    jplus = _partial_current(solver, result, bake)
    j_v = np.einsum("vk,vkc->vc", w, jplus[idx])
    dirs = scene_inputs.view_directions(view, V)
    cos_o = np.ones(len(V)) if dirs is None else np.einsum("vj,vj->v", N, dirs)
    return outgoing_radiance(j_v, cos_o, solver.eta)


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
        return (not force and view_sig == st.view_sig and _attribute_ok(obj)
                and (not (use_ss and split) or _attribute_ok(obj, SS_ATTRIBUTE_NAME)))

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
