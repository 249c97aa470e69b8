"""What became of each frame the semantic service received: the subscription's own counts in
health, and the frames still without an outcome.

Every frame that comes on ``sensor/rgbd`` (``frames_received``) ends in exactly one of
:data:`~openfusion.wire.counters.SEMANTIC_FRAME_OUTCOMES`: fused (``semantic_frames``), or not
encoded for a named reason: it added too little (``skipped_no_gain``), a full candidate window let
it go (``select_evicted``), the subscription's bounded queue let it go before the service took it
(``frames_dropped``; with ``select=latest`` every frame that came while the encoder was busy and
was replaced by a newer one), the switch, no instance image, no render, its robot not joined, a
failure, a malformed message, or the encoder pool lost it or its result came too late.
``frames_pending`` is the difference: frames queued, waiting in the window or at the encoder now;
once the service is idle it is 0, and a frame that vanished would show there.

The subscription counts samples on a Zenoh thread; a thread of the service copies them into its
stats every 0.1 s (:class:`FrameCounts`, :func:`note_frames`), also while the encoder is busy.
"""

from __future__ import annotations

import threading

from openfusion.bus import ServiceStats, Subscriber
from openfusion.wire.counters import SEMANTIC_FRAME_OUTCOMES, SemanticCounter


def count_embedded(stats: ServiceStats, regions: int, embedded: int) -> None:
    """An encoder call's regions: ``embedded`` of them carry an embedding (``encoder_regions``),
    the rest added nothing and were fused without one (``regions_not_embedded``,
    :mod:`openfusion.mapping.region_gate`)."""
    stats.incr(SemanticCounter.ENCODER_REGIONS, embedded)
    stats.incr(SemanticCounter.REGIONS_NOT_EMBEDDED, regions - embedded)


def note_frames(stats: ServiceStats, frames: Subscriber) -> None:
    """The subscription's counts (received, dropped by its queue, malformed) into ``stats``, and
    the frames received with no outcome yet (``frames_pending``)."""
    stats.set(SemanticCounter.FRAMES_RECEIVED, frames.arrived)
    stats.set(SemanticCounter.FRAMES_DROPPED, frames.dropped_queue)
    stats.set(SemanticCounter.FRAMES_MALFORMED, frames.errors)
    ended = sum(stats.counters.get(name, 0.0) for name in SEMANTIC_FRAME_OUTCOMES)
    stats.set(SemanticCounter.FRAMES_PENDING, max(0.0, frames.arrived - ended))


class FrameCounts:
    """Calls :func:`note_frames` every ``period_s`` on a thread of its own until :meth:`stop`."""

    def __init__(self, stats: ServiceStats, frames: Subscriber, *, period_s: float = 0.1) -> None:
        self.stats = stats
        self.frames = frames
        self.period_s = period_s
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="semantic-frame-counts", daemon=True)

    def start(self) -> FrameCounts:
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=2.0)
        note_frames(self.stats, self.frames)

    def _run(self) -> None:
        while not self._stop.wait(self.period_s):
            note_frames(self.stats, self.frames)
