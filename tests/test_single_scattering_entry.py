"""The world's light enters through the critical cone (single_scattering/entry.py, issue 30 item 3): the
weights g of eq. 2 against their closed forms on a ball, and the once-scattered light of a dark sphere
against an analogue random walk is tests/test_dark_media.py's."""

from __future__ import annotations

import numpy as np
import pytest

from translucency_addon.geometry import primitives
from translucency_addon.scene import sh as shmod
from translucency_addon.scene.fresnel import fresnel_transmittance
from translucency_addon.single_scattering.entry import inside_transmittance, world_entry
from translucency_addon.single_scattering.runtime import entry_transmittance

ETA = 1.3


def test_inside_transmittance_is_fresnel_at_the_refracted_angle_and_zero_past_the_critical_one():
    mu_c = np.sqrt(1.0 - 1.0 / ETA**2)
    mu = np.array([1.0, 0.9, mu_c + 1e-6, mu_c - 1e-6, 0.3, 0.0])
    cos_out = np.sqrt(np.clip(1.0 - ETA**2 * (1.0 - mu**2), 0.0, 1.0))
    want = np.where(mu > mu_c, fresnel_transmittance(cos_out, ETA), 0.0)
    np.testing.assert_allclose(inside_transmittance(mu, ETA), want, rtol=1e-12)
    assert inside_transmittance(np.array([1.0]), ETA)[0] == pytest.approx(0.98298677, rel=1e-6)


def entry_weights(V, F, points, dirs, eta):
    return world_entry(V, F, points, dirs, eta)[0]


def test_entry_weights_on_a_ball():
    """At the centre every chord leaves along the normal: g = eta^2 T(1) (to the facets' tilt); just under
    the surface a direction along the tangent plane is past the critical angle (g = 0) and the outward
    normal gets eta^2 T(1); outside the surface, and without an interface, the straight model's F_in."""
    V, F = primitives.icosphere(5.0, 4)
    F_in = entry_transmittance(ETA)
    dirs = shmod.fibonacci_directions(64)
    g = entry_weights(V, F, np.zeros((1, 3)), dirs, ETA)[:, 0]
    np.testing.assert_allclose(g, ETA**2 * 0.98298677, rtol=0.01)
    near = np.array([[0.0, 0.0, 4.9]])
    tangent_and_normal = np.array([[1.0, 0.0, 0.05], [0.0, 0.0, 1.0]])
    tangent_and_normal /= np.linalg.norm(tangent_and_normal, axis=1, keepdims=True)
    g = entry_weights(V, F, near, tangent_and_normal, ETA)[:, 0]
    assert g[0] == 0.0 and g[1] == pytest.approx(ETA**2 * 0.98298677, rel=1e-3)
    g = entry_weights(V, F, np.array([[0.0, 0.0, 5.5]]), dirs, ETA)
    assert np.all(g == F_in)
    assert np.all(entry_weights(V, F, np.zeros((1, 3)), dirs, 1.0) == 1.0)
    # inward-wound faces: the same weights (the outward side comes from the signed volume).  To rounding, not
    # bit for bit: the normal ray meets the icosphere exactly at its pole vertex, shared by five facets, and
    # which of them the walk reports is a tie its last bits break (facet 175 for one winding, 226 for the other
    # on this machine; the same facet on the last session's, where this compared bit for bit), so the facets'
    # tilt makes the two differ by 4e-8
    g_flipped = entry_weights(V, F[:, ::-1], near, tangent_and_normal, ETA)[:, 0]
    np.testing.assert_allclose(g_flipped, entry_weights(V, F, near, tangent_and_normal, ETA)[:, 0], rtol=1e-6)


def test_data_of_format_1_still_loads_and_renders_with_straight_chords():
    """A cache written before sh_env (format 1) is read (its key is stale: single_scattering.cached puts the
    format in it, so the add-on asks for the seconds-long re-bake) and, until then, its world term is the
    straight model: F_in times psi's own SH."""
    from translucency_addon.scene.lights import Environment
    from translucency_addon.scene.materials import Material, Medium
    from translucency_addon.single_scattering import SingleScatteringData, SingleScatteringSettings, light_term
    from translucency_addon.single_scattering import bake_single_scattering

    V, F = primitives.icosphere(3.0, 2)
    material = Material(Medium((0.8,) * 3, (0.2,) * 3, "dark"), None, ETA)
    data = bake_single_scattering(V, F, material, None, SingleScatteringSettings(quality="draft", n_samples=500,
                                                                                   n_dirs=32))
    assert data.sh_env is not None and data.entry_eta == ETA
    env = Environment((1.0, 1.0, 1.0))
    arrays = data.to_arrays()
    arrays["ss/version"] = np.array([1])
    del arrays["ss/sh_env"]
    old = SingleScatteringData.from_arrays(arrays)
    assert old.sh_env is None
    want = old.sigma_s / (4 * np.pi) * entry_transmittance(ETA) * np.sqrt(4 * np.pi) * old.sh[:, 0, :]
    np.testing.assert_allclose(light_term(old, [], env, ETA), want, rtol=1e-6)
    np.testing.assert_allclose(light_term(data, [], env, ETA),
                               data.sigma_s / (4 * np.pi) * np.sqrt(4 * np.pi) * data.sh_env[:, 0, :], rtol=1e-6)
    # the add-on's eta is Blender's float32 (1.2999999523), a command line's "1.3": the same baked cone
    np.testing.assert_array_equal(light_term(data, [], env, float(np.float32(ETA))), light_term(data, [], env, ETA))


def test_the_world_is_looked_up_where_each_chords_light_comes_from():
    """w' of eq. 1: Snell's law at the point where the chord leaves (sin out = eta sin in, in the plane of
    the chord and the normal, on the outside); unchanged along the normal, past the critical angle and
    where the chord does not leave."""
    from translucency_addon.single_scattering.entry import WorldEntry

    V, F = primitives.icosphere(5.0, 5)
    entry = WorldEntry(V, F, np.array([[0.0, 0.0, 4.99], [0.0, 0.0, 6.0]]), ETA)
    for theta in (0.0, 0.3, 0.6, 1.0):  # 1.0 rad: past the critical angle (0.88 rad at eta 1.3)
        d = np.array([np.sin(theta), 0.0, np.cos(theta)])
        g, w = entry(d)
        n = np.array([0.0, 0.0, 1.0])  # the facet the chord leaves through, a few 1e-3 rad off the pole's
        sin_out = ETA * np.sin(theta)
        if sin_out < 1.0:
            np.testing.assert_allclose(w[0], [sin_out, 0.0, np.sqrt(1 - sin_out**2)], atol=0.02)
            assert g[0] > 0
        else:
            np.testing.assert_array_equal(w[0], d)
            assert g[0] == 0.0
        np.testing.assert_array_equal(w[1], d)  # outside the object: the straight model
        assert np.isclose(np.linalg.norm(w[0]), 1.0) and w[0] @ n >= 0
