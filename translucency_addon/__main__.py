"""Command line: bake and solve OBJ files without Blender (pipelines, render farms).

    python -m translucency_addon bake MESH.obj -o CACHE.npz [--quality draft|preview|final]
                                      [--levels N] [--mm-per-unit X] [--sky-directions 64]
                                      [--single-scattering [--material marble] [--ss-quality preview]
                                       [--ss-dirs 128] [--ss-samples 20000] [--ss-order 4]]
    python -m translucency_addon bake OUTER.obj --inner PART.obj:ROLE ... [--voxel-number-map] -o CACHE.npz
                                      (ROLE: a preset name, cavity or opaque)
    python -m translucency_addon fluid POINTS.npy -o PHI.npz --radius R --mm-per-unit S
                                      (--material NAME | --sigma-a R,G,B --sigma-s R,G,B --eta X)
                                      [--env R,G,B] [--sun DX,DY,DZ:E] [--point X,Y,Z:W]
                                      [--surface MESH.obj --surface-out L.npy] [--stats STATS.json]
    python -m translucency_addon solve CACHE.npz -o OUT.npy [--deformed POSED.obj]
                                      [--material marble | --sigma-a R,G,B --sigma-s R,G,B --eta X]
                                      [--env R,G,B] [--sun DX,DY,DZ:E] [--point X,Y,Z:W]
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
import hashlib
import json
import os
import sys
import time

import numpy as np

from .errors import TranslucencyError


class _Parser(argparse.ArgumentParser):
    """argparse whose errors are one line on stderr, exit status 2, like every other refusal of the CLI."""

    def error(self, message):
        print(f"error: {message} (run '{self.prog} --help' for what each option accepts)", file=sys.stderr)
        sys.exit(2)


def _checked(check, what: str, cast=float):
    """An argparse type: ``cast(text)`` passed through the engine's ``check`` (its message on failure)."""
    kind = "a whole number" if cast is int else "a number"

    def parse(text):
        try:
            return check(cast(text))
        except ValueError:
            raise argparse.ArgumentTypeError(f"{what}: expected {kind}, got {text!r}") from None
        except TranslucencyError as exc:
            raise argparse.ArgumentTypeError(str(exc)) from None
    parse.__name__ = what
    return parse


def _in_range(lo: float, hi: float, what: str, cast=float, lo_open: bool = False, hi_open: bool = False):
    """An argparse type: a finite number in [lo, hi] (open ends where asked)."""
    def check(v):
        if not (np.isfinite(v) and (v > lo if lo_open else v >= lo) and (v < hi if hi_open else v <= hi)):
            ends = ("(" if lo_open else "[") + f"{lo:g}, {hi:g}" + (")" if hi_open else "]")
            raise TranslucencyError(f"expected a finite number in {ends}, got {v:g}")
        return v
    return _checked(check, what, cast)


def _mm_per_unit(text):
    from .materials import check_mm_per_unit

    return _checked(check_mm_per_unit, "--mm-per-unit")(text)


def _radius(text):
    from .fluid.particles import check_radius

    return _checked(check_radius, "--radius")(text)


def _eta(text):
    from .fresnel import check_eta

    return _checked(check_eta, "--eta")(text)


_tolerance = _in_range(0.0, 1.0, "--tol", lo_open=True, hi_open=True)


def _floats(text: str, n: int, what: str) -> tuple:
    try:
        vals = tuple(float(x) for x in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{what}: expected {n} comma-separated numbers, got {text!r}") from None
    if len(vals) != n:
        raise argparse.ArgumentTypeError(f"{what}: expected {n} comma-separated numbers, got {text!r}")
    if not all(np.isfinite(vals)):
        raise argparse.ArgumentTypeError(f"{what}: expected {n} finite numbers (no NaN or Inf), got {text!r}")
    return vals


def _rgb(text):
    return _floats(text, 3, "R,G,B")


def _camera(text):
    return _floats(text, 3, "--camera X,Y,Z")


def _sun(text):
    try:
        d, e = text.split(":")
    except ValueError:
        raise argparse.ArgumentTypeError(f"--sun: expected DX,DY,DZ:E, got {text!r}") from None
    return _floats(d, 3, "--sun direction"), _floats(e, 1, "--sun irradiance")[0]


def _point(text):
    try:
        p, w = text.split(":")
    except ValueError:
        raise argparse.ArgumentTypeError(f"--point: expected X,Y,Z:W, got {text!r}") from None
    return _floats(p, 3, "--point position"), _floats(w, 1, "--point power")[0]


def _field(text):
    kind, _, scale = text.partition(":")
    if not scale:
        return kind, 1.0
    return kind, _in_range(0.0, np.inf, "--field SCALE", lo_open=True, hi_open=True)(scale)


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
    b.add_argument("--levels", type=_in_range(1, 6, "--levels", int), default=None,
                   help="number of multi-resolution levels, 1 to 6 (default: the quality's)")
    b.add_argument("--mm-per-unit", type=_mm_per_unit, default=1.0,
                   help="millimetres per mesh unit, a finite number > 0 (default 1)")
    b.add_argument("--sky-directions", type=_in_range(0, 4096, "--sky-directions", int), default=0,
                   help="also bake sky visibility with N rays per surface node (self-occlusion and one "
                        "interreflection bounce for world light; 0 = off, the default, or 8 to 4096; the Blender "
                        "add-on uses 64)")
    b.add_argument("--level-mode", choices=["refine", "independent"], default="refine",
                   help="finer levels by nested refinement (fast) or independent tetrahedralisation (paper)")
    b.add_argument("--no-optimize", action="store_true", help="skip fTetWild's optimisation (fast, slivers)")
    b.add_argument("--single-scattering", action="store_true", help="also bake RBF optical-depth samples")
    _material_args(b, "single scattering: ")
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
    _material_args(s, "")
    s.add_argument("--env", type=_rgb, default=None, help="uniform environment radiance R,G,B, W/(m^2 sr), each >= 0 (unoccluded)")
    s.add_argument("--sun", type=_sun, action="append", default=[],
                   help="sun light DX,DY,DZ:E -- direction the light travels (object space, not 0,0,0) and "
                        "irradiance in W/m^2, >= 0 (repeatable)")
    s.add_argument("--point", type=_point, action="append", default=[],
                   help="point light X,Y,Z:W -- position (object units) and radiant power in W, >= 0 (isotropic; "
                        "repeatable)")
    s.add_argument("--solver", choices=["paper", "fast", "direct"], default="fast",
                   help="paper: Jacobi relaxation (eqs. 8-9, slow on fine graphs); fast: Chebyshev (default); "
                        "direct: sparse LU (exact, memory grows fast)")
    s.add_argument("--tol", type=_tolerance, default=1e-4,
                   help="relative residual tolerance, in (0, 1) (default 1e-4)")
    s.add_argument("--no-shadows", action="store_true", help="ignore occlusion of point and sun lights")
    s.add_argument("--mm-per-unit", type=_mm_per_unit, default=None,
                   help="override the baked scene scale: millimetres per mesh unit, a finite number > 0")
    s.add_argument("--stats", default=None, help="write node counts, sweeps, residual and timings (.json, in an "
                                                 "existing, writable folder)")
    s.add_argument("--camera", type=_camera, default=None,
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
    p.add_argument("--env", type=_rgb, default=None, help="uniform environment radiance R,G,B, W/(m^2 sr), each >= 0 (default: none)")
    p.add_argument("--sun", type=_sun, action="append", default=[],
                   help="sun light DX,DY,DZ:E -- direction the light travels (object space, not 0,0,0) and "
                        "irradiance in W/m^2, >= 0 (repeatable)")
    p.add_argument("--point", type=_point, action="append", default=[],
                   help="point light X,Y,Z:W -- position (object units) and radiant power in W, >= 0 (isotropic; "
                        "repeatable)")
    p.add_argument("--mm-per-unit", type=_mm_per_unit, default=None,
                   help="override the baked scene scale: millimetres per mesh unit, a finite number > 0")
    return ap


def _fluid_parser(sub) -> None:
    """The ``fluid`` subcommand (particle fluids, Kang & Kim 2013; ``fluid/cli.py``)."""
    f = sub.add_parser("fluid", help="solve a particle fluid frame by frame (Voronoi-fluid cells)")
    f.add_argument("points", help="(N, 3) or (F, N, 3) float array (.npy, numpy.save) of particle positions, "
                                  "object units; NaN rows are absent particles")
    f.add_argument("-o", "--output", required=True,
                   help="per-cell phi, V, surface flag and radiance along the normal; without --surface also "
                        "point_radiance, what the add-on writes onto a point cloud (.npz, in an existing, writable "
                        "folder)")
    f.add_argument("--radius", type=_radius, required=True,
                   help="particle radius, object units, a finite number > 0 (about the particle spacing)")
    f.add_argument("--mm-per-unit", type=_mm_per_unit, required=True,
                   help="millimetres per object unit, a finite number > 0")
    _material_args(f, "")
    f.add_argument("--env", type=_rgb, default=None, help="uniform environment radiance R,G,B, W/(m^2 sr), each >= 0")
    f.add_argument("--sun", type=_sun, action="append", default=[],
                   help="sun DX,DY,DZ:E -- direction (not 0,0,0) and irradiance in W/m^2, >= 0 (repeatable)")
    f.add_argument("--point", type=_point, action="append", default=[],
                   help="point light X,Y,Z:W -- position (object units) and power in W, >= 0 (repeatable)")
    f.add_argument("--camera", type=_camera, default=None,
                   help="perspective camera position X,Y,Z (object units): view-dependent radiance toward it "
                        "(default: along the normals)")
    f.add_argument("--surface", default=None,
                   help="surface mesh (a readable .obj, object units) to carry radiance onto")
    f.add_argument("--surface-out", default=None,
                   help="per-vertex RGB radiance on --surface (.npy, in an existing, writable folder)")
    f.add_argument("--tol", type=_tolerance, default=1e-4, help="relative residual tolerance, in (0, 1) (default 1e-4)")
    f.add_argument("--no-shadows", action="store_true", help="ignore occlusion of point and sun lights")
    f.add_argument("--stats", default=None,
                   help="cell counts, seconds per stage, sweeps per frame (.json, in an existing, writable folder)")


def cmd_fluid(a) -> int:
    from .fluid.cli import run_fluid

    check_files([("POINTS", a.points), ("--surface", a.surface)],
                [("-o", a.output), ("--surface-out", a.surface_out), ("--stats", a.stats)])
    return run_fluid(a, material_from_args(a), *lights_from_args(a), field_spec=lambda P: field_spec_from_args(a, P))


def _material_args(parser, prefix: str) -> None:
    parser.add_argument("--material", default=None, help=prefix + "preset name (marble, skimmilk, skin1, ketchup, ...)")
    parser.add_argument("--mix-with", default=None, help=prefix + "second preset mixed in by --field")
    parser.add_argument("--field", type=_field, default=None,
                        help=prefix + "mixing field KIND[:SCALE], SCALE in object units > 0, e.g. marble:0.05 "
                                      "(default marble, a quarter of the size)")
    parser.add_argument("--sigma-a", type=_rgb, default=None,
                        help=prefix + "absorption R,G,B per mm, each >= 0 (custom material)")
    parser.add_argument("--sigma-s", type=_rgb, default=None,
                        help=prefix + "reduced scattering R,G,B per mm, each >= 0 (custom material)")
    parser.add_argument("--eta", type=_eta, default=1.3,
                        help=prefix + "relative refractive index, in [1, 4] (default 1.3)")


def field_spec_from_args(a, V):
    """The mixing field of a heterogeneous material: --field, or marble at a quarter of the mesh size."""
    from .fields import FieldSpec

    kind, scale = a.field or ("marble", 0.25 * float(np.max(np.ptp(np.asarray(V), axis=0))))
    return FieldSpec(kind=kind, scale=scale)


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


def check_files(inputs=(), outputs=()) -> None:
    """Refuse, before any work, an input that is not a readable file or an output that cannot be written.

    ``inputs`` and ``outputs`` are ``(option, path)`` pairs (``path`` None: not given).  An output's folder
    must exist and be writable (nothing creates it), the output must not be a folder, and no two outputs
    may be the same file.  Raises :class:`InputError` naming the option and the file."""
    from .errors import InputError

    for option, path in inputs:
        if path is None:
            continue
        if not os.path.exists(path):
            raise InputError(f"{option} {path}: no such file")
        if not os.path.isfile(path):
            raise InputError(f"{option} {path}: is a folder, not a file")
        if not os.access(path, os.R_OK):
            raise InputError(f"{option} {path}: cannot be read (no read permission for this user)")
    seen = {}
    for option, path in outputs:
        if path is None:
            continue
        full = os.path.realpath(path)
        folder = os.path.dirname(full)
        if full in seen:
            raise InputError(f"{option} and {seen[full]} are the same file {path}; give each output its own name")
        seen[full] = option
        if os.path.isdir(full):
            raise InputError(f"{option} {path}: is a folder; give a file name inside it")
        if not os.path.isdir(folder):
            raise InputError(f"{option} {path}: the folder {os.path.dirname(os.path.abspath(path))} does not exist; "
                             "create it first")
        if not os.access(folder, os.W_OK | os.X_OK):
            raise InputError(f"{option} {path}: the folder {folder} is not writable for this user")
        if os.path.exists(full) and not os.access(full, os.W_OK) and not os.access(folder, os.W_OK):
            raise InputError(f"{option} {path}: cannot be replaced (no write permission)")


def _inner_paths(specs) -> list:
    """The files of ``--inner PART.obj:ROLE`` (malformed specs are refused later, with the spec)."""
    return [("--inner", str(spec).rpartition(":")[0]) for spec in specs if str(spec).rpartition(":")[0]]


def cmd_bake(a) -> int:
    from .bake import BakeSettings, bake_mesh, format_stats
    from .cache import save_bake
    from .meshio import load_obj

    check_files([("MESH", a.mesh)] + _inner_paths(a.inner), [("-o", a.output)])
    settings = BakeSettings(quality=a.quality, levels=a.levels, mm_per_unit=a.mm_per_unit,
                            level_mode=a.level_mode, optimize=not a.no_optimize, sky_directions=a.sky_directions)
    settings.resolved()  # its ranges (levels, sky directions), before the mesh is read
    if a.single_scattering or a.inner or a.voxel_number_map:
        material_from_args(a)
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
        from .composite_bake import bake_composite, composite_from_files
        from .voxel_number_map import VNMSettings

        material = material or material_from_args(a)
        field = None
        if material.heterogeneous:
            from .fields import evaluate_field

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
    save_bake(a.output, bake)
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


def cmd_solve(a) -> int:
    from .cache import load_bake
    from .diffusion import DiffusionSolver, SolveOptions
    from .fields import evaluate_field

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
    t_load = time.perf_counter() - t0
    field_values = None
    spec = None
    if a.field_values is not None and not material.heterogeneous:
        raise TranslucencyError("--field-values mixes two media: name the second with --mix-with")
    if a.field_values is not None and a.field is not None:
        raise TranslucencyError("--field-values and --field both give the mixing field: use one")
    if a.field_values is not None:
        from .fields import load_vertex_field, vertex_field_at_nodes

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
        from .deformation import deform_from_obj

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
    plan = plan_object(bake, outer_material, lights, env, field_values=field_values, has_single_scattering=has_ss,
                       overrides=overrides, name=name)
    passes = passes_for(plan, bake)
    solver = None
    if passes.use_ms:
        solver_material, solver_field = material, field_values
        if bake.composite is not None:  # inner parts: per-node media (composite_bake)
            from .composite_bake import diffusion_material

            solver_material, solver_field = diffusion_material(material, bake.composite, field_values)
        solver = DiffusionSolver(bake, solver_material, solver_field, SolveOptions(solver=a.solver, tol=a.tol))
    view = ("PERSP", tuple(a.camera)) if a.camera is not None else None
    ss_stats = _single_scattering_stats(a, bake, outer_material, spec) if passes.use_ss else None
    vnm_stats = {"enabled": False, "reason": (
        "turned off (--no-voxel-number-map)" if a.no_voxel_number_map
        else "the cache holds no Voxel Number Map (bake with --voxel-number-map)" if bake.voxel_number_map is None
        else "the planner leaves it out: " + _why(plan, plan.voxel_number_map))}

    def voxel_number_map():
        from .composite_bake import solve_voxel_number_map

        L_vnm, stats_vnm = solve_voxel_number_map(bake, outer_material, lights, env, view, shadows=not a.no_shadows)
        vnm_stats.clear()
        vnm_stats.update(stats_vnm)
        return L_vnm

    t1 = time.perf_counter()
    frame = render_frame(bake, plan, passes, bake_mapping(bake), solver=solver, lights=lights, environment=env,
                         view=view, eta=outer_material.eta, tol=a.tol, shadows=not a.no_shadows,
                         voxel_number_map=voxel_number_map, name=name)
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
        "final_relative_residual": result.residual.tolist() if result is not None else [0.0],
        "seconds": {"load": t_load, "setup": t1 - t0 - t_load, **(result.seconds if result is not None else {}),
                    "diffusion": t_diff - t1,
                    "single_scattering": 0.0 if ss_stats is None else ss_stats["seconds"]["total"],
                    "voxel_number_map": vnm_stats["seconds"]["total"] if vnm_stats["enabled"] else 0.0,
                    "total": t2 - t0},
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
