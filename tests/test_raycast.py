"""The triangle BVH (``geometry/raycast.py``) against brute force over every triangle.

The build orders triangles by median splits (``_balanced_order``); whatever the order, a closest hit,
an any-hit shadow query and a closest point must equal the exhaustive answer.  Meshes whose triangle
count is not a multiple of the leaf size exercise the padding slots.
"""

import numpy as np
import pytest

from translucency_addon.geometry import raycast

from translucency_addon.geometry import primitives
from translucency_addon.geometry.raycast import (
    LEAF, TriangleBVH, _balanced_order, check_order, closest_point_on_triangles, compiled_intersect, mesh_bvh,
    ray_path_note)


def _brute_hits(V, F, o, d):
    """Closest hit t of each ray over every triangle (Moller-Trumbore, the same test the leaves run)."""
    a, b, c = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
    e1, e2 = b - a, c - a
    p = np.cross(d[:, None, :], e2[None])
    det = np.einsum("tk,rtk->rt", e1, p)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / det
        s = o[:, None, :] - a[None]
        u = np.einsum("rtk,rtk->rt", s, p) * inv
        q = np.cross(s, e1[None])
        v = np.einsum("rk,rtk->rt", d, q) * inv
        t = np.einsum("tk,rtk->rt", e2, q) * inv
    ok = (np.abs(det) > 1e-300) & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0)
    return np.where(ok, t, np.inf).min(axis=1)


@pytest.mark.parametrize("walk", ["compiled", "numpy"])
@pytest.mark.parametrize("drop", [0, 1, 3, 37])
def test_hits_and_closest_points_equal_brute_force(drop, walk, monkeypatch):
    """Both traversals (compiled_raycast.py where numba is installed, and the numpy walk)."""
    if walk == "numpy":
        monkeypatch.setenv("TRANSLUCENCY_NUMPY_RAYS", "1")
    else:
        assert compiled_intersect() is not None  # the test environment installs numba
        monkeypatch.setattr(raycast, "COMPILED_MIN_RAYS", 1)  # these 600 rays through the compiled walk too
    rng = np.random.default_rng(drop)
    V, F = primitives.icosphere(2.0, 3)
    V = V * (1.0 + 0.2 * rng.random((len(V), 1)))  # a bumpy closed surface
    F = F[: len(F) - drop]  # padding slots in the last leaves
    bvh = TriangleBVH(V, F)
    assert bvh.leaf_tris.size % LEAF == 0 and sorted(bvh.leaf_tris[bvh.leaf_tris >= 0]) == list(range(len(F)))
    o = rng.normal(size=(600, 3)) * 1.5
    d = rng.normal(size=(600, 3))
    d /= np.linalg.norm(d, axis=1)[:, None]
    t, tri, _, _ = bvh.intersect(o, d)
    ref = _brute_hits(V, F, o, d)
    np.testing.assert_array_equal(np.isinf(t), np.isinf(ref))
    hit = np.isfinite(ref)
    assert hit.mean() > 0.5
    np.testing.assert_allclose(t[hit], ref[hit], rtol=1e-12, atol=1e-12)
    tmax = np.where(hit, 0.5 * ref + 0.5 * np.where(hit, ref, 0), 1.0) * rng.choice([0.9, 1.1], 600)
    np.testing.assert_array_equal(bvh.occluded(o, d, tmax), ref < tmax)
    # closest points: the distance to the nearest of every triangle
    _, _, dist = bvh.closest_point(o[:200])
    a, b, c = (np.broadcast_to(V[F[:, k]][None], (200, len(F), 3)) for k in range(3))
    q = closest_point_on_triangles(np.broadcast_to(o[:200, None], a.shape), a, b, c)
    q = q[0] if isinstance(q, tuple) else q
    np.testing.assert_allclose(dist, np.linalg.norm(q - o[:200, None], axis=2).min(axis=1), rtol=1e-10, atol=1e-12)


def test_median_split_order_is_a_balanced_tree():
    """Every node's range holds the lower half of its parent's along the parent's longest axis."""
    rng = np.random.default_rng(0)
    c = rng.random((1000, 3)) * [4.0, 1.0, 2.0]
    perm = _balanced_order(c, 1024)
    assert sorted(perm[perm >= 0]) == list(range(1000))
    first, second = perm[:512], perm[512:]
    assert c[first, 0].max() <= c[second[second >= 0], 0].min()  # root split along x, the longest axis
    assert np.sum(second < 0) == 24  # padding sorts into the upper half


def test_a_kept_order_gives_the_same_tree_and_a_wrong_one_is_refused():
    V, F = primitives.icosphere(2.0, 3)
    F = F[:-3]
    built = TriangleBVH(V, F)
    check_order(built.leaf_tris, len(F))
    again = TriangleBVH.from_order(V, F, built.leaf_tris.astype(np.int32))
    for name in ("lo", "hi", "v0", "e1", "e2", "valid", "split_axis", "second_is_plus"):
        np.testing.assert_array_equal(getattr(again, name), getattr(built, name))
    bad = built.leaf_tris.copy()
    bad[0, 0] = bad[0, 1]
    with pytest.raises(ValueError, match="exactly once"):
        check_order(bad, len(F))
    with pytest.raises(ValueError, match="expected"):
        check_order(built.leaf_tris[:-1], len(F))


def test_mesh_bvh_is_shared_by_content_not_by_identity():
    V, F = primitives.icosphere(1.0, 2)
    a = mesh_bvh(V, F)
    assert mesh_bvh(V.copy(), F.copy()) is a  # the same mesh in other arrays
    V2 = V.copy()
    V2[0, 0] += 1e-3
    assert mesh_bvh(V2, F) is not a  # an edited mesh never gets the old tree


def test_the_compiled_walk_returns_the_numpy_walks_hits(monkeypatch):
    """compiled_raycast.intersect against the numpy traversal on 20k rays through a bumpy sphere of 20k
    triangles: the same triangles for closest hits and for any-hit shadow rays with a tmax per ray,
    distances and barycentrics to rounding (the same arithmetic; LLVM may fuse a multiply-add)."""
    rng = np.random.default_rng(5)
    V, F = primitives.icosphere(10.0, 5)
    V = V * (1.0 + 0.05 * np.sin(0.7 * V[:, :1]))
    bvh = TriangleBVH(V, F)
    o = rng.normal(size=(20000, 3)) * 4.0
    d = rng.normal(size=(20000, 3))
    d[:50, 1:] = 0.0  # rays along an axis: 1/d is 1e300 there, in both walks
    tmax = rng.uniform(1.0, 30.0, 20000)
    fast = bvh.intersect(o, d, tmin=1e-9)
    fast_any = bvh.intersect(o, d, tmax=tmax, any_hit=True)[1] >= 0
    monkeypatch.setenv("TRANSLUCENCY_NUMPY_RAYS", "1")
    slow = bvh.intersect(o, d, tmin=1e-9)
    slow_any = bvh.intersect(o, d, tmax=tmax, any_hit=True)[1] >= 0
    np.testing.assert_array_equal(fast[1], slow[1])
    assert (fast[1] >= 0).mean() > 0.3
    hit = fast[1] >= 0
    for a, b in zip(fast, slow):
        np.testing.assert_allclose(a[hit], b[hit], rtol=1e-12, atol=1e-12)
    np.testing.assert_array_equal(fast_any, slow_any)


def test_the_numpy_walk_says_why(monkeypatch):
    """A fallback says why and what it costs: the bake's report carries the note (the same hits, slower)."""
    from translucency_addon.quadgraph.bake import format_stats
    from bakes import baked

    assert ray_path_note() == ""
    monkeypatch.setenv("TRANSLUCENCY_NUMPY_RAYS", "1")
    note = ray_path_note()
    assert note.startswith("ray casts take the numpy walk (TRANSLUCENCY_NUMPY_RAYS=1 is set)") and "12x" in note
    from dataclasses import replace

    bake = baked("sphere")
    assert f"note: {note}" in format_stats(replace(bake, stats={**bake.stats, "ray_casts": note}))


def test_the_compiled_leaf_fit_equals_the_numpy_fit_bit_for_bit(monkeypatch):
    """compiled_raycast.leaf_fit (trees of COMPILED_MIN_FIT slots or more) against the numpy fit, on a tree
    with padding slots and on a refit to moved vertices: every array of the tree equal, bit for bit."""
    V, F = primitives.icosphere(3.0, 4)
    F = F[:-3]  # padding slots in the last leaf
    rng = np.random.default_rng(2)
    arrays = ("v0", "e1", "e2", "valid", "lo", "hi", "nonempty", "split_axis", "second_is_plus")
    monkeypatch.setattr(raycast, "COMPILED_MIN_FIT", 1)
    assert raycast.compiled_leaf_fit() is not None
    fast = TriangleBVH(V, F)
    fast_moved = fast.refit(V + 0.1 * rng.normal(size=V.shape))
    monkeypatch.setattr(raycast, "COMPILED_MIN_FIT", 1 << 60)
    slow = TriangleBVH.from_order(V, F, fast.leaf_tris)
    slow_moved = slow.refit(fast_moved.V)
    for a, b in ((fast, slow), (fast_moved, slow_moved)):
        for name in arrays:
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
