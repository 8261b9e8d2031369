# SPDX-License-Identifier: GPL-3.0-or-later
"""Registration of the add-on from the working tree: classes, settings, panels,
persistence in .blend files, the gpu-free import rule and missing dependencies."""

from __future__ import annotations

import importlib.util
import json
import subprocess
import sys
import textwrap

import bpy
import pytest

from conftest import ROOT, addon_is_registered, factory_reset

PANEL_IDS = ("OBJECT_PT_translucency", "VIEW3D_PT_translucency")


def _registered_ids():
    return {name for name in PANEL_IDS if hasattr(bpy.types, name)}


def test_register_unregister_round_trip(addon):
    factory_reset()
    assert not addon_is_registered(addon)
    addon.register()
    try:
        assert _registered_ids() == set(PANEL_IDS)
        assert "translucency" in bpy.types.Object.bl_rna.properties
        assert "translucency" in bpy.types.Scene.bl_rna.properties
        assert hasattr(bpy.ops.translucency, "check_dependencies")
    finally:
        addon.unregister()
    assert _registered_ids() == set()
    assert "translucency" not in bpy.types.Object.bl_rna.properties
    assert "translucency" not in bpy.types.Scene.bl_rna.properties
    for module in addon.ops.MODULES:
        for cls in module.CLASSES:
            assert not cls.is_registered, cls


def test_every_module_has_a_classes_tuple(addon):
    for module in addon.ops.MODULES:
        assert isinstance(module.CLASSES, tuple), module.__name__


def test_register_again_after_unregister(blender, addon):
    addon.unregister()
    addon.register()
    addon.unregister()
    addon.register()
    assert _registered_ids() == set(PANEL_IDS)
    bpy.ops.mesh.primitive_cube_add()
    assert bpy.context.object.translucency.levels == 3


def test_factory_reset_keeps_one_registration(blender, addon):
    panel = addon.ops.panels.OBJECT_PT_translucency
    factory_reset()
    factory_reset()
    # Still registered, exactly once: the RNA type is our class, and
    # registering it again is refused as a duplicate.
    assert panel.is_registered
    assert bpy.types.OBJECT_PT_translucency is panel
    with pytest.raises((ValueError, RuntimeError)):
        bpy.utils.register_class(panel)
    bpy.ops.mesh.primitive_cube_add()
    assert bpy.context.object.translucency.quality == 'PREVIEW'
    addon.unregister()
    assert _registered_ids() == set()
    factory_reset()
    addon.register()  # the blender fixture unregisters it again


def test_object_settings_defaults(blender, addon):
    bpy.ops.mesh.primitive_cube_add()
    settings = bpy.context.object.translucency
    assert isinstance(settings, addon.ops.properties.TranslucencyObjectSettings)
    assert settings.enabled is False
    assert settings.quality == 'PREVIEW'
    assert settings.levels == 3
    assert settings.use_mm_per_unit_override is False
    assert settings.material_preset == 'MARBLE'
    assert tuple(round(v, 4) for v in settings.sigma_a) == (0.0021, 0.0041, 0.0071)
    assert settings.eta == pytest.approx(1.3)
    assert settings.field_source == 'TEXTURE'
    assert settings.field_texture is None
    with pytest.raises(TypeError):
        settings.quality = 'ULTRA'
    settings.levels = 99
    assert settings.levels == 5  # clamped to 1..5
    settings.levels = 0
    assert settings.levels == 1


def test_scene_settings_defaults(blender, addon):
    settings = bpy.context.scene.translucency
    assert isinstance(settings, addon.ops.properties.TranslucencySceneSettings)
    assert settings.cache_directory == "//translucency_cache/"
    assert settings.overlay_mode in {'ONLY', 'ADD'}
    assert settings.solver_backend == 'AUTO'
    assert settings.tolerance == pytest.approx(1e-4)
    # a solve's status is runtime state (ops.status), never a saved setting
    assert not any(hasattr(settings, name) for name in ("last_solve_time", "last_residual", "last_backend"))


def test_material_presets_come_from_the_engine(blender, addon):
    from translucency.translucency_addon.scene.materials import PRESETS, preset

    items = {item.identifier for item in addon.ops.properties.TranslucencyObjectSettings.bl_rna
             .properties["material_preset"].enum_items}
    assert items == {name.upper() for name in PRESETS} | {"CUSTOM"}
    for identifier in items - {"CUSTOM"}:
        assert preset(identifier) is PRESETS[identifier.lower()]


def test_every_property_has_a_description(blender, addon):
    for group in addon.ops.properties.CLASSES:
        for prop in group.bl_rna.properties:
            if prop.identifier in {"rna_type", "name"}:
                continue
            assert len(prop.description) > 15, f"{group.__name__}.{prop.identifier} needs a tooltip"


def test_panels_in_properties_editor_and_sidebar(blender, addon):
    props_panel = bpy.types.OBJECT_PT_translucency
    side_panel = bpy.types.VIEW3D_PT_translucency
    assert (props_panel.bl_space_type, props_panel.bl_region_type, props_panel.bl_context) == \
        ('PROPERTIES', 'WINDOW', 'object')
    assert (side_panel.bl_space_type, side_panel.bl_region_type, side_panel.bl_category) == \
        ('VIEW_3D', 'UI', 'Translucency')
    assert props_panel.bl_label == side_panel.bl_label == "Translucency"


@pytest.mark.parametrize("field_source", ["TEXTURE", "ATTRIBUTE", "VERTEX_GROUP"])
@pytest.mark.parametrize("material", ["MARBLE", "CUSTOM"])
def test_panel_draws_settings(blender, addon, ui, field_source, material):
    bpy.ops.mesh.primitive_cube_add()
    obj = bpy.context.object
    obj.translucency.field_source = field_source
    obj.translucency.material_preset = material
    for panel in (bpy.types.OBJECT_PT_translucency, bpy.types.VIEW3D_PT_translucency):
        layout = ui.FakeLayout()
        panel.draw(type("P", (), {"layout": layout})(), ui.draw_context(obj))
        drawn = set(layout.props())
        assert {"enabled", "quality", "levels", "material_preset", "eta", "use_heterogeneity",
                "field_source", "cache_filepath", "solver_backend", "cache_directory"} <= drawn
        assert ("sigma_a" in drawn) == (material == "CUSTOM")
        assert {"TEXTURE": "field_texture", "ATTRIBUTE": "field_attribute",
                "VERTEX_GROUP": "field_vertex_group"}[field_source] in drawn
        assert not any("Missing" in text for text in layout.labels())


def test_panel_draws_without_active_object(blender, addon, ui):
    layout = ui.FakeLayout()
    addon.ops.panels.draw_translucency(layout, ui.draw_context(None))
    assert "No active object" in layout.labels()
    assert "solver_backend" in layout.props()


def test_settings_persist_across_save_and_reload(blender, tmp_path):
    bpy.ops.mesh.primitive_cube_add()
    obj = bpy.context.object
    obj.name = "Persisted"
    texture = bpy.data.textures.new("mix", type='CLOUDS')
    s = obj.translucency
    s.enabled = True
    s.quality = 'FINAL'
    s.levels = 4
    s.use_mm_per_unit_override = True
    s.mm_per_unit = 25.4
    s.material_preset = 'CUSTOM'
    s.sigma_a = (0.1, 0.2, 0.3)
    s.sigma_s = (1.5, 2.5, 3.5)
    s.eta = 1.45
    s.use_heterogeneity = True
    s.second_preset = 'SKIN1'
    s.field_source = 'ATTRIBUTE'
    s.field_texture = texture
    s.field_attribute = "density"
    s.field_vertex_group = "veins"
    s.cache_filepath = "//cache/persisted.npz"
    s.status.bake_status = "Baked"
    s.status.bake_levels.add().n_surface = 321
    s.status.bake_memory = 1.5
    scene = bpy.context.scene.translucency
    scene.cache_directory = "//elsewhere/"
    scene.overlay_enabled = False
    scene.overlay_mode = 'ONLY'
    scene.solver_backend = 'CPU'
    scene.tolerance = 1e-6

    path = tmp_path / "persist.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(path))
    factory_reset()
    assert "Persisted" not in bpy.data.objects
    bpy.ops.wm.open_mainfile(filepath=str(path))

    s = bpy.data.objects["Persisted"].translucency
    assert s.enabled and s.quality == 'FINAL' and s.levels == 4
    assert s.use_mm_per_unit_override and s.mm_per_unit == pytest.approx(25.4)
    assert s.material_preset == 'CUSTOM'
    assert tuple(s.sigma_a) == pytest.approx((0.1, 0.2, 0.3))
    assert tuple(s.sigma_s) == pytest.approx((1.5, 2.5, 3.5))
    assert s.eta == pytest.approx(1.45)
    assert s.use_heterogeneity and s.second_preset == 'SKIN1' and s.field_source == 'ATTRIBUTE'
    assert s.field_texture is not None and s.field_texture.name == "mix"
    assert (s.field_attribute, s.field_vertex_group) == ("density", "veins")
    assert s.cache_filepath == "//cache/persisted.npz" and s.status.bake_status == "Baked"
    assert [lv.n_surface for lv in s.status.bake_levels] == [321] and s.status.bake_memory == pytest.approx(1.5)
    scene = bpy.context.scene.translucency
    assert scene.cache_directory == "//elsewhere/"
    assert not scene.overlay_enabled and scene.overlay_mode == 'ONLY' and scene.solver_backend == 'CPU'
    assert scene.tolerance == pytest.approx(1e-6)


def test_a_file_from_before_the_status_group_loads_with_its_status(blender, tmp_path):
    """Older files saved the bake status among the settings (``translucency.bake_status`` ...) and the
    solve's per-frame outputs there and on the scene.  On load the bake status moves into
    ``translucency.status``, the per-frame outputs are dropped, and the settings stay as they were."""
    bpy.ops.mesh.primitive_cube_add()
    obj = bpy.context.object
    obj.name = "Old"
    s = obj.translucency
    s.material_preset = 'SKIN1'
    s.bake_key = "k" * 64
    # what an older version left in the file: ID properties under the old names
    s["bake_status"] = "Baked"
    s["bake_stats"] = "N_s 1 / 2; N_i 3 / 4; 0.1 MiB; 2.0 s"
    s["bake_memory"] = 0.125
    s["bake_vertices"] = 8
    s["bake_levels"] = [{"n_surface": 10, "n_inner": 20}, {"n_surface": 40, "n_inner": 80}]
    s["solve_seconds"] = 0.5
    s["solve_backend"] = "GPU"
    bpy.context.scene.translucency["last_solve_time"] = 0.25
    path = tmp_path / "old.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(path))
    factory_reset()
    bpy.ops.wm.open_mainfile(filepath=str(path))

    s = bpy.data.objects["Old"].translucency
    assert s.material_preset == 'SKIN1' and s.bake_key == "k" * 64
    assert s.status.bake_status == "Baked" and s.status.bake_stats.startswith("N_s 1 / 2")
    assert s.status.bake_memory == pytest.approx(0.125) and s.status.bake_vertices == 8
    assert [(lv.n_surface, lv.n_inner) for lv in s.status.bake_levels] == [(10, 20), (40, 80)]
    assert not set(s.keys()) & {"bake_status", "bake_levels", "solve_seconds", "solve_backend"}
    assert "last_solve_time" not in bpy.context.scene.translucency.keys()


# --- no gpu, no wheels at import and register time -------------------------------------

_NO_GPU_SCRIPT = textwrap.dedent(r"""
    import importlib.util, json, sys
    import bpy, gpu

    calls = []

    def wrap(owner, name, value):
        def recorder(*args, **kwargs):
            calls.append(f"{owner.__name__}.{name}")
            return value(*args, **kwargs)
        return recorder

    for owner in (gpu, gpu.types, gpu.shader, gpu.compute, gpu.texture, gpu.state, gpu.platform,
                  gpu.matrix, gpu.capabilities, gpu.select):
        for name in dir(owner):
            value = getattr(owner, name)
            if not name.startswith("_") and callable(value) and not isinstance(value, type(gpu)):
                setattr(owner, name, wrap(owner, name, value))

    root = sys.argv[1]
    spec = importlib.util.spec_from_file_location("translucency", root + "/__init__.py",
                                                  submodule_search_locations=[root])
    module = importlib.util.module_from_spec(spec)
    sys.modules["translucency"] = module
    spec.loader.exec_module(module)
    module.register()
    bpy.ops.mesh.primitive_cube_add()
    bpy.context.object.translucency.enabled = True
    module.unregister()
    module.register()
    module.unregister()
    wheels = [name for name in ("scipy", "pytetwild", "fast_simplification") if name in sys.modules]
    print("RESULT " + json.dumps({"gpu_calls": calls, "wheels_imported": wheels}))
""")


def test_import_and_register_touch_neither_gpu_nor_wheels(tmp_path):
    """In a fresh Blender (GPU backend not started), import + register + unregister
    never call anything in ``gpu`` and never import the bundled wheels."""
    script = tmp_path / "no_gpu.py"
    script.write_text(_NO_GPU_SCRIPT)
    proc = subprocess.run([sys.executable, str(script), str(ROOT)], capture_output=True, text=True,
                          timeout=300, cwd=tmp_path)
    lines = [line for line in proc.stdout.splitlines() if line.startswith("RESULT ")]
    assert proc.returncode == 0 and lines, proc.stdout[-3000:] + proc.stderr[-3000:]
    result = json.loads(lines[-1][len("RESULT "):])
    assert result["gpu_calls"] == []
    assert result["wheels_imported"] == []


# --- bad input: a bundled wheel that does not import ------------------------------------

class _BrokenWheelFinder:
    """A meta-path finder that makes chosen modules fail like a broken wheel."""

    def __init__(self, errors):
        self.errors = errors

    def find_spec(self, name, path=None, target=None):
        top = name.partition(".")[0]
        if top in self.errors:
            raise self.errors[top]
        return None


@pytest.fixture
def broken_wheels(monkeypatch):
    """Make pytetwild absent and scipy's shared library fail to load."""
    for name in list(sys.modules):
        if name.partition(".")[0] in {"pytetwild", "scipy"}:
            monkeypatch.delitem(sys.modules, name)
    monkeypatch.setattr(sys, "meta_path", [_BrokenWheelFinder({
        "pytetwild": ModuleNotFoundError("No module named 'pytetwild'"),
        "scipy": OSError("libscipy_openblas.so: cannot open shared object file"),
    })] + sys.meta_path)
    yield
    # the fixture's monkeypatch restores sys.modules/meta_path; forget the cached result
    sys.modules["translucency"].ops.dependencies.clear_cache()


def test_missing_wheel_registers_and_panel_names_it(addon, broken_wheels, ui):
    factory_reset()
    addon.ops.dependencies.clear_cache()
    addon.register()  # must not raise
    try:
        problems = dict(addon.ops.dependencies.missing())
        assert set(problems) == {"pytetwild", "scipy"}
        assert "ModuleNotFoundError" in problems["pytetwild"]
        assert "OSError" in problems["scipy"] and "libscipy_openblas" in problems["scipy"]

        bpy.ops.mesh.primitive_cube_add()
        for panel in (bpy.types.OBJECT_PT_translucency, bpy.types.VIEW3D_PT_translucency):
            layout = ui.FakeLayout()
            panel.draw(type("P", (), {"layout": layout})(), ui.draw_context(bpy.context.object))
            text = "\n".join(layout.labels())
            assert "Missing dependencies" in text
            assert "pytetwild does not import" in text and "scipy does not import" in text
            assert "No module named 'pytetwild'" in text
            assert layout.props() == []  # nothing else is drawn
            assert layout.operators() == ["translucency.check_dependencies"]
        # An operator's ERROR report raises in background mode.
        with pytest.raises(RuntimeError, match="pytetwild does not import"):
            bpy.ops.translucency.check_dependencies()
    finally:
        addon.unregister()
        factory_reset()


def test_all_dependencies_found_in_test_environment(addon):
    addon.ops.dependencies.clear_cache()
    assert addon.ops.dependencies.missing() == []


def test_presets_fall_back_when_engine_cannot_import(addon, monkeypatch):
    """properties.py falls back to a static preset list if the engine import fails."""
    name = "translucency_noengine"
    spec = importlib.util.spec_from_file_location(name, ROOT / "__init__.py",
                                                  submodule_search_locations=[str(ROOT)])
    module = importlib.util.module_from_spec(spec)
    monkeypatch.setitem(sys.modules, name, module)
    monkeypatch.setitem(sys.modules, f"{name}.translucency_addon", None)  # import fails
    try:
        spec.loader.exec_module(module)
        items = [item[0] for item in module.ops.properties.MATERIAL_ITEMS]
        assert "MARBLE" in items and "CUSTOM" in items and len(items) > 5
        factory_reset()
        assert not addon_is_registered(addon)
        module.register()
        module.unregister()
    finally:
        for key in [k for k in sys.modules if k.startswith(name + ".")]:
            del sys.modules[key]
