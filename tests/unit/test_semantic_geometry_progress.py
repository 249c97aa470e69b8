"""The semantic service renders a frame once geometry holds it, ``select=latest`` encodes the
newest frame geometry holds (services.semantic.geometry_progress), and merge passes run off the
frame loop (services.semantic.merge_worker). No bus: acknowledgements are fed by hand.

Bad input tried: a resume announcement (frame -1) acknowledges nothing; a geometry that never
acknowledges delays a frame by ``wait_s`` at most (a robot's first frame waits for the first
acknowledgement, once); a merge pass that raises is counted and the
next one still runs."""

from __future__ import annotations

import threading
import time
from types import SimpleNamespace

from openfusion.services.semantic.geometry_progress import IntegratedFrames, NewestTaken
from openfusion.services.semantic.merge_worker import MergeWorker
from openfusion.wire.schemas import GeometryProgress


def _ack(frame_id: int, *, robot: str = "robot0", shard: str = "geometry") -> GeometryProgress:
    return GeometryProgress(frame_id=frame_id, stamp_ns=max(frame_id, 0) * 100, integrated=True, frames_integrated=0,
                            queued=0, robot=robot, shard=shard)


def _frame(frame_id: int, robot: str = "robot0") -> SimpleNamespace:
    return SimpleNamespace(frame_id=frame_id, stamp_ns=frame_id * 100, robot=robot)


def test_a_frame_is_taken_once_geometry_acknowledged_it_or_a_later_one() -> None:
    frames = IntegratedFrames()
    assert not frames.taken("robot0", 500)  # no acknowledgement yet: the first frame waits for one
    frames.on_progress(_ack(3))
    assert frames.taken("robot0", 300) and not frames.taken("robot0", 400)
    frames.on_progress(_ack(-1))  # a resume announcement acknowledges no frame
    frames.on_progress(_ack(2))  # an older acknowledgement does not move it back
    assert frames.taken("robot0", 300) and not frames.taken("robot0", 400)
    frames.on_progress(_ack(6))
    assert frames.taken("robot0", 500)  # a later frame acknowledged: this one was taken (or refused) before it
    # Another robot, never acknowledged: waited for once (bounded), then not again until an acknowledgement.
    assert not frames.taken("robot1", 100)
    assert not frames.wait("robot1", 100, timeout_s=0.05)
    assert frames.taken("robot1", 10**12) and frames.wait("robot1", 10**12, timeout_s=30)
    frames.on_progress(_ack(2, robot="robot1"))
    assert frames.taken("robot1", 200) and not frames.taken("robot1", 300)  # acknowledged: waited for again


def test_with_shards_every_shard_must_have_taken_the_frame_and_a_replica_stands_for_its_shard() -> None:
    frames = IntegratedFrames()
    frames.on_progress(_ack(5, shard="geometry-0of2"))
    assert not frames.taken("robot0", 500)  # shard 1 has not acknowledged it
    frames.on_progress(_ack(5, shard="geometry-1of2-r1"))
    assert frames.taken("robot0", 500)


def test_the_wait_ends_when_geometry_acknowledges_and_gives_up_after_the_timeout() -> None:
    frames = IntegratedFrames()
    frames.on_progress(_ack(1))
    assert not frames.wait("robot0", 900, timeout_s=0.05)  # never acknowledged: bounded
    threading.Timer(0.05, lambda: frames.on_progress(_ack(9))).start()
    assert frames.wait("robot0", 900, timeout_s=30)


def test_latest_gives_the_newest_frame_geometry_has_taken_and_supersedes_the_older_ones() -> None:
    frames = IntegratedFrames()
    newest = NewestTaken(frames, capacity=4, wait_s=10.0)
    frames.on_progress(_ack(0))
    for i in range(1, 5):
        assert newest.add(_frame(i), now_s=0.0) == []
    assert newest.take(now_s=0.1) == (None, [])  # geometry holds none of them yet
    frames.on_progress(_ack(3))
    chosen, passed = newest.take(now_s=0.2)
    assert chosen.frame_id == 3 and [f.frame_id for f in passed] == [1, 2]  # frame 4 waits for geometry
    assert len(newest) == 1
    pushed = [newest.add(_frame(i), now_s=0.3) for i in range(5, 9)]
    assert [f.frame_id for f in pushed[-1]] == [4]  # over capacity: the oldest goes
    # geometry never acknowledges: after wait_s the newest goes as it is
    chosen, passed = newest.take(now_s=0.3 + 10.0)
    assert chosen.frame_id == 8 and [f.frame_id for f in passed] == [5, 6, 7]


def test_a_requested_merge_pass_runs_on_the_workers_thread_and_passes_never_overlap() -> None:
    errors = []
    worker = MergeWorker(on_error=lambda: errors.append(1))
    running = threading.Event()
    release = threading.Event()
    overlap = []
    inside = threading.Lock()

    def slow_pass() -> str:
        if not inside.acquire(blocking=False):
            overlap.append(1)
        running.set()
        release.wait(30)
        inside.release()
        return "slow"

    worker.start()
    try:
        started = time.monotonic()
        worker.request(slow_pass)  # returns at once: the frame loop goes on
        assert running.wait(30)
        assert time.monotonic() - started < 30
        done = []
        caller = threading.Thread(target=lambda: done.append(worker.run_now(lambda: "asked")))
        caller.start()  # a pass asked for on semantic/merge waits for the running one
        assert not done
        release.set()
        caller.join(30)
        assert done == ["asked"] and not overlap

        def failing() -> None:
            raise RuntimeError("contacts were garbage")

        worker.request(failing)
        deadline = time.monotonic() + 30
        while not errors and time.monotonic() < deadline:
            time.sleep(0.01)
        assert errors == [1]
        ran = threading.Event()
        worker.request(ran.set)  # the worker goes on after a failed pass
        assert ran.wait(30)
    finally:
        worker.stop(timeout_s=5)
    assert not worker.running


def test_without_its_thread_a_requested_pass_runs_at_once() -> None:
    ran = []
    MergeWorker().request(lambda: ran.append(1))
    assert ran == [1]
