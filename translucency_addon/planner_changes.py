"""Change tracking for the planner: a frame re-solves only what changed since the last one.

Diffusion depends on the lights that reach the object, its material/field
and its geometry (and its plan); single scattering also on the camera.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass

import numpy as np

from .scene.lights import Light


def fingerprint(*parts) -> str:
    """Stable hash of numbers, arrays and strings (for change tracking)."""
    h = hashlib.sha1()
    for p in parts:
        if isinstance(p, np.ndarray):
            h.update(np.ascontiguousarray(p).tobytes())
        elif isinstance(p, (list, tuple)):
            h.update(fingerprint(*p).encode())
        else:
            h.update(repr(p).encode())
    return h.hexdigest()


@dataclass
class ObjectState:
    """What one object's solution depends on, as fingerprints."""

    material: str
    geometry: str
    lights: dict  # light name -> fingerprint, only the lights that reach it
    camera: str
    plan: str = ""


@dataclass
class FrameWork:
    """What a frame must recompute for one object."""

    multiple: bool
    single: bool
    reasons: list


class ChangeTracker:
    """Re-solve only what changed since the last frame.

    ``update(name, state)`` returns a :class:`FrameWork`: diffusion re-solves
    when the material/field, the geometry, the plan or any light that reaches
    the object changed (including a light starting or stopping to reach it);
    single scattering additionally when the camera moved.  Unchanged objects do
    no work.
    """

    def __init__(self):
        self.states: dict[str, ObjectState] = {}
        self.solves = {"multiple": 0, "single": 0}

    def update(self, name: str, state: ObjectState) -> FrameWork:
        old = self.states.get(name)
        self.states[name] = state
        if old is None:
            work = FrameWork(True, True, ["first frame"])
        else:
            why = []
            if old.material != state.material:
                why.append("material changed")
            if old.geometry != state.geometry:
                why.append("geometry changed")
            if old.plan != state.plan:
                why.append("passes changed")
            if old.lights != state.lights:
                moved = sorted(set(old.lights.items()) ^ set(state.lights.items()))
                why.append("lights changed: " + ", ".join(sorted({k for k, _ in moved})))
            ms = bool(why)
            camera = old.camera != state.camera
            work = FrameWork(ms, ms or camera, why + (["camera moved"] if camera else []))
        self.solves["multiple"] += int(work.multiple)
        self.solves["single"] += int(work.single)
        return work

    def forget(self, name: str) -> None:
        self.states.pop(name, None)


def light_fingerprint(light: Light) -> str:
    return fingerprint(light.kind, light.color, light.intensity, light.irradiance, light.position, light.direction,
                       light.spot_size, light.spot_blend)
