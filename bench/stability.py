"""Numerical stability of the hard cases (issue 9): one row per case and solver.

    .venv/bin/python bench/stability.py [--cases thin_shell kappa_contrast ...] [--no-gpu] [--no-paper]
                                        [--no-passes | --only-passes] [--out docs/stability.md]

The cases are those of ``tests/hard_cases/cases.py`` (the test suite asserts
the same bounds).  Per solving case and solver the row gives: the sweeps per
level (coarse to fine), the finest level's final relative residual, the
largest ``max phi / max 4q/(1-F_dr)`` over levels (maximum principle: <= 1),
the largest outgoing / incoming power over levels and channels (energy
bound: <= 1), and pass or fail with the violated bounds.  The paper's scheme
(Jacobi, eqs. 5-9, capped at ``PAPER_MAX_ITERATIONS`` sweeps per level) is
reported, not required to pass: its rows say "report" and list what it
violates.  Rejected cases give one row per input with the error raised.

Then one row per hard case of every other pass (issue 35: particle fluids, the cavity exchange,
the Voxel Number Map, deformed graphs, the first-scatter split; ``tests/hard_cases/passes_*.py``,
judged by ``passes.evaluate`` as the tests judge them): solved within its bounds, or refused by
name with what it said.

CPU rows always; GPU rows (the compute-shader solver through Blender's
``gpu`` module, llvmpipe without a GPU) when a GPU context can be created,
after ``gpu_shaders.init_headless()`` (the 1x1 Workbench render the tests use).
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests" / "hard_cases"))
sys.path.insert(0, str(ROOT / "tests"))

import numpy as np  # noqa: E402

import cases as hc  # noqa: E402  (tests/hard_cases on the path: the module, not the package)
from hard_cases import passes  # noqa: E402  (the passes' cases: a package, for their relative imports)


def init_gpu() -> tuple[bool, str]:
    """Blender's GPU backend headless (``gpu_shaders.init_headless``): ``(ok, renderer or error)``."""
    os.environ.setdefault("BLENDER_USER_RESOURCES", tempfile.mkdtemp(prefix="translucency-bench-user-"))
    try:
        import gpu_shaders

        gpu_shaders.init_headless()
        return gpu_shaders.available()
    except Exception as ex:  # noqa: BLE001 - no Blender or no GPU: CPU rows only
        return False, f"{type(ex).__name__}: {ex}"


def solve_rows(scn, gpu: bool, paper: bool) -> list[dict]:
    rows = []
    runs = {}
    for name in ("fast", "direct") + (("paper",) if paper and scn.paper else ()) + (("gpu",) if gpu else ()):
        t0 = time.perf_counter()
        try:
            run = hc.run_solver(scn, name, q=None if name == "fast" else runs["fast"].result.q)
        except Exception as ex:  # noqa: BLE001 - a crash is a failed row, not a crashed bench
            rows.append({"case": scn.label, "solver": name, "sweeps": [], "residual": np.nan, "flux_ratio": np.nan,
                         "power_ratio": np.nan, "status": "FAIL", "why": f"{type(ex).__name__}: {ex}",
                         "seconds": time.perf_counter() - t0})
            continue
        runs[name] = run
        metrics, problems = hc.check(run, strict=name != "paper")
        if name == "gpu":
            tol = max(hc.FP16_TOL if scn.precision == "fp16" else hc.GPU_TOL, hc.residual_floor(run, -1))
            err, more = hc.compare(run, runs["fast"], tol)
            metrics["gpu_err"] = err
            problems += more
        if name == "gpu" and not problems:
            problems_note = f"|L_gpu - L_cpu| = {metrics['gpu_err']:.1e} (tol {tol:.0e})"
        else:
            problems_note = ""
        if name == "paper":
            status = "report"
            why = ("converged" if metrics["converged"] else
                   "DIVERGED" if metrics["diverged"] else f"not converged in {hc.PAPER_MAX_ITERATIONS} sweeps/level")
            if problems:
                why += "; " + "; ".join(problems)
        else:
            status = "pass" if not problems else "FAIL"
            why = "; ".join(problems) or problems_note
            if metrics.get("tol", hc.TOL) > hc.TOL:
                why = (why + "; " if why else "") + f"fp32 floor {metrics['tol']:.1e}"
        metrics.update(status=status, why=why, seconds=time.perf_counter() - t0, solver=run.solver_name)
        rows.append(metrics)
        if name == "gpu":
            run.solver.free()
    return rows


def reject_rows(rej) -> list[dict]:
    import re

    t0 = time.perf_counter()
    try:
        rej.action()
    except rej.error as ex:
        ok = re.search(rej.match, str(ex)) is not None
        why = f"{type(ex).__name__}: {ex}"
        status = "pass" if ok else "FAIL"
    except Exception as ex:  # noqa: BLE001 - any other error is the failure this row reports
        status, why = "FAIL", f"wrong error {type(ex).__name__}: {ex}"
    else:
        status, why = "FAIL", "accepted (no error)"
    return [{"case": rej.label, "solver": "reject", "sweeps": [], "residual": np.nan, "flux_ratio": np.nan,
             "power_ratio": np.nan, "status": status, "why": why, "seconds": time.perf_counter() - t0}]


def fmt(row) -> list[str]:
    def num(x, f):
        return "-" if x is None or (isinstance(x, float) and np.isnan(x)) else format(x, f)

    sweeps = "/".join(str(s) for s in row["sweeps"]) or "-"
    why = row["why"].replace("|", "\\|")
    if len(why) > 160:
        why = why[:157] + "..."
    return [row["case"], row["solver"], sweeps, num(row["residual"], ".1e"), num(row["flux_ratio"], ".4f"),
            num(row["power_ratio"], ".4f"), row["status"], why]


HEADER = ["case", "solver", "sweeps (coarse..fine)", "final residual", "max flux / max source",
          "out / in power", "result", "notes"]

PASS_HEADER = ["pass", "case", "result", "status", "bounds measured, or what the refusal said", "seconds"]


def pass_rows(select=None) -> list[passes.Row]:
    """Every pass's hard cases (``passes.all_cases``), each judged by ``passes.evaluate``."""
    rows = []
    for case in passes.all_cases():
        if select and not any(case.name.startswith(s) or case.pass_name == s for s in select):
            continue
        row = passes.evaluate(case)
        print(f"{row.pass_name} | {row.case} | {row.result} | {row.status} | {row.detail}  ({row.seconds:.1f} s)",
              flush=True)
        rows.append(row)
    return rows


def pass_table(rows) -> list[str]:
    def cell(text):
        text = str(text).replace("|", "\\|").replace("\n", " ")
        return text if len(text) <= 220 else text[:217] + "..."
    lines = ["| " + " | ".join(PASS_HEADER) + " |", "|" + "---|" * len(PASS_HEADER)]
    lines += ["| " + " | ".join([r.pass_name, r.case, r.result, r.status, cell(r.detail), f"{r.seconds:.1f}"]) + " |"
              for r in rows]
    return lines


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cases", nargs="*", default=list(hc.CASES), choices=list(hc.CASES))
    ap.add_argument("--no-gpu", action="store_true", help="CPU rows only")
    ap.add_argument("--no-paper", action="store_true", help="skip the paper's scheme (slow: Jacobi)")
    ap.add_argument("--out", help="also write the table as markdown to this file")
    which = ap.add_mutually_exclusive_group()
    which.add_argument("--no-passes", action="store_true", help="only the diffusion solve's cases")
    which.add_argument("--only-passes", nargs="*", metavar="PASS_OR_CASE",
                       help="only the other passes' cases (all, or those of these passes / case-name prefixes)")
    args = ap.parse_args(argv)
    if args.only_passes is not None:
        args.cases = []

    gpu, renderer = (False, "not requested") if args.no_gpu else init_gpu()
    print(f"GPU rows: {'yes, ' + renderer if gpu else 'no (' + renderer + ')'}", flush=True)
    rows, notes = [], []
    t_all = time.perf_counter()
    for cid in args.cases:
        t0 = time.perf_counter()
        try:
            items = hc.CASES[cid]()
        except Exception as ex:  # noqa: BLE001 - a case that cannot be built is a failed row, not a crashed bench
            rows.append({"case": cid, "solver": "build", "sweeps": [], "residual": np.nan, "flux_ratio": np.nan,
                         "power_ratio": np.nan, "status": "FAIL", "why": f"{type(ex).__name__}: {ex}"})
            print(" | ".join(fmt(rows[-1])), flush=True)
            continue
        build = time.perf_counter() - t0
        for item in items:
            if isinstance(item, hc.Rejection):
                new = reject_rows(item)
            else:
                new = solve_rows(item, gpu and item.precision in ("fp32", "fp16"), not args.no_paper)
                notes += [f"{item.label}: {n}" for n in item.notes]
            for r in new:
                print(" | ".join(fmt(r)) + f"  ({r.get('seconds', 0):.1f} s)", flush=True)
            rows += new
        print(f"  [{cid}: built in {build:.1f} s]", flush=True)
    prows = [] if args.no_passes else pass_rows(args.only_passes)
    total = time.perf_counter() - t_all
    n_fail = sum(r["status"] == "FAIL" for r in rows)
    p_fail = sum(r.status == "FAIL" for r in prows)
    lines = ["| " + " | ".join(HEADER) + " |", "|" + "---|" * len(HEADER)]
    lines += ["| " + " | ".join(fmt(r)) + " |" for r in rows]
    plines = pass_table(prows)
    summary = (f"diffusion solve: {len(rows)} rows, {n_fail} failed; other passes: {len(prows)} cases, {p_fail} "
               f"failed; GPU: {renderer if gpu else 'none'}; tol {hc.TOL:g}; {total:.0f} s")
    print("\n" + "\n".join(lines) + "\n\n" + "\n".join(plines) + "\n\n" + summary)
    if notes:
        print("\nNotes:\n" + "\n".join(f"- {n}" for n in notes))
    if args.out:
        text = "# Stability of the hard cases (bench/stability.py)\n\n"
        if rows:
            text += "## The QuadGraph diffusion solve\n\n" + "\n".join(lines) + "\n\n"
        if prows:
            text += ("## Every other pass (issue 35)\n\nEach case solves within its bounds or is refused by name "
                     "(`tests/hard_cases/passes_*.py`; the tests assert the same rows).\n\n"
                     + "\n".join(plines) + "\n\n")
        text += summary + "\n"
        if notes:
            text += "\nNotes:\n\n" + "\n".join(f"- {n}" for n in notes) + "\n"
        Path(args.out).write_text(text)
    return 1 if n_fail or p_fail else 0


if __name__ == "__main__":
    sys.exit(main())
