"""The semantic service's scoring thread (openfusion.services.semantic.selection.CandidateFeeder)
without a bus: frames from a queue, renders from a function, the real window and scorer.

What a user would notice: with one render at a time the scoring thread fell behind a 30 fps
camera and the subscription dropped runs of frames; renders now overlap, yet frames are still
decided in the order they came (the decision of each depends on the ones before). A chosen frame
holds the surface it will label until it is done with, so the frames behind it do not choose the
same surface again. Bad input tried: a render that fails (geometry gave no answer): the frame is
counted as not scored, marked done, and the frames around it go on.
"""

from __future__ import annotations

import queue
import threading
import time
from types import SimpleNamespace

import numpy as np

from openfusion.bus import QueryError
from openfusion.bus.stats import ServiceStats
from openfusion.frame import CameraIntrinsics, Frame
from openfusion.mapping.params import SelectParams
from openfusion.mapping.selection import CandidateWindow, CoverageScorer
from openfusion.poses import look_at
from openfusion.services.semantic.selection import CandidateFeeder, HandledFrames
from openfusion.wire.counters import SemanticCounter
from openfusion.wire.schemas import RgbdFrame

W, H = 16, 12
K = CameraIntrinsics(W, H, 14.0, 14.0, (W - 1) / 2, (H - 1) / 2)
T_FRONT = look_at(np.array([0.0, 0.0, 1.0]), np.array([2.0, 0.0, 1.0]), up=np.array([0.0, 0.0, 1.0]))
WAIT_S = 10.0  # bound on every wait for the feeder's thread (it answers in milliseconds)


class QueueFrames:
    """The subscription: ``recv`` as the bus's subscriber does (None after ``timeout_s``)."""

    def __init__(self) -> None:
        self.queue: queue.Queue[RgbdFrame] = queue.Queue()

    def recv(self, timeout_s: float | None = None) -> RgbdFrame | None:
        try:
            return self.queue.get(timeout=timeout_s) if timeout_s else self.queue.get_nowait()
        except queue.Empty:
            return None


def wall_frame(frame_id: int, depth_m: float) -> RgbdFrame:
    """A view of a wall ``depth_m`` away: each depth is other surface (other cubes), new to the map."""
    frame = Frame(frame_id=frame_id, stamp_ns=frame_id * 33_000_000, color=np.zeros((H, W, 3), np.uint8),
                  depth=np.full((H, W), depth_m, np.float32), depth_scale=1.0, intrinsics=K, T_world_cam=T_FRONT)
    return RgbdFrame.from_frame(frame)


def wait_until(condition, what: str) -> None:  # noqa: ANN001
    deadline = time.monotonic() + WAIT_S
    while not condition():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.005)


def test_renders_overlap_frames_are_decided_in_arrival_order_and_a_failed_render_is_counted() -> None:
    scorer = CoverageScorer(SelectParams(select_width_px=W, select_patience_s=None, select_min_views=0))
    window: CandidateWindow = CandidateWindow(scorer, capacity=8)
    frames = QueueFrames()
    second_render_started = threading.Event()
    overlapped: list[bool] = []
    not_rendered: list[int] = []

    def render(request) -> SimpleNamespace:  # noqa: ANN001
        if request.frame_id == 1:
            second_render_started.set()
        if request.frame_id == 0:  # the first render returns only once the second one has started
            overlapped.append(second_render_started.wait(WAIT_S))
        if request.frame_id == 2:
            raise QueryError("test/geometry/render", "timeout", "no geometry answered")
        return SimpleNamespace(key_map=np.full((H, W), -1, np.int32), conf_map=np.zeros((H, W), np.float32),
                               T_map_cam=None)

    feeder = CandidateFeeder(
        frames=frames, window=window, scorer=scorer, accept=lambda frame_id, now: True, render=render,
        instances=None, instance_wait_s=0.0, on_no_instance=lambda runner, msg: None,
        on_no_render=lambda runner, robot, frame_id, exc: not_rendered.append(frame_id), renders_in_flight=3)
    runner = SimpleNamespace(stats=ServiceStats(), stopping=False)
    for frame_id, depth_m in enumerate((2.0, 3.0, 4.0, 5.0)):
        frames.queue.put(wall_frame(frame_id, depth_m))
    thread = threading.Thread(target=feeder.run, args=(runner,), daemon=True)
    thread.start()
    try:
        wait_until(lambda: runner.stats.counters.get(SemanticCounter.FRAMES_SCORED) == 3 and not_rendered,
                   "three frames scored and one refused")
    finally:
        runner.stopping = True
        thread.join(WAIT_S)
    assert overlapped == [True], "the second frame's render never started while the first one was out"
    assert not_rendered == [2]
    # every scored frame was new surface: chosen, and offered in the order the frames came
    waiting = sorted(window.drain(), key=lambda c: c.arrival)
    assert [c.payload.msg.frame_id for c in waiting] == [0, 1, 3]
    assert scorer.held == 0  # drained: nothing is held any more


def test_a_chosen_frame_holds_its_surface_until_it_is_done_with() -> None:
    """Frame 0 is chosen and waits for the encoder. The same wall again (frame 1) adds nothing
    while frame 0 waits: without the hold it was chosen as the surface's second try
    (``select_tries`` 2), which one process, having encoded frame 0 first, would not do. Once
    frame 0 is done with and its surface is still unlabelled (the encoder missed it), the wall is
    worth its second try (frame 2). The watermark moves as frames are done with."""
    scorer = CoverageScorer(SelectParams(select_width_px=W, select_patience_s=None, select_min_views=0))
    window: CandidateWindow = CandidateWindow(scorer, capacity=8)
    feeder = CandidateFeeder(
        frames=QueueFrames(), window=window, scorer=scorer, accept=lambda frame_id, now: True, render=None,
        instances=None, instance_wait_s=0.0, on_no_instance=None, on_no_render=None)
    runner = SimpleNamespace(stats=ServiceStats(), stopping=False)

    def blank(frame_id: int):  # noqa: ANN202
        msg = wall_frame(frame_id, 2.0)
        feeder.handled.arrived(msg.robot, msg.frame_id, msg.stamp_ns)
        return msg, scorer.prepare(frame_id=frame_id, stamp_ns=msg.stamp_ns, T_world_cam=T_FRONT, intrinsics=K,
                                   depth_m=np.full((H, W), 2.0), key_map=np.full((H, W), -1),
                                   conf_map=np.zeros((H, W), np.float32), robot=msg.robot)

    msg0, ev0 = blank(0)
    assert not window.offer(ev0, msg0).no_gain and scorer.held == 1
    msg1, ev1 = blank(1)
    assert [c.payload for c in window.offer(ev1, msg1).no_gain] == [msg1]
    feeder.finish(runner, msg1)
    assert runner.stats.counters.get(SemanticCounter.LAST_FRAME_HANDLED) is None  # frame 0 is not done yet
    assert window.take().taken.payload is msg0
    feeder.finish(runner, msg0)  # encoded, its update sent (no label came: the encoder missed the wall)
    assert scorer.held == 0 and runner.stats.counters[SemanticCounter.LAST_FRAME_HANDLED] == 1
    msg2, ev2 = blank(2)
    assert not window.offer(ev2, msg2).no_gain


def test_a_frame_the_full_window_lets_go_no_longer_holds_its_surface() -> None:
    scorer = CoverageScorer(SelectParams(select_width_px=W, select_patience_s=None, select_min_views=0))
    window: CandidateWindow = CandidateWindow(scorer, capacity=1)

    def wall(frame_id: int, depth_m: float, share: float):  # noqa: ANN202
        depth = np.zeros((H, W), np.float32)
        depth[:, : round(W * share)] = depth_m
        return scorer.prepare(frame_id=frame_id, stamp_ns=frame_id * 33_000_000, T_world_cam=T_FRONT, intrinsics=K,
                              depth_m=depth, key_map=np.full((H, W), -1), conf_map=np.zeros((H, W), np.float32))

    window.offer(wall(0, 2.0, 0.5), 0)
    change = window.offer(wall(1, 3.0, 1.0), 1)
    assert [c.payload for c in change.evicted] == [0] and scorer.held == 1
    # frame 0's surface is free again for a later view (its first try was recorded, its second is not held)
    assert scorer.score(wall(2, 2.0, 0.5)).new_surface > 0


def test_a_surface_two_waiting_frames_hold_stays_held_until_both_are_done() -> None:
    scorer = CoverageScorer(SelectParams(select_width_px=W, select_patience_s=None, select_min_views=0))

    def blank(frame_id: int):  # noqa: ANN202
        return scorer.prepare(frame_id=frame_id, stamp_ns=frame_id * 33_000_000, T_world_cam=T_FRONT, intrinsics=K,
                              depth_m=np.full((H, W), 2.0), key_map=np.full((H, W), -1),
                              conf_map=np.zeros((H, W), np.float32))

    first, second = blank(0), blank(1)
    assert scorer.score(blank(2)).new_surface == 1.0
    scorer.hold(first)
    scorer.hold(second)
    scorer.hold(second)  # held twice: still one hold
    assert scorer.score(blank(2)).new_surface == 0.0 and scorer.held == 2
    scorer.release(first.frame_id, first.stamp_s)
    assert scorer.score(blank(2)).new_surface == 0.0  # the other one still holds it
    scorer.release(second.frame_id, second.stamp_s)
    scorer.release(second.frame_id, second.stamp_s)  # released twice: nothing more to release
    assert scorer.score(blank(2)).new_surface == 1.0 and scorer.held == 0


def test_two_robots_frames_with_the_same_id_and_stamp_both_leave_the_window() -> None:
    """Two robots replaying one source send frames with equal ids and stamps. The window removed
    the frame it gave out by comparing candidates field by field, and two views of other sizes
    raised (the semantic service exited mid-run; seen in tests/process/test_several_robots.py)."""
    scorer = CoverageScorer(SelectParams(select_width_px=W, select_patience_s=None, select_min_views=0))
    window: CandidateWindow = CandidateWindow(scorer, capacity=8)

    def wall(depth_m: float, share: float):  # noqa: ANN202
        depth = np.zeros((H, W), np.float32)
        depth[:, : round(W * share)] = depth_m  # another surface for each: both chosen
        return scorer.prepare(frame_id=3, stamp_ns=99_000_000, T_world_cam=T_FRONT, intrinsics=K, depth_m=depth,
                              key_map=np.full((H, W), -1), conf_map=np.zeros((H, W), np.float32))

    assert not window.offer(wall(2.0, 0.5), "robot0").no_gain
    assert not window.offer(wall(3.0, 1.0), "robot1").no_gain
    assert sorted(window.take().taken.payload for _ in range(2)) == ["robot0", "robot1"]
    assert len(window) == 0


def test_two_robots_frames_with_the_same_id_and_stamp_hold_their_surface_apart() -> None:
    """A hold is the robot's: robot0's frame 3 done with does not release what robot1's frame 3
    (same id and stamp, another robot's clock) still waits to show."""
    scorer = CoverageScorer(SelectParams(select_width_px=W, select_patience_s=None, select_min_views=0))

    def blank(robot: str):  # noqa: ANN202
        return scorer.prepare(frame_id=3, stamp_ns=99_000_000, T_world_cam=T_FRONT, intrinsics=K,
                              depth_m=np.full((H, W), 2.0), key_map=np.full((H, W), -1),
                              conf_map=np.zeros((H, W), np.float32), robot=robot)

    scorer.hold(blank("robot0"))
    scorer.hold(blank("robot1"))
    assert scorer.held == 2
    scorer.release(3, 0.099, "robot0")
    assert scorer.held == 1 and scorer.score(blank("robot0")).new_surface == 0.0  # robot1's frame holds it
    scorer.release(3, 0.099, "robot1")
    assert scorer.held == 0 and scorer.score(blank("robot0")).new_surface == 1.0


def test_the_watermark_passes_two_robots_frames_with_the_same_id_and_stamp() -> None:
    """Both robots' frame 3 (same id and stamp) done before robot 0's frame 2: once frame 2 is done
    the watermark passes both; the same for one robot's frame taken twice. With one done mark for
    two equal frames it stopped for good (checked: a set in place of the count fails here)."""
    handled = HandledFrames()
    for robot, frame_id in (("robot0", 2), ("robot0", 3), ("robot1", 3)):
        handled.arrived(robot, frame_id, frame_id * 33_000_000)
    assert handled.done("robot0", 3, 99_000_000) is None
    assert handled.done("robot1", 3, 99_000_000) is None
    assert handled.done("robot0", 2, 66_000_000) == 3 and handled.pending == 0
    # one robot's frame taken twice (a replayed frame), both done before the frame ahead of them
    for frame_id in (6, 7, 7):
        handled.arrived("robot0", frame_id, frame_id * 33_000_000)
    assert handled.done("robot0", 7, 231_000_000) is None and handled.done("robot0", 7, 231_000_000) is None
    assert handled.done("robot0", 6, 198_000_000) == 7 and handled.pending == 0
