"""The hard cases of issue 9 as plain builders, shared by the test suite and ``bench/stability.py``.

Every case is a function ``build_<id>()`` registered in :data:`CASES`.  A case
that solves returns a list of :class:`Scenario` (one per variant: "tiny" and
"huge", the rocker arm and the torus grid, ...); a case that must be refused
returns a list of :class:`Rejection`.  Bakes are memoised per process.

:func:`run_solver` solves one scenario with one backend/scheme and
:func:`check` measures it against the bounds the issue asks for and returns
the metrics and the list of violated bounds (empty: pass).  The tests assert
that list is empty; the benchmark prints it as a table.  The bounds:

* no NaN or Inf in phi (every level), q, the vertex radiance;
* non-negative radiance;
* the discrete maximum principle on every level: ``0 <= phi <= max_s 4 q_s / (1 - F_dr)``
  per channel (exact for our finite-volume M-matrix, see ``diffusion.py``);
  with no light at all, phi and the radiance must be exactly zero;
* the energy bound on every level: outgoing power (clamped J+, i.e. the light
  the radiance output actually emits) <= incoming power, per channel;
* convergence: the finest level's true relative residual <= the tolerance
  (TOL; on the GPU the larger fp32 floor of :func:`residual_floor`),
  ``LevelSolve.diverged`` false, and on every level the residual history
  never rises above ``max(HISTORY_FACTOR, sqrt(max D / min D))`` times the
  smallest value seen before it.  Chebyshev is not monotone: in the
  ``D^-1`` norm its residual is ``p_k(A D^-1) r_0`` with ``|p_k| <= 1`` on the
  spectrum, but in the Euclidean norm the stopping test uses that allows a
  rise of up to ``sqrt(cond(D))`` (the diagonal spans four decades and more
  under strong kappa contrast); HISTORY_FACTOR = 10 is the floor (measured
  rises: up to ~6 on homogeneous graphs, 19 under a 4e4 kappa contrast).

Tolerances, and why:

* ``MP_EPS``: iterative solves stop at a relative residual of ``TOL``; the
  iterate differs from the exact discrete solution (which satisfies the
  bound exactly) by at most cond * TOL, so phi may exceed the bound by a
  small relative amount.  We allow ``MP_EPS`` = 1e-3 relative (measured:
  below 1e-5 in every case).  The direct solver is held to 1e-9.
* ``ENERGY_EPS``: the unclamped balance ``in = out + absorbed`` holds to
  the residual; 1e-3 relative covers TOL = 1e-5 on every case here.
* iterative vs direct: max |L - L_direct| / max L_direct <= ``AGREE`` =
  100 x TOL.  A relative residual bounds the error only up to the
  conditioning: measured 3e-8 .. 6e-6 on most cases; on the slivers, whose bakes differ
  from run to run, 6.5e-5 .. 1.8e-3 (12 bakes), so every case's iterative answer is
  checked against the direct one at TOL / 1000 (test_our_scheme_on_the_cpu).
* CPU vs GPU (fp32): max |L_gpu - L_cpu| / max L_cpu <= ``GPU_TOL`` = 1e-4,
  the tolerance of tests/test_gpu_solver.py, or the fp32 floor where that
  is larger (:func:`residual_floor`), or twice the CPU's measured distance
  from the direct solve, the larger of its default's (CG on large levels)
  and its Chebyshev iterate's, the GPU's method (two iterates stopped at the
  same residual differ by up to that: the slivers); the GPU's convergence is judged
  against the same floor.  Both outputs apply the same power-preserving
  clamp (``DiffusionSolver.output_clamp``), so the radiance is compared as it is.
* fp16 storage: ``FP16_TOL`` = 3e-3 (coefficients and q rounded to 11
  significant bits: 2^-11 = 4.9e-4 relative per value).
"""

from __future__ import annotations

import json
import os
import sys
from dataclasses import dataclass, field, replace
from functools import lru_cache
from pathlib import Path
from typing import Callable

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from translucency_addon import cache  # noqa: E402
from translucency_addon.geometry import meshio, primitives  # noqa: E402
from translucency_addon.quadgraph.bake import BakeSettings, bake_mesh  # noqa: E402
from translucency_addon.diffusion.solver import DiffusionSolver, SolveOptions  # noqa: E402
from translucency_addon.errors import CacheError, GraphTooLarge, MaterialError, MeshError  # noqa: E402
from translucency_addon.scene.fields import FieldSpec, evaluate_field  # noqa: E402
from translucency_addon.scene.lights import Environment, Light  # noqa: E402
from translucency_addon.diffusion.graph import graph_components  # noqa: E402,F401 - the engine's own, also used by test_hard_cases
from data import mesh_path  # noqa: E402
from translucency_addon.scene.materials import Material, Medium, material_from_preset  # noqa: E402


TOL = 1e-5  # relative residual of every iterative solve here (the GPU tests' tolerance)
MP_EPS = 1e-3
ENERGY_EPS = 1e-3
DIRECT_EPS = 1e-9  # maximum principle and energy bound of the direct solve
DIRECT_BALANCE_EPS = 1e-6  # its in = out + absorbed (sums of large terms; condition up to ~1e12 in the fuzz)
HISTORY_FACTOR = 10.0
AGREE = 100 * TOL
GPU_TOL = 1e-4
FP16_TOL = 3e-3
PAPER_MAX_ITERATIONS = 6000  # the paper's Jacobi needs ~(l/h)^2 sweeps; capped and reported

MARBLE = material_from_preset("marble")
ENV1 = Environment((1.0, 1.0, 1.0))
SUN = Light("sun", irradiance=1000.0, direction=(0.3, -0.5, -0.8), name="sun")


# ----------------------------------------------------------------------------- data


@dataclass
class Scenario:
    """One variant of a case that must solve."""

    case: str
    variant: str
    bake: object
    material: Material
    field_values: list | None = None
    lights: list = field(default_factory=list)
    environment: Environment | None = None
    occluders: tuple | None = None
    shadows: bool = True
    expect_zero: bool = False  # no light reaches the object: phi and L must be exactly 0
    expect_warning: str = ""  # regular expression the light pass's warnings must contain
    paper: bool = True  # run the paper's scheme too (reported, never asserted)
    precision: str = "fp32"  # GPU storage
    notes: list = field(default_factory=list)

    @property
    def label(self) -> str:
        return self.case if not self.variant else f"{self.case}/{self.variant}"


@dataclass
class Rejection:
    """One input that must be refused with a message naming the problem."""

    case: str
    variant: str
    action: Callable[[], object]
    error: type
    match: str  # regular expression the message must contain

    @property
    def label(self) -> str:
        return f"{self.case}/{self.variant}"


# ----------------------------------------------------------------------------- meshes and bakes


@lru_cache(maxsize=None)
def shared_mesh(name: str):
    V, F = meshio.load_obj(mesh_path(name))
    V.setflags(write=False)
    F.setflags(write=False)
    return V, F


@lru_cache(maxsize=None)
def _bake(key: str, quality="draft", levels=None, base_triangles=None, optimize=True, mm_per_unit=1.0):
    V, F = MESHES[key]()
    return bake_mesh(np.asarray(V), np.asarray(F), BakeSettings(quality=quality, levels=levels,
                                                                 base_triangles=base_triangles,
                                                                 optimize=optimize, mm_per_unit=mm_per_unit))


def baked(key: str, mm_per_unit: float, **kw):
    """A memoised bake of mesh ``key`` (geometry does not depend on the scale)."""
    return _bake(key, **kw).with_scale(mm_per_unit)


def _duplicated_degenerate_sphere():
    """An icosphere with every triangle on its own three vertices (all duplicated),
    plus zero-area triangles (repeated indices and collinear vertices) and unused vertices."""
    V, F = primitives.icosphere(1.0, 3)
    Vd = V[F.ravel()]
    Fd = np.arange(len(Vd)).reshape(-1, 3)
    rng = np.random.default_rng(9)
    picks = rng.choice(len(Vd), size=(40, 2), replace=False)
    rep = np.stack([picks[:, 0], picks[:, 0], picks[:, 1]], axis=1)  # a vertex used twice
    a, b = Vd[picks[:, 0]], Vd[picks[:, 1]]
    mids = 0.5 * (a + b)  # collinear: zero area with three distinct vertices
    base = len(Vd)
    Vd = np.vstack([Vd, mids, rng.normal(size=(7, 3)) * 0.1])  # + 7 unreferenced vertices
    col = np.stack([picks[:, 0], picks[:, 1], base + np.arange(len(mids))], axis=1)
    return Vd, np.vstack([Fd, rep, col])


MESHES: dict[str, Callable] = {
    "sphere": lambda: primitives.icosphere(1.0, 3),
    "cube": lambda: primitives.box((1.0, 1.0, 1.0), subdivisions=3),
    "shell": lambda: primitives.hollow_sphere(1.0, 0.01, 3),
    "torus_grid": lambda: primitives.torus_grid(3, 2, n_major=24, n_minor=10),
    "torus": lambda: primitives.torus(1.0, 0.4, 32, 12),
    "two_pieces": lambda: primitives.merge(primitives.icosphere(1.0, 3, center=(-2.0, 0.0, 0.0)),
                                           primitives.icosphere(0.5, 3, center=(2.0, 0.0, 0.0))),
    "tiny_piece": lambda: primitives.merge(primitives.icosphere(1.0, 3, center=(-1.5, 0.0, 0.0)),
                                           primitives.icosphere(0.05, 2, center=(1.5, 0.0, 0.0))),
    "degenerate": _duplicated_degenerate_sphere,
    "fandisk": lambda: shared_mesh("fandisk"),
    "rocker-arm": lambda: shared_mesh("rocker-arm"),
    "bunny": lambda: shared_mesh("stanford-bunny"),
}


def _medium(sa, ss, name):
    return Medium(tuple(float(x) for x in sa), tuple(float(x) for x in ss), name)


# ----------------------------------------------------------------------------- the cases that solve


def build_thin_shell():
    """1: a sphere (20 mm) with a 1 %-of-radius wall (0.1 mm).

    At draft quality the resampled surface (~150 triangles per sphere) cannot
    follow a 0.1 mm wall: its chord error is larger than the wall, so the
    decimated inner and outer spheres cross.  fTetWild fills by winding
    number and keeps a shell (not a closed ball); its thickness follows the
    crossing surfaces.  The notes record the baked volume against the exact one.
    """
    b = baked("shell", 10.0, base_triangles=300)
    exact = 4.0 / 3.0 * np.pi * (1.0 - 0.99**3)
    notes = [f"level {i}: volume {lv.volume.sum() / exact:.2f} x the exact shell's, "
             f"ball would be {1.0 / (1.0 - 0.99 ** 3):.0f} x; inner nodes at r = "
             f"{np.linalg.norm(lv.position[:lv.n_inner], axis=1).min():.3f}..."
             f"{np.linalg.norm(lv.position[:lv.n_inner], axis=1).max():.3f}"
             for i, lv in enumerate(b.levels)]
    return [Scenario("thin_shell", "", b, MARBLE, lights=[SUN], environment=ENV1, notes=notes)]


def build_thin_fin():
    """2: fandisk's creases and thin fins (50 mm across), marble, one sun."""
    b = baked("fandisk", 10.0)
    return [Scenario("thin_fin", "", b, MARBLE, lights=[Light("sun", irradiance=800.0, direction=(-0.4, 0.7, -0.6))],
                     environment=ENV1)]


def build_high_genus():
    """3: the rocker arm (genus 1, 100 mm) and a 3 x 2 grid of fused tori (genus >= 6, 60 mm)."""
    rocker = baked("rocker-arm", 100.0)
    grid = baked("torus_grid", 10.0, base_triangles=600)
    comps = graph_components(grid.finest)
    notes = [f"torus grid: finest graph has {len(np.unique(comps))} connected component(s)"]
    return [
        Scenario("high_genus", "rocker-arm", rocker, material_from_preset("skin1"), lights=[SUN], environment=ENV1),
        Scenario("high_genus", "torus-grid", grid, MARBLE, lights=[Light("point", intensity=20.0, position=(2.0, 1.0, 3.0))],
                 environment=ENV1, notes=notes),
    ]


def build_slivers():
    """4: the bunny tetrahedralized without fTetWild's optimisation (slivers), 150 mm."""
    b = baked("bunny", 1000.0, optimize=False)
    notes = [f"level {i}: tet quality median {lv.stats['tet_quality_median']:.3f}, "
             f"min {lv.stats['tet_quality_min']:.1e}" for i, lv in enumerate(b.levels)]
    return [Scenario("slivers", "", b, MARBLE, lights=[SUN], environment=ENV1, notes=notes)]


# kappa = 1 / (3 (sigma_a + sigma_s')): 1/3 mm against 1/30000 mm, same absorption.
CONTRAST_A = _medium((0.001,) * 3, (0.999,) * 3, "kappa 1/3 mm")
CONTRAST_B = _medium((0.001,) * 3, (9999.999,) * 3, "kappa 1/30000 mm")


def build_kappa_contrast():
    """5: a 20 mm cube, checkerboard of 5 mm cells whose kappa differs 1e4-fold."""
    b = baked("cube", 20.0, base_triangles=300)
    mat = Material(CONTRAST_A, CONTRAST_B, 1.3, name="contrast")
    spec = FieldSpec("checker", scale=0.25, offset=(0.013, 0.021, 0.034))
    fv = [evaluate_field(spec, lv.position) for lv in b.levels]
    return [Scenario("kappa_contrast", "", b, mat, field_values=fv, lights=[SUN], environment=ENV1,
                     notes=["kappa ratio between cells: 1e4"])]


def build_albedo_near_1():
    """6: sigma_a = 1e-6 sigma_s' (marble's scattering): nearly no absorption.

    At 20 mm the boundary leak still keeps the system well conditioned; at
    1 mm the leak is weak against the diffusion across the graph and the
    system is nearly singular (lambda_min of D^-1 A ~1e-3).
    """
    ss = np.array(material_from_preset("marble").medium_a.sigma_s)
    mat = Material(_medium(1e-6 * ss, ss, "albedo 1 - 1e-6"), None, 1.3)
    return [Scenario("albedo_near_1", "20 mm", baked("sphere", 10.0), mat, lights=[SUN], environment=ENV1),
            Scenario("albedo_near_1", "1 mm", baked("sphere", 0.5), mat, lights=[SUN], environment=ENV1)]


ALBEDO_0 = _medium((1.0, 2.0, 5.0), (0.01, 0.01, 0.01), "albedo ~0.01")


def build_albedo_near_0():
    """7: reduced albedo 0.01 .. 0.002 (diffusion is invalid here), 20 mm sphere."""
    b = baked("sphere", 10.0)
    return [Scenario("albedo_near_0", "", b, Material(ALBEDO_0, None, 1.3), lights=[SUN], environment=ENV1)]


def build_tiny_and_huge():
    """8: the same sphere at 0.1 mm and at 100 m across, marble coefficients in 1/mm."""
    return [
        Scenario("tiny_and_huge", "tiny 0.1 mm", baked("sphere", 0.05), MARBLE, lights=[SUN], environment=ENV1),
        Scenario("tiny_and_huge", "huge 100 m", baked("sphere", 5.0e4), MARBLE, lights=[SUN], environment=ENV1),
    ]


def build_fp16_scale():
    """9: fp16 storage on the GPU at both ends of the scale (CPU in fp64 is the reference)."""
    return [replace(s, case="fp16_scale", precision="fp16", paper=False) for s in build_tiny_and_huge()]


def build_grazing_light():
    """10: lights grazing a 20 mm cube's top face: a sun 1e-6 rad above the face's plane
    and a point light in that plane (exactly grazing: cos = 0)."""
    b = baked("cube", 20.0, base_triangles=300)
    d = np.array([1.0, 0.2, -1e-6])
    lights = [Light("sun", irradiance=1000.0, direction=tuple(d / np.linalg.norm(d)), name="grazing sun"),
              Light("point", intensity=10.0, position=(1.5, 0.1, 0.5), name="in-plane point")]
    return [Scenario("grazing_light", "", b, MARBLE, lights=lights)]


def build_light_inside():
    """11: a point light inside the object (convex sphere; inside a torus's tube, where
    surface elements on the far side of the hole face it), with and without shadow rays.

    Decision: eq. 3's q is light arriving at the surface from outside.  A source
    inside the medium is an interior source term that this boundary-source model
    does not have, so it contributes nothing, and the solver says so
    (``SolveResult.warnings``).
    """
    inside_sphere = Light("point", intensity=50.0, position=(0.1, 0.05, -0.1), name="inside")
    inside_torus = Light("point", intensity=50.0, position=(1.0, 0.0, 0.05), name="inside tube")
    out = []
    for shadows in (True, False):
        tag = "shadows" if shadows else "no shadows"
        out.append(Scenario("light_inside", f"sphere, {tag}", baked("sphere", 10.0), MARBLE,
                            lights=[inside_sphere], shadows=shadows, expect_zero=True, paper=False,
                            expect_warning=r"light 'inside' .* is inside the object"))
        out.append(Scenario("light_inside", f"torus, {tag}", baked("torus", 10.0, base_triangles=300), MARBLE,
                            lights=[inside_torus], shadows=shadows, expect_zero=True, paper=False,
                            expect_warning=r"light 'inside tube' .* is inside the object"))
    return out


def build_no_lights():
    """12: no lights and no (or a black) environment: exactly zero everywhere."""
    b = baked("sphere", 10.0)
    return [Scenario("no_lights", "none", b, MARBLE, expect_zero=True),
            Scenario("no_lights", "black world", b, MARBLE, environment=Environment((0.0, 0.0, 0.0)),
                     expect_zero=True)]


def build_occluded_light():
    """13: a sun fully blocked by a slab (exactly zero) and a point light half hidden by a box."""
    b = baked("sphere", 10.0)
    slab = primitives.box((3.0, 3.0, 0.1), center=(0.0, 0.0, 2.0))
    wall = primitives.box((0.2, 3.0, 3.0), center=(2.0, 1.5, 0.0))
    return [
        Scenario("occluded_light", "sun behind slab", b, MARBLE,
                 lights=[Light("sun", irradiance=1000.0, direction=(0.0, 0.0, -1.0))], occluders=slab,
                 expect_zero=True, paper=False),
        Scenario("occluded_light", "point behind wall", b, MARBLE,
                 lights=[Light("point", intensity=30.0, position=(3.0, 0.0, 0.0))], occluders=wall),
    ]


def build_open_mesh():
    """14: the raw Stanford bunny: 69k triangles, open (holes in the base), 150 mm."""
    b = baked("bunny", 1000.0)
    return [Scenario("open_mesh", "", b, MARBLE, lights=[SUN], environment=ENV1, notes=b.stats["mesh"]["warnings"])]


def build_degenerate():
    """15: every vertex duplicated, zero-area triangles (repeated and collinear vertices), unused vertices."""
    b = baked("degenerate", 10.0)
    return [Scenario("degenerate", "", b, MARBLE, lights=[SUN], environment=ENV1, notes=b.stats["mesh"]["warnings"])]


def build_disjoint():
    """16: two disjoint spheres in one object (20 mm and 10 mm), and a 1 mm sphere beside a 20 mm one."""
    out = []
    for key in ("two_pieces", "tiny_piece"):
        b = baked(key, 10.0)
        comps = graph_components(b.finest)
        sizes = np.bincount(comps)
        out.append(Scenario("disjoint", key.replace("_", " "), b, MARBLE,
                            lights=[Light("point", intensity=20.0, position=(-2.0, 0.0, 3.0))], environment=ENV1,
                            notes=[f"finest graph: {len(sizes)} component(s), nodes {sorted(sizes.tolist())}"]))
    return out


# ----------------------------------------------------------------------------- the cases that are refused


def build_flat_mesh():
    """17: flat or zero-volume meshes."""
    plane_V = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0], [0, 0, 0.0]])
    plane_F = np.array([[0, 1, 4], [1, 2, 4], [2, 3, 4], [3, 0, 4]])
    # closed but flat: both sides of the same square, every edge shared by two triangles
    closed_F = np.vstack([plane_F, plane_F[:, ::-1]])
    point_V = np.zeros((5, 3))

    def bake_of(V, F):
        return lambda: bake_mesh(V, F, BakeSettings(quality="draft"))

    return [
        Rejection("flat_mesh", "open plane", bake_of(plane_V, plane_F), MeshError, r"mesh is flat"),
        Rejection("flat_mesh", "closed double-sided plane", bake_of(plane_V, closed_F), MeshError,
                  r"flat|zero volume"),
        Rejection("flat_mesh", "all vertices coincide", bake_of(point_V, plane_F), MeshError, r"zero size"),
    ]


def build_nan_input():
    """18: NaN / Inf coordinates; NaN, Inf or negative material coefficients; NaN field values."""
    V, F = primitives.icosphere(1.0, 2)
    Vn = V.copy()
    Vn[5, 1] = np.nan
    Vi = V.copy()
    Vi[7, 0] = np.inf
    b = baked("sphere", 10.0)

    def bake_of(VV):
        return lambda: bake_mesh(VV, F, BakeSettings(quality="draft"))

    def nan_field():
        mat = Material(MARBLE.medium_a, CONTRAST_A, 1.3)
        fv = [np.zeros(lv.n_nodes) for lv in b.levels]
        fv[-1][3] = np.nan
        return DiffusionSolver(b, mat, fv)

    return [
        Rejection("nan_input", "NaN coordinate", bake_of(Vn), MeshError, r"1 vertices with NaN or Inf coordinates"),
        Rejection("nan_input", "Inf coordinate", bake_of(Vi), MeshError, r"1 vertices with NaN or Inf coordinates"),
        Rejection("nan_input", "NaN sigma_a", lambda: Material(_medium((np.nan, 0.1, 0.1), (1, 1, 1), "m")),
                  MaterialError, r"sigma_a contains NaN"),
        Rejection("nan_input", "Inf sigma_s", lambda: Material(_medium((0.1,) * 3, (1, np.inf, 1), "m")),
                  MaterialError, r"sigma_s contains NaN or Inf"),
        Rejection("nan_input", "negative sigma_a", lambda: Material(_medium((0.1, -0.01, 0.1), (1, 1, 1), "m")),
                  MaterialError, r"sigma_a is negative"),
        Rejection("nan_input", "negative sigma_s", lambda: Material(_medium((0.1,) * 3, (1, 1, -2), "m")),
                  MaterialError, r"sigma_s is negative"),
        Rejection("nan_input", "NaN eta", lambda: Material(MARBLE.medium_a, None, float("nan")), MaterialError,
                  r"refractive index eta=nan"),
        Rejection("nan_input", "NaN field value", nan_field, MaterialError, r"heterogeneity field contains NaN"),
    ]


def _rewrite_npz(src: str, dst: str, edit) -> None:
    """Copy a cache, letting ``edit(arrays)`` change its arrays (uncompressed rewrite)."""
    with np.load(src, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    edit(arrays)
    with open(dst, "wb") as fh:
        np.savez(fh, **arrays)


def _edit_meta(**changes):
    def edit(arrays):
        meta = json.loads(arrays["meta"].tobytes().decode())
        meta.update(changes)
        arrays["meta"] = np.frombuffer(json.dumps(meta).encode(), dtype=np.uint8)
    return edit


def _edit_array(name, index, value):
    def edit(arrays):
        a = arrays[name].copy()
        a[index] = value
        arrays[name] = a
    return edit


def _drop(name):
    def edit(arrays):
        del arrays[name]
    return edit


# variant -> (how to damage a good cache, regular expression the error message must contain)
CACHE_DAMAGE = {
    "truncated": ("truncate", r"is corrupt or truncated"),
    "corrupt bytes": ("flip", r"is corrupt or truncated"),
    "random bytes": ("random", r"is corrupt or truncated"),
    "wrong version": (_edit_meta(format=cache.CACHE_FORMAT + 98),
                      rf"has format version {cache.CACHE_FORMAT + 98}, written by Translucency .*; this version "
                      rf"\(Translucency .*\) reads {', '.join(str(f) for f in cache.READABLE_FORMATS)}\. Install the same "
                      "extension version on every machine"),
    "not a cache": ("foreign", r"is not a Translucency bake cache"),
    "wrong magic": (_edit_meta(magic="something-else"), r"is not a Translucency bake cache"),
    "neighbour index out of range": (_edit_array("L1/neighbors", (0, 0), 10**8),
                                     r"level 1 has neighbour indices out of range"),
    "NaN in a level": (_edit_array("L0/area", 2, np.nan), r"level 0 area contains NaN or Inf"),
    "missing array": (_drop("L1/position"), r"is incomplete or inconsistent"),
    "missing file": ("delete", r"does not exist"),
}


def damage_cache(src: str, dst: str, variant: str) -> str:
    """Write a damaged copy of the good cache ``src`` to ``dst`` (may be ``src``); returns the regex."""
    how, regex = CACHE_DAMAGE[variant]
    data = open(src, "rb").read()
    rng = np.random.default_rng(19)
    if how == "truncate":
        open(dst, "wb").write(data[: len(data) // 2])
    elif how == "flip":  # flip bytes inside the compressed members: CRC errors
        bad = bytearray(data)
        for i in rng.integers(200, len(bad) - 200, size=64):
            bad[i] ^= 0xFF
        open(dst, "wb").write(bytes(bad))
    elif how == "random":
        open(dst, "wb").write(rng.bytes(4096))
    elif how == "foreign":
        with open(dst, "wb") as fh:
            np.savez(fh, x=np.arange(3))
    elif how == "delete":
        if os.path.exists(dst):
            os.remove(dst)
    else:
        tmp = dst + ".tmp.npz"
        _rewrite_npz(src, tmp, how)
        os.replace(tmp, dst)
    return regex


def build_bad_cache(directory=None):
    """19: corrupt, truncated, wrong-version, foreign, inconsistent and missing caches, and a stale one."""
    import tempfile

    directory = directory or tempfile.mkdtemp(prefix="translucency-hard-cache-")
    b = baked("sphere", 10.0)
    good = cache.save_bake(os.path.join(directory, "good.npz"), b)
    out = []
    for k, variant in enumerate(CACHE_DAMAGE):
        path = os.path.join(directory, f"bad{k}.npz")
        regex = damage_cache(good, path, variant)
        out.append(Rejection("bad_cache", variant, (lambda p=path: cache.load_bake(p, expected_key=b.key)),
                             CacheError, regex))
    out.append(Rejection("bad_cache", "stale key", lambda: cache.load_bake(good, expected_key="0" * 64), CacheError,
                         r"is stale: the mesh or the bake settings changed"))
    return out


def build_texture_limit():
    """20: a graph larger than the GPU texture limit, simulated with 32 x 32 textures and 2 layers
    (2048 nodes at most): refused with a message naming the sizes.  (Splitting into
    layers under a 64-texel limit is a solve case, in the tests.)"""
    def gpu_refuses():
        import gpu_shaders

        b = baked("sphere", 10.0)
        return gpu_shaders.make_solver(b, MARBLE, None, SolveOptions(), prefer="GPU", max_texture_size=32,
                                       max_layers=2)

    return [Rejection("texture_limit", "32 x 32 x 2 layers, prefer GPU", gpu_refuses, GraphTooLarge,
                      r"level \d+ .*allows textures of at most 32 x 32 with 2 layers")]


CASES: dict[str, Callable] = {
    "thin_shell": build_thin_shell,
    "thin_fin": build_thin_fin,
    "high_genus": build_high_genus,
    "slivers": build_slivers,
    "kappa_contrast": build_kappa_contrast,
    "albedo_near_1": build_albedo_near_1,
    "albedo_near_0": build_albedo_near_0,
    "tiny_and_huge": build_tiny_and_huge,
    "fp16_scale": build_fp16_scale,
    "grazing_light": build_grazing_light,
    "light_inside": build_light_inside,
    "no_lights": build_no_lights,
    "occluded_light": build_occluded_light,
    "open_mesh": build_open_mesh,
    "degenerate": build_degenerate,
    "disjoint": build_disjoint,
    "flat_mesh": build_flat_mesh,
    "nan_input": build_nan_input,
    "bad_cache": build_bad_cache,
    "texture_limit": build_texture_limit,
}
REJECTED = ("flat_mesh", "nan_input", "bad_cache", "texture_limit")
SOLVING = tuple(c for c in CASES if c not in REJECTED)
SLOW = ("slivers", "open_mesh")  # the raw 69k-triangle bunny (decimated by the bake)


# ----------------------------------------------------------------------------- solve and check


@dataclass
class Run:
    """One solve of a scenario: the solver object, its result and the vertex radiance."""

    scenario: Scenario
    solver_name: str  # "fast", "paper", "direct", "gpu-fast", "gpu-fast-fp16"
    solver: object
    result: object
    radiance: np.ndarray
    phi: list  # per level (N, 3), float64
    warnings: list | None = None  # the light pass's warnings (None: q was given, no light pass ran)


def run_solver(scn: Scenario, name: str, q=None, tol: float = TOL, single: bool = False) -> Run:
    """Solve ``scn`` with ``name``: "fast" | "paper" | "direct" (CPU) or "gpu" (GPU, fast, scn.precision).

    ``single``: every term on -- the first-scatter split (closed-form single scattering plus the diffusion of
    what scatters more, ``SolveOptions.single_scattering``)."""
    if name == "gpu":
        import gpu_shaders

        opts = SolveOptions(solver="fast", tol=TOL, single_scattering=single)
        solver, backend, message = gpu_shaders.make_solver(scn.bake, scn.material, scn.field_values, opts, prefer="GPU",
                                                           precision=scn.precision, readback="phi")
        assert backend == "GPU", message
        label = "gpu-fast" + ("-fp16" if scn.precision == "fp16" else "")
    else:
        opts = SolveOptions(solver=name, tol=tol,
                            max_iterations=PAPER_MAX_ITERATIONS if name == "paper" else 50_000,
                            single_scattering=single)
        solver = DiffusionSolver(scn.bake, scn.material, scn.field_values, opts)
        label = name
    if single:
        label += "+single"
    kw = dict(shadows=scn.shadows, occluders=scn.occluders)
    result = solver.solve(scn.lights, scn.environment, q=q, **kw) if q is None else solver.solve(q=q)
    L = np.asarray(solver.vertex_radiance(result))
    phi = [np.asarray(p, dtype=np.float64) for p in result.phi]
    return Run(scn, label, solver, result, L, phi, list(solver.warnings) if q is None else None)


def check(run: Run, *, strict: bool = True) -> tuple[dict, list[str]]:
    """Metrics of one run and the bounds it violates (see the module docstring).

    ``strict=False`` (the paper's scheme) measures the same quantities but
    does not require convergence (the caller reports them).
    """
    scn, s, r = run.scenario, run.solver, run.result
    problems: list[str] = []
    fdr = s.fdr
    eps = DIRECT_EPS if run.solver_name == "direct" else MP_EPS
    flux_ratio = 0.0
    power_ratio = 0.0
    min_ratio = 0.0
    balance_err = 0.0
    for i, _lv in enumerate(scn.bake.levels):
        phi, q = run.phi[i], r.q[i]
        if phi is None or q is None:
            continue
        if not (np.all(np.isfinite(phi)) and np.all(np.isfinite(q))):
            problems.append(f"level {i}: NaN or Inf in phi or q")
            continue
        g = (4.0 * q / (1.0 - fdr)).max(axis=0)  # largest boundary source per channel
        if r.volume is not None and r.volume[i] is not None:  # or the lamps' volume source's bound
            g = np.maximum(g, s.phi_bound(r, i))
        if np.all(g == 0):
            if np.any(phi != 0):
                problems.append(f"level {i}: no light, but phi is not exactly zero (max {np.abs(phi).max():.3g})")
        else:
            gg = np.where(g > 0, g, np.inf)
            fr = float((phi.max(axis=0) / gg).max())
            mr = float((phi.min(axis=0) / gg).min())
            flux_ratio, min_ratio = max(flux_ratio, fr), min(min_ratio, mr)
            if fr > 1.0 + eps:
                problems.append(f"level {i}: maximum principle violated: max phi / max 4q/(1-F_dr) = {fr:.6g}")
            if mr < -eps:
                problems.append(f"level {i}: phi negative: min phi / max source = {mr:.3g}")
        p_in, p_out, imbalance = power(run, i)
        balance_err = max(balance_err, imbalance)
        if not (np.all(np.isfinite(p_in)) and np.all(np.isfinite(p_out))):
            problems.append(f"level {i}: power not finite")
            continue
        if np.all(p_in == 0):
            if np.any(p_out != 0):
                problems.append(f"level {i}: outgoing power without incoming power")
        else:
            pr = float((p_out / np.where(p_in > 0, p_in, np.inf)).max())
            power_ratio = max(power_ratio, pr)
            # (direct: a non-absorbing body returns exactly what it takes in, so round-off of the
            # ill-conditioned LU -- the same as in the balance -- may push the ratio just above 1)
            if pr > 1.0 + (DIRECT_BALANCE_EPS if run.solver_name == "direct" else ENERGY_EPS):
                problems.append(f"level {i}: energy bound violated: out / in = {pr:.6g}")
    L = run.radiance
    if not np.all(np.isfinite(L)):
        problems.append("vertex radiance has NaN or Inf")
    elif np.any(L < 0):
        problems.append(f"negative vertex radiance (min {L.min():.3g})")
    if scn.expect_warning and run.warnings is not None:
        import re

        if not any(re.search(scn.expect_warning, w) for w in run.warnings):
            problems.append(f"expected a warning matching {scn.expect_warning!r}, got {run.warnings}")
    if scn.expect_zero:
        if np.any(L != 0) or any(p is not None and np.any(p != 0) for p in run.phi):
            problems.append("no light reaches the object, but the output is not exactly zero")
    if strict and balance_err > (DIRECT_BALANCE_EPS if run.solver_name == "direct" else ENERGY_EPS):
        problems.append(f"discrete energy balance in = out + absorbed off by {balance_err:.3g} of in")
    growth, allowed = 1.0, HISTORY_FACTOR
    active = [i for i, p in enumerate(r.phi) if p is not None]
    floors = {i: residual_floor(run, i) for i in active}
    for ls, i in zip(r.level_solves, active[-len(r.level_solves):]):
        h = np.asarray(ls.history, dtype=np.float64)
        if len(h) > 1 and np.all(np.isfinite(h)):
            run_min = np.minimum.accumulate(h)
            with np.errstate(divide="ignore", invalid="ignore"):
                ratio = np.where(run_min[:-1] > 0, h[1:] / run_min[:-1], 1.0)
            ratio = np.where(h[1:] > floors[i], ratio, 1.0)  # below the rounding floor it is noise
            diag = np.asarray(s.systems[i].diag)
            lim = max(HISTORY_FACTOR, float(np.sqrt((diag.max(axis=0) / diag.min(axis=0)).max())))
            if ratio.max() / lim > growth / allowed:
                growth, allowed = float(ratio.max()), lim
    final = float(np.max(r.residual))
    target = floors[active[-1]] if active else TOL
    diverged = bool(any(ls.diverged for ls in r.level_solves))
    converged = final <= target * 1.05 and not diverged
    if strict:
        if not converged:
            problems.append(f"did not converge: final relative residual {final:.3g} (tol {target:.3g}), "
                            f"diverged={diverged}")
        if growth > allowed:
            problems.append(f"residual rose to {growth:.3g} x its running minimum (allowed {allowed:.3g})")
    metrics = {
        "case": scn.label, "solver": run.solver_name,
        "sweeps": [int(ls.iterations) for ls in r.level_solves],
        "residual": final, "tol": target, "converged": converged, "diverged": diverged, "growth": growth,
        "growth_allowed": allowed,
        "flux_ratio": flux_ratio, "min_ratio": min_ratio, "power_ratio": power_ratio, "balance": balance_err,
        "radiance_max": float(np.max(L)) if L.size else 0.0,
    }
    return metrics, problems


FP32_EPS = 2.0**-24


def residual_floor(run: Run, level: int) -> float:
    """The relative residual a run can be asked to reach on a level: TOL, or the fp32 floor on the GPU.

    The GPU keeps the iterate in fp32.  Rounding x to fp32 perturbs it by
    2^-24 relative; the residual of that perturbation is up to
    ``|D^-1 A| <= 2`` times it, while |b| is only ``lambda_min |D x|`` when
    the system is nearly singular.  So fp32 cannot bring the relative
    residual below about ``2 * 2^-24 / lambda_min`` (0.1 mm sphere:
    lambda_min = 5.5e-5, floor 2.2e-3; the exact solution merely rounded to
    fp32 already has 7.6e-5).  The CPU (fp64) is held to TOL.
    """
    if not run.solver_name.startswith("gpu"):
        return TOL
    from translucency_addon.diffusion.spectral import spectral_bounds

    lam_min, _ = spectral_bounds(run.solver.systems[level])
    return max(TOL, 2.0 * FP32_EPS / float(np.min(lam_min)))


def power(run: Run, level: int):
    """(in, out, imbalance) on one level: incoming and outgoing power (W, per channel).

    ``out`` is the larger of ``power_balance(clamp=True)["out"]`` and the power
    of the J+ the backend itself hands to the radiance output
    (``surface_partial_current``), so a GPU output is judged by what it
    emits.  ``imbalance``: relative error of the unclamped discrete balance
    ``in = out + absorbed`` (our scheme; the paper's is not conservative and
    the engine has no power accounting for it).  With every term on (the first-scatter split) ``in`` is
    the light that entered and ``out`` adds what the closed-form single scattering sends out; the
    balance is the diffusion's, on its own source.
    """
    s, r = run.solver, run.result
    lv = run.scenario.bake.levels[level]
    m = run.scenario.bake.mm_per_unit * 1e-3
    a = lv.area * m * m
    p_in = a @ r.q[level]
    if r.volume is not None and r.volume[level] is not None:  # the lamps' volume source (mm^2 W/m^2)
        p_in = p_in + np.asarray(r.volume[level]).sum(axis=0) * 1e-6
    p_out = a @ ((1.0 - s.fdr) * np.asarray(s.surface_partial_current(r, level)))
    imbalance = 0.0
    if r.scheme == "fv":
        pb = s.power_balance(r, level=level, clamp=True)
        pu = s.power_balance(r, level=level, clamp=False)
        p_out = np.maximum(p_out, np.asarray(pb["out"]))
        gap = np.abs(p_in - np.asarray(pu["out"]) - np.asarray(pu["absorbed"]))
        imbalance = float((gap / np.where(p_in > 0, p_in, np.inf)).max())
        if "incident" in pb:
            p_in, p_out = np.asarray(pb["incident"]), p_out + np.asarray(pb["single"])
    return p_in, p_out, imbalance


def compare(run: Run, ref: Run, tol: float) -> tuple[float, list[str]]:
    """Radiance difference ``max |L - L_ref| / scale`` and the problem if above ``tol``.

    ``scale`` is the larger of the reference's peak radiance and
    ``max q / (pi eta^2)``, the radiance the incoming light sets: a strong
    absorber returns almost nothing (all J+ clamped in the direct solve),
    and a relative error of almost nothing says nothing about the solve.
    Both exactly zero: 0.  The GPU's radiance is compared as it is: its output applies the
    CPU's power-preserving clamp (``DiffusionSolver.output_clamp``) itself.
    """
    q = ref.result.q[-1]
    scale = max(float(np.abs(ref.radiance).max()),
                float(np.abs(q).max()) / (np.pi * ref.solver.eta ** 2) if q is not None else 0.0)
    L = run.radiance
    diff = float(np.abs(L - ref.radiance).max())
    err = diff / scale if scale > 0 else (0.0 if diff == 0 else np.inf)
    problems = [] if err <= tol else [f"{run.solver_name} vs {ref.solver_name}: radiance differs by {err:.3g} (tol {tol:g})"]
    return err, problems
