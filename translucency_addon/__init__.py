"""The Translucency engine: bpy-free QuadGraph diffusion and single scattering.

Importable without Blender (numpy, scipy, pytetwild, fast_simplification).
See ``docs/architecture.md`` for the module map and unit conventions, and
``python -m translucency_addon --help`` for the command line.
"""

__version__ = "0.1.0"
