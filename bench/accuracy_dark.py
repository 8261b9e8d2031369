"""Media where diffusion fails (issue 30): a sphere of a dark medium, and an albedo sweep across the
planner's threshold, against an analogue random walk of the same sphere.

    python -m bench.accuracy_dark [--out docs/accuracy.md] [--quick]

Scene: a sphere of radius 5 mm (10 mm across, an icosphere of 2,562 vertices), unit extinction
(sigma_s' = albedo, sigma_a = 1 - albedo per mm), under a uniform white world of radiance 1, every vertex
seen along its normal -- what a new user gets from the command line with default settings
(``bake --single-scattering``, ``solve --env 1,1,1``; the add-on bakes single scattering by default for
such a medium).  The frame is the engine's (``frame.render_frame`` through ``python -m translucency_addon
solve``, in-process).

Reference: ``bench/sphere_walk.py``, an analogue random walk of the same sphere (its own Fresnel,
total internal reflection, every order), split into the once-scattered light, reflected inside or not (what
the single-scattering pass models: ``single_scattering/entry.py`` eq. 3, ``view_reflection.py``), and the rest.  By symmetry the exact
radiance is the same at every vertex, so the per-vertex error is ours alone; the noise floor is the
walk's standard error.

Columns: the mean over the vertices and the per-vertex relative RMS against the walk's total; the
single-scattering term alone against the walk's once-scattered light; the orders after the
first (``frame.orders_after_the_first``) against the walk's; the frame's cost (solve, single scattering,
the orders) on two shared CPU cores.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bench.bench_io import cli, command, commit, load_results, save_results, sphere_obj, write_section  # noqa: E402
from bench.sphere_walk import sphere_walk  # noqa: E402
from translucency_addon.planner_rules import ALBEDO_FULL, ALBEDO_MIN, diffusion_weight  # noqa: E402

HEADING = "## Media where diffusion fails (issue 30): a dark sphere and an albedo sweep\n"
RADIUS_MM = 5.0
DARK = [(0.2, 1.3), (0.2, 1.0)]
RESULTS = "dark_results.json"  # in bench/data
SWEEP = [0.1, 0.2, 0.3, 0.4, 0.45, 0.49, 0.51, 0.53, 0.55, 0.58, 0.6, 0.7, 0.8, 0.9]
DIFFUSION, SINGLE, BLEND = "diffusion + split", "single scattering + rest", "blend of both"


def run_case(work: Path, mesh: Path, albedo: float, eta: float, n_walk: int) -> dict:
    a, b = albedo, 1.0 - albedo
    material = ["--sigma-s", f"{a},{a},{a}", "--sigma-a", f"{b},{b},{b}", "--eta", repr(eta)]
    cache = work / f"sphere_{a}_{eta}.npz"
    t0 = time.perf_counter()
    cli(["bake", mesh, "-o", cache, "--single-scattering", *material])
    t_bake = time.perf_counter() - t0
    out, ss_out, stats = work / "L.npy", work / "ss.npy", work / "stats.json"
    cli(["solve", cache, "-o", out, *material, "--env", "1,1,1", "--ss-output", ss_out, "--stats", stats])
    st = json.loads(stats.read_text())
    L = np.load(out)[:, 0].astype(np.float64)
    ss = np.load(ss_out)[:, 0].astype(np.float64) if st["single_scattering"]["enabled"] else np.zeros_like(L)
    orders = float((st.get("orders_after_the_first_mean") or [0.0])[0])
    walk = sphere_walk(RADIUS_MM, a, eta, n=n_walk, seed=7)
    ref = walk.total
    sec = st["seconds"]
    # the plan's pass lines (the split's "closed-form single scattering [RGB]" is diffusion's own term)
    ms_on, ss_on = "\n  multiple scattering [RGB]" in st["plan"], "\n  single scattering [RGB]" in st["plan"]
    plan = BLEND if ms_on and ss_on else (DIFFUSION if ms_on else SINGLE)
    # the single-scattering side's share of the frame (the planner's blend weight; 1 outside the band)
    share = 1.0 - float(diffusion_weight(a)) if plan == BLEND else 1.0
    return {
        "albedo": a, "eta": eta, "mean": float(L.mean() / ref - 1.0),
        "rms": float(np.sqrt(np.mean((L / ref - 1.0) ** 2))),
        "single": float(ss.mean() / share / walk.single - 1.0) if ss.any() else None,
        "orders": float(orders / share / (ref - walk.single) - 1.0) if orders > 0 else None,
        "walk": ref, "walk_single": walk.single, "walk_rest": ref - walk.single,
        "noise": walk.stderr / ref, "ours": float(L.mean()), "share": share,
        "plan": plan,
        "seconds": {"frame": sec["total"] - sec["load"], "single_scattering": sec["single_scattering"],
                    "orders": sec.get("orders_after_the_first", 0.0), "diffusion": sec["diffusion"],
                    "bake": t_bake},
    }


def _pct(x) -> str:
    return "" if x is None else f"{100 * x:+.1f} %"


def markdown(results: dict, command: str) -> str:
    lines = [HEADING, f"From one run of `{command}` ({results['date']}, engine {results['commit']}; two shared CPU "
             "cores, no GPU).  A sphere 10 mm across, unit extinction per mm, under a white world, seen along "
             "the normals; reference: `bench/sphere_walk.py`, an analogue random walk of the same sphere "
             "(Fresnel boundary, total internal reflection, every order).  *mean*: our mean over the "
             "vertices against the walk; *RMS*: per vertex (the exact radiance is the same at every vertex, "
             "so this includes our vertex-to-vertex noise); *single*: the single-scattering term against the "
             "walk's once-scattered light (reflected inside or not); *rest*: the orders "
             "after the first against the walk's rest (both divided by their share of the frame where the "
             f"planner blends them with diffusion, reduced albedo {ALBEDO_MIN} to {ALBEDO_FULL}: "
             "`planner_rules.diffusion_weight`).  Noise floor: the walk's standard error.\n",
             "| albedo | IOR | passes | mean | RMS | single | rest | noise floor | frame (s) | of it: single, "
             "rest (ms) |", "|---|---|---|---|---|---|---|---|---|---|"]
    for r in results["dark"] + results["sweep"]:
        s = r["seconds"]
        lines.append(f"| {r['albedo']:.2f} | {r['eta']} | {r['plan']} | {_pct(r['mean'])} | {100 * r['rms']:.1f} % | "
                     f"{_pct(r['single'])} | {_pct(r['orders'])} | {100 * r['noise']:.2f} % | {s['frame']:.2f} | "
                     f"{1e3 * s['single_scattering']:.0f}, {1e3 * s['orders']:.1f} |")
    return "\n".join(lines) + "\n\n" + findings(results) + "\n"


def findings(results: dict) -> str:
    """What the table says, with the numbers of the same run; the 'before' figures are the CLI's at
    3fe77a8 (the engine before the margin and the orders after the first), measured with this bench."""
    rows = {(r["albedo"], r["eta"]): r for r in results["dark"] + results["sweep"]}
    d13, d10 = rows.get((0.2, 1.3)), rows.get((0.2, 1.0))
    ss_side = [r for r in results["sweep"] + results["dark"][:1] if r["plan"] == SINGLE]
    df_side = [r for r in results["sweep"] if r["plan"] == DIFFUSION]
    band = [r for r in results["sweep"] if r["plan"] == BLEND]
    out = ["Findings:\n"]
    if d13 and d10:
        out.append(f"* **The dark sphere** is {_pct(d13['mean'])} at IOR 1.3 and {_pct(d10['mean'])} at IOR 1 "
                   "(targets 10 % and 5 %); before this issue's work the same commands gave -22 % and -24 %, "
                   "and the add-on with default settings rendered it black (single scattering was not baked). "
                   "Two causes, each measured: view rays that started at the vertex missed half of the voxel "
                   "model's boundary ramp (the pass alone was -12 % at IOR 1; rays now cross the whole baked "
                   "medium), and the orders after the first were missing where the pass replaces diffusion "
                   f"({100 * d13['walk_rest'] / d13['walk']:.0f} % of this sphere's light; now eq. (5) of "
                   "`diffusion/split.py`).")
    if d13:
        out.append(f"* **The single-scattering term at IOR 1.3** is {_pct(d13['single'])} of the walk's once-scattered "
                   "light (at IOR 1 " + (_pct(d10['single']) if d10 else "?") + "): the world's light now enters "
                   "through the critical cone of the point where each chord leaves, eta^2 T times brighter "
                   "(`single_scattering/entry.py`, issue 30 item 3); with straight chords over the whole "
                   "hemisphere and one mean Fresnel factor the same term was +8.2 % (2026-12-04 run, engine "
                   "502ff43), and the dark sphere +6.4 %.  Light reflected inside before or after it scatters is "
                   "the orders-after-the-first's half-space share, not traced.")
    if ss_side and df_side:
        every = ss_side + band + df_side
        lo = max(ss_side, key=lambda r: r["albedo"])
        hi = min(df_side, key=lambda r: r["albedo"])
        over = [r for r in every if r["rms"] > 0.10]
        over_txt = ", ".join(f"{100 * r['rms']:.1f} % at {r['albedo']:.2f}" for r in sorted(over, key=lambda r: r["albedo"]))
        band_txt = ", ".join(f"{_pct(r['mean'])} at {r['albedo']:.2f}" for r in band)
        out.append(f"* **The sweep**: every mean within {100 * max(abs(r['mean']) for r in every):.1f} % of the walk "
                   f"at its own albedo, the per-vertex RMS over 10 % {('at ' + over_txt) if over else 'nowhere'}. "
                   f"From {ALBEDO_MIN} to {ALBEDO_FULL} the planner blends diffusion with single scattering and "
                   f"the orders after the first (diffusion's weight rising linearly): {_pct(lo['mean'])} at "
                   f"{lo['albedo']:.2f}, {band_txt}, {_pct(hi['mean'])} at {hi['albedo']:.2f}, continuous across "
                   "both ends (`tests/test_dark_media.py` pins the frame's step across 0.5 -/+ 1e-4 and "
                   "0.6 -/+ 1e-4 below 0.5 %).  Before the blend (engine 07f27e3, this bench) the frame "
                   "switched at 0.5, from -3.6 % at 0.49 to +7.9 % at 0.51 (RMS 13.9 %) and +5.5 % at 0.55 "
                   "(RMS 11.4 %): diffusion near its limit is too bright, single scattering with the half-space's "
                   "orders after the first slightly too dark, so the blend is also closer than either side.")
        ms = [1e3 * r["seconds"]["single_scattering"] for r in ss_side + band]
        mo = [1e3 * r["seconds"]["orders"] for r in ss_side + band]
        fb, fd, fs = ([r["seconds"]["frame"] for r in rows_] for rows_ in (band, df_side, ss_side))
        out.append(f"* **Cost**: the single-scattering pass is {min(ms):.0f}-{max(ms):.0f} ms of the frame here, the "
                   f"orders after the first {min(mo):.1f}-{max(mo):.1f} ms (one table lookup per vertex); in the "
                   "blend both passes run, so its frame is the two sides' together: "
                   + (f"{min(fb):.2f}-{max(fb):.2f} s against {min(fd):.2f}-{max(fd):.2f} s for diffusion alone and "
                      f"{min(fs):.2f}-{max(fs):.2f} s for single scattering alone (a cold frame of the command line: "
                      "the bake's load excluded, the single-scattering pass's pairs found anew)."
                      if band else "none in this run."))
    return "\n".join(out)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=None, help="markdown file whose section is (re)written")
    ap.add_argument("--quick", action="store_true", help="the two dark spheres only, a short walk")
    ap.add_argument("--walk-paths", type=int, default=400_000)
    ap.add_argument("--from-json", action="store_true",
                    help="rewrite the section from bench/data/dark_results.json without running")
    a = ap.parse_args(argv)
    if a.from_json:
        return write_section(markdown(load_results(RESULTS), command("accuracy_dark", out=a.out)), HEADING, a.out)
    results = {"date": time.strftime("%Y-%m-%d"), "commit": commit(), "dark": [], "sweep": []}
    n_walk = 50_000 if a.quick else a.walk_paths
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        mesh = sphere_obj(work, RADIUS_MM)
        for albedo, eta in DARK:
            results["dark"].append(run_case(work, mesh, albedo, eta, n_walk))
            print(results["dark"][-1], file=sys.stderr)
        for albedo in ([] if a.quick else SWEEP):
            if albedo == 0.2:
                continue  # the first dark row
            results["sweep"].append(run_case(work, mesh, albedo, 1.3, n_walk))
            print(results["sweep"][-1], file=sys.stderr)
    results["sweep"].sort(key=lambda r: r["albedo"])
    if not a.quick:
        save_results(RESULTS, results)
    return write_section(markdown(results, command("accuracy_dark", a.quick, a.out)), HEADING, a.out)


if __name__ == "__main__":
    raise SystemExit(main())
