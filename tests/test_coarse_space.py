"""The coarse space of the conjugate gradients (diffusion/coarse_space.py): the two-level preconditioner
M^-1 = D^-1 + P A_c^-1 P^T on a fluid frame's graph, against an independent assembly of P^T A P and a
direct sparse solve."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from test_fluid_solve import ENV1, SUN, ball_of_particles, jittered_frames
from translucency_addon.diffusion import coarse_space as cs
from translucency_addon.diffusion import iterative
from translucency_addon.diffusion.assembly import sparse_matrix
from translucency_addon.fluid import FluidSolver
from translucency_addon.scene.materials import material_from_preset


@pytest.fixture(autouse=True)
def small_graphs_get_one(monkeypatch):
    """The module's threshold (8,000 nodes, where the coarse space pays) lowered for this file's 2,800-node
    frame, so the tests stay small; the last test checks the threshold itself."""
    monkeypatch.setattr(cs, "MIN_NODES", 2000)


def _frame():
    """A warm frame of a ball of ~2,100 particles (~2,800 nodes): system, b and start."""
    r0, r1 = jittered_frames(8.0, 7)
    system = r1.diffusion.systems[0]
    b = system.rhs(r1.solve.q[0])
    x0 = r0.solve.phi[0][: system.n] if len(r0.solve.phi[0]) >= system.n else np.zeros_like(b)
    return system, b, np.ascontiguousarray(x0[: system.n])


@pytest.mark.parametrize("compiled", [True, False])
def test_the_coarse_correction_is_p_ac_inverse_pt(monkeypatch, compiled):
    """add_correction adds P (P^T A P)^-1 P^T r per channel, with A from assembly.sparse_matrix and P the
    aggregates' 0/1 matrix, both built here independently of the module's Galerkin sums: the compiled passes
    over the sweeps' link slots (compiled_cg.galerkin_sums, where numba runs) and numpy's bincount."""
    from translucency_addon.diffusion import compiled_cg

    system, _, _ = _frame()
    assert system.n >= cs.MIN_NODES
    op = system.sweep_operator(np.float64)
    if compiled and op.links is None:
        pytest.skip(f"the compiled CG kernels cannot run here: {compiled_cg.available()}")
    if not compiled:
        monkeypatch.setattr(op, "links", None)  # the numpy sums (slot_values then reads the system)
    calls, real = [], compiled_cg.galerkin_sums
    monkeypatch.setattr(compiled_cg, "galerkin_sums", lambda *a: calls.append(1) or real(*a))
    system.cache.pop("coarse_space", None)
    space = cs.coarse_space(system, op)
    assert len(calls) == int(compiled)
    assert space is not None and cs.MIN_AGGREGATES // 2 <= space.n_agg <= cs.MAX_AGGREGATES
    agg = np.empty(system.n, dtype=np.int64)
    agg[op.perm] = space.agg  # node order
    Pm = sp.csr_matrix((np.ones(system.n), (np.arange(system.n), agg)), shape=(system.n, space.n_agg))
    r = np.random.default_rng(0).normal(size=(system.n, 3))
    Z = np.zeros((3, system.n))
    space.add_correction(op.to_cm(r), Z)
    got = op.from_cm(Z)
    for c in range(3):
        A = sparse_matrix(system, c)
        Ac = (Pm.T @ A @ Pm).toarray()
        want = Pm @ np.linalg.solve(Ac, Pm.T @ r[:, c])
        np.testing.assert_allclose(got[:, c], want, rtol=1e-9, atol=1e-12 * np.abs(want).max())


def test_cg_with_the_coarse_space_needs_fewer_steps_and_keeps_the_answer():
    """Same system, same start: CG with the coarse space matches a direct solve to the tolerance and takes
    fewer than 0.75x the steps of Jacobi-preconditioned CG (measured 0.45x at 16k particles,
    docs/bench_fluid.md); without it (``coarse=False``) the steps are Jacobi CG's."""
    system, b, x0 = _frame()
    x_two, two = iterative.solve_cg(system, b, x0, 1e-4, 10_000)
    x_one, one = iterative.solve_cg(system, b, x0, 1e-4, 10_000, coarse=False)
    ref, _ = iterative.solve_direct(system, b)
    assert two.converged_to <= 1e-4 and one.converged_to <= 1e-4
    assert np.abs(x_two - ref).max() < 1e-3 * ref.max()
    assert two.iterations < 0.75 * one.iterations, (two.iterations, one.iterations)


def test_a_graph_kept_across_frames_gets_finer_aggregates_and_fewer_steps(monkeypatch):
    """A fluid's cells are built every frame (their set-up is paid per frame: a box per NODES_PER_AGGREGATE
    nodes, at most MAX_AGGREGATES); a bake's level is kept, so its boxes are finer (NODES_PER_AGGREGATE_KEPT,
    up to MAX_AGGREGATES_KEPT), which takes fewer CG steps to the same answer (the Final bunny's finest
    level: 1,587 aggregates, 88 steps over both blocks of a warm frame, against 267 and 113)."""
    from dataclasses import replace

    monkeypatch.setattr(cs, "MIN_AGGREGATES", 8)  # this file's 2,800 nodes: 21 boxes against 43
    system, b, x0 = _frame()
    assert system.level.built_per_frame
    kept = replace(system, level=replace(system.level, built_per_frame=False), cache={})
    per_frame = cs.coarse_space(system, system.sweep_operator(np.float64))
    finer = cs.coarse_space(kept, kept.sweep_operator(np.float64))
    assert finer.n_agg > 1.5 * per_frame.n_agg, (finer.n_agg, per_frame.n_agg)
    x_pf, pf = iterative.solve_cg(system, b, x0, 1e-6, 10_000)
    x_k, k = iterative.solve_cg(kept, b, x0, 1e-6, 10_000)
    assert k.iterations < pf.iterations, (k.iterations, pf.iterations)
    np.testing.assert_allclose(x_k, x_pf, rtol=0, atol=1e-5 * np.abs(x_pf).max())


def test_aggregates_number_every_occupied_box_once_and_survive_a_flat_graph():
    rng = np.random.default_rng(1)
    X = rng.uniform(0, 10, size=(5000, 3))
    agg, n = cs.aggregates(X, 125)
    assert agg.min() == 0 and agg.max() == n - 1 and len(np.unique(agg)) == n
    assert 60 <= n <= 200  # ~125 boxes over a filled cube
    flat = X.copy()
    flat[:, 2] = 3.0  # every node in one plane: boxes as thin as the graph, still about the target count
    agg, n = cs.aggregates(flat, 125)
    assert len(np.unique(agg)) == n and 20 <= n <= 200


def test_small_graphs_run_jacobi_cg_alone(monkeypatch):
    """Below MIN_NODES the coarse solve would cost about what it saves: no coarse space (the ~2,100-particle
    ball above, at the module's own threshold)."""
    monkeypatch.setattr(cs, "MIN_NODES", 8000)
    P0 = ball_of_particles(8.0, 1.0)
    r = FluidSolver(material_from_preset("skimmilk"), 1.0, 1.0).solve(P0, lights=SUN, environment=ENV1)
    system = r.diffusion.systems[0]
    assert system.n < cs.MIN_NODES
    assert cs.coarse_space(system, system.sweep_operator(np.float64)) is None


def test_a_coarse_operator_that_is_not_positive_definite_leaves_jacobi_alone():
    """A_c must be positive definite for M^-1 to be (CG's condition): the same graph with -A's entries
    negated (A negative definite) gets no coarse space; the true entries get one."""
    from types import SimpleNamespace

    system, _, _ = _frame()
    op = system.sweep_operator(np.float64)
    links = None if op.links is None else (op.links[0], -op.links[1], -op.links[2])  # the compiled sums' input
    flipped = SimpleNamespace(perm=op.perm, C=op.C, links=links,
                              slot_values=lambda c: tuple(-v for v in op.slot_values(c)))
    system.cache.pop("coarse_space", None)
    assert cs.coarse_space(system, flipped) is None
    system.cache.pop("coarse_space", None)
    assert cs.coarse_space(system, op) is not None


@pytest.mark.parametrize("coarse", [True, False])
def test_the_compiled_cg_step_is_the_numpy_step(coarse):
    """diffusion/compiled_cg.py's two passes per step (z never formed: r.z = r.D^-1 r + (P^T r).y) against
    cg_steps's numpy step: the same iterates to rounding at every step, the same step count, the same
    answer; with and without the coarse space (one aggregate whose value stays 0)."""
    from translucency_addon.diffusion import compiled_cg

    if compiled_cg.available():
        pytest.skip(f"the compiled CG step cannot run here: {compiled_cg.available()}")
    system, b, x0 = _frame()
    runs = {}
    for compiled in (True, False):
        gen = iterative.cg_steps(system, b, x0, 1e-8, 400, coarse=coarse, compiled=compiled)
        its = []
        try:
            while True:
                its.append(next(gen)())
        except StopIteration as stop:
            runs[compiled] = (its, stop.value)
    (it_c, (x_c, info_c)), (it_n, (x_n, info_n)) = runs[True], runs[False]
    assert info_c.iterations == info_n.iterations == len(it_c) == len(it_n) > 5
    scale = np.abs(x_n).max()
    for k in (0, len(it_n) // 2, len(it_n) - 1):
        np.testing.assert_allclose(it_c[k], it_n[k], rtol=0, atol=1e-9 * scale, err_msg=f"step {k}")
    np.testing.assert_allclose(x_c, x_n, rtol=0, atol=1e-10 * scale)
    assert info_c.residual.max() <= 1e-8 and info_c.seconds > 0


def test_without_the_compiled_step_large_levels_keep_chebyshev_and_cg_its_numpy_step(monkeypatch):
    """Where numba is missing (macOS x86-64) compiled_cg says so, iterative.prefers_cg keeps Chebyshev on a
    level of few links however large (its rule for CG there is the compiled step), a fluid's cells (many
    links) keep CG with the numpy step, and the answer is the same."""
    from translucency_addon.diffusion import compiled_cg

    system, b, x0 = _frame()
    x_fast, _ = iterative.solve_cg(system, b, x0, 1e-9, 400)
    monkeypatch.setattr(compiled_cg, "_KERNEL", {"error": "numba is not installed"})
    assert compiled_cg.available() == "numba is not installed"
    assert iterative.prefers_cg(system)  # 14-15 links per cell: CG either way
    x_numpy, info = iterative.solve_cg(system, b, x0, 1e-9, 400)
    np.testing.assert_allclose(x_numpy, x_fast, rtol=0, atol=1e-8 * np.abs(x_fast).max())
    monkeypatch.setattr(iterative, "CG_MIN_LINKS", 1e9)  # as a QuadGraph level (3-4 links) ...
    monkeypatch.setattr(iterative, "CG_MIN_NODES", 0)  # ... of any size
    assert not iterative.prefers_cg(system)
    monkeypatch.setattr(compiled_cg, "_KERNEL", {})  # the kernels load again: CG there
    assert iterative.prefers_cg(system) == (compiled_cg.available() == "")


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_the_compiled_reorderings_are_numpy_s(monkeypatch, dtype):
    """SweepOperator.to_cm / from_cm (node-major <-> channel-major in the sweep order), compiled where numba runs
    (cg_kernels.to_channel_major / from_channel_major), give numpy's arrays exactly, in either precision, and
    undo each other."""
    from translucency_addon.diffusion import compiled_cg, sweeps

    if compiled_cg.available():
        pytest.skip(f"the compiled kernels cannot run here: {compiled_cg.available()}")
    from bakes import baked
    from translucency_addon.diffusion.solver import DiffusionSolver

    system = DiffusionSolver(baked("sphere", "draft"), material_from_preset("marble")).systems[-1]  # RCM-ordered
    op = system.sweep_operator(np.float64)
    v = np.random.default_rng(2).normal(size=(system.n, 3))
    monkeypatch.setattr(sweeps, "COMPILED_PERM_MIN_NODES", 0)
    assert op._perm_compiled()
    cm, back = op.to_cm(v, dtype), op.from_cm(op.to_cm(v, dtype))
    wide = op.to_cm(v[:, :2].copy())  # two channels, the operator's own precision
    monkeypatch.setattr(sweeps, "COMPILED_PERM_MIN_NODES", 10**12)
    assert not op._perm_compiled()
    assert cm.dtype == dtype and cm.flags.c_contiguous
    np.testing.assert_array_equal(cm, op.to_cm(v, dtype))
    np.testing.assert_array_equal(back, op.from_cm(op.to_cm(v, dtype)))
    np.testing.assert_array_equal(wide, op.to_cm(v[:, :2].copy()))
    if dtype is np.float64:
        np.testing.assert_array_equal(back, v)
    assert not np.array_equal(op.perm, np.arange(system.n))  # a real reordering was checked
