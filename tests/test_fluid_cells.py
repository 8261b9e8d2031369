"""Voronoi-fluid cells (Kang & Kim 2013 sec. 4.1, 5.1; issue 14): exact geometry, partition, bad input.

Every expected value here comes from outside the code under test: closed
forms (cubic and FCC lattices, two overlapping balls, a disk cut by lines) or
a brute-force count of which particle is nearest to sample points.
"""

from __future__ import annotations

import numpy as np
import pytest

from translucency_addon.errors import ParticleError
from translucency_addon.fluid import FluidSolver, build_cells, build_graph, prepare_particles, suggest_radius
from translucency_addon.fluid import cells as cells_mod, compiled_faces
from translucency_addon.fluid.disk_faces import clipped_disk
from translucency_addon.diffusion.graph import check_graph
from translucency_addon.scene.lights import Environment
from translucency_addon.scene.materials import material_from_preset

# The bound for lattices: exact up to rounding (measured ~1e-15 relative).
EXACT = 1e-9


@pytest.fixture(params=["compiled", "numpy"])
def method(request):
    """Both paths of the faces (cells.cell_path): numba's kernel and the numpy fallback."""
    if request.param == "compiled" and compiled_faces.available():
        pytest.fail(f"the compiled path must run in the test environment: {compiled_faces.available()}")
    return request.param


def lattice(n, s=1.0):
    g = np.stack(np.meshgrid(*[np.arange(n)] * 3, indexing="ij"), axis=-1).reshape(-1, 3)
    return g.astype(np.float64) * s


def fcc(n, a=1.0):
    base = lattice(n, a)
    shifts = np.array([[0, 0, 0], [0.5, 0.5, 0], [0.5, 0, 0.5], [0, 0.5, 0.5]]) * a
    return (base[:, None, :] + shifts[None]).reshape(-1, 3)


def interior(P, lo, hi):
    return np.all((P > lo) & (P < hi), axis=1)


@pytest.mark.parametrize("R", [0.87, 1.0, 1.4])
def test_cubic_lattice_cells_are_unit_cubes(R, method):
    """Interior cells of a cubic lattice (spacing 1) are unit cubes once R >= sqrt(3)/2: V = 1, the six
    face neighbours share faces of area 1, the diagonal neighbours share none, nothing is free surface."""
    P = lattice(6)
    cells = build_cells(P, R, method=method)
    inner = interior(P, 0.5, 4.5)
    assert np.abs(cells.volume[inner] - 1.0).max() < EXACT
    assert cells.sphere_area[inner].max() < EXACT
    both = inner[cells.face_i] & inner[cells.face_j]
    assert np.abs(cells.face_area[both] - 1.0).max() < EXACT
    assert np.allclose(cells.face_distance[both], 1.0)  # only face neighbours keep a face
    assert np.all(cells.n_faces[inner] == 6)


def test_fcc_lattice_cells_are_rhombic_dodecahedra(method):
    """FCC (cube a = 1): Voronoi cells are rhombic dodecahedra, V = a^3/4, 12 faces of area sqrt(2) a^2/8
    (the cells have 4-valent vertices, where several cutting lines meet)."""
    P = fcc(5)
    cells = build_cells(P, 0.6, method=method)  # farthest vertex at a/2
    inner = interior(P, 0.9, 3.6)
    assert inner.sum() > 50
    assert np.abs(cells.volume[inner] - 0.25).max() < EXACT
    both = inner[cells.face_i] & inner[cells.face_j]
    assert np.abs(cells.face_area[both] - np.sqrt(2) / 8).max() < EXACT
    assert np.all(cells.n_faces[inner] == 12)


def test_two_balls_closed_form(method):
    R, d = 1.0, 1.2
    h = d / 2
    cells = build_cells(np.array([[0.0, 0, 0], [d, 0, 0]]), R, method=method)
    cap = np.pi * (R - h) ** 2 * (2 * R + h) / 3
    assert np.allclose(cells.volume, 4 / 3 * np.pi * R**3 - cap, rtol=EXACT)
    assert np.allclose(cells.face_area, np.pi * (R * R - h * h), rtol=EXACT)
    assert np.allclose(cells.sphere_area, 2 * np.pi * R * (R + h), rtol=EXACT)
    assert np.allclose(cells.surface_vector, [[-np.pi * (R * R - h * h), 0, 0], [np.pi * (R * R - h * h), 0, 0]])


def test_clipped_disk_against_closed_forms():
    """A square of half-side a inside the disk: area 4 a^2, solid angle 4 asin(a^2/(a^2 + h^2)); half a disk;
    repeated lines count once."""
    R, h = 1.0, 0.5
    r = np.sqrt(R * R - h * h)
    for a in (0.4, r / np.sqrt(2)):  # inside, and corners exactly on the circle
        nx = np.array([1.0, -1, 0, 0, 1, 0])[:, None]
        ny = np.array([0.0, 0, 1, -1, 0, 1])[:, None]
        area, om = clipped_disk(np.array([r]), np.array([h]), R, nx, ny, np.full((6, 1), -a))
        assert abs(area[0] - 4 * a * a) < 1e-12 and abs(om[0] - 4 * np.arcsin(a * a / (a * a + h * h))) < 1e-12
    area, om = clipped_disk(np.array([r]), np.array([h]), R, np.ones((1, 1)), np.zeros((1, 1)), np.zeros((1, 1)))
    assert abs(area[0] - np.pi * r * r / 2) < 1e-12 and abs(om[0] - np.pi * (1 - h / R)) < 1e-12


@pytest.mark.parametrize("R", [0.87, 1.4])
def test_lattice_ties_do_not_depend_on_the_particle_order(R, method):
    """A shuffled cubic lattice: four particles on one circle give one Voronoi edge to four triangles, and
    which of them keeps it depends on the particle indices; the cells are the same unit cubes in any order."""
    P = lattice(6)[np.random.default_rng(3).permutation(216)]
    cells = build_cells(P, R, method=method)
    inner = interior(P, 0.5, 4.5)
    assert np.abs(cells.volume[inner] - 1.0).max() < EXACT
    both = inner[cells.face_i] & inner[cells.face_j]
    assert np.abs(cells.face_area[both] - 1.0).max() < EXACT and np.all(cells.n_faces[inner] == 6)


def _fingerprint_sets():
    rng = np.random.default_rng(2024)
    out = [("jittered lattice", lattice(6) + rng.uniform(-0.2, 0.2, (216, 3)), 1.0),
           ("uniform random", rng.random((500, 3)) * 8.0, 1.3)]
    half = lattice(6)
    right = half[:, 0] > 2.5
    half[right] += rng.uniform(-0.1, 0.1, (int(right.sum()), 3))
    out.append(("half exact lattice", half, 0.95))
    out.append(("fcc, lightly jittered", fcc(4) + rng.uniform(-0.02, 0.02, (256, 3)), 0.62))
    out.append(("clustered", np.concatenate([rng.normal(0, 1.0, (300, 3)), rng.normal(3.0, 0.6, (200, 3))]), 0.7))
    return out


def _fingerprint(c):
    """Order-free sums with fixed pseudo-random weights per cell and per face (i, j)."""
    k = np.arange(c.n_cells)
    wv = np.cos(0.37 * k + 0.1)
    wf = np.sin(0.7 * c.face_i + 1.3 * c.face_j + 0.2)
    return [len(c.face_i), c.volume.sum(), (c.volume * wv).sum(), (c.sphere_area * wv).sum(),
            (c.surface_vector * np.stack([wv, wv ** 2, -wv], 1)).sum(), c.face_area.sum(), (c.face_area * wf).sum(),
            (c.face_distance * wf).sum()]


# Computed by the per-face clipping that the triangle-based one replaced (commit 32de383, build_cells at HEAD
# then): every face clipped by all its lines, O(m^2) per face.  The rewrite must give the same cells to rounding.
FINGERPRINTS = {
    "jittered lattice": [1256, 313.356342388183, -4.40654593728183, -6.19992448169297, 2.09204694401106,
                         629.128211905231, 2.58711679886639, -19.1457084259082],
    "uniform random": [3218, 831.48843269179, 13.7819600265953, 21.9072188817717, 23.0080733399024,
                       1684.60367476141, -22.3899116985916, 1.78552263872375],
    "half exact lattice": [966, 295.463481380849, -5.28751671062787, -9.43415336056685, 0.327604329031939,
                           622.848609275459, 3.07234146886322, -8.65262418992615],
    "fcc, lightly jittered": [1455, 93.8049870891456, -0.514631760310779, -1.77649703449604, -0.6040119563307,
                              282.820758725811, -5.62333120605787, -24.0975810787224],
    "clustered": [3200, 140.907809667882, 4.48818701038379, 10.9744254023246, -6.90360970999348,
                  408.433752672099, 6.8052093647902, 50.0192085422128],
}


@pytest.mark.parametrize("method, chunk", [("compiled", None), ("numpy", None), ("numpy", 2000)])
def test_cells_match_the_per_face_clipping_they_replaced(method, chunk):
    """Five particle sets (jittered and exact lattices, uniform and clustered random) against fingerprints of
    the previous exact implementation; ``chunk=2000`` splits the numpy path's work into 10-30 chunks, so
    that most faces take lines decided in earlier chunks."""
    for name, P, R in _fingerprint_sets():
        cells = build_cells(P, R, method=method) if chunk is None else build_cells(P, R, chunk=chunk, method=method)
        assert cells.path == method
        got, want = _fingerprint(cells), FINGERPRINTS[name]
        assert got[0] == want[0], name
        scale = np.array([1.0, abs(want[1]), *[abs(want[1])] * 4, abs(want[5]), abs(want[5])])
        assert np.all(np.abs(np.subtract(got, want)) <= 1e-9 * scale), (name, got, want)


def test_cells_do_not_depend_on_the_particle_order(method):
    """Shuffled input: the same cells, permuted (the engine sorts the particles spatially inside)."""
    P = _jittered(5, 0.2, 9)
    perm = np.random.default_rng(4).permutation(len(P))
    a, b = build_cells(P, 1.0, method=method), build_cells(P[perm], 1.0, method=method)
    assert np.allclose(b.volume, a.volume[perm], rtol=1e-12) and np.allclose(b.surface_vector, a.surface_vector[perm])
    inv = np.argsort(perm)
    fa = dict(zip(zip(a.face_i.tolist(), a.face_j.tolist()), a.face_area))
    fb = {tuple(sorted((int(perm[i]), int(perm[j])))): s for i, j, s in zip(b.face_i, b.face_j, b.face_area)}
    assert fa.keys() == fb.keys() and max(abs(fa[k] - fb[k]) for k in fa) < 1e-12
    assert len(inv) == len(P)


def test_graph_numbers_its_nodes_in_space_order_whatever_the_input_order():
    """Shuffled particles (a particle system emits in random order): consecutive inner nodes of the graph are
    neighbours in space (the sparse products of the solve then stay in cache), and every particle keeps its
    cell."""
    P = _jittered(8, 0.1, 5)
    perm = np.random.default_rng(6).permutation(len(P))
    g = build_graph(build_cells(P[perm], 1.0))
    step = np.linalg.norm(np.diff(g.position[:g.n_inner], axis=0), axis=1)
    assert np.median(step) < 1.5 and np.median(np.linalg.norm(np.diff(P[perm], axis=0), axis=1)) > 3.0
    assert np.array_equal(np.sort(g.cell), np.arange(len(P))) and np.allclose(g.position[:g.n_inner], P[perm][g.cell])


def _jittered(n, jitter, seed):
    rng = np.random.default_rng(seed)
    P = lattice(n)
    return P + rng.uniform(-jitter, jitter, P.shape)


def test_cells_partition_the_union_of_balls_and_match_a_nearest_particle_count(method):
    """Sample points: each in the fluid (within R of a particle) belongs to its nearest particle.  The
    fraction of samples per cell estimates V_i; the sum estimates the union of balls."""
    from scipy.spatial import cKDTree

    P = _jittered(4, 0.25, 0)
    R = 0.95
    cells = build_cells(P, R, method=method)
    rng = np.random.default_rng(1)
    lo, hi = P.min(axis=0) - R, P.max(axis=0) + R
    n = 1_500_000
    X = lo + (hi - lo) * rng.random((n, 3))
    dist, who = cKDTree(P).query(X)
    inside = dist <= R
    box = float(np.prod(hi - lo))
    union = box * inside.mean()
    se = box * np.sqrt(inside.mean() * (1 - inside.mean()) / n)
    assert abs(cells.volume.sum() - union) < 4 * se, (cells.volume.sum(), union, se)  # the partition
    per = box * np.bincount(who[inside], minlength=len(P)) / n
    se_cell = box * np.sqrt(per / box / n)
    assert np.all(np.abs(cells.volume - per) < 5 * se_cell + 1e-3), np.abs(cells.volume - per).max()


def test_face_areas_match_a_brute_force_count_on_the_bisecting_plane(method):
    """Points on the plane between i and j that lie within R and have no nearer particle than i and j."""
    from scipy.spatial import cKDTree

    P = _jittered(4, 0.3, 2)
    R = 1.0
    cells = build_cells(P, R, method=method)
    tree = cKDTree(P)
    rng = np.random.default_rng(3)
    picks = rng.choice(len(cells.face_i), 12, replace=False)
    for f in picks:
        i, j = cells.face_i[f], cells.face_j[f]
        n = (P[j] - P[i]) / np.linalg.norm(P[j] - P[i])
        e1 = np.cross(n, [0.3, 0.5, 0.8])
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(n, e1)
        g = (np.arange(600) + 0.5) / 600 * 2 * R - R
        U, W = np.meshgrid(g, g)
        X = 0.5 * (P[i] + P[j]) + U.reshape(-1, 1) * e1 + W.reshape(-1, 1) * e2
        d2, who = tree.query(X, k=2)
        ok = (np.linalg.norm(X - P[i], axis=1) <= R) & np.isin(who[:, 0], (i, j)) & np.isin(who[:, 1], (i, j))
        est = ok.sum() * (2 * R / 600) ** 2
        assert abs(cells.face_area[f] - est) < 0.01 * R * R + 0.01 * est, (f, cells.face_area[f], est)


def test_surface_cells_of_a_lattice_block_face_outward_with_their_flat_area(method):
    """A 6^3 block, R = 1: the 152 outer cells are the surface; a cell in the middle of a side has its
    surface face's vector area along the side's normal with length 1 (the flat projection)."""
    P = lattice(6)
    cells = build_cells(P, 1.0, method=method)
    graph = build_graph(cells)
    check_graph(graph, "fluid")
    assert graph.n_inner == 216 and graph.n_surface == 216 - 64
    side = np.nonzero((P[:, 2] == 5) & interior(P[:, :2], 0.5, 4.5))[0]
    assert np.allclose(cells.surface_vector[side], [0, 0, 1], atol=EXACT)
    s = np.isin(graph.cell[graph.surface_cell], side)
    assert s.sum() == 16 and np.allclose(graph.area[s], 1.0)
    h = graph.edge_length[graph.n_inner:, 0][s]
    assert np.all((h > 0.5) & (h < 1.0))  # the mean height of the cap above the particle
    # the smoothed normal (light pass, output) of the four central cells, whose neighbours within 2R are flat
    centre = np.isin(graph.cell[graph.surface_cell], side[interior(P[side, :2], 1.5, 3.5)])
    assert centre.sum() == 4 and np.allclose(graph.normal[centre], [0, 0, 1])


def test_suggested_radius_closes_the_interior():
    """At suggest_radius() a lattice jittered by 10 % has no interior voids; at 0.8x it has, and says so."""
    P = _jittered(8, 0.1, 4)
    R = suggest_radius(P)
    assert 0.9 < R < 1.2
    g = build_graph(build_cells(P, R))
    assert g.stats["voids"] == 0 and g.n_surface == 8**3 - 6**3
    g = build_graph(build_cells(P, 0.8 * R))
    assert g.stats["voids"] > 0 and "voids" in g.warnings[0]
    assert "below the particle spacing" in g.warnings[0] and f"{R:.4g}" in g.warnings[0]
    assert g.n_surface == 8**3 - 6**3  # the void faces are not mistaken for the free surface


def test_the_void_warning_at_the_suggested_radius_gives_advice_that_works():
    """Auto Radius picks the spacing; where voids remain there (particles spread unevenly) the
    warning does not tell the user to pick the spacing again, and what it does suggest closes them."""
    P = _jittered(10, 0.45, 1)
    R = suggest_radius(P)
    g = build_graph(build_cells(P, R))
    assert g.stats["voids"] > 0, "the case must have voids at the spacing to test the advice"
    text = g.warnings[0]
    assert "already the particle spacing" in text and "near the spacing" not in text
    suggested = float(text.split("about ")[1].split(";")[0])
    assert suggested > R
    assert build_graph(build_cells(P, suggested)).stats["voids"] == 0


# -- bad input: a clear message with numbers, or a zero result where zero is right ------------------------

def _solve(P, R=1.0, **kw):
    return FluidSolver(material_from_preset("skimmilk"), R, 1.0).solve(P, environment=Environment((1, 1, 1)), **kw)


def test_no_particles_is_a_zero_result():
    res = _solve(np.zeros((0, 3)))
    assert res.phi.shape == (0, 3) and "no particles" in res.warnings[-1]
    V = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]])
    res = _solve(np.zeros((0, 3)), surface=(V, np.array([[0, 1, 2]])))
    assert res.vertex_radiance.shape == (3, 3) and not res.vertex_radiance.any()


def test_one_particle_and_isolated_particles_get_zero_radiance_with_a_warning():
    res = _solve(np.array([[0.0, 0, 0]]))
    assert not res.point_radiance.any() and "no neighbour" in " ".join(res.warnings)
    P = np.vstack([lattice(4), [[20.0, 20, 20], [-20.0, 5, 5]]])
    res = _solve(P)
    assert "2 of 66 particles have no neighbour" in " ".join(res.warnings)
    assert not res.point_radiance[-2:].any() and res.point_radiance[:64].min() > 0


def _links_by_cell(g):
    """Each kept cell's links as a sorted list of (neighbour cell, length, area); surface links as cell -1."""
    out = {}
    for i in range(g.n_inner):
        row = []
        for k in range(g.neighbors.shape[1]):
            j = g.neighbors[i, k]
            if j >= 0:
                row.append((int(g.cell[j]) if j < g.n_inner else -1, g.edge_length[i, k], g.face_area[i, k]))
        out[int(g.cell[i])] = sorted(row)
    return out


def test_cells_left_out_leave_the_others_graph_as_it_was():
    """Cells left out of the graph -- isolated particles, and a piece of two cells whose surface faces both
    face a particle (interior voids: no light enters it) -- leave no node and no link: the lattice's nodes
    keep exactly the links, lengths and areas they have without them, however the nodes are renumbered."""
    rng = np.random.default_rng(2)
    P = lattice(5) + rng.uniform(-0.1, 0.1, (125, 3))
    o = np.array([-20.0, 5, 5])
    dark = o + np.array([[0.0, 0, 0], [1.5, 0, 0]])  # a piece of two cells (1.5 < 2R apart)
    caps = o + np.array([[-2.05, 0, 0], [3.55, 0, 0]])  # isolated (> 2R from all), each within R of a probe
    far = np.vstack([dark, caps, [[20.0, 20, 20]]])
    alone = build_graph(build_cells(P, 1.0))
    both = build_graph(build_cells(np.vstack([P, far]), 1.0))
    said = " ".join(both.warnings)
    assert "3 of 130 particles have no neighbour" in said and "2 cells lie in pieces without" in said, said
    assert both.n_inner == alone.n_inner == 125 and both.n_surface == alone.n_surface
    a, b = _links_by_cell(alone), _links_by_cell(both)
    assert a.keys() == b.keys()
    for c in a:
        assert [r[0] for r in a[c]] == [r[0] for r in b[c]]
        np.testing.assert_allclose([r[1:] for r in a[c]], [r[1:] for r in b[c]], rtol=1e-12)


def test_nan_positions_are_left_out_with_their_count():
    P = lattice(4)
    P[[3, 7]] = np.nan
    res = _solve(P)
    assert "2 of 64 particles have NaN or Inf positions" in res.warnings[0]
    assert not res.phi[[3, 7]].any() and res.phi[0].min() > 0
    with pytest.raises(ParticleError, match="all 5 particles have NaN"):
        _solve(np.full((5, 3), np.nan))


def test_particles_in_a_plane_are_refused():
    P = lattice(5)
    with pytest.raises(ParticleError, match="all 25 particles lie in one plane"):
        _solve(P[P[:, 2] == 0])


@pytest.mark.parametrize("R, match", [(0.0, "positive"), (-1.0, "positive"), (np.nan, "positive"),
                                      (50.0, "larger than the whole fluid"), (5.0, "times the particle spacing")])
def test_bad_radius_is_refused_with_numbers(R, match):
    with pytest.raises(ParticleError, match=match):
        _solve(lattice(12), R)


def test_too_many_particles_for_memory_is_refused_before_allocating():
    with pytest.raises(ParticleError, match=r"1,000,000 particles need about 7.5 GiB .*budget 1.0 GiB"):
        prepare_particles(np.broadcast_to(np.zeros(3), (1_000_000, 3)), 1.0, memory_budget=2**30)


def test_coincident_particles_share_a_cell():
    P = np.vstack([lattice(4), lattice(4)[:3]])
    res = _solve(P)
    assert "3 particles coincide" in " ".join(res.warnings)
    assert np.allclose(res.phi[-3:], res.phi[:3])


def test_a_broken_surface_mesh_is_refused():
    from translucency_addon.errors import MeshError

    V = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]])
    with pytest.raises(MeshError, match="finite"):
        _solve(lattice(4), surface=(np.where(V == 1, np.nan, V), np.array([[0, 1, 2]])))
    with pytest.raises(MeshError, match="indices outside its 3 vertices"):
        _solve(lattice(4), surface=(V, np.array([[0, 1, 3]])))


def test_the_compiled_and_numpy_paths_give_the_same_cells():
    """Face for face, to rounding, on the fingerprint sets (exact and jittered lattices, uniform and clustered
    random) and a jittered ball with the bench's radius (the kernel's nearest-first order and early exits)."""
    rng = np.random.default_rng(7)
    ball = lattice(12, 0.5) - 2.75
    ball = ball[np.linalg.norm(ball, axis=1) < 3.0] + rng.uniform(-0.05, 0.05, (1, 3))
    sets = _fingerprint_sets() + [("jittered ball", ball + rng.uniform(-0.05, 0.05, ball.shape), 0.5)]
    for name, P, R in sets:
        a, b = build_cells(P, R, method="compiled"), build_cells(P, R, method="numpy")
        assert (a.path, b.path) == ("compiled", "numpy")
        assert np.array_equal(a.face_i, b.face_i) and np.array_equal(a.face_j, b.face_j), name
        scale = R * R
        assert np.abs(a.face_area - b.face_area).max() < 1e-12 * scale, name
        assert np.abs(a.face_distance - b.face_distance).max() < 1e-12 * R, name  # the compiled face frames
        assert np.abs(a.volume - b.volume).max() < 1e-12 * scale * R, name
        assert np.abs(a.sphere_area - b.sphere_area).max() < 1e-11 * scale, name
        assert np.abs(a.surface_vector - b.surface_vector).max() < 1e-11 * scale, name


def test_the_compiled_neighbour_lists_are_the_k_d_trees_pairs():
    """The grid search of the compiled path (cells of 2R, 27 around each) finds exactly the pairs closer than
    2R that ``cKDTree.query_pairs`` finds, in both rows, ascending, with the distances: on a jittered lattice
    with pairs at exactly 2R (left out), a cloud spread over a box 40x its radius (mostly empty cells, rows and
    slabs), and one particle."""
    from scipy.spatial import cKDTree

    from translucency_addon.fluid.cells import _spatial_order

    rng = np.random.default_rng(3)
    sets = [("lattice, pairs at exactly 2R", lattice(6, 1.0), 1.0),
            ("sparse cloud", rng.uniform(0.0, 40.0, (600, 3)), 1.0),
            ("jittered lattice", lattice(7, 1.0) + rng.uniform(-0.1, 0.1, (343, 3)), 0.99),
            ("one particle", np.zeros((1, 3)), 1.0)]
    for name, P, R in sets:
        order, grid = _spatial_order(P, R)
        Q = P[order]
        start, nbr, dist = compiled_faces.neighbour_lists(Q, R, grid)
        pairs = cKDTree(Q).query_pairs(2.0 * R, output_type="ndarray")
        d = np.linalg.norm(Q[pairs[:, 1]] - Q[pairs[:, 0]], axis=1) if len(pairs) else np.zeros(0)
        pairs = pairs[d < 2.0 * R]
        want = sorted(map(tuple, np.vstack([pairs, pairs[:, ::-1]]).tolist())) if len(pairs) else []
        rows = np.repeat(np.arange(len(Q)), np.diff(start))
        assert sorted(zip(rows.tolist(), nbr.tolist())) == want, name
        assert all(np.all(np.diff(nbr[start[i]:start[i + 1]]) > 0) for i in range(len(Q))), name
        assert np.allclose(dist, np.linalg.norm(Q[nbr] - Q[rows], axis=1), rtol=1e-15, atol=0), name
        assert np.all(dist < 2.0 * R), name


def test_without_numba_the_cells_take_the_numpy_path_and_say_why(monkeypatch):
    """The fallback is the numpy path (the same cells), and the cells and a fluid frame's stats say why and
    what to change; asking for the compiled path without numba is refused with the reason."""
    monkeypatch.setattr(compiled_faces, "_KERNEL", {"error": "numba is not installed"})
    P = lattice(4) + np.random.default_rng(5).uniform(-0.1, 0.1, (64, 3))
    cells = build_cells(P, 1.0)
    assert cells.path == "numpy"
    assert "numba is not installed" in cells.path_note and "install numba" in cells.path_note
    with pytest.raises(RuntimeError, match="numba is not installed"):
        build_cells(P, 1.0, method="compiled")
    res = _solve(P, 1.0)
    assert res.stats["cell_path"] == "numpy" and "numba is not installed" in res.stats["cell_path_note"]
    with pytest.raises(ValueError, match="choose one of auto, compiled, numpy"):
        cells_mod.cell_path("fast")


def test_with_numba_a_fluid_frame_uses_the_compiled_path():
    res = _solve(lattice(4) + np.random.default_rng(6).uniform(-0.1, 0.1, (64, 3)), 1.0)
    assert res.stats["cell_path"] == "compiled" and res.stats["cell_path_note"] == ""


def test_the_first_compiled_call_of_a_process_is_timed_for_the_log():
    """The kernel is compiled (or loaded from numba's cache) at its first call in a process: that frame's
    stats carry what it took, later frames carry 0 (the add-on logs it once)."""
    import subprocess
    import sys
    from pathlib import Path

    code = ("import numpy as np\n"
            "from translucency_addon.fluid import FluidSolver\n"
            "from translucency_addon.scene.lights import Environment\n"
            "from translucency_addon.scene.materials import material_from_preset\n"
            "P = np.stack(np.meshgrid(*[np.arange(4.0)] * 3, indexing='ij'), -1).reshape(-1, 3)\n"
            "P += np.random.default_rng(0).uniform(-0.1, 0.1, P.shape)\n"
            "fs = FluidSolver(material_from_preset('skimmilk'), 1.0, 1.0)\n"
            "a = fs.solve(P, environment=Environment((1, 1, 1))).stats['cell_kernel_first_call_s']\n"
            "b = fs.solve(P, environment=Environment((1, 1, 1))).stats['cell_kernel_first_call_s']\n"
            "print(a, b)\n")
    root = Path(__file__).resolve().parents[1]
    out = subprocess.run([sys.executable, "-c", code], cwd=root, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    a, b = (float(x) for x in out.stdout.split())
    assert a > 0.0 and b == 0.0


def test_a_new_process_loads_the_compiled_kernels_from_numbas_cache():
    """The kernels are module-level (``compiled_kernels``): a second process finds them in numba's disk cache
    and compiles nothing (as closures the faces kernel missed the cache in every process: ~1.5 s each)."""
    import subprocess
    import sys
    from pathlib import Path

    code = ("import numpy as np\n"
            "from translucency_addon.fluid import build_cells, compiled_kernels as k\n"
            "build_cells(np.random.default_rng(0).uniform(0, 4, (200, 3)), 1.0, method='compiled')\n"
            "print(*(sum(getattr(f.stats, s).values()) for f in (k.faces, k.sort_rows, k.upper_faces)\n"
            "        for s in ('cache_hits', 'cache_misses')))\n")
    root = Path(__file__).resolve().parents[1]
    runs = [subprocess.run([sys.executable, "-c", code], cwd=root, capture_output=True, text=True, timeout=300)
            for _ in range(2)]
    assert all(r.returncode == 0 for r in runs), [r.stderr[-2000:] for r in runs]
    hits_and_misses = [int(x) for x in runs[1].stdout.split()]
    assert hits_and_misses[1::2] == [0, 0, 0] and all(h >= 1 for h in hits_and_misses[0::2]), hits_and_misses


@pytest.mark.parametrize("with_unlit", [False, True])
def test_the_graphs_compiled_links_are_numpys(with_unlit):
    """build_graph sorts the faces' links by (source, destination) and lays them into slots in compiled
    passes when the cells came from the compiled path (compiled_kernels.directed_links, fill_slots): the
    numpy lines' graph exactly, with unlit pieces and isolated particles left out or not."""
    from dataclasses import replace

    from translucency_addon.fluid import compiled_faces

    if compiled_faces.available():
        pytest.skip(f"the compiled cells cannot run here: {compiled_faces.available()}")
    rng = np.random.default_rng(5)
    P = lattice(9) + rng.uniform(-0.1, 0.1, (729, 3))
    if with_unlit:
        o = np.array([-20.0, 5, 5])  # as in the test above: a piece with no lit face, two caps and a far particle
        P = np.vstack([P, o + [[0.0, 0, 0], [1.5, 0, 0], [-2.05, 0, 0], [3.55, 0, 0]], [[30.0, 30, 30]]])
    cells = build_cells(P, 1.0, method="compiled")
    assert cells.path == "compiled"
    calls, real = [], compiled_faces.directed_links
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(compiled_faces, "directed_links", lambda *a: calls.append(1) or real(*a))
        got = build_graph(cells)
    assert calls == [1]
    want = build_graph(replace(cells, path="numpy"))
    for name in ("neighbors", "edge_length", "face_area", "position", "volume", "normal", "area", "cell",
                 "surface_cell"):
        np.testing.assert_array_equal(getattr(got, name), getattr(want, name), err_msg=name)
    assert got.stats == want.stats and got.warnings == want.warnings
    assert ("pieces without" in " ".join(got.warnings)) == with_unlit
