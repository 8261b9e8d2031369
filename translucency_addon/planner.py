"""Simulate only what a scene calls for: which passes run, per object, channel and frame.

The run-time pipeline has three passes, multiple scattering (the diffusion solve
on the QuadGraph), single scattering (the RBF optical-depth samples) and, for
objects with inner parts, the Voxel Number Map (Mochida et al.).  A
bpy-free planner decides, from the material, the geometry and the lights,
which of them run for each object and colour channel, and says why.  The
Blender side shows the reasons in the panel; ``python -m translucency_addon
plan`` prints them.

Physical criteria (per channel c; all lengths in mm).  The thresholds were
checked against the independent path tracer (Mitsuba, scattered light only:
the render minus the same medium without scattering); the numbers are quoted
below and in the tests.

* **Diffusion valid**, decided per finest surface node (a region, not the
  whole object: a thin tail does not invalidate a thick body), where the
  reduced albedo ``alpha'_c >= ALBEDO_MIN`` (0.5: on average at least one
  scattering event before absorption) and the local thickness (a ray along
  the inward normal, :func:`surface_thickness`) is at least ``THICK_MIN`` (1)
  transport mean free paths.  A 10 mm cube with alpha' = 0.98 under uniform light:
  diffusion is +440 % at 0.2 transport mean free paths (it diffuses light that
  would cross unscattered), +60 % at 1, +0.2 % at 10; single scattering is
  -66 %, -73 %, -88 %.  Ketchup (15 mm sphere): diffusion is right in red
  (alpha' 0.75), single scattering matches green and blue (alpha' 0.07, 0.02)
  where diffusion returns nothing.  Where diffusion is invalid and single
  scattering is baked, single scattering replaces it *in that region only*
  (per-node weights, :attr:`PassDecision.weights`, mapped to the vertices like
  the radiance); where single scattering is not baked or is turned off,
  diffusion keeps running there and the plan says it is doubtful, where and
  how much (**never turn off the only pass**).  A channel is left out only
  where its pass returns nothing (below).
* **Contribution** of the diffusion pass: our own model's semi-infinite
  albedo (the diffusive-source boundary of eq. 2 over a half-space):
  ``R_ms = (1 - F_dr)/(2 (1 + F_dr)) max(0, 4/((1 - F_dr)(1 + 2 A sqrt((1 - alpha')/3))) - 2)``,
  1 for alpha' = 1 and exactly 0 below alpha' ~ 0.27 at eta = 1.3, times the
  light reaching the object in that channel.  Single scattering: a half-space
  returns ``(1 - ln 2)/2 alpha = 0.153 alpha`` of the light once scattered
  (isotropic phase), a thin part at most its optical thickness' share.  A
  pass is skipped in a channel where its estimate is below ``NEGLIGIBLE``
  (1 %) of the brightest estimate ("negligible").
* **Single scattering where diffusion runs** is *contained in the diffusion
  term*: the diffusive-source boundary condition injects all transmitted
  light, so its first scattering near the surface is already in the
  diffusion solution.  Adding the RBF pass on top counts it twice (on the
  path-traced marble sphere diffusion alone is within 2 %, diffusion plus
  that pass 7.5 % off), so the RBF pass stays off there.  Instead the diffusion
  solve splits it off (:attr:`PassDecision.split`, the first-scatter split of
  :mod:`.single_scattering.closed_form`): closed-form single scattering of the
  local half-space plus the diffusion of what scatters more, which add up.
  It runs in every channel where its single-scattering term brings at least
  ``NEGLIGIBLE`` (1 %) of the object's peak (the brightest channel's
  half-space return ``s(alpha) + M(alpha)`` times the light reaching it), and
  the reasons say how much each term brings.  It needs no bake (it is a
  closed form), so it does not depend on the RBF pass being baked or on;
  ``overrides={"split": False}`` turns it off (diffusion alone), and forcing
  the RBF pass on everywhere (``{"single": True}``) turns it off too.
* **Objects with inner parts** (cavities, other media, opaque parts: ``bake.composite``): diffusion
  keeps its validity test (a marble with a hollow runs diffusion with the cavity exchange, and both
  single-scattering passes stay off as contained in it).  Where diffusion is invalid, the pass that
  replaces it is single scattering when its bake knows the parts (``voxelise_composite``), the
  Voxel Number Map otherwise (:func:`replacement_pass`; measured against Mitsuba's scattered light,
  docs/accuracy.md: single scattering 8 points of relative RMS more accurate on the cubes and the
  bottle, the map about 2x faster per frame).
* **Objects** are skipped when translucency is disabled, when they are not
  in the camera's view, or when no light reaches them (no light source with
  power whose range and cone reach the bounding sphere, and a black world).

Overrides force a pass on or off regardless (``overrides={"multiple": True}``).

Change tracking (:class:`ChangeTracker`): a frame re-solves only what changed
since the last one -- diffusion depends on the lights that reach the object,
its material/field and its geometry; single scattering also on the camera.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field

import numpy as np

from .lights import Environment, Light, spot_falloff
from .materials import Material, reduced_albedo
from .single_scattering.closed_form import half_space_split, semi_infinite_albedo  # noqa: F401 - the planner's measure

ALBEDO_MIN = 0.5
THICK_MIN = 1.0
# What makes the single-scattering pass available, in Blender and on the command line (plans' hints).
SS_HINT = ("Bake single scattering: in Blender turn on Single Scattering and press Bake (or Bake Single "
           "Scattering); on the command line, bake --single-scattering --material NAME")
NEGLIGIBLE = 0.01
CHANNELS = ("R", "G", "B")


@dataclass
class PassDecision:
    """One pass of one object: which channels run, where, and why."""

    name: str  # "multiple" (diffusion) or "single"
    channels: tuple  # (bool, bool, bool)
    reasons: list  # one human-readable reason per channel
    bound: tuple = (0.0, 0.0, 0.0)  # single scattering: B_ss relative to diffusion, per channel
    forced: bool = False
    # "multiple" only: the channels in which the diffusion solve splits off closed-form single scattering
    # (the first-scatter split; DiffusionSolver.solve(single=...)).
    split: tuple = (False, False, False)
    # (n_surface, 3) weights in [0, 1] at the finest level's surface nodes: where in the object the
    # pass counts (diffusion where it is valid, single scattering where it replaces diffusion).
    # None: everywhere.  Only channels that run matter.
    weights: np.ndarray | None = None

    @property
    def runs(self) -> bool:
        return any(self.channels)


@dataclass
class Plan:
    """The passes one object runs this frame (a plain data object; printable)."""

    object_name: str
    run: bool
    reason: str
    multiple: PassDecision | None = None
    single: PassDecision | None = None
    estimated_ms: float = 0.0
    facts: dict = field(default_factory=dict)
    advice: list = field(default_factory=list)  # what a better result would need (panel, CLI)
    voxel_number_map: PassDecision | None = None  # Mochida et al., when baked (inner parts)

    @property
    def passes(self) -> dict:
        return {p.name: p for p in (self.multiple, self.single, self.voxel_number_map) if p is not None}

    def channel_mask(self, name: str) -> np.ndarray:
        p = self.passes.get(name)
        return np.array(p.channels if (p is not None and self.run) else (False, False, False))

    def vertex_weights(self, name: str, idx, w) -> np.ndarray:
        """(n, 3) weight of pass ``name`` at points mapped onto the finest surface nodes.

        ``idx``/``w`` (n, k): the same node indices and weights that carry the
        radiance to the vertices (``Bake.vertex_map`` or :func:`.bake.vertex_mapping`),
        so the region a pass covers blends over the same few nodes as its
        radiance.  Channels that do not run are 0.
        """
        mask = self.channel_mask(name).astype(np.float64)
        idx = np.asarray(idx)
        p = self.passes.get(name)
        if p is None or p.weights is None or not self.run:
            return np.broadcast_to(mask, (len(idx), 3)).copy()
        mapped = np.einsum("vk,vkc->vc", np.asarray(w, dtype=np.float64), p.weights[idx])
        return np.clip(mapped, 0.0, 1.0) * mask


def surface_thickness(bake) -> np.ndarray:
    """Local thickness (object units) at every surface node of the finest level.

    One ray per node along its inward normal to the baked mesh (the scene's
    own BVH, :class:`.raycast.TriangleBVH`), from where it enters the surface
    to where it leaves again.  A ray that meets no triangle
    (a grazing ray at an edge or corner, or a hole in an open mesh) takes the
    median of the rays that did: one lost ray must not make a thin part
    thick.  Geometry only, so it is cached per bake key and scaled to mm by
    the caller.
    """
    # Keyed by the level itself, not by the bake key: two bakes of the same mesh and settings share
    # a key but not their nodes (fTetWild varies from run to run).
    lv = bake.finest
    key = (id(lv.position), lv.n_surface)
    cached = _THICKNESS.get(key)
    if cached is not None and cached[0] is lv.position:
        return cached[1]
    from .raycast import TriangleBVH

    V = np.asarray(bake.mesh_vertices, dtype=np.float64)
    diag = float(np.linalg.norm(np.ptp(V, axis=0)))
    n = np.asarray(lv.normal, dtype=np.float64)
    p = np.asarray(lv.surface_position, dtype=np.float64)
    bvh = TriangleBVH(V, bake.mesh_faces)
    # Enter from just outside and measure entry to exit: a node that sits a hair outside the mesh
    # (placement round-off; seen at 3e-5 units on the unit sphere) would otherwise measure ~0.
    eps = 1e-4 * diag
    origin = p + eps * n
    t_in, tri_in, _, _ = bvh.intersect(origin, -n, tmin=1e-7 * diag)
    entry = origin - np.where(tri_in >= 0, t_in + 1e-6 * diag, eps)[:, None] * n
    t_out, tri_out, _, _ = bvh.intersect(entry, -n, tmin=1e-7 * diag)
    hit = (tri_in >= 0) & (tri_out >= 0)
    t = np.where(hit, t_out + 1e-6 * diag, 0.0)
    t = np.where(hit, t, np.median(t[hit]) if hit.any() else diag)
    if len(_THICKNESS) > 64:
        _THICKNESS.clear()
    _THICKNESS[key] = (lv.position, t)  # the array is kept so its id cannot be reused while cached
    return t


def object_thickness(bake) -> dict:
    """Thickness facts (mm) of the object: 10th percentile and median of :func:`surface_thickness`
    (area-weighted over the surface nodes), the bounding sphere, and the per-node thickness."""
    V = np.asarray(bake.mesh_vertices, dtype=np.float64)
    t_mm = surface_thickness(bake) * bake.mm_per_unit
    center = 0.5 * (V.max(axis=0) + V.min(axis=0))
    radius = float(np.max(np.linalg.norm(V - center, axis=1)))
    return {
        "thin_mm": _weighted_percentile(t_mm, bake.finest.area, 10.0),
        "median_mm": _weighted_percentile(t_mm, bake.finest.area, 50.0),
        "radius_mm": radius * bake.mm_per_unit,
        "center": center,
        "radius_units": radius,
        "node_mm": t_mm,
    }


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


def unlit_reason(lights, environment, center, radius_units: float) -> str:
    """Why no light reaches an object, light by light in numbers, and what to change (a plan's skip)."""
    why = []
    c = np.asarray(center, dtype=np.float64)
    for light in lights or ():
        label = f"'{light.name or light.kind}' ({light.kind})"
        if not np.any(light.rgb > 0):
            why.append(f"{label} has no power (colour x strength = {np.round(light.rgb, 6).tolist()})")
            continue
        if light.kind in ("spot", "area"):
            delta = c - np.asarray(light.position)
            dist = float(np.linalg.norm(delta))
            if dist > radius_units:
                axis = np.degrees(np.arccos(np.clip(float(np.dot(delta / dist, light.unit_direction)), -1, 1)))
                edge = np.degrees(np.arcsin(min(1.0, radius_units / dist)))
                reach = np.degrees(0.5 * light.spot_size) if light.kind == "spot" else 90.0
                what = "its cone's half-angle" if light.kind == "spot" else "the side it emits to"
                why.append(f"{label} is aimed {axis:.0f} deg away from the object's centre; the object covers "
                           f"{edge:.0f} deg around it and {what} is {reach:.0f} deg")
    if environment is None or environment.is_black:
        why.append("the world is black" if environment is not None else "there is no world light")
    if not lights:
        why.insert(0, "no lights")
    return ("unlit: no light reaches it (" + "; ".join(why) + "). Give a light power, aim a spot or area light "
            "at the object, or give the World a colour and strength")


def plan_object(bake, material: Material, lights=(), environment: Environment | None = None, *,
                field_values=None, has_single_scattering: bool | None = None, in_view: bool = True,
                enabled: bool = True, overrides: dict | None = None, name: str = "object",
                has_voxel_number_map: bool | None = None, override_reasons: dict | None = None) -> Plan:
    """Decide the passes of one baked object for this frame (see the module docstring).

    ``overrides`` force a pass on or off (``{"single": False}``: single
    scattering is turned off, so it is not available to replace diffusion;
    ``{"voxel_number_map": False}`` likewise).  ``override_reasons``: per
    overridden pass, what forced it (the plan's reasons say it instead of
    "by the user": a setting's default is not the user's choice).
    """
    overrides = overrides or {}
    if has_single_scattering is None:
        has_single_scattering = getattr(bake, "single_scattering", None) is not None
    if has_voxel_number_map is None:
        has_voxel_number_map = getattr(bake, "voxel_number_map", None) is not None
    ss_real = bool(has_single_scattering) and overrides.get("single") is not False
    vnm_real = bool(has_voxel_number_map) and overrides.get("voxel_number_map") is not False
    parts = inner_parts(bake)
    ss_data = getattr(bake, "single_scattering", None)
    ss_knows_parts = bool(ss_data is not None and getattr(ss_data, "stats", {}).get("inner_parts"))
    replacement = replacement_pass(ss_real, vnm_real, parts, ss_knows_parts)
    # Below, "single scattering" is the pass that replaces diffusion where it is invalid; _split_replacement
    # hands its decision to the Voxel Number Map when that is the replacement.
    baked_ss, has_single_scattering = has_single_scattering, bool(has_single_scattering or has_voxel_number_map)
    ss_available = replacement is not None
    if hasattr(material, "outer"):  # a composite_bake.CompositeMaterial: plan for the outer medium
        material, field_values = material.outer, None
    vnm_n = bake.voxel_number_map.n if getattr(bake, "voxel_number_map", None) is not None else 2000

    def split(single):
        """The replacement pass's decision goes to single scattering or to the Voxel Number Map."""
        return _split_replacement(single, replacement, baked_ss, ss_real, bool(has_voxel_number_map), vnm_real,
                                  parts)

    skipped = _skipped(name, enabled, in_view)
    if skipped is not None:
        return skipped
    geo = object_thickness(bake)
    lv = bake.finest
    # Coefficients: the bulk medium, or the spread over the nodes of a heterogeneous one.
    if material.heterogeneous and field_values is not None:
        fv = np.asarray(field_values[-1] if isinstance(field_values, (list, tuple)) else field_values)
        sa_n, ss_n = material.coefficients(fv)
        bulk = (sa_n.mean(axis=0), ss_n.mean(axis=0))
        surface = (sa_n[lv.n_inner:], ss_n[lv.n_inner:])
    else:
        bulk = tuple(np.asarray(x) for x in material.bulk().arrays())
        surface = tuple(np.broadcast_to(x, (lv.n_surface, 3)) for x in bulk)
    plan = _plan(name, geo, np.asarray(lv.area, dtype=np.float64), material, bulk, surface, lights, environment,
                 bake.mm_per_unit, bool(has_single_scattering), overrides, override_reasons=override_reasons,
                 ms_cost=lambda channels: 1e-4 * lv.n_nodes * sum(channels) / 3.0,  # ~0.1 us per node-channel sweep x ~50
                 ss_available=ss_available, split_replacement=split,
                 split_blocked=("the cavity exchange's solve does not carry the split yet (diffusion alone)"
                                if getattr(getattr(bake, "composite", None), "exchange", None) is not None else ""),
                 # the packed kernel read once per frame (~2 GB/s on a CPU core) plus the light pass
                 vnm_cost=1.0 + 6e-6 * vnm_n * vnm_n / 2.0)
    if parts and plan.facts:
        plan.facts["inner_parts"] = parts
        plan.facts["replacement"] = replacement
    return plan


# Measured per-frame cost of a fluid (cells + warm solve + output), per particle: 5,105 ms at 16,375
# particles on 2 CPU cores (docs/bench_fluid.md); the stages grow about linearly with N.
FLUID_MS_PER_PARTICLE = 0.31


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


def plan_fluid(points, radius: float, mm_per_unit: float, material: Material, lights=(),
               environment: Environment | None = None, *, field_values=None, in_view: bool = True,
               enabled: bool = True, overrides: dict | None = None, name: str = "fluid") -> Plan:
    """Decide the diffusion pass of one particle fluid for this frame (Kang & Kim 2013; the module docstring).

    The same criteria as :func:`plan_object` on the whole fluid as one
    region (:func:`fluid_thickness`; ``field_values`` per particle give the
    mean coefficients of a two-media fluid).  A fluid has no single-scattering
    bake, so diffusion is its only pass and is never turned off for being
    doubtful.  ``facts["particles"]`` makes :func:`describe_plan` say
    "fluid: N particles, diffusion valid".
    """
    overrides = overrides or {}
    P = np.asarray(points, dtype=np.float64)
    skipped = _skipped(name, enabled, in_view)
    if skipped is not None:
        skipped.facts["particles"] = len(P)
        return skipped
    geo = fluid_thickness(P, radius, mm_per_unit)
    if material.heterogeneous and field_values is not None:
        sa_n, ss_n = material.coefficients(np.asarray(field_values, dtype=np.float64))
        bulk = (sa_n.mean(axis=0), ss_n.mean(axis=0))
    else:
        bulk = tuple(np.asarray(x) for x in material.bulk().arrays())
    surface = tuple(np.asarray(x, dtype=np.float64).reshape(1, 3) for x in bulk)
    plan = _plan(name, geo, np.ones(1), material, bulk, surface, lights, environment, mm_per_unit, False, overrides,
                 ms_cost=lambda _channels: FLUID_MS_PER_PARTICLE * len(P),  # every channel in one cell build
                 single_pass=False)
    plan.facts["particles"] = len(P)
    plan.facts["radius_units"] = float(radius)
    return plan


def _skipped(name: str, enabled: bool, in_view: bool) -> Plan | None:
    if not enabled:
        return Plan(name, False, "translucency disabled: turn on Enabled in the object's Translucency panel")
    if not in_view:
        return Plan(name, False, "outside the camera view: nothing to compute (its bounding sphere is outside the "
                                 "render camera's frustum; it is solved again when the camera sees it)")
    return None


def _plan(name, geo, area, material, bulk, surface, lights, environment, mm_per_unit, has_single_scattering,
          overrides, ms_cost, single_pass: bool = True, ss_available: bool | None = None, split_replacement=None,
          vnm_cost: float = 0.0, split_blocked: str = "", override_reasons: dict | None = None) -> Plan:
    """The passes of one object from its geometry facts (``geo``, per-node ``area``), its bulk and surface-node
    coefficients, and the light reaching it: the criteria of the module docstring, per channel and node.

    ``single_pass`` False: the object has no single-scattering pass at all (a particle fluid), so the plan
    has none, and diffusion, its only pass, runs wherever it returns light.

    ``ss_available``: whether a pass can replace diffusion where it is invalid (default: single scattering
    baked and not turned off); ``split_replacement(single) -> (single, voxel_number_map)`` hands that replacement to the
    Voxel Number Map where it is the better pass (:func:`plan_object`), costing ``vnm_cost`` ms per frame."""
    if ss_available is None:
        ss_available = has_single_scattering and overrides.get("single") is not False
    vnm = None
    E, reaching = light_reaching(lights, environment, geo["center"], geo["radius_units"], mm_per_unit)
    facts = {"thin_mm": geo["thin_mm"], "radius_mm": geo["radius_mm"], "irradiance": E.tolist(),
             "lights_reaching": [getattr(light, "name", "") for light in reaching]}
    if not np.any(E > 0) and not any(overrides.values()):
        return Plan(name, False, unlit_reason(lights, environment, geo["center"], geo["radius_units"]), facts=facts)
    sa, ss = bulk
    sa_s, ss_s = surface
    n_surface = len(area)
    st = sa + ss
    alpha = reduced_albedo(sa, ss)
    l_tr = 1.0 / st
    thin = geo["thin_mm"]
    tau_thin = thin / l_tr
    eta = material.eta
    R_ms = semi_infinite_albedo(alpha, eta)
    ms_estimate = R_ms * E
    facts.update(reduced_albedo=alpha.tolist(), optical_thickness=tau_thin.tolist(), ms_albedo=R_ms.tolist(),
                 transport_mfp_mm=l_tr.tolist())

    # Validity per surface node: local thickness in transport mean free paths, local albedo.
    area = area / max(area.sum(), 1e-300)
    tau_node = geo["node_mm"][:, None] * (sa_s + ss_s)
    thin_node = tau_node < THICK_MIN
    low_node = reduced_albedo(sa_s, ss_s) < ALBEDO_MIN
    valid_node = ~(thin_node | low_node)
    everywhere = ~valid_node.any(axis=0)  # exact, not a sum of areas that rounds below 1
    invalid_frac = np.where(everywhere, 1.0, np.minimum(area @ (~valid_node), 1.0))
    thin_frac = np.where(thin_node.all(axis=0), 1.0, area @ thin_node)
    low_frac = np.where(low_node.all(axis=0), 1.0, area @ low_node)
    facts.update(invalid_fraction=invalid_frac.tolist(), thin_fraction=thin_frac.tolist(),
                 low_albedo_fraction=low_frac.tolist())

    # Single-scattering estimate: a half-space returns (1 - ln 2)/2 alpha = 0.153 alpha of the
    # light once scattered (isotropic phase); a thin part at most its optical thickness' share.
    albedo_ss = ss / st
    ss_estimate = 0.5 * (1.0 - np.log(2.0)) * albedo_ss * np.minimum(1.0, st * thin) * E
    brightest = max(float(np.max(np.maximum(ms_estimate, ss_estimate))), 1e-300)
    facts.update(ms_estimate=ms_estimate.tolist(), ss_estimate=ss_estimate.tolist())

    def where(c: int) -> str:
        """The region where diffusion is doubtful in channel c, in numbers."""
        parts = []
        if thin_frac[c] > 0:
            parts.append(f"thinner than {THICK_MIN * l_tr[c]:.2g} mm ({THICK_MIN:g} transport mean free path)")
        if low_frac[c] > 0:
            parts.append(f"reduced albedo below {ALBEDO_MIN}")
        return " or ".join(parts) + f": {_pct(invalid_frac[c])} of the surface"

    def why_invalid(c: int) -> str:
        if alpha[c] < ALBEDO_MIN or low_frac[c] >= 1.0:
            return f"reduced albedo {alpha[c]:.2f} < {ALBEDO_MIN}"
        return f"optically thin: {tau_thin[c]:.1f} transport mean free paths across its thin parts"

    ms_ch, ms_why, ms_w = [], [], np.ones((n_surface, 3))
    ss_replaces = [False, False, False]
    unbaked = {}  # channel -> share of the surface where single scattering would be better, not available
    for c in range(3):
        C = CHANNELS[c]
        negligible = ms_estimate[c] < NEGLIGIBLE * brightest
        # where it is valid, diffusion returns too little to be worth a solve: single scattering takes it all
        rest_negligible = (1.0 - invalid_frac[c]) * ms_estimate[c] < NEGLIGIBLE * brightest
        if ss_available and 0.0 < invalid_frac[c] < 1.0 and rest_negligible and not negligible:
            ms_ch.append(False)
            cause = "optically thin" if thin_frac[c] > 0 else "low albedo"
            ms_why.append(f"{C}: diffusion invalid ({cause}) where {where(c)}; single scattering replaces it everywhere "
                          f"(the rest returns {_pct((1.0 - invalid_frac[c]) * ms_estimate[c] / brightest)} "
                          "of the brightest channel)")
            ss_replaces[c] = True
        elif invalid_frac[c] >= 1.0:
            if ss_available:
                ms_ch.append(False)
                ms_why.append(f"{C}: diffusion invalid ({why_invalid(c)})")
                ss_replaces[c] = True
            elif negligible:
                ms_ch.append(False)
                ms_why.append(f"{C}: diffusion invalid ({why_invalid(c)}) and it returns "
                              f"{_pct(ms_estimate[c] / brightest)} of the brightest channel")
                unbaked[c] = 1.0
            else:
                ms_ch.append(True)
                ms_why.append(f"{C}: diffusion doubtful everywhere ({why_invalid(c)}); it runs because "
                              + ("single scattering is not baked or is turned off" if single_pass
                                 else "a particle fluid has no other pass"))
                unbaked[c] = 1.0
        elif negligible:
            ms_ch.append(False)
            ms_why.append(f"{C}: negligible ({_pct(ms_estimate[c] / brightest)} of the brightest channel)")
        elif invalid_frac[c] > 0.0:
            ms_ch.append(True)
            if ss_available:
                ms_w[:, c] = valid_node[:, c]
                ss_replaces[c] = True
                ms_why.append(f"{C}: diffusion valid on {_pct(1.0 - invalid_frac[c])} of the surface; single "
                              f"scattering replaces it where {where(c)}")
            else:
                ms_why.append(f"{C}: diffusion doubtful where {where(c)}; it runs there too")
                unbaked[c] = float(invalid_frac[c])
        else:
            ms_ch.append(True)
            ms_why.append(f"{C}: diffusion valid (reduced albedo {alpha[c]:.3f}, "
                          f"{tau_thin[c]:.0f} transport mean free paths thick)")
    multiple = PassDecision("multiple", tuple(ms_ch), ms_why,
                            weights=None if np.all(ms_w == 1.0) else ms_w)
    advice = []
    if unbaked and single_pass:
        chans = "".join(CHANNELS[c] for c in sorted(unbaked))
        share = max(unbaked.values())
        what = "thin parts" if any(thin_frac[c] > 0 for c in unbaked) else "low albedo"
        todo = ("bake it to use it (" + SS_HINT[0].lower() + SS_HINT[1:] + ")" if not has_single_scattering
                else "turn it on to use it (the object's Single Scattering setting)")
        advice.append(f"{chans}: single scattering would be more accurate on {_pct(share)} of the surface "
                      f"({what}); {todo}")

    # The first-scatter split where diffusion runs: what each term brings over a half-space, per channel.
    split_model = half_space_split(eta)
    albedo_1 = ss / st
    ss_cf = split_model.single_escape(albedo_1) * E
    ms_cf = split_model.multiple_escape(albedo_1) * E
    peak = max(float(np.max(ss_cf + ms_cf)), 1e-300)
    split_on = overrides.get("split") is not False and single_pass and not split_blocked
    split = tuple(bool(split_on and ms_ch[c] and ss_cf[c] >= NEGLIGIBLE * peak) for c in range(3))
    facts.update(ss_closed_form=ss_cf.tolist(), ms_closed_form=ms_cf.tolist())

    def split_reason(c: int) -> str:
        C = CHANNELS[c]
        if split[c]:
            return (f"{C}: contained in the diffusion term, which splits it off in closed form (first-scatter "
                    f"split): single scattering brings {_pct(ss_cf[c] / peak)} and multiple scattering "
                    f"{_pct(ms_cf[c] / peak)} of the object's peak (half-space estimate)")
        if split_blocked:
            return f"{C}: contained in the diffusion term; not split off: {split_blocked}"
        if not split_on:
            return f"{C}: contained in the diffusion term; not split off (turned off)"
        return (f"{C}: contained in the diffusion term; split off it would bring {_pct(ss_cf[c] / peak)} of the "
                f"object's peak (< {_pct(NEGLIGIBLE)}): not split")

    ss_ch, ss_why, bound, ss_w = [], [], [], np.zeros((n_surface, 3))
    for c in range(3):
        C = CHANNELS[c]
        b = float(ss_estimate[c] / max(ms_estimate[c], 1e-300)) if ms_ch[c] else 0.0
        bound.append(b)
        if not has_single_scattering:
            ss_ch.append(False)
            ss_why.append(split_reason(c) if ms_ch[c] and not ss_replaces[c] and split_on else f"{C}: not baked")
        elif not ss_available:
            ss_ch.append(False)
            ss_why.append(split_reason(c) if ms_ch[c] and split_on else f"{C}: turned off")
        elif ms_ch[c] and not ss_replaces[c]:
            ss_ch.append(False)
            ss_why.append(split_reason(c))
        elif ss_estimate[c] < NEGLIGIBLE * brightest:
            ss_ch.append(False)
            ss_why.append(f"{C}: negligible ({_pct(ss_estimate[c] / brightest)} of the brightest channel)")
        elif ms_ch[c]:
            ss_ch.append(True)
            ss_w[:, c] = ~valid_node[:, c]
            ss_why.append(f"{C}: the valid term where diffusion is not ({where(c)})")
        else:
            ss_ch.append(True)
            ss_w[:, c] = 1.0
            ss_why.append(f"{C}: the valid term where diffusion is not")
    single = PassDecision("single", tuple(ss_ch), ss_why, tuple(bound),
                          weights=None if all(np.all(ss_w[:, c] == 1.0) for c in range(3) if ss_ch[c]) else ss_w)
    if not single_pass:
        single = None

    multiple.split = split
    if split_replacement is not None:
        single, vnm = split_replacement(single)
    for p in (multiple, single, vnm):
        if p is None:
            continue
        force = overrides.get(p.name)
        if force is not None:
            p.channels = (bool(force),) * 3
            why = (override_reasons or {}).get(p.name) or "by the user"
            p.reasons = [f"{CHANNELS[c]}: forced {'on' if force else 'off'} {why}" for c in range(3)]
            p.forced = True
            p.weights = None
    if overrides.get("single") is True:  # the forced RBF pass covers everything: no closed-form term on top
        multiple.split = (False, False, False)
    if not (multiple.runs or (single is not None and single.runs) or (vnm is not None and vnm.runs)):
        return Plan(name, False, _nothing_runs(multiple, single, ss_available), multiple, single, facts=facts,
                    advice=advice, voxel_number_map=vnm)
    cost = 0.0
    if multiple.runs:
        cost += ms_cost(multiple.channels)
    if single is not None and single.runs:
        cost += 5.0
    if vnm is not None and vnm.runs:
        cost += vnm_cost
    return Plan(name, True, "runs", multiple, single, estimated_ms=cost, facts=facts, advice=advice,
                voxel_number_map=vnm)


# What the accuracy bench measured on the paper's scenes (docs/accuracy.md, "Objects with inner parts"):
# the scattering passes against Mitsuba's scattered light, and their frame time on 2 CPU cores.
MEASURED_INNER_PARTS = ("measured against a path tracer on a cube with a cavity: single scattering 51 %, the Voxel "
                        "Number Map 59 % relative RMS, about 19 against 8 ms per frame; docs/accuracy.md")


def inner_parts(bake) -> dict:
    """{role: count} of the bake's inner parts ({} for a plain object)."""
    comp = getattr(bake, "composite", None)
    out: dict = {}
    for role in getattr(comp, "roles", ()) or ():
        out[role] = out.get(role, 0) + 1
    return out


def replacement_pass(ss_available: bool, vnm_available: bool, parts: dict, ss_knows_parts: bool = False):
    """Which pass replaces diffusion where it is invalid: ``"voxel_number_map"``, ``"single"`` or None.

    Measured on the paper's scenes against Mitsuba's scattered light
    (docs/accuracy.md, "Objects with inner parts"): single scattering baked
    with the inner parts (``voxelise_composite``) is the more accurate of the
    two everywhere (8 points of relative RMS on the cubes and on the bottle;
    both miss what they do not model: multiple scattering and the light the
    boundary reflects back inside), the Voxel Number Map about 2x faster per
    frame.  So: single scattering when it is baked and knows the parts (or
    there are none); otherwise the Voxel Number Map, whose chords cross
    cavities, inner media and opaque parts as they are; single scattering
    that does not know the parts only when there is no map.
    """
    if ss_available and (not parts or ss_knows_parts):
        return "single"
    if vnm_available:
        return "voxel_number_map"
    if ss_available:
        return "single"
    return None


def _split_replacement(single: PassDecision, replacement, baked_ss: bool, ss_on: bool, baked_vnm: bool, vnm_on: bool,
                       parts: dict):
    """The replacement pass's decision goes to single scattering or to the Voxel Number Map; the other says why not."""
    kinds = ", ".join(f"{n} {r}{'s' if n > 1 and r != 'opaque' else ''}" for r, n in sorted(parts.items()))
    if replacement == "voxel_number_map":
        vnm = PassDecision("voxel_number_map", single.channels,
                           [r.replace("single scattering", "the Voxel Number Map") for r in single.reasons],
                           single.bound, weights=single.weights)
        if not baked_ss:
            why = "not baked"
        elif not ss_on:
            why = "turned off"
        else:
            why = (f"the Voxel Number Map replaces it: the object has inner parts ({kinds}) that the single-"
                   f"scattering bake does not know (bake it with the parts to use it; {MEASURED_INNER_PARTS})")
        return PassDecision("single", (False,) * 3, [f"{C}: {why}" for C in CHANNELS]), vnm
    if not baked_vnm:
        why = "not baked"
    elif not vnm_on:
        why = "turned off"
    elif replacement == "single":
        why = ("single scattering replaces diffusion here: " + ("no inner parts" if not parts else
               f"baked with the inner parts, it is the more accurate ({MEASURED_INNER_PARTS})"))
    else:
        why = "nothing to replace"
    if replacement is None or not baked_ss and replacement != "single":
        single = PassDecision("single", (False,) * 3, [f"{C}: not baked" if not baked_ss else f"{C}: turned off"
                                                       for C in CHANNELS])
    vnm = PassDecision("voxel_number_map", (False,) * 3, [f"{C}: {why}" for C in CHANNELS])
    return single, vnm


def _nothing_runs(multiple: PassDecision, single: PassDecision | None, ss_available: bool) -> str:
    """Why no pass runs, in numbers: every channel's reason (never a bare 'skipped')."""
    forced_off = multiple.forced and not any(multiple.channels) and (single is None or single.forced
                                                                     or not ss_available)
    if forced_off:
        return ("every pass is turned off in the object's settings: turn Multiple Scattering (or Single "
                "Scattering, once baked) back on in its Translucency panel")
    if ss_available or single is None:
        hint = ("a material with a higher reduced albedo (sigma_s' / (sigma_a + sigma_s')) above "
                f"{ALBEDO_MIN} returns light by diffusion")
        return "no pass returns light (" + "; ".join(multiple.reasons) + "). " + hint[0].upper() + hint[1:]
    return ("no pass returns light (" + "; ".join(multiple.reasons) + "; single scattering is not baked). "
            + SS_HINT + " to render the light these channels scatter once")


def _fluid_validity(plan: Plan) -> str:
    """"diffusion valid", or where it is doubtful, for the channels that run (the fluid's first line)."""
    running = [c for c in range(3) if plan.multiple.channels[c]]
    if not running:
        return "diffusion off"
    doubtful = [c for c in running if plan.facts.get("invalid_fraction", (0.0,) * 3)[c] > 0.0]
    if not doubtful:
        return "diffusion valid"
    return "diffusion doubtful in " + "".join(CHANNELS[c] for c in doubtful) + " (see below)"


def _pct(x: float) -> str:
    v = 100.0 * x
    return "< 0.01 %" if x < 1e-4 else (f"{v:.2g} %" if v < 10 else f"{v:.0f} %")


def describe_plan(plan: Plan) -> str:
    """Multi-line, user-facing description (CLI and panel)."""
    if not plan.run:
        lines = [f"{plan.object_name}: skipped -- {plan.reason}"]
    else:
        lines = [f"{plan.object_name}: runs (estimated {plan.estimated_ms:,.0f} ms per frame)"]
    if "particles" in plan.facts:
        lines.insert(1, f"  fluid: {plan.facts['particles']:,} particles" + (
            f", {_fluid_validity(plan)}" if plan.multiple is not None else ""))
    for label, p in (("multiple scattering", plan.multiple), ("single scattering", plan.single),
                     ("Voxel Number Map", plan.voxel_number_map)):
        if p is None:
            continue
        on = "".join(ch if run else "-" for ch, run in zip(CHANNELS, p.channels))
        extra = ""
        if p.name == "multiple" and any(p.split):
            extra = " + closed-form single scattering [" + "".join(
                ch if run else "-" for ch, run in zip(CHANNELS, p.split)) + "]"
        lines.append(f"  {label} [{on}]{extra}{' (forced)' if p.forced else ''}")
        for r in p.reasons:
            lines.append(f"    {r}")
    for a in plan.advice:
        lines.append(f"  better: {a}")
    return "\n".join(lines)


# ----------------------------------------------------------------- change tracking
def fingerprint(*parts) -> str:
    """Stable hash of numbers, arrays and strings (for change tracking)."""
    h = hashlib.sha1()
    for p in parts:
        if isinstance(p, np.ndarray):
            h.update(np.ascontiguousarray(p).tobytes())
        elif isinstance(p, (list, tuple)):
            h.update(fingerprint(*p).encode())
        else:
            h.update(repr(p).encode())
    return h.hexdigest()


@dataclass
class ObjectState:
    """What one object's solution depends on, as fingerprints."""

    material: str
    geometry: str
    lights: dict  # light name -> fingerprint, only the lights that reach it
    camera: str
    plan: str = ""


@dataclass
class FrameWork:
    """What a frame must recompute for one object."""

    multiple: bool
    single: bool
    reasons: list


class ChangeTracker:
    """Re-solve only what changed since the last frame.

    ``update(name, state)`` returns a :class:`FrameWork`: diffusion re-solves
    when the material/field, the geometry, the plan or any light that reaches
    the object changed (including a light starting or stopping to reach it);
    single scattering additionally when the camera moved.  Unchanged objects do
    no work.
    """

    def __init__(self):
        self.states: dict[str, ObjectState] = {}
        self.solves = {"multiple": 0, "single": 0}

    def update(self, name: str, state: ObjectState) -> FrameWork:
        old = self.states.get(name)
        self.states[name] = state
        if old is None:
            work = FrameWork(True, True, ["first frame"])
        else:
            why = []
            if old.material != state.material:
                why.append("material changed")
            if old.geometry != state.geometry:
                why.append("geometry changed")
            if old.plan != state.plan:
                why.append("passes changed")
            if old.lights != state.lights:
                moved = sorted(set(old.lights.items()) ^ set(state.lights.items()))
                why.append("lights changed: " + ", ".join(sorted({k for k, _ in moved})))
            ms = bool(why)
            camera = old.camera != state.camera
            work = FrameWork(ms, ms or camera, why + (["camera moved"] if camera else []))
        self.solves["multiple"] += int(work.multiple)
        self.solves["single"] += int(work.single)
        return work

    def forget(self, name: str) -> None:
        self.states.pop(name, None)


def light_fingerprint(light: Light) -> str:
    return fingerprint(light.kind, light.color, light.intensity, light.irradiance, light.position, light.direction,
                       light.spot_size, light.spot_blend)
