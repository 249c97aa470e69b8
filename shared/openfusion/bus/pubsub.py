"""Typed publishers and subscribers: encode/decode through the codec, a sequence-number
attachment on every sample, bounded queues, counted drops (see :mod:`openfusion.bus`)."""

from __future__ import annotations

import collections
import logging
import os
import struct
import threading
import time
from collections.abc import Callable
from typing import Any, Generic, TypeVar

import zenoh

from openfusion.bus.session import BusError, is_matching
from openfusion.bus.stats import ServiceStats
from openfusion.wire.codec import (
    DEFAULT_MAX_ARRAY_ELEMENTS,
    DEFAULT_MAX_MESSAGE_BYTES,
    DecodeError,
    decode,
    encode,
)
from openfusion.wire.counters import CommonCounter
from openfusion.wire.message import Message

logger = logging.getLogger(__name__)

M = TypeVar("M", bound=Message)
_ATTACHMENT = struct.Struct("<8sQ")
_POLL_S = 0.2


class Publisher:
    """Encodes messages and publishes them on ``key`` with a sequence-number attachment."""

    def __init__(
        self,
        session: zenoh.Session,
        key: str,
        *,
        message: type[Message] | None = None,
        stats: ServiceStats | None = None,
        congestion_control: zenoh.CongestionControl | None = None,
        express: bool | None = None,
        max_bytes: int = DEFAULT_MAX_MESSAGE_BYTES,
    ) -> None:
        self.key = key
        self.message = message
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
        """Encode and publish ``msg``; returns its sequence number. EncodeError if it cannot go,
        TypeError when the publisher was declared for another message type."""
        if self.message is not None and not isinstance(msg, self.message):
            raise TypeError(f"{self.key} carries {self.message.__name__}, got {type(msg).__name__}")
        data = encode(msg, max_bytes=self._max_bytes)
        with self._lock:
            seq = self.sent
            self._pub.put(data, attachment=_ATTACHMENT.pack(self._source_id, seq))
            self.sent += 1
        if self._stats is not None:
            self._stats.incr(CommonCounter.PUBLISHED)
        return seq

    @property
    def has_subscribers(self) -> bool:
        """Whether any subscriber matches the key right now."""
        return is_matching(self._pub.matching_status)

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

    ``fair``: one queue of ``queue_size`` per publisher (the sample's source id; one bridge per
    robot on ``sensor/rgbd``), served in turn: a publisher whose samples come faster than they are
    handled (a live robot at 30 Hz) loses its own oldest samples, never another's, and each
    publisher with samples waiting gets every n-th turn of the worker (geometry serves n robots
    fairly). :attr:`current_source` and :attr:`current_arrival_s` tell a callback whose sample it
    handles and when it arrived.
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
        fair: bool = False,
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
        self.fair = fair
        # Queues by publisher (one queue under b"" unless fair), and the order they are served in.
        self._queues: dict[bytes, collections.deque[tuple[Any, float]]] = {}
        self._turns: collections.deque[bytes] = collections.deque()
        self.current_source = b""
        self.current_arrival_s = 0.0
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
            return sum(len(q) for q in self._queues.values())

    def queued_by_source(self) -> dict[bytes, tuple[int, float]]:
        """Per publisher (``fair``; else all under ``b""``): samples waiting and the arrival time
        (``time.monotonic()``) of the oldest."""
        with self._cond:
            return {source: (len(q), q[0][1]) for source, q in self._queues.items() if q}

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
            queue_id = raw[:8] if self.fair else b""
            queue = self._queues.get(queue_id)
            if queue is None:
                queue = self._queues[queue_id] = collections.deque()
                self._turns.append(queue_id)
            if len(queue) >= self.capacity:
                queue.popleft()
                self.dropped_queue += 1
                dropped += 1
            queue.append((sample.payload, now))
            self._cond.notify()
        if dropped and self._stats is not None:
            self._stats.add_drops(dropped)

    def _pop(self) -> tuple[Any, float] | None:
        """Call with ``_cond`` held: the next sample, taking the publishers in turn; a publisher
        whose queue is empty leaves the turns (it joins again with its next sample)."""
        while self._turns:
            source = self._turns[0]
            queue = self._queues[source]
            if not queue:
                self._turns.popleft()
                del self._queues[source]
                continue
            self._turns.rotate(-1)
            self.current_source = source
            return queue.popleft()
        return None

    def _next_payload(self, timeout_s: float | None) -> tuple[Any, float] | None:
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        with self._cond:
            while True:
                item = self._pop()
                if item is not None:
                    self.current_arrival_s = item[1]
                    return item
                if self._closed:
                    return None
                remaining = _POLL_S if deadline is None else min(_POLL_S, deadline - time.monotonic())
                if remaining <= 0:
                    return None
                self._cond.wait(remaining)

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
            self._queues.clear()
            self._turns.clear()
            self._cond.notify_all()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout_s)
            if self._thread.is_alive():
                logger.warning("subscriber worker for %s still busy after %.1f s", self.key, timeout_s)
