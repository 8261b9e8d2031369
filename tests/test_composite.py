"""Objects made of several parts (translucency_addon/scene/composite.py, voxelise_composite).

Every case of the issue's "defined behaviour" and "bad input" lists: nested and
touching parts, parts sticking out of the outer mesh, overlapping parts, a
cavity that reaches the outer surface, NaN / flat parts, a part given two
roles.  Each refusal is a TranslucencyError whose message names the part and
the problem; the voxel labels of the accepted cases are checked against the
geometry (analytic spheres and boxes).
"""

from __future__ import annotations

import numpy as np
import pytest

from translucency_addon.geometry import primitives
from translucency_addon.scene.composite import CompositeObject, InnerPart, parse_role
from translucency_addon.errors import MaterialError, MeshError, TranslucencyError
from translucency_addon.scene.materials import Material, Medium, preset
from translucency_addon.single_scattering.volume import voxelise_composite

THIN = Material(Medium((0.02, 0.02, 0.02), (0.05, 0.05, 0.05), "thin"))
BOX = primitives.box((2.0, 2.0, 2.0), n=4)


def sphere(r, c=(0.0, 0.0, 0.0)):
    return primitives.icosphere(r, 2, c)


def labels(parts, res=24):
    vol = voxelise_composite(CompositeObject(*BOX, THIN, parts), resolution=res)
    return vol, vol.labels


def centres(vol):
    return vol.centres().reshape(tuple(vol.shape) + (3,))


def test_nested_parts_innermost_wins_and_media_follow_labels():
    """A stone inside an air pocket inside the object: each voxel belongs to the innermost part."""
    vol, lab = labels([InnerPart("air", *sphere(0.7), "cavity"), InnerPart("stone", *sphere(0.3), "opaque")])
    r = np.linalg.norm(centres(vol), axis=-1)
    inside_box = np.all(np.abs(centres(vol)) < 1.0, axis=-1)
    clear = lambda a, b: (r > a + vol.h) & (r < b - vol.h)  # noqa: E731 -- away from the discretised surfaces
    assert np.all(lab.label[r < 0.3 - vol.h] == 3)  # stone
    assert np.all(lab.label[clear(0.3, 0.7)] == 2)  # air
    assert np.all(lab.label[(r > 0.7 + vol.h) & inside_box] == 1)  # outer medium
    assert lab.nested_in == {0: -1, 1: 0}
    assert np.all(vol.sigma_t[lab.label == 2] == 0)  # cavity: sigma_t = 0
    assert np.all(vol.blocked == (lab.label == 3))  # opaque: blocked (infinite extinction)
    assert np.all(vol.components[lab.label == 1, 0] == 1.0)


def test_touching_parts_keep_their_voxels_first_listed_wins_shared():
    """Two boxes sharing a face: no refusal, each keeps its side; a medium part gets its own component."""
    left = primitives.box((0.5, 1.0, 1.0), (-0.25, 0.0, 0.0), n=2)
    right = primitives.box((0.5, 1.0, 1.0), (0.25, 0.0, 0.0), n=2)
    vol, lab = labels([InnerPart("ketchup", *left, "medium", preset("ketchup")), InnerPart("stone", *right, "opaque")])
    x = centres(vol)[..., 0]
    core = np.all(np.abs(centres(vol)[..., 1:]) < 0.5 - vol.h, axis=-1)
    assert np.all(lab.label[core & (x < -vol.h) & (x > -0.5 + vol.h)] == 2)
    assert np.all(lab.label[core & (x > vol.h) & (x < 0.5 - vol.h)] == 3)
    k = preset("ketchup")
    assert np.allclose(vol.sigma_t[lab.label == 2], np.add(k.sigma_a, k.sigma_s), rtol=1e-6)
    assert vol.component_names[1].startswith("ketchup")


def test_part_sticking_out_is_clipped_with_a_warning_in_numbers():
    vol, lab = labels([InnerPart("jade", *sphere(0.5, (0.9, 0.0, 0.0)), "medium", preset("skin1"))])
    assert len(lab.warnings) == 1 and "'jade' sticks out" in lab.warnings[0] and "%" in lab.warnings[0]
    assert "clipped" in lab.warnings[0]
    assert not np.any((lab.label == 2) & ~np.all(np.abs(centres(vol)) < 1.0, axis=-1))


@pytest.mark.parametrize("parts, words", [
    ([InnerPart("a", *sphere(0.5, (0.2, 0, 0)), "cavity"), InnerPart("b", *sphere(0.5, (-0.2, 0, 0)), "opaque")],
     ["'a' and 'b' overlap", "neither contains the other"]),
    ([InnerPart("far", *sphere(0.3, (5.0, 0, 0)), "cavity")], ["'far' lies entirely outside"]),
    ([InnerPart("hole", *sphere(0.5, (0.9, 0, 0)), "cavity")], ["cavity 'hole' sticks out", "open"]),
    ([InnerPart("big", *sphere(3.0), "opaque")], ["'big' surrounds the outer mesh"]),
])
def test_refused_arrangements_name_the_parts(parts, words):
    with pytest.raises(MeshError) as err:
        labels(parts)
    for w in words:
        assert w in str(err.value)


def test_cavity_without_a_wall_is_refused_with_the_voxel_size():
    """Closed, but its wall is thinner than a voxel at this resolution: the message says what to raise."""
    with pytest.raises(MeshError) as err:
        labels([InnerPart("thin wall", *primitives.box((1.9, 1.9, 1.9), n=2), "cavity")], res=12)
    assert "'thin wall' touches the outer surface" in str(err.value) and "mm" in str(err.value)
    # the same cavity at a resolution that gives its wall a voxel is accepted
    vol, lab = labels([InnerPart("thin wall", *primitives.box((1.9, 1.9, 1.9), n=2), "cavity")], res=60)
    assert (lab.label == 2).sum() > 0


def test_bad_part_meshes_and_roles():
    V, F = sphere(0.3)
    Vn = V.copy()
    Vn[3, 1] = np.nan
    with pytest.raises(MeshError, match="inner part 'n': mesh has 1 vertices with NaN"):
        CompositeObject(*BOX, THIN, [InnerPart("n", Vn, F, "cavity")])
    with pytest.raises(MeshError, match="inner part 'f': mesh is flat"):
        CompositeObject(*BOX, THIN, [InnerPart("f", *primitives.box((0.5, 0.5, 0.0), n=2), "cavity")])
    with pytest.raises(TranslucencyError, match="two roles .cavity as 'x' and opaque as 'y'"):
        CompositeObject(*BOX, THIN, [InnerPart("x", V, F, "cavity"), InnerPart("y", V, F, "opaque")])
    with pytest.raises(TranslucencyError, match="two inner parts are named .x."):
        CompositeObject(*BOX, THIN, [InnerPart("x", V, F, "cavity"), InnerPart("x", *sphere(0.2), "opaque")])
    with pytest.raises(TranslucencyError, match="two roles: cavity and the medium 'marble'"):
        InnerPart("x", V, F, "cavity", preset("marble"))
    with pytest.raises(TranslucencyError, match="2 roles given"):
        parse_role("cavity+opaque", "x")
    with pytest.raises(MaterialError, match="inner part 'x': unknown material preset 'wine'"):
        parse_role("wine", "x")
    with pytest.raises(MaterialError, match="inner part 'm'.*negative"):
        InnerPart("m", V, F, "medium", Medium((-1.0, 0, 0), (1.0, 1.0, 1.0), "bad"))
    assert parse_role("Cavity", "x") == ("cavity", None)
    assert parse_role("opaque", "x") == ("opaque", None)
    assert parse_role("skin", "x") == ("medium", preset("skin1"))


def _open(V, F, cut):
    """The mesh without the triangles whose centre ``cut`` selects (each cap it removes is one hole)."""
    return V, F[~cut(V[F].mean(axis=1))]


@pytest.mark.parametrize("role", ["cavity", "opaque", "medium"])
def test_open_parts_are_refused_with_their_holes(role):
    """A part with holes has no inside (which voxels are its medium?): refused by name, with the number of
    boundary loops and their edges; the outer mesh's own holes stay a warning (the bake closes them)."""
    from translucency_addon.geometry.meshio import hole_loops

    V, F = _open(*sphere(0.5), lambda c: np.abs(c[:, 2]) > 0.45)  # both poles cut off: two holes
    loops = hole_loops(V, F)
    assert len(loops) == 2 and min(loops) >= 3
    medium = preset("marble") if role == "medium" else None
    with pytest.raises(MeshError) as err:
        CompositeObject(*BOX, THIN, [InnerPart("Stone", V, F, role, medium)])
    msg = str(err.value)
    assert "inner part 'Stone' is open: 2 holes" in msg
    assert f"{loops[0]} and {loops[1]} edges" in msg and "Fill Holes" in msg and "remove it" in msg
    one = _open(*sphere(0.5), lambda c: c[:, 2] > 0.45)
    with pytest.raises(MeshError, match=r"inner part 'Cap' is open: 1 hole \(boundary loop of \d+ edges\)"):
        CompositeObject(*BOX, THIN, [InnerPart("Cap", *one, role, medium)])
    # the same mesh unwelded (every triangle on its own vertices) is closed: accepted
    Vs, Fs = sphere(0.5)
    Vu = Vs[Fs].reshape(-1, 3)
    CompositeObject(*BOX, THIN, [InnerPart("Soup", Vu, np.arange(len(Vu)).reshape(-1, 3), role, medium)])
    # an open outer mesh with a closed part: a warning, as without parts
    CompositeObject(*_open(*BOX, lambda c: c[:, 2] > 0.99), THIN, [InnerPart("Ok", Vs, Fs, role, medium)])


@pytest.mark.parametrize("role", ["cavity", "opaque"])
def test_self_intersecting_parts_are_refused_with_the_crossing_pairs(role):
    """Two overlapping spheres in one mesh: its inside is not defined; the message counts the crossing pairs
    of triangles and gives one crossing point (on the circle where the spheres meet)."""
    from translucency_addon.geometry.meshio import self_intersections

    (V1, F1), (V2, F2) = sphere(0.4, (-0.15, 0.0, 0.0)), sphere(0.4, (0.15, 0.0, 0.0))
    V, F = np.concatenate([V1, V2]), np.concatenate([F1, F2 + len(V1)])
    pairs, point = self_intersections(V, F)
    assert pairs > 0 and abs(point[0]) < 0.02 and abs(np.linalg.norm(point[1:]) - np.sqrt(0.4**2 - 0.15**2)) < 0.03
    with pytest.raises(MeshError) as err:
        CompositeObject(*BOX, THIN, [InnerPart("Knot", V, F, role)])
    assert f"inner part 'Knot' intersects itself: {pairs} pairs of its triangles cross" in str(err.value)
    assert "remove it from the inner parts" in str(err.value)
    # closed, clean meshes of every kind used as parts give no crossing (flat strips of a cylinder included)
    for mesh in (sphere(0.4), primitives.box((0.5, 1.0, 1.0), n=2), primitives.torus(), primitives.uv_sphere(),
                 *primitives.bottle_with_wine().values()):
        assert self_intersections(*mesh) == (0, None)


def test_single_scattering_bakes_on_the_composite_volume_and_says_so():
    """The single-scattering pass can render an object with inner parts from the same voxels (the planner
    prefers it over the Voxel Number Map only when its bake knows the parts)."""
    from translucency_addon.single_scattering import SingleScatteringSettings, bake_single_scattering

    comp = CompositeObject(*BOX, THIN, [InnerPart("stone", *sphere(0.4), "opaque")])
    vol = voxelise_composite(comp, resolution=16, fine=True)
    data = bake_single_scattering(comp.V, comp.F, THIN, None,
                                  SingleScatteringSettings(quality=16, n_dirs=16, n_samples=200, sh_order=2),
                                  volume=vol)
    assert data.stats["inner_parts"] is True
    plain = bake_single_scattering(*BOX, THIN, None,
                                   SingleScatteringSettings(quality=16, n_dirs=16, n_samples=200, sh_order=2))
    assert plain.stats["inner_parts"] is False
