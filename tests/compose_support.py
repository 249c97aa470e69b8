"""Compose files read as data, as ``docker compose`` reads them (no Docker engine runs here): shared by
the deploy-file checks (tests/unit) and the routing tests of the same configs (tests/bus).

Hand-written because compose interpolation is a small, fixed grammar (``${VAR}``, ``${VAR:-default}``,
``${VAR:?error}``) and no maintained Python package implements it without a Docker install.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import yaml

_VAR = re.compile(r"\$\{([A-Za-z_][A-Za-z0-9_]*)(?:(:-|:\?)([^}]*))?\}")


def interpolate(value: Any, env: dict[str, str]) -> Any:
    """Compose-style ${VAR}, ${VAR:-default}, ${VAR:?error} substitution, recursively.

    Raises KeyError for ${VAR:?...} with VAR unset, like `docker compose` refusing to start.
    """
    if isinstance(value, dict):
        return {key: interpolate(item, env) for key, item in value.items()}
    if isinstance(value, list):
        return [interpolate(item, env) for item in value]
    if not isinstance(value, str):
        return value

    def substitute(match: re.Match[str]) -> str:
        name, op, arg = match.group(1), match.group(2), match.group(3)
        if env.get(name):
            return env[name]
        if op == ":-":
            return arg
        if op == ":?":
            raise KeyError(f"{name} must be set: {arg}")
        return ""

    if "$" in _VAR.sub("", value).replace("$$", ""):
        raise ValueError(f"unsupported variable syntax in {value!r}")
    return _VAR.sub(substitute, value)


def load_compose(*paths: Path, env: dict[str, str] | None = None) -> dict[str, Any]:
    """Load compose files like `docker compose -f a -f b`: later files merge into earlier ones."""
    merged: dict[str, Any] = {}
    for path in paths:
        data = interpolate(yaml.safe_load(path.read_text()), env or {})
        _merge(merged, data)
    return merged


def _merge(base: dict[str, Any], extra: dict[str, Any]) -> None:
    for key, value in extra.items():
        if isinstance(value, dict) and isinstance(base.get(key), dict):
            _merge(base[key], value)
        else:
            base[key] = value
