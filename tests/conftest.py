# SPDX-License-Identifier: GPL-3.0-or-later
"""Test harness: bpy from PyPI (Blender in background mode, like ``blender -b``).

* A temporary Blender user directory (``BLENDER_USER_RESOURCES``) is set up
  *before* ``import bpy`` so tests never touch a real profile.
* The repo root is importable two ways:
  - as the package ``translucency`` (the extension, like Blender loads it), so
    ``translucency.ops`` and ``translucency.translucency_addon`` resolve;
  - on ``sys.path``, so engine tests can ``import translucency_addon``.
  Note these are two separate module trees: ``translucency_addon.errors.MeshError``
  is not ``translucency.translucency_addon.errors.MeshError``.  Tests that go
  through ``ops`` should import engine names from ``translucency.translucency_addon``.
* Fixtures: ``addon`` (the loaded package), ``blender`` (factory reset around
  the test, add-on registered from the working tree for its duration) and the
  session fixture ``gpu_context``.  Tests marked ``gpu`` get ``gpu_context``
  automatically and FAIL (never skip) when the GPU backend cannot start.
"""

from __future__ import annotations

import atexit
import importlib.util
import os
import shutil
import sys
import tempfile
from pathlib import Path
from types import SimpleNamespace

import pytest

ROOT = Path(__file__).resolve().parent.parent
PACKAGE = "translucency"

# --- Blender user directories, before bpy is imported --------------------------------

_INSIDE_BLENDER = "bpy" in sys.modules  # `blender -b --python tests/run_blender.py`
if not _INSIDE_BLENDER and not os.environ.get("TRANSLUCENCY_KEEP_USER_RESOURCES"):
    _USER_DIR = tempfile.mkdtemp(prefix="translucency-blender-user-")
    os.environ["BLENDER_USER_RESOURCES"] = _USER_DIR
    # BLENDER_USER_RESOURCES covers config, scripts, datafiles and extensions;
    # the specific variables are set too in case one is already set in the shell.
    for _sub, _var in (("config", "BLENDER_USER_CONFIG"), ("scripts", "BLENDER_USER_SCRIPTS"),
                       ("datafiles", "BLENDER_USER_DATAFILES"), ("extensions", "BLENDER_USER_EXTENSIONS")):
        os.environ[_var] = os.path.join(_USER_DIR, _sub)
    atexit.register(shutil.rmtree, _USER_DIR, ignore_errors=True)

if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

import bpy  # noqa: E402  (must come after the environment above)


def load_addon():
    """Import the repo root as the package ``translucency`` (once per process)."""
    module = sys.modules.get(PACKAGE)
    if module is not None:
        return module
    spec = importlib.util.spec_from_file_location(
        PACKAGE, ROOT / "__init__.py", submodule_search_locations=[str(ROOT)])
    module = importlib.util.module_from_spec(spec)
    sys.modules[PACKAGE] = module
    try:
        spec.loader.exec_module(module)
    except BaseException:
        del sys.modules[PACKAGE]
        raise
    return module


def addon_is_registered(addon) -> bool:
    return any(getattr(cls, "is_registered", False) for cls in _addon_classes(addon))


def _addon_classes(addon):
    for module in addon.ops.MODULES:
        yield from module.CLASSES


def factory_reset() -> None:
    bpy.ops.wm.read_factory_settings(use_empty=True)


# --- markers ---------------------------------------------------------------------------

class _RootIsAFolder:
    """Collect the repository root as a plain folder, not as a package.

    The root is the extension's package (its ``__init__.py`` is the add-on), so pytest would make it
    a ``Package`` and import that ``__init__.py`` under the checkout folder's name: a clone in a
    folder whose name is no Python identifier (``translucency-main``, ``my-clone``) then failed
    every test with "attempted relative import with no known parent package".  The tests load the
    add-on themselves (:func:`load_addon`).  Registered as a plugin, not a conftest hook: a
    conftest's hooks do not apply to collecting the folder above it.
    """

    @staticmethod
    def pytest_collect_directory(path, parent):
        if Path(path) == ROOT:
            return pytest.Dir.from_parent(parent, path=Path(path))
        return None


def pytest_configure(config):
    # Also declared in pytest.ini; repeated so `blender -b --python tests/run_blender.py`
    # works from any directory.
    config.addinivalue_line("markers", "gpu: needs Blender's GPU backend (llvmpipe here); fails, never skips")
    config.addinivalue_line("markers", "slow: takes more than a minute")
    if not config.pluginmanager.has_plugin("translucency-root-is-a-folder"):
        config.pluginmanager.register(_RootIsAFolder(), "translucency-root-is-a-folder")


def pytest_collection_modifyitems(config, items):
    for item in items:
        if item.get_closest_marker("gpu") is not None and "gpu_context" not in item.fixturenames:
            item.fixturenames.append("gpu_context")


@pytest.hookimpl(tryfirst=True)
def pytest_runtest_call(item):
    # A test that needs the GPU fails (in its call phase, so it is reported as
    # FAILED, not ERROR or SKIPPED) when the backend did not start.
    context = getattr(item, "funcargs", {}).get("gpu_context")
    if context is not None and context.error:
        pytest.fail(f"GPU backend could not be initialised: {context.error}", pytrace=False)


# --- fixtures --------------------------------------------------------------------------

@pytest.fixture(scope="session")
def addon():
    """The extension package loaded from the working tree (``translucency``)."""
    return load_addon()


@pytest.fixture
def blender(addon):
    """Factory-reset Blender with the add-on registered for the test; yields ``bpy``."""
    if addon_is_registered(addon):  # a previous test failed half-way
        addon.unregister()
    factory_reset()
    addon.register()
    try:
        yield bpy
    finally:
        if addon_is_registered(addon):
            addon.unregister()
        factory_reset()


class GPUContext:
    """What the session fixture found: ``renderer``/``version`` or an ``error``."""

    def __init__(self):
        self.renderer = ""
        self.version = ""
        self.backend = ""
        self.error = ""

    def __repr__(self):
        return f"GPUContext(renderer={self.renderer!r}, version={self.version!r}, error={self.error!r})"


def init_gpu_backend() -> GPUContext:
    """Initialise Blender's GPU backend headless with a 1x1 Workbench render."""
    import gpu

    context = GPUContext()
    try:
        from gpu_shaders import init_headless  # the repo root is on sys.path (see above)

        init_headless()
        context.renderer = gpu.platform.renderer_get()
        context.version = gpu.platform.version_get()
        context.backend = getattr(gpu.platform, "backend_type_get", lambda: "")()
        if not context.renderer:
            context.error = "gpu.platform.renderer_get() returned an empty string"
    except Exception as ex:  # noqa: BLE001 - reported by every gpu test
        context.error = f"{type(ex).__name__}: {ex}"
    return context


@pytest.fixture(scope="session")
def gpu_context():
    """Session-wide GPU backend (llvmpipe on the CI machines).

    Returns a :class:`GPUContext`.  If initialisation failed, every test that
    uses this fixture (all tests marked ``gpu`` do) fails with its error.
    """
    return init_gpu_backend()


# --- headless panel drawing ----------------------------------------------------------
#
# Background Blender has no UI, so panels are never drawn.  ``FakeLayout`` stands
# in for ``bpy.types.UILayout``: it records what a draw function asks for and
# checks every ``prop``/``prop_search`` name against the RNA of the data it is
# given, which catches typos and properties drawn from the wrong group.

class FakeLayout:
    def __init__(self, log=None):
        self.log = [] if log is None else log
        self.active = True
        self.alert = False
        self.enabled = True
        self.use_property_split = False
        self.use_property_decorate = True

    # containers
    def _child(self, kind):
        self.log.append((kind,))
        return FakeLayout(self.log)

    def box(self):
        return self._child("box")

    def column(self, **_kw):
        return self._child("column")

    def row(self, **_kw):
        return self._child("row")

    def split(self, **_kw):
        return self._child("split")

    def grid_flow(self, **_kw):
        return self._child("grid_flow")

    def separator(self, **_kw):
        self.log.append(("separator",))

    # items
    def label(self, text="", icon='NONE', **_kw):
        self.log.append(("label", text))

    def prop(self, data, prop, **_kw):
        assert prop in data.bl_rna.properties, f"{type(data).__name__} has no property {prop!r}"
        self.log.append(("prop", prop))

    def prop_search(self, data, prop, search_data, search_prop, **_kw):
        assert prop in data.bl_rna.properties, f"{type(data).__name__} has no property {prop!r}"
        assert search_prop in search_data.bl_rna.properties, f"{type(search_data).__name__} has no {search_prop!r}"
        self.log.append(("prop", prop))

    def template_list(self, listtype, list_id, data, prop, active_data, active_prop, **_kw):
        assert hasattr(bpy.types, listtype), f"UI list {listtype} is not registered"
        assert prop in data.bl_rna.properties, f"{type(data).__name__} has no property {prop!r}"
        assert active_prop in active_data.bl_rna.properties, f"{type(active_data).__name__} has no {active_prop!r}"
        self.log.append(("list", prop))

    def operator(self, idname, **_kw):
        category, _, name = idname.partition(".")
        assert hasattr(getattr(bpy.ops, category), name), f"operator {idname} is not registered"
        self.log.append(("operator", idname))
        return SimpleNamespace()

    # queries on the log
    def labels(self):
        return [entry[1] for entry in self.log if entry[0] == "label"]

    def props(self):
        return [entry[1] for entry in self.log if entry[0] == "prop"]

    def operators(self):
        return [entry[1] for entry in self.log if entry[0] == "operator"]


def draw_context(obj=None, scene=None):
    """A minimal stand-in for ``bpy.context`` as a panel's draw() sees it."""
    return SimpleNamespace(object=obj, active_object=obj, scene=scene or bpy.context.scene)


@pytest.fixture
def ui():
    """``ui.FakeLayout()`` and ``ui.draw_context(obj)`` for calling panel draw code headless."""
    return SimpleNamespace(FakeLayout=FakeLayout, draw_context=draw_context)
