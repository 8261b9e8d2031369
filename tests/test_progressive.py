"""Progressive frames in the engine (issue 33, item 1): ``DiffusionSolver.solve_steps``, ``frame.diffuse_steps``
and ``progressive.ProgressiveSolve`` against the blocking solve of the same frame.

Run to its end a stepped solve is the blocking solve, bit for bit (the same Chebyshev arithmetic, whether or
not anyone looked at the iterates); the solutions so far approach it; a slice always makes progress.
"""

from __future__ import annotations

import numpy as np
import pytest

from translucency_addon import frame as frame_mod
from translucency_addon.diffusion import solver as diffusion
from translucency_addon.diffusion.iterative import drain
from translucency_addon.geometry import primitives
from translucency_addon.progressive import ProgressiveSolve
from translucency_addon.quadgraph import bake as bake_mod
from translucency_addon.scene import lights, materials

SUN = [lights.Light("sun", irradiance=1000.0, direction=(0.3, -0.2, -1.0))]
ENV = lights.Environment((0.2, 0.3, 0.4))


@pytest.fixture(scope="module")
def baked():
    V, F = primitives.icosphere(1.0, 3)
    return bake_mod.bake_mesh(V, F, bake_mod.BakeSettings(quality="draft", levels=3, base_triangles=120,
                                                          mm_per_unit=10.0, sky_directions=16))


def _steps(solver, **kw):
    """(every solution so far, the final result) of one stepped solve."""
    g = solver.solve_steps(SUN, ENV, **kw)
    partials = []
    while True:
        try:
            get = next(g)
        except StopIteration as stop:
            return partials, stop.value
        partials.append(get())


@pytest.mark.parametrize("bounced, single", [(False, None), (False, (True, True, True)), (True, None),
                                             (True, (True, False, True))])
def test_steps_run_to_the_end_are_the_blocking_solve(baked, bounced, single):
    solver = diffusion.DiffusionSolver(baked, materials.material_from_preset("marble"))
    ref = solver.solve(SUN, ENV, bounced=bounced, single=single)
    partials, res = _steps(solver, bounced=bounced, single=single)
    assert len(partials) >= 5
    for a, b in zip(ref.phi, res.phi):
        assert (a is None and b is None) or np.array_equal(a, b)
    L = solver.vertex_radiance(ref)
    assert np.array_equal(solver.vertex_radiance(res), L)
    # The solutions so far: finite, from the coarse levels carried up to the finest, approaching the answer.
    errs = []
    for p in partials:
        assert p.phi[-1].shape == ref.phi[-1].shape and np.all(np.isfinite(p.phi[-1]))
        errs.append(float(np.abs(solver.vertex_radiance(p) - L).max() / np.abs(L).max()))
    assert errs[-1] < 0.01 and errs[-1] < 0.1 * errs[0], errs


def test_a_warm_started_step_solves_only_the_finest_level(baked):
    solver = diffusion.DiffusionSolver(baked, materials.material_from_preset("skin1"))
    first = solver.solve(SUN, ENV)
    moved = [lights.Light("sun", irradiance=1000.0, direction=(-0.3, 0.4, -1.0))]
    ref = solver.solve(moved, ENV, warm_start=first)
    g = solver.solve_steps(moved, ENV, warm_start=first)
    partials = []
    res = drain(_collect(g, partials))
    assert np.array_equal(res.phi[-1], ref.phi[-1]) and len(res.level_solves) == 1
    assert partials and all(p.phi[:-1] == [None] * (len(baked.levels) - 1) for p in partials)


def _collect(g, out):
    while True:
        try:
            get = next(g)
        except StopIteration as stop:
            return stop.value
        out.append(get())
        yield get


def test_progressive_solve_slices_converge_to_diffuse(baked):
    """``ProgressiveSolve`` over ``frame.diffuse_steps``: with no budget each slice stops at the first check
    (it always makes progress), the last slice hands back ``frame.diffuse``'s own tuple."""
    solver = diffusion.DiffusionSolver(baked, materials.material_from_preset("marble"))
    passes = frame_mod.FramePasses(True, False, False, (True, True, True), (True, True, True))
    ref, ref_bounce, _ = frame_mod.diffuse(solver, baked, SUN, ENV, passes, tol=1e-4)
    job = ProgressiveSolve(frame_mod.diffuse_steps(solver, baked, SUN, ENV, passes, tol=1e-4), key="a")
    assert job.continues("a") and not job.continues("b")
    slices = 0
    while True:
        out, done = job.advance(0.0)
        slices += 1
        if done:
            break
        assert out is job.latest and not job.done
    result, bounce, cavity = out
    assert slices > 5 and job.done and not job.continues("a") and cavity is None
    assert np.array_equal(result.phi[-1], ref.phi[-1]) and np.array_equal(bounce, ref_bounce)


def test_a_backend_that_solves_its_own_levels_converges_in_one_slice(baked):
    """The GPU backend replaces ``solve_systems`` and cannot hand out its iterates: one slice, converged
    (a stand-in subclass here; the GPU's own parity tests are in test_gpu_solver.py)."""

    class OwnLevels(diffusion.DiffusionSolver):
        def solve_systems(self, q, active, warm_start=None, cols=(0, 1, 2)):
            return super().solve_systems(q, active, warm_start, cols)

    solver = OwnLevels(baked, materials.material_from_preset("marble"), options=diffusion.SolveOptions(
        sky_occlusion=False))
    passes = frame_mod.FramePasses(True, False, False, (True, True, True))
    job = ProgressiveSolve(frame_mod.diffuse_steps(solver, baked, SUN, ENV, passes, tol=1e-4), key=1)
    (result, _bounce, _cavity), done = job.advance(0.0)
    assert done and job.slices == 1
    ref = diffusion.DiffusionSolver(baked, materials.material_from_preset("marble"), options=diffusion.SolveOptions(
        sky_occlusion=False)).solve(SUN, ENV)
    assert np.array_equal(result.phi[-1], ref.phi[-1])


@pytest.mark.parametrize("bounce", [False, True])
def test_the_first_slice_after_a_light_move_shows_the_start_before_any_sweep(baked, bounce):
    """Issue 33, item 1: the first slice ends at the first image, the solve's start with this frame's light
    -- the last frame's solution, before the iteration's set-up (at Final the bounce's fp64 true residual,
    ~0.1 s, measured in docs/bench_progressive.md) -- whatever the budget; the next slices converge to the
    blocking frame bit for bit.  Without the start's image the first slice would run sweeps (its phi would
    not be the last frame's)."""
    solver = diffusion.DiffusionSolver(baked, materials.material_from_preset("marble"))
    passes = frame_mod.FramePasses(True, False, False, (True, True, True), (bounce,) * 3)
    start, _, _ = frame_mod.diffuse(solver, baked, SUN, ENV, passes, tol=1e-4)
    moved = [lights.Light("sun", irradiance=1000.0, direction=(-0.3, 0.4, -1.0))]
    ref, _, _ = frame_mod.diffuse(solver, baked, moved, ENV, passes, tol=1e-4, warm_start=start)
    job = ProgressiveSolve(frame_mod.diffuse_steps(solver, baked, moved, ENV, passes, tol=1e-4, warm_start=start),
                           key=0)
    first, done = job.advance(10.0)
    assert not done and job.slices == 1
    assert np.array_equal(first.phi[-1], start.phi[-1])  # no sweep yet: the last frame's solution
    assert not np.allclose(solver.vertex_radiance(first), solver.vertex_radiance(start))  # with the new light
    while not done:
        out, done = job.advance(0.0)
    assert np.array_equal(out[0].phi[-1], ref.phi[-1])


def test_a_solve_restarted_mid_drag_sweeps_in_its_first_slice(baked):
    """A caller that restarts from an unfinished solve's solution so far (ops.runtime, a light being dragged)
    passes ``show_start=False``: the first slice then sweeps, so a drag's redraws refine the image instead of
    showing the same start again."""
    solver = diffusion.DiffusionSolver(baked, materials.material_from_preset("marble"))
    passes = frame_mod.FramePasses(True, False, False, (True, True, True))
    start, _, _ = frame_mod.diffuse(solver, baked, SUN, ENV, passes, tol=1e-4)
    moved = [lights.Light("sun", irradiance=1000.0, direction=(-0.3, 0.4, -1.0))]
    job = ProgressiveSolve(frame_mod.diffuse_steps(solver, baked, moved, ENV, passes, tol=1e-4, warm_start=start),
                           key=0, show_start=False)
    first, done = job.advance(0.0)
    assert not done and not np.array_equal(first.phi[-1], start.phi[-1])
