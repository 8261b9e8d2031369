# SPDX-License-Identifier: GPL-3.0-or-later
"""The Blender side's house (docs/architecture.md, "How a frame flows"): each module imports only
modules on lower floors, module-level and lazy imports alike, and re-exports nobody's names."""

from __future__ import annotations

import ast
from pathlib import Path

OPS = Path(__file__).resolve().parent.parent / "ops"

# Top floor first; a module may import only modules on floors below its own.
FLOORS = (
    ("__init__",),
    ("handlers", "properties"),
    ("operators_bake", "operators_parts", "operators_solve", "panels", "overlay", "render_pass"),
    ("live",),
    ("runtime",),
    ("deformation", "fluid_runtime"),
    ("frame", "status", "cache_files", "attributes"),
    ("inner_parts",),
    ("state", "fluid_sources"),
    ("scene_inputs", "backend"),
    ("world",),
    ("compat", "dependencies", "quality_costs"),
)
# panels calls the draw_settings hooks of overlay and render_pass, which share its floor
SIDEWAYS = {("panels", "overlay"), ("panels", "render_pass")}


def imports(module: str) -> set[str]:
    """The ops modules ``module`` imports (``from . import x``, ``from .x import y``, at any depth)."""
    tree = ast.parse((OPS / f"{module}.py").read_text())
    found = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.level == 1:
            found.update([node.module.split(".")[0]] if node.module else [a.name for a in node.names])
    return found & {m for floor in FLOORS for m in floor}


def test_every_ops_module_has_a_floor():
    on_floors = {m for floor in FLOORS for m in floor}
    assert on_floors == {p.stem for p in OPS.glob("*.py")}


def test_calls_go_down_never_up():
    floor_of = {m: i for i, floor in enumerate(FLOORS) for m in floor}
    upward = [(m, dep) for m in floor_of for dep in sorted(imports(m))
              if floor_of[dep] <= floor_of[m] and (m, dep) not in SIDEWAYS]
    assert upward == [], f"imports to the same or a higher floor: {upward}"


def test_runtime_re_exports_nothing():
    """Callers import state, cache_files and attributes names from those modules, not through runtime."""
    tree = ast.parse((OPS / "runtime.py").read_text())
    names = {a.asname or a.name for node in ast.walk(tree) if isinstance(node, ast.ImportFrom) and node.level == 1
             and node.module in ("state", "cache_files", "attributes") for a in node.names}
    assert names == set()


def test_state_is_reached_through_its_functions():
    """ops/state.py keeps the add-on's runtime state behind functions (cache problems, errors, plans, counters, the
    Info queue, the handlers' bookkeeping): no other module reads or writes its private module variables."""
    reached = []
    for path in sorted(OPS.glob("*.py")):
        if path.stem == "state":
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id == "state" \
                    and node.attr.startswith("_"):
                reached.append(f"{path.stem}: state.{node.attr}")
            if isinstance(node, ast.ImportFrom) and node.level == 1 and node.module == "state":
                reached += [f"{path.stem}: from .state import {a.name}" for a in node.names if a.name.startswith("_")]
    assert reached == []
