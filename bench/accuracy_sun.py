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

Rows: the lamps' light as a volume source along its refracted chords (``diffusion/beam_source.py``, the
engine's default, ``--lamp-source volume``) and, in the same run, as a boundary source where it enters with
the incidence-aware split (``diffusion/split.py`` eq. 6; ``--lamp-source boundary``, what the engine did
before).  Columns: the profile's relative RMS from the lit pole to the terminator (polar angle <= 90
degrees; the issue's measure), the lit cap's mean (within 30 degrees of the pole), the band around the
terminator (80-100 degrees) and the shaded half's mean, each ours over the walk; the frame's time (light
pass and solve, the cache's load excluded).
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

from bench.bench_io import DATA, cli, command, commit, load_results, save_results, sphere_obj, write_section  # noqa: E402
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


def reference(n_walk: int, lamp: dict) -> dict:
    """The walk's radiance and standard error per channel on ``THETA_DEG`` (``lamp``: its keywords)."""
    L, E = [], []
    for sa, ss in zip(SIGMA_A, SIGMA_S):
        st = sa + ss
        r, e = sphere_lamp_walk(RADIUS_MM, st, ss / st, np.radians(THETA_DEG), n=n_walk, seed=11, **lamp)  # walk_key
        L.append(r)
        E.append(e)
    return {"theta": THETA_DEG.tolist(), "L": np.array(L).T.tolist(), "err": np.array(E).T.tolist()}


def walk_key(n_walk: int) -> str:
    """What :func:`reference` depends on: the sphere, the medium, the angles, the lamps, the paths and the seed."""
    return repr((RADIUS_MM, SIGMA_A, SIGMA_S, THETA_DEG.tolist(), {k: v[1] for k, v in LAMPS.items()}, n_walk, 11))


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
        for label, source in (("volume source (now)", "volume"), ("boundary source, eq. 6 (before)", "boundary")):
            out, stats = work / "L.npy", work / "stats.json"
            cli(["solve", cache, "-o", out, *material, *args, "--lamp-source", source, "--stats", stats])
            st = json.loads(stats.read_text())
            L = np.load(out).astype(np.float64)
            rows.append({"lamp": lamp, "quality": quality, "split": label, "bake_s": t_bake,
                         "frame_s": st["seconds"]["total"] - st["seconds"]["load"], **regions(theta_v, L, refs[lamp])})
            print(lamp, quality, label, rows[-1]["profile"]["rms"], rows[-1]["cap"]["mean"], file=sys.stderr)
    return rows


def _c3(v, pct=True, sign=False) -> str:
    if pct:
        return ", ".join(f"{100 * x:+.1f}" if sign else f"{100 * x:.1f}" for x in v) + " %"
    return ", ".join(f"{x:.3f}" for x in v)


def markdown(results: dict, command: str) -> str:
    lines = [HEADING, f"From one run of `{command}` ({results['date']}, engine {results['commit']}; two shared CPU "
             "cores shared with other work, no GPU: the frame times are a guide only).  " +
             "  ".join(p.replace("\n", " ") for p in __doc__.split("\n\n")[2:5]) + "\n",
             "| lamp | quality | the lamp's light enters | profile RMS, pole to terminator (R, G, B) | lit cap: ours / walk | terminator "
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
    rows = {(r["lamp"], r["quality"], r["split"][:6]): r for r in results["rows"]}
    out = ["Findings:\n"]
    best = "final" if ("sun", "final", "volume") in rows else "preview"
    now, before = rows.get(("sun", best, "volume")), rows.get(("sun", best, "bounda"))
    if now and before:
        out.append(f"* **The sun's light through the volume** ({best.title()}): the profile's RMS from the lit pole "
                   f"to the terminator {_c3(before['profile']['rms'])} -> {_c3(now['profile']['rms'])}; the lit cap "
                   f"{_c3(before['cap']['mean'], False)} -> {_c3(now['cap']['mean'], False)} of the walk, the band at "
                   f"80-100 degrees {_c3(before['terminator']['mean'], False)} -> {_c3(now['terminator']['mean'], False)}, "
                   f"the shaded half {_c3(before['shaded']['mean'], False)} -> {_c3(now['shaded']['mean'], False)}. "
                   "Transport carries the uncollided beam along chords through the volume, past the terminator "
                   "(skin's mean free path is 1.3 mm in red); a source on the surface where the light enters "
                   "cannot, and the half-space split put too much of the head-on light back out at the cap. "
                   "Issue 31's target, 5 %: **missed**.")
        out.append("* **Two calibrations to transport** make these rows (`diffusion/beam_source.py` eq. 8, "
                   "`diffusion/split.py` eq. 9). The volume source is weighted depth by depth, so a half-space "
                   "returns transport's multiple scattering at every incidence and deep sources keep their light "
                   "(one factor per incidence gave the shaded half 0.709, 0.692, 0.504 at Final; the depth weight "
                   "alone 0.730, 0.751, 0.573 and the profile 8.6, 10.0, 13.0 %). Light the diffusion carries to a "
                   "point from elsewhere leaves in the diffusion's own angular distribution, 1.25x the isotropic "
                   "output along the normal at eta 1 (with eq. 4's shape for all of the output the terminator band "
                   "was 0.856, 0.830, 0.781 at Final). Measured and not taken: the Milne problem's emergent shape "
                   "for that light (a source deep below, from `diffusion/half_space.py`; it sharpens as the albedo "
                   "falls) brought red's shaded half to 0.995 but overshot green and blue near the terminator "
                   "(1.14, 1.10; the point light's blue band 2.2x), where light arrives sideways, not from below.")
        out.append("* **Collisions the graph cannot place** (`diffusion/beam_source.py` eq. 9, 2026-12-07): a piece of "
                   "the beam nearer to the surface than to the inner node whose cell would hold it, and nearest to "
                   "its entry node, enters there as a boundary source of the same calibrated return. The same bakes "
                   "before and after, by hand (`/tmp` script: this bench's regions, a 40,000-path walk): Final sun "
                   "profile 5.5, 4.4, 7.9 % -> 5.5, 4.0, 7.0 %, lit cap 0.952, 0.967, 0.979 -> 0.955, 0.974, 0.989; "
                   "Preview sun 5.5, 4.5, 10.6 % -> 5.3, 3.8, 8.8 %; the near lamps' profiles within a point either "
                   "way (green's band past the terminator brighter: the disk's 1.107 -> 1.133 at Final). Where the "
                   "nodes lie far apart against the mean free path it is what counts: the same sphere 40 mm "
                   "across, lit cap 0.87, 0.75, 0.66 -> 0.95 at Preview (`tests/test_beam_source.py`).")
        out.append(f"* **What is left**: blue (albedo 0.68), the shaded half ({_c3(now['shaded']['mean'], False)} of "
                   "the walk) and, under the near lamps, the band past their geometric terminator, which the "
                   "lamps' light reaches only through the volume.")
        t_now = [r["frame_s"] for r in results["rows"] if r["quality"] == best and r["split"].startswith("volume")]
        t_before = [r["frame_s"] for r in results["rows"] if r["quality"] == best and r["split"].startswith("bounda")]
        out.append(f"* **Cost**: the frames with the volume source take {sum(t_now):.2f} s for the four lamps at "
                   f"{best.title()} against {sum(t_before):.2f} s with the boundary source "
                   f"({sum(t_now) / sum(t_before):.2f}x; one chord cast per lit surface node of the finest level "
                   "and 16 deposits along it, binned into the finest level's cells by a k-d tree and, merged four at "
                   "a time, into the coarser levels'; the rest is the solve: the volume source takes more CG steps "
                   "to the same relative residual, 54 against 41 on the finest level of the sun's frame, where its "
                   "vertex radiance comes out 3.2e-5 of the peak from a converged solve against the boundary "
                   "source's 1.1e-4; before 2026-12-07 the ratio was 1.85x, when every deposit was also matched "
                   "to its nearest surface node and binned unmerged into every level).")
    for lamp, what in (("point light", "20 mm from the surface; its geometric terminator lies at 70.5 degrees, so "
                                       "the 80-100 degree band is lit only through the volume"),
                       ("spot light", "its cone reaches 36 degrees from the pole"),
                       ("disk light", "points up to 80 degrees from the pole see part of the disk")):
        r, b = rows.get((lamp, best, "volume")), rows.get((lamp, best, "bounda"))
        if r and b:
            out.append(f"* **The {lamp}** ({what}): profile RMS {_c3(b['profile']['rms'])} -> "
                       f"{_c3(r['profile']['rms'])}, lit cap {_c3(b['cap']['mean'], False)} -> "
                       f"{_c3(r['cap']['mean'], False)}, terminator band {_c3(b['terminator']['mean'], False)} -> "
                       f"{_c3(r['terminator']['mean'], False)} of the walk.")
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
    n_walk = 20_000 if a.quick else a.walk_paths
    key = walk_key(n_walk)
    kept = load_results(RESULTS) if (DATA / RESULTS).exists() else {}
    if kept.get("walk_key") == key:  # the same walk (scene, lamps, paths, seed): its numbers, not ~4 min again
        refs, walk_s = kept["reference"], kept["walk_s"]
        print(f"the walk references of {kept['date']} ({key})", file=sys.stderr)
    else:
        refs = {lamp: reference(n_walk, kw) for lamp, (_, kw) in LAMPS.items()}
        walk_s = time.perf_counter() - t0
    results = {"date": time.strftime("%Y-%m-%d"), "commit": commit(), "walk_s": walk_s, "walk_key": key,
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
