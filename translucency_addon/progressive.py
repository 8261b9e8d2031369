"""Progressive frames: a frame's diffusion solved in time slices, the solution so far shown in between.

The viewport must never wait for a solve.  :class:`ProgressiveSolve` holds one frame's solve as the
generator :func:`.frame.diffuse_steps` (the same light pass, split, levels, bounce and checks as a
blocking frame) and runs it for a time budget at a time (:meth:`ProgressiveSolve.advance`): each slice
ends at the first Chebyshev sweep past the budget and hands back the solution so far -- the finest
level's iterate, or, while the coarser levels are still being solved, the latest of them carried up by
eq. 10's Shepard transfer -- and, at the end, the converged result, the same arithmetic as an
uninterrupted solve.  The
add-on runs a slice per redraw (``ops.live``); renders never use it, so a rendered frame is always the
converged one.

The first slice pays for the frame's light pass (the shadow rays, the split), which is not sliced, and
ends at the first image: the solve's start -- the last frame's solution (a warm start) or the coarser
level's answer carried up, with this frame's light at the surface -- before the iteration's own set-up
(the bounce's block system at Final: its fp64 true residual, ~0.1 s), so a light move shows within about
the light pass's time.  Every other slice makes at least one sweep (a level's start never ends it), so any
budget converges.  Showing an image costs
too (the iterate gathered from the sweeps' layout and carried to the vertices, the attribute written,
the redraw: 20-40 ms at Final quality, about one sweep): a slice runs at least
:data:`SLICE_OVER_DISPLAY` times as long as that cost of the last one, up to :data:`MAX_SLICE`, so about
four fifths of the time goes to the solve (``bench/progressive.py`` measures what a frame then takes
against the blocking one).
"""

from __future__ import annotations

import time

MAX_SLICE = 0.25  # seconds: a slice never grows past this for the time spent outside it (4 redraws a second)
SLICE_OVER_DISPLAY = 4.0  # a slice runs at least this many times as long as showing the last image took


class ProgressiveSolve:
    """One frame's diffusion (:func:`.frame.diffuse_steps`), run a time budget at a time.

    ``key``: what the solve is for (the caller's signature of its inputs): a caller continues the solve
    only while its key is the frame's (:meth:`continues`), and otherwise starts anew, warm-started from
    :attr:`latest` (the solution so far is closer to the new answer than the last converged one).
    ``show_start``: the first slice ends at the first image (the module docstring); a caller that starts
    anew from an unfinished solve's :attr:`latest` (a light being dragged) passes False, so that every
    redraw of the drag also advances the solve instead of showing the same start again.
    """

    def __init__(self, steps, key, show_start: bool = True):
        self._steps = steps
        self.key = key
        self.show_start = show_start  # the first slice ends at the first image (the solve's start)
        self.latest = None  # the last solution so far handed out (a SolveResult), None before the first
        self.final = None  # diffuse()'s (result, bounce, cavity_exchange) once converged
        self.slices = 0
        self.seconds = 0.0  # time spent in slices so far
        self._ended = None  # when the last slice ended (the time outside it: showing its image)
        self._handout = 0.0  # what the last slice's solution so far cost to hand out

    def continues(self, key) -> bool:
        return self.final is None and key == self.key

    @property
    def done(self) -> bool:
        return self.final is not None

    def advance(self, budget_s: float) -> tuple:
        """Run for about ``budget_s`` seconds (or :data:`SLICE_OVER_DISPLAY` times what showing the last
        image took, up to :data:`MAX_SLICE`, when that is longer); returns ``(solution so far, False)`` or
        ``(diffuse()'s result tuple, True)`` when the solve has converged."""
        t0 = time.perf_counter()
        if self._ended is not None:  # showing the last image: handing it out here, and the caller's part
            budget_s = max(budget_s, min(SLICE_OVER_DISPLAY * (self._handout + t0 - self._ended), MAX_SLICE))
        self.slices += 1
        first = self.show_start and self.slices == 1
        current = None
        try:
            while True:
                current = next(self._steps)
                if getattr(current, "is_start", False):  # a level's start: an image only for a first slice
                    if first:
                        break
                    continue
                if time.perf_counter() - t0 >= budget_s:
                    break
        except StopIteration as stop:
            self.final = stop.value
            self.seconds += time.perf_counter() - t0
            return self.final, True
        t1 = time.perf_counter()
        self.latest = current()
        self._ended = time.perf_counter()
        self._handout = self._ended - t1
        self.seconds += self._ended - t0
        return self.latest, False
