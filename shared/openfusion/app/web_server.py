"""The query page's HTTP server: a few fixed JSON endpoints and the page's own static files.

    server = QueryPageServer(ClientBackend(client), host="127.0.0.1", port=0)
    server.start()                    # a background thread; server.url is http://127.0.0.1:PORT/
    ...
    server.close()

Endpoints (GET only; every answer is JSON with ``Content-Type: application/json`` except the
page's files, served from a fixed table built at start, never from a path the request names):

- ``/api/query?text=TEXT[&top_k=K]``: the ranked answers of the query service
  (``{"query", "embedding_space", "regions": [{"key", "score", "label", "num_points", "bbox_min",
  "bbox_max", "points": [x, y, z, ...]}]}``, plus ``relevancy`` and ``match`` of a region when the
  service sends them). Each region carries at most :data:`HIGHLIGHT_MAX_POINTS` of its points.
- ``/api/points``: the map's surface points, at most ``max_points`` (evenly subsampled by the
  geometry service): ``{"count", "truncated", "positions", "colors", "keys"}`` (flat lists).
- ``/api/health``: the map's live services and their latest stats.

Bad input (no or empty text, a text longer than a query may carry, ``top_k`` not an integer in
1..:data:`MAX_TOP_K`, an unknown or repeated parameter, a body, another method) is answered 400
(405 for a method) with ``{"error": "..."}`` naming what was wrong; an unknown path 404; a service
that refused 502 and one that did not answer 504, with the service's reason. The server never
passes a request on to the bus as such: it calls three methods of a :class:`WebBackend`, and only
:class:`ClientBackend` (through :class:`~openfusion.client.OpenFusionClient`) talks to the
services, so no key, control action or raw request reaches the bus from a browser.

Security: the page is served with a Content-Security-Policy that allows only its own scripts
(the one inline import map by its hash), styles and connections; ``nosniff``; no referrer; no
framing. The ``Host`` header must name the address the server listens on when that is a loopback
address, which keeps other web sites from reaching it through DNS rebinding. The page builds all
text with ``textContent`` (never HTML from data).

Why the standard library's :class:`http.server.ThreadingHTTPServer`: the page needs three JSON
endpoints and a handful of static files for one local user; a web framework would be a new server
dependency for that. One thread per request, so a slow query does not hold up the health panel.
"""

from __future__ import annotations

import base64
import hashlib
import json
import logging
import math
import re
import threading
from collections.abc import Mapping
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from importlib import resources
from typing import Any, Protocol
from urllib.parse import parse_qs, urlsplit

from openfusion.bus import QueryError
from openfusion.errors import OpenFusionError, UsageError
from openfusion.wire.schemas.query import MAX_TEXT_CHARS

logger = logging.getLogger(__name__)

#: Most answers one query of the page asks for.
MAX_TOP_K = 20
#: Answers a query asks for when the page does not say.
DEFAULT_TOP_K = 5
#: Points of each answered region sent to the browser (the highlight).
HIGHLIGHT_MAX_POINTS = 4_000
#: Map surface points sent to the browser by default (``openfusion web --max-points``).
DEFAULT_MAX_POINTS = 60_000
#: Most map surface points ``--max-points`` may ask for (a browser draws this many smoothly).
MAX_POINTS_LIMIT = 500_000
#: Seconds the health panel waits for the services' stats.
HEALTH_TIMEOUT_S = 1.5

_CONTENT_TYPES = {
    ".html": "text/html; charset=utf-8",
    ".js": "text/javascript; charset=utf-8",
    ".css": "text/css; charset=utf-8",
    ".png": "image/png",
    ".svg": "image/svg+xml",
    ".txt": "text/plain; charset=utf-8",
    ".md": "text/plain; charset=utf-8",
}
_LOOPBACK_HOSTS = ("127.0.0.1", "localhost", "[::1]", "::1")


class WebError(OpenFusionError):
    """An HTTP error answer: ``status`` and a message for the page."""

    def __init__(self, status: HTTPStatus, message: str) -> None:
        self.status = status
        self.message = message
        super().__init__(f"{status.value}: {message}")


class WebBackend(Protocol):
    """What the page may ask of the map, and nothing else."""

    map_id: str

    def query(self, text: str, top_k: int) -> dict[str, Any]: ...

    def points(self, max_points: int) -> dict[str, Any]: ...

    def health(self) -> dict[str, Any]: ...


class ClientBackend:
    """:class:`WebBackend` through an :class:`~openfusion.client.OpenFusionClient` (its Zenoh
    session is safe to use from the server's request threads)."""

    def __init__(self, client: Any) -> None:
        self.client = client
        self.map_id = str(client.keys.map_id)

    def query(self, text: str, top_k: int) -> dict[str, Any]:
        reply = self.client.query_text(text, top_k=top_k, with_points=True, max_points=HIGHLIGHT_MAX_POINTS)
        return {"query": reply.query, "embedding_space": reply.embedding_space,
                "regions": [answer_record(region) for region in reply.regions]}

    def points(self, max_points: int) -> dict[str, Any]:
        reply = self.client.points(max_points=max_points)
        return {"count": len(reply.points), "truncated": bool(reply.truncated),
                "positions": _rounded(reply.points), "colors": [int(c) for c in reply.colors.reshape(-1)],
                "keys": [int(k) for k in reply.keys]}

    def health(self) -> dict[str, Any]:
        live = self.client.live_services(timeout_s=HEALTH_TIMEOUT_S)
        stats = self.client.health(timeout_s=HEALTH_TIMEOUT_S)
        services = []
        for name in sorted(set(live) | set(stats)):
            s = stats.get(name)
            services.append({"service": name, "alive": name in live,
                             **({"fps": s.fps, "errors": s.errors, "drops": s.drops, "uptime_s": s.uptime_s,
                                 "latency_ms_p50": s.latency_ms_p50} if s is not None else {})})
        return {"map_id": self.map_id, "services": services}


def answer_record(region: Any) -> dict[str, Any]:
    """One ranked region as the page shows it; ``relevancy`` and ``match`` only when the reply has them."""
    record: dict[str, Any] = {
        "key": int(region.key), "score": round(float(region.score), 4), "label": region.label,
        "num_points": int(region.num_points), "bbox_min": _rounded(region.bbox_min),
        "bbox_max": _rounded(region.bbox_max),
        "points": _rounded(region.points) if getattr(region, "points", None) is not None else [],
    }
    for name in ("relevancy", "match"):
        value = getattr(region, name, None)
        if value is not None:
            record[name] = _plain(value)
    return record


def _rounded(array: Any) -> list[float]:
    """A float array as a flat list, millimetres (3 decimals)."""
    return [round(float(v), 3) for v in array.reshape(-1)]


def _plain(value: Any) -> Any:
    """A reply field as plain JSON (models and arrays included)."""
    if hasattr(value, "model_dump"):
        value = value.model_dump(mode="json")
    if hasattr(value, "tolist"):
        value = value.tolist()
    if isinstance(value, float):
        return round(value, 4) if math.isfinite(value) else None
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_plain(v) for v in value]
    if value is None or isinstance(value, bool | int | str):
        return value
    return str(value)


# ------------------------------------------------------------------------------ the page


def _static_files() -> dict[str, tuple[bytes, str]]:
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


# ------------------------------------------------------------------------------ requests


def _one(params: Mapping[str, list[str]], name: str) -> str | None:
    values = params.get(name)
    if values is None:
        return None
    if len(values) != 1:
        raise WebError(HTTPStatus.BAD_REQUEST, f"give {name} once, got it {len(values)} times")
    return values[0]


def _only(params: Mapping[str, list[str]], allowed: tuple[str, ...]) -> None:
    unknown = sorted(set(params) - set(allowed))
    if unknown:
        allowed_text = ", ".join(allowed) if allowed else "none"
        raise WebError(HTTPStatus.BAD_REQUEST, f"unknown parameter {unknown[0]!r} (this endpoint takes: {allowed_text})")


def parse_query_params(query_string: str) -> tuple[str, int]:
    """(text, top_k) of ``/api/query``; :class:`WebError` 400 naming what is wrong."""
    try:
        params = parse_qs(query_string, keep_blank_values=True, strict_parsing=False, max_num_fields=8,
                          errors="strict")
    except (ValueError, UnicodeDecodeError) as exc:
        raise WebError(HTTPStatus.BAD_REQUEST, f"cannot read the query string: {exc}") from None
    _only(params, ("text", "top_k"))
    text = _one(params, "text")
    if text is None or not text.strip():
        raise WebError(HTTPStatus.BAD_REQUEST, "the query text is empty (give text=...)")
    if len(text) > MAX_TEXT_CHARS:
        raise WebError(HTTPStatus.BAD_REQUEST,
                       f"a query text of {len(text)} characters is longer than a query may carry ({MAX_TEXT_CHARS})")
    raw_k = _one(params, "top_k")
    top_k = DEFAULT_TOP_K
    if raw_k is not None:
        if not re.fullmatch(r"[0-9]{1,4}", raw_k):
            raise WebError(HTTPStatus.BAD_REQUEST, f"top_k must be a whole number from 1 to {MAX_TOP_K}, got {raw_k!r}")
        top_k = int(raw_k)
        if not 1 <= top_k <= MAX_TOP_K:
            raise WebError(HTTPStatus.BAD_REQUEST, f"top_k must be from 1 to {MAX_TOP_K}, got {top_k}")
    return text, top_k


def _bus_error(exc: QueryError) -> WebError:
    if exc.code == "timeout":
        return WebError(HTTPStatus.GATEWAY_TIMEOUT, f"the service did not answer: {exc.reason}")
    if exc.code == "too_large" or exc.code.startswith("bad_request"):
        return WebError(HTTPStatus.BAD_REQUEST, f"the service refused the request: {exc.reason}")
    return WebError(HTTPStatus.BAD_GATEWAY, f"the service refused the request ({exc.code}): {exc.reason}")


class _Handler(BaseHTTPRequestHandler):
    server: _Server
    server_version = "openfusion-web"
    sys_version = ""
    protocol_version = "HTTP/1.1"

    def log_message(self, format: str, *args: Any) -> None:  # noqa: A002 - BaseHTTPRequestHandler's name
        logger.debug("%s %s", self.address_string(), format % args)

    def do_GET(self) -> None:  # noqa: N802 - http.server's name
        self._serve(head=False)

    def do_HEAD(self) -> None:  # noqa: N802
        self._serve(head=True)

    def _refuse_method(self) -> None:
        self._send_json(HTTPStatus.METHOD_NOT_ALLOWED, {"error": f"{self.command} is not allowed; the page only reads"},
                        extra={"Allow": "GET, HEAD"})

    do_POST = do_PUT = do_DELETE = do_PATCH = do_OPTIONS = _refuse_method  # noqa: N815

    def _serve(self, *, head: bool) -> None:
        try:
            self._check_request()
            url = urlsplit(self.path)
            if url.path.startswith("/api/"):
                self._send_json(HTTPStatus.OK, self._api(url.path, url.query), head=head)
                return
            if url.query:
                raise WebError(HTTPStatus.BAD_REQUEST, "the page's files take no parameters")
            found = self.server.files.get(url.path)
            if found is None:
                raise WebError(HTTPStatus.NOT_FOUND, "no such page or file")
            body, content_type = found
            headers = {"Cache-Control": "no-cache"}
            if content_type.startswith("text/html"):
                headers["Content-Security-Policy"] = self.server.csp
            self._send(HTTPStatus.OK, body, content_type, headers, head=head)
        except WebError as exc:
            self._send_json(exc.status, {"error": exc.message}, head=head)
        except QueryError as exc:
            error = _bus_error(exc)
            logger.info("query page: %s", error.message)
            self._send_json(error.status, {"error": error.message}, head=head)
        except OpenFusionError as exc:
            logger.warning("query page: %s failed: %s", self.path[:200], exc)
            self._send_json(HTTPStatus.BAD_GATEWAY, {"error": str(exc).splitlines()[0]}, head=head)

    def _check_request(self) -> None:
        allowed = self.server.allowed_hosts
        if allowed is not None and (self.headers.get("Host") or "").lower() not in allowed:
            raise WebError(HTTPStatus.BAD_REQUEST, "unexpected Host header (the page answers only at its own address)")
        length = self.headers.get("Content-Length") or "0"
        if length.strip() != "0" or self.headers.get("Transfer-Encoding"):
            self.close_connection = True  # the body is not read: this connection ends with the answer
            raise WebError(HTTPStatus.BAD_REQUEST, "a GET request carries no body")

    def _api(self, path: str, query_string: str) -> dict[str, Any]:
        backend = self.server.backend
        if path == "/api/query":
            text, top_k = parse_query_params(query_string)
            return backend.query(text, top_k)
        if path in ("/api/points", "/api/health", "/api/info"):
            _only(parse_qs(query_string, keep_blank_values=True), ())
            if path == "/api/points":
                return backend.points(self.server.max_points)
            if path == "/api/health":
                return backend.health()
            return {"map_id": backend.map_id, "max_points": self.server.max_points, "max_top_k": MAX_TOP_K,
                    "max_text_chars": MAX_TEXT_CHARS}
        raise WebError(HTTPStatus.NOT_FOUND, f"no endpoint {path[:100]!r} (there are /api/query, /api/points, "
                       "/api/health, /api/info)")

    def _send_json(self, status: HTTPStatus, data: dict[str, Any], *, head: bool = False,
                   extra: dict[str, str] | None = None) -> None:
        body = json.dumps(data, allow_nan=False, separators=(",", ":")).encode()
        self._send(status, body, "application/json; charset=utf-8", {"Cache-Control": "no-store", **(extra or {})},
                   head=head)

    def _send(self, status: HTTPStatus, body: bytes, content_type: str, headers: dict[str, str], *,
              head: bool) -> None:
        self.send_response(status)
        self.send_header("Content-Type", content_type)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("X-Content-Type-Options", "nosniff")
        self.send_header("Referrer-Policy", "no-referrer")
        self.send_header("X-Frame-Options", "DENY")
        for name, value in headers.items():
            self.send_header(name, value)
        self.end_headers()
        if not head:
            self.wfile.write(body)


class _Server(ThreadingHTTPServer):
    daemon_threads = True
    backend: WebBackend
    files: dict[str, tuple[bytes, str]]
    csp: str
    max_points: int
    allowed_hosts: set[str] | None


def check_page_options(*, port: int, max_points: int, port_flag: str = "--port") -> None:
    """Refuse a port or a point budget the page cannot use (before anything is joined or bound)."""
    if not 0 <= port <= 65535:
        raise UsageError(f"{port_flag} must be between 0 and 65535, got {port}")
    if not 1 <= max_points <= MAX_POINTS_LIMIT:
        raise UsageError(f"--max-points must be between 1 and {MAX_POINTS_LIMIT:,}, got {max_points}")


class QueryPageServer:
    """The query page of one map on ``host:port`` (port 0: a free one; see :attr:`url`)."""

    def __init__(self, backend: WebBackend, *, host: str = "127.0.0.1", port: int = 0,
                 max_points: int = DEFAULT_MAX_POINTS) -> None:
        check_page_options(port=port, max_points=max_points)
        files = _static_files()
        try:
            self._httpd = _Server((host, port), _Handler, bind_and_activate=True)
        except (OSError, OverflowError) as exc:
            raise UsageError(f"cannot serve the query page on {host}:{port}: {exc}") from None
        self._httpd.backend = backend
        self._httpd.files = files
        self._httpd.csp = content_security_policy(files["/index.html"][0])
        self._httpd.max_points = max_points
        self.host = host
        self.port = int(self._httpd.server_address[1])
        shown = f"[{host}]" if ":" in host else host
        self.url = f"http://{shown}:{self.port}/"
        self.loopback = host in _LOOPBACK_HOSTS or host.startswith("127.")
        self._httpd.allowed_hosts = (
            {f"{h}:{self.port}" for h in ("127.0.0.1", "localhost", "[::1]", shown.lower())} if self.loopback else None
        )
        self._thread: threading.Thread | None = None

    def start(self) -> QueryPageServer:
        self._thread = threading.Thread(target=self._httpd.serve_forever, kwargs={"poll_interval": 0.2},
                                        name="query-page", daemon=True)
        self._thread.start()
        return self

    def close(self) -> None:
        if self._thread is not None:
            self._httpd.shutdown()
            self._thread.join()
            self._thread = None
        self._httpd.server_close()

    def __enter__(self) -> QueryPageServer:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()
