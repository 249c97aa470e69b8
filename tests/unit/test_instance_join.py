"""InstanceBuffer: the semantic service's join of ``sensor/rgbd`` frames with their instance
images from ``sensor/instance``. Plain library code, no bus. Bad input tried: a frame whose
instance image never comes (None after the wait, nothing else taken) and a flood of instance
images nobody asks for (memory stays at the capacity, evictions counted), a frame whose image was
evicted or lost while a later one came (None at once, no wait)."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from openfusion.bus.instance_join import InstanceBuffer
from openfusion.wire.schemas import InstanceFrame, RgbdFrame


def _rgbd(frame_id: int, stamp_ns: int) -> RgbdFrame:
    return RgbdFrame(frame_id=frame_id, stamp_ns=stamp_ns, width_px=4, height_px=3, fx=2.0, fy=2.0, cx=2.0, cy=1.5,
                     T_world_cam=np.eye(4), depth_scale=1000.0, color=np.zeros((3, 4, 3), np.uint8),
                     depth=np.ones((3, 4), np.uint16))


def _instance(frame_id: int, stamp_ns: int) -> InstanceFrame:
    return InstanceFrame(frame_id=frame_id, stamp_ns=stamp_ns, instance=np.full((3, 4), frame_id, np.int32),
                         instance_categories={frame_id: f"thing {frame_id}"})


def test_take_returns_the_frames_own_instance_image_and_drops_older_ones() -> None:
    buf = InstanceBuffer(capacity=8)
    for i in range(5):
        buf.add(_instance(i, i * 100))
    got = buf.take(_rgbd(3, 300))
    assert got is not None and got.frame_id == 3 and int(got.instance[0, 0]) == 3
    # Frames 0-2 were skipped by a latest-only consumer: gone. Frame 4 is still there.
    assert len(buf) == 1
    assert buf.take(_rgbd(1, 100)) is None
    assert buf.take(_rgbd(4, 400)) is not None


def test_same_frame_id_with_another_stamp_is_not_joined() -> None:
    """A replay that loops restarts frame ids: the stamp tells the passes apart."""
    buf = InstanceBuffer()
    buf.add(_instance(7, 700))
    assert buf.take(_rgbd(7, 999), timeout_s=0.0) is None
    assert len(buf) == 1


def test_take_waits_for_an_instance_image_that_comes_late() -> None:
    buf = InstanceBuffer()
    threading.Timer(0.1, buf.add, args=(_instance(2, 20),)).start()
    got = buf.take(_rgbd(2, 20), timeout_s=5.0)
    assert got is not None and got.frame_id == 2


def test_missing_instance_image_gives_none_after_the_wait() -> None:
    buf = InstanceBuffer()
    buf.add(_instance(1, 10))
    started = time.monotonic()
    assert buf.take(_rgbd(2, 20), timeout_s=0.05) is None
    assert time.monotonic() - started >= 0.04
    assert len(buf) == 1  # a miss takes nothing


def test_memory_stays_bounded_when_nobody_takes() -> None:
    buf = InstanceBuffer(capacity=4)
    for i in range(100):
        buf.add(_instance(i, i))
    assert len(buf) == 4 and buf.evicted == 96
    assert buf.take(_rgbd(95, 95)) is None and buf.take(_rgbd(99, 99)) is not None
    with pytest.raises(ValueError, match="capacity must be at least 1"):
        InstanceBuffer(capacity=0)


def test_an_instance_image_that_cannot_come_any_more_is_not_waited_for() -> None:
    """A consumer that fell behind its frames asks for images already gone: evicted, or lost on the
    way while a later one came. It gets None at once, not after its wait (which would make its own
    frame queue drop a run of frames meanwhile)."""
    buf = InstanceBuffer(capacity=4)
    for i in range(10):  # frames 0-5 evicted
        buf.add(_instance(i, i * 100))
    started = time.monotonic()
    assert buf.take(_rgbd(3, 300), timeout_s=60.0) is None  # evicted
    buf.take(_rgbd(7, 700))  # frames 6 and 7 taken
    later = InstanceBuffer()
    later.add(_instance(5, 500))  # frame 4's image never came, frame 5's did
    assert later.take(_rgbd(4, 400), timeout_s=60.0) is None
    assert time.monotonic() - started < 30.0  # neither waited its 60 s
    assert len(later) == 1 and later.take(_rgbd(5, 500)) is not None  # a miss takes nothing
    # another robot's later image says nothing about this robot's
    other = InstanceBuffer()
    other.add(InstanceFrame(frame_id=9, stamp_ns=900, robot="r2", instance=np.zeros((3, 4), np.int32),
                            instance_categories={}))
    threading.Timer(0.1, other.add, args=(_instance(4, 400),)).start()
    assert other.take(_rgbd(4, 400), timeout_s=30.0) is not None
