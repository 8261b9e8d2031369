# SPDX-License-Identifier: GPL-3.0-or-later
"""Quality preset labels and tooltips with their measured cost (issue 8).

The numbers come from ``translucency_addon/data/quality_costs.json``, which
``bench/accuracy.py`` writes from its measurements (never typed by hand): for
each preset the bake time, the time per frame and the relative RMS error
against an independent path tracer on the benchmark scene.  Without the file
(or with a malformed one) the presets keep their plain descriptions, so
registration never depends on it.  bpy-free: the enum items are plain tuples.
"""

from __future__ import annotations

import json
from pathlib import Path

COSTS_PATH = Path(__file__).resolve().parent.parent / "translucency_addon" / "data" / "quality_costs.json"
SCHEMA = 1
PRESETS = (
    ("DRAFT", "Draft", "Coarse graph for quick previews while modelling"),
    ("PREVIEW", "Preview", "Medium graph: a balance of speed and accuracy"),
    ("FINAL", "Final", "Fine graph for final renders"),
)
# Every preset entry in the JSON must carry these (numbers; error as a fraction).
REQUIRED_KEYS = ("bake_s", "frame_ms", "rel_rms")


def load_costs(path=None) -> dict | None:
    """The parsed cost file, or None when it is missing or does not match the schema."""
    p = Path(path) if path is not None else COSTS_PATH
    try:
        data = json.loads(p.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return data if validate(data) is None else None


def validate(data) -> str | None:
    """None if ``data`` matches the schema, else what is wrong (used by the tests)."""
    if not isinstance(data, dict) or data.get("schema") != SCHEMA:
        return f"not a quality-cost file of schema {SCHEMA}"
    presets = data.get("presets")
    if not isinstance(presets, dict):
        return "no 'presets' object"
    for ident, _, _ in PRESETS:
        entry = presets.get(ident.lower())
        if not isinstance(entry, dict):
            return f"no entry for preset {ident.lower()!r}"
        for k in REQUIRED_KEYS:
            v = entry.get(k)
            if not isinstance(v, (int, float)) or isinstance(v, bool) or not v >= 0 or v != v:
                return f"preset {ident.lower()!r}: {k!r} must be a non-negative number, got {v!r}"
    if not isinstance(data.get("scene", ""), str) or not isinstance(data.get("machine", ""), str):
        return "'scene' and 'machine' must be strings"
    return None


def fmt_seconds(s: float) -> str:
    return f"{s:.0f} s" if s >= 10 else f"{s:.1f} s"


def fmt_ms(ms: float) -> str:
    if ms >= 1000:
        return f"{ms / 1000:.1f} s"
    return f"{ms:.0f} ms" if ms >= 10 else f"{ms:.1f} ms"


def fmt_percent(x: float) -> str:
    return f"{100.0 * x:.1f} %"


def preset_texts(ident: str, name: str, description: str, entry: dict | None, data: dict | None):
    """``(name, description)`` of one preset, with its measured cost when known."""
    if entry is None:
        return name, description
    bake, frame, err = fmt_seconds(entry["bake_s"]), fmt_ms(entry["frame_ms"]), fmt_percent(entry["rel_rms"])
    label = f"{name} ({bake} bake, {frame}/frame, {err} error)"
    scene = (data or {}).get("scene", "the benchmark scene")
    machine = (data or {}).get("machine", "")
    desc = (f"{description}. Measured by bench/accuracy.py on {scene}"
            + (f" ({machine})" if machine else "")
            + f": bake {bake}, frame {frame}, error {err} relative RMS against a path tracer")
    return label, desc


def quality_items(path=None) -> tuple:
    """EnumProperty items ``(identifier, name, description)`` for the quality presets."""
    data = load_costs(path)
    presets = (data or {}).get("presets", {})
    out = []
    for ident, name, desc in PRESETS:
        label, d = preset_texts(ident, name, desc, presets.get(ident.lower()), data)
        out.append((ident, label, d))
    return tuple(out)
