"""Coverage-driven frame selection in the semantic service, on a real bus in this process: the
real geometry and semantic service objects (and an encoder worker of the pool), frames published
by the test as the bridge would.

Shown: a frame that adds nothing is not encoded even when the encoder is idle (``skipped_no_gain``),
and a camera that stands still is scored on its last render (``renders_reused``);
a frame with new surface is, with the pixels it adds for the encoder's per-region embeddings (here
and through the pool: the mask goes with the request, the embedded flags come back, counted); while the encoder is busy the candidates wait in the window and the
encoder gets the one that adds something, not the newest, and embeds what it adds once the frames
before it are in the map (its wanted pixels asked again over a second render); the encoder pool dispatches from the
same window; an encoded frame whose render times out once is asked again and fused. Bad input
tried: a geometry that does not answer an encoded frame's render twice (the frame is
``skipped_no_render``, the next one is fused); no geometry to render candidates (each frame is counted in
``skipped_no_render``, ``last_frame_handled`` still moves, nothing is encoded, the service keeps
running)."""

from __future__ import annotations

import dataclasses
import threading
from contextlib import ExitStack

from openfusion.bus import Publisher, QueryError, open_session
from openfusion.mapping.params import SelectParams
from openfusion.mapping.region_gate import gate_observation
from openfusion.services.encoder.service import EncoderConfig, EncoderWorker
from openfusion.services.geometry.service import GeometryConfig, GeometryService
from openfusion.services.semantic.service import SemanticConfig, SemanticService
from openfusion.shard_client import reader_for
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
from openfusion.wire.counters import GeometryCounter, PoolCounter, SemanticCounter
from openfusion.wire.endpoints import SENSOR_RGBD
from openfusion.wire.schemas import RgbdFrame

LAP = list(open_source("synthetic:frames=90,width=160,height=120"))
HERE, THERE = LAP[0], LAP[-1]  # a quarter of the room's lap apart: the second shows surface the first did not


def _as(frame, frame_id: int):  # noqa: ANN001, ANN202
    """``frame`` again under another id (the same view, later)."""
    return dataclasses.replace(frame, frame_id=frame_id, stamp_ns=frame_id * 33_333_333)



class GatedEncoder(FlakyEncoder):
    """Holds frame ``gate_on`` until :attr:`release` is set (a busy encoder, on cue)."""

    def __init__(self, gate_on: int) -> None:
        super().__init__(empty_on=(), fail_on=())
        self.gate_on = gate_on
        self.started = threading.Event()
        self.release = threading.Event()
        self.encoded: list[int] = []

    def encode(self, frame):  # noqa: ANN001, ANN201
        if frame.frame_id == self.gate_on:
            self.started.set()
            self.release.wait(timeout=120)
        self.encoded.append(frame.frame_id)
        return super().encode(frame)


class GateRecorder(FlakyEncoder):
    """Records what each call was asked to embed (the selection's wanted pixels and share) and
    how many regions it returned and embedded."""

    def __init__(self) -> None:
        super().__init__(empty_on=(), fail_on=())
        self.calls: list[tuple[object, float | None, int, int]] = []

    def encode_where(self, frame, wanted_px, min_share):  # noqa: ANN001, ANN201
        obs = gate_observation(self.encode(frame), wanted_px, min_share)
        self.calls.append((wanted_px, min_share, obs.num_regions, obs.num_embedded))
        return obs


SELECT = {"select": "coverage", "select_tries": 1, "recover_timeout_s": 0, "instance_wait_s": 5}


def _rig(stack: ExitStack, *, encoder, semantic_values: dict, geometry: bool = True):  # noqa: ANN001, ANN202
    map_id = unique_map_id("select")
    port = free_port()
    sem_cfg = loopback_config(map_id, model=SemanticConfig, semantic={**SELECT, **semantic_values}, listen=[port])
    semantic = stack.enter_context(ServiceThread(SemanticService(sem_cfg, encoder=encoder), sem_cfg, "semantic"))
    geo = None
    if geometry:
        geo_cfg = loopback_config(map_id, model=GeometryConfig, geometry={"initial_block_count": 2048}, connect=[port])
        geo = stack.enter_context(ServiceThread(GeometryService(geo_cfg), geo_cfg, "geometry"))
    session = open_session(loopback_config(map_id, connect=[port]))
    stack.callback(session.close)
    wait_for_services(session, map_id, ["semantic", *(["geometry"] if geometry else [])])
    rgbd = frame_publisher(session, SENSOR_RGBD.key(sem_cfg.keys), RgbdFrame)
    wait_until(lambda: rgbd.has_subscribers, timeout_s=60)
    return semantic, geo, rgbd, port, map_id


def _handled(semantic: ServiceThread) -> float:
    return semantic.counter(SemanticCounter.LAST_FRAME_HANDLED)


def _send(rgbd: Publisher, frame) -> None:  # noqa: ANN001
    rgbd.put(RgbdFrame.from_frame(frame, with_instance=True))


def test_a_frame_that_adds_nothing_is_not_encoded_even_when_the_encoder_is_idle() -> None:
    encoder = GateRecorder()
    with ExitStack() as stack:
        semantic, geometry, rgbd, _, _ = _rig(stack, encoder=encoder, semantic_values={})
        send_until_handled(lambda: _send(rgbd, _as(HERE, 0)), lambda: _handled(semantic) == 0)
        assert semantic.counter(SemanticCounter.ENCODER_CALLS) == 1
        for i in range(1, 5):  # the same view four times: nothing new
            _send(rgbd, _as(HERE, i))
            wait_until(lambda i=i: _handled(semantic) == i, timeout_s=60)
        assert semantic.counter(SemanticCounter.ENCODER_CALLS) == 1
        assert semantic.counter(SemanticCounter.SKIPPED_NO_GAIN) == 4
        # the camera stood still and nothing changed the labels after frame 0's update: frame 1 asked
        # geometry for a render (the first after that update), frames 2-4 were scored on it
        assert semantic.counter(SemanticCounter.RENDERS_REUSED) == 3
        _send(rgbd, _as(THERE, 5))  # new surface
        wait_until(lambda: _handled(semantic) == 5, timeout_s=60)
        assert semantic.counter(SemanticCounter.ENCODER_CALLS) == 2
        assert semantic.counter(SemanticCounter.SEMANTIC_FRAMES) == 2
        assert semantic.counter(SemanticCounter.FRAMES_SCORED) == 6
        assert semantic.counter(SemanticCounter.ENCODER_REGIONS) >= len(semantic.app.dictionary) > 3
        wait_until(lambda: geometry.counter(GeometryCounter.UPDATES_APPLIED) == 2, timeout_s=60)
        _assert_gated(semantic, encoder)


def _assert_gated(semantic: ServiceThread, encoder: GateRecorder) -> None:
    """Each chosen frame went to the encoder with the pixels it adds (the first: every surface pixel,
    the map is empty, so every region is embedded) and the default share; the counters split the
    returned regions into embedded and not."""
    assert len(encoder.calls) == 2
    share_default = SelectParams().select_embed_share
    assert all(mask is not None and share == share_default for mask, share, _, _ in encoder.calls)
    assert encoder.calls[0][0].mean() > 0.5 and encoder.calls[0][3] == encoder.calls[0][2] > 3
    assert semantic.counter(SemanticCounter.ENCODER_REGIONS) == sum(c[3] for c in encoder.calls)
    assert semantic.counter(SemanticCounter.REGIONS_NOT_EMBEDDED) == sum(c[2] - c[3] for c in encoder.calls)


def test_while_the_encoder_is_busy_it_gets_the_candidate_that_adds_something_not_the_newest() -> None:
    """Frame 0 holds the encoder. Meanwhile frame 1 (the same view), frame 2 (new surface) and frame 3
    (the same view as 0 again, the newest) come: 1 and 3 add nothing and are dropped, 2 waits in the
    window and is encoded next."""
    encoder = GatedEncoder(gate_on=0)
    with ExitStack() as stack:
        semantic, _geometry, rgbd, _, _ = _rig(stack, encoder=encoder, semantic_values={"select_window": 4})
        send_until_handled(lambda: _send(rgbd, _as(HERE, 0)), lambda: encoder.started.is_set())
        for frame in (_as(HERE, 1), _as(THERE, 2), _as(HERE, 3)):
            _send(rgbd, frame)
        wait_until(lambda: semantic.counter(SemanticCounter.FRAMES_SCORED) == 4, timeout_s=60)
        assert semantic.counter(SemanticCounter.SKIPPED_NO_GAIN) == 2
        assert semantic.counter(SemanticCounter.SELECT_WINDOW) == 1
        assert _handled(semantic) == -1  # frame 0 is still being encoded: nothing before it is done
        encoder.release.set()
        wait_until(lambda: _handled(semantic) == 3, timeout_s=60)
        assert encoder.encoded == [0, 2]
        assert semantic.counter(SemanticCounter.ENCODER_CALLS) == 2


def test_the_encoder_pool_dispatches_from_the_same_window() -> None:
    with ExitStack() as stack:
        semantic, _geometry, rgbd, port, _ = _rig(
            stack, encoder=FlakyEncoder(empty_on=(), fail_on=()),
            semantic_values={"encoder_pool": True, "local_encoder": False})
        cfg = loopback_config(unique_map_id("workers"), model=EncoderConfig, encoder={"worker_id": "w1"}, connect=[port])
        worker_encoder = GateRecorder()
        stack.enter_context(ServiceThread(EncoderWorker(cfg, encoder=worker_encoder), cfg, "encoder-w1"))
        wait_until(lambda: semantic.counter(PoolCounter.ENCODER_WORKERS) == 1, timeout_s=60)
        send_until_handled(lambda: _send(rgbd, _as(HERE, 0)), lambda: _handled(semantic) == 0)
        for i in range(1, 4):
            _send(rgbd, _as(HERE, i))
        _send(rgbd, _as(THERE, 4))
        wait_until(lambda: _handled(semantic) == 4, timeout_s=60,
                   describe=lambda: f"semantic {dict(semantic.stats.counters)}")
        assert semantic.counter(PoolCounter.FRAMES_DISPATCHED) == 2
        assert semantic.counter(SemanticCounter.ENCODER_CALLS) == 2
        assert semantic.counter(SemanticCounter.SKIPPED_NO_GAIN) == 3
        assert semantic.counter("encoded_by:w1") == 2
        _assert_gated(semantic, worker_encoder)  # the mask went with the frame, the flags came back


def test_without_geometry_frames_are_counted_as_not_rendered_and_the_service_goes_on() -> None:
    with ExitStack() as stack:
        semantic, _geometry, rgbd, _, _ = _rig(stack, encoder=FlakyEncoder(empty_on=(), fail_on=()),
                                               semantic_values={"render_timeout_s": 0.3}, geometry=False)
        send_until_handled(lambda: _send(rgbd, _as(HERE, 0)), lambda: _handled(semantic) == 0)
        _send(rgbd, _as(THERE, 1))
        wait_until(lambda: _handled(semantic) == 1, timeout_s=60)
        assert semantic.counter(SemanticCounter.SKIPPED_NO_RENDER) == 2
        assert semantic.counter(SemanticCounter.ENCODER_CALLS) == 0
        assert semantic._thread is not None and semantic._thread.is_alive()


class StepRendersTimeOut:
    """The semantic service's geometry reader, except that the step's renders of encoded frames
    (those that wait on an update, ``after_update_source``, at the encoder's size, not a taken
    candidate's second render at the scored size) time out as ``script`` says, in turn (True: no
    answer); candidates' renders and everything else go through."""

    def __init__(self, inner, script: list[bool]) -> None:  # noqa: ANN001
        self.inner = inner
        self.script = list(script)
        self.step_renders = 0

    def __getattr__(self, name: str):  # noqa: ANN204
        return getattr(self.inner, name)

    def render(self, request, *, timeout_s: float = 5.0):  # noqa: ANN001, ANN201
        if request.after_update_source and request.width_px > SelectParams().select_width_px:
            self.step_renders += 1
            if self.script and self.script.pop(0):
                raise QueryError("geometry/render", "timeout", f"no answer within {timeout_s} s (the test)")
        return self.inner.render(request, timeout_s=timeout_s)


def test_an_encoded_frame_whose_render_timed_out_is_asked_once_more_not_thrown_away() -> None:
    encoder = GateRecorder()
    with ExitStack() as stack:
        semantic, geometry, rgbd, _, _ = _rig(stack, encoder=encoder, semantic_values={})
        reader = StepRendersTimeOut(reader_for(semantic.runner), [True, False, True, True, False])
        semantic.runner._geometry_reader = reader  # noqa: SLF001 (what reader_for hands the service)
        send_until_handled(lambda: _send(rgbd, _as(HERE, 0)), lambda: _handled(semantic) == 0)
        # frame 0: no answer, then the render: fused, its encoder call not lost
        assert semantic.counter(SemanticCounter.STEP_RENDER_RETRIES) == 1
        assert semantic.counter(SemanticCounter.SEMANTIC_FRAMES) == 1
        assert semantic.counter(SemanticCounter.SKIPPED_NO_RENDER) == 0
        _send(rgbd, _as(THERE, 1))  # no answer twice: skipped, counted, the service goes on
        wait_until(lambda: _handled(semantic) == 1, timeout_s=60)
        assert semantic.counter(SemanticCounter.STEP_RENDER_RETRIES) == 2
        assert semantic.counter(SemanticCounter.SKIPPED_NO_RENDER) == 1
        assert semantic.counter(SemanticCounter.SEMANTIC_FRAMES) == 1
        _send(rgbd, _as(LAP[45], 2))  # the next frame with something new is fused again
        wait_until(lambda: _handled(semantic) == 2, timeout_s=60)
        assert semantic.counter(SemanticCounter.SEMANTIC_FRAMES) == 2
        assert reader.step_renders == 5 and semantic.counter(SemanticCounter.ENCODER_CALLS) == 3
        wait_until(lambda: geometry.counter(GeometryCounter.UPDATES_APPLIED) == 2, timeout_s=60)


#: 640x480: a 160x120 frame's update labels too little of the map to show it (13 % of its own view;
#: 320x240 58 %, and every region of the next frame then keeps 30 % of its pixels unlabelled)
NEAR = list(open_source("synthetic:frames=6,lap=90,width=640,height=480"))


class GatedRecorder(GateRecorder):
    """:class:`GateRecorder` that holds frame ``gate_on`` until :attr:`release` is set."""

    def __init__(self, gate_on: int) -> None:
        super().__init__()
        self.gate_on = gate_on
        self.started = threading.Event()
        self.release = threading.Event()

    def encode(self, frame):  # noqa: ANN001, ANN201
        if frame.frame_id == self.gate_on:
            self.started.set()
            self.release.wait(timeout=120)
        return super().encode(frame)


def test_a_frame_chosen_while_the_encoder_was_busy_embeds_what_is_new_when_it_is_encoded() -> None:
    """Frame 1 is scored while frame 0 holds the encoder: the map is still empty, so at its
    decision every pixel was worth an embedding. It is encoded after frame 0's update has labelled
    most of what it shows from about the same direction (regions settle after one view here): its
    wanted pixels are asked again over the map rendered again, and most of its regions are fused
    without an embedding (before, the services embedded 3.5-4x what one process does)."""
    encoder = GatedRecorder(gate_on=0)
    with ExitStack() as stack:
        semantic, geometry, rgbd, _, _ = _rig(stack, encoder=encoder, semantic_values={
            "select_window": 4, "select_embed_min_views": 1, "select_min_views": 1})
        send_until_handled(lambda: _send(rgbd, _as(NEAR[0], 0)), lambda: encoder.started.is_set())
        _send(rgbd, _as(NEAR[4], 1))
        wait_until(lambda: semantic.counter(SemanticCounter.FRAMES_SCORED) == 2, timeout_s=60)
        assert semantic.counter(SemanticCounter.SELECT_WINDOW) == 1  # chosen, waiting
        assert semantic.counter(SemanticCounter.SEMANTIC_FRAMES) == 0  # decided on an empty map
        encoder.release.set()
        wait_until(lambda: _handled(semantic) == 1, timeout_s=60)
        assert semantic.counter(SemanticCounter.ENCODER_CALLS) == 2
        (first, _, n0, e0), (second, share, n1, e1) = encoder.calls
        assert first.mean() > 0.9 and e0 == n0 > 3  # frame 0: everything is new
        # frame 1: only what frame 0 did not label (at 320x240 it labels about half of the view)
        assert second.mean() < first.mean() - 0.25 and e1 < n1
        assert semantic.counter(SemanticCounter.WANTED_RENDER_FAILURES) == 0
        wait_until(lambda: geometry.counter(GeometryCounter.UPDATES_APPLIED) == 2, timeout_s=60)
