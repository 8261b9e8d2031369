# SPDX-License-Identifier: GPL-3.0-or-later
"""Media where diffusion fails (issue 30): a 10 mm sphere of a dark medium under a white world, rendered as a
new user gets it from the command line with default settings, against an analogue random walk of the same
sphere (``bench/sphere_walk.py``: its own Fresnel, total internal reflection, every order; no code of the
add-on).  By symmetry the exact radiance is the same at every vertex.

* the single-scattering pass alone against the walk's once-scattered light (light that leaves without an
  internal reflection) at eta 1 and 1.3: the view rays cross the whole baked medium
  (``runtime.medium_margin``; from the vertex they returned 12 % too little), and at 1.3 the world's light
  enters through the critical cone (``single_scattering/entry.py``; straight chords were 9.5 % over);
* the frame (single scattering plus the orders after the first, ``frame.orders_after_the_first``) against
  the walk's total at eta 1.3 and 1 (issue 30's targets: 10 % and 5 %);
* no jump where the planner hands the sphere from single scattering to diffusion (albedo 0.5);
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
    rest = walk.total - walk.single_straight
    assert abs(orders / rest - 1.0) < 0.35, (orders, rest)  # the half-space's ratio on the pass's own light
    single = ss.mean() / walk.single_straight - 1.0  # the whole medium along each ray, the critical cone
    assert abs(single) < 0.04, f"single scattering {100 * single:+.1f} % against the walk's"


def test_no_jump_where_diffusion_takes_over(tmp_path, sphere_obj):
    """Albedo 0.49 (single scattering and the orders after the first) and 0.51 (diffusion with the
    first-scatter split): the truth changes by 4 % between them (the walk), we by no more than 12 %.
    Preview graphs (the add-on's default quality): on Draft graphs the diffusion side ranges +3 % to +10 %
    of the walk from bake to bake (fTetWild's run-to-run variation; +10.1 % failed a fresh-clone CI), on
    Preview graphs -1.1 % to +0.1 % (three bakes); the single-scattering side is +5.5 % on both."""
    lo = _frame(tmp_path, sphere_obj, 0.49, 1.3, quality="preview")
    hi = _frame(tmp_path, sphere_obj, 0.51, 1.3, quality="preview")
    assert "multiple scattering [---]" in lo[2]["plan"] and "multiple scattering [RGB]" in hi[2]["plan"]
    w_lo, w_hi = (sphere_walk(RADIUS_MM, a, 1.3, n=100_000, seed=5).total for a in (0.49, 0.51))
    ours = hi[0].mean() / lo[0].mean()
    truth = w_hi / w_lo
    assert abs(ours / truth - 1.0) < 0.12, f"ours x{ours:.3f} across the threshold, the walk x{truth:.3f}"
    for (L, _, _), w in ((lo, w_lo), (hi, w_hi)):
        assert abs(L.mean() / w - 1.0) < 0.10


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
