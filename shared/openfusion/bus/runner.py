"""A service's life: open the session, declare entities, announce liveliness and health, run
until SIGINT/SIGTERM, undeclare everything (see :mod:`openfusion.bus` for the pattern)."""

from __future__ import annotations

import logging
import signal
import threading
import time
from collections.abc import Callable
from types import FrameType
from typing import Any, TypeVar

import zenoh

from openfusion.bus.health import HealthReporter
from openfusion.bus.pubsub import Publisher, Subscriber
from openfusion.bus.query import Queryable, call
from openfusion.bus.session import BusError, open_session
from openfusion.bus.stats import ServiceStats
from openfusion.config import ServiceConfig
from openfusion.wire.endpoints import Endpoint, Topic
from openfusion.wire.keys import validate_segment
from openfusion.wire.message import Message

logger = logging.getLogger(__name__)

M = TypeVar("M", bound=Message)
Q = TypeVar("Q", bound=Message)
R = TypeVar("R", bound=Message)
_POLL_S = 0.2


class ServiceRunner:
    """Owns a service's session and entities: :meth:`start` opens the session, the service
    declares its entities, :meth:`ready` declares liveliness + health; signals call :meth:`stop`;
    :meth:`close` undeclares everything (health first, then entities newest first) and closes
    the session."""

    def __init__(self, config: ServiceConfig, service: str) -> None:
        self.config = config
        self.service = validate_segment(service, what="service name")
        self.keys = config.keys
        self.stats = ServiceStats()
        self.session: zenoh.Session | None = None
        self.health: HealthReporter | None = None
        self._entities: list[Any] = []
        self._stop = threading.Event()
        self._previous_handlers: dict[int, Any] = {}
        self._closed = False

    # lifecycle
    def start(self) -> ServiceRunner:
        """Open the session. Declare entities next, then call :meth:`ready`."""
        self.session = open_session(self.config)
        logger.info("%s: session %s on map %r", self.service, self.session.zid(), self.keys.map_id)
        return self

    def ready(self) -> None:
        """Declare the liveliness token and start health stats: the service is now visible as
        alive, so call this after declaring the entities it serves (no caller sees a token
        before the queryables behind it exist)."""
        if self.health is None:
            self.health = HealthReporter(
                self._require_session(), self.keys, self.service, self.stats, period_s=self.config.health_period_s
            )

    def __enter__(self) -> ServiceRunner:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _require_session(self) -> zenoh.Session:
        if self.session is None:
            raise RuntimeError("ServiceRunner.start() has not been called")
        return self.session

    # entities
    def publisher(self, topic: Topic, **options: Any) -> Publisher:
        """A :class:`Publisher` of ``topic`` (its message type is checked on every put), counted in
        this service's stats, closed with the service."""
        pub = Publisher(self._require_session(), topic.key(self.keys), message=topic.message, stats=self.stats,
                        **options)
        self._entities.append(pub)
        return pub

    def subscriber(self, topic: Topic[M], callback: Callable[[M], Any] | None = None, **options: Any) -> Subscriber[M]:
        """A :class:`Subscriber` of ``topic``, counted in this service's stats, closed with the service."""
        sub = Subscriber(self._require_session(), topic.key(self.keys), topic.message, callback, stats=self.stats,
                         **options)
        self._entities.append(sub)
        return sub

    def queryable(self, endpoint: Endpoint[Q, R], handler: Callable[[Q], R], **options: Any) -> Queryable[Q]:
        """A :class:`Queryable` answering ``endpoint`` (the handler must return its reply type),
        counted in this service's stats, closed with the service."""
        qbl = Queryable(self._require_session(), endpoint.key(self.keys), endpoint.request, handler,
                        reply_model=endpoint.reply, stats=self.stats, **options)
        self._entities.append(qbl)
        return qbl

    def queryable_at(self, key: str, request: type[Q], reply: type[R], handler: Callable[[Q], R],
                     **options: Any) -> Queryable[Q]:
        """A :class:`Queryable` on a key outside this map's endpoints (the encoder pool's
        ``@pool`` keys, :class:`openfusion.wire.keys.PoolKeys`), closed with the service."""
        qbl = Queryable(self._require_session(), key, request, handler, reply_model=reply, stats=self.stats, **options)
        self._entities.append(qbl)
        return qbl

    def liveliness_token(self, key: str) -> Any:
        """A liveliness token on ``key`` (presence outside the map's health keys), undeclared with
        the service."""
        try:
            token = self._require_session().liveliness().declare_token(key)
        except zenoh.ZError as exc:
            raise BusError(f"cannot declare a liveliness token on {key}: {exc}") from None
        self._entities.append(_Undeclarable(token))
        return token

    def call(self, endpoint: Endpoint[Q, R], request: Q, *, timeout_s: float = 5.0) -> R:
        """Ask another service's ``endpoint`` of this map (:func:`openfusion.bus.query.call`)."""
        return call(self._require_session(), self.keys, endpoint, request, timeout_s=timeout_s)

    # stopping
    def stop(self) -> None:
        """Ask the service to stop (thread- and signal-safe)."""
        self._stop.set()

    @property
    def stopping(self) -> bool:
        return self._stop.is_set()

    def wait(self, timeout_s: float | None = None) -> bool:
        """Block until :meth:`stop` (True) or ``timeout_s`` (False); wakes for signals."""
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        while not self._stop.is_set():
            remaining = _POLL_S if deadline is None else min(_POLL_S, deadline - time.monotonic())
            if remaining <= 0:
                return False
            self._stop.wait(remaining)
        return True

    def install_signal_handlers(self) -> None:
        """SIGINT and SIGTERM call :meth:`stop` (main thread only; restored on close)."""
        if threading.current_thread() is not threading.main_thread():
            logger.debug("not in the main thread: signal handlers not installed")
            return

        def _handler(signum: int, _frame: FrameType | None) -> None:
            logger.info("%s: got %s, stopping", self.service, signal.Signals(signum).name)
            self.stop()

        for signum in (signal.SIGINT, signal.SIGTERM):
            self._previous_handlers[signum] = signal.signal(signum, _handler)

    def close(self) -> None:
        """Undeclare every entity (newest first), the health entities, then close the session."""
        if self._closed:
            return
        self._closed = True
        self._stop.set()
        if self.health is not None:
            self.health.close()
        for entity in reversed(self._entities):
            entity.close()
        self._entities.clear()
        if self.session is not None:
            self.session.close()
        for signum, previous in self._previous_handlers.items():
            signal.signal(signum, previous)
        self._previous_handlers.clear()
        logger.info("%s: stopped", self.service)


class _Undeclarable:
    """A Zenoh entity with ``undeclare()`` in the runner's list of things to close."""

    def __init__(self, entity: Any) -> None:
        self.entity = entity

    def close(self) -> None:
        try:
            self.entity.undeclare()
        except zenoh.ZError as exc:
            logger.debug("already undeclared: %s", exc)


def run_service(
    config: ServiceConfig,
    service: str,
    setup: Callable[[ServiceRunner], Any],
    *,
    loop: Callable[[ServiceRunner], Any] | None = None,
) -> int:
    """Run a service until SIGINT/SIGTERM: start, ``setup(runner)`` (declare entities), then
    ``loop(runner)`` (return when ``runner.stopping``) or just wait; close everything; return 0."""
    with ServiceRunner(config, service) as runner:
        runner.install_signal_handlers()
        setup(runner)
        runner.ready()
        logger.info("%s: ready on %s", service, runner.keys.base)
        if loop is not None:
            loop(runner)
        else:
            runner.wait()
    return 0
