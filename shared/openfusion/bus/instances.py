"""Spreading a client's requests over several services that answer the same endpoints.

Zenoh delivers a ``get`` on a key that several ``complete`` queryables serve to ONE of them
(``QueryTarget.BEST_MATCHING``): on one router, always the same one (measured with eclipse-zenoh
1.10: two query services, 200 requests, all to the first). That answers every request once but
leaves the other services idle. So each query service also serves every endpoint on its own
instance key (:meth:`openfusion.wire.endpoints.Endpoint.instance_key`, ``…/query/text/query-2``),
and a client that spreads its requests (:class:`InstancePicker`) takes the live instances from
the services' liveliness tokens (refreshed every ``refresh_s``) and asks them in turn, starting
at a random one (so many clients do not all start on the first). Still one key per request, one
queryable behind it: answered once. An instance that does not answer (it went away between two
refreshes) is forgotten until the next refresh and the request is asked again on the shared key,
where Zenoh routes it to a live one.
"""

from __future__ import annotations

import itertools
import logging
import random
import threading
import time
from collections.abc import Callable

import zenoh

from openfusion.bus.health import live_services
from openfusion.wire.keys import KeySpace

logger = logging.getLogger(__name__)

#: How often the picker asks who is alive (a liveliness query, ~1 ms on loopback).
DEFAULT_REFRESH_S = 2.0


class InstancePicker:
    """The live services ``is_instance`` accepts, taken in turn; thread-safe."""

    def __init__(self, session: zenoh.Session, keys: KeySpace, is_instance: Callable[[str], bool], *,
                 refresh_s: float = DEFAULT_REFRESH_S, liveliness_timeout_s: float = 0.5) -> None:
        self._session = session
        self._keys = keys
        self._is_instance = is_instance
        self.refresh_s = refresh_s
        self._timeout_s = liveliness_timeout_s
        self._lock = threading.Lock()
        self._names: list[str] = []
        self._refreshed_at: float | None = None
        self._turn = itertools.count(random.randrange(1 << 16))

    def _refresh(self) -> None:
        names = sorted(n for n in live_services(self._session, self._keys, timeout_s=self._timeout_s)
                       if self._is_instance(n))
        with self._lock:
            self._names = names
            self._refreshed_at = time.monotonic()

    def names(self) -> list[str]:
        """The live instances (as of the last refresh, at most ``refresh_s`` ago)."""
        with self._lock:
            stale = self._refreshed_at is None or time.monotonic() - self._refreshed_at >= self.refresh_s
        if stale:
            try:
                self._refresh()
            except zenoh.ZError as exc:  # the session is closing: no instance, the shared key decides
                logger.debug("instance picker: liveliness query failed: %s", exc)
                return []
        with self._lock:
            return list(self._names)

    def pick(self) -> str | None:
        """The next live instance in turn; None when there are fewer than two (nothing to spread)."""
        names = self.names()
        if len(names) < 2:
            return None
        return names[next(self._turn) % len(names)]

    def forget(self, name: str) -> None:
        """``name`` did not answer: not picked again until the next refresh says it is alive."""
        with self._lock:
            if name in self._names:
                self._names.remove(name)
