"""InFlightWindow: the bridge's playback flow control, as plain library code (no bus). Bad input
tried: acknowledgements for frames this window never sent (another bridge), a geometry service
that never acknowledges (the wait gives up, the window goes open loop, the next acknowledgement
closes it again) and a limit of 0."""

from __future__ import annotations

import threading
import time

import pytest

from openfusion.bus.flow_control import InFlightWindow, ShardWindows


def test_window_holds_at_most_limit_frames_until_one_is_acknowledged() -> None:
    w = InFlightWindow(limit=3)
    for i in range(3):
        assert w.wait_for_room(0.0)
        w.sent(i, i * 10)
    assert not w.wait_for_room(0.02)  # full: no room without an acknowledgement
    w.acknowledge(0, 0)
    assert len(w) == 2 and w.wait_for_room(0.0)


def test_an_acknowledgement_covers_every_earlier_frame_and_foreign_ones_change_nothing() -> None:
    w = InFlightWindow(limit=8)
    for i in range(5):
        w.sent(i, i * 10)
    w.acknowledge(99, 990)  # another bridge's frame on the same map
    assert len(w) == 5
    w.acknowledge(1, 999)  # right id, other stamp (a looped replay's earlier pass): not ours
    assert len(w) == 5
    w.acknowledge(3, 30)  # frames 0-2 were taken too (or dropped: either way, gone from the queue)
    assert len(w) == 1 and w.acknowledged == 4


def test_waiting_publisher_wakes_when_geometry_acknowledges() -> None:
    w = InFlightWindow(limit=1)
    w.sent(7, 70)
    threading.Timer(0.1, w.acknowledge, args=(7, 70)).start()
    started = time.monotonic()
    assert w.wait_for_room(5.0)
    assert time.monotonic() - started < 4.0


def test_no_acknowledgement_gives_up_to_open_loop_until_geometry_answers_again() -> None:
    w = InFlightWindow(limit=2)
    w.sent(0, 0)
    w.sent(1, 10)
    assert not w.wait_for_room(0.01)
    w.give_up()
    assert w.timeouts == 1 and w.open_loop and len(w) == 0
    for i in range(2, 10):  # open loop: nothing is tracked, nothing waits
        assert w.wait_for_room(0.0)
        w.sent(i, i * 10)
    assert len(w) == 0
    w.acknowledge(9, 90)  # geometry is back: flow control again from the next frame
    assert not w.open_loop
    w.sent(10, 100)
    w.sent(11, 110)
    assert not w.wait_for_room(0.01)


def test_limit_must_be_positive() -> None:
    with pytest.raises(ValueError, match="limit must be at least 1"):
        InFlightWindow(0)


def test_shard_windows_wait_for_every_shard_and_a_replica_counts_for_its_shard() -> None:
    """Two shards: room only when both took the frames; shard 0's acknowledgement comes from its
    replica (geometry-0of2-r1). Bad input tried: an acknowledgement of another split's shard, or of
    no shard at all, changes nothing."""
    w = ShardWindows(2, ["geometry-0of2", "geometry-1of2"])
    w.sent(1, 10)
    w.sent(2, 20)
    assert not w.wait_for_room(0.0)
    w.acknowledge(2, 20, shard="geometry-1of2")
    assert not w.wait_for_room(0.0)  # shard 0 has not taken them
    w.acknowledge(2, 20, shard="geometry-0of3")
    w.acknowledge(2, 20, shard=None)
    assert not w.wait_for_room(0.0)
    w.acknowledge(2, 20, shard="geometry-0of2-r1")
    assert w.wait_for_room(0.0) and w.acknowledged == 2
    w.sent(3, 30)
    w.sent(4, 40)
    assert not w.wait_for_room(0.0)
    w.give_up()  # nobody answered: open loop for the shards without room
    assert w.timeouts == 1 and w.open_loop and w.wait_for_room(0.0)
