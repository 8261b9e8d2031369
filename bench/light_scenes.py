# SPDX-License-Identifier: GPL-3.0-or-later
"""Matched scenes with local lights (issue 17): area emitters the path tracer can render.

A unidirectional path tracer cannot light a medium behind a smooth dielectric with a delta light
(point, spot, sun: ``bench/reference/mitsuba_ref._emitters``), but a path that leaves the object
can *hit* an emitter of finite size.  So the reference gets an emitter shape
(:class:`bench.reference.scene.RefEmitter`) and our engine its counterpart light
(``RefEmitter.engine_light``):

* ``*_near``: a uniform spherical emitter of radius a = 0.3 d at d = 2.5 r from the object's
  centre (r: the sphere's radius, 12 mm; the bunny's half bounding-box diagonal, 20 mm), i.e. 18 mm
  from the sphere's surface.  Engine: a **point light** at its centre with the same radiant
  intensity I = pi a^2 L [W/sr, a in metres] -- the irradiance of a uniform sphere is exactly that
  of such a point wherever the sphere lies wholly above a surface point's horizon.
* ``*_far``: the same at d = 25 r (a 300 mm-away sphere of radius 90 mm for the 12 mm sphere): the
  same angular size, a far-field light.  Engine: the same point light, 10x further.
* ``*_area``: a one-sided square emitter of side 2h, h = a sqrt(pi) / 2 (so its area equals the
  sphere's cross-section and the same solid angle is hit), at the near position, facing the
  object's centre.  Engine: an **area light** of intensity L (2h)^2 along its normal, which the
  engine models as a point with a cosine lobe (far field).

The radiance L = (d / a)^2 = 11.1 W/(m^2 sr) makes the irradiance at the object's centre pi W/m^2
(a Lambertian plane facing the light would read radiance 1), as the sky scenes' lobe does.

The light comes from the right, above and in front (``LIGHT_DIR``); the camera looks along -z, so
the image shows the lit side on the right and light that crossed the object on the left.  The size
is a compromise: the reference hits the emitter only by chance (a fraction of about
(1 - cos asin(a/d)) of the paths that leave the lit side), so a smaller emitter costs
quadratically more samples for the same noise; a/d = 0.3 gave noise floors of 6.3 % (near sphere,
2048 spp per channel, 21 min), 13.1 % (near bunny, 1024 spp, 11 min), 12.7 % (far sphere, 1024 spp,
14 min) and 10.0 % (square, 1024 spp, 11 min) on 2 cores shared with other jobs (load average ~10).

**Spot lights are not in the set.**  A spot needs a hard-edged cone: the emitter inside a black
shade with an opening (``RefEmitter("shaded_sphere")``).  The shade must be several times larger
than the emitter for a sharp edge (penumbra +-asin(a / shade radius)), and must stay clear of the
object, so the emitter seen from the object is small: with a = 3 mm in a 12 mm shade 40 mm away
(penumbra +-14 degrees) the path tracer hits it about (0.075 / 0.3)^2 = 16x less often than the
near sphere, i.e. about 16x the samples for the same noise floor (estimated from the near sphere's
cost: 7 min per channel for 2048 spp on these shared cores, so about 2 h per channel).  The shaded
sphere itself renders as it should (``tests/test_light_reference.py``: light through the opening,
exactly none with the opening turned away).
"""

from __future__ import annotations

import numpy as np

from bench import accuracy_scenes as S
from bench.reference.scene import RefEmitter, RefScene

LIGHT_DIR = (0.7, 0.5, 0.5)  # towards the light: right, up, towards the camera
NEAR, FAR = 2.5, 25.0  # emitter centre distance / object radius
SIZE = 0.3  # emitter radius / its distance
OBJECT_RADIUS_MM = {"sphere": S.SPHERE_RADIUS_MM, "bunny": 0.5 * S.BUNNY_SIZE_MM}
# (mesh, material, light, spp per channel): rendered once, cached in bench/data/reference
REFERENCES = (
    ("sphere", "marble", "near", 2048),
    ("bunny", "marble", "near", 1024),
    ("sphere", "marble", "far", 1024),
    ("sphere", "marble", "area", 1024),
)
BATCHES = 8  # independent renders per channel: the noise floor's estimate


def emitter(mesh_name: str, light: str, V, mm_per_unit: float) -> RefEmitter:
    """The scene's emitter in object units (see the module docstring)."""
    lo, hi = V.min(axis=0), V.max(axis=0)
    centre = 0.5 * (lo + hi)
    s = np.asarray(LIGHT_DIR, dtype=np.float64)
    s /= np.linalg.norm(s)
    r = OBJECT_RADIUS_MM[mesh_name] / mm_per_unit
    d = (FAR if light == "far" else NEAR) * r
    a = SIZE * d
    L = (d / a) ** 2
    pos = tuple(float(x) for x in centre + d * s)
    if light in ("near", "far"):
        return RefEmitter("sphere", pos, a, (L, L, L))
    if light == "area":
        return RefEmitter("rectangle", pos, 0.5 * a * np.sqrt(np.pi), (L, L, L), direction=tuple(-s))
    raise ValueError(f"light must be 'near', 'far' or 'area', got {light!r}")


def make_scene(mesh_name: str, material_name: str, light: str, *, res: int = S.REF_RES, spp: int = 1024,
               seed: int = 0) -> RefScene:
    V, F, mpu = S.mesh(mesh_name)
    em = emitter(mesh_name, light, V, mpu)
    return RefScene(V, F, mpu, S.material(material_name), S.camera_for(V, (res, res)), emitters=(em,),
                    field=S.field_for(material_name, mpu, V), resolution=(res, res), spp=spp, seed=seed,
                    name=f"{mesh_name}_{material_name}_{light}")


def reference_scenes():
    return [make_scene(m, mat, light, spp=spp) for m, mat, light, spp in REFERENCES]


def get_reference(scene, refresh: bool = False, progress=None):
    """The cached reference (``bench/data/reference``, rendered on a miss), ``BATCHES`` batches."""
    from bench.reference.mitsuba_ref import cached_reference, scene_key

    d = S.reference_dir(False)
    if refresh:
        for p in d.glob(f"{scene.name}-{scene_key(scene, batches=BATCHES)}.npz"):
            p.unlink()
    return cached_reference(scene, d, batches=BATCHES, progress=progress)


if __name__ == "__main__":  # render the references:  nice -n 15 python -m bench.light_scenes [name ...]
    import sys
    import time

    from bench.reference.metrics import noise_floor

    want = sys.argv[1:]
    for sc in reference_scenes():
        if want and sc.name not in want:
            continue
        t = time.time()
        r = get_reference(sc, progress=lambda m, n=sc.name: print(f"  [{n}] {m}", flush=True))
        print(f"{sc.name}: {r.spp} spp, {r.seconds:.0f} s render ({time.time() - t:.0f} s now), "
              f"noise floor {noise_floor(r.image, r.stderr, r.mask):.4f}", flush=True)
