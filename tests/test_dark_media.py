# SPDX-License-Identifier: GPL-3.0-or-later
"""Media where diffusion fails (issue 30): a 10 mm sphere of a dark medium under a white world, rendered as a
new user gets it from the command line with default settings, against an analogue random walk of the same
sphere (``bench/sphere_walk.py``: its own Fresnel, total internal reflection, every order; no code of the
add-on).  By symmetry the exact radiance is the same at every vertex.

* the single-scattering pass alone against the walk's once-scattered light (reflected inside or not:
  ``single_scattering/entry.py`` eq. 3 and ``view_reflection.py``; in a ball they add 0.2 %) at eta 1 and
  1.3: the view rays cross the whole baked medium (``runtime.medium_margin``; from the vertex they returned
  12 % too little), and at 1.3 the world's light enters through the critical cone
  (``single_scattering/entry.py``; straight chords were 9.5 % over);
* the frame (single scattering plus the orders after the first, ``frame.orders_after_the_first``) against
  the walk's total at eta 1.3 and 1 (issue 30's targets: 10 % and 5 %);
* no jump where the planner hands the sphere from single scattering to diffusion (the blend from albedo 0.5
  to 0.6);
* the planner's reasons are true: a pass it leaves out for not being baked returns light once baked, and
  the diffusion it leaves out as invalid returns its error, not the light.
"""

from __future__ import annotations

import contextlib
import io
import json

import numpy as np
import pytest

from bench.sphere_walk import sphere_walk

RADIUS_MM = 5.0


def _cli(*args) -> str:
    from translucency_addon.__main__ import main

    out = io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(out):
        rc = main([str(a) for a in args])
    assert rc == 0, out.getvalue()[-3000:]
    return out.getvalue()


@pytest.fixture(scope="module")
def sphere_obj(tmp_path_factory):
    from translucency_addon.geometry import meshio, primitives

    path = tmp_path_factory.mktemp("dark") / "sphere.obj"
    V, F = primitives.icosphere(RADIUS_MM, 3)
    meshio.save_obj(path, V, F)
    return path


def _material(albedo: float, eta: float) -> list:
    a, b = albedo, 1.0 - albedo
    return ["--sigma-s", f"{a},{a},{a}", "--sigma-a", f"{b},{b},{b}", "--eta", repr(eta)]


def _frame(tmp_path, mesh, albedo: float, eta: float, single: bool = True, *solve_args, quality: str = "draft"):
    """(total, single-scattering term or None, stats) of the CLI's frame: bake (Draft graph unless
    ``quality`` says otherwise, default single scattering), then solve under a white world, every vertex
    seen along its normal."""
    cache = tmp_path / f"s_{albedo}_{eta}_{int(single)}_{quality}.npz"
    if not cache.exists():
        _cli("bake", mesh, "-o", cache, "--quality", quality, *(["--single-scattering"] if single else []),
             *_material(albedo, eta))
    out, ss, stats = tmp_path / "L.npy", tmp_path / "ss.npy", tmp_path / "st.json"
    ss_args = ["--ss-output", ss] if single and "--pass-planning" not in solve_args else []
    _cli("solve", cache, "-o", out, *_material(albedo, eta), "--env", "1,1,1", "--stats", stats, *ss_args,
         *solve_args)
    L = np.load(out)[:, 0].astype(np.float64)
    return L, (np.load(ss)[:, 0].astype(np.float64) if ss_args else None), json.loads(stats.read_text())


@pytest.mark.parametrize("eta, bound", [(1.3, 0.10), (1.0, 0.05)])
def test_dark_sphere_against_a_random_walk(tmp_path, sphere_obj, eta, bound):
    """Albedo 0.2 (sigma_s' 0.2, sigma_a 0.8 per mm).  Measured: eta 1.3 +1.3 %, eta 1 +0 %; before this
    issue -22 % and -24 % (single scattering from the vertex, no orders after the first).  The pass's own
    light against the walk's once-scattered light: eta 1.3 +2.8 % with the world's light through the
    critical cone (single_scattering/entry.py), +9.5 % with straight chords and F_in; eta 1 +1 %."""
    walk = sphere_walk(RADIUS_MM, 0.2, eta, n=200_000, seed=11)
    L, ss, st = _frame(tmp_path, sphere_obj, 0.2, eta)
    assert "multiple scattering [---]" in st["plan"] and "single scattering [RGB]" in st["plan"], st["plan"]
    err = L.mean() / walk.total - 1.0
    assert abs(err) <= bound, f"eta {eta}: {100 * err:+.1f} % against the walk ({L.mean():.5f} vs {walk.total:.5f})"
    orders = st["orders_after_the_first_mean"][0]
    rest = walk.total - walk.single
    assert abs(orders / rest - 1.0) < 0.35, (orders, rest)  # the half-space's ratio on the pass's own light
    single = ss.mean() / walk.single - 1.0  # the whole medium along each ray, the critical cone
    assert abs(single) < 0.04, f"single scattering {100 * single:+.1f} % against the walk's"


def test_no_jump_where_diffusion_takes_over(tmp_path, sphere_obj):
    """Across the band where the planner blends single scattering (with the orders after the first) into
    diffusion (reduced albedo 0.5 to 0.6), one Preview bake solved at each albedo: the frame moves by no more
    than the truth does at 0.5 -/+ 1e-4 and 0.6 -/+ 1e-4 (d ln L / d alpha' is about 4, so 2e-4 of alpha' moves
    it ~0.1 %; measured 0.03 % and 0.08 % on a Draft bake).  Switched at 0.5 without the blend it jumped by
    the two sides' difference: 11 % on Draft graphs (+7.9 % against -3.6 % of the walk), 8.6 % across 0.5 on
    this test's Preview bake (measured with diffusion_weight made a step at 0.5).
    In the band's middle (0.55) the blend is within 10 % of the walk (diffusion alone was +5.5 %)."""
    cache = tmp_path / "band.npz"
    _cli("bake", sphere_obj, "-o", cache, "--quality", "preview", "--single-scattering", *_material(0.55, 1.3))
    out, stats = tmp_path / "L.npy", tmp_path / "st.json"

    def mean(albedo):
        _cli("solve", cache, "-o", out, *_material(albedo, 1.3), "--env", "1,1,1", "--stats", stats)
        return float(np.load(out)[:, 0].astype(np.float64).mean()), json.loads(stats.read_text())["plan"]

    plans = {}
    for edge in (0.5, 0.6):
        (lo, plans[edge - 1e-4]), (hi, plans[edge + 1e-4]) = mean(edge - 1e-4), mean(edge + 1e-4)
        assert abs(hi / lo - 1.0) < 0.005, f"x{hi / lo:.4f} across {edge}"
    assert "multiple scattering [---]" in plans[0.5 - 1e-4] and "single scattering [---]" in plans[0.6 + 1e-4]
    mid, plan = mean(0.55)
    assert "multiple scattering [RGB]" in plan and "single scattering [RGB]" in plan and "blended" in plan, plan
    walk = sphere_walk(RADIUS_MM, 0.55, 1.3, n=100_000, seed=5).total
    assert abs(mid / walk - 1.0) < 0.10, f"{100 * (mid / walk - 1.0):+.1f} % against the walk at 0.55"


def test_the_planners_reasons_are_true(tmp_path, sphere_obj):
    """Without single scattering baked the plan renders nothing and says so: single scattering 'not baked'
    (never 'forced off by the user'), and what to bake.  Both are true: baked, it returns light; and the
    diffusion it leaves out as invalid, forced on (Pass Planning 'all'), returns its error: 1.35-1.96x the
    walk's light on average, from 0 to 3.6-7.4x vertex by vertex (relative RMS 0.88-1.69; two bakes)."""
    walk = sphere_walk(RADIUS_MM, 0.2, 1.3, n=100_000, seed=3).total
    L0, _, st0 = _frame(tmp_path, sphere_obj, 0.2, 1.3, False)
    plan = st0["plan"]
    assert "skipped -- no pass returns light" in plan and "single scattering is not baked" in plan, plan
    assert "by the user" not in plan and "holds no single-scattering data (bake with --single-scattering)" in plan
    assert "bake --single-scattering" in plan
    assert np.all(L0 == 0.0)
    L1, _, _ = _frame(tmp_path, sphere_obj, 0.2, 1.3, True)
    assert L1.mean() > 0.5 * walk  # the pass left out for not being baked returns the light
    L2, _, st2 = _frame(tmp_path, sphere_obj, 0.2, 1.3, False, "--pass-planning", "all")
    assert "multiple scattering [RGB] (forced)" in st2["plan"], st2["plan"]
    rms = float(np.sqrt(np.mean((L2 / walk - 1.0) ** 2)))
    assert rms > 0.5, (rms, L2.mean(), walk)  # "what it returns on the object is its error" (measured: 0.88-1.69)
