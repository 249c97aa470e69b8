"""The page's HTTP server and its connections: one thread per connection, at most
``max_connections`` held, a new one taking the place of the one that has waited longest for its
request (503 when every held one is busy), and a watchdog that closes a connection whose request
head is late (the package docstring says why)."""

from __future__ import annotations

import json
import logging
import math
import socket
import threading
import time
from dataclasses import dataclass
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any

from openfusion.app.web_server.backend import WebBackend

logger = logging.getLogger(__name__)

#: Seconds a connection has to send a whole request head (the package docstring).
READ_TIMEOUT_S = 10.0
#: Connections held at once (the package docstring).
MAX_CONNECTIONS = 64


@dataclass
class Connection:
    state: str  # "waiting" (for a request head, until deadline), "busy" (answering), "closing"
    since: float
    deadline: float


class PageHTTPServer(ThreadingHTTPServer):
    """The page's HTTP server: one thread per connection, at most ``max_connections`` of them, and
    a watchdog that closes connections whose request head is late (the package docstring)."""

    daemon_threads = True
    # The listen backlog: a burst of connections waits to be accepted. When it is full Linux drops
    # the SYN and the client retries only after a second, so it is sized past any burst the
    # watchdog's limit lets through (capped by net.core.somaxconn, 4096 by default).
    request_queue_size = 1024
    backend: WebBackend
    files: dict[str, tuple[bytes, str]]
    csp: str
    max_points: int
    allowed_hosts: set[str] | None

    def __init__(self, address: tuple[str, int], handler: type[BaseHTTPRequestHandler], *, read_timeout_s: float,
                 max_connections: int) -> None:
        self.read_timeout_s = read_timeout_s
        self.max_connections = max_connections
        self._lock = threading.Lock()
        self._connections: dict[socket.socket, Connection] = {}
        self._stats = {"accepted": 0, "peak": 0, "timed_out": 0, "evicted": 0, "refused": 0, "gone": 0, "errors": 0}
        self._stop = threading.Event()
        super().__init__(address, handler, bind_and_activate=True)
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
                self._connections[request] = Connection("waiting", now, now + self.read_timeout_s)
                self._stats["accepted"] += 1
                self._stats["peak"] = max(self._stats["peak"], len(held) + 1 - (victim is not None))
        if victim is not None:
            logger.debug("query page: at %d connections, closed the one waiting longest for a request",
                         self.max_connections)
            close_quietly(victim)
        if refuse:
            logger.debug("query page: %d connections busy, refused %s", self.max_connections, client_address[0])
            refuse_busy(request, self.max_connections)
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
                close_quietly(conn)
            if late:
                logger.debug("query page: closed %d connection(s) that sent no request within %.1f s", len(late),
                             self.read_timeout_s)

    def server_close(self) -> None:
        self._stop.set()
        super().server_close()
        with self._lock:
            open_now = [s for s, c in self._connections.items() if c.state != "closing"]
        for conn in open_now:
            close_quietly(conn)


def close_quietly(conn: socket.socket) -> None:
    """End a connection its handler thread is reading from: the read returns at once (end of
    stream) and the thread finishes and closes it."""
    try:
        conn.shutdown(socket.SHUT_RDWR)
    except OSError as exc:  # already closed by the client or the handler
        logger.debug("query page: connection already closed: %s", exc)


def refuse_busy(conn: socket.socket, limit: int) -> None:
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

