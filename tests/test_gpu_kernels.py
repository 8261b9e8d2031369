"""Parity of every GLSL kernel (gpu_shaders/*.glsl) with its numpy twin (translucency_addon.diffusion.kernels).

Each kernel runs on llvmpipe here (any GPU elsewhere) on random inputs over a
synthetic graph with partial blocks, missing neighbours and padding texels,
once in the normal layout and once split into texture layers (an artificially
small maximum texture size).

Tolerances, as max |gpu - twin| / max |twin|:

* ``FP32_TOL = 1e-5``: fp32 storage; and fp16 storage when the twin is fed the
  very numbers the GPU stores (pack.quantize rounds on the host, so the upload
  is exact).  Measured: about 2e-7.
* ``FP16_TOL = 2e-3``: fp16 storage against the twin on the unrounded fp64
  inputs, i.e. what storing coefficients/q/weights in fp16 costs one kernel
  application.  Measured: 1.5e-4 to 4.4e-4 (fp16 half-ulp rounding is 4.9e-4 per value).
"""

from __future__ import annotations

import numpy as np
import pytest

from gpu_shaders import device, pack, runtime
from translucency_addon import errors
from translucency_addon.diffusion import kernels

FP32_TOL = 1e-5
FP16_TOL = 2e-3

N_INNER, N_SURF = 3000, 700  # partial last blocks in both regions


def rel_err(got, ref) -> float:
    ref = np.asarray(ref, dtype=np.float64)
    return float(np.abs(np.asarray(got, dtype=np.float64) - ref).max() / max(np.abs(ref).max(), 1e-300))


def synthetic_system(seed=0, n_inner=N_INNER, n_surf=N_SURF):
    """A random system in kernel form: (nbr, off, diag, b_scale (n_surf, 3))."""
    rng = np.random.default_rng(seed)
    N = n_inner + n_surf
    nbr = rng.integers(0, N, size=(N, 4)).astype(np.int32)
    nbr[rng.random((N, 4)) < 0.1] = -1
    nbr[n_inner:, 1:] = -1  # surface nodes: one link
    nbr[n_inner:, 0] = rng.integers(0, n_inner, size=n_surf)
    off = np.where((nbr >= 0)[..., None], rng.uniform(0.05, 1.0, size=(N, 4, 3)), 0.0)
    diag = off.sum(axis=1) + rng.uniform(1e-3, 0.5, size=(N, 3))
    b_scale = np.repeat(rng.uniform(0.1, 2.0, size=(n_surf, 1)), 3, axis=1)
    return nbr, off, diag, b_scale


LAYOUTS = {"single": dict(max_size=16384), "layers": dict(max_size=64)}


@pytest.fixture(scope="module", params=sorted(LAYOUTS))
def layout(request):
    lay = pack.plan_layout(N_INNER, N_SURF, **LAYOUTS[request.param])
    if request.param == "layers":
        assert lay.layers > 1
    return lay


def make_level(layout, precision="fp32", seed=0):
    nbr, off, diag, b_scale = synthetic_system(seed)
    g = device.GPULevel(layout, nbr, precision)
    pc = g.upload_coefficients(off, diag, b_scale)
    return g, pc, (nbr, off, diag, b_scale)


def stored_system(pc, layout):
    """The system exactly as stored on the GPU (quantized/scaled in fp16)."""
    return pc.off_nodes, pc.diag, pc.b_scale


# ------------------------------------------------------------------ layout (no GPU)
def test_layout_is_a_block_ordered_bijection():
    lay = pack.plan_layout(N_INNER, N_SURF)
    idx = lay.flat_index()
    assert len(np.unique(idx)) == lay.n_nodes
    assert idx.max() < lay.texels
    x, y, layer = lay.texel(np.arange(lay.n_nodes))
    row = layer * lay.height + y
    assert np.all(row[:N_INNER] < lay.surf_y0) and np.all(row[N_INNER:] >= lay.surf_y0)
    # Node k of a block of r*r consecutive nodes stays inside one r x r texel block.
    B = lay.block
    blk = np.arange(lay.n_nodes) // (B * B)
    for b in np.unique(blk[:N_INNER]):
        m = blk[:N_INNER] == b
        assert len(np.unique(x[:N_INNER][m] // B)) == 1 and len(np.unique(row[:N_INNER][m] // B)) == 1


def test_layout_splits_into_layers_or_refuses():
    lay = pack.plan_layout(N_INNER, N_SURF, max_size=64)
    assert lay.width <= 64 and lay.height <= 64 and lay.layers > 1
    assert len(np.unique(lay.flat_index())) == lay.n_nodes
    with pytest.raises(errors.GraphTooLarge, match="layers"):
        pack.plan_layout(N_INNER, N_SURF, max_size=64, max_layers=1)
    with pytest.raises(errors.GraphTooLarge, match="smaller than one 32x32 block"):
        pack.plan_layout(N_INNER, N_SURF, max_size=16)


def test_fp16_scaling_keeps_values_normal():
    nbr, off, diag, b_scale = synthetic_system()
    lay = pack.plan_layout(N_INNER, N_SURF)
    pc = pack.pack_coefficients(lay, off * 1e-6, diag * 1e-6, b_scale * 1e-6, "fp16")  # far below fp16's range
    assert pc.subnormal == 0 and pc.scale > 1e5
    assert rel_err(pc.diag / pc.scale, diag * 1e-6) < 2e-3


# ------------------------------------------------------------------ kernels
@pytest.mark.gpu
def test_upload_and_readback_roundtrip(layout):
    rng = np.random.default_rng(1)
    g, _, _ = make_level(layout)
    x = rng.standard_normal((layout.n_nodes, 3)).astype(np.float32)
    tex = g.upload_nodes(x)
    assert np.array_equal(g.read(tex), x)
    assert np.array_equal(g.read_nodes(tex, layout.n_inner, layout.n_surface), x[layout.n_inner:])
    assert np.array_equal(g.read_nodes(tex, 17, 5), x[17:22])


@pytest.mark.gpu
@pytest.mark.parametrize("precision", ["fp32", "fp16"])
def test_jacobi_sweep(layout, precision):
    rng = np.random.default_rng(2)
    g, pc, (nbr, off, diag, b_scale) = make_level(layout, precision)
    q = rng.uniform(0.0, 3.0, size=(layout.n_surface, 3))
    qs = g.upload_q(q)
    x = rng.uniform(0.0, 2.0, size=(layout.n_nodes, 3)).astype(np.float32)
    g.set_x(x)
    g.jacobi_step()
    got = g.read(g.x_current)
    off_s, diag_s, bs_s = stored_system(pc, layout)
    b_s = np.zeros((layout.n_nodes, 3))
    b_s[layout.n_inner:] = bs_s[:, None] * qs
    assert rel_err(got, kernels.jacobi_sweep(nbr, off_s, diag_s, b_s, x.astype(np.float64))) < FP32_TOL
    b = np.zeros((layout.n_nodes, 3))
    b[layout.n_inner:] = b_scale * q
    exact = kernels.jacobi_sweep(nbr, off, diag, b, x.astype(np.float64))
    assert rel_err(got, exact) < (FP32_TOL if precision == "fp32" else FP16_TOL)


@pytest.mark.gpu
@pytest.mark.parametrize("precision", ["fp32", "fp16"])
def test_residual(layout, precision):
    rng = np.random.default_rng(3)
    g, pc, (nbr, off, diag, b_scale) = make_level(layout, precision)
    q = rng.uniform(0.0, 3.0, size=(layout.n_surface, 3))
    qs = g.upload_q(q)
    x = rng.uniform(0.0, 2.0, size=(layout.n_nodes, 3)).astype(np.float32)
    g.set_x(x)
    g.residual()
    got = g.read(g.r)
    off_s, diag_s, bs_s = stored_system(pc, layout)
    b_s = np.zeros((layout.n_nodes, 3))
    b_s[layout.n_inner:] = bs_s[:, None] * qs
    assert rel_err(got, kernels.residual(nbr, off_s, diag_s, b_s, x.astype(np.float64))) < FP32_TOL
    b = np.zeros((layout.n_nodes, 3))
    b[layout.n_inner:] = b_scale * q
    exact = kernels.residual(nbr, off, diag, b, x.astype(np.float64))
    assert rel_err(got / pc.scale, exact) < (FP32_TOL if precision == "fp32" else FP16_TOL)


@pytest.mark.gpu
@pytest.mark.parametrize("precision", ["fp32", "fp16"])
def test_chebyshev_step(layout, precision):
    rng = np.random.default_rng(4)
    g, pc, (nbr, off, diag, _) = make_level(layout, precision)
    N = layout.n_nodes
    x, r, d = (rng.standard_normal((N, 3)).astype(np.float32) for _ in range(3))
    coef_d, coef_r = np.array([0.31, 0.52, 0.77]), np.array([1.9, 1.4, 1.1])
    g.set_x(x)
    g.r = g.upload_nodes(r)
    g.d[0] = g.upload_nodes(d)
    g.chebyshev(g.d[0], g.d[1], coef_d, coef_r)
    got = (g.read(g.x_current), g.read(g.r), g.read(g.d[1]))
    off_s, diag_s, _ = stored_system(pc, layout)
    # In fp16 the stored matrix is pc.scale * A: r and A d scale with it, so feed r scaled.
    s = pc.scale
    ref = kernels.chebyshev_step(nbr, off_s, diag_s, x.astype(np.float64), r.astype(np.float64),
                                 d.astype(np.float64), coef_d, coef_r)
    for name, a, b in zip("xrd", got, ref):
        assert rel_err(a, b) < FP32_TOL, name
    exact = kernels.chebyshev_step(nbr, off, diag, x.astype(np.float64), r / s, d.astype(np.float64), coef_d, coef_r)
    tol = FP32_TOL if precision == "fp32" else FP16_TOL
    assert rel_err(got[0], exact[0]) < tol
    assert rel_err(got[1] / s, exact[1]) < tol
    assert rel_err(got[2], exact[2]) < tol


@pytest.mark.gpu
def test_cheb_init(layout):
    rng = np.random.default_rng(5)
    g, pc, (_, _, diag, _) = make_level(layout)
    r = rng.standard_normal((layout.n_nodes, 3)).astype(np.float32)
    g.r = g.upload_nodes(r)
    theta = np.array([0.9, 1.0, 1.1])
    g.cheb_init(theta)
    assert rel_err(g.read(g.d[0]), r / diag / theta) < FP32_TOL


@pytest.mark.gpu
@pytest.mark.parametrize("shape", [(1, 32, 32), (1, 64, 4096), (3, 64, 64)])
def test_squared_norms_reduction(shape):
    """Multi-pass reduction (2 or 3 passes, several layers) vs kernels.squared_norms."""
    rng = np.random.default_rng(6)
    layers, h, w = shape
    data = rng.standard_normal((layers, h, w, 4)).astype(np.float32)
    n = layers * h * w
    lay = pack.Layout(n_inner=n, n_surface=0, block=32, per_row=w // 32, rows_inner=layers * h // 32,
                      rows_surface=0, rows_per_layer=h // 32, layers=layers)
    g = device.GPULevel(lay, np.full((n, 4), -1, dtype=np.int32))
    tex = runtime.float_texture(data)
    got = g.norm2(tex)
    ref = kernels.squared_norms(data.reshape(-1, 4)[:, :3].astype(np.float64))
    assert np.all(np.abs(got - ref) / ref < FP32_TOL)


@pytest.mark.gpu
@pytest.mark.parametrize("precision", ["fp32", "fp16"])
def test_shepard_upsample(layout, precision):
    rng = np.random.default_rng(7)
    n_c_in, n_c_s = 900, 300
    coarse = pack.plan_layout(n_c_in, n_c_s)
    gc, _, _ = make_level(layout, precision)  # any fine level
    Nc, Nf = n_c_in + n_c_s, layout.n_nodes
    idx = np.full((Nf, 8), -1, dtype=np.int32)
    idx[: layout.n_inner] = rng.integers(0, n_c_in, size=(layout.n_inner, 8))
    idx[layout.n_inner:, :4] = rng.integers(n_c_in, Nc, size=(layout.n_surface, 4))
    w = np.where(idx >= 0, rng.random(idx.shape), 0.0)
    w = (w / w.sum(axis=1, keepdims=True)).astype(np.float32)
    gc.set_transfer(coarse, idx, w)
    xc = rng.uniform(0.0, 5.0, size=(Nc, 3)).astype(np.float32)
    coarse_level = device.GPULevel(coarse, np.full((Nc, 4), -1, dtype=np.int32))
    coarse_level.set_x(xc)
    gc.upsample_from(coarse_level)
    got = gc.read(gc.x_current)
    wq = pack.quantize(w, precision)
    assert rel_err(got, kernels.shepard_upsample(idx, wq, xc.astype(np.float64))) < FP32_TOL
    exact = kernels.shepard_upsample(idx, w.astype(np.float64), xc.astype(np.float64))
    assert rel_err(got, exact) < (FP32_TOL if precision == "fp32" else FP16_TOL)


@pytest.mark.gpu
@pytest.mark.parametrize("precision", ["fp32", "fp16"])
def test_outgoing_partial_current(layout, precision):
    rng = np.random.default_rng(8)
    g, _, _ = make_level(layout, precision)
    q = rng.uniform(0.0, 1.0, size=(layout.n_surface, 3))
    qs = g.upload_q(q)
    phi = rng.uniform(0.0, 4.0, size=(layout.n_nodes, 3)).astype(np.float32)  # phi - 2q < 0 in places
    g.set_x(phi)
    fdr = 0.4405
    g.jplus(fdr)
    allj = g.read(g.r)
    assert np.all(allj[: layout.n_inner] == 0)  # inner texels: zero
    got = allj[layout.n_inner:]
    ref = kernels.outgoing_partial_current(phi[layout.n_inner:].astype(np.float64), qs, fdr)
    assert np.any(ref == 0) and rel_err(got, ref) < FP32_TOL
    exact = kernels.outgoing_partial_current(phi[layout.n_inner:].astype(np.float64), q, fdr)
    assert rel_err(got, exact) < (FP32_TOL if precision == "fp32" else FP16_TOL)


@pytest.mark.gpu
@pytest.mark.parametrize("view", ["normal", "random"])
def test_vertex_radiance(layout, view):
    """J+ gather over the vertex map and L_o = F_t J+ / (pi eta^2): DiffusionSolver.vertex_radiance's formula."""
    from translucency_addon.diffusion.radiance import outgoing_radiance

    rng = np.random.default_rng(9)
    g, _, _ = make_level(layout)
    n_v = 1234
    idx = rng.integers(0, layout.n_surface, size=(n_v, 6)).astype(np.int32)
    w = rng.random((n_v, 6)).astype(np.float32)
    w /= w.sum(axis=1, keepdims=True)
    vl = pack.plan_vertex_layout(n_v, width=256)
    vm = device.GPUVertexMap(vl, layout, idx, w)
    jp = rng.uniform(0.0, 2.0, size=(layout.n_nodes, 3)).astype(np.float32)
    jtex = g.upload_nodes(jp)
    eta = 1.3
    cos_o = None if view == "normal" else rng.uniform(-0.3, 1.0, size=n_v)
    got = vm.radiance(jtex, eta, 1.0 / (np.pi * eta * eta), cos_o)
    j_v = np.einsum("vk,vkc->vc", w.astype(np.float64), jp[layout.n_inner:].astype(np.float64)[idx])
    ref = outgoing_radiance(j_v, np.ones(n_v) if cos_o is None else cos_o, eta)
    if cos_o is not None:
        assert np.all(got[cos_o <= 0] == 0)
    assert rel_err(got, ref) < FP32_TOL


@pytest.mark.gpu
def test_scale_kernel(layout):
    rng = np.random.default_rng(10)
    g, _, _ = make_level(layout)
    x = rng.standard_normal((layout.n_nodes, 3)).astype(np.float32)
    g.set_x(x)
    g.scale_x(0.25)
    assert np.array_equal(g.read(g.x_current), x * np.float32(0.25))


@pytest.mark.gpu
def test_kernels_are_compiled_once():
    for name in runtime.KERNELS:
        runtime.shader(name)
    before = runtime.STATS["compiled"]
    for name in runtime.KERNELS:
        assert runtime.shader(name) is runtime.shader(name)
    assert runtime.STATS["compiled"] == before
