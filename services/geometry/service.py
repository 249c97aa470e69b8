"""Geometry service: owns the semantic TSDF volume (the only writer of voxels).

| key | direction | message |
|---|---|---|
| ``…/sensor/rgbd`` | subscribes (every frame, bounded queue) | :class:`~openfusion.wire.schemas.RgbdFrame` |
| ``…/semantic/update`` | subscribes | :class:`~openfusion.wire.schemas.SemanticUpdate` |
| ``…/semantic/dictionary/delta`` | subscribes (replica for checkpoints) | :class:`~openfusion.wire.schemas.DictionaryDelta` |
| ``…/geometry/progress`` | publishes, one per frame taken from the queue, and resume announcements | :class:`~openfusion.wire.schemas.GeometryProgress` (the bridge's flow control; where a playback resumes) |
| ``…/geometry/render`` | queryable (one that names a semantic update first waits for it: :mod:`.applied_updates`; one with a frame's depth, ``probe_depth_m``, is answered by a probe, not a ray cast, on a map of more than ``probe_above_blocks`` blocks) | RenderRequest → RenderReply |
| ``…/geometry/points`` | queryable | PointsRequest → PointsReply (capped) |
| ``…/geometry/mesh`` | queryable | MeshRequest → MeshReply |
| ``…/geometry/regions`` | queryable | RegionSummaryRequest → RegionSummaryReply (per-region bbox + surface point count) |
| ``…/geometry/dictionary`` | queryable | DictionaryRequest → DictionarySnapshot (what the last checkpoint + deltas hold) |
| ``…/geometry/contacts`` | queryable | RegionContactsRequest → RegionContactsReply (which regions' voxels touch; the semantic service's merges) |
| ``…/control/{save,load,reset}`` | queryable (admin) | ControlRequest → ControlReply |
| ``…/geometry/checkpoint/{list,chunk,release}/{itself}`` | queryables at its own name; queries a peer's at start | a snapshot of its checkpoint for a peer replica that starts without one (:mod:`.peer_copy`) |
| ``…/semantic/merge`` | queries before ``control/save`` and the final save | MergeRequest → MergeReply |
| ``…/semantic/dictionary`` | queries on a gap in the deltas (resync) | DictionaryRequest → DictionarySnapshot |
| ``…/health/geometry`` | liveliness + stats | counters ``frames_integrated``, ``updates_applied``, ``renders``, ``render_busy_s``, ``probes``, ``probe_busy_s``, ``render_update_wait_timeouts``, ``checkpoints``, ``checkpoint_failures``, ``checkpoint_last_frame_id``, ``capacity_refused``, ``frames_duplicate``, ``frames_out_of_order``, ``frames_failed``, ``frames_gap``, ``num_blocks``, ``integrate_busy_s``, ``last_integrated_at_s`` (CLOCK_MONOTONIC), ``voxels_relabelled``, ``save_merges``, ``save_merge_failures``, ``dictionary_resyncs``; the map's size and memory: ``num_blocks`` (all), ``resident_blocks``, ``resident_mb``, ``tiles_paged_out``, ``tiles_paged_in``, ``checkpoint_last_s``, ``checkpoint_last_tiles``, ``saving``, ``rss_mb``, ``rss_peak_mb``, ``rss_anon_peak_mb`` (:mod:`.memory`); a copy of a peer's checkpoint: ``peer_copies``, ``peer_copy_failures``, ``peer_copy_tiles``, ``peer_copy_bytes``, ``peer_copy_s``, ``peer_copy_frame_id``, ``peer_copy_frames_held``, ``peer_copy_frames_lost`` (:mod:`.start_buffer`), ``peer_snapshots_served``, ``peer_bytes_served`` (:mod:`.peer_copy`) |

Checkpoints go to the tile store ``{map_dir}/{map_id}/map.ofz`` every ``checkpoint_period_s``
(when something changed; without region summaries, which would cost a surface read-out under the
lock integration waits on), on ``control/save`` and on shutdown (both with summaries). They are
incremental (:mod:`.checkpoints`, :mod:`openfusion.mapping.mapstore`): the tiles changed since the
last one are copied under the lock, then encoded and committed in one LMDB transaction while
integration goes on, so their cost follows what changed, and a crash at any instant leaves the
last committed checkpoint whole. With ``memory_budget_mb`` the least recently observed tiles
are paged out to the same store and read back when a frame or a render reaches them. On start
the service loads its checkpoint (an older ``map.ofz.npz`` one too, or its ``.prev`` when it is
corrupt: :func:`~openfusion.mapping.load_latest_map`; unreadable: the service does not start
rather than map over it), so a restart loses nothing that was saved. Each checkpoint's meta records ``frames_integrated`` and
``last_frame_id`` (the id of the last frame integrated into it); after a load or save the service
exposes it as :attr:`GeometryService.checkpoint_last_frame_id` and the health counter
``checkpoint_last_frame_id`` (-1: none). A checkpoint that fails with an ``OSError`` (disk full,
read-only folder) is logged in one line naming the path and reason, counted as
``checkpoint_failures`` and, on ``control/save``, answered with ``reply_err`` code
``checkpoint_failed``; the map stays in memory, integration goes on, and the periodic loop tries
again one ``checkpoint_period_s`` later. Every bad message is counted and dropped before it
reaches the volume; a bad request is answered with ``reply_err`` naming the limit or field.

The service is one class made of parts: frames in (:mod:`.frame_intake`), saves, checkpoints and
loads (:mod:`.persistence`), merges, the dictionary replica and its resync
(:mod:`.dictionary_follower`), a replica's copy of its peer's checkpoint (:mod:`.peer_copy`); requests, wiring and the loop are here.

Resume with nothing lost (playback): frames of a playback the bridge can replay carry the
playback's name and ``prev_frame_id`` (the frame published before them). The service takes such a
frame only when it holds that predecessor (:attr:`GeometryService.last_frame_id` of
:attr:`GeometryService.playback`, the last frame taken, restored from the checkpoint at start; the
first frame of a new playback follows -1): one it already holds (id <= the last taken) is dropped and counted as
``frames_duplicate``, one whose predecessor it does not hold as ``frames_out_of_order``; either is
acknowledged (the bridge's flow control) but changes nothing. On start, and whenever a frame comes
out of order, it announces on ``geometry/progress`` the last frame it holds
(:class:`~openfusion.wire.schemas.GeometryProgress` with ``resume > 0``), repeated every second
until the next frame arrives in order; the bridge then replays from the frame after it. So the
acknowledgement (frame taken from the queue) is only flow control: the resume point is the
checkpoint, and the frames acknowledged after it are replayed after a crash. A restart also
restores ``frames_integrated`` and ``integrate_busy_s`` from the checkpoint, so they count each
frame once. Live frames (no ``prev_frame_id``) are taken as they come, as before; the ids missing
between two of them (frames dropped anywhere: the rate cap, congestion, a restart) are counted in
``frames_gap``.

Several robots (:mod:`openfusion.mapping.robot_streams`, docs/MULTI_ROBOT.md): every frame names
its robot, and all of the above is per robot: a chain, a playback, duplicates, out-of-order frames,
gaps, resume announcements and counts for each (health ``robots``). Frames are served from one
queue per robot's bridge in turn (``Subscriber(fair=True)``), so one robot's backlog never starves
another. A robot's poses are in its own odometry frame; a transform joins it to the map's frame:
given (``geometry.robot_frames``), or found when it starts: until its submap registers to the map
(:mod:`openfusion.mapping.robot_join`, on the thread of :mod:`.robots`) its frames are held, never
fused misaligned, and its renders are refused (``robot_not_joined``); a joined robot is re-checked
against the map now and then and the correction logged.

Region summaries (``geometry/regions``, what the query service ranks with): computed from the
same surface points as ``geometry/points`` and cached per ``map_version`` (a counter bumped by
every integrated frame, semantic update, merge, load and reset). A request is answered from the
cache while the map is unchanged, or when the cached summary is younger than
``regions_min_interval_s`` (so many clients cannot make the service extract the surface over and
over while it integrates); ``fresh=True`` always recomputes a summary of an older map version.
The reply says its ``map_version``, ``age_s`` and ``key_horizon`` (every key below it is
covered: a covered key that is not listed has no surface points).
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
import uuid
from collections import OrderedDict
from pathlib import Path

import numpy as np

from openfusion.bus import Publisher, RequestError, ServiceRunner, Subscriber
from openfusion.mapping import (
    MapFormatError,
    RenderedView,
    readout_worker,
)
from openfusion.mapping.heap import limit_malloc_arenas
from openfusion.mapping.mapfile import resolve_map_path
from openfusion.mapping.robot_streams import RobotStream, RobotStreams, parse_robot_frames
from openfusion.services.common import ServiceDefinition
from openfusion.services.dictionary_replica import DictionaryReplica
from openfusion.services.geometry import checkpoints, sharding
from openfusion.services.geometry.applied_updates import AppliedUpdates
from openfusion.services.geometry.dictionary_follower import DictionaryFollower
from openfusion.services.geometry.frame_intake import FrameIntake
from openfusion.services.geometry.memory import MemoryPeaks, publish_map_size
from openfusion.services.geometry.peer_copy import PeerCopy
from openfusion.services.geometry.persistence import (  # re-exported: tests and callers name them here
    NO_EMBEDDING_SPACE as NO_EMBEDDING_SPACE,
)
from openfusion.services.geometry.persistence import NO_FRAME_ID as NO_FRAME_ID
from openfusion.services.geometry.persistence import CheckpointFailed as CheckpointFailed
from openfusion.services.geometry.persistence import MapPersistence, has_checkpoint
from openfusion.services.geometry.robots import RobotJoiner
from openfusion.services.geometry.section import GeometryConfig, SummaryCache
from openfusion.services.geometry.section import (
    GeometrySection as GeometrySection,  # re-exported: the config's section
)
from openfusion.services.geometry.start_buffer import FRAME, UPDATE, StartBuffer
from openfusion.wire.counters import GeometryCounter
from openfusion.wire.endpoints import (
    CONTROL,
    DICTIONARY_DELTA,
    GEOMETRY_CONTACTS,
    GEOMETRY_DICTIONARY,
    GEOMETRY_MESH,
    GEOMETRY_POINTS,
    GEOMETRY_PROGRESS,
    GEOMETRY_REGIONS,
    GEOMETRY_RENDER,
    SEMANTIC_UPDATE,
    SENSOR_RGBD,
)
from openfusion.wire.schemas import (
    ControlReply,
    ControlRequest,
    DictionaryRequest,
    DictionarySnapshot,
    MeshReply,
    MeshRequest,
    PointsReply,
    PointsRequest,
    RegionContactsReply,
    RegionContactsRequest,
    RegionSummaryReply,
    RegionSummaryRequest,
    RenderReply,
    RenderRequest,
    RgbdFrame,
    SemanticUpdate,
)

logger = logging.getLogger(__name__)


def check_update(msg: SemanticUpdate) -> None:
    """Refuse an update that would corrupt the map (keys below -1, confidences outside [0, 1])."""
    if msg.key_map.size and int(msg.key_map.min()) < -1:
        raise ValueError(f"key_map holds keys below -1 (min {int(msg.key_map.min())})")
    conf = msg.conf_map
    if conf.size and (not np.isfinite(conf).all() or float(conf.min()) < 0.0 or float(conf.max()) > 1.0):
        raise ValueError("conf_map must be finite and within [0, 1]")
    depth = msg.depth_m
    if depth is not None and depth.size and (not np.isfinite(depth).all() or float(depth.min()) < 0.0):
        raise ValueError("depth_m must be finite and >= 0")


#: glibc malloc arenas of a geometry process under a memory budget (measured in docs/SCALE.md).
MALLOC_ARENAS = 2
#: Renders kept for the semantic updates that follow them (the pool applies results in frame order).
RECENT_RENDERS = 2
#: A tile unchanged this long has settled: its region-summary part is read out as idle work.
SETTLE_S = 5.0
#: Idle read-out per turn of the service loop (about once a second), at least one chunk.
IDLE_READOUT_S = 0.5
#: threads answering renders (one may wait for a semantic update; :meth:`GeometryService.handle_render`)
RENDER_WORKERS = 2


class GeometryService(FrameIntake, MapPersistence, DictionaryFollower, PeerCopy):
    """The geometry service's logic; every handler is a plain method tests call without a bus."""

    def __init__(self, config: GeometryConfig) -> None:
        self.config = config
        self.section = config.geometry
        if self.section.volume_params().memory_budget_mb is not None:  # under a budget, before threads start (heap's docstring)
            limit_malloc_arenas(MALLOC_ARENAS)
        self._lock = threading.RLock()
        #: Which geometry shard this is (docs/SHARDS.md): 0/1, the whole map, unless ``shard`` says.
        self.shard = self.section.shard_service
        readout_worker.register_lock(self._lock, owner=self)  # read-out jobs take it: never asked for under it
        self.checkpoint_dir: Path | None = (
            sharding.checkpoint_dir(self.section.map_dir / config.map_id, self.shard)
            if self.section.map_dir is not None else None
        )
        load = self.section.load_on_start and self.checkpoint_dir is not None and has_checkpoint(self.checkpoint_dir)
        self.volume = checkpoints.new_volume(self.section.volume_params(), None if load else self.checkpoint_dir)
        self.replica = DictionaryReplica()
        self.frames_integrated = 0
        self.updates_applied = 0
        # Each robot's stream: chain, join, counts (openfusion.mapping.robot_streams).
        self.robots = RobotStreams(self.section.join_params(), parse_robot_frames(self.section.robot_frames))
        self._robot_sources: dict[bytes, str] = {}  # frame publisher (one bridge per robot) -> robot
        self.last_integrated_frame_id: int | None = None  # of any robot
        # The last frame id recorded in the newest checkpoint this service loaded or saved (first robot's).
        self.checkpoint_last_frame_id: int | None = None
        self.checkpoint_failures = 0
        # Bumped by every change of the map (frames, updates, merges, load, reset): region
        # summaries are cached per version. Keys below _key_horizon are ones this map has seen.
        self.map_version = 0
        self._key_horizon = 0
        self._summary: SummaryCache | None = None
        self._summary_lock = threading.Lock()
        self._updates = AppliedUpdates()  # which semantic updates were taken (a render may wait for one)
        #: Held by a save, a load and a reset: a load or reset waits for a save to end (a save
        #: holds the volume lock only for its copies, so they would otherwise overlap).
        self._swap_lock = threading.Lock()
        #: (monotonic s, the volume's change clock) of recent loop turns: which tiles have settled.
        self._change_marks: list[tuple[float, int]] = []
        self._dirty = False
        self._last_checkpoint = time.monotonic()
        self.saving = False
        self._memory = MemoryPeaks()
        self._runner: ServiceRunner | None = None
        self._frames_sub: Subscriber[RgbdFrame] | None = None
        self._progress_pub: Publisher | None = None
        # Resume (module docstring): this process's name; chains and announcements are per robot.
        self.incarnation = uuid.uuid4().hex[:16]
        self.integrate_busy_s = 0.0
        self._recent_renders: OrderedDict[tuple[str, int], RenderedView] = OrderedDict()  # (robot, frame id) -> render
        self.joiner = RobotJoiner(self, integrate_held=self._integrate_held)
        if load:
            self._load(self.checkpoint_dir, fallback=True, restore_counts=True)  # type: ignore[arg-type]

    # ----------------------------------------------------------- the first robot's chain (one robot: the map's)
    def _first_robot(self) -> RobotStream | None:
        return next(iter(self.robots), None)

    @property
    def last_frame_id(self) -> int | None:
        """The last frame taken of the map's first robot (one robot: the map's chain)."""
        robot = self._first_robot()
        return None if robot is None else robot.last_taken

    @property
    def playback(self) -> str:
        robot = self._first_robot()
        return "" if robot is None else robot.playback

    @property
    def waiting_for_frames(self) -> bool:
        """Some robot waits for the playback frame after the last one it holds."""
        return any(robot.waiting for robot in self.robots)

    def _map_empty(self) -> bool:
        return self.volume.num_blocks == 0

    def _robot(self, name: str) -> RobotStream:
        with self._lock:
            return self.robots.get(name, map_empty=self._map_empty())

    # ------------------------------------------------------------------ state changes
    def _set_memory_stats(self) -> None:
        if self._runner is not None:
            publish_map_size(self._runner.stats, self.volume)

    def _map_changed(self, *, reset_keys: bool = False) -> None:
        """Call with ``self._lock`` held after any change of the volume."""
        self.map_version += 1
        if reset_keys:  # a load or reset: another volume, whose ray hits these renders are not
            self._key_horizon = 0
            self._recent_renders.clear()

    def _count(self, name: str, by: float = 1.0) -> None:
        if self._runner is not None:
            self._runner.stats.incr(name, by)

    # ---------------------------------------------------------------------- handlers
    def _map_pose(self, robot_name: str, T_odom_cam: np.ndarray) -> np.ndarray:
        """A robot's pose in the map's frame; a robot not joined yet is refused (``robot_not_joined``)."""
        robot = self._robot(robot_name)
        if robot.state != "joined":
            raise RequestError("robot_not_joined", f"robot {robot_name!r} is not joined to the map's frame yet "
                               f"({robot.submap.num_frames} frames in its submap)")
        return robot.T_map_odom @ np.asarray(T_odom_cam, np.float64)

    def on_update(self, msg: SemanticUpdate) -> None:
        try:
            self._apply_update(msg)
        finally:  # written, refused or failed: a render waiting for it goes on (applied_updates)
            self._updates.applied(msg.source, msg.seq)

    def _apply_update(self, msg: SemanticUpdate) -> None:
        check_update(msg)
        with self._lock:  # resolved and applied under the lock on_delta relabels under: no orphan keys
            robot = self._robot(msg.robot)
            if robot.state != "joined":  # its render was refused: no update should come; nothing is written
                logger.warning("geometry: semantic update of frame %d of robot %s dropped: the robot is not joined",
                               msg.frame_id, msg.robot)
                self._count(GeometryCounter.UPDATES_DROPPED_NOT_JOINED)
                return
            key_map = self.replica.resolve_keys(msg.key_map)  # planned before a merge this replica has seen
            update = self.volume.apply_update(
                robot.T_map_odom @ msg.T_world_cam, msg.intrinsics, key_map, msg.conf_map,
                observed_depth_m=msg.depth_m, rendered=self._recent_renders.pop((msg.robot, msg.frame_id), None),
            )
            self.updates_applied += 1
            self._map_changed()
            if msg.key_map.size:
                self._key_horizon = max(self._key_horizon, int(msg.key_map.max()) + 1)
            self._dirty = True
        self._count(GeometryCounter.UPDATES_APPLIED)
        if update.reused_render:
            self._count(GeometryCounter.UPDATES_REUSED_RENDER)
        if self._runner is not None:
            self._runner.stats.set(GeometryCounter.LAST_UPDATE_FRAME_ID, msg.frame_id)

    def handle_render(self, req: RenderRequest) -> RenderReply:
        pixels = req.width_px * req.height_px
        if pixels > self.section.max_render_pixels:
            raise RequestError(
                "too_large",
                f"render of {req.width_px}x{req.height_px} exceeds max_render_pixels={self.section.max_render_pixels}",
            )
        if not self._updates.wait(req.after_update_source, req.after_update_seq, self.section.render_update_wait_s):
            logger.debug("geometry: render of frame %d: update %d of %s not here after %.2f s; rendering without it",
                         req.frame_id, req.after_update_seq, req.after_update_source, self.section.render_update_wait_s)
            self._count(GeometryCounter.RENDER_UPDATE_WAIT_TIMEOUTS)
        with self._lock:
            started = time.monotonic()  # the view's own time, not the wait for an integration to end
            T_map_cam = self._map_pose(req.robot, req.T_world_cam)
            if req.probe_depth_m is not None:  # with the frame's depth: probed near it on a large map
                view = self.volume.candidate_view(T_map_cam, req.intrinsics, req.probe_depth_m, req.probe_above_blocks)
            else:
                view = self.volume.render(T_map_cam, req.intrinsics)
            if req.after_update_source:
                # A semantic step's view (a candidate's names no update): the update for this frame
                # comes next, at the same pose and size, and writes through these hits instead of
                # casting again (the volume checks the pose, the size and that the grid's buffers
                # have not moved since).
                self._recent_renders[(req.robot, req.frame_id)] = view
                while len(self._recent_renders) > RECENT_RENDERS:
                    self._recent_renders.popitem(last=False)
            busy_s = time.monotonic() - started
        probed = view.probed
        self._count(GeometryCounter.PROBES if probed else GeometryCounter.RENDERS)
        self._count(GeometryCounter.PROBE_BUSY_S if probed else GeometryCounter.RENDER_BUSY_S, busy_s)
        return RenderReply(frame_id=req.frame_id, key_map=view.key_map, conf_map=view.conf_map, depth_m=view.depth_m,
                           T_map_cam=T_map_cam)

    def _points_cap(self, requested: int | None) -> int:
        cap = self.section.max_points_reply
        if requested is not None and requested > cap:
            raise RequestError(
                "too_large", f"max_points={requested} exceeds the service limit max_points_reply={cap}"
            )
        return requested or cap

    def handle_points(self, req: PointsRequest) -> PointsReply:
        cap = self._points_cap(req.max_points)
        with self._lock:
            volume = self.volume
        pts = volume.extract_points(keys=req.keys, max_points=None)  # a read-out job: asked for holding no lock
        n = len(pts.points)
        if n > cap:
            idx = np.sort(np.random.default_rng(0).choice(n, size=cap, replace=False))
            return PointsReply(
                points=pts.points[idx], colors=pts.colors[idx], keys=pts.keys[idx], truncated=True
            )
        return PointsReply(points=pts.points, colors=pts.colors, keys=pts.keys, truncated=False)

    def handle_regions(self, req: RegionSummaryRequest) -> RegionSummaryReply:
        with self._summary_lock:  # one computation at a time; later askers get its result
            cached = self._summary
            if cached is None or (
                cached.map_version != self.map_version
                and (
                    req.fresh or time.monotonic() - cached.computed_at >= self.section.regions_min_interval_s
                )
            ):
                with self._lock:
                    volume, version, horizon = self.volume, self.map_version, self._key_horizon
                # Per tile, only changed tiles read out again; the lock is held for each chunk's copy.
                table = volume.region_table(lock=self._lock)
                if len(table):  # keys present in the map (e.g. loaded from a checkpoint) are covered too
                    horizon = max(horizon, int(table.keys[-1]) + 1)
                cached = self._summary = SummaryCache(version, horizon, table)
        return cached.reply(req.keys)

    def handle_contacts(self, req: RegionContactsRequest) -> RegionContactsReply:
        with self._lock:
            volume, version = self.volume, self.map_version
        # Per tile, only tiles changed since the last pass counted again (copies under the lock).
        c = volume.region_contacts(radius_vox=req.radius_vox, lock=self._lock)
        return RegionContactsReply(map_version=version, keys=c.keys.astype(np.int32), surface_voxels=c.surface_voxels,
                                   pair_a=c.pair_a.astype(np.int32), pair_b=c.pair_b.astype(np.int32),
                                   contact_a=c.contact_a, contact_b=c.contact_b)

    def handle_mesh(self, req: MeshRequest) -> MeshReply:
        with self._lock:
            volume = self.volume
        mesh = volume.extract_mesh(keys=req.keys)  # a read-out job: asked for holding no lock
        if len(mesh.vertices) > self.section.max_points_reply:
            raise RequestError(
                "too_large",
                f"mesh has {len(mesh.vertices)} vertices, over max_points_reply={self.section.max_points_reply}; "
                "ask for fewer keys",
            )
        return MeshReply(
            vertices=mesh.vertices, triangles=mesh.triangles, vertex_colors=mesh.colors, vertex_keys=mesh.keys
        )

    def handle_dictionary(self, _req: DictionaryRequest) -> DictionarySnapshot:
        snap = self.replica.snapshot()
        if snap is None:
            raise RequestError("no_dictionary", "the geometry service holds no dictionary yet")
        return snap

    def handle_control(self, req: ControlRequest, *, action: str) -> ControlReply:
        if req.action != action:
            raise RequestError("bad_request", f"this key takes action {action!r}, got {req.action!r}")
        if action == "save":
            try:
                self.merge_before_save()
                path = self.save(sharding.part_path(Path(req.path), self.shard) if req.path else None)
            except Exception:  # counted (an asker whose request timed out learns it from health), then raised
                self._count(GeometryCounter.SAVE_FAILURES)
                raise
            self._count(GeometryCounter.SAVES)
            return ControlReply(ok=True, message=f"saved to {path}")
        if action == "load":
            # A named file is read strictly; our own checkpoint falls back to its .prev file.
            path = sharding.part_path(Path(req.path), self.shard) if req.path else self.checkpoint_dir
            own = not req.path
            if path is None or not (has_checkpoint(path) if own else resolve_map_path(path).exists()):
                raise RequestError("not_found", f"no map at {path}")
            try:
                with self._swap_lock:
                    self._load(path, fallback=own)
            except MapFormatError as exc:
                raise RequestError("bad_map", str(exc)) from exc
            return ControlReply(ok=True, message=f"loaded {path}")
        with self._swap_lock, self._lock:
            self.volume.close()
            self.volume = checkpoints.new_volume(self.section.volume_params(), self.checkpoint_dir, fresh=True)
            self.replica.reset(None)
            self.frames_integrated = 0
            self.robots = RobotStreams(self.section.join_params(), parse_robot_frames(self.section.robot_frames))
            self._map_changed(reset_keys=True)
            self._dirty = True
        return ControlReply(ok=True, message="map reset")

    # ------------------------------------------------------------------------ wiring
    def setup(self, runner: ServiceRunner) -> None:
        self._runner = runner
        self._progress_pub = runner.publisher(GEOMETRY_PROGRESS)
        # A replica with no checkpoint copies its peer's (peer_copy.py); what comes meanwhile is held
        # and taken after the copy (start_buffer.py), so the frames are subscribed first.
        held = self.held_at_start = self.start_buffer()
        if held is not None:
            self._subscribe_inputs(runner, held)
        self.copy_from_peer_at_start(runner)
        if held is None:
            self._subscribe_inputs(runner, None)
        else:
            self.release_held(runner, held)
        runner.stats.robots_provider = self.robot_status
        runner.subscriber(DICTIONARY_DELTA, self.on_delta, queue_size=256)
        # One shard (the default): today's keys; shard I of N: the same endpoints under its own
        # segment (…/geometry/render/geometry-0of2), merged by readers (openfusion.shard_client).
        # Renders: two workers, so a render waiting for a semantic update (up to
        # render_update_wait_s) does not hold up the semantic service's scoring renders behind it.
        sharding.serve(runner, GEOMETRY_RENDER, self.handle_render, self.shard, workers=RENDER_WORKERS)
        for endpoint, handler in ((GEOMETRY_POINTS, self.handle_points),
                                  (GEOMETRY_MESH, self.handle_mesh), (GEOMETRY_REGIONS, self.handle_regions),
                                  (GEOMETRY_DICTIONARY, self.handle_dictionary),
                                  (GEOMETRY_CONTACTS, self.handle_contacts)):
            sharding.serve(runner, endpoint, handler, self.shard)
        for action, endpoint in CONTROL.items():
            sharding.serve(runner, endpoint, lambda req, action=action: self.handle_control(req, action=action),
                           self.shard)
        self.serve_checkpoints(runner)  # its checkpoint to a peer that starts without one, at its own key
        runner.stats.set(GeometryCounter.FRAMES_INTEGRATED, self.frames_integrated)
        runner.stats.set(GeometryCounter.INTEGRATE_BUSY_S, self.integrate_busy_s)
        self._set_memory_stats()
        runner.stats.set(GeometryCounter.CHECKPOINT_FAILURES, self.checkpoint_failures)
        for name in (GeometryCounter.FRAMES_DUPLICATE, GeometryCounter.FRAMES_OUT_OF_ORDER):
            runner.stats.set(name, 0)
        if self.last_frame_id is not None:
            runner.stats.set(GeometryCounter.LAST_FRAME_ID, self.last_frame_id)
        for name in (GeometryCounter.FRAMES_HELD, GeometryCounter.JOIN_ATTEMPTS, GeometryCounter.ROBOTS_JOINED):
            runner.stats.set(name, 0)
        self._set_checkpoint_frame()
        self._memory.start(runner.stats)
        self.announce()  # every robot the checkpoint holds: where its playback continues
        self.joiner.start()

    def _subscribe_inputs(self, runner: ServiceRunner, held: StartBuffer | None) -> None:
        """Frames and semantic updates; with ``held``, what comes is held until it is released."""
        on_frame, on_update = self.on_frame, self.on_update
        if held is not None:
            def on_frame(msg: RgbdFrame) -> None:
                if not held.offer(FRAME, msg):
                    self.on_frame(msg)

            def on_update(msg: SemanticUpdate) -> None:
                if not held.offer(UPDATE, msg):
                    self.on_update(msg)
        # One queue per robot's bridge, served in turn: one robot's backlog never starves another.
        self._frames_sub = runner.subscriber(SENSOR_RGBD, on_frame, queue_size=self.section.frame_queue_size,
                                             fair=True)
        runner.subscriber(SEMANTIC_UPDATE, on_update, queue_size=64)

    def loop(self, runner: ServiceRunner) -> None:
        period = self.section.checkpoint_period_s
        while not runner.wait(min(period, 1.0) if period > 0 else 1.0):
            if self.waiting_for_frames:  # until each robot's next playback frame comes in order
                self.announce()
            if (
                period > 0
                and self._dirty
                and self.checkpoint_dir is not None
                and time.monotonic() - self._last_checkpoint >= period
            ):
                try:
                    self.save(summary=False)
                except CheckpointFailed:  # logged and counted by save(); mapping goes on
                    runner.stats.add_error()
                except Exception:  # not an OSError: logged with its traceback; tried again one period later
                    logger.exception("geometry: checkpoint to %s failed; the map is kept in memory",
                                     self.checkpoint_dir)
                    self._last_checkpoint = time.monotonic()
                    self.checkpoint_failures += 1
                    self._count(GeometryCounter.CHECKPOINT_FAILURES)
                    runner.stats.add_error()
            self._read_out_settled_tiles()
            if self.checkpoint_server is not None:
                self.checkpoint_server.expire()

    def _read_out_settled_tiles(self) -> None:
        """Idle work: read out the region-summary parts of tiles nothing changed for
        :data:`SETTLE_S` (a room the camera left), at most :data:`IDLE_READOUT_S` per turn, so a
        save or a region query has only the recent tiles left to read (a floor's final save read
        the whole map out: 50-150 s). Tiles the camera is working on are left for later."""
        with self._lock:
            volume = self.volume
            now = time.monotonic()
            self._change_marks.append((now, volume.change_clock))
        marks = [m for m in self._change_marks if now - m[0] <= 2 * SETTLE_S]
        self._change_marks = marks
        settled = [clock for t, clock in marks if now - t >= SETTLE_S]
        if not settled:
            return
        try:
            with self._swap_lock:
                if self.volume is volume:
                    volume.refresh_region_table(settled_clock=settled[-1], lock=self._lock, max_s=IDLE_READOUT_S)
        except Exception:  # idle work: a failure here only leaves the work to the next save
            logger.exception("geometry: reading out settled tiles failed")

    def close(self) -> None:
        self.joiner.stop()
        self._memory.stop()
        if self.checkpoint_server is not None:
            self.checkpoint_server.close()
        # The session is closed by now: this last checkpoint is saved without a merge pass.
        if self._dirty and self.checkpoint_dir is not None:
            with contextlib.suppress(CheckpointFailed):  # logged by save()
                self.save()  # with summaries: this one is what `query --map-dir` reads after a stop
        self.volume.close()


DEFINITION = ServiceDefinition(
    name="geometry",
    help="integrate frames into the semantic TSDF, render region keys, serve points/meshes, checkpoint",
    config_model=GeometryConfig,
    build=GeometryService,
    instance_name=lambda config: config.geometry.shard_service.service,  # geometry, geometry-0of2, geometry-0of2-r1
)
