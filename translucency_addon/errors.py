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


class MaterialError(TranslucencyError):
    """Optical coefficients are missing, NaN, negative or absurd."""


class LightError(TranslucencyError):
    """A light description is invalid."""


class CacheError(TranslucencyError):
    """A bake cache is missing, corrupt, truncated, stale or of another version."""


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
