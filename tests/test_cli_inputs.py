"""The command line checks its inputs at the door and writes all or nothing (issue 32, items 3, 5 and 6).

Every bad argument or file is refused before any work with exit status 2 and
one line on stderr (no traceback), and leaves no file behind; outputs and bake
caches get the umask's permissions (0644 under umask 022), not mkstemp's 0600.
"""

from __future__ import annotations

import json
import os
import stat
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from translucency_addon import cache
from translucency_addon.geometry import meshio, primitives
from translucency_addon.errors import CacheError, MeshError

ROOT = Path(__file__).resolve().parents[1]


def cli(*args, timeout=300):
    return subprocess.run([sys.executable, "-m", "translucency_addon", *map(str, args)], cwd=ROOT,
                          capture_output=True, text=True, timeout=timeout)


def refused(out) -> str:
    """The one stderr line of a refusal (exit 2, no traceback)."""
    lines = [line for line in out.stderr.splitlines() if line.strip()]
    assert out.returncode == 2, (out.returncode, out.stderr)
    assert "Traceback" not in out.stderr and len(lines) == 1, out.stderr
    return lines[0]


def _lattice(n=6, spacing=1.0):
    g = np.stack(np.meshgrid(*[np.arange(n)] * 3, indexing="ij"), axis=-1).reshape(-1, 3) * spacing
    return g + np.random.default_rng(0).uniform(-0.1, 0.1, g.shape) * spacing


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """A baked sphere, its mesh, a particle file and files that are not what their names say."""
    d = tmp_path_factory.mktemp("inputs")
    V, F = primitives.icosphere(1.0, 2)
    meshio.save_obj(d / "s.obj", V, F)
    out = cli("bake", d / "s.obj", "-o", d / "s.npz", "--quality", "draft", "--no-optimize")
    assert out.returncode == 0, out.stderr
    np.save(d / "p.npy", _lattice())
    (d / "text.npy").write_text("1 2 3\n4 5 6\n")
    (d / "text.npz").write_text("not a cache\n")
    (d / "text.obj").write_text("v 0 0 zero\nf 1 2 3\n")
    np.save(d / "wrong.npy", np.zeros((5, 4)))
    return d


def _bad_inputs(d, out):
    """(name, argv) of every bad input the issue lists, and more; ``out`` is the (empty) output folder."""
    s, p = d / "s.npz", d / "p.npy"
    fluid = ["fluid", p, "-o", out / "phi.npz", "--radius", "1", "--mm-per-unit", "1", "--env", "1,1,1"]
    solve = ["solve", s, "-o", out / "L.npy", "--env", "1,1,1"]
    return [
        *[(f"solve mm {v}", solve + ["--mm-per-unit", v]) for v in ("0", "-3", "nan", "inf")],
        *[(f"plan mm {v}", ["plan", s, "--mm-per-unit", v]) for v in ("0", "-3", "nan")],
        *[(f"bake mm {v}", ["bake", d / "s.obj", "-o", out / "b.npz", "--mm-per-unit", v]) for v in ("0", "nan")],
        *[(f"fluid mm {v}", fluid + ["--mm-per-unit", v]) for v in ("0", "-3", "nan")],
        *[(f"fluid radius {v}", fluid + ["--radius", v]) for v in ("0", "-1", "nan")],
        ("solve tol", solve + ["--tol", "0"]), ("solve eta", solve + ["--eta", "0.5"]),
        ("solve env nan", solve + ["--env", "nan,1,1"]), ("solve sun zero", solve + ["--sun", "0,0,0:100"]),
        ("solve point negative", solve + ["--point", "0,0,3:-5"]),
        ("solve spot size 0", solve + ["--spot", "0,0,3:0,0,-1:100:0"]),
        ("solve spot blend 2", solve + ["--spot", "0,0,3:0,0,-1:100:45:2"]),
        ("solve spot zero direction", solve + ["--spot", "0,0,3:0,0,0:100:45"]),
        ("solve spot negative", solve + ["--spot", "0,0,3:0,0,-1:-5:45"]),
        ("solve spot short", solve + ["--spot", "0,0,3:100"]),
        ("solve area parallel edges", solve + ["--area", "0,0,3:1,0,0:2,0,0:100"]),
        ("solve area shape", solve + ["--area", "0,0,3:1,0,0:0,1,0:100:round"]),
        ("solve area negative", solve + ["--area", "0,0,3:1,0,0:0,1,0:-5"]),
        ("plan spot nan", ["plan", s, "--spot", "0,0,3:0,0,-1:100:nan"]), ("bake levels", ["bake", d / "s.obj", "-o",
                                                                                  out / "b.npz", "--levels", "9"]),
        ("fluid missing surface", fluid + ["--surface", d / "none.obj", "--surface-out", out / "L.npy"]),
        ("fluid surface-out alone", fluid + ["--surface-out", out / "L.npy"]),
        ("bake missing mesh", ["bake", d / "none.obj", "-o", out / "b.npz"]),
        ("bake missing inner", ["bake", d / "s.obj", "--inner", f"{d / 'none.obj'}:cavity", "-o", out / "b.npz"]),
        ("bake text mesh", ["bake", d / "text.obj", "-o", out / "b.npz"]),
        ("solve missing deformed", solve + ["--deformed", d / "none.obj"]),
        ("solve missing cache", ["solve", d / "none.npz", "-o", out / "L.npy"]),
        ("solve text cache", ["solve", d / "text.npz", "-o", out / "L.npy"]),
        ("solve npy as cache", ["solve", p, "-o", out / "L.npy"]),
        ("bake output folder", ["bake", d / "s.obj", "-o", out / "new" / "b.npz"]),
        ("solve output folder", ["solve", s, "-o", out / "new" / "L.npy"]),
        ("solve stats folder", solve + ["--stats", out / "new" / "st.json"]),
        ("solve ss-output folder", solve + ["--ss-output", out / "new" / "ss.npy"]),
        ("fluid output folder", ["fluid", p, "-o", out / "new" / "phi.npz", "--radius", "1", "--mm-per-unit", "1"]),
        ("fluid stats folder", fluid + ["--stats", out / "new" / "st.json"]),
        ("fluid surface-out folder", fluid + ["--surface", d / "s.obj", "--surface-out", out / "new" / "L.npy"]),
        ("solve same outputs", solve + ["--stats", out / "L.npy"]),
        ("fluid text npy", ["fluid", d / "text.npy", *fluid[2:]]),
        ("fluid npz", ["fluid", s, *fluid[2:]]),
        ("fluid wrong shape", ["fluid", d / "wrong.npy", *fluid[2:]]),
        ("solve missing -o", ["solve", s]),
    ]


def test_every_bad_input_is_one_line_exit_2_and_writes_nothing(files, tmp_path):
    """Each subcommand with each bad input: exit 2, one stderr line, no traceback, no file left."""
    out = tmp_path / "out"
    out.mkdir()
    for name, argv in _bad_inputs(files, out):
        before = sorted(os.listdir(files))
        line = refused(cli(*argv))
        assert line.startswith("error: "), (name, line)
        assert "allow_pickle" not in line, (name, line)
        assert os.listdir(out) == [], (name, os.listdir(out))
        assert sorted(os.listdir(files)) == before, name


def test_refusals_name_the_option_and_the_file(files, tmp_path):
    s = files / "s.npz"
    line = refused(cli("plan", s, "--mm-per-unit", "-3"))
    assert "--mm-per-unit" in line and "-3" in line and "> 0" in line
    line = refused(cli("solve", s, "-o", tmp_path / "new" / "L.npy"))
    assert f"the folder {tmp_path / 'new'} does not exist" in line
    line = refused(cli("solve", s, "-o", tmp_path / "L.npy", "--deformed", files / "posed.obj"))
    assert f"--deformed {files / 'posed.obj'}: no such file" in line
    line = refused(cli("bake", files / "text.obj", "-o", tmp_path / "b.npz"))
    assert str(files / "text.obj") in line and "malformed vertex line" in line
    line = refused(cli("solve", files / "text.npz", "-o", tmp_path / "L.npy"))
    assert str(files / "text.npz") in line and "not an .npz archive" in line


def test_help_says_what_each_option_accepts():
    texts = {sub: " ".join(cli(sub, "--help").stdout.split()) for sub in ("bake", "solve", "plan", "fluid")}
    for sub in ("bake", "solve", "plan", "fluid"):
        assert "millimetres per mesh unit, a finite number > 0" in texts[sub] or \
            "millimetres per object unit, a finite number > 0" in texts[sub], sub
    assert "in (0, 1)" in texts["solve"] and "in (0, 1)" in texts["fluid"]
    assert "in [1, 4]" in texts["solve"] and "1 to 6" in texts["bake"] and "8 to 4096" in texts["bake"]
    assert "W/m^2, >= 0" in texts["solve"] and "object units, a finite number > 0" in texts["fluid"]
    assert "existing, writable folder" in texts["fluid"] and "existing, writable folder" in texts["solve"]


# -- particle files (item 6) ---------------------------------------------------------------------------

def _fluid(tmp_path, P, *extra):
    np.save(tmp_path / "pts.npy", P)
    return cli("fluid", tmp_path / "pts.npy", "-o", tmp_path / "phi.npz", "--radius", "1", "--mm-per-unit", "2",
               "--env", "1,1,1", *extra)


def test_an_all_nan_frame_is_a_frame_without_particles(tmp_path):
    P = _lattice()
    frames = np.stack([P, np.full_like(P, np.nan), P])
    out = _fluid(tmp_path, frames, "--stats", tmp_path / "st.json")
    assert out.returncode == 0, out.stderr
    d = np.load(tmp_path / "phi.npz")
    assert d["phi"].shape == (3, len(P), 3) and not d["phi"][1].any() and d["phi"][0].min() > 0
    np.testing.assert_allclose(d["phi"][2], d["phi"][0], rtol=1e-3)
    st = json.loads((tmp_path / "st.json").read_text())
    assert f"none of the {len(P)} particles exists in this frame" in " ".join(st["frames"][1]["warnings"])
    line = refused(_fluid(tmp_path, np.full((2, 4, 3), np.nan)))
    assert "all 4 particles have NaN or Inf positions in every one of its 2 frames" in line


def test_empty_and_single_particle_files_are_refused_with_numbers(tmp_path):
    line = refused(_fluid(tmp_path, np.zeros((0, 3))))
    assert "pts.npy holds no particles (shape (0, 3))" in line and "nothing to render" in line
    line = refused(_fluid(tmp_path, np.zeros((1, 3))))
    assert "pts.npy holds a single particle" in line and "radius 1 units (2 mm)" in line and "sphere mesh" in line
    frames = np.full((2, 5, 3), np.nan)
    frames[0, 1] = frames[1, 3] = 0.0
    line = refused(_fluid(tmp_path, frames))
    assert "at most one particle with a finite position per frame (of 5)" in line
    assert not (tmp_path / "phi.npz").exists()


def test_particle_file_messages_report_the_file_and_its_own_shape(tmp_path):
    line = refused(_fluid(tmp_path, np.zeros((5, 4))))
    assert "pts.npy holds a float64 array of shape (5, 4)" in line and "(N, 3) or (F, N, 3)" in line
    (tmp_path / "pts.npy").write_text("0 0 0\n1 1 1\n")
    out = cli("fluid", tmp_path / "pts.npy", "-o", tmp_path / "phi.npz", "--radius", "1", "--mm-per-unit", "2")
    line = refused(out)
    assert f"{tmp_path / 'pts.npy'} is not a NumPy .npy file" in line and "particle positions" in line
    assert "pickle" not in line


def test_radius_message_gives_one_suggestion_in_the_users_units(tmp_path):
    from translucency_addon.fluid import suggest_radius

    P = _lattice()
    spacing = suggest_radius(P)
    line = refused(_fluid(tmp_path, P, "--radius", "50"))
    assert "pts.npy, frame 0: the particle radius 50 units is larger than the whole fluid" in line
    assert f"use --radius {spacing:.4g} (the particle spacing)" in line
    assert "suggest_radius" not in line and line.count(f"{spacing:.4g}") == 1
    line = refused(_fluid(tmp_path, P, "--radius", "5"))
    assert "times the particle spacing" in line and f"use --radius {spacing:.4g}" in line


# -- atomic writes with the umask's permissions (item 3) -----------------------------------------------

@pytest.mark.parametrize("umask, mode", [(0o022, 0o644), (0o077, 0o600), (0o002, 0o664)])
def test_outputs_and_caches_get_the_umasks_mode(tmp_path, umask, mode):
    from bakes import baked

    bake = baked("sphere")
    old = os.umask(umask)
    try:
        assert cache.umask_mode() == mode and os.umask(umask) == umask  # reading it leaves it as it was
        cache.save_bake(tmp_path / "c.npz", bake)
        cache.write_files({tmp_path / "a.npy": lambda fh: np.save(fh, np.zeros(3)),
                           tmp_path / "b.json": lambda fh: fh.write(b"{}")})
    finally:
        os.umask(old)
    for name in ("c.npz", "a.npy", "b.json"):
        assert stat.S_IMODE(os.stat(tmp_path / name).st_mode) == mode, name
    assert sorted(os.listdir(tmp_path)) == ["a.npy", "b.json", "c.npz"]  # no temporary files left


def test_cli_outputs_get_the_umasks_mode(tmp_path):
    np.save(tmp_path / "p.npy", _lattice())
    out = subprocess.run(["sh", "-c", 'umask 022 && exec "$0" "$@"', sys.executable, "-m", "translucency_addon",
                          "fluid", str(tmp_path / "p.npy"), "-o", str(tmp_path / "phi.npz"), "--radius", "1",
                          "--mm-per-unit", "1", "--env", "1,1,1", "--stats", str(tmp_path / "st.json")],
                         cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    for name in ("phi.npz", "st.json"):
        assert stat.S_IMODE(os.stat(tmp_path / name).st_mode) == 0o644, name


def test_write_files_is_all_or_nothing(tmp_path):
    (tmp_path / "a.npy").write_bytes(b"old")

    def fail(fh):
        fh.write(b"half")
        raise OSError(28, "No space left on device")

    with pytest.raises(OSError):
        cache.write_files({tmp_path / "a.npy": lambda fh: np.save(fh, np.ones(3)), tmp_path / "b.json": fail})
    assert sorted(os.listdir(tmp_path)) == ["a.npy"] and (tmp_path / "a.npy").read_bytes() == b"old"


def test_engine_refusals_name_the_file(tmp_path):
    with pytest.raises(MeshError, match="cannot read the mesh .*none.obj"):
        meshio.load_obj(tmp_path / "none.obj")
    (tmp_path / "t.npz").write_text("hello\n")
    with pytest.raises(CacheError, match=r"t\.npz' is corrupt or truncated, or not a cache at all: it is not an "
                                         r"\.npz archive"):
        cache.load_bake(tmp_path / "t.npz")
    from bakes import baked
    from translucency_addon.errors import MaterialError

    with pytest.raises(MaterialError, match=r"must be a finite number > 0 \(positive\), got -3"):
        baked("sphere").with_scale(-3.0)  # a new scale is checked where it enters, as the baked one is


def test_ss_output_without_single_scattering_is_refused_before_the_solve(files, tmp_path, monkeypatch, capsys):
    """--ss-output for a cache without single scattering (or with the term turned off) is refused when the
    cache is read, before any solve: the solver is never built."""
    from translucency_addon import __main__ as cli_main
    from translucency_addon.diffusion import solver as diffusion

    def no_solve(*args, **kwargs):
        raise AssertionError("the solver was built before the refusal")

    monkeypatch.setattr(diffusion, "DiffusionSolver", no_solve)
    base = ["solve", str(files / "s.npz"), "-o", str(tmp_path / "L.npy"), "--env", "1,1,1",
            "--ss-output", str(tmp_path / "ss.npy")]
    for extra, fact in (([], "holds no single-scattering data"), (["--no-single-scattering"], "turns that term off")):
        assert cli_main.main(base + extra) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "--ss-output" in err[0] and fact in err[0], err
    assert os.listdir(tmp_path) == []


def test_a_damaged_npy_header_is_one_line_naming_the_file(tmp_path):
    """Damaged bytes in the header's dict literal reach numpy's header parser, which raises the
    tokenizer's errors (``TokenError``, ``SyntaxError``), not ``ValueError``."""
    from translucency_addon.errors import ParticleError
    from translucency_addon.cli_fluid import load_frames

    path = tmp_path / "pts.npy"
    np.save(path, _lattice())
    good = path.read_bytes()
    for where, byte in ((12, b"'"), (20, b"("), (30, b"{")):
        path.write_bytes(good[:where] + byte + good[where + 1:])
        with pytest.raises(ParticleError, match="pts.npy is not a readable .npy array"):
            load_frames(str(path))


def test_field_values_are_checked_before_the_solve(files, tmp_path):
    """--field-values (the add-on's attribute or vertex-group field, exported): one weight in [0, 1] per
    vertex of the baked mesh; every other file, and the option without a second medium, is one line."""
    n = len(cache.load_bake(files / "s.npz").mesh_vertices)
    base = ["solve", files / "s.npz", "-o", tmp_path / "L.npy", "--env", "1,1,1"]
    w = tmp_path / "w.npy"
    cases = [
        (np.full(n - 1, 0.5), f"holds a float64 array of shape ({n - 1},); it should hold one weight from 0 to 1 "
                              f"per vertex of the baked mesh: shape ({n},)"),
        (np.r_[np.full(n - 2, 0.5), 1.5, -2.0], f"2 of {n} weights lie outside [0, 1] (worst -2)"),
        (np.r_[np.full(n - 1, 0.5), np.nan], f"1 of {n} weights are NaN or Inf"),
    ]
    for values, message in cases:
        np.save(w, values)
        line = refused(cli(*base, "--material", "marble", "--mix-with", "skin1", "--field-values", w))
        assert message in line, line
    np.save(w, np.full(n, 0.5))
    assert "name the second with --mix-with" in refused(cli(*base, "--field-values", w))
    line = refused(cli(*base, "--mix-with", "skin1", "--field-values", w, "--field", "marble:0.5"))
    assert "--field-values and --field both give the mixing field" in line
    assert not (tmp_path / "L.npy").exists()
    out = cli(*base, "--material", "marble", "--mix-with", "skin1", "--field-values", w)
    assert out.returncode == 0, out.stderr


def test_point_light_takes_an_optional_radius():
    import argparse

    from translucency_addon import cli_args

    assert cli_args.point("1,2,3:10") == ((1.0, 2.0, 3.0), 10.0, 0.0)
    pos, watts, radius = cli_args.point("1,2,3:10:0.5")
    assert radius == 0.5 and watts == 10.0
    for bad, why in (("1,2,3:10:-1", "radius must be >= 0"), ("1,2,3:10:1:2", "expected X,Y,Z:W or X,Y,Z:W:R")):
        with pytest.raises(argparse.ArgumentTypeError, match=why):
            cli_args.point(bad)
