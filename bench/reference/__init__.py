# SPDX-License-Identifier: GPL-3.0-or-later
"""Independent reference renderer for matched scenes (``docs/reference.md``).

* :mod:`.scene`       ``RefScene``, ``Camera``, ``sphere_env``, ``mesh_sun`` (no Mitsuba, no bpy)
* :mod:`.mitsuba_ref` ``render_reference(scene) -> RefResult`` (Mitsuba 3 volumetric path tracer)
* :mod:`.raster`      ``rasterize(V, F, values, camera, resolution)``: our per-vertex result as an image
* :mod:`.metrics`     ``relative_rms``, ``scanline``
* :mod:`.cycles_ref`  one-time cross-check of the reference against Cycles (a script)

Run the validation: ``python -m bench.reference.validate --help``.
"""
