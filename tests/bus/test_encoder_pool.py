"""The encoder pool on a real bus, in this process: encoder workers (the real worker service
objects, gt encoder in the hash space) serving the semantic services of two maps, each with its
own geometry service; frames published by the test as the bridge would.

Shown: with no worker alive and no local encoder the semantic service fuses nothing and its
health says ``no_encoder``; a worker started late is used without a restart; one worker serves
two maps; frames spread over two workers and results are applied in frame order; a worker of
another embedding space is refused (health counts it; a request sent to it directly gets
``wrong_space`` naming both spaces). Bad input tried: a request for another space."""

from __future__ import annotations

import dataclasses
import threading
from collections.abc import Iterator
from contextlib import ExitStack

import pytest

from openfusion.bus import Publisher, QueryError, get, open_session
from openfusion.services.encoder.service import EncoderConfig, EncoderWorker
from openfusion.services.geometry.service import GeometryConfig, GeometryService
from openfusion.services.semantic.service import SemanticConfig, SemanticService
from openfusion.sources import open_source
from openfusion.testing.bus import (
    ServiceThread,
    frame_publisher,
    free_port,
    loopback_config,
    send_until_handled,
    unique_map_id,
    wait_for_services,
    wait_until,
)
from openfusion.testing.encoders import FlakyEncoder
from openfusion.wire.counters import (
    ENCODED_BY_PREFIX,
    EncoderCounter,
    GeometryCounter,
    PoolCounter,
    SemanticCounter,
)
from openfusion.wire.endpoints import SENSOR_INSTANCE, SENSOR_RGBD
from openfusion.wire.keys import PoolKeys
from openfusion.wire.schemas import EncodeReply, EncodeRequest, InstanceFrame, RgbdFrame

FRAMES = list(open_source("synthetic:frames=8,width=160,height=120"))
WARM_UP_ID = 1000  # the frame id of Map.publishers' warm-up frame



def _encoder() -> FlakyEncoder:
    return FlakyEncoder(empty_on=(), fail_on=())


class Map:
    """Geometry + a semantic service in pool mode (no local encoder) for one map id."""

    def __init__(self, stack: ExitStack, port: int, *, listen: bool, **semantic_values: object) -> None:
        self.map_id = unique_map_id("pool")
        ports = {"listen": [port]} if listen else {"connect": [port]}
        geo = loopback_config(self.map_id, model=GeometryConfig, geometry={"initial_block_count": 1024}, **ports)
        sem = loopback_config(self.map_id, model=SemanticConfig, semantic={"select": "latest", "recover_timeout_s": 0, "instance_wait_s": 2,
                                                               "encoder_pool": True, "local_encoder": False,
                                                               **semantic_values},
                      connect=[port])
        self.geometry = stack.enter_context(ServiceThread(GeometryService(geo), geo, "geometry"))
        self.semantic = stack.enter_context(ServiceThread(SemanticService(sem, encoder=_encoder()), sem, "semantic"))
        self.keys = geo.keys
        self.warmed = False

    def publishers(self, session) -> tuple[Publisher, Publisher]:  # noqa: ANN001
        """The bridge's two publishers, once the semantic service is seen to take what they send.
        A put from a publisher declared a moment ago can go nowhere, even once it matches a
        subscriber (geometry's): frame 0 never reached the semantic service now and then. So a
        warm-up frame (an id of its own, no instance image: skipped without being encoded, so it
        changes nothing a test counts) is sent until the semantic service has handled one."""
        pubs = (frame_publisher(session, SENSOR_RGBD.key(self.keys), RgbdFrame),
                frame_publisher(session, SENSOR_INSTANCE.key(self.keys), InstanceFrame))
        for pub in pubs:
            wait_until(lambda pub=pub: pub.has_subscribers, timeout_s=60)
        if not self.warmed:
            warm_up = dataclasses.replace(FRAMES[0], frame_id=WARM_UP_ID)
            send_until_handled(lambda: pubs[0].put(RgbdFrame.from_frame(warm_up, with_instance=False)),
                               lambda: self.semantic.counter(SemanticCounter.LAST_FRAME_HANDLED) == WARM_UP_ID)
            assert self.semantic.counter(PoolCounter.FRAMES_DISPATCHED) == 0
            self.warmed = True
        return pubs

    def fused(self) -> float:
        return self.semantic.counter(SemanticCounter.SEMANTIC_FRAMES)


def _worker(stack: ExitStack, port: int, worker_id: str, encoder: FlakyEncoder) -> ServiceThread:
    cfg = loopback_config(unique_map_id("workers"), model=EncoderConfig, encoder={"worker_id": worker_id}, connect=[port])
    return stack.enter_context(ServiceThread(EncoderWorker(cfg, encoder=encoder), cfg, f"encoder-{worker_id}"))


class GatedEncoder(FlakyEncoder):
    """Holds the frame ids in ``gate_on`` until :attr:`release` is set (a slow worker, on cue)."""

    def __init__(self, gate_on: set[int]) -> None:
        super().__init__(empty_on=(), fail_on=())
        self.gate_on = gate_on
        self.release = threading.Event()

    def encode(self, frame):  # noqa: ANN001, ANN201
        if frame.frame_id in self.gate_on:
            self.release.wait(timeout=120)
        return super().encode(frame)


@pytest.fixture
def rig() -> Iterator[tuple[ExitStack, int, Map, Map, object]]:
    port = free_port()
    with ExitStack() as stack:
        a = Map(stack, port, listen=True)
        b = Map(stack, port, listen=False)
        session = open_session(loopback_config(a.map_id, connect=[port]))
        stack.callback(session.close)
        wait_for_services(session, a.map_id, ["geometry", "semantic"])
        wait_for_services(session, b.map_id, ["geometry", "semantic"])
        yield stack, port, a, b, session


def _play(m: Map, session, frames) -> None:  # noqa: ANN001
    """Publish frames one at a time, each once the previous one was taken (so none is replaced)."""
    rgbd, instances = m.publishers(session)
    for frame in frames:  # the counter is -1 until the service has handled a frame
        instances.put(InstanceFrame.from_frame(frame))
        rgbd.put(RgbdFrame.from_frame(frame, with_instance=False))
        wait_until(lambda f=frame: m.semantic.counter(SemanticCounter.LAST_FRAME_HANDLED) == f.frame_id, timeout_s=120,
                   describe=lambda: f"semantic {dict(m.semantic.stats.counters)}")


def test_late_worker_serves_two_maps_and_a_worker_of_another_space_is_refused(rig) -> None:  # noqa: ANN001
    stack, port, a, b, session = rig
    # no worker yet: nothing is encoded, health says so
    wait_until(lambda: a.semantic.counter(PoolCounter.NO_ENCODER) == 1, timeout_s=60)
    assert a.fused() == 0
    # a worker started now is used by both maps, without restarting anything
    _worker(stack, port, "w1", _encoder())
    wait_until(lambda: a.semantic.counter(PoolCounter.ENCODER_WORKERS) == 1
               and b.semantic.counter(PoolCounter.ENCODER_WORKERS) == 1, timeout_s=60)
    _play(a, session, FRAMES[:4])
    _play(b, session, FRAMES[:3])
    wait_until(lambda: a.fused() == 4 and b.fused() == 3, timeout_s=120)
    assert a.semantic.counter(ENCODED_BY_PREFIX + "w1") == 4
    assert a.semantic.counter(PoolCounter.NO_ENCODER) == 0
    wait_until(lambda: a.geometry.counter(GeometryCounter.UPDATES_APPLIED) == 4, timeout_s=120)
    assert len(a.semantic.app.dictionary) > 3 and len(b.semantic.app.dictionary) > 3
    # a worker of another space: refused by both maps, never used
    other = _worker(stack, port, "w-other", FlakyEncoder(empty_on=(), fail_on=(), text_options={"dim": 64}))
    wait_until(lambda: a.semantic.counter(PoolCounter.WORKERS_REFUSED) == 1
               and b.semantic.counter(PoolCounter.WORKERS_REFUSED) == 1, timeout_s=60)
    assert a.semantic.counter(PoolCounter.ENCODER_WORKERS) == 1
    request = EncodeRequest.of(RgbdFrame.from_frame(FRAMES[0]), None, map_id=a.map_id,
                               embedding_space=a.semantic.app.dictionary.embedding_space)
    with pytest.raises(QueryError) as refused:
        get(session, PoolKeys().encode("w-other"), request, EncodeReply, timeout_s=30)
    assert refused.value.code == "wrong_space"
    assert "hash-trigram-64" in refused.value.reason and a.semantic.app.dictionary.embedding_space in refused.value.reason
    assert other.counter("refused_space") == 1


def test_frames_spread_over_workers_and_results_apply_in_frame_order(rig) -> None:  # noqa: ANN001
    stack, port, a, _b, session = rig
    w1 = _worker(stack, port, "w1", _encoder())
    w2 = _worker(stack, port, "w2", _encoder())
    wait_until(lambda: a.semantic.counter(PoolCounter.ENCODER_WORKERS) == 2, timeout_s=60)
    rgbd, instances = a.publishers(session)
    for frame in FRAMES:  # as fast as the bus takes them: the newest frame goes whenever a worker has room
        instances.put(InstanceFrame.from_frame(frame))
        rgbd.put(RgbdFrame.from_frame(frame, with_instance=False))
    # Done: nothing in flight, and every dispatched frame's result applied or dropped as stale (a
    # result can be out of flight but not yet taken by the service's loop).
    wait_until(lambda: a.semantic.counter(SemanticCounter.LAST_FRAME_HANDLED) == FRAMES[-1].frame_id
               and a.semantic.app._pool.in_flight() == 0
               and a.fused() + a.semantic.counter(PoolCounter.RESULTS_STALE)
               == a.semantic.counter(PoolCounter.FRAMES_DISPATCHED), timeout_s=120,
               describe=lambda: f"semantic {dict(a.semantic.stats.counters)}, in flight {a.semantic.app._pool.in_flight()}")
    fused = a.fused()
    stale = a.semantic.counter(PoolCounter.RESULTS_STALE)
    assert fused >= 1 and a.semantic.counter(SemanticCounter.LAST_FRAME_ID) == FRAMES[-1].frame_id
    assert fused + stale == a.semantic.counter(PoolCounter.FRAMES_DISPATCHED)
    assert w1.counter("frames_encoded") + w2.counter("frames_encoded") == a.semantic.counter(PoolCounter.FRAMES_DISPATCHED)


def test_a_result_waits_for_an_older_frame_in_flight_instead_of_dropping_it() -> None:
    """Frame 0 goes to a worker that holds it; frame 1 goes to the other worker and comes back
    first. Its result waits (``results_held``) until frame 0's arrives, then both are applied in
    frame order: nothing is dropped as stale."""
    port = free_port()
    with ExitStack() as stack:
        a = Map(stack, port, listen=True, pool_reorder_wait_s=120)
        session = open_session(loopback_config(a.map_id, connect=[port]))
        stack.callback(session.close)
        wait_for_services(session, a.map_id, ["geometry", "semantic"])
        gated = [GatedEncoder({0}), GatedEncoder({0})]
        _worker(stack, port, "w1", gated[0])
        _worker(stack, port, "w2", gated[1])
        wait_until(lambda: a.semantic.counter(PoolCounter.ENCODER_WORKERS) == 2, timeout_s=60)
        rgbd, instances = a.publishers(session)
        for frame in FRAMES[:2]:
            instances.put(InstanceFrame.from_frame(frame))
            rgbd.put(RgbdFrame.from_frame(frame, with_instance=False))
            wait_until(lambda f=frame: a.semantic.counter(PoolCounter.FRAMES_DISPATCHED) == f.frame_id + 1,
                       timeout_s=60, describe=lambda: f"semantic {dict(a.semantic.stats.counters)}")
        wait_until(lambda: a.semantic.counter(PoolCounter.RESULTS_HELD) == 1, timeout_s=60)
        assert a.fused() == 0  # frame 1 is encoded but waits for frame 0
        for encoder in gated:
            encoder.release.set()
        wait_until(lambda: a.fused() == 2, timeout_s=60, describe=lambda: f"semantic {dict(a.semantic.stats.counters)}")
        assert a.semantic.counter(PoolCounter.RESULTS_STALE) == 0
        assert a.semantic.counter(SemanticCounter.LAST_FRAME_ID) == 1


def test_a_worker_embeds_the_scene_categories_before_it_takes_frames() -> None:
    """A gt worker embeds the built-in scene's categories (names and captions, in one call) while
    it sets up (before its liveliness token), not inside its first frames: without it each worker
    of a four-worker pool lost 1 to 3 s of a 12 s run (bench/bench_pool.py 0.78 -> 1.0 of 4 x one
    worker)."""
    from openfusion.encoders.gt import GroundTruthRegionEncoder
    from openfusion.encoders.text_hash import HashTextEncoder
    from openfusion.sources.synthetic_categories import CATEGORIES

    calls: list[list[str]] = []

    class Counting(HashTextEncoder):
        def encode(self, texts: list[str]):  # noqa: ANN201
            calls.append(list(texts))
            return super().encode(texts)

    cfg = loopback_config(unique_map_id("workers"), model=EncoderConfig, encoder={"worker_id": "warm"}, listen=[free_port()])
    encoder = GroundTruthRegionEncoder(Counting(dim=32))
    with ServiceThread(EncoderWorker(cfg, encoder=encoder), cfg, "encoder-warm") as worker:
        assert len(calls) == 1 and calls[0][: len(CATEGORIES)] == sorted(CATEGORIES)  # names, then captions
        assert worker.counter(EncoderCounter.FRAMES_ENCODED) == 0
