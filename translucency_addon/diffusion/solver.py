r"""The diffusion equation on the QuadGraph (Wang et al. 2010, sec. 3 and 4.2-4.3).

Continuous problem (eq. 1 and 2), per colour channel::

    div(kappa grad phi) - mu phi = 0                      in the object
    phi + 2 A kappa dphi/dn = 4 q / (1 - F_dr)            on the boundary

with ``kappa = 1/(3 (sigma_a + sigma_s'))``, ``mu = sigma_a``,
``A = (1 + F_dr)/(1 - F_dr)`` and q the diffused incoming light of eq. 3.

Boundary condition and outgoing radiance, derived
-------------------------------------------------
Near the boundary the diffusion radiance is ``L(w) = phi/(4 pi) + 3/(4 pi) E.w``
with Fick's law ``E = -kappa grad phi``.  Integrating over the hemispheres
gives the partial currents (n the outward normal)::

    J- = phi/4 + (kappa/2) dphi/dn      (into the object)
    J+ = phi/4 - (kappa/2) dphi/dn      (out of the object)

The boundary transmits the incoming light q and reflects a fraction F_dr of
J+ back: ``J- = q + F_dr J+``.  Substituting::

    phi (1 - F_dr)/4 + (kappa/2)(1 + F_dr) dphi/dn = q
    =>  phi + 2 A kappa dphi/dn = 4 q / (1 - F_dr)                    (eq. 2, 6)

so eq. 9's ``4q/(1 + F_dr)`` is a misprint; the derivation (and Kang & Kim
eq. 17) give ``1 - F_dr``.  Eliminating the derivative::

    J+ = (phi - 2 q) / (2 (1 + F_dr)).

J+ leaves through the boundary; radiance crossing from index eta into air is
multiplied by the Fresnel transmittance and divided by eta^2 (L/n^2 is
invariant).  Assuming the exiting radiance is diffuse, ``L_in = J+/pi`` and::

    L_o(w_o) = F_t(w_o) J+ / (pi eta^2)                               (eq. 4, 7 corrected)

The printed eq. 7 has F_r where the transmittance belongs and omits 1/eta^2;
the printed eq. 4 returns eta^2 times too much power.  Check: the power that
leaves is ``int L_o cos dw = J+ (1 - F_dr,ext)/eta^2 = (1 - F_dr) J+`` by the
reciprocity identity of ``fresnel.py``, i.e. exactly the part of J+ the
boundary does not reflect, so a non-absorbing body returns all the power q it
takes in (tested).

Discretisations
---------------
*Paper* (eq. 5 and 6): ``sum_j kappa_j phi_j / d_ij^2 - (w kappa_i + mu_i) phi_i = 0``
with ``w = sum_j 1/d_ij^2``, and eq. 6 at surface nodes.  Not symmetric, and
with ``kappa_j`` of the neighbour inside the sum it is not the conservative
form of div(kappa grad phi): with strong contrast in kappa the row is no
longer diagonally dominant and Jacobi (eq. 8, 9) is not guaranteed to
converge.

*Ours* (default): a finite-volume scheme on the tetrahedra (the QuadGraph is
their dual).  Inner node i (tet volume V_i), link ij crossing a face of area
A_ij, surface node s linked to inner node k::

    sum_j T_ij (phi_i - phi_j) + mu_i V_i phi_i = 0,     T_ij = kappa_ij A_ij / d_ij
    T_sk (phi_s - phi_k) + a_s phi_s / (2A) = 2 a_s q_s / (1 + F_dr)

with ``kappa_ij`` the harmonic mean of the two nodes' kappa (the face
diffusivity of two media in series).  The second row is eq. 6 multiplied by
``a_s/(2A) = a_s (1 - F_dr)/(2 (1 + F_dr))``.  T_ij = T_ji > 0, so the matrix
is a symmetric M-matrix, strictly diagonally dominant at surface nodes and
irreducibly dominant overall: it is positive definite, the discrete maximum
principle holds (phi never exceeds the largest boundary source
``4 q/(1 - F_dr)``), and every Jacobi-preconditioned Chebyshev iteration with
an upper eigenvalue bound from Gershgorin converges -- whatever the contrast
in kappa.  Summing the rows gives the discrete energy balance
``sum_s a_s (q_s - (1 - F_dr) J+_s) = sum_i mu_i V_i phi_i`` exactly.

*Boundary layer.*  Near a lit surface phi falls off like exp(-sigma_tr z).
When a surface link is longer than the diffusion length (sigma_tr d_sk >~ 1:
skin in blue, ketchup, any coarse graph of a dense absorber), the linear
two-point flux ``kappa (phi_s - phi_k)/d`` under-estimates the flux into the
object and the surface node returns light the medium would have absorbed
(measured: +136 % in skin1's blue on a 12 mm sphere, ketchup's green and blue
bright where the exact answer is zero).  The surface end of each surface link
therefore uses the exponentially fitted flux of the 1D equation
``kappa phi'' = mu phi`` over the link (x = sigma_tr d_sk)::

    T_sk = kappa a x / (d sinh x)   (coupling),   C_sk = kappa a x coth(x) / d   (surface diagonal)

which tends to the plain two-point flux as x -> 0 and, as x -> infinity,
to the half-space value ``phi_s = 4q/(1 - F_dr) / (1 + 2 A kappa sigma_tr)``.
Its absorption ``C - T`` overlaps the inner cell's mu V, so the cell gives up
the leading-order overlap ``mu a d / 2`` (at most half its absorption).  The
matrix stays a symmetric M-matrix.  On the sphere the error of the mean goes
from (+0.1, +0.4, +0.9) % to (+0.03, +0.1, +0.3) % for marble on the coarsest
graph, skin1 converges (3.8 % -> 0.6 % worst channel over three levels) where
the plain flux was +136 %, and ketchup's green and blue are ~0.006 where the
exact answer is 0.

Solvers: ``paper`` (Jacobi, eq. 8-9, on the paper's scheme), ``fast``
(Chebyshev semi-iteration on ours) and ``direct`` (scipy sparse LU on ours),
each with the multi-resolution warm start of eq. 10 and a relative-residual
stopping test.

Where each part lives
---------------------
This module is the multi-level driver (:class:`DiffusionSolver`: material ->
systems, lights -> q, coarse-to-fine solves with eq. 10 warm starts, output).
It works on any graph of the contract in :mod:`.graph`; the parts are

* :mod:`.graph` -- the contract a discretisation implements, ``check_graph``;
* :mod:`.assembly` -- ``LevelSystem``, ``assemble`` (both schemes above, fitted links);
* :mod:`.spectral` -- Gershgorin and Lanczos bounds, constant-mode deflation;
* :mod:`.iterative` -- Jacobi, Chebyshev, sparse LU on one level;
* :mod:`.radiance` -- J+, its power-preserving clamp, ``outgoing_radiance``.

Import each part's names from its own module; this one defines only the driver.  It is longer than
the engine's other modules (about 670 lines, 115 of them this derivation) because the driver's contract
is one class: the GPU backend (``gpu_shaders.solver``) and the fluid solver subclass it and replace one
method each (``solve_systems``, the graph), so the light pass, the split, the level loop, the checks,
the output and the power balance stay side by side where every backend shares them.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace

import numpy as np

from . import compiled_map, kernels, radiance
from .assembly import assemble, node_coefficients
from .baked_bounds import adopt_bounds
from ..errors import MaterialError, TranslucencyError
from ..scene.fresnel import diffuse_reflectance_internal
from .graph import SolverInput
from .iterative import (BALANCE_TOL, SOLVER_FUNCTIONS, STEPS_FUNCTIONS, LevelSolve, drain, energy_imbalance,
                        lit_channels, outside_maximum_principle, relay, solve_direct, start_image)
from ..scene.lights import (LampBeams, environment_flux, incident_flux, shadow_visibility, weighted_cosine,
                            weighted_direction)
from ..scene.materials import Material
from .radiance import clamp_scale, map_to_points, outgoing_radiance
from .split import albedo, half_space_split

SOLVERS = ("fast", "paper", "direct", "jacobi")
LAMP_SOURCES = ("volume", "boundary")


@dataclass
class SolveOptions:
    solver: str = "fast"  # fast | paper | direct | jacobi (Jacobi on our scheme)
    tol: float = 1e-4
    max_iterations: int = 50_000
    check_every: int = 8
    coarse_tol: float | None = None  # tolerance on coarser levels (default: tol)
    levels: str = "all"  # "all": multi-resolution warm start; "finest": single level
    sky_occlusion: bool = True  # use the bake's sky visibility (when baked) for environment light
    # The first-scatter split (diffusion/split.py): closed-form single scattering added to the
    # output, the diffusion's boundary source reduced to what scatters more, so the two add up.  True: every
    # channel; a solve's ``single=`` (the planner's channels) overrides it.
    single_scattering: bool = False
    # Where a lamp's light enters the diffusion in the split's channels: "volume", the uncollided beam
    # along its refracted chords as a volume source (beam_source.py), or "boundary", all of it at the
    # surface node it enters (eq. 3 with eq. 6's share).  The world's light is always a boundary source.
    lamp_source: str = "volume"

    def scheme(self) -> str:
        return "paper" if self.solver == "paper" else "fv"


@dataclass
class SolveResult:
    phi: list  # per level (N_l, 3)
    q: list  # per level (n_surface_l, 3)
    level_solves: list
    seconds: dict = field(default_factory=dict)
    scheme: str = "fv"
    warnings: list = field(default_factory=list)  # from the light pass (e.g. a light inside the object)
    # With the first-scatter split: the light that entered (q above is the diffusion's source m q) and the
    # channels in which the closed-form single scattering is added to the output.
    q_incident: list | None = None
    single: tuple = (False, False, False)
    first_pass: np.ndarray | None = None  # finest phi without the bounce (solve(bounced=True))
    # Per level, the lamps' part of the entering light and their mean incidence cosine, (q_beam, mu), or
    # None: the incidence-aware split (split.py eq. 6) of that part (scene.lights.LampBeams)
    beams: list | None = None
    # Per level, the lamps' volume source (n_inner, 3) at the inner nodes (beam_source.py), or None
    volume: list | None = None

    @property
    def iterations(self) -> int:
        return int(sum(ls.iterations for ls in self.level_solves))

    def plus_finest(self, response: "SolveResult") -> "SolveResult":
        """The solution for this result's source plus ``response``'s on the finest level (diffusion is
        linear in q): phi, the diffusion's source and the entering light added there; the coarse levels
        (a warm start only), warnings and timings are this result's, the finest level's solve the
        response's.  Every field is carried, so the split's output (``q_incident``, ``single``) holds for
        the sum as for each part; both parts must come from the same solver and split."""
        if tuple(response.single) != tuple(self.single):
            raise ValueError(f"the split's channels differ: {self.single} and {response.single}")

        def finest(a, b):
            if a is None:
                return None
            out = list(a)
            out[-1] = a[-1] + b[-1]
            return out

        return replace(self, phi=finest(self.phi, response.phi), q=finest(self.q, response.q),
                       q_incident=finest(self.q_incident, response.q_incident),
                       beams=_sum_beams(self.beams, response.beams),
                       volume=_sum_volumes(self.volume, response.volume),
                       level_solves=self.level_solves[:-1] + response.level_solves[-1:],
                       seconds=dict(self.seconds), warnings=list(self.warnings), first_pass=None)

    @property
    def residual(self) -> np.ndarray:
        return self.level_solves[-1].residual



def start_no_worse_than_zero(system, b: np.ndarray, x0: np.ndarray) -> np.ndarray:
    """A level's start ``x0`` (n, C), or in a channel where its residual exceeds the zero start's
    (``|b - A x0| > |b|``) the multiple ``alpha x0``, ``alpha = max(0, x0.b / x0.A x0)``, that minimises the
    error's energy norm along it: ``|x - alpha x0|_A^2 = |x|_A^2 - (x0.b)^2 / x0.A x0 <= |x|_A^2``, never
    worse than starting from zero.

    A coarser level's answer carried up by eq. 10 can be far off where the levels see a source differently:
    a point light inside the object, at a coarse node's position, gave the finest level a start 9e9 times
    |b| (the fuzz, ``tests/hard_cases/test_fuzz.py``); the iteration's recursive residual then drifted
    from the true one by ~eps times that, and the solve's check found a true residual 12x the recursive one
    just before stopping.  One product per level solve; a start better than zero is left as it is."""
    if not x0.any():
        return x0
    Ax = system.apply(x0)
    bn = np.einsum("ij,ij->j", b, b)
    r = b - Ax
    worse = np.einsum("ij,ij->j", r, r) > bn
    if not worse.any():
        return x0
    x0 = np.array(x0, dtype=np.float64)
    for c in np.flatnonzero(worse):
        xAx = float(x0[:, c] @ Ax[:, c])
        alpha = max(0.0, float(x0[:, c] @ b[:, c]) / xAx) if xAx > 0 else 0.0
        x0[:, c] *= alpha
    return x0


class DiffusionSolver:
    """Multiple scattering for one baked object: material, lights -> radiance per vertex.

    Typical use::

        solver = DiffusionSolver(bake, material, field_values)   # field: per level, or None
        result = solver.solve(lights, environment)
        L = solver.vertex_radiance(result)                        # (n_vertices, 3)

    Changing the material re-samples kappa and mu at the nodes
    (:meth:`set_material`) without a re-bake.  ``bake`` is anything of the
    :class:`.graph.SolverInput` protocol: a :class:`.bake.Bake`, or one frame
    of a particle fluid (:class:`.fluid.FluidFrame`, solved by the subclass
    :class:`.fluid.FluidDiffusionSolver`).
    """

    def __init__(self, bake: SolverInput, material: Material, field_values=None,
                 options: SolveOptions | None = None):
        self.bake = bake
        self.options = options or SolveOptions()
        if self.options.solver not in SOLVERS:
            raise TranslucencyError(f"unknown solver {self.options.solver!r}; choose one of {', '.join(SOLVERS)}")
        if self.options.lamp_source not in LAMP_SOURCES:
            raise TranslucencyError(f"unknown lamp source {self.options.lamp_source!r}; choose one of "
                                    f"{', '.join(LAMP_SOURCES)}")
        self._shadow_bvh = bake.surface_bvh  # None: built on the first shadow ray
        self._occluder_cache = None  # (content key of other objects' triangles, BVH of the mesh and them)
        self.warnings: list[str] = []  # of the latest light pass (incident)
        # What this solver derives once and reuses, owned here: "inside" (whether a light position lies
        # inside the mesh, :meth:`lights_inside`), "bounce_G" and "bounced" (``interreflection``: the
        # bounce operator per eta and the block system per material, eta and split), "diagonal" (the mesh's,
        # :meth:`mesh_diagonal`), "inner_tree" (per level, a k-d tree of the inner nodes: :meth:`lamp_volume`).
        self.cache: dict = {}
        self.set_material(material, field_values)

    # -- material ------------------------------------------------------------
    #: A pose of the bake is handed to :meth:`rebind` rather than to a new solver (the GPU's: its graph
    #: textures stay, the coefficients are uploaded again); the CPU solver holds nothing a new one would not.
    rebinds_poses = False

    def set_material(self, material: Material, field_values=None) -> None:
        """Sample kappa and mu at every node of every level and assemble the systems."""
        self.material = material
        self.field_values = field_values
        self.eta = material.eta
        self.fdr = diffuse_reflectance_internal(material.eta)
        levels = self.bake.levels
        if field_values is not None and len(field_values) != len(levels):
            raise MaterialError(f"field values needed for {len(levels)} levels, got {len(field_values)}")
        self.systems = []
        self.surface_albedo = []  # per level (n_surface, 3): sigma_s'/sigma_t at the surface nodes (the split)
        self.surface_sigma_t = []  # per level (n_surface, 3): sigma_t per mm there (the lamps' volume source)
        for i, lv in enumerate(levels):
            fv = None if field_values is None else np.asarray(field_values[i])
            if fv is not None and fv.shape[0] != lv.n_nodes:
                raise MaterialError(f"level {i}: field has {fv.shape[0]} values for {lv.n_nodes} nodes")
            sa, ss = node_coefficients(material, fv, lv.n_nodes)
            self.surface_albedo.append(albedo(sa[lv.n_inner:], ss[lv.n_inner:]))
            self.surface_sigma_t.append(sa[lv.n_inner:] + ss[lv.n_inner:])
            self.systems.append(assemble(lv, sa, ss, material.eta, self.bake.mm_per_unit, self.options.scheme()))
        # the bake's kept bounds where these are its systems (baked_bounds: a cold frame runs no Lanczos)
        self.bounds_from_bake = adopt_bounds(self.systems, getattr(self.bake, "spectral_bounds", None))

    def rebind(self, bake: SolverInput) -> None:
        """This solver on another pose of its bake (Wang et al. sec. 6.4): the same graph -- levels, links,
        transfers, vertex map -- with moved nodes, so the systems are assembled again from its lengths,
        areas and volumes with the material and field as they are (attached to the rest pose); what
        depended on the geometry (the shadow trees, with or without other objects, the bounce's operators)
        is dropped.  The spectral bounds
        are the caller's to carry (:func:`.deformation.frames.carry_spectral_bounds`)."""
        old, new = self.bake.levels, bake.levels
        if len(old) != len(new) or any(a.n_inner != b.n_inner or a.n_surface != b.n_surface
                                       or not np.array_equal(a.neighbors, b.neighbors) for a, b in zip(old, new)):
            raise TranslucencyError("rebind needs a pose of the same graph (its levels, nodes and links); "
                                    "another graph needs a solver of its own")
        self.bake = bake
        self._shadow_bvh = bake.surface_bvh
        self._occluder_cache = None  # it holds the last pose's triangles
        self.cache = {}
        self.set_material(self.material, self.field_values)

    # -- lights ----------------------------------------------------------------
    def shadow_bvh(self, occluders=None):
        """BVH of the object's own surface plus other objects' triangles (object space).

        ``occluders``: ``None``, an ``(V, F)`` pair, or a prebuilt
        :class:`~.raycast.TriangleBVH` of the whole scene.  The combined BVH is
        cached and rebuilt only when the occluder arrays change.
        """
        from ..geometry.raycast import TriangleBVH, content_key, mesh_bvh

        if isinstance(occluders, TriangleBVH):
            return occluders
        if occluders is None:
            if self._shadow_bvh is None:
                self._shadow_bvh = mesh_bvh(self.bake.mesh_vertices, self.bake.mesh_faces,
                                            getattr(self.bake, "mesh_bvh_order", None))
            return self._shadow_bvh
        Vo, Fo = (np.ascontiguousarray(a) for a in occluders)
        key = content_key(Vo, Fo)
        cached = self._occluder_cache
        if cached is not None and cached[0] == key:
            return cached[1]
        V = np.vstack([self.bake.mesh_vertices, Vo])
        F = np.vstack([self.bake.mesh_faces, np.asarray(Fo) + len(self.bake.mesh_vertices)])
        bvh = TriangleBVH(V, F)
        self._occluder_cache = (key, bvh)
        return bvh

    def incident(self, lights, environment=None, shadows: bool = True, occluders=None,
                 levels=None, bounce=None, beams: list | None = None) -> list:
        """q (eq. 3) at the surface nodes of the requested levels (default all); None elsewhere.

        Lights inside the object contribute nothing and are named in
        :attr:`warnings` (see :meth:`lights_inside`).  When the bake carries
        sky visibility (``sky_visibility``) and ``options.sky_occlusion`` is
        on, the environment term loses the directions in which the object
        sees itself, and ``bounce`` -- the mesh's vertex radiance from a
        previous solve, (n_vertices, 3) -- adds the light the object sends to
        itself through those directions (one interreflection bounce).
        ``beams``: a list with one entry per level, filled with the lamps' part of q and their incidence
        cosines, ``(q_beam, mu)`` (:class:`~..scene.lights.LampBeams`), for the incidence-aware split.
        """
        sky = self.sky
        if sky is None:
            bounce = None
        want = range(len(self.bake.levels)) if levels is None else levels
        lights = list(lights or ())
        inside = self.lights_inside(lights)
        self.warnings = [
            f"light {light.name or light.kind!r} at {tuple(round(float(x), 6) for x in light.position)} is inside "
            "the object: a source inside the medium is not part of the surface-lighting model, so it adds no "
            "light; move it outside the surface" for light in inside]
        if inside:
            lights = [light for light in lights if not any(light is x for x in inside)]
        vis = None
        if shadows and lights:
            vis = shadow_visibility(self.shadow_bvh(occluders), offset=self.shadow_offset())
        out = [None] * len(self.bake.levels)
        for i in want:
            lv = self.bake.levels[i]
            lamp = LampBeams.zeros(len(lv.normal)) if beams is not None else None
            if sky is None:
                out[i] = incident_flux(lights, environment, lv.surface_position, lv.normal, self.eta,
                                       self.bake.mm_per_unit, visibility=vis, beams=lamp)
            else:
                q = incident_flux(lights, None, lv.surface_position, lv.normal, self.eta, self.bake.mm_per_unit,
                                  visibility=vis, beams=lamp)
                env = environment if environment is not None and not environment.is_black else None
                q_env = environment_flux(env, lv.normal, self.eta) if env is not None else None
                out[i] = q + sky.correct(i, lv.normal, self.eta, q_env, env, bounce)
            if beams is not None:  # once every lamp is in: the incidence cosine is their q-weighted mean
                beams[i] = lamp.parts()
        return out

    def mesh_diagonal(self) -> float:
        """The mesh's bounding-box diagonal (object units), computed once per bake (a pose: :meth:`rebind`)."""
        if "diagonal" not in self.cache:
            self.cache["diagonal"] = float(np.linalg.norm(np.ptp(self.bake.mesh_vertices, axis=0)))
        return self.cache["diagonal"]

    def shadow_offset(self) -> float:
        """How far along the normal (object units) shadow rays start: 1e-4 of the mesh's diagonal."""
        return 1e-4 * self.mesh_diagonal()

    def lights_inside(self, lights) -> list:
        """The point, spot and area lights whose position lies inside the object.

        Eq. 3's q is the light that reaches the surface from outside.  A
        source inside the medium would be an interior source term of the
        diffusion equation, which this boundary-source model (and its GPU
        kernels, which form b from q at surface nodes only) does not have.
        Counting it through the surface would be wrong: with shadow rays the
        object's own surface blocks it (zero), without them the surface
        elements on the far side of a concavity that face it would be lit as
        if from outside.  So such a light contributes nothing and
        :meth:`incident` says so.  Inside = majority vote of ray parity
        against the user's mesh (``raycast.inside_mesh``, robust to small
        holes); results are cached per position.
        """
        cand = [light for light in lights if light.kind != "sun"]
        if not cand:
            return []
        from ..geometry.raycast import inside_mesh

        cache = self.cache.setdefault("inside", {})
        keys = [tuple(float(x) for x in light.position) for light in cand]
        todo = sorted({k for k in keys if k not in cache})
        if todo:
            flags = inside_mesh(self.shadow_bvh(None), np.array(todo))
            if len(cache) > 1024:
                cache.clear()
            cache.update(zip(todo, (bool(f) for f in flags)))
        return [light for light, k in zip(cand, keys) if cache[k]]

    @property
    def sky(self):
        """The bake's sky visibility when this solver uses it (baked and ``options.sky_occlusion``), else None."""
        return self.bake.sky if self.options.sky_occlusion else None

    # -- solve -------------------------------------------------------------------
    def can_warm_start(self, warm_start) -> bool:
        """Whether ``warm_start`` carries a finest-level solution this solver can start from."""
        return warm_start is not None and warm_start.phi[-1] is not None

    def solve(self, lights=(), environment=None, **kw) -> SolveResult:
        """Solve every level coarse to fine (or only the finest, from ``warm_start``): :meth:`solve_steps`
        run to its end (the keywords are its own)."""
        return drain(self.solve_steps(lights, environment, **kw))

    def solve_steps(self, lights=(), environment=None, *, q=None, warm_start=None, shadows=True,
                    occluders=None, channels=None, bounce=None, single=None, bounced=False, beams=None):
        """Solve every level coarse to fine (or only the finest, from ``warm_start``): the one driver, as a
        generator (:meth:`solve` runs it to its end).

        After every sweep of the CPU's Chebyshev it yields a function that returns
        the solution so far as a :class:`SolveResult` (the finest level's iterate, or the latest coarser
        level carried up by eq. 10's Shepard transfer, with this frame's light; ``level_solves`` empty):
        the viewport's progressive frames show it and resume the generator on later redraws.  A backend
        of its own (the GPU) and the other solvers run their levels without yielding.  It returns the
        :class:`SolveResult`.

        ``q``: precomputed incident light per level (skips the light pass); ``beams``: its lamps' part per
        level, ``(q_beam, mu)`` or None (:meth:`incident`'s), for the incidence-aware split.
        ``bounce``: vertex radiance of a previous solve, the light the object
        sends to itself (used only with the bake's sky visibility; see
        :meth:`incident` and :meth:`solve_interreflected`).
        ``warm_start``: a previous :class:`SolveResult` of this solver; its
        finest solution starts the finest level directly (the frame-to-frame
        case), so coarse levels are skipped.
        ``channels``: (bool, bool, bool) from the planner; skipped channels
        cost nothing on the CPU and come out as zero flux.
        ``single``: (bool, bool, bool), the channels in which the first-scatter split runs
        (:meth:`split_source`; default ``options.single_scattering``): the diffusion solves for
        ``m(alpha) q`` and the output adds the closed-form single scattering of q.
        ``bounced``: the finest level solves the object's light and its bounce at once, the block
        system (1) of :mod:`.interreflection` (:func:`~.interreflection.solve_finest_bounced`, only
        where :func:`~.interreflection.one_solve_applies`); the result's finest ``q`` then holds the
        bounce and ``first_pass`` the phi0 of (1).  Everything else -- light pass, split, coarse
        levels, channel mask, checks, timings -- is this driver's, for both.
        """
        t0 = time.perf_counter()
        opts = self.options
        n_lv = len(self.bake.levels)
        fine = n_lv - 1
        if bounced:
            from .interreflection import one_solve_applies

            why = one_solve_applies(self)
            if why:
                raise ValueError(f"the block solve of the bounce does not apply: {why}")
        usable = self.can_warm_start(warm_start)
        finest_only = opts.levels == "finest" or usable
        active = [fine] if finest_only else list(range(n_lv))
        warnings = []
        if q is None:
            beams = [None] * n_lv
            q = self.incident(lights, environment, shadows=shadows, occluders=occluders, levels=active,
                              bounce=bounce, beams=beams)
            warnings = list(self.warnings)
        q_light = q
        single = self.split_channels(single)
        volume, at_surface = self.lamp_volume(beams, single)
        q, q_incident, single = self.split_source(q, single, beams, volume, at_surface)
        if q_incident is None:
            beams = None
        t1 = time.perf_counter()
        mask = (True, True, True) if channels is None else tuple(bool(c) for c in channels)
        cols = tuple(c for c in range(3) if mask[c])
        first_pass = None
        if not cols:
            phi = [None if p is None else np.zeros((lv.n_nodes, 3)) for p, lv in
                   zip([q[i] for i in range(n_lv)], self.bake.levels)]
            solves = [LevelSolve(0, np.zeros(3), [0.0], 0.0) for _ in active]
        else:
            levels = active[:-1] if bounced else active
            partial = self._partial_result(q, q_incident, single, cols, beams, volume)
            if not levels:
                phi, solves = [None] * n_lv, []
            elif type(self).solve_systems is DiffusionSolver.solve_systems and opts.solver == "fast":
                phi, solves = yield from self._systems_steps(q, levels, warm_start, cols, partial, volume)
            else:
                kw = {} if volume is None else {"volume": volume}  # a backend without volume sources sees none
                phi, solves = self.solve_systems(q, levels, warm_start, cols, **kw)
            if bounced:
                from .interreflection import finest_bounced_steps

                step = yield from finest_bounced_steps(self, q_light[fine], phi[fine - 1] if levels else None,
                                                       warm_start if usable else None, cols, single, partial,
                                                       beam=None if beams is None else beams[fine],
                                                       volume=None if volume is None else volume[fine],
                                                       at_surface=None if at_surface is None else at_surface[fine])
                phi[fine], q = step.phi, list(q)
                q[fine], first_pass = step.q, step.first_pass
                if q_incident is not None:
                    q_incident = list(q_incident)
                    q_incident[fine] = step.q_incident
                solves.append(step.info)
            warnings += [s.note for s in solves if getattr(s, "note", "")]
            if len(cols) < 3:  # a backend that ignores the mask still honours it
                off = [c for c in range(3) if not mask[c]]
                for p in phi:
                    if p is not None:
                        p[:, off] = 0.0
        t2 = time.perf_counter()
        return SolveResult(phi=phi, q=q, level_solves=solves, scheme=self.systems[-1].scheme,
                           seconds={"lights": t1 - t0, "solve": t2 - t1, "total": t2 - t0}, warnings=warnings,
                           q_incident=q_incident, single=single, first_pass=first_pass, beams=beams,
                           volume=volume)

    # -- the first-scatter split -----------------------------------------------------------
    def split_channels(self, single=None) -> tuple:
        """The channels in which the first-scatter split runs: ``single`` (the planner's), else every
        channel when ``options.single_scattering``, else none."""
        if single is None:
            single = (bool(self.options.single_scattering),) * 3
        return tuple(bool(c) for c in single)

    def lamp_volume(self, beams, single) -> tuple:
        """``(volume, at_surface)``: the lamps' volume source per level, (n_inner, 3), in the split's channels
        ``single`` (zero in the others, where the lamps stay boundary sources), and per level the part of the
        lamps' light that enters the diffusion at the boundary instead, per unit of it (n_surface, 3), or None
        (:func:`.beam_source.shallow_to_boundary`: collisions nearer to the surface than to the node whose cell
        would hold them; on the level the beams are traced from, the finest lit one -- a coarser level, only
        the finer one's starting guess, takes all of it in the volume).  ``(None, None)`` unless
        ``options.lamp_source == "volume"`` and some level has lamp light (:mod:`.beam_source`; ``beams`` per
        level ``(q_beam, mu, to_light)``)."""
        if self.options.lamp_source != "volume" or beams is None or not any(single):
            return None, None
        if all(b is None or not np.any(b[0]) for b in beams):
            return None, None
        from scipy.spatial import cKDTree

        from .beam_source import beam_deposits, deposit_in_cells, merged_pieces, shallow_to_boundary

        # The beams are traced once, from the finest level that has them (its surface is the closest to
        # the mesh), and their deposits binned into every level's cells, scaled on a coarser level to the
        # lamp light its own surface takes in (its nodes' areas and normals differ), so that each level
        # keeps its own energy balance: a coarser level is the finer one's starting guess only, and takes
        # the deposits merged a few pieces at a time (:func:`.beam_source.merged_pieces`).
        src = max(i for i, b in enumerate(beams) if b is not None and np.any(b[0]))

        def lamp_power(i):
            return (self.bake.levels[i].area[:, None] * np.asarray(beams[i][0])).sum(axis=0)
        p_src = lamp_power(src)
        dep = beam_deposits(self.bake.levels[src], self.shadow_bvh(None), self.bake.mm_per_unit, beams[src],
                            self.surface_sigma_t[src], self.surface_albedo[src], self.eta, self.mesh_diagonal())
        on = np.array(single, dtype=float)
        power = dep.power * on
        trees = self.cache.setdefault("inner_tree", {})  # per level, of its inner nodes (the cells) ...
        surface_trees = self.cache.setdefault("surface_tree", {})  # ... and of its surface nodes
        out = []
        at_surface = [None] * len(beams)
        mm = float(self.bake.mm_per_unit)
        coarse = None  # the deposits merged for the coarser levels, once
        for i, beam in enumerate(beams):
            lv = self.bake.levels[i]
            if beam is None or lv.n_inner == 0:
                out.append(None)
                continue
            if i not in trees:
                trees[i] = cKDTree(np.asarray(lv.position[: lv.n_inner], dtype=np.float64), balanced_tree=False)
            if i == src and len(dep.points):
                dist, cell = trees[i].query(dep.points, workers=-1)
                # whether the entry node is the surface node nearest to the deposit counts only where the
                # deposit lies nearer to the surface than to its cell's node (eq. 9): asked only there (the
                # query of every deposit, most of them deep and equidistant from many surface nodes, was a
                # third of the volume source's cost on the Final sphere)
                shallow = np.flatnonzero(dep.depth < dist * mm)
                at_entry = np.zeros(len(dep.points), dtype=bool)
                if shallow.size:
                    if i not in surface_trees:
                        surface_trees[i] = cKDTree(np.asarray(lv.surface_position, dtype=np.float64))
                    _, nearest = surface_trees[i].query(dep.points[shallow], workers=-1)
                    at_entry[shallow] = nearest == dep.entry[shallow]
                inside, q_surface = shallow_to_boundary(dep._replace(power=power), dist * mm, lv.area * mm * mm,
                                                        self.eta, at_entry=at_entry)
                q_b = np.asarray(beam[0], dtype=np.float64)
                at_surface[i] = np.where(q_b > 0, q_surface / np.where(q_b > 0, q_b, 1.0), 0.0)
                out.append(deposit_in_cells(trees[i], lv.n_inner, dep.points, inside, cell=cell))
            else:
                scale = np.where(p_src > 0, lamp_power(i) / np.where(p_src > 0, p_src, 1.0), 0.0) if i != src else 1.0
                if coarse is None:
                    coarse = merged_pieces(dep.points, power)
                out.append(deposit_in_cells(trees[i], lv.n_inner, *coarse) * scale)
        return out, at_surface

    def split_source(self, q, single=None, beams=None, volume=None, at_surface=None):
        """``(diffusion source per level, incident q per level or None, channels)`` of the split.

        In the channels of ``single`` (default: all when ``options.single_scattering``) the light that
        entered, q, is split over the local half-space (:mod:`.diffusion.split`): the part
        ``s(alpha) q`` that leaves after one scattering is the closed-form single-scattering term the output
        adds (:meth:`split_radiance_at`), and the diffusion solves for ``m(alpha) q`` (``m <= 1 - s``), the
        source whose half-space return is the multiple scattering M(alpha); alpha is each surface node's.
        So both terms add up, each path once, node by node in a heterogeneous medium.  ``beams`` (per
        level ``(q_beam, mu)`` or None): the lamps' part of q is split by its incidence (eq. 6 there).
        ``volume`` (:meth:`lamp_volume`, or None): on the levels where it holds a source, the lamps' light
        enters the diffusion through it, so their part of q leaves the boundary source (the output still
        adds their single scattering), but for ``at_surface`` per level (:meth:`lamp_volume`'s).
        """
        single = self.split_channels(single)
        if not any(single):
            return q, None, (False, False, False)
        split = half_space_split(self.eta)
        on = np.array(single)
        out = []
        for i, qi in enumerate(q):
            if qi is None:
                out.append(None)
                continue
            m = split.source_factors(self.surface_albedo[i], qi, None if beams is None else beams[i],
                                     beam_in_volume=volume is not None and volume[i] is not None,
                                     beam_at_surface=None if at_surface is None else at_surface[i])
            out.append(np.asarray(qi) * np.where(on, m, 1.0))
        return out, list(q), single

    def split_radiance_at(self, result: SolveResult, L, idx, w, normals, view_dirs=None,
                          transported: bool = True) -> np.ndarray:
        """The output of the first-scatter split at points mapped onto the finest surface nodes.

        ``L`` is the diffusion's isotropic output there (:func:`.radiance.outgoing_radiance`, CPU or the
        GPU's ``radiance.glsl``).  In the split's channels it leaves with the angular shape of multiple
        scattering (eq. 4 of :mod:`.diffusion.split`, same power) and the closed-form single
        scattering (eq. 2) is added (:meth:`split_terms_at`); without a split ``L`` is returned as it is.
        With ``transported``, in a frame whose lamps enter through the volume (:mod:`.beam_source`), the part
        of the output beyond the half-space's return of the point's own light -- light carried there from
        elsewhere -- leaves with the diffusion's own angular distribution instead (eq. 9 of
        :mod:`.diffusion.split`).  Without a volume source (a world, the sky alone) the output beyond the local
        return is mostly the diffusion's own excess over transport on a curved surface, not light from
        elsewhere: reshaped, it made the dark-sphere sweep 3-5 points brighter (11.8 % at albedo 0.51 against
        7.0 %), so there it keeps eq. 4's shape.  The sky bounce's light (:meth:`interreflected_steps`) keeps
        eq. 4's shape too, as its one-solve block system does.
        """
        if result.q_incident is None or not any(result.single) or result.q_incident[-1] is None:
            return L
        cos_o = None
        if view_dirs is not None:
            cos_o = np.einsum("vj,vj->v", np.asarray(normals, dtype=np.float64), view_dirs)
        on = np.array(result.single, dtype=bool)
        in_volume = result.volume is not None and result.volume[-1] is not None
        transported = transported and in_volume  # eq. 9 carries the lamps' light the volume source moved (below)
        terms = self.split_terms_at(result.q_incident[-1], None if result.beams is None else result.beams[-1],
                                    idx, w, cos_o, beam_in_volume=in_volume, local=transported)
        shape, single = terms[:2]
        if transported:
            c = 1.0 if cos_o is None else cos_o  # along the normal: one cosine, one factor for every point
            unit = outgoing_radiance(np.ones((np.size(c), 1)), c, self.eta)  # L per unit J+: (n, 1) or (1, 1)
            split = half_space_split(self.eta)
            if on.all() and len(single) >= radiance.COMPILED_MAP_MIN_POINTS and not compiled_map.available():
                # the lines below and eq. 9 in one compiled pass per point (a dozen numpy passes at 655 k vertices)
                return compiled_map.transported_output(L, shape, single, terms[2], unit, split.transported_shape(c),
                                                       self.fdr)
            power = np.where(unit > 0, (1.0 - self.fdr) * np.asarray(L) / np.where(unit > 0, unit, 1.0), 0.0)
            shape = split.with_transported(shape, terms[2], power, c)
        if on.all():  # in the terms' own (new) arrays: per render-mesh vertex, each temporary costs
            shape *= L
            shape += single
            return shape
        return np.asarray(L) * np.where(on, shape, 1.0) + single * on

    def split_terms_at(self, q_incident, beam, idx, w, cos_o=None, beam_in_volume: bool = False,
                       local: bool = False) -> tuple:
        """``(shape, single)`` of the split (:meth:`.split.HalfSpaceSplit.output_terms`: eq. 4's factor c on
        the diffusion's output, eqs. 2 and 6's single-scattering radiance) at the points of the map
        ``idx``/``w``, for the finest level's entering light ``q_incident`` (n_s, C) and lamps' part
        ``beam`` = (q_beam, mu) or None.

        Seen along the normal (``cos_o`` None: the viewport's view, and the bounce's), both are evaluated
        where the light pass computed q -- at the finest surface nodes -- and carried to the points by
        the map, one sparse product over both (:func:`.radiance.map_to_points`): the points cost the
        product, not the split's table lookups, which took 0.65 s per frame at 655 k vertices against
        ~40 ms at the 37 k nodes.  The map interpolates the terms instead of their inputs (q, albedo,
        incidence): the same where those are smooth, and within the map's own smoothing elsewhere.  Seen
        at a cosine ``cos_o`` (n,) per point (a camera's view, which varies from point to point), the terms
        are evaluated at the points from their interpolated inputs (:meth:`split_inputs_at`).  With ``local``
        a third array, the half-space's return of the points' own light (:meth:`.split.HalfSpaceSplit.local_return`).
        """
        split = half_space_split(self.eta)
        if cos_o is None:
            q = np.asarray(q_incident, dtype=np.float64)
            a = self.surface_albedo[-1]
            shape, single = split.output_terms(q, a, np.ones(len(q)), beam, beam_in_volume=beam_in_volume)
            more = (split.local_return(q, a, beam),) if local else ()
            return tuple(map_to_points(idx, w, shape, single, *more))
        q_v, a_v, beam_v = self.split_inputs_at(q_incident, beam, idx, w)
        terms = split.output_terms(q_v, a_v, cos_o, beam_v, beam_in_volume=beam_in_volume)
        return terms + ((split.local_return(q_v, a_v, beam_v),) if local else ())

    def split_inputs_at(self, q_incident, beam, idx, w) -> tuple:
        """``(q, alpha, beam)`` of the finest surface nodes mapped onto points (``idx``, ``w``: the vertex map's
        form): the entering light and albedo interpolated, and the lamps' part ``(q_beam, mu)`` with its
        incidence cosine weighted by the lamps' q (or None)."""
        if beam is None:
            q_v, a_v = map_to_points(idx, w, q_incident, self.surface_albedo[-1])
            return q_v, a_v, None
        qb = np.asarray(beam[0])
        q_v, a_v, qb_v, mu_q = map_to_points(idx, w, q_incident, self.surface_albedo[-1], qb,
                                             qb.mean(axis=1) * np.asarray(beam[1]))
        return q_v, a_v, (qb_v, weighted_cosine(mu_q, qb_v.mean(axis=1)))

    def solve_interreflected(self, lights=(), environment=None, **kw) -> tuple:
        """Solve, then solve again ``bounces`` times with the object's own radiance as ``bounce``:
        :meth:`interreflected_steps` run to its end (the keywords are its own)."""
        return drain(self.interreflected_steps(lights, environment, **kw))

    def interreflected_steps(self, lights=(), environment=None, *, bounces: int = 1, warm_start=None,
                             bounce=None, **kw):
        """Solve, then solve again ``bounces`` times with the object's own radiance as ``bounce``; a
        generator (:meth:`solve_interreflected` runs it to its end).

        One bounce (the add-on's default) is one Chebyshev solve of both passes as a block system
        (:mod:`.interreflection`: the same answer, warm-started frame to frame as a pair) wherever
        :func:`.interreflection.one_solve_applies`: that solve's steps are yielded (:meth:`solve_steps`);
        otherwise, and for other ``bounces``, each pass is a solve warm-started from the previous one, run
        to its end.  ``bounce`` (a previous frame's vertex radiance) replaces the first plain pass.
        Without sky visibility in the bake this is a single :meth:`solve`.
        Returns ``(SolveResult, vertex radiance along the normals)``.
        """
        # The first-scatter split (``single=``, ``options.single_scattering``) is part of the block
        # system ((1') of :mod:`.interreflection`).
        if self.sky is not None and int(bounces) == 1 and bounce is None:
            from .interreflection import one_solve_applies

            if not one_solve_applies(self):
                res = yield from self.solve_steps(lights, environment, warm_start=warm_start, bounced=True, **kw)
                return res, self.vertex_radiance(res, transported=False)
        res = self.solve(lights, environment, warm_start=warm_start, bounce=bounce, **kw)
        L = self.vertex_radiance(res, transported=False)  # the bounce's light: eq. 4's shape, as the block system
        if self.sky is None:
            return res, L
        for _ in range(int(bounces) - (bounce is not None)):
            res = self.solve(lights, environment, warm_start=res, bounce=L, **kw)
            L = self.vertex_radiance(res, transported=False)
        return res, L

    def solve_systems(self, q, active, warm_start=None, cols=(0, 1, 2), volume=None):
        """Run the linear solves on the ``active`` levels, coarse to fine (eq. 10 between them), in the
        channels ``cols``.

        This is the part a GPU backend replaces (``gpu_shaders.solver``); the
        assembly, the light pass, the solution checks after each level
        (:meth:`checked_level`) and the output stay shared.  ``volume``: the lamps' volume source per level
        (:meth:`lamp_volume`) or None.
        Returns ``(phi per level (None where inactive), [LevelSolve])``.
        """
        return drain(self._systems_steps(q, active, warm_start, cols, volume=volume))

    def _systems_steps(self, q, active, warm_start=None, cols=(0, 1, 2), partial=None, volume=None):
        """:meth:`solve_systems` as a generator: with the fast solver it yields ``partial(level, iterate)`` (a
        function, see :meth:`solve_steps`) after every sweep, and before a level's first sweep where its start
        is not zero (a warm start, or the coarser level's answer: an image before the solve's set-up)."""
        opts = self.options
        fn = SOLVER_FUNCTIONS[opts.solver]
        cols = tuple(cols)
        phi = [None] * len(self.bake.levels)
        solves = []
        coarser = None
        for i in active:
            system = self.systems[i].subset(cols)
            b = system.rhs(q[i][:, cols], None if volume is None or volume[i] is None else volume[i][:, cols])
            x0 = self.initial_guess(i, cols, coarser, warm_start)
            # No light on this level in a channel: the (non-singular) system's answer is exactly 0.  A warm
            # start from a coarser level that did see light (a light grazing the surface) would otherwise
            # leave a small residue the relative stopping test (|b| = 0) accepts.
            x0[:, ~lit_channels(b)] = 0.0
            x0 = start_no_worse_than_zero(system, b, x0)
            if partial is not None and fn in STEPS_FUNCTIONS:  # its steps (a replaced function runs as it is)
                if x0.any():  # the start (a warm start or the coarser level's answer) is an image already
                    yield start_image(lambda lv=i, x=x0: partial(lv, x))
                steps = STEPS_FUNCTIONS[fn](system, b, x0, self.level_tolerance(i), opts.max_iterations,
                                            opts.check_every)
                x, info = yield from relay(steps, lambda get, lv=i: lambda: partial(lv, get()))
            else:
                x, info = fn(system, b, x0, self.level_tolerance(i), opts.max_iterations, opts.check_every)
            x, info = self.checked_level(i, system, q[i][:, cols], b, x, info)
            phi[i] = coarser = kernels.in_channels(x, cols)
            info.residual = kernels.in_channels(info.residual, cols)
            solves.append(info)
        return phi, solves

    def initial_guess(self, level: int, cols, coarser=None, warm_start=None, previous=None) -> np.ndarray:
        """Where a level's solve starts, in the channels ``cols``: the warm start's finest solution (or
        ``previous``, a solution of the finest level given instead), else the next coarser level's solution
        ``coarser`` ((n, 3), all channels) carried up by Shepard interpolation (eq. 10), else zero."""
        n_lv = len(self.bake.levels)
        cols = list(cols)
        if level == n_lv - 1:
            if previous is not None:
                return np.array(np.asarray(previous)[:, cols], dtype=np.float64)
            if warm_start is not None and warm_start.phi[-1] is not None:
                return np.array(warm_start.phi[-1][:, cols], dtype=np.float64)
        if coarser is not None and level > 0:
            return self.upsample(level, np.asarray(coarser)[:, cols])
        return np.zeros((self.bake.levels[level].n_nodes, len(cols)))

    def upsample(self, level: int, x_coarse: np.ndarray) -> np.ndarray:
        """Eq. 10: level ``level - 1``'s values (n, channels) carried up to ``level`` by Shepard interpolation, as
        a sparse product (:func:`.kernels.shepard_matrix`, built once per level; the gather of
        :func:`.kernels.shepard_upsample`, the GPU kernel's twin, gives the same)."""
        mats = self.cache.setdefault("shepard", {})
        if level not in mats:
            idx, w = self.bake.shepard[level - 1]
            mats[level] = kernels.shepard_matrix(idx, w, self.bake.levels[level - 1].n_nodes)
        m, x = mats[level], np.asarray(x_coarse, dtype=np.float64)
        # column by column: a channel's values then do not depend on which other channels are solved (scipy's
        # product of several columns sums in another order), so the planner's skipped channels leave the
        # others bit for bit as in a full solve
        return np.stack([m @ x[:, c] for c in range(x.shape[1])], axis=1)

    def _partial_result(self, q, q_incident, single, cols, beams=None, volume=None):
        """``partial(level, iterate, q_fine=None, q_incident_fine=None)``: a :class:`SolveResult` of the solve
        so far (:meth:`solve_steps`): ``iterate`` (n_level, len(cols)) in its channels (0 in the others,
        the ones the planner turned off) carried up to the finest level by eq. 10's Shepard transfers
        where it is a coarser level's; ``q_fine``/``q_incident_fine`` replace
        the finest level's source and entering light (the bounced block solve's, from its iterate)."""
        fine = len(self.bake.levels) - 1
        cols = list(cols)

        def partial(level, iterate, q_fine=None, q_incident_fine=None):
            x = kernels.in_channels(np.asarray(iterate, dtype=np.float64), cols)
            for lv in range(level + 1, fine + 1):
                x = self.upsample(lv, x)
            qs, qi = list(q), None if q_incident is None else list(q_incident)
            if q_fine is not None:
                qs[fine] = q_fine
                if qi is not None:
                    qi[fine] = q_incident_fine
            return SolveResult(phi=[None] * fine + [x], q=qs, level_solves=[], scheme=self.systems[-1].scheme,
                               q_incident=qi, single=single, beams=beams, volume=volume)
        return partial

    def level_tolerance(self, level: int) -> float:
        """The relative residual a level's solve stops at: ``options.tol`` on the finest level, the coarse
        tolerance (default the same) below it."""
        opts = self.options
        return opts.tol if level == len(self.bake.levels) - 1 else (opts.coarse_tol or opts.tol)

    @property
    def guards_solutions(self) -> bool:
        """Whether :meth:`checked_level` checks this solver's level solutions.

        Only the default solver is guarded: Jacobi is the paper's baseline, whose failures are reported.
        """
        return self.options.solver == "fast"

    def checked_level(self, level: int, system, q, b, x, info):
        """The checks every backend's level solve must pass, and the redo when it does not.

        Called after each level's solve, by this class and by the GPU backend (which reads the level
        back for it), so both are guarded alike.  A solution of the FV system lies in
        ``0 <= phi <= max 4q/(1 - F_dr)`` (the discrete maximum principle,
        :func:`.iterative.outside_maximum_principle`) and keeps the discrete energy balance to
        :data:`.iterative.BALANCE_TOL` of the light in (:func:`.iterative.energy_imbalance`).  A
        near-singular level (little absorption, a weak leak) can let the iteration wander along its
        slowest mode while the residual looks small; such a level is redone by sparse LU on the CPU and
        the returned :class:`LevelSolve` carries a note that says so.

        ``q``, ``b``, ``x``: the level's incident light, right-hand side and solution, for the
        channels of ``system``.  Returns ``(x, info)``, unchanged when ``x`` passes.
        """
        ni = system.level.n_inner
        volume = b[:ni] if np.any(b[:ni]) else None  # the lamps' volume source (beam_source), if any
        if not self.guards_solutions or not (outside_maximum_principle(system, b, x)
                                             or energy_imbalance(system, q, x, self.fdr, volume) > BALANCE_TOL):
            return x, info
        x, direct = solve_direct(system, b)
        return x, LevelSolve(info.iterations, direct.residual, info.history + direct.history,
                             info.seconds + direct.seconds,
                             note=f"level {level}: the {self.options.solver} solve broke the maximum principle or "
                                  f"the energy balance (residual {float(np.max(info.residual)):.2e}); "
                                  "solved directly instead")

    # -- output ------------------------------------------------------------------
    def surface_phi(self, result: SolveResult, level: int = -1) -> np.ndarray:
        """phi at the level's surface nodes (the GPU backend reads them back instead)."""
        return result.phi[level][self.bake.levels[level].n_inner:]

    def output_clamp(self, result: SolveResult, level: int = -1) -> np.ndarray:
        """Per-channel factor (<= 1) that keeps the output's clamp of J+ at 0 from creating power.

        :func:`.radiance.clamp_scale` of the level's surface phi; every backend's output applies
        it (the CPU's in :meth:`surface_partial_current`, the GPU's to its kernel's radiance).
        """
        return clamp_scale(self.surface_phi(result, level), result.q[level], self.bake.levels[level].area,
                           self.fdr)

    def surface_partial_current(self, result: SolveResult, level: int = -1) -> np.ndarray:
        """J+ at the level's surface nodes: clamped at 0, scaled so that the clamp adds no power.

        See :meth:`output_clamp`.
        """
        jplus = kernels.outgoing_partial_current(self.surface_phi(result, level), result.q[level], self.fdr)
        return jplus * self.output_clamp(result, level)

    def vertex_radiance(self, result: SolveResult, view_dirs=None, transported: bool = True) -> np.ndarray:
        """Outgoing radiance (W/(m^2 sr)) at the baked mesh's vertices.

        ``view_dirs``: (n_vertices, 3) unit vectors from the surface towards
        the viewer; default: along the vertex normal.  ``transported``: as :meth:`split_radiance_at`.
        """
        idx, w = self.bake.vertex_map
        return self.radiance_at(result, idx, w, self.bake.mesh_normals, view_dirs, transported)

    def radiance_at(self, result: SolveResult, idx, w, normals, view_dirs=None,
                    transported: bool = True) -> np.ndarray:
        """Outgoing radiance at arbitrary points mapped onto the finest surface nodes.

        ``idx``/``w`` (n, k): surface-node indices and weights (e.g. from
        :func:`.bake.vertex_mapping` for another vertex set, such as a mesh
        before its modifiers); ``normals`` (n, 3); ``view_dirs`` as above.
        """
        (j_v,) = map_to_points(idx, w, self.surface_partial_current(result))
        n = np.asarray(normals, dtype=np.float64)
        # along the normal one cosine serves every point: no Fresnel factor per render-mesh vertex
        cos_o = 1.0 if view_dirs is None else np.einsum("vj,vj->v", n, view_dirs)
        return self.split_radiance_at(result, outgoing_radiance(j_v, cos_o, self.eta), idx, w, normals, view_dirs,
                                      transported)

    def phi_bound(self, result: SolveResult, level: int = -1) -> np.ndarray:
        """The discrete maximum principle's bound on the level's phi per channel, (3,)
        (:func:`.iterative.maximum_principle_bound`): ``max 4 q / (1 - F_dr)`` of the boundary source, or
        above it where the lamps' volume source (``result.volume``) drives a cell harder."""
        from .iterative import maximum_principle_bound

        volume = None if result.volume is None else result.volume[level]
        return maximum_principle_bound(self.systems[level], self.systems[level].rhs(result.q[level], volume))

    def power_balance(self, result: SolveResult, level: int = -1, clamp: bool = True) -> dict:
        """Incoming, absorbed and outgoing power (W, per channel) on one level.

        ``in`` is the boundary source's ``sum_s a_s q_s`` plus the lamps' volume source (when the result has
        one), ``out = sum_s a_s (1 - F_dr) J+_s``.  ``absorbed`` is what the
        discrete operator removes: ``(A 1 - a_s/(2A) at surface nodes) . phi``
        (cell absorption mu V plus the absorption inside fitted surface links);
        unclamped, ``in = out + absorbed`` holds to the solver tolerance.
        """
        lv = self.bake.levels[level]
        system = self.systems[level]
        s = self.bake.mm_per_unit * 1e-3  # metres per unit, so powers are in W
        a = lv.area * s * s
        q = result.q[level]
        phi = result.phi[level]
        phi_s = phi[lv.n_inner:]
        jp = kernels.partial_current(phi_s, q, self.fdr)
        if clamp:  # what the radiance output emits (surface_partial_current)
            jp = np.maximum(jp, 0.0) * clamp_scale(phi_s, q, lv.area, self.fdr)
        p_in = a @ q
        if result.volume is not None and result.volume[level] is not None:
            p_in = p_in + np.asarray(result.volume[level]).sum(axis=0) * 1e-6  # mm^2 -> m^2
        p_out = a @ ((1.0 - self.fdr) * jp)
        p_abs = np.einsum("nc,nc->c", system.absorption_weights(), phi) * 1e-6  # mm^2 -> m^2
        out = {"in": p_in, "out": p_out, "absorbed": p_abs}
        if result.q_incident is not None and result.q_incident[level] is not None:
            # the split: in = the light that entered; single = what the closed-form term sends out
            q_in = np.asarray(result.q_incident[level])
            beam = None if result.beams is None else result.beams[level]
            s = half_space_split(self.eta).single_escapes(self.surface_albedo[level], q_in, beam)
            s = s * np.array(result.single)
            out.update(incident=a @ q_in, single=a @ (s * q_in))
        return out


def _sum_volumes(a, b):
    """The lamps' volume sources of two results added on the finest level (:meth:`SolveResult.plus_finest`)."""
    if b is None or b[-1] is None:
        return a
    if a is None or a[-1] is None:
        return b
    out = list(a)
    out[-1] = np.asarray(a[-1]) + np.asarray(b[-1])
    return out


def _sum_beams(a, b):
    """The lamps' parts of two results' entering light added on the finest level (:meth:`SolveResult.plus_finest`):
    q_beam summed, the incidence cosine and direction weighted by each one's q."""
    if a is None or a[-1] is None:
        return b
    if b is None or b[-1] is None:
        return a
    (qa, ma, da), (qb, mb, db) = a[-1], b[-1]
    q = np.asarray(qa) + np.asarray(qb)
    wa, wb = np.asarray(qa).mean(axis=1), np.asarray(qb).mean(axis=1)
    out = list(a)
    out[-1] = (q, weighted_cosine(wa * ma + wb * mb, wa + wb),
               weighted_direction(wa[:, None] * np.asarray(da) + wb[:, None] * np.asarray(db)))
    return out
