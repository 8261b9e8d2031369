# SPDX-License-Identifier: GPL-3.0-or-later
"""Fuzz the inner-part passes (issue 35): the cavity exchange and the Voxel Number Map, the bounds of their hard
cases (``passes_cavity.measure``, ``passes_voxel_number_map.measure``), 0 crashes that are not a refusal by name.

Hypothesis, derandomised, shrinking off (as ``test_fuzz.py``):

* cavity exchange: media (sigma_a in {0} u [1e-6, 1e2] /mm, sigma_s' in [1e-3, 1e3]), eta, and one to three
  lights of every kind anywhere from the hollow's centre (inside it) through the medium to 3 cube sizes away,
  on the memoised 20 mm cube with a 6 mm cavity.  The cavity's size and position are not drawn: each would be a
  new QuadGraph bake (~7 s); ``passes_cavity`` covers them by name.
* Voxel Number Map: one inner part (a sphere of radius 0.1 to 9 mm anywhere in the cube, as a medium, a cavity
  or opaque), the outer and the part's media, the scale, lights and a world, on small maps (~150 surface
  voxels).  A part outside, sticking out as a cavity, without a wall or without a voxel centre is refused by
  name (a TranslucencyError); anything else must render within the bounds.
"""

from __future__ import annotations

import numpy as np
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st

from translucency_addon.geometry import primitives
from translucency_addon.scene.composite import CompositeObject, InnerPart
from translucency_addon.errors import TranslucencyError
from translucency_addon.scene.lights import Environment, Light
from translucency_addon.scene.materials import Material, Medium
from translucency_addon.voxel_number_map import VNMSettings, bake_voxel_number_map

from . import passes_cavity as pc
from . import passes_voxel_number_map as pv


def log_uniform(lo, hi):
    return st.floats(np.log10(lo), np.log10(hi)).map(lambda e: float(10.0**e))


sigma_a = st.one_of(st.just(0.0), log_uniform(1e-6, 1e2))
sigma_s = log_uniform(1e-3, 1e3)
rgb = lambda s: st.tuples(s, s, s)  # noqa: E731
unit = st.tuples(*[st.floats(-1.0, 1.0)] * 3).filter(lambda v: np.linalg.norm(v) > 1e-3)
FUZZ = dict(deadline=None, derandomize=True, print_blob=True,
            suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
            phases=(Phase.explicit, Phase.generate))


@st.composite
def lights(draw, radii):
    """One to three lights; ``radii``: distances from the centre (mm) to draw positions from."""
    out = []
    for k in range(draw(st.integers(1, 3))):
        kind = draw(st.sampled_from(["point", "spot", "sun", "area"]))
        d = np.asarray(draw(unit))
        d /= np.linalg.norm(d)
        r = draw(st.sampled_from(radii))
        power = draw(log_uniform(1e-3, 1e5))
        aim = -d if draw(st.booleans()) else np.asarray(draw(unit))
        out.append(Light(kind, color=draw(st.tuples(*[st.floats(0.0, 1.0)] * 3)), intensity=power, irradiance=power,
                         position=tuple(r * d), direction=tuple(aim), spot_size=draw(st.floats(0.05, np.pi)),
                         name=f"L{k}"))
    return out


def assert_bounds(outcome):
    broken = [b.describe() for b in outcome.bounds if not b.ok]
    assert broken == [], (broken, outcome.note)


@settings(max_examples=25, **FUZZ)
@given(sa=rgb(sigma_a), ss=rgb(sigma_s), eta=st.floats(1.0, 2.0),
       light_list=lights([0.0, 3.0, 5.9, 8.0, 10.5, 60.0]))  # hollow (r 6), medium, outside
def test_cavity_exchange_random_media_and_lights_stay_bounded(sa, ss, eta, light_list):
    bake = pc.baked("sphere")[0]
    medium = Medium(sa, ss, "fuzz")
    try:
        out = pc.measure(bake, medium, light_list, eta=eta)
    except TranslucencyError:
        return  # a refusal by name (e.g. an invalid medium) is an allowed outcome
    assert_bounds(out)


@settings(max_examples=20, **FUZZ)
@given(role=st.sampled_from(["medium", "cavity", "opaque"]), radius=log_uniform(0.1, 9.0),
       centre=st.tuples(*[st.floats(-9.0, 9.0)] * 3), outer=st.tuples(rgb(sigma_a), rgb(sigma_s)),
       inner=st.tuples(rgb(sigma_a), rgb(sigma_s)), mm=log_uniform(1e-2, 1e3),
       light_list=lights([0.0, 5.0, 10.5, 15.0, 60.0]), env=st.one_of(st.none(), st.floats(0.0, 2.0)))
def test_voxel_number_map_random_parts_media_and_lights_stay_bounded(role, radius, centre, outer, inner, mm,
                                                                     light_list, env):
    try:
        outer_m = Medium(outer[0], outer[1], "outer")
        part = InnerPart("part", *primitives.icosphere(radius, 1, centre), role,
                         Medium(inner[0], inner[1], "inner") if role == "medium" else None)
        material = Material(outer_m)
        vnm = bake_voxel_number_map(CompositeObject(*pv.cube(), material, [part]),
                                    VNMSettings(surface_voxels=150, env_directions=8), mm_per_unit=mm)
    except TranslucencyError:
        return  # refused by name: outside, sticking out, no wall, smaller than a voxel, ...
    world = None if env is None else Environment((env, 0.5 * env, 0.25 * env))
    out, _ = pv.measure(vnm, material, light_list, world)
    assert_bounds(out)
