# SPDX-License-Identifier: GPL-3.0-or-later
"""Fuzz the fluid, deformation and split passes (issue 35) with the bounds of their hard cases.

Hypothesis, derandomised (the same examples every run), shrinking off (a failure prints its example as
drawn), a few seconds per test.  Each example either keeps every bound of its pass's hard cases
(``passes_fluid.frame_bounds``, ``passes_deformation.solve_bounds``, ``passes_split.table_bounds`` and
``solve_bounds``) or is refused with a ``TranslucencyError``; anything else (a crash, NaN, a broken bound)
fails.  Over:

* fluid: 2 .. 60 particles, jittered lattice blocks or random clouds, scaled over 1e-6 .. 1e6 units, a
  radius 0.3 .. 6 spacings, optional coincident copies and NaN positions;
* deformation: the bar under a random affine map (scales 0.2 .. 4 per axis, a shear, a rotation, a
  translation up to 1e4), then a bend or twist of -170 .. 170 degrees;
* split: every albedo (log-close to 0 and 1 too) at eta 1 and 1.3 for the tables; the split solve on
  the icosphere with random per-channel albedo, eta from the few built (the tables take seconds per eta).
"""

from __future__ import annotations

import numpy as np
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st

from translucency_addon.geometry import primitives
from translucency_addon.errors import TranslucencyError

from . import passes_deformation as pd
from . import passes_fluid as pf
from . import passes_split as ps

FUZZ = dict(deadline=None, derandomize=True, print_blob=True, phases=[Phase.explicit, Phase.generate],
            suppress_health_check=list(HealthCheck))


def broken(bounds):
    return [b.describe() for b in bounds if not b.ok]


def log_uniform(lo, hi):
    return st.floats(np.log10(lo), np.log10(hi)).map(lambda e: float(10.0**e))


@settings(max_examples=40, **FUZZ)
@given(n=st.integers(2, 60), block=st.booleans(), scale=log_uniform(1e-6, 1e6), radius=st.floats(0.3, 6.0),
       copies=st.integers(0, 3), nans=st.integers(0, 2), seed=st.integers(0, 2**16))
def test_fluid_frames_stay_bounded(n, block, scale, radius, copies, nans, seed):
    rng = np.random.default_rng(seed)
    if block:
        k = max(2, int(round(n ** (1 / 3))))
        P = np.stack(np.meshgrid(*[np.arange(k)] * 3, indexing="ij"), axis=-1).reshape(-1, 3).astype(float)
        P += rng.uniform(-0.2, 0.2, P.shape)
    else:
        P = rng.uniform(0.0, n ** (1 / 3), (n, 3))
    if copies:
        P = np.vstack([P, np.repeat(P[:copies], 5, axis=0)])
    P[:nans] = np.nan
    try:
        res = pf.solve(P * scale, radius=radius * scale, mm_per_unit=1.0 / scale)
    except TranslucencyError:
        return
    assert not broken(pf.frame_bounds(res)), broken(pf.frame_bounds(res))


@settings(max_examples=25, **FUZZ)
@given(scales=st.tuples(*[st.floats(0.2, 4.0)] * 3), shear=st.floats(-1.0, 1.0), turn=st.floats(-180.0, 180.0),
       shift=st.tuples(*[st.floats(-1e4, 1e4)] * 3), kind=st.sampled_from(["bend", "twist", "none"]),
       degrees=st.floats(-170.0, 170.0), blend=st.floats(0.1, 1.5))
def test_deformed_poses_stay_bounded_or_are_refused(scales, shear, turn, shift, kind, degrees, blend):
    V = pd.bar()[0]
    if kind == "bend":
        V = primitives.bend(V, degrees, blend=blend, preserve_volume=False)
    elif kind == "twist":
        V = primitives.twist(V, degrees, along=0)
    t = np.radians(turn)
    R = np.array([[np.cos(t), -np.sin(t), 0.0], [np.sin(t), np.cos(t), 0.0], [0.0, 0.0, 1.0]])
    A = R @ np.array([[1.0, shear, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]) @ np.diag(scales)
    try:
        pose = pd.rig().deform(V @ A.T + np.array(shift))
    except TranslucencyError:
        return
    assert pose.report.valid
    solver, res = pd.solve(pose.bake)
    assert not broken(pd.solve_bounds(solver, res)), broken(pd.solve_bounds(solver, res))


@settings(max_examples=60, **FUZZ)
@given(alpha=st.lists(st.one_of(st.floats(0.0, 1.0), log_uniform(1e-12, 1.0).map(lambda g: 1.0 - g),
                                log_uniform(1e-12, 1.0)), min_size=1, max_size=8),
       eta=st.sampled_from([1.0, 1.3]))  # tables take 5-15 s per eta here; passes_split covers 1.0001, 2.5
def test_split_tables_stay_bounded(alpha, eta):
    assert not broken(ps.table_bounds(ps.half_space_split(eta), alpha))


@settings(max_examples=15, **FUZZ)
@given(alpha=st.tuples(*[st.one_of(st.floats(0.0, 1.0), log_uniform(1e-9, 1.0).map(lambda g: 1.0 - g))] * 3),
       sigma_t=log_uniform(1e-2, 1e2), eta=st.sampled_from([1.3]),
       single=st.tuples(st.booleans(), st.booleans(), st.booleans()), sun=st.booleans())
def test_split_solves_stay_bounded(alpha, sigma_t, eta, single, sun):
    try:
        solver, res, L = ps.split_solve(ps.material(alpha, eta, sigma_t), lights=ps.SUN if sun else (),
                                        single=single)
    except TranslucencyError:
        return
    assert not broken(ps.solve_bounds(solver, res, L)), broken(ps.solve_bounds(solver, res, L))
