# SPDX-License-Identifier: GPL-3.0-or-later
"""Independent path-traced reference for a :class:`~bench.reference.scene.RefScene` (Mitsuba 3).

None of this code comes from our solver.  The physics maps one to one
(``docs/reference.md``):

* boundary: Mitsuba ``dielectric`` with ``int_ior = eta``, ``ext_ior = 1``;
* interior: ``homogeneous`` (or ``heterogeneous`` with ``gridvolume``s) medium
  with ``sigma_t = sigma_a + sigma_s'``, ``albedo = sigma_s' / sigma_t`` and an
  isotropic phase function (``g = 0``, so ``sigma_s = sigma_s'``);
* the scene is built **in millimetres** (vertices x ``mm_per_unit``), so the
  per-mm coefficients apply unchanged.  Environment radiance is scale-free.
  Delta lights (sun, point, spot) are refused: behind a smooth dielectric a
  volumetric path tracer cannot reach them at all (``_emitters``);
* ``volpath``, ``max_depth = -1``, Russian roulette off (``rr_depth = 1e9``):
  roulette ruins high-albedo references (measured here: a white-furnace
  sphere gave about 0.80 instead of 1.0 at 1024 spp with the default ``rr_depth``).

Two measures keep the reference exact *and* low-noise:

* **one render per colour channel** with grey coefficients and grey lights.
  In an RGB render Mitsuba samples free paths with one channel and reweights
  the others; over hundreds of scattering events those ratios multiply into
  a heavy-tailed estimator (per-pixel noise 10-40x larger at the same spp on
  the marble sphere).  A grey medium has no such ratios.
* **translucency only**: each channel is also rendered with the interior
  replaced by a perfect absorber (``albedo 0``, ``sigma_t = 1e6 /mm``).  That
  image holds exactly the paths that never enter the medium (surface
  reflections, the environment beside the object); the plain render minus it
  holds exactly the paths that do, internal reflections included.  The
  absorber render is cheap (its paths end at the first refraction), so it gets
  ``reflection_spp_factor`` x the samples and independent seeds: the plain
  render's own variance is small when the transmitted light is about as bright
  as the reflected environment, whereas subtracting sample by sample would
  keep the full Bernoulli noise of Mitsuba's reflect-or-refract choice.

The mask is Mitsuba's own: a 1-spp ``aov`` depth render with an unjittered
stratified sampler, i.e. exactly the pixel-centre primary rays.
"""

from __future__ import annotations

import math
import os
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .scene import RefScene

ABSORBER_SIGMA_T = 1.0e6  # per mm: a mean free path of 1 nm
RR_OFF = 1_000_000_000  # rr_depth: Russian roulette never starts
MAX_LANES = 1 << 21  # LLVM wavefront size per mi.render call (memory bound)
MIN_LLVM = (19, 0, 0)  # libLLVM 15 and 16 abort with "Cannot select ... fminimum"; 19 is verified
VARIANT_ENV = "TRANSLUCENCY_MITSUBA_VARIANT"


@dataclass
class RefResult:
    image: np.ndarray  # (H, W, 3) translucency only (reflection subtracted), W/(m^2 sr)
    mask: np.ndarray  # (H, W) bool: the pixel-centre primary ray hits the mesh
    stderr: np.ndarray  # (H, W, 3) standard error of the mean of `image`, from independent batches
    seconds: float  # wall time of all renders (mask included)
    spp: int  # samples per pixel actually used, per channel
    reflection: np.ndarray | None = None  # (H, W, 3) the absorber render: surface reflection + background
    variant: str = ""
    batches: int = 0

    @property
    def full(self) -> np.ndarray:
        """What a plain render shows: translucency plus the surface's own reflection."""
        return self.image if self.reflection is None else self.image + self.reflection


# --- variant -------------------------------------------------------------------------

_VARIANT: str | None = None


def select_variant(preferred: str | None = None) -> str:
    """Set (once per process) and return the Mitsuba variant.

    ``preferred`` or ``$TRANSLUCENCY_MITSUBA_VARIANT`` wins; the default is
    ``scalar_rgb``.  ``llvm_ad_mono`` / ``llvm_ad_rgb`` work too, but need a
    libLLVM >= 19 (``DRJIT_LIBLLVM_PATH``; Debian 12's libLLVM 15 and 16 abort
    the process on the first kernel with "Cannot select ... fminimum"), and
    were *slower* here: 1024 spp of the grey marble sphere at 32x32 took
    18.4 s scalar, 22.8 s llvm_ad_mono, 30.3 s llvm_ad_rgb on 2 cores (the
    long, divergent random walks suit a per-thread loop better than a wavefront).
    """
    global _VARIANT
    import mitsuba as mi

    want = preferred or os.environ.get(VARIANT_ENV) or _VARIANT or "scalar_rgb"
    if want.startswith("llvm"):
        import drjit as dr

        if not dr.has_backend(dr.JitBackend.LLVM) or tuple(dr.detail.llvm_version()) < MIN_LLVM:
            raise RuntimeError(
                f"Mitsuba variant {want} needs libLLVM >= {'.'.join(map(str, MIN_LLVM))} "
                "(set DRJIT_LIBLLVM_PATH); older versions abort the process")
    if mi.variant() != want:
        mi.set_variant(want)
    _VARIANT = want
    return want


def _is_mono(variant: str) -> bool:
    return "_mono" in variant


# --- scene dictionary ----------------------------------------------------------------

def _grey(value: float, variant: str):
    v = float(value)
    if _is_mono(variant):
        return v
    return {"type": "rgb", "value": [v, v, v]}


def _write_ply(path: Path, V: np.ndarray, F: np.ndarray) -> None:
    with open(path, "wb") as fh:
        fh.write(
            (
                "ply\nformat binary_little_endian 1.0\n"
                f"element vertex {len(V)}\nproperty float x\nproperty float y\nproperty float z\n"
                f"element face {len(F)}\nproperty list uchar int vertex_indices\nend_header\n"
            ).encode("ascii")
        )
        fh.write(np.ascontiguousarray(V, dtype="<f4").tobytes())
        rec = np.zeros(len(F), dtype=[("n", "u1"), ("i", "<i4", (3,))])
        rec["n"] = 3
        rec["i"] = F
        fh.write(rec.tobytes())


def _object(scene: RefScene, ply_path: Path) -> dict:
    """The boundary shape in mm: the mesh (PLY) or, if requested, the exact sphere."""
    if scene.analytic_sphere is not None:
        import mitsuba as mi

        centre, radius = scene.analytic_sphere
        s = scene.mm_per_unit
        return {"type": "sphere", "to_world": mi.ScalarTransform4f().translate([float(c) * s for c in centre])
                @ mi.ScalarTransform4f().scale(float(radius) * s)}
    if not ply_path.exists():
        _write_ply(ply_path, scene.V * scene.mm_per_unit, scene.F)
    return {"type": "ply", "filename": str(ply_path), "face_normals": not scene.smooth_normals}


def _look_at(mi, origin, target, up):
    T = mi.ScalarTransform4f
    return T().look_at(origin=[float(x) for x in origin], target=[float(x) for x in target], up=[float(x) for x in up])


def _sensor_dict(scene: RefScene, mi, sampler: dict, pixel_format: str) -> dict:
    s = scene.mm_per_unit
    cam = scene.camera
    W, H = scene.resolution
    r, u, f = cam.basis()
    lo, hi = scene.bbox
    diag_mm = float(np.linalg.norm(hi - lo)) * s
    film = {"type": "hdrfilm", "width": W, "height": H, "rfilter": {"type": "box"},
            "pixel_format": pixel_format, "component_format": "float32"}
    p = np.asarray(cam.position) * s
    if cam.kind == "orthographic":
        # Back the origin off so the whole object lies in front of the near plane.
        centre = 0.5 * (lo + hi) * s
        back = float((centre - p) @ f) + 2.0 * diag_mm + 1.0
        origin = p - back * f
        half = 0.5 * cam.width * s
        to_world = _look_at(mi, origin, origin + f, u) @ mi.ScalarTransform4f().scale([half, half, 1.0])
        return {"type": "orthographic", "to_world": to_world, "near_clip": 1e-3, "far_clip": back + 4.0 * diag_mm + 10.0,
                "film": film, "sampler": sampler}
    return {"type": "perspective", "to_world": _look_at(mi, p, p + f, u), "fov": float(cam.fov_deg), "fov_axis": "y",
            "near_clip": 1e-3 * max(diag_mm, 1.0), "far_clip": 1e3 * max(diag_mm, 1.0) + float(np.linalg.norm(p)),
            "film": film, "sampler": sampler}


class DeltaLightError(NotImplementedError):
    """The reference cannot render a delta light behind a smooth dielectric (see :func:`_emitters`)."""


ENVMAP_WIDTH = 512  # lat-long map for an SH environment; bilinear error < 1e-4 for order-2 SH


def environment_radiance(env, dirs: np.ndarray) -> np.ndarray:
    """The engine's environment radiance at unit directions (n, 3) -> (n, 3) (the scene
    description's own ``Environment.radiance_at``)."""
    return env.radiance_at(dirs)


def _envmap_bitmap(env, channel: int, variant: str, mi, width: int = ENVMAP_WIDTH):
    """Mitsuba's ``envmap`` lat-long layout (measured against ``Emitter.eval``): column ``c`` at
    ``phi = 2 pi (c + 0.5) / W``, row ``r`` at ``theta = pi r / (H - 1)``, Y up, direction
    ``(sin t sin p, cos t, -sin t cos p)``."""
    H = width // 2
    phi = 2.0 * np.pi * (np.arange(width) + 0.5) / width
    theta = np.pi * np.arange(H) / (H - 1)
    P, T = np.meshgrid(phi, theta)
    d = np.stack([np.sin(T) * np.sin(P), np.cos(T), -np.sin(T) * np.cos(P)], axis=-1).reshape(-1, 3)
    L = environment_radiance(env, d)[:, channel].reshape(H, width)
    if L.min() < -1e-6 * max(abs(L).max(), 1e-30):
        raise ValueError(f"the environment radiance is negative in places (min {L.min():.3g}); "
                         "an SH environment must be non-negative to be rendered")
    L = np.maximum(L, 0.0).astype(np.float32)
    data = L[..., None] if _is_mono(variant) else np.repeat(L[..., None], 3, axis=-1)
    return mi.Bitmap(np.ascontiguousarray(data))


def _emitters(scene: RefScene, channel: int, variant: str, mi) -> dict:
    """Mitsuba emitters for one channel: the environment (uniform: ``constant``; with SH: ``envmap``).

    Delta lights (the engine's sun, point, spot and far-field area lights) are refused.  Behind a
    smooth dielectric they contribute *exactly nothing* to a volumetric path tracer: next-event
    shadow rays stop at the (non-null) boundary, and a refracted path leaving the object hits a
    delta light with probability zero (a sun-only marble sphere renders black, measured).  Light
    the reference with an environment instead: :func:`bench.reference.scene.sky_environment`
    is a directional sky that the engine represents exactly (order-2 SH).
    """
    if scene.lights:
        kinds = ", ".join(sorted({l.kind for l in scene.lights}))
        raise DeltaLightError(
            f"the reference cannot render delta lights ({kinds}) inside a smooth dielectric: volpath can "
            "neither shadow-test through the boundary nor hit a delta light by refraction, so their "
            "translucency is black. Use an environment (uniform, or bench.reference.scene.sky_environment).")
    out = {}
    for k, em in enumerate(scene.emitters):
        out.update(_area_emitter(scene, em, k, channel, variant, mi))
    env = scene.environment
    if env is not None and not env.is_black:
        if env.sh is not None and np.any(env.sh):
            out["environment"] = {"type": "envmap", "bitmap": _envmap_bitmap(env, channel, variant, mi)}
        else:
            value = float(env.radiance[channel])
            if value > 0:
                out["environment"] = {"type": "constant", "radiance": _grey(value, variant)}
    return out


def _area_emitter(scene: RefScene, em, k: int, channel: int, variant: str, mi) -> dict:
    """Mitsuba shapes for one :class:`~bench.reference.scene.RefEmitter` (in mm), black where they do
    not emit (a path that hits them ends there).  A sphere emits on its whole surface, a rectangle
    on the side its normal faces (Mitsuba's ``area`` emitter is one-sided, towards the shape's
    normal); a shaded sphere adds its black shade (an open mesh) around the sphere."""
    s = scene.mm_per_unit
    black = {"type": "diffuse", "reflectance": _grey(0.0, variant)}
    light = {"type": "area", "radiance": _grey(float(em.radiance[channel]), variant)}
    c = [float(x) * s for x in em.position]
    if em.kind in ("sphere", "shaded_sphere"):
        out = {f"emitter_{k}": {"type": "sphere", "center": c, "radius": float(em.radius) * s, "bsdf": black,
                                "emitter": light}}
        if em.kind == "shaded_sphere":
            V, F = em.shade_mesh()
            path = Path(_scratch_ply()).with_name(f"shade{k}.ply")
            _write_ply(path, V * s, F)
            out[f"shade_{k}"] = {"type": "ply", "filename": str(path), "face_normals": True, "bsdf": black}
        return out
    d = np.asarray(em.direction, dtype=np.float64)
    d = d / np.linalg.norm(d)
    up = np.array([0.0, 0.0, 1.0]) if abs(d[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    h = float(em.radius) * s
    to_world = _look_at(mi, c, np.asarray(c) + d, up) @ mi.ScalarTransform4f().scale([h, h, 1.0])
    return {f"emitter_{k}": {"type": "rectangle", "to_world": to_world, "bsdf": black, "emitter": light}}


def _grid_points(scene: RefScene):
    """Voxel centres over the mesh bbox (object units), the grid shape (nx, ny, nz) and the bbox."""
    lo, hi = scene.bbox
    ext = hi - lo
    pad = 1e-3 * float(ext.max())
    lo, hi = lo - pad, hi + pad
    ext = hi - lo
    n = np.maximum(np.round(scene.grid_resolution * ext / ext.max()).astype(int), 4)
    axes = [lo[k] + (np.arange(n[k]) + 0.5) / n[k] * ext[k] for k in range(3)]
    Z, Y, X = np.meshgrid(axes[2], axes[1], axes[0], indexing="ij")  # Mitsuba's (z, y, x) layout
    pts = np.stack([X, Y, Z], axis=-1).reshape(-1, 3)
    return pts, (int(n[0]), int(n[1]), int(n[2])), lo, hi


def _medium(scene: RefScene, channel: int, variant: str, mi, absorber: bool, grid_cache: dict) -> dict:
    phase = {"type": "isotropic"}
    if absorber:
        return {"type": "homogeneous", "sigma_t": _grey(1.0, variant), "scale": ABSORBER_SIGMA_T,
                "albedo": _grey(0.0, variant), "phase": phase}
    if not scene.material.heterogeneous:
        sa, ss = scene.material.coefficients(n=1)
        st = float(sa[0, channel] + ss[0, channel])
        return {"type": "homogeneous", "sigma_t": _grey(1.0, variant), "scale": st,
                "albedo": _grey(float(ss[0, channel]) / st, variant), "phase": phase}
    if "grid" not in grid_cache:
        pts, shape, lo, hi = _grid_points(scene)
        sa, ss = scene.coefficients(pts)  # the engine's own mixing rule
        grid_cache["grid"] = (sa, ss, shape, lo, hi)
    sa, ss, (nx, ny, nz), lo, hi = grid_cache["grid"]
    st = sa[:, channel] + ss[:, channel]
    alb = np.divide(ss[:, channel], st, out=np.zeros_like(st), where=st > 0)
    smax = float(st.max())
    s = scene.mm_per_unit
    to_world = mi.ScalarTransform4f().translate((lo * s).tolist()) @ mi.ScalarTransform4f().scale(((hi - lo) * s).tolist())

    def vol(values):
        data = np.ascontiguousarray(values.reshape(nz, ny, nx, 1), dtype=np.float32)
        return {"type": "gridvolume", "grid": mi.VolumeGrid(data), "to_world": to_world, "filter_type": "nearest"}

    return {"type": "heterogeneous", "sigma_t": vol(st / smax), "scale": smax, "albedo": vol(alb), "phase": phase}


def scene_dict(scene: RefScene, channel: int, *, absorber: bool = False, variant: str | None = None,
               ply_path: str | os.PathLike | None = None, max_depth: int = -1,
               _grid_cache: dict | None = None) -> dict:
    """The Mitsuba scene dictionary for one colour channel (0, 1, 2).

    ``absorber=True`` swaps the medium for a perfect absorber (the reflection-only render).
    ``ply_path``: where the mesh (in mm) is written; a temporary file by default.
    ``max_depth`` -1 (unlimited) is the reference; a finite value only mimics
    another renderer's bounce cap (``cycles_ref``).
    """
    import mitsuba as mi

    variant = variant or select_variant()
    if ply_path is None:
        ply_path = _scratch_ply()
    pixel_format = "luminance" if _is_mono(variant) else "rgb"
    obj = _object(scene, Path(ply_path))
    obj["bsdf"] = {"type": "dielectric", "int_ior": float(scene.material.eta), "ext_ior": 1.0}
    obj["interior"] = _medium(scene, channel, variant, mi, absorber, {} if _grid_cache is None else _grid_cache)
    parts = {}
    if scene.parts and not absorber:  # the absorber render ends every path at the outer surface
        parts = _parts(scene, channel, variant, Path(ply_path))
        parts["object_medium"] = obj["interior"]
        obj["interior"] = {"type": "ref", "id": "object_medium"}
    d = {
        "type": "scene",
        "integrator": {"type": "volpath", "max_depth": int(max_depth), "rr_depth": RR_OFF},
        "sensor": _sensor_dict(scene, mi, {"type": "independent", "sample_count": scene.spp}, pixel_format),
        "object": obj,
    }
    d.update(_emitters(scene, channel, variant, mi))
    d.update(parts)
    return d


def _parts(scene: RefScene, channel: int, variant: str, ply_path: Path) -> dict:
    """Shapes of the inner parts: a dielectric with the object's medium outside and the part's inside
    (air in a cavity), or a black diffuse surface for an opaque part.  Parts must not touch or nest."""
    out = {}
    s = scene.mm_per_unit
    eta_out = float(scene.material.eta)
    for k, part in enumerate(scene.parts):
        path = ply_path.with_name(f"part{k}.ply")
        if not path.exists():
            _write_ply(path, np.asarray(part.V) * s, np.asarray(part.F))
        shape = {"type": "ply", "filename": str(path), "face_normals": not scene.smooth_normals,
                 "exterior": {"type": "ref", "id": "object_medium"}}
        if part.role == "opaque":
            shape["bsdf"] = {"type": "diffuse", "reflectance": _grey(0.0, variant)}
        else:
            eta_in = 1.0 if part.role == "cavity" else float(part.eta)
            shape["bsdf"] = ({"type": "null"} if eta_in == eta_out else
                             {"type": "dielectric", "int_ior": eta_in, "ext_ior": eta_out})
            if part.role == "medium":
                sa, ss = (np.asarray(x, dtype=np.float64) for x in part.medium.arrays())
                st = float(sa[channel] + ss[channel])
                shape["interior"] = {"type": "homogeneous", "sigma_t": _grey(1.0, variant), "scale": st,
                                     "albedo": _grey(float(ss[channel]) / st, variant), "phase": {"type": "isotropic"}}
        out[f"part_{k}"] = shape
    return out


_SCRATCH: tempfile.TemporaryDirectory | None = None


def _scratch_ply() -> Path:
    """A PLY path in a per-process scratch directory (removed at exit)."""
    global _SCRATCH
    if _SCRATCH is None:
        _SCRATCH = tempfile.TemporaryDirectory(prefix="translucency-ref-")
    return Path(tempfile.mkdtemp(dir=_SCRATCH.name)) / "object.ply"


# --- rendering -------------------------------------------------------------------------

def render_mask(scene: RefScene, variant: str | None = None, ply_path=None) -> np.ndarray:
    """(H, W) bool: Mitsuba's pixel-centre primary ray hits the mesh (1 spp, unjittered, depth AOV)."""
    import mitsuba as mi

    variant = variant or select_variant()
    if ply_path is None:
        ply_path = _scratch_ply()
    sampler = {"type": "stratified", "sample_count": 1, "jitter": False}
    d = {
        "type": "scene",
        "integrator": {"type": "aov", "aovs": "dd.y:depth"},
        "sensor": _sensor_dict(scene, mi, sampler, "luminance" if _is_mono(variant) else "rgb"),
        "object": _object(scene, Path(ply_path)),
    }
    img = np.array(mi.render(mi.load_dict(d), spp=1, seed=0))
    depth = img[..., -1]
    return depth > 0


def _render_channel(mi, scene_obj, spp: int, seed: int) -> np.ndarray:
    img = np.array(mi.render(scene_obj, spp=spp, seed=seed), dtype=np.float64)
    return img[..., 0] if img.ndim == 3 else img


def render_reference(
    scene: RefScene,
    *,
    spp: int | None = None,
    batches: int = 4,
    variant: str | None = None,
    subtract_reflection: bool = True,
    reflection_spp_factor: int = 8,
    max_depth: int = -1,
    minus: RefScene | None = None,
    progress=None,
) -> RefResult:
    """Path-trace ``scene`` and return the translucency-only image with its noise.

    ``spp`` (default ``scene.spp``) is per pixel and per channel; it is split
    into ``batches`` >= 2 independent renders (more when the LLVM wavefront would
    exceed ``MAX_LANES``), whose spread gives ``stderr``.  The absorber
    (reflection) render gets ``reflection_spp_factor`` x ``spp``; its noise is in
    ``stderr`` too.  ``progress(msg)`` is called after each render.
    ``subtract_reflection=False`` returns the plain render in ``image``
    (``reflection`` is then None).  ``max_depth`` other than -1 (unlimited)
    is for cross-checks only.

    ``minus``: a scene of the same geometry, camera and extinction whose
    render is subtracted *sample by sample*: each of its renders takes the
    same seed and samples per pixel as the matching render of ``scene``, so
    every Mitsuba lane follows the same path in both until the first event
    where the two differ.  With ``minus`` = the scene without scattering
    (sigma_s = 0, the same sigma_t, so the free paths are drawn alike), a
    lane's difference is exactly the light of its scattered paths: the
    unscattered light and the surface reflection cancel lane by lane instead
    of adding their noise (``image`` is then the scattered light, with no
    absorber render; ``reflection`` is None).
    """
    import mitsuba as mi

    t0 = time.perf_counter()
    variant = select_variant(variant)
    W, H = scene.resolution
    spp = int(spp or scene.spp)
    batches = max(int(batches), 2)
    k_refl = 1 if minus is not None else max(int(reflection_spp_factor), 1)  # minus: no absorber render
    if variant.startswith(("llvm", "cuda")):
        batches = max(batches, math.ceil(W * H * spp * k_refl / MAX_LANES))
    spp_batch = max(1, math.ceil(spp / batches))
    env = scene.environment
    grey_lights = env is None or (len(set(env.radiance)) == 1 and (env.sh is None or np.allclose(env.sh, env.sh[:, :1])))
    grey_lights = grey_lights and all(len(set(em.radiance)) == 1 for em in scene.emitters)
    _emitters(scene, 0, variant, mi)  # refuse what cannot be rendered before any work
    with tempfile.TemporaryDirectory(prefix="translucency-ref-") as tmp:
        ply = Path(tmp) / "object.ply"
        mask = render_mask(scene, variant, ply)
        full = np.zeros((batches, H, W, 3))
        refl = np.zeros((batches, H, W, 3))
        grid_cache: dict = {}
        for c in range(3):
            plain = mi.load_dict(scene_dict(scene, c, variant=variant, ply_path=ply, max_depth=max_depth,
                                            _grid_cache=grid_cache))
            absorb = None
            if minus is not None:
                absorb = mi.load_dict(scene_dict(minus, c, variant=variant, ply_path=ply, max_depth=max_depth,
                                                 _grid_cache={}))
            elif subtract_reflection and not (grey_lights and c > 0):
                absorb = mi.load_dict(scene_dict(scene, c, absorber=True, variant=variant, ply_path=ply))
            for b in range(batches):
                seed = (scene.seed * 1_000_003 + c * 10_007 + b * 101 + 1) & 0x7FFFFFFF
                full[b, ..., c] = _render_channel(mi, plain, spp_batch, seed)
                if minus is not None:  # the same seed: lane by lane the same path until they differ
                    refl[b, ..., c] = _render_channel(mi, absorb, spp_batch, seed)
                elif absorb is not None:
                    refl[b, ..., c] = _render_channel(mi, absorb, spp_batch * k_refl, seed ^ 0x5BD1E995)
                elif subtract_reflection:
                    refl[b, ..., c] = refl[b, ..., 0]
                if progress is not None:
                    progress(f"channel {c} batch {b + 1}/{batches}: {time.perf_counter() - t0:.1f} s")
    diff = full - refl
    image = diff.mean(axis=0)
    stderr = diff.std(axis=0, ddof=1) / math.sqrt(batches)
    return RefResult(image=image, mask=mask, stderr=stderr, seconds=time.perf_counter() - t0, spp=spp_batch * batches,
                     reflection=refl.mean(axis=0) if subtract_reflection and minus is None else None, variant=variant,
                     batches=batches)


# --- cache ---------------------------------------------------------------------------

def scene_key(scene: RefScene, **render_kwargs) -> str:
    """A hash of everything that changes the reference image (mesh, scale, material,
    field, lights, camera, resolution, seed, spp and the render options)."""
    import hashlib
    import json

    h = hashlib.sha256()
    h.update(np.ascontiguousarray(scene.V, dtype=np.float64).tobytes())
    h.update(np.ascontiguousarray(scene.F, dtype=np.int64).tobytes())
    desc = {
        "mm_per_unit": scene.mm_per_unit, "material": repr(scene.material), "field": repr(scene.field),
        "lights": [repr(l) for l in scene.lights],
        # floats, not numpy scalars: numpy 2 writes np.float64(0.0) where the cached keys have 0.0
        "environment": None if scene.environment is None
        else repr(tuple(float(x) for x in scene.environment.radiance)),
        "environment_sh": None if scene.environment is None or scene.environment.sh is None
        else np.asarray(scene.environment.sh, dtype=np.float64).round(12).tolist(),
        "camera": repr(scene.camera), "resolution": scene.resolution, "spp": scene.spp, "seed": scene.seed,
        "smooth": scene.smooth_normals, "grid": scene.grid_resolution, "sphere": repr(scene.analytic_sphere),
        "render": {k: scene_key(v) if isinstance(v, RefScene) else repr(v) for k, v in sorted(render_kwargs.items())},
        "version": 1,
    }
    if scene.emitters:  # added with issue 17: scenes without emitters keep their keys
        desc["emitters"] = [repr(e) for e in scene.emitters]
    if scene.parts:  # added with issue 15: scenes without parts keep the keys they always had
        desc["parts"] = [[p.name, p.role, repr(p.medium), p.eta] for p in scene.parts]
        for p in scene.parts:
            h.update(np.ascontiguousarray(p.V, dtype=np.float64).tobytes())
            h.update(np.ascontiguousarray(p.F, dtype=np.int64).tobytes())
    h.update(json.dumps(desc, sort_keys=True).encode())
    return h.hexdigest()[:20]


def cached_reference(scene: RefScene, cache_dir, **render_kwargs) -> RefResult:
    """:func:`render_reference` with an ``.npz`` cache (``allow_pickle=False``) keyed by :func:`scene_key`."""
    cache_dir = Path(cache_dir)
    cache_dir.mkdir(parents=True, exist_ok=True)
    kw = {k: v for k, v in render_kwargs.items() if k != "progress"}
    path = cache_dir / f"{scene.name}-{scene_key(scene, **kw)}.npz"
    if path.exists():
        with np.load(path, allow_pickle=False) as z:
            return RefResult(image=z["image"], mask=z["mask"], stderr=z["stderr"], seconds=float(z["seconds"]),
                             spp=int(z["spp"]), reflection=z["reflection"] if z["has_reflection"] else None,
                             variant=str(z["variant"]), batches=int(z["batches"]))
    res = render_reference(scene, **render_kwargs)
    tmp = path.with_suffix(".tmp.npz")
    np.savez_compressed(tmp, image=res.image, mask=res.mask, stderr=res.stderr, seconds=res.seconds, spp=res.spp,
                        reflection=res.reflection if res.reflection is not None else np.zeros(0),
                        has_reflection=res.reflection is not None, variant=res.variant, batches=res.batches)
    tmp.replace(path)
    return res
