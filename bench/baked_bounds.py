"""A cold frame with and without the spectral bounds a bake keeps (diffusion/baked_bounds.py, issue 33: the
first Final frame).

    .venv/bin/python -m bench.baked_bounds [--qualities preview final] [--runs 3] [--out docs/bench_solve.md]

Scene: the accuracy bench's 40 mm marble bunny (``bunny_marble_sky``; its bakes from
``bench/out/accuracy_bakes``, made by ``python -m bench.accuracy`` or here on the first run).  Two caches of
the same bake, written here: one without a record, one with the marble's bounds kept
(``with_kept_bounds``: what ``bake --material marble`` and the add-on's bake now do).  Each is rendered by
``python -m translucency_addon solve`` in a process of its own (a farm's frame: nothing carried over; a sun
and a dim world), the two alternating, ``--runs`` times each; the medians of the command's wall time and of
the frame's own total (its ``--stats``), and whether the two radiance files are the same bytes.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bench.bench_io import write_section  # noqa: E402
from bench.mesh_scaling import SOLVE_ARGS  # noqa: E402  (the same frame: marble, a sun, a dim world)

HEADING = "## A farm's frame with the bake's spectral bounds (issue 33: the first Final frame)\n"
BAKES = ROOT / "bench" / "out" / "accuracy_bakes"


def caches(quality: str, work: Path) -> dict:
    """Write the scene's bake twice (without and with kept bounds); returns paths, nodes and the record's cost."""
    from bench import accuracy_scenes as scenes
    from bench.accuracy_core import Evaluator
    from translucency_addon import cache
    from translucency_addon.diffusion.baked_bounds import with_kept_bounds

    sc = next(s for s in scenes.reference_scenes() if s.name == "bunny_marble_sky")
    bk, _ = Evaluator(bake_cache=BAKES, log=lambda *a: None).bake(sc, quality=quality)
    bk = replace(bk, spectral_bounds=None)
    plain, kept = work / f"{quality}-plain.npz", work / f"{quality}-kept.npz"
    cache.save_bake(str(plain), bk, etas=(sc.material.eta,))
    t0 = time.perf_counter()
    with_bounds = with_kept_bounds(bk, sc.material)
    seconds = time.perf_counter() - t0
    cache.save_bake(str(kept), with_bounds, etas=(sc.material.eta,))
    return {"plain": plain, "kept": kept, "record_s": seconds, "nodes": int(bk.finest.n_nodes),
            "levels": len(bk.levels)}


def frame(path: Path, out: Path) -> tuple[float, dict]:
    stats = out.with_suffix(".json")
    t = time.perf_counter()
    r = subprocess.run([sys.executable, "-m", "translucency_addon", "solve", str(path), "-o", str(out), *SOLVE_ARGS,
                        "--stats", str(stats)], cwd=ROOT, capture_output=True, text=True)
    wall = time.perf_counter() - t
    if r.returncode:
        raise RuntimeError(f"solve {path} failed:\n{r.stderr[-2000:]}")
    return wall, json.loads(stats.read_text())


def measure(quality: str, runs: int, work: Path) -> dict:
    c = caches(quality, work)
    walls, totals, adopted = {"plain": [], "kept": []}, {"plain": [], "kept": []}, {}
    for _ in range(runs):
        for name in ("plain", "kept"):
            wall, st = frame(c[name], work / f"{quality}-{name}.npy")
            walls[name].append(wall)
            totals[name].append(st["seconds"]["total"])
            adopted[name] = st["spectral_bounds_from_bake"]
    same = (work / f"{quality}-plain.npy").read_bytes() == (work / f"{quality}-kept.npy").read_bytes()
    return {"quality": quality, "nodes": c["nodes"], "levels": c["levels"], "record_s": c["record_s"],
            "wall": {k: statistics.median(v) for k, v in walls.items()},
            "total": {k: statistics.median(v) for k, v in totals.items()},
            "adopted": adopted, "same_bytes": same, "runs": runs}


def markdown(rows: list, command: str, date: str, commit: str) -> str:
    lines = [HEADING, f"From one run of `{command}` ({date}, engine {commit}; two shared CPU cores, no GPU: compare "
             "within a row).  The accuracy bench's marble bunny, one bake per quality written twice: without a "
             "record and with the marble's spectral bounds kept (`diffusion/baked_bounds.py`: what `bake "
             "--material` and the add-on's bake now write).  Each cache rendered by `python -m translucency_addon "
             "solve ... " + " ".join(SOLVE_ARGS) + "` in its own process, as a farm renders every frame, the two "
             "alternating; medians.  *frame*: the frame's own total from its `--stats` (load, set-up, light pass, "
             "bounds, solve, output); *command*: the process's wall time.\n",
             "| quality | finest nodes | bounds kept at bake (s) | levels adopted | frame without -> with (s) | "
             "command without -> with (s) | saved per frame | radiance the same bytes |",
             "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        t, w = r["total"], r["wall"]
        lines.append(f"| {r['quality']} | {r['nodes']:,} | {r['record_s']:.2f} | {r['adopted']['kept']} of "
                     f"{r['levels']} | {t['plain']:.2f} -> {t['kept']:.2f} | {w['plain']:.2f} -> {w['kept']:.2f} | "
                     f"{t['plain'] - t['kept']:.2f} s ({(t['plain'] - t['kept']) / t['plain'] * 100:.0f} %) | "
                     f"{'yes' if r['same_bytes'] else 'no'} |")
    lines.append("")
    lines.append("The record costs the bake what one first frame spent on Lanczos and the deflation check; every "
                 "later cold frame of that material (a farm's every frame; the add-on's first frame after opening "
                 "the file) skips them and renders the same bytes.  A frame of another material, scale or pose "
                 "computes its own bounds, as before.")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--qualities", nargs="+", default=["preview", "final"])
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--out", default=None, help="markdown file whose section is (re)written")
    a = ap.parse_args(argv)
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True,
                            text=True).stdout.strip()
    with tempfile.TemporaryDirectory() as tmp:
        rows = [measure(q, a.runs, Path(tmp)) for q in a.qualities]
    command = ("python -m bench.baked_bounds" + (f" --qualities {' '.join(a.qualities)}" if a.qualities != [
        "preview", "final"] else "") + (f" --runs {a.runs}" if a.runs != 3 else "") + (f" --out {a.out}" if a.out else ""))
    return write_section(markdown(rows, command, time.strftime("%Y-%m-%d"), commit), HEADING, a.out)


if __name__ == "__main__":
    raise SystemExit(main())
