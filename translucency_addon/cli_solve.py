"""The command line's ``solve`` and ``plan``: one frame of a bake cache through the engine's recipe
(:func:`.frame.render_frame`, as the add-on renders it), written all or nothing; the plan alone."""

from __future__ import annotations

import hashlib
import json
import os
import sys
import time

import numpy as np

from .cli_args import check_files, field_spec_from_args, lights_from_args, material_from_args
from .errors import TranslucencyError


def cmd_solve(a) -> int:
    from .cache import load_bake
    from .diffusion.solver import DiffusionSolver, SolveOptions
    from .scene.fields import evaluate_field

    from .cache import write_files

    check_files([("CACHE", a.cache), ("--deformed", a.deformed), ("--field-values", a.field_values)],
                [("-o", a.output), ("--stats", a.stats), ("--ss-output", a.ss_output)])
    material = material_from_args(a)
    lights, env = lights_from_args(a)
    t0 = time.perf_counter()
    bake = load_bake(a.cache)
    if a.ss_output and (bake.single_scattering is None or a.no_single_scattering):
        raise TranslucencyError("--ss-output: " + (
            "--no-single-scattering turns that term off" if a.no_single_scattering
            else f"the cache {a.cache} holds no single-scattering data (bake with --single-scattering)"))
    if a.mm_per_unit is not None:
        bake = bake.with_scale(a.mm_per_unit)
    from .frame import lights_at_quality

    lights = list(lights_at_quality(lights, bake.settings.quality))
    t_load = time.perf_counter() - t0
    field_values = None
    spec = None
    if a.field_values is not None and not material.heterogeneous:
        raise TranslucencyError("--field-values mixes two media: name the second with --mix-with")
    if a.field_values is not None and a.field is not None:
        raise TranslucencyError("--field-values and --field both give the mixing field: use one")
    if a.field_values is not None:
        from .scene.fields import load_vertex_field, vertex_field_at_nodes

        weights = load_vertex_field(a.field_values, len(bake.mesh_vertices))
        field_values = [vertex_field_at_nodes(bake.mesh_vertices, weights, lv.position) for lv in bake.levels]
        spec = "vertex-values:" + hashlib.sha256(weights.tobytes()).hexdigest()[:32]
    elif material.heterogeneous:
        spec = field_spec_from_args(a, bake.mesh_vertices)
        field_values = [evaluate_field(spec, lv.position) for lv in bake.levels]
    deformation = None
    if a.deformed and bake.composite is not None:
        from .errors import DeformationError

        raise DeformationError("--deformed: this cache has inner parts (cavities, media or opaque parts), whose "
                               "cavity exchange and Voxel Number Map are baked in the rest pose and are not "
                               "deformed; re-bake the posed mesh instead")
    if a.deformed:  # after the field: the material stays attached to the rest pose
        from .deformation.pose import deform_from_obj

        pose = deform_from_obj(bake, a.deformed)
        deformation = {"worst_link_stretch": pose.report.worst_stretch, "inverted_tets": pose.report.inverted_tets,
                       "seconds": pose.seconds}
        print(pose.report.describe(), file=sys.stderr)
        if bake.single_scattering is not None and not a.no_single_scattering:
            print("warning: single scattering is baked in the rest pose and not deformed; left out", file=sys.stderr)
        bake = pose.bake
    # The frame: the engine's recipe (translucency_addon.frame), as the add-on runs it -- the planner with the
    # switches as overrides, the split, the bounce or the cavity exchange, single scattering and the Voxel
    # Number Map where the plan runs them, each weighted by the planner's region.
    from .frame import bake_mapping, pass_overrides, passes_for, render_frame
    from .planner import describe_plan, plan_object

    outer_material = material
    has_ss = bake.single_scattering is not None and not a.deformed  # baked in the rest pose: not deformed
    overrides = pass_overrides(single=not a.no_single_scattering, has_single=has_ss,
                               voxel_number_map=not a.no_voxel_number_map,
                               has_voxel_number_map=bake.voxel_number_map is not None,
                               all_passes=a.pass_planning == "all")
    name = os.path.splitext(os.path.basename(a.cache))[0]
    why = {}  # what forced each override off, in the command line's words (the plan says it)
    if "single" in overrides and not overrides["single"]:
        why["single"] = ("by --no-single-scattering" if a.no_single_scattering else
                         "because the cache holds no single-scattering data (bake with --single-scattering)"
                         if bake.single_scattering is None else
                         "because single scattering is baked in the rest pose and not deformed (--deformed)")
    if overrides.get("voxel_number_map") is False:
        why["voxel_number_map"] = "by --no-voxel-number-map"
    plan = plan_object(bake, outer_material, lights, env, field_values=field_values, has_single_scattering=has_ss,
                       overrides=overrides, name=name, override_reasons=why)
    passes = passes_for(plan, bake)
    solver = None
    if passes.use_ms:
        solver_material, solver_field = material, field_values
        if bake.composite is not None:  # inner parts: per-node media (composite_bake)
            from .inner_parts.bake import diffusion_material

            solver_material, solver_field = diffusion_material(material, bake.composite, field_values)
        opts = SolveOptions(solver=a.solver, tol=a.tol, lamp_source=getattr(a, "lamp_source", "volume"))
        solver = DiffusionSolver(bake, solver_material, solver_field, opts)
    view = ("PERSP", tuple(a.camera)) if a.camera is not None else None
    ss_stats = _single_scattering_stats(a, bake, outer_material, spec) if passes.use_ss else None
    vnm_stats = {"enabled": False, "reason": (
        "turned off (--no-voxel-number-map)" if a.no_voxel_number_map
        else "the cache holds no Voxel Number Map (bake with --voxel-number-map)" if bake.voxel_number_map is None
        else "the planner leaves it out: " + _why(plan, plan.voxel_number_map))}

    rest_sources: dict = {}  # the map's evaluator, for the orders after the first of several media

    def voxel_number_map():
        from .inner_parts.bake import solve_voxel_number_map

        L_vnm, stats_vnm = solve_voxel_number_map(bake, outer_material, lights, env, view, shadows=not a.no_shadows,
                                                  keep=rest_sources)
        vnm_stats.clear()
        vnm_stats.update(stats_vnm)
        return L_vnm

    t1 = time.perf_counter()
    frame = render_frame(bake, plan, passes, bake_mapping(bake), solver=solver, lights=lights, environment=env,
                         view=view, eta=outer_material.eta, tol=a.tol, shadows=not a.no_shadows,
                         voxel_number_map=voxel_number_map, rest_sources=rest_sources, name=name)
    result, cavity_info, L = frame.result, frame.cavity_exchange, frame.terms.total
    L_ss = frame.terms.single
    if ss_stats is not None:
        ss_stats["seconds"] = {**frame.single_evaluator.seconds, "total": frame.seconds["single_scattering"]}
        ss_stats["radiance_mean"] = L_ss.mean(axis=0).tolist()
    t_diff = t1 + frame.seconds["diffusion"]
    t2 = time.perf_counter()
    stats = {
        "levels": [{"n_inner": lv.n_inner, "n_surface": lv.n_surface} for lv in bake.levels],
        "solver": a.solver,
        "plan": describe_plan(plan),
        "scheme": result.scheme if result is not None else None,
        "sweeps": [ls.iterations for ls in result.level_solves] if result is not None else [],
        # levels whose Chebyshev bounds came from the cache (diffusion/baked_bounds.py), not from Lanczos
        "spectral_bounds_from_bake": getattr(solver, "bounds_from_bake", 0),
        "final_relative_residual": result.residual.tolist() if result is not None else [0.0],
        "seconds": {"load": t_load, "setup": t1 - t0 - t_load, **(result.seconds if result is not None else {}),
                    "diffusion": t_diff - t1,
                    "single_scattering": 0.0 if ss_stats is None else ss_stats["seconds"]["total"],
                    "voxel_number_map": vnm_stats["seconds"]["total"] if vnm_stats["enabled"] else 0.0,
                    "orders_after_the_first": frame.seconds["orders_after_the_first"],
                    "total": t2 - t0},
        "orders_after_the_first_mean": (frame.terms.orders.mean(axis=0).tolist()
                                        if frame.terms.orders is not None else None),
        "voxel_number_map": vnm_stats,
        "cavity_exchange": cavity_info,
        "single_scattering": ss_stats if ss_stats is not None else {
            "enabled": False,
            "reason": "turned off (--no-single-scattering)" if a.no_single_scattering
            else "the cache holds no single-scattering data (bake with --single-scattering)"
            if bake.single_scattering is None else "baked in the rest pose, not deformed" if a.deformed
            else "the planner leaves it out: " + _why(plan, plan.single)},
        "radiance_mean": L.mean(axis=0).tolist(),
        "n_vertices": int(len(L)),
        "deformation": deformation,
    }
    L32 = L.astype(np.float32)
    writers = {a.output: lambda fh: np.save(fh, L32)}
    if a.ss_output:  # the term as it entered the frame (zeros where the planner left it out)
        L_ss32 = (L_ss if L_ss is not None else np.zeros_like(L)).astype(np.float32)
        writers[a.ss_output] = lambda fh: np.save(fh, L_ss32)
    if a.stats:
        text = json.dumps(stats, indent=2)
        writers[a.stats] = lambda fh: fh.write(text.encode("utf-8"))
    write_files(writers)  # all or nothing, after everything else succeeded
    ss_note = ""
    if ss_stats is not None:
        ss_note = f" + single scattering ({ss_stats['n_samples']} samples, {ss_stats['seconds']['total']:.2f} s)"
    if vnm_stats["enabled"]:
        ss_note += (f" + Voxel Number Map ({vnm_stats['surface_voxels']} surface voxels, "
                    f"{vnm_stats['seconds']['frame']['total'] * 1e3:.1f} ms per frame)")
    print(f"solved {sum(stats['sweeps'])} sweeps ({a.solver}), residual {max(stats['final_relative_residual']):.2e}, "
          f"{stats['seconds']['total']:.2f} s{ss_note}; wrote {a.output} ({len(L)} vertices)")
    return 0


def _why(plan, decision) -> str:
    """Why the plan leaves a pass out: its channels' reasons, or the plan's own when it runs nothing."""
    if decision is None or not plan.run:
        return plan.reason
    return "; ".join(decision.reasons)


def _single_scattering_stats(a, bake, material, spec) -> dict:
    """What the --stats file says of the single-scattering term (its radiance comes from the frame); a bake
    whose optical depth no longer matches the material, field or scale is used as it is, with a warning."""
    from .single_scattering import fingerprint_field, stale_message, staleness

    data = bake.single_scattering
    reasons = staleness(data, material=material, field_fp=fingerprint_field(spec, material),
                        mm_per_unit=bake.mm_per_unit)
    if reasons:
        print(f"warning: {stale_message(reasons)} (bake again with --single-scattering)", file=sys.stderr)
    return {"enabled": True, "backend": "CPU (numpy)", "n_samples": data.n_samples, "n_dirs": data.n_dirs,
            "sh_order": data.order, "view": "camera" if a.camera is not None else "normal", "stale": reasons}


def cmd_plan(a) -> int:
    from .cache import load_bake
    from .planner import describe_plan, plan_object

    check_files([("CACHE", a.cache)])
    a.sigma_a = a.sigma_s = None
    a.mix_with = None
    a.eta = 1.3
    material = material_from_args(a)
    lights, env = lights_from_args(a)
    bake = load_bake(a.cache)
    if a.mm_per_unit is not None:
        bake = bake.with_scale(a.mm_per_unit)
    plan = plan_object(bake, material, lights, env)
    print(describe_plan(plan))
    return 0
