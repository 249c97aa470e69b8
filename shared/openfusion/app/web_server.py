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

Bad input (no or empty text, a text or ``top_k`` past the limits of :mod:`openfusion.wire.limits`
(512 characters, 1..100: the limits of every other surface, with the same one line), an unknown or
repeated parameter, a body, another method) is answered 400 (405 for a method) with ``{"error":
"..."}`` naming what was wrong; an unknown path 404; a service that refused 502 (400 when it refused
a value past a limit) and one that did not answer 504, with the service's reason. Every status the
server sends is JSON ``{"error": ...}``, those the standard library's parser raises too (400 for a
malformed request line, 414 for a request line over :data:`MAX_REQUEST_LINE` bytes, 431 for too
many or too long headers, 501 for an unknown method, 505 for another HTTP version, 503 when it holds
:data:`MAX_CONNECTIONS` busy connections, 500 for a failure of its own, logged with its traceback).

Hostile and slow clients (a page for one local user must not be held by anyone): every connection
must send a whole request head (request line and headers) within ``read_timeout_s``
(:data:`READ_TIMEOUT_S`, 10 s) of the moment the server starts waiting for it (the connection
opened, or the previous answer on it was sent); a watchdog closes those that do not, whether they
send nothing or trickle a byte at a time, and each socket read and write times out after twice that
(a client that stops reading its answer). At most ``max_connections`` (:data:`MAX_CONNECTIONS`, 64) are held at once: at the limit a new
connection takes the place of the one that has waited longest for its request (so idle connections
cannot lock a user out), and when every held connection is busy with a request the new one is
answered 503. A client that goes away before its answer is written is logged once at DEBUG, without
a traceback; an answer to a request the server did not read to the end (a body, a request line too
long) is followed by a lingering close, so the client reads the answer rather than a reset.
:meth:`QueryPageServer.connection_stats` counts what happened. The server never
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
import socket
import threading
import time
from collections.abc import Mapping
from dataclasses import dataclass
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from importlib import resources
from typing import Any, Protocol
from urllib.parse import parse_qs, urlsplit

from openfusion.bus import QueryError
from openfusion.errors import OpenFusionError, UsageError
from openfusion.wire.limits import (
    MAX_SURFACE_POINTS,
    MAX_TEXT_CHARS,
    MAX_TOP_K,
    LimitError,
    check_text,
    check_top_k,
)

logger = logging.getLogger(__name__)

#: Answers a query asks for when the page does not say.
DEFAULT_TOP_K = 5
#: Points of each answered region sent to the browser (the highlight)...
HIGHLIGHT_MAX_POINTS = 4_000
#: ... and of all answered regions together (fewer per region when a query asks for many).
HIGHLIGHT_BUDGET_POINTS = 80_000
#: Map surface points sent to the browser by default (``openfusion web --max-points``).
DEFAULT_MAX_POINTS = 60_000
#: Most map surface points ``--max-points`` may ask for (what one geometry reply may carry).
MAX_POINTS_LIMIT = MAX_SURFACE_POINTS
#: Seconds the health panel waits for the services' stats.
HEALTH_TIMEOUT_S = 1.5
#: Seconds a connection has to send a whole request head (module docstring).
READ_TIMEOUT_S = 10.0
#: Connections held at once (module docstring).
MAX_CONNECTIONS = 64
#: Longest request line in bytes: a query of MAX_TEXT_CHARS characters, each percent-encoded as up
#: to 12 bytes (a 4-byte UTF-8 character), and the rest of the line fit.
MAX_REQUEST_LINE = 12 * MAX_TEXT_CHARS + 2048
#: A lingering close reads and drops at most this many bytes, for at most LINGER_S seconds.
LINGER_BYTES = 4 * 1024 * 1024
LINGER_S = 2.0
#: Socket errors that mean the client went away (closed, reset, or stopped reading).
_GONE = (BrokenPipeError, ConnectionResetError, ConnectionAbortedError, TimeoutError)

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
        reply = self.client.query_text(text, top_k=top_k, with_points=True, max_points=highlight_points(top_k))
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


def highlight_points(top_k: int) -> int:
    """Points of each answered region sent to the browser when a query asks for ``top_k``."""
    return max(1, min(HIGHLIGHT_MAX_POINTS, HIGHLIGHT_BUDGET_POINTS // max(1, top_k)))


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
    raw_k = _one(params, "top_k")
    try:  # the one set of limits (openfusion.wire.limits), with the lines every surface gives
        check_text(text)
        top_k = DEFAULT_TOP_K if raw_k is None else check_top_k(
            int(raw_k) if re.fullmatch(r"[0-9]{1,12}", raw_k) else raw_k)
    except LimitError as exc:
        raise WebError(HTTPStatus.BAD_REQUEST, str(exc)) from None
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

    def setup(self) -> None:
        # each socket read and write (StreamRequestHandler applies it): a backstop behind the
        # watchdog for reads, the limit for a client that stops reading its answer
        self.timeout = 2 * self.server.read_timeout_s
        self._unread = False  # the request was not read to its end: close lingering
        super().setup()

    def handle(self) -> None:
        try:
            super().handle()
        except _GONE as exc:
            self._gone(exc)

    def finish(self) -> None:
        try:
            super().finish()
        except _GONE as exc:
            self._gone(exc)

    def _gone(self, exc: BaseException) -> None:
        self.close_connection = True
        logger.debug("query page: %s went away (%s)", self.client_address[0], type(exc).__name__)
        self.server.count("gone")

    def handle_one_request(self) -> None:
        """One request on this connection (http.server's, with the page's own request-line limit
        and the watchdog told when the server waits for a request head and when it has one)."""
        self.server.waiting(self.connection)
        self.raw_requestline = self.rfile.readline(MAX_REQUEST_LINE + 1)
        if len(self.raw_requestline) > MAX_REQUEST_LINE:
            self.server.busy(self.connection)
            self.requestline = ""
            self.request_version = ""
            self.command = ""
            self.send_error(HTTPStatus.REQUEST_URI_TOO_LONG,
                            f"the request line is longer than {MAX_REQUEST_LINE:,} bytes (a query text may have "
                            f"{MAX_TEXT_CHARS} characters)")
            return
        if not self.raw_requestline:
            self.close_connection = True
            return
        if not self.parse_request():  # it answered (send_error)
            return
        if not self.server.busy(self.connection):  # the watchdog closed it while the head trickled in
            self.close_connection = True
            return
        method = getattr(self, "do_" + self.command, None)
        if method is None:
            self.send_error(HTTPStatus.NOT_IMPLEMENTED, f"unsupported method {self.command[:20]!r}")
            return
        method()
        self.wfile.flush()

    def send_error(self, code: int, message: str | None = None, explain: str | None = None) -> None:
        """Every error the standard library's parser sends (400, 414, 431, 501, 505, ...) as the
        page's JSON ``{"error": ...}``; the connection then closes, lingering (the rest of the
        request was not read)."""
        status = HTTPStatus(code)
        if not str(getattr(self, "request_version", "")).startswith("HTTP/1."):
            self.request_version = self.protocol_version  # so the status line and headers are written
        self.close_connection = True
        self._unread = True
        text = message or status.phrase
        self.log_error("code %d, message %s", code, text)
        self._send_json(status, {"error": text[:300]}, head=self.command == "HEAD", extra={"Connection": "close"})
        self.server.count("errors")

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
        except _GONE:
            raise  # the client went away: handle() logs it once
        except WebError as exc:
            self._send_json(exc.status, {"error": exc.message}, head=head)
        except QueryError as exc:
            error = _bus_error(exc)
            logger.info("query page: %s", error.message)
            self._send_json(error.status, {"error": error.message}, head=head)
        except OpenFusionError as exc:
            logger.warning("query page: %s failed: %s", self.path[:200], exc)
            self._send_json(HTTPStatus.BAD_GATEWAY, {"error": str(exc).splitlines()[0]}, head=head)
        except Exception as exc:  # a failure of the page itself: logged with its traceback, answered 500
            logger.exception("query page: %s failed", self.path[:200])
            self.server.count("errors")
            self._send_json(HTTPStatus.INTERNAL_SERVER_ERROR,
                            {"error": f"the page failed: {type(exc).__name__} (its log has the details)"}, head=head)

    def _check_request(self) -> None:
        allowed = self.server.allowed_hosts
        if allowed is not None and (self.headers.get("Host") or "").lower() not in allowed:
            raise WebError(HTTPStatus.BAD_REQUEST, "unexpected Host header (the page answers only at its own address)")
        length = self.headers.get("Content-Length") or "0"
        if length.strip() != "0" or self.headers.get("Transfer-Encoding"):
            self.close_connection = True  # the body is not read: this connection ends with the answer
            self._unread = True
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
        if self.close_connection and "Connection" not in headers:
            headers = {**headers, "Connection": "close"}
        for name, value in headers.items():
            self.send_header(name, value)
        self.end_headers()
        if not head:
            self.wfile.write(body)
        if self._unread:
            self._linger()

    def _linger(self) -> None:
        """After an answer to a request not read to its end: stop writing, read and drop what the
        client still sends (at most LINGER_BYTES for LINGER_S), so it reads the answer instead of
        a connection reset."""
        self._unread = False
        try:
            self.wfile.flush()
            self.connection.shutdown(socket.SHUT_WR)
            self.connection.settimeout(LINGER_S)
            deadline = time.monotonic() + LINGER_S
            drained = 0
            while drained < LINGER_BYTES and time.monotonic() < deadline:
                chunk = self.connection.recv(65536)
                if not chunk:
                    break
                drained += len(chunk)
        except OSError as exc:  # gone, or nothing more to read in time: the connection closes either way
            logger.debug("query page: lingering close of %s ended: %s", self.client_address[0], type(exc).__name__)


@dataclass
class _Connection:
    state: str  # "waiting" (for a request head, until deadline), "busy" (answering), "closing"
    since: float
    deadline: float


class _Server(ThreadingHTTPServer):
    """The page's HTTP server: one thread per connection, at most ``max_connections`` of them, and
    a watchdog that closes connections whose request head is late (module docstring)."""

    daemon_threads = True
    request_queue_size = 128  # the listen backlog: a burst of connections waits to be accepted, not refused
    backend: WebBackend
    files: dict[str, tuple[bytes, str]]
    csp: str
    max_points: int
    allowed_hosts: set[str] | None

    def __init__(self, address: tuple[str, int], *, read_timeout_s: float, max_connections: int) -> None:
        self.read_timeout_s = read_timeout_s
        self.max_connections = max_connections
        self._lock = threading.Lock()
        self._connections: dict[socket.socket, _Connection] = {}
        self._stats = {"accepted": 0, "peak": 0, "timed_out": 0, "evicted": 0, "refused": 0, "gone": 0, "errors": 0}
        self._stop = threading.Event()
        super().__init__(address, _Handler, bind_and_activate=True)
        self._watchdog = threading.Thread(target=self._watch, name="query-page-watchdog", daemon=True)
        self._watchdog.start()

    def count(self, name: str) -> None:
        with self._lock:
            self._stats[name] += 1

    def stats(self) -> dict[str, int]:
        with self._lock:
            return {**self._stats, "open": sum(c.state != "closing" for c in self._connections.values())}

    def waiting(self, conn: socket.socket) -> None:
        now = time.monotonic()
        with self._lock:
            held = self._connections.get(conn)
            if held is not None and held.state != "closing":
                held.state, held.since, held.deadline = "waiting", now, now + self.read_timeout_s

    def busy(self, conn: socket.socket) -> bool:
        """Mark ``conn`` as answering a request; False when the watchdog has closed it."""
        with self._lock:
            held = self._connections.get(conn)
            if held is None or held.state == "closing":
                return False
            held.state, held.since, held.deadline = "busy", time.monotonic(), math.inf
            return True

    def process_request(self, request: Any, client_address: Any) -> None:
        """Hold the new connection (taking the place of the one that has waited longest for its
        request when at the limit) or, when every held one is busy, answer 503 and close it."""
        now = time.monotonic()
        victim = None
        with self._lock:
            held = [(c.since, s) for s, c in self._connections.items() if c.state != "closing"]
            if len(held) >= self.max_connections:
                waiting = [(since, s) for since, s in held if self._connections[s].state == "waiting"]
                if not waiting:
                    self._stats["refused"] += 1
                    refuse = True
                else:
                    victim = min(waiting, key=lambda w: w[0])[1]
                    self._connections[victim].state = "closing"
                    self._stats["evicted"] += 1
                    refuse = False
            else:
                refuse = False
            if not refuse:
                self._connections[request] = _Connection("waiting", now, now + self.read_timeout_s)
                self._stats["accepted"] += 1
                self._stats["peak"] = max(self._stats["peak"], len(held) + 1 - (victim is not None))
        if victim is not None:
            logger.debug("query page: at %d connections, closed the one waiting longest for a request",
                         self.max_connections)
            _close_quietly(victim)
        if refuse:
            logger.debug("query page: %d connections busy, refused %s", self.max_connections, client_address[0])
            _refuse_busy(request, self.max_connections)
            self.shutdown_request(request)
            return
        super().process_request(request, client_address)

    def shutdown_request(self, request: Any) -> None:
        with self._lock:
            self._connections.pop(request, None)
        super().shutdown_request(request)

    def handle_error(self, request: Any, client_address: Any) -> None:
        """An exception no handler caught (a bug of the page): logged once, with its traceback."""
        logger.exception("query page: a connection from %s failed", client_address[0] if client_address else "?")
        self.count("errors")

    def _watch(self) -> None:
        period = min(0.25, self.read_timeout_s / 4)
        while not self._stop.wait(period):
            now = time.monotonic()
            late = []
            with self._lock:
                for conn, held in self._connections.items():
                    if held.state == "waiting" and now >= held.deadline:
                        held.state = "closing"
                        late.append(conn)
                self._stats["timed_out"] += len(late)
            for conn in late:
                _close_quietly(conn)
            if late:
                logger.debug("query page: closed %d connection(s) that sent no request within %.1f s", len(late),
                             self.read_timeout_s)

    def server_close(self) -> None:
        self._stop.set()
        super().server_close()
        with self._lock:
            open_now = [s for s, c in self._connections.items() if c.state != "closing"]
        for conn in open_now:
            _close_quietly(conn)


def _close_quietly(conn: socket.socket) -> None:
    """End a connection its handler thread is reading from: the read returns at once (end of
    stream) and the thread finishes and closes it."""
    try:
        conn.shutdown(socket.SHUT_RDWR)
    except OSError as exc:  # already closed by the client or the handler
        logger.debug("query page: connection already closed: %s", exc)


def _refuse_busy(conn: socket.socket, limit: int) -> None:
    """A 503 JSON answer written straight to a connection the server does not hold."""
    body = json.dumps({"error": f"the page is busy: {limit} connections are being answered; try again"}).encode()
    head = (f"HTTP/1.1 503 Service Unavailable\r\nContent-Type: application/json; charset=utf-8\r\n"
            f"Content-Length: {len(body)}\r\nRetry-After: 1\r\nConnection: close\r\n"
            "X-Content-Type-Options: nosniff\r\nCache-Control: no-store\r\n\r\n").encode()
    try:
        conn.settimeout(0.5)
        conn.sendall(head + body)
    except OSError as exc:  # the client went away or does not read: it is closed either way
        logger.debug("query page: could not answer 503: %s", exc)


def check_page_options(*, port: int, max_points: int, port_flag: str = "--port") -> None:
    """Refuse a port or a point budget the page cannot use (before anything is joined or bound)."""
    if not 0 <= port <= 65535:
        raise UsageError(f"{port_flag} must be between 0 and 65535, got {port}")
    if not 1 <= max_points <= MAX_POINTS_LIMIT:
        raise UsageError(f"--max-points must be between 1 and {MAX_POINTS_LIMIT:,}, got {max_points}")


class QueryPageServer:
    """The query page of one map on ``host:port`` (port 0: a free one; see :attr:`url`);
    ``read_timeout_s`` and ``max_connections``: the module docstring."""

    def __init__(self, backend: WebBackend, *, host: str = "127.0.0.1", port: int = 0,
                 max_points: int = DEFAULT_MAX_POINTS, read_timeout_s: float = READ_TIMEOUT_S,
                 max_connections: int = MAX_CONNECTIONS) -> None:
        check_page_options(port=port, max_points=max_points)
        if not read_timeout_s > 0 or max_connections < 1:
            raise UsageError(f"the page needs read_timeout_s > 0 and max_connections >= 1, got {read_timeout_s} "
                             f"and {max_connections}")
        files = _static_files()
        try:
            self._httpd = _Server((host, port), read_timeout_s=read_timeout_s, max_connections=max_connections)
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

    def connection_stats(self) -> dict[str, int]:
        """Connections ``accepted``, held ``open`` now and at the ``peak``, closed for a late
        request head (``timed_out``), closed to make room (``evicted``), answered 503
        (``refused``), clients that went away before their answer (``gone``), and ``errors``."""
        return self._httpd.stats()

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
