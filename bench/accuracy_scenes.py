# SPDX-License-Identifier: GPL-3.0-or-later
"""The matched scenes of the accuracy benchmark (issue 8): meshes, materials, field, sky, camera.

Every scene is a :class:`bench.reference.scene.RefScene`; the path tracer
(``bench/reference/mitsuba_ref.py``) and our engine read the same one.

* **bunny**: the Stanford bunny, decimated to 10,000 triangles and made
  watertight (its five holes in the base fan-filled at their centroids), 40 mm
  along its bounding-box diagonal.  The raw scan has holes: a path tracer with
  an interior medium cannot render an open boundary correctly (a path leaving
  through a hole would stay "inside"), so both sides get the closed surface.
* **sphere**: an icosphere (4 subdivisions, 5,120 flat facets) of radius 12 mm.
* materials (Jensen et al. 2001, eta 1.3): ``marble``, ``skimmilk``, ``skin1`` and
  ``hetero``: marble mixed with skin1 by the engine's procedural ``marble``
  field (veins about 8 mm apart), exported to the reference as a 128^3 grid.
* light: the order-2 SH sky lobe ``sky_environment(SKY_DIR, lobe=2)`` (the
  engine represents it exactly; a path tracer cannot render a sun behind a
  smooth dielectric), from the right, above and slightly in front of the object,
  so the left of each image is lit only by light that crossed the object.
  ``sphere_uniform`` adds the marble sphere under a uniform environment
  (a low-noise check of the model alone).
* camera: orthographic along -z, the object filling the frame.
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

import numpy as np

from data import mesh_path
from bench.reference.scene import Camera, RefScene, sky_environment
from translucency_addon.scene.fields import FieldSpec
from translucency_addon.scene.lights import Environment
from translucency_addon.scene.materials import Material, material_from_preset

ROOT = Path(__file__).resolve().parents[1]

SKY_DIR = (1.0, 0.6, 0.35)  # towards the bright side of the sky: right, up, towards the camera
BUNNY_SIZE_MM = 40.0
SPHERE_RADIUS_MM = 12.0
VEIN_PERIOD_MM = 8.0
MATERIALS = ("marble", "skimmilk", "skin1", "hetero")
MESH_NAMES = ("bunny", "sphere")


def fill_holes(V, F):
    """Close every boundary loop with a fan around its centroid (small, nearly planar holes)."""
    from translucency_addon.geometry.meshio import boundary_edges

    V = np.asarray(V, dtype=np.float64)
    F = np.asarray(F, dtype=np.int64)
    # directed boundary half-edges: (a -> b) appears in a face, (b -> a) in none
    he = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
    und = {tuple(e) for e in boundary_edges(F)}
    nxt = {}
    for a, b in he:
        if (min(a, b), max(a, b)) in und:
            nxt[int(a)] = int(b)
    V2 = [V]
    newF = []
    seen = set()
    n = len(V)
    for start in list(nxt):
        if start in seen:
            continue
        loop = [start]
        seen.add(start)
        cur = nxt[start]
        while cur != start and cur in nxt and cur not in seen:
            loop.append(cur)
            seen.add(cur)
            cur = nxt[cur]
        if cur != start or len(loop) < 3:
            continue
        c = V[loop].mean(axis=0)
        V2.append(c[None])
        # the hole's faces run against the boundary half-edges: (b, a, centre)
        for i in range(len(loop)):
            a, b = loop[i], loop[(i + 1) % len(loop)]
            newF.append((b, a, n))
        n += 1
    if not newF:
        return V, F
    return np.vstack(V2), np.vstack([F, np.asarray(newF, dtype=np.int64)])


@lru_cache(maxsize=None)
def bunny_mesh(triangles: int = 10_000):
    """The closed, decimated Stanford bunny in its own object units (as the OBJ)."""
    from translucency_addon.quadgraph.bake import resample_surface
    from translucency_addon.geometry.meshio import count_holes, load_obj, signed_volume

    V, F = load_obj(mesh_path("stanford-bunny"))
    V, F = resample_surface(V, F, triangles)
    V, F = fill_holes(V, F)
    holes, _ = count_holes(F)
    if holes:
        raise RuntimeError(f"the bunny still has {holes} holes after filling")
    if signed_volume(V, F) < 0:
        F = F[:, ::-1].copy()
    return V, F


@lru_cache(maxsize=None)
def sphere_mesh(subdivisions: int = 4):
    from translucency_addon.geometry.primitives import icosphere

    return icosphere(1.0, subdivisions)


MESH_FILE = ROOT / "bench" / "data" / "meshes.npz"


@lru_cache(maxsize=None)
def _stored_meshes() -> dict:
    """The benchmark meshes as committed (bench/data/meshes.npz), so that the cached references
    (keyed by the exact vertices) stay valid whatever the decimator does in later versions."""
    if not MESH_FILE.exists():
        return {}
    with np.load(MESH_FILE, allow_pickle=False) as z:
        return {k: np.array(z[k]) for k in z.files}


def store_meshes() -> None:
    MESH_FILE.parent.mkdir(parents=True, exist_ok=True)
    arrays = {}
    for name, fn in (("bunny", bunny_mesh), ("sphere", sphere_mesh)):
        V, F = fn()
        arrays[f"{name}_V"], arrays[f"{name}_F"] = np.asarray(V, np.float64), np.asarray(F, np.int64)
    np.savez_compressed(MESH_FILE, **arrays)
    _stored_meshes.cache_clear()


def mesh(name: str):
    """``(V, F, mm_per_unit)`` of a benchmark mesh."""
    if name not in MESH_NAMES:
        raise ValueError(f"unknown mesh {name!r}; choose one of {', '.join(MESH_NAMES)}")
    stored = _stored_meshes()
    if f"{name}_V" in stored:
        V, F = stored[f"{name}_V"], stored[f"{name}_F"]
    else:
        V, F = bunny_mesh() if name == "bunny" else sphere_mesh()
    if name == "bunny":
        return V, F, BUNNY_SIZE_MM / float(np.linalg.norm(np.ptp(V, axis=0)))
    return V, F, SPHERE_RADIUS_MM


def material(name: str, sigma_a_scale: float = 1.0) -> Material:
    """A benchmark material; ``sigma_a_scale`` multiplies sigma_a (the deliberately wrong one)."""
    if name == "hetero":
        m = material_from_preset("marble", mix_with="skin1")
    else:
        m = material_from_preset(name)
    if sigma_a_scale != 1.0:
        from dataclasses import replace

        def scaled(med):
            return replace(med, sigma_a=tuple(float(x) * sigma_a_scale for x in med.sigma_a))

        m = replace(m, medium_a=scaled(m.medium_a),
                    medium_b=None if m.medium_b is None else scaled(m.medium_b))
    return m


def field_for(name: str, mm_per_unit: float, V) -> FieldSpec | None:
    if name != "hetero":
        return None
    lo = np.asarray(V).min(axis=0)
    return FieldSpec(kind="marble", scale=VEIN_PERIOD_MM / mm_per_unit, axis=0, turbulence=1.5, seed=3,
                     offset=tuple(float(x) for x in lo))


def camera_for(V, resolution, margin: float = 1.05) -> Camera:
    lo, hi = V.min(axis=0), V.max(axis=0)
    centre = 0.5 * (lo + hi)
    half = 0.5 * (hi - lo)
    width = 2.0 * max(half[0], half[1] * resolution[0] / resolution[1]) * margin
    return Camera.orthographic(centre, (0.0, 0.0, -1.0), (0.0, 1.0, 0.0), width=width)


def make_scene(mesh_name: str, material_name: str, *, res: int = 32, spp: int = 1024, light: str = "sky",
               sigma_a_scale: float = 1.0, seed: int = 0) -> RefScene:
    """The matched scene ``mesh_name`` x ``material_name`` under ``light`` ("sky" or "uniform")."""
    V, F, mpu = mesh(mesh_name)
    m = material(material_name, sigma_a_scale)
    if light == "sky":
        env = sky_environment(SKY_DIR, lobe=2, irradiance=np.pi)
    elif light == "uniform":
        env = Environment((1.0, 1.0, 1.0))
    else:
        raise ValueError(f"light must be 'sky' or 'uniform', got {light!r}")
    name = f"{mesh_name}_{material_name}_{light}" + (f"_sa{sigma_a_scale:g}" if sigma_a_scale != 1.0 else "")
    return RefScene(V, F, mpu, m, camera_for(V, (res, res)), lights=[], environment=env,
                    field=field_for(material_name, mpu, V), resolution=(res, res), spp=spp, seed=seed, name=name)


# --- the reference set -------------------------------------------------------------------
# (mesh, material, light, spp per channel) at REF_RES x REF_RES; rendered once, cached in bench/data.
REF_RES = 32
REFERENCES = (
    ("bunny", "marble", "sky", 4096),
    ("sphere", "marble", "sky", 8192),
    ("bunny", "hetero", "sky", 1024),
    ("bunny", "skimmilk", "sky", 1024),
    ("bunny", "skin1", "sky", 1024),
    ("sphere", "skin1", "sky", 1024),
    ("sphere", "skimmilk", "sky", 4096),
    ("sphere", "marble", "uniform", 2048),
    ("sphere", "hetero", "sky", 1024),
)
# --quick: tiny references (rendered in seconds; cached too)
QUICK_RES = 12
QUICK_REFERENCES = (("sphere", "marble", "uniform", 64), ("bunny", "marble", "sky", 64))
DATA = ROOT / "bench" / "data"


def reference_scenes(quick: bool = False):
    specs = QUICK_REFERENCES if quick else REFERENCES
    res = QUICK_RES if quick else REF_RES
    return [make_scene(m, mat, res=res, spp=spp, light=light) for m, mat, light, spp in specs]


def reference_dir(quick: bool = False) -> Path:
    return DATA / ("reference_quick" if quick else "reference")


def get_reference(scene, quick: bool = False, refresh: bool = False, progress=None):
    """The cached reference of ``scene`` (rendered and stored on a miss or with ``refresh``)."""
    from bench.reference.mitsuba_ref import cached_reference, scene_key

    d = reference_dir(quick)
    if refresh:
        for p in d.glob(f"{scene.name}-{scene_key(scene)}.npz"):
            p.unlink()
    return cached_reference(scene, d, progress=progress)


def prune_references(quick: bool = False) -> list:
    """Delete cached references of this report's scenes that no current key uses (e.g. after a change of spp).

    Only files named after one of these scenes are candidates: other benches keep their references in the same
    directory (``bench/fluid_reference.py``'s ellipsoid), and a prune here must not delete them.
    """
    from bench.reference.mitsuba_ref import scene_key

    scenes = list(reference_scenes(quick))
    keep = {f"{s.name}-{scene_key(s)}.npz" for s in scenes}
    if not quick:  # the local-light references (bench/light_scenes.py) share the directory
        from bench import light_scenes

        lights = list(light_scenes.reference_scenes())
        scenes += lights
        keep |= {f"{s.name}-{scene_key(s, batches=light_scenes.BATCHES)}.npz" for s in lights}
    names = {s.name for s in scenes}
    gone = [p for p in reference_dir(quick).glob("*.npz")
            if p.name not in keep and p.name.rsplit("-", 1)[0] in names]
    for p in gone:
        p.unlink()
    return [p.name for p in gone]


if __name__ == "__main__":  # render the reference set:  python -m bench.accuracy_scenes [--quick]
    import sys
    import time

    quick = "--quick" in sys.argv
    for sc in reference_scenes(quick):
        t = time.time()
        r = get_reference(sc, quick)
        from bench.reference.metrics import noise_floor

        print(f"{sc.name}: {r.spp} spp, {r.seconds:.0f} s render ({time.time() - t:.0f} s now), "
              f"noise floor {noise_floor(r.image, r.stderr, r.mask):.4f}", flush=True)
