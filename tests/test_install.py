# SPDX-License-Identifier: GPL-3.0-or-later
"""Build the extension zip, validate it, and install it with Blender's real
mechanism (``bpy.ops.extensions.package_install_files``), then disable it.

Runs on the bpy pinned for tests (5.2 LTS, Python 3.13).  To also run it on
another Blender, set one variable, e.g.::

    TRANSLUCENCY_BPY=4.5 .venv/bin/python -m pytest -q tests/test_install.py

``test_install_on_other_blender`` then creates ``.venv-bpy45`` (bpy 4.5 LTS,
numpy and pytest only, via ``tools/setup.sh``, on the Python that release
ships) and runs this file there; the bundled wheels must then come from the
extension, because that environment has no scipy, pytetwild or
fast_simplification of its own.  4.2, 4.5, 5.0, 5.1 and 5.2 are known series.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tomllib
import zipfile
from pathlib import Path

import bpy
import numpy as np
import pytest

from conftest import ROOT, addon_is_registered, factory_reset

MODULE = "bl_ext.user_default.translucency"
EXPECTED_TOP_LEVEL = {"__init__.py", "blender_manifest.toml", "LICENSE", "ops", "translucency_addon", "wheels"}
BUNDLED = ("scipy", "pytetwild", "fast_simplification")
# The fluid cells' compiled faces: in every zip of a platform PyPI has their wheels for (not macOS x86-64).
COMPILED = ("numba", "llvmlite")


def _blender_ext() -> Path:
    scripts = Path(bpy.utils.system_resource('SCRIPTS'))
    return scripts / "addons_core" / "bl_pkg" / "cli" / "blender_ext.py"


@pytest.fixture(scope="session")
def extension_zip(tmp_path_factory):
    """Build the zip once per session with tools/build_extension.py."""
    out = tmp_path_factory.mktemp("dist")
    summary_path = out / "summary.json"
    proc = subprocess.run(
        [sys.executable, str(ROOT / "tools" / "build_extension.py"),
         "--output-dir", str(out), "--json", str(summary_path)],
        capture_output=True, text=True, timeout=1800, cwd=ROOT)
    assert proc.returncode == 0, f"build failed:\n{proc.stdout[-4000:]}\n{proc.stderr[-4000:]}"
    summary = json.loads(summary_path.read_text())
    # The default build: one zip per platform (the extensions platform's format), each for both Pythons.
    zips = {Path(z).name: Path(z) for z in summary["zips"]}
    assert sorted(zips) == sorted(f"translucency-{_version()}-{p.replace('-', '_')}.zip" for p in summary["platforms"])
    for name, path in zips.items():
        with zipfile.ZipFile(path) as zf:
            manifest = _manifest(zf)
        platform = name.rsplit("-", 1)[1].removesuffix(".zip").replace("_", "-")
        assert manifest["platforms"] == [platform], (name, manifest["platforms"])
        assert all(w.removeprefix("./wheels/") in summary["wheels"][platform] for w in manifest["wheels"]), name
    return zips[f"translucency-{_version()}-linux_x64.zip"], summary


def _manifest(zf) -> dict:
    """The zip's manifest as Blender reads it: a split build writes each zip's own ``platforms`` and ``wheels``
    into ``[build.generated]``, which override the source manifest's."""
    manifest = tomllib.loads(zf.read("blender_manifest.toml").decode())
    return {**manifest, **manifest.get("build", {}).get("generated", {})}


def _version() -> str:
    return tomllib.loads((ROOT / "blender_manifest.toml").read_text())["version"]


def test_zip_validates_and_holds_only_the_extension(extension_zip):
    zip_path, summary = extension_zip
    proc = subprocess.run([sys.executable, str(_blender_ext()), "validate", str(zip_path)],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    with zipfile.ZipFile(zip_path) as zf:
        names = zf.namelist()
        manifest = _manifest(zf)
    top = {name.split("/", 1)[0] for name in names}
    assert top <= EXPECTED_TOP_LEVEL | {"gpu_shaders"}, top - EXPECTED_TOP_LEVEL
    assert EXPECTED_TOP_LEVEL <= top
    assert not [n for n in names if "__pycache__" in n or n.endswith(".pyc")]

    assert manifest["id"] == "translucency"
    assert manifest["type"] == "add-on"
    assert manifest["license"] == ["SPDX:GPL-3.0-or-later"]
    # Blender older than 4.2 has no extension system and refuses this manifest;
    # 4.2+ compares blender_version_min before installing.
    assert tuple(int(x) for x in manifest["blender_version_min"].split(".")) == (4, 2, 0)
    assert manifest["platforms"] == ["linux-x64"]
    wheels = [Path(w).name for w in manifest["wheels"]]
    assert sorted("wheels/" + w for w in wheels) == sorted(n for n in names if n.startswith("wheels/") and n != "wheels/")
    assert not [w for w in wheels if w.startswith("numpy-")], "numpy ships with Blender"
    linux = summary["wheels"]["linux-x64"]
    for dist in BUNDLED + COMPILED:
        assert any(w.startswith(dist + "-") and "linux" in w for w in linux), (dist, linux)
    # A platform without numba's wheels still gets its zip, without them, and the summary says why.
    for platform, missing in summary["without_compiled"].items():
        assert platform in summary["platforms"] and missing.split("==")[0] in COMPILED, (platform, missing)
        assert not [w for w in summary["wheels"][platform] if w.startswith(COMPILED)], platform
    # Every supported Blender's Python has its wheels: 3.11 (4.2-5.0) and 3.13 (5.1-5.2).
    # Blender reads the versions from the wheel tags; an abi3 wheel serves every newer CPython.
    assert summary["pythons"] == ["3.11", "3.13"]
    for abi in ("cp311", "cp313"):
        for dist in BUNDLED + COMPILED:
            assert any(w.startswith(dist + "-") and (f"-{abi}-" in w or _abi3_serves(w, abi)) for w in linux), \
                (dist, abi, linux)


def _abi3_serves(wheel: str, abi: str) -> bool:
    python_tag, abi_tag = wheel.split("-")[-3:-1]
    return abi_tag == "abi3" and python_tag.startswith("cp") and int(python_tag[2:]) <= int(abi[2:])


def _local_site_packages() -> Path:
    local = Path(bpy.utils.user_resource('EXTENSIONS', path=".local"))
    return local / "lib" / f"python{sys.version_info.major}.{sys.version_info.minor}" / "site-packages"


def _registered_now() -> dict:
    return {
        "panel_object": hasattr(bpy.types, "OBJECT_PT_translucency"),
        "panel_sidebar": hasattr(bpy.types, "VIEW3D_PT_translucency"),
        "operator": hasattr(bpy.types, "TRANSLUCENCY_OT_check_dependencies"),
        "object_settings": "translucency" in bpy.types.Object.bl_rna.properties,
        "scene_settings": "translucency" in bpy.types.Scene.bl_rna.properties,
    }


def test_install_enable_disable(extension_zip, tmp_path):
    zip_path, _summary = extension_zip
    working_tree = sys.modules.get("translucency")
    if working_tree is not None and addon_is_registered(working_tree):
        working_tree.unregister()
    factory_reset()
    assert not any(_registered_now().values()), "nothing may be registered before the install"

    result = bpy.ops.extensions.package_install_files(
        filepath=str(zip_path), repo='user_default', enable_on_install=True)
    try:
        assert result == {'FINISHED'}
        assert MODULE in bpy.context.preferences.addons
        assert all(_registered_now().values()), _registered_now()
        assert hasattr(bpy.ops.translucency, "check_dependencies")
        module = sys.modules[MODULE]
        assert Path(module.__file__).parent == Path(bpy.utils.user_resource('EXTENSIONS')) / "user_default" / "translucency"

        # Blender unpacked the linux wheels into the extensions' site-packages.
        site = _local_site_packages()
        for dist in BUNDLED + COMPILED:
            assert (site / dist).is_dir(), f"{dist} was not installed into {site}"
        module.ops.dependencies.clear_cache()
        assert module.ops.dependencies.missing() == []
        bpy.ops.translucency.check_dependencies()

        # The installed wheels work on their own: import them (and tetrahedralize
        # a tetrahedron) with the extensions' site-packages first on the path.
        code = (
            "import numpy as np, scipy.sparse.linalg, fast_simplification, pytetwild\n"
            "V = np.array([[0,0,0],[1,0,0],[0,1,0],[0,0,1]], float)\n"
            "F = np.array([[0,2,1],[0,1,3],[0,3,2],[1,2,3]], np.int32)\n"
            "v, t = pytetwild.tetrahedralize(V, F, optimize=False, quiet=True)\n"
            "assert len(t) > 0\n"
            "import numba, llvmlite\n"
            "assert numba.njit(lambda x: 2 * x + 1)(20) == 41\n"
            "print(scipy.__file__); print(pytetwild.__file__); print(fast_simplification.__file__)\n"
            "print(numba.__file__); print(llvmlite.__file__)\n")
        env = dict(os.environ, PYTHONPATH=str(site))
        proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                              env=env, cwd=tmp_path, timeout=300)
        assert proc.returncode == 0, proc.stdout + proc.stderr
        for line in proc.stdout.split():
            assert Path(line).is_relative_to(site), f"{line} is not from the extension's wheels"

        # The installed extension bakes, solves and renders its AOV in this Blender.
        _bake_solve_render(tmp_path)

        # Disable: every class and property is gone.
        assert bpy.ops.preferences.addon_disable(module=MODULE) == {'FINISHED'}
        assert MODULE not in bpy.context.preferences.addons
        assert not any(_registered_now().values()), _registered_now()
    finally:
        if MODULE in bpy.context.preferences.addons:
            bpy.ops.preferences.addon_disable(module=MODULE)
        repo_index = next(i for i, repo in enumerate(bpy.context.preferences.extensions.repos)
                          if repo.module == "user_default")
        bpy.ops.extensions.package_uninstall(repo_index=repo_index, pkg_id="translucency")
        factory_reset()
    assert not (Path(bpy.utils.user_resource('EXTENSIONS')) / "user_default" / "translucency").exists()


def _bake_solve_render(tmp_path) -> None:
    """Bake (Draft), solve and render the ``Translucency`` AOV with Cycles through the installed extension."""
    scene = bpy.context.scene
    scene.translucency.cache_directory = str(tmp_path / "cache") + os.sep
    bpy.ops.mesh.primitive_ico_sphere_add(subdivisions=2, radius=1.0)
    obj = bpy.context.object
    s = obj.translucency
    s.quality, s.levels, s.use_mm_per_unit_override, s.mm_per_unit = 'DRAFT', 2, True, 10.0
    lamp = bpy.data.objects.new("Lamp", bpy.data.lights.new("Lamp", 'POINT'))
    lamp.data.energy, lamp.location = 1000.0, (3.0, 0.0, 2.0)
    scene.collection.objects.link(lamp)
    camera = bpy.data.objects.new("Camera", bpy.data.cameras.new("Camera"))
    camera.location = (0.0, 0.0, 5.0)  # looks down -z at the sphere
    scene.collection.objects.link(camera)
    scene.camera = camera
    assert bpy.ops.translucency.bake() == {'FINISHED'}
    assert bpy.ops.translucency.solve() == {'FINISHED'}
    assert bpy.ops.translucency.add_to_material() == {'FINISHED'}
    render_pass = sys.modules[MODULE + ".ops.render_pass"]
    scene.render.engine = 'CYCLES'
    scene.cycles.device, scene.cycles.samples, scene.cycles.use_denoising = 'CPU', 2, False
    scene.render.resolution_x = scene.render.resolution_y = 16
    scene.render.resolution_percentage = 100
    render_pass.configure_output(scene.render.image_settings, 'OPEN_EXR_MULTILAYER')
    scene.render.filepath = str(tmp_path / "frame.exr")
    bpy.ops.render.render(write_still=True)
    from tools.exr import exr_pass  # the repo's reader: not shipped in the zip

    rgb = exr_pass(tmp_path / "frame.exr")[..., :3]
    assert np.isfinite(rgb).all() and rgb.max() > 0.0, "the Translucency pass is black"
    assert rgb[0, 0].max() == 0.0, "the pass is not zero off the object (the image corner)"


def test_install_on_other_blender(extension_zip, tmp_path):
    """TRANSLUCENCY_BPY=4.5 runs this file again in .venv-bpy45 (bpy 4.5 LTS), likewise 4.2, 5.0, 5.1; then the
    render-pass and render-farm tests there, with the engine's wheels for that Python (the ones the Linux zip
    bundles) on PYTHONPATH, never installed into that environment."""
    wanted = os.environ.get("TRANSLUCENCY_BPY", "").strip()
    if not wanted:
        pytest.skip("set TRANSLUCENCY_BPY=4.5 (or another bpy version) to also install into that Blender")
    version = wanted.removesuffix(".x").removesuffix(".*")
    if bpy.app.version_string.startswith(version):
        pytest.skip(f"already running on bpy {bpy.app.version_string}")
    major, minor = version.split(".")[:2]
    env = {k: v for k, v in os.environ.items() if not k.startswith("BLENDER_USER_")}
    setup = subprocess.run(["bash", str(ROOT / "tools" / "setup.sh")], cwd=ROOT, env=env,
                           capture_output=True, text=True, timeout=1800)
    assert setup.returncode == 0, setup.stdout[-3000:] + setup.stderr[-3000:]
    python = ROOT / f".venv-bpy{major}{minor}" / "bin" / "python"
    env.pop("TRANSLUCENCY_BPY")
    probe = subprocess.run([str(python), "-c", "import bpy; print(bpy.app.version_string)"],
                           env=env, capture_output=True, text=True, timeout=300)
    assert probe.stdout.strip().startswith(version), probe.stdout + probe.stderr
    print(f"installing into bpy {probe.stdout.strip()} ({python})")
    proc = subprocess.run([str(python), "-m", "pytest", "-q", "-p", "no:cacheprovider",
                           str(ROOT / "tests" / "test_install.py")],
                          cwd=ROOT, env=env, capture_output=True, text=True, timeout=1800)
    print(proc.stdout[-3000:])
    assert proc.returncode == 0, proc.stdout[-5000:] + proc.stderr[-3000:]

    abi = subprocess.run([str(python), "-c", "import sys; print(f'cp{sys.version_info[0]}{sys.version_info[1]}')"],
                         capture_output=True, text=True, timeout=60).stdout.strip()
    _zip, summary = extension_zip
    wheels = [ROOT / "wheels" / w for w in summary["wheels"]["linux-x64"] if f"-{abi}-" in w or _abi3_serves(w, abi)]
    assert len(wheels) == len(BUNDLED + COMPILED), wheels
    site = tmp_path / "engine-wheels"
    unpack = subprocess.run([str(python), "-m", "pip", "install", "-q", "--no-deps", "--disable-pip-version-check",
                             "--target", str(site), *map(str, wheels)], capture_output=True, text=True, timeout=600)
    assert unpack.returncode == 0, unpack.stdout + unpack.stderr
    proc = subprocess.run([str(python), "-m", "pytest", "-q", "-p", "no:cacheprovider",
                           str(ROOT / "tests" / "test_render_pass.py"), str(ROOT / "tests" / "test_render_farm.py")],
                          cwd=ROOT, env=dict(env, PYTHONPATH=str(site)), capture_output=True, text=True, timeout=1800)
    print(proc.stdout[-1500:])
    assert proc.returncode == 0, proc.stdout[-5000:] + proc.stderr[-3000:]
