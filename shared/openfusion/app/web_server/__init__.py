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

from openfusion.app.web_server.api_requests import DEFAULT_TOP_K, WebError, parse_query_params
from openfusion.app.web_server.backend import (
    HEALTH_TIMEOUT_S,
    HIGHLIGHT_BUDGET_POINTS,
    HIGHLIGHT_MAX_POINTS,
    ClientBackend,
    WebBackend,
    answer_record,
    highlight_points,
)
from openfusion.app.web_server.connections import MAX_CONNECTIONS, READ_TIMEOUT_S
from openfusion.app.web_server.handler import LINGER_BYTES, LINGER_S, MAX_REQUEST_LINE
from openfusion.app.web_server.page_files import content_security_policy
from openfusion.app.web_server.server import (
    DEFAULT_MAX_POINTS,
    MAX_POINTS_LIMIT,
    QueryPageServer,
    check_page_options,
)
from openfusion.wire.limits import MAX_TEXT_CHARS, MAX_TOP_K

__all__ = [
    "DEFAULT_MAX_POINTS",
    "DEFAULT_TOP_K",
    "HEALTH_TIMEOUT_S",
    "HIGHLIGHT_BUDGET_POINTS",
    "HIGHLIGHT_MAX_POINTS",
    "LINGER_BYTES",
    "LINGER_S",
    "MAX_CONNECTIONS",
    "MAX_POINTS_LIMIT",
    "MAX_REQUEST_LINE",
    "MAX_TEXT_CHARS",
    "MAX_TOP_K",
    "READ_TIMEOUT_S",
    "ClientBackend",
    "QueryPageServer",
    "WebBackend",
    "WebError",
    "answer_record",
    "check_page_options",
    "content_security_policy",
    "highlight_points",
    "parse_query_params",
]
