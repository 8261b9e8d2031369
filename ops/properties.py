# SPDX-License-Identifier: GPL-3.0-or-later
"""Settings stored in the .blend file: one PropertyGroup on Object, one on Scene.

``bpy.types.Object.translucency`` -> :class:`TranslucencyObjectSettings`
``bpy.types.Scene.translucency``  -> :class:`TranslucencySceneSettings`
(the PointerProperties are attached by ``ops.register()``).  What a bake
produced is kept apart from the settings, in
``object.translucency.status`` (:class:`TranslucencyObjectStatus`, written
only through ``ops.status``); a solve's per-frame status is runtime state
and never saved.

Units follow ``docs/architecture.md``: optical coefficients are per millimetre,
geometry is in object units and ``mm_per_unit`` converts it.
"""

from __future__ import annotations

import bpy
from bpy.props import (
    BoolProperty,
    CollectionProperty,
    EnumProperty,
    FloatProperty,
    FloatVectorProperty,
    IntProperty,
    PointerProperty,
    StringProperty,
)

from . import compat, live, quality_costs

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


def _request_update(_self, _context) -> None:
    """``update=`` callback of every setting that changes a solve's inputs.

    Setting a Python-defined property does not send a depsgraph update, so the
    live re-solve is scheduled here (throttled and coalesced by
    :func:`.live.request_update`; a no-op while the add-on is not registered).
    """
    try:
        live.request_update()
    except Exception:  # noqa: BLE001 - a property update must never fail
        pass


def _fmt3(values) -> str:
    return "(" + ", ".join(f"{v:g}" for v in values) + ")"


def _preset_items() -> list[tuple[str, str, str]]:
    """Enum items ``(IDENTIFIER, name, description)`` for the engine's presets.

    Identifiers are the preset keys in upper case; ``materials.preset()``
    accepts them as they are (it lower-cases its argument).
    """
    try:
        from ..translucency_addon.scene.materials import PRESETS
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
PATH_OPTIONS = compat.PATH_OPTIONS

_DEFAULT_PRESET = "MARBLE" if any(item[0] == "MARBLE" for item in PRESET_ITEMS) else PRESET_ITEMS[0][0]
_DEFAULT_SECOND = "KETCHUP" if any(item[0] == "KETCHUP" for item in PRESET_ITEMS) else PRESET_ITEMS[-1][0]


def _sigma_a(used: str):
    """The Custom absorption coefficient of a material (an object's or an inner part's)."""
    return FloatVectorProperty(
        update=_request_update,
        name="Absorption",
        description=f"Custom absorption coefficient sigma_a per millimetre (RGB), {used}",
        size=3,
        default=(0.0021, 0.0041, 0.0071),
        min=0.0,
        soft_max=10.0,
        precision=4,
    )


def _sigma_s(used: str):
    """The Custom reduced scattering coefficient of a material (an object's or an inner part's)."""
    return FloatVectorProperty(
        update=_request_update,
        name="Scattering",
        description=f"Custom reduced scattering coefficient sigma_s' per millimetre (RGB), {used}",
        size=3,
        default=(2.19, 2.62, 3.00),
        min=0.0,
        soft_max=100.0,
        precision=4,
    )


def _is_inner_part_candidate(item, obj) -> bool:
    """Poll of an inner part's object: a mesh other than the object the list belongs to."""
    return obj.type == 'MESH' and obj != getattr(item, "id_data", None)


class TranslucencyInnerPart(bpy.types.PropertyGroup):
    """One inner part of an object (``object.translucency.inner_parts``): a mesh object, typically a child,
    with its role (Mochida et al.; ``translucency_addon.scene.composite``)."""

    object: PointerProperty(
        update=_request_update,
        name="Object",
        description="Closed mesh object inside this object (typically a child): its evaluated mesh is the part",
        type=bpy.types.Object,
        poll=_is_inner_part_candidate,
    )
    role: EnumProperty(
        update=_request_update,
        name="Role",
        description="What the part is made of",
        items=(
            ("MEDIUM", "Medium", "Another translucent medium (wine in a bottle, a jade core): its own material below"),
            ("CAVITY", "Cavity", "A closed hollow of air inside the object (no extinction)"),
            ("OPAQUE", "Opaque", "An opaque body inside the object (a stone in jelly): it absorbs and casts shadows"),
        ),
        default="MEDIUM",
    )
    material_preset: EnumProperty(
        update=_request_update,
        name="Material",
        description="Measured material of a Medium part, or Custom coefficients (a change re-solves; no re-bake)",
        items=MATERIAL_ITEMS,
        default=_DEFAULT_SECOND,
    )
    sigma_a: _sigma_a("of a Medium part whose Material is Custom")
    sigma_s: _sigma_s("of a Medium part whose Material is Custom")


class TranslucencyLevelStats(bpy.types.PropertyGroup):
    """Node counts of one QuadGraph level of the last bake (written by the bake operator)."""

    n_surface: IntProperty(
        name="Surface Nodes",
        description="Number of surface nodes N_s of this QuadGraph level",
        default=0,
        min=0,
    )
    n_inner: IntProperty(
        name="Inner Nodes",
        description="Number of inner nodes N_i of this QuadGraph level",
        default=0,
        min=0,
    )


class TranslucencyObjectStatus(bpy.types.PropertyGroup):
    """What the last bake of an object produced (``object.translucency.status``; see ``ops.status``).

    Written only by ``status.set_bake_status`` and reset by ``status.clear_bake_status``; the
    solve's per-frame status lives in the runtime state and is never saved.
    """

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
    bake_levels: CollectionProperty(
        name="Bake Levels",
        description="Node counts N_s and N_i of every QuadGraph level, coarse to fine (written by the bake operator)",
        type=TranslucencyLevelStats,
    )
    bake_memory: FloatProperty(
        name="Graph Memory (MiB)",
        description="Memory the baked QuadGraph levels, transfer weights and vertex mapping take (written by the bake operator)",
        default=0.0,
        min=0.0,
        precision=2,
    )
    bake_seconds: FloatProperty(
        name="Bake Time (s)",
        description="Wall-clock time of the last bake in seconds (written by the bake operator)",
        default=0.0,
        min=0.0,
        precision=2,
    )
    bake_warnings: StringProperty(
        name="Bake Warnings",
        description="Warnings of the last bake, e.g. holes in the mesh or a non-uniform object scale (one per line)",
        default="",
    )
    bake_vertices: IntProperty(
        name="Baked Vertices",
        description="Vertex count of the evaluated mesh that was baked (written by the bake operator)",
        default=0,
        min=0,
    )
    ss_bake_stats: StringProperty(
        name="Single Scattering Bake",
        description="Samples, directions, SH order and bake time per stage of the last single-scattering bake",
        default="",
    )
    ss_bake_seconds: FloatProperty(
        name="SS Bake Time (s)",
        description="Wall-clock time of the last single-scattering bake in seconds",
        default=0.0,
        min=0.0,
        precision=2,
    )
    parts_bake_stats: StringProperty(
        name="Inner Parts Bake",
        description="Inner parts of the last bake with their roles, and its Voxel Number Map (surface voxels, LUT)",
        default="",
    )
    ss_samples_baked: IntProperty(
        name="SS Samples",
        description="Number of RBF samples in the baked single-scattering data (0: not baked)",
        default=0,
        min=0,
    )


FLUID_KINDS = (
    ("PARTICLES", "Particle System",
     "The alive particles of a particle system of the Source Object (an emitter); particle indices keep the warm "
     "start between frames"),
    ("POINT_CLOUD", "Point Cloud", "The points of a point-cloud object (evaluated; an 'id' attribute keeps the warm "
     "start between frames)"),
    ("GEOMETRY_NODES", "Geometry Nodes",
     "The points a Geometry Nodes object outputs (its evaluated point cloud; an 'id' attribute keeps the warm start)"),
    ("MANTAFLOW", "Mantaflow Liquid",
     "The FLIP particles of a Mantaflow liquid domain (Physics > Fluid); the radiance usually goes onto the domain's "
     "liquid mesh"),
)


def _fluid_object_poll(settings, obj) -> bool:
    """Objects the Source Object field offers for the chosen kind (the solve checks again: Python may set any)."""
    kind = settings.fluid_kind
    if kind == 'PARTICLES':
        return len(obj.particle_systems) > 0
    if kind == 'POINT_CLOUD':
        return obj.type == 'POINTCLOUD'
    if kind == 'GEOMETRY_NODES':
        return any(m.type == 'NODES' for m in obj.modifiers)
    return any(m.type == 'FLUID' and m.fluid_type == 'DOMAIN' for m in obj.modifiers)


class TranslucencyObjectSettings(bpy.types.PropertyGroup):
    """Per-object Translucency settings (``object.translucency``)."""

    enabled: BoolProperty(
        update=_request_update,
        name="Enabled",
        description="Simulate subsurface scattering in this object with Translucency",
        default=False,
    )
    source: EnumProperty(
        update=_request_update,
        name="Source",
        description="What the light scatters in",
        items=(
            ("MESH", "Mesh", "This mesh: its QuadGraph is baked once (Bake), then solved every frame"),
            ("FLUID", "Fluid",
             "A particle fluid (Kang & Kim 2013): Voronoi-fluid cells rebuilt from the particles every frame, no "
             "bake; the radiance goes onto this object (a mesh's vertices or a point cloud's points)"),
        ),
        default="MESH",
    )

    # -- fluid (source FLUID): where the particles come from, their radius ---------------------
    fluid_kind: EnumProperty(
        update=_request_update,
        name="Particles",
        description="Where the fluid's particles come from",
        items=FLUID_KINDS,
        default="PARTICLES",
    )
    fluid_object: PointerProperty(
        update=_request_update,
        name="Source Object",
        description="The object the particles come from (empty: this object)",
        type=bpy.types.Object,
        poll=_fluid_object_poll,
    )
    fluid_particle_system: StringProperty(
        update=_request_update,
        name="Particle System",
        description="Name of the Source Object's particle system (empty: its first)",
        default="",
    )
    fluid_radius_auto: BoolProperty(
        update=_request_update,
        name="Auto Radius",
        description=(
            "Use the particle spacing of each frame as the particle radius (the smallest radius that leaves no "
            "voids inside the fluid)"
        ),
        default=True,
    )
    fluid_radius: FloatProperty(
        update=_request_update,
        name="Radius",
        description=(
            "Particle radius in scene units when Auto Radius is off: each particle's cell is cut by a ball of this "
            "radius, so it sets how far the fluid reaches beyond its particles (about the particle spacing)"
        ),
        default=0.05,
        min=0.0,
        soft_max=10.0,
        precision=4,
        subtype='DISTANCE',
        unit='LENGTH',
    )

    # -- bake ---------------------------------------------------------------
    quality: EnumProperty(
        update=_request_update,
        name="Quality",
        description="Resolution of the QuadGraph the bake builds: finer graphs are more accurate and slower to bake and solve",
        # names and tooltips carry the measured cost (translucency_addon/data/quality_costs.json)
        items=quality_costs.quality_items(),
        default="PREVIEW",
    )
    levels: IntProperty(
        update=_request_update,
        name="Levels",
        description="Number of QuadGraph levels (coarse to fine) used by the multigrid solve",
        default=3,
        min=1,
        max=5,
    )
    use_mm_per_unit_override: BoolProperty(
        update=_request_update,
        name="Override Scale",
        description=(
            "Set the millimetres per object unit by hand instead of deriving it from the scene's "
            "unit scale and the object's scale"
        ),
        default=False,
    )
    mm_per_unit: FloatProperty(
        update=_request_update,
        name="mm per Unit",
        description="Millimetres per object-space unit, used when Override Scale is on (1000 = one unit is a metre)",
        default=1000.0,
        min=1e-6,
        soft_min=1e-3,
        soft_max=1e5,
        precision=3,
    )

    # -- terms and single scattering (Bernabei et al.) -------------------------
    sky_occlusion: BoolProperty(
        name="Self-Occlusion",
        description=(
            "Bake which directions of each surface point see the object itself, so that world light is "
            "shadowed there and the light the object sends to itself is added (one interreflection "
            "bounce). Matters on concave objects; adds a few seconds to the bake"
        ),
        default=True,
    )
    use_multiple_scattering: BoolProperty(
        update=_request_update,
        name="Multiple Scattering",
        description="Add the diffusion (multiple scattering) term, solved on the QuadGraph",
        default=True,
    )
    use_single_scattering: BoolProperty(
        update=_request_update,
        name="Single Scattering",
        description=(
            "Add the single-scattering term (RBF optical-depth samples). Bake bakes them too; after a material "
            "change use Bake Single Scattering, which keeps the QuadGraph"
        ),
        default=False,
    )
    pass_planning: EnumProperty(
        update=_request_update,
        name="Pass Planning",
        description="Which passes and colour channels run each frame",
        items=(
            ("AUTO", "Automatic",
             "The planner runs only the passes and channels this object calls for (diffusion where it is valid "
             "and not negligible; single scattering where diffusion is not valid) and skips unlit or unseen "
             "objects; the panel says why"),
            ("ALL", "All Passes", "Run every enabled term on every channel, every frame"),
        ),
        default="AUTO",
    )
    ss_quality: EnumProperty(
        update=_request_update,
        name="SS Quality",
        description="Voxel resolution of the single-scattering bake (voxels along the longest side)",
        items=(
            ("DRAFT", "Draft", "32 voxels along the longest side"),
            ("PREVIEW", "Preview", "48 voxels along the longest side"),
            ("FINAL", "Final", "64 voxels along the longest side"),
        ),
        default="PREVIEW",
    )
    ss_directions: EnumProperty(
        update=_request_update,
        name="Directions",
        description="Directions of the baked optical depth (more: sharper self-shadowing, longer bake)",
        items=(
            ("32", "32", "Fast bake, soft self-shadowing"),
            ("128", "128", "The paper's default"),
            ("512", "512", "Sharpest self-shadowing, slowest bake"),
        ),
        default="128",
    )
    ss_samples: IntProperty(
        update=_request_update,
        name="Samples",
        description="Target number of RBF samples (Poisson-disk) in the single-scattering bake",
        default=20000,
        min=100,
        soft_max=100000,
        max=1000000,
    )
    ss_sh_order: IntProperty(
        update=_request_update,
        name="SH Order",
        description=(
            "Spherical-harmonics order of the baked attenuation (9, 16 or 25 coefficients). A lower order than "
            "baked applies without a re-bake"
        ),
        default=4,
        min=2,
        max=4,
    )
    ss_split_pass: BoolProperty(
        update=_request_update,
        name="Split Pass",
        description=(
            "Also write the single-scattering term alone into the 'translucency_radiance_ss' attribute "
            "(the Translucency_SS render pass after Add to Material); Translucency keeps the total"
        ),
        default=False,
    )

    # -- material -----------------------------------------------------------
    material_preset: EnumProperty(
        update=_request_update,
        name="Material",
        description="Measured material the object is made of, or Custom coefficients",
        items=MATERIAL_ITEMS,
        default=_DEFAULT_PRESET,
    )
    sigma_a: _sigma_a("used when Material is Custom")
    sigma_s: _sigma_s("used when Material is Custom")
    eta: FloatProperty(
        update=_request_update,
        name="IOR",
        description="Relative index of refraction of the material against the surrounding air",
        default=1.3,
        min=1.0,
        soft_max=2.0,
        max=4.0,
        precision=3,
    )

    # -- inner parts (Mochida et al.; translucency_addon.scene.composite) ---------------
    inner_parts: CollectionProperty(
        name="Inner Parts",
        description=(
            "Mesh objects inside this one (typically children) that are another medium, a cavity or opaque; "
            "baked with the object"
        ),
        type=TranslucencyInnerPart,
    )
    inner_parts_index: IntProperty(
        name="Active Inner Part",
        description="Index of the inner part shown below the list",
        default=0,
        min=0,
    )
    use_voxel_number_map: BoolProperty(
        update=_request_update,
        name="Voxel Number Map",
        description=(
            "With inner parts: also bake the Voxel Number Map (a chord LUT between surface voxels), the pass the "
            "planner runs where diffusion is not valid and single scattering does not know the parts"
        ),
        default=True,
    )
    vnm_quality: EnumProperty(
        update=_request_update,
        name="Map Quality",
        description="Surface voxels the Voxel Number Map aims for (its LUT grows with their square)",
        items=(
            ("DRAFT", "Draft", "About 800 surface voxels"),
            ("PREVIEW", "Preview", "About 2,000 surface voxels"),
            ("FINAL", "Final", "About 3,500 surface voxels"),
        ),
        default="PREVIEW",
    )
    vnm_resolution: IntProperty(
        update=_request_update,
        name="Map Resolution",
        description=(
            "Voxels along the longest side of the Voxel Number Map; 0 chooses it from Map Quality within the "
            "budget of 4,096 surface voxels (a set resolution beyond the budget is refused with the numbers)"
        ),
        default=0,
        min=0,
        max=512,
    )

    # -- heterogeneity -----------------------------------------------------
    use_heterogeneity: BoolProperty(
        update=_request_update,
        name="Heterogeneous",
        description="Mix the material with a second medium, weighted by a field over the object",
        default=False,
    )
    second_preset: EnumProperty(
        update=_request_update,
        name="Second Medium",
        description="Measured material mixed in where the field is 1 (the first material is used where it is 0)",
        items=PRESET_ITEMS,
        default=_DEFAULT_SECOND,
    )
    field_source: EnumProperty(
        update=_request_update,
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
        update=_request_update,
        name="Texture",
        description="Texture whose intensity gives the mixing weight (0: first material, 1: second medium)",
        type=bpy.types.Texture,
    )
    field_attribute: StringProperty(
        update=_request_update,
        name="Attribute",
        description="Name of the mesh float attribute that gives the mixing weight (0 to 1)",
        default="",
    )
    field_vertex_group: StringProperty(
        update=_request_update,
        name="Vertex Group",
        description="Name of the vertex group whose weights give the mixing weight (0 to 1)",
        default="",
    )
    field_scale: FloatProperty(
        update=_request_update,
        name="Texture Scale",
        description=(
            "The texture is evaluated at (object-space position x this factor): larger values "
            "give a finer pattern"
        ),
        default=1.0,
        min=1e-6,
        soft_min=1e-3,
        soft_max=1e3,
        precision=3,
    )

    # -- the cache: where the bake is and which bake it must be ---------------
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
    packed_cache: StringProperty(
        name="Packed Cache",
        description=(
            "Name of the hidden Text datablock holding this object's bake cache packed into the .blend (base64), "
            "for single-file render farms; empty when not packed (written by Pack Cache)"
        ),
        default="",
    )
    bake_key: StringProperty(
        name="Bake Key",
        description="Hash of the baked mesh and bake settings; a cache with another key is stale (written by the bake operator)",
        default="",
    )
    status: PointerProperty(
        name="Status",
        description="What the last bake of this object produced (written by the bake operators)",
        type=TranslucencyObjectStatus,
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
        update=_request_update,
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
        update=_request_update,
        name="Tolerance",
        description="Relative residual at which the iterative solve stops",
        default=1e-4,
        min=1e-10,
        max=0.5,
        soft_min=1e-7,
        soft_max=1e-2,
        precision=6,
    )
    live_update: BoolProperty(
        update=_request_update,
        name="Live Update",
        description=(
            "Re-solve baked objects when a light, the world, the material, its field or the object "
            "changes, and on every frame change (renders always re-solve)"
        ),
        default=True,
    )
    progressive: BoolProperty(
        name="Progressive",
        description=(
            "In the viewport, show the solve so far within the frame budget after a light, the world or the "
            "material changes, and refine it on later redraws until it converges (renders always converge "
            "before the frame is drawn)"
        ),
        default=True,
    )
    frame_budget_ms: FloatProperty(
        name="Frame Budget",
        description=(
            "How long one progressive step may run before the viewport shows the solve so far, in "
            "milliseconds (the first step also pays for the light pass)"
        ),
        default=1000.0 / 30.0,
        min=1.0,
        max=5000.0,
        soft_max=500.0,
        precision=1,
    )
    missing_cache_in_render: EnumProperty(
        name="Cache Missing in Render",
        description=(
            "What a render does with a frame an object cannot be solved for: its bake cache is missing, "
            "unreadable or from another version of the extension (a render farm worker without the cache "
            "folder), its bake is stale (the mesh changed since the bake: re-bake), the deformation check "
            "refuses its pose (a fold or an overstretch), or the solve fails. A frame is never rendered with "
            "another frame's, another pose's or a stale bake's pass, whatever the worker rendered before; "
            "renders never bake"
        ),
        items=(
            ("FAIL", "Fail the Frame",
             "Background renders (blender -b, render farms) stop with exit code 1 and the reason as the log's "
             "last line, before the image is written, so the farm marks the frame failed; in the UI the object "
             "renders without its pass and the error is shown"),
            ("SKIP", "Render Without",
             "Render the frame without the object's Translucency pass (its attribute is removed, never another "
             "frame's or a stale bake's values), and log why"),
        ),
        default="FAIL",
    )


CLASSES = (TranslucencyInnerPart, TranslucencyLevelStats, TranslucencyObjectStatus, TranslucencyObjectSettings,
           TranslucencySceneSettings)
