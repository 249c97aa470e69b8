"""Errors of :mod:`openfusion.viz` that a user can cause (the CLI prints them as one line)."""

from __future__ import annotations


class VizError(ValueError):
    """A visualisation input is unusable: missing or foreign map, empty geometry, bad size, unknown query space."""


class MissingDependencyError(VizError):
    """An optional package (trimesh, rerun-sdk) is needed for what was asked and is not installed."""

    def __init__(self, package: str, purpose: str) -> None:
        super().__init__(
            f"{purpose} needs the optional package {package!r}, which is not installed: "
            f"pip install 'openfusion-z[viz]' (or pip install {package})"
        )
        self.package = package
