"""Lamps (issue 31): an index-matched sphere of skin under a sun and near point, spot and disk lights, the profile
from the lit pole to the shaded pole, against an analogue random walk of the same sphere.

    python -m bench.accuracy_sun [--out docs/accuracy.md] [--quick]

Scene: a sphere of radius 10 mm (an icosphere of 2,562 vertices), skin1 (Jensen et al. 2001:
sigma_a = 0.032, 0.17, 0.48 and sigma_s' = 0.74, 0.88, 1.01 per mm, isotropic phase), index-matched
(eta = 1), lit by a sun of irradiance 1 W/m^2 from +z, or on the +z axis at 30 mm (20 mm from the
surface) by a point light of 1 W/sr (4 pi W), a spot light of the same power pointing at the centre
(Spot Size 30 degrees, Blend 0.3: its cone meets the pole's tangent plane in a circle of radius 5.4 mm), or a
disk light 10 mm across facing the sphere (pi W, Blender's: 1 W/sr along its normal); nothing else; every
vertex seen along its normal.  The frame is the engine's (``frame.render_frame`` through ``python -m translucency_addon
solve``, in-process), at Preview and at Final.

Reference: ``bench/sphere_walk.sphere_lamp_walk``, an adjoint random walk of the same sphere with
next-event estimation towards the lamp (exact for an index-matched sphere; every order), per channel on
a grid of polar angles, interpolated to each vertex's angle; checked against the half-space transport
solution at the pole of a large sphere to 0.3 %.  The noise floor is the walk's standard error.

Rows: the incidence-aware split (``diffusion/split.py`` eq. 6, issue 31 item 1) and, in the same run,
the split with the diffuse light's tables for the lamp too (what the engine did before; the lamps' part
of q zeroed in ``scene.lights.LampBeams``, a bench-only switch).  Columns: the profile's relative RMS
from the lit pole to the terminator (polar angle <= 90 degrees; the issue's measure), the lit cap's mean
(within 30 degrees of the pole), the band around the terminator (80-100 degrees) and the shaded half's
mean, each ours over the walk.  A diagnostic row (sun, Preview graph, not the engine): diffusion alone
with the sun's uncollided beam as a *volume* source ``sigma_s' E e^{-sigma_t d}`` at the graph's inner
nodes instead of the boundary source, by a direct sparse solve of the engine's own assembly -- what moving
the lamps' light into the volume would give.
"""

from __future__ import annotations

import argparse
import contextlib
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
from bench.sphere_walk import sphere_lamp_walk  # noqa: E402

HEADING = "## Lamps (issue 31): an index-matched skin sphere under a sun, point, spot and disk light, pole to pole\n"
RADIUS_MM = 10.0
SIGMA_A = (0.032, 0.17, 0.48)  # skin1, per mm
SIGMA_S = (0.74, 0.88, 1.01)
RESULTS = "sun_results.json"  # in bench/data
THETA_DEG = np.arange(0.0, 180.1, 5.0)
POINT_MM = 30.0  # the point, spot and disk lights' distance from the centre, on +z
SPOT_DEG, SPOT_BLEND, DISK_MM = 30.0, 0.3, 5.0
# lamp -> (the CLI's option, the walk's keywords): each 1 W/sr (the sun 1 W/m^2) towards the sphere
LAMPS = {
    "sun": (["--sun", "0,0,-1:1"], {}),
    "point light": (["--point", f"0,0,{POINT_MM}:{4.0 * np.pi!r}"], {"point_mm": POINT_MM}),
    "spot light": (["--spot", f"0,0,{POINT_MM}:0,0,-1:{4.0 * np.pi!r}:{SPOT_DEG}:{SPOT_BLEND}"],
                   {"point_mm": POINT_MM, "spot": (float(np.radians(SPOT_DEG)), SPOT_BLEND)}),
    "disk light": (["--area", f"0,0,{POINT_MM}:{2 * DISK_MM},0,0:0,{2 * DISK_MM},0:{np.pi!r}:disk"],
                   {"point_mm": POINT_MM, "disk_mm": DISK_MM}),
}


@contextlib.contextmanager
def diffuse_tables_for_lamps():
    """The split as it was before eq. (6): every lamp's light split with the diffuse light's tables."""
    from translucency_addon.scene import lights

    add = lights.LampBeams.add
    lights.LampBeams.add = lambda self, dq, cos_i: None
    try:
        yield
    finally:
        lights.LampBeams.add = add


def reference(n_walk: int, lamp: dict) -> dict:
    """The walk's radiance and standard error per channel on ``THETA_DEG`` (``lamp``: its keywords)."""
    L, E = [], []
    for sa, ss in zip(SIGMA_A, SIGMA_S):
        st = sa + ss
        r, e = sphere_lamp_walk(RADIUS_MM, st, ss / st, np.radians(THETA_DEG), n=n_walk, seed=11, **lamp)
        L.append(r)
        E.append(e)
    return {"theta": THETA_DEG.tolist(), "L": np.array(L).T.tolist(), "err": np.array(E).T.tolist()}


def regions(theta_v: np.ndarray, L: np.ndarray, ref: dict) -> dict:
    """Ours against the walk interpolated to each vertex's polar angle, by region, per channel."""
    R = np.array([np.interp(theta_v, ref["theta"], np.array(ref["L"])[:, c]) for c in range(3)]).T
    Err = np.array([np.interp(theta_v, ref["theta"], np.array(ref["err"])[:, c]) for c in range(3)]).T
    out = {}
    for name, sel in (("profile", theta_v <= 90.0), ("cap", theta_v <= 30.0),
                      ("terminator", (theta_v >= 80.0) & (theta_v <= 100.0)), ("shaded", theta_v > 90.0)):
        r = L[sel] / R[sel] - 1.0
        out[name] = {"rms": np.sqrt(np.mean(r**2, axis=0)).tolist(), "mean": (L[sel].mean(0) / R[sel].mean(0)).tolist(),
                     "noise": np.sqrt(np.mean((Err[sel] / R[sel]) ** 2, axis=0)).tolist()}
    return out


def run_quality(work: Path, mesh: Path, quality: str, refs: dict) -> list:
    from translucency_addon.diffusion.split import half_space_split
    from translucency_addon.geometry import meshio

    material = ["--material", "skin1", "--eta", "1.0"]
    cache = work / f"sphere_{quality}.npz"
    t0 = time.perf_counter()
    cli(["bake", mesh, "-o", cache, "--quality", quality])
    t_bake = time.perf_counter() - t0
    half_space_split(1.0)  # the split's tables once, before any frame is timed
    V, _ = meshio.load_obj(mesh)
    theta_v = np.degrees(np.arccos(np.clip(V[:, 2] / np.linalg.norm(V, axis=1), -1.0, 1.0)))
    rows = []
    for lamp, (args, _) in LAMPS.items():
        for label, ctx in (("incidence-aware split (eq. 6)", contextlib.nullcontext()),
                           ("diffuse tables for the lamp too (before)", diffuse_tables_for_lamps())):
            out, stats = work / "L.npy", work / "stats.json"
            with ctx:
                cli(["solve", cache, "-o", out, *material, *args, "--stats", stats])
            st = json.loads(stats.read_text())
            L = np.load(out).astype(np.float64)
            rows.append({"lamp": lamp, "quality": quality, "split": label, "bake_s": t_bake,
                         "frame_s": st["seconds"]["total"] - st["seconds"]["load"], **regions(theta_v, L, refs[lamp])})
            print(lamp, quality, label, rows[-1]["profile"]["rms"], rows[-1]["cap"]["mean"], file=sys.stderr)
    if quality == "preview":
        rows.append({"lamp": "sun", "quality": quality, "split": "diagnostic: diffusion alone, the beam as a volume "
                     "source (direct solve)", "bake_s": t_bake, "frame_s": float("nan"),
                     **regions(theta_v, volume_source_radiance(cache), refs["sun"])})
    return rows


def volume_source_radiance(cache: Path) -> np.ndarray:
    """The diagnostic row: the engine's finest-level assembly solved directly with the sun's uncollided beam
    as a volume source at the inner nodes (no boundary source), radiance through the engine's output."""
    from dataclasses import replace

    from scipy.sparse.linalg import spsolve

    from translucency_addon import cache as cache_io
    from translucency_addon.diffusion import solver as dmod
    from translucency_addon.diffusion.assembly import sparse_matrix
    from translucency_addon.scene import materials

    bake = cache_io.load_bake(cache)
    mat = replace(materials.material_from_preset("skin1"), eta=1.0)
    s = dmod.DiffusionSolver(bake, mat, options=dmod.SolveOptions(single_scattering=False))
    fine = len(bake.levels) - 1
    lv, system = bake.levels[fine], s.systems[fine]
    P = lv.position[: lv.n_inner] * bake.mm_per_unit
    bz, cz = P[:, 2], (P * P).sum(axis=1) - RADIUS_MM**2
    d_sun = -bz + np.sqrt(np.maximum(bz * bz - cz, 0.0))  # mm to the surface towards the sun (+z)
    vol = lv.volume[: lv.n_inner] * bake.mm_per_unit**3
    phi = np.zeros((system.n, 3))
    for c in range(3):
        b = np.zeros(system.n)
        b[: lv.n_inner] = SIGMA_S[c] * np.exp(-(SIGMA_A[c] + SIGMA_S[c]) * d_sun) * vol
        phi[:, c] = spsolve(sparse_matrix(system, c).tocsc(), b)
    res = dmod.SolveResult(phi=[None] * fine + [phi], q=[None] * fine + [np.zeros((lv.n_surface, 3))],
                           level_solves=[])
    return s.vertex_radiance(res)


def _c3(v, pct=True, sign=False) -> str:
    if pct:
        return ", ".join(f"{100 * x:+.1f}" if sign else f"{100 * x:.1f}" for x in v) + " %"
    return ", ".join(f"{x:.3f}" for x in v)


def markdown(results: dict, command: str) -> str:
    lines = [HEADING, f"From one run of `{command}` ({results['date']}, engine {results['commit']}; two shared CPU "
             "cores shared with other work, no GPU: the frame times are a guide only).  " +
             "  ".join(p.replace("\n", " ") for p in __doc__.split("\n\n")[2:5]) + "\n",
             "| lamp | quality | split | profile RMS, pole to terminator (R, G, B) | lit cap: ours / walk | terminator "
             "80-100 deg: ours / walk | shaded half: ours / walk | walk noise (profile) | frame (s) |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in results["rows"]:
        frame = "" if r["frame_s"] != r["frame_s"] else f"{r['frame_s']:.2f}"
        lines.append(f"| {r['lamp']} | {r['quality']} | {r['split']} | {_c3(r['profile']['rms'])} | {_c3(r['cap']['mean'], False)} "
                     f"| {_c3(r['terminator']['mean'], False)} | {_c3(r['shaded']['mean'], False)} | "
                     f"{_c3(r['profile']['noise'])} | {frame} |")
    return "\n".join(lines) + "\n\n" + findings(results) + "\n"


def findings(results: dict) -> str:
    """What the table says, with the numbers of the same run."""
    rows = {(r["lamp"], r["quality"], r["split"][:9]): r for r in results["rows"]}
    out = ["Findings:\n"]
    best = "final" if ("sun", "final", "incidence") in rows else "preview"
    now, before = rows.get(("sun", best, "incidence")), rows.get(("sun", best, "diffuse t"))
    diag = rows.get(("sun", "preview", "diagnosti"))
    if now and before:
        out.append(f"* **The incidence-aware split** (eq. 6 of `diffusion/split.py`; per incidence within the walk's "
                   f"noise in `tests/test_scattering_split.py`) brings the sun's lit cap ({best.title()}) from "
                   f"{_c3(before['cap']['mean'], False)} of the walk to {_c3(now['cap']['mean'], False)}: head-on light "
                   "goes deeper, and less of it comes back; the grazing light near the terminator comes back "
                   f"more ({_c3(before['terminator']['mean'], False)} -> {_c3(now['terminator']['mean'], False)} at "
                   "80-100 degrees). The profile's RMS moves from "
                   f"{_c3(before['profile']['rms'])} to {_c3(now['profile']['rms'])}. Issue 31's target, 5 %: "
                   "**missed**.")
        out.append(f"* **What is left is the terminator and the shaded half**: ours over the walk "
                   f"{_c3(now['terminator']['mean'], False)} at 80-100 degrees and {_c3(now['shaded']['mean'], False)} on "
                   "the shaded half. The diffusion's source sits on the boundary (Wang et al. eq. 3) and a lamp's "
                   "light enters only where the surface faces it, while transport carries the uncollided beam "
                   "along chords through the volume, past the terminator (skin's mean free path is 1.3 mm in red).")
    if diag:
        out.append(f"* **The cause, measured**: the diagnostic row solves the same Preview graph with the beam as a "
                   f"volume source, diffusion alone: profile RMS {_c3(diag['profile']['rms'])}, terminator "
                   f"{_c3(diag['terminator']['mean'], False)}, shaded half {_c3(diag['shaded']['mean'], False)}. "
                   "The same with only a local half-space's depth (each inner node lit through the surface point "
                   "above it, no chords; measured once, not in the table) leaves the terminator at 0.40, 0.24, 0.10: "
                   "it is the chords. The engine does not do this yet: it needs the uncollided beam ray-traced to "
                   "the inner nodes per lamp, its split calibrated against the volume source's half-space return, "
                   "and a discretisation of the part shallower than the first inner node (on marble's 0.45 mm mean "
                   "free path, R = 5 mm, the point-sampled volume source came out 4-22 % dark at 30-90 degrees).")
    pt = rows.get(("point light", best, "incidence"))
    if pt:
        out.append(f"* **The point light** (20 mm from the surface): lit cap {_c3(pt['cap']['mean'], False)}, "
                   f"terminator band {_c3(pt['terminator']['mean'], False)}; its geometric terminator lies at "
                   "70.5 degrees, so the 80-100 degree band is lit only through the volume.")
    for lamp, what in (("spot light", "its cone reaches 36 degrees from the pole"),
                       ("disk light", "points up to 80 degrees from the pole see part of the disk")):
        r = rows.get((lamp, best, "incidence"))
        if r:
            out.append(f"* **The {lamp}** ({what}): lit cap {_c3(r['cap']['mean'], False)} of the walk, profile RMS "
                       f"{_c3(r['profile']['rms'])}; the same pattern, since the boundary source lights only "
                       "where the lamp reaches the surface.")
    return "\n".join(out)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=None, help="markdown file whose section is (re)written")
    ap.add_argument("--quick", action="store_true", help="Preview only, a short walk")
    ap.add_argument("--walk-paths", type=int, default=100_000)
    ap.add_argument("--from-json", action="store_true",
                    help="rewrite the section from bench/data/sun_results.json without running")
    a = ap.parse_args(argv)
    if a.from_json:
        return write_section(markdown(load_results(RESULTS), command("accuracy_sun", out=a.out)), HEADING, a.out)
    t0 = time.perf_counter()
    refs = {lamp: reference(20_000 if a.quick else a.walk_paths, kw) for lamp, (_, kw) in LAMPS.items()}
    results = {"date": time.strftime("%Y-%m-%d"), "commit": commit(), "walk_s": time.perf_counter() - t0,
               "reference": refs, "rows": []}
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        mesh = sphere_obj(work, RADIUS_MM)
        for quality in ("preview",) if a.quick else ("preview", "final"):
            results["rows"] += run_quality(work, mesh, quality, refs)
    if not a.quick:
        save_results(RESULTS, results)
    return write_section(markdown(results, command("accuracy_sun", a.quick, a.out)), HEADING, a.out)


if __name__ == "__main__":
    raise SystemExit(main())
