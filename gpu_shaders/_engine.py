"""The engine, imported the way this copy of ``gpu_shaders`` was loaded.

Inside the installed extension this package is ``translucency.gpu_shaders`` and
the engine is its sibling ``translucency.translucency_addon`` (relative
import).  In tests and benchmarks the repository root is on ``sys.path`` and
both are top-level packages.  Never mix the two copies' classes.
"""

try:  # installed extension: translucency.gpu_shaders -> translucency.translucency_addon
    from ..translucency_addon.quadgraph import bake, levels as quadgraph  # noqa: F401
    from ..translucency_addon.diffusion import solver as diffusion, iterative, kernels, spectral  # noqa: F401
    from ..translucency_addon import errors  # noqa: F401
    from ..translucency_addon.scene import fresnel  # noqa: F401
    from ..translucency_addon.fluid import solver as fluid  # noqa: F401
except ImportError:  # top-level package (repo root on sys.path)
    from translucency_addon.quadgraph import bake, levels as quadgraph  # noqa: F401
    from translucency_addon.diffusion import solver as diffusion, iterative, kernels, spectral  # noqa: F401
    from translucency_addon import errors  # noqa: F401
    from translucency_addon.scene import fresnel  # noqa: F401
    from translucency_addon.fluid import solver as fluid  # noqa: F401
