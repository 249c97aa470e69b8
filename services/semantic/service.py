"""Semantic service: region encoder + matcher at its own rate; owns the region dictionary.

| key | direction | message |
|---|---|---|
| ``…/sensor/rgbd`` | subscribes (``select``: a window of candidates, the latest frame only, or a queue) | :class:`~openfusion.wire.schemas.RgbdFrame` |
| ``…/sensor/instance`` | subscribes when the encoder reads instance images (gt) | :class:`~openfusion.wire.schemas.InstanceFrame` |
| ``…/geometry/progress`` | subscribes (which frames geometry has integrated: a frame is rendered for its update after) | :class:`~openfusion.wire.schemas.GeometryProgress` |
| ``…/geometry/render`` | queries (each frame it encodes; with ``select=coverage`` also each candidate, at the scored size, with its depth: a probe, ``select_view``) | RenderRequest → RenderReply |
| ``…/geometry/dictionary`` | queries once on start (recovery) | DictionaryRequest → DictionarySnapshot |
| ``…/geometry/contacts`` | queries every ``merge_every`` semantic frames | RegionContactsRequest → RegionContactsReply |
| ``…/semantic/update`` | publishes | :class:`~openfusion.wire.schemas.SemanticUpdate` |
| ``…/semantic/dictionary/delta`` | publishes | :class:`~openfusion.wire.schemas.DictionaryDelta` |
| ``…/semantic/dictionary`` | queryable | DictionaryRequest → DictionarySnapshot (with its merge table) |
| ``…/semantic/merge`` | queryable (geometry asks before it saves) | MergeRequest → MergeReply |
| ``…/health/semantic`` | liveliness + stats | counters ``semantic_frames``, ``skipped_switch``, ``skipped_no_instance``, ``regions``, ``matched``, ``new_regions``, ``merge_passes``, ``regions_merged``, ``regions_pruned``, ``merge_failures``, ``encoder_calls``, ``encoder_regions``, ``frames_scored``, ``skipped_no_gain``, ``select_evicted``, ``select_busy_s``, ``select_window``, ``renders_reused`` (candidates of a still camera scored on its last render), ``wanted_render_failures`` (a taken frame rendered again for its wanted pixels got no render: the decision's pixels were used); what became of each frame: ``frames_received``, ``frames_dropped``, ``frames_superseded``, ``frames_malformed``, ``frames_pending`` (:mod:`~openfusion.services.semantic.outcomes`), ``integrate_wait_timeouts``, ``step_render_retries`` (an encoded frame's render asked again after a timeout) |

Which frames are encoded (``select``, :class:`~openfusion.mapping.params.SelectParams`): with
``coverage`` (the default) a thread of its own scores every frame against the map
(:mod:`openfusion.services.semantic.selection`, rules in :mod:`openfusion.mapping.selection`) and
decides each as it comes with the in-process rule; the chosen frames wait in a window of
``select_window`` and the encoder (here, or the pool's workers) gets the one of highest gain
whenever it is free, and a frame that adds too little is never encoded (``skipped_no_gain``). With ``latest`` the
newest frame geometry has integrated (:mod:`~openfusion.services.semantic.geometry_progress`; the
ones passed over are ``frames_superseded``), with ``every`` a queue of frames. Any frame is
rendered for its update once geometry has integrated it (``integrate_wait_s`` at most). Either way a slow
encoder never builds an unbounded queue: frames a full queue or window lets go are counted. An encoder that reads ground-truth instance images (gt) gets each
frame joined with its ``InstanceFrame`` (same frame id and stamp; the bridge sends it first); a
frame whose instance image has not come within ``instance_wait_s`` is skipped and counted in
``skipped_no_instance`` (a frame that carries its own instance image uses that). The semantic switch: ``every_k = 0`` turns semantics off,
``every_k = k`` uses every k-th frame (by frame id), ``max_hz`` caps the rate.
The settings and the switch are :mod:`~openfusion.services.semantic.section`; the loop with an
encoder pool is :mod:`~openfusion.services.semantic.pool_loop`; periodic merge passes run on
:mod:`~openfusion.services.semantic.merge_worker`'s thread, off the frame loop.
On start the service asks geometry for the dictionary it checkpointed, so a restarted semantic
service continues with the same keys and embeddings.

Merges (:mod:`openfusion.mapping.merging`, parameters ``merge_*`` of :class:`MergeParams`): every
``merge_every`` semantic frames the service asks geometry (which owns the voxels) which regions
touch, decides in its dictionary which of them are one object, and publishes the merges as one
dictionary delta (``removed_keys`` + ``merged_into``). Geometry relabels the merged keys' voxels
and its replica follows, as does the query service's; a restarted semantic service recovers the
merged dictionary from geometry. A pass geometry does not answer is skipped and counted
(``merge_failures``); mapping goes on. A region without a labelled voxel in two passes in a row
(seen once, then taken over by other regions; it can never be matched again) is removed in the
same delta (``merged_into`` -1, ``regions_pruned``). Geometry asks ``semantic/merge`` for a pass
before it saves a map (``GeometrySection.merge_on_save``), so a saved map is merged; the reply
names the dictionary version after the pass and is sent after its delta. The dictionary is changed
under one lock by the frame loop and by that request, so deltas go out in version order.
"""

from __future__ import annotations

import logging
import threading
import time
import uuid
from typing import Any

import numpy as np
import zenoh

from openfusion.bus import Publisher, QueryError, ServiceRunner, Subscriber
from openfusion.bus.instance_join import InstanceBuffer
from openfusion.encoders import RegionObservation
from openfusion.frame import Frame, resize_nearest
from openfusion.mapping import RegionDictionary, RenderedView, plan_update
from openfusion.mapping.merging import EmptyRegions, MergeSchedule, RegionContacts, apply_merges, plan_merges
from openfusion.mapping.params import MatchParams, MergeParams, SelectParams
from openfusion.mapping.region_gate import encode_where
from openfusion.mapping.selection import CandidateWindow, CoverageScorer
from openfusion.services.common import ServiceDefinition
from openfusion.services.encoder.options import (
    encoder_identity_from_section,
    region_encoder_from_section,  # noqa: F401 (re-exported: bench/bench_laps.py)
    warm_up_encoder,
)
from openfusion.services.semantic.geometry_progress import IntegratedFrames, NewestTaken
from openfusion.services.semantic.merge_worker import MergeWorker
from openfusion.services.semantic.outcomes import FrameCounts, count_embedded
from openfusion.services.semantic.pool import EncoderPool
from openfusion.services.semantic.pool_loop import PoolDispatch
from openfusion.services.semantic.section import (  # noqa: F401 (re-exported: the service's settings lived here)
    EVERY_QUEUE,
    INSTANCE_MARGIN,
    LATEST_BUFFER,
    LATEST_QUEUE,
    SemanticConfig,
    SemanticSection,
    SemanticSwitch,
)
from openfusion.services.semantic.selection import CandidateFeeder, Pending
from openfusion.shard_client import reader_for
from openfusion.wire.counters import PoolCounter, SemanticCounter
from openfusion.wire.endpoints import (
    DICTIONARY_DELTA,
    GEOMETRY_PROGRESS,
    SEMANTIC_DICTIONARY,
    SEMANTIC_MERGE,
    SEMANTIC_UPDATE,
    SENSOR_INSTANCE,
    SENSOR_RGBD,
)
from openfusion.wire.keys import PoolKeys
from openfusion.wire.schemas import (
    DictionaryRequest,
    DictionarySnapshot,
    InstanceFrame,
    MergeReply,
    MergeRequest,
    RegionContactsRequest,
    RenderReply,
    RenderRequest,
    RgbdFrame,
    SemanticUpdate,
)
from openfusion.wire.schemas.base import DEFAULT_ROBOT

logger = logging.getLogger(__name__)


class SemanticService:
    """Encoder → render request → match → update; the dictionary lives here."""

    def __init__(self, config: SemanticConfig, *, encoder: Any = None) -> None:
        self.config = config
        self.section = config.semantic
        if encoder is None and self.section.encoder_pool and not self.section.local_encoder:
            # Only the pool's workers encode: the map's space and size are all this service needs.
            encoder = encoder_identity_from_section(self.section)
            if encoder is not None:
                logger.info("semantic: no local encoder (the pool encodes); map space %s, %d-d",
                            encoder.embedding_space, encoder.dim)
        self.encoder = encoder if encoder is not None else region_encoder_from_section(self.section)
        self.dictionary = RegionDictionary(self.encoder.embedding_space, self.encoder.dim)
        self.match_params = MatchParams.from_section(self.section)
        self.merge_params = MergeParams.from_section(self.section)
        self._merge_schedule = MergeSchedule(self.merge_params, min_interval_s=self.section.merge_min_interval_s)
        self._empty_regions = EmptyRegions()
        self._merges = MergeWorker(on_error=self._count_merge_error)
        self._integrated = IntegratedFrames()  # geometry's acknowledgements (geometry/progress)
        self._newest: NewestTaken | None = None  # select=latest (setup)
        self._stats: Any = None  # the runner's stats, for the merge worker's errors (set in setup)
        self.switch = SemanticSwitch(self.section.every_k, self.section.max_hz)
        self.select_params = SelectParams.from_section(self.section)
        # coverage: candidates are scored on a thread of their own (selection.CandidateFeeder)
        self._scorer = CoverageScorer(self.select_params) if self.select_params.select == "coverage" else None
        if self._scorer is not None:
            self._scorer.embedding_support = self._embedding_support
        self._feeder: CandidateFeeder | None = None
        self._next_seq = 0  # the order frames are taken for the encoder in (pool results apply in it)
        self._frames: Subscriber[RgbdFrame] | None = None
        # Instance images for every frame the frame queue may hold, and some: a frame at the head of a
        # full queue still finds its image (a buffer no deeper than the queue evicted it, and the frame
        # was then skipped; InstanceBuffer.take no longer waits for an image that is gone).
        self._instances: InstanceBuffer | None = (
            InstanceBuffer(capacity=self._frame_queue_size() + INSTANCE_MARGIN) if self.encoder.needs_instances else None)
        self._update_pub: Publisher | None = None
        self._delta_pub: Publisher | None = None
        self._published_version = self.dictionary.version
        # Updates are numbered per process; a frame's render asks geometry to apply the last one first
        # (services.geometry.applied_updates)
        self._update_source = uuid.uuid4().hex[:16]
        self._updates_sent = 0
        self._frames_without_instance = 0
        self._pool: EncoderPool | None = None
        # Held while the dictionary changes and its delta is published: the frame loop and a
        # merge requested on semantic/merge (another thread) change it.
        self._dictionary_lock = threading.RLock()

    def recover(self, runner: ServiceRunner) -> bool:
        """Take the dictionary geometry checkpointed (same space only). True when recovered."""
        if self.section.recover_timeout_s <= 0:
            return False
        # Right after joining, routes to geometry's queryable may not be known yet: a get then
        # finds nobody at once. Retry until the deadline; a refusal (no dictionary) is final.
        deadline = time.monotonic() + self.section.recover_timeout_s
        while True:
            try:
                snap = reader_for(runner).dictionary(DictionaryRequest(),
                                                     timeout_s=max(0.5, min(3.0, deadline - time.monotonic())))
                break
            except QueryError as exc:
                if exc.code != "timeout" or time.monotonic() >= deadline:
                    logger.info("semantic: no dictionary to recover (%s); starting empty", exc.reason)
                    return False
                time.sleep(0.3)
        if snap.embedding_space != self.dictionary.embedding_space:
            logger.error("semantic: the map's dictionary is in space %r but the encoder is %r; starting empty "
                         "(a new map id is safer)", snap.embedding_space, self.dictionary.embedding_space)
            runner.stats.add_error()
            return False
        self.dictionary = RegionDictionary.from_snapshot(snap)
        self._published_version = self.dictionary.version
        logger.info("semantic: recovered %d regions (version %d) from geometry", len(self.dictionary),
                    self.dictionary.version)
        return True

    def _frame_queue_size(self) -> int:
        """Frames ``sensor/rgbd``'s subscription holds per robot (coverage: the candidate window's size)."""
        return {"coverage": self.select_params.select_window, "every": EVERY_QUEUE,
                "latest": LATEST_QUEUE}[self.select_params.select]

    def _embedding_support(self, keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        with self._dictionary_lock:  # called while a candidate is prepared, never under the scorer's lock
            return self.dictionary.support_of(keys)

    def embed_gate(self, wanted_px: np.ndarray | None) -> tuple[np.ndarray | None, float | None]:
        """``(wanted_px, min_share)`` for a chosen frame's encoder call: ``(None, None)`` (every
        region embedded) without a wanted mask or with ``select_embed_share`` none."""
        share = self.select_params.select_embed_share
        return (None, None) if wanted_px is None or share is None else (wanted_px, share)

    def handle_snapshot(self, _req: DictionaryRequest) -> DictionarySnapshot:
        with self._dictionary_lock:
            return self.dictionary.snapshot()

    def handle_merge(self, runner: ServiceRunner, _req: MergeRequest) -> MergeReply:
        """A merge pass now (geometry asks before saving); its delta is published before the reply."""
        return self._merges.run_now(lambda: self._merge(runner))

    def process(self, runner: ServiceRunner, msg: RgbdFrame, instance: InstanceFrame | None = None,
                wanted_px: np.ndarray | None = None) -> None:
        """One semantic step for one frame (called from the loop), with its instance image when
        the encoder reads them; ``wanted_px``: the selection's pixels worth an embedding (None:
        every region, :mod:`openfusion.mapping.region_gate`)."""
        started = time.monotonic()
        frame = msg.to_frame(instance)
        runner.stats.incr(SemanticCounter.ENCODER_CALLS)
        obs = encode_where(self.encoder, frame, *self.embed_gate(wanted_px))
        count_embedded(runner.stats, obs.num_regions, obs.num_embedded)
        self.apply_observation(runner, frame, obs, started, robot=msg.robot)

    def apply_observation(self, runner: ServiceRunner, frame: Frame, obs: RegionObservation, started: float, *,
                          robot: str = DEFAULT_ROBOT) -> None:
        """Render the map at the frame's pose, match, update the dictionary, send the update.
        ``robot``: whose frame it is (its pose is in that robot's odometry frame; geometry joins it)."""
        h, w = obs.conf_maps.shape[1:] if obs.conf_maps.ndim == 3 else self.encoder.output_size(
            frame.intrinsics.height_px, frame.intrinsics.width_px)
        K_small = frame.intrinsics.scaled(w, h)
        # Render once geometry holds the frame (services.semantic.geometry_progress)
        if (self.section.integrate_wait_s > 0
                and not self._integrated.wait(robot, frame.stamp_ns, self.section.integrate_wait_s)):
            runner.stats.incr(SemanticCounter.INTEGRATE_WAIT_TIMEOUTS)
        # ... and has applied the update sent before it (that frame's labels: matched, not made again)
        # With the frame's depth, geometry probes it on a large map instead of ray-casting (step_probe_blocks)
        depth_m = resize_nearest(frame.depth_m(), (h, w)).astype(np.float32)
        probe_above = self.match_params.step_probe_blocks
        request = RenderRequest(frame_id=frame.frame_id, T_world_cam=frame.T_world_cam, robot=robot,
                                **self._after_update_fields(),
                                probe_depth_m=None if probe_above is None else depth_m,
                                probe_above_blocks=probe_above or 0, **RenderRequest.intrinsics_fields(K_small))
        reply = self._step_render(runner, request)
        rendered = RenderedView(key_map=reply.key_map, conf_map=reply.conf_map, depth_m=reply.depth_m)
        assert self._update_pub is not None and self._delta_pub is not None
        with self._dictionary_lock:
            prev_version = self.dictionary.version
            planned = plan_update(obs, rendered, self.dictionary, self.match_params)
            if self._scorer is not None:  # the regions this frame wrote: seen now, from its direction (map frame)
                T_map_cam = reply.T_map_cam if reply.T_map_cam is not None else frame.T_world_cam
                self._scorer.observe_plan(planned.key_map, T_map_cam, K_small, frame.stamp_ns, robot=robot)
            # The delta goes first, so a key never reaches geometry before its dictionary row.
            self._publish_delta()
            seq = self._updates_sent + 1
            self._update_pub.put(SemanticUpdate(
                frame_id=frame.frame_id, T_world_cam=frame.T_world_cam, **SemanticUpdate.intrinsics_fields(K_small),
                key_map=planned.key_map, conf_map=planned.conf_map,
                new_keys=np.array([key for _, key in planned.new_keys], np.int32), depth_m=depth_m, robot=robot,
                source=self._update_source, seq=seq))
            self._updates_sent = seq  # sent: the next render waits for it
        stats = runner.stats
        stats.record(time.monotonic() - started)
        stats.incr(SemanticCounter.SEMANTIC_FRAMES)
        stats.incr(SemanticCounter.MATCHED, len(planned.matched))
        stats.incr(SemanticCounter.NEW_REGIONS, len(planned.new_keys))
        stats.set(SemanticCounter.REGIONS, len(self.dictionary))
        stats.set(SemanticCounter.DICTIONARY_VERSION, self.dictionary.version)
        stats.set(SemanticCounter.LAST_FRAME_ID, frame.frame_id)
        now = time.monotonic()
        if not stats.counters.get(SemanticCounter.FIRST_FUSED_AT_S):
            stats.set(SemanticCounter.FIRST_FUSED_AT_S, now)
        stats.set(SemanticCounter.LAST_FUSED_AT_S, now)
        stats.incr(SemanticCounter.BUSY_S, time.monotonic() - started)
        logger.debug("semantic: frame %d: %d regions, %d matched, %d new (dictionary v%d -> v%d)",
                     frame.frame_id, obs.conf_maps.shape[0], len(planned.matched), len(planned.new_keys),
                     prev_version, self.dictionary.version)
        if self._merge_schedule.due():  # on the merge worker's thread: the loop goes on (merge_worker)
            self._merges.request(lambda: self._merge(runner))

    def _after_update_fields(self) -> dict[str, Any]:
        """A RenderRequest's ``after_update_*``: rendered once geometry applied the updates sent so far."""
        return {"after_update_source": self._update_source, "after_update_seq": self._updates_sent}

    def _labels_version(self) -> tuple[int, int]:
        """What changes whenever this service changes the map's labels: the updates it sent and its
        dictionary's version (merges): a still camera's kept render is reused only under the same
        (:mod:`openfusion.mapping.still_views`)."""
        return self._updates_sent, self.dictionary.version

    def _step_render(self, runner: ServiceRunner, request: RenderRequest) -> RenderReply:
        """Geometry's render for a frame's update, asked once more when the first request timed out
        (``step_render_retries``): the frame is encoded by now, the costliest step, and a geometry
        that is only slow (its checkpoint or a grid growth on a loaded box) usually answers the
        second time. A refusal, or a second timeout, raises (the frame is ``skipped_no_render``)."""
        reader = reader_for(runner)
        try:
            return reader.render(request, timeout_s=self.section.render_timeout_s)
        except QueryError as exc:
            if not exc.timed_out:
                raise
            runner.stats.incr(SemanticCounter.STEP_RENDER_RETRIES)
            logger.info("semantic: geometry did not render frame %d of robot %s within %.1f s; asking once more "
                        "(the frame is encoded already)", request.frame_id, request.robot,
                        self.section.render_timeout_s)
            return reader.render(request, timeout_s=self.section.render_timeout_s)

    def _publish_delta(self) -> None:
        """Publish what changed in the dictionary since the last delta (nothing when nothing did)."""
        assert self._delta_pub is not None
        delta = self.dictionary.delta_since(self._published_version)
        if delta is not None:
            self._delta_pub.put(delta)
            self._published_version = self.dictionary.version

    def merge_pass(self, runner: ServiceRunner) -> int:
        """Merge the regions that are one object (contacts from geometry, decision here), publish the
        merges as one delta; returns the number of regions merged away. A pass geometry does not
        answer is logged, counted in ``merge_failures`` and skipped. On the caller's thread, after
        a periodic pass still running."""
        return self._merges.run_now(lambda: self._merge(runner)).regions_merged

    def _merge(self, runner: ServiceRunner) -> MergeReply:
        started = time.monotonic()
        with self._dictionary_lock:  # the regions the contacts can know of (frames go on meanwhile)
            known = {int(k) for k in self.dictionary.keys.tolist()}
        try:
            reply = reader_for(runner).contacts(
                RegionContactsRequest(radius_vox=self.merge_params.merge_contact_radius_vox),
                timeout_s=self.section.contacts_timeout_s)
        except QueryError as exc:
            logger.warning("semantic: merge pass skipped: geometry did not give region contacts (%s)", exc)
            runner.stats.incr(SemanticCounter.MERGE_FAILURES)
            with self._dictionary_lock:
                version = self.dictionary.version
            return MergeReply(ok=False, regions_merged=0, regions_pruned=0, dictionary_version=version,
                              message=f"geometry gave no region contacts: {exc.reason}")
        contacts = RegionContacts(
            keys=reply.keys.astype(np.int64), surface_voxels=reply.surface_voxels.astype(np.int64),
            pair_a=reply.pair_a.astype(np.int64), pair_b=reply.pair_b.astype(np.int64),
            contact_a=reply.contact_a.astype(np.int64), contact_b=reply.contact_b.astype(np.int64))
        with self._dictionary_lock:
            plan = plan_merges(self.dictionary, contacts, self.merge_params)
            removed = (self._empty_regions.to_remove(self.dictionary, contacts, known=known)
                       if self.merge_params.merge_prune_empty else [])
            if plan.merged_into or removed:
                apply_merges(self.dictionary, plan.merged_into, embedding=self.merge_params.merge_embedding,
                             removed=removed)
                if self._scorer is not None:
                    self._scorer.merge(plan.merged_into, removed)
                self._publish_delta()
            version, regions = self.dictionary.version, len(self.dictionary)
        runner.stats.incr(SemanticCounter.MERGE_PASSES)
        runner.stats.incr(SemanticCounter.REGIONS_PRUNED, len(removed))
        done = MergeReply(ok=True, regions_merged=len(plan.merged_into), regions_pruned=len(removed),
                          dictionary_version=version)
        if not plan.merged_into:
            return done
        runner.stats.incr(SemanticCounter.REGIONS_MERGED, len(plan.merged_into))
        runner.stats.set(SemanticCounter.REGIONS, regions)
        runner.stats.set(SemanticCounter.DICTIONARY_VERSION, version)
        logger.info("semantic: merged %d regions into %d (map version %d, %.0f ms): %s", len(plan.merged_into),
                    len(plan.groups), reply.map_version, (time.monotonic() - started) * 1e3, plan.groups)
        return done

    def setup(self, runner: ServiceRunner) -> None:
        self._stats = runner.stats
        if not self.section.encoder_pool or self.section.local_encoder:
            warm_up_encoder(self.encoder, "semantic")
        self.recover(runner)
        # Updates and deltas change the map: they block when a link is congested (a camera's frames
        # on the same link are what congests it) instead of being dropped, which lost an update
        # now and then under load (geometry never applied it; nothing resends one).
        self._update_pub = runner.publisher(SEMANTIC_UPDATE, congestion_control=zenoh.CongestionControl.BLOCK)
        self._delta_pub = runner.publisher(DICTIONARY_DELTA, congestion_control=zenoh.CongestionControl.BLOCK)
        runner.queryable(SEMANTIC_DICTIONARY, self.handle_snapshot)
        runner.queryable(SEMANTIC_MERGE, lambda req: self.handle_merge(runner, req))
        if self._instances is not None:
            # As deep as the frame queue: its callback thread competes for the interpreter with the
            # scoring threads, and a queue of 8 let instance images go under load (their frames skipped)
            runner.subscriber(SENSOR_INSTANCE, self._instances.add, queue_size=self._frame_queue_size())
        if self.section.integrate_wait_s > 0 or self.select_params.select == "latest":
            runner.subscriber(GEOMETRY_PROGRESS, self._integrated.on_progress, queue_size=256, measure=False)
        # latest: a queue, of which the newest frame geometry has taken is encoded (the older ones are
        # superseded, counted); every: a queue (a slower encoder drops the oldest, counted);
        # coverage: a queue the size of the window, emptied by the scoring thread
        mode = self.select_params.select
        # Coverage and every: a queue per robot's bridge served in turn (fair), so one robot's backlog
        # never keeps another's frames from being scored; coverage then picks across robots by gain.
        self._frames = runner.subscriber(SENSOR_RGBD, queue_size=self._frame_queue_size(), fair=True)
        if mode == "latest":  # the newest frame geometry has taken (geometry_progress.NewestTaken)
            self._newest = NewestTaken(self._integrated, capacity=LATEST_BUFFER, wait_s=self.section.integrate_wait_s)
        if self._scorer is not None:
            self._feeder = CandidateFeeder(
                frames=self._frames, window=CandidateWindow(self._scorer), scorer=self._scorer,
                accept=self.switch.accept,
                render=lambda request: reader_for(runner).render(request, timeout_s=self.section.render_timeout_s),
                instances=self._instances, instance_wait_s=self.section.instance_wait_s,
                on_no_instance=self._skip_without_instance,
                on_no_render=self._skip_no_render,
                labels_version=self._labels_version,
                after_update=self._after_update_fields)
            runner.stats.set(SemanticCounter.SKIPPED_NO_GAIN, 0)
        if self.section.encoder_pool:
            assert runner.session is not None
            self._pool = EncoderPool(runner.session, PoolKeys(runner.keys.prefix), map_id=runner.keys.map_id,
                                     embedding_space=self.dictionary.embedding_space, stats=runner.stats,
                                     timeout_s=self.section.pool_timeout_s)
            runner.stats.set(PoolCounter.ENCODER_WORKERS, 0)
        runner.stats.set(SemanticCounter.SEMANTIC_FRAMES, 0)
        runner.stats.set(SemanticCounter.LAST_FRAME_HANDLED, -1)  # no frame yet
        runner.stats.set(SemanticCounter.MERGE_PASSES, 0)
        runner.stats.set(SemanticCounter.REGIONS_MERGED, 0)
        runner.stats.set(SemanticCounter.REGIONS, len(self.dictionary))

    def loop(self, runner: ServiceRunner) -> None:
        assert self._frames is not None
        self._merges.start()
        counts = FrameCounts(runner.stats, self._frames).start()  # what became of each frame (outcomes)
        feeding = None
        if self._feeder is not None:
            feeding = threading.Thread(target=self._feeder.run, args=(runner,), name="semantic-select", daemon=True)
            feeding.start()
        try:
            if self._pool is not None:
                PoolDispatch(self, self._pool).run(runner)
                return
            while not runner.stopping:
                self._local_step(runner)
        finally:
            if self._feeder is not None:
                self._feeder.window.close()
            if feeding is not None:
                feeding.join(timeout=max(self.section.render_timeout_s, 1.0) + 1.0)
            self._merges.stop(timeout_s=self.section.contacts_timeout_s + 1.0)
            counts.stop()

    def _count_merge_error(self) -> None:
        if self._stats is not None:
            self._stats.incr(SemanticCounter.MERGE_FAILURES)
            self._stats.add_error()

    def _local_step(self, runner: ServiceRunner) -> None:
        """Encode here the next frame: the best candidate (coverage), else the next one off the
        subscription (latest, every)."""
        assert self._frames is not None
        if self._feeder is not None:
            pending = self._feeder.take(runner, timeout_s=0.2)
            if pending is not None:
                self._encode_pending(runner, pending)
            return
        msg = self.next_frame(runner, timeout_s=0.2)
        if msg is None:
            return
        try:
            self._next_seq += 1
            self._handle(runner, msg)
        finally:  # whatever became of it, the frame is done with: tests and tools wait on this
            runner.stats.set(SemanticCounter.LAST_FRAME_HANDLED, msg.frame_id)

    def next_frame(self, runner: ServiceRunner, timeout_s: float) -> RgbdFrame | None:
        """The next frame off the subscription (every), or the newest one geometry has taken
        (latest: the older ones are superseded, counted), waiting up to ``timeout_s``."""
        assert self._frames is not None
        if self._newest is None:
            return self._frames.recv(timeout_s=timeout_s)
        deadline = time.monotonic() + timeout_s
        msg = self._frames.recv(timeout_s=0.0)
        while True:
            while msg is not None:  # everything queued, into the buffer
                self._supersede(runner, self._newest.add(msg, time.monotonic()))
                msg = self._frames.recv(timeout_s=0.0)
            chosen, passed = self._newest.take(time.monotonic())
            self._supersede(runner, passed)
            if chosen is not None:
                return chosen
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return None
            # a frame to come, or 10 ms for geometry to take one that waits here
            msg = self._frames.recv(timeout_s=min(remaining, 0.01))

    def _supersede(self, runner: ServiceRunner, frames: list[RgbdFrame]) -> None:
        for msg in frames:
            runner.stats.incr(SemanticCounter.FRAMES_SUPERSEDED)
            runner.stats.set(SemanticCounter.LAST_FRAME_HANDLED, msg.frame_id)

    def _encode_pending(self, runner: ServiceRunner, pending: Pending) -> None:
        """Encode a chosen candidate here (switch and instance join were done when it came)."""
        assert self._feeder is not None
        self._next_seq += 1
        try:
            self._process_counted(runner, pending.msg, pending.instance, pending.wanted_px)
        finally:
            self._feeder.finish(runner, pending.msg)

    def _handle(self, runner: ServiceRunner, msg: RgbdFrame) -> None:
        """Fuse one frame or count why it was skipped; never raises for one frame's failure."""
        if not self.switch.accept(msg.frame_id, time.monotonic()):
            runner.stats.incr(SemanticCounter.SKIPPED_SWITCH)
            return
        instance = None
        if self._instances is not None and msg.instance is None:
            instance = self._instances.take(msg, timeout_s=self.section.instance_wait_s)
            runner.stats.set(SemanticCounter.INSTANCES_EVICTED, self._instances.evicted)
            if instance is None:
                self._skip_without_instance(runner, msg)
                return
        self._process_counted(runner, msg, instance)

    def _process_counted(self, runner: ServiceRunner, msg: RgbdFrame, instance: InstanceFrame | None,
                         wanted_px: np.ndarray | None = None) -> None:
        """:meth:`process`; a failure is logged and counted, never raised."""
        try:
            self.process(runner, msg, instance, wanted_px)
        except QueryError as exc:  # geometry did not answer (or refused) the render request
            self._skip_no_render(runner, msg.robot, msg.frame_id, exc)
        except Exception:  # the encoder, a step or the bus failed on this frame: logged, counted, next frame
            logger.exception("semantic: frame %d failed and was skipped", msg.frame_id)
            runner.stats.incr(SemanticCounter.FRAMES_FAILED)
            runner.stats.add_error()

    def _frame_done(self, runner: ServiceRunner, msg: RgbdFrame) -> None:
        """A frame taken off the subscription is done with: ``last_frame_handled`` moves (with
        coverage, once every frame taken before it is done too: selection.HandledFrames)."""
        if self._feeder is not None:
            self._feeder.finish(runner, msg)
        else:
            runner.stats.set(SemanticCounter.LAST_FRAME_HANDLED, msg.frame_id)


    def _skip_no_render(self, runner: ServiceRunner, robot: str, frame_id: int, exc: QueryError) -> None:
        """Geometry gave no render: a robot not joined to the map yet (counted apart, expected while
        its submap grows), or no answer / another refusal (a warning)."""
        if exc.code == "robot_not_joined":
            logger.debug("semantic: frame %d of robot %s skipped: %s", frame_id, robot, exc)
            runner.stats.incr(SemanticCounter.SKIPPED_ROBOT_HELD)
            return
        logger.warning("semantic: frame %d of robot %s skipped: %s", frame_id, robot, exc)
        runner.stats.incr(SemanticCounter.SKIPPED_NO_RENDER)

    def _skip_without_instance(self, runner: ServiceRunner, msg: RgbdFrame) -> None:
        runner.stats.incr(SemanticCounter.SKIPPED_NO_INSTANCE)
        self._frames_without_instance += 1
        if self._frames_without_instance % 100 == 1:  # the first, then every 100th
            logger.warning(
                "semantic: frame %d skipped: its instance image did not arrive on %s within %.2f s (%d such "
                "frames so far; the %r encoder needs a source with instance labels)", msg.frame_id,
                SENSOR_INSTANCE.key(runner.keys), self.section.instance_wait_s, self._frames_without_instance,
                self.section.encoder)

    def close(self) -> None:
        if self._pool is not None:
            self._pool.close()


DEFINITION = ServiceDefinition(
    name="semantic",
    help="encode regions of the latest frame, match them to the map, send updates, own the dictionary",
    config_model=SemanticConfig,
    build=SemanticService,
)
