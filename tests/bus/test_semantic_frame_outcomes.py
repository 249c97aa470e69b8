"""Every frame the semantic service receives ends in exactly one counted outcome
(``wire.counters.SEMANTIC_FRAME_OUTCOMES``): on a real bus in this process, the real geometry and
semantic services, frames published by the test as the bridge would, the encoder held busy on cue.

Fed: with ``select=latest`` frames that come while the encoder is busy (the older ones are let go
by the subscription's queue or superseded by the newest geometry has taken) and one malformed message on ``sensor/rgbd``; with ``select=coverage`` a window of one
and a subscription queue of one, so frames are dropped by the queue, evicted from the window or
skipped for no gain. In each the outcomes add up to the frames received, ``frames_pending`` ends
at 0, and the service keeps running after the malformed message."""

from __future__ import annotations

from contextlib import ExitStack

from openfusion.bus import Publisher, open_session
from openfusion.services.geometry.service import GeometryConfig, GeometryService
from openfusion.services.semantic.service import SemanticConfig, SemanticService
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
from openfusion.wire.counters import SEMANTIC_FRAME_OUTCOMES, SemanticCounter, semantic_frame_outcomes
from openfusion.wire.endpoints import SENSOR_RGBD
from openfusion.wire.schemas import RgbdFrame
from tests.bus.test_semantic_selection import HERE, THERE, GatedEncoder, _as


def _rig(stack: ExitStack, *, encoder, semantic_values: dict):  # noqa: ANN001, ANN202
    map_id = unique_map_id("outcomes")
    port = free_port()
    sem_cfg = loopback_config(map_id, model=SemanticConfig, listen=[port], semantic={
        "recover_timeout_s": 0, "instance_wait_s": 5, "select_tries": 1, **semantic_values})
    semantic = stack.enter_context(ServiceThread(SemanticService(sem_cfg, encoder=encoder), sem_cfg, "semantic"))
    geo_cfg = loopback_config(map_id, model=GeometryConfig, geometry={"initial_block_count": 2048}, connect=[port])
    stack.enter_context(ServiceThread(GeometryService(geo_cfg), geo_cfg, "geometry"))
    session = open_session(loopback_config(map_id, connect=[port]))
    stack.callback(session.close)
    wait_for_services(session, map_id, ["semantic", "geometry"])
    rgbd = frame_publisher(session, SENSOR_RGBD.key(sem_cfg.keys), RgbdFrame)
    wait_until(lambda: rgbd.has_subscribers, timeout_s=60)
    return semantic, rgbd, session, SENSOR_RGBD.key(sem_cfg.keys)


def _outcomes(semantic: ServiceThread) -> dict[str, int]:
    return semantic_frame_outcomes(semantic.stats.counters)


def _settled(semantic: ServiceThread, received: int) -> bool:
    """Every frame received has its outcome (the received count is the subscription's)."""
    return (semantic.counter(SemanticCounter.FRAMES_RECEIVED) == received
            and sum(_outcomes(semantic).values()) == received
            and semantic.counter(SemanticCounter.FRAMES_PENDING) == 0)


def _feed(semantic: ServiceThread, rgbd: Publisher, session, key: str, encoder: GatedEncoder,  # noqa: ANN001
          frames: list) -> int:
    """Frame 0 holds the encoder; ``frames`` and one malformed message come meanwhile; then the
    encoder is let go. Returns the frames received in all."""
    send_until_handled(lambda: rgbd.put(RgbdFrame.from_frame(_as(HERE, 0), with_instance=True)),
                       lambda: encoder.started.is_set())
    wait_until(lambda: semantic.counter(SemanticCounter.FRAMES_RECEIVED) >= 1, timeout_s=30)
    before = int(semantic.counter(SemanticCounter.FRAMES_RECEIVED))  # frame 0 (sent more than once if the link was late)
    for frame in frames:
        rgbd.put(RgbdFrame.from_frame(frame, with_instance=True))
    session.put(key, b"not a frame")  # malformed: logged, counted, dropped
    received = before + len(frames) + 1
    wait_until(lambda: semantic.counter(SemanticCounter.FRAMES_RECEIVED) == received, timeout_s=60,
               describe=lambda: f"semantic {dict(semantic.stats.counters)}")
    encoder.release.set()
    wait_until(lambda: _settled(semantic, received), timeout_s=60,
               describe=lambda: f"received {received}, outcomes {_outcomes(semantic)}, "
               f"pending {semantic.counter(SemanticCounter.FRAMES_PENDING)}")
    assert semantic._thread is not None and semantic._thread.is_alive()
    assert semantic.counter(SemanticCounter.FRAMES_MALFORMED) == 1
    return received


def test_latest_every_frame_received_ends_fused_superseded_or_malformed() -> None:
    encoder = GatedEncoder(gate_on=0)
    with ExitStack() as stack:
        semantic, rgbd, session, key = _rig(stack, encoder=encoder, semantic_values={"select": "latest"})
        received = _feed(semantic, rgbd, session, key, encoder, [_as(THERE if i % 2 else HERE, i) for i in range(1, 9)])
        outcomes = _outcomes(semantic)
        assert set(outcomes) <= set(SEMANTIC_FRAME_OUTCOMES)
        # frame 0, then the newest frames geometry has taken, ending with frame 8; the others that came
        # while the encoder was held were let go by the subscription's queue of 4 or superseded
        assert encoder.encoded[0] == 0 and encoder.encoded[-1] == 8
        assert outcomes[SemanticCounter.SEMANTIC_FRAMES] == len(encoder.encoded) < received - 1
        assert outcomes.get(SemanticCounter.FRAMES_SUPERSEDED, 0) + outcomes.get(SemanticCounter.FRAMES_DROPPED, 0) \
            == received - 1 - len(encoder.encoded)
        assert semantic.counter(SemanticCounter.LAST_FRAME_HANDLED) == 8


def test_coverage_every_frame_received_ends_fused_dropped_evicted_or_skipped() -> None:
    encoder = GatedEncoder(gate_on=0)
    with ExitStack() as stack:
        semantic, rgbd, session, key = _rig(stack, encoder=encoder,
                                            semantic_values={"select": "coverage", "select_window": 1})
        views = [HERE, THERE, HERE, THERE, *(_as(f, 0) for f in _lap_views())]
        received = _feed(semantic, rgbd, session, key, encoder, [_as(v, i) for i, v in enumerate(views, start=1)])
        outcomes = _outcomes(semantic)
        # a queue of one while the scorer waits on renders, a window of one while the encoder is held
        assert outcomes.get(SemanticCounter.FRAMES_DROPPED, 0) + outcomes.get(SemanticCounter.SELECT_EVICTED, 0) \
            + outcomes.get(SemanticCounter.SKIPPED_NO_GAIN, 0) > 0
        assert outcomes[SemanticCounter.SEMANTIC_FRAMES] == semantic.counter(SemanticCounter.ENCODER_CALLS)
        assert sum(outcomes.values()) == received


def _lap_views() -> list:
    from tests.bus.test_semantic_selection import LAP

    return LAP[10:80:10]
