"""Credit-based flow control between the bridge and the geometry service (dataset playback).

The geometry service's frame queue is bounded (it drops the oldest frame when full, so a camera
faster than the map never grows memory). Dataset playback must not lose frames, and Zenoh's
congestion control only pushes back when the network is full, not when geometry is behind: a
bridge replaying as fast as it can filled the 64-frame queue within a second and geometry dropped
70 of 150 frames. So geometry acknowledges every frame it has taken out of its queue on
``…/geometry/progress`` (:class:`~openfusion.wire.schemas.GeometryProgress`), and the bridge keeps at
most ``limit`` frames unacknowledged (:class:`InFlightWindow`), well under the queue size.

Without acknowledgements (no geometry service yet, an old one, one that died) the bridge does not
stall for ever: after ``wait_s`` without room it counts a timeout, forgets what is in flight and
publishes open loop until the next acknowledgement arrives.
"""

from __future__ import annotations

import collections
import threading
import time

from openfusion.wire.keys import ShardId


class InFlightWindow:
    """Frames published and not yet acknowledged, identified by (frame id, stamp ns).

    Thread-safe: :meth:`acknowledge` runs on a subscriber thread, the rest on the publishing
    loop. ``limit`` frames may be in flight; :meth:`wait_for_room` blocks the publisher until
    one is acknowledged. An acknowledgement covers its frame and every frame published before it
    (a frame geometry could not integrate still counts as taken), and one for a frame this
    window never sent (another bridge on the same map) changes nothing.
    """

    def __init__(self, limit: int) -> None:
        if limit < 1:
            raise ValueError(f"limit must be at least 1, got {limit}")
        self.limit = limit
        self.timeouts = 0
        self.acknowledged = 0
        self._pending: collections.deque[tuple[int, int]] = collections.deque()
        self._open_loop = False  # after a timeout, until the next acknowledgement
        self._cond = threading.Condition()

    def __len__(self) -> int:
        with self._cond:
            return len(self._pending)

    @property
    def open_loop(self) -> bool:
        """True between a timeout and the next acknowledgement (publishing without waiting)."""
        with self._cond:
            return self._open_loop

    def sent(self, frame_id: int, stamp_ns: int) -> None:
        with self._cond:
            if not self._open_loop:
                self._pending.append((int(frame_id), int(stamp_ns)))

    def acknowledge(self, frame_id: int, stamp_ns: int, shard: str | None = None) -> None:
        """``frame_id`` was taken (``shard``: which geometry shard said so; one window, any)."""
        del shard
        key = (int(frame_id), int(stamp_ns))
        with self._cond:
            self._open_loop = False
            if key not in self._pending:
                return
            while self._pending:
                self.acknowledged += 1
                if self._pending.popleft() == key:
                    break
            self._cond.notify_all()

    def wait_for_room(self, wait_s: float) -> bool:
        """Block until fewer than ``limit`` frames are in flight or the window is open loop (True),
        or until ``wait_s`` has passed without room (False; call :meth:`give_up` to stop
        waiting for this geometry service, or wait again)."""
        deadline = time.monotonic() + wait_s
        with self._cond:
            while not self._open_loop and len(self._pending) >= self.limit:
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    return False
                self._cond.wait(remaining)
            return True

    def reset(self) -> None:
        """Forget what is in flight and wait for acknowledgements again (the bridge went back to
        replay frames for a restarted geometry: the frames in flight will never be taken)."""
        with self._cond:
            self._pending.clear()
            self._open_loop = False
            self._cond.notify_all()

    def give_up(self) -> None:
        """No acknowledgement came in time: count it, forget what is in flight and publish open
        loop until the next acknowledgement."""
        with self._cond:
            self.timeouts += 1
            self._pending.clear()
            self._open_loop = True
            self._cond.notify_all()


class ShardWindows:
    """Flow control towards several geometry shards (docs/SHARDS.md): one :class:`InFlightWindow`
    per shard, named by its service name (``geometry-0of2``...), all fed every frame; there is room
    for another frame only when every shard has room, so the slowest shard paces playback and no
    shard's queue overflows. An acknowledgement counts for its shard's window only; one of a shard
    not in the split (another map's, an old one) changes nothing. A timeout gives up on every
    window that has no room (open loop for those shards until they acknowledge again)."""

    def __init__(self, limit: int, shards: list[str]) -> None:
        if not shards:
            raise ValueError("ShardWindows needs at least one shard")
        self.limit = limit
        self._windows = {name: InFlightWindow(limit) for name in shards}
        self._gave_up = 0

    @property
    def shards(self) -> list[str]:
        return list(self._windows)

    @property
    def timeouts(self) -> int:
        return self._gave_up

    @property
    def acknowledged(self) -> int:
        """Frames every shard has taken."""
        return min(w.acknowledged for w in self._windows.values())

    @property
    def open_loop(self) -> bool:
        return any(w.open_loop for w in self._windows.values())

    def __len__(self) -> int:
        return max(len(w) for w in self._windows.values())

    def sent(self, frame_id: int, stamp_ns: int) -> None:
        for w in self._windows.values():
            w.sent(frame_id, stamp_ns)

    def acknowledge(self, frame_id: int, stamp_ns: int, shard: str | None = None) -> None:
        """An acknowledgement of ``shard`` (a service name; a replica's counts for its shard)."""
        sid = ShardId.of_service(shard or "")
        window = self._windows.get(sid.part.service if sid is not None else "")
        if window is not None:
            window.acknowledge(frame_id, stamp_ns)

    def wait_for_room(self, wait_s: float) -> bool:
        deadline = time.monotonic() + wait_s
        for w in self._windows.values():
            if not w.wait_for_room(max(0.0, deadline - time.monotonic())):
                return False
        return True

    def reset(self) -> None:
        for w in self._windows.values():
            w.reset()

    def give_up(self) -> None:
        self._gave_up += 1
        for w in self._windows.values():
            if len(w) >= w.limit:
                w.give_up()
