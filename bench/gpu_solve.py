"""Benchmark of the GPU diffusion solve (gpu_shaders) against the CPU numpy solver.

Usage (repo root)::

    .venv/bin/python bench/gpu_solve.py [--out FILE.md] [--graphs bunny,synthetic] [--cache-dir DIR]

For each graph -- the Stanford bunny baked at quality "preview"
(mm_per_unit = 1000, marble, one sun light) and a synthetic graph of about
500k nodes (the same bake refined one more level: one more nested 1-to-8
refinement, ``levels + 1``/``refinements + 1``, from a base surface scaled so
the finest level lands near 500k nodes) -- it prints:

* ms per Chebyshev step and per Jacobi sweep on the finest level, GPU and CPU
  numpy, and node updates per second;
* ms per converged solve (``fast``, tol 1e-4, all levels coarse to fine, and
  the frame-to-frame case: warm start after the sun moved 2 degrees), GPU
  fp32, GPU fp16 and CPU in the same run;
* the speed-up of the bake's block packing over a random node order
  (same system, nodes shuffled within the inner and the surface group);
* the error of fp16 storage against fp32 (vertex radiance and surface phi).

The GPU runs through Blender's ``gpu`` module, initialised headless by a 1x1
Workbench render.  On a machine without a GPU that is Mesa's llvmpipe, a
software rasteriser on the CPU: the absolute GPU times are then CPU times
and say nothing about a real GPU; the errors and step counts still hold.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402

from data import mesh_path  # noqa: E402

SUN = dict(irradiance=1000.0, direction=(0.3, -0.5, -0.8))


# ------------------------------------------------------------------ setup
def init_gpu() -> str:
    """Start Blender's GPU backend headless (1x1 Workbench render); returns the renderer."""
    if "bpy" not in sys.modules:
        os.environ.setdefault("BLENDER_USER_RESOURCES", tempfile.mkdtemp(prefix="translucency-bench-"))
    from gpu_shaders import init_headless

    return init_headless()


TARGET_NODES = 500_000


def _load_or_bake(V, F, settings, path):
    from translucency_addon.quadgraph import bake as bake_mod
    from translucency_addon import cache

    if path is not None and path.exists():
        try:
            return cache.load_bake(str(path), expected_key=bake_mod.mesh_key(V, F, settings)), 0.0
        except Exception as ex:  # noqa: BLE001 - stale cache (settings or engine changed): bake again
            print(f"  (cache {path.name} not usable, baking: {str(ex)[:100]})")
    t0 = time.perf_counter()
    bk = bake_mod.bake_mesh(V, F, settings)
    seconds = time.perf_counter() - t0
    if path is not None:
        cache.save_bake(str(path), bk)
    return bk, seconds


def get_bake(name: str, cache_dir: Path | None, _memo={}):  # noqa: B006 - the bakes memoised per process
    """'bunny': quality "preview"; 'synthetic': the same bake with one more nested 1-to-8
    refinement level, its base surface scaled so that the finest level has about 500k nodes."""
    from dataclasses import replace

    from translucency_addon.quadgraph import bake as bake_mod
    from translucency_addon.geometry import meshio

    V, F = meshio.load_obj(str(mesh_path("stanford-bunny")))[:2]
    bunny_settings = bake_mod.BakeSettings(quality="preview", mm_per_unit=1000.0)
    if "bunny" not in _memo:
        _memo["bunny"] = _load_or_bake(V, F, bunny_settings, cache_dir / "gpu-bench-bunny.npz" if cache_dir else None)
    if name == "bunny":
        return _memo["bunny"]
    bunny = _memo["bunny"][0]
    s = bunny.settings.resolved()
    fin = bunny.finest
    predicted = 8 * fin.n_inner + 4 * fin.n_surface  # one more 1-to-8 refinement
    base = max(20, int(round(s.base_triangles * TARGET_NODES / predicted)))
    extra = {"refinements": s.refinements + 1} if hasattr(s, "refinements") else {}
    settings = replace(s, levels=s.levels + 1, base_triangles=base, **extra)
    return _load_or_bake(V, F, settings, cache_dir / "gpu-bench-synthetic.npz" if cache_dir else None)


def permuted(system, rng):
    """The same system with nodes shuffled within the inner and within the surface group."""
    nI, N = system.level.n_inner, system.n
    perm = np.concatenate([rng.permutation(nI), nI + rng.permutation(N - nI)])  # new -> old
    inv = np.empty(N, dtype=np.int64)
    inv[perm] = np.arange(N)  # old -> new
    nbr = system.nbr[perm]
    nbr = np.where(nbr >= 0, inv[np.maximum(nbr, 0)], -1).astype(np.int32)
    return nbr, system.off[perm], system.diag[perm], system.b_scale[perm[nI:] - nI]


# ------------------------------------------------------------------ timing
def per_call(fn, sync, n: int, repeats: int = 3) -> float:
    """Seconds per call of fn: n calls bracketed by sync (a read-back that waits for the GPU),
    best of ``repeats`` (the minimum is the least disturbed by other load on the machine)."""
    fn()
    sync()
    best = None
    for _ in range(repeats):
        t0 = time.perf_counter()
        for _ in range(n):
            fn()
        sync()
        dt = (time.perf_counter() - t0) / n
        best = dt if best is None else min(best, dt)
    return best


def gpu_step_times(system, nbr, off, diag, b_scale, steps: int):
    from gpu_shaders import device, pack

    lv = system.level
    lay = pack.plan_layout(lv.n_inner, lv.n_surface, lv.block_size)
    g = device.GPULevel(lay, nbr)
    g.upload_coefficients(off, diag, b_scale)
    g.upload_q(np.ones((lv.n_surface, 3)))
    rng = np.random.default_rng(0)
    g.set_x(rng.random((lv.n_nodes, 3)))
    g.d[0] = g.upload_nodes(rng.random((lv.n_nodes, 3)))
    state = {"a": 0}

    def cheb():
        a = state["a"]
        g.chebyshev(g.d[a], g.d[1 - a], 0.5, 0.5)
        state["a"] = 1 - a

    def sync():
        g.norm2(g.x_current)

    t_cheb = per_call(cheb, sync, steps)
    t_jac = per_call(g.jacobi_step, sync, steps)
    t_red = per_call(lambda: g.norm2(g.r), lambda: None, max(steps // 4, 5))
    g.free()
    return t_cheb, t_jac, t_red


def cpu_step_times(system, steps: int):
    """The CPU solver's own steps: CSR products (LevelSystem.apply) where the engine has them,
    else the packed numpy twins."""
    from translucency_addon.diffusion import kernels

    rng = np.random.default_rng(0)
    N = system.n
    x, r, d = (rng.random((N, 3)) for _ in range(3))
    b = system.rhs(np.ones((system.level.n_surface, 3)))
    if hasattr(system, "apply") and hasattr(kernels, "chebyshev_update"):
        system.apply(x)  # builds the CSR matrices once

        def cheb():
            return kernels.chebyshev_update(x, r, d, system.apply(d), system.diag, 0.5, 0.5)

        def jac():
            return x + (b - system.apply(x)) / system.diag
    else:
        def cheb():
            return kernels.chebyshev_step(system.nbr, system.off, system.diag, x, r, d, 0.5, 0.5)

        def jac():
            return kernels.jacobi_sweep(system.nbr, system.off, system.diag, b, x)
    return per_call(cheb, lambda: None, steps), per_call(jac, lambda: None, steps)


BYTES_PER_NODE_UPDATE = 48  # roofline estimate: explicit 4-neighbour graph, fp32, one Chebyshev step
H200_BANDWIDTH = 4.8e12  # bytes/s, the H200's HBM3e: the roofline is ~100 G node updates/s


def timed_solve(solver, q, warm=None, repeat: int = 2):
    """Best of ``repeat`` solves (the first one also compiles kernels / warms caches).

    Also counts the GPU dispatches of the last solve (``gpu_shaders.runtime.STATS``) on ``solver.dispatches``.
    """
    from gpu_shaders import runtime

    best, res = None, None
    for _ in range(repeat):
        n0 = runtime.STATS["dispatches"]
        t0 = time.perf_counter()
        res = solver.solve(q=q, warm_start=warm)
        dt = time.perf_counter() - t0
        solver.dispatches = runtime.STATS["dispatches"] - n0
        best = dt if best is None else min(best, dt)
    return best, res


def node_updates(bake, res) -> int:
    """Node updates of a solve: steps x nodes, summed over the levels it solved."""
    n = [lv.n_nodes for lv in bake.levels][-len(res.level_solves):]
    return int(sum(ls.iterations * k for ls, k in zip(res.level_solves, n)))


# ------------------------------------------------------------------ one graph
def bench_graph(name: str, args) -> dict:
    import gpu_shaders
    from translucency_addon.diffusion import solver as diffusion, spectral
    from translucency_addon.scene import lights, materials

    bk, bake_s = get_bake(name, args.cache_dir)
    fin = bk.finest
    mat = materials.material_from_preset("marble")
    opts = diffusion.SolveOptions(solver="fast", tol=args.tol)
    print(f"\n[{name}] levels {[lv.n_nodes for lv in bk.levels]} nodes "
          f"(finest: {fin.n_inner:,} inner + {fin.n_surface:,} surface)" + (f", baked in {bake_s:.0f} s" if bake_s else ""),
          flush=True)
    cpu = diffusion.DiffusionSolver(bk, mat, options=opts)
    sun = lights.Light("sun", name="sun", **SUN)
    d2 = np.radians(2.0)
    rot = np.array([[np.cos(d2), -np.sin(d2), 0], [np.sin(d2), np.cos(d2), 0], [0, 0, 1]])
    sun2 = lights.Light("sun", name="sun", irradiance=SUN["irradiance"], direction=tuple(rot @ np.array(SUN["direction"])))
    q = cpu.incident([sun])
    q2 = cpu.incident([sun2])
    for s in cpu.systems:
        spectral.spectral_bounds(s)  # per material, not per frame: outside the timings

    row = {"graph": name, "nodes": fin.n_nodes, "levels": len(bk.levels), "all_nodes": sum(lv.n_nodes for lv in bk.levels)}
    system = cpu.systems[-1]
    # Steps on the finest level, block order vs random order.
    # Block and random order alternate, best of each, to cancel drifting load on a shared machine.
    rnbr, roff, rdiag, rbs = permuted(system, np.random.default_rng(1))
    block, rand = [], []
    for _ in range(args.rounds):
        block.append(gpu_step_times(system, system.nbr, system.off, system.diag, system.b_scale, args.steps))
        rand.append(gpu_step_times(system, rnbr, roff, rdiag, rbs, args.steps))
    t_cheb, t_jac, t_red = np.min(block, axis=0)
    rt_cheb, rt_jac, _ = np.min(rand, axis=0)
    c_cheb, c_jac = cpu_step_times(system, max(args.steps // 2, 3))
    row.update(gpu_cheb_ms=1e3 * t_cheb, gpu_jacobi_ms=1e3 * t_jac, gpu_norm_ms=1e3 * t_red,
               rand_cheb_ms=1e3 * rt_cheb, rand_jacobi_ms=1e3 * rt_jac,
               cpu_cheb_ms=1e3 * c_cheb, cpu_jacobi_ms=1e3 * c_jac)
    print(f"  steps: GPU cheb {1e3 * t_cheb:.2f} ms (random order {1e3 * rt_cheb:.2f}), jacobi {1e3 * t_jac:.2f} ms "
          f"(random {1e3 * rt_jac:.2f}); CPU numpy cheb {1e3 * c_cheb:.1f} ms, jacobi {1e3 * c_jac:.1f} ms", flush=True)

    # Converged solves.
    tc, rc = timed_solve(cpu, q, repeat=2)
    twc, rwc = timed_solve(cpu, q2, warm=rc, repeat=1)
    row.update(cpu_solve_s=tc, cpu_iters=rc.iterations, cpu_warm_s=twc, cpu_warm_iters=rwc.iterations,
               level_iters="/".join(str(ls.iterations) for ls in rc.level_solves))
    Lc = cpu.vertex_radiance(rc)
    print(f"  CPU solve {tc:.2f} s ({rc.iterations} steps), warm {twc:.2f} s ({rwc.iterations})", flush=True)
    results = {}
    for prec in ("fp32", "fp16"):
        solver, backend, msg = gpu_shaders.make_solver(bk, mat, None, opts, prefer="GPU", precision=prec)
        for s, sc in zip(solver.systems, cpu.systems):  # same bounds as the CPU run (deterministic anyway)
            s.lam_min, s.lam_max = sc.lam_min, sc.lam_max
        t, r = timed_solve(solver, q, repeat=2)
        disp = solver.dispatches
        upd = node_updates(bk, r)
        t0 = time.perf_counter()
        L = solver.vertex_radiance(r)
        t_rad = time.perf_counter() - t0
        tw, rw = timed_solve(solver, q2, warm=r, repeat=1)
        row.update({f"{prec}_dispatches": disp, f"{prec}_warm_dispatches": solver.dispatches,
                    f"{prec}_updates": upd, f"{prec}_gbs": upd * BYTES_PER_NODE_UPDATE / t / 1e9,
                    f"{prec}_warm_updates": node_updates(bk, rw),
                    f"{prec}_warm_gbs": node_updates(bk, rw) * BYTES_PER_NODE_UPDATE / tw / 1e9})
        results[prec] = (r, L)
        row.update({f"{prec}_solve_s": t, f"{prec}_iters": r.iterations,
                    f"{prec}_level_iters": "/".join(str(ls.iterations) for ls in r.level_solves), f"{prec}_warm_s": tw,
                    f"{prec}_warm_iters": rw.iterations, f"{prec}_radiance_ms": 1e3 * t_rad,
                    f"{prec}_residual": float(r.residual.max()),
                    f"{prec}_L_err_vs_cpu": float(np.abs(L - Lc).max() / np.abs(Lc).max())})
        print(f"  GPU {prec}: solve {t:.2f} s ({r.iterations} steps, residual {r.residual.max():.2e}), warm {tw:.2f} s "
              f"({rw.iterations}), radiance {1e3 * t_rad:.1f} ms; L_o vs CPU {row[f'{prec}_L_err_vs_cpu']:.2e}",
              flush=True)
        solver.free()
    (r32, L32), (r16, L16) = results["fp32"], results["fp16"]
    lit = L32 > 0.01 * L32.max()
    row.update(fp16_L_max=float(np.abs(L16 - L32).max() / np.abs(L32).max()),
               fp16_L_mean_rel=float(np.mean(np.abs(L16 - L32)[lit] / L32[lit])),
               fp16_phi_max=float(np.abs(r16.phi_surface[-1] - r32.phi_surface[-1]).max()
                                  / np.abs(r32.phi_surface[-1]).max()))
    return row


# ------------------------------------------------------------------ every pass (issue 33, item 4)
PASSES_HEADING = "## Every pass on the GPU path, per frame (issue 33, item 4)\n"


def _frame_costs(fn):
    """Run ``fn()`` and return (its value, wall seconds, GPU dispatches, bytes uploaded, bytes read back)."""
    from gpu_shaders import runtime

    before = dict(runtime.STATS)
    t0 = time.perf_counter()
    out = fn()
    dt = time.perf_counter() - t0
    return (out, dt, runtime.STATS["dispatches"] - before["dispatches"],
            runtime.STATS["bytes_up"] - before["bytes_up"], runtime.STATS["bytes_down"] - before["bytes_down"])


def bench_passes(args) -> list:
    """The passes a frame runs besides the plain solve, each on the CPU and the GPU solver, the second of two
    frames (the first builds and warms; the second is what a user's next frame costs): the cavity exchange
    (a marble cube 20 mm across with a hollow 6 mm in radius, Draft, the sun turned 2 degrees), a deformed
    frame (a marble bar 40 x 10 x 10 mm twisted 10 then 12 degrees, Draft, sky visibility, a sun) and a
    particle fluid's frame (bench/fluid.py's ball, the particles jittered again, warm-started: cells, light
    pass and output on the CPU in both columns, the diffusion solve on each backend)."""
    from gpu_shaders.solver import GPUDiffusionSolver
    from translucency_addon import __main__ as cli
    from translucency_addon.cache import load_bake
    from translucency_addon.deformation.frames import DeformationFrames
    from translucency_addon.deformation.pose import DeformationRig
    from translucency_addon.diffusion import solver as diffusion
    from translucency_addon.geometry import meshio, primitives
    from translucency_addon.inner_parts.bake import diffusion_material
    from translucency_addon.inner_parts.cavity import solve_with_cavities
    from translucency_addon.quadgraph import bake as bake_mod
    from translucency_addon.scene import lights, materials

    marble = materials.material_from_preset("marble")
    opts = diffusion.SolveOptions(tol=args.tol)
    d2 = np.radians(2.0)
    rot = np.array([[np.cos(d2), -np.sin(d2), 0], [np.sin(d2), np.cos(d2), 0], [0, 0, 1]])
    suns = [[lights.Light("sun", irradiance=1000.0, direction=tuple(v))]
            for v in (np.array([-1.0, -0.3, -0.2]), rot @ np.array([-1.0, -0.3, -0.2]))]
    rows = []

    work = Path(tempfile.mkdtemp(prefix="gpu-passes-"))
    (Vb, Fb), (Vs, Fs) = primitives.cube_with_sphere(20.0, 6.0, n=8, subdivisions=2)
    meshio.save_obj(work / "cube.obj", Vb, Fb)
    meshio.save_obj(work / "hole.obj", Vs, Fs)
    cli.main(["bake", str(work / "cube.obj"), "--inner", f"{work / 'hole.obj'}:cavity", "--quality", "draft",
              "--levels", "2", "--material", "marble", "-o", str(work / "cube.npz")])
    bk = load_bake(work / "cube.npz")
    mat, field = diffusion_material(marble, bk.composite)
    out = {}
    for label, solver in (("CPU", diffusion.DiffusionSolver(bk, mat, field, opts)),
                          ("GPU", GPUDiffusionSolver(bk, mat, field, opts))):
        res, info = solve_with_cavities(solver, bk.composite.exchange, suns[0], None, tol=args.tol)
        (res2, info2), dt, disp, up, down = _frame_costs(lambda: solve_with_cavities(
            solver, bk.composite.exchange, suns[1], None, tol=args.tol, warm_start=res))
        L = solver.vertex_radiance(res2)
        out[label] = dict(seconds=dt, dispatches=disp, up=up, down=down, solves=info2["solves"], L=L)
        getattr(solver, "free", lambda: None)()
    rows.append(_pass_row("cavity exchange (cube, hollow)", bk.finest.n_nodes, out))

    V, F = primitives.box((4.0, 1.0, 1.0), n=(16, 4, 4))
    bar = bake_mod.bake_mesh(V, F, bake_mod.BakeSettings(quality="draft", mm_per_unit=10.0, sky_directions=32))
    rig = DeformationRig(bar)
    out = {}
    for label, make in (("CPU", None), ("GPU", GPUDiffusionSolver)):
        frames = DeformationFrames(bar, marble, options=opts, rig=rig, make_solver=make)
        frames.solve(primitives.twist(V, 10.0, along=0), suns[0], None)
        o, dt, disp, up, down = _frame_costs(lambda: frames.solve(primitives.twist(V, 12.0, along=0), suns[0], None))
        out[label] = dict(seconds=dt, dispatches=disp, up=up, down=down, solves=1, L=o.radiance)
        getattr(o.solver, "free", lambda: None)()
    rows.append(_pass_row("deformed frame (bar, twisted)", bar.finest.n_nodes, out))

    from bench.fluid import scene as fluid_scene
    from gpu_shaders.solver import GPUFluidDiffusionSolver
    from translucency_addon.fluid import FluidSolver

    rest, R, surface, fs, light = fluid_scene(args.fluid_particles)
    rng = np.random.default_rng(1)
    frames = [rest + rng.uniform(-0.1, 0.1, rest.shape) for _ in range(2)]
    out = {}
    for label, make in (("CPU", None), ("GPU", GPUFluidDiffusionSolver)):
        solver = FluidSolver(fs.material, R, fs.mm_per_unit, fs.options, make_solver=make)
        first = solver.solve(frames[0], surface=surface, **light)
        res, dt, disp, up, down = _frame_costs(lambda: solver.solve(frames[1], surface=surface,
                                                                     warm_start=first.state, **light))
        out[label] = dict(seconds=dt, dispatches=disp, up=up, down=down, solves=1, L=res.vertex_radiance)
        for r in (first, res):
            getattr(r.diffusion, "free", lambda: None)()
    rows.append(_pass_row(f"particle fluid ({len(rest):,} particles, jittered)", res.graph.n_nodes, out))
    return rows


def _pass_row(name, nodes, out) -> dict:
    c, g = out["CPU"], out["GPU"]
    return {"pass": name, "nodes": nodes, "solves": g["solves"], "dispatches": g["dispatches"], "up": g["up"],
            "down": g["down"], "gpu_ms": 1e3 * g["seconds"], "cpu_ms": 1e3 * c["seconds"],
            "L_err": float(np.abs(g["L"] - c["L"]).max() / np.abs(c["L"]).max())}


def passes_markdown(rows, renderer: str) -> str:
    soft = "llvmpipe" in renderer.lower() or "softpipe" in renderer.lower()
    out = [PASSES_HEADING, f"`.venv/bin/python bench/gpu_solve.py --passes --out docs/bench_gpu.md` on **{renderer}**"
           + (" (Mesa's software rasteriser on the 2 CPU cores: the GPU times are CPU times and say nothing about a "
              "real GPU; the dispatches, bytes and errors carry over)." if soft else "."), "",
           "The passes that ran on the CPU only before (the cavity exchange's solves, deformed frames, a particle "
           "fluid's diffusion), each the "
           "second of two frames on the CPU solver and on the GPU solver in the same run; per frame: the solves "
           "it took, the GPU's compute dispatches, the texture data uploaded (q per solve; per pose the "
           "coefficients) and read back (the cavity exchange reads every solve's phi), the wall time, and the "
           "GPU's vertex radiance against the CPU's.", "",
           "| pass | finest nodes | solves | GPU dispatches | uploaded | read back | GPU ms | CPU ms | "
           "L_o GPU vs CPU (max abs / max) |", "|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        out.append(f"| {r['pass']} | {r['nodes']:,} | {r['solves']} | {r['dispatches']:,} | {r['up'] / 2**20:.2f} MiB | "
                   f"{r['down'] / 2**20:.2f} MiB | {r['gpu_ms']:,.0f} | {r['cpu_ms']:,.0f} | {r['L_err']:.1e} |")
    return "\n".join(out) + "\n"


# ------------------------------------------------------------------ report
def markdown(rows, renderer: str, args) -> str:
    out = []
    out.append("# GPU diffusion solve benchmark (`bench/gpu_solve.py`)\n")
    out.append(f"GPU backend: **{renderer}**.")
    if "llvmpipe" in renderer.lower() or "softpipe" in renderer.lower():
        out.append("**All GPU times below are llvmpipe times: Mesa's software rasteriser running the compute "
                   "shaders on the CPU (2 cores here). They are CPU times and say nothing about a real GPU; no "
                   "real GPU was used.** The errors and step counts carry over to a GPU; the block-vs-random "
                   "ratio here reflects CPU caches, not a GPU's texture cache.")
    (l0, l1, ncpu) = getattr(args, "load", ((0, 0, 0), (0, 0, 0), os.cpu_count()))
    out.append(f"Machine: {ncpu} CPU cores; 1-minute load average {l0[0]:.1f} at the start and {l1[0]:.1f} at the end "
               "of the run (other jobs shared the cores; step times are the best of several alternating runs).")
    out.append(f"\nMarble (Jensen 2001), one sun light (1000 W/m^2), `fast` solver (Chebyshev), tol {args.tol:g}, "
               f"check every 8 steps. CPU = the numpy `DiffusionSolver` in the same run (fp64).\n")
    out.append("## Per step, finest level\n")
    out.append("| graph | nodes | GPU Chebyshev step ms | GPU Jacobi sweep ms | GPU node updates/s (Cheb.) | "
               "CPU numpy Chebyshev step ms | CPU Jacobi ms | GPU/CPU step speed-up | "
               "block order vs random: Chebyshev | Jacobi |")
    out.append("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        out.append(
            f"| {r['graph']} | {r['nodes']:,} | {r['gpu_cheb_ms']:.2f} | {r['gpu_jacobi_ms']:.2f} | "
            f"{r['nodes'] / (r['gpu_cheb_ms'] * 1e-3) / 1e6:.1f} M | {r['cpu_cheb_ms']:.1f} | {r['cpu_jacobi_ms']:.1f} | "
            f"{r['cpu_cheb_ms'] / r['gpu_cheb_ms']:.1f}x | "
            f"{100 * (r['rand_cheb_ms'] / r['gpu_cheb_ms'] - 1):+.0f} % | {100 * (r['rand_jacobi_ms'] / r['gpu_jacobi_ms'] - 1):+.0f} % |")
    out.append("\n(\"block order vs random\": how much longer a step takes when the same nodes are stored in a random "
               "order within the inner and the surface groups; the paper reports 30-60 % on a 2010 GPU.)\n")
    out.append("## Converged solves\n")
    out.append("| graph | all levels, nodes | steps per level, coarse to fine (CPU / GPU fp32) | CPU s | GPU fp32 s | "
               "GPU fp16 s | warm start after 2 deg, finest steps | CPU s | GPU fp32 s | GPU fp16 s | "
               "GPU radiance + read-back ms |")
    out.append("|---|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        out.append(
            f"| {r['graph']} | {r['all_nodes']:,} | {r['level_iters']} / {r['fp32_level_iters']} | "
            f"{r['cpu_solve_s']:.2f} | {r['fp32_solve_s']:.2f} | {r['fp16_solve_s']:.2f} | "
            f"{r['cpu_warm_iters']} / {r['fp32_warm_iters']} | {r['cpu_warm_s']:.2f} | {r['fp32_warm_s']:.2f} | "
            f"{r['fp16_warm_s']:.2f} | {r['fp32_radiance_ms']:.1f} |")
    out.append("\n## Dispatches and bandwidth per converged solve\n")
    out.append(f"Achieved bandwidth = node updates (steps x nodes over the levels solved) x "
               f"{BYTES_PER_NODE_UPDATE} B (the roofline estimate for one fp32 step of a 4-neighbour graph) / "
               f"solve time; roofline = an H200's {H200_BANDWIDTH / 1e12:.1f} TB/s (~100 G node updates/s).  "
               "The CPU column is the numpy solve of the same run.\n")
    out.append("| graph | solve | GPU dispatches | dispatches per step | node updates | GPU fp32 ms | achieved GB/s | "
               "of the H200 roofline | GPU fp16 ms | CPU ms |")
    out.append("|---|---|---:|---:|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        for label, k, cpu_t, steps in (("all levels", "", r["cpu_solve_s"], r["fp32_iters"]),
                                       ("warm (finest)", "warm_", r["cpu_warm_s"], r["fp32_warm_iters"])):
            d = r[f"fp32_{k}dispatches"]
            gbs = r[f"fp32_{k}gbs"]
            t32 = r["fp32_solve_s"] if not k else r["fp32_warm_s"]
            t16 = r["fp16_solve_s"] if not k else r["fp16_warm_s"]
            out.append(f"| {r['graph']} | {label} | {d:,} | {d / max(steps, 1):.2f} | {r[f'fp32_{k}updates']:,} | "
                       f"{1e3 * t32:,.1f} | {gbs:.3g} | {100 * gbs * 1e9 / H200_BANDWIDTH:.2g} % | {1e3 * t16:,.1f} | "
                       f"{1e3 * cpu_t:,.1f} |")
    out.append("\n## Accuracy\n")
    out.append("| graph | L_o GPU fp32 vs CPU (max abs / max) | L_o GPU fp16 vs CPU | fp16 vs fp32: L_o max | "
               "L_o mean rel. (lit vertices) | surface phi max |")
    out.append("|---|---:|---:|---:|---:|---:|")
    for r in rows:
        out.append(f"| {r['graph']} | {r['fp32_L_err_vs_cpu']:.1e} | {r['fp16_L_err_vs_cpu']:.1e} | "
                   f"{r['fp16_L_max']:.1e} | {r['fp16_L_mean_rel']:.1e} | {r['fp16_phi_max']:.1e} |")
    return "\n".join(out) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", help="write the tables as markdown to this file")
    ap.add_argument("--graphs", default="bunny,synthetic", help="comma list: bunny, synthetic")
    ap.add_argument("--steps", type=int, default=40, help="steps per timing")
    ap.add_argument("--rounds", type=int, default=2, help="alternating block/random timing rounds")
    ap.add_argument("--tol", type=float, default=1e-4)
    ap.add_argument("--cache-dir", type=Path, default=Path(tempfile.gettempdir()),
                    help="where the bakes are cached between runs")
    ap.add_argument("--fluid-particles", type=int, default=16384, help="the fluid row's ball (--passes)")
    ap.add_argument("--passes", action="store_true",
                    help="only the passes besides the plain solve (cavity exchange, deformed frame), written as "
                         "their section of --out")
    args = ap.parse_args(argv)
    renderer = init_gpu()
    if args.passes:
        from bench.bench_io import write_section

        return write_section(passes_markdown(bench_passes(args), renderer), PASSES_HEADING, args.out)
    print(f"GPU backend: {renderer}")
    if "llvmpipe" in renderer.lower():
        print("NOTE: llvmpipe = software rendering on the CPU; GPU times below are CPU times.")
    load0 = os.getloadavg()
    rows = [bench_graph(name.strip(), args) for name in args.graphs.split(",") if name.strip()]
    args.load = (load0, os.getloadavg(), os.cpu_count())
    md = markdown(rows, renderer, args)
    print()
    print(md)
    if args.out:
        Path(args.out).write_text(md, encoding="utf-8")
        print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
