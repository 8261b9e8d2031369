"""What the benches that run the command line in-process share: the call, the engine's revision, and
writing their section of a docs file."""

from __future__ import annotations

import contextlib
import io
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


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
