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
  transport mean free paths.  Near the albedo limit, from ``ALBEDO_MIN`` to
  ``ALBEDO_FULL`` (0.6), diffusion is blended with the pass that replaces it
  (its weight rising linearly from 0 to 1, :func:`.planner_rules.diffusion_weight`):
  against a random walk of a 10 mm sphere (eta 1.3) diffusion alone is +7.9 %
  at 0.51 and +2.7 % at 0.6, single scattering with the orders after the
  first -3.6 % at 0.49, so the frame is continuous across 0.5.  A 10 mm cube with alpha' = 0.98 under uniform light:
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
  :mod:`.diffusion.split`): closed-form single scattering of the
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

Where it is: one small rule per pass in :mod:`.planner_rules`
(``decide_diffusion``, ``decide_split``, ``decide_single``,
``replacement_pass`` / ``hand_over`` for the Voxel Number Map, ``force``,
``nothing_runs``), each returning its reasons as data (``Reason``: what, the
measured value, the threshold); the words made from them in
:mod:`.planner_messages`; the measurements (thickness, light) in
:mod:`.planner_facts`; change tracking in :mod:`.planner_changes`.  This
module assembles a :class:`Plan` from them and keeps the public names.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .scene.lights import Environment
from .scene.materials import Material, reduced_albedo
from .planner_changes import ChangeTracker, FrameWork, ObjectState, fingerprint, light_fingerprint
from .planner_facts import fluid_thickness, light_reaching, object_thickness, surface_thickness, unlit_misses
from .planner_messages import (CHANNELS, MEASURED_INNER_PARTS, SS_HINT, advice_text, describe_plan, plan_reason_text,
                               reason_texts, unlit_text)
from .planner_rules import (ALBEDO_FULL, ALBEDO_MIN, NEGLIGIBLE, THICK_MIN, Decision, Reason, Why, decide_diffusion,
                            decide_single, decide_split, force, hand_over, is_lit, measure, nothing_runs,
                            replacement_pass, skip_object)
from .diffusion.split import half_space_split, semi_infinite_albedo  # the planner's measure

__all__ = [  # the public names, wherever they are defined (tests, ops/, bench/ and the CLI import them from here)
    "ALBEDO_FULL", "ALBEDO_MIN", "CHANNELS", "FLUID_MS_PER_PARTICLE", "MEASURED_INNER_PARTS", "NEGLIGIBLE", "SS_HINT", "THICK_MIN",
    "ChangeTracker", "FrameWork", "ObjectState", "PassDecision", "Plan", "describe_plan", "fingerprint",
    "fluid_thickness", "half_space_split", "inner_parts", "light_fingerprint", "light_reaching",
    "object_thickness", "plan_fluid", "plan_object", "replacement_pass", "semi_infinite_albedo",
    "surface_thickness", "unlit_reason",
]



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
    why: tuple = ()  # the reasons as data, one planner_rules.Reason per channel (``reasons`` is made from them)

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
    why: Reason | None = None  # ``reason`` as data (planner_rules.Why: runs, disabled, unlit, ...)
    # (n_surface, 3) reduced albedo at the finest level's surface nodes, as the rules measured it: what the
    # orders after the first scale with where a pass replaces diffusion (frame.orders_after_the_first).
    surface_albedo: np.ndarray | None = field(default=None, repr=False, compare=False)

    @property
    def passes(self) -> dict:
        return {p.name: p for p in (self.multiple, self.single, self.voxel_number_map) if p is not None}

    def channel_mask(self, name: str) -> np.ndarray:
        p = self.passes.get(name)
        return np.array(p.channels if (p is not None and self.run) else (False, False, False))

    def replaces_diffusion(self, name: str) -> tuple:
        """The channels in which pass ``name`` (single scattering or the Voxel Number Map) runs because it
        replaces diffusion (everywhere or in a region), not because an override forced it on."""
        p = self.passes.get(name)
        if p is None or not self.run:
            return (False, False, False)
        kinds = (Why.REPLACES, Why.REPLACES_IN_REGION, Why.BLENDS)
        return tuple(bool(p.channels[c] and c < len(p.why) and p.why[c].what in kinds) for c in range(3))

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



def unlit_reason(lights, environment, center, radius_units: float) -> str:
    """Why no light reaches an object, light by light in numbers, and what to change (a plan's skip)."""
    return unlit_text(*unlit_misses(lights, environment, center, radius_units))


@dataclass(frozen=True)
class InnerParts:
    """What decides between single scattering and the Voxel Number Map (:func:`.planner_rules.hand_over`):
    the pass :func:`replacement_pass` chose, each pass baked and turned on, the parts ({role: count}), and
    the map's cost (ms per frame)."""

    replacement: str | None
    baked_ss: bool
    ss_on: bool
    baked_vnm: bool
    vnm_on: bool
    parts: dict
    vnm_cost: float


@dataclass(frozen=True)
class PlanInputs:
    """One object's facts for :func:`_plan`, gathered by :func:`plan_object` or :func:`plan_fluid`.

    ``geo``: :func:`object_thickness` (or :func:`fluid_thickness`); ``area``: per surface node; ``bulk`` and
    ``surface``: (sigma_a, sigma_s') of the bulk (3,) and per surface node (n_surface, 3); ``ms_cost(channels)``:
    diffusion's ms per frame.  ``single_pass`` False: the object has no single-scattering pass at all (a particle
    fluid), so diffusion, its only pass, runs wherever it returns light.  ``has_pass``: a pass that can replace
    diffusion is baked; ``ss_available``: and not turned off.  ``inner``: objects only (single scattering or the Voxel Number Map).
    """

    name: str
    geo: dict
    area: np.ndarray
    eta: float
    bulk: tuple
    surface: tuple
    mm_per_unit: float
    ms_cost: object
    single_pass: bool = True
    has_pass: bool = False
    ss_available: bool = False
    inner: InnerParts | None = None


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
    if hasattr(material, "outer"):  # a composite_bake.CompositeMaterial: plan for the outer medium
        material, field_values = material.outer, None
    vnm_n = bake.voxel_number_map.n if getattr(bake, "voxel_number_map", None) is not None else 2000
    # the packed kernel read once per frame (~2 GB/s on a CPU core) plus the light pass
    inner = InnerParts(replacement, has_single_scattering, ss_real, bool(has_voxel_number_map), vnm_real, parts,
                       vnm_cost=1.0 + 6e-6 * vnm_n * vnm_n / 2.0)

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
    inputs = PlanInputs(
        name, geo, np.asarray(lv.area, dtype=np.float64), material.eta, bulk, surface, bake.mm_per_unit,
        ms_cost=lambda channels: 1e-4 * lv.n_nodes * sum(channels) / 3.0,  # ~0.1 us per node-channel sweep x ~50
        # "single scattering" below is the pass that replaces diffusion (single scattering or the map)
        has_pass=bool(has_single_scattering or has_voxel_number_map), ss_available=replacement is not None,
        inner=inner)
    plan = _plan(inputs, lights, environment, overrides, override_reasons)
    if parts and plan.facts:
        plan.facts["inner_parts"] = parts
        plan.facts["replacement"] = replacement
    return plan


# Measured per-frame cost of a fluid (cells + warm solve + output), per particle: 5,105 ms at 16,375
# particles on 2 CPU cores (docs/bench_fluid.md); the stages grow about linearly with N.
FLUID_MS_PER_PARTICLE = 0.31


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
    inputs = PlanInputs(name, geo, np.ones(1), material.eta, bulk, surface, mm_per_unit,
                        ms_cost=lambda _channels: FLUID_MS_PER_PARTICLE * len(P),  # every channel in one cell build
                        single_pass=False)
    plan = _plan(inputs, lights, environment, overrides)
    plan.facts["particles"] = len(P)
    plan.facts["radius_units"] = float(radius)
    return plan


def _skipped(name: str, enabled: bool, in_view: bool) -> Plan | None:
    why = skip_object(enabled, in_view)
    return None if why is None else Plan(name, False, plan_reason_text(Reason(why)), why=Reason(why))


def _pass(name: str, d: Decision | None) -> PassDecision | None:
    """A rule's decision as the plan's pass, its reasons in words (:mod:`.planner_messages`)."""
    if d is None:
        return None
    return PassDecision(name, d.channels, reason_texts(d.why), d.bound, forced=d.forced, split=d.split,
                        weights=d.weights, why=d.why)


def _plan(o: PlanInputs, lights, environment, overrides: dict, override_reasons: dict | None = None) -> Plan:
    """The passes of one object: light, then each pass's rule (:mod:`.planner_rules`), the overrides, the cost."""
    geo = o.geo
    E, reaching = light_reaching(lights, environment, geo["center"], geo["radius_units"], o.mm_per_unit)
    facts = {"thin_mm": geo["thin_mm"], "radius_mm": geo["radius_mm"], "irradiance": E.tolist(),
             "lights_reaching": [getattr(light, "name", "") for light in reaching]}
    if not is_lit(E, overrides):
        why = Reason(Why.UNLIT, detail=unlit_misses(lights, environment, geo["center"], geo["radius_units"]))
        return Plan(o.name, False, plan_reason_text(why), facts=facts, why=why)
    f = measure(geo, o.area, o.eta, o.bulk, o.surface, E)
    facts.update(f.as_facts())

    ms = decide_diffusion(f, o.ss_available, o.single_pass)
    advice = [advice_text(ms.unbaked, f.thin_fraction, o.has_pass)] if ms.unbaked and o.single_pass else []
    split_on = overrides.get("split") is not False and o.single_pass
    ms.split = decide_split(f, ms, split_on)
    single = decide_single(f, ms, o.has_pass, o.ss_available, split_on) if o.single_pass else None
    vnm = None
    if o.inner is not None:
        i = o.inner
        single, vnm = hand_over(single, i.replacement, i.baked_ss, i.ss_on, i.baked_vnm, i.vnm_on, i.parts)
    for name, d in (("multiple", ms), ("single", single), ("voxel_number_map", vnm)):
        if d is not None and overrides.get(name) is not None:
            force(d, overrides[name], (override_reasons or {}).get(name) or "by the user")
    if overrides.get("single") is True:  # the forced RBF pass covers everything: no closed-form term on top
        ms.split = (False, False, False)

    multiple, single_p, vnm_p = _pass("multiple", ms), _pass("single", single), _pass("voxel_number_map", vnm)
    if not (ms.runs or (single is not None and single.runs) or (vnm is not None and vnm.runs)):
        why = nothing_runs(ms, single, o.ss_available)
        return Plan(o.name, False, plan_reason_text(why, multiple.reasons), multiple, single_p, facts=facts,
                    advice=advice, voxel_number_map=vnm_p, why=why)
    cost = 0.0
    if ms.runs:
        cost += o.ms_cost(ms.channels)
    if single is not None and single.runs:
        cost += 5.0
    if vnm is not None and vnm.runs:
        cost += o.inner.vnm_cost
    return Plan(o.name, True, "runs", multiple, single_p, estimated_ms=cost, facts=facts, advice=advice,
                voxel_number_map=vnm_p, why=Reason(Why.RUNS), surface_albedo=reduced_albedo(*o.surface))


def inner_parts(bake) -> dict:
    """{role: count} of the bake's inner parts ({} for a plain object)."""
    comp = getattr(bake, "composite", None)
    out: dict = {}
    for role in getattr(comp, "roles", ()) or ():
        out[role] = out.get(role, 0) + 1
    return out
