# SPDX-License-Identifier: GPL-3.0-or-later
"""Write the small procedural HDRI the tests and the demo use: ``tests/data/sun_sky_cc0.exr``.

Generated here, not photographed, and dedicated to the public domain (CC0 1.0):
anyone may use it for anything.  It is a 1024 x 512 equirectangular map
(Cycles' convention, ``translucency_addon.scene.environment_map``), half-float
OpenEXR with ZIP compression (~ 100 KB):

* a sky above the horizon: blue, brighter towards the horizon,
  ``(0.35, 0.55, 1.0) * (0.4 + 0.6 (1 - sin el)^2)`` W/(m^2 sr);
* a ground below it: ``(0.12, 0.10, 0.08)``;
* a sun disk SUN_DIAMETER degrees across at elevation SUN_ELEVATION and azimuth
  SUN_AZIMUTH (``atan2(y, x)``), of uniform radiance chosen so that it gives
  SUN_IRRADIANCE W/m^2 on a plane facing it (1.5 degrees across rather than
  the real 0.53, so the disk covers ~ 20 pixels at this size).

    .venv/bin/python tools/make_hdri.py [out.exr]
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
OUT = ROOT / "tests" / "data" / "sun_sky_cc0.exr"
SIZE = (1024, 512)
SUN_ELEVATION = 35.0
SUN_AZIMUTH = 30.0
SUN_DIAMETER = 1.5
SUN_IRRADIANCE = 20.0  # luminance (Rec.709 Y) of the RGB irradiance, W/m^2
SUN_COLOR = np.array([1.0, 0.95, 0.85])


def sun_direction() -> np.ndarray:
    el, az = math.radians(SUN_ELEVATION), math.radians(SUN_AZIMUTH)
    return np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])


def pixels() -> np.ndarray:
    """(h, w, 3) radiance, rows bottom to top."""
    sys.path.insert(0, str(ROOT))
    from translucency_addon.scene.environment_map import equirect_directions

    w, h = SIZE
    d = equirect_directions(h, w)
    z = d[..., 2]
    sky = np.array([0.35, 0.55, 1.0]) * (0.4 + 0.6 * (1.0 - np.clip(z, 0, 1)) ** 2)[..., None]
    L = np.where((z > 0)[..., None], sky, np.array([0.12, 0.10, 0.08]))
    half = math.radians(SUN_DIAMETER / 2)
    omega = 2 * math.pi * (1 - math.cos(half))
    disk = d @ sun_direction() >= math.cos(half)
    L[disk] = SUN_IRRADIANCE / omega * SUN_COLOR / float(SUN_COLOR @ [0.2126, 0.7152, 0.0722])  # luminance E
    return L.astype(np.float32)


def write(path: Path = OUT) -> Path:
    import bpy

    w, h = SIZE
    img = bpy.data.images.new("sun_sky_cc0", w, h, float_buffer=True, alpha=False)
    rgba = np.ones((h, w, 4), np.float32)
    rgba[..., :3] = pixels()
    img.pixels.foreach_set(rgba.ravel())
    img.filepath_raw = str(path)
    img.file_format = 'OPEN_EXR'
    scene = bpy.context.scene
    s = scene.render.image_settings
    s.file_format = 'OPEN_EXR'
    s.color_depth = '16'
    s.exr_codec = 'ZIP'
    s.color_mode = 'RGB'
    path.parent.mkdir(parents=True, exist_ok=True)
    img.save_render(str(path), scene=scene)
    bpy.data.images.remove(img)
    return path


if __name__ == "__main__":
    p = write(Path(sys.argv[1]) if len(sys.argv) > 1 else OUT)
    print(f"wrote {p} ({p.stat().st_size / 1024:.0f} KB)")
