"""The semantic step's view by a probe through the services (``semantic.step_probe_blocks``), on a
real bus in this process: the real geometry and semantic service objects, frames published by the
test as the bridge would.

Shown: with ``step_probe_blocks`` 0 every encoded frame's render request carries the frame's depth,
geometry answers it with a probe (counted as a probe, not a render), and the update that follows
writes through that probe's hits (``updates_reused_render``): no ray cast anywhere, and the frames'
labels are in the map. With the default (none) the same frames are ray-cast."""

from __future__ import annotations

from contextlib import ExitStack

from openfusion.bus import open_session
from openfusion.mapping.params import MatchParams
from openfusion.services.geometry.service import GeometryConfig, GeometryService
from openfusion.services.semantic.service import SemanticConfig, SemanticService
from openfusion.sources import open_source
from openfusion.testing.bus import (
    ServiceThread,
    frame_publisher,
    free_port,
    loopback_config,
    unique_map_id,
    wait_for_services,
    wait_until,
)
from openfusion.testing.encoders import FlakyEncoder
from openfusion.wire.counters import GeometryCounter, SemanticCounter
from openfusion.wire.endpoints import SENSOR_RGBD
from openfusion.wire.schemas import RgbdFrame

FRAMES = list(open_source("synthetic:frames=24,width=160,height=120"))[::8]  # 3 frames, a third of a lap apart


def _map(step_probe_blocks: int | None) -> tuple[dict[str, float], int]:
    """Geometry's render and update counters after the semantic service fused FRAMES, and its labelled voxels."""
    map_id = unique_map_id("stepprobe")
    port = free_port()
    with ExitStack() as stack:
        sem_cfg = loopback_config(map_id, model=SemanticConfig, listen=[port], semantic={
            "select": "every", "step_probe_blocks": step_probe_blocks, "recover_timeout_s": 0, "instance_wait_s": 5})
        encoder = FlakyEncoder(empty_on=(), fail_on=())
        semantic = stack.enter_context(ServiceThread(SemanticService(sem_cfg, encoder=encoder), sem_cfg, "semantic"))
        geo_cfg = loopback_config(map_id, model=GeometryConfig, geometry={"initial_block_count": 2048}, connect=[port])
        geometry = stack.enter_context(ServiceThread(GeometryService(geo_cfg), geo_cfg, "geometry"))
        session = open_session(loopback_config(map_id, connect=[port]))
        stack.callback(session.close)
        wait_for_services(session, map_id, ["semantic", "geometry"])
        rgbd = frame_publisher(session, SENSOR_RGBD.key(sem_cfg.keys), RgbdFrame)
        wait_until(lambda: rgbd.has_subscribers, timeout_s=60)
        for frame in FRAMES:  # one at a time: each fused and applied before the next
            rgbd.put(RgbdFrame.from_frame(frame, with_instance=True))
            wait_until(lambda f=frame: semantic.counter(SemanticCounter.LAST_FRAME_HANDLED) == f.frame_id, timeout_s=60)
        fused = semantic.counter(SemanticCounter.SEMANTIC_FRAMES)
        wait_until(lambda: geometry.counter(GeometryCounter.UPDATES_APPLIED) >= fused, timeout_s=60)
        counters = {name: geometry.counter(name) for name in (
            GeometryCounter.RENDERS, GeometryCounter.PROBES, GeometryCounter.UPDATES_APPLIED,
            GeometryCounter.UPDATES_REUSED_RENDER)}
        counters["fused"] = fused
        labelled = int((geometry.app.volume.to_arrays()["key"] > 0).sum())
    return counters, labelled


def test_the_step_probes_the_frames_depth_and_the_update_writes_through_the_probe() -> None:
    probed, labelled = _map(0)
    assert probed["fused"] == len(FRAMES)
    assert probed[GeometryCounter.PROBES] == len(FRAMES) and probed[GeometryCounter.RENDERS] == 0
    assert probed[GeometryCounter.UPDATES_APPLIED] == probed[GeometryCounter.UPDATES_REUSED_RENDER] == len(FRAMES)
    rendered, labelled_rendered = _map(MatchParams().step_probe_blocks)  # the default: ray-cast
    assert rendered[GeometryCounter.RENDERS] == len(FRAMES) and rendered[GeometryCounter.PROBES] == 0
    assert rendered[GeometryCounter.UPDATES_REUSED_RENDER] == len(FRAMES)
    # the same frames label about as much of the map either way
    assert labelled > 1000 and abs(labelled - labelled_rendered) <= 0.1 * labelled_rendered, (labelled, labelled_rendered)
