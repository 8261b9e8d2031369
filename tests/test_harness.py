# SPDX-License-Identifier: GPL-3.0-or-later
"""The test harness itself: headless GPU start-up and the fail-not-skip rule."""

from __future__ import annotations

import re
import subprocess
import sys
import textwrap

import bpy
import pytest

from conftest import ROOT


@pytest.mark.gpu
def test_gpu_backend_starts_headless(gpu_context):
    import gpu

    assert gpu_context.error == ""
    assert gpu_context.renderer == gpu.platform.renderer_get() != ""
    assert bpy.app.background
    # A compute shader runs: write i + 1 into a 4x4 float image and read it back.
    info = gpu.types.GPUShaderCreateInfo()
    info.image(0, 'R32F', 'FLOAT_2D', "img", qualifiers={'WRITE'})
    info.local_group_size(4, 4)
    info.compute_source(
        "void main() { ivec2 p = ivec2(gl_GlobalInvocationID.xy);"
        " imageStore(img, p, vec4(float(p.y * 4 + p.x + 1))); }")
    shader = gpu.shader.create_from_info(info)
    texture = gpu.types.GPUTexture((4, 4), format='R32F')
    shader.image("img", texture)
    gpu.compute.dispatch(shader, 1, 1, 1)
    gpu.shader.unbind()
    values = [v for row in texture.read().to_list() for v in row]
    assert values == [float(i + 1) for i in range(16)]




def test_gpu_tests_fail_not_skip_when_backend_is_missing(tmp_path):
    """With GPU start-up broken, a ``gpu`` test is reported FAILED (not skipped, not error)."""
    (tmp_path / "conftest.py").write_text(textwrap.dedent(f"""
        import importlib.util, sys
        spec = importlib.util.spec_from_file_location("harness_conftest", {str(ROOT / "tests" / "conftest.py")!r})
        harness = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(harness)
        globals().update({{k: v for k, v in vars(harness).items() if not k.startswith("__")}})

        def broken_init():
            context = harness.GPUContext()
            context.error = "simulated: no GPU backend"
            return context

        harness.init_gpu_backend = broken_init
    """))
    (tmp_path / "pytest.ini").write_text("[pytest]\n")
    (tmp_path / "test_needs_gpu.py").write_text(textwrap.dedent("""
        import pytest

        @pytest.mark.gpu
        def test_marked():
            pass

        def test_uses_fixture(gpu_context):
            pass

        def test_plain():
            pass
    """))
    proc = subprocess.run([sys.executable, "-m", "pytest", "-q", "-rA", "-p", "no:cacheprovider", str(tmp_path)],
                          cwd=tmp_path, capture_output=True, text=True, timeout=300)
    out = proc.stdout + proc.stderr
    assert proc.returncode == 1, out
    assert re.search(r"\b2 failed, 1 passed in ", out), out  # no skips, no errors
    assert "FAILED test_needs_gpu.py::test_marked" in out
    assert "FAILED test_needs_gpu.py::test_uses_fixture" in out
    assert "simulated: no GPU backend" in out
