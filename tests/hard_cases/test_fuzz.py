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


def test_a_start_worse_than_zero_is_scaled_down():
    """An example the fuzz drew (2026-12-07): a point light at the centre, inside the object, and a zero-size
    area light just off its surface.  The coarse level's answer carried up gave the finest level a start
    9e9 times |b|; its recursive residual drifted from the true one and the check found the true residual
    12x the running minimum just before stopping (912 sweeps).  ``solver.start_no_worse_than_zero`` scales
    such a start to its energy-optimal multiple: the bounds hold, in 320 sweeps."""
    L0 = Light("area", color=(0.2867203370642171, 6.103515625e-05, 0.4634240508384201), intensity=338081.48326945043,
               irradiance=338081.48326945043, position=(-2.4589691135504753e-37, -1.0001, 0.0),
               direction=(2.4587232412263525e-37, 1.0, -0.0), spot_size=0.54627421529604, name="L0")
    L1 = Light("point", color=(0.25397946730531734, 0.088, 0.5033162831135786), intensity=1.0, irradiance=1.0,
               position=(0.0, 0.0, 0.0), direction=(0.9610626167161931, 0.2763306836936928, 0.0),
               spot_size=2.584771821872295, name="L1")
    material = Material(Medium((0.12602345075594426, 1.0, 0.0), (1.0, 0.9999998627552429, 1.0), "a"), None, 2.19)
    env = 1.8248510271533247
    scn = hc.Scenario("fuzz", "start", small_bake().with_scale(1.5959013770431274), material, lights=[L0, L1],
                      environment=Environment((env, 0.5 * env, 0.25 * env)), shadows=True, paper=False)
    fast = hc.run_solver(scn, "fast")
    _, problems = hc.check(fast)
    assert problems == [], problems
    assert fast.result.level_solves[-1].history[0] < 10.0  # the start's relative residual (9e9 unscaled)


def test_start_no_worse_than_zero_keeps_a_good_start():
    """The scaled start's energy error is no larger than zero's; a start better than zero is kept as it is."""
    from types import SimpleNamespace

    from translucency_addon.diffusion.solver import start_no_worse_than_zero

    rng = np.random.default_rng(3)
    M = rng.random((30, 30))
    A = M @ M.T + 30 * np.eye(30)
    system = SimpleNamespace(apply=lambda x: A @ x)
    x = rng.random((30, 2))
    b = A @ x
    good = x + 1e-3 * rng.random((30, 2))
    assert start_no_worse_than_zero(system, b, good) is good
    bad = 1e4 * rng.random((30, 2))
    scaled = start_no_worse_than_zero(system, b, bad)
    for c in range(2):
        e = x[:, c] - scaled[:, c]
        assert e @ A @ e <= x[:, c] @ A @ x[:, c] * (1 + 1e-12)
        assert np.linalg.norm(b[:, c] - A @ scaled[:, c]) < np.linalg.norm(b[:, c] - A @ bad[:, c])
