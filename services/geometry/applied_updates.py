"""Which semantic updates geometry has applied, so a render can wait for the one before it
(:attr:`~openfusion.wire.schemas.RenderRequest.after_update_seq`).

Why: the semantic service renders frame N+1 for its match right after it sent frame N's update.
With a fast encoder that render reached geometry before the update was applied, so frame N+1 was
matched against a map without frame N's labels and started its regions again; the next merge pass
joined the copies about two seconds later (a free gt encoder through the services: the first pass
folded 9 regions into 9 others). One process applies an update before it renders the next frame:
this makes the services do the same. Each semantic service process numbers its updates
(``source``, ``seq``); an update counts as applied once it was taken off the subscription, whether
it was written, refused or failed (none will follow for that number). The wait is bounded
(``GeometrySection.render_update_wait_s``): an update geometry never gets (one sent before this
geometry started) delays one render by that much at most, and only that one: renders are answered
by two threads (``RENDER_WORKERS``), so the semantic service's scoring renders go on meanwhile.
"""

from __future__ import annotations

import threading
import time
from collections import OrderedDict

#: semantic service processes remembered (the oldest forgotten first: each restart is a new one)
SOURCES_KEPT = 64


class AppliedUpdates:
    """The newest update number applied per semantic service process (thread-safe)."""

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._seq: OrderedDict[str, int] = OrderedDict()
        self._waiting = 0  # renders waiting now

    def applied(self, source: str, seq: int) -> None:
        """An update was taken (written, refused or failed); unnumbered updates (``seq`` 0) count for nothing."""
        if not source or seq <= 0:
            return
        with self._cond:
            if seq > self._seq.get(source, 0):
                self._seq[source] = seq
            self._seq.move_to_end(source)
            while len(self._seq) > SOURCES_KEPT:
                self._seq.popitem(last=False)
            self._cond.notify_all()

    def wait(self, source: str, seq: int, timeout_s: float) -> bool:
        """Wait up to ``timeout_s`` until update ``seq`` of ``source`` (or a later one) is applied;
        True at once for ``seq`` 0. False on timeout."""
        if seq <= 0:
            return True
        deadline = time.monotonic() + max(0.0, timeout_s)
        with self._cond:
            self._waiting += 1
            try:
                while self._seq.get(source, 0) < seq:
                    remaining = deadline - time.monotonic()
                    if remaining <= 0:
                        return False
                    self._cond.wait(remaining)
                return True
            finally:
                self._waiting -= 1

    @property
    def waiting(self) -> int:
        """Renders waiting for an update now."""
        with self._cond:
            return self._waiting
