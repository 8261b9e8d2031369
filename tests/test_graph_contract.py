# SPDX-License-Identifier: GPL-3.0-or-later
"""The graph contract (translucency_addon.diffusion.graph): one assembly and one set of solvers for every graph kind.

A graph that is not a QuadGraph -- a column of box cells with six link slots,
the shape of a Voronoi-fluid or voxel discretisation -- goes through the same
``assemble`` and solvers and matches the closed-form slab solution of eq. 1-2.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest

from bakes import baked
from translucency_addon.diffusion.assembly import assemble
from translucency_addon.errors import TranslucencyError
from translucency_addon.scene.fresnel import boundary_A, diffuse_reflectance_internal
from translucency_addon.diffusion.graph import check_graph, graph_components
from translucency_addon.diffusion.iterative import solve_cg, solve_chebyshev, solve_direct
from translucency_addon.scene.materials import diffusion_coefficient


@dataclass
class CellColumn:
    """n box cells (h x h x dz) stacked along z, six link slots each (+-x, +-y, +-z); the four side faces
    carry no link (zero flux), the top and bottom faces are surface nodes.  A graph kind of its own."""

    n_inner: int
    n_surface: int
    position: np.ndarray
    neighbors: np.ndarray
    edge_length: np.ndarray
    face_area: np.ndarray
    volume: np.ndarray
    normal: np.ndarray
    area: np.ndarray

    @property
    def n_nodes(self) -> int:
        return self.n_inner + self.n_surface

    @property
    def surface_position(self) -> np.ndarray:
        return self.position[self.n_inner:]

    @classmethod
    def slab(cls, n: int, thickness: float, h: float = 1.0) -> "CellColumn":
        dz = thickness / n
        z = (np.arange(n) + 0.5) * dz
        pos = np.zeros((n + 2, 3))
        pos[:n, 2] = z
        pos[n, 2], pos[n + 1, 2] = thickness, 0.0  # top, bottom surface nodes
        nbr = np.full((n + 2, 6), -1, dtype=np.int32)
        d = np.zeros((n + 2, 6))
        a = np.zeros((n + 2, 6))
        idx = np.arange(n)
        nbr[idx[1:], 5], nbr[idx[:-1], 4] = idx[:-1], idx[1:]  # slot 4: +z, slot 5: -z
        d[:n, 4:] = dz
        a[:n, 4:] = h * h
        nbr[n - 1, 4], nbr[0, 5] = n, n + 1  # the end cells link to the surface nodes, half a cell away
        d[n - 1, 4] = d[0, 5] = 0.5 * dz
        nbr[n:, 0] = (n - 1, 0)
        d[n:, 0] = 0.5 * dz
        a[n:, 0] = h * h
        return cls(n_inner=n, n_surface=2, position=pos, neighbors=nbr, edge_length=d, face_area=a,
                   volume=np.full(n, h * h * dz), normal=np.array([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]]),
                   area=np.full(2, h * h))


def slab_phi(sigma_a, sigma_s, eta, thickness, q):
    """Closed form of eq. 1-2 on a slab lit at z = L: kappa phi'' = mu phi, phi + 2 A kappa dphi/dn = 4q/(1-F_dr)
    at z = L (n = +z), and with no light at z = 0 (n = -z).  Returns (phi(L), phi(0))."""
    kappa = diffusion_coefficient(np.array([sigma_a]), np.array([sigma_s]))[0]
    s = np.sqrt(sigma_a / kappa)
    A, fdr = boundary_A(eta), diffuse_reflectance_internal(eta)
    L = thickness
    # phi = c1 cosh(s z) + c2 sinh(s z)
    M = np.array([[np.cosh(s * L) + 2 * A * kappa * s * np.sinh(s * L), np.sinh(s * L) + 2 * A * kappa * s * np.cosh(s * L)],
                  [1.0, -2 * A * kappa * s]])
    c1, c2 = np.linalg.solve(M, [4 * q / (1 - fdr), 0.0])
    return c1 * np.cosh(s * L) + c2 * np.sinh(s * L), c1


def test_quadgraph_levels_implement_the_contract():
    b = baked("sphere")
    for lv in b.levels:
        check_graph(lv)
    assert len(np.unique(graph_components(b.finest))) == 1


@pytest.mark.parametrize("break_it, message", [
    (lambda g: setattr(g, "edge_length", g.edge_length[:, :4]), "edge_length must have the shape of neighbors"),
    (lambda g: g.neighbors.__setitem__((g.n_inner, 0), -1), "surface node needs its inner node in link slot 0"),
    (lambda g: g.edge_length.__setitem__((0, 4), 0.0), "finite length > 0"),
    (lambda g: g.edge_length.__setitem__((0, 4), np.nan), "finite length > 0"),
    (lambda g: g.face_area.__setitem__((0, 4), np.inf), "face area >= 0"),
    (lambda g: g.face_area.__setitem__((0, 4), -1e-3), "face area >= 0"),
    (lambda g: g.neighbors.__setitem__((0, 1), 99), "outside 0.."),
    (lambda g: g.volume.__setitem__(0, -1.0), "volumes must be > 0"),
])
def test_a_broken_graph_is_refused_with_its_reason(break_it, message):
    g = CellColumn.slab(8, 4.0)
    check_graph(g)
    break_it(g)
    with pytest.raises(TranslucencyError, match=message):
        assemble(g, np.full((g.n_nodes, 3), 0.05), np.full((g.n_nodes, 3), 1.0), 1.3, 1.0)


def _compiled_or_skip(compiled):
    from translucency_addon.diffusion import assembly

    if compiled and assembly.available():
        pytest.skip(f"the compiled assembly cannot run here: {assembly.available()}")


@pytest.mark.parametrize("compiled", [False, True])
@pytest.mark.parametrize("sigma_a, sigma_s", [(0.01, 1.0), (0.05, 2.0), (0.3, 0.7)])
def test_another_graph_kind_solves_against_the_closed_form_slab(sigma_a, sigma_s, compiled):
    """Same assembly and solvers on a 6-slot cell column: phi at both faces within 0.02 % of eq. 1-2's slab,
    with the links assembled by numpy and by the compiled kernel (diffusion/assembly_kernels.py)."""
    _compiled_or_skip(compiled)
    eta, thickness, q = 1.3, 6.0, 1.0
    g = CellColumn.slab(400, thickness)
    n = g.n_nodes
    system = assemble(g, np.full((n, 3), sigma_a), np.full((n, 3), sigma_s), eta, mm_per_unit=1.0,
                      compiled=compiled)
    qs = np.array([[q] * 3, [0.0] * 3])
    b = system.rhs(qs)
    x_direct, _ = solve_direct(system, b)
    for solve in (solve_chebyshev, solve_cg):  # the same system by both iterations
        x_it, info = solve(system, b, np.zeros_like(b), 1e-10, 200_000)
        assert info.converged_to <= 1e-10, solve.__name__
        np.testing.assert_allclose(x_it, x_direct, rtol=1e-6, atol=1e-12)
    top, bottom = slab_phi(sigma_a, sigma_s, eta, thickness, q)
    np.testing.assert_allclose(x_direct[g.n_inner, 0], top, rtol=2e-4)  # measured <= 4.2e-5 (400 cells)
    np.testing.assert_allclose(x_direct[g.n_inner + 1, 0], bottom, rtol=2e-4)  # measured <= 4.2e-5 (400 cells)


def test_the_compiled_assembly_is_numpys(monkeypatch):
    """From COMPILED_ASSEMBLY_MIN_NODES nodes assemble() builds the conservative scheme's links in one compiled
    pass where numba runs: the numpy lines' system to rounding on a QuadGraph level and a fluid's cell graph
    (surface links fitted, harmonic means of coefficients that vary per node, a scale of 0.7 mm per unit)."""
    from translucency_addon.diffusion import assembly
    from translucency_addon.fluid import build_cells, build_graph

    _compiled_or_skip(True)
    rng = np.random.default_rng(3)
    lattice = np.stack(np.meshgrid(*[np.arange(12.0)] * 3, indexing="ij"), axis=-1).reshape(-1, 3)
    fluid = build_graph(build_cells(lattice + rng.uniform(-0.1, 0.1, lattice.shape), 1.0))
    for g in (baked("sphere").finest, fluid):
        n = g.n_nodes
        sa, ss = rng.uniform(0.005, 0.5, (n, 3)), rng.uniform(0.5, 3.0, (n, 3))
        want = assemble(g, sa, ss, 1.3, 0.7, compiled=False)
        calls, real = [], assembly._compiled_fv
        monkeypatch.setattr(assembly, "_compiled_fv", lambda *a, c=calls, f=real: c.append(1) or f(*a))
        monkeypatch.setattr(assembly, "COMPILED_ASSEMBLY_MIN_NODES", n)  # auto takes it from here
        got = assemble(g, sa, ss, 1.3, 0.7)
        assert calls == [1]
        for name in ("off", "diag", "b_scale", "boundary_diag"):
            np.testing.assert_allclose(getattr(got, name), getattr(want, name), rtol=1e-13, atol=0, err_msg=name)
        np.testing.assert_array_equal(got.nbr, want.nbr)
        monkeypatch.undo()
