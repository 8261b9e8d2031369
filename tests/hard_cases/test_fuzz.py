"""Fuzz the solve (issue 9): random materials, scales and lights on a small mesh, same bounds.

Hypothesis, derandomised (the same examples on every run, so CI is
reproducible), over:

* optical coefficients per channel, log-uniform and extreme but valid:
  sigma_a in {0} u [1e-6, 1e2] /mm, sigma_s' in [1e-3, 1e4] /mm (the engine's
  upper limit), eta in [1, 2.5]; optionally a second medium mixed in by a
  checkerboard field (contrasts up to ~1e7 in kappa);
* the scale: mm_per_unit log-uniform in [1e-3, 1e5] (a 2e-3 mm to 200 m sphere);
* one to three lights of every kind, placed anywhere from the centre of the
  object (inside) to 6 radii away, intensities over nine decades; an
  optional uniform environment; shadow rays on or off.

Each example is solved with the CPU default (``fast``) and the direct
solver and held to the bounds of ``cases.check``; the iterative answer must
agree with the direct one within ``AGREE`` (10 x TOL).  One baked icosphere
(two independently tetrahedralised levels, about 900 and 1,800 nodes) is
reused at every scale (``Bake.with_scale``).  Shrinking is off: a failure
prints its example as drawn (shrinking these solves can take many minutes).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st

from translucency_addon import cache
from translucency_addon.geometry import primitives
from translucency_addon.quadgraph.bake import BakeSettings, bake_mesh, mesh_key
from translucency_addon.errors import CacheError
from translucency_addon.scene.fields import FieldSpec, evaluate_field
from translucency_addon.scene.lights import Environment, Light
from translucency_addon.scene.materials import Material, Medium

from . import cases as hc

_BAKE = {}


FUZZ_BAKE = Path(__file__).resolve().parents[1] / "data" / "fuzz_icosphere.npz"


def small_bake():
    """The fuzz's icosphere bake, stored in tests/data so every run solves the same graphs.

    fTetWild does not give the same tetrahedra twice, so a bake made per run
    changed the drawn examples' graphs and let marginal ones pass on one run and
    fail on the next.  The stored bake is used while its key matches the mesh and
    settings; otherwise (the bake format or settings changed) the test bakes
    afresh and says so -- rewrite the file then with ``cache.save_bake``.
    """
    if "b" not in _BAKE:
        V, F = primitives.icosphere(1.0, 2)
        settings = BakeSettings(quality="draft", levels=2, refinements=0, base_triangles=400)
        try:
            _BAKE["b"] = cache.load_bake(FUZZ_BAKE, expected_key=mesh_key(V, F, settings))
        except CacheError as ex:
            print(f"fuzz: {FUZZ_BAKE.name} does not match ({ex}); baking afresh")
            _BAKE["b"] = bake_mesh(V, F, settings)
    return _BAKE["b"]


def log_uniform(lo, hi):
    return st.floats(np.log10(lo), np.log10(hi)).map(lambda e: float(10.0**e))


sigma_a = st.one_of(st.just(0.0), log_uniform(1e-6, 1e2))
sigma_s = log_uniform(1e-3, 1e4)
rgb_a = st.tuples(sigma_a, sigma_a, sigma_a)
rgb_s = st.tuples(sigma_s, sigma_s, sigma_s)
unit = st.tuples(*[st.floats(-1.0, 1.0)] * 3).filter(lambda v: np.linalg.norm(v) > 1e-3)


@st.composite
def lights(draw):
    out = []
    for k in range(draw(st.integers(1, 3))):
        kind = draw(st.sampled_from(["point", "spot", "sun", "area"]))
        d = np.asarray(draw(unit))
        d /= np.linalg.norm(d)
        r = draw(st.sampled_from([0.0, 0.3, 0.999, 1.0001, 1.5, 6.0]))  # in radii; < 1: inside
        power = draw(log_uniform(1e-3, 1e6))
        aim = -d if draw(st.booleans()) else np.asarray(draw(unit))
        out.append(Light(kind, color=draw(st.tuples(*[st.floats(0.0, 1.0)] * 3)), intensity=power,
                         irradiance=power, position=tuple(r * d), direction=tuple(aim),
                         spot_size=draw(st.floats(0.05, np.pi)), name=f"L{k}"))
    return out


@settings(max_examples=120, deadline=None, derandomize=True, print_blob=True,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
          phases=(Phase.explicit, Phase.generate))
@given(sa=rgb_a, ss=rgb_s, eta=st.floats(1.0, 2.5), mix=st.one_of(st.none(), st.tuples(rgb_a, rgb_s)),
       mm=log_uniform(1e-3, 1e5), light_list=lights(), env=st.one_of(st.none(), st.floats(0.0, 2.0)),
       shadows=st.booleans())
def test_random_materials_scales_and_lights_stay_bounded(sa, ss, eta, mix, mm, light_list, env, shadows):
    bake = small_bake().with_scale(mm)
    medium_b = None if mix is None else Medium(mix[0], mix[1], "b")
    material = Material(Medium(sa, ss, "a"), medium_b, eta)
    field = None
    if medium_b is not None:
        spec = FieldSpec("checker", scale=0.5, offset=(0.1, 0.2, 0.3))
        field = [evaluate_field(spec, lv.position) for lv in bake.levels]
    environment = None if env is None else Environment((env, 0.5 * env, 0.25 * env))
    scn = hc.Scenario("fuzz", "", bake, material, field_values=field, lights=light_list,
                      environment=environment, shadows=shadows, paper=False)
    fast = hc.run_solver(scn, "fast")
    _, problems = hc.check(fast)
    direct = hc.run_solver(scn, "direct", q=fast.result.q)
    _, more = hc.check(direct)
    err, diff = hc.compare(fast, direct, hc.AGREE)
    assert problems + more + diff == [], (problems, more, diff)


def test_fuzz_covers_lights_inside_and_empty_scenes():
    """The fixed corners hypothesis may not draw: every light inside, and nothing at all."""
    bake = small_bake().with_scale(10.0)
    mat = Material(Medium((0.01, 0.02, 0.03), (1.0, 1.0, 1.0)), None, 1.3)
    for lights_ in ([Light("point", intensity=1e6, position=(0.0, 0.0, 0.0))], []):
        scn = hc.Scenario("fuzz", "corner", bake, mat, lights=lights_, expect_zero=True, paper=False)
        run = hc.run_solver(scn, "fast")
        _, problems = hc.check(run)
        assert problems == []
