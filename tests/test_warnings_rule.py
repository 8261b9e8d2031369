"""pytest.ini's rule: a numpy RuntimeWarning raised from the engine's own code is an error.

numpy attributes a floating-point warning to the Python frame that called it, so the
rule's module regex has to match the engine's module names as both import paths give
them; warnings from other modules are left as they are.
"""

from __future__ import annotations

import numpy as np
import pytest


def _divide_in(module: str):
    code = compile("np.ones(1) / np.zeros(1)", f"<{module}>", "eval")
    return eval(code, {"__name__": module, "np": np})  # noqa: S307 -- a fixed expression


@pytest.mark.parametrize("module", ["translucency_addon.inner_parts.cavity", "translucency.translucency_addon.inner_parts.cavity",
                                    "translucency_addon"])
def test_numpy_warnings_from_the_engine_are_errors(module):
    with pytest.raises(RuntimeWarning, match="divide by zero"):
        _divide_in(module)


@pytest.mark.parametrize("module", ["some_other_module", "translucency_addon_extra", "translucency.ops.frame"])
def test_other_modules_keep_their_warnings(module):
    with pytest.warns(RuntimeWarning, match="divide by zero"):
        _divide_in(module)
