"""A minimal real service built with the bus helpers; the pattern every service follows.

It declares its liveliness token and publishes :class:`~openfusion.wire.schemas.HealthStats`
(both through :func:`openfusion.bus.run_service`), and answers :class:`PingRequest` on
``{prefix}/{map}/demo/ping`` with a :class:`PingReply`. Tests use it to check liveliness,
health, query/reply, handler failures and SIGTERM handling of a real process::

    python -m openfusion.testing.demo_service --map lab --listen tcp/127.0.0.1:7447 --no-multicast
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
import threading
from collections.abc import Sequence
from typing import ClassVar

from pydantic import Field

from openfusion.bus import RequestError, ServiceRunner, run_service
from openfusion.config import ConfigError, add_config_arguments, config_from_args, setup_logging
from openfusion.wire.endpoints import Endpoint
from openfusion.wire.schemas import Message

logger = logging.getLogger(__name__)

SERVICE = "demo"


class PingRequest(Message):
    """Ask the demo service to echo ``text``; ``fail`` makes the handler raise (to test errors)."""

    schema_name: ClassVar[str] = "demo.ping"
    schema_version: ClassVar[int] = 1

    text: str = Field(max_length=1000)
    fail: bool = False


class PingReply(Message):
    """The echo, the answering process id and how many pings it answered so far."""

    schema_name: ClassVar[str] = "demo.pong"
    schema_version: ClassVar[int] = 1

    text: str
    pid: int
    count: int


#: The demo service's one queryable, declared like the product's (:mod:`openfusion.wire.endpoints`).
PING = Endpoint((SERVICE, "ping"), PingRequest, PingReply, owner=SERVICE)


class DemoService:
    """The service logic, testable without a bus: ``handle_ping`` maps a request to a reply."""

    def __init__(self) -> None:
        self.count = 0
        self._lock = threading.Lock()

    def handle_ping(self, request: PingRequest) -> PingReply:
        if request.fail:
            raise RuntimeError("failure requested by the client")
        if request.text == "":
            raise RequestError("empty_text", "ping text must not be empty")
        with self._lock:
            self.count += 1
            count = self.count
        return PingReply(text=request.text, pid=os.getpid(), count=count)

    def setup(self, runner: ServiceRunner) -> None:
        runner.queryable(PING, self.handle_ping)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m openfusion.testing.demo_service", description=__doc__.splitlines()[0])
    add_config_arguments(parser)
    parser.add_argument("--service-name", default=SERVICE, help="service name (health / liveliness key)")
    args = parser.parse_args(argv)
    try:
        config = config_from_args(args)
    except ConfigError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    setup_logging(config.log_level)
    return run_service(config, args.service_name, DemoService().setup)


if __name__ == "__main__":
    sys.exit(main())
