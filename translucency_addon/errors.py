"""Exceptions raised by the engine.

Every error a user can cause (bad mesh, bad material, bad cache, no GPU) is a
``TranslucencyError`` whose message names the problem, so the Blender side can
show it in the status bar and the Info log without a traceback.
"""


class TranslucencyError(Exception):
    """Base class: a problem the user can act on."""


class MeshError(TranslucencyError):
    """The input mesh cannot be baked (NaN, too few vertices, no volume, too large)."""


class ParticleError(TranslucencyError):
    """A particle set cannot become Voronoi-fluid cells (bad radius, all in a plane, too many, broken data)."""


class RadiusError(ParticleError):
    """The particle radius does not fit the particles: larger than the whole fluid, or many times their spacing.

    ``kind`` ("fluid" or "spacing"), ``radius``, ``spacing`` and ``extent`` (object units) let a caller say it
    in its own units and name its own setting: :meth:`describe`.  The plain message is in object units."""

    def __init__(self, kind: str, radius: float, spacing: float, extent: float):
        self.kind, self.radius, self.spacing, self.extent = kind, float(radius), float(spacing), float(extent)
        super().__init__(self.describe())

    def describe(self, length=lambda x: f"{x:.4g} object units",
                 advice: str = "use a radius near the particle spacing, {spacing}") -> str:
        """The message with lengths formatted by ``length`` and one suggestion: ``advice``, in which
        ``{spacing}`` is the spacing formatted by ``length`` and ``{value}`` the bare number."""
        R, s = self.radius, self.spacing
        if self.kind == "fluid":
            problem = (f"the particle radius {length(R)} is larger than the whole fluid (its particles span "
                       f"{length(self.extent)}): the radius is one particle's size")
        else:
            problem = (f"the particle radius {length(R)} is {R / s:.0f} times the particle spacing ({length(s)}): "
                       f"every cell would have ~{int(4.19 * (2 * R / s) ** 3):,} neighbours")
        return f"{problem}; {advice.format(spacing=length(s), value=f'{s:.4g}')}"


class MaterialError(TranslucencyError):
    """Optical coefficients are missing, NaN, negative or absurd."""


class LightError(TranslucencyError):
    """A light description is invalid."""


class CacheError(TranslucencyError):
    """A bake cache is missing, corrupt, truncated, stale or of another version."""


class InputError(TranslucencyError):
    """A command-line argument or file is out of range, missing, unreadable or of the wrong kind."""


class BakeCancelled(TranslucencyError):
    """The user cancelled a bake; nothing was written."""


class GPUUnavailable(TranslucencyError):
    """No GPU context could be had; callers fall back to the CPU solver."""


class GraphTooLarge(TranslucencyError):
    """The QuadGraph does not fit the GPU's texture limits."""


class DeformationError(TranslucencyError):
    """A pose the baked graph cannot follow: vertex count changed, NaN vertices, a collapsed object."""


class GraphFolded(DeformationError):
    """A deformation inverts tetrahedra or links of the baked graph, or stretches a link too far.

    ``report`` is the :class:`~.deformation.DeformationReport` of the refused pose.
    """

    def __init__(self, message: str, report=None):
        super().__init__(message)
        self.report = report
