"""Hard cases stay numerically stable (issue 9).

One parametrised suite over the named case fixtures of ``conftest.py``
(builders in ``cases.py``, which also documents every bound and tolerance).
For every case that solves:

* ``test_our_scheme_on_the_cpu``: bake -> solve with the CPU default
  (``fast``: Chebyshev on our finite-volume scheme) and the direct solver;
  no NaN/Inf, radiance >= 0, the maximum principle and the energy bound on
  every level, the residual falls to the tolerance without rising more than
  ``HISTORY_FACTOR`` above its running minimum, the discrete energy balance,
  the QuadGraph invariants, and the iterative answer within ``AGREE`` =
  10 x TOL of the direct one;
* ``test_gpu_path``: the same bounds for the compute-shader solver
  (llvmpipe here) and agreement with the CPU: ``GPU_TOL`` = 1e-4 in fp32,
  ``FP16_TOL`` = 3e-3 with fp16 storage;
* ``test_paper_scheme_is_reported``: the paper's eqs. 5-9 (Jacobi) on the
  same light; reported (printed), only required to terminate honestly --
  under the 1e4 kappa contrast it diverges, which a dedicated test asserts
  next to our scheme converging.

Every case that must be refused raises a ``TranslucencyError`` naming the
problem (``test_rejected_with_a_message``); those that can go through Blender
are also driven through the bake/solve operators, which must leave the scene
unchanged (objects, mesh data, attributes, settings, cache files).
"""

from __future__ import annotations

import hashlib
import os
import re
from dataclasses import replace

import numpy as np
import pytest

from test_ops_bake import cache_dir, memo_bakes  # noqa: F401  (fixtures for the Blender tests)

from . import cases as hc

GPU_CASES = [c for c in hc.SOLVING]
CPU_CASES = [c for c in hc.SOLVING if c != "fp16_scale"]  # fp16 is a GPU storage option
PAPER_CASES = ["thin_shell", "thin_fin", "high_genus", "slivers", "kappa_contrast", "albedo_near_1",
               "albedo_near_0", "tiny_and_huge", "grazing_light", "occluded_light", "degenerate", "disjoint",
               "open_mesh", "no_lights"]


def _params(names, *marks):
    return [pytest.param(n, id=n, marks=list(marks) + ([pytest.mark.slow] if n in hc.SLOW else []))
            for n in names]


_RUNS: dict = {}


def cpu_run(scn: hc.Scenario, name: str = "fast") -> hc.Run:
    """Memoised CPU runs (the GPU and paper tests compare with the same CPU solve)."""
    key = (scn.label, name)
    if key not in _RUNS:
        q = None if name == "fast" else cpu_run(scn, "fast").result.q
        _RUNS[key] = hc.run_solver(scn, name, q=q)
    return _RUNS[key]


def conditioning_error(scn: hc.Scenario) -> float:
    """How far an iterate stopped at ``TOL`` may lie from the exact discrete solution, measured.

    The CPU's ``fast`` run, and the same run held to Chebyshev (the GPU's method; the CPU's default is CG on
    large levels, :func:`iterative.prefers_cg`, whose iterate lies closer), against the direct solve of the
    same case (``compare``'s scale), the larger of the two.  Two iterates that both stop at the same relative
    residual (the GPU's and the CPU's) may then differ by up to twice it: ~1e-6 on most cases, up to 1.5e-3
    on the slivers, whose bakes differ from run to run (fTetWild without optimisation is not deterministic)."""
    direct = cpu_run(scn, "direct")
    err, _ = hc.compare(cpu_run(scn, "fast"), direct, np.inf)
    key = (scn.label, "fast, Chebyshev")
    if key not in _RUNS:
        from translucency_addon.diffusion import iterative

        with pytest.MonkeyPatch.context() as mp:
            mp.setattr(iterative, "CG_MIN_NODES", 1 << 40)
            _RUNS[key] = hc.run_solver(scn, "fast")
    err_cheb, _ = hc.compare(_RUNS[key], direct, np.inf)
    return max(err, err_cheb)


def _report(metrics: dict, extra: str = "") -> str:
    sweeps = "/".join(str(s) for s in metrics["sweeps"])
    return (f"{metrics['case']:<34} {metrics['solver']:<12} sweeps {sweeps:<16} residual {metrics['residual']:.1e} "
            f"flux/source {metrics['flux_ratio']:.4g} out/in {metrics['power_ratio']:.4g} {extra}")


# ----------------------------------------------------------------------------- cases that solve


@pytest.mark.parametrize("case", _params(CPU_CASES), indirect=True)
def test_our_scheme_on_the_cpu(case):
    from translucency_addon.quadgraph.levels import check_invariants

    problems = []
    for scn in case:
        for i, lv in enumerate(scn.bake.levels):
            problems += [f"{scn.label}: level {i}: {p}" for p in check_invariants(lv)]
        fast = cpu_run(scn, "fast")
        metrics, p = hc.check(fast)
        problems += [f"{scn.label} fast: {x}" for x in p]
        direct = cpu_run(scn, "direct")
        _, p = hc.check(direct)
        problems += [f"{scn.label} direct: {x}" for x in p]
        # The iterative answer converges to the direct one: at tol / 1000 the largest per-vertex
        # difference is below AGREE.  A Euclidean relative residual bounds the error only up to the
        # conditioning, and the slivers' graph (fTetWild without optimisation is not deterministic:
        # every bake differs; its diagonal spans 9 decades, weakly coupled pockets of cells make slow
        # modes the residual hardly sees) leaves, over 12 bakes, 6.5e-5 .. 1.8e-3 at tol and
        # 1.5e-5 .. 5.9e-4 at tol / 10 (1.3e-3 on one CI bake); at tol / 1000 the five worst of them
        # leave 8.7e-7 .. 8.1e-5, 12x inside AGREE.  (Every other case: 3e-8 .. 6e-6 at tol, cases.py.)
        tight = hc.run_solver(scn, "fast", q=fast.result.q, tol=hc.TOL / 1000)
        err, p = hc.compare(tight, direct, hc.AGREE)
        problems += [f"{scn.label}: {x}" for x in p]
        print(_report(metrics, f"|L(tol/1000) - L_direct| / max L = {err:.1e}"))
    assert problems == []


@pytest.mark.parametrize("case", _params(CPU_CASES), indirect=True)
def test_every_term_on(case):
    """Single and multiple scattering together (the first-scatter split, issue 17): the same bounds.

    The maximum principle holds for the diffusion on its own source m q, and the energy bound for the
    sum: what the diffusion and the closed-form single scattering send out together never exceeds the
    light that entered (``cases.power``).  The split changes the result (single scattering is there)
    wherever light enters a scattering medium."""
    problems = []
    for scn in case:
        run = hc.run_solver(scn, "fast", single=True)
        metrics, p = hc.check(run)
        problems += [f"{scn.label} every term on: {x}" for x in p]
        plain = cpu_run(scn, "fast")
        q_in = run.result.q_incident[-1]
        if np.any(q_in > 0):
            pb = run.solver.power_balance(run.result)
            assert np.all(pb["single"] > 0) or not np.all(q_in.sum(axis=0) > 0), scn.label
            assert np.all(run.result.q[-1] <= q_in + 1e-15), scn.label  # the source never grows
        else:
            assert np.array_equal(run.radiance, plain.radiance), scn.label
        print(_report(metrics))
    assert problems == []


@pytest.mark.gpu
@pytest.mark.parametrize("case", _params(GPU_CASES), indirect=True)
def test_gpu_path(case):
    problems = []
    for scn in case:
        run = hc.run_solver(scn, "gpu")
        try:
            metrics, p = hc.check(run)
            problems += [f"{scn.label} {run.solver_name}: {x}" for x in p]
            tol = max(hc.FP16_TOL if scn.precision == "fp16" else hc.GPU_TOL, hc.residual_floor(run, -1),
                      2.0 * conditioning_error(scn))
            err, p = hc.compare(run, cpu_run(scn, "fast"), tol)
            problems += [f"{scn.label}: {x}" for x in p]
            if scn.expect_warning and not any(re.search(scn.expect_warning, w) for w in run.solver.warnings):
                problems.append(f"{scn.label}: the GPU solver's light pass did not warn")
            print(_report(metrics, f"|L_gpu - L_cpu| / max L = {err:.1e} (tol {tol:g})"))
        finally:
            run.solver.free()
    assert problems == []


@pytest.mark.parametrize("case", _params(PAPER_CASES), indirect=True)
def test_paper_scheme_is_reported(case):
    """The paper's Jacobi is not required to converge or to respect the bounds;
    it must stop (at convergence, at divergence, or at the sweep cap) and say which."""
    for scn in case:
        if not scn.paper:
            continue
        run = cpu_run(scn, "paper")
        metrics, problems = hc.check(run, strict=False)
        cap = hc.PAPER_MAX_ITERATIONS + 8
        assert all(ls.iterations <= cap for ls in run.result.level_solves)
        state = "converged" if metrics["converged"] else "DIVERGED" if metrics["diverged"] else "stopped at the cap"
        print(_report(metrics, state + ("; violates: " + "; ".join(problems) if problems else "")))
        if metrics["diverged"]:  # divergence is detected and reported, not hidden
            assert run.result.level_solves[-1].diverged or any(ls.diverged for ls in run.result.level_solves)


# ----------------------------------------------------------------------------- case-specific facts


def test_kappa_contrast_paper_diverges_where_ours_converges(kappa_contrast):
    """Neighbouring nodes' kappa really differs 1e4-fold; eq. 5's Jacobi diverges, ours does not."""
    scn = kappa_contrast[0]
    lv = scn.bake.finest
    sa, ss = scn.material.coefficients(scn.field_values[-1])
    kappa = 1.0 / (3.0 * (sa + ss))[:, 0]
    nb = lv.neighbors[: lv.n_inner]
    ratio = kappa[: lv.n_inner, None] / kappa[np.maximum(nb, 0)]
    assert np.max(ratio[nb >= 0]) == pytest.approx(1e4, rel=1e-9)
    assert np.mean(np.abs(np.log10(ratio[nb >= 0])) > 3.9) > 0.05  # many links cross a jump
    paper = cpu_run(scn, "paper")
    assert any(ls.diverged for ls in paper.result.level_solves)
    fast = cpu_run(scn, "fast")
    metrics, problems = hc.check(fast)
    assert problems == [] and metrics["converged"]


def _chebyshev_bound(system, tol):
    """Sweeps Chebyshev needs to cut the residual by ``tol`` with the exact eigenvalue interval."""
    from scipy.sparse import diags
    from scipy.sparse.linalg import eigsh

    from translucency_addon.diffusion.assembly import sparse_matrix
    from translucency_addon.diffusion.spectral import gershgorin_upper

    worst = 0.0
    for c in range(3):
        A = sparse_matrix(system, c)
        d = diags(1.0 / np.sqrt(system.diag[:, c]))
        lam_min = eigsh((d @ A @ d).tocsc(), k=1, sigma=0, which="LM", return_eigenvectors=False)[0]
        lam_max = gershgorin_upper(system)[c]
        sigma = (lam_max + lam_min) / (lam_max - lam_min)
        worst = max(worst, np.arccosh(2.0 / tol) / np.arccosh(sigma))
    return worst, lam_min


@pytest.mark.parametrize("which", ["albedo_near_1/1 mm", "tiny_and_huge/tiny 0.1 mm"])
def test_nearly_singular_systems_converge_in_a_bounded_number_of_sweeps(which, albedo_near_1, tiny_and_huge):
    """Little absorption and a weak boundary leak: lambda_min of D^-1 A is ~1e-3..1e-4.

    The finest level must need at most 1.5x the sweeps Chebyshev needs with
    the exact eigenvalue interval (measured 1.0-1.3x; with the old random-start
    Lanczos estimate, 2.7x, and an error above the tolerance).
    """
    scn = next(s for s in albedo_near_1 + tiny_and_huge if s.label == which)
    run = cpu_run(scn, "fast")
    bound, lam_min = _chebyshev_bound(run.solver.systems[-1], hc.TOL)
    sweeps = run.result.level_solves[-1].iterations
    print(f"{which}: lambda_min {lam_min:.2e}, finest sweeps {sweeps}, exact-interval bound {bound:.0f}")
    assert sweeps <= 1.5 * bound
    err, problems = hc.compare(run, cpu_run(scn, "direct"), hc.AGREE)
    assert problems == [], err


def test_albedo_near_1_returns_nearly_all_light(albedo_near_1):
    for scn in albedo_near_1:
        run = cpu_run(scn, "direct")
        pb = run.solver.power_balance(run.result)
        ratio = pb["out"] / pb["in"]
        assert np.all(ratio > 0.99) and np.all(ratio <= 1.0), (scn.label, ratio)


def test_albedo_near_0_is_bounded_and_flagged(albedo_near_0):
    """The solver guarantees bounded, non-negative output that returns little light.

    The planner assertion at the end is conditional on ``translucency_addon.planner``
    being importable (it is developed in parallel); only that part is.
    """
    scn = albedo_near_0[0]
    run = cpu_run(scn, "fast")
    metrics, problems = hc.check(run)
    assert problems == []
    pb = run.solver.power_balance(run.result)
    assert np.all(pb["out"] < 0.05 * pb["in"]), pb  # an absorber: ~2 % comes back, never more than 5 %
    try:
        from translucency_addon import planner
    except ImportError:  # the planner is optional here; the bounds above are not
        return
    plan = planner.plan_object(scn.bake, scn.material, scn.lights, scn.environment)
    assert plan.multiple is not None and not any(plan.multiple.channels), planner.describe_plan(plan)
    assert all("diffusion invalid" in r for r in plan.multiple.reasons), plan.multiple.reasons


def test_thin_shell_stays_a_shell(thin_shell):
    """The draft bake cannot follow a 0.1 mm wall exactly (the resampled spheres cross),
    but fTetWild keeps a shell: its volume is that of the shell, not of the filled ball."""
    scn = thin_shell[0]
    exact = 4.0 / 3.0 * np.pi * (1.0 - 0.99**3)
    for note in scn.notes:
        print(note)
    for lv in scn.bake.levels:
        assert 0.3 < lv.volume.sum() / exact < 3.0  # a filled ball would be 34x
        r = np.linalg.norm(lv.position[: lv.n_inner], axis=1)
        assert r.min() > 0.8


def test_slivers_are_really_there(slivers):
    """optimize=False leaves slivers (NOTES.md: median quality ~0.02) and the bounds still hold."""
    lv0 = slivers[0].bake.levels[0]
    for note in slivers[0].notes:
        print(note)
    assert lv0.stats["tet_quality_median"] < 0.1
    assert lv0.stats["tet_quality_min"] < 1e-3


def test_torus_grid_is_one_body(high_genus):
    grid = next(s for s in high_genus if s.variant == "torus-grid")
    assert len(np.unique(hc.graph_components(grid.bake.finest))) == 1  # the tori fused: genus >= 6


def test_grazing_light_adds_almost_nothing_to_the_grazed_face(grazing_light):
    """Nodes of the top face's interior (exact normal +z) see cos 1e-6 (sun) and 0 (point light);
    near the edges the interpolated vertex normals tilt, so those are not counted."""
    scn = grazing_light[0]
    run = cpu_run(scn, "fast")
    lv = scn.bake.finest
    q = run.result.q[-1]
    top = lv.normal[:, 2] > 1.0 - 1e-12
    side = lv.normal[:, 0] > 1.0 - 1e-12
    assert top.sum() > 10 and side.sum() > 10
    assert q[top].max() < 1e-4 * q[side].max()


def test_light_inside_is_not_a_surface_source(light_inside, thin_shell):
    """A light inside contributes nothing (with a warning); just outside it lights as usual;
    in the hollow of the shell it is outside the medium and lights the inner wall."""
    from translucency_addon.diffusion.solver import DiffusionSolver, SolveOptions
    from translucency_addon.scene.lights import Light

    torus = next(s for s in light_inside if s.variant.startswith("torus"))
    inside = torus.lights[0]
    solver = DiffusionSolver(torus.bake, torus.material)
    outside = Light("point", intensity=50.0, position=(1.0, 0.0, 0.6), name="above the tube")
    r = solver.solve([outside])
    assert solver.warnings == [] and r.warnings == []
    alone = solver.vertex_radiance(r)
    assert alone.max() > 0
    # the inside light adds exactly nothing, also next to a light that counts, and it is named
    both = solver.solve([outside, inside])
    assert len(both.warnings) == 1 and "'inside tube'" in both.warnings[0]
    np.testing.assert_array_equal(solver.vertex_radiance(both), alone)
    only_inside = solver.solve([inside])
    assert np.all(solver.vertex_radiance(only_inside) == 0.0)
    # In the shell's hollow the light is outside the medium: it lights the inner wall (surface
    # nodes facing it) and no node that faces away, and what leaves is what came in less what
    # the wall absorbed.
    shell = thin_shell[0]
    solver = DiffusionSolver(shell.bake, shell.material, options=SolveOptions(solver="direct"))
    r = solver.solve([Light("point", intensity=50.0, position=(0.0, 0.0, 0.0), name="in the hollow")])
    assert solver.warnings == []
    L = solver.vertex_radiance(r)
    assert np.all(np.isfinite(L)) and L.min() > 0
    lv = shell.bake.finest
    facing = np.einsum("ij,ij->i", lv.normal, -lv.surface_position) > 0  # the normal points at the light
    q = r.q[-1]
    lit = q.max(axis=1) > 0
    print("lit share of the nodes facing the light", lit[facing].mean(), "of the others", lit[~facing].mean())
    assert facing.any() and lit[facing].mean() > 0.9  # a few are shadowed where the resampled walls cross
    assert not lit[~facing].any()
    pb = solver.power_balance(r)
    assert np.all(pb["in"] > 0)
    np.testing.assert_allclose(pb["out"] + pb["absorbed"], pb["in"], rtol=1e-6)


def test_occluder_dims_the_light(occluded_light):
    scn = next(s for s in occluded_light if s.variant == "point behind wall")
    blocked = cpu_run(scn, "fast").radiance
    free = hc.run_solver(replace(scn, occluders=None, variant="unblocked"), "fast").radiance
    assert blocked.sum() < 0.75 * free.sum()  # the wall hides the light from half the lit side (measured 0.50)


def test_open_and_degenerate_meshes_are_reported_truthfully(open_mesh, degenerate):
    warnings = open_mesh[0].bake.stats["mesh"]["warnings"]
    assert any(re.match(r"mesh is open: [1-9]\d* hole", w) for w in warnings), warnings
    warnings = degenerate[0].bake.stats["mesh"]["warnings"]
    # welded by position the mesh is closed: duplicates must not count as holes
    assert not any("open" in w for w in warnings), warnings
    assert any("80 degenerate" in w for w in warnings) and any("7 unreferenced" in w for w in warnings), warnings


def test_disjoint_pieces_each_obey_the_maximum_principle(disjoint):
    """The graph has one component per piece; on each, phi stays below that piece's own largest source."""
    for scn in disjoint:
        run = cpu_run(scn, "direct")
        for i, lv in enumerate(scn.bake.levels):
            comp = hc.graph_components(lv)
            labels = np.unique(comp)
            assert len(labels) == 2, (scn.label, i, len(labels))
            g = 4.0 * run.result.q[i] / (1.0 - run.solver.fdr)
            surf_comp = comp[lv.n_inner:]
            for c in labels:
                assert np.any(surf_comp == c)  # every piece has surface nodes (was not lost)
                gmax = g[surf_comp == c].max(axis=0)
                assert np.all(run.phi[i][comp == c].max(axis=0) <= gmax * (1 + 1e-9)), (scn.label, i, c)


# ----------------------------------------------------------------------------- cases that are refused


REJECT_PARAMS = _params(["flat_mesh", "nan_input", "bad_cache"]) + [
    pytest.param("texture_limit", id="texture_limit", marks=pytest.mark.gpu)]


@pytest.mark.parametrize("case", REJECT_PARAMS, indirect=True)
def test_rejected_with_a_message(case):
    for rej in case:
        with pytest.raises(rej.error) as info:
            rej.action()
        assert re.search(rej.match, str(info.value)), (rej.label, str(info.value))
        print(f"{rej.label}: {type(info.value).__name__}: {info.value}")


@pytest.mark.gpu
def test_texture_limit_splits_into_layers():
    """Under a 64-texel limit the finest level is split over array-texture layers and still solves."""
    from gpu_shaders.solver import GPUDiffusionSolver
    from translucency_addon.diffusion.solver import SolveOptions

    scn = hc.build_no_lights()[0]
    scn = replace(scn, case="texture_limit", variant="split", lights=[hc.SUN], environment=hc.ENV1,
                     expect_zero=False)
    s = GPUDiffusionSolver(scn.bake, scn.material, None, SolveOptions(tol=hc.TOL), readback="phi",
                           max_texture_size=64)
    try:
        assert s.layouts[-1].layers > 1 and all(lay.width <= 64 and lay.height <= 64 for lay in s.layouts)
        r = s.solve(scn.lights, scn.environment)
        run = hc.Run(scn, "gpu-split", s, r, np.asarray(s.vertex_radiance(r)), [np.asarray(p) for p in r.phi])
        _, problems = hc.check(run)
        _, more = hc.compare(run, cpu_run(scn, "fast"), hc.GPU_TOL)
        assert problems + more == []
    finally:
        s.free()


@pytest.mark.gpu
def test_texture_limit_falls_back_to_the_cpu_with_the_reason():
    import gpu_shaders
    from translucency_addon.diffusion.solver import DiffusionSolver, SolveOptions

    b = hc.baked("sphere", 10.0)
    s, backend, msg = gpu_shaders.make_solver(b, hc.MARBLE, None, SolveOptions(), max_texture_size=32, max_layers=2)
    assert backend == "CPU" and type(s) is DiffusionSolver
    assert "32 x 32 with 2 layers" in msg and "CPU" in msg


# ----------------------------------------------------------------------------- through Blender

# The operators (ops/) use the extension's own copy of the engine
# (translucency.translucency_addon), so errors are matched by message here.


def _attribute_bytes(attr) -> bytes:
    for key in ("color", "vector", "value"):
        try:
            n = len(attr.data)
            width = {"color": 4, "vector": 3}.get(key, 1)
            if key == "vector" and attr.data_type in {"FLOAT2", "INT32_2D"}:
                width = 2
            arr = np.empty(n * width, dtype=np.float64)
            attr.data.foreach_get(key, arr)
            return arr.tobytes()
        except (AttributeError, TypeError, RuntimeError):
            continue
    return b""


def scene_digest(cache_dir=None) -> str:
    """Hash of what a failed operator must not change: objects, their transforms and
    Translucency settings, every mesh's geometry and attributes, the cache folder's files."""
    import bpy

    from test_ops_bake import files_in, settings_snapshot

    h = hashlib.sha256()
    for ob in sorted(bpy.data.objects, key=lambda o: o.name):
        h.update(f"{ob.name}|{ob.type}|{ob.data.name if ob.data else ''}".encode())
        h.update(np.array(ob.matrix_world, dtype=np.float64).tobytes())
        if ob.type == 'MESH':
            h.update(repr(sorted(settings_snapshot(ob).items())).encode())
    for me in sorted(bpy.data.meshes, key=lambda m: m.name):
        co = np.empty(len(me.vertices) * 3)
        me.vertices.foreach_get("co", co)
        loops = np.empty(len(me.loops), dtype=np.int64)
        me.loops.foreach_get("vertex_index", loops)
        h.update(me.name.encode() + co.tobytes() + loops.tobytes())
        for attr in sorted(me.attributes, key=lambda a: a.name):
            if attr.name.startswith("."):
                continue
            h.update(f"{attr.name}|{attr.domain}|{attr.data_type}".encode())
            h.update(_attribute_bytes(attr))
    if cache_dir is not None:
        h.update(repr(files_in(cache_dir)).encode())
    return h.hexdigest()


def _mesh_object(name, V, F):
    import bpy

    me = bpy.data.meshes.new(name)
    me.from_pydata([tuple(map(float, v)) for v in V], [], [tuple(map(int, f)) for f in F])
    me.update()
    obj = bpy.data.objects.new(name, me)
    bpy.context.scene.collection.objects.link(obj)
    s = obj.translucency
    s.quality = 'DRAFT'
    s.levels = 2
    s.use_mm_per_unit_override = True
    s.mm_per_unit = 10.0
    return obj


BAD_MESHES = {
    "flat open plane": (lambda: (np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0.0]]),
                                 np.array([[0, 1, 2], [0, 2, 3]])), r"mesh is flat"),
    "flat closed double-sided plane": (lambda: (np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0.0]]),
                                                np.array([[0, 1, 2], [0, 2, 3], [2, 1, 0], [3, 2, 0]])),
                                       r"flat|zero volume"),
    "NaN coordinate": (lambda: _nan_sphere(), r"1 vertices with NaN or Inf coordinates"),
}


def _nan_sphere():
    from translucency_addon.geometry import primitives

    V, F = primitives.icosphere(1.0, 2)
    V = V.copy()
    V[4] = (np.nan, 0.0, 0.0)
    return V, F


@pytest.mark.parametrize("variant", list(BAD_MESHES))
def test_blender_bake_refuses_and_leaves_the_scene_unchanged(variant, blender, addon, cache_dir):
    import bpy

    from test_ops_bake import activate, add_light, bake, sphere

    keep = sphere(name="Bystander")  # another baked object whose data must not change
    add_light()
    assert bake(keep) == {'FINISHED'}
    V, F = BAD_MESHES[variant][0]()
    obj = _mesh_object("Bad", V, F)
    activate(obj)
    before = scene_digest(cache_dir)
    with pytest.raises(RuntimeError, match=r"Cannot bake 'Bad': .*(" + BAD_MESHES[variant][1] + ")"):
        bpy.ops.translucency.bake(base_triangles=200)
    assert scene_digest(cache_dir) == before
    assert obj.data.attributes.get("translucency_radiance") is None
    assert not any(f.endswith(".partial") for f in os.listdir(cache_dir))


def _baked_and_solved(name="Blob", lights=True):
    import bpy

    from test_ops_bake import activate, add_light, bake, radiance, sphere

    obj = sphere(name=name)
    if lights:
        add_light()
    assert bake(obj) == {'FINISHED'}
    activate(obj)
    assert bpy.ops.translucency.solve() == {'FINISHED'}
    L = radiance(obj)
    assert L is not None and np.all(np.isfinite(L)) and L.min() >= 0.0
    return obj, L


@pytest.mark.parametrize("variant,values,match", [
    ("NaN sigma_a", dict(sigma_a=(float("nan"), 0.01, 0.01)), r"sigma_a contains NaN"),
    # Blender clamps an Inf property to FLT_MAX, which the engine refuses as absurd
    ("Inf sigma_s", dict(sigma_s=(1.0, float("inf"), 1.0)), r"sigma_s contains NaN or Inf|sigma_s = .* is absurd"),
    ("negative clamps to an empty medium", dict(sigma_a=(-1.0, 0.0, 0.0), sigma_s=(0.0, 1.0, 1.0)),
     r"sigma_a \+ sigma_s is zero"),
])
def test_blender_solve_refuses_bad_materials(variant, values, match, blender, addon, cache_dir, memo_bakes):
    import bpy

    obj, L = _baked_and_solved()
    s = obj.translucency
    s.material_preset = 'CUSTOM'
    for key, v in values.items():
        setattr(s, key, v)
    if variant.startswith("negative"):
        assert s.sigma_a[0] == 0.0  # the property clamps negatives: they never reach the engine
    before = scene_digest(cache_dir)
    with pytest.raises(RuntimeError, match=match):
        bpy.ops.translucency.solve()
    assert scene_digest(cache_dir) == before  # the attribute still holds the last good solve


@pytest.mark.parametrize("variant", [v for v in hc.CACHE_DAMAGE])
def test_blender_solve_refuses_a_bad_cache(variant, blender, addon, cache_dir, memo_bakes):
    import bpy

    from translucency.ops import cache_files, state

    obj, L = _baked_and_solved()
    path = cache_files.resolve_cache_path(obj)
    regex = hc.damage_cache(path, path, variant)
    state.clear()  # as after reopening the .blend: the bake must come from the file
    before = scene_digest(cache_dir)
    with pytest.raises(RuntimeError, match=r"Cannot solve 'Blob': .*(" + regex + ")"):
        bpy.ops.translucency.solve()
    assert scene_digest(cache_dir) == before
    assert state.cache_problem("Blob").startswith("Cache problem")


def test_blender_no_lights_and_light_inside_give_exact_zero(blender, addon, cache_dir, memo_bakes):
    """No lights (and no world) -> the attribute is exactly 0; a point light inside the
    sphere adds nothing (see cases.build_light_inside for why), so it stays exactly 0."""
    import bpy

    from test_ops_bake import add_light, radiance

    bpy.context.scene.world = None
    obj, L = _baked_and_solved(lights=False)
    assert np.all(L == 0.0)
    add_light('POINT', location=(0.05, 0.02, -0.03), energy=500.0, name="inside")
    assert bpy.ops.translucency.solve() == {'FINISHED'}
    L = radiance(obj)
    assert np.all(np.isfinite(L)) and np.all(L == 0.0)


def test_blender_two_pieces_solve(blender, addon, cache_dir):
    """Two disjoint pieces in one Blender object bake and solve: finite, non-negative, both lit."""
    import bpy

    from test_ops_bake import activate, add_light, radiance
    from translucency_addon.geometry import primitives

    V, F = primitives.merge(primitives.icosphere(1.0, 2, center=(-2.0, 0.0, 0.0)),
                            primitives.icosphere(0.5, 2, center=(2.0, 0.0, 0.0)))
    obj = _mesh_object("Pair", V, F)
    add_light('SUN', energy=5.0)
    activate(obj)
    assert bpy.ops.translucency.bake(base_triangles=200) == {'FINISHED'}
    L = radiance(obj)
    assert np.all(np.isfinite(L)) and L.min() >= 0.0
    left = V[:, 0] < 0
    assert L[left].max() > 0 and L[~left].max() > 0


@pytest.mark.gpu
def test_blender_texture_limit_falls_back_to_the_cpu(blender, addon, cache_dir, memo_bakes, monkeypatch):
    """With the device limits below the graph's size the operator still solves, on the CPU, and says why."""
    import bpy
    import gpu

    from translucency.ops import state

    monkeypatch.setattr(gpu.capabilities, "max_texture_size_get", lambda: 32)
    monkeypatch.setattr(gpu.capabilities, "max_texture_layers_get", lambda: 2)
    bpy.context.scene.translucency.solver_backend = 'AUTO'
    obj, L = _baked_and_solved()
    st = state.get_state(obj)
    assert st.backend == "CPU" and "32 x 32 with 2 layers" in st.backend_message, st.backend_message


def test_a_level_without_light_solves_to_exactly_zero_whatever_the_warm_start():
    """A light grazing the surface can light the coarse level's nodes and none of the finest's (the
    fuzz found one: a spot on the unit sphere).  The finest level's answer is then exactly 0, not the
    upsampled coarse solution the relative stopping test (|b| = 0) would accept."""
    from translucency_addon.diffusion.solver import DiffusionSolver, SolveOptions

    b = hc.baked("sphere", 10.0)
    solver = DiffusionSolver(b, hc.MARBLE, options=SolveOptions(solver="fast"))
    q = [np.zeros((lv.n_surface, 3)) for lv in b.levels]
    q[0][:5] = 1.0  # light on a few coarse surface nodes only
    r = solver.solve(q=q)
    assert np.abs(r.phi[0]).max() > 0
    assert np.all(r.phi[-1] == 0.0)


def test_a_solve_that_breaks_the_maximum_principle_is_redone_directly():
    """The FV solution lies in [0, max 4q/(1 - F_dr)]; an iterate outside is refused and the level is
    solved by sparse LU, with a warning that says so (the derandomised fuzz found a near-singular
    mix -- no absorption in one channel -- where Chebyshev wandered to 1e185 at a residual of 1e-5)."""
    from translucency_addon.diffusion import iterative
    from translucency_addon.diffusion.solver import DiffusionSolver, SolveOptions
    from translucency_addon.diffusion.iterative import BALANCE_TOL, energy_imbalance, outside_maximum_principle

    b = hc.baked("sphere", 10.0)
    q = [np.full((lv.n_surface, 3), 1.0) for lv in b.levels]
    good = DiffusionSolver(b, hc.MARBLE, options=SolveOptions(solver="direct")).solve(q=q)
    solver = DiffusionSolver(b, hc.MARBLE, options=SolveOptions(solver="fast"))
    system = solver.systems[-1]
    rhs = system.rhs(q[-1])
    assert not outside_maximum_principle(system, rhs, good.phi[-1])
    assert outside_maximum_principle(system, rhs, good.phi[-1] * 2.0)
    assert outside_maximum_principle(system, rhs, -good.phi[-1])
    # the discrete energy balance: exact for the solution, broken by an unconverged one
    assert energy_imbalance(system, q[-1], good.phi[-1], solver.fdr) < 1e-8
    assert energy_imbalance(system, q[-1], 0.9 * good.phi[-1], solver.fdr) > BALANCE_TOL

    def wander(system, b, x0, tol, max_iter, check_every=8):  # a broken iteration: 1e185 at a small residual
        x, info = iterative.solve_chebyshev(system, b, x0, tol, max_iter, check_every)
        return x + 1e185, info

    original = iterative.SOLVER_FUNCTIONS["fast"]
    iterative.SOLVER_FUNCTIONS["fast"] = wander
    try:
        r = solver.solve(q=q)
    finally:
        iterative.SOLVER_FUNCTIONS["fast"] = original
    np.testing.assert_allclose(r.phi[-1], good.phi[-1], rtol=1e-9)
    assert any("broke the maximum principle" in w and "solved directly" in w for w in r.warnings), r.warnings
