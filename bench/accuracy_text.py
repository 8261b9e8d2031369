# SPDX-License-Identifier: GPL-3.0-or-later
"""The text of docs/accuracy.md, written by bench/accuracy.py from its measurements."""

from __future__ import annotations

import math
from pathlib import Path

from bench import accuracy_report as report
from bench.accuracy_core import SKY_DIRECTIONS
from bench.accuracy_report import (headline_table, knob_table, ms, one, pct, reference_table, rows, scenes_table,
                                   sec, table, transport_targets_table)


def _iters(r):
    return str(r.get("level_iterations") or r.get("iterations"))


def render(b, link: dict, costs, head: str) -> str:
    q = b.quick
    L = []
    add = L.append
    add("# Accuracy versus time" + (" (quick mode: smoke test only)" if q else ""))
    add("")
    add("Written by `bench/accuracy.py`" + (" --quick" if q else "") + f" in {b.seconds / 60:.1f} min "
        f"({', '.join(f'{k} {v:.0f} s' for k, v in b.section_seconds.items())}; references from the cache "
        f"in {b.t_refs:.0f} s) on the engine at {getattr(b, 'engine', 'unknown')}. Do not edit by hand: run "
        "`.venv/bin/python -m bench.accuracy`.")
    add("")
    add("**Times are wall-clock on 2 shared CPU cores without a GPU** (the \"GPU\" rows ran on Mesa's "
        "llvmpipe, a software rasteriser, i.e. also on the CPU). Compare ratios between rows, not absolute "
        "times with the paper's GPU. Errors are relative RMS over the object's pixels "
        "(`bench/reference/metrics.py`: both masks, eroded by one pixel).")
    add("")
    if q:
        add("Quick mode: 12 x 12 references at 64 spp (noise floors of several per cent), Draft graphs only, "
            "\"converged\" = the Draft graph solved to 1e-6. The numbers say only that the pipeline runs.")
        add("")
    # --- headline
    add("## Headline: the quality presets on the marble bunny")
    add("")
    add(headline_table(b, head))
    add("")
    add("* **(a)** discretisation + iteration error: against our own solve of the finest (Final) graph "
        "converged to a relative residual of 1e-6.")
    add("* **(b)** against the path tracer (model + discretisation + iteration). The reference carries noise "
        "(its *noise floor*, the error a perfect image would show); **(b) debiased** = "
        "sqrt((b)^2 - floor^2) is the error against a noise-free reference.")
    add("* *first frame*: light pass + all levels solved coarse to fine from zero + vertex radiance, in a process "
        "that has loaded the bake (whose cache keeps the split's half-space tables for the material's index, as "
        "the add-on's and the command line's bakes do; `save_bake(etas=...)`); "
        "*frame (warm)*: the sky turned by 5 degrees, the finest level warm-started from the previous frame "
        "(what an interactive edit costs). Tolerance 1e-4 (the add-on's default), the default CPU solver (CG with a "
        "coarse space on levels of 8,000 nodes and more, Chebyshev below).")
    add("")
    for para in findings_headline(b, head):
        add(para)
        add("")
    add(f"![error against time]({link['pareto']})")
    add("")
    # --- setup
    add("## Matched scenes and the reference")
    add("")
    add("`bench/accuracy_scenes.py`. Meshes: the Stanford bunny decimated to 10,000 triangles and made "
        "watertight (its base holes fan-filled: a path tracer cannot give an open boundary an inside), "
        "40 mm along its bounding-box diagonal; an icosphere (5,120 flat facets) of radius 12 mm. Materials "
        "(Jensen et al. 2001, eta 1.3): marble, skim milk, skin1, and *hetero*: marble veined with skin1 by "
        "the engine's procedural `marble` field (veins ~8 mm apart), which the reference receives as a "
        "128^3 grid volume. Light: the order-2 SH sky lobe `sky_environment((1, 0.6, 0.35), lobe=2)` "
        "(from the right, above, slightly in front), which our engine represents exactly; the path tracer "
        "cannot light a medium behind a smooth dielectric with a sun or point light "
        "(`docs/reference.md`). `sphere_marble_uniform`: the marble sphere under a uniform environment "
        "(the lowest-noise check of the model). Orthographic camera along -z.")
    add("")
    add("Reference: Mitsuba 3 `volpath`, one grey render per colour channel, Russian roulette off, the "
        "surface reflection subtracted (translucency only, as the paper's Fig. 11), split into 4 batches "
        "whose spread gives the standard error per pixel. Cached in `bench/data/reference/` "
        "(`--refresh-references` renders them again).")
    add("")
    add(reference_table(b))
    add("")
    add("Our side: the engine API exactly as the add-on calls it (`bake_mesh` with sky visibility, "
        f"{SKY_DIRECTIONS} rays per surface node (the add-on's Self-Occlusion default), `DiffusionSolver` or "
        "`gpu_shaders.make_solver`, `solve_interreflected`: on the CPU the first pass and the pass with its "
        "interreflection bounce are one block solve (`interreflection.py`), on the GPU two passes, warm-started; "
        "`vertex_radiance(result, view_dirs)` with per-vertex directions "
        "toward the camera, plus `single_scattering.render_vertices` where switched on), the per-vertex radiance "
        "rasterised from the reference's camera by `bench/reference/raster.py`. Bake times include the sky "
        "visibility; frame times include the bounce; *iterations* are those of the finest level's solve "
        "(the block solve where the bounce is folded in; each of its sweeps updates both passes).")
    ur = rows(b, "user")
    if ur:
        r = ur[0]
        add(f"The Blender user path (`bpy.ops.translucency.bake`, `bpy.ops.translucency.solve`, the "
            f"`translucency_radiance` attribute toward the scene camera, same rasteriser) on `{r['scene']}` at "
            f"{r['quality'].capitalize()}: error (b) {pct(r['err_ref'], 2)} against {pct(r['err_ref_api'], 2)} "
            f"for the engine API; the two images differ by {pct(r['err_vs_api'], 3)} relative RMS.")
    add("")
    # --- all scenes
    add("## All scenes at the three presets")
    add("")
    add(scenes_table(b))
    add("")
    for para in findings_scenes(b):
        add(para)
        add("")
    table17 = transport_targets_table(b)
    if table17.count("\n") > 1:
        add("### Issue 17's targets: one transport model")
        add("")
        add("Every term on where the planner turns it on (the first-scatter split for every scene here), "
            "converged Final graph against the path tracer, debiased; the near-light target is in *Local lights "
            "against the path tracer* below (its own bench). Where a row is missed, the paragraphs above and "
            "below say why.")
        add("")
        add(table17)
        add("")
    add(f"![images]({link['images']})")
    add("")
    add("Scan lines (cf. the paper's Fig. 11): RGB mean along two image rows; the grey band is +- 2 standard "
        "errors of the reference.")
    add("")
    add(f"![scan lines]({link['scanlines']})")
    add("")
    # --- knobs
    add("## The knobs")
    add("")
    add("Every row is one full run (bake, first frame) on the marble bunny unless the scene says otherwise; "
        "(a) is against the converged Final solve of the same scene.")
    add("")
    if rows(b, "K"):
        add("### K: inner-tet coarsening (the paper's Fig. 13)")
        add("")
        add("`BakeSettings(quality='preview', K=...)`: fTetWild's target edge length is (1 + K) x the surface "
            "triangle size, so K trades inner nodes for accuracy; the surface is the same in every row.")
        add("")
        add(knob_table(b, "K"))
        add("")
        kf = rows(b, "K_final")
        if kf:
            fin = one(b, "preset", kf[0]["scene"], "final")
            add("The Final surface (two refinements) with Preview's K, against the Final preset:")
            add("")
            add(knob_table(b, "K_final"))
            add("")
            if fin:
                r = kf[0]
                add(f"{r['label']}: {sum(r['nodes']):,} nodes instead of {sum(fin['nodes']):,}, first frame "
                    f"{ms(r['first_ms'])} ms instead of {ms(fin['first_ms'])} ms, warm frame {ms(r['frame_ms'])} ms "
                    f"instead of {ms(fin['frame_ms'])} ms; (a) {pct(r.get('err_conv'), 2)}, (b) {pct(r.get('err_ref'))} "
                    f"against the preset's {pct(fin.get('err_ref'))}.")
                add("")
        for p in findings_K(b):
            add(p)
            add("")
        if "K" in link:
            add(f"![error against K]({link['K']})")
            add("")
    if rows(b, "levels"):
        add("### Levels: the multi-resolution warm start (the paper's Fig. 14)")
        add("")
        add("Same finest graph in every row (Preview; the coarse levels are independent tetrahedralisations "
            "of 4x coarser surfaces); *finest level only* solves it from zero.")
        add("")
        add(knob_table(b, "levels"))
        add("")
        for p in findings_levels(b):
            add(p)
            add("")
    if rows(b, "tol") or rows(b, "iterations"):
        add("### Tolerance and iteration count")
        add("")
        add("Preview graph, the default solver. *iteration error* is against the direct (LU) solve of the same graph.")
        add("")
        ex = [("iteration error", "err_iter", lambda v: pct(v, 3))]
        add(knob_table(b, "tol", ex))
        add("")
        add(knob_table(b, "iterations", ex))
        add("")
        for p in findings_tol(b):
            add(p)
            add("")
    if rows(b, "solver"):
        add("### Solver: the paper's Jacobi against ours")
        add("")
        add("Tolerance 1e-4 on every level, at most 20,000 iterations per level. *paper* = the paper's "
            "discretisation (eq. 5-6, kappa of the neighbour inside the sum) relaxed by Jacobi (eq. 8-9); "
            "*Jacobi (our scheme)* = Jacobi on our finite-volume matrix; *ours: CG / Chebyshev* = the default (CG with a coarse space on levels of 8,000 nodes "
            "and more, Chebyshev below).")
        add("")
        add(knob_table(b, "solver", [("iteration error", "err_iter", lambda v: pct(v, 3))]))
        add("")
        kr = getattr(b, "kappa_rows", [])
        if kr:
            add("Kappa jump: marble veined with ketchup (same field; ketchup's blue sigma_s' is 0.03/mm "
                "against marble's 3.0/mm, kappa jumps ~100x), convergence only:")
            add("")
            add(table(["solver", "iterations per level", "final relative residual", "seconds", ""],
                      [[{"fast": "ours: CG / Chebyshev", "paper": "Jacobi (paper eq. 5-9)"}[r["solver"]],
                        str(r["iterations"]), f"{r['residual']:.2e}" if math.isfinite(r["residual"]) else "inf",
                        sec(r["seconds"]), "**diverged**" if r["diverged"] else "converged"] for r in kr]))
            add("")
            if "kappa" in link:
                add(f"![kappa jump]({link['kappa']})")
                add("")
        for p in findings_solver(b):
            add(p)
            add("")
    if rows(b, "precision"):
        add("### fp16 against fp32 (GPU path on llvmpipe)")
        add("")
        add(f"`gpu_shaders.make_solver(..., prefer='GPU', precision=...)` on {getattr(b, 'gpu_renderer', 'llvmpipe')}. "
            "fp16 stores the coefficients, q and the Shepard weights in half floats; the iterates stay fp32.")
        add("")
        add(knob_table(b, "precision", [("vs CPU image", "err_vs_cpu", lambda v: pct(v, 3))]))
        add("")
        for p in findings_precision(b):
            add(p)
            add("")
    if rows(b, "ss"):
        add("### Single scattering")
        add("")
        add("Preview graph. *diffusion only*: the diffusion term alone; *every term (split)*: the first-scatter "
            "split, closed-form single scattering plus the diffusion of what scatters more (the add-on's "
            "default, and every other row of this report); *SS ...*: diffusion alone plus Bernabei et al.'s "
            "single scattering (`bake_single_scattering`, `render_vertices` toward the camera; default: Preview "
            "voxels (48 on the longest side), 128 directions, 20,000 samples, SH order 4; bake time = diffusion "
            "bake + SS bake; first frame = diffusion + one SS frame with cached ray-sample pairs).")
        add("")
        add(knob_table(b, "ss", [("SS bake s", "ss_bake_s", sec), ("SS frame ms", "ss_frame_ms", ms),
                                 ("mean free path / voxel", "ss_mfp_voxels",
                                  lambda v: "-" if v is None else f"{v:.2f}")]))
        add("")
        for p in findings_ss(b):
            add(p)
            add("")
    if rows(b, "model"):
        add("### Where the bunny's model error comes from")
        add("")
        mr = rows(b, "model")
        po = mr[0].get("pixels_open", 0)
        pc = mr[0].get("pixels_concave", 0)
        add("Pixels split by how much of the sky their surface point sees (ray-traced against the mesh): "
            f"*open* >= 90 % ({po} px), *concave* < 90 % ({pc} px); bias = mean(ours) / mean(reference) - 1.")
        add("")
        add(table(["setting", "(b) all", "(b) debiased", "(b) open", "bias open", "(b) concave", "bias concave",
                   "mean q / engine q"],
                  [[r["label"], pct(r["err_ref"]), pct(r["err_ref_debiased"]), pct(r.get("err_ref_open")),
                    pct(r.get("bias_open")), pct(r.get("err_ref_concave")), pct(r.get("bias_concave")),
                    f"{r['q_ratio']:.3f}"] for r in mr]))
        add("")
        for p in findings_model(b):
            add(p)
            add("")
    if costs:
        add("## The preset cost file")
        add("")
        add("`translucency_addon/data/quality_costs.json` (written by this script, shipped in the extension) "
            "gives the Quality menu its labels and tooltips (`ops/quality_costs.py`): bake time, warm frame "
            "time and error (b) of each preset on the marble bunny, measured above.")
        add("")
    if b.notes:
        add("## Notes")
        add("")
        for n in b.notes:
            add(f"* {n}")
        add("")
    return "\n".join(L)


# --- findings (numbers from the run; the interpretation is the measured one) ----------------

def _conv(b, scene):
    r = rows(b, "converged", scene)
    return r[0] if r else None


def findings_headline(b, head):
    out = []
    c = _conv(b, head)
    pv, fi = one(b, "preset", head, "preview"), one(b, "preset", head, "final")
    if c is None or pv is None or fi is None:
        return out
    model = c["err_ref_debiased"]
    out.append(
        f"**Targets.** Preview: (b) {pct(pv['err_ref'])} against the 5 % target "
        f"({'met' if pv['err_ref'] <= 0.05 else 'missed'}). Final: (b) {pct(fi['err_ref'])} against 2 % "
        f"({'met' if fi['err_ref'] <= 0.02 else 'met only after removing the reference noise' if fi['err_ref_debiased'] <= 0.02 else 'missed'}). "
        f"The reference's own noise floor on this scene is {pct(c['noise_floor'], 2)}. "
        f"Our converged solve of the Final graph is {pct(c['err_ref'])} from the path tracer "
        f"({pct(model)} debiased): that is the **model error** of diffusion on this scene, which no quality "
        f"setting can remove; the discretisation + iteration error (a) of the presets is "
        f"{pct(one(b, 'preset', head, 'draft')['err_conv'], 2)} (Draft), {pct(pv['err_conv'], 2)} (Preview) and "
        f"{pct(fi['err_conv'], 2)} (Final).")
    return out


def findings_scenes(b):
    from translucency_addon.scene.materials import reduced_albedo

    out = []
    lines = []
    for name in b.scenes:
        c = _conv(b, name)
        if c is None:
            continue
        rgb = ", ".join(pct(v) for v in c["err_ref_rgb"])
        lines.append(f"{name} {pct(c['err_ref_debiased'])} (R, G, B {rgb}; mean brightness {pct(c.get('bias'))})")
    if lines:
        out.append("**Model error** (converged Final solve against the path tracer, debiased; bias = "
                   "mean(ours)/mean(reference) - 1): " + "; ".join(lines) + ".")
    sc = {n: s for n, s in b.scenes.items()}
    low = []
    for _n, s in sc.items():
        m = s.material
        for med in (m.medium_a, m.medium_b):
            if med is None:
                continue
            a = reduced_albedo(*med.arrays())
            if a.min() < 0.95 and med.name not in low:
                low.append(med.name)
                out.append(f"{med.name} has a reduced albedo of {', '.join(f'{v:.2f}' for v in a)} (R, G, B): "
                           "where it is well below 1, light is absorbed within a few mean free paths of where it "
                           "entered, the regime where the diffusion approximation overestimates the light that "
                           "comes back out, and single scattering is a large share of what does (about half at "
                           "0.68, blue). The first-scatter split (every term on, "
                           "`diffusion/split.py`) returns the once-scattered light in closed form "
                           "and lets diffusion carry only what scatters more, with its source calibrated on the "
                           "transport solution of a half-space (`diffusion/half_space.py`), so that a "
                           "half-space returns what transport returns (diffusion's own half-space answer for "
                           "that light is 8 % high at 0.68 and 4 % at 0.84; the sum now within 0.2 % of a "
                           "random walk, `tests/test_scattering_split.py`). What remains is where the object "
                           "is not a half-space -- the ears, the concavities, curvature on the scale of a few "
                           "mean free paths -- across which the graph's diffusion carries light that has "
                           "scattered only a few times; it is largest in blue, where that light is the largest "
                           "share.")
    sphere = _conv(b, "sphere_marble_sky")
    bunny = _conv(b, "bunny_marble_sky")
    if sphere and bunny:
        out.append(f"Marble: on the convex sphere diffusion is within {pct(sphere['err_ref_debiased'])} of the "
                   f"path tracer (bias {pct(sphere.get('bias'))}, consistent with docs/reference.md's closed-form "
                   f"check), on the bunny {pct(bunny['err_ref_debiased'])} with almost no mean bias "
                   f"({pct(bunny.get('bias'))}); see *Where the bunny's model error comes from* below for how much "
                   "of it sits in the concavities. With every term on (the first-scatter split) the once-scattered "
                   "light leaves mostly at grazing angles, so the rest must leave with the angular shape of multiple "
                   "scattering, not isotropically (`diffusion/split.py` eq. 4); with an isotropic rest the sum was too "
                   "dark head-on, -4 % along the normal at alpha 0.999 and IOR 1 against a random walk of the same "
                   "half-space (angular RMS 3.7 %, with eq. 4 0.7 %; `tests/test_scattering_split.py`), and marble "
                   "was worse with every term on than with diffusion alone (sphere 1.4 -> 1.7 %, bunny 3.4 -> 3.7 % "
                   "at Preview, commit a03c8e1). What remains is in the mean brightness: with every term on marble "
                   "is about 0.5 % darker than the path tracer where diffusion alone is about 0.6 % brighter "
                   "(section *Single scattering*). The split's diffusion source m = M/B is calibrated on a "
                   "half-space, where light injected a mean free path deep (the second scattering) is absorbed "
                   "1.6 % more than light injected at the surface, on the long walks that reach deep; the object, "
                   "12-40 mm, is not much larger than marble's diffusion length (8.5 mm in red) and holds fewer of "
                   "those walks, so the split takes a little too much (scaling the calibration by the object's own "
                   "uniform-light absorption fixed the spheres but brightened the skim-milk bunny, whose diffusion "
                   "alone is already bright in red: not adopted).")
    return out


def _label_rows(b, knob, scene=None):
    return {r["label"]: r for r in rows(b, knob, scene)}


def findings_K(b):
    out = []
    for name in b.scenes:
        kr = sorted(rows(b, "K", name), key=lambda r: r["K"])
        if len(kr) < 2:
            continue
        lo, hi = kr[0], kr[-1]
        out.append(
            f"{name}: from K = {hi['K']:g} to K = {lo['K']:g} the finest graph grows from "
            f"{sum(hi['nodes']):,} to {sum(lo['nodes']):,} nodes and the first frame from {ms(hi['first_ms'])} to "
            f"{ms(lo['first_ms'])} ms, while (a) goes from {pct(hi.get('err_conv'), 2)} to {pct(lo.get('err_conv'), 2)} "
            f"and (b) from {pct(hi.get('err_ref'))} to {pct(lo.get('err_ref'))}.")
    if out:
        out.append("K changes only the inner tets; at a fixed surface resolution the discretisation error is "
                   "dominated by the surface spacing (compare the presets, whose surfaces differ by 4x per "
                   "refinement), so K is a weak knob here, unlike the paper's Fig. 13 where a smaller K also "
                   "refined the surface.")
    return out


def findings_levels(b):
    lr = _label_rows(b, "levels")
    one_l = lr.get("finest level only")
    multi = [r for k, r in lr.items() if k != "finest level only"]
    if one_l is None or not multi:
        return []
    best = min(multi, key=lambda r: r["first_ms"])
    return [f"Without the coarse levels the finest level needs {one_l['iterations']} steps from zero "
            f"({ms(one_l['first_ms'])} ms); with {best['label']} it needs {best['iterations']} after the warm start "
            f"({ms(best['first_ms'])} ms in total, coarse levels included). The converged images are the same "
            f"((a) {pct(one_l.get('err_conv'), 2)} vs {pct(best.get('err_conv'), 2)}): the multi-resolution "
            "start buys time, not accuracy (the paper's Fig. 14). Our solve (CG with a coarse space on levels of "
            "8,000 nodes and more, Chebyshev below) needs far fewer steps than the paper's Jacobi in either case, "
            "so the gain is smaller than in the paper."]


def findings_tol(b):
    tr = [r for r in rows(b, "tol") if r.get("tol")]
    if not tr:
        return []
    tr.sort(key=lambda r: -r["tol"])
    d = next((r for r in rows(b, "tol") if r["label"].startswith("direct")), None)
    ok = next((r for r in tr if r.get("err_iter", 1) < 0.001), None)
    out = []
    if ok is not None:
        out.append(f"The iteration error falls below 0.1 % at tol = {ok['tol']:g} ({ok['iterations']} steps on the "
                   f"finest level, {ms(ok['first_ms'])} ms), far below the discretisation error of the same graph "
                   f"((a) {pct(ok.get('err_conv'), 2)}); the add-on's default 1e-4 is conservative"
                   + (f"; the direct LU of the same graph takes {ms(d['first_ms'])} ms." if d else "."))
    it = sorted(rows(b, "iterations"), key=lambda r: r["steps"])
    if it:
        out.append("With a fixed number of steps per level (no residual test): "
                   + ", ".join(f"{r['steps']} steps {pct(r.get('err_iter'), 2)}" for r in it)
                   + " iteration error against the direct solve.")
    return out


def findings_solver(b):
    out = []
    for name in b.scenes:
        sr = _label_rows(b, "solver", name)
        ch, pj, oj = sr.get("ours: CG / Chebyshev"), sr.get("Jacobi (paper eq. 5-9)"), sr.get("Jacobi (our scheme)")
        if ch is None or pj is None:
            continue
        s = (f"{name}: the paper's Jacobi took {pj['level_iterations']} iterations per level "
             f"({ms(pj['first_ms'])} ms) against ours {ch['level_iterations']} ({ms(ch['first_ms'])} ms), "
             f"{pj['first_ms'] / max(ch['first_ms'], 1e-9):.0f}x the time")
        if pj.get("diverged"):
            s += ", and **diverged**."
        else:
            s += (f". It converges to a *different* image: the paper's eq. 5 is not the conservative "
                  f"discretisation of div(kappa grad phi), so even converged it is {pct(pj.get('err_iter'))} from "
                  f"our direct solve of the same graph and (b) is {pct(pj.get('err_ref'))} against our "
                  f"{pct(ch.get('err_ref'))}.")
        if oj is not None:
            s += f" Jacobi on our matrix: {oj['level_iterations']} iterations, {ms(oj['first_ms'])} ms."
        out.append(s)
    kr = {r["solver"]: r for r in getattr(b, "kappa_rows", [])}
    if "paper" in kr and "fast" in kr:
        p, f = kr["paper"], kr["fast"]
        out.append("Under a sharp jump in kappa (marble veined with ketchup) the paper's scheme "
                   + ("**diverges**" if p["diverged"] else "does not diverge here")
                   + f" (residual {p['residual']:.1e} after {p['iterations']} iterations), as its rows lose "
                   f"diagonal dominance; ours converges ({f['residual']:.1e} after {f['iterations']}), as its "
                   "symmetric M-matrix guarantees whatever the contrast.")
    return out


def findings_precision(b):
    pr = list(rows(b, "precision"))
    c = next((r for r in pr if r.get("backend") == "cpu"), None)
    g32 = next((r for r in pr if r.get("backend") == "gpu32"), None)
    g16 = next((r for r in pr if r.get("backend") == "gpu16"), None)
    if not (c and g32 and g16):
        return []
    return [f"fp16 storage changes the image by {pct(g16.get('err_vs_cpu'), 3)} (fp32: "
            f"{pct(g32.get('err_vs_cpu'), 3)}) against the CPU solve, 100x below the discretisation error, so "
            f"(b) is unchanged ({pct(g16.get('err_ref'), 2)} vs {pct(g32.get('err_ref'), 2)}). On llvmpipe the "
            f"times ({ms(g32['first_ms'])} ms fp32, {ms(g16['first_ms'])} ms fp16, {ms(c['first_ms'])} ms numpy) "
            "are CPU times and say nothing about a GPU; fp16 halves the bytes per node update, which is what "
            "a bandwidth-bound GPU solve is limited by (gpu_shaders/README.md)."]


def findings_ss(b):
    out = []
    for name in b.scenes:
        sr = _label_rows(b, "ss", name)
        d, e = sr.get("diffusion only"), sr.get("every term (split)")
        if d is not None and e is not None:
            out.append(f"{name}: every term on (the first-scatter split) moves (b) from {pct(d.get('err_ref'))} to "
                       f"{pct(e.get('err_ref'))} (mean brightness {pct(d.get('bias'))} -> {pct(e.get('bias'))}); "
                       f"warm frame {ms(d.get('frame_ms'))} -> {ms(e.get('frame_ms'))} ms.")
    for name in b.scenes:
        sr = _label_rows(b, "ss", name)
        d, s = sr.get("diffusion only"), sr.get("SS default")
        if d is None or s is None:
            continue
        out.append(f"{name}: single scattering moves (b) from {pct(d.get('err_ref'))} to {pct(s.get('err_ref'))} "
                   f"(mean brightness {pct(d.get('bias'))} -> {pct(s.get('bias'))} against the path tracer) and "
                   f"adds {sec(s.get('ss_bake_s'))} s of bake and {ms(s.get('ss_frame_ms'))} ms per frame; the mean "
                   f"free path is {s.get('ss_mfp_voxels', float('nan')):.2f} voxels.")
    if out:
        out.append("The RBF rows add Bernabei et al.'s pass to the *unsplit* diffusion, whose boundary source q "
                   "is the whole transmitted flux (eq. 3): the once-scattered light is counted twice, and where "
                   "the mean free path is below a voxel (marble at these sizes) the voxels cannot resolve the "
                   "layer where single scattering happens. *Every term (split)* is what the add-on runs where "
                   "diffusion is valid: the entering light split over the local half-space into the closed-form "
                   "single scattering (exact for a half-space, no voxels) and the diffusion of what scatters "
                   "more (source m q, `diffusion/split.py`), so each path counts once; the "
                   "RBF pass replaces diffusion only where diffusion is invalid (planner).")
    return out


def findings_model(b):
    mr = _label_rows(b, "model")
    u = mr.get("without sky visibility")
    o = mr.get("hidden sky removed, no interreflection")
    ir = mr.get("hidden sky + one bounce (the add-on's default)")
    c = mr.get("converged Final graph (default)")
    if u is None or o is None or ir is None:
        return []
    out = [f"Without sky visibility the environment term ignores the object itself: no self-occlusion, no "
           f"light the object sends to itself. On the bunny the error then concentrates where the surface sees "
           f"less than 90 % of the sky (concave: (b) {pct(u.get('err_ref_concave'))}, ours "
           f"{pct(u.get('bias_concave'))} too bright) against {pct(u.get('err_ref_open'))} elsewhere (bias "
           f"{pct(u.get('bias_open'))})."]
    out.append(f"Removing the hidden sky alone (mean q x {o['q_ratio']:.2f}) overshoots: (b) {pct(o['err_ref'])}, "
               f"concave pixels {pct(o.get('bias_concave'))} too dark -- the hidden directions see the bright "
               "translucent bunny, not black, so a plain ambient-occlusion factor is the wrong fix.")
    out.append(f"The hidden sky plus one bounce (hidden directions see the object's own outgoing radiance from "
               f"a first solve, interpolated at the ray's hit point: `sky_visibility.py`, baked with "
               f"{SKY_DIRECTIONS} rays per surface node, the add-on's default) brings (b) from {pct(u['err_ref'])} "
               f"to **{pct(ir['err_ref'])}** (concave {pct(ir.get('err_ref_concave'))}, open "
               f"{pct(ir.get('err_ref_open'))})"
               + (f"; on the converged Final graph {pct(c['err_ref'])} (concave {pct(c.get('err_ref_concave'))}, "
                  f"open {pct(c.get('err_ref_open'))})" if c else "") + ". What remains is spread over the "
               "open surface as well: the diffusion model itself (compare the convex sphere's row above).")
    return out


# Sections other benches write into docs/accuracy.md (replace_section); a rewrite by bench/accuracy.py keeps them.
KEPT_SECTIONS = ("## Particle fluids (Voronoi-fluid cells, issue 14)\n", "## Deformation without a re-bake\n",
                 "## Objects with inner parts (issue 15): cavities, several media, an opaque part\n",
                 "## HDRI world (issue 19): the add-on against Cycles\n",
                 "## Local lights against the path tracer (issue 17)\n",
                 "## The user's alternative: Cycles, timed (issue 17)\n",
                 "## Media where diffusion fails (issue 30): a dark sphere and an albedo sweep\n",
                 "## Lamps (issue 31): an index-matched skin sphere under a sun, point, spot and disk light, pole to "
                 "pole\n")


def section_span(text: str, head: str):
    """``(start, end)`` of the section under ``head`` (a "## " heading line), or None."""
    if head not in text:
        return None
    start = text.index(head)
    nxt = text.find("\n## ", start + len(head))
    return start, len(text) if nxt < 0 else nxt + 1


def replace_section(text: str, head: str, body: str) -> str:
    """``text`` with the section under ``head`` replaced by ``head + body`` (appended when absent)."""
    span = section_span(text, head)
    if span is None:
        return text.rstrip("\n") + "\n\n" + head + body
    return text[:span[0]] + head + body + text[span[1]:]


def kept_sections(path: Path) -> str:
    """The :data:`KEPT_SECTIONS` of the report at ``path`` as they are now."""
    text = Path(path).read_text() if Path(path).exists() else ""
    spans = [section_span(text, h) for h in KEPT_SECTIONS]
    return "".join("\n" + text[a:b].rstrip("\n") + "\n" for a, b in (s for s in spans if s))


def write(b, out: Path, img_dir: Path, costs=None):
    """The plots (accuracy_report) and the text (render, here) of docs/accuracy.md."""
    out = Path(out)
    img_dir = Path(img_dir)
    img_dir.mkdir(parents=True, exist_ok=True)
    rel = Path("images") if img_dir.parent == out.parent else Path(img_dir.name)
    head_scene = "bunny_marble_sky" if "bunny_marble_sky" in b.scenes else next(iter(b.scenes))
    figs = {}
    figs["pareto"] = img_dir / "accuracy_pareto.png"
    report.plot_pareto(b, head_scene, figs["pareto"])
    figs["headline"] = img_dir / "accuracy_presets.png"
    report.plot_headline(b, figs["headline"])
    figs["images"] = img_dir / "accuracy_images.png"
    report.plot_images(b, figs["images"])
    figs["scanlines"] = img_dir / "accuracy_scanlines.png"
    report.plot_scanlines(b, figs["scanlines"])
    if rows(b, "K"):
        figs["K"] = img_dir / "accuracy_k.png"
        report.plot_K(b, figs["K"])
    figs["kappa"] = img_dir / "accuracy_kappa_jump.png"
    if not report.plot_kappa(b, figs["kappa"]):
        figs.pop("kappa")
    link = {k: (rel / v.name).as_posix() for k, v in figs.items()}
    text = render(b, link, costs, head_scene) + kept_sections(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(text)
    return figs
