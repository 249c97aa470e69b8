"""Resume with nothing lost, the logic of both ends called directly (no Zenoh session): a restarted
geometry loads its checkpoint, announces the last frame it holds, drops the frames it already
holds and the ones whose predecessor it does not hold, and integrates the replayed ones exactly
once, to the same map as an uninterrupted run; the bridge goes back to the frame after the
announced one, also after its playback was done, and counts each frame once.

Bad input tried: frames published to a restarted geometry before the bridge went back (out of
order), frames it already holds (duplicates), a stale repeat of an announcement the bridge already
went back for, a live frame after a gap of ids."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from openfusion.bus.stats import ServiceStats
from openfusion.frame import Frame
from openfusion.services.bridge.service import BridgeConfig, BridgeSection, BridgeService
from openfusion.services.geometry.service import GeometryConfig, GeometrySection, GeometryService
from openfusion.sources.synthetic import SyntheticSource, SyntheticWorld
from openfusion.wire.counters import BridgeCounter, GeometryCounter
from openfusion.wire.schemas import GeometryProgress, RgbdFrame

pytestmark = pytest.mark.timeout(120)

N = 10
FRAMES = list(SyntheticSource(SyntheticWorld(0), num_frames=N, width_px=80, height_px=60))
PLAYBACK = "p1"


class _Recorder:
    """A publisher that keeps what is put (and may call ``on_put``)."""

    def __init__(self, on_put: Any = None) -> None:
        self.sent: list[Any] = []
        self.on_put = on_put

    def put(self, msg: Any) -> int:
        self.sent.append(msg)
        if self.on_put is not None:
            self.on_put(msg)
        return len(self.sent)

    def wait_for_subscribers(self, _timeout_s: float) -> bool:
        return True


class _Runner:
    """What the services use of a ServiceRunner, without a bus. ``wait`` returns True (stop)
    unless ``on_wait`` says to go on."""

    def __init__(self, on_wait: Any = None) -> None:
        self.stats = ServiceStats()
        self.published = _Recorder()
        self.on_wait = on_wait
        self.stopping = False

    def wait(self, timeout_s: float | None = None) -> bool:
        if self.on_wait is not None and self.on_wait():
            return False
        self.stopping = True
        return True

    def publisher(self, *_args: object, **_kwargs: object) -> _Recorder:
        return self.published

    def subscriber(self, *_args: object, **_kwargs: object) -> None:
        return None

    def queryable(self, *_args: object, **_kwargs: object) -> None:
        return None

    def counter(self, name: str) -> float:
        return self.stats.counters.get(name, 0.0)


def _geometry(map_dir: Path) -> tuple[GeometryService, _Runner]:
    section = GeometrySection(map_dir=map_dir, load_on_start=True, checkpoint_period_s=0.0, voxel_size_m=0.08,
                              initial_block_count=256)
    geo = GeometryService(GeometryConfig(map_id="resume", geometry=section))
    runner = _Runner()
    geo.setup(runner)  # type: ignore[arg-type]
    return geo, runner


def _msg(frame: Frame, prev: int | None, playback: str = PLAYBACK) -> RgbdFrame:
    return RgbdFrame.from_frame(frame, playback=playback if prev is not None else "", prev_frame_id=prev)


def _play(geo: GeometryService, frames: list[Frame]) -> None:
    for f in frames:
        geo.on_frame(_msg(f, f.frame_id - 1))


def _announcements(runner: _Runner) -> list[GeometryProgress]:
    return [m for m in runner.published.sent if m.resume > 0]


def test_restarted_geometry_integrates_every_frame_exactly_once(tmp_path: Path) -> None:
    """Checkpoint after frame 4, frames 5-9 taken (acknowledged) and lost in a crash: the restarted
    service holds frames 0-4 and says so; frames the bridge sent before it went back are dropped
    (out of order: counted, no second announcement while it waits), a frame it holds is dropped
    (duplicate), frames 5-9 replayed are integrated; the map equals an uninterrupted one's."""
    geo, _ = _geometry(tmp_path / "maps")
    _play(geo, FRAMES[:5])
    geo.save()
    _play(geo, FRAMES[5:])
    assert geo.frames_integrated == N
    del geo  # the crash: what was not checkpointed is gone

    restarted, runner = _geometry(tmp_path / "maps")
    assert restarted.last_frame_id == 4 and restarted.frames_integrated == 5 and restarted.playback == PLAYBACK
    (hello,) = _announcements(runner)
    assert (hello.holds_playback, hello.holds_frame_id, hello.resume, hello.frame_id) == (PLAYBACK, 4, 1, -1)
    assert runner.counter(GeometryCounter.FRAMES_INTEGRATED) == 5

    restarted.on_frame(_msg(FRAMES[9], 8))  # open loop before the bridge went back
    restarted.on_frame(_msg(FRAMES[3], 2))  # a frame it holds
    assert restarted.frames_integrated == 5
    assert runner.counter(GeometryCounter.FRAMES_OUT_OF_ORDER) == 1
    assert runner.counter(GeometryCounter.FRAMES_DUPLICATE) == 1
    assert len(_announcements(runner)) == 1  # still waiting for frame 5: the loop repeats the same one
    acks = [m for m in runner.published.sent if m.frame_id >= 0]
    assert [(m.frame_id, m.integrated) for m in acks] == [(9, False), (3, False)]  # flow control goes on

    _play(restarted, FRAMES[5:])
    assert restarted.frames_integrated == N and restarted.last_frame_id == N - 1
    assert not restarted.waiting_for_frames

    uninterrupted, _ = _geometry(tmp_path / "other")
    _play(uninterrupted, FRAMES)
    a, b = restarted.volume.extract_points(), uninterrupted.volume.extract_points()
    assert len(a.points) == len(b.points) > 0
    np.testing.assert_allclose(np.sort(a.points, axis=0), np.sort(b.points, axis=0), atol=1e-5)

    # A frame lost on the way (frame 10 never came): out of order again, so a new announcement.
    restarted.on_frame(_msg(FRAMES[9], 8).model_copy(update={"frame_id": 11, "prev_frame_id": 10}))
    assert [m.resume for m in _announcements(runner)] == [1, 2]


def test_a_new_playback_starts_at_its_first_frame_and_live_frames_count_the_gap(tmp_path: Path) -> None:
    """A second playback (another bridge) is taken from its first frame although its ids repeat;
    live frames (no predecessor) are taken as they come and the missing ids are counted."""
    geo, runner = _geometry(tmp_path / "maps")
    _play(geo, FRAMES[:3])
    for f in FRAMES[:2]:
        geo.on_frame(_msg(f, f.frame_id - 1, playback="p2"))
    assert geo.frames_integrated == 5 and geo.playback == "p2"
    geo.on_frame(_msg(FRAMES[5], None))
    geo.on_frame(_msg(FRAMES[9], None))
    assert geo.frames_integrated == 7
    assert runner.counter(GeometryCounter.FRAMES_GAP) == (5 - 1 - 1) + (9 - 5 - 1)


def _bridge(frames: int, *, heard: bool = True) -> BridgeService:
    """A bridge on a synthetic source; ``heard``: it has heard an acknowledgement of a geometry
    ("g1") that is not the one announcing later (a restart)."""
    config = BridgeConfig(map_id="resume", bridge=BridgeSection(
        source="synthetic", rate_hz=0, max_in_flight=0, wait_for_subscribers_s=0, flow_wait_s=5.0))
    bridge = BridgeService(config, source=SyntheticSource(SyntheticWorld(0), num_frames=frames, width_px=40,
                                                          height_px=30))
    assert bridge.replayable
    if heard:
        bridge.on_progress(GeometryProgress(frame_id=0, stamp_ns=0, integrated=True, frames_integrated=1, queued=0,
                                            incarnation="g1", holds_playback=bridge.playback, holds_frame_id=0))
    return bridge


def _resume(bridge: BridgeService, holds: int, resume: int = 1, incarnation: str = "g2") -> GeometryProgress:
    return GeometryProgress(frame_id=-1, stamp_ns=0, integrated=False, frames_integrated=0, queued=0,
                            incarnation=incarnation, holds_playback=bridge.playback, holds_frame_id=holds,
                            resume=resume)


def test_bridge_goes_back_to_the_frame_after_the_announced_one(tmp_path: Path) -> None:
    """Geometry announces (mid-playback) that it holds frames up to 3: the bridge publishes 4-6
    again with the chain intact; a stale repeat of the same announcement changes nothing; the
    counters count each frame once plus the replays."""
    bridge = _bridge(10)
    runner = _Runner()
    sent: list[RgbdFrame] = []

    def on_put(msg: RgbdFrame) -> None:
        sent.append(msg)
        if msg.frame_id == 6 and len(sent) == 7:
            bridge.on_resume(_resume(bridge, holds=3))
            bridge.on_resume(_resume(bridge, holds=3))  # repeated: once is enough

    frames = _Recorder(on_put)
    bridge._pub, bridge._instance_pub = frames, _Recorder()
    bridge.loop(runner)  # type: ignore[arg-type]
    ids = [(m.frame_id, m.prev_frame_id) for m in sent]
    assert ids == [(i, i - 1) for i in range(7)] + [(i, i - 1) for i in range(4, 10)]
    assert {m.playback for m in sent} == {bridge.playback}
    assert runner.counter(BridgeCounter.FRAMES_PUBLISHED) == 10 and runner.counter(BridgeCounter.FRAMES_READ) == 10
    assert runner.counter(BridgeCounter.FRAMES_REPLAYED) == 3 and runner.counter(BridgeCounter.REWINDS) == 1
    assert runner.counter(BridgeCounter.PLAYBACK_DONE) == 1


def test_bridge_goes_back_after_its_playback_was_done_and_for_a_geometry_that_holds_nothing() -> None:
    """Playback done, then a restarted geometry without a checkpoint (holds nothing of this
    playback): every frame again from the first; a second announcement of another geometry that
    holds all frames changes nothing."""
    bridge = _bridge(5)
    calls = {"n": 0}

    def on_wait() -> bool:
        calls["n"] += 1
        if calls["n"] == 1:
            bridge.on_resume(GeometryProgress(frame_id=-1, stamp_ns=0, integrated=False, frames_integrated=0,
                                              queued=0, incarnation="g3", holds_playback="", resume=1))
            return True
        if calls["n"] == 2:
            bridge.on_resume(_resume(bridge, holds=4, incarnation="g4"))
            return True
        return False

    runner = _Runner(on_wait)
    sent = _Recorder()
    bridge._pub, bridge._instance_pub = sent, _Recorder()
    bridge.loop(runner)  # type: ignore[arg-type]
    assert [(m.frame_id, m.prev_frame_id) for m in sent.sent] == [(i, i - 1) for i in range(5)] * 2
    assert runner.counter(BridgeCounter.FRAMES_REPLAYED) == 5 and runner.counter(BridgeCounter.REWINDS) == 1
    assert runner.counter(BridgeCounter.PLAYBACK_DONE) == 1


def test_the_first_geometrys_start_announcement_is_not_a_restart() -> None:
    """The first geometry the bridge hears of announced "holds nothing" before the first frames
    reached it (the announcement arrives after they were published): nothing is replayed; its
    next announcement (a frame came out of order) is acted on."""
    bridge = _bridge(5, heard=False)
    sent = _Recorder()
    bridge._pub, bridge._instance_pub = sent, _Recorder()
    calls = {"n": 0}

    def on_wait() -> bool:
        calls["n"] += 1
        first = GeometryProgress(frame_id=-1, stamp_ns=0, integrated=False, frames_integrated=0, queued=0,
                                 incarnation="g1", holds_playback="", resume=1)
        if calls["n"] == 1:
            bridge.on_progress(first)
            return True
        if calls["n"] == 2:
            bridge.on_progress(first.model_copy(update={"resume": 2, "holds_playback": bridge.playback,
                                                        "holds_frame_id": 2}))
            return True
        return False

    runner = _Runner(on_wait)
    bridge.loop(runner)  # type: ignore[arg-type]
    assert [m.frame_id for m in sent.sent] == [0, 1, 2, 3, 4, 3, 4]
    assert runner.counter(BridgeCounter.REWINDS) == 1


def test_bridge_replays_for_a_semantic_service_that_came_back() -> None:
    """The semantic service's token goes after frame 5 was published and comes back after frame 7:
    the bridge goes back to frame 5 (the latest-only semantic service never saw what came while it
    was down), the chain intact; a token that comes with none gone before changes nothing."""
    bridge = _bridge(9)
    bridge.on_semantic(alive=True)
    sent: list[RgbdFrame] = []

    def on_put(msg: RgbdFrame) -> None:
        sent.append(msg)
        if len(sent) == 7:  # publishing frame 6: frame 5 is the last one out
            bridge.on_semantic(alive=False)
        if len(sent) == 8:
            bridge.on_semantic(alive=True)

    bridge._pub, bridge._instance_pub = _Recorder(on_put), _Recorder()
    runner = _Runner()
    bridge.loop(runner)  # type: ignore[arg-type]
    assert [(m.frame_id, m.prev_frame_id) for m in sent] == [(i, i - 1) for i in range(8)] + [(i, i - 1) for i in range(5, 9)]
    assert runner.counter(BridgeCounter.FRAMES_REPLAYED) == 3 and runner.counter(BridgeCounter.FRAMES_PUBLISHED) == 9


def test_a_restarted_bridge_with_the_same_playback_name_integrates_nothing_twice(tmp_path: Path) -> None:
    """The bridge of `openfusion run` is named; restarted, it plays from the first frame again under
    the same name: geometry drops the frames it holds and takes the rest in order."""
    config = BridgeConfig(map_id="resume", bridge=BridgeSection(source="synthetic", playback=PLAYBACK))
    assert BridgeService(config, source=SyntheticSource(SyntheticWorld(0), num_frames=2, width_px=40,
                                                        height_px=30)).playback == PLAYBACK
    geo, runner = _geometry(tmp_path / "maps")
    _play(geo, FRAMES[:5])
    _play(geo, FRAMES)  # the restarted bridge, same playback
    assert geo.frames_integrated == N and runner.counter(GeometryCounter.FRAMES_DUPLICATE) == 5
