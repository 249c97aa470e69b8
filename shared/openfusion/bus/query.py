"""Queryables that answer typed requests, and ``get`` / ``call`` that ask them."""

from __future__ import annotations

import collections
import logging
import threading
import time
from collections.abc import Callable
from typing import Generic, TypeVar

import zenoh

from openfusion.bus.session import BusError
from openfusion.bus.stats import ServiceStats
from openfusion.errors import OpenFusionError
from openfusion.wire.codec import (
    DEFAULT_MAX_ARRAY_ELEMENTS,
    DEFAULT_MAX_MESSAGE_BYTES,
    DecodeError,
    EncodeError,
    decode,
    encode,
)
from openfusion.wire.counters import CommonCounter
from openfusion.wire.endpoints import Endpoint
from openfusion.wire.keys import KeySpace
from openfusion.wire.message import Message
from openfusion.wire.schemas import ErrorReply

logger = logging.getLogger(__name__)

M = TypeVar("M", bound=Message)
Q = TypeVar("Q", bound=Message)
R = TypeVar("R", bound=Message)
_POLL_S = 0.2


class QueryError(OpenFusionError):
    """A ``get`` failed: ``code`` (``timeout``, ``bad_reply:<reason>``, or the service's
    :class:`ErrorReply` code) and ``reason`` (human text, from the remote service when it answered)."""

    def __init__(self, key: str, code: str, reason: str) -> None:
        self.key = key
        self.code = code
        self.reason = reason
        super().__init__(f"{key}: {reason}" if code == "timeout" else f"{key}: {code}: {reason}")

    @property
    def timed_out(self) -> bool:
        """No answer in time: our own timeout, or Zenoh's error reply ``Timeout`` (a queryable whose
        session closed with the query pending, or a router that gave up on it)."""
        return self.code == "timeout" or (self.code == "error" and self.reason.strip().lower() == "timeout")


class RequestError(OpenFusionError):
    """Raise in a queryable handler to refuse a request with your own ``code`` and ``reason``
    (answered as ``reply_err``; counted as ``refused``, not as a service error)."""

    def __init__(self, code: str, reason: str) -> None:
        self.code = code
        self.reason = reason
        super().__init__(f"{code}: {reason}")


def _error_payload(code: str, reason: str) -> bytes:
    return encode(ErrorReply(code=code, reason=reason[:4000]))


class Queryable(Generic[M]):
    """Answers queries on ``key``: decodes the request into ``request_model``, runs
    ``handler(request) -> Message`` on a worker thread and replies with the encoded result.

    A request that does not decode is answered ``reply_err(code="bad_request:<reason>")``; a
    :class:`RequestError` from the handler with its code; any other exception is logged with its
    traceback, counted as an error and answered ``reply_err(code="handler_error")``. More than
    ``queue_size`` waiting queries: the newest is dropped (finalized unanswered) and counted.

    ``workers`` threads take queries off one queue (default 1: answered one at a time, in order);
    more let a handler that waits (geometry's render waiting for a semantic update) hold one of
    them while the others answer. The handler must then be thread-safe.
    """

    def __init__(
        self,
        session: zenoh.Session,
        key: str,
        request_model: type[M],
        handler: Callable[[M], Message],
        *,
        reply_model: type[Message] | None = None,
        stats: ServiceStats | None = None,
        measure: bool = True,
        complete: bool = True,
        queue_size: int = 256,
        workers: int = 1,
        max_bytes: int = DEFAULT_MAX_MESSAGE_BYTES,
        max_array_elements: int = DEFAULT_MAX_ARRAY_ELEMENTS,
        undeclare_on_close: bool = True,
    ) -> None:
        if workers < 1:
            raise ValueError(f"a queryable needs at least one worker, got {workers}")
        self.key = key
        self._undeclare_on_close = undeclare_on_close
        self.request_model = request_model
        self.handler = handler
        self.reply_model = reply_model or Message
        self.answered = 0
        self.refused = 0
        self.errors = 0
        self.dropped = 0
        self._stats = stats
        self._measure = measure
        self._limits = {"max_bytes": max_bytes, "max_array_elements": max_array_elements}
        self._reply_key = None if any(c in key for c in "*$") else key
        self._queue: collections.deque[tuple[zenoh.Query, float]] = collections.deque()
        self._capacity = queue_size
        self._cond = threading.Condition()
        self._closed = False
        try:
            self._qbl = session.declare_queryable(key, zenoh.handlers.Callback(self._on_query), complete=complete)
        except zenoh.ZError as exc:
            raise BusError(f"cannot declare a queryable on {key}: {exc}") from None
        self._threads = [threading.Thread(target=self._run, name=f"qbl:{key}:{i}", daemon=True)
                         for i in range(workers)]
        for thread in self._threads:
            thread.start()

    def _on_query(self, query: zenoh.Query) -> None:
        # Zenoh thread: queue only. A query we do not keep is finalized when dropped.
        with self._cond:
            if self._closed or len(self._queue) >= self._capacity:
                self.dropped += 1
                dropped = True
            else:
                self._queue.append((query, time.monotonic()))
                self._cond.notify()
                dropped = False
        if dropped:
            logger.warning("queryable %s: dropped a query (queue full or closing)", self.key)
            if self._stats is not None:
                self._stats.add_drops()
            query.drop()

    def _run(self) -> None:
        while True:
            with self._cond:
                while not self._queue and not self._closed:
                    self._cond.wait(_POLL_S)
                if self._closed and not self._queue:
                    return
                query, arrived = self._queue.popleft()
            self._serve(query, arrived)

    def _count(self, attr: str) -> None:
        with self._cond:
            setattr(self, attr, getattr(self, attr) + 1)

    def _serve(self, query: zenoh.Query, arrived: float) -> None:
        try:
            with query:
                self._answer(query)
        except zenoh.ZError as exc:  # the caller went away / timed out before our reply
            logger.warning("queryable %s: could not answer %s: %s", self.key, query.selector, exc)
            self._count("errors")
            if self._stats is not None:
                self._stats.add_error()
            return
        if self._stats is not None and self._measure:
            self._stats.record(time.monotonic() - arrived)

    def _answer(self, query: zenoh.Query) -> None:
        payload = query.payload
        try:
            if payload is None:
                raise DecodeError("truncated", "the query has no payload")
            request = decode(payload, expected=self.request_model, **self._limits)
        except DecodeError as exc:
            logger.warning("queryable %s: refused a request: %s", self.key, exc)
            self._count("errors")
            if self._stats is not None:
                self._stats.add_error()
            query.reply_err(_error_payload(f"bad_request:{exc.reason}", str(exc)))
            return
        try:
            reply = self.handler(request)
            if not isinstance(reply, self.reply_model):
                raise TypeError(f"handler returned {type(reply).__name__}, not a {self.reply_model.__name__}")
            data = encode(reply)
        except RequestError as exc:
            logger.info("queryable %s: refused (%s): %s", self.key, exc.code, exc.reason)
            self._count("refused")
            if self._stats is not None:
                self._stats.incr(CommonCounter.REFUSED)
            query.reply_err(_error_payload(exc.code, exc.reason))
            return
        except Exception as exc:  # the service keeps running: logged with traceback, counted, answered
            logger.exception("queryable %s: handler failed on a %s request", self.key, self.request_model.schema_name)
            self._count("errors")
            if self._stats is not None:
                self._stats.add_error()
            code = "reply_too_large" if isinstance(exc, EncodeError) else "handler_error"
            query.reply_err(_error_payload(code, f"{type(exc).__name__}: {exc}"))
            return
        query.reply(self._reply_key or query.key_expr, data)
        self._count("answered")

    def close(self, *, timeout_s: float = 5.0) -> None:
        """Undeclare, answer nothing more, and finalize queries still waiting (callers see no reply).
        With ``undeclare_on_close=False`` the declaration stays until the session closes (queries
        arriving meanwhile are finalized unanswered, which :func:`get` asks again): one of several
        ``complete`` queryables on a key must go that way, because a router (eclipse-zenoh 1.10)
        keeps routing BEST_MATCHING queries to an undeclared complete queryable whose session is
        still open and stops answering the key altogether, while a closed session's queryables are
        routed around at once (tests/bus/test_query_services.py)."""
        if self._undeclare_on_close:
            try:
                self._qbl.undeclare()
            except zenoh.ZError as exc:
                logger.debug("queryable %s already undeclared: %s", self.key, exc)
        with self._cond:
            self._closed = True
            pending = list(self._queue)
            self._queue.clear()
            self._cond.notify_all()
        for query, _ in pending:
            query.drop()
        deadline = time.monotonic() + timeout_s
        for thread in self._threads:
            if thread is not threading.current_thread():
                thread.join(max(0.0, deadline - time.monotonic()))


#: A query that came back with no reply at all is asked again after this pause (:func:`get`
#: with ``retry_unanswered_s``).
_RETRY_UNANSWERED_PAUSE_S = 0.05
#: How long clients of several interchangeable services (the query services) ask again.
RETRY_UNANSWERED_S = 0.5


def _first_reply(key: str, reply: zenoh.Reply, reply_model: type[M], *, max_bytes: int,
                 max_array_elements: int) -> M:
    """The reply as ``reply_model``; QueryError for an error reply or one that does not decode."""
    if reply.ok is not None:
        try:
            return decode(reply.ok.payload, expected=reply_model, max_bytes=max_bytes,
                          max_array_elements=max_array_elements)
        except DecodeError as exc:
            raise QueryError(key, f"bad_reply:{exc.reason}", str(exc)) from None
    err = reply.err
    try:
        error = decode(err.payload, expected=ErrorReply)
    except DecodeError:
        text = err.payload.to_bytes()[:300].decode("utf-8", "replace")
        raise QueryError(key, "error", text) from None
    raise QueryError(key, error.code, error.reason)


def _zenoh_timeout(reply: zenoh.Reply) -> bool:
    """Zenoh's own ``Timeout`` error reply (not a service's :class:`ErrorReply`): the queryable's
    session closed, or a router gave up, with the query pending."""
    if reply.ok is not None:
        return False
    return reply.err.payload.to_bytes()[:16].decode("utf-8", "replace").strip().lower() == "timeout"


def _service_hint(key: str) -> str:
    parts = key.split("/")
    return parts[-2] if len(parts) >= 2 else key


def get(
    session: zenoh.Session,
    key: str,
    request: Message,
    reply_model: type[M],
    *,
    timeout_s: float = 5.0,
    service: str | None = None,
    max_bytes: int = DEFAULT_MAX_MESSAGE_BYTES,
    max_array_elements: int = DEFAULT_MAX_ARRAY_ELEMENTS,
    retry_unanswered_s: float = 0.0,
) -> M:
    """Ask the service on ``key`` and return its first reply as ``reply_model``.

    Raises :class:`QueryError`: with the remote ``code``/``reason`` when it answered
    ``reply_err``; ``bad_reply:<reason>`` when the reply does not decode; ``timeout`` ("no
    service answered on KEY within T s: is the SERVICE service running?") when nobody answered.
    ``retry_unanswered_s``: a query that ends with no reply at all before its timeout is asked
    again, every 50 ms, for up to that long (the queryable it went to was going away, or dropped
    it: another one of several answers; for requests that may be asked twice, e.g. queries).
    """
    payload = encode(request, max_bytes=max_bytes)
    started = time.monotonic()
    deadline = started + timeout_s
    while True:
        try:
            replies = session.get(key, payload=payload, timeout=max(deadline - time.monotonic(), 0.001))
        except zenoh.ZError as exc:
            raise QueryError(key, "bus_error", f"cannot send the query: {exc}") from None
        for reply in replies:
            if retry_unanswered_s > 0 and _zenoh_timeout(reply):
                break  # the queryable closed with the query pending: as unanswered (below)
            return _first_reply(key, reply, reply_model, max_bytes=max_bytes, max_array_elements=max_array_elements)
        # No reply at all, well before the timeout: the query went to a queryable that is going
        # away (one of several query services closing: Zenoh finalizes the query unanswered, or
        # answers it with its own ``Timeout`` error) or dropped it. Ask again for a moment, so
        # another instance answers (services/query/instances.py).
        now = time.monotonic()
        if now - started >= retry_unanswered_s or deadline - now < 2 * _RETRY_UNANSWERED_PAUSE_S:
            break
        time.sleep(_RETRY_UNANSWERED_PAUSE_S)
    hint = service or _service_hint(key)
    raise QueryError(
        key, "timeout", f"no service answered on {key} within {timeout_s:g} s: is the {hint} service running?"
    )


def get_all(
    session: zenoh.Session,
    key: str,
    request: Message,
    reply_model: type[M],
    *,
    timeout_s: float = 5.0,
    max_bytes: int = DEFAULT_MAX_MESSAGE_BYTES,
    max_array_elements: int = DEFAULT_MAX_ARRAY_ELEMENTS,
    retry_unanswered_s: float = 0.0,
) -> list[M | QueryError]:
    """EVERY reply to one query on ``key`` (what :func:`get` returns the first of), each decoded
    or a :class:`QueryError`, waiting for the query to finish; asked again like :func:`get` when
    none came (``retry_unanswered_s``). For counting: several services behind one key must answer a request once
    (``bench/bench_query_load.py``, ``tests/bus/test_query_services.py``)."""
    payload = encode(request, max_bytes=max_bytes)
    started = time.monotonic()
    deadline = started + timeout_s
    while True:
        try:
            replies = list(session.get(key, payload=payload, timeout=max(deadline - time.monotonic(), 0.001)))
        except zenoh.ZError as exc:
            raise QueryError(key, "bus_error", f"cannot send the query: {exc}") from None
        if retry_unanswered_s > 0 and replies and all(_zenoh_timeout(r) for r in replies):
            replies = []  # only a closing queryable's Timeout: as unanswered
        now = time.monotonic()
        if replies or now - started >= retry_unanswered_s or deadline - now < 2 * _RETRY_UNANSWERED_PAUSE_S:
            break
        time.sleep(_RETRY_UNANSWERED_PAUSE_S)
    out: list[M | QueryError] = []
    for reply in replies:
        try:
            out.append(_first_reply(key, reply, reply_model, max_bytes=max_bytes,
                                    max_array_elements=max_array_elements))
        except QueryError as exc:
            out.append(exc)
    return out


def call(
    session: zenoh.Session,
    keys: KeySpace,
    endpoint: Endpoint[Q, R],
    request: Q,
    *,
    timeout_s: float = 5.0,
    max_bytes: int = DEFAULT_MAX_MESSAGE_BYTES,
    max_array_elements: int = DEFAULT_MAX_ARRAY_ELEMENTS,
    retry_unanswered_s: float = 0.0,
) -> R:
    """Ask ``endpoint`` of the map ``keys`` and return its typed reply (:func:`get` with the
    key, reply type and owner the endpoint declares). TypeError for a request of another type."""
    if not isinstance(request, endpoint.request):
        raise TypeError(f"{endpoint.path} takes {endpoint.request.__name__}, got {type(request).__name__}")
    return get(
        session,
        endpoint.key(keys),
        request,
        endpoint.reply,
        timeout_s=timeout_s,
        service=endpoint.owner,
        max_bytes=max_bytes,
        max_array_elements=max_array_elements,
        retry_unanswered_s=retry_unanswered_s,
    )
