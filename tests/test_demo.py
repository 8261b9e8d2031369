# SPDX-License-Identifier: GPL-3.0-or-later
"""The README's demo (demo/demo.py) in its --quick form: it bakes, solves and
renders two frames through the add-on, and the Translucency pass is there."""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest

from conftest import ROOT
from data import mesh_path



@pytest.mark.slow
def test_demo_quick_writes_frames_and_translucency_pass(addon, tmp_path):
    mesh_path("stanford-bunny")  # the demo's mesh is in the repository (raises naming it if not)
    out = tmp_path / "demo"
    env = dict(os.environ)
    env.pop("TRANSLUCENCY_KEEP_USER_RESOURCES", None)
    proc = subprocess.run(
        [sys.executable, str(ROOT / "demo" / "demo.py"), "--quick", "--output", str(out)],
        cwd=ROOT, env=env, capture_output=True, text=True, timeout=600,
    )
    log = proc.stdout + proc.stderr
    assert proc.returncode == 0, log[-4000:]

    from tools.exr import exr_pass

    passes = []
    for frame in (1, 40):
        for name in (f"frame_{frame:04d}.png", f"frame_{frame:04d}.exr", f"translucency_{frame:04d}.png"):
            path = out / name
            assert path.exists() and path.stat().st_size > 0, f"{name} missing\n{log[-2000:]}"
            assert str(path) in log, f"the demo does not print where {name} is"
        translucency = exr_pass(out / f"frame_{frame:04d}.exr", "Translucency")
        assert translucency.shape[:2] == (48, 64)
        rgb = translucency[..., :3]
        assert np.isfinite(rgb).all()
        assert (rgb.max(axis=2) > 0).mean() > 0.05, f"frame {frame}: the Translucency pass is (nearly) black"
        # The border of the image is floor and sky: the pass is zero there.
        assert not rgb[:, 0].any() and not rgb[0, :].any()
        passes.append(rgb)
    # The light moved between the frames and the handlers re-solved.
    assert not np.allclose(passes[0], passes[1])
    # It went through the add-on's operators, not around them.
    assert "baked in" in log and "solved in" in log


def test_fluid_demo_quick_renders_the_pour(addon, tmp_path):
    """demo/fluid_demo.py --quick: milk poured onto a plate through the Fluid source, two frames rendered
    with Cycles; the Translucency pass covers the milk and grows with the puddle."""
    out = tmp_path / "fluid_demo"
    env = dict(os.environ)
    env.pop("TRANSLUCENCY_KEEP_USER_RESOURCES", None)
    proc = subprocess.run([sys.executable, str(ROOT / "demo" / "fluid_demo.py"), "--quick", "--output", str(out)],
                          cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)
    log = proc.stdout + proc.stderr
    assert proc.returncode == 0, log[-4000:]

    from tools.exr import exr_pass

    covered = []
    for frame in (8, 14):
        for name in (f"frame_{frame:04d}.png", f"frame_{frame:04d}.exr", f"translucency_{frame:04d}.png"):
            assert (out / name).exists() and str(out / name) in log, f"{name}\n{log[-2000:]}"
        rgb = exr_pass(out / f"frame_{frame:04d}.exr", "Translucency")[..., :3]
        assert rgb.shape[:2] == (72, 96) and np.isfinite(rgb).all()
        assert not rgb[:, 0].any() and not rgb[:, -1].any()  # plate and sky at the sides: no pass there
        covered.append((rgb.max(axis=2) > 0).mean())
        assert f"frame {frame}: " in log and "particles ->" in log
    assert covered[0] > 0.02 and covered[1] > covered[0]  # more milk at frame 14
    assert "fluid frame 14:" in log and "view towards the camera" in log  # solved for the frame it renders
