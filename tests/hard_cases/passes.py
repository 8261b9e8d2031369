# SPDX-License-Identifier: GPL-3.0-or-later
"""Hard cases for the passes beyond the QuadGraph diffusion solve (issue 35): one small contract.

``cases.py`` holds the diffusion solve's cases.  Every other pass (particle fluids, the cavity
exchange, the Voxel Number Map, deformed graphs, the first-scatter split and its half-space tables)
has a module ``passes_<pass>.py`` beside this one that defines ``CASES``: a list of
:class:`PassCase`.  ``test_pass_cases.py`` runs every case as a test, and ``bench/stability.py
--passes`` writes one row per case into docs/stability.md, from the same :func:`evaluate`.

A case either must solve -- its ``run`` returns an :class:`Outcome` whose :class:`Bound` s all
hold (radiance finite and >= 0, out <= in power where the pass conserves energy, GPU = CPU where
both exist, continuity, ...) -- or must be refused: ``refusal`` is a regular expression the
``TranslucencyError`` the pass raises must match (a refusal by name, with its numbers).
"""

from __future__ import annotations

import importlib
import pkgutil
import re
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np


@dataclass(frozen=True)
class Bound:
    """One bound a case must keep: ``value <= limit`` (``name`` says what, e.g. ``"out / in power"``)."""

    name: str
    value: float
    limit: float

    @property
    def ok(self) -> bool:
        return bool(np.isfinite(self.value) and self.value <= self.limit)

    def describe(self) -> str:
        return f"{self.name} {self.value:.3g} (<= {self.limit:.3g})"


@dataclass
class Outcome:
    """What a run measured: its bounds and a short note for the table (sizes, sweeps, seconds)."""

    bounds: list[Bound]
    note: str = ""


@dataclass(frozen=True)
class PassCase:
    """A named hard case of one pass.

    ``run``: builds the input and runs the pass; returns an :class:`Outcome` (must solve), or raises
    the pass's ``TranslucencyError`` (must be refused when ``refusal`` is set: its message must match
    the regular expression ``refusal``).
    """

    name: str
    pass_name: str
    run: Callable[[], Outcome]
    refusal: str | None = None
    slow: bool = False


@dataclass
class Row:
    case: str
    pass_name: str
    status: str  # "pass" or "FAIL"
    result: str  # "solved" or "refused"
    detail: str
    seconds: float = 0.0
    problems: list[str] = field(default_factory=list)


def finite_nonnegative(name: str, L) -> list[Bound]:
    """Two bounds on a radiance array: the count of NaN/Inf values and the most negative value (<= 0)."""
    L = np.asarray(L, dtype=np.float64)
    bad = float(np.count_nonzero(~np.isfinite(L)))
    neg = float(-np.min(L[np.isfinite(L)], initial=0.0))
    return [Bound(f"{name}: NaN/Inf values", bad, 0.0), Bound(f"{name}: -min", max(neg, 0.0), 0.0)]


def evaluate(case: PassCase) -> Row:
    """Run ``case`` and judge it: a solve keeps every bound; a refusal matches ``case.refusal``."""
    from translucency_addon.errors import TranslucencyError

    t0 = time.perf_counter()
    try:
        outcome = case.run()
    except TranslucencyError as ex:
        text = f"{type(ex).__name__}: {ex}"
        seconds = time.perf_counter() - t0
        if case.refusal is not None and re.search(case.refusal, str(ex)):
            return Row(case.name, case.pass_name, "pass", "refused", text, seconds)
        why = "refused, but the message does not match " + repr(case.refusal) if case.refusal else "refused"
        return Row(case.name, case.pass_name, "FAIL", "refused", text, seconds, [f"{why}: {text}"])
    except Exception as ex:  # noqa: BLE001 - a crash is a failed row, not a crashed bench
        return Row(case.name, case.pass_name, "FAIL", "crashed", f"{type(ex).__name__}: {ex}",
                   time.perf_counter() - t0, [f"crashed: {type(ex).__name__}: {ex}"])
    seconds = time.perf_counter() - t0
    if case.refusal is not None:
        return Row(case.name, case.pass_name, "FAIL", "solved", outcome.note, seconds,
                   [f"accepted, but must be refused ({case.refusal!r})"])
    broken = [b.describe() for b in outcome.bounds if not b.ok]
    detail = "; ".join([b.describe() for b in outcome.bounds if b.ok][:4] + ([outcome.note] if outcome.note else []))
    return Row(case.name, case.pass_name, "FAIL" if broken else "pass", "solved",
               "; ".join(broken) if broken else detail, seconds, ["bound broken: " + s for s in broken])


def all_cases() -> list[PassCase]:
    """Every ``CASES`` of every ``passes_*.py`` module beside this one, in module order."""
    here = Path(__file__).resolve().parent
    out: list[PassCase] = []
    for info in sorted(pkgutil.iter_modules([str(here)]), key=lambda m: m.name):
        if info.name.startswith("passes_"):
            module = importlib.import_module(f"{__package__}.{info.name}" if __package__ else info.name)
            out += list(module.CASES)
    names = [c.name for c in out]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise ValueError(f"hard-case names must be unique: {dup}")
    return out
