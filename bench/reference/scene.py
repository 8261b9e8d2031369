# SPDX-License-Identifier: GPL-3.0-or-later
"""A matched scene: everything the path-traced reference and our solver must share.

Conventions (see ``docs/reference.md``):

* Geometry ``V`` (n, 3) and ``F`` (m, 3) are in **object units**; ``mm_per_unit``
  converts them to millimetres, like a bake (``docs/architecture.md``).
* The material is a :class:`translucency_addon.scene.materials.Material` (per-mm
  ``sigma_a`` and reduced ``sigma_s'``, ``eta``); an optional
  :class:`translucency_addon.scene.fields.FieldSpec` mixes its two media.
* Lights are :class:`translucency_addon.scene.lights.Light` in object space (point
  intensity in W/sr with 1/r^2 in metres, sun irradiance in W/m^2) plus an
  optional uniform :class:`~translucency_addon.scene.lights.Environment`.
* The camera is orthographic or perspective (:class:`Camera`).  Pixel ``(i, j)``
  is row ``i`` from the **top**, column ``j`` from the **left**; its centre is
  at ``((j + 0.5) / W, (i + 0.5) / H)`` of the image.  The camera's right vector
  is ``normalize(direction x up)``, so ``up`` points to the top of the image.

Nothing here imports Mitsuba or bpy.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from translucency_addon.scene.fields import FieldSpec
from translucency_addon.scene.lights import Environment, Light
from translucency_addon.scene.materials import Material


def _unit(v, what: str) -> np.ndarray:
    a = np.asarray(v, dtype=np.float64).reshape(3)
    n = np.linalg.norm(a)
    if not np.isfinite(n) or n == 0:
        raise ValueError(f"{what} must be a non-zero finite 3-vector, got {v!r}")
    return a / n


@dataclass(frozen=True)
class Camera:
    """An orthographic or perspective pinhole camera in object space.

    * orthographic: ``position`` is the point at the image centre, ``direction``
      the viewing direction, ``width`` the image width in object units (the
      height is ``width * H / W``).  Rays start far behind ``position``, so
      the whole object is seen whatever ``position`` is along the view axis.
    * perspective: ``position`` is the eye, ``direction`` the optical axis,
      ``fov_deg`` the **vertical** field of view in degrees.
    """

    kind: str
    position: tuple[float, float, float]
    direction: tuple[float, float, float]
    up: tuple[float, float, float] = (0.0, 1.0, 0.0)
    width: float = 0.0  # orthographic
    fov_deg: float = 0.0  # perspective, vertical

    def __post_init__(self):
        if self.kind not in ("orthographic", "perspective"):
            raise ValueError(f"camera kind must be 'orthographic' or 'perspective', got {self.kind!r}")
        d = _unit(self.direction, "camera direction")
        u = _unit(self.up, "camera up")
        if abs(float(d @ u)) > 1.0 - 1e-9:
            raise ValueError("camera up is parallel to the view direction")
        if self.kind == "orthographic" and not (np.isfinite(self.width) and self.width > 0):
            raise ValueError(f"orthographic camera needs width > 0, got {self.width}")
        if self.kind == "perspective" and not (0.0 < self.fov_deg < 180.0):
            raise ValueError(f"perspective camera needs 0 < fov_deg < 180, got {self.fov_deg}")

    @classmethod
    def orthographic(cls, center, direction, up=(0.0, 1.0, 0.0), width=1.0) -> "Camera":
        return cls("orthographic", tuple(map(float, center)), tuple(map(float, direction)),
                   tuple(map(float, up)), width=float(width))

    @classmethod
    def perspective(cls, position, look_at, up=(0.0, 1.0, 0.0), fov_deg=40.0) -> "Camera":
        d = np.asarray(look_at, dtype=np.float64) - np.asarray(position, dtype=np.float64)
        return cls("perspective", tuple(map(float, position)), tuple(map(float, d)),
                   tuple(map(float, up)), fov_deg=float(fov_deg))

    def basis(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(right, up, forward)``: orthonormal, right-handed with right x up = -forward."""
        f = _unit(self.direction, "camera direction")
        r = np.cross(f, _unit(self.up, "camera up"))
        r /= np.linalg.norm(r)
        u = np.cross(r, f)
        return r, u, f

    def half_extent(self, resolution) -> tuple[float, float]:
        """Half width and half height of the image at unit distance (perspective) or in units (ortho)."""
        W, H = resolution
        if self.kind == "orthographic":
            hw = 0.5 * self.width
            return hw, hw * H / W
        hh = np.tan(np.radians(0.5 * self.fov_deg))
        return hh * W / H, hh

    def pixel_rays(self, resolution) -> tuple[np.ndarray, np.ndarray]:
        """Origins and unit directions (H, W, 3) of the pixel-centre rays, object space.

        Orthographic origins lie on the plane through ``position``; callers that
        need the whole object in front of the origin move them back along -forward.
        """
        W, H = resolution
        r, u, f = self.basis()
        hw, hh = self.half_extent(resolution)
        x = ((np.arange(W) + 0.5) / W * 2.0 - 1.0) * hw
        y = (1.0 - (np.arange(H) + 0.5) / H * 2.0) * hh
        X, Y = np.meshgrid(x, y)
        p = np.asarray(self.position, dtype=np.float64)
        if self.kind == "orthographic":
            o = p + X[..., None] * r + Y[..., None] * u
            d = np.broadcast_to(f, o.shape).copy()
        else:
            d = f + X[..., None] * r + Y[..., None] * u
            d /= np.linalg.norm(d, axis=-1, keepdims=True)
            o = np.broadcast_to(p, d.shape).copy()
        return o, d

    def project(self, P, resolution) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Object-space points (n, 3) -> continuous pixel coords ``(col, row)`` and view depth.

        ``col = j + 0.5`` at the centre of column ``j``.  Depth is the distance
        along ``forward`` from ``position`` (may be negative for orthographic).
        """
        W, H = resolution
        r, u, f = self.basis()
        q = np.asarray(P, dtype=np.float64) - np.asarray(self.position, dtype=np.float64)
        x, y, z = q @ r, q @ u, q @ f
        hw, hh = self.half_extent(resolution)
        if self.kind == "perspective":
            with np.errstate(divide="ignore", invalid="ignore"):
                x = x / z
                y = y / z
        col = (x / hw + 1.0) * 0.5 * W
        row = (1.0 - y / hh) * 0.5 * H
        return col, row, z


@dataclass(frozen=True)
class RefPart:
    """An inner part for the reference: a closed mesh (object units, outward) and what it is.

    ``role``: ``"medium"`` (``medium`` a translucency_addon Medium, ``eta`` its refractive index),
    ``"cavity"`` (air, eta 1) or ``"opaque"`` (a black absorber).  Interfaces are smooth
    dielectrics with the true indices on both sides: the reference keeps the refraction at inner
    interfaces that our passes neglect.
    """

    name: str
    V: np.ndarray
    F: np.ndarray
    role: str
    medium: object = None
    eta: float = 1.0


EMITTER_KINDS = ("sphere", "rectangle", "shaded_sphere")


@dataclass(frozen=True)
class RefEmitter:
    """An area emitter the path tracer can render, and its engine counterpart (issue 17).

    A delta light behind a smooth dielectric contributes nothing to a unidirectional path tracer
    (``mitsuba_ref._emitters``), but a path leaving the object can *hit* an emitter of finite size.
    Geometry in object units (like ``RefScene.V``); ``radiance`` in W/(m^2 sr) per channel.

    * ``"sphere"``: a uniform Lambertian sphere of ``radius`` centred at ``position``.  Seen from a
      point x at distance d >= radius whose tangent plane does not cut it, it gives the irradiance
      E = pi L (a / d)^2 cos(theta) *exactly* (a in the same unit as d), i.e. what a point light of
      radiant intensity I = pi a^2 L [W/sr, a in metres] at its centre gives (the engine's
      ``light_irradiance``: I / r^2 with r in metres).  Its power is 4 pi I = 4 pi^2 a^2 L
      [W]; a Blender point light of that power has I = P / (4 pi) (``ops/scene_inputs``).  The two
      differ only where the sphere is partly below a surface point's horizon or partly shadowed
      (the penumbra a point light does not have), and by the Fresnel factor's variation across
      the sphere's solid angle.
    * ``"rectangle"``: a one-sided Lambertian square of side ``2 * radius`` at ``position``,
      emitting towards ``direction``.  Radiant intensity I(w) = L A cos(w, n) with A its area in
      m^2: the engine's ``area`` light with the square's edges (``intensity = L A`` along the normal,
      integrated over the square; a Blender area light of power P has I = P / pi along its normal, so
      P = pi L A).
    * ``"shaded_sphere"``: the sphere inside a black spherical shade of radius ``shade_radius``
      with a circular opening of full angle ``cone_deg`` around ``direction``: a spot light with a
      hard edge (Blender's spot with blend 0) blurred by a penumbra of about
      +-asin(radius / shade_radius).  Mitsuba's own ``spot`` is a delta light, which it cannot
      render through the boundary.
    """

    kind: str
    position: tuple
    radius: float
    radiance: tuple = (1.0, 1.0, 1.0)
    direction: tuple = (0.0, 0.0, -1.0)
    cone_deg: float = 60.0
    shade_radius: float = 0.0

    def __post_init__(self):
        if self.kind not in EMITTER_KINDS:
            raise ValueError(f"emitter kind must be one of {', '.join(EMITTER_KINDS)}, got {self.kind!r}")
        if not (np.isfinite(self.radius) and self.radius > 0):
            raise ValueError(f"emitter radius must be > 0, got {self.radius}")
        if self.kind == "shaded_sphere" and not (self.shade_radius > self.radius and 0 < self.cone_deg < 180):
            raise ValueError("a shaded sphere needs shade_radius > radius and 0 < cone_deg < 180")
        if min(self.radiance) < 0:
            raise ValueError(f"emitter radiance must be >= 0, got {self.radiance}")

    def engine_light(self, mm_per_unit: float) -> Light:
        """The engine's counterpart (module docstring): same position, same radiant intensity."""
        a_m = self.radius * mm_per_unit * 1e-3
        col = tuple(float(c) for c in self.radiance)
        pos = tuple(float(x) for x in self.position)
        if self.kind == "sphere":
            return Light("point", color=col, intensity=np.pi * a_m * a_m, position=pos, radius=float(self.radius),
                         name="sphere emitter")
        if self.kind == "rectangle":
            # the square's edges as the reference places it (mitsuba_ref._area_emitter: look_at with this
            # up vector, then scaled by the half side): the engine integrates over them
            d = _unit(self.direction, "emitter direction")
            up = np.array([0.0, 0.0, 1.0]) if abs(d[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
            left = _unit(np.cross(up, d), "emitter edge")
            ex, ey = 2.0 * self.radius * left, 2.0 * self.radius * np.cross(d, left)
            return Light("area", color=col, intensity=(2.0 * a_m) ** 2, position=pos, direction=tuple(d),
                         edge_x=tuple(map(float, ex)), edge_y=tuple(map(float, ey)), name="rectangle emitter")
        return Light("spot", color=col, intensity=np.pi * a_m * a_m, position=pos,
                     direction=tuple(_unit(self.direction, "emitter direction")),
                     spot_size=float(np.radians(self.cone_deg)), spot_blend=0.0, name="shaded sphere emitter")

    def shade_mesh(self, segments: int = 96):
        """The shade of a ``shaded_sphere``: a UV sphere of ``shade_radius`` without the facets whose
        centroid lies inside the opening's cone (object units)."""
        V, F = uv_sphere(self.shade_radius, segments)
        d = _unit(self.direction, "emitter direction")
        z = np.array([0.0, 0.0, 1.0])
        # rotate +z onto d (Rodrigues), then move to the emitter's position
        v = np.cross(z, d)
        c = float(z @ d)
        if np.linalg.norm(v) < 1e-12:
            R = np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
        else:
            K = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
            R = np.eye(3) + K + K @ K / (1.0 + c)
        V = V @ R.T
        cen = V[F].mean(axis=1)
        cen /= np.linalg.norm(cen, axis=1, keepdims=True)
        keep = cen @ d < np.cos(np.radians(0.5 * self.cone_deg))
        return V + np.asarray(self.position, dtype=np.float64), F[keep]


@dataclass
class RefScene:
    """One matched scene for the reference renderer and for our solver."""

    V: np.ndarray  # (n, 3) object units
    F: np.ndarray  # (m, 3) int, outward (counter-clockwise seen from outside)
    mm_per_unit: float
    material: Material
    camera: Camera
    lights: list = field(default_factory=list)  # [Light]
    environment: Environment | None = None
    field: FieldSpec | None = None  # heterogeneous mix of material.medium_a/b
    resolution: tuple[int, int] = (32, 32)  # (W, H)
    spp: int = 1024
    seed: int = 0
    name: str = "scene"
    # Flat facets by default: Mitsuba's dielectric with interpolated shading normals does not
    # conserve energy (white furnace: pixels 0.99-1.04 instead of 1.000, docs/reference.md).
    smooth_normals: bool = False
    grid_resolution: int = 128  # voxels along the longest bbox axis for a heterogeneous medium
    # ((cx, cy, cz), radius) in object units: the reference renders this exact sphere instead of
    # the mesh (the mesh still defines the bbox, the heterogeneity grid and our side).
    analytic_sphere: tuple | None = None
    # Inner parts (issue 15): RefPart shapes inside the object, rendered with their own media and
    # interfaces (mitsuba_ref._parts).  Our side reads them as a translucency_addon CompositeObject.
    parts: tuple = ()
    # Area emitters (issue 17): RefEmitter shapes the path tracer renders; our side lights the
    # object with their engine counterparts (RefEmitter.engine_light).
    emitters: tuple = ()

    def __post_init__(self):
        self.V = np.asarray(self.V, dtype=np.float64).reshape(-1, 3)
        self.F = np.asarray(self.F, dtype=np.int64).reshape(-1, 3)
        if len(self.V) == 0 or len(self.F) == 0:
            raise ValueError("RefScene needs a non-empty mesh")
        if self.F.min() < 0 or self.F.max() >= len(self.V):
            raise ValueError("face indices out of range")
        if not (np.isfinite(self.mm_per_unit) and self.mm_per_unit > 0):
            raise ValueError(f"mm_per_unit must be > 0, got {self.mm_per_unit}")
        if self.material.heterogeneous and self.field is None:
            raise ValueError("a heterogeneous material needs a FieldSpec (RefScene.field)")
        for light in self.lights:
            if not isinstance(light, Light):
                raise TypeError(f"lights must be translucency_addon.scene.lights.Light, got {type(light).__name__}")
        for em in self.emitters:
            if not isinstance(em, RefEmitter):
                raise TypeError(f"emitters must be RefEmitter, got {type(em).__name__}")
        W, H = self.resolution
        self.resolution = (int(W), int(H))
        if min(self.resolution) < 1 or self.spp < 1:
            raise ValueError("resolution and spp must be positive")

    @property
    def bbox(self) -> tuple[np.ndarray, np.ndarray]:
        return self.V.min(axis=0), self.V.max(axis=0)

    def engine_lights(self) -> list:
        """The engine's lights for this scene: ``lights`` plus each emitter's counterpart."""
        return list(self.lights) + [em.engine_light(self.mm_per_unit) for em in self.emitters]

    def field_values(self, points) -> np.ndarray | None:
        """Mixing field at object-space points, or None for a homogeneous material."""
        if not self.material.heterogeneous:
            return None
        from translucency_addon.scene.fields import evaluate_field

        return evaluate_field(self.field, points)

    def coefficients(self, points) -> tuple[np.ndarray, np.ndarray]:
        """``(sigma_a, sigma_s')`` (n, 3) per mm at object-space points, exactly as the engine mixes them."""
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        return self.material.coefficients(self.field_values(pts), n=len(pts))


# --- meshes ------------------------------------------------------------------------------

def uv_sphere(radius: float = 1.0, segments: int = 32, rings: int | None = None):
    """A closed UV sphere, outward-oriented: ``segments`` around, ``rings`` (default segments/2) pole to pole."""
    segments = int(segments)
    rings = int(rings) if rings is not None else max(segments // 2, 2)
    if segments < 3 or rings < 2:
        raise ValueError("uv_sphere needs segments >= 3 and rings >= 2")
    theta = np.pi * np.arange(1, rings) / rings  # polar angle of the inner rings
    phi = 2.0 * np.pi * np.arange(segments) / segments
    T, P = np.meshgrid(theta, phi, indexing="ij")
    ring_pts = np.stack([np.sin(T) * np.cos(P), np.sin(T) * np.sin(P), np.cos(T)], axis=-1).reshape(-1, 3)
    V = np.vstack([[0.0, 0.0, 1.0], ring_pts, [0.0, 0.0, -1.0]]) * radius
    north, south = 0, len(V) - 1
    F = []
    s = np.arange(segments)
    s1 = (s + 1) % segments
    F.append(np.stack([np.full(segments, north), 1 + s, 1 + s1], axis=1))
    for k in range(rings - 2):
        a = 1 + k * segments
        b = a + segments
        F.append(np.stack([a + s, b + s, b + s1], axis=1))
        F.append(np.stack([a + s, b + s1, a + s1], axis=1))
    a = 1 + (rings - 2) * segments
    F.append(np.stack([a + s, np.full(segments, south), a + s1], axis=1))
    return V, np.vstack(F).astype(np.int64)


# --- environments ---------------------------------------------------------------------

# Irradiance on a plane facing the lobe, per unit peak radiance, of L = ((1 + w.s) / 2)^p.
_LOBE_FACING_IRRADIANCE = {0: np.pi, 1: 5.0 * np.pi / 6.0, 2: 17.0 * np.pi / 24.0}


def sky_environment(to_light=(0.4, 0.5, 1.0), lobe: int = 2, irradiance: float = np.pi,
                    ambient: float = 0.0, color=(1.0, 1.0, 1.0)) -> Environment:
    """A smooth directional sky the engine represents *exactly* (real SH of order <= 2).

    Radiance ``L(w) = ambient + L_peak ((1 + w.s) / 2)^lobe`` (times ``color``), with
    ``s`` the unit vector *towards* the bright side.  ``lobe = 2`` is the most
    directional non-negative function of SH order 2 (zero exactly opposite ``s``);
    ``L_peak`` is chosen so that the lobe alone gives ``irradiance`` [W/m^2] on a
    plane facing ``s`` (the default pi matches a sun of irradiance pi).  The whole
    function goes into ``Environment.sh`` (``radiance`` holds only ``ambient``),
    so the engine's SH irradiance is non-negative everywhere.

    This is the reference's stand-in for a sun: a path tracer cannot render a
    delta light behind a smooth dielectric (``mitsuba_ref._emitters``).
    """
    from translucency_addon.scene.sh import fibonacci_directions, sh_basis

    if lobe not in _LOBE_FACING_IRRADIANCE:
        raise ValueError(f"lobe must be 0, 1 or 2 (SH order <= 2), got {lobe}")
    s = _unit(to_light, "sky direction")
    peak = float(irradiance) / _LOBE_FACING_IRRADIANCE[lobe]
    dirs = fibonacci_directions(4096)
    f = peak * ((1.0 + dirs @ s) / 2.0) ** lobe
    Y = sh_basis(dirs, 2)
    # Least squares by its 9x9 normal equations (exact: f is a polynomial of degree <= 2, in Y's span), not
    # np.linalg.lstsq: LAPACK on 4096 rows runs on OpenBLAS's threads, which then spin for ~0.1 s and took
    # the cores from the frame a bench timed right after turning the sky (a warm Draft bunny frame 117-128 ms
    # against 30-32 ms; bench/frame.py, bench/accuracy).
    coef = np.linalg.solve(np.einsum("nk,nl->kl", Y, Y), np.einsum("nk,n->k", Y, f))
    col = np.asarray(color, dtype=np.float64).reshape(3)
    return Environment(radiance=tuple(float(ambient) * col), sh=coef[:, None] * col[None, :])


# --- canonical scenes ----------------------------------------------------------------

def sphere_env(
    material: Material,
    radius_mm: float = 12.0,
    res: int = 32,
    *,
    mm_per_unit: float = 1.0,
    image_res: int = 32,
    spp: int = 1024,
    radiance=(1.0, 1.0, 1.0),
    margin: float = 1.1,
    field: FieldSpec | None = None,
    seed: int = 0,
    analytic: bool = False,
    name: str = "sphere_env",
) -> RefScene:
    """A UV sphere (``res`` segments, ``res/2`` rings) of radius ``radius_mm`` under a
    uniform environment of radiance ``radiance``, seen orthographically along -z
    (up +y), the image ``margin`` x the diameter wide.  ``analytic=True`` makes
    the reference render the exact sphere instead of the mesh."""
    R = radius_mm / mm_per_unit
    V, F = uv_sphere(R, res)
    cam = Camera.orthographic((0.0, 0.0, 0.0), (0.0, 0.0, -1.0), (0.0, 1.0, 0.0), width=2.0 * R * margin)
    return RefScene(V, F, mm_per_unit, material, cam, lights=[], environment=Environment(tuple(radiance)),
                    field=field, resolution=(image_res, image_res), spp=spp, seed=seed, name=name,
                    analytic_sphere=((0.0, 0.0, 0.0), R) if analytic else None)


def _framed_mesh(path, size_mm, mm_per_unit, view_direction, up, margin):
    from translucency_addon.geometry.meshio import load_obj

    V, F = load_obj(path)
    lo, hi = V.min(axis=0), V.max(axis=0)
    if mm_per_unit is None:
        if size_mm is None:
            raise ValueError("give size_mm or mm_per_unit")
        mm_per_unit = float(size_mm) / float(np.linalg.norm(hi - lo))
    centre = 0.5 * (lo + hi)
    r, u, _ = Camera.orthographic(centre, view_direction, up, width=1.0).basis()
    rel = V - centre
    width = 2.0 * max(np.abs(rel @ r).max(), np.abs(rel @ u).max()) * margin
    return V, F, float(mm_per_unit), Camera.orthographic(centre, view_direction, up, width=width)


def mesh_sky(
    path,
    material: Material,
    *,
    size_mm: float | None = 40.0,
    mm_per_unit: float | None = None,
    to_light=(0.4, 0.5, 1.0),
    lobe: int = 2,
    irradiance: float = np.pi,
    ambient: float = 0.0,
    view_direction=(0.0, 0.0, -1.0),
    up=(0.0, 1.0, 0.0),
    image_res: int = 64,
    spp: int = 1024,
    margin: float = 1.05,
    field: FieldSpec | None = None,
    seed: int = 0,
    name: str | None = None,
) -> RefScene:
    """An OBJ mesh under a directional :func:`sky_environment`, seen orthographically
    along ``view_direction`` with the whole object in frame.  The reference can render it.

    The scale is ``mm_per_unit`` or, by default, such that the bounding-box
    diagonal is ``size_mm`` millimetres.
    """
    V, F, mpu, cam = _framed_mesh(path, size_mm, mm_per_unit, view_direction, up, margin)
    env = sky_environment(to_light, lobe=lobe, irradiance=irradiance, ambient=ambient)
    return RefScene(V, F, mpu, material, cam, lights=[], environment=env, field=field,
                    resolution=(image_res, image_res), spp=spp, seed=seed, name=name or Path(path).stem + "_sky")


def mesh_sun(
    path,
    material: Material,
    *,
    size_mm: float | None = 40.0,
    mm_per_unit: float | None = None,
    sun_direction=(-0.4, -0.5, -1.0),
    irradiance: float = np.pi,
    sun_color=(1.0, 1.0, 1.0),
    environment: Environment | None = None,
    view_direction=(0.0, 0.0, -1.0),
    up=(0.0, 1.0, 0.0),
    image_res: int = 64,
    spp: int = 1024,
    margin: float = 1.05,
    field: FieldSpec | None = None,
    seed: int = 0,
    name: str | None = None,
) -> RefScene:
    """An OBJ mesh lit by one sun (irradiance in W/m^2, light travelling along
    ``sun_direction``), optionally plus an environment, seen orthographically
    along ``view_direction`` with the whole object in frame.

    **Our side only.**  :func:`bench.reference.mitsuba_ref.render_reference`
    refuses delta lights: a volumetric path tracer cannot reach a sun through a
    smooth dielectric, so its translucency would be black.  For a reference
    with directional light use :func:`mesh_sky` (a sky lobe the engine
    represents exactly).  The scale is ``mm_per_unit`` or, by default, such that
    the bounding-box diagonal is ``size_mm`` millimetres.  The default
    irradiance pi W/m^2 makes a white Lambertian plane facing the sun read radiance 1.
    """
    V, F, mpu, cam = _framed_mesh(path, size_mm, mm_per_unit, view_direction, up, margin)
    sun = Light("sun", color=tuple(sun_color), irradiance=float(irradiance), direction=tuple(sun_direction), name="sun")
    return RefScene(V, F, mpu, material, cam, lights=[sun], environment=environment, field=field,
                    resolution=(image_res, image_res), spp=spp, seed=seed, name=name or Path(path).stem)
