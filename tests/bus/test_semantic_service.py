"""The semantic service's logic on a real bus, in this process (no subprocess): the real
geometry and semantic service objects, each with its own ServiceRunner and Zenoh session on
loopback, frames published by the test as the bridge would.

Bad inputs tried: a frame whose encoder returns no region (a normal frame: an update with no
key is sent, nothing breaks), a frame whose encoder raises (logged, ``frames_failed`` counted,
the next frame is processed), and a frame whose ground-truth instance image belongs to another
image size (refused when joined; counted, the service keeps running)."""

from __future__ import annotations

import numpy as np

from openfusion.bus import open_session
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
from openfusion.wire.counters import GeometryCounter, SemanticCounter
from openfusion.wire.endpoints import SENSOR_INSTANCE, SENSOR_RGBD
from openfusion.wire.schemas import InstanceFrame, RgbdFrame


def test_semantic_service_counts_failed_and_empty_frames_and_keeps_going() -> None:
    """Six frames: frame 2 has no region, frame 3 makes the encoder raise, frame 4 carries an
    instance image of the wrong size. Geometry integrates all six; the semantic service fuses
    frames 0, 1, 2 and 5, counts two failures, and its dictionary has regions."""
    map_id = unique_map_id("sem")
    port = free_port()
    geo_cfg = loopback_config(map_id, model=GeometryConfig, geometry={"initial_block_count": 2048}, listen=[port])
    sem_cfg = loopback_config(map_id, model=SemanticConfig, semantic={"select": "latest", "recover_timeout_s": 0, "instance_wait_s": 10},
                      connect=[port])
    frames = list(open_source("synthetic:frames=6,width=160,height=120"))
    with (
        ServiceThread(GeometryService(geo_cfg), geo_cfg, "geometry") as geometry,
        ServiceThread(SemanticService(sem_cfg, encoder=FlakyEncoder(empty_on=[2], fail_on=[3])), sem_cfg, "semantic") as semantic,
    ):
        session = open_session(loopback_config(map_id, connect=[port]))
        try:
            keys = geo_cfg.keys
            rgbd = frame_publisher(session, SENSOR_RGBD.key(keys), RgbdFrame)
            instances = frame_publisher(session, SENSOR_INSTANCE.key(keys), InstanceFrame)
            # Both services' tokens are declared after their subscribers: once seen, frames reach both.
            wait_for_services(session, map_id, ["geometry", "semantic"])
            wait_until(lambda: rgbd.has_subscribers and instances.has_subscribers, timeout_s=60)
            # Frame 0 (its instance image inline: fused) is sent until the semantic service has
            # handled it: a put from this fresh session can miss the semantic service even once
            # the publisher matches geometry (frame 0 got lost about one run in three).
            send_until_handled(lambda: rgbd.put(RgbdFrame.from_frame(frames[0], with_instance=True)),
                               lambda: semantic.counter(SemanticCounter.LAST_FRAME_HANDLED) == 0)
            for frame in frames[1:]:
                done_before = semantic.counter(SemanticCounter.SEMANTIC_FRAMES) + semantic.counter(
                    SemanticCounter.FRAMES_FAILED)
                instance = InstanceFrame.from_frame(frame)
                if frame.frame_id == 4:  # a valid message, but for an image of another size
                    instance = instance.model_copy(update={"instance": np.zeros((8, 8), np.int32)})
                instances.put(instance)
                rgbd.put(RgbdFrame.from_frame(frame, with_instance=False))
                wait_until(lambda before=done_before: semantic.counter(SemanticCounter.SEMANTIC_FRAMES)
                           + semantic.counter(SemanticCounter.FRAMES_FAILED) > before, timeout_s=120)
            wait_until(lambda: geometry.counter(GeometryCounter.FRAMES_INTEGRATED) == 6, timeout_s=120)
            wait_until(lambda: geometry.counter(GeometryCounter.UPDATES_APPLIED) == 4, timeout_s=120)
        finally:
            session.close()
        # Frame 0 sent twice (its first put slow, not lost) would count twice: never seen so far.
        assert semantic.counter(SemanticCounter.SEMANTIC_FRAMES) == 4
        assert semantic.counter(SemanticCounter.FRAMES_FAILED) == 2
        assert semantic.stats.errors == 2
        assert len(semantic.app.dictionary) > 3
        assert geometry.app.replica.embedding_space == semantic.app.dictionary.embedding_space
