# SPDX-License-Identifier: GPL-3.0-or-later
"""The orders after the first of an object with several media (issue 30): each medium's once-scattered light
takes its own medium's rest (``frame.orders_after_the_first`` eq. 1, ``frame.rest_of_media``).

A 20 mm cube of a dark medium (albedo 0.2) holding a sphere of a bright one (albedo 0.9), both extinction
0.25 per mm, index 1.3, under a white world, each vertex seen along its normal.  The independent split: the
same object baked twice more with one medium's scattering turned off (sigma_s = 0, the same sigma_t: the
same chords, so the once-scattered light of each medium alone), each times eq. (5)'s ratio at its own albedo.
At the cube's albedo for all of it (what the frame did before), the sphere's light took a tenth of its rest.
Physics against Mitsuba: ``python -m bench.accuracy_inner_parts`` (the bottle of wine).
"""

from __future__ import annotations

import numpy as np
import pytest

SIGMA_T = 0.25
DARK, BRIGHT = 0.2, 0.9
ETA = 1.3


def _medium(albedo, name):
    from translucency_addon.scene.materials import Medium

    return Medium((SIGMA_T * (1 - albedo),) * 3, (SIGMA_T * albedo,) * 3, name)


def _dark(medium):
    """The same extinction, no scattering."""
    from translucency_addon.scene.materials import Medium

    sa, ss = (np.asarray(x, dtype=np.float64) for x in medium.arrays())
    return Medium(tuple(sa + ss), (0.0, 0.0, 0.0), medium.name + " (no scattering)")


def _single(outer, inner):
    """(evaluator, radiance along the normals) of single scattering baked for the cube of ``outer`` holding
    the sphere of ``inner``."""
    from translucency_addon.geometry import primitives
    from translucency_addon.scene.composite import CompositeObject, InnerPart
    from translucency_addon.scene.lights import Environment
    from translucency_addon.scene.materials import Material
    from translucency_addon.single_scattering import FrameEvaluator, SingleScatteringSettings, bake_single_scattering
    from translucency_addon.single_scattering.volume import voxelise_composite

    (V, F), (Vs, Fs) = primitives.cube_with_sphere(20.0, 8.0, n=8, subdivisions=2)
    comp = CompositeObject(V, F, Material(outer, eta=ETA), [InnerPart("sphere", Vs, Fs, "medium", inner)])
    vol = voxelise_composite(comp, resolution=24, mm_per_unit=1.0, fine=True, walls=False)
    data = bake_single_scattering(V, F, comp.material, None,
                                  SingleScatteringSettings(quality=24, n_dirs=64, n_samples=4000),
                                  mm_per_unit=1.0, volume=vol)
    ev = FrameEvaluator(data, V, F)
    return ev, ev.radiance([], Environment((1.0, 1.0, 1.0)), ETA, 1.0, None)


@pytest.fixture(scope="module")
def bakes():
    dark, bright = _medium(DARK, "dark"), _medium(BRIGHT, "bright")
    return {"both": _single(dark, bright), "outer": _single(dark, _dark(bright)),
            "inner": _single(_dark(dark), bright)}


def test_each_medium_takes_its_own_rest(bakes):
    from translucency_addon.diffusion.split import half_space_split
    from translucency_addon.frame import rest_of_media

    split = half_space_split(ETA)
    ev, L = bakes["both"]
    n = len(L)
    rho = {a: float(split.multiple_over_single(np.full((1, 3), a), np.ones(1))[0, 0]) for a in (DARK, BRIGHT)}
    L_outer, L_inner = bakes["outer"][1], bakes["inner"][1]
    np.testing.assert_allclose(L_outer + L_inner, L, rtol=1e-6, atol=1e-9 * L.max())  # linear in sigma_s
    assert L_inner.sum() > 0.2 * L.sum()  # the sphere's light is a good part of it: the test can tell
    expected = rho[DARK] * L_outer + rho[BRIGHT] * L_inner
    got = rest_of_media(ev.weighted_radiance, ev.rest_media(), np.full((n, 3), DARK), np.ones(n), split)
    # samples that straddle the interface mix the two albedos; with equal extinctions the mix is undone
    # exactly (frame.sample_rho; measured 2e-8 over the object, 7e-8 per lit vertex)
    assert abs(got.sum() / expected.sum() - 1) < 1e-3
    lit = expected[:, 0] > 0.2 * expected[:, 0].max()
    np.testing.assert_allclose(got[lit], expected[lit], rtol=1e-3)
    at_surface = rho[DARK] * L  # the surface's albedo for all of it
    assert at_surface.sum() < 0.6 * expected.sum()


def test_one_medium_keeps_the_surface_albedo(bakes):
    """A homogeneous object's samples all hold its albedo: the frame keeps the per-vertex form (exact, no
    second pass); two media are told apart."""
    import dataclasses

    from translucency_addon.single_scattering import FrameEvaluator

    ev = bakes["both"][0]
    a = ev.rest_media()
    assert a is not None and np.isclose(a.min(), DARK, atol=1e-6) and np.isclose(a.max(), BRIGHT, atol=1e-6)
    one = dataclasses.replace(ev.data, albedo=np.full_like(ev.data.albedo, DARK))
    assert FrameEvaluator(one, ev.V, ev.F).rest_media() is None
    assert FrameEvaluator(dataclasses.replace(ev.data, albedo=None), ev.V, ev.F).rest_media() is None


def test_the_samples_albedo_round_trips_and_corrupt_is_refused(bakes):
    from translucency_addon.errors import CacheError
    from translucency_addon.single_scattering.data import SingleScatteringData

    data = bakes["both"][0].data
    arrays = data.to_arrays()
    back = SingleScatteringData.from_arrays(arrays)
    np.testing.assert_allclose(back.albedo, data.albedo, rtol=1e-6)
    bad = dict(arrays)
    bad["ss/albedo"] = np.full_like(arrays["ss/albedo"], 1.5)
    with pytest.raises(CacheError, match="albedo"):
        SingleScatteringData.from_arrays(bad)
    bad["ss/albedo"] = arrays["ss/albedo"][:-1]
    with pytest.raises(CacheError, match="albedo"):
        SingleScatteringData.from_arrays(bad)


def test_the_voxel_number_maps_media_take_their_own_rest():
    """The map's chords cross both media; its kernel's scattering depth is each medium's sigma_s times its
    length (``voxel_number_map/transport.py`` eq. 4), so a medium's share is the map with the other's
    sigma_s turned off (the same extinction).  The weighted map is the two shares each times its own rest,
    under a world and a sun; one medium: no split."""
    from dataclasses import replace

    from translucency_addon.diffusion.split import half_space_split
    from translucency_addon.frame import rest_of_media
    from translucency_addon.geometry import primitives
    from translucency_addon.scene.composite import CompositeObject, InnerPart
    from translucency_addon.scene.lights import Environment, Light
    from translucency_addon.scene.materials import Material
    from translucency_addon.voxel_number_map import VNMSettings, VoxelNumberMapEvaluator, bake_voxel_number_map

    dark, bright = _medium(DARK, "dark"), _medium(BRIGHT, "bright")
    (V, F), (Vs, Fs) = primitives.cube_with_sphere(20.0, 8.0, n=8, subdivisions=2)
    comp = CompositeObject(V, F, Material(dark, eta=ETA), [InnerPart("sphere", Vs, Fs, "medium", bright)])
    vnm = bake_voxel_number_map(comp, VNMSettings(quality="draft"), mm_per_unit=1.0)
    lights = [Light("sun", irradiance=2.0, direction=(0.3, -0.2, -0.93))]
    world = Environment((0.5, 0.5, 0.5))
    view = ("ORTHO", (0.2, 0.3, 0.93))

    def evaluate(vnm_m, material):
        ev = VoxelNumberMapEvaluator(vnm_m, material, mm_per_unit=1.0)
        return ev, ev.radiance(lights, world, view)

    ev, L = evaluate(vnm, comp.material)
    a = ev.rest_media()
    assert a is not None and len(a) == 2
    # the sphere's scattering off (its row in the map's media), then the cube's
    part = np.asarray(vnm.component_sigma_s).copy()
    part_off = replace(vnm, component_sigma_a=np.asarray(vnm.component_sigma_a) + part, component_sigma_s=0 * part)
    L_outer = evaluate(part_off, comp.material)[1]
    L_inner = evaluate(vnm, Material(_dark(dark), eta=ETA))[1]
    assert L_inner.sum() > 0.1 * L.sum()
    np.testing.assert_allclose(L_outer + L_inner, L, rtol=1e-4, atol=1e-6 * L.max())  # linear in sigma_s
    split = half_space_split(ETA)
    rho = {x: float(split.multiple_over_single(np.full((1, 3), x), np.ones(1))[0, 0]) for x in (DARK, BRIGHT)}
    n = len(L)
    got = rest_of_media(ev.weighted_radiance, a, np.full((n, 3), DARK), np.ones(n), split)
    expected = rho[DARK] * L_outer + rho[BRIGHT] * L_inner
    np.testing.assert_allclose(got, expected, rtol=1e-3, atol=1e-6 * expected.max())
    assert (rho[DARK] * L).sum() < 0.6 * expected.sum()
    one = VoxelNumberMapEvaluator(vnm, Material(_medium(BRIGHT, "b2"), eta=ETA), mm_per_unit=1.0)
    assert one.rest_media() is None
