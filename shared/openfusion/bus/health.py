"""Presence and stats of services: liveliness tokens, periodic :class:`HealthStats`, and the
queries that list who is alive (``openfusion health``, the launcher)."""

from __future__ import annotations

import collections
import logging
import threading
import time

import zenoh

from openfusion.bus.session import BusError
from openfusion.bus.stats import ServiceStats
from openfusion.wire.codec import DecodeError, decode, encode
from openfusion.wire.keys import KeySpace
from openfusion.wire.schemas import HealthStats

logger = logging.getLogger(__name__)


def live_services(session: zenoh.Session, keys: KeySpace, *, timeout_s: float = 2.0) -> list[str]:
    """Names of the services of ``keys.map_id`` whose liveliness token is present, sorted."""
    names = set()
    for reply in session.liveliness().get(keys.health_all, timeout=timeout_s):
        if reply.ok is not None:
            try:
                names.add(keys.service_from_health_key(str(reply.ok.key_expr)))
            except ValueError as exc:
                logger.debug("ignoring liveliness key: %s", exc)
    return sorted(names)


def collect_health(session: zenoh.Session, keys: KeySpace, *, timeout_s: float = 2.0) -> dict[str, HealthStats]:
    """Latest :class:`HealthStats` of every service of the map that answers, by service name."""
    out: dict[str, HealthStats] = {}
    replies = session.get(
        keys.health_all,
        timeout=timeout_s,
        target=zenoh.QueryTarget.ALL,
        consolidation=zenoh.QueryConsolidation(zenoh.ConsolidationMode.NONE),
    )
    for reply in replies:
        if reply.ok is None:
            continue
        try:
            stats = decode(reply.ok.payload, expected=HealthStats)
        except DecodeError as exc:
            logger.warning("bad health reply on %s: %s", reply.ok.key_expr, exc)
            continue
        out[stats.service] = stats
    return out


class HealthReporter:
    """Liveliness token + periodic :class:`HealthStats` on ``keys.health(service)`` + a queryable
    on the same key answering the current stats (so ``openfusion health`` need not wait)."""

    def __init__(
        self,
        session: zenoh.Session,
        keys: KeySpace,
        service: str,
        stats: ServiceStats,
        *,
        period_s: float = 1.0,
    ) -> None:
        self.key = keys.health(service)
        self.service = service
        self.map_id = keys.map_id
        self.stats = stats
        self.period_s = period_s
        self.published = 0
        self._stop = threading.Event()
        self._queries: collections.deque[zenoh.Query] = collections.deque(maxlen=64)
        self._wake = threading.Condition()
        try:
            # The token last: whoever sees the service alive can already query its health.
            self._pub = session.declare_publisher(self.key)
            self._qbl = session.declare_queryable(self.key, zenoh.handlers.Callback(self._on_query))
            self._token = session.liveliness().declare_token(keys.liveliness(service))
        except zenoh.ZError as exc:
            raise BusError(f"cannot declare health entities on {self.key}: {exc}") from None
        self._thread = threading.Thread(target=self._run, name=f"health:{service}", daemon=True)
        self._thread.start()

    def _on_query(self, query: zenoh.Query) -> None:
        with self._wake:
            self._queries.append(query)
            self._wake.notify()

    def _snapshot(self) -> bytes:
        return encode(self.stats.snapshot(service=self.service, map_id=self.map_id))

    def _run(self) -> None:
        next_publish = time.monotonic()
        while not self._stop.is_set():
            with self._wake:
                timeout = next_publish - time.monotonic()
                if not self._queries and timeout > 0:
                    self._wake.wait(timeout)
                pending = list(self._queries)
                self._queries.clear()
            try:
                for query in pending:
                    with query:
                        query.reply(self.key, self._snapshot())
                if time.monotonic() >= next_publish and not self._stop.is_set():
                    self._pub.put(self._snapshot())
                    self.published += 1
                    next_publish = time.monotonic() + self.period_s
            except zenoh.ZError as exc:
                logger.warning("health %s: %s", self.key, exc)
                next_publish = time.monotonic() + self.period_s

    def close(self) -> None:
        self._stop.set()
        with self._wake:
            self._wake.notify_all()
        self._thread.join(5.0)
        for entity in (self._token, self._qbl, self._pub):  # not alive before not answering
            try:
                entity.undeclare()
            except zenoh.ZError as exc:
                logger.debug("health entity on %s already undeclared: %s", self.key, exc)
        for query in self._queries:
            query.drop()
