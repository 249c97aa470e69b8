"""Join frames from ``…/sensor/rgbd`` with their instance images from ``…/sensor/instance``.

The bridge publishes a frame's :class:`~openfusion.wire.schemas.InstanceFrame` just before the
frame itself, on the same session, so it normally arrives first. The semantic service keeps the
last few in an :class:`InstanceBuffer` and, for the frame it is about to encode, takes the one
with the same frame id and time stamp, waiting a little for it when the frame overtook it.
"""

from __future__ import annotations

import collections
import threading
import time

from openfusion.wire.schemas import InstanceFrame, RgbdFrame

DEFAULT_CAPACITY = 32


class InstanceBuffer:
    """The newest ``capacity`` instance messages, looked up by (robot, frame id, stamp).

    Thread-safe: :meth:`add` runs on a subscriber thread, :meth:`take` on the service loop. The
    semantic service encodes only the newest frame of a robot, so taking one entry also drops every
    entry of that robot that arrived before it (those frames were skipped and will not be asked
    for); other robots' entries stay. Memory is bounded: past ``capacity`` the oldest entry goes
    (counted in ``evicted``).
    """

    def __init__(self, capacity: int = DEFAULT_CAPACITY) -> None:
        if capacity < 1:
            raise ValueError(f"capacity must be at least 1, got {capacity}")
        self.capacity = capacity
        self.evicted = 0
        self._entries: collections.OrderedDict[tuple[str, int, int], InstanceFrame] = collections.OrderedDict()
        self._evicted_stamp: dict[str, int] = {}  # per robot, the latest stamp evicted
        self._cond = threading.Condition()

    def __len__(self) -> int:
        with self._cond:
            return len(self._entries)

    def add(self, msg: InstanceFrame) -> None:
        key = (msg.robot, msg.frame_id, msg.stamp_ns)
        with self._cond:
            self._entries.pop(key, None)
            self._entries[key] = msg
            while len(self._entries) > self.capacity:
                (robot, _, stamp), _ = self._entries.popitem(last=False)
                self._evicted_stamp[robot] = max(stamp, self._evicted_stamp.get(robot, stamp))
                self.evicted += 1
            self._cond.notify_all()

    def _gone(self, robot: str, stamp_ns: int) -> bool:
        """(lock held) Whether the instance of ``robot``'s frame at ``stamp_ns`` can no longer come."""
        if self._evicted_stamp.get(robot, -1) >= stamp_ns:
            return True
        return any(k[0] == robot and k[2] > stamp_ns for k in self._entries)

    def take(self, frame: RgbdFrame, timeout_s: float = 0.0) -> InstanceFrame | None:
        """The instance message of ``frame`` (removed, with everything older), waiting up to
        ``timeout_s`` for it to arrive; None when it did not, and at once when it cannot come any
        more: an instance of a later frame of the robot is here, or one at least as late was
        evicted (the bridge sends a frame's instance image just before the frame, so a later one
        here means this one was lost). A caller that fell behind its frames (a queue of frames
        deeper than this buffer) thus loses the frames whose images went, one by one, instead of
        waiting ``timeout_s`` on each while its frame queue drops a run of frames."""
        key = (frame.robot, frame.frame_id, frame.stamp_ns)
        deadline = time.monotonic() + max(0.0, timeout_s)
        with self._cond:
            while key not in self._entries:
                if self._gone(frame.robot, frame.stamp_ns):
                    return None
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    return None
                self._cond.wait(remaining)
            for k in list(self._entries):
                if k[0] != frame.robot:
                    continue
                msg = self._entries.pop(k)
                if k == key:
                    return msg
            raise AssertionError("unreachable: the key was in the buffer")
