"""The Voxel Number Map's GLSL kernel (gpu_shaders/voxel_number_map.glsl) against its numpy twin.

The twin is ``transport.pair_kernel`` packed and multiplied with BLAS
(``PreparedKernel.product``), on the very same map, coefficients and source.
``PARITY_TOL = 1e-5`` (max |kernel - twin| / max |twin|; the kernel is float32
from fp16 lengths, the twin float32 packed with float64 geometry).  Measured on
llvmpipe: 7e-7.  Tests marked ``gpu`` need Blender's GPU backend (llvmpipe
here) and fail, never skip, without it; packing and fallback run without it.
"""

from __future__ import annotations

import numpy as np
import pytest

import gpu_shaders
from gpu_shaders import voxel_number_map as gv
from translucency_addon import errors
from translucency_addon.geometry import primitives
from translucency_addon.scene.composite import CompositeObject, InnerPart
from translucency_addon.scene.lights import Environment, Light
from translucency_addon.scene.materials import Material, Medium, preset
from translucency_addon.voxel_number_map import VNMSettings, VoxelNumberMapEvaluator, bake_voxel_number_map

PARITY_TOL = 1e-5
THIN = Medium((0.02, 0.03, 0.05), (0.05, 0.06, 0.08), "thin")


@pytest.fixture(scope="module")
def vnm():
    """A 20 mm cube with an opaque stone and a skin1 inclusion: two component media, blocked pairs."""
    (Vc, Fc), (Vs, Fs) = primitives.cube_with_sphere(20.0, 6.0, n=8, subdivisions=2)
    parts = [InnerPart("stone", Vs, Fs, "opaque"),
             InnerPart("jade", *primitives.icosphere(3.0, 2, (5.5, 5.5, 5.5)), "medium", preset("skin1"))]
    return bake_voxel_number_map(CompositeObject(Vc, Fc, Material(THIN), parts),
                                 VNMSettings(surface_voxels=300, env_directions=16))


def test_packing_is_exact_and_row_major(vnm):
    packed = gv.pack_map(vnm)
    lut = packed["lut"].reshape(-1, 4)[: vnm.lengths.shape[1]]
    assert np.array_equal(lut[:, :2], vnm.lengths.T.astype(np.float32))
    assert np.array_equal(lut[:, 3].astype(bool), np.unpackbits(vnm.blocked, count=len(lut)).astype(bool))
    assert np.all(lut[:, 2] == 0)
    assert np.array_equal(lut.astype(np.float16).astype(np.float32), lut)  # RGBA16F uploads without rounding
    ga = packed["geom_a"].reshape(-1, 4)[: vnm.n, :3].astype(np.float64)
    assert np.allclose(np.diff(ga, axis=0), np.diff(vnm.surface.position, axis=0), atol=1e-5)  # a shift only


def test_more_than_three_media_and_unavailable_gpu_fall_back(vnm, monkeypatch, capsys):
    monkeypatch.setattr(gpu_shaders, "available", lambda: (False, "no GPU context (test)"))
    tr, backend, msg = gv.make_transmission(vnm, prefer="AUTO")
    assert tr is None and backend == "CPU" and "no GPU context (test)" in msg
    with pytest.raises(errors.GPUUnavailable):
        gv.make_transmission(vnm, prefer="GPU")
    monkeypatch.setattr(gpu_shaders, "available", lambda: (True, "llvmpipe (LLVM 15.0.6, 256 bits)"))
    tr, backend, msg = gv.make_transmission(vnm, prefer="AUTO")
    assert tr is None and "software rasteriser" in msg
    monkeypatch.setattr(type(vnm), "n_components", property(lambda self: 4))
    with pytest.raises(errors.GraphTooLarge, match="4 component media"):
        gv.pack_map(vnm)


@pytest.mark.gpu
def test_kernel_matches_numpy_twin(vnm):
    tr, backend, _ = gv.make_transmission(vnm, prefer="GPU")
    try:
        mat = Material(THIN)
        cpu = VoxelNumberMapEvaluator(vnm, mat)
        gpu = VoxelNumberMapEvaluator(vnm, mat, transmission=tr)
        assert backend == "GPU" and gpu.backend == "GPU" and tr.uploads["material"] == 1
        x = np.random.default_rng(0).random((vnm.n, 3))
        ref = cpu.kernel.product(x)
        got = tr.product(x)
        assert np.abs(got - ref).max() / np.abs(ref).max() < PARITY_TOL
        lights = [Light("sun", irradiance=1000.0, direction=(-1.0, -0.3, -0.2)),
                  Light("point", intensity=20.0, position=(25.0, 5.0, 3.0))]
        env = Environment((0.2, 0.1, 0.05))
        a = cpu.radiance(lights, env, ("ORTHO", (-1.0, 0.2, 0.1)))
        b = gpu.radiance(lights, env, ("ORTHO", (-1.0, 0.2, 0.1)))
        assert a.max() > 0 and np.abs(a - b).max() / np.abs(a).max() < PARITY_TOL
        # another material re-uploads the coefficients only; the result follows it
        gpu.set_material(Material(preset("ketchup")))
        cpu.set_material(Material(preset("ketchup")))
        assert tr.uploads["bake"] == 1 and tr.uploads["material"] == 2
        a = cpu.radiance(lights, env)
        b = gpu.radiance(lights, env)
        assert np.abs(a - b).max() / np.abs(a).max() < PARITY_TOL
    finally:
        tr.free()
    with pytest.raises(errors.GPUUnavailable):
        tr.product(np.zeros((vnm.n, 3)))


@pytest.mark.gpu
def test_texture_limit_is_refused_in_numbers(vnm):
    with pytest.raises(errors.GraphTooLarge, match="surface voxels"):
        gv.GPUTransmission(vnm, max_texture_size=2)
    assert gv.free_all() == 0
