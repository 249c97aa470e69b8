"""One connection of the page, request by request: the standard library's parser with the page's
own request-line limit, every error answered as JSON, the page's files and API served, and a
lingering close after an answer to a request not read to its end (the package docstring)."""

from __future__ import annotations

import json
import logging
import socket
import time
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler
from typing import Any
from urllib.parse import parse_qs, urlsplit

from openfusion.app.web_server.api_requests import WebError, bus_error, only_params, parse_query_params
from openfusion.app.web_server.connections import PageHTTPServer
from openfusion.bus import QueryError
from openfusion.errors import OpenFusionError
from openfusion.wire.limits import MAX_TEXT_CHARS, MAX_TOP_K

logger = logging.getLogger(__name__)

#: Longest request line in bytes: a query of MAX_TEXT_CHARS characters, each percent-encoded as up
#: to 12 bytes (a 4-byte UTF-8 character), and the rest of the line fit.
MAX_REQUEST_LINE = 12 * MAX_TEXT_CHARS + 2048
#: A lingering close reads and drops at most this many bytes, for at most LINGER_S seconds.
LINGER_BYTES = 4 * 1024 * 1024
LINGER_S = 2.0
#: Socket errors that mean the client went away (closed, reset, or stopped reading).
_GONE = (BrokenPipeError, ConnectionResetError, ConnectionAbortedError, TimeoutError)


class PageRequestHandler(BaseHTTPRequestHandler):
    """A connection of the page (module docstring)."""

    server: PageHTTPServer
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
            error = bus_error(exc)
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
            only_params(parse_qs(query_string, keep_blank_values=True), ())
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
