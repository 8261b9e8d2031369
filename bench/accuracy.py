# SPDX-License-Identifier: GPL-3.0-or-later
"""What accuracy costs in time (issue 8): our engine against an independent path tracer.

    .venv/bin/python -m bench.accuracy [--quick] [--refresh-references] [--sections ...]
                                       [--out docs/accuracy.md] [--no-costs]

Matched scenes (``bench/accuracy_scenes.py``): the Stanford bunny (closed, 40 mm)
and a 12 mm sphere, in marble, skim milk, skin1 and a heterogeneous marble
(marble veined with skin1 by the engine's procedural field; the reference
gets the same field as a 128^3 grid volume), under a directional order-2 SH
sky (the engine represents it exactly; a path tracer cannot light a medium
behind a smooth dielectric with a sun), orthographic camera, 32 x 32 pixels.
The references are Mitsuba 3 renders (``bench/reference``, translucency only,
per-channel grey renders, Russian roulette off) cached in ``bench/data`` and
committed; ``--refresh-references`` renders them again (~1.5 h on 2 cores).

Our side: the engine API as the add-on calls it -- ``bake_mesh``,
``DiffusionSolver`` (or ``gpu_shaders.make_solver``), ``vertex_radiance``
with per-vertex view directions toward the camera (+ single scattering's
``render_vertices`` where switched on) -- rasterised from the reference's
camera (``bench/reference/raster.py``).  ``--sections user`` also runs the
Blender operators (bake, solve, the ``translucency_radiance`` attribute) on
one scene and checks they give the same image.

Errors: relative RMS over the object's pixels (``bench/reference/metrics.py``):

* **(a) discretisation + iteration**: against our own converged solve of the
  finest (Final) graph;
* **(b) against the path tracer** (model + discretisation + iteration),
  with the reference's own noise floor; ``(b) debiased`` is
  ``sqrt(max(b^2 - floor^2, 0))``, the expected error against a noise-free
  reference (the reference noise is independent of our error).

Writes ``docs/accuracy.md``, ``docs/images/accuracy_*.png``,
``bench/data/accuracy_results.json`` and the preset cost file
``translucency_addon/data/quality_costs.json`` (read by the panel).
``--quick`` (CI smoke, ~1-2 min): 12 x 12 references at 64 spp, draft
quality only, a few knobs; writes to ``bench/out/accuracy_quick.md``.
Times are wall-clock on the machine that runs it (here: 2 shared CPU cores,
no GPU; the "GPU" path is Mesa llvmpipe, i.e. also the CPU): compare ratios.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402

from bench import accuracy_scenes as scenes  # noqa: E402
from bench.accuracy_core import ALL_TERMS, SUPERSAMPLE, Evaluator, Render, solve  # noqa: E402
from bench.reference.metrics import relative_rms  # noqa: E402

DOCS = ROOT / "docs"
IMAGES = DOCS / "images"
COSTS_JSON = ROOT / "translucency_addon" / "data" / "quality_costs.json"
RESULTS_JSON = ROOT / "bench" / "data" / "accuracy_results.json"
SECTIONS = ("presets", "K", "levels", "tol", "solver", "precision", "ss", "model", "user")
HEADLINE = "bunny_marble_sky"
TARGETS = {"preview": 0.05, "final": 0.02}
USER_TOL = 1e-4  # the add-on's default tolerance (scene.translucency.tolerance)
CONVERGED = dict(solver="fast", tol=1e-6, single_scattering=ALL_TERMS)  # continuation of the Final solve


class Bench:
    def __init__(self, quick=False, refresh=False, log=print, bake_cache=None):
        self.quick = quick
        self.refresh = refresh
        self.log = log
        self.ev = Evaluator(log=log) if bake_cache is None else Evaluator(bake_cache, log=log)
        self.refs = {}
        self.scenes = {}
        self.records = []
        self.converged_images = {}
        self.notes = []

    # -- references --------------------------------------------------------------------
    def load_references(self):
        for sc in scenes.reference_scenes(self.quick):
            if getattr(self, "only", None) and sc.name not in self.only:
                continue
            t0 = time.perf_counter()
            ref = scenes.get_reference(sc, self.quick, self.refresh)
            dt = time.perf_counter() - t0
            self.scenes[sc.name] = sc
            self.refs[sc.name] = ref
            fl = relative_rms(ref.image, ref.image, ref.mask, stderr=ref.stderr).noise_floor
            self.log(f"reference {sc.name}: {ref.spp} spp/channel, rendered in {ref.seconds:.0f} s"
                     f"{' (cached)' if dt < 0.5 * ref.seconds else ''}, noise floor {fl:.4f}")

    # -- errors ------------------------------------------------------------------------
    def errors(self, name, image, mask):
        ref = self.refs[name]
        b = relative_rms(image, ref.image, mask, ref.mask, stderr=ref.stderr)
        out = {"err_ref": b.rel_rms, "err_ref_rgb": list(b.rel_rms_rgb), "noise_floor": b.noise_floor,
               "err_ref_debiased": float(np.sqrt(max(b.rel_rms**2 - b.noise_floor**2, 0.0))), "pixels": b.pixels}
        from bench.reference.metrics import comparison_mask

        P = comparison_mask(mask, ref.mask)
        out["bias"] = float(image[P].mean() / ref.image[P].mean() - 1.0)
        conv = self.converged_images.get(name)
        if conv is not None:
            a = relative_rms(image, conv[0], mask, conv[1] & ref.mask)
            out["err_conv"] = a.rel_rms
        return out

    def record(self, knob, label, name, r, **extra):
        rec = {"knob": knob, "label": label, "scene": name, "bake_s": r.bake_s, "first_ms": r.first_ms,
               "frame_ms": r.frame_ms, "iterations": r.iterations, "frame_iterations": r.frame_iterations,
               "level_iterations": r.extra.get("level_iterations"), "residual": r.residual,
               "diverged": bool(r.diverged), "nodes": list(r.nodes)}
        if not r.diverged:
            rec.update(self.errors(name, r.image, r.mask))
        for k in ("ss_bake_s", "ss_frame_ms", "ss_mfp_voxels", "ss_samples"):
            if k in r.extra:
                rec[k] = r.extra[k]
        rec.update(extra)
        self.records.append(rec)
        e = rec.get("err_ref", float("nan"))
        c = rec.get("err_conv", float("nan"))
        self.log(f"  {knob:9s} {label:28s} {name:24s} bake {r.bake_s:6.1f} s  first {r.first_ms:8.0f} ms  "
                 f"frame {r.frame_ms:8.0f} ms  err(ref) {e:.4f}  err(conv) {c:.4f}"
                 + ("  DIVERGED" if r.diverged else ""))
        return rec

    # -- converged solution --------------------------------------------------------------
    def converged(self, name, final: "Render"):
        """The scene's converged image: the Final preset's solve continued (the default solver, finest
        level, warm-started) to a relative residual of CONVERGED["tol"].  A direct LU of the Final
        graph (several hundred thousand nodes) does not fit this machine's time budget; on the
        Preview graph the direct solve and this continuation agree (the tol section)."""
        from bench.accuracy_core import view_dirs
        from bench.reference.raster import rasterize
        from translucency_addon.diffusion.solver import SolveOptions

        sc = self.scenes[name]
        solver, res = final.extra.pop("solver"), final.extra.pop("result")
        t0 = time.perf_counter()
        solver.options = SolveOptions(**CONVERGED, max_iterations=50_000)
        res = solve(solver, environment=sc.environment, warm_start=res)[0]
        L = solver.vertex_radiance(res, view_dirs(sc))
        ras = rasterize(sc.V, sc.F, L, sc.camera, sc.resolution, supersample=SUPERSAMPLE)
        self.converged_images[name] = (ras.image, ras.mask)
        rec = {"knob": "converged", "label": f"Final graph, tol {CONVERGED['tol']:g}", "scene": name,
               "residual": float(np.max(res.residual)), "seconds": time.perf_counter() - t0,
               "iterations": int(res.level_solves[-1].iterations), "nodes": list(final.nodes)}
        rec.update(self.errors(name, ras.image, ras.mask))
        rec["err_conv"] = 0.0
        self.records.append(rec)
        self.log(f"  converged {name:24s} residual {rec['residual']:.1e} in {rec['seconds']:.0f} s: "
                 f"model error (b) {rec['err_ref']:.4f} (debiased {rec['err_ref_debiased']:.4f}, floor "
                 f"{rec['noise_floor']:.4f})")
        if hasattr(solver, "free"):
            solver.free()

    # -- sections ----------------------------------------------------------------------
    def presets(self):
        qualities = ("draft",) if self.quick else ("draft", "preview", "final")
        final = qualities[-1]
        self.images = {}
        for name in self.scenes:
            frames = self.quick or name in (HEADLINE, "sphere_marble_sky")
            runs = {}
            for q in reversed(qualities):  # Final first: its solve, continued, is the converged image
                runs[q] = self.ev.run(self.scenes[name], dict(quality=q), dict(solver="fast", tol=USER_TOL),
                                      frames=frames, keep=(q == final))
                if q == final:
                    self.converged(name, runs[q])
            for q in qualities:
                self.record("preset", q, name, runs[q])
                self.images[(name, q)] = (runs[q].image, runs[q].mask)

    def sweep_K(self):
        names = [n for n in (HEADLINE, "sphere_marble_sky") if n in self.scenes]
        values = (1.0,) if self.quick else (0.5, 1.0, 2.0, 4.0)
        base = "draft" if self.quick else "preview"
        for name in names:
            for K in values:
                r = self.ev.run(self.scenes[name], dict(quality=base, K=K), dict(solver="fast", tol=USER_TOL))
                self.record("K", f"K={K:g}", name, r, K=K)
        if not self.quick and HEADLINE in self.scenes:  # the Final surface with Preview's K
            from translucency_addon.quadgraph.bake import QUALITY_PRESETS

            K = QUALITY_PRESETS["preview"]["K"]
            r = self.ev.run(self.scenes[HEADLINE], dict(quality="final", K=K), dict(solver="fast", tol=USER_TOL))
            self.record("K_final", f"Final surface, K={K:g}", HEADLINE, r, K=K)

    def sweep_levels(self):
        name = HEADLINE if HEADLINE in self.scenes else next(iter(self.scenes))
        base = "draft" if self.quick else "preview"
        sc = self.scenes[name]
        r = self.ev.run(sc, dict(quality=base), dict(solver="fast", tol=USER_TOL, levels="finest"), frames=False)
        self.record("levels", "finest level only", name, r, levels=1)
        for L in ((3,) if self.quick else (2, 3, 4)):
            r = self.ev.run(sc, dict(quality=base, levels=L, refinements=1), dict(solver="fast", tol=USER_TOL),
                            frames=False)
            self.record("levels", f"{L} levels", name, r, levels=L)

    def sweep_tol(self):
        name = HEADLINE if HEADLINE in self.scenes else next(iter(self.scenes))
        base = "draft" if self.quick else "preview"
        sc = self.scenes[name]
        tols = (1e-2, 1e-4) if self.quick else (1e-1, 3e-2, 1e-2, 3e-3, 1e-3, 1e-4, 1e-5, 1e-6)
        direct = self.ev.run(sc, dict(quality=base), dict(solver="direct"), frames=False)
        self.record("tol", "direct (same graph)", name, direct, tol=0.0)
        for tol in tols:
            r = self.ev.run(sc, dict(quality=base), dict(solver="fast", tol=tol), frames=False)
            rec = self.record("tol", f"tol={tol:g}", name, r, tol=tol)
            rec["err_iter"] = relative_rms(r.image, direct.image, r.mask, direct.mask).rel_rms
        # fixed iteration counts (tol 0): the paper's "iterations per frame" knob
        for n in ((8,) if self.quick else (8, 16, 32, 64, 128)):
            r = self.ev.run(sc, dict(quality=base), dict(solver="fast", tol=0.0, max_iterations=n), frames=False)
            rec = self.record("iterations", f"{n} steps/level", name, r, steps=n)
            rec["err_iter"] = relative_rms(r.image, direct.image, r.mask, direct.mask).rel_rms

    def sweep_solver(self):
        base = "draft" if self.quick else "preview"
        names = [n for n in (HEADLINE, "bunny_hetero_sky") if n in self.scenes] or [next(iter(self.scenes))]
        cap = 2_000 if self.quick else 20_000
        for name in names:
            sc = self.scenes[name]
            direct = self.ev.run(sc, dict(quality=base), dict(solver="direct"), frames=False)
            self.record("solver", "direct LU (ours)", name, direct)
            for solver, label in (("fast", "ours: CG / Chebyshev"), ("jacobi", "Jacobi (our scheme)"),
                                  ("paper", "Jacobi (paper eq. 5-9)")):
                r = self.ev.run(sc, dict(quality=base), dict(solver=solver, tol=USER_TOL, max_iterations=cap),
                                frames=False)
                rec = self.record("solver", label, name, r, solver=solver)
                if not r.diverged:
                    rec["err_iter"] = relative_rms(r.image, direct.image, r.mask, direct.mask).rel_rms
        self.kappa_jump(base, cap)

    def kappa_jump(self, base, cap):
        """Convergence only (no reference): marble veined with ketchup, a ~100x jump in kappa
        (ketchup's blue sigma_s' is 0.03/mm against marble's 3.0/mm)."""
        from dataclasses import replace

        from translucency_addon.scene.materials import material_from_preset

        name = HEADLINE if HEADLINE in self.scenes else next(iter(self.scenes))
        sc0 = self.scenes[name]
        sc = replace(sc0, material=material_from_preset("marble", mix_with="ketchup"),
                     field=scenes.field_for("hetero", sc0.mm_per_unit, sc0.V), name=sc0.name + "_ketchup")
        self.kappa_rows = []
        for solver in ("fast", "paper"):
            bk, _ = self.ev.bake(sc, quality=base)
            from translucency_addon.diffusion.solver import SolveOptions

            s = self.ev.make_solver(bk, sc, SolveOptions(solver=solver, tol=USER_TOL, max_iterations=cap), "cpu")
            t0 = time.perf_counter()
            res = s.solve(environment=sc.environment)  # convergence only: one plain solve
            ls = res.level_solves[-1]
            row = {"solver": solver, "iterations": [int(x.iterations) for x in res.level_solves],
                   "residual": float(np.max(ls.residual)), "diverged": any(x.diverged for x in res.level_solves),
                   "seconds": time.perf_counter() - t0,
                   "history": [float(h) for h in ls.history]}
            # the plot: the finest level alone from zero (the multi-level run starts it from the
            # coarse levels' result, which for the paper's scheme has already diverged)
            s1 = self.ev.make_solver(bk, sc, SolveOptions(solver=solver, tol=USER_TOL, max_iterations=cap,
                                                          levels="finest"), "cpu")
            r1 = s1.solve(environment=sc.environment)
            row["history_finest"] = [float(h) for h in r1.level_solves[-1].history]
            self.kappa_rows.append(row)
            self.log(f"  kappa-jump {solver}: iterations {row['iterations']} residual {row['residual']:.2e} "
                     f"diverged {row['diverged']}")

    def sweep_precision(self):
        name = HEADLINE if HEADLINE in self.scenes else next(iter(self.scenes))
        base = "draft" if self.quick else "preview"
        sc = self.scenes[name]
        try:
            from bench.gpu_solve import init_gpu

            renderer = init_gpu()
        except Exception as ex:  # noqa: BLE001 - no Blender or no GPU: the section is skipped, with the reason
            self.notes.append(f"GPU section skipped: {type(ex).__name__}: {ex}")
            self.log(self.notes[-1])
            return
        self.gpu_renderer = renderer
        cpu = self.ev.run(sc, dict(quality=base), dict(solver="fast", tol=USER_TOL))
        self.record("precision", "CPU fp64", name, cpu, backend="cpu")
        for backend, label in (("gpu32", f"GPU fp32 ({renderer.split('(')[0].strip()})"),
                               ("gpu16", f"GPU fp16 ({renderer.split('(')[0].strip()})")):
            try:
                r = self.ev.run(sc, dict(quality=base), dict(solver="fast", tol=USER_TOL), backend=backend)
            except Exception as ex:  # noqa: BLE001 - a failed GPU run is a noted row, not a crashed bench
                self.notes.append(f"{label} failed: {type(ex).__name__}: {ex}")
                self.log(self.notes[-1])
                continue
            rec = self.record("precision", label, name, r, backend=backend)
            rec["err_vs_cpu"] = relative_rms(r.image, cpu.image, r.mask, cpu.mask).rel_rms

    def sweep_ss(self):
        base = "draft" if self.quick else "preview"
        names = [n for n in (HEADLINE, "sphere_skin1_sky", "sphere_marble_sky") if n in self.scenes]
        if self.quick:
            names = names[:1]
        default = dict(quality="draft", n_dirs=32, n_samples=2000, sh_order=2) if self.quick else {}
        variants = [("SS default", default)]
        if not self.quick:
            variants += [("SS 32 directions", dict(n_dirs=32)), ("SS 5k samples", dict(n_samples=5000)),
                         ("SS SH order 2", dict(sh_order=2)), ("SS final voxels", dict(quality="final"))]
        alone = dict(solver="fast", tol=USER_TOL, single_scattering=False)
        every = dict(solver="fast", tol=USER_TOL, single_scattering=True)
        for name in names:
            sc = self.scenes[name]
            # the two frame costs compared (issue 17: every term <= 1.3x diffusion alone): interleaved, twice,
            # the faster of each kept -- one warm frame on 2 shared cores varies by +-30 % from run to run
            runs = {"diffusion only": [], "every term (split)": []}
            for _ in range(1 if self.quick else 2):
                for label, opts in (("diffusion only", alone), ("every term (split)", every)):
                    runs[label].append(self.ev.run(sc, dict(quality=base), opts, frames=True))
            for label, rs in runs.items():
                self.record("ss", label, name, min(rs, key=lambda r: r.frame_ms), ss=None)
            for label, ss in (variants if name == HEADLINE else variants[:1]):
                r = self.ev.run(sc, dict(quality=base), alone, ss=ss, frames=False)
                self.record("ss", label, name, r, ss=ss)

    def model(self):
        """Where the bunny's model error comes from: the environment term without sky visibility
        (every surface point sees the whole sky), with the hidden sky removed only, and with the
        hidden sky plus one interreflection bounce (the add-on's default; sky_visibility.py)."""
        from bench.accuracy_core import SUPERSAMPLE, view_dirs
        from bench.reference.raster import rasterize
        from translucency_addon.diffusion.solver import SolveOptions

        name = HEADLINE if HEADLINE in self.scenes else next(iter(self.scenes))
        sc = self.scenes[name]
        base = "draft" if self.quick else "preview"
        bk, bake_s = self.ev.bake(sc, quality=base)
        every = dict(single_scattering=ALL_TERMS)
        solver = self.ev.make_solver(bk, sc, SolveOptions(solver="fast", tol=USER_TOL, **every), "cpu")
        plain = self.ev.make_solver(bk, sc, SolveOptions(solver="fast", tol=USER_TOL, sky_occlusion=False, **every),
                                    "cpu")
        t0 = time.perf_counter()
        q0 = plain.incident([], sc.environment)
        q = solver.incident([], sc.environment)
        # per-pixel sky visibility (occluded / unoccluded q at the finest surface nodes -> vertices -> pixels)
        idx, w = bk.vertex_map
        vis_node = np.mean(q[-1] / np.maximum(q0[-1], 1e-30), axis=1)
        vis = rasterize(sc.V, sc.F, np.einsum("vk,vk->v", w, vis_node[idx])[:, None], sc.camera,
                        sc.resolution).image[..., 0]
        res0 = solver.solve(q=q)  # the add-on's first pass: hidden sky removed, no bounce yet
        q_ir = solver.incident([], sc.environment, bounce=solver.vertex_radiance(res0))
        t_q = time.perf_counter() - t0
        variants = (("without sky visibility", q0, plain), ("hidden sky removed, no interreflection", q, solver),
                    ("hidden sky + one bounce (the add-on's default)", q_ir, solver))
        conv = self.converged_images.get(name)
        if conv is not None:
            variants += (("converged Final graph (default)", None, None),)
        for label, qq, sv in variants:
            t0 = time.perf_counter()
            if qq is None:
                image, mask = conv
                rec = {"knob": "model", "label": label, "scene": name, "q_ratio": 1.0}
            else:
                res = sv.solve(q=qq)
                L = sv.vertex_radiance(res, view_dirs(sc))
                dt = time.perf_counter() - t0
                ras = rasterize(sc.V, sc.F, L, sc.camera, sc.resolution, supersample=SUPERSAMPLE)
                image, mask = ras.image, ras.mask
                rec = {"knob": "model", "label": label, "scene": name, "bake_s": bake_s, "first_ms": 1e3 * dt,
                       "nodes": [bk.finest.n_surface, bk.finest.n_inner],
                       "q_ratio": float(np.mean(qq[-1] / np.maximum(q0[-1], 1e-30))), "q_seconds": t_q}
            ras = type("R", (), {"image": image, "mask": mask})
            rec.update(self.errors(name, ras.image, ras.mask))
            ref = self.refs[name]
            for key, sel in (("open", vis >= 0.9), ("concave", vis < 0.9)):
                try:
                    from bench.reference.metrics import comparison_mask

                    m = comparison_mask(ras.mask, ref.mask) & sel
                    e = relative_rms(ras.image, ref.image, m, None, stderr=ref.stderr, erode=0)
                    rec[f"err_ref_{key}"], rec[f"pixels_{key}"] = e.rel_rms, e.pixels
                    rec[f"bias_{key}"] = float(ras.image[m].mean() / ref.image[m].mean() - 1.0)
                except ValueError:
                    pass
            self.records.append(rec)
            self.log(f"  model     {label:46s} err(ref) {rec['err_ref']:.4f} open {rec.get('err_ref_open', np.nan):.4f} "
                     f"concave {rec.get('err_ref_concave', np.nan):.4f} mean q / engine q {rec['q_ratio']:.3f}")

    def user_path(self):
        """The Blender operators on one scene (subprocess: a fresh Blender with the add-on)."""
        import subprocess

        name = "sphere_marble_uniform" if "sphere_marble_uniform" in self.scenes else next(iter(self.scenes))
        out = ROOT / "bench" / "out" / "accuracy_user.npz"
        out.parent.mkdir(parents=True, exist_ok=True)
        cmd = [sys.executable, "-m", "bench.accuracy_blender", name, str(out), "--quick" if self.quick else "--full"]
        t0 = time.perf_counter()
        p = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=1800)
        if p.returncode != 0 or not out.exists():
            self.notes.append(f"user path failed: {p.stderr.strip().splitlines()[-1:] if p.stderr else p.returncode}")
            self.log(self.notes[-1])
            return
        with np.load(out, allow_pickle=False) as z:
            img, mask = z["image"], z["mask"]
            meta = json.loads(str(z["meta"]))
        sc = self.scenes[name]
        quality = meta["quality"]
        r = self.ev.run(sc, dict(quality=quality), dict(solver="fast", tol=USER_TOL), frames=False)
        rec = {"knob": "user", "label": f"Blender operators, {quality}", "scene": name,
               "seconds": time.perf_counter() - t0, **meta}
        rec.update(self.errors(name, img, mask))
        api = self.errors(name, r.image, r.mask)
        rec["err_ref_api"] = api["err_ref"]
        rec["err_vs_api"] = relative_rms(img, r.image, mask, r.mask).rel_rms
        bk, _ = self.ev.bake(sc, quality=quality)
        rec["levels_api"] = [[lv.n_surface, lv.n_inner] for lv in bk.levels]
        self.records.append(rec)
        self.log(f"  user path: err(ref) {rec['err_ref']:.4f} (engine API {rec['err_ref_api']:.4f}); "
                 f"operators vs API {rec['err_vs_api']:.2e}")


def engine_state() -> str:
    """The commit the engine came from, and any uncommitted engine files (others work in the same tree)."""
    import subprocess

    try:
        head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True,
                              timeout=10).stdout.strip()
        dirty = subprocess.run(["git", "status", "--short", "--", "translucency_addon", "gpu_shaders"], cwd=ROOT,
                               capture_output=True, text=True, timeout=10).stdout.split("\n")
        dirty = [d[3:] for d in dirty if d.strip() and "translucency_addon/data" not in d]  # our own output
    except Exception:  # noqa: BLE001 - not a git checkout
        return "unknown"
    return f"commit {head}" + (f" with uncommitted changes in {', '.join(dirty)}" if dirty else "")


def run(quick=False, refresh=False, sections=SECTIONS, log=print, bake_cache=None, only=None) -> Bench:
    b = Bench(quick, refresh, log, bake_cache)
    b.only = set(only) if only else None
    b.engine = engine_state()
    log(f"engine: {b.engine}")
    t0 = time.perf_counter()
    b.load_references()
    b.t_refs = time.perf_counter() - t0
    for gone in ([] if b.only else scenes.prune_references(quick)):  # a narrow run (--scenes) prunes nothing
        log(f"removed stale reference {gone}")
    order = [("presets", b.presets), ("K", b.sweep_K), ("levels", b.sweep_levels), ("tol", b.sweep_tol),
             ("solver", b.sweep_solver), ("precision", b.sweep_precision), ("ss", b.sweep_ss),
             ("model", b.model), ("user", b.user_path)]
    b.section_seconds = {}
    for key, fn in order:
        if key in sections or (key == "presets"):
            t = time.perf_counter()
            log(f"[{key}]")
            fn()
            b.section_seconds[key] = time.perf_counter() - t
    b.seconds = time.perf_counter() - t0
    return b


def machine_string() -> str:
    n = os.cpu_count() or 0
    return f"{n}-core CPU, no GPU: CPU times" if n else "CPU times"


def write_costs(b: Bench, path=COSTS_JSON):
    """The preset cost file shipped in the extension (read by ops/quality_costs.py)."""
    rows = {r["label"]: r for r in b.records if r["knob"] == "preset" and r["scene"] == HEADLINE}
    if set(rows) != {"draft", "preview", "final"}:
        return None
    data = {
        "schema": 1,
        "generated_by": "bench/accuracy.py",
        "generated": time.strftime("%Y-%m-%d"),
        "scene": "a 40 mm marble bunny under a sky light",
        "machine": machine_string(),
        "presets": {q: {"bake_s": round(r["bake_s"], 1), "frame_ms": round(r["frame_ms"], 1),
                        "first_frame_ms": round(r["first_ms"], 1), "rel_rms": round(r["err_ref"], 4),
                        "rel_rms_converged": round(r.get("err_conv", float("nan")), 4),
                        "noise_floor": round(r["noise_floor"], 4),
                        "nodes": int(sum(r["nodes"]))} for q, r in rows.items()},
    }
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(data, indent=2) + "\n")
    return data


def update_readme(b, path=ROOT / "README.md"):
    """Replace the body of README.md's "Accuracy versus time" section (only that section)."""
    from bench.accuracy_report import headline_table
    from bench.accuracy_text import findings_headline, replace_section

    text = path.read_text()
    head = "## Accuracy versus time\n"
    if head not in text:
        return False
    body = ["",
            "Measured by `bench/accuracy.py` against an independent path tracer (Mitsuba 3, translucency only) "
            "on matched scenes; the full report, every knob and the plots are in "
            "[docs/accuracy.md](docs/accuracy.md). The marble bunny (40 mm) under a sky light, times on "
            "2 shared CPU cores (no GPU):",
            "", headline_table(b, HEADLINE), ""]
    body += [p + "\n" for p in findings_headline(b, HEADLINE)]
    image = "![accuracy of the presets on every scene against time](docs/images/accuracy_presets.png)"
    body += [image, ""]
    # what other benches wrote after the plot (the progressive frames, the lamps) stays
    start = text.index(head)
    end = text.find("\n## ", start + len(head))
    old = text[start:end if end >= 0 else len(text)]
    after = old[old.index(image) + len(image):].strip("\n") if image in old else ""
    if after:
        body += [after, ""]
    path.write_text(replace_section(text, head, "\n".join(body) + "\n"))
    return True


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="CI smoke: tiny references, draft quality, few knobs")
    ap.add_argument("--refresh-references", action="store_true", help="render the references again")
    ap.add_argument("--sections", nargs="+", default=list(SECTIONS), choices=SECTIONS)
    ap.add_argument("--out", default=None, help="markdown report (default docs/accuracy.md; quick: bench/out)")
    ap.add_argument("--no-costs", action="store_true", help="do not write translucency_addon/data/quality_costs.json")
    ap.add_argument("--bake-cache", default=None, help="directory for cached bakes (default bench/out/accuracy_bakes)")
    ap.add_argument("--scenes", nargs="+", default=None,
                    help="only these scenes (a narrow check of some rows; with --out the images and the results "
                         "JSON go next to the report, and docs/ is left alone)")
    a = ap.parse_args(argv)
    import matplotlib

    matplotlib.use("Agg")
    from bench import accuracy_text as report  # writes the plots and the text

    b = run(a.quick, a.refresh_references, tuple(a.sections), bake_cache=a.bake_cache, only=a.scenes)
    if a.quick:
        out = Path(a.out or ROOT / "bench" / "out" / "accuracy_quick.md")
        img_dir = out.parent / "images"
    else:
        out = Path(a.out or DOCS / "accuracy.md")
        img_dir = IMAGES if a.out is None else out.parent / "images"
    costs = None
    if not a.quick and not a.no_costs:
        costs = write_costs(b)
    results = out.parent / "accuracy_quick_results.json" if a.quick else (
        RESULTS_JSON if a.out is None else out.with_suffix(".json"))
    results.parent.mkdir(parents=True, exist_ok=True)
    results.write_text(json.dumps({"records": b.records, "kappa_jump": getattr(b, "kappa_rows", []),
                                   "seconds": b.seconds, "notes": b.notes}, indent=1, default=float) + "\n")
    report.write(b, out, img_dir, costs)
    if not a.quick and a.out is None and "presets" in a.sections:
        update_readme(b)
    print(f"wrote {out} ({b.seconds:.0f} s)")


if __name__ == "__main__":
    main()
