"""Procedural test meshes (closed, outward-oriented triangle meshes): bpy-free.

Used by tests, benchmarks and the reference scenes where an analytic answer
exists (the sphere) or a hard case must be built (thin shells, high genus).
"""

from __future__ import annotations

import numpy as np


def icosphere(radius: float = 1.0, subdivisions: int = 3, center=(0.0, 0.0, 0.0)):
    t = (1.0 + 5**0.5) / 2.0
    V = np.array([[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t],
                  [0, -1, -t], [0, 1, -t], [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]], dtype=np.float64)
    F = np.array([[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4],
                  [11, 10, 2], [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8],
                  [3, 8, 9], [4, 9, 5], [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]], dtype=np.int64)
    V /= np.linalg.norm(V, axis=1, keepdims=True)
    for _ in range(subdivisions):
        e = np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1)
        uniq, inv = np.unique(e, axis=0, return_inverse=True)
        inv = inv.reshape(3, -1).T
        mids = V[uniq].mean(axis=1)
        mids /= np.linalg.norm(mids, axis=1, keepdims=True)
        m = len(V) + inv
        V = np.vstack([V, mids])
        a, b, c = F.T
        mab, mbc, mca = m[:, 0], m[:, 1], m[:, 2]
        F = np.concatenate([np.stack([a, mab, mca], 1), np.stack([b, mbc, mab], 1),
                            np.stack([c, mca, mbc], 1), np.stack([mab, mbc, mca], 1)])
    return V * radius + np.asarray(center, dtype=np.float64), F


def uv_sphere(radius: float = 1.0, n_lat: int = 24, n_lon: int = 48, center=(0.0, 0.0, 0.0)):
    """Latitude/longitude sphere with poles (closed, outward)."""
    th = np.linspace(0, np.pi, n_lat + 1)[1:-1]
    ph = np.linspace(0, 2 * np.pi, n_lon, endpoint=False)
    T, Pp = np.meshgrid(th, ph, indexing="ij")
    V = np.stack([np.sin(T) * np.cos(Pp), np.sin(T) * np.sin(Pp), np.cos(T)], -1).reshape(-1, 3)
    V = np.vstack([[0, 0, 1.0], V, [0, 0, -1.0]])
    F = []
    idx = lambda i, j: 1 + i * n_lon + (j % n_lon)  # noqa: E731
    for j in range(n_lon):
        F.append([0, idx(0, j), idx(0, j + 1)])
        F.append([len(V) - 1, idx(n_lat - 2, j + 1), idx(n_lat - 2, j)])
    for i in range(n_lat - 2):
        for j in range(n_lon):
            a, b, c, d = idx(i, j), idx(i + 1, j), idx(i + 1, j + 1), idx(i, j + 1)
            F.append([a, b, c])
            F.append([a, c, d])
    return V * radius + np.asarray(center, dtype=np.float64), np.asarray(F, dtype=np.int64)


def box(size=(1.0, 1.0, 1.0), center=(0.0, 0.0, 0.0), subdivisions: int = 0, n=None):
    """Axis-aligned box, each face split into quads: n x n (n = 2^subdivisions unless given), or
    ``n = (nx, ny, nz)`` divisions along each axis (a bar with square-ish triangles).

    Shared vertices are merged; vertices are sorted lexicographically (np.unique).
    """
    n = 2**subdivisions if n is None else n
    ns = np.broadcast_to(np.asarray(n, dtype=np.int64), (3,))
    if np.any(ns < 1):
        raise ValueError(f"a box face needs at least 1 division, got {n}")
    grids = [np.linspace(-0.5, 0.5, int(k) + 1) for k in ns]
    Vs, Fs = [], []
    off = 0
    for axis in range(3):
        for sign in (-1.0, 1.0):
            u, v = [a for a in range(3) if a != axis]
            U, W = np.meshgrid(grids[u], grids[v], indexing="ij")
            nu, nv = U.shape
            P = np.zeros((nu, nv, 3))
            P[..., axis] = 0.5 * sign
            P[..., u] = U
            P[..., v] = W
            idx = np.arange(nu * nv).reshape(nu, nv) + off
            a, b, c, d = idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]
            tris = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
            # Orient outward: normal of (a,b,c) is u x v = +axis direction for even permutations.
            nrm = np.cross(np.eye(3)[u], np.eye(3)[v])
            if np.dot(nrm, np.eye(3)[axis]) * sign < 0:
                tris = tris[:, [0, 2, 1]]
            Vs.append(P.reshape(-1, 3))
            Fs.append(tris)
            off += nu * nv
    V = np.concatenate(Vs)
    F = np.concatenate(Fs)
    # Merge the duplicated edge vertices (keyed on the unit-box lattice: exact for any n).
    key = np.round(V * 2 * ns).astype(np.int64)
    _, first, inv = np.unique(key, axis=0, return_index=True, return_inverse=True)
    V = V[first] * np.asarray(size, dtype=np.float64) + np.asarray(center, dtype=np.float64)
    return V, inv.reshape(-1)[F]


def torus(major: float = 1.0, minor: float = 0.3, n_major: int = 48, n_minor: int = 16,
          center=(0.0, 0.0, 0.0), axis: int = 2):
    """Torus around ``axis`` (0, 1 or 2)."""
    i, j = np.meshgrid(np.arange(n_major), np.arange(n_minor), indexing="ij")
    u = 2 * np.pi * i / n_major
    v = 2 * np.pi * j / n_minor
    x = (major + minor * np.cos(v)) * np.cos(u)
    y = (major + minor * np.cos(v)) * np.sin(u)
    z = minor * np.sin(v)
    P = np.stack([x, y, z], -1).reshape(-1, 3)
    perm = {2: [0, 1, 2], 0: [2, 0, 1], 1: [1, 2, 0]}[axis]
    P = P[:, perm]
    idx = np.arange(n_major * n_minor).reshape(n_major, n_minor)
    a = idx
    b = np.roll(idx, -1, axis=0)
    c = np.roll(np.roll(idx, -1, axis=0), -1, axis=1)
    d = np.roll(idx, -1, axis=1)
    F = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
    return P + np.asarray(center), F


def merge(*meshes):
    """Concatenate meshes into one (disjoint pieces in one object)."""
    Vs, Fs, off = [], [], 0
    for V, F in meshes:
        Vs.append(V)
        Fs.append(np.asarray(F) + off)
        off += len(V)
    return np.concatenate(Vs), np.concatenate(Fs)


def hollow_sphere(radius: float = 1.0, wall: float = 0.01, subdivisions: int = 4):
    """A thin spherical shell: outer sphere plus an inward-facing inner sphere."""
    Vo, Fo = icosphere(radius, subdivisions)
    Vi, Fi = icosphere(radius - wall, subdivisions)
    return merge((Vo, Fo), (Vi, Fi[:, [0, 2, 1]]))


def torus_grid(nx: int = 3, ny: int = 2, major: float = 1.0, minor: float = 0.35, n_major: int = 32, n_minor: int = 12):
    """Interlinked-free grid of overlapping tori: a single solid of genus >= nx*ny (when fused).

    The tori overlap their neighbours, so the tetrahedraliser (which fills by
    winding number) fuses them into one body with nx*ny handles.
    """
    pitch = 2.0 * major * 0.95
    parts = [torus(major, minor, n_major, n_minor, center=(ix * pitch, iy * pitch, 0.0))
             for ix in range(nx) for iy in range(ny)]
    return merge(*parts)


def finned_sphere(radius: float = 1.0, fin_thickness: float = 0.04, fin_reach: float = 1.5,
                  fin_height: float = 1.6, subdivisions: int = 3, fin_divisions: int = 8):
    """A sphere with one thin flat fin sticking out along +x (a body with a thin part).

    The fin is a box ``fin_reach`` beyond the sphere, ``fin_thickness`` thick
    (along y) and ``fin_height`` tall (along z), starting inside the sphere.
    The result is the closed boundary of their union (:func:`union_surface`),
    with no faces left inside, as a Boolean union in Blender would give.
    """
    Vs, Fs = icosphere(radius, subdivisions)
    inner = 0.6 * radius
    length = radius + fin_reach - inner
    Vb, Fb = box((length, fin_thickness, fin_height), center=(inner + 0.5 * length, 0.0, 0.0), n=fin_divisions)
    return union_surface(*merge((Vs, Fs), (Vb, Fb)), edge_length=0.5 * fin_thickness)


def union_surface(V, F, edge_length: float):
    """The outward-oriented boundary of the volume that overlapping closed pieces enclose.

    fTetWild (:func:`.tetra.tetrahedralize`) fills the union by its winding
    number; the boundary faces of its tetrahedra are the union's surface.  A
    library does the Boolean here, so nothing is written by hand but the
    orientation: each face's normal points away from its tet's fourth vertex.
    """
    from . import tetra

    TV, TT = tetra.tetrahedralize(V, F, edge_length=edge_length, optimize=False)
    t, k = tetra.boundary_faces(TT, tetra.topology(TT, len(TV)))
    tris = TT[t][np.arange(len(t))[:, None], tetra.FACE_VERTS[k]]
    a, b, c = (TV[tris[:, i]] for i in range(3))
    outward = np.einsum("ij,ij->i", np.cross(b - a, c - a), (a + b + c) / 3.0 - TV[TT[t, k]]) > 0
    tris[~outward] = tris[~outward][:, [0, 2, 1]]
    used, inverse = np.unique(tris, return_inverse=True)
    return TV[used], inverse.reshape(-1, 3)


# -- procedural poses (deformations of a mesh's vertices, same count and order) ---------------------
def _smoothstep(x):
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def rotation(axis, degrees: float) -> np.ndarray:
    """3x3 rotation matrix about ``axis`` (Rodrigues)."""
    k = np.asarray(axis, dtype=np.float64)
    k = k / np.linalg.norm(k)
    a = np.deg2rad(degrees)
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + np.sin(a) * K + (1.0 - np.cos(a)) * K @ K


def bend(V, degrees: float, joint=(0.0, 0.0, 0.0), along: int = 0, axis=(0.0, 1.0, 0.0), blend: float = 0.5,
         preserve_volume: bool = True):
    """Two bones meeting at ``joint``, the second turned by ``degrees`` about ``axis``, with the
    weight w of the second rising smoothly from 0 to 1 over ``joint -+ blend`` along the
    coordinate ``along`` (an armature with automatic weights).

    ``preserve_volume`` (Blender's armature option of that name, dual-quaternion skinning):
    a point turns by w x degrees about the joint, so the bend is a smooth arc; without it,
    linear blend skinning mixes the two bones' positions, which pinches the inside of the
    joint (its width falls to cos(degrees / 2) at w = 1/2).
    """
    V = np.asarray(V, dtype=np.float64)
    j = np.asarray(joint, dtype=np.float64)
    w = _smoothstep((V[:, along] - j[along] + blend) / (2.0 * blend))
    if not preserve_volume:
        turned = (V - j) @ rotation(axis, degrees).T + j
        return (1.0 - w[:, None]) * V + w[:, None] * turned
    k = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    a = np.deg2rad(degrees) * w[:, None]
    p = V - j
    return j + p * np.cos(a) + np.cross(k, p) * np.sin(a) + np.outer(p @ k, k) * (1.0 - np.cos(a))


def twist(V, degrees: float, along: int = 2):
    """Twist about the axis ``along`` through the bounding-box centre: 0 at the lowest vertex,
    ``degrees`` at the highest, linear in between."""
    V = np.asarray(V, dtype=np.float64)
    lo, hi = V[:, along].min(), V[:, along].max()
    c = 0.5 * (V.min(axis=0) + V.max(axis=0))
    t = (V[:, along] - lo) / max(hi - lo, 1e-300)
    e = np.eye(3)[along]
    a = np.deg2rad(degrees) * t[:, None]
    p = V - c
    return c + p * np.cos(a) + np.cross(e, p) * np.sin(a) + np.outer(p @ e, e) * (1.0 - np.cos(a))


def squash(V, factor: float = 0.7, along: int = 2, bulge: float = 0.25):
    """Squash to ``factor`` of the height along ``along`` (the lowest point stays), bulging out
    sideways by up to ``bulge`` at mid-height (a shape key's squash-and-stretch; not affine)."""
    V = np.asarray(V, dtype=np.float64)
    lo, hi = V[:, along].min(), V[:, along].max()
    c = 0.5 * (V.min(axis=0) + V.max(axis=0))
    t = (V[:, along] - lo) / max(hi - lo, 1e-300)
    side = 1.0 + bulge * 4.0 * t * (1.0 - t)
    out = c + (V - c) * side[:, None]
    out[:, along] = lo + factor * (V[:, along] - lo)
    return out


def revolve(profile, n_theta: int = 64):
    """Closed surface of revolution about z from a profile ``(r, z)`` running from the bottom pole
    (r = 0) to the top pole (r = 0); outward-oriented."""
    prof = np.asarray(profile, dtype=np.float64)
    if prof[0, 0] != 0.0 or prof[-1, 0] != 0.0 or np.any(prof[1:-1, 0] <= 0):
        raise ValueError("a profile starts and ends on the axis (r = 0) and stays off it in between")
    ring = prof[1:-1]
    m = len(ring)
    th = 2.0 * np.pi * np.arange(n_theta) / n_theta
    P = np.stack([ring[:, None, 0] * np.cos(th)[None], ring[:, None, 0] * np.sin(th)[None],
                  np.broadcast_to(ring[:, None, 1], (m, n_theta))], axis=-1).reshape(-1, 3)
    V = np.vstack([[0.0, 0.0, prof[0, 1]], P, [0.0, 0.0, prof[-1, 1]]])
    idx = 1 + np.arange(m * n_theta).reshape(m, n_theta)
    nxt = np.roll(idx, -1, axis=1)
    F = [np.stack([np.zeros(n_theta, dtype=np.int64), nxt[0], idx[0]], 1),
         np.stack([np.full(n_theta, len(V) - 1), idx[-1], nxt[-1]], 1)]
    for k in range(m - 1):
        F.append(np.stack([idx[k], nxt[k], nxt[k + 1]], 1))
        F.append(np.stack([idx[k], nxt[k + 1], idx[k + 1]], 1))
    F = np.concatenate(F).astype(np.int64)
    p = V[F]
    if np.einsum("ij,ij->i", p[:, 0], np.cross(p[:, 1], p[:, 2])).sum() < 0:
        F = F[:, [0, 2, 1]]
    return V, F


def _resample(polyline, n: int):
    """``n`` points evenly spaced by arc length along a polyline (its ends kept)."""
    pts = np.asarray(polyline, dtype=np.float64)
    seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    t = np.linspace(0.0, s[-1], n)
    return np.stack([np.interp(t, s, pts[:, 0]), np.interp(t, s, pts[:, 1])], axis=1)


def _rounded_profile(radius: float, z0: float, z_body: float, neck: float, z_neck: float, z1: float,
                     fillet: float, n: int):
    """Bottle-like profile (r, z): flat bottom, body, cosine shoulder, neck, flat top; fillets at the rims."""
    pts = [(0.0, z0)]
    a = np.linspace(0.0, 0.5 * np.pi, 6)
    pts += [(radius - fillet + fillet * np.sin(x), z0 + fillet - fillet * np.cos(x)) for x in a]
    u = np.linspace(0.0, 1.0, 24)
    pts += [(radius - (radius - neck) * 0.5 * (1 - np.cos(np.pi * x)), z_body + (z_neck - z_body) * x) for x in u]
    pts += [(neck - fillet + fillet * np.cos(x), z1 - fillet + fillet * np.sin(x)) for x in a]
    pts.append((0.0, z1))
    return _resample(pts, n)


def bottle_with_wine(n_theta: int = 64, wall: float = 0.4, fill: float = 7.0):
    """A sealed bottle (outer glass surface), its inside (a cavity) and the wine in it (z up, units ~ cm).

    Returns ``{"outer": (V, F), "inside": (V, F), "wine": (V, F)}``: the wine
    lies inside the inside volume and touches it at the bottom and the sides
    (nested, touching parts); about 10,000 vertices in all at n_theta = 64.
    """
    R, neck, z_body, z_neck, top = 3.0, 1.2, 10.0, 12.5, 16.0
    outer = revolve(_rounded_profile(R, 0.0, z_body, neck, z_neck, top, 0.4, 62), n_theta)
    inner_prof = _rounded_profile(R - wall, wall, z_body, neck - wall, z_neck, top - wall, 0.3, 62)
    inside = revolve(inner_prof, n_theta)
    # the wine: the inside's profile up to the fill height, closed by a flat surface
    body = inner_prof[inner_prof[:, 1] < fill]
    wine_prof = np.vstack([body, [[R - wall, fill]], [[0.0, fill]]])
    wine_prof = np.vstack([_resample(wine_prof[:-1], 36), [[0.0, fill]]])
    wine_prof[:, 0] = np.where(wine_prof[:, 0] > 0, wine_prof[:, 0], 0.0)
    interior = wine_prof[1:-1, 0] > 1e-9
    wine_prof = np.vstack([wine_prof[:1], wine_prof[1:-1][interior], wine_prof[-1:]])
    wine = revolve(wine_prof, n_theta)
    return {"outer": outer, "inside": inside, "wine": wine}


def cube_with_sphere(size: float = 1.0, radius: float = 0.3, center=(0.0, 0.0, 0.0), n: int = 16,
                     subdivisions: int = 3):
    """A cube (each face n x n quads) and a sphere inside it, as two closed meshes.

    The paper's first scene (about 2,000 vertices at the defaults) with the
    sphere as a cavity; with the sphere opaque, the cube of the shadow test.
    """
    return box((size, size, size), n=n), icosphere(radius, subdivisions, center)
