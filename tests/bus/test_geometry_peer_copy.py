"""A replica that starts with no checkpoint of its own copies its peer's over Zenoh, then follows
(docs/SHARDS.md, "Replicas"; services/geometry/peer_copy.py). Real Zenoh sessions in this process
(a router and client sessions on loopback), services on threads.

- A replica with an empty folder joins after its peer mapped a playback: it copies the peer's
  checkpoint (the peer checkpoints first), loads it as a restart loads its own, and its map equals
  the peer's, block for block and point for point; the playback continued (the same playback name,
  from its start) is followed: the replica drops the frames its copy holds as duplicates,
  integrates the rest once, and the two maps are equal again.
- Frames that come while the replica copies (a source nobody replays for it): the replica
  subscribed before the copy, holds them, and takes them once the copy is loaded: its map is the
  peer's, every frame once, no gap (services/geometry/start_buffer.py).
- A live source (frames with no playback, never replayed; shard 0 of 2 and its replica): frames
  the replica never received are counted as ``frames_gap`` at the first live frame it takes, and
  it takes the frames after it once.
- Bad input: a chunk corrupted in transit (bytes flipped after the peer computed their digest),
  and a peer that goes away mid-copy (its session closed after its first chunk): each copy is
  logged, counted (``peer_copy_failures``) and discarded; the next peer is tried; with none left
  the replica starts empty, with no partial copy in its folder and nothing loaded from one.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from openfusion.services.bridge.service import BridgeConfig, BridgeSection, BridgeService
from openfusion.services.geometry import checkpoints, peer_copy
from openfusion.services.geometry.service import GeometryConfig, GeometrySection, GeometryService
from openfusion.sources import open_source
from openfusion.testing.bus import (
    LoopbackRouter,
    ServiceThread,
    frame_publisher,
    send_until_handled,
    wait_until,
)
from openfusion.wire.counters import GeometryCounter
from openfusion.wire.endpoints import SENSOR_RGBD
from openfusion.wire.keys import ShardId
from openfusion.wire.schemas import CheckpointChunk, RgbdFrame

pytestmark = pytest.mark.timeout(180)

SOURCE = "synthetic:seed=1,width=160,height=120"
N = 8
VOLUME = {"voxel_size_m": 0.04, "tile_blocks": 4, "initial_block_count": 2048}


@pytest.fixture
def net() -> Iterator[LoopbackRouter]:
    with LoopbackRouter("peercopy") as router:
        yield router


def _geometry(net: LoopbackRouter, folder: Path, replica: int, **extra: object) -> tuple[GeometryService, ServiceThread]:
    service = GeometryService(net.config(GeometryConfig, geometry=GeometrySection(
        map_dir=folder, checkpoint_period_s=0, replica=replica, **VOLUME, **extra)))
    return service, ServiceThread(service, net.config(GeometryConfig), service.shard.service)


def _play(net: LoopbackRouter, frames: int, *geometries: GeometryService) -> None:
    """The synthetic room's first ``frames`` frames (one playback name: a second call continues it
    from its start), until every geometry holds them."""
    bridge = BridgeService(net.config(BridgeConfig, bridge=BridgeSection(
        source=SOURCE, max_frames=frames, rate_hz=0, max_in_flight=2, playback="peer-copy-test")))
    with ServiceThread(bridge, net.config(BridgeConfig), "bridge"):
        wait_until(lambda: all(g.frames_integrated >= frames for g in geometries), timeout_s=60,
                   describe=lambda: str([g.frames_integrated for g in geometries]))


def _arrays(service: GeometryService) -> dict[str, np.ndarray]:
    arrays = service.volume.to_arrays()
    order = np.lexsort(arrays["block_coords"].T)
    return {k: v[order] for k, v in arrays.items()}


def _assert_same_map(a: GeometryService, b: GeometryService) -> None:
    x, y = _arrays(a), _arrays(b)
    assert len(x["block_coords"]) == len(y["block_coords"]) > 100
    for name in x:
        np.testing.assert_array_equal(x[name], y[name], err_msg=name)
    pa, pb = a.volume.extract_points().points, b.volume.extract_points().points
    assert len(pa) == len(pb) > 1000
    np.testing.assert_array_equal(np.sort(pa, axis=0), np.sort(pb, axis=0))


def test_a_replica_with_no_checkpoint_copies_its_peers_then_follows(net: LoopbackRouter, tmp_path: Path,
                                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(peer_copy, "MAX_CHECKPOINT_CHUNK_BYTES", 64 * 1024)  # several chunks of a small map
    primary, p_thread = _geometry(net, tmp_path / "host1", 0)
    with p_thread:
        _play(net, N, primary)
        replica, r_thread = _geometry(net, tmp_path / "host2", 1)  # a new host: an empty folder
        with r_thread:
            assert r_thread.counter(GeometryCounter.PEER_COPIES) == 1
            assert r_thread.counter(GeometryCounter.PEER_COPY_FAILURES) == 0
            assert r_thread.counter(GeometryCounter.PEER_COPY_TILES) > 0
            assert r_thread.counter(GeometryCounter.PEER_COPY_BYTES) > 64 * 1024
            assert r_thread.counter(GeometryCounter.PEER_COPY_FRAME_ID) == primary.last_frame_id
            assert p_thread.counter(GeometryCounter.PEER_SNAPSHOTS_SERVED) == 1
            assert primary.checkpoint_last_frame_id == primary.last_frame_id  # it checkpointed first
            # Loaded as a restart loads its own checkpoint: its chain, its counts, its map.
            assert replica.last_frame_id == primary.last_frame_id and replica.frames_integrated == N
            assert replica.checkpoint_dir is not None and checkpoints.has_checkpoint(replica.checkpoint_dir)
            _assert_same_map(primary, replica)
            # The snapshot is gone from the peer's disk, the copy's scratch folder from the replica's.
            assert not any((primary.checkpoint_dir / peer_copy.SNAPSHOTS_DIR).iterdir())
            assert not list(replica.checkpoint_dir.glob(peer_copy.INCOMING_PREFIX + "*"))
            # The playback goes on (the same playback, from its start): the replica follows.
            _play(net, N + 4, primary, replica)
            assert replica.frames_integrated == primary.frames_integrated == N + 4  # each frame once
            assert r_thread.counter(GeometryCounter.FRAMES_DUPLICATE) == N  # what its copy held
            _assert_same_map(primary, replica)
        replica.close()
    primary.close()


def test_frames_that_come_during_the_copy_are_held_and_taken_once_after_it(
        net: LoopbackRouter, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A source that no one replays for the replica (its own publisher, not a bridge): frames 0-5
    before the replica starts (in the checkpoint it copies), 6-7 while it copies (sent when the
    first chunk comes back, so after the peer's checkpoint), 8-11 after. Subscribed only after the
    copy, the replica missed 6-7 and, its chain broken, took none of the later frames either."""
    monkeypatch.setattr(peer_copy, "MAX_CHECKPOINT_CHUNK_BYTES", 32 * 1024)  # several chunks
    frames = [RgbdFrame.from_frame(f, with_instance=False, playback="no-replay", prev_frame_id=f.frame_id - 1)
              for f in open_source(f"{SOURCE},frames=12")]
    session = net.open_client()
    pub = frame_publisher(session, SENSOR_RGBD.key(net.keys), RgbdFrame)
    primary, p_thread = _geometry(net, tmp_path / "host1", 0)
    replica, r_thread = _geometry(net, tmp_path / "host2", 1)
    real_get = peer_copy.get

    def get_during_copy(session_, key, request, reply_model, **kw):  # noqa: ANN001, ANN003, ANN202
        reply = real_get(session_, key, request, reply_model, **kw)
        held = replica.held_at_start
        if isinstance(reply, CheckpointChunk) and held is not None and held.frames == 0:
            for i in (6, 7):  # resent until held (a subscription declared a moment ago may miss a put)
                send_until_handled(lambda i=i: pub.put(frames[i]), lambda i=i: held.frames >= i - 5, timeout_s=2.0)
            wait_until(lambda: primary.frames_integrated == 8, timeout_s=30)
        return reply

    try:
        with p_thread:
            wait_until(lambda: pub.has_subscribers, timeout_s=30)
            send_until_handled(lambda: pub.put(frames[0]), lambda: primary.frames_integrated >= 1, timeout_s=2.0)
            for msg in frames[1:6]:
                pub.put(msg)
            wait_until(lambda: primary.frames_integrated == 6, timeout_s=30,
                       describe=lambda: f"integrated {primary.frames_integrated}, last {primary.last_frame_id}, "
                                        f"gap {p_thread.counter(GeometryCounter.FRAMES_GAP)}")
            monkeypatch.setattr(peer_copy, "get", get_during_copy)
            with r_thread:  # its start copies the checkpoint (frames 0-5); 6 and 7 come meanwhile
                assert r_thread.counter(GeometryCounter.PEER_COPY_FRAME_ID) == frames[5].frame_id
                assert r_thread.counter(GeometryCounter.PEER_COPY_FRAMES_HELD) >= 2
                assert r_thread.counter(GeometryCounter.PEER_COPY_FRAMES_LOST) == 0
                assert replica.frames_integrated == 8
                for msg in frames[8:]:
                    pub.put(msg)
                wait_until(lambda: primary.frames_integrated == replica.frames_integrated == 12, timeout_s=30,
                           describe=lambda: f"{primary.frames_integrated} / {replica.frames_integrated}")
                assert r_thread.counter(GeometryCounter.FRAMES_GAP) == 0
                assert replica.last_frame_id == primary.last_frame_id == frames[-1].frame_id
                _assert_same_map(primary, replica)
    finally:
        replica.close()
        primary.close()
        pub.close()
        session.close()


def test_a_live_source_counts_the_frames_the_replica_never_got(net: LoopbackRouter, tmp_path: Path) -> None:
    frames = [RgbdFrame.from_frame(f, with_instance=False) for f in open_source(f"{SOURCE},frames=12")]
    primary, p_thread = _geometry(net, tmp_path / "host1", 0, shard="0/2")  # one shard of two: its own keys
    with p_thread:
        for msg in frames[:6]:  # live frames: no playback, no predecessor
            primary.on_frame(msg)
        replica, r_thread = _geometry(net, tmp_path / "host2", 1, shard="0/2")
        assert replica.shard.service == "geometry-0of2-r1"
        with r_thread:
            assert r_thread.counter(GeometryCounter.PEER_COPY_FRAME_ID) == frames[5].frame_id
            assert replica.checkpoint_dir is not None and replica.checkpoint_dir.name == "shard-0of2-r1"
            _assert_same_map(primary, replica)
            for msg in frames[6:8]:  # the peer goes on before the replica takes frames: lost for it
                primary.on_frame(msg)
            for msg in frames[8:]:
                primary.on_frame(msg)
                replica.on_frame(msg)
            assert primary.frames_integrated == 12 and replica.frames_integrated == 10
            assert r_thread.counter(GeometryCounter.FRAMES_GAP) == 2  # said, not silent
            assert p_thread.counter(GeometryCounter.FRAMES_GAP) == 0
            assert replica.last_frame_id == primary.last_frame_id == frames[-1].frame_id
        replica.close()
    primary.close()


def test_a_corrupt_chunk_or_a_vanishing_peer_is_discarded_and_the_next_tried(
        net: LoopbackRouter, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(peer_copy, "MAX_CHECKPOINT_CHUNK_BYTES", 32 * 1024)
    primary, p_thread = _geometry(net, tmp_path / "r0", 0)
    threads: list[ServiceThread] = []
    try:
        p_thread.__enter__()
        threads.append(p_thread)
        _play(net, N, primary)
        second, s_thread = _geometry(net, tmp_path / "r2", 2)  # a good copy first: two peers to choose from
        s_thread.__enter__()
        threads.append(s_thread)
        assert s_thread.counter(GeometryCounter.PEER_COPIES) == 1

        real_get = peer_copy.get
        plan = {"corrupt": ShardId(0, 1, 0).service, "vanish": None, "chunks": 0}

        def faulty_get(session, key, request, reply_model, **kw):  # noqa: ANN001, ANN003, ANN202
            reply = real_get(session, key, request, reply_model, **kw)
            if isinstance(reply, CheckpointChunk):
                peer = key.rsplit("/", 1)[-1]
                if peer == plan["corrupt"]:  # flipped in transit, after the peer computed the digest
                    data = reply.data.copy()
                    data[len(data) // 2] ^= 0x40
                    reply = reply.model_copy(update={"data": data})
                elif peer == plan["vanish"]:  # its host goes away after its first chunk
                    s_thread.__exit__(None, None, None)
                    threads.remove(s_thread)
            return reply

        monkeypatch.setattr(peer_copy, "get", faulty_get)
        # r0's chunks arrive corrupt: discarded, r2 tried next.
        third, t_thread = _geometry(net, tmp_path / "r1", 1)
        with t_thread:
            assert t_thread.counter(GeometryCounter.PEER_COPY_FAILURES) == 1
            assert t_thread.counter(GeometryCounter.PEER_COPIES) == 1
            assert third.frames_integrated == N
            _assert_same_map(primary, third)
        third.close()
        # r0 corrupt again and r2 vanishing mid-copy: no peer left; starts empty, nothing half loaded.
        plan["vanish"] = second.shard.service
        fourth, f_thread = _geometry(net, tmp_path / "r3", 3, peer_copy_timeout_s=5.0)
        with f_thread:
            assert f_thread.counter(GeometryCounter.PEER_COPY_FAILURES) == 2
            assert f_thread.counter(GeometryCounter.PEER_COPIES) == 0
            assert fourth.volume.num_blocks == 0 and fourth.frames_integrated == 0 and fourth.last_frame_id is None
            assert fourth.checkpoint_dir is not None and not checkpoints.has_checkpoint(fourth.checkpoint_dir)
            assert not list(fourth.checkpoint_dir.glob(peer_copy.INCOMING_PREFIX + "*"))
        fourth.close()
        # The peer that served the corrupt copies let its snapshots go (released by the asker).
        assert not any((primary.checkpoint_dir / peer_copy.SNAPSHOTS_DIR).iterdir())
        assert p_thread.counter(GeometryCounter.PEER_SNAPSHOTS_SERVED) == 3
    finally:
        for t in reversed(threads):
            t.__exit__(None, None, None)
        primary.close()
        second.close()


def test_a_peer_with_nothing_to_copy_is_not_a_failure(net: LoopbackRouter, tmp_path: Path) -> None:
    """A shard's first start (its peer holds no checkpoint yet) and a peer with no checkpoint folder:
    answered ``no_checkpoint`` at once (a timeout would count a failure); the replica starts empty."""
    fresh, f_thread = _geometry(net, tmp_path / "r0", 0)
    nodisk = GeometryService(net.config(GeometryConfig, geometry=GeometrySection(replica=2, **VOLUME)))
    with f_thread, ServiceThread(nodisk, net.config(GeometryConfig), nodisk.shard.service):
        replica, r_thread = _geometry(net, tmp_path / "r1", 1)
        with r_thread:
            assert r_thread.counter(GeometryCounter.PEER_COPY_FAILURES) == 0
            assert r_thread.counter(GeometryCounter.PEER_COPIES) == 0
            assert replica.volume.num_blocks == 0
        replica.close()
    fresh.close()
    nodisk.close()


def test_peers_are_the_other_replicas_of_the_same_shard() -> None:
    me = ShardId(0, 2, 1)
    names = ["bridge", "geometry-0of2", "geometry-1of2", "geometry-0of2-r1", "geometry-0of2-r3", "geometry-1of2-r1",
             "semantic"]
    assert [s.service for s in peer_copy.peers_of(names, me)] == ["geometry-0of2", "geometry-0of2-r3"]
    assert peer_copy.peers_of(["geometry"], ShardId(0, 1, 1)) == [ShardId(0, 1, 0)]
    assert peer_copy.wants_peer_copy(None, me) and not peer_copy.wants_peer_copy(None, ShardId(0, 2))
    assert peer_copy.wants_peer_copy(True, ShardId(0, 2)) and not peer_copy.wants_peer_copy(False, me)
