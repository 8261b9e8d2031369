# SPDX-License-Identifier: GPL-3.0-or-later
"""Hard cases of the deformation pass (issue 35): ``DeformationRig.deform`` and ``DeformationFrames`` on poses
at and past the edge of what the baked graph can follow.

One Draft bake of a 4 x 1 x 1 bar (40 x 10 x 10 mm, two levels, ~1,500 nodes each; 2.5 s, once per process).
Every solved pose keeps, on every level, from the shared solver's own bookkeeping (``power_balance``):
finite radiance >= 0, the maximum principle ``max phi / max 4q/(1-F_dr) <= 1 + EPS``, out / in power
``<= 1 + EPS`` and the balance ``|in - out - absorbed| / in <= EPS`` (EPS = 1e-3, as cases.py's MP_EPS and
ENERGY_EPS, solved to a relative residual of 1e-6).  A pose the graph cannot follow must raise
``GraphFolded`` / ``DeformationError`` naming what broke with its numbers, and change nothing.

The deformed graph is solved by the one DiffusionSolver, whose GPU path is judged by the diffusion cases
(test_hard_cases.py, Blender's gpu module); no GPU = CPU bound is repeated here.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from translucency_addon.geometry import primitives
from translucency_addon.quadgraph.bake import BakeSettings, bake_mesh
from translucency_addon.deformation.pose import FOLD_VOLUME, STRETCH_LIMIT, DeformationRig
from translucency_addon.deformation.frames import DeformationFrames, pose_solver
from translucency_addon.diffusion.solver import SolveOptions
from translucency_addon.errors import GraphFolded
from translucency_addon.scene.lights import Environment, Light
from translucency_addon.scene.materials import material_from_preset

from .passes import Bound, Outcome, PassCase, finite_nonnegative

EPS = 1e-3
TOL = 1e-6
MPU = 10.0
MARBLE = material_from_preset("marble")
SUN_DIR = np.array([0.3, -1.0, -0.5])
ENV = Environment((0.5, 0.5, 0.5))


def sun(direction=SUN_DIR):
    return [Light("sun", irradiance=500.0, direction=tuple(float(x) for x in direction))]


@lru_cache(maxsize=1)
def bar():
    V, F = primitives.box((4.0, 1.0, 1.0), n=(8, 2, 2))
    bake = bake_mesh(V, F, BakeSettings(quality="draft", levels=2, refinements=0, base_triangles=400, mm_per_unit=MPU))
    return V, F, bake


@lru_cache(maxsize=4)
def rig(stretch_limit=STRETCH_LIMIT):
    return DeformationRig(bar()[2], stretch_limit)


def solve(bake, lights=None, environment=ENV):
    solver = pose_solver_for(bake)
    result = solver.solve(sun() if lights is None else lights, environment)
    return solver, result


def pose_solver_for(bake):
    from translucency_addon.diffusion.solver import DiffusionSolver

    return DiffusionSolver(bake, MARBLE, options=SolveOptions(tol=TOL))


def solve_bounds(solver, result, radiance=None, label="") -> list[Bound]:
    """The maximum principle, out <= in and the balance on every level; the radiance finite and >= 0."""
    L = solver.vertex_radiance(result) if radiance is None else radiance
    mp = ratio = balance = low = 0.0
    for i in range(len(solver.bake.levels)):
        phi, q = result.phi[i], result.q[i]
        if phi is None or q is None:
            continue
        g = solver.phi_bound(result, i)  # max 4q/(1 - F_dr), or the lamps' volume source's bound
        gg = np.where(g > 0, g, np.inf)
        mp = max(mp, float((phi.max(axis=0) / gg).max()))
        low = max(low, float(-(phi.min(axis=0) / gg).min()))  # phi >= 0 to a relative EPS, as cases.py
        pb = solver.power_balance(result, level=i)
        raw = solver.power_balance(result, level=i, clamp=False)
        p_in = np.where(pb["in"] > 0, pb["in"], np.inf)
        ratio = max(ratio, float((pb["out"] / p_in).max()))
        balance = max(balance, float((np.abs(raw["in"] - raw["out"] - raw["absorbed"]) / p_in).max()))
    return ([Bound(f"{label}out / in power", ratio, 1.0 + EPS), Bound(f"{label}max phi / max 4q/(1-F_dr)", mp, 1.0 + EPS),
             Bound(f"{label}|in - out - absorbed| / in", balance, EPS)]
            + finite_nonnegative(f"{label}radiance", L)
            + [finite_nonnegative(f"{label}phi", p)[0] for p in result.phi if p is not None]
            + [Bound(f"{label}-min phi / max 4q/(1-F_dr)", low, EPS)])


def rel_diff(a, b) -> float:
    return float(np.abs(np.asarray(a) - b).max() / max(np.abs(b).max(), 1e-300))


def stretch_x(V, s):
    return V * np.array([s, 1.0, 1.0])


# -- cases --------------------------------------------------------------------------------------------
def _edge(lo, hi, refused, steps=60):
    """Bisect a pose parameter between an accepted ``lo`` and a refused ``hi`` to within 1e-9 relative."""
    assert not refused(lo) and refused(hi)
    for _ in range(steps):
        mid = 0.5 * (lo + hi)
        lo, hi = (lo, mid) if refused(mid) else (mid, hi)
        if hi - lo <= 1e-9 * hi:
            break
    return lo, hi


def stretch_edge():
    """The bar stretched along x by s, s bisected to the stretch check's edge (worst link just under 3x):
    the pose just inside solves within every bound; the pose 1e-9 further is refused by name."""
    V = bar()[0]
    r = rig()

    def refused(s):
        return not r.deform(stretch_x(V, s), refuse_folds=False).report.valid

    lo, hi = _edge(1.0, 4.0, refused)
    pose = r.deform(stretch_x(V, lo))
    rep = pose.report
    solver, result = solve(pose.bake)
    inside = Bound("worst stretch at the edge, from the limit (1 - w / 3)", 1.0 - rep.worst_stretch / STRETCH_LIMIT, 1e-6)
    try:
        r.deform(stretch_x(V, hi))
        refusal = 1.0
    except GraphFolded as ex:
        refusal = 0.0 if "overstretches" in str(ex) and "limit 3x" in str(ex) else 1.0
    return Outcome([inside, Bound("pose 1e-9 past the edge not refused by name", refusal, 0.0)]
                   + solve_bounds(solver, result), f"s = {lo:.9f}, worst link {rep.worst_stretch:.9f}x")


def fold_edge():
    """The bar bent at a narrow joint (linear skinning, which pinches it), the angle bisected to the fold
    check's edge (stretch check lifted: a rig with limit 1e6): just inside, the inverted slivers are
    repaired and the pose solves within every bound; 1e-9 further it is refused as a fold."""
    V = bar()[0]
    r = rig(1e6)

    def pose(a):
        return primitives.bend(V, a, blend=0.2, preserve_volume=False)

    def refused(a):
        return r.deform(pose(a), refuse_folds=False).report.folded

    lo, hi = _edge(0.0, 170.0, refused)
    p = r.deform(pose(lo))
    rep = p.report
    solver, result = solve(p.bake)
    vol = Bound("inverted volume just inside the edge / FOLD_VOLUME", rep.inverted_volume / FOLD_VOLUME, 1.0)
    try:
        r.deform(pose(hi))
        refusal = 1.0
    except GraphFolded as ex:
        refusal = 0.0 if "folds the baked graph" in str(ex) and "tets inverted" in str(ex) else 1.0
    return Outcome([vol, Bound("pose 1e-9 past the edge not refused as a fold", refusal, 0.0)]
                   + solve_bounds(solver, result),
                   f"bend {lo:.6f} deg: {rep.inverted_tets} slivers ({100 * rep.inverted_volume:.2g} % of the volume), "
                   f"{rep.inverted_links} links turned")


def rigid_motion_1e4():
    """The bar turned by 40 degrees about a skew axis and moved 1e4 units (10 m at 10 mm per unit), the sun
    turned with it: the same radiance as at rest (the harmonic field is exact on affine maps; measured
    ~1e-9, from rounding at 1e4 units; limit 100 x the solve's tolerance)."""
    V, F, bake = bar()
    ax = np.array([1.0, 2.0, 3.0]) / np.sqrt(14.0)
    t = np.radians(40.0)
    K = np.array([[0, -ax[2], ax[1]], [ax[2], 0, -ax[0]], [-ax[1], ax[0], 0]])
    R = np.eye(3) + np.sin(t) * K + (1 - np.cos(t)) * K @ K
    pose = rig().deform(V @ R.T + np.array([1e4, -1e4, 1e4]))
    s0, r0 = solve(bake)
    s1, r1 = solve(pose.bake, sun(R @ SUN_DIR))
    L0, L1 = s0.vertex_radiance(r0), s1.vertex_radiance(r1)
    return Outcome([Bound("rel. diff. from the rest pose", rel_diff(L1, L0), 100 * TOL),
                    Bound("worst stretch - 1", pose.report.worst_stretch - 1.0, 1e-6)] + solve_bounds(s1, r1),
                   f"{pose.report.inverted_tets} inverted")


def flattened():
    """Every vertex onto the plane z = 0: every tet of zero volume -- refused as a fold, with its numbers."""
    rig().deform(bar()[0] * np.array([1.0, 1.0, 0.0]))
    return Outcome([], "solved a flattened bar")


def half_flattened():
    """The part of the bar beyond x = 0.5 squashed onto the plane x = 0.5 (a bone scaled to zero along x):
    its tets have zero volume -- refused as a fold."""
    V = bar()[0].copy()
    V[V[:, 0] > 0.5, 0] = 0.5
    rig().deform(V)
    return Outcome([], "solved a half-flattened bar")


def collapsed_to_a_point():
    rig().deform(0.0 * bar()[0] + 1.0)
    return Outcome([], "solved a bar collapsed to a point")


def alternating_frames():
    """Six frames: a growing bend (valid), then a pinched fold (refused), in turn.  Each refusal names the
    frame and leaves the last valid frame in place; each valid frame, warm-started from the last valid one,
    keeps every bound and equals a cold solve of its pose (measured ~1e-7; limit 100 x the tolerance)."""
    V = bar()[0]
    frames = DeformationFrames(bar()[2], MARBLE, rig=rig(), options=SolveOptions(tol=TOL))
    bounds, worst, refused_right, kept = [], 0.0, 0, 0
    for k in range(6):
        if k % 2 == 0:
            out = frames.solve(primitives.bend(V, 10.0 + 5.0 * k, blend=1.0), sun(), ENV, frame=k, interreflect=False)
            cold = pose_solver(out.pose, MARBLE, options=SolveOptions(tol=TOL))
            cres = cold.solve(sun(), ENV)
            worst = max(worst, rel_diff(out.radiance, cold.vertex_radiance(cres)))
            bounds += solve_bounds(out.solver, out.result, out.radiance, f"frame {k}: ")
        else:
            before = frames.last
            try:
                frames.solve(primitives.bend(V, 150.0, blend=0.2, preserve_volume=False), sun(), ENV, frame=k,
                             interreflect=False)
            except GraphFolded as ex:
                refused_right += int(f"at frame {k}" in str(ex) and "folds the baked graph" in str(ex))
            kept += int(frames.last is before)
    return Outcome([Bound("rel. diff. warm vs cold", worst, 100 * TOL),
                    Bound("refused frames not refused by name (of 3)", 3.0 - refused_right, 0.0),
                    Bound("refused frames that changed the last valid one (of 3)", 3.0 - kept, 0.0)] + bounds,
                   "3 valid, 3 refused")


def _case(name, run, refusal=None):
    return PassCase(f"deformation/{name}", "deformation", run, refusal)


CASES = [
    _case("stretch at the edge", stretch_edge),
    _case("fold at the edge", fold_edge),
    _case("rigid motion of 1e4 units", rigid_motion_1e4),
    _case("zero-volume tets: flattened", flattened,
          r"folds the baked graph: \d+ tets inverted \(1e\+02 % of the volume\).*re-bake in this pose or at rest"),
    _case("zero-volume tets: half flattened", half_flattened,
          r"folds the baked graph: \d+ tets inverted \(\d+ % of the volume\), \d+ links turned inside out"),
    _case("collapsed to a point", collapsed_to_a_point, r"collapses the object to a point \(bounding box 0 against 4\.2"),
    _case("alternating valid and refused frames", alternating_frames),
]
