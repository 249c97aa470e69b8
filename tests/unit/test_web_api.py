"""The query page's HTTP API (``openfusion web``), served by the real server in a thread against a
stand-in backend (no bus): what the browser may ask, what it gets, and what is refused.

Bad input tried: no text, a blank text, a text over the query limit, a repeated text, top_k 0 /
21 / "abc" / "1e3", an unknown parameter, a parameter on the points endpoint, a body on a GET,
POST/PUT/DELETE, a path outside the page (``..``, the control keys, a Python file), another web
site's Host header, and services that refused or did not answer."""

from __future__ import annotations

import http.client
import json
import socket
import struct
import threading
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from openfusion.app.web_server import (
    HIGHLIGHT_MAX_POINTS,
    MAX_TOP_K,
    ClientBackend,
    QueryPageServer,
    answer_record,
    check_page_options,
)
from openfusion.bus import QueryError
from openfusion.errors import UsageError
from openfusion.testing.bus import wait_until
from openfusion.wire.schemas import HealthStats, PointsReply, QueryReply
from openfusion.wire.schemas.query import MAX_TEXT_CHARS, RegionHit

pytestmark = pytest.mark.timeout(60)


class _Backend:
    """Records every call; answers like the client backend does."""

    map_id = "lab"

    def __init__(self) -> None:
        self.calls: list[tuple[Any, ...]] = []
        self.fail: QueryError | None = None

    def query(self, text: str, top_k: int) -> dict[str, Any]:
        self.calls.append(("query", text, top_k))
        if self.fail is not None:
            raise self.fail
        return {"query": text, "embedding_space": "hash", "regions": []}

    def points(self, max_points: int) -> dict[str, Any]:
        self.calls.append(("points", max_points))
        return {"count": 0, "truncated": False, "positions": [], "colors": [], "keys": []}

    def health(self) -> dict[str, Any]:
        self.calls.append(("health",))
        return {"map_id": self.map_id, "services": []}


@pytest.fixture
def served() -> Any:
    backend = _Backend()
    with QueryPageServer(backend, port=0, max_points=1234) as server:
        yield server, backend


def _get(server: QueryPageServer, path: str, *, method: str = "GET", host: str | None = None,
         body: bytes | None = None) -> tuple[int, dict[str, str], bytes]:
    conn = http.client.HTTPConnection("127.0.0.1", server.port, timeout=20)
    try:
        headers = {"Host": host} if host is not None else {}
        conn.request(method, path, body=body, headers=headers)
        response = conn.getresponse()
        return response.status, {k.lower(): v for k, v in response.getheaders()}, response.read()
    finally:
        conn.close()


def _json(server: QueryPageServer, path: str, **kw: Any) -> tuple[int, dict[str, Any]]:
    status, headers, body = _get(server, path, **kw)
    assert headers["content-type"] == "application/json; charset=utf-8", (path, headers)
    assert headers["x-content-type-options"] == "nosniff"
    return status, json.loads(body)


def test_the_page_and_its_files_are_served_with_their_types_and_a_strict_policy(served) -> None:  # noqa: ANN001
    server, _ = served
    assert server.url == f"http://127.0.0.1:{server.port}/"
    status, headers, body = _get(server, "/")
    assert status == 200 and headers["content-type"] == "text/html; charset=utf-8"
    assert b'<input id="query-text"' in body
    csp = headers["content-security-policy"]
    assert "script-src 'self' 'sha256-" in csp and "unsafe-inline" not in csp and "default-src 'none'" in csp
    assert headers["x-frame-options"] == "DENY" and headers["referrer-policy"] == "no-referrer"
    for path, kind, marker in [("/app.js", "text/javascript", b"textContent"),
                               ("/vendor/three/three.module.min.js", "text/javascript", b'const t="170"'),
                               ("/vendor/three/LICENSE.txt", "text/plain", b"The MIT License"),
                               ("/style.css", "text/css", b"#viewer")]:
        status, headers, body = _get(server, path)
        assert status == 200 and headers["content-type"].startswith(kind) and marker in body, path


@pytest.mark.parametrize(
    ("path", "status", "error"),
    [
        ("/api/query", 400, "the query text is empty"),
        ("/api/query?text=%20%20", 400, "the query text is empty"),
        (f"/api/query?text={'x' * (MAX_TEXT_CHARS + 1)}", 400,
         f"the query text has {MAX_TEXT_CHARS + 1} characters; the limit is {MAX_TEXT_CHARS}"),
        (f"/api/query?text={'x' * 600}", 400, "the query text has 600 characters; the limit is 512"),
        (f"/api/query?text={'x' * 5000}", 400, "the query text has 5000 characters; the limit is 512"),
        ("/api/query?text=chair&text=lamp", 400, "give text once, got it 2 times"),
        ("/api/query?text=%FF%FE", 400, "cannot read the query string"),
        ("/api/query?text=chair&top_k=0", 400, f"top_k must be from 1 to {MAX_TOP_K}, got 0"),
        (f"/api/query?text=chair&top_k={MAX_TOP_K + 1}", 400, f"top_k must be from 1 to {MAX_TOP_K}"),
        ("/api/query?text=chair&top_k=abc", 400, "top_k must be a whole number from 1 to 100, got 'abc'"),
        ("/api/query?text=chair&top_k=1000000000", 400, "top_k must be from 1 to 100, got 1000000000"),
        ("/api/query?text=chair&top_k=-1", 400, "top_k must be a whole number from 1 to 100, got '-1'"),
        ("/api/query?text=chair&top_k=1e3", 400, "top_k must be a whole number"),
        ("/api/query?text=chair&key=openfusion/**", 400, "unknown parameter 'key' (this endpoint takes: text, top_k)"),
        ("/api/points?max_points=100000000", 400, "unknown parameter 'max_points' (this endpoint takes: none)"),
        ("/api/control/save", 404, "no endpoint '/api/control/save'"),
        ("/api/../../pyproject.toml", 404, "no endpoint"),
        ("/../web_server.py", 404, "no such page or file"),
        ("/__init__.py", 404, "no such page or file"),
        ("/vendor/three/../../web_server.py", 404, "no such page or file"),
        ("/index.html?x=<script>", 400, "the page's files take no parameters"),
    ],
)
def test_bad_requests_are_refused_with_a_clear_json_error_and_reach_no_service(served, path, status, error) -> None:  # noqa: ANN001
    server, backend = served
    got, data = _json(server, path)
    assert got == status and error in data["error"], data
    assert backend.calls == []


def test_only_reading_methods_only_this_host_and_no_bodies(served) -> None:  # noqa: ANN001
    server, backend = served
    for method in ("POST", "PUT", "DELETE"):
        status, headers, body = _get(server, "/api/query?text=chair", method=method, body=b"{}")
        assert status == 405 and headers["allow"] == "GET, HEAD" and b"is not allowed" in body
    status, data = _json(server, "/api/query?text=chair", host=f"evil.example:{server.port}")
    assert status == 400 and "unexpected Host header" in data["error"]
    status, data = _json(server, "/api/query?text=chair", body=b"x" * 10)
    assert status == 400 and "a GET request carries no body" in data["error"]
    conn = http.client.HTTPConnection("127.0.0.1", server.port, timeout=20)
    conn.putrequest("GET", "/api/query?text=chair")
    conn.putheader("Content-Length", "lots")
    conn.endheaders()
    response = conn.getresponse()
    assert response.status == 400 and "a GET request carries no body" in json.loads(response.read())["error"]
    conn.close()
    assert backend.calls == []
    status, data = _json(server, "/api/query?text=chair", host=f"localhost:{server.port}")
    assert status == 200 and backend.calls == [("query", "chair", 5)]


def test_queries_points_health_and_info_go_to_the_backend_as_asked(served) -> None:  # noqa: ANN001
    server, backend = served
    status, data = _json(server, "/api/query?text=%3Cscript%3Ealert(1)%3C%2Fscript%3E&top_k=3")
    assert status == 200 and data["query"] == "<script>alert(1)</script>"
    status, data = _json(server, "/api/points")
    assert status == 200 and data["count"] == 0
    assert _json(server, "/api/health")[1] == {"map_id": "lab", "services": []}
    assert _json(server, "/api/info")[1] == {"map_id": "lab", "max_points": 1234, "max_top_k": MAX_TOP_K,
                                             "max_text_chars": MAX_TEXT_CHARS}
    assert backend.calls == [("query", "<script>alert(1)</script>", 3), ("points", 1234), ("health",)]


@pytest.mark.parametrize(
    ("code", "status", "error"),
    [
        ("timeout", 504, "the service did not answer: no reply in 10 s"),
        ("no_map", 502, "the service refused the request (no_map): no reply in 10 s"),
        ("too_large", 400, "the service refused the request: no reply in 10 s"),
    ],
)
def test_a_service_that_refuses_or_does_not_answer_is_a_gateway_error_with_its_reason(served, code, status, error) -> None:  # noqa: ANN001
    server, backend = served
    backend.fail = QueryError("openfusion/lab/query/text", code, "no reply in 10 s")
    got, data = _json(server, "/api/query?text=chair")
    assert got == status and data == {"error": error}


def test_page_options_are_checked_before_anything_is_bound() -> None:
    with pytest.raises(UsageError, match="--port must be between 0 and 65535, got 70000"):
        check_page_options(port=70000, max_points=10)
    with pytest.raises(UsageError, match="--max-points must be between 1 and 500,000, got 0"):
        check_page_options(port=0, max_points=0)
    with pytest.raises(UsageError, match="cannot serve the query page on 203.0.113.7:0"):
        QueryPageServer(_Backend(), host="203.0.113.7", port=0)


class _Client:
    """Only what ClientBackend may call: three reading calls (no control, no raw get)."""

    keys = SimpleNamespace(map_id="lab")

    def __init__(self, hit: RegionHit) -> None:
        self.hit = hit
        self.asked: list[tuple[Any, ...]] = []

    def query_text(self, text: str, **kw: Any) -> QueryReply:
        self.asked.append(("query_text", text, kw))
        return QueryReply(embedding_space="hash", query=text, regions=[self.hit])

    def points(self, **kw: Any) -> PointsReply:
        self.asked.append(("points", kw))
        pts = np.array([[0.00049, 1.0, 2.0], [3.0, 4.0, 5.0]], np.float32)
        return PointsReply(points=pts, colors=np.array([[1, 2, 3], [4, 5, 6]], np.uint8),
                           keys=np.array([7, -1], np.int32), truncated=True)

    def live_services(self, *, timeout_s: float) -> list[str]:
        return ["query"]

    def health(self, *, timeout_s: float) -> dict[str, HealthStats]:
        stats = HealthStats(service="geometry", map_id="lab", pid=1, uptime_s=2.0, fps=30.0, latency_ms_p50=1.0,
                            latency_ms_p99=2.0, drops=0, errors=1)
        return {"geometry": stats}


def test_the_client_backend_sends_answers_with_their_points_and_the_map_as_flat_lists() -> None:
    hit = RegionHit(key=7, score=0.91234567, label="chair", bbox_min=np.zeros(3, np.float32),
                    bbox_max=np.ones(3, np.float32), num_points=2,
                    points=np.array([[0.1, 0.2, 0.3], [0.4, 0.5, 0.6]], np.float32))
    client = _Client(hit)
    backend = ClientBackend(client)
    reply = backend.query("chair", 4)
    assert client.asked == [("query_text", "chair", {"top_k": 4, "with_points": True,
                                                      "max_points": HIGHLIGHT_MAX_POINTS})]
    region = reply["regions"][0]
    assert region["key"] == 7 and region["score"] == 0.9123 and region["label"] == "chair"
    assert region["points"] == [0.1, 0.2, 0.3, 0.4, 0.5, 0.6] and region["bbox_max"] == [1.0, 1.0, 1.0]
    assert "relevancy" not in region and "match" not in region
    points = backend.points(100)
    assert points == {"count": 2, "truncated": True, "positions": [0.0, 1.0, 2.0, 3.0, 4.0, 5.0],
                      "colors": [1, 2, 3, 4, 5, 6], "keys": [7, -1]}
    health = backend.health()
    assert [(s["service"], s["alive"]) for s in health["services"]] == [("geometry", False), ("query", True)]
    assert health["services"][0]["fps"] == 30.0 and health["services"][0]["errors"] == 1


def test_relevancy_and_match_are_passed_on_when_a_reply_has_them() -> None:
    region = SimpleNamespace(key=1, score=0.5, label=None, num_points=0, bbox_min=np.zeros(3), bbox_max=np.zeros(3),
                             points=None, relevancy=0.87654, match={"kind": "exact", "margin": float("nan")})
    record = answer_record(region)
    assert record["relevancy"] == 0.8765 and record["match"] == {"kind": "exact", "margin": None}
    assert record["points"] == []
    json.dumps(record, allow_nan=False)


# ------------------------------------------------------------------ hostile and slow clients


def _raw(server: QueryPageServer, data: bytes, *, timeout_s: float = 20.0) -> tuple[int, dict[str, str], bytes]:
    """Send ``data`` on a fresh connection, read the answer to its end: (status, headers, body)."""
    with socket.create_connection(("127.0.0.1", server.port), timeout=timeout_s) as sock:
        sock.sendall(data)
        chunks = []
        while chunk := sock.recv(65536):
            chunks.append(chunk)
    head, _, body = b"".join(chunks).partition(b"\r\n\r\n")
    status_line, *lines = head.decode("latin-1").split("\r\n")
    headers = {k.strip().lower(): v.strip() for k, _, v in (line.partition(":") for line in lines)}
    return int(status_line.split()[1]), headers, body


def _closed_by_server(sock: socket.socket, timeout_s: float) -> bool:
    """Whether the server ends ``sock`` (end of stream or reset) within ``timeout_s``."""
    sock.settimeout(timeout_s)
    try:
        return sock.recv(1) == b""
    except ConnectionResetError:
        return True
    except TimeoutError:
        return False


def test_every_status_the_server_sends_is_json_and_it_keeps_answering(served, caplog) -> None:  # noqa: ANN001
    """What http.server's parser answers (400, 414, 431, 501, 505) is the page's JSON too; a 1 MB
    query line gets 414 (not the standard library's HTML page) and the client reads it, not a
    reset; a failure of the page's own code is a 500 JSON, logged once with its traceback; the
    next query is answered."""
    server, backend = served
    host = f"Host: 127.0.0.1:{server.port}\r\n".encode()
    line = b"GET /api/query?text=" + b"x" * 1_000_000 + b" HTTP/1.1\r\n" + host + b"\r\n"
    cases = [
        (line, 414, "the request line is longer than"),
        (b"FOO / HTTP/1.1\r\n" + host + b"\r\n", 501, "unsupported method 'FOO'"),
        (b"TRACE / HTTP/1.1\r\n" + host + b"\r\n", 501, "unsupported method 'TRACE'"),
        (b"GARBAGE\r\n\r\n", 400, "Bad request"),
        (b"GET / HTTP/2.0\r\n" + host + b"\r\n", 505, "Invalid HTTP version"),
        (b"GET / HTTP/1.1\r\n" + host + b"".join(b"X-%d: y\r\n" % i for i in range(120)) + b"\r\n", 431,
         "Too many headers"),
    ]
    for request, status, error in cases:
        got, headers, body = _raw(server, request)
        assert got == status and headers["content-type"] == "application/json; charset=utf-8", (status, body[:200])
        assert error in json.loads(body)["error"], body[:200]
    assert backend.calls == []

    def broken(text: str, top_k: int) -> dict[str, Any]:
        raise RuntimeError("a bug")

    backend.query = broken  # type: ignore[method-assign]
    caplog.set_level("DEBUG", logger="openfusion.app.web_server")
    status, data = _json(server, "/api/query?text=chair")
    assert status == 500 and data == {"error": "the page failed: RuntimeError (its log has the details)"}
    assert [r.exc_info is not None for r in caplog.records if r.levelname == "ERROR"] == [True]
    assert _json(server, "/api/info")[0] == 200


class _SlowBackend(_Backend):
    """Answers /api/points with a reply too large for the socket buffers, once ``go`` is set."""

    def __init__(self) -> None:
        super().__init__()
        self.asked = threading.Event()
        self.go = threading.Event()

    def points(self, max_points: int) -> dict[str, Any]:
        self.asked.set()
        assert self.go.wait(30)
        return {"count": 0, "truncated": False, "positions": [0] * 12_000_000, "colors": [], "keys": []}


def test_a_client_that_goes_away_is_logged_once_at_debug_without_a_traceback(caplog, capfd) -> None:  # noqa: ANN001
    """The client resets its connection while the page is writing a large answer: one DEBUG line
    "went away", no traceback in the log or on stderr, and the page answers the next query."""
    caplog.set_level("DEBUG", logger="openfusion.app.web_server")
    backend = _SlowBackend()
    with QueryPageServer(backend, port=0) as server:
        sock = socket.create_connection(("127.0.0.1", server.port), timeout=20)
        sock.sendall(f"GET /api/points HTTP/1.1\r\nHost: 127.0.0.1:{server.port}\r\n\r\n".encode())
        assert backend.asked.wait(20)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))  # close = reset
        sock.close()
        backend.go.set()
        wait_until(lambda: server.connection_stats()["gone"] == 1, timeout_s=30,
                   describe=lambda: str(server.connection_stats()))
        assert _json(server, "/api/info")[0] == 200
    gone = [r for r in caplog.records if "went away" in r.getMessage()]
    assert len(gone) == 1 and gone[0].levelname == "DEBUG"
    assert not any(r.exc_info for r in caplog.records)
    assert "Traceback" not in capfd.readouterr().err


def test_slow_clients_are_bounded_in_count_and_time_and_the_page_keeps_answering(caplog, capfd) -> None:  # noqa: ANN001
    """200 connections that send nothing and one that trickles its request a byte at a time: the
    page holds at most max_connections of them (a new connection takes the place of the one that
    has waited longest), answers a real query within 1 s while they are open, and closes every one
    of them by itself within the read timeout (the trickling one too: it never completes its
    request head in time); no traceback anywhere."""
    caplog.set_level("DEBUG", logger="openfusion.app.web_server")
    backend = _Backend()
    with QueryPageServer(backend, port=0, read_timeout_s=1.5, max_connections=64) as server:
        idle = [socket.create_connection(("127.0.0.1", server.port), timeout=20) for _ in range(200)]
        trickle = socket.create_connection(("127.0.0.1", server.port), timeout=20)
        # The 1 s bound is on the page's answer, not on the kernel: wait until the page has taken
        # all 201 connections off its listen queue, so the query's own connect is not the one
        # still queued behind them (a loaded CI box once took over 1 s to accept them).
        wait_until(lambda: sum(server.connection_stats()[k] for k in ("accepted", "refused")) >= 201,
                   timeout_s=20, describe=lambda: str(server.connection_stats()))
        conn = http.client.HTTPConnection("127.0.0.1", server.port, timeout=1.0)  # the 1 s bound
        conn.request("GET", "/api/query?text=chair")
        response = conn.getresponse()
        assert response.status == 200 and json.loads(response.read())["query"] == "chair"
        conn.close()
        request = f"GET /api/query?text=lamp HTTP/1.1\r\nHost: 127.0.0.1:{server.port}\r\n\r\n".encode()
        sent = 0
        for byte in request:  # one byte per 0.1 s: the head would take 5 s, the page gives it 1.5 s
            try:
                trickle.sendall(bytes([byte]))
            except OSError:  # the page closed it
                break
            sent += 1
            if _closed_by_server(trickle, 0.1):
                break
        assert sent < len(request) and _closed_by_server(trickle, 10)
        assert all(_closed_by_server(sock, 10) for sock in idle)
        stats = server.connection_stats()
        assert stats["peak"] <= 64 and stats["timed_out"] + stats["evicted"] >= 201 and stats["refused"] == 0
        wait_until(lambda: server.connection_stats()["open"] == 0, timeout_s=10,
                   describe=lambda: str(server.connection_stats()))
        assert ("query", "chair", 5) in backend.calls and ("query", "lamp", 5) not in backend.calls
        for sock in [*idle, trickle]:
            sock.close()
    assert not any(r.exc_info for r in caplog.records) and not any(r.levelno >= 30 for r in caplog.records)
    assert "Traceback" not in capfd.readouterr().err
