"""Command line: bake and solve OBJ files without Blender (pipelines, render farms).

    python -m translucency_addon bake MESH.obj -o CACHE.npz [--quality draft|preview|final]
                                      [--levels N] [--mm-per-unit X] [--sky-directions 64]
                                      [--single-scattering [--material marble] [--ss-quality preview]
                                       [--ss-dirs 128] [--ss-samples 20000] [--ss-order 4]]
    python -m translucency_addon bake OUTER.obj --inner PART.obj:ROLE ... [--voxel-number-map] -o CACHE.npz
                                      (ROLE: a preset name, cavity or opaque)
    python -m translucency_addon fluid POINTS.npy -o PHI.npz --radius R --mm-per-unit S
                                      (--material NAME | --sigma-a R,G,B --sigma-s R,G,B --eta X)
                                      [--env R,G,B] [--sun DX,DY,DZ:E] [--point X,Y,Z:W[:R]]
                                      [--surface MESH.obj --surface-out L.npy] [--stats STATS.json]
    python -m translucency_addon solve CACHE.npz -o OUT.npy [--deformed POSED.obj]
                                      [--material marble | --sigma-a R,G,B --sigma-s R,G,B --eta X]
                                      [--env R,G,B] [--sun DX,DY,DZ:E] [--point X,Y,Z:W[:R]]
                                      [--camera X,Y,Z] [--no-single-scattering] [--ss-output SS.npy]
                                      [--solver paper|fast|direct] [--tol 1e-4] [--stats STATS.json]
                                      [--no-voxel-number-map]

Single scattering: ``bake --single-scattering`` also bakes the RBF
optical-depth samples (Bernabei et al.) for the material given to ``bake``
(the optical depth depends on sigma_t, so the material is baked in);
``solve`` adds that term to the diffusion radiance whenever the cache holds
it, and warns when the material, field or scale given to ``solve`` differ
from the ones it was baked with (re-bake with ``--single-scattering`` then).

Run ``python -m translucency_addon <command> --help`` for every option.
"""

from __future__ import annotations

import argparse
import json
import sys
import time

from . import cli_args as arg
from .cli_args import check_files, field_spec_from_args, lights_from_args, material_from_args
from .cli_solve import cmd_plan, cmd_solve
from .errors import TranslucencyError


class _Parser(argparse.ArgumentParser):
    """argparse whose errors are one line on stderr, exit status 2, like every other refusal of the CLI."""

    def error(self, message):
        print(f"error: {message} (run '{self.prog} --help' for what each option accepts)", file=sys.stderr)
        sys.exit(2)


def build_parser() -> argparse.ArgumentParser:
    ap = _Parser(prog="python -m translucency_addon", description=__doc__.split("\n\n")[0],
                                 epilog="Run 'python -m translucency_addon COMMAND --help' for a command's options. "
                                        "Errors exit with status 2 and one line 'error: ...' that names the problem; "
                                        "arguments and files are checked before any work, and nothing is written "
                                        "unless everything succeeds.")
    sub = ap.add_subparsers(dest="command", required=True)

    b = sub.add_parser("bake", help="bake the multi-resolution QuadGraph of a mesh")
    b.add_argument("mesh", help="triangle mesh (.obj, a readable file), in object units")
    b.add_argument("-o", "--output", required=True,
                   help="cache file to write (.npz) in an existing, writable folder")
    b.add_argument("--quality", default="preview", choices=["draft", "preview", "final"],
                   help="graph resolution and level count (draft: fastest bake, coarsest graph; default preview)")
    b.add_argument("--levels", type=arg.in_range(1, 6, "--levels", int), default=None,
                   help="number of multi-resolution levels, 1 to 6 (default: the quality's)")
    b.add_argument("--mm-per-unit", type=arg.mm_per_unit, default=1.0,
                   help="millimetres per mesh unit, a finite number > 0 (default 1)")
    b.add_argument("--sky-directions", type=arg.in_range(0, 4096, "--sky-directions", int), default=0,
                   help="also bake sky visibility with N rays per surface node (self-occlusion and one "
                        "interreflection bounce for world light; 0 = off, the default, or 8 to 4096; the Blender "
                        "add-on uses 64)")
    b.add_argument("--level-mode", choices=["refine", "independent"], default="refine",
                   help="finer levels by nested refinement (fast) or independent tetrahedralisation (paper)")
    b.add_argument("--no-optimize", action="store_true", help="skip fTetWild's optimisation (fast, slivers)")
    b.add_argument("--single-scattering", action="store_true", help="also bake RBF optical-depth samples")
    arg.material_args(b, "the frames' material, default marble (single scattering bakes with it; the cache keeps "
                         "what a cold frame of it would compute): ")
    b.add_argument("--ss-quality", default="preview", choices=["draft", "preview", "final"],
                   help="single scattering: voxel resolution (32/48/64 on the longest side)")
    b.add_argument("--ss-dirs", type=int, default=128,
                   help="single scattering: optical-depth directions, at least 6 (32, 128, 512; default 128)")
    b.add_argument("--ss-samples", type=int, default=20000,
                   help="single scattering: target number of RBF samples, at least 8 (default 20000)")
    b.add_argument("--ss-order", type=int, default=4, choices=[1, 2, 3, 4], help="single scattering: SH order")
    b.add_argument("--inner", action="append", default=[], metavar="PART.obj:ROLE",
                   help="an inner part (a readable .obj, same object space): ROLE a preset name (another "
                        "medium), cavity or opaque")
    b.add_argument("--voxel-number-map", action="store_true",
                   help="also bake the Voxel Number Map (surface-voxel optical-thickness LUT, Mochida et al.)")
    b.add_argument("--vnm-quality", default="preview", choices=["draft", "preview", "final"],
                   help="Voxel Number Map: target surface voxels 800 / 2,000 / 3,500 (budget 4,096)")
    b.add_argument("--json", action="store_true", help="print the statistics as JSON")

    s = sub.add_parser("solve", help="solve the diffusion (and single scattering) for a baked mesh")
    s.description = ("Solve a baked mesh under the given lights: diffusion on the QuadGraph, plus single scattering "
                     "and the Voxel Number Map when the cache holds them (the --stats file says why a term was "
                     "left out).")
    s.add_argument("cache", help="bake cache (.npz) from 'bake'")
    s.add_argument("-o", "--output", required=True,
                   help="RGB radiance per vertex of the baked mesh, W/(m^2 sr) (.npy, in an existing, writable "
                        "folder)")
    arg.material_args(s, "")
    s.add_argument("--env", type=arg.rgb, default=None, help="uniform environment radiance R,G,B, W/(m^2 sr), each >= 0 (unoccluded)")
    s.add_argument("--sun", type=arg.sun, action="append", default=[],
                   help="sun light DX,DY,DZ:E -- direction the light travels (object space, not 0,0,0) and "
                        "irradiance in W/m^2, >= 0 (repeatable)")
    s.add_argument("--point", type=arg.point, action="append", default=[],
                   help="point light X,Y,Z:W[:R] -- position (object units), radiant power in W, >= 0 (isotropic), "
                        "and optionally its radius R in object units (a sphere light: soft shadows, Blender's "
                        "Radius; repeatable)")
    s.add_argument("--spot", type=arg.spot, action="append", default=[],
                   help="spot light X,Y,Z:DX,DY,DZ:W:SIZE[:BLEND[:R]] -- position, the direction it points, power "
                        "in W, Blender's Spot Size (full cone angle, degrees), Spot Blend (default 0.15) and Radius "
                        "(object units, default 0; repeatable)")
    s.add_argument("--area", type=arg.area, action="append", default=[],
                   help="area light X,Y,Z:EX,EY,EZ:FX,FY,FZ:W[:disk] -- centre, its two full edges (object units; "
                        "it emits along F x E), power in W (Blender's), disk for Disk (default Square/Rectangle; "
                        "repeatable)")
    s.add_argument("--solver", choices=["paper", "fast", "direct"], default="fast",
                   help="paper: Jacobi relaxation (eqs. 8-9, slow on fine graphs); fast: Chebyshev (default); "
                        "direct: sparse LU (exact, memory grows fast)")
    s.add_argument("--tol", type=arg.tolerance, default=1e-4,
                   help="relative residual tolerance, in (0, 1) (default 1e-4)")
    s.add_argument("--lamp-source", choices=["volume", "boundary"], default="volume",
                   help="where a lamp's light enters the diffusion: volume, along its refracted chords "
                        "(default), or boundary, all of it at the surface it reaches (the model before; "
                        "for comparisons)")
    s.add_argument("--no-shadows", action="store_true", help="ignore occlusion of point and sun lights")
    s.add_argument("--mm-per-unit", type=arg.mm_per_unit, default=None,
                   help="override the baked scene scale: millimetres per mesh unit, a finite number > 0")
    s.add_argument("--stats", default=None, help="write node counts, sweeps, residual and timings (.json, in an "
                                                 "existing, writable folder)")
    s.add_argument("--camera", type=arg.camera, default=None,
                   help="perspective camera position X,Y,Z (object units): view-dependent radiance toward it "
                        "(default: each vertex seen along its normal)")
    s.add_argument("--no-single-scattering", action="store_true",
                   help="leave out the single-scattering term even when the cache holds it")
    s.add_argument("--ss-output", default=None,
                   help="also write the single-scattering term alone (.npy, in an existing, writable folder)")
    s.add_argument("--deformed", default=None, metavar="POSED.obj",
                   help="solve on the baked graph deformed to this pose (a readable .obj: the baked mesh's vertices, same count "
                        "and order; Wang et al. sec. 6.4) instead of re-baking; radiance at the posed vertices")
    s.add_argument("--no-voxel-number-map", action="store_true",
                   help="leave out the Voxel Number Map term even when the cache holds it")
    s.add_argument("--field-values", default=None, metavar="WEIGHTS.npy",
                   help="the mixing field as one weight from 0 to 1 per vertex of the baked mesh (numpy.save of an "
                        "(N,) array; a mesh attribute or vertex group exported from Blender), instead of --field; "
                        "needs --mix-with")
    s.add_argument("--pass-planning", choices=["auto", "all"], default="auto",
                   help="auto: the planner runs each pass where it adds light (as the add-on's Pass Planning "
                        "'Automatic', the default); all: every term that is on and baked runs on every channel "
                        "('All Passes')")

    _fluid_parser(sub)

    p = sub.add_parser("plan", help="print which passes the planner would run for a baked mesh, and why",
                       description="Print which passes (diffusion, single scattering, Voxel Number Map) and colour "
                                   "channels the planner runs for a baked mesh under the given lights, with each "
                                   "channel's reason in numbers (reduced albedo, optical thickness, share of the "
                                   "brightest channel) and what would make a skipped pass run.")
    p.add_argument("cache", help="bake cache (.npz) from 'bake'")
    p.add_argument("--material", default="marble",
                   help="preset name (marble, skimmilk, skin1, ketchup, ...; default marble)")
    p.add_argument("--env", type=arg.rgb, default=None, help="uniform environment radiance R,G,B, W/(m^2 sr), each >= 0 (default: none)")
    p.add_argument("--sun", type=arg.sun, action="append", default=[],
                   help="sun light DX,DY,DZ:E -- direction the light travels (object space, not 0,0,0) and "
                        "irradiance in W/m^2, >= 0 (repeatable)")
    p.add_argument("--point", type=arg.point, action="append", default=[],
                   help="point light X,Y,Z:W[:R] -- position (object units), radiant power in W, >= 0 (isotropic), "
                        "and optionally its radius R in object units (a sphere light: soft shadows, Blender's "
                        "Radius; repeatable)")
    p.add_argument("--spot", type=arg.spot, action="append", default=[],
                   help="spot light X,Y,Z:DX,DY,DZ:W:SIZE[:BLEND[:R]] (as for solve; repeatable)")
    p.add_argument("--area", type=arg.area, action="append", default=[],
                   help="area light X,Y,Z:EX,EY,EZ:FX,FY,FZ:W[:disk] (as for solve; repeatable)")
    p.add_argument("--mm-per-unit", type=arg.mm_per_unit, default=None,
                   help="override the baked scene scale: millimetres per mesh unit, a finite number > 0")
    return ap


def _fluid_parser(sub) -> None:
    """The ``fluid`` subcommand (particle fluids, Kang & Kim 2013; ``cli_fluid.py``)."""
    f = sub.add_parser("fluid", help="solve a particle fluid frame by frame (Voronoi-fluid cells)")
    f.add_argument("points", help="(N, 3) or (F, N, 3) float array (.npy, numpy.save) of particle positions, "
                                  "object units; NaN rows are absent particles")
    f.add_argument("-o", "--output", required=True,
                   help="per-cell phi, V, surface flag and radiance along the normal; without --surface also "
                        "point_radiance, what the add-on writes onto a point cloud (.npz, in an existing, writable "
                        "folder)")
    f.add_argument("--radius", type=arg.radius, required=True,
                   help="particle radius, object units, a finite number > 0 (about the particle spacing)")
    f.add_argument("--mm-per-unit", type=arg.mm_per_unit, required=True,
                   help="millimetres per object unit, a finite number > 0")
    arg.material_args(f, "")
    f.add_argument("--env", type=arg.rgb, default=None, help="uniform environment radiance R,G,B, W/(m^2 sr), each >= 0")
    f.add_argument("--sun", type=arg.sun, action="append", default=[],
                   help="sun DX,DY,DZ:E -- direction (not 0,0,0) and irradiance in W/m^2, >= 0 (repeatable)")
    f.add_argument("--point", type=arg.point, action="append", default=[],
                   help="point light X,Y,Z:W[:R] -- position (object units), power in W, >= 0, optional radius "
                        "(object units; repeatable)")
    f.add_argument("--spot", type=arg.spot, action="append", default=[],
                   help="spot light X,Y,Z:DX,DY,DZ:W:SIZE[:BLEND[:R]] (as for solve; repeatable)")
    f.add_argument("--area", type=arg.area, action="append", default=[],
                   help="area light X,Y,Z:EX,EY,EZ:FX,FY,FZ:W[:disk] (as for solve; repeatable)")
    f.add_argument("--camera", type=arg.camera, default=None,
                   help="perspective camera position X,Y,Z (object units): view-dependent radiance toward it "
                        "(default: along the normals)")
    f.add_argument("--surface", default=None,
                   help="surface mesh (a readable .obj, object units) to carry radiance onto")
    f.add_argument("--surface-out", default=None,
                   help="per-vertex RGB radiance on --surface (.npy, in an existing, writable folder)")
    f.add_argument("--tol", type=arg.tolerance, default=1e-4, help="relative residual tolerance, in (0, 1) (default 1e-4)")
    f.add_argument("--no-shadows", action="store_true", help="ignore occlusion of point and sun lights")
    f.add_argument("--stats", default=None,
                   help="cell counts, seconds per stage, sweeps per frame (.json, in an existing, writable folder)")


def cmd_fluid(a) -> int:
    from .cli_fluid import run_fluid

    check_files([("POINTS", a.points), ("--surface", a.surface)],
                [("-o", a.output), ("--surface-out", a.surface_out), ("--stats", a.stats)])
    return run_fluid(a, material_from_args(a), *lights_from_args(a), field_spec=lambda P: field_spec_from_args(a, P))


def cmd_bake(a) -> int:
    from .quadgraph.bake import BakeSettings, bake_mesh, format_stats
    from .cache import save_bake
    from .diffusion.baked_bounds import with_kept_bounds
    from .geometry.meshio import load_obj

    check_files([("MESH", a.mesh)] + arg.inner_paths(a.inner), [("-o", a.output)])
    settings = BakeSettings(quality=a.quality, levels=a.levels, mm_per_unit=a.mm_per_unit,
                            level_mode=a.level_mode, optimize=not a.no_optimize, sky_directions=a.sky_directions)
    settings.resolved()  # its ranges (levels, sky directions), before the mesh is read
    if a.single_scattering or a.inner or a.voxel_number_map:
        material_from_args(a)
    try:  # the material's half-space transport tables go with the bake: a cold frame of this eta skips them
        kept = material_from_args(a)
        etas = (kept.eta,)
    except TranslucencyError:  # a plain bake does not need the material; no tables (the first frame solves them)
        kept, etas = None, ()
    V, F = load_obj(a.mesh)
    t0 = time.perf_counter()

    def progress(frac, stage):
        print(f"\r[{frac * 100:5.1f}%] {stage:<16}", end="", file=sys.stderr, flush=True)

    ss = ss_settings = material = None
    if a.single_scattering:  # check the single-scattering inputs before the long QuadGraph bake
        from .single_scattering import SingleScatteringSettings, attach, bake_single_scattering_for

        material = material_from_args(a)
        ss_settings = SingleScatteringSettings(quality=a.ss_quality, n_dirs=a.ss_dirs, n_samples=a.ss_samples,
                                               sh_order=a.ss_order)
        try:
            ss_settings.validated()
        except ValueError as exc:
            raise TranslucencyError(f"single scattering: {exc}") from None
    if a.inner or a.voxel_number_map:
        from .inner_parts.bake import bake_composite, composite_from_files
        from .voxel_number_map import VNMSettings

        material = material or material_from_args(a)
        field = None
        if material.heterogeneous:
            from .scene.fields import evaluate_field

            spec = field_spec_from_args(a, V)
            field = lambda p: evaluate_field(spec, p)  # noqa: E731
        comp = composite_from_files(V, F, material, a.inner, field)
        bake = bake_composite(comp, settings, VNMSettings(quality=a.vnm_quality) if a.voxel_number_map else None,
                              progress=progress)
    else:
        bake = bake_mesh(V, F, settings, progress=progress)
    print(file=sys.stderr)
    if a.single_scattering:
        field = field_spec_from_args(a, bake.mesh_vertices) if material.heterogeneous else None
        ss = bake_single_scattering_for(bake, material, field, ss_settings,
                                        progress=lambda f, st: progress(f, "ss: " + st))
        print(file=sys.stderr)
        bake = attach(bake, ss)
    if kept is not None:  # its spectral bounds too: a cold frame runs no Lanczos
        bake = with_kept_bounds(bake, kept)
    save_bake(a.output, bake, etas=etas)
    if a.json:
        out = dict(bake.stats)
        if ss is not None:
            out["single_scattering"] = {k: v for k, v in ss.stats.items()}
        print(json.dumps(out, indent=2, default=str))
    else:
        print(format_stats(bake))
        if bake.composite is not None:
            print(f"inner parts: {bake.composite.describe()}"
                  + (f"; cavity exchange between {bake.composite.exchange.m} wall nodes" if bake.composite.exchange
                     else ""))
        if bake.voxel_number_map is not None:
            from .voxel_number_map import format_stats as vnm_stats

            print(vnm_stats(bake.voxel_number_map))
        if ss is not None:
            t = ss.stats["time"]
            print(f"single scattering: {ss.n_samples} samples, {ss.n_dirs} directions, SH order {ss.order}, "
                  f"voxels {'x'.join(str(v) for v in ss.stats['voxels'])}, {sum(t.values()):.2f} s ("
                  + ", ".join(f"{k} {v:.2f}" for k, v in t.items()) + ")")
        print(f"wrote {a.output} in {time.perf_counter() - t0:.2f} s")
    return 0


def main(argv=None) -> int:
    a = build_parser().parse_args(argv)
    try:
        return {"bake": cmd_bake, "solve": cmd_solve, "plan": cmd_plan, "fluid": cmd_fluid}[a.command](a)
    except TranslucencyError as exc:
        print(f"error: {' '.join(str(exc).split())}", file=sys.stderr)
        return 2
    except OSError as exc:  # a disk full or a file gone while writing: nothing was written (cache.write_files)
        where = f" {exc.filename}" if exc.filename else ""
        print(f"error: cannot write or read{where}: {exc.strerror or exc}; nothing was written", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
