# SPDX-License-Identifier: GPL-3.0-or-later
"""Single and multiple scattering that add up (issue 17): the first-scatter split.

* the closed form (``diffusion/split.py``) against an independent Monte Carlo random walk of
  the same half-space (isotropic phase, Fresnel boundary at eta = 1.3, diffuse light): the single-scattering
  power to noise, and single + multiple no further from the walk's total than diffusion alone;
* per scene family, against the cached Mitsuba reference (``bench/data/reference``): every term on is never
  worse than diffusion alone, and counting the once-scattered light twice (the closed-form term added to
  the unsplit diffusion) is seen by the metric -- the test fails when the terms double-count;
* the solver's bookkeeping: the split leaves the light that entered in the result, the source it solves
  never grows, the power that leaves is at most the light that entered.
"""

from __future__ import annotations

import numpy as np
import pytest

from translucency_addon.scene.fresnel import fresnel_transmittance
from translucency_addon.diffusion.split import HalfSpaceSplit, half_space_split, inside_transmittance

ETA = 1.3


def random_walk(alpha: float, eta: float = ETA, n: int = 200_000, seed: int = 1, bins: int = 1, orders: int = 2,
                mu_in: float | None = None):
    """Power leaving a half-space per unit of the light that entered (diffuse light outside, refracted in),
    by scattering order: ``orders`` arrays, the last for that order and above (default: single, multiple).
    Isotropic scattering, unit sigma_t, Fresnel reflection at every boundary hit -- the reflected flight
    goes on for the rest of its sampled length and ends in a collision --, Russian roulette below 1e-3
    of the weight.  With ``bins`` > 1 each is an array over equal bins of mu_o^2 (the outside cosine
    squared: equal projected solid angle).  ``mu_in``: a collimated beam (a lamp) at that outside
    incidence cosine instead of diffuse light.

    (Until this was fixed the reflected flight drew a new free path instead of colliding at its end:
    one extra mean free path after every internal reflection, which made the walk's multiple scattering
    4-8 % low at eta = 1.3 and led the first version of this test to overstate diffusion's error there.)"""
    rng = np.random.default_rng(seed)
    mu0 = np.sqrt(rng.random(n)) if mu_in is None else np.full(n, float(mu_in))  # cosine-weighted, or a beam
    w = fresnel_transmittance(mu0, eta)
    w0 = w.sum()
    mu = np.sqrt(1.0 - (1.0 - mu0**2) / eta**2)  # inside, into the medium (+z)
    z = np.zeros(n)
    k = np.zeros(n, dtype=np.int64)
    alive = np.ones(n, dtype=bool)
    out = np.zeros((orders, bins))
    for _ in range(100_000):
        idx = np.flatnonzero(alive)
        if idx.size == 0:
            break
        zn = z[idx] + mu[idx] * -np.log(rng.random(idx.size))
        hit = zn < 0
        h = idx[hit]
        T = inside_transmittance(-mu[h], eta)
        leave = w[h] * T
        mu_o2 = np.clip(1.0 - eta**2 * (1.0 - mu[h] ** 2), 0.0, 1.0)
        b = np.minimum((mu_o2 * bins).astype(np.int64), bins - 1)
        np.add.at(out, (np.minimum(k[h], orders) - 1, b), leave)
        w[h] *= 1.0 - T
        zn[hit] = -zn[hit]  # reflected: the rest of the flight mirrored, ending in a collision
        z[idx] = zn
        w[idx] *= alpha
        k[idx] += 1
        mu[idx] = rng.uniform(-1.0, 1.0, idx.size)
        small = np.flatnonzero(alive & (w < 1e-3))
        survive = rng.random(small.size) < 0.1
        w[small[survive]] *= 10.0
        w[small[~survive]] = 0.0
        alive[small[~survive]] = False
    out /= w0
    return tuple(o[0] for o in out) if bins == 1 else tuple(out)


@pytest.mark.parametrize("eta, alpha", [(1.3, 0.68), (1.3, 0.96), (1.0, 0.84), (2.0, 0.84)])
def test_transport_solution_against_a_random_walk_order_by_order(eta, alpha):
    """half_space.py's solution of the half-space (eq. 1-2 there) against the walk, per scattering order:
    the first three orders and all the rest.  Measured (400k paths): every order within 1 % (the walk's
    noise: about 0.3 % for the first orders), where diffusion (closed_form eq. 3) is 6-10 % over the walk's
    multiple scattering at alpha 0.68-0.84."""
    from translucency_addon.diffusion.half_space import HalfSpaceTransport, depth_grid

    split = HalfSpaceSplit(eta)
    ht = HalfSpaceTransport(eta, lambda m: inside_transmittance(m, eta), depth_grid(h0=0.001, growth=1.04,
                                                                                     h_max=0.5, depth=100.0))
    phi = ht.uncollided(split.nu, split.p[:, None])
    ours = []
    for _ in range(3):
        ours.append(ht.exitance(alpha, phi)[0])
        phi = alpha * (ht.K @ phi)  # the fluence of the next order (eq. 1's Neumann series)
    ours.append(ht.exitance(alpha, ht.solve(alpha, phi) + phi)[0])  # order 4 and above
    walk = random_walk(alpha, eta, n=400_000, seed=3, orders=4)
    print(f"eta {eta} alpha {alpha}: walk {np.round(walk, 5)}, transport {np.round(ours, 5)}")
    np.testing.assert_allclose(ours, walk, rtol=0.02)
    assert sum(ours) == pytest.approx(sum(walk), rel=0.01)


@pytest.mark.parametrize("alpha", [0.68, 0.84, 0.96])  # skin1's B, G, R single-scattering albedo
def test_closed_form_against_a_random_walk(alpha):
    split = half_space_split(ETA)
    single, multiple = random_walk(alpha)
    s = float(split.single_escape(alpha))
    M = float(split.multiple_escape(alpha))
    M_diff = float(split._lookup(split.M_diffusion_table, alpha))  # eq. 3, looked up as M is
    B = float(split.boundary_escape(alpha))
    total = single + multiple
    print(f"alpha {alpha}: walk single {single:.4f} multiple {multiple:.4f} total {total:.4f}; "
          f"split {s:.4f} + {M:.4f} = {s + M:.4f} (with diffusion's M {s + M_diff:.4f}); diffusion alone {B:.4f}")
    assert s == pytest.approx(single, rel=0.02)  # exact for the half-space: only the walk's noise
    assert s + M == pytest.approx(total, rel=0.01)  # the transport solution: measured within 0.5 %
    if alpha <= 0.84:  # where diffusion's M is off by more than the walk's noise (at 0.96: +0.2 %)
        assert abs(s + M - total) < 0.5 * abs(s + M_diff - total)  # diffusion's M: +4.5 %, +3.0 %
    assert abs(s + M - total) < abs(B - total)  # diffusion alone: +2.4 %, +6.9 %, +3.8 %


@pytest.mark.parametrize("eta, alpha", [(1.0, 0.999), (1.0, 0.9), (1.3, 0.999), (1.3, 0.96), (1.3, 0.68)])
def test_directions_of_single_plus_multiple_against_a_random_walk(eta, alpha):
    """The directions in which the split's light leaves, against the random walk of the same half-space.

    Single scattering leaves mostly at grazing angles (eq. 1); an isotropic multiple-scattering term then
    makes the sum too dark head-on and too bright at the rim.  Compared: the radiance of single +
    multiple in 10 bins of mu_o^2 (the model averaged over each bin), RMS over the bins of the ratio to
    the walk's, minus 1.  Measured (200k paths): eta = 1, alpha = 0.999 (marble, index-matched):
    isotropic 3.9 %, eq. 4 0.6 %; alpha = 0.9: 2.2 % against 0.7 %; eta = 1.3, where Fresnel shapes both
    alike: 0.999 0.5 % against 0.5 %, 0.96 2.1 % against 1.1 %, 0.68 (skin1's blue) 2.6 % against 1.1 %.
    The walk's noise is about 1 % per bin at 200k paths: at 800k eq. 4's bins are within 1 % of the walk
    with no pattern."""
    from translucency_addon.diffusion.radiance import outgoing_radiance

    bins, sub = 10, 64
    split = HalfSpaceSplit(eta)
    single, multiple = random_walk(alpha, eta, n=200_000, bins=bins)
    walk = single + multiple  # power per bin of equal projected solid angle: proportional to radiance
    mu_o = np.sqrt((np.arange(bins * sub) + 0.5) / (bins * sub))  # each bin sampled uniformly in mu_o^2
    a = np.full((len(mu_o), 3), alpha)
    ss = split.single_radiance(np.ones((len(mu_o), 3)), a, mu_o)[:, 0]
    M = float(split.multiple_escape(alpha))
    iso = outgoing_radiance(np.full((len(mu_o), 3), M / (1.0 - split.fdr)), mu_o, eta)[:, 0]  # J+ = M/(1 - F_dr)
    shaped = iso * split.multiple_shape(a, mu_o)[:, 0]
    assert shaped.sum() == pytest.approx(iso.sum(), rel=0.005)  # eq. 4 moves light between directions only

    def rms(model):
        per_bin = model.reshape(bins, sub).mean(axis=1) * np.pi / bins  # the power in each bin
        return float(np.sqrt(np.mean((per_bin / walk - 1.0) ** 2)))

    e_iso, e_shaped = rms(ss + iso), rms(ss + shaped)
    print(f"eta {eta} alpha {alpha}: RMS against the walk per direction, isotropic {100 * e_iso:.1f} %, "
          f"eq. 4 {100 * e_shaped:.1f} %")
    assert e_shaped < 0.013  # the transport solution: the walk's noise (no pattern over the bins at 800k paths)
    if eta == 1.0:  # where single scattering is a large share and leaves at grazing angles
        assert e_shaped < 0.5 * e_iso


def test_split_conserves_and_limits():
    split = HalfSpaceSplit(ETA)
    a = np.linspace(0.0, 1.0, 1001)
    s, m, M, _ = split.single_escape(a), split.source_factor(a), split.multiple_escape(a), split.boundary_escape(a)
    assert np.all(s >= 0) and np.all(m >= 0) and np.all(s + m <= 1.0 + 1e-12)  # never more light than entered
    assert np.all(s + M <= 1.0 + 1e-9)
    assert s[-1] + M[-1] == pytest.approx(1.0, abs=1e-6)  # no absorption: everything leaves, once
    ok = split.B_table > 1e-6  # on the diffusion's own half-space, the source m q returns M (or what is left)
    np.testing.assert_allclose((split.m_table * split.B_table)[ok],
                               np.minimum(split.M_table, (1 - split.s_table) * split.B_table)[ok], rtol=1e-9)
    # the radiance of eq. 2 integrates to s over the outside hemisphere
    x, w = np.polynomial.legendre.leggauss(400)
    x, w = 0.5 * (x + 1), 0.5 * w
    L = split.single_radiance(np.ones((400, 3)), np.full((400, 3), 0.84), x)
    assert 2 * np.pi * np.sum(L[:, 0] * x * w) == pytest.approx(float(split.single_escape(0.84)), rel=0.01)


# --- per scene family, against the path tracer -------------------------------------------------

@pytest.fixture(scope="module")
def evaluator():
    from bench.accuracy_core import Evaluator

    return Evaluator(bake_cache=None, log=lambda *_: None)


def _images(ev, scene):
    """Diffusion alone, every term on, and the once-scattered light counted twice (the closed-form term added
    to the unsplit diffusion), on the scene's Draft bake with sky visibility, as the add-on solves."""
    from dataclasses import replace

    from bench.accuracy_core import SUPERSAMPLE, solve, view_dirs
    from bench.reference.raster import rasterize
    from translucency_addon.diffusion.solver import DiffusionSolver, SolveOptions

    bk, _ = ev.bake(scene, quality="draft")
    solver = DiffusionSolver(bk, scene.material, ev.field_values(scene, bk), SolveOptions(solver="fast", tol=1e-5))
    vd = view_dirs(scene)
    alone = solve(solver, environment=scene.environment)[0]
    every = solve(solver, environment=scene.environment, single=(True, True, True))[0]
    L = {"diffusion": solver.vertex_radiance(alone, vd), "every term": solver.vertex_radiance(every, vd),
         "double": solver.vertex_radiance(replace(alone, q_incident=list(alone.q), single=(True,) * 3), vd)}
    return {k: rasterize(scene.V, scene.F, v, scene.camera, scene.resolution, supersample=SUPERSAMPLE)
            for k, v in L.items()}, every, solver


@pytest.mark.parametrize("name", ["sphere_marble_sky", "sphere_skin1_sky"])
def test_every_term_on_is_never_worse_than_diffusion_alone(evaluator, name):
    """All terms on against diffusion alone against the cached Mitsuba reference (bench/data/reference).

    Measured (Draft graphs, debiased relative RMS; fTetWild's graphs differ a little from run to run, so
    five runs): skin1 11.0-16.3 % alone, 6.3-9.3 % every term on, 28-32 % with the once-scattered light
    counted twice; marble 1.42-1.86 % alone, 1.42-1.65 % every term on (never above alone in the same
    run), about 10 % counted twice.  Before multiple scattering left with its own angular shape (eq. 4 of
    closed_form.py) marble was 1.65 -> 1.81 % (every term on worse by 0.16-0.3 points): the isotropic
    remainder made the sum too dark head-on.  "Never worse" is held to 0.1 point, the gain where single
    scattering is a large share (skin1) to 2 points."""
    from bench import accuracy_scenes as scenes
    from bench.reference.metrics import relative_rms

    scene = next(s for s in scenes.reference_scenes() if s.name == name)
    ref = scenes.get_reference(scene)
    images, result, solver = _images(evaluator, scene)
    err = {}
    for k, ras in images.items():
        b = relative_rms(ras.image, ref.image, ras.mask, ref.mask, stderr=ref.stderr)
        err[k] = float(np.sqrt(max(b.rel_rms**2 - b.noise_floor**2, 0.0)))
        floor = b.noise_floor
    print(name, {k: round(100 * v, 2) for k, v in err.items()}, "floor", round(100 * floor, 2))
    assert err["every term"] <= err["diffusion"] + 0.001  # never worse (0.1 point: fTetWild's run-to-run)
    if name == "sphere_skin1_sky":  # where single scattering is a large share, the split is a large gain
        assert err["every term"] < err["diffusion"] - 0.02
    assert err["double"] > err["every term"] + floor  # the metric sees a double count
    pb = solver.power_balance(result)
    assert np.all(pb["out"] + pb["single"] <= pb["incident"])  # the terms together never create light


@pytest.mark.parametrize("eta", [1.0, 1.3, 1.5])
def test_the_exit_integrals_table_is_the_sum(eta):
    """HalfSpaceSplit._h reads a render mesh's many exit cosines from a table: within its bound
    (1.4e-6 relative) of the exact quadrature sum at every m, grazing ones included."""
    split = HalfSpaceSplit(eta)
    m = np.concatenate([np.random.default_rng(1).random(20_000), np.linspace(0.0, 0.06, 5000), [1.0]])
    np.testing.assert_allclose(split._h(m), split._h_exact(m), rtol=1.4e-6, atol=0)
    assert split._h_table is not None  # the table was used (a call this large)


@pytest.mark.parametrize("eta, alpha, mu_in", [(1.0, 0.84, 1.0), (1.0, 0.84, 0.25), (1.3, 0.68, 1.0),
                                               (1.3, 0.68, 0.25), (1.0, 0.96, 1.0)])
def test_the_split_of_a_lamp_follows_its_incidence(eta, alpha, mu_in):
    """Issue 31, item 1: under a lamp (a collimated beam) the shares of single and multiple scattering depend
    on the incidence -- head-on light goes deeper, so less leaves after one scattering and more is absorbed;
    grazing light stays near the surface.  The split's eq. (6) tables (the half-space's transport solution
    for each beam, ``HalfSpaceSplit.beam_*``) against the random walk of a beam at the same incidence: the
    once-scattered light and the rest, as power and per direction.  The diffuse light's tables, which the
    split used for every light until now, are off by more than 4 % here, so the test fails when the incidence is
    ignored.  Measured (200k paths): the beam tables within 1.2 % of the walk in power, 0.7-1.6 % RMS per
    direction; the diffuse tables' total at eta 1, alpha 0.84 18 % over the walk head-on and 20 % under at
    mu 0.25, at eta 1.3, alpha 0.68 (skin1's blue) 8 % over and 8 % under."""
    split = HalfSpaceSplit(eta)
    bins, sub = 8, 64
    single, multiple = random_walk(alpha, eta, n=200_000, seed=5, bins=bins, mu_in=mu_in)
    a1, mu1 = np.full((1, 3), alpha), np.array([mu_in])
    s_b = float(split.beam_single_escape(a1, mu1)[0, 0])
    M_b = float(split.lookup_beam(split.M_beam_table, a1, mu1)[0, 0])
    s_d, M_d = float(split.single_escape(alpha)), float(split.multiple_escape(alpha))
    total = single.sum() + multiple.sum()
    print(f"eta {eta} alpha {alpha} mu {mu_in}: walk {single.sum():.4f} + {multiple.sum():.4f}; beam tables "
          f"{s_b:.4f} + {M_b:.4f}; diffuse tables {s_d:.4f} + {M_d:.4f}")
    assert s_b == pytest.approx(single.sum(), rel=0.02)  # closed form: the walk's noise
    assert M_b == pytest.approx(multiple.sum(), rel=0.02)  # the transport solution
    assert abs(s_d + M_d - total) > 0.04 * total  # what ignoring the incidence costs here
    # per direction: eq. (6)'s single radiance plus M_b's shape, the model averaged over each bin of mu_o^2
    from translucency_addon.diffusion.radiance import outgoing_radiance

    mu_o = np.sqrt((np.arange(bins * sub) + 0.5) / (bins * sub))
    a = np.full((len(mu_o), 3), alpha)
    mus = np.full(len(mu_o), mu_in)
    ss = split.beam_single_radiance(np.ones((len(mu_o), 3)), a, mu_o, mus)[:, 0]
    iso = outgoing_radiance(np.full((len(mu_o), 3), M_b / (1.0 - split.fdr)), mu_o, eta)[:, 0]
    ms = iso * split.beam_multiple_shape(a, mu_o, mus)[:, 0]
    per_bin = (ss + ms).reshape(bins, sub).mean(axis=1) * np.pi / bins
    walk = single + multiple
    err = float(np.sqrt(np.mean((per_bin / walk - 1.0) ** 2)))
    print(f"  per direction RMS {100 * err:.1f} %")
    assert err < 0.02


@pytest.mark.parametrize("eta", [1.0, 1.3])
def test_output_terms_with_beams_are_the_per_term_lookups(eta):
    """HalfSpaceSplit.output_terms gathers from the flattened tables with shared indices (speed on render
    meshes); it must be the same numbers as the per-term lookups it replaces, facing-away points included."""
    split = half_space_split(eta)
    rng = np.random.default_rng(4)
    n = 5000
    a = rng.uniform(0.0, 1.0, (n, 3))
    q = rng.uniform(0.0, 1.0, (n, 3))
    qb = q * rng.uniform(0.0, 1.0, (n, 1))
    qb[:100] = 0.0  # world light only
    mu = rng.uniform(0.0, 1.0, n)
    cos_o = rng.uniform(-0.2, 1.0, n)
    shape, single = split.output_terms(q, a, cos_o, (qb, mu))
    qd = q - qb
    wd, wb = split.source_factor(a) * qd, split.beam_source_factor(a, mu) * qb
    w = wd + wb
    cd, cb = split.multiple_shape(a, cos_o), split.beam_multiple_shape(a, cos_o, mu)
    want = np.where(w > 0, (wd * cd + wb * cb) / np.where(w > 0, w, 1.0), cd)
    np.testing.assert_allclose(shape, want, rtol=0, atol=1e-12)
    np.testing.assert_allclose(single, split.single_radiance(qd, a, cos_o)
                               + split.beam_single_radiance(qb, a, cos_o, mu), rtol=1e-12, atol=0)
    np.testing.assert_array_equal(split.output_terms(q, a, cos_o, None)[0], cd)  # no lamps: the diffuse tables


def test_a_solve_splits_each_lamps_light_by_its_incidence():
    """The pipeline end to end (issue 31, item 1): the light pass hands the split the incidence each surface
    node sees its lamp at (n . the direction to the sun), and the diffusion's source is eq. (6)'s at that
    incidence, not the diffuse light's -- a light pass that reported normal incidence everywhere (as one
    version of this change did) or the diffuse tables both fail here.  With the lamps' light on the boundary
    (``lamp_source="boundary"``; the default sends it through the volume, tests/test_beam_source.py), whose
    direction the volume source also takes from the light pass (checked here too)."""
    from translucency_addon.diffusion import solver as dmod
    from translucency_addon.geometry import primitives
    from translucency_addon.quadgraph import bake as bake_mod
    from translucency_addon.scene.lights import Light
    from translucency_addon.scene.materials import material_from_preset

    V, F = primitives.icosphere(1.0, 3)
    bk = bake_mod.bake_mesh(V, F, bake_mod.BakeSettings(quality="draft", levels=2, base_triangles=200,
                                                        mm_per_unit=10.0))
    s = dmod.DiffusionSolver(bk, material_from_preset("skin1"), options=dmod.SolveOptions(single_scattering=True,
                                                                                         lamp_source="boundary"))
    d = np.array([0.3, -0.2, -1.0])
    r = s.solve([Light("sun", irradiance=1000.0, direction=tuple(d))])
    q_beam, mu, to_light = r.beams[-1]
    lit = q_beam.mean(axis=1) > 0
    assert lit.sum() > 50
    n = bk.levels[-1].normal
    np.testing.assert_allclose(mu[lit], np.clip(n[lit] @ (-d / np.linalg.norm(d)), 0.0, 1.0), rtol=0, atol=1e-12)
    np.testing.assert_allclose(to_light[lit], np.broadcast_to(-d / np.linalg.norm(d), (lit.sum(), 3)), atol=1e-12)
    split = half_space_split(s.eta)
    alpha, q_in = s.surface_albedo[-1][lit], r.q_incident[-1][lit]
    np.testing.assert_allclose(r.q[-1][lit], split.beam_source_factor(alpha, mu[lit]) * q_in, rtol=1e-12)
    diffuse = split.source_factor(alpha) * q_in
    assert np.abs(r.q[-1][lit] - diffuse).max() > 0.02 * np.abs(diffuse).max()


def test_the_split_along_the_normal_is_evaluated_at_the_nodes_and_mapped():
    """Issue 33 item 3: a render mesh's vertices cost the vertex map's sparse product, not the split's
    table lookups.  Along the normal (the viewport's view) the vertex radiance is the diffusion's output
    times the node terms carried by the map, plus the carried single scattering -- a version that looks the
    tables up per vertex from interpolated inputs differs from it on this sun-lit sphere (checked, so the
    test can tell them apart).  A camera's view, whose cosine varies per vertex, keeps the per-vertex
    evaluation."""
    from translucency_addon.diffusion import solver as dmod
    from translucency_addon.diffusion.radiance import map_to_points, outgoing_radiance
    from translucency_addon.geometry import primitives
    from translucency_addon.quadgraph import bake as bake_mod
    from translucency_addon.scene.lights import Light
    from translucency_addon.scene.materials import material_from_preset

    V, F = primitives.icosphere(1.0, 4)
    bk = bake_mod.bake_mesh(V, F, bake_mod.BakeSettings(quality="draft", levels=2, base_triangles=200,
                                                        mm_per_unit=10.0))
    s = dmod.DiffusionSolver(bk, material_from_preset("skin1"), options=dmod.SolveOptions(single_scattering=True))
    r = s.solve([Light("sun", irradiance=1000.0, direction=(0.3, -0.2, -1.0))], None)
    idx, w = bk.vertex_map
    q, beam = r.q_incident[-1], r.beams[-1]
    split = half_space_split(s.eta)
    inside = r.volume is not None and r.volume[-1] is not None
    shape_n, single_n = split.output_terms(q, s.surface_albedo[-1], np.ones(len(q)), beam, beam_in_volume=inside)
    shape_v, single_v = map_to_points(idx, w, shape_n, single_n)
    (j_v,) = map_to_points(idx, w, s.surface_partial_current(r))
    L_iso = outgoing_radiance(j_v, np.ones(len(V)), s.eta)
    np.testing.assert_allclose(s.vertex_radiance(r, transported=False), L_iso * shape_v + single_v, rtol=1e-12,
                               atol=1e-15)
    # eq. 9: the light beyond the nodes' own half-space return leaves in the diffusion's shape, blended per vertex
    (local_v,) = map_to_points(idx, w, split.local_return(q, s.surface_albedo[-1], beam))
    ft = fresnel_transmittance(1.0, s.eta)
    power = (1.0 - s.fdr) * np.pi * s.eta**2 * L_iso / ft
    blended = split.with_transported(shape_v, local_v, power, np.ones(len(V)))
    np.testing.assert_allclose(s.vertex_radiance(r), L_iso * blended + single_v, rtol=1e-12, atol=1e-15)

    assert np.abs(s.vertex_radiance(r) - s.vertex_radiance(r, transported=False)).max() > 1e-3 * L_iso.max()
    # a world alone moves no lamp light through the volume: eq. 9 leaves its output as it is
    from translucency_addon.scene.lights import Environment

    rw = s.solve([], Environment((1.0, 1.0, 1.0)))
    np.testing.assert_array_equal(s.vertex_radiance(rw), s.vertex_radiance(rw, transported=False))

    q_v, a_v, beam_v = s.split_inputs_at(q, beam, idx, w)
    shape_p, single_p = split.output_terms(q_v, a_v, np.ones(len(V)), beam_v, beam_in_volume=inside)
    per_vertex = L_iso * shape_p + single_p
    assert np.abs(per_vertex - s.vertex_radiance(r, transported=False)).max() > 1e-6 * np.abs(per_vertex).max()
    # A camera straight along each normal: the per-vertex path, the same cosine.
    np.testing.assert_allclose(s.vertex_radiance(r, view_dirs=bk.mesh_normals, transported=False), per_vertex,
                               rtol=1e-12, atol=1e-15)


@pytest.mark.parametrize("eta", [1.0, 1.3])
def test_light_carried_from_elsewhere_leaves_in_the_diffusion_s_own_shape(eta):
    """Eq. 9 of split.py.  The shape (1 + 3m/(2A)), normalised, keeps the output's power (2 pi int T_in c m dm =
    pi (1 - F_dr), by an independent Gauss rule); at albedo 0.999 and eta 1 it is the Milne problem's emergent
    distribution -- transport's, for light from a source deep below (the half-space solver, a unit source 60 mean
    free paths deep) -- within 2 % at exit cosines 0.5-1 and 4 % at 0.2; and the blend takes it only for the
    output beyond the point's own return."""
    from scipy import linalg

    from translucency_addon.diffusion.half_space import HalfSpaceTransport
    from translucency_addon.diffusion.split import refracted_cosine
    from translucency_addon.scene.fresnel import diffuse_reflectance_internal

    split = half_space_split(eta)
    m_c = np.sqrt(max(0.0, 1.0 - 1.0 / eta**2))  # below it nothing leaves (total internal reflection)
    x, wq = np.polynomial.legendre.leggauss(300)
    m = m_c + (1.0 - m_c) * 0.5 * (x + 1.0)
    wq = (1.0 - m_c) * 0.5 * wq
    cos_o = np.sqrt(np.clip(1.0 - eta**2 * (1.0 - m**2), 0.0, 1.0))  # outside cosine of inside cosine m
    assert np.allclose(refracted_cosine(cos_o, eta), m, atol=1e-7)
    power = 2.0 * np.pi * np.sum(wq * inside_transmittance(m, eta) * split.transported_shape(cos_o) * m)
    assert power == pytest.approx(np.pi * (1.0 - diffuse_reflectance_internal(eta)), rel=1e-4)
    if eta == 1.0:
        a = 0.999
        ht = HalfSpaceTransport(1.0, lambda mm: inside_transmittance(mm, 1.0))
        j = int(np.searchsorted(ht.z, 60.0))
        phi = linalg.solve(np.eye(len(ht.z)) - a * ht.K, ht.K[:, j] / ht.h[j])
        mc = np.array([1.0, 0.7, 0.5, 0.2])
        L = (ht.escape(mc).T @ phi)  # its radiance towards inside cosines mc, up to a factor
        Lq = ht.escape(m).T @ phi
        milne = L / (2.0 * np.sum(wq * Lq * m))  # normalised as c (eta 1: 2 int c m dm = 1)
        c = split.transported_shape(mc)
        assert np.allclose(c[:3], milne[:3], rtol=0.02)  # 1.25 / 1.26 along the normal (Chandrasekhar's 1.259)
        assert c[3] == pytest.approx(milne[3], rel=0.05)  # at grazing exit P1 is 4 % high (0.65 / 0.627)
        assert split.transported_shape(np.array([1.0]))[0] == pytest.approx(1.25)
    shape = np.full((3, 1), 0.9)
    local = np.array([[1.0], [1.0], [0.0]])
    out = split.with_transported(shape, local, np.array([[0.5], [3.0], [2.0]]), np.ones(3))
    cT = split.transported_shape(np.ones(1))[0]
    assert out[0, 0] == pytest.approx(0.9) and out[2, 0] == pytest.approx(cT)  # all local; none local
    assert out[1, 0] == pytest.approx((0.9 * 1.0 + cT * 2.0) / 3.0)


def test_many_albedos_by_one_eigendecomposition_are_the_dense_solves():
    """half_space.HalfSpaceTransport.solve_albedos (one eigendecomposition of K for every albedo, what the
    split's tables use) gives each albedo's dense LU solve (solve) to 1e-10, at eta 1 and 1.3."""
    from translucency_addon.diffusion.half_space import HalfSpaceTransport, depth_grid
    from translucency_addon.diffusion.split import inside_transmittance

    for eta in (1.0, 1.3):
        ht = HalfSpaceTransport(eta, lambda m, eta=eta: inside_transmittance(m, eta),
                                depth_grid(h0=0.004, growth=1.12, h_max=2.0))
        phi0 = ht.uncollided(np.array([0.3, 0.7, 1.0]), np.eye(3))
        alphas = np.array([0.1, 0.5, 0.9, 0.99, 0.999])
        many = ht.solve_albedos(alphas, phi0)
        for a, got in zip(alphas, many):
            ref = ht.solve(a, phi0)
            np.testing.assert_allclose(got, ref, rtol=0, atol=1e-10 * np.abs(ref).max())
