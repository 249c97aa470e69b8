"""``openfusion web``: the query page of a running map, in the browser.

    openfusion web --connect tcp/127.0.0.1:7447 --map lab [--host 127.0.0.1] [--port 8765] [--max-points N]

Serves a page (default http://127.0.0.1:8765/; ``--port 0`` picks a free port) with a text box,
the ranked answers of the query service (label, score, points, box; ``relevancy`` and ``match``
when the service sends them), a 3D view of the map's surface points (at most ``--max-points``,
subsampled by the geometry service) with the chosen answer highlighted, and the health of the
services. It prints the page's address on stdout (``query page: http://...``) and serves until
SIGINT/SIGTERM. The page talks to the services only through
:class:`~openfusion.client.OpenFusionClient` (see :mod:`openfusion.app.web_server`); the browser
never reaches the bus. ``--host`` other than a loopback address lets anyone who can reach this
machine query the map: the command says so on stderr. ``openfusion run --web`` starts the same
page beside its services.
"""

from __future__ import annotations

import argparse
import logging
import sys

from openfusion.app.web_server import DEFAULT_MAX_POINTS, ClientBackend, QueryPageServer, check_page_options
from openfusion.config import add_config_arguments, config_from_args, setup_logging
from openfusion.errors import UsageError

logger = logging.getLogger(__name__)

DEFAULT_PORT = 8765
#: Seconds the page's calls wait for the services.
DEFAULT_TIMEOUT_S = 10.0


def start_query_page(client: object, *, host: str = "127.0.0.1", port: int = 0,
                     max_points: int = DEFAULT_MAX_POINTS) -> QueryPageServer:
    """The query page of ``client``'s map, serving in a background thread; say where on stderr when
    it is reachable from other machines."""
    server = QueryPageServer(ClientBackend(client), host=host, port=port, max_points=max_points).start()
    if not server.loopback:
        print(f"warning: the query page listens on {host}, not a loopback address: anyone who can reach this "
              "machine can query the map", file=sys.stderr, flush=True)
    return server


class WebCommand:
    """Registry entry for ``openfusion web``."""

    @staticmethod
    def add_arguments(parser: argparse.ArgumentParser) -> None:
        parser.add_argument("--host", default="127.0.0.1",
                            help="address to serve the page on (default 127.0.0.1, this machine only)")
        parser.add_argument("--port", type=int, default=DEFAULT_PORT,
                            help=f"port (default {DEFAULT_PORT}; 0 picks a free one; the URL is printed)")
        parser.add_argument("--max-points", type=int, default=DEFAULT_MAX_POINTS, metavar="N",
                            help=f"most map surface points sent to the browser (default {DEFAULT_MAX_POINTS:,})")
        parser.add_argument("--timeout", type=float, default=DEFAULT_TIMEOUT_S, metavar="S",
                            help=f"seconds each call waits for the services (default {DEFAULT_TIMEOUT_S:g})")
        add_config_arguments(parser)

    @staticmethod
    def run(args: argparse.Namespace) -> int:
        from openfusion.app.bus_cmds import stop_on_signals
        from openfusion.client import OpenFusionClient

        if args.timeout <= 0:
            raise UsageError(f"--timeout must be positive, got {args.timeout:g}")
        check_page_options(port=args.port, max_points=args.max_points)
        config = config_from_args(args)
        setup_logging(config.log_level if args.log_level else "WARNING")
        stop = stop_on_signals()
        with OpenFusionClient.from_config(config, timeout_s=args.timeout) as client:
            server = start_query_page(client, host=args.host, port=args.port, max_points=args.max_points)
            try:
                print(f"query page: {server.url}  (map {config.map_id}; Ctrl-C stops it)", flush=True)
                while not stop.wait(0.5):
                    pass
            finally:
                server.close()
        return 0
