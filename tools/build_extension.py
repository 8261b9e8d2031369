#!/usr/bin/env python3
# SPDX-License-Identifier: GPL-3.0-or-later
"""Build the Translucency extension zip.

1. Download the bundled wheels (pytetwild, fast_simplification, scipy; numba
   and llvmlite where PyPI has them, for the fluid cells' compiled faces; never
   numpy, which Blender ships) for every platform PyPI has them for and for
   every Python a supported Blender ships (``PYTHONS``: 3.11 for Blender
   4.2-5.0, 3.13 for 5.1-5.2), with ``pip download --only-binary=:all:
   --no-deps --python-version X.Y``.  The versions are the pins in
   ``requirements-test.txt``.  A platform that lacks one of the wheels for
   one of the Pythons is skipped with a message; Linux x86-64 is required.

   One zip serves every supported Blender: Blender reads the Python versions
   from the wheels' tags (``python_versions`` in the built package is their
   union, so 5.2 no longer refuses it as "isn't compatible with (3.11)") and,
   when it installs, unpacks only the wheels that match its own Python and
   platform.  By default the build writes **one zip per platform** (Blender's
   ``build --split-platforms``), each still serving both Pythons: what the
   extensions platform expects, and a quarter of the download.
   ``--all-platforms-zip`` writes the single zip with every platform's
   wheels instead (one file for every machine, about four times larger).
   numba and llvmlite make a zip 2.4-2.6x larger (linux-x64: 74 -> 195 MiB,
   macos-arm64: 59 -> 142 MiB, windows-x64: 75 -> 160 MiB; macos-x64 has no
   numba wheel and stays 66 MiB); ``--without-compiled`` leaves them out.
2. Check each wheel's ``Requires-Dist``: nothing may be needed besides numpy.
3. Rewrite ``platforms`` and ``wheels`` in ``blender_manifest.toml``.
4. Build the zip with Blender's own ``blender_ext.py build`` (it ships inside
   the bpy wheel) and check it with ``blender_ext.py validate``.
5. Check that the zip holds only the extension.

Usage::

    .venv/bin/python tools/build_extension.py                  # one zip per platform -> dist/
    .venv/bin/python tools/build_extension.py --all-platforms-zip   # one zip for every platform
    .venv/bin/python tools/build_extension.py --platforms linux-x64
    .venv/bin/python tools/build_extension.py --offline        # reuse wheels/ only
    .venv/bin/python tools/build_extension.py --without-compiled   # no numba: zips 2.4-2.6x smaller

Downloaded wheels are kept in ``wheels/`` (git-ignored), so a second run does
not download again.  The last lines printed are a summary; ``--json`` writes it
to a file as well.
"""

from __future__ import annotations

import argparse
import contextlib
import email.parser
import glob
import importlib.util
import json
import os
import re
import subprocess
import sys
import time
import zipfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
MANIFEST = ROOT / "blender_manifest.toml"
REQUIREMENTS = ROOT / "requirements-test.txt"
WHEELS_DIR = ROOT / "wheels"

# The Python of each supported Blender series, and its CPython ABI tag.
PYTHONS = (
    ("3.11", "cp311"),  # Blender 4.2 LTS, 4.5 LTS, 5.0
    ("3.13", "cp313"),  # Blender 5.1, 5.2 LTS
)

# Bundled distributions (import names differ only by dash/underscore).
BUNDLED = ("pytetwild", "fast_simplification", "scipy")
# Bundled where PyPI has them for the platform and both Pythons, else left out of that platform's zip: the
# Voronoi-fluid cells' compiled faces (translucency_addon/fluid/compiled_faces.py), whose numpy path runs
# without them and says so.  numba has no macOS x86-64 wheel.
COMPILED = ("numba", "llvmlite")
# What a bundled wheel may require: Blender ships numpy (and the other bundled wheels of its platform).
ALLOWED_REQUIREMENTS = {"numpy"}
# Fallback pins, used only if requirements-test.txt is missing a line.
DEFAULT_PINS = {"pytetwild": "0.2.3", "fast_simplification": "0.2.0", "scipy": "1.17.1", "numba": "0.68.1",
                "llvmlite": "0.50.0"}

# Blender platform -> groups of pip --platform tags, tried in order for each
# wheel; the first group that yields a wheel wins.  Older tags come first so the
# zip runs on the oldest OS a wheel supports (Blender 4.2 needs glibc 2.28 and
# macOS 11.2).  pip expands a macOS tag to older macOS versions itself, but not
# manylinux_2_X tags, so those are listed.
PLATFORM_TAGS: dict[str, list[list[str]]] = {
    "linux-x64": [[
        "manylinux_2_28_x86_64", "manylinux_2_27_x86_64", "manylinux_2_26_x86_64",
        "manylinux_2_24_x86_64", "manylinux_2_17_x86_64", "manylinux2014_x86_64",
        "manylinux2010_x86_64", "manylinux1_x86_64",
    ]],
    "windows-x64": [["win_amd64"]],
    "macos-arm64": [["macosx_11_0_arm64"], ["macosx_12_0_arm64"], ["macosx_13_0_arm64"],
                    ["macosx_14_0_arm64"], ["macosx_15_0_arm64"], ["macosx_26_0_arm64"]],
    "macos-x64": [["macosx_11_0_x86_64"], ["macosx_12_0_x86_64"], ["macosx_13_0_x86_64"],
                  ["macosx_14_0_x86_64"], ["macosx_15_0_x86_64"], ["macosx_26_0_x86_64"]],
}
REQUIRED_PLATFORMS = ("linux-x64",)

# Top-level entries the zip may contain (directories end with "/").
ALLOWED_TOP_LEVEL = {
    "__init__.py", "blender_manifest.toml", "LICENSE",
    "translucency_addon/", "ops/", "gpu_shaders/", "wheels/",
}


class BuildError(RuntimeError):
    pass


def log(msg: str) -> None:
    print(msg, flush=True)


def normalise(name: str) -> str:
    return re.sub(r"[-_.]+", "_", name).lower()


def read_pins() -> dict[str, str]:
    pins = dict(DEFAULT_PINS)
    if REQUIREMENTS.exists():
        for line in REQUIREMENTS.read_text().splitlines():
            line = line.split("#", 1)[0].strip()
            m = re.fullmatch(r"([A-Za-z0-9_.\-]+)\s*==\s*([^\s;]+)", line)
            if m and normalise(m.group(1)) in BUNDLED + COMPILED:
                pins[normalise(m.group(1))] = m.group(2)
    return pins


# -- wheels ---------------------------------------------------------------------

def wheel_platform_tag(filename: str) -> str:
    return Path(filename).stem.split("-")[-1]


def abi_matches(python_tag: str, abi_tag: str, abi: str) -> bool:
    """A wheel with these tags runs on CPython ``abi`` (e.g. cp313): its own ABI, or the stable
    ABI (abi3) of a CPython no newer than it."""
    if abi in python_tag.split("."):
        return True
    if "abi3" not in abi_tag.split("."):
        return False
    target = int(abi[2:])
    return any(t.startswith("cp") and t[2:].isdigit() and int(t[2:]) <= target for t in python_tag.split("."))


def wheel_matches(filename: str, dist: str, version: str, tags: list[str], abi: str) -> bool:
    """True if ``filename`` is a wheel of dist==version for CPython ``abi`` and one of the pip ``tags``."""
    parts = Path(filename).stem.split("-")
    if len(parts) < 5 or normalise(parts[0]) != dist or parts[1] != version:
        return False
    if not abi_matches(parts[-3], parts[-2], abi):
        return False
    wheel_tags = parts[-1].split(".")
    for tag in tags:
        m = re.fullmatch(r"macosx_(\d+)_(\d+)_(\w+)", tag)
        for wt in wheel_tags:
            if wt == tag:
                return True
            if m:  # pip accepts older macOS builds for the same (or universal2) arch
                wm = re.fullmatch(r"macosx_(\d+)_(\d+)_(\w+)", wt)
                if wm and (int(wm.group(1)), int(wm.group(2))) <= (int(m.group(1)), int(m.group(2))) \
                        and wm.group(3) in (m.group(3), "universal2"):
                    return True
    return False


def find_cached(dist: str, version: str, tags: list[str], abi: str) -> Path | None:
    for path in sorted(WHEELS_DIR.glob("*.whl")):
        if wheel_matches(path.name, dist, version, tags, abi):
            return path
    return None


def pip_download(dist: str, version: str, tags: list[str], dest: Path, python: str, abi: str
                 ) -> tuple[Path | None, str]:
    """Download one wheel into ``dest``; return (path or None, pip's last error line)."""
    before = set(dest.glob("*.whl"))
    cmd = [sys.executable, "-m", "pip", "download", "--only-binary=:all:", "--no-deps",
           "--disable-pip-version-check", "--quiet", "--python-version", python,
           "--implementation", "cp", "--abi", abi, "-d", str(dest)]
    for tag in tags:
        cmd += ["--platform", tag]
    cmd.append(f"{dist}=={version}")
    proc = subprocess.run(cmd, capture_output=True, text=True)
    new = sorted(set(dest.glob("*.whl")) - before)
    found = [p for p in dest.glob("*.whl") if wheel_matches(p.name, dist, version, tags, abi)]
    if proc.returncode == 0 and (new or found):
        return (new or found)[0], ""
    errors = [line for line in (proc.stderr or "").splitlines() if line.startswith("ERROR")]
    return None, (errors[-1] if errors else (proc.stderr or "").strip()[-300:])


def wheel_requirements(path: Path) -> list[str]:
    """Requires-Dist entries of a wheel that apply without extras."""
    with zipfile.ZipFile(path) as zf:
        meta_name = next(n for n in zf.namelist() if n.endswith(".dist-info/METADATA"))
        meta = email.parser.Parser().parsestr(zf.read(meta_name).decode("utf-8", "replace"))
    needed = []
    for req in meta.get_all("Requires-Dist") or []:
        try:
            from packaging.requirements import Requirement
            r = Requirement(req)
            if r.marker is not None and not r.marker.evaluate({"extra": ""}):
                continue
            needed.append(normalise(r.name))
        except ImportError:
            name, _, marker = req.partition(";")
            if "extra" in marker:
                continue
            needed.append(normalise(re.split(r"[\s<>=!~\[(]", name.strip(), maxsplit=1)[0]))
    return needed


def _platform_wheels(platform: str, dists: tuple, pins: dict[str, str], offline: bool) -> tuple[dict, str]:
    """({"dist cpXY": wheel path}, '') when ``platform`` has every wheel of ``dists`` for every Python, else
    ({}, what is missing)."""
    chosen: dict[str, Path] = {}
    for python, abi in PYTHONS:
        for dist in dists:
            version = pins[dist]
            path, error = None, "not in wheels/ (offline)"
            for tags in PLATFORM_TAGS[platform]:  # reuse a downloaded wheel first
                path = find_cached(dist, version, tags, abi)
                if path is not None:
                    break
            if path is None and not offline:
                for tags in PLATFORM_TAGS[platform]:
                    path, error = pip_download(dist, version, tags, WHEELS_DIR, python, abi)
                    if path is not None:
                        break
            if path is None:
                missing = f"{dist}=={version} for Python {python}"
                log(f"  {platform:12s} {missing}: no wheel ({error})")
                return {}, missing
            chosen[f"{dist} {abi}"] = path
            log(f"  {platform:12s} {abi} {path.name} ({path.stat().st_size / 2**20:.1f} MiB)")
    return chosen, ""


def collect_wheels(platforms: list[str], pins: dict[str, str], offline: bool,
                   without_compiled: dict | None = None, compiled: bool = True) -> dict[str, dict[str, Path]]:
    """{platform: {"dist cpXY": wheel path}} for the platforms that have every wheel of ``BUNDLED`` for every
    Python, with the ``COMPILED`` wheels where they have those too (else ``without_compiled[platform]`` says
    which is missing)."""
    WHEELS_DIR.mkdir(exist_ok=True)
    result: dict[str, dict[str, Path]] = {}
    for platform in platforms:
        chosen, missing = _platform_wheels(platform, BUNDLED, pins, offline)
        if missing:
            if platform in REQUIRED_PLATFORMS:
                raise BuildError(f"the {platform} wheels are required, but {missing} has none")
            log(f"  {platform}: skipped (no wheel of {missing})")
            continue
        extra, missing = _platform_wheels(platform, COMPILED, pins, offline) if compiled else ({}, "--without-compiled")
        if missing:
            log(f"  {platform}: without the compiled cells ({missing}; the numpy path runs there)")
            if without_compiled is not None:
                without_compiled[platform] = missing
        result[platform] = {**chosen, **extra}
    return result


def check_requirements(wheels: dict[str, dict[str, Path]]) -> None:
    for per_platform in wheels.values():
        bundled = {key.split(" ", 1)[0] for key in per_platform}
        for path in per_platform.values():
            extra = [r for r in wheel_requirements(path) if r not in ALLOWED_REQUIREMENTS | bundled]
            if extra:
                raise BuildError(f"{path.name} requires {', '.join(extra)}, which the extension does not bundle")


# -- manifest ----------------------------------------------------------------------

def _replace_list(text: str, key: str, values: list[str]) -> str:
    if len(values) <= 2:
        body = "[" + ", ".join(json.dumps(v) for v in values) + "]"
    else:
        body = "[\n" + "".join(f"  {json.dumps(v)},\n" for v in values) + "]"
    pattern = re.compile(rf"^{key}\s*=\s*\[.*?\]", re.S | re.M)
    if not pattern.search(text):
        raise BuildError(f"blender_manifest.toml has no top-level `{key} = [...]` list to rewrite")
    return pattern.sub(lambda _m: f"{key} = {body}", text, count=1)


def write_manifest(wheels: dict[str, dict[str, Path]]) -> list[str]:
    platforms = [p for p in PLATFORM_TAGS if p in wheels]
    files = sorted({p.name for per in wheels.values() for p in per.values()})
    text = MANIFEST.read_text()
    new = _replace_list(text, "platforms", platforms)
    new = _replace_list(new, "wheels", [f"./wheels/{name}" for name in files])
    if new != text:
        MANIFEST.write_text(new)
        log(f"updated {MANIFEST.name}: platforms {platforms}, {len(files)} wheels")
    else:
        log(f"{MANIFEST.name} already lists these platforms and wheels")
    return files


def remove_unlisted_wheels(keep: list[str]) -> None:
    """blender_ext.py packs every file under wheels/, so drop the ones not listed."""
    for path in WHEELS_DIR.glob("*.whl"):
        if path.name not in keep:
            path.unlink()


# -- Blender's extension tool ---------------------------------------------------------

def find_blender_ext() -> Path:
    override = os.environ.get("BLENDER_EXT_PY")
    if override:
        return Path(override)
    candidates = []
    if "bpy" in sys.modules and getattr(sys.modules["bpy"], "utils", None):
        import bpy  # running inside Blender
        candidates.append(Path(bpy.utils.system_resource('SCRIPTS')))
    spec = importlib.util.find_spec("bpy")
    if spec is not None:
        for location in spec.submodule_search_locations or [os.path.dirname(spec.origin or "")]:
            candidates += [Path(p) for p in glob.glob(os.path.join(location, "*", "scripts"))]
    for scripts in candidates:
        tool = scripts / "addons_core" / "bl_pkg" / "cli" / "blender_ext.py"
        if tool.exists():
            return tool
    raise BuildError("cannot find blender_ext.py: install bpy (bash tools/setup.sh) or set BLENDER_EXT_PY")


def run_tool(tool: Path, *args: str) -> str:
    proc = subprocess.run([sys.executable, str(tool), *args], capture_output=True, text=True)
    output = (proc.stdout + proc.stderr).strip()
    if proc.returncode != 0:
        raise BuildError(f"blender_ext.py {args[0]} failed:\n{output}")
    return output


def check_zip_contents(zip_path: Path, listed: list[str]) -> list[str]:
    """The zip holds only the extension, and under wheels/ only the listed wheels."""
    with zipfile.ZipFile(zip_path) as zf:
        names = zf.namelist()
    top = sorted({n.split("/", 1)[0] + ("/" if "/" in n else "") for n in names})
    unexpected = [t for t in top if t not in ALLOWED_TOP_LEVEL]
    junk = [n for n in names if "__pycache__" in n or n.endswith(".pyc")]
    junk += [n for n in names if n.startswith("wheels/") and n != "wheels/" and n[len("wheels/"):] not in listed]
    if unexpected or junk:
        raise BuildError(
            f"{zip_path.name} holds files that are not part of the extension: {unexpected + junk[:5]}; "
            "add them to [build] paths_exclude_pattern in blender_manifest.toml")
    for required in ("__init__.py", "blender_manifest.toml", "LICENSE", "ops/", "translucency_addon/", "wheels/"):
        if required not in top:
            raise BuildError(f"{zip_path.name} lacks {required}")
    return top


@contextlib.contextmanager
def build_lock():
    """Serialise builds in one checkout (tests and people may build at once)."""
    import hashlib
    import tempfile
    key = hashlib.sha1(str(ROOT).encode()).hexdigest()[:12]
    with open(Path(tempfile.gettempdir()) / f"translucency-build-{key}.lock", "w") as fh:
        try:
            import fcntl
            fcntl.flock(fh, fcntl.LOCK_EX)
        except ImportError:  # Windows: no lock
            pass
        yield


def build(platforms: list[str], output_dir: Path, offline: bool = False, split: bool = True,
          compiled: bool = True) -> dict:
    start = time.time()
    pins = read_pins()
    log(f"bundled wheels: {', '.join(f'{d}=={v}' for d, v in pins.items() if d in BUNDLED + COMPILED)} "
        f"(for {', '.join(abi for _py, abi in PYTHONS)}; numpy is not bundled, Blender ships it)")
    with build_lock():
        without_compiled: dict = {}
        wheels = collect_wheels(platforms, pins, offline, without_compiled, compiled)
        check_requirements(wheels)
        files = write_manifest(wheels)
        remove_unlisted_wheels(files)
        tool = find_blender_ext()
        output_dir.mkdir(parents=True, exist_ok=True)
        before = {p: p.stat().st_mtime for p in output_dir.glob("*.zip")}
        args = ["build", "--source-dir", str(ROOT), "--output-dir", str(output_dir)]
        if split:
            args.append("--split-platforms")
        build_started = time.time()
        log(run_tool(tool, *args).splitlines()[-1])
        zips = sorted(p for p in output_dir.glob("translucency-*.zip")
                      if p not in before or p.stat().st_mtime >= build_started - 1)
        if not zips:
            raise BuildError(f"blender_ext.py build wrote no zip to {output_dir}")
        for zip_path in zips:
            log(run_tool(tool, "validate", str(zip_path)).splitlines()[-1] + f" ({zip_path.name})")
            check_zip_contents(zip_path, files)
    summary = {
        "zips": [str(p) for p in zips],
        "zip_sizes_mib": {p.name: round(p.stat().st_size / 2**20, 1) for p in zips},
        "platforms": list(wheels),
        "wheels": {platform: sorted({p.name for p in per.values()}) for platform, per in wheels.items()},
        "pythons": [py for py, _abi in PYTHONS],
        "skipped_platforms": [p for p in platforms if p not in wheels],
        "without_compiled": without_compiled,
        "blender_ext": str(tool),
        "seconds": round(time.time() - start, 1),
    }
    log("summary:")
    for platform, names in summary["wheels"].items():
        log(f"  {platform}: {', '.join(names)}")
    for platform in summary["skipped_platforms"]:
        log(f"  {platform}: skipped, PyPI lacks a wheel")
    for platform, missing in without_compiled.items():
        log(f"  {platform}: without numba ({missing}): the fluid cells take the numpy path there")
    for name, size in summary["zip_sizes_mib"].items():
        log(f"  {output_dir / name}: {size} MiB")
    return summary


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n", 1)[0])
    parser.add_argument("--platforms", default=",".join(PLATFORM_TAGS),
                        help=f"comma-separated Blender platforms (default: {','.join(PLATFORM_TAGS)})")
    parser.add_argument("--output-dir", type=Path, default=ROOT / "dist", help="where the zips go (default: dist/)")
    parser.add_argument("--offline", action="store_true", help="use only wheels already in wheels/")
    shape = parser.add_mutually_exclusive_group()
    shape.add_argument("--split-platforms", dest="split", action="store_true", default=True,
                       help="one zip per platform (the default; what the extensions platform expects)")
    shape.add_argument("--all-platforms-zip", dest="split", action="store_false",
                       help="one zip holding every platform's wheels instead (about 4x the size of one platform's)")
    parser.add_argument("--without-compiled", dest="compiled", action="store_false",
                        help="leave numba and llvmlite out (each zip ~40-120 MiB smaller; the fluid cells then take "
                             "their numpy path, about 4x slower)")
    parser.add_argument("--json", type=Path, help="also write the summary to this JSON file")
    args = parser.parse_args(argv)
    platforms = [p.strip() for p in args.platforms.split(",") if p.strip()]
    unknown = [p for p in platforms if p not in PLATFORM_TAGS]
    if unknown:
        parser.error(f"unknown platform(s) {unknown}; choose from {list(PLATFORM_TAGS)}")
    for required in REQUIRED_PLATFORMS:
        if required not in platforms:
            platforms.insert(0, required)
    try:
        summary = build(platforms, args.output_dir.resolve(), offline=args.offline, split=args.split,
                        compiled=args.compiled)
    except BuildError as ex:
        print(f"build_extension: error: {ex}", file=sys.stderr)
        return 1
    if args.json:
        args.json.write_text(json.dumps(summary, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
