"""Single scattering (Bernabei et al.): bake, run time (eq. 3) and the brute-force reference.

The RBF/SH result is compared with an independent brute-force reference
(voxel marching along the view ray and a shadow ray per step, no RBFs, no SH),
and the reference itself with the closed form for a back-lit homogeneous
sphere.  Tolerances were set from measured errors plus a margin (the measured
values are in the comments; seeds 0..2 gave the same to +-0.01).

Scenes (object units = mm, mm_per_unit = 1):
* homogeneous sphere, R = 10 mm, sigma_t = 0.22..0.36 /mm, sun from +z, oblique view;
* the paper's layered cube (Fig. 7d): 20 mm cube, layers 2.5 mm thick mixing
  two media with a 6x density contrast, oblique sun and view;
* the paper's torus in a cube (Fig. 7a): 20 mm cube, opaque torus (R = 5, r = 2 mm)
  inside, point light behind the cube, camera in front.
"""

from __future__ import annotations

import io

import numpy as np
import pytest

from translucency_addon.geometry import meshio
from translucency_addon.errors import BakeCancelled, CacheError, MaterialError, MeshError
from translucency_addon.scene.fields import FieldSpec, evaluate_field
from translucency_addon.scene.fresnel import diffuse_reflectance_external, fresnel_transmittance
from translucency_addon.scene.lights import Environment, Light
from translucency_addon.scene.materials import Material, Medium
from translucency_addon.single_scattering import (
    STAGES, SampleGrid, SingleScatteringData, SingleScatteringSettings, bake_single_scattering, integrate_view_rays,
    light_term, ray_sample_pairs, reference_vertices, render_vertices, view_rays, view_term, voxelise)
from translucency_addon.single_scattering import optical_depth as od
from translucency_addon.single_scattering import shapes
from translucency_addon.single_scattering.sampling import gaussian_matrix
from translucency_addon.single_scattering.volume import trilinear

# Relative RMS error over the visible vertices (all channels), RBF/SH vs reference.
TOL_SPHERE = 0.12  # measured 0.096 .. 0.098 (seeds 0..2)
TOL_LAYERS = 0.36  # measured 0.248 (0.272 .. 0.303 with straight view rays)
TOL_TORUS = 0.58  # measured 0.478 .. 0.483 (order-4 SH cannot hold the torus's sharp shadow)

BASE = SingleScatteringSettings(quality=32, n_dirs=128, n_samples=6000, sh_order=4, seed=0)


def rel_rms(L, ref):
    return float(np.sqrt(((L - ref) ** 2).sum() / (ref**2).sum()))


class Scene:
    def __init__(self, V, F, material, field, lights, view, blockers=(), env=None):
        self.V, self.F = V, F
        self.N = meshio.vertex_normals(V, F)
        self.material, self.field, self.lights, self.view = material, field, lights, view
        self.blockers, self.env = blockers, env
        self._vol = None

    def bake(self, settings=BASE, **kw):
        data = bake_single_scattering(self.V, self.F, self.material, self.field, settings, blockers=self.blockers,
                                      keep_volume=True, volume=self._vol if settings.quality == BASE.quality else None,
                                      **kw)
        if settings.quality == BASE.quality:
            self._vol = data.volume
        return data

    def render(self, data, **kw):
        kw.setdefault("view_dir", self.view)
        return render_vertices(data, self.V, self.F, self.N, kw.pop("lights", self.lights), kw.pop("env", self.env),
                               self.material, **kw)

    def reference(self, volume, **kw):
        kw.setdefault("view_dir", self.view)
        return reference_vertices(volume, self.V, self.F, self.N, kw.pop("lights", self.lights),
                                  kw.pop("env", self.env), self.material.eta, **kw)


def sphere_scene():
    V, F = shapes.uv_sphere(10.0, 24, 48)
    mat = Material(Medium((0.02, 0.04, 0.06), (0.2, 0.25, 0.3)), eta=1.3)
    view = np.array([1.0, 0.3, -0.2])
    return Scene(V, F, mat, None, [Light("sun", irradiance=1.0, direction=(0, 0, -1))], view / np.linalg.norm(view))


def layered_scene():
    V, F = shapes.box((20, 20, 20), n=16)
    mat = Material(Medium((0.01, 0.02, 0.03), (0.08, 0.1, 0.12)), Medium((0.05, 0.08, 0.1), (0.5, 0.6, 0.7)), eta=1.3)
    spec = FieldSpec("layers", scale=2.5, axis=0)
    view = np.array([-0.2, 0.5, -1.0])
    return Scene(V, F, mat, lambda p: evaluate_field(spec, p), [Light("sun", irradiance=1.0, direction=(-0.3, -0.2, -1.0))],
                 view / np.linalg.norm(view))


def torus_scene(with_torus=True):
    V, F = shapes.box((20, 20, 20), n=24)
    mat = Material(Medium((0.01, 0.015, 0.02), (0.08, 0.09, 0.1)), eta=1.3)
    blockers = [shapes.torus(5.0, 2.0, 48, 16)] if with_torus else ()
    # point light behind the cube (+z), camera in front (-z)
    return Scene(V, F, mat, None, [Light("point", intensity=0.16, position=(0.0, 0.0, 60.0))], np.array([0.0, 0.0, -1.0]),
                 blockers=blockers)


@pytest.fixture(scope="module")
def sphere():
    sc = sphere_scene()
    sc.data = sc.bake()
    sc.ref = sc.reference(sc.data.volume)
    return sc


@pytest.fixture(scope="module")
def layered():
    sc = layered_scene()
    sc.data = sc.bake()
    sc.ref = sc.reference(sc.data.volume)
    return sc


@pytest.fixture(scope="module")
def torus():
    sc = torus_scene()
    sc.data = sc.bake()
    sc.ref = sc.reference(sc.data.volume)
    return sc


# ----------------------------------------------------------------- reference


def test_reference_matches_closed_form_for_backlit_sphere():
    """Collinear back light and view through the centre: tau = 2 R sigma_t for every point of the ray."""
    R = 10.0
    V, F = shapes.uv_sphere(R, 24, 48)
    N = meshio.vertex_normals(V, F)
    sa, ss = np.array([0.02, 0.04, 0.06]), np.array([0.2, 0.25, 0.3])
    mat = Material(Medium(tuple(sa), tuple(ss)), eta=1.3)
    vol = voxelise(V, F, mat, None, resolution=48)
    pole = int(np.argmin(V[:, 2]))
    E = 2.0
    L = reference_vertices(vol, V, F, N, [Light("sun", irradiance=E, direction=(0, 0, -1))], None, 1.3,
                           view_dir=(0, 0, -1), vertices=[pole])[pole]
    f_in = 1.0 - diffuse_reflectance_external(1.3)
    exact = ss * 2 * R / (4 * np.pi) * f_in * E * np.exp(-2 * R * (sa + ss)) * fresnel_transmittance(1.0, 1.3) / 1.3**2
    # measured 0.5 % low (the voxel boundary of the sphere); 2 % allowed
    np.testing.assert_allclose(L, exact, rtol=0.02)


def test_optical_depth_lattice_matches_marching_and_converges():
    """tau(x, w) from the sheared lattice vs fine marching of the same trilinear field (2nd order)."""
    rng = np.random.default_rng(1)
    errs = []
    for n in (20, 40):
        shape = (n, n + 3, n - 2)
        h = 20.0 / n
        c = (np.stack(np.unravel_index(np.arange(np.prod(shape)), shape), 1) + 0.5) * h
        r = np.linalg.norm(c - 10, axis=1)
        S = (np.exp(-((r / 5) ** 2)) * (r < 9)).reshape(shape + (1,)).astype(np.float32)
        worst = 0.0
        for w in rng.normal(size=(5, 3)):
            w /= np.linalg.norm(w)
            tau = od.optical_depth(S, h, w)
            idx = rng.integers(0, np.prod(shape), 200)
            s = np.arange(0.01, 36, 0.02)  # midpoint rule to beyond the grid (diagonal < 36)
            pts = c[idx][:, None, :] + s[None, :, None] * w
            ref = trilinear(S, np.zeros(3), h, pts.reshape(-1, 3)).reshape(200, -1).sum(1) * 0.02
            worst = max(worst, np.abs(tau.reshape(-1)[idx] - ref).max() / ref.max())
        errs.append(worst)
    # measured 1.7 % and 0.47 %
    assert errs[1] < 0.01
    assert errs[1] < errs[0] / 3


# ----------------------------------------------------------- building blocks


def test_gaussian_ray_integral_matches_quadrature(sphere):
    data = sphere.data
    rng = np.random.default_rng(3)
    i = rng.choice(data.n_samples, 20, replace=False)
    b = data.centers[i]
    # rays passing near each sample, segments cutting the Gaussian at random places
    d = rng.normal(size=(20, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    o = b - 2.0 * data.support[i, None] * d + rng.normal(size=(20, 3)) * 0.3 * data.sigma[i, None]
    t1 = rng.uniform(0.5, 4.0, 20) * data.support[i]
    r, s, g = ray_sample_pairs(data, o, d, t1)
    t = np.linspace(0, 1, 20001)
    for k in range(20):
        sel = (r == k) & (s == i[k])
        assert sel.sum() <= 1
        x = o[k] + (t * t1[k])[:, None] * d[k]
        dist = np.linalg.norm(x - b[k], axis=1)
        f = data.weight[i[k]] * np.exp(-data.alpha[i[k]] * dist**2) * (dist < data.support[i[k]])
        quad = np.trapezoid(f, t * t1[k])
        got = g[sel].sum() if sel.any() else 0.0
        assert got == pytest.approx(quad, rel=2e-3, abs=1e-6 * data.weight[i[k]] * data.sigma[i[k]])


def test_grid_traversal_counts_every_pair_exactly_once(sphere):
    """Grid + ownership rule == brute force over all samples, for any cell size."""
    data = sphere.data
    rays = view_rays(sphere.V, sphere.F, sphere.N, view_dir=sphere.view)
    o, d, t1 = rays.origins[::3], rays.dirs[::3], rays.t_exit[::3]
    # brute force: every sample against every ray, truncated Gaussian integrated by erf
    from scipy.special import erf

    bo = data.centers[None, :, :] - o[:, None, :]
    m = np.einsum("rsk,rk->rs", bo, d)
    dp2 = np.maximum((bo**2).sum(-1) - m * m, 0)
    R2 = data.support[None] ** 2
    hc = np.sqrt(np.maximum(R2 - dp2, 0))
    ta = np.maximum(0, m - hc)
    tb = np.minimum(t1[:, None], m + hc)
    a = data.alpha[None]
    g = np.where((dp2 < R2) & (tb > ta), data.weight[None] * 0.5 * np.sqrt(np.pi / a) * np.exp(-a * dp2)
                 * (erf(np.sqrt(a) * (tb - m)) - erf(np.sqrt(a) * (ta - m))), 0.0)
    lt = np.random.default_rng(0).random((data.n_samples, 3))
    expect = g @ lt
    assert np.count_nonzero(g) > 20 * len(o)
    for factor in (0.4, 1.0, 3.0):
        data.grid = SampleGrid.build(data.centers, data.support, factor * np.median(data.support))
        got = integrate_view_rays(data, lt, o, d, t1, 1.0, view_term=np.ones((data.n_samples, 3)))
        np.testing.assert_allclose(got, expect, rtol=1e-9, atol=1e-12)
    data.grid = SampleGrid.build(data.centers, data.support, np.median(data.support))


def test_compiled_pair_sums_are_numpys_bit_for_bit(sphere):
    """The view rays' sums over their pairs (``pair_kernels``): with a view term and with the per-pair psi
    weights the cached pairs keep, the compiled pass adds the same products per ray in the same order."""
    from translucency_addon.single_scattering.runtime import _pair_kernels, all_ray_sample_pairs, pair_psi_weights

    if "error" in _pair_kernels():
        pytest.skip(f"numba cannot run here: {_pair_kernels()['error']}")
    data = sphere.data
    rays = view_rays(sphere.V, sphere.F, sphere.N, camera_position=(30.0, 5.0, -8.0))
    rng = np.random.default_rng(1)
    lt, vt = rng.random((data.n_samples, 3)), rng.random((data.n_samples, 3))
    pairs = all_ray_sample_pairs(data, rays.origins, rays.dirs, rays.t_exit)
    pw = pair_psi_weights(data, pairs, rays.dirs)
    assert len(pairs[0]) > 20 * len(rays.origins)
    for kw in ({"view_term": vt}, {"pair_weights": pw}):
        a, b = (integrate_view_rays(data, lt, rays.origins, rays.dirs, rays.t_exit, 1.0, pairs=pairs,
                                    compiled=c, **kw) for c in (False, True))
        assert np.count_nonzero(a.sum(1)) > 100
        np.testing.assert_array_equal(a, b)


def test_rbfs_are_a_partition_of_unity_inside(sphere):
    data = sphere.data
    rng = np.random.default_rng(5)
    p = rng.uniform(-10, 10, (20000, 3))
    p = p[np.linalg.norm(p, axis=1) < 9.0][:4000]
    S = gaussian_matrix(p, data.centers, data.sigma) @ data.weight
    # measured: mean 0.994, 5 .. 95 % = 0.87 .. 1.11
    assert abs(S.mean() - 1.0) < 0.03
    assert np.percentile(S, 5) > 0.8 and np.percentile(S, 95) < 1.2


def test_sampling_is_denser_where_divergence_is_high(sphere):
    """rho = |div T| peaks under the surface: samples there get smaller Poisson radii."""
    data = sphere.data
    r = np.linalg.norm(data.centers, axis=1)
    near, deep = data.poisson_radius[r > 8.5], data.poisson_radius[r < 5.0]
    assert near.mean() < 0.5 * deep.mean()  # measured 0.29
    assert data.poisson_radius.max() <= 4.0 * data.poisson_radius.min() * (1 + 1e-9)
    assert abs(data.n_samples - BASE.n_samples) <= 0.06 * BASE.n_samples


def test_per_sample_and_per_ray_view_psi_agree_for_orthographic_view(sphere):
    a = sphere.render(sphere.data)
    b = sphere.render(sphere.data, per_ray_psi=True)
    np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-12)


def test_cached_pairs_give_the_same_frame(sphere):
    rays = view_rays(sphere.V, sphere.F, sphere.N, camera_position=(30.0, 5.0, -8.0))
    a = sphere.render(sphere.data, view_dir=None, rays=rays)
    b = sphere.render(sphere.data, view_dir=None, rays=rays, cache_pairs=True)
    c = sphere.render(sphere.data, view_dir=None, rays=rays, cache_pairs=True)
    assert np.count_nonzero(a.sum(1)) > 100
    np.testing.assert_allclose(b, a, rtol=1e-12)
    np.testing.assert_allclose(c, a, rtol=1e-12)


# ------------------------------------------------------- against the reference


def test_sphere_matches_reference(sphere):
    L = sphere.render(sphere.data)
    vis = sphere.ref.sum(1) > 0
    assert vis.sum() > 300
    assert np.all((L.sum(1) > 0) == vis)
    assert rel_rms(L, sphere.ref) < TOL_SPHERE
    # measured total ratio 0.973 .. 0.991 per channel
    np.testing.assert_allclose(L.sum(0) / sphere.ref.sum(0), 1.0, atol=0.06)


def test_sphere_without_far_clip_matches_reference(sphere):
    """The paper's renderer integrates to infinity (no far-side cast); the reference can do the same."""
    L = sphere.render(sphere.data, far_clip=False)
    ref = sphere.reference(sphere.data.volume, far_clip=False)
    assert rel_rms(L, ref) < TOL_SPHERE
    # on a convex body the far-side clip changes little (only the Gaussian tails beyond the surface)
    assert rel_rms(L, sphere.render(sphere.data)) < 0.10  # measured 0.068


def test_layered_cube_matches_reference(layered):
    L = layered.render(layered.data)
    assert rel_rms(L, layered.ref) < TOL_LAYERS
    # measured 1.10 .. 1.12 with the view rays refracted (0.95 .. 1.02 straight, before runtime.refract_in): the
    # face seen at 80 degrees 1.14 .. 1.25, the main face 1.00 .. 1.04 (0.82 .. 0.88 straight); relative RMS 0.25
    # (0.27 straight)
    np.testing.assert_allclose(L.sum(0) / layered.ref.sum(0), 1.0, atol=0.16)


def test_torus_cube_matches_reference(torus):
    L = torus.render(torus.data)
    assert rel_rms(L, torus.ref) < TOL_TORUS
    ratio = L.sum(0) / torus.ref.sum(0)  # measured 1.13 / 1.20 / 1.28 (SH ringing lights the shadow)
    assert np.all(ratio > 0.95) and np.all(ratio < 1.45)


def test_environment_light_matches_reference(sphere):
    """Uniform + order-3 SH world: the SH dot product against marching 48 directions per step.

    (The reference with 48 directions is within 0.25 % of one with 300.)"""
    sh = np.zeros((16, 3))
    sh[2] = (0.4, 0.3, 0.2)  # brighter towards +z
    sh[15] = (0.1, 0.05, 0.0)  # a band-3 lobe
    env = Environment(radiance=(0.5, 0.5, 0.5), sh=sh)
    rng = np.random.default_rng(2)
    rays = view_rays(sphere.V, sphere.F, sphere.N, view_dir=sphere.view)
    pick = rng.choice(rays.vertices, 40, replace=False)
    L = sphere.render(sphere.data, lights=[], env=env)
    ref = sphere.reference(sphere.data.volume, lights=[], env=env, vertices=pick, env_dirs=48)
    err = rel_rms(L[pick], ref[pick])
    assert err < 0.12, err  # measured 0.080 .. 0.095


def test_error_falls_with_directions_samples_and_order(layered):
    """Layered cube: the error against the reference falls with n_dirs, N_s and the SH order."""
    ref = layered.ref
    e_dirs = [rel_rms(layered.render(layered.bake(SingleScatteringSettings(
        quality=32, n_dirs=n, n_samples=6000, sh_order=4))), ref) for n in (32, 128, 512)]
    e_samples = [rel_rms(layered.render(layered.bake(SingleScatteringSettings(
        quality=32, n_dirs=128, n_samples=n, sh_order=4))), ref) for n in (1000, 3000, 12000)]
    data = layered.data
    e_order = [rel_rms(layered.render(data.with_order(o)), ref) for o in (2, 3, 4)]
    print("dirs", e_dirs, "samples", e_samples, "order", e_order)
    # measured: dirs 0.266 / 0.248 / 0.235, samples 0.335 / 0.286 / 0.229, order 0.393 / 0.338 / 0.248 (view rays
    # refracted; straight: dirs 0.357 / 0.303 / 0.280, samples 0.374 / 0.325 / 0.276, order 0.451 / 0.365 / 0.303)
    assert e_dirs[0] > e_dirs[1] + 0.01 and e_dirs[2] < e_dirs[1]
    assert e_samples[0] > e_samples[1] + 0.02 and e_samples[1] > e_samples[2] + 0.02
    assert e_order[0] > e_order[1] + 0.04 and e_order[1] > e_order[2] + 0.04


# ------------------------------------------------------------- torus shadow


def test_torus_shadow_is_visible(torus):
    free = torus_scene(with_torus=False)
    data_free = free.bake()
    L = torus.render(torus.data).sum(1)
    L0 = free.render(data_free).sum(1)
    ref, ref0 = torus.ref.sum(1), free.reference(data_free.volume).sum(1)
    V = torus.V
    front = np.abs(V[:, 2] + 10.0) < 1e-9
    rxy = np.hypot(V[:, 0], V[:, 1])
    # the light at (0, 0, 60) projects the tube (r = 3 .. 7 at z = 0) onto the front face at r * 70 / 60
    shadow = front & (rxy > 4.0) & (rxy < 7.0)
    lit = front & ((rxy < 1.5) | (rxy > 9.0))
    assert shadow.sum() > 30 and lit.sum() > 20
    dark = L[shadow].mean() / L0[shadow].mean()
    ref_dark = ref[shadow].mean() / ref0[shadow].mean()
    print("shadow ratio", dark, "reference", ref_dark, "lit", L[lit].mean() / L0[lit].mean())
    assert ref_dark < 0.01  # the reference really has a full shadow there (measured 1e-15)
    assert dark < 0.25  # measured 0.11 (SH ringing leaks a little light into the shadow)
    assert 0.75 < L[lit].mean() / L0[lit].mean() < 1.3  # measured 0.98


# ------------------------------------------------------------ robustness


LIGHT_KINDS = [
    Light("point", intensity=0.1, position=(0, 30, 40)),
    Light("spot", intensity=0.2, position=(0, 0, -40), direction=(0, 0, 1), spot_size=0.6),
    Light("sun", irradiance=0.7, direction=(1, -1, 0.2), color=(1.0, 0.2, 0.1)),
    Light("area", intensity=0.3, position=(40, 0, 0), direction=(-1, 0, 0)),
]


@pytest.mark.parametrize("kind", [light.kind for light in LIGHT_KINDS])
def test_each_light_kind_matches_the_brute_force_reference(sphere, kind):
    """Each light kind alone against the independent brute-force integral of eq. 3 (reference_vertices).

    Measured rel. RMS: point 0.098, spot 0.097, sun 0.096, area 0.080 (TOL_SPHERE = 0.12).
    """
    light = next(l for l in LIGHT_KINDS if l.kind == kind)
    L = sphere.render(sphere.data, lights=[light], env=None)
    ref = sphere.reference(sphere.data.volume, lights=[light], env=None)
    assert ref.max() > 0  # the light reaches the visible side
    assert rel_rms(L, ref) < TOL_SPHERE, (kind, rel_rms(L, ref))


def test_light_kinds_add_up(sphere):
    """The four kinds together are the sum of each alone (eq. 3 is linear in the lights)."""
    alone = sum(sphere.render(sphere.data, lights=[light], env=None) for light in LIGHT_KINDS)
    together = sphere.render(sphere.data, lights=LIGHT_KINDS, env=None)
    np.testing.assert_allclose(together, alone, rtol=1e-10, atol=1e-14 * together.max())


def test_output_is_finite_and_non_negative_for_all_light_kinds(torus):
    lights = [
        Light("point", intensity=0.1, position=(0, 30, 40)),
        Light("spot", intensity=0.2, position=(0, 0, -40), direction=(0, 0, 1), spot_size=0.6),
        Light("sun", irradiance=0.7, direction=(1, -1, 0.2), color=(1.0, 0.2, 0.1)),
        Light("area", intensity=0.3, position=(40, 0, 0), direction=(-1, 0, 0)),
    ]
    env = Environment(radiance=(0.1, 0.2, 0.3))
    for kw in ({"view_dir": (0.3, -0.4, -1.0)}, {"view_dir": None, "camera_position": (15.0, 20.0, -35.0)}):
        L = torus.render(torus.data, lights=lights, env=env, **kw)
        assert np.all(np.isfinite(L)) and np.all(L >= 0) and L.max() > 0
    lt = light_term(torus.data, lights, env, 1.3, 1.0)
    assert np.all(np.isfinite(lt)) and np.all(lt >= 0)
    vt = view_term(torus.data, camera_position=(0, 0, -50))
    assert np.all((vt >= 0) & (vt <= 1))


def test_bad_input_raises_named_errors():
    V, F = shapes.uv_sphere(10.0, 8, 16)
    good = Material(Medium((0.02, 0.04, 0.06), (0.2, 0.25, 0.3)))
    s = SingleScatteringSettings(quality=16, n_dirs=16, n_samples=200)
    mix = Material(good.medium_a, Medium((0.1, 0.1, 0.1), (1.0, 1.0, 1.0)))
    with pytest.raises(MaterialError, match="NaN"):
        bake_single_scattering(V, F, mix, lambda p: np.full(len(p), np.nan), s)
    with pytest.raises(MaterialError, match="field"):
        bake_single_scattering(V, F, mix, None, s)

    class Negative:
        heterogeneous = False
        eta = 1.3

        def coefficients(self, values=None, n=None):
            return np.full((n, 3), -0.1), np.full((n, 3), 1.0)

    with pytest.raises(MaterialError, match="negative"):
        bake_single_scattering(V, F, Negative(), None, s)
    flat = V.copy()
    flat[:, 2] = 0.0
    with pytest.raises(MeshError):
        bake_single_scattering(flat, F, good, None, s)
    with pytest.raises(MeshError):
        bake_single_scattering(V, np.zeros((0, 3), dtype=np.int64), good, None, s)
    bad = V.copy()
    bad[3] = np.nan
    with pytest.raises(MeshError, match="NaN"):
        bake_single_scattering(bad, F, good, None, s)
    with pytest.raises(MeshError, match="mm_per_unit"):
        bake_single_scattering(V, F, good, None, s, mm_per_unit=-1.0)
    with pytest.raises(ValueError):
        SingleScatteringSettings(sh_order=7).validated()


def test_progress_reports_stages_and_cancels():
    V, F = shapes.uv_sphere(10.0, 8, 16)
    mat = Material(Medium((0.02, 0.04, 0.06), (0.2, 0.25, 0.3)))
    s = SingleScatteringSettings(quality=16, n_dirs=64, n_samples=300)
    seen = []
    bake_single_scattering(V, F, mat, None, s, progress=lambda f, name: seen.append((f, name)))
    fr = [f for f, _ in seen]
    assert fr == sorted(fr) and 0.0 <= fr[0] and fr[-1] == pytest.approx(1.0)
    assert [n for n, _ in STAGES] == list(dict.fromkeys(name for _, name in seen))
    assert sum(1 for _, name in seen if name == "ddod") >= 4  # checked inside the direction loop

    def cancel(f, name):
        if name == "ddod" and f > 0.2:
            raise BakeCancelled("cancelled by the user")

    with pytest.raises(BakeCancelled):
        bake_single_scattering(V, F, mat, None, s, progress=cancel)


def test_arrays_round_trip_through_npz(sphere):
    data = sphere.data
    arrays = data.to_arrays(prefix="ss/")
    assert all(k.startswith("ss/") for k in arrays)
    assert all(isinstance(v, np.ndarray) and v.dtype != object for v in arrays.values())
    buf = io.BytesIO()
    np.savez(buf, **arrays, **{"other/x": np.arange(3)})
    buf.seek(0)
    with np.load(buf, allow_pickle=False) as z:
        back = SingleScatteringData.from_arrays(dict(z), prefix="ss/")
    assert back.order == data.order and back.n_dirs == data.n_dirs and back.n_samples == data.n_samples
    np.testing.assert_allclose(sphere.render(back), sphere.render(data), rtol=1e-6)
    broken = dict(arrays)
    del broken["ss/sh"]
    with pytest.raises(CacheError, match="sh"):
        SingleScatteringData.from_arrays(broken)
    old = dict(arrays)
    old["ss/version"] = np.array([99])
    with pytest.raises(CacheError, match="version"):
        SingleScatteringData.from_arrays(old)
    wrong = dict(arrays)
    wrong["ss/cell_start"] = arrays["ss/cell_start"][:-1]
    with pytest.raises(CacheError):
        SingleScatteringData.from_arrays(wrong)
    k = data.kernel_arrays()
    assert k["samples"].shape == (data.n_samples, 8) and k["sh"].shape == (data.n_samples, 25, 4)
    assert k["cell_start"].dtype == np.uint32 and k["cell_start"][-1] == len(k["cell_items"])
