# SPDX-License-Identifier: GPL-3.0-or-later
"""Settings stored in the .blend file: one PropertyGroup on Object, one on Scene.

``bpy.types.Object.translucency`` -> :class:`TranslucencyObjectSettings`
``bpy.types.Scene.translucency``  -> :class:`TranslucencySceneSettings`
(the PointerProperties are attached by ``ops.register()``).

Units follow ``docs/architecture.md``: optical coefficients are per millimetre,
geometry is in object units and ``mm_per_unit`` converts it.
"""

from __future__ import annotations

import bpy
from bpy.props import (
    BoolProperty,
    EnumProperty,
    FloatProperty,
    FloatVectorProperty,
    IntProperty,
    PointerProperty,
    StringProperty,
)

# Used when the engine's preset table cannot be imported (it needs only numpy,
# but registration must never depend on it): Jensen et al. 2001 names.
_FALLBACK_PRESET_NAMES = (
    "apple", "chicken1", "chicken2", "cream", "ketchup", "marble",
    "potato", "skimmilk", "skin1", "skin2", "wholemilk",
)
_DISPLAY_NAMES = {
    "skimmilk": "Skim Milk",
    "wholemilk": "Whole Milk",
    "chicken1": "Chicken 1",
    "chicken2": "Chicken 2",
    "skin1": "Skin 1",
    "skin2": "Skin 2",
}


def _fmt3(values) -> str:
    return "(" + ", ".join(f"{v:g}" for v in values) + ")"


def _preset_items() -> list[tuple[str, str, str]]:
    """Enum items ``(IDENTIFIER, name, description)`` for the engine's presets.

    Identifiers are the preset keys in upper case; ``materials.preset()``
    accepts them as they are (it lower-cases its argument).
    """
    try:
        from ..translucency_addon.materials import PRESETS
        presets = [
            (key, f"Jensen et al. 2001, per mm: sigma_a {_fmt3(m.sigma_a)}, sigma_s' {_fmt3(m.sigma_s)}")
            for key, m in PRESETS.items()
        ]
    except Exception:  # noqa: BLE001 - a broken engine import must not break registration
        presets = [(key, "Jensen et al. 2001 measured coefficients") for key in _FALLBACK_PRESET_NAMES]
    return [
        (key.upper(), _DISPLAY_NAMES.get(key, key.replace("_", " ").title()), description)
        for key, description in presets
    ]


PRESET_ITEMS = _preset_items()
MATERIAL_ITEMS = PRESET_ITEMS + [
    ("CUSTOM", "Custom", "Use the absorption and reduced scattering coefficients given below"),
]
# Blender 4.5+ warns when a path property gets a "//" (blend-relative) value
# unless the property says it supports one; 4.2 does not know the flag.
PATH_OPTIONS = {'PATH_SUPPORTS_BLEND_RELATIVE'} if bpy.app.version >= (4, 5, 0) else set()

_DEFAULT_PRESET = "MARBLE" if any(item[0] == "MARBLE" for item in PRESET_ITEMS) else PRESET_ITEMS[0][0]
_DEFAULT_SECOND = "KETCHUP" if any(item[0] == "KETCHUP" for item in PRESET_ITEMS) else PRESET_ITEMS[-1][0]


class TranslucencyObjectSettings(bpy.types.PropertyGroup):
    """Per-object Translucency settings (``object.translucency``)."""

    enabled: BoolProperty(
        name="Enabled",
        description="Simulate subsurface scattering in this object with Translucency",
        default=False,
    )

    # -- bake ---------------------------------------------------------------
    quality: EnumProperty(
        name="Quality",
        description="Resolution of the QuadGraph the bake builds: finer graphs are more accurate and slower to bake and solve",
        items=(
            ("DRAFT", "Draft", "Coarse graph for quick previews while modelling"),
            ("PREVIEW", "Preview", "Medium graph: a balance of speed and accuracy"),
            ("FINAL", "Final", "Fine graph for final renders"),
        ),
        default="PREVIEW",
    )
    levels: IntProperty(
        name="Levels",
        description="Number of QuadGraph levels (coarse to fine) used by the multigrid solve",
        default=3,
        min=1,
        max=5,
    )
    use_mm_per_unit_override: BoolProperty(
        name="Override Scale",
        description=(
            "Set the millimetres per object unit by hand instead of deriving it from the scene's "
            "unit scale and the object's scale"
        ),
        default=False,
    )
    mm_per_unit: FloatProperty(
        name="mm per Unit",
        description="Millimetres per object-space unit, used when Override Scale is on (1000 = one unit is a metre)",
        default=1000.0,
        min=1e-6,
        soft_min=1e-3,
        soft_max=1e5,
        precision=3,
    )

    # -- material -----------------------------------------------------------
    material_preset: EnumProperty(
        name="Material",
        description="Measured material the object is made of, or Custom coefficients",
        items=MATERIAL_ITEMS,
        default=_DEFAULT_PRESET,
    )
    sigma_a: FloatVectorProperty(
        name="Absorption",
        description="Custom absorption coefficient sigma_a per millimetre (RGB), used when Material is Custom",
        size=3,
        default=(0.0021, 0.0041, 0.0071),
        min=0.0,
        soft_max=10.0,
        precision=4,
    )
    sigma_s: FloatVectorProperty(
        name="Scattering",
        description="Custom reduced scattering coefficient sigma_s' per millimetre (RGB), used when Material is Custom",
        size=3,
        default=(2.19, 2.62, 3.00),
        min=0.0,
        soft_max=100.0,
        precision=4,
    )
    eta: FloatProperty(
        name="IOR",
        description="Relative index of refraction of the material against the surrounding air",
        default=1.3,
        min=1.0,
        soft_max=2.0,
        max=4.0,
        precision=3,
    )

    # -- heterogeneity -----------------------------------------------------
    use_heterogeneity: BoolProperty(
        name="Heterogeneous",
        description="Mix the material with a second medium, weighted by a field over the object",
        default=False,
    )
    second_preset: EnumProperty(
        name="Second Medium",
        description="Measured material mixed in where the field is 1 (the first material is used where it is 0)",
        items=PRESET_ITEMS,
        default=_DEFAULT_SECOND,
    )
    field_source: EnumProperty(
        name="Field Source",
        description="Where the mixing weight between the two media comes from",
        items=(
            ("TEXTURE", "Texture", "Intensity of a texture, evaluated at each graph node in object space"),
            ("ATTRIBUTE", "Attribute", "A float attribute of the mesh"),
            ("VERTEX_GROUP", "Vertex Group", "Weights of a vertex group"),
        ),
        default="TEXTURE",
    )
    field_texture: PointerProperty(
        name="Texture",
        description="Texture whose intensity gives the mixing weight (0: first material, 1: second medium)",
        type=bpy.types.Texture,
    )
    field_attribute: StringProperty(
        name="Attribute",
        description="Name of the mesh float attribute that gives the mixing weight (0 to 1)",
        default="",
    )
    field_vertex_group: StringProperty(
        name="Vertex Group",
        description="Name of the vertex group whose weights give the mixing weight (0 to 1)",
        default="",
    )

    # -- cache and status -------------------------------------------------
    cache_filepath: StringProperty(
        name="Cache File",
        description=(
            "Bake cache (.npz) of this object; empty to use a file named after the object "
            "in the scene's cache directory"
        ),
        default="",
        subtype='FILE_PATH',
        options=PATH_OPTIONS,
    )
    bake_status: StringProperty(
        name="Bake Status",
        description="Result of the last bake of this object (written by the bake operator)",
        default="Not baked",
    )
    bake_stats: StringProperty(
        name="Bake Statistics",
        description="Size and timing of the last bake: nodes per level, time taken (written by the bake operator)",
        default="",
    )


class TranslucencySceneSettings(bpy.types.PropertyGroup):
    """Per-scene Translucency settings (``scene.translucency``)."""

    cache_directory: StringProperty(
        name="Cache Directory",
        description="Directory for bake caches; // means relative to the .blend file",
        default="//translucency_cache/",
        subtype='DIR_PATH',
        options=PATH_OPTIONS,
    )
    overlay_enabled: BoolProperty(
        name="Viewport Overlay",
        description="Show the solved subsurface radiance in the 3D viewport",
        default=True,
    )
    overlay_mode: EnumProperty(
        name="Overlay Mode",
        description="How the solved radiance is combined with the viewport shading",
        items=(
            ("ONLY", "Only", "Show only the subsurface radiance"),
            ("ADD", "Add", "Add the subsurface radiance to the viewport shading"),
        ),
        default="ADD",
    )
    solver_backend: EnumProperty(
        name="Solver",
        description="Where the diffusion solve runs",
        items=(
            ("AUTO", "Auto", "Use the GPU when Blender's GPU compute shaders are available, otherwise the CPU"),
            ("GPU", "GPU", "Solve with GPU compute shaders through Blender's gpu module"),
            ("CPU", "CPU", "Solve with numpy/scipy on the CPU"),
        ),
        default="AUTO",
    )
    tolerance: FloatProperty(
        name="Tolerance",
        description="Relative residual at which the iterative solve stops",
        default=1e-4,
        min=1e-10,
        max=0.5,
        soft_min=1e-7,
        soft_max=1e-2,
        precision=6,
    )
    last_solve_time: FloatProperty(
        name="Last Solve Time (s)",
        description="Wall-clock time of the last solve in seconds (written by the solver)",
        default=0.0,
        min=0.0,
        precision=3,
    )
    last_residual: FloatProperty(
        name="Last Residual",
        description="Relative residual reached by the last solve (written by the solver)",
        default=0.0,
        min=0.0,
        precision=8,
    )


CLASSES = (TranslucencyObjectSettings, TranslucencySceneSettings)
