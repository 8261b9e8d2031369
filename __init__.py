# SPDX-License-Identifier: GPL-3.0-or-later
"""Translucency: real-time heterogeneous subsurface scattering for Blender.

The extension has three parts:

* ``translucency_addon`` -- the bpy-free engine (QuadGraph bake, diffusion and
  single-scattering solvers, planner, cache I/O, command line);
* ``ops`` -- Blender operators, panels, property groups and handlers;
* ``gpu_shaders`` -- GLSL compute kernels and the thin dispatch layer that runs
  them through Blender's ``gpu`` module.

Registration never touches the ``gpu`` module and never imports the bundled
wheels at module level: if a wheel is missing, the add-on still registers and
its panel says which dependency is missing.
"""

from . import ops


def register():
    ops.register()


def unregister():
    ops.unregister()
