"""Objects with inner parts through the QuadGraph bake, the cavity exchange and the command line.

* The bake keeps the cavity: no graph node inside the hollow, and the wall's
  surface nodes carry the hollow's area (4 pi r^2).
* The exchange: the power that leaves the wall into the hollow comes back
  into the wall (closed, non-absorbing air), and with it a nearly
  non-absorbing medium returns through its outer surface all the light that
  entered (without the exchange, the part lost into the hollow is missing).
* Per-node media: an opaque part's nodes absorb (phi ~ 0 there).
* The CLI: ``bake OUTER.obj --inner PART.obj:ROLE ... --voxel-number-map``,
  ``solve`` with the pass and its time in ``--stats``,
  ``--no-voxel-number-map``; a refused part writes nothing.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from translucency_addon import __main__ as cli
from translucency_addon.geometry import meshio, primitives
from translucency_addon.cache import load_bake
from translucency_addon.inner_parts.cavity import exchange_power, solve_with_cavities, wall_partial_current
from translucency_addon.inner_parts.bake import CompositeMaterial
from translucency_addon.diffusion.solver import DiffusionSolver, SolveOptions
from translucency_addon.scene.lights import Environment, Light
from translucency_addon.scene.materials import Material, Medium

R_CAVITY = 6.0


@pytest.fixture(scope="module")
def cli_bake(tmp_path_factory):
    """A 20 mm cube with a 6 mm spherical cavity and a 2.5 mm opaque stone, baked through the CLI."""
    d = tmp_path_factory.mktemp("composite")
    (Vb, Fb), (Vs, Fs) = primitives.cube_with_sphere(20.0, R_CAVITY, n=8, subdivisions=2)
    meshio.save_obj(d / "cube.obj", Vb, Fb)
    meshio.save_obj(d / "hole.obj", Vs, Fs)
    meshio.save_obj(d / "stone.obj", *primitives.icosphere(2.5, 2, (6.0, 6.0, 6.0)))
    rc = cli.main(["bake", str(d / "cube.obj"), "--inner", f"{d / 'hole.obj'}:cavity",
                   "--inner", f"{d / 'stone.obj'}:opaque", "--voxel-number-map", "--vnm-quality", "draft",
                   "--quality", "draft", "--levels", "2", "--material", "skin1", "-o", str(d / "c.npz")])
    assert rc == 0
    return d, load_bake(d / "c.npz")


def test_the_bake_keeps_the_cavity_and_its_wall(cli_bake):
    _, bake = cli_bake
    for lv in bake.levels:
        r = np.linalg.norm(lv.position[: lv.n_inner], axis=1)
        assert r.min() > R_CAVITY - 0.3  # no node in the hollow (a tet centroid lies inside its cell)
    ex = bake.composite.exchange
    assert ex is not None and ex.names == ("hole",)
    lv = bake.finest
    assert np.allclose(np.linalg.norm(lv.surface_position[ex.nodes], axis=1), R_CAVITY, atol=0.2)
    assert abs(lv.area[ex.nodes].sum() / (4 * np.pi * R_CAVITY**2) - 1.0) < 0.05
    assert np.all(np.einsum("ij,ij->i", lv.normal[ex.nodes], lv.surface_position[ex.nodes]) < 0)  # into the hollow
    assert np.allclose(ex.K.sum(axis=1), 1.0, atol=1e-5)  # a closed cavity's wall sees only itself
    assert bake.voxel_number_map is not None and bake.composite.roles == ("cavity", "opaque")


def _clear_without_stone(bake, tol, lamp_source="volume"):
    """A solver of the cube in a clear medium (albedo ~1) with the stone left out (as the outer medium: it
    absorbs, and these tests hold the power to account), and a sun."""
    info = bake.composite
    clear = Material(Medium((1e-4, 1e-4, 1e-4), (1.0, 1.0, 1.0), "clear"))
    no_stone = type(info)(info.names, ("cavity", "medium"), (None, ((1e-4,) * 3, (1.0,) * 3)), info.labels,
                          info.n_outer_vertices, info.exchange)
    solver = DiffusionSolver(bake, CompositeMaterial(clear, no_stone), info.labels,
                             SolveOptions(tol=tol, lamp_source=lamp_source))
    return solver, [Light("sun", irradiance=1000.0, direction=(-1.0, -0.3, -0.2))]


def test_the_exchange_returns_the_light_the_wall_loses(cli_bake):
    _, bake = cli_bake
    info = bake.composite
    solver, sun = _clear_without_stone(bake, 1e-6)
    plain = solver.solve(sun, None)
    with_ex, meta = solve_with_cavities(solver, info.exchange, sun, None, tol=1e-6)
    p = exchange_power(solver, with_ex, info.exchange)
    assert meta["residual"] < 1e-4 and meta["solves"] <= 12
    assert np.allclose(p["out"], p["back"], rtol=1e-4) and np.all(p["out"] > 0)
    # outer surface: in = out + absorbed with the exchange; without it the light lost into the hollow is missing
    lv = bake.finest
    outer = np.ones(lv.n_surface, dtype=bool)
    outer[info.exchange.nodes] = False
    a = lv.area * (bake.mm_per_unit * 1e-3) ** 2

    def outer_balance(res):
        jp = (res.phi[-1][lv.n_inner:] - 2.0 * res.q[-1]) / (2.0 * (1.0 + solver.fdr))
        out = (1.0 - solver.fdr) * (a[outer] @ jp[outer])
        return out, a[outer] @ res.q[-1][outer], solver.power_balance(res, clamp=False)["absorbed"]

    out0, in0, abs0 = outer_balance(plain)
    out1, in1, abs1 = outer_balance(with_ex)
    lost = (1.0 - solver.fdr) * (a[info.exchange.nodes] @ wall_partial_current(solver, plain, info.exchange.nodes))
    assert np.allclose(in0, in1)
    assert np.allclose(out1 + abs1, in1, rtol=2e-3)  # nothing vanishes into the hollow
    assert np.allclose(out0 + abs0 + lost, in0, rtol=2e-3)  # ... which is what the plain solve loses
    assert np.all(out1 > out0 * 1.001)
    # a world lights the outer surface only: the walls receive nothing but the exchange
    res, _ = solve_with_cavities(solver, info.exchange, [], Environment((1.0, 1.0, 1.0)), tol=1e-5)
    assert np.allclose(res.q[-1][info.exchange.nodes], res.cavity_q) and np.all(res.q[-1][outer] > 0)


def test_opaque_part_absorbs_in_the_diffusion(cli_bake):
    _, bake = cli_bake
    mat = CompositeMaterial(Material(Medium((0.01,) * 3, (1.0,) * 3, "m")), bake.composite)
    lab = bake.composite.labels[-1]
    sa, _ = mat.coefficients(lab)
    assert np.all(sa[lab == 2] == 1e3) and np.all(sa[lab == 0] == 0.01) and (lab == 2).sum() > 0
    solver = DiffusionSolver(bake, mat, bake.composite.labels, SolveOptions(tol=1e-5))
    res = solver.solve([Light("sun", irradiance=1000.0, direction=(-1.0, -1.0, -1.0))], None)
    phi = res.phi[-1][: bake.finest.n_inner, 0]
    assert phi[lab[: bake.finest.n_inner] == 2].max() < 0.05 * np.median(phi[lab[: bake.finest.n_inner] == 0])


def test_cli_solve_reports_the_pass_and_can_leave_it_out(cli_bake):
    d, bake = cli_bake
    args = ["solve", str(d / "c.npz"), "--material", "skin1", "--sun=-1,0,0:1000", "--pass-planning", "all"]
    assert cli.main(args + ["-o", str(d / "on.npy"), "--stats", str(d / "on.json")]) == 0
    assert cli.main(args + ["-o", str(d / "off.npy"), "--stats", str(d / "off.json"), "--no-voxel-number-map"]) == 0
    on, off = json.loads((d / "on.json").read_text()), json.loads((d / "off.json").read_text())
    assert on["voxel_number_map"]["enabled"] and on["voxel_number_map"]["surface_voxels"] == bake.voxel_number_map.n
    assert on["seconds"]["voxel_number_map"] > 0 and on["voxel_number_map"]["seconds"]["frame"]["total"] > 0
    assert not off["voxel_number_map"]["enabled"] and "--no-voxel-number-map" in off["voxel_number_map"]["reason"]
    assert on["cavity_exchange"]["residual"] < 1e-3
    L_on, L_off = np.load(d / "on.npy"), np.load(d / "off.npy")
    n_outer = bake.composite.n_outer_vertices
    assert L_on.shape == (len(bake.mesh_vertices), 3)
    assert np.all(L_on[:n_outer] >= L_off[:n_outer] - 1e-6) and L_on[:n_outer].sum() > L_off[:n_outer].sum()
    assert np.array_equal(L_on[n_outer:], L_off[n_outer:])  # the pass writes the outer surface only


def test_cli_refuses_bad_parts_and_writes_nothing(cli_bake, tmp_path, capsys):
    d, _ = cli_bake
    out = tmp_path / "bad.npz"
    rc = cli.main(["bake", str(d / "cube.obj"), "--inner", f"{d / 'hole.obj'}:cavity",
                   "--inner", f"{d / 'hole.obj'}:opaque", "--voxel-number-map", "-o", str(out)])
    assert rc == 2 and not out.exists()
    assert "two roles (cavity as 'hole' and opaque as 'hole')" in capsys.readouterr().err
    meshio.save_obj(tmp_path / "far.obj", *primitives.icosphere(2.0, 1, (40.0, 0.0, 0.0)))
    rc = cli.main(["bake", str(d / "cube.obj"), "--inner", f"{tmp_path / 'far.obj'}:marble", "-o", str(out)])
    assert rc == 2 and not out.exists() and "'far' lies entirely outside" in capsys.readouterr().err
    rc = cli.main(["bake", str(d / "cube.obj"), "--inner", f"{d / 'hole.obj'}", "-o", str(out)])
    assert rc == 2 and not out.exists() and "PART.obj:ROLE" in capsys.readouterr().err


@pytest.mark.parametrize("role", ["cavity", "opaque"])
def test_cli_refuses_open_and_self_intersecting_parts_by_name(cli_bake, tmp_path, capsys, role):
    """An open part (two holes) or one crossing itself is refused by its name, in numbers; nothing is written."""
    d, _ = cli_bake
    out = tmp_path / "open.npz"
    V, F = primitives.icosphere(2.5, 2, (-5.0, -5.0, -5.0))
    z = V[F].mean(axis=1)[:, 2] + 5.0
    meshio.save_obj(tmp_path / "Stone.obj", V, F[np.abs(z) < 2.2])  # both caps cut off
    rc = cli.main(["bake", str(d / "cube.obj"), "--inner", f"{tmp_path / 'Stone.obj'}:{role}", "--quality", "draft",
                   "-o", str(out)])
    err = capsys.readouterr().err
    assert rc == 2 and not out.exists() and not list(tmp_path.glob("*.npz*"))
    assert "inner part 'Stone' is open: 2 holes (boundary loops of 12 and 12 edges)" in err
    V2, F2 = primitives.icosphere(2.5, 2, (-4.0, -5.0, -5.0))
    meshio.save_obj(tmp_path / "Knot.obj", np.concatenate([V, V2]), np.concatenate([F, F2 + len(V)]))
    rc = cli.main(["bake", str(d / "cube.obj"), "--inner", f"{tmp_path / 'Knot.obj'}:{role}", "-o", str(out)])
    err = capsys.readouterr().err
    assert rc == 2 and not out.exists() and "inner part 'Knot' intersects itself:" in err and "pairs" in err


def test_exchange_with_coincident_wall_nodes_drops_the_pair_without_a_warning():
    """Two wall nodes at one point (R = 0) have no form factor: the pair is left out before any division (it
    divided 0 by 0 and let numpy's RuntimeWarning out); every row still sums to 1."""
    import warnings
    from types import SimpleNamespace

    from translucency_addon.inner_parts.cavity import build_cavity_exchange
    from translucency_addon.scene.composite import CompositeObject, InnerPart

    (Vb, Fb), (Vs, Fs) = primitives.cube_with_sphere(20.0, R_CAVITY, n=4, subdivisions=1)
    comp = CompositeObject(Vb, Fb, Material(Medium((0.01,) * 3, (1.0,) * 3, "m")), [InnerPart("hole", Vs, Fs, "cavity")])
    V, F, _ = comp.diffusion_mesh()
    P = np.concatenate([Vb, Vs, Vs[:1]])  # the outer surface's nodes, the wall's, and the wall's first node twice
    N = np.concatenate([Vb, -Vs, -Vs[:1]]) / np.linalg.norm(np.concatenate([Vb, Vs, Vs[:1]]), axis=1)[:, None]
    lv = SimpleNamespace(surface_position=P, normal=N, area=np.ones(len(P)))
    bake = SimpleNamespace(finest=lv, levels=[lv], mesh_vertices=V, mesh_faces=F)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        ex = build_cavity_exchange(bake, comp)
    assert ex.m == len(Vs) + 1 and np.all(np.isfinite(ex.K))
    assert np.allclose(ex.K.sum(axis=1), 1.0, atol=1e-5)
    assert ex.K[0, -1] == 0.0 and ex.K[-1, 0] == 0.0  # the coincident pair exchanges nothing


def test_the_exchange_carries_the_first_scatter_split(cli_bake):
    """With the split (the planner's default where single scattering matters) the cavity solve keeps its
    output fields (``single``, ``q_incident``: the closed form is added at the outer surface) and counts the
    light that leaves the wall after one scattering: in a clear medium (albedo ~1, where the split and plain
    diffusion return the same from a half-space) the wall loses the same power into the hollow with and
    without the split, 1 % apart; leaving out the once-scattered share made it 17 % short.  The sun's light
    enters at the boundary here, as without the split (with the split it would otherwise take the volume,
    diffusion/beam_source.py, and reach the wall along its chords: 20 % more)."""
    _, bake = cli_bake
    info = bake.composite
    solver, sun = _clear_without_stone(bake, 1e-7, lamp_source="boundary")
    plain, _ = solve_with_cavities(solver, info.exchange, sun, None, tol=1e-6)
    split, meta = solve_with_cavities(solver, info.exchange, sun, None, tol=1e-6, single=(True, True, True))
    assert split.single == (True, True, True) and split.q_incident is not None
    assert meta["residual"] < 1e-4
    p0, p1 = exchange_power(solver, plain, info.exchange), exchange_power(solver, split, info.exchange)
    assert np.allclose(p1["out"], p1["back"], rtol=1e-4)
    assert np.all(np.abs(p1["out"] / p0["out"] - 1.0) < 0.03), (p1["out"], p0["out"])
    # the wall's light enters the split's output: the outer surface is brighter than with dark walls
    dark = solver.solve(q=info.exchange.dark_walls(solver.incident(sun, None)), single=(True, True, True))
    n = info.n_outer_vertices
    assert np.all(solver.vertex_radiance(split)[:n].mean(axis=0) > solver.vertex_radiance(dark)[:n].mean(axis=0))
