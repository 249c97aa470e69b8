"""The query page of one map served on ``host:port`` (:class:`QueryPageServer`), and the check of
the page's options every surface that starts one makes first (:func:`check_page_options`). The
package docstring says what the page serves and how it treats bad input and hostile clients."""

from __future__ import annotations

import threading

from openfusion.app.web_server.backend import WebBackend
from openfusion.app.web_server.connections import MAX_CONNECTIONS, READ_TIMEOUT_S, PageHTTPServer
from openfusion.app.web_server.handler import PageRequestHandler
from openfusion.app.web_server.page_files import content_security_policy, static_files
from openfusion.errors import UsageError
from openfusion.wire.limits import MAX_SURFACE_POINTS

#: Map surface points sent to the browser by default (``openfusion web --max-points``).
DEFAULT_MAX_POINTS = 60_000
#: Most map surface points ``--max-points`` may ask for (what one geometry reply may carry).
MAX_POINTS_LIMIT = MAX_SURFACE_POINTS
_LOOPBACK_HOSTS = ("127.0.0.1", "localhost", "[::1]", "::1")


def check_page_options(*, port: int, max_points: int, port_flag: str = "--port") -> None:
    """Refuse a port or a point budget the page cannot use (before anything is joined or bound)."""
    if not 0 <= port <= 65535:
        raise UsageError(f"{port_flag} must be between 0 and 65535, got {port}")
    if not 1 <= max_points <= MAX_POINTS_LIMIT:
        raise UsageError(f"--max-points must be between 1 and {MAX_POINTS_LIMIT:,}, got {max_points}")


class QueryPageServer:
    """The query page of one map on ``host:port`` (port 0: a free one; see :attr:`url`);
    ``read_timeout_s`` and ``max_connections``: the package docstring."""

    def __init__(self, backend: WebBackend, *, host: str = "127.0.0.1", port: int = 0,
                 max_points: int = DEFAULT_MAX_POINTS, read_timeout_s: float = READ_TIMEOUT_S,
                 max_connections: int = MAX_CONNECTIONS) -> None:
        check_page_options(port=port, max_points=max_points)
        if not read_timeout_s > 0 or max_connections < 1:
            raise UsageError(f"the page needs read_timeout_s > 0 and max_connections >= 1, got {read_timeout_s} "
                             f"and {max_connections}")
        files = static_files()
        try:
            self._httpd = PageHTTPServer((host, port), PageRequestHandler, read_timeout_s=read_timeout_s, max_connections=max_connections)
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
