"""Errors of :mod:`openfusion.viz`: bad input the user gave (one line, exit code 2) and a missing
optional package (one line, exit code 1)."""

from __future__ import annotations

from openfusion.errors import OpenFusionError, UserError


class VizError(UserError, ValueError):
    """A visualisation input is unusable: missing or foreign map, empty geometry, bad size, unknown query space."""


class MissingDependencyError(OpenFusionError, ImportError):
    """An optional package (trimesh, rerun-sdk) is needed for what was asked and is not installed."""

    def __init__(self, package: str, purpose: str) -> None:
        super().__init__(
            f"{purpose} needs the optional package {package!r}, which is not installed: "
            f"pip install 'openfusion-z[viz]' (or pip install {package})"
        )
        self.package = package
