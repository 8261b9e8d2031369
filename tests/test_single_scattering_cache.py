"""Single scattering baked for a QuadGraph bake: keys, staleness, the cache round trip and the CLI."""

from __future__ import annotations

import json
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from translucency_addon import cache
from translucency_addon.geometry import meshio, primitives
from translucency_addon.quadgraph.bake import BakeSettings, bake_mesh
from translucency_addon.scene.fields import FieldSpec, evaluate_field
from translucency_addon.scene.lights import Light
from translucency_addon.scene.materials import Material, material_from_preset, preset
from translucency_addon.single_scattering import (FrameEvaluator, GridField, SingleScatteringSettings, attach,
                                                  bake_single_scattering_for, expected_key, fingerprint_field,
                                                  graph_key, stale_message, staleness)

ROOT = Path(__file__).resolve().parent.parent
SMALL = SingleScatteringSettings(quality="draft", n_dirs=32, n_samples=400)


@pytest.fixture(scope="module")
def graph():
    V, F = primitives.icosphere(1.0, 2)
    return bake_mesh(V, F, BakeSettings(quality="draft", levels=1, mm_per_unit=10.0, base_triangles=200))


@pytest.fixture(scope="module")
def with_ss(graph):
    data = bake_single_scattering_for(graph, material_from_preset("marble"), None, SMALL)
    return attach(graph, data)


def test_bake_for_records_its_inputs_and_the_key_includes_them(graph, with_ss):
    data = with_ss.single_scattering
    inputs = data.stats["inputs"]
    assert inputs["graph_key"] == graph.key and inputs["mm_per_unit"] == 10.0
    assert inputs["material"] == {"a": {"sigma_a": [0.0021, 0.0041, 0.0071], "sigma_s": [2.19, 2.62, 3.0]}}
    assert inputs["settings"]["n_dirs"] == 32 and inputs["field"] is None
    assert data.mm_per_unit == 10.0
    # the bake's key now says "with this single scattering"; the QuadGraph key is kept
    assert with_ss.key != graph.key and graph_key(with_ss) == graph.key
    assert with_ss.key == expected_key(graph, SMALL, material_from_preset("marble"))  # known before baking
    assert expected_key(graph, replace(SMALL, n_samples=500), material_from_preset("marble")) != with_ss.key
    assert expected_key(graph, SMALL, material_from_preset("skin1")) != with_ss.key
    assert expected_key(graph, SMALL, material_from_preset("marble"), mm_per_unit=20.0) != with_ss.key
    # the key of a bake never depends on the order things were attached in, and detaching restores it
    assert attach(with_ss, data).key == with_ss.key
    assert attach(with_ss, None).key == graph.key and attach(with_ss, None).single_scattering is None
    assert graph.single_scattering is None and "graph_key" not in graph.stats  # the input bake is untouched


def test_cache_round_trip(with_ss, tmp_path):
    path = cache.save_bake(tmp_path / "b.npz", with_ss)
    back = cache.load_bake(path, expected_key=with_ss.key)
    a, b = with_ss.single_scattering, back.single_scattering
    assert back.key == with_ss.key and graph_key(back) == graph_key(with_ss)
    for name in ("centers", "sigma", "weight", "support", "sigma_s", "sh"):
        assert np.array_equal(getattr(a, name), getattr(b, name)), name
    assert np.array_equal(a.grid.cell_items, b.grid.cell_items)
    assert b.stats["inputs"] == a.stats["inputs"] and b.stats["key"] == a.stats["key"]
    assert cache.read_meta(path)["stats"]["graph_key"] == graph_key(with_ss)
    assert staleness(b, settings=SMALL, material=material_from_preset("marble"), field_fp=None,
                     mm_per_unit=10.0, graph=graph_key(back)) == []
    # the same frame from the original and the loaded data
    lights = [Light("point", intensity=20.0, position=(3.0, 0.0, 2.0))]
    V, F, N = with_ss.mesh_vertices, with_ss.mesh_faces, with_ss.mesh_normals
    L1 = FrameEvaluator(a, V, F, N).radiance(lights, None, 1.3, 10.0, ("PERSP", (0.0, 0.5, 4.0)))
    L2 = FrameEvaluator(b, V, F, N).radiance(lights, None, 1.3, 10.0, ("PERSP", (0.0, 0.5, 4.0)))
    assert np.array_equal(L1, L2) and L1.max() > 0


def test_staleness_names_what_changed(with_ss):
    data = with_ss.single_scattering
    marble = material_from_preset("marble")
    assert staleness(data, material=marble, settings=SMALL) == []
    assert staleness(data, settings=replace(SMALL, sh_order=2)) == []  # lower order: truncated at run time
    reasons = staleness(data, material=material_from_preset("ketchup"))
    assert len(reasons) == 1 and "material changed" in reasons[0]
    msg = stale_message(reasons)
    assert "re-bake single scattering" in msg and "sigma_t" in msg
    assert staleness(data, material=Material(preset("marble"), eta=1.5)) == []  # eta is not baked
    assert "settings changed (directions 32 -> 128)" in staleness(data, settings=replace(SMALL, n_dirs=128))[0]
    assert "SH order" in staleness(replace(data, stats={**data.stats, "inputs": {
        **data.stats["inputs"], "settings": {**data.stats["inputs"]["settings"], "sh_order": 2}}}), settings=SMALL)[0]
    assert "scale changed" in staleness(data, mm_per_unit=20.0)[0]
    hetero = Material(preset("marble"), preset("ketchup"))
    r = staleness(data, material=hetero, field_fp=fingerprint_field(FieldSpec("layers", 0.3), hetero))
    assert any("material" in x for x in r) and any("field" in x for x in r)
    assert "re-baked" in staleness(data, graph="another")[0]
    assert stale_message([]) == ""


def test_field_sampled_on_the_grid_gives_the_same_bake(graph):
    """Blender samples the field on its main thread at the voxel centres (GridField); same result."""
    mat = Material(preset("marble"), preset("ketchup"))
    spec = FieldSpec("layers", 0.4)
    a = bake_single_scattering_for(graph, mat, spec, SMALL)
    origin, h, shape, pts = GridField.grid_points(graph.mesh_vertices, SMALL.quality)
    gf = GridField(origin, h, shape, evaluate_field(spec, pts))
    b = bake_single_scattering_for(graph, mat, gf, SMALL, field_fingerprint="blender-field-1")
    assert np.allclose(a.sigma_s, b.sigma_s) and np.array_equal(a.centers, b.centers)
    assert a.stats["inputs"]["field"].startswith("spec:") and b.stats["inputs"]["field"] == "blender-field-1"
    c = bake_single_scattering_for(graph, mat, gf, SMALL)  # a callable without a fingerprint: a digest of its values
    assert c.stats["inputs"]["field"].startswith("values:")
    assert staleness(a, material=mat, field_fp=fingerprint_field(spec, mat)) == []
    assert staleness(a, material=mat, field_fp=fingerprint_field(FieldSpec("layers", 0.5), mat)) != []


def test_progress_stages_and_cancel(graph):
    from translucency_addon.errors import BakeCancelled

    seen = []

    def progress(f, stage):
        seen.append(stage)
        if stage == "pds":
            raise BakeCancelled("stop")

    with pytest.raises(BakeCancelled):
        bake_single_scattering_for(graph, None, None, SMALL, progress=progress)
    assert seen[0] == "voxelise" and "ddod" in seen and seen[-1] == "pds"


# ------------------------------------------------------------------ CLI

def run_cli(*args, cwd):
    return subprocess.run([sys.executable, "-m", "translucency_addon", *map(str, args)], cwd=cwd,
                          env={"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin"}, capture_output=True, text=True,
                          timeout=300)


@pytest.fixture(scope="module")
def cli_cache(tmp_path_factory):
    d = tmp_path_factory.mktemp("cli")
    V, F = primitives.icosphere(1.0, 2)
    meshio.save_obj(d / "s.obj", V, F)
    r = run_cli("bake", "s.obj", "-o", "s.npz", "--quality", "draft", "--levels", "1", "--mm-per-unit", "10",
                "--single-scattering", "--ss-quality", "draft", "--ss-dirs", "32", "--ss-samples", "400", cwd=d)
    assert r.returncode == 0, r.stderr
    assert "single scattering: " in r.stdout
    return d


def test_cli_bake_single_scattering_writes_it_to_the_cache(cli_cache):
    b = cache.load_bake(cli_cache / "s.npz")
    ss = b.single_scattering
    assert ss is not None and ss.n_dirs == 32 and ss.stats["inputs"]["settings"]["n_samples"] == 400
    assert b.key != graph_key(b) and b.mm_per_unit == 10.0


def test_cli_solve_adds_single_scattering(cli_cache):
    """With Pass Planning 'All Passes' (``--pass-planning all``, as the add-on's setting) the baked single
    scattering runs beside diffusion on every channel; the frame is the two terms' sum.  (Under 'Automatic'
    the planner leaves it out for this marble sphere, where diffusion with the first-scatter split holds.)
    Turning the term off changes the plan (the diffusion then carries the split), so the off-run is not the
    on-run's diffusion term; what the frame is made of is checked against the add-on in test_cli_parity."""
    d = cli_cache
    light = ["--point", "3,0,2:1000", "--pass-planning", "all"]
    r = run_cli("solve", "s.npz", "-o", "all.npy", *light, "--stats", "st.json", "--ss-output", "ss.npy", cwd=d)
    assert r.returncode == 0, r.stderr
    assert "single scattering" in r.stdout and "warning" not in r.stderr
    r = run_cli("solve", "s.npz", "-o", "ms.npy", *light, "--no-single-scattering", "--stats", "st0.json", cwd=d)
    assert r.returncode == 0, r.stderr
    total, ms, ss = (np.load(d / n) for n in ("all.npy", "ms.npy", "ss.npy"))
    assert ss.max() > 0 and ss.min() >= 0
    assert np.all(total - ss >= -1e-6 * total.max()) and ms.min() >= 0  # the frame is diffusion + this term
    assert not np.allclose(total, ms, rtol=1e-3)
    r = run_cli("solve", "s.npz", "-o", "auto.npy", "--point", "3,0,2:1000", "--stats", "sta.json", cwd=d)
    assert r.returncode == 0, r.stderr
    auto = json.loads((d / "sta.json").read_text())["single_scattering"]
    assert not auto["enabled"] and "the planner leaves it out" in auto["reason"]
    st = json.loads((d / "st.json").read_text())
    assert st["single_scattering"]["enabled"] and st["seconds"]["single_scattering"] > 0
    assert st["single_scattering"]["n_samples"] == cache.load_bake(d / "s.npz").single_scattering.n_samples
    st0 = json.loads((d / "st0.json").read_text())
    assert not st0["single_scattering"]["enabled"] and st0["seconds"]["single_scattering"] == 0.0
    # a camera makes both terms view dependent
    r = run_cli("solve", "s.npz", "-o", "cam.npy", *light, "--camera", "0,0,5", "--ss-output", "sscam.npy", cwd=d)
    assert r.returncode == 0, r.stderr
    sscam = np.load(d / "sscam.npy")
    V = cache.load_bake(d / "s.npz").mesh_vertices
    assert np.all(sscam[V[:, 2] < -0.3] == 0) and sscam[V[:, 2] > 0.3].max() > 0  # back faces see nothing


def test_cli_reports_a_stale_single_scattering_bake(cli_cache):
    r = run_cli("solve", "s.npz", "-o", "k.npy", "--point", "3,0,2:1000", "--material", "ketchup", cwd=cli_cache)
    assert r.returncode == 0
    assert "single scattering needs a re-bake: the material changed" in r.stderr
    r = run_cli("solve", "s.npz", "-o", "k.npy", "--env", "1,1,1", "--mm-per-unit", "20", "--pass-planning", "all",
                cwd=cli_cache)
    assert r.returncode == 0 and "the scale changed" in r.stderr


def test_cli_without_single_scattering_data(cli_cache):
    d = cli_cache
    V, F = primitives.icosphere(1.0, 1)
    meshio.save_obj(d / "t.obj", V, F)
    r = run_cli("bake", "t.obj", "-o", "t.npz", "--quality", "draft", "--levels", "1", "--mm-per-unit", "10", cwd=d)
    assert r.returncode == 0, r.stderr
    r = run_cli("solve", "t.npz", "-o", "t.npy", "--env", "1,1,1", "--stats", "t.json", cwd=d)
    assert r.returncode == 0, r.stderr
    assert "bake with --single-scattering" in json.loads((d / "t.json").read_text())["single_scattering"]["reason"]
    r = run_cli("solve", "t.npz", "-o", "t.npy", "--env", "1,1,1", "--ss-output", "x.npy", cwd=d)
    assert r.returncode == 2 and "no single-scattering data" in r.stderr
    r = run_cli("bake", "t.obj", "-o", "u.npz", "--quality", "draft", "--levels", "1", "--single-scattering",
                "--ss-dirs", "3", cwd=d)
    assert r.returncode == 2 and "n_dirs must be at least 6" in r.stderr
