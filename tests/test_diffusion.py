"""Diffusion on the QuadGraph (issue 4): independent checks, never our own output frozen.

* the sphere under uniform light against the closed-form solution;
* the fast (Chebyshev) and paper (Jacobi) iterations against direct sparse solves;
* energy: exact balance for a non-absorbing body, outgoing <= incoming power;
* the discrete maximum principle;
* heterogeneity and shadows change the answer the way physics says.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from bakes import baked
from translucency_addon import cache
from translucency_addon.scene import fresnel
from translucency_addon.diffusion import kernels
from translucency_addon.geometry import primitives
from translucency_addon.quadgraph.bake import BakeSettings, bake_mesh
from translucency_addon.diffusion.solver import DiffusionSolver, SolveOptions
from translucency_addon.diffusion.iterative import solve_direct
from translucency_addon.scene.fields import FieldSpec, evaluate_field
from translucency_addon.scene.lights import Environment, Light
from translucency_addon.scene.materials import Material, Medium, material_from_preset, preset

ROOT = Path(__file__).resolve().parents[1]
MARBLE = material_from_preset("marble")
ENV1 = Environment((1.0, 1.0, 1.0))


def sphere_analytic(R_mm, sigma_a, sigma_s, eta, L=1.0):
    """Closed form for a homogeneous sphere under uniform radiance L (no occlusion).

    phi(r) = C sinh(r/l)/r, l = sqrt(kappa/mu), with the Robin condition
    phi + 2 A kappa phi' = 4 q/(1 - F_dr) at r = R and q = L pi (1 - F_dr,ext);
    returns L_o along the normal = F_t(0) J+ / (pi eta^2), J+ = (phi(R) - 2q)/(2(1 + F_dr)).
    """
    sa, ss = np.asarray(sigma_a), np.asarray(sigma_s)
    k = 1.0 / (3.0 * (sa + ss))
    l = np.sqrt(k / sa)
    fdr = fresnel.diffuse_reflectance_internal(eta)
    A = (1 + fdr) / (1 - fdr)
    q = L * np.pi * (1 - fresnel.diffuse_reflectance_external(eta))
    R = R_mm
    C = (4 * q / (1 - fdr)) / (np.sinh(R / l) / R + 2 * A * k * (np.cosh(R / l) / (l * R) - np.sinh(R / l) / R**2))
    phi_R = C * np.sinh(R / l) / R
    J = (phi_R - 2 * q) / (2 * (1 + fdr))
    return fresnel.fresnel_transmittance(1.0, eta) * J / (np.pi * eta**2)


@pytest.fixture(scope="module")
def sphere_bakes():
    """One sphere (radius 12 mm), baked at three resolutions sharing one base level."""
    V, F = primitives.icosphere(1.0, 4)
    b3 = bake_mesh(V, F, BakeSettings(quality="draft", levels=3, refinements=2, base_triangles=500, mm_per_unit=12.0))
    return b3


def test_sphere_converges_to_the_closed_form(sphere_bakes):
    exact = sphere_analytic(12.0, MARBLE.medium_a.sigma_a, MARBLE.medium_a.sigma_s, MARBLE.eta)
    b = sphere_bakes
    errors = []
    for n_levels in (1, 2, 3):
        sub = type(b)(levels=b.levels[:n_levels], shepard=b.shepard[: n_levels - 1],
                      vertex_map=_remap(b, n_levels), mesh_vertices=b.mesh_vertices, mesh_faces=b.mesh_faces,
                      mesh_normals=b.mesh_normals, shadow_vertices=b.shadow_vertices, shadow_faces=b.shadow_faces,
                      settings=b.settings, mm_per_unit=b.mm_per_unit, key=b.key)
        s = DiffusionSolver(sub, MARBLE, options=SolveOptions(solver="fast", tol=1e-6))
        L = s.vertex_radiance(s.solve([], ENV1))
        # uniform to within a few percent (node-to-node scatter of the two-point
        # flux on non-orthogonal tets is ~1-2 % and does not shrink with refinement)
        assert np.all(L.std(axis=0) / L.mean(axis=0) < 0.03), (n_levels, L.std(axis=0) / L.mean(axis=0))
        w = _vertex_areas(b)
        mean = (w[:, None] * L).sum(axis=0) / w.sum()
        errors.append(float(np.abs((mean - exact) / exact).max()))
    # the mean approaches the analytic value as the graph is refined (measured:
    # about 0.9 %, 0.2 %, 0.03 % for 2.4k, 17k and 130k nodes).  Below ~0.05 % the
    # order of the two finer graphs is fTetWild's run-to-run variation (one fresh-clone
    # run: 0.22 %, 0.013 %, 0.046 %), so they must beat the coarsest and stay small.
    assert errors[0] > max(errors[1], errors[2]), errors
    assert errors[1] < 0.003 and errors[2] < 0.002, errors


@pytest.mark.parametrize("name", ["skin1", "ketchup"])
def test_unresolved_boundary_layer_matches_the_closed_form(sphere_bakes, name):
    """Absorbing channels whose diffusion length is shorter than a surface link.

    Without the fitted surface flux, skin1's blue came out +136 % (coarse) to
    +19 % (fine) and ketchup's green/blue ~0.2 where the exact answer is 0.
    With it, skin1 is within 0.3-3.2 % per channel over fTetWild runs (its
    output is not deterministic; one fresh-clone run gave 5.9 % in blue), hence the 8 % bound.
    """
    mat = material_from_preset(name)
    exact = np.maximum(sphere_analytic(12.0, mat.medium_a.sigma_a, mat.medium_a.sigma_s, mat.eta), 0.0)
    b = sphere_bakes
    s = DiffusionSolver(b, mat, options=SolveOptions(tol=1e-7))
    L = s.vertex_radiance(s.solve([], ENV1))
    w = _vertex_areas(b)
    mean = (w[:, None] * L).sum(axis=0) / w.sum()
    resolved = exact > 0.05
    assert np.all(np.abs(mean[resolved] - exact[resolved]) / exact[resolved] < 0.08), (mean, exact)
    # where diffusion returns (almost) nothing, so do we: < 5 % of the brightest channel (measured
    # 2.4-3.1 % for ketchup's green over fTetWild runs: the clamped J+ = (phi - 2q)/(2(1 + F_dr)) of a
    # boundary layer thinner than a link; without the fitted links it is ~60 %; the planner never runs
    # diffusion in these channels, whose reduced albedo is below 0.5)
    assert np.all(mean[~resolved] < 0.05 * exact.max()), (mean, exact)


def _vertex_areas(b):
    from translucency_addon.geometry.meshio import triangle_areas

    w = np.zeros(len(b.mesh_vertices))
    a = triangle_areas(b.mesh_vertices, b.mesh_faces)
    for k in range(3):
        np.add.at(w, b.mesh_faces[:, k], a / 3.0)
    return w


def _remap(b, n_levels):
    from translucency_addon.quadgraph.bake import vertex_mapping

    return vertex_mapping(b.mesh_vertices, b.mesh_normals, b.levels[n_levels - 1])


def _direct_on(solver: DiffusionSolver, q):
    """Direct sparse solve of each level's own system (paper or ours)."""
    return [solve_direct(sys_, sys_.rhs(q[i]))[0] for i, sys_ in enumerate(solver.systems)]


def _hetero_cube(kind="layers", other="skin1", levels=2, scale=0.25):
    b = _cube_bake(levels)
    mat = Material(preset("marble"), preset(other), 1.3)
    spec = FieldSpec(kind, scale=scale, axis=0)
    field = [evaluate_field(spec, lv.position) for lv in b.levels]
    return b, mat, field


_CUBE = {}


def _cube_bake(levels):
    """A 20 mm cube (one bake per level count per test session)."""
    if levels not in _CUBE:
        V, F = primitives.box((1.0, 1.0, 1.0), subdivisions=4)  # fine enough for per-vertex patterns
        _CUBE[levels] = bake_mesh(V, F, BakeSettings(quality="draft", levels=levels, base_triangles=300,
                                                      mm_per_unit=20.0))
    return _CUBE[levels]


@pytest.mark.parametrize("case", ["spot", "hetero-cube"])
def test_fast_and_paper_iterations_agree_with_direct_solves(case):
    if case == "spot":
        b, mat, field = baked("spot", levels=2, base_triangles=300, mm_per_unit=40.0), MARBLE, None
    else:
        # a smooth field: with sharp layers the paper's Jacobi diverges (test_paper_scheme_diverges_...)
        # (one level: the paper's Jacobi needs ~(l/h)^2 sweeps, too many for a test on finer graphs)
        b, mat, field = _hetero_cube("noise", "skimmilk", levels=1, scale=0.5)
    lights = [Light("sun", irradiance=1000.0, direction=(0.3, -0.5, -0.8))]
    tol = 1e-6
    fast = DiffusionSolver(b, mat, field, SolveOptions(solver="fast", tol=tol))
    rf = fast.solve(lights, ENV1)
    ref = _direct_on(fast, rf.q)
    for i in range(len(b.levels)):
        err = np.abs(rf.phi[i] - ref[i]).max() / np.abs(ref[i]).max()
        assert err < 50 * tol, (case, "fast", i, err)
    paper = DiffusionSolver(b, mat, field, SolveOptions(solver="paper", tol=tol, levels="finest"))
    rp = paper.solve(lights, ENV1, q=rf.q)
    ref_p = _direct_on(paper, rf.q)[-1]
    err = np.abs(rp.phi[-1] - ref_p).max() / np.abs(ref_p).max()
    assert err < 500 * tol, (case, "paper", err)  # Jacobi's error is larger than its residual
    # The two discretisations describe the same physics: vertex radiance within discretisation error.
    Lf = fast.vertex_radiance(rf)
    Lp = paper.vertex_radiance(rp)
    rel = np.linalg.norm(Lf - Lp) / np.linalg.norm(Lf)
    assert rel < 0.25, rel
    # and ours needs far fewer sweeps than the paper's Jacobi
    assert rf.level_solves[-1].iterations * 5 < rp.level_solves[-1].iterations


def test_paper_scheme_diverges_under_kappa_jumps_where_ours_converges():
    """Eq. 5 puts kappa(n_j) inside the sum: with marble/skin1 layers the Jacobi
    iteration matrix has spectral radius > 1 (measured 1.25 in red), so eqs. 8-9
    diverge.  Our conservative scheme converges on the same graph and field."""
    b, mat, field = _hetero_cube("layers", "skin1")
    paper = DiffusionSolver(b, mat, field, SolveOptions(solver="paper", tol=1e-6, levels="finest", max_iterations=4000))
    rp = paper.solve([], ENV1)
    assert rp.level_solves[-1].diverged
    fast = DiffusionSolver(b, mat, field, SolveOptions(solver="fast", tol=1e-8))
    rf = fast.solve([], ENV1)
    assert rf.residual.max() <= 1e-8 and not rf.level_solves[-1].diverged
    L = fast.vertex_radiance(rf)
    assert np.all(np.isfinite(L)) and np.all(L >= 0)


def test_non_absorbing_body_returns_exactly_the_power_it_takes_in():
    b = baked("sphere", levels=2, base_triangles=300, mm_per_unit=10.0)
    white = Material(Medium((0.0, 0.0, 0.0), (1.0, 2.0, 3.0), "white"), None, 1.3)
    s = DiffusionSolver(b, white, options=SolveOptions(solver="direct"))
    lights = [Light("sun", irradiance=500.0, direction=(0, 0, -1)), Light("point", intensity=2.0, position=(2, 1, 0))]
    r = s.solve(lights, ENV1)
    for level in range(len(b.levels)):
        pb = s.power_balance(r, level=level, clamp=False)
        np.testing.assert_allclose(pb["absorbed"], 0.0, atol=1e-15)
        np.testing.assert_allclose(pb["out"], pb["in"], rtol=1e-9)
        pbc = s.power_balance(r, level=level, clamp=True)
        np.testing.assert_allclose(pbc["out"], pb["out"], rtol=1e-9)  # nothing was clamped here


@pytest.mark.parametrize("material", ["marble", "skimmilk", "skin1", "ketchup"])
def test_energy_and_maximum_principle(material):
    b = baked("spot", levels=2, base_triangles=300, mm_per_unit=40.0)
    mat = material_from_preset(material)
    s = DiffusionSolver(b, mat, options=SolveOptions(solver="direct"))
    lights = [Light("point", intensity=5.0, position=(1.0, 1.5, 1.0)), Light("sun", irradiance=300.0, direction=(1, 0, 0))]
    r = s.solve(lights, ENV1)
    L = s.vertex_radiance(r)
    assert np.all(np.isfinite(L)) and np.all(L >= 0)
    for level in range(len(b.levels)):
        pb = s.power_balance(r, level=level)
        assert np.all(pb["out"] <= pb["in"] * (1 + 1e-9)), (material, level, pb)
        np.testing.assert_allclose(s.power_balance(r, level, clamp=False)["out"] + pb["absorbed"], pb["in"], rtol=1e-8)
        g = 4.0 * r.q[level] / (1.0 - s.fdr)  # the Robin condition's boundary source
        assert np.all(r.phi[level] <= g.max(axis=0) * (1 + 1e-9))
        assert np.all(r.phi[level] >= -1e-12 * g.max())


def test_heterogeneity_is_visible_and_homogeneity_is_not():
    b, mat, field = _hetero_cube("layers", "ketchup", scale=0.5)
    V = b.mesh_vertices
    field_v = evaluate_field(FieldSpec("layers", scale=0.5, axis=0), V)
    het = DiffusionSolver(b, mat, field, SolveOptions(tol=1e-6))
    L_het = het.vertex_radiance(het.solve([], ENV1)).mean(axis=1)
    hom = DiffusionSolver(b, MARBLE, None, SolveOptions(tol=1e-6))
    L_hom = hom.vertex_radiance(hom.solve([], ENV1)).mean(axis=1)
    # skin1 (field = 1) absorbs far more than marble: the pattern follows the field
    c_het = np.corrcoef(field_v, L_het)[0, 1]
    c_hom = np.corrcoef(field_v, L_hom)[0, 1]
    assert c_het < -0.4, c_het  # measured -0.57 (edges and corners mix both layers)
    assert abs(c_hom) < 0.2, c_hom
    # editing the material re-samples kappa/mu: no re-bake, a different answer
    het.set_material(MARBLE, None)
    L_edit = het.vertex_radiance(het.solve([], ENV1)).mean(axis=1)
    np.testing.assert_allclose(L_edit, L_hom, rtol=1e-4)


def test_a_light_behind_an_occluder_is_dimmer():
    b = baked("sphere", levels=2, base_triangles=300, mm_per_unit=10.0)
    s = DiffusionSolver(b, MARBLE, options=SolveOptions(tol=1e-6))
    sun = [Light("sun", irradiance=1000.0, direction=(0, 0, -1))]
    Vo, Fo = primitives.box((3.0, 3.0, 0.1), center=(0, 0, 2.0))  # a slab between the sun and the sphere
    free = s.vertex_radiance(s.solve(sun))
    blocked = s.vertex_radiance(s.solve(sun, occluders=(Vo, Fo)))
    assert blocked.sum() < 0.05 * free.sum()
    # self-shadowing: the far side of the sphere gets only light diffused through it
    z = b.mesh_vertices[:, 2]
    assert free[z > 0.5].mean() > 5 * free[z < -0.5].mean()


def test_warm_start_from_previous_frame_saves_sweeps():
    b = baked("spot", levels=2, base_triangles=300, mm_per_unit=40.0)
    s = DiffusionSolver(b, MARBLE, options=SolveOptions(tol=1e-4))
    d0 = np.array([0.0, -0.5, -1.0])
    r0 = s.solve([Light("sun", irradiance=1000.0, direction=d0)])
    ang = np.deg2rad(5.0)
    rot = np.array([[np.cos(ang), -np.sin(ang), 0], [np.sin(ang), np.cos(ang), 0], [0, 0, 1]])
    lights = [Light("sun", irradiance=1000.0, direction=rot @ d0)]
    cold = s.solve(lights)
    warm = s.solve(lights, warm_start=r0)
    # The previous frame starts the finest level closer than the coarse level's upsampled solution,
    # and the frame skips the coarse level.  (The finest level's own count alone saves one check
    # interval, 8 sweeps, over 12 bakes: 40-56 against 48-72, equal now and then when both round to
    # the same check; the frame's total is 40-56 against 80-112.)
    assert warm.level_solves[-1].history[0] < cold.level_solves[-1].history[0]
    assert sum(ls.iterations for ls in warm.level_solves) < sum(ls.iterations for ls in cold.level_solves)
    assert warm.residual.max() <= 1e-4
    Lw, Lc = s.vertex_radiance(warm), s.vertex_radiance(cold)
    assert np.abs(Lw - Lc).max() < 2e-3 * Lc.max()  # both are within the tolerance of the same solution
    # a QuadGraph level (4 link slots) keeps Chebyshev as the default solve (iterative.fast_steps) below
    # CG_MIN_NODES nodes, and runs CG from there where the compiled step runs
    from translucency_addon.diffusion import compiled_cg, iterative

    system = s.systems[-1]
    assert iterative.links_per_node(system) < iterative.CG_MIN_LINKS
    for threshold, method in ((system.n + 1, iterative.chebyshev_steps), (system.n, iterative.cg_steps)):
        iterative.CG_MIN_NODES, saved = threshold, iterative.CG_MIN_NODES
        try:
            steps = iterative.fast_steps(system, system.rhs(warm.q[-1]), warm.phi[-1], 1e-4, 10)
        finally:
            iterative.CG_MIN_NODES = saved
        if not compiled_cg.available():
            assert steps.gi_code is method.__code__


def test_no_light_gives_exactly_zero():
    b = baked("sphere", levels=2, base_triangles=300, mm_per_unit=10.0)
    for solver in ("fast", "paper", "direct"):
        s = DiffusionSolver(b, MARBLE, options=SolveOptions(solver=solver))
        r = s.solve([], None)
        assert np.all(s.vertex_radiance(r) == 0.0)


def test_kernel_twins_match_the_sparse_matrix():
    """The packed (N,4) kernels equal the assembled CSR matrix product."""
    from translucency_addon.diffusion.assembly import sparse_matrix

    b = baked("sphere", levels=2, base_triangles=300, mm_per_unit=10.0)
    s = DiffusionSolver(b, MARBLE)
    sy = s.systems[-1]
    x = np.random.default_rng(1).random((sy.n, 3))
    Ax = kernels.apply_matrix(sy.nbr, sy.off, sy.diag, x)
    np.testing.assert_allclose(sy.apply(x), Ax, rtol=1e-10, atol=1e-13 * np.abs(Ax).max())  # CPU fast path
    for c in range(3):
        ref = sparse_matrix(sy, c) @ x[:, c]
        np.testing.assert_allclose(Ax[:, c], ref, rtol=1e-10, atol=1e-13 * np.abs(ref).max())
        A = sparse_matrix(sy, c)
        assert abs(A - A.T).max() < 1e-12 * abs(A).max()  # our scheme is symmetric


def test_cli_solve_writes_radiance_and_stats(tmp_path):
    b = baked("spot", levels=2, base_triangles=300, mm_per_unit=40.0)
    c = cache.save_bake(tmp_path / "spot.npz", b)
    out, stats = tmp_path / "L.npy", tmp_path / "stats.json"
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    r = subprocess.run([sys.executable, "-m", "translucency_addon", "solve", c, "-o", str(out), "--material", "marble",
                        "--env", "1,1,1", "--sun", "0,0,-1:500", "--solver", "fast", "--tol", "1e-5",
                        "--stats", str(stats)], capture_output=True, text=True, env=env)
    assert r.returncode == 0, r.stderr
    L = np.load(out)
    assert L.shape == (len(b.mesh_vertices), 3) and np.all(np.isfinite(L)) and L.min() >= 0
    st = json.loads(stats.read_text())
    assert st["levels"][-1]["n_surface"] == b.finest.n_surface
    assert max(st["final_relative_residual"]) <= 1e-5
    assert sum(st["sweeps"]) > 0 and st["seconds"]["total"] > 0
    # the env-only answer of the CLI matches the engine API
    r = subprocess.run([sys.executable, "-m", "translucency_addon", "solve", c, "-o", str(out), "--env", "1,1,1",
                        "--tol", "1e-8"], capture_output=True, text=True, env=env)
    assert r.returncode == 0, r.stderr
    # the CLI runs the add-on's recipe: the planner's first-scatter split in the diffusion solve
    from translucency_addon.planner import plan_object

    plan = plan_object(b, MARBLE, [], ENV1)
    assert any(plan.multiple.split), "marble under a uniform world: the split is on"
    s = DiffusionSolver(b, MARBLE, options=SolveOptions(tol=1e-8))
    np.testing.assert_allclose(np.load(out), s.vertex_radiance(s.solve([], ENV1, single=plan.multiple.split)),
                               rtol=1e-4)
    # bad material is a clear error, not a traceback
    r = subprocess.run([sys.executable, "-m", "translucency_addon", "solve", c, "-o", str(out),
                        "--sigma-a", "nan,0,0", "--sigma-s", "1,1,1"], capture_output=True, text=True, env=env)
    assert r.returncode == 2 and "NaN" in r.stderr


def test_subnormal_light_colours_are_flushed_to_zero():
    """A colour channel below float32's smallest normal carries no light (no subnormal arithmetic)."""
    from translucency_addon.scene.lights import Light

    sun = Light("sun", color=(1.0, 2.2e-311, 1e-39), irradiance=2.0)
    np.testing.assert_array_equal(sun.rgb, [2.0, 0.0, 0.0])
    assert Light("point", color=(1e-30, 1.0, 1.0), intensity=1.0).rgb[0] == 1e-30  # small but normal: kept


def test_first_residual_check_with_a_zero_tolerance():
    """tol = 0 (a fixed sweep count, as the accuracy bench's tolerance table runs it) skips no check and
    does not divide by zero; a finite tolerance skips half the steps the Chebyshev bound needs."""
    from translucency_addon.diffusion.iterative import first_check

    assert first_check(np.array([1.0, 0.5, 0.2]), 0.0, np.array([1.01, 1.01, 1.01]), 8) == 0
    k = first_check(np.array([1.0]), 1e-4, np.array([1.01]), 8)
    need = np.arccosh(1e4) / np.arccosh(1.01)
    assert k % 8 == 0 and 0.5 * need - 8 < k <= 0.5 * need


def test_the_vertex_map_is_one_sparse_product_equal_to_the_gather():
    """``radiance.map_to_points`` (one CSR product over every array a frame maps) against the per-slot gather
    it replaced, on a map with padded slots (weight 0) and a node named twice in one row; the operator is
    built once per map and rebuilt for another."""
    from translucency_addon.diffusion import radiance

    rng = np.random.default_rng(3)
    n_nodes, n, k = 50, 400, 6
    idx = rng.integers(0, n_nodes, (n, k)).astype(np.int32)
    idx[:, 1] = idx[:, 0]  # twice in each row
    w = rng.random((n, k)).astype(np.float32)
    w[:, -1] = 0.0  # a padded slot
    a, b = rng.random((n_nodes, 3)), rng.random(n_nodes)
    got_a, got_b = radiance.map_to_points(idx, w, a, b)
    w64 = w.astype(np.float64)
    np.testing.assert_allclose(got_a, np.einsum("vk,vkc->vc", w64, a[idx]), rtol=1e-14, atol=0)
    np.testing.assert_allclose(got_b, np.einsum("vk,vk->v", w64, b[idx]), rtol=1e-14, atol=0)
    assert got_b.shape == (n,)
    assert radiance.mapping_operator(idx, w, n_nodes) is radiance.mapping_operator(idx, w, n_nodes)
    w2 = w.copy()
    w2[:, 0] = 0.0
    (got2,) = radiance.map_to_points(idx, w2, a)
    np.testing.assert_allclose(got2, np.einsum("vk,vkc->vc", w2.astype(np.float64), a[idx]), rtol=1e-14, atol=0)


@pytest.mark.parametrize("dtypes", [(np.int32, np.float32), (np.int64, np.float64)])
def test_the_compiled_vertex_map_is_the_sparse_product(monkeypatch, dtypes):
    """On large meshes map_to_points runs the compiled gather (diffusion/compiled_map.py) where numba runs: the
    CSR product's sums to rounding, padded slots and a node named twice in a row included, for the maps' index
    and weight types (a bake's int32 / float32, a fluid's int64 / float64)."""
    from translucency_addon.diffusion import compiled_map, radiance

    if compiled_map.available():
        pytest.skip(f"the compiled gather cannot run here: {compiled_map.available()}")
    rng = np.random.default_rng(4)
    n_nodes, n, k = 60, 500, 6
    idx = rng.integers(0, n_nodes, (n, k)).astype(dtypes[0])
    idx[:, 2] = idx[:, 0]
    w = rng.random((n, k)).astype(dtypes[1])
    w[:, -1] = 0.0
    a, b = rng.random((n_nodes, 3)), rng.random(n_nodes)
    monkeypatch.setattr(radiance, "COMPILED_MAP_MIN_POINTS", 0)
    calls = []
    real = compiled_map.gather
    monkeypatch.setattr(compiled_map, "gather", lambda *args: calls.append(1) or real(*args))
    got_a, got_b = radiance.map_to_points(idx, w, a, b)
    assert calls == [1] and got_b.shape == (n,)
    want = radiance.mapping_operator(idx, w, n_nodes) @ np.hstack([a, b[:, None]])
    np.testing.assert_allclose(got_a, want[:, :3], rtol=1e-15, atol=0)
    np.testing.assert_allclose(got_b, want[:, 3], rtol=1e-15, atol=0)


def test_the_drivers_sparse_upsample_is_eq_10s_gather():
    """DiffusionSolver.upsample (eq. 10 as one sparse product, kernels.shepard_matrix) gives what the GPU
    kernel's twin, kernels.shepard_upsample (a gather of the 8 coarse neighbours), gives, empty slots
    included; a multi-level solve starts its finer levels from it."""
    from translucency_addon.diffusion import kernels

    b = baked("spot", levels=2, base_triangles=300, mm_per_unit=40.0)
    s = DiffusionSolver(b, MARBLE)
    idx, w = b.shepard[0]
    assert (idx < 0).any()  # the gather's zero row is exercised
    x = np.random.default_rng(0).standard_normal((b.levels[0].n_nodes, 3))
    np.testing.assert_allclose(s.upsample(1, x), kernels.shepard_upsample(idx, w, x), rtol=0, atol=1e-13)
    np.testing.assert_allclose(s.initial_guess(1, (0, 2), coarser=x), kernels.shepard_upsample(idx, w, x[:, [0, 2]]),
                               rtol=0, atol=1e-13)
