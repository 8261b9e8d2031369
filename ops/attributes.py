# SPDX-License-Identifier: GPL-3.0-or-later
"""Where results go on the mesh: the radiance attributes the overlay, the AOV and renders read.

* :data:`ATTRIBUTE_NAME` = ``"translucency_radiance"``: a ``FLOAT_COLOR``
  attribute on the ``POINT`` domain of the object's **original** mesh
  (``obj.data``), RGB = outgoing radiance in W/(m^2 sr), alpha = 1; modifiers
  carry it to the evaluated mesh.
* :data:`SS_ATTRIBUTE_NAME` = ``"translucency_radiance_ss"``: single
  scattering alone, when the object's "Split Pass" is on.

The only place these names are spelled; ``overlay`` and ``render_pass`` import them.
"""

from __future__ import annotations

import numpy as np

from .state import COUNTERS, OWN_WRITES

ATTRIBUTE_NAME = "translucency_radiance"
SS_ATTRIBUTE_NAME = "translucency_radiance_ss"
ATTRIBUTE_DOMAIN = 'POINT'
ATTRIBUTE_TYPE = 'FLOAT_COLOR'


def write_radiance(obj, rgb: np.ndarray, name: str = ATTRIBUTE_NAME) -> None:
    """Write (n, 3) radiance into ``obj.data``'s ``translucency_radiance`` attribute.

    Only the attribute's values change: never the topology, never another
    attribute.  A layer of the wrong type or domain under our name is replaced.
    """
    mesh = obj.data
    n = len(mesh.vertices)
    rgb = np.asarray(rgb, dtype=np.float32)
    if rgb.shape != (n, 3):
        raise ValueError(f"radiance has shape {rgb.shape}, the mesh has {n} vertices")
    attr = mesh.attributes.get(name)
    if attr is not None and (attr.domain != ATTRIBUTE_DOMAIN or attr.data_type != ATTRIBUTE_TYPE):
        mesh.attributes.remove(attr)
        attr = None
    if attr is None:
        attr = mesh.attributes.new(name, ATTRIBUTE_TYPE, ATTRIBUTE_DOMAIN)
    rgba = np.ones((n, 4), dtype=np.float32)
    rgba[:, :3] = np.nan_to_num(rgb, nan=0.0, posinf=0.0, neginf=0.0)
    attr.data.foreach_set("color", rgba.ravel())
    OWN_WRITES.add(obj.name)
    COUNTERS["writes"] += 1
    mesh.update_tag()


def read_radiance(obj, name: str = ATTRIBUTE_NAME) -> np.ndarray | None:
    """The attribute (default: the total radiance) as (n, 3) float32, or None."""
    mesh = obj.data
    attr = mesh.attributes.get(name) if mesh is not None else None
    if attr is None or attr.domain != ATTRIBUTE_DOMAIN or attr.data_type != ATTRIBUTE_TYPE:
        return None
    rgba = np.empty(len(attr.data) * 4, dtype=np.float32)
    attr.data.foreach_get("color", rgba)
    return rgba.reshape(-1, 4)[:, :3].copy()


def remove_attribute(obj, name: str = ATTRIBUTE_NAME) -> bool:
    mesh = obj.data
    attr = mesh.attributes.get(name) if mesh is not None else None
    if attr is None:
        return False
    mesh.attributes.remove(attr)
    mesh.update_tag()
    return True


def attribute_ok(obj, name: str = ATTRIBUTE_NAME) -> bool:
    attr = obj.data.attributes.get(name)
    return (attr is not None and attr.domain == ATTRIBUTE_DOMAIN and attr.data_type == ATTRIBUTE_TYPE
            and len(attr.data) == len(obj.data.vertices))
