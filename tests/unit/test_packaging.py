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



def test_every_file_of_the_query_page_is_package_data() -> None:
    """``openfusion web`` serves web_static/ from the installed package: every folder there holding
    files is a package (``__init__.py``, listed) with package-data ``*`` (a new subfolder must be added)."""
    setuptools = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    app = ROOT / "shared" / "openfusion" / "app"
    folders = {p.parent for p in (app / "web_static").rglob("*") if p.is_file() and p.suffix not in (".py", ".pyc")}
    names = {".".join(("openfusion", "app", *f.relative_to(app).parts)) for f in folders}
    assert {"openfusion.app.web_static", "openfusion.app.web_static.vendor.three"} <= names
    missing = sorted(n for n in names if n not in setuptools["packages"] or setuptools["package-data"].get(n) != ["*"])
    assert not missing, f"list these in [tool.setuptools] packages and package-data (['*']): {missing}"
