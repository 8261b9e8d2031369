# SPDX-License-Identifier: GPL-3.0-or-later
"""``translucency.bake``, ``translucency.bake_single_scattering`` and ``translucency.free_bake``.

The bake runs on the active mesh object's **evaluated** mesh (modifiers
applied, loop triangles, object space).  In the UI it is a modal operator:
the engine bake runs in a background thread, a window-manager timer polls
it, the progress bar and the status bar show the stage, and Esc cancels.
The engine checks for cancellation between its stages; fTetWild's own
tetrahedralization is one C++ call that cannot be interrupted, so an Esc
pressed during it takes effect when it returns.

In background mode (``blender -b``, bpy from PyPI, tests) a modal timer never
fires, so :meth:`execute` runs the same :class:`BakeJob` synchronously.

Single scattering (Bernabei et al.) is baked by ``translucency.bake`` too
when the object's "Single Scattering" setting is on: after the QuadGraph, in
the same job, with its own stage names ("single scattering: optical depth",
...).  ``translucency.bake_single_scattering`` re-bakes only the
single-scattering samples onto the existing QuadGraph (same job, modal
progress, cancel and undo rules): the optical depth depends on sigma_t, so a
material, field or scale change needs a single-scattering re-bake, but the
QuadGraph (fTetWild, the slow part) does not depend on the material.  The
heterogeneity field is sampled on the main thread at the voxel centres
before the job starts (Blender textures are not evaluated off the main
thread).  The cache file name carries the combined key (QuadGraph and
single-scattering inputs), so undo returns to a file that still exists.

An object that lists **inner parts** (:mod:`.inner_parts`) bakes as one
assembly: its parts are read on the main thread (each evaluated mesh moved
into the object's space), the engine's ``composite_bake.bake_composite``
runs in the job (the Voxel Number Map first, so that every refusal --
parts outside or overlapping, a cavity open to the outside, a map over its
budget -- comes before the long QuadGraph bake; then the QuadGraph with the
cavities carved, the cavity exchange and the node labels), and single
scattering, when on, is baked from the assembly's voxels
(``voxelise_composite``), so it knows the parts.

Nothing in the scene changes until the bake has succeeded: the cache is
written to ``<name>.npz.partial`` (atomically, by the engine) and renamed to
its final name by :meth:`BakeJob.commit` on the main thread, together with
the settings, statistics and runtime state.  On cancel or failure the
partial file (and a cache folder the bake created) is removed and no
property, attribute or file is left behind.
"""

from __future__ import annotations

import os
import threading
import time

import bpy
import numpy as np
from bpy.props import BoolProperty, IntProperty

from . import attributes, cache_files, inner_parts, runtime, scene_inputs, state, status
from .status import SS_STAGE_NAMES

# Test seam: callables ``(fraction, stage) -> bool | None``; returning False cancels the bake.
PROGRESS_LISTENERS: list = []
TETWILD_NOTE = ("fTetWild's tetrahedralization is one uninterruptible step: if it is running, the bake "
                "stops as soon as it returns")

_RUNNING: dict[str, "BakeJob"] = {}  # object name -> job (one bake per object at a time)


SS_SHARE = 0.4  # share of the progress bar the single-scattering stages take in a full bake


class SSJobInputs:
    """What the single-scattering part of a bake needs, gathered on the main thread."""

    def __init__(self, settings, material, field, field_fp, key: str, extra_inputs=None):
        self.settings = settings
        self.material = material
        self.field = field  # a GridField (sampled on the main thread) or None
        self.field_fp = field_fp
        self.key = key  # the final key of the bake (QuadGraph + single scattering)
        self.extra_inputs = extra_inputs  # what else the optical depth is made of (the inner parts' media)


class BakeJob:
    """One bake: inputs gathered on the main thread, the engine bake in ``run``,
    the scene changed only in ``commit`` (main thread).

    ``ss``: :class:`SSJobInputs` to bake single scattering too; ``base_bake``:
    an existing QuadGraph bake to bake single scattering onto (no QuadGraph bake);
    ``composite``: :class:`.inner_parts.BakeInputs` of an object with inner parts.
    """

    def __init__(self, obj_name: str, V, F, settings, final_path: str, notes: list[str], ss: SSJobInputs | None = None,
                 base_bake=None, composite=None, material=None):
        self.obj_name = obj_name
        self.material = material  # the object's material: what the cache keeps of it (None: nothing)
        self.ss = ss
        self.base_bake = base_bake
        self.composite = composite
        self.needs_ss = ""  # why single scattering is baked although its switch is off ('' when it is on or not needed)
        self.ss_seconds = 0.0
        self.V, self.F = V, F
        self.settings = settings
        self.final_path = final_path
        self.tmp_path = final_path + ".partial"
        self.notes = list(notes)
        self.lock = threading.Lock()
        self.cancel_requested = False
        self.fraction = 0.0
        self.stage = "starting"
        self.done = False
        self.error: BaseException | None = None
        self.bake = None
        self.thread: threading.Thread | None = None
        self.t0 = time.perf_counter()
        self.seconds = 0.0
        directory = os.path.dirname(final_path)
        self.created_dir = directory if not os.path.isdir(directory) else None

    # -- worker -----------------------------------------------------------------
    def progress(self, fraction: float, stage: str) -> bool:
        # A progress bar never steps back: stage weights summed in floating point can give a stage's
        # end as 0.44 and the next stage's start as 0.43999999999999995.
        fraction = max(float(fraction), self.fraction)
        self.fraction, self.stage = fraction, str(stage)
        for listener in list(PROGRESS_LISTENERS):
            if listener(fraction, stage) is False:
                self.cancel_requested = True
        return not self.cancel_requested

    def run(self) -> None:
        from ..translucency_addon.quadgraph import bake as bake_mod
        from ..translucency_addon.cache import save_bake
        from ..translucency_addon.errors import BakeCancelled

        try:
            if self.base_bake is None:
                share = 1.0 - SS_SHARE if self.ss is not None else 1.0

                def progress(f, st):
                    if not self.progress(share * f, st):  # the map's stages ignore a False: raise
                        raise BakeCancelled("bake cancelled")
                    return True

                if self.composite is not None:
                    bake = inner_parts.bake(self.composite, self.settings, progress=progress)
                else:
                    bake = bake_mod.bake_mesh(self.V, self.F, self.settings, progress=progress)
            else:
                bake = self.base_bake
            if self.cancel_requested:
                raise BakeCancelled("bake cancelled")
            if self.base_bake is None and self.material is not None:
                self.stage = "spectral bounds"  # the material's, kept in the cache: a cold frame runs no Lanczos
                from ..translucency_addon.diffusion.baked_bounds import with_kept_bounds

                bake = with_kept_bounds(bake, self.material)
                if self.cancel_requested:
                    raise BakeCancelled("bake cancelled")
            if self.ss is not None:
                bake = self._bake_single_scattering(bake)
            self.stage = "writing cache"
            save_bake(self.tmp_path, bake, etas=() if self.eta is None else (self.eta,))
            with self.lock:
                if self.cancel_requested:
                    raise BakeCancelled("bake cancelled")
                self.bake = bake
        except BaseException as ex:  # noqa: BLE001 - reported on the main thread
            self.error = ex
            self.cleanup()
        finally:
            self.seconds = time.perf_counter() - self.t0
            self.done = True

    @property
    def eta(self) -> float | None:
        """The material's index of refraction: its transport tables go into the cache (None: no material)."""
        return None if self.material is None else float(self.material.eta)

    def _bake_single_scattering(self, bake):
        from ..translucency_addon.errors import BakeCancelled, TranslucencyError
        from ..translucency_addon.single_scattering import attach, bake_single_scattering_for

        base = 1.0 - SS_SHARE if self.base_bake is None else 0.0
        span = 1.0 - base

        def progress(fraction, stage):
            if not self.progress(base + span * fraction, "single scattering: " + SS_STAGE_NAMES.get(stage, stage)):
                raise BakeCancelled("bake cancelled")

        t0 = time.perf_counter()
        kw = {}
        if self.composite is not None:  # from the assembly's voxels: the samples know the inner parts
            from ..translucency_addon.single_scattering.volume import voxelise_composite

            V, F, _ = inner_parts.outer_mesh(bake)
            volume = voxelise_composite(self.composite.composite, resolution=self.ss.settings.quality,
                                        mm_per_unit=bake.mm_per_unit, walls=False)
            kw = dict(volume=volume, mesh=(V, F), extra_inputs=self.ss.extra_inputs)
        data = bake_single_scattering_for(bake, self.ss.material, self.ss.field, self.ss.settings, progress=progress,
                                          field_fingerprint=self.ss.field_fp, **kw)
        self.ss_seconds = time.perf_counter() - t0
        out = attach(bake, data)
        if out.key != self.ss.key:  # the file name was chosen from the key expected before the bake
            raise TranslucencyError("internal error: the single-scattering key differs from the expected one")
        return out

    def start(self) -> None:
        self.thread = threading.Thread(target=self.run, name=f"translucency-bake-{self.obj_name}", daemon=True)
        self.thread.start()

    def wait(self, timeout: float | None = None) -> bool:
        if self.thread is not None:
            self.thread.join(timeout)
        return self.done

    def request_cancel(self) -> None:
        with self.lock:
            self.cancel_requested = True
            if self.done and self.bake is not None:
                self.bake = None
                self.cleanup()

    def cleanup(self) -> None:
        """Remove everything this job wrote (the partial cache, a folder it created)."""
        for path in (self.tmp_path,):
            try:
                if os.path.exists(path):
                    os.remove(path)
            except OSError:
                pass
        if self.created_dir:
            try:
                os.rmdir(self.created_dir)  # only if empty
            except OSError:
                pass

    @property
    def cancelled(self) -> bool:
        from ..translucency_addon.errors import BakeCancelled

        return isinstance(self.error, BakeCancelled) or (self.done and self.cancel_requested and self.bake is None)

    # -- main thread --------------------------------------------------------------
    def commit(self, context) -> list[tuple[str, str]]:
        """Apply a finished bake to the scene; returns ``[(level, message)]`` to report."""
        from ..translucency_addon.quadgraph.bake import format_stats
        from ..translucency_addon.errors import TranslucencyError

        obj = bpy.data.objects.get(self.obj_name)
        if obj is None or obj.type != 'MESH':
            self.cleanup()
            raise TranslucencyError(f"object '{self.obj_name}' was removed during the bake; nothing was saved")
        bake = self.bake
        os.replace(self.tmp_path, self.final_path)
        s = obj.translucency
        s.cache_filepath = cache_files.stored_cache_path(self.final_path)  # the link to the cache: settings
        s.bake_key = bake.key
        graph_seconds = float(self.seconds - self.ss_seconds) if self.base_bake is None else s.status.bake_seconds
        warnings = status.set_bake_status(obj, bake, graph_seconds=graph_seconds, ss_seconds=self.ss_seconds,
                                          notes=self.notes)
        s.enabled = True
        turned_on = bool(self.needs_ss) and bake.single_scattering is not None
        if turned_on:  # baked because the material needs it: the switch follows, or the plan leaves it out
            s.use_single_scattering = True
        state.install_state(obj, bake, self.final_path)
        ss = bake.single_scattering
        done = s.status
        state.log(f"baked '{obj.name}' -> {self.final_path}\n{format_stats(bake)}"
                  + (f"\nsingle scattering: {done.ss_bake_stats}" if ss is not None else ""))
        if self.base_bake is not None:
            messages = [('INFO', f"Baked single scattering of '{obj.name}' in {self.seconds:.1f} s: "
                                 f"{done.ss_bake_stats}")]
        else:
            messages = [('INFO', f"Baked '{obj.name}' in {self.seconds:.1f} s: {done.bake_stats}"
                         + (f"; single scattering: {done.ss_bake_stats}" if ss is not None else ""))]
        messages += [('WARNING', f"'{obj.name}': {w}") for w in warnings]
        if turned_on:
            messages.append(('INFO', f"'{obj.name}': Single Scattering was off; it is baked and turned on because "
                                     f"{self.needs_ss}; turn it "
                                     "off in the Translucency panel to leave it out"))
        if s.packed_cache:  # the packed copy follows the bake
            name, size = cache_files.pack_cache(obj)
            messages.append(('INFO', f"'{obj.name}': the new cache is packed into the .blend ({size / 2**20:.1f} MiB)"))
        try:
            report = runtime.solve_object(obj, context.scene, context.evaluated_depsgraph_get(), force=True)
        except TranslucencyError as ex:
            messages.append(('WARNING', f"'{obj.name}' baked, but the first solve failed: {ex}"))
        else:
            if report is not None:
                messages.append(('WARNING' if report.skipped else 'INFO', report.describe()))
        return messages


def _check_object(obj) -> None:
    from ..translucency_addon.errors import MeshError

    if obj is None or obj.type != 'MESH':
        raise MeshError("select a mesh object to bake")
    if obj.mode == 'EDIT':
        raise MeshError(f"'{obj.name}' is in Edit Mode: switch to Object Mode to bake it")
    if obj.name in _RUNNING and not _RUNNING[obj.name].done:
        raise MeshError(f"'{obj.name}' is already being baked")


def _ss_inputs(obj, depsgraph, V, graph_key: str, mm: float, parts: bool = False) -> SSJobInputs:
    """Single-scattering inputs (main thread): settings, material, the field sampled on the voxel grid, the key
    (``parts``: baked with the inner parts, whose media it records)."""
    from ..translucency_addon.single_scattering import expected_key

    s = obj.translucency
    settings = scene_inputs.ss_settings(s)
    material = scene_inputs.build_material(s)
    field_fp = scene_inputs.ss_field_fingerprint(obj, s, depsgraph) if material.heterogeneous else None
    field = scene_inputs.ss_field_sampler(obj, s, depsgraph, V, settings.quality) if material.heterogeneous else None
    extra = inner_parts.ss_inputs(inner_parts.part_media(obj)) if parts else None
    key = expected_key(graph_key, settings, material, field_fp=field_fp, mm_per_unit=mm, extra_inputs=extra)
    return SSJobInputs(settings, material, field, field_fp, key, extra)


def _check_writable(directory: str) -> None:
    """Refuse, before any work, a cache directory this machine cannot write (a read-only farm share)."""
    from ..translucency_addon.errors import CacheError

    problem = cache_files.unwritable(directory)
    if problem:
        raise CacheError(problem)


def prepare_job(context, obj, base_triangles: int = 0) -> BakeJob:
    """Gather the bake's inputs on the main thread (raises ``TranslucencyError``)."""
    from ..translucency_addon.quadgraph import bake as bake_mod
    from ..translucency_addon.diffusion.sky_visibility import DEFAULT_DIRECTIONS

    _check_object(obj)
    scene = context.scene
    s = obj.translucency
    depsgraph = context.evaluated_depsgraph_get()
    V, F = scene_inputs.evaluated_triangles(obj, depsgraph)
    mm, scale_warning = scene_inputs.mm_per_unit(obj, scene)
    settings = bake_mod.BakeSettings(quality=s.quality.lower(), levels=int(s.levels), mm_per_unit=mm,
                                     base_triangles=int(base_triangles) or None,
                                     sky_directions=DEFAULT_DIRECTIONS if s.sky_occlusion else 0)
    settings.resolved()  # raises MeshError for impossible settings
    composite = inner_parts.bake_inputs(obj, depsgraph, V, F, settings) if inner_parts.listed(obj) else None
    key = composite.key if composite is not None else bake_mod.mesh_key(V, F, settings)
    needs_ss = "" if s.use_single_scattering or composite is not None else _single_scattering_needed(s, V, mm)
    ss = (_ss_inputs(obj, depsgraph, V, key, mm, parts=composite is not None)
          if s.use_single_scattering or needs_ss else None)
    if ss is not None:
        key = ss.key
    directory, note = cache_files.cache_directory(scene)
    _check_writable(directory)
    final = os.path.join(directory, cache_files.cache_file_name(obj.name, key))
    notes = [w for w in (scale_warning, note) if w]
    job = BakeJob(obj.name, V, F, settings, final, notes, ss=ss, composite=composite, material=_bake_material(s))
    job.needs_ss = needs_ss
    return job


def _bake_material(settings):
    """The object's material, for what the cache keeps of it (the transport tables of its index of refraction,
    its systems' spectral bounds); None (nothing kept: the first frame computes them) when the material does
    not build -- the bake itself does not need it."""
    from ..translucency_addon.errors import TranslucencyError

    try:
        return scene_inputs.build_material(settings)
    except TranslucencyError:
        return None


def _single_scattering_needed(settings, V, mm: float) -> str:
    """Why the object's material needs single scattering although its switch is off ('' when it does not):
    the engine's :func:`~translucency_addon.frame.single_scattering_needed` on the material and the
    object's smallest extent (an object with inner parts hands such media to the Voxel Number Map)."""
    from ..translucency_addon.frame import single_scattering_needed

    thickness = float(np.min(np.ptp(np.asarray(V, dtype=np.float64), axis=0))) * mm
    return single_scattering_needed(scene_inputs.build_material(settings), thickness)


def prepare_ss_job(context, obj) -> BakeJob:
    """Inputs of a single-scattering-only bake onto the object's existing QuadGraph (main thread)."""
    from ..translucency_addon.errors import CacheError

    _check_object(obj)
    scene = context.scene
    depsgraph = context.evaluated_depsgraph_get()
    if not state.is_baked(obj):
        raise CacheError(f"'{obj.name}' has no QuadGraph bake yet: press Bake (it bakes single scattering too)")
    st = cache_files.ensure_state(obj, retry=True)
    cache_files.update_staleness(obj, st, depsgraph)
    if st.stale_message:
        raise CacheError(f"the QuadGraph of '{obj.name}' is stale ({st.stale_message}); press Bake, which bakes "
                         "both")
    mm, scale_warning = scene_inputs.mm_per_unit(obj, scene)
    base = st.bake.with_scale(mm)
    from ..translucency_addon.single_scattering import graph_key

    V, F, _ = inner_parts.outer_mesh(base)
    composite = None
    if base.composite is not None:  # the parts as baked (the bake is not stale): their voxels for the samples
        composite = inner_parts.bake_inputs(obj, depsgraph, V, F, base.settings)
    ss = _ss_inputs(obj, depsgraph, V, graph_key(base), mm, parts=composite is not None)
    directory, note = cache_files.cache_directory(scene)
    _check_writable(directory)
    final = os.path.join(directory, cache_files.cache_file_name(obj.name, ss.key))
    notes = [w for w in (scale_warning, note) if w]
    return BakeJob(obj.name, V, F, base.settings, final, notes, ss=ss, base_bake=base, composite=composite,
                   material=_bake_material(obj.translucency))


def _error_text(obj_name: str, ex: BaseException) -> str:
    from ..translucency_addon.errors import TranslucencyError

    if isinstance(ex, TranslucencyError):
        return f"Cannot bake '{obj_name}': {ex}"
    return f"Bake of '{obj_name}' failed: {type(ex).__name__}: {ex}"


class _ModalBake:
    """Shared by the bake operators: synchronous ``execute`` (background mode, scripts) and a modal
    ``invoke`` (UI: a worker thread, progress bar, status text with the stage, Esc cancels)."""

    def _prepare(self, context, obj) -> BakeJob:
        raise NotImplementedError

    @classmethod
    def poll(cls, context):
        obj = context.active_object
        return obj is not None and obj.type == 'MESH'

    # -- synchronous (background mode, scripts) ---------------------------------
    def execute(self, context):
        obj = context.active_object
        name = obj.name if obj is not None else "?"
        try:
            job = self._prepare(context, obj)
        except Exception as ex:  # noqa: BLE001 - reported to the user
            self.report({'ERROR'}, _error_text(name, ex))
            return {'CANCELLED'}
        job.run()
        return self._finish(context, job)

    # -- modal (UI) ----------------------------------------------------------------
    def invoke(self, context, event):
        if bpy.app.background or context.window is None:
            return self.execute(context)
        obj = context.active_object
        try:
            job = self._prepare(context, obj)
        except Exception as ex:  # noqa: BLE001 - reported to the user
            self.report({'ERROR'}, _error_text(obj.name if obj else "?", ex))
            return {'CANCELLED'}
        self._job = job
        _RUNNING[job.obj_name] = job
        job.start()
        wm = context.window_manager
        self._timer = wm.event_timer_add(0.1, window=context.window)
        wm.progress_begin(0, 100)
        wm.modal_handler_add(self)
        self._set_text(context, f"Translucency: baking '{job.obj_name}': starting (Esc to cancel)")
        return {'RUNNING_MODAL'}

    def modal(self, context, event):
        job = self._job
        if event.type == 'ESC' and event.value == 'PRESS':
            if not job.cancel_requested:
                job.request_cancel()
                note = TETWILD_NOTE if job.stage == "tetrahedralize" else "stopping at the next stage"
                self.report({'INFO'}, f"Cancelling the bake of '{job.obj_name}': {note}")
            return {'RUNNING_MODAL'}
        if event.type == 'TIMER':
            context.window_manager.progress_update(int(100 * job.fraction))
            state = "cancelling" if job.cancel_requested else f"{job.stage} {100 * job.fraction:.0f}%"
            extra = f" ({TETWILD_NOTE})" if job.cancel_requested and job.stage == "tetrahedralize" else ""
            self._set_text(context, f"Translucency: baking '{job.obj_name}': {state}{extra} - Esc to cancel")
            if job.done:
                self._end_ui(context)
                return self._finish(context, job)
        return {'PASS_THROUGH'}

    def cancel(self, context):
        # Blender cancels modal operators on file load / quit: stop and clean up.
        job = getattr(self, "_job", None)
        if job is not None:
            job.request_cancel()
        self._end_ui(context)

    # -- shared ------------------------------------------------------------------------
    def _finish(self, context, job: BakeJob):
        _RUNNING.pop(job.obj_name, None)
        if job.cancelled:
            job.cleanup()
            self.report({'WARNING'}, f"Bake of '{job.obj_name}' cancelled; nothing was changed")
            return {'CANCELLED'}
        if job.error is not None:
            job.cleanup()
            self.report({'ERROR'}, _error_text(job.obj_name, job.error))
            return {'CANCELLED'}
        try:
            messages = job.commit(context)
        except Exception as ex:  # noqa: BLE001 - reported to the user, the job's files cleaned up
            job.cleanup()
            self.report({'ERROR'}, _error_text(job.obj_name, ex))
            return {'CANCELLED'}
        for level, message in messages:
            self.report({level}, message)
        return {'FINISHED'}

    def _set_text(self, context, text) -> None:
        workspace = getattr(context, "workspace", None)
        if workspace is not None:
            workspace.status_text_set(text)
        if context.area is not None:
            context.area.header_text_set(text)

    def _end_ui(self, context) -> None:
        wm = context.window_manager
        timer = getattr(self, "_timer", None)
        if timer is not None:
            wm.event_timer_remove(timer)
            self._timer = None
        wm.progress_end()
        workspace = getattr(context, "workspace", None)
        if workspace is not None:
            workspace.status_text_set(None)
        if context.area is not None:
            context.area.header_text_set(None)


class TRANSLUCENCY_OT_bake(_ModalBake, bpy.types.Operator):
    """Bake the QuadGraph of the active mesh object (after modifiers) for subsurface scattering, and the single-scattering samples when Single Scattering is on. Esc cancels"""

    bl_idname = "translucency.bake"
    bl_label = "Bake"
    bl_options = {'REGISTER', 'UNDO'}

    base_triangles: IntProperty(
        name="Base Triangles",
        description="Triangles of the coarsest level's resampled surface (0: the quality preset's)",
        default=0,
        min=0,
        options={'SKIP_SAVE', 'HIDDEN'},
    )

    def _prepare(self, context, obj) -> BakeJob:
        return prepare_job(context, obj, self.base_triangles)


class TRANSLUCENCY_OT_bake_single_scattering(_ModalBake, bpy.types.Operator):
    """Re-bake only the single-scattering samples (RBF optical depth) onto the existing QuadGraph: needed after a change of the material, its field, the scale or the single-scattering settings. Esc cancels"""

    bl_idname = "translucency.bake_single_scattering"
    bl_label = "Bake Single Scattering"
    bl_options = {'REGISTER', 'UNDO'}

    @classmethod
    def poll(cls, context):
        obj = context.active_object
        return obj is not None and obj.type == 'MESH' and state.is_baked(obj)

    def _prepare(self, context, obj) -> BakeJob:
        return prepare_ss_job(context, obj)


class TRANSLUCENCY_OT_free_bake(bpy.types.Operator):
    """Remove the active object's bake: the cache reference, the solver (GPU memory) and the radiance attribute"""

    bl_idname = "translucency.free_bake"
    bl_label = "Free Bake"
    bl_options = {'REGISTER', 'UNDO'}

    delete_cache_file: BoolProperty(
        name="Delete Cache File",
        description="Also delete the cache file from disk (undo cannot bring it back)",
        default=False,
    )

    @classmethod
    def poll(cls, context):
        obj = context.active_object
        return obj is not None and obj.type == 'MESH'

    def execute(self, context):
        obj = context.active_object
        s = obj.translucency
        path = cache_files.resolve_cache_path(obj)
        state.drop_state(obj.name)
        removed_attr = attributes.remove_attribute(obj)
        removed_attr = attributes.remove_attribute(obj, attributes.SS_ATTRIBUTE_NAME) or removed_attr
        had_bake = bool(s.cache_filepath or s.bake_key)
        cache_files.unpack_cache(obj)
        s.cache_filepath = ""
        s.bake_key = ""
        status.clear_bake_status(obj)
        deleted = False
        if self.delete_cache_file and path and os.path.isfile(path):
            os.remove(path)
            deleted = True
        if not had_bake and not removed_attr:
            self.report({'INFO'}, f"'{obj.name}' had no bake")
        else:
            self.report({'INFO'}, f"Freed the bake of '{obj.name}'" + (f" and deleted {path}" if deleted else ""))
        return {'FINISHED'}


class TRANSLUCENCY_OT_pack_cache(bpy.types.Operator):
    """Pack the active object's bake cache into the .blend (for render farms that take a single file), or unpack it.
    The .blend grows by the cache's size x 4/3"""

    bl_idname = "translucency.pack_cache"
    bl_label = "Pack Cache into .blend"
    bl_options = {'REGISTER', 'UNDO'}

    unpack: BoolProperty(
        name="Unpack",
        description="Remove the packed copy from the .blend (the cache file stays where it is)",
        default=False,
    )

    @classmethod
    def poll(cls, context):
        obj = context.active_object
        return obj is not None and obj.type == 'MESH' and state.is_baked(obj)

    def execute(self, context):
        from ..translucency_addon.errors import TranslucencyError

        obj = context.active_object
        if self.unpack:
            removed = cache_files.unpack_cache(obj)
            self.report({'INFO'}, f"'{obj.name}': " + ("the packed cache was removed from the .blend" if removed
                                                       else "nothing was packed"))
            return {'FINISHED'}
        try:
            name, size = cache_files.pack_cache(obj)
        except TranslucencyError as ex:
            self.report({'ERROR'}, f"Cannot pack the cache of '{obj.name}': {ex}")
            return {'CANCELLED'}
        self.report({'INFO'}, f"'{obj.name}': cache packed into the .blend ({size / 2**20:.1f} MiB, Text '{name}'); "
                              "save the .blend; a worker without the cache folder reads it from there")
        return {'FINISHED'}


CLASSES = (TRANSLUCENCY_OT_bake, TRANSLUCENCY_OT_bake_single_scattering, TRANSLUCENCY_OT_free_bake,
           TRANSLUCENCY_OT_pack_cache)
