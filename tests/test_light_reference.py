# SPDX-License-Identifier: GPL-3.0-or-later
"""Local lights against the cached path-traced references (issue 17, ``bench/light_scenes.py``).

The reference (Mitsuba 3) renders the marble sphere lit by a spherical area emitter; the engine lights
it with a point light of radiant intensity pi a^2 L [W/sr, a in metres] at the emitter's centre.  A
Draft solve is compared with the cached reference images: the bounds fail if the light's units were
off by a factor like pi (mean ratio 3.1 or 0.32), if the distance were taken in millimetres instead
of metres (x 1e-6), or if the inverse-square falloff were missing or wrong (the far scene has its
emitter 10x further away and 100x more intense, so that 1/r would make it 10x too bright, and the
near scene's own brightness falls by (18/42)^2 across the sphere).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from bench import light_scenes as LS
from bench.reference.scene import RefEmitter
from translucency_addon.scene.lights import light_irradiance


def _cached(name):
    from bench.accuracy_scenes import reference_dir
    from bench.reference.mitsuba_ref import scene_key

    sc = next(s for s in LS.reference_scenes() if s.name == name)
    path = reference_dir(False) / f"{sc.name}-{scene_key(sc, batches=LS.BATCHES)}.npz"
    assert path.exists(), (f"the cached reference {path.name} is missing: render it with "
                           f"`nice -n 15 .venv/bin/python -m bench.light_scenes {name}` (minutes) and commit it")
    return sc, LS.get_reference(sc)


def test_sphere_emitter_irradiance_is_the_point_lights():
    """Closed form: a uniform Lambertian sphere (radius a, radiance L) gives E = pi L (a/d)^2 cos at
    distance d wherever it lies wholly above the horizon; the counterpart point light must agree."""
    mm_per_unit = 12.0
    a, L = 0.5, 7.0  # object units, W/(m^2 sr)
    em = RefEmitter("sphere", (0.0, 0.0, 3.0), a, (L, 2 * L, 0.5 * L))
    light = em.engine_light(mm_per_unit)
    assert light.kind == "point"
    pts = np.array([[0.0, 0.0, 0.0], [0.4, -0.2, 1.0], [1.5, 0.0, 0.0]])
    E, to_light, _ = light_irradiance(light, pts, mm_per_unit)
    d = np.linalg.norm(np.asarray(em.position) - pts, axis=1)
    expected = np.pi * L * (a / d) ** 2  # on a plane facing the emitter; a/d is unit-free
    np.testing.assert_allclose(E[:, 0], expected, rtol=1e-12)
    np.testing.assert_allclose(E[:, 1] / E[:, 0], 2.0)
    # an area emitter: I = L A along the normal, A in m^2
    sq = RefEmitter("rectangle", (0.0, 0.0, 3.0), a, (L, L, L), direction=(0.0, 0.0, -1.0))
    area = sq.engine_light(mm_per_unit)
    E2, _, _ = light_irradiance(area, pts[:1], mm_per_unit)
    A_m2 = (2 * a * mm_per_unit * 1e-3) ** 2
    assert E2[0, 0] == pytest.approx(L * A_m2 / (3.0 * mm_per_unit * 1e-3) ** 2, rel=1e-12)


@pytest.fixture(scope="module")
def ev():
    from bench.accuracy_core import Evaluator

    return Evaluator(bake_cache=None, log=lambda *_: None)


def _draft(ev, scene):
    from bench.accuracy_lights import compare, render_ours

    img, mask, *_ = render_ours(ev, scene, "draft", 1e-5)
    return compare(img, mask, LS.get_reference(scene)), img, mask


def test_point_light_matches_the_spherical_emitter_near(ev):
    sc, ref = _cached("sphere_marble_near")
    c, img, mask = _draft(ev, sc)
    ratio = np.asarray(c["mean_ratio"])
    # measured (Preview, tol 1e-4): error 8.8 % against a noise floor of 6.3 %, mean ratio 0.975
    assert np.all(np.abs(ratio - 1.0) < 0.12), f"mean ours / reference {ratio}"
    assert c["err"] < 0.15, c
    # the sensitivity the bounds give: a factor pi in the units fails them
    from bench.accuracy_lights import compare

    for k in (math.pi, 1.0 / math.pi):
        wrong = compare(img * k, mask, ref)
        assert wrong["err"] > 0.5 and np.all(np.abs(np.asarray(wrong["mean_ratio"]) - 1.0) > 0.5)


def test_inverse_square_near_and_far(ev):
    """Far: 10x the distance, 10x the radius (100x the intensity): with 1/r^2 the same brightness."""
    near, _ = _cached("sphere_marble_near")
    far, _ = _cached("sphere_marble_far")
    cn, *_ = _draft(ev, near)
    cf, *_ = _draft(ev, far)
    rn, rf = np.asarray(cn["mean_ratio"]), np.asarray(cf["mean_ratio"])
    assert np.all(np.abs(rf - 1.0) < 0.12), f"far: mean ours / reference {rf}"
    assert cf["err"] < 0.2, cf
    assert np.all(np.abs(rn - 1.0) < 0.12)


def test_report_sections_survive_a_rewrite():
    """bench/accuracy.py rewrites docs/accuracy.md and keeps only KEPT_SECTIONS of the other benches."""
    from bench import accuracy_dark, accuracy_lights, accuracy_sun, cycles_alternative
    from bench.accuracy_text import KEPT_SECTIONS, kept_sections, replace_section

    for bench in (accuracy_lights, cycles_alternative, accuracy_dark, accuracy_sun):  # each writes its own section
        assert bench.HEADING in KEPT_SECTIONS, bench.__name__
    text = replace_section("# Accuracy\n\nbody\n", accuracy_lights.HEADING, "\nlights table\n")
    text = replace_section(text, cycles_alternative.HEADING, "\ncycles table\n")
    import tempfile
    from pathlib import Path

    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "accuracy.md"
        p.write_text(text)
        kept = kept_sections(p)
    assert "lights table" in kept and "cycles table" in kept


def test_the_readme_s_accuracy_section_keeps_what_other_benches_wrote_after_the_plot(tmp_path, monkeypatch):
    """bench/accuracy.py rewrites the README's headline table and its findings; the paragraphs after the plot
    (the progressive frames, the lamps: other benches' numbers) stay, and so do the other sections."""
    from bench import accuracy

    monkeypatch.setattr("bench.accuracy_report.headline_table", lambda b, head: "| new table |")
    monkeypatch.setattr("bench.accuracy_text.findings_headline", lambda b, head: ["new findings"])
    image = "![accuracy of the presets on every scene against time](docs/images/accuracy_presets.png)"
    readme = tmp_path / "README.md"
    readme.write_text(f"# X\n\n## Accuracy versus time\n\n| old table |\n\nold findings\n\n{image}\n\n"
                      "Under lamps: a paragraph of another bench.\n\n## Benchmarks\n\nrows\n")
    assert accuracy.update_readme(None, readme)
    text = readme.read_text()
    assert "| new table |" in text and "new findings" in text and "old" not in text
    assert "Under lamps: a paragraph of another bench." in text and text.index("Under lamps") > text.index(image)
    assert text.endswith("## Benchmarks\n\nrows\n")


def test_principled_base_color_inverts_the_albedo_fit():
    """Chiang et al. 2016 (g = 0): the Base Color found for marble's single-scattering albedo maps back to it."""
    from bench.cycles_alternative import base_color_for, chiang_alpha

    for alpha in (0.5, 0.9, 0.99, 2.19 / (2.19 + 0.0021)):
        A, clamped = base_color_for(alpha)
        assert not clamped and 0.0 < A < 1.0
        assert chiang_alpha(A) == pytest.approx(alpha, abs=1e-9)
    assert chiang_alpha(0.0) == pytest.approx(0.0, abs=1e-3)


def test_shaded_sphere_emits_only_into_its_cone():
    """The spot stand-in: the emitter inside a black shade lights the object through the opening, and
    nothing when the opening faces away (the shade mesh, its placement and its black BSDF)."""
    from bench import accuracy_scenes as S
    from bench.reference.mitsuba_ref import render_reference
    from bench.reference.scene import RefScene

    V, F, mpu = S.mesh("sphere")
    d = np.array([1.0, 0.0, 0.0])  # beside the object, out of the camera's frame
    means = []
    for facing in (-d, d):
        em = RefEmitter("shaded_sphere", tuple(3.0 * d), 0.5, (40.0, 40.0, 40.0), direction=tuple(facing),
                        cone_deg=60.0, shade_radius=1.2)
        sc = RefScene(V, F, mpu, S.material("skin1"), S.camera_for(V, (8, 8)), emitters=(em,), resolution=(8, 8),
                      spp=16, name="shaded")
        ref = render_reference(sc, batches=2, reflection_spp_factor=1)
        means.append(float(ref.full[ref.mask].mean()))
    lit, away = means
    assert lit > 0.01, means
    assert away == 0.0, means
