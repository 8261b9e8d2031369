# SPDX-License-Identifier: GPL-3.0-or-later
"""Where a frame's time goes, against a baseline checkout in the same run, and how cost grows (issue 18).

    .venv/bin/python bench/frame.py [--baseline OTHER_CHECKOUT] [--qualities preview final]
                                    [--sizes 10000 30000 100000 300000 1000000] [--profile final]
                                    [--out docs/bench_solve.md]

*Frame* (the accuracy bench's headline scene ``bunny_marble_sky``: the 40 mm
marble bunny under the sky, Self-Occlusion on, tol 1e-4, bakes from
``bench/out/accuracy_bakes``): each tree -- this one and ``--baseline`` -- runs
in its own process, alternately, twice; the best of each is kept.  Measured:
the first frame (light pass, every level from zero, the bounce, vertex
radiance), two warm frames (the sky turned 5 degrees and back, warm-started
from the previous frame: ``bench/accuracy_core.py``'s frame), and the parts of
a frame with today's two passes (light pass, coarse levels, first use of a
level's spectral bounds, finest pass 1, the bounce's light pass, finest pass 2,
vertex radiance) against this tree's block solve.  The radiance of both trees
is compared.

*Scaling*: a voxel ball (a graph of the contract, 6 links per cell, 40 mm,
marble, uniform light on the surface) from 10k to 1M nodes: sweeps from zero
to the tolerance, ms per sweep (this tree's sweeps and the node-major loop
they replace, same process), a warm frame (light changed by 5 %), setup (spectral bounds,
sweep layout) and memory.  Times are wall-clock on a shared machine: compare ratios.

*Profile* (``--profile QUALITY``): a first and a warm frame of the same scene under cProfile (CPU
clock), each tree in its own process; the parts (light pass, Lanczos, deflation check, sweep layout,
sparse products, the iteration's vector updates) as cumulative times.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
BAKES = ROOT / "bench" / "out" / "accuracy_bakes"


# ---------------------------------------------------------------- worker (runs inside either tree)
def worker(root: str, quality: str, out: str) -> None:
    sys.path.insert(0, root)
    from bench import accuracy_scenes as scenes
    from bench.accuracy_core import Evaluator, environment_turned, view_dirs
    from translucency_addon.diffusion import solver as diffusion

    sc = next(s for s in scenes.reference_scenes() if s.name == "bunny_marble_sky")
    bk, _ = Evaluator(bake_cache=BAKES, log=lambda *a: None).bake(sc, quality=quality)
    mk = lambda: diffusion.DiffusionSolver(bk, sc.material, None, diffusion.SolveOptions(solver="fast", tol=1e-4))  # noqa: E731
    vd = view_dirs(sc)
    fine = len(bk.levels) - 1
    rec = {"nodes": int(bk.finest.n_nodes), "levels": [int(lv.n_nodes) for lv in bk.levels]}
    # The parts of today's frame (two passes), on a fresh solver (so the first use of the bounds counts).
    s = mk()
    from translucency_addon.diffusion.spectral import deflation, spectral_bounds

    clock = time.perf_counter  # wall time: the compiled CG step (diffusion/compiled_cg.py) runs on both cores
    t = {}
    t0 = clock()
    for system in s.systems:  # what a new material costs once: bounds, deflation check, sweep layout
        spectral_bounds(system), deflation(system)
        if hasattr(system, "sweep_operator"):
            system.sweep_operator(np.float32)  # tol 1e-4: the fp32 sweeps (sweeps.FP32_TOL)
    t["setup, all levels (once per material)"] = clock() - t0
    t0 = clock()
    q = s.incident([], sc.environment)
    t["light pass"] = clock() - t0
    t0 = clock()
    if fine:
        s.solve_systems(q, list(range(fine)))
    t["coarse levels"] = clock() - t0
    t0 = clock()
    r1 = s.solve(q=q)  # all levels again (now set up): minus the coarse levels, the finest pass
    t["finest pass 1"] = clock() - t0 - t["coarse levels"]
    fin1 = r1.level_solves[-1]
    t0 = clock()
    L1 = s.vertex_radiance(r1)
    q2 = s.incident([], sc.environment, levels=[fine], bounce=L1)
    t["bounce light pass"] = clock() - t0
    t0 = clock()
    r2 = s.solve(q=q2, warm_start=r1)
    t["finest pass 2"] = clock() - t0
    t0 = clock()
    s.vertex_radiance(r2, vd)
    t["vertex radiance"] = clock() - t0
    rec["parts_ms"] = {k: 1e3 * v for k, v in t.items()}
    rec["parts_sweeps"] = {"finest pass 1": int(fin1.iterations), "finest pass 2": int(r2.level_solves[-1].iterations)}
    # The frame as the add-on runs it (solve_interreflected), fresh solver again.
    s = mk()
    t0, w0 = time.process_time(), time.perf_counter()
    r, _ = s.solve_interreflected((), sc.environment)
    s.vertex_radiance(r, vd)
    rec["first_ms"], rec["first_wall_ms"] = 1e3 * (time.process_time() - t0), 1e3 * (time.perf_counter() - w0)
    rec["first_sweeps"] = [int(ls.iterations) for ls in r.level_solves]
    warm, wall, its = [], [], []
    for deg in (5.0, 0.0):
        env = environment_turned(sc, deg)  # the scene's sky turned: not part of the frame's cost
        t0, w0 = time.process_time(), time.perf_counter()
        r, _ = s.solve_interreflected((), env, warm_start=r)
        L = s.vertex_radiance(r, vd)
        warm.append(time.process_time() - t0)
        wall.append(time.perf_counter() - w0)
        its.append(int(r.level_solves[-1].iterations))
    rec["warm_ms"], rec["warm_wall_ms"] = 1e3 * float(np.mean(warm)), 1e3 * float(np.mean(wall))
    rec["warm_sweeps"] = its
    rec["block"] = getattr(r, "first_pass", None) is not None
    np.save(out + ".npy", L)
    Path(out).write_text(json.dumps(rec))


PROFILE_PARTS = (  # (row, how to read it from the profile); cumulative times overlap: see profile_section
    ("light pass (shadow rays, sky)", ("ct", "solver.py", "incident")),
    ("coarse levels (their set-up and sweeps)", ("ct", "solver.py", "_systems_steps")),
    ("spectral bounds: Lanczos for lambda_min, every level", ("ct", "spectral.py", "lanczos_lower")),
    ("deflation check (its own Lanczos)", ("defl",)),
    ("sweep layout (RCM order, fused CSR), every level", ("ct", None, "sweep_operator")),
    ("sweeps: sparse products (scipy csr_matvec)", ("tt", None, "csr_matvec")),
    ("sweeps: vector updates (the Chebyshev iteration's own time)", ("tt", "iterative.py", "chebyshev_steps")),
    ("vertex radiance", ("ct", "solver.py", "vertex_radiance")),
)


def profile_worker(root: str, quality: str, out: str) -> None:
    """cProfile (CPU time) of a first and a warm frame as :func:`worker` runs them; the parts of PROFILE_PARTS."""
    import cProfile
    import pstats

    sys.path.insert(0, root)
    from bench import accuracy_scenes as scenes
    from bench.accuracy_core import Evaluator, environment_turned, view_dirs
    from translucency_addon.diffusion import solver as diffusion

    sc = next(s for s in scenes.reference_scenes() if s.name == "bunny_marble_sky")
    bk, _ = Evaluator(bake_cache=BAKES, log=lambda *a: None).bake(sc, quality=quality)
    s = diffusion.DiffusionSolver(bk, sc.material, None, diffusion.SolveOptions(solver="fast", tol=1e-4))
    vd = view_dirs(sc)
    rec = {}
    r = None
    for name, env in (("first", sc.environment), ("warm", environment_turned(sc, 5.0))):
        pr = cProfile.Profile(time.process_time)
        pr.enable()
        r, _ = s.solve_interreflected((), env, warm_start=r)
        s.vertex_radiance(r, vd)
        pr.disable()
        st = pstats.Stats(pr).stats
        parts = {"frame": 1e3 * max(v[3] for v in st.values())}

        def pick(kind, fname, func):
            tot = 0.0
            for (f, _, fn), (_, _, tt, ct, _callers) in st.items():
                if (fn == func or fn.endswith(f".{func}>")) and (fname is None or f.endswith(fname)):
                    tot += tt if kind == "tt" else ct
            return 1e3 * tot

        for row, how in PROFILE_PARTS:
            if how[0] == "defl":
                d = [(k, v) for k, v in st.items() if k[0].endswith("spectral.py") and k[2] == "deflation"]
                sb = [v for k, v in st.items() if k[0].endswith("spectral.py") and k[2] == "spectral_bounds"]
                inner = sum(c[3] for v in sb for ck, c in v[4].items() if ck[2] == "deflation")
                parts[row] = 1e3 * (sum(v[3] for _, v in d) - inner)
            else:
                parts[row] = pick(*how)
        parts["finest-level sweeps"] = int(r.level_solves[-1].iterations)
        rec[name] = parts
    Path(out).write_text(json.dumps(rec))


def profile_section(baseline: Path | None, quality: str) -> str:
    """The breakdown of a first and a warm frame (cProfile), both trees, one after the other."""
    recs = {}
    for tag, root in (("base", baseline), ("ours", ROOT)):
        if root is None:
            continue
        out = ROOT / "bench" / "out" / f"profile_{tag}_{quality}.json"
        cmd = [sys.executable, str(Path(__file__).resolve()), "--profile-worker", str(root), quality, str(out)]
        subprocess.run(cmd, check=True, cwd=str(root))
        recs[tag] = json.loads(out.read_text())
    base = recs.get("base")
    lines = [f"## Where a {quality} frame's time goes (cProfile)", "",
             f"`bench/frame.py --profile {quality}`: one process per tree (*baseline* = `{baseline}`), a first "
             "frame on a fresh solver (every set-up included) and a warm one (the sky turned 5 degrees, "
             "warm-started), each under cProfile with CPU time as its clock (the profiler itself adds ~10 %).  "
             "Rows are a function's time *including what it calls*, so they overlap: the coarse levels include "
             "their own Lanczos, layout and sweeps; the sweep rows are the products and the iteration's own "
             "vector work over all levels.", "",
             "| part | first: baseline ms | first: ours ms | warm: baseline ms | warm: ours ms |",
             "|---|---|---|---|---|"]
    rows = ["frame"] + [r for r, _ in PROFILE_PARTS] + ["finest-level sweeps"]
    for row in rows:
        cells = []
        for kind in ("first", "warm"):
            for rec in (base, recs["ours"]):
                v = None if rec is None else rec[kind].get(row)
                cells.append("-" if v is None else (f"{v:,}" if isinstance(v, int) else f"{v:,.0f}"))
        label = "**whole frame**" if row == "frame" else row
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def run_tree(root: Path, quality: str, tag: str) -> dict:
    out = ROOT / "bench" / "out" / f"frame_{tag}_{quality}.json"
    cmd = [sys.executable, str(Path(__file__).resolve()), "--worker", str(root), quality, str(out)]
    subprocess.run(cmd, check=True, cwd=str(root))
    rec = json.loads(out.read_text())
    rec["L"] = np.load(str(out) + ".npy")
    return rec


def commit_of(root: Path) -> str:
    """The short commit of a checkout (for the table's text)."""
    out = subprocess.run(["git", "-C", str(root), "rev-parse", "--short", "HEAD"], capture_output=True, text=True)
    return out.stdout.strip() or "?"


def frame_section(baseline: Path | None, qualities) -> tuple[str, list]:
    rows = []
    for q in qualities:
        best = {}
        for _ in range(2):  # alternate the trees, keep the best of each (the machine is shared)
            for tag, root in (("base", baseline), ("ours", ROOT)):
                if root is None:
                    continue
                rec = run_tree(root, q, tag)
                print(f"  {q} {tag}: first {rec['first_ms']:.0f} ms, warm {rec['warm_ms']:.0f} ms "
                      f"{rec['warm_sweeps']}", flush=True)
                old = best.get(tag)
                if old is None:
                    best[tag] = rec
                else:
                    for k in ("first_ms", "warm_ms", "first_wall_ms", "warm_wall_ms"):
                        old[k] = min(old[k], rec[k])
                    for k, v in rec["parts_ms"].items():
                        old["parts_ms"][k] = min(old["parts_ms"][k], v)
        rows.append((q, best))
    lines = ["## A frame with Self-Occlusion (bunny_marble_sky, tol 1e-4)", "",
             f"Both trees in this run, alternating, best of two: *baseline* = `{baseline}` "
             f"({commit_of(baseline) if baseline else '-'}), *ours* = this tree "
             f"({commit_of(ROOT)}).  Command: `nice .venv/bin/python bench/frame.py --baseline OTHER_CHECKOUT`.", "",
             "Times are wall ms (`time.perf_counter`; the compiled CG step of `diffusion/compiled_cg.py` runs on "
             "both cores, so CPU time would count it twice); the CPU ms of the process (`time.process_time`) of "
             "the same runs are in brackets.  *Finest steps*: the finest level's block sweeps (Chebyshev on the "
             "block system) or CG steps over both blocks (`interreflection._block_by_block`), per warm frame.", "",
             "| preset | finest nodes | first frame ms: baseline / ours | ratio | warm frame ms: baseline / ours | "
             "ratio | finest steps per warm frame: baseline / ours | radiance: max rel. difference |",
             "|---|---|---|---|---|---|---|---|"]
    for q, b in rows:
        base, ours = b.get("base"), b["ours"]
        if base is None:
            lines.append(f"| {q} | {ours['nodes']:,} | - / {ours['first_ms']:,.0f} | - | - / {ours['warm_ms']:,.0f} | - | "
                         f"- / {ours['warm_sweeps']} | - |")
            continue
        diff = float(np.abs(base["L"] - ours["L"]).max() / np.abs(base["L"]).max())
        lines.append(f"| {q} | {ours['nodes']:,} | {base['first_wall_ms']:,.0f} / {ours['first_wall_ms']:,.0f} "
                     f"({base['first_ms']:,.0f} / {ours['first_ms']:,.0f}) | "
                     f"{base['first_wall_ms'] / ours['first_wall_ms']:.2f}x | {base['warm_wall_ms']:,.0f} / "
                     f"{ours['warm_wall_ms']:,.0f} ({base['warm_ms']:,.0f} / {ours['warm_ms']:,.0f}) | "
                     f"{base['warm_wall_ms'] / ours['warm_wall_ms']:.2f}x | {base['warm_sweeps']} / "
                     f"{ours['warm_sweeps']} | {diff:.1e} |")
    lines += ["", "Where the first frame's time goes (the two passes run one after the other by both trees' code; "
              "*finest pass* = the finest level's solve; wall ms; *steps*: ours, sweeps or CG steps):", "",
              "| preset | part | baseline ms | ours ms | steps |", "|---|---|---|---|---|"]
    for q, b in rows:
        base, ours = b.get("base"), b["ours"]
        for k, v in ours["parts_ms"].items():
            bv = f"{base['parts_ms'][k]:,.0f}" if base else "-"
            sw = ours["parts_sweeps"].get(k, "")
            lines.append(f"| {q} | {k} | {bv} | {v:,.0f} | {sw} |")
    return "\n".join(lines), rows


# ---------------------------------------------------------------- scaling: a voxel ball
class VoxelBall:
    """A graph of the contract (graph.py): voxels inside a ball, one surface node per outer face."""

    def __init__(self, n_target: int, radius: float = 20.0):
        h = (4.0 / 3.0 * np.pi * radius**3 / n_target) ** (1.0 / 3.0)
        m = int(np.ceil(radius / h)) + 1
        ax = (np.arange(-m, m) + 0.5) * h
        X, Y, Z = np.meshgrid(ax, ax, ax, indexing="ij")
        inside = X**2 + Y**2 + Z**2 <= radius**2
        idx = -np.ones(inside.shape, dtype=np.int64)
        ijk = np.argwhere(inside)
        ijk = ijk[np.lexsort((ijk[:, 2], ijk[:, 1], ijk[:, 0]))]
        ni = len(ijk)
        idx[tuple(ijk.T)] = np.arange(ni)
        nbr = -np.ones((ni, 6), dtype=np.int64)
        surf_owner, surf_dir = [], []
        dirs = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]])
        for k, dv in enumerate(dirs):
            j = ijk + dv
            ok = np.all((j >= 0) & (j < inside.shape[0]), axis=1)
            nb = np.full(ni, -1)
            nb[ok] = idx[tuple(j[ok].T)]
            nbr[:, k] = nb
            out = np.nonzero(nb < 0)[0]
            surf_owner.append(out)
            surf_dir.append(np.full(len(out), k))
        owner = np.concatenate(surf_owner)
        sdir = np.concatenate(surf_dir)
        ns = len(owner)
        sid = ni + np.arange(ns)
        nbr[owner, sdir] = sid
        P = np.stack([ax[ijk[:, 0]], ax[ijk[:, 1]], ax[ijk[:, 2]]], axis=1)
        self.n_inner, self.n_surface = ni, ns
        full = -np.ones((ni + ns, 6), dtype=np.int64)
        full[:ni] = nbr
        full[ni:, 0] = owner
        self.neighbors = full
        el = np.where(full >= 0, h, 0.0)
        el[:ni][nbr >= ni] = 0.5 * h
        el[ni:, 0] = 0.5 * h
        self.edge_length = el
        self.face_area = np.where(full >= 0, h * h, 0.0)
        self.volume = np.full(ni, h**3)
        self.normal = dirs[sdir].astype(np.float64)
        self.area = np.full(ns, h * h)
        self.position = np.vstack([P, P[owner] + 0.5 * h * self.normal])
        self.h = h

    @property
    def n_nodes(self) -> int:
        return self.n_inner + self.n_surface

    @property
    def surface_position(self):
        return self.position[self.n_inner:]


def scaling_section(sizes, tol: float) -> str:
    sys.path.insert(0, str(ROOT))
    from translucency_addon.diffusion import kernels
    from translucency_addon.diffusion.assembly import assemble, node_coefficients
    from translucency_addon.diffusion.iterative import solve_chebyshev
    from translucency_addon.scene.materials import material_from_preset
    from translucency_addon.diffusion.spectral import deflation, spectral_bounds

    mat = material_from_preset("marble")
    lines = ["## How cost grows (voxel ball, 40 mm, marble, tol %g)" % tol, "",
             "A graph of the contract built in the bench (`VoxelBall`: cubic cells, one surface node per outer face; "
             "6 links per cell where the bunny's tetrahedra have 4), lit uniformly (q = 1 W/m^2 on every surface "
             "node), solved on one level from zero (the solves run the fp32 sweeps: tol >= `sweeps.FP32_TOL`; the ms/sweep columns compare the two fp64 layouts).  *node-major* = the loop the sweeps replace "
             "(`kernels.chebyshev_update` on `LevelSystem.apply`), timed in the same process.  *warm frame* = "
             "warm-started from the solution, the light changed by 5 % over the ball (a smooth gradient).  "
             "*memory* = the level's arrays plus the sweep layout and the four work vectors.  CPU ms of the process "
             "(`time.process_time`).", "",
             "| nodes | h mm | sweeps from zero | ms/sweep (ours, fp64) | ms/sweep (node-major, fp64) | ratio | solve from zero ms | "
             "warm frame: sweeps | warm frame ms | setup ms (bounds + layout) | memory MB |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for n in sizes:
        g = VoxelBall(int(n))
        sa, ss = node_coefficients(mat, None, g.n_nodes)
        system = assemble(g, sa, ss, mat.eta, 1.0, "fv")
        clock = time.process_time
        t0 = clock()
        spectral_bounds(system), deflation(system)
        op = system.sweep_operator()
        setup = clock() - t0
        q = np.ones((g.n_surface, 3))
        b = system.rhs(q)
        t0 = clock()
        x, info = solve_chebyshev(system, b, np.zeros_like(b), tol, 100_000, 8)
        solve_s = clock() - t0
        q2 = q * (1.0 + 0.05 * g.normal[:, :1])
        b2 = system.rhs(q2)
        t0 = clock()
        _, winfo = solve_chebyshev(system, b2, x, tol, 100_000, 8)
        warm_s = clock() - t0
        # ms per sweep, both layouts, same process
        X, R, D = op.to_cm(x), op.to_cm(b), op.to_cm(b)
        T = np.empty_like(R)
        k = 10

        def ours():
            op.sub_a(R, D)  # noqa: F821 - called in this iteration, before the del at its end
            X.__iadd__(D)
            np.multiply(R, op.inv_diag, out=T)  # noqa: F821 - called in this iteration, before the del at its end
            T.__imul__(0.3)
            D.__imul__(0.5)
            D.__iadd__(T)

        xx, rr, dd = x.copy(), b.copy(), b.copy()
        system.off_csr()  # apply() then takes the per-channel CSR products, not the sweeps' layout

        def node_major():
            nonlocal xx, rr, dd
            xx, rr, dd = kernels.chebyshev_update(xx, rr, dd, system.apply(dd), system.diag, 0.5, 0.3)  # noqa: F821 - called in this iteration, before the del at its end

        times = {}
        for name, f in (("ours", ours), ("node", node_major)) * 3:
            f()
            t0 = clock()
            for _ in range(k):
                f()
            dt = (clock() - t0) / k
            times[name] = min(times.get(name, np.inf), dt)
        mem = (system.off.nbytes + system.diag.nbytes + system.nbr.nbytes + system.b_scale.nbytes
               + sum(c.data.nbytes + c.indices.nbytes + c.indptr.nbytes for c in system.off_csr())
               + op.nbytes + 4 * X.nbytes)
        row = (f"| {g.n_nodes:,} | {g.h:.3f} | {info.iterations} | {1e3 * times['ours']:.2f} | "
               f"{1e3 * times['node']:.2f} | {times['node'] / times['ours']:.2f}x | {1e3 * solve_s:,.0f} | "
               f"{winfo.iterations} | {1e3 * warm_s:,.0f} | {1e3 * setup:,.0f} | {mem / 2**20:,.0f} |")
        print(row, flush=True)
        lines.append(row)
        del system, op, g
    return "\n".join(lines)


def main(argv=None):
    if argv is None and len(sys.argv) > 1 and sys.argv[1] == "--worker":
        worker(*sys.argv[2:5])
        return
    if argv is None and len(sys.argv) > 1 and sys.argv[1] == "--profile-worker":
        profile_worker(*sys.argv[2:5])
        return
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--baseline", type=Path, default=None, help="a checkout of the code to compare with")
    ap.add_argument("--qualities", nargs="*", default=["preview", "final"])
    ap.add_argument("--sizes", nargs="*", type=float, default=[1e4, 3e4, 1e5, 3e5, 1e6])
    ap.add_argument("--tol", type=float, default=1e-4)
    ap.add_argument("--profile", nargs="*", default=[], help="qualities to profile (cProfile breakdown)")
    ap.add_argument("--out", default=None, help="append the sections to this markdown file "
                                                 "(replacing an earlier run's sections)")
    a = ap.parse_args(argv)
    new = {}  # section header -> text, in the file's order: frame, profiles, scaling
    if a.qualities:
        text, _ = frame_section(a.baseline, a.qualities)
        print(text)
        new["## A frame with Self-Occlusion"] = text
    for q in a.profile:
        text = profile_section(a.baseline, q)
        print(text)
        new[f"## Where a {q} frame's time goes"] = text
    if a.sizes:
        text = scaling_section(a.sizes, a.tol)
        print(text)
        new["## How cost grows"] = text
    if a.out:  # replace this run's sections, keep the others of an earlier run
        p = Path(a.out)
        old = p.read_text() if p.exists() else ""
        heads = ("## A frame with Self-Occlusion", "## Where a ", "## How cost grows")
        chunks = ("\n" + old).split("\n## ")
        head = chunks[0].strip("\n")
        kept = {}
        for c in chunks[1:]:
            c = "## " + c.rstrip("\n")
            if c.startswith(heads):
                key = c.split(" (")[0] if c.startswith("## Where a ") else next(h for h in heads if c.startswith(h))
                kept[key] = c
            else:
                head += "\n\n" + c
        for k, v in new.items():
            kept[k.split(" (")[0]] = v
        order = lambda k: [i for i, h in enumerate(heads) if k.startswith(h)][0]  # noqa: E731
        p.write_text(head + "\n\n" + "\n\n".join(kept[k] for k in sorted(kept, key=order)) + "\n")

if __name__ == "__main__":
    main()
