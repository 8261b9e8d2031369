# SPDX-License-Identifier: GPL-3.0-or-later
"""Render farms (issue 19, part 2): many machines render frames of the same .blend, each its own process.

A worker here is a fresh Python process with the bpy module, which is Blender in background mode: it
registers the add-on (a farm worker has the extension installed), opens the .blend and renders a frame
range with ``render(animation=True)``, which is what ``blender -b shot.blend -s A -e B -a`` (or ``-f N``)
does.  The scene: a Draft bake of a small icosphere, a point light moving across it and changing power
over frames 1-9, Cycles at 16x16 px and one sample, the ``Translucency`` AOV in a multilayer EXR.

The proof: three workers rendering frames 1, 5 and 9 from one shared copy of the .blend and its cache
folder (made read-only) give the same Translucency pass, and the same per-vertex radiance, as one process
rendering 1-9 in order (which warm-starts every frame from the last); the frames differ from each other
(the light moves), and nothing is written into the shared folder.  Bad input: a worker without the cache
folder, or with a cache from another version of the extension, fails its frame (exit code 1, the reason,
no image); with "Render Without" it renders the frame without the pass.
"""

from __future__ import annotations

import json
import os
import shutil
import stat
import subprocess
import sys
import tempfile
import textwrap
from pathlib import Path

import bpy
import numpy as np
import pytest

from conftest import ROOT
from test_ops_bake import activate, add_light, memo_bakes, sphere  # noqa: F401
from tools.exr import exr_pass
from translucency_addon.cache import umask_mode

FRAMES = (1, 5, 9)
SIZE = 16

_WORKER = textwrap.dedent(r"""
    import importlib.util, os, sys
    import bpy
    import numpy as np
    root, blend, first, last, out = sys.argv[1:6]
    policy = sys.argv[6] if len(sys.argv) > 6 else ""
    name = sys.argv[7] if len(sys.argv) > 7 else "Blob"
    spec = importlib.util.spec_from_file_location("translucency", os.path.join(root, "__init__.py"),
                                                  submodule_search_locations=[root])
    module = importlib.util.module_from_spec(spec)
    sys.modules["translucency"] = module
    spec.loader.exec_module(module)
    module.register()                                   # the extension, installed on the worker
    bpy.ops.wm.open_mainfile(filepath=blend)            # blender -b shot.blend
    scene = bpy.context.scene
    if policy:
        scene.translucency.missing_cache_in_render = policy
    scene.frame_start, scene.frame_end = int(first), int(last)   # -s first -e last -a  (or -f N)
    scene.render.filepath = os.path.join(out, "frame_")
    obj = bpy.data.objects[name]

    def keep(scene, *_args):                            # the per-vertex radiance this frame rendered
        attr = obj.data.attributes.get("translucency_radiance")
        if attr is not None:
            buf = np.empty(len(attr.data) * 4, np.float32)
            attr.data.foreach_get("color", buf)
            np.save(os.path.join(out, f"radiance_{scene.frame_current:04d}.npy"), buf.reshape(-1, 4)[:, :3])

    bpy.app.handlers.render_write.append(keep)
    bpy.ops.render.render(animation=True)
    bpy.app.handlers.render_write.remove(keep)
    module.unregister()  # bpy 4.2 as a module crashes at exit while a property with a Python callback is registered
    print("WORKER DONE", flush=True)
""")


def _render_and_bake(scene, obj, render_pass_module) -> None:
    """The farm shots' render settings (Cycles on the CPU, 1 sample, a fixed seed, a multilayer EXR of SIZE
    pixels), then, on frame 1, the object's bake and its render pass."""
    scene.render.engine = 'CYCLES'
    scene.cycles.device, scene.cycles.samples, scene.cycles.use_denoising, scene.cycles.seed = 'CPU', 1, False, 0
    scene.render.resolution_x = scene.render.resolution_y = SIZE
    scene.render.resolution_percentage = 100
    render_pass_module.configure_output(scene.render.image_settings, 'OPEN_EXR_MULTILAYER')
    scene.frame_set(1)
    activate(obj)
    assert bpy.ops.translucency.bake(base_triangles=200) == {'FINISHED'}, obj.translucency.status.bake_status
    assert bpy.ops.translucency.add_to_material() == {'FINISHED'}


def _shot(tmp_path, render_pass_module):
    """The animated scene, baked and saved as ``tmp_path/src/shot.blend`` with its cache folder next to it."""
    src = tmp_path / "src"
    src.mkdir()
    blend = src / "shot.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(blend))  # saved first: the cache goes to //translucency_cache/
    scene = bpy.context.scene
    assert scene.translucency.cache_directory == "//translucency_cache/"
    scene.translucency.tolerance = 1e-8  # both runs converge to the same solution (warm and cold starts)
    obj = sphere()
    light = add_light(location=(3.0, 0.0, 1.0), energy=200.0)
    light.keyframe_insert("location", frame=1)
    light.data.keyframe_insert("energy", frame=1)
    light.location, light.data.energy = (-3.0, 1.0, 1.0), 1000.0
    light.keyframe_insert("location", frame=9)
    light.data.keyframe_insert("energy", frame=9)
    cam = bpy.data.objects.new("cam", bpy.data.cameras.new("cam"))
    scene.collection.objects.link(cam)
    cam.location = (0.0, -6.0, 0.0)
    cam.rotation_euler = (np.pi / 2, 0.0, 0.0)
    scene.camera = cam
    _render_and_bake(scene, obj, render_pass_module)
    assert obj.translucency.cache_filepath.startswith("//translucency_cache/"), obj.translucency.cache_filepath
    bpy.ops.wm.save_mainfile()
    return src


def _copy(src, dst):
    shutil.copytree(src, dst)
    return dst / "shot.blend"


def _snapshot(folder):
    return sorted((str(p.relative_to(folder)), p.stat().st_size, p.stat().st_mtime_ns) for p in folder.rglob("*"))


def _run(blend, first, last, out, policy="", wait=True, name="Blob"):
    out.mkdir(parents=True, exist_ok=True)
    script = out / "_worker.py"  # one per worker: a shared script rewritten while another worker reads it
    script.write_text(_WORKER)  # can be read empty (such a worker ran nothing and exited 0)
    proc = subprocess.Popen([sys.executable, str(script), str(ROOT), str(blend), str(first), str(last), str(out),
                             policy, name], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            cwd=out)
    return proc.communicate(timeout=600)[0] if wait else proc


def _passes(out, frames):
    return {f: exr_pass(out / f"frame_{f:04d}.exr", "Translucency")[..., :3] for f in frames}


@pytest.fixture
def render_pass_module(blender, addon):
    from translucency.ops import render_pass

    return render_pass


def test_three_workers_render_what_one_process_renders(render_pass_module, memo_bakes, tmp_path):
    src = _shot(tmp_path, render_pass_module)
    shared = _copy(src, tmp_path / "farm_share")  # what the workers see
    single = _copy(src, tmp_path / "workstation")
    shutil.rmtree(src / "translucency_cache")  # the workers must not find the original
    cache = shared.parent / "translucency_cache"
    for p in [cache, *cache.iterdir()]:  # read-only for the workers (root ignores the bits; the snapshot checks)
        p.chmod(p.stat().st_mode & ~(stat.S_IWUSR | stat.S_IWGRP | stat.S_IWOTH))
    before = _snapshot(shared.parent)
    try:
        workers = {f: _run(shared, f, f, tmp_path / f"worker_{f}", wait=False) for f in FRAMES}
        logs = {f: p.communicate(timeout=600)[0] for f, p in workers.items()}
        log_single = _run(single, 1, 9, tmp_path / "single")
        after = _snapshot(shared.parent)
    finally:
        for p in [cache, *cache.iterdir()]:
            p.chmod(p.stat().st_mode | stat.S_IWUSR)
    for f, log in logs.items():
        assert workers[f].returncode == 0 and "WORKER DONE" in log, log[-3000:]
        assert "loaded the bake of 'Blob'" in log and f"frame {f}: 'Blob' solved on the" in log, log[-3000:]
    assert "WORKER DONE" in log_single and "frame 9: 'Blob' solved on the" in log_single, log_single[-3000:]
    assert after == before, "a render wrote into the shared folder"

    farm = {}
    for f in FRAMES:
        farm.update(_passes(tmp_path / f"worker_{f}", [f]))
    one = _passes(tmp_path / "single", range(1, 10))
    for f in FRAMES:
        assert farm[f].max() > 0, f"frame {f}: the pass is black"
        np.testing.assert_allclose(farm[f], one[f], rtol=1e-5, atol=1e-7 * one[f].max(), err_msg=f"frame {f}")
        attr_farm = np.load(tmp_path / f"worker_{f}" / f"radiance_{f:04d}.npy")
        attr_one = np.load(tmp_path / "single" / f"radiance_{f:04d}.npy")
        np.testing.assert_allclose(attr_farm, attr_one, rtol=1e-5, atol=1e-7 * attr_one.max(), err_msg=f"frame {f}")
    # The light moves and brightens: every frame is its own solve, not one frame's values rendered nine times.
    assert np.abs(one[5] - one[1]).max() > 0.1 * one[5].max()
    assert np.abs(one[9] - one[5]).max() > 0.1 * one[9].max()
    print("worker of frame 5:\n" + "\n".join(line for line in logs[5].splitlines() if "Translucency" in line))
    print("max relative difference of the pass, farm vs one process:",
          json.dumps({f: float(np.abs(farm[f] - one[f]).max() / one[f].max()) for f in FRAMES}))


def test_a_worker_without_a_usable_cache_fails_its_frame(render_pass_module, memo_bakes, tmp_path):
    from translucency.translucency_addon import cache

    src = _shot(tmp_path, render_pass_module)
    # 1. The .blend copied without its cache folder: the frame fails with the reason; no image, nothing baked.
    bare = tmp_path / "bare"
    bare.mkdir()
    shutil.copy(src / "shot.blend", bare / "shot.blend")
    log = _run(bare / "shot.blend", 5, 5, tmp_path / "out_bare")
    assert "Translucency: frame 5 FAILED, the render stops with exit code 1 and writes no image" in log, log[-3000:]
    assert "the bake cache of 'Blob' is not on this machine" in log and "Copy the cache folder" in log
    assert "WORKER DONE" not in log
    assert not list((tmp_path / "out_bare").glob("frame_*")), "a failed frame wrote an image"
    assert sorted(p.name for p in bare.iterdir()) == ["shot.blend"], "a render wrote a cache"

    # 2. A cache written by another version of the extension (another cache format): the same, naming both.
    other = _copy(src, tmp_path / "other_version")
    (npz,) = (other.parent / "translucency_cache").glob("*.npz")
    with np.load(npz, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    meta = json.loads(arrays["meta"].tobytes())
    meta["format"], meta["extension_version"] = cache.CACHE_FORMAT + 1, "9.9.9"
    arrays["meta"] = np.frombuffer(json.dumps(meta).encode(), np.uint8)
    np.savez(npz, **arrays)
    before = _snapshot(other.parent)
    log = _run(other, 5, 5, tmp_path / "out_other")
    assert "frame 5 FAILED" in log and "written by Translucency 9.9.9" in log, log[-3000:]
    assert "Install the same extension version on every machine" in log
    assert not list((tmp_path / "out_other").glob("frame_*"))
    assert _snapshot(other.parent) == before

    # 3. "Render Without": the frame renders, without the pass (never the values the .blend was saved with).
    log = _run(bare / "shot.blend", 5, 5, tmp_path / "out_skip", policy="SKIP")
    assert "WORKER DONE" in log and "frame 5: 'Blob' renders WITHOUT its Translucency pass" in log, log[-3000:]
    assert _passes(tmp_path / "out_skip", [5])[5].max() == 0.0
    assert sorted(p.name for p in bare.iterdir()) == ["shot.blend"]


def test_bake_refuses_a_read_only_cache_directory(blender, addon, memo_bakes, tmp_path, monkeypatch):
    """A read-only share (a worker, or a user without write access): the bake says so before any work, writes
    nothing and leaves the object as it was."""
    from translucency.ops import cache_files

    share = tmp_path / "share"
    share.mkdir()
    share.chmod(0o555)
    if os.access(share, os.W_OK):  # root ignores the bits; a read-only mount is what it would meet
        real_access = os.access
        monkeypatch.setattr(cache_files.os, "access",
                            lambda p, mode, **kw: False if os.path.samefile(p, share) else real_access(p, mode, **kw))
    try:
        for directory in (share, share / "translucency_cache"):  # the folder itself, or the one above it
            bpy.context.scene.translucency.cache_directory = str(directory) + os.sep
            obj = bpy.data.objects.get("Blob") or sphere()
            activate(obj)
            with pytest.raises(RuntimeError) as info:
                bpy.ops.translucency.bake(base_triangles=200)
            text = str(info.value)
            assert "Cannot bake 'Blob': cannot write the bake cache" in text, text
            assert "read-only" in text and "Choose a writable Cache Directory" in text and "nothing was written" in text
            assert obj.translucency.bake_key == "" and obj.translucency.cache_filepath == ""
            assert obj.data.attributes.get("translucency_radiance") is None
            assert list(share.iterdir()) == []
            assert memo_bakes.calls == 0  # refused before the bake started
    finally:
        share.chmod(0o755)


def test_a_cache_moved_into_the_cache_directory_is_found_by_name(blender, addon, memo_bakes, tmp_path, capfd):
    """A cache baked into another folder (an absolute Cache Directory, or the temporary folder of an unsaved
    .blend), then copied next to the .blend: found by its file name in the scene's Cache Directory, and the
    log says where; the stored path is not rewritten (a render changes nothing)."""
    from translucency.ops import runtime, state

    scene = bpy.context.scene
    scene.translucency.cache_directory = str(tmp_path / "elsewhere") + os.sep
    obj = sphere()
    add_light(location=(3.0, 0.0, 1.0))
    activate(obj)
    assert bpy.ops.translucency.bake(base_triangles=200) == {'FINISHED'}
    stored = obj.translucency.cache_filepath
    (baked,) = (tmp_path / "elsewhere").glob("*.npz")
    assert os.path.isabs(stored) and os.path.samefile(stored, baked)
    shot = tmp_path / "shot"
    (shot / "translucency_cache").mkdir(parents=True)
    scene.translucency.cache_directory = "//translucency_cache/"
    bpy.ops.wm.save_as_mainfile(filepath=str(shot / "shot.blend"))
    shutil.move(baked, shot / "translucency_cache" / baked.name)  # the farm copy: the old folder is gone
    state.clear()
    capfd.readouterr()
    report = runtime.solve_object(obj, scene, force=True)
    assert report is not None and report.ms_ran
    out = capfd.readouterr().out
    found = shot / "translucency_cache" / baked.name
    assert f"the cache of 'Blob' is not at {stored} (the path the .blend stores); using {found}" in out, out
    assert obj.translucency.cache_filepath == stored


def test_a_single_file_farm_renders_from_the_cache_packed_into_the_blend(render_pass_module, memo_bakes, tmp_path):
    """Pack Cache: the .blend alone renders on a worker (the cache comes out of the .blend into the temporary
    folder, checked like any cache file), with the radiance this process solves for the same frame."""
    from translucency.ops import attributes, runtime

    src = _shot(tmp_path, render_pass_module)
    obj = bpy.data.objects["Blob"]
    size = os.path.getsize(next((src / "translucency_cache").glob("*.npz")))
    assert bpy.ops.translucency.pack_cache() == {'FINISHED'}
    text = bpy.data.texts[obj.translucency.packed_cache]
    assert text.name.startswith(".translucency_cache Blob_") and text.use_fake_user
    bpy.ops.wm.save_mainfile()
    single = tmp_path / "single_file"
    single.mkdir()
    shutil.copy(src / "shot.blend", single / "shot.blend")
    unpacked = Path(tempfile.gettempdir()) / "translucency_packed"
    suffix = "_" + text.name[len(".translucency_cache "):]
    for old in unpacked.glob("*" + suffix):  # an earlier run's copy would be reused, not written
        old.unlink()
    log = _run(single / "shot.blend", 5, 5, tmp_path / "out_packed")
    assert "WORKER DONE" in log and "using the cache of 'Blob' packed into the .blend" in log, log[-3000:]
    (copy,) = unpacked.glob("*" + suffix)  # readable like any file the worker writes, not mkstemp's 0600
    assert stat.S_IMODE(copy.stat().st_mode) == umask_mode(), oct(copy.stat().st_mode)
    assert sorted(p.name for p in single.iterdir()) == ["shot.blend"]
    worker = np.load(tmp_path / "out_packed" / "radiance_0005.npy")
    scene = bpy.context.scene
    scene.frame_set(5)
    runtime.solve_object(obj, scene, use_camera=True, force=True)
    np.testing.assert_allclose(worker, attributes.read_radiance(obj), rtol=1e-5, atol=1e-7 * worker.max())
    assert _passes(tmp_path / "out_packed", [5])[5].max() > 0
    # Unpack: the Text is gone, the cache file stays.
    assert bpy.ops.translucency.pack_cache(unpack=True) == {'FINISHED'}
    assert obj.translucency.packed_cache == ""
    assert not [t for t in bpy.data.texts if t.name.startswith(".translucency_cache")]
    assert os.path.getsize(next((src / "translucency_cache").glob("*.npz"))) == size
    # A re-bake re-packs the new cache; Free Bake removes the packed copy with the bake.
    assert bpy.ops.translucency.pack_cache() == {'FINISHED'}
    old_key = obj.translucency.bake_key
    assert bpy.ops.translucency.bake(base_triangles=160) == {'FINISHED'}  # another graph, another key
    assert obj.translucency.bake_key != old_key
    (packed,) = [t for t in bpy.data.texts if t.name.startswith(".translucency_cache")]
    assert packed.name == obj.translucency.packed_cache and obj.translucency.bake_key[:16] in packed.name
    assert bpy.ops.translucency.free_bake() == {'FINISHED'}
    assert not [t for t in bpy.data.texts if t.name.startswith(".translucency_cache")]
    assert obj.translucency.packed_cache == ""


def test_a_stale_cache_in_a_render_is_named_and_never_rendered(render_pass_module, memo_bakes, tmp_path, capfd):
    """A cache file that holds another bake than the object's (same name, another key: a folder copied from an
    older version of the shot): the render names it and renders without the pass, never the stale values.
    (In-process with "Render Without": "Fail the Frame" would end this test process.)"""
    from translucency.ops import state

    src = _shot(tmp_path, render_pass_module)
    scene = bpy.context.scene
    obj = bpy.data.objects["Blob"]
    (npz,) = (src / "translucency_cache").glob("*.npz")
    with np.load(npz, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    meta = json.loads(arrays["meta"].tobytes())
    meta["key"] = "0" * 64
    arrays["meta"] = np.frombuffer(json.dumps(meta).encode(), np.uint8)
    np.savez(npz, **arrays)
    before = _snapshot(src)
    state.clear()
    scene.translucency.missing_cache_in_render = 'SKIP'
    scene.render.filepath = str(tmp_path / "stale_")
    capfd.readouterr()
    scene.frame_set(5)
    bpy.ops.render.render(write_still=True)
    out = capfd.readouterr().out
    assert "frame 5: 'Blob' renders WITHOUT its Translucency pass: bake cache" in out and "is stale" in out, out
    assert obj.data.attributes.get("translucency_radiance") is None
    assert _snapshot(src) == before


# ------------------------------------------------------------------ issue 32: every frame right or loudly refused
#
# A frame's pass depends on the frame, never on what the worker rendered before: a pose the deformation check
# refuses and a bake that no longer matches the mesh either fail the frame (exit 1, the reason as the log's last
# line) or, with "Render Without", render without the pass; the same on a fresh worker and on one that rendered
# other frames first, bit for bit.

REFUSED = 10  # the posed shot's frame whose pose folds the baked graph


def _posed_shot(tmp_path, render_pass_module):
    """A Draft bake of the deformation tests' bar with a two-bone rig, saved as ``tmp_path/src/shot.blend``:
    frame 1 at rest, frame 9 bent by 20 degrees (a valid pose), frame 10 by 150 degrees with linear skinning
    (the graph folds: refused)."""
    from test_ops_deformation import armature, bar, key_bend, sun

    src = tmp_path / "src"
    src.mkdir()
    bpy.ops.wm.save_as_mainfile(filepath=str(src / "shot.blend"))
    scene = bpy.context.scene
    obj = bar()
    rig = armature(obj, blend=0.2, preserve_volume=False)
    sun()
    key_bend(rig, 1, 0.0)
    key_bend(rig, 9, 20.0)
    key_bend(rig, REFUSED, 150.0)
    cam = bpy.data.objects.new("cam", bpy.data.cameras.new("cam"))
    cam.data.type, cam.data.ortho_scale = 'ORTHO', 6.0
    cam.location, cam.rotation_euler = (0.0, -10.0, 1.0), (np.pi / 2, 0.0, 0.0)
    scene.collection.objects.link(cam)
    scene.camera = cam
    _render_and_bake(scene, obj, render_pass_module)
    scene.frame_set(9)  # the .blend is saved holding frame 9's radiance (what a fresh worker would find)
    bpy.ops.wm.save_mainfile()
    return src


def _render(blend, first, last, out, policy, name):
    """A worker rendering ``first``..``last``: ``(exit code, log)``."""
    proc = _run(blend, first, last, out, policy=policy, name=name, wait=False)
    log = proc.communicate(timeout=600)[0]
    return proc.returncode, log


def _channels(path):
    from tools.exr import read_exr

    return read_exr(path)


def _assert_same_everywhere(runs, frame, policy, reason):
    """``runs``: {label: (exit code, log, out folder)} of workers that each rendered ``frame`` last."""
    codes = {label: rc for label, (rc, _log, _out) in runs.items()}
    if policy == 'FAIL':
        assert set(codes.values()) == {1}, codes
        for label, (_rc, log, out) in runs.items():
            last = log.strip().splitlines()[-1]
            assert last.startswith(f"Translucency: frame {frame} FAILED, the render stops with exit code 1") and \
                reason in last, f"{label}: {log[-3000:]}"
            assert not (out / f"frame_{frame:04d}.exr").exists(), f"{label}: a failed frame wrote an image"
        return
    assert set(codes.values()) == {0}, {label: (rc, log[-2000:]) for label, (rc, log, _out) in runs.items()}
    images = {label: _channels(out / f"frame_{frame:04d}.exr") for label, (_rc, _log, out) in runs.items()}
    (first_label, first), *others = images.items()
    for label, image in others:
        assert sorted(image) == sorted(first)
        for channel in first:  # bit for bit
            assert np.array_equal(image[channel], first[channel]), (label, first_label, channel)
    for _label, (_rc, log, _out) in runs.items():
        assert f"frame {frame}: " in log and "renders WITHOUT its Translucency pass" in log and reason in log, log
    aov = [c for c in first if ".Translucency." in c and c[-1] in "RGB"]
    assert aov and all(first[c].max() == 0.0 for c in aov), "the pass of a refused frame is not empty"


@pytest.mark.parametrize("policy", ['FAIL', 'SKIP'])
def test_a_refused_pose_renders_the_same_on_every_worker(render_pass_module, memo_bakes, tmp_path, policy):
    """Frame 10's pose folds the graph.  A fresh worker (the .blend holds frame 9's radiance) and a worker that
    rendered frame 9 first give the same result: exit 1 with the reason last under Fail the Frame; with Render
    Without, exit 0 and the same image bit for bit, without the pass; never frame 9's radiance."""
    src = _posed_shot(tmp_path, render_pass_module)
    blend = src / "shot.blend"
    runs = {}
    for label, first in (("fresh", REFUSED), ("after frame 9", 9)):
        out = tmp_path / label.replace(" ", "_")
        rc, log = _render(blend, first, REFUSED, out, policy, "Bar")
        runs[label] = (rc, log, out)
    _assert_same_everywhere(runs, REFUSED, policy, "folds the baked graph")
    for _rc, log, _out in runs.values():  # a render never claims to keep another frame's radiance
        assert "nothing was solved for this frame" in log and "keeps frame" not in log, log[-3000:]
    rc, log, out = runs["after frame 9"]
    assert "frame 9: 'Bar' solved on the CPU" in log, log[-3000:]
    assert _passes(out, [9])[9].max() > 0.0  # frame 9 rendered its own pose


@pytest.mark.parametrize("policy", ['FAIL', 'SKIP'])
def test_a_stale_bake_renders_the_same_on_every_worker(render_pass_module, memo_bakes, tmp_path, policy):
    """A Subdivision modifier added after the bake (another vertex count: not a pose): no worker solves the rest
    pose on the old graph.  A fresh worker on frame 5 and one rendering 4 then 5 both fail (exit 1, the re-bake
    reason last), or both render frame 5 without the pass, bit for bit the same."""
    src = _shot(tmp_path, render_pass_module)
    obj = bpy.data.objects["Blob"]
    obj.modifiers.new("Subdivision", type="SUBSURF")
    bpy.ops.wm.save_mainfile()
    blend = src / "shot.blend"
    runs = {}
    for label, first in (("fresh", 5), ("after frame 4", 4)):
        out = tmp_path / label.replace(" ", "_")
        rc, log = _render(blend, first, 5, out, policy, "Blob")
        runs[label] = (rc, log, out)
    if policy == 'SKIP':
        _assert_same_everywhere(runs, 5, policy, "re-bake to update the graph")
    else:  # each worker fails its first frame
        _assert_same_everywhere({"fresh": runs["fresh"]}, 5, policy, "re-bake to update the graph")
        _assert_same_everywhere({"after frame 4": runs["after frame 4"]}, 4, policy, "re-bake to update the graph")
    for _rc, log, _out in runs.values():
        assert "solved on the" not in log, log[-3000:]
