# SPDX-License-Identifier: GPL-3.0-or-later
"""The World as the engine's environment, bpy-free: equirect SH projection against closed forms, the HDRI
sun extraction on a synthetic map, the node evaluator (Mapping rotation rotates the SH, mixes, Light Path),
downsampling that keeps power, and the refusals (OSL, no output, missing pixels)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from translucency_addon.scene import environment_map as em
from translucency_addon.scene.sh import evaluate, fibonacci_directions, sh_basis
from translucency_addon.scene.world_nodes import (WorldGraph, WorldNode, WorldNodeError, euler_matrix,
                                                  evaluate as world_eval)

C00, C1, C20 = 0.282094791773878, 0.488602511902920, 0.315391565252520


def lobe_map(axis, h=256, w=512):
    """max(0, d . axis) as an equirect map (grey)."""
    d = em.equirect_directions(h, w)
    a = np.asarray(axis, dtype=np.float64)
    v = np.maximum(d @ (a / np.linalg.norm(a)), 0.0)
    return np.repeat(v[..., None], 3, axis=2).astype(np.float32)


def lobe_sh(axis):
    """Closed form of max(0, d . n): l=0: pi C00; l=1: (2 pi / 3) C1 (n_y, n_z, n_x); l=2 zonal (pi/2) C20 P2."""
    n = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    c = np.zeros(9)
    c[0] = math.pi * C00
    c[1:4] = 2 * math.pi / 3 * C1 * np.array([n[1], n[2], n[0]])
    # the l=2 band of a zonal function f about n: (4 pi / 5) f_2 Y_2m(n) with f_2 = int f P_2 / (2 pi)...
    # written through the addition theorem: coefficient_m = 2 pi int_0^1 mu P2(mu) dmu * Y_2m(n)
    c[4:9] = 2 * math.pi * (1.0 / 8.0) * sh_basis(n[None, :], 2)[0, 4:9]
    return c


def test_equirect_solid_angles_sum_to_the_sphere():
    for h, w in ((8, 16), (256, 512), (3, 7)):
        assert em.equirect_solid_angles(h, w).sum() * w == pytest.approx(4 * math.pi, rel=1e-12)


def test_constant_map_projects_to_its_closed_form():
    for h, tol in ((64, 2.5e-3), (512, 4e-5)):  # the midpoint rule in elevation: O(1/H^2)
        sh = em.project_equirect(np.full((h, 2 * h, 3), 2.5, np.float32))
        assert sh[0] == pytest.approx(np.full(3, 2.5 * math.sqrt(4 * math.pi)), rel=1e-12)
        assert np.abs(sh[1:]).max() < tol * sh[0, 0]


@pytest.mark.parametrize("axis", [(0, 0, 1), (1, 0, 0), (0.3, -0.5, 0.8)])
def test_cosine_lobe_projects_to_its_closed_form(axis):
    sh = em.project_equirect(lobe_map(axis))
    expected = lobe_sh(axis)
    np.testing.assert_allclose(sh[:, 0], expected, atol=2e-4 * math.pi)
    # the l=2 band is the part an order-1 projection would miss: it is there
    assert np.abs(expected[4:9]).max() > 0.1


def test_sample_equirect_returns_pixels_at_their_centres():
    rng = np.random.default_rng(1)
    img = rng.random((16, 32, 3)).astype(np.float32)
    d = em.equirect_directions(16, 32).reshape(-1, 3)
    np.testing.assert_allclose(em.sample_equirect(img, d), img.reshape(-1, 3), atol=1e-6)
    np.testing.assert_allclose(em.sample_equirect(img, d, "Closest"), img.reshape(-1, 3), atol=0)


def test_downsample_keeps_power_and_stays_in_bands():
    rng = np.random.default_rng(2)
    img = (rng.random((512, 1024, 4)) ** 8 * 100).astype(np.float32)
    small = em.downsample(img, max_width=128, band_rows=5)
    assert small.shape == (64, 128, 3) and small.dtype == np.float32
    def power(m):
        return np.sum(m[..., :3] * em.equirect_solid_angles(*m.shape[:2])[:, None, None], axis=(0, 1))

    np.testing.assert_allclose(power(small), power(img), rtol=1e-5)
    assert em.downsample(img[:, :100], max_width=128).shape == (512, 100, 3)


def sun_map(direction, diameter_deg, irradiance, sky=0.3, h=512, w=1024):
    d = em.equirect_directions(h, w)
    L = np.full((h, w, 3), sky)
    half = math.radians(diameter_deg / 2)
    disk = d @ direction >= math.cos(half)
    L[disk] += irradiance / (2 * math.pi * (1 - math.cos(half)))
    return L.astype(np.float32), disk


def test_sun_extraction_finds_direction_power_and_size():
    el, az = math.radians(35), math.radians(-120)
    true = np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
    img, disk = sun_map(true, 2.0, 50.0)
    sun, rest, why = em.extract_sun(img)
    assert sun is not None, why
    assert math.degrees(math.acos(min(1.0, float(np.dot(sun.direction, true))))) < 0.1
    # power: the map's own disk (its pixels hold what they hold) exactly, the analytic 50 W/m^2 to pixelisation
    omega = np.repeat(em.equirect_solid_angles(*img.shape[:2])[:, None], img.shape[1], axis=1)
    held = float(np.sum((img[disk, 0] - 0.3) * omega[disk]))
    assert sun.irradiance[0] == pytest.approx(held, rel=1e-4)
    assert sun.irradiance[0] == pytest.approx(50.0, rel=0.05)
    assert sun.angle_degrees == pytest.approx(2.0, rel=0.1)
    # the sun is out of the map: the rest is the sky, and sky + sun holds the map's power
    assert np.abs(rest - 0.3).max() < 1e-5
    sh_all, sh_rest = em.project_equirect(img), em.project_equirect(rest)
    assert sh_all[0, 0] - sh_rest[0, 0] == pytest.approx(sun.irradiance[0] * C00, rel=1e-4)


def test_smooth_sky_has_no_sun_and_says_why():
    sun, rest, why = em.extract_sun(lobe_map((0, 0, 1)) + 0.1)
    assert sun is None and "median" in why and rest is not None
    big, _ = sun_map(np.array([0, 0, 1.0]), 40.0, 50.0)
    sun, _, why = em.extract_sun(big)
    assert sun is None and "sr" in why


def test_rotate_sh_is_exact_for_band_limited_radiance():
    c = em.project_equirect(lobe_map((0.2, 0.4, 0.9)))
    R = euler_matrix((0.3, -0.7, 1.1))
    d = fibonacci_directions(200)
    np.testing.assert_allclose(evaluate(em.rotate_sh(c, R), d), evaluate(c, d @ R.T), atol=1e-10)


# --- the node evaluator --------------------------------------------------------------------------------

def env_graph(img, mapping=None, strength=1.0):
    nodes = {
        "Output": WorldNode("Output", "OUTPUT_WORLD", links={"Surface": ("Background", "Background")}),
        "Background": WorldNode("Background", "BACKGROUND", values={"Strength": strength},
                                links={"Color": ("Env", "Color")}),
        "Env": WorldNode("Env", "TEX_ENVIRONMENT", props={"interpolation": "Linear"}),
        "Coord": WorldNode("Coord", "TEX_COORD", props={"object": ""}),
    }
    if mapping is not None:
        kind, rot = mapping
        nodes["Mapping"] = WorldNode("Mapping", "MAPPING", props={"vector_type": kind},
                                     values={"Location": (0, 0, 0), "Rotation": rot, "Scale": (1, 1, 1)},
                                     links={"Vector": ("Coord", "Generated")})
        nodes["Env"].links["Vector"] = ("Mapping", "Vector")
    return WorldGraph(nodes=nodes, output="Output", images={"Env": img})


def project_world(graph, h=256, w=512):
    d = em.equirect_directions(h, w).reshape(-1, 3)
    return em.project_equirect(world_eval(graph, d).reshape(h, w, 3))


@pytest.mark.parametrize("kind", ["POINT", "TEXTURE"])
def test_mapping_rotation_rotates_the_world_and_its_sh(kind):
    axis = np.array([1.0, 0.0, 0.0])
    img = lobe_map(axis)
    rot = (0.0, 0.0, math.radians(90))
    sh = project_world(env_graph(img, (kind, rot), strength=2.0))
    # POINT looks the map up at R d, so the lobe turns to R^T a; TEXTURE at R^T d, so to R a
    R = euler_matrix(rot)
    turned = R.T @ axis if kind == "POINT" else R @ axis
    np.testing.assert_allclose(sh[:, 1], 2.0 * lobe_sh(turned), atol=3e-3)
    assert np.allclose(turned, [0, -1, 0] if kind == "POINT" else [0, 1, 0], atol=1e-12)
    # and against rotating the unrotated world's SH
    sh0 = project_world(env_graph(img, strength=2.0))
    np.testing.assert_allclose(sh, em.rotate_sh(sh0, R if kind == "POINT" else R.T), atol=3e-3)


def test_light_path_mix_takes_the_non_camera_branch_and_add_sums():
    img = np.full((8, 16, 3), 0.5, np.float32)
    g = env_graph(img)
    g.nodes["Backdrop"] = WorldNode("Backdrop", "BACKGROUND", values={"Color": (9, 9, 9, 1), "Strength": 1.0})
    g.nodes["Path"] = WorldNode("Path", "LIGHT_PATH")
    g.nodes["Mix"] = WorldNode("Mix", "MIX_SHADER", links={"Fac": ("Path", "Is Camera Ray"),
                                                           "Shader": ("Background", "Background"),
                                                           "Shader_001": ("Backdrop", "Background")})
    g.nodes["Fill"] = WorldNode("Fill", "BACKGROUND", values={"Color": (0.1, 0.2, 0.3, 1), "Strength": 2.0})
    g.nodes["Add"] = WorldNode("Add", "ADD_SHADER", links={"Shader": ("Mix", "Shader"),
                                                           "Shader_001": ("Fill", "Background")})
    g.nodes["Output"].links["Surface"] = ("Add", "Shader")
    L = world_eval(g, fibonacci_directions(50))
    np.testing.assert_allclose(L, np.broadcast_to([0.7, 0.9, 1.1], L.shape), atol=1e-6)
    g.nodes["Mix"].links["Fac"] = ("Path", "Is Diffuse Ray")
    with pytest.raises(WorldNodeError, match="depends on the bounce"):
        world_eval(g, fibonacci_directions(5))


def test_unevaluable_worlds_are_refused_with_the_node_named():
    g = env_graph(np.ones((4, 8, 3), np.float32))
    g.nodes["Script"] = WorldNode("Script", "SCRIPT")
    g.nodes["Background"].links["Color"] = ("Script", "Color")
    with pytest.raises(WorldNodeError, match="Script \\(OSL\\) node 'Script'"):
        world_eval(g, fibonacci_directions(5))
    g = env_graph(np.ones((4, 8, 3), np.float32))
    g.images.clear()  # an image that did not load has no pixels
    with pytest.raises(WorldNodeError, match="'Env' has no pixels"):
        world_eval(g, fibonacci_directions(5))
    g.output = "nothing"
    with pytest.raises(WorldNodeError, match="no World Output"):
        world_eval(g, fibonacci_directions(5))


def test_the_hdri_accuracy_section_survives_the_main_accuracy_bench(tmp_path):
    from bench.accuracy_text import kept_sections
    from bench.world import HEADING

    report = tmp_path / "accuracy.md"
    report.write_text("# Accuracy\n\n## Something the main bench rewrites\n\nold\n\n" + HEADING + "\nrow\n")
    assert kept_sections(report).strip() == (HEADING + "\nrow").strip()
