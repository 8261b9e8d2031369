# SPDX-License-Identifier: GPL-3.0-or-later
"""Local lights against the path tracer (issue 17): point and area lights next to area emitters.

    nice -n 10 .venv/bin/python -m bench.accuracy_lights [--out docs/accuracy.md] [--scenes ...]

Scenes and the radiometric match: ``bench/light_scenes.py`` (a spherical emitter of radius a and
radiance L in the reference, a point light of radiant intensity pi a^2 L [W/sr, a in metres] at its
centre in the engine; a square emitter of area A, an area light of intensity L A along its normal).
References cached in ``bench/data/reference`` (``python -m bench.light_scenes`` renders them).

Our side, as the add-on renders it (``bench.accuracy_core.solve``: the bake's sky visibility and
one interreflection bounce, shadow rays toward each light): the Preview preset at the add-on's
tolerance, and the Final graph converged to a relative residual of 1e-6 (the row the targets are
about).  Error: relative RMS over the pixels both masks cover (eroded by one), the reference's noise
floor, the debiased error sqrt(b^2 - floor^2) with its statistical uncertainty (one standard
deviation of the floor's own estimate, propagated), the same on 2 x 2 blocks of pixels (the
reference's noise halves, a smooth model error stays), and mean ours / reference per channel.

The references hit an emitter only by chance, so their noise floors are several per cent: the
debiased error is what is compared with the target, and its +- says how far it can be trusted.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bench import light_scenes as LS  # noqa: E402
from bench.accuracy_core import ALL_TERMS, SUPERSAMPLE, Evaluator, solve, view_dirs  # noqa: E402
from bench.reference.metrics import comparison_mask, relative_rms  # noqa: E402
from bench.reference.raster import rasterize  # noqa: E402

HEADING = "## Local lights against the path tracer (issue 17)\n"
RESULTS = ROOT / "bench" / "data" / "accuracy_lights.json"
IMAGES = ROOT / "bench" / "out" / "accuracy_lights"  # our images, for a look (not committed)
USER_TOL = 1e-4
CONVERGED_TOL = 1e-6
PATCHES = 64  # area lights standing in for a spherical emitter (diagnostic rows)
TARGET = 0.03  # near spherical light, converged Final graph, debiased (issue 17)


def render_ours(ev: Evaluator, scene, quality: str, tol: float, lights=None):
    """``(image, mask, vertex radiance, seconds of the first frame, bake seconds, nodes, residual)``
    lit by ``lights`` (default: the scene's emitters' engine counterparts), solved from zero."""
    from translucency_addon.diffusion.solver import SolveOptions

    bk, bake_s = ev.bake(scene, quality=quality)
    # every term on, as the add-on's planner runs marble (the first-scatter split; ALL_TERMS)
    solver = ev.make_solver(bk, scene, SolveOptions(solver="fast", tol=tol, max_iterations=50_000,
                                                    single_scattering=ALL_TERMS), "cpu")
    lights = scene.engine_lights() if lights is None else lights
    t0 = time.perf_counter()
    res, _ = solve(solver, lights=lights, environment=None)
    L = solver.vertex_radiance(res, view_dirs(scene))
    dt = time.perf_counter() - t0
    ras = rasterize(scene.V, scene.F, L, scene.camera, scene.resolution, supersample=SUPERSAMPLE)
    return ras.image, ras.mask, L, dt, bake_s, (bk.finest.n_surface, bk.finest.n_inner), float(np.max(res.residual))


def emitter_as_area_lights(em, mm_per_unit: float, n: int = 64) -> list:
    """A spherical emitter as ``n`` engine area lights on its surface (diagnostic).

    A uniform Lambertian sphere is exactly the sum of its surface patches, each a one-sided
    Lambertian emitter of intensity L dA along its outward normal -- the engine's ``area`` light.
    With n patches (Fibonacci directions, dA = 4 pi a^2 / n in m^2), each with its own shadow ray,
    the engine sees the emitter's extent: the penumbra and the light that reaches surface points
    whose horizon cuts the sphere, which the single point light at the centre does not.  What is
    left against the reference is then the transport model (and the discretisation).
    """
    from translucency_addon.scene.lights import Light
    from translucency_addon.scene.sh import fibonacci_directions

    dirs = fibonacci_directions(n)
    a_m = em.radius * mm_per_unit * 1e-3
    dA = 4.0 * np.pi * a_m * a_m / n
    c = np.asarray(em.position, dtype=np.float64)
    return [Light("area", color=tuple(em.radiance), intensity=dA, position=tuple(c + em.radius * 1.0001 * d),
                  direction=tuple(d), name=f"patch {k}") for k, d in enumerate(dirs)]


def compare(image, mask, ref) -> dict:
    """Error against the reference, debiased, with the uncertainty of the debiasing.

    With n_p = reference noise per pixel (standard error s_p), b^2 = sum (m_p + n_p)^2 / sum r^2,
    whose expectation is m^2 + floor^2; its standard deviation (Gaussian n_p) is
    sqrt(sum 2 s_p^4 + 4 m_p^2 s_p^2) / sum r^2, propagated to sqrt(b^2 - floor^2).
    """
    e = relative_rms(image, ref.image, mask, ref.mask, stderr=ref.stderr)
    P = comparison_mask(mask, ref.mask)
    d = image[P] - ref.image[P]
    s2 = ref.stderr[P] ** 2
    denom = float((ref.image[P] ** 2).sum())
    m2 = max(e.rel_rms ** 2 - e.noise_floor ** 2, 0.0)
    var_b2 = float((2.0 * s2 ** 2 + 4.0 * np.maximum(d ** 2 - s2, 0.0) * s2).sum()) / denom ** 2
    deb = math.sqrt(m2)
    sd = math.sqrt(var_b2) / (2.0 * deb) if deb > 0 else math.sqrt(math.sqrt(var_b2))
    return {"err": e.rel_rms, "err_rgb": [float(x) for x in e.rel_rms_rgb], "floor": e.noise_floor,
            "debiased": deb, "debiased_sd": sd, "pixels": e.pixels,
            "mean_ratio": [float(x) for x in image[P].mean(0) / ref.image[P].mean(0)]}


def quartile_ratios(image, mask, ref) -> list:
    """Mean ours / reference over the pixels in each quartile of the reference's brightness (darkest first)."""
    P = comparison_mask(mask, ref.mask)
    r, o = ref.image.mean(-1), image.mean(-1)
    q = np.quantile(r[P], [0.0, 0.25, 0.5, 0.75, 1.0])
    q[-1] = np.inf
    return [float(o[P & (r >= a) & (r < b)].mean() / r[P & (r >= a) & (r < b)].mean()) for a, b in zip(q[:-1], q[1:])]


def add_quartiles(res: dict) -> dict:
    """Fill ``quartiles`` of rows from a run that did not store them, from its saved images (IMAGES)."""
    for name, rec in res["scenes"].items():
        ref = None
        for k, row in enumerate(rec["rows"]):
            f = IMAGES / f"{name}_{k}.npz"
            if "quartiles" in row or not f.exists():
                continue
            if ref is None:
                ref = LS.get_reference(next(s for s in LS.reference_scenes() if s.name == name))
            with np.load(f, allow_pickle=False) as z:
                row["quartiles"] = quartile_ratios(z["image"], z["mask"], ref)
    return res


def compare_binned(image, mask, ref, k: int = 2) -> dict:
    """:func:`compare` on k x k blocks of pixels (all k^2 inside the eroded comparison mask): the
    reference's noise falls by k, the smooth model error hardly changes.  A check that the
    debiasing is not fooled by noise the batches underestimate (an emitter hit by chance gives
    heavy-tailed pixels)."""
    P = comparison_mask(mask, ref.mask)
    H, W = P.shape
    h, w = H // k, W // k

    def blocks(a):
        return a[:h * k, :w * k].reshape(h, k, w, k, *a.shape[2:])

    ok = blocks(P).all(axis=(1, 3))
    ours = blocks(image).mean(axis=(1, 3))[ok]
    r = blocks(ref.image).mean(axis=(1, 3))[ok]
    s2 = (blocks(ref.stderr) ** 2).sum(axis=(1, 3))[ok] / k ** 4
    denom = float((r ** 2).sum())
    err = math.sqrt(float(((ours - r) ** 2).sum()) / denom)
    floor = math.sqrt(float(s2.sum()) / denom)
    return {"err": err, "floor": floor, "debiased": math.sqrt(max(err ** 2 - floor ** 2, 0.0)), "blocks": int(ok.sum())}


def run(names=None, log=print) -> dict:
    ev = Evaluator(log=log)
    out = {"scenes": {}}
    t_all = time.perf_counter()
    for sc in LS.reference_scenes():
        if names and sc.name not in names:
            continue
        ref = LS.get_reference(sc)
        em = sc.emitters[0]
        light = em.engine_light(sc.mm_per_unit)
        rec = {"ref_spp": ref.spp, "ref_seconds": ref.seconds, "ref_batches": ref.batches,
               "emitter": {"kind": em.kind, "radius_mm": em.radius * sc.mm_per_unit,
                           "distance_mm": float(np.linalg.norm(np.asarray(em.position) - 0.5 * sum(sc.bbox)))
                           * sc.mm_per_unit, "radiance": list(em.radiance)},
               "light": {"kind": light.kind, "intensity_W_sr": float(light.rgb[0])}, "rows": []}
        log(f"[{sc.name}] reference {ref.spp} spp x {ref.batches} batches, {ref.seconds:.0f} s; "
            f"engine {light.kind} light {light.rgb[0]:.4g} W/sr")
        runs = [("Preview", "preview", USER_TOL, None)]
        if em.kind == "sphere":
            runs.append((f"Preview, the emitter as {PATCHES} area lights (diagnostic)", "preview", USER_TOL,
                         emitter_as_area_lights(em, sc.mm_per_unit, PATCHES)))
        runs.append((f"Final graph, converged (tol {CONVERGED_TOL:g})", "final", CONVERGED_TOL, None))
        for label, quality, tol, lights in runs:
            img, mask, _, dt, bake_s, nodes, resid = render_ours(ev, sc, quality, tol, lights)
            row = {"label": label, "quality": quality, "tol": tol, "first_ms": 1e3 * dt, "bake_s": bake_s,
                   "nodes": list(nodes), "residual": resid, **compare(img, mask, ref),
                   "binned": compare_binned(img, mask, ref), "quartiles": quartile_ratios(img, mask, ref)}
            IMAGES.mkdir(parents=True, exist_ok=True)
            np.savez_compressed(IMAGES / f"{sc.name}_{len(rec['rows'])}.npz", image=img, mask=mask)
            rec["rows"].append(row)
            log(f"  {label:40s} first {row['first_ms']:8.0f} ms  err {row['err']:.4f} floor {row['floor']:.4f} "
                f"debiased {row['debiased']:.4f} +- {row['debiased_sd']:.4f} "
                f"binned {row['binned']['debiased']:.4f} mean "
                + ", ".join(f"{x:.3f}" for x in row["mean_ratio"]))
        out["scenes"][sc.name] = rec
    out["seconds"] = time.perf_counter() - t_all
    return out


def _pct(x):
    return f"{100 * x:.1f} %"


KIND = {"sphere": "spherical emitter", "rectangle": "square emitter", "shaded_sphere": "shaded sphere"}
ENGINE = {"point": "point light", "area": "area light", "spot": "spot light"}


def section(res: dict) -> str:
    L = ["", "Written by `nice -n 10 .venv/bin/python -m bench.accuracy_lights` in "
         f"{res['seconds']:.0f} s (references from the cache; `python -m bench.light_scenes` renders them). "
         "Do not edit by hand.", "",
         "A path tracer cannot light a medium behind a smooth dielectric with a delta light (docs/reference.md), "
         "but a path leaving the object can hit an emitter of finite size. So the reference (Mitsuba 3, as in "
         "docs/reference.md: one grey medium per channel, roulette off, translucency only) gets an **area "
         "emitter** and the engine its counterpart **light** (`bench/light_scenes.py`, "
         "`bench/reference/scene.RefEmitter`):", "",
         "* a uniform spherical emitter of radius a and radiance L [W/(m^2 sr)] <-> a **point light** at its centre "
         "of radiant intensity I = pi a^2 L [W/sr, a in metres] (power 4 pi I; Blender: a point light of that "
         "power). Outside the sphere, wherever it lies wholly above a surface point's horizon, its irradiance is "
         "exactly pi L (a/d)^2 cos = I cos / d^2 with d in metres, which is the engine's `light_irradiance`; the "
         "two differ only in the penumbra and near the terminator, which the engine's light now has too: it "
         "carries the radius a (Blender's Radius) and shades with four points of the disc facing each receiver "
         "(`scene.lights.sphere_visibility`; until this run a bare point);",
         "* a one-sided square emitter of area A <-> an **area light** of intensity L A [W/sr] along its normal "
         "(Blender: power pi L A) with the square's edges, which the engine integrates over the square (16 "
         "Lambertian patches, `scene.lights.emitter_samples`; before, a point with a cosine lobe);",
         "* *near*: the emitter's centre 2.5 object radii from the object's centre (sphere: 30 mm, 18 mm from its "
         "surface), radius 0.3 x that distance; *far*: 10x further and 10x larger (the same angular size); "
         "L = 11.1 makes the irradiance at the object's centre pi W/m^2. Light from the right, above and in front.",
         "* **Spot lights are not in the set**: a hard-edged cone needs the emitter inside a black shade several "
         "times its size, so the path tracer would hit it about 16x less often than the near sphere (see "
         "`bench/light_scenes.py`); Mitsuba's own `spot` is a delta light it cannot render through the boundary.",
         "", "The references hit the emitter only by chance, so their noise floors are several per cent; "
         "*debiased* = sqrt(error^2 - floor^2), +- one standard deviation of that estimate (the floor's own "
         "statistical error, propagated). Target (issue 17): <= 3.0 % debiased for the marble sphere and bunny "
         "under the near spherical light, converged Final graph.", "",
         "Our solve runs every term, as the add-on runs marble (the first-scatter split, "
         "`diffusion/split.py`; until 2098aba this bench solved diffusion alone, which gave the "
         "near sphere 6.7 % and the near bunny 9.3 %, converged). Under a lamp the split follows the "
         "incidence of its light at each surface node (eq. 6 there, issue 31; before 412760d it used the diffuse "
         "light's tables for every light, which gave the near sphere 5.8 %, the near bunny 9.1 %, the far "
         "sphere 4.0 % and the square 4.3 %, converged; from 412760d to fe6a6be the light pass handed it "
         "normal incidence everywhere). A lamp's light enters the diffusion as a volume source along its "
         "refracted chords (`diffusion/beam_source.py`, issue 31; before 99661fc it entered at the surface, which "
         "gave the near sphere 5.2 %, the near bunny 8.5 %, the far sphere 3.4 % and the square 3.7 %, "
         "converged). The first frame of the first scene includes the "
         "split's tables for eta 1.3 (the transport solves, cold process).", "",
         "| scene | reference light <-> engine light | reference spp (batches), s | our solve | first frame ms "
         "| error | noise floor | debiased | R, G, B | 2x2 binned: error / floor / debiased "
         "| mean ours / ref (R, G, B) |",
         "|---|---|---|---|---|---|---|---|---|---|---|"]
    for name, rec in res["scenes"].items():
        em, li = rec["emitter"], rec["light"]
        lab = (f"{KIND[em['kind']]} r = {em['radius_mm']:.1f} mm at {em['distance_mm']:.0f} mm <-> "
               f"{ENGINE[li['kind']]} {1e3 * li['intensity_W_sr']:.3g} mW/sr")
        for i, r in enumerate(rec["rows"]):
            head = "| | | |"
            if i == 0:
                head = f"| {name} | {lab} | {rec['ref_spp']:,} ({rec['ref_batches']}), {rec['ref_seconds']:.0f} |"
            L.append(f"{head} {r['label']} | {r['first_ms']:,.0f} | {_pct(r['err'])} | {_pct(r['floor'])} | "
                     f"{_pct(r['debiased'])} +- {100 * r['debiased_sd']:.1f} | "
                     + ", ".join(f"{100 * x:.1f}" for x in r["err_rgb"]) + " | "
                     + (f"{_pct(r['binned']['err'])} / {_pct(r['binned']['floor'])} / "
                        f"{_pct(r['binned']['debiased'])} | " if "binned" in r else "- | ")
                     + ", ".join(f"{x:.3f}" for x in r["mean_ratio"]) + " |")
    L.append("")
    L += findings(res)
    return "\n".join(L) + "\n"


def findings(res: dict) -> list:
    out = []
    for name, rec in res["scenes"].items():
        rows = {r["label"].split(",")[0] if not r["label"].startswith("Preview, the") else "patches": r
                for r in rec["rows"]}
        conv, prev, patches = rows.get("Final graph"), rows.get("Preview"), rows.get("patches")
        mean = ", ".join(f"{100 * (x - 1):+.1f} %" for x in conv["mean_ratio"])
        line = (f"* **{name}**: converged Final graph {_pct(conv['debiased'])} +- {100 * conv['debiased_sd']:.1f} "
                f"debiased (2x2 binned {_pct(conv['binned']['debiased'])}), mean brightness {mean} in R, G, B")
        if name.endswith("_near"):
            ok = conv["debiased"] <= TARGET
            line += f"; target {_pct(TARGET)}: **{'met' if ok else 'missed'}**"
        line += "."
        if rec["emitter"]["kind"] == "rectangle":
            em = rec["emitter"]
            d = em["distance_mm"] - LS.OBJECT_RADIUS_MM[name.split("_")[0]]
            R = 2.0 * em["radius_mm"] / math.sqrt(math.pi)  # the disc of the square's area
            line += (f" The engine integrates the area light over the square (`scene.lights.emitter_samples`, "
                     f"16 patches; until this run it was a far-field point with a cosine lobe): on the axis of a "
                     f"Lambertian disc of radius R at distance d the exact irradiance is pi L R^2 / (R^2 + d^2), "
                     f"the point's pi L R^2 / d^2, so at the sphere's nearest point (d = {d:.0f} mm, R = {R:.1f} mm) "
                     f"the far-field point was {100 * (R / d) ** 2:.0f} % too bright.")
        if "quartiles" in conv:
            line += (" Mean ours / reference by quartile of the reference's brightness, darkest first: "
                     + ", ".join(f"{x:.2f}" for x in conv["quartiles"]) + ".")
        if patches is not None and prev is not None:
            line += (f" The sphere light against the emitter as {PATCHES} area lights on its surface (Preview): "
                     f"{_pct(prev['debiased'])} -> {_pct(patches['debiased'])} debiased, mean "
                     + ", ".join(f"{x:.3f}" for x in prev["mean_ratio"]) + " -> "
                     + ", ".join(f"{x:.3f}" for x in patches["mean_ratio"])
                     + ("; by brightness quartile " + ", ".join(f"{x:.2f}" for x in prev["quartiles"]) + " -> "
                        + ", ".join(f"{x:.2f}" for x in patches["quartiles"])
                        if "quartiles" in prev and "quartiles" in patches else "")
                     + ": what is left of that difference is the four-point disc standing in for the emitter "
                     "(its penumbra, and the light it sends past the horizon of the surface points near the "
                     "terminator); the rest is the transport model and the discretisation.")
        out.append(line)
    return [o + "\n" for o in out]


def write(res: dict, path: Path) -> None:
    from bench.accuracy_text import replace_section

    res = add_quartiles(res)

    text = path.read_text() if path.exists() else ""
    path.write_text(replace_section(text, HEADING, section(res)))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", nargs="*", default=None)
    ap.add_argument("--out", default=str(ROOT / "docs" / "accuracy.md"))
    ap.add_argument("--from-json", action="store_true", help="rewrite the section from the last results, no solves")
    a = ap.parse_args(argv)
    if a.from_json:
        write(json.loads(RESULTS.read_text()), Path(a.out))
        print(f"wrote {a.out} from {RESULTS}")
        return
    res = run(a.scenes, log=lambda m: print(m, flush=True))
    if a.scenes and RESULTS.exists():  # a partial run: the other scenes' rows from the last run
        old = json.loads(RESULTS.read_text())
        merged = {n: res["scenes"].get(n, old["scenes"].get(n)) for n in [s.name for s in LS.reference_scenes()]}
        res = {"scenes": {n: r for n, r in merged.items() if r is not None},
               "seconds": res["seconds"] + old.get("seconds", 0.0)}
    RESULTS.write_text(json.dumps(res, indent=1, default=float) + "\n")
    write(res, Path(a.out))
    print(f"wrote {a.out} and {RESULTS} ({res['seconds']:.0f} s)")


if __name__ == "__main__":
    main()
