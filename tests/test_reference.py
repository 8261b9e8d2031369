# SPDX-License-Identifier: GPL-3.0-or-later
"""Quick tests of the independent reference renderer (bench/reference, docs/reference.md).

The whole file runs in well under a minute on 2 cores: tiny images, few samples.
"""

from __future__ import annotations

import numpy as np
import pytest

mi = pytest.importorskip("mitsuba")

from bench.reference import metrics  # noqa: E402
from bench.reference.mitsuba_ref import (  # noqa: E402
    DeltaLightError, cached_reference, environment_radiance, render_mask, render_reference, scene_dict)
from bench.reference.raster import rasterize  # noqa: E402
from bench.reference.scene import Camera, RefScene, sky_environment, sphere_env, uv_sphere  # noqa: E402
from translucency_addon.scene.fields import FieldSpec  # noqa: E402
from translucency_addon.scene.lights import Light  # noqa: E402
from translucency_addon.scene.materials import Material, Medium, material_from_preset, preset  # noqa: E402

WHITE = Material(Medium((0.0, 0.0, 0.0), (2.19, 2.62, 3.00), "white"), eta=1.3)


def tiny_sphere(material, image_res=12, spp=64, segments=16, **kw):
    return sphere_env(material, res=segments, image_res=image_res, spp=spp, **kw)


# --- scene and camera ------------------------------------------------------------------

def test_uv_sphere_is_closed_and_outward():
    V, F = uv_sphere(2.0, 24)
    p = V[F]
    volume = np.einsum("ij,ij->i", p[:, 0], np.cross(p[:, 1], p[:, 2])).sum() / 6.0
    assert 0.95 * (4 / 3) * np.pi * 8 < volume < (4 / 3) * np.pi * 8  # positive: outward
    edges = np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    assert np.all(counts == 2)  # closed, manifold


@pytest.mark.parametrize("camera", [
    Camera.orthographic((1.0, 2.0, 3.0), (0.3, -0.2, -1.0), (0, 1, 0), width=5.0),
    Camera.perspective((4.0, 3.0, 9.0), (0.0, 0.0, 0.0), (0, 1, 0), fov_deg=35.0),
])
def test_camera_project_inverts_pixel_rays(camera):
    res = (7, 5)
    o, d = camera.pixel_rays(res)
    col, row, _ = camera.project((o + 3.0 * d).reshape(-1, 3), res)
    J, I = np.meshgrid(np.arange(7), np.arange(5))
    np.testing.assert_allclose(col.reshape(5, 7), J + 0.5, atol=1e-9)
    np.testing.assert_allclose(row.reshape(5, 7), I + 0.5, atol=1e-9)
    r, u, f = camera.basis()
    assert o.shape == (5, 7, 3)
    # row 0 is the top: its rays lie further along `up` than the last row's
    assert ((o[0, 3] + d[0, 3]) - (o[-1, 3] + d[-1, 3])) @ u > 0


# --- the reference ----------------------------------------------------------------------

def test_white_furnace_returns_everything():
    """Albedo 1, eta 1.3, uniform environment 1: translucency + reflection == 1.

    With flat facets Mitsuba's plain render is 1 sample by sample (measured:
    1.0000 +- 0.0001 at 32x32, 1024 spp; docs/reference.md), so the
    tolerance is float round-off, not noise.  The translucency part alone
    must be 1 minus the Fresnel reflection (about 0.02-0.03 on the disc).
    """
    sc = tiny_sphere(WHITE, image_res=12, spp=64)
    res = render_reference(sc, batches=2)
    P = metrics.comparison_mask(res.mask)
    assert P.sum() >= 20
    full = res.full[P]
    assert abs(full.mean() - 1.0) < 2e-3, full.mean(axis=0)
    assert np.abs(full - 1.0).max() < 1e-2
    trans, refl = res.image[P].mean(), res.reflection[P].mean()
    assert 0.9 < trans < 0.995 and 0.005 < refl < 0.1, (trans, refl)
    # the noise estimate is real: Mitsuba's reflect-or-refract choice is random
    assert np.all(np.isfinite(res.stderr)) and res.stderr[P].mean() > 1e-4
    assert res.spp == 64 and res.batches == 2
    assert res.image.shape == (12, 12, 3) and res.mask.shape == (12, 12)


def test_absorbing_medium_is_darker_and_ordered_by_absorption():
    """The reference responds to the material: marble is bright, sigma_a x 200 is much darker."""
    marble = material_from_preset("marble")
    sa = np.asarray(preset("marble").sigma_a) * 200.0
    dark = Material(Medium(tuple(sa), preset("marble").sigma_s, "dark"), eta=1.3)
    a = render_reference(tiny_sphere(marble, image_res=10, spp=32), batches=2)
    b = render_reference(tiny_sphere(dark, image_res=10, spp=32), batches=2)
    P = metrics.comparison_mask(a.mask)
    assert 0.7 < a.image[P].mean() < 1.0
    assert b.image[P].mean() < 0.6 * a.image[P].mean()
    # blue absorbs most in marble: ordering of channels survives in the darker copy
    mb = b.image[P].mean(axis=0)
    assert mb[0] > mb[2]


def test_a_render_minus_another_cancels_sample_by_sample():
    """``render_reference(minus=...)``: the second scene is rendered with the same seeds, so every lane
    follows the same path in both until they differ.  A scene minus itself is exactly 0 with no noise
    (an independent subtraction would keep both renders' noise); a dark medium minus the same without
    scattering (same sigma_t) is its scattered light, the difference of the two plain renders, with less
    noise than their independent errors add up to."""
    dark = Material(Medium((0.8, 0.8, 0.8), (0.2, 0.2, 0.2), "dark"), eta=1.3)
    clear = Material(Medium((1.0, 1.0, 1.0), (0.0, 0.0, 0.0), "clear"), eta=1.3)
    scene = tiny_sphere(dark, image_res=8, spp=64)
    same = render_reference(scene, batches=2, minus=scene)
    assert np.all(same.image == 0.0) and np.all(same.stderr == 0.0) and same.reflection is None
    no_scattering = tiny_sphere(clear, image_res=8, spp=64)
    scattered = render_reference(scene, batches=2, minus=no_scattering)
    P = metrics.comparison_mask(scattered.mask)
    plain, unscattered = (render_reference(sc, batches=2, reflection_spp_factor=1) for sc in (scene, no_scattering))
    assert scattered.image[P].mean() > 0.0
    np.testing.assert_allclose(scattered.image[P].mean(), (plain.image - unscattered.image)[P].mean(), rtol=0.15)
    independent = np.sqrt(plain.stderr**2 + unscattered.stderr**2)
    assert scattered.stderr[P].mean() < 0.8 * independent[P].mean()


def test_heterogeneous_grid_reduces_to_its_media():
    """A mix with field 0 everywhere renders medium A; field 1 renders medium B (grid path)."""
    A, B = preset("marble"), preset("ketchup")
    homog = render_reference(tiny_sphere(Material(A), image_res=10, spp=32), batches=2)
    f0 = tiny_sphere(Material(A, B), image_res=10, spp=32, field=FieldSpec("uniform"))
    f0.grid_resolution = 16
    f1 = tiny_sphere(Material(A, B), image_res=10, spp=32, field=FieldSpec("sphere", scale=1e3))
    f1.grid_resolution = 16
    d = scene_dict(f0, 0)
    assert d["object"]["interior"]["type"] == "heterogeneous"
    r0, r1 = render_reference(f0, batches=2), render_reference(f1, batches=2)
    P = metrics.comparison_mask(homog.mask)
    diff = (r0.image[P] - homog.image[P]).mean(axis=0)
    se = np.sqrt(((r0.stderr[P] ** 2 + homog.stderr[P] ** 2)).sum(axis=0)) / P.sum()
    assert np.all(np.abs(diff) < 5 * se + 5e-3), (diff, se)
    # ketchup absorbs green and blue strongly
    assert r1.image[P][:, 1].mean() < 0.5 * r0.image[P][:, 1].mean()


def test_delta_lights_are_refused_not_rendered_black():
    """Behind a smooth dielectric a path tracer cannot reach a sun: refuse, never return black."""
    sc = tiny_sphere(material_from_preset("marble"), image_res=6, spp=4)
    sc.lights = [Light("sun", irradiance=3.0, direction=(0.0, 0.0, -1.0))]
    with pytest.raises(DeltaLightError, match="delta lights"):
        render_reference(sc)


def test_sky_environment_is_exact_sh_and_lights_the_right_side():
    """The SH sky goes through Mitsuba's envmap with the right orientation and scale."""
    s = np.array([1.0, 0.0, 0.0])
    env = sky_environment(to_light=s, lobe=2, irradiance=np.pi)
    d = np.array([[1.0, 0, 0], [-1.0, 0, 0], [0, 0, 1.0], [0, 1.0, 0]])
    L = environment_radiance(env, d)[:, 0]
    peak = np.pi / (17 * np.pi / 24)
    np.testing.assert_allclose(L, peak * ((1 + d @ s) / 2) ** 2, atol=1e-9)
    # constant sky (lobe 0, irradiance pi -> radiance 1) == the uniform environment: furnace again
    sc = tiny_sphere(WHITE, image_res=10, spp=16)
    sc.environment = sky_environment(lobe=0)
    res = render_reference(sc, batches=2)
    P = metrics.comparison_mask(res.mask)
    assert abs(res.full[P].mean() - 1.0) < 2e-3
    # a lobe towards +x (image right, camera looks down -z with +y up) lights the right half
    sc = tiny_sphere(material_from_preset("marble"), image_res=12, spp=16)
    sc.environment = env
    res = render_reference(sc, batches=2)
    img = np.where(metrics.comparison_mask(res.mask)[..., None], res.image, np.nan)
    right, left = np.nanmean(img[:, 7:]), np.nanmean(img[:, :5])
    assert right > 1.8 * left, (right, left)  # measured 2.5x at this size


def test_cached_reference_roundtrip(tmp_path):
    sc = tiny_sphere(WHITE, image_res=6, spp=8)
    a = cached_reference(sc, tmp_path, batches=2)
    b = cached_reference(sc, tmp_path, batches=2)
    assert len(list(tmp_path.glob("*.npz"))) == 1
    np.testing.assert_array_equal(a.image, b.image)
    np.testing.assert_array_equal(a.mask, b.mask)


# --- rasteriser -------------------------------------------------------------------------

def test_raster_constant_colour_is_exact_inside_mask():
    V, F = uv_sphere(1.0, 20)
    cam = Camera.orthographic((0, 0, 0), (0.2, -0.1, -1.0), (0, 1, 0), width=2.4)
    colour = np.array([0.25, 0.5, 0.75])
    r = rasterize(V, F, np.tile(colour, (len(V), 1)), cam, (40, 30), background=-1.0)
    assert r.mask.sum() > 300
    np.testing.assert_allclose(r.image[r.mask], np.broadcast_to(colour, (r.mask.sum(), 3)), rtol=0, atol=1e-12)
    assert np.all(r.image[~r.mask] == -1.0)
    # supersampling (box filter like the reference) keeps a constant exact and the centre mask
    r3 = rasterize(V, F, np.tile(colour, (len(V), 1)), cam, (40, 30), background=-1.0, supersample=3)
    assert np.array_equal(r3.mask, r.mask)
    np.testing.assert_allclose(r3.image[r.mask], np.broadcast_to(colour, (r.mask.sum(), 3)), rtol=0, atol=1e-12)


def test_raster_interpolates_linear_functions_exactly():
    """Barycentric interpolation reproduces a linear function of position (here x + 2y - z),
    perspective-correct for a perspective camera, and picks the nearest surface (z-buffer)."""
    V, F = uv_sphere(1.0, 24)
    vals = V @ np.array([1.0, 2.0, -1.0])
    for cam in (Camera.orthographic((0, 0, 0), (0, 0, -1), (0, 1, 0), width=2.2),
                Camera.perspective((0.5, 0.4, 4.0), (0, 0, 0), (0, 1, 0), fov_deg=40.0)):
        res = (33, 29)
        r = rasterize(V, F, vals, cam, res)
        o, d = cam.pixel_rays(res)
        if cam.kind == "orthographic":
            o = o - 10.0 * d
            depth_offset = 10.0
        else:
            depth_offset = 0.0
        _, _, f = cam.basis()
        # hit point from the rasteriser's view depth along each pixel ray
        t = np.where(r.mask, (r.depth + depth_offset) / (d @ f), 0.0)
        hit = o + t[..., None] * d
        expect = hit @ np.array([1.0, 2.0, -1.0])
        np.testing.assert_allclose(r.image[r.mask], expect[r.mask], atol=1e-9)
        # z-buffer: the nearest brute-force ray-triangle hit (Moller-Trumbore over all triangles)
        O, D = o.reshape(-1, 1, 3), d.reshape(-1, 1, 3)
        p0, e1, e2 = V[F][:, 0], V[F][:, 1] - V[F][:, 0], V[F][:, 2] - V[F][:, 0]
        pv = np.cross(D, e2)
        det = np.einsum("ptk,tk->pt", pv, e1)
        tv = O - p0
        with np.errstate(divide="ignore", invalid="ignore"):
            uu = np.einsum("ptk,ptk->pt", tv, pv) / det
            qv = np.cross(tv, e1)
            vv = np.einsum("ptk,ptk->pt", D * np.ones_like(qv), qv) / det
            tt = np.einsum("ptk,tk->pt", qv, e2) / det
        ok = (uu >= 0) & (vv >= 0) & (uu + vv <= 1) & (tt > 0)
        t_near = np.where(ok, tt, np.inf).min(axis=1).reshape(t.shape)
        both = np.isfinite(t_near) & r.mask
        assert (np.isfinite(t_near) ^ r.mask).sum() <= 2  # rays through a vertex or an edge may differ
        np.testing.assert_allclose(t[both], t_near[both], rtol=1e-9)


@pytest.mark.parametrize("segments,res", [(16, (24, 24)), (32, (40, 28))])
def test_raster_mask_matches_mitsuba_mask(segments, res):
    sc = sphere_env(material_from_preset("marble"), res=segments, image_res=res[0])
    sc.resolution = res
    r = rasterize(sc.V, sc.F, np.ones(len(sc.V)), sc.camera, sc.resolution)
    m = render_mask(sc)
    assert m.sum() > 100
    assert (m ^ r.mask).sum() <= 2  # measured: 0 on spheres, the bunny and spot (docs/reference.md)


def test_raster_mask_matches_mitsuba_on_an_asymmetric_mesh():
    """An L-shaped prism seen obliquely, non-square image: catches any flip or transposition."""
    prof = np.array([[0, 0], [3, 0], [3, 1], [1, 1], [1, 2.5], [0, 2.5]], dtype=float)
    n = len(prof)
    V = np.vstack([np.c_[prof, np.zeros(n)], np.c_[prof, np.ones(n)]])
    tri = [[0, 2, 1], [0, 3, 2], [0, 5, 3], [3, 5, 4]]  # bottom (z = 0), facing -z
    F = [t for t in tri] + [[a + n, b + n, c + n] for a, c, b in tri]
    for k in range(n):
        k1 = (k + 1) % n
        F += [[k, k1, k1 + n], [k, k1 + n, k + n]]
    F = np.asarray(F)
    p = V[F]
    assert np.einsum("ij,ij->i", p[:, 0], np.cross(p[:, 1], p[:, 2])).sum() > 0
    cam = Camera.orthographic((1.5, 1.25, 0.5), (0.3, -0.4, -1.0), (0, 1, 0), width=4.5)
    sc = RefScene(V, F, 5.0, material_from_preset("marble"), cam, resolution=(36, 24))
    r = rasterize(V, F, np.ones(len(V)), cam, sc.resolution)
    m = render_mask(sc)
    assert m.sum() > 150
    assert (m ^ r.mask).sum() <= 2
    assert not np.array_equal(m, m[::-1]) and not np.array_equal(m, m[:, ::-1])


# --- metrics ----------------------------------------------------------------------------

def test_metric_zero_for_identical_and_linear_in_scale():
    rng = np.random.default_rng(1)
    ref = rng.uniform(0.2, 1.0, (20, 30, 3))
    mask = np.zeros((20, 30), bool)
    mask[3:17, 4:26] = True
    assert metrics.relative_rms(ref, ref, mask).rel_rms == 0.0
    for k in (0.01, 0.1, -0.3):
        rep = metrics.relative_rms(ref * (1 + k), ref, mask)
        assert rep.rel_rms == pytest.approx(abs(k), rel=1e-12)
        assert rep.rel_rms_rgb == pytest.approx((abs(k),) * 3, rel=1e-12)
    # one channel wrong by 10 %: that channel 0.1, overall below
    ours = ref.copy()
    ours[..., 1] *= 1.1
    rep = metrics.relative_rms(ours, ref, mask)
    assert rep.rel_rms_rgb[0] == 0.0 and rep.rel_rms_rgb[1] == pytest.approx(0.1)
    assert 0.0 < rep.rel_rms < 0.1
    # erosion: 12 x 20 interior pixels of a 14 x 22 block
    assert rep.pixels == 12 * 20


def test_metric_ignores_silhouette_and_uses_both_masks():
    ref = np.ones((10, 10))
    mask = np.zeros((10, 10), bool)
    mask[2:8, 2:8] = True
    ours = ref.copy()
    ours[2, :] = 5.0  # the silhouette row: eroded away
    assert metrics.relative_rms(ours, ref, mask).rel_rms == 0.0
    ours[4, 4] = 2.0
    rep = metrics.relative_rms(ours, ref, mask)
    assert rep.rel_rms == pytest.approx(np.sqrt(1.0 / 16.0))
    smaller = mask.copy()
    smaller[2:4, :] = False
    assert metrics.relative_rms(ours, ref, mask, smaller).pixels == 2 * 4
    rep = metrics.relative_rms(ref, ref, mask, stderr=np.full((10, 10), 0.01))
    assert rep.noise_floor == pytest.approx(0.01)


def test_scanline_masks_outside():
    img = np.arange(30.0).reshape(5, 6)
    mask = np.zeros((5, 6), bool)
    mask[1:4, 1:5] = True
    idx, vals, err = metrics.scanline(img, mask)
    assert list(idx) == list(range(6)) and err is None
    assert np.isnan(vals[0]) and np.isnan(vals[5]) and vals[1] == 13.0
    _, vals, err = metrics.scanline(img, mask, col=2, stderr=np.ones((5, 6)))
    assert vals[2] == 14.0 and np.isnan(vals[0]) and np.isnan(err[4]) and err[1] == 1.0
