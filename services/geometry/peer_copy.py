"""A replica that starts with no checkpoint of its own copies its peer's (docs/SHARDS.md, "Replicas").

Two halves, both parts of the geometry service (the file steps are library code:
:mod:`openfusion.mapping.checkpoint_copy`):

Serving (every geometry; one with no checkpoint folder answers ``no_checkpoint``):
:class:`CheckpointServer` answers, at the
process's own key (:meth:`~openfusion.wire.endpoints.Endpoint.peer_key`:
``…/geometry/checkpoint/list/geometry-0of2-r1``, so a listing and its chunks reach the one process
that holds the snapshot):

- ``geometry/checkpoint/list``: a checkpoint first when the request asks (``checkpoint_first``,
  the default) and anything changed since the last one, then a **snapshot** of the newest committed
  checkpoint (copy-on-serve, why: :mod:`openfusion.mapping.checkpoint_copy`) under
  ``{checkpoint folder}/.peer-snapshots/``, listed (names, sizes, SHA-256);
- ``geometry/checkpoint/chunk``: at most :data:`~openfusion.wire.limits.MAX_CHECKPOINT_CHUNK_BYTES`
  of one of its files, with the chunk's digest;
- ``geometry/checkpoint/release``: the snapshot is deleted (else after :data:`SNAPSHOT_IDLE_S`
  without a request, and at shutdown; a start removes those a crash left). At most
  :data:`MAX_SNAPSHOTS` at once (``busy`` beyond: the asker tries another peer).

Copying (:meth:`PeerCopy.copy_from_peer_at_start`, in ``setup``; frames and semantic updates that
come meanwhile are held and taken after it, :mod:`.start_buffer`): a
geometry with a checkpoint folder holding no checkpoint, and ``copy_from_peer`` (default: on for a
replica, ``replica >= 1``; ``--copy-from-peer`` for replica 0 whose disk was lost), finds the live
peers of its shard by liveliness (same shard, other replica numbers; replica 0 first), asks one for
its checkpoint, writes the files into a folder of its own, checks every chunk's and file's digest
and opens the copy as a map, puts it in its checkpoint folder and loads it exactly as a restart
loads its own checkpoint (its robots' chains, ``frames_integrated``, the dictionary). Then it
announces the last frame it holds as a restart does: the bridge of a recording replays the frames
after it; a live source's frames are taken as they come. A peer that does not answer, goes away
mid-copy, or sends a chunk or file that fails its digest: logged, counted
(``peer_copy_failures``), the partial copy removed, the next peer tried; with none left the
geometry starts empty with a warning saying what a live source loses.
"""

from __future__ import annotations

import hashlib
import logging
import shutil
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import zenoh

from openfusion.bus import QueryError, RequestError, ServiceRunner, get, live_services
from openfusion.mapping.checkpoint_copy import (
    CheckpointCopyError,
    CopyReceiver,
    FileEntry,
    Snapshot,
    free_bytes,
    install_copy,
    read_chunk,
    snapshot_checkpoint,
    verify_store,
)
from openfusion.services.geometry import checkpoints
from openfusion.services.geometry.start_buffer import UPDATE, StartBuffer
from openfusion.wire.counters import GeometryCounter
from openfusion.wire.endpoints import (
    GEOMETRY_CHECKPOINT_CHUNK,
    GEOMETRY_CHECKPOINT_LIST,
    GEOMETRY_CHECKPOINT_RELEASE,
)
from openfusion.wire.keys import KeySpace, ShardId
from openfusion.wire.limits import MAX_CHECKPOINT_CHUNK_BYTES
from openfusion.wire.schemas import (
    CheckpointChunk,
    CheckpointChunkRequest,
    CheckpointFile,
    CheckpointListing,
    CheckpointListRequest,
    CheckpointRelease,
    ControlReply,
)

if TYPE_CHECKING:
    from openfusion.mapping import SemanticVolume
    from openfusion.services.geometry.section import GeometrySection

logger = logging.getLogger("openfusion.services.geometry.service")

#: Where a geometry keeps the snapshots it serves, inside its checkpoint folder.
SNAPSHOTS_DIR = ".peer-snapshots"
#: Where a copy is written before it is checked and installed, inside the checkpoint folder.
INCOMING_PREFIX = ".peer-copy-"
#: Snapshots served at once (each a compacted copy of the map on the peer's disk).
MAX_SNAPSHOTS = 2
#: A snapshot nobody asked about for this long is deleted (its asker died or gave up).
SNAPSHOT_IDLE_S = 120.0
#: How long the liveliness query that finds the peers waits.
PEERS_TIMEOUT_S = 1.0
#: The shortest time one chunk is given (:func:`chunk_timeout`).
MIN_CHUNK_TIMEOUT_S = 5.0
#: Room left on the disk beyond the copy's size.
DISK_MARGIN_BYTES = 64 * 1024 * 1024


class CheckpointServer:
    """Serves snapshots of one geometry's checkpoint to its peers (module docstring)."""

    def __init__(self, service: PeerCopy) -> None:
        self.service = service
        #: None: a geometry with no checkpoint folder answers every listing ``no_checkpoint`` at once.
        self.folder = None if service.checkpoint_dir is None else service.checkpoint_dir / SNAPSHOTS_DIR
        self._lock = threading.Lock()
        self._snapshots: dict[str, tuple[Snapshot, float]] = {}  # id -> (snapshot, last used, monotonic s)
        if self.folder is not None:
            shutil.rmtree(self.folder, ignore_errors=True)  # a crash's leftovers

    def setup(self, runner: ServiceRunner) -> None:
        me = self.service.shard
        for endpoint, handler in ((GEOMETRY_CHECKPOINT_LIST, self.handle_list),
                                  (GEOMETRY_CHECKPOINT_CHUNK, self.handle_chunk),
                                  (GEOMETRY_CHECKPOINT_RELEASE, self.handle_release)):
            runner.queryable(endpoint.at_process(me), handler)

    def _count(self, name: str, by: float = 1.0) -> None:
        self.service._count(name, by)  # noqa: SLF001 (the service's counter helper)

    def handle_list(self, req: CheckpointListRequest) -> CheckpointListing:
        svc = self.service
        if self.folder is None or svc.checkpoint_dir is None:
            raise RequestError("no_checkpoint", f"{svc.shard.service} keeps no checkpoint (no map_dir)")
        self.expire()
        with self._lock:
            if len(self._snapshots) >= MAX_SNAPSHOTS:
                raise RequestError("busy", f"{svc.shard.service} serves {MAX_SNAPSHOTS} snapshots already")
        if req.checkpoint_first and svc._dirty:  # noqa: SLF001 (something changed since the last checkpoint)
            svc.save(summary=False)  # CheckpointFailed is a RequestError: answered as such
        try:
            with svc._swap_lock:  # noqa: SLF001 (no load or reset swaps the store while it is copied)
                snap = snapshot_checkpoint(svc.checkpoint_dir, self.folder)  # type: ignore[arg-type]
        except CheckpointCopyError as exc:
            raise RequestError(exc.reason, str(exc)) from exc
        with self._lock:
            self._snapshots[snap.snapshot_id] = (snap, time.monotonic())
        self._count(GeometryCounter.PEER_SNAPSHOTS_SERVED)
        logger.info("geometry: serving snapshot %s of checkpoint (last frame %d, %d tiles, %d bytes) to %s",
                    snap.snapshot_id[:12], snap.last_frame_id, snap.tiles, snap.total_bytes, req.requester or "a peer")
        return CheckpointListing(
            snapshot_id=snap.snapshot_id, source=svc.shard.service,
            files=[CheckpointFile(name=f.name, size_bytes=f.size_bytes, sha256=f.sha256) for f in snap.files],
            chunk_bytes=MAX_CHECKPOINT_CHUNK_BYTES, last_frame_id=snap.last_frame_id,
            frames_integrated=snap.frames_integrated, tiles=snap.tiles,
        )

    def _snapshot(self, snapshot_id: str) -> Snapshot:
        with self._lock:
            entry = self._snapshots.get(snapshot_id)
            if entry is None:
                raise RequestError("unknown_snapshot", f"no snapshot {snapshot_id} here (released, expired, or this "
                                   "geometry restarted): ask for a listing again")
            self._snapshots[snapshot_id] = (entry[0], time.monotonic())
            return entry[0]

    def handle_chunk(self, req: CheckpointChunkRequest) -> CheckpointChunk:
        snap = self._snapshot(req.snapshot_id)
        try:
            data = read_chunk(snap, req.name, req.offset_bytes, req.length_bytes)
        except CheckpointCopyError as exc:
            raise RequestError(exc.reason, str(exc)) from exc
        self._count(GeometryCounter.PEER_BYTES_SERVED, len(data))
        return CheckpointChunk(snapshot_id=req.snapshot_id, name=req.name, offset_bytes=req.offset_bytes,
                               data=np.frombuffer(data, np.uint8), sha256=hashlib.sha256(data).hexdigest())

    def handle_release(self, req: CheckpointRelease) -> ControlReply:
        with self._lock:
            entry = self._snapshots.pop(req.snapshot_id, None)
        if entry is not None:
            entry[0].remove()
        return ControlReply(ok=entry is not None, message="released" if entry is not None else "no such snapshot")

    def expire(self) -> None:
        """Delete snapshots idle for :data:`SNAPSHOT_IDLE_S`."""
        now = time.monotonic()
        with self._lock:
            stale = [sid for sid, (_, used) in self._snapshots.items() if now - used >= SNAPSHOT_IDLE_S]
            gone = [self._snapshots.pop(sid)[0] for sid in stale]
        for snap in gone:
            logger.info("geometry: snapshot %s expired unreleased", snap.snapshot_id[:12])
            snap.remove()

    def close(self) -> None:
        with self._lock:
            gone = [s for s, _ in self._snapshots.values()]
            self._snapshots.clear()
        for snap in gone:
            snap.remove()
        if self.folder is not None:
            shutil.rmtree(self.folder, ignore_errors=True)


@dataclass(frozen=True)
class CopyResult:
    """A verified copy of a peer's checkpoint, in ``folder`` (not yet installed)."""

    source: str
    folder: Path
    last_frame_id: int
    frames_integrated: int
    tiles: int
    bytes: int
    seconds: float


def peers_of(names: list[str], me: ShardId) -> list[ShardId]:
    """Of the service ``names``, the geometry processes of ``me``'s shard other than ``me``
    (replica 0 first)."""
    found = (ShardId.of_service(n) for n in names)
    return sorted((s for s in found if s is not None and s.part == me.part and s.replica != me.replica),
                  key=lambda s: s.replica)


def find_peers(session: zenoh.Session, keys: KeySpace, me: ShardId, *, timeout_s: float = PEERS_TIMEOUT_S) -> list[ShardId]:
    """The live peers of ``me`` (:func:`peers_of` the services whose liveliness token is present)."""
    return peers_of(live_services(session, keys, timeout_s=timeout_s), me)


def chunk_timeout(timeout_s: float) -> float:
    """How long one chunk may take: a quarter of the listing's (which includes the peer's checkpoint
    and snapshot; 15 s at the default 60 s: 4 MiB at 0.3 MB/s), at least :data:`MIN_CHUNK_TIMEOUT_S`
    (never more than the listing's), so a peer gone mid-copy is given up sooner than one
    checkpointing a large map."""
    return min(timeout_s, max(MIN_CHUNK_TIMEOUT_S, timeout_s / 4))


def copy_checkpoint(session: zenoh.Session, keys: KeySpace, peer: ShardId, into: Path, *, requester: str,
                    checkpoint_first: bool = True, timeout_s: float = 60.0) -> CopyResult:
    """Copy ``peer``'s checkpoint into the new folder ``into`` and check it (module docstring).
    :class:`~openfusion.bus.QueryError` (the peer did not answer, refused, went away) or
    :class:`~openfusion.mapping.checkpoint_copy.CheckpointCopyError` (a bad chunk, digest or copy;
    no room on the disk); ``into`` is removed on any failure."""
    started = time.monotonic()
    listing = get(session, GEOMETRY_CHECKPOINT_LIST.peer_key(keys, peer),
                  CheckpointListRequest(checkpoint_first=checkpoint_first, requester=requester), CheckpointListing,
                  timeout_s=timeout_s, service=peer.service)
    try:
        need = listing.total_bytes + DISK_MARGIN_BYTES
        if free_bytes(into.parent) < need:
            raise CheckpointCopyError("no_space", f"{into.parent}: {free_bytes(into.parent)} bytes free, the copy of "
                                      f"{peer.service}'s checkpoint needs {need}")
        receiver = CopyReceiver([FileEntry(f.name, f.size_bytes, f.sha256) for f in listing.files], into)
        try:
            chunk_key = GEOMETRY_CHECKPOINT_CHUNK.peer_key(keys, peer)
            chunk_timeout_s = chunk_timeout(timeout_s)
            for f in listing.files:
                while not receiver.done(f.name):
                    offset = receiver.next_offset(f.name)
                    length = min(listing.chunk_bytes, f.size_bytes - offset)
                    chunk = get(session, chunk_key, CheckpointChunkRequest(
                        snapshot_id=listing.snapshot_id, name=f.name, offset_bytes=offset, length_bytes=length),
                        CheckpointChunk, timeout_s=chunk_timeout_s, service=peer.service)
                    if chunk.snapshot_id != listing.snapshot_id or chunk.name != f.name:
                        raise CheckpointCopyError("bad_chunk", f"asked {f.name} of snapshot {listing.snapshot_id}, "
                                                  f"got {chunk.name} of {chunk.snapshot_id}")
                    receiver.write(f.name, chunk.offset_bytes, chunk.data.data, chunk.sha256)
            receiver.finish()
            info = verify_store(into)
        except BaseException:
            receiver.discard()
            raise
    finally:
        try:
            get(session, GEOMETRY_CHECKPOINT_RELEASE.peer_key(keys, peer), CheckpointRelease(
                snapshot_id=listing.snapshot_id), ControlReply, timeout_s=2.0, service=peer.service)
        except QueryError as exc:  # the peer deletes it when idle anyway
            logger.debug("geometry: releasing snapshot %s: %s", listing.snapshot_id[:12], exc)
    return CopyResult(listing.source, into, info["last_frame_id"], info["frames_integrated"], info["tiles"],
                      receiver.bytes_written, time.monotonic() - started)


def wants_peer_copy(copy_from_peer: bool | None, shard: ShardId) -> bool:
    """Whether a geometry with no checkpoint asks its peers: ``copy_from_peer``, or by default for a replica."""
    return shard.replica >= 1 if copy_from_peer is None else bool(copy_from_peer)


class PeerCopy:
    """The start-up copy and the serving side, as a part of the geometry service (mixed into it;
    the state it works on is the service's)."""

    section: GeometrySection
    shard: ShardId
    checkpoint_dir: Path | None
    volume: SemanticVolume
    frames_integrated: int
    _lock: threading.RLock
    _swap_lock: threading.Lock
    _dirty: bool
    checkpoint_server: CheckpointServer | None = None
    # and the service's save(), _load(), _count(), _robot(), on_frame() and on_update()
    save: Any
    _load: Any
    _count: Any
    _robot: Any
    on_frame: Any
    on_update: Any

    def wants_copy_at_start(self) -> bool:
        """Whether :meth:`copy_from_peer_at_start` will ask its peers: a checkpoint folder without a
        checkpoint, loading on start, and ``copy_from_peer`` (by default a replica)."""
        folder = self.checkpoint_dir
        return (folder is not None and self.section.load_on_start
                and wants_peer_copy(self.section.copy_from_peer, self.shard) and not checkpoints.has_checkpoint(folder))

    def start_buffer(self) -> StartBuffer | None:
        """A buffer for what comes during the copy (:mod:`.start_buffer`), or None when no copy
        will run or ``peer_copy_buffer_frames`` is 0."""
        if self.section.peer_copy_buffer_frames <= 0 or not self.wants_copy_at_start():
            return None
        return StartBuffer(self.section.peer_copy_buffer_frames)

    def release_held(self, runner: ServiceRunner, held: StartBuffer) -> None:
        """After the copy: what came during it, in order, through the service's handlers; a live
        frame the copy holds already is a duplicate (counted, dropped). A live frame is taken for
        one the copy holds when its id is at or below the copy's last and its stamp not later than
        that frame's (``RobotStream.copy_holds``; a copy from before stamps were recorded: the id
        alone). Its bridge restarted during the copy when the id is lower but the stamp later (a
        bridge that stamps by the clock), or when the robot's held ids went back (one whose stamps
        start again too): from there on its frames are new."""
        last_held: dict[str, int] = {}  # per robot, the id of the live frame held before
        restarted: set[str] = set()

        def handle(kind: str, msg: Any) -> None:
            if kind == UPDATE:
                self.on_update(msg)
                return
            if msg.prev_frame_id is None:
                before = last_held.get(msg.robot)
                last_held[msg.robot] = msg.frame_id
                if before is not None and msg.frame_id < before and msg.robot not in restarted:
                    restarted.add(msg.robot)
                    logger.info("geometry: robot %s's live frames went back from id %d to %d during the peer "
                                "copy (its bridge restarted): taking them as new", msg.robot, before, msg.frame_id)
                robot = self._robot(msg.robot)
                if msg.robot not in restarted and robot.copy_holds(frame_id=msg.frame_id, stamp_ns=msg.stamp_ns):
                    self._count(GeometryCounter.FRAMES_DUPLICATE)
                    return
            self.on_frame(msg)

        held.release(handle)
        runner.stats.set(GeometryCounter.PEER_COPY_FRAMES_HELD, held.frames)
        runner.stats.set(GeometryCounter.PEER_COPY_FRAMES_LOST, held.frames_lost)
        if held.frames_lost or held.updates_lost:
            logger.warning("geometry: %d frames and %d semantic updates came during the peer copy beyond what is held "
                           "(peer_copy_buffer_frames=%d): they are not in this map", held.frames_lost,
                           held.updates_lost, held.max_frames)
        elif held.frames or held.updates:
            logger.info("geometry: took %d frames and %d semantic updates that came during the peer copy",
                        held.frames, held.updates)

    def serve_checkpoints(self, runner: ServiceRunner) -> None:
        """Answer the peers' checkpoint requests (without a checkpoint folder: ``no_checkpoint``, at once)."""
        self.checkpoint_server = CheckpointServer(self)
        self.checkpoint_server.setup(runner)
        for name in (GeometryCounter.PEER_SNAPSHOTS_SERVED, GeometryCounter.PEER_BYTES_SERVED):
            runner.stats.set(name, 0)

    def copy_from_peer_at_start(self, runner: ServiceRunner) -> bool:
        """With no checkpoint of its own, copy a peer's and load it as a restart loads its own
        (module docstring). True when a copy was loaded."""
        stats = runner.stats
        for name in (GeometryCounter.PEER_COPIES, GeometryCounter.PEER_COPY_FAILURES, GeometryCounter.PEER_COPY_TILES,
                     GeometryCounter.PEER_COPY_BYTES):
            stats.set(name, 0)
        stats.set(GeometryCounter.PEER_COPY_FRAME_ID, -1)
        folder = self.checkpoint_dir
        if folder is None or not self.wants_copy_at_start():
            return False
        session = runner.session
        assert session is not None
        peers = find_peers(session, runner.keys, self.shard)
        if not peers:
            logger.warning("geometry: %s has no checkpoint and no live peer of shard %s to copy one from: starting "
                           "empty (a recording is replayed from its start; a live source's earlier frames are not "
                           "in this map)", self.shard.service, self.shard.part)
            return False
        for stale in folder.glob(INCOMING_PREFIX + "*"):  # a copy a crash interrupted: never loaded
            shutil.rmtree(stale, ignore_errors=True)
        failed = 0
        for peer in peers:
            into = folder / f"{INCOMING_PREFIX}{peer.service}"
            shutil.rmtree(into, ignore_errors=True)
            try:
                result = copy_checkpoint(session, runner.keys, peer, into, requester=self.shard.service,
                                         checkpoint_first=self.section.peer_copy_checkpoint_first,
                                         timeout_s=self.section.peer_copy_timeout_s)
            except (QueryError, CheckpointCopyError, OSError) as exc:
                shutil.rmtree(into, ignore_errors=True)
                if isinstance(exc, QueryError) and exc.code == "no_checkpoint":
                    # A peer that started with this one: nothing to copy, not a failure.
                    logger.info("geometry: %s has no checkpoint to copy yet", peer.service)
                    continue
                failed += 1
                stats.incr(GeometryCounter.PEER_COPY_FAILURES)
                stats.add_error()
                logger.warning("geometry: copying the checkpoint of %s failed (%s); the partial copy is discarded",
                               peer.service, exc)
                continue
            with self._lock:
                self.volume.close()  # the empty store of the checkpoint folder: replaced by the copy
                install_copy(result.folder, folder)
            self._load(folder, fallback=False, restore_counts=True)
            stats.incr(GeometryCounter.PEER_COPIES)
            stats.set(GeometryCounter.PEER_COPY_TILES, result.tiles)
            stats.set(GeometryCounter.PEER_COPY_BYTES, result.bytes)
            stats.set(GeometryCounter.PEER_COPY_S, result.seconds)
            stats.set(GeometryCounter.PEER_COPY_FRAME_ID, result.last_frame_id)
            logger.info("geometry: copied the checkpoint of %s (last frame %d, %d frames, %d tiles, %.1f MB in %.2f s); "
                        "following from there", result.source, result.last_frame_id, result.frames_integrated,
                        result.tiles, result.bytes / 1e6, result.seconds)
            return True
        if failed:
            logger.warning("geometry: no peer of shard %s gave a usable checkpoint (%s): starting empty (a recording "
                           "is replayed from its start; a live source's earlier frames are not in this map)",
                           self.shard.part, ", ".join(p.service for p in peers))
        else:  # the shard's first start: its peers start empty too
            logger.info("geometry: no peer of shard %s has a checkpoint yet: starting empty", self.shard.part)
        return False
