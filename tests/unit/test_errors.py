"""Every exception class OpenFusion-Z defines derives from ``OpenFusionError`` (the promise of
``openfusion.errors``): the ``openfusion`` command shows a one-line error only for that tree, so a
class outside it would end as a traceback (or, caught as a bare ``Exception``, be hidden).

The test imports every module of the package, both source roots (``shared/openfusion`` and
``services``, installed as ``openfusion.services``), and collects every subclass of
``BaseException`` whose ``__module__`` is in ``openfusion``, nested and private classes included.
A module that cannot be imported because an optional dependency is not installed (rerun-sdk,
trimesh, pyk4a, ...) is skipped by name (``-rs`` lists it); any other import error fails.
"""

from __future__ import annotations

import gc
import importlib
import pkgutil
import tomllib
from pathlib import Path
from types import ModuleType

import pytest

from openfusion.errors import OpenFusionError
from openfusion.mapping.errors import CapacityError, MapFormatError

ROOT = next(p for p in Path(__file__).resolve().parents if (p / "pyproject.toml").is_file())

#: The two source roots: ``openfusion.services`` lives in ``services/``, outside ``openfusion.__path__``,
#: so a walk of ``openfusion`` alone never reaches it.
ROOTS = ("openfusion", "openfusion.services")

#: Top-level names of optional dependencies (extras in pyproject.toml, PyYAML): a module that needs
#: one at import time is skipped when it is missing. Any other import error is a failure.
OPTIONAL_DEPENDENCIES = frozenset({"rerun", "trimesh", "pyk4a", "pyrealsense2", "transformers", "onnx", "yaml"})


def _module_names() -> list[str]:
    """Every module and package under :data:`ROOTS`, except ``__main__`` modules (importing one
    runs the command, and they define nothing)."""
    names: set[str] = set()
    for root in ROOTS:
        package = importlib.import_module(root)
        names.add(root)
        # onerror: a package that failed to import is still listed, so its import test reports why.
        for info in pkgutil.walk_packages(package.__path__, f"{root}.", onerror=names.add):
            if info.name.rpartition(".")[2] != "__main__":
                names.add(info.name)
    return sorted(names)


MODULES = _module_names()


def _import(name: str) -> tuple[ModuleType | None, str | None]:
    """(the module, None), or (None, why it is skipped) when an optional dependency is missing."""
    try:
        return importlib.import_module(name), None
    except ImportError as exc:
        missing = (exc.name or "").partition(".")[0]
        if missing in OPTIONAL_DEPENDENCIES:
            return None, f"{name} not checked: optional dependency {missing!r} is not installed"
        raise


def _openfusion_exception_classes() -> list[type[BaseException]]:
    """Every loaded subclass of BaseException defined in an ``openfusion`` module (walks the
    subclass tree, so classes nested in classes or functions are found too)."""
    found: dict[type[BaseException], None] = {}
    stack: list[type[BaseException]] = [BaseException]
    while stack:
        cls = stack.pop()
        for sub in cls.__subclasses__():
            if sub in found or sub is cls:
                continue
            stack.append(sub)
            module = getattr(sub, "__module__", "") or ""
            if module == "openfusion" or module.startswith("openfusion."):
                found[sub] = None
    return sorted(found, key=lambda c: (c.__module__, c.__qualname__))


def _offenders(classes: list[type[BaseException]]) -> list[str]:
    """The classes of ``classes`` outside the OpenFusionError tree, named with their bases."""
    return [
        f"{c.__module__}.{c.__qualname__}({', '.join(b.__name__ for b in c.__bases__)})"
        for c in classes
        if not issubclass(c, OpenFusionError)
    ]


@pytest.mark.parametrize("name", MODULES)
def test_every_module_imports(name: str) -> None:
    """Each module imports (what the exception check below relies on); one that needs a missing
    optional dependency is skipped and named."""
    module, skipped = _import(name)
    if skipped is not None:
        pytest.skip(skipped)
    assert module is not None


def test_the_walk_covers_every_installed_package() -> None:
    """Every package pyproject.toml installs is walked (a new source root would otherwise be
    left out of the check without a sound)."""
    listed = set(tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"])
    assert listed <= set(MODULES), f"not walked: {sorted(listed - set(MODULES))}; add their root to ROOTS"


def test_every_exception_class_derives_from_openfusion_error() -> None:
    """Every exception class defined in the package is an OpenFusionError; the failure lists each
    offender with its bases (make it derive from OpenFusionError, or UserError when the user can fix
    it; keep a builtin such as ValueError as a second base where callers catch that)."""
    skipped = [why for _module, why in map(_import, MODULES) if why is not None]
    classes = _openfusion_exception_classes()
    # The walk reaches classes two levels below OpenFusionError and in the second branch (UserError).
    assert CapacityError in classes and MapFormatError in classes and OpenFusionError in classes, classes
    offenders = _offenders(classes)
    note = f" (modules not checked: {'; '.join(skipped)})" if skipped else ""
    assert not offenders, (
        f"{len(offenders)} exception class(es) do not derive from openfusion.errors.OpenFusionError{note}: "
        + ", ".join(offenders)
    )


def test_the_check_flags_a_class_outside_the_tree() -> None:
    """The collection and the check catch an exception class of an openfusion module that derives
    only from a builtin (the class is made here, with that module name, and dropped again)."""

    class Stray(ValueError):
        pass

    Stray.__module__ = "openfusion.mapping.errors"
    classes: list[type[BaseException]] = []
    try:
        classes = _openfusion_exception_classes()
        assert Stray in classes
        assert f"openfusion.mapping.errors.{Stray.__qualname__}(ValueError)" in _offenders(classes)
    finally:
        del Stray, classes
        gc.collect()
    assert not any(c.__qualname__.endswith("<locals>.Stray") for c in _openfusion_exception_classes())
