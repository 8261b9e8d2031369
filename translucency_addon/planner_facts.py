"""What the planner measures on an object before it decides: its thickness and the light reaching it.

Geometry (:func:`surface_thickness`, :func:`object_thickness`, a fluid's
:func:`fluid_thickness`) and light (:func:`light_reaching`, and
:func:`unlit_misses`: why each light misses, in numbers).  No decisions and
no words here: the rules are in :mod:`.planner_rules`, the words in
:mod:`.planner_messages`.
"""

from __future__ import annotations

import numpy as np

from .scene.lights import spot_falloff


def surface_thickness(bake) -> np.ndarray:
    """Local thickness (object units) at every surface node of the finest level.

    :func:`.raycast.inward_thickness` of the finest level's surface nodes against the baked mesh.  The
    bake measures it once and keeps it with the digest of what it was measured on
    (``Bake.surface_thickness``, in the cache: a cold frame of a 1.3 M-triangle mesh spent 0.45 s casting
    these rays); a bake without it (an older cache) or whose nodes or mesh no longer match it (a deformed
    pose, a bake rebuilt from another's parts) is measured here.  Either way once per level in a process.
    Geometry only; scaled to mm by the caller.
    """
    # Keyed by the level itself, not by the bake key: two bakes of the same mesh and settings share
    # a key but not their nodes (fTetWild varies from run to run).
    lv = bake.finest
    key = (id(lv.position), lv.n_surface)
    cached = _THICKNESS.get(key)
    if cached is not None and cached[0] is lv.position:
        return cached[1]
    from .geometry.raycast import inward_thickness, mesh_bvh, thickness_digest

    kept = getattr(bake, "surface_thickness", None)
    if kept is not None and kept.digest == thickness_digest(bake.mesh_vertices, bake.mesh_faces,
                                                            lv.surface_position, lv.normal):
        t = kept.values
    else:
        bvh = mesh_bvh(bake.mesh_vertices, bake.mesh_faces, getattr(bake, "mesh_bvh_order", None))
        t = inward_thickness(bvh, bake.mesh_vertices, lv.surface_position, lv.normal)
    if len(_THICKNESS) > 64:
        _THICKNESS.clear()
    _THICKNESS[key] = (lv.position, t)  # the array is kept so its id cannot be reused while cached
    return t


def object_thickness(bake) -> dict:
    """Thickness facts (mm) of the object: 10th percentile and median of :func:`surface_thickness`
    (area-weighted over the surface nodes), the bounding sphere, and the per-node thickness."""
    t_mm = surface_thickness(bake) * bake.mm_per_unit
    center, radius = bounding_sphere(bake.mesh_vertices)
    return {
        "thin_mm": _weighted_percentile(t_mm, bake.finest.area, 10.0),
        "median_mm": _weighted_percentile(t_mm, bake.finest.area, 50.0),
        "radius_mm": radius * bake.mm_per_unit,
        "center": center,
        "radius_units": radius,
        "node_mm": t_mm,
    }


def bounding_sphere(V) -> tuple[np.ndarray, float]:
    """``(center, radius)`` of the sphere around the vertices ``V`` centred on their box: computed once per
    vertex array (every frame's plan asks; 40 ms a frame for 655 k vertices), kept while the array lives."""
    hit = _SPHERES.get(id(V))
    if hit is not None and hit[0] is V:
        return hit[1].copy(), hit[2]
    P = np.asarray(V, dtype=np.float64)
    center = 0.5 * (P.max(axis=0) + P.min(axis=0))
    radius = float(np.max(np.linalg.norm(P - center, axis=1)))
    if len(_SPHERES) > 16:
        _SPHERES.clear()
    _SPHERES[id(V)] = (V, center, radius)  # the array is kept so its id cannot be reused while cached
    return center.copy(), radius


_SPHERES: dict = {}  # id(vertex array) -> (array, center, radius)


def _weighted_percentile(x, w, q: float) -> float:
    order = np.argsort(x)
    cw = np.cumsum(np.asarray(w, dtype=np.float64)[order])
    if cw[-1] <= 0:
        return float(np.percentile(x, q))
    return float(np.asarray(x)[order][min(np.searchsorted(cw, q / 100.0 * cw[-1]), len(x) - 1)])


_THICKNESS: dict = {}  # (id of the finest level's positions, n_surface) -> (positions, thickness in units)


def light_reaching(lights, environment, center, radius_units: float, mm_per_unit: float) -> tuple[np.ndarray, list]:
    """Upper estimate of the irradiance (W/m^2, RGB) any light can bring to the bounding sphere.

    Point lights are evaluated at the nearest point of the sphere (or inside
    it); a spot counts only if its cone reaches the sphere.  Returns the
    total and the list of lights that reach the object.
    """
    total = np.zeros(3)
    reaching = []
    c = np.asarray(center, dtype=np.float64)
    for light in lights or ():
        if not np.any(light.rgb > 0):
            continue
        if light.kind == "sun":
            E = light.rgb
        else:
            delta = c - np.asarray(light.position)
            dist = float(np.linalg.norm(delta))
            nearest = max(dist - radius_units, 1e-3 * max(radius_units, 1e-9))
            r_m = nearest * mm_per_unit * 1e-3
            E = light.rgb / (r_m * r_m)
            if light.kind in ("spot", "area") and dist > radius_units:
                # angle between the light's axis and the direction to the sphere, less its angular radius
                cos_axis = float(np.dot(delta / dist, light.unit_direction))
                half = np.arcsin(min(1.0, radius_units / dist))
                ang = max(0.0, np.arccos(np.clip(cos_axis, -1, 1)) - half)
                if light.kind == "spot":
                    E = E * float(spot_falloff(light, np.array([np.cos(ang)]))[0])
                else:
                    E = E * max(np.cos(ang), 0.0)
        if np.any(E > 0):
            total += E
            reaching.append(light)
    if environment is not None and not environment.is_black:
        total += np.pi * np.asarray(environment.radiance)
        if environment.sh is not None:
            total += np.pi * np.abs(np.asarray(environment.sh)[0]) * 0.282095 * 4.0
    return total, reaching


def unlit_misses(lights, environment, center, radius_units: float) -> tuple[list, str, bool]:
    """Why no light reaches an object, light by light in numbers: ``(misses, world, no_lights)`` for
    :func:`.planner_messages.unlit_text` -- per light without power ``(label, kind, rgb)``, per spot or area
    light aimed away ``(label, kind, axis_deg, covers_deg, reach_deg)`` (the angle between its axis and the
    object's centre, the object's angular radius, the cone's half-angle or 90 deg); the world "black", "none" or
    "lit"; and whether there are no lights at all."""
    misses = []
    c = np.asarray(center, dtype=np.float64)
    for light in lights or ():
        label = f"'{light.name or light.kind}' ({light.kind})"
        if not np.any(light.rgb > 0):
            misses.append((label, light.kind, np.round(light.rgb, 6).tolist()))
            continue
        if light.kind in ("spot", "area"):
            delta = c - np.asarray(light.position)
            dist = float(np.linalg.norm(delta))
            if dist > radius_units:
                axis = np.degrees(np.arccos(np.clip(float(np.dot(delta / dist, light.unit_direction)), -1, 1)))
                edge = np.degrees(np.arcsin(min(1.0, radius_units / dist)))
                reach = np.degrees(0.5 * light.spot_size) if light.kind == "spot" else 90.0
                misses.append((label, light.kind, axis, edge, reach))
    world = "lit" if environment is not None and not environment.is_black else (
        "black" if environment is not None else "none")
    return misses, world, not lights


def fluid_thickness(points, radius: float, mm_per_unit: float) -> dict:
    """Thickness facts (mm) of a particle fluid, in the keys of :func:`object_thickness`, one "node".

    A fluid has no surface nodes before its cells are built (that is the
    frame's cost), so its thickness is estimated from the particles alone:
    the smallest extent along the principal axes of their positions (an SVD
    of the centred points), plus one particle diameter (each ball reaches a
    radius beyond its centre).  Exact for a slab, a box and a ball; an upper
    estimate for a curved sheet (a splash crown), whose thickness the
    principal axes cannot see.
    """
    P = np.asarray(points, dtype=np.float64)
    R = float(radius)
    lo, hi = P.min(axis=0) - R, P.max(axis=0) + R
    center = 0.5 * (lo + hi)
    c = P - P.mean(axis=0)
    axes = np.linalg.svd(c[:: max(1, len(P) // 20000)], full_matrices=False)[2] if len(P) >= 3 else np.eye(3)
    proj = c @ axes.T
    thin = (float(np.ptp(proj, axis=0).min()) if len(P) >= 3 else 0.0) + 2.0 * R
    bound = float(np.max(np.linalg.norm(P - center, axis=1))) + R
    return {"thin_mm": thin * mm_per_unit, "median_mm": thin * mm_per_unit, "radius_mm": bound * mm_per_unit,
            "center": center, "radius_units": bound, "node_mm": np.array([thin * mm_per_unit])}

