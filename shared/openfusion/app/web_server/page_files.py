"""The page's own files (``openfusion/app/web_static``), read once into a fixed table the server
answers from (never from a path a request names), and the Content-Security-Policy of its HTML."""

from __future__ import annotations

import base64
import hashlib
import re
from importlib import resources
from typing import Any

from openfusion.errors import OpenFusionError

_CONTENT_TYPES = {
    ".html": "text/html; charset=utf-8",
    ".js": "text/javascript; charset=utf-8",
    ".css": "text/css; charset=utf-8",
    ".png": "image/png",
    ".svg": "image/svg+xml",
    ".txt": "text/plain; charset=utf-8",
    ".md": "text/plain; charset=utf-8",
}


def static_files() -> dict[str, tuple[bytes, str]]:
    """URL path -> (bytes, content type) of every file under ``web_static`` (read once)."""
    root = resources.files("openfusion.app").joinpath("web_static")
    table: dict[str, tuple[bytes, str]] = {}

    def walk(node: Any, prefix: str) -> None:
        for child in node.iterdir():
            if child.is_dir():
                walk(child, f"{prefix}{child.name}/")
                continue
            suffix = "." + child.name.rsplit(".", 1)[-1] if "." in child.name else ""
            if suffix in _CONTENT_TYPES:
                table[f"{prefix}{child.name}"] = (child.read_bytes(), _CONTENT_TYPES[suffix])

    walk(root, "/")
    if "/index.html" not in table:
        raise OpenFusionError(f"the query page's files are missing (no index.html in {root}); reinstall openfusion-z")
    table["/"] = table["/index.html"]
    return table


def content_security_policy(index_html: bytes) -> str:
    """The page's CSP: its own files only, plus the inline import map by its SHA-256."""
    hashes = [
        "'sha256-" + base64.b64encode(hashlib.sha256(m.group(1)).digest()).decode() + "'"
        for m in re.finditer(rb'<script type="importmap">(.*?)</script>', index_html, re.S)
    ]
    return ("default-src 'none'; script-src 'self' " + " ".join(hashes) + "; style-src 'self'; img-src 'self' data:; "
            "connect-src 'self'; base-uri 'none'; form-action 'self'; frame-ancestors 'none'")
