"""The semantic service's encoder-pool loop (``semantic.encoder_pool``): frames to the pool's
workers, their results applied to the map in the order the frames were taken.

:class:`PoolDispatch` runs two threads: this one dispatches (the best candidate with
``select=coverage``, the next frame off the subscription otherwise) whenever a worker has room,
encoding here while no worker is alive and a local encoder is configured; the other applies the
workers' results in frame order (:meth:`PoolDispatch._apply_loop`). The pool's bookkeeping (workers,
in flight, resends) is :class:`~openfusion.services.semantic.pool.EncoderPool`; fusing one result
is the service's :meth:`~openfusion.services.semantic.service.SemanticService.apply_observation`.
"""

from __future__ import annotations

import heapq
import itertools
import logging
import threading
import time
from typing import Any

import numpy as np

from openfusion.bus import QueryError, ServiceRunner
from openfusion.encoders import RegionObservation
from openfusion.services.semantic.outcomes import count_embedded
from openfusion.services.semantic.pool import EncoderPool, PoolResult
from openfusion.services.semantic.selection import Pending
from openfusion.wire.counters import ENCODED_BY_PREFIX, PoolCounter, SemanticCounter
from openfusion.wire.schemas import EncodeRequest, RgbdFrame

logger = logging.getLogger(__name__)


class PoolDispatch:
    """The semantic service's loop with an encoder pool (module docstring). ``service``: the
    :class:`~openfusion.services.semantic.service.SemanticService` (typed as Any: importing it here
    would be an import cycle); it owns the subscription, the candidate window, the dictionary and
    the order frames are taken in (``_next_seq``)."""

    def __init__(self, service: Any, pool: EncoderPool) -> None:
        self.service = service
        self.pool = pool
        self._last_applied = -1  # the seq of the newest frame whose result was applied
        # Results waiting for frames taken before them, still in flight: (seq, arrival order, arrived at, result).
        self._held: list[tuple[int, int, float, PoolResult]] = []
        self._arrivals = itertools.count()
        self._waited: set[int] = set()  # arrival numbers of held results already counted as held

    def run(self, runner: ServiceRunner) -> None:
        """Frames go to the pool's workers, at most ``max_in_flight`` per worker, the newest frame
        whenever one has room; results are applied in frame order: a result whose older frames
        are still in flight waits for them up to ``pool_reorder_wait_s`` (``results_held``), and
        an older result than one applied is dropped and counted (``results_stale``); with no worker alive the local encoder (if configured)
        takes the frames, else they are skipped and health says ``no_encoder``.

        Results are applied on a thread of their own (:meth:`_apply_loop`): applying one asks
        geometry for a render, and while this loop waited on it no worker got a new frame (with
        four workers on two cores, about a third of their time went idle that way)."""
        assert self.service._frames is not None
        stats = runner.stats
        applier = threading.Thread(target=self._apply_loop, args=(runner,), name="semantic-apply", daemon=True)
        applier.start()
        try:
            while not runner.stopping:
                try:
                    self._pool_step(runner)
                except Exception:  # a failure of the loop itself never ends the service: logged, counted
                    logger.exception("semantic: a step of the encoder pool loop failed; going on")
                    stats.add_error()
        finally:
            applier.join(timeout=max(self.service.section.render_timeout_s, 1.0) + 1.0)

    def _apply_loop(self, runner: ServiceRunner) -> None:
        """Apply the pool's results in frame order as they come (the thread :meth:`run` starts)."""
        while not runner.stopping:
            try:
                self._apply_step(runner)
            except Exception:  # (a result's own failure is counted in _apply_pool_result) logged, counted
                logger.exception("semantic: applying the encoder pool's results failed; going on")
                runner.stats.add_error()

    def _apply_step(self, runner: ServiceRunner) -> None:
        now = time.monotonic()
        for lost in self.pool.take_lost():  # frames the pool gave up on are done with too
            if self.service._feeder is not None:
                self.service._frame_done(runner, lost)
        for result in self.pool.take_results():
            runner.stats.incr(SemanticCounter.ENCODER_CALLS)
            reply = result.reply
            n = len(reply.conf_maps)
            count_embedded(runner.stats, n, n if reply.embedded is None else int(np.count_nonzero(reply.embedded)))
            heapq.heappush(self._held, (result.seq, next(self._arrivals), now, result))
        self._release_results(runner)
        self.pool.wait(0.2)  # a result, a worker change, or the reorder wait's next check

    def _pool_step(self, runner: ServiceRunner) -> None:
        """One turn of :meth:`run`: re-send, then dispatch or encode one frame (the best
        candidate with ``select=coverage``: the pool takes from the same window when it has more
        candidates than free workers)."""
        assert self.service._frames is not None
        stats = runner.stats
        self.pool.pump_resends(self._last_applied)
        alive = self.pool.alive
        stats.set(PoolCounter.NO_ENCODER, int(alive == 0 and not self.service.section.local_encoder))
        if alive == 0 and self.service.section.local_encoder:
            before = self.service._next_seq
            self.service._local_step(runner)
            if self.service._next_seq != before:  # a frame was taken and encoded here
                stats.incr(PoolCounter.LOCAL_FRAMES)
                self._last_applied = self.service._next_seq
            return
        if not self.pool.wait_for_capacity(0.2):
            return
        if self.service._feeder is not None:
            pending = self.service._feeder.take(runner, timeout_s=0.05)
            if pending is None:
                return
            msg = pending.msg
        else:
            pending = None
            msg = self.service.next_frame(runner, timeout_s=0.05)
            if msg is None:
                return
        try:
            self._dispatch(runner, msg, pending)
        except Exception:  # this frame is done with: logged, counted as failed
            logger.exception("semantic: frame %d could not go to the encoder pool; skipped", msg.frame_id)
            stats.incr(SemanticCounter.FRAMES_FAILED)
            stats.add_error()
            self.service._frame_done(runner, msg)

    def _dispatch(self, runner: ServiceRunner, msg: RgbdFrame, pending: Pending | None) -> None:
        """Send one frame taken off the window (``pending``) or the subscription to a worker."""
        if pending is not None:
            embed_where, embed_share = self.service.embed_gate(pending.wanted_px)
            request: EncodeRequest | None = EncodeRequest.of(
                msg, pending.instance, map_id=runner.keys.map_id,
                embedding_space=self.service.dictionary.embedding_space, embed_where=embed_where,
                embed_share=embed_share)
        else:
            request = self._pool_request(runner, msg)
        if request is None:
            self.service._frame_done(runner, msg)
            return
        self.service._next_seq += 1
        if not self.pool.submit(request, self.service._next_seq):  # the worker with room died in between
            runner.stats.incr(SemanticCounter.FRAMES_FAILED)
            self.service._frame_done(runner, msg)

    def _release_results(self, runner: ServiceRunner) -> None:
        """Apply held results in the order their frames were taken; one whose earlier frames are
        still in flight waits for them up to ``pool_reorder_wait_s`` (a result that comes after a
        later one was applied is dropped as stale by :meth:`_apply_pool_result`)."""
        while self._held:
            seq, order, arrived, result = self._held[0]
            if (self.pool.older_in_flight(seq)
                    and time.monotonic() - arrived < self.service.section.pool_reorder_wait_s):
                if order not in self._waited:
                    self._waited.add(order)
                    runner.stats.incr(PoolCounter.RESULTS_HELD)
                return
            heapq.heappop(self._held)
            self._waited.discard(order)
            self._apply_pool_result(runner, result)

    def _pool_request(self, runner: ServiceRunner, msg: RgbdFrame) -> EncodeRequest | None:
        """The encode request of a frame the switch accepts (joined with its instance image when the
        workers need it), or None when the frame is skipped (counted)."""
        if not self.service.switch.accept(msg.frame_id, time.monotonic()):
            runner.stats.incr(SemanticCounter.SKIPPED_SWITCH)
            return None
        instance = None
        if self.service._instances is not None and msg.instance is None:
            instance = self.service._instances.take(msg, timeout_s=self.service.section.instance_wait_s)
            if instance is None:
                self.service._skip_without_instance(runner, msg)
                return None
        return EncodeRequest.of(msg, instance, map_id=runner.keys.map_id,
                                embedding_space=self.service.dictionary.embedding_space)

    def _apply_pool_result(self, runner: ServiceRunner, result: PoolResult) -> None:
        frame_id = result.request.frame_id
        if result.seq <= self._last_applied:  # a later frame's result is in the map already
            runner.stats.incr(PoolCounter.RESULTS_STALE)
            if self.service._feeder is not None:  # the watermark waits for every frame taken
                self.service._frame_done(runner, result.request)
            return
        try:
            obs = RegionObservation(conf_maps=result.reply.conf_maps, embeddings=result.reply.embeddings,
                                    embedding_space=result.reply.embedding_space, embedded=result.reply.embedded)
            obs.validate(dim=self.service.dictionary.dim)
            self.service.apply_observation(runner, result.request.to_frame(), obs, time.monotonic(),
                                           robot=result.request.robot)
            self._last_applied = result.seq
            runner.stats.incr(ENCODED_BY_PREFIX + result.worker_id)
        except QueryError as exc:
            self.service._skip_no_render(runner, result.request.robot, frame_id, exc)
        except Exception:  # a bad result or a failed step: logged, counted, next result
            logger.exception("semantic: the pool's result for frame %d failed and was skipped", frame_id)
            runner.stats.incr(SemanticCounter.FRAMES_FAILED)
            runner.stats.add_error()
        finally:
            self.service._frame_done(runner, result.request)
