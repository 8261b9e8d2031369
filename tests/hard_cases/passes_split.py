# SPDX-License-Identifier: GPL-3.0-or-later
"""Hard cases of the first-scatter split (issue 35): ``half_space_split`` tables and the split solve.

Two levels are held to their bounds:

* the half-space tables (``HalfSpaceSplit``): s (single), M (multiple), B (boundary diffusion) and the
  source factor m finite and in [0, 1]; s + M <= 1 (a half-space never returns more than entered; 1e-9
  for the tables' interpolation rounding) and s + m <= 1 (the diffusion's source never exceeds what did
  not leave by single scattering);
* the split solve on a graph (``DiffusionSolver`` with ``single=``; the stored fuzz icosphere, ~1,800
  nodes, at 20 mm): radiance finite and >= 0, the maximum principle on the diffusion's own source, and
  ``(out + single) / incident <= 1 + EPS`` per channel (``power_balance``'s ``incident`` and ``single``:
  the closed-form term plus what the diffusion sends out never exceeds the light that entered;
  EPS = 1e-3 as cases.py's ENERGY_EPS, solved to a relative residual of 1e-6).

The split's GPU path (gpu_shaders) is compared with the CPU in test_hard_cases.py's split test under
Blender's gpu module; no GPU = CPU bound is repeated here (this suite runs without Blender).
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from translucency_addon.diffusion.solver import DiffusionSolver, SolveOptions
from translucency_addon.scene.lights import Environment, Light
from translucency_addon.scene.materials import Material, Medium
from translucency_addon.planner import ALBEDO_MIN, plan_object
from translucency_addon.diffusion.split import HalfSpaceSplit, half_space_split  # noqa: F401

from .passes import Bound, Outcome, PassCase, finite_nonnegative

EPS = 1e-3
TOL = 1e-6
MPU = 10.0  # the unit icosphere at 10 mm per unit: a 20 mm ball
SUN = [Light("sun", irradiance=300.0, direction=(0.3, -0.5, -0.8))]
ENV = Environment((0.5, 0.5, 0.5))
ALPHAS = np.concatenate([np.linspace(0.0, 1.0, 201), 1.0 - np.logspace(-12, -1, 45)])


@lru_cache(maxsize=1)
def sphere():
    from .test_fuzz import small_bake

    return small_bake().with_scale(MPU)


def material(alpha, eta=1.3, sigma_t=1.0):
    """A homogeneous medium of reduced albedo ``alpha`` (per channel, or one for all) and sigma_t' 1/mm."""
    a = np.broadcast_to(np.asarray(alpha, dtype=np.float64), (3,))
    ss = tuple(float(x) for x in sigma_t * a)
    sa = tuple(float(x) for x in sigma_t * (1.0 - a))
    return Material(Medium(sa, ss, "hard"), None, eta)


def table_bounds(split: HalfSpaceSplit, alpha, label="") -> list[Bound]:
    a = np.asarray(alpha, dtype=np.float64)
    s, M, B, m = (split.single_escape(a), split.multiple_escape(a), split.boundary_escape(a),
                  split.source_factor(a))
    out = [Bound(f"{label}s + M", float(np.max(s + M)), 1.0 + 1e-9),
           Bound(f"{label}s + m", float(np.max(s + m)), 1.0 + 1e-12)]
    for name, t in (("s", s), ("M", M), ("B", B), ("m", m)):
        out += finite_nonnegative(f"{label}{name}", t) + [Bound(f"{label}max {name}", float(np.max(t)), 1.0)]
    tables = (split.s_table, split.M_table, split.B_table, split.m_table, split.shape_table)
    out.append(Bound(f"{label}NaN/Inf table entries", float(sum(np.count_nonzero(~np.isfinite(t)) for t in tables)), 0))
    return out


def split_solve(mat, lights=SUN, environment=ENV, single=(True, True, True), view_dirs=None):
    solver = DiffusionSolver(sphere(), mat, options=SolveOptions(tol=TOL))
    res = solver.solve(lights, environment, single=single)
    return solver, res, solver.vertex_radiance(res, view_dirs)


def solve_bounds(solver, res, L, label="") -> list[Bound]:
    """(out + single) / incident, the maximum principle on the diffusion's source, finite and >= 0."""
    pb = solver.power_balance(res)
    if "incident" not in pb:  # no channel split (the planner's choice or the caller's): diffusion alone
        pb.update(incident=pb["in"], single=np.zeros(3))
    inc = np.where(pb["incident"] > 0, pb["incident"], np.inf)
    ratio = float(((pb["out"] + pb["single"]) / inc).max())
    phi = res.phi[-1]
    g = solver.phi_bound(res)  # max 4q/(1 - F_dr), or the lamps' volume source's bound
    gg = np.where(g > 0, g, np.inf)
    mp = float((phi.max(axis=0) / gg).max())
    # phi >= 0 as cases.py holds it: an iterate stopped at the tolerance may dip below 0 by a relative MP_EPS
    low = float(max(-(phi.min(axis=0) / gg).min(), 0.0))
    return ([Bound(f"{label}(out + single) / incident", ratio, 1.0 + EPS),
             Bound(f"{label}max phi / max 4q/(1-F_dr)", mp, 1.0 + EPS)]
            + finite_nonnegative(f"{label}radiance", L) + finite_nonnegative(f"{label}phi", phi)[:1]
            + [Bound(f"{label}-min phi / max 4q/(1-F_dr)", low, EPS)])


# -- cases --------------------------------------------------------------------------------------------
def near_white(gap):
    """Albedo 1 - gap: the tables keep their bounds, and a half-space absorbs almost nothing: 1 - (s + M)
    <= 10 sqrt(gap) (the loss of a nearly white half-space goes as sqrt(1 - alpha): measured 4.1 sqrt(gap) at
    both gaps)."""
    def run():
        split = half_space_split(1.3)
        a = 1.0 - gap
        lost = 1.0 - float(split.single_escape(a) + split.multiple_escape(a))
        solver, res, L = split_solve(material(a))
        return Outcome([Bound("1 - (s + M)", lost, 10.0 * np.sqrt(gap))] + solve_bounds(solver, res, L)
                       + table_bounds(split, [a]), f"alpha = 1 - {gap:g}")
    return run


def ior(eta):
    """The tables at eta over every albedo (0 .. 1 and 45 values up to 1 - 1e-12), and a split solve."""
    def run():
        split = half_space_split(eta)  # the solver's own (cached) tables: built once (6-17 s on 2 cores)
        solver, res, L = split_solve(material((0.99, 0.9, 0.6), eta=eta))
        extra = []
        if eta == 1.0001:  # continuous in eta: the tables of eta = 1 within 1e-3 (measured in the row)
            one = half_space_split(1.0)
            jump = max(float(np.max(np.abs(getattr(split, f)(ALPHAS) - getattr(one, f)(ALPHAS))))
                       for f in ("single_escape", "multiple_escape", "boundary_escape", "source_factor"))
            extra = [Bound("max |table(1.0001) - table(1.0)|", jump, 1e-3)]
        return Outcome(extra + solve_bounds(solver, res, L) + table_bounds(split, ALPHAS),
                       f"eta = {eta:g}, F_dr = {split.fdr:.4f}")
    return run


def grazing():
    """Grazing view and light: the closed form of eq. 2 at outside cosines 1 .. 1e-12, 0 and just below 0 is
    finite, >= 0, 0 at and below the horizon and falls to 0 as the view grazes (continuity: L(1e-12) <=
    1e-3 L(1)); the shape factor there finite; a split solve seen along the tangent at every vertex (a
    sun at 89.9 degrees from the z axis) keeps its bounds."""
    split = half_space_split(1.3)
    c = np.array([1.0, 0.5, 1e-3, 1e-6, 1e-12, 0.0, -1e-12, -1.0])
    Ls = split.single_radiance(np.ones((len(c), 3)), np.full((len(c), 3), 0.9), c)
    shape = split.multiple_shape(np.full((len(c), 3), 0.9), c)
    bake = sphere()
    n = np.asarray(bake.mesh_normals, dtype=np.float64)
    t = np.cross(n, [0.577, 0.577, 0.577])
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    sun = [Light("sun", irradiance=300.0, direction=(float(np.sin(np.radians(89.9))), 0.0,
                                                       float(-np.cos(np.radians(89.9)))))]
    solver, res, L = split_solve(material(0.95), lights=sun, environment=None, view_dirs=t)
    return Outcome([Bound("L_ss(1e-12) / L_ss(1)", float(Ls[4].max() / Ls[0].max()), 1e-3),
                    Bound("L_ss at and below the horizon", float(np.abs(Ls[5:]).max()), 0.0)]
                   + solve_bounds(solver, res, L) + finite_nonnegative("L_ss", Ls) + finite_nonnegative("shape", shape), "cos_o 1 .. -1; view along the tangents")


def planner_threshold():
    """Reduced albedo 0.5 -/+ 1e-6 (the planner's ALBEDO_MIN, where diffusion turns 'doubtful'): each side
    planned (no single-scattering bake: diffusion runs on both, with the split where the planner says) and
    solved; the relative jump of the mean radiance must be continuous: <= 1e-4.  The radiance changes with
    alpha' at d ln L / d alpha' of a few, so 2e-6 of alpha' moves it ~1e-5; a pass switched on one side only
    (diffusion dropped, the split turned off) moves it by tens of per cent."""
    means, bounds, passes = [], [], []
    for a in (ALBEDO_MIN - 1e-6, ALBEDO_MIN + 1e-6):
        mat = material(a)
        plan = plan_object(sphere(), mat, SUN, ENV, has_single_scattering=False)
        passes.append((plan.multiple.channels, plan.multiple.split))
        solver = DiffusionSolver(sphere(), mat, options=SolveOptions(tol=TOL))
        res = solver.solve(SUN, ENV, channels=plan.multiple.channels, single=plan.multiple.split)
        L = solver.vertex_radiance(res)
        bounds += solve_bounds(solver, res, L, f"alpha' {a:.6f}: ")
        means.append(L.mean(axis=0))
    jump = float((np.abs(means[1] - means[0]) / np.maximum(np.abs(means[0]), 1e-300)).max())
    return Outcome([Bound("rel. jump of the mean radiance across 0.5 -/+ 1e-6", jump, 1e-4)] + bounds,
                   f"passes below / above: {passes[0]} / {passes[1]}")


def _case(name, run, refusal=None):
    return PassCase(f"split/{name}", "split", run, refusal)


CASES = [
    _case("albedo 1 - 1e-9", near_white(1e-9)),
    _case("albedo 1 - 1e-6", near_white(1e-6)),
    _case("IOR 1.0", ior(1.0)),
    _case("IOR 1.0001", ior(1.0001)),
    _case("IOR 2.5", ior(2.5)),
    _case("grazing incidence", grazing),
    _case("planner threshold from both sides", planner_threshold),
]
