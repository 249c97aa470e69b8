"""The semantic service's side of frame selection (``semantic.select = coverage``): candidates in,
the best one out when the encoder is free.

A thread of its own (:meth:`CandidateFeeder.run`) takes every frame off the ``sensor/rgbd``
subscription (a queue of ``select_window`` frames, not latest-only), applies the semantic switch,
joins the frame with its instance image when the encoder reads them, asks geometry for a render of
the map at the frame's pose at the scored size (``geometry/render``, ``select_width_px`` wide) and
offers the prepared view to the :class:`~openfusion.mapping.selection.CandidateWindow`, which
decides it at once with the rule of the in-process pipeline (so the services choose the frames one
process would; with ``select_lookahead`` K > 1 it decides K frames at a time, and a run cut short
because frames stopped coming for 0.2 s is decided then). The encoding side (the service loop with its local encoder, or the encoder pool's
dispatch) takes the chosen frame of highest gain whenever it is free; a frame that adds too little
is dropped without being encoded (``skipped_no_gain``), a chosen one a full window lets go for
frames of higher gain is counted in ``select_evicted``. Scoring on its own thread keeps the encoder busy: scoring the frames that
came during one encoder call costs a render request each, and with the local encoder those
requests would otherwise wait for, and delay, the next call. A candidate whose camera stands still
reuses the render of its robot's last one (:mod:`openfusion.mapping.still_views`; the service's
labels version: the updates it sent and its dictionary's version), counted in ``renders_reused``.

``last_frame_handled`` (the counter tests and tools wait on) keeps its meaning under selection,
where frames leave the window out of order: it is the newest frame taken off the subscription
such that it and every frame taken before it are done with (encoded, or skipped for a counted
reason): :class:`HandledFrames`.

The rules and the scorer are library code (:mod:`openfusion.mapping.selection`); this module only
wires them to the bus.
"""

from __future__ import annotations

import collections
import logging
import threading
import time
from collections.abc import Callable, Hashable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any

import numpy as np

from openfusion.bus import QueryError, ServiceRunner, Subscriber
from openfusion.bus.instance_join import InstanceBuffer
from openfusion.frame import CameraIntrinsics
from openfusion.mapping.selection import CandidateWindow, CoverageScorer, ViewEvidence, WindowChange
from openfusion.wire.counters import SemanticCounter
from openfusion.wire.schemas import InstanceFrame, RenderRequest, RgbdFrame

logger = logging.getLogger(__name__)

#: Frames being rendered and scored at once. Through the services a candidate's render (64 px
#: wide, 1.7 ms of ray casting) took 35-195 ms on a loaded 2-core box, almost all of it waiting:
#: in geometry's queue behind integrations, on the bus, for the interpreter; one at a time, the
#: scoring thread fell behind a 30 fps camera and the subscription dropped frames (21-32 of 90 on
#: the bench scene). Renders in flight overlap those waits; 3 keeps up with 30 fps there.
RENDERS_IN_FLIGHT = 3


class HandledFrames:
    """The ``last_frame_handled`` watermark: frames are announced as they are taken off the
    subscription and marked done in any order; :meth:`done` returns the newest frame id whose
    frame and every frame announced before it are done (None when that did not move). A frame is
    (robot, frame id, stamp), and done marks are counted: two robots replaying one source send
    frames with equal ids and stamps, and with one mark for both the watermark stopped for good."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._order: collections.deque[tuple[str, int, int]] = collections.deque()  # in arrival order
        self._done: collections.Counter[tuple[str, int, int]] = collections.Counter()

    def arrived(self, robot: str, frame_id: int, stamp_ns: int) -> None:
        with self._lock:
            self._order.append((robot, frame_id, stamp_ns))

    def done(self, robot: str, frame_id: int, stamp_ns: int) -> int | None:
        with self._lock:
            self._done[(robot, frame_id, stamp_ns)] += 1
            mark = None
            while self._order and self._done[self._order[0]] > 0:
                head = self._order.popleft()
                self._done[head] -= 1
                if not self._done[head]:
                    del self._done[head]
                mark = head[1]
            return mark

    @property
    def pending(self) -> int:
        with self._lock:
            return len(self._order)


@dataclass(eq=False)  # compared by identity (arrays inside)
class Pending:
    """A candidate's payload: the frame as it came and its instance image (when the encoder reads them)."""

    msg: RgbdFrame
    instance: InstanceFrame | None
    #: the pixels worth an embedding (set when the window hands it out: the selection's decision,
    #: :mod:`openfusion.mapping.region_gate`); None: every region is embedded
    wanted_px: np.ndarray | None = None


@dataclass(eq=False)
class Scoring:
    """A frame whose render (and scoring) is under way on the scoring pool."""

    msg: RgbdFrame
    instance: InstanceFrame | None
    evidence: Future  # -> ViewEvidence (raises QueryError when geometry gave no render)


class CandidateFeeder:
    """Frames off the subscription -> scored candidates in the window (module docstring).

    ``render(request) -> RenderReply`` asks geometry (the service passes its geometry reader);
    up to :data:`RENDERS_IN_FLIGHT` frames are being rendered at once, and are offered to the
    window in the order they came."""

    def __init__(
        self,
        *,
        frames: Subscriber[RgbdFrame],
        window: CandidateWindow[Pending],
        scorer: CoverageScorer,
        accept: Any,
        render: Callable[[RenderRequest], Any],
        instances: InstanceBuffer | None,
        instance_wait_s: float,
        on_no_instance: Any,
        on_no_render: Any,
        renders_in_flight: int = RENDERS_IN_FLIGHT,
        labels_version: Callable[[], Hashable] | None = None,
        after_update: Callable[[], dict[str, Any]] | None = None,
    ) -> None:
        self.frames = frames
        self.window = window
        self.scorer = scorer
        self.accept = accept  # (frame id, now) -> bool: the semantic switch
        self.render = render
        self.instances = instances
        self.instance_wait_s = instance_wait_s
        self.on_no_instance = on_no_instance  # (runner, msg): counts and logs a frame without its instance image
        self.on_no_render = on_no_render  # (runner, robot, frame id, QueryError): counts and logs an unscored frame
        self.renders_in_flight = max(1, renders_in_flight)
        #: () -> a value that changes with the map's labels: given, a still camera's candidates reuse
        #: its last render (openfusion.mapping.still_views); None: every candidate is rendered
        self.labels_version = labels_version
        #: () -> the RenderRequest fields of the last update this service sent (``after_update_*``): a
        #: taken frame's second render waits for geometry to apply it (:meth:`_wanted_now`)
        self.after_update = after_update
        self.handled = HandledFrames()

    def run(self, runner: ServiceRunner) -> None:
        """Feed the window until the service stops (a thread of the service): frames are taken
        off the subscription while fewer than ``renders_in_flight`` are being scored, and
        offered in the order they came."""
        scoring: collections.deque[Scoring] = collections.deque()
        pool = ThreadPoolExecutor(max_workers=self.renders_in_flight, thread_name_prefix="semantic-score")
        try:
            while not runner.stopping:
                msg = None
                while len(scoring) < self.renders_in_flight:
                    msg = self.frames.recv(timeout_s=0.0 if scoring else 0.2)
                    if msg is None:
                        break
                    started = self._guarded(runner, msg, lambda m=msg: self.start(runner, m, pool))
                    if started is not None:
                        scoring.append(started)
                if scoring:
                    head = scoring.popleft()
                    self._guarded(runner, head.msg, lambda h=head: self.offer(runner, h))
                elif msg is None and self.window.undecided:  # frames paused: a run cut short is decided now
                    self.account(runner, self.window.flush())
        finally:
            pool.shutdown(wait=False, cancel_futures=True)

    def _guarded(self, runner: ServiceRunner, msg: RgbdFrame, step: Callable[[], Scoring | None]) -> Scoring | None:
        try:
            return step()
        except Exception:  # one frame's failure never ends the feeding: logged, counted, next frame
            logger.exception("semantic: scoring frame %d failed; it is skipped", msg.frame_id)
            runner.stats.incr(SemanticCounter.FRAMES_FAILED)
            runner.stats.add_error()
            self.finish(runner, msg)
            return None

    def start(self, runner: ServiceRunner, msg: RgbdFrame, pool: ThreadPoolExecutor) -> Scoring | None:
        """A frame off the subscription: the switch, its instance image, then its render and
        scoring on ``pool``; None when it is not a candidate (counted, done with)."""
        stats = runner.stats
        self.handled.arrived(msg.robot, msg.frame_id, msg.stamp_ns)
        if not self.accept(msg.frame_id, time.monotonic()):
            stats.incr(SemanticCounter.SKIPPED_SWITCH)
            self.finish(runner, msg)
            return None
        instance = None
        if self.instances is not None and msg.instance is None:
            instance = self.instances.take(msg, timeout_s=self.instance_wait_s)
            stats.set(SemanticCounter.INSTANCES_EVICTED, self.instances.evicted)
            if instance is None:
                self.on_no_instance(runner, msg)
                self.finish(runner, msg)
                return None
        return Scoring(msg, instance, pool.submit(self._prepare, runner, msg))

    def offer(self, runner: ServiceRunner, scoring: Scoring) -> None:
        """Offer a scored frame to the window (or count why it was not scored)."""
        msg = scoring.msg
        try:
            evidence, busy_s = scoring.evidence.result()
        except QueryError as exc:  # no render (geometry gone, or the robot not joined yet): not scored
            self.on_no_render(runner, msg.robot, msg.frame_id, exc)
            self.finish(runner, msg)
            return
        started = time.monotonic()
        change = self.window.offer(evidence, Pending(msg, scoring.instance))
        runner.stats.incr(SemanticCounter.SELECT_BUSY_S, busy_s + time.monotonic() - started)
        runner.stats.incr(SemanticCounter.FRAMES_SCORED)
        self.account(runner, change)

    def _prepare(self, runner: ServiceRunner, msg: RgbdFrame) -> tuple[Any, float]:
        """(on the scoring pool) The frame's evidence and the seconds it took."""
        started = time.monotonic()
        version = self.labels_version() if self.labels_version is not None else None
        evidence = self.scorer.prepare_frame(msg.to_frame(), self._render_for(msg), robot=msg.robot,
                                             labels_version=version)
        runner.stats.set(SemanticCounter.RENDERS_REUSED, self.scorer.still.reused)
        return evidence, time.monotonic() - started

    def _render_for(self, msg: RgbdFrame, *, after_updates: bool = False) -> Callable[..., Any]:
        """``render(T_world_cam, K_small[, depth_m])`` of the map for ``msg`` (a geometry request);
        ``after_updates``: once geometry has applied the updates this service sent."""
        wait = self.after_update() if after_updates and self.after_update is not None else {}

        def render(T_world_cam: Any, K_small: CameraIntrinsics, depth_m: np.ndarray | None = None) -> Any:
            # with the candidate's depth (select_view auto / probe) geometry may probe rather than ray-cast
            probe = None if depth_m is None else np.clip(
                np.nan_to_num(np.asarray(depth_m, np.float32), nan=0.0, posinf=0.0, neginf=0.0), 0.0, None)
            return self.render(RenderRequest(
                frame_id=msg.frame_id, T_world_cam=T_world_cam, robot=msg.robot, probe_depth_m=probe,
                probe_above_blocks=self.scorer.params.probe_above_blocks or 0, **wait,
                **RenderRequest.intrinsics_fields(K_small)))

        return render

    def _wanted_now(self, runner: ServiceRunner, pending: Pending, evidence: ViewEvidence) -> np.ndarray | None:
        """The chosen frame's wanted pixels against the map as it is when the encoder takes it
        (:meth:`CoverageScorer.wanted_now`: the frames taken before it have labelled and settled
        much of what its render showed); as decided when geometry gives no render."""
        if evidence.wanted_base is None:
            return evidence.wanted_px
        try:
            key_map, conf_map = self.scorer.render_again(pending.msg.to_frame(),
                                                         self._render_for(pending.msg, after_updates=True))
        except QueryError as exc:
            runner.stats.incr(SemanticCounter.WANTED_RENDER_FAILURES)
            logger.debug("frame %s: no render for its wanted pixels (%s); the decision's are used",
                         pending.msg.frame_id, exc)
            key_map = conf_map = None
        wanted = self.scorer.wanted_now(evidence, key_map, conf_map)
        self.scorer.embedding_in_flight(evidence, key_map, wanted)  # until finish() releases it
        return wanted

    def take(self, runner: ServiceRunner, timeout_s: float) -> Pending | None:
        """The best candidate for the encoder now (waiting up to ``timeout_s``), or None."""
        change = self.window.take(timeout_s)
        self.account(runner, change)
        if change.taken is None:
            return None
        pending = change.taken.payload
        pending.wanted_px = self._wanted_now(runner, pending, change.taken.evidence)
        return pending

    def account(self, runner: ServiceRunner, change: WindowChange[Pending]) -> None:
        """Count the candidates that left without being encoded; they are done with."""
        for cand in change.no_gain:
            runner.stats.incr(SemanticCounter.SKIPPED_NO_GAIN)
            self.finish(runner, cand.payload.msg)
        for cand in change.evicted:
            runner.stats.incr(SemanticCounter.SELECT_EVICTED)
            self.finish(runner, cand.payload.msg)
        runner.stats.set(SemanticCounter.SELECT_WINDOW, len(self.window))

    def finish(self, runner: ServiceRunner, msg: RgbdFrame) -> None:
        """``msg`` is done with (encoded and its update sent, failed or skipped): the surface it
        was chosen for is no longer held for it (:meth:`CoverageScorer.hold`), and
        ``last_frame_handled`` moves."""
        self.scorer.release(msg.frame_id, msg.stamp_ns / 1e9, msg.robot)
        mark = self.handled.done(msg.robot, msg.frame_id, msg.stamp_ns)
        if mark is not None:
            runner.stats.set(SemanticCounter.LAST_FRAME_HANDLED, mark)
