# SPDX-License-Identifier: GPL-3.0-or-later
"""Single scattering in Blender: baked by ``translucency.bake`` (or ``translucency.bake_single_scattering``
alone), added to the diffusion at solve time, split into its own attribute / AOV, staleness reports."""

from __future__ import annotations

import os

import bpy
import numpy as np
import pytest

from test_ops_bake import activate, add_light, bake, cache_dir, memo_bakes, radiance, sphere  # noqa: F401

SS_ATTR = "translucency_radiance_ss"


def ss_sphere(name="Blob", split=True, **kw):
    obj = sphere(name=name, **kw)
    s = obj.translucency
    s.use_single_scattering = True
    s.pass_planning = 'ALL'  # these tests exercise the single-scattering pipeline, not the planner
    s.ss_quality = 'DRAFT'
    s.ss_directions = '32'
    s.ss_samples = 500
    s.ss_split_pass = split
    return obj


def ss_radiance(obj):
    from translucency.ops import attributes

    return attributes.read_radiance(obj, SS_ATTR)


def solve(obj, **kw):
    activate(obj)
    return bpy.ops.translucency.solve(**kw)


def solved(obj):
    """The object's solve status (runtime state, never saved)."""
    from translucency.ops import status

    return status.solve_status(obj)


@pytest.fixture
def baked(blender, cache_dir, memo_bakes):
    add_light()
    obj = ss_sphere()
    assert bake(obj) == {'FINISHED'}
    return obj


def test_bake_with_single_scattering_reports_stages_and_stats(blender, cache_dir, memo_bakes):
    from translucency.ops import cache_files, operators_bake, state
    from translucency.translucency_addon.cache import load_bake
    from translucency.translucency_addon.single_scattering import graph_key

    add_light()
    obj = ss_sphere()
    stages = []
    operators_bake.PROGRESS_LISTENERS.append(lambda f, st: stages.append((f, st)))
    try:
        assert bake(obj) == {'FINISHED'}
    finally:
        operators_bake.PROGRESS_LISTENERS.clear()
    names = [st for _, st in stages]
    for stage in ("voxelise", "optical depth", "Poisson-disk samples", "RBF fit", "spherical harmonics"):
        assert f"single scattering: {stage}" in names
    fractions = [f for f, _ in stages]
    assert fractions == sorted(fractions) and fractions[-1] == pytest.approx(1.0)
    s = obj.translucency
    st = state.get_state(obj)
    data = st.bake.single_scattering
    assert data is not None and s.status.ss_samples_baked == data.n_samples > 100
    assert f"{data.n_samples:,} samples, 32 directions, SH order 4" in s.status.ss_bake_stats
    assert s.status.ss_bake_seconds > 0 and s.status.bake_seconds > 0
    # the key (and the file name) include the single-scattering inputs; the QuadGraph key is kept for staleness
    assert s.bake_key == st.bake.key != graph_key(st.bake)
    assert s.bake_key[:16] in os.path.basename(s.cache_filepath)
    assert load_bake(cache_files.resolve_cache_path(obj), expected_key=s.bake_key).single_scattering.n_samples \
        == data.n_samples
    assert cache_files.check_cache(obj, bpy.context.evaluated_depsgraph_get()).startswith("Baked")
    assert solved(obj).ss_backend in {"CPU", "GPU"} and solved(obj).ss_seconds > 0  # the bake's first solve


def test_solve_adds_single_scattering_and_splits_it(baked):
    obj = baked
    assert solve(obj) == {'FINISHED'}
    total, ss = radiance(obj), ss_radiance(obj)
    attr = obj.data.attributes[SS_ATTR]
    assert (attr.domain, attr.data_type) == ('POINT', 'FLOAT_COLOR')
    assert ss.shape == total.shape and np.all(np.isfinite(ss)) and ss.min() >= 0 and ss.max() > 0
    from translucency.ops import state

    # The diffusion term of the same frame, from the engine's own output of the solve the add-on ran (with
    # Bernabei's pass on, "All Passes" runs diffusion without the closed-form first-scatter split).
    st = state.get_state(obj)
    assert not any(st.result.single)
    diffusion = st.result_solver.vertex_radiance(st.result)
    assert np.allclose(total, diffusion + ss, rtol=1e-4, atol=1e-5 * total.max())
    obj.translucency.use_single_scattering = False
    solve(obj)
    assert obj.data.attributes.get(SS_ATTR) is None  # no stale pass once the term is off
    # without Bernabei's pass the once-scattered light is the closed-form term of the split (issue 17)
    assert any(state.get_state(obj).result.single) and not np.allclose(radiance(obj), total, rtol=1e-3)
    # lit side: single scattering is brighter toward the light, like the diffusion
    x = np.array([v.co.x for v in obj.data.vertices])
    assert ss[x > 0.5].mean() > 3 * ss[x < -0.5].mean()


def test_each_term_can_be_turned_off(baked):
    obj = baked
    s = obj.translucency
    solve(obj)
    ss = ss_radiance(obj)
    s.use_multiple_scattering = False
    assert solve(obj) == {'FINISHED'}
    assert np.allclose(radiance(obj), ss, rtol=1e-6, atol=0)
    assert np.allclose(ss_radiance(obj), ss, rtol=1e-6, atol=0)
    s.use_single_scattering = False
    solve(obj)
    assert np.all(radiance(obj) == 0)
    s.use_multiple_scattering = True
    s.use_single_scattering = True
    s.ss_split_pass = False
    solve(obj)
    assert obj.data.attributes.get(SS_ATTR) is None and radiance(obj).max() > ss.max()


def test_single_scattering_aov_after_add_to_material(baked):
    obj = baked
    solve(obj)
    activate(obj)
    assert bpy.ops.translucency.add_to_material() == {'FINISHED'}
    assert {"Translucency", "Translucency_SS"} <= {a.name for a in bpy.context.view_layer.aovs}


def test_material_change_asks_for_a_single_scattering_rebake(baked, memo_bakes, capsys):
    from translucency.ops import cache_files, state

    obj = baked
    s = obj.translucency
    solve(obj)
    assert solved(obj).ss_message == "" or "re-bake" not in solved(obj).ss_message
    old_key, old_path, old_stored = s.bake_key, cache_files.resolve_cache_path(obj), s.cache_filepath
    before = ss_radiance(obj)
    s.material_preset = 'KETCHUP'
    assert solve(obj) == {'FINISHED'}
    assert "single scattering needs a re-bake: the material changed" in solved(obj).ss_message
    assert "single scattering needs a re-bake" in capsys.readouterr().out  # the log, and the operator's warning
    st = state.get_state(obj)
    assert any("single scattering needs a re-bake" in w for w in st.warnings)
    # the QuadGraph stays: only single scattering is re-baked
    calls = memo_bakes.calls
    activate(obj)
    assert bpy.ops.translucency.bake_single_scattering() == {'FINISHED'}
    assert memo_bakes.calls == calls
    assert s.bake_key != old_key and os.path.exists(old_path)  # undo can go back to the old file
    solve(obj)
    assert solved(obj).ss_message == "" or "re-bake" not in solved(obj).ss_message
    after = ss_radiance(obj)
    assert after[:, 2].sum() < 0.5 * before[:, 2].sum()  # ketchup scatters little blue
    # eta is not baked: no re-bake needed
    s.eta = 1.45
    solve(obj)
    assert "re-bake" not in solved(obj).ss_message
    # what undo does: the old key and path come back, and the old file is still there to load
    new_key = s.bake_key
    s.bake_key, s.cache_filepath = old_key, old_stored
    assert solve(obj) == {'FINISHED'}
    assert state.get_state(obj).bake.key == old_key != new_key
    assert "the material changed" in solved(obj).ss_message


def test_single_scattering_settings_staleness(baked):
    obj = baked
    s = obj.translucency
    s.ss_sh_order = 2  # lower than baked: truncated at run time
    solve(obj)
    assert "re-bake" not in solved(obj).ss_message
    s.ss_directions = '128'
    solve(obj)
    assert "settings changed (directions 32 -> 128)" in solved(obj).ss_message
    s.ss_directions = '32'
    s.use_mm_per_unit_override = True
    s.mm_per_unit = 20.0
    solve(obj)
    assert "the scale changed" in solved(obj).ss_message


def test_single_scattering_on_but_not_baked(blender, cache_dir, memo_bakes):
    add_light()
    obj = ss_sphere()
    obj.translucency.use_single_scattering = False
    assert bake(obj) == {'FINISHED'}
    obj.translucency.use_single_scattering = True
    solve(obj)
    assert "not baked" in solved(obj).ss_message
    assert obj.data.attributes.get(SS_ATTR) is None
    other = ss_sphere(name="Unbaked", location=(4.0, 0.0, 0.0))
    activate(other)
    assert not bpy.ops.translucency.bake_single_scattering.poll()


def test_cancel_during_single_scattering_leaves_nothing(blender, cache_dir, memo_bakes):
    from translucency.ops import operators_bake

    add_light()
    obj = ss_sphere()
    operators_bake.PROGRESS_LISTENERS.append(lambda f, st: not st.startswith("single scattering: optical"))
    try:
        assert bake(obj) == {'CANCELLED'}
    finally:
        operators_bake.PROGRESS_LISTENERS.clear()
    s = obj.translucency
    assert s.bake_key == "" and s.status.ss_samples_baked == 0
    assert not cache_dir.exists() or not any(cache_dir.iterdir())


def test_camera_view_and_field_change(blender, cache_dir, memo_bakes):
    add_light()
    obj = ss_sphere()
    s = obj.translucency
    tex = bpy.data.textures.new("Clouds", 'CLOUDS')
    tex.noise_scale = 0.5
    s.use_heterogeneity = True
    s.field_source = 'TEXTURE'
    s.field_texture = tex
    assert bake(obj) == {'FINISHED'}
    cam = bpy.data.objects.new("Cam", bpy.data.cameras.new("Cam"))
    cam.location = (0.0, -6.0, 0.0)
    cam.rotation_euler = (np.pi / 2, 0.0, 0.0)
    bpy.context.scene.collection.objects.link(cam)
    bpy.context.scene.camera = cam
    solve(obj)
    normal_view = ss_radiance(obj)
    assert solve(obj, use_camera=True) == {'FINISHED'}
    toward_camera = ss_radiance(obj)
    y = np.array([v.co.y for v in obj.data.vertices])
    assert np.all(toward_camera[y > 0.3] == 0)  # facing away from the camera
    assert toward_camera[y < -0.3].max() > 0 and np.abs(toward_camera - normal_view).max() > 0
    assert "re-bake" not in solved(obj).ss_message
    tex.noise_scale = 0.25
    solve(obj)
    assert "the heterogeneity field changed" in solved(obj).ss_message


def test_panel_shows_single_scattering(baked, ui):
    from translucency.ops import panels

    obj = baked
    solve(obj)
    layout = ui.FakeLayout()
    panels.draw_translucency(layout, ui.draw_context(obj))
    props = layout.props()
    for name in ("use_multiple_scattering", "use_single_scattering", "ss_quality", "ss_directions", "ss_samples",
                 "ss_sh_order", "ss_split_pass"):
        assert name in props
    assert "translucency.bake_single_scattering" in layout.operators()
    labels = " | ".join(layout.labels())
    assert "Single scattering: " in labels and "samples, 32 directions" in labels
    assert " ms on the " in labels


def test_free_bake_removes_the_split_attribute(baked):
    obj = baked
    solve(obj)
    activate(obj)
    assert bpy.ops.translucency.free_bake() == {'FINISHED'}
    assert obj.data.attributes.get(SS_ATTR) is None and obj.translucency.status.ss_samples_baked == 0


@pytest.mark.gpu
def test_gpu_kernel_in_blender_matches_numpy(gpu_context, baked):
    from translucency.ops import state

    obj = baked
    scene = bpy.context.scene
    scene.translucency.solver_backend = 'CPU'
    solve(obj)
    cpu = ss_radiance(obj)
    scene.translucency.solver_backend = 'GPU'  # the kernel even on llvmpipe (AUTO prefers numpy there)
    solve(obj)
    assert solved(obj).ss_backend == "GPU" and state.get_state(obj).ss_backend == "GPU"
    gpu = ss_radiance(obj)
    assert np.abs(gpu - cpu).max() <= 1e-5 * np.abs(cpu).max()


def test_modifier_changes_the_vertex_count(blender, cache_dir, memo_bakes):
    """The baked (evaluated) mesh has more vertices than obj.data: rays start at the closest baked surface point."""
    add_light()
    obj = ss_sphere(subsurf=1)
    assert bake(obj) == {'FINISHED'}
    assert obj.translucency.status.bake_vertices > len(obj.data.vertices)
    solve(obj)
    ss = ss_radiance(obj)
    assert ss.shape == (len(obj.data.vertices), 3) and np.all(np.isfinite(ss))
    x = np.array([v.co.x for v in obj.data.vertices])
    assert ss[x > 0.5].mean() > 3 * ss[x < -0.5].mean() and ss[x > 0.5].mean() > 0


@pytest.mark.parametrize("backend", ["AUTO", "GPU"])
def test_render_evaluates_single_scattering_toward_the_camera(blender, cache_dir, memo_bakes, tmp_path, backend):
    """An F12-style render solves in frame_change_post toward the render camera; with the GPU preferred the
    kernel runs when the render handler has a GPU context, numpy otherwise (per-call fallback)."""
    from translucency.ops import runtime, state

    scene = bpy.context.scene
    add_light()
    obj = ss_sphere()
    assert bake(obj) == {'FINISHED'}
    cam = bpy.data.objects.new("Cam", bpy.data.cameras.new("Cam"))
    cam.location = (0.0, -6.0, 0.0)
    cam.rotation_euler = (np.pi / 2, 0.0, 0.0)
    scene.collection.objects.link(cam)
    scene.camera = cam
    scene.render.engine = 'BLENDER_WORKBENCH'
    scene.render.resolution_x = scene.render.resolution_y = 8
    scene.render.filepath = str(tmp_path / "frame_")
    scene.translucency.solver_backend = backend
    seen = []

    def written(*_args):
        seen.append(ss_radiance(obj).copy())
        backends.append(state.get_state(obj).ss_backend)

    backends = []

    bpy.app.handlers.render_write.append(written)
    try:
        bpy.ops.render.render(write_still=True)
    finally:
        bpy.app.handlers.render_write.remove(written)
    assert len(seen) == 1
    print(f"render with solver {backend}: single scattering on the {backends[0]}")
    assert backends[0] == "CPU" if backend == "AUTO" else backends[0] in {"GPU", "CPU"}
    y = np.array([v.co.y for v in obj.data.vertices])
    assert np.all(seen[0][y > 0.3] == 0) and seen[0][y < -0.3].max() > 0  # toward the camera at -y
    scene.translucency.solver_backend = 'CPU'
    runtime.solve_object(obj, scene, use_camera=True, force=True)
    np.testing.assert_allclose(ss_radiance(obj), seen[0], rtol=1e-4, atol=1e-6 * seen[0].max())


def test_a_dark_medium_bakes_single_scattering_by_default(blender, cache_dir, memo_bakes, capfd):
    """Issue 30's new user: a dark medium (reduced albedo 0.2) with default settings rendered black -- the
    planner hands it to single scattering, which was not baked.  The bake now knows: it bakes single
    scattering too, turns the switch on and says why, so the first solve returns light.  A medium where
    diffusion holds (marble) is baked as before, without it."""
    from translucency.ops import state

    add_light('SUN', location=(0.0, 0.0, 5.0), energy=3.0)
    dark = sphere(name="Ink")
    s = dark.translucency
    s.material_preset = 'CUSTOM'
    s.sigma_a, s.sigma_s, s.eta = (0.8, 0.8, 0.8), (0.2, 0.2, 0.2), 1.3
    s.ss_quality, s.ss_directions, s.ss_samples = 'DRAFT', '32', 300
    assert not s.use_single_scattering  # the default
    assert bake(dark) == {'FINISHED'}
    out = capfd.readouterr().out
    assert state.get_state(dark).bake.single_scattering is not None and s.use_single_scattering
    assert "Single Scattering was off; it is baked and turned on because" in out and "0.20" in out, out[-2000:]
    L = radiance(dark)
    assert L.max() > 0 and L.mean() > 1e-3 * L.max(), "a dark medium under a sun must not render black"

    marble = sphere(name="Marble", location=(4.0, 0.0, 0.0))
    assert bake(marble) == {'FINISHED'}
    assert state.get_state(marble).bake.single_scattering is None and not marble.translucency.use_single_scattering
