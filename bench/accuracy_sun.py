"""Lamps (issue 31): an index-matched sphere of skin under a sun, the profile from the lit pole to the
shaded pole, against an analogue random walk of the same sphere.

    python -m bench.accuracy_sun [--out docs/accuracy.md] [--quick]

Scene: a sphere of radius 10 mm (an icosphere of 2,562 vertices), skin1 (Jensen et al. 2001:
sigma_a = 0.032, 0.17, 0.48 and sigma_s' = 0.74, 0.88, 1.01 per mm, isotropic phase), index-matched
(eta = 1), lit by a sun of irradiance 1 W/m^2 from +z and nothing else; every vertex seen along its
normal.  The frame is the engine's (``frame.render_frame`` through ``python -m translucency_addon
solve``, in-process), at Preview and at Final.

Reference: ``bench/sphere_walk.sphere_sun_walk``, an adjoint random walk of the same sphere with
next-event estimation towards the sun (exact for an index-matched sphere; every order), per channel on
a grid of polar angles, interpolated to each vertex's angle; checked against the half-space transport
solution at the pole of a large sphere to 0.3 %.  The noise floor is the walk's standard error.

Rows: the incidence-aware split (``diffusion/split.py`` eq. 6, issue 31 item 1) and, in the same run,
the split with the diffuse light's tables for the lamp too (what the engine did before; the lamps' part
of q zeroed in ``scene.lights.LampBeams``, a bench-only switch).  Columns: the profile's relative RMS
from the lit pole to the terminator (polar angle <= 90 degrees; the issue's measure), the lit cap's mean
(within 30 degrees of the pole), the band around the terminator (80-100 degrees) and the shaded half's
mean, each ours over the walk.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bench.sphere_walk import sphere_sun_walk  # noqa: E402

HEADING = "## Lamps (issue 31): an index-matched skin sphere under a sun, pole to pole\n"
RADIUS_MM = 10.0
SIGMA_A = (0.032, 0.17, 0.48)  # skin1, per mm
SIGMA_S = (0.74, 0.88, 1.01)
THETA_DEG = np.arange(0.0, 180.1, 5.0)


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


def _cli(args) -> None:
    from translucency_addon.__main__ import main

    out = io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(out):
        rc = main([str(a) for a in args])
    if rc:
        raise RuntimeError(f"translucency_addon {' '.join(map(str, args))} failed ({rc}):\n{out.getvalue()[-2000:]}")


def reference(n_walk: int) -> dict:
    """The walk's radiance and standard error per channel on ``THETA_DEG``."""
    L, E = [], []
    for sa, ss in zip(SIGMA_A, SIGMA_S):
        st = sa + ss
        r, e = sphere_sun_walk(RADIUS_MM * st, ss / st, np.radians(THETA_DEG), n=n_walk, seed=11)
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


def run_quality(work: Path, mesh: Path, quality: str, ref: dict) -> list:
    material = ["--material", "skin1", "--eta", "1.0"]
    cache = work / f"sphere_{quality}.npz"
    t0 = time.perf_counter()
    _cli(["bake", mesh, "-o", cache, "--quality", quality])
    t_bake = time.perf_counter() - t0
    from translucency_addon.geometry import meshio

    V, _ = meshio.load_obj(mesh)
    theta_v = np.degrees(np.arccos(np.clip(V[:, 2] / np.linalg.norm(V, axis=1), -1.0, 1.0)))
    rows = []
    for label, ctx in (("incidence-aware split (eq. 6)", contextlib.nullcontext()),
                       ("diffuse tables for the sun too (before)", diffuse_tables_for_lamps())):
        out, stats = work / "L.npy", work / "stats.json"
        with ctx:
            _cli(["solve", cache, "-o", out, *material, "--sun", "0,0,-1:1", "--stats", stats])
        st = json.loads(stats.read_text())
        L = np.load(out).astype(np.float64)
        rows.append({"quality": quality, "split": label, "bake_s": t_bake,
                     "frame_s": st["seconds"]["total"] - st["seconds"]["load"], **regions(theta_v, L, ref)})
        print(quality, label, rows[-1]["profile"], rows[-1]["cap"]["mean"], file=sys.stderr)
    return rows


def _c3(v, pct=True, sign=False) -> str:
    if pct:
        return ", ".join(f"{100 * x:+.1f}" if sign else f"{100 * x:.1f}" for x in v) + " %"
    return ", ".join(f"{x:.3f}" for x in v)


def markdown(results: dict, command: str) -> str:
    lines = [HEADING, f"From one run of `{command}` ({results['date']}, engine {results['commit']}; two shared CPU "
             "cores, no GPU).  " + __doc__.split("\n\n")[1].replace("\n", " ") + "  " +
             __doc__.split("\n\n")[2].replace("\n", " ") + "\n",
             "| quality | split | profile RMS, pole to terminator (R, G, B) | lit cap: ours / walk | terminator "
             "80-100 deg: ours / walk | shaded half: ours / walk | walk noise (profile) | frame (s) |",
             "|---|---|---|---|---|---|---|---|"]
    for r in results["rows"]:
        lines.append(f"| {r['quality']} | {r['split']} | {_c3(r['profile']['rms'])} | {_c3(r['cap']['mean'], False)} "
                     f"| {_c3(r['terminator']['mean'], False)} | {_c3(r['shaded']['mean'], False)} | "
                     f"{_c3(r['profile']['noise'])} | {r['frame_s']:.2f} |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=None, help="markdown file whose section is (re)written")
    ap.add_argument("--quick", action="store_true", help="Preview only, a short walk")
    ap.add_argument("--walk-paths", type=int, default=100_000)
    a = ap.parse_args(argv)
    import subprocess

    from translucency_addon.geometry import meshio, primitives

    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True,
                            text=True).stdout.strip()
    t0 = time.perf_counter()
    ref = reference(20_000 if a.quick else a.walk_paths)
    results = {"date": time.strftime("%Y-%m-%d"), "commit": commit, "walk_s": time.perf_counter() - t0,
               "reference": ref, "rows": []}
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        mesh = work / "sphere.obj"
        V, F = primitives.icosphere(RADIUS_MM, 4)
        meshio.save_obj(mesh, V, F)
        for quality in ("preview",) if a.quick else ("preview", "final"):
            results["rows"] += run_quality(work, mesh, quality, ref)
    command = "python -m bench.accuracy_sun" + (" --quick" if a.quick else "") + (f" --out {a.out}" if a.out else "")
    if not a.quick:
        (ROOT / "bench" / "data").mkdir(exist_ok=True)
        (ROOT / "bench" / "data" / "sun_results.json").write_text(json.dumps(results, indent=1) + "\n")
    text = markdown(results, command)
    print(text)
    if a.out:
        from bench.accuracy_text import replace_section

        out = Path(a.out)
        old = out.read_text() if out.exists() else ""
        out.write_text(replace_section(old, HEADING, text[len(HEADING):]))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
