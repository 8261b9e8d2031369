# SPDX-License-Identifier: GPL-3.0-or-later
"""Hard cases of the Voxel Number Map (``translucency_addon/voxel_number_map``; issue 35, contract in ``passes.py``).

The bounds every solved case keeps (``VoxelNumberMapEvaluator``):

* the vertex radiance and the surface voxels' J+ finite and >= 0;
* energy: the power that leaves, ``(1 - F_dr,int) J+`` over the surface voxels, never exceeds the power that
  entered (``evaluator.power``; the kernel's clamp guarantees it per entry voxel, ``transport.py``):
  ``out / in <= 1 + 1e-9`` (tests/test_voxel_number_map.py's bound), and per entry voxel, what it sends out
  (``x_i s_i + A_i rho_i Phi_i``) <= what it took in (``A_i E_i``), for each light and the world alone: the
  clamp's guarantee, which the grazing sun on the thin medium breaks without it;
* the fp16 LUT finite and >= 0 (what the cache reader accepts).

What the map cannot hold is refused by name, with its numbers: an inner part smaller than a voxel, a surface-
voxel count above the budget (by one), a resolution outside [8, 512].  GPU = CPU: the GLSL kernel is compared
to this CPU path in ``tests/test_gpu_voxel_number_map.py`` (marked ``gpu``); these cases run the CPU path only.
Every map is of a 20 mm cube (or a 10 mm sphere) at a few hundred surface voxels (memoised, ~1 s each).
"""

from __future__ import annotations

import functools

import numpy as np

from translucency_addon.geometry import primitives
from translucency_addon.scene.composite import CompositeObject, InnerPart
from translucency_addon.scene.lights import Environment, Light
from translucency_addon.scene.materials import Material, Medium
from translucency_addon.voxel_number_map import VNMSettings, VoxelNumberMapEvaluator, bake_voxel_number_map
from translucency_addon.voxel_number_map.bake import choose_resolution

from .passes import Bound, Outcome, PassCase, finite_nonnegative

SIZE = 20.0
OUT_IN_EPS = 1e-9
FP16_MAX = 65504.0
THIN = Medium((0.02, 0.03, 0.05), (0.05, 0.06, 0.08), "thin")
LIGHTS = (Light("sun", irradiance=1000.0, direction=(-1.0, -0.3, -0.2), name="sun"),
          Light("sun", irradiance=800.0, direction=(0.3, 0.2, -0.008), name="grazing"),
          Light("point", intensity=20.0, position=(25.0, 5.0, 3.0), name="lamp"))
WORLD = Environment((0.2, 0.1, 0.05))


def cube():
    return primitives.box((SIZE,) * 3, n=4)


def vnm_bake(parts=(), material=Material(THIN), mm=1.0, **kw):
    kw.setdefault("env_directions", 16)
    kw.setdefault("surface_voxels", 300)
    return bake_voxel_number_map(CompositeObject(*cube(), material, list(parts)), VNMSettings(**kw), mm_per_unit=mm)


def measure(vnm, material, lights=LIGHTS, env=WORLD, mm=None) -> tuple[Outcome, VoxelNumberMapEvaluator]:
    ev = VoxelNumberMapEvaluator(vnm, material, mm_per_unit=mm)
    _, _, E = ev.sources(lights, env)
    A = vnm.surface.area[:, None]
    excess = -np.inf
    for one, world in [([light], None) for light in lights] + [([], env)]:  # each light alone, then the world
        x, local, took = ev.sources(one, world)
        sent, took = x * ev.kernel.s + A * local, A * took  # per entry voxel: what it sends out, what it took in
        excess = max(excess, float(np.max(sent - took * (1.0 + OUT_IN_EPS))) / max(float(np.max(took)), 1e-300))
    J = ev.exitance(lights, env)
    L = ev.radiance(lights, env, ("ORTHO", (-1.0, 0.2, 0.1)))
    p = ev.power(J, E)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where(p["in"] > 0, p["out"] / p["in"], np.where(p["out"] != 0, np.inf, 0.0))
    lengths = vnm.lengths.astype(np.float64)
    bounds = finite_nonnegative("radiance", L) + finite_nonnegative("J+", J) + \
        finite_nonnegative("fp16 lengths", lengths) + [Bound("out / in power", float(np.max(ratio)), 1.0 + OUT_IN_EPS),
         Bound("per entry voxel (out - in) / max in", excess, 0.0)]
    note = f"{vnm.n} surface voxels, {vnm.n_components} media, in {p['in'][0]:.3g} W, out {p['out'][0]:.3g} W"
    return Outcome(bounds, note), ev


def sub_voxel_part():
    """A jade part a fifth of a voxel across (resolution 16: 1.25 mm voxels), away from every voxel centre."""
    h = SIZE / 16
    part = InnerPart("grain", *primitives.icosphere(0.1 * h, 1, (0.2 * h, 0.2 * h, 0.2 * h)), "medium",
                     Medium((0.5,) * 3, (2.0,) * 3, "jade"))
    vnm_bake([part], resolution=16)


def fp16_depths():
    """Optical depths beyond fp16's 65504: sigma_t 1e4 /mm (the engine's limit) at 1 unit = 1 m.  The LUT
    stores lengths in voxels (fp16), tau is formed in float32 from them; exp(-tau) underflows to 0, which must
    give a dark, finite object and not 0 * inf.  The case also checks it reaches the regime: 65504 / max tau <= 1."""
    dense = Medium((5e3,) * 3, (5e3,) * 3, "tar")
    vnm = memo_map("plain")
    out, ev = measure(vnm, Material(dense), mm=1e3)
    tau_max = float(np.max(ev.coef.sigma_t)) * ev.coef.h_mm * float(vnm.lengths.astype(np.float64).max())
    out.bounds.append(Bound("65504 / max tau", FP16_MAX / tau_max, 1.0))
    out.note += f", max tau {tau_max:.3g}"
    return out


def fp16_depths_thin_part():
    """The same depths in the outer medium around a near-empty inner part (contrast with the tar 1e8): the
    light that crosses the part's chords only, still finite and within the power that entered."""
    dense = Medium((5e3,) * 3, (5e3,) * 3, "tar")
    out, _ = measure(memo_map("contrast"), Material(dense), mm=1e3)
    return out


@functools.lru_cache(maxsize=None)
def memo_map(kind: str):
    if kind == "plain":
        return vnm_bake()
    if kind == "contrast":  # a 12 mm cube of an inner medium at contrast 1e6 with the outer one
        part = InnerPart("core", *primitives.box((12.0,) * 3, n=2), "medium", Medium((1e-4,) * 3, (1e-4,) * 3, "air-ish"))
        return vnm_bake([part])
    if kind == "contrast_dense":  # the other way round: a dense core (1e2 /mm) in a thin (1e-4 /mm) medium
        part = InnerPart("core", *primitives.box((12.0,) * 3, n=2), "medium", Medium((20.0,) * 3, (80.0,) * 3, "dense"))
        return vnm_bake([part], material=Material(Medium((2e-5,) * 3, (8e-5,) * 3, "clear")))
    raise KeyError(kind)


def contrast_1e6():
    """Media of contrast 1e6: a dense core (sigma_t 100 /mm) in a clear outer medium (1e-4 /mm)."""
    vnm = memo_map("contrast_dense")
    return measure(vnm, Material(Medium((2e-5,) * 3, (8e-5,) * 3, "clear")))[0]


def contrast_1e6_inverse():
    """A near-empty core (2e-4 /mm) in an outer medium of sigma_t 200 /mm (contrast 1e6)."""
    return measure(memo_map("contrast"), Material(Medium((40.0,) * 3, (160.0,) * 3, "dense")))[0]


@functools.lru_cache(maxsize=None)
def budget_count(resolution: int = 12) -> int:
    return choose_resolution(*cube(), VNMSettings(resolution=resolution, max_surface_voxels=100_000))[1]


def budget_met_exactly():
    """max_surface_voxels = the count at resolution 12: must bake (the limit is inclusive) and render."""
    n = budget_count()
    vnm = vnm_bake(resolution=12, max_surface_voxels=n, surface_voxels=None)
    out, _ = measure(vnm, Material(THIN))
    out.bounds.append(Bound("surface voxels - budget", float(vnm.n - n), 0.0))
    out.note += f", budget {n}"
    return out


def budget_exceeded_by_one():
    """max_surface_voxels one below the count: refused, and the message names the count, the limit and the
    object's one medium (the refusal said "2 media" for every object before)."""
    from translucency_addon.errors import MeshError

    n = budget_count()
    try:
        vnm_bake(resolution=12, max_surface_voxels=n - 1, surface_voxels=None)
    except MeshError as ex:
        if f"{n:,} surface voxels" not in str(ex) or f"limit of {n - 1:,} surface voxels" not in str(ex):
            raise AssertionError(f"the refusal does not name the count {n} and the limit {n - 1}: {ex}") from None
        raise


def resolution_out_of_range():
    vnm_bake(resolution=600, surface_voxels=None)


CASES = [
    PassCase("voxel_number_map/sub_voxel_part", "voxel_number_map", sub_voxel_part,
             refusal=r"inner part 'grain' holds no voxel centre at this resolution \(voxel 1.25 mm\): it is smaller "
                     r"than a voxel"),
    PassCase("voxel_number_map/fp16_depths", "voxel_number_map", fp16_depths),
    PassCase("voxel_number_map/fp16_depths_thin_part", "voxel_number_map", fp16_depths_thin_part),
    PassCase("voxel_number_map/contrast_1e6", "voxel_number_map", contrast_1e6),
    PassCase("voxel_number_map/contrast_1e6_inverse", "voxel_number_map", contrast_1e6_inverse),
    PassCase("voxel_number_map/budget_met_exactly", "voxel_number_map", budget_met_exactly),
    PassCase("voxel_number_map/budget_exceeded_by_one", "voxel_number_map", budget_exceeded_by_one,
             refusal=r"Voxel Number Map at resolution 12: [\d,]+ surface voxels: the LUT would take \d+ MiB \(1 media\) "
                     r"and the run-time kernel \d+ MiB, above the limit of [\d,]+ surface voxels .*lower the resolution "
                     r"to about \d+ or use 'auto'"),
    PassCase("voxel_number_map/resolution_out_of_range", "voxel_number_map", resolution_out_of_range,
             refusal=r"resolution must be in \[8, 512\], got 600"),
]
