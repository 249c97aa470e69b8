"""Every package folder is installed (two source roots, listed explicitly in pyproject.toml)."""

from __future__ import annotations

import tomllib
from pathlib import Path

ROOT = next(p for p in Path(__file__).resolve().parents if (p / "pyproject.toml").is_file())


def _package_folders() -> set[str]:
    names = set()
    for init in (ROOT / "shared" / "openfusion").rglob("__init__.py"):
        rel = init.parent.relative_to(ROOT / "shared")
        names.add(".".join(rel.parts))
    for init in (ROOT / "services").rglob("__init__.py"):
        rel = init.parent.relative_to(ROOT / "services")
        names.add(".".join(("openfusion", "services", *rel.parts)) if rel.parts else "openfusion.services")
    return names


def test_every_package_folder_is_listed_in_pyproject() -> None:
    listed = set(tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"])
    missing = _package_folders() - listed
    assert not missing, f"add these packages to [tool.setuptools] packages in pyproject.toml: {sorted(missing)}"


def test_no_top_level_shared_or_services_module_is_importable_as_such() -> None:
    import openfusion
    import openfusion.services

    assert Path(openfusion.__file__).parent == ROOT / "shared" / "openfusion"
    assert Path(openfusion.services.__file__).parent == ROOT / "services"
