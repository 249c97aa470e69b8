"""Region merges across the services, on a real bus in this process: geometry, semantic and query
service objects each on their own ServiceRunner and Zenoh session (loopback), frames published by
the test as the bridge would.

The encoder splits every object in two on the first frame, so the map starts with two touching
fragments per object; the semantic service's merge pass (every 2 semantic frames, contacts from
geometry's ``geometry/contacts``) joins them and publishes one delta. Checked: the query service's
and geometry's replicas equal the semantic service's dictionary, geometry's voxels carry only live
keys (no merged-away key), and a restarted semantic service recovers the merged dictionary from
geometry and continues with it (new keys above the old ones; the replicas follow).

A lost merge delta: the replica's next delta leaves a gap, geometry resyncs from the semantic
service's snapshot, and the snapshot's merge table relabels the voxels the lost delta would have.
A save (``control/save``) first asks the semantic service for a merge pass and saves the merged
map; with the semantic service gone the map is saved as it is and the failure counted.

Bad input tried: a contacts request with radius 0 is refused by its schema before geometry sees it
(``tests/unit/test_messages.py``); here, a merge pass while geometry is gone is counted in
``merge_failures`` and mapping goes on; a dropped (never delivered) merge delta."""

from __future__ import annotations

import numpy as np
import pytest

from openfusion.bus import Publisher, call
from openfusion.mapping import RegionDictionary, load_map
from openfusion.services.geometry.service import GeometryConfig, GeometryService
from openfusion.services.query.service import QueryConfig, QueryService
from openfusion.services.semantic.service import SemanticConfig, SemanticService
from openfusion.sources import open_source
from openfusion.testing.bus import (
    LoopbackRouter,
    ServiceThread,
    frame_publisher,
    loopback_config,
    unique_map_id,
    wait_for_services,
    wait_until,
)
from openfusion.testing.encoders import SplittingEncoder
from openfusion.wire.counters import GeometryCounter, SemanticCounter
from openfusion.wire.endpoints import CONTROL, SENSOR_INSTANCE, SENSOR_RGBD
from openfusion.wire.schemas import ControlRequest, InstanceFrame, RgbdFrame

pytestmark = pytest.mark.timeout(300)

FRAMES = list(open_source("synthetic:frames=8,width=160,height=120"))


def _feed(rgbd: Publisher, instances: Publisher, semantic: ServiceThread, frames) -> None:  # noqa: ANN001
    """Publish each frame (instance image first) and wait until the semantic service has fused it
    and run the merge pass that follows it, if one is due."""
    for frame in frames:
        # A frame is sent again when the service skipped it (a render timeout on a busy machine) or
        # never saw it: the token that wait_for_services saw can reach this session before the
        # route of the subscriber it follows, so the very first frame may go nowhere.
        for _attempt in range(5):
            fused, handled = semantic.counter(SemanticCounter.SEMANTIC_FRAMES), _handled(semantic)
            instances.put(InstanceFrame.from_frame(frame))
            rgbd.put(RgbdFrame.from_frame(frame, with_instance=False))
            try:
                wait_until(lambda handled=handled: _handled(semantic) > handled, timeout_s=20)
            except AssertionError:
                continue
            if semantic.counter(SemanticCounter.SEMANTIC_FRAMES) > fused:
                break
        else:
            raise AssertionError(f"frame {frame.frame_id} was not fused in 5 tries: {dict(semantic.stats.counters)}")
        wait_until(lambda: _passes_done(semantic))


def _passes_done(semantic: ServiceThread) -> bool:
    """The merge pass due after the last fused frame has run (it runs right after the frame counts;
    passes asked for on semantic/merge or by the test come on top)."""
    done = semantic.counter(SemanticCounter.MERGE_PASSES) + semantic.counter(SemanticCounter.MERGE_FAILURES)
    return done >= semantic.counter(SemanticCounter.SEMANTIC_FRAMES) // semantic.app.merge_params.merge_every


def _handled(semantic: ServiceThread) -> float:
    """Frames the semantic service is done with: fused, skipped or failed."""
    return sum(semantic.counter(c) for c in (
        SemanticCounter.SEMANTIC_FRAMES, SemanticCounter.SKIPPED_NO_RENDER, SemanticCounter.SKIPPED_NO_INSTANCE,
        SemanticCounter.FRAMES_FAILED))


def _wait_replicas_agree(semantic: RegionDictionary, geometry: ServiceThread, query: ServiceThread, *,
                         updates: int) -> None:
    """Both replicas reach the semantic dictionary's version and geometry has applied every update."""
    version = semantic.version
    wait_until(lambda: query.app.replica.dictionary is not None and query.app.replica.dictionary.version == version)
    wait_until(lambda: geometry.app.replica.dictionary is not None
               and geometry.app.replica.dictionary.version == version)
    wait_until(lambda: geometry.counter(GeometryCounter.UPDATES_APPLIED) >= updates)


def _assert_same(a: RegionDictionary, b: RegionDictionary) -> None:
    sa, sb = a.snapshot(), b.snapshot()
    order_a, order_b = np.argsort(sa.keys), np.argsort(sb.keys)
    np.testing.assert_array_equal(sa.keys[order_a], sb.keys[order_b])
    np.testing.assert_array_equal(sa.counts[order_a], sb.counts[order_b])
    np.testing.assert_allclose(sa.embeddings[order_a], sb.embeddings[order_b], atol=1e-6)
    assert (sa.version, sa.next_key) == (sb.version, sb.next_key)


def _merged_away(d: RegionDictionary) -> set[int]:
    return {k for k in range(d.next_key) if k not in d and d.survivor_of(k) is not None}


def test_merges_reach_every_replica_and_survive_a_semantic_restart() -> None:
    # Every service a client of the router (it relays between them, so no two services depend on
    # finding each other as peers), with the services' default health period.
    router = LoopbackRouter("merge", health_period_s=1.0)
    map_id = router.map_id
    geo_cfg = router.config(GeometryConfig, geometry={"initial_block_count": 2048})
    sem_cfg = router.config(SemanticConfig, semantic={"select": "latest", "merge_every": 2, "merge_min_interval_s": 0,
                                                      "recover_timeout_s": 30, "instance_wait_s": 10})
    query_cfg = router.config(QueryConfig, query={"text_encoder": "hash"})
    with (
        ServiceThread(GeometryService(geo_cfg), geo_cfg, "geometry") as geometry,
        ServiceThread(QueryService(query_cfg), query_cfg, "query") as query,
    ):
        session = router.open_client()
        try:
            keys = geo_cfg.keys
            # Declared before waiting for the services (their tokens come after their subscribers).
            rgbd = frame_publisher(session, SENSOR_RGBD.key(keys), RgbdFrame)
            instances = frame_publisher(session, SENSOR_INSTANCE.key(keys), InstanceFrame)
            first = SemanticService(sem_cfg, encoder=SplittingEncoder(split_on=[0]))
            with ServiceThread(first, sem_cfg, "semantic") as semantic:
                wait_for_services(session, map_id, ["geometry", "semantic", "query"])
                _feed(rgbd, instances, semantic, FRAMES[:4])
                assert semantic.counter(SemanticCounter.MERGE_PASSES) == 2
                merged = semantic.counter(SemanticCounter.REGIONS_MERGED)
                assert merged > 0
                _wait_replicas_agree(first.dictionary, geometry, query,
                                     updates=semantic.counter(SemanticCounter.SEMANTIC_FRAMES))
                _assert_same(query.app.replica.dictionary, first.dictionary)
                _assert_same(geometry.app.replica.dictionary, first.dictionary)
                gone = _merged_away(first.dictionary)
                assert len(gone) == merged
                assert _merged_away(query.app.replica.dictionary) == gone  # the replica knows the merges too
                stored = set(np.unique(geometry.app.volume.to_arrays()["key"]).tolist()) - {-1}
                assert stored and not stored & gone and stored <= set(first.dictionary.keys.tolist())
                assert geometry.counter(GeometryCounter.VOXELS_RELABELLED) > 0
                # Updates wrote through the render of their frame (one ray cast per semantic frame).
                assert geometry.counter(GeometryCounter.UPDATES_REUSED_RENDER) > 0
                before_restart = first.dictionary.snapshot()
                fused_before = semantic.counter(SemanticCounter.SEMANTIC_FRAMES)

            # A restarted semantic service: the merged dictionary comes back from geometry.
            second = SemanticService(sem_cfg, encoder=SplittingEncoder(split_on=[]))
            with ServiceThread(second, sem_cfg, "semantic") as semantic:
                assert sorted(second.dictionary.keys.tolist()) == sorted(before_restart.keys.tolist())
                assert second.dictionary.next_key == before_restart.next_key
                wait_for_services(session, map_id, ["semantic"])
                _feed(rgbd, instances, semantic, FRAMES[4:])
                _wait_replicas_agree(second.dictionary, geometry, query, updates=fused_before
                                     + semantic.counter(SemanticCounter.SEMANTIC_FRAMES))
                _assert_same(query.app.replica.dictionary, second.dictionary)
                new_keys = set(second.dictionary.keys.tolist()) - set(before_restart.keys.tolist())
                assert all(k >= before_restart.next_key for k in new_keys)
                assert not set(second.dictionary.keys.tolist()) & gone  # no merged key comes back
                stored = set(np.unique(geometry.app.volume.to_arrays()["key"]).tolist()) - {-1}
                assert stored <= set(second.dictionary.keys.tolist())
        finally:
            session.close()
            router.close()


def test_a_merge_pass_without_geometry_is_counted_and_mapping_goes_on() -> None:
    """No geometry on the bus: the pass's contacts request times out; merge_failures counts it and
    the dictionary is unchanged."""
    sem_cfg = loopback_config(unique_map_id("merge-nogeo"), model=SemanticConfig,
                              semantic={"select": "latest", "recover_timeout_s": 0, "render_timeout_s": 0.5,
                                        "contacts_timeout_s": 0.5})
    service = SemanticService(sem_cfg, encoder=SplittingEncoder(split_on=[]))
    with ServiceThread(service, sem_cfg, "semantic") as semantic:
        version = service.dictionary.version
        assert service.merge_pass(semantic.runner) == 0
        assert semantic.counter(SemanticCounter.MERGE_FAILURES) == 1
        assert service.dictionary.version == version


class _Lost:
    """Stands in for the delta publisher: what is put here never reaches anyone."""

    def __init__(self) -> None:
        self.dropped = 0

    def put(self, _msg: object) -> None:
        self.dropped += 1


def _stored_keys(geometry: ServiceThread) -> set[int]:
    return set(np.unique(geometry.app.volume.to_arrays()["key"]).tolist()) - {-1}


def test_a_lost_merge_delta_is_repaired_by_the_resync_and_a_save_merges_first(tmp_path) -> None:  # noqa: ANN001
    router = LoopbackRouter("merge-save", health_period_s=1.0)
    map_id = router.map_id
    geo_cfg = router.config(GeometryConfig, geometry={"initial_block_count": 2048, "checkpoint_period_s": 0,
                                                      "merge_on_save_timeout_s": 10})
    # No periodic pass (merge_every far away): only the passes this test asks for happen.
    sem_cfg = router.config(SemanticConfig, semantic={"select": "latest", "merge_every": 1000, "recover_timeout_s": 0,
                                                      "instance_wait_s": 10})
    with ServiceThread(GeometryService(geo_cfg), geo_cfg, "geometry") as geometry:
        session = router.open_client()
        try:
            keys = geo_cfg.keys
            rgbd = frame_publisher(session, SENSOR_RGBD.key(keys), RgbdFrame)
            instances = frame_publisher(session, SENSOR_INSTANCE.key(keys), InstanceFrame)
            service = SemanticService(sem_cfg, encoder=SplittingEncoder(split_on=[0, 3]))
            with ServiceThread(service, sem_cfg, "semantic") as semantic:
                wait_for_services(session, map_id, ["geometry", "semantic"])
                _feed(rgbd, instances, semantic, FRAMES[:2])
                _wait_replicas_agree_geometry(service.dictionary, geometry,
                                              updates=semantic.counter(SemanticCounter.SEMANTIC_FRAMES))

                # A merge pass whose delta is lost on the way.
                lost, real = _Lost(), service._delta_pub
                service._delta_pub = lost
                try:
                    merged = service.merge_pass(semantic.runner)
                finally:
                    service._delta_pub = real
                assert merged > 0 and lost.dropped == 1
                gone = _merged_away(service.dictionary)
                assert _stored_keys(geometry) & gone  # geometry still holds the fragments' keys
                # The next frame's delta starts after the lost one: geometry resyncs, and the
                # snapshot's merge table relabels the merged keys' voxels.
                _feed(rgbd, instances, semantic, FRAMES[2:3])
                _wait_replicas_agree_geometry(service.dictionary, geometry,
                                              updates=semantic.counter(SemanticCounter.SEMANTIC_FRAMES))
                assert geometry.counter(GeometryCounter.DICTIONARY_RESYNCS) >= 1
                # The replica's version shows before the relabelling under the same lock ends.
                wait_until(lambda: geometry.counter(GeometryCounter.VOXELS_RELABELLED) > 0)
                assert not _stored_keys(geometry) & gone
                assert _merged_away(geometry.app.replica.dictionary) == gone

                # Frame 3 splits every object again; no periodic pass joins the halves.
                _feed(rgbd, instances, semantic, FRAMES[3:5])
                passes = semantic.counter(SemanticCounter.MERGE_PASSES)
                before_save = len(service.dictionary)
                saved = tmp_path / "saved"
                reply = call(session, keys, CONTROL["save"], ControlRequest(action="save", path=str(saved)),
                             timeout_s=60)
                assert reply.ok
                assert semantic.counter(SemanticCounter.MERGE_PASSES) == passes + 1  # asked by the save
                assert geometry.counter(GeometryCounter.SAVE_MERGES) == 1
                assert len(service.dictionary) < before_save  # the halves were joined before saving
                loaded = load_map(saved)
                live = set(service.dictionary.keys.tolist())
                assert set(loaded.dictionary.keys.tolist()) == live
                in_file = set(np.unique(loaded.volume.to_arrays()["key"]).tolist()) - {-1}
                assert in_file and in_file <= live  # no fragment key left in the saved voxels

            # The semantic service is gone: the save goes ahead unmerged, and says so in a counter.
            reply = call(session, keys, CONTROL["save"], ControlRequest(action="save", path=str(tmp_path / "alone")),
                         timeout_s=60)
            assert reply.ok and load_map(tmp_path / "alone").volume.num_blocks > 0
            assert geometry.counter(GeometryCounter.SAVE_MERGE_FAILURES) == 1
        finally:
            session.close()
            router.close()


def _wait_replicas_agree_geometry(semantic: RegionDictionary, geometry: ServiceThread, *, updates: int) -> None:
    version = semantic.version
    wait_until(lambda: geometry.app.replica.dictionary is not None
               and geometry.app.replica.dictionary.version == version)
    wait_until(lambda: geometry.counter(GeometryCounter.UPDATES_APPLIED) >= updates)
