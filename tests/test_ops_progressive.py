# SPDX-License-Identifier: GPL-3.0-or-later
"""Progressive viewport frames (issue 33, item 1): a light move shows the solve so far within the frame budget
and refines on later checks to the blocking solve's radiance; renders and background checks always converge.

Background Blender has no event loop, so the refine timer never fires: the tests run its body,
``live.check_now(progressive=True)``, until no object refines.  The engine's steps are tested against the
blocking solve in ``tests/test_progressive.py``.
"""

from __future__ import annotations

import bpy
import numpy as np
import pytest

from test_ops_bake import add_light, bake, cache_dir, memo_bakes, radiance, sphere  # noqa: F401


@pytest.fixture
def lit_ball(blender, addon, cache_dir, memo_bakes):  # noqa: F811 - pytest fixtures by name
    """A baked ball solved on the CPU for a point light on its +x side; returns (obj, light, ops.live, ops.state).
    (With a GPU context the Auto backend solves on the GPU, which converges in one step: its own test.)"""
    from translucency.ops import live, state

    bpy.context.scene.translucency.solver_backend = 'CPU'
    obj = sphere(subdivisions=3)
    light = add_light(location=(3.0, 0.0, 1.0))
    assert bake(obj) == {'FINISHED'}
    bpy.context.view_layer.update()
    live.flush()
    return obj, light, live, state


def _refine(live, limit=2000):
    """Run progressive checks until no object refines: [reports of each check]."""
    steps = []
    for _ in range(limit):
        reports = live.check_now(progressive=True)
        steps.append(reports)
        if not any(r.refining for r in reports):
            return steps
    raise AssertionError(f"still refining after {limit} steps")


def test_a_light_move_refines_to_the_blocking_solve(lit_ball, monkeypatch):
    """Blocking: move the light to -x and back.  Progressive, with a 1 ms budget: the same move shows the
    solution so far at once (brighter on the lit side already, the report and the status bar say it
    refines, a refine step is scheduled), then converges over later checks to the blocking radiance.

    A slice normally also runs 4x as long as showing the last image took (``progressive.SLICE_OVER_DISPLAY``):
    a timing policy, off here, so that the number of checks does not depend on the machine's load (under
    a loaded CI the slices grew until the ball converged in two checks)."""
    from translucency.translucency_addon import progressive

    monkeypatch.setattr(progressive, "SLICE_OVER_DISPLAY", 0.0)
    obj, light, live, state = lit_ball
    x = np.array([v.co.x for v in obj.data.vertices])
    start = radiance(obj)
    light.location = (-3.0, 0.0, 1.0)
    bpy.context.view_layer.update()
    live.flush()  # background mode: converged
    blocking = radiance(obj)
    light.location = (3.0, 0.0, 1.0)
    bpy.context.view_layer.update()
    live.flush()
    assert np.abs(radiance(obj) - start).max() < 1e-3 * start.max()

    bpy.context.scene.translucency.frame_budget_ms = 1.0
    light.location = (-3.0, 0.0, 1.0)
    bpy.context.view_layer.update()
    solves = state.counters()["solves"]
    first = live.check_now(progressive=True)
    assert [r.name for r in first] == ["Blob"] and first[0].refining, first
    assert "refining" in first[0].describe()
    assert live.refining()
    shown = radiance(obj)
    assert shown[x < -0.5].mean() > 2 * start[x < -0.5].mean()  # the move shows at once
    assert state.counters()["solves"] == solves  # a solution so far is not a solve
    steps = _refine(live)
    assert len(steps) >= 3, len(steps)
    last = steps[-1][0]  # the converged frame's report: a solve, timed over all its slices
    assert last.solved and not last.refining and last.seconds >= steps[-2][0].seconds >= first[0].seconds
    assert not live.refining()
    assert state.counters()["solves"] == solves + 1
    done = radiance(obj)
    assert np.abs(done - blocking).max() < 1e-3 * blocking.max(), np.abs(done - blocking).max() / blocking.max()
    assert live.check_now(progressive=True) == []  # converged and current: nothing to do


def test_a_new_move_mid_refinement_starts_from_the_solution_so_far(lit_ball):
    obj, light, live, state = lit_ball
    bpy.context.scene.translucency.frame_budget_ms = 1.0
    light.location = (-3.0, 0.0, 1.0)
    bpy.context.view_layer.update()
    assert live.check_now(progressive=True)[0].refining
    light.location = (0.0, 3.0, 1.0)
    bpy.context.view_layer.update()
    _refine(live)
    progressive = radiance(obj)
    live.check_now(progressive=False)
    assert np.abs(radiance(obj) - progressive).max() == 0.0  # converged: nothing left to do
    from translucency.ops import runtime

    runtime.solve_object(obj, force=True)  # a blocking solve of the same frame from the converged one
    assert np.abs(radiance(obj) - progressive).max() < 1e-3 * progressive.max()


def test_renders_and_background_checks_never_show_a_solution_so_far(lit_ball):
    """A render (no budget) while an object refines converges at once, and so does a background live check
    (``flush``: progressive only when asked); the Progressive setting off makes the viewport block too."""
    from translucency.ops import runtime

    obj, light, live, state = lit_ball
    scene = bpy.context.scene
    scene.translucency.frame_budget_ms = 1.0
    light.location = (-3.0, 0.0, 1.0)
    bpy.context.view_layer.update()
    assert live.check_now(progressive=True)[0].refining
    reports = runtime.solve_scene(scene)  # what renders and frame changes call: no budget
    assert reports and not reports[0].refining and reports[0].solved
    converged = radiance(obj)
    assert live.check_now(progressive=True) == []
    assert np.array_equal(radiance(obj), converged)

    assert live.budget(scene) is None  # background mode converges unless asked
    assert live.budget(scene, progressive=True) == pytest.approx(0.001)
    scene.translucency.progressive = False
    assert live.budget(scene, progressive=True) is None
    light.location = (0.0, -3.0, 1.0)
    bpy.context.view_layer.update()
    reports = live.check_now(progressive=True)
    assert reports and not reports[0].refining and reports[0].solved


@pytest.mark.gpu
def test_on_the_gpu_a_progressive_check_converges_at_once(lit_ball):
    """The GPU backend solves its levels itself and cannot hand out its iterates: a progressive check there
    converges in its one step, as a blocking one (the engine's side: tests/test_progressive.py)."""
    obj, light, live, state = lit_ball
    scene = bpy.context.scene
    scene.translucency.solver_backend = 'GPU'
    scene.translucency.frame_budget_ms = 1.0
    light.location = (-3.0, 0.0, 1.0)
    bpy.context.view_layer.update()
    reports = live.check_now(progressive=True)
    assert [r.name for r in reports] == ["Blob"] and reports[0].backend == "GPU", reports
    assert reports[0].solved and not reports[0].refining and not live.refining()
