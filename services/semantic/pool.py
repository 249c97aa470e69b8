"""The semantic service's side of the encoder pool: find workers, send them frames, collect results.

Workers announce themselves with a liveliness token on ``{prefix}/@pool/encoder/{worker_id}``
(:class:`openfusion.wire.keys.PoolKeys`); on a new token the pool asks the worker's ``info`` and
uses it only when it holds the map's embedding space (another space is logged once and counted in
``workers_refused``). Dispatch is least-loaded first with at most ``max_in_flight`` requests per
worker (so one frame is encoded while the next travels). Of the workers with room, the frame
goes to the one that should finish it first: each worker's time per frame is measured (from its
answers, queueing left out) and the pool knows when each should be done with what it holds, so
the frame goes where ``max(now, free at) + time per frame`` is least (an idle worker of the same
speed before a busy one). Frames then come back in the order they went out: a frame queued
behind a worker that frees up later would be overtaken by a newer frame on a worker that frees up
sooner, and its result, older than one applied, would be dropped as stale (wasted work). Each request runs on a thread of a small
executor (Zenoh's ``get`` blocks); results are queued for the service loop, which applies them in
the order the service took the frames (``seq``, given with each request: frame order for
``select=latest`` and ``every``, the order of choice for ``coverage``, which may take an older
frame after a newer one; :class:`~openfusion.services.semantic.service.SemanticService`).

A worker that dies (its token goes, or its request fails without an answer) never holds anything
up: the frames it held are sent once more to another worker, a frame that already went twice is
counted as lost, and a late answer of an abandoned request is ignored. A worker that refuses a
request (``wrong_space``: it was restarted with another model) is dropped from the pool.

Written here rather than taken from a library: the policy (least loaded, two in flight, one
re-send, results in frame order) is the design's, and Zenoh gives the pieces (liveliness, get).
"""

from __future__ import annotations

import collections
import logging
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import zenoh

from openfusion.bus import QueryError, get
from openfusion.bus.stats import ServiceStats
from openfusion.wire.counters import PoolCounter
from openfusion.wire.keys import PoolKeys
from openfusion.wire.schemas import EncodeReply, EncodeRequest, WorkerInfo, WorkerInfoRequest

logger = logging.getLogger(__name__)

INFO_TIMEOUT_S = 5.0


@dataclass
class PoolWorker:
    worker_id: str
    info: WorkerInfo
    in_flight: set[int] = field(default_factory=set)  # request ids
    sent: int = 0
    encoded: int = 0
    frame_s: float | None = None  # measured time per frame (moving average), None before its first answer
    free_at_s: float = 0.0  # CLOCK_MONOTONIC when it should be done with what it holds
    last_done_s: float = 0.0  # when its last answer came


@dataclass
class _Request:
    request_id: int
    request: EncodeRequest
    worker_id: str
    attempt: int  # 1, or 2 when re-sent
    seq: int  # the service's order of the frame (results apply in this order)
    abandoned: bool = False
    sent_at_s: float = 0.0  # CLOCK_MONOTONIC when dispatched


@dataclass
class PoolResult:
    """A frame's regions from worker ``worker_id`` (``request`` is the frame as sent)."""

    request: EncodeRequest
    reply: EncodeReply
    worker_id: str
    seq: int = 0  # the order the service took the frame in (results apply in this order)


#: Weight of the newest answer in a worker's time per frame (exponential moving average).
FRAME_TIME_WEIGHT = 0.3


@dataclass(frozen=True)
class WorkerLoad:
    """What dispatch looks at for one worker."""

    worker_id: str
    in_flight: int
    capacity: int  # most requests in flight at once (the pool's and the worker's limit)
    sent: int
    free_at_s: float  # when it should be done with what it holds (CLOCK_MONOTONIC)
    frame_s: float | None  # its time per frame, None before it answered once


def pick_worker(workers: list[WorkerLoad], now_s: float) -> str | None:
    """The worker with room that should finish the next frame first (``max(now, free at) + time
    per frame``; a worker not measured yet counts with the median of those that are), fewest sent
    on ties; None when no worker has room (module docstring)."""
    known = sorted(w.frame_s for w in workers if w.frame_s is not None)
    typical = known[len(known) // 2] if known else 0.0
    room = [w for w in workers if w.in_flight < w.capacity]
    if not room:
        return None

    def finish(w: WorkerLoad) -> float:
        return max(now_s, w.free_at_s if w.in_flight else now_s) + (w.frame_s if w.frame_s is not None else typical)

    return min(room, key=lambda w: (finish(w), w.in_flight, w.sent, w.worker_id)).worker_id


class EncoderPool:
    """Workers of the map's embedding space and the frames in flight to them (module docstring)."""

    def __init__(
        self,
        session: zenoh.Session,
        pool_keys: PoolKeys,
        *,
        map_id: str,
        embedding_space: str,
        stats: ServiceStats,
        timeout_s: float = 30.0,
        max_in_flight: int = 2,
    ) -> None:
        self.session = session
        self.keys = pool_keys
        self.map_id = map_id
        self.embedding_space = embedding_space
        self.stats = stats
        self.timeout_s = timeout_s
        self.max_in_flight = max_in_flight
        self.workers: dict[str, PoolWorker] = {}
        self.refused: set[str] = set()
        self.lost = 0
        self._requests: dict[int, _Request] = {}
        self._resend: collections.deque[_Request] = collections.deque()
        self._results: collections.deque[PoolResult] = collections.deque()
        self._lost: collections.deque[EncodeRequest] = collections.deque()  # frames given up on, for the service
        self._next_id = 0
        self._closed = False
        self._cond = threading.Condition()
        self._executor = ThreadPoolExecutor(max_workers=32, thread_name_prefix="pool")
        self.encoded_by: collections.Counter[str] = collections.Counter()
        try:
            self._tokens = session.liveliness().declare_subscriber(
                pool_keys.workers, zenoh.handlers.Callback(self._on_token), history=True
            )
        except zenoh.ZError as exc:
            raise QueryError(
                pool_keys.workers, "bus_error", f"cannot watch the encoder pool: {exc}"
            ) from None

    # workers coming and going
    def _on_token(self, sample: zenoh.Sample) -> None:  # Zenoh thread: hand off, never call Zenoh here
        try:
            worker_id = self.keys.worker_id_of(str(sample.key_expr))
        except ValueError as exc:
            logger.debug("pool: ignoring token %s: %s", sample.key_expr, exc)
            return
        if sample.kind == zenoh.SampleKind.PUT:
            self._submit_task(self._admit, worker_id)
        else:
            self._worker_gone(worker_id, "its liveliness token went away")

    def _submit_task(self, fn, *args) -> None:  # noqa: ANN001
        with self._cond:
            if self._closed:
                return
            self._executor.submit(fn, *args)

    def _admit(self, worker_id: str) -> None:
        try:
            info = get(
                self.session,
                self.keys.info(worker_id),
                WorkerInfoRequest(),
                WorkerInfo,
                timeout_s=INFO_TIMEOUT_S,
                service=f"encoder worker {worker_id}",
            )
        except QueryError as exc:
            logger.warning("pool: encoder worker %s did not say what it holds (%s); not used", worker_id, exc)
            return
        with self._cond:
            if info.embedding_space != self.embedding_space:
                if worker_id not in self.refused:
                    self.refused.add(worker_id)
                    self.stats.incr(PoolCounter.WORKERS_REFUSED)
                    logger.warning(
                        "pool: encoder worker %s holds embedding space %r (%s), but map %r is in %r: "
                        "not used",
                        worker_id,
                        info.embedding_space,
                        info.encoder,
                        self.map_id,
                        self.embedding_space,
                    )
                return
            if worker_id not in self.workers:
                self.workers[worker_id] = PoolWorker(worker_id, info)
                logger.info(
                    "pool: encoder worker %s joined (%s on %s); %d alive",
                    worker_id,
                    info.encoder,
                    info.device,
                    len(self.workers),
                )
            self._publish_alive()
            self._cond.notify_all()

    def _worker_gone(self, worker_id: str, why: str) -> None:
        with self._cond:
            worker = self.workers.pop(worker_id, None)
            if worker is None:
                return
            logger.warning(
                "pool: encoder worker %s is gone (%s); %d frame(s) it held go elsewhere; %d alive",
                worker_id,
                why,
                len(worker.in_flight),
                len(self.workers),
            )
            for rid in sorted(worker.in_flight):
                req = self._requests.pop(rid, None)
                if req is not None:
                    req.abandoned = True
                    self._retry_or_lose(req)
            self._publish_alive()
            self._cond.notify_all()

    def _publish_alive(self) -> None:
        self.stats.set(PoolCounter.ENCODER_WORKERS, len(self.workers))

    def _retry_or_lose(self, req: _Request) -> None:
        """(lock held) Send a failed frame once more, or count it as lost."""
        if req.attempt >= 2:
            self.lost += 1
            self._lost.append(req.request)
            self.stats.incr(PoolCounter.FRAMES_LOST)
            logger.warning("pool: frame %d lost (its workers died twice)", req.request.frame_id)
            return
        self._resend.append(_Request(-1, req.request, "", req.attempt + 1, req.seq))

    # dispatch
    @property
    def alive(self) -> int:
        with self._cond:
            return len(self.workers)

    def _free_worker(self) -> PoolWorker | None:
        """(lock held) The worker the next frame goes to (:func:`pick_worker`), None when none."""
        loads = [
            WorkerLoad(w.worker_id, len(w.in_flight), min(self.max_in_flight, w.info.max_in_flight), w.sent,
                       w.free_at_s, w.frame_s)
            for w in self.workers.values()
        ]
        chosen = pick_worker(loads, time.monotonic())
        return self.workers[chosen] if chosen is not None else None

    def wait_for_capacity(self, timeout_s: float) -> bool:
        """Block until a worker has room (True) or ``timeout_s`` passed (False)."""
        with self._cond:
            return self._cond.wait_for(lambda: self._closed or self._free_worker() is not None, timeout=timeout_s) \
                and not self._closed

    def submit(self, request: EncodeRequest, seq: int) -> bool:
        """Send ``request`` (the service's ``seq``-th frame) to the least-loaded worker; False when
        no worker has room."""
        with self._cond:
            return self._dispatch(request, attempt=1, seq=seq)

    def pump_resends(self, newer_than: int) -> None:
        """Send frames whose worker died to another worker, while there is room; frames whose
        ``seq`` is not newer than ``newer_than`` (a later frame's result is already applied) are
        counted as lost instead."""
        with self._cond:
            while self._resend:
                req = self._resend[0]
                if req.seq <= newer_than:
                    self._resend.popleft()
                    self._lost.append(req.request)
                    self.lost += 1
                    self.stats.incr(PoolCounter.FRAMES_LOST)
                    continue
                if not self._dispatch(req.request, attempt=req.attempt, seq=req.seq):
                    return
                self._resend.popleft()
                self.stats.incr(PoolCounter.FRAMES_RESENT)

    def _dispatch(self, request: EncodeRequest, *, attempt: int, seq: int) -> bool:
        worker = self._free_worker()
        if worker is None or self._closed:
            return False
        rid = self._next_id
        self._next_id += 1
        now = time.monotonic()
        req = _Request(rid, request, worker.worker_id, attempt, seq, sent_at_s=now)
        self._requests[rid] = req
        start = max(now, worker.free_at_s) if worker.in_flight else now
        worker.free_at_s = start + (worker.frame_s or 0.0)
        worker.in_flight.add(rid)
        worker.sent += 1
        self.stats.incr(PoolCounter.FRAMES_DISPATCHED)
        self._executor.submit(self._send, req)
        return True

    def _send(self, req: _Request) -> None:
        reply: EncodeReply | None = None
        error: QueryError | None = None
        try:
            reply = get(
                self.session,
                self.keys.encode(req.worker_id),
                req.request,
                EncodeReply,
                timeout_s=self.timeout_s,
                service=f"encoder worker {req.worker_id}",
            )
        except QueryError as exc:
            error = exc
        with self._cond:
            worker = self.workers.get(req.worker_id)
            if worker is not None:
                worker.in_flight.discard(req.request_id)
                if error is None:
                    # Its time for this frame, queueing behind its previous frame left out.
                    now = time.monotonic()
                    took = now - max(req.sent_at_s, worker.last_done_s)
                    worker.frame_s = took if worker.frame_s is None else (
                        (1 - FRAME_TIME_WEIGHT) * worker.frame_s + FRAME_TIME_WEIGHT * took)
                    worker.last_done_s = now
                    worker.free_at_s = now + worker.frame_s * len(worker.in_flight)
            if req.abandoned or self._requests.pop(req.request_id, None) is None:
                return  # its worker was declared gone; the frame was already sent elsewhere or counted
            if error is None and reply is not None:
                if worker is not None:
                    worker.encoded += 1
                self.encoded_by[req.worker_id] += 1
                self._results.append(PoolResult(req.request, reply, req.worker_id, req.seq))
            else:
                assert error is not None
                logger.warning(
                    "pool: frame %d on worker %s failed: %s", req.request.frame_id, req.worker_id, error
                )
                if error.code == "wrong_space" and worker is not None:
                    self.workers.pop(req.worker_id, None)
                    self.refused.add(req.worker_id)
                    self.stats.incr(PoolCounter.WORKERS_REFUSED)
                    self._publish_alive()
                elif error.code in ("timeout", "bus_error") and worker is not None:
                    # no answer at all: the worker died with the frame (its token may still linger)
                    self.workers.pop(req.worker_id, None)
                    self._publish_alive()
                    for rid in sorted(worker.in_flight):
                        other = self._requests.pop(rid, None)
                        if other is not None:
                            other.abandoned = True
                            self._retry_or_lose(other)
                    self._submit_task(self._readmit_later, req.worker_id)
                self._retry_or_lose(req)
            self._cond.notify_all()

    def _readmit_later(self, worker_id: str) -> None:
        """A worker that timed out may only have been slow: take it back if it still answers."""
        self._admit(worker_id)

    # results
    def take_results(self) -> list[PoolResult]:
        with self._cond:
            out = list(self._results)
            self._results.clear()
            return out

    def take_lost(self) -> list[EncodeRequest]:
        """The frames given up on (counted in ``frames_lost``) since the last call."""
        with self._cond:
            out = list(self._lost)
            self._lost.clear()
            return out

    def wait(self, timeout_s: float) -> None:
        """Block until a result, a worker change or ``timeout_s``."""
        with self._cond:
            if not self._results:
                self._cond.wait(timeout_s)

    def in_flight(self) -> int:
        with self._cond:
            return len(self._requests) + len(self._resend)

    def older_in_flight(self, seq: int) -> bool:
        """Whether a frame taken before the ``seq``-th is still being encoded or waits to go again."""
        with self._cond:
            return (any(r.seq < seq for r in self._requests.values() if not r.abandoned)
                    or any(r.seq < seq for r in self._resend))

    def close(self) -> None:
        with self._cond:
            self._closed = True
            for req in self._requests.values():
                req.abandoned = True
            self._cond.notify_all()
        try:
            self._tokens.undeclare()
        except zenoh.ZError as exc:
            logger.debug("pool token subscriber already undeclared: %s", exc)
        self._executor.shutdown(wait=False, cancel_futures=True)
