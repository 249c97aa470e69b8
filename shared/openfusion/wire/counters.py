"""The named counters each service publishes in its :class:`~openfusion.wire.schemas.HealthStats`.

``HealthStats.counters`` is a ``{name: value}`` map on the wire; these enums are its contract:
services count with them (``stats.incr(GeometryCounter.FRAMES_INTEGRATED)``) and readers
(``openfusion run``'s ``run.json``, ``openfusion health``, benches, tests) read with them
(``stats.counter(GeometryCounter.FRAMES_INTEGRATED)``), so a renamed counter breaks at import
time, not silently in a report. Values are floats; times end in ``_s``.
"""

from __future__ import annotations

from collections.abc import Mapping
from enum import StrEnum


class CommonCounter(StrEnum):
    """Counted by the bus helpers for every service."""

    PUBLISHED = "published"  # messages published
    REFUSED = "refused"  # queries refused with a reason (RequestError)
    RESTARTS = "restarts"  # times a supervisor restarted this service (openfusion.services.common.RESTARTS_ENV)


class BridgeCounter(StrEnum):
    FRAMES_READ = "frames_read"  # frames taken from the source (all passes)
    FRAMES_READ_PASS = "frames_read_pass"  # the source's own count of the current pass
    FRAMES_PUBLISHED = "frames_published"
    INSTANCES_PUBLISHED = "instances_published"
    PLAYBACK_DONE = "playback_done"  # 1 once the source is exhausted
    PASSES = "passes"
    FLOW_WAIT_S = "flow_wait_s"  # time spent waiting for geometry's acknowledgements
    FLOW_TIMEOUTS = "flow_timeouts"
    SKIPPED_UNENCODABLE = "skipped_unencodable"
    SKIPPED_PUBLISH_FAILED = "skipped_publish_failed"  # publishing raised something else (logged with traceback)
    FRAMES_THROTTLED = "frames_throttled"  # live frames dropped to keep to rate_hz
    FRAMES_REPLAYED = "frames_replayed"  # playback: frames published again for a restarted geometry
    REWINDS = "rewinds"  # playback: times the bridge went back to the frame after geometry's checkpoint

    @staticmethod
    def skipped(reason: str) -> str:
        """Frames the source skipped for ``reason`` (``skipped_invalid_pose``, ...)."""
        return f"{SKIPPED_PREFIX}{reason}"


#: Prefix of the bridge's per-reason skip counters.
SKIPPED_PREFIX = "skipped_"


class GeometryCounter(StrEnum):
    FRAMES_INTEGRATED = "frames_integrated"
    INTEGRATE_BUSY_S = "integrate_busy_s"  # time spent integrating
    LAST_INTEGRATED_AT_S = "last_integrated_at_s"  # CLOCK_MONOTONIC of the last integration
    LAST_FRAME_ID = "last_frame_id"
    UPDATES_APPLIED = "updates_applied"
    LAST_UPDATE_FRAME_ID = "last_update_frame_id"
    CAPACITY_REFUSED = "capacity_refused"
    NUM_BLOCKS = "num_blocks"
    CHECKPOINTS = "checkpoints"
    CHECKPOINT_FAILURES = "checkpoint_failures"  # checkpoints that failed (OSError: disk full, read-only)
    CHECKPOINT_LAST_FRAME_ID = "checkpoint_last_frame_id"  # last frame in the newest checkpoint (-1: none)
    DICTIONARY_RESYNCS = "dictionary_resyncs"
    FRAMES_DUPLICATE = "frames_duplicate"  # playback frames dropped: already held (id <= the last one taken)
    FRAMES_OUT_OF_ORDER = "frames_out_of_order"  # playback frames dropped: the frame before them is not held
    FRAMES_FAILED = "frames_failed"  # integration raised on the frame (logged, taken as done: never retried)
    FRAMES_GAP = "frames_gap"  # live frames that never reached the map (ids skipped between two frames taken)
    VOXELS_RELABELLED = "voxels_relabelled"  # voxels whose key a merge (delta or resync) changed to the surviving key
    RENDERS = "renders"  # geometry/render requests answered with a ray cast (updates, candidates with select_view=render; a split map: summed over its shards, each renders its own blocks)
    RENDER_BUSY_S = "render_busy_s"  # time spent on them, not counting the wait for the map's lock (ray casts of the map; grows with the blocks held)
    PROBES = "probes"  # geometry/render requests with a frame's depth answered by a probe (candidates with select_view=probe)
    PROBE_BUSY_S = "probe_busy_s"  # time spent on them, not counting the wait for the map's lock (does not grow with the blocks held)
    RENDER_UPDATE_WAIT_TIMEOUTS = "render_update_wait_timeouts"  # renders that waited render_update_wait_s for an update in vain
    UPDATES_REUSED_RENDER = "updates_reused_render"  # updates written through their frame's render (no second ray cast)
    SAVE_MERGES = "save_merges"  # merge passes the semantic service ran because this service was saving
    SAVES = "saves"  # control/save requests that completed (the map written where asked)
    SAVE_FAILURES = "save_failures"  # control/save requests that failed (the error went to the asker, and the log)
    SAVE_MERGE_FAILURES = "save_merge_failures"  # saves that went ahead without one (semantic gone or silent)
    ROBOTS = "robots"  # robots whose frames this map has taken
    ROBOTS_HELD = "robots_held"  # of them, not joined to the map's frame yet (their frames wait in their submaps)
    FRAMES_HELD = "frames_held"  # frames taken from held robots (in their submaps; integrated when they join)
    ROBOTS_JOINED = "robots_joined"  # held robots joined by a registration
    JOIN_ATTEMPTS = "join_attempts"  # registrations of held robots' submaps tried
    JOIN_FAILURES = "join_failures"  # registration steps that raised (logged; the robot stays as it was)
    JOIN_RECHECKS = "join_rechecks"  # re-checks of joined robots' transforms
    JOIN_CORRECTIONS = "join_corrections"  # re-checks that changed a transform
    UPDATES_DROPPED_NOT_JOINED = "updates_dropped_not_joined"  # semantic updates of a robot not joined (none written)
    RESIDENT_BLOCKS = "resident_blocks"  # blocks in RAM (num_blocks counts the whole map: resident + paged out)
    RESIDENT_MB = "resident_mb"  # MiB of the grid's voxel buffers (its capacity: allocated and touched at once)
    TILES_PAGED_OUT = "tiles_paged_out"  # tiles that left RAM for the tile store (memory budget)
    TILES_PAGED_IN = "tiles_paged_in"  # tiles read back before a frame or a render reached them
    CHECKPOINT_LAST_S = "checkpoint_last_s"  # seconds the last checkpoint took (snapshot to commit)
    CHECKPOINT_LAST_TILES = "checkpoint_last_tiles"  # tiles it encoded (those changed since the one before)
    SAVING = "saving"  # 1 while a save or a periodic checkpoint is being written
    RSS_MB = "rss_mb"  # the process's resident memory, sampled once a second
    RSS_PEAK_MB = "rss_peak_mb"  # ... its largest sample
    RSS_ANON_PEAK_MB = "rss_anon_peak_mb"  # largest sample of RssAnon (without the store's mapped file pages)
    # A replica's copy of its peer's checkpoint (docs/SHARDS.md; services/geometry/peer_copy.py)
    PEER_COPIES = "peer_copies"  # checkpoints copied from a peer and loaded at start (0 or 1)
    PEER_COPY_FAILURES = "peer_copy_failures"  # copies given up (peer gone, bad digest, corrupt copy): discarded
    PEER_COPY_TILES = "peer_copy_tiles"  # tiles in the checkpoint copied from the peer
    PEER_COPY_BYTES = "peer_copy_bytes"  # bytes of checkpoint files copied from the peer
    PEER_COPY_S = "peer_copy_s"  # seconds the copy took (listing to verified files)
    PEER_COPY_FRAMES_HELD = "peer_copy_frames_held"  # frames that came during the copy, held and taken after it
    PEER_COPY_FRAMES_LOST = "peer_copy_frames_lost"  # frames that came during the copy over peer_copy_buffer_frames
    PEER_COPY_FRAME_ID = "peer_copy_frame_id"  # last frame the copied checkpoint holds (-1: none or no copy)
    PEER_SNAPSHOTS_SERVED = "peer_snapshots_served"  # snapshots of this geometry's checkpoint served to a peer
    PEER_BYTES_SERVED = "peer_bytes_served"  # bytes of checkpoint files served to peers


class SemanticCounter(StrEnum):
    SEMANTIC_FRAMES = "semantic_frames"  # frames fused (encoded, matched, update sent)
    BUSY_S = "busy_s"  # time spent on those frames
    REGIONS = "regions"  # regions in the dictionary
    DICTIONARY_VERSION = "dictionary_version"
    MATCHED = "matched"
    NEW_REGIONS = "new_regions"
    LAST_FRAME_ID = "last_frame_id"  # last frame fused
    FIRST_FUSED_AT_S = "first_fused_at_s"  # CLOCK_MONOTONIC of the first frame fused
    LAST_FUSED_AT_S = "last_fused_at_s"  # ... and of the last one (semantic rate = frames / span)
    LAST_FRAME_HANDLED = "last_frame_handled"  # last frame taken off the subscription and done with (fused or skipped)
    SKIPPED_SWITCH = "skipped_switch"  # frames the semantic switch left out (every_k, max_hz)
    SKIPPED_NO_INSTANCE = "skipped_no_instance"  # gt encoder: the instance image did not come
    SKIPPED_NO_RENDER = "skipped_no_render"  # geometry did not answer the render request
    STEP_RENDER_RETRIES = "step_render_retries"  # an encoded frame's render asked again after a timeout
    SKIPPED_ROBOT_HELD = "skipped_robot_held"  # the frame's robot is not joined to the map's frame yet
    FRAMES_FAILED = "frames_failed"  # the encoder or a step raised on the frame (logged, skipped)
    INSTANCES_EVICTED = "instances_evicted"
    MERGE_PASSES = "merge_passes"  # region merge passes run (every merge_every semantic frames)
    REGIONS_MERGED = "regions_merged"  # regions folded into another by those passes
    REGIONS_PRUNED = "regions_pruned"  # regions removed for holding no voxel in two passes in a row
    MERGE_FAILURES = "merge_failures"  # passes skipped: geometry did not answer geometry/contacts
    # frame selection (openfusion.mapping.selection; semantic.select)
    ENCODER_CALLS = "encoder_calls"  # frames the region encoder encoded (here, or answered by the pool's workers)
    ENCODER_REGIONS = "encoder_regions"  # regions it embedded, summed over those calls
    REGIONS_NOT_EMBEDDED = "regions_not_embedded"  # regions of encoded frames that added nothing: fused, no embedding
    FRAMES_SCORED = "frames_scored"  # candidate frames scored (coverage)
    SKIPPED_NO_GAIN = "skipped_no_gain"  # frames not encoded: they would add less than select_min_gain
    SELECT_EVICTED = "select_evicted"  # candidates a full window let go for better ones (never encoded)
    SELECT_BUSY_S = "select_busy_s"  # time spent scoring candidates (render request + scoring)
    RENDERS_REUSED = "renders_reused"  # candidates scored on their still camera's last render, not a new one
    WANTED_RENDER_FAILURES = "wanted_render_failures"  # a taken frame's second render failed: the decision's mask
    SELECT_WINDOW = "select_window"  # candidates waiting for the encoder now
    # what became of the frames on sensor/rgbd (SEMANTIC_FRAME_OUTCOMES: each frame ends in one)
    FRAMES_RECEIVED = "frames_received"  # frames that came on the subscription
    FRAMES_DROPPED = "frames_dropped"  # let go by its bounded queue before the service took them
    FRAMES_SUPERSEDED = "frames_superseded"  # select=latest: a newer frame geometry had taken was encoded instead
    FRAMES_MALFORMED = "frames_malformed"  # could not be decoded (logged)
    FRAMES_PENDING = "frames_pending"  # received, no outcome yet: queued, in the window, at the encoder
    INTEGRATE_WAIT_TIMEOUTS = "integrate_wait_timeouts"  # rendered before geometry took the frame (integrate_wait_s)


class EncoderCounter(StrEnum):
    FRAMES_ENCODED = "frames_encoded"  # encode requests answered (an encoder worker of the pool)
    REFUSED_SPACE = "refused_space"  # requests of a map in another embedding space
    ENCODE_BUSY_S = "encode_busy_s"


class PoolCounter(StrEnum):
    """The semantic service's view of the encoder pool."""

    ENCODER_WORKERS = "encoder_workers"  # workers alive in the map's space now
    WORKERS_REFUSED = "workers_refused"  # workers seen in another embedding space (not used)
    FRAMES_DISPATCHED = "frames_dispatched"
    FRAMES_RESENT = "frames_resent"  # sent again after their worker died
    FRAMES_LOST = "frames_lost"  # their worker died twice, or they were too old to send again
    RESULTS_STALE = "results_stale"  # came back after a newer frame's result was applied
    RESULTS_HELD = "results_held"  # waited for an older frame still in flight before being applied
    NO_ENCODER = "no_encoder"  # 1 while no worker is alive and there is no local encoder
    LOCAL_FRAMES = "local_frames"  # encoded by the local encoder (no worker alive)


#: Every frame the semantic service receives (``frames_received``) ends in exactly one of these
#: (``frames_pending`` until then): fused, or not encoded for the reason named. Outcomes of the
#: encoder pool (``frames_lost``, ``results_stale``) are :class:`PoolCounter`'s.
SEMANTIC_FRAME_OUTCOMES: tuple[str, ...] = (
    SemanticCounter.SEMANTIC_FRAMES, SemanticCounter.SKIPPED_NO_GAIN, SemanticCounter.SELECT_EVICTED,
    SemanticCounter.FRAMES_SUPERSEDED, SemanticCounter.SKIPPED_SWITCH, SemanticCounter.SKIPPED_NO_INSTANCE, SemanticCounter.SKIPPED_NO_RENDER,
    SemanticCounter.SKIPPED_ROBOT_HELD, SemanticCounter.FRAMES_FAILED, SemanticCounter.FRAMES_DROPPED,
    SemanticCounter.FRAMES_MALFORMED, PoolCounter.FRAMES_LOST, PoolCounter.RESULTS_STALE,
)

def semantic_frame_outcomes(counters: Mapping[str, float]) -> dict[str, int]:
    """What became of the frames the semantic service received, from its counters: each outcome
    of :data:`SEMANTIC_FRAME_OUTCOMES` that happened, by name."""
    return {str(name): int(counters[name]) for name in SEMANTIC_FRAME_OUTCOMES if counters.get(name)}


#: The semantic service's counter ``encoded_by:<worker id>``: results of that encoder worker
#: applied to the map (one counter per worker; run.json's ``frames_encoded_per_worker``).
ENCODED_BY_PREFIX = "encoded_by:"


class QueryCounter(StrEnum):
    QUERIES = "queries"
    REGIONS = "regions"
    DICTIONARY_RESYNCS = "dictionary_resyncs"
    SUMMARY_FETCHES = "summary_fetches"
    SUMMARY_FAILURES = "summary_failures"
