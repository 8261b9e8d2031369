# SPDX-License-Identifier: GPL-3.0-or-later
"""The engine's house (docs/architecture.md, "The engine's floors"): each package or top-level module of
``translucency_addon`` imports only units on lower floors, module-level and lazy imports alike, so a reader
finds where a frame's data goes by following the folders down (issue 29, item 5)."""

from __future__ import annotations

import ast
from pathlib import Path

ENGINE = Path(__file__).resolve().parent.parent / "translucency_addon"

# Top floor first.  A unit is a subpackage (its modules import each other freely) or a top-level module.
FLOORS = (
    ("__main__",),
    ("cli_solve", "cli_fluid"),
    ("cli_args",),
    ("frame", "progressive"),
    ("planner",),
    ("planner_messages", "planner_changes", "planner_facts"),
    ("planner_rules", "cache"),
    ("inner_parts",),
    ("voxel_number_map",),
    ("single_scattering", "deformation", "fluid"),
    ("quadgraph",),
    ("diffusion",),
    ("scene",),
    ("geometry",),
    ("errors", "compiled", "__init__"),
)


def unit(path: Path) -> str:
    rel = path.relative_to(ENGINE)
    return rel.parts[0] if len(rel.parts) > 1 else rel.stem


def imports(path: Path) -> set[str]:
    """The engine units ``path`` imports (relative imports at any depth, ``from . import x`` included)."""
    rel = path.relative_to(ENGINE).with_suffix("")
    package = list(rel.parts[:-1])  # the module's package inside the engine
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.level:
            base = package[: len(package) - (node.level - 1)] if node.level > 1 else package
            target = base + (node.module.split(".") if node.module else [])
            targets = [target] if node.module else [target + [a.name] for a in node.names]
            found.update(t[0] for t in targets if t)
    return found - {"__version__"}


def test_every_engine_unit_has_a_floor():
    on_floors = {u for floor in FLOORS for u in floor}
    units = {unit(p) for p in ENGINE.rglob("*.py")}
    assert units == on_floors, f"without a floor: {sorted(units - on_floors)}; gone: {sorted(on_floors - units)}"


def test_engine_imports_go_down_never_up():
    floor_of = {u: i for i, floor in enumerate(FLOORS) for u in floor}
    upward = sorted({(unit(p), dep) for p in ENGINE.rglob("*.py") for dep in imports(p)
                     if dep != unit(p) and dep in floor_of and floor_of[dep] <= floor_of[unit(p)]})
    assert upward == [], f"imports to the same or a higher floor: {upward}"


def test_the_engine_does_not_import_blender_or_the_add_on():
    """io_scene_psk_psa's rule: the core runs without bpy (the CLI, the benches, a farm's plain Python)."""
    offenders = []
    for p in ENGINE.rglob("*.py"):
        for node in ast.walk(ast.parse(p.read_text())):
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else \
                [node.module or ""] if isinstance(node, ast.ImportFrom) and not node.level else []
            offenders += [f"{p.relative_to(ENGINE)}: {n}" for n in names
                          if n.split(".")[0] in ("bpy", "mathutils", "gpu", "bmesh", "ops", "gpu_shaders")]
    assert offenders == []
