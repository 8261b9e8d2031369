"""The sweeps' operator (diffusion/sweeps.py): ``r -= A d`` over the graph's link slots in compiled code
against the system's matrix built independently (assembly.sparse_matrix), in both sweep precisions, with
the bounce's two copies, on a QuadGraph level (RCM order) and a fluid frame's cells (their own order)."""

import numpy as np
import pytest
import scipy.sparse as sp

from translucency_addon.quadgraph.bake import BakeSettings, bake_mesh
from translucency_addon.diffusion import compiled_cg
from translucency_addon.diffusion.assembly import sparse_matrix
from translucency_addon.diffusion.solver import DiffusionSolver
from translucency_addon.diffusion.sweeps import SweepOperator, _identity, sweep_links
from translucency_addon.scene.materials import material_from_preset
from translucency_addon.geometry import primitives

from test_fluid_solve import jittered_frames

_SYSTEMS = {}


def _system(kind):
    if kind not in _SYSTEMS:
        if kind == "quadgraph":
            V, F = primitives.box((1.0, 1.0, 1.0), subdivisions=3)
            b = bake_mesh(V, F, BakeSettings(quality="draft", levels=1, base_triangles=300, mm_per_unit=20.0))
            _SYSTEMS[kind] = DiffusionSolver(b, material_from_preset("marble")).systems[-1]
        else:
            _SYSTEMS[kind] = jittered_frames(8.0, 7)[1].diffusion.systems[0]
    return _SYSTEMS[kind]


@pytest.mark.parametrize("kind", ["quadgraph", "fluid"])
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("copies", [1, 2])
def test_the_link_product_is_the_assembled_matrix(kind, dtype, copies):
    assert compiled_cg.available() == ""  # numba is in the test environment: the compiled product runs
    system = _system(kind)
    op = SweepOperator(system, copies=copies, dtype=dtype)
    assert op.links is not None and op._neg_a is None  # the link slots, no CSR built
    assert _identity(op.perm) == (kind == "fluid")
    C0, n = system.diag.shape[1], system.n
    # the slots' one compiled pass (cg_kernels.permuted_slots) also writes the Jacobi preconditioner in sweep order
    np.testing.assert_array_equal(op.inv_diag, np.tile(1.0 / system.diag[op.perm].T, (copies, 1)).astype(dtype))
    assert op.links[0] is sweep_links(system)  # one copy of the graph's reordered slots, the coarse space's too
    A = [sparse_matrix(system, c)[op.perm][:, op.perm] for c in range(C0)]  # sweep order
    rng = np.random.default_rng(3)
    d = rng.standard_normal((C0 * copies, n)).astype(dtype)
    r0 = rng.standard_normal((C0 * copies, n)).astype(dtype)
    expected = np.stack([r0[c].astype(np.float64) - A[c % C0] @ d[c].astype(np.float64) for c in range(len(d))])
    r = r0.copy()
    op.sub_a(r, d)
    rtol = 1e-5 if dtype == np.float32 else 1e-12
    scale = np.abs(expected).max()
    np.testing.assert_allclose(r, expected, rtol=0, atol=rtol * scale)
    out = np.full_like(d, np.nan)  # overwritten, not accumulated
    dad = op.product(d, out)
    Ad = np.stack([A[c % C0] @ d[c].astype(np.float64) for c in range(len(d))])
    np.testing.assert_allclose(out, -Ad, rtol=0, atol=rtol * np.abs(Ad).max())
    np.testing.assert_allclose(dad, np.einsum("cn,cn->c", d.astype(np.float64), Ad), rtol=10 * rtol)
    links = sweep_links(system)
    for c in range(len(d)):  # the coarse space's Galerkin sums read these: -A by slot, on both paths
        off, neg_diag = op.slot_values(c)
        rows = np.broadcast_to(np.arange(n)[:, None], links.shape)[links >= 0]
        slots = sp.csr_matrix((off[links >= 0], (rows, links[links >= 0])), shape=(n, n)) + sp.diags(neg_diag)
        np.testing.assert_allclose(slots.toarray(), -A[c % C0].toarray(), rtol=1e-6 if dtype == np.float32 else 1e-15)
        csr_path = SweepOperator(system, copies=copies, dtype=dtype)
        csr_path.links = None  # as where numba is missing
        for a, b in zip(csr_path.slot_values(c), (off, neg_diag)):
            np.testing.assert_allclose(a, b, rtol=1e-6 if dtype == np.float32 else 0)


def test_without_numba_the_product_is_scipys_csr(monkeypatch):
    """Where the kernels cannot load, the same operator (built with link slots) falls back to the CSR."""
    system = _system("fluid")
    op = SweepOperator(system)
    d = np.random.default_rng(0).standard_normal((op.C, op.n))
    fast = np.zeros_like(d)
    op.sub_a(fast, d)
    monkeypatch.setattr(compiled_cg, "_KERNEL", {"error": "numba is not installed"})
    slow = np.zeros_like(d)
    op.sub_a(slow, d)
    assert op._neg_a is not None
    np.testing.assert_allclose(slow, fast, rtol=0, atol=1e-12 * np.abs(fast).max())
    assert SweepOperator(system).links is None


def test_a_bake_carries_its_sweep_order_so_a_frame_computes_no_rcm(monkeypatch):
    """The bake computes each level's RCM order once (GraphLevel.sweep_order, kept in the cache); the solver
    sweeps in it and runs no Cuthill-McKee of its own, and the order is the one it would compute."""
    from translucency_addon.diffusion import sweeps

    V, F = primitives.box((1.0, 1.0, 1.0), subdivisions=3)
    b = bake_mesh(V, F, BakeSettings(quality="draft", levels=2, base_triangles=300, mm_per_unit=20.0))
    for lv in b.levels:
        np.testing.assert_array_equal(lv.sweep_order, sweeps.rcm_permutation(lv.neighbors, lv.n_inner))

    def no_rcm(*a, **k):
        raise AssertionError("the solver ran RCM though the bake keeps the order")

    monkeypatch.setattr(sweeps, "rcm_permutation", no_rcm)
    s = DiffusionSolver(b, material_from_preset("marble"))
    for system, lv in zip(s.systems, b.levels):
        np.testing.assert_array_equal(SweepOperator(system, dtype=np.float32).perm, lv.sweep_order)
