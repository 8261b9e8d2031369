"""Area lights as areas (issue 31, item 2): ``scene.lights.emitter_samples`` against closed forms.

On the axis of a uniform Lambertian disc of radius R (radiance L) at height h the irradiance on a plane
parallel to it is exactly ``pi L R^2 / (R^2 + h^2)``; the far-field point the engine made of an area light
gives ``pi L R^2 / h^2``, twice as much at h = R.  Off the axis and for rectangles the reference is the
defining integral by the midpoint rule on a 600 x 600 grid.  The Cycles check of the same conversion is in
tests/test_light_units.py."""

import dataclasses

import numpy as np
import pytest

from translucency_addon.errors import LightError
from translucency_addon.scene.lights import Light, emitter_samples, incident_flux, light_irradiance


def _irradiance(lights, points, normal):
    E = 0.0
    for light in emitter_samples(lights):
        e, to_light, _ = light_irradiance(light, points, 1000.0)  # 1 unit = 1 m
        E = E + e[:, 0] * np.maximum(to_light @ normal, 0.0)
    return E


def _integral(points, corners_uv, h, inside):
    """E at points (z = 0, facing +z) under an emitter in the plane z = h, facing -z, radiance 1."""
    m = 600
    u = (np.arange(m) + 0.5) / m
    U, V = np.meshgrid(u, u)
    (x0, x1), (y0, y1) = corners_uv
    X, Y = x0 + (x1 - x0) * U, y0 + (y1 - y0) * V
    keep = inside(X, Y)
    dA = (x1 - x0) * (y1 - y0) / m ** 2
    return np.array([np.sum(h * h / ((X[keep] - p[0]) ** 2 + (Y[keep] - p[1]) ** 2 + h * h) ** 2) * dA for p in points])


@pytest.mark.parametrize("h", [1.0, 2.0, 6.0])  # half, one and three diameters
def test_disc_on_its_axis_is_the_closed_form(h):
    R = 1.0
    disc = Light("area", intensity=np.pi * R * R, position=(0, 0, h), direction=(0, 0, -1), shape="ellipse",
                 edge_x=(2 * R, 0, 0), edge_y=(0, 2 * R, 0))
    exact = np.pi * R * R / (R * R + h * h)
    E = _irradiance([disc], np.zeros((1, 3)), np.array([0.0, 0.0, 1.0]))[0]
    assert E == pytest.approx(exact, rel=0.01)  # 16 patches: within 1 % from half the emitter's size
    far = _irradiance([dataclasses.replace(disc, samples=1)], np.zeros((1, 3)), np.array([0.0, 0.0, 1.0]))[0]
    assert far == pytest.approx(np.pi * R * R / (h * h), rel=1e-9)  # what it was: (R/h)^2 too bright


@pytest.mark.parametrize("shape", ["rectangle", "ellipse"])
def test_near_field_off_the_axis_is_the_integral(shape):
    a, b, h = 1.6, 0.9, 0.9  # the emitter larger than its height (h = 0.56 of its longer side)
    light = Light("area", intensity=a * b * (np.pi / 4 if shape == "ellipse" else 1.0), position=(0, 0, h),
                  direction=(0, 0, -1), shape=shape, edge_x=(a, 0, 0), edge_y=(0, b, 0))
    g = np.linspace(-1.2, 1.2, 9)
    P = np.array([(x, y, 0.0) for x in g for y in g])
    inside = (lambda X, Y: (2 * X / a) ** 2 + (2 * Y / b) ** 2 <= 1) if shape == "ellipse" else (
        lambda X, Y: np.ones_like(X, dtype=bool))
    ref = _integral(P, ((-a / 2, a / 2), (-b / 2, b / 2)), h, inside)
    E = _irradiance([light], P, np.array([0.0, 0.0, 1.0]))
    lit = ref > 0.1 * ref.max()
    err = np.abs(E[lit] / ref[lit] - 1.0)
    assert np.percentile(err, 95) < 0.01, np.percentile(err, 95)
    far = _irradiance([dataclasses.replace(light, samples=1)], P, np.array([0.0, 0.0, 1.0]))
    assert np.percentile(np.abs(far[lit] / ref[lit] - 1.0), 95) > 0.15  # the far-field point is not this


def test_patches_carry_the_power_and_shadows_fall_by_quadrant():
    light = Light("area", intensity=2.0, position=(0, 0, 5), direction=(0, 0, -1), edge_x=(1, 0, 0),
                  edge_y=(0, 0.5, 0), samples=12)
    patches = emitter_samples([light])
    assert len(patches) == 12 and sum(p.intensity for p in patches) == pytest.approx(2.0)
    assert emitter_samples([light]) == patches  # deterministic: a frame depends on the frame only
    assert emitter_samples([dataclasses.replace(light, samples=1)]) == [dataclasses.replace(light, samples=1)]
    # a blocker that hides the emitter's x > 0 half from the point halves q (a penumbra, not all or nothing)
    p, n = np.zeros((1, 3)), np.array([[0.0, 0.0, 1.0]])
    full = incident_flux([light], None, p, n, 1.3, 1000.0)
    half = incident_flux([light], None, p, n, 1.3, 1000.0,
                         visibility=lambda pts, nrm, to_l, dist: to_l[:, 0] <= 0)
    assert half[0, 0] == pytest.approx(0.5 * full[0, 0], rel=1e-6)


def test_bad_emitters_are_refused_by_name():
    with pytest.raises(LightError, match="shape must be"):
        Light("area", name="A", shape="triangle")
    with pytest.raises(LightError, match="samples must be"):
        Light("area", name="A", samples=0)
    with pytest.raises(LightError, match="edge_x"):
        Light("area", name="A", edge_x=(np.nan, 0, 0))


def test_a_sphere_light_is_the_point_above_the_horizon_and_soft_at_it():
    """A point light with a radius (Blender's Radius): unshadowed and above the horizon, exactly the point's
    q (eta 1: no Fresnel variation across the disc); past the terminator it still lights, up to the
    sphere's angular radius; a straight occluder edge gives a penumbra, not a step."""
    R, D = 1.0, 3.0
    sphere = Light("point", intensity=1.0, position=(0, 0, D), radius=R)
    point = dataclasses.replace(sphere, radius=0.0)
    P = np.array([[x, 0.0, 0.0] for x in (0.0, 1.0, 2.0, 5.0)])
    N = np.tile([0.0, 0.0, 1.0], (len(P), 1))
    np.testing.assert_allclose(incident_flux([sphere], None, P, N, 1.0, 1000.0),
                               incident_flux([point], None, P, N, 1.0, 1000.0), rtol=1e-12)
    # normals turned away from the centre by 90 + t degrees: in this plane the disc's points reach
    # atan(0.5 R / D) = 9.5 degrees past the horizon (the sphere's angular radius is 19.5)
    t = np.radians([-5.0, 4.0, 8.0, 25.0])
    Nh = np.stack([np.sin(np.pi / 2 + t), np.zeros_like(t), np.cos(np.pi / 2 + t)], axis=1)
    q = incident_flux([sphere], None, np.zeros((4, 3)), Nh, 1.0, 1000.0)[:, 0]
    qp = incident_flux([point], None, np.zeros((4, 3)), Nh, 1.0, 1000.0)[:, 0]
    assert qp[1] == qp[2] == qp[3] == 0.0 and q[1] > 0 and q[2] > 0 and q[3] == 0.0
    # an occluder covering x > c as seen from the receiver at the origin: the fraction of the disc's points
    xs = np.linspace(-1.0, 1.0, 9)
    frac = [incident_flux([sphere], None, np.zeros((1, 3)), np.array([[0.0, 0.0, 1.0]]), 1.0, 1000.0,
                          visibility=lambda pts, nrm, to_l, dist, c=c: to_l[:, 0] * D / to_l[:, 2] < c)[0, 0]
            for c in xs] / incident_flux([point], None, np.zeros((1, 3)), np.array([[0.0, 0.0, 1.0]]), 1.0,
                                         1000.0)[0, 0]
    assert frac[0] == 0.0 and frac[-1] == pytest.approx(1.0) and np.all(np.diff(frac) >= 0)
    assert 0.0 < frac[4] < 1.0  # the edge through the centre: a penumbra


def test_the_addon_passes_the_radius_and_the_edges(blender, addon):
    import bpy
    from mathutils import Matrix

    from translucency.ops import scene_inputs

    point = bpy.data.lights.new("p", 'POINT')
    point.energy, point.shadow_soft_size = 100.0, 0.2
    area = bpy.data.lights.new("a", 'AREA')
    area.energy, area.shape, area.size, area.size_y = 100.0, 'RECTANGLE', 0.4, 0.1
    to_object = Matrix.Diagonal((2.0, 2.0, 2.0, 1.0))  # the object half as large: lengths double
    lp = scene_inputs.convert_light(point, Matrix.Translation((0, 0, 1)), to_object, 1.0)
    la = scene_inputs.convert_light(area, Matrix.Translation((0, 0, 1)), to_object, 1.0)
    assert lp.radius == pytest.approx(0.4)
    assert la.shape == "rectangle" and np.linalg.norm(la.edge_x) == pytest.approx(0.8)
    assert np.linalg.norm(la.edge_y) == pytest.approx(0.2) and la.is_extended


def test_draft_renders_every_light_as_a_point():
    from translucency_addon.frame import lights_at_quality

    area = Light("area", intensity=1.0, edge_x=(1, 0, 0), edge_y=(0, 1, 0))
    sphere = Light("point", intensity=1.0, radius=0.5)
    sun = Light("sun", irradiance=1.0)
    draft = lights_at_quality((area, sphere, sun), "draft")
    assert [x.samples for x in draft[:2]] == [1, 1] and draft[2] is sun
    assert not draft[0].is_extended and len(emitter_samples([draft[0]])) == 1
    p, n = np.zeros((1, 3)), np.array([[0.0, 0.0, 1.0]])
    moved = dataclasses.replace(sphere, position=(0, 0, 3))
    blocked = lambda pts, nrm, to_l, dist: to_l[:, 0] < 0  # noqa: E731 - hides the disc's x > 0 half
    assert incident_flux(lights_at_quality((moved,), "draft"), None, p, n, 1.0, 1000.0, visibility=blocked)[0, 0] == 0
    assert incident_flux(lights_at_quality((moved,), "preview"), None, p, n, 1.0, 1000.0, visibility=blocked)[0, 0] > 0
    assert lights_at_quality((area, sphere), "Final") == (area, sphere)
