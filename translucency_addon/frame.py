# SPDX-License-Identifier: GPL-3.0-or-later
"""One frame of one baked object: the recipe the add-on, the command line and the benches share.

    plan          planner.plan_object, the object's switches as overrides (:func:`pass_overrides`)
    -> passes     which passes run, on which channels, and where the diffusion solve adds the
                  first-scatter split's single scattering (:func:`passes_for`)
    -> diffusion  the solve: with the split's channels, the interreflection bounce when the bake has
                  sky visibility, the cavity exchange when it has cavities (:func:`diffuse`)
    -> radiance   the diffusive sources' outgoing radiance at the mesh's vertices, towards the view
                  (:func:`multiple_radiance`: corrected eqs. 4 / 7 and the split's closed form)
    -> terms      single scattering (Bernabei et al.; :func:`single_evaluator`) and the Voxel Number
                  Map (Mochida et al.) where the plan runs them
    -> compose    each term weighted by the planner's region, summed, refused if not finite
                  (:func:`compose`)
    -> orders     where a pass replaces diffusion, the light it does not return: the orders after the
                  first, from the half-space's ratio to the first (:func:`orders_after_the_first`)

:func:`render_frame` runs the whole chain for one frame from scratch (the CLI's ``solve``); the add-on's
runtime (``ops/runtime.py``) runs the same steps, keeping the solver, the last solution and the
evaluators between frames and re-running only what a change needs.  Neither adds a term, a weight or
a clamp of its own: a frame's answer is this module's.

bpy-free: views are ``None`` (along the normals), ``("PERSP", eye)`` or ``("ORTHO", towards_viewer)``
in object space; lengths in object units, coefficients per mm with ``bake.mm_per_unit``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from .errors import TranslucencyError

CHANNELS_OFF = (False, False, False)


@dataclass(frozen=True)
class MeshMapping:
    """How values at the finest surface nodes reach the vertices a frame is written to.

    ``same``: those vertices are the baked mesh's (the first ``len(idx)`` rows of ``bake.mesh_vertices``),
    so the bake's own map serves; otherwise (a modifier changed the vertex count) a map to other
    ``positions`` and ``normals``, whose ``digest`` keys what is cached per vertex set.
    """

    same: bool
    idx: np.ndarray
    w: np.ndarray
    positions: np.ndarray | None = None
    normals: np.ndarray | None = None
    digest: str | None = None


def bake_mapping(bake, n: int | None = None) -> MeshMapping:
    """The bake's own map onto its first ``n`` mesh vertices (default: all of them, cavity walls included)."""
    idx, w = bake.vertex_map
    n = len(idx) if n is None else int(n)
    return MeshMapping(True, np.asarray(idx)[:n], np.asarray(w)[:n])


def n_outer_vertices(bake) -> int:
    """Vertices of the outer mesh: a bake with inner parts continues ``mesh_vertices`` with the cavity walls."""
    info = getattr(bake, "composite", None)
    return len(bake.mesh_vertices) if info is None else int(info.n_outer_vertices)


def outer_mesh(bake) -> tuple:
    """``(V, F, N)`` of the outer mesh of a bake (the whole baked mesh when it has no inner parts)."""
    n = n_outer_vertices(bake)
    V, F, N = bake.mesh_vertices, np.asarray(bake.mesh_faces), bake.mesh_normals
    if n == len(V):
        return V, F, N
    return V[:n], F[np.all(F < n, axis=1)], N[:n]


def view_directions(view, positions) -> np.ndarray | None:
    """Unit vectors from each point towards the viewer (None: along the normal)."""
    if view is None:
        return None
    kind, value = view
    positions = np.asarray(positions, dtype=np.float64)
    if kind == "ORTHO":
        return np.broadcast_to(np.asarray(value, dtype=np.float64), positions.shape).copy()
    d = np.asarray(value, dtype=np.float64)[None, :] - positions
    return d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-30)


# ------------------------------------------------------------------ plan -> passes


def pass_overrides(*, multiple: bool = True, single: bool = True, has_single: bool = False,
                   voxel_number_map: bool = True, has_voxel_number_map: bool = False,
                   all_passes: bool = False) -> dict:
    """The planner's overrides from an object's switches (the panel's, or the CLI's flags).

    A term that is off, or single scattering that is not baked, is forced off; with Pass Planning
    "All Passes" every term that is on (and baked) is forced on, on every channel.
    """
    out = {}
    if not multiple:
        out["multiple"] = False
    elif all_passes:
        out["multiple"] = True
    if not (single and has_single):
        out["single"] = False
    elif all_passes:
        out["single"] = True
    if not voxel_number_map:
        out["voxel_number_map"] = False
    elif all_passes and has_voxel_number_map:
        out["voxel_number_map"] = True
    return out


@dataclass(frozen=True)
class FramePasses:
    """What runs this frame, from the plan: the passes and the diffusion's channels.

    ``single_channels``: where the diffusion solve adds the first-scatter split's closed-form single
    scattering (the split), so the terms add up without counting a path twice.
    """

    use_ms: bool
    use_ss: bool
    use_vnm: bool
    ms_channels: tuple = CHANNELS_OFF
    single_channels: tuple = CHANNELS_OFF


def passes_for(plan, bake, want_ms: bool = True) -> FramePasses:
    """The passes ``plan`` runs on ``bake`` (single scattering and the map only where baked)."""
    vnm = plan.voxel_number_map
    return FramePasses(
        use_ms=bool(want_ms and plan.run and plan.multiple.runs),
        use_ss=bool(plan.run and plan.single.runs and bake.single_scattering is not None),
        use_vnm=bool(plan.run and vnm is not None and vnm.runs and bake.voxel_number_map is not None),
        ms_channels=plan.multiple.channels if plan.multiple is not None else CHANNELS_OFF,
        single_channels=plan.multiple.split if plan.multiple is not None else CHANNELS_OFF)


def lights_at_quality(lights, quality: str) -> tuple:
    """The lights as a frame of this bake quality renders them: at Draft every light is a point (one
    shadow ray; ``Light.samples`` 1: an area light's 16 patches and 4 shadow rays, a sphere light's 4,
    cost 3.4-3.7x a point's light pass), at Preview and Final as they are.  The add-on and the CLI both
    call it, so a Draft frame is the same either way."""
    if str(quality).lower() != "draft":
        return tuple(lights)
    from dataclasses import replace

    return tuple(replace(x, samples=1) if x.kind != "sun" else x for x in lights)


def single_scattering_needed(material, thickness_mm: float) -> str:
    """Why this material needs single scattering baked ('' when diffusion holds alone): the planner's own
    criteria (``planner.ALBEDO_MIN``, ``ALBEDO_FULL``, ``THICK_MIN``) on the material's media before any bake.

    Where a medium's reduced albedo is below ``ALBEDO_MIN`` in a channel, or the object (``thickness_mm``:
    its smallest extent) is thinner than ``THICK_MIN`` transport mean free paths, the planner hands that
    channel to single scattering; without its bake the channel renders black (diffusion there returns a
    fraction of the light, or several times too much).  Between ``ALBEDO_MIN`` and ``ALBEDO_FULL`` the
    planner blends diffusion with single scattering (``planner_rules.diffusion_weight``); without its bake
    diffusion runs alone there, up to 8 % too bright.  A bake asks this first, so no default scene renders
    black, or less accurate than it could, because a pass was not baked.
    """
    from .scene.materials import reduced_albedo
    from .planner import ALBEDO_FULL, ALBEDO_MIN, THICK_MIN
    from .planner_rules import diffusion_weight

    media = [material.medium_a] + ([material.medium_b] if material.medium_b is not None else [])
    names = "RGB"
    for m in media:
        sa, ss = m.arrays()
        alpha = reduced_albedo(sa, ss)
        low = [names[c] for c in range(3) if alpha[c] < ALBEDO_MIN]
        if low:
            return (f"{m.name or 'the medium'} has a reduced albedo of {min(alpha):.2f} (below {ALBEDO_MIN}) in "
                    f"{', '.join(low)}: diffusion does not hold there (without single scattering those channels "
                    "would render black)")
        l_tr = 1.0 / (sa + ss)  # transport mean free path, mm
        thin = [names[c] for c in range(3) if thickness_mm < THICK_MIN * l_tr[c]]
        if thin:
            return (f"the object ({thickness_mm:.3g} mm thin) is thinner than {THICK_MIN:g} transport mean free "
                    f"path ({max(l_tr):.3g} mm) of {m.name or 'the medium'} in {', '.join(thin)}: diffusion "
                    "does not hold there (without single scattering those channels would render black)")
        near = [names[c] for c in range(3) if diffusion_weight(alpha[c]) < 1.0]  # the planner's blend
        if near:
            return (f"{m.name or 'the medium'} has a reduced albedo of {min(alpha):.2f} in {', '.join(near)}, "
                    f"between {ALBEDO_MIN} and {ALBEDO_FULL}: diffusion is blended with single scattering there "
                    "(alone it would be up to 8 % too bright)")
    return ""


# ------------------------------------------------------------------ the passes


def diffuse(solver, bake, lights, environment, passes: FramePasses, *, tol: float, occluders=None,
            warm_start=None, shadows: bool = True) -> tuple:
    """One multiple-scattering solve of the frame: ``(result, bounce, cavity_exchange)``;
    :func:`diffuse_steps` run to its end."""
    from .diffusion.iterative import drain

    return drain(diffuse_steps(solver, bake, lights, environment, passes, tol=tol, occluders=occluders,
                               warm_start=warm_start, shadows=shadows))


def diffuse_steps(solver, bake, lights, environment, passes: FramePasses, *, tol: float, occluders=None,
                  warm_start=None, shadows: bool = True):
    """:func:`diffuse` as a generator for the viewport's progressive frames (:mod:`.progressive`): it yields
    what ``DiffusionSolver.solve_steps`` yields (functions that return the solve so far) where the frame is
    one solve on the CPU -- without sky visibility, or with the bounce's block solve -- and returns
    ``(result, bounce, cavity_exchange)``.  The cavity exchange (GMRES around the solver), the bounce's two
    passes and the GPU backend run to their end before it returns, yielding nothing.

    With the split on ``passes.single_channels``; with the interreflection bounce when the bake has
    sky visibility (``DiffusionSolver.solve_interreflected``: the bounce comes from a first solve of
    the same frame, never an earlier one, so a frame depends only on its own inputs); through
    ``cavity.solve_with_cavities`` (the wall exchange, GMRES around the same solver, the split carried
    into the hollow) when the bake has cavities, without the bounce.  ``bounce`` is None where none was
    solved; ``cavity_exchange`` is
    the exchange's report (its GMRES residual and iterations), None without cavities.
    """
    lights = list(lights)
    exchange = getattr(getattr(bake, "composite", None), "exchange", None)
    if exchange is not None:
        from .inner_parts.cavity import solve_with_cavities

        result, info = solve_with_cavities(solver, exchange, lights, environment, tol=tol, warm_start=warm_start,
                                           shadows=shadows, occluders=occluders, channels=passes.ms_channels,
                                           single=passes.single_channels)
        return result, None, info
    kw = {"warm_start": warm_start, "shadows": shadows, "occluders": occluders, "channels": passes.ms_channels,
          "single": passes.single_channels}
    if solver.sky is None:
        result = yield from solver.solve_steps(lights, environment, **kw)
        return result, None, None
    result, bounce = yield from solver.interreflected_steps(lights, environment, **kw)
    return result, bounce, None


def multiple_radiance(solver, result, bake, mapping: MeshMapping, view) -> np.ndarray:
    """(n, 3) outgoing radiance of the diffusion (and the split's closed form) at the mapping's vertices.

    The baked mesh's own vertex map, or one to other vertices (``mapping.same`` False); either way the
    solver's ``radiance_at`` (corrected eqs. 4 / 7).
    """
    if mapping.same:  # a bake with cavities continues with their walls: the mapping's vertices are the first rows
        dirs = view_directions(view, np.asarray(bake.mesh_vertices))
        return np.asarray(solver.vertex_radiance(result, dirs))[: len(mapping.idx)]
    return np.asarray(solver.radiance_at(result, mapping.idx, mapping.w, mapping.normals,
                                         view_directions(view, mapping.positions)))


def single_evaluator(bake, order: int, mapping: MeshMapping, integrator=None):
    """Single scattering's frame evaluator (Bernabei et al. eq. 3) for the mapping's vertices of the outer mesh.

    ``order``: the SH order used (at most the baked one); ``integrator``: where its view rays run (default
    numpy).
    """
    from .single_scattering import FrameEvaluator

    data = bake.single_scattering
    data_o = data if order == data.order else data.with_order(order)
    V, F, N = outer_mesh(bake)
    if mapping.same:
        return FrameEvaluator(data_o, V, F, N, integrator=integrator)
    return FrameEvaluator(data_o, V, F, points=mapping.positions, point_normals=mapping.normals, integrator=integrator)


@dataclass
class FrameTerms:
    """A frame's radiance, W/(m^2 sr) per vertex: the total and each term as it entered it (weighted)."""

    total: np.ndarray
    multiple: np.ndarray
    single: np.ndarray | None = None
    voxel_number_map: np.ndarray | None = None
    orders: np.ndarray | None = None  # the orders after the first where a pass replaces diffusion


def _rows(rgb, n: int) -> np.ndarray:
    """A term's (n, 3) rows: one evaluated on the outer mesh only is 0 on the cavity walls after it."""
    rgb = np.asarray(rgb, dtype=np.float64)
    if len(rgb) == n:
        return rgb
    out = np.zeros((n, 3))
    out[: len(rgb)] = rgb[:n]
    return out


def compose(plan, mapping: MeshMapping | None, name: str, multiple=None, single=None, voxel_number_map=None,
            n: int | None = None) -> FrameTerms:
    """The frame's radiance: each term weighted by the planner's region (``Plan.vertex_weights``) and summed.

    ``multiple`` None: diffusion did not run (zeros).  A term with NaN or Inf is refused, never written.
    ``mapping`` may be None only when no term ran; ``n`` is then the vertex count (zeros).
    """
    n = len(mapping.idx) if mapping is not None else int(n)
    terms = {}
    for kind, rgb, what in (("multiple", multiple, "the solve"), ("single", single, "single scattering"),
                            ("voxel_number_map", voxel_number_map, "the Voxel Number Map")):
        if rgb is None:
            terms[kind] = None
            continue
        rgb = _rows(rgb, n)
        if not np.all(np.isfinite(rgb)):
            raise TranslucencyError(f"'{name}': {what} produced NaN or Inf radiance; check the material")
        # Every term gets the planner's channels and region.  Diffusion too: a backend that solves every
        # channel (the GPU solver ignores the plan's channel mask) must not add diffusion where the planner
        # found it invalid -- ketchup's green and blue under a sun came out 4.5x and 13x the single
        # scattering that replaces it there, on the GPU only.
        rgb = rgb * plan.vertex_weights(kind, mapping.idx, mapping.w)
        terms[kind] = rgb
    ms = terms["multiple"] if terms["multiple"] is not None else np.zeros((n, 3))
    total = ms + sum(t for t in (terms["single"], terms["voxel_number_map"]) if t is not None)
    return FrameTerms(total, ms, terms["single"], terms["voxel_number_map"])


_SAMPLE_RHO: dict = {}  # rho(alpha_i, 1) of the last samples and index (rest_of_media)
PURE_SHARE = 0.005  # an albedo held by this share of the samples (to 1e-4; 8 at least) is a medium's own
# (sample_rho): single scattering's samples crowd near the surface, and a sphere that fills 27 % of a cube
# holds 1.7 % of them


def sample_rho(media: np.ndarray, split) -> np.ndarray:
    """(N, 3) eq. (5)'s ratio rho(alpha_i, 1) for each sample, per channel.  A sample whose Gaussian straddles
    two media holds a mixed albedo ``alpha = (w_A s_A + w_B s_B) / (w_A t_A + w_B t_B)`` (s, t: each medium's
    sigma_s, sigma_t; w: its share of the Gaussian); its light is each medium's share of sigma_s, so its
    ratio is ``(w_A s_A rho_A + w_B s_B rho_B) / sigma_s``: where the media's extinctions are equal, ``alpha
    rho`` linear in alpha between the media's own albedos (those held by :data:`PURE_SHARE` of the samples or
    more).  rho is convex (0.10 at albedo 0.2, 4.0 at 0.9): at the mixed albedo a bright sphere inside a dark
    cube lost 10 % of its rest, linear in rho 5 % (``tests/test_media_orders.py``).  Beyond the media's
    albedos, and in a field without two, each sample's own."""
    rho = split.multiple_over_single(media, np.ones(len(media)))
    for c in range(media.shape[1]):
        vals, counts = np.unique(np.round(media[:, c], 4), return_counts=True)
        pure = vals[counts >= max(PURE_SHARE * len(media), 8)]
        if len(pure) < 2:
            continue
        at = split.multiple_over_single(np.repeat(pure[:, None], media.shape[1], axis=1), np.ones(len(pure)))[:, c]
        inside = (media[:, c] > pure[0]) & (media[:, c] < pure[-1])
        a = media[inside, c]
        rho[inside, c] = np.interp(a, pure, pure * at) / a
    return rho


def rest_of_media(single_weighted, media: np.ndarray, alpha: np.ndarray, cos_o: np.ndarray, split) -> np.ndarray:
    """(n, 3) eq. (1) of :func:`orders_after_the_first`: single scattering's rest, each sample at its own
    ``media`` albedo (N, 3) through ``single_weighted`` (per-sample weights -> (n, 3) radiance), shaped in
    exit angle by the vertices' own albedo ``alpha`` (n, 3) at ``cos_o`` (n,); ``split`` is
    :func:`.diffusion.split.half_space_split` at the object's index."""
    key = (id(media), len(media), id(split))
    if _SAMPLE_RHO.get("key") != key or _SAMPLE_RHO.get("media") is not media:  # a bake's samples, frame after frame
        _SAMPLE_RHO.update(key=key, media=media, rho=sample_rho(media, split))
    per_sample = single_weighted(_SAMPLE_RHO["rho"])
    rho = split.multiple_over_single(alpha, cos_o)
    return per_sample * rho / np.maximum(split.multiple_over_single(alpha, np.ones(len(alpha))), 1e-300)


def orders_after_the_first(plan, mapping: MeshMapping, bake, terms: FrameTerms, eta: float, view,
                           rest_sources: dict | None = None) -> np.ndarray | None:
    """(n, 3) light scattered two or more times where a pass replaces diffusion, or None where none does.

    Single scattering (Bernabei et al.) and the Voxel Number Map (Mochida et al.) return the once-scattered
    light only; where diffusion is invalid (reduced albedo below the planner's 0.5, or too thin) nothing
    else returns the rest -- 17 % of a dark sphere's light (albedo 0.2, eta 1.3) and 39 % at albedo 0.45,
    against a random walk (docs/accuracy.md, "Media where diffusion fails").  Each such term (as ``compose``
    weighted it) times eq. (5) of :mod:`.diffusion.split`, ``rho(alpha, m)`` -- the half-space transport
    solution's ratio of the orders after the first to the first, at the vertex's reduced albedo (the
    planner's, mapped from the finest surface nodes like every term) and exit angle towards ``view`` -- is
    that rest.  Only in the channels where the pass *replaces* diffusion (``Plan.replaces_diffusion``):
    where diffusion runs it carries those orders itself, and an override that forces every pass on adds
    nothing here.

    **Several media** (a bottle of wine: glass 0.83-0.95, wine 0.13-0.71): the once-scattered light at a
    vertex comes from media whose rest differs tenfold, so each pass's is summed medium by medium, each at
    its own albedo::

        L_rest(x, w_o) = sum_m rho(alpha_m, 1) L_m(x, w_o) * rho(alpha_x, mu_o) / rho(alpha_x, 1)        (1)

    with ``L_m`` the share of the pass's light that medium m scattered and the exit-angle shape of the
    vertex's own medium (1 along the normal; within 4-11 % of the other media's over mu_o 0.4-1).
    ``rest_sources`` maps a pass (``"single"``, ``"voxel_number_map"``) to its evaluator, or a callable
    returning it, with ``rest_media()`` (the media's albedos, None for one) and ``weighted_radiance(w)``
    (the pass's last frame with each medium's sigma_s times w: single scattering per sample, one more pass
    over the view rays; the Voxel Number Map per component, a second kernel).  ``eta`` is the outer
    surface's for every medium (the wine's own 1.33 against glass: rho 1.40 in place of 1.51 in red).  At
    the surface's albedo alone, the bottle's green came out 2.5x Mitsuba's (docs/accuracy.md).
    """
    from .diffusion.split import half_space_split

    parts = [(kind, rgb, np.array(plan.replaces_diffusion(kind), dtype=np.float64))
             for kind, rgb in (("single", terms.single), ("voxel_number_map", terms.voxel_number_map))]
    parts = [(kind, rgb, on) for kind, rgb, on in parts if rgb is not None and on.any()]
    if not parts or plan.surface_albedo is None:
        return None
    n = len(terms.total)
    if mapping.same:
        positions, normals = np.asarray(bake.mesh_vertices)[:n], np.asarray(bake.mesh_normals)[:n]
    else:
        positions, normals = mapping.positions, mapping.normals
    dirs = view_directions(view, positions)
    cos_o = np.ones(n) if dirs is None else np.einsum("vj,vj->v", np.asarray(normals, dtype=np.float64), dirs)
    alpha = np.einsum("vk,vkc->vc", np.asarray(mapping.w, dtype=np.float64),
                      np.asarray(plan.surface_albedo)[np.asarray(mapping.idx)])
    split = half_space_split(float(eta))
    rho = split.multiple_over_single(alpha, cos_o)
    out = np.zeros((n, 3))
    for kind, rgb, on in parts:
        ev = (rest_sources or {}).get(kind)
        ev = ev() if callable(ev) and not hasattr(ev, "rest_media") else ev
        media = ev.rest_media() if ev is not None else None
        if media is not None:  # eq. (1)
            rest = rest_of_media(ev.weighted_radiance, media, alpha, cos_o, split)
            out += rest * plan.vertex_weights(kind, mapping.idx, mapping.w) * on
        else:
            out += rgb * rho * on
    return out


# ------------------------------------------------------------------ one frame from scratch


@dataclass
class FrameResult:
    """:func:`render_frame`'s answer: the terms, the diffusion's solution and what each step cost."""

    terms: FrameTerms
    result: object = None  # the diffusion's SolveResult (None when it did not run)
    bounce: object = None
    cavity_exchange: dict | None = None
    seconds: dict = field(default_factory=dict)
    single_evaluator: object = None


def render_frame(bake, plan, passes: FramePasses, mapping: MeshMapping | None, *, solver=None, lights=(),
                 environment=None, view=None, ss_view=None, eta: float = 1.3, tol: float = 1e-5, occluders=None,
                 shadows: bool = True, warm_start=None, ss_order: int | None = None, ss_evaluator=None,
                 multiple=None, single=None, voxel_number_map=None, rest_sources: dict | None = None,
                 n: int | None = None,
                 name: str = "object") -> FrameResult:
    """Every pass ``passes`` turns on, for one frame, composed (see the module docstring).

    Each term comes from a step the caller may supply, a callable returning its radiance at the mapping's
    vertices: ``multiple`` (default: :func:`diffuse` on ``solver`` from ``warm_start``, then
    :func:`multiple_radiance` towards ``view``), ``single`` (default: ``ss_evaluator`` or a new
    :func:`single_evaluator`, towards ``ss_view``, default ``view``) and ``voxel_number_map`` (no default: the
    caller owns the map's evaluator and backend); ``rest_sources`` (default: the single-scattering
    evaluator this call made) gives each pass's evaluator, for the orders after the first of an object with
    several media (:func:`orders_after_the_first` eq. 1).  The add-on's runtime supplies its own steps (they keep the
    solver, the last solution and the evaluators between frames, and retry a GPU failure on the CPU); the
    CLI takes the defaults.  Either way which terms run, in what order, and how they are weighted and
    summed is decided here.  ``n``: the vertex count when no pass runs (``mapping`` None).
    """
    seconds = {}
    found = {"result": None, "bounce": None, "cavity": None}
    ms = ss = vnm = None

    def default_multiple():
        if solver is None:
            raise TranslucencyError(f"'{name}': the plan runs diffusion but no solver was given")
        found["result"], found["bounce"], found["cavity"] = diffuse(
            solver, bake, lights, environment, passes, tol=tol, occluders=occluders, warm_start=warm_start,
            shadows=shadows)
        return multiple_radiance(solver, found["result"], bake, mapping, view)

    def default_single():
        nonlocal ss_evaluator
        if ss_evaluator is None:
            order = bake.single_scattering.order if ss_order is None else min(int(ss_order),
                                                                               bake.single_scattering.order)
            ss_evaluator = single_evaluator(bake, order, mapping)
        return ss_evaluator.radiance(list(lights), environment, float(eta), bake.mm_per_unit,
                                     view if ss_view is None else ss_view)

    t0 = time.perf_counter()
    if passes.use_ms:
        ms = (multiple or default_multiple)()
    seconds["diffusion"] = time.perf_counter() - t0
    t1 = time.perf_counter()
    if passes.use_ss:
        ss = (single or default_single)()
    seconds["single_scattering"] = time.perf_counter() - t1
    t2 = time.perf_counter()
    if passes.use_vnm:
        if voxel_number_map is None:
            raise TranslucencyError(f"'{name}': the plan runs the Voxel Number Map but no evaluator was given")
        vnm = voxel_number_map()
    seconds["voxel_number_map"] = time.perf_counter() - t2
    terms = compose(plan, mapping, name, ms, ss, vnm, n=n)
    t3 = time.perf_counter()
    if ss is not None or vnm is not None:
        sources = dict(rest_sources or {})
        if "single" not in sources and single is None and ss_evaluator is not None:
            sources["single"] = ss_evaluator
        orders = orders_after_the_first(plan, mapping, bake, terms, eta, view if ss_view is None else ss_view,
                                        sources)
        if orders is not None:
            terms.orders = orders
            terms.total = terms.total + orders
    seconds["orders_after_the_first"] = time.perf_counter() - t3
    seconds["total"] = time.perf_counter() - t0
    return FrameResult(terms, found["result"], found["bounce"], found["cavity"], seconds, ss_evaluator)


# ------------------------------------------------------------------ a particle fluid's frame


def fluid_radiance(result, plan, on_points: bool, n: int) -> np.ndarray:
    """(n, 3) radiance of a particle fluid's frame (Kang & Kim 2013) where it is written: at the particles
    (``on_points``: a point cloud that is its own source; ``FluidResult.point_radiance``) or at the surface
    mesh's vertices (``vertex_radiance``), the planner's channels only (``planner.plan_fluid``); zeros when
    nothing ran (``result`` None).  NaN or Inf is refused, never written."""
    if result is None:
        return np.zeros((n, 3))
    rgb = result.point_radiance if on_points else result.vertex_radiance
    rgb = np.asarray(rgb, dtype=np.float64) * plan.channel_mask("multiple")
    if not np.all(np.isfinite(rgb)):
        raise TranslucencyError("the fluid's solve produced NaN or Inf radiance; check the material")
    return rgb
