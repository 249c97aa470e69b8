"""Frames and semantic updates that come while a replica copies its peer's checkpoint
(:class:`StartBuffer`), taken once the copy is loaded.

Why: a replica that starts with no checkpoint copies its peer's (:mod:`.peer_copy`), which takes
seconds for a large map (110-130 MB/s). Subscribed only after the copy, it lost a live source's
frames (and the semantic updates) that came between the peer's checkpoint and its subscription:
they were counted as ``frames_gap``, and its map was not its peer's. Now it subscribes before the
copy and holds what comes, in arrival order, up to ``peer_copy_buffer_frames`` frames (the oldest
kept: they continue the copy; the frames over that are counted as ``peer_copy_frames_lost`` and
seen as a gap). Once the copy is loaded the held frames and updates go through the service's own
handlers in the order they came: a live frame the copy already holds (its id at most the robot's
last in the copy, same stream) is a duplicate, counted and dropped; a playback's frames are sorted
out by the usual admission (duplicates, then the chain). While the buffer is emptied the
subscriptions' threads wait, so nothing overtakes it.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from typing import Any

logger = logging.getLogger(__name__)

FRAME = "frame"
UPDATE = "update"
#: semantic updates held at most (small messages; over this the oldest are kept and the rest counted lost)
UPDATES_KEPT = 1024


class StartBuffer:
    """What comes while the copy runs, in arrival order (thread-safe)."""

    def __init__(self, max_frames: int) -> None:
        self.max_frames = max_frames
        self._lock = threading.Lock()
        self._items: list[tuple[str, Any]] = []
        self._holding = True
        self.frames = 0
        self.updates = 0
        self.frames_lost = 0
        self.updates_lost = 0

    def offer(self, kind: str, msg: Any) -> bool:
        """Hold ``msg`` (a :data:`FRAME` or an :data:`UPDATE`) while the copy runs: True when held
        (or counted lost over the limit); False once the buffer is emptied (handle it now)."""
        with self._lock:
            if not self._holding:
                return False
            if kind == FRAME:
                if self.frames >= self.max_frames:
                    self.frames_lost += 1
                    return True
                self.frames += 1
            else:
                if self.updates >= UPDATES_KEPT:
                    self.updates_lost += 1
                    return True
                self.updates += 1
            self._items.append((kind, msg))
            return True

    def release(self, handle: Callable[[str, Any], None]) -> None:
        """Hand everything held to ``handle(kind, msg)`` in arrival order, then stop holding;
        :meth:`offer` waits meanwhile. One item's failure is logged and the next goes on."""
        with self._lock:
            items, self._items = self._items, []
            for kind, msg in items:
                try:
                    handle(kind, msg)
                except Exception:  # as the subscription would: logged, the next one goes on
                    logger.exception("geometry: a %s held during the peer copy failed; skipped", kind)
            self._holding = False
