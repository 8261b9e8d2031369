# SPDX-License-Identifier: GPL-3.0-or-later
"""The accuracy benchmark (issue 8): quick-mode smoke test, a sanity check that cannot pass
by accident, and the preset cost file the Quality menu reads."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from bench import accuracy_scenes as scenes
from bench.accuracy_core import Evaluator
from bench.reference.metrics import relative_rms


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    """A tiny reference (12 x 12, 64 spp per channel: a few seconds) and one Draft bake."""
    from bench.reference.mitsuba_ref import cached_reference

    scene = scenes.make_scene("sphere", "marble", res=12, spp=64, light="uniform")
    ref = cached_reference(scene, tmp_path_factory.mktemp("ref"))
    ev = Evaluator(bake_cache=None, log=lambda *_: None)
    return scene, ref, ev


def _error(ev, scene, ref, **kw):
    r = ev.run(scene, dict(quality="draft"), dict(solver="fast", tol=1e-4), frames=False, **kw)
    return r, relative_rms(r.image, ref.image, r.mask, ref.mask, stderr=ref.stderr)


def test_quick_pipeline_reference_ours_metric(tiny):
    scene, ref, ev = tiny
    assert ref.image.shape == (12, 12, 3) and ref.mask.sum() > 50
    assert np.all(np.isfinite(ref.image)) and np.all(ref.stderr >= 0)
    r, err = _error(ev, scene, ref)
    assert r.mask.sum() > 50 and not r.diverged
    assert math.isfinite(err.rel_rms) and math.isfinite(err.noise_floor)
    assert err.pixels > 20
    assert err.rel_rms < 0.15  # marble under a uniform sky: diffusion is within a few per cent
    assert r.bake_s > 0 and r.first_ms > 0


def test_wrong_material_is_much_worse(tiny):
    """sigma_a x 10 against the same reference: the metric must see it (not pass by accident)."""
    from dataclasses import replace

    scene, ref, ev = tiny
    _, right = _error(ev, scene, ref)
    wrong_scene = replace(scene, material=scenes.material("marble", sigma_a_scale=10.0), name=scene.name + "_sa10")
    assert wrong_scene.material.medium_a.sigma_a[0] == pytest.approx(10 * scene.material.medium_a.sigma_a[0])
    _, wrong = _error(ev, wrong_scene, ref)
    assert wrong.rel_rms > 4.0 * right.rel_rms
    assert wrong.rel_rms > 0.1
    assert wrong.rel_rms > 3.0 * wrong.noise_floor


def test_scenes_are_closed_and_matched():
    from translucency_addon.geometry.meshio import count_holes, signed_volume

    for name in scenes.MESH_NAMES:
        V, F, mpu = scenes.mesh(name)
        assert count_holes(F)[0] == 0 and signed_volume(V, F) > 0
    s = scenes.make_scene("bunny", "hetero", res=8, spp=1)
    f = s.field_values(s.V)
    assert s.material.heterogeneous and 0.05 < f.mean() < 0.95  # both media present


# --- the preset cost file ----------------------------------------------------------------

def _costs_module():
    import importlib.util

    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    spec = importlib.util.spec_from_file_location("quality_costs_under_test", root / "ops" / "quality_costs.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_cost_file_schema_and_enum_texts():
    qc = _costs_module()
    data = json.loads(qc.COSTS_PATH.read_text())
    assert qc.validate(data) is None
    assert data["generated_by"] == "bench/accuracy.py"
    items = qc.quality_items()
    assert [i[0] for i in items] == ["DRAFT", "PREVIEW", "FINAL"]
    for ident, name, desc in items:
        e = data["presets"][ident.lower()]
        for text in (name, desc):
            assert qc.fmt_seconds(e["bake_s"]) in text
            assert qc.fmt_ms(e["frame_ms"]) in text
            assert qc.fmt_percent(e["rel_rms"]) in text
    # the numbers are the ones in the file, formatted as shown
    e = data["presets"]["preview"]
    assert f"{100 * e['rel_rms']:.1f} %" in items[1][1]


def test_cost_file_fallbacks(tmp_path):
    qc = _costs_module()
    assert qc.quality_items(tmp_path / "missing.json")[1] == qc.PRESETS[1]
    bad = tmp_path / "bad.json"
    bad.write_text('{"schema": 1, "presets": {"draft": {"bake_s": "fast"}}}')
    assert qc.load_costs(bad) is None and qc.quality_items(bad) == qc.PRESETS
    assert qc.validate({"schema": 1, "presets": {}}) is not None


def test_writer_output_matches_the_reader(tmp_path):
    """bench/accuracy.write_costs produces what ops/quality_costs accepts."""
    from types import SimpleNamespace

    from bench import accuracy

    recs = [{"knob": "preset", "label": q, "scene": accuracy.HEADLINE, "bake_s": 1.0 + i, "frame_ms": 10.0 * (i + 1),
             "first_ms": 20.0, "err_ref": 0.05 - 0.01 * i, "err_conv": 0.01, "noise_floor": 0.005, "nodes": [10, 20]}
            for i, q in enumerate(("draft", "preview", "final"))]
    path = tmp_path / "costs.json"
    data = accuracy.write_costs(SimpleNamespace(records=recs), path)
    qc = _costs_module()
    assert qc.validate(data) is None and qc.load_costs(path) == data
    assert "30 ms" in qc.quality_items(path)[2][1]
    assert qc.fmt_ms(12345.0) == "12.3 s" and qc.fmt_ms(250.0) == "250 ms"


def test_quality_enum_in_blender_shows_the_costs(blender, addon):
    import bpy

    qc = _costs_module()
    data = qc.load_costs()
    assert data is not None
    obj = bpy.data.objects.new("e", bpy.data.meshes.new("e"))
    items = obj.translucency.bl_rna.properties["quality"].enum_items
    for ident in ("DRAFT", "PREVIEW", "FINAL"):
        e = data["presets"][ident.lower()]
        assert qc.fmt_percent(e["rel_rms"]) in items[ident].name
        assert qc.fmt_ms(e["frame_ms"]) in items[ident].description
