"""Zenoh helpers every service and client uses: session, typed publisher/subscriber/queryable,
``get`` for clients, liveliness, periodic health stats and clean shutdown.

Rules these helpers enforce (style.md, design §2):

- Zenoh never calls user code directly: each entity registers a tiny callback that only puts
  the sample/query into a Python queue; a worker thread of ours decodes it and runs the user's
  callback/handler, which may then call Zenoh freely.
- A message that does not decode (:class:`openfusion.wire.codec.DecodeError`) is logged with the key
  and reason, counted as an error and dropped: subscriber callbacks never see bad messages;
  queryables answer it with ``reply_err(ErrorReply(code="bad_request:<reason>"))``.
- Every query is answered (reply or reply_err) or, when the service is overloaded, dropped
  (which finalizes it, so the caller does not wait for its timeout).
- Drops are counted, not silent. Each :class:`Publisher` stamps every sample with an attachment
  ``<8-byte source id><uint64 little-endian sequence number>``; a :class:`Subscriber` counts
  (a) samples its own bounded queue discarded (``latest_only`` keeps one) and (b) gaps in the
  sequence of each source (samples lost before they reached us, e.g. dropped by congestion
  control). Samples sent before a subscriber saw a source's first sample are not counted (a late
  joiner has not "dropped" history). Hence, for one publisher and a subscriber declared before it
  started: ``published == received + drops`` once the queue is drained.

A service is a :class:`ServiceRunner` (see ``openfusion.testing.demo_service`` for the pattern)::

    def setup(runner: ServiceRunner) -> None:
        runner.queryable(runner.keys.key("demo", "ping"), PingRequest, handle_ping)

    sys.exit(run_service(config, "demo", setup))

After ``setup`` has declared the service's entities it declares the liveliness token
``{prefix}/{map}/health/{service}`` (so "alive" means "ready to answer"), publishes
:class:`HealthStats` there every ``config.health_period_s`` (and answers queries on that key with
the latest stats), stops on SIGINT/SIGTERM, undeclares everything, closes the session and
returns exit code 0.
"""

from __future__ import annotations

import collections
import logging
import os
import signal
import socket
import struct
import threading
import time
from collections.abc import Callable
from types import FrameType
from typing import Any, Generic, TypeVar

import numpy as np
import zenoh

from openfusion.config import ServiceConfig, zenoh_config
from openfusion.errors import OpenFusionError
from openfusion.wire.codec import (
    DEFAULT_MAX_ARRAY_ELEMENTS,
    DEFAULT_MAX_MESSAGE_BYTES,
    DecodeError,
    EncodeError,
    decode,
    encode,
)
from openfusion.wire.keys import KeySpace, validate_segment
from openfusion.wire.schemas import ErrorReply, HealthStats, Message

logger = logging.getLogger(__name__)

M = TypeVar("M", bound=Message)
_ATTACHMENT = struct.Struct("<8sQ")
_POLL_S = 0.2


class BusError(OpenFusionError):
    """The Zenoh network could not be joined or an entity could not be declared."""


class QueryError(OpenFusionError):
    """A ``get`` failed: ``code`` (``timeout``, ``bad_reply:<reason>``, or the service's
    :class:`ErrorReply` code) and ``reason`` (human text, from the remote service when it answered)."""

    def __init__(self, key: str, code: str, reason: str) -> None:
        self.key = key
        self.code = code
        self.reason = reason
        super().__init__(f"{key}: {reason}" if code == "timeout" else f"{key}: {code}: {reason}")


class RequestError(OpenFusionError):
    """Raise in a queryable handler to refuse a request with your own ``code`` and ``reason``
    (answered as ``reply_err``; counted as ``refused``, not as a service error)."""

    def __init__(self, code: str, reason: str) -> None:
        self.code = code
        self.reason = reason
        super().__init__(f"{code}: {reason}")


def free_loopback_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago (the embedded run's router, tests)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def open_session(config: ServiceConfig) -> zenoh.Session:
    """A Zenoh session joined as ``config.zenoh`` says; BusError with the endpoints when it fails."""
    conf = zenoh_config(config)
    try:
        return zenoh.open(conf)
    except zenoh.ZError as exc:
        z = config.zenoh
        raise BusError(
            f"cannot open a Zenoh session (mode={z.mode or 'peer'}, listen={z.listen or 'default'}, "
            f"connect={z.connect or 'none'}): {exc}"
        ) from None


def _is_matching(status: Any) -> bool:
    return bool(getattr(status, "matching", status))


# ------------------------------------------------------------------------------------ stats


class ServiceStats:
    """Thread-safe counters of one service: processed items (fps), latency, drops, errors and
    named counters; :meth:`snapshot` makes the :class:`HealthStats` message."""

    def __init__(self, *, window_s: float = 5.0, latency_samples: int = 1024) -> None:
        self._lock = threading.Lock()
        self._window_s = window_s
        self._done: collections.deque[float] = collections.deque()
        self._latencies_ms: collections.deque[float] = collections.deque(maxlen=latency_samples)
        self.started = time.monotonic()
        self.processed = 0
        self.drops = 0
        self.errors = 0
        self.counters: dict[str, float] = {}

    def record(self, latency_s: float | None = None) -> None:
        """One item processed (counts towards fps), optionally with its latency in seconds."""
        now = time.monotonic()
        with self._lock:
            self.processed += 1
            self._done.append(now)
            while self._done and self._done[0] < now - self._window_s:
                self._done.popleft()
            if latency_s is not None:
                self._latencies_ms.append(latency_s * 1000.0)

    def add_drops(self, n: int = 1) -> None:
        with self._lock:
            self.drops += n

    def add_error(self, n: int = 1) -> None:
        with self._lock:
            self.errors += n

    def incr(self, name: str, by: float = 1.0) -> None:
        with self._lock:
            self.counters[name] = self.counters.get(name, 0.0) + by

    def set(self, name: str, value: float) -> None:
        with self._lock:
            self.counters[name] = float(value)

    def fps(self) -> float:
        now = time.monotonic()
        with self._lock:
            while self._done and self._done[0] < now - self._window_s:
                self._done.popleft()
            span = min(self._window_s, now - self.started)
            return len(self._done) / span if span > 0 else 0.0

    def snapshot(self, *, service: str, map_id: str) -> HealthStats:
        fps = self.fps()
        with self._lock:
            lat = np.asarray(self._latencies_ms, dtype=np.float64)
            p50, p99 = (float(np.percentile(lat, 50)), float(np.percentile(lat, 99))) if lat.size else (0.0, 0.0)
            return HealthStats(
                service=service,
                map_id=map_id,
                pid=os.getpid(),
                stamp_ns=time.time_ns(),
                uptime_s=time.monotonic() - self.started,
                fps=fps,
                latency_ms_p50=p50,
                latency_ms_p99=p99,
                drops=self.drops,
                errors=self.errors,
                counters=dict(self.counters),
            )


# --------------------------------------------------------------------------------- pub/sub


class Publisher:
    """Encodes messages and publishes them on ``key`` with a sequence-number attachment."""

    def __init__(
        self,
        session: zenoh.Session,
        key: str,
        *,
        stats: ServiceStats | None = None,
        congestion_control: zenoh.CongestionControl | None = None,
        express: bool | None = None,
        max_bytes: int = DEFAULT_MAX_MESSAGE_BYTES,
    ) -> None:
        self.key = key
        self.sent = 0
        self._stats = stats
        self._max_bytes = max_bytes
        self._source_id = os.urandom(8)
        self._lock = threading.Lock()
        try:
            self._pub = session.declare_publisher(key, congestion_control=congestion_control, express=express)
        except zenoh.ZError as exc:
            raise BusError(f"cannot declare a publisher on {key}: {exc}") from None

    def put(self, msg: Message) -> int:
        """Encode and publish ``msg``; returns its sequence number. EncodeError if it cannot go."""
        data = encode(msg, max_bytes=self._max_bytes)
        with self._lock:
            seq = self.sent
            self._pub.put(data, attachment=_ATTACHMENT.pack(self._source_id, seq))
            self.sent += 1
        if self._stats is not None:
            self._stats.incr("published")
        return seq

    @property
    def has_subscribers(self) -> bool:
        """Whether any subscriber matches the key right now."""
        return _is_matching(self._pub.matching_status)

    def wait_for_subscribers(self, timeout_s: float) -> bool:
        """Wait up to ``timeout_s`` for a matching subscriber; True when there is one."""
        deadline = time.monotonic() + timeout_s
        while not self.has_subscribers:
            if time.monotonic() >= deadline:
                return False
            time.sleep(0.01)
        return True

    def close(self) -> None:
        try:
            self._pub.undeclare()
        except zenoh.ZError as exc:
            logger.debug("publisher %s already undeclared: %s", self.key, exc)


class Subscriber(Generic[M]):
    """Decodes samples on ``key`` into ``model`` messages, with a bounded queue and counted drops.

    With a ``callback`` a worker thread calls ``callback(msg)`` for each valid message (an
    exception in it is logged and counted as an error; the subscriber keeps running). Without
    one, pull messages with :meth:`recv`. ``latest_only`` keeps only the newest sample (the
    queue holds one), ``queue_size`` bounds the queue otherwise; either way the oldest sample
    is discarded and counted when a new one arrives at a full queue.
    """

    def __init__(
        self,
        session: zenoh.Session,
        key: str,
        model: type[M],
        callback: Callable[[M], Any] | None = None,
        *,
        latest_only: bool = False,
        queue_size: int = 64,
        stats: ServiceStats | None = None,
        measure: bool = True,
        max_bytes: int = DEFAULT_MAX_MESSAGE_BYTES,
        max_array_elements: int = DEFAULT_MAX_ARRAY_ELEMENTS,
    ) -> None:
        if queue_size < 1:
            raise ValueError(f"queue_size must be at least 1, got {queue_size}")
        self.key = key
        self.model = model
        self.capacity = 1 if latest_only else queue_size
        self.arrived = 0
        self.received = 0
        self.dropped_queue = 0
        self.dropped_upstream = 0
        self.errors = 0
        self._stats = stats
        self._measure = measure
        self._limits = {"max_bytes": max_bytes, "max_array_elements": max_array_elements}
        self._queue: collections.deque[tuple[Any, float]] = collections.deque()
        self._cond = threading.Condition()
        self._last_seq: dict[bytes, int] = {}
        self._closed = False
        self._callback = callback
        try:
            self._sub = session.declare_subscriber(key, zenoh.handlers.Callback(self._on_sample))
        except zenoh.ZError as exc:
            raise BusError(f"cannot declare a subscriber on {key}: {exc}") from None
        self._thread: threading.Thread | None = None
        if callback is not None:
            self._thread = threading.Thread(target=self._run, name=f"sub:{key}", daemon=True)
            self._thread.start()

    @property
    def queued(self) -> int:
        """Samples waiting in the queue now."""
        with self._cond:
            return len(self._queue)

    @property
    def drops(self) -> int:
        """Samples lost: discarded by our queue plus gaps in the publishers' sequence numbers."""
        return self.dropped_queue + self.dropped_upstream

    def _on_sample(self, sample: zenoh.Sample) -> None:
        # Runs on a Zenoh thread: only bookkeeping and a queue push, never a Zenoh call.
        now = time.monotonic()
        attachment = sample.attachment
        raw = attachment.to_bytes() if attachment is not None else b""
        with self._cond:
            if self._closed:
                return
            gap = 0
            if len(raw) == _ATTACHMENT.size:
                source, seq = _ATTACHMENT.unpack(raw)
                last = self._last_seq.get(source)
                if last is not None and seq > last + 1:
                    gap = seq - last - 1
                if last is None or seq > last:
                    self._last_seq[source] = seq
            self.arrived += 1
            dropped = gap
            self.dropped_upstream += gap
            if len(self._queue) >= self.capacity:
                self._queue.popleft()
                self.dropped_queue += 1
                dropped += 1
            self._queue.append((sample.payload, now))
            self._cond.notify()
        if dropped and self._stats is not None:
            self._stats.add_drops(dropped)

    def _next_payload(self, timeout_s: float | None) -> tuple[Any, float] | None:
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        with self._cond:
            while not self._queue:
                if self._closed:
                    return None
                remaining = _POLL_S if deadline is None else min(_POLL_S, deadline - time.monotonic())
                if remaining <= 0:
                    return None
                self._cond.wait(remaining)
            return self._queue.popleft()

    def recv(self, timeout_s: float | None = None) -> M | None:
        """The next valid message, or None after ``timeout_s`` (or when closed)."""
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        while True:
            remaining = None if deadline is None else max(0.0, deadline - time.monotonic())
            item = self._next_payload(remaining)
            if item is None:
                return None
            msg = self._decode(item[0])
            if msg is not None:
                return msg

    def _decode(self, payload: Any) -> M | None:
        try:
            msg = decode(payload, expected=self.model, **self._limits)
        except DecodeError as exc:
            with self._cond:
                self.errors += 1
            if self._stats is not None:
                self._stats.add_error()
            logger.warning("dropped a message on %s (%d bytes): %s", self.key, len(payload), exc)
            return None
        with self._cond:
            self.received += 1
        return msg

    def _run(self) -> None:
        assert self._callback is not None
        while not self._closed:
            item = self._next_payload(None)
            if item is None:
                continue
            msg = self._decode(item[0])
            if msg is None:
                continue
            try:
                self._callback(msg)
            except Exception:  # the service keeps running; the error is logged and counted
                logger.exception("callback for %s failed on a %s message", self.key, self.model.schema_name)
                with self._cond:
                    self.errors += 1
                if self._stats is not None:
                    self._stats.add_error()
                continue
            if self._stats is not None and self._measure:
                self._stats.record(time.monotonic() - item[1])

    def close(self, *, timeout_s: float = 5.0) -> None:
        """Undeclare, stop the worker (after the message in hand) and drop what is queued."""
        try:
            self._sub.undeclare()
        except zenoh.ZError as exc:
            logger.debug("subscriber %s already undeclared: %s", self.key, exc)
        with self._cond:
            self._closed = True
            self._queue.clear()
            self._cond.notify_all()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout_s)
            if self._thread.is_alive():
                logger.warning("subscriber worker for %s still busy after %.1f s", self.key, timeout_s)


# ------------------------------------------------------------------------------ query/reply


def _error_payload(code: str, reason: str) -> bytes:
    return encode(ErrorReply(code=code, reason=reason[:4000]))


class Queryable(Generic[M]):
    """Answers queries on ``key``: decodes the request into ``request_model``, runs
    ``handler(request) -> Message`` on a worker thread and replies with the encoded result.

    A request that does not decode is answered ``reply_err(code="bad_request:<reason>")``; a
    :class:`RequestError` from the handler with its code; any other exception is logged with its
    traceback, counted as an error and answered ``reply_err(code="handler_error")``. More than
    ``queue_size`` waiting queries: the newest is dropped (finalized unanswered) and counted.
    """

    def __init__(
        self,
        session: zenoh.Session,
        key: str,
        request_model: type[M],
        handler: Callable[[M], Message],
        *,
        stats: ServiceStats | None = None,
        measure: bool = True,
        complete: bool = True,
        queue_size: int = 256,
        max_bytes: int = DEFAULT_MAX_MESSAGE_BYTES,
        max_array_elements: int = DEFAULT_MAX_ARRAY_ELEMENTS,
    ) -> None:
        self.key = key
        self.request_model = request_model
        self.handler = handler
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
        self._thread = threading.Thread(target=self._run, name=f"qbl:{key}", daemon=True)
        self._thread.start()

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
            if not isinstance(reply, Message):
                raise TypeError(f"handler returned {type(reply).__name__}, not a Message")
            data = encode(reply)
        except RequestError as exc:
            logger.info("queryable %s: refused (%s): %s", self.key, exc.code, exc.reason)
            self._count("refused")
            if self._stats is not None:
                self._stats.incr("refused")
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
        """Undeclare, answer nothing more, and finalize queries still waiting (callers see no reply)."""
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
        if self._thread is not threading.current_thread():
            self._thread.join(timeout_s)


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
) -> M:
    """Ask the service on ``key`` and return its first reply as ``reply_model``.

    Raises :class:`QueryError`: with the remote ``code``/``reason`` when it answered
    ``reply_err``; ``bad_reply:<reason>`` when the reply does not decode; ``timeout`` ("no
    service answered on KEY within T s: is the SERVICE service running?") when nobody answered.
    """
    payload = encode(request, max_bytes=max_bytes)
    try:
        replies = session.get(key, payload=payload, timeout=timeout_s)
    except zenoh.ZError as exc:
        raise QueryError(key, "bus_error", f"cannot send the query: {exc}") from None
    for reply in replies:
        if reply.ok is not None:
            try:
                return decode(
                    reply.ok.payload, expected=reply_model, max_bytes=max_bytes, max_array_elements=max_array_elements
                )
            except DecodeError as exc:
                raise QueryError(key, f"bad_reply:{exc.reason}", str(exc)) from None
        err = reply.err
        try:
            error = decode(err.payload, expected=ErrorReply)
        except DecodeError:
            text = err.payload.to_bytes()[:300].decode("utf-8", "replace")
            raise QueryError(key, "error", text) from None
        raise QueryError(key, error.code, error.reason)
    hint = service or _service_hint(key)
    raise QueryError(
        key, "timeout", f"no service answered on {key} within {timeout_s:g} s: is the {hint} service running?"
    )


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


# ----------------------------------------------------------------------------- health/liveliness


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
            self._token = session.liveliness().declare_token(keys.liveliness(service))
            self._pub = session.declare_publisher(self.key)
            self._qbl = session.declare_queryable(self.key, zenoh.handlers.Callback(self._on_query))
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
        for entity in (self._qbl, self._pub, self._token):
            try:
                entity.undeclare()
            except zenoh.ZError as exc:
                logger.debug("health entity on %s already undeclared: %s", self.key, exc)
        for query in self._queries:
            query.drop()


# ---------------------------------------------------------------------------- service runner


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
    def publisher(self, key: str, **options: Any) -> Publisher:
        """A :class:`Publisher` counted in this service's stats, closed with the service."""
        pub = Publisher(self._require_session(), key, stats=self.stats, **options)
        self._entities.append(pub)
        return pub

    def subscriber(self, key: str, model: type[M], callback: Callable[[M], Any] | None = None, **options: Any) -> Subscriber[M]:
        """A :class:`Subscriber` counted in this service's stats, closed with the service."""
        sub = Subscriber(self._require_session(), key, model, callback, stats=self.stats, **options)
        self._entities.append(sub)
        return sub

    def queryable(self, key: str, model: type[M], handler: Callable[[M], Message], **options: Any) -> Queryable[M]:
        """A :class:`Queryable` counted in this service's stats, closed with the service."""
        qbl = Queryable(self._require_session(), key, model, handler, stats=self.stats, **options)
        self._entities.append(qbl)
        return qbl

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
