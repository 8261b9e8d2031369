# SPDX-License-Identifier: GPL-3.0-or-later
"""``translucency.bake`` / ``translucency.free_bake`` in headless Blender.

Also holds the small helpers the other ``test_ops_*`` files import:
:func:`sphere`, :func:`add_light`, :func:`bake` and the :func:`memo_bakes`
fixture (an engine bake memoised by its key, so tests that are not about the
bake itself do not run fTetWild again; tests about the bake call the real
engine).
"""

from __future__ import annotations

import math
import os

import bpy
import numpy as np
import pytest

from conftest import factory_reset

BASE_TRIANGLES = 300  # small graphs: a 2-level draft bake of an icosphere takes ~2 s

# --------------------------------------------------------------------------- helpers

_MEMO: dict = {}


class BakeCounter:
    """Wraps the engine's ``bake_mesh``: ``calls`` counts every bake the operator asked for,
    ``real`` those that ran fTetWild (the others came from the memo)."""

    def __init__(self, original, memo: bool):
        self.original = original
        self.memo = memo
        self.calls = 0
        self.real = 0

    def __call__(self, V, F, settings, progress=None):
        from translucency.translucency_addon.quadgraph import bake as bake_mod

        self.calls += 1
        key = bake_mod.mesh_key(V, F, settings)
        if self.memo and key in _MEMO:
            if progress is not None and progress(1.0, "done") is False:
                from translucency.translucency_addon.errors import BakeCancelled

                raise BakeCancelled("bake cancelled")
            return _MEMO[key].with_scale(settings.mm_per_unit)
        self.real += 1
        result = self.original(V, F, settings, progress=progress)
        _MEMO[key] = result
        return result


@pytest.fixture
def memo_bakes(monkeypatch):
    """Memoised engine bakes (same mesh + settings -> the same graph, no fTetWild)."""
    from translucency.translucency_addon.quadgraph import bake as bake_mod

    counter = BakeCounter(bake_mod.bake_mesh, memo=True)
    monkeypatch.setattr(bake_mod, "bake_mesh", counter)
    return counter


@pytest.fixture
def real_bakes(monkeypatch):
    """Counts real engine bakes."""
    from translucency.translucency_addon.quadgraph import bake as bake_mod

    counter = BakeCounter(bake_mod.bake_mesh, memo=False)
    monkeypatch.setattr(bake_mod, "bake_mesh", counter)
    return counter


@pytest.fixture
def cache_dir(blender, tmp_path):
    """Point the scene's cache directory at a fresh folder (the .blend is unsaved)."""
    directory = tmp_path / "cache"
    bpy.context.scene.translucency.cache_directory = str(directory) + os.sep
    return directory


def activate(obj) -> None:
    for other in bpy.context.view_layer.objects:
        other.select_set(False)
    obj.select_set(True)
    bpy.context.view_layer.objects.active = obj


def sphere(name="Blob", radius=1.0, subdivisions=2, location=(0.0, 0.0, 0.0), subsurf=0):
    """An icosphere mesh object (Blender's ``subdivisions=2``: 42 vertices, 80 triangles)."""
    bpy.ops.mesh.primitive_ico_sphere_add(subdivisions=subdivisions, radius=radius, location=location)
    obj = bpy.context.object
    obj.name = name
    obj.data.name = name
    if subsurf:
        obj.modifiers.new("Subdivision", 'SUBSURF').levels = subsurf
    s = obj.translucency
    s.quality = 'DRAFT'
    s.levels = 2
    s.use_mm_per_unit_override = True
    s.mm_per_unit = 10.0  # a 2 cm marble ball: diffusion lengths of a few graph spacings
    return obj


def add_light(kind='POINT', location=(3.0, 0.0, 2.0), energy=1000.0, name=None, rotation=(0.0, 0.0, 0.0)):
    data = bpy.data.lights.new(name or kind.lower(), kind)
    data.energy = energy
    if kind in {'POINT', 'SPOT'}:
        data.shadow_soft_size = 0.0
    obj = bpy.data.objects.new(name or kind.lower(), data)
    obj.location = location
    obj.rotation_euler = rotation
    bpy.context.scene.collection.objects.link(obj)
    return obj


def bake(obj, base_triangles=BASE_TRIANGLES):
    activate(obj)
    return bpy.ops.translucency.bake(base_triangles=base_triangles)


def radiance(obj) -> np.ndarray:
    from translucency.ops import attributes

    return attributes.read_radiance(obj)


def mesh_snapshot(obj):
    me = obj.data
    co = np.empty(len(me.vertices) * 3)
    me.vertices.foreach_get("co", co)
    return (len(me.vertices), len(me.polygons), co.tobytes(),
            sorted(a.name for a in me.attributes if not a.name.startswith(".")))


def settings_snapshot(obj):
    s = obj.translucency
    return {p.identifier: (tuple(getattr(s, p.identifier)) if p.type == 'FLOAT' and p.is_array
                           else getattr(s, p.identifier) if p.type != 'COLLECTION' else len(getattr(s, p.identifier)))
            for p in s.bl_rna.properties if p.identifier not in {"rna_type", "field_texture"}}


def files_in(directory) -> list[str]:
    if not os.path.isdir(directory):
        return []
    return sorted(os.listdir(directory))


# --------------------------------------------------------------------------- the bake


def test_bake_evaluated_mesh_with_modifier(blender, addon, cache_dir, real_bakes):
    """The operator bakes the mesh after modifiers, headless, and fills the statistics."""
    from translucency.ops import cache_files
    from translucency.translucency_addon.cache import load_bake

    obj = sphere(subsurf=1)
    add_light()
    evaluated = obj.evaluated_get(bpy.context.evaluated_depsgraph_get()).data
    n_eval, n_orig = len(evaluated.vertices), len(obj.data.vertices)
    assert n_eval > n_orig  # the modifier changes the topology

    assert bake(obj) == {'FINISHED'}
    assert real_bakes.real == 1
    s = obj.translucency
    assert s.enabled and s.status.bake_status == "Baked" and len(s.bake_key) == 64
    assert len(s.status.bake_levels) == 2
    for level in s.status.bake_levels:
        assert level.n_surface > 50 and level.n_inner > 50
    assert s.status.bake_levels[1].n_surface > s.status.bake_levels[0].n_surface
    assert s.status.bake_memory > 0.1 and s.status.bake_seconds > 0.0 and s.status.bake_vertices == n_eval
    assert "N_s" in s.status.bake_stats and "N_i" in s.status.bake_stats and "MiB" in s.status.bake_stats

    path = cache_files.resolve_cache_path(obj)
    assert os.path.dirname(path) == str(cache_dir)
    assert files_in(cache_dir) == [os.path.basename(path)]  # no partial file left
    assert os.path.basename(path).startswith("Blob_")
    loaded = load_bake(path, expected_key=s.bake_key)
    assert len(loaded.mesh_vertices) == n_eval  # the evaluated mesh was baked

    # The first solve ran: the attribute lives on the original mesh, one value per vertex.
    rgb = radiance(obj)
    assert rgb.shape == (n_orig, 3) and np.all(np.isfinite(rgb)) and rgb.max() > 0
    # The cache keeps the material's spectral bounds (diffusion/baked_bounds.py), and the frame's solver,
    # at the scene's scale, took them instead of running Lanczos.
    from translucency.ops import state

    assert loaded.spectral_bounds is not None and "spectral bounds" in loaded.stats["timings"]
    assert state.get_state(obj).solver.bounds_from_bake == len(loaded.levels)


def test_unsaved_blend_uses_a_temporary_folder_and_says_so(blender, addon, memo_bakes):
    import tempfile

    from translucency.ops import cache_files

    obj = sphere()
    assert bake(obj) == {'FINISHED'}
    path = cache_files.resolve_cache_path(obj)
    assert path.startswith(tempfile.gettempdir())
    assert "not saved" in obj.translucency.status.bake_warnings
    os.remove(path)


def _assert_unchanged(obj, before_mesh, before_settings, cache_dir, names):
    assert sorted(o.name for o in bpy.data.objects) == names
    assert mesh_snapshot(obj) == before_mesh
    assert settings_snapshot(obj) == before_settings
    assert obj.data.attributes.get("translucency_radiance") is None
    assert files_in(cache_dir) == []
    from translucency.ops import state

    assert state.get_state(obj) is None


def test_flat_mesh_fails_and_leaves_the_scene_unchanged(blender, addon, cache_dir):
    bpy.ops.mesh.primitive_plane_add(size=2.0)
    obj = bpy.context.object
    obj.translucency.quality = 'DRAFT'
    names = sorted(o.name for o in bpy.data.objects)
    before_mesh, before_settings = mesh_snapshot(obj), settings_snapshot(obj)
    with pytest.raises(RuntimeError, match=r"Cannot bake 'Plane': mesh is flat .*encloses no volume"):
        bake(obj)
    _assert_unchanged(obj, before_mesh, before_settings, cache_dir, names)


def test_nan_vertex_fails_and_leaves_the_scene_unchanged(blender, addon, cache_dir):
    obj = sphere()
    obj.data.vertices[3].co = (float("nan"), 0.0, 0.0)
    names = sorted(o.name for o in bpy.data.objects)
    before_mesh, before_settings = mesh_snapshot(obj), settings_snapshot(obj)
    with pytest.raises(RuntimeError, match=r"Cannot bake 'Blob': mesh has 1 vertices with NaN or Inf"):
        bake(obj)
    _assert_unchanged(obj, before_mesh, before_settings, cache_dir, names)


def test_cancel_leaves_nothing_behind(blender, addon, cache_dir, real_bakes, monkeypatch):
    """The engine's progress callback returning False (Esc in the UI) cancels the bake."""
    from translucency.ops import operators_bake

    obj = sphere()
    names = sorted(o.name for o in bpy.data.objects)
    before_mesh, before_settings = mesh_snapshot(obj), settings_snapshot(obj)
    stages = []

    def cancel_after_tetrahedralize(fraction, stage):
        stages.append(stage)
        return stage != "levels"

    monkeypatch.setattr(operators_bake, "PROGRESS_LISTENERS", [cancel_after_tetrahedralize])
    assert bake(obj) == {'CANCELLED'}
    assert "tetrahedralize" in stages and stages[-1] == "levels"
    _assert_unchanged(obj, before_mesh, before_settings, cache_dir, names)


def test_threaded_job_cancel_after_the_cache_was_written(blender, addon, cache_dir, memo_bakes):
    """The modal path: the job runs in a thread; a cancel that arrives after the
    partial cache was written still leaves nothing."""
    from translucency.ops import operators_bake

    obj = sphere()
    before_settings = settings_snapshot(obj)
    job = operators_bake.prepare_job(bpy.context, obj, BASE_TRIANGLES)
    job.start()
    assert job.wait(120)
    assert job.error is None and os.path.exists(job.tmp_path)
    job.request_cancel()
    assert job.cancelled
    assert files_in(cache_dir) == []
    assert settings_snapshot(obj) == before_settings

    # The same path to the end: a threaded bake commits like the synchronous one.
    job = operators_bake.prepare_job(bpy.context, obj, BASE_TRIANGLES)
    job.start()
    assert job.wait(120) and job.error is None
    messages = job.commit(bpy.context)
    assert messages[0][0] == 'INFO' and "Baked 'Blob'" in messages[0][1]
    assert files_in(cache_dir) == [os.path.basename(job.final_path)]
    assert obj.translucency.bake_key


def test_save_and_reload_finds_the_cache(blender, addon, tmp_path, memo_bakes):
    from translucency.ops import state

    blend = tmp_path / "scene.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(blend))  # so // resolves next to it
    obj = sphere(subsurf=1)
    obj.translucency.material_preset = 'SKIMMILK'
    add_light()
    assert bake(obj) == {'FINISHED'}
    s = obj.translucency
    assert s.cache_filepath.startswith("//translucency_cache/Blob_")
    key, levels = s.bake_key, [(lv.n_surface, lv.n_inner) for lv in s.status.bake_levels]
    assert (tmp_path / "translucency_cache").is_dir()
    before = radiance(obj)
    bpy.ops.wm.save_mainfile()

    factory_reset()
    assert "Blob" not in bpy.data.objects
    calls = memo_bakes.calls
    loads = state.counters()["loads"]
    bpy.ops.wm.open_mainfile(filepath=str(blend))
    obj = bpy.data.objects["Blob"]
    s = obj.translucency
    assert s.bake_key == key and [(lv.n_surface, lv.n_inner) for lv in s.status.bake_levels] == levels
    assert s.material_preset == 'SKIMMILK' and s.status.bake_memory > 0
    assert state.cache_problem("Blob") is None  # the load handler found the cache
    assert state.get_state(obj) is None  # loaded lazily, on first use
    np.testing.assert_allclose(radiance(obj), before)  # the attribute was saved in the .blend

    activate(obj)
    assert bpy.ops.translucency.solve() == {'FINISHED'}
    assert state.counters()["loads"] == loads + 1 and memo_bakes.calls == calls  # no re-bake
    np.testing.assert_allclose(radiance(obj), before, rtol=2e-3, atol=1e-6)


def test_stale_cache_is_reported(blender, addon, tmp_path, memo_bakes):
    from translucency.ops import state, status

    blend = tmp_path / "stale.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(blend))
    obj = sphere()
    add_light()
    assert bake(obj) == {'FINISHED'}
    obj.data.vertices[0].co.z += 0.2  # the same vertices and polygons elsewhere: a pose of the bake, not stale
    obj.data.update()
    bpy.ops.wm.save_mainfile()
    bpy.ops.wm.open_mainfile(filepath=str(blend))
    assert state.cache_problem("Blob") is None
    bpy.data.objects["Blob"].modifiers.new("Subdivision", 'SUBSURF')  # the topology changes after the bake
    bpy.ops.wm.save_mainfile()
    bpy.ops.wm.open_mainfile(filepath=str(blend))
    obj = bpy.data.objects["Blob"]
    assert state.cache_problem("Blob").startswith("Stale: the mesh changed since it was baked (modifiers "
                                                 "included): 42 vertices baked, 242 now")
    # Solve refuses it (never the old graph's solution as if it were current), with the reason and the fix,
    # and the object keeps no radiance from the old graph.
    activate(obj)
    with pytest.raises(RuntimeError, match="Cannot solve 'Blob': stale bake: the mesh changed since it was baked") \
            as info:
        bpy.ops.translucency.solve()
    assert "42 vertices baked, 242 now" in str(info.value) and "re-bake" in str(info.value)
    assert "stale bake" in status.solve_status(obj).message
    assert obj.data.attributes.get("translucency_radiance") is None



def test_changed_bake_settings_are_reported(blender, addon, cache_dir, memo_bakes):
    from translucency.ops import cache_files, runtime, state
    from translucency.translucency_addon.errors import CacheError

    obj = sphere()
    assert bake(obj) == {'FINISHED'}
    depsgraph = bpy.context.evaluated_depsgraph_get()
    assert cache_files.check_cache(obj, depsgraph).startswith("Baked (cache found")
    obj.translucency.levels = 3
    found = cache_files.check_cache(obj, depsgraph)
    assert found.startswith("Stale: the bake settings changed (baked: draft, 2 levels)")
    with pytest.raises(CacheError, match=r"stale bake: the bake settings changed \(baked: draft, 2 levels\)"):
        runtime.solve_object(obj, force=True)
    assert state.cache_problem("Blob") == found


def test_truncated_cache_gives_a_clear_error(blender, addon, cache_dir, memo_bakes):
    from translucency.ops import cache_files, state

    obj = sphere()
    assert bake(obj) == {'FINISHED'}
    path = cache_files.resolve_cache_path(obj)
    data = open(path, "rb").read()
    with open(path, "wb") as fh:
        fh.write(data[: len(data) // 2])
    state.clear()  # as after a reload: the bake must come from the file
    before = radiance(obj)
    with pytest.raises(RuntimeError, match=r"Cannot solve 'Blob': bake cache .* is corrupt or truncated"):
        bpy.ops.translucency.solve()
    np.testing.assert_array_equal(radiance(obj), before)  # nothing was written
    assert state.cache_problem("Blob").startswith("Cache problem")


def test_missing_cache_is_reported_after_reload(blender, addon, tmp_path, memo_bakes):
    from translucency.ops import cache_files, state

    blend = tmp_path / "missing.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(blend))
    obj = sphere()
    assert bake(obj) == {'FINISHED'}
    bpy.ops.wm.save_mainfile()
    os.remove(cache_files.resolve_cache_path(obj))
    bpy.ops.wm.open_mainfile(filepath=str(blend))
    assert "does not exist" in state.cache_problem("Blob")
    activate(bpy.data.objects["Blob"])
    with pytest.raises(RuntimeError, match="does not exist"):
        bpy.ops.translucency.solve()


def test_free_bake(blender, addon, cache_dir, memo_bakes):
    from translucency.ops import cache_files, state

    obj = sphere()
    assert bake(obj) == {'FINISHED'}
    path = cache_files.resolve_cache_path(obj)
    assert state.get_state(obj) is not None and radiance(obj) is not None
    assert bpy.ops.translucency.free_bake() == {'FINISHED'}
    s = obj.translucency
    assert s.cache_filepath == "" and s.bake_key == "" and len(s.status.bake_levels) == 0
    assert s.status.bake_status == "Not baked" and s.status.bake_stats == ""
    cleared = (s.status.bake_memory, s.status.bake_seconds, s.status.bake_vertices, s.status.bake_warnings)
    assert cleared == (0.0, 0.0, 0, "")
    assert radiance(obj) is None and state.get_state(obj) is None and all(st.name != "Blob" for st in state.object_states())
    assert os.path.exists(path)  # the file stays unless asked (undo may need it)

    assert bake(obj) == {'FINISHED'}
    assert bpy.ops.translucency.free_bake(delete_cache_file=True) == {'FINISHED'}
    assert not os.path.exists(path)


def test_mm_per_unit_from_scene_units_and_object_scale(blender, addon, cache_dir, memo_bakes):
    from translucency.ops import scene_inputs

    scene = bpy.context.scene
    obj = sphere()
    obj.translucency.use_mm_per_unit_override = False
    scene.unit_settings.scale_length = 0.01
    obj.scale = (2.0, 2.0, 2.0)
    bpy.context.view_layer.update()
    assert scene_inputs.mm_per_unit(obj, scene) == (pytest.approx(20.0), None)
    obj.translucency.use_mm_per_unit_override = True
    obj.translucency.mm_per_unit = 3.5
    assert scene_inputs.mm_per_unit(obj, scene) == (pytest.approx(3.5), None)

    obj.translucency.use_mm_per_unit_override = False
    obj.scale = (1.0, 2.0, 1.0)
    bpy.context.view_layer.update()
    mm, warning = scene_inputs.mm_per_unit(obj, scene)
    assert mm == pytest.approx(10.0 * 2.0 ** (1.0 / 3.0)) and "non-uniform scale" in warning
    assert bake(obj) == {'FINISHED'}
    assert "non-uniform scale" in obj.translucency.status.bake_warnings


def test_bake_refuses_non_mesh_and_edit_mode(blender, addon, cache_dir):
    obj = sphere()
    activate(obj)
    bpy.ops.object.mode_set(mode='EDIT')
    with pytest.raises(RuntimeError, match="Edit Mode"):
        bpy.ops.translucency.bake()
    bpy.ops.object.mode_set(mode='OBJECT')
    empty = bpy.data.objects.new("Empty", None)
    bpy.context.scene.collection.objects.link(empty)
    activate(empty)
    assert not bpy.ops.translucency.bake.poll()
    assert math.isfinite(obj.translucency.mm_per_unit)


# --------------------------------------------------------------------------- the modal path


class _Recorder:
    def __init__(self):
        self.calls = []

    def __getattr__(self, name):
        def record(*args, **kwargs):
            self.calls.append((name, args))
        return record


class _FakeOperator:
    """Stands in for the operator instance (Blender creates those only through bpy.ops)."""

    def __init__(self, job):
        from translucency.ops.operators_bake import TRANSLUCENCY_OT_bake as op

        self._job = job
        self._timer = object()
        self.reports = []
        for name in ("modal", "cancel", "_finish", "_set_text", "_end_ui"):
            setattr(self, name, getattr(op, name).__get__(self))

    def report(self, level, message):
        self.reports.append((next(iter(level)), message))


def _fake_context():
    from types import SimpleNamespace

    return SimpleNamespace(window_manager=_Recorder(), workspace=_Recorder(), area=None,
                           scene=bpy.context.scene, evaluated_depsgraph_get=bpy.context.evaluated_depsgraph_get)


def _event(kind, value='NOTHING'):
    from types import SimpleNamespace

    return SimpleNamespace(type=kind, value=value)


def _drive(op, context, job, esc_at_stage=None, timeout=120.0):
    import time

    t0 = time.time()
    while time.time() - t0 < timeout:
        if esc_at_stage is not None and job.stage == esc_at_stage and not job.cancel_requested:
            assert op.modal(context, _event('ESC', 'PRESS')) == {'RUNNING_MODAL'}
        result = op.modal(context, _event('TIMER'))
        if result != {'PASS_THROUGH'}:
            return result
        assert op.modal(context, _event('MOUSEMOVE')) == {'PASS_THROUGH'}  # Blender stays usable
        time.sleep(0.02)
    raise AssertionError("the modal bake did not finish")


def test_modal_bake_progress_and_finish(blender, addon, cache_dir, memo_bakes):
    from translucency.ops import operators_bake

    obj = sphere()
    job = operators_bake.prepare_job(bpy.context, obj, BASE_TRIANGLES)
    op, context = _FakeOperator(job), _fake_context()
    job.start()
    assert _drive(op, context, job) == {'FINISHED'}
    wm = [name for name, _ in context.window_manager.calls]
    assert "progress_update" in wm and "progress_end" in wm and "event_timer_remove" in wm
    texts = [args[0] for name, args in context.workspace.calls if name == "status_text_set"]
    assert any(t and "Esc to cancel" in t for t in texts) and texts[-1] is None  # cleared at the end
    assert op.reports[0][0] == 'INFO' and "Baked 'Blob'" in op.reports[0][1]
    assert obj.translucency.bake_key and len(files_in(cache_dir)) == 1


def test_modal_bake_escape_cancels(blender, addon, cache_dir, real_bakes):
    from translucency.ops import operators_bake

    obj = sphere()
    before = settings_snapshot(obj)
    job = operators_bake.prepare_job(bpy.context, obj, BASE_TRIANGLES)
    op, context = _FakeOperator(job), _fake_context()
    job.start()
    assert _drive(op, context, job, esc_at_stage="tetrahedralize") == {'CANCELLED'}
    levels = [level for level, _ in op.reports]
    assert levels[-1] == 'WARNING' and "cancelled" in op.reports[-1][1]
    assert any("uninterruptible" in message for _, message in op.reports)  # Esc during fTetWild says so
    assert files_in(cache_dir) == [] and settings_snapshot(obj) == before
    assert obj.data.attributes.get("translucency_radiance") is None
