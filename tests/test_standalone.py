# SPDX-License-Identifier: GPL-3.0-or-later
"""The repository stands alone: a clone with nothing beside it runs the demo and the tests.

* No tracked file outside ``docs/`` names a path outside the repository: the folder beside the
  checkout that the project once read its meshes from, or an absolute path of one machine.
  (``docs/`` keeps its history: old benchmark commands quoted as they were run.)
* The meshes the demo, the tests and the benchmarks read are in ``data/meshes`` and resolve
  through the one function ``data.mesh_path``; a missing one is an error that names the file.
* The extension zip leaves ``data/`` out (the manifest's exclude list), so it does not grow.
"""

from __future__ import annotations

import re
import subprocess
import tomllib

import pytest

from conftest import ROOT
from data import MESHES, mesh_names, mesh_path
from translucency_addon.geometry import meshio

# Written in pieces so this file does not match itself.
_OUTSIDE = [
    re.escape(".." + "/shared"),                      # the reference folder beside the checkout
    r"(?<![\w.])/" + "work" + r"/",                   # this workplace's absolute paths
    r"(?<![\w.])/" + "root" + r"/",
    r"(?<![\w.])/" + "home" + r"/\w",
    r"(?<![\w.])/" + "Users" + r"/\w",
    r"\b[A-Z]:\\" + r"\\?" + "Users",
]
OUTSIDE = re.compile("|".join(_OUTSIDE))

# What each mesh is, as data/README.md's table states it (vertices, triangles).
COUNTS = {"stanford-bunny": (35_947, 69_451), "spot": (2_930, 5_856), "fandisk": (6_475, 12_946),
          "rocker-arm": (10_044, 20_088)}


def _tracked_files() -> list[str]:
    proc = subprocess.run(["git", "ls-files", "-z"], cwd=ROOT, capture_output=True, text=True)
    if proc.returncode != 0:  # an exported tree without .git: every file under the root
        return [str(p.relative_to(ROOT)) for p in ROOT.rglob("*")
                if p.is_file() and not any(part.startswith(".venv") or part == ".git" for part in p.parts)]
    return [f for f in proc.stdout.split("\0") if f]


def test_no_tracked_file_names_a_path_outside_the_repository():
    hits = []
    for name in _tracked_files():
        if name.startswith("docs/"):
            continue
        path = ROOT / name
        try:
            text = path.read_text(encoding="utf-8")
        except (UnicodeDecodeError, FileNotFoundError, IsADirectoryError):
            continue  # binary data (meshes' npz, EXR, PNG) or a file deleted in the work tree
        for lineno, line in enumerate(text.splitlines(), 1):
            if OUTSIDE.search(line):
                hits.append(f"{name}:{lineno}: {line.strip()[:120]}")
    assert not hits, ("these lines name a path outside the repository; a clone with nothing beside it "
                      "cannot follow them (put the data under data/ and resolve it with data.mesh_path):\n"
                      + "\n".join(hits))


def test_the_pattern_catches_what_it_is_for():
    """The check above is only as good as its pattern: each kind of outside path is caught."""
    for line in ['MESH = ROOT.parent / "shared" / "meshes"'.replace('ROOT.parent / "shared"', ".." + "/shared"),
                 'BUNNY = "/' + 'work/shared/meshes/stanford-bunny.obj"',
                 "python bench/frame.py --baseline /" + "home/alice/main",
                 "C:\\" + "Users\\bob\\mesh.obj"]:
        assert OUTSIDE.search(line), line
    for line in ["data/meshes/spot.obj", "bench/out/frame.md", "see docs/accuracy.md", "tmp_path / 'work/'"]:
        assert not OUTSIDE.search(line), line


@pytest.mark.parametrize("name", sorted(COUNTS))
def test_each_mesh_is_in_the_repository_and_loads(name):
    path = mesh_path(name)
    assert path.parent == MESHES and path.is_file()
    assert mesh_path(name + ".obj") == path
    V, F = meshio.load_obj(path)[:2]
    assert (len(V), len(F)) == COUNTS[name]
    readme = (ROOT / "data" / "README.md").read_text()
    assert f"`{name}.obj`" in readme, "data/README.md must give each mesh's source and terms"


def test_the_meshes_are_exactly_the_documented_ones():
    assert mesh_names() == sorted(COUNTS)


def test_a_missing_mesh_is_an_error_that_names_the_file():
    with pytest.raises(FileNotFoundError) as err:
        mesh_path("teapot")
    text = str(err.value)
    assert "teapot.obj" in text and "data/meshes" in text
    for name in COUNTS:  # and says what is there
        assert name in text


def test_the_extension_zip_leaves_the_data_out():
    manifest = tomllib.loads((ROOT / "blender_manifest.toml").read_text())
    assert "/data/" in manifest["build"]["paths_exclude_pattern"]


def test_the_demo_and_the_test_meshes_resolve_through_data():
    """The demo, the shared test bakes and the hard cases find their meshes with data.mesh_path."""
    for rel in ("demo/demo.py", "tests/bakes.py", "tests/hard_cases/cases.py", "bench/accuracy_scenes.py"):
        text = (ROOT / rel).read_text()
        assert "mesh_path(" in text, f"{rel} does not resolve its meshes through data.mesh_path"


def test_the_tests_run_in_a_clone_whose_folder_name_is_no_identifier(tmp_path):
    """A stranger may clone into ``translucency-main``: pytest must not import the root ``__init__.py``
    (the add-on) under the folder's name (it failed every test there with a relative-import error)."""
    import shutil
    import sys

    clone = tmp_path / "translucency-main"
    for name in _tracked_files():
        if name.startswith(("tests/", "translucency_addon/", "data/")) or "/" not in name:
            target = clone / name
            target.parent.mkdir(parents=True, exist_ok=True)
            if (ROOT / name).is_file():
                shutil.copy2(ROOT / name, target)
    proc = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider",
                           "tests/test_standalone.py", "-k", "pattern_catches"],
                          cwd=clone, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, (proc.stdout + proc.stderr)[-3000:]
    assert "1 passed" in proc.stdout
