"""The planner with inner parts and the Voxel Number Map (issue 15).

Where diffusion is valid (thick, high albedo: marble) it runs, with the cavity
exchange, and both single-scattering passes stay off as contained in it.
Where it is invalid (low albedo or optically thin), the pass that replaces it
is the Voxel Number Map when the object has inner parts, single scattering
when it has none; each skipped pass says why.  The measured accuracy and
speed behind the choice are in docs/accuracy.md (bench/accuracy_inner_parts.py).
"""

from __future__ import annotations

import dataclasses
from types import SimpleNamespace

import numpy as np

from bakes import baked
from translucency_addon.inner_parts.bake import CompositeInfo
from translucency_addon.scene.lights import Light
from translucency_addon.scene.materials import Material, Medium, material_from_preset
from translucency_addon.planner import describe_plan, plan_object, replacement_pass

SUN = [Light("sun", irradiance=1000.0, direction=(0.2, -0.3, -1.0), name="sun")]
THIN = Material(Medium((0.10, 0.12, 0.16), (0.025, 0.03, 0.035), "single-scattering"))  # albedo 0.2


def with_parts(roles=("cavity",), vnm=True):
    b = baked("sphere", mm_per_unit=15.0)
    info = CompositeInfo(tuple(f"p{k}" for k in range(len(roles))), tuple(roles), (None,) * len(roles),
                         [np.zeros(lv.n_nodes, dtype=np.int16) for lv in b.levels], len(b.mesh_vertices))
    return dataclasses.replace(b, composite=info if roles else None,
                               voxel_number_map=SimpleNamespace(n=1500) if vnm else None)


def test_replacement_rule():
    assert replacement_pass(True, True, {"cavity": 1}) == "voxel_number_map"  # its bake does not know the parts
    assert replacement_pass(True, True, {"cavity": 1}, ss_knows_parts=True) == "single"  # measured more accurate
    assert replacement_pass(True, True, {}) == "single"
    assert replacement_pass(False, True, {}) == "voxel_number_map"
    assert replacement_pass(True, False, {"opaque": 1}) == "single"
    assert replacement_pass(False, False, {"medium": 2}) is None


def test_low_albedo_object_with_a_cavity_runs_the_voxel_number_map():
    plan = plan_object(with_parts(("cavity", "opaque")), THIN, SUN, None, has_single_scattering=True, name="cube")
    assert plan.run and plan.multiple.channels == (False, False, False)
    assert plan.voxel_number_map.channels == (True, True, True)
    assert plan.single.channels == (False, False, False)
    assert all("the Voxel Number Map replaces it" in r and "1 cavity, 1 opaque" in r for r in plan.single.reasons)
    assert plan.facts["inner_parts"] == {"cavity": 1, "opaque": 1}
    text = describe_plan(plan)
    assert "Voxel Number Map [RGB]" in text and plan.estimated_ms > 1.0
    # single scattering baked with the parts is the more accurate replacement (docs/accuracy.md)
    b = with_parts(("cavity", "opaque"))
    b = dataclasses.replace(b, single_scattering=SimpleNamespace(stats={"inner_parts": True}))
    plan = plan_object(b, THIN, SUN, None, name="cube")
    assert plan.single.channels == (True, True, True) and plan.voxel_number_map.channels == (False, False, False)
    assert all("baked with the inner parts, it is the more accurate" in r for r in plan.voxel_number_map.reasons)


def test_marble_with_a_cavity_runs_diffusion_only():
    plan = plan_object(with_parts(("cavity",)), material_from_preset("marble"), SUN, None, has_single_scattering=True)
    assert plan.multiple.channels == (True, True, True)
    assert plan.voxel_number_map.channels == (False, False, False) and plan.single.channels == (False, False, False)
    assert all("contained in the diffusion term" in r for r in plan.voxel_number_map.reasons)


def test_without_parts_single_scattering_replaces_diffusion_and_the_map_says_why_not():
    plan = plan_object(with_parts(()), THIN, SUN, None, has_single_scattering=True)
    assert plan.single.channels == (True, True, True) and plan.voxel_number_map.channels == (False, False, False)
    assert all("no inner parts" in r for r in plan.voxel_number_map.reasons)
    # the map alone (no single scattering baked) replaces diffusion as well
    plan = plan_object(with_parts(()), THIN, SUN, None, has_single_scattering=False)
    assert plan.voxel_number_map.channels == (True, True, True)
    assert all("not baked" in r for r in plan.single.reasons)


def test_turning_the_map_off_hands_back_to_single_scattering_and_forcing_works():
    b = with_parts(("cavity",))
    plan = plan_object(b, THIN, SUN, None, has_single_scattering=True, overrides={"voxel_number_map": False})
    assert plan.single.channels == (True, True, True)
    assert all("forced off by the user" in r for r in plan.voxel_number_map.reasons)
    plan = plan_object(b, material_from_preset("marble"), SUN, None, overrides={"voxel_number_map": True})
    assert plan.voxel_number_map.channels == (True, True, True) and plan.voxel_number_map.forced
    plan = plan_object(with_parts(("cavity",), vnm=False), THIN, SUN, None, has_single_scattering=False)
    assert all("not baked" in r for r in plan.voxel_number_map.reasons)
