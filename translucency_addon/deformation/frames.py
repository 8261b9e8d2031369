"""Solving a deformed bake frame after frame (Wang et al. 2010 sec. 6.4): the Blender side's entry point.

:class:`DeformationFrames` keeps, per deforming object, the :class:`~.deformation.DeformationRig`
and the last valid frame: pose -> deformed graph -> the one :class:`~.diffusion.DiffusionSolver`
on it (:func:`pose_solver`), warm-started from the previous frame's solution and spectral
bounds -> radiance at the posed vertices.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from ..quadgraph.bake import Bake
from .pose import STRETCH_LIMIT, DeformationReport, DeformationRig, DeformedPose
from ..errors import DeformationError, GraphFolded


def carry_spectral_bounds(previous_systems, solver) -> None:
    """Start each level's Chebyshev interval from the previous frame's (same bake, other pose).

    The upper end is Gershgorin's bound of the new system (cheap and guaranteed); the lower
    end is the previous frame's Lanczos estimate, so a frame runs no Lanczos.  A pose that
    lowers the true bottom of the spectrum leaves modes below the interval, which Chebyshev
    still damps (its polynomial stays below 1 there), only more slowly: this changes speed,
    never stability, and the solution checks of :mod:`.iterative` stay in force.
    """
    from ..diffusion.spectral import gershgorin_upper

    for old, new in zip(previous_systems, solver.systems):
        if old.lam_min is not None and new.lam_max is None and old.scheme == new.scheme:
            new.lam_max = gershgorin_upper(new)
            new.lam_min = np.minimum(old.lam_min, 0.5 * new.lam_max)


def pose_solver(pose: DeformedPose, material, field_values=None, options=None, previous=None, make_solver=None):
    """The one :class:`~.diffusion.DiffusionSolver`, on the deformed bake.

    ``field_values``: the heterogeneity field per level sampled at the **rest** positions
    (the material stays attached to the rest pose, sec. 6.4).  ``previous``: the last
    frame's solver on the same bake (rest or deformed) lends its spectral bounds
    (:func:`carry_spectral_bounds`); a solver that ``rebinds_poses`` (the GPU's: its graph
    textures stay, only the coefficients travel) is that solver moved to the pose.
    ``make_solver(bake, material, field_values, options)`` makes a new one (default: the CPU's).
    """
    if previous is not None and getattr(previous, "rebinds_poses", False):
        before = list(previous.systems)
        previous.rebind(pose.bake)
        carry_spectral_bounds(before, previous)
        return previous
    if make_solver is None:
        from ..diffusion.solver import DiffusionSolver as make_solver
    solver = make_solver(pose.bake, material, field_values, options)
    if previous is not None:
        carry_spectral_bounds(previous.systems, solver)
    return solver


@dataclass
class FrameOutcome:
    """One solved pose: radiance at the posed mesh's vertices and what produced it."""

    radiance: np.ndarray  # (n_vertices, 3) W/(m^2 sr), toward view_dirs (default: along the posed normals)
    result: object  # diffusion.SolveResult (the warm start of the next frame)
    pose: DeformedPose
    solver: object  # the DiffusionSolver of this pose
    seconds: dict

    @property
    def report(self) -> DeformationReport:
        return self.pose.report


class DeformationFrames:
    """One deforming object frame after frame: pose -> deformed graph -> warm-started solve -> radiance.

    Typical use (the Blender side keeps one per baked object)::

        frames = DeformationFrames(bake, material, field_values)   # field at the rest positions
        out = frames.solve(V_posed, lights, environment, frame=37)  # raises on a bad or folding pose
        out.radiance, out.report.worst_stretch

    A pose that cannot be solved raises (:class:`DeformationError`, :class:`GraphFolded`)
    and changes nothing: :attr:`last` still holds the last valid frame, to show instead.
    """

    def __init__(self, bake: Bake, material, field_values=None, options=None, *, rig: DeformationRig | None = None,
                 stretch_limit: float = STRETCH_LIMIT, make_solver=None):
        self.rig = rig if rig is not None else DeformationRig(bake, stretch_limit)
        self.make_solver = make_solver  # (bake, material, field_values, options) -> solver; None: the CPU's
        self.material = material
        self.field_values = field_values
        self.options = options
        self.last: FrameOutcome | None = None

    def solve(self, V, lights=(), environment=None, *, frame=None, view_dirs=None, interreflect: bool = True,
              **solve_kw) -> FrameOutcome:
        """Deform to ``V``, solve warm-started from the last valid frame, return its radiance."""
        t0 = time.perf_counter()
        try:
            pose = self.rig.deform(V)
        except GraphFolded as exc:
            raise GraphFolded(exc.report.describe(frame), exc.report) from None
        except DeformationError as exc:
            raise DeformationError(f"frame {frame}: {exc}" if frame is not None else str(exc)) from None
        t1 = time.perf_counter()
        last = self.last
        solver = pose_solver(pose, self.material, self.field_values, self.options,
                             previous=None if last is None else last.solver, make_solver=self.make_solver)
        t2 = time.perf_counter()
        warm = None if last is None else last.result
        if interreflect:
            result, _ = solver.solve_interreflected(lights, environment, warm_start=warm, **solve_kw)
        else:
            result = solver.solve(lights, environment, warm_start=warm, **solve_kw)
        L = solver.vertex_radiance(result, view_dirs)
        t3 = time.perf_counter()
        out = FrameOutcome(radiance=L, result=result, pose=pose, solver=solver,
                           seconds={"deform": t1 - t0, "assemble": t2 - t1, "solve": t3 - t2, "total": t3 - t0})
        self.last = out
        return out
