"""Command line: bake and solve OBJ files without Blender (pipelines, render farms).

    python -m translucency_addon bake MESH.obj -o CACHE.npz [--quality draft|preview|final]
                                      [--levels N] [--mm-per-unit X]
    python -m translucency_addon solve CACHE.npz -o OUT.npy
                                      [--material marble | --sigma-a R,G,B --sigma-s R,G,B --eta X]
                                      [--env R,G,B] [--sun DX,DY,DZ:E] [--point X,Y,Z:W]
                                      [--solver paper|fast|direct] [--tol 1e-4] [--stats STATS.json]

Run ``python -m translucency_addon <command> --help`` for every option.
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import numpy as np

from .errors import TranslucencyError


def _floats(text: str, n: int, what: str) -> tuple:
    try:
        vals = tuple(float(x) for x in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{what}: expected {n} comma-separated numbers, got {text!r}")
    if len(vals) != n:
        raise argparse.ArgumentTypeError(f"{what}: expected {n} comma-separated numbers, got {text!r}")
    return vals


def _rgb(text):
    return _floats(text, 3, "RGB")


def _sun(text):
    try:
        d, e = text.split(":")
    except ValueError:
        raise argparse.ArgumentTypeError(f"--sun: expected DX,DY,DZ:E, got {text!r}")
    return _floats(d, 3, "--sun direction"), float(e)


def _point(text):
    try:
        p, w = text.split(":")
    except ValueError:
        raise argparse.ArgumentTypeError(f"--point: expected X,Y,Z:W, got {text!r}")
    return _floats(p, 3, "--point position"), float(w)


def _field(text):
    kind, _, scale = text.partition(":")
    return kind, float(scale) if scale else 1.0


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="python -m translucency_addon", description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="command", required=True)

    b = sub.add_parser("bake", help="bake the multi-resolution QuadGraph of a mesh")
    b.add_argument("mesh", help="triangle mesh (.obj), in object units")
    b.add_argument("-o", "--output", required=True, help="cache file to write (.npz)")
    b.add_argument("--quality", default="preview", choices=["draft", "preview", "final"])
    b.add_argument("--levels", type=int, default=None, help="number of multi-resolution levels (default: the quality's)")
    b.add_argument("--mm-per-unit", type=float, default=1.0, help="millimetres per mesh unit (default 1)")
    b.add_argument("--level-mode", choices=["refine", "independent"], default="refine",
                   help="finer levels by nested refinement (fast) or independent tetrahedralisation (paper)")
    b.add_argument("--no-optimize", action="store_true", help="skip fTetWild's optimisation (fast, slivers)")
    b.add_argument("--single-scattering", action="store_true", help="also bake RBF optical-depth samples")
    b.add_argument("--json", action="store_true", help="print the statistics as JSON")

    s = sub.add_parser("solve", help="solve the diffusion (and single scattering) for a baked mesh")
    s.add_argument("cache", help="bake cache (.npz) from 'bake'")
    s.add_argument("-o", "--output", required=True, help="RGB radiance per vertex of the baked mesh (.npy)")
    s.add_argument("--material", default=None, help="preset name (marble, skimmilk, skin1, ketchup, ...)")
    s.add_argument("--mix-with", default=None, help="second preset mixed in by --field")
    s.add_argument("--field", type=_field, default=None, help="mixing field KIND[:SCALE], e.g. marble:0.05")
    s.add_argument("--sigma-a", type=_rgb, default=None, help="absorption R,G,B per mm (custom material)")
    s.add_argument("--sigma-s", type=_rgb, default=None, help="reduced scattering R,G,B per mm (custom material)")
    s.add_argument("--eta", type=float, default=1.3, help="relative refractive index (default 1.3)")
    s.add_argument("--env", type=_rgb, default=None, help="uniform environment radiance R,G,B (unoccluded)")
    s.add_argument("--sun", type=_sun, action="append", default=[],
                   help="sun light DX,DY,DZ:E -- direction the light travels (object space) and irradiance in W/m^2")
    s.add_argument("--point", type=_point, action="append", default=[],
                   help="point light X,Y,Z:W -- position (object units) and radiant power in W (isotropic)")
    s.add_argument("--solver", choices=["paper", "fast", "direct"], default="fast")
    s.add_argument("--tol", type=float, default=1e-4, help="relative residual tolerance (default 1e-4)")
    s.add_argument("--no-shadows", action="store_true", help="ignore occlusion of point and sun lights")
    s.add_argument("--mm-per-unit", type=float, default=None, help="override the baked scene scale")
    s.add_argument("--stats", default=None, help="write node counts, sweeps, residual and timings (.json)")

    p = sub.add_parser("plan", help="print which passes the planner would run for a baked mesh")
    p.add_argument("cache")
    p.add_argument("--material", default="marble")
    p.add_argument("--env", type=_rgb, default=None)
    p.add_argument("--sun", type=_sun, action="append", default=[])
    p.add_argument("--point", type=_point, action="append", default=[])
    p.add_argument("--mm-per-unit", type=float, default=None)
    return ap


def material_from_args(a):
    from .materials import Material, Medium, material_from_preset, preset

    if a.sigma_a is not None or a.sigma_s is not None:
        if a.sigma_a is None or a.sigma_s is None:
            raise TranslucencyError("a custom material needs both --sigma-a and --sigma-s")
        return Material(Medium(a.sigma_a, a.sigma_s, "custom"), preset(a.mix_with) if a.mix_with else None, a.eta)
    return material_from_preset(a.material or "marble", eta=a.eta, mix_with=a.mix_with)


def lights_from_args(a):
    from .lights import Environment, Light

    lights = []
    for d, e in a.sun:
        lights.append(Light("sun", irradiance=e, direction=d, name="sun"))
    for pos, watts in a.point:
        lights.append(Light("point", intensity=watts / (4.0 * np.pi), position=pos, name="point"))
    env = Environment(a.env) if a.env is not None else None
    return lights, env


def cmd_bake(a) -> int:
    from .bake import BakeSettings, bake_mesh, format_stats
    from .cache import save_bake
    from .meshio import load_obj

    V, F = load_obj(a.mesh)
    settings = BakeSettings(quality=a.quality, levels=a.levels, mm_per_unit=a.mm_per_unit,
                            level_mode=a.level_mode, optimize=not a.no_optimize)
    t0 = time.perf_counter()

    def progress(frac, stage):
        print(f"\r[{frac * 100:5.1f}%] {stage:<16}", end="", file=sys.stderr, flush=True)

    bake = bake_mesh(V, F, settings, progress=progress)
    print(file=sys.stderr)
    if a.single_scattering:
        from .single_scattering import bake_single_scattering_for
        bake.single_scattering = bake_single_scattering_for(bake)
    save_bake(a.output, bake)
    if a.json:
        print(json.dumps(bake.stats, indent=2, default=str))
    else:
        print(format_stats(bake))
        print(f"wrote {a.output} in {time.perf_counter() - t0:.2f} s")
    return 0


def cmd_solve(a) -> int:
    from .cache import load_bake
    from .diffusion import DiffusionSolver, SolveOptions
    from .fields import FieldSpec, evaluate_field

    t0 = time.perf_counter()
    bake = load_bake(a.cache)
    if a.mm_per_unit is not None:
        bake = bake.with_scale(a.mm_per_unit)
    t_load = time.perf_counter() - t0
    material = material_from_args(a)
    field_values = None
    if material.heterogeneous:
        kind, scale = a.field or ("marble", 0.25 * float(np.max(np.ptp(bake.mesh_vertices, axis=0))))
        spec = FieldSpec(kind=kind, scale=scale)
        field_values = [evaluate_field(spec, lv.position) for lv in bake.levels]
    lights, env = lights_from_args(a)
    solver = DiffusionSolver(bake, material, field_values, SolveOptions(solver=a.solver, tol=a.tol))
    t1 = time.perf_counter()
    result = solver.solve(lights, env, shadows=not a.no_shadows)
    L = solver.vertex_radiance(result)
    np.save(a.output, L.astype(np.float32))
    t2 = time.perf_counter()
    stats = {
        "levels": [{"n_inner": lv.n_inner, "n_surface": lv.n_surface} for lv in bake.levels],
        "solver": a.solver,
        "scheme": result.scheme,
        "sweeps": [ls.iterations for ls in result.level_solves],
        "final_relative_residual": result.residual.tolist(),
        "seconds": {"load": t_load, "setup": t1 - t0 - t_load, **result.seconds, "total": t2 - t0},
        "radiance_mean": L.mean(axis=0).tolist(),
        "n_vertices": int(len(L)),
    }
    if a.stats:
        with open(a.stats, "w", encoding="utf-8") as fh:
            json.dump(stats, fh, indent=2)
    print(f"solved {sum(stats['sweeps'])} sweeps ({a.solver}), residual {max(stats['final_relative_residual']):.2e}, "
          f"{stats['seconds']['total']:.2f} s; wrote {a.output} ({len(L)} vertices)")
    return 0


def cmd_plan(a) -> int:
    from .cache import load_bake
    from .planner import describe_plan, plan_object

    bake = load_bake(a.cache)
    if a.mm_per_unit is not None:
        bake = bake.with_scale(a.mm_per_unit)
    a.sigma_a = a.sigma_s = None
    a.mix_with = None
    a.eta = 1.3
    material = material_from_args(a)
    lights, env = lights_from_args(a)
    plan = plan_object(bake, material, lights, env)
    print(describe_plan(plan))
    return 0


def main(argv=None) -> int:
    a = build_parser().parse_args(argv)
    try:
        return {"bake": cmd_bake, "solve": cmd_solve, "plan": cmd_plan}[a.command](a)
    except TranslucencyError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
