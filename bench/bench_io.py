"""What the benches that run the command line in-process share: the call, the engine's revision, and
writing their section of a docs file."""

from __future__ import annotations

import contextlib
import io
import json
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
DATA = ROOT / "bench" / "data"  # where benches keep the numbers of their last run (their sections' source)


def cli(args) -> None:
    """``python -m translucency_addon ARGS`` in this process; raises with the tail of its output on failure."""
    from translucency_addon.__main__ import main

    out = io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(out):
        rc = main([str(a) for a in args])
    if rc:
        raise RuntimeError(f"translucency_addon {' '.join(map(str, args))} failed ({rc}):\n{out.getvalue()[-2000:]}")


def commit() -> str:
    """The short hash of the checked-out revision (the engine a run measured)."""
    return subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True,
                          text=True).stdout.strip()


def command(module: str, quick: bool = False, out=None) -> str:
    """The command line a docs section names: ``python -m bench.MODULE [--quick] [--out OUT]``."""
    return f"python -m bench.{module}" + (" --quick" if quick else "") + (f" --out {out}" if out else "")


def save_results(name: str, results: dict) -> None:
    """Keep a run's numbers as ``bench/data/NAME`` (JSON), so its section can be written again unrun."""
    DATA.mkdir(exist_ok=True)
    (DATA / name).write_text(json.dumps(results, indent=1) + "\n")


def load_results(name: str) -> dict:
    return json.loads((DATA / name).read_text())


def sphere_obj(folder, radius_mm: float) -> Path:
    """An icosphere of ``radius_mm`` (2,562 vertices) written as ``folder/sphere.obj``, the benches' sphere."""
    from translucency_addon.geometry import meshio, primitives

    path = Path(folder) / "sphere.obj"
    V, F = primitives.icosphere(radius_mm, 4)
    meshio.save_obj(path, V, F)
    return path


def write_file(text: str, out_path) -> int:
    """Print ``text`` and, with ``out_path``, write it as that whole file; returns 0 (the benches' exit status)."""
    print(text)
    if out_path:
        Path(out_path).write_text(text)
    return 0


def write_section(text: str, heading: str, out_path) -> int:
    """Print ``text`` (a section starting with ``heading``) and, with ``out_path``, (re)write that section
    of the markdown file; returns 0 (the benches' exit status)."""
    print(text)
    if out_path:
        from bench.accuracy_text import replace_section

        out = Path(out_path)
        old = out.read_text() if out.exists() else ""
        body = text[len(heading):].rstrip("\n") + "\n\n"  # a blank line before the next section
        out.write_text(replace_section(old, heading, body).rstrip("\n") + "\n")
    return 0
