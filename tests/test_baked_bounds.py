"""The spectral bounds a bake keeps (diffusion/baked_bounds.py): a cold frame of the baked material runs no
Lanczos and renders the same radiance bit for bit; any other system computes its own; the cache keeps the
record and refuses a malformed one; the bake command keeps them for its material (marble by default)."""

from __future__ import annotations

import json
import subprocess
import sys
from dataclasses import replace

import numpy as np
import pytest

from bakes import baked
from translucency_addon import cache
from translucency_addon.diffusion import spectral
from translucency_addon.diffusion.baked_bounds import adopt_bounds, with_kept_bounds
from translucency_addon.diffusion.solver import DiffusionSolver, SolveOptions
from translucency_addon.errors import CacheError
from translucency_addon.geometry import meshio, primitives
from translucency_addon.scene.lights import Environment, Light
from translucency_addon.scene.materials import material_from_preset

SUN = [Light(kind="sun", direction=(0.3, 0.2, -1.0), irradiance=3.0)]
SKY = Environment((0.1, 0.1, 0.1))


def _solve(bake, material, calls):
    solver = DiffusionSolver(bake, material, None, SolveOptions())
    before = len(calls)
    L = solver.vertex_radiance(solver.solve(SUN, SKY))
    return solver, L, len(calls) - before


def _chebyshev_levels(bake, material) -> int:
    """The levels whose default solve is Chebyshev, which needs the bounds (CG, on the large ones where its
    compiled step runs, does not: iterative.prefers_cg)."""
    from translucency_addon.diffusion.iterative import prefers_cg

    return sum(not prefers_cg(s) for s in DiffusionSolver(bake, material, None, SolveOptions()).systems)


@pytest.fixture
def lanczos_calls(monkeypatch):
    calls = []
    real = spectral.lanczos_lower

    def counted(system, *a, **k):
        calls.append(system.n)
        return real(system, *a, **k)

    monkeypatch.setattr(spectral, "lanczos_lower", counted)
    return calls


def test_a_kept_record_spares_the_frame_its_lanczos_and_changes_nothing(lanczos_calls):
    marble = material_from_preset("marble")
    plain = replace(baked("sphere"), spectral_bounds=None)
    kept = with_kept_bounds(plain, marble)
    assert "spectral bounds" in kept.stats["timings"]
    solver, L_kept, runs = _solve(kept, marble, lanczos_calls)
    assert solver.bounds_from_bake == len(plain.levels) and runs == 0
    solver, L_plain, runs = _solve(plain, marble, lanczos_calls)
    assert solver.bounds_from_bake == 0 and runs == _chebyshev_levels(plain, marble) > 0
    np.testing.assert_array_equal(L_kept, L_plain)


def test_another_material_scale_or_pose_computes_its_own(lanczos_calls):
    kept = with_kept_bounds(replace(baked("sphere"), spectral_bounds=None), material_from_preset("marble"))
    for bake, material in ((kept, material_from_preset("skin1")), (kept.with_scale(kept.mm_per_unit * 1.5),
                                                                   material_from_preset("marble"))):
        solver, L, runs = _solve(bake, material, lanczos_calls)
        assert solver.bounds_from_bake == 0 and runs == _chebyshev_levels(bake, material) > 0 and np.all(np.isfinite(L))
    # the bake keeps none where a frame's systems do not come from the material alone
    heterogeneous = material_from_preset("marble", mix_with="skin1")
    plain = replace(kept, spectral_bounds=None)
    assert with_kept_bounds(plain, heterogeneous) is plain
    assert with_kept_bounds(replace(plain, composite=object()), material_from_preset("marble")).spectral_bounds is None
    # bounds a caller already set (a pose carries the last frame's) are left as they are
    solver = DiffusionSolver(kept, material_from_preset("marble"))
    systems = [replace(s, lam_min=s.lam_min * 0.5, cache={}) for s in solver.systems]
    assert adopt_bounds(systems, kept.spectral_bounds) == 0
    assert all(np.array_equal(a.lam_min, 0.5 * b.lam_min) for a, b in zip(systems, solver.systems))


def test_the_cache_keeps_the_record_and_refuses_a_malformed_one(tmp_path):
    kept = with_kept_bounds(replace(baked("sphere"), spectral_bounds=None), material_from_preset("marble"))
    path = cache.save_bake(tmp_path / "k.npz", kept)
    back = cache.load_bake(path).spectral_bounds
    assert back.keys() == kept.spectral_bounds.keys()
    for k, v in kept.spectral_bounds.items():
        np.testing.assert_array_equal(back[k], v)
    assert cache.load_bake(cache.save_bake(tmp_path / "p.npz", replace(kept, spectral_bounds=None))).spectral_bounds is None
    for key, value in (("spectral/0/lam_min", np.array([-1.0, 0.1, 0.1])), ("spectral/1/lam_max", np.array([np.nan] * 3))):
        arrays = dict(np.load(path))
        arrays[key] = value
        np.savez(tmp_path / "bad.npz", **arrays)
        with pytest.raises(CacheError, match="spectral bounds are corrupt"):
            cache.load_bake(tmp_path / "bad.npz")
    arrays = dict(np.load(path))
    del arrays["spectral/0/no_deflation"]
    np.savez(tmp_path / "bad.npz", **arrays)
    with pytest.raises(CacheError, match="lacks no_deflation"):
        cache.load_bake(tmp_path / "bad.npz")


def test_the_bake_command_keeps_them_for_its_material_only(tmp_path):
    V, F = primitives.icosphere(1.0, 3)
    meshio.save_obj(tmp_path / "s.obj", V, F)

    def bake(*extra):
        out = tmp_path / f"b{len(extra)}.npz"
        r = subprocess.run([sys.executable, "-m", "translucency_addon", "bake", str(tmp_path / "s.obj"), "-o", str(out),
                            "--quality", "draft", "--no-optimize", "--mm-per-unit", "10", "--json", *extra],
                           capture_output=True, text=True)
        assert r.returncode == 0, r.stderr
        return cache.load_bake(out), json.loads(r.stdout)

    kept, stats = bake("--material", "skin1")
    assert "spectral bounds" in stats["timings"]
    assert DiffusionSolver(kept, material_from_preset("skin1")).bounds_from_bake == len(kept.levels)
    assert DiffusionSolver(kept, material_from_preset("marble")).bounds_from_bake == 0
    plain, stats = bake()  # the command's default material, marble, as for its transport tables
    assert DiffusionSolver(plain, material_from_preset("marble")).bounds_from_bake == len(plain.levels)
    r = subprocess.run([sys.executable, "-m", "translucency_addon", "solve", str(tmp_path / "b0.npz"), "-o",
                        str(tmp_path / "L.npy"), "--env", "1,1,1", "--stats", str(tmp_path / "st.json")],
                       capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert json.loads((tmp_path / "st.json").read_text())["spectral_bounds_from_bake"] == len(plain.levels)
