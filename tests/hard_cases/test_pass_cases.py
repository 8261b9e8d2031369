# SPDX-License-Identifier: GPL-3.0-or-later
"""Every pass's hard cases (``passes_*.py``, contract in ``passes.py``): each keeps its bounds or is refused by
name; the same :func:`passes.evaluate` writes docs/stability.md's pass rows (``bench/stability.py --passes``)."""

from __future__ import annotations

import pytest

from . import passes

CASES = passes.all_cases()


@pytest.mark.parametrize("case", [pytest.param(c, id=c.name, marks=[pytest.mark.slow] if c.slow else [])
                                  for c in CASES])
def test_pass_case(case):
    row = passes.evaluate(case)
    print(f"{row.case:40s} {row.result:8s} {row.detail} ({row.seconds:.1f} s)")
    assert row.status == "pass", "\n".join(row.problems)


def test_every_pass_has_cases():
    have = {c.pass_name for c in CASES}
    for name in ("fluid", "cavity", "voxel_number_map", "deformation", "split"):
        assert name in have, f"no hard case for the {name} pass"


def test_a_broken_bound_fails_the_case():
    """The judge itself: a bound above its limit, a NaN, a wrong refusal and a missing refusal all fail."""
    from translucency_addon.errors import MeshError

    ok = passes.PassCase("t/ok", "t", lambda: passes.Outcome([passes.Bound("x", 0.5, 1.0)]))
    over = passes.PassCase("t/over", "t", lambda: passes.Outcome([passes.Bound("x", 1.5, 1.0)]))
    nan = passes.PassCase("t/nan", "t", lambda: passes.Outcome(passes.finite_nonnegative("L", [1.0, float("nan")])))
    neg = passes.PassCase("t/neg", "t", lambda: passes.Outcome(passes.finite_nonnegative("L", [1.0, -1e-3])))

    def refuse():
        raise MeshError("the part 'Stone' is open: 2 holes")

    right = passes.PassCase("t/right", "t", refuse, refusal=r"'Stone' is open: 2 holes")
    wrong = passes.PassCase("t/wrong", "t", refuse, refusal=r"'Knot'")
    missing = passes.PassCase("t/missing", "t", ok.run, refusal=r"anything")
    assert [passes.evaluate(c).status for c in (ok, over, nan, neg, right, wrong, missing)] == \
        ["pass", "FAIL", "FAIL", "FAIL", "pass", "FAIL", "FAIL"]
