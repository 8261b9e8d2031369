"""The single-scattering GLSL kernel (gpu_shaders/single_scattering.glsl) against its numpy twin.

The twin is ``integrate_view_rays(...) * exit_factor(cos_o, eta)``
(translucency_addon.single_scattering.runtime) on the very same inputs: the
same bake, light term, view term and view rays.

Tolerances:

* ``ERF_TOL = 1e-6``: relative error of the kernel's erf (Maclaurin series
  below |x| = 0.5, Numerical Recipes' erfc above) against scipy, in float32.
  Measured on llvmpipe: 3.8e-7.
* ``PARITY_TOL = 1e-5``: max |kernel - twin| / max |twin| over rays and RGB
  (the kernel is float32, the twin float64).  Measured on llvmpipe: 6e-7 to
  8e-7 on the small sphere, 2e-6 on the bunny (bench).

Tests marked ``gpu`` need Blender's GPU backend (llvmpipe here) and fail,
never skip, without it; the packing and fallback tests run without it.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.special import erf

import gpu_shaders
from gpu_shaders import runtime as gpu_runtime
from gpu_shaders import single_scattering as gss
from translucency_addon import errors
from translucency_addon.geometry import primitives
from translucency_addon.scene.fields import FieldSpec, evaluate_field
from translucency_addon.scene.lights import Environment, Light
from translucency_addon.scene.materials import Material, material_from_preset, preset
from translucency_addon.geometry.meshio import vertex_normals
from translucency_addon.single_scattering import (CPUIntegrator, FrameEvaluator, SingleScatteringSettings,
                                                  bake_single_scattering, integrate_view_rays, light_term,
                                                  view_rays, view_term)
from translucency_addon.single_scattering.runtime import exit_factor

ERF_TOL = 1e-6
PARITY_TOL = 1e-5
MM = 10.0
ETA = 1.3


def rel_err(got, ref) -> float:
    ref = np.asarray(ref, dtype=np.float64)
    return float(np.abs(np.asarray(got, dtype=np.float64) - ref).max() / max(np.abs(ref).max(), 1e-300))


@pytest.fixture(scope="module")
def sphere():
    V, F = primitives.icosphere(1.0, 3)
    N = vertex_normals(V, F)
    data = bake_single_scattering(V, F, material_from_preset("marble"), None,
                                  SingleScatteringSettings(quality="draft", n_dirs=32, n_samples=2000), mm_per_unit=MM)
    return V, F, N, data


@pytest.fixture(scope="module")
def layered():
    """A heterogeneous box (marble / ketchup layers) under two lights and an environment: other SH, other grid."""
    V, F = primitives.box((1.0, 1.0, 1.0), n=4)
    N = vertex_normals(V, F)
    mat = Material(preset("marble"), preset("ketchup"), eta=ETA)
    spec = FieldSpec(kind="layers", scale=0.25)
    data = bake_single_scattering(V, F, mat, lambda p: evaluate_field(spec, p),
                                  SingleScatteringSettings(quality="draft", n_dirs=32, n_samples=800, sh_order=2),
                                  mm_per_unit=MM)
    return V, F, N, data


LIGHTS = [Light("point", intensity=50.0, position=(3.0, 0.5, 2.0)),
          Light("sun", irradiance=2.0, direction=(-0.3, -1.0, -0.2))]


def twin(data, rays, LT, VT):
    return integrate_view_rays(data, LT, rays.origins, rays.dirs, rays.t_exit, MM, view_term=VT) \
        * exit_factor(rays.cos_o, ETA)[:, None]


# ------------------------------------------------------------------ no GPU needed

def test_packing_is_row_major_and_exact():
    v = np.arange(3 * gss.TEX_W * 4 + 5, dtype=np.uint32) * 7919 + 3
    p = gss.pack_uints(v)
    assert p.shape == (1, gss.rows_for(len(v), 4), gss.TEX_W, 4)
    j = np.array([0, 1, 4, 4 * gss.TEX_W + 3, len(v) - 1])
    flat = p.reshape(-1, 4)
    assert np.array_equal(flat[j // 4, j % 4], v[j])
    assert flat.reshape(-1)[len(v):].max() == 0
    rows = np.random.default_rng(0).random((gss.TEX_W + 10, 4)).astype(np.float32)
    pr = gss.pack_rows(rows)
    assert np.array_equal(pr.reshape(-1, 4)[: len(rows)], rows)


def test_pack_bake_shifts_positions_consistently(sphere):
    _, _, _, data = sphere
    pk = gss.pack_bake(data)
    a = pk["samp_a"].reshape(-1, 4)[: data.n_samples]
    assert np.allclose(a[:, :3] + pk["shift"], data.centers, atol=1e-6)
    assert np.allclose(a[:, 3], data.alpha, rtol=1e-6)
    g = pk["grid"].reshape(-1, 4)
    assert np.allclose(g[0, :3] + pk["shift"], data.grid.origin, atol=1e-6)
    assert np.array_equal(g[1, :3], data.grid.dims.astype(np.float32))
    assert pk["sh_k"] == 25


def test_erf_formula_in_float32_is_accurate():
    x = np.linspace(-6.0, 6.0, 200001).astype(np.float32)
    ref = erf(x.astype(np.float64))
    got = gss.erf_approx_numpy(x)
    nz = ref != 0
    assert (np.abs(got - ref)[nz] / np.abs(ref[nz])).max() < ERF_TOL
    assert got[x == 0].item() == 0.0
    assert np.all(np.abs(got) <= 1.0)


def test_unavailable_gpu_falls_back_to_numpy_with_one_message(sphere, monkeypatch, capsys):
    _, _, _, data = sphere
    monkeypatch.setattr(gpu_shaders, "available", lambda: (False, "no GPU context (test)"))
    gss._LOGGED.clear()
    integ, backend, message = gss.make_integrator(data, "AUTO")
    assert backend == "CPU" and "no GPU context" in message and integ.backend == "CPU"
    gss.make_integrator(data, "AUTO")
    assert capsys.readouterr().out.count("no GPU context (test)") == 1  # logged once per session
    with pytest.raises(errors.GPUUnavailable):
        gss.make_integrator(data, "GPU")
    cpu, backend, _ = gss.make_integrator(data, "CPU")
    assert backend == "CPU" and isinstance(cpu, CPUIntegrator)


def test_software_rasteriser_prefers_numpy_in_auto(sphere, monkeypatch):
    _, _, _, data = sphere
    monkeypatch.setattr(gpu_shaders, "available", lambda: (True, "llvmpipe (LLVM 15.0.6, 256 bits)"))
    integ, backend, message = gss.make_integrator(data, "AUTO")
    assert backend == "CPU" and "software rasteriser" in message and integ.gpu is None


# ------------------------------------------------------------------ kernel parity (llvmpipe here)

@pytest.mark.gpu
def test_erf_on_the_gpu():
    x = np.concatenate([np.linspace(-6.0, 6.0, 100001), [0.0, 0.4999999, 0.5, 1e-6, -1e-6, 30.0]]).astype(np.float32)
    got = gss.erf_on_gpu(x).astype(np.float64)
    ref = erf(x.astype(np.float64))
    nz = ref != 0
    err = (np.abs(got - ref)[nz] / np.abs(ref[nz])).max()
    print(f"erf on the GPU: max relative error {err:.2e}")
    assert err < ERF_TOL


@pytest.mark.gpu
@pytest.mark.parametrize("view", ["camera", "ortho", "normals", "no-far-clip"])
def test_kernel_matches_numpy_twin(sphere, view):
    V, F, N, data = sphere
    LT = light_term(data, LIGHTS, Environment((0.2, 0.2, 0.25)), ETA, MM)
    cam = (0.5, 0.3, 4.0)
    if view == "camera":
        rays, VT = view_rays(V, F, N, camera_position=cam), view_term(data, camera_position=cam)
    elif view == "ortho":
        rays, VT = view_rays(V, F, N, view_dir=(0.2, -1.0, 0.3)), view_term(data, view_dir=(0.2, -1.0, 0.3))
    elif view == "normals":
        rays, VT = view_rays(V, F, N, view_dirs=N), None
    else:
        rays, VT = view_rays(V, F, N, camera_position=cam, far_clip=False), None
        assert np.all(np.isinf(rays.t_exit))
    ref = twin(data, rays, LT, VT)
    g = gss.GPUSingleScattering(data)
    got = g.integrate(LT, rays, view_term=VT, eta=ETA, mm_per_unit=MM)
    err = rel_err(got, ref)
    print(f"{view}: {len(rays.origins)} rays, max rel err {err:.2e}")
    assert ref.max() > 0 and err < PARITY_TOL
    assert gpu_runtime.STATS["dispatches"] > 0
    g.free()


@pytest.mark.gpu
def test_kernel_matches_twin_on_a_heterogeneous_box(layered):
    V, F, N, data = layered
    LT = light_term(data, LIGHTS, Environment((0.3, 0.3, 0.3)), ETA, MM)
    g = gss.GPUSingleScattering(data)
    for kw in ({"camera_position": (2.0, 1.5, 3.0)}, {"view_dirs": N}):
        rays = view_rays(V, F, N, **kw)
        VT = view_term(data, camera_position=kw["camera_position"]) if "camera_position" in kw else None
        err = rel_err(g.integrate(LT, rays, view_term=VT, eta=ETA, mm_per_unit=MM), twin(data, rays, LT, VT))
        print(f"layered box {sorted(kw)}: max rel err {err:.2e}")
        assert err < PARITY_TOL
    g.free()


@pytest.mark.gpu
def test_only_per_frame_inputs_are_uploaded(sphere):
    V, F, N, data = sphere
    g = gss.GPUSingleScattering(data)
    ev = FrameEvaluator(data, V, F, N, integrator=g)
    cpu = FrameEvaluator(data, V, F, N)
    view = ("PERSP", (0.5, 0.3, 4.0))
    a = ev.radiance(LIGHTS[:1], None, ETA, MM, view)
    assert dict(g.uploads) == {"bake": 1, "rays": 1, "frame": 1}
    moved = [Light("point", intensity=80.0, position=(-2.0, 1.0, 3.0))]
    b = ev.radiance(moved, None, ETA, MM, view)  # lights only: one small upload
    assert dict(g.uploads) == {"bake": 1, "rays": 1, "frame": 2}
    assert rel_err(b, cpu.radiance(moved, None, ETA, MM, view)) < PARITY_TOL
    assert np.abs(a - b).max() > 0
    ev.radiance(moved, None, ETA, MM, ("PERSP", (-3.0, 0.0, 2.0)))  # the camera moved: new rays
    assert dict(g.uploads) == {"bake": 1, "rays": 2, "frame": 3}
    g.free()
    with pytest.raises(errors.GPUUnavailable):
        g.run(np.zeros((data.n_samples, 3)), False, ETA, MM)


@pytest.mark.gpu
def test_a_frame_with_reflected_view_rays_matches_the_cpu_and_keeps_its_rays_resident():
    """A thin dark box (eta 1.3): the frame integrates its refracted view rays and the far side's reflections of
    them (single_scattering/view_reflection.py) on the GPU as on the CPU; once uploaded, every ray set stays
    resident, so a frame that moves only the lights uploads no rays."""
    from translucency_addon.scene.materials import Medium

    V, F = primitives.box((2.0, 2.0, 4.0), n=4)
    N = vertex_normals(V, F)
    data = bake_single_scattering(V, F, Material(Medium((0.8,) * 3, (0.2,) * 3, "dark"), None, ETA), None,
                                  SingleScatteringSettings(quality="draft", n_dirs=32, n_samples=2000), mm_per_unit=1.0)
    g = gss.GPUSingleScattering(data)
    ev, cpu = FrameEvaluator(data, V, F, N, integrator=g), FrameEvaluator(data, V, F, N)
    view = ("ORTHO", (-0.65, 0.0, 0.76))
    env = Environment((1.0, 1.0, 1.0))
    a = ev.radiance([], env, ETA, 1.0, view)
    n_sets = 1 + len(ev.reflected())
    assert n_sets >= 2 and dict(g.uploads)["rays"] == n_sets
    assert rel_err(a, cpu.radiance([], env, ETA, 1.0, view)) < PARITY_TOL
    b = ev.radiance(LIGHTS[:1], env, ETA, 1.0, view)
    assert dict(g.uploads)["rays"] == n_sets
    assert rel_err(b, cpu.radiance(LIGHTS[:1], env, ETA, 1.0, view)) < PARITY_TOL
    g.free()


@pytest.mark.gpu
def test_gpu_preference_and_texture_limits(sphere):
    _, _, _, data = sphere
    g, backend, message = gss.make_integrator(data, "GPU")
    assert backend == "GPU" and isinstance(g, gss.GPUSingleScattering) and message
    g.free()
    with pytest.raises(errors.GraphTooLarge):
        gss.make_integrator(data, "GPU", max_texture_size=1)
    assert gss.free_all() >= 0


@pytest.mark.gpu
def test_dispatch_failure_falls_back_per_call(sphere, monkeypatch):
    """No active GPU context at dispatch time (a render handler): that call runs in numpy, the GPU stays."""
    V, F, N, data = sphere
    auto = gss.AutoIntegrator(data, gss.GPUSingleScattering(data))
    rays = view_rays(V, F, N, camera_position=(0.5, 0.3, 4.0))
    LT = light_term(data, LIGHTS, None, ETA, MM)
    VT = view_term(data, camera_position=(0.5, 0.3, 4.0))
    ref = twin(data, rays, LT, VT)

    def no_context(*_a, **_k):
        raise SystemError("GPU functions for drawing are not available in background mode")

    monkeypatch.setattr(gpu_runtime, "dispatch", no_context)
    out = auto.integrate(LT, rays, view_term=VT, eta=ETA, mm_per_unit=MM)
    assert auto.last_backend == "CPU" and auto.gpu is not None and "no GPU context" in auto.message
    assert rel_err(out, ref) < 1e-12
    monkeypatch.undo()
    out = auto.integrate(LT, rays, view_term=VT, eta=ETA, mm_per_unit=MM)
    assert auto.last_backend == "GPU" and rel_err(out, ref) < PARITY_TOL

    def broken(*_a, **_k):
        raise RuntimeError("compiling GPU kernel single_scattering.glsl failed")

    monkeypatch.setattr(gpu_runtime, "dispatch", broken)
    auto.integrate(LT, rays, view_term=VT, eta=ETA, mm_per_unit=MM)
    assert auto.gpu is None and auto.backend == "CPU"  # a real failure drops the GPU for good
    auto.free()
